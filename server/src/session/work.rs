//! What a session asks of the compute engine: a registration of all its points with its current
//! model (plain, or augmented by discovery), and the start of an in-surgery discovery run.

use super::state::Session;
use crate::shared::{Shared, count_error};
use librplus::pipeline::Method;
use librplus_proto::v1 as pb;
use std::time::Instant;
use tokio::sync::mpsc::UnboundedSender;

/// Registers every point of the session with its current model; the update to send.
/// METHOD_NONLINEAR's linear answer goes to `first` before its refinement runs.
pub(crate) async fn register_session(
    shared: &Shared,
    s: &Session,
    (arrival, deadline): (Instant, Option<Instant>),
    seq: u64,
    first: Option<UnboundedSender<pb::Registration>>,
) -> pb::stream_update::Update {
    if s.measurements().points.is_empty() {
        // Nothing measured yet (an ultrasound frame in which nothing was found): the answer is
        // the starting pose, flagged, as the proto promises.
        let prepared = s.prepared();
        let n = prepared.model.mesh.num_nodes();
        let pose = s.measurements().initial_alignment.unwrap_or_default();
        let omit = s.options().omit_displacements;
        return pb::stream_update::Update::Registration(pb::Registration {
            image_to_physical: Some(crate::convert::rigid_to_pb(&pose)),
            displacement_mm: if omit { Vec::new() } else { vec![0.0; 3 * n] },
            node_count: n as u32,
            method_used: crate::convert::method_to_pb(Method::Rigid) as i32,
            quality: pb::Quality::Degenerate as i32,
            quality_reason: "the session holds no points yet: the initial alignment (identity \
                             when none was given) is the answer"
                .into(),
            effects: crate::convert::effects(prepared),
            timings: Some(pb::StageTimings {
                total_ms: arrival.elapsed().as_secs_f64() * 1e3,
                ..Default::default()
            }),
            ..Default::default()
        });
    }
    s.case().touch();
    let mut job = s.job(arrival, deadline);
    job.first = first;
    match shared.engine.run(job, None).await {
        Ok(r) => pb::stream_update::Update::Registration(r),
        Err(b) => {
            count_error(b.code());
            pb::stream_update::Update::Rejection(b.to_rejection(seq))
        }
    }
}

/// Starts a discovery run on the session's points (the caller checked it may); the update that
/// says so, or why it could not start.
pub(crate) fn start_discovery(
    shared: &Shared,
    s: &mut Session,
    seq: u64,
) -> pb::stream_update::Update {
    let Some(req) = s.discovery_request(shared.config.discovery_coarse, seq) else {
        // `accept` refuses `discover` when the session did not opt in; kept as a report.
        return pb::stream_update::Update::Discovery(pb::DiscoveryReport {
            client_seq: seq,
            state: pb::DiscoveryState::Failed as i32,
            message: "discover: this session did not opt in to discovery".into(),
            ..Default::default()
        });
    };
    let n = req.measurements.points.len();
    if n < crate::discovery::MIN_POINTS {
        let mut r = crate::discovery::started(&req);
        r.state = pb::DiscoveryState::Failed as i32;
        r.message = format!(
            "discover: the session holds {n} points; discovery needs at least {}",
            crate::discovery::MIN_POINTS
        );
        return pb::stream_update::Update::Discovery(r);
    }
    tracing::info!(points = n, client_seq = seq, "discovery started");
    let report = crate::discovery::started(&req);
    s.start_discovery(crate::discovery::spawn(req));
    pb::stream_update::Update::Discovery(report)
}
