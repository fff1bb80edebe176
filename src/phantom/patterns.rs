//! Deformation patterns after the LIBR+ paper, randomised from a seed: what loads the "true organ".
//!
//! All patterns include gravity on a supine patient (+y, LPS) and the posterior support: isotropic
//! springs on the bare-area nodes (stiffness per unit surface area, lumped to nodes) and softer
//! springs on the rest of the posterior surface (the organ bed; normal, with 10 % of that
//! tangentially). On top:
//!
//! - **L** (laparoscopic, left-lobe retraction): a patch of the left lobe's inferior ridge is lifted
//!   anteriorly and superiorly by a retractor (prescribed displacement).
//! - **R** (laparoscopic, right-lobe packing): a surgical pack under the right lobe pushes a patch of
//!   its posterior-inferior surface anteriorly and superiorly (surface traction).
//! - **W** (laparoscopic, whole organ): stronger gravity plus insufflation pressure on the whole
//!   anterior surface.
//! - **V** (open surgery, test only): posterior packing over a large part of the posterior surface
//!   pushing the organ anteriorly, plus gravity.
//!
//! Loads are dead loads on the reference configuration (see `fem::hyperelastic`).

use super::labels::{AnatomyLabels, Region};
use crate::fem::{Dirichlet, NodeSpring, loads};
use crate::mesh::{TetMesh, TriSurface};
use crate::util::SplitMix64;

/// A deformation pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum Pattern {
    /// Left-lobe retraction.
    L,
    /// Right-lobe packing.
    R,
    /// Whole-organ gravity and pneumoperitoneum.
    W,
    /// Open surgery: posterior packing, large anterior motion (test only).
    V,
}

/// Parameters shared by all patterns (units: mm, kPa, mN).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PatternParams {
    /// Body force of gravity (mN/mm³), along +y. Default 0.0104.
    pub gravity: f64,
    /// Bare-area spring stiffness per unit area (mN/mm per mm²). Default 0.5.
    pub bare_area_stiffness: f64,
    /// Organ-bed normal spring stiffness per unit area on the posterior surface. Default 0.08.
    pub bed_stiffness: f64,
}

impl Default for PatternParams {
    fn default() -> Self {
        Self {
            gravity: 0.0104,
            bare_area_stiffness: 0.5,
            bed_stiffness: 0.08,
        }
    }
}

/// One randomised load case: constraints, springs and dead loads.
#[derive(Debug, Clone)]
pub struct LoadCase {
    /// Pattern.
    pub pattern: Pattern,
    /// Seed it was drawn from.
    pub seed: u64,
    /// Prescribed displacements (retractor).
    pub dirichlet: Dirichlet,
    /// Support springs.
    pub springs: Vec<NodeSpring>,
    /// External dead load (mN, node-major).
    pub load: Vec<f64>,
    /// What was drawn, for provenance.
    pub description: String,
}

/// Area lumped to each node from the boundary triangles (a third of each triangle).
fn node_areas(nodes: &[[f64; 3]], triangles: &[[u32; 3]], n: usize) -> Vec<f64> {
    let mut a = vec![0.0; n];
    let s = TriSurface::new(nodes.to_vec(), triangles.to_vec()).ok();
    if let Some(s) = s {
        for (t, area) in triangles.iter().zip(s.triangle_areas()) {
            for &v in t {
                a[v as usize] += area / 3.0;
            }
        }
    }
    a
}

/// Adds a uniform traction on the boundary triangles whose three nodes satisfy `inside`; returns
/// how many triangles were loaded.
fn push_patch(
    load: &mut [f64],
    nodes: &[[f64; 3]],
    triangles: &[[u32; 3]],
    traction: [f64; 3],
    inside: impl Fn(usize) -> bool,
) -> usize {
    let patch: Vec<[u32; 3]> = triangles
        .iter()
        .copied()
        .filter(|t| t.iter().all(|&v| inside(v as usize)))
        .collect();
    loads::add_traction(load, nodes, &patch, &vec![traction; patch.len()]);
    patch.len()
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if l > 0.0 { v.map(|x| x / l) } else { v }
}

/// Draws a load case of `pattern` for a labelled liver mesh.
pub fn load_case(
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    pattern: Pattern,
    params: &PatternParams,
    seed: u64,
) -> Result<LoadCase, String> {
    let n = mesh.num_nodes();
    let nodes = mesh.nodes();
    let boundary = mesh.boundary().map_err(|e| e.to_string())?;
    let surface = TriSurface::new(nodes.to_vec(), boundary.triangles.clone())?;
    let normals = surface.vertex_normals();
    let area = node_areas(nodes, &boundary.triangles, n);
    let mut rng = SplitMix64::new(seed ^ (pattern as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut uniform = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
    let (lo, hi) = mesh.bounding_box();
    let x_f = {
        let f = AnatomyLabels::nodes_where(&labels.falciform);
        if f.is_empty() {
            0.5 * (lo[0] + hi[0])
        } else {
            f.iter().map(|&i| nodes[i as usize][0]).sum::<f64>() / f.len() as f64
        }
    };
    let centroid_z = 0.5 * (lo[2] + hi[2]);
    // Supports.
    let mut springs = Vec::new();
    for i in 0..n {
        if labels.bare_area[i] {
            springs.push(NodeSpring::isotropic(
                i as u32,
                params.bare_area_stiffness * area[i],
            ));
        } else if labels.region[i] == Region::Posterior {
            // The bed resists sliding a little too (attachments, friction): 10 % tangentially.
            let k = params.bed_stiffness * area[i];
            springs.push(NodeSpring::normal_tangent(i as u32, normals[i], k, 0.1 * k));
        }
    }
    if !labels.bare_area.iter().any(|&b| b) {
        return Err("the mesh has no bare-area nodes to support it".into());
    }
    let mut load = vec![0.0; 3 * n];
    let mut dirichlet = Dirichlet::new(n);
    let pick =
        |cands: &[u32], r: f64| cands[((r * cands.len() as f64) as usize).min(cands.len() - 1)];
    let description = match pattern {
        Pattern::L => {
            let g = uniform(0.8, 1.2);
            loads::add_body_force(&mut load, mesh, [0.0, g * params.gravity, 0.0]);
            let ridge: Vec<u32> = AnatomyLabels::nodes_where(&labels.inferior_ridge)
                .into_iter()
                .filter(|&i| nodes[i as usize][0] > x_f)
                .collect();
            let cands = if ridge.is_empty() {
                labels
                    .nodes_in(Region::Anterior)
                    .into_iter()
                    .filter(|&i| nodes[i as usize][0] > x_f && nodes[i as usize][2] < centroid_z)
                    .collect()
            } else {
                ridge
            };
            if cands.is_empty() {
                return Err("no left-lobe surface to retract".into());
            }
            let c = nodes[pick(&cands, uniform(0.0, 1.0)) as usize];
            let radius = uniform(10.0, 18.0);
            let lift = uniform(10.0, 25.0);
            let dir = unit([uniform(-0.3, 0.3), -uniform(0.5, 1.0), uniform(0.3, 1.0)]);
            let mut count = 0;
            for &v in &boundary.nodes {
                if dist(nodes[v as usize], c) <= radius {
                    dirichlet.prescribe_node(v, dir.map(|d| d * lift));
                    count += 1;
                }
            }
            format!(
                "gravity x{g:.2}; retractor at {c:.1?} radius {radius:.1} mm ({count} nodes) lifts {lift:.1} mm along {dir:.2?}"
            )
        }
        Pattern::R => {
            let g = uniform(0.8, 1.2);
            loads::add_body_force(&mut load, mesh, [0.0, g * params.gravity, 0.0]);
            let cands: Vec<u32> = labels
                .nodes_in(Region::Posterior)
                .into_iter()
                .filter(|&i| nodes[i as usize][0] < x_f && nodes[i as usize][2] < centroid_z)
                .collect();
            if cands.is_empty() {
                return Err("no right-lobe posterior-inferior surface to pack".into());
            }
            let c = nodes[pick(&cands, uniform(0.0, 1.0)) as usize];
            let radius = uniform(25.0, 40.0);
            let p = uniform(0.3, 0.8);
            let dir = unit([uniform(-0.2, 0.2), -1.0, uniform(0.2, 0.8)]);
            let count = push_patch(
                &mut load,
                nodes,
                &boundary.triangles,
                dir.map(|d| d * p),
                |v| dist(nodes[v], c) <= radius,
            );
            format!(
                "gravity x{g:.2}; pack at {c:.1?} radius {radius:.1} mm ({count} triangles), traction {p:.2} kPa along {dir:.2?}"
            )
        }
        Pattern::W => {
            let g = uniform(1.0, 1.4);
            loads::add_body_force(&mut load, mesh, [0.0, g * params.gravity, 0.0]);
            let p = uniform(0.03, 0.1);
            let anterior: Vec<[u32; 3]> = boundary
                .triangles
                .iter()
                .copied()
                .filter(|t| {
                    t.iter()
                        .all(|&v| labels.region[v as usize] == Region::Anterior)
                })
                .collect();
            loads::add_pressure(&mut load, nodes, &anterior, p);
            format!(
                "gravity x{g:.2}; insufflation pressure {p:.2} kPa on {} anterior triangles",
                anterior.len()
            )
        }
        Pattern::V => {
            let g = uniform(0.8, 1.2);
            loads::add_body_force(&mut load, mesh, [0.0, g * params.gravity, 0.0]);
            let cy = 0.5 * (lo[1] + hi[1]);
            let p = uniform(0.4, 1.0);
            let dir = unit([uniform(-0.2, 0.2), -1.0, uniform(-0.2, 0.4)]);
            let count = push_patch(
                &mut load,
                nodes,
                &boundary.triangles,
                dir.map(|d| d * p),
                |v| {
                    labels.region[v] == Region::Posterior
                        && !labels.bare_area[v]
                        && nodes[v][1] > cy
                },
            );
            format!(
                "gravity x{g:.2}; posterior packing {p:.2} kPa along {dir:.2?} on {count} triangles"
            )
        }
    };
    Ok(LoadCase {
        pattern,
        seed,
        dirichlet,
        springs,
        load,
        description,
    })
}
