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

pub mod cv;
pub mod maps;
pub mod noise;
pub mod oracle;
pub mod prior;
pub mod rows;
pub mod search;

use crate::pipeline::{Method, PipelineError, PipelineParams, Prepared, register};
use crate::register::physics::model::{BoundaryGeometry, ModelSolver, Sites};
use crate::register::physics::{Effect, EffectKind, Physics};
use crate::register::{MeasuredKind, Measurements, PreopModel, RegisterError};
use cv::{AmplitudePrior, CvScore, Design, cross_validate, cross_validate_rhs, fitted};
use rayon::prelude::*;
use rows::{CohortRows, cluster_centers, nearest, scenario_rows};
use search::{Candidate, Current, SearchContext, basis_design};
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

/// How finely each family is searched.
#[derive(Debug, Clone, Copy)]
pub struct SearchGrid {
    /// Directions tried for gravity and pressure (then refined). Default 32.
    pub directions: usize,
    /// Boundary sites tried for packs. Default 24.
    pub pack_sites: usize,
    /// Pack widths (mm). Default 12, 25.
    pub pack_widths: [f64; 2],
    /// Boundary sites tried for fixations. Default 8.
    pub fixation_sites: usize,
    /// Interior sites tried for inclusions. Default 6.
    pub inclusion_sites: usize,
}

impl Default for SearchGrid {
    fn default() -> Self {
        Self {
            directions: 32,
            pack_sites: 24,
            pack_widths: [12.0, 25.0],
            fixation_sites: 8,
            inclusion_sites: 6,
        }
    }
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
                .filter(|k| *k != EffectKind::Nonlinear)
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
            grid: SearchGrid {
                directions: 16,
                pack_sites: 8,
                pack_widths: [12.0, 25.0],
                fixation_sites: 4,
                inclusion_sites: 2,
            },
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
    pub measurements: Measurements,
}

/// One acquisition (a surgery session's points, all of one deformed state under one pose) as
/// `parts` sweeps for [`discover_cohort`]: point `i` (in acquisition order) goes to sweep
/// `i mod parts`, so every sweep covers what the acquisition covers, every ultrasound plane
/// included. The sweeps are not independent acquisitions: each is registered with its own pose,
/// which the shared pose makes agree, and the cross-validation still holds out whole spatial
/// blocks of every sweep, so a misfit must be shared by the region to count.
pub fn session_sweeps(m: &Measurements, parts: usize) -> Vec<Sweep> {
    let parts = parts.max(1);
    (0..parts)
        .map(|k| {
            let pick = |i: &usize| i % parts == k;
            let idx: Vec<usize> = (0..m.points.len()).filter(pick).collect();
            Sweep {
                id: format!("part-{}-of-{parts}", k + 1),
                measurements: Measurements {
                    points: idx.iter().map(|&i| m.points[i]).collect(),
                    kind: idx.iter().map(|&i| m.kind[i]).collect(),
                    feature: if m.feature.len() == m.points.len() {
                        idx.iter().map(|&i| m.feature[i]).collect()
                    } else {
                        Vec::new()
                    },
                    initial_alignment: m.initial_alignment,
                },
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
    let found = find(model, sweeps, params, cache_dir, progress)?;
    let t2 = Instant::now();
    let named = name(model, sweeps, params, &found, progress)?;
    let name_s = crate::util::secs(t2);
    Ok(show(model, sweeps, found, named, name_s, t0))
}

/// What the find stage leaves for naming: the plain model's registrations, rows and
/// cross-validated score, the noise floor, and whether the data disagree beyond noise.
struct Found {
    prepared: Prepared,
    plain: Vec<crate::pipeline::Registration>,
    rows: CohortRows,
    geom: BoundaryGeometry,
    basis: crate::register::libr::LibrBasis,
    a: nalgebra::DMatrix<f64>,
    prior: nalgebra::DMatrix<f64>,
    base_score: CvScore,
    noise_floor_mm: f64,
    noise_var: f64,
    null_max_mm: f64,
    beyond_noise: bool,
    heldout_at_lambda_mm: f64,
    richer_loads: bool,
    /// The `refine-loads` record, where LIBR's loads cross-validate best under a weaker prior.
    refine_record: Option<CandidateRecord>,
    register_s: f64,
    find_s: f64,
}

/// Steps 1 and 2: registers every sweep with plain LIBR, linearizes, cross-validates plain LIBR,
/// estimates the noise floor and the bootstrap null, and asks whether richer loads explain more.
fn find(
    model: &PreopModel,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cache_dir: Option<&Path>,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Found, DiscoverError> {
    let t0 = Instant::now();
    if sweeps.is_empty() {
        return Err(DiscoverError::Input(
            "cohort: no scenarios (a cohort needs at least 2 sweeps of one deformed state)".into(),
        ));
    }
    if sweeps.len() < 2 {
        return Err(DiscoverError::Input(format!(
            "cohort: only 1 scenario ({}); cross-validation across sweeps needs at least 2",
            sweeps[0].id
        )));
    }
    if params.folds < 2 {
        return Err(DiscoverError::Input(format!(
            "folds: {} (at least 2 spatial blocks are needed to hold one out)",
            params.folds
        )));
    }
    for s in sweeps {
        crate::register::correspondence::validate_measurements(&s.measurements)
            .map_err(|e| DiscoverError::Input(format!("scenario {}: measurements: {e}", s.id)))?;
    }
    // 1. Register each sweep with plain LIBR.
    let prepared =
        Prepared::new(model.clone(), Some(&params.pipeline.libr), cache_dir).map_err(|e| {
            DiscoverError::Scenario {
                scenario: "(case)".into(),
                cause: e,
            }
        })?;
    let (plain, images, rows) = linearize(&prepared, sweeps, params, None, progress)?;
    let register_s = crate::util::secs(t0);
    let t1 = Instant::now();
    in_time(params, "registering the sweeps")?;
    if rows.rows.len() < 50 {
        return Err(DiscoverError::Underdetermined(format!(
            "the cohort's {} sweeps give only {} matched rows; discovery needs at least 50",
            sweeps.len(),
            rows.rows.len()
        )));
    }
    // Noise floor: median over sweeps of the local-quadric estimate on surface points.
    let mut floors: Vec<f64> = sweeps
        .iter()
        .zip(&images)
        .filter_map(|(s, pts)| {
            let surf: Vec<[f64; 3]> = pts
                .iter()
                .zip(&s.measurements.kind)
                .filter(|(_, k)| **k == MeasuredKind::Surface)
                .map(|(p, _)| *p)
                .collect();
            noise::noise_floor(&surf).map(|(s, _)| s)
        })
        .collect();
    floors.sort_by(f64::total_cmp);
    let local_floor = if floors.is_empty() {
        f64::INFINITY
    } else {
        floors[floors.len() / 2]
    };
    // Base model.
    let geom = BoundaryGeometry::new(&model.mesh)?;
    let libr = &params.pipeline.libr;
    let basis = prepared
        .basis
        .clone()
        .ok_or_else(|| DiscoverError::Input("the case has no LIBR basis".into()))?;
    let (a, prior) = basis_design(&rows, &basis, libr.regularization);
    let no_amplitude = AmplitudePrior::none(a.ncols());
    let base_score = cross_validate(
        &rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &no_amplitude,
        },
    )
    .ok_or_else(|| {
        DiscoverError::Underdetermined(
            "no fold could be fitted: too few points per sweep and block".into(),
        )
    })?;
    // The noise floor: the smaller of two estimates that can only overstate it, the local
    // quadrics (curvature the quadric misses) and plain LIBR's in-sample misfit corrected for its
    // degrees of freedom (model error it cannot fit).
    let dof = (rows.rows.len() as f64 - a.ncols() as f64 - 6.0 * sweeps.len() as f64).max(1.0);
    let insample_floor =
        (base_score.full_rss / base_score.full_w.max(1e-300) * rows.rows.len() as f64 / dof).sqrt();
    let noise_floor_mm = local_floor.min(insample_floor);
    // Bootstrap null, posterior-predictive: if plain LIBR were right, the truth would be a draw
    // of its weights from their posterior (the fit plus what the sparse data leave open, at the
    // prior's scale), seen with noise at the floor. Cross-validating such replicates the same
    // way gives the held-out misfit that noise *and* sparse extrapolation explain.
    progress("bootstrap", 0, params.bootstrap);
    let null_prior = &prior * base_score.prior_scale;
    let noise_var = noise_floor_mm * noise_floor_mm;
    let posterior = (&base_score.inverse * noise_var).cholesky();
    let null: Vec<f64> = (0..params.bootstrap)
        .into_par_iter()
        .filter_map(|k| {
            let mut rng = crate::util::SplitMix64::new(
                params.seed ^ (k as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            );
            let mut draw = base_score.clone();
            if let Some(ch) = &posterior {
                let z = nalgebra::DVector::from_fn(draw.coef.len(), |_, _| gaussian(&mut rng));
                draw.coef += ch.l() * z;
            }
            let fit = fitted(&rows, &a, &draw);
            let b: Vec<f64> = fit
                .iter()
                .map(|f| f + noise_floor_mm * gaussian(&mut rng))
                .collect();
            cross_validate_rhs(
                &rows,
                &Design {
                    a: &a,
                    prior: &null_prior,
                    amplitude: &no_amplitude,
                },
                &b,
            )
            .map(|s| s.heldout_mse.sqrt())
        })
        .collect();
    let null_max_mm = null.iter().copied().fold(0.0, f64::max);
    let before_rms = base_score.heldout_mse.sqrt();
    let beyond_noise = before_rms > null_max_mm && before_rms > 1.25 * noise_floor_mm;
    let find_s = crate::util::secs(t1);
    in_time(params, "testing the misfit against noise")?;
    let mut records = Vec::new();
    // Richer loads: does plain LIBR under a weaker prior than registration's λ explain more?
    let at_lambda = cv::cross_validate_at(
        &rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &AmplitudePrior::none(a.ncols()),
        },
        1.0,
    );
    let mut richer_loads = false;
    if let Some(l) = at_lambda.as_ref().filter(|_| base_score.prior_scale < 1.0) {
        let (z, t, gain) = paired(l, &base_score);
        richer_loads = z > params.z_threshold && gain > params.min_gain;
        records.push(CandidateRecord {
            round: 0,
            kind: "refine-loads".into(),
            effect: format!("LIBR's loads at {} × λ (against λ)", base_score.prior_scale),
            heldout_rms_mm: before_rms,
            gain,
            rank_z: z,
            t,
            delta_bic: f64::NAN,
            relinearized: false,
            significant: richer_loads,
        });
    }
    let heldout_at_lambda_mm = at_lambda.map_or(before_rms, |l| l.heldout_mse.sqrt());
    Ok(Found {
        prepared,
        plain,
        rows,
        geom,
        basis,
        a,
        prior,
        base_score,
        noise_floor_mm,
        noise_var,
        null_max_mm,
        beyond_noise,
        heldout_at_lambda_mm,
        richer_loads,
        refine_record: records.pop(),
        register_s,
        find_s,
    })
}

/// What naming leaves: the final model, its linearization, every candidate's record and the
/// named effects.
struct Named {
    cur: Current,
    cur_rows: CohortRows,
    records: Vec<CandidateRecord>,
    named: Vec<NamedEffect>,
}

/// Step 3, forward selection: each round searches every kind (and support × load pairs) on the
/// current model, confirms the most promising on their own linearization, and names the best
/// that passes the rule.
fn name(
    model: &PreopModel,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    found: &Found,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Named, DiscoverError> {
    let libr = &params.pipeline.libr;
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    let (prepared, geom, noise_var) = (&found.prepared, &found.geom, found.noise_var);
    let solver = std::sync::Arc::new(ModelSolver::new(
        &model.mesh,
        &libr.material,
        sites,
        &Physics::none(),
    )?);
    let mut cur = Current {
        physics: Physics::none(),
        basis: found.basis.clone(),
        solver,
        a: found.a.clone(),
        prior: found.prior.clone(),
        amplitude: AmplitudePrior::none(found.a.ncols()),
        score: found.base_score.clone(),
    };
    // The rows the current model is linearized at: its own registrations' correspondences.
    let mut cur_rows = found.rows.clone();
    let mut records: Vec<CandidateRecord> = found.refine_record.iter().cloned().collect();
    let mut named: Vec<NamedEffect> = Vec::new();
    for round in 0..params.max_effects {
        let kinds: Vec<EffectKind> = params
            .kinds
            .iter()
            .copied()
            .filter(|k| !cur.physics.effects.iter().any(|e| e.kind == *k))
            .collect();
        if kinds.is_empty() {
            break;
        }
        let ctx = SearchContext {
            mesh: &model.mesh,
            sites,
            libr,
            rows: &cur_rows,
            geom,
            noise_var,
        };
        // Screen: every kind searched on the current linearization; shape parameters by the
        // full fit (maximum likelihood).
        let mut screened: Vec<(Candidate, Vec<Candidate>, usize)> = Vec::new();
        let mut consider = |top: Candidate, family: Vec<Candidate>| {
            let (z, t, gain) = paired(&cur.score, &top.score);
            let delta_bic = bic_change(&cur.score, &top.score, top.parameters);
            records.push(CandidateRecord {
                round,
                kind: top.kinds(),
                effect: top.describe(),
                heldout_rms_mm: top.score.heldout_mse.sqrt(),
                gain,
                rank_z: z,
                t,
                delta_bic,
                relinearized: false,
                significant: false,
            });
            // Promising: it lowers the held-out misfit or the BIC on the current linearization
            // (which understates a large effect; the confirmation decides).
            if gain > 0.0 || delta_bic < 0.0 {
                let at = records.len() - 1;
                screened.push((top, family, at));
            }
        };
        let mut supports = Vec::new();
        for (i, kind) in kinds.iter().enumerate() {
            progress(&format!("round {round}: searching {kind}"), i, kinds.len());
            in_time(params, &format!("searching {kind} (round {round})"))?;
            let family = search_family(&ctx, &cur, *kind, &params.grid)?;
            let Some(top) = search::best_fit(&family) else {
                continue;
            };
            if kind.is_support() {
                supports.push(top.clone());
            }
            consider(top, family);
        }
        // A load and what carries it are one signature: with neither in the model yet, each
        // support's best is searched again with every load kind carried by it.
        let loads: Vec<EffectKind> = kinds.iter().copied().filter(|k| k.is_load()).collect();
        if !cur.physics.has_support() && !cur.physics.effects.iter().any(|e| e.kind.is_load()) {
            for s in &supports {
                progress(
                    &format!("round {round}: pairs with {}", s.effect.kind),
                    0,
                    1,
                );
                in_time(
                    params,
                    &format!("pairs with {} (round {round})", s.effect.kind),
                )?;
                for (top, family) in pair_candidates(&ctx, &cur, s, &loads, &params.grid)? {
                    consider(top, family);
                }
            }
        }
        // Confirm the most promising on their own linearization: each sweep registered again
        // with the augmented model, its misfit linearized at the new correspondences, and the
        // two models compared unit by unit, each at its own fit (a large hidden effect moves
        // the correspondences plain LIBR converged to; rows linearized there understate it).
        screened.sort_by(|a, b| records[b.2].gain.total_cmp(&records[a.2].gain));
        screened.truncate(params.confirmations.max(1));
        let mut passing: Vec<(Confirmed, Candidate, Vec<Candidate>, f64, f64, f64)> = Vec::new();
        for (top, family, _) in screened {
            progress(&format!("round {round}: confirming {}", top.kinds()), 0, 1);
            in_time(
                params,
                &format!("confirming {} (round {round})", top.kinds()),
            )?;
            let Some(conf) = confirm(&ctx, prepared, sweeps, params, &cur, &top, progress)? else {
                continue;
            };
            let (z, t, gain) = paired(&conf.compared.0, &conf.compared.1);
            let delta_bic = bic_change(&conf.compared.0, &conf.compared.1, top.parameters);
            let significant = z > params.z_threshold && gain > params.min_gain && delta_bic < 0.0;
            let mut effect = conf
                .physics
                .effects
                .iter()
                .rev()
                .find(|e| e.kind == top.effect.kind)
                .cloned()
                .unwrap_or_else(|| top.effect.clone());
            if let Some(e) = conf.refitted.as_ref() {
                effect = e.clone();
            }
            let described = match &top.partner {
                Some(p) => format!("{} + {}", p.describe(), effect.describe()),
                None => effect.describe(),
            };
            records.push(CandidateRecord {
                round,
                kind: top.kinds(),
                effect: described,
                heldout_rms_mm: conf.compared.1.heldout_mse.sqrt(),
                gain,
                rank_z: z,
                t,
                delta_bic,
                relinearized: true,
                significant,
            });
            if significant {
                passing.push((conf, top, family, z, gain, delta_bic));
            }
        }
        let best = passing.into_iter().max_by(|a, b| a.4.total_cmp(&b.4));
        let Some((conf, top, family, z, gain, delta_bic)) = best else {
            break;
        };
        let before = conf.compared.0.heldout_mse.sqrt();
        let uncertainty = shape_uncertainty(&top, &family);
        let effect = conf.refitted.clone().unwrap_or_else(|| top.effect.clone());
        let evidence = serde_json::json!({
            "heldout_rms_before_mm": before,
            "heldout_rms_after_mm": conf.compared.1.heldout_mse.sqrt(),
            "gain": gain,
            "rank_z": z,
            "delta_bic": delta_bic,
            "round": round,
            "candidates_tried": family.len(),
        });
        if let Some(p) = &top.partner {
            // Named together: the support that carries the load, with the same evidence.
            let mut with = evidence.clone();
            with["named_with"] = serde_json::json!(effect.kind.name());
            named.push(NamedEffect {
                effect: p.clone(),
                uncertainty: serde_json::json!({}),
                evidence: with,
            });
        }
        named.push(NamedEffect {
            effect,
            uncertainty,
            evidence,
        });
        cur_rows = conf.rows;
        cur = conf.current;
    }
    Ok(Named {
        cur,
        cur_rows,
        records,
        named,
    })
}

/// Step 4: before and after per block, and the verdict.
fn show(
    model: &PreopModel,
    sweeps: &[Sweep],
    found: Found,
    named: Named,
    name_s: f64,
    t0: Instant,
) -> CohortDiscovery {
    let Found {
        plain,
        rows,
        a: base_a,
        prior: base_prior,
        base_score,
        noise_floor_mm,
        null_max_mm,
        beyond_noise,
        heldout_at_lambda_mm,
        richer_loads,
        register_s,
        find_s,
        ..
    } = found;
    let Named {
        cur,
        cur_rows,
        records,
        named,
    } = named;
    // Regions: per block, before and after.
    // Before and after on the points both the plain and the final linearization matched.
    let (before_s, after_s) = if named.is_empty() {
        (base_score.clone(), cur.score.clone())
    } else {
        let (ib, ia) = common_rows(&rows, &cur_rows);
        let none = AmplitudePrior::none(base_a.ncols());
        let b = cross_validate(
            &subset(&rows, &ib),
            &Design {
                a: &base_a.select_rows(&ib),
                prior: &base_prior,
                amplitude: &none,
            },
        );
        let f = cross_validate(
            &subset(&cur_rows, &ia),
            &Design {
                a: &cur.a.select_rows(&ia),
                prior: &cur.prior,
                amplitude: &cur.amplitude,
            },
        );
        match (b, f) {
            (Some(b), Some(f)) => (b, f),
            _ => (base_score.clone(), cur.score.clone()),
        }
    };
    let regions = region_table(&rows, model, &before_s, &after_s);
    let verdict = if !named.is_empty() {
        Verdict::Effects
    } else if richer_loads {
        Verdict::RefineLoads
    } else if beyond_noise {
        Verdict::Unexplained
    } else {
        Verdict::None
    };
    CohortDiscovery {
        verdict,
        effects: named,
        physics: cur.physics.clone(),
        heldout_before_mm: before_s.heldout_mse.sqrt(),
        insample_before_mm: (base_score.full_rss / base_score.full_w.max(1e-300)).sqrt(),
        prior_scale_before: base_score.prior_scale,
        heldout_after_mm: after_s.heldout_mse.sqrt(),
        noise_floor_mm,
        null_max_mm,
        beyond_noise,
        heldout_at_lambda_mm,
        richer_loads,
        regions,
        candidates: records,
        rows: rows.rows.len(),
        sweeps: sweeps.len(),
        plain,
        timings: StageTimings {
            register_s,
            find_s,
            name_s,
            total_s: crate::util::secs(t0),
        },
    }
}

/// Registers every sweep with `prepared`'s model (wICP, then LIBR with the physics it carries)
/// and linearizes the misfit at the converged correspondences: one row per match along its
/// direction, over the spatial blocks `centers` (k-means of the pooled points when `None`).
/// Returns the registrations, each sweep's points in the image frame, and the rows.
#[allow(clippy::type_complexity)]
fn linearize(
    prepared: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    centers: Option<&[[f64; 3]]>,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<
    (
        Vec<crate::pipeline::Registration>,
        Vec<Vec<[f64; 3]>>,
        CohortRows,
    ),
    DiscoverError,
> {
    let stage = if prepared.physics.is_empty() {
        "registering sweeps".to_string()
    } else {
        format!("registering sweeps with {}", prepared.physics.describe())
    };
    progress(&stage, 0, sweeps.len());
    let done = std::sync::atomic::AtomicUsize::new(0);
    let regs: Vec<crate::pipeline::Registration> =
        sweeps
            .par_iter()
            .map(|s| {
                in_time(params, &format!("registering sweep {}", s.id))?;
                let r = register(prepared, &s.measurements, Method::Libr, &params.pipeline)
                    .map_err(|e| DiscoverError::Scenario {
                        scenario: s.id.clone(),
                        cause: e,
                    });
                let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                progress(&stage, d, sweeps.len());
                r
            })
            .collect::<Result<_, _>>()?;
    let cparams = params.pipeline.libr_correspondence();
    let mut images: Vec<Vec<[f64; 3]>> = Vec::with_capacity(sweeps.len());
    let mut all_matches = Vec::with_capacity(sweeps.len());
    for (s, reg) in sweeps.iter().zip(&regs) {
        let inv = reg.image_to_physical.inverse();
        let pts: Vec<[f64; 3]> = s
            .measurements
            .points
            .iter()
            .map(|&p| inv.apply(p))
            .collect();
        let (m, _) = prepared
            .correspondence
            .match_points(&pts, &s.measurements, Some(&reg.u), &cparams)
            .map_err(|e| DiscoverError::Scenario {
                scenario: s.id.clone(),
                cause: PipelineError::Libr(e),
            })?;
        images.push(pts);
        all_matches.push(m);
    }
    let centers = match centers {
        Some(c) => c.to_vec(),
        None => {
            let pooled: Vec<[f64; 3]> = images.iter().flatten().copied().collect();
            cluster_centers(&pooled, params.folds)
        }
    };
    let mut rows_v = Vec::new();
    for (s, (m, pts)) in all_matches.iter().zip(&images).enumerate() {
        scenario_rows(s, m, pts, |p| nearest(&centers, p), &mut rows_v);
    }
    let rows = CohortRows {
        rows: rows_v,
        scenarios: sweeps.len(),
        clusters: centers.len(),
        centers,
    };
    Ok((regs, images, rows))
}

fn gaussian(rng: &mut crate::util::SplitMix64) -> f64 {
    let (u1, u2) = (rng.next_f64().max(1e-300), rng.next_f64());
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Paired comparison over the units both scored: the Wilcoxon signed-rank test's z for
/// `sse_cur − sse_cand` (normal approximation with tie correction; ranks make it robust to the
/// heavy tails of per-unit misfits, and unlike a sign test it weighs a large improvement above a
/// small worsening), the t statistic of the differences, and the fraction of the current
/// held-out misfit removed.
fn paired(cur: &CvScore, cand: &CvScore) -> (f64, f64, f64) {
    let d: Vec<f64> = cur
        .unit_sse
        .iter()
        .zip(&cand.unit_sse)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| a - b)
        .collect();
    let total: f64 = cur.unit_sse.iter().filter(|x| x.is_finite()).sum();
    if d.len() < 2 || total <= 0.0 {
        return (0.0, 0.0, 0.0);
    }
    let rank_z = signed_rank_z(&d);
    let n = d.len() as f64;
    let mean = d.iter().sum::<f64>() / n;
    let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let t = if var > 0.0 {
        mean / (var / n).sqrt()
    } else if mean > 0.0 {
        f64::INFINITY
    } else {
        0.0
    };
    (rank_z, t, d.iter().sum::<f64>() / total)
}

/// Wilcoxon signed-rank z of differences (zeros dropped, tied magnitudes get their mean rank).
fn signed_rank_z(d: &[f64]) -> f64 {
    let mut nz: Vec<f64> = d.iter().copied().filter(|x| *x != 0.0).collect();
    let n = nz.len();
    if n == 0 {
        return 0.0;
    }
    nz.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
    let (mut w_plus, mut tie) = (0.0, 0.0);
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && nz[j + 1].abs() == nz[i].abs() {
            j += 1;
        }
        let rank = (i + j) as f64 / 2.0 + 1.0;
        let t = (j - i + 1) as f64;
        tie += t * t * t - t;
        for x in &nz[i..=j] {
            if *x > 0.0 {
                w_plus += rank;
            }
        }
        i = j + 1;
    }
    let nf = n as f64;
    let mean = nf * (nf + 1.0) / 4.0;
    let var = nf * (nf + 1.0) * (2.0 * nf + 1.0) / 24.0 - tie / 48.0;
    if var <= 0.0 {
        0.0
    } else {
        (w_plus - mean) / var.sqrt()
    }
}

/// Searches one kind over its parameter grid on top of the current model.
fn search_family(
    ctx: &SearchContext<'_>,
    cur: &Current,
    kind: EffectKind,
    grid: &SearchGrid,
) -> Result<Vec<Candidate>, DiscoverError> {
    let mut out = Vec::new();
    let mut push = |c: Option<Candidate>| {
        if let Some(c) = c {
            out.push(c);
        }
    };
    match kind {
        EffectKind::Gravity | EffectKind::Pressure => {
            let (dir_name, amp, amp_value) = if kind == EffectKind::Gravity {
                ("direction", "magnitude", 0.01)
            } else {
                ("direction", "magnitude_kpa", 1.0)
            };
            let make = |d: [f64; 3]| Effect::new(kind, &[(dir_name, &d), (amp, &[amp_value])]);
            let mut tried = Vec::new();
            // Directions over the sphere, those physics rules out dropped (a prone patient,
            // insufflation behind the organ: see [`prior::direction_cone`]).
            for d in search::sphere_directions(grid.directions)
                .into_iter()
                .filter(|d| prior::direction_plausible(kind, *d))
            {
                let e = make(d)?;
                let c = search::evaluate_load(ctx, cur, &e)?;
                tried.push((
                    d,
                    c.as_ref()
                        .map(|c| c.score.full_rss)
                        .unwrap_or(f64::INFINITY),
                ));
                push(c);
            }
            // Refine the three best grid directions by a pattern search with shrinking turns
            // (a turn is repeated while it improves). Directions are estimated by the full fit's
            // misfit (maximum likelihood, sharper than the held-out score); whether the effect
            // is real is the held-out score's question.
            tried.sort_by(|a, b| a.1.total_cmp(&b.1));
            let starts: Vec<([f64; 3], f64)> = tried.iter().take(3).copied().collect();
            for start in starts {
                let mut best = start;
                for step in [20.0f64, 10.0, 5.0, 2.5, 1.25] {
                    let mut moved = true;
                    let mut guard = 0;
                    while moved && guard < 6 {
                        moved = false;
                        guard += 1;
                        for d in search::neighbours(best.0, step.to_radians())
                            .into_iter()
                            .filter(|d| prior::direction_plausible(kind, *d))
                        {
                            let e = make(d)?;
                            let c = search::evaluate_load(ctx, cur, &e)?;
                            let s = c
                                .as_ref()
                                .map(|c| c.score.full_rss)
                                .unwrap_or(f64::INFINITY);
                            if s < best.1 {
                                best = (d, s);
                                moved = true;
                            }
                            push(c);
                        }
                    }
                }
            }
        }
        EffectKind::Pack => {
            for c in search::boundary_sites(ctx.mesh, ctx.geom, grid.pack_sites) {
                for w in grid.pack_widths {
                    let e = Effect::new(
                        kind,
                        &[
                            ("center", &c),
                            ("width_mm", &[w]),
                            ("force_mn", &[0.0, 0.0, 1.0]),
                        ],
                    )?;
                    push(search::evaluate_load(ctx, cur, &e)?);
                }
            }
        }
        EffectKind::BedSupport | EffectKind::Ligament => {
            let ks: &[f64] = if kind == EffectKind::BedSupport {
                &[0.02, 0.07, 0.25]
            } else {
                &[0.1, 0.3, 1.0]
            };
            for &k in ks {
                let e = Effect::new(kind, &[("stiffness", &[k])])?;
                push(search::evaluate_rebuilt(ctx, cur, &e)?);
            }
        }
        EffectKind::Fixation => {
            for c in search::boundary_sites(ctx.mesh, ctx.geom, grid.fixation_sites) {
                for k in [0.3, 1.5] {
                    let e = Effect::new(
                        kind,
                        &[("center", &c), ("radius_mm", &[25.0]), ("stiffness", &[k])],
                    )?;
                    push(search::evaluate_rebuilt(ctx, cur, &e)?);
                }
            }
        }
        EffectKind::Inclusion => {
            for c in search::interior_sites(ctx.mesh, ctx.geom, 15.0, grid.inclusion_sites) {
                let e = Effect::new(
                    kind,
                    &[
                        ("center", &c),
                        ("radius_mm", &[15.0]),
                        ("stiffness_ratio", &[5.0]),
                    ],
                )?;
                push(search::evaluate_rebuilt(ctx, cur, &e)?);
            }
        }
        EffectKind::Nonlinear => {}
    }
    Ok(out)
}

/// The factorized model of `physics` on the case (for load columns on top of it).
fn solver_for(
    ctx: &SearchContext<'_>,
    physics: &Physics,
) -> Result<std::sync::Arc<ModelSolver>, DiscoverError> {
    Ok(std::sync::Arc::new(ModelSolver::new(
        ctx.mesh,
        &ctx.libr.material,
        ctx.sites,
        physics,
    )?))
}

/// The pairs of a support candidate `support` (from [`search::evaluate_rebuilt`]) and each load
/// kind of `loads` carried by it: the load's family searched on top of the supported model, its
/// best returned as a candidate with the support as its partner, scored against the current
/// model (both columns' parameters counted).
fn pair_candidates(
    ctx: &SearchContext<'_>,
    cur: &Current,
    support: &Candidate,
    loads: &[EffectKind],
    grid: &SearchGrid,
) -> Result<Vec<(Candidate, Vec<Candidate>)>, DiscoverError> {
    let Some(basis) = support.basis.clone() else {
        return Ok(Vec::new());
    };
    let physics = with_effect(&cur.physics, &support.effect);
    let solver = solver_for(ctx, &physics)?;
    let (a, prior) = basis_design(ctx.rows, &basis, ctx.libr.regularization);
    let supported = Current {
        physics,
        basis,
        solver,
        a,
        prior,
        amplitude: support
            .amplitude
            .clone()
            .unwrap_or_else(|| cur.amplitude.clone()),
        score: support.score.clone(),
    };
    let mut out = Vec::new();
    for &kind in loads {
        let family = search_family(ctx, &supported, kind, grid)?;
        let Some(best) = search::best_fit(&family) else {
            continue;
        };
        let top = Candidate {
            partner: Some(support.effect.clone()),
            parameters: best.parameters + support.parameters,
            columns: None,
            basis: None,
            ..best
        };
        out.push((top, family));
    }
    Ok(out)
}

/// The spread of the shape parameters among the family's candidates the data cannot tell apart
/// from the best (paired t below 2 against it), plus the amplitudes' standard deviations.
fn shape_uncertainty(top: &Candidate, family: &[Candidate]) -> serde_json::Value {
    let mut out = serde_json::Map::new();
    for (name, sd) in &top.amplitude_sd {
        out.insert(name.clone(), serde_json::json!(sd));
    }
    let close: Vec<&Candidate> = family
        .iter()
        .filter(|c| paired(&c.score, &top.score).0 < 2.0)
        .collect();
    let p = &top.effect.parameters;
    if p.contains_key("direction") {
        let d = top.effect.direction("direction");
        let spread = close
            .iter()
            .map(|c| search::angle_deg(d, c.effect.direction("direction")))
            .fold(0.0, f64::max);
        out.insert("direction_deg".into(), serde_json::json!(spread));
    }
    if p.contains_key("center") {
        let c0 = top.effect.vector("center");
        let spread = close
            .iter()
            .map(|c| crate::mesh::vec3::dist2(c0, c.effect.vector("center")).sqrt())
            .fold(0.0, f64::max);
        out.insert("center_mm".into(), serde_json::json!(spread));
    }
    if p.contains_key("stiffness") {
        let k: Vec<f64> = close.iter().map(|c| c.effect.scalar("stiffness")).collect();
        let (lo, hi) = k
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
        out.insert("stiffness_range".into(), serde_json::json!([lo, hi]));
    }
    serde_json::Value::Object(out)
}

/// A candidate confirmed on its own linearization.
struct Confirmed {
    /// The augmented model's physics.
    physics: Physics,
    /// The augmented model as the next round's current model.
    current: Current,
    /// The rows it is linearized at.
    rows: CohortRows,
    /// The candidate's effect with its amplitudes fitted on those rows (load effects).
    refitted: Option<Effect>,
    /// The current model and the candidate scored on the points both linearizations matched
    /// (each at its own correspondences): the fair comparison.
    compared: (CvScore, CvScore),
}

/// The rows of `a` and of `b` whose (sweep, point) both have: the same measured points, each at
/// its own model's correspondences (trimming keeps different points for different fits).
fn common_rows(a: &CohortRows, b: &CohortRows) -> (Vec<usize>, Vec<usize>) {
    use std::collections::HashSet;
    let ka: HashSet<(usize, usize)> = a.rows.iter().map(|r| (r.scenario, r.point)).collect();
    let kb: HashSet<(usize, usize)> = b.rows.iter().map(|r| (r.scenario, r.point)).collect();
    let pick = |rows: &CohortRows, other: &HashSet<(usize, usize)>| {
        rows.rows
            .iter()
            .enumerate()
            .filter(|(_, r)| other.contains(&(r.scenario, r.point)))
            .map(|(i, _)| i)
            .collect::<Vec<usize>>()
    };
    (pick(a, &kb), pick(b, &ka))
}

/// A subset of the rows (same blocks).
fn subset(rows: &CohortRows, idx: &[usize]) -> CohortRows {
    CohortRows {
        rows: idx.iter().map(|&i| rows.rows[i]).collect(),
        scenarios: rows.scenarios,
        clusters: rows.clusters,
        centers: rows.centers.clone(),
    }
}

/// The physics of `current` plus `effect`: stiffness effects first, then loads (the order
/// [`search::evaluate_rebuilt`] builds bases in; loads keep theirs, the new one last).
fn with_effect(current: &Physics, effect: &Effect) -> Physics {
    let all: Vec<&Effect> = current
        .effects
        .iter()
        .chain(std::iter::once(effect))
        .collect();
    Physics {
        effects: all
            .iter()
            .filter(|e| !e.kind.is_load())
            .chain(all.iter().filter(|e| e.kind.is_load()))
            .map(|e| (*e).clone())
            .collect(),
    }
}

/// Confirms a candidate ([`confirm_once`]), then estimates its shape parameters again on its own
/// linearization (the kind searched afresh on the rows the augmented registrations matched,
/// which lie closer to the truth than plain LIBR's when the effect is large) and, where they
/// moved, confirms the re-estimate too; the better of the two (by the held-out misfit removed)
/// is returned.
#[allow(clippy::too_many_arguments)]
fn confirm(
    ctx: &SearchContext<'_>,
    prepared: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cur: &Current,
    top: &Candidate,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Option<Confirmed>, DiscoverError> {
    let Some(first) = confirm_once(ctx, prepared, sweeps, params, cur, top, progress)? else {
        return Ok(None);
    };
    if top.partner.is_some() {
        // A pair's load was searched on top of its support: confirmed as found.
        return Ok(Some(first));
    }
    let (a, _) = basis_design(&first.rows, &cur.basis, ctx.libr.regularization);
    let Some(score) = cross_validate(
        &first.rows,
        &Design {
            a: &a,
            prior: &cur.prior,
            amplitude: &cur.amplitude,
        },
    ) else {
        return Ok(Some(first));
    };
    let there = Current {
        physics: cur.physics.clone(),
        basis: cur.basis.clone(),
        solver: cur.solver.clone(),
        a,
        prior: cur.prior.clone(),
        amplitude: cur.amplitude.clone(),
        score,
    };
    let ctx2 = SearchContext {
        rows: &first.rows,
        ..*ctx
    };
    let family = search_family(&ctx2, &there, top.effect.kind, &params.grid)?;
    let Some(top2) = search::best_fit(&family) else {
        return Ok(Some(first));
    };
    if same_shape(&top2.effect, &top.effect) {
        return Ok(Some(first));
    }
    // A rebuilt candidate's basis was built for the plain rows' search; it is the same basis.
    let Some(second) = confirm_once(ctx, prepared, sweeps, params, cur, &top2, progress)? else {
        return Ok(Some(first));
    };
    let gain = |c: &Confirmed| paired(&c.compared.0, &c.compared.1).2;
    Ok(Some(if gain(&second) > gain(&first) {
        second
    } else {
        first
    }))
}

/// Whether two effects of a kind have the same shape parameters (amplitudes aside).
fn same_shape(a: &Effect, b: &Effect) -> bool {
    let amplitude = a.kind.amplitude().map(|(n, _)| n);
    a.kind == b.kind
        && a.parameters
            .iter()
            .filter(|(k, _)| amplitude != Some(k.as_str()))
            .all(|(k, v)| b.parameters.get(k).is_some_and(|w| w == v))
}

/// Registers every sweep again with the current model plus the candidate, linearizes there and
/// cross-validates the augmented model on those rows. `None` when the augmented model cannot
/// be built or a sweep cannot be registered with it (then it is no candidate).
fn confirm_once(
    ctx: &SearchContext<'_>,
    prepared: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cur: &Current,
    top: &Candidate,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Option<Confirmed>, DiscoverError> {
    let physics = match &top.partner {
        Some(p) => with_effect(&with_effect(&cur.physics, p), &top.effect),
        None => with_effect(&cur.physics, &top.effect),
    };
    let basis = match &top.basis {
        Some(b) => b.clone(),
        None => match crate::register::libr::LibrBasis::build_with(
            ctx.mesh, ctx.libr, &physics, ctx.sites,
        ) {
            Ok(b) => b,
            Err(RegisterError::Model(_)) => return Ok(None),
            Err(e) => return Err(e.into()),
        },
    };
    let augmented = Prepared {
        model: prepared.model.clone(),
        correspondence: prepared.correspondence.clone(),
        basis: Some(basis.clone()),
        basis_from_cache: false,
        librplus: None,
        v2s: None,
        adaptive: None,
        physics: physics.clone(),
        error_model: None,
        seconds: 0.0,
    };
    let rows = match linearize(
        &augmented,
        sweeps,
        params,
        Some(&ctx.rows.centers),
        progress,
    ) {
        Ok((_, _, rows)) => rows,
        Err(DiscoverError::Scenario { .. }) => return Ok(None),
        Err(e) => return Err(e),
    };
    let (a, prior) = basis_design(&rows, &basis, ctx.libr.regularization);
    let amplitude = search::basis_amplitude_prior(ctx, &basis, &physics);
    let Some(score) = cross_validate(
        &rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &amplitude,
        },
    ) else {
        return Ok(None);
    };
    // The fair comparison: both models on the points both matched.
    let (ic, ia) = common_rows(ctx.rows, &rows);
    let (rc, ra) = (subset(ctx.rows, &ic), subset(&rows, &ia));
    let (ac, aa) = (cur.a.select_rows(&ic), a.select_rows(&ia));
    let (Some(sc), Some(sa)) = (
        cross_validate(
            &rc,
            &Design {
                a: &ac,
                prior: &cur.prior,
                amplitude: &cur.amplitude,
            },
        ),
        cross_validate(
            &ra,
            &Design {
                a: &aa,
                prior: &prior,
                amplitude: &amplitude,
            },
        ),
    ) else {
        return Ok(None);
    };
    // The new effect's amplitudes on these rows.
    let refitted = if top.effect.kind.is_load() {
        let mut j = basis.libr_columns();
        let mut out = None;
        for e in physics.effects.iter().filter(|e| e.kind.is_load()) {
            let k = e.kind.amplitude().map_or(0, |(_, k)| k);
            if e.kind == top.effect.kind {
                let amp: Vec<f64> = (0..k)
                    .map(|i| score.coef[j + i] * basis.load_scale[j + i])
                    .collect();
                let Some(e) = search::with_amplitudes(e, amp, &physics) else {
                    return Ok(None);
                };
                out = Some(e);
            }
            j += k;
        }
        out
    } else {
        None
    };
    let solver = solver_for(ctx, &physics)?;
    Ok(Some(Confirmed {
        physics: physics.clone(),
        current: Current {
            physics,
            basis,
            solver,
            a,
            prior,
            amplitude,
            score,
        },
        rows,
        refitted,
        compared: (sc, sa),
    }))
}

/// Change of the Bayesian information criterion from `cur` to `cand` (negative favours
/// `cand`), each by its own mean-square misfit, `extra` parameters added.
fn bic_change(cur: &CvScore, cand: &CvScore, extra: usize) -> f64 {
    let n = cand.rows as f64;
    let ms = |s: &CvScore| s.full_rss / s.full_w.max(1e-300);
    n * (ms(cand) / ms(cur)).ln() + extra as f64 * n.ln()
}

/// Per block: held-out RMS before and after, and how systematic the misfit is across sweeps.
fn region_table(
    rows: &CohortRows,
    model: &PreopModel,
    before: &CvScore,
    after: &CvScore,
) -> Vec<RegionMisfit> {
    let nc = rows.clusters;
    (0..nc)
        .map(|c| {
            let rms = |s: &CvScore| {
                let (mut e, mut w) = (0.0, 0.0);
                for sc in 0..rows.scenarios {
                    let u = sc * nc + c;
                    if s.unit_sse[u].is_finite() {
                        e += s.unit_sse[u];
                        w += s.unit_w[u];
                    }
                }
                if w > 0.0 { (e / w).sqrt() } else { f64::NAN }
            };
            let means: Vec<f64> = (0..rows.scenarios)
                .map(|sc| before.unit_mean[sc * nc + c])
                .filter(|x| x.is_finite())
                .collect();
            let n = means.len() as f64;
            let mean = means.iter().sum::<f64>() / n.max(1.0);
            let sd =
                (means.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
            let t = if sd > 0.0 && n > 1.0 {
                mean / (sd / n.sqrt())
            } else {
                0.0
            };
            let center = rows.centers[c];
            let node = (0..model.mesh.num_nodes())
                .filter(|&v| model.anterior[v] || model.posterior[v])
                .min_by(|&a, &b| {
                    crate::mesh::vec3::dist2(model.mesh.nodes()[a], center)
                        .total_cmp(&crate::mesh::vec3::dist2(model.mesh.nodes()[b], center))
                });
            let region = match node {
                Some(v) if model.falciform[v] => "anterior (falciform)",
                Some(v) if model.inferior_ridge[v] => "anterior (inferior ridge)",
                Some(v) if model.anterior[v] => "anterior",
                Some(v) if model.posterior[v] => "posterior",
                _ => "interior",
            };
            RegionMisfit {
                center,
                region: region.into(),
                before_mm: rms(before),
                after_mm: rms(after),
                mean_signed_mm: mean,
                t_across_sweeps: t,
                sweeps: means.len(),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests;
