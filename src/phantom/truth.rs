//! Ground-truth simulation of a load case, the linear homogeneous model under the same loads, and
//! the breakdown of what separates them.
//!
//! The ground truth is the compressible Neo-Hookean solid with the heterogeneous tissue field, the
//! posterior bed as unilateral contact and the pattern's loads ([`solve_truth`]); a deformation that
//! does not converge is an error, never a result. [`solve_linear`] is what a linear homogeneous
//! model (LIBR's physics) gives under the same loads and supports — the bed can only be bilateral
//! there. [`breakdown`] walks from one to the other, adding one effect at a time, and also splits
//! the gap by load, so a report can say what the linear model misses and why.
//!
//! [`solve_libr`] is the other kind of truth (`generate --truth libr`): LIBR's own free-floating
//! linear homogeneous model plus named hidden effects ([`crate::register::physics`]), under the
//! pattern's surface load alone ([`libr_base_load`]).

use super::PhantomError;
use super::patterns::LoadCase;
use crate::fem::hyperelastic::{HyperelasticModel, NewtonInfo, NewtonParams};
use crate::fem::{
    Dirichlet, FemError, LameField, LinearMaterial, NodeSpring, StiffnessSystem, loads,
};
use crate::mesh::TetMesh;
use crate::register::anatomy::{AnatomyLabels, Region};
use crate::register::physics::Physics;
use crate::register::physics::model::{Sites, forward};

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

/// Traction (kPa, times `load_scale`) that replaces pattern L's retractor under `--truth libr`.
///
/// A free-floating model cannot carry a prescribed displacement, so the retractor becomes the
/// load it stands for: a uniform traction on the gripped patch. 1 kPa over the 30–50 mm patch the
/// retractor grips (about 2,000–5,000 mm² of surface) is 2–5 N, the order of pattern R's pack
/// (4.5–9 N) and of pattern V's packing pressure (0.8–1.4 kPa).
pub const RETRACTOR_TRACTION_KPA: f64 = 1.0;

/// The per-node anatomical sites the augmented model's supports attach to, from a phantom's
/// labels: `posterior` = nodes of [`Region::Posterior`] (boundary nodes on the organ bed),
/// `falciform` = the falciform-ligament flags.
#[derive(Debug, Clone, PartialEq)]
pub struct LibrSites {
    /// Posterior boundary nodes.
    pub posterior: Vec<bool>,
    /// Falciform-ligament nodes.
    pub falciform: Vec<bool>,
}

impl LibrSites {
    /// The sites of a labelled mesh.
    pub fn new(labels: &AnatomyLabels) -> Self {
        Self {
            posterior: labels
                .region
                .iter()
                .map(|r| *r == Region::Posterior)
                .collect(),
            falciform: labels.falciform.clone(),
        }
    }

    /// Borrowed, as [`forward`] takes them.
    pub fn sites(&self) -> Sites<'_> {
        Sites {
            posterior: &self.posterior,
            falciform: &self.falciform,
        }
    }
}

/// The load LIBR's own physics carries for a load case (`--truth libr`): the case's surface load
/// only (packs, pressure); no gravity, no bed or bare-area springs. A retractor (pattern L's
/// prescribed displacement) is replaced by a uniform traction of
/// [`RETRACTOR_TRACTION_KPA`] × `load_scale` on the boundary triangles whose three nodes it
/// prescribes, along the unit mean of the prescribed displacements. Returns the load (mN,
/// node-major) and a note for the deformation's description (empty when nothing was replaced).
pub fn libr_base_load(
    mesh: &TetMesh,
    case: &LoadCase,
    load_scale: f64,
) -> Result<(Vec<f64>, String), PhantomError> {
    let n = mesh.num_nodes();
    if case.surface.len() != 3 * n || case.dirichlet.len() != 3 * n {
        return Err(PhantomError::Inconsistent(format!(
            "load case has {} load and {} constrained entries for {n} nodes",
            case.surface.len(),
            case.dirichlet.len()
        )));
    }
    let mut load = case.surface.clone();
    if case.dirichlet.count() == 0 {
        return Ok((load, String::new()));
    }
    let gripped: Vec<bool> = (0..n)
        .map(|v| (0..3).all(|a| case.dirichlet.get(3 * v + a).is_some()))
        .collect();
    let mut mean = [0.0; 3];
    let mut count = 0usize;
    for (v, _) in gripped.iter().enumerate().filter(|(_, g)| **g) {
        for (a, m) in mean.iter_mut().enumerate() {
            *m += case.dirichlet.get(3 * v + a).unwrap_or(0.0);
        }
        count += 1;
    }
    let length = mean.iter().map(|x| x * x).sum::<f64>().sqrt();
    let dir = if length > 0.0 {
        mean.map(|x| x / length)
    } else {
        [0.0; 3]
    };
    let patch: Vec<[u32; 3]> = mesh
        .boundary()?
        .triangles
        .into_iter()
        .filter(|t| t.iter().all(|&v| gripped[v as usize]))
        .collect();
    if patch.is_empty() {
        return Err(PhantomError::Geometry(format!(
            "the retractor prescribes {count} nodes but no boundary triangle: no patch to load in its place"
        )));
    }
    let p = RETRACTOR_TRACTION_KPA * load_scale;
    loads::add_traction(
        &mut load,
        mesh.nodes(),
        &patch,
        &vec![dir.map(|d| d * p); patch.len()],
    );
    Ok((
        load,
        format!(
            "the retractor replaced by a {p:.2} kPa traction along {dir:.2?} on its {} triangles",
            patch.len()
        ),
    ))
}

/// LIBR's own physics plus `physics` under `base` (mN, node-major), with the homogeneous
/// `material`: [`forward`] (free-floating with inertia relief when no effect supports the organ,
/// carried by the springs otherwise).
pub fn solve_libr(
    mesh: &TetMesh,
    material: &LinearMaterial,
    sites: &LibrSites,
    physics: &Physics,
    base: &[f64],
) -> Result<Vec<f64>, PhantomError> {
    forward(mesh, material, sites.sites(), physics, base).map_err(PhantomError::Model)
}
