//! Helpers shared by the commands: printing results, the command line and commit of a run.

use serde_json::Value;

/// Prints `value` as JSON, or as `key: value` lines.
pub(crate) fn emit(json: bool, value: &Value) {
    if json {
        println!("{value}");
        return;
    }
    if let Value::Object(map) = value {
        for (k, v) in map {
            match v {
                Value::Object(inner) => {
                    println!("{k}:");
                    for (ik, iv) in inner {
                        println!("  {ik}: {}", human(iv));
                    }
                }
                _ => println!("{k}: {}", human(v)),
            }
        }
    }
}

fn human(v: &Value) -> String {
    match v {
        Value::Number(n) => match n.as_f64() {
            Some(x) if n.is_f64() && x != 0.0 && x.abs() < 1e-3 => format!("{x:.3e}"),
            Some(x) if n.is_f64() => format!("{x:.6}"),
            _ => n.to_string(),
        },
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

pub(crate) fn git_commit() -> String {
    std::process::Command::new("git")
        .args(["rev-parse", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_else(|| "unknown".into())
}

/// This process's command line as a shell would need it: an empty argument or one holding a space
/// or a shell character in single quotes, so a recorded command runs again when pasted.
pub(crate) fn shell_command() -> String {
    std::env::args()
        .map(|a| {
            let plain = !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_=./,:@%+".contains(c));
            if plain {
                a
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// The scenarios of a split's deformations (those `refs` name), by deformation id, and each
/// deformation's geometry.
pub(crate) struct SplitScenarios {
    scen: std::collections::BTreeMap<String, Vec<librplus::eval::ScenarioData>>,
    geom_of: std::collections::BTreeMap<String, String>,
}

impl SplitScenarios {
    /// Reads the scenarios of every deformation of `m` that `refs` name.
    pub(crate) fn load<'a>(
        data: &std::path::Path,
        m: &librplus::dataset::Manifest,
        refs: impl Iterator<Item = &'a (String, usize)>,
    ) -> anyhow::Result<Self> {
        let needed: std::collections::BTreeSet<&str> = refs.map(|(d, _)| d.as_str()).collect();
        let mut scen = std::collections::BTreeMap::new();
        let mut geom_of = std::collections::BTreeMap::new();
        for d in m
            .deformations
            .iter()
            .filter(|d| needed.contains(d.id.as_str()))
        {
            scen.insert(d.id.clone(), librplus::eval::load_scenarios(data, d)?);
            geom_of.insert(d.id.clone(), d.geometry.clone());
        }
        Ok(Self { scen, geom_of })
    }

    /// The geometries of the deformations read (one per deformation, in deformation order).
    pub(crate) fn geometries(&self) -> Vec<String> {
        self.geom_of.values().cloned().collect()
    }

    /// The scenarios `refs` name, each with its geometry.
    pub(crate) fn pick(
        &self,
        refs: &[(String, usize)],
    ) -> Vec<(&librplus::eval::ScenarioData, &str)> {
        refs.iter()
            .filter_map(|(d, i)| self.scen[d].get(*i).map(|s| (s, self.geom_of[d].as_str())))
            .collect()
    }
}

/// A progress bar's style: `what`, the bar, counts, message, elapsed time and estimate.
pub(crate) fn bar_style(what: &str) -> indicatif::ProgressStyle {
    indicatif::ProgressStyle::with_template(&format!(
        "{{spinner}} {what} [{{bar:30}}] {{pos}}/{{len}} {{msg}} {{elapsed}} (eta {{eta}})"
    ))
    .expect("valid template")
    .progress_chars("=> ")
}
