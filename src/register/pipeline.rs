//! The registration pipeline of one case: rigid wICP from the navigation system's coarse start,
//! then (for LIBR) the iterative basis fit re-matching correspondences on the deformed model at
//! every iteration. A [`Prepared`] case (correspondence structures and the LIBR basis) is built once
//! before surgery; [`register`] then answers one set of measurements.

use super::correspondence::{Correspondence, CorrespondenceParams, validate_measurements};
use super::libr::{self, LibrBasis, LibrInfo, LibrParams};
use super::wicp::{WicpParams, WicpResult, wicp};
use super::{Measurements, PreopModel};
use crate::mesh::rigid::Rigid;
use std::path::Path;
use std::time::Instant;

/// Registration method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Salient-feature weighted rigid ICP only.
    Rigid,
    /// wICP followed by LIBR.
    Libr,
}

impl Method {
    /// Name as on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Method::Rigid => "rigid",
            Method::Libr => "libr",
        }
    }
}

/// Parameters of the whole pipeline.
#[derive(Debug, Clone, Default)]
pub struct PipelineParams {
    /// Rigid stage (and its correspondence parameters, also used by LIBR).
    pub wicp: WicpParams,
    /// LIBR stage.
    pub libr: LibrParams,
    /// LIBR stops iterating before an iteration that would end past this instant (the service's
    /// time budget); None: no deadline.
    pub deadline: Option<Instant>,
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
    ) -> Result<Self, String> {
        let t0 = Instant::now();
        let correspondence = Correspondence::new(&model)?;
        let (basis, basis_from_cache) = match (libr, cache_dir) {
            (None, _) => (None, false),
            (Some(p), Some(dir)) => {
                let (b, cached) = LibrBasis::load_or_build(&model.mesh, p, dir)?;
                (Some(b), cached)
            }
            (Some(p), None) => (Some(LibrBasis::build(&model.mesh, p)?), false),
        };
        Ok(Self {
            model,
            correspondence,
            basis,
            basis_from_cache,
            seconds: crate::util::secs(t0),
        })
    }
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
    /// The rigid stage.
    pub rigid: WicpResult,
    /// The LIBR stage, when run.
    pub libr: Option<LibrInfo>,
    /// Total time (s).
    pub seconds: f64,
}

/// Registers measurements to a prepared case.
pub fn register(
    case: &Prepared,
    meas: &Measurements,
    method: Method,
    params: &PipelineParams,
) -> Result<Registration, String> {
    let t0 = Instant::now();
    validate_measurements(meas)?;
    let rigid = wicp(&case.model, &case.correspondence, meas, &params.wicp)?;
    let n = case.model.mesh.num_nodes();
    if method == Method::Rigid {
        return Ok(Registration {
            method,
            image_to_physical: rigid.image_to_physical,
            u: vec![0.0; 3 * n],
            rigid,
            libr: None,
            seconds: crate::util::secs(t0),
        });
    }
    if let Some(reason) = &rigid.degenerate {
        return Err(format!(
            "the rigid stage found the data degenerate ({reason}); LIBR needs spread-out points"
        ));
    }
    let basis = case
        .basis
        .as_ref()
        .ok_or("the case was prepared without a LIBR basis")?;
    let cparams = CorrespondenceParams {
        trim_floor_mm: params.libr.trim_floor_mm,
        ..params.wicp.correspondence
    };
    let cparams = &cparams;
    let corr = &case.correspondence;
    let sol = libr::register_active(
        &case.model.mesh,
        basis,
        &params.libr,
        &meas.points,
        &rigid.image_to_physical,
        libr::RunLimits {
            active: Some(corr.active_nodes()),
            deadline: params.deadline,
        },
        |u, t| {
            let inv = t.inverse();
            let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
            corr.match_points(&pts, meas, Some(u), cparams)
                .map(|(m, _)| m)
        },
    )?;
    Ok(Registration {
        method,
        image_to_physical: sol.image_to_physical,
        u: sol.u,
        rigid,
        libr: Some(sol.info),
        seconds: crate::util::secs(t0),
    })
}
