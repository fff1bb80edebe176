//! The model-discrepancy workflow: find where LIBR's model and a cohort's measured data disagree,
//! name the missing physical effect, add it to the model, and show the gap shrink.
//!
//! A **cohort** is the sparse measurements of one deformed state (several sweeps of the same
//! organ). The workflow never sees how the data were made, nor any ground truth.
//!
//! 1. **Register** each sweep with plain LIBR (wICP, then LIBR); keep its pose and its converged
//!    correspondences, and linearize the misfit there ([`rows`]): one row per surface match along
//!    its normal (three for vessel points), with the sweep's six pose columns.
//! 2. **Find** ([`cv`]): the points of all sweeps are split into spatial blocks (k-means); each
//!    fold holds one block out of every sweep, fits the shared deformation on the rest with every
//!    sweep's own pose, and scores the held-out rows after fitting only the sweep's pose. The
//!    noise floor comes from the data ([`noise`]: local quadric fits); a posterior-predictive
//!    bootstrap (LIBR's weights drawn from their posterior, seen with noise at the floor,
//!    cross-validated the same way) says how large the held-out misfit would be if the model
//!    were right: "disagrees beyond noise" when the observed
//!    misfit exceeds every bootstrap replicate and the noise floor by a clear margin.
//! 3. **Name** ([`search`]): every kind in the library is searched over its parameters on top of
//!    the current model, under physics' priors on the loads' size and direction ([`prior`]), and
//!    scored by the same cross-validation; the promising are confirmed on their own
//!    linearization (every sweep registered again with the augmented model). The best is named
//!    only when it
//!    beats the current model on the held-out blocks significantly (a paired comparison over
//!    the sweep × block units: Wilcoxon signed-rank z above [`DiscoverParams::z_threshold`]), by a practical margin
//!    ([`DiscoverParams::min_gain`]) and by the Bayesian information criterion; then the next is
//!    tried on top (forward selection). Every model is compared at its own cross-validated
//!    prior weight ([`cv::PRIOR_SCALES`], reaching below LIBR's λ). Verdicts: named effects;
//!    `refine-loads` (LIBR's loads under a weaker prior than λ explain the misfit, nothing
//!    physical adds to them); no missing effect; or an unexplained discrepancy (real, but no
//!    candidate explains it).
//! 4. **Add**: the named effects are a [`Physics`] (`physics.json`) that `register --physics`
//!    carries.

mod confirm;
pub mod cv;
mod family;
mod find;
mod linearize;
pub mod maps;
mod name;
pub mod noise;
pub mod oracle;
pub mod prior;
pub mod rows;
pub mod search;
mod show;
mod stats;

use crate::pipeline::{PipelineError, PipelineParams};
pub use crate::register::physics::kinds::SearchGrid;
use crate::register::physics::{Effect, EffectKind, Physics};
use crate::register::{Checked, PreopModel, RegisterError};
use std::path::Path;
use std::time::Instant;

/// Why discovery could not run.
#[derive(Debug, thiserror::Error)]
pub enum DiscoverError {
    /// The cohort or a parameter is unusable; the message names the field.
    #[error("{0}")]
    Input(String),
    /// A sweep could not be registered (the message names it).
    /// (The cause is in the message and not chained as a source, so an error report prints it
    /// once.)
    #[error("scenario {scenario}: {cause}")]
    Scenario {
        /// The sweep's id.
        scenario: String,
        /// Why.
        cause: PipelineError,
    },
    /// The model (basis, physics) could not be built.
    #[error(transparent)]
    Model(#[from] RegisterError),
    /// The cohort's data do not determine the fit (too few points per sweep).
    #[error("{0}")]
    Underdetermined(String),
    /// [`DiscoverParams::deadline`] passed before the workflow finished (the stage named).
    #[error("out of time: the deadline passed while {0}")]
    OutOfTime(String),
}

/// Fails with [`DiscoverError::OutOfTime`] once `params.deadline` has passed.
fn in_time(params: &DiscoverParams, stage: &str) -> Result<(), DiscoverError> {
    match params.deadline {
        Some(d) if Instant::now() >= d => Err(DiscoverError::OutOfTime(stage.to_string())),
        _ => Ok(()),
    }
}

/// Settings of the workflow.
#[derive(Debug, Clone)]
pub struct DiscoverParams {
    /// Registration settings (wICP, LIBR).
    pub pipeline: PipelineParams,
    /// Spatial blocks (folds). Default 6.
    pub folds: usize,
    /// Bootstrap replicates of the no-discrepancy null. Default 19 (p ≤ 0.05 when the observed
    /// misfit exceeds all).
    pub bootstrap: usize,
    /// Wilcoxon signed-rank z a candidate must exceed over the sweep × block units (of the
    /// held-out misfit it removes per unit). Default 3.0 (one-sided p ≈ 0.001, a
    /// Bonferroni-style margin for searching eight kinds and their parameters).
    pub z_threshold: f64,
    /// Smallest fraction of the held-out misfit a candidate must remove. Default 0.05.
    pub min_gain: f64,
    /// Most effects named. Default 3.
    pub max_effects: usize,
    /// Candidates per round confirmed on their own linearization (the best screened). Default 3.
    pub confirmations: usize,
    /// Kinds searched. Default every kind the augmented model carries (not `nonlinear`).
    pub kinds: Vec<EffectKind>,
    /// Grid sizes: gravity/pressure directions, pack and fixation sites, inclusion sites.
    pub grid: SearchGrid,
    /// Seed of the bootstrap noise.
    pub seed: u64,
    /// Give up (with [`DiscoverError::OutOfTime`]) once this instant has passed; checked
    /// between stages, sweeps and candidates, so the overrun is at most one such step. None:
    /// no limit.
    pub deadline: Option<Instant>,
}

impl Default for DiscoverParams {
    fn default() -> Self {
        Self {
            pipeline: PipelineParams::default(),
            folds: 6,
            bootstrap: 19,
            z_threshold: 3.0,
            min_gain: 0.05,
            max_effects: 3,
            confirmations: 3,
            kinds: EffectKind::ALL
                .into_iter()
                .filter(|k| k.is_carried())
                .collect(),
            grid: SearchGrid::default(),
            seed: 0,
            deadline: None,
        }
    }
}

impl DiscoverParams {
    /// The coarse search (16 directions, 8 pack, 4 fixation and 2 inclusion sites, 5 blocks, 9
    /// bootstrap replicates; everything else the default): for discovery under a time limit
    /// (the server's in-surgery runs) and for tests.
    pub fn coarse() -> Self {
        Self {
            folds: 5,
            bootstrap: 9,
            grid: SearchGrid::coarse(),
            ..Self::default()
        }
    }
}

/// One sweep of a cohort.
#[derive(Debug, Clone)]
pub struct Sweep {
    /// Its id (for messages and reports).
    pub id: String,
    /// Its measurements (physical frame).
    pub measurements: Checked,
}

/// One acquisition (a surgery session's points, all of one deformed state under one pose) as
/// `parts` sweeps for [`discover_cohort`]: point `i` (in acquisition order) goes to sweep
/// `i mod parts`, so every sweep covers what the acquisition covers, every ultrasound plane
/// included. The sweeps are not independent acquisitions: each is registered with its own pose,
/// which the shared pose makes agree, and the cross-validation still holds out whole spatial
/// blocks of every sweep, so a misfit must be shared by the region to count.
pub fn session_sweeps(m: &Checked, parts: usize) -> Vec<Sweep> {
    let parts = parts.max(1);
    (0..parts)
        .map(|k| {
            let idx: Vec<usize> = (0..m.points.len()).filter(|i| i % parts == k).collect();
            Sweep {
                id: format!("part-{}-of-{parts}", k + 1),
                measurements: m.subset(&idx),
            }
        })
        .collect()
}

/// The verdict of a cohort.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// Named effects explain (part of) the discrepancy.
    Effects,
    /// The model and the data agree within what noise and sparse data allow.
    None,
    /// Real discrepancy, no candidate explains it.
    Unexplained,
    /// Richer surface loads explain the misfit (LIBR's loads under a weaker strain-energy prior
    /// than registration's λ) and no physical kind adds to them: the load model is too stiff
    /// here, no physical effect is missing.
    #[serde(rename = "refine-loads")]
    RefineLoads,
}

/// A named effect with its evidence.
#[derive(Debug, Clone, serde::Serialize)]
pub struct NamedEffect {
    /// The effect and its parameters.
    #[serde(skip)]
    pub effect: Effect,
    /// Parameter uncertainty (standard deviations of amplitudes; spread of the searched shape
    /// parameters among candidates the data cannot tell apart).
    pub uncertainty: serde_json::Value,
    /// Evidence: held-out misfit before/after, t statistic, gain, BIC change.
    pub evidence: serde_json::Value,
}

/// A candidate's score in one round of the forward selection.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CandidateRecord {
    /// Round (0 = on top of plain LIBR).
    pub round: usize,
    /// Kind.
    pub kind: String,
    /// The best parameters found.
    pub effect: String,
    /// Held-out RMS misfit with it (mm).
    pub heldout_rms_mm: f64,
    /// Fraction of the current held-out misfit (mean square) it removes.
    pub gain: f64,
    /// Wilcoxon signed-rank z over the sweep × block units (positive: the candidate lowers
    /// the held-out misfit).
    pub rank_z: f64,
    /// Paired t statistic over units (reported).
    pub t: f64,
    /// Change of the Bayesian information criterion (negative favours it).
    pub delta_bic: f64,
    /// Whether the scores come from the candidate's own linearization (every sweep registered
    /// again with it; the confirming comparison) rather than the current model's (screening).
    pub relinearized: bool,
    /// Whether it passed every test.
    pub significant: bool,
}

/// The misfit in one spatial block.
#[derive(Debug, Clone, serde::Serialize)]
pub struct RegionMisfit {
    /// Block centre (image frame, mm).
    pub center: [f64; 3],
    /// Where it lies: `anterior`, `posterior`, with the nearest node's labels.
    pub region: String,
    /// Held-out RMS misfit before (plain LIBR) and after (the augmented model), mm.
    pub before_mm: f64,
    /// After.
    pub after_mm: f64,
    /// Mean signed held-out residual across sweeps (mm, outward) before.
    pub mean_signed_mm: f64,
    /// Its t statistic across sweeps (large: the same offset in every sweep, systematic).
    pub t_across_sweeps: f64,
    /// Sweeps scored in the block.
    pub sweeps: usize,
}

/// What discovery found for one cohort.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CohortDiscovery {
    /// Verdict.
    pub verdict: Verdict,
    /// Named effects.
    pub effects: Vec<NamedEffect>,
    /// The augmented model.
    #[serde(skip)]
    pub physics: Physics,
    /// Held-out RMS misfit (mm) before and after.
    pub heldout_before_mm: f64,
    /// In-sample RMS misfit of plain LIBR over the cohort (mm), poses fitted per sweep.
    pub insample_before_mm: f64,
    /// The prior weight cross-validation chose for plain LIBR, as a multiple of LIBR's λ.
    pub prior_scale_before: f64,
    /// After.
    pub heldout_after_mm: f64,
    /// Noise floor (mm) estimated from the data.
    pub noise_floor_mm: f64,
    /// Held-out RMS misfit of the bootstrap replicates under "the model is right" (mm): the
    /// largest.
    pub null_max_mm: f64,
    /// Whether the data disagree with plain LIBR beyond noise.
    pub beyond_noise: bool,
    /// Held-out RMS misfit (mm) of plain LIBR at registration's own λ (the prior weight 1; the
    /// comparisons use each model's cross-validated weight, [`cv::PRIOR_SCALES`]).
    pub heldout_at_lambda_mm: f64,
    /// Whether plain LIBR under a weaker prior than λ lowers that held-out misfit by the naming
    /// rule's z and gain: the data ask for richer surface loads than registration allows.
    pub richer_loads: bool,
    /// Spatial blocks.
    pub regions: Vec<RegionMisfit>,
    /// Every candidate scored.
    pub candidates: Vec<CandidateRecord>,
    /// Rows (matches along their directions) used.
    pub rows: usize,
    /// Sweeps used.
    pub sweeps: usize,
    /// Per-sweep registrations with plain LIBR (image → physical and u), for the caller.
    #[serde(skip)]
    pub plain: Vec<crate::pipeline::Registration>,
    /// Stage timings (s).
    pub timings: StageTimings,
}

/// Where the time went (s).
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct StageTimings {
    /// Plain basis and per-sweep registrations.
    pub register_s: f64,
    /// Rows, blocks, noise floor, base cross-validation and bootstrap.
    pub find_s: f64,
    /// The candidate search.
    pub name_s: f64,
    /// Total.
    pub total_s: f64,
}

/// Runs the workflow on one cohort. `progress(stage, done, total)` is called as it goes.
pub fn discover_cohort(
    model: &PreopModel,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cache_dir: Option<&Path>,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<CohortDiscovery, DiscoverError> {
    let t0 = Instant::now();
    let found = find::find(model, sweeps, params, cache_dir, progress)?;
    let t2 = Instant::now();
    let named = name::name(model, sweeps, params, &found, progress)?;
    let name_s = crate::util::secs(t2);
    Ok(show::show(model, sweeps, found, named, name_s, t0))
}

#[cfg(test)]
mod tests;
