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
    /// METHOD_AUTO: registration updates by the model chosen (empty for the other methods).
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub chosen: BTreeMap<String, u64>,
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
    /// Sessions whose discovery run ended without a verdict (failed, out of time, never
    /// reported), each with the server's reason.
    pub discovery_unfinished: Vec<UnfinishedDiscovery>,
    /// DEGRADED updates by what they gave up ([`degradations`] of their reasons; an update
    /// may give up more than one thing).
    pub degraded: BTreeMap<String, u64>,
}

/// A discovery run that ended without a verdict.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct UnfinishedDiscovery {
    /// The session's scenario.
    pub scenario: String,
    /// `FAILED`, `OUT_OF_TIME`, or `RUNNING` when its end was never reported.
    pub state: String,
    /// Why, in the server's words.
    pub reason: String,
}

/// What a DEGRADED answer gave up, in a few plain words each, read from the server's reason:
/// the answer came over its time budget, a lighter method answered in place of the one asked
/// for, a stage was cut short or left out. A reason of another kind is kept as its first
/// clause (up to a `:` or `;`), its numbers as `#`.
pub fn degradations(reason: &str) -> Vec<String> {
    let known: [(&str, &str); 11] = [
        ("over its time budget", "answered over its time budget"),
        ("LIBR+ needs about", "LIBR in place of LIBR+ (time budget)"),
        (
            "LIBR needs about",
            "the rigid result in place of LIBR (time budget)",
        ),
        (
            "pose search was skipped",
            "pose search skipped (time budget)",
        ),
        (
            "refit stopped after",
            "LIBR+'s refit cut short (time budget)",
        ),
        ("LIBR stopped after", "LIBR cut short (time budget)"),
        ("refit failed", "LIBR+'s refit failed"),
        ("SR-GCN correction failed", "SR-GCN correction failed"),
        ("SR-GCN correction skipped", "SR-GCN correction skipped"),
        (
            "no time left for the SR-GCN correction",
            "SR-GCN correction left out (time budget)",
        ),
        (
            "outside what the SR-GCN learned",
            "SR-GCN correction left out (outside what it learned)",
        ),
    ];
    let found: Vec<String> = known
        .iter()
        .filter(|(k, _)| reason.contains(k))
        .map(|(_, label)| label.to_string())
        .collect();
    if !found.is_empty() {
        return found;
    }
    let first = reason.split([';', ':']).next().unwrap_or_default().trim();
    if first.is_empty() {
        return vec!["no reason given".into()];
    }
    let mut label = String::new();
    let mut in_number = false;
    for c in first.chars() {
        let digit = c.is_ascii_digit() || (in_number && (c == '.' || c == ','));
        if digit && !in_number {
            label.push('#');
        } else if !digit {
            label.push(c);
        }
        in_number = digit;
    }
    vec![label.chars().take(100).collect()]
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
                if let Some(c) = &st.chosen {
                    *m.chosen.entry(c.clone()).or_default() += 1;
                }
                if st.quality == "DEGRADED" {
                    for what in degradations(&st.quality_reason) {
                        *m.degraded.entry(what).or_default() += 1;
                    }
                }
            }
            if let Some(d) = r.discovery.as_ref().filter(|d| d.unfinished()) {
                m.discovery_unfinished.push(UnfinishedDiscovery {
                    scenario: r.scenario.clone(),
                    state: d.state.clone(),
                    reason: d.reason().to_string(),
                });
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

/// `name count, name count, ...` of a count map.
fn counted(m: &BTreeMap<String, u64>) -> String {
    let v: Vec<String> = m.iter().map(|(k, v)| format!("{k} {v}")).collect();
    v.join(", ")
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
        if !m.chosen.is_empty() {
            let _ = writeln!(o, "  model chosen per update: {}", counted(&m.chosen));
        }
        if let Some(n) = m.quality.get("DEGRADED") {
            let _ = writeln!(
                o,
                "  degraded: {n} update(s), giving up: {}",
                counted(&m.degraded)
            );
        }
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
        for u in &m.discovery_unfinished {
            let _ = writeln!(
                o,
                "    {} {}: {}",
                u.scenario,
                u.state.to_lowercase(),
                u.reason
            );
        }
    }
    let l = &s.latency_ms;
    let degraded: u64 = s
        .methods
        .values()
        .filter_map(|m| m.quality.get("DEGRADED"))
        .sum();
    let _ = writeln!(
        o,
        "{} updates over {} sessions ({} scenarios), {degraded} degraded, {} rejected, {} failed; latency p50 {:.1} ms, p95 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        s.updates, s.sessions, s.scenarios, s.rejections, s.failed, l.p50, l.p95, l.p99, l.max
    );
    o
}

#[cfg(test)]
mod tests {
    use super::degradations;

    /// The server's reasons for a DEGRADED answer read as what it gave up: each thing named
    /// once, the late answer and its inner reason both; a reason of another kind keeps its
    /// first clause, numbers left out.
    #[test]
    fn degraded_answers_are_named() {
        let cases: [(&str, &[&str]); 7] = [
            (
                "time budget 250 ms: 40 ms left, LIBR+ needs about 300 ms (SR-GCN 200 ms); LIBR result",
                &["LIBR in place of LIBR+ (time budget)"],
            ),
            (
                "time budget 250 ms: 230 ms waiting for a compute slot left 20 ms, LIBR needs about 90 ms; rigid result",
                &["the rigid result in place of LIBR (time budget)"],
            ),
            (
                "over its time budget: answered in 412 ms of 250 ms (300 points; 0 ms waiting, rigid stage 80 ms); time budget 250 ms: LIBR stopped after 3 of 30 iterations",
                &[
                    "answered over its time budget",
                    "LIBR cut short (time budget)",
                ],
            ),
            (
                "time budget 250 ms: LIBR+'s refit stopped after 1 of 5 iterations",
                &["LIBR+'s refit cut short (time budget)"],
            ),
            (
                "outside what the SR-GCN learned: LIBR misses the points by 4.2 mm RMS (in-family limit 3.1 mm)",
                &["SR-GCN correction left out (outside what it learned)"],
            ),
            (
                "no time left for the SR-GCN correction (about 180 ms): LIBR's answer",
                &["SR-GCN correction left out (time budget)"],
            ),
            (
                "the case's full basis is still building (12 %): answered from a coarser one",
                &["the case's full basis is still building (# %)"],
            ),
        ];
        for (reason, want) in cases {
            assert_eq!(degradations(reason), *want, "{reason}");
        }
        assert_eq!(degradations(""), ["no reason given"]);
    }
}
