//! [`evaluate`]: every method on the scenarios of a split, LIBR+ on every LIBR result, and
//! discovery on held-in scenarios, scored against the truth and accumulated in error maps.

use super::{
    CATEGORY_ORDER, CohortPhysics, DISCOVERED_METHOD, DiscoverEval, ErrorMap, Evaluation,
    LibrPlusEval, ScenarioResult, Split,
};
use crate::dataset::{DeformationEntry, Manifest};
use crate::eval::{
    EvalError, GeometryData, ScenarioData, load_geometry, load_scenarios, node_errors_mm,
    tre_from_errors,
};
use crate::gcn::infer::LibrPlusCase;
use crate::pipeline::{Method, PipelineParams, Prepared, register};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Scenarios registered in parallel at a time; their node errors are then added to the error
/// maps in scenario order, so the sums do not depend on thread scheduling.
const CHUNK: usize = 32;

/// Runs `methods` on the scenarios of the split's deformations: every `every`-th block of five
/// consecutive scenarios (one per category). Besides per-scenario results it accumulates each
/// geometry's and method's per-node errors ([`ErrorMap`]). With `librplus`, every LIBR result is
/// also corrected by the SR-GCN model and reported as method `librplus` (its time includes LIBR's).
#[allow(clippy::too_many_arguments)]
pub fn evaluate(
    dir: &Path,
    m: &Manifest,
    split: Split,
    methods: &[Method],
    every: usize,
    params: &PipelineParams,
    physics: &crate::register::physics::Physics,
    librplus: Option<LibrPlusEval<'_>>,
    discover: Option<DiscoverEval<'_>>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Evaluation, EvalError> {
    let v2s = librplus.and_then(|l| l.v2s);
    if methods.contains(&Method::V2s) && v2s.is_none() {
        return Err(EvalError::Parameter(
            "method v2s needs a V2S model (--v2s-model, or the built-in one)".into(),
        ));
    }
    let test_geos = m.test_geometries();
    let defs: Vec<&DeformationEntry> = m
        .deformations
        .iter()
        .filter(|d| match split {
            Split::All => true,
            Split::Test => test_geos.contains(&d.geometry.as_str()),
            Split::Train => !test_geos.contains(&d.geometry.as_str()),
        })
        .collect();
    let mut run = Run {
        dir,
        m,
        methods,
        every: every.max(1),
        params,
        physics,
        // LIBR+ runs when SR-GCN models are given.
        librplus: librplus.filter(|l| !l.models.is_empty()),
        v2s,
        only: librplus.and_then(|l| l.only),
        discover,
        cache: dir.join("cache"),
        progress,
        done: AtomicUsize::new(0),
        total: 0,
    };
    run.total = defs
        .iter()
        .map(|d| {
            (0..d.scenarios.len())
                .filter(|&i| run.keep(&d.id, i))
                .count()
                * methods.len()
        })
        .sum();
    let mut acc = Accumulated::default();
    let mut prepared: BTreeMap<String, Geometry> = BTreeMap::new();
    for d in defs {
        if !prepared.contains_key(&d.geometry) {
            let g = run.prepare(d, &mut acc.maps)?;
            prepared.insert(d.geometry.clone(), g);
        }
        run.deformation(d, &prepared[&d.geometry], &mut acc)?;
    }
    Ok(Evaluation {
        discovered: acc.discovered,
        results: acc.out,
        error_maps: acc.maps,
        meshes: prepared
            .into_iter()
            .map(|(id, g)| (id, g.geo.model.mesh))
            .collect(),
    })
}

/// A result row and its node errors (None when the registration failed).
type Row = (ScenarioResult, Option<Vec<f64>>);

/// One scenario's result and node errors for a method, and LIBR+'s when it ran on this result.
type Outcome = (
    ScenarioResult,
    Option<Vec<f64>>,
    Option<ScenarioResult>,
    Option<Vec<f64>>,
);

/// A geometry prepared for the evaluation: the case (with what the methods need), its data,
/// and LIBR+'s networks on its mesh when LIBR+ runs.
struct Geometry {
    case: Prepared,
    geo: GeometryData,
    frame: Option<LibrPlusCase>,
}

/// What the evaluation gathers: result rows, error maps, and what discovery named per cohort.
#[derive(Default)]
struct Accumulated {
    out: Vec<ScenarioResult>,
    maps: Vec<ErrorMap>,
    discovered: Vec<CohortPhysics>,
}

impl Accumulated {
    /// Adds rows, and their node errors to the error map of (geometry, method).
    fn add(
        &mut self,
        geometry: &str,
        method: &str,
        rows: Vec<(ScenarioResult, Option<Vec<f64>>)>,
    ) -> Result<(), EvalError> {
        let map = self
            .maps
            .iter_mut()
            .find(|e| e.geometry == geometry && e.method == method)
            .ok_or_else(|| EvalError::Internal(format!("no {method} error map for {geometry}")))?;
        for (res, err) in rows {
            if let Some(err) = err {
                map.add(&err)?;
            }
            self.out.push(res);
        }
        Ok(())
    }
}

/// An evaluation under way: what it runs, on which scenarios, and its progress.
struct Run<'a> {
    dir: &'a Path,
    m: &'a Manifest,
    methods: &'a [Method],
    every: usize,
    params: &'a PipelineParams,
    physics: &'a crate::register::physics::Physics,
    librplus: Option<LibrPlusEval<'a>>,
    /// The V2S network of method v2s (given with or without SR-GCN models).
    v2s: Option<&'a std::sync::Arc<crate::v2s::io::V2sModel>>,
    only: Option<&'a std::collections::BTreeSet<(String, usize)>>,
    discover: Option<DiscoverEval<'a>>,
    cache: PathBuf,
    progress: &'a (dyn Fn(usize, usize) + Sync),
    done: AtomicUsize,
    total: usize,
}

impl Run<'_> {
    /// Whether scenario `i` of deformation `d` is evaluated: every `every`-th block of
    /// consecutive scenarios (categories cycle through the five in order, so a subsample keeps
    /// every category), and only those asked for.
    fn keep(&self, d: &str, i: usize) -> bool {
        (i / CATEGORY_ORDER.len()) % self.every == 0
            && self
                .only
                .is_none_or(|only| only.contains(&(d.to_string(), i)))
    }

    /// With discovery, the kept blocks alternate: held in (discovery reads them), held out
    /// (every method is scored on them).
    fn held_out(&self, i: usize) -> bool {
        self.discover.is_none() || (i / CATEGORY_ORDER.len() / self.every) % 2 == 1
    }

    /// Prepares a deformation's geometry (its LIBR basis and what the methods need), and adds
    /// its error maps.
    fn prepare(
        &self,
        d: &DeformationEntry,
        maps: &mut Vec<ErrorMap>,
    ) -> Result<Geometry, EvalError> {
        let (methods, params) = (self.methods, self.params);
        let geo = load_geometry(self.dir, self.m, &d.geometry)?;
        let auto = methods.contains(&Method::Auto);
        let libr = (auto || methods.contains(&Method::Libr)).then_some(&params.libr);
        // The built-in error model, as the service attaches it: each registration's estimate
        // and its quality flag read as the service would answer them.
        let mut case =
            Prepared::with_physics(geo.model.clone(), libr, self.physics, Some(&self.cache))?
                .with_error_model(crate::register::uncertainty::builtin());
        if auto || methods.contains(&Method::Adaptive) || methods.contains(&Method::Nonlinear) {
            case = case.with_adaptive(&params.libr, &params.adaptive, Some(&self.cache))?;
        }
        if let Some(v) = self.v2s.filter(|_| methods.contains(&Method::V2s)) {
            case = case.with_v2s(v.clone())?;
        }
        let nodes = geo.model.mesh.num_nodes();
        for &method in methods {
            maps.push(ErrorMap::new(&d.geometry, method.name(), nodes));
        }
        if self.discover.is_some() {
            maps.push(ErrorMap::new(&d.geometry, DISCOVERED_METHOD, nodes));
        }
        let mut frame = None;
        if let Some(l) = self.librplus {
            maps.push(ErrorMap::new(&d.geometry, "librplus", nodes));
            frame = Some(LibrPlusCase::new(l.models.to_vec(), &geo.model.mesh)?);
        }
        Ok(Geometry { case, geo, frame })
    }

    /// Every method (and LIBR+ on LIBR's results) on a deformation's held-out scenarios, then
    /// discovery on its held-in ones and LIBR with what it named on the held-out ones.
    fn deformation(
        &self,
        d: &DeformationEntry,
        g: &Geometry,
        acc: &mut Accumulated,
    ) -> Result<(), EvalError> {
        let scenarios = load_scenarios(self.dir, d)?;
        let picked: Vec<&ScenarioData> = scenarios
            .iter()
            .enumerate()
            .filter(|(i, _)| self.keep(&d.id, *i) && self.held_out(*i))
            .map(|(_, s)| s)
            .collect();
        let mut plus: Vec<(ScenarioResult, Option<Vec<f64>>)> = Vec::new();
        for &method in self.methods {
            for chunk in picked.chunks(CHUNK) {
                let results: Vec<Outcome> = chunk
                    .par_iter()
                    .map(|sc| self.outcome(d, g, sc, method))
                    .collect();
                let mut rows = Vec::with_capacity(results.len());
                for (res, err, pr, pe) in results {
                    rows.push((res, err));
                    if let Some(pr) = pr {
                        plus.push((pr, pe));
                    }
                }
                acc.add(&d.geometry, method.name(), rows)?;
            }
        }
        if !plus.is_empty() {
            acc.add(&d.geometry, "librplus", plus)?;
        }
        if let Some(de) = self.discover {
            let held_in: Vec<&ScenarioData> = scenarios
                .iter()
                .enumerate()
                .filter(|(i, _)| self.keep(&d.id, *i) && !self.held_out(*i))
                .map(|(_, s)| s)
                .collect();
            let rows = self.discovered(d, g, &held_in, &picked, de, &mut acc.discovered)?;
            acc.add(&d.geometry, DISCOVERED_METHOD, rows)?;
        }
        Ok(())
    }

    /// One scenario registered by `method`, scored; for LIBR with LIBR+ on, its correction too.
    fn outcome(
        &self,
        d: &DeformationEntry,
        g: &Geometry,
        sc: &ScenarioData,
        method: Method,
    ) -> Outcome {
        let r = register(&g.case, &sc.measurements, method, self.params);
        let k = self.done.fetch_add(1, Ordering::SeqCst) + 1;
        (self.progress)(k, self.total);
        let (pr, pe) = match (&r, &g.frame, method) {
            (Ok(r), Some(frame), Method::Libr) => {
                let (row, err) = self.librplus_row(d, g, frame, sc, r);
                (Some(row), err)
            }
            _ => (None, None),
        };
        let (a, b) = scored(
            &g.geo,
            sc,
            (&d.geometry, d.family()),
            method.name(),
            r,
            self.params,
        );
        (a, b, pr, pe)
    }

    /// LIBR+'s row for a scenario: the model's correction of its LIBR result, scored.
    fn librplus_row(
        &self,
        d: &DeformationEntry,
        g: &Geometry,
        frame: &LibrPlusCase,
        sc: &ScenarioData,
        r: &crate::pipeline::Registration,
    ) -> (ScenarioResult, Option<Vec<f64>>) {
        let t = std::time::Instant::now();
        let corrected = correct_one(frame, &g.case, self.params, sc, r);
        let base = ScenarioResult {
            scenario: sc.id.clone(),
            geometry: d.geometry.clone(),
            family: d.family().to_string(),
            category: sc.category.clone(),
            method: "librplus".into(),
            tre: None,
            error: None,
            seconds: r.seconds + t.elapsed().as_secs_f64(),
            outside: None,
            abstained: false,
            auto: None,
            quality: None,
            quality_reason: None,
            surface: None,
            nonlinear: None,
        };
        match corrected {
            Ok((u, transform, outside, abstained)) => {
                let err = node_errors_mm(
                    g.geo.model.mesh.nodes(),
                    (&transform, &u),
                    (&sc.truth.image_to_physical, &sc.truth.displacement),
                );
                let t = tre_from_errors(&err, &g.geo.surface, &g.geo.targets);
                // The flag of the LIBR answer it corrected (an abstention answers it).
                let judged = r.quality(self.params);
                let row = ScenarioResult {
                    tre: Some(t),
                    outside,
                    abstained,
                    quality: Some(judged.quality),
                    quality_reason: Some(judged.reason),
                    ..base
                };
                (row, Some(err))
            }
            Err(e) => {
                let row = ScenarioResult {
                    error: Some(e.to_string()),
                    ..base
                };
                (row, None)
            }
        }
    }

    /// Discovery on the held-in scenarios (its record added to `discovered`), then LIBR with
    /// the physics it named on the held-out ones, scored.
    fn discovered(
        &self,
        d: &DeformationEntry,
        g: &Geometry,
        held_in: &[&ScenarioData],
        picked: &[&ScenarioData],
        de: DiscoverEval<'_>,
        discovered: &mut Vec<CohortPhysics>,
    ) -> Result<Vec<Row>, EvalError> {
        let (found, record) = discover_physics(&g.geo, held_in, de, &self.cache, &d.id);
        discovered.push(record);
        let own;
        let case_d = if found.is_empty() {
            &g.case
        } else {
            own = Prepared::with_physics(
                g.geo.model.clone(),
                Some(&self.params.libr),
                &found,
                Some(&self.cache),
            )?;
            &own
        };
        Ok(picked
            .par_iter()
            .map(|sc| {
                let r = register(case_d, &sc.measurements, Method::Libr, self.params);
                scored(
                    &g.geo,
                    sc,
                    (&d.geometry, d.family()),
                    DISCOVERED_METHOD,
                    r,
                    self.params,
                )
            })
            .collect())
    }
}

/// Auto's choice in one registration, each candidate's answer scored against the truth.
fn auto_outcome(
    geo: &GeometryData,
    sc: &ScenarioData,
    a: &crate::pipeline::auto::AutoInfo,
) -> super::AutoOutcome {
    let tre = |c: crate::pipeline::auto::Candidate| {
        let (_, t, u) = a.answers.iter().find(|(k, _, _)| *k == c)?;
        let err = node_errors_mm(
            geo.model.mesh.nodes(),
            (t, u),
            (&sc.truth.image_to_physical, &sc.truth.displacement),
        );
        Some(err.iter().sum::<f64>() / err.len().max(1) as f64)
    };
    let candidates: Vec<super::AutoCandidateRow> = a
        .candidates
        .iter()
        .map(|c| super::AutoCandidateRow {
            candidate: c.candidate.name().to_string(),
            held_out_mm2: c.held_out_mm2,
            folds_mm2: c.folds_mm2.clone(),
            in_sample_mm2: c.in_sample_mm2,
            predicted_tre_mm: c.predicted_tre_mm,
            tre_mm: tre(c.candidate),
            apart_mm: c.apart_mm,
        })
        .collect();
    let oracle = candidates
        .iter()
        .filter_map(|c| c.tre_mm.map(|t| (c.candidate.clone(), t)))
        .min_by(|x, y| x.1.total_cmp(&y.1))
        .map(|(c, _)| c);
    super::AutoOutcome {
        chosen: a.chosen.name().to_string(),
        best_scoring: a.best_scoring.name().to_string(),
        runner_up: a.runner_up.map(|c| c.name().to_string()),
        margin_se: a.margin_se,
        ambiguous: a.ambiguous.clone(),
        hold_hypothesis: a.hold_hypothesis,
        oracle,
        candidates,
    }
}

/// A registration's result row and node errors against the scenario's truth.
fn scored(
    geo: &GeometryData,
    sc: &ScenarioData,
    (geometry, family): (&str, &str),
    method: &str,
    r: Result<crate::pipeline::Registration, crate::pipeline::PipelineError>,
    params: &crate::pipeline::PipelineParams,
) -> (ScenarioResult, Option<Vec<f64>>) {
    let base = ScenarioResult {
        scenario: sc.id.clone(),
        geometry: geometry.to_string(),
        family: family.to_string(),
        category: sc.category.clone(),
        method: method.into(),
        tre: None,
        error: None,
        seconds: 0.0,
        outside: None,
        abstained: false,
        auto: None,
        quality: None,
        quality_reason: None,
        surface: None,
        nonlinear: None,
    };
    match r {
        Ok(r) => {
            let err = node_errors_mm(
                geo.model.mesh.nodes(),
                (&r.image_to_physical, &r.u),
                (&sc.truth.image_to_physical, &sc.truth.displacement),
            );
            let t = tre_from_errors(&err, &geo.surface, &geo.targets);
            let auto = r.auto.as_ref().map(|a| auto_outcome(geo, sc, a));
            let judged = r.quality(params);
            (
                ScenarioResult {
                    tre: Some(t),
                    seconds: r.seconds,
                    auto,
                    quality: Some(judged.quality),
                    quality_reason: Some(judged.reason),
                    surface: r.surface.clone(),
                    nonlinear: r.nonlinear.clone(),
                    ..base
                },
                Some(err),
            )
        }
        Err(e) => (
            ScenarioResult {
                error: Some(e.to_string()),
                ..base
            },
            None,
        ),
    }
}

/// Discovery on a cohort's held-in scenarios: the augmented model (empty when nothing was named
/// or discovery failed) and what to report.
fn discover_physics(
    geo: &GeometryData,
    held_in: &[&ScenarioData],
    de: DiscoverEval<'_>,
    cache: &Path,
    deformation: &str,
) -> (crate::register::physics::Physics, CohortPhysics) {
    let sweeps: Vec<crate::discover::Sweep> = held_in
        .iter()
        .map(|s| crate::discover::Sweep {
            id: s.id.clone(),
            measurements: s.measurements.clone(),
        })
        .collect();
    let mut record = CohortPhysics {
        deformation: deformation.to_string(),
        held_in: held_in.len(),
        verdict: "error".into(),
        effects: Vec::new(),
        error: None,
    };
    match crate::discover::discover_cohort(
        &geo.model,
        &sweeps,
        de.params,
        Some(cache),
        &|_, _, _| {},
    ) {
        Ok(f) => {
            record.verdict = serde_json::to_value(f.verdict)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default();
            record.effects = f.physics.effects.iter().map(|e| e.describe()).collect();
            (f.physics, record)
        }
        Err(e) => {
            record.error = Some(e.to_string());
            (crate::register::physics::Physics::none(), record)
        }
    }
}

/// LIBR+ node displacements, image → physical transform and outside signals for one scenario
/// from its LIBR registration, as the pipeline's LIBR+ stage ([`crate::pipeline::correct_libr`]).
fn correct_one(
    lp: &LibrPlusCase,
    case: &Prepared,
    params: &PipelineParams,
    sc: &ScenarioData,
    r: &crate::pipeline::Registration,
) -> Result<
    (
        Vec<f64>,
        crate::mesh::rigid::Rigid,
        Option<crate::pipeline::OutsideSignals>,
        bool,
    ),
    EvalError,
> {
    let libr = r
        .libr
        .as_ref()
        .ok_or_else(|| EvalError::Internal("a LIBR registration without its LIBR stage".into()))?;
    let params = PipelineParams {
        deadline: None,
        ..params.clone()
    };
    let answer = crate::pipeline::LibrAnswer {
        u: &r.u,
        image_to_physical: &r.image_to_physical,
        info: libr,
        rigid_prior: r.rigid.prior.as_ref(),
    };
    let out = crate::pipeline::correct_libr(lp, case, &sc.measurements, &params, answer);
    // A network that failed is an error of the evaluation, not LIBR's answer.
    if let Some(e) = &out.info.skipped
        && e.starts_with("SR-GCN correction failed")
    {
        return Err(EvalError::Internal(e.clone()));
    }
    Ok((
        out.u,
        out.image_to_physical,
        out.info.signals,
        out.info.abstained,
    ))
}
