//! Liver-like shape variants: smooth random deformations of a real liver surface, from a seed.
//!
//! A variant is the image of the surface under the map `φ(x) = c + S (x − c) + d(x)`, where `S` is
//! a random anisotropic scaling (per-axis factors in `[1 − scale_jitter, 1 + scale_jitter]`) about
//! the centroid `c`, and `d` is a sum of Gaussian radial bumps
//! `d(x) = Σ_k a_k exp(−|x − c_k|² / (2σ²))` with centres spread over the bounding box. The bump
//! amplitudes are scaled so that `Σ_k |a_k| / (σ√e) ≤ max_gradient < 1`, which bounds ‖∇d‖ and
//! makes `φ` a diffeomorphism: the variant is again a closed, consistently oriented surface with no
//! self-intersection, and anatomy drawn on the original maps onto it.

use super::PhantomError;
use crate::mesh::TriSurface;
use crate::util::SplitMix64;

/// Parameters of a shape variant. Lengths in mm.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ShapeVariantParams {
    /// Number of Gaussian bumps. Default 12.
    pub bumps: usize,
    /// Bump width σ as a fraction of the bounding-box diagonal. Default 0.18.
    pub width_fraction: f64,
    /// Bound on ‖∇d‖ (must be < 1 for a fold-free map). Default 0.45.
    pub max_gradient: f64,
    /// Per-axis scaling jitter. Default 0.12 (factors in [0.88, 1.12]).
    pub scale_jitter: f64,
}

impl Default for ShapeVariantParams {
    fn default() -> Self {
        Self {
            bumps: 12,
            width_fraction: 0.18,
            max_gradient: 0.45,
            scale_jitter: 0.12,
        }
    }
}

/// A smooth, invertible map of space drawn from a seed (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct ShapeMap {
    centroid: [f64; 3],
    scale: [f64; 3],
    centres: Vec<[f64; 3]>,
    amplitudes: Vec<[f64; 3]>,
    sigma: f64,
}

impl ShapeMap {
    /// Draws a map for a surface (its bounding box sets the bump positions and widths).
    pub fn random(
        surface: &TriSurface,
        params: &ShapeVariantParams,
        seed: u64,
    ) -> Result<Self, PhantomError> {
        if !(params.max_gradient > 0.0 && params.max_gradient < 1.0) {
            return Err(PhantomError::Parameter(format!(
                "max_gradient must be in (0, 1), got {}",
                params.max_gradient
            )));
        }
        if !(params.width_fraction > 0.0 && params.width_fraction.is_finite()) {
            return Err(PhantomError::Parameter(format!(
                "width_fraction must be > 0, got {}",
                params.width_fraction
            )));
        }
        if !(0.0..0.5).contains(&params.scale_jitter) {
            return Err(PhantomError::Parameter(format!(
                "scale_jitter must be in [0, 0.5), got {}",
                params.scale_jitter
            )));
        }
        let used = surface.used_vertices();
        if used.is_empty() {
            return Err(PhantomError::Parameter("surface has no triangles".into()));
        }
        let (lo, hi) = surface.bounding_box();
        let mut centroid = [0.0; 3];
        for &v in &used {
            for k in 0..3 {
                centroid[k] += surface.nodes()[v as usize][k] / used.len() as f64;
            }
        }
        let diag =
            ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt();
        let sigma = params.width_fraction * diag;
        let mut rng = SplitMix64::new(seed ^ 0x5AA9_E11F_0000_0001);
        let scale = [0; 3].map(|_| 1.0 + params.scale_jitter * (2.0 * rng.next_f64() - 1.0));
        let centres: Vec<[f64; 3]> = (0..params.bumps)
            .map(|_| [0, 1, 2].map(|k| lo[k] + rng.next_f64() * (hi[k] - lo[k])))
            .collect();
        let mut amplitudes: Vec<[f64; 3]> = (0..params.bumps)
            .map(|_| {
                // Uniform direction, magnitude in [0.3, 1] (normalised below).
                let z = 2.0 * rng.next_f64() - 1.0;
                let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
                let r = (1.0 - z * z).sqrt();
                let m = 0.3 + 0.7 * rng.next_f64();
                [m * r * phi.cos(), m * r * phi.sin(), m * z]
            })
            .collect();
        // ‖∇ of one bump‖ ≤ |a| / (σ√e); scale the sum to the gradient bound.
        let total: f64 =
            amplitudes.iter().map(|a| norm(*a)).sum::<f64>() / (sigma * 1f64.exp().sqrt());
        if total > 0.0 {
            let f = params.max_gradient / total;
            for a in &mut amplitudes {
                *a = a.map(|x| x * f);
            }
        }
        Ok(Self {
            centroid,
            scale,
            centres,
            amplitudes,
            sigma,
        })
    }

    /// Image of a point (mm).
    pub fn apply(&self, x: [f64; 3]) -> [f64; 3] {
        let mut y = [0.0; 3];
        for k in 0..3 {
            y[k] = self.centroid[k] + self.scale[k] * (x[k] - self.centroid[k]);
        }
        let inv2s2 = 1.0 / (2.0 * self.sigma * self.sigma);
        for (c, a) in self.centres.iter().zip(&self.amplitudes) {
            let r2 = (x[0] - c[0]).powi(2) + (x[1] - c[1]).powi(2) + (x[2] - c[2]).powi(2);
            let w = (-r2 * inv2s2).exp();
            for k in 0..3 {
                y[k] += a[k] * w;
            }
        }
        y
    }

    /// Jacobian `∂φ/∂x` at a point.
    pub fn jacobian(&self, x: [f64; 3]) -> [[f64; 3]; 3] {
        let mut j = [[0.0; 3]; 3];
        for k in 0..3 {
            j[k][k] = self.scale[k];
        }
        let inv_s2 = 1.0 / (self.sigma * self.sigma);
        for (c, a) in self.centres.iter().zip(&self.amplitudes) {
            let d = [x[0] - c[0], x[1] - c[1], x[2] - c[2]];
            let w = (-(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) * 0.5 * inv_s2).exp();
            for r in 0..3 {
                for col in 0..3 {
                    j[r][col] -= a[r] * w * d[col] * inv_s2;
                }
            }
        }
        j
    }

    /// The per-axis scale factors.
    pub fn scale(&self) -> [f64; 3] {
        self.scale
    }
}

fn norm(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

/// A liver-like variant of `surface` drawn from `seed` (same triangles, moved vertices).
pub fn variant(
    surface: &TriSurface,
    params: &ShapeVariantParams,
    seed: u64,
) -> Result<(TriSurface, ShapeMap), PhantomError> {
    let map = ShapeMap::random(surface, params, seed)?;
    let nodes = surface.nodes().iter().map(|&p| map.apply(p)).collect();
    let moved = TriSurface::new(nodes, surface.triangles().to_vec())?;
    Ok((moved, map))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::procedural::box_mesh;

    fn det(m: &[[f64; 3]; 3]) -> f64 {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    }

    #[test]
    fn jacobian_matches_finite_differences_and_stays_positive() {
        let s = box_mesh([100.0, 80.0, 60.0], [4, 4, 3], 0.0)
            .boundary_surface()
            .unwrap();
        let map = ShapeMap::random(&s, &ShapeVariantParams::default(), 9).unwrap();
        let mut rng = SplitMix64::new(1);
        for _ in 0..200 {
            let x = [0, 1, 2].map(|k| [100.0, 80.0, 60.0][k] * (1.4 * rng.next_f64() - 0.2));
            let j = map.jacobian(x);
            let h = 1e-5;
            for c in 0..3 {
                let mut xp = x;
                let mut xm = x;
                xp[c] += h;
                xm[c] -= h;
                let (yp, ym) = (map.apply(xp), map.apply(xm));
                for r in 0..3 {
                    let fd = (yp[r] - ym[r]) / (2.0 * h);
                    assert!(
                        (fd - j[r][c]).abs() < 1e-7,
                        "J[{r}][{c}] {fd} vs {}",
                        j[r][c]
                    );
                }
            }
            // ‖∇d‖ ≤ 0.45 and scales ≥ 0.88: det J > 0 everywhere.
            assert!(det(&j) > 0.0);
        }
    }

    #[test]
    fn variants_are_deterministic_closed_and_distinct() {
        let s = box_mesh([100.0, 80.0, 60.0], [6, 5, 4], 0.0)
            .boundary_surface()
            .unwrap();
        let p = ShapeVariantParams::default();
        let (a, _) = variant(&s, &p, 1).unwrap();
        let (a2, _) = variant(&s, &p, 1).unwrap();
        let (b, _) = variant(&s, &p, 2).unwrap();
        assert_eq!(a, a2);
        assert_ne!(a, b);
        for v in [&a, &b] {
            let st = v.stats();
            assert!(st.closed && st.consistently_oriented);
            // Orientation kept (positive volume), size changed by at most the scale jitter and bumps.
            let ratio = st.signed_volume_mm3 / (100.0 * 80.0 * 60.0);
            assert!(ratio > 0.5 && ratio < 1.6, "{ratio}");
        }
        let moved: f64 = a
            .nodes()
            .iter()
            .zip(s.nodes())
            .map(|(p, q)| norm([p[0] - q[0], p[1] - q[1], p[2] - q[2]]))
            .fold(0.0, f64::max);
        assert!(moved > 1.0, "the variant differs visibly ({moved} mm)");
        assert!(
            ShapeMap::random(
                &s,
                &ShapeVariantParams {
                    max_gradient: 1.2,
                    ..p
                },
                1
            )
            .is_err()
        );
    }
}
