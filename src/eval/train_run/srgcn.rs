//! SR-GCN training runs: LIBR on the split's scenarios, the network trained on its residual, the
//! correction scale fitted again through LIBR+'s refit, then LIBR and LIBR+ tested on the
//! held-out scenarios.

use super::scenarios::SplitScenarios;
use super::{
    PairTotals, SrgcnOptions, TrainRunOptions, TrainRunOutcome, TrainedNetwork, epoch_progress,
    pair_rows, series,
};
use crate::dataset::Manifest;
use crate::eval::report::{self, LibrPlusEval, Split};
use crate::eval::runs::{RunProgress, read_physics, write_file, write_json};
use crate::eval::train::{
    self as tr, EpochLog, GeometryCase, LibrSolution, SplitSets, TrainOptions, TrainReport,
    TrainSplit, TrainingSample,
};
use crate::eval::{EvalError, ScenarioData, node_errors_mm, open, plot, tre_from_errors};
use crate::gcn::io::TrainedModel;
use crate::gcn::model::{SrGcnConfig, Target};
use crate::register::physics::Physics;
use serde_json::{Value, json};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::time::Instant;

/// A scenario with its geometry.
type Item<'a> = (&'a ScenarioData, &'a str);

/// A scenario, its geometry and LIBR's solution (None where LIBR failed).
type Solved<'a> = (&'a ScenarioData, &'a str, &'a Option<LibrSolution>);

/// Trains SR-GCN on the split `o` names and tests LIBR and LIBR+ on its held-out scenarios.
pub(super) fn train_and_test(
    o: &TrainRunOptions,
    s: &SrgcnOptions,
    progress: &dyn RunProgress,
) -> Result<TrainRunOutcome, EvalError> {
    let t_all = Instant::now();
    let (run, init_provenance) = Run::prepare(o, s, progress)?;
    let train_items = run.scenarios.pick(&run.sets.train);
    let valid_items = run.scenarios.pick(&run.sets.valid);
    let t_libr = Instant::now();
    let train_sol = run.solve(&train_items, "LIBR on training scenarios")?;
    let valid_sol = run.solve(&valid_items, "LIBR on validation scenarios")?;
    let libr_seconds = t_libr.elapsed().as_secs_f64();
    let train_s = run.samples(&solved(&train_items, &train_sol))?;
    let valid_s = run.samples(&solved(&valid_items, &valid_sol))?;
    let provenance = run.provenance(init_provenance);
    let mut report = run.train(&train_s, &valid_s, &provenance)?;
    let refit_fit = run.fit_scale_through_refit(&mut report, &solved(&valid_items, &valid_sol))?;
    let model = Arc::new(report.model);
    let t_inf = Instant::now();
    let rows = run.test_rows(&model)?;
    let tested = Tested {
        totals: PairTotals::of(&rows, "libr", "librplus"),
        rows,
        libr_seconds,
        inference_seconds: t_inf.elapsed().as_secs_f64(),
    };
    let trained = Trained {
        log: report.log,
        best_valid_mm: report.best_valid_mm,
        scaled_valid_mm: report.scaled_valid_mm,
        libr_valid_mm: report.libr_valid_mm,
        train_samples: report.train_samples,
        valid_samples: report.valid_samples,
        seconds: report.seconds,
        refit_fit,
    };
    run.write(&model, &trained, &tested, provenance, t_all)?;
    Ok(TrainRunOutcome {
        network: TrainedNetwork::Srgcn,
        split: run.split.name(),
        test: tested.totals,
        train_seconds: trained.seconds,
        libr_seconds,
    })
}

/// Each scenario of `items` with its LIBR solution.
fn solved<'a>(items: &[Item<'a>], sols: &'a [Option<LibrSolution>]) -> Vec<Solved<'a>> {
    items
        .iter()
        .zip(sols)
        .map(|((s, g), o)| (*s, *g, o))
        .collect()
}

/// The paper's Table 2 settings as configurations: (LIBR input, bipartite, target, sparse loss).
fn ablation_config(
    mut cfg: SrGcnConfig,
    setting: u32,
    sparse: f64,
) -> Result<SrGcnConfig, EvalError> {
    let (libr, bip, target, sp) = match setting {
        1 => (false, false, Target::Gt, false),
        2 => (false, false, Target::Residual, false),
        3 => (true, false, Target::Residual, false),
        4 => (true, true, Target::Residual, false),
        5 => (true, true, Target::Gt, true),
        6 => (true, true, Target::Residual, true),
        other => {
            return Err(EvalError::Parameter(format!(
                "--ablation {other}: settings are 1-6 (the paper's Table 2)"
            )));
        }
    };
    cfg.libr_input = libr;
    cfg.bipartite = bip;
    // The measured misfit is measurement information, like the bipartite branch.
    cfg.misfit_input = cfg.misfit_input && bip;
    cfg.target = target;
    cfg.sparse_weight = if sp { sparse } else { 0.0 };
    Ok(cfg)
}

/// The network's configuration (the ablation setting's, or the initial model's) and what the
/// provenance records of the initial model.
fn network_config(
    o: &TrainRunOptions,
    s: &SrgcnOptions,
    progress: &dyn RunProgress,
) -> Result<(SrGcnConfig, Value), EvalError> {
    let base = s.config.clone();
    let sparse = s.sparse_weight.unwrap_or(base.sparse_weight);
    let Some(dir) = &o.init else {
        return Ok((ablation_config(base, s.ablation, sparse)?, Value::Null));
    };
    let m = crate::gcn::io::load_model(dir, &crate::gcn::device::compute())
        .map_err(|e| EvalError::Parameter(format!("--init: {e}")))?;
    progress.log(&format!(
        "--init {}: its network and settings replace the network options",
        dir.display()
    ));
    let cfg = SrGcnConfig {
        correction_scale: 1.0,
        ..m.config
    };
    let provenance = json!({"dir": dir.display().to_string(), "provenance": m.provenance});
    Ok((cfg, provenance))
}

/// What the steps of a run share: its options, dataset, split, network and prepared cases.
struct Run<'a> {
    o: &'a TrainRunOptions,
    s: &'a SrgcnOptions,
    progress: &'a dyn RunProgress,
    m: Manifest,
    split: TrainSplit,
    cfg: SrGcnConfig,
    /// Whether the node loss scores what the refit makes of the correction.
    refit_loss: bool,
    physics: Physics,
    sets: SplitSets,
    scenarios: SplitScenarios,
    cases: BTreeMap<String, GeometryCase>,
}

/// The figures of a finished training (the model moved out).
struct Trained {
    log: Vec<EpochLog>,
    best_valid_mm: f64,
    scaled_valid_mm: f64,
    libr_valid_mm: f64,
    train_samples: usize,
    valid_samples: usize,
    seconds: f64,
    /// The correction scale's fit through the refit (null without it).
    refit_fit: Value,
}

/// The test of a trained model.
struct Tested {
    /// `test.json`'s per-scenario rows.
    rows: Vec<Value>,
    totals: PairTotals,
    libr_seconds: f64,
    inference_seconds: f64,
}

impl<'a> Run<'a> {
    /// Reads the dataset, checks the options, splits the scenarios and prepares every case the
    /// split uses (LIBR bases); also returns the initial model's provenance.
    fn prepare(
        o: &'a TrainRunOptions,
        s: &'a SrgcnOptions,
        progress: &'a dyn RunProgress,
    ) -> Result<(Self, Value), EvalError> {
        let m = open(&o.data)?;
        let split = TrainSplit::parse(&o.split)
            .map_err(|e| EvalError::Parameter(format!("--split: {e}")))?;
        let (cfg, init_provenance) = network_config(o, s, progress)?;
        cfg.validate()
            .map_err(|e| EvalError::Parameter(format!("network options: {e}")))?;
        let params = &o.params;
        params
            .libr
            .validate()
            .map_err(|e| EvalError::Parameter(format!("LIBR options: {e}")))?;
        // Training through the refit needs a refit, and a correction of LIBR's shape to refit.
        let refit_loss =
            s.refit_loss && params.refit_iterations > 0 && cfg.target == Target::Residual;
        let sets = tr::split_scenarios(&m, &split, o.seed, o.every, o.validation)?;
        progress.log(&format!(
            "split {}: {} training, {} validation, {} test scenarios",
            split.name(),
            sets.train.len(),
            sets.valid.len(),
            sets.test.len()
        ));
        // Scenarios of every deformation used.
        let all = sets.train.iter().chain(&sets.valid).chain(&sets.test);
        let scenarios = SplitScenarios::load(&o.data, &m, all)?;
        progress.spin("preparing cases (LIBR bases)");
        let physics = read_physics(o.physics.as_deref())?;
        let cases = tr::load_cases(&o.data, &m, &scenarios.geometries(), params, &physics)?;
        progress.finish();
        let run = Self {
            o,
            s,
            progress,
            m,
            split,
            cfg,
            refit_loss,
            physics,
            sets,
            scenarios,
            cases,
        };
        Ok((run, init_provenance))
    }

    /// LIBR's solution of every scenario of `items` (cached in the dataset), shown as `what`.
    fn solve(&self, items: &[Item], what: &str) -> Result<Vec<Option<LibrSolution>>, EvalError> {
        self.progress.start(what, items.len());
        let r = tr::libr_solutions(&self.o.data, &self.cases, items, &self.o.params, &|d, _| {
            self.progress.step(d, items.len(), None)
        });
        self.progress.finish();
        r
    }

    /// The training samples of the scenarios whose LIBR succeeded.
    fn samples(&self, items: &[Solved]) -> Result<Vec<TrainingSample>, EvalError> {
        let samples = tr::build_samples(
            &self.cfg,
            &self.cases,
            items,
            &self.o.params,
            true,
            self.refit_loss,
        )?;
        Ok(samples.into_iter().flatten().collect())
    }

    /// The model's provenance: how it was made, from which data and split.
    fn provenance(&self, init: Value) -> Value {
        let (o, m, physics) = (self.o, &self.m, &self.physics);
        json!({
            "command": o.origin.command,
            "data": o.data.display().to_string(),
            "data_preset": m.preset,
            "data_seed": m.seed,
            "data_parameters_hash": m.parameters_hash,
            "split": self.split.name(),
            "every": o.every,
            "validation": o.validation.name(),
            "seed": o.seed,
            "ablation": self.s.ablation,
            "init": init,
            "commit": o.origin.commit,
            "libr_solution_key": tr::solution_key(&o.params, physics),
            // The LIBR whose residual the network learns (absent: plain LIBR); LIBR+ applies the
            // network only to a LIBR with the same physics.
            "physics_hash": (!physics.is_empty()).then(|| physics.hash()),
            "physics": (!physics.is_empty()).then(|| physics.to_value(&[])),
            "train_scenarios": self.sets.train.len(),
            "valid_scenarios": self.sets.valid.len(),
            "test_scenarios": self.sets.test.len(),
        })
    }

    /// Trains the network (checkpoints into the model directory) and logs every epoch.
    fn train(
        &self,
        train_s: &[TrainingSample],
        valid_s: &[TrainingSample],
        provenance: &Value,
    ) -> Result<TrainReport, EvalError> {
        let (o, s) = (self.o, self.s);
        let opts = TrainOptions {
            config: self.cfg.clone(),
            split: self.split.clone(),
            every: o.every,
            seed: o.seed,
            epochs_bipartite: s.epochs_bipartite,
            epochs: o.epochs,
            learning_rate: s.learning_rate,
            max_minutes: o.max_minutes,
            init: o.init.clone(),
            patience: o.patience,
            refit_loss: self.refit_loss,
            average_epochs: s.average_epochs,
            weight_decay: s.weight_decay,
            position_jitter: s.position_jitter,
            schedule: o.schedule,
        };
        self.progress.start("training", 0);
        let t_train = Instant::now();
        let on_step = |stage: u32, epoch: usize, done: usize, total: usize, loss: f64| {
            let prefix = format!("stage {stage} ");
            epoch_progress(self.progress, &prefix, epoch, done, total, loss, t_train);
        };
        let report = tr::train(
            &opts,
            &self.cases,
            train_s,
            valid_s,
            &o.out,
            provenance,
            &on_step,
        );
        self.progress.finish();
        let report = report?;
        for l in &report.log {
            self.progress.log(&format!(
                "stage {} epoch {:>2}: train loss {:.5}, validation {:.4}{}, lr {:.1e}, {:.0} s",
                l.stage,
                l.epoch,
                l.train_loss,
                l.valid,
                if l.stage == 2 { " mm" } else { "" },
                l.learning_rate,
                l.seconds
            ));
        }
        self.progress.log(&format!(
            "correction scale {:.2} (validation node error {:.4} mm; {:.4} mm at scale 1, LIBR {:.4} mm)",
            report.model.config.correction_scale,
            report.scaled_valid_mm,
            report.best_valid_mm,
            report.libr_valid_mm
        ));
        Ok(report)
    }

    /// With the data-consistency refit (as LIBR+ runs), fits the correction scale again on the
    /// validation scenarios through the refit; returns what `training.json` records of the fit
    /// (null without a refit).
    fn fit_scale_through_refit(
        &self,
        report: &mut TrainReport,
        valid: &[Solved],
    ) -> Result<Value, EvalError> {
        let params = &self.o.params;
        let scale_without_refit = report.model.config.correction_scale;
        if report.model.config.target != Target::Residual || params.refit_iterations == 0 {
            return Ok(Value::Null);
        }
        self.progress
            .spin("fitting the correction scale through the refit (validation)");
        let grid = tr::refit_scale_grid();
        let (scale, errs) = tr::fit_refit_scale(&report.model, &self.cases, valid, params, &grid)?;
        self.progress.finish();
        let k = grid.iter().position(|&g| g == scale).unwrap_or(0);
        self.progress.log(&format!(
            "with the refit ({} iterations): correction scale {scale:.3}, validation node error {:.4} mm ({:.4} mm without the correction)",
            params.refit_iterations, errs[k], errs[0]
        ));
        report.model.config.correction_scale = scale;
        report.scaled_valid_mm = errs[k];
        Ok(json!({
            "refit_iterations": params.refit_iterations,
            "grid": grid,
            "valid_node_error_mm": errs,
            "scale_without_refit": scale_without_refit,
        }))
    }

    /// LIBR and LIBR+ on the held-out scenarios, scored by `evaluate`'s own code (a diagnostic
    /// model needs the truth to build its samples and has its own loop).
    fn test_rows(&self, model: &Arc<TrainedModel>) -> Result<Vec<Value>, EvalError> {
        if self.cfg.diagnostic_truth_neighbours {
            let items = self.scenarios.pick(&self.sets.test);
            let sols = self.solve(&items, "LIBR on test scenarios")?;
            return self.diagnostic_test_rows(&solved(&items, &sols), model);
        }
        let only: BTreeSet<(String, usize)> = self.sets.test.iter().cloned().collect();
        self.progress.start("LIBR and LIBR+ on test scenarios", 0);
        let ev = report::evaluate(
            &self.o.data,
            &self.m,
            Split::All,
            &[crate::pipeline::Method::Libr],
            1,
            &self.o.params,
            &self.physics,
            Some(LibrPlusEval {
                models: std::slice::from_ref(model),
                v2s: None,
                only: Some(&only),
            }),
            None,
            &|done, total| self.progress.step(done, total, None),
        );
        self.progress.finish();
        Ok(pair_rows(&ev?.results, "libr", "librplus"))
    }

    /// The rows of `test.json` for a diagnostic model (its `diagnostic_truth_neighbours`), which
    /// `evaluate` refuses: its test samples link the measured points to the true deformed mesh.
    fn diagnostic_test_rows(
        &self,
        test: &[Solved],
        model: &TrainedModel,
    ) -> Result<Vec<Value>, EvalError> {
        // The paper's leak: the test samples link to the true deformed mesh.
        let samples = tr::build_samples(&self.cfg, &self.cases, test, &self.o.params, true, false)?;
        let plain = crate::gcn::device::compute();
        let mut graphs = BTreeMap::new();
        for (g, gc) in &self.cases {
            let graph = gc
                .frame
                .mesh_graphs(&self.cfg, &plain)
                .map_err(|e| EvalError::Training(e.to_string()))?;
            graphs.insert(g.clone(), graph);
        }
        let mut rows = Vec::new();
        self.progress.start("LIBR+ on test scenarios", test.len());
        for (k, (&(sc, g, sol), sample)) in test.iter().zip(&samples).enumerate() {
            self.progress.step(k + 1, test.len(), None);
            let (Some(sol), Some(sample)) = (sol, sample) else {
                rows.push(
                    json!({"scenario": sc.id, "category": sc.category, "error": "LIBR failed"}),
                );
                continue;
            };
            let gc = &self.cases[g];
            let u_plus =
                crate::gcn::infer::correct(model, &gc.frame, &graphs[g], &sample.data, &sol.u)
                    .map_err(|e| EvalError::Training(format!("{}: {e}", sc.id)))?;
            rows.push(self.diagnostic_row(gc, sc, g, sol, u_plus)?);
        }
        self.progress.finish();
        Ok(rows)
    }

    /// A diagnostic model's row of `test.json`: LIBR's and LIBR+'s (refitted) TREs.
    fn diagnostic_row(
        &self,
        gc: &GeometryCase,
        sc: &ScenarioData,
        g: &str,
        sol: &LibrSolution,
        u_plus: Vec<f64>,
    ) -> Result<Value, EvalError> {
        let params = &self.o.params;
        let nodes = gc.geo.model.mesh.nodes();
        let truth = (
            &sc.truth.image_to_physical,
            sc.truth.displacement.as_slice(),
        );
        let e_libr = node_errors_mm(nodes, (&sol.transform, &sol.u), truth);
        let (u_plus, t_plus) = if params.refit_iterations > 0 {
            let r = crate::pipeline::refit(
                &gc.case,
                &sc.measurements,
                params,
                &u_plus,
                &sol.transform,
                None,
                None,
            )
            .map_err(|e| EvalError::Training(format!("{}: refit: {e}", sc.id)))?;
            (r.u, r.image_to_physical)
        } else {
            (u_plus, sol.transform)
        };
        let e_plus = node_errors_mm(nodes, (&t_plus, &u_plus), truth);
        let t_l = tre_from_errors(&e_libr, &gc.geo.surface, &gc.geo.targets);
        let t_p = tre_from_errors(&e_plus, &gc.geo.surface, &gc.geo.targets);
        Ok(
            json!({"scenario": sc.id, "geometry": g, "category": sc.category, "libr": t_l, "librplus": t_p}),
        )
    }

    /// Writes `test.json`, `training.json`, the model with its provenance (metrics included)
    /// and the loss curves.
    fn write(
        &self,
        model: &TrainedModel,
        trained: &Trained,
        tested: &Tested,
        mut provenance: Value,
        t_all: Instant,
    ) -> Result<(), EvalError> {
        let out = &self.o.out;
        let a = &tested.totals.all;
        let (sl, sp, n) = (a.first, a.second, a.count);
        let test = json!({
            "format": 1,
            "split": self.split.name(),
            "scenarios": n,
            "failed": tested.rows.len() - n,
            "libr_tre_mm": a.first_mean(),
            "librplus_tre_mm": a.second_mean(),
            "ratio": if sl > 0.0 { sp / sl } else { f64::NAN },
            "by_category": tested.totals.by_category_json("libr_tre_mm", "librplus_tre_mm"),
            "results": tested.rows,
        });
        write_json(&out.join("test.json"), &test, "")?;
        let training = json!({
            "format": 1,
            "log": trained.log,
            "best_valid_node_error_mm": trained.best_valid_mm,
            "correction_scale": model.config.correction_scale,
            "scaled_valid_node_error_mm": trained.scaled_valid_mm,
            "refit_scale_fit": trained.refit_fit,
            "libr_valid_node_error_mm": trained.libr_valid_mm,
            "train_samples": trained.train_samples,
            "valid_samples": trained.valid_samples,
            "train_seconds": trained.seconds,
            "libr_solution_seconds": tested.libr_seconds,
            "test_inference_seconds": tested.inference_seconds,
            "total_seconds": t_all.elapsed().as_secs_f64(),
        });
        write_json(&out.join("training.json"), &training, "")?;
        provenance["metrics"] = json!({
            "valid_node_error_mm": trained.best_valid_mm,
            "correction_scale": model.config.correction_scale,
            "libr_valid_node_error_mm": trained.libr_valid_mm,
            "test_libr_tre_mm": a.first_mean(),
            "test_librplus_tre_mm": a.second_mean(),
            "train_seconds": trained.seconds,
        });
        crate::gcn::io::save_model(out, &model.config, &model.net, provenance)?;
        self.write_loss_curves(trained)
    }

    /// The loss curves: stage 2 (the mesh branch) and, with the bipartite branch, stage 1.
    fn write_loss_curves(&self, trained: &Trained) -> Result<(), EvalError> {
        let log = &trained.log;
        let stage = |k: u32| move |l: &EpochLog| l.stage == k;
        let png = plot::line_chart_png(
            "SR-GCN stage 2 (mesh branch)",
            "epoch",
            "validation node error (mm) / training loss",
            &[
                (
                    "validation node error (mm)".into(),
                    series(log, stage(2), |l| l.valid),
                ),
                (
                    "training loss".into(),
                    series(log, stage(2), |l| l.train_loss),
                ),
                (
                    "LIBR alone (mm)".into(),
                    series(log, stage(2), |_| trained.libr_valid_mm),
                ),
            ],
        )?;
        write_file(&self.o.out.join("loss_stage2.png"), &png)?;
        if self.cfg.bipartite {
            let png = plot::line_chart_png(
                "SR-GCN stage 1 (bipartite reconstruction)",
                "epoch",
                "loss",
                &[
                    ("training".into(), series(log, stage(1), |l| l.train_loss)),
                    ("validation".into(), series(log, stage(1), |l| l.valid)),
                ],
            )?;
            write_file(&self.o.out.join("loss_stage1.png"), &png)?;
        }
        Ok(())
    }
}
