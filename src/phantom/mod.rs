//! Liver phantoms for ground truth: geometries and their variants (later: anatomical labels, load
//! patterns, ground-truth simulation, sparse measurements and the dataset writer).
//!
//! Only data generation uses this module; `register` and `gcn` never import it, since what runs in
//! surgery cannot see how the ground truth was made.

pub mod dataset;
pub mod family;
pub mod hidden;
pub mod measure;
pub mod patterns;
pub mod shape;
pub mod tissue;
pub mod truth;
pub mod vessels;

/// Why a phantom could not be built or measured, or a dataset not generated.
#[derive(Debug, thiserror::Error)]
pub enum PhantomError {
    /// A parameter is out of its range; the message names it and the range.
    #[error("{0}")]
    Parameter(String),
    /// The liver cannot host what was asked (no surface to retract, no bare area to support it,
    /// collinear landmarks): choose another pattern or liver.
    #[error("{0}")]
    Geometry(String),
    /// Inputs of mismatched sizes or non-finite values passed between the generator's stages.
    #[error("{0}")]
    Inconsistent(String),
    /// The elastic solve failed.
    #[error(transparent)]
    Fem(#[from] crate::fem::FemError),
    /// A mesh is invalid.
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshError),
    /// A surface is invalid.
    #[error(transparent)]
    Surface(#[from] crate::mesh::SurfaceError),
    /// Tetrahedralisation failed.
    #[error(transparent)]
    Tetra(#[from] crate::mesh::tetra::TetraError),
    /// Anatomical labelling failed.
    #[error(transparent)]
    Labels(#[from] crate::register::RegisterError),
    /// The augmented model ([`crate::register::physics`]) refused an effect or failed to solve
    /// (`--truth libr`, hidden effects).
    #[error(transparent)]
    Model(crate::register::RegisterError),
    /// An array file could not be encoded.
    #[error(transparent)]
    Npz(#[from] crate::mesh::io::npz::NpzError),
    /// A mesh file could not be written.
    #[error(transparent)]
    MeshFile(#[from] crate::mesh::io::IoError),
    /// A file could not be written.
    #[error(transparent)]
    File(#[from] crate::util::FileError),
    /// A JSON file could not be encoded.
    #[error("JSON: {0}")]
    Json(#[from] serde_json::Error),
    /// What failed, in which geometry, deformation or scenario.
    #[error("{context}: {source}")]
    In {
        /// Where (e.g. "liver-1: meshing failed", "scenario 3").
        context: String,
        /// What failed.
        source: Box<PhantomError>,
    },
}

/// A seed derived from a seed and a path of keys (SplitMix64 finaliser chain): every random stage
/// of the generator draws from its own derived stream, so adding a stage changes no other draw.
pub(crate) fn derive(seed: u64, keys: &[u64]) -> u64 {
    let mut s = seed;
    for &k in keys {
        s = crate::util::SplitMix64::new(s ^ k.wrapping_mul(0x9E37_79B9_7F4A_7C15)).next_u64();
    }
    s
}

impl PhantomError {
    /// `source`, said to have happened in `context`.
    pub fn within(context: impl Into<String>, source: impl Into<PhantomError>) -> Self {
        Self::In {
            context: context.into(),
            source: Box::new(source.into()),
        }
    }
}
