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
