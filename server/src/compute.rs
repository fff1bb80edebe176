//! The compute engine: registrations run on blocking threads, at most `compute_slots` at once,
//! each planned to fit its time budget (queue wait included): fewer LIBR iterations, or the rigid
//! result when LIBR cannot fit, flagged DEGRADED, rather than a late answer.

use crate::cases::Case;
use crate::convert::{method_to_pb, rigid_to_pb};
use crate::error::{Internal, ServiceError, Unavailable, libr_can_fall_back};
use librplus::pipeline::{Method, PipelineParams, register};
use librplus::register::Measurements;
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::Semaphore;

/// One registration to compute.
pub struct Job {
    /// The case.
    pub case: Arc<Case>,
    /// All measurements.
    pub measurements: Measurements,
    /// Method asked for.
    pub method: Method,
    /// Time budget from `arrival`.
    pub budget: Duration,
    /// When the request arrived.
    pub arrival: Instant,
    /// Leave the displacements out of the reply.
    pub omit_displacements: bool,
    /// The initial alignment trusted to this uncertainty (mm), when the client says so.
    pub trusted_alignment_mm: Option<f64>,
    /// The organ is held in place, when the client says so ([`librplus::pipeline::hold`]).
    pub held: bool,
    /// The session's own model (in-surgery discovery switched it to an augmented one), in place
    /// of the case's.
    pub prepared: Option<Arc<librplus::pipeline::Prepared>>,
}

/// Bounded pool of compute slots.
pub struct Engine {
    slots: Arc<Semaphore>,
    /// Unary registrations hold at most this many slots (or wait for them): the rest are the
    /// sessions' (surgeries come first).
    unary: Arc<Semaphore>,
    queued: AtomicUsize,
    max_queued: usize,
    /// Unary registrations waiting or running, per client (principal and connection).
    by_client: std::sync::Mutex<std::collections::HashMap<String, usize>>,
}

impl Engine {
    /// `slots` registrations at once; at most `max_queued` unary requests waiting.
    pub fn new(slots: usize, max_queued: usize) -> Self {
        Self {
            slots: Arc::new(Semaphore::new(slots.max(1))),
            unary: Arc::new(Semaphore::new((slots - slots / 2).max(1))),
            queued: AtomicUsize::new(0),
            max_queued,
            by_client: Default::default(),
        }
    }

    /// Most unary registrations one client may have waiting or running: a quarter of the
    /// queue (at least 1), so that one client's burst cannot fill it.
    pub fn per_client(&self) -> usize {
        (self.max_queued / 4).max(1)
    }

    /// Runs a job. With `bounded` (a unary request, from that client), refuses
    /// (RESOURCE_EXHAUSTED) when `max_queued` jobs already wait or that client already has
    /// [`Engine::per_client`] in the server; sessions are admitted at their start and always
    /// queue.
    pub async fn run(
        &self,
        job: Job,
        bounded: Option<&str>,
    ) -> Result<pb::Registration, ServiceError> {
        let _client = match bounded {
            None => None,
            Some(key) => Some(self.admit_client(key)?),
        };
        let dec = self.admit_queue(bounded.is_some())?;
        // A unary request first takes one of the unary slots, so that no more of them than
        // those wait ahead of a session's update.
        let unary = match bounded {
            Some(_) => Some(
                self.unary
                    .clone()
                    .acquire_owned()
                    .await
                    .map_err(|_| Unavailable::ShuttingDown)?,
            ),
            None => None,
        };
        let permit = self
            .slots
            .clone()
            .acquire_owned()
            .await
            .map_err(|_| Unavailable::ShuttingDown)?;
        drop(dec);
        let handle = tokio::task::spawn_blocking(move || {
            let r = compute(job);
            drop(permit);
            drop(unary);
            r
        });
        match handle.await {
            Ok(r) => r,
            Err(e) => {
                tracing::error!(error = %e, "registration task failed");
                metrics::counter!("librplus_errors_total", "code" => "INTERNAL").increment(1);
                Err(Internal::RegistrationTask(e).into())
            }
        }
    }

    /// Counts a unary registration against its client (`key`), refusing it when the client
    /// already has [`Engine::per_client`] in the server; the count is released on drop.
    fn admit_client(&self, key: &str) -> Result<ClientHold<'_>, ServiceError> {
        let mut m = self.by_client.lock().unwrap_or_else(|e| e.into_inner());
        let n = m.entry(key.to_string()).or_insert(0);
        if *n >= self.per_client() {
            metrics::counter!("librplus_refused_total", "reason" => "client_queue").increment(1);
            return Err(ServiceError::Quota {
                message: format!(
                    "this client already has {n} registrations in the server (limit {} \
                     per client); retry when one is answered",
                    self.per_client()
                ),
                subject: "client_queue",
                description: format!(
                    "at most {} unary registrations per client wait or run at once",
                    self.per_client()
                ),
            });
        }
        *n += 1;
        Ok(ClientHold(self, key.to_string()))
    }

    /// Counts a job as waiting for a compute slot (until the hold drops), refusing a unary one
    /// (`bounded`) when `max_queued` already wait.
    fn admit_queue(&self, bounded: bool) -> Result<QueueHold<'_>, ServiceError> {
        let waiting = self.queued.fetch_add(1, Ordering::SeqCst);
        let hold = QueueHold(&self.queued);
        if bounded && waiting >= self.max_queued {
            metrics::counter!("librplus_refused_total", "reason" => "queue").increment(1);
            return Err(ServiceError::Quota {
                message: format!(
                    "{waiting} registrations are already waiting for a compute slot (limit {}); retry later",
                    self.max_queued
                ),
                subject: "queue",
                description: format!(
                    "at most {} unary registrations wait for a compute slot; retry later",
                    self.max_queued
                ),
            });
        }
        Ok(hold)
    }
}

/// A unary registration counted against its client ([`Engine::admit_client`]).
struct ClientHold<'a>(&'a Engine, String);

impl Drop for ClientHold<'_> {
    fn drop(&mut self) {
        let mut m = self.0.by_client.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = m.get_mut(&self.1) {
            *n -= 1;
            if *n == 0 {
                m.remove(&self.1);
            }
        }
    }
}

/// A job counted as waiting for a compute slot ([`Engine::admit_queue`]).
struct QueueHold<'a>(&'a AtomicUsize);

impl Drop for QueueHold<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// What a registration ran into, for [`judge`].
struct Outcome<'a> {
    degenerate: Option<&'a str>,
    fallback: Option<String>,
    degraded: Option<String>,
    refit_error: Option<&'a str>,
    refit: Option<&'a librplus::register::libr::LibrInfo>,
    libr: Option<&'a librplus::register::libr::LibrInfo>,
    rigid_converged: bool,
    rigid_iterations: usize,
    /// Why the pose is ambiguous, when it is.
    ambiguous_pose: Option<String>,
    /// Why the answer has likely failed, when the error estimate says so.
    likely_failed: Option<String>,
}

/// The error estimate's failure probability from which an answer is flagged
/// `QUALITY_LIKELY_FAILED`. On the paper preset (seed 2, 500 LIBR registrations with the gated
/// pose search, the built-in error model) this flag or an ambiguous pose catches 9 of the 14
/// wrong answers (mean TRE > 20 mm) and flags 17 of the 486 others; at 0.5, 7 and 12.
pub const LIKELY_FAILED_PROBABILITY: f64 = 0.3;

/// Why an answer has likely failed, from its error estimate (None: not likely).
fn likely_failed(e: Option<&librplus::register::uncertainty::ErrorEstimate>) -> Option<String> {
    let e = e?;
    let p = e.failure_probability?;
    (p >= LIKELY_FAILED_PROBABILITY).then(|| {
        format!(
            "the error estimate gives a {:.0} % chance that the mean error exceeds {:.0} mm (predicted mean error {:.1} mm): check the alignment",
            100.0 * p,
            e.failure_threshold_mm.unwrap_or(f64::NAN),
            e.predicted_tre_mm
        )
    })
}

/// The answer's quality and its reason: the first that applies of degenerate data, a fallback,
/// a planned degradation, a failed or cut-short refit, LIBR cut short, not converged.
fn judge(o: &Outcome<'_>, budget: Duration, params: &PipelineParams) -> (pb::Quality, String) {
    if let Some(r) = o.degenerate {
        (pb::Quality::Degenerate, format!("degenerate data: {r}"))
    } else if let Some(r) = &o.fallback {
        (pb::Quality::Degenerate, r.clone())
    } else if let Some(r) = &o.ambiguous_pose {
        (pb::Quality::AmbiguousPose, r.clone())
    } else if let Some(r) = &o.likely_failed {
        (pb::Quality::LikelyFailed, r.clone())
    } else if let Some(r) = &o.degraded {
        (pb::Quality::Degraded, r.clone())
    } else if let Some(e) = o.refit_error {
        (
            pb::Quality::Degraded,
            format!("LIBR+'s refit failed ({e}); the answer is the network's correction of LIBR"),
        )
    } else if let Some(i) = o.refit.filter(|i| i.stopped_at_deadline) {
        // Finding 7.5: a refit cut short is not the full computation either.
        (
            pb::Quality::Degraded,
            format!(
                "time budget {:.0} ms: LIBR+'s refit stopped after {} of {} iterations",
                ms(budget),
                i.iterations,
                params.refit_iterations
            ),
        )
    } else if let Some(i) = o.libr.filter(|i| i.stopped_at_deadline) {
        (
            pb::Quality::Degraded,
            format!(
                "time budget {:.0} ms: LIBR stopped after {} of {} iterations",
                ms(budget),
                i.iterations,
                params.libr.max_iterations
            ),
        )
    } else if let Some(i) = o.libr.filter(|i| !i.settled) {
        // Not settled: the objective was still falling, or the model running away, when the
        // iteration cap came (a fit that cycles around a flat objective is settled, and OK).
        (
            pb::Quality::NotConverged,
            format!(
                "LIBR ran its {} iterations without settling; the last moved the model by up to {:.2} mm (tolerance {} mm)",
                i.iterations,
                i.movement_history_mm.last().copied().unwrap_or(f64::NAN),
                params.libr.tolerance_mm
            ),
        )
    } else if !o.rigid_converged && o.libr.is_none() {
        (
            pb::Quality::NotConverged,
            format!(
                "the rigid stage ran its {} iterations without converging",
                o.rigid_iterations
            ),
        )
    } else {
        (pb::Quality::Ok, String::new())
    }
}

/// How many single registrations' time the pose search takes, with a margin (measured about six
/// on the paper liver, 2 cores; up to eight on a 1,800-node liver, whose fixed costs weigh more).
const POSE_SEARCH_COST: f64 = 8.0;

/// What a registration was planned to be within its budget.
struct Plan {
    /// The method it runs (LIBR+ → LIBR → rigid when the budget cannot hold more).
    method: Method,
    /// Why it runs less than was asked for.
    degraded: Option<String>,
    params: PipelineParams,
    /// Time spent waiting for a compute slot (ms).
    queue_ms: f64,
    /// Why the pose search was turned off (the budget left could not hold it); said in the
    /// answer when the registration needed it
    /// ([`librplus::pipeline::Registration::search_skipped_mm2`]).
    search_off: Option<String>,
}

/// Plans and runs one registration within its budget.
fn compute(job: Job) -> Result<pb::Registration, ServiceError> {
    let prepared = job.prepared.as_deref().unwrap_or(&job.case.prepared);
    let mut plan = plan(&job, prepared, Instant::now());
    let mut result = register(prepared, &job.measurements, plan.method, &plan.params);
    let mut fallback: Option<String> = None;
    if let (Err(e), Method::Libr | Method::LibrPlus) = (&result, plan.method)
        && libr_can_fall_back(e)
    {
        // The data stopped LIBR (too few, degenerate or clustered points): the rigid result,
        // flagged, is still the best available answer. Any other error is the server's and is
        // reported as such.
        fallback = Some(format!("LIBR could not run: {e}; rigid result"));
        plan.method = Method::Rigid;
        result = register(prepared, &job.measurements, plan.method, &plan.params);
    }
    let reg = result?;
    job.case.observe(
        reg.rigid.seconds * 1e3,
        reg.libr.as_ref().map(|i| (i.total_s * 1e3, i.iterations)),
    );
    if let (Some(why), Some(score)) = (&plan.search_off, reg.search_skipped_mm2) {
        // Never silently: the registration the gate would have searched says it was not.
        plan.degraded.get_or_insert_with(|| {
            format!(
                "{why}: the pose search was skipped, though the navigation start's fit scored {score:.1} mm² (the search runs above {:.1} mm²)",
                plan.params.pose.search_above_mm2
            )
        });
    }
    if let Some(c) = reg.correction.as_ref().filter(|c| !c.applied) {
        plan.method = Method::Libr;
        plan.degraded.get_or_insert_with(|| {
            c.skipped
                .clone()
                .unwrap_or_else(|| "SR-GCN correction skipped".into())
        });
    }
    let (quality, reason) = judge(
        &outcome(&reg, fallback, plan.degraded.take()),
        job.budget,
        &plan.params,
    );
    let total_ms = ms(job.arrival.elapsed());
    let (quality, reason) = late(&job, &reg, &plan, quality, reason, total_ms);
    record_stages(&reg, &plan, quality, total_ms);
    Ok(answer(
        &job, prepared, &reg, &plan, quality, reason, total_ms,
    ))
}

/// The method and parameters that fit the time left: LIBR+ only when the SR-GCN fits, LIBR
/// when two iterations fit, else the rigid result; the pose search only when about
/// [`POSE_SEARCH_COST`] registrations fit.
fn plan(job: &Job, prepared: &librplus::pipeline::Prepared, start: Instant) -> Plan {
    let queue_ms = ms(start - job.arrival);
    let deadline = job.arrival + job.budget;
    let est = job.case.estimates();
    let mut method = job.method;
    let mut degraded: Option<String> = None;
    let mut params = PipelineParams::default();
    params.wicp.trusted_alignment_mm = job.trusted_alignment_mm;
    params.held = job.held;
    let gcn_ms = prepared
        .librplus
        .as_ref()
        .map_or(0.0, |g| 1e3 * g.expected_seconds());
    let left = ms(deadline.saturating_duration_since(start));
    if method == Method::LibrPlus {
        let need = est.rigid_ms + est.libr_fixed_ms + 2.0 * est.libr_iteration_ms + gcn_ms;
        if left < need {
            method = Method::Libr;
            degraded = Some(format!(
                "time budget {:.0} ms: {left:.0} ms left, LIBR+ needs about {need:.0} ms (SR-GCN {gcn_ms:.0} ms); LIBR result",
                ms(job.budget)
            ));
            if left >= need - gcn_ms {
                // The SR-GCN estimate alone did not fit: let it fall slowly, so that a
                // correction once timed slow (a busy machine) is tried and timed again.
                if let Some(g) = &prepared.librplus {
                    g.relax_estimate();
                }
            }
        }
    }
    if matches!(method, Method::Libr | Method::LibrPlus) {
        let need = est.rigid_ms + est.libr_fixed_ms + 2.0 * est.libr_iteration_ms;
        if left < need {
            method = Method::Rigid;
            degraded = Some(format!(
                "time budget {:.0} ms: {queue_ms:.0} ms waiting for a compute slot left {left:.0} ms, LIBR needs about {need:.0} ms; rigid result",
                ms(job.budget)
            ));
        } else {
            params.deadline =
                Some(deadline - Duration::from_secs_f64(est.libr_fixed_ms.max(0.0) / 1e3));
        }
    }
    // The pose search (`librplus::pipeline::pose`) costs about six single registrations: it
    // runs when the budget left holds that many, otherwise the navigation start alone.
    let left = ms(deadline.saturating_duration_since(Instant::now()));
    let one = est.rigid_ms
        + if matches!(method, Method::Rigid | Method::V2s) {
            0.0
        } else {
            est.libr_fixed_ms + 10.0 * est.libr_iteration_ms
        };
    let mut search_off = None;
    if left < POSE_SEARCH_COST * one {
        params.pose.start_angles_deg.clear();
        search_off = Some(format!(
            "time budget {:.0} ms: {left:.0} ms left, the pose search needs about {:.0} ms",
            ms(job.budget),
            POSE_SEARCH_COST * one
        ));
    }
    Plan {
        method,
        degraded,
        params,
        queue_ms,
        search_off,
    }
}

/// What the quality judgement reads of a registration.
fn outcome(
    reg: &librplus::pipeline::Registration,
    fallback: Option<String>,
    degraded: Option<String>,
) -> Outcome<'_> {
    let gcn = reg.correction.as_ref();
    Outcome {
        degenerate: reg.rigid.degenerate.as_deref(),
        fallback,
        degraded,
        refit_error: gcn.and_then(|c| c.refit_error.as_deref()),
        refit: gcn.and_then(|c| c.refit.as_ref()),
        libr: reg.libr.as_ref(),
        rigid_converged: reg.rigid.converged,
        rigid_iterations: reg.rigid.iterations,
        likely_failed: likely_failed(reg.error.as_ref()),
        ambiguous_pose: reg.pose.as_ref().filter(|p| p.ambiguous).map(|p| {
            let mut sorted = p.scores.clone();
            sorted.sort_by(f64::total_cmp);
            format!(
                "two rigid poses {:.0} mm apart explain the points about equally after the deformable fit (scores {:.2} and {:.2} mm²): the answer is the better one and may be wrong",
                p.runner_up_mm.unwrap_or(0.0),
                sorted[0],
                sorted.get(1).copied().unwrap_or(f64::NAN)
            )
        }),
    }
}

/// An answer later than its budget says so (the plan keeps to it when the estimates hold; a
/// slow machine, a huge request or a tiny budget may not).
fn late(
    job: &Job,
    reg: &librplus::pipeline::Registration,
    plan: &Plan,
    quality: pb::Quality,
    reason: String,
    total_ms: f64,
) -> (pb::Quality, String) {
    let budget_ms = ms(job.budget);
    if total_ms <= budget_ms {
        return (quality, reason);
    }
    match quality {
        pb::Quality::Ok | pb::Quality::NotConverged | pb::Quality::Degraded => (
            pb::Quality::Degraded,
            format!(
                "over its time budget: answered in {total_ms:.0} ms of {budget_ms:.0} ms ({} points; \
                 {:.0} ms waiting, rigid stage {:.0} ms){}",
                job.measurements.points.len(),
                plan.queue_ms,
                reg.rigid.seconds * 1e3,
                if reason.is_empty() {
                    String::new()
                } else {
                    format!("; {reason}")
                }
            ),
        ),
        // An ambiguous pose or a likely failure stays flagged as such, and says it was late too.
        pb::Quality::AmbiguousPose | pb::Quality::LikelyFailed => (
            quality,
            format!(
                "{reason}; over its time budget too: answered in {total_ms:.0} ms of {budget_ms:.0} ms"
            ),
        ),
        _ => (quality, reason),
    }
}

/// Stage timings and the registration count, as metrics.
fn record_stages(
    reg: &librplus::pipeline::Registration,
    plan: &Plan,
    quality: pb::Quality,
    total_ms: f64,
) {
    let stage = |name: &'static str, v: f64| {
        metrics::histogram!("librplus_stage_seconds", "stage" => name).record(v / 1e3);
    };
    stage("queue", plan.queue_ms);
    stage("rigid", reg.rigid.seconds * 1e3);
    if let Some(l) = &reg.libr {
        stage("libr", l.total_s * 1e3);
    }
    if let Some(c) = &reg.correction {
        stage("gcn", c.seconds * 1e3);
        if let Some(r) = &c.refit {
            stage("refit", r.total_s * 1e3);
        }
    }
    stage("total", total_ms);
    metrics::counter!("librplus_registrations_total", "method" => plan.method.name(), "quality" => quality.as_str_name()).increment(1);
}

/// The reply to a registration.
fn answer(
    job: &Job,
    prepared: &librplus::pipeline::Prepared,
    reg: &librplus::pipeline::Registration,
    plan: &Plan,
    quality: pb::Quality,
    reason: String,
    total_ms: f64,
) -> pb::Registration {
    let gcn = reg.correction.as_ref();
    let info = reg.libr.as_ref();
    let refit = gcn.and_then(|c| c.refit.as_ref());
    pb::Registration {
        image_to_physical: Some(rigid_to_pb(&reg.image_to_physical)),
        displacement_mm: if job.omit_displacements {
            Vec::new()
        } else {
            reg.u.iter().map(|&x| x as f32).collect()
        },
        node_count: prepared.model.mesh.num_nodes() as u32,
        method_used: method_to_pb(plan.method) as i32,
        residual_rms_mm: refit.or(info).map_or(reg.rigid.rms_mm, |i| i.rms_mm),
        points_used: job.measurements.points.len() as u32,
        points_matched: reg.rigid.matched as u32,
        timings: Some(pb::StageTimings {
            queue_ms: plan.queue_ms,
            rigid_ms: reg.rigid.seconds * 1e3,
            libr_ms: info.map_or(0.0, |i| i.total_s * 1e3),
            libr_matching_ms: info.map_or(0.0, |i| i.matching_s * 1e3),
            libr_assemble_ms: info.map_or(0.0, |i| i.assemble_s * 1e3),
            libr_solve_ms: info.map_or(0.0, |i| i.solve_s * 1e3),
            gcn_ms: gcn.map_or(0.0, |c| c.seconds * 1e3),
            total_ms,
            libr_iterations: info.map_or(0, |i| i.iterations as u32),
            refit_ms: refit.map_or(0.0, |i| i.total_s * 1e3),
            refit_iterations: refit.map_or(0, |i| i.iterations as u32),
        }),
        quality: quality as i32,
        quality_reason: reason,
        effects: crate::convert::effects(prepared),
        rigid_ill_posed: reg.rigid.ill_posed,
        error_estimate: reg
            .error
            .as_ref()
            .map(|e| error_estimate(e, job.omit_displacements)),
    }
}

/// The reply's error estimate (the per-node bound left out with the displacements).
fn error_estimate(
    e: &librplus::register::uncertainty::ErrorEstimate,
    omit: bool,
) -> pb::ErrorEstimate {
    pb::ErrorEstimate {
        predicted_tre_mm: e.predicted_tre_mm,
        level: e.level,
        node_uncertainty_mm: if omit {
            Vec::new()
        } else {
            e.node_bound_mm.iter().map(|&x| x as f32).collect()
        },
        coverage_mean_mm: e.features.coverage_mean_mm,
        surface_covered: e.features.surface_covered,
        strain_energy_uj: e.features.strain_energy_uj,
        failure: e.failure_probability.zip(e.failure_threshold_mm).map(
            |(probability, threshold_mm)| pb::FailureEstimate {
                probability,
                threshold_mm,
            },
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use librplus::register::libr::LibrInfo;

    fn clean<'a>(libr: Option<&'a LibrInfo>, refit: Option<&'a LibrInfo>) -> Outcome<'a> {
        Outcome {
            degenerate: None,
            fallback: None,
            degraded: None,
            refit_error: None,
            refit,
            libr,
            rigid_converged: true,
            rigid_iterations: 10,
            ambiguous_pose: None,
            likely_failed: None,
        }
    }

    /// An answer the error estimate gives a high failure probability is flagged LIKELY_FAILED
    /// (from [`LIKELY_FAILED_PROBABILITY`] on), with the probability and the prediction in its
    /// reason; below it, or without a failure part, it is not.
    #[test]
    fn a_likely_failure_is_flagged() {
        let params = PipelineParams::default();
        let est = |p: Option<f64>| librplus::register::uncertainty::ErrorEstimate {
            predicted_tre_mm: 23.4,
            level: 0.9,
            node_bound_mm: Vec::new(),
            failure_probability: p,
            failure_threshold_mm: Some(20.0),
            features: Default::default(),
            seconds: 0.0,
        };
        assert_eq!(likely_failed(None), None);
        assert_eq!(likely_failed(Some(&est(None))), None);
        assert_eq!(
            likely_failed(Some(&est(Some(LIKELY_FAILED_PROBABILITY - 1e-9)))),
            None
        );
        let why = likely_failed(Some(&est(Some(0.47)))).unwrap();
        assert!(
            why.contains("47 %") && why.contains("20 mm") && why.contains("23.4 mm"),
            "{why}"
        );
        let libr = LibrInfo {
            settled: true,
            ..LibrInfo::default()
        };
        let o = Outcome {
            likely_failed: Some(why.clone()),
            ..clean(Some(&libr), None)
        };
        let (q, r) = judge(&o, Duration::from_millis(250), &params);
        assert_eq!((q, r), (pb::Quality::LikelyFailed, why));
        // An ambiguous pose says more (which poses) and comes first.
        let o = Outcome {
            ambiguous_pose: Some("two poses".into()),
            ..o
        };
        assert_eq!(
            judge(&o, Duration::from_millis(250), &params).0,
            pb::Quality::AmbiguousPose
        );
    }

    /// Finding 7.5: a LIBR+ answer whose refit ran 1 of its 5 iterations (the deadline) was
    /// flagged OK; it is DEGRADED, and says how far the refit got.
    #[test]
    fn a_refit_cut_short_is_degraded() {
        let params = PipelineParams::default();
        let budget = Duration::from_millis(250);
        let libr = LibrInfo {
            iterations: 4,
            converged: true,
            settled: true,
            ..Default::default()
        };
        let full = LibrInfo {
            iterations: params.refit_iterations,
            converged: true,
            settled: true,
            ..Default::default()
        };
        assert_eq!(
            judge(&clean(Some(&libr), Some(&full)), budget, &params).0,
            pb::Quality::Ok
        );
        let cut = LibrInfo {
            iterations: 1,
            stopped_at_deadline: true,
            ..full.clone()
        };
        let (q, why) = judge(&clean(Some(&libr), Some(&cut)), budget, &params);
        assert_eq!(q, pb::Quality::Degraded);
        assert!(why.contains("refit stopped after 1 of"), "{why}");
        // LIBR cut short, and not converged, keep their flags.
        let libr_cut = LibrInfo {
            stopped_at_deadline: true,
            ..libr.clone()
        };
        assert_eq!(
            judge(&clean(Some(&libr_cut), None), budget, &params).0,
            pb::Quality::Degraded
        );
        // Settled without converging (nodes cycling around a flat objective) is OK; not
        // settled is NOT_CONVERGED.
        let cycling = LibrInfo {
            converged: false,
            ..libr.clone()
        };
        assert_eq!(
            judge(&clean(Some(&cycling), None), budget, &params).0,
            pb::Quality::Ok
        );
        let unconverged = LibrInfo {
            converged: false,
            settled: false,
            ..libr
        };
        assert_eq!(
            judge(&clean(Some(&unconverged), None), budget, &params).0,
            pb::Quality::NotConverged
        );
    }
}
