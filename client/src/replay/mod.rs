//! `replay`: streams recorded dataset scenarios to a server, one session per scenario and method,
//! in lockstep, and scores every registration against the ground truth (TRE). The summary over
//! all sessions and its table: `summary`; a session's registrations as a ParaView time series:
//! `series`.

mod series;
mod summary;

use crate::data::{Selection, load_selection};
use crate::messages::{MessageError, rigid_from_message, stream_messages};
use crate::pb;
use crate::session::{SessionConfig, SessionEnd, SessionOutcome, connect_with, run_session};
use crate::stats::{Latencies, LatencyMs};
use anyhow::{Result, bail};
use futures_util::StreamExt;
use librplus::eval::{GeometryData, ScenarioData, Tre, tre};
use librplus::mesh::rigid::Rigid;
pub use series::series_name;
use series::{SeriesStep, write_series};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;
use summary::summarize;
pub use summary::{
    CategorySummary, MethodSummary, ReplaySummary, UnfinishedDiscovery, degradations, replay_table,
};

/// The short name of a method ("default", "rigid", "libr", "libr_plus").
pub fn method_name(m: pb::Method) -> &'static str {
    match m {
        pb::Method::Unspecified => "default",
        pb::Method::Rigid => "rigid",
        pb::Method::Libr => "libr",
        pb::Method::LibrPlus => "libr_plus",
        pb::Method::V2s => "v2s",
        pb::Method::Adaptive => "adaptive",
        pb::Method::Auto => "auto",
        pb::Method::Nonlinear => "nonlinear",
    }
}

/// A method from its short name (`rigid`, `libr`, `libr_plus` or `libr+`, `v2s`, `adaptive`,
/// `auto`, `nonlinear`, `default`).
pub fn parse_method(s: &str) -> Result<pb::Method> {
    Ok(match s.trim() {
        "rigid" => pb::Method::Rigid,
        "libr" => pb::Method::Libr,
        "libr_plus" | "libr+" | "libr-plus" => pb::Method::LibrPlus,
        "v2s" => pb::Method::V2s,
        "adaptive" => pb::Method::Adaptive,
        "auto" => pb::Method::Auto,
        "nonlinear" => pb::Method::Nonlinear,
        "default" => pb::Method::Unspecified,
        other => {
            bail!(
                "unknown method {other:?}: expected rigid, libr, libr_plus, v2s, adaptive, auto, nonlinear or default"
            )
        }
    })
}

/// A comma-separated list of methods (`rigid,libr`).
pub fn parse_methods(s: &str) -> Result<Vec<pb::Method>> {
    let v = s
        .split(',')
        .filter(|x| !x.trim().is_empty())
        .map(parse_method)
        .collect::<Result<Vec<_>>>()?;
    if v.is_empty() {
        bail!("--methods is empty");
    }
    Ok(v)
}

/// The short name of a quality ("OK", "NOT_CONVERGED", "DEGRADED", "DEGENERATE", ...).
pub fn quality_name(q: i32) -> String {
    match pb::Quality::try_from(q) {
        Ok(q) => q.as_str_name().trim_start_matches("QUALITY_").to_string(),
        Err(_) => format!("UNKNOWN_{q}"),
    }
}

/// What `replay` does.
#[derive(Debug, Clone)]
pub struct ReplayOptions {
    /// Server URL, e.g. `http://127.0.0.1:50051`.
    pub server: String,
    /// Dataset directory.
    pub data: PathBuf,
    /// Scenarios to replay.
    pub selection: Selection,
    /// Methods, each replayed on every scenario.
    pub methods: Vec<pb::Method>,
    /// At most this many messages per second.
    pub rate_hz: Option<f64>,
    /// Surface points per `SurfaceBatch` (0: all in one).
    pub batch: usize,
    /// Options sent in each `SessionStart`.
    pub options: Option<pb::RegisterOptions>,
    /// Bearer token.
    pub token: Option<String>,
    /// Resume sessions whose stream is lost.
    pub resume: bool,
    /// Longest wait for a stream to open and for each answer.
    pub timeout: Duration,
    /// Progress lines on stderr.
    pub progress: bool,
    /// Methods replayed once more with in-surgery discovery (named `METHOD+discovery`): the
    /// session opts in with these options and, after its last points, asks for a discovery run
    /// on all of them; its outcome (and, when the model switched, the registration with the
    /// augmented model) is the session's final answer.
    pub discover_with: Vec<pb::Method>,
    /// Discovery options of those sessions (`enabled` is set).
    pub discovery: pb::DiscoveryOptions,
    /// Replay the sessions with discovery on this many of the selected scenarios only (0:
    /// every one): those with the most points, taken from each deformation in turn
    /// ([`discovery_picks`]).
    pub discover_scenarios: usize,
    /// Sessions with discovery replayed at once, side by side with the others: they send their
    /// messages in turn with the others (no more than `concurrency` sessions register at a
    /// time), and wait for their discovery runs (which use only the CPU time registrations
    /// leave) beside them. 0: one after another with the others, `concurrency` at a time.
    pub discovery_concurrency: usize,
    /// TLS settings.
    pub tls: crate::session::Tls,
    /// Sessions replayed at once (1: one after another).
    pub concurrency: usize,
    /// Most resumes of one session (with `resume`).
    pub resume_attempts: u32,
    /// Write every session's registrations as a time series here: one `.vtu` per update and a
    /// `.pvd` collection per session (see `write_series` in `replay/series.rs`).
    pub series: Option<PathBuf>,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            server: "http://127.0.0.1:50051".into(),
            data: PathBuf::new(),
            selection: Selection::Spread(10),
            methods: vec![pb::Method::Libr],
            rate_hz: None,
            batch: 100,
            options: None,
            token: None,
            resume: false,
            timeout: Duration::from_secs(120),
            progress: false,
            discover_with: Vec::new(),
            discovery: pb::DiscoveryOptions::default(),
            discover_scenarios: 0,
            discovery_concurrency: 0,
            tls: crate::session::Tls::default(),
            concurrency: 1,
            resume_attempts: crate::session::Resume::default().attempts,
            series: None,
        }
    }
}

/// One rejected message.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RejectionRecord {
    /// The rejected message's `client_seq`.
    pub client_seq: u64,
    /// Its code name.
    pub code: String,
    /// The server's message.
    pub message: String,
}

/// One registration update of a session, scored.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Step {
    /// Newest message it reflects.
    pub client_seq: u64,
    /// SHA-256 (hex) of the protobuf-encoded `Registration`, as the server's audit log keeps
    /// it: what the client received, byte for byte.
    pub answer_sha256: String,
    /// SHA-256 (hex) of the same `Registration` without its stage timings: equal for equal
    /// results (the transform, displacements, quality, method used, residual), whichever
    /// replica computed them and however long it took.
    pub result_sha256: String,
    /// Points accepted so far.
    pub points_total: u32,
    /// TRE over all nodes (None when the registration could not be read: see `error`).
    pub tre_mm: Option<f64>,
    /// The server's predicted mean TRE (its error estimate; None when it sent none).
    pub predicted_tre_mm: Option<f64>,
    /// Quality name.
    pub quality: String,
    /// Why the quality is not OK, in the server's words (empty when OK).
    pub quality_reason: String,
    /// Method the server used.
    pub method_used: String,
    /// The model METHOD_AUTO chose (`Registration.choice.chosen`; None for the other methods).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub chosen: Option<String>,
    /// Latency of the message it answered (None for an extra update).
    pub latency_ms: Option<f64>,
    /// Why the registration could not be scored.
    pub error: Option<String>,
}

/// One scenario replayed with one method.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ScenarioResult {
    /// `DEFORMATION_ID/INDEX`.
    pub scenario: String,
    /// Measurement category.
    pub category: String,
    /// Case id sent.
    pub case_id: String,
    /// The server's id of the session (empty when none was opened).
    pub session_id: String,
    /// Times the session was resumed after a lost stream.
    pub resumed: u32,
    /// Method asked for.
    pub method: String,
    /// Messages in the session (with the start).
    pub messages: usize,
    /// Updates received.
    pub updates: u64,
    /// Rejected messages.
    pub rejections: Vec<RejectionRecord>,
    /// Registration updates, scored, in arrival order.
    pub steps: Vec<Step>,
    /// TRE of the final registration (the last registration received).
    pub tre: Option<Tre>,
    /// TRE of the initial alignment with no deformation (the starting point).
    pub tre_initial_mm: f64,
    /// Quality of the final registration.
    pub final_quality: Option<String>,
    /// The server's predicted mean TRE of the final registration (its error estimate).
    pub predicted_tre_mm: Option<f64>,
    /// Latencies of this session's answers.
    pub latency_ms: LatencyMs,
    /// How the session ended ("completed", or what went wrong).
    pub end: String,
    /// gRPC status code name when the session ended with a status.
    pub status: Option<String>,
    /// Why this scenario has no TRE, or how the session failed.
    pub error: Option<String>,
    /// The last discovery report (sessions with discovery).
    pub discovery: Option<DiscoveryRecord>,
    /// The session's `.pvd` time series (with `series`).
    pub series: Option<PathBuf>,
}

/// What a session's discovery run reported last.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct DiscoveryRecord {
    /// `DISCOVERY_STATE_...` without the prefix.
    pub state: String,
    /// `effects`, `none`, `unexplained` (when done).
    pub verdict: String,
    /// The effects named.
    pub effects: Vec<String>,
    /// Whether the session switched to the augmented model.
    pub switched: bool,
    /// Wall time of the run, ms.
    pub elapsed_ms: f64,
    /// The server's words.
    pub message: String,
}

impl DiscoveryRecord {
    /// Whether the run ended without a verdict (`FAILED`, `OUT_OF_TIME`) or its end was never
    /// reported (still `RUNNING` when the session ended).
    pub fn unfinished(&self) -> bool {
        self.state != "DONE"
    }

    /// Why the run ended as it did, in the server's words ("the server gave no reason" when it
    /// sent none).
    pub fn reason(&self) -> &str {
        if self.message.trim().is_empty() {
            "the server gave no reason"
        } else {
            &self.message
        }
    }
}

/// The server's discovery budget when a session leaves it to the server's default: the largest
/// one it allows by default (`max_discovery_budget_ms`), for how long the client waits.
pub const DEFAULT_MAX_DISCOVERY_BUDGET: Duration = Duration::from_secs(600);

/// How long after its last answer a session with discovery waits for each further update: the
/// run's budget (the server reports every run by then, `OUT_OF_TIME` when it had to stop it)
/// and a margin for the report and the registration that follows a switch.
pub fn discovery_wait(d: &pb::DiscoveryOptions) -> Duration {
    let budget = if d.budget_ms == 0 {
        DEFAULT_MAX_DISCOVERY_BUDGET
    } else {
        Duration::from_millis(u64::from(d.budget_ms))
    };
    budget + Duration::from_secs(30)
}

/// A registration's transform and displacements, or why they could not be read.
type RegistrationState = Result<(Rigid, Vec<f64>), MessageError>;

/// Reads a registration's transform and displacements (empty displacements count as zeros for a
/// rigid result).
fn registration_state(r: &pb::Registration, nodes: usize) -> RegistrationState {
    let t = r
        .image_to_physical
        .as_ref()
        .ok_or_else(|| MessageError {
            field: "registration.image_to_physical".into(),
            problem: "is unset".into(),
        })
        .and_then(|t| {
            rigid_from_message(t).map_err(|e| e.within("registration.image_to_physical"))
        })?;
    let u = if r.displacement_mm.len() == 3 * nodes {
        r.displacement_mm.iter().map(|&x| f64::from(x)).collect()
    } else if r.displacement_mm.is_empty() && r.method_used == pb::Method::Rigid as i32 {
        vec![0.0; 3 * nodes]
    } else {
        return Err(MessageError {
            field: "registration.displacement_mm".into(),
            problem: format!(
                "has {} values, expected 3 × {nodes} nodes",
                r.displacement_mm.len()
            ),
        });
    };
    Ok((t, u))
}

/// Replays one scenario with one method over `client` and scores it.
#[allow(clippy::too_many_arguments)]
async fn replay_one(
    client: &crate::session::Client,
    case_id: &str,
    sc: &ScenarioData,
    planes: &librplus::eval::ScenarioPlanes,
    geo: &GeometryData,
    method: pb::Method,
    discovery: Option<pb::DiscoveryOptions>,
    opts: &ReplayOptions,
    cfg: &SessionConfig,
    all_latencies: &mut Latencies,
) -> ScenarioResult {
    let msgs = session_messages(case_id, sc, planes, method, discovery, opts);
    let scoring = Scoring { sc, geo };
    let zeros = vec![0.0; 3 * scoring.nodes()];
    let tre_initial_mm = sc
        .measurements
        .initial_alignment
        .as_ref()
        .map_or(f64::NAN, |t| scoring.tre(t, &zeros).tre_mm);
    let keep_series = opts.series.is_some();
    let mut got = Received::default();
    let outcome = run_session(client, &msgs, cfg, |u, lat| {
        got.update(u, lat, &scoring, keep_series)
    })
    .await;
    all_latencies.merge(&got.latencies);
    let status = match &outcome.end {
        SessionEnd::Refused(s) | SessionEnd::Failed(s) => {
            Some(crate::stats::code_name(s.code()).to_string())
        }
        _ => None,
    };
    let (tre, final_quality, mut error) = final_registration(got.last.take(), &outcome, &scoring);
    let method_label = if discovery.is_some() {
        format!("{}+discovery", method_name(method))
    } else {
        method_name(method).to_string()
    };
    let series = session_series(opts, &method_label, &scoring, &got.series, &mut error);
    let predicted_tre_mm = got.steps.last().and_then(|s| s.predicted_tre_mm);
    ScenarioResult {
        scenario: sc.id.clone(),
        category: sc.category.clone(),
        case_id: case_id.to_string(),
        session_id: got.session_id,
        resumed: outcome.resumed,
        method: method_label,
        messages: msgs.len(),
        updates: outcome.updates,
        rejections: got.rejections,
        steps: got.steps,
        tre: if outcome.end.is_completed() {
            tre
        } else {
            None
        },
        tre_initial_mm,
        final_quality,
        predicted_tre_mm,
        latency_ms: got.latencies.summary(),
        end: outcome.end.describe(),
        status,
        error,
        discovery: got.found,
        series,
    }
}

/// The messages of one replayed session: the scenario's, and with `discovery` a session that
/// opts in (with these options, enabled) and asks for a discovery run after its last points.
fn session_messages(
    case_id: &str,
    sc: &ScenarioData,
    planes: &librplus::eval::ScenarioPlanes,
    method: pb::Method,
    discovery: Option<pb::DiscoveryOptions>,
    opts: &ReplayOptions,
) -> Vec<pb::StreamRegisterRequest> {
    let mut msgs = stream_messages(case_id, method, opts.options, sc, planes, opts.batch);
    if let Some(d) = discovery {
        use pb::stream_register_request::Msg;
        if let Some(Msg::Start(start)) = msgs.first_mut().and_then(|m| m.msg.as_mut()) {
            start.discovery = Some(pb::DiscoveryOptions { enabled: true, ..d });
        }
        let client_seq = msgs.len() as u64 + 1;
        msgs.push(pb::StreamRegisterRequest {
            client_seq,
            msg: Some(Msg::Discover(pb::DiscoverNow {})),
        });
    }
    msgs
}

/// What a replayed session is scored against: its scenario's ground truth on its geometry.
struct Scoring<'a> {
    sc: &'a ScenarioData,
    geo: &'a GeometryData,
}

impl Scoring<'_> {
    /// The mesh's node count.
    fn nodes(&self) -> usize {
        self.geo.model.mesh.nodes().len()
    }

    /// The TRE of a registration (transform `t`, node displacements `u`) against the truth.
    fn tre(&self, t: &Rigid, u: &[f64]) -> Tre {
        tre(
            self.geo.model.mesh.nodes(),
            (t, u),
            (
                &self.sc.truth.image_to_physical,
                &self.sc.truth.displacement,
            ),
            &self.geo.surface,
            &self.geo.targets,
        )
    }
}

/// What a session's updates brought, recorded as they arrive.
#[derive(Default)]
struct Received {
    /// Latencies of the messages answered.
    latencies: Latencies,
    /// Registrations, scored.
    steps: Vec<Step>,
    /// Rejected messages.
    rejections: Vec<RejectionRecord>,
    /// The last registration read (or why it could not be) and its quality.
    last: Option<(RegistrationState, String)>,
    /// The server's id of the session.
    session_id: String,
    /// Registrations kept for the time series (with `series`).
    series: Vec<SeriesStep>,
    /// The last discovery report.
    found: Option<DiscoveryRecord>,
}

impl Received {
    /// Records one update (`lat`: the latency of the message it answers): a registration scored
    /// (and kept for the time series when `keep_series`), a rejection, a discovery report.
    fn update(
        &mut self,
        u: &pb::StreamUpdate,
        lat: Option<Duration>,
        scoring: &Scoring<'_>,
        keep_series: bool,
    ) {
        if let Some(l) = lat {
            self.latencies.record(l);
        }
        self.session_id.clone_from(&u.session_id);
        match &u.update {
            Some(pb::stream_update::Update::Registration(r)) => {
                self.registration(u, r, lat, scoring, keep_series)
            }
            Some(pb::stream_update::Update::Rejection(r)) => {
                self.rejections.push(RejectionRecord {
                    client_seq: r.client_seq,
                    code: r.code.clone(),
                    message: r.message.clone(),
                })
            }
            Some(pb::stream_update::Update::Discovery(d)) => self.found = Some(discovery_record(d)),
            None => {}
        }
    }

    /// Records a registration: read, scored, and kept as the last one.
    fn registration(
        &mut self,
        u: &pb::StreamUpdate,
        r: &pb::Registration,
        lat: Option<Duration>,
        scoring: &Scoring<'_>,
        keep_series: bool,
    ) {
        let nodes = scoring.nodes();
        let state = registration_state(r, nodes);
        let quality = quality_name(r.quality);
        if let (true, Ok((t, d))) = (keep_series, &state) {
            self.series.push(SeriesStep {
                client_seq: u.last_client_seq,
                image_to_physical: *t,
                displacement: d.clone(),
                uncertainty: r
                    .error_estimate
                    .as_ref()
                    .filter(|e| e.node_uncertainty_mm.len() == nodes)
                    .map(|e| {
                        e.node_uncertainty_mm
                            .iter()
                            .map(|&x| f64::from(x))
                            .collect()
                    }),
            });
        }
        self.steps.push(Step {
            client_seq: u.last_client_seq,
            answer_sha256: sha256_hex(&prost::Message::encode_to_vec(r)),
            result_sha256: result_sha256(r),
            points_total: u.points_total,
            tre_mm: state.as_ref().ok().map(|(t, d)| scoring.tre(t, d).tre_mm),
            predicted_tre_mm: r.error_estimate.as_ref().map(|e| e.predicted_tre_mm),
            quality: quality.clone(),
            quality_reason: r.quality_reason.clone(),
            method_used: pb::Method::try_from(r.method_used).map_or_else(
                |_| format!("UNKNOWN_{}", r.method_used),
                |m| method_name(m).to_string(),
            ),
            chosen: r.choice.as_ref().map(|c| c.chosen.clone()),
            latency_ms: lat.map(|l| l.as_secs_f64() * 1e3),
            error: state.as_ref().err().map(|e| e.to_string()),
        });
        self.last = Some((state, quality));
    }
}

/// A discovery report as recorded.
fn discovery_record(d: &pb::DiscoveryReport) -> DiscoveryRecord {
    DiscoveryRecord {
        state: pb::DiscoveryState::try_from(d.state).map_or_else(
            |_| format!("UNKNOWN_{}", d.state),
            |x| {
                x.as_str_name()
                    .trim_start_matches("DISCOVERY_STATE_")
                    .to_string()
            },
        ),
        verdict: d.verdict.clone(),
        effects: d.effects.clone(),
        switched: d.switched,
        elapsed_ms: d.elapsed_ms,
        message: d.message.clone(),
    }
}

/// The final registration's TRE and quality, and why the scenario has none: the last
/// registration unreadable, none received, or the session not completed (how it ended).
fn final_registration(
    last: Option<(RegistrationState, String)>,
    outcome: &SessionOutcome,
    scoring: &Scoring<'_>,
) -> (Option<Tre>, Option<String>, Option<String>) {
    let (tre, final_quality, mut error) = match last {
        Some((Ok((t, u)), q)) => (Some(scoring.tre(&t, &u)), Some(q), None),
        Some((Err(e), q)) => (None, Some(q), Some(e.to_string())),
        None => (None, None, Some("no registration received".to_string())),
    };
    if !outcome.end.is_completed() {
        error = Some(outcome.end.describe());
    }
    (tre, final_quality, error)
}

/// Writes the session's time series (with `opts.series`, when registrations were read): its
/// `.pvd`, or None; a failure to write it becomes the session's `error`.
fn session_series(
    opts: &ReplayOptions,
    method_label: &str,
    scoring: &Scoring<'_>,
    steps: &[SeriesStep],
    error: &mut Option<String>,
) -> Option<PathBuf> {
    match &opts.series {
        Some(dir) if !steps.is_empty() => {
            let name = series_name(&scoring.sc.id, method_label);
            match write_series(dir, &name, scoring.geo, scoring.sc, steps) {
                Ok(p) => Some(p),
                Err(e) => {
                    *error = Some(format!("series: {e}"));
                    None
                }
            }
        }
        _ => None,
    }
}

/// Replays the selected scenarios with every method (one session each, in lockstep) and scores
/// the final registrations against the ground truth. A session that fails is recorded in its
/// result; only an unreadable dataset or an unreachable server is an error.
pub async fn replay(opts: &ReplayOptions) -> Result<ReplaySummary> {
    let loaded = load_selection(&opts.data, &opts.selection, true)?;
    if loaded.scenarios.is_empty() {
        bail!("no scenarios selected in {}", opts.data.display());
    }
    // Replicas (several URLs): connected lazily (one may be down now), sessions spread over
    // them.
    let replicas = if opts.server.contains(',') {
        crate::session::connect_replicas(&opts.server, &opts.tls)?
    } else {
        Vec::new()
    };
    let client = match replicas.first() {
        Some(c) => c.clone(),
        None => connect_with(&opts.server, &opts.tls).await?,
    };
    let mut cfg = SessionConfig::new(opts.timeout, opts.token.as_deref())?;
    cfg.resume = opts.resume.then(|| crate::session::Resume {
        attempts: opts.resume_attempts,
        ..Default::default()
    });
    cfg.rate_hz = opts.rate_hz;
    cfg.replicas = replicas;
    if opts.discovery_concurrency > 0 && !opts.discover_with.is_empty() {
        // Sessions with discovery run beside the others, but send in turn with them: no more
        // than `concurrency` sessions at a time register, and a session waiting for its
        // discovery run holds no turn.
        cfg.lockstep = Some(std::sync::Arc::new(tokio::sync::Semaphore::new(
            opts.concurrency.max(1),
        )));
    }
    let mut all = Latencies::new();
    let mut per_method: BTreeMap<String, Latencies> = BTreeMap::new();
    let mut results = Vec::new();
    let runs: Vec<(pb::Method, Option<pb::DiscoveryOptions>)> = opts
        .methods
        .iter()
        .map(|&m| (m, None))
        .chain(
            opts.discover_with
                .iter()
                .map(|&m| (m, Some(opts.discovery))),
        )
        .collect();
    let picked = discovery_picks(&loaded.scenarios, opts.discover_scenarios);
    let (client, cfg) = (&client, &cfg);
    // Futures made in a plain loop (not a closure over borrowed items), so the whole replay
    // stays `Send`. Each job is numbered in replay order (scenario by scenario, method by
    // method), the order of the results.
    let mut jobs = Vec::new();
    let mut discovery_jobs = Vec::new();
    let mut order = 0usize;
    for (si, s) in loaded.scenarios.iter().enumerate() {
        let geo = &loaded.geometries[&s.case_id];
        for &(method, discovery) in &runs {
            if discovery.is_some() && !picked[si] {
                continue;
            }
            let mut cfg = cfg.clone();
            cfg.first_replica = order;
            if let Some(d) = &discovery {
                cfg.final_timeout = Some(discovery_wait(d));
            }
            let at = order;
            order += 1;
            let job = async move {
                let mut lat = Latencies::new();
                let r = replay_one(
                    client,
                    &s.case_id,
                    &s.scenario,
                    &s.planes,
                    geo,
                    method,
                    discovery,
                    opts,
                    &cfg,
                    &mut lat,
                )
                .await;
                (at, r, lat)
            };
            if discovery.is_some() && opts.discovery_concurrency > 0 {
                discovery_jobs.push(job);
            } else {
                jobs.push(job);
            }
        }
    }
    let total = order;
    let others = futures_util::stream::iter(jobs).buffered(opts.concurrency.max(1));
    let beside =
        futures_util::stream::iter(discovery_jobs).buffered(opts.discovery_concurrency.max(1));
    let mut done = futures_util::stream::select(others, beside);
    let mut numbered = Vec::with_capacity(total);
    while let Some((at, r, lat)) = done.next().await {
        {
            all.merge(&lat);
            per_method.entry(r.method.clone()).or_default().merge(&lat);
            if opts.progress {
                eprintln!(
                    "[{}/{total}] {} {}: {} updates, {} rejected, TRE {}{}{}{}",
                    results.len() + 1,
                    r.scenario,
                    r.method,
                    r.updates,
                    r.rejections.len(),
                    r.tre
                        .map_or("-".to_string(), |t| format!("{:.2} mm", t.tre_mm)),
                    r.discovery.as_ref().map_or(String::new(), discovery_line),
                    if r.resumed > 0 {
                        format!("; resumed {}×", r.resumed)
                    } else {
                        String::new()
                    },
                    r.error
                        .as_ref()
                        .map_or(String::new(), |e| format!(" ({e})"))
                );
            }
            results.push(r);
            numbered.push(at);
        }
    }
    // In replay order, however the sessions finished.
    let mut ordered: Vec<(usize, ScenarioResult)> = numbered.into_iter().zip(results).collect();
    ordered.sort_by_key(|(at, _)| *at);
    let results: Vec<ScenarioResult> = ordered.into_iter().map(|(_, r)| r).collect();
    if opts.series.is_some()
        && let Some(r) = results.iter().find(|r| {
            r.error
                .as_deref()
                .is_some_and(|e| e.starts_with("series: "))
        })
    {
        bail!(
            "could not write the time series of {} ({}): {}",
            r.scenario,
            r.method,
            r.error.as_deref().unwrap_or_default()
        );
    }
    Ok(summarize(
        loaded.scenarios.len(),
        results,
        &all,
        &per_method,
    ))
}

/// Which of `scenarios` get a session with discovery: `n` of them (0: all), those with the most
/// points, taken from each deformation in turn (in order of first appearance), so that a few
/// runs still cover every deformation and none is spent on a scenario too sparse for one.
pub fn discovery_picks(scenarios: &[crate::data::Replayable], n: usize) -> Vec<bool> {
    if n == 0 || n >= scenarios.len() {
        return vec![true; scenarios.len()];
    }
    let mut groups: Vec<(String, Vec<usize>)> = Vec::new();
    for (i, s) in scenarios.iter().enumerate() {
        let d = s
            .scenario
            .id
            .rsplit_once('/')
            .map_or(s.scenario.id.as_str(), |(d, _)| d);
        match groups.iter_mut().find(|(g, _)| g == d) {
            Some((_, v)) => v.push(i),
            None => groups.push((d.to_string(), vec![i])),
        }
    }
    let points = |i: usize| scenarios[i].scenario.measurements.points.len();
    for (_, v) in &mut groups {
        // Most points first; the selection's order among equals.
        v.sort_by_key(|&i| (std::cmp::Reverse(points(i)), i));
    }
    let mut picked = vec![false; scenarios.len()];
    let mut taken = 0;
    for round in 0.. {
        let mut any = false;
        for (_, v) in &groups {
            if let Some(&i) = v.get(round) {
                any = true;
                if taken < n {
                    picked[i] = true;
                    taken += 1;
                }
            }
        }
        if !any || taken == n {
            break;
        }
    }
    picked
}

/// A session's discovery outcome for its progress line: the verdict (and the switch) of a run
/// that finished, else its state and the server's reason.
fn discovery_line(d: &DiscoveryRecord) -> String {
    if d.unfinished() {
        return format!(
            "; discovery {} ({:.1} s): {}",
            d.state,
            d.elapsed_ms / 1e3,
            d.reason()
        );
    }
    format!(
        "; discovery {} {}{} ({:.1} s)",
        d.state,
        d.verdict,
        if d.switched {
            format!(", switched to {}", d.effects.join("+"))
        } else {
            String::new()
        },
        d.elapsed_ms / 1e3
    )
}

/// SHA-256 of `bytes`, lower-case hex (the audit log's `answer_sha256`).
pub fn sha256_hex(bytes: &[u8]) -> String {
    ring::digest::digest(&ring::digest::SHA256, bytes)
        .as_ref()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// SHA-256 (hex) of a registration without its stage timings (the part that differs between two
/// computations of the same result).
pub fn result_sha256(r: &pb::Registration) -> String {
    let mut r = r.clone();
    r.timings = None;
    sha256_hex(&prost::Message::encode_to_vec(&r))
}
