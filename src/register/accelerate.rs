//! Anderson acceleration of the ICP iterations (D. G. Anderson, "Iterative procedures for
//! nonlinear integral equations", J. ACM 12(4), 1965), as A. L. Pavlov, G. W. Ovchinnikov,
//! D. Yu. Derbyshev, D. Tsetserukou and I. V. Oseledets apply it to ICP ("AA-ICP: Iterative
//! closest point with Anderson acceleration", ICRA 2018).
//!
//! One ICP iteration (match, then fit) is a map `G` from a pose to the next; ICP is the
//! fixed-point iteration `x ← G(x)`, which converges linearly and slowly where the points can
//! slide along the surface (hundreds of iterations from a start tens of degrees off). Anderson
//! acceleration keeps the last few poses `x_j` and their images `g_j = G(x_j)` and proposes
//! `g_k − Σ γ_j Δg_j`, with `γ` the least-squares combination of the last residual
//! differences `Δf_j` (`f_j = g_j − x_j`) closest to the current residual: the extrapolation a
//! secant method makes of the fixed point. The proposal is kept only when its matching is no
//! worse than the current pose's (the caller checks); otherwise the plain step `g_k` is taken and
//! the history restarts, so each iteration is never worse than plain ICP's and the iteration
//! still converges to one of its fixed points.
//!
//! Poses are six numbers: the rotation vector of the motion from a reference pose (scaled by the
//! points' RMS radius, so that it is in millimetres like the translation) and the translation of
//! the points' centroid.

use crate::mesh::rigid::Rigid;
use nalgebra::{DMatrix, DVector};

/// Poses remembered (the history's depth). Pavlov et al. found 5–10 about as good; the residual
/// differences beyond a few poses back are nearly dependent on a smooth surface.
const MEMORY: usize = 5;

/// Anderson acceleration of a rigid fixed-point iteration (module doc).
#[derive(Debug, Clone)]
pub(crate) struct Anderson {
    /// The pose the parameters are measured from.
    reference: Rigid,
    /// The centroid of the points (physical frame) rotations turn about.
    centre: [f64; 3],
    /// The points' RMS distance to `centre` (mm per radian).
    radius: f64,
    /// Recent (x_j, g_j), oldest first.
    history: Vec<([f64; 6], [f64; 6])>,
}

impl Anderson {
    /// An accelerator for poses near `reference`, moving `points` (physical frame).
    pub(crate) fn new(reference: Rigid, points: &[[f64; 3]]) -> Self {
        let n = points.len().max(1) as f64;
        let mut centre = [0.0; 3];
        for p in points {
            for a in 0..3 {
                centre[a] += p[a] / n;
            }
        }
        let radius = (points
            .iter()
            .map(|p| (0..3).map(|a| (p[a] - centre[a]).powi(2)).sum::<f64>())
            .sum::<f64>()
            / n)
            .sqrt()
            .max(1.0);
        Self {
            reference,
            centre,
            radius,
            history: Vec::new(),
        }
    }

    /// Records that the plain step from `x` is `g` and returns the accelerated pose, when the
    /// history holds an earlier step to extrapolate from.
    pub(crate) fn propose(&mut self, x: &Rigid, g: &Rigid) -> Option<Rigid> {
        let (xv, gv) = (self.params(x), self.params(g));
        self.history.push((xv, gv));
        if self.history.len() > MEMORY + 1 {
            self.history.remove(0);
        }
        let k = self.history.len();
        if k < 2 {
            return None;
        }
        let f = |j: usize| {
            let (x, g) = &self.history[j];
            [0, 1, 2, 3, 4, 5].map(|a| g[a] - x[a])
        };
        let fk = f(k - 1);
        let m = k - 1;
        let mut df = DMatrix::<f64>::zeros(6, m);
        let mut dg = DMatrix::<f64>::zeros(6, m);
        for j in 0..m {
            let (fa, fb) = (f(j), f(j + 1));
            for a in 0..6 {
                df[(a, j)] = fb[a] - fa[a];
                dg[(a, j)] = self.history[j + 1].1[a] - self.history[j].1[a];
            }
        }
        let gamma = df
            .svd(true, true)
            .solve(&DVector::from_row_slice(&fk), 1e-10)
            .ok()?;
        let step = &dg * &gamma;
        let mut out = gv;
        for a in 0..6 {
            out[a] -= step[a];
        }
        out.iter().all(|v| v.is_finite()).then(|| self.pose(&out))
    }

    /// Forgets the history (after a rejected proposal: the plain step restarts it).
    pub(crate) fn restart(&mut self) {
        self.history.clear();
    }

    /// The pose's six numbers (module doc).
    fn params(&self, t: &Rigid) -> [f64; 6] {
        // The motion from the reference, in the physical frame: t = delta ∘ reference.
        let delta = self.reference.inverse().then(t);
        let w = rotation_vector(&delta.rotation);
        let moved = delta.apply(self.centre);
        [
            w[0] * self.radius,
            w[1] * self.radius,
            w[2] * self.radius,
            moved[0] - self.centre[0],
            moved[1] - self.centre[1],
            moved[2] - self.centre[2],
        ]
    }

    /// The pose of six numbers.
    fn pose(&self, v: &[f64; 6]) -> Rigid {
        let w = [v[0], v[1], v[2]].map(|c| c / self.radius);
        let angle = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
        let rot = Rigid::from_axis_angle(w, angle, [0.0; 3]);
        // The centroid goes to centre + v[3..]: translation = centre + s − R centre.
        let rc = rot.apply(self.centre);
        let translation = [0, 1, 2].map(|a| self.centre[a] + v[3 + a] - rc[a]);
        let delta = Rigid {
            rotation: rot.rotation,
            translation,
        };
        self.reference.then(&delta)
    }
}

/// The rotation vector (axis × angle, radians) of a rotation matrix, for angles below π.
fn rotation_vector(r: &[[f64; 3]; 3]) -> [f64; 3] {
    let a = [r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]];
    let s = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt(); // 2 sin θ
    let c = r[0][0] + r[1][1] + r[2][2] - 1.0; // 2 cos θ
    let theta = s.atan2(c);
    // θ / (2 sin θ), → 1/2 as θ → 0.
    let k = if s > 1e-12 { theta / s } else { 0.5 };
    a.map(|x| x * k)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Rigid, b: &Rigid, tol: f64) -> bool {
        a.rotation
            .iter()
            .flatten()
            .zip(b.rotation.iter().flatten())
            .all(|(x, y)| (x - y).abs() < tol)
            && a.translation
                .iter()
                .zip(&b.translation)
                .all(|(x, y)| (x - y).abs() < tol)
    }

    #[test]
    fn a_pose_survives_its_six_numbers() {
        let reference = Rigid::from_axis_angle([0.3, -1.0, 0.2], 0.4, [10.0, -5.0, 30.0]);
        let points = [
            [0.0; 3],
            [100.0, 0.0, 0.0],
            [0.0, 80.0, 0.0],
            [0.0, 0.0, 60.0],
        ];
        let acc = Anderson::new(reference, &points);
        for (axis, angle) in [
            ([1.0, 2.0, 3.0], 0.7),
            ([0.0, 0.0, 1.0], 1e-9),
            ([1.0, 0.0, 0.0], 2.5),
        ] {
            let t = Rigid::from_axis_angle(axis, angle, [3.0, 4.0, -7.0]);
            let back = acc.pose(&acc.params(&t));
            assert!(close(&back, &t, 1e-9), "{t:?} came back as {back:?}");
        }
        assert!(acc.params(&reference).iter().all(|v| v.abs() < 1e-9));
    }

    /// A linear contraction towards a fixed pose: plain iteration crawls, Anderson's secant
    /// steps reach the fixed point in a few.
    #[test]
    fn a_slow_linear_iteration_is_solved_in_a_few_steps() {
        let points = [
            [0.0; 3],
            [50.0, 0.0, 0.0],
            [0.0, 50.0, 0.0],
            [0.0, 0.0, 50.0],
        ];
        let acc0 = Anderson::new(Rigid::identity(), &points);
        let fixed = [5.0, -3.0, 2.0, 10.0, 4.0, -6.0];
        // g = fixed + A (x − fixed) with A's eigenvalues up to 0.98 (a sliding direction).
        let contraction = [0.98, 0.9, 0.5, 0.95, 0.7, 0.3];
        let g_of = |x: &[f64; 6]| {
            [0, 1, 2, 3, 4, 5].map(|a| fixed[a] + contraction[a] * (x[a] - fixed[a]))
        };
        let gap = |x: &[f64; 6]| (0..6).map(|a| (x[a] - fixed[a]).abs()).fold(0.0, f64::max);
        let mut acc = acc0.clone();
        let mut x = acc.pose(&[0.0; 6]);
        for _ in 0..12 {
            let xv = acc.params(&x);
            let g = acc.pose(&g_of(&xv));
            x = acc.propose(&x, &g).unwrap_or(g);
        }
        assert!(
            gap(&acc.params(&x)) < 1e-6,
            "accelerated: {:?}",
            acc.params(&x)
        );
        // Plain iteration after as many steps is still far off.
        let mut xv = [0.0; 6];
        for _ in 0..12 {
            xv = g_of(&xv);
        }
        assert!(gap(&xv) > 0.5, "plain: {xv:?}");
    }
}
