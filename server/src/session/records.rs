//! What the audit log keeps of registrations and sessions: the record of a registration (unary
//! or streamed), the event of a rejected message, and writing a session's records through its
//! stream's lease (only while that stream holds the session).

use crate::audit::{Record, RegistrationRecord};
use crate::error::{ServiceError, short};
use crate::shared::Shared;
use librplus_proto::v1 as pb;

/// The audit record of a registration.
pub(crate) fn audit_record(
    reg: &pb::Registration,
    principal: &str,
    case_id: &str,
    session_id: Option<&str>,
    client_seq: u64,
) -> RegistrationRecord {
    use prost::Message;
    RegistrationRecord {
        principal: principal.to_string(),
        case_id: case_id.to_string(),
        session_id: session_id.map(str::to_string),
        client_seq,
        method: reg.method_used().as_str_name().to_string(),
        quality: reg.quality().as_str_name().to_string(),
        quality_reason: reg.quality_reason.clone(),
        total_ms: reg.timings.as_ref().map_or(0.0, |t| t.total_ms),
        residual_rms_mm: reg.residual_rms_mm,
        points_total: reg.points_used as u64,
        measurements: None,
        answer_sha256: crate::auth::hex(&crate::auth::sha256(&reg.encode_to_vec())),
        timings: reg
            .timings
            .as_ref()
            .map(|t| {
                serde_json::json!({
                    "queue_ms": t.queue_ms, "rigid_ms": t.rigid_ms, "libr_ms": t.libr_ms,
                    "gcn_ms": t.gcn_ms, "refit_ms": t.refit_ms, "total_ms": t.total_ms,
                    "libr_iterations": t.libr_iterations, "refit_iterations": t.refit_iterations,
                })
                .to_string()
            })
            .unwrap_or_default(),
        choice: reg.choice.as_ref().map(|c| {
            serde_json::json!({
                "chosen": c.chosen, "best_scoring": c.best_scoring, "runner_up": c.runner_up,
                "margin_mm2": c.margin_mm2, "margin_se": c.margin_se,
                "runner_up_mm": c.runner_up_mm,
                "candidates": c.candidates.iter().map(|k| serde_json::json!({
                    "name": k.name, "held_out_mm2": k.held_out_mm2, "failed": k.failed,
                })).collect::<Vec<_>>(),
            })
            .to_string()
        }),
        surface: reg.surface.as_ref().map(|s| {
            serde_json::json!({
                "target": s.target, "anterior_mm2": s.anterior_mm2,
                "boundary_mm2": s.boundary_mm2,
            })
            .to_string()
        }),
    }
}

/// The audit event of a message (or registration) the session answered with a rejection.
pub(crate) fn rejected_event(
    principal: &str,
    case_id: &str,
    session_id: &str,
    r: &pb::Rejection,
) -> Record {
    Record::Event {
        kind: "rejected",
        principal: principal.to_string(),
        case_id: Some(case_id.to_string()),
        session_id: Some(session_id.to_string()),
        detail: serde_json::json!({
            "client_seq": r.client_seq,
            "code": r.code,
            "message": short(&r.message, 300),
        }),
    }
}

/// Writes a session's records through its stream's lease: only while the stream holds the
/// session (TakenOver otherwise), and never while a resume reads them.
pub(crate) async fn lease_record(
    shared: &Shared,
    lease: &crate::live::Lease,
    sid: &str,
    records: Vec<Record>,
) -> Result<(), ServiceError> {
    match lease.record(shared.record(records)).await {
        Ok(r) => r,
        Err(crate::live::TakenOver) => Err(ServiceError::TakenOver {
            session_id: sid.to_string(),
        }),
    }
}
