//! Every way a request can fail, and the one place that turns each into a gRPC status with the
//! `google.rpc` details the proto promises (BadRequest, PreconditionFailure, ResourceInfo,
//! QuotaFailure) or an in-stream rejection.

use librplus::pipeline::PipelineError;
use librplus::register::RegisterError;
use librplus_proto::v1 as pb;
use std::time::Duration;
use tokio::task::JoinError;
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

/// A cause from a module above this one (the audit log, the case store, the session journal),
/// kept whole: its type can be recovered with `downcast_ref`.
pub type DynError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// The `google.rpc.ErrorInfo` reason of the ABORTED status that ends a stream whose session was
/// taken over by a newer stream.
pub const TAKEN_OVER: &str = "SESSION_TAKEN_OVER";

/// At most `n` characters of `s` (what is logged or echoed of a client's string).
pub fn short(s: &str, n: usize) -> std::borrow::Cow<'_, str> {
    match s.char_indices().nth(n) {
        None => s.into(),
        Some((i, _)) => format!("{}… ({} bytes)", &s[..i], s.len()).into(),
    }
}

/// A request the server did not answer with a registration.
#[derive(Debug)]
pub enum ServiceError {
    /// A field is malformed (INVALID_ARGUMENT, BadRequest: one violation per field).
    InvalidArgument {
        /// Summary.
        message: String,
        /// (field path, problem) pairs.
        violations: Vec<(String, String)>,
    },
    /// The request is well-formed but the session or case is not in a state to take it
    /// (FAILED_PRECONDITION, PreconditionFailure): a message out of order, a second start, a
    /// method the case cannot run.
    Precondition {
        /// Summary.
        message: String,
        /// Kind of precondition (`ORDER`, `SESSION`, `CASE`).
        kind: &'static str,
        /// The field or case it concerns.
        subject: String,
        /// What must hold.
        description: String,
    },
    /// No such case (NOT_FOUND, ResourceInfo and a BadRequest violation of the field).
    UnknownCase {
        /// The request field that named it.
        field: String,
        /// The id asked for.
        id: String,
        /// The ids this server has.
        known: Vec<String>,
    },
    /// No recorded session of that id for this caller (NOT_FOUND, a BadRequest violation).
    UnknownSession {
        /// The request field that named it.
        field: String,
        /// The id asked for (bounded by the caller).
        id: String,
    },
    /// A limit of the server (RESOURCE_EXHAUSTED, QuotaFailure).
    Quota {
        /// Summary.
        message: String,
        /// What ran out (`sessions`, `queue`, `points_per_session`).
        subject: &'static str,
        /// The limit and what to do.
        description: String,
    },
    /// The server cannot take requests now (UNAVAILABLE): preloading or shutting down.
    Unavailable(Unavailable),
    /// No credentials, or credentials the server does not know (UNAUTHENTICATED).
    Unauthenticated(Unauthenticated),
    /// Known credentials without the role the call needs (PERMISSION_DENIED).
    PermissionDenied(PermissionDenied),
    /// The client did not send in time (DEADLINE_EXCEEDED).
    Deadline(Deadline),
    /// A status from the transport (a message too large, a reset stream), passed on.
    Received {
        /// Its code.
        code: Code,
        /// Its message.
        message: String,
    },
    /// The pipeline refused or failed; mapped by cause in [`ServiceError::parts`].
    Registration(PipelineError),
    /// Something failed inside the server: a task, a write, a recorded session (INTERNAL).
    Internal(Internal),
    /// The stream's session was taken over by a newer stream, a resume of the same session
    /// (ABORTED, ErrorInfo reason [`TAKEN_OVER`]): this stream has ended.
    TakenOver {
        /// The session.
        session_id: String,
    },
}

/// Why the server cannot take a request now (UNAVAILABLE); its text is the status message.
#[derive(Debug, thiserror::Error)]
pub enum Unavailable {
    /// The server is draining (or its compute slots have closed).
    #[error("the server is shutting down")]
    ShuttingDown,
    /// Preload has not finished.
    #[error("the server is still preloading its cases; retry when health reports SERVING")]
    Preloading,
    /// An uploaded case left memory while idle and is being loaded again.
    #[error(
        "{field}: case {:?} was idle and left memory; it is being loaded again ({stage}); retry \
         in a few seconds, or follow it with WatchCase",
        short(.id, 64)
    )]
    Reloading {
        /// The request field that named it.
        field: String,
        /// The case.
        id: String,
        /// Its loading stage and progress (`stage, NN %`; empty when unknown).
        stage: String,
    },
    /// The audit log could not be written (its `AuditError`): nothing is answered
    /// that is not recorded.
    #[error("the audit log cannot be written, so nothing is answered: {0}")]
    AuditLog(#[source] DynError),
    /// The case store failed (its `StoreError`: neither a quota nor a full disk).
    #[error("{0}; nothing was stored")]
    Store(#[source] DynError),
    /// A recorded session could not be read (the session journal or the audit log).
    #[error("reading the session record: {0}")]
    SessionRecord(#[source] DynError),
}

/// Why a caller is not authenticated (UNAUTHENTICATED); its text is the status message (which
/// never echoes a token).
#[derive(Debug, thiserror::Error)]
pub enum Unauthenticated {
    /// More than one `authorization` header.
    #[error("authorization: sent more than once; send exactly one \"Bearer TOKEN\"")]
    RepeatedHeader,
    /// An `authorization` header longer than the server reads.
    #[error("authorization: longer than {max} bytes")]
    LongHeader {
        /// Its length, bytes.
        len: usize,
        /// The longest read, bytes.
        max: usize,
    },
    /// An `authorization` header that is not `Bearer TOKEN`.
    #[error("authorization: expected \"Bearer TOKEN\"")]
    NotBearer,
    /// A bearer token the auth file does not list.
    #[error("authorization: the token is not valid")]
    UnknownToken,
    /// A client certificate whose subject the auth file does not list (and no token).
    #[error(
        "the client certificate's subject is not in the auth file, and no authorization token \
         was sent"
    )]
    UnknownCertificate,
    /// Neither a token nor a client certificate.
    #[error(
        "no credentials: send \"authorization: Bearer TOKEN\" (or a client certificate the auth \
         file lists)"
    )]
    NoCredentials,
}

/// Why an authenticated caller may not do what it asked (PERMISSION_DENIED).
#[derive(Debug, thiserror::Error)]
pub enum PermissionDenied {
    /// The principal lacks the role the call needs.
    #[error("principal {principal:?} may not {action}: it lacks the role {role:?}")]
    MissingRole {
        /// The principal.
        principal: String,
        /// What it asked to do (`upload cases`, ...).
        action: String,
        /// The role it lacks.
        role: &'static str,
    },
    /// An upload of a case outside the cases the principal may use.
    #[error(
        "principal {principal:?} may not upload case {case_id:?}: it is outside the cases it may \
         use"
    )]
    CaseOutside {
        /// The principal.
        principal: String,
        /// The case it tried to upload.
        case_id: String,
    },
}

/// What a client did not send in time (DEADLINE_EXCEEDED).
#[derive(Debug, thiserror::Error)]
pub enum Deadline {
    /// An upload stream sent no message for `waited`.
    #[error("no upload message for {} s; nothing was stored", .waited.as_secs())]
    UploadIdle {
        /// How long the server waited.
        waited: Duration,
    },
    /// An upload arrived slower than the server's minimum rate.
    #[error(
        "upload: {received} bytes in {:.0} s, slower than the server's minimum of {min_per_s} bytes/s (min_upload_bytes_per_s); nothing was stored",
        .after.as_secs_f64()
    )]
    UploadSlow {
        /// Bytes received.
        received: u64,
        /// Since the upload started.
        after: Duration,
        /// The minimum rate, bytes/s.
        min_per_s: u64,
    },
}

/// What failed inside the server (INTERNAL); its text is the status message.
#[derive(Debug, thiserror::Error)]
pub enum Internal {
    /// A registration task panicked or was cancelled (logged; the message does not say more).
    #[error("the registration failed inside the server (logged); the session goes on")]
    RegistrationTask(#[source] JoinError),
    /// A blocking task of the server (storing an upload, deleting a case, reading a session
    /// record) panicked or was cancelled.
    #[error("{doing}: {source}")]
    Task {
        /// What it was doing (`storing the upload`, `deleting`, ...).
        doing: &'static str,
        /// How it ended.
        source: JoinError,
    },
    /// A mesh that passed its checks could not be written as VTU.
    #[error("writing the mesh: {0}")]
    MeshWrite(#[source] librplus::mesh::io::IoError),
    /// A recorded session cannot be replayed on resume.
    #[error("session {session_id}: its record cannot be replayed: {problem}")]
    Unreplayable {
        /// The session.
        session_id: String,
        /// What is wrong with its record.
        #[source]
        problem: Unreplayable,
    },
}

/// What is wrong with a recorded session that cannot be replayed.
#[derive(Debug, thiserror::Error)]
pub enum Unreplayable {
    /// The start message does not decode.
    #[error("start: {0}")]
    Start(#[source] prost::DecodeError),
    /// The first message is not a `SessionStart`.
    #[error("the first message is not a start")]
    NotAStart,
    /// A recorded message does not decode.
    #[error("message {seq}: {source}")]
    Decode {
        /// Its client_seq.
        seq: u64,
        /// The decoder's error.
        source: prost::DecodeError,
    },
    /// A recorded message is refused by the checks in force now.
    #[error("message {seq} is refused now: {refusal}")]
    Refused {
        /// Its client_seq.
        seq: u64,
        /// Why (its text is the refusal's status message).
        #[source]
        refusal: Box<ServiceError>,
    },
}

impl From<PipelineError> for ServiceError {
    fn from(e: PipelineError) -> Self {
        Self::Registration(e)
    }
}

impl From<Unavailable> for ServiceError {
    fn from(e: Unavailable) -> Self {
        Self::Unavailable(e)
    }
}

impl From<Unauthenticated> for ServiceError {
    fn from(e: Unauthenticated) -> Self {
        Self::Unauthenticated(e)
    }
}

impl From<PermissionDenied> for ServiceError {
    fn from(e: PermissionDenied) -> Self {
        Self::PermissionDenied(e)
    }
}

impl From<Deadline> for ServiceError {
    fn from(e: Deadline) -> Self {
        Self::Deadline(e)
    }
}

impl From<Internal> for ServiceError {
    fn from(e: Internal) -> Self {
        Self::Internal(e)
    }
}

/// The status message a client gets ([`ServiceError::parts`]).
impl std::fmt::Display for ServiceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.parts().1)
    }
}

impl std::error::Error for ServiceError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Registration(e) => Some(e),
            Self::Unavailable(e) => e.source(),
            Self::Unauthenticated(e) => e.source(),
            Self::PermissionDenied(e) => e.source(),
            Self::Deadline(e) => e.source(),
            Self::Internal(e) => e.source(),
            Self::InvalidArgument { .. }
            | Self::Precondition { .. }
            | Self::UnknownCase { .. }
            | Self::UnknownSession { .. }
            | Self::Quota { .. }
            | Self::Received { .. }
            | Self::TakenOver { .. } => None,
        }
    }
}

/// How a library error reaches the client.
enum Cause {
    /// The measurements break a rule: INVALID_ARGUMENT on `measurements`.
    Input,
    /// The measurements cannot determine a registration: FAILED_PRECONDITION, type `DATA`.
    Data,
    /// The case cannot run the method: FAILED_PRECONDITION, type `CASE`.
    Case,
    /// The server's own state or configuration: INTERNAL.
    Server,
}

fn register_cause(e: &RegisterError) -> Cause {
    match e {
        RegisterError::Measurements(_) => Cause::Input,
        RegisterError::FarFromModel { .. }
        | RegisterError::TooFewMatches { .. }
        | RegisterError::IllConditioned(_) => Cause::Data,
        RegisterError::Parameter(_)
        | RegisterError::Model(_)
        | RegisterError::Inconsistent(_)
        | RegisterError::BasisFile(_)
        | RegisterError::Fem(_)
        | RegisterError::Mesh(_)
        | RegisterError::Surface(_)
        | RegisterError::Npz(_)
        | RegisterError::File(_) => Cause::Server,
    }
}

fn pipeline_cause(e: &PipelineError) -> Cause {
    match e {
        PipelineError::Rigid(r)
        | PipelineError::Libr(r)
        | PipelineError::Refit(r)
        | PipelineError::Nonlinear(r) => register_cause(r),
        PipelineError::Degenerate { .. } => Cause::Data,
        PipelineError::NoBasis
        | PipelineError::NoAdaptiveBasis
        | PipelineError::NoModel
        | PipelineError::NoV2sModel => Cause::Case,
        PipelineError::Case(_)
        | PipelineError::Model(_)
        | PipelineError::V2s(_)
        | PipelineError::NoRefitIterations => Cause::Server,
    }
}

impl ServiceError {
    /// INVALID_ARGUMENT with violations.
    pub fn invalid(message: impl Into<String>, violations: Vec<(String, String)>) -> Self {
        Self::InvalidArgument {
            message: message.into(),
            violations,
        }
    }

    /// One invalid field.
    pub fn field(field: impl Into<String>, problem: impl Into<String>) -> Self {
        let (f, p) = (field.into(), problem.into());
        Self::invalid(format!("{f}: {p}"), vec![(f, p)])
    }

    /// A precondition on `subject` (a field or a case) that the request breaks.
    pub fn precondition(
        kind: &'static str,
        subject: impl Into<String>,
        description: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Self::Precondition {
            message: message.into(),
            kind,
            subject: subject.into(),
            description: description.into(),
        }
    }

    /// The gRPC code, message and details: the one mapping of every error to the wire.
    pub fn parts(&self) -> (Code, String, Option<ErrorDetails>) {
        let mut d = ErrorDetails::new();
        match self {
            Self::InvalidArgument {
                message,
                violations,
            } => {
                for (f, p) in violations {
                    d.add_bad_request_violation(f.clone(), p.clone());
                }
                (Code::InvalidArgument, message.clone(), Some(d))
            }
            Self::Precondition {
                message,
                kind,
                subject,
                description,
            } => {
                d.add_precondition_failure_violation(*kind, subject.clone(), description.clone());
                (Code::FailedPrecondition, message.clone(), Some(d))
            }
            Self::UnknownCase { field, id, known } => unknown_case(field, id, known, d),
            Self::UnknownSession { field, id } => {
                let id = short(id, 64);
                d.add_bad_request_violation(field.clone(), format!("no session {id:?}"));
                (
                    Code::NotFound,
                    format!("{field}: no recorded session {id:?} of yours to resume"),
                    Some(d),
                )
            }
            Self::Quota {
                message,
                subject,
                description,
            } => {
                d.add_quota_failure_violation(*subject, description.clone());
                (Code::ResourceExhausted, message.clone(), Some(d))
            }
            Self::Unavailable(e) => (Code::Unavailable, e.to_string(), None),
            Self::Unauthenticated(e) => (Code::Unauthenticated, e.to_string(), None),
            Self::PermissionDenied(e) => (Code::PermissionDenied, e.to_string(), None),
            Self::Deadline(e) => (Code::DeadlineExceeded, e.to_string(), None),
            Self::Received { code, message } => (*code, message.clone(), None),
            Self::Internal(e) => (Code::Internal, e.to_string(), None),
            Self::TakenOver { session_id } => taken_over(session_id, d),
            Self::Registration(e) => registration(e, d),
        }
    }

    /// The gRPC status code.
    pub fn code(&self) -> Code {
        self.parts().0
    }

    /// As a gRPC status with its `google.rpc` details.
    pub fn to_status(&self) -> Status {
        match self.parts() {
            (code, message, Some(details)) => Status::with_error_details(code, message, details),
            (code, message, None) => Status::new(code, message),
        }
    }

    /// As an in-stream rejection of message `client_seq`: the code's name, the message, and the
    /// fields concerned (BadRequest violations, or the subject of a precondition).
    pub fn to_rejection(&self, client_seq: u64) -> pb::Rejection {
        let (code, message, _) = self.parts();
        let violations = match self {
            Self::InvalidArgument { violations, .. } => violations.clone(),
            Self::Precondition {
                subject,
                description,
                ..
            } => vec![(subject.clone(), description.clone())],
            Self::UnknownCase { field, id, .. } => {
                vec![(field.clone(), format!("no case {:?}", short(id, 64)))]
            }
            Self::UnknownSession { field, id } => {
                vec![(field.clone(), format!("no session {:?}", short(id, 64)))]
            }
            Self::Quota { .. }
            | Self::Unavailable(_)
            | Self::Unauthenticated(_)
            | Self::PermissionDenied(_)
            | Self::Deadline(_)
            | Self::Received { .. }
            | Self::Internal(_)
            | Self::TakenOver { .. }
            | Self::Registration(_) => Vec::new(),
        };
        pb::Rejection {
            client_seq,
            code: librplus_proto::code_name(code).to_string(),
            message,
            violations: violations
                .into_iter()
                .map(|(field, description)| pb::FieldViolation { field, description })
                .collect(),
        }
    }
}

/// True when LIBR's failure leaves the rigid result as the best answer (the data, not the server,
/// stopped it): the result is then flagged DEGENERATE instead of failing the request.
pub fn libr_can_fall_back(e: &PipelineError) -> bool {
    match e {
        PipelineError::Degenerate { .. } => true,
        PipelineError::Libr(r) => r.is_data_limited(),
        PipelineError::Case(_)
        | PipelineError::Model(_)
        | PipelineError::Rigid(_)
        | PipelineError::Refit(_)
        | PipelineError::Nonlinear(_)
        | PipelineError::NoBasis
        | PipelineError::NoAdaptiveBasis
        | PipelineError::NoModel
        | PipelineError::NoV2sModel
        | PipelineError::V2s(_)
        | PipelineError::NoRefitIterations => false,
    }
}

/// A case the caller may not use or that does not exist: the id echoed (cut to 64 characters,
/// as every echo of a client's string) with the cases the caller may use (the first 20).
fn unknown_case(
    field: &str,
    id: &str,
    known: &[String],
    mut d: ErrorDetails,
) -> (Code, String, Option<ErrorDetails>) {
    let id = short(id, 64);
    let mut list = known
        .iter()
        .take(20)
        .cloned()
        .collect::<Vec<_>>()
        .join(", ");
    if known.len() > 20 {
        list.push_str(&format!(" and {} more", known.len() - 20));
    }
    d.add_bad_request_violation(field.to_string(), format!("no case {id:?}"));
    d.set_resource_info(
        "case",
        id.to_string(),
        "",
        format!("the cases you may use: {list}"),
    );
    (
        Code::NotFound,
        format!("{field}: no case {id:?} (the cases you may use: {list})"),
        Some(d),
    )
}

/// A stream whose session a newer stream (a resume of it) took over.
fn taken_over(session_id: &str, mut d: ErrorDetails) -> (Code, String, Option<ErrorDetails>) {
    d.set_error_info(
        TAKEN_OVER,
        "librplus.v1",
        std::collections::HashMap::from([("session_id".to_string(), session_id.to_string())]),
    );
    (
        Code::Aborted,
        format!(
            "session {session_id} was taken over by a newer stream (a resume of the \
             same session), which holds it now; this stream has ended and sends \
             nothing more"
        ),
        Some(d),
    )
}

/// A registration that failed, by cause: the measurements, the data, the case, or the server.
fn registration(e: &PipelineError, mut d: ErrorDetails) -> (Code, String, Option<ErrorDetails>) {
    match pipeline_cause(e) {
        Cause::Input => {
            d.add_bad_request_violation("measurements", e.to_string());
            (Code::InvalidArgument, format!("measurements: {e}"), Some(d))
        }
        Cause::Data => {
            d.add_precondition_failure_violation("DATA", "measurements", e.to_string());
            (
                Code::FailedPrecondition,
                format!("these measurements do not permit a registration: {e}"),
                Some(d),
            )
        }
        Cause::Case => {
            d.add_precondition_failure_violation("CASE", "method", e.to_string());
            (Code::FailedPrecondition, e.to_string(), Some(d))
        }
        Cause::Server => (
            Code::Internal,
            format!("the registration failed inside the server: {e}"),
            None,
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic_types::StatusExt;

    fn details(e: &ServiceError) -> (Code, tonic_types::ErrorDetails) {
        let s = e.to_status();
        (s.code(), s.get_error_details())
    }

    #[test]
    fn each_cause_has_its_code_and_details() {
        // Data the pipeline cannot register: FAILED_PRECONDITION with a DATA precondition.
        let far = ServiceError::Registration(PipelineError::Rigid(RegisterError::FarFromModel {
            far: 9,
            total: 10,
            cap_mm: 500.0,
            worst: 3,
            worst_mm: 1000.0,
        }));
        let (code, d) = details(&far);
        assert_eq!(code, Code::FailedPrecondition);
        let v = &d
            .precondition_failure()
            .expect("PreconditionFailure")
            .violations[0];
        assert_eq!(
            (v.r#type.as_str(), v.subject.as_str()),
            ("DATA", "measurements")
        );
        assert!(far.to_status().message().contains("wrong units"));
        // Bad measurements: INVALID_ARGUMENT with a BadRequest naming the field.
        let bad = ServiceError::Registration(PipelineError::Rigid(RegisterError::Measurements(
            "measurements.kind has 2 entries".into(),
        )));
        let (code, d) = details(&bad);
        assert_eq!(code, Code::InvalidArgument);
        assert_eq!(
            d.bad_request().expect("BadRequest").field_violations[0].field,
            "measurements"
        );
        // The case cannot run the method: FAILED_PRECONDITION, type CASE.
        let (code, d) = details(&ServiceError::Registration(PipelineError::NoModel));
        assert_eq!(code, Code::FailedPrecondition);
        assert_eq!(
            d.precondition_failure().unwrap().violations[0].r#type,
            "CASE"
        );
        // The server's own failures are INTERNAL, without details.
        let internal = ServiceError::Registration(PipelineError::Libr(
            RegisterError::Inconsistent("mesh has 3 nodes, the basis 4".into()),
        ));
        let (code, d) = details(&internal);
        assert_eq!(code, Code::Internal);
        assert!(d.precondition_failure().is_none() && d.bad_request().is_none());
        // Unknown case: NOT_FOUND with ResourceInfo and the field.
        let (code, d) = details(&ServiceError::UnknownCase {
            field: "case_id".into(),
            id: "nope".into(),
            known: vec!["a".into(), "b".into()],
        });
        assert_eq!(code, Code::NotFound);
        let r = d.resource_info().expect("ResourceInfo");
        assert_eq!(
            (r.resource_type.as_str(), r.resource_name.as_str()),
            ("case", "nope")
        );
        assert_eq!(
            d.bad_request().unwrap().field_violations[0].field,
            "case_id"
        );
        // Limits: RESOURCE_EXHAUSTED with QuotaFailure.
        let (code, d) = details(&ServiceError::Quota {
            message: "full".into(),
            subject: "sessions",
            description: "4 open".into(),
        });
        assert_eq!(code, Code::ResourceExhausted);
        assert_eq!(d.quota_failure().unwrap().violations[0].subject, "sessions");
    }

    #[test]
    fn only_data_limited_libr_failures_fall_back_to_rigid() {
        assert!(libr_can_fall_back(&PipelineError::Degenerate {
            reason: "one spot".into()
        }));
        assert!(libr_can_fall_back(&PipelineError::Libr(
            RegisterError::TooFewMatches { matched: 2 }
        )));
        assert!(!libr_can_fall_back(&PipelineError::Libr(
            RegisterError::Inconsistent("bug".into())
        )));
        assert!(!libr_can_fall_back(&PipelineError::NoBasis));
        assert!(!libr_can_fall_back(&PipelineError::Rigid(
            RegisterError::TooFewMatches { matched: 2 }
        )));
    }

    #[test]
    fn typed_reasons_keep_their_codes_and_messages() {
        let cases: Vec<(ServiceError, Code, &str)> = vec![
            (
                Unavailable::ShuttingDown.into(),
                Code::Unavailable,
                "the server is shutting down",
            ),
            (
                Unavailable::Preloading.into(),
                Code::Unavailable,
                "the server is still preloading its cases; retry when health reports SERVING",
            ),
            (
                Unavailable::Reloading {
                    field: "case_id".into(),
                    id: "c1".into(),
                    stage: "basis, 50 %".into(),
                }
                .into(),
                Code::Unavailable,
                "case_id: case \"c1\" was idle and left memory; it is being loaded again (basis, \
                 50 %); retry in a few seconds, or follow it with WatchCase",
            ),
            (
                Unavailable::AuditLog("disk full".into()).into(),
                Code::Unavailable,
                "the audit log cannot be written, so nothing is answered: disk full",
            ),
            (
                Unauthenticated::RepeatedHeader.into(),
                Code::Unauthenticated,
                "authorization: sent more than once; send exactly one \"Bearer TOKEN\"",
            ),
            (
                Unauthenticated::LongHeader {
                    len: 2000,
                    max: 1024,
                }
                .into(),
                Code::Unauthenticated,
                "authorization: longer than 1024 bytes",
            ),
            (
                Unauthenticated::UnknownCertificate.into(),
                Code::Unauthenticated,
                "the client certificate's subject is not in the auth file, and no authorization \
                 token was sent",
            ),
            (
                Unauthenticated::NoCredentials.into(),
                Code::Unauthenticated,
                "no credentials: send \"authorization: Bearer TOKEN\" (or a client certificate \
                 the auth file lists)",
            ),
            (
                PermissionDenied::MissingRole {
                    principal: "a".into(),
                    action: "upload cases".into(),
                    role: "manage",
                }
                .into(),
                Code::PermissionDenied,
                "principal \"a\" may not upload cases: it lacks the role \"manage\"",
            ),
            (
                PermissionDenied::CaseOutside {
                    principal: "a".into(),
                    case_id: "b/1".into(),
                }
                .into(),
                Code::PermissionDenied,
                "principal \"a\" may not upload case \"b/1\": it is outside the cases it may use",
            ),
            (
                Deadline::UploadIdle {
                    waited: Duration::from_secs(30),
                }
                .into(),
                Code::DeadlineExceeded,
                "no upload message for 30 s; nothing was stored",
            ),
            (
                Deadline::UploadSlow {
                    received: 12,
                    after: Duration::from_secs(10),
                    min_per_s: 65_536,
                }
                .into(),
                Code::DeadlineExceeded,
                "upload: 12 bytes in 10 s, slower than the server's minimum of 65536 bytes/s (min_upload_bytes_per_s); nothing was stored",
            ),
            (
                Internal::Unreplayable {
                    session_id: "s1-2".into(),
                    problem: Unreplayable::Refused {
                        seq: 3,
                        refusal: Box::new(ServiceError::field("surface.xyz_mm", "is empty")),
                    },
                }
                .into(),
                Code::Internal,
                "session s1-2: its record cannot be replayed: message 3 is refused now: \
                 surface.xyz_mm: is empty",
            ),
        ];
        for (e, code, message) in cases {
            let s = e.to_status();
            assert_eq!((s.code(), s.message()), (code, message));
            assert_eq!(e.to_string(), message);
        }
        // The cause stays reachable.
        let e = ServiceError::from(Internal::Unreplayable {
            session_id: "s1-2".into(),
            problem: Unreplayable::NotAStart,
        });
        let source = std::error::Error::source(&e).expect("a source");
        assert!(matches!(
            source.downcast_ref::<Unreplayable>(),
            Some(Unreplayable::NotAStart)
        ));
    }

    #[test]
    fn rejections_carry_the_code_name_and_the_field() {
        let r = ServiceError::precondition("ORDER", "client_seq", "must be greater than 3", "dup")
            .to_rejection(3);
        assert_eq!(r.code, "FAILED_PRECONDITION");
        assert_eq!(r.violations[0].field, "client_seq");
        let r = ServiceError::field("surface.xyz_mm[4]", "is not finite").to_rejection(5);
        assert_eq!((r.client_seq, r.code.as_str()), (5, "INVALID_ARGUMENT"));
        assert_eq!(r.violations[0].field, "surface.xyz_mm[4]");
    }
}
