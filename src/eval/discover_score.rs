//! Scoring discovery against the truth of hidden-effect datasets (`librplus discover-score`): per
//! cohort, what was hidden (the effects whose role is `hidden`), what carries it (roles `carrier`
//! and `carried`: naming them is right, not required), whether the oracle could see it
//! ([`crate::dataset::Detectability`]) and what `discover` named; per hidden kind and
//! detectability, how often the name was right, and the confusion matrix of hidden against
//! named. Evaluation only: discovery itself never reads any of this.

use crate::dataset::Manifest;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};

/// Format of the score file.
pub const SCORE_FORMAT: u32 = 1;

/// What a cohort's truth holds, for scoring.
#[derive(Debug, Clone, PartialEq)]
pub struct CohortTruth {
    /// Deformation id.
    pub cohort: String,
    /// Kinds hidden.
    pub hidden: BTreeSet<String>,
    /// Kinds that carry them or that they carry.
    pub carriers: BTreeSet<String>,
    /// The oracle's verdict, where recorded.
    pub detectable: Option<bool>,
    /// The oracle's statistic, where recorded.
    pub statistic: Option<f64>,
}

/// How a cohort's naming compares with its truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Outcome {
    /// Every hidden kind named, nothing outside the truth (nothing hidden: nothing named).
    Right,
    /// Some hidden kinds named, none outside the truth.
    Partial,
    /// A kind named that the truth does not hold.
    Wrong,
    /// Something hidden, nothing named.
    Missed,
}

/// The outcome of naming `named` where `hidden` was hidden and `carriers` carry it.
pub fn outcome(
    hidden: &BTreeSet<String>,
    carriers: &BTreeSet<String>,
    named: &BTreeSet<String>,
) -> Outcome {
    if named
        .iter()
        .any(|k| !hidden.contains(k) && !carriers.contains(k))
    {
        Outcome::Wrong
    } else if hidden.is_subset(named) {
        Outcome::Right
    } else if named.is_empty() {
        Outcome::Missed
    } else {
        Outcome::Partial
    }
}

/// One cohort scored.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CohortScore {
    /// Dataset (as given) and deformation id.
    pub dataset: String,
    /// Cohort.
    pub cohort: String,
    /// Kinds hidden.
    pub hidden: Vec<String>,
    /// Kinds carrying them.
    pub carriers: Vec<String>,
    /// Oracle detectability (null where not recorded).
    pub detectable: Option<bool>,
    /// Oracle statistic.
    pub statistic: Option<f64>,
    /// `discover`'s verdict.
    pub verdict: String,
    /// Kinds named.
    pub named: Vec<String>,
    /// The outcome.
    pub outcome: Outcome,
    /// TRE before and after (mm), where `discover` reported it.
    pub tre_mm: Option<[f64; 2]>,
}

/// Counts of outcomes.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct Tally {
    /// Cohorts.
    pub cohorts: usize,
    /// Right.
    pub right: usize,
    /// Partial.
    pub partial: usize,
    /// Wrong.
    pub wrong: usize,
    /// Missed.
    pub missed: usize,
}

impl Tally {
    fn add(&mut self, o: Outcome) {
        self.cohorts += 1;
        match o {
            Outcome::Right => self.right += 1,
            Outcome::Partial => self.partial += 1,
            Outcome::Wrong => self.wrong += 1,
            Outcome::Missed => self.missed += 1,
        }
    }
}

/// A whole score.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DiscoverScore {
    /// [`SCORE_FORMAT`].
    pub format: u32,
    /// Per cohort.
    pub cohorts: Vec<CohortScore>,
    /// Per hidden kinds (`+`-joined, `nothing`) and oracle class (`detectable`,
    /// `undetectable`, `unknown`): the outcomes.
    pub by_hidden: BTreeMap<String, BTreeMap<String, Tally>>,
    /// Rows: hidden kinds with their oracle class; columns: what was named (`+`-joined kinds,
    /// or the verdict `none` / `unexplained`); cohort counts.
    pub confusion: BTreeMap<String, BTreeMap<String, usize>>,
}

/// The truths of a dataset's deformations (none where nothing is recorded as hidden).
pub fn truths(m: &Manifest) -> Vec<CohortTruth> {
    m.deformations
        .iter()
        .map(|d| {
            let mut hidden = BTreeSet::new();
            let mut carriers = BTreeSet::new();
            for e in d
                .hidden_effects
                .as_ref()
                .and_then(|v| v["effects"].as_array())
                .into_iter()
                .flatten()
            {
                let kind = e["kind"].as_str().unwrap_or("?").to_string();
                match e["role"].as_str().unwrap_or("hidden") {
                    "hidden" => hidden.insert(kind),
                    _ => carriers.insert(kind),
                };
            }
            CohortTruth {
                cohort: d.id.clone(),
                hidden,
                carriers,
                detectable: d.detectability.as_ref().map(|x| x.detectable),
                statistic: d.detectability.as_ref().map(|x| x.statistic),
            }
        })
        .collect()
}

fn label(kinds: &BTreeSet<String>, empty: &str) -> String {
    if kinds.is_empty() {
        empty.to_string()
    } else {
        kinds.iter().cloned().collect::<Vec<_>>().join("+")
    }
}

/// Scores the cohorts of one `discover.json` value (`dataset` names it in the output) against
/// the truths, adding to `score`. A cohort the truths do not hold is an error naming it.
pub fn add_run(
    score: &mut DiscoverScore,
    dataset: &str,
    truths: &[CohortTruth],
    discover: &Value,
) -> Result<(), String> {
    let cohorts = discover["cohorts"]
        .as_array()
        .ok_or_else(|| format!("{dataset}: discover.json has no `cohorts` array"))?;
    for c in cohorts {
        let id = c["cohort"]
            .as_str()
            .ok_or_else(|| format!("{dataset}: a cohort without an id"))?;
        let t = truths.iter().find(|t| t.cohort == id).ok_or_else(|| {
            format!("{dataset}: cohort {id:?} is not a deformation of the dataset")
        })?;
        let verdict = c["verdict"].as_str().unwrap_or("?").to_string();
        let named: BTreeSet<String> = c["effects"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|e| e["kind"].as_str().map(str::to_string))
            .collect();
        let o = outcome(&t.hidden, &t.carriers, &named);
        let class = match t.detectable {
            Some(true) => "detectable",
            Some(false) => "undetectable",
            None => "unknown",
        };
        let row = label(&t.hidden, "nothing");
        score
            .by_hidden
            .entry(row.clone())
            .or_default()
            .entry(class.to_string())
            .or_default()
            .add(o);
        let column = label(&named, &verdict);
        *score
            .confusion
            .entry(format!("{row} ({class})"))
            .or_default()
            .entry(column)
            .or_default() += 1;
        let tre = match (
            c["tre_mm"]["before"].as_f64(),
            c["tre_mm"]["after"].as_f64(),
        ) {
            (Some(b), Some(a)) => Some([b, a]),
            _ => None,
        };
        score.cohorts.push(CohortScore {
            dataset: dataset.to_string(),
            cohort: id.to_string(),
            hidden: t.hidden.iter().cloned().collect(),
            carriers: t.carriers.iter().cloned().collect(),
            detectable: t.detectable,
            statistic: t.statistic,
            verdict,
            named: named.into_iter().collect(),
            outcome: o,
            tre_mm: tre,
        });
    }
    Ok(())
}

impl Default for DiscoverScore {
    fn default() -> Self {
        Self {
            format: SCORE_FORMAT,
            cohorts: Vec::new(),
            by_hidden: BTreeMap::new(),
            confusion: BTreeMap::new(),
        }
    }
}

/// The score as Markdown: outcomes per hidden kind and oracle class, then the confusion matrix.
pub fn markdown(s: &DiscoverScore) -> String {
    let mut out = String::from(
        "| hidden | oracle | cohorts | right | partial | wrong | missed |\n| --- | --- | --- | --- | --- | --- | --- |\n",
    );
    for (row, classes) in &s.by_hidden {
        for (class, t) in classes {
            out.push_str(&format!(
                "| {row} | {class} | {} | {} | {} | {} | {} |\n",
                t.cohorts, t.right, t.partial, t.wrong, t.missed
            ));
        }
    }
    let columns: BTreeSet<&String> = s.confusion.values().flat_map(|r| r.keys()).collect();
    out.push_str("\nConfusion (rows: hidden, with the oracle's class; columns: named):\n\n| hidden \\ named |");
    for c in &columns {
        out.push_str(&format!(" {c} |"));
    }
    out.push_str("\n| --- |");
    out.push_str(&" --- |".repeat(columns.len()));
    out.push('\n');
    for (row, cells) in &s.confusion {
        out.push_str(&format!("| {row} |"));
        for c in &columns {
            out.push_str(&format!(" {} |", cells.get(*c).copied().unwrap_or(0)));
        }
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(k: &[&str]) -> BTreeSet<String> {
        k.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn outcomes_follow_their_definitions() {
        let (g, bed) = (set(&["gravity"]), set(&["bed-support"]));
        assert_eq!(outcome(&g, &bed, &set(&["gravity"])), Outcome::Right);
        assert_eq!(
            outcome(&g, &bed, &set(&["gravity", "bed-support"])),
            Outcome::Right,
            "naming the carrier is right"
        );
        assert_eq!(outcome(&g, &bed, &set(&["bed-support"])), Outcome::Partial);
        assert_eq!(outcome(&g, &bed, &set(&[])), Outcome::Missed);
        assert_eq!(
            outcome(&g, &bed, &set(&["gravity", "pack"])),
            Outcome::Wrong
        );
        let nothing = set(&[]);
        assert_eq!(outcome(&nothing, &nothing, &nothing), Outcome::Right);
        assert_eq!(outcome(&nothing, &nothing, &g), Outcome::Wrong);
        let two = set(&["gravity", "pressure"]);
        assert_eq!(outcome(&two, &bed, &set(&["pressure"])), Outcome::Partial);
    }

    #[test]
    fn runs_add_up_per_kind_and_class_and_unknown_cohorts_are_errors() {
        let truths = vec![
            CohortTruth {
                cohort: "a".into(),
                hidden: set(&["gravity"]),
                carriers: set(&["bed-support"]),
                detectable: Some(true),
                statistic: Some(5.0),
            },
            CohortTruth {
                cohort: "b".into(),
                hidden: set(&["gravity"]),
                carriers: set(&["bed-support"]),
                detectable: Some(false),
                statistic: Some(1.0),
            },
            CohortTruth {
                cohort: "c".into(),
                hidden: set(&[]),
                carriers: set(&[]),
                detectable: None,
                statistic: None,
            },
        ];
        let run = serde_json::json!({"cohorts": [
            {"cohort": "a", "verdict": "effects", "effects": [{"kind": "gravity"}],
             "tre_mm": {"before": 3.0, "after": 1.5}},
            {"cohort": "b", "verdict": "none", "effects": []},
            {"cohort": "c", "verdict": "unexplained", "effects": []},
        ]});
        let mut s = DiscoverScore::default();
        add_run(&mut s, "d", &truths, &run).unwrap();
        assert_eq!(s.by_hidden["gravity"]["detectable"].right, 1);
        assert_eq!(s.by_hidden["gravity"]["undetectable"].missed, 1);
        assert_eq!(s.by_hidden["nothing"]["unknown"].right, 1);
        assert_eq!(s.confusion["gravity (detectable)"]["gravity"], 1);
        assert_eq!(s.confusion["nothing (unknown)"]["unexplained"], 1);
        assert_eq!(s.cohorts[0].tre_mm, Some([3.0, 1.5]));
        let md = markdown(&s);
        assert!(
            md.contains("| gravity | detectable | 1 | 1 | 0 | 0 | 0 |"),
            "{md}"
        );
        let bad = serde_json::json!({"cohorts": [{"cohort": "zz", "verdict": "none"}]});
        let e = add_run(&mut s, "d", &truths, &bad).unwrap_err();
        assert!(e.contains("\"zz\""), "{e}");
    }
}
