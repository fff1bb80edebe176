//! The next thing a streamed session hears: a client message, the end of the client's stream, a
//! finished discovery run, or why there is none (the server drains, a newer stream took the
//! session over, the call's deadline or the idle timeout passed).

use crate::error::ServiceError;
use librplus_proto::v1 as pb;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tonic::{Status, Streaming};

/// What [`next`] heard.
pub(crate) enum Next {
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

/// How long a session may stay silent.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Quiet {
    /// This long from now without a message.
    For(Duration),
    /// A session with no points yet: until `at`, `after` its start, whatever it sends.
    NoData { at: Instant, after: Duration },
}

impl Quiet {
    fn until(self) -> tokio::time::Instant {
        match self {
            Quiet::For(d) => tokio::time::Instant::now() + d,
            Quiet::NoData { at, .. } => tokio::time::Instant::from_std(at),
        }
    }

    fn ended(self) -> Status {
        match self {
            Quiet::For(d) => Status::deadline_exceeded(format!(
                "no message for {:.0} s; session closed",
                d.as_secs_f64()
            )),
            Quiet::NoData { after, .. } => Status::deadline_exceeded(format!(
                "no points accepted {:.0} s after the session's start \
                 (session_no_data_timeout_s); session closed, its slot freed",
                after.as_secs_f64()
            )),
        }
    }
}

/// The next client message, or why there is none.
pub(crate) async fn next(
    inbound: &mut Streaming<pb::StreamRegisterRequest>,
    quiet: Quiet,
    deadline: Option<Instant>,
    drain: &mut watch::Receiver<bool>,
    pending: &mut Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>>,
    lease: Option<(&str, &mut crate::live::Lease)>,
) -> Result<Next, Status> {
    let idle_at = quiet.until();
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
                Err(quiet.ended())
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
