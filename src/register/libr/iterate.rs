//! The LIBR iteration both fits share ([`solve_with_limits`] on the whole basis,
//! [`solve_adaptive`] on the columns it keeps): match the measured points to the current model,
//! take one step of the fit, compose its rigid correction, record it, and stop when the fit says
//! so or the next iteration would end past the deadline. What differs between the two is the
//! step and the stopping rule ([`Stepper`]).

use super::*;
use crate::mesh::rigid::Rigid;
use crate::register::Match;
use std::time::Instant;

/// What one fit does in an iteration of [`iterate`].
pub(super) trait Stepper {
    /// What the held-out check needs of a step's system.
    type Last;

    /// The current displacement (node-major `3n`, image frame): what the matching reads.
    fn u(&self) -> &[f64];

    /// One step from `matches` under the pose `t`: moves the displacement and returns the step,
    /// the largest node movement it made and its system; may add to `info`'s timings.
    fn step(
        &mut self,
        matches: Vec<Match>,
        t: &Rigid,
        info: &mut LibrInfo,
    ) -> Result<(StepResult, f64, Self::Last), RegisterError>;

    /// Keeps what the step fitted, after it was recorded.
    fn keep(&mut self, step: StepResult, info: &mut LibrInfo);

    /// Whether the fit stops after a step that moved a node by `moved` (mm).
    fn done(&mut self, info: &mut LibrInfo, moved: f64, params: &LibrParams) -> bool;
}

/// Where the iterations ended: the pose, the record, and the last step's system when asked for.
pub(super) struct Iterated<L> {
    /// Image → physical.
    pub t: Rigid,
    /// The iterations' record.
    pub info: LibrInfo,
    /// The last step's system (None unless asked for, or when no step ran).
    pub last: Option<L>,
}

/// At most `params.fit.max_iterations` iterations of `fit` from the pose `initial`, matched by
/// `rematch(u, t)`; the last step's system is kept when `keep_last`. At least one iteration
/// runs; with a `deadline`, none that the last one's duration says would end past it.
pub(super) fn iterate<S: Stepper>(
    fit: &mut S,
    params: &LibrParams,
    initial: &Rigid,
    (deadline, keep_last): (Option<Instant>, bool),
    mut rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, RegisterError>,
) -> Result<Iterated<S::Last>, RegisterError> {
    let mut info = LibrInfo::default();
    let mut t = *initial;
    let mut last = None;
    for _ in 0..params.fit.max_iterations {
        let tm = Instant::now();
        let matches = rematch(fit.u(), &t)?;
        info.matching_s += crate::util::secs(tm);
        let (step, moved, system) = fit.step(matches, &t, &mut info)?;
        t = step.rigid_correction.then(&t);
        record(&mut info, &step, moved);
        fit.keep(step, &mut info);
        if keep_last {
            last = Some(system);
        }
        if fit.done(&mut info, moved, params) || past_deadline(&mut info, deadline, params, tm) {
            break;
        }
    }
    Ok(Iterated { t, info, last })
}
