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
mod run;
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
use crate::gcn::io::TrainedModel;
use crate::gcn::model::SrGcnConfig;
use loss::*;
use samples::through_refit;
use std::path::PathBuf;

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

pub use run::train;

#[cfg(test)]
mod tests {
    use super::average::FlatParams;
    use super::*;
    use crate::eval::EvalError;
    use crate::gcn::model::SrGcn;
    use burn::module::Module;
    use burn::tensor::Device;
    use std::collections::BTreeMap;

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
