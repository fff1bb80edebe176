//! How far to trust a registration: a predicted mean TRE and a per-node error bound, from what
//! surgery has (after Heiselman et al., IEEE TMI 2021, who predicted a registration's TRE from its
//! strain energy and data coverage).
//!
//! The estimate reads [`ErrorFeatures`] of a registration — the number and kind of measured
//! points, the fit's residual, the strain energy of the fitted deformation, how far the model
//! moved, and how much of the organ the data cover (each node's distance to the nearest measured
//! point) — and an [`ErrorModel`] calibrated on generated data where the truth is known
//! (`librplus calibrate-error`, which lives in `eval`; this module never sees a truth):
//!
//! - mean TRE: `ln T̂ = w₀ + Σ w_k z_k`, z the standardised [`ErrorFeatures::regressors`]
//!   (clamped to the calibration range), fitted by ridge least squares, times the smearing factor
//!   `mean(exp(residual))` so that T̂ estimates the mean rather than the median;
//! - failed registrations (model version 2): a few registrations land in a wrong pose (true TRE
//!   of 20–90 mm where the rest have 2–10) and one log-linear law cannot hold both. A model with
//!   a [`FailureModel`] gives the probability `p = σ(v₀ + Σ v_k z_k)` (logistic regression) that
//!   the TRE exceeds its threshold, fits the law above on the registrations under it (T̂_ok) and
//!   a second one on those over it (T̂_fail), and predicts `T̂ = p·T̂_fail + (1 − p)·T̂_ok`;
//! - per node: `ln(e_i + ε) = b₀ + b₁ ln T̂ + b₂ ρ_i + b₃ ρ_i²` with ρ_i the node's distance to
//!   the nearest measured point over the organ's size, and the bound at level p is
//!   `exp(b·x_i + q_p) − ε`, q_p the p-quantile of the calibration residuals (a split-conformal
//!   interval: on data like the calibration's, the bound covers a fraction p of the nodes).
//!
//! Model file: JSON, `format` [`FORMAT`], `version` [`VERSION`]; documented in
//! docs/error-estimate.md.

use crate::mesh::rigid::Rigid;
use crate::register::{Checked, MeasuredKind};
use std::collections::BTreeMap;

/// The model file's `format`.
pub const FORMAT: &str = "librplus-error-model";
/// The model file's `version` written (2: with [`FailureModel`]s; version 1 files, without,
/// are read too).
pub const VERSION: u32 = 2;
/// A boundary node counts as covered when a measured point lies within this distance (mm).
pub const COVER_RADIUS_MM: f64 = 10.0;
/// ε of the per-node model's logarithm (mm): node errors below it are all alike.
pub const NODE_EPS_MM: f64 = 0.1;
/// Names of [`ErrorFeatures::regressors`], in order.
pub const REGRESSORS: [&str; 12] = [
    "ln(1+surface_points)",
    "ln(1+ultrasound_points)",
    "ln(0.1+residual_rms_mm)",
    "ln(0.1+rigid_rms_mm)",
    "ln(1+strain_energy_uj)",
    "ln(0.1+mean_displacement_mm)",
    "coverage_mean_mm/size_mm",
    "surface_covered",
    "ln(size_mm)",
    "ln(0.1+far_displacement_mm)",
    "ln(0.1+max_displacement_mm)",
    "coverage_p90_mm/size_mm",
];
/// A node counts as far from the data beyond this distance from every measured point (mm).
pub const FAR_MM: f64 = 20.0;

/// What the estimate reads of one registration (surgery-time quantities only).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ErrorFeatures {
    /// Measured surface points.
    pub surface_points: usize,
    /// Measured ultrasound points (posterior contour and vessel).
    pub ultrasound_points: usize,
    /// Residual RMS of the final fit (LIBR's, the refit's, or wICP's) (mm).
    pub residual_rms_mm: f64,
    /// Residual RMS of the rigid stage (mm).
    pub rigid_rms_mm: f64,
    /// Strain energy ½αᵀEα of LIBR's fitted deformation (µJ; 0 without LIBR).
    pub strain_energy_uj: f64,
    /// Mean node displacement of the answer (mm).
    pub mean_displacement_mm: f64,
    /// Mean over nodes of the distance to the nearest measured point (mm).
    pub coverage_mean_mm: f64,
    /// Fraction of boundary nodes with a measured point within [`COVER_RADIUS_MM`].
    pub surface_covered: f64,
    /// The organ's size: RMS distance of its nodes from their centroid (mm).
    pub size_mm: f64,
    /// Mean displacement of the nodes farther than [`FAR_MM`] from every measured point (mm;
    /// 0 when none is): how much the answer extrapolates beyond the data.
    pub far_displacement_mm: f64,
    /// Largest node displacement (mm).
    pub max_displacement_mm: f64,
    /// 90th percentile over nodes of the distance to the nearest measured point (mm).
    pub coverage_p90_mm: f64,
}

impl ErrorFeatures {
    /// The regression inputs, named by [`REGRESSORS`].
    pub fn regressors(&self) -> [f64; 12] {
        [
            (1.0 + self.surface_points as f64).ln(),
            (1.0 + self.ultrasound_points as f64).ln(),
            (0.1 + self.residual_rms_mm).ln(),
            (0.1 + self.rigid_rms_mm).ln(),
            (1.0 + self.strain_energy_uj.max(0.0)).ln(),
            (0.1 + self.mean_displacement_mm).ln(),
            self.coverage_mean_mm / self.size_mm.max(1e-9),
            self.surface_covered,
            self.size_mm.max(1e-9).ln(),
            (0.1 + self.far_displacement_mm).ln(),
            (0.1 + self.max_displacement_mm).ln(),
            self.coverage_p90_mm / self.size_mm.max(1e-9),
        ]
    }
}

/// What a registration's fit left that the features read.
#[derive(Debug, Clone, Copy)]
pub struct FitSummary {
    /// Residual RMS of the final fit (mm).
    pub residual_rms_mm: f64,
    /// Residual RMS of the rigid stage (mm).
    pub rigid_rms_mm: f64,
    /// ½αᵀEα of LIBR's deformation (µJ; 0 without LIBR).
    pub strain_energy_uj: f64,
}

/// The features of a registration and each node's distance to the nearest measured point
/// (mm, at the registered shape). `nodes` are the preoperative node positions (image frame),
/// `u` the registered displacements (node-major 3n), `boundary` flags boundary nodes (empty:
/// every node counts). None when there are no measured points or sizes disagree.
pub fn features(
    nodes: &[[f64; 3]],
    boundary: &[bool],
    u: &[f64],
    image_to_physical: &Rigid,
    meas: &Checked,
    fit: FitSummary,
) -> Option<(ErrorFeatures, Vec<f64>)> {
    let n = nodes.len();
    if meas.points.is_empty() || u.len() != 3 * n || n == 0 {
        return None;
    }
    if !boundary.is_empty() && boundary.len() != n {
        return None;
    }
    let inv = image_to_physical.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
    if pts.iter().flatten().any(|x| !x.is_finite()) || u.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let tree: kiddo::ImmutableKdTree<f64, 3> = kiddo::ImmutableKdTree::new_from_slice(&pts);
    let at = |i: usize| [0, 1, 2].map(|a| nodes[i][a] + u[3 * i + a]);
    let dist: Vec<f64> = (0..n)
        .map(|i| {
            tree.nearest_one::<kiddo::SquaredEuclidean>(&at(i))
                .distance
                .sqrt()
        })
        .collect();
    let size = rms_radius(nodes);
    let (mut on, mut covered) = (0usize, 0usize);
    for (i, d) in dist.iter().enumerate() {
        if boundary.is_empty() || boundary[i] {
            on += 1;
            covered += usize::from(*d <= COVER_RADIUS_MM);
        }
    }
    let norm: Vec<f64> = (0..n)
        .map(|i| (u[3 * i].powi(2) + u[3 * i + 1].powi(2) + u[3 * i + 2].powi(2)).sqrt())
        .collect();
    let mean_u = norm.iter().sum::<f64>() / n as f64;
    let (far_sum, far_count) = norm
        .iter()
        .zip(&dist)
        .filter(|(_, d)| **d > FAR_MM)
        .fold((0.0, 0usize), |(s, c), (x, _)| (s + x, c + 1));
    // Counted as received: a reduced cloud's centroid counts the points it stands for.
    let (mut surface, mut ultrasound) = (0.0, 0.0);
    for (i, k) in meas.kind.iter().enumerate() {
        if *k == MeasuredKind::Surface {
            surface += meas.weight(i);
        } else {
            ultrasound += meas.weight(i);
        }
    }
    let f = ErrorFeatures {
        surface_points: surface.round() as usize,
        ultrasound_points: ultrasound.round() as usize,
        residual_rms_mm: fit.residual_rms_mm,
        rigid_rms_mm: fit.rigid_rms_mm,
        strain_energy_uj: fit.strain_energy_uj,
        mean_displacement_mm: mean_u,
        coverage_mean_mm: dist.iter().sum::<f64>() / n as f64,
        surface_covered: covered as f64 / on.max(1) as f64,
        size_mm: size,
        far_displacement_mm: if far_count == 0 {
            0.0
        } else {
            far_sum / far_count as f64
        },
        max_displacement_mm: norm.iter().copied().fold(0.0, f64::max),
        coverage_p90_mm: crate::util::quantile(&dist, 0.9),
    };
    Some((f, dist))
}

/// RMS distance of the nodes from their centroid (mm): the organ's size.
fn rms_radius(nodes: &[[f64; 3]]) -> f64 {
    let n = nodes.len();
    let mut centroid = [0.0; 3];
    for x in nodes {
        for a in 0..3 {
            centroid[a] += x[a] / n as f64;
        }
    }
    (nodes
        .iter()
        .map(|x| (0..3).map(|a| (x[a] - centroid[a]).powi(2)).sum::<f64>())
        .sum::<f64>()
        / n as f64)
        .sqrt()
}

/// The failed-registration part of a method's model (see the module documentation).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FailureModel {
    /// A registration whose true mean TRE exceeds this counts as failed (mm).
    pub threshold_mm: f64,
    /// Intercept and weights of the logistic regression of "failed" on the standardised
    /// regressors.
    pub logistic: Vec<f64>,
    /// Intercept and weights of `ln T̂_fail`, fitted on the failed calibration registrations.
    pub weights: Vec<f64>,
    /// Smearing factor of `T̂_fail`.
    pub smearing: f64,
    /// Failed calibration registrations.
    pub failed: usize,
}

/// One method's calibrated estimate.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MethodErrorModel {
    /// Mean of each regressor over the calibration registrations.
    pub mean: Vec<f64>,
    /// Standard deviation of each (1 where constant).
    pub std: Vec<f64>,
    /// Smallest and largest standardised value seen (inputs are clamped to them).
    pub z_min: Vec<f64>,
    /// See `z_min`.
    pub z_max: Vec<f64>,
    /// Intercept and weights of `ln T̂` on the standardised regressors (with a `failure` part:
    /// of `ln T̂_ok`, fitted on the registrations under its threshold).
    pub weights: Vec<f64>,
    /// Smearing factor: mean of `exp(residual)` on the calibration set.
    pub smearing: f64,
    /// The failed-registration part (version 2; absent: one law for all).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<FailureModel>,
    /// Per-node model `[b₀, b₁, b₂, b₃]` (see the module documentation).
    pub node: [f64; 4],
    /// Per-node residual quantiles: (level, q) pairs, increasing.
    pub node_quantiles: Vec<(f64, f64)>,
    /// Registrations it was calibrated on.
    pub registrations: usize,
}

/// A calibrated error model: one [`MethodErrorModel`] per registration method name (`rigid`,
/// `libr`, `librplus`, `v2s`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ErrorModel {
    /// [`FORMAT`].
    pub format: String,
    /// [`VERSION`].
    pub version: u32,
    /// The regressor names ([`REGRESSORS`]).
    pub regressors: Vec<String>,
    /// The level of the per-node bound the service reports.
    pub level: f64,
    /// Per method.
    pub methods: BTreeMap<String, MethodErrorModel>,
    /// Where it came from (dataset, its parameters hash, command, commit).
    #[serde(default)]
    pub provenance: serde_json::Value,
}

/// A registration's error estimate.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ErrorEstimate {
    /// Predicted mean TRE over the organ's nodes (mm).
    pub predicted_tre_mm: f64,
    /// The level of `node_bound_mm`.
    pub level: f64,
    /// Per node: the error stays below this with probability `level` (mm).
    pub node_bound_mm: Vec<f64>,
    /// Probability that the registration failed: its mean TRE above `failure_threshold_mm`
    /// (None when the model has no failure part for the method).
    pub failure_probability: Option<f64>,
    /// The TRE that counts as failed (mm).
    pub failure_threshold_mm: Option<f64>,
    /// What the estimate read.
    pub features: ErrorFeatures,
    /// Time to compute it, features included (s; set by the pipeline).
    pub seconds: f64,
}

/// Why an error model file was refused.
#[derive(Debug, thiserror::Error)]
pub enum ErrorModelError {
    /// Not JSON, or a field missing or of the wrong type.
    #[error("error model: {0}")]
    Parse(String),
    /// Another format or version.
    #[error("error model: {0}")]
    Format(String),
    /// Sizes or values that cannot be used (the message names the field).
    #[error("error model: {0}")]
    Invalid(String),
}

impl ErrorModel {
    /// Parses and checks a model file's text.
    pub fn from_json(text: &str) -> Result<Self, ErrorModelError> {
        let m: ErrorModel =
            serde_json::from_str(text).map_err(|e| ErrorModelError::Parse(e.to_string()))?;
        if m.format != FORMAT || !(1..=VERSION).contains(&m.version) {
            return Err(ErrorModelError::Format(format!(
                "format {:?} version {} (this build reads {FORMAT:?} versions 1 to {VERSION})",
                m.format, m.version
            )));
        }
        if m.regressors != REGRESSORS {
            return Err(ErrorModelError::Invalid(format!(
                "regressors {:?} differ from this build's {REGRESSORS:?}",
                m.regressors
            )));
        }
        if !(m.level > 0.0 && m.level < 1.0) {
            return Err(ErrorModelError::Invalid(format!(
                "level {} is not in (0, 1)",
                m.level
            )));
        }
        let k = REGRESSORS.len();
        for (name, mm) in &m.methods {
            let ok = mm.mean.len() == k
                && mm.std.len() == k
                && mm.z_min.len() == k
                && mm.z_max.len() == k
                && mm.weights.len() == k + 1
                && !mm.node_quantiles.is_empty()
                && mm.std.iter().all(|s| *s > 0.0)
                && mm
                    .mean
                    .iter()
                    .chain(&mm.std)
                    .chain(&mm.z_min)
                    .chain(&mm.z_max)
                    .chain(&mm.weights)
                    .chain(&mm.node)
                    .chain(&[mm.smearing])
                    .all(|x| x.is_finite());
            if !ok {
                return Err(ErrorModelError::Invalid(format!(
                    "methods.{name}: sizes (mean, std, z_min, z_max: {k}; weights: {}) or values (finite, std > 0) wrong",
                    k + 1
                )));
            }
            if let Some(f) = &mm.failure {
                let ok = m.version >= 2
                    && f.logistic.len() == k + 1
                    && f.weights.len() == k + 1
                    && f.threshold_mm > 0.0
                    && f.logistic
                        .iter()
                        .chain(&f.weights)
                        .chain(&[f.smearing, f.threshold_mm])
                        .all(|x| x.is_finite());
                if !ok {
                    return Err(ErrorModelError::Invalid(format!(
                        "methods.{name}.failure: sizes (logistic, weights: {}), values (finite, threshold_mm > 0) or version (2) wrong",
                        k + 1
                    )));
                }
            }
        }
        Ok(m)
    }

    /// The estimate for a registration by `method` with these features and node distances
    /// ([`features`]); None when the model has no calibration for the method.
    pub fn estimate(
        &self,
        method: &str,
        features: &ErrorFeatures,
        node_distance_mm: &[f64],
    ) -> Option<ErrorEstimate> {
        let mm = self.methods.get(method)?;
        let t = mm.predict_tre(features);
        let q = mm.quantile(self.level);
        let size = features.size_mm.max(1e-9);
        let node_bound_mm = node_distance_mm
            .iter()
            .map(|d| mm.node_bound(t, d / size, q))
            .collect();
        Some(ErrorEstimate {
            predicted_tre_mm: t,
            level: self.level,
            node_bound_mm,
            failure_probability: mm.failure_probability(features),
            failure_threshold_mm: mm.failure.as_ref().map(|f| f.threshold_mm),
            features: *features,
            seconds: 0.0,
        })
    }
}

impl MethodErrorModel {
    /// The standardised, clamped regressors.
    pub fn standardise(&self, f: &ErrorFeatures) -> Vec<f64> {
        f.regressors()
            .iter()
            .enumerate()
            .map(|(k, x)| {
                let z = (x - self.mean[k]) / self.std[k];
                if z.is_finite() {
                    z.clamp(self.z_min[k], self.z_max[k])
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// Predicted mean TRE (mm).
    pub fn predict_tre(&self, f: &ErrorFeatures) -> f64 {
        let z = self.standardise(f);
        let ok = linear(&self.weights, &z).exp() * self.smearing;
        match &self.failure {
            None => ok,
            Some(fm) => {
                let p = sigmoid(linear(&fm.logistic, &z));
                p * linear(&fm.weights, &z).exp() * fm.smearing + (1.0 - p) * ok
            }
        }
    }

    /// Probability that the registration failed (true TRE above the failure part's threshold);
    /// None without a failure part.
    pub fn failure_probability(&self, f: &ErrorFeatures) -> Option<f64> {
        let fm = self.failure.as_ref()?;
        Some(sigmoid(linear(&fm.logistic, &self.standardise(f))))
    }

    /// The per-node model's `ln(e + ε)` at predicted TRE `t` and relative distance `rho`.
    pub fn node_log(&self, t: f64, rho: f64) -> f64 {
        let b = &self.node;
        b[0] + b[1] * t.max(1e-6).ln() + b[2] * rho + b[3] * rho * rho
    }

    /// A node's bound (mm) at predicted TRE `t`, relative distance `rho` and residual quantile
    /// `q` ([`MethodErrorModel::quantile`]).
    pub fn node_bound(&self, t: f64, rho: f64, q: f64) -> f64 {
        ((self.node_log(t, rho) + q).exp() - NODE_EPS_MM).max(0.0)
    }

    /// The residual quantile at `level`, interpolated between the stored ones (the nearest end
    /// outside them).
    pub fn quantile(&self, level: f64) -> f64 {
        let q = &self.node_quantiles;
        if level <= q[0].0 {
            return q[0].1;
        }
        for w in q.windows(2) {
            if level <= w[1].0 {
                let s = (level - w[0].0) / (w[1].0 - w[0].0);
                return w[0].1 + s * (w[1].1 - w[0].1);
            }
        }
        q[q.len() - 1].1
    }
}

/// `w₀ + Σ w_k z_k`.
pub fn linear(w: &[f64], z: &[f64]) -> f64 {
    w[0] + z.iter().zip(&w[1..]).map(|(a, b)| a * b).sum::<f64>()
}

/// The logistic function, without overflow for large |x|.
pub fn sigmoid(x: f64) -> f64 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// The built-in error model (`assets/models/error/model.json`, calibrated by the command in its
/// README), parsed once.
pub fn builtin() -> Option<std::sync::Arc<ErrorModel>> {
    static M: std::sync::OnceLock<Option<std::sync::Arc<ErrorModel>>> = std::sync::OnceLock::new();
    M.get_or_init(|| {
        ErrorModel::from_json(include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/assets/models/error/model.json"
        )))
        .ok()
        .map(std::sync::Arc::new)
    })
    .clone()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    /// The features against direct computations: each node's distance to the nearest measured
    /// point by brute force in the image frame (the points mapped back by the inverse pose, the
    /// nodes at X + u), the covered fraction of boundary nodes, the organ's RMS radius and the
    /// mean displacement; and the same distances whatever the pose (the features are
    /// pose-invariant when points and pose move together).
    #[test]
    fn features_agree_with_brute_force_and_do_not_depend_on_the_pose() {
        let mut rng = SplitMix64::new(5);
        let nodes: Vec<[f64; 3]> = (0..300)
            .map(|_| [0, 1, 2].map(|_| 80.0 * rng.next_f64() - 40.0))
            .collect();
        let boundary: Vec<bool> = (0..300).map(|i| i % 3 == 0).collect();
        let u: Vec<f64> = (0..900).map(|_| 4.0 * rng.next_f64() - 2.0).collect();
        let image: Vec<[f64; 3]> = (0..40)
            .map(|_| [0, 1, 2].map(|_| 80.0 * rng.next_f64() - 40.0))
            .collect();
        let pose = Rigid::from_axis_angle([0.3, -0.5, 0.8], 0.4, [12.0, -7.0, 30.0]);
        let kind: Vec<MeasuredKind> = (0..40)
            .map(|k| {
                if k < 30 {
                    MeasuredKind::Surface
                } else {
                    MeasuredKind::Vessel
                }
            })
            .collect();
        let raw = |t: &Rigid| crate::register::Measurements {
            points: image.iter().map(|&p| t.apply(p)).collect(),
            kind: kind.clone(),
            feature: Vec::new(),
            initial_alignment: None,
        };
        let fit = FitSummary {
            residual_rms_mm: 1.5,
            rigid_rms_mm: 3.0,
            strain_energy_uj: 2.0,
        };
        let meas = |t: &Rigid| Checked::new(raw(t)).unwrap();
        let (f, d) = features(&nodes, &boundary, &u, &pose, &meas(&pose), fit).unwrap();
        let (g, e) = features(
            &nodes,
            &boundary,
            &u,
            &Rigid::identity(),
            &meas(&Rigid::identity()),
            fit,
        )
        .unwrap();
        let mut covered = 0;
        for i in 0..300 {
            let x = [0, 1, 2].map(|a| nodes[i][a] + u[3 * i + a]);
            let direct = image
                .iter()
                .map(|p| ((0..3).map(|a| (p[a] - x[a]).powi(2)).sum::<f64>()).sqrt())
                .fold(f64::INFINITY, f64::min);
            assert!(
                (d[i] - direct).abs() < 1e-9,
                "node {i}: {} vs {direct}",
                d[i]
            );
            assert!((e[i] - direct).abs() < 1e-9);
            covered += usize::from(boundary[i] && direct <= COVER_RADIUS_MM);
        }
        // The same up to rounding (the pose's round trip moves the points by ulps).
        for (a, b) in f.regressors().iter().zip(g.regressors()) {
            assert!((a - b).abs() < 1e-9, "{f:?} vs {g:?}");
        }
        assert_eq!((f.surface_points, f.ultrasound_points), (30, 10));
        assert!((f.surface_covered - covered as f64 / 100.0).abs() < 1e-12);
        assert!((f.coverage_mean_mm - d.iter().sum::<f64>() / 300.0).abs() < 1e-9);
        let c = [0, 1, 2].map(|a| nodes.iter().map(|x| x[a]).sum::<f64>() / 300.0);
        let r2 = nodes
            .iter()
            .map(|x| (0..3).map(|a| (x[a] - c[a]).powi(2)).sum::<f64>())
            .sum::<f64>()
            / 300.0;
        assert!((f.size_mm - r2.sqrt()).abs() < 1e-9);
        let mu = (0..300)
            .map(|i| (0..3).map(|a| u[3 * i + a].powi(2)).sum::<f64>().sqrt())
            .sum::<f64>()
            / 300.0;
        assert!((f.mean_displacement_mm - mu).abs() < 1e-12);
        // No points, or sizes that disagree: no features.
        let empty = Checked::empty(None).unwrap();
        assert!(features(&nodes, &boundary, &u, &pose, &empty, fit).is_none());
        assert!(features(&nodes, &boundary[1..], &u, &pose, &meas(&pose), fit).is_none());
    }

    /// The bound grows with the node's distance from the data when the per-node law says so,
    /// and a model without the method gives no estimate.
    #[test]
    fn the_bound_grows_away_from_the_data_and_unknown_methods_get_none() {
        let mm = MethodErrorModel {
            mean: vec![0.0; REGRESSORS.len()],
            std: vec![1.0; REGRESSORS.len()],
            z_min: vec![-1e9; REGRESSORS.len()],
            z_max: vec![1e9; REGRESSORS.len()],
            weights: vec![0.0; REGRESSORS.len() + 1],
            smearing: 2.0,
            node: [0.0, 1.0, 2.0, 0.0],
            node_quantiles: vec![(0.5, 0.0), (0.9, 0.5)],
            registrations: 100,
            failure: None,
        };
        let model = ErrorModel {
            format: FORMAT.into(),
            version: VERSION,
            regressors: REGRESSORS.iter().map(|s| s.to_string()).collect(),
            level: 0.9,
            methods: [("libr".to_string(), mm)].into(),
            provenance: serde_json::Value::Null,
        };
        let f = ErrorFeatures {
            surface_points: 10,
            ultrasound_points: 0,
            residual_rms_mm: 1.0,
            rigid_rms_mm: 1.0,
            strain_energy_uj: 0.0,
            mean_displacement_mm: 1.0,
            coverage_mean_mm: 10.0,
            surface_covered: 0.5,
            size_mm: 50.0,
            far_displacement_mm: 0.0,
            max_displacement_mm: 1.0,
            coverage_p90_mm: 20.0,
        };
        let e = model.estimate("libr", &f, &[0.0, 25.0, 50.0]).unwrap();
        // T̂ = exp(0) · 2 = 2; bound = exp(ln 2 + 2ρ + 0.5) − ε.
        assert!((e.predicted_tre_mm - 2.0).abs() < 1e-12);
        for (b, rho) in e.node_bound_mm.iter().zip([0.0, 0.5, 1.0]) {
            let want = (2.0f64.ln() + 2.0 * rho + 0.5).exp() - NODE_EPS_MM;
            assert!((b - want).abs() < 1e-9, "{b} vs {want}");
        }
        assert!(model.estimate("rigid", &f, &[0.0]).is_none());
        // The quantile between stored levels is interpolated.
        let q = model.methods["libr"].quantile(0.7);
        assert!((q - 0.25).abs() < 1e-12);
        assert_eq!(e.failure_probability, None);

        // With a failure part: p = σ(0.3 + 0.1·z₁), T̂_fail = exp(ln 30) · 1.5, T̂_ok = 2;
        // z₁ = ln(1 + 10) (standardisation is the identity here).
        let mut with = model.clone();
        let k = REGRESSORS.len();
        let mut logistic = vec![0.0; k + 1];
        logistic[0] = 0.3;
        logistic[1] = 0.1;
        let mut weights = vec![0.0; k + 1];
        weights[0] = 30f64.ln();
        with.version = 2;
        with.methods.get_mut("libr").unwrap().failure = Some(FailureModel {
            threshold_mm: 20.0,
            logistic,
            weights,
            smearing: 1.5,
            failed: 12,
        });
        let with = ErrorModel::from_json(&serde_json::to_string(&with).unwrap()).unwrap();
        let e = with.estimate("libr", &f, &[0.0]).unwrap();
        let p = 1.0 / (1.0 + (-(0.3 + 0.1 * 11f64.ln())).exp());
        assert!((e.failure_probability.unwrap() - p).abs() < 1e-12);
        assert_eq!(e.failure_threshold_mm, Some(20.0));
        let want = p * 45.0 + (1.0 - p) * 2.0;
        assert!((e.predicted_tre_mm - want).abs() < 1e-9, "{e:?}");
        // A failure part in a version 1 file, or of the wrong size, is refused by name.
        let mut v1 = with.clone();
        v1.version = 1;
        let err = ErrorModel::from_json(&serde_json::to_string(&v1).unwrap()).unwrap_err();
        assert!(err.to_string().contains("methods.libr.failure"), "{err}");
        let mut short = with.clone();
        short
            .methods
            .get_mut("libr")
            .unwrap()
            .failure
            .as_mut()
            .unwrap()
            .logistic
            .pop();
        let err = ErrorModel::from_json(&serde_json::to_string(&short).unwrap()).unwrap_err();
        assert!(err.to_string().contains("methods.libr.failure"), "{err}");
        // The logistic function stays finite and exact at its ends.
        assert_eq!(sigmoid(-1000.0), 0.0);
        assert_eq!(sigmoid(1000.0), 1.0);
        assert!((sigmoid(0.0) - 0.5).abs() < 1e-15);
    }

    #[test]
    fn the_built_in_model_parses_and_covers_the_served_methods() {
        let m = builtin().expect("assets/models/error/model.json parses");
        // Every method the service answers with (auto answers with its chosen candidate's).
        for method in ["initial", "rigid", "libr", "librplus", "adaptive"] {
            assert!(
                m.methods.contains_key(method),
                "no calibration for {method}"
            );
            // Each has its failure part, and it separates: a registration like the failed
            // ones (large rigid and final residuals, large strain energy) is more likely failed
            // than a typical one.
            let mm = &m.methods[method];
            assert!(mm.failure.is_some(), "{method}: no failure part");
            let typical = ErrorFeatures {
                surface_points: 300,
                ultrasound_points: 50,
                residual_rms_mm: 1.0,
                rigid_rms_mm: 3.0,
                strain_energy_uj: 50_000.0,
                mean_displacement_mm: 6.0,
                coverage_mean_mm: 30.0,
                surface_covered: 0.3,
                size_mm: 60.0,
                far_displacement_mm: 6.0,
                max_displacement_mm: 40.0,
                coverage_p90_mm: 50.0,
            };
            let failed_like = ErrorFeatures {
                residual_rms_mm: 8.0,
                rigid_rms_mm: 10.0,
                strain_energy_uj: 400_000.0,
                ..typical
            };
            // Doing nothing moves nothing: its residual is the start's.
            let (typical, failed_like) = if method == "initial" {
                let still = |rms_mm| ErrorFeatures {
                    residual_rms_mm: rms_mm,
                    rigid_rms_mm: rms_mm,
                    strain_energy_uj: 0.0,
                    mean_displacement_mm: 0.0,
                    far_displacement_mm: 0.0,
                    max_displacement_mm: 0.0,
                    ..typical
                };
                (still(2.0), still(10.0))
            } else {
                (typical, failed_like)
            };
            let (p0, p1) = (
                mm.failure_probability(&typical).unwrap(),
                mm.failure_probability(&failed_like).unwrap(),
            );
            assert!(p0 < 0.1 && p1 > p0, "{method}: {p0} vs {p1}");
        }
    }
}
