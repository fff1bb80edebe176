//! The 58-byte message header ([`Header`]), the version 2 extended header ([`ExtendedHeader`])
//! and the split of a body into extended header, content and metadata ([`split_body`]), whose
//! sizes are checked and whose metadata is skipped. This module owns the header layout and the
//! raw header reads the framing needs before a header has parsed.

use crate::error::WireError;
use crate::reader::{Reader, put_fixed_text};
use crate::time::timestamp_to_secs;

/// Size of the message header in bytes (all header versions).
pub const HEADER_SIZE: usize = 58;
/// Size of the version 2 extended header this codec writes (and the least it accepts).
pub const EXTENDED_HEADER_SIZE: usize = 12;
/// Width of the header's `TYPE` field.
pub const TYPE_NAME_LEN: usize = 12;
/// Width of the header's `DEVICE_NAME` field.
pub const DEVICE_NAME_LEN: usize = 20;

/// The 58-byte message header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Header {
    /// Header version: 1 (protocol 1 and 2) or 2 (protocol 3, extended header in the body).
    pub version: u16,
    /// Message type, e.g. `"TRANSFORM"` (at most 12 bytes).
    pub type_name: String,
    /// Device name (at most 20 bytes).
    pub device_name: String,
    /// 32.32 fixed-point seconds since the Unix epoch, 0 if unused (see [`timestamp_to_secs`]).
    pub timestamp: u64,
    /// Size of the body in bytes (for version 2: extended header + content + metadata).
    pub body_size: u64,
    /// CRC-64 of the body ([`crc64`]).
    ///
    /// [`crc64`]: crate::crc64
    pub crc: u64,
}

impl Header {
    /// Parses a header. Checks the version (1 or 2) and that the names are UTF-8; the body
    /// size and CRC are checked against the body later ([`Message::decode`]).
    ///
    /// [`Message::decode`]: crate::Message::decode
    pub fn parse(bytes: &[u8; HEADER_SIZE]) -> Result<Header, WireError> {
        let mut r = Reader::new(bytes, "header");
        let version = r.u16("VERSION")?;
        if version != 1 && version != 2 {
            return Err(WireError::UnsupportedVersion { version });
        }
        let type_name = r.fixed_text(TYPE_NAME_LEN, "TYPE")?;
        let device_name = r.fixed_text(DEVICE_NAME_LEN, "DEVICE_NAME")?;
        let timestamp = r.u64("TIME_STAMP")?;
        let body_size = r.u64("BODY_SIZE")?;
        let crc = r.u64("CRC")?;
        Ok(Header {
            version,
            type_name,
            device_name,
            timestamp,
            body_size,
            crc,
        })
    }

    /// Encodes the header. Fails on a version other than 1 or 2 and on names that do not fit
    /// their fields or contain NUL.
    pub fn encode(&self) -> Result<[u8; HEADER_SIZE], WireError> {
        if self.version != 1 && self.version != 2 {
            return Err(WireError::UnsupportedVersion {
                version: self.version,
            });
        }
        let mut out = Vec::with_capacity(HEADER_SIZE);
        out.extend_from_slice(&self.version.to_be_bytes());
        put_fixed_text(&mut out, &self.type_name, TYPE_NAME_LEN, "header", || {
            "TYPE".into()
        })?;
        put_fixed_text(
            &mut out,
            &self.device_name,
            DEVICE_NAME_LEN,
            "header",
            || "DEVICE_NAME".into(),
        )?;
        out.extend_from_slice(&self.timestamp.to_be_bytes());
        out.extend_from_slice(&self.body_size.to_be_bytes());
        out.extend_from_slice(&self.crc.to_be_bytes());
        let mut bytes = [0u8; HEADER_SIZE];
        bytes.copy_from_slice(&out);
        Ok(bytes)
    }

    /// The timestamp in seconds since the Unix epoch.
    pub fn timestamp_secs(&self) -> f64 {
        timestamp_to_secs(self.timestamp)
    }
}

/// `BODY_SIZE` straight from header bytes, valid or not (the reader needs it to skip a frame).
pub(crate) fn raw_body_size(bytes: &[u8; HEADER_SIZE]) -> u64 {
    let mut size = [0u8; 8];
    size.copy_from_slice(&bytes[42..50]);
    u64::from_be_bytes(size)
}

/// `TYPE` straight from header bytes, lossily (for error messages about unparsed headers).
pub(crate) fn raw_type_name(bytes: &[u8; HEADER_SIZE]) -> String {
    let field = &bytes[2..2 + TYPE_NAME_LEN];
    let end = field.iter().position(|&b| b == 0).unwrap_or(field.len());
    String::from_utf8_lossy(&field[..end]).into_owned()
}

/// The version 2 extended header at the start of the body.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ExtendedHeader {
    /// `EXT_HEADER_SIZE`: bytes from the body start to the content (12 today).
    pub ext_header_size: u16,
    /// `META_HEADER_SIZE`: bytes of the metadata header (2 + 8 per entry).
    pub meta_header_size: u16,
    /// `META_SIZE`: bytes of the metadata keys and values.
    pub meta_size: u32,
    /// `MSG_ID`.
    pub message_id: u32,
}

/// A body split into its sections (see [`split_body`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BodyParts<'a> {
    /// The extended header (version 2 only).
    pub extended: Option<ExtendedHeader>,
    /// The message content.
    pub content: &'a [u8],
    /// The metadata header (`INDEX_COUNT` and entry headers; version 2 only).
    pub metadata_header: &'a [u8],
    /// The metadata keys and values (version 2 only).
    pub metadata: &'a [u8],
}

/// Splits a body into extended header, content and metadata, checking that the sizes the
/// extended header and the metadata header declare fit the body. For version 1 the whole body
/// is content. Content size is `BODY_SIZE - EXT_HEADER_SIZE - META_HEADER_SIZE - META_SIZE`, as
/// the reference library computes it; the metadata sits at the end of the body. An empty
/// version 2 body (no extended header at all) is taken as an empty content, as the reference
/// library does.
pub fn split_body<'a>(header: &Header, body: &'a [u8]) -> Result<BodyParts<'a>, WireError> {
    if header.version < 2 || body.is_empty() {
        return Ok(BodyParts {
            extended: None,
            content: body,
            metadata_header: &[],
            metadata: &[],
        });
    }
    const SECTION: &str = "extended header";
    let mut r = Reader::new(body, SECTION);
    let fixed = "EXT_HEADER_SIZE, META_HEADER_SIZE, META_SIZE and MSG_ID";
    let mut ext = Reader::new(r.take(EXTENDED_HEADER_SIZE, fixed)?, SECTION);
    let extended = ExtendedHeader {
        ext_header_size: ext.u16("EXT_HEADER_SIZE")?,
        meta_header_size: ext.u16("META_HEADER_SIZE")?,
        meta_size: ext.u32("META_SIZE")?,
        message_id: ext.u32("MSG_ID")?,
    };
    let ext_size = usize::from(extended.ext_header_size);
    if ext_size < EXTENDED_HEADER_SIZE {
        return Err(WireError::Value {
            section: SECTION,
            field: "EXT_HEADER_SIZE".into(),
            problem: format!("is {ext_size}, at least {EXTENDED_HEADER_SIZE} expected"),
        });
    }
    // Fields a later protocol may add to the extended header are skipped.
    r.take_declared((ext_size - EXTENDED_HEADER_SIZE) as u64, || {
        format!("EXT_HEADER_SIZE {ext_size}")
    })?;
    let rest = r.rest();
    let meta_total = u64::from(extended.meta_header_size) + u64::from(extended.meta_size);
    let content_len = usize::try_from(meta_total)
        .ok()
        .and_then(|meta| rest.len().checked_sub(meta))
        .ok_or_else(|| WireError::CountMismatch {
            section: SECTION,
            field: format!(
                "META_HEADER_SIZE {} + META_SIZE {}",
                extended.meta_header_size, extended.meta_size
            ),
            declared: meta_total,
            remaining: rest.len() as u64,
        })?;
    let (content, metadata_all) = rest.split_at(content_len);
    let (metadata_header, metadata) = metadata_all.split_at(usize::from(extended.meta_header_size));
    check_metadata(metadata_header, metadata)?;
    Ok(BodyParts {
        extended: Some(extended),
        content,
        metadata_header,
        metadata,
    })
}

/// Checks that the metadata header's entries fit it and that their key and value sizes fit the
/// metadata section (keys and values themselves are not interpreted).
fn check_metadata(metadata_header: &[u8], metadata: &[u8]) -> Result<(), WireError> {
    const SECTION: &str = "metadata";
    if metadata_header.is_empty() {
        if metadata.is_empty() {
            return Ok(());
        }
        return Err(WireError::Value {
            section: SECTION,
            field: "META_SIZE".into(),
            problem: format!("is {} but META_HEADER_SIZE is 0", metadata.len()),
        });
    }
    let mut r = Reader::new(metadata_header, SECTION);
    let count = r.u16("INDEX_COUNT")?;
    let entries = r.take_declared(u64::from(count) * 8, || format!("INDEX_COUNT {count}"))?;
    let mut total = 0u64;
    for entry in entries.chunks_exact(8) {
        let mut e = Reader::new(entry, SECTION);
        let key_size = e.u16("KEY_SIZE")?;
        let _encoding = e.u16("VALUE_ENCODING")?;
        let value_size = e.u32("VALUE_SIZE")?;
        total += u64::from(key_size) + u64::from(value_size);
    }
    if total > metadata.len() as u64 {
        return Err(WireError::CountMismatch {
            section: SECTION,
            field: format!("KEY_SIZE + VALUE_SIZE of {count} entries"),
            declared: total,
            remaining: metadata.len() as u64,
        });
    }
    Ok(())
}
