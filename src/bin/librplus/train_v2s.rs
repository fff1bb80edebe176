//! `librplus train --method v2s`: the V2S baseline trained and tested on a split, its test
//! scored by `librplus evaluate`'s own code (methods rigid and v2s on the held-out scenarios).

use crate::args::TrainArgs;
use crate::util::{SplitScenarios, bar_style};
use crate::util::{git_commit, shell_command};
use anyhow::Result;
use serde_json::{Value, json};
use std::time::Instant;

/// Trains and tests one V2S model; returns its test.json (without per-scenario rows) and a
/// summary of its training.
pub(crate) fn train_v2s(a: &TrainArgs) -> Result<Value> {
    use librplus::eval::train::v2s::{
        V2sTrainOptions, train_v2s as fit, v2s_geometries, v2s_samples,
    };
    use librplus::eval::train::{TrainSplit, split_scenarios};
    use librplus::v2s::model::V2sConfig;
    let t_all = Instant::now();
    let m = librplus::eval::open(&a.data)?;
    let split = TrainSplit::parse(&a.split).map_err(|e| anyhow::anyhow!("--split: {e}"))?;
    let cfg = V2sConfig::new()
        .with_grid(a.grid)
        .with_width(a.v2s_width)
        .with_depth(a.v2s_depth)
        .with_convs(a.v2s_convs);
    cfg.validate()
        .map_err(|e| anyhow::anyhow!("--grid/--v2s-*: {e}"))?;
    if a.physics.is_some() || a.init.is_some() {
        anyhow::bail!("--physics and --init are SR-GCN options; V2S has no physics prior");
    }
    let params = a.libr.params();
    let sets = split_scenarios(&m, &split, a.seed, a.every, a.validation.get())?;
    eprintln!(
        "V2S, split {}: {} training, {} validation, {} test scenarios; grid {}³",
        split.name(),
        sets.train.len(),
        sets.valid.len(),
        sets.test.len(),
        cfg.grid
    );
    let split_scen = SplitScenarios::load(&a.data, &m, sets.train.iter().chain(&sets.valid))?;
    let geos = split_scen.geometries();
    let spinner = indicatif::ProgressBar::new_spinner()
        .with_message("preparing the grids (signed distance of every liver)");
    spinner.enable_steady_tick(std::time::Duration::from_millis(200));
    let frames = v2s_geometries(&a.data, &m, &geos, &cfg)?;
    spinner.finish_and_clear();
    let pick = |refs: &[(String, usize)]| split_scen.pick(refs);
    let samples = |items: &[(&librplus::eval::ScenarioData, &str)], what: &str| {
        let bar = indicatif::ProgressBar::new(items.len() as u64).with_style(bar_style(what));
        let r = v2s_samples(&frames, items, &params, &|d, _| bar.set_position(d as u64));
        bar.finish_and_clear();
        r.map(|v| v.into_iter().flatten().collect::<Vec<_>>())
            .map_err(anyhow::Error::msg)
    };
    let train_s = samples(&pick(&sets.train), "wICP and grids, training scenarios")?;
    let valid_s = samples(&pick(&sets.valid), "wICP and grids, validation scenarios")?;
    let provenance = json!({
        "command": shell_command(),
        "method": "v2s",
        "data": a.data.display().to_string(),
        "data_preset": m.preset,
        "data_seed": m.seed,
        "data_parameters_hash": m.parameters_hash,
        "split": split.name(),
        "every": a.every,
        "validation": a.validation.get().name(),
        "seed": a.seed,
        "commit": git_commit(),
        "train_scenarios": sets.train.len(),
        "valid_scenarios": sets.valid.len(),
        "test_scenarios": sets.test.len(),
    });
    let opts = V2sTrainOptions {
        config: cfg.clone(),
        seed: a.seed,
        epochs: a.epochs,
        learning_rate: a.v2s_lr,
        patience: a.patience,
        schedule: match a.schedule {
            crate::args::ScheduleArg::Plateau => librplus::eval::train::Schedule::Plateau,
            crate::args::ScheduleArg::Cosine => librplus::eval::train::Schedule::Cosine,
        },
        max_minutes: a.max_minutes,
    };
    let bar = indicatif::ProgressBar::new(0).with_style(bar_style("training V2S"));
    let t_train = Instant::now();
    let progress = |epoch: usize, done: usize, total: usize, loss: f64| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(format!("epoch {epoch} loss {loss:.4}"));
        if done == total {
            bar.suspend(|| {
                eprintln!(
                    "epoch {epoch}: {total} steps, training loss {loss:.5}, {:.0} s",
                    t_train.elapsed().as_secs_f64()
                )
            });
        }
    };
    let report = fit(
        &opts,
        &frames,
        &train_s,
        &valid_s,
        &a.out,
        &provenance,
        &progress,
    )?;
    bar.finish_and_clear();
    for l in &report.log {
        eprintln!(
            "epoch {:>2}: train loss {:.5}, validation {:.4} mm, lr {:.1e}, {:.0} s",
            l.epoch, l.train_loss, l.valid, l.learning_rate, l.seconds
        );
    }
    eprintln!(
        "validation node error {:.4} mm (rigid alone {:.4} mm)",
        report.best_valid_mm, report.rigid_valid_mm
    );
    // Test: rigid and V2S on the held-out scenarios, scored by `librplus evaluate`'s own code.
    let model = std::sync::Arc::new(report.model);
    let t_inf = Instant::now();
    let only: std::collections::BTreeSet<(String, usize)> = sets.test.iter().cloned().collect();
    let bar =
        indicatif::ProgressBar::new(0).with_style(bar_style("rigid and V2S on test scenarios"));
    let ev = librplus::eval::report::evaluate(
        &a.data,
        &m,
        librplus::eval::report::Split::All,
        &[
            librplus::pipeline::Method::Rigid,
            librplus::pipeline::Method::V2s,
        ],
        1,
        &params,
        &librplus::register::physics::Physics::none(),
        Some(librplus::eval::report::LibrPlusEval {
            models: &[],
            v2s: Some(&model),
            only: Some(&only),
        }),
        None,
        &|done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        },
    )?;
    bar.finish_and_clear();
    let inference_seconds = t_inf.elapsed().as_secs_f64();
    let rows = pair_rows(&ev.results, "rigid", "v2s");
    let (sr, sv, n, by_cat) = pair_sums(&rows, "rigid", "v2s");
    let nn = n.max(1) as f64;
    let test = json!({
        "format": 1,
        "method": "v2s",
        "split": split.name(),
        "scenarios": n,
        "failed": rows.len() - n,
        "rigid_tre_mm": sr / nn,
        "v2s_tre_mm": sv / nn,
        "by_category": by_cat.iter().map(|(k, v)| (k.clone(), json!({"rigid_tre_mm": v.0 / v.2 as f64, "v2s_tre_mm": v.1 / v.2 as f64, "scenarios": v.2}))).collect::<serde_json::Map<_, _>>(),
        "results": rows,
    });
    std::fs::write(
        a.out.join("test.json"),
        serde_json::to_string_pretty(&test)?,
    )?;
    let training = json!({
        "format": 1,
        "method": "v2s",
        "grid": cfg.grid,
        "log": report.log,
        "best_valid_node_error_mm": report.best_valid_mm,
        "rigid_valid_node_error_mm": report.rigid_valid_mm,
        "train_samples": report.train_samples,
        "valid_samples": report.valid_samples,
        "train_seconds": report.seconds,
        "test_inference_seconds": inference_seconds,
        "total_seconds": t_all.elapsed().as_secs_f64(),
    });
    std::fs::write(
        a.out.join("training.json"),
        serde_json::to_string_pretty(&training)?,
    )?;
    let mut prov = provenance;
    prov["metrics"] = json!({
        "valid_node_error_mm": report.best_valid_mm,
        "rigid_valid_node_error_mm": report.rigid_valid_mm,
        "test_rigid_tre_mm": sr / nn,
        "test_v2s_tre_mm": sv / nn,
        "train_seconds": report.seconds,
    });
    librplus::v2s::io::save_model(&a.out, &model.config, &model.net, prov)?;
    let series = |f: &dyn Fn(&librplus::eval::train::EpochLog) -> f64| -> Vec<(f64, f64)> {
        report.log.iter().map(|l| (l.epoch as f64, f(l))).collect()
    };
    let png = librplus::eval::plot::line_chart_png(
        "V2S training",
        "epoch",
        "validation node error (mm) / training loss",
        &[
            ("validation node error (mm)".into(), series(&|l| l.valid)),
            ("training loss".into(), series(&|l| l.train_loss)),
            (
                "rigid alone (mm)".into(),
                series(&|_| report.rigid_valid_mm),
            ),
        ],
    )?;
    std::fs::write(a.out.join("loss.png"), png)?;
    println!(
        "V2S, split {}: test wICP {:.3} mm, V2S {:.3} mm over {n} scenarios; training {:.0} s",
        split.name(),
        sr / nn,
        sv / nn,
        report.seconds
    );
    for (k, v) in &by_cat {
        println!(
            "  {k:<12} wICP {:.3}  V2S {:.3}  ({} scenarios)",
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

/// Sums of the TREs of methods `a` and `b` over the rows of [`pair_rows`] where both
/// registered, their count, and the same per category.
pub(crate) type PairSums = (
    f64,
    f64,
    usize,
    std::collections::BTreeMap<String, (f64, f64, usize)>,
);

/// [`PairSums`] of `rows`.
pub(crate) fn pair_sums(rows: &[Value], a: &str, b: &str) -> PairSums {
    let mut by_cat: std::collections::BTreeMap<String, (f64, f64, usize)> = Default::default();
    let (mut sa, mut sb, mut n) = (0.0, 0.0, 0usize);
    for r in rows {
        if let (Some(x), Some(y)) = (r[a]["tre_mm"].as_f64(), r[b]["tre_mm"].as_f64()) {
            sa += x;
            sb += y;
            n += 1;
            let e = by_cat
                .entry(r["category"].as_str().unwrap_or("?").to_string())
                .or_default();
            e.0 += x;
            e.1 += y;
            e.2 += 1;
        }
    }
    (sa, sb, n, by_cat)
}

/// Per scenario the TREs of two methods of an evaluation (keys `a` and `b`), or why it failed.
pub(crate) fn pair_rows(
    results: &[librplus::eval::report::ScenarioResult],
    a: &str,
    b: &str,
) -> Vec<Value> {
    let second: std::collections::BTreeMap<&str, &librplus::eval::report::ScenarioResult> = results
        .iter()
        .filter(|r| r.method == b)
        .map(|r| (r.scenario.as_str(), r))
        .collect();
    results
        .iter()
        .filter(|r| r.method == a)
        .map(|x| {
            let y = second.get(x.scenario.as_str());
            match (&x.tre, y.and_then(|y| y.tre.as_ref())) {
                (Some(tx), Some(ty)) => {
                    json!({"scenario": x.scenario, "geometry": x.geometry, "category": x.category, a: tx, b: ty})
                }
                _ => json!({
                    "scenario": x.scenario,
                    "geometry": x.geometry,
                    "category": x.category,
                    "error": x.error.clone().or_else(|| y.and_then(|y| y.error.clone())).unwrap_or_else(|| format!("{b} failed")),
                }),
            }
        })
        .collect()
}
