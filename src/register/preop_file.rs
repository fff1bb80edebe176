//! A dataset's preoperative model from its files: the tet mesh with its anatomical labels
//! (`preop.vtu`) and the vessel centerlines (`vessels.vtp`).

use super::{PreopModel, RegisterError};
use crate::mesh::TetMesh;
use crate::mesh::io::MeshFile;

/// Builds a [`PreopModel`] from a dataset's `preop.vtu` (tet mesh with point arrays `region`
/// — 0 interior, 1 anterior, 2 posterior — and, when present, `falciform` and `inferior_ridge`
/// 0/1 flags) and its `vessels.vtp` (centerline points with a `parent` array, −1 for roots; an
/// empty file means no vessels). Errors name the file role, array and index.
pub fn preop_model_from_file(
    file: &MeshFile,
    vessels: &MeshFile,
) -> Result<PreopModel, RegisterError> {
    let mesh =
        TetMesh::from_file(file).map_err(|e| RegisterError::Model(format!("preop mesh: {e}")))?;
    let n = mesh.num_nodes();
    let array = |name: &str, required: bool| -> Result<Option<Vec<f64>>, RegisterError> {
        match file.point_array(name) {
            None if required => Err(RegisterError::Model(format!(
                "preop mesh: point array '{name}' is missing"
            ))),
            None => Ok(None),
            Some(a) => {
                if a.components != 1 || a.values.len() != n {
                    return Err(RegisterError::Model(format!(
                        "preop mesh: point array '{name}' has {} values in {} components, \
                         expected one per node ({n})",
                        a.values.len(),
                        a.components
                    )));
                }
                Ok(Some(a.values.clone()))
            }
        }
    };
    let region = array("region", true)?.unwrap_or_default();
    if let Some(i) = region
        .iter()
        .position(|&r| !(r == 0.0 || r == 1.0 || r == 2.0))
    {
        return Err(RegisterError::Model(format!(
            "preop mesh: region[{i}] is {}, expected 0 (interior), 1 (anterior) or 2 (posterior)",
            region[i]
        )));
    }
    let flags = |name: &str| -> Result<Vec<bool>, RegisterError> {
        let Some(v) = array(name, false)? else {
            return Ok(vec![false; n]);
        };
        if let Some(i) = v.iter().position(|&x| !(x == 0.0 || x == 1.0)) {
            return Err(RegisterError::Model(format!(
                "preop mesh: {name}[{i}] is {}, expected 0 or 1",
                v[i]
            )));
        }
        Ok(v.iter().map(|&x| x == 1.0).collect())
    };
    let falciform = flags("falciform")?;
    let inferior_ridge = flags("inferior_ridge")?;
    let (vessel_points, vessel_segments) = vessel_tree(vessels)?;
    Ok(PreopModel {
        mesh,
        anterior: region.iter().map(|&r| r == 1.0).collect(),
        posterior: region.iter().map(|&r| r == 2.0).collect(),
        falciform,
        inferior_ridge,
        vessel_points,
        vessel_segments,
    })
}

/// The vessel centerlines of a dataset's `vessels.vtp`: its points and one segment
/// `[parent, child]` per point with a parent (`parent` array, −1 for roots).
#[allow(clippy::type_complexity)]
fn vessel_tree(vessels: &MeshFile) -> Result<(Vec<[f64; 3]>, Vec<[u32; 2]>), RegisterError> {
    let vessel_points = vessels.nodes.clone();
    if let Some(i) = vessel_points
        .iter()
        .position(|p| p.iter().any(|c| !c.is_finite()))
    {
        return Err(RegisterError::Model(format!(
            "vessels: point {i} is not finite"
        )));
    }
    let mut vessel_segments = Vec::new();
    if !vessel_points.is_empty() {
        let parent = vessels.point_array("parent").ok_or_else(|| {
            RegisterError::Model("vessels: point array 'parent' is missing".into())
        })?;
        if parent.components != 1 || parent.values.len() != vessel_points.len() {
            return Err(RegisterError::Model(format!(
                "vessels: point array 'parent' has {} values, expected one per point ({})",
                parent.values.len(),
                vessel_points.len()
            )));
        }
        for (i, &p) in parent.values.iter().enumerate() {
            if p == -1.0 {
                continue;
            }
            if !(p >= 0.0 && p.fract() == 0.0 && (p as usize) < vessel_points.len())
                || p as usize == i
            {
                return Err(RegisterError::Model(format!(
                    "vessels: parent[{i}] is {p}, expected −1 or the index of another of the {} \
                     points",
                    vessel_points.len()
                )));
            }
            vessel_segments.push([p as u32, i as u32]);
        }
    }
    Ok((vessel_points, vessel_segments))
}
