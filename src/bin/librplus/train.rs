//! `librplus train` (one SR-GCN model, trained and tested) and `librplus ensemble`.

use crate::args::{EnsembleArgs, ScheduleArg, TrainArgs};
use crate::util::bar_style;
use crate::util::{git_commit, shell_command};
use anyhow::{Result, bail};
use serde_json::{Value, json};
use std::time::Instant;

pub(crate) fn ensemble(a: &EnsembleArgs) -> Result<()> {
    let command: Vec<String> = std::env::args().collect();
    let names = librplus::gcn::io::make_ensemble(
        &a.out,
        &a.models,
        json!({ "command": command.join(" ") }),
    )?;
    let models = librplus::gcn::io::load_models_on_device(&a.out)?;
    println!("{}: ensemble of {} networks", a.out.display(), names.len());
    for (name, m) in names.iter().zip(&models) {
        let p = &m.provenance;
        println!(
            "  {name}: split {}, correction scale {}, test LIBR {} → LIBR+ {} mm",
            p["split"].as_str().unwrap_or("?"),
            m.config.correction_scale,
            p["metrics"]["test_libr_tre_mm"]
                .as_f64()
                .map_or("?".into(), |x| format!("{x:.3}")),
            p["metrics"]["test_librplus_tre_mm"]
                .as_f64()
                .map_or("?".into(), |x| format!("{x:.3}")),
        );
    }
    Ok(())
}

/// The paper's Table 2 settings as configurations: (LIBR input, bipartite, target, sparse loss).
fn ablation_config(
    mut cfg: librplus::gcn::model::SrGcnConfig,
    setting: u32,
    sparse: f64,
) -> Result<librplus::gcn::model::SrGcnConfig> {
    use librplus::gcn::model::Target;
    let (libr, bip, target, sp) = match setting {
        1 => (false, false, Target::Gt, false),
        2 => (false, false, Target::Residual, false),
        3 => (true, false, Target::Residual, false),
        4 => (true, true, Target::Residual, false),
        5 => (true, true, Target::Gt, true),
        6 => (true, true, Target::Residual, true),
        other => bail!("--ablation {other}: settings are 1-6 (the paper's Table 2)"),
    };
    cfg.libr_input = libr;
    cfg.bipartite = bip;
    // The measured misfit is measurement information, like the bipartite branch.
    cfg.misfit_input = cfg.misfit_input && bip;
    cfg.target = target;
    cfg.sparse_weight = if sp { sparse } else { 0.0 };
    Ok(cfg)
}

/// Trains and tests one model; returns its test.json (without per-scenario rows) and a
/// summary of its training.
pub(crate) fn train(a: &TrainArgs) -> Result<Value> {
    use librplus::eval::train::{self as tr, TrainOptions, TrainSplit};
    use librplus::gcn::model::SrGcnConfig;
    if a.method == crate::args::TrainMethod::V2s {
        return crate::train_v2s::train_v2s(a);
    }
    let t_all = Instant::now();
    let m = librplus::eval::open(&a.data)?;
    let split = TrainSplit::parse(&a.split).map_err(|e| anyhow::anyhow!("--split: {e}"))?;
    let base = SrGcnConfig::new()
        .with_misfit_input(a.misfit_input)
        .with_surface_input(a.surface_input)
        .with_load_input(a.load_input)
        .with_diagnostic_truth_neighbours(a.diagnostic_truth_neighbours)
        .with_width(a.width)
        .with_convs(a.convs)
        .with_kernel_size(a.kernel_size)
        .with_levels(a.levels)
        .with_resolution(a.resolution)
        .with_pool_ratio(a.pool_ratio)
        .with_clusters(a.clusters)
        .with_coarse_convs(a.coarse_convs)
        .with_residual(!a.no_residual)
        .with_n_top(a.n_top);
    let sparse = a.sparse_weight.unwrap_or(base.sparse_weight);
    let (cfg, init_provenance) = match &a.init {
        None => (ablation_config(base, a.ablation, sparse)?, Value::Null),
        Some(dir) => {
            let m = librplus::gcn::io::load_model(dir, &librplus::gcn::device::compute())
                .map_err(|e| anyhow::anyhow!("--init: {e}"))?;
            eprintln!(
                "--init {}: its network and settings replace the network options",
                dir.display()
            );
            (
                SrGcnConfig {
                    correction_scale: 1.0,
                    ..m.config
                },
                json!({"dir": dir.display().to_string(), "provenance": m.provenance}),
            )
        }
    };
    cfg.validate()
        .map_err(|e| anyhow::anyhow!("network options: {e}"))?;
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    // Training through the refit needs a refit, and a correction of LIBR's shape to refit.
    let refit_loss = !a.no_refit_loss
        && params.refit_iterations > 0
        && cfg.target == librplus::gcn::model::Target::Residual;
    let opts = TrainOptions {
        config: cfg.clone(),
        split: split.clone(),
        every: a.every,
        seed: a.seed,
        epochs_bipartite: a.epochs_bipartite,
        epochs: a.epochs,
        learning_rate: a.lr,
        max_minutes: a.max_minutes,
        init: a.init.clone(),
        patience: a.patience,
        refit_loss,
        average_epochs: a.average_epochs,
        weight_decay: a.weight_decay,
        position_jitter: a.position_jitter,
        schedule: match a.schedule {
            ScheduleArg::Plateau => tr::Schedule::Plateau,
            ScheduleArg::Cosine => tr::Schedule::Cosine,
        },
    };
    let sets = tr::split_scenarios(&m, &split, a.seed, a.every, a.validation.get())?;
    eprintln!(
        "split {}: {} training, {} validation, {} test scenarios",
        split.name(),
        sets.train.len(),
        sets.valid.len(),
        sets.test.len()
    );
    // Scenarios of every deformation used.
    let split_scen = crate::util::SplitScenarios::load(
        &a.data,
        &m,
        sets.train.iter().chain(&sets.valid).chain(&sets.test),
    )?;
    let geos = split_scen.geometries();
    let spinner =
        indicatif::ProgressBar::new_spinner().with_message("preparing cases (LIBR bases)");
    spinner.enable_steady_tick(std::time::Duration::from_millis(200));
    let physics = match &a.physics {
        None => librplus::register::physics::Physics::none(),
        Some(p) => librplus::register::physics::Physics::read(p)
            .map_err(|e| anyhow::anyhow!("--physics: {e}"))?,
    };
    let cases = tr::load_cases(&a.data, &m, &geos, &params, &physics)?;
    spinner.finish_and_clear();
    let pick = |refs: &[(String, usize)]| split_scen.pick(refs);
    let solve = |items: &[(&librplus::eval::ScenarioData, &str)],
                 what: &str|
     -> Result<Vec<Option<tr::LibrSolution>>> {
        let bar = indicatif::ProgressBar::new(items.len() as u64).with_style(bar_style(what));
        let r = tr::libr_solutions(&a.data, &cases, items, &params, &|d, _| {
            bar.set_position(d as u64)
        });
        bar.finish_and_clear();
        r.map_err(anyhow::Error::msg)
    };
    let t_libr = Instant::now();
    let train_items = pick(&sets.train);
    let valid_items = pick(&sets.valid);
    let train_sol = solve(&train_items, "LIBR on training scenarios")?;
    let valid_sol = solve(&valid_items, "LIBR on validation scenarios")?;
    let libr_seconds = t_libr.elapsed().as_secs_f64();
    let samples = |items: &[(&librplus::eval::ScenarioData, &str)],
                   sols: &[Option<tr::LibrSolution>]|
     -> Result<Vec<tr::TrainingSample>> {
        let z: Vec<_> = items
            .iter()
            .zip(sols)
            .map(|((s, g), o)| (*s, *g, o))
            .collect();
        Ok(
            tr::build_samples(&cfg, &cases, &z, &params, true, refit_loss)?
                .into_iter()
                .flatten()
                .collect(),
        )
    };
    let train_s = samples(&train_items, &train_sol)?;
    let valid_s = samples(&valid_items, &valid_sol)?;
    let command = shell_command();
    let provenance = json!({
        "command": command,
        "data": a.data.display().to_string(),
        "data_preset": m.preset,
        "data_seed": m.seed,
        "data_parameters_hash": m.parameters_hash,
        "split": split.name(),
        "every": a.every,
        "validation": a.validation.get().name(),
        "seed": a.seed,
        "ablation": a.ablation,
        "init": init_provenance,
        "commit": git_commit(),
        "libr_solution_key": tr::solution_key(&params, &physics),
        // The LIBR whose residual the network learns (absent: plain LIBR); LIBR+ applies the
        // network only to a LIBR with the same physics.
        "physics_hash": (!physics.is_empty()).then(|| physics.hash()),
        "physics": (!physics.is_empty()).then(|| physics.to_value(&[])),
        "train_scenarios": sets.train.len(),
        "valid_scenarios": sets.valid.len(),
        "test_scenarios": sets.test.len(),
    });
    let bar = indicatif::ProgressBar::new(0).with_style(bar_style("training"));
    let t_train = Instant::now();
    let progress = |stage: u32, epoch: usize, done: usize, total: usize, loss: f64| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(format!("stage {stage} epoch {epoch} loss {loss:.4}"));
        if done == total {
            bar.suspend(|| {
                eprintln!(
                    "stage {stage} epoch {epoch}: {total} steps, training loss {loss:.5}, {:.0} s",
                    t_train.elapsed().as_secs_f64()
                )
            });
        }
    };
    let mut report = tr::train(
        &opts,
        &cases,
        &train_s,
        &valid_s,
        &a.out,
        &provenance,
        &progress,
    )?;
    bar.finish_and_clear();
    for l in &report.log {
        eprintln!(
            "stage {} epoch {:>2}: train loss {:.5}, validation {:.4}{}, lr {:.1e}, {:.0} s",
            l.stage,
            l.epoch,
            l.train_loss,
            l.valid,
            if l.stage == 2 { " mm" } else { "" },
            l.learning_rate,
            l.seconds
        );
    }
    eprintln!(
        "correction scale {:.2} (validation node error {:.4} mm; {:.4} mm at scale 1, LIBR {:.4} mm)",
        report.model.config.correction_scale,
        report.scaled_valid_mm,
        report.best_valid_mm,
        report.libr_valid_mm
    );
    // With the data-consistency refit (as LIBR+ runs), the scale is fitted again on the
    // validation scenarios through the refit.
    let scale_without_refit = report.model.config.correction_scale;
    let mut refit_fit = serde_json::Value::Null;
    if report.model.config.target == librplus::gcn::model::Target::Residual
        && params.refit_iterations > 0
    {
        let spinner = indicatif::ProgressBar::new_spinner()
            .with_message("fitting the correction scale through the refit (validation)");
        spinner.enable_steady_tick(std::time::Duration::from_millis(200));
        let z: Vec<_> = valid_items
            .iter()
            .zip(&valid_sol)
            .map(|((s, g), o)| (*s, *g, o))
            .collect();
        let grid = tr::refit_scale_grid();
        let (scale, errs) = tr::fit_refit_scale(&report.model, &cases, &z, &params, &grid)?;
        spinner.finish_and_clear();
        let k = grid.iter().position(|&g| g == scale).unwrap_or(0);
        eprintln!(
            "with the refit ({} iterations): correction scale {scale:.3}, validation node error {:.4} mm ({:.4} mm without the correction)",
            params.refit_iterations, errs[k], errs[0]
        );
        report.model.config.correction_scale = scale;
        report.scaled_valid_mm = errs[k];
        refit_fit = json!({
            "refit_iterations": params.refit_iterations,
            "grid": grid,
            "valid_node_error_mm": errs,
            "scale_without_refit": scale_without_refit,
        });
    }
    // Test: LIBR and LIBR+ on the held-out scenarios, scored by `librplus evaluate`'s own code
    // (a diagnostic model needs the truth to build its samples and has its own loop).
    let model = std::sync::Arc::new(report.model);
    let t_inf = Instant::now();
    let rows = if cfg.diagnostic_truth_neighbours {
        let test_items = pick(&sets.test);
        let test_sol = solve(&test_items, "LIBR on test scenarios")?;
        diagnostic_test_rows(&cfg, &cases, &test_items, &test_sol, &params, &model)?
    } else {
        let only: std::collections::BTreeSet<(String, usize)> = sets.test.iter().cloned().collect();
        let bar = indicatif::ProgressBar::new(0)
            .with_style(bar_style("LIBR and LIBR+ on test scenarios"));
        let ev = librplus::eval::report::evaluate(
            &a.data,
            &m,
            librplus::eval::report::Split::All,
            &[librplus::pipeline::Method::Libr],
            1,
            &params,
            &physics,
            Some(librplus::eval::report::LibrPlusEval {
                models: std::slice::from_ref(&model),
                v2s: None,
                only: Some(&only),
            }),
            None,
            &|done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            },
        )?;
        bar.finish_and_clear();
        crate::train_v2s::pair_rows(&ev.results, "libr", "librplus")
    };
    let inference_seconds = t_inf.elapsed().as_secs_f64();
    // Aggregate.
    let (sl, sp, n, by_cat) = crate::train_v2s::pair_sums(&rows, "libr", "librplus");
    let nn = n.max(1) as f64;
    let test = json!({
        "format": 1,
        "split": split.name(),
        "scenarios": n,
        "failed": rows.len() - n,
        "libr_tre_mm": sl / nn,
        "librplus_tre_mm": sp / nn,
        "ratio": if sl > 0.0 { sp / sl } else { f64::NAN },
        "by_category": by_cat.iter().map(|(k, v)| (k.clone(), json!({"libr_tre_mm": v.0 / v.2 as f64, "librplus_tre_mm": v.1 / v.2 as f64, "scenarios": v.2}))).collect::<serde_json::Map<_, _>>(),
        "results": rows,
    });
    std::fs::write(
        a.out.join("test.json"),
        serde_json::to_string_pretty(&test)?,
    )?;
    let training = json!({
        "format": 1,
        "log": report.log,
        "best_valid_node_error_mm": report.best_valid_mm,
        "correction_scale": model.config.correction_scale,
        "scaled_valid_node_error_mm": report.scaled_valid_mm,
        "refit_scale_fit": refit_fit,
        "libr_valid_node_error_mm": report.libr_valid_mm,
        "train_samples": report.train_samples,
        "valid_samples": report.valid_samples,
        "train_seconds": report.seconds,
        "libr_solution_seconds": libr_seconds,
        "test_inference_seconds": inference_seconds,
        "total_seconds": t_all.elapsed().as_secs_f64(),
    });
    std::fs::write(
        a.out.join("training.json"),
        serde_json::to_string_pretty(&training)?,
    )?;
    // Final model with full provenance (metrics included).
    let mut prov = provenance.clone();
    prov["metrics"] = json!({
        "valid_node_error_mm": report.best_valid_mm,
        "correction_scale": model.config.correction_scale,
        "libr_valid_node_error_mm": report.libr_valid_mm,
        "test_libr_tre_mm": sl / nn,
        "test_librplus_tre_mm": sp / nn,
        "train_seconds": report.seconds,
    });
    librplus::gcn::io::save_model(&a.out, &model.config, &model.net, prov)?;
    // Loss curves.
    let series =
        |stage: u32, f: &dyn Fn(&librplus::eval::train::EpochLog) -> f64| -> Vec<(f64, f64)> {
            report
                .log
                .iter()
                .filter(|l| l.stage == stage)
                .map(|l| (l.epoch as f64, f(l)))
                .collect()
        };
    let png = librplus::eval::plot::line_chart_png(
        "SR-GCN stage 2 (mesh branch)",
        "epoch",
        "validation node error (mm) / training loss",
        &[
            ("validation node error (mm)".into(), series(2, &|l| l.valid)),
            ("training loss".into(), series(2, &|l| l.train_loss)),
            (
                "LIBR alone (mm)".into(),
                series(2, &|_| report.libr_valid_mm),
            ),
        ],
    )?;
    std::fs::write(a.out.join("loss_stage2.png"), png)?;
    if cfg.bipartite {
        let png = librplus::eval::plot::line_chart_png(
            "SR-GCN stage 1 (bipartite reconstruction)",
            "epoch",
            "loss",
            &[
                ("training".into(), series(1, &|l| l.train_loss)),
                ("validation".into(), series(1, &|l| l.valid)),
            ],
        )?;
        std::fs::write(a.out.join("loss_stage1.png"), png)?;
    }
    println!(
        "split {}: test LIBR {:.3} mm, LIBR+ {:.3} mm (ratio {:.3}) over {n} scenarios; training {:.0} s, LIBR solutions {:.0} s",
        split.name(),
        sl / nn,
        sp / nn,
        sp / sl.max(1e-12),
        report.seconds,
        libr_seconds
    );
    for (k, v) in &by_cat {
        println!(
            "  {k:<12} LIBR {:.3}  LIBR+ {:.3}  ({} scenarios)",
            v.0 / v.2 as f64,
            v.1 / v.2 as f64,
            v.2
        );
    }
    let mut summary = test;
    if let Some(o) = summary.as_object_mut() {
        o.remove("results");
        o.insert("training".into(), training);
    }
    Ok(summary)
}

/// The rows of `test.json` for a diagnostic model (`--diagnostic-truth-neighbours`), which
/// `evaluate` refuses: its test samples link the measured points to the true deformed mesh.
fn diagnostic_test_rows(
    cfg: &librplus::gcn::model::SrGcnConfig,
    cases: &std::collections::BTreeMap<String, librplus::eval::train::GeometryCase>,
    test_items: &[(&librplus::eval::ScenarioData, &str)],
    test_sol: &[Option<librplus::eval::train::LibrSolution>],
    params: &librplus::pipeline::PipelineParams,
    model: &librplus::gcn::io::TrainedModel,
) -> Result<Vec<Value>> {
    use librplus::eval::train as tr;
    use librplus::eval::{node_errors_mm, tre_from_errors};
    let z: Vec<_> = test_items
        .iter()
        .zip(test_sol)
        .map(|((s, g), o)| (*s, *g, o))
        .collect();
    // The paper's leak: the test samples link to the true deformed mesh.
    let test_s = tr::build_samples(cfg, cases, &z, params, true, false)?;
    let plain = librplus::gcn::device::compute();
    let mut graphs = std::collections::BTreeMap::new();
    for (g, gc) in cases {
        graphs.insert(
            g.clone(),
            gc.frame
                .mesh_graphs(cfg, &plain)
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        );
    }
    let mut rows = Vec::new();
    let bar = indicatif::ProgressBar::new(test_items.len() as u64);
    for (((sc, g), sol), sample) in test_items.iter().zip(test_sol).zip(&test_s) {
        bar.inc(1);
        let gc = &cases[*g];
        let (Some(sol), Some(sample)) = (sol, sample) else {
            rows.push(json!({"scenario": sc.id, "category": sc.category, "error": "LIBR failed"}));
            continue;
        };
        let nodes = gc.geo.model.mesh.nodes();
        let truth = (
            &sc.truth.image_to_physical,
            sc.truth.displacement.as_slice(),
        );
        let e_libr = node_errors_mm(nodes, (&sol.transform, &sol.u), truth);
        let u_plus =
            librplus::gcn::infer::correct(model, &gc.frame, &graphs[*g], &sample.data, &sol.u)
                .map_err(|e| anyhow::anyhow!("{}: {e}", sc.id))?;
        let (u_plus, t_plus) = if params.refit_iterations > 0 {
            let r = librplus::pipeline::refit(
                &gc.case,
                &sc.measurements,
                params,
                &u_plus,
                &sol.transform,
                None,
                None,
            )
            .map_err(|e| anyhow::anyhow!("{}: refit: {e}", sc.id))?;
            (r.u, r.image_to_physical)
        } else {
            (u_plus, sol.transform)
        };
        let e_plus = node_errors_mm(nodes, (&t_plus, &u_plus), truth);
        let t_l = tre_from_errors(&e_libr, &gc.geo.surface, &gc.geo.targets);
        let t_p = tre_from_errors(&e_plus, &gc.geo.surface, &gc.geo.targets);
        rows.push(json!({"scenario": sc.id, "geometry": g, "category": sc.category, "libr": t_l, "librplus": t_p}));
    }
    bar.finish_and_clear();
    Ok(rows)
}
