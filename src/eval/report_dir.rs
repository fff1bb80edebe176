//! The report directory of `librplus evaluate`: methods evaluated over dataset splits (or over a
//! learned model's held-out scenarios), with `summary.json`, `results.json`, `report.md`, plots
//! per split and error maps per split, geometry and method.

use super::report::{self, DiscoverEval, Evaluation, LibrPlusEval, MethodSummary, Split};
use super::runs::{RunProgress, create_dir, read_physics, write_file, write_json};
use super::train::{TrainSplit, Validation, split_scenarios};
use super::{EvalError, open, plot};
use crate::dataset::Manifest;
use crate::discover::DiscoverParams;
use crate::gcn::io::TrainedModel;
use crate::mesh::io::WriteOptions;
use crate::pipeline::{Method, PipelineParams};
use crate::register::physics::Physics;
use crate::v2s::io::V2sModel;
use serde_json::{Map, Value, json};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// What `librplus evaluate` evaluates and where it writes the report.
#[derive(Debug, Clone)]
pub struct EvaluateOptions {
    /// Dataset directory.
    pub data: PathBuf,
    /// Report directory to write.
    pub out: PathBuf,
    /// Comma-separated methods: initial, rigid, libr, adaptive, v2s, librplus.
    pub methods: String,
    /// A trained SR-GCN model or ensemble directory for LIBR+ (None: the built-in model).
    pub model: Option<PathBuf>,
    /// A V2S model directory for method v2s (None: the built-in V2S model).
    pub v2s_model: Option<PathBuf>,
    /// Comma-separated splits: all, train, test (a model trained on this dataset replaces them
    /// with its held-out scenarios).
    pub splits: String,
    /// Every k-th block of five scenarios of each deformation is evaluated.
    pub every: usize,
    /// The registration's parameters.
    pub params: PipelineParams,
    /// An augmented model (`physics.json`) LIBR and LIBR+ register with.
    pub physics: Option<PathBuf>,
    /// Each deformation gets its own physics, discovered on its held-in scenarios.
    pub discover: bool,
}

/// What the report directory holds, for the caller to show.
#[derive(Debug, Clone)]
pub struct ReportDir {
    /// `summary.json`.
    pub summary: Value,
    /// `report.md`.
    pub markdown: String,
}

/// The scenarios (deformation id, index) learned models held out, under their splits' names.
type HeldOut = (String, BTreeSet<(String, usize)>);

/// The learned models evaluated: SR-GCN members for LIBR+, the V2S network.
struct Learned {
    models: Option<Vec<Arc<TrainedModel>>>,
    v2s: Option<Arc<V2sModel>>,
}

/// What the report gathers split by split, under each split's name.
#[derive(Default)]
struct Gathered {
    summaries: BTreeMap<String, BTreeMap<String, MethodSummary>>,
    discovered: Map<String, Value>,
    results: Map<String, Value>,
    plots: Map<String, Value>,
    error_maps: Map<String, Value>,
}

/// Evaluates the methods `o` names over its splits and writes the report directory.
pub fn evaluate_into(
    o: &EvaluateOptions,
    progress: &dyn RunProgress,
) -> Result<ReportDir, EvalError> {
    let m = open(&o.data)?;
    let (mut methods, want_plus) = parse_methods(&o.methods)?;
    let learned = Learned {
        models: load_models(o.model.as_deref(), want_plus)?,
        v2s: load_v2s(o.v2s_model.as_deref(), methods.contains(&Method::V2s))?,
    };
    if learned.models.is_some() && !methods.contains(&Method::Libr) {
        // LIBR+ corrects LIBR's result: LIBR runs (and is reported) with it.
        methods.push(Method::Libr);
    }
    let held_out = held_out(&m, &learned)?;
    let splits = match &held_out {
        Some(_) => vec![Split::All],
        None => o
            .splits
            .split(',')
            .map(|s| Split::parse(s.trim()).map_err(|e| param(format!("--split: {e}"))))
            .collect::<Result<Vec<_>, _>>()?,
    };
    create_dir(&o.out)?;
    let physics = read_physics(o.physics.as_deref())?;
    o.params
        .libr
        .validate()
        .map_err(|e| param(format!("LIBR options: {e}")))?;
    if let Some(members) = &learned.models {
        let refs: Vec<&TrainedModel> = members.iter().map(|m| &**m).collect();
        if let Some(why) = crate::gcn::infer::physics_mismatch(&refs, &physics) {
            progress.log(&format!(
                "warning: LIBR+ is LIBR's answer throughout: {why}"
            ));
        }
    }
    let discover = o.discover.then(DiscoverParams::default);
    if o.discover && !methods.contains(&Method::Libr) {
        return Err(param(
            "--discover scores LIBR with each cohort's physics: --methods must include libr",
        ));
    }
    if o.discover && o.physics.is_some() {
        return Err(param(
            "--discover finds each cohort's physics: leave out --physics",
        ));
    }
    let plan = Plan {
        o,
        m: &m,
        methods: &methods,
        learned: &learned,
        held_out: held_out.as_ref(),
        physics: &physics,
        discover: discover.as_ref(),
    };
    let mut gathered = Gathered::default();
    for split in splits {
        plan.evaluate_split(split, &mut gathered, progress)?;
    }
    write_reports(o, gathered)
}

/// An option error with its message.
fn param(message: impl Into<String>) -> EvalError {
    EvalError::Parameter(message.into())
}

/// The pipeline methods of `--methods`, and whether LIBR+ (`librplus`) is asked for.
fn parse_methods(names: &str) -> Result<(Vec<Method>, bool), EvalError> {
    let mut want_plus = false;
    let mut methods = Vec::new();
    for x in names.split(',') {
        match x.trim() {
            "initial" => methods.push(Method::Initial),
            "rigid" => methods.push(Method::Rigid),
            "libr" => methods.push(Method::Libr),
            "librplus" => want_plus = true,
            "v2s" => methods.push(Method::V2s),
            "adaptive" => methods.push(Method::Adaptive),
            "auto" => methods.push(Method::Auto),
            "nonlinear" => methods.push(Method::Nonlinear),
            other => {
                return Err(param(format!(
                    "--methods: unknown method {other:?} (initial, rigid, libr, adaptive, nonlinear, auto, v2s, librplus)"
                )));
            }
        }
    }
    Ok((methods, want_plus))
}

/// The SR-GCN models of `dir` (one, or an ensemble's members), or the built-in model when LIBR+
/// is asked for without one.
fn load_models(
    dir: Option<&Path>,
    want_plus: bool,
) -> Result<Option<Vec<Arc<TrainedModel>>>, EvalError> {
    let models = match (dir, want_plus) {
        (Some(dir), _) => crate::gcn::io::load_models_on_device(dir)
            .map_err(|e| param(format!("--model: {e}")))?,
        (None, true) => {
            crate::gcn::io::builtin_models().map_err(|e| param(format!("built-in model: {e}")))?
        }
        (None, false) => return Ok(None),
    };
    Ok(Some(models.into_iter().map(Arc::new).collect()))
}

/// The V2S network of `dir`, or the built-in one, when method v2s is `wanted`.
fn load_v2s(dir: Option<&Path>, wanted: bool) -> Result<Option<Arc<V2sModel>>, EvalError> {
    let model = match (dir, wanted) {
        (Some(dir), true) => crate::v2s::io::load_model_on_device(dir)
            .map_err(|e| param(format!("--v2s-model: {e}")))?,
        (None, true) => crate::v2s::io::builtin_model()
            .map_err(|e| param(format!("built-in V2S model: {e}")))?,
        (Some(_), false) => return Err(param("--v2s-model is used with --methods v2s")),
        (None, false) => return Ok(None),
    };
    Ok(Some(Arc::new(model)))
}

/// With learned models trained on this dataset: the scenarios every one of them held out, under
/// their splits' names. A model trained on another dataset (its provenance's parameters hash
/// differs) saw none of this one and restricts nothing.
fn held_out(m: &Manifest, learned: &Learned) -> Result<Option<HeldOut>, EvalError> {
    let trained_here = |p: &&Value| {
        p["data_parameters_hash"]
            .as_str()
            .is_none_or(|h| h == m.parameters_hash)
    };
    // The provenance of every learned model evaluated: SR-GCN members, then V2S.
    let provenances: Vec<&Value> = learned
        .models
        .iter()
        .flatten()
        .map(|mm| &mm.provenance)
        .chain(learned.v2s.iter().map(|v| &v.provenance))
        .filter(trained_here)
        .collect();
    if provenances.is_empty() {
        return Ok(None);
    }
    let mut names = Vec::new();
    let mut common: Option<BTreeSet<(String, usize)>> = None;
    for p in provenances {
        let split = p["split"].as_str().unwrap_or("");
        let sp = TrainSplit::parse(split).map_err(|e| param(format!("--model provenance: {e}")))?;
        let seed = p["seed"].as_u64().unwrap_or(1);
        let every = p["every"].as_u64().unwrap_or(1) as usize;
        // The test set does not depend on how the model was validated.
        let sets = split_scenarios(m, &sp, seed, every, Validation::Deformations)
            .map_err(|e| param(format!("--model split on this dataset: {e}")))?;
        let test: BTreeSet<_> = sets.test.into_iter().collect();
        common = Some(match common {
            None => test,
            Some(c) => c.intersection(&test).cloned().collect(),
        });
        if !names.contains(&sp.name()) {
            names.push(sp.name());
        }
    }
    Ok(Some((names.join("+"), common.unwrap_or_default())))
}

/// What every split's evaluation reads.
struct Plan<'a> {
    o: &'a EvaluateOptions,
    m: &'a Manifest,
    methods: &'a [Method],
    learned: &'a Learned,
    held_out: Option<&'a HeldOut>,
    physics: &'a Physics,
    discover: Option<&'a DiscoverParams>,
}

impl Plan<'_> {
    /// Evaluates one split, writes its plots and error maps, and gathers its results.
    fn evaluate_split(
        &self,
        split: Split,
        gathered: &mut Gathered,
        progress: &dyn RunProgress,
    ) -> Result<(), EvalError> {
        let o = self.o;
        let name = match self.held_out {
            Some((n, _)) => n.clone(),
            None => split.name().to_string(),
        };
        let learned = self.learned;
        let plus = (learned.models.is_some() || learned.v2s.is_some()).then(|| LibrPlusEval {
            models: learned.models.as_deref().unwrap_or(&[]),
            v2s: learned.v2s.as_ref(),
            only: self.held_out.map(|t| &t.1),
        });
        let disc = self.discover.map(|p| DiscoverEval { params: p });
        progress.start(&format!("split {name}"), 0);
        let ev = report::evaluate(
            &o.data,
            self.m,
            split,
            self.methods,
            o.every,
            &o.params,
            self.physics,
            plus,
            disc,
            &|done, total| progress.step(done, total, None),
        );
        progress.finish();
        let ev = ev?;
        let plots = write_plots(&o.out, &name, &ev)?;
        let maps = write_error_maps(&o.out, &name, &ev)?;
        gathered.plots.insert(name.clone(), json!(plots));
        gathered.error_maps.insert(name.clone(), Value::Array(maps));
        gathered
            .summaries
            .insert(name.clone(), report::summarize(&ev.results));
        if o.discover {
            gathered
                .discovered
                .insert(name.clone(), to_value(&ev.discovered)?);
        }
        gathered.results.insert(name, to_value(&ev.results)?);
        Ok(())
    }
}

/// `value` as JSON.
fn to_value(value: &impl serde::Serialize) -> Result<Value, EvalError> {
    serde_json::to_value(value).map_err(|e| EvalError::Internal(e.to_string()))
}

/// The split's plots (TRE by category, TRE distribution); returns their file names.
fn write_plots(out: &Path, name: &str, ev: &Evaluation) -> Result<Vec<String>, EvalError> {
    let mut files = Vec::new();
    for (file, png) in [
        (
            format!("tre_by_category_{name}.png"),
            plot::tre_by_category_png(name, &ev.results),
        ),
        (
            format!("tre_cdf_{name}.png"),
            plot::tre_cdf_png(name, &ev.results),
        ),
    ] {
        let png = png.map_err(|e| EvalError::within(format!("plot {file}"), e))?;
        write_file(&out.join(&file), &png)?;
        files.push(file);
    }
    Ok(files)
}

/// The split's error maps, one mesh file per geometry and method with scenarios; returns what
/// `summary.json` records of each.
fn write_error_maps(out: &Path, name: &str, ev: &Evaluation) -> Result<Vec<Value>, EvalError> {
    create_dir(&out.join("error_maps").join(name))?;
    let mut maps = Vec::new();
    for map in ev.error_maps.iter().filter(|m| m.scenarios > 0) {
        let mesh = &ev.meshes[&map.geometry];
        let file = format!("error_maps/{name}/{}_{}.vtu", map.geometry, map.method);
        let f = map.to_file(mesh)?;
        crate::mesh::io::write(out.join(&file), &f, WriteOptions::default())?;
        let mean = map.mean_mm();
        maps.push(json!({
            "file": file,
            "geometry": map.geometry,
            "method": map.method,
            "scenarios": map.scenarios,
            "nodes": mean.len(),
            "tre_mm": mean.iter().sum::<f64>() / mean.len().max(1) as f64,
        }));
    }
    Ok(maps)
}

/// Writes `summary.json`, `results.json` and `report.md`.
fn write_reports(o: &EvaluateOptions, g: Gathered) -> Result<ReportDir, EvalError> {
    let splits: Map<String, Value> = g
        .summaries
        .iter()
        .map(|(k, v)| (k.clone(), json!({"methods": v})))
        .collect();
    let mut summary = json!({
        "format": 1,
        "data": o.data.display().to_string(),
        "every": o.every,
        "splits": splits,
        "plots": g.plots,
        "error_maps": g.error_maps,
    });
    if o.discover {
        summary["discovered"] = Value::Object(g.discovered);
    }
    write_json(&o.out.join("summary.json"), &summary, "\n")?;
    write_json(&o.out.join("results.json"), &Value::Object(g.results), "\n")?;
    let markdown = report::markdown(&g.summaries);
    write_file(&o.out.join("report.md"), markdown.as_bytes())?;
    Ok(ReportDir { summary, markdown })
}
