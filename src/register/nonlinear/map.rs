//! The nonlinear response of a linear displacement: the equilibrium under the loads behind it,
//! on the case's own mesh, or on a coarser mesh of the same organ for a large case.
//!
//! The refinement asks one thing of the nonlinear model: given a linear displacement `v = Φα`
//! (the loads `K v` behind it), where does the organ go under those loads? On the case's mesh
//! that is [`NonlinearModel::equilibrium`] of `K v`. Its cost is the preconditioner's solves,
//! which grow faster than the mesh (about n^1.5 per solve with the fill of the factor). The
//! difference the nonlinearity makes, `d = u(v) − v`, is smooth on the scale of the loads (tens of
//! millimetres), as the deformation itself is, so a mesh a few times coarser resolves it: the
//! case's boundary is meshed again with larger tets ([`crate::mesh::tetra`]), `v` interpolated at
//! the coarse nodes, the coarse model's equilibrium under the coarse mesh's loads behind that
//! interpolation solved, and its correction `d_c = u_c − P v_c` (both on the coarse mesh, so that
//! the coarse discretisation's own stiffness cancels to first order) interpolated back to the
//! case's nodes: `u = v + I d_c`. Transfers are linear interpolation in the tet holding the node
//! (a node outside, near a curved boundary, takes the closest boundary point's weights,
//! [`TetLocator::weights`]); the coarse model's supports attach where the case's nearest boundary
//! node's do.

use super::{ForwardInfo, ForwardParams, NonlinearModel};
use crate::fem::LinearMaterial;
use crate::mesh::TetMesh;
use crate::mesh::locate::TetLocator;
use crate::mesh::tetra::remesh;
use crate::register::RegisterError;
use crate::register::physics::Physics;
use crate::register::physics::boundary::Sites;
use rayon::prelude::*;
use std::time::Instant;

/// The node count a large case's coarse mesh is sized for ([`coarse_edge`]; the mesher's
/// boundary refinement adds to it: 3,446 nodes on the 9,089-node paper liver).
pub const COARSE_NODES: usize = 2_000;

/// A case with more nodes than this solves its nonlinear response on a coarse mesh sized for
/// [`COARSE_NODES`] nodes; a smaller one on its own.
pub const COARSE_ABOVE: usize = 4_000;

/// Linear interpolation weights: for each target node, the four source nodes of the tet that
/// holds it and their weights.
struct Interpolation(Vec<([u32; 4], [f64; 4])>);

impl Interpolation {
    /// Weights of `targets` in `source`'s tets.
    fn new(source: &TetMesh, targets: &[[f64; 3]]) -> Result<Self, RegisterError> {
        let loc = TetLocator::new(source);
        let w: Option<Vec<_>> = targets
            .par_iter()
            .map(|&p| loc.weights(p).map(|(t, w)| (loc.tet(t), w)))
            .collect();
        w.map(Self).ok_or_else(|| {
            RegisterError::Model("nonlinear coarse mesh: a node lies in no tet".into())
        })
    }

    /// The node-major 3-vector field `f` (on the source's nodes) at the targets.
    fn apply(&self, f: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; 3 * self.0.len()];
        out.par_chunks_mut(3)
            .zip(&self.0)
            .for_each(|(o, (nodes, w))| {
                for (&v, &wk) in nodes.iter().zip(w) {
                    for a in 0..3 {
                        o[a] += wk * f[3 * v as usize + a];
                    }
                }
            });
        out
    }
}

/// A coarse mesh and the transfers between it and the case's.
struct Coarse {
    to_coarse: Interpolation,
    to_fine: Interpolation,
    nodes: usize,
    edge_mm: f64,
}

/// The nonlinear response of a case's linear displacements (module doc).
pub struct NonlinearMap {
    model: NonlinearModel,
    coarse: Option<Coarse>,
    fine_dofs: usize,
    /// Seconds spent building (meshing again, the factorization, the transfers).
    pub build_s: f64,
}

impl NonlinearMap {
    /// The response on the case's own mesh.
    pub fn fine(model: NonlinearModel) -> Self {
        Self {
            fine_dofs: model.dofs(),
            build_s: model.build_s,
            model,
            coarse: None,
        }
    }

    /// The response of `physics` on `mesh` with `material`: on the mesh itself up to
    /// `coarse_above` nodes (all of them when 0), above it on the boundary meshed again to about
    /// `coarse_nodes` nodes.
    pub fn for_case(
        mesh: &TetMesh,
        material: &LinearMaterial,
        sites: Sites<'_>,
        physics: &Physics,
        (coarse_above, coarse_nodes): (usize, usize),
    ) -> Result<Self, RegisterError> {
        if coarse_above == 0 || mesh.num_nodes() <= coarse_above {
            return Ok(Self::fine(NonlinearModel::new(
                mesh, material, sites, physics,
            )?));
        }
        let edge = coarse_edge(mesh, coarse_nodes);
        Self::coarse(mesh, material, sites, physics, edge)
    }

    /// The response on `mesh`'s boundary meshed again with tets of `edge_mm`.
    pub fn coarse(
        mesh: &TetMesh,
        material: &LinearMaterial,
        sites: Sites<'_>,
        physics: &Physics,
        edge_mm: f64,
    ) -> Result<Self, RegisterError> {
        let t0 = Instant::now();
        if !(edge_mm.is_finite() && edge_mm > 0.0) {
            return Err(RegisterError::Parameter(format!(
                "nonlinear coarse edge_mm must be finite and > 0, got {edge_mm}"
            )));
        }
        let coarse = remesh(mesh, edge_mm)
            .map_err(|e| RegisterError::Model(format!("nonlinear coarse mesh: {e}")))?;
        let flags = coarse_sites(mesh, &coarse, sites)?;
        let coarse_sites = Sites {
            posterior: &flags.0,
            falciform: &flags.1,
        };
        let model = NonlinearModel::new(&coarse, material, coarse_sites, physics)?;
        let transfer = Coarse {
            to_coarse: Interpolation::new(mesh, coarse.nodes())?,
            to_fine: Interpolation::new(&coarse, mesh.nodes())?,
            nodes: coarse.num_nodes(),
            edge_mm,
        };
        Ok(Self {
            model,
            coarse: Some(transfer),
            fine_dofs: 3 * mesh.num_nodes(),
            build_s: crate::util::secs(t0),
        })
    }

    /// Dofs of the case's displacements (3n).
    pub fn dofs(&self) -> usize {
        self.fine_dofs
    }

    /// The model the response is solved on (the case's mesh, or the coarse one).
    pub fn model(&self) -> &NonlinearModel {
        &self.model
    }

    /// The coarse mesh's nodes and edge (mm), when the response is solved on one.
    pub fn coarse_mesh(&self) -> Option<(usize, f64)> {
        self.coarse.as_ref().map(|c| (c.nodes, c.edge_mm))
    }

    /// A displacement of the case's nodes in the model's space (the coarse mesh's nodes, or as
    /// it is): how a warm start follows a change of the linear displacement.
    pub fn restrict(&self, v: &[f64]) -> Vec<f64> {
        match &self.coarse {
            Some(c) => c.to_coarse.apply(v),
            None => v.to_vec(),
        }
    }

    /// The response to the linear displacement `lin` (the case's nodes, mm) from the model-space
    /// state `warm` (None: from the linear shape): the displacement of the case's nodes, the
    /// model-space equilibrium (the next warm start) and what the solve did.
    pub fn response(
        &self,
        lin: &[f64],
        warm: Option<&[f64]>,
        params: &ForwardParams,
    ) -> Result<(Vec<f64>, Vec<f64>, ForwardInfo), RegisterError> {
        if lin.len() != self.fine_dofs {
            return Err(RegisterError::Inconsistent(format!(
                "nonlinear response: {} values for {} dofs",
                lin.len(),
                self.fine_dofs
            )));
        }
        let Some(c) = &self.coarse else {
            let load = self.model.load_of(lin);
            let (u, info) = self
                .model
                .equilibrium(&load, Some(warm.unwrap_or(lin)), params)?;
            return Ok((u.clone(), u, info));
        };
        let mut lin_c = c.to_coarse.apply(lin);
        let load = self.model.load_of(&lin_c);
        self.model.project(&mut lin_c);
        let (uc, info) = self
            .model
            .equilibrium(&load, Some(warm.unwrap_or(&lin_c)), params)?;
        let dc: Vec<f64> = uc.iter().zip(&lin_c).map(|(a, b)| a - b).collect();
        let d = c.to_fine.apply(&dc);
        let u = lin.iter().zip(&d).map(|(a, b)| a + b).collect();
        Ok((u, uc, info))
    }
}

/// The tet edge (mm) that meshes `mesh`'s volume with about `nodes` nodes: its own mean edge
/// (from the mean tet volume, as for regular tets) scaled by the cube root of the node ratio.
pub fn coarse_edge(mesh: &TetMesh, nodes: usize) -> f64 {
    let tets = mesh.num_tets().max(1) as f64;
    let mean = mesh.volume() / tets;
    let edge = (mean * 6.0 * std::f64::consts::SQRT_2).cbrt();
    edge * (mesh.num_nodes() as f64 / nodes.max(1) as f64).cbrt()
}

/// The coarse mesh's site flags: a coarse boundary node takes the flags of the case's boundary
/// node nearest to it; interior nodes none.
fn coarse_sites(
    fine: &TetMesh,
    coarse: &TetMesh,
    sites: Sites<'_>,
) -> Result<(Vec<bool>, Vec<bool>), RegisterError> {
    let n = coarse.num_nodes();
    let (mut posterior, mut falciform) = (vec![false; n], vec![false; n]);
    if !sites.posterior.iter().chain(sites.falciform).any(|&b| b) {
        return Ok((posterior, falciform));
    }
    let err = |e| RegisterError::Model(format!("nonlinear coarse mesh: {e}"));
    let fb = fine.boundary().map_err(err)?;
    let cb = coarse.boundary().map_err(err)?;
    let (fnodes, cnodes) = (fine.nodes(), coarse.nodes());
    for &c in &cb.nodes {
        let p = cnodes[c as usize];
        let d2 = |i: u32| {
            let q = fnodes[i as usize];
            (0..3).map(|a| (p[a] - q[a]).powi(2)).sum::<f64>()
        };
        let nearest = fb
            .nodes
            .iter()
            .copied()
            .min_by(|&a, &b| d2(a).total_cmp(&d2(b)).then(a.cmp(&b)));
        if let Some(f) = nearest {
            posterior[c as usize] = sites.posterior.get(f as usize).copied().unwrap_or(false);
            falciform[c as usize] = sites.falciform.get(f as usize).copied().unwrap_or(false);
        }
    }
    Ok((posterior, falciform))
}
