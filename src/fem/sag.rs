//! The project's reference linear problem: gravity sag of a liver on its posterior side.
//!
//! Linear elasticity (E = 5 kPa, ν = 0.45), body force 0.0104 mN/mm³ along +y (gravity on a supine
//! patient in LPS), nodes with `y > y_min + 0.8·(y_max − y_min)` fixed. Used by `librplus fem sag`
//! and checked node by node against scikit-fem.

use super::hyperelastic::{HyperelasticModel, NewtonInfo, NewtonParams};
use super::{Dirichlet, FemError, LameField, LinearMaterial, StiffnessSystem, loads};
use crate::mesh::TetMesh;
use std::time::Instant;

/// Parameters of the sag problem; defaults are the project's reference values.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SagParams {
    /// Material (kPa). Default E = 5 kPa, ν = 0.45.
    pub material: LinearMaterial,
    /// Body force (mN/mm³). Default `[0, 0.0104, 0]` (1.06 g/cm³ × 9.81 m/s², posterior).
    pub body_force: [f64; 3],
    /// Nodes with `y > y_min + fixed_fraction·(y_max − y_min)` are fixed. Default 0.8.
    pub fixed_fraction: f64,
}

impl Default for SagParams {
    fn default() -> Self {
        Self {
            material: LinearMaterial::new(5.0, 0.45),
            body_force: [0.0, 0.0104, 0.0],
            fixed_fraction: 0.8,
        }
    }
}

/// Result of the sag problem.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SagResult {
    /// Node-major displacement (mm).
    #[serde(skip)]
    pub displacement: Vec<f64>,
    /// Number of fixed nodes.
    pub fixed_nodes: usize,
    /// Largest nodal displacement magnitude (mm).
    pub max_disp_mm: f64,
    /// Mean nodal displacement magnitude over all nodes (mm).
    pub mean_disp_mm: f64,
    /// Total applied body force (mN).
    pub applied_load_mn: [f64; 3],
    /// Total support reaction (mN); balances the applied load in equilibrium.
    pub reaction_mn: [f64; 3],
    /// Strain energy (mN·mm): `uᵀKu/2` for the linear model, `∫W dV` for Neo-Hookean.
    pub strain_energy: f64,
    /// Free dofs.
    pub free_dofs: usize,
    /// Newton solver facts (Neo-Hookean model only).
    pub newton: Option<NewtonInfo>,
    /// Stage timings (s).
    pub timings: SagTimings,
}

/// Stage timings of the sag solve (seconds).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SagTimings {
    /// Stiffness assembly (pattern + values).
    pub assemble_s: f64,
    /// Constraint elimination + symbolic + numeric Cholesky (all Newton iterations for
    /// Neo-Hookean).
    pub factor_s: f64,
    /// Load assembly + back-substitution (the whole Newton loop less factorizations for
    /// Neo-Hookean).
    pub solve_s: f64,
}

/// Nodes fixed by the sag rule.
pub fn fixed_nodes(mesh: &TetMesh, fixed_fraction: f64) -> Vec<u32> {
    let (lo, hi) = mesh.bounding_box();
    let cut = lo[1] + fixed_fraction * (hi[1] - lo[1]);
    mesh.nodes()
        .iter()
        .enumerate()
        .filter(|(_, p)| p[1] > cut)
        .map(|(i, _)| i as u32)
        .collect()
}

fn check(params: &SagParams) -> Result<(), FemError> {
    params.material.validate()?;
    if !(params.fixed_fraction >= 0.0 && params.fixed_fraction < 1.0) {
        return Err(FemError::InvalidParameter {
            field: "fixed_fraction",
            message: format!("must be in [0, 1), got {}", params.fixed_fraction),
        });
    }
    if !params.body_force.iter().all(|b| b.is_finite()) {
        return Err(FemError::InvalidParameter {
            field: "body_force",
            message: format!("must be finite, got {:?}", params.body_force),
        });
    }
    Ok(())
}

fn summarize(u: Vec<f64>, fixed_nodes: usize, strain_energy: f64) -> SagResult {
    let mags: Vec<f64> = u
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .collect();
    SagResult {
        fixed_nodes,
        max_disp_mm: mags.iter().copied().fold(0.0, super::basis_bench::nan_max),
        mean_disp_mm: mags.iter().sum::<f64>() / mags.len().max(1) as f64,
        strain_energy,
        displacement: u,
        applied_load_mn: [0.0; 3],
        reaction_mn: [0.0; 3],
        free_dofs: 0,
        newton: None,
        timings: SagTimings {
            assemble_s: 0.0,
            factor_s: 0.0,
            solve_s: 0.0,
        },
    }
}

/// Solves the sag problem with the compressible Neo-Hookean model (same E, ν, loads and
/// supports): the nonlinear counterpart used to show what the linear model misses.
pub fn solve_neo_hookean(
    mesh: &TetMesh,
    params: &SagParams,
    newton: &NewtonParams,
) -> Result<SagResult, FemError> {
    check(params)?;
    let t0 = Instant::now();
    let (l, m) = params.material.lame();
    let model = HyperelasticModel::new(mesh, LameField::Uniform(l, m))?;
    let assemble_s = t0.elapsed().as_secs_f64();
    let fixed = fixed_nodes(mesh, params.fixed_fraction);
    let mut bc = Dirichlet::new(mesh.num_nodes());
    bc.fix_nodes(&fixed);
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    loads::add_body_force(&mut f, mesh, params.body_force);
    let (u, info) = model.solve(&bc, &f, newton)?;
    let energy = model.energy(&u).unwrap_or(f64::NAN);
    let fint = model.internal_force(&u).unwrap_or_default();
    let mut r = summarize(u, fixed.len(), energy);
    for a in 0..3 {
        r.applied_load_mn[a] = f.iter().skip(a).step_by(3).sum();
        r.reaction_mn[a] = fint.iter().skip(a).step_by(3).sum::<f64>() - r.applied_load_mn[a];
    }
    r.free_dofs = 3 * mesh.num_nodes() - bc.count();
    r.timings = SagTimings {
        assemble_s,
        factor_s: info.factor_s + info.symbolic_s,
        solve_s: info.total_s - info.factor_s - info.symbolic_s,
    };
    r.newton = Some(info);
    Ok(r)
}

/// Solves the sag problem.
pub fn solve(mesh: &TetMesh, params: &SagParams) -> Result<SagResult, FemError> {
    check(params)?;
    let t0 = Instant::now();
    let system = StiffnessSystem::linear(mesh, &params.material)?;
    let assemble_s = t0.elapsed().as_secs_f64();
    let fixed = fixed_nodes(mesh, params.fixed_fraction);
    let mut bc = Dirichlet::new(mesh.num_nodes());
    bc.fix_nodes(&fixed);
    let t1 = Instant::now();
    let fact = system.factorize(&bc)?;
    let factor_s = t1.elapsed().as_secs_f64();
    let t2 = Instant::now();
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    loads::add_body_force(&mut f, mesh, params.body_force);
    let u = fact.solve(&f);
    let solve_s = t2.elapsed().as_secs_f64();
    let mut r = summarize(u, fixed.len(), 0.0);
    r.strain_energy = system.energy(&r.displacement);
    let reactions = system.reactions(&r.displacement, &f);
    for a in 0..3 {
        r.applied_load_mn[a] = f.iter().skip(a).step_by(3).sum();
        r.reaction_mn[a] = reactions.iter().skip(a).step_by(3).sum();
    }
    r.free_dofs = fact.info().free_dofs;
    r.timings = SagTimings {
        assemble_s,
        factor_s,
        solve_s,
    };
    Ok(r)
}
