//! Opening a streamed session: its first message must be a SessionStart, within
//! `session_start_timeout_s`. A new session takes a slot and its principal's quota and is
//! recorded; a resume rebuilds the recorded session (the same checks as when its messages
//! arrived), takes over the stream that holds it if any, claims it on a shared journal, and is
//! recorded as taken over. Either way the stream then holds a lease on the session.

use super::inbound::{Next, Quiet, next};
use super::records::lease_record;
use super::state::{Session, accept, start_session};
use crate::audit::Record;
use crate::auth::Principal;
use crate::error::{DynError, Internal, ServiceError, Unavailable, Unreplayable, short};
use crate::shared::Shared;
use librplus_proto::v1 as pb;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tonic::{Code, Status, Streaming};

/// A session the stream now holds.
pub(crate) struct Opened {
    pub session: Session,
    /// Its id (a resume keeps the recorded one).
    pub session_id: String,
    /// This stream's hold on the session: records go through it.
    pub lease: crate::live::Lease,
    /// Whether it was resumed (its recorded messages are answered again first).
    pub resumed: bool,
}

/// Waits for the start and opens the session; `Ok(None)` when the client ended the stream
/// before starting. `fresh`: the id a new session gets.
pub(crate) async fn open(
    shared: &Arc<Shared>,
    who: &Arc<Principal>,
    inbound: &mut Streaming<pb::StreamRegisterRequest>,
    deadline: Option<Instant>,
    drain: &mut watch::Receiver<bool>,
    fresh: &str,
) -> Result<Option<Opened>, Status> {
    let start_within = Duration::from_secs_f64(shared.config.session_start_timeout_s);
    let first = match next(
        inbound,
        Quiet::For(start_within),
        deadline,
        drain,
        &mut None,
        None,
    )
    .await
    {
        Ok(Next::Msg(m)) => m,
        Ok(Next::End | Next::Discovered(_)) => return Ok(None),
        Err(e)
            if e.code() == Code::DeadlineExceeded
                && deadline.is_none_or(|d| Instant::now() < d) =>
        {
            metrics::counter!("librplus_refused_total", "reason" => "no_start").increment(1);
            return Err(Status::deadline_exceeded(format!(
                "no SessionStart within {:.0} s of opening the stream; session closed",
                start_within.as_secs_f64()
            )));
        }
        Err(e) => return Err(e),
    };
    let first_bytes = shared
        .audit
        .is_some()
        .then(|| prost::Message::encode_to_vec(&first));
    let Some(pb::stream_register_request::Msg::Start(start)) = first.msg else {
        return Err(ServiceError::precondition(
            "SESSION",
            "msg",
            "expected start",
            "msg: the first message of a session must be a SessionStart",
        )
        .to_status());
    };
    let opened = if start.resume_session_id.is_empty() {
        let bytes = first_bytes.unwrap_or_default();
        start_new(shared, who, &start, first.client_seq, fresh, bytes).await
    } else {
        resume(shared, who, &start.resume_session_id).await
    };
    opened.map(Some).map_err(|b| b.to_status())
}

/// A new session: checked, admitted (slot and quota), recorded.
async fn start_new(
    shared: &Arc<Shared>,
    who: &Principal,
    start: &pb::SessionStart,
    seq: u64,
    fresh: &str,
    start_bytes: Vec<u8>,
) -> Result<Opened, ServiceError> {
    let s = start_session(shared, who, start, seq)?;
    let admission = shared.admit(who).await?;
    let lease = shared.live.start(fresh, admission);
    let records = vec![Record::SessionStart {
        session_id: fresh.to_string(),
        principal: who.name.clone(),
        case_id: s.case().id.clone(),
        case_version: s.case().version.clone(),
        start: start_bytes,
    }];
    lease_record(shared, &lease, fresh, records).await?;
    tracing::info!(case = %s.case().id, method = s.method().name(), "session started");
    Ok(Opened {
        session: s,
        session_id: fresh.to_string(),
        lease,
        resumed: false,
    })
}

/// A recorded session resumed: rebuilt, its slot taken (from the stream that holds it, if
/// any), claimed on a shared journal, and recorded as taken over.
async fn resume(shared: &Arc<Shared>, who: &Principal, id: &str) -> Result<Opened, ServiceError> {
    check_session_id(id)?;
    // Nothing of the session is recorded while it is read and taken over.
    let takeover = shared.live.lock(id).await;
    let (mut s, mut recorded) = resume_session(shared, who, id).await?;
    let admission = match takeover.held() {
        true => None,
        false => Some(shared.admit(who).await?),
    };
    if shared
        .audit
        .as_ref()
        .is_some_and(|a| a.journal_dir().is_some())
    {
        // Replicas: the session's next epoch is claimed (no other replica answers for it from
        // now), then read again — what was recorded up to the claim is the session. A resume
        // refused by the first read claims nothing.
        shared
            .record(vec![Record::Claim {
                session_id: id.to_string(),
            }])
            .await?;
        (s, recorded) = resume_session(shared, who, id).await?;
    }
    let was_live = takeover.held();
    let lease = takeover.take(admission);
    let detail = serde_json::json!({
        "points": s.measurements().points.len(),
        "last_client_seq": s.last_seq(),
        "replica": crate::config::host_name(),
        "took_over_a_live_stream": was_live,
    });
    let records = vec![
        // This replica holds the session from here (the journal's next epoch).
        Record::Takeover {
            session_id: id.to_string(),
            principal: who.name.clone(),
            case_id: s.case().id.clone(),
            case_version: s.case().version.clone(),
            start: recorded,
            last_seq: s.last_seq(),
        },
        Record::Event {
            kind: "session_resumed",
            principal: who.name.clone(),
            case_id: Some(s.case().id.clone()),
            session_id: Some(id.to_string()),
            detail,
        },
    ];
    lease_record(shared, &lease, id, records).await?;
    tracing::info!(case = %s.case().id, resumed = %id, points = s.measurements().points.len(), last_client_seq = s.last_seq(), took_over = was_live, "session resumed");
    Ok(Opened {
        session: s,
        session_id: id.to_string(),
        lease,
        resumed: true,
    })
}

/// A resumed session id is at most 128 bytes (checked before anything is looked up).
fn check_session_id(id: &str) -> Result<(), ServiceError> {
    if id.len() > 128 {
        return Err(ServiceError::field(
            "start.resume_session_id",
            format!("is {} bytes long; session ids are at most 128", id.len()),
        ));
    }
    Ok(())
}

/// The field every resume error names.
const RESUME_FIELD: &str = "start.resume_session_id";

/// Rebuilds a recorded session: its start and accepted messages, in order, through the same
/// checks as when they arrived. The case must still have the content the session started on.
async fn resume_session(
    shared: &Arc<Shared>,
    who: &Principal,
    id: &str,
) -> Result<(Session, Vec<u8>), ServiceError> {
    use prost::Message;
    let rec = read_record(shared, who, id).await?;
    let broken = |problem: Unreplayable| {
        ServiceError::from(Internal::Unreplayable {
            session_id: id.to_string(),
            problem,
        })
    };
    let first = pb::StreamRegisterRequest::decode(&rec.start[..])
        .map_err(|e| broken(Unreplayable::Start(e)))?;
    let Some(pb::stream_register_request::Msg::Start(start)) = &first.msg else {
        return Err(broken(Unreplayable::NotAStart));
    };
    let mut s = start_session(shared, who, start, first.client_seq).map_err(|e| match e {
        ServiceError::UnknownCase { .. } => ServiceError::precondition(
            "CASE",
            RESUME_FIELD,
            format!("the session's case {:?} no longer exists", rec.case_id),
            format!(
                "{RESUME_FIELD}: session {id} was started on case {:?} (version {}), which no \
                 longer exists; start a new session",
                short(&rec.case_id, 64),
                rec.case_version.as_deref().unwrap_or("not recorded")
            ),
        ),
        e => e,
    })?;
    check_case_version(&rec, &s, id)?;
    for (seq, bytes) in &rec.messages {
        let m = pb::StreamRegisterRequest::decode(&bytes[..])
            .map_err(|source| broken(Unreplayable::Decode { seq: *seq, source }))?;
        if matches!(m.msg, Some(pb::stream_register_request::Msg::Discover(_))) {
            // A discovery run is not repeated; its message still counts.
            s.replayed(*seq);
            continue;
        }
        accept(&mut s, m, &shared.config).map_err(|e| {
            broken(Unreplayable::Refused {
                seq: *seq,
                refusal: Box::new(e),
            })
        })?;
    }
    Ok((s, rec.start))
}

/// The recorded session `id` of `who` (NOT_FOUND, worded the same, for another principal's).
async fn read_record(
    shared: &Shared,
    who: &Principal,
    id: &str,
) -> Result<crate::journal::SessionRecord, ServiceError> {
    let Some(audit) = &shared.audit else {
        return Err(ServiceError::precondition(
            "SESSION",
            RESUME_FIELD,
            "the server keeps no audit log",
            format!(
                "{RESUME_FIELD}: this server keeps no audit log (audit_db), so no session resumes"
            ),
        ));
    };
    let path = audit.path().to_path_buf();
    let journal = audit.journal_dir().map(Path::to_path_buf);
    let key = id.to_string();
    let rec = tokio::task::spawn_blocking(move || -> Result<_, DynError> {
        match journal {
            // Replicas: the shared journal has every replica's sessions.
            Some(dir) => Ok(crate::journal::read(&dir, &key)?),
            None => {
                let c = crate::audit::open_db(&path)?;
                Ok(crate::audit::read_session(&c, &key)?)
            }
        }
    })
    .await
    .map_err(|source| Internal::Task {
        doing: "reading the session record",
        source,
    })?
    .map_err(Unavailable::SessionRecord)?;
    let unknown = || ServiceError::UnknownSession {
        field: RESUME_FIELD.into(),
        id: id.to_string(),
    };
    let rec = rec.ok_or_else(unknown)?;
    if rec.principal != who.name {
        return Err(unknown());
    }
    Ok(rec)
}

/// The case must still have the version the session started on.
fn check_case_version(
    rec: &crate::journal::SessionRecord,
    s: &Session,
    id: &str,
) -> Result<(), ServiceError> {
    let Some(v) = &rec.case_version else {
        return Ok(());
    };
    if *v == s.case().version {
        return Ok(());
    }
    Err(ServiceError::precondition(
        "CASE",
        RESUME_FIELD,
        format!(
            "the session's case {:?} changed since it started (version {v}, now {})",
            rec.case_id,
            s.case().version
        ),
        format!(
            "{RESUME_FIELD}: session {id} was started on case {:?} version {v}; the case now has \
             version {} (it was replaced since), so the session's points would be registered \
             to another model; start a new session",
            short(&rec.case_id, 64),
            s.case().version
        ),
    ))
}
