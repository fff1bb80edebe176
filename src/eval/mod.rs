//! Evaluation: target registration error against the ground truth, and loading dataset scenarios.
//!
//! TRE is the mean over mesh nodes of the distance between predicted and ground-truth node
//! positions, both in the physical frame: predicted `T_est(X + u_est)`, true `T_true(X + u_true)`.
//! It is also reported for surface nodes, interior nodes and the labelled targets. Evaluation may
//! read the ground truth; registration (`crate::register`) never does — [`ScenarioData`] keeps the
//! two apart (`measurements` vs `truth`).

use crate::dataset::{DeformationEntry, Manifest, read_manifest};
use crate::mesh::TetMesh;
use crate::mesh::io::npz::{NpyArray, read_npz};
use crate::mesh::io::{self, DataArray, MeshFile, Unit};
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::preop_model_from_file;
use crate::register::{MeasuredKind, Measurements, PreopModel};
use std::path::Path;

pub mod bench;
pub mod plot;
pub mod report;

/// Target registration errors (mm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Tre {
    /// Mean over all nodes.
    pub tre_mm: f64,
    /// Mean over boundary nodes.
    pub tre_surface_mm: f64,
    /// Mean over interior nodes.
    pub tre_interior_mm: f64,
    /// Mean over the labelled targets (NaN when there are none).
    pub tre_targets_mm: f64,
    /// Largest node error.
    pub max_mm: f64,
}

/// Per-node distance (mm) between predicted and true node positions, both in the physical frame:
/// `|T_est(X_i + u_est,i) − T_true(X_i + u_true,i)|` for node i. The one definition of the node
/// error that [`tre`], `evaluate`'s error maps and `register --out` share.
pub fn node_errors_mm(
    nodes: &[[f64; 3]],
    predicted: (&Rigid, &[f64]),
    truth: (&Rigid, &[f64]),
) -> Vec<f64> {
    nodes
        .iter()
        .enumerate()
        .map(|(i, x)| {
            let at = |u: &[f64]| [0, 1, 2].map(|a| x[a] + u[3 * i + a]);
            let p = predicted.0.apply(at(predicted.1));
            let q = truth.0.apply(at(truth.1));
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .collect()
}

/// TRE of a prediction. `surface` flags boundary nodes; `targets` are node ids.
pub fn tre(
    nodes: &[[f64; 3]],
    predicted: (&Rigid, &[f64]),
    truth: (&Rigid, &[f64]),
    surface: &[bool],
    targets: &[u32],
) -> Tre {
    tre_from_errors(&node_errors_mm(nodes, predicted, truth), surface, targets)
}

/// TRE from per-node errors ([`node_errors_mm`]). `surface` flags boundary nodes; `targets` are
/// node ids.
pub fn tre_from_errors(err: &[f64], surface: &[bool], targets: &[u32]) -> Tre {
    let mean = |it: &mut dyn Iterator<Item = f64>| {
        let (s, c) = it.fold((0.0, 0usize), |(s, c), e| (s + e, c + 1));
        if c == 0 { f64::NAN } else { s / c as f64 }
    };
    Tre {
        tre_mm: mean(&mut err.iter().copied()),
        tre_surface_mm: mean(&mut err.iter().zip(surface).filter(|x| *x.1).map(|x| *x.0)),
        tre_interior_mm: mean(&mut err.iter().zip(surface).filter(|x| !*x.1).map(|x| *x.0)),
        tre_targets_mm: mean(&mut targets.iter().map(|&t| err[t as usize])),
        max_mm: err.iter().copied().fold(0.0, f64::max),
    }
}

/// The preoperative mesh as a mesh file carrying per-node arrays (an error map: open it in
/// ParaView or 3D Slicer and colour by an array). Pure: write it with [`crate::mesh::io::write`].
pub fn error_map_file(mesh: &TetMesh, point_data: Vec<DataArray>) -> MeshFile {
    let mut f = mesh.to_file();
    f.point_data = point_data;
    f
}

/// The ground truth of one scenario (evaluation only).
#[derive(Debug, Clone)]
pub struct Truth {
    /// True node displacements (image frame).
    pub displacement: Vec<f64>,
    /// True misalignment image → physical.
    pub image_to_physical: Rigid,
}

/// One scenario read from a dataset: what registration may see, and the truth kept apart.
#[derive(Debug, Clone)]
pub struct ScenarioData {
    /// `deformation/index`.
    pub id: String,
    /// Category name.
    pub category: String,
    /// The measurements (registration input).
    pub measurements: Measurements,
    /// The ground truth (evaluation only).
    pub truth: Truth,
}

/// A dataset geometry ready for registration: model, boundary flags and targets.
#[derive(Debug, Clone)]
pub struct GeometryData {
    /// The preoperative model.
    pub model: PreopModel,
    /// Boundary flag per node.
    pub surface: Vec<bool>,
    /// Target node ids.
    pub targets: Vec<u32>,
}

/// Reads a geometry of a dataset (its `preop.vtu` and `vessels.vtp`).
pub fn load_geometry(dir: &Path, m: &Manifest, geometry: &str) -> Result<GeometryData, String> {
    let g = m
        .geometries
        .iter()
        .find(|g| g.id == geometry)
        .ok_or_else(|| format!("the manifest has no geometry {geometry:?}"))?;
    let preop = io::read(dir.join(&g.preop), Unit::Mm).map_err(|e| e.to_string())?;
    let vessels = io::read(dir.join(&g.vessels), Unit::Mm).map_err(|e| e.to_string())?;
    let model = preop_model_from_file(&preop, &vessels)?;
    let surface = model
        .anterior
        .iter()
        .zip(&model.posterior)
        .map(|(a, p)| *a || *p)
        .collect();
    Ok(GeometryData {
        model,
        surface,
        targets: g.targets.clone(),
    })
}

fn array<'a>(arrays: &'a [NpyArray], name: &str, file: &str) -> Result<&'a NpyArray, String> {
    arrays
        .iter()
        .find(|a| a.name == name)
        .ok_or_else(|| format!("{file}: no array {name:?}"))
}

fn rigid_from(m: &[f64]) -> Rigid {
    Rigid {
        rotation: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
        translation: [m[3], m[7], m[11]],
    }
}

/// Reads every scenario of a deformation from its `scenarios.npz`.
pub fn load_scenarios(dir: &Path, d: &DeformationEntry) -> Result<Vec<ScenarioData>, String> {
    let bytes = std::fs::read(dir.join(&d.npz)).map_err(|e| format!("{}: {e}", d.npz))?;
    let a = read_npz(&bytes).map_err(|e| format!("{}: {e}", d.npz))?;
    let get = |name: &str| array(&a, name, &d.npz).map(|x| x.data.to_f64());
    let (points, kind, feature) = (get("points")?, get("kind")?, get("feature")?);
    let offsets = get("offsets")?;
    let (t_true, t_init) = (get("image_to_physical")?, get("initial_alignment")?);
    let displacement = get("displacement")?;
    if offsets.len() != d.scenarios.len() + 1 {
        return Err(format!(
            "{}: {} offsets for {} scenarios",
            d.npz,
            offsets.len(),
            d.scenarios.len()
        ));
    }
    d.scenarios
        .iter()
        .map(|s| {
            let (lo, hi) = (offsets[s.index] as usize, offsets[s.index + 1] as usize);
            if hi < lo || 3 * hi > points.len() || hi > kind.len() || hi > feature.len() {
                return Err(format!("{}: scenario {} out of range", d.npz, s.index));
            }
            let kinds = kind[lo..hi]
                .iter()
                .map(|&k| {
                    MeasuredKind::from_code(k as u8)
                        .ok_or_else(|| format!("{}: unknown point kind {k}", d.npz))
                })
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ScenarioData {
                id: format!("{}/{}", d.id, s.index),
                category: s.category.clone(),
                measurements: Measurements {
                    points: points[3 * lo..3 * hi]
                        .chunks_exact(3)
                        .map(|c| [c[0], c[1], c[2]])
                        .collect(),
                    kind: kinds,
                    feature: feature[lo..hi].iter().map(|&f| f as u8).collect(),
                    initial_alignment: Some(rigid_from(&t_init[16 * s.index..16 * s.index + 16])),
                },
                truth: Truth {
                    displacement: displacement.clone(),
                    image_to_physical: rigid_from(&t_true[16 * s.index..16 * s.index + 16]),
                },
            })
        })
        .collect()
}

/// Opens a dataset: its manifest.
pub fn open(dir: &Path) -> Result<Manifest, String> {
    read_manifest(dir)
}
