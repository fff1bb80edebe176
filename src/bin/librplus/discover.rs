//! `librplus discover`: the model-discrepancy workflow over a dataset's cohorts, with TRE before
//! and after from the dataset's ground truth (read here, never by the workflow).

use crate::args::DiscoverArgs;
use crate::util::emit;
use anyhow::{Context, Result, bail};
use librplus::discover::{CohortDiscovery, DiscoverParams, Sweep, discover_cohort};
use librplus::pipeline::{Method, Prepared, register};
use librplus::register::physics::EffectKind;
use rayon::prelude::*;
use serde_json::{Value, json};
use std::fmt::Write as _;

/// Format of `discover.json`.
const DISCOVER_FORMAT: u32 = 1;

pub(crate) fn discover(a: &DiscoverArgs) -> Result<()> {
    let m = librplus::eval::open(&a.data).map_err(anyhow::Error::msg)?;
    let cohorts: Vec<&librplus::dataset::DeformationEntry> = if a.cohort.is_empty() {
        m.deformations.iter().collect()
    } else {
        a.cohort
            .iter()
            .map(|c| {
                m.deformations.iter().find(|d| &d.id == c).with_context(|| {
                    format!(
                        "--cohort {c:?}: no deformation with that id in {} (have: {})",
                        a.data.display(),
                        m.deformations
                            .iter()
                            .map(|d| d.id.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    )
                })
            })
            .collect::<Result<_>>()?
    };
    if cohorts.is_empty() {
        bail!(
            "--data {}: the dataset has no deformations",
            a.data.display()
        );
    }
    let mut params = DiscoverParams {
        pipeline: a.libr.params(),
        folds: a.folds,
        max_effects: a.max_effects,
        ..DiscoverParams::default()
    };
    params
        .pipeline
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    if let Some(k) = &a.kinds {
        params.kinds = k
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| {
                EffectKind::from_name(s).with_context(|| {
                    format!(
                        "--kinds: unknown kind {s:?} (known: {})",
                        EffectKind::ALL.map(|k| k.name()).join(", ")
                    )
                })
            })
            .collect::<Result<_>>()?;
        if let Some(k) = params.kinds.iter().find(|k| **k == EffectKind::Nonlinear) {
            bail!("--kinds: {k} cannot be searched yet (the augmented model does not carry it)");
        }
    }
    let cache = a.cache.clone().unwrap_or_else(|| a.data.join("cache"));
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let bar = indicatif::ProgressBar::new(cohorts.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} cohorts {msg}")
            .expect("static template"),
    );
    let mut entries = Vec::new();
    for d in &cohorts {
        bar.set_message(d.id.clone());
        let geo =
            librplus::eval::load_geometry(&a.data, &m, &d.geometry).map_err(anyhow::Error::msg)?;
        let mut scenarios =
            librplus::eval::load_scenarios(&a.data, d).map_err(anyhow::Error::msg)?;
        if a.max_sweeps > 0 {
            scenarios.truncate(a.max_sweeps);
        }
        let sweeps: Vec<Sweep> = scenarios
            .iter()
            .map(|s| Sweep {
                id: s.id.clone(),
                measurements: s.measurements.clone(),
            })
            .collect();
        let id = d.id.clone();
        let progress = |stage: &str, done: usize, total: usize| {
            bar.set_message(format!("{id}: {stage} {done}/{total}"));
        };
        let found = discover_cohort(&geo.model, &sweeps, &params, Some(&cache), &progress)
            .with_context(|| format!("cohort {}", d.id))?;
        // TRE before (plain LIBR) and after (the augmented model), against the truth.
        let tre_of = |regs: &[librplus::pipeline::Registration]| -> f64 {
            let v: Vec<f64> = regs
                .iter()
                .zip(&scenarios)
                .map(|(r, s)| {
                    librplus::eval::tre(
                        geo.model.mesh.nodes(),
                        (&r.image_to_physical, &r.u),
                        (&s.truth.image_to_physical, &s.truth.displacement),
                        &geo.surface,
                        &geo.targets,
                    )
                    .tre_mm
                })
                .collect();
            v.iter().sum::<f64>() / v.len().max(1) as f64
        };
        let before = tre_of(&found.plain);
        let after = if found.physics.is_empty() {
            before
        } else {
            bar.set_message(format!("{}: registering with the augmented model", d.id));
            let case = Prepared::with_physics(
                geo.model.clone(),
                Some(&params.pipeline.libr),
                &found.physics,
                Some(&cache),
            )
            .with_context(|| format!("cohort {}: the augmented model", d.id))?;
            let regs: Vec<librplus::pipeline::Registration> = sweeps
                .par_iter()
                .map(|s| register(&case, &s.measurements, Method::Libr, &params.pipeline))
                .collect::<std::result::Result<_, _>>()
                .with_context(|| {
                    format!("cohort {}: registering with the augmented model", d.id)
                })?;
            tre_of(&regs)
        };
        let dir = a.out.join(&d.id);
        std::fs::create_dir_all(&dir)?;
        write_figures(&dir, &d.id, &geo.model, &found)?;
        let extra: Vec<Value> = found
            .effects
            .iter()
            .map(|e| json!({"uncertainty": e.uncertainty, "evidence": e.evidence}))
            .collect();
        let physics = found.physics.to_value(&extra);
        librplus::util::write_atomic(
            &dir.join("physics.json"),
            serde_json::to_string_pretty(&physics)?.as_bytes(),
        )?;
        entries.push(cohort_json(&d.id, &found, physics, before, after));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let summary = summary_json(&entries);
    let doc = json!({"format": DISCOVER_FORMAT, "cohorts": entries, "summary": summary});
    librplus::util::write_atomic(
        &a.out.join("discover.json"),
        serde_json::to_string_pretty(&doc)?.as_bytes(),
    )?;
    librplus::util::write_atomic(&a.out.join("report.md"), report_md(&doc).as_bytes())?;
    if a.json {
        println!("{doc}");
    } else {
        emit(
            false,
            &json!({"out": a.out.display().to_string(), "summary": summary}),
        );
    }
    Ok(())
}

/// `misfit.vtu` (held-out misfit per block and the named effects on the mesh),
/// `misfit_by_region.png` (before and after per block) and `candidates.png` (every candidate's
/// share of the held-out misfit removed, per round and stage).
fn write_figures(
    dir: &std::path::Path,
    id: &str,
    model: &librplus::register::PreopModel,
    found: &CohortDiscovery,
) -> Result<()> {
    let maps = librplus::discover::maps::discovery_maps(model, found)
        .with_context(|| format!("cohort {id}: maps"))?;
    librplus::mesh::io::write(
        dir.join("misfit.vtu"),
        &maps,
        librplus::mesh::io::WriteOptions::default(),
    )?;
    let groups: Vec<String> = found
        .regions
        .iter()
        .enumerate()
        .map(|(i, r)| format!("{i}: {}", r.region))
        .collect();
    let png = librplus::eval::plot::grouped_bars_png(
        &format!("{id}: held-out misfit per block"),
        "spatial block (held out in turn)",
        "held-out RMS misfit (mm)",
        &groups,
        &[
            (
                "plain LIBR".into(),
                found.regions.iter().map(|r| r.before_mm).collect(),
            ),
            (
                "augmented model".into(),
                found.regions.iter().map(|r| r.after_mm).collect(),
            ),
        ],
    )
    .map_err(anyhow::Error::msg)?;
    librplus::util::write_atomic(&dir.join("misfit_by_region.png"), &png)?;
    let mut kinds: Vec<String> = found.candidates.iter().map(|c| c.kind.clone()).collect();
    kinds.sort();
    kinds.dedup();
    let rounds = found
        .candidates
        .iter()
        .map(|c| c.round)
        .max()
        .map_or(0, |r| r + 1);
    let mut series = Vec::new();
    for round in 0..rounds {
        for (stage, relin) in [("screen", false), ("confirm", true)] {
            let v: Vec<f64> = kinds
                .iter()
                .map(|k| {
                    found
                        .candidates
                        .iter()
                        .find(|c| c.round == round && &c.kind == k && c.relinearized == relin)
                        .map_or(f64::NAN, |c| c.gain)
                })
                .collect();
            if v.iter().any(|x| x.is_finite()) {
                series.push((format!("round {round} {stage}"), v));
            }
        }
    }
    let png = librplus::eval::plot::grouped_bars_png(
        &format!("{id}: candidates (named when confirmed, z > 3, gain > 5 %, ΔBIC < 0)"),
        "effect kind",
        "share of held-out misfit removed",
        &kinds,
        &series,
    )
    .map_err(anyhow::Error::msg)?;
    librplus::util::write_atomic(&dir.join("candidates.png"), &png)?;
    Ok(())
}

fn cohort_json(id: &str, f: &CohortDiscovery, physics: Value, before: f64, after: f64) -> Value {
    let effects: Vec<Value> = physics["effects"].as_array().cloned().unwrap_or_default();
    json!({
        "cohort": id,
        "verdict": f.verdict,
        "effects": effects,
        "heldout_misfit_mm": {"before": f.heldout_before_mm, "after": f.heldout_after_mm},
        "tre_mm": {"before": before, "after": after},
        "noise_floor_mm": f.noise_floor_mm,
        "null_max_mm": f.null_max_mm,
        "beyond_noise": f.beyond_noise,
        "sweeps": f.sweeps,
        "rows": f.rows,
        "regions": f.regions,
        "candidates": f.candidates,
        "timings": f.timings,
    })
}

fn summary_json(entries: &[Value]) -> Value {
    let count = |v: &str| entries.iter().filter(|e| e["verdict"] == v).count();
    let mut named = std::collections::BTreeMap::<String, usize>::new();
    for e in entries {
        for eff in e["effects"].as_array().into_iter().flatten() {
            *named
                .entry(eff["kind"].as_str().unwrap_or("?").to_string())
                .or_default() += 1;
        }
    }
    let mean = |path: [&str; 2]| {
        let v: Vec<f64> = entries
            .iter()
            .filter_map(|e| e[path[0]][path[1]].as_f64())
            .collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    json!({
        "cohorts": entries.len(),
        "verdicts": {"effects": count("effects"), "none": count("none"), "unexplained": count("unexplained")},
        "named": named,
        "heldout_misfit_mm": {"before": mean(["heldout_misfit_mm", "before"]), "after": mean(["heldout_misfit_mm", "after"])},
        "tre_mm": {"before": mean(["tre_mm", "before"]), "after": mean(["tre_mm", "after"])},
    })
}

fn report_md(doc: &Value) -> String {
    let mut s = String::from("# Model discrepancy (`librplus discover`)\n\n");
    let sum = &doc["summary"];
    let _ = writeln!(
        s,
        "{} cohorts: {} with named effects, {} with no missing effect, {} unexplained. Mean held-out misfit {:.2} → {:.2} mm; mean TRE {:.2} → {:.2} mm.\n",
        sum["cohorts"],
        sum["verdicts"]["effects"],
        sum["verdicts"]["none"],
        sum["verdicts"]["unexplained"],
        sum["heldout_misfit_mm"]["before"]
            .as_f64()
            .unwrap_or(f64::NAN),
        sum["heldout_misfit_mm"]["after"]
            .as_f64()
            .unwrap_or(f64::NAN),
        sum["tre_mm"]["before"].as_f64().unwrap_or(f64::NAN),
        sum["tre_mm"]["after"].as_f64().unwrap_or(f64::NAN),
    );
    s.push_str("| cohort | verdict | effects | held-out misfit before → after (mm) | noise floor (mm) | TRE before → after (mm) |\n| --- | --- | --- | --- | --- | --- |\n");
    for c in doc["cohorts"].as_array().into_iter().flatten() {
        let effects: Vec<String> = c["effects"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|e| e["kind"].as_str().unwrap_or("?").to_string())
            .collect();
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.2} → {:.2} | {:.2} | {:.2} → {:.2} |",
            c["cohort"].as_str().unwrap_or("?"),
            c["verdict"].as_str().unwrap_or("?"),
            if effects.is_empty() {
                "–".into()
            } else {
                effects.join(", ")
            },
            c["heldout_misfit_mm"]["before"]
                .as_f64()
                .unwrap_or(f64::NAN),
            c["heldout_misfit_mm"]["after"].as_f64().unwrap_or(f64::NAN),
            c["noise_floor_mm"].as_f64().unwrap_or(f64::NAN),
            c["tre_mm"]["before"].as_f64().unwrap_or(f64::NAN),
            c["tre_mm"]["after"].as_f64().unwrap_or(f64::NAN),
        );
    }
    s.push_str("\n## Candidates per cohort\n\n");
    for c in doc["cohorts"].as_array().into_iter().flatten() {
        let _ = writeln!(
            s,
            "### {}\n\n| round | kind | stage | best parameters | held-out RMS (mm) | gain | signed-rank z | t | ΔBIC | significant |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
            c["cohort"].as_str().unwrap_or("?")
        );
        for r in c["candidates"].as_array().into_iter().flatten() {
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:.3} | {:.3} | {:.2} | {:.2} | {:.1} | {} |",
                r["round"],
                r["kind"].as_str().unwrap_or("?"),
                if r["relinearized"].as_bool().unwrap_or(false) {
                    "confirm"
                } else {
                    "screen"
                },
                r["effect"].as_str().unwrap_or("?"),
                r["heldout_rms_mm"].as_f64().unwrap_or(f64::NAN),
                r["gain"].as_f64().unwrap_or(f64::NAN),
                r["rank_z"].as_f64().unwrap_or(f64::NAN),
                r["t"].as_f64().unwrap_or(f64::NAN),
                r["delta_bic"].as_f64().unwrap_or(f64::NAN),
                r["significant"],
            );
        }
        s.push('\n');
    }
    s
}
