//! The quality flag of an answer: whether it ran as asked and whether the data decided it. The
//! service answers it (`Quality` in the proto), `librplus register --json` and each registration
//! of `librplus evaluate` carry it (`quality`, `quality_reason`), so that an answer reads the
//! same wherever it was made.
//!
//! The first that applies, most severe first: degenerate data, a fallback the caller made (the
//! data stopped LIBR, the rigid answer given), an ambiguous pose, a likely failure (the error
//! estimate), an ambiguous model ([`Method::Auto`] could not decide between candidates whose
//! answers differ), a planned degradation (a time budget), a provisional first answer (the pose
//! search follows, [`super::progressive`]), a failed or cut-short refit, LIBR cut
//! short, LIBR not settled, the rigid stage not converged; else OK.

use super::{Method, PipelineParams, Registration, pose::PoseInfo};
use crate::register::uncertainty::ErrorEstimate;

/// An answer's quality (the proto's `Quality`, without its unspecified value).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Quality {
    /// Ran as asked and converged or settled.
    Ok,
    /// Ran as asked but stopped at its iteration limit with the fit not settled.
    NotConverged,
    /// Less than was asked ran (a time budget, a skipped correction): see the reason.
    Degraded,
    /// The data do not determine a registration: the answer is the best rigid guess and must
    /// not be used for navigation.
    Degenerate,
    /// Two rigid poses, far apart, explain the points about equally.
    AmbiguousPose,
    /// Candidate models whose answers lie far apart predict the points about equally
    /// ([`super::auto::AutoInfo::ambiguous`]).
    AmbiguousModel,
    /// The error estimate gives the answer a high chance of having failed.
    LikelyFailed,
}

impl Quality {
    /// The name in `--json` and `results.json` (`ok`, `not_converged`, `degraded`,
    /// `degenerate`, `ambiguous_pose`, `ambiguous_model`, `likely_failed`).
    pub fn name(self) -> &'static str {
        match self {
            Quality::Ok => "ok",
            Quality::NotConverged => "not_converged",
            Quality::Degraded => "degraded",
            Quality::Degenerate => "degenerate",
            Quality::AmbiguousPose => "ambiguous_pose",
            Quality::AmbiguousModel => "ambiguous_model",
            Quality::LikelyFailed => "likely_failed",
        }
    }
}

/// An answer's quality and why (empty for OK).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Judgement {
    /// The flag.
    pub quality: Quality,
    /// Why, in words (empty when OK).
    pub reason: String,
}

/// What the caller knows of a registration beyond the registration itself.
#[derive(Debug, Clone, Default)]
pub struct Circumstances {
    /// The caller gave another method's answer because the asked one could not run (the
    /// reason).
    pub fallback: Option<String>,
    /// The caller ran less than was asked (the reason: a time budget).
    pub degraded: Option<String>,
    /// The time budget the registration ran under (ms), named when a stage was cut short.
    pub budget_ms: Option<f64>,
}

/// The error estimate's failure probability from which an answer is flagged
/// [`Quality::LikelyFailed`]. On the paper preset (seed 2, 500 LIBR registrations with the gated
/// pose search, the built-in error model) this flag or an ambiguous pose catches 9 of the 14
/// wrong answers (mean TRE > 20 mm) and flags 17 of the 486 others; at 0.5, 7 and 12.
pub const LIKELY_FAILED_PROBABILITY: f64 = 0.3;

/// Why an answer has likely failed, from its error estimate (None: not likely).
pub fn likely_failed(e: Option<&ErrorEstimate>) -> Option<String> {
    let e = e?;
    let p = e.failure_probability?;
    (p >= LIKELY_FAILED_PROBABILITY).then(|| {
        format!(
            "the error estimate gives a {:.0} % chance that the mean error exceeds {:.0} mm (predicted mean error {:.1} mm): check the alignment",
            100.0 * p,
            e.failure_threshold_mm.unwrap_or(f64::NAN),
            e.predicted_tre_mm
        )
    })
}

/// Why the pose is ambiguous, when the pose search says it is.
pub fn ambiguous_pose(p: &PoseInfo) -> Option<String> {
    if !p.ambiguous {
        return None;
    }
    let mut sorted = p.scores.clone();
    sorted.sort_by(f64::total_cmp);
    Some(format!(
        "two rigid poses {:.0} mm apart explain the points about equally after the deformable fit (scores {:.2} and {:.2} mm²): the answer is the better one and may be wrong",
        p.runner_up_mm.unwrap_or(0.0),
        sorted.first().copied().unwrap_or(f64::NAN),
        sorted.get(1).copied().unwrap_or(f64::NAN)
    ))
}

/// `the time budget B ms: ` or `the deadline: `.
fn budget(c: &Circumstances) -> String {
    c.budget_ms.map_or_else(
        || "the deadline".into(),
        |b| format!("time budget {b:.0} ms"),
    )
}

/// The quality of `reg` (module doc), run with `params`.
pub fn judge(reg: &Registration, params: &PipelineParams, c: &Circumstances) -> Judgement {
    let j = |quality, reason: String| Judgement { quality, reason };
    let gcn = reg.correction.as_ref();
    let refit = gcn.and_then(|c| c.refit.as_ref());
    // The stages of the answer given: for auto, the chosen candidate's.
    let base = reg.auto.as_ref().map_or(reg.method, |a| a.chosen.method());
    if let Some(r) = &reg.rigid.degenerate {
        j(Quality::Degenerate, format!("degenerate data: {r}"))
    } else if let Some(r) = &c.fallback {
        j(Quality::Degenerate, r.clone())
    } else if let Some(r) = reg.pose.as_ref().and_then(ambiguous_pose) {
        j(Quality::AmbiguousPose, r)
    } else if let Some(r) = likely_failed(reg.error.as_ref()) {
        j(Quality::LikelyFailed, r)
    } else if let Some(r) = reg.auto.as_ref().and_then(|a| a.ambiguous.clone()) {
        j(Quality::AmbiguousModel, r)
    } else if let Some(r) = &c.degraded {
        j(Quality::Degraded, r.clone())
    } else if reg.search_follows {
        let why = format!(
            "a first answer from the navigation start alone: its fit scored {:.1} mm² (the pose search runs above {:.1} mm²); the searched answer follows",
            reg.search_skipped_mm2.unwrap_or(f64::NAN),
            params.pose.search_above_mm2
        );
        j(Quality::Degraded, why)
    } else if let Some(e) = gcn.and_then(|c| c.refit_error.as_deref()) {
        let why =
            format!("LIBR+'s refit failed ({e}); the answer is the network's correction of LIBR");
        j(Quality::Degraded, why)
    } else if let Some(i) = refit.filter(|i| i.stopped_at_deadline) {
        let why = format!(
            "{}: LIBR+'s refit stopped after {} of {} iterations",
            budget(c),
            i.iterations,
            params.refit_iterations
        );
        j(Quality::Degraded, why)
    } else if reg.rigid.stopped_at_deadline {
        let why = format!(
            "{}: the rigid stage stopped after {} of {} iterations",
            budget(c),
            reg.rigid.iterations,
            params.wicp.max_iterations
        );
        j(Quality::Degraded, why)
    } else if let Some(i) = reg.libr.as_ref().filter(|i| i.stopped_at_deadline) {
        let why = format!(
            "{}: LIBR stopped after {} of {} iterations",
            budget(c),
            i.iterations,
            params.libr.fit.max_iterations
        );
        j(Quality::Degraded, why)
    } else if let Some(i) = reg.libr.as_ref().filter(|i| !i.settled) {
        // Not settled: the objective was still falling, or the model running away, when the
        // iteration cap came (a fit that cycles around a flat objective is settled, and OK).
        let why = format!(
            "LIBR ran its {} iterations without settling; the last moved the model by up to {:.2} mm (tolerance {} mm)",
            i.iterations,
            i.movement_history_mm.last().copied().unwrap_or(f64::NAN),
            params.libr.fit.tolerance_mm
        );
        j(Quality::NotConverged, why)
    } else if !reg.rigid.converged && reg.libr.is_none() && base != Method::Initial {
        let why = format!(
            "the rigid stage ran its {} iterations without converging",
            reg.rigid.iterations
        );
        j(Quality::NotConverged, why)
    } else {
        j(Quality::Ok, String::new())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::CorrectionInfo;
    use crate::pipeline::auto::{AutoInfo, Candidate};
    use crate::register::libr::LibrInfo;
    use crate::register::wicp::WicpResult;

    /// A LIBR answer that ran as asked: the rigid stage converged, `libr` and `refit` as given.
    fn answer(libr: Option<LibrInfo>, refit: Option<LibrInfo>) -> Registration {
        Registration {
            method: if refit.is_some() {
                Method::LibrPlus
            } else {
                Method::Libr
            },
            image_to_physical: Default::default(),
            u: Vec::new(),
            rigid: WicpResult {
                iterations: 10,
                converged: true,
                ..Default::default()
            },
            pose: None,
            libr,
            correction: refit.map(|r| CorrectionInfo {
                applied: true,
                refit: Some(r),
                ..Default::default()
            }),
            v2s: None,
            nonlinear: None,
            error: None,
            auto: None,
            search_skipped_mm2: None,
            search_follows: false,
            refinement_follows: false,
            surface: None,
            points: None,
            seconds: 0.0,
        }
    }

    fn settled() -> LibrInfo {
        LibrInfo {
            iterations: 4,
            converged: true,
            settled: true,
            ..LibrInfo::default()
        }
    }

    fn quality(r: &Registration) -> Quality {
        r.quality(&PipelineParams::default()).quality
    }

    /// An answer the error estimate gives a high failure probability is flagged LIKELY_FAILED
    /// (from [`LIKELY_FAILED_PROBABILITY`] on), with the probability and the prediction in its
    /// reason; below it, or without a failure part, it is not; an ambiguous pose comes first.
    #[test]
    fn a_likely_failure_is_flagged() {
        let est = |p: Option<f64>| ErrorEstimate {
            predicted_tre_mm: 23.4,
            level: 0.9,
            node_bound_mm: Vec::new(),
            failure_probability: p,
            failure_threshold_mm: Some(20.0),
            features: Default::default(),
            seconds: 0.0,
        };
        assert_eq!(likely_failed(None), None);
        assert_eq!(likely_failed(Some(&est(None))), None);
        let below = Some(LIKELY_FAILED_PROBABILITY - 1e-9);
        assert_eq!(likely_failed(Some(&est(below))), None);
        let why = likely_failed(Some(&est(Some(0.47)))).unwrap();
        assert!(
            why.contains("47 %") && why.contains("20 mm") && why.contains("23.4 mm"),
            "{why}"
        );
        let mut r = answer(Some(settled()), None);
        assert_eq!(quality(&r), Quality::Ok);
        r.error = Some(est(Some(0.47)));
        let j = r.quality(&PipelineParams::default());
        assert_eq!((j.quality, j.reason), (Quality::LikelyFailed, why));
        r.pose = Some(PoseInfo {
            starts: 5,
            distinct: 2,
            scores: vec![3.0, 2.9],
            prior_mm2: vec![0.0, 0.0],
            chosen: 1,
            moved_from_single_start_mm: 30.0,
            ambiguous: true,
            runner_up_mm: Some(31.0),
            rigid_seconds: 0.0,
        });
        let j = r.quality(&PipelineParams::default());
        assert_eq!(j.quality, Quality::AmbiguousPose);
        assert!(j.reason.contains("31 mm apart") && j.reason.contains("2.90 and 3.00"));
    }

    /// A LIBR+ answer whose refit ran 1 of its 5 iterations (the deadline) is DEGRADED and says
    /// how far the refit got, naming the budget; LIBR cut short is DEGRADED; settled without
    /// converging (cycling around a flat objective) is OK, not settled NOT_CONVERGED.
    #[test]
    fn a_refit_cut_short_is_degraded() {
        let params = PipelineParams::default();
        let full = LibrInfo {
            iterations: params.refit_iterations,
            ..settled()
        };
        assert_eq!(
            quality(&answer(Some(settled()), Some(full.clone()))),
            Quality::Ok
        );
        let cut = LibrInfo {
            iterations: 1,
            stopped_at_deadline: true,
            ..full
        };
        let c = Circumstances {
            budget_ms: Some(250.0),
            ..Default::default()
        };
        let j = judge(&answer(Some(settled()), Some(cut)), &params, &c);
        assert_eq!(j.quality, Quality::Degraded);
        assert!(
            j.reason
                .contains("time budget 250 ms: LIBR+'s refit stopped after 1 of"),
            "{}",
            j.reason
        );
        let libr_cut = LibrInfo {
            stopped_at_deadline: true,
            ..settled()
        };
        let j = answer(Some(libr_cut), None).quality(&params);
        assert_eq!(j.quality, Quality::Degraded);
        assert!(
            j.reason.starts_with("the deadline: LIBR stopped"),
            "{}",
            j.reason
        );
        // The rigid stage stopped at its deadline: DEGRADED, saying how far it got.
        let mut rigid_cut = answer(Some(settled()), None);
        rigid_cut.rigid.stopped_at_deadline = true;
        rigid_cut.rigid.converged = false;
        let j = judge(&rigid_cut, &params, &c);
        assert_eq!(j.quality, Quality::Degraded);
        assert!(
            j.reason
                .starts_with("time budget 250 ms: the rigid stage stopped after 10 of 200"),
            "{}",
            j.reason
        );
        let cycling = LibrInfo {
            converged: false,
            ..settled()
        };
        assert_eq!(quality(&answer(Some(cycling), None)), Quality::Ok);
        let unconverged = LibrInfo {
            converged: false,
            settled: false,
            ..settled()
        };
        assert_eq!(
            quality(&answer(Some(unconverged), None)),
            Quality::NotConverged
        );
        // A caller's fallback and degradation come before the stages' own.
        let c = Circumstances {
            degraded: Some("time budget 10 ms: rigid result".into()),
            ..Default::default()
        };
        let j = judge(&answer(None, None), &params, &c);
        assert_eq!(j.quality, Quality::Degraded);
        let c = Circumstances {
            fallback: Some("LIBR could not run".into()),
            ..c
        };
        assert_eq!(
            judge(&answer(None, None), &params, &c).quality,
            Quality::Degenerate
        );
    }

    /// Auto's ambiguity is AMBIGUOUS_MODEL with its reason; doing nothing chosen by auto (a
    /// rigid stage of no iterations) is OK, while a rigid stage that ran out of iterations is
    /// NOT_CONVERGED.
    #[test]
    fn an_undecided_model_is_flagged_and_doing_nothing_is_not_unconverged() {
        let info = |chosen, ambiguous: Option<&str>| AutoInfo {
            chosen,
            best_scoring: chosen,
            runner_up: Some(Candidate::Libr),
            margin_mm2: Some(0.1),
            margin_se: Some(0.2),
            runner_up_mm: Some(7.0),
            ambiguous: ambiguous.map(str::to_string),
            hold_hypothesis: false,
            candidates: Vec::new(),
            answers: Vec::new(),
        };
        let mut r = answer(None, None);
        r.method = Method::Auto;
        r.rigid = WicpResult::default();
        r.auto = Some(info(Candidate::Initial, None));
        assert_eq!(quality(&r), Quality::Ok);
        r.auto = Some(info(Candidate::Initial, Some("the data do not decide")));
        let j = r.quality(&PipelineParams::default());
        assert_eq!(
            (j.quality, j.reason.as_str()),
            (Quality::AmbiguousModel, "the data do not decide")
        );
        r.auto = Some(info(Candidate::Rigid, None));
        assert_eq!(quality(&r), Quality::NotConverged);
        assert_eq!(Quality::AmbiguousModel.name(), "ambiguous_model");
        assert_eq!(
            serde_json::to_value(Quality::NotConverged).unwrap(),
            serde_json::json!("not_converged")
        );
    }
}
