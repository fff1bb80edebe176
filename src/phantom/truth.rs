//! Ground-truth simulation of a load case, the linear homogeneous model under the same loads, and
//! the breakdown of what separates them.
//!
//! The ground truth is the compressible Neo-Hookean solid with the heterogeneous tissue field, the
//! posterior bed as unilateral contact and the pattern's loads ([`solve_truth`]); a deformation that
//! does not converge is an error, never a result. [`solve_linear`] is what a linear homogeneous
//! model (LIBR's physics) gives under the same loads and supports — the bed can only be bilateral
//! there. [`breakdown`] walks from one to the other, adding one effect at a time, and also splits
//! the gap by load, so a report can say what the linear model misses and why.

use super::patterns::LoadCase;
use crate::fem::hyperelastic::{HyperelasticModel, NewtonInfo, NewtonParams};
use crate::fem::{Dirichlet, FemError, LameField, LinearMaterial, NodeSpring, StiffnessSystem};
use crate::mesh::TetMesh;

/// A converged ground-truth deformation.
#[derive(Debug, Clone)]
pub struct GroundTruth {
    /// Node displacements (mm, node-major).
    pub displacement: Vec<f64>,
    /// Newton statistics.
    pub info: NewtonInfo,
    /// Bed contacts pressing into the bed at equilibrium (of the case's contacts).
    pub active_contacts: usize,
}

/// Mean and maximum node displacement magnitude (mm).
pub fn magnitude_stats(u: &[f64]) -> (f64, f64) {
    let mags: Vec<f64> = u
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .collect();
    let mean = mags.iter().sum::<f64>() / mags.len().max(1) as f64;
    (mean, mags.iter().copied().fold(0.0, f64::max))
}

/// Mean over nodes of `|a − b|` (mm).
pub fn mean_distance(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() / 3;
    a.chunks_exact(3)
        .zip(b.chunks_exact(3))
        .map(|(p, q)| {
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .sum::<f64>()
        / n.max(1) as f64
}

/// Which parts of a load case to apply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoadParts {
    /// Gravity.
    pub gravity: bool,
    /// Surface loads and the retractor (prescribed displacement).
    pub pattern: bool,
}

impl LoadParts {
    /// Everything.
    pub const ALL: LoadParts = LoadParts {
        gravity: true,
        pattern: true,
    };
}

fn parts_of(case: &LoadCase, parts: LoadParts) -> (Vec<f64>, Dirichlet) {
    let n = case.load.len();
    let load: Vec<f64> = (0..n)
        .map(|d| {
            (if parts.gravity { case.gravity[d] } else { 0.0 })
                + if parts.pattern { case.surface[d] } else { 0.0 }
        })
        .collect();
    let bc = if parts.pattern {
        case.dirichlet.clone()
    } else {
        // Keep what is fixed, release what the retractor prescribes.
        let mut bc = Dirichlet::new(n / 3);
        for d in 0..n {
            if let Some(v) = case.dirichlet.get(d)
                && v == 0.0
            {
                bc.prescribe_dof((d / 3) as u32, d % 3, 0.0);
            }
        }
        bc
    };
    (load, bc)
}

/// Solves the Neo-Hookean model with `lame`; `unilateral` keeps the bed as contact (the ground
/// truth), otherwise the bed is bilateral (to isolate the contact's contribution).
pub fn solve_nonlinear(
    mesh: &TetMesh,
    lame: &LameField,
    case: &LoadCase,
    parts: LoadParts,
    unilateral: bool,
    newton: &NewtonParams,
) -> Result<GroundTruth, FemError> {
    let mut model = HyperelasticModel::new(mesh, lame.clone())?;
    model.add_springs(&case.springs)?;
    if unilateral {
        model.add_contacts(&case.contacts)?;
    } else {
        let bilateral: Vec<NodeSpring> = case.contacts.iter().map(|c| c.bilateral()).collect();
        model.add_springs(&bilateral)?;
    }
    let (load, bc) = parts_of(case, parts);
    let (u, info) = model.solve(&bc, &load, newton)?;
    let active = model.active_contacts(&u);
    Ok(GroundTruth {
        displacement: u,
        info,
        active_contacts: active,
    })
}

/// The ground truth of a load case: Neo-Hookean, heterogeneous `lame`, unilateral bed, all loads.
pub fn solve_truth(
    mesh: &TetMesh,
    lame: &LameField,
    case: &LoadCase,
    newton: &NewtonParams,
) -> Result<GroundTruth, FemError> {
    solve_nonlinear(mesh, lame, case, LoadParts::ALL, true, newton)
}

/// Linear elasticity with `lame` under the case's loads (the selected parts) and supports, the bed
/// as bilateral springs.
pub fn solve_linear(
    mesh: &TetMesh,
    lame: &LameField,
    case: &LoadCase,
    parts: LoadParts,
) -> Result<Vec<f64>, FemError> {
    let mut system = StiffnessSystem::linear_field(mesh, lame)?;
    system.add_springs(&case.springs)?;
    let bilateral: Vec<NodeSpring> = case.contacts.iter().map(|c| c.bilateral()).collect();
    system.add_springs(&bilateral)?;
    let (load, bc) = parts_of(case, parts);
    Ok(system.factorize(&bc)?.solve(&load))
}

/// One row of a breakdown: the effect and the mean node distance it adds (mm).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Contribution {
    /// What was switched on (or which load).
    pub effect: String,
    /// Mean over nodes of the displacement change it causes (mm).
    pub mean_mm: f64,
}

/// What separates the ground truth from the linear homogeneous model for one load case.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Breakdown {
    /// Mean / max ground-truth displacement (mm).
    pub truth_mean_mm: f64,
    /// Maximum ground-truth displacement (mm).
    pub truth_max_mm: f64,
    /// Mean over nodes of |u_truth − u_linear-homogeneous| (mm): the gap.
    pub gap_mm: f64,
    /// The ladder: linear homogeneous → + heterogeneity → + nonlinear material and geometry →
    /// + unilateral bed; each row the mean change of that step.
    pub steps: Vec<Contribution>,
    /// The gap under each load alone (gravity only; the pattern's own load only).
    pub by_load: Vec<Contribution>,
}

/// Computes the breakdown; `homogeneous` is the linear model's material (the parenchyma's).
pub fn breakdown(
    mesh: &TetMesh,
    lame: &LameField,
    homogeneous: &LinearMaterial,
    case: &LoadCase,
    newton: &NewtonParams,
) -> Result<Breakdown, FemError> {
    let (l, m) = homogeneous.lame();
    let homog = LameField::Uniform(l, m);
    let lin_homog = solve_linear(mesh, &homog, case, LoadParts::ALL)?;
    let lin_het = solve_linear(mesh, lame, case, LoadParts::ALL)?;
    let nl_bilateral = solve_nonlinear(mesh, lame, case, LoadParts::ALL, false, newton)?;
    let truth = solve_truth(mesh, lame, case, newton)?;
    let (truth_mean_mm, truth_max_mm) = magnitude_stats(&truth.displacement);
    let steps = vec![
        Contribution {
            effect: "heterogeneity (linear)".into(),
            mean_mm: mean_distance(&lin_het, &lin_homog),
        },
        Contribution {
            effect: "nonlinear material and geometry".into(),
            mean_mm: mean_distance(&nl_bilateral.displacement, &lin_het),
        },
        Contribution {
            effect: "unilateral bed contact".into(),
            mean_mm: mean_distance(&truth.displacement, &nl_bilateral.displacement),
        },
    ];
    let mut by_load = Vec::new();
    for (name, parts) in [
        (
            "gravity only",
            LoadParts {
                gravity: true,
                pattern: false,
            },
        ),
        (
            "pattern load only",
            LoadParts {
                gravity: false,
                pattern: true,
            },
        ),
    ] {
        let t = solve_nonlinear(mesh, lame, case, parts, true, newton)?;
        let lh = solve_linear(mesh, &homog, case, parts)?;
        by_load.push(Contribution {
            effect: name.into(),
            mean_mm: mean_distance(&t.displacement, &lh),
        });
    }
    Ok(Breakdown {
        truth_mean_mm,
        truth_max_mm,
        gap_mm: mean_distance(&truth.displacement, &lin_homog),
        steps,
        by_load,
    })
}
