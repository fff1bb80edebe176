//! The OpenIGTLink bridge (`librplus-server igtl`): an OpenIGTLink server for navigation software
//! that forwards what it receives to a LIBR+ gRPC server as a streamed session and sends each
//! registration back as OpenIGTLink messages.
//!
//! One TCP connection is at most one registration session (`StreamRegister` on the gRPC server,
//! case and method fixed by the bridge's options), opened when the connection's first message
//! that carries data (`POINT`, or a `POLYDATA` plane) arrives: a connection that sends nothing
//! holds no server session. **Limits** (so that idle or hostile sockets cannot take the server's
//! session slots): at most [`BridgeConfig::max_sessions`] connections are served at once (more
//! are answered with `STATUS` 6, busy, and closed); a connection that sends no complete message
//! for [`BridgeConfig::idle_timeout`] before its session is open, or for
//! [`BridgeConfig::session_idle_timeout`] after, is sent `STATUS` 7 (time-out) and closed; when
//! the gRPC session ends (refused, timed out by the server, the server draining), the connection
//! is closed after the `STATUS` saying why. Received (device names are free unless stated):
//!
//! | message | meaning |
//! | --- | --- |
//! | `POINT` | surface points (a stylus sweep or a laparoscope frame): one `SurfaceBatch` |
//! | `TRANSFORM` device *D* | the pose of ultrasound plane *D*: plane (u, v, 0) → physical, mm |
//! | `POLYDATA` device *D* | the points found in plane *D* (u, v, 0 in the plane's frame, mm; point scalar `kind`: 0 contour, 1 vessel, absent: all contour), sent with the last pose of *D*: one `UltrasoundPlane` |
//!
//! Sent after every registration (device names fixed): `TRANSFORM` [`DEVICE_TRANSFORM`] (image →
//! physical), `POINT` [`DEVICE_TARGETS`] (the targets given with `--targets`, where the
//! registration puts them) and `POLYDATA` [`DEVICE_LIVER`] (the liver's boundary surface at its
//! registered position, point vector `displacement` and, when the server estimates its error, point
//! scalar `uncertainty_mm`: the node's 90 % error bound); `STATUS` [`DEVICE_STATUS`] when the
//! quality is not OK, for a rejected message, and for a malformed or unsupported one (the
//! connection goes on; only a message whose header cannot be trusted ends it).
//!
//! **Frames.** LIBR+ works in LPS; 3D Slicer's world is RAS. With `--frame ras` (the default)
//! every coordinate received is converted RAS → LPS (x and y negated) and every one sent LPS →
//! RAS, and the image → physical transform is sent as `F T F` (F = diag(−1, −1, 1)): the
//! transform to apply in Slicer to the preoperative model loaded there (Slicer converts LPS files
//! to RAS on loading). A plane pose (plane frame → physical) is converted as `F P`. With
//! `--frame lps` everything passes unchanged.

use super::wire::{
    self, AttributeKind, AttributeLocation, CellArray, Decoder, EncodeOptions, Message,
    PointElement, PolyAttribute, PolyData, Status, Transform, status_code,
};
use librplus::mesh::TetMesh;
use librplus::mesh::locate::TetLocator;
use librplus::mesh::rigid::Rigid;
use librplus_client::pb;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{Semaphore, mpsc};
use tokio::time::Instant;
use tracing::Instrument;

/// Device name of the image → physical `TRANSFORM` sent after each registration.
pub const DEVICE_TRANSFORM: &str = "LIBR_ImageToPhysical";
/// Device name of the registered targets' `POINT`.
pub const DEVICE_TARGETS: &str = "LIBR_Targets";
/// Device name of the registered liver's `POLYDATA`.
pub const DEVICE_LIVER: &str = "LIBR_Liver";
/// Device name of the bridge's `STATUS` messages.
pub const DEVICE_STATUS: &str = "LIBR_Status";

/// The patient frame the OpenIGTLink peer works in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    /// Right, anterior, superior (3D Slicer's world).
    Ras,
    /// Left, posterior, superior (DICOM, ITK, LIBR+).
    Lps,
}

impl Frame {
    /// Converts a point or vector between this frame and LPS (its own inverse).
    pub fn convert(self, p: [f64; 3]) -> [f64; 3] {
        match self {
            Frame::Ras => [-p[0], -p[1], p[2]],
            Frame::Lps => p,
        }
    }
}

/// A named target in the preoperative image frame (LPS, mm).
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    /// Its label.
    pub name: String,
    /// Position, image frame, LPS, mm.
    pub image_mm: [f64; 3],
}

/// What the bridge does.
#[derive(Debug, Clone)]
pub struct BridgeConfig {
    /// The gRPC server's URL.
    pub server: String,
    /// Its TLS settings.
    pub tls: librplus_client::Tls,
    /// Bearer token for the gRPC server.
    pub token: Option<String>,
    /// The case every session registers.
    pub case_id: String,
    /// The method asked for.
    pub method: pb::Method,
    /// Time budget per registration, ms (0: the server's default).
    pub time_budget_ms: u32,
    /// The peer's patient frame.
    pub frame: Frame,
    /// Targets to send back where each registration puts them.
    pub targets: Vec<Target>,
    /// Largest OpenIGTLink body accepted (bytes).
    pub max_body: u64,
    /// Most OpenIGTLink connections served at once (each holds at most one gRPC session); more
    /// are answered with `STATUS` 6 (busy) and closed. At least 1; keep it below the server's
    /// `max_sessions` so that the bridge cannot take every slot (`--max-sessions`, default
    /// [`DEFAULT_MAX_SESSIONS`]).
    pub max_sessions: usize,
    /// A connection with no session yet (no `POINT` or `POLYDATA` received) that sends no
    /// complete message for this long is sent `STATUS` 7 (time-out) and closed
    /// (`--idle-timeout-s`, default [`DEFAULT_IDLE_TIMEOUT_S`]).
    pub idle_timeout: Duration,
    /// The same once its session is open (`--session-idle-timeout-s`, default
    /// [`DEFAULT_SESSION_IDLE_TIMEOUT_S`], the server's own `session_idle_timeout_s`).
    pub session_idle_timeout: Duration,
}

/// Default of [`BridgeConfig::max_sessions`]: half the server's default `max_sessions` (8).
pub const DEFAULT_MAX_SESSIONS: usize = 4;
/// Default of [`BridgeConfig::idle_timeout`], s.
pub const DEFAULT_IDLE_TIMEOUT_S: f64 = 30.0;
/// Default of [`BridgeConfig::session_idle_timeout`], s.
pub const DEFAULT_SESSION_IDLE_TIMEOUT_S: f64 = 600.0;

/// How long the gRPC server has to answer a session's opening.
const OPEN_TIMEOUT: Duration = Duration::from_secs(30);
/// How long the peer has to take one message sent to it before its connection is closed.
const WRITE_TIMEOUT: Duration = Duration::from_secs(30);
/// How long a closing connection waits for the gRPC session's last answers.
const CLOSE_GRACE: Duration = Duration::from_secs(30);
/// How often a refused connection is logged at most (the count since is in the line).
const REFUSAL_LOG_EVERY: Duration = Duration::from_secs(10);

/// A timeout option in seconds as a [`Duration`]: finite and positive, else an error naming
/// `flag` (for example `--idle-timeout-s`).
pub fn timeout_of(flag: &str, seconds: f64) -> anyhow::Result<Duration> {
    if !(seconds.is_finite() && seconds > 0.0) {
        anyhow::bail!("{flag} {seconds}: a positive number of seconds");
    }
    Duration::try_from_secs_f64(seconds).map_err(|e| anyhow::anyhow!("{flag} {seconds}: {e}"))
}

/// Reads targets from a 3D Slicer markups file (`.mrk.json`, schema 1.0: `markups[].
/// controlPoints[].{label, position}` with `markups[].coordinateSystem` `LPS` or `RAS`, which
/// Slicer writes) into the image frame (LPS).
pub fn read_targets(path: &std::path::Path) -> anyhow::Result<Vec<Target>> {
    use anyhow::Context;
    let text =
        std::fs::read_to_string(path).with_context(|| format!("--targets {}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("--targets {}: not JSON", path.display()))?;
    let bad = |what: String| anyhow::anyhow!("--targets {}: {what}", path.display());
    let markups = v["markups"]
        .as_array()
        .ok_or_else(|| bad("no `markups` array (a 3D Slicer .mrk.json)".into()))?;
    let mut out = Vec::new();
    for (m, mk) in markups.iter().enumerate() {
        let frame = match mk["coordinateSystem"].as_str().unwrap_or("LPS") {
            "LPS" => Frame::Lps,
            "RAS" => Frame::Ras,
            other => {
                return Err(bad(format!(
                    "markups[{m}].coordinateSystem {other:?} is neither LPS nor RAS"
                )));
            }
        };
        for (k, cp) in mk["controlPoints"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or_default()
            .iter()
            .enumerate()
        {
            let field = format!("markups[{m}].controlPoints[{k}]");
            let p: Vec<f64> = cp["position"]
                .as_array()
                .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect())
                .unwrap_or_default();
            if p.len() != 3 || p.iter().any(|x| !x.is_finite()) {
                return Err(bad(format!("{field}.position is not 3 finite numbers")));
            }
            out.push(Target {
                name: cp["label"]
                    .as_str()
                    .map_or_else(|| format!("target-{}", out.len() + 1), str::to_string),
                image_mm: frame.convert([p[0], p[1], p[2]]),
            });
        }
    }
    Ok(out)
}

/// The case as the bridge needs it: nodes, the boundary surface and the targets' embedding.
struct CaseGeometry {
    nodes: Vec<[f64; 3]>,
    /// Boundary nodes (indices into `nodes`) and triangles over them (local indices).
    surface_nodes: Vec<u32>,
    surface_triangles: Vec<[u32; 3]>,
    targets: Vec<Embedded>,
}

/// A target embedded in the mesh: its name, image position, and the nodes and barycentric
/// weights of the tet it is in (or nearest to).
struct Embedded {
    name: String,
    image_mm: [f64; 3],
    nodes: [u32; 4],
    weights: [f64; 4],
}

impl CaseGeometry {
    fn new(d: &pb::DescribeCaseResponse, targets: &[Target]) -> anyhow::Result<Self> {
        let nodes: Vec<[f64; 3]> = d
            .nodes_mm
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let tets: Vec<[u32; 4]> = d
            .tets
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect();
        let mesh = TetMesh::new(nodes.clone(), tets)
            .map_err(|e| anyhow::anyhow!("the case's mesh from DescribeCase: {e}"))?;
        let b = mesh
            .boundary()
            .map_err(|e| anyhow::anyhow!("the case's boundary surface: {e}"))?;
        let mut local = vec![u32::MAX; nodes.len()];
        for (k, &n) in b.nodes.iter().enumerate() {
            local[n as usize] = k as u32;
        }
        let surface_triangles = b
            .triangles
            .iter()
            .map(|t| t.map(|n| local[n as usize]))
            .collect();
        let locator = TetLocator::new(&mesh);
        let targets = targets
            .iter()
            .map(|t| {
                let (tet, w) = locator.weights(t.image_mm).ok_or_else(|| {
                    anyhow::anyhow!("target {:?}: no tet of the case near it", t.name)
                })?;
                Ok(Embedded {
                    name: t.name.clone(),
                    image_mm: t.image_mm,
                    nodes: locator.tet(tet),
                    weights: w,
                })
            })
            .collect::<anyhow::Result<_>>()?;
        Ok(Self {
            nodes,
            surface_nodes: b.nodes,
            surface_triangles,
            targets,
        })
    }
}

/// Runs the bridge on `listener` until the process ends: describes the case once, then serves
/// every OpenIGTLink connection (at most [`BridgeConfig::max_sessions`] at once) as its own
/// registration session.
pub async fn serve(listener: TcpListener, cfg: BridgeConfig) -> anyhow::Result<()> {
    if cfg.max_sessions == 0 {
        anyhow::bail!("--max-sessions 0: at least 1 (the most OpenIGTLink connections served)");
    }
    for (flag, t) in [
        ("--idle-timeout-s", cfg.idle_timeout),
        ("--session-idle-timeout-s", cfg.session_idle_timeout),
    ] {
        if t.is_zero() {
            anyhow::bail!("{flag} 0: a positive number of seconds");
        }
    }
    let client = librplus_client::connect_with(&cfg.server, &cfg.tls).await?;
    let session_cfg = librplus_client::SessionConfig::new(
        std::time::Duration::from_secs(60),
        cfg.token.as_deref(),
    )?;
    let mut req = tonic::Request::new(pb::DescribeCaseRequest {
        case_id: cfg.case_id.clone(),
        include_mesh: true,
    });
    if let Some(t) = &session_cfg.token {
        req.metadata_mut().insert("authorization", t.clone());
    }
    let described = client
        .clone()
        .describe_case(req)
        .await
        .map_err(|s| anyhow::anyhow!("DescribeCase {:?}: {}", cfg.case_id, s.message()))?
        .into_inner();
    let geo = Arc::new(CaseGeometry::new(&described, &cfg.targets)?);
    let cfg = Arc::new(cfg);
    let token = session_cfg.token.clone();
    tracing::info!(
        listen = %listener.local_addr()?,
        case = %cfg.case_id,
        nodes = geo.nodes.len(),
        targets = geo.targets.len(),
        max_sessions = cfg.max_sessions,
        idle_timeout_s = cfg.idle_timeout.as_secs_f64(),
        session_idle_timeout_s = cfg.session_idle_timeout.as_secs_f64(),
        "OpenIGTLink bridge ready"
    );
    let slots = Arc::new(Semaphore::new(cfg.max_sessions));
    let mut next_id = 1u64;
    // Refused connections since the last line about them (logged at most every
    // REFUSAL_LOG_EVERY, so a flood of connections does not flood the log).
    let (mut refused, mut refusal_logged) = (0u64, None::<Instant>);
    loop {
        let (socket, peer) = match listener.accept().await {
            Ok(x) => x,
            Err(e) => {
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                continue;
            }
        };
        let id = next_id;
        next_id += 1;
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            refused += 1;
            if refusal_logged.is_none_or(|t| t.elapsed() >= REFUSAL_LOG_EVERY) {
                tracing::warn!(
                    connection = id,
                    %peer,
                    max_sessions = cfg.max_sessions,
                    refused,
                    "OpenIGTLink connection refused: the bridge already serves --max-sessions connections (refused: since the last such line)"
                );
                (refused, refusal_logged) = (0, Some(Instant::now()));
            }
            let busy = status(
                status_code::BUSY,
                "BUSY",
                &format!(
                    "the LIBR+ bridge already serves its {} connections (--max-sessions); try again later",
                    cfg.max_sessions
                ),
            );
            tokio::spawn(async move {
                let mut socket = socket;
                let _ = tokio::time::timeout(Duration::from_secs(2), async {
                    socket.write_all(&busy).await?;
                    socket.shutdown().await
                })
                .await;
            });
            continue;
        };
        let (client, cfg, geo, token) = (client.clone(), cfg.clone(), geo.clone(), token.clone());
        tokio::spawn(
            async move {
                tracing::info!(%peer, "OpenIGTLink peer connected");
                match connection(socket, client, &cfg, &geo, token).await {
                    Ok(()) => tracing::info!("OpenIGTLink peer left"),
                    Err(e) => tracing::warn!(error = %e, "connection ended"),
                }
                drop(slot);
            }
            .instrument(tracing::info_span!("igtl", connection = id)),
        );
    }
}

/// An encoded STATUS message (never fails: the texts are cut to their fields' sizes).
fn status(code: u16, name: &str, message: &str) -> Vec<u8> {
    let s = Status {
        code,
        subcode: 0,
        error_name: name.chars().take(20).collect(),
        message: message.replace('\0', " "),
    };
    Message::Status(s)
        .encode(DEVICE_STATUS, &EncodeOptions::default())
        .unwrap_or_default()
}

/// A gRPC status as an encoded STATUS: its code mapped, its name, `what: message`.
fn grpc_status(s: &tonic::Status, what: &str) -> Vec<u8> {
    let code = librplus_client::code_name(s.code());
    status(
        status_code_of(code),
        code,
        &format!("{what}: {}", s.message()),
    )
}

/// The OpenIGTLink status code for a gRPC status code name.
fn status_code_of(code: &str) -> u16 {
    match code {
        "NOT_FOUND" => status_code::NOT_FOUND,
        "PERMISSION_DENIED" | "UNAUTHENTICATED" => status_code::ACCESS_DENIED,
        "RESOURCE_EXHAUSTED" => status_code::BUSY,
        "DEADLINE_EXCEEDED" => status_code::TIME_OUT,
        "UNAVAILABLE" => status_code::NOT_READY,
        "INVALID_ARGUMENT" | "FAILED_PRECONDITION" | "OUT_OF_RANGE" => status_code::CONFIG_ERROR,
        _ => status_code::UNKNOWN_ERROR,
    }
}

/// The gRPC side of a connection, opened by its first message that carries data.
struct Session {
    /// Requests to the gRPC stream (its SessionStart already sent).
    requests: mpsc::Sender<pb::StreamRegisterRequest>,
    /// Forwards the gRPC answers to the peer; ends with the gRPC stream (with the reason when it
    /// ended with an error).
    answers: tokio::task::JoinHandle<Option<String>>,
    /// Whether `answers` has ended (and was awaited).
    ended: bool,
}

/// Opens the connection's gRPC session: sends its SessionStart and starts forwarding the
/// answers to `out_tx`.
async fn open_session(
    client: &librplus_client::Client,
    cfg: &BridgeConfig,
    geo: &Arc<CaseGeometry>,
    token: Option<&tonic::metadata::AsciiMetadataValue>,
    out_tx: &mpsc::Sender<Vec<u8>>,
) -> Result<Session, tonic::Status> {
    let (req_tx, req_rx) = mpsc::channel::<pb::StreamRegisterRequest>(64);
    let start = pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(pb::stream_register_request::Msg::Start(pb::SessionStart {
            case_id: cfg.case_id.clone(),
            method: cfg.method as i32,
            options: Some(pb::RegisterOptions {
                time_budget_ms: cfg.time_budget_ms,
                ..Default::default()
            }),
            ..Default::default()
        })),
    };
    req_tx.send(start).await.ok();
    let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(req_rx));
    if let Some(t) = token {
        req.metadata_mut().insert("authorization", t.clone());
    }
    let mut updates =
        match tokio::time::timeout(OPEN_TIMEOUT, client.clone().stream_register(req)).await {
            Ok(r) => r?.into_inner(),
            Err(_) => {
                return Err(tonic::Status::deadline_exceeded(format!(
                    "the LIBR+ server did not answer StreamRegister within {} s",
                    OPEN_TIMEOUT.as_secs()
                )));
            }
        };
    // gRPC answers → OpenIGTLink messages.
    let (out_tx, geo, frame) = (out_tx.clone(), geo.clone(), cfg.frame);
    let answers = tokio::spawn(
        async move {
            loop {
                match updates.message().await {
                    Ok(Some(u)) => {
                        for bytes in answer_messages(&u, &geo, frame) {
                            if out_tx.send(bytes).await.is_err() {
                                return Some("the peer's socket is closed".into());
                            }
                        }
                    }
                    Ok(None) => return None,
                    Err(s) => {
                        let code = librplus_client::code_name(s.code());
                        tracing::warn!(code, message = s.message(), "the gRPC session ended");
                        out_tx
                            .send(grpc_status(&s, "the LIBR+ session ended"))
                            .await
                            .ok();
                        return Some(format!("the gRPC session ended: {code}: {}", s.message()));
                    }
                }
            }
        }
        .in_current_span(),
    );
    Ok(Session {
        requests: req_tx,
        answers,
        ended: false,
    })
}

/// What ended a wait of [`connection`]'s loop.
enum Event {
    /// The socket read (bytes, or the end of the peer's stream).
    Read(std::io::Result<usize>),
    /// No complete message for the idle timeout in force.
    Idle,
    /// The writer stopped: the peer did not take a message in time, or the socket failed.
    WriterEnded(Result<Result<(), String>, tokio::task::JoinError>),
    /// The gRPC session ended (the reason when it was an error).
    SessionEnded(Option<String>),
}

/// One OpenIGTLink connection: at most one gRPC session, opened by its first message that
/// carries data; closed when it stays silent past its idle timeout or when the gRPC session ends.
async fn connection(
    socket: TcpStream,
    client: librplus_client::Client,
    cfg: &BridgeConfig,
    geo: &Arc<CaseGeometry>,
    token: Option<tonic::metadata::AsciiMetadataValue>,
) -> anyhow::Result<()> {
    let (mut rd, mut wr) = socket.into_split();
    let (out_tx, mut out_rx) = mpsc::channel::<Vec<u8>>(64);
    let opened = Instant::now();
    // When the last message to the peer was written, ms after `opened`.
    let last_sent_ms = Arc::new(AtomicU64::new(0));
    let sent = last_sent_ms.clone();
    let mut writer = tokio::spawn(async move {
        while let Some(bytes) = out_rx.recv().await {
            match tokio::time::timeout(WRITE_TIMEOUT, wr.write_all(&bytes)).await {
                Ok(Ok(())) => sent.store(
                    u64::try_from(opened.elapsed().as_millis()).unwrap_or(u64::MAX),
                    Ordering::Relaxed,
                ),
                Ok(Err(e)) => return Err(format!("writing the socket: {e}")),
                Err(_) => {
                    return Err(format!(
                        "the peer took no message for {} s",
                        WRITE_TIMEOUT.as_secs()
                    ));
                }
            }
        }
        let _ = tokio::time::timeout(Duration::from_secs(2), wr.shutdown()).await;
        Ok(())
    });
    let mut writer_ended = false;
    let mut session: Option<Session> = None;
    // OpenIGTLink messages → gRPC requests.
    let mut decoder = Decoder::with_max_body_size(cfg.max_body);
    let mut poses: std::collections::HashMap<String, Rigid> = Default::default();
    let mut seq = 1u64;
    let mut buf = vec![0u8; 64 * 1024];
    // When the last complete message (well-formed or not) arrived: partial bytes do not count,
    // so a peer trickling a message byte by byte is idle too. The idle timeout runs from it or
    // from the last message sent to the peer, whichever is later (a registration being computed
    // is not silence).
    let mut last_message = opened;
    let result = 'read: loop {
        let (limit, flag) = if session.is_some() {
            (cfg.session_idle_timeout, "--session-idle-timeout-s")
        } else {
            (cfg.idle_timeout, "--idle-timeout-s")
        };
        let last_sent = opened + Duration::from_millis(last_sent_ms.load(Ordering::Relaxed));
        let event = tokio::select! {
            r = rd.read(&mut buf) => Event::Read(r),
            () = tokio::time::sleep_until(last_message.max(last_sent) + limit) => Event::Idle,
            r = &mut writer, if !writer_ended => Event::WriterEnded(r),
            r = async {
                match session.as_mut() {
                    Some(s) if !s.ended => (&mut s.answers).await.unwrap_or(None),
                    _ => std::future::pending().await,
                }
            } => Event::SessionEnded(r),
        };
        let n = match event {
            Event::Read(Ok(0)) => break Ok(()),
            Event::Read(Ok(n)) => n,
            Event::Read(Err(e)) => break Err(anyhow::anyhow!("reading the socket: {e}")),
            // A message was sent to the peer meanwhile: wait on from it.
            Event::Idle
                if Instant::now()
                    < opened
                        + Duration::from_millis(last_sent_ms.load(Ordering::Relaxed))
                        + limit =>
            {
                continue;
            }
            Event::Idle => {
                let why = format!(
                    "no OpenIGTLink message from the peer, nor to it, for {} s ({flag}; {}): connection closed",
                    limit.as_secs_f64(),
                    if session.is_some() {
                        "session open"
                    } else {
                        "no POINT or POLYDATA yet, so no session"
                    }
                );
                tracing::warn!("{why}");
                // Never waits: a peer that does not read gets no STATUS.
                out_tx
                    .try_send(status(status_code::TIME_OUT, "IDLE_TIMEOUT", &why))
                    .ok();
                break Err(anyhow::anyhow!(why));
            }
            Event::WriterEnded(r) => {
                writer_ended = true;
                let why = match r {
                    Ok(Ok(())) => "the writer ended".to_string(),
                    Ok(Err(why)) => why,
                    Err(e) => format!("the writer failed: {e}"),
                };
                break Err(anyhow::anyhow!("{why}; connection closed"));
            }
            Event::SessionEnded(why) => {
                if let Some(s) = session.as_mut() {
                    s.ended = true;
                }
                break match why {
                    Some(why) => Err(anyhow::anyhow!("{why}; connection closed")),
                    None => Err(anyhow::anyhow!(
                        "the LIBR+ server ended the session; connection closed"
                    )),
                };
            }
        };
        decoder.feed(&buf[..n]);
        while let Some(next) = decoder.next_message() {
            last_message = Instant::now();
            match next {
                Ok((header, msg)) => match request_of(&header, msg, cfg.frame, &mut poses) {
                    Ok(Some(m)) => {
                        if session.is_none() {
                            match open_session(&client, cfg, geo, token.as_ref(), &out_tx).await {
                                Ok(s) => {
                                    tracing::info!(
                                        kind = %header.type_name,
                                        device = %header.device_name,
                                        "first data message: gRPC session opened"
                                    );
                                    session = Some(s);
                                }
                                Err(s) => {
                                    out_tx
                                        .send(grpc_status(
                                            &s,
                                            "the LIBR+ server refused the session",
                                        ))
                                        .await
                                        .ok();
                                    break 'read Err(anyhow::anyhow!(
                                        "StreamRegister refused: {}: {}",
                                        librplus_client::code_name(s.code()),
                                        s.message()
                                    ));
                                }
                            }
                        }
                        let Some(s) = session.as_ref() else {
                            break 'read Err(anyhow::anyhow!("no gRPC session"));
                        };
                        seq += 1;
                        let r = pb::StreamRegisterRequest {
                            client_seq: seq,
                            msg: Some(m),
                        };
                        if s.requests.send(r).await.is_err() {
                            break 'read Err(anyhow::anyhow!("the gRPC session has ended"));
                        }
                    }
                    Ok(None) => {}
                    Err((code, why)) => {
                        tracing::warn!(
                            device = %header.device_name,
                            kind = %header.type_name,
                            "{why}"
                        );
                        out_tx.send(status(code, "BAD_MESSAGE", &why)).await.ok();
                    }
                },
                Err(e) => {
                    let recoverable = e.is_recoverable();
                    tracing::warn!(error = %e, recoverable, "malformed OpenIGTLink message");
                    let code = match e {
                        wire::WireError::BadCrc { .. } => status_code::CHECKSUM_ERROR,
                        _ => status_code::CONFIG_ERROR,
                    };
                    out_tx
                        .send(status(code, "BAD_MESSAGE", &e.to_string()))
                        .await
                        .ok();
                    if !recoverable {
                        break 'read Err(anyhow::anyhow!("unrecoverable stream error: {e}"));
                    }
                }
            }
        }
    };
    // Close the gRPC side, let the last answers through, then the socket.
    if let Some(Session {
        requests,
        mut answers,
        ended,
    }) = session
    {
        drop(requests);
        if !ended
            && tokio::time::timeout(CLOSE_GRACE, &mut answers)
                .await
                .is_err()
        {
            answers.abort();
        }
    }
    drop(out_tx);
    if !writer_ended
        && tokio::time::timeout(WRITE_TIMEOUT, &mut writer)
            .await
            .is_err()
    {
        writer.abort();
    }
    result
}

/// The gRPC request for one OpenIGTLink message (None: a pose, stored for the next POLYDATA of
/// its device), or the STATUS code and reason it is refused with.
fn request_of(
    header: &wire::Header,
    msg: Message,
    frame: Frame,
    poses: &mut std::collections::HashMap<String, Rigid>,
) -> Result<Option<pb::stream_register_request::Msg>, (u16, String)> {
    use pb::stream_register_request::Msg;
    let acquired_at = Some(acquired_at(header));
    let device = &header.device_name;
    match msg {
        Message::Point(points) => {
            if points.is_empty() {
                return Err((status_code::CONFIG_ERROR, "POINT: no points".into()));
            }
            Ok(Some(Msg::Surface(pb::SurfaceBatch {
                acquired_at,
                xyz_mm: points
                    .iter()
                    .flat_map(|p| frame.convert(p.position_mm.map(f64::from)))
                    .collect(),
                feature: Vec::new(),
            })))
        }
        Message::Transform(t) => {
            let pose = rigid_of(&t).map_err(|why| {
                (
                    status_code::CONFIG_ERROR,
                    format!("TRANSFORM {device:?}: {why}"),
                )
            })?;
            // Plane → peer frame, then peer frame → LPS.
            poses.insert(device.clone(), pose.then(&frame_rigid(frame)));
            Ok(None)
        }
        Message::PolyData(pd) => {
            let pose = poses.get(device).ok_or_else(|| {
                (
                    status_code::CONFIG_ERROR,
                    format!(
                        "POLYDATA {device:?}: no TRANSFORM {device:?} (the plane's pose) received before it"
                    ),
                )
            })?;
            let kind = pd
                .attributes
                .iter()
                .find(|a| a.name == "kind" && a.location == AttributeLocation::Point);
            if let Some(k) = kind
                && (k.kind.components() != 1 || k.tuple_count() != pd.points.len())
            {
                return Err((
                    status_code::CONFIG_ERROR,
                    format!(
                        "POLYDATA {device:?}: attribute `kind` needs one scalar per point ({} points)",
                        pd.points.len()
                    ),
                ));
            }
            let (mut contour, mut vessel) = (Vec::new(), Vec::new());
            for (i, p) in pd.points.iter().enumerate() {
                if f64::from(p[2]).abs() > 0.5 {
                    return Err((
                        status_code::CONFIG_ERROR,
                        format!(
                            "POLYDATA {device:?}: point {i} has w = {} mm: points are (u, v, 0) in the plane's own frame",
                            p[2]
                        ),
                    ));
                }
                let uv = [f64::from(p[0]), f64::from(p[1])];
                let k = kind.map_or(0.0, |k| k.data[i]);
                if k == 0.0 {
                    contour.extend(uv);
                } else if k == 1.0 {
                    vessel.extend(uv);
                } else {
                    return Err((
                        status_code::CONFIG_ERROR,
                        format!(
                            "POLYDATA {device:?}: kind of point {i} is {k}: 0 (contour) or 1 (vessel)"
                        ),
                    ));
                }
            }
            Ok(Some(Msg::Ultrasound(pb::UltrasoundPlane {
                acquired_at,
                plane_to_physical: Some(librplus_client::rigid_message(pose)),
                contour_uv_mm: contour,
                vessel_uv_mm: vessel,
            })))
        }
        Message::Status(_) => Ok(None),
        Message::Unknown { type_name, .. } => Err((
            status_code::ILLEGAL_INSTRUCTION,
            format!(
                "{type_name:?} messages are not used by LIBR+ (POINT, TRANSFORM and POLYDATA are)"
            ),
        )),
    }
}

/// The header's timestamp, or now when it is 0 (unused).
fn acquired_at(h: &wire::Header) -> prost_types::Timestamp {
    let secs = if h.timestamp == 0 {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64())
    } else {
        h.timestamp_secs()
    };
    prost_types::Timestamp {
        seconds: secs.floor() as i64,
        nanos: ((secs - secs.floor()) * 1e9).round().min(999_999_999.0) as i32,
    }
}

/// The frame change as a rigid transform (a rotation by 180° about z for RAS ↔ LPS).
fn frame_rigid(frame: Frame) -> Rigid {
    let mut r = Rigid::identity();
    if frame == Frame::Ras {
        r.rotation[0][0] = -1.0;
        r.rotation[1][1] = -1.0;
    }
    r
}

/// A received TRANSFORM as a rigid transform: its rotation re-orthonormalised (the wire's
/// float32 rounding), refused when it is not a rotation to 1e-3.
fn rigid_of(t: &Transform) -> Result<Rigid, String> {
    let m = &t.matrix;
    let col = |j: usize| [m[0][j], m[1][j], m[2][j]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (a, b, c) = (col(0), col(1), col(2));
    let err = [
        (dot(a, a) - 1.0).abs(),
        (dot(b, b) - 1.0).abs(),
        (dot(c, c) - 1.0).abs(),
        dot(a, b).abs(),
        dot(a, c).abs(),
        dot(b, c).abs(),
    ]
    .into_iter()
    .fold(0.0, f64::max);
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    if err.is_nan() || err > 1e-3 || dot(cross(a, b), c) <= 0.0 {
        return Err(
            "the rotation part is not a rotation (orthonormal, determinant +1, to 1e-3)".into(),
        );
    }
    let norm = |v: [f64; 3]| {
        let n = dot(v, v).sqrt();
        v.map(|x| x / n)
    };
    let u = norm(a);
    let w = norm(cross(u, b));
    let v = cross(w, u);
    Ok(Rigid {
        rotation: [[u[0], v[0], w[0]], [u[1], v[1], w[1]], [u[2], v[2], w[2]]],
        translation: [m[0][3], m[1][3], m[2][3]],
    })
}

/// A rigid transform as an OpenIGTLink TRANSFORM.
fn transform_of(r: &Rigid) -> Transform {
    let mut m = Transform::IDENTITY.matrix;
    for (i, row) in m.iter_mut().take(3).enumerate() {
        row[..3].copy_from_slice(&r.rotation[i]);
        row[3] = r.translation[i];
    }
    Transform { matrix: m }
}

/// The OpenIGTLink messages answering one gRPC update.
fn answer_messages(u: &pb::StreamUpdate, geo: &CaseGeometry, frame: Frame) -> Vec<Vec<u8>> {
    use pb::stream_update::Update;
    match &u.update {
        Some(Update::Registration(r)) => match registration_messages(r, geo, frame) {
            Ok(v) => v,
            Err(why) => vec![status(status_code::UNKNOWN_ERROR, "BAD_ANSWER", &why)],
        },
        Some(Update::Rejection(r)) => {
            let detail: Vec<String> = r
                .violations
                .iter()
                .map(|v| format!("{}: {}", v.field, v.description))
                .collect();
            vec![status(
                status_code_of(&r.code),
                &r.code,
                &format!(
                    "message {} rejected: {}{}",
                    r.client_seq,
                    r.message,
                    if detail.is_empty() {
                        String::new()
                    } else {
                        format!(" ({})", detail.join("; "))
                    }
                ),
            )]
        }
        _ => Vec::new(),
    }
}

/// TRANSFORM, target POINT, liver POLYDATA (and a STATUS when the quality is not OK) for one
/// registration.
fn registration_messages(
    r: &pb::Registration,
    geo: &CaseGeometry,
    frame: Frame,
) -> Result<Vec<Vec<u8>>, String> {
    let t = match &r.image_to_physical {
        None => return Err("registration.image_to_physical is unset".into()),
        Some(t) => librplus_client::rigid_from_message(t)
            .map_err(|e| format!("registration.image_to_physical.{e}"))?,
    };
    let n = geo.nodes.len();
    let u: Vec<f64> = if r.displacement_mm.len() == 3 * n {
        r.displacement_mm.iter().map(|&x| f64::from(x)).collect()
    } else if r.displacement_mm.is_empty() {
        vec![0.0; 3 * n]
    } else {
        return Err(format!(
            "registration.displacement_mm has {} values for {n} nodes",
            r.displacement_mm.len()
        ));
    };
    let f = frame_rigid(frame);
    let placed =
        |x: [f64; 3], d: [f64; 3]| frame.convert(t.apply([x[0] + d[0], x[1] + d[1], x[2] + d[2]]));
    let opts = EncodeOptions::default();
    let enc = |m: Message, device: &str| m.encode(device, &opts).map_err(|e| e.to_string());
    let mut out = Vec::with_capacity(4);
    // The quality first when it is not OK; the liver POLYDATA last (it ends an update).
    if r.quality != pb::Quality::Ok as i32 {
        let q = pb::Quality::try_from(r.quality).map_or_else(
            |_| format!("QUALITY_{}", r.quality),
            |q| q.as_str_name().to_string(),
        );
        out.push(status(
            status_code::OK,
            q.trim_start_matches("QUALITY_"),
            &r.quality_reason,
        ));
    }
    // Image (peer frame) → physical (peer frame).
    out.push(enc(
        Message::Transform(transform_of(&f.then(&t).then(&f))),
        DEVICE_TRANSFORM,
    )?);
    if !geo.targets.is_empty() {
        let points = geo
            .targets
            .iter()
            .map(|e| {
                let mut d = [0.0; 3];
                for (&node, &w) in e.nodes.iter().zip(&e.weights) {
                    for (a, da) in d.iter_mut().enumerate() {
                        *da += w * u[3 * node as usize + a];
                    }
                }
                PointElement {
                    name: e.name.chars().take(64).collect(),
                    group: "Target".into(),
                    rgba: [255, 64, 64, 255],
                    position_mm: placed(e.image_mm, d).map(|c| c as f32),
                    diameter_mm: 5.0,
                    owner: String::new(),
                }
            })
            .collect();
        out.push(enc(Message::Point(points), DEVICE_TARGETS)?);
    }
    let mut points = Vec::with_capacity(geo.surface_nodes.len());
    let mut displacement = Vec::with_capacity(3 * geo.surface_nodes.len());
    for &i in &geo.surface_nodes {
        let i = i as usize;
        let d = [u[3 * i], u[3 * i + 1], u[3 * i + 2]];
        points.push(placed(geo.nodes[i], d).map(|c| c as f32));
        // The node's deformation in the peer's physical frame: F R u.
        displacement.extend(frame.convert(t.apply_vector(d)).map(|c| c as f32));
    }
    let mut attributes = vec![PolyAttribute {
        name: "displacement".into(),
        location: AttributeLocation::Point,
        kind: AttributeKind::Vector,
        data: displacement,
    }];
    // The error estimate's per-node bound, when the server sent one for every node.
    if let Some(e) = r
        .error_estimate
        .as_ref()
        .filter(|e| e.node_uncertainty_mm.len() == n)
    {
        attributes.push(PolyAttribute {
            name: "uncertainty_mm".into(),
            location: AttributeLocation::Point,
            kind: AttributeKind::Scalar { components: 1 },
            data: geo
                .surface_nodes
                .iter()
                .map(|&i| e.node_uncertainty_mm[i as usize])
                .collect(),
        });
    }
    let liver = PolyData {
        points,
        polygons: CellArray::from_cells(geo.surface_triangles.iter().map(|t| t.to_vec())),
        attributes,
        ..PolyData::default()
    };
    out.push(enc(Message::PolyData(liver), DEVICE_LIVER)?);
    Ok(out)
}

/// Binds `addr` and runs [`serve`].
pub async fn run(addr: SocketAddr, cfg: BridgeConfig) -> anyhow::Result<()> {
    let listener = TcpListener::bind(addr)
        .await
        .map_err(|e| anyhow::anyhow!("--listen {addr}: {e}"))?;
    serve(listener, cfg).await
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_default_below_the_server_and_timeouts_are_checked() {
        // The bridge alone cannot take every session slot of a server with default settings.
        let server = crate::config::ServerConfig::default();
        assert!(DEFAULT_MAX_SESSIONS >= 1 && DEFAULT_MAX_SESSIONS < server.max_sessions);
        assert_eq!(
            DEFAULT_SESSION_IDLE_TIMEOUT_S,
            server.session_idle_timeout_s
        );
        assert_eq!(
            timeout_of("--idle-timeout-s", 1.5).unwrap(),
            Duration::from_millis(1500)
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e300] {
            let e = timeout_of("--idle-timeout-s", bad).unwrap_err().to_string();
            assert!(e.starts_with("--idle-timeout-s "), "{e}");
        }
    }

    #[test]
    fn frames_convert_and_transforms_round_trip() {
        assert_eq!(Frame::Ras.convert([1.0, 2.0, 3.0]), [-1.0, -2.0, 3.0]);
        assert_eq!(Frame::Lps.convert([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0]);
        // A rotation about an oblique axis, through the wire's float32 and back.
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let r = Rigid {
            rotation: [
                [c, -s, 0.0],
                [s * 0.6, c * 0.6, -0.8],
                [s * 0.8, c * 0.8, 0.6],
            ],
            translation: [10.0, -20.5, 300.25],
        };
        let t = Transform::from_wire(&transform_of(&r).to_wire().unwrap());
        let back = rigid_of(&t).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                assert!((back.rotation[i][j] - r.rotation[i][j]).abs() < 1e-6);
            }
            assert!((back.translation[i] - r.translation[i]).abs() < 1e-4);
        }
        // Not a rotation: a scaling, a reflection.
        let mut scaled = transform_of(&r);
        scaled.matrix[0][0] *= 1.1;
        assert!(rigid_of(&scaled).is_err());
        let mut reflected = transform_of(&Rigid::identity());
        reflected.matrix[2][2] = -1.0;
        assert!(rigid_of(&reflected).is_err());
        // F T F in RAS equals T applied to converted points.
        let f = frame_rigid(Frame::Ras);
        let p = [3.0, -4.0, 5.0];
        let a = f.then(&r).then(&f).apply(Frame::Ras.convert(p));
        let b = Frame::Ras.convert(r.apply(p));
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-12);
        }
    }
}
