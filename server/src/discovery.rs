//! In-surgery discovery (opt in per session): the `librplus discover` workflow on the points a
//! session has received so far, run in the background so that it never delays a registration
//! update, and the switch to the augmented model when an effect is named.
//!
//! - **Where it runs.** One OS thread per run with a one-thread rayon pool, both at Linux's
//!   `SCHED_IDLE` (elsewhere the lowest priority): registrations keep their compute slots and
//!   the global pool, any of their threads that wakes takes the CPU from the run at once, and
//!   the run gets only the CPU time they leave (a core of an idle machine, nothing of a busy
//!   one).
//! - **Bounded.** The run stops at its budget (checked between the workflow's steps, see
//!   [`librplus::discover::DiscoverParams::deadline`]); a run that overruns is reported
//!   `OUT_OF_TIME` and changes nothing. A watchdog on the server's runtime sends that report
//!   [`REPORT_GRACE`] after the budget when the run has not ended by then (a step that the busy
//!   machine gives no CPU time cannot reach its next check), so every run is reported in time
//!   however loaded the machine is. One run per session at a time.
//! - **Never silent.** Every outcome, a failure too, carries its reason in `message`.
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
use librplus::pipeline::Prepared;
use librplus::register::Checked;
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
    pub measurements: Checked,
    /// The session's trusted-alignment uncertainty, if any.
    pub trusted_alignment_mm: Option<f64>,
    /// The session's organ is held ([`librplus::pipeline::hold`]).
    pub held: bool,
    /// Wall-clock limit.
    pub budget: Duration,
    /// The coarse search grid.
    pub coarse: bool,
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

/// How long after its budget a run that has not ended is reported `OUT_OF_TIME` by its
/// watchdog: the run checks its deadline only between steps, and on a busy machine a step may
/// get no CPU time at all.
pub const REPORT_GRACE: Duration = Duration::from_secs(1);

/// Where a run's outcome goes: sent once, by the run or by its watchdog, whichever comes first.
type Slot = Arc<std::sync::Mutex<Option<oneshot::Sender<Outcome>>>>;

/// Sends `outcome` unless the slot's outcome was already sent; whether it was sent now.
fn deliver(slot: &Slot, outcome: Outcome) -> bool {
    let tx = slot.lock().unwrap_or_else(|e| e.into_inner()).take();
    match tx {
        Some(tx) => {
            let _ = tx.send(outcome);
            true
        }
        None => false,
    }
}

/// Starts a run on its own threads; the receiver gets its outcome (a failure is an outcome
/// too, with its reason) at the latest [`REPORT_GRACE`] after the budget, however busy the
/// machine is.
pub fn spawn(req: Request) -> oneshot::Receiver<Outcome> {
    let (tx, rx) = oneshot::channel();
    let slot: Slot = Arc::new(std::sync::Mutex::new(Some(tx)));
    let t0 = Instant::now();
    let (seq, n, budget) = (req.client_seq, req.measurements.points.len(), req.budget);
    let watchdog = watchdog(slot.clone(), seq, n, budget, t0);
    let mine = slot.clone();
    let spawned = std::thread::Builder::new()
        .name("discovery".into())
        .spawn(move || {
            lower_priority();
            let outcome =
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(req, t0)))
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
            if let Some(w) = &watchdog {
                w.abort();
            }
            if !deliver(&mine, outcome) {
                tracing::info!(
                    elapsed_ms = t0.elapsed().as_secs_f64() * 1e3,
                    "discovery ended after its budget; it was reported out of time, its result is dropped"
                );
            }
        });
    if let Err(e) = spawned {
        tracing::error!(error = %e, "cannot start a discovery thread");
        deliver(
            &slot,
            failed(
                seq,
                n,
                t0,
                pb::DiscoveryState::Failed,
                format!(
                    "discovery could not start: no thread for it ({e}); the model is unchanged"
                ),
            ),
        );
    }
    rx
}

/// The run's watchdog: at its budget plus [`REPORT_GRACE`], reports it `OUT_OF_TIME` unless
/// it was reported already. A task on the server's runtime (its handle, to abort it when the
/// run ends first), or a thread of its own outside one.
fn watchdog(
    slot: Slot,
    seq: u64,
    points: usize,
    budget: Duration,
    t0: Instant,
) -> Option<tokio::task::AbortHandle> {
    let at = t0 + budget + REPORT_GRACE;
    let fire = move || {
        let message = format!(
            "out of time: the run had not finished {:.1} s after it started (budget {:.0} s); \
             discovery gets only the CPU time that registrations and other programs leave, \
             and the machine left it too little; the model is unchanged",
            t0.elapsed().as_secs_f64(),
            budget.as_secs_f64()
        );
        if deliver(
            &slot,
            failed(seq, points, t0, pb::DiscoveryState::OutOfTime, message),
        ) {
            tracing::warn!(
                budget_s = budget.as_secs_f64(),
                "discovery reported out of time by its watchdog (the machine is busy)"
            );
        }
    };
    match tokio::runtime::Handle::try_current() {
        Ok(h) => Some(
            h.spawn(async move {
                tokio::time::sleep_until(tokio::time::Instant::from_std(at)).await;
                fire();
            })
            .abort_handle(),
        ),
        Err(_) => {
            let spawned = std::thread::Builder::new()
                .name("discovery-watchdog".into())
                .spawn(move || {
                    std::thread::sleep(at.saturating_duration_since(Instant::now()));
                    fire();
                });
            if let Err(e) = spawned {
                tracing::error!(error = %e, "cannot start a discovery watchdog");
            }
            None
        }
    }
}

/// Threads of a run's pool: one. Runs of several sessions at once use several cores; with two
/// threads each, three runs side by side on two cores took about 30 % more CPU time than with
/// one (parallel steps waiting on each other) and ended later.
const POOL_THREADS: usize = 1;

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
    // The case's own parameters: its basis was built with their LIBR settings.
    p.pipeline = req.case.params.clone();
    p.pipeline.wicp.trusted_alignment_mm = req.trusted_alignment_mm;
    p.pipeline.held = req.held;
    p.deadline = Some(deadline);
    p
}

/// The run (started at `t0`) on its own pool.
fn run(req: Request, t0: Instant) -> Outcome {
    let deadline = t0 + req.budget;
    let n = req.measurements.points.len();
    let seq = req.client_seq;
    let pool = match rayon::ThreadPoolBuilder::new()
        .num_threads(POOL_THREADS)
        .thread_name(|i| format!("discovery-{i}"))
        .start_handler(|_| lower_priority())
        .build()
    {
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
        tracing::info!(
            verdict = ?found.verdict,
            register_s = found.timings.register_s,
            find_s = found.timings.find_s,
            name_s = found.timings.name_s,
            total_s = found.timings.total_s,
                        "discovery workflow done"
        );
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
    let mut p = Prepared::with_physics(
        case.model.clone(),
        Some(&req.case.params.libr),
        physics,
        None,
    )?
    .with_error_model(case.error_model.clone());
    if let Some(l) = &case.librplus {
        p = p.with_models(l.members.iter().map(|m| m.model.clone()).collect())?;
    }
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slot() -> (Slot, oneshot::Receiver<Outcome>) {
        let (tx, rx) = oneshot::channel();
        (Arc::new(std::sync::Mutex::new(Some(tx))), rx)
    }

    /// A run that has not ended by its budget (a step the busy machine gives no CPU time) is
    /// reported `OUT_OF_TIME` by its watchdog [`REPORT_GRACE`] after the budget, with its
    /// reason, and the run's own outcome, when it comes, is not sent again.
    #[tokio::test]
    async fn a_run_past_its_budget_is_reported_by_its_watchdog() {
        let (slot, rx) = slot();
        let budget = Duration::from_millis(200);
        let t0 = Instant::now();
        let _w = watchdog(slot.clone(), 7, 321, budget, t0);
        let o = tokio::time::timeout(Duration::from_secs(30), rx)
            .await
            .expect("reported in time")
            .expect("an outcome");
        let waited = t0.elapsed();
        assert!(waited >= budget + REPORT_GRACE, "{waited:?}");
        let r = &o.report;
        assert_eq!(r.state, pb::DiscoveryState::OutOfTime as i32);
        assert_eq!((r.client_seq, r.points_used), (7, 321));
        assert!(r.message.starts_with("out of time"), "{}", r.message);
        assert!(
            r.message.contains("the model is unchanged"),
            "{}",
            r.message
        );
        assert!(r.elapsed_ms >= 1e3 * (budget + REPORT_GRACE).as_secs_f64() - 1.0);
        assert!(o.augmented.is_none());
        let late = failed(7, 321, t0, pb::DiscoveryState::Done, "late".into());
        assert!(!deliver(&slot, late));
    }

    /// A run that ends first is the one reported; its watchdog, outside a runtime a thread of
    /// its own, then finds nothing to send.
    #[test]
    fn a_run_that_ends_first_is_the_one_reported() {
        let (slot, mut rx) = slot();
        let t0 = Instant::now();
        assert!(watchdog(slot.clone(), 3, 250, Duration::ZERO, t0).is_none());
        let done = failed(3, 250, t0, pb::DiscoveryState::Done, "finished".into());
        assert!(deliver(&slot, done));
        std::thread::sleep(REPORT_GRACE + Duration::from_millis(300));
        let o = rx.try_recv().expect("the run's outcome");
        assert_eq!(o.report.state, pb::DiscoveryState::Done as i32);
        assert_eq!(o.report.message, "finished");
    }
}
