//! The registration pipeline of one case: rigid wICP from the navigation system's coarse start,
//! then (for LIBR) the iterative basis fit re-matching correspondences on the deformed model at
//! every iteration. A [`Prepared`] case (correspondence structures and the LIBR basis) is built once
//! before surgery; [`register`] then answers one set of measurements.

use crate::gcn::abstain::AbstainSignals;
use crate::gcn::infer::LibrPlusCase;
use crate::gcn::io::TrainedModel;
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::{
    Correspondence, CorrespondenceParams, validate_measurements,
};
use crate::register::libr::{self, AdaptiveParams, LibrBasis, LibrInfo, LibrParams};
use crate::register::physics::model::Sites;
use crate::register::physics::{EffectKind, Physics};
use crate::register::prior::{HELD_SIGMA_MM, RigidPrior};
use crate::register::uncertainty::{ErrorEstimate, ErrorFeatures, ErrorModel, FitSummary};
use crate::register::wicp::{WicpParams, WicpResult, wicp};
use crate::register::{Measurements, PreopModel, RegisterError};
use crate::v2s::io::V2sModel;
use crate::v2s::{V2sCase, V2sError};
use std::path::Path;
use std::sync::Arc;

pub mod hold;
pub mod pose;
use std::time::{Duration, Instant};

/// Why a case could not be prepared or a registration did not run, by stage.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// The case's correspondence structures or LIBR basis could not be built.
    #[error(transparent)]
    Case(RegisterError),
    /// The case's SR-GCN could not be prepared for its mesh.
    #[error(transparent)]
    Model(crate::gcn::GcnError),
    /// The measurements were refused, or the rigid stage (wICP) could not run.
    #[error(transparent)]
    Rigid(RegisterError),
    /// The rigid stage found the points degenerate (one spot, a line): LIBR cannot run.
    #[error("the rigid stage found the data degenerate ({reason}); LIBR needs spread-out points")]
    Degenerate {
        /// What the rigid stage found.
        reason: String,
    },
    /// LIBR could not run on these data.
    #[error(transparent)]
    Libr(RegisterError),
    /// LIBR+'s data-consistency refit could not run.
    #[error(transparent)]
    Refit(RegisterError),
    /// LIBR or LIBR+ was asked of a case prepared without a LIBR basis.
    #[error("the case was prepared without a LIBR basis")]
    NoBasis,
    /// Adaptive LIBR was asked of a case prepared without its basis.
    #[error("the case was prepared without adaptive LIBR's basis (method adaptive)")]
    NoAdaptiveBasis,
    /// LIBR+ was asked of a case without an SR-GCN model.
    #[error("the case has no SR-GCN model: LIBR+ needs one (use LIBR)")]
    NoModel,
    /// V2S was asked of a case without a V2S model.
    #[error("the case has no V2S model: the v2s method needs one")]
    NoV2sModel,
    /// The case's V2S network could not be prepared, or its prediction failed.
    #[error(transparent)]
    V2s(V2sError),
    /// The refit was asked with no iterations.
    #[error("refit_iterations is 0")]
    NoRefitIterations,
}

/// Registration method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// No registration: the navigation system's initial alignment and the undeformed model (the
    /// baseline every method must beat; identity when the measurements carry no alignment).
    Initial,
    /// Salient-feature weighted rigid ICP only.
    Rigid,
    /// wICP followed by LIBR.
    Libr,
    /// wICP, LIBR, then the SR-GCN correction (needs a case prepared with a model).
    #[serde(rename = "librplus")]
    LibrPlus,
    /// wICP, then the V2S network's displacement (the paper's data-driven baseline; needs a case
    /// prepared with a V2S model, [`Prepared::with_v2s`]).
    V2s,
    /// wICP followed by adaptive LIBR: control loads resolved finely where the data are, the
    /// prior's strength chosen by the data's evidence ([`crate::register::libr::solve_adaptive`];
    /// needs a case prepared with [`Prepared::with_adaptive`]).
    Adaptive,
}

impl Method {
    /// Name as on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Method::Initial => "initial",
            Method::Rigid => "rigid",
            Method::Libr => "libr",
            Method::LibrPlus => "librplus",
            Method::V2s => "v2s",
            Method::Adaptive => "adaptive",
        }
    }

    /// The method of a name ([`Method::name`]).
    pub fn from_name(name: &str) -> Option<Self> {
        [
            Method::Initial,
            Method::Rigid,
            Method::Libr,
            Method::LibrPlus,
            Method::V2s,
            Method::Adaptive,
        ]
        .into_iter()
        .find(|m| m.name() == name)
    }
}

/// LIBR iterations of LIBR+'s data-consistency refit by default ([`PipelineParams::refit_iterations`]).
pub const REFIT_ITERATIONS: usize = 5;

/// Parameters of the whole pipeline.
#[derive(Debug, Clone)]
pub struct PipelineParams {
    /// Rigid stage (and its correspondence parameters, also used by LIBR).
    pub wicp: WicpParams,
    /// LIBR stage.
    pub libr: LibrParams,
    /// LIBR stops iterating before an iteration that would end past this instant (the service's
    /// time budget); None: no deadline.
    pub deadline: Option<Instant>,
    /// LIBR+ only: most LIBR iterations of the data-consistency refit after the SR-GCN
    /// correction ([`refit`]; 0: none, the network's shape is the answer). Default
    /// [`REFIT_ITERATIONS`].
    pub refit_iterations: usize,
    /// Adaptive LIBR's basis levels, reach and λ search (its iterations and matching are
    /// `libr`'s).
    pub adaptive: AdaptiveParams,
    /// The rigid stage's extra starts and the choice among the poses they reach ([`pose`]).
    pub pose: pose::PoseParams,
    /// The navigation system says the organ is held in place and its start trusted ([`hold`]):
    /// the start is trusted (no pose search) and the surface the data do not see is held.
    /// Default false.
    pub held: bool,
    /// How a held organ's unseen surface is held.
    pub hold: hold::HoldParams,
    /// LIBR+ abstains, answering LIBR's result flagged, when a registration lies outside what
    /// its networks learned (their `abstain.json`, [`crate::gcn::abstain`]). Default true.
    pub abstain: bool,
}

impl Default for PipelineParams {
    fn default() -> Self {
        Self {
            wicp: WicpParams::default(),
            libr: LibrParams::default(),
            deadline: None,
            refit_iterations: REFIT_ITERATIONS,
            adaptive: AdaptiveParams::default(),
            pose: pose::PoseParams::default(),
            held: false,
            hold: hold::HoldParams::default(),
            abstain: true,
        }
    }
}

impl PipelineParams {
    /// The correspondence settings of LIBR's iterations (wICP's, with LIBR's trimming floor; the
    /// robust kernel instead of the trimming for a held organ, or when asked).
    pub fn libr_correspondence(&self) -> CorrespondenceParams {
        CorrespondenceParams {
            trim_floor_mm: self.libr.trim_floor_mm,
            // A held organ's dent leaves large residuals where the tool pushed: the median
            // trimming cuts them, the kernel keeps them at a lower weight.
            robust_kernel: self.libr.robust_kernel
                || self.wicp.correspondence.robust_kernel
                || self.held && !self.hold.trimmed,
            ..self.wicp.correspondence
        }
    }
}

/// A case prepared before surgery.
pub struct Prepared {
    /// The preoperative model.
    pub model: PreopModel,
    /// Correspondence structures.
    pub correspondence: Correspondence,
    /// The LIBR basis (None when only rigid registration is wanted).
    pub basis: Option<LibrBasis>,
    /// Whether the basis came from the disk cache.
    pub basis_from_cache: bool,
    /// The SR-GCN of LIBR+, when the case has one ([`Prepared::with_model`]).
    pub librplus: Option<LibrPlusCase>,
    /// The V2S network, when the case has one ([`Prepared::with_v2s`]).
    pub v2s: Option<V2sCase>,
    /// Adaptive LIBR's multi-level basis, when prepared ([`Prepared::with_adaptive`]).
    pub adaptive: Option<AdaptiveBasis>,
    /// The physics LIBR's model carries (empty: plain LIBR).
    pub physics: Physics,
    /// The error model every registration's estimate comes from (None: no estimate).
    pub error_model: Option<Arc<ErrorModel>>,
    /// Preparation time (s).
    pub seconds: f64,
}

impl Prepared {
    /// Builds the correspondence structures and, with `libr`, loads or builds the basis (cached
    /// in `cache_dir` when given).
    pub fn new(
        model: PreopModel,
        libr: Option<&LibrParams>,
        cache_dir: Option<&Path>,
    ) -> Result<Self, PipelineError> {
        Self::with_physics(model, libr, &Physics::none(), cache_dir)
    }

    /// [`Prepared::new`] with an augmented model: LIBR's basis carries `physics` (its supports,
    /// material and effect columns; see [`crate::register::physics`]), cached per physics.
    pub fn with_physics(
        model: PreopModel,
        libr: Option<&LibrParams>,
        physics: &Physics,
        cache_dir: Option<&Path>,
    ) -> Result<Self, PipelineError> {
        let t0 = Instant::now();
        let correspondence = Correspondence::new(&model).map_err(PipelineError::Case)?;
        let sites = Sites {
            posterior: &model.posterior,
            falciform: &model.falciform,
        };
        let (basis, basis_from_cache) = match (libr, cache_dir) {
            (None, _) => (None, false),
            (Some(p), Some(dir)) => {
                let (b, cached) =
                    LibrBasis::load_or_build_with(&model.mesh, p, physics, sites, dir)
                        .map_err(PipelineError::Case)?;
                (Some(b), cached)
            }
            (Some(p), None) => (
                Some(
                    LibrBasis::build_with(&model.mesh, p, physics, sites)
                        .map_err(PipelineError::Case)?,
                ),
                false,
            ),
        };
        Ok(Self {
            model,
            correspondence,
            basis,
            basis_from_cache,
            librplus: None,
            v2s: None,
            adaptive: None,
            physics: physics.clone(),
            error_model: None,
            seconds: crate::util::secs(t0),
        })
    }

    /// Sets the error model of the case's registrations' estimates (None: none).
    pub fn with_error_model(mut self, model: Option<Arc<ErrorModel>>) -> Self {
        self.error_model = model;
        self
    }

    /// Adds a trained SR-GCN so the case answers [`Method::LibrPlus`].
    pub fn with_model(self, model: Arc<TrainedModel>) -> Result<Self, PipelineError> {
        self.with_models(vec![model])
    }

    /// Adds an ensemble of trained SR-GCNs (their corrections averaged; one member is a single
    /// model) so the case answers [`Method::LibrPlus`].
    pub fn with_models(mut self, models: Vec<Arc<TrainedModel>>) -> Result<Self, PipelineError> {
        let t0 = Instant::now();
        self.librplus =
            Some(LibrPlusCase::new(models, &self.model.mesh).map_err(PipelineError::Model)?);
        self.seconds += crate::util::secs(t0);
        Ok(self)
    }
}

/// Adaptive LIBR's basis of a case: all levels' columns (broadest first) and its parameters.
pub struct AdaptiveBasis {
    /// The multi-level basis ([`LibrBasis::build_levels`]), with the case's physics.
    pub basis: LibrBasis,
    /// The parameters it was built with.
    pub params: AdaptiveParams,
    /// Whether it came from the disk cache.
    pub from_cache: bool,
}

impl Prepared {
    /// Builds (or loads from `cache_dir`) adaptive LIBR's multi-level basis with the case's
    /// physics, so the case answers [`Method::Adaptive`]. `libr` gives the material and the
    /// sampling seed.
    pub fn with_adaptive(
        mut self,
        libr: &LibrParams,
        params: &AdaptiveParams,
        cache_dir: Option<&Path>,
    ) -> Result<Self, PipelineError> {
        params.validate().map_err(PipelineError::Case)?;
        let t0 = Instant::now();
        let sites = Sites {
            posterior: &self.model.posterior,
            falciform: &self.model.falciform,
        };
        let (basis, from_cache) = match cache_dir {
            Some(dir) => LibrBasis::load_or_build_levels(
                &self.model.mesh,
                libr,
                &params.levels,
                &self.physics,
                sites,
                dir,
            ),
            None => LibrBasis::build_levels(
                &self.model.mesh,
                libr,
                &params.levels,
                &self.physics,
                sites,
            )
            .map(|b| (b, false)),
        }
        .map_err(PipelineError::Case)?;
        self.adaptive = Some(AdaptiveBasis {
            basis,
            params: params.clone(),
            from_cache,
        });
        self.seconds += crate::util::secs(t0);
        Ok(self)
    }
}

impl Prepared {
    /// Adds a trained V2S network so the case answers [`Method::V2s`] (its grid and the
    /// preoperative channels are built here, once).
    pub fn with_v2s(mut self, model: Arc<V2sModel>) -> Result<Self, PipelineError> {
        let t0 = Instant::now();
        let m = &self.model;
        self.v2s = Some(
            V2sCase::new(model, &m.mesh, (&m.vessel_points, &m.vessel_segments))
                .map_err(PipelineError::V2s)?,
        );
        self.seconds += crate::util::secs(t0);
        Ok(self)
    }
}

/// How the SR-GCN stage of a LIBR+ registration went.
#[derive(Debug, Clone, PartialEq)]
pub struct CorrectionInfo {
    /// Whether the correction was applied (false: the answer is LIBR's, see `skipped`).
    pub applied: bool,
    /// Why it was not applied.
    pub skipped: Option<String>,
    /// Time of the stage, refit included (s).
    pub seconds: f64,
    /// Of which the network's forward pass (s; 0 when not run).
    pub network_seconds: f64,
    /// The data-consistency refit ([`refit`]), when it ran.
    pub refit: Option<LibrInfo>,
    /// Why the refit failed, when it did (the answer is then the network's shape).
    pub refit_error: Option<String>,
    /// What the registration shows of being outside what the network learned (when the
    /// correction ran).
    pub signals: Option<OutsideSignals>,
    /// The registration was outside what the network learned ([`crate::gcn::abstain`]): the
    /// answer is LIBR's, `skipped` says why.
    pub abstained: bool,
}

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
    meas: &Measurements,
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
    let lp = LibrParams {
        max_iterations: params.refit_iterations,
        ..params.libr
    };
    let cparams = &params.libr_correspondence();
    let corr = &case.correspondence;
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
        },
        |u, t| {
            let inv = t.inverse();
            let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
            corr.match_points(&pts, meas, Some(u), cparams)
                .map(|(m, _)| m)
        },
    )
    .map_err(PipelineError::Refit)
}

/// LIBR+'s stage on LIBR's answer `(u, transform)`: the SR-GCN correction (unless
/// [`correction_mismatch`] or the deadline leaves LIBR's answer), then the data-consistency
/// [`refit`], with the signals of being outside what the network learned
/// ([`OutsideSignals`]). Shared by [`register`] and the evaluation of cached LIBR runs.
#[allow(clippy::too_many_arguments)]
pub fn correct_libr(
    g: &LibrPlusCase,
    case: &Prepared,
    meas: &Measurements,
    params: &PipelineParams,
    u: &[f64],
    transform: &Rigid,
    libr_info: &LibrInfo,
    rigid_prior: Option<&RigidPrior>,
) -> CorrectionOutcome {
    let t1 = Instant::now();
    let cparams = &params.libr_correspondence();
    let late = params
        .deadline
        .is_some_and(|d| Instant::now() + Duration::from_secs_f64(g.expected_seconds()) > d);
    let mut out_u = u.to_vec();
    let mut out_t = *transform;
    let mut network_seconds = 0.0;
    let mut signals = None;
    let mut abstained = false;
    let skipped = if let Some(why) = correction_mismatch(g, case, params) {
        Some(format!("{why}: LIBR's answer"))
    } else if late {
        g.relax_estimate();
        Some(format!(
            "no time left for the SR-GCN correction (about {:.0} ms): LIBR's answer",
            1e3 * g.expected_seconds()
        ))
    } else {
        match g.correct(
            &case.model.mesh,
            &case.correspondence,
            cparams,
            meas,
            u,
            transform,
        ) {
            Ok(c) => {
                network_seconds = c.network_seconds;
                let spread_ratio = c
                    .spread_mm
                    .filter(|_| c.correction_rms_mm > 1e-9)
                    .map(|s| s / c.correction_rms_mm);
                signals = Some(OutsideSignals {
                    spread_mm: c.spread_mm,
                    spread_ratio,
                    correction_rms_mm: c.correction_rms_mm,
                    libr_displacement_mm: rms_mm(u),
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
                        abstained = true;
                        Some(format!("{why}: LIBR's answer"))
                    }
                    None => {
                        out_u = c.u;
                        None
                    }
                }
            }
            Err(e) => Some(format!("SR-GCN correction failed ({e}): LIBR's answer")),
        }
    };
    // The refit, when the correction applied and asked for (it fails only on data LIBR itself
    // fitted, so a failure keeps the network's shape).
    let (refit_info, refit_error) = if skipped.is_none() && params.refit_iterations > 0 {
        match refit(
            case,
            meas,
            params,
            &out_u,
            &out_t,
            params.deadline,
            rigid_prior,
        ) {
            Ok(r) => {
                if let Some(sig) = signals.as_mut() {
                    sig.refit_rms_mm = Some(r.info.rms_mm);
                    sig.refit_shift_mm = Some(node_shift_mm(
                        case.model.mesh.nodes(),
                        (&out_t, &out_u),
                        (&r.image_to_physical, &r.u),
                    ));
                }
                out_u = r.u;
                out_t = r.image_to_physical;
                (Some(r.info), None)
            }
            Err(e) => (None, Some(e.to_string())),
        }
    } else {
        (None, None)
    };
    let seconds = crate::util::secs(t1);
    if skipped.is_none() || abstained {
        g.record_seconds(seconds);
    }
    CorrectionOutcome {
        u: out_u,
        image_to_physical: out_t,
        info: CorrectionInfo {
            applied: skipped.is_none(),
            skipped,
            seconds,
            network_seconds,
            refit: refit_info,
            refit_error,
            signals,
            abstained,
        },
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

/// What [`correct_libr`] returns: LIBR+'s answer (LIBR's when the correction did not apply) and
/// how the stage went.
#[derive(Debug, Clone)]
pub struct CorrectionOutcome {
    /// Node displacements (image frame, node-major).
    pub u: Vec<f64>,
    /// Image → physical transform.
    pub image_to_physical: Rigid,
    /// How the stage went.
    pub info: CorrectionInfo,
}

/// What a LIBR+ registration shows of being outside what its network learned, all computed
/// from the registration itself (no truth): the ensemble's disagreement, the correction's size
/// against LIBR's displacement, and how far the data pushed the corrected shape back.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct OutsideSignals {
    /// The ensemble members' disagreement ([`crate::gcn::infer::Corrected::spread_mm`]).
    pub spread_mm: Option<f64>,
    /// `spread_mm` over `correction_rms_mm` (None for one network or no correction).
    pub spread_ratio: Option<f64>,
    /// RMS over nodes of the network's correction (mm).
    pub correction_rms_mm: f64,
    /// RMS over nodes of LIBR's displacement (mm).
    pub libr_displacement_mm: f64,
    /// LIBR's final weighted residual RMS (mm).
    pub libr_rms_mm: f64,
    /// The refit's final weighted residual RMS (mm), when it ran.
    pub refit_rms_mm: Option<f64>,
    /// RMS over nodes of how far the refit moved the corrected shape (mm), when it ran.
    pub refit_shift_mm: Option<f64>,
}

/// How the V2S stage of a registration went.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct V2sInfo {
    /// The stage: the measured channels on the grid, the network, the interpolation (s).
    pub seconds: f64,
    /// Of which the network and the interpolation to the nodes (s).
    pub network_seconds: f64,
}

/// What a registration returns.
#[derive(Debug, Clone)]
pub struct Registration {
    /// Method run.
    pub method: Method,
    /// Image → physical transform: node i is at `image_to_physical.apply(X_i + u_i)`.
    pub image_to_physical: Rigid,
    /// Node displacements (image frame, node-major 3n; zero for rigid).
    pub u: Vec<f64>,
    /// The rigid stage (from the pose chosen).
    pub rigid: WicpResult,
    /// How the pose was chosen among the rigid stage's starts (None: one start, or every start
    /// reached the same pose).
    pub pose: Option<pose::PoseInfo>,
    /// The LIBR stage, when run.
    pub libr: Option<LibrInfo>,
    /// The SR-GCN stage, for LIBR+.
    pub correction: Option<CorrectionInfo>,
    /// The V2S stage, for V2S.
    pub v2s: Option<V2sInfo>,
    /// The error estimate (when the case has an error model calibrated for the method).
    pub error: Option<ErrorEstimate>,
    /// Total time (s).
    pub seconds: f64,
}

impl Registration {
    /// What the error estimate reads of this registration: the fit's residual (LIBR+'s refit,
    /// else LIBR's, else wICP's), LIBR's strain energy, and the coverage of the answer by the
    /// measured points ([`crate::register::uncertainty::features`]), with each node's distance
    /// to the nearest measured point (mm). None without measured points.
    pub fn error_features(
        &self,
        case: &Prepared,
        boundary: &[bool],
        meas: &Measurements,
    ) -> Option<(ErrorFeatures, Vec<f64>)> {
        let refit = self.correction.as_ref().and_then(|c| c.refit.as_ref());
        let residual = refit
            .or(self.libr.as_ref())
            .map_or(self.rigid.rms_mm, |i| i.rms_mm);
        crate::register::uncertainty::features(
            case.model.mesh.nodes(),
            boundary,
            &self.u,
            &self.image_to_physical,
            meas,
            FitSummary {
                residual_rms_mm: residual,
                rigid_rms_mm: self.rigid.rms_mm,
                strain_energy_uj: self.libr.as_ref().map_or(0.0, |i| i.strain_energy_uj),
            },
        )
    }

    fn estimated(mut self, case: &Prepared, meas: &Measurements) -> Self {
        let t0 = Instant::now();
        self.estimate_error(case, meas);
        let dt = crate::util::secs(t0);
        if let Some(e) = &mut self.error {
            e.seconds = dt;
        }
        self.seconds += dt;
        self
    }

    /// Fills [`Registration::error`] from the case's error model (left None when the case has
    /// none, it has no calibration for the method, or the case carries physics effects: the
    /// model is calibrated on plain LIBR).
    pub fn estimate_error(&mut self, case: &Prepared, meas: &Measurements) {
        let Some(model) = &case.error_model else {
            return;
        };
        if !case.physics.effects.is_empty() {
            // Calibrated on plain LIBR: an augmented model's fit is another estimator.
            return;
        }
        // LIBR+ whose correction was skipped answered with LIBR's result.
        let answered_by = match (&self.correction, self.method) {
            (Some(c), Method::LibrPlus) if !c.applied => Method::Libr,
            (_, m) => m,
        };
        if !model.methods.contains_key(answered_by.name()) {
            return;
        }
        if let Some((f, d)) = self.error_features(case, &case.model.boundary_flags(), meas) {
            self.error = model.estimate(answered_by.name(), &f, &d);
        }
    }
}

/// The rigid stage's parameters for a case: the pipeline's, with the start trusted to
/// [`HELD_SIGMA_MM`] when the organ is held ([`PipelineParams::held`], or the case's physics
/// holds it: a `fixation` or `ligament` effect) and no uncertainty was declared.
pub fn rigid_params(case: &Prepared, params: &PipelineParams) -> WicpParams {
    let held = params.held
        || case
            .physics
            .effects
            .iter()
            .any(|e| matches!(e.kind, EffectKind::Fixation | EffectKind::Ligament));
    WicpParams {
        trusted_alignment_mm: params
            .wicp
            .trusted_alignment_mm
            .or(held.then_some(HELD_SIGMA_MM)),
        ..params.wicp
    }
}

/// Why LIBR+'s correction is outside what its network learned, so that LIBR's answer stands:
/// a network trained on a LIBR with other physics ([`LibrPlusCase::mismatch`]), or a held organ
/// ([`PipelineParams::held`]): the network learned the residual of free-floating LIBR on organs
/// that are not held, and after the held fit its correction made things worse (pattern H seed
/// 302: LIBR held 5.26 mm mean TRE, corrected 11.95, doing nothing 6.66).
pub fn correction_mismatch(
    g: &LibrPlusCase,
    case: &Prepared,
    params: &PipelineParams,
) -> Option<String> {
    g.mismatch(&case.physics).or_else(|| {
        params.held.then(|| {
            "the organ is held: the SR-GCN learned the residual of LIBR on free organs, not of the held fit".to_string()
        })
    })
}

/// The hold of a held organ at `pose` ([`hold::hold`]); None when the organ is not said to be
/// held.
fn held_at(
    case: &Prepared,
    meas: &Measurements,
    params: &PipelineParams,
    pose: &Rigid,
) -> Result<Option<libr::Hold>, PipelineError> {
    if !params.held {
        return Ok(None);
    }
    hold::hold(&case.model, meas, pose, &params.hold)
        .map(Some)
        .map_err(PipelineError::Libr)
}

/// Registers measurements to a prepared case.
pub fn register(
    case: &Prepared,
    meas: &Measurements,
    method: Method,
    params: &PipelineParams,
) -> Result<Registration, PipelineError> {
    let t0 = Instant::now();
    validate_measurements(meas).map_err(PipelineError::Rigid)?;
    let n = case.model.mesh.num_nodes();
    let wparams = rigid_params(case, params);
    let v2s = match method {
        Method::V2s => Some(case.v2s.as_ref().ok_or(PipelineError::NoV2sModel)?),
        _ => None,
    };
    let rigid_params = if method == Method::Initial {
        // No iterations: the start, with its match statistics.
        WicpParams {
            max_iterations: 0,
            min_conditioning: 0.0,
            ..wparams
        }
    } else {
        wparams
    };
    // The rigid stage: from the navigation start alone for the baseline, else from every start
    // of the pose search (distinct poses, the navigation start's first).
    let t_rigid = Instant::now();
    // With a gate on the search, a deformable method first fits from the navigation start alone
    // and searches only when that fit scores badly.
    let gated = params.pose.search_above_mm2 > 0.0
        && !matches!(method, Method::Rigid | Method::Initial | Method::V2s);
    let candidates = if method == Method::Initial || gated {
        let r = wicp(&case.model, &case.correspondence, meas, &rigid_params)
            .map_err(PipelineError::Rigid)?;
        pose::Candidates {
            poses: vec![r],
            starts: 1,
            distinct: 1,
        }
    } else {
        pose::rigid_candidates(
            &case.model,
            &case.correspondence,
            meas,
            &rigid_params,
            &params.pose,
        )
        .map_err(PipelineError::Rigid)?
    };
    let mut search_seconds = crate::util::secs(t_rigid);
    let rigid_scores = |poses: &[WicpResult]| -> Result<Vec<f64>, PipelineError> {
        poses
            .iter()
            .map(|r| {
                pose::score(
                    &case.correspondence,
                    meas,
                    &rigid_params.correspondence,
                    None,
                    &r.image_to_physical,
                    params.pose.cap_mm,
                )
                .map_err(PipelineError::Rigid)
            })
            .collect()
    };
    if matches!(method, Method::Rigid | Method::Initial | Method::V2s) {
        // No deformable fit to score the poses by: their rigid scores decide.
        let (rigid, pose) = if candidates.poses.len() > 1 {
            let scores = rigid_scores(&candidates.poses)?;
            let poses: Vec<Rigid> = candidates
                .poses
                .iter()
                .map(|r| r.image_to_physical)
                .collect();
            let info = pose::choose(
                &case.model,
                &poses,
                &scores,
                &vec![0.0; scores.len()],
                candidates.starts,
                candidates.distinct,
                &params.pose,
            );
            let mut c = candidates.poses;
            let info = pose::PoseInfo {
                rigid_seconds: search_seconds,
                ..info
            };
            (c.swap_remove(info.chosen), Some(info))
        } else {
            (candidates.poses.into_iter().next().expect("one pose"), None)
        };
        if let Some(v) = v2s {
            // V2S reads the points after the rigid stage, as V2S-Net assumes a rigid alignment.
            let t1 = Instant::now();
            let (u, network_seconds) = v
                .displacement(meas, &rigid.image_to_physical)
                .map_err(PipelineError::V2s)?;
            return Ok(Registration {
                method,
                image_to_physical: rigid.image_to_physical,
                u,
                rigid,
                pose,
                libr: None,
                correction: None,
                v2s: Some(V2sInfo {
                    seconds: crate::util::secs(t1),
                    network_seconds,
                }),
                error: None,
                seconds: crate::util::secs(t0),
            }
            .estimated(case, meas));
        }
        return Ok(Registration {
            method,
            image_to_physical: rigid.image_to_physical,
            u: vec![0.0; 3 * n],
            rigid,
            pose,
            libr: None,
            correction: None,
            v2s: None,
            error: None,
            seconds: crate::util::secs(t0),
        }
        .estimated(case, meas));
    }
    if let Some(reason) = &candidates.poses[0].degenerate {
        return Err(PipelineError::Degenerate {
            reason: reason.clone(),
        });
    }
    let cparams = &params.libr_correspondence();
    let corr = &case.correspondence;
    let rematch = |u: &[f64], t: &Rigid| {
        let inv = t.inverse();
        let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
        corr.match_points(&pts, meas, Some(u), cparams)
            .map(|(m, _)| m)
    };
    let gcn = match method {
        Method::LibrPlus => Some(case.librplus.as_ref().ok_or(PipelineError::NoModel)?),
        _ => None,
    };
    // LIBR+ leaves the correction its expected time before the deadline.
    let libr_deadline = match (params.deadline, gcn) {
        (Some(d), Some(g)) => Some(
            d.checked_sub(Duration::from_secs_f64(g.expected_seconds()))
                .unwrap_or(d),
        ),
        (d, _) => d,
    };
    // The deformable fit from one rigid pose.
    let deform = |rigid: &WicpResult| -> Result<libr::LibrSolution, PipelineError> {
        let held = held_at(case, meas, params, &rigid.image_to_physical)?;
        let run = libr::RunLimits {
            active: Some(corr.active_nodes()),
            deadline: libr_deadline,
            offset: None,
            // A held organ is anchored by its hold: the fit's rigid correction is then free to
            // carry the rigid part the free-floating basis leaves out of a dent (a trusted
            // pose prior against it made the held fits worse than doing nothing).
            rigid_prior: if held.is_some() {
                None
            } else {
                rigid.prior.as_ref()
            },
            hold: held.as_ref(),
        };
        if method == Method::Adaptive {
            let ad = case
                .adaptive
                .as_ref()
                .ok_or(PipelineError::NoAdaptiveBasis)?;
            libr::solve_adaptive(
                &case.model.mesh,
                &ad.basis,
                ad.params.levels[0].0,
                &params.libr,
                &ad.params,
                &meas.points,
                &rigid.image_to_physical,
                run,
                rematch,
            )
        } else {
            let basis = case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
            libr::solve_with_limits(
                &case.model.mesh,
                basis,
                &params.libr,
                &meas.points,
                &rigid.image_to_physical,
                run,
                rematch,
            )
        }
        .map_err(PipelineError::Libr)
    };
    let fitted_score = |sol: &libr::LibrSolution| -> Result<f64, PipelineError> {
        let s = pose::score(
            corr,
            meas,
            cparams,
            Some(&sol.u),
            &sol.image_to_physical,
            params.pose.cap_mm,
        )
        .map_err(PipelineError::Libr)?;
        Ok(s + params.pose.energy_weight * sol.info.prior_mm2)
    };
    // The gate: the navigation start's fit, kept when it scores well (or no search can run).
    let mut candidates = candidates;
    let mut first_fit: Option<libr::LibrSolution> = None;
    if gated {
        let sol = deform(&candidates.poses[0])?;
        if pose::searchable(&candidates.poses[0], &rigid_params, &params.pose)
            && fitted_score(&sol)? > params.pose.search_above_mm2
        {
            let t = Instant::now();
            let first = candidates.poses.swap_remove(0);
            // The search keeps the navigation start's wICP first: its fit is the one just made.
            candidates = pose::candidates_from(
                first,
                &case.model,
                &case.correspondence,
                meas,
                &rigid_params,
                &params.pose,
            )
            .map_err(PipelineError::Rigid)?;
            search_seconds += crate::util::secs(t);
        }
        first_fit = Some(sol);
    }
    // Every candidate pose through the fit, scored on what it leaves; the best wins.
    let (rigid, sol, pose) = if candidates.poses.len() == 1 {
        let rigid = candidates.poses.into_iter().next().expect("one pose");
        let sol = match first_fit {
            Some(s) => s,
            None => deform(&rigid)?,
        };
        (rigid, sol, None)
    } else {
        use rayon::prelude::*;
        let fitted: Vec<Result<(libr::LibrSolution, f64), PipelineError>> = candidates
            .poses
            .par_iter()
            .enumerate()
            .map(|(k, r)| {
                let sol = match (k, &first_fit) {
                    (0, Some(s)) => s.clone(),
                    _ => deform(r)?,
                };
                let score = fitted_score(&sol)?;
                Ok((sol, score))
            })
            .collect();
        let mut sols = Vec::new();
        let mut scores = Vec::new();
        let mut priors = Vec::new();
        for (k, f) in fitted.into_iter().enumerate() {
            match f {
                Ok((sol, score)) => {
                    scores.push(score);
                    priors.push(sol.info.prior_mm2);
                    sols.push(Some(sol));
                }
                // The navigation start's fit failing fails the registration as before; another
                // start's failure only drops that start.
                Err(e) if k == 0 => return Err(e),
                Err(_) => {
                    scores.push(f64::INFINITY);
                    priors.push(0.0);
                    sols.push(None);
                }
            }
        }
        let poses: Vec<Rigid> = sols
            .iter()
            .zip(&candidates.poses)
            .map(|(s, r)| {
                s.as_ref()
                    .map_or(r.image_to_physical, |s| s.image_to_physical)
            })
            .collect();
        let info = pose::choose(
            &case.model,
            &poses,
            &scores,
            &priors,
            candidates.starts,
            candidates.distinct,
            &params.pose,
        );
        let info = pose::PoseInfo {
            rigid_seconds: search_seconds,
            ..info
        };
        let mut rs = candidates.poses;
        let rigid = rs.swap_remove(info.chosen);
        let sol = sols
            .swap_remove(info.chosen)
            .expect("the chosen pose was fitted");
        (rigid, sol, Some(info))
    };
    let mut u = sol.u;
    let mut image_to_physical = sol.image_to_physical;
    let correction = gcn.map(|g| {
        let out = correct_libr(
            g,
            case,
            meas,
            params,
            &u,
            &image_to_physical,
            &sol.info,
            rigid.prior.as_ref(),
        );
        u = out.u;
        image_to_physical = out.image_to_physical;
        out.info
    });
    Ok(Registration {
        method,
        image_to_physical,
        u,
        rigid,
        pose,
        libr: Some(sol.info),
        correction,
        v2s: None,
        error: None,
        seconds: crate::util::secs(t0),
    }
    .estimated(case, meas))
}
