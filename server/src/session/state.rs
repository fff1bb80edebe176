//! A streamed session's state and the checks every message passes: the start (case, method,
//! options, discovery), then each surface batch, ultrasound plane or discovery request, whose
//! points join the session only when every field holds. Also the request options shared with
//! unary `Register` (time budget, method, trusted alignment).

use crate::auth::Principal;
use crate::cases::Case;
use crate::config::ServerConfig;
use crate::convert::{features, method_from_pb, plane_points, points3, rigid_from_pb};
use crate::error::ServiceError;
use crate::shared::Shared;
use librplus::pipeline::Method;
use librplus::register::{MeasuredKind, Measurements};
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::time::Duration;

/// Session state after a valid start.
pub(crate) struct Session {
    pub case: Arc<Case>,
    pub method: Method,
    pub budget: Duration,
    pub omit: bool,
    pub trusted_alignment_mm: Option<f64>,
    /// The client said the organ is held (`RegisterOptions.held`).
    pub held: bool,
    pub meas: Arc<Measurements>,
    pub last_seq: u64,
    pub last_time: Option<(i64, i32)>,
    /// In-surgery discovery, when the session opted in.
    pub discovery: Option<DiscoveryPlan>,
    /// The running discovery's outcome.
    pub pending: Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>>,
    /// The session's augmented model, once discovery switched to one.
    pub augmented: Option<Arc<librplus::pipeline::Prepared>>,
}

/// A session's discovery settings.
pub(crate) struct DiscoveryPlan {
    pub budget: Duration,
    /// Run automatically at this many points (0: only when asked).
    pub auto_at: usize,
}

/// What an accepted message asks for.
pub(crate) enum Accepted {
    /// Points were added.
    Points,
    /// A discovery run.
    Discover,
}

/// The time budget of a request's options (`field`: where they are); the server's default
/// when 0 or absent, INVALID_ARGUMENT above its limit.
pub(crate) fn budget(
    config: &ServerConfig,
    options: Option<&pb::RegisterOptions>,
    field: &str,
) -> Result<Duration, ServiceError> {
    // Every field of the options; `omit_displacements`, `trusted_alignment_mm` and `held`
    // are read by the caller.
    let ms = options.map_or(
        0,
        |pb::RegisterOptions {
             time_budget_ms,
             omit_displacements: _,
             trusted_alignment_mm: _,
             held: _,
         }| *time_budget_ms,
    );
    if ms > config.max_time_budget_ms {
        return Err(ServiceError::field(
            format!("{field}.time_budget_ms"),
            format!(
                "{ms} ms is above the server's limit of {} ms",
                config.max_time_budget_ms
            ),
        ));
    }
    let ms = if ms == 0 { config.time_budget_ms } else { ms };
    Ok(Duration::from_millis(ms as u64))
}

/// The method a request asks of `case` (`field`: where it is), checked against what the case
/// was prepared for.
pub(crate) fn check_method(case: &Case, m: i32, field: &str) -> Result<Method, ServiceError> {
    let method = method_from_pb(
        m,
        case.default_method,
        case.prepared.librplus.is_some(),
        case.prepared.v2s.is_some(),
        field,
    )?;
    if method == Method::Adaptive && case.prepared.adaptive.is_none() {
        return Err(ServiceError::precondition(
            "CASE",
            field,
            format!(
                "case {} was prepared without adaptive LIBR's basis (the server's adaptive setting is off)",
                case.id
            ),
            format!("{field}: case {} has no adaptive LIBR basis", case.id),
        ));
    }
    if matches!(method, Method::Libr | Method::LibrPlus | Method::Auto)
        && case.prepared.basis.is_none()
    {
        return Err(ServiceError::precondition(
            "CASE",
            field,
            format!("case {} has no LIBR basis: only METHOD_RIGID", case.id),
            format!("{field}: case {} has no LIBR basis", case.id),
        ));
    }
    Ok(method)
}

/// The options' trusted-alignment uncertainty: None when 0 or absent; an error naming the field
/// when negative or not finite.
pub(crate) fn trusted(
    options: Option<&pb::RegisterOptions>,
    field: &str,
) -> Result<Option<f64>, ServiceError> {
    let v = options.map_or(0.0, |o| o.trusted_alignment_mm);
    if !(v.is_finite() && v >= 0.0) {
        return Err(ServiceError::field(
            format!("{field}.trusted_alignment_mm"),
            format!(
                "{} must be finite and ≥ 0 (mm; 0: fitted freely)",
                crate::convert::num(v)
            ),
        ));
    }
    Ok((v > 0.0).then_some(v))
}

/// A new session from its start message (`seq`: the start's client_seq).
pub(crate) fn start_session(
    shared: &Arc<Shared>,
    who: &Principal,
    start: &pb::SessionStart,
    seq: u64,
) -> Result<Session, ServiceError> {
    let pb::SessionStart {
        case_id,
        method,
        options,
        initial_alignment,
        discovery,
        resume_session_id: _, // handled by the caller
    } = start;
    check_seq_range(seq, "client_seq")?;
    let case = crate::access::case(shared, case_id, "start.case_id", who)?;
    let method = check_method(&case, *method, "start.method")?;
    let budget = budget(&shared.config, options.as_ref(), "start.options")?;
    let trusted_alignment_mm = trusted(options.as_ref(), "start.options")?;
    let initial = initial_alignment
        .as_ref()
        .map(|r| rigid_from_pb(r, "start.initial_alignment"))
        .transpose()?;
    let discovery = discovery_plan(&shared.config, &case, discovery.as_ref())?;
    Ok(Session {
        case,
        method,
        budget,
        omit: options.as_ref().is_some_and(|o| o.omit_displacements),
        trusted_alignment_mm,
        held: options.as_ref().is_some_and(|o| o.held),
        meas: Arc::new(Measurements {
            initial_alignment: initial,
            ..Default::default()
        }),
        last_seq: seq,
        last_time: None,
        discovery,
        pending: None,
        augmented: None,
    })
}

/// The start's discovery options: None when the session did not opt in.
fn discovery_plan(
    c: &ServerConfig,
    case: &Case,
    options: Option<&pb::DiscoveryOptions>,
) -> Result<Option<DiscoveryPlan>, ServiceError> {
    match options {
        Some(pb::DiscoveryOptions {
            enabled: true,
            budget_ms,
            auto_after_points,
        }) => {
            if *budget_ms > c.max_discovery_budget_ms {
                return Err(ServiceError::field(
                    "start.discovery.budget_ms",
                    format!(
                        "{budget_ms} ms is above the server's limit of {} ms",
                        c.max_discovery_budget_ms
                    ),
                ));
            }
            if case.prepared.basis.is_none() {
                return Err(ServiceError::precondition(
                    "CASE",
                    "start.discovery.enabled",
                    format!("case {} has no LIBR basis", case.id),
                    format!(
                        "start.discovery.enabled: case {} has no LIBR basis to discover with",
                        case.id
                    ),
                ));
            }
            let ms = if *budget_ms == 0 {
                c.discovery_budget_ms
            } else {
                *budget_ms
            };
            Ok(Some(DiscoveryPlan {
                budget: Duration::from_millis(ms as u64),
                auto_at: *auto_after_points as usize,
            }))
        }
        Some(pb::DiscoveryOptions {
            enabled: false,
            budget_ms,
            auto_after_points,
        }) if *budget_ms != 0 || *auto_after_points != 0 => Err(ServiceError::field(
            "start.discovery.enabled",
            "is false while budget_ms or auto_after_points is set: set enabled to opt in",
        )),
        _ => Ok(None),
    }
}

/// A message's acquisition time, checked: nanoseconds in range, never before the previous
/// message's.
fn check_time(
    s: &Session,
    t: Option<&prost_types::Timestamp>,
    field: &str,
) -> Result<Option<(i64, i32)>, ServiceError> {
    let Some(t) = t else {
        return Ok(None);
    };
    if !(0..1_000_000_000).contains(&t.nanos) {
        return Err(ServiceError::field(
            format!("{field}.nanos"),
            format!("{} is outside 0..1e9", t.nanos),
        ));
    }
    let now = (t.seconds, t.nanos);
    if let Some(last) = s.last_time
        && now < last
    {
        return Err(ServiceError::precondition(
            "ORDER",
            field,
            "goes back in time",
            format!(
                "{field}: {}.{:09} s is before the previous message's {}.{:09} s (out-of-order frame)",
                now.0, now.1, last.0, last.1
            ),
        ));
    }
    Ok(Some(now))
}

/// A message's points: (positions, kinds, salient features, acquisition time).
type MessagePoints = (
    Vec<[f64; 3]>,
    Vec<MeasuredKind>,
    Vec<u8>,
    Option<(i64, i32)>,
);

/// Checks one message and adds its points to the session.
pub(crate) fn accept(
    s: &mut Session,
    m: pb::StreamRegisterRequest,
    cfg: &ServerConfig,
) -> Result<Accepted, ServiceError> {
    use pb::stream_register_request::Msg;
    let pb::StreamRegisterRequest {
        client_seq: seq,
        msg,
    } = m;
    check_seq(s, seq)?;
    s.last_seq = seq;
    let (points, kinds, feature, time) = match msg {
        None => {
            return Err(ServiceError::field(
                "msg",
                "is empty: set start, surface, ultrasound or discover",
            ));
        }
        Some(Msg::Discover(pb::DiscoverNow {})) => return discover_asked(s),
        Some(Msg::Start(_)) => {
            return Err(ServiceError::precondition(
                "SESSION",
                "start",
                "only the first message may start",
                "start: the session has already started",
            ));
        }
        Some(Msg::Surface(b)) => surface_points(s, b, cfg)?,
        Some(Msg::Ultrasound(u)) => {
            let time = check_time(s, u.acquired_at.as_ref(), "ultrasound.acquired_at")?;
            let (c, v) = plane_points(&u, cfg.max_points_per_message)?;
            let mut k = vec![MeasuredKind::PosteriorContour; c.len()];
            k.extend(std::iter::repeat_n(MeasuredKind::Vessel, v.len()));
            let n = k.len();
            let mut p = c;
            p.extend(v);
            (p, k, vec![0; n], time)
        }
    };
    let total = s.meas.points.len() + points.len();
    if total > cfg.max_points_per_session {
        return Err(ServiceError::Quota {
            message: format!(
                "the session would hold {total} points, above the server's limit of {}",
                cfg.max_points_per_session
            ),
            subject: "points_per_session",
            description: format!(
                "at most {} points in one session; start a new session",
                cfg.max_points_per_session
            ),
        });
    }
    if let Some(t) = time {
        s.last_time = Some(t);
    }
    append(&mut s.meas, points, kinds, feature);
    Ok(Accepted::Points)
}

/// Appends a message's points to a session's measurements. The registrations that shared them
/// have let go of them (a session awaits its registrations), so they grow in place; only a
/// discovery run still going keeps its snapshot, and the session then continues on a copy.
fn append(
    meas: &mut Arc<Measurements>,
    points: Vec<[f64; 3]>,
    kinds: Vec<MeasuredKind>,
    feature: Vec<u8>,
) {
    let meas = Arc::make_mut(meas);
    meas.points.extend(points);
    meas.kind.extend(kinds);
    meas.feature.extend(feature);
}

/// The largest `client_seq` a session takes: the audit log and the session journal keep it as a
/// signed 64-bit integer (SQLite's INTEGER), so a larger one could be answered but not replayed.
pub(crate) const MAX_CLIENT_SEQ: u64 = i64::MAX as u64;

/// A `client_seq` the log can keep (at most [`MAX_CLIENT_SEQ`]); `field`: where it was sent.
pub(crate) fn check_seq_range(seq: u64, field: &str) -> Result<(), ServiceError> {
    if seq <= MAX_CLIENT_SEQ {
        return Ok(());
    }
    Err(ServiceError::field(
        field,
        format!("is {seq}, above the largest the server records ({MAX_CLIENT_SEQ} = 2^63 - 1)"),
    ))
}

/// `client_seq` must grow from message to message, within what the log can keep.
fn check_seq(s: &Session, seq: u64) -> Result<(), ServiceError> {
    check_seq_range(seq, "client_seq")?;
    if seq > s.last_seq {
        return Ok(());
    }
    Err(ServiceError::precondition(
        "ORDER",
        "client_seq",
        format!("must be greater than {}", s.last_seq),
        if seq == s.last_seq {
            format!("client_seq {seq}: duplicate of the previous message")
        } else {
            format!(
                "client_seq {seq}: out of order (the session is at {})",
                s.last_seq
            )
        },
    ))
}

/// A `discover` message: taken when the session opted in and no run is in progress.
fn discover_asked(s: &Session) -> Result<Accepted, ServiceError> {
    if s.discovery.is_none() {
        return Err(ServiceError::precondition(
            "SESSION",
            "discover",
            "the session did not opt in",
            "discover: this session did not opt in to discovery (start.discovery.enabled)",
        ));
    }
    if s.pending.is_some() {
        return Err(ServiceError::precondition(
            "SESSION",
            "discover",
            "a discovery run is in progress",
            "discover: a discovery run is already in progress; its report will follow",
        ));
    }
    Ok(Accepted::Discover)
}

/// A surface batch's points, checked.
fn surface_points(
    s: &Session,
    b: pb::SurfaceBatch,
    cfg: &ServerConfig,
) -> Result<MessagePoints, ServiceError> {
    let pb::SurfaceBatch {
        acquired_at,
        xyz_mm,
        feature,
    } = b;
    let time = check_time(s, acquired_at.as_ref(), "surface.acquired_at")?;
    let p = points3(&xyz_mm, "surface.xyz_mm", cfg.max_points_per_message)?;
    if p.is_empty() {
        return Err(ServiceError::field("surface.xyz_mm", "is empty: no points"));
    }
    let f = features(&feature, p.len(), "surface.feature")?;
    let k = vec![MeasuredKind::Surface; p.len()];
    Ok((p, k, f, time))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A registration shares the session's measurements and lets go of them: the next message
    /// appends to the same allocation (nothing copied), and a snapshot still held (a discovery
    /// run) keeps the points it was given.
    #[test]
    fn updates_share_the_session_s_measurements_without_copying_them() {
        let mut meas = Arc::new(Measurements::default());
        let at = Arc::as_ptr(&meas);
        for k in 0..50 {
            let job = meas.clone();
            assert!(Arc::ptr_eq(&job, &meas));
            drop(job);
            append(
                &mut meas,
                vec![[k as f64, 0.0, 0.0]; 10],
                vec![MeasuredKind::Surface; 10],
                vec![0; 10],
            );
            assert_eq!(
                Arc::as_ptr(&meas),
                at,
                "message {k} copied the measurements"
            );
        }
        assert_eq!(meas.points.len(), 500);
        let snapshot = meas.clone();
        append(
            &mut meas,
            vec![[1.0; 3]],
            vec![MeasuredKind::Vessel],
            vec![0],
        );
        assert_eq!((snapshot.points.len(), meas.points.len()), (500, 501));
        assert_eq!(meas.kind[500], MeasuredKind::Vessel);
        assert_eq!(meas.feature.len(), 501);
    }
}
