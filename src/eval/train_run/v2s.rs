//! V2S training runs: the data-driven baseline trained on a split's scenarios (after wICP, on a
//! grid), then wICP and V2S tested on the held-out scenarios by `evaluate`'s own code.

use super::scenarios::SplitScenarios;
use super::{
    PairTotals, TrainRunOptions, TrainRunOutcome, TrainedNetwork, V2sOptions, epoch_progress,
    pair_rows, series,
};
use crate::dataset::Manifest;
use crate::eval::report::{self, LibrPlusEval, Split};
use crate::eval::runs::{RunProgress, write_file, write_json};
use crate::eval::train::v2s::{
    V2sGeometry, V2sSample, V2sTrainOptions, V2sTrainReport, train_v2s, v2s_geometries, v2s_samples,
};
use crate::eval::train::{EpochLog, SplitSets, TrainSplit, split_scenarios};
use crate::eval::{EvalError, ScenarioData, open, plot};
use crate::pipeline::Method;
use crate::v2s::io::V2sModel;
use serde_json::{Value, json};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::time::Instant;

/// Trains V2S on the split `o` names and tests wICP and V2S on its held-out scenarios.
pub(super) fn train_and_test(
    o: &TrainRunOptions,
    v: &V2sOptions,
    progress: &dyn RunProgress,
) -> Result<TrainRunOutcome, EvalError> {
    let t_all = Instant::now();
    let run = Run::prepare(o, v, progress)?;
    let train_s = run.samples(&run.sets.train, "wICP and grids, training scenarios")?;
    let valid_s = run.samples(&run.sets.valid, "wICP and grids, validation scenarios")?;
    let provenance = run.provenance();
    let (model, trained) = Trained::split(run.train(&train_s, &valid_s, &provenance)?);
    let model = Arc::new(model);
    let t_inf = Instant::now();
    let rows = run.test_rows(&model)?;
    let inference_seconds = t_inf.elapsed().as_secs_f64();
    let totals = PairTotals::of(&rows, "rigid", "v2s");
    let a = &totals.all;
    let test = json!({
        "format": 1,
        "method": "v2s",
        "split": run.split.name(),
        "scenarios": a.count,
        "failed": rows.len() - a.count,
        "rigid_tre_mm": a.first_mean(),
        "v2s_tre_mm": a.second_mean(),
        "by_category": totals.by_category_json("rigid_tre_mm", "v2s_tre_mm"),
        "results": rows,
    });
    write_json(&o.out.join("test.json"), &test, "")?;
    let training = json!({
        "format": 1,
        "method": "v2s",
        "grid": v.config.grid,
        "log": trained.log,
        "best_valid_node_error_mm": trained.best_valid_mm,
        "rigid_valid_node_error_mm": trained.rigid_valid_mm,
        "train_samples": trained.train_samples,
        "valid_samples": trained.valid_samples,
        "train_seconds": trained.seconds,
        "test_inference_seconds": inference_seconds,
        "total_seconds": t_all.elapsed().as_secs_f64(),
    });
    write_json(&o.out.join("training.json"), &training, "")?;
    run.save(&model, &trained, &totals, provenance)?;
    Ok(TrainRunOutcome {
        network: TrainedNetwork::V2s,
        split: run.split.name(),
        test: totals,
        train_seconds: trained.seconds,
        libr_seconds: 0.0,
    })
}

/// The figures of a finished training (the model moved out).
struct Trained {
    log: Vec<EpochLog>,
    best_valid_mm: f64,
    rigid_valid_mm: f64,
    train_samples: usize,
    valid_samples: usize,
    seconds: f64,
}

impl Trained {
    /// The model of a training report, and its figures.
    fn split(r: V2sTrainReport) -> (V2sModel, Self) {
        let figures = Self {
            log: r.log,
            best_valid_mm: r.best_valid_mm,
            rigid_valid_mm: r.rigid_valid_mm,
            train_samples: r.train_samples,
            valid_samples: r.valid_samples,
            seconds: r.seconds,
        };
        (r.model, figures)
    }
}

/// What the steps of a run share: its options, dataset, split and prepared grids.
struct Run<'a> {
    o: &'a TrainRunOptions,
    v: &'a V2sOptions,
    progress: &'a dyn RunProgress,
    m: Manifest,
    split: TrainSplit,
    sets: SplitSets,
    scenarios: SplitScenarios,
    frames: BTreeMap<String, V2sGeometry>,
}

impl<'a> Run<'a> {
    /// Reads the dataset, checks the options, splits the scenarios and prepares the grid of
    /// every training liver.
    fn prepare(
        o: &'a TrainRunOptions,
        v: &'a V2sOptions,
        progress: &'a dyn RunProgress,
    ) -> Result<Self, EvalError> {
        let m = open(&o.data)?;
        let split = TrainSplit::parse(&o.split)
            .map_err(|e| EvalError::Parameter(format!("--split: {e}")))?;
        let cfg = &v.config;
        cfg.validate()
            .map_err(|e| EvalError::Parameter(format!("--grid/--v2s-*: {e}")))?;
        if o.physics.is_some() || o.init.is_some() {
            return Err(EvalError::Parameter(
                "--physics and --init are SR-GCN options; V2S has no physics prior".into(),
            ));
        }
        let sets = split_scenarios(&m, &split, o.seed, o.every, o.validation)?;
        progress.log(&format!(
            "V2S, split {}: {} training, {} validation, {} test scenarios; grid {}³",
            split.name(),
            sets.train.len(),
            sets.valid.len(),
            sets.test.len(),
            cfg.grid
        ));
        let scenarios = SplitScenarios::load(&o.data, &m, sets.train.iter().chain(&sets.valid))?;
        progress.spin("preparing the grids (signed distance of every liver)");
        let frames = v2s_geometries(&o.data, &m, &scenarios.geometries(), cfg)?;
        progress.finish();
        Ok(Self {
            o,
            v,
            progress,
            m,
            split,
            sets,
            scenarios,
            frames,
        })
    }

    /// The samples of the scenarios `refs` name (wICP, then the grids), shown as `what`.
    fn samples(&self, refs: &[(String, usize)], what: &str) -> Result<Vec<V2sSample>, EvalError> {
        let items: Vec<(&ScenarioData, &str)> = self.scenarios.pick(refs);
        self.progress.start(what, items.len());
        let r = v2s_samples(&self.frames, &items, &self.o.params, &|d, _| {
            self.progress.step(d, items.len(), None)
        });
        self.progress.finish();
        Ok(r?.into_iter().flatten().collect())
    }

    /// The model's provenance: how it was made, from which data and split.
    fn provenance(&self) -> Value {
        let (o, m) = (self.o, &self.m);
        json!({
            "command": o.origin.command,
            "method": "v2s",
            "data": o.data.display().to_string(),
            "data_preset": m.preset,
            "data_seed": m.seed,
            "data_parameters_hash": m.parameters_hash,
            "split": self.split.name(),
            "every": o.every,
            "validation": o.validation.name(),
            "seed": o.seed,
            "commit": o.origin.commit,
            "train_scenarios": self.sets.train.len(),
            "valid_scenarios": self.sets.valid.len(),
            "test_scenarios": self.sets.test.len(),
        })
    }

    /// Trains the network (the best epoch written to the model directory) and logs every epoch.
    fn train(
        &self,
        train_s: &[V2sSample],
        valid_s: &[V2sSample],
        provenance: &Value,
    ) -> Result<V2sTrainReport, EvalError> {
        let o = self.o;
        let opts = V2sTrainOptions {
            config: self.v.config.clone(),
            seed: o.seed,
            epochs: o.epochs,
            learning_rate: self.v.learning_rate,
            patience: o.patience,
            schedule: o.schedule,
            max_minutes: o.max_minutes,
        };
        self.progress.start("training V2S", 0);
        let t_train = Instant::now();
        let on_step = |epoch: usize, done: usize, total: usize, loss: f64| {
            epoch_progress(self.progress, "", epoch, done, total, loss, t_train);
        };
        let report = train_v2s(
            &opts,
            &self.frames,
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
                "epoch {:>2}: train loss {:.5}, validation {:.4} mm, lr {:.1e}, {:.0} s",
                l.epoch, l.train_loss, l.valid, l.learning_rate, l.seconds
            ));
        }
        self.progress.log(&format!(
            "validation node error {:.4} mm (rigid alone {:.4} mm)",
            report.best_valid_mm, report.rigid_valid_mm
        ));
        Ok(report)
    }

    /// wICP and V2S on the held-out scenarios, scored by `evaluate`'s own code.
    fn test_rows(&self, model: &Arc<V2sModel>) -> Result<Vec<Value>, EvalError> {
        let only: BTreeSet<(String, usize)> = self.sets.test.iter().cloned().collect();
        self.progress.start("rigid and V2S on test scenarios", 0);
        let ev = report::evaluate(
            &self.o.data,
            &self.m,
            Split::All,
            &[Method::Rigid, Method::V2s],
            1,
            &self.o.params,
            &crate::register::physics::Physics::none(),
            Some(LibrPlusEval {
                models: &[],
                v2s: Some(model),
                only: Some(&only),
            }),
            None,
            &|done, total| self.progress.step(done, total, None),
        );
        self.progress.finish();
        Ok(pair_rows(&ev?.results, "rigid", "v2s"))
    }

    /// Writes the model with its provenance (metrics included) and its loss curve.
    fn save(
        &self,
        model: &V2sModel,
        trained: &Trained,
        totals: &PairTotals,
        mut provenance: Value,
    ) -> Result<(), EvalError> {
        provenance["metrics"] = json!({
            "valid_node_error_mm": trained.best_valid_mm,
            "rigid_valid_node_error_mm": trained.rigid_valid_mm,
            "test_rigid_tre_mm": totals.all.first_mean(),
            "test_v2s_tre_mm": totals.all.second_mean(),
            "train_seconds": trained.seconds,
        });
        crate::v2s::io::save_model(&self.o.out, &model.config, &model.net, provenance)?;
        let all = |_: &EpochLog| true;
        let png = plot::line_chart_png(
            "V2S training",
            "epoch",
            "validation node error (mm) / training loss",
            &[
                (
                    "validation node error (mm)".into(),
                    series(&trained.log, all, |l| l.valid),
                ),
                (
                    "training loss".into(),
                    series(&trained.log, all, |l| l.train_loss),
                ),
                (
                    "rigid alone (mm)".into(),
                    series(&trained.log, all, |_| trained.rigid_valid_mm),
                ),
            ],
        )?;
        write_file(&self.o.out.join("loss.png"), &png)
    }
}
