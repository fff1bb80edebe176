//! Two answers where the pose search would run: the navigation start's fit at once, flagged
//! provisional, then the searched answer.
//!
//! The gated pose search ([`super::pose::PoseParams::search_above_mm2`]) runs on about one registration
//! in ten, and costs 4–10 single registrations (its extra starts, their refinement and the
//! candidates' deformable fits). Answered in one piece, those registrations are the latency's
//! whole tail. [`register_progressive`] answers them in two: first the registration with the
//! search turned off, which is the navigation start's fit with
//! [`Registration::search_follows`] set (its quality [`Quality::Degraded`](super::quality::Quality),
//! the reason naming the fit's score and that the searched answer follows), handed to the
//! caller as soon as it is made; then the registration exactly as [`register`] makes it, search
//! included. A registration the gate does not search is answered once, as [`register`] answers
//! it.
//!
//! [`Method::Nonlinear`] answers in two as well: its linear fit (adaptive LIBR, or LIBR), with
//! [`Registration::refinement_follows`] set, as soon as it is made; then the refinement of that
//! fit, [`register`]'s answer. Nothing is repeated: the refinement starts from the answer
//! handed over. Its pose search, when the gate runs one, is inside the linear fit (no
//! provisional pose answer of its own).
//!
//! The second answer repeats the first's work (the side test, the navigation start's wICP and
//! its fit) before it searches: about one unsearched registration more, on searched
//! registrations only, so that it is [`register`]'s answer bit for bit.

use super::{
    FirstAnswer, Method, PipelineError, PipelineParams, Prepared, Registration, register,
    register_with,
};
use crate::register::Checked;

/// Whether `method` under `params` can answer in two: a deformable method with the gated pose
/// search configured (extra starts, a gate above 0).
pub fn can_follow(method: Method, params: &PipelineParams) -> bool {
    let deformable = matches!(
        method,
        Method::Libr | Method::LibrPlus | Method::Adaptive | Method::Nonlinear | Method::Auto
    );
    deformable && !params.pose.start_angles_deg.is_empty() && params.pose.search_above_mm2 > 0.0
}

/// [`register`] in one or two answers (module doc): `first` receives the provisional answer
/// when the pose search or the nonlinear refinement follows, before it runs; the returned
/// registration is the final answer, [`register`]'s.
pub fn register_progressive(
    case: &Prepared,
    meas: &Checked,
    method: Method,
    params: &PipelineParams,
    first: FirstAnswer<'_>,
) -> Result<Registration, PipelineError> {
    if method == Method::Nonlinear {
        return register_with(case, meas, method, params, Some(first));
    }
    if !can_follow(method, params) {
        return register(case, meas, method, params);
    }
    let mut quick = params.clone();
    quick.pose.start_angles_deg.clear();
    let mut answer = register(case, meas, method, &quick)?;
    if answer.search_skipped_mm2.is_none() {
        // The gate would not have searched: this is the final answer.
        return Ok(answer);
    }
    answer.search_follows = true;
    first(&answer);
    register(case, meas, method, params)
}
