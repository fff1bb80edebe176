//! Training runs (`librplus train`): a network trained on a dataset split, then tested on the
//! split's held-out scenarios by `evaluate`'s own code. The model directory gets the network
//! with its provenance, `training.json`, `test.json` and the loss curves; the caller gets the
//! test figures to show.

mod pairs;
mod scenarios;
mod srgcn;
mod v2s;

pub use pairs::{PairTotals, pair_rows};

use super::EvalError;
use super::runs::{RunOrigin, RunProgress};
use super::train::{Schedule, Validation};
use crate::gcn::model::SrGcnConfig;
use crate::pipeline::PipelineParams;
use crate::v2s::model::V2sConfig;
use std::path::PathBuf;

/// One training run: its data, model directory, split and budget, and the network it trains.
#[derive(Debug, Clone)]
pub struct TrainRunOptions {
    /// Dataset directory (from `librplus generate`).
    pub data: PathBuf,
    /// Model directory to write.
    pub out: PathBuf,
    /// The split, as [`super::train::TrainSplit::parse`] reads it (`random`, `geo-def`,
    /// `logo:GEOMETRY`, `pattern-v`, `family:NAME`).
    pub split: String,
    /// Every k-th block of five scenarios is used (training and test).
    pub every: usize,
    /// Seed of the split, the initial weights and the sample order.
    pub seed: u64,
    /// What validation holds out of the training scenarios.
    pub validation: Validation,
    /// Epochs at most (SR-GCN: of stage 2).
    pub epochs: usize,
    /// Epochs in a row without a better validation error before training stops (plateau
    /// schedule).
    pub patience: usize,
    /// The learning-rate schedule.
    pub schedule: Schedule,
    /// Training stops before an epoch that would end past this many minutes.
    pub max_minutes: f64,
    /// The registration's parameters (wICP, LIBR, the refit).
    pub params: PipelineParams,
    /// An augmented model (`physics.json`) whose LIBR residual the network learns (SR-GCN only).
    pub physics: Option<PathBuf>,
    /// A model directory whose network and weights training starts from (SR-GCN only).
    pub init: Option<PathBuf>,
    /// The network trained, with its own options.
    pub network: NetworkOptions,
    /// How the run was started (recorded in the model's provenance).
    pub origin: RunOrigin,
}

/// The network a training run trains.
#[derive(Debug, Clone)]
pub enum NetworkOptions {
    /// SR-GCN, LIBR's learned residual (LIBR+).
    Srgcn(SrgcnOptions),
    /// The V2S-Net-style volumetric network, the data-driven baseline.
    V2s(V2sOptions),
}

/// The options of an SR-GCN training run.
#[derive(Debug, Clone)]
pub struct SrgcnOptions {
    /// The network's settings before [`Self::ablation`] applies (an initial model's replace
    /// them).
    pub config: SrGcnConfig,
    /// Weight λ of the sparse-measurement loss (None: the configuration's).
    pub sparse_weight: Option<f64>,
    /// The paper's Table 2 setting 1-6 (inputs and losses; 6: the full model).
    pub ablation: u32,
    /// Stage-1 (bipartite branch) epochs.
    pub epochs_bipartite: usize,
    /// Initial Adam learning rate.
    pub learning_rate: f64,
    /// Train through LIBR+'s refit where it applies (the refit on, a residual target); false:
    /// on the raw correction.
    pub refit_loss: bool,
    /// Epochs of the exponential moving average of the stage-2 weights (0: off).
    pub average_epochs: f64,
    /// L2 penalty on the mesh branch's weights (0: none).
    pub weight_decay: f64,
    /// Strength of the random affine jitter of the position inputs (0: none).
    pub position_jitter: f64,
}

/// The options of a V2S training run.
#[derive(Debug, Clone)]
pub struct V2sOptions {
    /// The network and its grid.
    pub config: V2sConfig,
    /// Initial Adam learning rate.
    pub learning_rate: f64,
}

/// Which network a run trained, as its figures name the two methods compared.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrainedNetwork {
    /// SR-GCN: LIBR (first) against LIBR+ (second).
    Srgcn,
    /// V2S: wICP (first) against V2S (second).
    V2s,
}

/// What a training run found on its held-out scenarios.
#[derive(Debug, Clone)]
pub struct TrainRunOutcome {
    /// The network trained.
    pub network: TrainedNetwork,
    /// The split's name.
    pub split: String,
    /// TRE sums of the method without the network (first) and with it (second).
    pub test: PairTotals,
    /// Seconds of training.
    pub train_seconds: f64,
    /// Seconds of the LIBR solutions the samples were built from (SR-GCN; 0 for V2S).
    pub libr_seconds: f64,
}

/// Trains the network `o` names on its split and tests it on the held-out scenarios, writing the
/// model directory.
pub fn train_and_test(
    o: &TrainRunOptions,
    progress: &dyn RunProgress,
) -> Result<TrainRunOutcome, EvalError> {
    match &o.network {
        NetworkOptions::Srgcn(s) => srgcn::train_and_test(o, s, progress),
        NetworkOptions::V2s(v) => v2s::train_and_test(o, v, progress),
    }
}

/// A loss chart's series: (epoch, value) of every epoch of `log` that `keep` selects.
fn series(
    log: &[super::train::EpochLog],
    keep: impl Fn(&super::train::EpochLog) -> bool,
    value: impl Fn(&super::train::EpochLog) -> f64,
) -> Vec<(f64, f64)> {
    log.iter()
        .filter(|l| keep(l))
        .map(|l| (l.epoch as f64, value(l)))
        .collect()
}

/// A training step's progress and, at the end of each epoch, its log line (`started`: when
/// training began).
fn epoch_progress(
    progress: &dyn RunProgress,
    prefix: &str,
    epoch: usize,
    done: usize,
    total: usize,
    loss: f64,
    started: std::time::Instant,
) {
    progress.step(
        done,
        total,
        Some(&format!("{prefix}epoch {epoch} loss {loss:.4}")),
    );
    if done == total {
        progress.log(&format!(
            "{prefix}epoch {epoch}: {total} steps, training loss {loss:.5}, {:.0} s",
            started.elapsed().as_secs_f64()
        ));
    }
}
