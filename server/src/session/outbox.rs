//! The session's outbox: numbers each update, stamps it with the session's id, points and last
//! client message, times it from the message's arrival, and sends it to the client's stream.

use super::state::Session;
use librplus_proto::v1 as pb;
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
        }
    }

    /// Sends one update of `s` (numbered after the last), answering a message that arrived at
    /// `arrival`.
    pub(crate) async fn send(
        &self,
        s: &mut Session,
        update: pb::stream_update::Update,
        arrival: Instant,
    ) -> Result<(), Gone> {
        s.sequence += 1;
        let out = pb::StreamUpdate {
            sequence: s.sequence,
            session_id: self.session_id.clone(),
            last_client_seq: s.last_seq,
            update: Some(update),
            points_total: s.meas.points.len() as u32,
        };
        metrics::histogram!("librplus_update_seconds").record(arrival.elapsed().as_secs_f64());
        self.tx.send(Ok(out)).await.map_err(|_| Gone)
    }
}
