//! `librplus experiments`: every split and ablation as `train` runs, then RESULTS.md.

use crate::args::{ExperimentsArgs, TrainOnly};
use crate::train::train;
use crate::util::{git_commit, shell_command};
use anyhow::{Context, Result, bail};
use clap::Parser;
use serde_json::{Value, json};
use std::time::Instant;

/// `librplus experiments`: every split and ablation as `librplus train` runs, then the reports.
pub(crate) fn experiments(a: &ExperimentsArgs) -> Result<()> {
    use librplus::eval::experiments::{RunOutcome, results_markdown, scenario_results};
    let t0 = Instant::now();
    let m = librplus::eval::open(&a.data)?;
    let test_geos = m.test_geometries();
    let mut train_geos: Vec<String> = m
        .deformations
        .iter()
        .filter(|d| !test_geos.contains(&d.geometry.as_str()))
        .map(|d| d.geometry.clone())
        .collect();
    train_geos.sort();
    train_geos.dedup();
    // (split, setting) of every run, the full model's splits first.
    let mut plan: Vec<(String, u32)> = Vec::new();
    for s in a.splits.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        if s == "logo" {
            plan.extend(train_geos.iter().map(|g| (format!("logo:{g}"), 6)));
        } else if s == "family" {
            // Every truth family held out in turn (`generate --families`).
            let mut families: Vec<&str> = m.deformations.iter().map(|d| d.family()).collect();
            families.sort();
            families.dedup();
            if families.len() < 2 {
                bail!(
                    "--splits family: the dataset has one truth family ({}); generate it with \
                     --families",
                    families.join(", ")
                );
            }
            plan.extend(families.iter().map(|f| (format!("family:{f}"), 6)));
        } else {
            librplus::eval::train::TrainSplit::parse(s)
                .map_err(|e| anyhow::anyhow!("--splits: {e}"))?;
            plan.push((s.to_string(), 6));
        }
    }
    let ablation_split = a.ablation_split.trim().to_string();
    for t in a
        .ablations
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
    {
        let k: u32 = t
            .parse()
            .ok()
            .filter(|k| (1..=6).contains(k))
            .ok_or_else(|| anyhow::anyhow!("--ablations: {t:?} is not a setting 1-6"))?;
        if !plan.contains(&(ablation_split.clone(), k)) {
            plan.push((ablation_split.clone(), k));
        }
    }
    let extra: Vec<String> = a.train_args.split_whitespace().map(String::from).collect();
    for reserved in [
        "--data",
        "--split",
        "--out",
        "--every",
        "--seed",
        "--ablation",
        "--max-minutes",
    ] {
        if extra
            .iter()
            .any(|x| x == reserved || x.starts_with(&format!("{reserved}=")))
        {
            bail!("--train-args: {reserved} is set by `experiments` itself");
        }
    }
    // The user's training options, read once by `train`'s own parser (which requires `--data`
    // and `--out`: placeholders, replaced below with every field this command sets per run).
    let mut run_args = TrainOnly::try_parse_from(
        ["train", "--data", "-", "--out", "-"]
            .into_iter()
            .map(String::from)
            .chain(extra.iter().cloned()),
    )
    .map_err(|e| anyhow::anyhow!("--train-args: {e}"))?
    .args;
    run_args.data = a.data.clone();
    run_args.every = a.every;
    run_args.seed = a.seed;
    run_args.max_minutes = a.minutes;
    std::fs::create_dir_all(a.out.join("runs")).with_context(|| a.out.display().to_string())?;
    eprintln!(
        "experiments: {} runs, about {:.0} minutes of training each",
        plan.len(),
        a.minutes
    );
    let mut outcomes: Vec<RunOutcome> = Vec::new();
    for (i, (split, setting)) in plan.iter().enumerate() {
        let name = format!("{}-ablation{setting}", split.replace(':', "-"));
        let dir = a.out.join("runs").join(&name);
        let test_path = dir.join("test.json");
        if !(a.resume && test_path.exists()) {
            eprintln!(
                "\n[{}/{}] {split}, setting {setting} → {}",
                i + 1,
                plan.len(),
                dir.display()
            );
            run_args.split = split.clone();
            run_args.out = dir.clone();
            run_args.ablation = *setting;
            train(&run_args).with_context(|| format!("run {name}"))?;
        }
        let test: Value = serde_json::from_str(
            &std::fs::read_to_string(&test_path)
                .with_context(|| test_path.display().to_string())?,
        )
        .with_context(|| test_path.display().to_string())?;
        let png = librplus::eval::plot::tre_by_category_png(split, &scenario_results(&test))?;
        std::fs::write(a.out.join(format!("tre_by_category_{name}.png")), png)?;
        outcomes.push(RunOutcome {
            name,
            split: split.clone(),
            ablation: *setting,
            test,
        });
    }
    // V2S on every split of the full model (the same test scenarios: same split, seed, every).
    let mut v2s_outcomes: Vec<RunOutcome> = Vec::new();
    if !a.no_v2s {
        let v2s_extra: Vec<String> = a.v2s_args.split_whitespace().map(String::from).collect();
        let mut v2s_args = TrainOnly::try_parse_from(
            ["train", "--data", "-", "--out", "-", "--method", "v2s"]
                .into_iter()
                .map(String::from)
                .chain(v2s_extra),
        )
        .map_err(|e| anyhow::anyhow!("--v2s-args: {e}"))?
        .args;
        v2s_args.data = a.data.clone();
        v2s_args.every = a.every;
        v2s_args.seed = a.seed;
        v2s_args.max_minutes = a.v2s_minutes.unwrap_or(a.minutes);
        let splits: Vec<String> = plan
            .iter()
            .filter(|(_, k)| *k == 6)
            .map(|(s, _)| s.clone())
            .collect();
        for (i, split) in splits.iter().enumerate() {
            let name = format!("{}-v2s", split.replace(':', "-"));
            let dir = a.out.join("runs").join(&name);
            let test_path = dir.join("test.json");
            if !(a.resume && test_path.exists()) {
                eprintln!(
                    "\n[V2S {}/{}] {split} → {}",
                    i + 1,
                    splits.len(),
                    dir.display()
                );
                v2s_args.split = split.clone();
                v2s_args.out = dir.clone();
                train(&v2s_args).with_context(|| format!("run {name}"))?;
            }
            let test: Value = serde_json::from_str(
                &std::fs::read_to_string(&test_path)
                    .with_context(|| test_path.display().to_string())?,
            )
            .with_context(|| test_path.display().to_string())?;
            v2s_outcomes.push(RunOutcome {
                name,
                split: split.clone(),
                ablation: 0,
                test,
            });
        }
    }
    let main: Vec<RunOutcome> = outcomes
        .iter()
        .filter(|r| r.ablation == 6)
        .cloned()
        .collect();
    let mut abl: Vec<RunOutcome> = outcomes
        .iter()
        .filter(|r| r.split == ablation_split && plan.contains(&(r.split.clone(), r.ablation)))
        .filter(|r| {
            a.ablations
                .split(',')
                .any(|t| t.trim() == r.ablation.to_string())
        })
        .cloned()
        .collect();
    abl.sort_by_key(|r| r.ablation);
    let command = shell_command();
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let header = format!(
        "# LIBR+ results\n\nMade by one command (commit `{}`):\n\n```\n{}\n```\n\n\
         - Data: `{}` (preset {}, seed {}, parameters {}); {} of five scenarios.\n\
         - Each run is `librplus train` with a training limit of {} minutes (V2S: `librplus \
         train --method v2s`, {}); its model, `training.json` and `test.json` are under \
         `runs/`.\n\
         - Machine: {cpu}, {threads} threads. Total wall time {:.0} minutes.\n\
         - TRE: mean distance over mesh nodes between the registered and the true deformed \
         liver (physical frame), averaged over the held-out scenarios.\n",
        git_commit(),
        command,
        a.data.display(),
        m.preset,
        m.seed,
        m.parameters_hash,
        every_block(a.every),
        a.minutes,
        if a.no_v2s {
            "not run".to_string()
        } else {
            format!(
                "{} minutes, options `{}`",
                a.v2s_minutes.unwrap_or(a.minutes),
                a.v2s_args
            )
        },
        t0.elapsed().as_secs_f64() / 60.0
    );
    let md = results_markdown(&header, &main, &abl, &v2s_outcomes);
    std::fs::write(a.out.join("RESULTS.md"), &md)?;
    let runs: Vec<Value> = outcomes
        .iter()
        .map(|r| {
            json!({"name": r.name, "split": r.split, "ablation": r.ablation,
                   "figures": librplus::eval::experiments::figures(&r.test)})
        })
        .chain(v2s_outcomes.iter().map(|r| {
            json!({"name": r.name, "split": r.split, "method": "v2s",
                   "figures": librplus::eval::experiments::v2s_figures(&r.test)})
        }))
        .collect();
    std::fs::write(
        a.out.join("results.json"),
        serde_json::to_string_pretty(&json!({"format": 1, "command": command, "runs": runs}))?,
    )?;
    println!("{md}");
    eprintln!("wrote {}", a.out.join("RESULTS.md").display());
    Ok(())
}

/// "every block", "every 2nd block", "every 8th block", ...
fn every_block(k: usize) -> String {
    let suffix = match (k % 10, k % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    if k <= 1 {
        "every block".into()
    } else {
        format!("every {k}{suffix} block")
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn every_block_reads_as_english() {
        let got: Vec<String> = [1, 2, 3, 4, 8, 11, 12, 21, 22, 113]
            .into_iter()
            .map(super::every_block)
            .collect();
        assert_eq!(
            got,
            [
                "every block",
                "every 2nd block",
                "every 3rd block",
                "every 4th block",
                "every 8th block",
                "every 11th block",
                "every 12th block",
                "every 21st block",
                "every 22nd block",
                "every 113th block"
            ]
        );
    }
}
