//! What the long runs of the command line (training, evaluation, experiments, benchmarks) share:
//! the progress they report, the record of how a run was started, and the files they read and
//! write the same way.

use super::EvalError;
use crate::register::physics::Physics;
use crate::util::FileError;
use std::path::Path;

/// What a long run reports while it works. The command line draws it (progress bars, log lines
/// on stderr); every method does nothing by default, so a caller watches only what it wants.
pub trait RunProgress: Sync {
    /// A step of unknown length began: `what` it does (a spinner).
    fn spin(&self, what: &str) {
        let _ = what;
    }

    /// A step of `total` items began: `what` it does (0: the total is learned as it goes).
    fn start(&self, what: &str, total: usize) {
        let _ = (what, total);
    }

    /// `done` of `total` items of the current step, with what the step is at (a loss, an
    /// epoch) when it says.
    fn step(&self, done: usize, total: usize, message: Option<&str>) {
        let _ = (done, total, message);
    }

    /// The current step ended.
    fn finish(&self) {}

    /// A line of the run's log (the command line writes it on stderr, above any bar).
    fn log(&self, line: &str) {
        let _ = line;
    }
}

/// Progress nobody watches.
#[derive(Debug, Clone, Copy, Default)]
pub struct Quiet;

impl RunProgress for Quiet {}

/// How a run was started, as the provenance of what it writes records it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RunOrigin {
    /// The command line, as a shell would need it to run again.
    pub command: String,
    /// The source commit of the program (`unknown` when not known).
    pub commit: String,
}

/// The augmented model (`physics.json`) at `path`, or no physics when there is none; an error
/// names the `--physics` option.
pub fn read_physics(path: Option<&Path>) -> Result<Physics, EvalError> {
    match path {
        None => Ok(Physics::none()),
        Some(p) => Physics::read(p).map_err(|e| EvalError::Parameter(format!("--physics: {e}"))),
    }
}

/// Writes `value` to `path` as pretty-printed JSON followed by `end` ("" or "\n").
pub(crate) fn write_json(
    path: &Path,
    value: &serde_json::Value,
    end: &str,
) -> Result<(), EvalError> {
    let text = serde_json::to_string_pretty(value)
        .map_err(|e| EvalError::Internal(format!("{}: {e}", path.display())))?;
    write_file(path, (text + end).as_bytes())
}

/// Writes `bytes` to `path`.
pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<(), EvalError> {
    std::fs::write(path, bytes).map_err(FileError::at("writing", path))?;
    Ok(())
}

/// Creates the directory `dir` and its parents.
pub(crate) fn create_dir(dir: &Path) -> Result<(), EvalError> {
    std::fs::create_dir_all(dir).map_err(FileError::at("creating directory", dir))?;
    Ok(())
}
