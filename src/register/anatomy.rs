//! Automatic anatomical labels of a liver tet mesh in the LPS frame (x left, y posterior,
//! z superior).
//!
//! - **Anterior / posterior surface**: every boundary node is anterior when its area-weighted
//!   outward normal points anteriorly (`n_y < 0`), posterior otherwise — a partition of the surface.
//! - **Inferior ridge**: the liver's anterior-inferior border as a laparoscope sees it: anterior
//!   nodes adjacent (by a boundary edge) to posterior nodes — where the surface turns from facing
//!   the camera to facing away — that lie on the lower outline of the anterior view (within
//!   `ridge_tolerance_mm` of the lowest boundary point in their `ridge_bin_mm`-wide x slice), below
//!   the centroid. Turns on the concave visceral surface, inside the outline, do not count.
//! - **Falciform ligament**: anterior nodes within a band around the sagittal plane
//!   `x = x_min + falciform_x_fraction·(x_max − x_min)` in the superior half; the ligament separates
//!   the (larger, patient-right = low-x) right lobe from the left lobe.
//! - **Bare area**: posterior nodes in the superior `bare_area_z_fraction` of the height on the
//!   right-lobe side of the falciform plane, where the liver is attached to the diaphragm (used as
//!   the spring support).
//! - **Targets**: interior nodes at least `target_depth_mm` from the surface, spread by farthest-point
//!   sampling from a seeded start.
//!
//! These are geometric stand-ins for what a clinician would mark; they are deterministic and only
//! need the mesh to be in LPS.

use super::RegisterError;
use crate::mesh::io::DataArray;
use crate::mesh::spatial::TriangleBvh;
use crate::mesh::{TetMesh, TriSurface};
use crate::util::SplitMix64;

/// Parameters of the automatic labelling. Lengths in mm.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LabelParams {
    /// Position of the falciform plane as a fraction of the x extent from x_min. Default 0.58.
    pub falciform_x_fraction: f64,
    /// Half-width of the falciform band (mm). Default 4.
    pub falciform_half_width_mm: f64,
    /// Top fraction of the height holding the bare area. Default 0.35.
    pub bare_area_z_fraction: f64,
    /// Width of the x slices used to find the lower outline (mm). Default 10.
    pub ridge_bin_mm: f64,
    /// Height above the lowest point of its slice within which a node is on the outline (mm).
    /// Default 8.
    pub ridge_tolerance_mm: f64,
    /// Number of interior targets. Default 8.
    pub targets: usize,
    /// Minimum depth of a target below the surface (mm). Default 10.
    pub target_depth_mm: f64,
    /// Seed of the first target.
    pub seed: u64,
}

impl Default for LabelParams {
    fn default() -> Self {
        Self {
            falciform_x_fraction: 0.58,
            falciform_half_width_mm: 4.0,
            bare_area_z_fraction: 0.35,
            ridge_bin_mm: 10.0,
            ridge_tolerance_mm: 8.0,
            targets: 8,
            target_depth_mm: 10.0,
            seed: 0,
        }
    }
}

/// Surface region of a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[repr(u8)]
pub enum Region {
    /// Not on the boundary.
    Interior = 0,
    /// Boundary, facing anteriorly (visible to a laparoscope or stylus).
    Anterior = 1,
    /// Boundary, facing posteriorly.
    Posterior = 2,
}

/// Per-node anatomical labels.
#[derive(Debug, Clone, PartialEq)]
pub struct AnatomyLabels {
    /// Region of each node.
    pub region: Vec<Region>,
    /// Falciform-ligament nodes.
    pub falciform: Vec<bool>,
    /// Inferior-ridge nodes.
    pub inferior_ridge: Vec<bool>,
    /// Bare-area nodes (posterior support).
    pub bare_area: Vec<bool>,
    /// Interior target nodes.
    pub targets: Vec<u32>,
}

impl AnatomyLabels {
    /// Indices of the nodes for which `flags` is set.
    pub fn nodes_where(flags: &[bool]) -> Vec<u32> {
        flags
            .iter()
            .enumerate()
            .filter(|(_, f)| **f)
            .map(|(i, _)| i as u32)
            .collect()
    }

    /// Nodes of a region.
    pub fn nodes_in(&self, region: Region) -> Vec<u32> {
        self.region
            .iter()
            .enumerate()
            .filter(|(_, r)| **r == region)
            .map(|(i, _)| i as u32)
            .collect()
    }

    /// The preoperative model registration sees: the mesh, these labels as its surfaces and
    /// salient features, and vessel centerlines (points and segments; empty for none).
    pub fn preop_model(
        &self,
        mesh: &TetMesh,
        vessel_points: &[[f64; 3]],
        vessel_segments: &[[u32; 2]],
    ) -> crate::register::PreopModel {
        let region = |want: Region| self.region.iter().map(|r| *r == want).collect();
        crate::register::PreopModel {
            mesh: mesh.clone(),
            anterior: region(Region::Anterior),
            posterior: region(Region::Posterior),
            falciform: self.falciform.clone(),
            inferior_ridge: self.inferior_ridge.clone(),
            vessel_points: vessel_points.to_vec(),
            vessel_segments: vessel_segments.to_vec(),
        }
    }

    /// The labels as point-data arrays (`region` 0/1/2, `falciform`, `inferior_ridge`,
    /// `bare_area`, `target` as 0/1), for `.vtu` files.
    pub fn to_point_data(&self) -> Vec<DataArray> {
        let flag = |v: &[bool]| v.iter().map(|&b| if b { 1.0 } else { 0.0 }).collect();
        let mut target = vec![0.0; self.region.len()];
        for &t in &self.targets {
            target[t as usize] = 1.0;
        }
        vec![
            DataArray::new(
                "region",
                1,
                self.region.iter().map(|r| *r as u8 as f64).collect(),
            ),
            DataArray::new("falciform", 1, flag(&self.falciform)),
            DataArray::new("inferior_ridge", 1, flag(&self.inferior_ridge)),
            DataArray::new("bare_area", 1, flag(&self.bare_area)),
            DataArray::new("target", 1, target),
        ]
    }
}

/// Labels a liver mesh given in LPS.
pub fn label(mesh: &TetMesh, params: &LabelParams) -> Result<AnatomyLabels, RegisterError> {
    let n = mesh.num_nodes();
    let boundary = mesh.boundary()?;
    let surface = TriSurface::new(mesh.nodes().to_vec(), boundary.triangles.clone())?;
    let normals = surface.vertex_normals();
    let mut region = vec![Region::Interior; n];
    for &v in &boundary.nodes {
        region[v as usize] = if normals[v as usize][1] < 0.0 {
            Region::Anterior
        } else {
            Region::Posterior
        };
    }
    let (lo, hi) = mesh.bounding_box();
    let nodes = mesh.nodes();
    let centroid_z = boundary
        .nodes
        .iter()
        .map(|&v| nodes[v as usize][2])
        .sum::<f64>()
        / boundary.nodes.len().max(1) as f64;
    // Inferior ridge: anterior nodes sharing a boundary edge with a posterior node, below the centroid.
    let mut inferior_ridge = vec![false; n];
    // Lowest boundary z per x slice (the lower outline of the anterior view).
    let bin_w = params.ridge_bin_mm.max(1e-6);
    let bins = (((hi[0] - lo[0]) / bin_w).ceil() as usize).clamp(1, 100_000);
    let bin_of = |x: f64| (((x - lo[0]) / bin_w) as usize).min(bins - 1);
    let mut zmin = vec![f64::INFINITY; bins];
    for &v in &boundary.nodes {
        let q = nodes[v as usize];
        let b = bin_of(q[0]);
        zmin[b] = zmin[b].min(q[2]);
    }
    for t in &boundary.triangles {
        for k in 0..3 {
            let (a, b) = (t[k] as usize, t[(k + 1) % 3] as usize);
            for (p, q) in [(a, b), (b, a)] {
                if region[p] == Region::Anterior
                    && region[q] == Region::Posterior
                    && nodes[p][2] < centroid_z
                    && nodes[p][2] <= zmin[bin_of(nodes[p][0])] + params.ridge_tolerance_mm
                {
                    inferior_ridge[p] = true;
                }
            }
        }
    }
    let x_f = lo[0] + params.falciform_x_fraction * (hi[0] - lo[0]);
    let falciform: Vec<bool> = (0..n)
        .map(|i| {
            region[i] == Region::Anterior
                && (nodes[i][0] - x_f).abs() <= params.falciform_half_width_mm
                && nodes[i][2] >= centroid_z
        })
        .collect();
    let z_cut = hi[2] - params.bare_area_z_fraction * (hi[2] - lo[2]);
    let bare_area: Vec<bool> = (0..n)
        .map(|i| region[i] == Region::Posterior && nodes[i][2] >= z_cut && nodes[i][0] < x_f)
        .collect();
    let targets = pick_targets(mesh, &surface, &region, params);
    Ok(AnatomyLabels {
        region,
        falciform,
        inferior_ridge,
        bare_area,
        targets,
    })
}

/// Farthest-point sampling of deep interior nodes.
fn pick_targets(
    mesh: &TetMesh,
    surface: &TriSurface,
    region: &[Region],
    params: &LabelParams,
) -> Vec<u32> {
    let bvh = TriangleBvh::new(surface);
    let deep: Vec<u32> = (0..mesh.num_nodes() as u32)
        .filter(|&i| {
            region[i as usize] == Region::Interior
                && bvh.distance(mesh.nodes()[i as usize]) >= params.target_depth_mm
        })
        .collect();
    if deep.is_empty() || params.targets == 0 {
        return Vec::new();
    }
    let mut rng = SplitMix64::new(params.seed ^ 0x7A96_E75E_ED00_0001);
    let mut chosen = vec![deep[rng.below(deep.len())]];
    let p = |i: u32| mesh.nodes()[i as usize];
    let d2 = |a: [f64; 3], b: [f64; 3]| {
        (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
    };
    let mut nearest: Vec<f64> = deep.iter().map(|&i| d2(p(i), p(chosen[0]))).collect();
    while chosen.len() < params.targets.min(deep.len()) {
        let (k, _) = nearest
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap_or((0, &0.0));
        let next = deep[k];
        chosen.push(next);
        for (j, &i) in deep.iter().enumerate() {
            nearest[j] = nearest[j].min(d2(p(i), p(next)));
        }
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::tetra::{TetraParams, tetrahedralize};

    /// A tet mesh of a sphere of radius 30 mm centred at (50, 50, 50).
    fn ball() -> TetMesh {
        let m = crate::mesh::procedural::box_mesh([100.0, 100.0, 100.0], [10, 10, 10], 0.0);
        // Use the box's boundary as a surface, projected onto the sphere.
        let s = m.boundary_surface().unwrap();
        let nodes = s
            .nodes()
            .iter()
            .map(|p| {
                let d = [p[0] - 50.0, p[1] - 50.0, p[2] - 50.0];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-9);
                [
                    50.0 + 30.0 * d[0] / l,
                    50.0 + 30.0 * d[1] / l,
                    50.0 + 30.0 * d[2] / l,
                ]
            })
            .collect();
        let sphere = TriSurface::new(nodes, s.triangles().to_vec())
            .unwrap()
            .compacted();
        tetrahedralize(&sphere, &TetraParams::with_edge(5.0)).unwrap()
    }

    #[test]
    fn labels_on_a_ball_follow_the_definitions() {
        let mesh = ball();
        let l = label(&mesh, &LabelParams::default()).unwrap();
        let p = mesh.nodes();
        let ant = l.nodes_in(Region::Anterior);
        let post = l.nodes_in(Region::Posterior);
        assert!(!ant.is_empty() && !post.is_empty());
        // On a sphere, facing anteriorly means lying on the anterior half (up to facet tilt).
        assert!(ant.iter().all(|&i| p[i as usize][1] < 50.0 + 3.0));
        assert!(post.iter().all(|&i| p[i as usize][1] > 50.0 - 3.0));
        // On a sphere the anterior–posterior seam is the equator x–z circle (y ≈ 50); its part on
        // the lower outline of the anterior view is the bottom of that circle.
        let ridge = AnatomyLabels::nodes_where(&l.inferior_ridge);
        assert!(!ridge.is_empty());
        for &i in &ridge {
            let q = p[i as usize];
            assert!((q[1] - 50.0).abs() < 6.0 && q[2] < 51.0, "ridge node {q:?}");
            // Within tolerance of the lowest sphere point in its x slice: z ≤ 50 − √(30² − dx²) + 8
            // (+ slice width and facet slack).
            let dx = ((q[0] - 50.0).abs() + 10.0).min(30.0);
            assert!(
                q[2] <= 50.0 - (900.0 - dx * dx).sqrt() + 8.0 + 2.0,
                "ridge node {q:?}"
            );
        }
        let falciform = AnatomyLabels::nodes_where(&l.falciform);
        assert!(!falciform.is_empty());
        let x_f = 20.0 + 0.58 * 60.0;
        assert!(
            falciform
                .iter()
                .all(|&i| (p[i as usize][0] - x_f).abs() <= 4.0)
        );
        // Bare area: posterior, top 35 % of the height (z ≥ 80 − 0.35·60 = 59), right of x_f.
        let bare = AnatomyLabels::nodes_where(&l.bare_area);
        assert!(!bare.is_empty());
        for &i in &bare {
            let q = p[i as usize];
            assert!(q[2] >= 59.0 - 1e-9 && q[0] < x_f && l.region[i as usize] == Region::Posterior);
        }
        // Targets: distinct, deep, spread.
        assert_eq!(l.targets.len(), 8);
        for &t in &l.targets {
            let q = p[t as usize];
            let r = ((q[0] - 50.0).powi(2) + (q[1] - 50.0).powi(2) + (q[2] - 50.0).powi(2)).sqrt();
            assert!(r <= 30.0 - 10.0 + 0.5, "target at depth {}", 30.0 - r);
        }
        let arrays = l.to_point_data();
        assert_eq!(arrays.len(), 5);
        assert!(arrays.iter().all(|a| a.len() == mesh.num_nodes()));
        // Deterministic.
        assert_eq!(l, label(&mesh, &LabelParams::default()).unwrap());
    }
}
