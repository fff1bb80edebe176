//! A prior on the rigid registration: the organ stays near a trusted pose.
//!
//! When the navigation system declares its initial alignment trusted (an organ held in place and
//! tracked, `--trusted-alignment SIGMA`), or the model says the organ is held (a `fixation` or
//! `ligament` effect), the rigid motion is regularised towards that pose instead of fitted freely:
//! a partial surface over a locally pushed region otherwise turns the push into a global rotation.
//!
//! The penalty is the **mean squared displacement of the organ's nodes** between the current pose
//! `T` and the trusted one `T₀`, `Q(T) = (1/n) Σᵢ |T xᵢ − T₀ xᵢ|²`, weighted by `κ = s²/σ²`
//! against the weighted mean squared misfit of the data, `(1/W) Σ wⱼ |rⱼ|²`: `σ` is the declared
//! uncertainty (mm, RMS over the organ) and `s` the misfit the data show under `T₀` (the rigid
//! stage's starting RMS, at least 1 mm). Moving the organ by σ then costs as much as explaining
//! all of the starting misfit would gain, so the data move the organ by at most about σ however
//! the start disagrees with them: a local misfit cannot swing the whole organ (measured on exact
//! data of a pose 13 mm from the start: σ = 1 mm moved it 0.1 mm, σ = 3 mm 0.8 mm, σ = 10 mm
//! 4.3 mm; `tests/wicp.rs`).
//!
//! For a rigid motion `Q` depends on the nodes only through their centroid and covariance, so the
//! n nodes are replaced exactly by six **pose points** `c ± √(3λₖ) eₖ` (the covariance's
//! eigenpairs): the same mean and covariance, hence the same `Q` for every rigid motion. The prior
//! is then six extra pairs, pose point → its trusted position, each with weight `κ W / 6` in a
//! weighted Kabsch fit ([`crate::register::wicp`]) or `κ / 6` in LIBR's normalized rows.

use crate::mesh::rigid::Rigid;
use crate::mesh::vec3::{add, dist2, scale, sub};
use nalgebra::{Matrix3, Vector3};

/// Default uncertainty (mm, RMS over the organ) of the pose when the model holds the organ (a
/// `fixation` or `ligament` effect) and no uncertainty is declared.
pub const HELD_SIGMA_MM: f64 = 5.0;

/// A prior on the rigid pose (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RigidPrior {
    /// The trusted pose, image → physical.
    pub start: Rigid,
    /// Declared uncertainty σ (mm, RMS node displacement).
    pub sigma_mm: f64,
    /// Misfit scale s (mm): the data's RMS misfit under the trusted pose, at least 1 mm.
    pub scale_mm: f64,
    /// Six points (image frame) with the nodes' centroid and covariance.
    pub pose_points: [[f64; 3]; 6],
}

impl RigidPrior {
    /// The prior of `nodes` (image frame) at `start` with uncertainty `sigma_mm` and misfit scale
    /// `scale_mm` (floored at 1 mm). Panics on no nodes (a mesh always has some).
    pub fn new(nodes: &[[f64; 3]], start: Rigid, sigma_mm: f64, scale_mm: f64) -> Self {
        Self {
            start,
            sigma_mm,
            scale_mm: scale_mm.max(1.0),
            pose_points: pose_points(nodes),
        }
    }

    /// κ = s²/σ²: the weight of the mean squared node displacement against the weighted mean
    /// squared misfit.
    pub fn weight(&self) -> f64 {
        (self.scale_mm / self.sigma_mm).powi(2)
    }

    /// Mean squared node displacement between `t` and the trusted pose (mm²).
    pub fn mean_square(&self, t: &Rigid) -> f64 {
        self.pose_points
            .iter()
            .map(|&p| dist2(t.apply(p), self.start.apply(p)))
            .sum::<f64>()
            / 6.0
    }

    /// RMS node displacement between `t` and the trusted pose (mm).
    pub fn rms_mm(&self, t: &Rigid) -> f64 {
        self.mean_square(t).sqrt()
    }

    /// The six pairs in the image frame of the current pose `t`: each pose point and where the
    /// trusted pose puts it, mapped back by `t` (`t⁻¹(T₀ p)`). A rigid correction δ applied
    /// first (the new pose `t ∘ δ`) moves the organ by `|δ p − target|` per pose point.
    pub fn image_pairs(&self, t: &Rigid) -> [([f64; 3], [f64; 3]); 6] {
        let inv = t.inverse();
        self.pose_points
            .map(|p| (p, inv.apply(self.start.apply(p))))
    }
}

/// Six points with the centroid and covariance of `nodes`: `c ± √(3λₖ) eₖ`.
pub fn pose_points(nodes: &[[f64; 3]]) -> [[f64; 3]; 6] {
    let n = nodes.len().max(1) as f64;
    let c = scale(nodes.iter().fold([0.0; 3], |a, &p| add(a, p)), 1.0 / n);
    let mut cov = Matrix3::zeros();
    for &p in nodes {
        let d = Vector3::from(sub(p, c));
        cov += d * d.transpose();
    }
    cov /= n;
    let e = cov.symmetric_eigen();
    let mut out = [[0.0; 3]; 6];
    for k in 0..3 {
        let r = (3.0 * e.eigenvalues[k].max(0.0)).sqrt();
        let v = e.eigenvectors.column(k);
        let d = [v[0] * r, v[1] * r, v[2] * r];
        out[2 * k] = add(c, d);
        out[2 * k + 1] = sub(c, d);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    fn cloud(seed: u64, n: usize) -> Vec<[f64; 3]> {
        let mut g = SplitMix64::new(seed);
        (0..n)
            .map(|_| {
                [
                    40.0 * g.normal() + 10.0,
                    15.0 * g.normal() - 5.0,
                    25.0 * g.normal() + 3.0,
                ]
            })
            .collect()
    }

    #[test]
    fn pose_points_give_the_nodes_mean_square_displacement_for_any_rigid_motion() {
        let nodes = cloud(1, 500);
        let start = Rigid::from_axis_angle([0.3, -0.2, 0.9], 0.2, [4.0, -1.0, 2.0]);
        let prior = RigidPrior::new(&nodes, start, 2.0, 3.0);
        let mut g = SplitMix64::new(9);
        for _ in 0..20 {
            let t = Rigid::from_axis_angle(
                [g.normal(), g.normal(), g.normal()],
                0.5 * g.next_f64(),
                [10.0 * g.normal(), 10.0 * g.normal(), 10.0 * g.normal()],
            );
            let direct = nodes
                .iter()
                .map(|&p| dist2(t.apply(p), start.apply(p)))
                .sum::<f64>()
                / nodes.len() as f64;
            let by_pose = prior.mean_square(&t);
            assert!(
                (direct - by_pose).abs() <= 1e-9 * direct.max(1.0),
                "{direct} vs {by_pose}"
            );
        }
        assert_eq!(prior.mean_square(&start), 0.0);
        assert!((prior.weight() - 2.25).abs() < 1e-12);
    }

    #[test]
    fn image_pairs_measure_the_motion_of_a_correction_applied_first() {
        let nodes = cloud(2, 200);
        let start = Rigid::from_axis_angle([0.0, 0.0, 1.0], 0.1, [1.0, 2.0, 3.0]);
        let prior = RigidPrior::new(&nodes, start, 1.0, 1.0);
        let t = Rigid::from_axis_angle([1.0, 0.0, 0.0], 0.05, [-2.0, 0.0, 5.0]);
        let delta = Rigid::from_axis_angle([0.0, 1.0, 0.0], 0.03, [0.5, 0.5, -0.5]);
        let new = delta.then(&t);
        let by_pairs = prior
            .image_pairs(&t)
            .iter()
            .map(|&(p, q)| dist2(delta.apply(p), q))
            .sum::<f64>()
            / 6.0;
        let direct = prior.mean_square(&new);
        assert!((by_pairs - direct).abs() < 1e-9, "{by_pairs} vs {direct}");
    }
}
