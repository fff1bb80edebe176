//! A whole message: [`Message`] (the four decoded types or the content of any other), the
//! header and version 2 sections wrapped around its content on encoding ([`EncodeOptions`]), and
//! the length, CRC and section checks on decoding. This module owns the dispatch on the header's
//! `TYPE`.

use crate::crc::crc64;
use crate::error::WireError;
use crate::header::{EXTENDED_HEADER_SIZE, HEADER_SIZE, Header, split_body};
use crate::point::{PointElement, decode_points, encode_points};
use crate::polydata::PolyData;
use crate::status::Status;
use crate::transform::Transform;

/// A decoded message content.
#[derive(Clone, Debug, PartialEq)]
pub enum Message {
    /// `TRANSFORM`.
    Transform(Transform),
    /// `POINT`: a list of points (possibly empty).
    Point(Vec<PointElement>),
    /// `STATUS`.
    Status(Status),
    /// `POLYDATA`.
    PolyData(PolyData),
    /// Any other type: the content bytes (for version 2, without extended header and metadata).
    Unknown {
        /// The header's message type.
        type_name: String,
        /// The content bytes.
        body: Vec<u8>,
    },
}

/// How [`Message::encode`] writes the header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EncodeOptions {
    /// Header version: 1 (default; read by every OpenIGTLink peer) or 2 (extended header and an
    /// empty metadata section).
    pub header_version: u16,
    /// 32.32 fixed-point timestamp ([`timestamp_from_secs`]); 0 means unused.
    ///
    /// [`timestamp_from_secs`]: crate::timestamp_from_secs
    pub timestamp: u64,
    /// `MSG_ID` of the extended header (version 2 only).
    pub message_id: u32,
}

impl Default for EncodeOptions {
    fn default() -> Self {
        EncodeOptions {
            header_version: 1,
            timestamp: 0,
            message_id: 0,
        }
    }
}

impl EncodeOptions {
    /// Version 2 header with the given message id, timestamp 0.
    pub fn version2(message_id: u32) -> Self {
        EncodeOptions {
            header_version: 2,
            timestamp: 0,
            message_id,
        }
    }
}

impl Message {
    /// The header `TYPE` of this message.
    pub fn type_name(&self) -> &str {
        match self {
            Message::Transform(_) => "TRANSFORM",
            Message::Point(_) => "POINT",
            Message::Status(_) => "STATUS",
            Message::PolyData(_) => "POLYDATA",
            Message::Unknown { type_name, .. } => type_name,
        }
    }

    /// The content bytes (no header, no extended header, no metadata).
    pub fn encode_content(&self) -> Result<Vec<u8>, WireError> {
        match self {
            Message::Transform(t) => t.encode_content(),
            Message::Point(points) => encode_points(points),
            Message::Status(s) => s.encode_content(),
            Message::PolyData(p) => p.encode_content(),
            Message::Unknown { body, .. } => Ok(body.clone()),
        }
    }

    /// Decodes a content of the given type; types other than the four known ones give
    /// [`Message::Unknown`].
    pub fn decode_content(type_name: &str, content: &[u8]) -> Result<Message, WireError> {
        Ok(match type_name {
            "TRANSFORM" => Message::Transform(Transform::decode_content(content)?),
            "POINT" => Message::Point(decode_points(content)?),
            "STATUS" => Message::Status(Status::decode_content(content)?),
            "POLYDATA" => Message::PolyData(PolyData::decode_content(content)?),
            other => Message::Unknown {
                type_name: other.to_owned(),
                body: content.to_vec(),
            },
        })
    }

    /// A complete message: header (CRC filled) followed by the body.
    pub fn encode(&self, device_name: &str, options: &EncodeOptions) -> Result<Vec<u8>, WireError> {
        let content = self.encode_content()?;
        let mut body = Vec::with_capacity(content.len() + EXTENDED_HEADER_SIZE + 2);
        match options.header_version {
            1 => body.extend_from_slice(&content),
            2 => {
                body.extend_from_slice(&(EXTENDED_HEADER_SIZE as u16).to_be_bytes());
                body.extend_from_slice(&2u16.to_be_bytes()); // META_HEADER_SIZE: INDEX_COUNT only
                body.extend_from_slice(&0u32.to_be_bytes()); // META_SIZE
                body.extend_from_slice(&options.message_id.to_be_bytes());
                body.extend_from_slice(&content);
                body.extend_from_slice(&0u16.to_be_bytes()); // INDEX_COUNT 0
            }
            version => return Err(WireError::UnsupportedVersion { version }),
        }
        let header = Header {
            version: options.header_version,
            type_name: self.type_name().to_owned(),
            device_name: device_name.to_owned(),
            timestamp: options.timestamp,
            body_size: body.len() as u64,
            crc: crc64(&body),
        };
        let mut out = Vec::with_capacity(HEADER_SIZE + body.len());
        out.extend_from_slice(&header.encode()?);
        out.extend_from_slice(&body);
        Ok(out)
    }

    /// Decodes a body received after `header`: checks its length against `BODY_SIZE`, its CRC,
    /// the version 2 sections, then the content.
    pub fn decode(header: &Header, body: &[u8]) -> Result<Message, WireError> {
        if body.len() as u64 != header.body_size {
            return Err(WireError::BodyLength {
                declared: header.body_size,
                given: body.len() as u64,
            });
        }
        let computed_crc = crc64(body);
        if computed_crc != header.crc {
            return Err(WireError::BadCrc {
                type_name: header.type_name.clone(),
                device_name: header.device_name.clone(),
                header_crc: header.crc,
                computed_crc,
            });
        }
        let parts = split_body(header, body)?;
        Message::decode_content(&header.type_name, parts.content)
    }

    /// `Ok(self)` for the four known types, [`WireError::UnknownType`] for [`Message::Unknown`]
    /// (for a caller that answers unknown types like malformed ones).
    pub fn require_known(self) -> Result<Message, WireError> {
        match self {
            Message::Unknown { type_name, .. } => Err(WireError::UnknownType { type_name }),
            known => Ok(known),
        }
    }
}

/// Decodes one complete message held in `bytes` (header and body, nothing after).
pub fn decode_message(bytes: &[u8]) -> Result<(Header, Message), WireError> {
    let Some((head, body)) = bytes.split_first_chunk::<HEADER_SIZE>() else {
        return Err(WireError::Truncated {
            part: "header",
            expected: HEADER_SIZE as u64,
            got: bytes.len() as u64,
        });
    };
    let header = Header::parse(head)?;
    let message = Message::decode(&header, body)?;
    Ok((header, message))
}
