//! The experiments campaign (`librplus experiments`): every split of the full model and every
//! ablation setting as a training run, V2S on the full model's splits, then `RESULTS.md` and
//! `results.json`. The caller runs each training (and shows its figures); a campaign resumes
//! by keeping the runs whose `test.json` is already written.

use super::EvalError;
use super::experiments::{RunOutcome, figures, results_markdown, scenario_results, v2s_figures};
use super::runs::{RunOrigin, RunProgress, create_dir, write_file, write_json};
use super::train::TrainSplit;
use super::train_run::{NetworkOptions, TrainRunOptions};
use crate::dataset::Manifest;
use crate::util::FileError;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What a campaign runs and where it writes.
#[derive(Debug, Clone)]
pub struct CampaignOptions {
    /// Dataset directory.
    pub data: PathBuf,
    /// Output directory: one model directory per run under `runs/`, and the reports.
    pub out: PathBuf,
    /// Splits, comma-separated: random, geo-def, logo (every training geometry), logo:G,
    /// pattern-v, family (every truth family held out in turn), family:NAME.
    pub splits: String,
    /// Table 2 settings run on [`Self::ablation_split`], comma-separated (1-6; empty: none).
    pub ablations: String,
    /// The split the ablations run on.
    pub ablation_split: String,
    /// Every k-th block of five scenarios, in every run.
    pub every: usize,
    /// Seed of every run.
    pub seed: u64,
    /// Training time limit per SR-GCN run (minutes).
    pub minutes: f64,
    /// Keep the runs whose directory already has `test.json`.
    pub resume: bool,
    /// The V2S runs on every split of the full model (None: none).
    pub v2s: Option<V2sRuns>,
    /// How the campaign was started (recorded in the reports).
    pub origin: RunOrigin,
}

/// The V2S runs of a campaign.
#[derive(Debug, Clone)]
pub struct V2sRuns {
    /// Their training options as the user gave them (recorded in `RESULTS.md`).
    pub options: String,
    /// Training time limit per run (minutes).
    pub minutes: f64,
}

/// A campaign under way: its plan and the runs finished so far.
pub struct Campaign {
    o: CampaignOptions,
    m: Manifest,
    /// (split, setting) of every SR-GCN run, the full model's splits first.
    plan: Vec<(String, u32)>,
    started: Instant,
    srgcn: Vec<RunOutcome>,
    v2s: Vec<RunOutcome>,
}

/// Runs one training: given the run's name and options, trains and tests it (writing its model
/// directory). The campaign's own errors reach the caller as `E`.
pub type TrainOne<'a, E> = dyn FnMut(&str, &TrainRunOptions) -> Result<(), E> + 'a;

impl Campaign {
    /// Reads the dataset and plans the runs: each split of `splits` with the full model, then
    /// each setting of `ablations` on the ablation split (unless already planned).
    pub fn plan(o: CampaignOptions) -> Result<Self, EvalError> {
        let started = Instant::now();
        let m = super::open(&o.data)?;
        let mut plan: Vec<(String, u32)> = Vec::new();
        for s in o.splits.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            plan.extend(full_model_splits(&m, s)?.into_iter().map(|s| (s, 6)));
        }
        let ablation_split = o.ablation_split.trim().to_string();
        for t in o
            .ablations
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
        {
            let k: u32 = t
                .parse()
                .ok()
                .filter(|k| (1..=6).contains(k))
                .ok_or_else(|| param(format!("--ablations: {t:?} is not a setting 1-6")))?;
            if !plan.contains(&(ablation_split.clone(), k)) {
                plan.push((ablation_split.clone(), k));
            }
        }
        Ok(Self {
            o,
            m,
            plan,
            started,
            srgcn: Vec::new(),
            v2s: Vec::new(),
        })
    }

    /// The SR-GCN runs planned.
    pub fn runs(&self) -> usize {
        self.plan.len()
    }

    /// Runs every planned SR-GCN training with `base`'s options (the campaign sets the data,
    /// split, model directory, every, seed, setting and time limit) through `train`, and reads
    /// each run's test.
    pub fn train_srgcn<E: From<EvalError>>(
        &mut self,
        base: &TrainRunOptions,
        progress: &dyn RunProgress,
        train: &mut TrainOne<'_, E>,
    ) -> Result<(), E> {
        create_dir(&self.o.out.join("runs"))?;
        progress.log(&format!(
            "experiments: {} runs, about {:.0} minutes of training each",
            self.plan.len(),
            self.o.minutes
        ));
        let mut run = self.base(base, self.o.minutes);
        for (i, (split, setting)) in self.plan.iter().enumerate() {
            let name = format!("{}-ablation{setting}", split.replace(':', "-"));
            let dir = self.o.out.join("runs").join(&name);
            if !(self.o.resume && dir.join("test.json").exists()) {
                progress.log(&format!(
                    "\n[{}/{}] {split}, setting {setting} → {}",
                    i + 1,
                    self.plan.len(),
                    dir.display()
                ));
                run.split = split.clone();
                run.out = dir.clone();
                if let NetworkOptions::Srgcn(s) = &mut run.network {
                    s.ablation = *setting;
                }
                train(&name, &run)?;
            }
            let test = read_test(&dir.join("test.json"))?;
            let png = super::plot::tre_by_category_png(split, &scenario_results(&test))?;
            write_file(
                &self.o.out.join(format!("tre_by_category_{name}.png")),
                &png,
            )?;
            self.srgcn.push(RunOutcome {
                name,
                split: split.clone(),
                ablation: *setting,
                test,
            });
        }
        Ok(())
    }

    /// Runs V2S on every split of the full model (the same test scenarios: same split, seed and
    /// every) with `base`'s options through `train`, and reads each run's test.
    pub fn train_v2s<E: From<EvalError>>(
        &mut self,
        base: &TrainRunOptions,
        progress: &dyn RunProgress,
        train: &mut TrainOne<'_, E>,
    ) -> Result<(), E> {
        let minutes = self.o.v2s.as_ref().map_or(self.o.minutes, |v| v.minutes);
        let mut run = self.base(base, minutes);
        let splits: Vec<String> = self
            .plan
            .iter()
            .filter(|(_, k)| *k == 6)
            .map(|(s, _)| s.clone())
            .collect();
        for (i, split) in splits.iter().enumerate() {
            let name = format!("{}-v2s", split.replace(':', "-"));
            let dir = self.o.out.join("runs").join(&name);
            if !(self.o.resume && dir.join("test.json").exists()) {
                progress.log(&format!(
                    "\n[V2S {}/{}] {split} → {}",
                    i + 1,
                    splits.len(),
                    dir.display()
                ));
                run.split = split.clone();
                run.out = dir.clone();
                train(&name, &run)?;
            }
            self.v2s.push(RunOutcome {
                name,
                split: split.clone(),
                ablation: 0,
                test: read_test(&dir.join("test.json"))?,
            });
        }
        Ok(())
    }

    /// `base` with what the campaign sets in every run: its data, every, seed and time limit.
    fn base(&self, base: &TrainRunOptions, minutes: f64) -> TrainRunOptions {
        let mut run = base.clone();
        run.data = self.o.data.clone();
        run.every = self.o.every;
        run.seed = self.o.seed;
        run.max_minutes = minutes;
        run
    }

    /// Writes `RESULTS.md` and `results.json` from the runs finished; returns `RESULTS.md`.
    pub fn write_reports(&self) -> Result<String, EvalError> {
        let main: Vec<RunOutcome> = self
            .srgcn
            .iter()
            .filter(|r| r.ablation == 6)
            .cloned()
            .collect();
        let ablation_split = self.o.ablation_split.trim();
        let mut abl: Vec<RunOutcome> = self
            .srgcn
            .iter()
            .filter(|r| {
                r.split == ablation_split && self.plan.contains(&(r.split.clone(), r.ablation))
            })
            .filter(|r| {
                self.o
                    .ablations
                    .split(',')
                    .any(|t| t.trim() == r.ablation.to_string())
            })
            .cloned()
            .collect();
        abl.sort_by_key(|r| r.ablation);
        let md = results_markdown(&self.header(), &main, &abl, &self.v2s);
        write_file(&self.o.out.join("RESULTS.md"), md.as_bytes())?;
        let runs: Vec<Value> = self
            .srgcn
            .iter()
            .map(|r| {
                json!({"name": r.name, "split": r.split, "ablation": r.ablation,
                       "figures": figures(&r.test)})
            })
            .chain(self.v2s.iter().map(|r| {
                json!({"name": r.name, "split": r.split, "method": "v2s",
                       "figures": v2s_figures(&r.test)})
            }))
            .collect();
        let results = json!({"format": 1, "command": self.o.origin.command, "runs": runs});
        write_json(&self.o.out.join("results.json"), &results, "")?;
        Ok(md)
    }

    /// `RESULTS.md`'s header: how it was made, from which data, on which machine.
    fn header(&self) -> String {
        let (o, m) = (&self.o, &self.m);
        let v2s = match &o.v2s {
            None => "not run".to_string(),
            Some(v) => format!("{} minutes, options `{}`", v.minutes, v.options),
        };
        format!(
            "# LIBR+ results\n\nMade by one command (commit `{}`):\n\n```\n{}\n```\n\n\
             - Data: `{}` (preset {}, seed {}, parameters {}); {} of five scenarios.\n\
             - Each run is `librplus train` with a training limit of {} minutes (V2S: `librplus \
             train --method v2s`, {}); its model, `training.json` and `test.json` are under \
             `runs/`.\n\
             - Machine: {}, {} threads. Total wall time {:.0} minutes.\n\
             - TRE: mean distance over mesh nodes between the registered and the true deformed \
             liver (physical frame), averaged over the held-out scenarios.\n",
            o.origin.commit,
            o.origin.command,
            o.data.display(),
            m.preset,
            m.seed,
            m.parameters_hash,
            every_block(o.every),
            o.minutes,
            v2s,
            cpu_name(),
            std::thread::available_parallelism().map_or(1, |n| n.get()),
            self.started.elapsed().as_secs_f64() / 60.0
        )
    }
}

/// An option error with its message.
fn param(message: String) -> EvalError {
    EvalError::Parameter(message)
}

/// The full model's splits one entry of `--splits` names: `logo` every training geometry held
/// out in turn, `family` every truth family; another a split of its own (checked).
fn full_model_splits(m: &Manifest, s: &str) -> Result<Vec<String>, EvalError> {
    match s {
        "logo" => {
            let test_geos = m.test_geometries();
            let mut train_geos: Vec<String> = m
                .deformations
                .iter()
                .filter(|d| !test_geos.contains(&d.geometry.as_str()))
                .map(|d| d.geometry.clone())
                .collect();
            train_geos.sort();
            train_geos.dedup();
            Ok(train_geos.iter().map(|g| format!("logo:{g}")).collect())
        }
        "family" => {
            // Every truth family held out in turn (`generate --families`).
            let mut families: Vec<&str> = m.deformations.iter().map(|d| d.family()).collect();
            families.sort();
            families.dedup();
            if families.len() < 2 {
                return Err(param(format!(
                    "--splits family: the dataset has one truth family ({}); generate it with \
                     --families",
                    families.join(", ")
                )));
            }
            Ok(families.iter().map(|f| format!("family:{f}")).collect())
        }
        other => {
            TrainSplit::parse(other).map_err(|e| param(format!("--splits: {e}")))?;
            Ok(vec![other.to_string()])
        }
    }
}

/// A run's `test.json`.
fn read_test(path: &Path) -> Result<Value, EvalError> {
    let text = std::fs::read_to_string(path).map_err(FileError::at("reading", path))?;
    serde_json::from_str(&text).map_err(|e| EvalError::Data(format!("{}: {e}", path.display())))
}

/// The processor's model name (`unknown CPU` where the system does not say).
fn cpu_name() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into())
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
