//! Streamed sessions (`StreamRegister`): one per stream, opened by its first message, then
//! served message by message until the client ends it, goes away, or an error ends it.
//!
//! - [`open`]: the start or resume, the slot and quota, the lease on the session.
//! - [`stream`]: batches of messages checked, recorded and answered; discovery runs.
//! - [`state`]: the session's state and the checks each message passes.
//! - [`work`]: a registration and a discovery run of the session.
//! - [`records`]: what the audit log keeps; [`outbox`]: what the client receives;
//!   [`inbound`]: what the session hears next.
//!
//! The server's order (tests/architecture.rs): sessions use the shared state and case access
//! below them; the service above spawns them.

pub(crate) mod inbound;
pub(crate) mod open;
pub(crate) mod outbox;
pub(crate) mod records;
pub(crate) mod state;
pub(crate) mod stream;
pub(crate) mod work;

use crate::audit::Record;
use crate::auth::Principal;
use crate::convert::code_name;
use crate::error::short;
use crate::shared::{Shared, count_error};
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::time::Instant;
use tokio::sync::mpsc;
use tonic::{Status, Streaming};

/// Serves one stream to its end: opens the session, runs it, records how it ended (its end
/// while the stream holds it, or the refusal of a stream that never started), and sends a
/// closing error to the client.
pub(crate) async fn serve(
    shared: Arc<Shared>,
    who: Arc<Principal>,
    mut inbound: Streaming<pb::StreamRegisterRequest>,
    tx: mpsc::Sender<Result<pb::StreamUpdate, Status>>,
    deadline: Option<Instant>,
    fresh: String,
) {
    metrics::gauge!("librplus_sessions_active").increment(1.0);
    let mut drain = shared.drain.clone();
    let opened = open::open(&shared, &who, &mut inbound, deadline, &mut drain, &fresh).await;
    let (outcome, started) = match opened {
        Ok(Some(o)) => {
            let mut s = stream::Stream::new(
                shared.clone(),
                who.clone(),
                inbound,
                o,
                tx.clone(),
                deadline,
                drain,
            );
            (s.run().await, Some(s))
        }
        Ok(None) => (Ok(()), None),
        Err(e) => (Err(e), None),
    };
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
        Some(s) => s.close(text).await,
        None => {
            let refused = Record::Event {
                kind: "refused",
                principal: who.name.clone(),
                case_id: None,
                session_id: None,
                detail: serde_json::json!({"rpc": "StreamRegister", "outcome": text}),
            };
            let _ = shared.record(vec![refused]).await;
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
