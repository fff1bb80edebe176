//! `POINT`: a list of fiducials, each a 136-byte `POINT_DATA` element (name, group, colour,
//! position, diameter, owner). This module owns [`PointElement`] and the content encoding of a
//! list of them.

use crate::error::WireError;
use crate::reader::{Reader, put_fixed_text};

/// Size of one `POINT_DATA` element.
pub const POINT_ELEMENT_SIZE: usize = 136;
/// Width of a `POINT` element's `NAME` field.
pub const POINT_NAME_LEN: usize = 64;
/// Width of a `POINT` element's `GROUP` field.
pub const POINT_GROUP_LEN: usize = 32;
/// Width of a `POINT` element's `OWNER` field.
pub const POINT_OWNER_LEN: usize = 20;

/// One element of a `POINT` message (a fiducial).
#[derive(Clone, Debug, PartialEq)]
pub struct PointElement {
    /// Name or description (at most 64 bytes).
    pub name: String,
    /// Group, e.g. "Landmark" (at most 32 bytes).
    pub group: String,
    /// Colour, RGBA.
    pub rgba: [u8; 4],
    /// Position in millimetres.
    pub position_mm: [f32; 3],
    /// Diameter in millimetres, may be 0 (the C library calls this field `radius`; the
    /// specification says diameter).
    pub diameter_mm: f32,
    /// Id of the owner image or slice set (at most 20 bytes).
    pub owner: String,
}

pub(crate) fn encode_points(points: &[PointElement]) -> Result<Vec<u8>, WireError> {
    const S: &str = "POINT";
    let mut out = Vec::with_capacity(points.len() * POINT_ELEMENT_SIZE);
    for (i, p) in points.iter().enumerate() {
        put_fixed_text(&mut out, &p.name, POINT_NAME_LEN, S, || {
            format!("point {i} NAME")
        })?;
        put_fixed_text(&mut out, &p.group, POINT_GROUP_LEN, S, || {
            format!("point {i} GROUP")
        })?;
        out.extend_from_slice(&p.rgba);
        for v in p.position_mm {
            out.extend_from_slice(&v.to_be_bytes());
        }
        out.extend_from_slice(&p.diameter_mm.to_be_bytes());
        put_fixed_text(&mut out, &p.owner, POINT_OWNER_LEN, S, || {
            format!("point {i} OWNER")
        })?;
    }
    Ok(out)
}

pub(crate) fn decode_points(content: &[u8]) -> Result<Vec<PointElement>, WireError> {
    const S: &str = "POINT";
    if content.len() % POINT_ELEMENT_SIZE != 0 {
        return Err(WireError::Value {
            section: S,
            field: "content".into(),
            problem: format!(
                "is {} bytes, not a multiple of the {POINT_ELEMENT_SIZE}-byte POINT_DATA element",
                content.len()
            ),
        });
    }
    let mut points = Vec::with_capacity(content.len() / POINT_ELEMENT_SIZE);
    for (i, element) in content.chunks_exact(POINT_ELEMENT_SIZE).enumerate() {
        let mut r = Reader::new(element, S);
        let name = r.fixed_text(POINT_NAME_LEN, &format!("point {i} NAME"))?;
        let group = r.fixed_text(POINT_GROUP_LEN, &format!("point {i} GROUP"))?;
        let rgba = r.array::<4>("R,G,B,A")?;
        let position_mm = [r.f32("X")?, r.f32("Y")?, r.f32("Z")?];
        let diameter_mm = r.f32("DIAMETER")?;
        let owner = r.fixed_text(POINT_OWNER_LEN, &format!("point {i} OWNER"))?;
        points.push(PointElement {
            name,
            group,
            rgba,
            position_mm,
            diameter_mm,
            owner,
        });
    }
    Ok(points)
}
