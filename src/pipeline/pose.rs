//! A pose that cannot silently go wrong: the rigid stage from several starts across the
//! navigation start's uncertainty, each distinct pose scored after the deformable fit.
//!
//! The navigation system's start is a fit to a few noisy landmarks, off by tens of millimetres
//! and degrees at worst. wICP from it alone can settle in a wrong basin (a retracted left lobe
//! matched to the right lobe's surface) with a residual that looks no worse than a deformation's:
//! the deformable fit then bends the wrong pose into the points. So the rigid stage also starts
//! from the navigation start turned by [`PoseParams::start_angles_deg`] about each axis through
//! the measured points' centroid (in parallel), each on a subsample of the points
//! ([`PoseParams::search_points`]). The distinct poses they reach (closer than
//! [`PoseParams::same_pose_mm`] RMS over the organ's nodes is one pose) are refined on every
//! point best subsample score first, only until [`PoseParams::max_candidates`] distinct poses are
//! in hand (the navigation start's own result always among them). Each is carried through the
//! deformable fit and scored again on what it leaves: the
//! robust mean squared distance of every measured point to the deformed model (each capped at
//! [`PoseParams::cap_mm`], unmatched points counting the cap) plus the fit's regularisation term,
//! in mm² both. The lowest wins. When the runner-up scores within [`PoseParams::ambiguous_ratio`]
//! of it and the two poses differ by more than [`PoseParams::ambiguous_mm`], the data do not
//! decide the pose and the registration says so ([`PoseInfo::ambiguous`]).

use crate::mesh::rigid::Rigid;
use crate::register::correspondence::{Correspondence, CorrespondenceParams};
use crate::register::prior::RigidPrior;
use crate::register::wicp::{WicpParams, WicpResult, wicp};
use crate::register::{Checked, PreopModel, RegisterError};
use rayon::prelude::*;

/// Parameters of the multi-start rigid stage and the pose choice.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PoseParams {
    /// Angles (degrees) the extra starts turn the navigation start by, each about the three
    /// axes both ways (6 starts per angle); empty: the navigation start alone. Default 15, 30
    /// and 45 (18 extra starts).
    pub start_angles_deg: Vec<f64>,
    /// Poses closer than this (RMS distance over the organ's nodes, mm) are one. Default 10.
    pub same_pose_mm: f64,
    /// Most distinct poses carried through the deformable fit. Default 3.
    pub max_candidates: usize,
    /// Each measured point's squared distance counts at most `cap_mm²` in the score. Default 10.
    pub cap_mm: f64,
    /// The runner-up within this ratio of the best score (and `ambiguous_mm` away) makes the pose
    /// ambiguous. Default 1.5.
    pub ambiguous_ratio: f64,
    /// See `ambiguous_ratio` (mm, RMS over the organ's nodes). Default 10.
    pub ambiguous_mm: f64,
    /// The extra starts' wICP runs on at most this many of the points (every k-th, so all
    /// kinds keep their share), with a looser tolerance; the distinct poses they reach are
    /// refined on every point from there, best subsample score first, until
    /// `max_candidates - 1` distinct poses are in hand. Default 200.
    pub search_points: usize,
    /// The search runs only when the navigation start's own deformable fit scores above this
    /// ([`score`] plus the fit's regularisation term, mm²); a start whose fit explains the
    /// points that well is kept without trying the others. 0: always search. Default 4 (2 mm
    /// RMS): on the paper preset (seed 2, 500 registrations) LIBR's mean TRE with the gate at 4
    /// is that of always searching (6.25 mm, 14 wrong poses against 15; single start 6.52, 18)
    /// at the single start's median time; at 8, 6.29; at 16, 6.36.
    pub search_above_mm2: f64,
    /// The fit's regularisation term counts this many times in a pose's score (the fit itself
    /// keeps LIBR's λ): a wrong pose bent into the points needs more deformation than the right
    /// one. Default 1.
    pub energy_weight: f64,
}

impl Default for PoseParams {
    fn default() -> Self {
        Self {
            start_angles_deg: vec![15.0, 30.0, 45.0],
            same_pose_mm: 10.0,
            max_candidates: 3,
            cap_mm: 10.0,
            ambiguous_ratio: 1.5,
            ambiguous_mm: 10.0,
            search_points: 200,
            search_above_mm2: 4.0,
            energy_weight: 1.0,
        }
    }
}

impl PoseParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        let bad = |f: &str, v: f64| {
            Err(RegisterError::Parameter(format!(
                "pose {f} must be finite and > 0, got {v}"
            )))
        };
        for &a in &self.start_angles_deg {
            if !(a.is_finite() && a > 0.0 && a < 180.0) {
                return Err(RegisterError::Parameter(format!(
                    "pose start_angles_deg must be in (0, 180), got {a}"
                )));
            }
        }
        for (f, v) in [
            ("same_pose_mm", self.same_pose_mm),
            ("cap_mm", self.cap_mm),
            ("ambiguous_mm", self.ambiguous_mm),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(f, v);
            }
        }
        if !(self.ambiguous_ratio.is_finite() && self.ambiguous_ratio >= 1.0) {
            return Err(RegisterError::Parameter(format!(
                "pose ambiguous_ratio must be finite and >= 1, got {}",
                self.ambiguous_ratio
            )));
        }
        if !(self.search_above_mm2.is_finite() && self.search_above_mm2 >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "pose search_above_mm2 must be finite and >= 0, got {}",
                self.search_above_mm2
            )));
        }
        if !(self.energy_weight.is_finite() && self.energy_weight >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "pose energy_weight must be finite and >= 0, got {}",
                self.energy_weight
            )));
        }
        if self.search_points < 3 {
            return Err(RegisterError::Parameter(format!(
                "pose search_points must be at least 3, got {}",
                self.search_points
            )));
        }
        if self.max_candidates == 0 {
            return Err(RegisterError::Parameter(
                "pose max_candidates must be at least 1".into(),
            ));
        }
        Ok(())
    }
}

/// How the pose was chosen.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PoseInfo {
    /// Rigid starts run (the navigation start and the turned ones).
    pub starts: usize,
    /// Distinct poses the coarse search reached on its subsample (the navigation start's result
    /// counted); only the best of them were refined on every point.
    pub distinct: usize,
    /// Scores (mm²) of the candidates carried through the fit, in the order tried (the
    /// navigation start's first).
    pub scores: Vec<f64>,
    /// Of each score, the fit's regularisation term (mm²; the rest is the robust misfit).
    pub prior_mm2: Vec<f64>,
    /// Which candidate was chosen (index into `scores`).
    pub chosen: usize,
    /// RMS distance over the organ's nodes between the chosen pose and the navigation start's
    /// own result (mm; 0 when it won).
    pub moved_from_single_start_mm: f64,
    /// The runner-up scored within [`PoseParams::ambiguous_ratio`] of the chosen pose and lies
    /// more than [`PoseParams::ambiguous_mm`] from it: the data do not decide the pose.
    pub ambiguous: bool,
    /// The distance (mm, RMS over the nodes) to the runner-up, when there was one.
    pub runner_up_mm: Option<f64>,
    /// Wall-clock time of the whole rigid stage, every start included (s).
    pub rigid_seconds: f64,
}

/// The robust score of a placement (mm²): the mean over measured points of the squared distance
/// to its match on the model displaced by `u` (undeformed when None) under `t`, each capped at
/// `cap²`; points left unmatched or trimmed count `cap²`.
pub fn score(
    corr: &Correspondence,
    meas: &Checked,
    cparams: &CorrespondenceParams,
    u: Option<&[f64]>,
    t: &Rigid,
    cap: f64,
) -> Result<f64, RegisterError> {
    let inv = t.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
    let (matches, _) = corr.match_points(&pts, meas, u, cparams)?;
    let zero;
    let u = match u {
        Some(u) => u,
        None => {
            zero = vec![0.0; 3 * corr.num_nodes()];
            &zero
        }
    };
    let c2 = cap * cap;
    let mut sum = 0.0;
    // Each point counts for the measured points it stands for (a reduced cloud's centroid).
    let mut counted = 0.0;
    for m in &matches {
        let w = meas.weight(m.point);
        counted += w;
        if m.weight > 0.0 {
            let q = m.model_point(u);
            let p = pts[m.point];
            let d2 = (0..3).map(|a| (q[a] - p[a]).powi(2)).sum::<f64>();
            sum += w * d2.min(c2);
        } else {
            sum += w * c2;
        }
    }
    let n = meas.represented().max(1.0);
    sum += (n - counted).max(0.0) * c2;
    Ok(sum / n)
}

/// The starts: the navigation start, then it turned by each angle about the x, y and z axes
/// (both ways) through the measured points' centroid (physical frame).
pub fn starts(meas: &Checked, params: &PoseParams) -> Vec<Rigid> {
    let start = meas.initial_alignment.unwrap_or_default();
    let n = meas.points.len().max(1) as f64;
    let mut c = [0.0; 3];
    for p in &meas.points {
        for a in 0..3 {
            c[a] += p[a] / n;
        }
    }
    let mut out = vec![start];
    for &deg in &params.start_angles_deg {
        for axis in 0..3 {
            for sign in [1.0, -1.0] {
                let mut e = [0.0; 3];
                e[axis] = 1.0;
                let rot = Rigid::from_axis_angle(e, sign * deg.to_radians(), [0.0; 3]);
                let rc = rot.apply_vector(c);
                let turn = Rigid {
                    rotation: rot.rotation,
                    translation: [0, 1, 2].map(|k| c[k] - rc[k]),
                };
                out.push(start.then(&turn));
            }
        }
    }
    out
}

/// RMS distance over the model's nodes between two poses (mm).
pub fn pose_gap(model: &PreopModel, a: &Rigid, b: &Rigid) -> f64 {
    RigidPrior::new(model.mesh.nodes(), *a, 1.0, 1.0).rms_mm(b)
}

/// Whether the pose search can run after the navigation start's wICP `first`: extra starts are
/// configured, the start is not trusted, and `first` is neither degenerate nor ill-posed.
pub fn searchable(first: &WicpResult, wicp_params: &WicpParams, params: &PoseParams) -> bool {
    !(params.start_angles_deg.is_empty()
        || wicp_params.trusted_alignment_mm.is_some()
        || first.degenerate.is_some()
        || first.ill_posed)
}

/// The rigid stage from every start ([`starts`]; in parallel), its results reduced to distinct
/// poses ranked by rigid [`score`], at most `max_candidates`, the navigation start's own result
/// first. With no extra start (or a
/// trusted start, whose prior holds every start near it anyway) this is wICP from the
/// navigation start alone. A start whose wICP fails or is degenerate is left out; the navigation
/// start's error is returned as it is.
pub fn rigid_candidates(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Checked,
    wicp_params: &WicpParams,
    params: &PoseParams,
) -> Result<Candidates, RegisterError> {
    params.validate()?;
    let first = wicp(model, corr, meas, wicp_params)?;
    // `candidates_from` checks the parameters again: cheap, and it is public on its own.
    candidates_from(first, model, corr, meas, wicp_params, params)
}

/// [`rigid_candidates`] from the navigation start's wICP result `first`, already computed (the
/// gated search has it from the fit it judged).
pub fn candidates_from(
    first: WicpResult,
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Checked,
    wicp_params: &WicpParams,
    params: &PoseParams,
) -> Result<Candidates, RegisterError> {
    params.validate()?;
    if !searchable(&first, wicp_params, params) {
        return Ok(Candidates {
            poses: vec![first],
            starts: 1,
            distinct: 1,
        });
    }
    let extra = starts(meas, params).split_off(1);
    let first_pose = first.image_to_physical;
    let reached = search(model, corr, meas, &first_pose, &extra, wicp_params, params);
    let found = 1 + reached.len();
    let mut out = vec![first];
    out.extend(refine_best(
        model,
        corr,
        meas,
        &first_pose,
        reached,
        wicp_params,
        params,
    ));
    out.truncate(params.max_candidates);
    Ok(Candidates {
        poses: out,
        starts: 1 + extra.len(),
        distinct: found,
    })
}

/// Every `len / n`-th measured point (rounded up), at least one step: the search's subsample.
pub(super) fn subsample(meas: &Checked, n: usize) -> Checked {
    let step = meas.points.len().div_ceil(n).max(1);
    let keep: Vec<usize> = (0..meas.points.len()).step_by(step).collect();
    meas.subset(&keep)
}

/// The coarse search's poses (`reached`, best first) refined on every point, a batch at a time
/// (in parallel), until `max_candidates - 1` distinct from `first` and from each other are in
/// hand: a refinement that lands on a pose already held is dropped and the next one tried.
/// Those, by their rigid [`score`] on every point.
fn refine_best(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Checked,
    first: &Rigid,
    reached: Vec<Rigid>,
    wicp_params: &WicpParams,
    params: &PoseParams,
) -> Vec<WicpResult> {
    let cap = params.cap_mm;
    let cp = &wicp_params.correspondence;
    let wanted = params.max_candidates.saturating_sub(1);
    let mut refined: Vec<(f64, WicpResult)> = Vec::new();
    let mut next = reached.into_iter();
    // Past the rigid stage's deadline no further batch starts (the candidates so far stand).
    let late = || {
        wicp_params
            .deadline
            .is_some_and(|d| std::time::Instant::now() >= d)
    };
    while refined.len() < wanted && !late() {
        let batch: Vec<Rigid> = next.by_ref().take(wanted - refined.len()).collect();
        if batch.is_empty() {
            break;
        }
        let done: Vec<(f64, WicpResult)> = batch
            .par_iter()
            .filter_map(|s| {
                let m = meas.with_alignment(Some(*s)).ok()?;
                let r = wicp(model, corr, &m, wicp_params)
                    .ok()
                    .filter(|r| r.degenerate.is_none())?;
                let sc = score(corr, meas, cp, None, &r.image_to_physical, cap).ok()?;
                Some((sc, r))
            })
            .collect();
        for (sc, r) in done {
            let t = r.image_to_physical;
            let held = refined.iter().map(|(_, o)| &o.image_to_physical);
            if !near_any(model, first, held, &t, params.same_pose_mm) {
                refined.push((sc, r));
            }
        }
    }
    refined.sort_by(|a, b| a.0.total_cmp(&b.0));
    refined.into_iter().map(|(_, r)| r).collect()
}

/// The coarse search: every extra start's wICP on a subsample of the points
/// ([`PoseParams::search_points`]) with a looser tolerance, in parallel; the poses reached,
/// best subsample [`score`] first, each at least `same_pose_mm` from `first` and from every
/// better one.
fn search(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Checked,
    first: &Rigid,
    extra: &[Rigid],
    wicp_params: &WicpParams,
    params: &PoseParams,
) -> Vec<Rigid> {
    let sub = subsample(meas, params.search_points);
    let coarse = coarse_params(wicp_params);
    let cap = params.cap_mm;
    let cp = &wicp_params.correspondence;
    let mut reached: Vec<(f64, Rigid)> = extra
        .par_iter()
        .filter_map(|s| {
            let m = sub.with_alignment(Some(*s)).ok()?;
            let r = wicp(model, corr, &m, &coarse)
                .ok()
                .filter(|r| r.degenerate.is_none())?;
            let t = r.image_to_physical;
            score(corr, &sub, cp, None, &t, cap).ok().map(|s| (s, t))
        })
        .collect();
    // Stable: equal scores keep the starts' order.
    reached.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut distinct: Vec<Rigid> = Vec::new();
    for (_, t) in reached {
        if !near_any(model, first, distinct.iter(), &t, params.same_pose_mm) {
            distinct.push(t);
        }
    }
    distinct
}

/// The search's wICP settings where a pose is only approximate (the extra starts on the
/// subsample; the side test's boundary hypothesis): tolerance at least 0.01 mm, at most 60
/// iterations.
pub(super) fn coarse_params(w: &WicpParams) -> WicpParams {
    WicpParams {
        tolerance_mm: w.tolerance_mm.max(1e-2),
        max_iterations: w.max_iterations.min(60),
        ..*w
    }
}

/// Whether `t` lies within `d` (RMS over the organ's nodes) of `first` or of any of `others`.
fn near_any<'a>(
    model: &PreopModel,
    first: &'a Rigid,
    others: impl Iterator<Item = &'a Rigid>,
    t: &Rigid,
    d: f64,
) -> bool {
    std::iter::once(first)
        .chain(others)
        .any(|o| pose_gap(model, o, t) < d)
}

/// What [`rigid_candidates`] found.
pub struct Candidates {
    /// Distinct rigid results, at most `max_candidates`, the navigation start's first, then by
    /// rigid score.
    pub poses: Vec<WicpResult>,
    /// Starts run.
    pub starts: usize,
    /// Distinct poses the coarse search reached on its subsample, the navigation start's
    /// result counted (only the best of them are refined on every point).
    pub distinct: usize,
}

/// Chooses among scored candidates (score per candidate, in order; the first the navigation
/// start's): the lowest score, and whether the runner-up makes it ambiguous.
pub fn choose(
    model: &PreopModel,
    poses: &[Rigid],
    scores: &[f64],
    prior_mm2: &[f64],
    starts: usize,
    distinct: usize,
    params: &PoseParams,
) -> PoseInfo {
    let mut order: Vec<usize> = (0..scores.len()).collect();
    order.sort_by(|&a, &b| scores[a].total_cmp(&scores[b]).then(a.cmp(&b)));
    let chosen = order[0];
    let runner = order.get(1).copied();
    let runner_up_mm = runner.map(|r| pose_gap(model, &poses[chosen], &poses[r]));
    let ambiguous = runner.is_some_and(|r| {
        scores[r] <= params.ambiguous_ratio * scores[chosen]
            && runner_up_mm.is_some_and(|d| d > params.ambiguous_mm)
    });
    PoseInfo {
        starts,
        distinct,
        scores: scores.to_vec(),
        prior_mm2: prior_mm2.to_vec(),
        chosen,
        moved_from_single_start_mm: pose_gap(model, &poses[0], &poses[chosen]),
        ambiguous,
        runner_up_mm,
        rigid_seconds: 0.0,
    }
}
