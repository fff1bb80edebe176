//! Rigid transforms `p ↦ R p + t` between the preoperative (image) and intraoperative (physical)
//! frames: application to points and vectors, inverse, composition, axis–angle construction, the
//! rotation angle, and the weighted least-squares fit of one point set to another.
//!
//! The fit is the SVD solution of W. Kabsch, "A solution for the best rotation to relate two sets of
//! vectors", Acta Cryst. A32 (1976), in the form of K. S. Arun, T. S. Huang and S. D. Blostein,
//! "Least-squares fitting of two 3-D point sets", IEEE TPAMI 9(5), 1987, with the reflection fix of
//! S. Umeyama, IEEE TPAMI 13(4), 1991: `R = V diag(1, 1, det(V Uᵀ)) Uᵀ` for the weighted
//! cross-covariance `H = Σ wᵢ (sᵢ − s̄)(dᵢ − d̄)ᵀ = U Σ Vᵀ`, so that the result is always a proper
//! rotation, also for planar point sets.

use nalgebra::{Matrix3, Vector3};

/// A rigid transform p ↦ R p + t (R a rotation matrix, row-major).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Rigid {
    /// Rotation matrix, row-major (`rotation[i][j]` is row i, column j).
    pub rotation: [[f64; 3]; 3],
    /// Translation (mm), applied after the rotation.
    pub translation: [f64; 3],
}

/// Relative size of the second singular value of the source spread below which a point set counts
/// as collinear (or coincident) and the rotation is undetermined.
const COLLINEAR_REL: f64 = 1e-10;

impl Rigid {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [0.0; 3],
        }
    }

    /// `R p + t`.
    pub fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let r = self.apply_vector(p);
        [
            r[0] + self.translation[0],
            r[1] + self.translation[1],
            r[2] + self.translation[2],
        ]
    }

    /// `R v` (a direction or displacement: rotation only).
    pub fn apply_vector(&self, v: [f64; 3]) -> [f64; 3] {
        let r = &self.rotation;
        [0, 1, 2].map(|i| r[i][0] * v[0] + r[i][1] * v[1] + r[i][2] * v[2])
    }

    /// The inverse transform `p ↦ Rᵀ (p − t)`.
    pub fn inverse(&self) -> Self {
        let r = &self.rotation;
        let rotation = [0, 1, 2].map(|i| [r[0][i], r[1][i], r[2][i]]);
        let rt = Rigid {
            rotation,
            translation: [0.0; 3],
        }
        .apply_vector(self.translation);
        Self {
            rotation,
            translation: rt.map(|c| -c),
        }
    }

    /// `next ∘ self`: first this transform, then `next`.
    pub fn then(&self, next: &Rigid) -> Rigid {
        let a = &next.rotation;
        let b = &self.rotation;
        let rotation = [0, 1, 2]
            .map(|i| [0, 1, 2].map(|j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j]));
        Rigid {
            rotation,
            translation: next.apply(self.translation),
        }
    }

    /// Rotation by `angle_rad` about `axis` (Rodrigues; normalised here, a zero axis gives no
    /// rotation), followed by `translation`.
    pub fn from_axis_angle(axis: [f64; 3], angle_rad: f64, translation: [f64; 3]) -> Self {
        let l = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
        if l.is_nan() || l <= 0.0 || angle_rad == 0.0 {
            return Self {
                translation,
                ..Self::identity()
            };
        }
        let [x, y, z] = axis.map(|c| c / l);
        let (s, c) = angle_rad.sin_cos();
        let k = 1.0 - c;
        Self {
            rotation: [
                [c + x * x * k, x * y * k - z * s, x * z * k + y * s],
                [y * x * k + z * s, c + y * y * k, y * z * k - x * s],
                [z * x * k - y * s, z * y * k + x * s, c + z * z * k],
            ],
            translation,
        }
    }

    /// The rotation angle in degrees, in [0, 180] (from `atan2(|axial vector|, trace − 1)`, accurate
    /// for small angles too).
    pub fn rotation_angle_deg(&self) -> f64 {
        let r = &self.rotation;
        let s = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]];
        let sin2 = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        let cos2 = r[0][0] + r[1][1] + r[2][2] - 1.0;
        sin2.atan2(cos2).to_degrees()
    }

    /// Least-squares rigid fit src→dst (Kabsch/Horn with SVD, reflection-safe, optional weights); None if fewer than 3 non-collinear points.
    ///
    /// Minimises `Σ wᵢ |R srcᵢ + t − dstᵢ|²`. `None` also when the lengths differ, a weight is
    /// negative or not finite, all weights are zero, or a coordinate is not finite.
    pub fn fit(src: &[[f64; 3]], dst: &[[f64; 3]], weights: Option<&[f64]>) -> Option<Rigid> {
        if src.len() != dst.len() || src.len() < 3 {
            return None;
        }
        if let Some(w) = weights {
            if w.len() != src.len() || w.iter().any(|&x| !(x >= 0.0 && x.is_finite())) {
                return None;
            }
        }
        if src.iter().chain(dst).flatten().any(|c| !c.is_finite()) {
            return None;
        }
        let w = |i: usize| weights.map_or(1.0, |w| w[i]);
        let total: f64 = (0..src.len()).map(w).sum();
        if total.is_nan() || total <= 0.0 {
            return None;
        }
        let mut cs = Vector3::zeros();
        let mut cd = Vector3::zeros();
        for i in 0..src.len() {
            cs += Vector3::from(src[i]) * w(i);
            cd += Vector3::from(dst[i]) * w(i);
        }
        cs /= total;
        cd /= total;
        let mut h = Matrix3::zeros();
        let mut spread = Matrix3::zeros();
        for i in 0..src.len() {
            let a = Vector3::from(src[i]) - cs;
            let b = Vector3::from(dst[i]) - cd;
            h += a * b.transpose() * w(i);
            spread += a * a.transpose() * w(i);
        }
        // Collinear or coincident (weighted) sources leave a rotation about their line free.
        let sv = spread.symmetric_eigenvalues();
        let mut ev = [sv[0], sv[1], sv[2]];
        ev.sort_by(|a, b| b.total_cmp(a));
        if ev[0].is_nan() || ev[0] <= 0.0 || ev[1] <= COLLINEAR_REL * ev[0] {
            return None;
        }
        let svd = h.svd(true, true);
        let u = svd.u?;
        let v = svd.v_t?.transpose();
        let d = (v * u.transpose()).determinant().signum();
        let r = v * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * u.transpose();
        let t = cd - r * cs;
        Some(Rigid {
            rotation: [0, 1, 2].map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]),
            translation: [t[0], t[1], t[2]],
        })
    }
}

impl Default for Rigid {
    fn default() -> Self {
        Self::identity()
    }
}
