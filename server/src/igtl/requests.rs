//! The OpenIGTLink messages a peer sends, as the requests of its registration session: `POINT`
//! a `SurfaceBatch`, `TRANSFORM` a plane's pose (kept for its device), `POLYDATA` an
//! `UltrasoundPlane` in the last pose of its device.

use super::geometry::{Frame, frame_rigid, rigid_of};
use super::wire::{
    self, AttributeLocation, Message, PointElement, PolyAttribute, PolyData, Transform, status_code,
};
use librplus::mesh::rigid::Rigid;
use librplus_proto::v1 as pb;
use pb::stream_register_request::Msg;

/// Why a message is refused: the STATUS code and the reason sent with it.
type Refusal = (u16, String);

/// The last pose of each ultrasound plane (by device), LPS, or why its last TRANSFORM was
/// refused (its next POLYDATA is refused too, never placed with an older pose).
pub(super) type Poses = std::collections::HashMap<String, Result<Rigid, String>>;

/// The gRPC request for one OpenIGTLink message (None: a pose, stored for the next POLYDATA of
/// its device), or the STATUS code and reason it is refused with.
pub(super) fn request_of(
    header: &wire::Header,
    msg: Message,
    frame: Frame,
    poses: &mut Poses,
) -> Result<Option<Msg>, Refusal> {
    match msg {
        Message::Point(points) => surface_batch(header, &points, frame).map(Some),
        Message::Transform(t) => {
            store_pose(&header.device_name, &t, frame, poses)?;
            Ok(None)
        }
        Message::PolyData(pd) => ultrasound_plane(header, &pd, poses).map(Some),
        Message::Status(_) => Ok(None),
        Message::Unknown { type_name, .. } => Err((
            status_code::ILLEGAL_INSTRUCTION,
            format!(
                "{type_name:?} messages are not used by LIBR+ (POINT, TRANSFORM and POLYDATA are)"
            ),
        )),
    }
}

/// A `POINT` as one `SurfaceBatch` (its positions converted from `frame` to LPS); refused when
/// it holds no point.
fn surface_batch(
    header: &wire::Header,
    points: &[PointElement],
    frame: Frame,
) -> Result<Msg, Refusal> {
    let acquired_at = Some(acquired_at(header));
    if points.is_empty() {
        return Err((status_code::CONFIG_ERROR, "POINT: no points".into()));
    }
    Ok(Msg::Surface(pb::SurfaceBatch {
        acquired_at,
        xyz_mm: points
            .iter()
            .flat_map(|p| frame.convert(p.position_mm.map(f64::from)))
            .collect(),
        feature: Vec::new(),
    }))
}

/// A `TRANSFORM` of `device`: stored in `poses` as the plane's pose (plane → LPS) for its next
/// `POLYDATA`; refused (and so noted in `poses`) when it is not a rigid transform.
fn store_pose(device: &str, t: &Transform, frame: Frame, poses: &mut Poses) -> Result<(), Refusal> {
    match rigid_of(t) {
        Ok(pose) => {
            // Plane → peer frame, then peer frame → LPS.
            poses.insert(device.to_string(), Ok(pose.then(&frame_rigid(frame))));
            Ok(())
        }
        Err(why) => {
            poses.insert(device.to_string(), Err(why.to_string()));
            Err((
                status_code::CONFIG_ERROR,
                format!("TRANSFORM {device:?}: {why}"),
            ))
        }
    }
}

/// A `POLYDATA` as one `UltrasoundPlane` in the last pose of its device; refused when no pose
/// was received for it, its last one was refused, or its points or `kind` attribute are not as documented.
fn ultrasound_plane(header: &wire::Header, pd: &PolyData, poses: &Poses) -> Result<Msg, Refusal> {
    let acquired_at = Some(acquired_at(header));
    let device = &header.device_name;
    let pose = match poses.get(device) {
        Some(Ok(pose)) => pose,
        Some(Err(why)) => {
            return Err((
                status_code::CONFIG_ERROR,
                format!(
                    "POLYDATA {device:?}: the last TRANSFORM {device:?} (the plane's pose) was refused ({why}); send a valid pose before the plane's points"
                ),
            ));
        }
        None => {
            return Err((
                status_code::CONFIG_ERROR,
                format!(
                    "POLYDATA {device:?}: no TRANSFORM {device:?} (the plane's pose) received before it"
                ),
            ));
        }
    };
    let kind = kind_attribute(device, pd)?;
    let (contour, vessel) = split_points(device, &pd.points, kind)?;
    Ok(Msg::Ultrasound(pb::UltrasoundPlane {
        acquired_at,
        plane_to_physical: Some(crate::convert::rigid_to_pb(pose)),
        contour_uv_mm: contour,
        vessel_uv_mm: vessel,
    }))
}

/// The point attribute `kind` of a `POLYDATA` of `device`, when it has one; refused unless it
/// holds one scalar per point.
fn kind_attribute<'a>(
    device: &str,
    pd: &'a PolyData,
) -> Result<Option<&'a PolyAttribute>, Refusal> {
    let kind = pd
        .attributes
        .iter()
        .find(|a| a.name == "kind" && a.location == AttributeLocation::Point);
    if let Some(k) = kind
        && (k.kind.components() != 1 || k.tuple_count() != pd.points.len())
    {
        return Err((
            status_code::CONFIG_ERROR,
            format!(
                "POLYDATA {device:?}: attribute `kind` needs one scalar per point ({} points)",
                pd.points.len()
            ),
        ));
    }
    Ok(kind)
}

/// The (u, v) of a plane's points, split by `kind` (0 or absent: contour, 1: vessel) into
/// (contour, vessel); refused for a point off the plane (|w| > 0.5 mm) or another kind.
fn split_points(
    device: &str,
    points: &[[f32; 3]],
    kind: Option<&PolyAttribute>,
) -> Result<(Vec<f64>, Vec<f64>), Refusal> {
    let (mut contour, mut vessel) = (Vec::new(), Vec::new());
    for (i, p) in points.iter().enumerate() {
        if f64::from(p[2]).abs() > 0.5 {
            return Err((
                status_code::CONFIG_ERROR,
                format!(
                    "POLYDATA {device:?}: point {i} has w = {} mm: points are (u, v, 0) in the plane's own frame",
                    p[2]
                ),
            ));
        }
        let uv = [f64::from(p[0]), f64::from(p[1])];
        let k = kind.map_or(0.0, |k| k.data[i]);
        if k == 0.0 {
            contour.extend(uv);
        } else if k == 1.0 {
            vessel.extend(uv);
        } else {
            return Err((
                status_code::CONFIG_ERROR,
                format!("POLYDATA {device:?}: kind of point {i} is {k}: 0 (contour) or 1 (vessel)"),
            ));
        }
    }
    Ok((contour, vessel))
}

/// The header's timestamp, or now when it is 0 (unused).
fn acquired_at(h: &wire::Header) -> prost_types::Timestamp {
    let secs = if h.timestamp == 0 {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64())
    } else {
        h.timestamp_secs()
    };
    prost_types::Timestamp {
        seconds: secs.floor() as i64,
        nanos: ((secs - secs.floor()) * 1e9).round().min(999_999_999.0) as i32,
    }
}
