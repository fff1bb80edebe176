//! Two methods side by side on the same test scenarios: the rows of `test.json` and their sums.

use crate::eval::report::ScenarioResult;
use serde_json::{Value, json};
use std::collections::BTreeMap;

/// Per scenario the TREs of two methods of an evaluation (keys `a` and `b`), or why it failed.
pub fn pair_rows(results: &[ScenarioResult], a: &str, b: &str) -> Vec<Value> {
    let second: BTreeMap<&str, &ScenarioResult> = results
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
                (Some(tx), Some(ty)) => json!({
                    "scenario": x.scenario,
                    "geometry": x.geometry,
                    "category": x.category,
                    a: tx,
                    b: ty,
                }),
                _ => json!({
                    "scenario": x.scenario,
                    "geometry": x.geometry,
                    "category": x.category,
                    "error": x
                        .error
                        .clone()
                        .or_else(|| y.and_then(|y| y.error.clone()))
                        .unwrap_or_else(|| format!("{b} failed")),
                }),
            }
        })
        .collect()
}

/// TRE sums (mm) of two methods over the scenarios where both registered.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PairSums {
    /// Sum of the first method's TREs.
    pub first: f64,
    /// Sum of the second method's TREs.
    pub second: f64,
    /// Scenarios summed.
    pub count: usize,
}

impl PairSums {
    /// The first method's mean TRE (mm; 0 over no scenario).
    pub fn first_mean(&self) -> f64 {
        self.first / self.count.max(1) as f64
    }

    /// The second method's mean TRE (mm; 0 over no scenario).
    pub fn second_mean(&self) -> f64 {
        self.second / self.count.max(1) as f64
    }
}

/// `PairSums` over all the rows of [`pair_rows`] and per measurement category.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PairTotals {
    /// Over every scenario.
    pub all: PairSums,
    /// Per category.
    pub by_category: BTreeMap<String, PairSums>,
}

impl PairTotals {
    /// The sums of methods `a` and `b` over `rows` ([`pair_rows`]).
    pub fn of(rows: &[Value], a: &str, b: &str) -> Self {
        let mut out = Self::default();
        for r in rows {
            if let (Some(x), Some(y)) = (r[a]["tre_mm"].as_f64(), r[b]["tre_mm"].as_f64()) {
                let category = r["category"].as_str().unwrap_or("?").to_string();
                for s in [&mut out.all, out.by_category.entry(category).or_default()] {
                    s.first += x;
                    s.second += y;
                    s.count += 1;
                }
            }
        }
        out
    }

    /// `test.json`'s `by_category`: the two means under `first` and `second`, and the count.
    pub(super) fn by_category_json(
        &self,
        first: &str,
        second: &str,
    ) -> serde_json::Map<String, Value> {
        self.by_category
            .iter()
            .map(|(k, v)| {
                (
                    k.clone(),
                    json!({first: v.first_mean(), second: v.second_mean(), "scenarios": v.count}),
                )
            })
            .collect()
    }
}
