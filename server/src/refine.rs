//! METHOD_NONLINEAR in the service: the linear fit answered at once, its nonlinear refinement
//! following for the same `client_seq` within the same time budget
//! ([`librplus::pipeline::register_progressive`]); one answer when the client asks for one (a
//! unary request, or a stream's `single_answer`); the refinement skipped, and said so, when the
//! budget left cannot hold it.

use crate::cases::{Case, Estimates};
use librplus::pipeline::{
    FirstAnswer, Method, PipelineError, PipelineParams, Prepared, Registration, register,
    register_progressive,
};
use librplus::register::Checked;
use librplus_proto::v1 as pb;
use std::time::{Duration, Instant};

/// Registers as planned: METHOD_NONLINEAR with somewhere to hand its linear answer (`first`)
/// answers in two ([`register_progressive`]); everything else once.
pub(crate) fn register_planned(
    prepared: &Prepared,
    meas: &Checked,
    (method, params): (Method, &PipelineParams),
    first: Option<FirstAnswer<'_>>,
) -> Result<Registration, PipelineError> {
    match first {
        Some(first) if method == Method::Nonlinear => {
            register_progressive(prepared, meas, method, params, first)
        }
        _ => register(prepared, meas, method, params),
    }
}

/// The linear method METHOD_NONLINEAR refines on `prepared`: adaptive LIBR with its basis,
/// else LIBR.
fn linear_method(prepared: &Prepared) -> Method {
    match prepared.adaptive.is_some() {
        true => Method::Adaptive,
        false => Method::Libr,
    }
}

/// Plans METHOD_NONLINEAR within the `left` ms of its budget (ending at `deadline`): the linear
/// fit must leave the refinement its estimated time, and the refinement stops at the deadline
/// (less what follows it). Err: the linear method and why the refinement was skipped.
pub(crate) fn plan_nonlinear(
    prepared: &Prepared,
    est: &Estimates,
    left: f64,
    deadline: Instant,
    params: &mut PipelineParams,
) -> Result<(), (Method, Option<String>)> {
    let linear = est.rigid_ms + est.other_ms + est.libr_fixed_ms + 2.0 * est.libr_iteration_ms;
    let need = linear + est.refine_ms;
    let base = linear_method(prepared);
    if left < need {
        let why = format!(
            "{left:.0} ms left of the time budget, the nonlinear refinement needs about {:.0} ms \
             after the linear fit's {linear:.0} ms: skipped, {} result",
            est.refine_ms,
            base.name()
        );
        return Err((base, Some(why)));
    }
    let before = |ms: f64| deadline.checked_sub(Duration::from_secs_f64(ms.max(0.0) / 1e3));
    params.deadline = before(est.refine_ms + est.other_ms + est.libr_fixed_ms);
    params.refine_deadline = before(est.other_ms);
    Ok(())
}

/// Folds a refinement's time into the case's estimate: its own when it finished, twice that
/// when the deadline stopped it (it needed more).
pub(crate) fn observe(case: &Case, reg: &Registration) {
    let Some(n) = reg.nonlinear.as_ref().filter(|n| n.solves > 0) else {
        return;
    };
    let stopped = n
        .kept_linear
        .as_deref()
        .is_some_and(|k| k.contains("time budget"));
    let ms = n.seconds * 1e3 * if stopped { 2.0 } else { 1.0 };
    case.observe_refine(ms);
}

/// The wire's record of METHOD_NONLINEAR's refinement on its final answer (None when another
/// method was asked): what it did, whether it `refines` a linear answer sent before it, or why
/// it was skipped (`degraded`: why the plan ran less than was asked).
pub(crate) fn refinement_pb(
    asked: Method,
    refines: bool,
    reg: &Registration,
    degraded: Option<&str>,
) -> Option<pb::Refinement> {
    if asked != Method::Nonlinear {
        return None;
    }
    let Some(n) = &reg.nonlinear else {
        // Skipped by the plan: one answer, the linear fit, saying why.
        let why = degraded.unwrap_or("the refinement did not run");
        return Some(pb::Refinement {
            kept_linear: why.to_string(),
            ..Default::default()
        });
    };
    Some(pb::Refinement {
        follows: false,
        refines,
        kept_linear: n.kept_linear.clone().unwrap_or_default(),
        linear_objective_mm2: n.linear_objective_mm2,
        refined_objective_mm2: n.refined_objective_mm2,
        change_rms_mm: n.change_rms_mm,
        solves: n.solves as u32,
        newton_iterations: n.newton as u32,
        cg_iterations: n.cg as u32,
        refine_ms: n.seconds * 1e3,
    })
}
