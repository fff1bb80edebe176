//! Preconditioned conjugate gradients for the Newton systems of the nonlinear model.

use super::{dot, norm};

/// What [`pcg`] returns.
#[derive(Debug, Clone, PartialEq)]
pub struct Pcg {
    /// The approximate solution.
    pub x: Vec<f64>,
    /// Iterations run (operator applications).
    pub iterations: usize,
    /// Final relative residual `‖b − Ax‖ / ‖b‖`.
    pub relative_residual: f64,
    /// The operator showed a direction of non-positive curvature (`pᵀAp ≤ 0`): `x` is the
    /// iterate before it (the preconditioned residual when it came first), a descent direction
    /// of the quadratic model all the same.
    pub negative_curvature: bool,
}

/// Solves `A x = b` by conjugate gradients preconditioned with `m_inv` (`M⁻¹ v`, symmetric
/// positive definite), from `x = 0`, until `‖b − Ax‖ ≤ eta ‖b‖` or `max_it` iterations (Hestenes
/// & Stiefel; Saad, "Iterative Methods for Sparse Linear Systems", Alg. 9.1). Stops at a
/// direction of non-positive curvature (Steihaug's rule): an indefinite `A` (a tangent past a
/// limit point) still yields a descent direction.
pub fn pcg(
    mut a: impl FnMut(&[f64]) -> Vec<f64>,
    mut m_inv: impl FnMut(&[f64]) -> Vec<f64>,
    b: &[f64],
    eta: f64,
    max_it: usize,
) -> Pcg {
    let n = b.len();
    let bn = norm(b);
    let mut x = vec![0.0; n];
    if bn == 0.0 {
        return Pcg {
            x,
            iterations: 0,
            relative_residual: 0.0,
            negative_curvature: false,
        };
    }
    let mut r = b.to_vec();
    let mut z = m_inv(&r);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    let mut it = 0;
    let mut negative = false;
    while it < max_it {
        let q = a(&p);
        it += 1;
        let pq = dot(&p, &q);
        if pq.is_nan() || pq <= 0.0 || !rz.is_finite() {
            negative = true;
            if it == 1 {
                x = z;
            }
            break;
        }
        let step = rz / pq;
        for k in 0..n {
            x[k] += step * p[k];
            r[k] -= step * q[k];
        }
        if norm(&r) <= eta * bn {
            break;
        }
        z = m_inv(&r);
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        for k in 0..n {
            p[k] = z[k] + beta * p[k];
        }
    }
    Pcg {
        relative_residual: norm(&r) / bn,
        x,
        iterations: it,
        negative_curvature: negative,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 1-D Laplacian plus a diagonal: SPD, with a known solution.
    fn laplacian(x: &[f64]) -> Vec<f64> {
        let n = x.len();
        (0..n)
            .map(|i| {
                let l = if i > 0 { x[i - 1] } else { 0.0 };
                let r = if i + 1 < n { x[i + 1] } else { 0.0 };
                2.5 * x[i] - l - r
            })
            .collect()
    }

    #[test]
    fn solves_an_spd_system_to_its_tolerance() {
        let n = 50;
        let truth: Vec<f64> = (0..n).map(|i| (i as f64 * 0.3).sin()).collect();
        let b = laplacian(&truth);
        let out = pcg(laplacian, |v| v.to_vec(), &b, 1e-12, 200);
        assert!(!out.negative_curvature);
        assert!(out.relative_residual <= 1e-12);
        let err = out
            .x
            .iter()
            .zip(&truth)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-10, "max error {err}");
        // Exact preconditioner: one iteration.
        let exact = pcg(laplacian, |_| truth.clone(), &b, 1e-12, 5);
        assert_eq!(exact.iterations, 1);
    }

    #[test]
    fn stops_at_negative_curvature_with_a_descent_direction() {
        // A = diag(1, -1): indefinite; the first direction (the residual) has pᵀAp = 0 here.
        let a = |x: &[f64]| vec![x[0], -2.0 * x[1]];
        let b = [1.0, 1.0];
        let out = pcg(a, |v| v.to_vec(), &b, 1e-10, 10);
        assert!(out.negative_curvature);
        assert!(dot(&out.x, &b) > 0.0, "not a descent direction");
    }
}
