//! A LIBR basis built on a coarser mesh of the same organ and carried to the case's nodes: an
//! answer within seconds of a large case's upload, while its own basis builds.
//!
//! The preload's cost is the factorization, which grows as about n^1.9 with the mesh's nodes
//! (38 s at 64,000 nodes, two cores). The deformation LIBR fits is smooth on the scale of its
//! control points' spacing (tens of millimetres), so a mesh a few times coarser resolves it: the
//! case's boundary is meshed again with tets of `edge_mm` ([`crate::mesh::tetra`]), the basis
//! built there ([`LibrBasis::build`]: its control points, loads, factorization and solves), and
//! each column carried to the case's nodes by linear interpolation in the coarse tet that holds
//! the node (a node outside the coarse mesh, near a curved boundary, takes the value at the
//! closest coarse boundary point, [`TetLocator::weights`]). The energy matrix `E = ΦᵀKΦ` is the
//! coarse mesh's: the strain energy of the same displacement field on a coarser discretisation.
//! The control points become the case's boundary nodes nearest to the coarse ones.
//!
//! The carried basis is marked in its [`LibrBasis::params_hash`] (`…-coarse-E`), so that it is
//! never taken for the case's own basis by the cache, and it carries no physics: an augmented
//! model's supports and loads live on the case's nodes.

use super::{LibrBasis, LibrParams, mesh_hash};
use crate::mesh::TetMesh;
use crate::mesh::locate::TetLocator;
use crate::mesh::tetra::remesh;
use crate::register::RegisterError;
use crate::util::secs;
use rayon::prelude::*;
use std::time::Instant;

/// What [`coarse_basis`] made, with its times.
#[derive(Debug, Clone)]
pub struct CoarseBasis {
    /// The basis on the case's nodes.
    pub basis: LibrBasis,
    /// Nodes of the coarse mesh it was built on.
    pub coarse_nodes: usize,
    /// The coarse mesh's edge length (mm).
    pub edge_mm: f64,
    /// Seconds: meshing the boundary again, the basis on the coarse mesh, carrying it over.
    pub mesh_s: f64,
    /// See `mesh_s`.
    pub basis_s: f64,
    /// See `mesh_s`.
    pub transfer_s: f64,
}

/// A [`CoarseBasis`]'s figures without its basis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoarseFigures {
    /// Nodes of the coarse mesh.
    pub coarse_nodes: usize,
    /// The coarse mesh's edge length (mm).
    pub edge_mm: f64,
    /// Seconds it took in all: meshing again, the coarse basis, carrying it over.
    pub seconds: f64,
}

impl CoarseBasis {
    /// Its figures.
    pub fn figures(&self) -> CoarseFigures {
        CoarseFigures {
            coarse_nodes: self.coarse_nodes,
            edge_mm: self.edge_mm,
            seconds: self.mesh_s + self.basis_s + self.transfer_s,
        }
    }
}

/// The LIBR basis of `fine` built on its boundary meshed again with tets of `edge_mm`, carried
/// to `fine`'s nodes (module doc). Fails with a message naming the step: a mesh without a
/// closed boundary, an edge that is not finite and positive, a coarse mesh the basis cannot be
/// built on.
pub fn coarse_basis(
    fine: &TetMesh,
    params: &LibrParams,
    edge_mm: f64,
) -> Result<CoarseBasis, RegisterError> {
    if !(edge_mm.is_finite() && edge_mm > 0.0) {
        return Err(RegisterError::Parameter(format!(
            "coarse basis edge_mm must be finite and > 0, got {edge_mm}"
        )));
    }
    let t0 = Instant::now();
    let coarse =
        remesh(fine, edge_mm).map_err(|e| RegisterError::Model(format!("coarse basis: {e}")))?;
    let mesh_s = secs(t0);
    let t1 = Instant::now();
    let cb = LibrBasis::build(&coarse, params)?;
    let basis_s = secs(t1);
    let t2 = Instant::now();
    let phi = carried(&coarse, fine, &cb);
    let control_nodes = nearest_boundary_nodes(&coarse, fine, &cb.control_nodes)?;
    let basis = LibrBasis {
        control_nodes,
        nodes: fine.num_nodes(),
        phi,
        mesh_hash: mesh_hash(fine),
        params_hash: format!("{}-coarse-{edge_mm}", cb.params_hash),
        ..cb
    };
    Ok(CoarseBasis {
        basis,
        coarse_nodes: coarse.num_nodes(),
        edge_mm,
        mesh_s,
        basis_s,
        transfer_s: secs(t2),
    })
}

/// Φ of the coarse basis `cb` (on `coarse`) interpolated at every node of `fine`: row-major
/// 3n × m, rows `3·node + axis`.
fn carried(coarse: &TetMesh, fine: &TetMesh, cb: &LibrBasis) -> Vec<f64> {
    let loc = TetLocator::new(coarse);
    let m = cb.columns();
    let rows: Vec<Vec<f64>> = fine
        .nodes()
        .par_iter()
        .map(|&p| {
            let mut out = vec![0.0; 3 * m];
            // A mesh with a boundary always has a closest boundary face.
            if let Some((t, w)) = loc.weights(p) {
                for (&v, &wk) in loc.tet(t).iter().zip(&w) {
                    let v = v as usize;
                    for axis in 0..3 {
                        let src = &cb.phi[(3 * v + axis) * m..(3 * v + axis + 1) * m];
                        let dst = &mut out[axis * m..(axis + 1) * m];
                        for (d, s) in dst.iter_mut().zip(src) {
                            *d += wk * s;
                        }
                    }
                }
            }
            out
        })
        .collect();
    rows.concat()
}

/// For each coarse boundary node in `coarse_control`, the boundary node of `fine` nearest to
/// it (lowest index among ties).
fn nearest_boundary_nodes(
    coarse: &TetMesh,
    fine: &TetMesh,
    coarse_control: &[u32],
) -> Result<Vec<u32>, RegisterError> {
    let boundary = fine
        .boundary()
        .map_err(|e| RegisterError::Model(format!("coarse basis: the case's boundary: {e}")))?;
    let fine_nodes = fine.nodes();
    let cn = coarse.nodes();
    Ok(coarse_control
        .iter()
        .map(|&c| {
            let p = cn[c as usize];
            let d2 = |i: u32| {
                let q = fine_nodes[i as usize];
                (0..3).map(|a| (p[a] - q[a]).powi(2)).sum::<f64>()
            };
            boundary
                .nodes
                .iter()
                .copied()
                .min_by(|&a, &b| d2(a).total_cmp(&d2(b)).then(a.cmp(&b)))
                .unwrap_or(0)
        })
        .collect())
}
