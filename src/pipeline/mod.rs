//! The registration pipeline of one case: rigid wICP from the navigation system's coarse start,
//! then (for LIBR) the iterative basis fit re-matching correspondences on the deformed model at
//! every iteration. A [`Prepared`] case (correspondence structures and the LIBR basis) is built once
//! before surgery; [`register`] then answers one set of measurements.

use crate::gcn::infer::LibrPlusCase;
use crate::gcn::io::TrainedModel;
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::{Correspondence, CorrespondenceParams};
use crate::register::libr::{self, AdaptiveParams, LibrBasis, LibrInfo, LibrParams};
use crate::register::nonlinear::NonlinearMap;
use crate::register::physics::Physics;
use crate::register::physics::kinds::Hold;
use crate::register::physics::model::Sites;
use crate::register::prior::HELD_SIGMA_MM;
use crate::register::reduce::Reduction;
use crate::register::uncertainty::{ErrorEstimate, ErrorFeatures, ErrorModel, FitSummary};
use crate::register::wicp::{WicpParams, WicpResult};
use crate::register::{Checked, PreopModel, RegisterError};
use crate::v2s::io::V2sModel;
use crate::v2s::{V2sCase, V2sError};
use std::path::Path;
use std::sync::Arc;

pub mod auto;
mod correct;
pub mod hold;
pub mod pose;
pub mod progressive;
pub mod quality;
mod run;
pub mod side;
pub use correct::{LibrAnswer, correct_libr, refit};
pub use progressive::register_progressive;
use std::time::Instant;

/// Registers measurements to a prepared case ([`Method::Auto`]: every candidate, the one that
/// best predicts the points it did not see chosen, [`auto`]).
pub fn register(
    case: &Prepared,
    meas: &Checked,
    method: Method,
    params: &PipelineParams,
) -> Result<Registration, PipelineError> {
    register_with(case, meas, method, params, None)
}

/// A registration's provisional answer, handed over before the registration goes on
/// ([`progressive`]).
pub type FirstAnswer<'a> = &'a (dyn Fn(&Registration) + Sync);

/// [`register`], handing the linear answer of [`Method::Nonlinear`] to `first` (with
/// [`Registration::refinement_follows`] set) before its refinement runs.
pub(crate) fn register_with(
    case: &Prepared,
    meas: &Checked,
    method: Method,
    params: &PipelineParams,
    first: Option<FirstAnswer<'_>>,
) -> Result<Registration, PipelineError> {
    let t0 = Instant::now();
    let reduced = reduce_points(case, meas, method, params).map_err(PipelineError::Rigid)?;
    let meas = reduced.as_ref().map_or(meas, |(m, _)| m);
    // The side the surface patch lies on, decided once for every stage (not for doing nothing).
    let side = match method {
        Method::Initial => None,
        _ => side::choose(case, meas, params)?,
    };
    let (params, start) = match &side {
        Some((info, start)) => (side::params_for(params, info.target), Some(start)),
        None => (params.clone(), None),
    };
    let surface = side.as_ref().map(|(info, _)| info.clone());
    let points = reduced.as_ref().map(|(_, r)| *r);
    // The provisional answer says what the final one will of the side and the points.
    let wrapped = |r: &Registration| {
        let mut r = r.clone();
        r.surface = surface.clone();
        r.points = points;
        r.seconds = crate::util::secs(t0);
        first.expect("called only when set")(&r)
    };
    let mut reg = if method == Method::Auto {
        auto::register_auto(case, meas, &params, start)?
    } else {
        let first = first.map(|_| &wrapped as FirstAnswer<'_>);
        let shared = run::Shared {
            folds: None,
            start,
            first,
        };
        run::register_scored(case, meas, method, &params, shared)?
    };
    reg.surface = surface;
    reg.points = points;
    // The side test's time counts in the registration's.
    reg.seconds = crate::util::secs(t0);
    Ok(reg)
}

/// The measurements every stage of `method` registers: the surface cloud reduced per
/// [`PipelineParams::reduce_above`] (None: as received; doing nothing reads no points). The
/// cells start at a quarter of the model's mean boundary edge.
fn reduce_points(
    case: &Prepared,
    meas: &Checked,
    method: Method,
    params: &PipelineParams,
) -> Result<Option<(Checked, Reduction)>, RegisterError> {
    if method == Method::Initial || params.reduce_above == 0.0 {
        return Ok(None);
    }
    if !(params.reduce_above.is_finite() && params.reduce_above > 0.0) {
        return Err(RegisterError::Parameter(format!(
            "pipeline reduce_above must be finite and >= 0, got {}",
            params.reduce_above
        )));
    }
    let corr = &case.correspondence;
    let triangles = corr.surface_triangles(&params.wicp.correspondence);
    let budget = ((params.reduce_above * triangles as f64).ceil() as usize).max(REDUCE_FLOOR);
    crate::register::reduce::reduce_to_budget(meas, budget, || 0.25 * corr.mean_boundary_edge_mm())
}

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
    /// The nonlinear model could not be built, or its refinement could not run.
    #[error("nonlinear refinement: {0}")]
    Nonlinear(RegisterError),
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
    /// The nonlinear refinement of the deformable fit ([`libr::refine_nonlinear`]): adaptive
    /// LIBR's answer (LIBR's when the case has no adaptive basis) fitted again through the
    /// geometrically nonlinear model of the case, kept only where it fits the data and prior
    /// better ([`Prepared::nonlinear_model`]).
    Nonlinear,
    /// The method chosen per registration from the data ([`auto`]): doing nothing, the rigid
    /// answer, LIBR, adaptive LIBR (when prepared) and, with a trusted start, their held
    /// variants, each scored by how well it predicts measured points it did not see.
    Auto,
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
            Method::Nonlinear => "nonlinear",
            Method::Auto => "auto",
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
            Method::Nonlinear,
            Method::Auto,
        ]
        .into_iter()
        .find(|m| m.name() == name)
    }
}

/// LIBR iterations of LIBR+'s data-consistency refit by default ([`PipelineParams::refit_iterations`]).
pub const REFIT_ITERATIONS: usize = 5;

/// The point budget, in points per surface-target triangle ([`PipelineParams::reduce_above`]).
pub const REDUCE_ABOVE: f64 = 0.5;

/// Surface clouds of at most this many points are never reduced: a navigation system's own
/// clouds are registered as sent, whatever the model's resolution.
pub const REDUCE_FLOOR: usize = 4000;

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
    /// The nonlinear refinement ([`Method::Nonlinear`]).
    pub nonlinear: libr::RefineParams,
    /// The nonlinear refinement stops before an iteration or solve that would end past this
    /// instant, keeping the linear answer unless what it reached fits better (the service's time
    /// budget); None: [`PipelineParams::deadline`].
    pub refine_deadline: Option<Instant>,
    /// How [`Method::Auto`] scores and chooses its candidates.
    pub auto: auto::AutoParams,
    /// LIBR+ abstains, answering LIBR's result flagged, when a registration lies outside what
    /// its networks learned (their `abstain.json`, [`crate::gcn::abstain`]). Default true.
    pub abstain: bool,
    /// Whether the surface patch is matched to the anterior surface or the whole boundary,
    /// decided from the data ([`side`]).
    pub side: side::SideParams,
    /// A surface cloud with more points than this many per triangle of the model's surface
    /// target, and more than [`REDUCE_FLOOR`], is reduced to about that many (at least the
    /// floor) before every stage: one weighted centroid per cubic cell, the cells as small as
    /// the budget allows ([`crate::register::reduce`]), so that a dense cloud costs what the
    /// model can use of it; 0: every point as received. Default [`REDUCE_ABOVE`].
    pub reduce_above: f64,
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
            nonlinear: libr::RefineParams::default(),
            refine_deadline: None,
            auto: auto::AutoParams::default(),
            abstain: true,
            side: side::SideParams::default(),
            reduce_above: REDUCE_ABOVE,
        }
    }
}

impl PipelineParams {
    /// The correspondence settings of LIBR's iterations (wICP's, with LIBR's trimming floor; the
    /// robust kernel instead of the trimming for a held organ, or when asked).
    pub fn libr_correspondence(&self) -> CorrespondenceParams {
        CorrespondenceParams {
            trim_floor_mm: self.libr.fit.trim_floor_mm,
            // A held organ's dent leaves large residuals where the tool pushed: the median
            // trimming cuts them, the kernel keeps them at a lower weight.
            robust_kernel: self.libr.fit.robust_kernel
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
    /// The nonlinear model of [`Method::Nonlinear`], built on first use or by
    /// [`Prepared::with_nonlinear`] (its linear factorization is the refinement's preconditioner).
    pub nonlinear: std::sync::OnceLock<Result<NonlinearMap, String>>,
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
            nonlinear: std::sync::OnceLock::new(),
            seconds: crate::util::secs(t0),
        })
    }

    /// [`Prepared::new`] with a basis built on the model's boundary meshed again with tets of
    /// `edge_mm` and carried to its nodes ([`libr::coarse_basis`]): an answer within seconds of
    /// a large case's upload, while its own basis builds. Plain physics only (the carried basis
    /// has no supports or effects); the coarse basis's figures are returned beside it.
    pub fn with_coarse_basis(
        model: PreopModel,
        libr: &LibrParams,
        edge_mm: f64,
    ) -> Result<(Self, libr::CoarseFigures), PipelineError> {
        let t0 = Instant::now();
        let correspondence = Correspondence::new(&model).map_err(PipelineError::Case)?;
        let coarse = libr::coarse_basis(&model.mesh, libr, edge_mm).map_err(PipelineError::Case)?;
        let figures = coarse.figures();
        let prepared = Self {
            model,
            correspondence,
            basis: Some(coarse.basis),
            basis_from_cache: false,
            librplus: None,
            v2s: None,
            adaptive: None,
            physics: Physics::none(),
            error_model: None,
            nonlinear: std::sync::OnceLock::new(),
            seconds: crate::util::secs(t0),
        };
        Ok((prepared, figures))
    }

    /// The nonlinear model of the case with `material` (LIBR's), built on first use with
    /// `refine`'s mesh settings (a large case's on a coarse mesh of its boundary,
    /// [`NonlinearMap`]): the linear model factorized once and the hyperelastic solid. An error
    /// names why it could not be built.
    pub fn nonlinear_model(
        &self,
        material: &crate::fem::LinearMaterial,
        refine: &libr::RefineParams,
    ) -> Result<&NonlinearMap, PipelineError> {
        let mesh_settings = (refine.coarse_above, refine.coarse_nodes);
        let sites = Sites {
            posterior: &self.model.posterior,
            falciform: &self.model.falciform,
        };
        self.nonlinear
            .get_or_init(|| {
                let mesh = &self.model.mesh;
                NonlinearMap::for_case(mesh, material, sites, &self.physics, mesh_settings)
                    .map_err(|e| e.to_string())
            })
            .as_ref()
            .map_err(|e| PipelineError::Nonlinear(RegisterError::Model(e.clone())))
    }

    /// Builds the nonlinear model now (a case preloaded for [`Method::Nonlinear`] answers its
    /// first registration without the build), adding its time to [`Prepared::seconds`].
    pub fn with_nonlinear(
        mut self,
        libr: &LibrParams,
        refine: &libr::RefineParams,
    ) -> Result<Self, PipelineError> {
        let t0 = Instant::now();
        self.nonlinear_model(&libr.basis.material, refine)?;
        self.seconds += crate::util::secs(t0);
        Ok(self)
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
#[derive(Debug, Clone, Default, PartialEq)]
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
    /// The error estimate (when the case has an error model calibrated for the method; for
    /// [`Method::Auto`], the chosen candidate's).
    pub error: Option<ErrorEstimate>,
    /// How [`Method::Auto`] chose (None for the other methods).
    pub auto: Option<auto::AutoInfo>,
    /// The nonlinear refinement, for [`Method::Nonlinear`]; when it was kept, [`Registration::libr`]
    /// records its iterations, else the linear fit's.
    pub nonlinear: Option<libr::NonlinearInfo>,
    /// The navigation start's fit score (mm²) when it was above
    /// [`pose::PoseParams::search_above_mm2`] but no pose search was configured (no
    /// [`pose::PoseParams::start_angles_deg`]: asked for, or a time budget too tight for it):
    /// the search would have run. None otherwise.
    pub search_skipped_mm2: Option<f64>,
    /// A provisional answer: the navigation start's fit, given before the pose search it
    /// needs ([`progressive`]); the searched answer follows.
    pub search_follows: bool,
    /// A provisional answer: the linear fit of [`Method::Nonlinear`] (its method the fit's,
    /// adaptive LIBR or LIBR), given before its refinement runs ([`progressive`]); the
    /// refined answer follows.
    pub refinement_follows: bool,
    /// Which side of the organ the surface patch was matched to, when it was decided from the
    /// data ([`side`]; None: not tested).
    pub surface: Option<side::SideInfo>,
    /// How the surface cloud was reduced before every stage ([`crate::register::reduce`];
    /// None: used as received).
    pub points: Option<Reduction>,
    /// Total time (s).
    pub seconds: f64,
}

impl Registration {
    /// The answer's quality flag and its reason ([`quality::judge`]) as run with `params`,
    /// with nothing the caller adds (no fallback, no time budget).
    pub fn quality(&self, params: &PipelineParams) -> quality::Judgement {
        quality::judge(self, params, &quality::Circumstances::default())
    }

    /// What the error estimate reads of this registration: the fit's residual (LIBR+'s refit,
    /// else LIBR's, else wICP's), LIBR's strain energy, and the coverage of the answer by the
    /// measured points ([`crate::register::uncertainty::features`]), with each node's distance
    /// to the nearest measured point (mm). None without measured points.
    pub fn error_features(
        &self,
        case: &Prepared,
        boundary: &[bool],
        meas: &Checked,
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

    fn estimated(mut self, case: &Prepared, meas: &Checked) -> Self {
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
    /// model is calibrated on plain LIBR). The nonlinear refinement is estimated with the
    /// calibration of the linear method it refines.
    pub fn estimate_error(&mut self, case: &Prepared, meas: &Checked) {
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
            (_, Method::Auto) => match &self.auto {
                Some(a) => a.chosen.method(),
                None => return,
            },
            // The refinement of the linear fit, within a few millimetres of it (the fit itself
            // where it was kept): judged by the linear method's calibration.
            (_, Method::Nonlinear) if case.adaptive.is_some() => Method::Adaptive,
            (_, Method::Nonlinear) => Method::Libr,
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
            .any(|e| e.kind.hold() == Some(Hold::Local));
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
    meas: &Checked,
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
