//! LIBR+'s stage on LIBR's answer: the SR-GCN correction ([`correct_libr`]) and the
//! data-consistency [`refit`] that puts the corrected shape back onto the measurements.

use super::{
    CorrectionInfo, CorrectionOutcome, OutsideSignals, PipelineError, PipelineParams, Prepared,
    correction_mismatch,
};
use crate::gcn::abstain::AbstainSignals;
use crate::gcn::infer::LibrPlusCase;
use crate::gcn::sample::Registered;
use crate::mesh::rigid::Rigid;
use crate::register::Checked;
use crate::register::libr::{self, LibrInfo};
use crate::register::prior::RigidPrior;
use std::time::{Duration, Instant};

/// LIBR+'s data-consistency refit: LIBR started from the SR-GCN's corrected shape `u_start`
/// (image frame, `transform` image → physical), which stays as an offset, while the basis
/// weights (regularised by their strain energy as in LIBR) and the rigid transform fit what the
/// correction left of the misfit to the measurements, re-matching every iteration; at most
/// `params.refit_iterations` (≥ 1) iterations, stopping before one that would end past
/// `deadline`.
///
/// The network learns LIBR's residual from training data and does not see the measurements
/// exactly; its correction moves the measured surface off the points (on held-out livers the
/// mean distance of the measured points grew from 0.95 to 1.14 mm). The refit puts the shape
/// back onto them with LIBR's smooth elastic modes and keeps the correction where no data are.
pub fn refit(
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
    u_start: &[f64],
    transform: &Rigid,
    deadline: Option<Instant>,
    rigid_prior: Option<&RigidPrior>,
) -> Result<libr::LibrSolution, PipelineError> {
    let basis = case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
    if params.refit_iterations == 0 {
        return Err(PipelineError::NoRefitIterations);
    }
    let mut lp = params.libr;
    lp.fit.max_iterations = params.refit_iterations;
    let cparams = &params.libr_correspondence();
    let corr = &case.correspondence;
    // Each search starts from the triangle the point matched last time (same matches).
    let mut hints = crate::register::correspondence::Hints::default();
    libr::solve_with_limits(
        &case.model.mesh,
        basis,
        &lp,
        &meas.points,
        transform,
        libr::RunLimits {
            active: Some(corr.active_nodes()),
            deadline,
            offset: Some(u_start),
            rigid_prior,
            // The refit keeps the correction's shape where no data are: nothing more to hold.
            hold: None,
            held_out: None,
        },
        |u, t| {
            let inv = t.inverse();
            let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
            corr.match_points_hinted(&pts, meas, Some(u), cparams, &mut hints)
                .map(|(m, _)| m)
        },
    )
    .map_err(PipelineError::Refit)
}

/// LIBR's answer as LIBR+'s stage starts from it.
#[derive(Debug, Clone, Copy)]
pub struct LibrAnswer<'a> {
    /// Node displacements (image frame, mm, node-major `3n`).
    pub u: &'a [f64],
    /// Image → physical transform.
    pub image_to_physical: &'a Rigid,
    /// LIBR's iterations and residuals.
    pub info: &'a LibrInfo,
    /// The rigid stage's prior on the pose, when it had one (the refit keeps it).
    pub rigid_prior: Option<&'a RigidPrior>,
}

/// LIBR+'s stage on LIBR's answer: the SR-GCN correction (unless [`correction_mismatch`] or the
/// deadline leaves LIBR's answer), then the data-consistency [`refit`], with the signals of
/// being outside what the network learned ([`OutsideSignals`]). Shared by [`super::register`]
/// and the evaluation of cached LIBR runs.
pub fn correct_libr(
    g: &LibrPlusCase,
    case: &Prepared,
    meas: &Checked,
    params: &PipelineParams,
    libr: LibrAnswer<'_>,
) -> CorrectionOutcome {
    let LibrAnswer {
        u,
        image_to_physical: transform,
        info: libr_info,
        rigid_prior,
    } = libr;
    let t1 = Instant::now();
    let mut stage = Stage {
        u: u.to_vec(),
        transform: *transform,
        network_seconds: 0.0,
        signals: None,
        abstained: false,
    };
    let skipped = match skip_reason(g, case, params) {
        Some(why) => Some(why),
        None => stage.network(g, case, meas, params, libr_info),
    };
    // The refit, when the correction applied and asked for (it fails only on data LIBR itself
    // fitted, so a failure keeps the network's shape).
    let (refit_info, refit_error) = if skipped.is_none() && params.refit_iterations > 0 {
        stage.refit(case, meas, params, rigid_prior)
    } else {
        (None, None)
    };
    let seconds = crate::util::secs(t1);
    if skipped.is_none() || stage.abstained {
        g.record_seconds(seconds);
    }
    CorrectionOutcome {
        u: stage.u,
        image_to_physical: stage.transform,
        info: CorrectionInfo {
            applied: skipped.is_none(),
            skipped,
            seconds,
            network_seconds: stage.network_seconds,
            refit: refit_info,
            refit_error,
            signals: stage.signals,
            abstained: stage.abstained,
        },
    }
}

/// Why the network is not run at all: the case's physics or a held organ lie outside what it
/// learned, or the deadline leaves it no time.
fn skip_reason(g: &LibrPlusCase, case: &Prepared, params: &PipelineParams) -> Option<String> {
    if let Some(why) = correction_mismatch(g, case, params) {
        return Some(format!("{why}: LIBR's answer"));
    }
    let late = params
        .deadline
        .is_some_and(|d| Instant::now() + Duration::from_secs_f64(g.expected_seconds()) > d);
    if !late {
        return None;
    }
    g.relax_estimate();
    Some(format!(
        "no time left for the SR-GCN correction (about {:.0} ms): LIBR's answer",
        1e3 * g.expected_seconds()
    ))
}

/// LIBR+'s answer as its stage builds it: LIBR's until the correction applies.
struct Stage {
    u: Vec<f64>,
    transform: Rigid,
    network_seconds: f64,
    signals: Option<OutsideSignals>,
    abstained: bool,
}

impl Stage {
    /// The network's correction of LIBR's answer, unless the registration is outside what it
    /// learned (abstained) or it fails; returns why it was not applied.
    fn network(
        &mut self,
        g: &LibrPlusCase,
        case: &Prepared,
        meas: &Checked,
        params: &PipelineParams,
        libr_info: &LibrInfo,
    ) -> Option<String> {
        let cparams = &params.libr_correspondence();
        let c = match g.correct(&Registered {
            mesh: &case.model.mesh,
            correspondence: &case.correspondence,
            cparams,
            meas,
            u: &self.u,
            transform: &self.transform,
        }) {
            Ok(c) => c,
            Err(e) => return Some(format!("SR-GCN correction failed ({e}): LIBR's answer")),
        };
        self.network_seconds = c.network_seconds;
        let spread_ratio = c
            .spread_mm
            .filter(|_| c.correction_rms_mm > 1e-9)
            .map(|s| s / c.correction_rms_mm);
        self.signals = Some(OutsideSignals {
            spread_mm: c.spread_mm,
            spread_ratio,
            correction_rms_mm: c.correction_rms_mm,
            libr_displacement_mm: rms_mm(&self.u),
            libr_rms_mm: libr_info.rms_mm,
            refit_rms_mm: None,
            refit_shift_mm: None,
        });
        let why = g.abstain_rule().filter(|_| params.abstain).and_then(|r| {
            r.outside(&AbstainSignals {
                spread_ratio,
                libr_rms_mm: libr_info.rms_mm,
            })
        });
        match why {
            Some(why) => {
                self.abstained = true;
                Some(format!("{why}: LIBR's answer"))
            }
            None => {
                self.u = c.u;
                None
            }
        }
    }

    /// The data-consistency refit of the corrected shape: its info, or why it failed (the
    /// answer then stays the network's shape).
    fn refit(
        &mut self,
        case: &Prepared,
        meas: &Checked,
        params: &PipelineParams,
        rigid_prior: Option<&RigidPrior>,
    ) -> (Option<LibrInfo>, Option<String>) {
        let r = match refit(
            case,
            meas,
            params,
            &self.u,
            &self.transform,
            params.deadline,
            rigid_prior,
        ) {
            Ok(r) => r,
            Err(e) => return (None, Some(e.to_string())),
        };
        if let Some(sig) = self.signals.as_mut() {
            sig.refit_rms_mm = Some(r.info.rms_mm);
            sig.refit_shift_mm = Some(node_shift_mm(
                case.model.mesh.nodes(),
                (&self.transform, &self.u),
                (&r.image_to_physical, &r.u),
            ));
        }
        self.u = r.u;
        self.transform = r.image_to_physical;
        (Some(r.info), None)
    }
}

/// RMS over nodes of a node-major displacement (mm).
fn rms_mm(u: &[f64]) -> f64 {
    let n = (u.len() / 3).max(1) as f64;
    (u.iter().map(|x| x * x).sum::<f64>() / n).sqrt()
}

/// RMS over nodes of the distance between two placements `T(X + u)` of the same nodes (mm).
fn node_shift_mm(nodes: &[[f64; 3]], a: (&Rigid, &[f64]), b: (&Rigid, &[f64])) -> f64 {
    let place = |t: &Rigid, u: &[f64], i: usize, x: &[f64; 3]| {
        t.apply([x[0] + u[3 * i], x[1] + u[3 * i + 1], x[2] + u[3 * i + 2]])
    };
    let ss: f64 = nodes
        .iter()
        .enumerate()
        .map(|(i, x)| {
            let (p, q) = (place(a.0, a.1, i, x), place(b.0, b.1, i, x));
            (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)
        })
        .sum();
    (ss / nodes.len().max(1) as f64).sqrt()
}
