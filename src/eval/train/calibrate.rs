//! Calibration of a trained network's correction scale on validation scenarios, through the
//! data-consistency refit.

use super::*;
use crate::dataset::read::ScenarioData;
use crate::eval::EvalError;
use crate::gcn::infer::{apply_prediction, predict};
use crate::gcn::io::TrainedModel;
use crate::gcn::model::{SrGcnConfig, Target};
use crate::pipeline::PipelineParams;
use rayon::prelude::*;
use std::collections::BTreeMap;

/// Candidate correction scales with the data-consistency refit: 0, 0.125, …, 2.
pub fn refit_scale_grid() -> Vec<f64> {
    (0..=16).map(|k| k as f64 / 8.0).collect()
}

/// Fits a residual model's correction scale for LIBR+ as the pipeline runs it, with the
/// data-consistency refit ([`crate::pipeline::refit`], `params.refit_iterations` ≥ 1):
/// for each validation scenario (`items`: scenario, geometry, LIBR's solution), the network's
/// correction at every factor of `grid`, refitted, against the truth. Returns the factor with the
/// least mean node error (ties keep the larger) and the mean node error (mm) at every factor.
/// Scenarios whose LIBR failed are skipped; an error if none is left.
pub fn fit_refit_scale(
    model: &TrainedModel,
    cases: &BTreeMap<String, GeometryCase>,
    items: &[(&ScenarioData, &str, &Option<LibrSolution>)],
    params: &PipelineParams,
    grid: &[f64],
) -> Result<(f64, Vec<f64>), EvalError> {
    if model.config.target != Target::Residual {
        return Err(EvalError::Parameter(
            "only a residual model's correction has a scale".into(),
        ));
    }
    if params.refit_iterations == 0 {
        return Err(EvalError::Parameter(
            "refit_iterations is 0: nothing to refit".into(),
        ));
    }
    if grid.is_empty()
        || grid
            .iter()
            .any(|a| !(a.is_finite() && (0.0..=2.0).contains(a)))
    {
        return Err(EvalError::Parameter(
            "the scale grid must be non-empty, in [0, 2]".into(),
        ));
    }
    let unit_model = TrainedModel {
        config: SrGcnConfig {
            correction_scale: 1.0,
            ..model.config.clone()
        },
        net: model.net.clone(),
        provenance: serde_json::Value::Null,
        abstain: None,
    };
    let plain = crate::gcn::device::compute();
    let mut graphs = BTreeMap::new();
    for (g, gc) in cases {
        graphs.insert(g.clone(), gc.frame.mesh_graphs(&unit_model.config, &plain)?);
    }
    // Validation samples carry no truth, except for the paper's leak (a diagnostic).
    let leak = unit_model.config.diagnostic_truth_neighbours;
    let samples = build_samples(&unit_model.config, cases, items, params, leak, false)?;
    let per: Vec<Vec<f64>> = items
        .par_iter()
        .zip(samples.par_iter())
        .filter_map(|((sc, g, sol), sample)| {
            let (sol, sample) = (sol.as_ref()?, sample.as_ref()?);
            Some((sc, *g, sol, sample))
        })
        .map(|(sc, g, sol, sample)| -> Result<Vec<f64>, EvalError> {
            let gc = &cases[g];
            let y = predict(&unit_model, &graphs[g], &sample.data)
                .map_err(|e| EvalError::within(sc.id.clone(), e))?;
            let nodes = gc.geo.model.mesh.nodes();
            grid.iter()
                .map(|&a| {
                    let config = SrGcnConfig {
                        correction_scale: a,
                        ..unit_model.config.clone()
                    };
                    let ua = apply_prediction(&config, &gc.frame, &sol.u, &y)
                        .map_err(|e| EvalError::within(sc.id.clone(), e))?;
                    let r = crate::pipeline::refit(
                        &gc.case,
                        &sc.measurements,
                        params,
                        &ua,
                        &sol.transform,
                        None,
                        None,
                    )
                    .map_err(|e| EvalError::within(format!("{}: refit", sc.id), e))?;
                    let e = crate::eval::node_errors_mm(
                        nodes,
                        (&r.image_to_physical, &r.u),
                        (&sc.truth.image_to_physical, &sc.truth.displacement),
                    );
                    Ok(e.iter().sum::<f64>() / e.len().max(1) as f64)
                })
                .collect()
        })
        .collect::<Result<_, _>>()?;
    if per.is_empty() {
        return Err(EvalError::Data(
            "no validation scenario with a LIBR solution".into(),
        ));
    }
    let mean: Vec<f64> = (0..grid.len())
        .map(|k| per.iter().map(|e| e[k]).sum::<f64>() / per.len() as f64)
        .collect();
    let mut best = grid.len() - 1;
    for k in (0..grid.len()).rev() {
        if mean[k] < mean[best] - 1e-9 {
            best = k;
        }
    }
    Ok((grid[best], mean))
}
