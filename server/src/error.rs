//! Every way a request can fail, and the one place that turns each into a gRPC status with the
//! `google.rpc` details the proto promises (BadRequest, PreconditionFailure, ResourceInfo,
//! QuotaFailure) or an in-stream rejection.

use librplus::pipeline::PipelineError;
use librplus::register::RegisterError;
use librplus_proto::v1 as pb;
use tonic::{Code, Status};
use tonic_types::{ErrorDetails, StatusExt};

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
    Unavailable(String),
    /// No credentials, or credentials the server does not know (UNAUTHENTICATED).
    Unauthenticated(String),
    /// Known credentials without the role the call needs (PERMISSION_DENIED).
    PermissionDenied(String),
    /// The client did not send in time (DEADLINE_EXCEEDED).
    Deadline(String),
    /// A status from the transport (a message too large, a reset stream), passed on.
    Received {
        /// Its code.
        code: Code,
        /// Its message.
        message: String,
    },
    /// The pipeline refused or failed; mapped by cause in [`ServiceError::parts`].
    Registration(PipelineError),
    /// A registration task failed inside the server (INTERNAL; logged).
    Internal(String),
    /// The stream's session was taken over by a newer stream, a resume of the same session
    /// (ABORTED, ErrorInfo reason [`TAKEN_OVER`]): this stream has ended.
    TakenOver {
        /// The session.
        session_id: String,
    },
}

impl From<PipelineError> for ServiceError {
    fn from(e: PipelineError) -> Self {
        Self::Registration(e)
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
        PipelineError::Rigid(r) | PipelineError::Libr(r) | PipelineError::Refit(r) => {
            register_cause(r)
        }
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
            Self::UnknownCase { field, id, known } => {
                // The id echoed is cut to 64 characters (as every echo of a client's string);
                // the list to the first 20.
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
                d.add_bad_request_violation(field.clone(), format!("no case {id:?}"));
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
            Self::Unavailable(m) => (Code::Unavailable, m.clone(), None),
            Self::Unauthenticated(m) => (Code::Unauthenticated, m.clone(), None),
            Self::PermissionDenied(m) => (Code::PermissionDenied, m.clone(), None),
            Self::Deadline(m) => (Code::DeadlineExceeded, m.clone(), None),
            Self::Received { code, message } => (*code, message.clone(), None),
            Self::Internal(m) => (Code::Internal, m.clone(), None),
            Self::TakenOver { session_id } => {
                d.set_error_info(
                    TAKEN_OVER,
                    "librplus.v1",
                    std::collections::HashMap::from([(
                        "session_id".to_string(),
                        session_id.clone(),
                    )]),
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
            Self::Registration(e) => match pipeline_cause(e) {
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
            },
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
        | PipelineError::NoBasis
        | PipelineError::NoAdaptiveBasis
        | PipelineError::NoModel
        | PipelineError::NoV2sModel
        | PipelineError::V2s(_)
        | PipelineError::NoRefitIterations => false,
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
