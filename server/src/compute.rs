//! The compute engine: registrations run on blocking threads, at most `compute_slots` at once,
//! each planned to fit its time budget (queue wait included): fewer LIBR iterations, or the rigid
//! result when LIBR cannot fit, flagged DEGRADED, rather than a late answer.

use crate::cases::Case;
use crate::convert::{method_to_pb, rigid_to_pb};
use crate::counted::{KeyHold, PerKey};
use crate::error::{Internal, ServiceError, Unavailable, libr_can_fall_back};
use librplus::pipeline::quality::Circumstances;
use librplus::pipeline::{Method, PipelineParams, Registration, register};
use librplus::register::Checked;
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};
use tokio::sync::Semaphore;

/// What a client asks of a registration, checked where it arrived (a unary request, or a
/// session's start and messages) and not again: the measurements, the method and the options.
/// A session keeps one and appends its messages' points to it; each of its registrations shares
/// it (the measurements are an [`Arc`] inside [`Checked`]: a job never copies them).
#[derive(Debug, Clone)]
pub struct Request {
    /// All measurements.
    pub measurements: Checked,
    /// Method asked for (checked against what the case was prepared for).
    pub method: Method,
    /// The options.
    pub options: Options,
}

/// A request's options, checked where the request arrived (a unary call's or a session start's
/// `RegisterOptions`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Options {
    /// Time budget from the request's arrival.
    pub budget: Duration,
    /// Leave the displacements out of the reply.
    pub omit_displacements: bool,
    /// The initial alignment trusted to this uncertainty (mm), when the client says so.
    pub trusted_alignment_mm: Option<f64>,
    /// The organ is held in place, when the client says so ([`librplus::pipeline::hold`]).
    pub held: bool,
    /// METHOD_NONLINEAR answers once (the refined answer) even in a stream.
    pub single_answer: bool,
}

/// One registration to compute: a case and a request.
pub struct Job {
    /// The case.
    pub case: Arc<Case>,
    /// What the client asks (its budget: the time left of the request's or session's).
    pub request: Request,
    /// When the request arrived.
    pub arrival: Instant,
    /// The session's own model (in-surgery discovery switched it to an augmented one), in place
    /// of the case's.
    pub prepared: Option<Arc<librplus::pipeline::Prepared>>,
    /// Where METHOD_NONLINEAR's linear answer goes as soon as it is made, its refinement to
    /// follow (a stream's; None: one answer, the refined one).
    pub first: Option<tokio::sync::mpsc::UnboundedSender<pb::Registration>>,
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
    by_client: Arc<PerKey>,
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
    fn admit_client(&self, key: &str) -> Result<KeyHold, ServiceError> {
        self.by_client
            .try_hold(key, self.per_client())
            .map_err(|n| {
                metrics::counter!("librplus_refused_total", "reason" => "client_queue")
                    .increment(1);
                ServiceError::Quota {
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
                }
            })
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

/// The wire's quality flag of the library's.
pub fn quality_to_pb(q: librplus::pipeline::quality::Quality) -> pb::Quality {
    use librplus::pipeline::quality::Quality;
    match q {
        Quality::Ok => pb::Quality::Ok,
        Quality::NotConverged => pb::Quality::NotConverged,
        Quality::Degraded => pb::Quality::Degraded,
        Quality::Degenerate => pb::Quality::Degenerate,
        Quality::AmbiguousPose => pb::Quality::AmbiguousPose,
        Quality::AmbiguousModel => pb::Quality::AmbiguousModel,
        Quality::LikelyFailed => pb::Quality::LikelyFailed,
    }
}

/// How many single registrations' time the pose search takes, with a margin (measured about six
/// on the paper liver, 2 cores; up to eight on a 1,800-node liver, whose fixed costs weigh more).
const POSE_SEARCH_COST: f64 = 8.0;

/// How many LIBR registrations' time the automatic choice takes, with a margin: its four
/// deformable candidates (LIBR, adaptive LIBR and their held variants) share the compute
/// slot's cores, and each is cross-validated on its last matches (`BENCHMARKS.md`).
const AUTO_COST: f64 = 4.0;

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
    coarse_plan(&job, prepared, &mut plan);
    let meas = &job.request.measurements;
    let mut result = register_job(&job, prepared, &plan);
    let mut fallback: Option<String> = None;
    if let (Err(e), Method::Libr | Method::LibrPlus | Method::Auto) = (&result, plan.method)
        && libr_can_fall_back(e)
    {
        // The data stopped LIBR (too few, degenerate or clustered points): the rigid result,
        // flagged, is still the best available answer. Any other error is the server's and is
        // reported as such.
        fallback = Some(format!("LIBR could not run: {e}; rigid result"));
        plan.method = Method::Rigid;
        result = register(prepared, meas, plan.method, &plan.params);
    }
    let reg = result?;
    // A deformable answer's time outside its rigid stage, LIBR and the SR-GCN (the search's,
    // when one ran, is the rigid stage's: no other estimate counts it).
    let other_ms = reg.libr.as_ref().filter(|_| reg.pose.is_none()).map(|l| {
        let gcn = reg.correction.as_ref().map_or(0.0, |c| c.seconds);
        (reg.seconds - reg.rigid.seconds - l.total_s - gcn) * 1e3
    });
    job.case.observe(
        reg.rigid.seconds * 1e3,
        reg.libr.as_ref().map(|i| (i.total_s * 1e3, i.iterations)),
        other_ms,
    );
    crate::refine::observe(&job.case, &reg);
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
    let circumstances = Circumstances {
        fallback,
        degraded: plan.degraded.clone(),
        budget_ms: Some(ms(job.request.options.budget)),
    };
    let mut out = judged_answer(&job, prepared, &reg, &plan, circumstances);
    let asked = job.request.method;
    let refines = job.first.is_some() && !job.request.options.single_answer;
    out.refinement = crate::refine::refinement_pb(asked, refines, &reg, plan.degraded.as_deref());
    Ok(out)
}

/// Runs a job's registration as planned: METHOD_NONLINEAR with somewhere to send its linear
/// answer hands it over there first (judged and put on the wire as any answer, with
/// `refinement.follows` set); every other registration answers once.
fn register_job(
    job: &Job,
    prepared: &librplus::pipeline::Prepared,
    plan: &Plan,
) -> Result<Registration, librplus::pipeline::PipelineError> {
    let to = job
        .first
        .as_ref()
        .filter(|_| !job.request.options.single_answer);
    let send = |r: &Registration| {
        let circumstances = Circumstances {
            degraded: plan.degraded.clone(),
            budget_ms: Some(ms(job.request.options.budget)),
            ..Default::default()
        };
        let mut out = judged_answer(job, prepared, r, plan, circumstances);
        out.refinement = Some(pb::Refinement {
            follows: true,
            ..Default::default()
        });
        // The session may have ended meanwhile: nothing then waits for it.
        if let Some(tx) = to {
            let _ = tx.send(out);
        }
    };
    let first = to.map(|_| &send as librplus::pipeline::FirstAnswer<'_>);
    let meas = &job.request.measurements;
    crate::refine::register_planned(prepared, meas, (plan.method, &plan.params), first)
}

/// A registration judged (its quality and reason, late or not) and put on the wire.
fn judged_answer(
    job: &Job,
    prepared: &librplus::pipeline::Prepared,
    reg: &Registration,
    plan: &Plan,
    circumstances: Circumstances,
) -> pb::Registration {
    let judged = librplus::pipeline::quality::judge(reg, &plan.params, &circumstances);
    let (quality, reason) = (quality_to_pb(judged.quality), judged.reason);
    let total_ms = ms(job.arrival.elapsed());
    let (quality, reason) = late(job, reg, plan, quality, reason, total_ms);
    if !reg.refinement_follows {
        // One registration counted, at its final answer.
        record_stages(reg, plan, quality, total_ms);
    }
    let mut out = answer(job, prepared, reg, plan, quality, reason, total_ms);
    // A provisional answer names its own method (the linear fit the refinement follows).
    if reg.refinement_follows {
        out.method_used = method_to_pb(reg.method) as i32;
    }
    out
}

/// The method and parameters that fit the time left: LIBR+ only when the SR-GCN fits, LIBR
/// when two iterations fit, else the rigid result; the pose search only when about
/// [`POSE_SEARCH_COST`] registrations fit.
fn plan(job: &Job, prepared: &librplus::pipeline::Prepared, start: Instant) -> Plan {
    let queue_ms = ms(start - job.arrival);
    let options = job.request.options;
    let deadline = job.arrival + options.budget;
    let est = job.case.estimates();
    let mut method = job.request.method;
    let mut degraded: Option<String> = None;
    // The case's parameters (its basis was built with their LIBR settings), within this request.
    let mut params = job.case.params.clone();
    params.wicp.trusted_alignment_mm = options.trusted_alignment_mm;
    params.held = options.held;
    let gcn_ms = prepared
        .librplus
        .as_ref()
        .map_or(0.0, |g| g.expected_seconds());
    let gcn_ms = 1e3 * gcn_ms;
    let left = ms(deadline.saturating_duration_since(start));
    if method == Method::LibrPlus
        && let Some(why) = librplus_does_not_fit(job, prepared, &est, left, gcn_ms)
    {
        (method, degraded) = (Method::Libr, Some(why));
    }
    if method == Method::Auto
        && let Some(why) = auto_does_not_fit(job, left)
    {
        (method, degraded) = (Method::Libr, Some(why));
    }
    if method == Method::Nonlinear
        && let Err(why) = crate::refine::plan_nonlinear(prepared, &est, left, deadline, &mut params)
    {
        (method, degraded) = why;
    }
    if matches!(method, Method::Libr | Method::LibrPlus | Method::Auto) {
        let need = est.rigid_ms + est.other_ms + est.libr_fixed_ms + 2.0 * est.libr_iteration_ms;
        if left < need {
            method = Method::Rigid;
            degraded = Some(format!(
                "time budget {:.0} ms: {queue_ms:.0} ms waiting for a compute slot left {left:.0} ms, LIBR needs about {need:.0} ms; rigid result",
                ms(job.request.options.budget)
            ));
        } else {
            let after_libr_ms = est.libr_fixed_ms.max(0.0) + est.other_ms.max(0.0);
            params.deadline = deadline.checked_sub(Duration::from_secs_f64(after_libr_ms / 1e3));
        }
    }
    params.wicp.deadline = rigid_deadline(method, &est, gcn_ms, deadline);
    // The pose search (`librplus::pipeline::pose`) costs about six single registrations: it
    // runs when the budget left holds that many, otherwise the navigation start alone.
    let left = ms(deadline.saturating_duration_since(Instant::now()));
    let single = est.rigid_ms + est.other_ms + est.libr_fixed_ms + 10.0 * est.libr_iteration_ms;
    let one = match method {
        Method::Rigid | Method::V2s => est.rigid_ms,
        Method::Auto => AUTO_COST * single,
        _ => single,
    };
    let mut search_off = None;
    if left < POSE_SEARCH_COST * one {
        params.pose.start_angles_deg.clear();
        search_off = Some(format!(
            "time budget {:.0} ms: {left:.0} ms left, the pose search needs about {:.0} ms",
            ms(job.request.options.budget),
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

/// Why LIBR+ does not fit the `left` ms of the budget (None: it does), by the case's running
/// estimates and the SR-GCN's (`gcn_ms`).
fn librplus_does_not_fit(
    job: &Job,
    prepared: &librplus::pipeline::Prepared,
    est: &crate::cases::Estimates,
    left: f64,
    gcn_ms: f64,
) -> Option<String> {
    let need =
        est.rigid_ms + est.other_ms + est.libr_fixed_ms + 2.0 * est.libr_iteration_ms + gcn_ms;
    if left >= need {
        return None;
    }
    if left >= need - gcn_ms {
        // The SR-GCN estimate alone did not fit: let it fall slowly, so that a
        // correction once timed slow (a busy machine) is tried and timed again.
        if let Some(g) = &prepared.librplus {
            g.relax_estimate();
        }
    }
    Some(format!(
        "time budget {:.0} ms: {left:.0} ms left, LIBR+ needs about {need:.0} ms (SR-GCN {gcn_ms:.0} ms); LIBR result",
        ms(job.request.options.budget)
    ))
}

/// Where the rigid stage (the side test's fits, wICP, the pose search's refinements) stops, in
/// time for what follows it: LIBR's fixed cost and two iterations and the rest of the
/// registration (for auto, its candidates'; for LIBR+, the SR-GCN's too).
fn rigid_deadline(
    method: Method,
    est: &crate::cases::Estimates,
    gcn_ms: f64,
    deadline: Instant,
) -> Option<Instant> {
    let libr_ms = est.libr_fixed_ms + 2.0 * est.libr_iteration_ms + est.other_ms;
    let after_rigid_ms = match method {
        // What follows a rigid answer (its candidates' scores, the error estimate) is about
        // what follows a deformable one's LIBR.
        Method::Rigid | Method::V2s | Method::Initial => est.other_ms,
        Method::Auto => AUTO_COST * libr_ms,
        Method::LibrPlus => libr_ms + gcn_ms,
        _ => libr_ms,
    };
    deadline.checked_sub(Duration::from_secs_f64(after_rigid_ms.max(0.0) / 1e3))
}

/// A registration on a case that serves from a coarse basis while its own builds
/// ([`Case::coarse`]) says so; adaptive LIBR, whose basis comes with the case's own, answers as
/// LIBR meanwhile.
fn coarse_plan(job: &Job, prepared: &librplus::pipeline::Prepared, plan: &mut Plan) {
    if plan.method == Method::Adaptive && prepared.adaptive.is_none() {
        plan.method = Method::Libr;
        plan.degraded
            .get_or_insert_with(|| "adaptive LIBR's basis is not ready: LIBR result".to_string());
    }
    let Some(f) = job.case.coarse.filter(|_| job.prepared.is_none()) else {
        return;
    };
    let why = format!(
        "the case's own basis is still building: answered from a basis built on its boundary meshed again at {} mm ({} nodes)",
        crate::convert::num(f.edge_mm),
        f.coarse_nodes
    );
    plan.degraded = Some(match plan.degraded.take() {
        Some(r) => format!("{r}; {why}"),
        None => why,
    });
}

/// Why the automatic choice does not fit the `left` ms of the budget (None: it does), by the
/// case's running estimates.
fn auto_does_not_fit(job: &Job, left: f64) -> Option<String> {
    let est = job.case.estimates();
    let need =
        AUTO_COST * (est.rigid_ms + est.other_ms + est.libr_fixed_ms + 2.0 * est.libr_iteration_ms);
    (left < need).then(|| {
        format!(
            "time budget {:.0} ms: {left:.0} ms left, the automatic choice needs about {need:.0} ms; LIBR result",
            ms(job.request.options.budget)
        )
    })
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
    let budget_ms = ms(job.request.options.budget);
    if total_ms <= budget_ms {
        return (quality, reason);
    }
    match quality {
        pb::Quality::Ok | pb::Quality::NotConverged | pb::Quality::Degraded => (
            pb::Quality::Degraded,
            format!(
                "over its time budget: answered in {total_ms:.0} ms of {budget_ms:.0} ms ({} points; \
                 {:.0} ms waiting, rigid stage {:.0} ms){}",
                job.request.measurements.points.len(),
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
    tracing::debug!(
        method = plan.method.name(),
        quality = quality.as_str_name(),
        total_ms,
        queue_ms = plan.queue_ms,
        rigid_ms = reg.rigid.seconds * 1e3,
        libr_ms = reg.libr.as_ref().map_or(0.0, |l| l.total_s * 1e3),
        libr_iterations = reg.libr.as_ref().map_or(0, |l| l.iterations),
        gcn_ms = reg.correction.as_ref().map_or(0.0, |c| c.seconds * 1e3),
        pipeline_ms = reg.seconds * 1e3,
        "registration"
    );
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
        displacement_mm: if job.request.options.omit_displacements {
            Vec::new()
        } else {
            reg.u.iter().map(|&x| x as f32).collect()
        },
        node_count: prepared.model.mesh.num_nodes() as u32,
        method_used: method_to_pb(plan.method) as i32,
        choice: reg.auto.as_ref().map(crate::convert::choice_to_pb),
        surface: reg.surface.as_ref().map(crate::convert::side_to_pb),
        coarse_basis: job.case.coarse.is_some() && job.prepared.is_none(),
        residual_rms_mm: refit.or(info).map_or(reg.rigid.rms_mm, |i| i.rms_mm),
        points_used: job.request.measurements.points.len() as u32,
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
            .map(|e| error_estimate(e, job.request.options.omit_displacements)),
        // Set by the caller for METHOD_NONLINEAR.
        refinement: None,
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
    use librplus::pipeline::quality::Quality;

    /// Every library flag has its own wire value (the judgement itself is the library's,
    /// tested there).
    #[test]
    fn every_quality_has_its_own_wire_value() {
        let all = [
            Quality::Ok,
            Quality::NotConverged,
            Quality::Degraded,
            Quality::Degenerate,
            Quality::AmbiguousPose,
            Quality::AmbiguousModel,
            Quality::LikelyFailed,
        ];
        let wire: std::collections::HashSet<i32> =
            all.iter().map(|&q| quality_to_pb(q) as i32).collect();
        assert_eq!(wire.len(), all.len());
        assert!(!wire.contains(&(pb::Quality::Unspecified as i32)));
        assert_eq!(
            quality_to_pb(Quality::AmbiguousModel).as_str_name(),
            "QUALITY_AMBIGUOUS_MODEL"
        );
    }

    /// A registration on a case, and a discovery run on it, are planned with the settings the
    /// case's basis was built with (its LIBR basis settings, by hash) and the case's own fit
    /// settings: the server makes no parameters of its own.
    #[test]
    fn a_case_is_registered_with_the_settings_its_basis_was_built_with() {
        let dir = tempfile::tempdir().unwrap();
        let mesh = librplus::mesh::procedural::box_mesh([120.0, 90.0, 60.0], [5, 4, 3], 0.1);
        let path = dir.path().join("organ.vtu");
        librplus::mesh::io::write(&path, &mesh.to_file(), Default::default()).unwrap();
        let config = crate::config::ServerConfig {
            default_method: "libr".into(),
            adaptive: false,
            ..Default::default()
        };
        let learned = crate::cases::Learned {
            gcn: None,
            v2s: None,
        };
        let source = crate::cases::CaseSource::Mesh { path };
        let case = Arc::new(crate::cases::load("organ", &source, &config, &learned).unwrap());
        let built = case.prepared.basis.as_ref().unwrap().params_hash.clone();
        assert_eq!(case.params.libr.basis.hash(), built);
        let request = Request {
            measurements: Checked::new(librplus::register::Measurements {
                points: vec![[0.0; 3]],
                kind: vec![librplus::register::MeasuredKind::Surface],
                feature: Vec::new(),
                initial_alignment: None,
            })
            .unwrap(),
            method: Method::Libr,
            options: Options {
                budget: Duration::from_secs(60),
                omit_displacements: true,
                trusted_alignment_mm: Some(3.0),
                held: false,
                single_answer: false,
            },
        };
        let job = Job {
            case: case.clone(),
            request,
            arrival: Instant::now(),
            prepared: None,
            first: None,
        };
        let planned = plan(&job, &case.prepared, Instant::now()).params;
        assert_eq!(planned.libr.basis.hash(), built);
        assert_eq!(planned.libr, case.params.libr);
        assert_eq!(planned.adaptive, case.params.adaptive);
        assert_eq!(planned.wicp.trusted_alignment_mm, Some(3.0));
        let req = crate::discovery::Request {
            case: case.clone(),
            measurements: job.request.measurements.clone(),
            trusted_alignment_mm: None,
            held: false,
            budget: Duration::from_secs(1),
            coarse: true,
            client_seq: 0,
        };
        let discovery = crate::discovery::params(&req, Instant::now()).pipeline;
        assert_eq!(discovery.libr.basis.hash(), built);
        assert_eq!(discovery.libr, case.params.libr);
    }
}
