//! The boundary of a mesh as the effects see it: its nodes, faces, normals and lumped areas
//! ([`BoundaryGeometry`], computed once per mesh), the anatomical sites supports attach to
//! ([`Sites`]), and the boundary nodes near a point. Below both the table of kinds
//! ([`super::kinds`]) and the augmented model's solve ([`super::model`]), which read it.

use crate::mesh::TetMesh;
use crate::mesh::vec3::{cross, dist2, dot, sub, unit};
use crate::register::RegisterError;

/// Anatomical sites the supports attach to (per node flags, as in [`crate::register::PreopModel`]).
#[derive(Debug, Clone, Copy)]
pub struct Sites<'a> {
    /// Posterior boundary nodes (the organ bed).
    pub posterior: &'a [bool],
    /// Falciform-ligament nodes.
    pub falciform: &'a [bool],
}

/// The boundary quantities the effects need, computed once per mesh.
#[derive(Debug, Clone)]
pub struct BoundaryGeometry {
    /// Boundary nodes.
    pub nodes: Vec<u32>,
    /// Boundary triangles (outward).
    pub triangles: Vec<[u32; 3]>,
    /// Per triangle: unit outward normal, area, centroid.
    pub tri_normal: Vec<[f64; 3]>,
    /// Per triangle: area (mm²).
    pub tri_area: Vec<f64>,
    /// Per triangle: centroid.
    pub tri_center: Vec<[f64; 3]>,
    /// Per node (all nodes): lumped boundary area (mm², zero inside).
    pub node_area: Vec<f64>,
    /// Per node: area-weighted unit vertex normal (zero inside).
    pub node_normal: Vec<[f64; 3]>,
    /// Total volume (mm³).
    pub volume: f64,
}

impl BoundaryGeometry {
    /// Computes the boundary geometry of a mesh.
    pub fn new(mesh: &TetMesh) -> Result<Self, RegisterError> {
        let b = mesh.boundary()?;
        let nodes = mesh.nodes();
        let n = nodes.len();
        let mut node_area = vec![0.0; n];
        let mut node_normal = vec![[0.0; 3]; n];
        let (mut tri_normal, mut tri_area, mut tri_center) = (vec![], vec![], vec![]);
        for t in &b.triangles {
            let [p, q, r] = t.map(|v| nodes[v as usize]);
            let na = cross(sub(q, p), sub(r, p));
            let a = 0.5 * dot(na, na).sqrt();
            tri_normal.push(unit(na));
            tri_area.push(a);
            tri_center.push([0, 1, 2].map(|k| (p[k] + q[k] + r[k]) / 3.0));
            for &v in t {
                node_area[v as usize] += a / 3.0;
                for k in 0..3 {
                    node_normal[v as usize][k] += na[k];
                }
            }
        }
        for nn in node_normal.iter_mut() {
            *nn = unit(*nn);
        }
        Ok(Self {
            nodes: b.nodes,
            triangles: b.triangles,
            tri_normal,
            tri_area,
            tri_center,
            node_area,
            node_normal,
            volume: mesh.volume().abs(),
        })
    }
}

/// Boundary nodes within `radius` of `center`.
pub fn nodes_within(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    center: [f64; 3],
    radius: f64,
) -> Vec<u32> {
    geom.nodes
        .iter()
        .copied()
        .filter(|&v| dist2(mesh.nodes()[v as usize], center) <= radius * radius)
        .collect()
}
