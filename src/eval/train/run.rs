//! [`train`]: the two training stages of SR-GCN over prepared samples, with validation after
//! every epoch, checkpoints of the best, and the correction's scale fitted at the end.

use super::loss::*;
use super::samples::{RefitLoss, TrainingSample, refit_modes};
use super::{EpochLog, GeometryCase, Schedule, TrainOptions, TrainReport, WeightAverage};
use crate::eval::EvalError;
use crate::eval::splits::shuffle;
use crate::gcn::io::{TrainedModel, save_model};
use crate::gcn::model::{MeshGraphs, SrGcn, Target};
use crate::gcn::sample::{PositionJitter, SampleData};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

/// Trains SR-GCN on prepared samples (`train`, `valid`), writing a checkpoint to `out` after
/// every improving epoch. `progress(stage, epoch, done, total, loss)` reports steps.
#[allow(clippy::too_many_arguments)]
pub fn train(
    opts: &TrainOptions,
    cases: &BTreeMap<String, GeometryCase>,
    train: &[TrainingSample],
    valid: &[TrainingSample],
    out: &Path,
    provenance: &serde_json::Value,
    progress: &dyn Fn(u32, usize, usize, usize, f64),
) -> Result<TrainReport, EvalError> {
    check_options(opts, train, valid)?;
    std::fs::create_dir_all(out).map_err(crate::util::FileError::at("creating directory", out))?;
    let t0 = Instant::now();
    let plain = crate::gcn::device::compute();
    let device = plain.clone().autodiff();
    device.seed(opts.seed);
    let net = initial_net(opts, &device)?;
    let run = Run::new(opts, cases, train, valid, (plain, device), t0, progress)?;
    let mut log = Vec::new();
    let mut order: Vec<usize> = (0..train.len()).collect();
    // Stage 1: the bipartite branch reconstructs its input.
    let net = if opts.config.bipartite {
        run.bipartite_stage(net, &mut order, &mut log)?
    } else {
        net
    };
    // Stage 2: the mesh branch.
    let libr_valid_mm = run.libr_valid_mm();
    let best = run.mesh_stage(net, &mut order, &mut log, out, provenance)?;
    // The correction's scale, fitted on the best epoch's validation errors: the largest factor
    // among the best (ties keep more of the correction).
    let grid = &run.grid;
    let mut config = opts.config.clone();
    let (k, scaled_valid_mm) =
        best.errs
            .iter()
            .enumerate()
            .rev()
            .fold((grid.len() - 1, best.mm), |acc, (k, e)| {
                if *e < acc.1 - 1e-9 { (k, *e) } else { acc }
            });
    config.correction_scale = grid[k];
    Ok(TrainReport {
        model: TrainedModel {
            config,
            net: best.net,
            provenance: provenance.clone(),
            abstain: None,
        },
        log,
        scaled_valid_mm,
        best_valid_mm: best.mm,
        libr_valid_mm,
        train_samples: train.len(),
        valid_samples: valid.len(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Checks the options and that there are samples to train and validate on.
fn check_options(
    opts: &TrainOptions,
    train: &[TrainingSample],
    valid: &[TrainingSample],
) -> Result<(), EvalError> {
    opts.config.validate()?;
    if !(opts.weight_decay >= 0.0 && opts.weight_decay.is_finite()) {
        return Err(EvalError::Data(format!(
            "weight_decay must be finite and ≥ 0, got {}",
            opts.weight_decay
        )));
    }
    if !(opts.position_jitter >= 0.0 && opts.position_jitter.is_finite()) {
        return Err(EvalError::Data(format!(
            "position_jitter must be finite and ≥ 0, got {}",
            opts.position_jitter
        )));
    }
    if train.is_empty() || valid.is_empty() {
        return Err(EvalError::Data(
            "no training or no validation samples".into(),
        ));
    }
    Ok(())
}

/// The network training starts from: fresh, or the initial model asked for (which must be the
/// same network, its correction scale aside).
fn initial_net(opts: &TrainOptions, device: &Device) -> Result<SrGcn, EvalError> {
    let cfg = &opts.config;
    let Some(dir) = &opts.init else {
        return Ok(cfg.init(device)?);
    };
    let m = crate::gcn::io::load_model(dir, device)
        .map_err(|e| EvalError::within(format!("initial model {}", dir.display()), e))?;
    let (mut a, mut b) = (m.config.clone(), cfg.clone());
    a.correction_scale = 1.0;
    b.correction_scale = 1.0;
    if serde_json::to_value(&a).ok() != serde_json::to_value(&b).ok() {
        return Err(EvalError::Training(format!(
            "initial model {}: its network differs from the one asked for",
            dir.display()
        )));
    }
    Ok(m.net)
}

/// A training run: its samples, each geometry's graphs (autodiff, plain) and refit modes, the
/// two devices, and the candidate correction scales.
struct Run<'a> {
    opts: &'a TrainOptions,
    cases: &'a BTreeMap<String, GeometryCase>,
    train: &'a [TrainingSample],
    valid: &'a [TrainingSample],
    graphs: BTreeMap<String, (MeshGraphs, MeshGraphs)>,
    /// The refit modes of every geometry, when training through the refit.
    modes: BTreeMap<String, (Tensor<2>, Tensor<2>)>,
    plain: Device,
    device: Device,
    /// Candidate factors on the correction: 0, 0.05, …, 1 for a residual target (the last 1).
    grid: Vec<f64>,
    t0: Instant,
    progress: &'a dyn Fn(u32, usize, usize, usize, f64),
}

/// The best network of the mesh stage: its validation node error (mm), and its errors at every
/// candidate correction scale.
struct Best {
    net: SrGcn,
    mm: f64,
    errs: Vec<f64>,
}

impl<'a> Run<'a> {
    fn new(
        opts: &'a TrainOptions,
        cases: &'a BTreeMap<String, GeometryCase>,
        train: &'a [TrainingSample],
        valid: &'a [TrainingSample],
        (plain, device): (Device, Device),
        t0: Instant,
        progress: &'a dyn Fn(u32, usize, usize, usize, f64),
    ) -> Result<Self, EvalError> {
        let cfg = &opts.config;
        let mut graphs = BTreeMap::new();
        for (g, gc) in cases {
            let ad = gc.frame.mesh_graphs(cfg, &device)?;
            let pl = gc.frame.mesh_graphs(cfg, &plain)?;
            graphs.insert(g.clone(), (ad, pl));
        }
        let mut modes = BTreeMap::new();
        if opts.refit_loss {
            if let Some(s) = train.iter().chain(valid).find(|s| s.refit.is_none()) {
                return Err(EvalError::Training(format!(
                    "training through the refit needs every sample's linearised refit; a sample of {} has none",
                    s.geometry
                )));
            }
            for (g, gc) in cases {
                modes.insert(
                    g.clone(),
                    (refit_modes(gc, &device)?, refit_modes(gc, &plain)?),
                );
            }
        }
        let grid: Vec<f64> = if cfg.target == Target::Residual {
            (0..=20).map(|k| k as f64 / 20.0).collect()
        } else {
            vec![1.0]
        };
        Ok(Self {
            opts,
            cases,
            train,
            valid,
            graphs,
            modes,
            plain,
            device,
            grid,
            t0,
            progress,
        })
    }

    /// A sample's linearised refit with its geometry's modes on the autodiff (0) or plain (1)
    /// device.
    fn through(&self, s: &'a TrainingSample, k: usize) -> Option<(&RefitLoss, &Tensor<2>)> {
        let m = self.modes.get(&s.geometry)?;
        Some((s.refit.as_ref()?, if k == 0 { &m.0 } else { &m.1 }))
    }

    /// A training sample as the network sees it at step (stage, epoch, k): jittered when asked.
    fn seen<'s>(
        &self,
        s: &'s SampleData,
        stage: u64,
        epoch: usize,
        k: usize,
    ) -> Cow<'s, SampleData> {
        let opts = self.opts;
        if opts.position_jitter > 0.0 {
            let seed = opts
                .seed
                .wrapping_mul(0x100_0000_01b3)
                .wrapping_add((stage << 48) ^ ((epoch as u64) << 32) ^ k as u64);
            Cow::Owned(s.jittered(
                &opts.config,
                &PositionJitter::draw(opts.position_jitter, seed),
            ))
        } else {
            Cow::Borrowed(s)
        }
    }

    /// Stage 1: the bipartite branch trained to reconstruct its input, validated every epoch.
    fn bipartite_stage(
        &self,
        mut net: SrGcn,
        order: &mut [usize],
        log: &mut Vec<EpochLog>,
    ) -> Result<SrGcn, EvalError> {
        let (opts, cfg) = (self.opts, &self.opts.config);
        let err = EvalError::from;
        let mut optim = AdamConfig::new().init();
        for epoch in 1..=opts.epochs_bipartite {
            shuffle(order, opts.seed.wrapping_add(epoch as u64));
            let mut sum = 0.0;
            for (k, &i) in order.iter().enumerate() {
                let (_, bip) = self
                    .seen(&self.train[i].data, 1, epoch, k)
                    .tensors(cfg, &self.device)
                    .map_err(err)?;
                let b = bip.ok_or_else(|| EvalError::Internal("no bipartite input".into()))?;
                let o = net
                    .forward_bipartite(&b)
                    .map_err(err)?
                    .ok_or_else(|| EvalError::Internal("no bipartite branch".into()))?;
                let loss = (o.reconstruction - b.features.clone())
                    .powi_scalar(2)
                    .mean();
                let l: f64 = loss.clone().into_scalar::<f32>() as f64;
                sum += l;
                let grads = GradientsParams::from_grads(loss.backward(), &net);
                net = optim.step(opts.learning_rate, net, grads);
                (self.progress)(1, epoch, k + 1, order.len(), sum / (k + 1) as f64);
            }
            log.push(EpochLog {
                stage: 1,
                epoch,
                train_loss: sum / order.len() as f64,
                valid: self.bipartite_valid(&net.valid())?,
                learning_rate: opts.learning_rate,
                seconds: self.t0.elapsed().as_secs_f64(),
            });
        }
        Ok(net)
    }

    /// The bipartite branch's mean reconstruction loss over the validation samples.
    fn bipartite_valid(&self, vnet: &SrGcn) -> Result<f64, EvalError> {
        let err = EvalError::from;
        let mut vsum = 0.0;
        for s in self.valid {
            let (_, bip) = s
                .data
                .tensors(&self.opts.config, &self.plain)
                .map_err(err)?;
            let b = bip.ok_or_else(|| EvalError::Internal("no bipartite input".into()))?;
            let o = vnet
                .forward_bipartite(&b)
                .map_err(err)?
                .ok_or_else(|| EvalError::Internal("no output".into()))?;
            vsum += (o.reconstruction - b.features)
                .powi_scalar(2)
                .mean()
                .into_scalar::<f32>() as f64;
        }
        Ok(vsum / self.valid.len() as f64)
    }

    /// The millimetres per network output unit of a geometry.
    fn unit(&self, g: &str) -> f64 {
        self.cases[g].frame.unit_mm()
    }

    /// Validation node error of LIBR alone (mm): the correction's starting point (NaN for a
    /// ground-truth target).
    fn libr_valid_mm(&self) -> f64 {
        self.valid
            .iter()
            .map(|s| {
                let t = s.data.target.as_deref().unwrap_or(&[]);
                let zero = Tensor::<2>::zeros([s.data.num_nodes, 3], &self.plain);
                match self.opts.config.target {
                    Target::Residual => node_error_mm(&zero, t, self.unit(&s.geometry)),
                    Target::Gt => f64::NAN,
                }
            })
            .sum::<f64>()
            / self.valid.len() as f64
    }

    /// Validation node error at every candidate correction scale (the last is 1).
    fn validate(&self, vnet: &SrGcn) -> Result<Vec<f64>, EvalError> {
        let grid = &self.grid;
        let mut verr = vec![0.0; grid.len()];
        for s in self.valid {
            let (_, y) = mesh_loss(
                vnet,
                vnet,
                &self.opts.config,
                &s.data,
                &self.graphs[&s.geometry].1,
                self.through(s, 1),
                &self.plain,
                &self.plain,
            )
            .map_err(EvalError::from)?;
            let errs = scaled_errors_mm(
                &y,
                s.data.target.as_deref().unwrap_or(&[]),
                self.unit(&s.geometry),
                grid,
            );
            for (a, e) in verr.iter_mut().zip(errs) {
                *a += e / self.valid.len() as f64;
            }
        }
        Ok(verr)
    }

    /// Stage 2: the mesh branch, the bipartite branch frozen; validated every epoch, the best
    /// checkpointed to `out`, stopping on a plateau or before the time limit.
    fn mesh_stage(
        &self,
        mut net: SrGcn,
        order: &mut [usize],
        log: &mut Vec<EpochLog>,
        out: &Path,
        provenance: &serde_json::Value,
    ) -> Result<Best, EvalError> {
        let opts = self.opts;
        let frozen = net.valid();
        let mut optim = AdamConfig::new()
            .with_weight_decay(
                (opts.weight_decay > 0.0)
                    .then(|| burn::optim::decay::WeightDecayConfig::new(opts.weight_decay as f32)),
            )
            .init();
        let mut lr = opts.learning_rate;
        let last = self.grid.len() - 1;
        let mut best = Best {
            net: net.valid(),
            mm: f64::INFINITY,
            errs: vec![f64::INFINITY; self.grid.len()],
        };
        if opts.epochs == 0 {
            // Nothing to train: the starting network, validated.
            best.errs = self.validate(&best.net)?;
            best.mm = best.errs[last];
        }
        let mut average = weight_average(opts, order.len())?;
        let mut stall = 0;
        for epoch in 1..=opts.epochs {
            shuffle(order, opts.seed.wrapping_add(1000 + epoch as u64));
            let mut step = |lr: f64, net: SrGcn, grads: GradientsParams| optim.step(lr, net, grads);
            let (trained, sum, mean_lr) =
                self.mesh_epoch(net, &frozen, order, epoch, &mut lr, &mut step, &mut average)?;
            net = trained;
            let vnet = match average.as_ref().and_then(WeightAverage::get) {
                Some(a) => a.clone(),
                None => net.valid(),
            };
            let verr = self.validate(&vnet)?;
            let v = verr[last];
            log.push(EpochLog {
                stage: 2,
                epoch,
                train_loss: sum / order.len() as f64,
                valid: v,
                learning_rate: mean_lr,
                seconds: self.t0.elapsed().as_secs_f64(),
            });
            if v < best.mm {
                best = Best {
                    net: vnet,
                    mm: v,
                    errs: verr,
                };
                stall = 0;
                let mut prov = provenance.clone();
                prov["checkpoint"] =
                    serde_json::json!({"stage": 2, "epoch": epoch, "valid_node_error_mm": v});
                save_model(out, &opts.config, &best.net, prov)?;
            } else if opts.schedule == Schedule::Plateau {
                stall += 1;
                lr *= 0.5;
                if stall >= opts.patience {
                    break;
                }
            }
            if self.out_of_time(log) {
                break;
            }
        }
        Ok(best)
    }

    /// One epoch of the mesh stage over `order`: the trained network, the summed loss and the
    /// epoch's learning rate (its mean under the cosine schedule, which sets `lr` step by step).
    #[allow(clippy::too_many_arguments)]
    fn mesh_epoch(
        &self,
        mut net: SrGcn,
        frozen: &SrGcn,
        order: &[usize],
        epoch: usize,
        lr: &mut f64,
        step: &mut dyn FnMut(f64, SrGcn, GradientsParams) -> SrGcn,
        average: &mut Option<WeightAverage>,
    ) -> Result<(SrGcn, f64, f64), EvalError> {
        let opts = self.opts;
        let mut sum = 0.0;
        let mut lr_sum = 0.0;
        for (k, &i) in order.iter().enumerate() {
            let s = &self.train[i];
            let (loss, _) = mesh_loss(
                &net,
                frozen,
                &opts.config,
                &self.seen(&s.data, 2, epoch, k),
                &self.graphs[&s.geometry].0,
                self.through(s, 0),
                &self.plain,
                &self.device,
            )
            .map_err(EvalError::from)?;
            let l: f64 = loss.clone().into_scalar::<f32>() as f64;
            if !l.is_finite() {
                return Err(EvalError::Training(format!(
                    "stage 2, epoch {epoch}: the loss is not finite"
                )));
            }
            sum += l;
            if opts.schedule == Schedule::Cosine {
                let steps = (opts.epochs * order.len()).max(1) as f64;
                let p_steps = ((epoch - 1) * order.len() + k) as f64 / steps;
                let p_time = self.t0.elapsed().as_secs_f64() / (60.0 * opts.max_minutes).max(1e-9);
                *lr = opts.schedule.rate(opts.learning_rate, p_steps.max(p_time));
                lr_sum += *lr;
            }
            let grads = GradientsParams::from_grads(loss.backward(), &net);
            net = step(*lr, net, grads);
            if let Some(a) = average.as_mut() {
                a.update(net.valid())?;
            }
            (self.progress)(2, epoch, k + 1, order.len(), sum / (k + 1) as f64);
        }
        let mean_lr = if opts.schedule == Schedule::Cosine {
            lr_sum / order.len().max(1) as f64
        } else {
            *lr
        };
        Ok((net, sum, mean_lr))
    }

    /// Whether the next epoch would end past the time limit (judged by the last one).
    fn out_of_time(&self, log: &[EpochLog]) -> bool {
        let epoch_s = log.last().map_or(0.0, |l| l.seconds)
            - log.iter().rev().nth(1).map_or(0.0, |l| l.seconds);
        self.t0.elapsed().as_secs_f64() + epoch_s > 60.0 * self.opts.max_minutes
    }
}

/// The running weight average of the mesh stage, when asked (`average_epochs` > 0: its decay
/// spans that many epochs of `steps_per_epoch` steps).
fn weight_average(
    opts: &TrainOptions,
    steps_per_epoch: usize,
) -> Result<Option<WeightAverage>, EvalError> {
    if !(opts.average_epochs >= 0.0 && opts.average_epochs.is_finite()) {
        return Err(EvalError::Training(format!(
            "average_epochs must be finite and ≥ 0, got {}",
            opts.average_epochs
        )));
    }
    if opts.average_epochs == 0.0 {
        return Ok(None);
    }
    let steps = opts.average_epochs * steps_per_epoch as f64;
    Ok(Some(WeightAverage::new(1.0 - 1.0 / steps.max(1.0))?))
}
