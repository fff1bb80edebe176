//! Calibrating when LIBR+ abstains ([`crate::gcn::abstain`]) on data like its networks'
//! training data: every kept scenario is registered by LIBR+ with abstention off, and the signals
//! the rule reads are collected. The truth is not read: the rule is set from what a registration
//! shows, on data known to be in family.

use super::EvalError;
use crate::gcn::abstain::AbstainSignals;
use crate::gcn::io::TrainedModel;
use crate::pipeline::{Method, PipelineParams, Prepared, register};
use std::path::Path;
use std::sync::Arc;

/// The signals of every kept scenario's LIBR+ registration (every `every`-th block of five, as
/// `evaluate`), in dataset order, and how many registrations failed or did not correct (left
/// out).
pub fn collect(
    dir: &Path,
    every: usize,
    params: &PipelineParams,
    models: &[Arc<TrainedModel>],
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<(Vec<AbstainSignals>, usize), EvalError> {
    if models.is_empty() {
        return Err(EvalError::Parameter("LIBR+ needs SR-GCN models".into()));
    }
    let params = PipelineParams {
        abstain: false,
        deadline: None,
        ..params.clone()
    };
    let cache = dir.join("cache");
    let results = super::over_kept_scenarios(
        dir,
        every,
        1,
        |geo| {
            Ok(
                Prepared::new(geo.model.clone(), Some(&params.libr), Some(&cache))?
                    .with_models(models.to_vec())?,
            )
        },
        |case, sc, tick| {
            let r = register(case, &sc.measurements, Method::LibrPlus, &params);
            tick();
            let s = r.ok().and_then(|r| r.correction?.signals);
            vec![s.map(|s| AbstainSignals {
                spread_ratio: s.spread_ratio,
                libr_rms_mm: s.libr_rms_mm,
            })]
        },
        progress,
    )?;
    let left_out = results.iter().filter(|s| s.is_none()).count();
    Ok((results.into_iter().flatten().collect(), left_out))
}
