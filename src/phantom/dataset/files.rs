//! The dataset's files as generation writes them: a geometry's meshes and vessels, a
//! deformation's ground truth and scenarios (`.vtu`, `.vtp`, `scenarios.npz`), and the entries
//! the manifest is assembled from.

use super::{Built, DeformationPlan};
use crate::dataset::{DeformationEntry, FailedEntry, GeometryEntry, ScenarioEntry, VERSION};
use crate::mesh::TetMesh;
use crate::mesh::io::npz::{NpyArray, NpyData, write_npz};
use crate::mesh::io::{self, DataArray, MeshFile};
use crate::mesh::rigid::Rigid;
use crate::phantom::PhantomError;
use crate::phantom::measure::{Category, PointKind, Scenario};
use std::path::{Path, PathBuf};

pub(super) fn write_mesh_file(path: &Path, file: &MeshFile) -> Result<(), PhantomError> {
    let format = io::Format::from_path(path)?;
    let bytes = io::write_bytes(file, format, Default::default(), path)?;
    Ok(crate::util::write_atomic(path, &bytes)?)
}

pub(super) fn json_bytes<T: serde::Serialize>(value: &T) -> Result<Vec<u8>, PhantomError> {
    let mut s = serde_json::to_string_pretty(value)?;
    s.push('\n');
    Ok(s.into_bytes())
}

pub(super) fn write_geometry(
    dir: &Path,
    entry: &GeometryEntry,
    b: &Built,
) -> Result<(), PhantomError> {
    let mut file = b.mesh.to_file();
    file.point_data = b.labels.to_point_data();
    file.point_data.push(DataArray::new(
        "tumour",
        1,
        b.tissue
            .nodes_in_tumours(&b.mesh)
            .iter()
            .map(|&t| if t { 1.0 } else { 0.0 })
            .collect(),
    ));
    file.cell_data = b.tissue.to_cell_data();
    write_mesh_file(&dir.join(&entry.preop), &file)?;
    let mut parent = vec![-1.0; b.vessels.points.len()];
    for s in &b.vessels.segments {
        parent[s[1] as usize] = s[0] as f64;
    }
    let vessels = MeshFile {
        nodes: b.vessels.points.clone(),
        point_data: vec![
            DataArray::new("radius_mm", 1, b.vessels.radii.clone()),
            DataArray::new("parent", 1, parent),
        ],
        ..Default::default()
    };
    write_mesh_file(&dir.join(&entry.vessels), &vessels)
}

pub(super) fn rigid_matrix(r: &Rigid) -> [f64; 16] {
    let m = r.rotation;
    let t = r.translation;
    [
        m[0][0], m[0][1], m[0][2], t[0], m[1][0], m[1][1], m[1][2], t[1], m[2][0], m[2][1],
        m[2][2], t[2], 0.0, 0.0, 0.0, 1.0,
    ]
}

/// The npz arrays of a deformation's scenarios (documented in docs/dataset-and-models.md).
pub(super) fn scenarios_npz(
    mesh: &TetMesh,
    u: &[f64],
    scenarios: &[Scenario],
) -> Result<Vec<u8>, PhantomError> {
    let s = scenarios.len();
    let total: usize = scenarios.iter().map(|c| c.points.len()).sum();
    let planes: usize = scenarios.iter().map(|c| c.planes.len()).sum();
    let landmarks = scenarios.first().map_or(0, |c| c.landmark_nodes.len());
    if scenarios
        .iter()
        .any(|c| c.landmark_nodes.len() != landmarks)
    {
        return Err(PhantomError::Inconsistent(
            "scenarios have different numbers of landmarks".into(),
        ));
    }
    let mut offsets = vec![0i64];
    let mut plane_offsets = vec![0i64];
    let (mut points, mut truth) = (Vec::with_capacity(total), Vec::with_capacity(total));
    let (mut kind, mut plane) = (Vec::with_capacity(total), Vec::with_capacity(total));
    let mut feature = Vec::with_capacity(total);
    let mut plane_data: [Vec<[f64; 3]>; 4] = Default::default();
    let (mut t_true, mut t_init) = (Vec::new(), Vec::new());
    let (mut lm_nodes, mut lm_img, mut lm_phys) = (Vec::new(), Vec::new(), Vec::new());
    for c in scenarios {
        points.extend_from_slice(&c.points);
        truth.extend_from_slice(&c.truth_image);
        kind.extend(c.kind.iter().map(|&k| k as u8));
        plane.extend_from_slice(&c.plane);
        feature.extend_from_slice(&c.feature);
        offsets.push(points.len() as i64);
        for p in &c.planes {
            plane_data[0].push(p.origin);
            plane_data[1].push(p.depth_dir);
            plane_data[2].push(p.lateral_dir);
            plane_data[3].push(p.normal);
        }
        plane_offsets.push(plane_data[0].len() as i64);
        t_true.extend(rigid_matrix(&c.image_to_physical));
        t_init.extend(rigid_matrix(&c.initial_alignment));
        lm_nodes.extend(c.landmark_nodes.iter().map(|&n| n as i32));
        lm_img.extend(c.landmarks_image.iter().flatten());
        lm_phys.extend(c.landmarks_physical.iter().flatten());
    }
    let nodes = mesh.num_nodes();
    let arrays = vec![
        NpyArray::new("format_version", &[1], NpyData::I32(vec![VERSION as i32]))?,
        NpyArray::points("nodes", mesh.nodes()),
        NpyArray::new(
            "tets",
            &[mesh.num_tets(), 4],
            NpyData::I32(mesh.tets().iter().flatten().map(|&v| v as i32).collect()),
        )?,
        NpyArray::new("displacement", &[nodes, 3], NpyData::F64(u.to_vec()))?,
        NpyArray::points("points", &points),
        NpyArray::new("kind", &[total], NpyData::U8(kind))?,
        NpyArray::new("plane", &[total], NpyData::I32(plane))?,
        NpyArray::new("feature", &[total], NpyData::U8(feature))?,
        NpyArray::points("truth_image", &truth),
        NpyArray::new("offsets", &[s + 1], NpyData::I64(offsets))?,
        NpyArray::new(
            "category",
            &[s],
            NpyData::U8(
                scenarios
                    .iter()
                    .map(|c| {
                        Category::ALL
                            .iter()
                            .position(|&k| k == c.category)
                            .unwrap_or(0) as u8
                    })
                    .collect(),
            ),
        )?,
        NpyArray::new(
            "seed",
            &[s],
            NpyData::U64(scenarios.iter().map(|c| c.seed).collect()),
        )?,
        NpyArray::new(
            "coverage",
            &[s],
            NpyData::F64(scenarios.iter().map(|c| c.coverage).collect()),
        )?,
        NpyArray::new("image_to_physical", &[s, 4, 4], NpyData::F64(t_true))?,
        NpyArray::new("initial_alignment", &[s, 4, 4], NpyData::F64(t_init))?,
        NpyArray::new("landmark_nodes", &[s, landmarks], NpyData::I32(lm_nodes))?,
        NpyArray::new("landmarks_image", &[s, landmarks, 3], NpyData::F64(lm_img))?,
        NpyArray::new(
            "landmarks_physical",
            &[s, landmarks, 3],
            NpyData::F64(lm_phys),
        )?,
        NpyArray::new("plane_offsets", &[s + 1], NpyData::I64(plane_offsets))?,
        NpyArray::points("plane_origin", &plane_data[0]),
        NpyArray::points("plane_depth_dir", &plane_data[1]),
        NpyArray::points("plane_lateral_dir", &plane_data[2]),
        NpyArray::points("plane_normal", &plane_data[3]),
    ];
    debug_assert_eq!(planes, plane_data[0].len());
    Ok(write_npz(&arrays)?)
}

/// Every planned deformation's entry as written (complete ones), the ids of those missing, and
/// the failed draws recorded beside them (sorted by file name).
#[allow(clippy::type_complexity)]
pub(super) fn collect_entries(
    dir: &Path,
    def_plan: &[DeformationPlan],
    read_entry: &dyn Fn(&DeformationPlan) -> Option<DeformationEntry>,
) -> (Vec<DeformationEntry>, Vec<String>, Vec<FailedEntry>) {
    let mut deformations = Vec::new();
    let mut missing = Vec::new();
    let mut failed = Vec::new();
    for d in def_plan {
        match read_entry(d) {
            Some(e) => deformations.push(e),
            None => missing.push(d.id.clone()),
        }
        if let Ok(rd) = std::fs::read_dir(dir.join(format!("deformations/{}", d.id))) {
            let mut names: Vec<PathBuf> = rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("failed-") && n.ends_with(".json"))
                })
                .collect();
            names.sort();
            for p in names {
                if let Ok(t) = std::fs::read_to_string(&p)
                    && let Ok(f) = serde_json::from_str::<FailedEntry>(&t)
                {
                    failed.push(f);
                }
            }
        }
    }
    (deformations, missing, failed)
}

/// Writes a deformation's ground truth (`BASE/gt.vtu`), one `.vtp` per scenario and
/// `scenarios.npz`; returns the scenarios' manifest entries.
pub(super) fn write_scenarios(
    dir: &Path,
    base: &str,
    b: &Built,
    u: &[f64],
    scenarios: &[Scenario],
) -> Result<Vec<ScenarioEntry>, PhantomError> {
    let mut gt = b.mesh.to_file();
    gt.point_data = vec![DataArray::new("displacement", 3, u.to_vec())];
    write_mesh_file(&dir.join(format!("{base}/gt.vtu")), &gt)?;
    let mut entries = Vec::with_capacity(scenarios.len());
    for (k, c) in scenarios.iter().enumerate() {
        let file = format!("{base}/scenarios/{k:04}.vtp");
        let pts = MeshFile {
            nodes: c.points.clone(),
            point_data: vec![
                DataArray::new("kind", 1, c.kind.iter().map(|&k| k as u8 as f64).collect()),
                DataArray::new("plane", 1, c.plane.iter().map(|&p| p as f64).collect()),
                DataArray::new("feature", 1, c.feature.iter().map(|&f| f as f64).collect()),
                DataArray::new(
                    "truth_image",
                    3,
                    c.truth_image.iter().flatten().copied().collect(),
                ),
            ],
            ..Default::default()
        };
        write_mesh_file(&dir.join(&file), &pts)?;
        entries.push(ScenarioEntry {
            index: k,
            category: c.category.name().into(),
            seed: c.seed,
            file,
            coverage: c.coverage,
            surface_points: c.count(PointKind::Surface),
            contour_points: c.count(PointKind::PosteriorContour),
            vessel_points: c.count(PointKind::Vessel),
            feature_points: c.feature.iter().filter(|&&f| f > 0).count(),
            misalignment_deg: c.image_to_physical.rotation_angle_deg(),
        });
    }
    crate::util::write_atomic(
        &dir.join(format!("{base}/scenarios.npz")),
        &scenarios_npz(&b.mesh, u, scenarios)?,
    )?;
    Ok(entries)
}
