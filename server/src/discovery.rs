//! In-surgery discovery (opt in per session): the `librplus discover` workflow on the points a
//! session has received so far, run in the background so that it never delays a registration
//! update, and the switch to the augmented model when an effect is named.
//!
//! - **Where it runs.** One OS thread per run, at the lowest CPU priority (nice 19), with a
//!   one-thread rayon pool: registrations keep their compute slots and the global pool, and the
//!   scheduler gives the run only what they leave.
//! - **Bounded.** The run stops at its budget (checked between the workflow's steps, see
//!   [`librplus::discover::DiscoverParams::deadline`]); a run that overruns is reported
//!   `OUT_OF_TIME` and changes nothing. One run per session at a time.
//! - **The data.** The session's points, split into 4–6 interleaved parts
//!   ([`librplus::discover::session_sweeps`]: the workflow cross-validates across parts and
//!   spatial blocks), registered with the case's plain LIBR model as `librplus discover` does.
//! - **The switch.** When the workflow names effects (significant on held-out blocks, by a
//!   practical margin and by BIC), the session's model becomes the case's physics plus the named
//!   effects (a kind the case already carries is not added twice), its LIBR basis built in the
//!   same background run. Later registrations of the session use it; `Registration.effects` and
//!   the `DiscoveryReport` say so. The case itself, and every other session, are untouched.

use crate::cases::Case;
use librplus::discover::{
    CohortDiscovery, DiscoverError, DiscoverParams, Verdict, discover_cohort, session_sweeps,
};
use librplus::pipeline::{PipelineParams, Prepared};
use librplus::register::Measurements;
use librplus::register::libr::LibrParams;
use librplus::register::physics::Physics;
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::oneshot;

/// Fewest points a run needs (below, it is refused at once): four parts of 50.
pub const MIN_POINTS: usize = 200;

/// What one run asks for.
pub struct Request {
    /// The case.
    pub case: Arc<Case>,
    /// The session's points so far.
    pub measurements: Measurements,
    /// The session's trusted-alignment uncertainty, if any.
    pub trusted_alignment_mm: Option<f64>,
    /// The session's organ is held ([`librplus::pipeline::hold`]).
    pub held: bool,
    /// Wall-clock limit.
    pub budget: Duration,
    /// The coarse search grid.
    pub coarse: bool,
    /// The LIBR settings the case was prepared with.
    pub libr: LibrParams,
    /// The DiscoverNow message that asked (0: automatic).
    pub client_seq: u64,
}

/// A finished run: its report and, when it switched, the session's new model.
pub struct Outcome {
    /// The report to send.
    pub report: pb::DiscoveryReport,
    /// The augmented model, when effects were named and it was built in time.
    pub augmented: Option<Arc<Prepared>>,
}

/// Parts the session's points are split into: at least four, because the workflow names an
/// effect only when its paired signed-rank z over the part × block units exceeds 3, and with
/// two parts of five blocks (10 units) z cannot exceed 2.8; four give 20 units (z up to 3.9).
/// Up to six for large sessions (about 150 points each).
fn parts(points: usize) -> usize {
    (points / 150).clamp(4, 6)
}

/// The report sent when a run starts.
pub fn started(req: &Request) -> pb::DiscoveryReport {
    let n = req.measurements.points.len();
    pb::DiscoveryReport {
        client_seq: req.client_seq,
        state: pb::DiscoveryState::Running as i32,
        message: format!(
            "discovery started on {n} points ({} parts), budget {:.0} s; registrations go on with the current model",
            parts(n),
            req.budget.as_secs_f64()
        ),
        points_used: n as u32,
        sweeps: parts(n) as u32,
        ..Default::default()
    }
}

/// Starts a run on its own thread; the receiver gets its outcome (a failure is an outcome too).
pub fn spawn(req: Request) -> oneshot::Receiver<Outcome> {
    let (tx, rx) = oneshot::channel();
    let spawned = std::thread::Builder::new()
        .name("discovery".into())
        .spawn(move || {
            lower_priority();
            let t0 = Instant::now();
            let seq = req.client_seq;
            let n = req.measurements.points.len();
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(req)))
                .unwrap_or_else(|_| {
                    tracing::error!("discovery panicked");
                    failed(
                        seq,
                        n,
                        t0,
                        pb::DiscoveryState::Failed,
                        "discovery failed inside the server (logged); the model is unchanged"
                            .into(),
                    )
                });
            let _ = tx.send(outcome);
        });
    if let Err(e) = spawned {
        tracing::error!(error = %e, "cannot start a discovery thread");
    }
    rx
}

/// The calling thread at Linux's SCHED_IDLE (it runs only when no other thread wants the CPU;
/// no privileges needed); elsewhere the lowest priority the platform gives.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    let r = {
        use thread_priority::unix::{
            NormalThreadSchedulePolicy, ThreadSchedulePolicy, set_thread_priority_and_policy,
            thread_native_id,
        };
        set_thread_priority_and_policy(
            thread_native_id(),
            thread_priority::ThreadPriority::Min,
            ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Idle),
        )
    };
    #[cfg(not(target_os = "linux"))]
    let r = thread_priority::set_current_thread_priority(thread_priority::ThreadPriority::Min);
    if let Err(e) = r {
        tracing::warn!(error = ?e, "discovery runs at normal priority");
    }
}

fn failed(
    client_seq: u64,
    points: usize,
    t0: Instant,
    state: pb::DiscoveryState,
    message: String,
) -> Outcome {
    Outcome {
        report: pb::DiscoveryReport {
            client_seq,
            state: state as i32,
            message,
            points_used: points as u32,
            sweeps: parts(points) as u32,
            elapsed_ms: t0.elapsed().as_secs_f64() * 1e3,
            ..Default::default()
        },
        augmented: None,
    }
}

/// The case's physics plus the named effects (kinds it already carries are not added again).
pub fn augmented_physics(case: &Physics, found: &Physics) -> Physics {
    let mut effects = case.effects.clone();
    for e in &found.effects {
        if !effects.iter().any(|c| c.kind == e.kind) {
            effects.push(e.clone());
        }
    }
    Physics { effects }
}

/// The workflow's parameters for a run.
pub fn params(req: &Request, deadline: Instant) -> DiscoverParams {
    let mut p = if req.coarse {
        DiscoverParams::coarse()
    } else {
        DiscoverParams::default()
    };
    p.pipeline = PipelineParams {
        libr: req.libr,
        ..PipelineParams::default()
    };
    p.pipeline.wicp.trusted_alignment_mm = req.trusted_alignment_mm;
    p.pipeline.held = req.held;
    p.deadline = Some(deadline);
    p
}

fn run(req: Request) -> Outcome {
    let t0 = Instant::now();
    let deadline = t0 + req.budget;
    let n = req.measurements.points.len();
    let seq = req.client_seq;
    let pool = match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
        Ok(p) => p,
        Err(e) => {
            return failed(
                seq,
                n,
                t0,
                pb::DiscoveryState::Failed,
                format!("cannot start discovery's thread pool: {e}"),
            );
        }
    };
    pool.install(|| {
        let params = params(&req, deadline);
        let sweeps = session_sweeps(&req.measurements, parts(n));
        let model = &req.case.prepared.model;
        let found = match discover_cohort(model, &sweeps, &params, None, &|_, _, _| {}) {
            Ok(f) => f,
            Err(e) => {
                let state = if matches!(e, DiscoverError::OutOfTime(_)) {
                    pb::DiscoveryState::OutOfTime
                } else {
                    pb::DiscoveryState::Failed
                };
                return failed(
                    seq,
                    n,
                    t0,
                    state,
                    format!("{e}; the model is unchanged"),
                );
            }
        };
        let mut report = done_report(&req, &found, n);
        let mut augmented = None;
        if found.verdict == Verdict::Effects {
            let physics = augmented_physics(&req.case.prepared.physics, &found.physics);
            match build(&req, &physics) {
                Ok(p) if Instant::now() <= deadline => {
                    report.switched = true;
                    report.message = format!(
                        "named {}: held-out misfit {:.2} → {:.2} mm (noise floor {:.2} mm); this session now registers with {}",
                        found.physics.describe(),
                        found.heldout_before_mm,
                        found.heldout_after_mm,
                        found.noise_floor_mm,
                        physics.describe()
                    );
                    augmented = Some(Arc::new(p));
                }
                Ok(_) => {
                    report.state = pb::DiscoveryState::OutOfTime as i32;
                    report.message = format!(
                        "named {}, but its model was ready only after the budget of {:.0} s; the model is unchanged",
                        found.physics.describe(),
                        req.budget.as_secs_f64()
                    );
                }
                Err(e) => {
                    report.state = pb::DiscoveryState::Failed as i32;
                    report.message = format!(
                        "named {}, but its model could not be built ({e}); the model is unchanged",
                        found.physics.describe()
                    );
                }
            }
        }
        report.elapsed_ms = t0.elapsed().as_secs_f64() * 1e3;
        Outcome { report, augmented }
    })
}

fn done_report(req: &Request, found: &CohortDiscovery, n: usize) -> pb::DiscoveryReport {
    let verdict = match found.verdict {
        Verdict::Effects => "effects",
        Verdict::None => "none",
        Verdict::Unexplained => "unexplained",
        Verdict::RefineLoads => "refine-loads",
    };
    let message = match found.verdict {
        Verdict::Effects => String::new(),
        Verdict::None => format!(
            "the points agree with the model within noise (held-out misfit {:.2} mm, noise floor {:.2} mm); the model is unchanged",
            found.heldout_before_mm, found.noise_floor_mm
        ),
        Verdict::Unexplained => format!(
            "the points disagree with the model beyond noise (held-out misfit {:.2} mm, noise floor {:.2} mm) but no effect in the library explains it; the model is unchanged",
            found.heldout_before_mm, found.noise_floor_mm
        ),
        Verdict::RefineLoads => format!(
            "the points ask for richer surface loads than the model's prior allows (held-out misfit {:.2} mm at its λ, {:.2} mm with a weaker prior) and no physical effect adds to them; the model is unchanged",
            found.heldout_at_lambda_mm, found.heldout_before_mm
        ),
    };
    pb::DiscoveryReport {
        client_seq: req.client_seq,
        state: pb::DiscoveryState::Done as i32,
        verdict: verdict.into(),
        effects: found
            .effects
            .iter()
            .map(|e| e.effect.kind.name().to_string())
            .collect(),
        physics_json: if found.physics.is_empty() {
            String::new()
        } else {
            found.physics.to_value(&[]).to_string()
        },
        switched: false,
        message,
        points_used: n as u32,
        sweeps: found.sweeps as u32,
        heldout_before_mm: found.heldout_before_mm,
        heldout_after_mm: found.heldout_after_mm,
        noise_floor_mm: found.noise_floor_mm,
        elapsed_ms: 0.0,
    }
}

/// The session's augmented model: the case's mesh with `physics`, and the case's SR-GCN (which
/// LIBR+ applies only where it learned this physics).
fn build(req: &Request, physics: &Physics) -> Result<Prepared, librplus::pipeline::PipelineError> {
    let case = &req.case.prepared;
    let mut p = Prepared::with_physics(case.model.clone(), Some(&req.libr), physics, None)?
        .with_error_model(case.error_model.clone());
    if let Some(l) = &case.librplus {
        p = p.with_models(l.members.iter().map(|m| m.model.clone()).collect())?;
    }
    Ok(p)
}
