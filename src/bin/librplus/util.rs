//! Helpers shared by the commands: printing results and progress, the command line and commit of
//! a run.

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

/// How this process was started, as the provenance of what a run writes records it.
pub(crate) fn origin() -> librplus::eval::runs::RunOrigin {
    librplus::eval::runs::RunOrigin {
        command: shell_command(),
        commit: git_commit(),
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

/// The library's progress of a long run on the terminal: one progress bar (or spinner) at a time
/// and log lines on stderr, written above the bar.
#[derive(Default)]
pub(crate) struct Bars {
    bar: std::sync::Mutex<Option<indicatif::ProgressBar>>,
}

impl Bars {
    /// The current bar, locked.
    fn current(&self) -> std::sync::MutexGuard<'_, Option<indicatif::ProgressBar>> {
        self.bar.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Shows `bar` instead of the current one (which goes away).
    fn show(&self, bar: Option<indicatif::ProgressBar>) {
        if let Some(old) = std::mem::replace(&mut *self.current(), bar) {
            old.finish_and_clear();
        }
    }
}

impl librplus::eval::runs::RunProgress for Bars {
    fn spin(&self, what: &str) {
        let bar = indicatif::ProgressBar::new_spinner().with_message(what.to_string());
        bar.enable_steady_tick(std::time::Duration::from_millis(200));
        self.show(Some(bar));
    }

    fn start(&self, what: &str, total: usize) {
        self.show(Some(
            indicatif::ProgressBar::new(total as u64).with_style(bar_style(what)),
        ));
    }

    fn step(&self, done: usize, total: usize, message: Option<&str>) {
        if let Some(bar) = &*self.current() {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            if let Some(m) = message {
                bar.set_message(m.to_string());
            }
        }
    }

    fn finish(&self) {
        self.show(None);
    }

    fn log(&self, line: &str) {
        match &*self.current() {
            Some(bar) => bar.suspend(|| eprintln!("{line}")),
            None => eprintln!("{line}"),
        }
    }
}
