//! A session's stream once it has started: each client message and every one already waiting
//! behind it are taken as one batch (each rejected message answered on its own, the accepted
//! ones folded into one registration of the newest state), recorded before any answer, then
//! answered in order: rejections, a discovery run asked for or due, the registration. A
//! finished discovery run is reported as it ends; the client's end of stream waits for a run it
//! started.

use super::inbound::{Next, Quiet, next};
use super::open::Opened;
use super::outbox::{Gone, Outbox};
use super::records::{audit_record, lease_record, rejected_event};
use super::state::{Accepted, Session, accept};
use super::work::{register_session, start_discovery};
use crate::audit::Record;
use crate::auth::Principal;
use crate::cases::Case;
use crate::shared::{Shared, count_error};
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};
use tonic::{Status, Streaming};

/// Most waiting stream messages folded into one registration.
const MAX_COALESCED: usize = 256;

/// Why a session stops before the client's stream ends: the client went away (nothing more to
/// send), or an error that ends the stream with its status.
enum Halt {
    Gone,
    Status(Status),
}

impl From<Gone> for Halt {
    fn from(_: Gone) -> Self {
        Halt::Gone
    }
}

impl From<Status> for Halt {
    fn from(s: Status) -> Self {
        Halt::Status(s)
    }
}

impl From<crate::error::ServiceError> for Halt {
    fn from(e: crate::error::ServiceError) -> Self {
        Halt::Status(e.to_status())
    }
}

/// The case is in use while a session on it lasts (DeleteCase waits for none).
struct InUse(Arc<Case>);

impl InUse {
    fn new(case: &Arc<Case>) -> Self {
        case.sessions.fetch_add(1, Ordering::SeqCst);
        Self(case.clone())
    }
}

impl Drop for InUse {
    fn drop(&mut self) {
        self.0.sessions.fetch_sub(1, Ordering::SeqCst);
    }
}

/// One batch of client messages, checked.
#[derive(Default)]
struct Batch {
    /// The newest accepted message with points (its client_seq).
    accepted: Option<u64>,
    /// A discovery run asked for (its client_seq).
    discover: Option<u64>,
    /// The answers to rejected messages, in order.
    rejections: Vec<pb::stream_update::Update>,
    /// What the audit log keeps of the batch (committed before any answer).
    records: Vec<Record>,
}

/// A started session and its stream.
pub(crate) struct Stream {
    shared: Arc<Shared>,
    who: Arc<Principal>,
    inbound: Streaming<pb::StreamRegisterRequest>,
    deadline: Option<Instant>,
    drain: watch::Receiver<bool>,
    idle: Duration,
    /// How long after `started` a session with no points yet ends
    /// (`session_no_data_timeout_s`).
    no_data: Duration,
    started: Instant,
    s: Session,
    sid: String,
    lease: crate::live::Lease,
    resumed: bool,
    out: Outbox,
    in_use: InUse,
}

impl Stream {
    /// The stream of an opened session.
    pub(crate) fn new(
        shared: Arc<Shared>,
        who: Arc<Principal>,
        inbound: Streaming<pb::StreamRegisterRequest>,
        opened: Opened,
        tx: mpsc::Sender<Result<pb::StreamUpdate, Status>>,
        deadline: Option<Instant>,
        drain: watch::Receiver<bool>,
    ) -> Self {
        let Opened {
            session,
            session_id,
            lease,
            resumed,
        } = opened;
        Self {
            idle: Duration::from_secs_f64(shared.config.session_idle_timeout_s),
            no_data: Duration::from_secs_f64(shared.config.session_no_data_timeout_s),
            started: Instant::now(),
            out: Outbox::new(tx, &session_id),
            in_use: InUse::new(session.case()),
            shared,
            who,
            inbound,
            deadline,
            drain,
            s: session,
            sid: session_id,
            lease,
            resumed,
        }
    }

    /// Serves the session until the client's stream ends (Ok), the client goes away (Ok), or
    /// an error ends it.
    pub(crate) async fn run(&mut self) -> Result<(), Status> {
        match self.serve().await {
            Ok(()) | Err(Halt::Gone) => Ok(()),
            Err(Halt::Status(s)) => Err(s),
        }
    }

    async fn serve(&mut self) -> Result<(), Halt> {
        if self.resumed {
            // The recorded messages answered again: the client goes on after `last_client_seq`.
            let seq = self.s.last_seq();
            self.register(seq, Instant::now()).await?;
        }
        loop {
            // A session that holds no points yet keeps its slot only briefly.
            let quiet = match self.s.measurements().points.is_empty() && self.no_data < self.idle {
                true => Quiet::NoData {
                    at: self.started + self.no_data,
                    after: self.no_data,
                },
                false => Quiet::For(self.idle),
            };
            let heard = next(
                &mut self.inbound,
                quiet,
                self.deadline,
                &mut self.drain,
                self.s.pending_mut(),
                Some((self.sid.as_str(), &mut self.lease)),
            )
            .await?;
            let m = match heard {
                Next::Msg(m) => m,
                Next::End => return self.finish().await,
                Next::Discovered(o) => {
                    *self.s.pending_mut() = None;
                    self.discovered(o).await?;
                    continue;
                }
            };
            let arrival = Instant::now();
            let (batch, end) = self.gather(m).await;
            self.answer(batch, arrival).await?;
            match end {
                Some(Ok(())) => return self.finish().await,
                Some(Err(e)) => return Err(e.into()),
                None => {}
            }
        }
    }

    /// The message `m` and every one already waiting (a client sending faster than its
    /// registrations complete), and how the client's stream ended if it did meanwhile.
    async fn gather(
        &mut self,
        m: pb::StreamRegisterRequest,
    ) -> (Vec<pb::StreamRegisterRequest>, Option<Result<(), Status>>) {
        let mut batch = vec![m];
        while batch.len() < MAX_COALESCED {
            // `Streaming::message` keeps its state in the stream, so giving up on a pending
            // poll loses nothing.
            match tokio::time::timeout(Duration::ZERO, self.inbound.message()).await {
                Err(_) => break,
                Ok(Ok(Some(m))) => batch.push(m),
                Ok(Ok(None)) => return (batch, Some(Ok(()))),
                Ok(Err(e)) => {
                    let status = Status::new(e.code(), format!("receiving: {}", e.message()));
                    return (batch, Some(Err(status)));
                }
            }
        }
        (batch, None)
    }

    /// Checks each message of a batch into the session; the answers and records it needs.
    fn check(&mut self, batch: Vec<pb::StreamRegisterRequest>) -> Batch {
        let audit = self.shared.audit.is_some();
        let mut b = Batch::default();
        let mut kept = Vec::new();
        for m in batch {
            let seq = m.client_seq;
            let bytes = audit.then(|| prost::Message::encode_to_vec(&m));
            match accept(&mut self.s, m, &self.shared.config) {
                Ok(a) => {
                    kept.extend(bytes.map(|x| (seq, x)));
                    match a {
                        Accepted::Points => b.accepted = Some(seq),
                        Accepted::Discover => b.discover = Some(seq),
                    }
                }
                Err(e) => {
                    count_error(e.code());
                    let r = e.to_rejection(seq);
                    if audit {
                        let case = &self.s.case().id;
                        b.records
                            .push(rejected_event(&self.who.name, case, &self.sid, &r));
                    }
                    b.rejections.push(pb::stream_update::Update::Rejection(r));
                }
            }
        }
        if !kept.is_empty() {
            b.records.push(Record::Messages {
                session_id: self.sid.clone(),
                messages: kept,
            });
        }
        b
    }

    /// Records a batch, then answers it: rejections, a discovery run asked for or due, the
    /// registration of the accepted points.
    async fn answer(
        &mut self,
        batch: Vec<pb::StreamRegisterRequest>,
        arrival: Instant,
    ) -> Result<(), Halt> {
        let b = self.check(batch);
        if !b.records.is_empty() {
            lease_record(&self.shared, &self.lease, &self.sid, b.records).await?;
        }
        for r in b.rejections {
            self.out.send(&self.s, r, arrival).await?;
        }
        // A discovery run: asked for, or due (the session grew to its automatic threshold).
        let due = self.s.discovery_due();
        if let Some(seq) = b.discover.or(due.then_some(0)) {
            let update = start_discovery(&self.shared, &mut self.s, seq);
            self.out.send(&self.s, update, arrival).await?;
        }
        if let Some(seq) = b.accepted {
            self.register(seq, arrival).await?;
        }
        Ok(())
    }

    /// Registers the session's points, records each answer (acknowledged only once recorded)
    /// and sends it: METHOD_NONLINEAR's linear answer as soon as it is made, then the refined
    /// one.
    async fn register(&mut self, seq: u64, arrival: Instant) -> Result<(), Halt> {
        self.swap_to_own_basis().await?;
        let (tx, mut firsts) = mpsc::unbounded_channel();
        let work = register_session(
            &self.shared,
            &self.s,
            (arrival, self.deadline),
            seq,
            Some(tx),
        );
        tokio::pin!(work);
        let update = loop {
            tokio::select! {
                biased;
                u = &mut work => break u,
                Some(r) = firsts.recv() => {
                    let first = pb::stream_update::Update::Registration(r);
                    self.deliver(first, arrival).await?;
                }
            }
        };
        // A linear answer handed over just before the work ended goes first.
        while let Ok(r) = firsts.try_recv() {
            self.deliver(pb::stream_update::Update::Registration(r), arrival)
                .await?;
        }
        self.deliver(update, arrival).await
    }

    /// Records an answer of the session's registration (acknowledged only once recorded) and
    /// sends it.
    async fn deliver(
        &self,
        update: pb::stream_update::Update,
        arrival: Instant,
    ) -> Result<(), Halt> {
        if self.shared.audit.is_some() {
            let record = match &update {
                pb::stream_update::Update::Registration(r) => {
                    Some(Record::Registration(Box::new(audit_record(
                        r,
                        &self.who.name,
                        &self.s.case().id,
                        Some(&self.sid),
                        self.s.last_seq(),
                    ))))
                }
                pb::stream_update::Update::Rejection(r) => Some(rejected_event(
                    &self.who.name,
                    &self.s.case().id,
                    &self.sid,
                    r,
                )),
                pb::stream_update::Update::Discovery(_) => None,
            };
            if let Some(record) = record {
                lease_record(&self.shared, &self.lease, &self.sid, vec![record]).await?;
            }
        }
        self.out.send(&self.s, update, arrival).await?;
        Ok(())
    }

    /// A session on a case that served from a coarse basis takes the case's own basis once it
    /// is ready; the swap is audited before the registration it changes.
    async fn swap_to_own_basis(&mut self) -> Result<(), Halt> {
        let Some(full) = self.s.swap_to_own_basis() else {
            return Ok(());
        };
        self.in_use = InUse::new(&full);
        tracing::info!(session = %self.sid, case = %full.id, "session swapped to the case's own basis");
        if self.shared.audit.is_some() {
            let record = Record::Event {
                kind: "session_basis_swapped",
                principal: self.who.name.clone(),
                case_id: Some(full.id.clone()),
                session_id: Some(self.sid.clone()),
                detail: serde_json::json!({
                    "version": full.version,
                    "after_client_seq": self.s.last_seq(),
                }),
            };
            lease_record(&self.shared, &self.lease, &self.sid, vec![record]).await?;
        }
        Ok(())
    }

    /// A finished discovery run: the session takes its model when it switched, the report is
    /// sent, then (after a switch) the session's points registered with the new model.
    async fn discovered(&mut self, o: Option<crate::discovery::Outcome>) -> Result<(), Halt> {
        let arrival = Instant::now();
        let Some(o) = o else {
            tracing::error!("discovery ended without an outcome");
            return Ok(());
        };
        let switched = o.augmented.is_some();
        let state =
            pb::DiscoveryState::try_from(o.report.state).map_or("UNKNOWN", |x| x.as_str_name());
        metrics::counter!("librplus_discovery_total", "state" => state).increment(1);
        tracing::info!(
            verdict = %o.report.verdict,
            switched,
            elapsed_ms = o.report.elapsed_ms,
            message = %o.report.message,
            "discovery finished"
        );
        if let Some(p) = o.augmented {
            self.s.switch_to(p);
        }
        let report = pb::stream_update::Update::Discovery(o.report);
        self.out.send(&self.s, report, arrival).await?;
        // The switch shows at once: the session's points registered with its new model.
        if switched && !self.s.measurements().points.is_empty() {
            let seq = self.s.last_seq();
            let update =
                register_session(&self.shared, &self.s, (arrival, self.deadline), seq, None).await;
            self.out.send(&self.s, update, arrival).await?;
        }
        Ok(())
    }

    /// The client finished sending: a discovery run it started is still reported (it was
    /// acknowledged), unless the server drains or the call's deadline passes first.
    async fn finish(&mut self) -> Result<(), Halt> {
        let Some(rx) = self.s.pending_mut().take() else {
            return Ok(());
        };
        let until = self.deadline.map_or_else(
            || tokio::time::Instant::now() + Duration::from_secs(24 * 3600),
            tokio::time::Instant::from_std,
        );
        let o = tokio::select! {
            biased;
            _ = self.drain.wait_for(|d| *d) => return Err(Status::unavailable("the server is shutting down; session ended before its discovery run finished").into()),
            _ = tokio::time::sleep_until(until) => return Err(Status::deadline_exceeded("the call's deadline passed before the discovery run finished").into()),
            o = rx => o.ok(),
        };
        // The client may have gone away: nothing is left to send then.
        match self.discovered(o).await {
            Ok(()) | Err(Halt::Gone) => Ok(()),
            Err(h) => Err(h),
        }
    }

    /// Records the session's end (`outcome`) while this stream still holds it (nothing after a
    /// takeover: the session goes on in the newer stream), then releases its slot.
    pub(crate) async fn close(self, outcome: String) {
        let end = vec![Record::SessionEnd {
            session_id: self.sid.clone(),
            outcome,
        }];
        let _ = lease_record(&self.shared, &self.lease, &self.sid, end).await;
    }
}
