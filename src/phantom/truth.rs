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
//! loads of LIBR's own kind ([`libr_base_load`]).

use super::PhantomError;
use super::patterns::LoadCase;
use crate::fem::hyperelastic::{HyperelasticModel, MaterialLaw, NewtonInfo, NewtonParams};
use crate::fem::{Dirichlet, FemError, LameField, LinearMaterial, NodeSpring, StiffnessSystem};
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
    solve_nonlinear_law(
        mesh,
        lame,
        MaterialLaw::NeoHookean,
        case,
        parts,
        unilateral,
        newton,
    )
}

/// [`solve_nonlinear`] with another strain-energy law.
pub fn solve_nonlinear_law(
    mesh: &TetMesh,
    lame: &LameField,
    law: MaterialLaw,
    case: &LoadCase,
    parts: LoadParts,
    unilateral: bool,
    newton: &NewtonParams,
) -> Result<GroundTruth, FemError> {
    let mut model = HyperelasticModel::new(mesh, lame.clone())?.with_law(law)?;
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

/// The ground truth of a load case made with another strain-energy law (a truth family,
/// [`super::family`]).
pub fn solve_truth_law(
    mesh: &TetMesh,
    lame: &LameField,
    law: MaterialLaw,
    case: &LoadCase,
    newton: &NewtonParams,
) -> Result<GroundTruth, FemError> {
    solve_nonlinear_law(mesh, lame, law, case, LoadParts::ALL, true, newton)
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

/// Broad tractions in a `--truth libr` base load ([`libr_base_load`]).
pub const LIBR_BASE_PATCHES: usize = 3;

/// Range of their peak traction (kPa, times `load_scale`): 0.15–0.45 kPa over LIBR's patch width
/// moves a liver of E = 5 kPa by roughly 5–20 mm, the order of the phantom's patterns.
pub const LIBR_BASE_PEAK_KPA: (f64, f64) = (0.15, 0.45);

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

/// The load of a `--truth libr` ground truth: loads LIBR's own model is made of, so that without
/// hidden effects the data hold nothing a discovery could name. [`LIBR_BASE_PATCHES`] smooth
/// traction patches exactly like LIBR's basis loads
/// ([`control_traction`](crate::register::libr::control_traction): a Gaussian of LIBR's default
/// width, 1.25 × the spacing of 25 control points, times the facing factor), each at a boundary
/// node drawn from the case's seed, along that node's inward normal turned by up to 45°, with a
/// peak in [`LIBR_BASE_PEAK_KPA`] × `load_scale`. The pattern's own loads (packs, pressure, the
/// retractor) are not used: each is, or resembles, an effect of the library (`pack`, `pressure`),
/// and would make the negative control hold one. Returns the load (mN, node-major) and a note
/// for the deformation's description.
pub fn libr_base_load(
    mesh: &TetMesh,
    case: &LoadCase,
    load_scale: f64,
) -> Result<(Vec<f64>, String), PhantomError> {
    use crate::mesh::vec3::{cross, dot, sub, unit};
    let n = mesh.num_nodes();
    if case.surface.len() != 3 * n {
        return Err(PhantomError::Inconsistent(format!(
            "load case has {} load entries for {n} nodes",
            case.surface.len()
        )));
    }
    let nodes = mesh.nodes();
    let b = mesh.boundary()?;
    let mut normal = vec![[0.0; 3]; n];
    let mut area = 0.0;
    for t in &b.triangles {
        let [p, q, r] = t.map(|v| nodes[v as usize]);
        let na = cross(sub(q, p), sub(r, p));
        area += 0.5 * dot(na, na).sqrt();
        for &v in t {
            for k in 0..3 {
                normal[v as usize][k] += na[k];
            }
        }
    }
    let width = 1.25 * (2.0 * area / (3f64.sqrt() * 25.0)).sqrt();
    let mut rng = crate::util::SplitMix64::new(case.seed ^ 0x4C49_4252_4241_5345);
    let mut load = vec![0.0; 3 * n];
    let mut parts = Vec::new();
    for _ in 0..LIBR_BASE_PATCHES {
        let v = b.nodes[rng.below(b.nodes.len())];
        let nv = unit(normal[v as usize]);
        // Inward normal turned by up to 45° towards a random tangent direction.
        let helper = if nv[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let t1 = unit(cross(nv, helper));
        let t2 = cross(nv, t1);
        let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
        let tilt = 45f64.to_radians() * rng.next_f64();
        let dir = [0, 1, 2]
            .map(|k| -tilt.cos() * nv[k] + tilt.sin() * (phi.cos() * t1[k] + phi.sin() * t2[k]));
        let peak = load_scale
            * (LIBR_BASE_PEAK_KPA.0
                + (LIBR_BASE_PEAK_KPA.1 - LIBR_BASE_PEAK_KPA.0) * rng.next_f64());
        for (axis, d) in dir.iter().enumerate() {
            let f = crate::register::libr::control_traction(
                nodes,
                &b.triangles,
                nodes[v as usize],
                nv,
                axis,
                width,
            );
            for (x, y) in load.iter_mut().zip(&f) {
                *x += peak * d * y;
            }
        }
        parts.push(format!("{peak:.2} kPa at node {v} along {dir:.2?}"));
    }
    Ok((
        load,
        format!(
            "base load: {} broad tractions of LIBR's own kind (σ {width:.1} mm): {}; the pattern's loads are not used",
            LIBR_BASE_PATCHES,
            parts.join("; ")
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
