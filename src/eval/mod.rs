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

/// The pose of one ultrasound plane, physical frame, as the dataset stores it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanePose {
    /// Probe contact (mm), the apex of the fan: the plane's origin.
    pub origin: [f64; 3],
    /// In-plane direction across the beam (unit).
    pub lateral_dir: [f64; 3],
    /// Beam direction into the liver (unit).
    pub depth_dir: [f64; 3],
    /// Plane normal (unit), `depth_dir × lateral_dir` as the generator writes it.
    pub normal: [f64; 3],
}

/// The ultrasound planes of one scenario: the plane of each measured point and the plane poses.
#[derive(Debug, Clone, PartialEq)]
pub struct ScenarioPlanes {
    /// Per measured point (the order of [`ScenarioData::measurements`]): its plane's index into
    /// `planes`, −1 for surface points.
    pub plane_of_point: Vec<i32>,
    /// The scenario's planes, in their index order.
    pub planes: Vec<PlanePose>,
}

/// Reads the ultrasound planes of every scenario of a deformation from its `scenarios.npz`
/// (arrays `plane`, `plane_offsets`, `plane_origin`, `plane_lateral_dir`, `plane_depth_dir`,
/// `plane_normal`), in the scenario order of [`load_scenarios`]. Checks that every point's plane
/// index is in range and that exactly the surface points have none.
pub fn load_scenario_planes(
    dir: &Path,
    d: &DeformationEntry,
) -> Result<Vec<ScenarioPlanes>, String> {
    let bytes = std::fs::read(dir.join(&d.npz)).map_err(|e| format!("{}: {e}", d.npz))?;
    let a = read_npz(&bytes).map_err(|e| format!("{}: {e}", d.npz))?;
    let get = |name: &str| array(&a, name, &d.npz).map(|x| x.data.to_f64());
    let (kind, plane, offsets) = (get("kind")?, get("plane")?, get("offsets")?);
    let plane_offsets = get("plane_offsets")?;
    let axes = [
        get("plane_origin")?,
        get("plane_lateral_dir")?,
        get("plane_depth_dir")?,
        get("plane_normal")?,
    ];
    let s = d.scenarios.len();
    if offsets.len() != s + 1 || plane_offsets.len() != s + 1 {
        return Err(format!(
            "{}: {} offsets and {} plane_offsets for {s} scenarios",
            d.npz,
            offsets.len(),
            plane_offsets.len()
        ));
    }
    let q = axes[0].len();
    if q % 3 != 0 || axes.iter().any(|x| x.len() != q) {
        return Err(format!(
            "{}: plane_origin, plane_lateral_dir, plane_depth_dir and plane_normal need the same \
             shape (Q, 3)",
            d.npz
        ));
    }
    let at = |x: &[f64], i: usize| [x[3 * i], x[3 * i + 1], x[3 * i + 2]];
    d.scenarios
        .iter()
        .map(|sc| {
            let k = sc.index;
            if k >= s {
                return Err(format!("{}: scenario {k} out of range", d.npz));
            }
            let (lo, hi) = (offsets[k] as usize, offsets[k + 1] as usize);
            let (plo, phi) = (plane_offsets[k] as usize, plane_offsets[k + 1] as usize);
            if hi < lo || hi > plane.len() || hi > kind.len() || phi < plo || 3 * phi > q {
                return Err(format!("{}: scenario {k} out of range", d.npz));
            }
            let n = (phi - plo) as i64;
            let plane_of_point: Vec<i32> = plane[lo..hi].iter().map(|&p| p as i32).collect();
            for (j, (&p, &kd)) in plane_of_point.iter().zip(&kind[lo..hi]).enumerate() {
                let surface = kd as u8 == MeasuredKind::Surface as u8;
                if (p as i64) < -1 || p as i64 >= n || (p == -1) != surface {
                    return Err(format!(
                        "{}: scenario {k}, point {j}: plane {p} for a point of kind {kd} \
                         (the scenario has {n} planes; -1 exactly for surface points)",
                        d.npz
                    ));
                }
            }
            let planes = (plo..phi)
                .map(|i| PlanePose {
                    origin: at(&axes[0], i),
                    lateral_dir: at(&axes[1], i),
                    depth_dir: at(&axes[2], i),
                    normal: at(&axes[3], i),
                })
                .collect();
            Ok(ScenarioPlanes {
                plane_of_point,
                planes,
            })
        })
        .collect()
}

/// Opens a dataset: its manifest.
pub fn open(dir: &Path) -> Result<Manifest, String> {
    read_manifest(dir)
}
