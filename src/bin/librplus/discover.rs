//! `librplus discover`: the model-discrepancy workflow over a dataset's cohorts, with TRE before
//! and after from the dataset's ground truth (read here, never by the workflow), or over a
//! user's own mesh and sweeps (`--preop MESH --scenarios DIR`, no TRE).

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
    let params = discover_params(a)?;
    if let Some(preop) = &a.preop {
        return discover_files(a, preop, &params);
    }
    let data = a
        .data
        .as_ref()
        .context("--data DIR or --preop MESH --scenarios DIR")?;
    let m = librplus::eval::open(data)?;
    let cohorts: Vec<&librplus::dataset::DeformationEntry> = if a.cohort.is_empty() {
        m.deformations.iter().collect()
    } else {
        a.cohort
            .iter()
            .map(|c| {
                m.deformations.iter().find(|d| &d.id == c).with_context(|| {
                    format!(
                        "--cohort {c:?}: no deformation with that id in {} (have: {})",
                        data.display(),
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
        bail!("--data {}: the dataset has no deformations", data.display());
    }
    let cache = a.cache.clone().unwrap_or_else(|| data.join("cache"));
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let bar = indicatif::ProgressBar::new(cohorts.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} cohorts {msg}")
            .expect("static template"),
    );
    let mut entries = Vec::new();
    for d in &cohorts {
        bar.set_message(d.id.clone());
        let geo = librplus::eval::load_geometry(data, &m, &d.geometry)?;
        let mut scenarios = librplus::eval::load_scenarios(data, d)?;
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
        let physics = write_cohort(&a.out, &d.id, &geo.model, &found)?;
        entries.push(cohort_json(&d.id, &found, physics, Some((before, after))));
        bar.inc(1);
    }
    bar.finish_and_clear();
    finish(a, entries)
}

/// The workflow's settings from the command line.
fn discover_params(a: &DiscoverArgs) -> Result<DiscoverParams> {
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
                        EffectKind::known()
                    )
                })
            })
            .collect::<Result<_>>()?;
        if let Some(k) = params.kinds.iter().find(|k| !k.is_carried()) {
            bail!("--kinds: {k} cannot be searched yet (the augmented model does not carry it)");
        }
    }
    Ok(params)
}

/// Writes `discover.json` and `report.md`, and prints the summary (or the whole document).
fn finish(a: &DiscoverArgs, entries: Vec<Value>) -> Result<()> {
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

/// `COHORT/physics.json` and the figures; returns the physics document.
fn write_cohort(
    out: &std::path::Path,
    id: &str,
    model: &librplus::register::PreopModel,
    found: &CohortDiscovery,
) -> Result<Value> {
    let dir = out.join(id);
    std::fs::create_dir_all(&dir).with_context(|| format!("--out {}", dir.display()))?;
    write_figures(&dir, id, model, found)?;
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
    Ok(physics)
}

/// `discover --preop MESH --scenarios DIR`: a user's own mesh and sweeps, one cohort, no TRE.
fn discover_files(
    a: &DiscoverArgs,
    preop: &std::path::Path,
    params: &DiscoverParams,
) -> Result<()> {
    use librplus::register::{MeasuredKind, Measurements};
    let dir = a
        .scenarios
        .as_ref()
        .context("--preop needs --scenarios DIR")?;
    let file = librplus::mesh::io::read(preop, a.unit)
        .with_context(|| format!("--preop {}", preop.display()))?;
    let model = librplus::input::preop_model_from_mesh(preop, &file, a.unit, a.edge_mm)?;
    let mut entries: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("--scenarios {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            !p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with('.'))
        })
        .collect();
    entries.sort();
    let read = |p: &std::path::Path, kind: MeasuredKind, m: &mut Measurements| -> Result<()> {
        let pts = librplus::input::read_points(p, a.unit)
            .map_err(|e| anyhow::anyhow!("--scenarios: {e}"))?;
        m.kind.extend(std::iter::repeat_n(kind, pts.len()));
        m.points.extend(pts);
        Ok(())
    };
    let mut sweeps = Vec::new();
    for p in &entries {
        let id = p
            .file_stem()
            .and_then(|n| n.to_str())
            .unwrap_or("?")
            .to_string();
        let mut m = Measurements {
            points: Vec::new(),
            kind: Vec::new(),
            feature: Vec::new(),
            initial_alignment: None,
        };
        if p.is_dir() {
            let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(p)
                .with_context(|| format!("--scenarios: {}", p.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .collect();
            files.sort();
            let stem = |f: &std::path::Path| {
                f.file_stem()
                    .and_then(|n| n.to_str())
                    .unwrap_or("")
                    .to_ascii_lowercase()
            };
            let surface: Vec<&std::path::PathBuf> =
                files.iter().filter(|f| stem(f) == "surface").collect();
            if surface.len() != 1 {
                bail!(
                    "--scenarios: sweep folder {} needs exactly one surface.* point file (found {})",
                    p.display(),
                    surface.len()
                );
            }
            read(surface[0], MeasuredKind::Surface, &mut m)?;
            for f in &files {
                let s = stem(f);
                if s.starts_with("ultrasound") {
                    read(f, MeasuredKind::PosteriorContour, &mut m)?;
                } else if s.starts_with("vessel") {
                    read(f, MeasuredKind::Vessel, &mut m)?;
                } else if f.file_name().is_some_and(|n| n == "initial_alignment.json") {
                    let text = std::fs::read_to_string(f)
                        .with_context(|| format!("--scenarios: {}", f.display()))?;
                    let mut t: librplus::mesh::rigid::Rigid = serde_json::from_str(&text)
                        .with_context(|| format!("--scenarios: {}: expected {{\"rotation\": [[3×3]], \"translation\": [3]}}", f.display()))?;
                    t.translation = t.translation.map(|x| x * a.unit.to_mm());
                    m.initial_alignment = Some(t);
                }
            }
        } else {
            read(p, MeasuredKind::Surface, &mut m)?;
        }
        let measurements = librplus::register::Checked::new(m)
            .with_context(|| format!("--scenarios: sweep {id}"))?;
        sweeps.push(Sweep { id, measurements });
    }
    if sweeps.len() < 2 {
        bail!(
            "--scenarios {}: {} sweeps; a cohort needs at least 2 (one point file or folder per sweep)",
            dir.display(),
            sweeps.len()
        );
    }
    if a.max_sweeps > 0 {
        sweeps.truncate(a.max_sweeps);
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("--out {}", a.out.display()))?;
    let cache = a.cache.clone().unwrap_or_else(|| {
        preop
            .parent()
            .unwrap_or(std::path::Path::new("."))
            .join("cache")
    });
    let id = dir
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("cohort")
        .to_string();
    let bar = indicatif::ProgressBar::new_spinner();
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let progress = |stage: &str, done: usize, total: usize| {
        bar.set_message(format!("{id}: {stage} {done}/{total}"));
    };
    let found = discover_cohort(&model, &sweeps, params, Some(&cache), &progress)
        .with_context(|| format!("cohort {id}"))?;
    bar.finish_and_clear();
    let physics = write_cohort(&a.out, &id, &model, &found)?;
    finish(a, vec![cohort_json(&id, &found, physics, None)])
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
    )?;
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
    )?;
    librplus::util::write_atomic(&dir.join("candidates.png"), &png)?;
    Ok(())
}

/// One cohort's entry of `discover.json`; `tre` (before, after) only where truth exists.
fn cohort_json(id: &str, f: &CohortDiscovery, physics: Value, tre: Option<(f64, f64)>) -> Value {
    let effects: Vec<Value> = physics["effects"].as_array().cloned().unwrap_or_default();
    let mut v = json!({
        "cohort": id,
        "verdict": f.verdict,
        "effects": effects,
        "heldout_misfit_mm": {"before": f.heldout_before_mm, "after": f.heldout_after_mm},
        "noise_floor_mm": f.noise_floor_mm,
        "null_max_mm": f.null_max_mm,
        "beyond_noise": f.beyond_noise,
        "heldout_at_lambda_mm": f.heldout_at_lambda_mm,
        "richer_loads": f.richer_loads,
        "sweeps": f.sweeps,
        "rows": f.rows,
        "regions": f.regions,
        "candidates": f.candidates,
        "timings": f.timings,
    });
    if let Some((before, after)) = tre {
        v["tre_mm"] = json!({"before": before, "after": after});
    }
    v
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
    // The mean over the cohorts that have the figure (null where none has: no truth, no TRE).
    let mean = |path: [&str; 2]| -> Value {
        let v: Vec<f64> = entries
            .iter()
            .filter_map(|e| e[path[0]][path[1]].as_f64())
            .collect();
        if v.is_empty() {
            Value::Null
        } else {
            json!(v.iter().sum::<f64>() / v.len() as f64)
        }
    };
    json!({
        "cohorts": entries.len(),
        "verdicts": {"effects": count("effects"), "none": count("none"), "refine-loads": count("refine-loads"), "unexplained": count("unexplained")},
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
        "{} cohorts: {} with named effects, {} with no missing effect, {} where finer surface loads explain the misfit, {} unexplained. Mean held-out misfit {:.2} → {:.2} mm; mean TRE {:.2} → {:.2} mm.\n",
        sum["cohorts"],
        sum["verdicts"]["effects"],
        sum["verdicts"]["none"],
        sum["verdicts"]["refine-loads"],
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

/// `librplus discover-score`: every `discover` report against its dataset's truth.
pub(crate) fn discover_score(a: &crate::args::DiscoverScoreArgs) -> Result<()> {
    use librplus::eval::discover_score::{DiscoverScore, add_run, markdown, truths};
    if a.data.len() != a.report.len() {
        bail!(
            "--data is given {} times and --report {} times: each dataset needs its report",
            a.data.len(),
            a.report.len()
        );
    }
    let mut score = DiscoverScore::default();
    for (data, report) in a.data.iter().zip(&a.report) {
        let m = librplus::dataset::read_manifest(data)
            .with_context(|| format!("--data {}", data.display()))?;
        let path = report.join("discover.json");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("--report {}: reading discover.json", report.display()))?;
        let run: Value =
            serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        add_run(&mut score, &data.display().to_string(), &truths(&m), &run)
            .map_err(anyhow::Error::msg)?;
    }
    let md = markdown(&score);
    let json_path = a.out.with_extension("json");
    let md_path = a.out.with_extension("md");
    let mut text = serde_json::to_string_pretty(&score)?;
    text.push('\n');
    librplus::util::write_atomic(&json_path, text.as_bytes())
        .with_context(|| format!("--out {}", json_path.display()))?;
    librplus::util::write_atomic(&md_path, md.as_bytes())
        .with_context(|| format!("--out {}", md_path.display()))?;
    if a.json {
        println!("{}", serde_json::to_string(&score)?);
    } else {
        print!("{md}");
    }
    Ok(())
}
