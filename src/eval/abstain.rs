//! Calibrating when LIBR+ abstains ([`crate::gcn::abstain`]) on data like its networks'
//! training data: every kept scenario is registered by LIBR+ with abstention off, and the signals
//! the rule reads are collected. The truth is not read: the rule is set from what a registration
//! shows, on data known to be in family.

use super::report::CATEGORY_ORDER;
use super::{EvalError, load_geometry, load_scenarios, open};
use crate::gcn::abstain::AbstainSignals;
use crate::gcn::io::TrainedModel;
use crate::pipeline::{Method, PipelineParams, Prepared, register};
use rayon::prelude::*;
use std::collections::BTreeMap;
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
    let m = open(dir)?;
    let every = every.max(1);
    let block = CATEGORY_ORDER.len();
    let keep = |i: usize| (i / block) % every == 0;
    let total: usize = m
        .deformations
        .iter()
        .map(|d| (0..d.scenarios.len()).filter(|&i| keep(i)).count())
        .sum();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let cache = dir.join("cache");
    let mut prepared: BTreeMap<String, Prepared> = BTreeMap::new();
    let mut out = Vec::new();
    let mut left_out = 0;
    for d in &m.deformations {
        if !prepared.contains_key(&d.geometry) {
            let geo = load_geometry(dir, &m, &d.geometry)?;
            let case = Prepared::new(geo.model.clone(), Some(&params.libr), Some(&cache))?
                .with_models(models.to_vec())?;
            prepared.insert(d.geometry.clone(), case);
        }
        let case = &prepared[&d.geometry];
        let scenarios = load_scenarios(dir, d)?;
        let picked: Vec<_> = scenarios
            .iter()
            .enumerate()
            .filter(|(i, _)| keep(*i))
            .map(|(_, s)| s)
            .collect();
        let results: Vec<Option<AbstainSignals>> = picked
            .par_iter()
            .map(|sc| {
                let r = register(case, &sc.measurements, Method::LibrPlus, &params);
                let k = done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
                progress(k, total);
                let s = r.ok()?.correction?.signals?;
                Some(AbstainSignals {
                    spread_ratio: s.spread_ratio,
                    libr_rms_mm: s.libr_rms_mm,
                })
            })
            .collect();
        for r in results {
            match r {
                Some(s) => out.push(s),
                None => left_out += 1,
            }
        }
    }
    Ok((out, left_out))
}
