//! Rigid registration by salient-feature weighted ICP (wICP), after L. W. Clements, W. C. Chapman,
//! B. M. Dawant, R. L. Galloway and M. I. Miga, "Robust surface registration using salient anatomical
//! features for image-guided liver surgery: algorithm and validation", Med. Phys. 35(6), 2008.
//!
//! Starting from the navigation system's coarse landmark alignment (`Measurements::initial_alignment`,
//! identity when absent), each iteration maps the measured points into the image frame by the
//! inverse of the current transform, matches them to the undeformed model ([`Correspondence`]:
//! anterior surface, salient-feature neighbourhoods with extra weight, posterior surface, vessel
//! centerlines; trimmed), and fits image → physical by weighted Kabsch ([`Rigid::fit`]) from the
//! matched model points to the measured points. It stops when the RMS distance of the kept pairs
//! changes by less than `tolerance_mm` between iterations; the reported transform, RMS and counts
//! belong together (the RMS is that of the returned transform's matches).
//!
//! With a trusted start ([`WicpParams::trusted_alignment_mm`], or a held organ) the fit is
//! regularised towards it ([`crate::register::prior`]); when the final pairs cannot fix the
//! rigid motion (their point-to-plane conditioning below [`WicpParams::min_conditioning`]) the
//! fit is redone with the start trusted to [`ILL_POSED_SIGMA_MM`] and flagged `ill_posed`.
//!
//! Garbage in gives an error naming the field (no points, length mismatches, non-finite values,
//! most points more than `max_distance_mm` from the model after the initial alignment) or a result
//! flagged `degenerate` with the transform left where it was (all points on one spot, collinear
//! points, fewer than three pairs left, a rank-deficient fit) — never NaN.

use super::RegisterError;
use std::time::Instant;

use nalgebra::{Matrix3, Vector3};

use super::PreopModel;
use super::correspondence::{Correspondence, CorrespondenceParams, MatchStats};
use super::measured::not_empty;
use super::prior::RigidPrior;
use super::{Checked, Match, MeasuredKind};
use crate::mesh::rigid::Rigid;

/// Parameters of [`wicp`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WicpParams {
    /// Most iterations (match + fit). Default 200.
    pub max_iterations: usize,
    /// Converged when the RMS distance changes by less than this between iterations (mm).
    /// Default 1e-3 (a thousandth of the tracking noise; 1e-4 took twice the iterations, 62 on
    /// average on the paper preset, for no change in the LIBR result that follows).
    pub tolerance_mm: f64,
    /// Weights and trimming of the pairs.
    pub correspondence: CorrespondenceParams,
    /// Register on the anterior-surface points alone (with their salient features), as Clements
    /// et al. did and as the LIBR+ paper's wICP baseline does (its TRE is the same whatever
    /// ultrasound planes a scenario has); ultrasound contour and vessel points are then left to
    /// LIBR. With fewer than 3 surface points every point is used, with a warning. Default
    /// false: every point.
    #[serde(default)]
    pub surface_only: bool,
    /// The navigation system's initial alignment is trusted to this uncertainty (mm, RMS
    /// displacement over the organ): the rigid motion is regularised towards it
    /// ([`crate::register::prior`]) instead of fitted freely. Default None: free.
    #[serde(default)]
    pub trusted_alignment_mm: Option<f64>,
    /// Below this conditioning of the final point-to-plane system ([`WicpResult::conditioning`])
    /// the data cannot fix the rigid motion (a partial, smooth patch): the fit is redone with the
    /// start trusted to [`ILL_POSED_SIGMA_MM`] and flagged. 0 turns the check off. Default
    /// [`MIN_CONDITIONING`].
    #[serde(default = "default_min_conditioning")]
    pub min_conditioning: f64,
    /// Anderson acceleration of the iterations ([`super::accelerate`]): each step extrapolated
    /// from the last few, kept when its matching is no worse than the current pose's. Same
    /// fixed points as plain ICP in a fraction of the iterations, but it stops nearer them than
    /// plain ICP's tolerance does, and that changes answers downstream (pose choices; the
    /// discovery workflow named an effect on a cohort with nothing hidden). Default false.
    #[serde(default = "default_accelerate")]
    pub accelerate: bool,
    /// Stop iterating at this instant (a time budget): the result is the pose reached, with
    /// [`WicpResult::stopped_at_deadline`] set, and the ill-posed refit (above) does not run
    /// past it. Default None: no deadline. Not serialised (an instant of this process).
    #[serde(skip)]
    pub deadline: Option<Instant>,
}

fn default_accelerate() -> bool {
    false
}

fn default_min_conditioning() -> f64 {
    MIN_CONDITIONING
}

/// Default [`WicpParams::min_conditioning`].
pub const MIN_CONDITIONING: f64 = 1e-3;
/// Uncertainty (mm) the start is trusted to when the data cannot fix the rigid motion.
pub const ILL_POSED_SIGMA_MM: f64 = 10.0;

impl Default for WicpParams {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            tolerance_mm: 1e-3,
            correspondence: CorrespondenceParams::default(),
            surface_only: false,
            trusted_alignment_mm: None,
            min_conditioning: MIN_CONDITIONING,
            accelerate: false,
            deadline: None,
        }
    }
}

/// Result of [`wicp`] (the default: no iterations, an identity pose).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WicpResult {
    /// The registration, image → physical.
    pub image_to_physical: Rigid,
    /// RMS distance of the kept pairs under `image_to_physical` (mm).
    pub rms_mm: f64,
    /// RMS distance of the kept pairs under the starting transform (mm).
    pub initial_rms_mm: f64,
    /// Iterations run (fits made).
    pub iterations: usize,
    /// Whether the RMS change fell below the tolerance.
    pub converged: bool,
    /// Pairs kept at the end.
    pub matched: usize,
    /// Pairs trimmed at the end (including far ones).
    pub trimmed: usize,
    /// Points more than `max_distance_mm` from the model after the initial alignment (excluded).
    pub far: usize,
    /// Statistics of the final matching.
    pub stats: MatchStats,
    /// Why the result cannot be trusted (the transform is then the last well-determined one,
    /// the start when the data are degenerate from the outset); `None` when it can.
    pub degenerate: Option<String>,
    /// Things worth knowing that did not stop the registration (e.g. far points dropped).
    pub warnings: Vec<String>,
    /// How well the final pairs fix the rigid motion: the smallest over the largest eigenvalue
    /// of their point-to-plane system (rotations scaled by the pairs' RMS radius; 1: as well in
    /// every direction, 0: a direction left free). 0 when degenerate.
    #[serde(default)]
    pub conditioning: f64,
    /// The prior the rigid motion was regularised with (a trusted start, or the start trusted
    /// because the data could not fix the motion), when there was one; LIBR keeps it.
    #[serde(default)]
    pub prior: Option<RigidPrior>,
    /// Whether the data could not fix the rigid motion ([`WicpParams::min_conditioning`]) and
    /// the start was trusted instead.
    #[serde(default)]
    pub ill_posed: bool,
    /// RMS displacement of the organ's nodes between the start and the result (mm).
    #[serde(default)]
    pub moved_from_start_mm: f64,
    /// Wall-clock time (s) of this run (in a registration with a pose search, of the chosen
    /// pose's run; the pipeline reports the whole search's separately).
    pub seconds: f64,
    /// Whether the iterations stopped at [`WicpParams::deadline`] before converging.
    #[serde(default)]
    pub stopped_at_deadline: bool,
}

/// RMS spread (mm) across the principal line below which measured points count as collinear:
/// with tracking noise of about a millimetre, points within a couple of millimetres of a line (a
/// stylus swiped along one stroke) cannot fix the rotation about it, and a fit would turn on the
/// noise alone (a line with 0.2 mm jitter came out 80° off before this bound).
const COLLINEAR_MM: f64 = 2.0;
/// RMS spread (mm) below which measured points count as one spot.
const SPOT_MM: f64 = 1e-3;
/// Coordinates (mm) within which a degenerate (collinear) point set is taken for metres sent as
/// millimetres: a liver measured in metres lies within a couple of units of the tracker's
/// origin, and spreads over a fraction of one.
const METRES_REACH_MM: f64 = 2.0;

/// Rigid salient-feature weighted ICP of `meas` (physical frame) to the undeformed `model`; `corr`
/// must have been built from `model`. See the module doc.
pub fn wicp(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Checked,
    params: &WicpParams,
) -> Result<WicpResult, RegisterError> {
    let clock = Instant::now();
    check_inputs(model, corr, meas, params)?;
    let mut warnings = Vec::new();
    let surface = surface_points(meas, params, &mut warnings);
    let meas = surface.as_ref().unwrap_or(meas);
    let start = meas.initial_alignment.unwrap_or_default();
    let cap = params.correspondence.max_distance_mm;
    let to_image = |t: &Rigid| -> Vec<[f64; 3]> {
        let inv = t.inverse();
        meas.points.iter().map(|&p| inv.apply(p)).collect()
    };
    let (dist, far) = far_points(corr, &to_image(&start), cap, &mut warnings)?;
    let npts = meas.points.len();

    let corr_params = &params.correspondence;
    // The closest-triangle searches start where the last iteration's ended (same matches).
    let hints = std::cell::RefCell::new(super::correspondence::Hints::default());
    let matching = |t: &Rigid| {
        corr.match_points_hinted(
            &to_image(t),
            meas,
            None,
            corr_params,
            &mut hints.borrow_mut(),
        )
    };
    let (_, initial_stats) = matching(&start)?;
    let mut result = WicpResult::at_start(start, initial_stats, far.len(), warnings);

    // Degenerate point sets: the rotation is undetermined whatever the model.
    let near: Vec<[f64; 3]> = (0..npts)
        .filter(|&i| dist[i] <= cap)
        .map(|i| meas.points[i])
        .collect();
    if let Some(reason) = degenerate_points(&near) {
        result.degenerate = Some(reason);
        result.seconds = clock.elapsed().as_secs_f64();
        return Ok(result);
    }

    let nodes = model.mesh.nodes();
    let declared = params
        .trusted_alignment_mm
        .map(|sig| RigidPrior::new(nodes, start, sig, initial_stats.rms_mm));
    let mut run = icp_loop(
        meas,
        params,
        start,
        initial_stats,
        declared.as_ref(),
        &matching,
    )?;
    let mut ill_posed = false;
    if declared.is_none() && run.leaves_motion_free(params) {
        // The data leave a rigid direction free: trust the start instead of sliding along it.
        let prior = RigidPrior::new(nodes, start, ILL_POSED_SIGMA_MM, initial_stats.rms_mm);
        let free = run.conditioning;
        run = icp_loop(meas, params, start, initial_stats, Some(&prior), &matching)?;
        ill_posed = true;
        result.warnings.push(format!(
            "the measured points do not fix the rigid motion (conditioning {free:.1e} < {:.0e}: a \
             partial, smooth patch): the start was trusted to {ILL_POSED_SIGMA_MM} mm",
            params.min_conditioning
        ));
    }
    result.ill_posed = ill_posed;
    result.moved_from_start_mm = RigidPrior::new(nodes, start, 1.0, 1.0).rms_mm(&run.t);
    result.ended(run);
    result.seconds = clock.elapsed().as_secs_f64();
    Ok(result)
}

/// The measurements, the parameters, and the correspondence against the model.
fn check_inputs(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Checked,
    params: &WicpParams,
) -> Result<(), RegisterError> {
    not_empty(meas)?;
    params.validate()?;
    if corr.num_nodes() != model.mesh.num_nodes() {
        return Err(RegisterError::Inconsistent(format!(
            "the correspondence was built for {} nodes, the model has {}",
            corr.num_nodes(),
            model.mesh.num_nodes()
        )));
    }
    Ok(())
}

impl WicpParams {
    /// Checks the parameters, naming the first bad one.
    pub fn validate(&self) -> Result<(), RegisterError> {
        self.correspondence.validate()?;
        if !(self.tolerance_mm.is_finite() && self.tolerance_mm >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "wicp parameter tolerance_mm must be finite and ≥ 0, got {}",
                self.tolerance_mm
            )));
        }
        if let Some(sig) = self.trusted_alignment_mm {
            if !(sig.is_finite() && sig > 0.0) {
                return Err(RegisterError::Parameter(format!(
                    "wicp parameter trusted_alignment_mm must be finite and > 0, got {sig}"
                )));
            }
        }
        if !(self.min_conditioning.is_finite() && self.min_conditioning >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "wicp parameter min_conditioning must be finite and ≥ 0, got {}",
                self.min_conditioning
            )));
        }
        Ok(())
    }
}

impl WicpResult {
    /// The result before any iteration: the start, its matching's figures.
    fn at_start(start: Rigid, stats: MatchStats, far: usize, warnings: Vec<String>) -> Self {
        WicpResult {
            image_to_physical: start,
            rms_mm: stats.rms_mm,
            initial_rms_mm: stats.rms_mm,
            iterations: 0,
            converged: false,
            matched: stats.kept,
            trimmed: stats.trimmed,
            far,
            stats,
            degenerate: None,
            warnings,
            seconds: 0.0,
            conditioning: 0.0,
            prior: None,
            ill_posed: false,
            moved_from_start_mm: 0.0,
            stopped_at_deadline: false,
        }
    }

    /// Takes the transform and the final matching's figures from the ICP iterations' end.
    fn ended(&mut self, run: LoopEnd) {
        self.iterations = run.iterations;
        self.converged = run.converged;
        self.stopped_at_deadline = run.stopped_at_deadline;
        self.degenerate = run.degenerate;
        self.conditioning = run.conditioning;
        self.prior = run.prior;
        self.image_to_physical = run.t;
        self.rms_mm = run.stats.rms_mm;
        self.matched = run.stats.kept;
        self.trimmed = run.stats.trimmed;
        self.stats = run.stats;
    }
}

/// Clements' data: the anterior-surface points alone, when asked and there are at least three
/// (None: every point, with a warning when the surface alone was asked but too few).
fn surface_points(
    meas: &Checked,
    params: &WicpParams,
    warnings: &mut Vec<String>,
) -> Option<Checked> {
    if !params.surface_only {
        return None;
    }
    let keep: Vec<usize> = (0..meas.points.len())
        .filter(|&i| meas.kind[i] == MeasuredKind::Surface)
        .collect();
    if keep.len() >= 3 {
        return Some(meas.subset(&keep));
    }
    warnings.push(format!(
        "{} anterior-surface point(s): the rigid stage used every point instead of the \
         surface alone",
        keep.len()
    ));
    None
}

/// Each point's distance to the model's boundary after the initial alignment (`start_image`:
/// the points in the image frame) and the points farther than `cap` mm, which are left out
/// (with a warning); an error when they are more than half.
fn far_points(
    corr: &Correspondence,
    start_image: &[[f64; 3]],
    cap: f64,
    warnings: &mut Vec<String>,
) -> Result<(Vec<f64>, Vec<usize>), RegisterError> {
    let dist: Vec<f64> = start_image
        .iter()
        .map(|&p| corr.distance_to_boundary(p))
        .collect();
    let far: Vec<usize> = (0..dist.len()).filter(|&i| dist[i] > cap).collect();
    let npts = dist.len();
    if 2 * far.len() > npts {
        let worst = (0..npts)
            .max_by(|&a, &b| dist[a].total_cmp(&dist[b]))
            .unwrap_or(0);
        return Err(RegisterError::FarFromModel {
            far: far.len(),
            total: npts,
            cap_mm: cap,
            worst,
            worst_mm: dist[worst],
        });
    }
    if !far.is_empty() {
        warnings.push(format!(
            "{} measured point(s) more than {cap} mm from the model after the initial alignment \
             were left out (first: measurements.points[{}], {:.0} mm away)",
            far.len(),
            far[0],
            dist[far[0]]
        ));
    }
    Ok((dist, far))
}

/// The matching of the measured points under a transform.
type Matching<'a> = dyn Fn(&Rigid) -> Result<(Vec<Match>, MatchStats), RegisterError> + 'a;

/// What one run of the ICP iterations ended with.
struct LoopEnd {
    t: Rigid,
    stats: MatchStats,
    iterations: usize,
    converged: bool,
    degenerate: Option<String>,
    conditioning: f64,
    prior: Option<RigidPrior>,
    stopped_at_deadline: bool,
}

impl LoopEnd {
    /// Whether the fit left a rigid direction free ([`WicpParams::min_conditioning`]) and
    /// there is time to fit again with the start trusted.
    fn leaves_motion_free(&self, params: &WicpParams) -> bool {
        self.degenerate.is_none()
            && self.conditioning < params.min_conditioning
            && !past(params.deadline)
    }
}

/// Whether `deadline` has passed.
fn past(deadline: Option<Instant>) -> bool {
    deadline.is_some_and(|d| Instant::now() >= d)
}

/// The ICP iterations from `start` (match, weighted Kabsch fit with the prior's pose pairs,
/// until the RMS settles).
fn icp_loop(
    meas: &Checked,
    params: &WicpParams,
    start: Rigid,
    initial_stats: MatchStats,
    prior: Option<&RigidPrior>,
    matching: &Matching<'_>,
) -> Result<LoopEnd, RegisterError> {
    let mut end = LoopEnd {
        t: start,
        stats: initial_stats,
        iterations: 0,
        converged: false,
        degenerate: None,
        conditioning: 0.0,
        prior: prior.copied(),
        stopped_at_deadline: false,
    };
    let mut prev_rms = f64::INFINITY;
    let (mut matches, _) = matching(&start)?;
    let mut accel = params
        .accelerate
        .then(|| super::accelerate::Anderson::new(start, &meas.points));
    loop {
        if (prev_rms - end.stats.rms_mm).abs() < params.tolerance_mm {
            end.converged = true;
            break;
        }
        if end.iterations >= params.max_iterations {
            break;
        }
        if past(params.deadline) {
            end.stopped_at_deadline = true;
            break;
        }
        if matches.len() < 3 {
            end.degenerate = Some(format!(
                "only {} pair(s) left after trimming ({} trimmed, {} unmatched): at least 3 are \
                 needed",
                matches.len(),
                end.stats.trimmed,
                end.stats.unmatched
            ));
            break;
        }
        let fit = match weighted_fit(meas, &matches, prior) {
            Ok(fit) => fit,
            Err(reason) => {
                end.degenerate = Some(reason);
                break;
            }
        };
        end.iterations += 1;
        let (t, m, s) = next_pose(&end, fit, accel.as_mut(), matching)?;
        prev_rms = end.stats.rms_mm;
        end.t = t;
        matches = m;
        end.stats = s;
    }
    if end.degenerate.is_none() {
        end.conditioning = conditioning(&matches);
    }
    Ok(end)
}

/// One ICP step's fit: weighted Kabsch from the matched model points to the measured points,
/// with the prior's pose pairs (weight κ·W/6 each against the data's total weight W). Err: why
/// the rotation is undetermined or the fit not finite.
fn weighted_fit(
    meas: &Checked,
    matches: &[Match],
    prior: Option<&RigidPrior>,
) -> Result<Rigid, String> {
    let mut src: Vec<[f64; 3]> = matches.iter().map(|m| m.anchor).collect();
    let mut dst: Vec<[f64; 3]> = matches.iter().map(|m| meas.points[m.point]).collect();
    let mut w: Vec<f64> = matches.iter().map(|m| m.weight).collect();
    if let Some(p) = prior {
        let wk = p.weight() * w.iter().sum::<f64>() / 6.0;
        for q in p.pose_points {
            src.push(q);
            dst.push(p.start.apply(q));
            w.push(wk);
        }
    }
    let Some(fit) = Rigid::fit(&src, &dst, Some(&w)) else {
        return Err(format!(
            "the {} matched model points are collinear or coincident (or all weights are 0): \
             the rotation is undetermined",
            matches.len()
        ));
    };
    let finite = fit
        .rotation
        .iter()
        .flatten()
        .chain(&fit.translation)
        .all(|c| c.is_finite());
    if !finite {
        return Err("the rigid fit is not finite".into());
    }
    Ok(fit)
}

/// The pose after `end.t` whose plain ICP step is `fit`, and its matching: the accelerated
/// proposal when there is one and its matching is no worse than the current pose's, else `fit`
/// (and the accelerator restarts).
fn next_pose(
    end: &LoopEnd,
    fit: Rigid,
    accel: Option<&mut super::accelerate::Anderson>,
    matching: &Matching<'_>,
) -> Result<(Rigid, Vec<Match>, MatchStats), RegisterError> {
    if let Some(acc) = accel {
        if let Some(t) = acc.propose(&end.t, &fit) {
            let (m, s) = matching(&t)?;
            if s.kept >= 3 && s.rms_mm <= end.stats.rms_mm {
                return Ok((t, m, s));
            }
            acc.restart();
        }
    }
    let (m, s) = matching(&fit)?;
    Ok((fit, m, s))
}

/// The smallest over the largest eigenvalue of the weighted point-to-plane system of `matches`
/// (rotations about their weighted centroid, scaled by their RMS radius so that both blocks are
/// in millimetres); a match without a normal (a vessel point) counts in all three directions.
pub fn conditioning(matches: &[Match]) -> f64 {
    let wsum: f64 = matches.iter().map(|m| m.weight).sum();
    if wsum.is_nan() || wsum <= 0.0 {
        return 0.0;
    }
    let mut c = [0.0; 3];
    for m in matches {
        for a in 0..3 {
            c[a] += m.weight * m.anchor[a] / wsum;
        }
    }
    let radius = (matches
        .iter()
        .map(|m| m.weight * crate::mesh::vec3::dist2(m.anchor, c))
        .sum::<f64>()
        / wsum)
        .sqrt()
        .max(1e-9);
    let mut h = nalgebra::Matrix6::<f64>::zeros();
    let mut add_row = |w: f64, d: [f64; 3], n: [f64; 3]| {
        let r = crate::mesh::vec3::cross(d, n);
        let g = nalgebra::Vector6::new(
            r[0] / radius,
            r[1] / radius,
            r[2] / radius,
            n[0],
            n[1],
            n[2],
        );
        h += w * g * g.transpose();
    };
    for m in matches {
        let d = crate::mesh::vec3::sub(m.anchor, c);
        let len = crate::mesh::vec3::dot(m.normal, m.normal).sqrt();
        if len > 0.0 {
            add_row(m.weight, d, m.normal.map(|x| x / len));
        } else {
            for e in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] {
                add_row(m.weight, d, e);
            }
        }
    }
    let ev = h.symmetric_eigenvalues();
    let (lo, hi) = ev.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &x| {
        (lo.min(x), hi.max(x))
    });
    if hi > 0.0 { (lo / hi).max(0.0) } else { 0.0 }
}

/// Why a measured point set cannot fix a rotation (one spot, collinear, fewer than 3 points), if so;
/// a collinear set within 2 mm of the origin is said to look like metres.
pub fn degenerate_points(points: &[[f64; 3]]) -> Option<String> {
    if points.len() < 3 {
        return Some(format!(
            "{} usable point(s): at least 3 non-collinear points are needed",
            points.len()
        ));
    }
    let c = points
        .iter()
        .fold(Vector3::zeros(), |a, p| a + Vector3::from(*p))
        / points.len() as f64;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = Vector3::from(*p) - c;
        cov += d * d.transpose();
    }
    cov /= points.len() as f64;
    let e = cov.symmetric_eigenvalues();
    let mut ev = [e[0], e[1], e[2]];
    ev.sort_by(|a, b| b.total_cmp(a));
    if !ev[0].is_finite() || ev[0].max(0.0).sqrt() < SPOT_MM {
        return Some(format!(
            "all {} points on one spot (spread {:.1e} mm): the rotation is undetermined",
            points.len(),
            ev[0].max(0.0).sqrt()
        ));
    }
    let reach = points.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs()));
    if ev[1].max(0.0).sqrt() < COLLINEAR_MM && reach <= METRES_REACH_MM {
        return Some(format!(
            "the {} points spread {:.3} mm (RMS, along a line), every coordinate within \
             {reach:.3} mm of the origin: they look like metres sent as millimetres (a liver \
             spans 150 to 250 mm; multiply by 1000)",
            points.len(),
            ev[0].sqrt()
        ));
    }
    if ev[1].max(0.0).sqrt() < COLLINEAR_MM {
        return Some(format!(
            "the {} points are collinear (spread {:.3} mm along the line, {:.1e} mm across): the \
             rotation about the line is undetermined",
            points.len(),
            ev[0].sqrt(),
            ev[1].max(0.0).sqrt()
        ));
    }
    None
}
