//! SR-GCN training and LIBR+ inference on a dataset.
//!
//! **Splits** ([`TrainSplit`]), over the dataset's training geometries (pattern V stays unseen
//! except as the `pattern-v` test): `random` (blocks of five consecutive scenarios, one per
//! measurement category, shuffled by the seed; 80 % train, 20 % test), `geo-def` (three whole
//! geometry–pattern deformations held out: the first geometry's first two patterns and the last
//! geometry's third, as the paper's 1-L, 1-R, 3-W), `logo:G` (every deformation of geometry G held
//! out) and `pattern-v` (train on every training deformation, test on the test geometry). A
//! seeded 10 % of the training blocks is kept for validation (early stopping).
//!
//! **Inputs** come from LIBR run on each scenario's measurements (never from the ground truth;
//! the truth only makes the training targets). LIBR solutions are cached under
//! `DATA/cache/libr-solutions/KEY/` (KEY hashes the registration parameters) so retraining or a
//! second split does not rerun LIBR.
//!
//! **Two stages** (the paper's): stage 1 trains the bipartite branch on reconstructing its input
//! (`L_b`); stage 2 freezes it and trains the mesh branch on `L_residual + λ L_sparse` (or `L_gt`
//! in the ablations). Adam; the learning rate either halves when validation stalls, with early
//! stopping ([`Schedule::Plateau`]), or anneals on a cosine over the epoch and time budget
//! ([`Schedule::Cosine`]); the epoch with the best validation node error (mm) is kept.

mod average;
mod cache;
mod calibrate;
mod loss;
mod samples;
pub mod v2s;

pub use super::splits::{
    ScenarioRef, SplitSets, TrainSplit, Validation, split_scenarios, validation_deformations,
};
pub use average::WeightAverage;
pub use cache::{
    GeometryCase, LibrSolution, final_cparams, libr_solutions, load_cases, solution_key,
    truth_positions,
};
pub use calibrate::{fit_refit_scale, refit_scale_grid};
pub use samples::{
    RefitLoss, TrainingSample, answer_through_refit, build_samples, refit_loss_data,
    training_target,
};

use super::splits::shuffle;
use crate::eval::EvalError;
use crate::gcn::io::{TrainedModel, save_model};
use crate::gcn::model::{MeshGraphs, SrGcn, SrGcnConfig, Target};
use crate::gcn::sample::{PositionJitter, SampleData};
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::Tensor;
use loss::*;
use samples::{refit_modes, through_refit};
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Training settings.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// Network configuration.
    pub config: SrGcnConfig,
    /// Split.
    pub split: TrainSplit,
    /// Keep every `every`-th block of scenarios.
    pub every: usize,
    /// Seed (split, initialisation, sample order).
    pub seed: u64,
    /// Stage-1 epochs (bipartite branch).
    pub epochs_bipartite: usize,
    /// Stage-2 epochs at most (mesh branch).
    pub epochs: usize,
    /// Initial learning rate.
    pub learning_rate: f64,
    /// Epochs without validation improvement before stopping ([`Schedule::Plateau`] only).
    pub patience: usize,
    /// How the stage-2 learning rate changes.
    pub schedule: Schedule,
    /// Train through LIBR+'s refit: the node loss (and validation) scores what the refit,
    /// linearised at each sample's LIBR solution ([`RefitLoss`]), makes of the correction, so
    /// the network learns what the refit will not put back instead of what it will
    /// overwrite. The samples must carry their [`RefitLoss`] ([`build_samples`]).
    pub refit_loss: bool,
    /// Validate and keep an exponential moving average of the stage-2 weights instead of the
    /// weights themselves, over a horizon of this many epochs (decay `1 − 1/(h·steps)` per
    /// step, warmed up over the first steps so the start does not weigh on it; 0 turns it
    /// off). The average smooths the last steps' noise, which a single validation set would
    /// otherwise pick from.
    pub average_epochs: f64,
    /// L2 penalty on the stage-2 weights, added to their gradients before Adam (0: none).
    pub weight_decay: f64,
    /// Strength of a random affine jitter of the normalised position inputs, drawn afresh for
    /// every training step ([`crate::gcn::sample::PositionJitter`]; validation is never jittered).
    /// 0: none.
    pub position_jitter: f64,
    /// Stage 2 stops before an epoch that would end past this many minutes of training (judged
    /// by the last epoch's duration).
    pub max_minutes: f64,
    /// A model directory whose weights training starts from instead of a seeded initialisation
    /// (its configuration must be `config`'s network). With 0 stage-2 epochs the model is only
    /// validated (and its correction scale fitted again).
    pub init: Option<PathBuf>,
}

impl Default for TrainOptions {
    fn default() -> Self {
        Self {
            config: SrGcnConfig::new(),
            split: TrainSplit::PatternV,
            every: 2,
            seed: 1,
            epochs_bipartite: 2,
            epochs: 12,
            learning_rate: 2e-3,
            patience: 3,
            schedule: Schedule::Plateau,
            refit_loss: false,
            average_epochs: 0.0,
            weight_decay: 0.0,
            position_jitter: 0.0,
            init: None,
            max_minutes: 25.0,
        }
    }
}

/// The stage-2 learning-rate schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Schedule {
    /// Halve the rate after every epoch whose validation error is not the best so far; stop
    /// after `patience` such epochs in a row.
    #[default]
    Plateau,
    /// Cosine annealing over the whole budget, step by step: `lr₀·½(1 + cos πp)`, where `p` is
    /// the larger of the fraction of epochs done and the fraction of `max_minutes` spent, so the
    /// rate reaches its low end whichever limit ends training. No early stop: the best
    /// validation epoch is kept.
    Cosine,
}

impl Schedule {
    /// The rate at budget fraction `p` (clamped to [0, 1]) from the initial rate `lr0`; the
    /// plateau schedule's rate is set by its epochs, so it returns `lr0`.
    pub fn rate(self, lr0: f64, p: f64) -> f64 {
        match self {
            Schedule::Plateau => lr0,
            Schedule::Cosine => {
                lr0 * 0.5 * (1.0 + (std::f64::consts::PI * p.clamp(0.0, 1.0)).cos())
            }
        }
    }
}

/// One epoch's figures.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EpochLog {
    /// Stage (1 bipartite, 2 mesh).
    pub stage: u32,
    /// Epoch within the stage (from 1).
    pub epoch: usize,
    /// Mean training loss.
    pub train_loss: f64,
    /// Validation: mean node error after correction (mm) in stage 2, loss in stage 1.
    pub valid: f64,
    /// Learning rate used.
    pub learning_rate: f64,
    /// Wall time since the start (s).
    pub seconds: f64,
}

/// What [`train`] returns.
pub struct TrainReport {
    /// The trained network (best validation epoch), on the plain device.
    pub model: TrainedModel,
    /// Per-epoch figures.
    pub log: Vec<EpochLog>,
    /// Best validation node error (mm).
    pub best_valid_mm: f64,
    /// Validation node error with the fitted correction scale (`model.config.correction_scale`).
    pub scaled_valid_mm: f64,
    /// Validation node error of LIBR alone (mm): the correction's starting point.
    pub libr_valid_mm: f64,
    /// Training samples used.
    pub train_samples: usize,
    /// Validation samples used.
    pub valid_samples: usize,
    /// Training time (s), LIBR solutions excluded.
    pub seconds: f64,
}

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
    let cfg = &opts.config;
    cfg.validate()?;
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
    std::fs::create_dir_all(out).map_err(crate::util::FileError::at("creating directory", out))?;
    let t0 = Instant::now();
    let plain = crate::gcn::device::compute();
    let device = plain.clone().autodiff();
    device.seed(opts.seed);
    let mut net = match &opts.init {
        None => cfg.init(&device)?,
        Some(dir) => {
            let m = crate::gcn::io::load_model(dir, &device)
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
            m.net
        }
    };
    let mut graphs: BTreeMap<String, (MeshGraphs, MeshGraphs)> = BTreeMap::new();
    for (g, gc) in cases {
        let ad = gc.frame.mesh_graphs(cfg, &device)?;
        let pl = gc.frame.mesh_graphs(cfg, &plain)?;
        graphs.insert(g.clone(), (ad, pl));
    }
    // The refit modes of every geometry, when training through the refit.
    let mut modes: BTreeMap<String, (Tensor<2>, Tensor<2>)> = BTreeMap::new();
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
    // A sample's linearised refit with its geometry's modes on the autodiff (0) or plain (1)
    // device.
    fn through<'a>(
        modes: &'a BTreeMap<String, (Tensor<2>, Tensor<2>)>,
        s: &'a TrainingSample,
        k: usize,
    ) -> Option<(&'a RefitLoss, &'a Tensor<2>)> {
        let m = modes.get(&s.geometry)?;
        Some((s.refit.as_ref()?, if k == 0 { &m.0 } else { &m.1 }))
    }
    let err = EvalError::from;
    // A training sample as the network sees it at step (stage, epoch, k): jittered when asked.
    fn seen<'a>(
        opts: &TrainOptions,
        s: &'a SampleData,
        stage: u64,
        epoch: usize,
        k: usize,
    ) -> Cow<'a, SampleData> {
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
    let mut log = Vec::new();
    let mut order: Vec<usize> = (0..train.len()).collect();
    // Stage 1: the bipartite branch reconstructs its input.
    if cfg.bipartite {
        let mut optim = AdamConfig::new().init();
        for epoch in 1..=opts.epochs_bipartite {
            shuffle(&mut order, opts.seed.wrapping_add(epoch as u64));
            let mut sum = 0.0;
            for (k, &i) in order.iter().enumerate() {
                let (_, bip) = seen(opts, &train[i].data, 1, epoch, k)
                    .tensors(cfg, &device)
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
                progress(1, epoch, k + 1, order.len(), sum / (k + 1) as f64);
            }
            let vnet = net.valid();
            let mut vsum = 0.0;
            for s in valid {
                let (_, bip) = s.data.tensors(cfg, &plain).map_err(err)?;
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
            log.push(EpochLog {
                stage: 1,
                epoch,
                train_loss: sum / order.len() as f64,
                valid: vsum / valid.len() as f64,
                learning_rate: opts.learning_rate,
                seconds: t0.elapsed().as_secs_f64(),
            });
        }
    }
    // Stage 2: the mesh branch.
    let unit = |g: &str| cases[g].frame.unit_mm();
    let libr_valid_mm = valid
        .iter()
        .map(|s| {
            let t = s.data.target.as_deref().unwrap_or(&[]);
            let zero = Tensor::<2>::zeros([s.data.num_nodes, 3], &plain);
            match cfg.target {
                Target::Residual => node_error_mm(&zero, t, unit(&s.geometry)),
                Target::Gt => f64::NAN,
            }
        })
        .sum::<f64>()
        / valid.len() as f64;
    let frozen = net.valid();
    let mut optim = AdamConfig::new()
        .with_weight_decay(
            (opts.weight_decay > 0.0)
                .then(|| burn::optim::decay::WeightDecayConfig::new(opts.weight_decay as f32)),
        )
        .init();
    let mut lr = opts.learning_rate;
    let mut best = f64::INFINITY;
    let mut best_net = net.valid();
    // Candidate factors on the correction: 0, 0.05, …, 1 for a residual target.
    let grid: Vec<f64> = if cfg.target == Target::Residual {
        (0..=20).map(|k| k as f64 / 20.0).collect()
    } else {
        vec![1.0]
    };
    // Validation node error at every candidate correction scale (the last is 1).
    let validate = |vnet: &SrGcn| -> Result<Vec<f64>, EvalError> {
        let mut verr = vec![0.0; grid.len()];
        for s in valid {
            let (_, y) = mesh_loss(
                vnet,
                vnet,
                cfg,
                &s.data,
                &graphs[&s.geometry].1,
                through(&modes, s, 1),
                &plain,
                &plain,
            )
            .map_err(err)?;
            let errs = scaled_errors_mm(
                &y,
                s.data.target.as_deref().unwrap_or(&[]),
                unit(&s.geometry),
                &grid,
            );
            for (a, e) in verr.iter_mut().zip(errs) {
                *a += e / valid.len() as f64;
            }
        }
        Ok(verr)
    };
    let mut best_err = vec![f64::INFINITY; grid.len()];
    if opts.epochs == 0 {
        // Nothing to train: the starting network, validated.
        best_err = validate(&best_net)?;
        best = best_err[grid.len() - 1];
    }
    if !(opts.average_epochs >= 0.0 && opts.average_epochs.is_finite()) {
        return Err(EvalError::Training(format!(
            "average_epochs must be finite and ≥ 0, got {}",
            opts.average_epochs
        )));
    }
    let mut average = if opts.average_epochs > 0.0 {
        let steps = opts.average_epochs * order.len() as f64;
        Some(WeightAverage::new(1.0 - 1.0 / steps.max(1.0))?)
    } else {
        None
    };
    let mut stall = 0;
    for epoch in 1..=opts.epochs {
        shuffle(&mut order, opts.seed.wrapping_add(1000 + epoch as u64));
        let mut sum = 0.0;
        let mut lr_sum = 0.0;
        for (k, &i) in order.iter().enumerate() {
            let s = &train[i];
            let (loss, _) = mesh_loss(
                &net,
                &frozen,
                cfg,
                &seen(opts, &s.data, 2, epoch, k),
                &graphs[&s.geometry].0,
                through(&modes, s, 0),
                &plain,
                &device,
            )
            .map_err(err)?;
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
                let p_time = t0.elapsed().as_secs_f64() / (60.0 * opts.max_minutes).max(1e-9);
                lr = opts.schedule.rate(opts.learning_rate, p_steps.max(p_time));
                lr_sum += lr;
            }
            let grads = GradientsParams::from_grads(loss.backward(), &net);
            net = optim.step(lr, net, grads);
            if let Some(a) = average.as_mut() {
                a.update(net.valid())?;
            }
            progress(2, epoch, k + 1, order.len(), sum / (k + 1) as f64);
        }
        let vnet = match average.as_ref().and_then(WeightAverage::get) {
            Some(a) => a.clone(),
            None => net.valid(),
        };
        let verr = validate(&vnet)?;
        let v = verr[grid.len() - 1];
        log.push(EpochLog {
            stage: 2,
            epoch,
            train_loss: sum / order.len() as f64,
            valid: v,
            // The epoch's mean rate under the cosine schedule.
            learning_rate: if opts.schedule == Schedule::Cosine {
                lr_sum / order.len().max(1) as f64
            } else {
                lr
            },
            seconds: t0.elapsed().as_secs_f64(),
        });
        if v < best {
            best = v;
            best_net = vnet;
            best_err = verr;
            stall = 0;
            let mut prov = provenance.clone();
            prov["checkpoint"] =
                serde_json::json!({"stage": 2, "epoch": epoch, "valid_node_error_mm": v});
            save_model(out, cfg, &best_net, prov)?;
        } else if opts.schedule == Schedule::Plateau {
            stall += 1;
            lr *= 0.5;
            if stall >= opts.patience {
                break;
            }
        }
        // Stop before an epoch that would end past the time limit (judged by the last one).
        let epoch_s = log.last().map_or(0.0, |l: &EpochLog| l.seconds)
            - log
                .iter()
                .rev()
                .nth(1)
                .map_or(0.0, |l: &EpochLog| l.seconds);
        if t0.elapsed().as_secs_f64() + epoch_s > 60.0 * opts.max_minutes {
            break;
        }
    }
    // The correction's scale, fitted on the best epoch's validation errors: the largest factor
    // among the best (ties keep more of the correction).
    let mut config = cfg.clone();
    let (k, scaled_valid_mm) =
        best_err
            .iter()
            .enumerate()
            .rev()
            .fold((grid.len() - 1, best), |acc, (k, e)| {
                if *e < acc.1 - 1e-9 { (k, *e) } else { acc }
            });
    config.correction_scale = grid[k];
    Ok(TrainReport {
        model: TrainedModel {
            config,
            net: best_net,
            provenance: provenance.clone(),
            abstain: None,
        },
        log,
        scaled_valid_mm,
        best_valid_mm: best,
        libr_valid_mm,
        train_samples: train.len(),
        valid_samples: valid.len(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::average::FlatParams;
    use super::*;
    use burn::tensor::Device;

    fn flat(net: &SrGcn) -> Vec<Vec<f32>> {
        let mut f = FlatParams(Vec::new());
        net.visit(&mut f);
        f.0.into_iter()
            .map(|t| t.into_data().try_to_vec::<f32>().unwrap())
            .collect()
    }

    fn net(seed: u64) -> SrGcn {
        let device = Device::flex();
        device.seed(seed);
        SrGcnConfig::new().with_width(8).init(&device).unwrap()
    }

    #[test]
    fn the_weight_average_blends_every_parameter_by_its_warmed_up_decay() {
        let (a, b, c) = (net(1), net(2), net(3));
        // (Parameters initialise lazily: read them once so the clones below share them.)
        let (fa, fb, fc) = (flat(&a), flat(&b), flat(&c));
        let (a2, b2) = (a.clone(), b.clone());
        assert!(
            fa.len() > 4,
            "the network has {} float parameters",
            fa.len()
        );
        assert_ne!(fa, fb, "two seeds gave the same weights");
        let mut avg = WeightAverage::new(0.9).unwrap();
        assert!(avg.get().is_none());
        avg.update(a).unwrap();
        assert_eq!(
            flat(avg.get().unwrap()),
            fa,
            "the first update is the weights"
        );
        avg.update(b).unwrap();
        avg.update(c).unwrap();
        assert_eq!(avg.steps(), 3);
        // Step 2 keeps min(0.9, 3/12) of the average, step 3 min(0.9, 4/13).
        let (k2, k3) = (3.0 / 12.0, 4.0 / 13.0);
        let got = flat(avg.get().unwrap());
        let mut worst = 0.0f64;
        for (((g, a), b), c) in got.iter().zip(&fa).zip(&fb).zip(&fc) {
            assert_eq!(g.len(), a.len());
            for i in 0..g.len() {
                let want = (k3 * (k2 * a[i] as f64 + (1.0 - k2) * b[i] as f64)
                    + (1.0 - k3) * c[i] as f64) as f32;
                worst = worst.max((g[i] - want).abs() as f64 / (1.0 + want.abs() as f64));
            }
        }
        assert!(worst < 1e-6, "largest relative difference {worst}");
        // Late in training the decay rules: keep = 0.9 from step 81 on.
        let mut late = WeightAverage::new(0.9).unwrap();
        for _ in 0..100 {
            late.update(a2.clone()).unwrap();
        }
        late.update(b2).unwrap();
        let got = flat(late.get().unwrap());
        let (p, q, r) = (fa[0][0] as f64, fb[0][0] as f64, got[0][0] as f64);
        // (101 f32 blends: rounding grows to a few 1e-7.)
        let want = 0.9 * p + 0.1 * q;
        assert!(
            (r - want).abs() < 1e-5 * (1.0 + p.abs()),
            "got {r}, want {want} (0.9 × {p} + 0.1 × {q})"
        );
    }

    #[test]
    fn the_weight_average_refuses_a_bad_decay_or_another_network() {
        for d in [1.0, -0.1, f64::NAN] {
            let e = WeightAverage::new(d).err().unwrap();
            assert!(matches!(e, EvalError::Parameter(_)), "{e}");
            assert!(e.to_string().contains("decay"), "{e}");
        }
        let mut avg = WeightAverage::new(0.5).unwrap();
        avg.update(net(1)).unwrap();
        let device = Device::flex();
        let other = SrGcnConfig::new().with_width(4).init(&device).unwrap();
        let e = avg.update(other).err().unwrap();
        assert!(e.to_string().contains("differ"), "{e}");
    }

    #[test]
    fn training_refuses_a_negative_or_non_finite_weight_decay_or_position_jitter() {
        let with_decay = |x| TrainOptions {
            weight_decay: x,
            ..TrainOptions::default()
        };
        let with_jitter = |x| TrainOptions {
            position_jitter: x,
            ..TrainOptions::default()
        };
        let cases: [(&str, &dyn Fn(f64) -> TrainOptions); 2] = [
            ("weight_decay", &with_decay),
            ("position_jitter", &with_jitter),
        ];
        for (field, options) in cases {
            for x in [-1e-3, f64::NAN, f64::INFINITY] {
                let tmp = tempfile::tempdir().unwrap();
                let out = tmp.path().join("refused");
                let err = match train(
                    &options(x),
                    &BTreeMap::new(),
                    &[],
                    &[],
                    &out,
                    &serde_json::json!({}),
                    &|_, _, _, _, _| {},
                ) {
                    Ok(_) => panic!("{field} {x} accepted"),
                    Err(e) => e,
                };
                assert!(err.to_string().contains(field), "{field} {x}: {err}");
            }
        }
    }
}
