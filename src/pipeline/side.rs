//! Which side of the organ the surface patch lies on, decided from the data.
//!
//! Surface points are matched to the model's anterior triangles by default: a laparoscope sees
//! the organ from the front, and the restriction keeps a patch from sliding round an edge onto
//! the back. But a patch seen from another side (the dome, the posterior, a hemisphere, or a
//! model whose anterior labels were made in another convention) matched to the anterior surface
//! is pulled onto the wrong side: the pose then ends tens of millimetres off while every point
//! has a match. So before the rigid stage the navigation start's wICP is run twice, with the
//! anterior surface as the target and with the whole boundary, and each pose is scored by what
//! its own hypothesis leaves unexplained ([`super::pose::score`], each point's squared distance
//! capped). The anterior hypothesis is kept unless it leaves clearly more:
//! `anterior > ratio × boundary + margin` ([`SideParams`]). The boundary's wICP runs first on a
//! subsample of the points (as the pose search's starts do), its pose scored on every point;
//! only where that estimate comes within half of taking the boundary is it run on every point
//! and the test decided on that. Then every stage — the pose search,
//! the deformable fits, every candidate of [`super::Method::Auto`] — matches surface points to
//! the whole boundary, and the registration reports it ([`SideInfo`]).

use super::{PipelineError, PipelineParams, Prepared, pose, rigid_params};
use crate::register::MeasuredKind;
use crate::register::correspondence::SurfaceTarget;
use crate::register::wicp::{WicpParams, WicpResult, wicp};
use crate::register::{Checked, RegisterError};

/// How the side is decided.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SideParams {
    /// Decide from the data (when the surface target is the anterior surface). Default true.
    pub from_data: bool,
    /// The whole boundary is taken when the anterior hypothesis leaves more than `ratio` times
    /// its score plus `margin_mm2`. Default 2.
    pub ratio: f64,
    /// See `ratio` (mm²). Default 4 (2 mm RMS).
    pub margin_mm2: f64,
}

impl Default for SideParams {
    fn default() -> Self {
        Self {
            from_data: true,
            ratio: 2.0,
            margin_mm2: 4.0,
        }
    }
}

impl SideParams {
    /// Checks the parameters; the message names the field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        if !(self.ratio.is_finite() && self.ratio >= 1.0) {
            return Err(RegisterError::Parameter(format!(
                "side ratio must be finite and >= 1, got {}",
                self.ratio
            )));
        }
        if !(self.margin_mm2.is_finite() && self.margin_mm2 >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "side margin_mm2 must be finite and >= 0, got {}",
                self.margin_mm2
            )));
        }
        Ok(())
    }
}

/// What the side test found.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SideInfo {
    /// The target every stage matched surface points to.
    pub target: SurfaceTarget,
    /// The anterior hypothesis' score at its rigid pose (mm², capped mean squared distance).
    pub anterior_mm2: f64,
    /// The whole boundary's score at its rigid pose (mm²; the pose its wICP reached on a
    /// subsample, where that was far from deciding: see the module doc).
    pub boundary_mm2: f64,
}

/// The side test (module doc) and, for the side chosen, the navigation start's wICP result.
/// None when it does not apply: not asked, a target other than the anterior surface already
/// set, no surface points, a model whose anterior surface is its whole boundary, or a rigid
/// stage that fails (the run then reports its own error). Fails on bad [`SideParams`].
pub fn choose(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
) -> Result<Option<(SideInfo, WicpResult)>, PipelineError> {
    let side = &params.side;
    side.validate().map_err(PipelineError::Rigid)?;
    if !side.from_data
        || params.wicp.correspondence.surface_target != SurfaceTarget::Anterior
        || !meas.kind.contains(&MeasuredKind::Surface)
        || !case.correspondence.anterior_is_part()
    {
        return Ok(None);
    }
    Ok(test(case, meas, params))
}

/// [`choose`] once it applies.
fn test(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
) -> Option<(SideInfo, WicpResult)> {
    let side = &params.side;
    let anterior = rigid_params(case, params);
    let boundary = with_target(&anterior, SurfaceTarget::Boundary);
    let cap = params.pose.cap_mm;
    let fit = |w: &WicpParams| -> Option<(f64, WicpResult)> {
        let r = wicp(&case.model, &case.correspondence, meas, w).ok()?;
        let s = pose::score(
            &case.correspondence,
            meas,
            &w.correspondence,
            None,
            &r.image_to_physical,
            cap,
        )
        .ok()?;
        Some((s, r))
    };
    // The boundary hypothesis first on a subsample ([`coarse`]); run on every point only where
    // that could decide (it would take the boundary, or comes within half of it) and the
    // rigid stage's deadline has not passed (the estimate decides then).
    let (a, b) = rayon::join(|| fit(&anterior), || coarse(case, meas, &boundary, params));
    let (anterior_mm2, ra) = a?;
    let threshold = |b: f64| side.ratio * b + side.margin_mm2;
    let late = anterior
        .deadline
        .is_some_and(|d| std::time::Instant::now() >= d);
    let (boundary_mm2, rb) = match b {
        Some(b) if anterior_mm2 <= 0.5 * threshold(b) || late => (b, None),
        _ => {
            let (s, r) = fit(&boundary)?;
            (s, Some(r))
        }
    };
    let whole = anterior_mm2 > threshold(boundary_mm2);
    let info = SideInfo {
        target: if whole {
            SurfaceTarget::Boundary
        } else {
            SurfaceTarget::Anterior
        },
        anterior_mm2,
        boundary_mm2,
    };
    let start = match (whole, rb) {
        (true, Some(rb)) => rb,
        _ => ra,
    };
    Some((info, start))
}

/// The whole-boundary hypothesis' score (on every point) at the pose its wICP reaches on a
/// subsample of the points ([`pose::PoseParams::search_points`]) with the pose search's
/// looser tolerance; None where that wICP fails. The pose lies near the one a fit to every
/// point converges to, so the score is near that pose's, a little above it as a rule: the
/// test runs the fit on every point whenever this estimate comes within half of deciding.
fn coarse(
    case: &Prepared,
    meas: &Checked,
    boundary: &WicpParams,
    params: &PipelineParams,
) -> Option<f64> {
    let sub = pose::subsample(meas, params.pose.search_points);
    let w = pose::coarse_params(boundary);
    let r = wicp(&case.model, &case.correspondence, &sub, &w).ok()?;
    pose::score(
        &case.correspondence,
        meas,
        &boundary.correspondence,
        None,
        &r.image_to_physical,
        params.pose.cap_mm,
    )
    .ok()
}

/// `w` with surface points matched to `target`.
fn with_target(w: &WicpParams, target: SurfaceTarget) -> WicpParams {
    let mut w = *w;
    w.correspondence.surface_target = target;
    w
}

/// `params` with surface points matched to `target` at every stage.
pub fn params_for(params: &PipelineParams, target: SurfaceTarget) -> PipelineParams {
    let mut p = params.clone();
    p.wicp.correspondence.surface_target = target;
    p
}
