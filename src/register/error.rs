//! What can stop a registration stage, by cause: what the caller got wrong (a parameter, the
//! measurements, the preoperative model), what the data cannot determine, and what failed
//! numerically. The server maps each cause to its own status.

use crate::fem::FemError;
use crate::mesh::io::npz::NpzError;
use crate::mesh::{MeshError, SurfaceError};
use crate::util::FileError;

/// Why a registration stage (correspondence, wICP, LIBR, its basis) did not run.
#[derive(Debug, thiserror::Error)]
pub enum RegisterError {
    /// A parameter is out of its range; the message names it and the range. Fix the parameter.
    #[error("{0}")]
    Parameter(String),
    /// The measurements break a rule (the message names the field and index). Fix the input.
    #[error("{0}")]
    Measurements(String),
    /// The preoperative model or its files are inconsistent (labels, vessels, boundary). Fix or
    /// rebuild the case.
    #[error("{0}")]
    Model(String),
    /// Most measured points lie beyond the correspondence cap from the model after the initial
    /// alignment: wrong units, frame or initial alignment.
    #[error(
        "{far} of {total} measured points are more than {cap_mm} mm from the model after the initial alignment (measurements.points[{worst}] is {worst_mm:.0} mm away): wrong units, wrong frame or a wrong initial alignment?"
    )]
    FarFromModel {
        /// Points beyond the cap.
        far: usize,
        /// Points measured.
        total: usize,
        /// The cap (mm).
        cap_mm: f64,
        /// The farthest point.
        worst: usize,
        /// Its distance (mm).
        worst_mm: f64,
    },
    /// Fewer than three matches carry weight: the data cannot fix the rigid correction. Collect
    /// more (or more spread-out) points.
    #[error(
        "{matched} matches with positive weight; at least 3 are needed to fix the rigid correction"
    )]
    TooFewMatches {
        /// Matches with positive weight.
        matched: usize,
    },
    /// A least-squares system was singular or gave non-finite values: the matches do not
    /// determine the unknowns (clustered points, or no regularisation).
    #[error("{0}")]
    IllConditioned(String),
    /// Inputs of mismatched sizes or out-of-range indices between the caller's own objects (a
    /// correspondence or basis built for another model): a bug in the caller.
    #[error("{0}")]
    Inconsistent(String),
    /// A cached LIBR basis file is unreadable or not this build's version (delete it to rebuild).
    #[error("LIBR basis file: {0}")]
    BasisFile(String),
    /// The elastic solve behind the basis failed.
    #[error(transparent)]
    Fem(#[from] FemError),
    /// The model's mesh is invalid.
    #[error(transparent)]
    Mesh(#[from] MeshError),
    /// The model's surface is invalid.
    #[error(transparent)]
    Surface(#[from] SurfaceError),
    /// The basis cache could not be encoded or decoded.
    #[error(transparent)]
    Npz(#[from] NpzError),
    /// The basis cache could not be written.
    #[error(transparent)]
    File(#[from] FileError),
}

impl RegisterError {
    /// True when the measurements themselves cannot determine the stage (too few matches, points
    /// far from the model, an ill-conditioned fit): a caller may fall back to a simpler method.
    /// False for errors in parameters, models, files or the caller's own objects.
    pub fn is_data_limited(&self) -> bool {
        match self {
            Self::FarFromModel { .. } | Self::TooFewMatches { .. } | Self::IllConditioned(_) => {
                true
            }
            Self::Parameter(_)
            | Self::Measurements(_)
            | Self::Model(_)
            | Self::Inconsistent(_)
            | Self::BasisFile(_)
            | Self::Fem(_)
            | Self::Mesh(_)
            | Self::Surface(_)
            | Self::Npz(_)
            | Self::File(_) => false,
        }
    }
}
