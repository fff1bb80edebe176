//! `librplus experiments`: every split and ablation as `train` runs, then RESULTS.md.

use crate::args::{ExperimentsArgs, TrainArgs, TrainOnly};
use crate::train::{print_outcome, train_options};
use crate::util::Bars;
use anyhow::{Context, Result, bail};
use clap::Parser;
use librplus::eval::campaign::{Campaign, CampaignOptions, V2sRuns};
use librplus::eval::train_run::{TrainRunOptions, train_and_test};

/// `librplus experiments`: every split and ablation as `librplus train` runs, then the reports.
pub(crate) fn experiments(a: &ExperimentsArgs) -> Result<()> {
    let bars = Bars::default();
    let mut campaign = Campaign::plan(CampaignOptions {
        data: a.data.clone(),
        out: a.out.clone(),
        splits: a.splits.clone(),
        ablations: a.ablations.clone(),
        ablation_split: a.ablation_split.clone(),
        every: a.every,
        seed: a.seed,
        minutes: a.minutes,
        resume: a.resume,
        v2s: (!a.no_v2s).then(|| V2sRuns {
            options: a.v2s_args.clone(),
            minutes: a.v2s_minutes.unwrap_or(a.minutes),
        }),
        origin: crate::util::origin(),
    })?;
    let base = train_options(&srgcn_run_args(&a.train_args)?);
    campaign.train_srgcn(&base, &bars, &mut |name, run| run_one(name, run, &bars))?;
    if !a.no_v2s {
        // V2S on every split of the full model (the same test scenarios: same split, seed, every).
        let extra = a.v2s_args.split_whitespace().map(String::from);
        let args = parse_run_args(&["--method", "v2s"], extra)
            .map_err(|e| anyhow::anyhow!("--v2s-args: {e}"))?;
        campaign.train_v2s(&train_options(&args), &bars, &mut |name, run| {
            run_one(name, run, &bars)
        })?;
    }
    let md = campaign.write_reports()?;
    println!("{md}");
    eprintln!("wrote {}", a.out.join("RESULTS.md").display());
    Ok(())
}

/// Trains and tests one run of the campaign and prints its test figures.
fn run_one(name: &str, run: &TrainRunOptions, bars: &Bars) -> Result<()> {
    let outcome = train_and_test(run, bars).with_context(|| format!("run {name}"))?;
    print_outcome(&outcome);
    Ok(())
}

/// The user's training options (`--train-args`), read once by `train`'s own parser; what the
/// campaign sets itself cannot be given.
fn srgcn_run_args(train_args: &str) -> Result<TrainArgs> {
    let extra: Vec<String> = train_args.split_whitespace().map(String::from).collect();
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
    parse_run_args(&[], extra).map_err(|e| anyhow::anyhow!("--train-args: {e}"))
}

/// `train`'s arguments from `fixed` and `extra` (`train`'s parser requires `--data` and `--out`:
/// placeholders, which the campaign replaces in every run).
fn parse_run_args(
    fixed: &[&str],
    extra: impl IntoIterator<Item = String>,
) -> std::result::Result<TrainArgs, clap::Error> {
    let args = ["train", "--data", "-", "--out", "-"]
        .iter()
        .chain(fixed)
        .map(|s| s.to_string())
        .chain(extra);
    TrainOnly::try_parse_from(args).map(|t| t.args)
}
