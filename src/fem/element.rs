//! The P1 (linear) tetrahedron: shape-function gradients, element stiffness, strain and stress.

use crate::mesh::vec3::{cross, dot, sub};

/// Gradients of the four barycentric shape functions (1/mm) and the signed volume (mm³) of a tet;
/// `None` when the tet is degenerate (zero volume).
#[inline]
pub fn p1_gradients(p: &[[f64; 3]; 4]) -> Option<([[f64; 3]; 4], f64)> {
    let a = sub(p[1], p[0]);
    let b = sub(p[2], p[0]);
    let c = sub(p[3], p[0]);
    let bc = cross(b, c);
    let det = dot(a, bc);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    // Rows of J⁻¹ for J = [a b c]: (b×c, c×a, a×b) / det.
    let g1 = bc.map(|x| x * inv);
    let g2 = cross(c, a).map(|x| x * inv);
    let g3 = cross(a, b).map(|x| x * inv);
    let g0 = [
        -(g1[0] + g2[0] + g3[0]),
        -(g1[1] + g2[1] + g3[1]),
        -(g1[2] + g2[2] + g3[2]),
    ];
    Some(([g0, g1, g2, g3], det / 6.0))
}

/// Stiffness block `K_ij` (3×3, rows = components at node i, cols = components at node j) of a P1
/// tet with gradients `gi`, `gj`, volume `vol` (use |V|) and Lamé parameters (kPa):
/// `K_ij[a][b] = V (λ g_i[a] g_j[b] + μ (g_i[b] g_j[a] + δ_ab g_i·g_j))`.
#[inline]
pub fn stiffness_block(
    gi: [f64; 3],
    gj: [f64; 3],
    vol: f64,
    lambda: f64,
    mu: f64,
) -> [[f64; 3]; 3] {
    let d = dot(gi, gj);
    let mut k = [[0.0; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            let diag = if a == b { d } else { 0.0 };
            k[a][b] = vol * (lambda * gi[a] * gj[b] + mu * (gi[b] * gj[a] + diag));
        }
    }
    k
}

/// Full 12×12 element stiffness (dof order: node-major, `3·i + a`).
pub fn element_stiffness(p: &[[f64; 3]; 4], lambda: f64, mu: f64) -> Option<[[f64; 12]; 12]> {
    let (g, v) = p1_gradients(p)?;
    let mut k = [[0.0; 12]; 12];
    for i in 0..4 {
        for j in 0..4 {
            let b = stiffness_block(g[i], g[j], v.abs(), lambda, mu);
            for a in 0..3 {
                for c in 0..3 {
                    k[3 * i + a][3 * j + c] = b[a][c];
                }
            }
        }
    }
    Some(k)
}

/// Small strain ε = sym(∇u) of a P1 tet (constant), as a symmetric 3×3 matrix.
#[inline]
pub fn strain(g: &[[f64; 3]; 4], u: &[[f64; 3]; 4]) -> [[f64; 3]; 3] {
    let mut h = [[0.0; 3]; 3];
    for i in 0..4 {
        for a in 0..3 {
            for b in 0..3 {
                h[a][b] += u[i][a] * g[i][b];
            }
        }
    }
    let mut e = [[0.0; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            e[a][b] = 0.5 * (h[a][b] + h[b][a]);
        }
    }
    e
}

/// Cauchy stress σ = λ tr(ε) I + 2μ ε (kPa).
#[inline]
pub fn stress(eps: &[[f64; 3]; 3], lambda: f64, mu: f64) -> [[f64; 3]; 3] {
    let tr = eps[0][0] + eps[1][1] + eps[2][2];
    let mut s = [[0.0; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            s[a][b] = 2.0 * mu * eps[a][b] + if a == b { lambda * tr } else { 0.0 };
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tet() -> [[f64; 3]; 4] {
        [
            [0.1, 0.0, -0.2],
            [1.3, 0.2, 0.1],
            [0.2, 1.1, 0.3],
            [0.0, 0.4, 1.2],
        ]
    }

    #[test]
    fn gradients_reproduce_linear_fields() {
        // Σ_i f(p_i) g_i = ∇f for linear f, and Σ_i g_i = 0.
        let p = tet();
        let (g, v) = p1_gradients(&p).unwrap();
        assert!(v > 0.0);
        let grad = [0.7, -1.9, 2.3];
        let f = |x: [f64; 3]| 4.0 + dot(grad, x);
        for k in 0..3 {
            let s: f64 = (0..4).map(|i| f(p[i]) * g[i][k]).sum();
            assert!((s - grad[k]).abs() < 1e-13);
            let z: f64 = (0..4).map(|i| g[i][k]).sum();
            assert!(z.abs() < 1e-14);
        }
    }

    #[test]
    fn stiffness_is_symmetric_and_energy_matches_continuum() {
        // uᵀKu / 2 must equal V (λ/2 tr(ε)² + μ ε:ε) for any nodal displacement.
        let p = tet();
        let (lambda, mu) = (3.1, 1.7);
        let k = element_stiffness(&p, lambda, mu).unwrap();
        for i in 0..12 {
            for j in 0..12 {
                assert!((k[i][j] - k[j][i]).abs() < 1e-12);
            }
        }
        let u = [
            [0.1, -0.2, 0.05],
            [0.3, 0.1, -0.1],
            [-0.2, 0.4, 0.2],
            [0.0, 0.1, 0.3],
        ];
        let flat: Vec<f64> = u.iter().flatten().copied().collect();
        let mut e_k = 0.0;
        for i in 0..12 {
            for j in 0..12 {
                e_k += 0.5 * flat[i] * k[i][j] * flat[j];
            }
        }
        let (g, v) = p1_gradients(&p).unwrap();
        let eps = strain(&g, &u);
        let sig = stress(&eps, lambda, mu);
        let e_c: f64 = 0.5
            * v
            * (0..3)
                .flat_map(|a| (0..3).map(move |b| (a, b)))
                .map(|(a, b)| sig[a][b] * eps[a][b])
                .sum::<f64>();
        assert!(
            (e_k - e_c).abs() < 1e-12 * e_c.abs().max(1.0),
            "{e_k} {e_c}"
        );
    }

    #[test]
    fn degenerate_tet_has_no_gradients() {
        let p = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 0.]];
        assert!(p1_gradients(&p).is_none());
    }
}
