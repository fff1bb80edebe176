//! V2S training (`librplus train --method v2s`): the network is supervised by the ground-truth
//! displacement alone (it has no physics prior; that is the point of the baseline), on the same
//! splits as SR-GCN.
//!
//! Each scenario's input is built after the rigid stage (wICP, as registration runs it), and its
//! target is the displacement that carries the preoperative nodes onto their true positions
//! under that rigid transform: `u_i = T_wICP⁻¹(T_true(X_i + u_true,i)) − X_i`, so the node error of
//! a prediction is exactly the TRE of the registration it makes. The loss is the mean over nodes
//! of the Charbonnier distance `√(|e|² + ε²) − ε` (ε = 0.01 output units) between the
//! interpolated prediction and the target; validation keeps the epoch with the least mean node
//! error (mm). Adam; the learning rate anneals on a cosine over the epoch and time budget
//! ([`super::Schedule::Cosine`], as SR-GCN's default), or halves after an epoch that does not
//! improve and stops after `patience` such epochs ([`super::Schedule::Plateau`]).

use super::shuffle;
use crate::dataset::read::{GeometryData, ScenarioData};
use crate::eval::EvalError;
use crate::mesh::rigid::Rigid;
use crate::pipeline::{Method, PipelineParams, Prepared, register};
use crate::v2s::io::{V2sModel, save_model};
use crate::v2s::model::{V2sConfig, V2sNet};
use crate::v2s::{OUTPUT_UNIT_MM, V2sFrame};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// One geometry prepared for V2S: its rigid registration case and its grid frame.
pub struct V2sGeometry {
    /// The geometry (model, surface flags, targets).
    pub geo: GeometryData,
    /// Its registration case without a LIBR basis (wICP only).
    pub case: Prepared,
    /// The grid and preoperative channels.
    pub frame: V2sFrame,
}

/// Prepares every named geometry for a network of `cfg`.
pub fn v2s_geometries(
    dir: &Path,
    m: &crate::dataset::Manifest,
    geometries: &[String],
    cfg: &V2sConfig,
) -> Result<BTreeMap<String, V2sGeometry>, EvalError> {
    let mut out = BTreeMap::new();
    for g in geometries {
        if out.contains_key(g) {
            continue;
        }
        let geo = crate::dataset::read::load_geometry(dir, m, g)?;
        let case = Prepared::new(geo.model.clone(), None, None)?;
        let model = &geo.model;
        let frame = V2sFrame::new(
            &model.mesh,
            (&model.vessel_points, &model.vessel_segments),
            cfg,
        )
        .map_err(|e| EvalError::Training(format!("geometry {g}: {e}")))?;
        out.insert(g.clone(), V2sGeometry { geo, case, frame });
    }
    Ok(out)
}

/// One training or validation sample.
pub struct V2sSample {
    /// Scenario id.
    pub id: String,
    /// Geometry id.
    pub geometry: String,
    /// The measured channels (2..INPUTS) on the grid, `[3·n³]` (the preoperative ones are the
    /// geometry's).
    pub measured: Vec<f32>,
    /// The target displacement at the nodes, `[V, 3]` row-major, output units.
    pub target: Vec<f32>,
}

/// The target of a scenario under the rigid `t` (`u = T⁻¹(T_true(X + u_true)) − X`, mm).
pub fn rigid_frame_truth(geo: &GeometryData, sc: &ScenarioData, t: &Rigid) -> Vec<f64> {
    let inv = t.inverse();
    let truth = &sc.truth;
    let mut u = Vec::with_capacity(3 * geo.model.mesh.num_nodes());
    for (i, x) in geo.model.mesh.nodes().iter().enumerate() {
        let p = truth
            .image_to_physical
            .apply([0, 1, 2].map(|a| x[a] + truth.displacement[3 * i + a]));
        let q = inv.apply(p);
        u.extend([0, 1, 2].map(|a| q[a] - x[a]));
    }
    u
}

/// Builds the samples of `items` (scenario, geometry); None where the rigid stage failed.
pub fn v2s_samples(
    geos: &BTreeMap<String, V2sGeometry>,
    items: &[(&ScenarioData, &str)],
    params: &PipelineParams,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Option<V2sSample>>, EvalError> {
    let done = std::sync::atomic::AtomicUsize::new(0);
    items
        .par_iter()
        .map(|(sc, g)| {
            let vg = geos
                .get(*g)
                .ok_or_else(|| EvalError::Internal(format!("no V2S frame for geometry {g}")))?;
            let r = register(&vg.case, &sc.measurements, Method::Rigid, params).ok();
            let out = r.map(|r| {
                let t = r.image_to_physical;
                let input = vg.frame.input_for(&sc.measurements, &t);
                let preop = vg.frame.preop.len();
                V2sSample {
                    id: sc.id.clone(),
                    geometry: g.to_string(),
                    measured: input[preop..].to_vec(),
                    target: rigid_frame_truth(&vg.geo, sc, &t)
                        .into_iter()
                        .map(|x| (x / OUTPUT_UNIT_MM) as f32)
                        .collect(),
                }
            });
            progress(
                done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1,
                items.len(),
            );
            Ok(out)
        })
        .collect()
}

/// V2S training settings.
#[derive(Debug, Clone)]
pub struct V2sTrainOptions {
    /// Network and grid.
    pub config: V2sConfig,
    /// Seed (initialisation, sample order).
    pub seed: u64,
    /// Epochs at most.
    pub epochs: usize,
    /// Initial learning rate.
    pub learning_rate: f64,
    /// Epochs without validation improvement before stopping (plateau schedule only).
    pub patience: usize,
    /// How the learning rate changes ([`super::Schedule`]: cosine annealing over the epoch and
    /// time budget, keeping the best validation epoch; or halving on a stall with early stop).
    pub schedule: super::Schedule,
    /// Training stops before an epoch that would end past this many minutes.
    pub max_minutes: f64,
}

impl Default for V2sTrainOptions {
    fn default() -> Self {
        Self {
            config: V2sConfig::new(),
            seed: 1,
            epochs: 30,
            learning_rate: 3e-3,
            patience: 4,
            schedule: super::Schedule::Cosine,
            max_minutes: 25.0,
        }
    }
}

/// What [`train_v2s`] returns.
pub struct V2sTrainReport {
    /// The best validation epoch's network, on the plain device.
    pub model: V2sModel,
    /// Per-epoch figures (stage 2 in [`super::EpochLog`]'s terms).
    pub log: Vec<super::EpochLog>,
    /// Best validation mean node error (mm).
    pub best_valid_mm: f64,
    /// Validation mean node error of the rigid registration alone (mm).
    pub rigid_valid_mm: f64,
    /// Training samples.
    pub train_samples: usize,
    /// Validation samples.
    pub valid_samples: usize,
    /// Training time (s).
    pub seconds: f64,
}

fn input_tensor(g: &V2sGeometry, s: &V2sSample, device: &Device) -> Tensor<5> {
    let mut x = g.frame.preop.clone();
    x.extend_from_slice(&s.measured);
    g.frame.tensor(x, device)
}

/// Mean node penalty: Charbonnier distance (output units).
fn loss_of(pred: Tensor<2>, target: &[f32], device: &Device) -> Tensor<1> {
    let n = target.len() / 3;
    let t = Tensor::<2>::from_data(TensorData::new(target.to_vec(), [n, 3]), device);
    let eps = 0.01f32;
    ((pred - t).powi_scalar(2).sum_dim(1) + eps * eps)
        .sqrt()
        .mean()
        - eps
}

/// Mean node error (mm) of a prediction `[V, 3]` (output units) against the target.
fn node_error_mm(pred: &Tensor<2>, target: &[f32]) -> f64 {
    let p = pred
        .clone()
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default();
    if p.len() != target.len() || target.is_empty() {
        return f64::NAN;
    }
    let n = target.len() / 3;
    p.chunks_exact(3)
        .zip(target.chunks_exact(3))
        .map(|(a, b)| {
            (0..3)
                .map(|c| (a[c] as f64 - b[c] as f64).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .sum::<f64>()
        / n as f64
        * OUTPUT_UNIT_MM
}

/// Mean validation node error (mm) of `net`.
fn validate(
    net: &V2sNet,
    geos: &BTreeMap<String, V2sGeometry>,
    valid: &[V2sSample],
    device: &Device,
) -> Result<f64, EvalError> {
    let mut sum = 0.0;
    for s in valid {
        let g = &geos[&s.geometry];
        let y = net.forward(input_tensor(g, s, device))?;
        sum += node_error_mm(&g.frame.at_nodes(y)?, &s.target);
    }
    Ok(sum / valid.len().max(1) as f64)
}

/// Trains V2S on prepared samples, writing the best epoch's model to `out` as it improves.
/// `progress(epoch, done, total, loss)` reports steps.
pub fn train_v2s(
    opts: &V2sTrainOptions,
    geos: &BTreeMap<String, V2sGeometry>,
    train: &[V2sSample],
    valid: &[V2sSample],
    out: &Path,
    provenance: &serde_json::Value,
    progress: &dyn Fn(usize, usize, usize, f64),
) -> Result<V2sTrainReport, EvalError> {
    let cfg = &opts.config;
    cfg.validate()?;
    if train.is_empty() || valid.is_empty() {
        return Err(EvalError::Data(
            "no training or no validation samples".into(),
        ));
    }
    if !(opts.learning_rate.is_finite() && opts.learning_rate > 0.0) {
        return Err(EvalError::Parameter(format!(
            "learning rate {} (finite, > 0)",
            opts.learning_rate
        )));
    }
    let t0 = Instant::now();
    let plain = crate::gcn::device::compute();
    let device = plain.clone().autodiff();
    device.seed(opts.seed);
    let mut net = cfg.init(&device)?;
    let rigid_valid_mm = valid
        .iter()
        .map(|s| {
            let z = Tensor::<2>::zeros([s.target.len() / 3, 3], &plain);
            node_error_mm(&z, &s.target)
        })
        .sum::<f64>()
        / valid.len() as f64;
    let mut optim = AdamConfig::new().init();
    let mut lr = opts.learning_rate;
    let mut best = f64::INFINITY;
    let mut best_net = net.valid();
    let mut log: Vec<super::EpochLog> = Vec::new();
    let mut order: Vec<usize> = (0..train.len()).collect();
    let mut stall = 0;
    for epoch in 1..=opts.epochs {
        shuffle(&mut order, opts.seed.wrapping_add(7000 + epoch as u64));
        let mut sum = 0.0;
        let mut lr_sum = 0.0;
        for (k, &i) in order.iter().enumerate() {
            if opts.schedule == super::Schedule::Cosine {
                let steps = (opts.epochs * order.len()).max(1) as f64;
                let p_steps = ((epoch - 1) * order.len() + k) as f64 / steps;
                let p_time = t0.elapsed().as_secs_f64() / (60.0 * opts.max_minutes).max(1e-9);
                lr = opts.schedule.rate(opts.learning_rate, p_steps.max(p_time));
            }
            lr_sum += lr;
            let s = &train[i];
            let g = &geos[&s.geometry];
            let y = net.forward(input_tensor(g, s, &device))?;
            let loss = loss_of(g.frame.at_nodes(y)?, &s.target, &device);
            let l = loss.clone().into_scalar::<f32>() as f64;
            if !l.is_finite() {
                return Err(EvalError::Training(format!(
                    "V2S epoch {epoch}: the loss is not finite"
                )));
            }
            sum += l;
            let grads = GradientsParams::from_grads(loss.backward(), &net);
            net = optim.step(lr, net, grads);
            progress(epoch, k + 1, order.len(), sum / (k + 1) as f64);
        }
        let vnet = net.valid();
        let v = validate(&vnet, geos, valid, &plain)?;
        log.push(super::EpochLog {
            stage: 2,
            epoch,
            train_loss: sum / order.len() as f64,
            valid: v,
            // The epoch's mean rate.
            learning_rate: lr_sum / order.len().max(1) as f64,
            seconds: t0.elapsed().as_secs_f64(),
        });
        if v < best {
            best = v;
            best_net = vnet;
            stall = 0;
            let mut prov = provenance.clone();
            prov["checkpoint"] = serde_json::json!({"epoch": epoch, "valid_node_error_mm": v});
            save_model(out, cfg, &best_net, prov)?;
        } else if opts.schedule == super::Schedule::Plateau {
            stall += 1;
            lr *= 0.5;
            if stall >= opts.patience {
                break;
            }
        }
        let n = log.len();
        let epoch_s = log[n - 1].seconds - if n > 1 { log[n - 2].seconds } else { 0.0 };
        if t0.elapsed().as_secs_f64() + epoch_s > 60.0 * opts.max_minutes {
            break;
        }
    }
    Ok(V2sTrainReport {
        model: V2sModel {
            config: cfg.clone(),
            net: best_net,
            provenance: provenance.clone(),
        },
        log,
        best_valid_mm: best,
        rigid_valid_mm,
        train_samples: train.len(),
        valid_samples: valid.len(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}
