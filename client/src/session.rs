//! One streamed session in lockstep: connect, send a message, wait for the update that answers
//! it (the first whose `last_client_seq` reaches the message's `client_seq`), time it, repeat.

use crate::pb;
use crate::pb::lib_r_plus_client::LibRPlusClient;
use crate::stats::code_name;
use anyhow::{Context, Result};
use std::future::Future;
use std::ops::ControlFlow;
use std::time::Duration;
use tokio::time::Instant;
use tonic::metadata::{AsciiMetadataValue, MetadataValue};
use tonic::transport::{Channel, Endpoint};

/// Largest message the clients send or accept (64 MiB).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;

/// A connected client.
pub type Client = LibRPlusClient<Channel>;

/// How the client secures its connection (all unset: plaintext, unless the URL is `https://`).
#[derive(Debug, Clone, Default)]
pub struct Tls {
    /// CA certificate (PEM) the server's certificate must chain to; setting it turns TLS on.
    /// Unset with an `https://` URL: the system's roots are not loaded, so a CA is required.
    pub ca: Option<std::path::PathBuf>,
    /// Client certificate (PEM) for mTLS; with `key`.
    pub cert: Option<std::path::PathBuf>,
    /// Client private key (PEM).
    pub key: Option<std::path::PathBuf>,
    /// Name the server's certificate must carry (default: the URL's host).
    pub domain: Option<String>,
}

impl Tls {
    /// Whether TLS is on for `server`.
    pub fn enabled(&self, server: &str) -> bool {
        self.ca.is_some() || server.starts_with("https://")
    }

    /// tonic's client TLS settings; errors name the option and the file.
    pub fn client_config(&self) -> Result<tonic::transport::ClientTlsConfig> {
        use tonic::transport::{Certificate, ClientTlsConfig, Identity};
        let read = |flag: &str, p: &std::path::Path| {
            std::fs::read(p).with_context(|| format!("{flag} {}: cannot read", p.display()))
        };
        let Some(ca) = &self.ca else {
            anyhow::bail!(
                "--ca: an https:// server needs the CA certificate (PEM) its certificate chains to"
            );
        };
        let mut c = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read("--ca", ca)?));
        match (&self.cert, &self.key) {
            (Some(cert), Some(key)) => {
                c = c.identity(Identity::from_pem(
                    read("--cert", cert)?,
                    read("--key", key)?,
                ));
            }
            (None, None) => {}
            (Some(_), None) => anyhow::bail!("--key: missing (--cert is set; mTLS needs both)"),
            (None, Some(_)) => anyhow::bail!("--cert: missing (--key is set; mTLS needs both)"),
        }
        if let Some(d) = &self.domain {
            c = c.domain_name(d.clone());
        }
        Ok(c)
    }
}

/// Connects to each of `servers` (URLs, comma-separated: replicas of one service), lazily: a
/// replica that is down now is tried again when a session moves to it.
pub fn connect_replicas(servers: &str, tls: &Tls) -> Result<Vec<Client>> {
    servers
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| endpoint(s, tls).map(|(e, _)| client_of(e.connect_lazy())))
        .collect()
}

fn client_of(channel: Channel) -> Client {
    LibRPlusClient::new(channel)
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES)
}

/// The endpoint of `server` with the client's settings (TLS when asked), and its URL.
fn endpoint(server: &str, tls: &Tls) -> Result<(Endpoint, String)> {
    let url = if tls.enabled(server) {
        match server.strip_prefix("http://") {
            Some(rest) => format!("https://{rest}"),
            None => server.to_string(),
        }
    } else {
        server.to_string()
    };
    let mut endpoint = Endpoint::from_shared(url.clone())
        .with_context(|| format!("--server {server:?} is not a valid URL"))?
        .connect_timeout(Duration::from_secs(10))
        .tcp_nodelay(true);
    if tls.enabled(server) {
        endpoint = endpoint
            .tls_config(tls.client_config()?)
            .context("TLS settings (--ca, --cert, --key)")?;
    }
    Ok((endpoint, url))
}

/// Connects to `server` (a URL such as `http://127.0.0.1:50051`) with 64 MiB message limits.
pub async fn connect(server: &str) -> Result<Client> {
    connect_with(server, &Tls::default()).await
}

/// [`connect`] with TLS settings (TLS when `tls.ca` is set or the URL is `https://`; an
/// `http://` URL is then read as `https://`).
pub async fn connect_with(server: &str, tls: &Tls) -> Result<Client> {
    let (endpoint, url) = endpoint(server, tls)?;
    let channel = endpoint
        .connect()
        .await
        .with_context(|| format!("connecting to {url}"))?;
    Ok(client_of(channel))
}

/// How a session runs.
#[derive(Debug, Clone)]
pub struct SessionConfig {
    /// At most this many messages per second (None: as fast as the answers come).
    pub rate_hz: Option<f64>,
    /// Longest wait for the stream to open and for each answer.
    pub timeout: Duration,
    /// Longest wait, once every message is answered, for each update that still follows (a
    /// discovery run's report comes as late as its budget): `timeout` when shorter or unset.
    pub final_timeout: Option<Duration>,
    /// Give up (without counting an error) at this instant: the end of a load test.
    pub deadline: Option<Instant>,
    /// `authorization: Bearer TOKEN` metadata, when set.
    pub token: Option<AsciiMetadataValue>,
    /// Resume a lost stream (None: a lost stream ends the session).
    pub resume: Option<Resume>,
    /// Server replicas (empty: the one client given to [`run_session`]): the session opens on
    /// `replicas[first_replica]` and each resume moves to the next one in turn, so that a
    /// session whose replica went away goes on on another.
    pub replicas: Vec<Client>,
    /// The replica a session opens on (an index into `replicas`).
    pub first_replica: usize,
    /// Sessions sharing this gate send in turn, one per permit: a session holds a permit from
    /// the opening of its stream to its last answer and lets it go while it waits for what
    /// follows (a discovery run's report), so that sessions waiting on their discovery run
    /// beside the others without taking their compute. None: no gate.
    pub lockstep: Option<std::sync::Arc<tokio::sync::Semaphore>>,
}

/// How a client resumes a lost session.
#[derive(Debug, Clone, Copy)]
pub struct Resume {
    /// Most reconnections in a row without an answer in between (a connection that got an
    /// answer starts the count again, so a long session survives any number of separate
    /// outages).
    pub attempts: u32,
    /// The first wait; it doubles on each retry in a row, up to 5 s, and starts again after a
    /// connection that got an answer.
    pub first_backoff: Duration,
    /// Resume also after the session was taken over by another stream (ABORTED, reason
    /// `SESSION_TAKEN_OVER`: another client resumed it). Off by default: two clients resuming
    /// each other's session would take it from each other without end.
    pub take_back: bool,
}

impl Default for Resume {
    fn default() -> Self {
        Self {
            attempts: 10,
            first_backoff: Duration::from_millis(100),
            take_back: false,
        }
    }
}

impl SessionConfig {
    /// No rate limit, the given timeout, no deadline, and a bearer token when given.
    pub fn new(timeout: Duration, token: Option<&str>) -> Result<Self> {
        let token = token
            .map(|t| MetadataValue::try_from(format!("Bearer {t}")))
            .transpose()
            .context("--token must be printable ASCII")?;
        Ok(Self {
            rate_hz: None,
            timeout,
            final_timeout: None,
            deadline: None,
            token,
            resume: None,
            replicas: Vec::new(),
            first_replica: 0,
            lockstep: None,
        })
    }
}

/// How a session ended.
#[derive(Debug, Clone)]
pub enum SessionEnd {
    /// Every message answered and the stream closed with OK.
    Completed,
    /// The stream failed to open or ended with a status before any update (e.g. a bad
    /// SessionStart, or the server refusing the session).
    Refused(tonic::Status),
    /// The stream ended with a non-OK status after some updates.
    Failed(tonic::Status),
    /// The server closed the stream (OK) before answering this `client_seq`.
    ClosedEarly(u64),
    /// No answer to this `client_seq` (0: the stream did not open) within the timeout.
    TimedOut(u64),
    /// Every message was answered, but the server sent nothing more (and did not end the
    /// stream) within this wait: the update still owed after the last answer, a discovery
    /// run's report, never came.
    NothingAfter(u64, Duration),
    /// The deadline passed first (not an error).
    Cut,
}

impl SessionEnd {
    /// The error name a report counts this end under: the gRPC status code name of a refused or
    /// failed session, `DEADLINE_EXCEEDED` for a client-side timeout, `CLOSED_EARLY` for a stream
    /// closed before its last answer; None for a completed or cut session.
    pub fn error_code(&self) -> Option<&'static str> {
        match self {
            SessionEnd::Completed | SessionEnd::Cut => None,
            SessionEnd::Refused(s) | SessionEnd::Failed(s) => Some(code_name(s.code())),
            SessionEnd::ClosedEarly(_) => Some("CLOSED_EARLY"),
            SessionEnd::TimedOut(_) | SessionEnd::NothingAfter(..) => Some("DEADLINE_EXCEEDED"),
        }
    }

    /// Whether every message was answered and the stream closed with OK.
    pub fn is_completed(&self) -> bool {
        matches!(self, SessionEnd::Completed)
    }

    /// A one-line description.
    pub fn describe(&self) -> String {
        match self {
            SessionEnd::Completed => "completed".into(),
            SessionEnd::Refused(s) => format!("refused: {} {}", code_name(s.code()), s.message()),
            SessionEnd::Failed(s) => format!("failed: {} {}", code_name(s.code()), s.message()),
            SessionEnd::ClosedEarly(q) => {
                format!("the server closed the stream before answering client_seq {q}")
            }
            SessionEnd::TimedOut(0) => "the stream did not open in time".into(),
            SessionEnd::TimedOut(q) => format!("no answer to client_seq {q} in time"),
            SessionEnd::NothingAfter(q, wait) => format!(
                "client_seq {q} was answered, then the server sent nothing more and did not end the stream within {:.0} s",
                wait.as_secs_f64()
            ),
            SessionEnd::Cut => "cut at the deadline".into(),
        }
    }
}

/// What a session did.
#[derive(Debug, Clone)]
pub struct SessionOutcome {
    /// Updates received.
    pub updates: u64,
    /// Messages answered (sent and their update received).
    pub answered: u64,
    /// Times the session was resumed after a lost stream.
    pub resumed: u32,
    /// How it ended.
    pub end: SessionEnd,
}

enum Bounded<T> {
    Done(T),
    TimedOut,
    Cut,
}

async fn bounded<T>(
    fut: impl Future<Output = T>,
    timeout: Duration,
    deadline: Option<Instant>,
) -> Bounded<T> {
    let t = tokio::time::timeout(timeout, fut);
    let r = match deadline {
        Some(d) => tokio::select! {
            r = t => r,
            _ = tokio::time::sleep_until(d) => return Bounded::Cut,
        },
        None => t.await,
    };
    match r {
        Ok(x) => Bounded::Done(x),
        Err(_) => Bounded::TimedOut,
    }
}

/// Whether a lost stream is worth resuming: the server or the network went away (not a refusal
/// of what the client sent).
fn transient(s: &tonic::Status) -> bool {
    use tonic::Code::*;
    matches!(s.code(), Unavailable | Unknown | Cancelled | Aborted)
        || (s.code() == Internal && s.message().contains("h2"))
}

/// Whether the stream ended because a newer stream took its session over (a resume of it).
pub fn taken_over(s: &tonic::Status) -> bool {
    use tonic_types::StatusExt;
    s.code() == tonic::Code::Aborted
        && s.get_error_details()
            .error_info()
            .is_some_and(|i| i.reason == "SESSION_TAKEN_OVER")
}

/// What one connection of a session came to.
enum Attempt {
    /// The session ended (`out.end` says how).
    Over,
    /// The stream was lost; resumable with the session's id.
    Lost(SessionEnd),
}

/// Runs one session: `msgs[0]` must be the `SessionStart` (it gets no answer), then every further
/// message is sent only after the previous one was answered. `on_update` sees every update with
/// the latency of the message it answers (None for an update that answers none: extra ones). After
/// the last answer the client closes its side and reads the stream to its end. With
/// `cfg.resume`, a stream lost to the server or the network (UNAVAILABLE, a reset, a closed
/// connection) is opened again after a backoff and the session resumed
/// (`SessionStart.resume_session_id`): the server answers the messages it recorded, and the
/// client goes on after them.
pub async fn run_session<F>(
    client: &Client,
    msgs: &[pb::StreamRegisterRequest],
    cfg: &SessionConfig,
    mut on_update: F,
) -> SessionOutcome
where
    F: FnMut(&pb::StreamUpdate, Option<Duration>) + Send,
{
    let mut out = SessionOutcome {
        updates: 0,
        answered: 0,
        resumed: 0,
        end: SessionEnd::Completed,
    };
    let Some((start, rest)) = msgs.split_first() else {
        return out;
    };
    let mut st = State {
        next: 0,
        session_id: None,
        pending: None,
        last_send: None,
    };
    // Reconnections since the last answer.
    let mut in_a_row: u32 = 0;
    loop {
        let answered_before = out.answered;
        let first = match &st.session_id {
            None => start.clone(),
            Some(id) => pb::StreamRegisterRequest {
                client_seq: start.client_seq,
                msg: Some(pb::stream_register_request::Msg::Start(pb::SessionStart {
                    resume_session_id: id.clone(),
                    ..Default::default()
                })),
            },
        };
        let resuming = st.session_id.is_some();
        let client = match cfg.replicas.len() {
            0 => client,
            n => &cfg.replicas[(cfg.first_replica + out.resumed as usize) % n],
        };
        match attempt(
            client,
            first,
            rest,
            cfg,
            &mut st,
            &mut out,
            resuming,
            &mut on_update,
        )
        .await
        {
            Attempt::Over => return out,
            Attempt::Lost(end) => {
                let Some(r) = &cfg.resume else {
                    out.end = end;
                    return out;
                };
                if out.answered > answered_before {
                    in_a_row = 0;
                }
                if in_a_row >= r.attempts {
                    out.end = end;
                    return out;
                }
                if st.session_id.is_none() {
                    // Lost before the server named the session: nothing was acknowledged, so
                    // it starts again.
                    st.next = 0;
                    st.pending = None;
                }
                let wait = r
                    .first_backoff
                    .saturating_mul(1 << in_a_row.min(6))
                    .min(Duration::from_secs(5));
                if cfg.deadline.is_some_and(|d| Instant::now() + wait >= d) {
                    out.end = SessionEnd::Cut;
                    return out;
                }
                tokio::time::sleep(wait).await;
                out.resumed += 1;
                in_a_row += 1;
            }
        }
    }
}

/// Where a session is, across its connections.
struct State {
    /// Index in the messages after the start of the next one to send.
    next: usize,
    /// The server's id of the session (from its updates).
    session_id: Option<String>,
    /// The message sent and not yet answered: its client_seq and when it was sent.
    pending: Option<(u64, Instant)>,
    /// When the last message was sent (rate limit).
    last_send: Option<Instant>,
}

/// Ends a session's attempt with `end`.
fn over(out: &mut SessionOutcome, end: SessionEnd) -> Attempt {
    out.end = end;
    Attempt::Over
}

/// One connection of a session: open the stream (a resume when `resuming`), send what is left,
/// read the answers.
#[allow(clippy::too_many_arguments)]
async fn attempt<F>(
    client: &Client,
    first: pb::StreamRegisterRequest,
    rest: &[pb::StreamRegisterRequest],
    cfg: &SessionConfig,
    st: &mut State,
    out: &mut SessionOutcome,
    resuming: bool,
    on_update: &mut F,
) -> Attempt
where
    F: FnMut(&pb::StreamUpdate, Option<Duration>) + Send,
{
    let updates_before = out.updates;
    let gate = match &cfg.lockstep {
        Some(g) => match bounded(g.clone().acquire_owned(), Duration::MAX, cfg.deadline).await {
            Bounded::Done(Ok(permit)) => Some(permit),
            // A closed gate lets every session through.
            Bounded::Done(Err(_)) | Bounded::TimedOut => None,
            Bounded::Cut => return over(out, SessionEnd::Cut),
        },
        None => None,
    };
    let (tx, mut inbound) = match open_stream(client, first, rest.len(), cfg, out).await {
        ControlFlow::Continue(opened) => opened,
        ControlFlow::Break(a) => return a,
    };
    // A resumed session first answers what the server recorded.
    if resuming
        && let ControlFlow::Break(a) =
            recorded_answer(&mut inbound, rest, cfg, st, out, on_update).await
    {
        return a;
    }
    let interval = cfg
        .rate_hz
        .filter(|&r| r > 0.0 && r.is_finite())
        .map(|r| Duration::from_secs_f64(1.0 / r));
    while st.next < rest.len() {
        let m = &rest[st.next];
        if let ControlFlow::Break(a) = pace(interval, cfg, st, out).await {
            return a;
        }
        let sent = Instant::now();
        st.last_send = Some(sent);
        st.pending = Some((m.client_seq, sent));
        // A failed send means the server already ended the stream: its status comes next.
        let _ = tx.send(m.clone()).await;
        let answer = Answer {
            m,
            sent,
            updates_before,
            fresh: !resuming,
        };
        if let ControlFlow::Break(a) = answer.wait(&mut inbound, cfg, st, out, on_update).await {
            return a;
        }
    }
    drop(tx);
    // Every message answered: what still follows (a discovery run's report) is waited for
    // without the gate.
    drop(gate);
    read_to_end(&mut inbound, rest, cfg, out, on_update).await
}

/// Where an open stream's requests go, and the stream of its updates.
type Opened = (
    tokio::sync::mpsc::Sender<pb::StreamRegisterRequest>,
    tonic::Streaming<pb::StreamUpdate>,
);

/// How a lost stream ends an attempt: resumable when the status is transient (and not a take-over
/// by another stream, unless `take_back`), else the session is over. `refused`: a stream lost
/// before any update counts as refused, not failed.
fn lost_or(
    s: tonic::Status,
    cfg: &SessionConfig,
    out: &mut SessionOutcome,
    refused: bool,
) -> Attempt {
    let end = if refused && out.updates == 0 {
        SessionEnd::Refused(s.clone())
    } else {
        SessionEnd::Failed(s.clone())
    };
    let take_back = cfg.resume.is_some_and(|r| r.take_back);
    if transient(&s) && (take_back || !taken_over(&s)) {
        Attempt::Lost(end)
    } else {
        out.end = end;
        Attempt::Over
    }
}

/// Opens the session's stream with `first` (queued before the call: a server may read the start
/// before it answers with headers) and room for `rest` more messages; breaks with how the
/// attempt ended when it does not open.
async fn open_stream(
    client: &Client,
    first: pb::StreamRegisterRequest,
    rest: usize,
    cfg: &SessionConfig,
    out: &mut SessionOutcome,
) -> ControlFlow<Attempt, Opened> {
    let (tx, rx) = tokio::sync::mpsc::channel(rest + 1);
    // Queued before the call: a server may read the start before it answers with headers.
    tx.try_send(first).expect("the channel has room");
    let mut req = tonic::Request::new(tokio_stream::wrappers::ReceiverStream::new(rx));
    if let Some(t) = &cfg.token {
        req.metadata_mut().insert("authorization", t.clone());
    }
    let mut client = client.clone();
    match bounded(client.stream_register(req), cfg.timeout, cfg.deadline).await {
        Bounded::Done(Ok(r)) => ControlFlow::Continue((tx, r.into_inner())),
        Bounded::Done(Err(s)) => ControlFlow::Break(lost_or(s, cfg, out, true)),
        Bounded::TimedOut => ControlFlow::Break(over(out, SessionEnd::TimedOut(0))),
        Bounded::Cut => ControlFlow::Break(over(out, SessionEnd::Cut)),
    }
}

/// A resumed session's first update: what the server recorded. The message sent and not answered
/// counts as answered when the update covers it; the next message to send is the first after the
/// last one the server recorded. Breaks with how the attempt ended when no update comes.
async fn recorded_answer<F>(
    inbound: &mut tonic::Streaming<pb::StreamUpdate>,
    rest: &[pb::StreamRegisterRequest],
    cfg: &SessionConfig,
    st: &mut State,
    out: &mut SessionOutcome,
    on_update: &mut F,
) -> ControlFlow<Attempt>
where
    F: FnMut(&pb::StreamUpdate, Option<Duration>) + Send,
{
    match bounded(inbound.message(), cfg.timeout, cfg.deadline).await {
        Bounded::Done(Ok(Some(u))) => {
            out.updates += 1;
            let done = u.last_client_seq;
            match st.pending.take() {
                Some((seq, sent)) if seq <= done => {
                    out.answered += 1;
                    on_update(&u, Some(sent.elapsed()));
                }
                _ => on_update(&u, None),
            }
            st.next = rest
                .iter()
                .position(|m| m.client_seq > done)
                .unwrap_or(rest.len());
            ControlFlow::Continue(())
        }
        Bounded::Done(Ok(None)) => ControlFlow::Break(Attempt::Lost(SessionEnd::ClosedEarly(
            rest.get(st.next).map_or(0, |m| m.client_seq),
        ))),
        Bounded::Done(Err(s)) => ControlFlow::Break(lost_or(s, cfg, out, false)),
        Bounded::TimedOut => ControlFlow::Break(over(out, SessionEnd::TimedOut(0))),
        Bounded::Cut => ControlFlow::Break(over(out, SessionEnd::Cut)),
    }
}

/// Waits for the rate limit (`interval` after the last message sent); breaks with the session
/// cut when the deadline comes first.
async fn pace(
    interval: Option<Duration>,
    cfg: &SessionConfig,
    st: &State,
    out: &mut SessionOutcome,
) -> ControlFlow<Attempt> {
    if let (Some(iv), Some(t)) = (interval, st.last_send) {
        let at = t + iv;
        if cfg.deadline.is_some_and(|d| at >= d) {
            return ControlFlow::Break(over(out, SessionEnd::Cut));
        }
        tokio::time::sleep_until(at).await;
    }
    if cfg.deadline.is_some_and(|d| Instant::now() >= d) {
        return ControlFlow::Break(over(out, SessionEnd::Cut));
    }
    ControlFlow::Continue(())
}

/// A message sent and the wait for its answer.
struct Answer<'a> {
    /// The message.
    m: &'a pb::StreamRegisterRequest,
    /// When it was sent.
    sent: Instant,
    /// The session's updates before this connection.
    updates_before: u64,
    /// Whether this connection opened the session (not a resume): a stream lost before its
    /// first update was then refused.
    fresh: bool,
}

impl Answer<'_> {
    /// Reads updates until one answers the message (`last_client_seq` reaches its
    /// `client_seq`): each goes to `on_update`, the answer with its latency. Breaks with how the
    /// attempt ended when the stream ends, fails, times out or is cut first.
    async fn wait<F>(
        &self,
        inbound: &mut tonic::Streaming<pb::StreamUpdate>,
        cfg: &SessionConfig,
        st: &mut State,
        out: &mut SessionOutcome,
        on_update: &mut F,
    ) -> ControlFlow<Attempt>
    where
        F: FnMut(&pb::StreamUpdate, Option<Duration>) + Send,
    {
        let m = self.m;
        loop {
            match bounded(inbound.message(), cfg.timeout, cfg.deadline).await {
                Bounded::Done(Ok(Some(u))) => {
                    out.updates += 1;
                    if !u.session_id.is_empty() {
                        st.session_id = Some(u.session_id.clone());
                    }
                    if u.last_client_seq >= m.client_seq {
                        out.answered += 1;
                        st.pending = None;
                        st.next += 1;
                        on_update(&u, Some(self.sent.elapsed()));
                        return ControlFlow::Continue(());
                    }
                    on_update(&u, None);
                }
                Bounded::Done(Ok(None)) => {
                    let end = SessionEnd::ClosedEarly(m.client_seq);
                    if cfg.resume.is_some() {
                        return ControlFlow::Break(Attempt::Lost(end));
                    }
                    return ControlFlow::Break(over(out, end));
                }
                Bounded::Done(Err(s)) => {
                    let refused = out.updates == self.updates_before && self.fresh;
                    return ControlFlow::Break(lost_or(s, cfg, out, refused));
                }
                Bounded::TimedOut => {
                    return ControlFlow::Break(over(out, SessionEnd::TimedOut(m.client_seq)));
                }
                Bounded::Cut => return ControlFlow::Break(over(out, SessionEnd::Cut)),
            }
        }
    }
}

/// After the last answer (the client's side closed): reads the stream to its end, each extra
/// update to `on_update`.
async fn read_to_end<F>(
    inbound: &mut tonic::Streaming<pb::StreamUpdate>,
    rest: &[pb::StreamRegisterRequest],
    cfg: &SessionConfig,
    out: &mut SessionOutcome,
    on_update: &mut F,
) -> Attempt
where
    F: FnMut(&pb::StreamUpdate, Option<Duration>) + Send,
{
    let wait = cfg
        .final_timeout
        .map_or(cfg.timeout, |t| t.max(cfg.timeout));
    loop {
        match bounded(inbound.message(), wait, cfg.deadline).await {
            Bounded::Done(Ok(Some(u))) => {
                out.updates += 1;
                on_update(&u, None);
            }
            Bounded::Done(Ok(None)) => return Attempt::Over,
            // Lost after the last answer (the server killed, the session taken over): resumed
            // like any lost stream, to end it cleanly; without `resume` it ends here.
            Bounded::Done(Err(s)) if out.updates > 0 => {
                return lost_or(s, cfg, out, false);
            }
            Bounded::Done(Err(s)) => {
                out.end = SessionEnd::Refused(s);
                return Attempt::Over;
            }
            Bounded::TimedOut => {
                return over(
                    out,
                    SessionEnd::NothingAfter(rest.last().map_or(0, |m| m.client_seq), wait),
                );
            }
            // Every message was answered: the session counts as completed.
            Bounded::Cut => return Attempt::Over,
        }
    }
}
