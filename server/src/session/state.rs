//! A streamed session's state and the checks every message passes: the start (case, method,
//! options, discovery), then each surface batch, ultrasound plane or discovery request, whose
//! points join the session only when every field holds. Also the request options shared with
//! unary `Register` (time budget, method, trusted alignment).

use crate::auth::Principal;
use crate::cases::Case;
use crate::compute::{Job, Options, Request};
use crate::config::ServerConfig;
use crate::convert::{features, method_from_pb, plane_points, points3, rigid_from_pb};
use crate::error::ServiceError;
use crate::shared::Shared;
use librplus::pipeline::Method;
use librplus::register::{Checked, MeasuredKind};
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Session state after a valid start. Changed only through its methods: [`accept`] (a message),
/// [`Session::replayed`] (a resumed session's discovery message), [`Session::start_discovery`],
/// [`Session::switch_to`] (discovery's model) and [`Session::swap_to_own_basis`].
pub(crate) struct Session {
    case: Arc<Case>,
    /// The start's method and options, and every point accepted so far.
    request: Request,
    last_seq: u64,
    last_time: Option<(i64, i32)>,
    /// In-surgery discovery, when the session opted in.
    discovery: Option<DiscoveryPlan>,
    /// The running discovery's outcome.
    pending: Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>>,
    /// The session's augmented model, once discovery switched to one.
    augmented: Option<Arc<librplus::pipeline::Prepared>>,
}

impl Session {
    /// The session's case.
    pub fn case(&self) -> &Arc<Case> {
        &self.case
    }

    /// Every point accepted so far.
    pub fn measurements(&self) -> &Checked {
        &self.request.measurements
    }

    /// The start's method.
    pub fn method(&self) -> Method {
        self.request.method
    }

    /// The start's options.
    pub fn options(&self) -> Options {
        self.request.options
    }

    /// The last accepted message's `client_seq`.
    pub fn last_seq(&self) -> u64 {
        self.last_seq
    }

    /// The model the session registers with: discovery's augmented one, or the case's.
    pub fn prepared(&self) -> &librplus::pipeline::Prepared {
        self.augmented.as_deref().unwrap_or(&self.case.prepared)
    }

    /// A registration of every point with the session's current model, arriving at `arrival`,
    /// within the session's budget and the client's `deadline`.
    pub fn job(&self, arrival: Instant, deadline: Option<Instant>) -> Job {
        let mut request = self.request.clone();
        if let Some(d) = deadline {
            request.options.budget = request
                .options
                .budget
                .min(d.saturating_duration_since(arrival));
        }
        Job {
            case: self.case.clone(),
            request,
            arrival,
            prepared: self.augmented.clone(),
            first: None,
        }
    }

    /// A resumed session's replayed discovery message: it counts, but is not run again.
    pub fn replayed(&mut self, seq: u64) {
        self.last_seq = seq;
    }

    /// Whether an automatic discovery run is due: none is under way, and the session grew to
    /// its threshold.
    pub fn discovery_due(&self) -> bool {
        let n = self.request.measurements.points.len();
        self.pending.is_none()
            && self
                .discovery
                .as_ref()
                .is_some_and(|d| d.auto_at > 0 && n >= d.auto_at)
    }

    /// The running discovery's outcome, when there is one (the session keeps waiting on it).
    pub fn pending_mut(
        &mut self,
    ) -> &mut Option<tokio::sync::oneshot::Receiver<crate::discovery::Outcome>> {
        &mut self.pending
    }

    /// A discovery run on the session's points, with its settings: None when the session did
    /// not opt in. The next automatic run is moved to when the session has grown by half.
    pub fn discovery_request(
        &mut self,
        coarse: bool,
        seq: u64,
    ) -> Option<crate::discovery::Request> {
        let plan = self.discovery.as_mut()?;
        let n = self.request.measurements.points.len();
        if plan.auto_at > 0 {
            plan.auto_at = plan.auto_at.max(n + n / 2);
        }
        Some(crate::discovery::Request {
            case: self.case.clone(),
            measurements: self.request.measurements.clone(),
            trusted_alignment_mm: self.request.options.trusted_alignment_mm,
            held: self.request.options.held,
            budget: plan.budget,
            coarse,
            client_seq: seq,
        })
    }

    /// A discovery run was started; its outcome arrives on `rx`.
    pub fn start_discovery(
        &mut self,
        rx: tokio::sync::oneshot::Receiver<crate::discovery::Outcome>,
    ) {
        self.pending = Some(rx);
    }

    /// A session on a coarse case takes the case's own basis once it is ready
    /// ([`Case::full`]); the case it took, when it did.
    pub fn swap_to_own_basis(&mut self) -> Option<Arc<Case>> {
        let full = self.case.full.get()?.clone();
        self.case = full.clone();
        Some(full)
    }

    /// Discovery's augmented model replaces the session's.
    pub fn switch_to(&mut self, prepared: Arc<librplus::pipeline::Prepared>) {
        self.augmented = Some(prepared);
    }
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

/// A request's options (`field`: where they are), checked: the budget, the trusted alignment,
/// whether to leave the displacements out and whether the organ is held.
pub(crate) fn options(
    config: &ServerConfig,
    options: Option<&pb::RegisterOptions>,
    field: &str,
) -> Result<Options, ServiceError> {
    Ok(Options {
        budget: budget(config, options, field)?,
        omit_displacements: options.is_some_and(|o| o.omit_displacements),
        trusted_alignment_mm: trusted(options, field)?,
        held: options.is_some_and(|o| o.held),
        single_answer: options.is_some_and(|o| o.single_answer),
    })
}

/// The time budget of a request's options (`field`: where they are); the server's default
/// when 0 or absent, INVALID_ARGUMENT above its limit.
fn budget(
    config: &ServerConfig,
    options: Option<&pb::RegisterOptions>,
    field: &str,
) -> Result<Duration, ServiceError> {
    // Every field of the options; `omit_displacements`, `trusted_alignment_mm` and `held`
    // are read by [`options`].
    let ms = options.map_or(
        0,
        |pb::RegisterOptions {
             time_budget_ms,
             omit_displacements: _,
             trusted_alignment_mm: _,
             held: _,
             single_answer: _,
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
    // A case serving from a coarse basis gets adaptive LIBR's with its own.
    if method == Method::Adaptive && case.prepared.adaptive.is_none() && case.coarse.is_none() {
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
fn trusted(
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
    let options = self::options(&shared.config, options.as_ref(), "start.options")?;
    let initial = initial_alignment
        .as_ref()
        .map(|r| rigid_from_pb(r, "start.initial_alignment"))
        .transpose()?;
    let discovery = discovery_plan(&shared.config, &case, discovery.as_ref())?;
    let measurements = Checked::empty(initial)
        .map_err(|e| ServiceError::field("start.initial_alignment", e.to_string()))?;
    Ok(Session {
        case,
        request: Request {
            measurements,
            method,
            options,
        },
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
    let total = s.request.measurements.points.len() + points.len();
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
    append(&mut s.request.measurements, points, kinds, feature)?;
    Ok(Accepted::Points)
}

/// Appends a message's points to a session's measurements ([`Checked::append`]: only the new
/// points are checked). The registrations that shared them have let go of them (a session awaits
/// its registrations), so they grow in place; only a discovery run still going keeps its
/// snapshot, and the session then continues on a copy.
fn append(
    meas: &mut Checked,
    points: Vec<[f64; 3]>,
    kinds: Vec<MeasuredKind>,
    feature: Vec<u8>,
) -> Result<(), ServiceError> {
    meas.append(points, kinds, feature)
        .map_err(|e| ServiceError::field("msg", e.to_string()))
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
        let mut meas = Checked::empty(None).unwrap();
        let at = Arc::as_ptr(meas.shared());
        for k in 0..50 {
            let job = meas.clone();
            assert!(Arc::ptr_eq(job.shared(), meas.shared()));
            drop(job);
            append(
                &mut meas,
                vec![[k as f64, 0.0, 0.0]; 10],
                vec![MeasuredKind::Surface; 10],
                vec![0; 10],
            )
            .unwrap();
            assert_eq!(
                Arc::as_ptr(meas.shared()),
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
        )
        .unwrap();
        assert_eq!((snapshot.points.len(), meas.points.len()), (500, 501));
        assert_eq!(meas.kind[500], MeasuredKind::Vessel);
        assert_eq!(meas.feature.len(), 501);
    }
}
