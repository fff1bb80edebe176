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
//! connection goes on; only a message whose header cannot be trusted ends it, after its `STATUS`:
//! a header version other than 1 or 2, or a `BODY_SIZE` over `--max-body` too large to skip,
//! [`wire::MAX_DISCARDED_BODY_SIZE`]).
//!
//! **Frames.** LIBR+ works in LPS; 3D Slicer's world is RAS. With `--frame ras` (the default)
//! every coordinate received is converted RAS → LPS (x and y negated) and every one sent LPS →
//! RAS, and the image → physical transform is sent as `F T F` (F = diag(−1, −1, 1)): the
//! transform to apply in Slicer to the preoperative model loaded there (Slicer converts LPS files
//! to RAS on loading). A plane pose (plane frame → physical) is converted as `F P`. With
//! `--frame lps` everything passes unchanged.

pub use super::answers::{DEVICE_LIVER, DEVICE_STATUS, DEVICE_TARGETS, DEVICE_TRANSFORM};
use super::answers::{registered_messages, rejection_status, status, status_code_of};
use super::geometry::CaseGeometry;
pub use super::geometry::{Frame, Target, read_targets};
use super::requests::{Poses, request_of};
use super::wire::{self, Decoder, status_code};
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

/// Runs the bridge on `listener` until the process ends: describes the case once, then serves
/// every OpenIGTLink connection (at most [`BridgeConfig::max_sessions`] at once) as its own
/// registration session.
pub async fn serve(listener: TcpListener, cfg: BridgeConfig) -> anyhow::Result<()> {
    check_limits(&cfg)?;
    let shared = Shared::connect(cfg).await?;
    let (cfg, geo) = (&shared.cfg, &shared.geo);
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
    let mut refusals = Refusals::default();
    loop {
        let (socket, peer) = accept(&listener).await;
        let id = next_id;
        next_id += 1;
        match slots.clone().try_acquire_owned() {
            Ok(slot) => shared.spawn_connection(socket, peer, id, slot),
            Err(_) => {
                refusals.note(id, peer, cfg.max_sessions);
                refuse_busy(socket, cfg.max_sessions);
            }
        }
    }
}

/// Checks the limits of `cfg`: at least one session, timeouts above zero.
fn check_limits(cfg: &BridgeConfig) -> anyhow::Result<()> {
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
    Ok(())
}

/// The next connection on `listener`; a failed accept is logged and retried after 100 ms.
async fn accept(listener: &TcpListener) -> (TcpStream, SocketAddr) {
    loop {
        match listener.accept().await {
            Ok(x) => return x,
            Err(e) => {
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
            }
        }
    }
}

/// What every connection of the bridge shares: the gRPC client, the options, the case.
#[derive(Clone)]
struct Shared {
    client: librplus_client::Client,
    cfg: Arc<BridgeConfig>,
    geo: Arc<CaseGeometry>,
    /// The bearer token's metadata value, when there is one.
    token: Option<tonic::metadata::AsciiMetadataValue>,
}

impl Shared {
    /// Connects to the gRPC server and describes the case (with its mesh) once.
    async fn connect(cfg: BridgeConfig) -> anyhow::Result<Self> {
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
        Ok(Self {
            client,
            cfg: Arc::new(cfg),
            geo,
            token: session_cfg.token,
        })
    }

    /// Serves connection `id` from `peer` on its own task, holding `slot` until it ends.
    fn spawn_connection(
        &self,
        socket: TcpStream,
        peer: SocketAddr,
        id: u64,
        slot: tokio::sync::OwnedSemaphorePermit,
    ) {
        let Self {
            client,
            cfg,
            geo,
            token,
        } = self.clone();
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

/// Refused connections since the last line about them (logged at most every
/// [`REFUSAL_LOG_EVERY`], so a flood of connections does not flood the log).
#[derive(Default)]
struct Refusals {
    /// Connections refused since the last line.
    refused: u64,
    /// When the last line was logged.
    logged: Option<Instant>,
}

impl Refusals {
    /// Counts connection `id` from `peer` as refused; logs the count when the last line is old
    /// enough.
    fn note(&mut self, id: u64, peer: SocketAddr, max_sessions: usize) {
        self.refused += 1;
        if self.logged.is_none_or(|t| t.elapsed() >= REFUSAL_LOG_EVERY) {
            tracing::warn!(
                connection = id,
                %peer,
                max_sessions,
                refused = self.refused,
                "OpenIGTLink connection refused: the bridge already serves --max-sessions connections (refused: since the last such line)"
            );
            (self.refused, self.logged) = (0, Some(Instant::now()));
        }
    }
}

/// Answers a connection the bridge has no slot for with `STATUS` 6 (busy) and closes it, on its
/// own task (2 s at most).
fn refuse_busy(socket: TcpStream, max_sessions: usize) {
    let busy = status(
        status_code::BUSY,
        "BUSY",
        &format!(
            "the LIBR+ bridge already serves its {max_sessions} connections (--max-sessions); try again later"
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

/// Why a connection's gRPC session ended early (the text is the connection's log line).
#[derive(Debug, thiserror::Error)]
enum SessionEnd {
    /// The peer's socket closed while answers were being forwarded.
    #[error("the peer's socket is closed")]
    PeerClosed,
    /// The gRPC stream ended with an error status.
    #[error(
        "the gRPC session ended: {}: {}",
        librplus_client::code_name(.0.code()),
        .0.message()
    )]
    Status(#[source] tonic::Status),
}

/// Why a connection's writer stopped early.
#[derive(Debug, thiserror::Error)]
enum WriteError {
    /// Writing to the socket failed.
    #[error("writing the socket: {0}")]
    Socket(#[source] std::io::Error),
    /// The peer took no message within the time allowed.
    #[error("the peer took no message for {} s", .0.as_secs())]
    Stalled(Duration),
}

/// Why a connection was closed when its writer or its gRPC session ended.
#[derive(Debug, thiserror::Error)]
enum Closed {
    /// The writer ended (its channel closed).
    #[error("the writer ended; connection closed")]
    WriterEnded,
    /// The writer stopped early.
    #[error("{0}; connection closed")]
    WriteFailed(#[source] WriteError),
    /// The writer task panicked or was cancelled.
    #[error("the writer failed: {0}; connection closed")]
    WriterPanicked(#[source] tokio::task::JoinError),
    /// The gRPC server ended the session without an error.
    #[error("the LIBR+ server ended the session; connection closed")]
    SessionEnded,
    /// The gRPC session ended early.
    #[error("{0}; connection closed")]
    SessionFailed(#[source] SessionEnd),
}

/// The gRPC side of a connection, opened by its first message that carries data.
struct Session {
    /// Requests to the gRPC stream (its SessionStart already sent).
    requests: mpsc::Sender<pb::StreamRegisterRequest>,
    /// Forwards the gRPC answers to the peer; ends with the gRPC stream (with the reason when it
    /// ended with an error).
    answers: tokio::task::JoinHandle<Option<SessionEnd>>,
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
                                return Some(SessionEnd::PeerClosed);
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
                        return Some(SessionEnd::Status(s));
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
    WriterEnded(Result<Result<(), WriteError>, tokio::task::JoinError>),
    /// The gRPC session ended (the reason when it was an error).
    SessionEnded(Option<SessionEnd>),
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
    let (mut rd, wr) = socket.into_split();
    let (out_tx, out_rx) = mpsc::channel::<Vec<u8>>(64);
    let opened = Instant::now();
    // When the last message to the peer was written, ms after `opened`.
    let last_sent_ms = Arc::new(AtomicU64::new(0));
    let mut writer = spawn_writer(wr, out_rx, opened, last_sent_ms.clone());
    let mut writer_ended = false;
    let mut link = Link::new(client, cfg, geo, token, out_tx);
    // OpenIGTLink messages → gRPC requests.
    let mut decoder = Decoder::with_max_body_size(cfg.max_body);
    let mut buf = vec![0u8; 64 * 1024];
    // When the last complete message (well-formed or not) arrived: partial bytes do not count,
    // so a peer trickling a message byte by byte is idle too. The idle timeout runs from it or
    // from the last message sent to the peer, whichever is later (a registration being computed
    // is not silence).
    let mut last_message = opened;
    let result = loop {
        let (limit, flag) = link.idle_limit();
        let last_sent = opened + Duration::from_millis(last_sent_ms.load(Ordering::Relaxed));
        let event = tokio::select! {
            r = rd.read(&mut buf) => Event::Read(r),
            () = tokio::time::sleep_until(last_message.max(last_sent) + limit) => Event::Idle,
            r = &mut writer, if !writer_ended => Event::WriterEnded(r),
            r = async {
                match link.session.as_mut() {
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
            Event::Idle => break Err(link.idle(limit, flag)),
            Event::WriterEnded(r) => {
                writer_ended = true;
                break Err(writer_end(r));
            }
            Event::SessionEnded(why) => break Err(link.session_ended(why)),
        };
        decoder.feed(&buf[..n]);
        if let Err(e) = link.messages(&mut decoder, &mut last_message).await {
            break Err(e);
        }
    };
    // Close the gRPC side, let the last answers through, then the socket.
    link.close().await;
    if !writer_ended
        && tokio::time::timeout(WRITE_TIMEOUT, &mut writer)
            .await
            .is_err()
    {
        writer.abort();
    }
    result
}

/// Writes what `out_rx` brings to the peer's socket, each message within [`WRITE_TIMEOUT`],
/// noting when the last one was written (`last_sent_ms`, ms after `opened`); shuts the socket
/// down when `out_rx` ends. Err: why it stopped early.
fn spawn_writer(
    mut wr: tokio::net::tcp::OwnedWriteHalf,
    mut out_rx: mpsc::Receiver<Vec<u8>>,
    opened: Instant,
    last_sent_ms: Arc<AtomicU64>,
) -> tokio::task::JoinHandle<Result<(), WriteError>> {
    tokio::spawn(async move {
        while let Some(bytes) = out_rx.recv().await {
            match tokio::time::timeout(WRITE_TIMEOUT, wr.write_all(&bytes)).await {
                Ok(Ok(())) => last_sent_ms.store(
                    u64::try_from(opened.elapsed().as_millis()).unwrap_or(u64::MAX),
                    Ordering::Relaxed,
                ),
                Ok(Err(e)) => return Err(WriteError::Socket(e)),
                Err(_) => return Err(WriteError::Stalled(WRITE_TIMEOUT)),
            }
        }
        let _ = tokio::time::timeout(Duration::from_secs(2), wr.shutdown()).await;
        Ok(())
    })
}

/// Why the connection ends when its writer stopped.
fn writer_end(r: Result<Result<(), WriteError>, tokio::task::JoinError>) -> anyhow::Error {
    anyhow::Error::new(match r {
        Ok(Ok(())) => Closed::WriterEnded,
        Ok(Err(e)) => Closed::WriteFailed(e),
        Err(e) => Closed::WriterPanicked(e),
    })
}

impl Session {
    /// Closes the gRPC side: no more requests; the last answers are let through (for
    /// [`CLOSE_GRACE`] at most).
    async fn close(self) {
        let Session {
            requests,
            mut answers,
            ended,
        } = self;
        drop(requests);
        if !ended
            && tokio::time::timeout(CLOSE_GRACE, &mut answers)
                .await
                .is_err()
        {
            answers.abort();
        }
    }
}

/// A connection's side towards the gRPC server: what it forwards the peer's messages with.
struct Link<'a> {
    client: librplus_client::Client,
    cfg: &'a BridgeConfig,
    geo: &'a Arc<CaseGeometry>,
    token: Option<tonic::metadata::AsciiMetadataValue>,
    /// Messages to the peer (through the writer).
    out_tx: mpsc::Sender<Vec<u8>>,
    /// The gRPC session, once a message that carries data arrived.
    session: Option<Session>,
    /// The last pose of each ultrasound plane (by device), LPS, or why it was refused.
    poses: Poses,
    /// The `client_seq` of the last request sent.
    seq: u64,
}

impl<'a> Link<'a> {
    /// A connection's link, with no session yet: its messages to the peer go to `out_tx`.
    fn new(
        client: librplus_client::Client,
        cfg: &'a BridgeConfig,
        geo: &'a Arc<CaseGeometry>,
        token: Option<tonic::metadata::AsciiMetadataValue>,
        out_tx: mpsc::Sender<Vec<u8>>,
    ) -> Self {
        Self {
            client,
            cfg,
            geo,
            token,
            out_tx,
            session: None,
            poses: Default::default(),
            seq: 1,
        }
    }

    /// Closes the gRPC side (its last answers let through, see [`Session::close`]), then the
    /// way to the writer, so that it ends once it has written what is queued.
    async fn close(self) {
        if let Some(s) = self.session {
            s.close().await;
        }
        drop(self.out_tx);
    }

    /// The idle timeout in force and its option's name: before the session opens, and after.
    fn idle_limit(&self) -> (Duration, &'static str) {
        if self.session.is_some() {
            (self.cfg.session_idle_timeout, "--session-idle-timeout-s")
        } else {
            (self.cfg.idle_timeout, "--idle-timeout-s")
        }
    }

    /// The connection stayed silent for `limit` (option `flag`): logged, the peer sent a STATUS
    /// 7 (never waiting: a peer that does not read gets none); the error that ends it.
    fn idle(&self, limit: Duration, flag: &str) -> anyhow::Error {
        let why = format!(
            "no OpenIGTLink message from the peer, nor to it, for {} s ({flag}; {}): connection closed",
            limit.as_secs_f64(),
            if self.session.is_some() {
                "session open"
            } else {
                "no POINT or POLYDATA yet, so no session"
            }
        );
        tracing::warn!("{why}");
        // Never waits: a peer that does not read gets no STATUS.
        self.out_tx
            .try_send(status(status_code::TIME_OUT, "IDLE_TIMEOUT", &why))
            .ok();
        anyhow::anyhow!(why)
    }

    /// The gRPC session ended (`why`, when with an error): the error that ends the connection.
    fn session_ended(&mut self, why: Option<SessionEnd>) -> anyhow::Error {
        if let Some(s) = self.session.as_mut() {
            s.ended = true;
        }
        anyhow::Error::new(match why {
            Some(why) => Closed::SessionFailed(why),
            None => Closed::SessionEnded,
        })
    }

    /// Handles every complete message `decoder` holds (noting when each arrived in
    /// `last_message`): forwarded, or answered with a STATUS. Err: the connection ends (the
    /// session refused or ended, a stream that cannot be trusted).
    async fn messages(
        &mut self,
        decoder: &mut Decoder,
        last_message: &mut Instant,
    ) -> anyhow::Result<()> {
        while let Some(next) = decoder.next_message() {
            *last_message = Instant::now();
            match next {
                Ok((header, msg)) => {
                    match request_of(&header, msg, self.cfg.frame, &mut self.poses) {
                        Ok(Some(m)) => self.send(&header, m).await?,
                        Ok(None) => {}
                        Err((code, why)) => {
                            tracing::warn!(
                                device = %header.device_name,
                                kind = %header.type_name,
                                "{why}"
                            );
                            self.out_tx
                                .send(status(code, "BAD_MESSAGE", &why))
                                .await
                                .ok();
                        }
                    }
                }
                Err(e) => self.malformed(e).await?,
            }
        }
        Ok(())
    }

    /// Sends one request on the gRPC session, opening the session first (for the first message
    /// that carries data, `header`'s). Err: the session was refused or has ended.
    async fn send(
        &mut self,
        header: &wire::Header,
        m: pb::stream_register_request::Msg,
    ) -> anyhow::Result<()> {
        if self.session.is_none() {
            match open_session(
                &self.client,
                self.cfg,
                self.geo,
                self.token.as_ref(),
                &self.out_tx,
            )
            .await
            {
                Ok(s) => {
                    tracing::info!(
                        kind = %header.type_name,
                        device = %header.device_name,
                        "first data message: gRPC session opened"
                    );
                    self.session = Some(s);
                }
                Err(s) => {
                    self.out_tx
                        .send(grpc_status(&s, "the LIBR+ server refused the session"))
                        .await
                        .ok();
                    anyhow::bail!(
                        "StreamRegister refused: {}: {}",
                        librplus_client::code_name(s.code()),
                        s.message()
                    );
                }
            }
        }
        let Some(s) = self.session.as_ref() else {
            anyhow::bail!("no gRPC session");
        };
        self.seq += 1;
        let r = pb::StreamRegisterRequest {
            client_seq: self.seq,
            msg: Some(m),
        };
        if s.requests.send(r).await.is_err() {
            anyhow::bail!("the gRPC session has ended");
        }
        Ok(())
    }

    /// A malformed message: logged and answered with a STATUS; Err when the stream cannot be
    /// read on (its header cannot be trusted).
    async fn malformed(&self, e: wire::WireError) -> anyhow::Result<()> {
        let recoverable = e.is_recoverable();
        tracing::warn!(error = %e, recoverable, "malformed OpenIGTLink message");
        let code = match e {
            wire::WireError::BadCrc { .. } => status_code::CHECKSUM_ERROR,
            _ => status_code::CONFIG_ERROR,
        };
        let why = if recoverable {
            e.to_string()
        } else {
            format!("{e}; connection closed")
        };
        self.out_tx
            .send(status(code, "BAD_MESSAGE", &why))
            .await
            .ok();
        if !recoverable {
            anyhow::bail!("unrecoverable stream error: {e}");
        }
        Ok(())
    }
}

/// The OpenIGTLink messages answering one gRPC update.
fn answer_messages(u: &pb::StreamUpdate, geo: &CaseGeometry, frame: Frame) -> Vec<Vec<u8>> {
    use pb::stream_update::Update;
    match &u.update {
        Some(Update::Registration(r)) => match registration_messages(r, geo, frame) {
            Ok(v) => v,
            Err(why) => vec![status(
                status_code::UNKNOWN_ERROR,
                "BAD_ANSWER",
                &why.to_string(),
            )],
        },
        Some(Update::Rejection(r)) => vec![rejection_status(r)],
        _ => Vec::new(),
    }
}

/// Why a registration cannot be sent to the peer (its text is the STATUS message sent instead).
#[derive(Debug, thiserror::Error)]
enum AnswerError {
    /// The registration has no transform.
    #[error("registration.image_to_physical is unset")]
    NoTransform,
    /// Its transform is malformed (the field named from the registration).
    #[error("{0}")]
    Transform(#[source] librplus_client::MessageError),
    /// Its displacements do not match the case's nodes.
    #[error("registration.displacement_mm has {values} values for {nodes} nodes")]
    Displacement {
        /// Values received.
        values: usize,
        /// The case's nodes.
        nodes: usize,
    },
    /// An OpenIGTLink message could not be encoded.
    #[error("{0}")]
    Encode(#[source] wire::WireError),
}

/// TRANSFORM, target POINT, liver POLYDATA (and a STATUS when the quality is not OK) for one
/// registration.
fn registration_messages(
    r: &pb::Registration,
    geo: &CaseGeometry,
    frame: Frame,
) -> Result<Vec<Vec<u8>>, AnswerError> {
    let t = match &r.image_to_physical {
        None => return Err(AnswerError::NoTransform),
        Some(t) => librplus_client::rigid_from_message(t)
            .map_err(|e| AnswerError::Transform(e.within("registration.image_to_physical")))?,
    };
    let u = displacements(r, geo.nodes.len())?;
    registered_messages(r, &t, &u, geo, frame).map_err(AnswerError::Encode)
}

/// The registration's node displacements (mm, three per node of the case's `n`; all zero when
/// it sent none).
fn displacements(r: &pb::Registration, n: usize) -> Result<Vec<f64>, AnswerError> {
    if r.displacement_mm.len() == 3 * n {
        Ok(r.displacement_mm.iter().map(|&x| f64::from(x)).collect())
    } else if r.displacement_mm.is_empty() {
        Ok(vec![0.0; 3 * n])
    } else {
        Err(AnswerError::Displacement {
            values: r.displacement_mm.len(),
            nodes: n,
        })
    }
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
}
