//! What the bridge sends the peer: its `STATUS` messages, a rejected request's `STATUS`, and
//! for each registration the image → physical `TRANSFORM`, the targets' `POINT` and the liver's
//! `POLYDATA` (see the bridge's documentation for the devices and frames).

use super::geometry::{CaseGeometry, Frame, frame_rigid, transform_of};
use super::wire::{
    AttributeKind, AttributeLocation, CellArray, EncodeOptions, Message, PointElement,
    PolyAttribute, PolyData, Status, WireError, status_code,
};
use librplus::mesh::rigid::Rigid;
use librplus_proto::v1 as pb;

/// Device name of the image → physical `TRANSFORM` sent after each registration.
pub const DEVICE_TRANSFORM: &str = "LIBR_ImageToPhysical";
/// Device name of the registered targets' `POINT`.
pub const DEVICE_TARGETS: &str = "LIBR_Targets";
/// Device name of the registered liver's `POLYDATA`.
pub const DEVICE_LIVER: &str = "LIBR_Liver";
/// Device name of the bridge's `STATUS` messages.
pub const DEVICE_STATUS: &str = "LIBR_Status";

/// An encoded STATUS message (never fails: the texts are cut to their fields' sizes).
pub(super) fn status(code: u16, name: &str, message: &str) -> Vec<u8> {
    let s = Status {
        code,
        subcode: 0,
        error_name: name.chars().take(20).collect(),
        message: message.replace('\0', " "),
    };
    Message::Status(s)
        .encode(DEVICE_STATUS, &EncodeOptions::default())
        .unwrap_or_default()
}

/// The OpenIGTLink status code for a gRPC status code name.
pub(super) fn status_code_of(code: &str) -> u16 {
    match code {
        "NOT_FOUND" => status_code::NOT_FOUND,
        "PERMISSION_DENIED" | "UNAUTHENTICATED" => status_code::ACCESS_DENIED,
        "RESOURCE_EXHAUSTED" => status_code::BUSY,
        "DEADLINE_EXCEEDED" => status_code::TIME_OUT,
        "UNAVAILABLE" => status_code::NOT_READY,
        "INVALID_ARGUMENT" | "FAILED_PRECONDITION" | "OUT_OF_RANGE" => status_code::CONFIG_ERROR,
        _ => status_code::UNKNOWN_ERROR,
    }
}

/// The STATUS for a request the server rejected: its code, the message's `client_seq`, the
/// reason and each field violation.
pub(super) fn rejection_status(r: &pb::Rejection) -> Vec<u8> {
    let detail: Vec<String> = r
        .violations
        .iter()
        .map(|v| format!("{}: {}", v.field, v.description))
        .collect();
    status(
        status_code_of(&r.code),
        &r.code,
        &format!(
            "message {} rejected: {}{}",
            r.client_seq,
            r.message,
            if detail.is_empty() {
                String::new()
            } else {
                format!(" ({})", detail.join("; "))
            }
        ),
    )
}

/// TRANSFORM, target POINT, liver POLYDATA (and a STATUS when the quality is not OK) for
/// registration `r`, whose image → physical transform is `t` and node displacements `u` (mm,
/// LPS, three per node of the case).
pub(super) fn registered_messages(
    r: &pb::Registration,
    t: &Rigid,
    u: &[f64],
    geo: &CaseGeometry,
    frame: Frame,
) -> Result<Vec<Vec<u8>>, WireError> {
    let f = frame_rigid(frame);
    let opts = EncodeOptions::default();
    let mut out = Vec::with_capacity(4);
    // The quality first when it is not OK; the liver POLYDATA last (it ends an update).
    out.extend(quality_status(r));
    // Image (peer frame) → physical (peer frame).
    out.push(
        Message::Transform(transform_of(&f.then(t).then(&f))).encode(DEVICE_TRANSFORM, &opts)?,
    );
    if !geo.targets.is_empty() {
        out.push(Message::Point(target_points(t, u, geo, frame)).encode(DEVICE_TARGETS, &opts)?);
    }
    out.push(Message::PolyData(liver(r, t, u, geo, frame)).encode(DEVICE_LIVER, &opts)?);
    Ok(out)
}

/// The STATUS (code OK, named after the quality) giving the quality and its reason, when the
/// registration's quality is not OK.
fn quality_status(r: &pb::Registration) -> Option<Vec<u8>> {
    if r.quality == pb::Quality::Ok as i32 {
        return None;
    }
    let q = pb::Quality::try_from(r.quality).map_or_else(
        |_| format!("QUALITY_{}", r.quality),
        |q| q.as_str_name().to_string(),
    );
    Some(status(
        status_code::OK,
        q.trim_start_matches("QUALITY_"),
        &r.quality_reason,
    ))
}

/// Image point `x` displaced by `d` (LPS), placed by `t` and converted to the peer's frame.
fn placed(t: &Rigid, frame: Frame, x: [f64; 3], d: [f64; 3]) -> [f32; 3] {
    frame
        .convert(t.apply([x[0] + d[0], x[1] + d[1], x[2] + d[2]]))
        .map(|c| c as f32)
}

/// The case's targets where the registration puts them (each moved by its nodes' weighted
/// displacements, then placed), as POINT elements.
fn target_points(t: &Rigid, u: &[f64], geo: &CaseGeometry, frame: Frame) -> Vec<PointElement> {
    geo.targets
        .iter()
        .map(|e| {
            let mut d = [0.0; 3];
            for (&node, &w) in e.nodes.iter().zip(&e.weights) {
                for (a, da) in d.iter_mut().enumerate() {
                    *da += w * u[3 * node as usize + a];
                }
            }
            PointElement {
                name: e.name.chars().take(64).collect(),
                group: "Target".into(),
                rgba: [255, 64, 64, 255],
                position_mm: placed(t, frame, e.image_mm, d),
                diameter_mm: 5.0,
                owner: String::new(),
            }
        })
        .collect()
}

/// The liver's boundary surface at its registered position: point vector `displacement` (in
/// the peer's frame) and, when the server estimated every node's error, point scalar
/// `uncertainty_mm`.
fn liver(r: &pb::Registration, t: &Rigid, u: &[f64], geo: &CaseGeometry, frame: Frame) -> PolyData {
    let mut points = Vec::with_capacity(geo.surface_nodes.len());
    let mut displacement = Vec::with_capacity(3 * geo.surface_nodes.len());
    for &i in &geo.surface_nodes {
        let i = i as usize;
        let d = [u[3 * i], u[3 * i + 1], u[3 * i + 2]];
        points.push(placed(t, frame, geo.nodes[i], d));
        // The node's deformation in the peer's physical frame: F R u.
        displacement.extend(frame.convert(t.apply_vector(d)).map(|c| c as f32));
    }
    let mut attributes = vec![PolyAttribute {
        name: "displacement".into(),
        location: AttributeLocation::Point,
        kind: AttributeKind::Vector,
        data: displacement,
    }];
    attributes.extend(uncertainty(r, geo));
    PolyData {
        points,
        polygons: CellArray::from_cells(geo.surface_triangles.iter().map(|t| t.to_vec())),
        attributes,
        ..PolyData::default()
    }
}

/// The error estimate's per-node bound on the surface nodes (point scalar `uncertainty_mm`),
/// when the server sent one for every node.
fn uncertainty(r: &pb::Registration, geo: &CaseGeometry) -> Option<PolyAttribute> {
    let e = r
        .error_estimate
        .as_ref()
        .filter(|e| e.node_uncertainty_mm.len() == geo.nodes.len())?;
    Some(PolyAttribute {
        name: "uncertainty_mm".into(),
        location: AttributeLocation::Point,
        kind: AttributeKind::Scalar { components: 1 },
        data: geo
            .surface_nodes
            .iter()
            .map(|&i| e.node_uncertainty_mm[i as usize])
            .collect(),
    })
}
