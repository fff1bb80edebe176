//! Reading datasets back: the geometries (preoperative model, boundary flags, targets) and the
//! scenarios (measurements, and the ground truth kept apart from them), as evaluation and
//! training read them. Registration never reads the truth: [`ScenarioData`] keeps `measurements`
//! and `truth` separate.

use super::{DatasetError, DeformationEntry, Manifest, read_manifest};
use crate::mesh::io::npz::{NpyArray, read_npz};
use crate::mesh::io::{self, Unit};
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::preop_model_from_file;
use crate::register::{Checked, MeasuredKind, Measurements, PreopModel};
use std::path::Path;

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
    pub measurements: Checked,
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
pub fn load_geometry(
    dir: &Path,
    m: &Manifest,
    geometry: &str,
) -> Result<GeometryData, DatasetError> {
    let g = m
        .geometries
        .iter()
        .find(|g| g.id == geometry)
        .ok_or_else(|| {
            DatasetError::Content(format!("the manifest has no geometry {geometry:?}"))
        })?;
    let preop = io::read(dir.join(&g.preop), Unit::Mm)?;
    let vessels = io::read(dir.join(&g.vessels), Unit::Mm)?;
    let model = preop_model_from_file(&preop, &vessels)?;
    let surface = model.boundary_flags();
    Ok(GeometryData {
        model,
        surface,
        targets: g.targets.clone(),
    })
}

fn array<'a>(arrays: &'a [NpyArray], name: &str, file: &str) -> Result<&'a NpyArray, DatasetError> {
    arrays
        .iter()
        .find(|a| a.name == name)
        .ok_or_else(|| DatasetError::Content(format!("{file}: no array {name:?}")))
}

fn rigid_from(m: &[f64]) -> Rigid {
    Rigid {
        rotation: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
        translation: [m[3], m[7], m[11]],
    }
}

/// The arrays of a deformation's `scenarios.npz`.
fn read_deformation_npz(dir: &Path, d: &DeformationEntry) -> Result<Vec<NpyArray>, DatasetError> {
    let path = dir.join(&d.npz);
    let bytes = std::fs::read(&path).map_err(crate::util::FileError::at("reading", &path))?;
    read_npz(&bytes).map_err(|source| DatasetError::Npz {
        file: d.npz.clone(),
        source,
    })
}

/// Reads every scenario of a deformation from its `scenarios.npz`.
pub fn load_scenarios(dir: &Path, d: &DeformationEntry) -> Result<Vec<ScenarioData>, DatasetError> {
    let a = read_deformation_npz(dir, d)?;
    let get = |name: &str| array(&a, name, &d.npz).map(|x| x.data.to_f64());
    let (points, kind, feature) = (get("points")?, get("kind")?, get("feature")?);
    let offsets = get("offsets")?;
    let (t_true, t_init) = (get("image_to_physical")?, get("initial_alignment")?);
    let displacement = get("displacement")?;
    if offsets.len() != d.scenarios.len() + 1 {
        return Err(DatasetError::Content(format!(
            "{}: {} offsets for {} scenarios",
            d.npz,
            offsets.len(),
            d.scenarios.len()
        )));
    }
    d.scenarios
        .iter()
        .map(|s| {
            let (lo, hi) = (offsets[s.index] as usize, offsets[s.index + 1] as usize);
            if hi < lo || 3 * hi > points.len() || hi > kind.len() || hi > feature.len() {
                return Err(DatasetError::Content(format!(
                    "{}: scenario {} out of range",
                    d.npz, s.index
                )));
            }
            let kinds = kind[lo..hi]
                .iter()
                .map(|&k| {
                    MeasuredKind::from_code(k as u8).ok_or_else(|| {
                        DatasetError::Content(format!("{}: unknown point kind {k}", d.npz))
                    })
                })
                .collect::<Result<Vec<_>, _>>()?;
            Ok(ScenarioData {
                id: format!("{}/{}", d.id, s.index),
                category: s.category.clone(),
                measurements: Checked::new(Measurements {
                    points: points[3 * lo..3 * hi]
                        .chunks_exact(3)
                        .map(|c| [c[0], c[1], c[2]])
                        .collect(),
                    kind: kinds,
                    feature: feature[lo..hi].iter().map(|&f| f as u8).collect(),
                    initial_alignment: Some(rigid_from(&t_init[16 * s.index..16 * s.index + 16])),
                })
                .map_err(|e| {
                    DatasetError::Content(format!("{}: scenario {}: {e}", d.npz, s.index))
                })?,
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
) -> Result<Vec<ScenarioPlanes>, DatasetError> {
    let a = read_deformation_npz(dir, d)?;
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
        return Err(DatasetError::Content(format!(
            "{}: {} offsets and {} plane_offsets for {s} scenarios",
            d.npz,
            offsets.len(),
            plane_offsets.len()
        )));
    }
    let q = axes[0].len();
    if q % 3 != 0 || axes.iter().any(|x| x.len() != q) {
        return Err(DatasetError::Content(format!(
            "{}: plane_origin, plane_lateral_dir, plane_depth_dir and plane_normal need the same \
             shape (Q, 3)",
            d.npz
        )));
    }
    let at = |x: &[f64], i: usize| [x[3 * i], x[3 * i + 1], x[3 * i + 2]];
    d.scenarios
        .iter()
        .map(|sc| {
            let k = sc.index;
            if k >= s {
                return Err(DatasetError::Content(format!(
                    "{}: scenario {k} out of range",
                    d.npz
                )));
            }
            let (lo, hi) = (offsets[k] as usize, offsets[k + 1] as usize);
            let (plo, phi) = (plane_offsets[k] as usize, plane_offsets[k + 1] as usize);
            if hi < lo || hi > plane.len() || hi > kind.len() || phi < plo || 3 * phi > q {
                return Err(DatasetError::Content(format!(
                    "{}: scenario {k} out of range",
                    d.npz
                )));
            }
            let n = (phi - plo) as i64;
            let plane_of_point: Vec<i32> = plane[lo..hi].iter().map(|&p| p as i32).collect();
            for (j, (&p, &kd)) in plane_of_point.iter().zip(&kind[lo..hi]).enumerate() {
                let surface = kd as u8 == MeasuredKind::Surface as u8;
                if (p as i64) < -1 || p as i64 >= n || (p == -1) != surface {
                    return Err(DatasetError::Content(format!(
                        "{}: scenario {k}, point {j}: plane {p} for a point of kind {kd} \
                         (the scenario has {n} planes; -1 exactly for surface points)",
                        d.npz
                    )));
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
pub fn open(dir: &Path) -> Result<Manifest, DatasetError> {
    read_manifest(dir)
}
