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
//! Garbage in gives an error naming the field (no points, length mismatches, non-finite values,
//! most points more than `max_distance_mm` from the model after the initial alignment) or a result
//! flagged `degenerate` with the transform left where it was (all points on one spot, collinear
//! points, fewer than three pairs left, a rank-deficient fit) — never NaN.

use super::RegisterError;
use std::time::Instant;

use nalgebra::{Matrix3, Vector3};

use super::PreopModel;
use super::correspondence::{
    Correspondence, CorrespondenceParams, MatchStats, validate_measurements,
};
use super::{MeasuredKind, Measurements};
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
}

impl Default for WicpParams {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            tolerance_mm: 1e-3,
            correspondence: CorrespondenceParams::default(),
            surface_only: false,
        }
    }
}

/// Result of [`wicp`].
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
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
    /// Wall-clock time (s).
    pub seconds: f64,
}

/// RMS spread (mm) across the principal line below which measured points count as collinear:
/// with tracking noise of about a millimetre, points within a couple of millimetres of a line (a
/// stylus swiped along one stroke) cannot fix the rotation about it, and a fit would turn on the
/// noise alone (a line with 0.2 mm jitter came out 80° off before this bound).
const COLLINEAR_MM: f64 = 2.0;
/// RMS spread (mm) below which measured points count as one spot.
const SPOT_MM: f64 = 1e-3;

/// Rigid salient-feature weighted ICP of `meas` (physical frame) to the undeformed `model`; `corr`
/// must have been built from `model`. See the module doc.
pub fn wicp(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Measurements,
    params: &WicpParams,
) -> Result<WicpResult, RegisterError> {
    let clock = Instant::now();
    validate_measurements(meas)?;
    params.correspondence.validate()?;
    if !(params.tolerance_mm.is_finite() && params.tolerance_mm >= 0.0) {
        return Err(RegisterError::Parameter(format!(
            "wicp parameter tolerance_mm must be finite and ≥ 0, got {}",
            params.tolerance_mm
        )));
    }
    if corr.num_nodes() != model.mesh.num_nodes() {
        return Err(RegisterError::Inconsistent(format!(
            "the correspondence was built for {} nodes, the model has {}",
            corr.num_nodes(),
            model.mesh.num_nodes()
        )));
    }
    // Clements' data: the anterior-surface points alone, when asked and there are enough.
    let mut warnings = Vec::new();
    let surface;
    let meas = if params.surface_only {
        let keep: Vec<usize> = (0..meas.points.len())
            .filter(|&i| meas.kind[i] == MeasuredKind::Surface)
            .collect();
        if keep.len() >= 3 {
            surface = Measurements {
                points: keep.iter().map(|&i| meas.points[i]).collect(),
                kind: vec![MeasuredKind::Surface; keep.len()],
                feature: if meas.feature.is_empty() {
                    Vec::new()
                } else {
                    keep.iter().map(|&i| meas.feature[i]).collect()
                },
                initial_alignment: meas.initial_alignment,
            };
            &surface
        } else {
            warnings.push(format!(
                "{} anterior-surface point(s): the rigid stage used every point instead of the \
                 surface alone",
                keep.len()
            ));
            meas
        }
    } else {
        meas
    };
    let start = meas.initial_alignment.unwrap_or_default();
    let cap = params.correspondence.max_distance_mm;
    let to_image = |t: &Rigid| -> Vec<[f64; 3]> {
        let inv = t.inverse();
        meas.points.iter().map(|&p| inv.apply(p)).collect()
    };

    // Points far from the model after the initial alignment.
    let start_image = to_image(&start);
    let dist: Vec<f64> = start_image
        .iter()
        .map(|&p| corr.distance_to_boundary(p))
        .collect();
    let far: Vec<usize> = (0..dist.len()).filter(|&i| dist[i] > cap).collect();
    let npts = meas.points.len();
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

    let corr_params = &params.correspondence;
    let matching = |t: &Rigid| corr.match_points(&to_image(t), meas, None, corr_params);
    let (_, initial_stats) = matching(&start)?;
    let mut result = WicpResult {
        image_to_physical: start,
        rms_mm: initial_stats.rms_mm,
        initial_rms_mm: initial_stats.rms_mm,
        iterations: 0,
        converged: false,
        matched: initial_stats.kept,
        trimmed: initial_stats.trimmed,
        far: far.len(),
        stats: initial_stats,
        degenerate: None,
        warnings,
        seconds: 0.0,
    };

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

    let mut t = start;
    let mut prev_rms = f64::INFINITY;
    let mut stats = initial_stats;
    let mut matches;
    (matches, _) = matching(&t)?;
    loop {
        if (prev_rms - stats.rms_mm).abs() < params.tolerance_mm {
            result.converged = true;
            break;
        }
        if result.iterations >= params.max_iterations {
            break;
        }
        if matches.len() < 3 {
            result.degenerate = Some(format!(
                "only {} pair(s) left after trimming ({} trimmed, {} unmatched): at least 3 are \
                 needed",
                matches.len(),
                stats.trimmed,
                stats.unmatched
            ));
            break;
        }
        let src: Vec<[f64; 3]> = matches.iter().map(|m| m.anchor).collect();
        let dst: Vec<[f64; 3]> = matches.iter().map(|m| meas.points[m.point]).collect();
        let w: Vec<f64> = matches.iter().map(|m| m.weight).collect();
        let Some(fit) = Rigid::fit(&src, &dst, Some(&w)) else {
            result.degenerate = Some(format!(
                "the {} matched model points are collinear or coincident (or all weights are 0): \
                 the rotation is undetermined",
                matches.len()
            ));
            break;
        };
        let fit_ok = fit
            .rotation
            .iter()
            .flatten()
            .chain(&fit.translation)
            .all(|c| c.is_finite());
        if !fit_ok {
            result.degenerate = Some("the rigid fit is not finite".into());
            break;
        }
        result.iterations += 1;
        let (m, s) = matching(&fit)?;
        prev_rms = stats.rms_mm;
        t = fit;
        matches = m;
        stats = s;
    }
    result.image_to_physical = t;
    result.rms_mm = stats.rms_mm;
    result.matched = stats.kept;
    result.trimmed = stats.trimmed;
    result.stats = stats;
    result.seconds = clock.elapsed().as_secs_f64();
    Ok(result)
}

/// Why a measured point set cannot fix a rotation (one spot, collinear, fewer than 3 points), if so.
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
