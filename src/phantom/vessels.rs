//! A synthetic vessel tree inside a liver and the stiffness heterogeneity it causes.
//!
//! The tree grows from a hilum point (the deepest interior point in the posterior-inferior quarter)
//! by recursive bifurcation: each segment continues its parent's direction with a random deviation
//! (the deepest-ending of a few candidates),
//! splits into two children at `branch_angle_deg` ± jitter, radius × `radius_ratio` (Murray-like
//! narrowing) and length × `length_ratio`; a segment is kept only if its end stays inside the liver
//! by at least its radius + `margin_mm` (signed distance to the boundary). Deterministic for a seed.
//! Tets whose centroid lies inside a vessel tube get their Young's modulus multiplied by
//! `stiffness_factor` (vessel walls and blood-filled vessels are stiffer than parenchyma).

use super::PhantomError;
use crate::fem::{LameField, LinearMaterial};
use crate::mesh::spatial::SignedDistance;
use crate::mesh::{TetMesh, TriSurface};
use crate::util::SplitMix64;

/// Parameters of the vessel tree (lengths in mm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VesselParams {
    /// Radius of the root segment. Default 6.
    pub root_radius_mm: f64,
    /// Length of the root segment. Default 35.
    pub root_length_mm: f64,
    /// Child/parent radius ratio. Default 0.8.
    pub radius_ratio: f64,
    /// Child/parent length ratio. Default 0.8.
    pub length_ratio: f64,
    /// Branches thinner than this are not grown. Default 1.
    pub min_radius_mm: f64,
    /// Half-angle between the two children (degrees). Default 35.
    pub branch_angle_deg: f64,
    /// Random deviation of directions (degrees). Default 15.
    pub jitter_deg: f64,
    /// Clearance between a vessel and the liver surface. Default 2.
    pub margin_mm: f64,
    /// Young's modulus multiplier inside vessels (3–10 for vessels/tumours). Default 5.
    pub stiffness_factor: f64,
    /// Also grow a hepatic-vein tree from the posterior-superior liver (near the vena cava).
    /// Default true.
    pub hepatic_tree: bool,
    /// Seed.
    pub seed: u64,
}

impl Default for VesselParams {
    fn default() -> Self {
        Self {
            root_radius_mm: 6.0,
            root_length_mm: 35.0,
            radius_ratio: 0.8,
            length_ratio: 0.8,
            min_radius_mm: 1.0,
            branch_angle_deg: 35.0,
            jitter_deg: 15.0,
            margin_mm: 2.0,
            stiffness_factor: 5.0,
            hepatic_tree: true,
            seed: 0,
        }
    }
}

/// Vessel centerlines: points with radii, joined by segments `[parent, child]`; a forest whose roots
/// (points no segment ends at) are the portal hilum (point 0) and, with `hepatic_tree`, the
/// hepatic-vein root.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct VesselTree {
    /// Centerline points (mm).
    pub points: Vec<[f64; 3]>,
    /// Tube radius at each point (mm).
    pub radii: Vec<f64>,
    /// Segments `[parent point, child point]`.
    pub segments: Vec<[u32; 2]>,
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn normalize(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    if l > 0.0 {
        a.map(|x| x / l)
    } else {
        [0.0, 0.0, 1.0]
    }
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Rotates `d` by `angle` (radians) about a random axis perpendicular to it.
fn deviate(d: [f64; 3], angle: f64, rng: &mut SplitMix64) -> [f64; 3] {
    let helper = if d[0].abs() < 0.9 {
        [1.0, 0.0, 0.0]
    } else {
        [0.0, 1.0, 0.0]
    };
    let u = normalize(cross(d, helper));
    let v = cross(d, u);
    let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
    let axis = [0, 1, 2].map(|k| u[k] * phi.cos() + v[k] * phi.sin());
    normalize([0, 1, 2].map(|k| d[k] * angle.cos() + axis[k] * angle.sin()))
}

pub use crate::mesh::spatial::point_segment_distance;

impl VesselTree {
    /// Grows a tree inside the liver mesh (LPS frame).
    pub fn grow(mesh: &TetMesh, params: &VesselParams) -> Result<Self, PhantomError> {
        if !(params.radius_ratio > 0.0 && params.radius_ratio < 1.0) {
            return Err(PhantomError::Parameter(format!(
                "radius_ratio must be in (0, 1), got {}",
                params.radius_ratio
            )));
        }
        if !(params.min_radius_mm > 0.0 && params.root_radius_mm >= params.min_radius_mm) {
            return Err(PhantomError::Parameter(
                "need 0 < min_radius_mm ≤ root_radius_mm".into(),
            ));
        }
        let boundary = mesh.boundary()?;
        let surface = TriSurface::new(mesh.nodes().to_vec(), boundary.triangles)?;
        let sd = SignedDistance::new(&surface)?;
        let (lo, hi) = mesh.bounding_box();
        let centre = [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k]));
        let depth = |p: [f64; 3]| -sd.eval(p);
        // The deepest node in a quarter of the liver (the whole liver if the quarter is empty).
        let deepest = |keep: &dyn Fn(&[f64; 3]) -> bool| {
            mesh.nodes()
                .iter()
                .filter(|p| keep(p))
                .map(|&p| (depth(p), p))
                .max_by(|a, b| a.0.total_cmp(&b.0))
                .or_else(|| {
                    mesh.nodes()
                        .iter()
                        .map(|&p| (depth(p), p))
                        .max_by(|a, b| a.0.total_cmp(&b.0))
                })
        };
        // Portal tree from the hilum (posterior-inferior quarter); hepatic-vein tree from near the
        // vena cava (posterior-superior quarter), both heading for the liver's centre.
        let mut roots = vec![
            deepest(&|p| p[1] > centre[1] && p[2] < centre[2])
                .ok_or_else(|| PhantomError::Geometry("mesh has no nodes".into()))?,
        ];
        if params.hepatic_tree {
            roots.push(
                deepest(&|p| p[1] > centre[1] && p[2] > centre[2])
                    .ok_or_else(|| PhantomError::Geometry("mesh has no nodes".into()))?,
            );
        }
        let mut rng = SplitMix64::new(params.seed ^ 0x0E55_E150_0000_0001);
        let mut tree = VesselTree {
            points: Vec::new(),
            radii: Vec::new(),
            segments: Vec::new(),
        };
        let jitter = params.jitter_deg.to_radians();
        let branch = params.branch_angle_deg.to_radians();
        for (k, root) in roots.into_iter().enumerate() {
            let root_index = tree.points.len() as u32;
            tree.points.push(root.1);
            tree.radii
                .push(params.root_radius_mm.min(0.5 * root.0.max(0.0)));
            let first = normalize(sub(centre, root.1));
            let radius0 = if k == 0 {
                params.root_radius_mm
            } else {
                params.root_radius_mm * params.radius_ratio
            };
            let mut stack = vec![(root_index, first, params.root_length_mm, radius0)];
            let root_segments = tree.segments.len();
            while let Some((parent, dir, length, radius)) = stack.pop() {
                if radius < params.min_radius_mm || tree.points.len() > 4096 {
                    continue;
                }
                // Of a few random deviations, take the one that ends deepest inside the liver (the
                // root may turn further, to find its way from the hilum into the parenchyma).
                let start = tree.points[parent as usize];
                let spread = if parent == root_index && tree.segments.len() == root_segments {
                    4.0 * jitter
                } else {
                    jitter
                };
                // A branch that does not fit at full length is tried shorter.
                let (end_depth, d, end, length) = [1.0, 0.7, 0.5]
                    .iter()
                    .flat_map(|f| {
                        let len = length * f;
                        (0..8)
                            .map(|_| {
                                let d = deviate(dir, spread * rng.next_f64(), &mut rng);
                                let end = [0, 1, 2].map(|k| start[k] + len * d[k]);
                                (depth(end), d, end, len)
                            })
                            .collect::<Vec<_>>()
                    })
                    .find(|c| c.0 >= radius + params.margin_mm)
                    .unwrap_or((f64::NEG_INFINITY, dir, start, length));
                if end_depth < radius + params.margin_mm {
                    continue;
                }
                tree.points.push(end);
                tree.radii.push(radius);
                let child = (tree.points.len() - 1) as u32;
                tree.segments.push([parent, child]);
                let (r2, l2) = (radius * params.radius_ratio, length * params.length_ratio);
                for sign in [1.0, -1.0] {
                    let a = sign * branch * (0.7 + 0.6 * rng.next_f64());
                    stack.push((child, deviate(d, a.abs(), &mut rng), l2, r2));
                }
            }
        }
        Ok(tree)
    }

    /// Distance from `p` to the nearest tube surface (negative inside a vessel), and whether any.
    pub fn clearance(&self, p: [f64; 3]) -> f64 {
        self.segments
            .iter()
            .map(|s| {
                let (a, b) = (self.points[s[0] as usize], self.points[s[1] as usize]);
                let (d, t) = point_segment_distance(p, a, b);
                let r = self.radii[s[0] as usize] * (1.0 - t) + self.radii[s[1] as usize] * t;
                d - r
            })
            .fold(f64::INFINITY, f64::min)
    }

    /// Per-tet flag: the tet's centroid is inside a vessel tube.
    pub fn tets_inside(&self, mesh: &TetMesh) -> Vec<bool> {
        (0..mesh.num_tets())
            .map(|t| {
                let p = mesh.tet_points(t);
                let c = [0, 1, 2].map(|k| 0.25 * (p[0][k] + p[1][k] + p[2][k] + p[3][k]));
                self.clearance(c) < 0.0
            })
            .collect()
    }

    /// Heterogeneous Lamé field: `material` in the parenchyma, `stiffness_factor × E` (same ν)
    /// inside vessels.
    pub fn lame_field(
        &self,
        mesh: &TetMesh,
        material: &LinearMaterial,
        stiffness_factor: f64,
    ) -> LameField {
        let soft = material.lame();
        let hard = LinearMaterial::new(
            material.youngs_modulus_kpa * stiffness_factor,
            material.poisson_ratio,
        )
        .lame();
        LameField::PerTet(
            self.tets_inside(mesh)
                .into_iter()
                .map(|v| if v { hard } else { soft })
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segment_distance_closed_form() {
        let (d, t) = point_segment_distance([1.0, 2.0, 0.0], [0.0; 3], [4.0, 0.0, 0.0]);
        assert!((d - 2.0).abs() < 1e-15 && (t - 0.25).abs() < 1e-15);
        let (d, t) = point_segment_distance([-3.0, 4.0, 0.0], [0.0; 3], [4.0, 0.0, 0.0]);
        assert!((d - 5.0).abs() < 1e-15 && t == 0.0);
    }
}
