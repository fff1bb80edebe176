//! Detectability curves of effect discovery (`librplus discover-study`): for each kind and each
//! amplitude scale (the generator's `--hidden-effect KIND:scale=F`), how many cohorts the oracle
//! can see ([`crate::dataset::Detectability`]) and how often `discover` names the hidden kind;
//! the smallest scale at which each is reached; and, over everything, the confusion matrix of
//! [`super::discover_score`]. Evaluation only: discovery itself never reads any of this.

use super::discover_score::{DiscoverScore, Outcome};
use serde::Serialize;

/// Format of `study.json`.
pub const STUDY_FORMAT: u32 = 1;

/// Share a curve must reach for its minimum scale ([`minimum_scale`]): the oracle's detectability
/// at one half, naming at 0.9 (the acceptance's figures).
pub const DETECTABLE_SHARE: f64 = 0.5;
/// See [`DETECTABLE_SHARE`].
pub const NAMED_SHARE: f64 = 0.9;

/// One kind at one scale.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StudyPoint {
    /// Kind hidden (`nothing` for the negative control).
    pub kind: String,
    /// Amplitude scale.
    pub scale: f64,
    /// Cohorts scored.
    pub cohorts: usize,
    /// Of them, oracle-detectable.
    pub detectable: usize,
    /// Named right (every hidden kind, nothing outside the truth; nothing hidden: nothing named).
    pub right: usize,
    /// Named right among the detectable.
    pub right_detectable: usize,
    /// Nothing named among the undetectable.
    pub quiet_undetectable: usize,
    /// A kind outside the truth named.
    pub wrong: usize,
}

impl StudyPoint {
    /// Share of cohorts oracle-detectable.
    pub fn p_detectable(&self) -> f64 {
        share(self.detectable, self.cohorts)
    }

    /// Share of cohorts named right.
    pub fn p_named(&self) -> f64 {
        share(self.right, self.cohorts)
    }
}

fn share(k: usize, n: usize) -> f64 {
    if n == 0 {
        f64::NAN
    } else {
        k as f64 / n as f64
    }
}

/// The point of `kind` at `scale` from the score of its runs.
pub fn point(kind: &str, scale: f64, score: &DiscoverScore) -> StudyPoint {
    let mut p = StudyPoint {
        kind: kind.to_string(),
        scale,
        cohorts: 0,
        detectable: 0,
        right: 0,
        right_detectable: 0,
        quiet_undetectable: 0,
        wrong: 0,
    };
    for c in &score.cohorts {
        p.cohorts += 1;
        let detectable = c.detectable == Some(true);
        p.detectable += usize::from(detectable);
        let right = c.outcome == Outcome::Right;
        p.right += usize::from(right);
        p.wrong += usize::from(c.outcome == Outcome::Wrong);
        if detectable {
            p.right_detectable += usize::from(right);
        } else if c.named.is_empty() {
            p.quiet_undetectable += 1;
        }
    }
    p
}

/// The smallest scale of `kind` from which on `value` stays at or above `share` (every larger
/// scale too); `None` when it never does.
pub fn minimum_scale(
    points: &[StudyPoint],
    kind: &str,
    value: impl Fn(&StudyPoint) -> f64,
    share: f64,
) -> Option<f64> {
    let mut mine: Vec<&StudyPoint> = points.iter().filter(|p| p.kind == kind).collect();
    mine.sort_by(|a, b| a.scale.total_cmp(&b.scale));
    let mut out = None;
    for p in mine.iter().rev() {
        if value(p) >= share {
            out = Some(p.scale);
        } else {
            break;
        }
    }
    out
}

/// Per kind: the minimum scales of detectability and of naming.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct KindSummary {
    /// Kind.
    pub kind: String,
    /// Smallest scale from which at least [`DETECTABLE_SHARE`] of the cohorts are detectable.
    pub min_detectable_scale: Option<f64>,
    /// Smallest scale from which at least [`NAMED_SHARE`] are named right.
    pub min_named_scale: Option<f64>,
}

/// The summaries of every kind of `points` (not the control, `nothing`), in order of first
/// appearance.
pub fn summaries(points: &[StudyPoint]) -> Vec<KindSummary> {
    let mut kinds: Vec<&str> = Vec::new();
    for p in points.iter().filter(|p| p.kind != "nothing") {
        if !kinds.contains(&p.kind.as_str()) {
            kinds.push(&p.kind);
        }
    }
    kinds
        .into_iter()
        .map(|k| KindSummary {
            kind: k.to_string(),
            min_detectable_scale: minimum_scale(
                points,
                k,
                StudyPoint::p_detectable,
                DETECTABLE_SHARE,
            ),
            min_named_scale: minimum_scale(points, k, StudyPoint::p_named, NAMED_SHARE),
        })
        .collect()
}

/// The study as Markdown: one row per kind and scale, the minimum scales, then the confusion
/// matrix and outcomes of everything ([`super::discover_score::markdown`]).
pub fn markdown(points: &[StudyPoint], all: &DiscoverScore) -> String {
    let mut s = String::from(
        "| kind | scale | cohorts | detectable | named right | right among detectable | nothing named among undetectable | wrong kind named |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n",
    );
    for p in points {
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {}/{} | {}/{} | {} |\n",
            p.kind,
            p.scale,
            p.cohorts,
            p.detectable,
            p.right,
            p.right_detectable,
            p.detectable,
            p.quiet_undetectable,
            p.cohorts - p.detectable,
            p.wrong
        ));
    }
    let scale = |x: Option<f64>| x.map_or("never".to_string(), |v| format!("{v}"));
    s.push_str(&format!(
        "\n| kind | smallest scale detectable in ≥ {:.0} % | smallest scale named right in ≥ {:.0} % |\n| --- | --- | --- |\n",
        100.0 * DETECTABLE_SHARE,
        100.0 * NAMED_SHARE
    ));
    for k in summaries(points) {
        s.push_str(&format!(
            "| {} | {} | {} |\n",
            k.kind,
            scale(k.min_detectable_scale),
            scale(k.min_named_scale)
        ));
    }
    s.push('\n');
    s.push_str(&super::discover_score::markdown(all));
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::discover_score::CohortScore;

    fn cohort(detectable: bool, named: &[&str], outcome: Outcome) -> CohortScore {
        CohortScore {
            dataset: "d".into(),
            cohort: "c".into(),
            hidden: vec!["gravity".into()],
            carriers: vec![],
            detectable: Some(detectable),
            statistic: None,
            verdict: if named.is_empty() { "none" } else { "effects" }.into(),
            named: named.iter().map(|s| s.to_string()).collect(),
            outcome,
            tre_mm: None,
        }
    }

    fn score(cohorts: Vec<CohortScore>) -> DiscoverScore {
        DiscoverScore {
            cohorts,
            ..DiscoverScore::default()
        }
    }

    #[test]
    fn points_count_outcomes_by_oracle_class() {
        let s = score(vec![
            cohort(true, &["gravity"], Outcome::Right),
            cohort(true, &[], Outcome::Missed),
            cohort(false, &[], Outcome::Missed),
            cohort(false, &["pack"], Outcome::Wrong),
        ]);
        let p = point("gravity", 0.5, &s);
        assert_eq!(
            (p.cohorts, p.detectable, p.right, p.right_detectable),
            (4, 2, 1, 1)
        );
        assert_eq!((p.quiet_undetectable, p.wrong), (1, 1));
        assert_eq!((p.p_detectable(), p.p_named()), (0.5, 0.25));
        let md = markdown(&[p], &s);
        assert!(
            md.contains("| gravity | 0.5 | 4 | 2 | 1 | 1/2 | 1/2 | 1 |"),
            "{md}"
        );
    }

    #[test]
    fn the_minimum_scale_is_where_the_curve_stays_above_the_share() {
        let at = |scale: f64, right: usize| StudyPoint {
            kind: "gravity".into(),
            scale,
            cohorts: 10,
            detectable: right,
            right,
            right_detectable: right,
            quiet_undetectable: 0,
            wrong: 0,
        };
        // Dips below at 1 after passing at 0.5: the curve holds from 2 on only.
        let pts = vec![at(2.0, 10), at(0.25, 1), at(0.5, 9), at(1.0, 6)];
        assert_eq!(
            minimum_scale(&pts, "gravity", StudyPoint::p_named, 0.9),
            Some(2.0)
        );
        assert_eq!(
            minimum_scale(&pts, "gravity", StudyPoint::p_detectable, 0.5),
            Some(0.5)
        );
        assert_eq!(
            minimum_scale(&pts, "gravity", StudyPoint::p_named, 1.1),
            None
        );
        assert_eq!(minimum_scale(&pts, "pack", StudyPoint::p_named, 0.5), None);
        let k = summaries(&pts);
        assert_eq!(k.len(), 1);
        assert_eq!(k[0].min_named_scale, Some(2.0));
    }
}
