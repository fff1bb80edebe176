//! Calibrating and checking the per-registration error estimate
//! ([`crate::register::uncertainty`]) on generated data, where the truth is known: every kept
//! scenario is registered by each method, the registration's surgery-time features are read as
//! the service reads them, and the true TRE and node errors are measured against the truth.
//! [`fit`] makes an [`ErrorModel`] from such samples; [`check`] scores a model on samples it was
//! not calibrated on (another seed): correlation and mean absolute error of the predicted mean
//! TRE, and how often the per-node bound covers the true node error.

use super::report::CATEGORY_ORDER;
use super::{EvalError, node_errors_mm};
use crate::gcn::io::TrainedModel;
use crate::pipeline::{Method, PipelineParams, Prepared, register};
use crate::register::uncertainty::{
    ErrorFeatures, ErrorModel, FORMAT, FailureModel, MethodErrorModel, NODE_EPS_MM, REGRESSORS,
    VERSION, linear, sigmoid,
};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

/// Every `NODE_STRIDE`-th node of each registration is kept for the per-node model and its
/// coverage (about 2,000 of a 9,000-node liver).
pub const NODE_STRIDE: usize = 4;

/// A method gets a failure part ([`FailureModel`]) only with at least this many calibration
/// registrations over the threshold.
pub const MIN_FAILED: usize = 10;

/// Per-node residual quantile levels stored in a model.
pub const QUANTILE_LEVELS: [f64; 7] = [0.5, 0.68, 0.8, 0.85, 0.9, 0.95, 0.99];

/// One registration of a scenario, with what the estimate reads and what the truth says.
#[derive(Debug, Clone)]
pub struct Sample {
    /// Method name.
    pub method: String,
    /// Scenario id.
    pub scenario: String,
    /// Measurement category.
    pub category: String,
    /// The surgery-time features.
    pub features: ErrorFeatures,
    /// True mean TRE over nodes (mm).
    pub tre_mm: f64,
    /// Kept nodes: (distance to the nearest measured point / organ size, true error in mm).
    pub nodes: Vec<(f32, f32)>,
}

/// Registers the kept scenarios of a dataset (every `every`-th block of five, as `evaluate`)
/// with each method and returns the samples in dataset order. `models`: the SR-GCN members
/// LIBR+ needs (required when `methods` has it). A registration that fails is left out and
/// counted in the second value.
pub fn collect(
    dir: &Path,
    methods: &[Method],
    every: usize,
    params: &PipelineParams,
    models: &[Arc<TrainedModel>],
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Vec<Sample>, usize), EvalError> {
    if methods.contains(&Method::LibrPlus) && models.is_empty() {
        return Err(EvalError::Parameter(
            "method librplus needs SR-GCN models".into(),
        ));
    }
    if methods
        .iter()
        .any(|m| matches!(m, Method::V2s | Method::Auto))
    {
        return Err(EvalError::Parameter(
            "the error estimate is calibrated for initial, rigid, libr, librplus and adaptive (auto's answers carry their chosen candidate's)".into(),
        ));
    }
    let cache = dir.join("cache");
    let needs_basis = methods
        .iter()
        .any(|m| matches!(m, Method::Libr | Method::LibrPlus | Method::Adaptive));
    let results = super::over_kept_scenarios(
        dir,
        every,
        methods.len(),
        |geo| {
            let mut case = Prepared::new(
                geo.model.clone(),
                needs_basis.then_some(&params.libr),
                Some(&cache),
            )?;
            if methods.contains(&Method::LibrPlus) {
                case = case.with_models(models.to_vec())?;
            }
            if methods.contains(&Method::Adaptive) {
                case = case.with_adaptive(&params.libr, &params.adaptive, Some(&cache))?;
            }
            Ok((case, geo.surface.clone()))
        },
        |(case, boundary), sc, tick| {
            let nodes = case.model.mesh.nodes();
            methods
                .iter()
                .map(|&method| {
                    let r = register(case, &sc.measurements, method, params);
                    tick();
                    let r = r.ok()?;
                    let (features, dist) = r.error_features(case, boundary, &sc.measurements)?;
                    let err = node_errors_mm(
                        nodes,
                        (&r.image_to_physical, &r.u),
                        (&sc.truth.image_to_physical, &sc.truth.displacement),
                    );
                    let tre_mm = err.iter().sum::<f64>() / err.len() as f64;
                    let size = features.size_mm.max(1e-9);
                    let kept = (0..nodes.len())
                        .step_by(NODE_STRIDE)
                        .map(|i| ((dist[i] / size) as f32, err[i] as f32))
                        .collect();
                    Some(Sample {
                        method: method.name().to_string(),
                        scenario: sc.id.clone(),
                        category: sc.category.clone(),
                        features,
                        tre_mm,
                        nodes: kept,
                    })
                })
                .collect()
        },
        progress,
    )?;
    let failed = results.iter().filter(|s| s.is_none()).count();
    let out: Vec<Sample> = results.into_iter().flatten().collect();
    Ok((out, failed))
}

/// `Σ c_r x_r x_rᵀ + λ I'` and `Σ d_r x_r` over the rows r of `z`, x_r = [1, z_r] and
/// `(c_r, d_r) = cd(r)`; λ on the diagonal except the intercept's. The normal equations of a
/// ridge fit (c = 1, d = target) and a Newton step of the logistic fit.
fn normal_equations(
    z: &[Vec<f64>],
    lambda: f64,
    cd: impl Fn(usize) -> (f64, f64),
) -> Option<(nalgebra::DMatrix<f64>, nalgebra::DVector<f64>)> {
    let k = z.first()?.len() + 1;
    let mut a = nalgebra::DMatrix::<f64>::zeros(k, k);
    let mut b = nalgebra::DVector::<f64>::zeros(k);
    for (r, row) in z.iter().enumerate() {
        let (c, d) = cd(r);
        let x: Vec<f64> = std::iter::once(1.0).chain(row.iter().copied()).collect();
        for i in 0..k {
            b[i] += d * x[i];
            for j in 0..k {
                a[(i, j)] += c * x[i] * x[j];
            }
        }
    }
    for i in 1..k {
        a[(i, i)] += lambda;
    }
    Some((a, b))
}

/// Ridge least squares: weights (intercept first, not penalised) of `y` on the rows of `z`.
fn ridge(z: &[Vec<f64>], y: &[f64], lambda: f64) -> Option<Vec<f64>> {
    let (a, b) = normal_equations(z, lambda, |r| (1.0, y[r]))?;
    let w = a.cholesky()?.solve(&b);
    w.iter()
        .all(|x| x.is_finite())
        .then(|| w.iter().copied().collect())
}

/// Ridge-penalised logistic regression (Newton's method with step halving, so that the
/// penalised negative log-likelihood falls at every step; intercept first, not penalised) of
/// the labels `y` on the rows of `z`.
fn logistic(z: &[Vec<f64>], y: &[bool], lambda: f64) -> Option<Vec<f64>> {
    let k = z.first()?.len() + 1;
    let rate = (y.iter().filter(|b| **b).count() as f64 + 0.5) / (y.len() as f64 + 1.0);
    // ln(1 + e^x) without overflow.
    let softplus = |x: f64| x.max(0.0) + (-x.abs()).exp().ln_1p();
    let objective = |w: &[f64]| {
        z.iter()
            .zip(y)
            .map(|(row, &label)| {
                let eta = linear(w, row);
                softplus(eta) - if label { eta } else { 0.0 }
            })
            .sum::<f64>()
            + 0.5 * lambda * w[1..].iter().map(|x| x * x).sum::<f64>()
    };
    let mut w = vec![0.0; k];
    w[0] = (rate / (1.0 - rate)).ln();
    let mut current = objective(&w);
    for _ in 0..100 {
        // Hessian and gradient of the objective.
        let (h, mut g) = normal_equations(z, lambda, |r| {
            let p = sigmoid(linear(&w, &z[r]));
            ((p * (1.0 - p)).max(1e-12), p - f64::from(u8::from(y[r])))
        })?;
        for i in 1..k {
            g[i] += lambda * w[i];
        }
        let step = h.cholesky()?.solve(&g);
        let mut scale = 1.0;
        let (trial, value) = loop {
            let trial: Vec<f64> = (0..k).map(|i| w[i] - scale * step[i]).collect();
            let value = objective(&trial);
            if value <= current || scale < 1e-9 {
                break (trial, value);
            }
            scale *= 0.5;
        };
        let moved = scale * step.amax();
        if value > current {
            break;
        }
        (w, current) = (trial, value);
        if moved < 1e-10 {
            break;
        }
    }
    w.iter().all(|x| x.is_finite()).then_some(w)
}

/// `ln T` weights fitted by ridge on the rows `z` (of the samples `picked`), and their smearing
/// factor.
fn log_law(z: &[Vec<f64>], y: &[f64], picked: &[bool], lambda: f64) -> Option<(Vec<f64>, f64)> {
    let (zs, ys): (Vec<Vec<f64>>, Vec<f64>) = z
        .iter()
        .zip(y)
        .zip(picked)
        .filter(|(_, p)| **p)
        .map(|((r, t), _)| (r.clone(), *t))
        .unzip();
    let weights = ridge(&zs, &ys, lambda)?;
    let smearing = zs
        .iter()
        .zip(&ys)
        .map(|(r, t)| (t - linear(&weights, r)).exp())
        .sum::<f64>()
        / ys.len().max(1) as f64;
    Some((weights, smearing))
}

/// The mean-TRE part of a method's model fitted on `samples` (all of one method); with a
/// failure threshold (mm) and at least [`MIN_FAILED`] registrations over it (and enough
/// under it), the failure part too.
fn fit_tre(samples: &[&Sample], lambda: f64, failure_mm: Option<f64>) -> Option<MethodErrorModel> {
    let k = REGRESSORS.len();
    let n = samples.len();
    if n < 2 * (k + 1) {
        return None;
    }
    let xs: Vec<[f64; 12]> = samples.iter().map(|s| s.features.regressors()).collect();
    let mut mean = vec![0.0; k];
    let mut std = vec![0.0; k];
    for j in 0..k {
        mean[j] = xs.iter().map(|x| x[j]).sum::<f64>() / n as f64;
        let v = xs.iter().map(|x| (x[j] - mean[j]).powi(2)).sum::<f64>() / n as f64;
        std[j] = if v.sqrt() > 1e-9 { v.sqrt() } else { 1.0 };
    }
    let z: Vec<Vec<f64>> = xs
        .iter()
        .map(|x| (0..k).map(|j| (x[j] - mean[j]) / std[j]).collect())
        .collect();
    let z_min = (0..k)
        .map(|j| z.iter().map(|r| r[j]).fold(f64::INFINITY, f64::min))
        .collect();
    let z_max = (0..k)
        .map(|j| z.iter().map(|r| r[j]).fold(f64::NEG_INFINITY, f64::max))
        .collect();
    let y: Vec<f64> = samples.iter().map(|s| s.tre_mm.max(1e-3).ln()).collect();
    let failed: Vec<bool> = samples
        .iter()
        .map(|s| failure_mm.is_some_and(|t| s.tre_mm > t))
        .collect();
    let n_failed = failed.iter().filter(|b| **b).count();
    let (weights, smearing, failure) = match failure_mm {
        Some(threshold_mm) if n_failed >= MIN_FAILED && n - n_failed >= 2 * (k + 1) => {
            let ok: Vec<bool> = failed.iter().map(|b| !b).collect();
            let (weights, smearing) = log_law(&z, &y, &ok, lambda)?;
            let (fw, fs) = log_law(&z, &y, &failed, lambda)?;
            let failure = FailureModel {
                threshold_mm,
                logistic: logistic(&z, &failed, lambda)?,
                weights: fw,
                smearing: fs,
                failed: n_failed,
            };
            (weights, smearing, Some(failure))
        }
        _ => {
            let (weights, smearing) = log_law(&z, &y, &vec![true; n], lambda)?;
            (weights, smearing, None)
        }
    };
    Some(MethodErrorModel {
        mean,
        std,
        z_min,
        z_max,
        weights,
        smearing,
        node: [0.0; 4],
        node_quantiles: vec![(0.5, 0.0)],
        registrations: n,
        failure,
    })
}

/// Folds of the cross-fitted TRE predictions the per-node model is fitted on.
const FOLDS: usize = 5;

/// Fits an error model on calibration samples: per method, the mean-TRE regression, then the
/// per-node model on the TRE each registration gets from a model fitted without its fold
/// (5 folds by scenario, so the node bound is calibrated on predictions as uncertain as those on
/// new data), and its residual quantiles. `lambda`: the ridge penalty (standardised units, also
/// the logistic regression's); `failure_mm`: the TRE over which a registration counts as failed
/// (None: no failure part).
pub fn fit(
    samples: &[Sample],
    level: f64,
    lambda: f64,
    failure_mm: Option<f64>,
    provenance: serde_json::Value,
) -> Result<ErrorModel, EvalError> {
    if let Some(t) = failure_mm.filter(|t| !(t.is_finite() && *t > 0.0)) {
        return Err(EvalError::Parameter(format!(
            "--failure-threshold {t} is not a positive number of mm"
        )));
    }
    if !(level > 0.0 && level < 1.0) {
        return Err(EvalError::Parameter(format!(
            "--level {level} is not in (0, 1)"
        )));
    }
    let mut by_method: BTreeMap<&str, Vec<&Sample>> = BTreeMap::new();
    for s in samples {
        by_method.entry(&s.method).or_default().push(s);
    }
    let mut methods = BTreeMap::new();
    for (name, ss) in by_method {
        let Some(mut mm) = fit_tre(&ss, lambda, failure_mm) else {
            return Err(EvalError::Parameter(format!(
                "method {name}: {} registrations are too few to calibrate (at least {})",
                ss.len(),
                2 * (REGRESSORS.len() + 1)
            )));
        };
        // Cross-fitted TRE predictions.
        let fold = |s: &Sample| (crate::util::fnv1a(s.scenario.as_bytes()) % FOLDS as u64) as usize;
        let mut t_hat = vec![0.0; ss.len()];
        for f in 0..FOLDS {
            let train: Vec<&Sample> = ss.iter().filter(|s| fold(s) != f).copied().collect();
            let model = fit_tre(&train, lambda, failure_mm).unwrap_or_else(|| mm.clone());
            for (i, s) in ss.iter().enumerate() {
                if fold(s) == f {
                    t_hat[i] = model.predict_tre(&s.features);
                }
            }
        }
        // Per-node regression of ln(e + ε) on [1, ln T̂, ρ, ρ²].
        let mut a = nalgebra::Matrix4::<f64>::zeros();
        let mut b = nalgebra::Vector4::<f64>::zeros();
        for (s, &t) in ss.iter().zip(&t_hat) {
            for &(rho, e) in &s.nodes {
                let rho = rho as f64;
                let x = nalgebra::Vector4::new(1.0, t.max(1e-6).ln(), rho, rho * rho);
                a += x * x.transpose();
                b += x * (e as f64 + NODE_EPS_MM).ln();
            }
        }
        let node = a
            .cholesky()
            .map(|c| c.solve(&b))
            .filter(|w| w.iter().all(|x| x.is_finite()))
            .ok_or_else(|| {
                EvalError::Internal(format!("method {name}: the per-node fit is singular"))
            })?;
        mm.node = [node[0], node[1], node[2], node[3]];
        let res: Vec<f64> = ss
            .iter()
            .zip(&t_hat)
            .flat_map(|(s, &t)| {
                let mm = &mm;
                s.nodes.iter().map(move |&(rho, e)| {
                    (e as f64 + NODE_EPS_MM).ln() - mm.node_log(t, rho as f64)
                })
            })
            .collect();
        let mut levels: Vec<f64> = QUANTILE_LEVELS.to_vec();
        if !levels.iter().any(|l| (l - level).abs() < 1e-12) {
            levels.push(level);
            levels.sort_by(f64::total_cmp);
        }
        mm.node_quantiles = levels
            .iter()
            .map(|&p| (p, crate::util::quantile(&res, p)))
            .collect();
        methods.insert(name.to_string(), mm);
    }
    Ok(ErrorModel {
        format: FORMAT.into(),
        version: VERSION,
        regressors: REGRESSORS.iter().map(|s| s.to_string()).collect(),
        level,
        methods,
        provenance,
    })
}

/// How an error model does on a set of samples (one method, one category or all).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CheckRow {
    /// Registrations.
    pub registrations: usize,
    /// Mean true TRE (mm).
    pub true_tre_mm: f64,
    /// Mean predicted TRE (mm).
    pub predicted_tre_mm: f64,
    /// Pearson correlation of predicted and true TRE (NaN under 3 registrations or no spread).
    pub r: f64,
    /// Mean absolute error of the predicted TRE (mm).
    pub mae_mm: f64,
    /// Fraction of kept nodes whose true error is within their bound at the model's level.
    pub coverage: f64,
    /// Mean of the node bounds (mm).
    pub mean_bound_mm: f64,
    /// Registrations over the model's failure threshold (0 without a failure part).
    pub failures: usize,
    /// Area under the ROC curve of the failure probability against "failed" (NaN without a
    /// failure part, or without failed and unfailed registrations both).
    pub failure_auc: f64,
}

/// A model's check per method: all categories, then each.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct MethodCheck {
    /// Every sample of the method.
    pub all: CheckRow,
    /// Per category.
    pub by_category: BTreeMap<String, CheckRow>,
    /// Per registration: (scenario, category, predicted, true TRE), for plots.
    pub points: Vec<(String, String, f64, f64)>,
}

fn pearson(x: &[f64], y: &[f64]) -> f64 {
    let n = x.len() as f64;
    if x.len() < 3 {
        return f64::NAN;
    }
    let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in x.iter().zip(y) {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx).powi(2);
        syy += (b - my).powi(2);
    }
    if sxx <= 0.0 || syy <= 0.0 {
        return f64::NAN;
    }
    sxy / (sxx * syy).sqrt()
}

/// Area under the ROC curve of `score` for the `positive` ones (ties count half); NaN without
/// both kinds.
fn auc(score: &[f64], positive: &[bool]) -> f64 {
    let (mut wins, mut pairs) = (0.0, 0usize);
    for (a, pa) in score.iter().zip(positive) {
        if !pa {
            continue;
        }
        for (b, pb) in score.iter().zip(positive) {
            if !pb {
                pairs += 1;
                wins += if a > b {
                    1.0
                } else if a == b {
                    0.5
                } else {
                    0.0
                };
            }
        }
    }
    if pairs == 0 {
        f64::NAN
    } else {
        wins / pairs as f64
    }
}

fn row(ss: &[(&Sample, f64)], model: &MethodErrorModel, level: f64) -> CheckRow {
    let pred: Vec<f64> = ss.iter().map(|(_, t)| *t).collect();
    let truth: Vec<f64> = ss.iter().map(|(s, _)| s.tre_mm).collect();
    let n = ss.len().max(1) as f64;
    let q = model.quantile(level);
    let (mut inside, mut nodes, mut bound_sum) = (0usize, 0usize, 0.0);
    for (s, t) in ss {
        for &(rho, e) in &s.nodes {
            let bound = model.node_bound(*t, rho as f64, q);
            inside += usize::from(e as f64 <= bound);
            nodes += 1;
            bound_sum += bound;
        }
    }
    let (failures, failure_auc) = match &model.failure {
        Some(f) => {
            let failed: Vec<bool> = truth.iter().map(|t| *t > f.threshold_mm).collect();
            let p: Vec<f64> = ss
                .iter()
                .map(|(s, _)| model.failure_probability(&s.features).unwrap_or(0.0))
                .collect();
            (failed.iter().filter(|b| **b).count(), auc(&p, &failed))
        }
        None => (0, f64::NAN),
    };
    CheckRow {
        failures,
        failure_auc,
        registrations: ss.len(),
        true_tre_mm: truth.iter().sum::<f64>() / n,
        predicted_tre_mm: pred.iter().sum::<f64>() / n,
        r: pearson(&pred, &truth),
        mae_mm: pred
            .iter()
            .zip(&truth)
            .map(|(a, b)| (a - b).abs())
            .sum::<f64>()
            / n,
        coverage: inside as f64 / nodes.max(1) as f64,
        mean_bound_mm: bound_sum / nodes.max(1) as f64,
    }
}

/// Scores `model` on `samples` per method (those the model has).
pub fn check(model: &ErrorModel, samples: &[Sample]) -> BTreeMap<String, MethodCheck> {
    let mut out = BTreeMap::new();
    for (name, mm) in &model.methods {
        let ss: Vec<(&Sample, f64)> = samples
            .iter()
            .filter(|s| &s.method == name)
            .map(|s| (s, mm.predict_tre(&s.features)))
            .collect();
        if ss.is_empty() {
            continue;
        }
        let mut cats: BTreeMap<String, Vec<(&Sample, f64)>> = BTreeMap::new();
        for &(s, t) in &ss {
            cats.entry(s.category.clone()).or_default().push((s, t));
        }
        out.insert(
            name.clone(),
            MethodCheck {
                all: row(&ss, mm, model.level),
                by_category: cats
                    .iter()
                    .map(|(c, v)| (c.clone(), row(v, mm, model.level)))
                    .collect(),
                points: ss
                    .iter()
                    .map(|(s, t)| (s.scenario.clone(), s.category.clone(), *t, s.tre_mm))
                    .collect(),
            },
        );
    }
    out
}

/// The samples as CSV (one registration a row: set, method, scenario, category, the features,
/// the true TRE), for a look at what predicts the error.
pub fn samples_csv(sets: &[(&str, &[Sample])]) -> String {
    let mut s = String::from(
        "set,method,scenario,category,surface_points,ultrasound_points,residual_rms_mm,rigid_rms_mm,strain_energy_uj,mean_displacement_mm,coverage_mean_mm,surface_covered,size_mm,far_displacement_mm,max_displacement_mm,coverage_p90_mm,true_tre_mm\n",
    );
    for (set, samples) in sets {
        for x in *samples {
            let f = &x.features;
            s += &format!(
                "{set},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
                x.method,
                x.scenario,
                x.category,
                f.surface_points,
                f.ultrasound_points,
                f.residual_rms_mm,
                f.rigid_rms_mm,
                f.strain_energy_uj,
                f.mean_displacement_mm,
                f.coverage_mean_mm,
                f.surface_covered,
                f.size_mm,
                f.far_displacement_mm,
                f.max_displacement_mm,
                f.coverage_p90_mm,
                x.tre_mm
            );
        }
    }
    s
}

/// A Markdown table of a check: one row per method and category (all first).
pub fn markdown(checks: &BTreeMap<String, MethodCheck>, level: f64) -> String {
    let mut s = format!(
        "| method | category | registrations | true TRE (mm) | predicted (mm) | r | MAE (mm) | {:.0} % node bound covers | mean bound (mm) | failed (AUC of the failure probability) |\n|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        100.0 * level
    );
    for (name, c) in checks {
        let mut cats: Vec<(&str, &CheckRow)> = vec![("all", &c.all)];
        for cat in CATEGORY_ORDER {
            if let Some(r) = c.by_category.get(cat) {
                cats.push((cat, r));
            }
        }
        for (cat, r) in c.by_category.iter() {
            if !CATEGORY_ORDER.contains(&cat.as_str()) {
                cats.push((cat, r));
            }
        }
        for (cat, r) in cats {
            s += &format!(
                "| {name} | {cat} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.1} % | {:.2} | {} |\n",
                r.registrations,
                r.true_tre_mm,
                r.predicted_tre_mm,
                r.r,
                r.mae_mm,
                100.0 * r.coverage,
                r.mean_bound_mm,
                if r.failure_auc.is_finite() {
                    format!("{} ({:.3})", r.failures, r.failure_auc)
                } else {
                    format!("{}", r.failures)
                }
            );
        }
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(
        method: &str,
        id: usize,
        f: ErrorFeatures,
        tre: f64,
        nodes: Vec<(f32, f32)>,
    ) -> Sample {
        Sample {
            method: method.into(),
            scenario: format!("d/{id}"),
            category: CATEGORY_ORDER[id % 5].into(),
            features: f,
            tre_mm: tre,
            nodes,
        }
    }

    fn features(seed: u64) -> ErrorFeatures {
        let mut rng = crate::util::SplitMix64::new(seed);
        ErrorFeatures {
            surface_points: 50 + (rng.next_f64() * 500.0) as usize,
            ultrasound_points: (rng.next_f64() * 300.0) as usize,
            residual_rms_mm: 0.5 + 2.0 * rng.next_f64(),
            rigid_rms_mm: 1.0 + 4.0 * rng.next_f64(),
            strain_energy_uj: 10.0 * rng.next_f64(),
            mean_displacement_mm: 1.0 + 8.0 * rng.next_f64(),
            coverage_mean_mm: 10.0 + 30.0 * rng.next_f64(),
            surface_covered: rng.next_f64(),
            size_mm: 60.0 + 10.0 * rng.next_f64(),
            far_displacement_mm: 3.0 * rng.next_f64(),
            max_displacement_mm: 5.0 + 10.0 * rng.next_f64(),
            coverage_p90_mm: 30.0 + 30.0 * rng.next_f64(),
        }
    }

    /// Data made by a known law (ln TRE linear in the regressors, node errors log-normal around
    /// a known per-node law): the fit recovers the TRE law (r → 1, small MAE on new draws) and
    /// its bound covers its level of new nodes, within sampling error.
    #[test]
    fn the_fit_recovers_a_known_law_and_its_bound_covers_its_level() {
        let law = |f: &ErrorFeatures| {
            let x = f.regressors();
            (0.3 + 0.5 * x[3] - 0.2 * x[1] + 0.4 * x[6]).exp()
        };
        let make = |seed0: u64, count: usize| -> Vec<Sample> {
            let mut rng = crate::util::SplitMix64::new(seed0 + 7);
            (0..count)
                .map(|i| {
                    let f = features(seed0 + i as u64);
                    let t = law(&f);
                    let nodes = (0..200)
                        .map(|_| {
                            let rho = rng.next_f64() as f32 * 0.8;
                            // ln(e + ε) = ln t + 0.8 ρ + N(0, 0.5²).
                            let g = rng.normal();
                            let e = (t.ln() + 0.8 * rho as f64 + 0.5 * g).exp() - NODE_EPS_MM;
                            (rho, e.max(0.0) as f32)
                        })
                        .collect();
                    sample("libr", i, f, t, nodes)
                })
                .collect()
        };
        let train = make(1_000, 400);
        let model = fit(&train, 0.9, 1e-6, Some(1e6), serde_json::Value::Null).unwrap();
        assert!(
            model.methods["libr"].failure.is_none(),
            "no failures to learn"
        );
        let text = serde_json::to_string(&model).unwrap();
        let back = ErrorModel::from_json(&text).unwrap();
        // serde_json's parser may round the last bit of a float.
        let (a, b) = (&model.methods["libr"], &back.methods["libr"]);
        for (x, y) in a
            .weights
            .iter()
            .chain(&a.node)
            .zip(b.weights.iter().chain(&b.node))
        {
            assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{x} vs {y}");
        }
        let held = make(50_000, 200);
        let c = &check(&back, &held)["libr"];
        assert!(c.all.r > 0.99, "r {}", c.all.r);
        assert!(c.all.mae_mm < 0.02 * c.all.true_tre_mm, "{:?}", c.all);
        assert!(
            (c.all.coverage - 0.9).abs() < 0.02,
            "coverage {}",
            c.all.coverage
        );
        // The node law's slope on ρ is found.
        let b = back.methods["libr"].node;
        assert!(
            (b[1] - 1.0).abs() < 0.05 && (b[2] - 0.8).abs() < 0.1,
            "{b:?}"
        );
    }

    /// Data with failures (a known law under 20 mm, and the fifth of the registrations with
    /// the largest rigid residual at 40–80 mm): the failure part separates them on new draws
    /// (AUC ≈ 1), and the mixture predicts far better than one law fitted to all.
    #[test]
    fn the_failure_part_finds_failed_registrations_and_the_mixture_predicts_them() {
        let law = |f: &ErrorFeatures| {
            let x = f.regressors();
            (0.8 + 0.3 * x[2] - 0.1 * x[1] + 0.4 * x[6]).exp()
        };
        let make = |seed0: u64, count: usize| -> Vec<Sample> {
            (0..count)
                .map(|i| {
                    let f = features(seed0 + i as u64);
                    let t = if f.rigid_rms_mm > 4.2 {
                        40.0 + 4.0 * f.strain_energy_uj
                    } else {
                        law(&f)
                    };
                    let nodes = (0..10)
                        .map(|j| {
                            let rho = 0.08 * j as f32;
                            (rho, (t * (0.5 + rho as f64 + 0.01 * (i % 7) as f64)) as f32)
                        })
                        .collect();
                    sample("libr", i, f, t, nodes)
                })
                .collect()
        };
        let train = make(3_000, 600);
        let with = fit(&train, 0.9, 1.0, Some(20.0), serde_json::Value::Null).unwrap();
        let without = fit(&train, 0.9, 1.0, None, serde_json::Value::Null).unwrap();
        let f = with.methods["libr"]
            .failure
            .as_ref()
            .expect("a failure part");
        assert!((100..140).contains(&f.failed), "failed {}", f.failed);
        let back = ErrorModel::from_json(&serde_json::to_string(&with).unwrap()).unwrap();
        assert_eq!(back.version, 2);
        let held = make(90_000, 300);
        let (a, b) = (
            &check(&back, &held)["libr"].all,
            &check(&without, &held)["libr"].all,
        );
        assert!(a.failure_auc > 0.98, "{a:?}");
        assert!(a.failures > 40 && b.failures == 0 && b.failure_auc.is_nan());
        assert!(a.mae_mm < 0.5 * b.mae_mm, "mixture {a:?} vs one law {b:?}");
        assert!(
            fit(&train, 0.9, 1.0, Some(-1.0), serde_json::Value::Null)
                .unwrap_err()
                .to_string()
                .contains("--failure-threshold")
        );
        // The AUC by counting.
        assert_eq!(auc(&[0.9, 0.8, 0.1, 0.2], &[true, true, false, false]), 1.0);
        assert_eq!(auc(&[0.1, 0.5, 0.5], &[true, true, false]), 0.25);
        assert!(auc(&[0.1], &[true]).is_nan());
    }

    /// The logistic fit reaches the penalised optimum (its gradient, computed here directly,
    /// vanishes) on separable data with a weak penalty, where the optimum's weights are large
    /// and undamped Newton steps from the base rate overshoot.
    #[test]
    fn logistic_reaches_the_penalised_optimum_on_separable_data() {
        let z: Vec<Vec<f64>> = (0..400)
            .map(|i| {
                let t = -3.0 + 6.0 * i as f64 / 399.0;
                vec![t, (7.0 * t).sin()]
            })
            .collect();
        let y: Vec<bool> = z.iter().map(|r| r[0] > 2.6).collect();
        for lambda in [1e-2, 1.0] {
            let w = logistic(&z, &y, lambda).expect("a fit");
            let mut g = [0.0, lambda * w[1], lambda * w[2]];
            for (r, &label) in z.iter().zip(&y) {
                let d = sigmoid(linear(&w, r)) - f64::from(u8::from(label));
                g[0] += d;
                g[1] += d * r[0];
                g[2] += d * r[1];
            }
            assert!(
                g.iter().all(|x| x.abs() < 1e-6),
                "λ {lambda}: gradient {g:?}, w {w:?}"
            );
            assert!(w[1] > 1.0, "λ {lambda}: {w:?}");
        }
    }

    #[test]
    fn pearson_agrees_with_direct_values() {
        assert!((pearson(&[1.0, 2.0, 3.0, 4.0], &[2.0, 4.0, 6.0, 8.0]) - 1.0).abs() < 1e-12);
        assert!((pearson(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]) + 1.0).abs() < 1e-12);
        assert!(pearson(&[1.0, 1.0, 1.0], &[1.0, 2.0, 3.0]).is_nan());
    }

    #[test]
    fn a_model_file_of_another_version_or_size_is_refused_by_name() {
        let m = ErrorModel {
            format: FORMAT.into(),
            version: VERSION + 1,
            regressors: REGRESSORS.iter().map(|s| s.to_string()).collect(),
            level: 0.9,
            methods: BTreeMap::new(),
            provenance: serde_json::Value::Null,
        };
        let e = ErrorModel::from_json(&serde_json::to_string(&m).unwrap()).unwrap_err();
        assert!(e.to_string().contains("version"), "{e}");
        let mut m = m;
        m.version = VERSION;
        let mut mm = fit_tre(
            &(0..40)
                .map(|i| sample("rigid", i, features(i as u64), 3.0 + i as f64 * 0.1, vec![]))
                .collect::<Vec<_>>()
                .iter()
                .collect::<Vec<_>>(),
            1.0,
            None,
        )
        .unwrap();
        mm.weights.pop();
        m.methods.insert("rigid".into(), mm);
        let e = ErrorModel::from_json(&serde_json::to_string(&m).unwrap()).unwrap_err();
        assert!(e.to_string().contains("methods.rigid"), "{e}");
    }
}
