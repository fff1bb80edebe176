//! Evaluation over a dataset: runs registration methods on the scenarios of a split and aggregates
//! TRE per method and per measurement category into the stable `summary.json` contract and a
//! Markdown report, and per-node error statistics per geometry and method ([`ErrorMap`], written
//! as `.vtu` error maps).
//!
//! `summary.json` (format 1):
//! `{"format": 1, "splits": {SPLIT: {"methods": {METHOD: {"tre_mm", "tre_surface_mm",
//! "tre_interior_mm", "tre_targets_mm", "scenarios", "failed", "seconds_median",
//! "by_category": {CATEGORY: {"tre_mm", "scenarios"}}, "by_geometry": {GEOMETRY: {"tre_mm",
//! "scenarios"}}}}}}}` — means in mm over scenarios. Keys are only ever added to format 1.

mod run;
pub use run::evaluate;

use super::{Tre, error_map_file};
use crate::eval::EvalError;
use crate::gcn::io::TrainedModel;
use crate::mesh::TetMesh;
use crate::mesh::io::{DataArray, MeshFile};
use crate::v2s::io::V2sModel;
use std::collections::BTreeMap;

/// Which scenarios a split evaluates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    /// Every deformation.
    All,
    /// Deformations of geometries marked `test` (the held-out geometry, pattern V).
    Test,
    /// Deformations of training geometries.
    Train,
}

impl Split {
    /// Parses `all`, `test`, `train`.
    pub fn parse(s: &str) -> Result<Self, EvalError> {
        match s {
            "all" => Ok(Split::All),
            "test" => Ok(Split::Test),
            "train" => Ok(Split::Train),
            other => Err(EvalError::Parameter(format!(
                "unknown split {other:?}: expected all, test or train"
            ))),
        }
    }

    /// Name.
    pub fn name(self) -> &'static str {
        match self {
            Split::All => "all",
            Split::Test => "test",
            Split::Train => "train",
        }
    }
}

/// One scenario's result for one method.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ScenarioResult {
    /// `deformation/index`.
    pub scenario: String,
    /// Geometry id of the deformation.
    pub geometry: String,
    /// The deformation's truth family ([`crate::dataset::DeformationEntry::family`]).
    pub family: String,
    /// Category.
    pub category: String,
    /// Method.
    pub method: String,
    /// TRE (None when the registration failed).
    pub tre: Option<Tre>,
    /// Why it failed.
    pub error: Option<String>,
    /// Registration time (s).
    pub seconds: f64,
    /// LIBR+ only: what the registration showed of being outside what the network learned.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outside: Option<crate::pipeline::OutsideSignals>,
    /// LIBR+ only: it abstained (the answer is LIBR's; [`crate::gcn::abstain`]).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub abstained: bool,
    /// Auto only: what it chose, and every candidate's score and true error.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub auto: Option<AutoOutcome>,
    /// The quality flag the service would answer ([`crate::pipeline::quality`]; None when the
    /// registration failed, or for rows read back from other runs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quality: Option<crate::pipeline::quality::Quality>,
    /// Why the flag is not OK (empty when it is).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub quality_reason: Option<String>,
    /// The side test: which side of the organ the surface patch was matched to
    /// ([`crate::pipeline::side`]; None when it did not run).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub surface: Option<crate::pipeline::side::SideInfo>,
    /// The nonlinear refinement, for `nonlinear` (None otherwise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nonlinear: Option<crate::register::libr::NonlinearInfo>,
}

/// What [`crate::pipeline::Method::Auto`] chose in one registration, with each candidate's
/// true error (the oracle: the candidate the truth prefers).
#[derive(Debug, Clone, serde::Serialize)]
pub struct AutoOutcome {
    /// The candidate chosen.
    pub chosen: String,
    /// The best-scoring candidate, when more flexible than the chosen one.
    pub best_scoring: String,
    /// The runner-up.
    pub runner_up: Option<String>,
    /// The runner-up's margin in standard errors.
    pub margin_se: Option<f64>,
    /// Why the data did not decide, when they did not.
    pub ambiguous: Option<String>,
    /// The held variants were tried without a trusted start (ranked after the free fits).
    pub hold_hypothesis: bool,
    /// The candidate with the lowest true mean TRE.
    pub oracle: Option<String>,
    /// Every candidate: name, held-out score (mm²), in-sample (mm²), predicted TRE (mm), true
    /// mean TRE (mm).
    pub candidates: Vec<AutoCandidateRow>,
}

/// One candidate of [`AutoOutcome`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct AutoCandidateRow {
    /// Its name.
    pub candidate: String,
    /// Mean capped squared held-out error (mm²).
    pub held_out_mm2: Option<f64>,
    /// Per fold (mm²).
    pub folds_mm2: Vec<f64>,
    /// In sample (mm²).
    pub in_sample_mm2: Option<f64>,
    /// The error estimate's predicted mean TRE (mm).
    pub predicted_tre_mm: Option<f64>,
    /// The true mean TRE over nodes (mm).
    pub tre_mm: Option<f64>,
    /// How far its answer lies from the chosen one's (RMS over the organ, mm).
    pub apart_mm: Option<f64>,
}

/// Aggregate of one method.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct MethodSummary {
    /// Mean TRE over scenarios (mm).
    pub tre_mm: f64,
    /// Mean surface-node TRE.
    pub tre_surface_mm: f64,
    /// Mean interior-node TRE.
    pub tre_interior_mm: f64,
    /// Mean target TRE.
    pub tre_targets_mm: f64,
    /// Scenarios that registered.
    pub scenarios: usize,
    /// Scenarios that failed (error).
    pub failed: usize,
    /// LIBR+: registrations where it abstained and answered LIBR's result.
    pub abstained: usize,
    /// Median registration time (s).
    pub seconds_median: f64,
    /// Per category: mean TRE and count.
    pub by_category: BTreeMap<String, CategorySummary>,
    /// Per geometry: mean TRE and count (the mean over nodes of that geometry's error map).
    pub by_geometry: BTreeMap<String, CategorySummary>,
    /// Per deformation pattern (`L`, `R`, `W`, `V`, ... from the deformation id): mean TRE and
    /// count.
    pub by_pattern: BTreeMap<String, CategorySummary>,
    /// Per truth family (`generate --families`; `neo-hookean` for data without): mean TRE and
    /// count.
    pub by_family: BTreeMap<String, CategorySummary>,
    /// Registrations per quality flag ([`crate::pipeline::quality::Quality::name`]).
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub quality: BTreeMap<String, usize>,
    /// Registrations confidently worse than doing nothing: flagged `ok`, yet more than
    /// [`FAILED_MM`] off or more than [`WORSE_MM`] worse than method `initial` on the same
    /// scenario (None when `initial` was not run).
    pub bad_flagged_ok: Option<usize>,
    /// Auto only: its choices against the truth's best candidate.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub auto: Option<AutoSummary>,
}

/// How [`crate::pipeline::Method::Auto`] chose over a split, judged by the truth.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct AutoSummary {
    /// Registrations with a truth-scored oracle.
    pub registrations: usize,
    /// Mean over them of the chosen candidate's TRE minus the oracle's (mm, ≥ 0).
    pub regret_mm: f64,
    /// `confusion[chosen][oracle]`: how often each candidate was chosen when the truth
    /// preferred each.
    pub confusion: BTreeMap<String, BTreeMap<String, usize>>,
}

impl AutoSummary {
    /// Adds one registration's choice (skipped when no candidate was scored by the truth).
    fn add(&mut self, a: &AutoOutcome) {
        let tre = |name: &str| {
            a.candidates
                .iter()
                .find(|c| c.candidate == name)
                .and_then(|c| c.tre_mm)
        };
        let Some(oracle) = &a.oracle else { return };
        let (Some(chosen), Some(best)) = (tre(&a.chosen), tre(oracle)) else {
            return;
        };
        self.registrations += 1;
        self.regret_mm += (chosen - best).max(0.0);
        *self
            .confusion
            .entry(a.chosen.clone())
            .or_default()
            .entry(oracle.clone())
            .or_default() += 1;
    }
}

/// A registration whose mean TRE exceeds this has failed (mm).
pub const FAILED_MM: f64 = 20.0;

/// A registration this much worse than doing nothing is worse than doing nothing (mm).
pub const WORSE_MM: f64 = 2.0;

/// The deformation pattern of a scenario id `GEOMETRY-PATTERN-NN/INDEX` (`g1-L-00/5` → `L`);
/// `?` when the id has another shape.
pub fn pattern_of(scenario: &str) -> String {
    let deformation = scenario.split('/').next().unwrap_or(scenario);
    let parts: Vec<&str> = deformation.split('-').collect();
    if parts.len() >= 3 {
        parts[parts.len() - 2].to_string()
    } else {
        "?".into()
    }
}

/// Aggregate of one method in one group of scenarios (a category or a geometry).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct CategorySummary {
    /// Mean TRE (mm).
    pub tre_mm: f64,
    /// Scenarios.
    pub scenarios: usize,
}

/// Per-node error statistics of one method on one geometry over the scenarios of a split that
/// registered: running sums, so memory stays at three arrays per mesh whatever the number of
/// scenarios. Node errors as [`crate::eval::node_errors_mm`] (the definition of [`super::tre`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ErrorMap {
    /// Geometry id.
    pub geometry: String,
    /// Method name.
    pub method: String,
    /// Scenarios added.
    pub scenarios: usize,
    /// Per node: sum of errors over scenarios (mm).
    pub sum_mm: Vec<f64>,
    /// Per node: sum of squared errors (mm²).
    pub sum_sq_mm2: Vec<f64>,
    /// Per node: largest error (mm).
    pub max_mm: Vec<f64>,
}

impl ErrorMap {
    /// An empty map of `nodes` nodes.
    pub fn new(geometry: &str, method: &str, nodes: usize) -> Self {
        Self {
            geometry: geometry.to_string(),
            method: method.to_string(),
            scenarios: 0,
            sum_mm: vec![0.0; nodes],
            sum_sq_mm2: vec![0.0; nodes],
            max_mm: vec![0.0; nodes],
        }
    }

    /// Adds one scenario's node errors (one per node).
    pub fn add(&mut self, err: &[f64]) -> Result<(), EvalError> {
        if err.len() != self.sum_mm.len() {
            return Err(EvalError::Internal(format!(
                "error map {}/{}: {} node errors for {} nodes",
                self.geometry,
                self.method,
                err.len(),
                self.sum_mm.len()
            )));
        }
        for (i, &e) in err.iter().enumerate() {
            self.sum_mm[i] += e;
            self.sum_sq_mm2[i] += e * e;
            self.max_mm[i] = self.max_mm[i].max(e);
        }
        self.scenarios += 1;
        Ok(())
    }

    /// Per node: mean error over the scenarios (mm; NaN when none was added).
    pub fn mean_mm(&self) -> Vec<f64> {
        let n = self.scenarios as f64;
        self.sum_mm.iter().map(|s| s / n).collect()
    }

    /// Per node: standard deviation of the error over the scenarios (population, mm).
    pub fn std_mm(&self) -> Vec<f64> {
        let n = self.scenarios as f64;
        self.sum_mm
            .iter()
            .zip(&self.sum_sq_mm2)
            .map(|(s, q)| (q / n - (s / n).powi(2)).max(0.0).sqrt())
            .collect()
    }

    /// Point arrays `tre_mean_mm`, `tre_max_mm` and `tre_std_mm` (one value per node).
    pub fn point_data(&self) -> Vec<DataArray> {
        vec![
            DataArray::new("tre_mean_mm", 1, self.mean_mm()),
            DataArray::new("tre_max_mm", 1, self.max_mm.clone()),
            DataArray::new("tre_std_mm", 1, self.std_mm()),
        ]
    }

    /// The error map as a mesh file on `mesh` (the geometry's preoperative mesh).
    pub fn to_file(&self, mesh: &TetMesh) -> Result<MeshFile, EvalError> {
        if mesh.num_nodes() != self.sum_mm.len() {
            return Err(EvalError::Internal(format!(
                "error map {}/{} has {} nodes, the mesh {}",
                self.geometry,
                self.method,
                self.sum_mm.len(),
                mesh.num_nodes()
            )));
        }
        Ok(error_map_file(mesh, self.point_data()))
    }
}

/// What [`evaluate`] returns.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Every scenario and method, in deformation, method, scenario order.
    pub results: Vec<ScenarioResult>,
    /// One per geometry and method (geometry order of the deformations, then method order).
    pub error_maps: Vec<ErrorMap>,
    /// The preoperative mesh of each evaluated geometry (for writing the error maps).
    pub meshes: BTreeMap<String, TetMesh>,
    /// With discovery ([`DiscoverEval`]): what each cohort's held-in scenarios named.
    pub discovered: Vec<CohortPhysics>,
}

/// `evaluate --discover`: each deformation (a cohort: one organ state) gets its own augmented
/// model, found by [`crate::discover::discover_cohort`] on its held-in scenarios (the even kept
/// blocks of five: 0, 2, 4, …) and scored as method [`DISCOVERED_METHOD`] (LIBR with it) on the
/// held-out ones (the odd blocks), where every other method then runs too: the physics never
/// sees the scenarios it is scored on.
#[derive(Debug, Clone, Copy)]
pub struct DiscoverEval<'a> {
    /// Discovery's parameters.
    pub params: &'a crate::discover::DiscoverParams,
}

/// The method name of LIBR with a cohort's discovered physics.
pub const DISCOVERED_METHOD: &str = "libr-discovered";

/// What discovery named for one cohort in [`evaluate`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct CohortPhysics {
    /// The deformation.
    pub deformation: String,
    /// Held-in scenarios discovery read.
    pub held_in: usize,
    /// `effects`, `none` or `unexplained`; `error` when discovery failed (the cohort's
    /// `libr-discovered` is then plain LIBR).
    pub verdict: String,
    /// The augmented model's effects, described.
    pub effects: Vec<String>,
    /// Why discovery failed, when it did.
    pub error: Option<String>,
}

/// Learned models in an evaluation: a trained SR-GCN applied to every LIBR result, reported as
/// method `librplus`; the V2S network that method `v2s` runs; optionally only the scenarios a
/// model was not trained on.
#[derive(Clone, Copy)]
pub struct LibrPlusEval<'a> {
    /// The trained model, or an ensemble's members (their corrections averaged); empty: no
    /// LIBR+.
    pub models: &'a [std::sync::Arc<TrainedModel>],
    /// The V2S network of method [`crate::pipeline::Method::V2s`].
    pub v2s: Option<&'a std::sync::Arc<V2sModel>>,
    /// Only these scenarios (deformation id, index), e.g. the model's test split.
    pub only: Option<&'a std::collections::BTreeSet<(String, usize)>>,
}

/// Aggregates results per method.
pub fn summarize(results: &[ScenarioResult]) -> BTreeMap<String, MethodSummary> {
    let mut out: BTreeMap<String, MethodSummary> = BTreeMap::new();
    let mut times: BTreeMap<String, Vec<f64>> = BTreeMap::new();
    // Doing nothing's TRE per scenario, when it ran.
    let nothing: BTreeMap<&str, f64> = results
        .iter()
        .filter(|r| r.method == crate::pipeline::Method::Initial.name())
        .filter_map(|r| Some((r.scenario.as_str(), r.tre.as_ref()?.tre_mm)))
        .collect();
    let with_nothing = results
        .iter()
        .any(|r| r.method == crate::pipeline::Method::Initial.name());
    for r in results {
        let s = out.entry(r.method.clone()).or_default();
        if let Some(q) = r.quality {
            *s.quality.entry(q.name().to_string()).or_default() += 1;
        }
        if with_nothing {
            let bad = r.tre.as_ref().is_some_and(|t| {
                t.tre_mm > FAILED_MM
                    || nothing
                        .get(r.scenario.as_str())
                        .is_some_and(|&n| t.tre_mm > n + WORSE_MM)
            });
            let ok = r.quality == Some(crate::pipeline::quality::Quality::Ok);
            *s.bad_flagged_ok.get_or_insert(0) += usize::from(bad && ok);
        }
        if let Some(a) = &r.auto {
            s.auto.get_or_insert_with(AutoSummary::default).add(a);
        }
        match &r.tre {
            Some(t) => {
                s.scenarios += 1;
                s.abstained += usize::from(r.abstained);
                s.tre_mm += t.tre_mm;
                s.tre_surface_mm += t.tre_surface_mm;
                s.tre_interior_mm += t.tre_interior_mm;
                s.tre_targets_mm += t.tre_targets_mm;
                let c = s.by_category.entry(r.category.clone()).or_default();
                c.scenarios += 1;
                c.tre_mm += t.tre_mm;
                let g = s.by_geometry.entry(r.geometry.clone()).or_default();
                g.scenarios += 1;
                g.tre_mm += t.tre_mm;
                let p = s.by_pattern.entry(pattern_of(&r.scenario)).or_default();
                p.scenarios += 1;
                p.tre_mm += t.tre_mm;
                let f = s.by_family.entry(r.family.clone()).or_default();
                f.scenarios += 1;
                f.tre_mm += t.tre_mm;
                times.entry(r.method.clone()).or_default().push(r.seconds);
            }
            None => s.failed += 1,
        }
    }
    for (m, s) in out.iter_mut() {
        let n = s.scenarios.max(1) as f64;
        s.tre_mm /= n;
        s.tre_surface_mm /= n;
        s.tre_interior_mm /= n;
        s.tre_targets_mm /= n;
        for c in s
            .by_category
            .values_mut()
            .chain(s.by_geometry.values_mut())
            .chain(s.by_pattern.values_mut())
            .chain(s.by_family.values_mut())
        {
            c.tre_mm /= c.scenarios.max(1) as f64;
        }
        if let Some(a) = &mut s.auto {
            a.regret_mm /= a.registrations.max(1) as f64;
        }
        if let Some(t) = times.get_mut(m) {
            t.sort_by(f64::total_cmp);
            s.seconds_median = t[t.len() / 2];
        }
    }
    out
}

/// The categories in the paper's order.
pub const CATEGORY_ORDER: [&str; 5] = [
    "surface",
    "surface+1us",
    "surface+2us",
    "surface+3us",
    "surface+16us",
];

/// A Markdown report of per-split summaries.
pub fn markdown(splits: &BTreeMap<String, BTreeMap<String, MethodSummary>>) -> String {
    let mut s = String::from(
        "# Registration report\n\nTRE in mm, mean over scenarios (mean over mesh nodes per scenario).\n",
    );
    for (split, methods) in splits {
        s.push_str(&format!("\n## Split `{split}`\n\n| method | TRE | surface | interior | targets | scenarios | failed | median time (s) |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n"));
        for (m, v) in methods {
            s.push_str(&format!(
                "| {m} | {:.2} | {:.2} | {:.2} | {:.2} | {} | {} | {:.3} |\n",
                v.tre_mm,
                v.tre_surface_mm,
                v.tre_interior_mm,
                v.tre_targets_mm,
                v.scenarios,
                v.failed,
                v.seconds_median
            ));
        }
        s.push_str("\nBy measurement category (as the paper's Table S1):\n\n| method |");
        for c in CATEGORY_ORDER {
            s.push_str(&format!(" {c} |"));
        }
        s.push_str("\n| --- |");
        for _ in CATEGORY_ORDER {
            s.push_str(" --- |");
        }
        s.push('\n');
        for (m, v) in methods {
            s.push_str(&format!("| {m} |"));
            for c in CATEGORY_ORDER {
                match v.by_category.get(c) {
                    Some(x) => s.push_str(&format!(" {:.2} ({}) |", x.tre_mm, x.scenarios)),
                    None => s.push_str(" – |"),
                }
            }
            s.push('\n');
        }
        s.push_str(&pattern_table(methods));
        s.push_str(&flags_table(methods));
    }
    s
}

/// The quality flags each method answered, the answers confidently worse than doing nothing
/// (flagged OK), and auto's choices against the truth's best candidate; empty when no method
/// carries flags.
fn flags_table(methods: &BTreeMap<String, MethodSummary>) -> String {
    if methods.values().all(|v| v.quality.is_empty()) {
        return String::new();
    }
    let mut s = String::from(
        "\nQuality flags (the flag the service would answer; confidently worse: flagged ok, yet more than 20 mm off or more than 2 mm worse than doing nothing):\n\n| method | flags | confidently worse |\n| --- | --- | --- |\n",
    );
    for (m, v) in methods {
        let flags: Vec<String> = v.quality.iter().map(|(q, n)| format!("{q} {n}")).collect();
        let worse = v
            .bad_flagged_ok
            .map_or_else(|| "– (initial not run)".to_string(), |n| n.to_string());
        s.push_str(&format!("| {m} | {} | {worse} |\n", flags.join(", ")));
    }
    for (m, v) in methods {
        let Some(a) = &v.auto else { continue };
        let mut cols: Vec<&String> = a.confusion.values().flat_map(|o| o.keys()).collect();
        cols.sort();
        cols.dedup();
        s.push_str(&format!(
            "\n`{m}`: the candidate chosen (rows) against the truth's best (columns), {} registrations; regret {:.2} mm mean:\n\n| chosen |",
            a.registrations, a.regret_mm
        ));
        for c in &cols {
            s.push_str(&format!(" {c} |"));
        }
        s.push_str("\n| --- |");
        for _ in &cols {
            s.push_str(" --- |");
        }
        s.push('\n');
        for (chosen, row) in &a.confusion {
            s.push_str(&format!("| {chosen} |"));
            for c in &cols {
                s.push_str(&format!(" {} |", row.get(*c).copied().unwrap_or(0)));
            }
            s.push('\n');
        }
    }
    s
}

/// A table of the split's TRE per group (`groups` of a method's summary) under `title`; empty
/// when there are fewer than two groups.
fn group_table(
    methods: &BTreeMap<String, MethodSummary>,
    title: &str,
    groups: fn(&MethodSummary) -> &BTreeMap<String, CategorySummary>,
) -> (String, Vec<String>) {
    let mut names: Vec<String> = methods
        .values()
        .flat_map(|v| groups(v).keys().cloned())
        .collect();
    names.sort();
    names.dedup();
    if names.len() < 2 {
        return (String::new(), names);
    }
    let mut s = format!("\n{title}:\n\n| method |");
    for p in &names {
        s.push_str(&format!(" {p} |"));
    }
    s.push_str("\n| --- |");
    for _ in &names {
        s.push_str(" --- |");
    }
    s.push('\n');
    for (m, v) in methods {
        s.push_str(&format!("| {m} |"));
        for p in &names {
            match groups(v).get(p) {
                Some(x) => s.push_str(&format!(" {:.2} ({}) |", x.tre_mm, x.scenarios)),
                None => s.push_str(" – |"),
            }
        }
        s.push('\n');
    }
    (s, names)
}

/// The split's TRE per deformation pattern and per truth family, and LIBR with discovered
/// physics against plain LIBR per pattern when both were evaluated (`evaluate --discover`).
fn pattern_table(methods: &BTreeMap<String, MethodSummary>) -> String {
    let (mut s, patterns) = group_table(methods, "By deformation pattern", |v| &v.by_pattern);
    s.push_str(&group_table(methods, "By truth family", |v| &v.by_family).0);
    if patterns.len() < 2 {
        return s;
    }
    if let (Some(plain), Some(found)) = (methods.get("libr"), methods.get("libr-discovered")) {
        let change: Vec<String> = patterns
            .iter()
            .filter_map(|p| {
                let (a, b) = (plain.by_pattern.get(p)?, found.by_pattern.get(p)?);
                Some(format!("{p} {:+.1} %", 100.0 * (b.tre_mm / a.tre_mm - 1.0)))
            })
            .collect();
        s.push_str(&format!(
            "\nLIBR with each cohort's discovered physics against plain LIBR (TRE change): {}.\n",
            change.join(", ")
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(scenario: &str, method: &str, tre_mm: f64) -> ScenarioResult {
        ScenarioResult {
            scenario: scenario.into(),
            geometry: scenario[..2].into(),
            family: "neo-hookean".into(),
            category: "surface".into(),
            method: method.into(),
            tre: Some(crate::eval::Tre {
                tre_mm,
                tre_surface_mm: tre_mm,
                tre_interior_mm: tre_mm,
                tre_targets_mm: tre_mm,
                max_mm: tre_mm,
            }),
            error: None,
            seconds: 0.1,
            outside: None,
            abstained: false,
            auto: None,
            quality: None,
            quality_reason: None,
            surface: None,
            nonlinear: None,
        }
    }

    /// The count of confidently worse answers: flagged OK and more than 20 mm off, or more than
    /// 2 mm worse than doing nothing on the same scenario; a flagged one is not counted, and
    /// without doing nothing among the methods there is no count.
    #[test]
    fn confidently_worse_answers_are_counted_against_doing_nothing() {
        use crate::pipeline::quality::Quality;
        let flagged = |mut r: ScenarioResult, q: Quality| {
            r.quality = Some(q);
            r
        };
        let rows = vec![
            row("g1-L-00/0", "initial", 5.0),
            row("g1-L-00/1", "initial", 30.0),
            row("g1-L-00/2", "initial", 5.0),
            // 2.5 mm worse, OK: counted.
            flagged(row("g1-L-00/0", "libr", 7.5), Quality::Ok),
            // 21 mm off though better than doing nothing, OK: counted.
            flagged(row("g1-L-00/1", "libr", 21.0), Quality::Ok),
            // 3 mm worse but flagged: not counted.
            flagged(row("g1-L-00/2", "libr", 8.0), Quality::AmbiguousModel),
            // 1.5 mm worse, OK: not counted.
            flagged(row("g1-L-00/2", "rigid", 6.5), Quality::Ok),
        ];
        let s = summarize(&rows);
        assert_eq!(s["libr"].bad_flagged_ok, Some(2));
        assert_eq!(s["rigid"].bad_flagged_ok, Some(0));
        assert_eq!(s["libr"].quality["ok"], 2);
        assert_eq!(s["libr"].quality["ambiguous_model"], 1);
        let without: Vec<ScenarioResult> =
            rows.into_iter().filter(|r| r.method != "initial").collect();
        assert_eq!(summarize(&without)["libr"].bad_flagged_ok, None);
    }

    /// Patterns are read from the deformation id; the per-pattern means are the means of their
    /// rows, and the discovered-against-plain change is their ratio.
    #[test]
    fn tre_by_pattern_and_the_discovered_change() {
        assert_eq!(pattern_of("g1-L-00/5"), "L");
        assert_eq!(pattern_of("g12-V-03/0"), "V");
        assert_eq!(pattern_of("scenario7"), "?");
        let rows = [
            row("g1-L-00/1", "libr", 8.0),
            row("g1-L-00/3", "libr", 6.0),
            row("g2-V-00/1", "libr", 4.0),
            row("g1-L-00/1", "libr-discovered", 6.3),
            row("g1-L-00/3", "libr-discovered", 6.3),
            row("g2-V-00/1", "libr-discovered", 5.0),
        ];
        let s = summarize(&rows);
        let l = &s["libr"].by_pattern["L"];
        assert_eq!((l.scenarios, l.tre_mm), (2, 7.0));
        let md = markdown(&BTreeMap::from([("all".to_string(), s)]));
        assert!(md.contains("| libr | 7.00 (2) | 4.00 (1) |"), "{md}");
        assert!(md.contains("L -10.0 %, V +25.0 %"), "{md}");
    }

    /// Auto's regret is the chosen candidate's true TRE minus the best one's, averaged; the
    /// confusion counts chosen against best; both show in the report.
    #[test]
    fn auto_regret_and_confusion_are_read_from_the_candidates_true_errors() {
        use crate::pipeline::quality::Quality;
        let outcome = |chosen: &str, tres: &[(&str, f64)]| {
            let candidates: Vec<AutoCandidateRow> = tres
                .iter()
                .map(|&(c, t)| AutoCandidateRow {
                    candidate: c.into(),
                    held_out_mm2: Some(1.0),
                    folds_mm2: Vec::new(),
                    in_sample_mm2: None,
                    predicted_tre_mm: None,
                    tre_mm: Some(t),
                    apart_mm: None,
                })
                .collect();
            let oracle = tres
                .iter()
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|x| x.0.to_string());
            AutoOutcome {
                chosen: chosen.into(),
                best_scoring: chosen.into(),
                runner_up: None,
                margin_se: None,
                ambiguous: None,
                hold_hypothesis: false,
                oracle,
                candidates,
            }
        };
        let with = |scenario: &str, a: AutoOutcome, tre: f64| {
            let mut r = row(scenario, "auto", tre);
            r.auto = Some(a);
            r.quality = Some(Quality::Ok);
            r
        };
        let rows = vec![
            // Chose the best: no regret.
            with(
                "g1-L-00/0",
                outcome("libr", &[("libr", 5.0), ("adaptive", 6.0)]),
                5.0,
            ),
            // Chose adaptive, LIBR was 1.5 mm better.
            with(
                "g1-L-00/1",
                outcome("adaptive", &[("libr", 4.0), ("adaptive", 5.5)]),
                5.5,
            ),
            // Chose adaptive, it was the best.
            with(
                "g1-L-00/2",
                outcome("adaptive", &[("libr", 7.0), ("adaptive", 6.5)]),
                6.5,
            ),
        ];
        let s = summarize(&rows);
        let a = s["auto"].auto.as_ref().unwrap();
        assert_eq!(a.registrations, 3);
        assert!((a.regret_mm - 0.5).abs() < 1e-12, "{}", a.regret_mm);
        assert_eq!(a.confusion["libr"]["libr"], 1);
        assert_eq!(a.confusion["adaptive"]["libr"], 1);
        assert_eq!(a.confusion["adaptive"]["adaptive"], 1);
        let md = markdown(&BTreeMap::from([("all".to_string(), s)]));
        assert!(md.contains("3 registrations; regret 0.50 mm mean"), "{md}");
        assert!(md.contains("| adaptive | 1 | 1 |"), "{md}");
        assert!(md.contains("| auto | ok 3 | – (initial not run) |"), "{md}");
    }
}
