//! `librplus calibrate-error`: the per-registration error estimate, calibrated on one generated
//! dataset and checked on another.

use crate::args::{CalibrateAbstainArgs, CalibrateErrorArgs};
use crate::register::shared_models;
use crate::util::{git_commit, shell_command};
use anyhow::{Context, Result, bail};
use librplus::eval::calibrate_error::{Sample, check, collect, fit, markdown, samples_csv};
use librplus::pipeline::{Method, PipelineParams};
use serde_json::json;
use std::path::Path;

/// The registration progress bar of calibration runs.
fn registration_bar(what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} {msg} [{bar:30}] {pos}/{len} registrations, {elapsed} (eta {eta})",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

fn registrations(
    what: &str,
    dir: &Path,
    methods: &[Method],
    every: usize,
    params: &PipelineParams,
    models: &[std::sync::Arc<librplus::gcn::io::TrainedModel>],
) -> Result<Vec<Sample>> {
    let bar = registration_bar(what);
    let progress = |done: usize, total: usize| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let (samples, failed) = collect(dir, methods, every, params, models, &progress)
        .map_err(|e| anyhow::anyhow!("{what} ({}): {e}", dir.display()))?;
    bar.finish_and_clear();
    if failed > 0 {
        eprintln!("{what}: {failed} registrations failed and are left out");
    }
    if samples.is_empty() {
        bail!("{what} ({}): no registration succeeded", dir.display());
    }
    Ok(samples)
}

pub(crate) fn calibrate_error(a: &CalibrateErrorArgs) -> Result<()> {
    let mut methods = Vec::new();
    for x in a.methods.split(',') {
        methods.push(match x.trim() {
            "initial" => Method::Initial,
            "rigid" => Method::Rigid,
            "libr" => Method::Libr,
            "librplus" => Method::LibrPlus,
            "adaptive" => Method::Adaptive,
            other => bail!(
                "--methods: unknown method {other:?} (initial, rigid, libr, librplus, adaptive)"
            ),
        });
    }
    let models = if methods.contains(&Method::LibrPlus) {
        shared_models(match &a.model {
            Some(dir) => librplus::gcn::io::load_models_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
            None => librplus::gcn::io::builtin_models()
                .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?,
        })
    } else {
        Vec::new()
    };
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    let mut hashes = Vec::new();
    for d in &a.data {
        let m =
            librplus::eval::open(d).map_err(|e| anyhow::anyhow!("--data {}: {e}", d.display()))?;
        hashes.push(m.parameters_hash);
    }
    if let Some(c) = &a.check {
        let h = librplus::eval::open(c).map_err(|e| anyhow::anyhow!("--check: {e}"))?;
        if hashes.contains(&h.parameters_hash) {
            bail!(
                "--check is a calibration dataset (same parameters hash as a --data): use another seed"
            );
        }
    }
    if let Some(existing) = &a.existing {
        return check_existing(a, existing, &methods, &params, &models);
    }
    let mut cal = Vec::new();
    for d in &a.data {
        cal.extend(registrations(
            "calibration",
            d,
            &methods,
            a.every,
            &params,
            &models,
        )?);
    }
    let names: Vec<String> = a.data.iter().map(|d| d.display().to_string()).collect();
    let provenance = json!({
        "data": names,
        "data_parameters_hash": hashes,
        "every": a.every,
        "registrations": cal.len(),
        "ridge": a.ridge,
        "failure_threshold_mm": a.failure_threshold,
        "sr_gcn": a.model.as_ref().map_or("built-in".to_string(), |p| p.display().to_string()),
        "command": shell_command(),
        "commit": git_commit(),
    });
    let failure = (a.failure_threshold != 0.0).then_some(a.failure_threshold);
    let model = fit(&cal, a.level, a.ridge, failure, provenance)?;
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
    }
    std::fs::write(&a.out, serde_json::to_string_pretty(&model)? + "\n")
        .with_context(|| a.out.display().to_string())?;
    let in_sample = check(&model, &cal);
    let mut md = format!(
        "# Error estimate: calibration on {} ({} registrations)\n\nIn sample:\n\n{}",
        names.join(", "),
        cal.len(),
        markdown(&in_sample, model.level)
    );
    let mut report = json!({
        "format": 1,
        "model": a.out.display().to_string(),
        "calibration": {"data": names, "checks": in_sample},
    });
    let mut held = Vec::new();
    if let Some(c) = &a.check {
        held = registrations(
            "held-out check",
            c,
            &methods,
            a.check_every,
            &params,
            &models,
        )?;
        let out = check(&model, &held);
        md += &format!(
            "\nHeld out ({}, {} registrations, never used for calibration):\n\n{}",
            c.display(),
            held.len(),
            markdown(&out, model.level)
        );
        report["held_out"] = json!({"data": c.display().to_string(), "checks": out});
    }
    let csv = samples_csv(&[("calibration", &cal), ("held_out", &held)]);
    write_report(a, &md, &report, &csv, Some(&a.out))
}

/// Writes `OUT.report.md`, `OUT.report.json` and `OUT.samples.csv` beside `--out`, then prints
/// the report (JSON with `--json`) and what was written (`model` first when one was).
fn write_report(
    a: &CalibrateErrorArgs,
    md: &str,
    report: &serde_json::Value,
    csv: &str,
    model: Option<&Path>,
) -> Result<()> {
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
    }
    let base = a.out.display().to_string();
    let (md_path, json_path) = (format!("{base}.report.md"), format!("{base}.report.json"));
    let csv_path = format!("{base}.samples.csv");
    std::fs::write(&csv_path, csv).with_context(|| csv_path.clone())?;
    std::fs::write(&md_path, md).with_context(|| md_path.clone())?;
    std::fs::write(&json_path, serde_json::to_string_pretty(report)? + "\n")
        .with_context(|| json_path.clone())?;
    if a.json {
        println!("{report}");
    } else {
        print!("{md}");
        let model = model.map_or(String::new(), |m| format!("{}, ", m.display()));
        println!("\nwritten: {model}{md_path}, {json_path}, {csv_path}");
    }
    Ok(())
}

/// `calibrate-error --existing`: an error model checked on new data (every --data), nothing
/// calibrated.
fn check_existing(
    a: &CalibrateErrorArgs,
    existing: &Path,
    methods: &[Method],
    params: &PipelineParams,
    models: &[std::sync::Arc<librplus::gcn::io::TrainedModel>],
) -> Result<()> {
    let text = std::fs::read_to_string(existing)
        .with_context(|| format!("--existing {}", existing.display()))?;
    let model = librplus::register::uncertainty::ErrorModel::from_json(&text)
        .map_err(|e| anyhow::anyhow!("--existing {}: {e}", existing.display()))?;
    let mut samples = Vec::new();
    for d in &a.data {
        samples.extend(registrations("check", d, methods, a.every, params, models)?);
    }
    let names: Vec<String> = a.data.iter().map(|d| d.display().to_string()).collect();
    let out = check(&model, &samples);
    let md = format!(
        "# Error estimate {} checked on {} ({} registrations)\n\n{}",
        existing.display(),
        names.join(", "),
        samples.len(),
        markdown(&out, model.level)
    );
    let report = json!({
        "format": 1,
        "model": existing.display().to_string(),
        "held_out": {"data": names, "checks": out},
    });
    write_report(
        a,
        &md,
        &report,
        &samples_csv(&[("held_out", &samples)]),
        None,
    )
}

/// `librplus calibrate-abstain`: LIBR+'s outside signals on in-family data, the rule at
/// `--alpha`, written as `abstain.json` ([`librplus::gcn::abstain`]).
pub(crate) fn calibrate_abstain(a: &CalibrateAbstainArgs) -> Result<()> {
    let models = shared_models(match &a.model {
        Some(dir) => librplus::gcn::io::load_models_on_device(dir)
            .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
        None => librplus::gcn::io::builtin_models()
            .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?,
    });
    let out = match (&a.out, &a.model) {
        (Some(o), _) => o.clone(),
        (None, Some(m)) => m.clone(),
        (None, None) => bail!("--out: needed with the built-in model (where abstain.json goes)"),
    };
    if !(a.alpha > 0.0 && a.alpha < 1.0) {
        bail!("--alpha must lie in (0, 1), got {}", a.alpha);
    }
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    let mut signals = Vec::new();
    let mut hashes = Vec::new();
    for d in &a.data {
        let m =
            librplus::eval::open(d).map_err(|e| anyhow::anyhow!("--data {}: {e}", d.display()))?;
        hashes.push(m.parameters_hash);
        let bar = registration_bar("LIBR+ without abstention");
        let progress = |done: usize, total: usize| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        };
        let (s, left) = librplus::eval::abstain::collect(d, a.every, &params, &models, &progress)
            .map_err(|e| anyhow::anyhow!("--data {}: {e}", d.display()))?;
        bar.finish_and_clear();
        if left > 0 {
            eprintln!(
                "{}: {left} registrations failed or did not correct and are left out",
                d.display()
            );
        }
        signals.extend(s);
    }
    let mut rule = librplus::gcn::abstain::AbstainRule::calibrate(&signals, a.alpha)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let abstaining = signals.iter().filter(|s| rule.outside(s).is_some()).count();
    let names: Vec<String> = a.data.iter().map(|d| d.display().to_string()).collect();
    rule.provenance = json!({
        "data": names,
        "data_parameters_hash": hashes,
        "every": a.every,
        "registrations": signals.len(),
        "abstaining_on_calibration": abstaining,
        "sr_gcn": a.model.as_ref().map_or("built-in".to_string(), |p| p.display().to_string()),
        "command": shell_command(),
        "commit": git_commit(),
    });
    std::fs::create_dir_all(&out).with_context(|| format!("--out {}", out.display()))?;
    rule.write(&out).map_err(|e| anyhow::anyhow!("{e}"))?;
    println!(
        "{} registrations: abstain when {}{}; {} of them ({:.1} %) would abstain (bound {:.0} %)",
        signals.len(),
        rule.spread_ratio
            .map(|t| format!(
                "the ensemble disagrees by more than {:.0} % of its correction, or ",
                100.0 * t
            ))
            .unwrap_or_default(),
        rule.libr_rms_mm
            .map(|t| format!("LIBR's residual exceeds {t:.2} mm RMS"))
            .unwrap_or_default(),
        abstaining,
        100.0 * abstaining as f64 / signals.len().max(1) as f64,
        100.0 * a.alpha
    );
    println!(
        "written: {}",
        out.join(librplus::gcn::abstain::ABSTAIN_FILE).display()
    );
    Ok(())
}
