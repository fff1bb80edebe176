//! `librplus discover-study`: detectability curves by one command (generate, discover, score per
//! kind and amplitude scale; see `librplus::eval::discover_study`).

use crate::args::DiscoverStudyArgs;
use anyhow::{Context, Result, bail};
use librplus::eval::discover_score::{DiscoverScore, add_run, truths};
use librplus::eval::discover_study::{STUDY_FORMAT, StudyPoint, markdown, point, summaries};
use librplus::register::physics::EffectKind;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::process::Command;

/// One dataset of the study: its label, the kind hidden (`nothing` for the control), the scale and
/// the `--hidden-effect` given to `generate`.
struct Step {
    label: String,
    kind: String,
    scale: f64,
    hidden: Option<String>,
}

fn steps(a: &DiscoverStudyArgs) -> Result<(Vec<Step>, Vec<f64>)> {
    let kinds: Vec<EffectKind> = match &a.kinds {
        None => EffectKind::ALL
            .into_iter()
            .filter(|k| k.is_carried())
            .collect(),
        Some(list) => list
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(|s| match EffectKind::from_name(s) {
                Some(k) if !k.is_carried() => {
                    bail!("--kinds: {k} is not generated yet")
                }
                Some(k) => Ok(k),
                None => bail!(
                    "--kinds: unknown kind {s:?} (known: {})",
                    EffectKind::known()
                ),
            })
            .collect::<Result<_>>()?,
    };
    let mut scales: Vec<f64> = a
        .scales
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<f64>()
                .ok()
                .filter(|x| *x > 0.0 && *x <= librplus::phantom::hidden::MAX_SCALE)
                .with_context(|| {
                    format!(
                        "--scales: {s:?} is not a number in (0, {}]",
                        librplus::phantom::hidden::MAX_SCALE
                    )
                })
        })
        .collect::<Result<_>>()?;
    scales.sort_by(f64::total_cmp);
    scales.dedup();
    if scales.is_empty() && !kinds.is_empty() {
        bail!("--scales: no scale given");
    }
    let mut out = Vec::new();
    for k in &kinds {
        for &s in &scales {
            out.push(Step {
                label: format!("{}-x{s}", k.name()),
                kind: k.name().to_string(),
                scale: s,
                hidden: Some(format!("{}:scale={s}", k.name())),
            });
        }
    }
    if !a.no_control {
        out.push(Step {
            label: "nothing".into(),
            kind: "nothing".into(),
            scale: 1.0,
            hidden: None,
        });
    }
    if out.is_empty() {
        bail!("--kinds is empty and --no-control is given: nothing to study");
    }
    Ok((out, scales))
}

/// Runs this executable with `args`, its output in `log`; an error names the step and the log.
fn run_self(args: &[String], log: &Path, what: &str) -> Result<()> {
    let exe = std::env::current_exe().context("finding the librplus executable")?;
    let file = std::fs::File::create(log).with_context(|| format!("{}", log.display()))?;
    let status = Command::new(exe)
        .args(args)
        .stdout(file.try_clone()?)
        .stderr(file)
        .status()
        .with_context(|| format!("{what}: starting librplus"))?;
    if !status.success() {
        bail!(
            "{what} failed ({status}); its output is in {}",
            log.display()
        );
    }
    Ok(())
}

pub(crate) fn discover_study(a: &DiscoverStudyArgs) -> Result<()> {
    let (steps, scales) = steps(a)?;
    let (data_dir, report_dir) = (a.out.join("data"), a.out.join("reports"));
    for d in [&data_dir, &report_dir] {
        std::fs::create_dir_all(d).with_context(|| format!("--out: creating {}", d.display()))?;
    }
    let bar = indicatif::ProgressBar::new(2 * steps.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} steps {msg}")
            .expect("static template"),
    );
    let mut all = DiscoverScore::default();
    let mut points: Vec<StudyPoint> = Vec::new();
    for step in &steps {
        let data: PathBuf = data_dir.join(&step.label);
        let report: PathBuf = report_dir.join(&step.label);
        if !data.join("manifest.json").exists() {
            bar.set_message(format!("{}: generating", step.label));
            let mut args: Vec<String> = [
                "generate",
                "--preset",
                &a.preset,
                "--truth",
                "libr",
                "--seed",
                &a.seed.to_string(),
                "--geometries",
                &a.geometries.to_string(),
                "--deformations",
                &a.deformations.to_string(),
                "--scenarios",
                &a.scenarios.to_string(),
                "--out",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect();
            args.push(data.display().to_string());
            if let Some(h) = &step.hidden {
                args.extend(["--hidden-effect".to_string(), h.clone()]);
            }
            run_self(
                &args,
                &data_dir.join(format!("{}.log", step.label)),
                &format!("generating {}", step.label),
            )?;
        }
        bar.inc(1);
        if !report.join("discover.json").exists() {
            bar.set_message(format!("{}: discovering", step.label));
            let args: Vec<String> = vec![
                "discover".into(),
                "--data".into(),
                data.display().to_string(),
                "--out".into(),
                report.display().to_string(),
                "--cache".into(),
                a.out.join("cache").display().to_string(),
            ];
            run_self(
                &args,
                &report_dir.join(format!("{}.log", step.label)),
                &format!("discover on {}", step.label),
            )?;
        }
        bar.inc(1);
        let m = librplus::dataset::read_manifest(&data)
            .with_context(|| format!("{}", data.display()))?;
        let path = report.join("discover.json");
        let run: Value = serde_json::from_str(
            &std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?,
        )
        .with_context(|| format!("{}: not JSON", path.display()))?;
        let t = truths(&m);
        let mut mine = DiscoverScore::default();
        add_run(&mut mine, &step.label, &t, &run).map_err(anyhow::Error::msg)?;
        add_run(&mut all, &step.label, &t, &run).map_err(anyhow::Error::msg)?;
        points.push(point(&step.kind, step.scale, &mine));
    }
    bar.finish_and_clear();
    write_outputs(a, &points, &all, &scales)
}

fn write_outputs(
    a: &DiscoverStudyArgs,
    points: &[StudyPoint],
    all: &DiscoverScore,
    scales: &[f64],
) -> Result<()> {
    let doc = json!({
        "format": STUDY_FORMAT,
        "preset": a.preset,
        "seed": a.seed,
        "geometries": a.geometries,
        "deformations": a.deformations,
        "scenarios": a.scenarios,
        "scales": scales,
        "points": points,
        "kinds": summaries(points),
        "score": all,
    });
    let mut text = serde_json::to_string_pretty(&doc)?;
    text.push('\n');
    librplus::util::write_atomic(&a.out.join("study.json"), text.as_bytes())?;
    let md = format!(
        "# Discovery study (`librplus discover-study`)\n\nPreset {}, seed {}: per dataset {} geometries, {} deformations per geometry and pattern, {} sweeps per cohort; the scale multiplies each kind's drawn amplitude.\n\n{}",
        a.preset,
        a.seed,
        a.geometries,
        a.deformations,
        a.scenarios,
        markdown(points, all)
    );
    librplus::util::write_atomic(&a.out.join("study.md"), md.as_bytes())?;
    for (file, title, y, value) in [
        (
            "named.png",
            "P(named right | amplitude scale)",
            "share of cohorts named right",
            StudyPoint::p_named as fn(&StudyPoint) -> f64,
        ),
        (
            "detectable.png",
            "P(oracle-detectable | amplitude scale)",
            "share of cohorts detectable",
            StudyPoint::p_detectable,
        ),
    ] {
        let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
        for p in points.iter().filter(|p| p.kind != "nothing") {
            match series.iter_mut().find(|s| s.0 == p.kind) {
                Some(s) => s.1.push((p.scale, value(p))),
                None => series.push((p.kind.clone(), vec![(p.scale, value(p))])),
            }
        }
        let png = librplus::eval::plot::line_chart_png(title, "amplitude scale", y, &series)?;
        librplus::util::write_atomic(&a.out.join(file), &png)?;
    }
    if a.json {
        println!("{doc}");
    } else {
        print!("{md}");
    }
    Ok(())
}
