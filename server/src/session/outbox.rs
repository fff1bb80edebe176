//! The session's outbox: numbers each update, stamps it with the session's id, points and last
//! client message, times it from the message's arrival, and sends it to the client's stream.

use super::state::Session;
use librplus_proto::v1 as pb;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;
use tokio::sync::mpsc;
use tonic::Status;

/// The client's end of the stream went away: nothing more can be sent.
#[derive(Debug)]
pub(crate) struct Gone;

/// Where a session's updates go.
pub(crate) struct Outbox {
    tx: mpsc::Sender<Result<pb::StreamUpdate, Status>>,
    session_id: String,
    /// The last update's number (the first is 1).
    sequence: AtomicU64,
}

impl Outbox {
    /// The outbox of session `session_id` over `tx`.
    pub(crate) fn new(
        tx: mpsc::Sender<Result<pb::StreamUpdate, Status>>,
        session_id: &str,
    ) -> Self {
        Self {
            tx,
            session_id: session_id.to_string(),
            sequence: AtomicU64::new(0),
        }
    }

    /// Sends one update of `s` (numbered after the last), answering a message that arrived at
    /// `arrival`.
    pub(crate) async fn send(
        &self,
        s: &Session,
        update: pb::stream_update::Update,
        arrival: Instant,
    ) -> Result<(), Gone> {
        let sequence = self.sequence.fetch_add(1, Ordering::Relaxed) + 1;
        let out = pb::StreamUpdate {
            sequence,
            session_id: self.session_id.clone(),
            last_client_seq: s.last_seq(),
            update: Some(update),
            points_total: s.measurements().points.len() as u32,
        };
        metrics::histogram!("librplus_update_seconds").record(arrival.elapsed().as_secs_f64());
        self.tx.send(Ok(out)).await.map_err(|_| Gone)
    }
}
