//! The measurement noise floor, estimated from the data alone: each surface point's distance to a
//! quadric fitted to its nearest neighbours in the same sweep (a surface patch is a dense sample
//! of a smooth surface, so what a local quadric cannot follow is noise), corrected for the
//! quadric's degrees of freedom.

use crate::mesh::vec3::{cross, dist2, dot, sub, unit};
use nalgebra::{DMatrix, DVector, SymmetricEigen};

/// Neighbours per local fit.
const NEIGHBOURS: usize = 16;

/// Noise standard deviation (mm) along the surface normal of a point set (one sweep's surface
/// points), with the number of local fits used; `None` with fewer than `NEIGHBOURS + 1` points.
pub fn noise_floor(points: &[[f64; 3]]) -> Option<(f64, usize)> {
    if points.len() <= NEIGHBOURS {
        return None;
    }
    let mut sum = 0.0;
    let mut count = 0usize;
    // At most 400 fits, spread over the points.
    let step = (points.len() / 400).max(1);
    for i in (0..points.len()).step_by(step) {
        let p = points[i];
        let mut idx: Vec<usize> = (0..points.len()).collect();
        idx.select_nth_unstable_by(NEIGHBOURS, |&a, &b| {
            dist2(points[a], p).total_cmp(&dist2(points[b], p))
        });
        let nb: Vec<[f64; 3]> = idx[..=NEIGHBOURS].iter().map(|&j| points[j]).collect();
        if let Some(r2) = quadric_residual(&nb) {
            sum += r2;
            count += 1;
        }
    }
    if count == 0 {
        return None;
    }
    // 6 quadric coefficients per NEIGHBOURS + 1 points.
    let k = (NEIGHBOURS + 1) as f64;
    Some(((sum / count as f64) * k / (k - 6.0)).sqrt().max(1e-6)).map(|s| (s, count))
}

/// Mean squared residual of a height-field quadric fitted in the points' principal frame.
fn quadric_residual(nb: &[[f64; 3]]) -> Option<f64> {
    let n = nb.len() as f64;
    let mut c = [0.0; 3];
    for p in nb {
        for a in 0..3 {
            c[a] += p[a] / n;
        }
    }
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    for p in nb {
        let d = sub(*p, c);
        for a in 0..3 {
            for b in 0..3 {
                cov[(a, b)] += d[a] * d[b];
            }
        }
    }
    let eig = SymmetricEigen::new(cov);
    let mut order = [0, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    let nrm = [0, 1, 2].map(|a| eig.eigenvectors[(a, order[0])]);
    let t1 = unit(if nrm[0].abs() < 0.9 {
        cross(nrm, [1.0, 0.0, 0.0])
    } else {
        cross(nrm, [0.0, 1.0, 0.0])
    });
    let t2 = cross(nrm, t1);
    let mut a = DMatrix::<f64>::zeros(nb.len(), 6);
    let mut h = DVector::<f64>::zeros(nb.len());
    for (i, p) in nb.iter().enumerate() {
        let d = sub(*p, c);
        let (x, y) = (dot(d, t1), dot(d, t2));
        for (j, v) in [x * x, x * y, y * y, x, y, 1.0].into_iter().enumerate() {
            a[(i, j)] = v;
        }
        h[i] = dot(d, nrm);
    }
    let ata = a.transpose() * &a;
    let atb = a.transpose() * &h;
    let sol = ata.cholesky()?.solve(&atb);
    let r = h - a * sol;
    Some(r.norm_squared() / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    /// Points on a curved surface with Gaussian noise of known σ along z: the estimate is within
    /// 15 % of σ, and of order zero without noise.
    #[test]
    fn noise_floor_recovers_a_known_sigma_on_a_curved_patch() {
        let mut rng = SplitMix64::new(3);
        let mut gauss = || {
            let (u1, u2) = (rng.next_f64().max(1e-12), rng.next_f64());
            (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
        };
        for sigma in [0.5, 1.5] {
            let mut pts = Vec::new();
            let mut clean = Vec::new();
            for i in 0..40 {
                for j in 0..40 {
                    let (x, y) = (i as f64 * 2.5, j as f64 * 2.5);
                    let z = 0.004 * x * x - 0.003 * x * y + 0.002 * y * y;
                    clean.push([x, y, z]);
                    pts.push([x, y, z + sigma * gauss()]);
                }
            }
            let (s, fits) = noise_floor(&pts).unwrap();
            assert!(fits > 100);
            assert!((s / sigma - 1.0).abs() < 0.15, "σ {sigma}: estimated {s}");
            let (s0, _) = noise_floor(&clean).unwrap();
            assert!(s0 < 0.05, "noise-free patch: {s0}");
        }
        assert!(noise_floor(&[[0.0; 3]; 5]).is_none());
    }
}
