//! The OpenIGTLink messages a peer sends, as the requests of its registration session: `POINT`
//! a `SurfaceBatch`, `TRANSFORM` a plane's pose (kept for its device), `POLYDATA` an
//! `UltrasoundPlane` in the last pose of its device.

use super::geometry::{Frame, frame_rigid, rigid_of};
use super::wire::{self, AttributeLocation, Message, status_code};
use librplus::mesh::rigid::Rigid;
use librplus_proto::v1 as pb;

/// The gRPC request for one OpenIGTLink message (None: a pose, stored for the next POLYDATA of
/// its device), or the STATUS code and reason it is refused with.
pub(super) fn request_of(
    header: &wire::Header,
    msg: Message,
    frame: Frame,
    poses: &mut std::collections::HashMap<String, Rigid>,
) -> Result<Option<pb::stream_register_request::Msg>, (u16, String)> {
    use pb::stream_register_request::Msg;
    let acquired_at = Some(acquired_at(header));
    let device = &header.device_name;
    match msg {
        Message::Point(points) => {
            if points.is_empty() {
                return Err((status_code::CONFIG_ERROR, "POINT: no points".into()));
            }
            Ok(Some(Msg::Surface(pb::SurfaceBatch {
                acquired_at,
                xyz_mm: points
                    .iter()
                    .flat_map(|p| frame.convert(p.position_mm.map(f64::from)))
                    .collect(),
                feature: Vec::new(),
            })))
        }
        Message::Transform(t) => {
            let pose = rigid_of(&t).map_err(|why| {
                (
                    status_code::CONFIG_ERROR,
                    format!("TRANSFORM {device:?}: {why}"),
                )
            })?;
            // Plane → peer frame, then peer frame → LPS.
            poses.insert(device.clone(), pose.then(&frame_rigid(frame)));
            Ok(None)
        }
        Message::PolyData(pd) => {
            let pose = poses.get(device).ok_or_else(|| {
                (
                    status_code::CONFIG_ERROR,
                    format!(
                        "POLYDATA {device:?}: no TRANSFORM {device:?} (the plane's pose) received before it"
                    ),
                )
            })?;
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
            let (mut contour, mut vessel) = (Vec::new(), Vec::new());
            for (i, p) in pd.points.iter().enumerate() {
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
                        format!(
                            "POLYDATA {device:?}: kind of point {i} is {k}: 0 (contour) or 1 (vessel)"
                        ),
                    ));
                }
            }
            Ok(Some(Msg::Ultrasound(pb::UltrasoundPlane {
                acquired_at,
                plane_to_physical: Some(crate::convert::rigid_to_pb(pose)),
                contour_uv_mm: contour,
                vessel_uv_mm: vessel,
            })))
        }
        Message::Status(_) => Ok(None),
        Message::Unknown { type_name, .. } => Err((
            status_code::ILLEGAL_INSTRUCTION,
            format!(
                "{type_name:?} messages are not used by LIBR+ (POINT, TRANSFORM and POLYDATA are)"
            ),
        )),
    }
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
