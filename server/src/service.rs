//! The `librplus.v1.LibRPlus` service: case listing, unary and streamed registration, with
//! admission control, limits, deadlines and drain on shutdown.

use crate::audit::{Audit, Record, RegistrationRecord};
use crate::auth::{Auth, Principal, Role};
use crate::cases::Case;
use crate::compute::{Engine, Job};
use crate::config::ServerConfig;
use crate::convert::{
    code_name, features, measurements_from_pb, method_from_pb, plane_points, points3, rigid_from_pb,
};
use crate::error::ServiceError;
use librplus::pipeline::Method;
use librplus::register::{MeasuredKind, Measurements};
use librplus_proto::v1 as pb;
use pb::lib_r_plus_server::LibRPlus;
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Request, Response, Status, Streaming};
use tracing::Instrument;

/// State shared by every request.
pub struct Shared {
    /// Configuration.
    pub config: ServerConfig,
    /// The cases: ready ones, and the state of each.
    pub registry: crate::registry::Registry,
    /// The case store (uploads), when configured.
    pub store: Option<crate::store::Store>,
    /// Uploads received at once (each is held in memory until it is checked and stored).
    pub uploads: Arc<Semaphore>,
    /// The learned models every case gets (set by the preload at start).
    pub learned: OnceLock<crate::cases::Learned>,
    /// Compute slots.
    pub engine: Engine,
    /// Session admission.
    pub sessions: Arc<Semaphore>,
    /// Becomes true when the server starts draining.
    pub drain: watch::Receiver<bool>,
    /// Session counter (ids).
    pub next_session: AtomicU64,
    /// The auth file's principals (None: no `--auth`, every caller is [`Shared::anonymous`]);
    /// replaced on reload.
    pub auth: Option<std::sync::RwLock<Arc<Auth>>>,
    /// The principal of every call when there is no auth file.
    pub anonymous: Arc<Principal>,
    /// Sessions open per principal.
    pub per_principal: std::sync::Mutex<HashMap<String, usize>>,
    /// The audit log, when kept (`audit_db`).
    pub audit: Option<Arc<Audit>>,
    /// This run's prefix of session ids (unique across restarts).
    pub boot: String,
    /// Which stream holds each live session (one stream per session id).
    pub live: Arc<crate::live::Live>,
}

impl Shared {
    /// Shared state for `config` with `auth` (None: no auth file).
    pub fn new(
        config: ServerConfig,
        auth: Option<Auth>,
        audit: Option<Audit>,
        store: Option<crate::store::Store>,
        engine: Engine,
        drain: watch::Receiver<bool>,
    ) -> Self {
        Self {
            store,
            uploads: Arc::new(Semaphore::new(MAX_UPLOADS)),
            registry: Default::default(),
            learned: OnceLock::new(),
            audit: audit.map(Arc::new),
            // Unique across replicas sharing a session journal: the start time and 32 random
            // bits (two replicas starting in the same millisecond).
            boot: format!("{:x}{:08x}", crate::audit::now_ms(), boot_nonce()),
            engine,
            sessions: Arc::new(Semaphore::new(config.max_sessions)),
            drain,
            next_session: AtomicU64::new(0),
            auth: auth.map(|a| std::sync::RwLock::new(Arc::new(a))),
            anonymous: Principal::anonymous(),
            per_principal: Default::default(),
            live: Default::default(),
            config,
        }
    }

    /// Writes audit records and waits for their commit (nothing without an audit log). An
    /// error is UNAVAILABLE: nothing is acknowledged that is not recorded.
    pub async fn record(&self, records: Vec<Record>) -> Result<(), ServiceError> {
        let Some(a) = &self.audit else {
            return Ok(());
        };
        a.write(records).await.map_err(|e| {
            ServiceError::Unavailable(format!(
                "the audit log cannot be written, so nothing is answered: {e}"
            ))
        })
    }

    /// Records a refusal without waiting for it.
    pub fn refused(&self, rpc: &str, who: &str, case: Option<&str>, e: &ServiceError) {
        let Some(a) = self.audit.clone() else {
            return;
        };
        let (code, message, _) = e.parts();
        let r = Record::Event {
            kind: "refused",
            principal: who.to_string(),
            case_id: case.map(|c| short(c, 64).into_owned()),
            session_id: None,
            detail: serde_json::json!({
                "rpc": rpc,
                "code": code_name(code),
                "message": short(&message, 300),
            }),
        };
        tokio::spawn(async move {
            let _ = a.write(vec![r]).await;
        });
    }

    /// The current auth file, if any.
    pub fn auth(&self) -> Option<Arc<Auth>> {
        self.auth
            .as_ref()
            .map(|a| a.read().unwrap_or_else(|e| e.into_inner()).clone())
    }

    /// The caller of a request: anonymous without an auth file, else its token's or client
    /// certificate's principal (UNAUTHENTICATED otherwise).
    pub fn caller(
        &self,
        md: &tonic::metadata::MetadataMap,
        certs: Option<&[tonic::transport::CertificateDer<'static>]>,
    ) -> Result<Arc<Principal>, ServiceError> {
        match self.auth() {
            None => Ok(self.anonymous.clone()),
            Some(a) => a.authenticate(md, certs),
        }
    }
}

/// Uploads received at once: each may hold up to `max_case_bytes` in memory.
pub const MAX_UPLOADS: usize = 2;

/// Longest case id, bytes.
pub const MAX_CASE_ID: usize = 256;

/// At most `n` characters of `s` (what is logged or echoed of a client's string).
pub fn short(s: &str, n: usize) -> std::borrow::Cow<'_, str> {
    match s.char_indices().nth(n) {
        None => s.into(),
        Some((i, _)) => format!("{}… ({} bytes)", &s[..i], s.len()).into(),
    }
}

/// A session's hold on a server slot and on its principal's quota; released on drop.
pub(crate) struct Admission {
    _permit: OwnedSemaphorePermit,
    /// The principal whose quota it holds (None: its quota is the server's).
    principal: Option<String>,
    shared: Arc<Shared>,
}

impl Drop for Admission {
    fn drop(&mut self) {
        let Some(principal) = &self.principal else {
            return;
        };
        let mut m = self
            .shared
            .per_principal
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(n) = m.get_mut(principal) {
            *n -= 1;
            if *n == 0 {
                m.remove(principal);
            }
        }
    }
}

/// The service.
#[derive(Clone)]
pub struct Svc(pub Arc<Shared>);

fn count_error(code: Code) {
    metrics::counter!("librplus_errors_total", "code" => code_name(code)).increment(1);
}

fn fail(b: ServiceError) -> Status {
    count_error(b.code());
    b.to_status()
}

/// The client's deadline from the `grpc-timeout` header, if any.
pub fn grpc_timeout(md: &tonic::metadata::MetadataMap) -> Option<Duration> {
    let v = md.get("grpc-timeout")?.to_str().ok()?;
    if v.len() < 2 {
        return None;
    }
    let (num, unit) = v.split_at(v.len() - 1);
    let n: u64 = num.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

impl Svc {
    /// The caller of `rpc` (refusals are audited).
    fn caller<T>(&self, req: &Request<T>, rpc: &str) -> Result<Arc<Principal>, Status> {
        let certs = req.peer_certs();
        self.0
            .caller(req.metadata(), certs.as_deref().map(Vec::as_slice))
            .map_err(|e| {
                self.0.refused(rpc, "", None, &e);
                fail(e)
            })
    }

    /// `who` may call `rpc` (it holds `role`); refusals are audited.
    fn allowed(&self, who: &Principal, role: Role, rpc: &str, what: &str) -> Result<(), Status> {
        who.require(role, what).map_err(|e| {
            self.0.refused(rpc, &who.name, None, &e);
            fail(e)
        })
    }

    /// A session slot for `who`: its principal's quota, then the server's (waiting briefly for
    /// a slot a session just released).
    async fn admit(&self, who: &Principal) -> Result<Admission, ServiceError> {
        let limit = self.0.config.principal_sessions(who.max_sessions);
        // A quota of its own only when it is below the server's.
        let own = limit < self.0.config.max_sessions;
        if own {
            let mut m = self
                .0
                .per_principal
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            let n = m.entry(who.name.clone()).or_insert(0);
            if *n >= limit {
                metrics::counter!("librplus_refused_total", "reason" => "principal_sessions")
                    .increment(1);
                return Err(ServiceError::Quota {
                    message: format!(
                        "principal {:?} holds {n} sessions, its limit; retry after one ends",
                        who.name
                    ),
                    subject: "principal_sessions",
                    description: format!(
                        "at most {limit} streamed sessions per principal; retry after one ends"
                    ),
                });
            }
            *n += 1;
        }
        let undo = || {
            if !own {
                return;
            }
            let mut m = self
                .0
                .per_principal
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            if let Some(n) = m.get_mut(&who.name) {
                *n -= 1;
                if *n == 0 {
                    m.remove(&who.name);
                }
            }
        };
        let sessions = self.0.sessions.clone();
        let permit = match sessions.clone().try_acquire_owned() {
            Ok(p) => Ok(p),
            Err(_) => tokio::time::timeout(ADMISSION_GRACE, sessions.acquire_owned())
                .await
                .map_err(|_| ())
                .and_then(|r| r.map_err(|_| ())),
        };
        match permit {
            Ok(p) => Ok(Admission {
                _permit: p,
                principal: own.then(|| who.name.clone()),
                shared: self.0.clone(),
            }),
            Err(()) => {
                undo();
                metrics::counter!("librplus_refused_total", "reason" => "sessions").increment(1);
                Err(ServiceError::Quota {
                    message: format!(
                        "session limit reached ({} open); retry later",
                        self.0.config.max_sessions
                    ),
                    subject: "sessions",
                    description: format!(
                        "{} streamed sessions are open, the server's limit; retry after one ends",
                        self.0.config.max_sessions
                    ),
                })
            }
        }
    }

    pub(crate) fn cases(&self) -> Result<crate::registry::Ready, ServiceError> {
        if !self.0.registry.preloaded() {
            return Err(ServiceError::Unavailable(
                "the server is still preloading its cases; retry when health reports SERVING"
                    .into(),
            ));
        }
        Ok(self.0.registry.ready())
    }

    /// Whether `who` may use a case named `id` (whether or not it exists).
    pub(crate) fn visible(id: &str, who: &Principal) -> bool {
        id.len() <= MAX_CASE_ID && who.may_use(id)
    }

    /// The NOT_FOUND (or INVALID_ARGUMENT for an overlong id) a caller gets for case `id` that
    /// it may not see or that has no state, worded as for any unknown case.
    pub(crate) fn not_found(&self, id: &str, field: &str, who: &Principal) -> ServiceError {
        self.case(id, field, who)
            .err()
            .unwrap_or_else(|| ServiceError::UnknownCase {
                field: field.into(),
                id: id.into(),
                known: Vec::new(),
            })
    }

    /// The case `id` if `who` may use it; NOT_FOUND, worded the same, when it does not exist or
    /// `who` may not use it (a caller learns nothing of other tenants' cases).
    pub(crate) fn case(
        &self,
        id: &str,
        field: &str,
        who: &Principal,
    ) -> Result<Arc<Case>, ServiceError> {
        if id.len() > MAX_CASE_ID {
            return Err(ServiceError::field(
                field,
                format!(
                    "is {} bytes long; case ids are at most {MAX_CASE_ID}",
                    id.len()
                ),
            ));
        }
        let cases = self.cases()?;
        match cases.get(id) {
            Some(c) if who.may_use(id) => Ok(c.clone()),
            // An uploaded case evicted while idle: loaded again, the caller retries.
            None if who.may_use(id) && self.0.registry.is_evicted(id) => {
                crate::upload::reload(&self.0, id);
                let stage = self
                    .0
                    .registry
                    .status(id)
                    .map(|s| format!("{}, {:.0} %", s.stage, 100.0 * s.fraction))
                    .unwrap_or_default();
                Err(ServiceError::Unavailable(format!(
                    "{field}: case {:?} was idle and left memory; it is being loaded again \
                     ({stage}); retry in a few seconds, or follow it with WatchCase",
                    short(id, 64)
                )))
            }
            _ => Err(ServiceError::UnknownCase {
                field: field.to_string(),
                id: id.to_string(),
                known: cases.keys().filter(|k| who.may_use(k)).cloned().collect(),
            }),
        }
    }

    fn budget(
        &self,
        options: Option<&pb::RegisterOptions>,
        field: &str,
    ) -> Result<Duration, ServiceError> {
        let c = &self.0.config;
        // Every field of the options; `omit_displacements`, `trusted_alignment_mm` and `held`
        // are read by the caller.
        let ms = options.map_or(
            0,
            |pb::RegisterOptions {
                 time_budget_ms,
                 omit_displacements: _,
                 trusted_alignment_mm: _,
                 held: _,
             }| *time_budget_ms,
        );
        if ms > c.max_time_budget_ms {
            return Err(ServiceError::field(
                format!("{field}.time_budget_ms"),
                format!(
                    "{ms} ms is above the server's limit of {} ms",
                    c.max_time_budget_ms
                ),
            ));
        }
        let ms = if ms == 0 { c.time_budget_ms } else { ms };
        Ok(Duration::from_millis(ms as u64))
    }

    fn check_method(&self, case: &Case, m: i32, field: &str) -> Result<Method, ServiceError> {
        let method = method_from_pb(
            m,
            case.default_method,
            case.prepared.librplus.is_some(),
            case.prepared.v2s.is_some(),
            field,
        )?;
        if method == Method::Adaptive && case.prepared.adaptive.is_none() {
            return Err(ServiceError::precondition(
                "CASE",
                field,
                format!(
                    "case {} was prepared without adaptive LIBR's basis (the server's adaptive setting is off)",
                    case.id
                ),
                format!("{field}: case {} has no adaptive LIBR basis", case.id),
            ));
        }
        if matches!(method, Method::Libr | Method::LibrPlus) && case.prepared.basis.is_none() {
            return Err(ServiceError::precondition(
                "CASE",
                field,
                format!("case {} has no LIBR basis: only METHOD_RIGID", case.id),
                format!("{field}: case {} has no LIBR basis", case.id),
            ));
        }
        Ok(method)
    }
}

fn summary(c: &Case) -> pb::CaseSummary {
    let m = &c.prepared.model.mesh;
    pb::CaseSummary {
        case_id: c.id.clone(),
        source: c.source.display().to_string(),
        node_count: m.num_nodes() as u32,
        tet_count: m.num_tets() as u32,
        libr_ready: c.prepared.basis.is_some(),
        libr_plus_ready: c.prepared.librplus.is_some(),
        v2s_ready: c.prepared.v2s.is_some(),
        default_method: crate::convert::method_to_pb(c.default_method) as i32,
        preload_seconds: c.prepared.seconds,
        basis_from_cache: c.prepared.basis_from_cache,
        effects: effects(&c.prepared),
    }
}

/// The named effects a model carries.
pub(crate) fn effects(p: &librplus::pipeline::Prepared) -> Vec<String> {
    p.physics.kinds().into_iter().map(str::to_string).collect()
}

/// The options' trusted-alignment uncertainty: None when 0 or absent; an error naming the field
/// when negative or not finite.
fn trusted(
    options: Option<&pb::RegisterOptions>,
    field: &str,
) -> Result<Option<f64>, ServiceError> {
    let v = options.map_or(0.0, |o| o.trusted_alignment_mm);
    if !(v.is_finite() && v >= 0.0) {
        return Err(ServiceError::field(
            format!("{field}.trusted_alignment_mm"),
            format!(
                "{} must be finite and ≥ 0 (mm; 0: fitted freely)",
                crate::convert::num(v)
            ),
        ));
    }
    Ok((v > 0.0).then_some(v))
}

type UpdateStream = ReceiverStream<Result<pb::StreamUpdate, Status>>;

/// Most waiting stream messages folded into one registration.
const MAX_COALESCED: usize = 256;

/// How long a new session waits for a slot before RESOURCE_EXHAUSTED.
const ADMISSION_GRACE: Duration = Duration::from_millis(100);

#[tonic::async_trait]
impl LibRPlus for Svc {
    async fn list_cases(
        &self,
        req: Request<pb::ListCasesRequest>,
    ) -> Result<Response<pb::ListCasesResponse>, Status> {
        let who = self.caller(&req, "ListCases")?;
        self.allowed(&who, Role::Read, "ListCases", "list cases")?;
        let cases = self.cases().map_err(fail)?;
        let mut out: Vec<pb::CaseSummary> = cases
            .values()
            .filter(|c| who.may_use(&c.id))
            .map(|c| summary(c))
            .collect();
        // Uploaded cases out of memory while idle are listed too (loaded when asked for).
        if let Some(store) = &self.0.store {
            for st in self.0.registry.all() {
                if st.state == pb::CaseState::Stored as i32
                    && who.may_use(&st.case_id)
                    && let Some(s) = store.find(&st.case_id)
                {
                    out.push(pb::CaseSummary {
                        case_id: st.case_id.clone(),
                        source: "case store (idle, not in memory: loaded when asked for)".into(),
                        node_count: s.nodes as u32,
                        tet_count: s.tets as u32,
                        ..Default::default()
                    });
                }
            }
            out.sort_by(|a, b| a.case_id.cmp(&b.case_id));
        }
        Ok(Response::new(pb::ListCasesResponse { cases: out }))
    }

    async fn describe_case(
        &self,
        req: Request<pb::DescribeCaseRequest>,
    ) -> Result<Response<pb::DescribeCaseResponse>, Status> {
        let who = self.caller(&req, "DescribeCase")?;
        self.allowed(&who, Role::Read, "DescribeCase", "describe cases")?;
        let pb::DescribeCaseRequest {
            case_id,
            include_mesh,
        } = req.into_inner();
        // An upload still loading, or failed: its state only.
        if Self::visible(&case_id, &who)
            && !self.cases().map_err(fail)?.contains_key(&case_id)
            && let Some(status) = self.0.registry.status(&case_id)
        {
            return Ok(Response::new(pb::DescribeCaseResponse {
                status: Some(status),
                length_unit: "mm".into(),
                frame: "image (preoperative), LPS".into(),
                ..Default::default()
            }));
        }
        let c = self.case(&case_id, "case_id", &who).map_err(|e| {
            self.0
                .refused("DescribeCase", &who.name, Some(&case_id), &e);
            fail(e)
        })?;
        let mut out = pb::DescribeCaseResponse {
            summary: Some(summary(&c)),
            status: Some(crate::ready_status(&c)),
            length_unit: "mm".into(),
            frame: "image (preoperative), LPS".into(),
            ..Default::default()
        };
        if include_mesh {
            let model = &c.prepared.model;
            out.nodes_mm = model.mesh.nodes().iter().flatten().copied().collect();
            out.tets = model.mesh.tets().iter().flatten().copied().collect();
            out.node_labels = (0..model.mesh.num_nodes())
                .map(|i| {
                    [
                        (model.anterior[i], pb::NodeLabel::Anterior),
                        (model.posterior[i], pb::NodeLabel::Posterior),
                        (model.falciform[i], pb::NodeLabel::Falciform),
                        (model.inferior_ridge[i], pb::NodeLabel::InferiorRidge),
                    ]
                    .iter()
                    .filter(|(on, _)| *on)
                    .fold(0u32, |acc, (_, bit)| acc | *bit as u32)
                })
                .collect();
            out.vessel_points_mm = model.vessel_points.iter().flatten().copied().collect();
            out.vessel_segments = model.vessel_segments.iter().flatten().copied().collect();
        }
        Ok(Response::new(out))
    }

    async fn register(
        &self,
        req: Request<pb::RegisterRequest>,
    ) -> Result<Response<pb::Registration>, Status> {
        let arrival = Instant::now();
        if *self.0.drain.borrow() {
            return Err(fail(ServiceError::Unavailable(
                "the server is shutting down".into(),
            )));
        }
        let client_deadline = grpc_timeout(req.metadata());
        let who = self.caller(&req, "Register")?;
        self.allowed(&who, Role::Register, "Register", "register")?;
        // Fairness between clients: the principal and its connection.
        let client = format!(
            "{}@{}",
            who.name,
            req.remote_addr()
                .map_or_else(|| "?".to_string(), |a| a.to_string())
        );
        // Every field, so that a new one breaks the build until it is handled.
        let pb::RegisterRequest {
            case_id,
            method,
            measurements,
            options,
        } = req.into_inner();
        let run = async {
            let case = self.case(&case_id, "case_id", &who)?;
            // A registration is a use (an idle upload leaves memory; describing it is not).
            case.touch();
            let method = self.check_method(&case, method, "method")?;
            let m = measurements
                .as_ref()
                .ok_or_else(|| ServiceError::field("measurements", "is missing"))?;
            let meas =
                measurements_from_pb(m, "measurements", self.0.config.max_points_per_message)?;
            librplus::register::correspondence::validate_measurements(&meas)
                .map_err(|e| ServiceError::field("measurements", e.to_string()))?;
            let mut budget = self.budget(options.as_ref(), "options")?;
            let trusted_alignment_mm = trusted(options.as_ref(), "options")?;
            if let Some(d) = client_deadline {
                // Answer before the client gives up: keep 10% (at least 5 ms) for the reply.
                budget = budget.min(d.mul_f64(0.9).saturating_sub(Duration::from_millis(5)));
            }
            let job = Job {
                case,
                measurements: meas,
                method,
                budget,
                arrival,
                omit_displacements: options.as_ref().is_some_and(|o| o.omit_displacements),
                trusted_alignment_mm,
                held: options.as_ref().is_some_and(|o| o.held),
                prepared: None,
            };
            let reg = self.0.engine.run(job, Some(&client)).await?;
            // Acknowledged only once recorded.
            if self.0.audit.is_some() {
                let mut rec = audit_record(&reg, &who.name, &case_id, None, 0);
                rec.measurements = measurements.as_ref().map(prost::Message::encode_to_vec);
                self.0
                    .record(vec![Record::Registration(Box::new(rec))])
                    .await?;
            }
            Ok(reg)
        };
        let span =
            tracing::info_span!("register", case = %short(&case_id, 64), principal = %who.name);
        match run.instrument(span).await {
            Ok(reg) => Ok(Response::new(reg)),
            Err(b) => {
                self.0.refused("Register", &who.name, Some(&case_id), &b);
                tracing::info!(code = code_name(b.code()), message = %short(b.to_status().message(), 200), "register refused");
                Err(fail(b))
            }
        }
    }

    async fn create_case(
        &self,
        req: Request<Streaming<pb::CreateCaseRequest>>,
    ) -> Result<Response<pb::CreateCaseResponse>, Status> {
        let who = self.caller(&req, "CreateCase")?;
        self.allowed(&who, Role::Manage, "CreateCase", "upload cases")?;
        let r = crate::upload::create(self, &who, req.into_inner()).await;
        r.map(Response::new).map_err(|e| {
            self.0.refused("CreateCase", &who.name, None, &e);
            fail(e)
        })
    }

    type WatchCaseStream = ReceiverStream<Result<pb::CaseStatus, Status>>;

    async fn watch_case(
        &self,
        req: Request<pb::WatchCaseRequest>,
    ) -> Result<Response<Self::WatchCaseStream>, Status> {
        let who = self.caller(&req, "WatchCase")?;
        self.allowed(&who, Role::Read, "WatchCase", "watch cases")?;
        let pb::WatchCaseRequest { case_id } = req.into_inner();
        self.cases().map_err(fail)?;
        let rx = Self::visible(&case_id, &who)
            .then(|| self.0.registry.watch(&case_id))
            .flatten();
        let Some(mut rx) = rx else {
            return Err(fail(self.not_found(&case_id, "case_id", &who)));
        };
        let (tx, out) = mpsc::channel(4);
        let mut drain = self.0.drain.clone();
        tokio::spawn(async move {
            loop {
                let s = rx.borrow_and_update().clone();
                let done = s.state != pb::CaseState::Loading as i32;
                if tx.send(Ok(s)).await.is_err() || done {
                    return;
                }
                let changed = tokio::select! {
                    r = rx.changed() => Some(r.is_ok()),
                    _ = drain.wait_for(|d| *d) => None,
                };
                match changed {
                    Some(true) => {}
                    Some(false) => return,
                    None => {
                        let _ = tx
                            .send(Err(Status::unavailable("the server is shutting down")))
                            .await;
                        return;
                    }
                }
            }
        });
        Ok(Response::new(ReceiverStream::new(out)))
    }

    async fn delete_case(
        &self,
        req: Request<pb::DeleteCaseRequest>,
    ) -> Result<Response<pb::DeleteCaseResponse>, Status> {
        let who = self.caller(&req, "DeleteCase")?;
        self.allowed(&who, Role::Manage, "DeleteCase", "delete cases")?;
        let pb::DeleteCaseRequest { case_id } = req.into_inner();
        let r = crate::upload::delete(self, &who, &case_id).await;
        r.map(Response::new).map_err(|e| {
            self.0.refused("DeleteCase", &who.name, Some(&case_id), &e);
            fail(e)
        })
    }

    type StreamRegisterStream = UpdateStream;

    async fn stream_register(
        &self,
        req: Request<Streaming<pb::StreamRegisterRequest>>,
    ) -> Result<Response<Self::StreamRegisterStream>, Status> {
        if *self.0.drain.borrow() {
            return Err(fail(ServiceError::Unavailable(
                "the server is shutting down".into(),
            )));
        }
        self.cases().map_err(fail)?;
        let who = self.caller(&req, "StreamRegister")?;
        self.allowed(&who, Role::Register, "StreamRegister", "register")?;
        // The session's slot is taken when its SessionStart arrives (a stream that never
        // starts holds none, and is closed after `session_start_timeout_s`).
        let deadline = grpc_timeout(req.metadata()).map(|d| Instant::now() + d);
        // The run's prefix, a counter (unique) and 48 random bits (not guessable).
        let sid = format!(
            "s{}-{:06}{:015}",
            self.0.boot,
            self.0.next_session.fetch_add(1, Ordering::Relaxed) + 1,
            random_u64() % 1_000_000_000_000_000
        );
        let inbound = req.into_inner();
        let (tx, rx) = mpsc::channel(8);
        let svc = self.clone();
        let span = tracing::info_span!("session", session_id = %sid, principal = %who.name);
        tokio::spawn(
            async move {
                metrics::gauge!("librplus_sessions_active").increment(1.0);
                let mut started = None;
                let outcome = session(
                    svc.clone(),
                    who.clone(),
                    inbound,
                    &tx,
                    deadline,
                    &sid,
                    &mut started,
                )
                .await;
                metrics::gauge!("librplus_sessions_active").decrement(1.0);
                let label = match &outcome {
                    Ok(()) => "OK",
                    Err(s) => code_name(s.code()),
                };
                metrics::counter!("librplus_sessions_total", "outcome" => label).increment(1);
                let text = match &outcome {
                    Ok(()) => "OK".to_string(),
                    Err(s) => format!("{label}: {}", short(s.message(), 300)),
                };
                match started {
                    // Written while the stream holds the session (none after a takeover: the
                    // session goes on in the newer stream), then the slot is released.
                    Some((session_id, lease)) => {
                        let end = vec![Record::SessionEnd {
                            session_id: session_id.clone(),
                            outcome: text,
                        }];
                        let _ = lease_record(&svc, &lease, &session_id, end).await;
                        drop(lease);
                    }
                    None => {
                        let _ = svc
                            .0
                            .record(vec![Record::Event {
                                kind: "refused",
                                principal: who.name.clone(),
                                case_id: None,
                                session_id: None,
                                detail: serde_json::json!({"rpc": "StreamRegister", "outcome": text}),
                            }])
                            .await;
                    }
                }
                match outcome {
                    Ok(()) => tracing::info!("session ended"),
                    Err(s) => {
                        tracing::info!(code = label, message = s.message(), "session ended");
                        count_error(s.code());
                        let _ = tx.send(Err(s)).await;
                    }
                }
            }
            .instrument(span),
        );
        Ok(Response::new(ReceiverStream::new(rx)))
    }
}

enum Next {
    Msg(pb::StreamRegisterRequest),
    End,
    /// A discovery run finished (None: it ended without an outcome).
    Discovered(Option<crate::discovery::Outcome>),
}

/// The outcome of the session's discovery run, when one is running; never, otherwise.
async fn discovered(
    pending: &mut Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>>,
) -> Option<crate::discovery::Outcome> {
    match pending.as_mut() {
        Some(rx) => rx.await.ok(),
        None => std::future::pending().await,
    }
}

/// The next client message, or why there is none.
async fn next(
    inbound: &mut Streaming<pb::StreamRegisterRequest>,
    idle: Duration,
    deadline: Option<Instant>,
    drain: &mut watch::Receiver<bool>,
    pending: &mut Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>>,
    lease: Option<(&str, &mut crate::live::Lease)>,
) -> Result<Next, Status> {
    let idle_at = tokio::time::Instant::now() + idle;
    let until = match deadline {
        Some(d) => idle_at.min(tokio::time::Instant::from_std(d)),
        None => idle_at,
    };
    if *drain.borrow() {
        return Err(Status::unavailable(
            "the server is shutting down; session ended",
        ));
    }
    let (sid, taken_over) = match lease {
        Some((sid, l)) => (sid, futures_taken_over(l)),
        None => ("", Box::pin(std::future::pending()) as TakenOverFut<'_>),
    };
    tokio::select! {
        biased;
        _ = drain.wait_for(|d| *d) => Err(Status::unavailable("the server is shutting down; session ended")),
        _ = taken_over => Err(ServiceError::TakenOver { session_id: sid.to_string() }.to_status()),
        _ = tokio::time::sleep_until(until) => {
            if deadline.is_some_and(|d| Instant::now() >= d) {
                Err(Status::deadline_exceeded("the call's deadline passed"))
            } else {
                Err(Status::deadline_exceeded(format!(
                    "no message for {:.0} s; session closed",
                    idle.as_secs_f64()
                )))
            }
        }
        o = discovered(pending) => Ok(Next::Discovered(o)),
        m = inbound.message() => match m {
            Ok(Some(m)) => Ok(Next::Msg(m)),
            Ok(None) => Ok(Next::End),
            Err(s) => Err(Status::new(s.code(), format!("receiving: {}", s.message()))),
        },
    }
}

type TakenOverFut<'a> = std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send + 'a>>;

fn futures_taken_over(l: &mut crate::live::Lease) -> TakenOverFut<'_> {
    Box::pin(l.taken_over())
}

/// Writes a session's records through its stream's lease: only while the stream holds the
/// session (TakenOver otherwise), and never while a resume reads them.
async fn lease_record(
    svc: &Svc,
    lease: &crate::live::Lease,
    sid: &str,
    records: Vec<Record>,
) -> Result<(), ServiceError> {
    match lease.record(svc.0.record(records)).await {
        Ok(r) => r,
        Err(crate::live::TakenOver) => Err(ServiceError::TakenOver {
            session_id: sid.to_string(),
        }),
    }
}

/// Session state after a valid start.
struct Session {
    case: Arc<Case>,
    method: Method,
    budget: Duration,
    omit: bool,
    trusted_alignment_mm: Option<f64>,
    /// The client said the organ is held (`RegisterOptions.held`).
    held: bool,
    meas: Measurements,
    last_seq: u64,
    last_time: Option<(i64, i32)>,
    sequence: u64,
    /// In-surgery discovery, when the session opted in.
    discovery: Option<DiscoveryPlan>,
    /// The running discovery's outcome.
    pending: Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>>,
    /// The session's augmented model, once discovery switched to one.
    augmented: Option<Arc<librplus::pipeline::Prepared>>,
}

/// A session's discovery settings.
struct DiscoveryPlan {
    budget: Duration,
    /// Run automatically at this many points (0: only when asked).
    auto_at: usize,
}

/// What an accepted message asks for.
enum Accepted {
    /// Points were added.
    Points,
    /// A discovery run.
    Discover,
}

/// One streamed session. `fresh` is the id of a new session; `started` is set to the session's
/// id and this stream's lease on it once it has started (and is recorded).
async fn session(
    svc: Svc,
    who: Arc<Principal>,
    mut inbound: Streaming<pb::StreamRegisterRequest>,
    tx: &mpsc::Sender<Result<pb::StreamUpdate, Status>>,
    deadline: Option<Instant>,
    fresh: &str,
    started: &mut Option<(String, crate::live::Lease)>,
) -> Result<(), Status> {
    let cfg = &svc.0.config;
    let idle = Duration::from_secs_f64(cfg.session_idle_timeout_s);
    let start_within = Duration::from_secs_f64(cfg.session_start_timeout_s);
    let mut drain = svc.0.drain.clone();
    // The first message must start the session, within `session_start_timeout_s`; a bad start
    // ends it with its status.
    let first = match next(
        &mut inbound,
        start_within,
        deadline,
        &mut drain,
        &mut None,
        None,
    )
    .await
    {
        Ok(Next::Msg(m)) => m,
        Ok(Next::End | Next::Discovered(_)) => return Ok(()),
        Err(e)
            if e.code() == Code::DeadlineExceeded
                && deadline.is_none_or(|d| Instant::now() < d) =>
        {
            metrics::counter!("librplus_refused_total", "reason" => "no_start").increment(1);
            return Err(Status::deadline_exceeded(format!(
                "no SessionStart within {:.0} s of opening the stream; session closed",
                start_within.as_secs_f64()
            )));
        }
        Err(e) => return Err(e),
    };
    let first_bytes = svc
        .0
        .audit
        .is_some()
        .then(|| prost::Message::encode_to_vec(&first));
    let Some(pb::stream_register_request::Msg::Start(start)) = first.msg else {
        return Err(ServiceError::precondition(
            "SESSION",
            "msg",
            "expected start",
            "msg: the first message of a session must be a SessionStart",
        )
        .to_status());
    };
    let resume = !start.resume_session_id.is_empty();
    // The session's slot and quota are taken here; a resume of a session that a stream holds
    // takes that stream's (live.rs: the newest stream holds the session, the older one ends).
    let (mut s, sid, lease) = if resume {
        let id = start.resume_session_id.clone();
        check_session_id(&id).map_err(|b| b.to_status())?;
        // Nothing of the session is recorded while it is read and taken over.
        let takeover = svc.0.live.lock(&id).await;
        let (mut s, mut recorded) = resume_session(&svc, &who, &id)
            .await
            .map_err(|b| b.to_status())?;
        let admission = match takeover.held() {
            true => None,
            false => {
                let a = svc.admit(&who).await.map_err(|b| b.to_status())?;
                Some(Box::new(a) as Box<dyn Send>)
            }
        };
        if svc
            .0
            .audit
            .as_ref()
            .is_some_and(|a| a.journal_dir().is_some())
        {
            // Replicas: the session's next epoch is claimed (no other replica answers for it
            // from now), then read again — what was recorded up to the claim is the session.
            // A resume refused by the first read claims nothing.
            svc.0
                .record(vec![Record::Claim {
                    session_id: id.clone(),
                }])
                .await
                .map_err(|b| b.to_status())?;
            (s, recorded) = resume_session(&svc, &who, &id)
                .await
                .map_err(|b| b.to_status())?;
        }
        let was_live = takeover.held();
        let lease = takeover.take(admission);
        let detail = serde_json::json!({
            "points": s.meas.points.len(),
            "last_client_seq": s.last_seq,
            "replica": crate::config::host_name(),
            "took_over_a_live_stream": was_live,
        });
        let records = vec![
            // This replica holds the session from here (the journal's next epoch).
            Record::Takeover {
                session_id: id.clone(),
                principal: who.name.clone(),
                case_id: s.case.id.clone(),
                case_version: s.case.version.clone(),
                start: recorded,
                last_seq: s.last_seq,
            },
            Record::Event {
                kind: "session_resumed",
                principal: who.name.clone(),
                case_id: Some(s.case.id.clone()),
                session_id: Some(id.clone()),
                detail,
            },
        ];
        lease_record(&svc, &lease, &id, records)
            .await
            .map_err(|b| b.to_status())?;
        tracing::info!(case = %s.case.id, resumed = %id, points = s.meas.points.len(), last_client_seq = s.last_seq, took_over = was_live, "session resumed");
        (s, id, lease)
    } else {
        let s = start_session(&svc, &who, &start, first.client_seq).map_err(|b| b.to_status())?;
        let admission = svc.admit(&who).await.map_err(|b| b.to_status())?;
        let lease = svc.0.live.start(fresh, Box::new(admission));
        let records = vec![Record::SessionStart {
            session_id: fresh.to_string(),
            principal: who.name.clone(),
            case_id: s.case.id.clone(),
            case_version: s.case.version.clone(),
            start: first_bytes.unwrap_or_default(),
        }];
        lease_record(&svc, &lease, fresh, records)
            .await
            .map_err(|b| b.to_status())?;
        tracing::info!(case = %s.case.id, method = s.method.name(), "session started");
        (s, fresh.to_string(), lease)
    };
    // The caller writes the session's end through the lease (nothing when it was taken over).
    let (sid, lease) = started.insert((sid, lease));
    let sid = sid.as_str();
    // The case is in use while the session lasts (DeleteCase waits for none).
    struct InUse(Arc<Case>);
    impl Drop for InUse {
        fn drop(&mut self) {
            self.0.sessions.fetch_sub(1, Ordering::SeqCst);
        }
    }
    s.case.sessions.fetch_add(1, Ordering::SeqCst);
    let _in_use = InUse(s.case.clone());
    let send = |s: &mut Session, update: pb::stream_update::Update, arrival: Instant| {
        s.sequence += 1;
        let out = pb::StreamUpdate {
            sequence: s.sequence,
            session_id: sid.to_string(),
            last_client_seq: s.last_seq,
            update: Some(update),
            points_total: s.meas.points.len() as u32,
        };
        metrics::histogram!("librplus_update_seconds").record(arrival.elapsed().as_secs_f64());
        let tx = tx.clone();
        Box::pin(async move { tx.send(Ok(out)).await.map_err(|_| ()) })
            as std::pin::Pin<Box<dyn std::future::Future<Output = Result<(), ()>> + Send>>
    };
    if resume {
        // The recorded messages answered again: the client goes on after `last_client_seq`.
        let arrival = Instant::now();
        let seq = s.last_seq;
        let update = register_session(&svc, &s, arrival, deadline, seq).await;
        audit_update(&svc, lease, &who, &s, sid, &update)
            .await
            .map_err(|b| b.to_status())?;
        if send(&mut s, update, arrival).await.is_err() {
            return Ok(());
        }
    }
    loop {
        let m = match next(
            &mut inbound,
            idle,
            deadline,
            &mut drain,
            &mut s.pending,
            Some((sid, &mut *lease)),
        )
        .await?
        {
            Next::Msg(m) => m,
            Next::End => return finish(&svc, &mut s, deadline, &mut drain, &send).await,
            Next::Discovered(o) => {
                s.pending = None;
                if discovered_update(&svc, &mut s, o, deadline, &send)
                    .await
                    .is_err()
                {
                    return Ok(());
                }
                continue;
            }
        };
        let arrival = Instant::now();
        // This message and every one already waiting (a client sending faster than its
        // registrations complete): each rejected message is answered on its own, the accepted
        // ones are folded into one registration of the newest state (latest wins).
        let mut batch = vec![m];
        let mut end: Option<Result<(), Status>> = None;
        while batch.len() < MAX_COALESCED {
            // `Streaming::message` keeps its state in the stream, so giving up on a pending
            // poll loses nothing.
            match tokio::time::timeout(Duration::ZERO, inbound.message()).await {
                Err(_) => break,
                Ok(Ok(Some(m))) => batch.push(m),
                Ok(Ok(None)) => {
                    end = Some(Ok(()));
                    break;
                }
                Ok(Err(e)) => {
                    end = Some(Err(Status::new(
                        e.code(),
                        format!("receiving: {}", e.message()),
                    )));
                    break;
                }
            }
        }
        let mut accepted = None;
        let mut discover_asked = None;
        let mut rejections = Vec::new();
        // What the audit log keeps of this batch: the accepted messages (a resumed session is
        // rebuilt from them) and the refusals; committed before any update is sent.
        let mut records = Vec::new();
        let mut kept = Vec::new();
        for m in batch {
            let seq = m.client_seq;
            let bytes = svc
                .0
                .audit
                .is_some()
                .then(|| prost::Message::encode_to_vec(&m));
            match accept(&mut s, m, cfg) {
                Ok(a) => {
                    kept.extend(bytes.map(|b| (seq, b)));
                    match a {
                        Accepted::Points => accepted = Some(seq),
                        Accepted::Discover => discover_asked = Some(seq),
                    }
                }
                Err(b) => {
                    count_error(b.code());
                    let r = b.to_rejection(seq);
                    if svc.0.audit.is_some() {
                        records.push(Record::Event {
                            kind: "rejected",
                            principal: who.name.clone(),
                            case_id: Some(s.case.id.clone()),
                            session_id: Some(sid.to_string()),
                            detail: serde_json::json!({
                                "client_seq": seq,
                                "code": r.code,
                                "message": short(&r.message, 300),
                            }),
                        });
                    }
                    rejections.push(pb::stream_update::Update::Rejection(r));
                }
            }
        }
        if !kept.is_empty() {
            records.push(Record::Messages {
                session_id: sid.to_string(),
                messages: kept,
            });
        }
        if !records.is_empty() {
            lease_record(&svc, lease, sid, records)
                .await
                .map_err(|b| b.to_status())?;
        }
        for r in rejections {
            if send(&mut s, r, arrival).await.is_err() {
                return Ok(());
            }
        }
        // A discovery run: asked for, or due (the session grew to its automatic threshold).
        let due = s.pending.is_none()
            && s.discovery
                .as_ref()
                .is_some_and(|d| d.auto_at > 0 && s.meas.points.len() >= d.auto_at);
        if let Some(seq) = discover_asked.or(due.then_some(0)) {
            let update = start_discovery(&svc, &mut s, seq);
            if send(&mut s, update, arrival).await.is_err() {
                return Ok(());
            }
        }
        if let Some(seq) = accepted {
            let update = register_session(&svc, &s, arrival, deadline, seq).await;
            audit_update(&svc, lease, &who, &s, sid, &update)
                .await
                .map_err(|b| b.to_status())?;
            if send(&mut s, update, arrival).await.is_err() {
                // The client went away.
                return Ok(());
            }
        }
        match end {
            Some(Ok(())) => return finish(&svc, &mut s, deadline, &mut drain, &send).await,
            Some(e) => return e,
            None => {}
        }
    }
}

/// The audit record of a registration.
fn audit_record(
    reg: &pb::Registration,
    principal: &str,
    case_id: &str,
    session_id: Option<&str>,
    client_seq: u64,
) -> RegistrationRecord {
    use prost::Message;
    RegistrationRecord {
        principal: principal.to_string(),
        case_id: case_id.to_string(),
        session_id: session_id.map(str::to_string),
        client_seq,
        method: reg.method_used().as_str_name().to_string(),
        quality: reg.quality().as_str_name().to_string(),
        quality_reason: reg.quality_reason.clone(),
        total_ms: reg.timings.as_ref().map_or(0.0, |t| t.total_ms),
        residual_rms_mm: reg.residual_rms_mm,
        points_total: reg.points_used as u64,
        measurements: None,
        answer_sha256: crate::auth::hex(&crate::auth::sha256(&reg.encode_to_vec())),
        timings: reg
            .timings
            .as_ref()
            .map(|t| {
                serde_json::json!({
                    "queue_ms": t.queue_ms, "rigid_ms": t.rigid_ms, "libr_ms": t.libr_ms,
                    "gcn_ms": t.gcn_ms, "refit_ms": t.refit_ms, "total_ms": t.total_ms,
                    "libr_iterations": t.libr_iterations, "refit_iterations": t.refit_iterations,
                })
                .to_string()
            })
            .unwrap_or_default(),
    }
}

/// Records a session's registration update (a rejection in its place is an event), and waits
/// for the commit.
async fn audit_update(
    svc: &Svc,
    lease: &crate::live::Lease,
    who: &Principal,
    s: &Session,
    sid: &str,
    update: &pb::stream_update::Update,
) -> Result<(), ServiceError> {
    if svc.0.audit.is_none() {
        return Ok(());
    }
    let record =
        match update {
            pb::stream_update::Update::Registration(r) => Record::Registration(Box::new(
                audit_record(r, &who.name, &s.case.id, Some(sid), s.last_seq),
            )),
            pb::stream_update::Update::Rejection(r) => Record::Event {
                kind: "rejected",
                principal: who.name.clone(),
                case_id: Some(s.case.id.clone()),
                session_id: Some(sid.to_string()),
                detail: serde_json::json!({
                    "client_seq": r.client_seq,
                    "code": r.code,
                    "message": short(&r.message, 300),
                }),
            },
            pb::stream_update::Update::Discovery(_) => return Ok(()),
        };
    lease_record(svc, lease, sid, vec![record]).await
}

/// How many sessions recorded on case `case_id` at `version` a client could still resume (this
/// server's audit log; sessions older than the journal's retention are no longer resumable).
/// None without an audit log (no session resumes) or when it cannot be read.
pub(crate) async fn resumable_sessions(
    shared: &Shared,
    case_id: &str,
    version: &str,
) -> Option<u64> {
    let audit = shared.audit.as_ref()?;
    let path = audit.path().to_path_buf();
    let since = match audit.journal_dir() {
        Some(_) => {
            crate::audit::now_ms()
                - (shared.config.session_journal_retention_h * 3.6e6).min(1e15) as i64
        }
        None => 0,
    };
    let (id, v) = (case_id.to_string(), version.to_string());
    tokio::task::spawn_blocking(move || {
        let c = crate::audit::open_db(&path).ok()?;
        crate::audit::count_sessions(&c, &id, &v, since).ok()
    })
    .await
    .ok()
    .flatten()
}

/// A resumed session id is at most 128 bytes (checked before anything is looked up).
fn check_session_id(id: &str) -> Result<(), ServiceError> {
    if id.len() > 128 {
        return Err(ServiceError::field(
            "start.resume_session_id",
            format!("is {} bytes long; session ids are at most 128", id.len()),
        ));
    }
    Ok(())
}

/// Rebuilds a recorded session: its start and accepted messages, in order, through the same
/// checks as when they arrived. The case must still have the content the session started on.
async fn resume_session(
    svc: &Svc,
    who: &Principal,
    id: &str,
) -> Result<(Session, Vec<u8>), ServiceError> {
    use prost::Message;
    let field = "start.resume_session_id";
    let Some(audit) = &svc.0.audit else {
        return Err(ServiceError::precondition(
            "SESSION",
            field,
            "the server keeps no audit log",
            format!("{field}: this server keeps no audit log (audit_db), so no session resumes"),
        ));
    };
    check_session_id(id)?;
    let path = audit.path().to_path_buf();
    let journal = audit.journal_dir().map(Path::to_path_buf);
    let key = id.to_string();
    let rec = tokio::task::spawn_blocking(move || match journal {
        // Replicas: the shared journal has every replica's sessions.
        Some(dir) => crate::journal::read(&dir, &key),
        None => {
            let c = crate::audit::open_db(&path).map_err(|e| e.to_string())?;
            crate::audit::read_session(&c, &key).map_err(|e| e.to_string())
        }
    })
    .await
    .map_err(|e| ServiceError::Internal(format!("reading the session record: {e}")))?
    .map_err(|e| ServiceError::Unavailable(format!("reading the session record: {e}")))?;
    let unknown = || ServiceError::UnknownSession {
        field: field.into(),
        id: id.to_string(),
    };
    let rec = rec.ok_or_else(unknown)?;
    if rec.principal != who.name {
        return Err(unknown());
    }
    let broken = |what: String| {
        ServiceError::Internal(format!(
            "session {id}: its record cannot be replayed: {what}"
        ))
    };
    let first = pb::StreamRegisterRequest::decode(&rec.start[..])
        .map_err(|e| broken(format!("start: {e}")))?;
    let Some(pb::stream_register_request::Msg::Start(start)) = &first.msg else {
        return Err(broken("the first message is not a start".into()));
    };
    let mut s = start_session(svc, who, start, first.client_seq).map_err(|e| match e {
        ServiceError::UnknownCase { .. } => ServiceError::precondition(
            "CASE",
            field,
            format!("the session's case {:?} no longer exists", rec.case_id),
            format!(
                "{field}: session {id} was started on case {:?} (version {}), which no longer \
                 exists; start a new session",
                short(&rec.case_id, 64),
                rec.case_version.as_deref().unwrap_or("not recorded")
            ),
        ),
        e => e,
    })?;
    if let Some(v) = &rec.case_version
        && *v != s.case.version
    {
        return Err(ServiceError::precondition(
            "CASE",
            field,
            format!(
                "the session's case {:?} changed since it started (version {v}, now {})",
                rec.case_id, s.case.version
            ),
            format!(
                "{field}: session {id} was started on case {:?} version {v}; the case now has \
                 version {} (it was replaced since), so the session's points would be \
                 registered to another model; start a new session",
                short(&rec.case_id, 64),
                s.case.version
            ),
        ));
    }
    for (seq, bytes) in &rec.messages {
        let m = pb::StreamRegisterRequest::decode(&bytes[..])
            .map_err(|e| broken(format!("message {seq}: {e}")))?;
        if matches!(m.msg, Some(pb::stream_register_request::Msg::Discover(_))) {
            // A discovery run is not repeated; its message still counts.
            s.last_seq = *seq;
            continue;
        }
        accept(&mut s, m, &svc.0.config).map_err(|e| {
            broken(format!(
                "message {seq} is refused now: {}",
                e.to_status().message()
            ))
        })?;
    }
    Ok((s, rec.start))
}

/// Sends one update of a session (numbered, with its points and last client message).
type Emit<'a> = dyn Fn(
        &mut Session,
        pb::stream_update::Update,
        Instant,
    ) -> std::pin::Pin<
        Box<dyn std::future::Future<Output = Result<(), ()>> + std::marker::Send + 'a>,
    > + Sync
    + 'a;

/// A finished discovery run: the session takes its model when it switched, the report is sent,
/// then (after a switch) the session's points registered with the new model. Err: the client
/// went away.
async fn discovered_update(
    svc: &Svc,
    s: &mut Session,
    o: Option<crate::discovery::Outcome>,
    deadline: Option<Instant>,
    send: &Emit<'_>,
) -> Result<(), ()> {
    let arrival = Instant::now();
    let Some(o) = o else {
        tracing::error!("discovery ended without an outcome");
        return Ok(());
    };
    let switched = o.augmented.is_some();
    let state = pb::DiscoveryState::try_from(o.report.state).map_or("UNKNOWN", |x| x.as_str_name());
    metrics::counter!("librplus_discovery_total", "state" => state).increment(1);
    tracing::info!(
        verdict = %o.report.verdict,
        switched,
        elapsed_ms = o.report.elapsed_ms,
        message = %o.report.message,
        "discovery finished"
    );
    if let Some(p) = o.augmented {
        s.augmented = Some(p);
    }
    send(s, pb::stream_update::Update::Discovery(o.report), arrival).await?;
    // The switch shows at once: the session's points registered with its new model.
    if switched && !s.meas.points.is_empty() {
        let update = register_session(svc, s, arrival, deadline, s.last_seq).await;
        send(s, update, arrival).await?;
    }
    Ok(())
}

/// The client finished sending: a discovery run it started is still reported (it was
/// acknowledged), unless the server drains or the call's deadline passes first.
async fn finish(
    svc: &Svc,
    s: &mut Session,
    deadline: Option<Instant>,
    drain: &mut watch::Receiver<bool>,
    send: &Emit<'_>,
) -> Result<(), Status> {
    let Some(rx) = s.pending.take() else {
        return Ok(());
    };
    let until = deadline.map_or_else(
        || tokio::time::Instant::now() + Duration::from_secs(24 * 3600),
        tokio::time::Instant::from_std,
    );
    let o = tokio::select! {
        biased;
        _ = drain.wait_for(|d| *d) => return Err(Status::unavailable("the server is shutting down; session ended before its discovery run finished")),
        _ = tokio::time::sleep_until(until) => return Err(Status::deadline_exceeded("the call's deadline passed before the discovery run finished")),
        o = rx => o.ok(),
    };
    // Err: the client went away; nothing is left to send.
    let _ = discovered_update(svc, s, o, deadline, send).await;
    Ok(())
}

/// Registers every point of the session with its current model; the update to send.
async fn register_session(
    svc: &Svc,
    s: &Session,
    arrival: Instant,
    deadline: Option<Instant>,
    seq: u64,
) -> pb::stream_update::Update {
    if s.meas.points.is_empty() {
        // Nothing measured yet (an ultrasound frame in which nothing was found): the answer is
        // the starting pose, flagged, as the proto promises.
        let prepared = s.augmented.as_deref().unwrap_or(&s.case.prepared);
        let n = prepared.model.mesh.num_nodes();
        let pose = s.meas.initial_alignment.unwrap_or_default();
        return pb::stream_update::Update::Registration(pb::Registration {
            image_to_physical: Some(crate::convert::rigid_to_pb(&pose)),
            displacement_mm: if s.omit { Vec::new() } else { vec![0.0; 3 * n] },
            node_count: n as u32,
            method_used: crate::convert::method_to_pb(Method::Rigid) as i32,
            quality: pb::Quality::Degenerate as i32,
            quality_reason: "the session holds no points yet: the initial alignment (identity \
                             when none was given) is the answer"
                .into(),
            effects: effects(prepared),
            timings: Some(pb::StageTimings {
                total_ms: arrival.elapsed().as_secs_f64() * 1e3,
                ..Default::default()
            }),
            ..Default::default()
        });
    }
    s.case.touch();
    let job = Job {
        case: s.case.clone(),
        measurements: s.meas.clone(),
        method: s.method,
        budget: match deadline {
            Some(d) => s.budget.min(d.saturating_duration_since(arrival)),
            None => s.budget,
        },
        arrival,
        omit_displacements: s.omit,
        trusted_alignment_mm: s.trusted_alignment_mm,
        held: s.held,
        prepared: s.augmented.clone(),
    };
    match svc.0.engine.run(job, None).await {
        Ok(r) => pb::stream_update::Update::Registration(r),
        Err(b) => {
            count_error(b.code());
            pb::stream_update::Update::Rejection(b.to_rejection(seq))
        }
    }
}

/// Starts a discovery run on the session's points (the caller checked it may); the update that
/// says so, or why it could not start.
fn start_discovery(svc: &Svc, s: &mut Session, seq: u64) -> pb::stream_update::Update {
    let Some(plan) = s.discovery.as_mut() else {
        // `accept` refuses `discover` when the session did not opt in; kept as a report.
        return pb::stream_update::Update::Discovery(pb::DiscoveryReport {
            client_seq: seq,
            state: pb::DiscoveryState::Failed as i32,
            message: "discover: this session did not opt in to discovery".into(),
            ..Default::default()
        });
    };
    let n = s.meas.points.len();
    if plan.auto_at > 0 {
        // The next automatic run when the session has grown by half.
        plan.auto_at = plan.auto_at.max(n + n / 2);
    }
    let req = crate::discovery::Request {
        case: s.case.clone(),
        measurements: s.meas.clone(),
        trusted_alignment_mm: s.trusted_alignment_mm,
        held: s.held,
        budget: plan.budget,
        coarse: svc.0.config.discovery_coarse,
        libr: librplus::register::libr::LibrParams::default(),
        client_seq: seq,
    };
    if n < crate::discovery::MIN_POINTS {
        let mut r = crate::discovery::started(&req);
        r.state = pb::DiscoveryState::Failed as i32;
        r.message = format!(
            "discover: the session holds {n} points; discovery needs at least {}",
            crate::discovery::MIN_POINTS
        );
        return pb::stream_update::Update::Discovery(r);
    }
    tracing::info!(points = n, client_seq = seq, "discovery started");
    let report = crate::discovery::started(&req);
    s.pending = Some(crate::discovery::spawn(req));
    pb::stream_update::Update::Discovery(report)
}

fn start_session(
    svc: &Svc,
    who: &Principal,
    start: &pb::SessionStart,
    seq: u64,
) -> Result<Session, ServiceError> {
    let pb::SessionStart {
        case_id,
        method,
        options,
        initial_alignment,
        discovery,
        resume_session_id: _, // handled by the caller
    } = start;
    let case = svc.case(case_id, "start.case_id", who)?;
    let method = svc.check_method(&case, *method, "start.method")?;
    let budget = svc.budget(options.as_ref(), "start.options")?;
    let trusted_alignment_mm = trusted(options.as_ref(), "start.options")?;
    let initial = initial_alignment
        .as_ref()
        .map(|r| rigid_from_pb(r, "start.initial_alignment"))
        .transpose()?;
    let discovery = match discovery {
        Some(pb::DiscoveryOptions {
            enabled: true,
            budget_ms,
            auto_after_points,
        }) => {
            let c = &svc.0.config;
            if *budget_ms > c.max_discovery_budget_ms {
                return Err(ServiceError::field(
                    "start.discovery.budget_ms",
                    format!(
                        "{budget_ms} ms is above the server's limit of {} ms",
                        c.max_discovery_budget_ms
                    ),
                ));
            }
            if case.prepared.basis.is_none() {
                return Err(ServiceError::precondition(
                    "CASE",
                    "start.discovery.enabled",
                    format!("case {} has no LIBR basis", case.id),
                    format!(
                        "start.discovery.enabled: case {} has no LIBR basis to discover with",
                        case.id
                    ),
                ));
            }
            let ms = if *budget_ms == 0 {
                c.discovery_budget_ms
            } else {
                *budget_ms
            };
            Some(DiscoveryPlan {
                budget: Duration::from_millis(ms as u64),
                auto_at: *auto_after_points as usize,
            })
        }
        Some(pb::DiscoveryOptions {
            enabled: false,
            budget_ms,
            auto_after_points,
        }) if *budget_ms != 0 || *auto_after_points != 0 => {
            return Err(ServiceError::field(
                "start.discovery.enabled",
                "is false while budget_ms or auto_after_points is set: set enabled to opt in",
            ));
        }
        _ => None,
    };
    Ok(Session {
        case,
        method,
        budget,
        omit: options.as_ref().is_some_and(|o| o.omit_displacements),
        trusted_alignment_mm,
        held: options.as_ref().is_some_and(|o| o.held),
        meas: Measurements {
            initial_alignment: initial,
            ..Default::default()
        },
        last_seq: seq,
        last_time: None,
        sequence: 0,
        discovery,
        pending: None,
        augmented: None,
    })
}

fn check_time(
    s: &Session,
    t: Option<&prost_types::Timestamp>,
    field: &str,
) -> Result<Option<(i64, i32)>, ServiceError> {
    let Some(t) = t else {
        return Ok(None);
    };
    if !(0..1_000_000_000).contains(&t.nanos) {
        return Err(ServiceError::field(
            format!("{field}.nanos"),
            format!("{} is outside 0..1e9", t.nanos),
        ));
    }
    let now = (t.seconds, t.nanos);
    if let Some(last) = s.last_time
        && now < last
    {
        return Err(ServiceError::precondition(
            "ORDER",
            field,
            "goes back in time",
            format!(
                "{field}: {}.{:09} s is before the previous message's {}.{:09} s (out-of-order frame)",
                now.0, now.1, last.0, last.1
            ),
        ));
    }
    Ok(Some(now))
}

/// Checks one message and adds its points to the session.
fn accept(
    s: &mut Session,
    m: pb::StreamRegisterRequest,
    cfg: &ServerConfig,
) -> Result<Accepted, ServiceError> {
    use pb::stream_register_request::Msg;
    let pb::StreamRegisterRequest {
        client_seq: seq,
        msg,
    } = m;
    if seq <= s.last_seq {
        return Err(ServiceError::precondition(
            "ORDER",
            "client_seq",
            format!("must be greater than {}", s.last_seq),
            if seq == s.last_seq {
                format!("client_seq {seq}: duplicate of the previous message")
            } else {
                format!(
                    "client_seq {seq}: out of order (the session is at {})",
                    s.last_seq
                )
            },
        ));
    }
    s.last_seq = seq;
    let (points, kinds, feature, time) = match msg {
        None => {
            return Err(ServiceError::field(
                "msg",
                "is empty: set start, surface, ultrasound or discover",
            ));
        }
        Some(Msg::Discover(pb::DiscoverNow {})) => {
            if s.discovery.is_none() {
                return Err(ServiceError::precondition(
                    "SESSION",
                    "discover",
                    "the session did not opt in",
                    "discover: this session did not opt in to discovery (start.discovery.enabled)",
                ));
            }
            if s.pending.is_some() {
                return Err(ServiceError::precondition(
                    "SESSION",
                    "discover",
                    "a discovery run is in progress",
                    "discover: a discovery run is already in progress; its report will follow",
                ));
            }
            return Ok(Accepted::Discover);
        }
        Some(Msg::Start(_)) => {
            return Err(ServiceError::precondition(
                "SESSION",
                "start",
                "only the first message may start",
                "start: the session has already started",
            ));
        }
        Some(Msg::Surface(pb::SurfaceBatch {
            acquired_at,
            xyz_mm,
            feature,
        })) => {
            let time = check_time(s, acquired_at.as_ref(), "surface.acquired_at")?;
            let p = points3(&xyz_mm, "surface.xyz_mm", cfg.max_points_per_message)?;
            if p.is_empty() {
                return Err(ServiceError::field("surface.xyz_mm", "is empty: no points"));
            }
            let f = features(&feature, p.len(), "surface.feature")?;
            let k = vec![MeasuredKind::Surface; p.len()];
            (p, k, f, time)
        }
        Some(Msg::Ultrasound(u)) => {
            let time = check_time(s, u.acquired_at.as_ref(), "ultrasound.acquired_at")?;
            let (c, v) = plane_points(&u, cfg.max_points_per_message)?;
            let mut k = vec![MeasuredKind::PosteriorContour; c.len()];
            k.extend(std::iter::repeat_n(MeasuredKind::Vessel, v.len()));
            let n = k.len();
            let mut p = c;
            p.extend(v);
            (p, k, vec![0; n], time)
        }
    };
    let total = s.meas.points.len() + points.len();
    if total > cfg.max_points_per_session {
        return Err(ServiceError::Quota {
            message: format!(
                "the session would hold {total} points, above the server's limit of {}",
                cfg.max_points_per_session
            ),
            subject: "points_per_session",
            description: format!(
                "at most {} points in one session; start a new session",
                cfg.max_points_per_session
            ),
        });
    }
    if let Some(t) = time {
        s.last_time = Some(t);
    }
    s.meas.points.extend(points);
    s.meas.kind.extend(kinds);
    s.meas.feature.extend(feature);
    Ok(Accepted::Points)
}

/// 32 random bits for the session ids of this run.
fn boot_nonce() -> u32 {
    random_u64() as u32
}

/// 64 bits from the system's secure random source.
fn random_u64() -> u64 {
    use ring::rand::SecureRandom;
    let mut b = [0u8; 8];
    let _ = ring::rand::SystemRandom::new().fill(&mut b);
    u64::from_le_bytes(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grpc_timeout_headers_parse() {
        let mut md = tonic::metadata::MetadataMap::new();
        assert_eq!(grpc_timeout(&md), None);
        for (v, d) in [
            ("250m", Duration::from_millis(250)),
            ("3S", Duration::from_secs(3)),
            ("2M", Duration::from_secs(120)),
            ("1H", Duration::from_secs(3600)),
            ("500u", Duration::from_micros(500)),
            ("7n", Duration::from_nanos(7)),
        ] {
            md.insert("grpc-timeout", v.parse().unwrap());
            assert_eq!(grpc_timeout(&md), Some(d), "{v}");
        }
        for bad in ["", "m", "12x", "-5m"] {
            md.insert("grpc-timeout", bad.parse().unwrap());
            assert_eq!(grpc_timeout(&md), None, "{bad}");
        }
    }
}
