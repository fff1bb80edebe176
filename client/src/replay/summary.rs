//! The summary of a replay over every session ([`ReplaySummary`]) and its table
//! ([`replay_table`]).

use super::ScenarioResult;
use crate::stats::{Latencies, LatencyMs};
use librplus::eval::Tre;
use std::collections::BTreeMap;

/// Mean TRE and count of one category.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CategorySummary {
    /// Mean final TRE (mm).
    pub tre_mm: f64,
    /// Scenarios with a TRE.
    pub scenarios: usize,
}

/// Per-method figures over every replayed scenario.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct MethodSummary {
    /// Mean final TRE over all nodes (mm).
    pub tre_mm: f64,
    /// Mean over surface nodes.
    pub tre_surface_mm: f64,
    /// Mean over interior nodes.
    pub tre_interior_mm: f64,
    /// Mean over the targets (of scenarios whose geometry has targets).
    pub tre_targets_mm: f64,
    /// Mean TRE of the initial alignment.
    pub tre_initial_mm: f64,
    /// Scenarios with a final TRE.
    pub scenarios: usize,
    /// Scenarios without one (failed session or no registration).
    pub failed: usize,
    /// Registration updates by quality name.
    pub quality: BTreeMap<String, u64>,
    /// Mean of the server's predicted TRE over the scenarios with a final TRE and a prediction
    /// (None when the server sent no error estimate), beside `tre_mm` over the same scenarios.
    pub predicted_tre_mm: Option<(f64, f64)>,
    /// Latency of this method's answers.
    pub latency_ms: LatencyMs,
    /// Mean final TRE per measurement category.
    pub by_category: BTreeMap<String, CategorySummary>,
    /// Sessions with discovery: their final discovery reports by verdict (or state when not
    /// done), and how many switched to an augmented model (by its effects).
    pub discovery: BTreeMap<String, u64>,
}

/// What `replay` measured (`replay --json` prints it).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ReplaySummary {
    /// Updates received in all.
    pub updates: u64,
    /// Scenarios replayed.
    pub scenarios: usize,
    /// Sessions (scenarios × methods).
    pub sessions: usize,
    /// Sessions without a final TRE.
    pub failed: usize,
    /// Rejected messages in all.
    pub rejections: u64,
    /// Rejections by code.
    pub rejections_by_code: BTreeMap<String, u64>,
    /// Mean final TRE (mm) per method.
    pub tre_mm: BTreeMap<String, f64>,
    /// Latency of every answer.
    pub latency_ms: LatencyMs,
    /// Per-method details.
    pub methods: BTreeMap<String, MethodSummary>,
    /// Every session.
    pub results: Vec<ScenarioResult>,
}

/// The mean of the finite values (NaN when there are none).
fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (s, c) = v
        .into_iter()
        .filter(|x| x.is_finite())
        .fold((0.0, 0usize), |(s, c), x| (s + x, c + 1));
    if c == 0 { f64::NAN } else { s / c as f64 }
}

/// The summary of `results` (of `scenarios` scenarios) with their latencies, in all and per
/// method.
pub(super) fn summarize(
    scenarios: usize,
    results: Vec<ScenarioResult>,
    all: &Latencies,
    per_method: &BTreeMap<String, Latencies>,
) -> ReplaySummary {
    let mut s = ReplaySummary {
        scenarios,
        sessions: results.len(),
        latency_ms: all.summary(),
        ..Default::default()
    };
    for r in &results {
        s.updates += r.updates;
        s.rejections += r.rejections.len() as u64;
        for x in &r.rejections {
            *s.rejections_by_code.entry(x.code.clone()).or_default() += 1;
        }
        if r.tre.is_none() {
            s.failed += 1;
        }
    }
    for (name, lat) in per_method {
        let mine: Vec<&ScenarioResult> = results.iter().filter(|r| &r.method == name).collect();
        let ok: Vec<&Tre> = mine.iter().filter_map(|r| r.tre.as_ref()).collect();
        let mut m = MethodSummary {
            tre_mm: mean(ok.iter().map(|t| t.tre_mm)),
            tre_surface_mm: mean(ok.iter().map(|t| t.tre_surface_mm)),
            tre_interior_mm: mean(ok.iter().map(|t| t.tre_interior_mm)),
            tre_targets_mm: mean(ok.iter().map(|t| t.tre_targets_mm)),
            tre_initial_mm: mean(mine.iter().map(|r| r.tre_initial_mm)),
            scenarios: ok.len(),
            failed: mine.len() - ok.len(),
            latency_ms: lat.summary(),
            ..Default::default()
        };
        for r in &mine {
            for st in &r.steps {
                *m.quality.entry(st.quality.clone()).or_default() += 1;
            }
            if let Some(d) = &r.discovery {
                let key = if d.switched {
                    format!("switched to {}", d.effects.join("+"))
                } else if d.state == "DONE" {
                    d.verdict.clone()
                } else {
                    d.state.to_lowercase()
                };
                *m.discovery.entry(key).or_default() += 1;
            }
        }
        let both: Vec<(f64, f64)> = mine
            .iter()
            .filter_map(|r| Some((r.predicted_tre_mm?, r.tre.as_ref()?.tre_mm)))
            .collect();
        if !both.is_empty() {
            m.predicted_tre_mm = Some((
                mean(both.iter().map(|b| b.0)),
                mean(both.iter().map(|b| b.1)),
            ));
        }
        let mut cats: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        for r in &mine {
            if let Some(t) = &r.tre {
                cats.entry(r.category.clone()).or_default().push(t.tre_mm);
            }
        }
        m.by_category = cats
            .into_iter()
            .map(|(c, v)| {
                (
                    c,
                    CategorySummary {
                        scenarios: v.len(),
                        tre_mm: mean(v),
                    },
                )
            })
            .collect();
        s.tre_mm.insert(name.clone(), m.tre_mm);
        s.methods.insert(name.clone(), m);
    }
    s.results = results;
    s
}

/// The summary as a readable table.
pub fn replay_table(s: &ReplaySummary) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let f = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.2}"));
    let _ = writeln!(
        o,
        "{:<16} {:<13} {:<14} {:>5} {:>7} {:>9} {:>9} {:>9} {:>9}  quality / error",
        "scenario",
        "category",
        "method",
        "msgs",
        "updates",
        "rejected",
        "TRE0 mm",
        "TRE mm",
        "p50 ms"
    );
    for r in &s.results {
        let _ = writeln!(
            o,
            "{:<16} {:<13} {:<14} {:>5} {:>7} {:>9} {:>9} {:>9} {:>9}  {}",
            r.scenario,
            r.category,
            r.method,
            r.messages,
            r.updates,
            r.rejections.len(),
            f(Some(r.tre_initial_mm)),
            f(r.tre.map(|t| t.tre_mm)),
            f(Some(r.latency_ms.p50)),
            r.error
                .clone()
                .or_else(|| r.final_quality.clone())
                .unwrap_or_default()
        );
    }
    let _ = writeln!(o);
    for (name, m) in &s.methods {
        let _ = writeln!(
            o,
            "{name}: TRE {} mm (surface {}, interior {}, targets {}; initial {}) over {} scenarios, {} failed; latency p50 {:.1} ms, p95 {:.1} ms",
            f(Some(m.tre_mm)),
            f(Some(m.tre_surface_mm)),
            f(Some(m.tre_interior_mm)),
            f(Some(m.tre_targets_mm)),
            f(Some(m.tre_initial_mm)),
            m.scenarios,
            m.failed,
            m.latency_ms.p50,
            m.latency_ms.p95
        );
        for (c, cs) in &m.by_category {
            let _ = writeln!(
                o,
                "  {c:<13} TRE {} mm ({} scenarios)",
                f(Some(cs.tre_mm)),
                cs.scenarios
            );
        }
        let q: Vec<String> = m.quality.iter().map(|(k, v)| format!("{k} {v}")).collect();
        let _ = writeln!(o, "  quality: {}", q.join(", "));
        if let Some((p, t)) = m.predicted_tre_mm {
            let _ = writeln!(
                o,
                "  error estimate: predicted TRE {p:.2} mm, measured {t:.2} mm (mean of the final registrations)"
            );
        }
        if !m.discovery.is_empty() {
            let d: Vec<String> = m
                .discovery
                .iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect();
            let _ = writeln!(o, "  discovery: {}", d.join(", "));
        }
    }
    let l = &s.latency_ms;
    let _ = writeln!(
        o,
        "{} updates over {} sessions ({} scenarios), {} rejected, {} failed; latency p50 {:.1} ms, p95 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        s.updates, s.sessions, s.scenarios, s.rejections, s.failed, l.p50, l.p95, l.p99, l.max
    );
    o
}
