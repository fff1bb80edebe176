//! [`Method::Auto`]: the model chosen per registration from the measurements alone.
//!
//! No single model is right for every organ state: adaptive LIBR resolves a local dent that
//! LIBR's broad loads cannot, and overfits where the data are thin; a held organ is described
//! by a held fit and made worse than doing nothing by a free one; on noisy data the rigid answer
//! can beat every deformable one. So auto runs the candidates — doing nothing (the navigation
//! start, undeformed), the rigid answer, LIBR, adaptive LIBR (when the case has its basis), and
//! LIBR and adaptive LIBR held ([`super::hold`]: the start trusted, the unseen surface held) —
//! and scores each by **how well it predicts measured points it did not
//! see** ([`crate::register::libr::held_out`]): the measured points are split into
//! [`AutoParams::folds`] spatial patches, each candidate's last fit is solved again without
//! each patch (its matches fixed: a downdate of one linear least-squares system, no new
//! matching) and the patch predicted; a point's squared error counts at most
//! [`AutoParams::cap_mm`]². The rigid answer's score comes from the same system with six
//! unknowns, doing nothing's from its residual.
//!
//! **The choice** is the one-standard-error rule of cross-validation: the simplest candidate
//! (in the order doing nothing, rigid, held LIBR, held adaptive, LIBR, adaptive) whose score is
//! within [`AutoParams::within_se`] standard errors of the best score (the standard error of
//! the paired difference over the folds) and within [`AutoParams::within_ratio`] of it. A more flexible model must predict unseen points
//! clearly better to be chosen; where it does not, the simpler answer changes the organ less.
//! The held fits rank before the free ones when the start is trusted ([`PipelineParams::held`]
//! or a [`crate::register::wicp::WicpParams::trusted_alignment_mm`]); without a trusted start
//! the hold is a hypothesis ([`AutoParams::hypothesise_hold`]) and ranks after them: it is
//! chosen only when it predicts clearly better, and one within reach whose answer lies apart
//! makes the choice ambiguous, a flag rather than a guess.
//! **When the data cannot decide** — a candidate within the rule's reach of the chosen one
//! whose answer lies more than [`AutoParams::ambiguous_mm`] from it (RMS over the organ's
//! nodes) — the answer says so ([`AutoInfo::ambiguous`]).

use super::run::{Shared, register_scored};
use super::{Method, PipelineError, PipelineParams, Prepared, Registration, rigid_params};
use crate::mesh::rigid::Rigid;
use crate::register::libr::{FitModel, Folds, HeldOut, held_out};
use crate::register::wicp::{WicpResult, wicp};
use crate::register::{Checked, RegisterError};
use crate::util::secs;
use rayon::prelude::*;
use std::time::Instant;

/// How [`Method::Auto`] scores and chooses.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AutoParams {
    /// Spatial folds of the measured points. Default 5.
    pub folds: usize,
    /// A point's squared held-out error counts at most `cap_mm²` (mm). Default 10.
    pub cap_mm: f64,
    /// The simplest candidate within this many standard errors of the best score is chosen.
    /// Default 1.
    pub within_se: f64,
    /// ... and at most this many times the best score: with five folds one odd patch (a few
    /// ultrasound contours) can make the standard error as large as the scores themselves.
    /// Default 1.25.
    pub within_ratio: f64,
    /// Candidates within reach of the chosen one whose answers differ from it by more than this
    /// (RMS over the organ's nodes, mm) make the choice ambiguous. Default 5.
    pub ambiguous_mm: f64,
    /// Without a trusted start, the held variants are still tried — the hold as a hypothesis,
    /// the start trusted to 5 mm as with `held` — but ranked after the free fits: a hold the
    /// request did not declare is chosen only when it predicts the unseen points clearly
    /// better, and one within reach whose answer lies apart makes the choice ambiguous.
    /// Default true.
    pub hypothesise_hold: bool,
}

impl Default for AutoParams {
    fn default() -> Self {
        Self {
            folds: 5,
            cap_mm: 10.0,
            within_se: 1.0,
            within_ratio: 1.25,
            ambiguous_mm: 5.0,
            hypothesise_hold: true,
        }
    }
}

impl AutoParams {
    /// Checks the parameters; the message names the field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        if !(2..=20).contains(&self.folds) {
            return Err(RegisterError::Parameter(format!(
                "auto folds must be in 2..=20, got {}",
                self.folds
            )));
        }
        for (f, v) in [("cap_mm", self.cap_mm), ("ambiguous_mm", self.ambiguous_mm)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(RegisterError::Parameter(format!(
                    "auto {f} must be finite and > 0, got {v}"
                )));
            }
        }
        if !(self.within_ratio.is_finite() && self.within_ratio >= 1.0) {
            return Err(RegisterError::Parameter(format!(
                "auto within_ratio must be finite and >= 1, got {}",
                self.within_ratio
            )));
        }
        if !(self.within_se.is_finite() && self.within_se >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "auto within_se must be finite and >= 0, got {}",
                self.within_se
            )));
        }
        Ok(())
    }
}

/// A candidate of [`Method::Auto`], simplest first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Candidate {
    /// Doing nothing: the navigation start, undeformed.
    Initial,
    /// The rigid answer (LIBR's rigid stage, its pose search included).
    Rigid,
    /// LIBR with the organ held ([`super::hold`]).
    LibrHeld,
    /// Adaptive LIBR with the organ held.
    AdaptiveHeld,
    /// LIBR.
    Libr,
    /// Adaptive LIBR.
    Adaptive,
}

impl Candidate {
    /// Name as in reports.
    pub fn name(self) -> &'static str {
        match self {
            Candidate::Initial => "initial",
            Candidate::Rigid => "rigid",
            Candidate::LibrHeld => "libr-held",
            Candidate::AdaptiveHeld => "adaptive-held",
            Candidate::Libr => "libr",
            Candidate::Adaptive => "adaptive",
        }
    }

    /// The method that computes it.
    pub fn method(self) -> Method {
        match self {
            Candidate::Initial => Method::Initial,
            Candidate::Rigid => Method::Rigid,
            Candidate::LibrHeld | Candidate::Libr => Method::Libr,
            Candidate::AdaptiveHeld | Candidate::Adaptive => Method::Adaptive,
        }
    }

    /// Whether it holds the organ.
    pub fn held(self) -> bool {
        matches!(self, Candidate::LibrHeld | Candidate::AdaptiveHeld)
    }
}

impl std::fmt::Display for Candidate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One candidate's score.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CandidateScore {
    /// The candidate.
    pub candidate: Candidate,
    /// Mean capped squared held-out error (mm²; None when the candidate failed or could not be
    /// scored).
    pub held_out_mm2: Option<f64>,
    /// The same per fold (mm²).
    pub folds_mm2: Vec<f64>,
    /// The fit's own mean capped squared error on the same points (mm²).
    pub in_sample_mm2: Option<f64>,
    /// Its error estimate's predicted mean TRE (mm), when the case's error model has one.
    pub predicted_tre_mm: Option<f64>,
    /// Why it has no score (it failed, or its held-out check could not be solved).
    pub failed: Option<String>,
    /// How far its answer lies from the chosen one's (RMS over the organ's nodes, mm; None
    /// when it failed).
    pub apart_mm: Option<f64>,
    /// Its registration's time (s).
    pub seconds: f64,
}

/// How [`Method::Auto`] chose.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct AutoInfo {
    /// The candidate answered.
    pub chosen: Candidate,
    /// The candidate with the best held-out score (the chosen one, or a more flexible one that
    /// did not predict clearly better).
    pub best_scoring: Candidate,
    /// The best-scoring candidate other than the chosen one.
    pub runner_up: Option<Candidate>,
    /// The runner-up's score minus the chosen one's (mm²; negative when the runner-up scored
    /// better but not clearly).
    pub margin_mm2: Option<f64>,
    /// The margin in standard errors of the paired fold differences (None when they do not
    /// vary).
    pub margin_se: Option<f64>,
    /// RMS distance over the organ's nodes between the chosen answer and the runner-up's (mm).
    pub runner_up_mm: Option<f64>,
    /// Why the data do not decide, when they do not: a candidate within the rule's reach whose
    /// answer lies more than [`AutoParams::ambiguous_mm`] from the chosen one.
    pub ambiguous: Option<String>,
    /// The held variants were tried without a trusted start, ranked after the free fits
    /// ([`AutoParams::hypothesise_hold`]).
    pub hold_hypothesis: bool,
    /// Every candidate tried, simplest first.
    pub candidates: Vec<CandidateScore>,
    /// Every candidate's answer that registered (image → physical transform, node
    /// displacements), for scoring each against a truth in evaluation; not serialised.
    #[serde(skip)]
    pub answers: Vec<(Candidate, Rigid, Vec<f64>)>,
}

/// A candidate's registration and score.
struct Tried {
    candidate: Candidate,
    reg: Result<Registration, PipelineError>,
    score: Result<HeldOut, String>,
}

/// [`Method::Auto`] (module doc).
pub(super) fn register_auto(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
    side_start: Option<&WicpResult>,
) -> Result<Registration, PipelineError> {
    let t0 = Instant::now();
    params.auto.validate().map_err(PipelineError::Libr)?;
    let folds = Folds::spatial(&meas.points, params.auto.folds, params.auto.cap_mm)
        .weighted((0..meas.points.len()).map(|i| meas.weight(i)).collect());
    let free = PipelineParams {
        held: false,
        ..params.clone()
    };
    let initial = initial_candidate(case, meas, &free, &folds);
    let trusted = params.held || params.wicp.trusted_alignment_mm.is_some();
    let hypothesis = !trusted && params.auto.hypothesise_hold;
    let deformable = deformable_candidates(case, trusted || hypothesis);
    let held = PipelineParams {
        held: true,
        ..params.clone()
    };
    // The rigid stage from the navigation start, once for the free fits and once for the held.
    // The side test's start is the free fits' own unless the request holds the organ.
    let side_start = side_start.filter(|_| !params.held);
    let (free_start, held_start) = rayon::join(
        || {
            side_start
                .cloned()
                .or_else(|| start_pose(case, meas, &free))
        },
        || {
            (trusted || hypothesis)
                .then(|| start_pose(case, meas, &held))
                .flatten()
        },
    );
    let mut tried: Vec<Tried> = deformable
        .par_iter()
        .map(|&c| {
            let (p, start) = if c.held() {
                (&held, held_start.as_ref())
            } else {
                (&free, free_start.as_ref())
            };
            let shared = Shared {
                folds: Some(&folds),
                start,
                first: None,
            };
            let reg = register_scored(case, meas, c.method(), p, shared);
            let score = match &reg {
                Ok(r) => r
                    .libr
                    .as_ref()
                    .and_then(|i| i.held_out.clone())
                    .unwrap_or_else(|| Err("no held-out check was made".into())),
                Err(e) => Err(e.to_string()),
            };
            Tried {
                candidate: c,
                reg,
                score,
            }
        })
        .collect();
    tried.push(initial);
    tried.push(rigid_candidate(case, meas, &free, &folds, &tried));
    // Simplest first; a hypothesised hold after the free fits.
    tried.sort_by_key(|t| (hypothesis && t.candidate.held(), t.candidate));
    let mut answer = choose(case, tried, &params.auto, t0)?;
    if let Some(a) = answer.auto.as_mut() {
        a.hold_hypothesis = hypothesis;
    }
    Ok(answer)
}

/// The deformable candidates the case can run (the held ones with `held`), the heaviest first,
/// so that the two halves rayon splits them into take about as long.
fn deformable_candidates(case: &Prepared, held: bool) -> Vec<Candidate> {
    let adaptive = case.adaptive.is_some();
    let mut out = Vec::new();
    if adaptive && held {
        out.push(Candidate::AdaptiveHeld);
    }
    out.push(Candidate::Libr);
    if adaptive {
        out.push(Candidate::Adaptive);
    }
    if held {
        out.push(Candidate::LibrHeld);
    }
    out
}

/// The rigid stage from the navigation start with `params`' rigid settings (None when it fails:
/// each candidate then runs, and reports, its own).
fn start_pose(case: &Prepared, meas: &Checked, params: &PipelineParams) -> Option<WicpResult> {
    wicp(
        &case.model,
        &case.correspondence,
        meas,
        &rigid_params(case, params),
    )
    .ok()
}

/// Doing nothing, scored by its residual.
fn initial_candidate(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
    folds: &Folds,
) -> Tried {
    let reg = register_scored(case, meas, Method::Initial, params, Shared::default());
    let score = match &reg {
        Ok(r) => pose_score(
            case,
            meas,
            params,
            &r.image_to_physical,
            FitModel::Fixed,
            folds,
        ),
        Err(e) => Err(e.to_string()),
    };
    Tried {
        candidate: Candidate::Initial,
        reg,
        score,
    }
}

/// The rigid answer: LIBR's rigid stage when LIBR ran (its pose search shared), else a rigid
/// registration of its own; scored with six unknowns.
fn rigid_candidate(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
    folds: &Folds,
    tried: &[Tried],
) -> Tried {
    let libr = tried
        .iter()
        .find(|t| t.candidate == Candidate::Libr)
        .and_then(|t| t.reg.as_ref().ok());
    let reg = match libr {
        Some(l) => {
            let n = case.model.mesh.num_nodes();
            let r = Registration {
                method: Method::Rigid,
                image_to_physical: l.rigid.image_to_physical,
                u: vec![0.0; 3 * n],
                rigid: l.rigid.clone(),
                pose: l.pose.clone(),
                libr: None,
                correction: None,
                v2s: None,
                nonlinear: None,
                error: None,
                auto: None,
                search_skipped_mm2: l.search_skipped_mm2,
                search_follows: false,
                refinement_follows: false,
                surface: None,
                points: None,
                seconds: l.rigid.seconds,
            };
            Ok(r.estimated(case, meas))
        }
        None => register_scored(case, meas, Method::Rigid, params, Shared::default()),
    };
    let score = match &reg {
        Ok(r) => pose_score(
            case,
            meas,
            params,
            &r.image_to_physical,
            FitModel::Rigid,
            folds,
        ),
        Err(e) => Err(e.to_string()),
    };
    Tried {
        candidate: Candidate::Rigid,
        reg,
        score,
    }
}

/// The held-out score of an undeformed model at `pose`: the points matched there (LIBR's
/// correspondence settings), fitted with `model`'s unknowns.
fn pose_score(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
    pose: &Rigid,
    model: FitModel<'_>,
    folds: &Folds,
) -> Result<HeldOut, String> {
    let inv = pose.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
    let (matches, _) = case
        .correspondence
        .match_points(&pts, meas, None, &params.libr_correspondence())
        .map_err(|e| e.to_string())?;
    held_out(model, &matches, &pts, &params.libr, None, folds).map_err(|e| e.to_string())
}

/// RMS distance over the nodes between two answers (mm).
fn answers_apart(case: &Prepared, a: &Registration, b: &Registration) -> f64 {
    let nodes = case.model.mesh.nodes();
    let sum: f64 = nodes
        .iter()
        .enumerate()
        .map(|(i, x)| {
            let at = |r: &Registration| {
                r.image_to_physical
                    .apply([0, 1, 2].map(|k| x[k] + r.u[3 * i + k]))
            };
            let (p, q) = (at(a), at(b));
            (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>()
        })
        .sum();
    (sum / nodes.len().max(1) as f64).sqrt()
}

/// The standard error of the paired fold differences of two scores (mm²).
fn paired_se(a: &HeldOut, b: &HeldOut) -> f64 {
    let d: Vec<f64> = a
        .folds_mm2
        .iter()
        .zip(&b.folds_mm2)
        .map(|(x, y)| x - y)
        .collect();
    let k = d.len() as f64;
    if k < 2.0 {
        return 0.0;
    }
    let mean = d.iter().sum::<f64>() / k;
    let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (k - 1.0);
    (var / k).sqrt()
}

/// The one-standard-error rule over the scored candidates (module doc), and the answer.
fn choose(
    case: &Prepared,
    tried: Vec<Tried>,
    params: &AutoParams,
    t0: Instant,
) -> Result<Registration, PipelineError> {
    let scored: Vec<usize> = (0..tried.len())
        .filter(|&i| tried[i].reg.is_ok() && tried[i].score.is_ok())
        .collect();
    let score = |i: usize| tried[i].score.as_ref().expect("scored");
    let Some(&best) = scored
        .iter()
        .min_by(|&&a, &&b| score(a).mean_mm2.total_cmp(&score(b).mean_mm2))
    else {
        // Nothing could be scored: the first candidate's error says why.
        let mut tried = tried;
        return Err(tried
            .drain(..)
            .find_map(|t| t.reg.err())
            .unwrap_or(PipelineError::NoBasis));
    };
    let within = |i: usize| {
        let (s, b) = (score(i).mean_mm2, score(best).mean_mm2);
        s - b <= params.within_se * paired_se(score(i), score(best)) && s <= params.within_ratio * b
    };
    let chosen = scored
        .iter()
        .copied()
        .find(|&i| within(i))
        .expect("the best is within its own reach");
    let runner = scored
        .iter()
        .copied()
        .filter(|&i| i != chosen)
        .min_by(|&a, &b| score(a).mean_mm2.total_cmp(&score(b).mean_mm2));
    let reg = |i: usize| tried[i].reg.as_ref().expect("scored");
    let apart = |i: usize| answers_apart(case, reg(chosen), reg(i));
    let ambiguous = ambiguity(&tried, &scored, chosen, &within, &apart, params);
    let info = AutoInfo {
        chosen: tried[chosen].candidate,
        best_scoring: tried[best].candidate,
        runner_up: runner.map(|i| tried[i].candidate),
        margin_mm2: runner.map(|i| score(i).mean_mm2 - score(chosen).mean_mm2),
        margin_se: runner.and_then(|i| {
            let se = paired_se(score(i), score(chosen));
            let m = score(i).mean_mm2 - score(chosen).mean_mm2;
            (se > 0.0).then_some(m / se)
        }),
        runner_up_mm: runner.map(apart),
        ambiguous,
        hold_hypothesis: false,
        candidates: tried
            .iter()
            .enumerate()
            .map(|(i, t)| candidate_score(t, t.reg.as_ref().ok().map(|_| apart(i))))
            .collect(),
        answers: tried
            .iter()
            .filter_map(|t| {
                let r = t.reg.as_ref().ok()?;
                Some((t.candidate, r.image_to_physical, r.u.clone()))
            })
            .collect(),
    };
    let mut tried = tried;
    let mut answer = tried
        .swap_remove(chosen)
        .reg
        .expect("the chosen candidate registered");
    answer.method = Method::Auto;
    answer.auto = Some(info);
    answer.seconds = secs(t0);
    Ok(answer)
}

/// Why the data do not decide, when a candidate within the rule's reach of the chosen one
/// answers more than [`AutoParams::ambiguous_mm`] from it (the farthest such named).
fn ambiguity(
    tried: &[Tried],
    scored: &[usize],
    chosen: usize,
    within: &dyn Fn(usize) -> bool,
    apart: &dyn Fn(usize) -> f64,
    params: &AutoParams,
) -> Option<String> {
    let rms = |i: usize| tried[i].score.as_ref().map_or(f64::NAN, HeldOut::rms_mm);
    let (i, d) = scored
        .iter()
        .copied()
        .filter(|&i| i != chosen && within(i))
        .map(|i| (i, apart(i)))
        .filter(|&(_, d)| d > params.ambiguous_mm)
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    Some(format!(
        "the data do not decide between {} and {}: they predict the points they did not see equally well (held-out RMS {:.2} and {:.2} mm), and their answers lie {d:.1} mm apart (RMS over the organ)",
        tried[chosen].candidate,
        tried[i].candidate,
        rms(chosen),
        rms(i)
    ))
}

/// A candidate's line in [`AutoInfo::candidates`] (`apart_mm`: its answer's distance from the
/// chosen one's).
fn candidate_score(t: &Tried, apart_mm: Option<f64>) -> CandidateScore {
    let s = t.score.as_ref().ok();
    let r = t.reg.as_ref().ok();
    CandidateScore {
        candidate: t.candidate,
        held_out_mm2: s.map(|s| s.mean_mm2),
        folds_mm2: s.map(|s| s.folds_mm2.clone()).unwrap_or_default(),
        in_sample_mm2: s.map(|s| s.in_sample_mm2),
        predicted_tre_mm: r.and_then(|r| r.error.as_ref()).map(|e| e.predicted_tre_mm),
        failed: match (&t.reg, &t.score) {
            (Err(e), _) => Some(e.to_string()),
            (_, Err(e)) => Some(e.clone()),
            _ => None,
        },
        apart_mm,
        seconds: r.map_or(0.0, |r| r.seconds),
    }
}
