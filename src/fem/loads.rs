//! Consistent nodal loads for P1 tets (mN): body forces, surface tractions, pressure, point loads.
//!
//! Load vectors are node-major (`3·node + axis`) and are added into, so several loads combine.

use crate::mesh::TetMesh;
use crate::mesh::vec3::{cross, sub};

/// Adds a uniform body force `b` (mN/mm³, e.g. ρg) to `f`: each tet gives `b·|V|/4` to each node.
pub fn add_body_force(f: &mut [f64], mesh: &TetMesh, b: [f64; 3]) {
    for (t, tet) in mesh.tets().iter().enumerate() {
        let w = mesh.tet_volume(t).abs() / 4.0;
        for &v in tet {
            for a in 0..3 {
                f[3 * v as usize + a] += b[a] * w;
            }
        }
    }
}

/// Adds constant tractions (kPa = mN/mm²) on triangles: each corner gets `t·A/3`.
/// `traction` holds one vector per triangle.
///
/// # Panics
/// If `traction.len() != triangles.len()` (a programming error, not user input).
pub fn add_traction(
    f: &mut [f64],
    nodes: &[[f64; 3]],
    triangles: &[[u32; 3]],
    traction: &[[f64; 3]],
) {
    assert_eq!(
        traction.len(),
        triangles.len(),
        "add_traction: one traction vector per triangle"
    );
    for (tri, t) in triangles.iter().zip(traction) {
        let area = triangle_area(nodes, tri);
        for &v in tri {
            for a in 0..3 {
                f[3 * v as usize + a] += t[a] * area / 3.0;
            }
        }
    }
}

/// Adds a uniform pressure `p` (kPa) on triangles: force `−p·n·A` with `n` the triangle's
/// right-hand normal (outward for boundary faces), so positive pressure pushes inward.
pub fn add_pressure(f: &mut [f64], nodes: &[[f64; 3]], triangles: &[[u32; 3]], p: f64) {
    for tri in triangles {
        let (a, b, c) = (
            nodes[tri[0] as usize],
            nodes[tri[1] as usize],
            nodes[tri[2] as usize],
        );
        // n·A = (b−a)×(c−a)/2
        let na = cross(sub(b, a), sub(c, a)).map(|x| 0.5 * x);
        for &v in tri {
            for k in 0..3 {
                f[3 * v as usize + k] -= p * na[k] / 3.0;
            }
        }
    }
}

/// Adds a point load (mN) at a node.
pub fn add_point_load(f: &mut [f64], node: u32, force: [f64; 3]) {
    for a in 0..3 {
        f[3 * node as usize + a] += force[a];
    }
}

fn triangle_area(nodes: &[[f64; 3]], tri: &[u32; 3]) -> f64 {
    let (a, b, c) = (
        nodes[tri[0] as usize],
        nodes[tri[1] as usize],
        nodes[tri[2] as usize],
    );
    let n = cross(sub(b, a), sub(c, a));
    0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::procedural::box_mesh;

    #[test]
    fn resultants_equal_integrals() {
        // Total body force = b·V; total pressure force on a closed surface = 0; traction = t·A.
        let m = box_mesh([2.0, 3.0, 1.0], [3, 3, 2], 0.2);
        let n = m.num_nodes();
        let mut f = vec![0.0; 3 * n];
        add_body_force(&mut f, &m, [0.0, 0.5, -1.0]);
        let sum = |f: &[f64], a: usize| (0..n).map(|i| f[3 * i + a]).sum::<f64>();
        assert!((sum(&f, 1) - 3.0).abs() < 1e-12 && (sum(&f, 2) + 6.0).abs() < 1e-12);
        let b = m.boundary().unwrap();
        let mut g = vec![0.0; 3 * n];
        add_pressure(&mut g, m.nodes(), &b.triangles, 2.5);
        for a in 0..3 {
            assert!(sum(&g, a).abs() < 1e-12);
        }
        let mut h = vec![0.0; 3 * n];
        let tr = vec![[1.0, 0.0, 2.0]; b.triangles.len()];
        add_traction(&mut h, m.nodes(), &b.triangles, &tr);
        let area = 2.0 * (2.0 * 3.0 + 3.0 * 1.0 + 2.0 * 1.0);
        assert!((sum(&h, 0) - area).abs() < 1e-10 && (sum(&h, 2) - 2.0 * area).abs() < 1e-10);
    }
}
