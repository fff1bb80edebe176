//! `replay`: streams recorded dataset scenarios to a server, one session per scenario and method,
//! in lockstep, and scores every registration against the ground truth (TRE).

use crate::data::{Selection, load_selection};
use crate::messages::{MessageError, rigid_from_message, stream_messages};
use crate::pb;
use crate::session::{SessionConfig, SessionEnd, connect_with, run_session};
use crate::stats::{Latencies, LatencyMs};
use anyhow::{Result, bail};
use futures_util::StreamExt;
use librplus::eval::{GeometryData, ScenarioData, Tre, tre};
use librplus::mesh::rigid::Rigid;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

/// The short name of a method ("default", "rigid", "libr", "libr_plus").
pub fn method_name(m: pb::Method) -> &'static str {
    match m {
        pb::Method::Unspecified => "default",
        pb::Method::Rigid => "rigid",
        pb::Method::Libr => "libr",
        pb::Method::LibrPlus => "libr_plus",
        pb::Method::V2s => "v2s",
        pb::Method::Adaptive => "adaptive",
    }
}

/// A method from its short name (`rigid`, `libr`, `libr_plus` or `libr+`, `v2s`, `adaptive`,
/// `default`).
pub fn parse_method(s: &str) -> Result<pb::Method> {
    Ok(match s.trim() {
        "rigid" => pb::Method::Rigid,
        "libr" => pb::Method::Libr,
        "libr_plus" | "libr+" | "libr-plus" => pb::Method::LibrPlus,
        "v2s" => pb::Method::V2s,
        "adaptive" => pb::Method::Adaptive,
        "default" => pb::Method::Unspecified,
        other => {
            bail!(
                "unknown method {other:?}: expected rigid, libr, libr_plus, v2s, adaptive or default"
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
    /// TLS settings.
    pub tls: crate::session::Tls,
    /// Sessions replayed at once (1: one after another).
    pub concurrency: usize,
    /// Most resumes of one session (with `resume`).
    pub resume_attempts: u32,
    /// Write every session's registrations as a time series here: one `.vtu` per update and a
    /// `.pvd` collection per session (see `write_series` in this module).
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
    /// Method the server used.
    pub method_used: String,
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

/// Mean TRE and count of one category.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct CategorySummary {
    /// Mean final TRE (mm).
    pub tre_mm: f64,
    /// Scenarios with a TRE.
    pub scenarios: usize,
}

/// Per-method figures over every replayed scenario.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct MethodSummary {
    /// Mean final TRE over all nodes (mm).
    pub tre_mm: f64,
    /// Mean over surface nodes.
    pub tre_surface_mm: f64,
    /// Mean over interior nodes.
    pub tre_interior_mm: f64,
    /// Mean over the targets (of scenarios whose geometry has targets).
    pub tre_targets_mm: f64,
    /// Mean TRE of the initial alignment.
    pub tre_initial_mm: f64,
    /// Scenarios with a final TRE.
    pub scenarios: usize,
    /// Scenarios without one (failed session or no registration).
    pub failed: usize,
    /// Registration updates by quality name.
    pub quality: BTreeMap<String, u64>,
    /// Mean of the server's predicted TRE over the scenarios with a final TRE and a prediction
    /// (None when the server sent no error estimate), beside `tre_mm` over the same scenarios.
    pub predicted_tre_mm: Option<(f64, f64)>,
    /// Latency of this method's answers.
    pub latency_ms: LatencyMs,
    /// Mean final TRE per measurement category.
    pub by_category: BTreeMap<String, CategorySummary>,
    /// Sessions with discovery: their final discovery reports by verdict (or state when not
    /// done), and how many switched to an augmented model (by its effects).
    pub discovery: BTreeMap<String, u64>,
}

/// What `replay` measured (`replay --json` prints it).
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ReplaySummary {
    /// Updates received in all.
    pub updates: u64,
    /// Scenarios replayed.
    pub scenarios: usize,
    /// Sessions (scenarios × methods).
    pub sessions: usize,
    /// Sessions without a final TRE.
    pub failed: usize,
    /// Rejected messages in all.
    pub rejections: u64,
    /// Rejections by code.
    pub rejections_by_code: BTreeMap<String, u64>,
    /// Mean final TRE (mm) per method.
    pub tre_mm: BTreeMap<String, f64>,
    /// Latency of every answer.
    pub latency_ms: LatencyMs,
    /// Per-method details.
    pub methods: BTreeMap<String, MethodSummary>,
    /// Every session.
    pub results: Vec<ScenarioResult>,
}

fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (s, c) = v
        .into_iter()
        .filter(|x| x.is_finite())
        .fold((0.0, 0usize), |(s, c), x| (s + x, c + 1));
    if c == 0 { f64::NAN } else { s / c as f64 }
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
    let mut found: Option<DiscoveryRecord> = None;
    let nodes = geo.model.mesh.nodes();
    let score = |t: &Rigid, u: &[f64]| {
        tre(
            nodes,
            (t, u),
            (&sc.truth.image_to_physical, &sc.truth.displacement),
            &geo.surface,
            &geo.targets,
        )
    };
    let zeros = vec![0.0; 3 * nodes.len()];
    let tre_initial_mm = sc
        .measurements
        .initial_alignment
        .as_ref()
        .map_or(f64::NAN, |t| score(t, &zeros).tre_mm);
    let mut latencies = Latencies::new();
    let mut steps = Vec::new();
    let mut rejections = Vec::new();
    let mut last: Option<(RegistrationState, String)> = None;
    let mut session_id = String::new();
    let mut series: Vec<SeriesStep> = Vec::new();
    let outcome = run_session(client, &msgs, cfg, |u, lat| {
        if let Some(l) = lat {
            latencies.record(l);
        }
        session_id.clone_from(&u.session_id);
        match &u.update {
            Some(pb::stream_update::Update::Registration(r)) => {
                let state = registration_state(r, nodes.len());
                let quality = quality_name(r.quality);
                if let (Some(_), Ok((t, d))) = (&opts.series, &state) {
                    series.push(SeriesStep {
                        client_seq: u.last_client_seq,
                        image_to_physical: *t,
                        displacement: d.clone(),
                        uncertainty: r
                            .error_estimate
                            .as_ref()
                            .filter(|e| e.node_uncertainty_mm.len() == nodes.len())
                            .map(|e| {
                                e.node_uncertainty_mm
                                    .iter()
                                    .map(|&x| f64::from(x))
                                    .collect()
                            }),
                    });
                }
                steps.push(Step {
                    client_seq: u.last_client_seq,
                    answer_sha256: sha256_hex(&prost::Message::encode_to_vec(r)),
                    result_sha256: result_sha256(r),
                    points_total: u.points_total,
                    tre_mm: state.as_ref().ok().map(|(t, d)| score(t, d).tre_mm),
                    predicted_tre_mm: r.error_estimate.as_ref().map(|e| e.predicted_tre_mm),
                    quality: quality.clone(),
                    method_used: pb::Method::try_from(r.method_used).map_or_else(
                        |_| format!("UNKNOWN_{}", r.method_used),
                        |m| method_name(m).to_string(),
                    ),
                    latency_ms: lat.map(|l| l.as_secs_f64() * 1e3),
                    error: state.as_ref().err().map(|e| e.to_string()),
                });
                last = Some((state, quality));
            }
            Some(pb::stream_update::Update::Rejection(r)) => rejections.push(RejectionRecord {
                client_seq: r.client_seq,
                code: r.code.clone(),
                message: r.message.clone(),
            }),
            Some(pb::stream_update::Update::Discovery(d)) => {
                found = Some(DiscoveryRecord {
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
                })
            }
            None => {}
        }
    })
    .await;
    all_latencies.merge(&latencies);
    let status = match &outcome.end {
        SessionEnd::Refused(s) | SessionEnd::Failed(s) => {
            Some(crate::stats::code_name(s.code()).to_string())
        }
        _ => None,
    };
    let (tre, final_quality, mut error) = match last {
        Some((Ok((t, u)), q)) => (Some(score(&t, &u)), Some(q), None),
        Some((Err(e), q)) => (None, Some(q), Some(e.to_string())),
        None => (None, None, Some("no registration received".to_string())),
    };
    if !outcome.end.is_completed() {
        error = Some(outcome.end.describe());
    }
    let method_label = if discovery.is_some() {
        format!("{}+discovery", method_name(method))
    } else {
        method_name(method).to_string()
    };
    let series = match &opts.series {
        Some(dir) if !series.is_empty() => {
            let name = series_name(&sc.id, &method_label);
            match write_series(dir, &name, geo, sc, &series) {
                Ok(p) => Some(p),
                Err(e) => {
                    error = Some(format!("series: {e}"));
                    None
                }
            }
        }
        _ => None,
    };
    let predicted_tre_mm = steps.last().and_then(|s| s.predicted_tre_mm);
    ScenarioResult {
        scenario: sc.id.clone(),
        category: sc.category.clone(),
        case_id: case_id.to_string(),
        session_id,
        resumed: outcome.resumed,
        method: method_label,
        messages: msgs.len(),
        updates: outcome.updates,
        rejections,
        steps,
        tre: if outcome.end.is_completed() {
            tre
        } else {
            None
        },
        tre_initial_mm,
        final_quality,
        predicted_tre_mm,
        latency_ms: latencies.summary(),
        end: outcome.end.describe(),
        status,
        error,
        discovery: found,
        series,
    }
}

/// One registration of a session, kept for its time series.
struct SeriesStep {
    client_seq: u64,
    image_to_physical: Rigid,
    displacement: Vec<f64>,
    /// The error estimate's per-node bound, when the server sent it for every node.
    uncertainty: Option<Vec<f64>>,
}

/// A file-name-safe name for a session's series: `SCENARIO-METHOD` with every character outside
/// `A-Z a-z 0-9 . _ + -` replaced by `_` (a scenario id `g1-L-00/3` becomes `g1-L-00_3`).
pub fn series_name(scenario: &str, method: &str) -> String {
    format!("{scenario}-{method}")
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "._+-".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Writes a session's registrations as a ParaView time series: `DIR/NAME/update-KKKK.vtu`, one
/// per registration in arrival order, and `DIR/NAME.pvd`, whose time steps are the acquisition
/// times of the newest message each registration reflects (seconds after the session's first
/// data message, [`crate::messages::EPOCH_UNIX_S`]). Each `.vtu` is the preoperative
/// tetrahedral mesh with its nodes at their **registered** positions (physical frame, mm), and
/// point data `displacement` (the registration's node displacement, image frame, mm: the nodes
/// are already moved, so do not warp by it again) and `error_mm` (distance from the registered
/// to the true node position: the dataset's ground truth, which only a replay has). Files are
/// written atomically; returns the `.pvd`'s path.
fn write_series(
    dir: &std::path::Path,
    name: &str,
    geo: &GeometryData,
    sc: &ScenarioData,
    steps: &[SeriesStep],
) -> Result<PathBuf, String> {
    use librplus::mesh::io::{DataArray, MeshFile, PvdEntry, WriteOptions, pvd_collection};
    let mesh = &geo.model.mesh;
    let x = mesh.nodes();
    let place = |t: &Rigid, u: &[f64]| -> Vec<[f64; 3]> {
        x.iter()
            .enumerate()
            .map(|(i, p)| t.apply([0, 1, 2].map(|a| p[a] + u[3 * i + a])))
            .collect()
    };
    let truth = place(&sc.truth.image_to_physical, &sc.truth.displacement);
    let mut entries = Vec::with_capacity(steps.len());
    for (k, s) in steps.iter().enumerate() {
        let nodes = place(&s.image_to_physical, &s.displacement);
        let error: Vec<f64> = nodes
            .iter()
            .zip(&truth)
            .map(|(p, q)| {
                ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
            })
            .collect();
        let file = MeshFile {
            nodes,
            tets: mesh.tets().to_vec(),
            point_data: [
                DataArray::new("displacement", 3, s.displacement.clone()),
                DataArray::new("error_mm", 1, error),
            ]
            .into_iter()
            .chain(
                s.uncertainty
                    .as_ref()
                    .map(|b| DataArray::new("uncertainty_mm", 1, b.clone())),
            )
            .collect(),
            ..MeshFile::default()
        };
        let rel = format!("{name}/update-{:04}.vtu", k + 1);
        let bytes = librplus::mesh::io::write_bytes(
            &file,
            librplus::mesh::io::Format::Vtu,
            WriteOptions::default(),
            &dir.join(&rel),
        )
        .map_err(|e| e.to_string())?;
        librplus::util::write_atomic(&dir.join(&rel), &bytes).map_err(|e| e.to_string())?;
        entries.push(PvdEntry {
            timestep: (s.client_seq as f64 - 2.0).max(0.0),
            file: rel,
        });
    }
    let pvd = dir.join(format!("{name}.pvd"));
    librplus::util::write_atomic(&pvd, pvd_collection(&entries).as_bytes())
        .map_err(|e| e.to_string())?;
    Ok(pvd)
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
    let total = loaded.scenarios.len() * runs.len();
    let (client, cfg) = (&client, &cfg);
    // Futures made in a plain loop (not a closure over borrowed items), so the whole replay
    // stays `Send`.
    let mut jobs = Vec::with_capacity(total);
    for s in &loaded.scenarios {
        let geo = &loaded.geometries[&s.case_id];
        for &(method, discovery) in &runs {
            let mut cfg = cfg.clone();
            cfg.first_replica = jobs.len();
            jobs.push(async move {
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
                (r, lat)
            });
        }
    }
    let mut done = futures_util::stream::iter(jobs).buffered(opts.concurrency.max(1));
    while let Some((r, lat)) = done.next().await {
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
                    r.discovery.as_ref().map_or(String::new(), |d| format!(
                        "; discovery {} {}{} ({:.1} s)",
                        d.state,
                        d.verdict,
                        if d.switched {
                            format!(", switched to {}", d.effects.join("+"))
                        } else {
                            String::new()
                        },
                        d.elapsed_ms / 1e3
                    )),
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
        }
    }
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

fn summarize(
    scenarios: usize,
    results: Vec<ScenarioResult>,
    all: &Latencies,
    per_method: &BTreeMap<String, Latencies>,
) -> ReplaySummary {
    let mut s = ReplaySummary {
        scenarios,
        sessions: results.len(),
        latency_ms: all.summary(),
        ..Default::default()
    };
    for r in &results {
        s.updates += r.updates;
        s.rejections += r.rejections.len() as u64;
        for x in &r.rejections {
            *s.rejections_by_code.entry(x.code.clone()).or_default() += 1;
        }
        if r.tre.is_none() {
            s.failed += 1;
        }
    }
    for (name, lat) in per_method {
        let mine: Vec<&ScenarioResult> = results.iter().filter(|r| &r.method == name).collect();
        let ok: Vec<&Tre> = mine.iter().filter_map(|r| r.tre.as_ref()).collect();
        let mut m = MethodSummary {
            tre_mm: mean(ok.iter().map(|t| t.tre_mm)),
            tre_surface_mm: mean(ok.iter().map(|t| t.tre_surface_mm)),
            tre_interior_mm: mean(ok.iter().map(|t| t.tre_interior_mm)),
            tre_targets_mm: mean(ok.iter().map(|t| t.tre_targets_mm)),
            tre_initial_mm: mean(mine.iter().map(|r| r.tre_initial_mm)),
            scenarios: ok.len(),
            failed: mine.len() - ok.len(),
            latency_ms: lat.summary(),
            ..Default::default()
        };
        for r in &mine {
            for st in &r.steps {
                *m.quality.entry(st.quality.clone()).or_default() += 1;
            }
            if let Some(d) = &r.discovery {
                let key = if d.switched {
                    format!("switched to {}", d.effects.join("+"))
                } else if d.state == "DONE" {
                    d.verdict.clone()
                } else {
                    d.state.to_lowercase()
                };
                *m.discovery.entry(key).or_default() += 1;
            }
        }
        let both: Vec<(f64, f64)> = mine
            .iter()
            .filter_map(|r| Some((r.predicted_tre_mm?, r.tre.as_ref()?.tre_mm)))
            .collect();
        if !both.is_empty() {
            m.predicted_tre_mm = Some((
                mean(both.iter().map(|b| b.0)),
                mean(both.iter().map(|b| b.1)),
            ));
        }
        let mut cats: BTreeMap<String, Vec<f64>> = BTreeMap::new();
        for r in &mine {
            if let Some(t) = &r.tre {
                cats.entry(r.category.clone()).or_default().push(t.tre_mm);
            }
        }
        m.by_category = cats
            .into_iter()
            .map(|(c, v)| {
                (
                    c,
                    CategorySummary {
                        scenarios: v.len(),
                        tre_mm: mean(v),
                    },
                )
            })
            .collect();
        s.tre_mm.insert(name.clone(), m.tre_mm);
        s.methods.insert(name.clone(), m);
    }
    s.results = results;
    s
}

/// The summary as a readable table.
pub fn replay_table(s: &ReplaySummary) -> String {
    use std::fmt::Write;
    let mut o = String::new();
    let f = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.2}"));
    let _ = writeln!(
        o,
        "{:<16} {:<13} {:<14} {:>5} {:>7} {:>9} {:>9} {:>9} {:>9}  quality / error",
        "scenario",
        "category",
        "method",
        "msgs",
        "updates",
        "rejected",
        "TRE0 mm",
        "TRE mm",
        "p50 ms"
    );
    for r in &s.results {
        let _ = writeln!(
            o,
            "{:<16} {:<13} {:<14} {:>5} {:>7} {:>9} {:>9} {:>9} {:>9}  {}",
            r.scenario,
            r.category,
            r.method,
            r.messages,
            r.updates,
            r.rejections.len(),
            f(Some(r.tre_initial_mm)),
            f(r.tre.map(|t| t.tre_mm)),
            f(Some(r.latency_ms.p50)),
            r.error
                .clone()
                .or_else(|| r.final_quality.clone())
                .unwrap_or_default()
        );
    }
    let _ = writeln!(o);
    for (name, m) in &s.methods {
        let _ = writeln!(
            o,
            "{name}: TRE {} mm (surface {}, interior {}, targets {}; initial {}) over {} scenarios, {} failed; latency p50 {:.1} ms, p95 {:.1} ms",
            f(Some(m.tre_mm)),
            f(Some(m.tre_surface_mm)),
            f(Some(m.tre_interior_mm)),
            f(Some(m.tre_targets_mm)),
            f(Some(m.tre_initial_mm)),
            m.scenarios,
            m.failed,
            m.latency_ms.p50,
            m.latency_ms.p95
        );
        for (c, cs) in &m.by_category {
            let _ = writeln!(
                o,
                "  {c:<13} TRE {} mm ({} scenarios)",
                f(Some(cs.tre_mm)),
                cs.scenarios
            );
        }
        let q: Vec<String> = m.quality.iter().map(|(k, v)| format!("{k} {v}")).collect();
        let _ = writeln!(o, "  quality: {}", q.join(", "));
        if let Some((p, t)) = m.predicted_tre_mm {
            let _ = writeln!(
                o,
                "  error estimate: predicted TRE {p:.2} mm, measured {t:.2} mm (mean of the final registrations)"
            );
        }
        if !m.discovery.is_empty() {
            let d: Vec<String> = m
                .discovery
                .iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect();
            let _ = writeln!(o, "  discovery: {}", d.join(", "));
        }
    }
    let l = &s.latency_ms;
    let _ = writeln!(
        o,
        "{} updates over {} sessions ({} scenarios), {} rejected, {} failed; latency p50 {:.1} ms, p95 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        s.updates, s.sessions, s.scenarios, s.rejections, s.failed, l.p50, l.p95, l.p99, l.max
    );
    o
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
