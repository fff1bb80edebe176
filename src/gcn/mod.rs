//! Graph convolution for the SR-GCN residual network: the B-spline basis of spline convolution
//! ([`spline`], plain f64 Rust, computed once per graph), Cartesian pseudo-coordinates, and the
//! `pytorch_spline_conv`-compatible [`SplineConv`] layer in burn ([`spline_conv`]). This module
//! owns graph-index validation: every index handed to burn's `select`/`select_assign` has been
//! checked here first, so a bad graph is an error, never a panic or a silent out-of-bounds read.

pub mod abstain;
pub mod bench;
pub mod coarsen;
pub mod device;
pub mod graph;
pub mod infer;
pub mod io;
pub mod model;
pub mod sample;
pub mod sparse;
pub mod spline;
pub mod spline_conv;

pub use graph::{Graph, mesh_graph};
pub use spline::{SplineBasis, SplineKernel, cartesian_pseudo, spline_basis};
pub use spline_conv::{Aggregation, SplineConv, SplineConvConfig, SplineGraph};

/// Errors of graph construction and graph convolution.
#[derive(Debug, thiserror::Error)]
pub enum GcnError {
    /// Invalid input: shapes, ranges, kernel settings.
    #[error("invalid input: {0}")]
    Invalid(String),
    /// The stiffness behind the load input could not be assembled (a degenerate tet).
    #[error("the load input's stiffness: {0}")]
    LoadStiffness(crate::fem::FemError),
    /// The model cannot serve this use (an empty ensemble, a diagnostic network that needs the
    /// ground truth).
    #[error("{0}")]
    Unusable(String),
    /// The network's correction came out non-finite.
    #[error("{0}")]
    NonFinite(String),
    /// A model directory or weights file is unreadable or of another format.
    #[error("{0}")]
    ModelFile(String),
    /// The compute device is not available in this build or on this machine.
    #[error("{0}")]
    Device(String),
    /// A model file could not be written.
    #[error(transparent)]
    File(#[from] crate::util::FileError),
    /// Matching the measurements to the model (building a sample) failed.
    #[error(transparent)]
    Register(#[from] crate::register::RegisterError),
    /// A node index outside `0..num_nodes`.
    #[error("edge {edge}: node index {index} out of range for {num_nodes} nodes")]
    IndexOutOfRange {
        /// Edge position in the edge list.
        edge: usize,
        /// The offending node index.
        index: usize,
        /// Number of nodes of the graph.
        num_nodes: usize,
    },
}

/// Checks that `targets` and `sources` (edge_index rows 0 and 1) have equal length and index
/// nodes in `0..num_nodes`.
pub fn check_edges(num_nodes: usize, targets: &[usize], sources: &[usize]) -> Result<(), GcnError> {
    if targets.len() != sources.len() {
        return Err(GcnError::Invalid(format!(
            "edge_index rows differ in length: {} targets, {} sources",
            targets.len(),
            sources.len()
        )));
    }
    for (edge, (&t, &s)) in targets.iter().zip(sources).enumerate() {
        for index in [t, s] {
            if index >= num_nodes {
                return Err(GcnError::IndexOutOfRange {
                    edge,
                    index,
                    num_nodes,
                });
            }
        }
    }
    Ok(())
}
