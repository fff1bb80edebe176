//! When LIBR+ abstains: a registration outside what the networks learned gets the base
//! method's answer instead of the correction.
//!
//! The networks learned LIBR's residual on one simulator's data. On data unlike it (another
//! group's simulator, a held organ pushed by a tool, a real phantom) the correction can make LIBR
//! worse, and nothing in the correction itself says so. Two signals, both read from the
//! registration (never from the truth), say when an input lies outside what was learned:
//! - **the ensemble's disagreement relative to its correction** (`spread_ratio`): the RMS over
//!   nodes of the members' distances from their mean, over the RMS of the mean correction.
//!   Networks trained on different livers agree where the data are like their training data
//!   and part where they are not; the ratio is scale free, so large in-family deformations (large
//!   corrections, large absolute disagreement) are not taken for outside ones.
//! - **LIBR's data misfit** (`libr_rms_mm`, its final weighted residual RMS): an input the
//!   base model cannot fit (a held organ's dent, a sensor far noisier than the training data's)
//!   is unlike every training sample, whose LIBR fitted the points to about the noise.
//!
//! Each threshold is a quantile of its signal over registrations of data like the training data
//! but never trained on (a fresh seed of the same generator), at level `1 − α/k` for `k` signals,
//! so at most about a fraction `α` of in-family registrations abstains (a Bonferroni bound). The
//! rule is a file beside the networks, `abstain.json` (format [`ABSTAIN_FORMAT`]), written by
//! `librplus calibrate-abstain`.

use super::GcnError;
use std::path::Path;

/// The rule's file name in a model or ensemble directory.
pub const ABSTAIN_FILE: &str = "abstain.json";

/// The format version this build writes and reads.
pub const ABSTAIN_FORMAT: u32 = 1;

/// When LIBR+ abstains (`abstain.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AbstainRule {
    /// Format version ([`ABSTAIN_FORMAT`]).
    pub format: u32,
    /// Abstain when the ensemble's disagreement exceeds this share of its correction (absent:
    /// not used, e.g. for a single network).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spread_ratio: Option<f64>,
    /// Abstain when LIBR's final weighted residual RMS exceeds this (mm; absent: not used).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub libr_rms_mm: Option<f64>,
    /// The in-family abstention rate the thresholds were set for (their Bonferroni bound).
    pub alpha: f64,
    /// How the rule was calibrated (data, command, counts; free-form).
    #[serde(default)]
    pub provenance: serde_json::Value,
}

/// What [`AbstainRule::outside`] reads of one registration.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AbstainSignals {
    /// The ensemble's disagreement over its correction (None for one network).
    pub spread_ratio: Option<f64>,
    /// LIBR's final weighted residual RMS (mm).
    pub libr_rms_mm: f64,
}

impl AbstainRule {
    /// Checks the rule, naming the field at fault.
    pub fn check(&self) -> Result<(), GcnError> {
        let bad = |field: &str, why: String| {
            Err(GcnError::ModelFile(format!(
                "{ABSTAIN_FILE}: {field} {why}"
            )))
        };
        if self.format != ABSTAIN_FORMAT {
            return bad(
                "format",
                format!("is {}, this build reads {ABSTAIN_FORMAT}", self.format),
            );
        }
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            return bad("alpha", format!("must lie in (0, 1), got {}", self.alpha));
        }
        for (field, v) in [
            ("spread_ratio", self.spread_ratio),
            ("libr_rms_mm", self.libr_rms_mm),
        ] {
            if let Some(v) = v
                && !(v.is_finite() && v > 0.0)
            {
                return bad(field, format!("must be finite and positive, got {v}"));
            }
        }
        if self.spread_ratio.is_none() && self.libr_rms_mm.is_none() {
            return bad(
                "spread_ratio",
                "and libr_rms_mm are both absent: no rule".into(),
            );
        }
        Ok(())
    }

    /// Reads `dir/abstain.json`; `None` when the directory has none (LIBR+ then never abstains).
    pub fn read(dir: &Path) -> Result<Option<Self>, GcnError> {
        let p = dir.join(ABSTAIN_FILE);
        if !p.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&p)
            .map_err(|e| GcnError::ModelFile(format!("{}: {e}", p.display())))?;
        Self::parse(&text)
            .map(Some)
            .map_err(|e| GcnError::ModelFile(format!("{}: {e}", p.display())))
    }

    /// Parses and checks a rule's JSON text.
    pub fn parse(text: &str) -> Result<Self, GcnError> {
        let rule: Self = serde_json::from_str(text)
            .map_err(|e| GcnError::ModelFile(format!("{ABSTAIN_FILE}: {e}")))?;
        rule.check()?;
        Ok(rule)
    }

    /// Writes the rule as `dir/abstain.json`.
    pub fn write(&self, dir: &Path) -> Result<(), GcnError> {
        self.check()?;
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| GcnError::ModelFile(format!("{ABSTAIN_FILE}: {e}")))?;
        crate::util::write_atomic(&dir.join(ABSTAIN_FILE), text.as_bytes())
            .map_err(|e| GcnError::ModelFile(e.to_string()))
    }

    /// Why a registration with these signals lies outside what the networks learned, if it
    /// does.
    pub fn outside(&self, s: &AbstainSignals) -> Option<String> {
        let mut why = Vec::new();
        if let (Some(t), Some(v)) = (self.spread_ratio, s.spread_ratio)
            && v > t
        {
            why.push(format!(
                "the ensemble disagrees by {:.0} % of its correction (in-family limit {:.0} %)",
                100.0 * v,
                100.0 * t
            ));
        }
        if let Some(t) = self.libr_rms_mm
            && s.libr_rms_mm > t
        {
            why.push(format!(
                "LIBR misses the points by {:.1} mm RMS (in-family limit {t:.1} mm)",
                s.libr_rms_mm
            ));
        }
        (!why.is_empty())
            .then(|| format!("outside what the SR-GCN learned: {}", why.join(", and ")))
    }

    /// The rule at in-family abstention rate about `alpha` from signals of in-family
    /// registrations: each used signal's threshold is its `⌈(n + 1)(1 − α/k)⌉`-th smallest value
    /// (`k` signals, `n` registrations with that signal), so that a new in-family registration
    /// exceeds it with probability at most `α/k` (split-conformal; exchangeable data).
    pub fn calibrate(samples: &[AbstainSignals], alpha: f64) -> Result<Self, GcnError> {
        if !(alpha > 0.0 && alpha < 1.0) {
            return Err(GcnError::Unusable(format!(
                "alpha must lie in (0, 1), got {alpha}"
            )));
        }
        let spreads: Vec<f64> = samples
            .iter()
            .filter_map(|s| s.spread_ratio)
            .filter(|v| v.is_finite())
            .collect();
        let misfits: Vec<f64> = samples
            .iter()
            .map(|s| s.libr_rms_mm)
            .filter(|v| v.is_finite())
            .collect();
        let k = if spreads.is_empty() { 1.0 } else { 2.0 };
        let quantile = |mut v: Vec<f64>| -> Result<f64, GcnError> {
            v.sort_by(f64::total_cmp);
            let n = v.len();
            let rank = ((n as f64 + 1.0) * (1.0 - alpha / k)).ceil() as usize;
            if n == 0 || rank > n {
                return Err(GcnError::Unusable(format!(
                    "{n} registrations cannot set a threshold at level {:.4}: need at least {}",
                    1.0 - alpha / k,
                    ((k / alpha) - 1.0).ceil()
                )));
            }
            Ok(v[rank - 1])
        };
        let rule = Self {
            format: ABSTAIN_FORMAT,
            spread_ratio: if spreads.is_empty() {
                None
            } else {
                Some(quantile(spreads)?)
            },
            libr_rms_mm: Some(quantile(misfits)?),
            alpha,
            provenance: serde_json::Value::Null,
        };
        rule.check()?;
        Ok(rule)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

    fn draw(rng: &mut SplitMix64) -> AbstainSignals {
        AbstainSignals {
            spread_ratio: Some(0.2 + 0.1 * rng.next_f64()),
            libr_rms_mm: 1.0 + rng.next_f64(),
        }
    }

    #[test]
    fn calibrated_thresholds_abstain_on_about_alpha_of_new_in_family_registrations() {
        let mut rng = SplitMix64::new(7);
        let cal: Vec<_> = (0..400).map(|_| draw(&mut rng)).collect();
        let rule = AbstainRule::calibrate(&cal, 0.1).unwrap();
        let fresh: Vec<_> = (0..20_000).map(|_| draw(&mut rng)).collect();
        let rate =
            fresh.iter().filter(|s| rule.outside(s).is_some()).count() as f64 / fresh.len() as f64;
        // Two independent uniform signals, each cut at its 95th percentile: 1 − 0.95² = 9.75 %.
        assert!((0.07..=0.11).contains(&rate), "in-family abstention {rate}");
        // Far outside on either signal abstains, naming it.
        let why = rule
            .outside(&AbstainSignals {
                spread_ratio: Some(0.6),
                libr_rms_mm: 1.2,
            })
            .unwrap();
        assert!(
            why.contains("ensemble disagrees") && !why.contains("LIBR misses"),
            "{why}"
        );
        let why = rule
            .outside(&AbstainSignals {
                spread_ratio: Some(0.21),
                libr_rms_mm: 9.0,
            })
            .unwrap();
        assert!(
            why.contains("LIBR misses") && !why.contains("ensemble"),
            "{why}"
        );
        // A single network: the misfit alone, at level 1 − α.
        let single: Vec<_> = cal
            .iter()
            .map(|s| AbstainSignals {
                spread_ratio: None,
                ..*s
            })
            .collect();
        let one = AbstainRule::calibrate(&single, 0.1).unwrap();
        assert!(one.spread_ratio.is_none());
        assert!(one.libr_rms_mm.unwrap() < rule.libr_rms_mm.unwrap());
    }

    #[test]
    fn a_rule_file_round_trips_and_bad_ones_are_refused_by_field() {
        let tmp = tempfile::tempdir().unwrap();
        assert_eq!(AbstainRule::read(tmp.path()).unwrap(), None);
        let rule = AbstainRule {
            format: ABSTAIN_FORMAT,
            spread_ratio: Some(0.35),
            libr_rms_mm: Some(2.5),
            alpha: 0.05,
            provenance: serde_json::json!({"data": "x"}),
        };
        rule.write(tmp.path()).unwrap();
        assert_eq!(AbstainRule::read(tmp.path()).unwrap(), Some(rule));
        for (text, field) in [
            (r#"{"format":2,"libr_rms_mm":1,"alpha":0.05}"#, "format"),
            (r#"{"format":1,"libr_rms_mm":1,"alpha":1.5}"#, "alpha"),
            (
                r#"{"format":1,"libr_rms_mm":-1,"alpha":0.05}"#,
                "libr_rms_mm",
            ),
            (r#"{"format":1,"alpha":0.05}"#, "spread_ratio"),
            (
                r#"{"format":1,"libr_rms_mm":1,"alpha":0.05,"extra":1}"#,
                "extra",
            ),
        ] {
            let e = AbstainRule::parse(text).unwrap_err().to_string();
            assert!(e.contains(field), "{text}: {e}");
        }
        // Too few registrations for the level are refused, saying how many are needed.
        let few = vec![
            AbstainSignals {
                spread_ratio: Some(0.2),
                libr_rms_mm: 1.0
            };
            10
        ];
        let e = AbstainRule::calibrate(&few, 0.05).unwrap_err().to_string();
        assert!(e.contains("need at least 39"), "{e}");
    }
}
