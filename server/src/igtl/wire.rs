//! OpenIGTLink wire codec: the byte layout of the messages the LIBR+ bridge speaks, and nothing else.
//!
//! This module turns bytes into typed messages and back. It does no I/O of its own beyond reading
//! from a caller's [`std::io::Read`] ([`read_message`]), keeps no connection state beyond a byte
//! buffer ([`Decoder`]), and depends on `std` only, so it compiles on its own
//! (`rustc --edition 2024 --test wire.rs`).
//!
//! # What subset
//!
//! * The 58-byte header in both header versions: version 1 (protocol 1 and 2) and version 2
//!   (protocol 3, whose body starts with a 12-byte extended header and ends with a metadata
//!   section). Version 2 metadata is checked for consistent sizes and skipped: callers see the
//!   message *content* only. Encoding writes version 1 by default; [`EncodeOptions`] selects
//!   version 2, written with an empty metadata section.
//! * The CRC-64 of the body ([`crc64`]): ECMA-182 polynomial, not reflected, initial value 0,
//!   no final XOR (what `igtl_util.c` computes; check value `0x6C40DF5F0B497347`).
//! * Four message types: `TRANSFORM` ([`Transform`]), `POINT` ([`PointElement`]s), `STATUS`
//!   ([`Status`], codes in [`status_code`]) and `POLYDATA` ([`PolyData`]). Every other type,
//!   including the `GET_`/`STT_`/`STP_`/`RTS_` query messages, decodes to
//!   [`Message::Unknown`] with its content bytes, after the CRC check.
//!
//! # Byte order and text
//!
//! Every number is big-endian; `float32` is IEEE 754 binary32. Fixed-width text fields
//! (`char[N]`) are NUL padded; a value of exactly `N` bytes has no terminator. On decoding, a
//! fixed field ends at its first NUL (anything after it is ignored) and must be UTF-8 (the
//! specification asks for ASCII, a subset). On encoding, a value longer than its field or
//! containing NUL is an error, never silently truncated.
//!
//! # Timestamps
//!
//! The header timestamp is 32.32 fixed-point seconds since the Unix epoch (integer part in the high
//! 32 bits). [`timestamp_from_secs`] and [`timestamp_to_secs`] convert exactly by `2^32` scaling;
//! the C library's `igtl_nanosec_to_frac` approximates the same scaling, so fractions made by it
//! (and by pyigtl, which ports it) differ from ours by up to about 9 ns (36 × 2^-32 s).
//!
//! # Frames of reference: not handled here
//!
//! Coordinates pass through unchanged, in millimetres as they are on the wire. OpenIGTLink does not
//! fix a patient coordinate system: 3D Slicer works in RAS, LIBR+ in LPS. Converting between them
//! (negating x and y) is the bridge's business, not the codec's.
//!
//! # Errors and recovery
//!
//! Malformed input never panics; it yields a [`WireError`] whose `Display` names the section, the
//! field and the problem, e.g. `POLYDATA: SIZE_POLYGONS says 400 bytes but 120 remain`. Both
//! readers ([`read_message`] and [`Decoder`]) consume exactly one frame (58 + `BODY_SIZE` bytes)
//! per message, decoded or not, so after a bad CRC, an oversized body (discarded as it arrives,
//! never buffered), a header with a non-UTF-8 name or a malformed content the next message is
//! read normally. The exception is a header version other than 1 or 2: its size field cannot be
//! trusted, so only the 58 header bytes are consumed and the error comes at once.
//! [`WireError::is_recoverable`] says when the stream itself is suspect (e.g. a header version
//! other than 1 or 2 usually means the peer is not speaking OpenIGTLink) and the connection
//! should be closed instead.
//!
//! # Interoperability notes
//!
//! * `POLYDATA` attribute headers are 6 bytes: one byte attribute type (bits 0–3 the kind,
//!   bit 4 set for cell data), one byte number of components, then a `uint32` count. Read as the
//!   specification's big-endian `uint16` `TYPE_ATTRIBUTE`, the type is the high byte (the
//!   specification numbers bits from the most significant end, as its timestamp page says).
//!   The data size of an attribute is `count × components × 4` bytes, components taken from the
//!   header byte and checked against the kind (3 for vectors and normals, 9 for tensors, 4 for
//!   RGBA, 1–127 for scalars as the reference C++ `PolyDataAttribute::SetType` allows).
//!   The reference C library (`igtl_polydata.c`) sizes cell attributes, RGBA and texture
//!   coordinates as 9-component tensors (OpenIGTLink issue #36), so only point scalars, vectors,
//!   normals and tensors round-trip with peers built on it; such malformed cell attributes from
//!   those peers are rejected here rather than misread.
//! * pyigtl 0.3.4 (the Python peer) writes `POLYDATA` vertex indices in the host byte order
//!   (little-endian on x86), which this decoder rejects; its lines, polygons and strips are
//!   big-endian as specified. It cannot encode attributes or decode `POLYDATA` at all, and has no
//!   `STATUS` message class.

use std::fmt;
use std::io::{self, Read};

/// Size of the message header in bytes (all header versions).
pub const HEADER_SIZE: usize = 58;
/// Size of the version 2 extended header this codec writes (and the least it accepts).
pub const EXTENDED_HEADER_SIZE: usize = 12;
/// Default limit on `BODY_SIZE` for [`read_message`] and [`Decoder::new`]: 64 MiB.
pub const DEFAULT_MAX_BODY_SIZE: u64 = 64 * 1024 * 1024;
/// Width of the header's `TYPE` field.
pub const TYPE_NAME_LEN: usize = 12;
/// Width of the header's `DEVICE_NAME` field.
pub const DEVICE_NAME_LEN: usize = 20;
/// Size of a `TRANSFORM` content: 12 `float32`.
pub const TRANSFORM_CONTENT_SIZE: usize = 48;
/// Size of one `POINT_DATA` element.
pub const POINT_ELEMENT_SIZE: usize = 136;
/// Width of a `POINT` element's `NAME` field.
pub const POINT_NAME_LEN: usize = 64;
/// Width of a `POINT` element's `GROUP` field.
pub const POINT_GROUP_LEN: usize = 32;
/// Width of a `POINT` element's `OWNER` field.
pub const POINT_OWNER_LEN: usize = 20;
/// Size of the fixed part of a `STATUS` content (code, sub-code, error name).
pub const STATUS_HEADER_SIZE: usize = 30;
/// Width of a `STATUS` message's `ERROR_NAME` field.
pub const STATUS_ERROR_NAME_LEN: usize = 20;
/// Size of the `POLYDATA` content header (ten `uint32`).
pub const POLYDATA_HEADER_SIZE: usize = 40;
/// Size of one `POLYDATA` attribute header (type byte, components byte, `uint32` count).
pub const POLYDATA_ATTRIBUTE_HEADER_SIZE: usize = 6;
/// Longest `POLYDATA` attribute name, in bytes, without its terminator.
pub const MAX_ATTRIBUTE_NAME_LEN: usize = 255;

// ---------------------------------------------------------------------------------------------
// CRC-64
// ---------------------------------------------------------------------------------------------

/// The ECMA-182 generator polynomial (the `x^64` term implied).
pub const CRC64_POLY: u64 = 0x42F0_E1EB_A9EA_3693;

const CRC64_TABLE: [u64; 256] = crc64_table();

const fn crc64_table() -> [u64; 256] {
    let mut table = [0u64; 256];
    let mut byte = 0;
    while byte < 256 {
        let mut crc = (byte as u64) << 56;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & (1 << 63) != 0 {
                (crc << 1) ^ CRC64_POLY
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[byte] = crc;
        byte += 1;
    }
    table
}

/// CRC-64 of `bytes` as OpenIGTLink computes it over a message body: ECMA-182 polynomial,
/// most significant bit first (not reflected), initial value 0, no final XOR
/// (the catalogue's CRC-64/ECMA-182; `crc64(b"123456789") == 0x6C40_DF5F_0B49_7347`).
pub fn crc64(bytes: &[u8]) -> u64 {
    crc64_update(0, bytes)
}

/// Continues a CRC-64 over more bytes: `crc64_update(crc64(a), b) == crc64(a ++ b)`.
pub fn crc64_update(crc: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(crc, |crc, &byte| {
        let index = usize::from(((crc >> 56) as u8) ^ byte);
        CRC64_TABLE[index] ^ (crc << 8)
    })
}

// ---------------------------------------------------------------------------------------------
// Timestamps
// ---------------------------------------------------------------------------------------------

const TWO_POW_32: f64 = 4_294_967_296.0;

/// Seconds since the Unix epoch to the header's 32.32 fixed-point timestamp, rounded to the
/// nearest `2^-32` s. Negative and NaN give 0 ("unused"); values past 2106 saturate.
pub fn timestamp_from_secs(secs: f64) -> u64 {
    // Float-to-integer `as` saturates and maps NaN to 0.
    (secs * TWO_POW_32).round() as u64
}

/// The header's 32.32 fixed-point timestamp to seconds since the Unix epoch.
pub fn timestamp_to_secs(timestamp: u64) -> f64 {
    (timestamp >> 32) as f64 + (timestamp & 0xFFFF_FFFF) as f64 / TWO_POW_32
}

/// A [`std::time::SystemTime`] as a header timestamp (0 before the epoch).
pub fn timestamp_from_system_time(time: std::time::SystemTime) -> u64 {
    match time.duration_since(std::time::UNIX_EPOCH) {
        Ok(since) => {
            let secs = since.as_secs().min(u64::from(u32::MAX));
            let frac = (u64::from(since.subsec_nanos()) << 32) / 1_000_000_000;
            (secs << 32) | frac
        }
        Err(_) => 0,
    }
}

// ---------------------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------------------

/// What is wrong with a text field.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TextProblem {
    /// The bytes are not UTF-8 (the first `valid_up_to` bytes are).
    NotUtf8 {
        /// Length of the valid UTF-8 prefix.
        valid_up_to: usize,
    },
    /// The value is longer than its field (encoding) or its format allows.
    TooLong {
        /// Length of the value in bytes.
        len: usize,
        /// Most bytes the field takes.
        max: usize,
    },
    /// The value contains a NUL byte, which would end it early on the wire (encoding).
    ContainsNul,
    /// A NUL-terminated string has no terminator before the content ends.
    Unterminated,
    /// A NUL-terminated string of at most `max` bytes has no terminator within `max + 1` bytes.
    TooLongUnterminated {
        /// Most bytes the string may have before its terminator.
        max: usize,
    },
}

impl fmt::Display for TextProblem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TextProblem::NotUtf8 { valid_up_to } => {
                write!(f, "is not valid UTF-8 (valid up to byte {valid_up_to})")
            }
            TextProblem::TooLong { len, max } => write!(f, "is {len} bytes, at most {max} fit"),
            TextProblem::ContainsNul => write!(f, "contains a NUL byte"),
            TextProblem::Unterminated => write!(f, "has no NUL terminator before the content ends"),
            TextProblem::TooLongUnterminated { max } => write!(
                f,
                "has no NUL terminator within {} bytes (at most {max} allowed)",
                max + 1
            ),
        }
    }
}

/// Everything that can go wrong reading or writing OpenIGTLink bytes.
///
/// `section` fields name the part of the message (`"header"`, `"extended header"`,
/// `"metadata"`, or the message type); `field` fields name the specification's field
/// (`SIZE_POLYGONS`, `point 3 NAME`, ...).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum WireError {
    /// The underlying reader failed.
    Io {
        /// The I/O error kind.
        kind: io::ErrorKind,
        /// The I/O error's message.
        message: String,
    },
    /// The stream ended cleanly before the first byte of a message: no more messages.
    EndOfStream,
    /// The stream ended inside a message.
    Truncated {
        /// Which part was cut: `"header"`, `"body"` or `"discarded body"`.
        part: &'static str,
        /// Bytes the part needed.
        expected: u64,
        /// Bytes that arrived.
        got: u64,
    },
    /// The header's version field is neither 1 nor 2 (usually: the peer does not speak
    /// OpenIGTLink, or the stream lost its framing).
    UnsupportedVersion {
        /// The version found.
        version: u16,
    },
    /// `BODY_SIZE` exceeds the configured limit; the body was discarded.
    BodyTooLarge {
        /// The header's message type.
        type_name: String,
        /// The header's `BODY_SIZE`.
        body_size: u64,
        /// The limit in force.
        limit: u64,
    },
    /// [`Message::decode`] was given a body whose length differs from the header's `BODY_SIZE`.
    BodyLength {
        /// The header's `BODY_SIZE`.
        declared: u64,
        /// Length of the body given.
        given: u64,
    },
    /// The CRC in the header does not match the body.
    BadCrc {
        /// The header's message type.
        type_name: String,
        /// The header's device name.
        device_name: String,
        /// The CRC the header carries.
        header_crc: u64,
        /// The CRC of the body received.
        computed_crc: u64,
    },
    /// A text field is not valid.
    Text {
        /// Message part.
        section: &'static str,
        /// Field name.
        field: String,
        /// What is wrong.
        problem: TextProblem,
    },
    /// A fixed-size part needs more bytes than remain.
    TooShort {
        /// Message part.
        section: &'static str,
        /// Field name(s).
        field: String,
        /// Bytes needed.
        needed: u64,
        /// Bytes remaining.
        remaining: u64,
    },
    /// A count or size field declares more bytes than remain.
    CountMismatch {
        /// Message part.
        section: &'static str,
        /// The field that declares the size (with its value where that helps).
        field: String,
        /// Bytes the field implies.
        declared: u64,
        /// Bytes remaining.
        remaining: u64,
    },
    /// Bytes remain after the last part the message's fields account for.
    Trailing {
        /// Message part.
        section: &'static str,
        /// The last part read.
        after: String,
        /// Number of unexplained bytes.
        extra: u64,
    },
    /// A field has a value the specification does not allow.
    Value {
        /// Message part.
        section: &'static str,
        /// Field name.
        field: String,
        /// What is wrong and what is allowed.
        problem: String,
    },
    /// A message type this codec does not decode (from [`Message::require_known`]).
    UnknownType {
        /// The header's message type.
        type_name: String,
    },
}

impl WireError {
    /// Whether the stream's framing is still trustworthy after this error, so that reading the
    /// next message makes sense. `false` for I/O errors, the end of the stream, truncation and an
    /// unsupported header version (the bytes are probably not OpenIGTLink): close the connection.
    pub fn is_recoverable(&self) -> bool {
        !matches!(
            self,
            WireError::Io { .. }
                | WireError::EndOfStream
                | WireError::Truncated { .. }
                | WireError::UnsupportedVersion { .. }
        )
    }

    fn from_io(error: &io::Error) -> WireError {
        WireError::Io {
            kind: error.kind(),
            message: error.to_string(),
        }
    }
}

impl fmt::Display for WireError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            WireError::Io { message, .. } => write!(f, "I/O error: {message}"),
            WireError::EndOfStream => write!(f, "stream ended (no further message)"),
            WireError::Truncated {
                part,
                expected,
                got,
            } => write!(
                f,
                "stream ended inside the message {part}: {got} of {expected} bytes arrived"
            ),
            WireError::UnsupportedVersion { version } => write!(
                f,
                "header: VERSION {version} is not supported (1 or 2 expected; is the peer \
                 speaking OpenIGTLink?)"
            ),
            WireError::BodyTooLarge {
                type_name,
                body_size,
                limit,
            } => write!(
                f,
                "header: BODY_SIZE {body_size} of a {type_name:?} message exceeds the limit of \
                 {limit} bytes (body discarded)"
            ),
            WireError::BodyLength { declared, given } => {
                write!(
                    f,
                    "header: BODY_SIZE says {declared} bytes but {given} were given"
                )
            }
            WireError::BadCrc {
                type_name,
                device_name,
                header_crc,
                computed_crc,
            } => write!(
                f,
                "{type_name} from device {device_name:?}: CRC mismatch: header says \
                 0x{header_crc:016X}, body computes 0x{computed_crc:016X}"
            ),
            WireError::Text {
                section,
                field,
                problem,
            } => write!(f, "{section}: {field} {problem}"),
            WireError::TooShort {
                section,
                field,
                needed,
                remaining,
            } => {
                write!(
                    f,
                    "{section}: {field} needs {needed} bytes but {remaining} remain"
                )
            }
            WireError::CountMismatch {
                section,
                field,
                declared,
                remaining,
            } => {
                write!(
                    f,
                    "{section}: {field} says {declared} bytes but {remaining} remain"
                )
            }
            WireError::Trailing {
                section,
                after,
                extra,
            } => {
                write!(f, "{section}: {extra} unexplained bytes after {after}")
            }
            WireError::Value {
                section,
                field,
                problem,
            } => write!(f, "{section}: {field} {problem}"),
            WireError::UnknownType { type_name } => {
                write!(f, "message type {type_name:?} is not supported")
            }
        }
    }
}

impl std::error::Error for WireError {}

// ---------------------------------------------------------------------------------------------
// Byte helpers
// ---------------------------------------------------------------------------------------------

/// A bounds-checked big-endian reader over a byte slice; every shortfall is a [`WireError`].
struct Reader<'a> {
    bytes: &'a [u8],
    section: &'static str,
}

impl<'a> Reader<'a> {
    fn new(bytes: &'a [u8], section: &'static str) -> Self {
        Reader { bytes, section }
    }

    fn remaining(&self) -> usize {
        self.bytes.len()
    }

    fn rest(&self) -> &'a [u8] {
        self.bytes
    }

    /// Takes `n` bytes of a fixed-size part.
    fn take(&mut self, n: usize, field: &str) -> Result<&'a [u8], WireError> {
        match self.bytes.split_at_checked(n) {
            Some((head, tail)) => {
                self.bytes = tail;
                Ok(head)
            }
            None => Err(WireError::TooShort {
                section: self.section,
                field: field.to_owned(),
                needed: n as u64,
                remaining: self.bytes.len() as u64,
            }),
        }
    }

    /// Takes `n` bytes whose size a count field of the message declared.
    fn take_declared(
        &mut self,
        n: u64,
        field: impl FnOnce() -> String,
    ) -> Result<&'a [u8], WireError> {
        let split = usize::try_from(n)
            .ok()
            .and_then(|n| self.bytes.split_at_checked(n));
        match split {
            Some((head, tail)) => {
                self.bytes = tail;
                Ok(head)
            }
            None => Err(WireError::CountMismatch {
                section: self.section,
                field: field(),
                declared: n,
                remaining: self.bytes.len() as u64,
            }),
        }
    }

    fn array<const N: usize>(&mut self, field: &str) -> Result<[u8; N], WireError> {
        let bytes = self.take(N, field)?;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        Ok(out)
    }

    fn u8(&mut self, field: &str) -> Result<u8, WireError> {
        Ok(u8::from_be_bytes(self.array(field)?))
    }
    fn u16(&mut self, field: &str) -> Result<u16, WireError> {
        Ok(u16::from_be_bytes(self.array(field)?))
    }
    fn u32(&mut self, field: &str) -> Result<u32, WireError> {
        Ok(u32::from_be_bytes(self.array(field)?))
    }
    fn u64(&mut self, field: &str) -> Result<u64, WireError> {
        Ok(u64::from_be_bytes(self.array(field)?))
    }
    fn i64(&mut self, field: &str) -> Result<i64, WireError> {
        Ok(i64::from_be_bytes(self.array(field)?))
    }
    fn f32(&mut self, field: &str) -> Result<f32, WireError> {
        Ok(f32::from_be_bytes(self.array(field)?))
    }

    /// A fixed-width, NUL-padded text field.
    fn fixed_text(&mut self, width: usize, field: &str) -> Result<String, WireError> {
        let bytes = self.take(width, field)?;
        decode_fixed_text(bytes, self.section, || field.to_owned())
    }
}

fn decode_fixed_text(
    bytes: &[u8],
    section: &'static str,
    field: impl FnOnce() -> String,
) -> Result<String, WireError> {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    let text = bytes.get(..end).unwrap_or(bytes);
    match std::str::from_utf8(text) {
        Ok(text) => Ok(text.to_owned()),
        Err(e) => Err(WireError::Text {
            section,
            field: field(),
            problem: TextProblem::NotUtf8 {
                valid_up_to: e.valid_up_to(),
            },
        }),
    }
}

/// Writes `text` into a `width`-byte NUL-padded field.
fn put_fixed_text(
    out: &mut Vec<u8>,
    text: &str,
    width: usize,
    section: &'static str,
    field: impl FnOnce() -> String,
) -> Result<(), WireError> {
    check_text(text, width, section, field)?;
    out.extend_from_slice(text.as_bytes());
    out.resize(out.len() + (width - text.len()), 0);
    Ok(())
}

fn check_text(
    text: &str,
    max: usize,
    section: &'static str,
    field: impl FnOnce() -> String,
) -> Result<(), WireError> {
    let problem = if text.len() > max {
        TextProblem::TooLong {
            len: text.len(),
            max,
        }
    } else if text.bytes().any(|b| b == 0) {
        TextProblem::ContainsNul
    } else {
        return Ok(());
    };
    Err(WireError::Text {
        section,
        field: field(),
        problem,
    })
}

/// The first four bytes of a `chunks_exact(4)` piece (zeros if shorter, which cannot happen).
fn word(bytes: &[u8]) -> [u8; 4] {
    bytes.first_chunk::<4>().copied().unwrap_or_default()
}

/// Big-endian `float32` triples; a partial triple at the end is ignored (callers size exactly).
fn be_f32_triples(bytes: &[u8]) -> Vec<[f32; 3]> {
    bytes
        .chunks_exact(12)
        .map(|c| {
            let mut xyz = [0f32; 3];
            for (v, w) in xyz.iter_mut().zip(c.chunks_exact(4)) {
                *v = f32::from_be_bytes(word(w));
            }
            xyz
        })
        .collect()
}

/// Big-endian `float32` values; a partial value at the end is ignored (callers size exactly).
fn be_f32s(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|w| f32::from_be_bytes(word(w)))
        .collect()
}

fn u32_count(n: usize, section: &'static str, field: &str) -> Result<u32, WireError> {
    u32::try_from(n).map_err(|_| WireError::Value {
        section,
        field: field.to_owned(),
        problem: format!("would be {n}, more than a uint32 holds"),
    })
}

// ---------------------------------------------------------------------------------------------
// Header
// ---------------------------------------------------------------------------------------------

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
    pub crc: u64,
}

impl Header {
    /// Parses a header. Checks the version (1 or 2) and that the names are UTF-8; the body
    /// size and CRC are checked against the body later ([`Message::decode`]).
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
fn raw_body_size(bytes: &[u8; HEADER_SIZE]) -> u64 {
    let mut size = [0u8; 8];
    size.copy_from_slice(&bytes[42..50]);
    u64::from_be_bytes(size)
}

/// `TYPE` straight from header bytes, lossily (for error messages about unparsed headers).
fn raw_type_name(bytes: &[u8; HEADER_SIZE]) -> String {
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

// ---------------------------------------------------------------------------------------------
// Message types
// ---------------------------------------------------------------------------------------------

/// `TRANSFORM`: an affine transform; translation in millimetres.
///
/// On the wire the upper 3×4 of the matrix, column by column (R11 R21 R31 R12 ... TX TY TZ), as
/// `float32`; the bottom row is implied `[0, 0, 0, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// Row-major homogeneous matrix: `matrix[row][column]`, translation in `matrix[0..3][3]`
    /// (mm). Encoding rounds to `float32` and requires the bottom row `[0, 0, 0, 1]`.
    pub matrix: [[f64; 4]; 4],
}

impl Transform {
    /// The identity transform.
    pub const IDENTITY: Transform = Transform {
        matrix: [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };

    /// The 12 wire values, column-major over the upper 3×4.
    pub fn to_wire(&self) -> Result<[f32; 12], WireError> {
        let bottom = self.matrix[3];
        if bottom != [0.0, 0.0, 0.0, 1.0] {
            return Err(WireError::Value {
                section: "TRANSFORM",
                field: "matrix row 4".into(),
                problem: format!(
                    "is {bottom:?}; TRANSFORM carries only the upper 3x4, the bottom row must be \
                     [0, 0, 0, 1]"
                ),
            });
        }
        let mut wire = [0f32; 12];
        for (column, values) in wire.chunks_exact_mut(3).enumerate() {
            for (row, value) in values.iter_mut().enumerate() {
                *value = self.matrix[row][column] as f32;
            }
        }
        Ok(wire)
    }

    /// From the 12 wire values, column-major over the upper 3×4.
    pub fn from_wire(wire: &[f32; 12]) -> Transform {
        let mut matrix = Transform::IDENTITY.matrix;
        for (column, values) in wire.chunks_exact(3).enumerate() {
            for (row, &value) in values.iter().enumerate() {
                matrix[row][column] = f64::from(value);
            }
        }
        Transform { matrix }
    }

    fn encode_content(&self) -> Result<Vec<u8>, WireError> {
        Ok(self
            .to_wire()?
            .iter()
            .flat_map(|v| v.to_be_bytes())
            .collect())
    }

    fn decode_content(content: &[u8]) -> Result<Transform, WireError> {
        if content.len() != TRANSFORM_CONTENT_SIZE {
            return Err(WireError::Value {
                section: "TRANSFORM",
                field: "content".into(),
                problem: format!(
                    "is {} bytes, a TRANSFORM has exactly {TRANSFORM_CONTENT_SIZE} (12 float32)",
                    content.len()
                ),
            });
        }
        let mut wire = [0f32; 12];
        for (w, v) in wire.iter_mut().zip(be_f32s(content)) {
            *w = v;
        }
        Ok(Transform::from_wire(&wire))
    }
}

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

fn encode_points(points: &[PointElement]) -> Result<Vec<u8>, WireError> {
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

fn decode_points(content: &[u8]) -> Result<Vec<PointElement>, WireError> {
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

/// The status codes of `STATUS` (`C` field), from the specification's table.
pub mod status_code {
    /// 0: invalid packet (0 is not used).
    pub const INVALID: u16 = 0;
    /// 1: OK (default status).
    pub const OK: u16 = 1;
    /// 2: unknown error.
    pub const UNKNOWN_ERROR: u16 = 2;
    /// 3: panic mode (emergency).
    pub const PANIC_MODE: u16 = 3;
    /// 4: not found (file, configuration, device, ...).
    pub const NOT_FOUND: u16 = 4;
    /// 5: access denied.
    pub const ACCESS_DENIED: u16 = 5;
    /// 6: busy.
    pub const BUSY: u16 = 6;
    /// 7: time out / connection lost.
    pub const TIME_OUT: u16 = 7;
    /// 8: overflow / can't be reached.
    pub const OVERFLOW: u16 = 8;
    /// 9: checksum error.
    pub const CHECKSUM_ERROR: u16 = 9;
    /// 10: configuration error.
    pub const CONFIG_ERROR: u16 = 10;
    /// 11: not enough resource (memory, storage, ...).
    pub const RESOURCE_ERROR: u16 = 11;
    /// 12: illegal/unknown instruction (or feature not implemented / unknown command received).
    pub const ILLEGAL_INSTRUCTION: u16 = 12;
    /// 13: device not ready (starting up).
    pub const NOT_READY: u16 = 13;
    /// 14: manual mode (device does not accept commands).
    pub const MANUAL_MODE: u16 = 14;
    /// 15: device disabled.
    pub const DISABLED: u16 = 15;
    /// 16: device not present.
    pub const NOT_PRESENT: u16 = 16;
    /// 17: device version not known.
    pub const UNKNOWN_VERSION: u16 = 17;
    /// 18: hardware failure.
    pub const HARDWARE_FAILURE: u16 = 18;
    /// 19: exiting / shut down in progress.
    pub const SHUT_DOWN: u16 = 19;

    /// The specification's short description of a status code, `None` for codes it does not
    /// define.
    pub fn describe(code: u16) -> Option<&'static str> {
        Some(match code {
            INVALID => "invalid packet",
            OK => "OK",
            UNKNOWN_ERROR => "unknown error",
            PANIC_MODE => "panic mode (emergency)",
            NOT_FOUND => "not found",
            ACCESS_DENIED => "access denied",
            BUSY => "busy",
            TIME_OUT => "time out / connection lost",
            OVERFLOW => "overflow / can't be reached",
            CHECKSUM_ERROR => "checksum error",
            CONFIG_ERROR => "configuration error",
            RESOURCE_ERROR => "not enough resource",
            ILLEGAL_INSTRUCTION => "illegal/unknown instruction",
            NOT_READY => "device not ready",
            MANUAL_MODE => "manual mode",
            DISABLED => "device disabled",
            NOT_PRESENT => "device not present",
            UNKNOWN_VERSION => "device version not known",
            HARDWARE_FAILURE => "hardware failure",
            SHUT_DOWN => "exiting / shut down in progress",
            _ => return None,
        })
    }
}

/// `STATUS`: a status code, a device-specific sub-code, an error name and a message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Status {
    /// Status code ([`status_code`]).
    pub code: u16,
    /// Device-specific sub-code.
    pub subcode: i64,
    /// Error name, e.g. "OK" (at most 20 bytes).
    pub error_name: String,
    /// Description; written NUL-terminated after the 30-byte fixed part.
    pub message: String,
}

impl Status {
    fn encode_content(&self) -> Result<Vec<u8>, WireError> {
        const S: &str = "STATUS";
        check_text(&self.message, usize::MAX, S, || "MESSAGE".into())?;
        let mut out = Vec::with_capacity(STATUS_HEADER_SIZE + self.message.len() + 1);
        out.extend_from_slice(&self.code.to_be_bytes());
        out.extend_from_slice(&self.subcode.to_be_bytes());
        put_fixed_text(&mut out, &self.error_name, STATUS_ERROR_NAME_LEN, S, || {
            "ERROR_NAME".into()
        })?;
        out.extend_from_slice(self.message.as_bytes());
        out.push(0);
        Ok(out)
    }

    /// The message ends at its first NUL; a message without terminator (which the reference
    /// library would drop) is taken whole; a content of exactly 30 bytes has an empty message.
    fn decode_content(content: &[u8]) -> Result<Status, WireError> {
        const S: &str = "STATUS";
        let mut r = Reader::new(content, S);
        let mut fixed = Reader::new(r.take(STATUS_HEADER_SIZE, "C, SUB_CODE and ERROR_NAME")?, S);
        let code = fixed.u16("C")?;
        let subcode = fixed.i64("SUB_CODE")?;
        let error_name = fixed.fixed_text(STATUS_ERROR_NAME_LEN, "ERROR_NAME")?;
        let message = decode_fixed_text(r.rest(), S, || "MESSAGE".into())?;
        Ok(Status {
            code,
            subcode,
            error_name,
            message,
        })
    }
}

/// Cells of a `POLYDATA` section (vertices, lines, polygons or triangle strips): each cell a
/// list of point indices, stored flat.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CellArray {
    /// End of each cell in `indices`.
    ends: Vec<usize>,
    indices: Vec<u32>,
}

impl CellArray {
    /// An empty array.
    pub fn new() -> CellArray {
        CellArray::default()
    }

    /// From a list of cells, e.g. `CellArray::from_cells([[0, 1, 2], [2, 1, 3]])`.
    pub fn from_cells<I, C>(cells: I) -> CellArray
    where
        I: IntoIterator<Item = C>,
        C: AsRef<[u32]>,
    {
        let mut array = CellArray::new();
        for cell in cells {
            array.push(cell.as_ref());
        }
        array
    }

    /// Appends a cell.
    pub fn push(&mut self, cell: &[u32]) {
        self.indices.extend_from_slice(cell);
        self.ends.push(self.indices.len());
    }

    /// Number of cells.
    pub fn len(&self) -> usize {
        self.ends.len()
    }

    /// Whether there are no cells.
    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// The point indices of cell `i`.
    pub fn get(&self, i: usize) -> Option<&[u32]> {
        let end = *self.ends.get(i)?;
        let start = if i == 0 { 0 } else { *self.ends.get(i - 1)? };
        self.indices.get(start..end)
    }

    /// The cells in order.
    pub fn iter(&self) -> impl Iterator<Item = &[u32]> + '_ {
        (0..self.len()).filter_map(move |i| self.get(i))
    }

    /// All point indices, cell after cell.
    pub fn indices(&self) -> &[u32] {
        &self.indices
    }

    /// The section's wire size in bytes: one `NINDICES` and the indices per cell.
    pub fn wire_size(&self) -> usize {
        4 * (self.ends.len() + self.indices.len())
    }
}

/// Whether an attribute belongs to points or to cells.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttributeLocation {
    /// `POINT_DATA` (type bit 4 clear).
    Point,
    /// `CELL_DATA` (type bit 4 set).
    Cell,
}

/// What an attribute holds; the number of `float32` per point or cell follows from it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttributeKind {
    /// Scalars (type 0x00) with 1 to 127 components.
    Scalar {
        /// Components per tuple (1–127).
        components: u8,
    },
    /// Vectors (type 0x01), 3 components.
    Vector,
    /// Normals (type 0x02), 3 components.
    Normal,
    /// Tensors (type 0x03), 9 components.
    Tensor,
    /// RGBA colours (type 0x04), 4 components in \[0, 1\].
    Rgba,
}

impl AttributeKind {
    /// Components per point or cell.
    pub fn components(self) -> u8 {
        match self {
            AttributeKind::Scalar { components } => components,
            AttributeKind::Vector | AttributeKind::Normal => 3,
            AttributeKind::Tensor => 9,
            AttributeKind::Rgba => 4,
        }
    }

    fn code(self) -> u8 {
        match self {
            AttributeKind::Scalar { .. } => 0x00,
            AttributeKind::Vector => 0x01,
            AttributeKind::Normal => 0x02,
            AttributeKind::Tensor => 0x03,
            AttributeKind::Rgba => 0x04,
        }
    }
}

/// A `POLYDATA` dataset attribute (a VTK point or cell data array).
///
/// The specification does not tie the tuple count to `NPOINTS` or the number of cells, so the
/// decoder does not either: check `tuple_count()` before using the data per point or cell.
#[derive(Clone, Debug, PartialEq)]
pub struct PolyAttribute {
    /// Name (at most 255 bytes, no NUL).
    pub name: String,
    /// Point or cell data.
    pub location: AttributeLocation,
    /// Kind and number of components.
    pub kind: AttributeKind,
    /// Values, tuple after tuple: `tuple_count() * kind.components()` of them.
    pub data: Vec<f32>,
}

impl PolyAttribute {
    /// Number of tuples (points or cells) the data covers.
    pub fn tuple_count(&self) -> usize {
        self.data.len() / usize::from(self.kind.components().max(1))
    }

    /// The wire type byte: the kind in bits 0–3, bit 4 set for cell data.
    pub fn type_byte(&self) -> u8 {
        let cell = match self.location {
            AttributeLocation::Point => 0x00,
            AttributeLocation::Cell => 0x10,
        };
        cell | self.kind.code()
    }

    /// The specification's `TYPE_ATTRIBUTE` read as a big-endian `uint16`: type byte high,
    /// components low.
    pub fn type_attribute(&self) -> u16 {
        u16::from_be_bytes([self.type_byte(), self.kind.components()])
    }
}

/// `POLYDATA`: points, four cell sections and dataset attributes (VTK polydata).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PolyData {
    /// Point coordinates in millimetres.
    pub points: Vec<[f32; 3]>,
    /// Vertex cells.
    pub vertices: CellArray,
    /// Line (polyline) cells.
    pub lines: CellArray,
    /// Polygon cells.
    pub polygons: CellArray,
    /// Triangle strip cells.
    pub triangle_strips: CellArray,
    /// Point and cell data.
    pub attributes: Vec<PolyAttribute>,
}

const CELL_SECTIONS: [&str; 4] = ["VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS"];

impl PolyData {
    fn cell_sections(&self) -> [&CellArray; 4] {
        [
            &self.vertices,
            &self.lines,
            &self.polygons,
            &self.triangle_strips,
        ]
    }

    fn encode_content(&self) -> Result<Vec<u8>, WireError> {
        const S: &str = "POLYDATA";
        let npoints = u32_count(self.points.len(), S, "NPOINTS")?;
        let mut header = Vec::with_capacity(POLYDATA_HEADER_SIZE);
        header.extend_from_slice(&npoints.to_be_bytes());
        for (name, cells) in CELL_SECTIONS.iter().zip(self.cell_sections()) {
            let count = u32_count(cells.len(), S, &format!("N{name}"))?;
            let size = u32_count(cells.wire_size(), S, &format!("SIZE_{name}"))?;
            for (c, cell) in cells.iter().enumerate() {
                if let Some(index) = cell.iter().find(|&&index| index >= npoints) {
                    return Err(WireError::Value {
                        section: S,
                        field: format!("{name} cell {c}"),
                        problem: format!(
                            "has point index {index}, out of range (NPOINTS {npoints})"
                        ),
                    });
                }
            }
            header.extend_from_slice(&count.to_be_bytes());
            header.extend_from_slice(&size.to_be_bytes());
        }
        let nattributes = u32_count(self.attributes.len(), S, "NATTRIBUTES")?;
        header.extend_from_slice(&nattributes.to_be_bytes());

        let mut out = header;
        for p in &self.points {
            for v in p {
                out.extend_from_slice(&v.to_be_bytes());
            }
        }
        for cells in self.cell_sections() {
            for cell in cells.iter() {
                out.extend_from_slice(&(cell.len() as u32).to_be_bytes());
                for index in cell {
                    out.extend_from_slice(&index.to_be_bytes());
                }
            }
        }
        for (i, a) in self.attributes.iter().enumerate() {
            let components = a.kind.components();
            if let AttributeKind::Scalar {
                components: 0 | 128..,
            } = a.kind
            {
                return Err(WireError::Value {
                    section: S,
                    field: format!("attribute {i} {:?} NCOMPONENTS", a.name),
                    problem: format!("is {components}; scalars have 1 to 127 components"),
                });
            }
            if a.data.len() % usize::from(components) != 0 {
                return Err(WireError::Value {
                    section: S,
                    field: format!("attribute {i} {:?} data", a.name),
                    problem: format!(
                        "has {} values, not a multiple of its {components} components",
                        a.data.len()
                    ),
                });
            }
            let n = u32_count(a.tuple_count(), S, &format!("NATTRIBUTE_{i}"))?;
            out.push(a.type_byte());
            out.push(components);
            out.extend_from_slice(&n.to_be_bytes());
        }
        let mut names_len = 0usize;
        for (i, a) in self.attributes.iter().enumerate() {
            check_text(&a.name, MAX_ATTRIBUTE_NAME_LEN, S, || {
                format!("NAME_ATTRIBUTE_{i}")
            })?;
            out.extend_from_slice(a.name.as_bytes());
            out.push(0);
            names_len += a.name.len() + 1;
        }
        if names_len % 2 == 1 {
            out.push(0);
        }
        for a in &self.attributes {
            for v in &a.data {
                out.extend_from_slice(&v.to_be_bytes());
            }
        }
        Ok(out)
    }

    fn decode_content(content: &[u8]) -> Result<PolyData, WireError> {
        const S: &str = "POLYDATA";
        let mut r = Reader::new(content, S);
        let mut h = Reader::new(
            r.take(POLYDATA_HEADER_SIZE, "header (NPOINTS ... NATTRIBUTES)")?,
            S,
        );
        let npoints = h.u32("NPOINTS")?;
        let mut counts = [(0u32, 0u32); 4];
        for (count, name) in counts.iter_mut().zip(CELL_SECTIONS) {
            *count = (h.u32(name)?, h.u32(name)?);
        }
        let nattributes = h.u32("NATTRIBUTES")?;

        let point_bytes =
            r.take_declared(u64::from(npoints) * 12, || format!("NPOINTS {npoints}"))?;
        let points = be_f32_triples(point_bytes);

        let mut sections: [CellArray; 4] = Default::default();
        for ((cells, (count, size)), name) in sections.iter_mut().zip(counts).zip(CELL_SECTIONS) {
            *cells = decode_cells(&mut r, name, count, size, npoints)?;
        }
        let [vertices, lines, polygons, triangle_strips] = sections;

        let headers = r.take_declared(
            u64::from(nattributes) * POLYDATA_ATTRIBUTE_HEADER_SIZE as u64,
            || format!("NATTRIBUTES {nattributes}"),
        )?;
        let mut kinds = Vec::with_capacity(headers.len() / POLYDATA_ATTRIBUTE_HEADER_SIZE);
        for (i, header) in headers
            .chunks_exact(POLYDATA_ATTRIBUTE_HEADER_SIZE)
            .enumerate()
        {
            let mut h = Reader::new(header, S);
            let type_byte = h.u8("TYPE_ATTRIBUTE")?;
            let components = h.u8("TYPE_ATTRIBUTE")?;
            let n = h.u32("NATTRIBUTE")?;
            kinds.push((attribute_kind(i, type_byte, components)?, n));
        }

        let mut names = Vec::with_capacity(kinds.len());
        let mut names_len = 0usize;
        for i in 0..kinds.len() {
            let rest = r.rest();
            let window = &rest[..rest.len().min(MAX_ATTRIBUTE_NAME_LEN + 1)];
            let Some(len) = window.iter().position(|&b| b == 0) else {
                let problem = if rest.len() > MAX_ATTRIBUTE_NAME_LEN {
                    TextProblem::TooLongUnterminated {
                        max: MAX_ATTRIBUTE_NAME_LEN,
                    }
                } else {
                    TextProblem::Unterminated
                };
                return Err(WireError::Text {
                    section: S,
                    field: format!("NAME_ATTRIBUTE_{i}"),
                    problem,
                });
            };
            let bytes = r.take(len + 1, "NAME_ATTRIBUTE")?;
            names.push(decode_fixed_text(bytes, S, || {
                format!("NAME_ATTRIBUTE_{i}")
            })?);
            names_len += len + 1;
        }
        if names_len % 2 == 1 {
            r.take(1, "ATTRIBUTE_NAMES padding")?;
        }

        let mut attributes = Vec::with_capacity(kinds.len());
        for (i, (((location, kind), n), name)) in kinds.into_iter().zip(names).enumerate() {
            let components = kind.components();
            let bytes = r.take_declared(u64::from(n) * u64::from(components) * 4, || {
                format!("attribute {i} {name:?} NATTRIBUTE {n} x {components} components")
            })?;
            attributes.push(PolyAttribute {
                name,
                location,
                kind,
                data: be_f32s(bytes),
            });
        }
        if r.remaining() > 0 {
            let after = match attributes.len() {
                0 => "TRIANGLE_STRIPS (NATTRIBUTES 0)".to_owned(),
                n => format!("the data of attribute {}", n - 1),
            };
            return Err(WireError::Trailing {
                section: S,
                after,
                extra: r.remaining() as u64,
            });
        }
        Ok(PolyData {
            points,
            vertices,
            lines,
            polygons,
            triangle_strips,
            attributes,
        })
    }
}

fn attribute_kind(
    i: usize,
    type_byte: u8,
    components: u8,
) -> Result<(AttributeLocation, AttributeKind), WireError> {
    let value_error = |problem: String| WireError::Value {
        section: "POLYDATA",
        field: format!("attribute {i} TYPE_ATTRIBUTE 0x{type_byte:02X}{components:02X}"),
        problem,
    };
    let location = match type_byte >> 4 {
        0 => AttributeLocation::Point,
        1 => AttributeLocation::Cell,
        _ => {
            return Err(value_error(
                "has a type other than POINT_DATA (0x0_) or CELL_DATA (0x1_)".into(),
            ));
        }
    };
    let (kind, kind_name) = match type_byte & 0x0F {
        0x00 => (AttributeKind::Scalar { components }, "scalar"),
        0x01 => (AttributeKind::Vector, "vector"),
        0x02 => (AttributeKind::Normal, "normal"),
        0x03 => (AttributeKind::Tensor, "tensor"),
        0x04 => (AttributeKind::Rgba, "RGBA"),
        0x05 => {
            return Err(value_error(
                "is texture coordinates (0x05), which the specification does not define".into(),
            ));
        }
        other => {
            return Err(value_error(format!(
                "has unknown attribute type 0x{other:02X}"
            )));
        }
    };
    let (fits, allowed) = match kind {
        AttributeKind::Scalar { .. } => ((1..=127).contains(&components), "1 to 127".to_owned()),
        other => (
            other.components() == components,
            other.components().to_string(),
        ),
    };
    if !fits {
        let hint = if components == 9 {
            " (the reference C library writes 9 for cell and RGBA attributes, OpenIGTLink issue #36)"
        } else {
            ""
        };
        return Err(value_error(format!(
            "has {components} components where a {kind_name} has {allowed}{hint}"
        )));
    }
    Ok((location, kind))
}

fn decode_cells(
    r: &mut Reader<'_>,
    name: &str,
    count: u32,
    size: u32,
    npoints: u32,
) -> Result<CellArray, WireError> {
    const S: &str = "POLYDATA";
    if size % 4 != 0 {
        return Err(WireError::Value {
            section: S,
            field: format!("SIZE_{name}"),
            problem: format!("is {size}, not a multiple of 4 (uint32 indices)"),
        });
    }
    let bytes = r.take_declared(u64::from(size), || format!("SIZE_{name}"))?;
    let words: Vec<u32> = bytes
        .chunks_exact(4)
        .map(|w| u32::from_be_bytes(word(w)))
        .collect();
    let mut cells = CellArray {
        ends: Vec::with_capacity((count as usize).min(words.len())),
        indices: Vec::with_capacity(words.len()),
    };
    let mut at = 0usize;
    for c in 0..count {
        let Some(&nindices) = words.get(at) else {
            return Err(WireError::Value {
                section: S,
                field: format!("N{name}"),
                problem: format!("is {count} but SIZE_{name} ({size} bytes) holds only {c} cells"),
            });
        };
        at += 1;
        let left = words.len() - at;
        let cell = usize::try_from(nindices)
            .ok()
            .and_then(|n| words.get(at..at.checked_add(n)?))
            .ok_or_else(|| WireError::CountMismatch {
                section: S,
                field: format!("{name} cell {c} NINDICES {nindices}"),
                declared: u64::from(nindices) * 4,
                remaining: left as u64 * 4,
            })?;
        at += cell.len();
        for &index in cell {
            if index >= npoints {
                return Err(WireError::Value {
                    section: S,
                    field: format!("{name} cell {c}"),
                    problem: format!("has point index {index}, out of range (NPOINTS {npoints})"),
                });
            }
            cells.indices.push(index);
        }
        cells.ends.push(cells.indices.len());
    }
    if at != words.len() {
        return Err(WireError::Value {
            section: S,
            field: format!("SIZE_{name}"),
            problem: format!(
                "is {size} bytes but its N{name} {count} cells use {}",
                at * 4
            ),
        });
    }
    Ok(cells)
}

// ---------------------------------------------------------------------------------------------
// Message
// ---------------------------------------------------------------------------------------------

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

// ---------------------------------------------------------------------------------------------
// Framing: blocking reader
// ---------------------------------------------------------------------------------------------

/// Reads one message with the default body limit ([`DEFAULT_MAX_BODY_SIZE`]).
/// See [`read_message_with_limit`].
pub fn read_message<R: Read + ?Sized>(reader: &mut R) -> Result<(Header, Message), WireError> {
    read_message_with_limit(reader, DEFAULT_MAX_BODY_SIZE)
}

/// Reads one message: the header, then `BODY_SIZE` bytes, then decodes them.
///
/// Whatever the outcome, the whole frame is consumed, so the next call reads the next message:
/// a body over `max_body_size` is read and discarded without being buffered; a header with a
/// non-UTF-8 name still has its body skipped. After [`WireError::UnsupportedVersion`] only the
/// header was consumed (its size cannot be trusted; close the connection).
/// [`WireError::EndOfStream`] means the stream ended cleanly between messages.
pub fn read_message_with_limit<R: Read + ?Sized>(
    reader: &mut R,
    max_body_size: u64,
) -> Result<(Header, Message), WireError> {
    let mut head = [0u8; HEADER_SIZE];
    let got = read_full(reader, &mut head)?;
    if got == 0 {
        return Err(WireError::EndOfStream);
    }
    if got < HEADER_SIZE {
        return Err(WireError::Truncated {
            part: "header",
            expected: HEADER_SIZE as u64,
            got: got as u64,
        });
    }
    let body_size = raw_body_size(&head);
    let header = match Header::parse(&head) {
        Ok(header) => header,
        // The size field of a header with a foreign version cannot be trusted: do not skip.
        Err(e @ WireError::UnsupportedVersion { .. }) => return Err(e),
        Err(e) => {
            skip(reader, body_size)?;
            return Err(e);
        }
    };
    if body_size > max_body_size {
        skip(reader, body_size)?;
        return Err(WireError::BodyTooLarge {
            type_name: header.type_name,
            body_size,
            limit: max_body_size,
        });
    }
    let mut body = Vec::with_capacity(body_size.min(1 << 20) as usize);
    (&mut *reader)
        .take(body_size)
        .read_to_end(&mut body)
        .map_err(|e| WireError::from_io(&e))?;
    if (body.len() as u64) < body_size {
        return Err(WireError::Truncated {
            part: "body",
            expected: body_size,
            got: body.len() as u64,
        });
    }
    let message = Message::decode(&header, &body)?;
    Ok((header, message))
}

/// Fills `buf` unless the stream ends first; returns the bytes read.
fn read_full<R: Read + ?Sized>(reader: &mut R, buf: &mut [u8]) -> Result<usize, WireError> {
    let mut filled = 0;
    while filled < buf.len() {
        match reader.read(&mut buf[filled..]) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(WireError::from_io(&e)),
        }
    }
    Ok(filled)
}

fn skip<R: Read + ?Sized>(reader: &mut R, n: u64) -> Result<(), WireError> {
    let skipped = io::copy(&mut (&mut *reader).take(n), &mut io::sink())
        .map_err(|e| WireError::from_io(&e))?;
    if skipped < n {
        return Err(WireError::Truncated {
            part: "discarded body",
            expected: n,
            got: skipped,
        });
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Framing: incremental decoder
// ---------------------------------------------------------------------------------------------

/// An incremental decoder for non-blocking I/O: [`Decoder::feed`] it the bytes as they arrive,
/// then call [`Decoder::next_message`] until it returns `None`.
///
/// It buffers at most one header and one body (bounded by the body limit) plus what the last
/// `feed` brought; a body over the limit is dropped as it arrives. Each `Some` result consumes
/// one whole frame, so an error (bad CRC, malformed content, oversized body) is followed by the
/// next message as usual (but see [`WireError::is_recoverable`]).
#[derive(Clone, Debug)]
pub struct Decoder {
    buf: Vec<u8>,
    /// Start of the unread bytes in `buf` (compacted on the next `feed`).
    pos: usize,
    max_body_size: u64,
    /// Bytes of a discarded body still to drop from the input.
    skip_left: u64,
    /// Size of the body being discarded (for the truncation report).
    skip_total: u64,
}

impl Default for Decoder {
    fn default() -> Self {
        Decoder::new()
    }
}

impl Decoder {
    /// A decoder with the default body limit ([`DEFAULT_MAX_BODY_SIZE`]).
    pub fn new() -> Decoder {
        Decoder::with_max_body_size(DEFAULT_MAX_BODY_SIZE)
    }

    /// A decoder that rejects (and discards) bodies over `max_body_size` bytes.
    pub fn with_max_body_size(max_body_size: u64) -> Decoder {
        Decoder {
            buf: Vec::new(),
            pos: 0,
            max_body_size,
            skip_left: 0,
            skip_total: 0,
        }
    }

    /// The body limit in force.
    pub fn max_body_size(&self) -> u64 {
        self.max_body_size
    }

    /// The bytes received and not yet consumed.
    fn pending(&self) -> &[u8] {
        self.buf.get(self.pos..).unwrap_or_default()
    }

    /// Appends received bytes.
    pub fn feed(&mut self, mut bytes: &[u8]) {
        if self.pos > 0 {
            self.buf.drain(..self.pos.min(self.buf.len()));
            self.pos = 0;
        }
        if self.skip_left > 0 {
            let drop = usize::try_from(self.skip_left)
                .unwrap_or(usize::MAX)
                .min(bytes.len());
            self.skip_left -= drop as u64;
            bytes = bytes.get(drop..).unwrap_or_default();
        }
        self.buf.extend_from_slice(bytes);
    }

    /// Bytes buffered and not yet returned as a message.
    pub fn buffered(&self) -> usize {
        self.pending().len()
    }

    /// Whether the decoder sits between messages (nothing partial buffered or being skipped).
    pub fn is_at_boundary(&self) -> bool {
        self.pending().is_empty() && self.skip_left == 0
    }

    /// The next complete message, `None` when more bytes are needed.
    pub fn next_message(&mut self) -> Option<Result<(Header, Message), WireError>> {
        if self.skip_left > 0 {
            return None;
        }
        let head: [u8; HEADER_SIZE] = *self.pending().first_chunk::<HEADER_SIZE>()?;
        let body_size = raw_body_size(&head);
        let header = match Header::parse(&head) {
            Ok(header) => header,
            // The size field of a header with a foreign version cannot be trusted: drop the
            // header only.
            Err(e @ WireError::UnsupportedVersion { .. }) => {
                self.discard(0);
                return Some(Err(e));
            }
            Err(e) => {
                self.discard(body_size);
                return Some(Err(e));
            }
        };
        if body_size > self.max_body_size {
            self.discard(body_size);
            return Some(Err(WireError::BodyTooLarge {
                type_name: raw_type_name(&head),
                body_size,
                limit: self.max_body_size,
            }));
        }
        // body_size <= max_body_size, which the caller sized for memory: it fits a usize.
        let total = HEADER_SIZE.saturating_add(usize::try_from(body_size).unwrap_or(usize::MAX));
        let body = self.pending().get(HEADER_SIZE..total)?;
        let result = Message::decode(&header, body).map(|message| (header, message));
        self.pos += total;
        Some(result)
    }

    /// Drops the buffered header and `body_size` body bytes, buffered or still to come.
    fn discard(&mut self, body_size: u64) {
        let body_buffered = self.buffered().saturating_sub(HEADER_SIZE);
        // now <= the buffered body length, so it fits a usize.
        let now = body_size.min(body_buffered as u64) as usize;
        self.pos += (HEADER_SIZE + now).min(self.buffered());
        self.skip_left = body_size - now as u64;
        self.skip_total = body_size;
    }

    /// To call when the stream ends, after [`Decoder::next_message`] returned `None`: `Ok`
    /// between messages, [`WireError::Truncated`] when a message was cut short.
    pub fn finish(&self) -> Result<(), WireError> {
        if self.skip_left > 0 {
            return Err(WireError::Truncated {
                part: "discarded body",
                expected: self.skip_total,
                got: self.skip_total - self.skip_left,
            });
        }
        let pending = self.pending();
        match pending.first_chunk::<HEADER_SIZE>() {
            None if pending.is_empty() => Ok(()),
            None => Err(WireError::Truncated {
                part: "header",
                expected: HEADER_SIZE as u64,
                got: pending.len() as u64,
            }),
            Some(head) => Err(WireError::Truncated {
                part: "body",
                expected: raw_body_size(head),
                got: (pending.len() - HEADER_SIZE) as u64,
            }),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    // --- helpers ------------------------------------------------------------------------------

    /// Bytes from a hex string; whitespace ignored.
    fn hex(text: &str) -> Vec<u8> {
        let digits: Vec<u8> = text.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
        assert!(digits.len() % 2 == 0, "odd number of hex digits");
        digits
            .chunks(2)
            .map(|pair| {
                let pair = std::str::from_utf8(pair).expect("hex digits are ASCII");
                u8::from_str_radix(pair, 16).expect("valid hex")
            })
            .collect()
    }

    /// A NUL-padded fixed-width text field, built by hand.
    fn field(text: &[u8], width: usize) -> Vec<u8> {
        let mut out = text.to_vec();
        out.resize(width, 0);
        out
    }

    fn be_f32_bytes(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_be_bytes()).collect()
    }

    fn be_u32_bytes(values: &[u32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_be_bytes()).collect()
    }

    /// A version 1 frame around `body` with a correct CRC (computed by the bitwise reference).
    fn frame_v1(type_name: &str, device: &str, body: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(&1u16.to_be_bytes());
        out.extend(field(type_name.as_bytes(), 12));
        out.extend(field(device.as_bytes(), 20));
        out.extend_from_slice(&0u64.to_be_bytes());
        out.extend_from_slice(&(body.len() as u64).to_be_bytes());
        out.extend_from_slice(&crc64_bitwise(body).to_be_bytes());
        out.extend_from_slice(body);
        out
    }

    /// Bit-at-a-time CRC-64/ECMA-182 (MSB first, init 0, no final XOR), independent of the table.
    fn crc64_bitwise(bytes: &[u8]) -> u64 {
        let mut crc = 0u64;
        for &byte in bytes {
            crc ^= u64::from(byte) << 56;
            for _ in 0..8 {
                crc = if crc & (1 << 63) != 0 {
                    (crc << 1) ^ CRC64_POLY
                } else {
                    crc << 1
                };
            }
        }
        crc
    }

    fn decode_err(bytes: &[u8]) -> WireError {
        match decode_message(bytes) {
            Ok(ok) => panic!("expected an error, decoded {ok:?}"),
            Err(e) => e,
        }
    }

    fn content_err(type_name: &str, content: &[u8]) -> String {
        match Message::decode_content(type_name, content) {
            Ok(ok) => panic!("expected an error, decoded {ok:?}"),
            Err(e) => e.to_string(),
        }
    }

    fn roundtrip(message: &Message, options: &EncodeOptions) -> (Header, Message) {
        let bytes = message.encode("dev", options).expect("encodes");
        let (header, decoded) = decode_message(&bytes).expect("decodes");
        assert_eq!(&decoded, message);
        assert_eq!(header.version, options.header_version);
        assert_eq!(header.type_name, message.type_name());
        assert_eq!(header.body_size as usize, bytes.len() - HEADER_SIZE);
        (header, decoded)
    }

    fn sample_points() -> Vec<PointElement> {
        vec![
            PointElement {
                name: "F-1".into(),
                group: "Landmark".into(),
                rgba: [255, 0, 0, 255],
                position_mm: [1.5, -2.25, 3.0],
                diameter_mm: 2.5,
                owner: String::new(),
            },
            PointElement {
                name: "n".repeat(64),
                group: "g".repeat(32),
                rgba: [1, 2, 3, 4],
                position_mm: [-1e6, 0.0, 1e-3],
                diameter_mm: 0.0,
                owner: "o".repeat(20),
            },
        ]
    }

    fn sample_polydata() -> PolyData {
        PolyData {
            points: vec![
                [0.0, 0.0, 0.0],
                [10.0, 0.0, 0.0],
                [0.0, 10.0, 0.0],
                [0.0, 0.0, 10.0],
            ],
            vertices: CellArray::from_cells([[3u32]]),
            lines: CellArray::from_cells([vec![0u32, 1, 2], vec![]]),
            polygons: CellArray::from_cells([[0u32, 1, 2], [0, 1, 3], [0, 2, 3]]),
            triangle_strips: CellArray::from_cells([[0u32, 1, 2, 3]]),
            attributes: vec![
                PolyAttribute {
                    name: "uncertainty_mm".into(),
                    location: AttributeLocation::Point,
                    kind: AttributeKind::Scalar { components: 1 },
                    data: vec![0.5, 1.0, 1.5, 2.0],
                },
                PolyAttribute {
                    name: "displacement".into(),
                    location: AttributeLocation::Point,
                    kind: AttributeKind::Vector,
                    data: (0..12).map(|i| i as f32).collect(),
                },
                PolyAttribute {
                    name: "n".into(),
                    location: AttributeLocation::Point,
                    kind: AttributeKind::Normal,
                    data: [0.0, 0.0, 1.0].repeat(4),
                },
                PolyAttribute {
                    name: "stress".into(),
                    location: AttributeLocation::Cell,
                    kind: AttributeKind::Tensor,
                    data: (0..27).map(|i| i as f32 * 0.25).collect(),
                },
                PolyAttribute {
                    name: "colour".into(),
                    location: AttributeLocation::Cell,
                    kind: AttributeKind::Rgba,
                    data: [0.0, 0.5, 1.0, 1.0].repeat(3),
                },
                PolyAttribute {
                    name: "rg".into(),
                    location: AttributeLocation::Cell,
                    kind: AttributeKind::Scalar { components: 4 },
                    data: vec![0.25; 12],
                },
            ],
        }
    }

    // --- CRC ----------------------------------------------------------------------------------

    #[test]
    fn crc64_check_value_is_ecma_182() {
        // CRC-64/ECMA-182 catalogue check value; pyigtl 0.3.4's crcmod function (the one it
        // signs messages with) gives the same for b"123456789".
        assert_eq!(crc64_bitwise(b"123456789"), 0x6C40_DF5F_0B49_7347);
        assert_eq!(crc64(b"123456789"), 0x6C40_DF5F_0B49_7347);
        assert_eq!(crc64(b""), 0);
    }

    #[test]
    fn crc64_table_matches_reference_and_bitwise() {
        // Entries quoted from the table in OpenIGTLink's igtl_util.c.
        assert_eq!(CRC64_TABLE[1], 0x42F0_E1EB_A9EA_3693);
        assert_eq!(CRC64_TABLE[2], 0x85E1_C3D7_53D4_6D26);
        assert_eq!(CRC64_TABLE[254], 0xD80C_07CD_676F_8394);
        assert_eq!(CRC64_TABLE[255], 0x9AFC_E626_CE85_B507);
        for byte in 0..=255u8 {
            assert_eq!(crc64(&[byte]), crc64_bitwise(&[byte]));
        }
        let mut rng = Rng(7);
        for len in [1, 2, 7, 64, 1000] {
            let data = rng.bytes(len);
            assert_eq!(crc64(&data), crc64_bitwise(&data));
            let (a, b) = data.split_at(len / 2);
            assert_eq!(crc64_update(crc64(a), b), crc64(&data));
        }
    }

    // --- timestamps ---------------------------------------------------------------------------

    #[test]
    fn timestamps_are_32_32_fixed_point() {
        assert_eq!(timestamp_from_secs(1.5), 0x0000_0001_8000_0000);
        assert_eq!(timestamp_to_secs(0x0000_0001_8000_0000), 1.5);
        assert_eq!(
            timestamp_from_secs(1_700_000_000.25),
            (1_700_000_000u64 << 32) | 0x4000_0000
        );
        assert_eq!(timestamp_from_secs(-3.0), 0);
        assert_eq!(timestamp_from_secs(f64::NAN), 0);
        assert_eq!(timestamp_from_secs(1e30), u64::MAX);
        for secs in [0.0, 1e-9, 0.123_456_789, 1_234_567.891, 4_294_967_295.5] {
            let back = timestamp_to_secs(timestamp_from_secs(secs));
            assert!(
                (back - secs).abs() <= 2.4e-10 + secs * f64::EPSILON,
                "{secs} -> {back}"
            );
        }
        let t = std::time::UNIX_EPOCH + std::time::Duration::new(10, 500_000_000);
        assert_eq!(timestamp_from_system_time(t), (10u64 << 32) | 0x8000_0000);
        let before = std::time::UNIX_EPOCH - std::time::Duration::from_secs(1);
        assert_eq!(timestamp_from_system_time(before), 0);
    }

    // --- header -------------------------------------------------------------------------------

    #[test]
    fn header_roundtrip_and_full_width_names() {
        let header = Header {
            version: 2,
            type_name: "ABCDEFGHIJKL".into(), // 12 bytes: no terminator on the wire
            device_name: "D".repeat(20),
            timestamp: 0x0102_0304_0506_0708,
            body_size: 12345,
            crc: 0xDEAD_BEEF_0000_0001,
        };
        let bytes = header.encode().expect("encodes");
        assert_eq!(&bytes[0..2], &[0, 2]);
        assert_eq!(&bytes[2..14], b"ABCDEFGHIJKL");
        assert_eq!(&bytes[42..50], &12345u64.to_be_bytes());
        assert_eq!(Header::parse(&bytes), Ok(header.clone()));
        assert_eq!(header.timestamp_secs(), timestamp_to_secs(header.timestamp));
    }

    #[test]
    fn header_errors() {
        let good = Header {
            version: 1,
            type_name: "POINT".into(),
            device_name: "x".into(),
            timestamp: 0,
            body_size: 0,
            crc: 0,
        };
        let mut bytes = good.encode().expect("encodes");
        bytes[1] = 3;
        assert_eq!(
            Header::parse(&bytes),
            Err(WireError::UnsupportedVersion { version: 3 })
        );
        bytes[1] = 0;
        assert_eq!(
            Header::parse(&bytes),
            Err(WireError::UnsupportedVersion { version: 0 })
        );

        let mut bytes = good.encode().expect("encodes");
        bytes[3] = 0xFF;
        let e = Header::parse(&bytes).expect_err("non-UTF-8 type");
        assert_eq!(
            e.to_string(),
            "header: TYPE is not valid UTF-8 (valid up to byte 1)"
        );
        let mut bytes = good.encode().expect("encodes");
        bytes[14] = 0xC3; // a lone UTF-8 lead byte
        let e = Header::parse(&bytes).expect_err("non-UTF-8 device");
        assert!(
            e.to_string()
                .starts_with("header: DEVICE_NAME is not valid UTF-8"),
            "{e}"
        );

        // Bytes after the terminating NUL are ignored.
        let mut bytes = good.encode().expect("encodes");
        bytes[10] = b'Z';
        assert_eq!(
            Header::parse(&bytes).map(|h| h.type_name),
            Ok("POINT".into())
        );

        let long = Header {
            type_name: "THIRTEEN_CHRS".into(),
            ..good.clone()
        };
        assert_eq!(
            long.encode().expect_err("too long").to_string(),
            "header: TYPE is 13 bytes, at most 12 fit"
        );
        let nul = Header {
            device_name: "a\0b".into(),
            ..good.clone()
        };
        assert_eq!(
            nul.encode().expect_err("NUL").to_string(),
            "header: DEVICE_NAME contains a NUL byte"
        );
        let v3 = Header { version: 3, ..good };
        assert_eq!(
            v3.encode(),
            Err(WireError::UnsupportedVersion { version: 3 })
        );
    }

    // --- TRANSFORM ----------------------------------------------------------------------------

    /// Hand-built from the header table and the TRANSFORM table of the specification: a 90°
    /// rotation about z and a translation of (10, -20, 30.5) mm, elements R11 R21 R31 R12 R22 R32
    /// R13 R23 R33 TX TY TZ. CRC computed with crcmod (the function pyigtl uses), not with this
    /// module.
    fn transform_fixture() -> Vec<u8> {
        let mut bytes = hex("0001"); // V
        bytes.extend(field(b"TRANSFORM", 12)); // TYPE
        bytes.extend(field(b"Tracker", 20)); // DEVICE_NAME
        bytes.extend(hex("00000001 80000000")); // TIME_STAMP 1.5 s
        bytes.extend(hex("00000000 00000030")); // BODY_SIZE 48
        bytes.extend(hex("9C7663F5 F9CD7B70")); // CRC
        bytes.extend(hex("00000000 3F800000 00000000 \
             BF800000 00000000 00000000 \
             00000000 00000000 3F800000 \
             41200000 C1A00000 41F40000"));
        bytes
    }

    #[test]
    fn transform_fixture_from_the_specification() {
        let bytes = transform_fixture();
        let (header, message) = decode_message(&bytes).expect("decodes");
        assert_eq!(header.type_name, "TRANSFORM");
        assert_eq!(header.device_name, "Tracker");
        assert_eq!(header.timestamp_secs(), 1.5);
        let expected = Transform {
            matrix: [
                [0.0, -1.0, 0.0, 10.0],
                [1.0, 0.0, 0.0, -20.0],
                [0.0, 0.0, 1.0, 30.5],
                [0.0, 0.0, 0.0, 1.0],
            ],
        };
        assert_eq!(message, Message::Transform(expected));
        // And the encoder writes exactly those bytes.
        let options = EncodeOptions {
            timestamp: timestamp_from_secs(1.5),
            ..EncodeOptions::default()
        };
        assert_eq!(
            Message::Transform(expected).encode("Tracker", &options),
            Ok(bytes)
        );
    }

    #[test]
    fn transform_roundtrip_v1_and_v2() {
        let mut t = Transform::IDENTITY;
        t.matrix[0] = [0.5, -0.25, 0.125, 100.0];
        t.matrix[2][3] = -0.75;
        roundtrip(&Message::Transform(t), &EncodeOptions::default());
        let (header, _) = roundtrip(&Message::Transform(t), &EncodeOptions::version2(9));
        assert_eq!(header.body_size, 12 + 48 + 2);
        // The v2 frame: extended header {12, 2, 0, 9}, content, INDEX_COUNT 0. CRC from crcmod.
        let bytes = Message::Transform(t)
            .encode("dev", &EncodeOptions::version2(9))
            .expect("encodes");
        assert_eq!(
            &bytes[HEADER_SIZE..HEADER_SIZE + 12],
            &hex("000C 0002 00000000 00000009")
        );
        assert_eq!(&bytes[bytes.len() - 2..], &[0, 0]);
        let v2 = Message::Transform(
            Transform::decode_content(&transform_fixture()[HEADER_SIZE..]).expect("ok"),
        )
        .encode("dev", &EncodeOptions::version2(9))
        .expect("encodes");
        assert_eq!(&v2[50..58], &hex("C613EA0A 4F4072AC"));
        let parts = split_body(
            &Header::parse(v2.first_chunk().expect("58")).expect("h"),
            &v2[HEADER_SIZE..],
        )
        .expect("splits");
        assert_eq!(parts.extended.map(|e| e.message_id), Some(9));
        assert_eq!(parts.content.len(), 48);
        assert_eq!(parts.metadata_header, &[0, 0]);
    }

    #[test]
    fn transform_errors() {
        assert_eq!(
            content_err("TRANSFORM", &[0; 47]),
            "TRANSFORM: content is 47 bytes, a TRANSFORM has exactly 48 (12 float32)"
        );
        assert!(content_err("TRANSFORM", &[0; 52]).contains("is 52 bytes"));
        let mut projective = Transform::IDENTITY;
        projective.matrix[3][0] = 0.1;
        let e = Message::Transform(projective)
            .encode("d", &EncodeOptions::default())
            .expect_err("row 4");
        assert!(
            e.to_string()
                .starts_with("TRANSFORM: matrix row 4 is [0.1, 0.0, 0.0, 1.0]"),
            "{e}"
        );
    }

    // --- POINT --------------------------------------------------------------------------------

    /// Hand-built from the POINT_DATA table: NAME char[64], GROUP char[32], RGBA, XYZ, DIAMETER,
    /// OWNER char[20]. CRC computed with crcmod.
    fn point_fixture() -> Vec<u8> {
        let mut body = field(b"tip", 64);
        body.extend(field(b"Landmark", 32));
        body.extend(hex("10 20 30 FF"));
        body.extend(hex("3F800000 C0200000 447A0000")); // 1, -2.5, 1000 mm
        body.extend(hex("40000000")); // diameter 2 mm
        body.extend(field(b"CT", 20));
        assert_eq!(body.len(), 136);
        let mut bytes = hex("0001");
        bytes.extend(field(b"POINT", 12));
        bytes.extend(field(b"Stylus", 20));
        bytes.extend(hex("00000000 00000000"));
        bytes.extend(hex("00000000 00000088")); // 136
        bytes.extend(hex("7D8DE2A0 A2A8E777"));
        bytes.extend(body);
        bytes
    }

    #[test]
    fn point_fixture_from_the_specification() {
        let bytes = point_fixture();
        let (header, message) = decode_message(&bytes).expect("decodes");
        assert_eq!(header.device_name, "Stylus");
        let expected = vec![PointElement {
            name: "tip".into(),
            group: "Landmark".into(),
            rgba: [0x10, 0x20, 0x30, 0xFF],
            position_mm: [1.0, -2.5, 1000.0],
            diameter_mm: 2.0,
            owner: "CT".into(),
        }];
        assert_eq!(message, Message::Point(expected.clone()));
        assert_eq!(
            Message::Point(expected).encode("Stylus", &EncodeOptions::default()),
            Ok(bytes)
        );
    }

    #[test]
    fn point_roundtrip() {
        roundtrip(&Message::Point(sample_points()), &EncodeOptions::default());
        roundtrip(
            &Message::Point(sample_points()),
            &EncodeOptions::version2(1),
        );
        roundtrip(&Message::Point(Vec::new()), &EncodeOptions::default());
        let many: Vec<PointElement> = (0..500)
            .map(|i| PointElement {
                name: format!("p{i}"),
                group: "Surface".into(),
                rgba: [0, 0, 0, 255],
                position_mm: [i as f32, -(i as f32), 0.5],
                diameter_mm: 1.0,
                owner: String::new(),
            })
            .collect();
        roundtrip(&Message::Point(many), &EncodeOptions::default());
    }

    #[test]
    fn point_errors() {
        assert_eq!(
            content_err("POINT", &[0; 137]),
            "POINT: content is 137 bytes, not a multiple of the 136-byte POINT_DATA element"
        );
        let mut body = point_fixture()[HEADER_SIZE..].to_vec();
        body.extend_from_within(..);
        body[136 + 64] = 0xFF; // second element's GROUP
        assert_eq!(
            content_err("POINT", &body),
            "POINT: point 1 GROUP is not valid UTF-8 (valid up to byte 0)"
        );
        body[136 + 64] = b'G';
        body[136 + 116] = 0x80; // second element's OWNER
        assert!(content_err("POINT", &body).starts_with("POINT: point 1 OWNER is not valid UTF-8"));

        let mut points = sample_points();
        points[1].name.push('x');
        let e = Message::Point(points)
            .encode("d", &EncodeOptions::default())
            .expect_err("long name");
        assert_eq!(
            e.to_string(),
            "POINT: point 1 NAME is 65 bytes, at most 64 fit"
        );
        let mut points = sample_points();
        points[0].owner = "a\0".into();
        let e = Message::Point(points)
            .encode("d", &EncodeOptions::default())
            .expect_err("NUL");
        assert_eq!(e.to_string(), "POINT: point 0 OWNER contains a NUL byte");
    }

    // --- STATUS -------------------------------------------------------------------------------

    #[test]
    fn status_roundtrip_and_codes() {
        for code in 0..=19u16 {
            let status = Status {
                code,
                subcode: -(i64::from(code)) * 1_000_000_007,
                error_name: status_code::describe(code)
                    .map(|d| d.chars().take(20).collect())
                    .unwrap_or_default(),
                message: format!(
                    "code {code}: {}",
                    status_code::describe(code).unwrap_or("?")
                ),
            };
            roundtrip(&Message::Status(status), &EncodeOptions::default());
        }
        assert_eq!(status_code::describe(20), None);
        assert_eq!(status_code::OK, 1);
        assert_eq!(status_code::ILLEGAL_INSTRUCTION, 12);
        assert_eq!(status_code::SHUT_DOWN, 19);
        let empty = Status {
            code: 1,
            subcode: 0,
            error_name: String::new(),
            message: String::new(),
        };
        let (header, _) = roundtrip(&Message::Status(empty), &EncodeOptions::version2(3));
        assert_eq!(header.body_size, 12 + 31 + 2);
    }

    #[test]
    fn status_layout_and_lenient_message() {
        // Hand-built: C=9, SUB_CODE=-1, ERROR_NAME "CRC", MESSAGE "bad\0".
        let mut content = hex("0009 FFFFFFFFFFFFFFFF");
        content.extend(field(b"CRC", 20));
        content.extend(b"bad\0");
        let expected = Status {
            code: 9,
            subcode: -1,
            error_name: "CRC".into(),
            message: "bad".into(),
        };
        assert_eq!(
            Message::decode_content("STATUS", &content),
            Ok(Message::Status(expected.clone()))
        );
        assert_eq!(
            Message::Status(expected).encode_content(),
            Ok(content.clone())
        );
        // Without the terminator the message is taken whole; with none at all it is empty.
        content.pop();
        assert!(
            matches!(Message::decode_content("STATUS", &content), Ok(Message::Status(s)) if s.message == "bad")
        );
        assert!(
            matches!(Message::decode_content("STATUS", &content[..30]), Ok(Message::Status(s)) if s.message.is_empty())
        );
    }

    #[test]
    fn status_errors() {
        assert_eq!(
            content_err("STATUS", &[0; 29]),
            "STATUS: C, SUB_CODE and ERROR_NAME needs 30 bytes but 29 remain"
        );
        let mut content = vec![0; 30];
        content.extend(b"\xFFoops\0");
        assert_eq!(
            content_err("STATUS", &content),
            "STATUS: MESSAGE is not valid UTF-8 (valid up to byte 0)"
        );
        let status = Status {
            code: 2,
            subcode: 0,
            error_name: "e".repeat(21),
            message: String::new(),
        };
        let e = Message::Status(status).encode_content().expect_err("long");
        assert_eq!(
            e.to_string(),
            "STATUS: ERROR_NAME is 21 bytes, at most 20 fit"
        );
        let status = Status {
            code: 2,
            subcode: 0,
            error_name: String::new(),
            message: "a\0b".into(),
        };
        let e = Message::Status(status).encode_content().expect_err("NUL");
        assert_eq!(e.to_string(), "STATUS: MESSAGE contains a NUL byte");
    }

    // --- POLYDATA -----------------------------------------------------------------------------

    /// Hand-built from the POLYDATA tables: 3 points, one triangle, a 1-component point scalar
    /// "u" and a point vector "disp"; names "u\0disp\0" (7 bytes) padded to 8. CRC from crcmod.
    fn polydata_fixture_content() -> Vec<u8> {
        let mut c = be_u32_bytes(&[3, 0, 0, 0, 0, 1, 16, 0, 0, 2]);
        c.extend(be_f32_bytes(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]));
        c.extend(be_u32_bytes(&[3, 0, 1, 2]));
        c.extend(hex("00 01 00000003")); // POINT_DATA scalar, 1 component, 3 tuples
        c.extend(hex("01 03 00000003")); // POINT_DATA vector, 3 components, 3 tuples
        c.extend(b"u\0disp\0\0");
        c.extend(be_f32_bytes(&[0.5, 1.5, 2.5]));
        c.extend(be_f32_bytes(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]));
        assert_eq!(c.len(), 160);
        c
    }

    #[test]
    fn polydata_fixture_from_the_specification() {
        let content = polydata_fixture_content();
        assert_eq!(crc64(&content), 0xAD21_92C9_69CB_F549);
        let decoded = Message::decode_content("POLYDATA", &content).expect("decodes");
        let Message::PolyData(poly) = &decoded else {
            panic!("not POLYDATA: {decoded:?}")
        };
        assert_eq!(
            poly.points,
            vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
        );
        assert_eq!(
            poly.polygons.iter().collect::<Vec<_>>(),
            vec![&[0u32, 1, 2][..]]
        );
        assert!(
            poly.vertices.is_empty() && poly.lines.is_empty() && poly.triangle_strips.is_empty()
        );
        assert_eq!(poly.attributes.len(), 2);
        assert_eq!(poly.attributes[0].name, "u");
        assert_eq!(
            poly.attributes[0].kind,
            AttributeKind::Scalar { components: 1 }
        );
        assert_eq!(poly.attributes[0].type_attribute(), 0x0001);
        assert_eq!(poly.attributes[1].kind, AttributeKind::Vector);
        assert_eq!(poly.attributes[1].location, AttributeLocation::Point);
        assert_eq!(poly.attributes[1].type_attribute(), 0x0103);
        assert_eq!(poly.attributes[1].tuple_count(), 3);
        assert_eq!(decoded.encode_content(), Ok(content));
    }

    #[test]
    fn polydata_roundtrip_all_attribute_kinds() {
        let poly = sample_polydata();
        let (_, decoded) = roundtrip(&Message::PolyData(poly.clone()), &EncodeOptions::default());
        roundtrip(&decoded, &EncodeOptions::version2(77));
        // Cell data sets bit 4 of the type byte.
        assert_eq!(poly.attributes[3].type_attribute(), 0x1309);
        assert_eq!(poly.attributes[4].type_attribute(), 0x1404);
        assert_eq!(poly.attributes[5].type_attribute(), 0x1004);
        // Even total name length: no padding byte.
        let mut even = poly.clone();
        even.attributes.truncate(1); // "uncertainty_mm\0" is 15 bytes: padded
        let odd_len = Message::PolyData(even.clone())
            .encode_content()
            .expect("ok")
            .len();
        even.attributes[0].name = "uncertainty_m".into(); // 14 bytes with NUL: no padding
        let even_len = Message::PolyData(even.clone())
            .encode_content()
            .expect("ok")
            .len();
        assert_eq!(odd_len, even_len + 2);
        roundtrip(&Message::PolyData(even), &EncodeOptions::default());
        roundtrip(
            &Message::PolyData(PolyData::default()),
            &EncodeOptions::default(),
        );
        // CellArray accessors.
        assert_eq!(poly.lines.get(1), Some(&[][..]));
        assert_eq!(poly.lines.get(2), None);
        assert_eq!(poly.polygons.indices().len(), 9);
        assert_eq!(poly.polygons.wire_size(), 4 * 12);
    }

    /// A POLYDATA content with the given header words and a tail.
    fn polydata_with(header: [u32; 10], tail: &[u8]) -> Vec<u8> {
        let mut c = be_u32_bytes(&header);
        c.extend_from_slice(tail);
        c
    }

    #[test]
    fn polydata_count_errors() {
        assert_eq!(
            content_err("POLYDATA", &[0; 39]),
            "POLYDATA: header (NPOINTS ... NATTRIBUTES) needs 40 bytes but 39 remain"
        );
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([2, 0, 0, 0, 0, 0, 0, 0, 0, 0], &[0; 20])
            ),
            "POLYDATA: NPOINTS 2 says 24 bytes but 20 remain"
        );
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([0, 0, 0, 0, 0, 1, 400, 0, 0, 0], &[0; 120])
            ),
            "POLYDATA: SIZE_POLYGONS says 400 bytes but 120 remain"
        );
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([0, 0, 0, 1, 6, 0, 0, 0, 0, 0], &[0; 8])
            ),
            "POLYDATA: SIZE_LINES is 6, not a multiple of 4 (uint32 indices)"
        );
        // Two strips announced, the section holds one.
        let tail = be_u32_bytes(&[0]);
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([0, 0, 0, 0, 0, 0, 0, 2, 4, 0], &tail)
            ),
            "POLYDATA: NTRIANGLE_STRIPS is 2 but SIZE_TRIANGLE_STRIPS (4 bytes) holds only 1 cells"
        );
        // A cell whose NINDICES runs past the section.
        let mut tail = be_f32_bytes(&[0.0; 9]);
        tail.extend(be_u32_bytes(&[5, 0, 1]));
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([3, 0, 0, 0, 0, 1, 12, 0, 0, 0], &tail)
            ),
            "POLYDATA: POLYGONS cell 0 NINDICES 5 says 20 bytes but 8 remain"
        );
        // An index past NPOINTS.
        let mut tail = be_f32_bytes(&[0.0; 9]);
        tail.extend(be_u32_bytes(&[3, 0, 1, 3]));
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([3, 0, 0, 0, 0, 1, 16, 0, 0, 0], &tail)
            ),
            "POLYDATA: POLYGONS cell 0 has point index 3, out of range (NPOINTS 3)"
        );
        // A section larger than its cells.
        let tail = be_u32_bytes(&[0, 0]);
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([0, 1, 8, 0, 0, 0, 0, 0, 0, 0], &tail)
            ),
            "POLYDATA: SIZE_VERTICES is 8 bytes but its NVERTICES 1 cells use 4"
        );
        // Huge counts never allocate: they fail on the size check.
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([u32::MAX, 0, 0, 0, 0, 0, 0, 0, 0, 0], &[])
            ),
            "POLYDATA: NPOINTS 4294967295 says 51539607540 bytes but 0 remain"
        );
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([0, u32::MAX, 0, 0, 0, 0, 0, 0, 0, 0], &[])
            ),
            "POLYDATA: NVERTICES is 4294967295 but SIZE_VERTICES (0 bytes) holds only 0 cells"
        );
        assert_eq!(
            content_err(
                "POLYDATA",
                &polydata_with([0, 0, 0, 0, 0, 0, 0, 0, 0, u32::MAX], &[0; 12])
            ),
            "POLYDATA: NATTRIBUTES 4294967295 says 25769803770 bytes but 12 remain"
        );
        // Bytes after the last attribute / after the cells.
        let mut content = polydata_fixture_content();
        content.extend([0, 0, 0, 0]);
        assert_eq!(
            content_err("POLYDATA", &content),
            "POLYDATA: 4 unexplained bytes after the data of attribute 1"
        );
        assert_eq!(
            content_err("POLYDATA", &polydata_with([0; 10], &[1])),
            "POLYDATA: 1 unexplained bytes after TRIANGLE_STRIPS (NATTRIBUTES 0)"
        );
        // Attribute data shorter than NATTRIBUTE x components.
        let content = polydata_fixture_content();
        assert_eq!(
            content_err("POLYDATA", &content[..content.len() - 4]),
            "POLYDATA: attribute 1 \"disp\" NATTRIBUTE 3 x 3 components says 36 bytes but 32 remain"
        );
    }

    #[test]
    fn polydata_attribute_errors() {
        // Offset of the first attribute header in the fixture: 40 + 36 + 16.
        const AT: usize = 92;
        let edit = |offset: usize, bytes: &[u8]| {
            let mut c = polydata_fixture_content();
            c[AT + offset..AT + offset + bytes.len()].copy_from_slice(bytes);
            content_err("POLYDATA", &c)
        };
        assert_eq!(
            edit(0, &[0x20]),
            "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x2001 has a type other than POINT_DATA (0x0_) or CELL_DATA (0x1_)"
        );
        assert_eq!(
            edit(0, &[0x07]),
            "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0701 has unknown attribute type 0x07"
        );
        assert_eq!(
            edit(0, &[0x05, 0x03]),
            "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0503 is texture coordinates (0x05), which the specification does not define"
        );
        assert_eq!(
            edit(1, &[0x00]),
            "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0000 has 0 components where a scalar has 1 to 127"
        );
        assert_eq!(
            edit(1, &[0x80]),
            "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0080 has 128 components where a scalar has 1 to 127"
        );
        assert_eq!(
            edit(6, &[0x12, 0x09]),
            "POLYDATA: attribute 1 TYPE_ATTRIBUTE 0x1209 has 9 components where a normal has 3 (the reference \
             C library writes 9 for cell and RGBA attributes, OpenIGTLink issue #36)"
        );
        assert_eq!(
            edit(6, &[0x03, 0x03]),
            "POLYDATA: attribute 1 TYPE_ATTRIBUTE 0x0303 has 3 components where a tensor has 9"
        );
        assert_eq!(
            edit(12, &[0xFF]),
            "POLYDATA: NAME_ATTRIBUTE_0 is not valid UTF-8 (valid up to byte 0)"
        );
        // Scalars may have more than one component (the data must then be longer).
        assert_eq!(
            edit(1, &[0x02]),
            "POLYDATA: attribute 1 \"disp\" NATTRIBUTE 3 x 3 components says 36 bytes but 24 remain"
        );

        // Names: unterminated, longer than 255, missing padding.
        let mut c = polydata_fixture_content();
        c.truncate(AT + 12);
        c.extend(b"u\0disp");
        assert_eq!(
            content_err("POLYDATA", &c),
            "POLYDATA: NAME_ATTRIBUTE_1 has no NUL terminator before the content ends"
        );
        let mut c = polydata_fixture_content();
        c.truncate(AT + 12);
        c.extend(vec![b'a'; 300]);
        assert_eq!(
            content_err("POLYDATA", &c),
            "POLYDATA: NAME_ATTRIBUTE_0 has no NUL terminator within 256 bytes (at most 255 allowed)"
        );
        let mut c = polydata_fixture_content();
        c.truncate(AT + 12 + 7);
        assert_eq!(
            content_err("POLYDATA", &c),
            "POLYDATA: ATTRIBUTE_NAMES padding needs 1 bytes but 0 remain"
        );
    }

    #[test]
    fn polydata_encode_errors() {
        let encode = |poly: PolyData| {
            Message::PolyData(poly)
                .encode_content()
                .expect_err("invalid")
                .to_string()
        };
        let mut p = sample_polydata();
        p.polygons.push(&[0, 4]);
        assert_eq!(
            encode(p),
            "POLYDATA: POLYGONS cell 3 has point index 4, out of range (NPOINTS 4)"
        );
        let mut p = sample_polydata();
        p.attributes[0].kind = AttributeKind::Scalar { components: 0 };
        assert_eq!(
            encode(p),
            "POLYDATA: attribute 0 \"uncertainty_mm\" NCOMPONENTS is 0; scalars have 1 to 127 components"
        );
        let mut p = sample_polydata();
        p.attributes[1].data.pop();
        assert_eq!(
            encode(p),
            "POLYDATA: attribute 1 \"displacement\" data has 11 values, not a multiple of its 3 components"
        );
        let mut p = sample_polydata();
        p.attributes[2].name = "x".repeat(256);
        assert_eq!(
            encode(p),
            "POLYDATA: NAME_ATTRIBUTE_2 is 256 bytes, at most 255 fit"
        );
        let mut p = sample_polydata();
        p.attributes[2].name = "a\0".into();
        assert_eq!(encode(p), "POLYDATA: NAME_ATTRIBUTE_2 contains a NUL byte");
    }

    // --- version 2 bodies ---------------------------------------------------------------------

    /// A version 2 frame with the given extended header fields, content and metadata bytes.
    fn frame_v2(type_name: &str, ext: [u32; 4], content: &[u8], metadata: &[u8]) -> Vec<u8> {
        let mut body = Vec::new();
        body.extend_from_slice(&(ext[0] as u16).to_be_bytes());
        body.extend_from_slice(&(ext[1] as u16).to_be_bytes());
        body.extend_from_slice(&ext[2].to_be_bytes());
        body.extend_from_slice(&ext[3].to_be_bytes());
        body.extend_from_slice(content);
        body.extend_from_slice(metadata);
        let mut out = frame_v1(type_name, "dev", &body);
        out[1] = 2;
        out
    }

    #[test]
    fn version2_metadata_is_skipped() {
        let content = transform_fixture()[HEADER_SIZE..].to_vec();
        // INDEX_COUNT 1: key "Units" (5), encoding 3 (US-ASCII), value "mm" (2).
        let mut meta = hex("0001 0005 0003 00000002");
        meta.extend(b"Unitsmm");
        let bytes = frame_v2("TRANSFORM", [12, 10, 7, 42], &content, &meta);
        let (header, message) = decode_message(&bytes).expect("decodes");
        assert_eq!(header.version, 2);
        assert!(matches!(message, Message::Transform(t) if t.matrix[2][3] == 30.5));
        // A longer extended header (future fields) is skipped too.
        let mut longer = vec![0xAB, 0xCD];
        longer.extend(&content);
        let bytes = frame_v2("TRANSFORM", [14, 10, 7, 42], &longer, &meta);
        assert!(matches!(
            decode_message(&bytes),
            Ok((_, Message::Transform(_)))
        ));
        // Unknown types expose the content only.
        let bytes = frame_v2("GET_STATUS", [12, 10, 7, 1], b"xyz", &meta);
        assert_eq!(
            decode_message(&bytes).map(|(_, m)| m),
            Ok(Message::Unknown {
                type_name: "GET_STATUS".into(),
                body: b"xyz".to_vec()
            })
        );
    }

    #[test]
    fn version2_empty_body_is_empty_content() {
        let mut bytes = frame_v1("GET_STATUS", "dev", &[]);
        bytes[1] = 2;
        assert_eq!(
            decode_message(&bytes).map(|(_, m)| m),
            Ok(Message::Unknown {
                type_name: "GET_STATUS".into(),
                body: vec![]
            })
        );
    }

    #[test]
    fn version2_errors() {
        let content = [0u8; 48];
        let err = |bytes: Vec<u8>| decode_err(&bytes).to_string();
        let mut short = frame_v1("TRANSFORM", "dev", &[0; 11]);
        short[1] = 2;
        assert_eq!(
            err(short),
            "extended header: EXT_HEADER_SIZE, META_HEADER_SIZE, META_SIZE and MSG_ID needs 12 bytes but 11 remain"
        );
        assert_eq!(
            err(frame_v2("TRANSFORM", [8, 2, 0, 0], &content, &[0, 0])),
            "extended header: EXT_HEADER_SIZE is 8, at least 12 expected"
        );
        assert_eq!(
            err(frame_v2("TRANSFORM", [100, 2, 0, 0], &content, &[0, 0])),
            "extended header: EXT_HEADER_SIZE 100 says 88 bytes but 50 remain"
        );
        assert_eq!(
            err(frame_v2("TRANSFORM", [12, 60, 0, 0], &content, &[0, 0])),
            "extended header: META_HEADER_SIZE 60 + META_SIZE 0 says 60 bytes but 50 remain"
        );
        // Sizes that fit the body but not the content show up as a content of the wrong length.
        assert_eq!(
            err(frame_v2("TRANSFORM", [12, 2, 9, 0], &content, &[0, 0])),
            "TRANSFORM: content is 39 bytes, a TRANSFORM has exactly 48 (12 float32)"
        );
    }

    #[test]
    fn version2_metadata_errors() {
        let content = [0u8; 48];
        let err = |bytes: Vec<u8>| decode_err(&bytes).to_string();
        assert_eq!(
            err(frame_v2(
                "TRANSFORM",
                [12, 2, 3, 0],
                &content,
                &hex("0002 616263")
            )),
            "metadata: INDEX_COUNT 2 says 16 bytes but 0 remain"
        );
        assert_eq!(
            err(frame_v2(
                "TRANSFORM",
                [12, 10, 3, 0],
                &content,
                &hex("0001 0002 0003 00000002 616263")
            )),
            "metadata: KEY_SIZE + VALUE_SIZE of 1 entries says 4 bytes but 3 remain"
        );
        assert_eq!(
            err(frame_v2(
                "TRANSFORM",
                [12, 0, 3, 0],
                &content,
                &hex("616263")
            )),
            "metadata: META_SIZE is 3 but META_HEADER_SIZE is 0"
        );
        assert_eq!(
            err(frame_v2("TRANSFORM", [12, 1, 0, 0], &content, &hex("00"))),
            "metadata: INDEX_COUNT needs 2 bytes but 1 remain"
        );
    }

    // --- message-level errors -----------------------------------------------------------------

    #[test]
    fn crc_and_body_length_errors() {
        let mut bytes = transform_fixture();
        bytes[HEADER_SIZE + 5] ^= 0x10;
        assert_eq!(
            decode_err(&bytes).to_string(),
            format!(
                "TRANSFORM from device \"Tracker\": CRC mismatch: header says 0x9C7663F5F9CD7B70, body computes 0x{:016X}",
                crc64(&bytes[HEADER_SIZE..])
            )
        );
        let bytes = transform_fixture();
        let header = Header::parse(bytes.first_chunk().expect("58")).expect("parses");
        assert_eq!(
            Message::decode(&header, &bytes[HEADER_SIZE + 1..])
                .expect_err("short")
                .to_string(),
            "header: BODY_SIZE says 48 bytes but 47 were given"
        );
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(
            decode_err(&long),
            WireError::BodyLength {
                declared: 48,
                given: 49
            }
        );
        assert_eq!(
            decode_err(&bytes[..57]),
            WireError::Truncated {
                part: "header",
                expected: 58,
                got: 57
            }
        );
    }

    #[test]
    fn unknown_types_decode_to_unknown() {
        let bytes = frame_v1("IMAGE", "US", b"\x01\x02\x03");
        let (_, message) = decode_message(&bytes).expect("decodes");
        assert_eq!(
            message,
            Message::Unknown {
                type_name: "IMAGE".into(),
                body: vec![1, 2, 3]
            }
        );
        assert_eq!(message.type_name(), "IMAGE");
        assert_eq!(
            message
                .clone()
                .require_known()
                .expect_err("unknown")
                .to_string(),
            "message type \"IMAGE\" is not supported"
        );
        roundtrip(&message, &EncodeOptions::default());
        let get = Message::Unknown {
            type_name: "GET_TRANS".into(),
            body: vec![],
        };
        roundtrip(&get, &EncodeOptions::version2(5));
        assert!(Message::Point(vec![]).require_known().is_ok());
        assert_eq!(
            Message::Unknown {
                type_name: "A_VERY_LONG_TYPE".into(),
                body: vec![]
            }
            .encode("d", &EncodeOptions::default())
            .expect_err("long")
            .to_string(),
            "header: TYPE is 16 bytes, at most 12 fit"
        );
        let options = EncodeOptions {
            header_version: 3,
            ..EncodeOptions::default()
        };
        assert_eq!(
            Message::Point(vec![]).encode("d", &options),
            Err(WireError::UnsupportedVersion { version: 3 })
        );
    }

    #[test]
    fn error_display_and_recoverability() {
        let io = WireError::Io {
            kind: io::ErrorKind::ConnectionReset,
            message: "reset".into(),
        };
        assert_eq!(io.to_string(), "I/O error: reset");
        assert!(!io.is_recoverable());
        assert_eq!(
            WireError::EndOfStream.to_string(),
            "stream ended (no further message)"
        );
        assert!(!WireError::EndOfStream.is_recoverable());
        let t = WireError::Truncated {
            part: "body",
            expected: 10,
            got: 3,
        };
        assert_eq!(
            t.to_string(),
            "stream ended inside the message body: 3 of 10 bytes arrived"
        );
        assert!(!t.is_recoverable());
        assert!(!WireError::UnsupportedVersion { version: 9 }.is_recoverable());
        assert!(
            WireError::UnsupportedVersion { version: 9 }
                .to_string()
                .starts_with("header: VERSION 9 is not supported")
        );
        let big = WireError::BodyTooLarge {
            type_name: "IMAGE".into(),
            body_size: 100,
            limit: 10,
        };
        assert_eq!(
            big.to_string(),
            "header: BODY_SIZE 100 of a \"IMAGE\" message exceeds the limit of 10 bytes (body discarded)"
        );
        assert!(big.is_recoverable());
        let crc = WireError::BadCrc {
            type_name: "POINT".into(),
            device_name: "d".into(),
            header_crc: 1,
            computed_crc: 2,
        };
        assert!(crc.is_recoverable());
        let as_dyn: &dyn std::error::Error = &crc;
        assert!(as_dyn.to_string().contains("CRC mismatch"));
    }

    // --- framing ------------------------------------------------------------------------------

    fn three_messages_with_bad_crc_in_the_middle() -> (Vec<u8>, Vec<Message>) {
        let a = Message::Point(sample_points());
        let b = Message::PolyData(sample_polydata());
        let c = Message::Status(Status {
            code: 1,
            subcode: 0,
            error_name: "OK".into(),
            message: "fine".into(),
        });
        let mut stream = a.encode("a", &EncodeOptions::default()).expect("a");
        let mut bad = b.encode("b", &EncodeOptions::version2(2)).expect("b");
        let last = bad.len() - 5;
        bad[last] ^= 0x01;
        stream.extend(bad);
        stream.extend(c.encode("c", &EncodeOptions::default()).expect("c"));
        (stream, vec![a, b, c])
    }

    #[test]
    fn read_message_continues_after_bad_crc() {
        let (stream, messages) = three_messages_with_bad_crc_in_the_middle();
        let mut cursor = Cursor::new(stream);
        assert_eq!(
            read_message(&mut cursor).map(|(_, m)| m),
            Ok(messages[0].clone())
        );
        assert!(
            matches!(read_message(&mut cursor), Err(WireError::BadCrc { ref type_name, .. }) if type_name == "POLYDATA")
        );
        assert_eq!(
            read_message(&mut cursor).map(|(_, m)| m),
            Ok(messages[2].clone())
        );
        assert_eq!(read_message(&mut cursor), Err(WireError::EndOfStream));
    }

    #[test]
    fn decoder_continues_after_bad_crc_byte_by_byte() {
        let (stream, messages) = three_messages_with_bad_crc_in_the_middle();
        let mut decoder = Decoder::new();
        let mut results = Vec::new();
        for byte in &stream {
            decoder.feed(std::slice::from_ref(byte));
            while let Some(result) = decoder.next_message() {
                results.push(result);
            }
        }
        assert_eq!(decoder.finish(), Ok(()));
        assert!(decoder.is_at_boundary());
        assert_eq!(results.len(), 3);
        assert_eq!(results[0].as_ref().map(|(_, m)| m), Ok(&messages[0]));
        assert!(matches!(results[1], Err(WireError::BadCrc { .. })));
        assert_eq!(results[2].as_ref().map(|(_, m)| m), Ok(&messages[2]));
        // All at once gives the same.
        let mut decoder = Decoder::default();
        decoder.feed(&stream);
        let all: Vec<_> = std::iter::from_fn(|| decoder.next_message()).collect();
        assert_eq!(all, results);
    }

    #[test]
    fn decoder_handles_many_messages_in_one_chunk() {
        // 20 000 small messages fed at once: consumed by offset, not by moving the buffer each time.
        let one = Message::Point(sample_points()[..1].to_vec())
            .encode("s", &EncodeOptions::default())
            .expect("ok");
        let stream = one.repeat(20_000);
        let mut decoder = Decoder::new();
        decoder.feed(&stream);
        let started = std::time::Instant::now();
        let count = std::iter::from_fn(|| decoder.next_message())
            .filter(Result::is_ok)
            .count();
        assert_eq!(count, 20_000);
        assert!(decoder.is_at_boundary());
        assert!(started.elapsed().as_secs() < 10);
        decoder.feed(&one[..10]);
        assert_eq!(decoder.buffered(), 10);
    }

    #[test]
    fn oversized_bodies_are_discarded_without_buffering() {
        let big = Message::Unknown {
            type_name: "IMAGE".into(),
            body: vec![7; 1000],
        };
        let after = Message::Transform(Transform::IDENTITY);
        let mut stream = big.encode("us", &EncodeOptions::default()).expect("big");
        stream.extend(after.encode("t", &EncodeOptions::default()).expect("after"));

        let mut decoder = Decoder::with_max_body_size(100);
        assert_eq!(decoder.max_body_size(), 100);
        let mut results = Vec::new();
        for chunk in stream.chunks(64) {
            decoder.feed(chunk);
            assert!(
                decoder.buffered() <= 64 + HEADER_SIZE + 48,
                "buffered {}",
                decoder.buffered()
            );
            while let Some(result) = decoder.next_message() {
                results.push(result.map(|(_, m)| m));
            }
        }
        assert_eq!(
            results,
            vec![
                Err(WireError::BodyTooLarge {
                    type_name: "IMAGE".into(),
                    body_size: 1000,
                    limit: 100
                }),
                Ok(after.clone())
            ]
        );

        let mut cursor = Cursor::new(stream);
        assert_eq!(
            read_message_with_limit(&mut cursor, 100),
            Err(WireError::BodyTooLarge {
                type_name: "IMAGE".into(),
                body_size: 1000,
                limit: 100
            })
        );
        assert_eq!(
            read_message_with_limit(&mut cursor, 100).map(|(_, m)| m),
            Ok(after)
        );
    }

    #[test]
    fn header_errors_skip_the_frame() {
        let mut bad = frame_v1("POINT", "d", &[1, 2, 3]);
        bad[14] = 0xFF; // device name not UTF-8
        let good = Message::Transform(Transform::IDENTITY)
            .encode("t", &EncodeOptions::default())
            .expect("ok");
        let mut stream = bad.clone();
        stream.extend(&good);
        let mut cursor = Cursor::new(stream.clone());
        assert!(matches!(
            read_message(&mut cursor),
            Err(WireError::Text { .. })
        ));
        assert!(matches!(
            read_message(&mut cursor),
            Ok((_, Message::Transform(_)))
        ));
        let mut decoder = Decoder::new();
        decoder.feed(&stream);
        assert!(matches!(
            decoder.next_message(),
            Some(Err(WireError::Text { .. }))
        ));
        assert!(matches!(
            decoder.next_message(),
            Some(Ok((_, Message::Transform(_))))
        ));
        assert_eq!(decoder.next_message(), None);

        // A foreign version: only the header is consumed, whatever BODY_SIZE says.
        let mut foreign = frame_v1("POINT", "d", &[1, 2, 3]);
        foreign[0..2].copy_from_slice(b"GE");
        foreign[42..50].copy_from_slice(&u64::MAX.to_be_bytes());
        let mut cursor = Cursor::new(foreign.clone());
        assert_eq!(
            read_message(&mut cursor),
            Err(WireError::UnsupportedVersion { version: 0x4745 })
        );
        assert_eq!(cursor.position(), HEADER_SIZE as u64);
        let mut decoder = Decoder::new();
        decoder.feed(&foreign);
        assert_eq!(
            decoder.next_message(),
            Some(Err(WireError::UnsupportedVersion { version: 0x4745 }))
        );
        assert_eq!(decoder.buffered(), 3);
    }

    #[test]
    fn truncation_and_end_of_stream() {
        let bytes = transform_fixture();
        assert_eq!(
            read_message(&mut Cursor::new(Vec::new())),
            Err(WireError::EndOfStream)
        );
        assert_eq!(
            read_message(&mut Cursor::new(bytes[..20].to_vec())),
            Err(WireError::Truncated {
                part: "header",
                expected: 58,
                got: 20
            })
        );
        assert_eq!(
            read_message(&mut Cursor::new(bytes[..70].to_vec())),
            Err(WireError::Truncated {
                part: "body",
                expected: 48,
                got: 12
            })
        );
        let mut big = frame_v1("IMAGE", "d", &[0; 50]);
        big.truncate(80);
        assert_eq!(
            read_message_with_limit(&mut Cursor::new(big.clone()), 10),
            Err(WireError::Truncated {
                part: "discarded body",
                expected: 50,
                got: 22
            })
        );

        let mut decoder = Decoder::new();
        assert_eq!(decoder.finish(), Ok(()));
        decoder.feed(&bytes[..20]);
        assert_eq!(decoder.next_message(), None);
        assert_eq!(
            decoder.finish(),
            Err(WireError::Truncated {
                part: "header",
                expected: 58,
                got: 20
            })
        );
        decoder.feed(&bytes[20..70]);
        assert_eq!(decoder.next_message(), None);
        assert_eq!(
            decoder.finish(),
            Err(WireError::Truncated {
                part: "body",
                expected: 48,
                got: 12
            })
        );
        let mut decoder = Decoder::with_max_body_size(10);
        decoder.feed(&big);
        assert!(matches!(
            decoder.next_message(),
            Some(Err(WireError::BodyTooLarge { .. }))
        ));
        assert_eq!(decoder.next_message(), None);
        assert!(!decoder.is_at_boundary());
        assert_eq!(
            decoder.finish(),
            Err(WireError::Truncated {
                part: "discarded body",
                expected: 50,
                got: 22
            })
        );
    }

    /// A reader that yields some bytes, is interrupted once, then fails.
    struct Flaky {
        data: Vec<u8>,
        interrupted: bool,
    }

    impl Read for Flaky {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            if !self.interrupted {
                self.interrupted = true;
                return Err(io::Error::new(io::ErrorKind::Interrupted, "signal"));
            }
            if self.data.is_empty() {
                return Err(io::Error::new(io::ErrorKind::ConnectionReset, "peer reset"));
            }
            let n = buf.len().min(self.data.len()).min(7);
            buf[..n].copy_from_slice(&self.data[..n]);
            self.data.drain(..n);
            Ok(n)
        }
    }

    #[test]
    fn io_errors_are_reported() {
        let mut ok = Flaky {
            data: transform_fixture(),
            interrupted: false,
        };
        assert!(matches!(
            read_message(&mut ok),
            Ok((_, Message::Transform(_)))
        ));
        let mut reader = Flaky {
            data: transform_fixture()[..30].to_vec(),
            interrupted: false,
        };
        assert_eq!(
            read_message(&mut reader),
            Err(WireError::Io {
                kind: io::ErrorKind::ConnectionReset,
                message: "peer reset".into()
            })
        );
        let mut reader = Flaky {
            data: transform_fixture()[..70].to_vec(),
            interrupted: false,
        };
        assert!(matches!(
            read_message(&mut reader),
            Err(WireError::Io { .. })
        ));
    }

    // --- fixtures produced by pyigtl ----------------------------------------------------------

    // Produced by pyigtl 0.3.4 from PyPI (its _version.py says 0.3.2) with numpy: the message
    // classes' pack(), called as each constant's comment says. Header version 1 unless noted.

    /// TransformMessage(matrix [[0,-1,0,10.5],[1,0,0,-20.25],[0,0,1,300.125]],
    /// timestamp=1700000000.25, device_name="ImageToPhysical").
    const PYIGTL_TRANSFORM_V1: &str = "\
        00015452414e53464f524d000000496d616765546f506879736963616c00000000006553f1004000000000000000000000302b59975f00d24720000000003f80\
        000000000000bf800000000000000000000000000000000000003f80000041280000c1a2000043961000";

    /// The same matrix, header_version=2, message_id=7, metadata {"Units": "mm", "Frame": "RAS"},
    /// timestamp=1.5, device_name="Probe".
    const PYIGTL_TRANSFORM_V2_META: &str = "\
        00025452414e53464f524d00000050726f62650000000000000000000000000000000000000180000000000000000000005d5d4c0b30a5639fca000c00120000\
        000f00000007000000003f80000000000000bf800000000000000000000000000000000000003f80000041280000c1a200004396100000020005000300000002\
        0005000300000003556e6974736d6d4672616d65524153";

    /// PointMessage: ("F-1", "Landmark", rgba 255,0,0,255, (1.5,-2.25,3), diameter 2.5, owner "")
    /// and ("tumour centre", "Target", rgba 0,128,255,200, (100,200.5,-300.75), 0, "CT"),
    /// timestamp=1234.5, device_name="Fiducials".
    const PYIGTL_POINT_V1: &str = "\
        0001504f494e5400000000000000466964756369616c730000000000000000000000000004d28000000000000000000001102963bceb31c91e17462d31000000\
        000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000004c616e646d61\
        726b000000000000000000000000000000000000000000000000ff0000ff3fc00000c01000004040000040200000000000000000000000000000000000000000\
        000074756d6f75722063656e74726500000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000\
        000054617267657400000000000000000000000000000000000000000000000000000080ffc842c8000043488000c39660000000000043540000000000000000\
        00000000000000000000";

    /// PolyDataMessage(points 4x3, lines [2,0,3], polygons [3,0,1,2, 3,0,1,3, 4,0,1,2,3]),
    /// timestamp=42, device_name="Liver".
    const PYIGTL_POLYDATA: &str = "\
        0001504f4c5944415441000000004c697665720000000000000000000000000000000000002a0000000000000000000000981c62ff36b27ab293000000040000\
        000000000000000000010000000c0000000300000034000000000000000000000000000000000000000000000000412000000000000000000000000000004120\
        00000000000000000000000000004120000000000002000000000000000300000003000000000000000100000002000000030000000000000001000000030000\
        000400000000000000010000000200000003";

    /// PolyDataMessage(points 4x3, vertices [1, 0, 1, 2]): pyigtl writes vertex cells in host
    /// (little-endian) byte order, so NINDICES reads as 0x01000000.
    const PYIGTL_POLYDATA_VERTICES_LE: &str = "\
        0001504f4c5944415441000000004c697665720000000000000000000000000000000000002a00000000000000000000006839ceefca74d25675000000040000\
        00020000001000000000000000000000000000000000000000000000000000000000000000000000000000000000412000000000000000000000000000004120\
        00000000000000000000000000004120000001000000000000000100000002000000";

    /// STATUS (pyigtl has no STATUS class: header, framing and CRC by pyigtl's MessageBase.pack,
    /// content by struct.pack("> H q 20s") + text + NUL): code 12, subcode -3, "UnknownType",
    /// "type FOO is not supported", timestamp=5, device_name="LIBR+".
    const PYIGTL_STATUS_V1: &str = "\
        00015354415455530000000000004c4942522b00000000000000000000000000000000000005000000000000000000000038276561b1127140f6000cffffffff\
        fffffffd556e6b6e6f776e547970650000000000000000007479706520464f4f206973206e6f7420737570706f7274656400";

    #[test]
    fn pyigtl_transform_fixtures() {
        let expected = Transform {
            matrix: [
                [0.0, -1.0, 0.0, 10.5],
                [1.0, 0.0, 0.0, -20.25],
                [0.0, 0.0, 1.0, 300.125],
                [0.0, 0.0, 0.0, 1.0],
            ],
        };
        let (header, message) = decode_message(&hex(PYIGTL_TRANSFORM_V1)).expect("decodes");
        assert_eq!(header.version, 1);
        assert_eq!(header.device_name, "ImageToPhysical");
        assert_eq!(header.timestamp_secs(), 1_700_000_000.25);
        assert_eq!(message, Message::Transform(expected));
        // Our encoder produces pyigtl's bytes exactly.
        let options = EncodeOptions {
            timestamp: header.timestamp,
            ..EncodeOptions::default()
        };
        assert_eq!(
            Message::Transform(expected).encode("ImageToPhysical", &options),
            Ok(hex(PYIGTL_TRANSFORM_V1))
        );

        let bytes = hex(PYIGTL_TRANSFORM_V2_META);
        let (header, message) = decode_message(&bytes).expect("decodes");
        assert_eq!(
            (
                header.version,
                header.device_name.as_str(),
                header.timestamp_secs()
            ),
            (2, "Probe", 1.5)
        );
        assert_eq!(message, Message::Transform(expected));
        let parts = split_body(&header, &bytes[HEADER_SIZE..]).expect("splits");
        assert_eq!(
            parts.extended,
            Some(ExtendedHeader {
                ext_header_size: 12,
                meta_header_size: 18,
                meta_size: 15,
                message_id: 7
            })
        );
        assert_eq!(parts.metadata, b"UnitsmmFrameRAS");
    }

    #[test]
    fn pyigtl_point_fixture() {
        let bytes = hex(PYIGTL_POINT_V1);
        let (header, message) = decode_message(&bytes).expect("decodes");
        assert_eq!(header.device_name, "Fiducials");
        assert_eq!(header.timestamp_secs(), 1234.5);
        let expected = vec![
            PointElement {
                name: "F-1".into(),
                group: "Landmark".into(),
                rgba: [255, 0, 0, 255],
                position_mm: [1.5, -2.25, 3.0],
                diameter_mm: 2.5,
                owner: String::new(),
            },
            PointElement {
                name: "tumour centre".into(),
                group: "Target".into(),
                rgba: [0, 128, 255, 200],
                position_mm: [100.0, 200.5, -300.75],
                diameter_mm: 0.0,
                owner: "CT".into(),
            },
        ];
        assert_eq!(message, Message::Point(expected.clone()));
        let options = EncodeOptions {
            timestamp: header.timestamp,
            ..EncodeOptions::default()
        };
        assert_eq!(
            Message::Point(expected).encode("Fiducials", &options),
            Ok(bytes)
        );
    }

    #[test]
    fn pyigtl_polydata_and_status_fixtures() {
        let bytes = hex(PYIGTL_POLYDATA);
        let (_, message) = decode_message(&bytes).expect("decodes");
        let Message::PolyData(poly) = &message else {
            panic!("{message:?}")
        };
        assert_eq!(poly.points.len(), 4);
        assert_eq!(poly.points[3], [0.0, 0.0, 10.0]);
        assert_eq!(poly.lines, CellArray::from_cells([[0u32, 3]]));
        assert_eq!(
            poly.polygons,
            CellArray::from_cells([vec![0u32, 1, 2], vec![0, 1, 3], vec![0, 1, 2, 3]])
        );
        assert!(poly.attributes.is_empty() && poly.vertices.is_empty());
        let options = EncodeOptions {
            timestamp: timestamp_from_secs(42.0),
            ..EncodeOptions::default()
        };
        assert_eq!(message.encode("Liver", &options), Ok(bytes));

        assert_eq!(
            decode_err(&hex(PYIGTL_POLYDATA_VERTICES_LE)).to_string(),
            "POLYDATA: VERTICES cell 0 NINDICES 16777216 says 67108864 bytes but 12 remain"
        );

        let (header, message) = decode_message(&hex(PYIGTL_STATUS_V1)).expect("decodes");
        assert_eq!(header.device_name, "LIBR+");
        let expected = Status {
            code: status_code::ILLEGAL_INSTRUCTION,
            subcode: -3,
            error_name: "UnknownType".into(),
            message: "type FOO is not supported".into(),
        };
        assert_eq!(message, Message::Status(expected.clone()));
        let options = EncodeOptions {
            timestamp: header.timestamp,
            ..EncodeOptions::default()
        };
        assert_eq!(
            Message::Status(expected).encode("LIBR+", &options),
            Ok(hex(PYIGTL_STATUS_V1))
        );
    }

    /// Canonical text of a decoded message: the `NAME.expect` format a fixture script writes from
    /// the values it gave pyigtl (one value per line, f32 as bit patterns, timestamp in seconds
    /// compared to 1e-6, a lone `error` line for a message that must be rejected).
    fn render(header: &Header, message: &Message) -> Vec<String> {
        let bits = |v: f32| format!("{:08x}", v.to_bits());
        let mut out = vec![
            format!("type {}", header.type_name),
            format!("device {}", header.device_name),
            format!("version {}", header.version),
            format!("timestamp {:.6}", header.timestamp_secs()),
        ];
        match message {
            Message::Transform(t) => {
                for r in 0..3 {
                    for c in 0..4 {
                        out.push(format!("m{r}{c} {}", bits(t.matrix[r][c] as f32)));
                    }
                }
            }
            Message::Point(points) => {
                for (i, p) in points.iter().enumerate() {
                    let [r, g, b, a] = p.rgba;
                    let [x, y, z] = p.position_mm;
                    out.push(format!("point {i} name={}", p.name));
                    out.push(format!("point {i} group={}", p.group));
                    out.push(format!("point {i} rgba={r},{g},{b},{a}"));
                    out.push(format!("point {i} xyz={},{},{}", bits(x), bits(y), bits(z)));
                    out.push(format!("point {i} diameter={}", bits(p.diameter_mm)));
                    out.push(format!("point {i} owner={}", p.owner));
                }
            }
            Message::Status(s) => {
                out.push(format!("code {}", s.code));
                out.push(format!("subcode {}", s.subcode));
                out.push(format!("error_name {}", s.error_name));
                out.push(format!("message {}", s.message));
            }
            Message::PolyData(p) => {
                out.push(format!("points {}", p.points.len()));
                for (i, [x, y, z]) in p.points.iter().enumerate() {
                    out.push(format!("p {i} {},{},{}", bits(*x), bits(*y), bits(*z)));
                }
                for (name, one, cells) in [
                    ("vertices", "vertex", &p.vertices),
                    ("lines", "line", &p.lines),
                    ("polygons", "polygon", &p.polygons),
                    ("triangle_strips", "triangle_strip", &p.triangle_strips),
                ] {
                    out.push(format!("{name} {}", cells.len()));
                    for (i, cell) in cells.iter().enumerate() {
                        let list: Vec<String> = cell.iter().map(u32::to_string).collect();
                        out.push(format!("{one} {i} {}", list.join(",")));
                    }
                }
                out.push(format!("attributes {}", p.attributes.len()));
            }
            Message::Unknown { type_name, body } => {
                out.push(format!("unknown {type_name} {}", body.len()))
            }
        }
        out
    }

    /// Decodes every `NAME.igtl` in `$IGTL_PEER_FIXTURES` (messages packed by pyigtl) and compares
    /// with `NAME.expect` (see [`render`]); skipped when the variable is unset.
    #[test]
    fn peer_fixtures_from_env() {
        let Some(dir) = std::env::var_os("IGTL_PEER_FIXTURES") else {
            eprintln!(
                "peer_fixtures_from_env: skipped (set IGTL_PEER_FIXTURES to a pyigtl fixture directory)"
            );
            return;
        };
        let mut entries: Vec<_> = std::fs::read_dir(&dir)
            .expect("fixture directory readable")
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "igtl"))
            .collect();
        entries.sort();
        assert!(!entries.is_empty(), "no .igtl files in {dir:?}");
        for path in entries {
            let bytes = std::fs::read(&path).expect("fixture readable");
            let expect =
                std::fs::read_to_string(path.with_extension("expect")).expect("expect file");
            let expect: Vec<&str> = expect.lines().collect();
            let decoded = decode_message(&bytes);
            if expect == ["error"] {
                let e = decoded.expect_err("pyigtl fixture expected to be rejected");
                eprintln!("{}: rejected as expected: {e}", path.display());
                continue;
            }
            let (header, message) = decoded.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            let got = render(&header, &message);
            assert_eq!(got.len(), expect.len(), "{}: {got:#?}", path.display());
            for (g, e) in got.iter().zip(&expect) {
                match (g.strip_prefix("timestamp "), e.strip_prefix("timestamp ")) {
                    (Some(g), Some(e)) => {
                        let (g, e): (f64, f64) = (g.parse().expect("f64"), e.parse().expect("f64"));
                        assert!(
                            (g - e).abs() <= 1e-6,
                            "{}: timestamp {g} vs {e}",
                            path.display()
                        );
                    }
                    _ => assert_eq!(g, e, "{}", path.display()),
                }
            }
            eprintln!("{}: {} values equal", path.display(), got.len());
        }
    }

    // --- fuzz ---------------------------------------------------------------------------------

    /// xorshift64* (deterministic, no dependency).
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
        }
        fn below(&mut self, n: usize) -> usize {
            (self.next() % n.max(1) as u64) as usize
        }
        fn bytes(&mut self, n: usize) -> Vec<u8> {
            (0..n).map(|_| self.next() as u8).collect()
        }
        fn text(&mut self, max: usize) -> String {
            let n = self.below(max + 1);
            (0..n)
                .map(|_| (b'a' + self.below(26) as u8) as char)
                .collect()
        }
        fn f32(&mut self) -> f32 {
            (self.next() % 2_000_001) as f32 / 1000.0 - 1000.0
        }
    }

    fn random_message(rng: &mut Rng) -> Message {
        match rng.below(5) {
            0 => {
                let mut t = Transform::IDENTITY;
                for row in t.matrix.iter_mut().take(3) {
                    for v in row.iter_mut() {
                        *v = f64::from(rng.f32());
                    }
                }
                Message::Transform(t)
            }
            1 => Message::Point(
                (0..rng.below(4))
                    .map(|_| PointElement {
                        name: rng.text(64),
                        group: rng.text(32),
                        rgba: [rng.next() as u8, 1, 2, 3],
                        position_mm: [rng.f32(), rng.f32(), rng.f32()],
                        diameter_mm: rng.f32().abs(),
                        owner: rng.text(20),
                    })
                    .collect(),
            ),
            2 => Message::Status(Status {
                code: rng.below(20) as u16,
                subcode: rng.next() as i64,
                error_name: rng.text(20),
                message: rng.text(50),
            }),
            3 => {
                let npoints = rng.below(6);
                let points = (0..npoints)
                    .map(|_| [rng.f32(), rng.f32(), rng.f32()])
                    .collect();
                let mut cells = || {
                    let mut array = CellArray::new();
                    if npoints > 0 {
                        for _ in 0..rng.below(4) {
                            let cell: Vec<u32> = (0..rng.below(5))
                                .map(|_| rng.below(npoints) as u32)
                                .collect();
                            array.push(&cell);
                        }
                    }
                    array
                };
                let (vertices, lines, polygons, triangle_strips) =
                    (cells(), cells(), cells(), cells());
                let attributes = (0..rng.below(4))
                    .map(|_| {
                        let kind = match rng.below(5) {
                            0 => AttributeKind::Scalar {
                                components: 1 + rng.below(4) as u8,
                            },
                            1 => AttributeKind::Vector,
                            2 => AttributeKind::Normal,
                            3 => AttributeKind::Tensor,
                            _ => AttributeKind::Rgba,
                        };
                        let location = if rng.below(2) == 0 {
                            AttributeLocation::Point
                        } else {
                            AttributeLocation::Cell
                        };
                        let n = rng.below(4) * usize::from(kind.components());
                        PolyAttribute {
                            name: rng.text(9),
                            location,
                            kind,
                            data: (0..n).map(|_| rng.f32()).collect(),
                        }
                    })
                    .collect();
                Message::PolyData(PolyData {
                    points,
                    vertices,
                    lines,
                    polygons,
                    triangle_strips,
                    attributes,
                })
            }
            _ => {
                let len = rng.below(40);
                Message::Unknown {
                    type_name: rng.text(12),
                    body: rng.bytes(len),
                }
            }
        }
    }

    fn mutate(rng: &mut Rng, bytes: &mut Vec<u8>) {
        if bytes.is_empty() {
            bytes.extend(rng.bytes(10));
            return;
        }
        match rng.below(6) {
            0 => {
                let len = rng.below(bytes.len());
                bytes.truncate(len);
            }
            1 => {
                for _ in 0..1 + rng.below(3) {
                    let at = rng.below(bytes.len());
                    bytes[at] ^= 1 << rng.below(8);
                }
            }
            2 => {
                let at = rng.below(bytes.len());
                bytes[at] = rng.next() as u8;
            }
            3 => {
                let at = rng.below(bytes.len());
                let n = 1 + rng.below(8);
                let extra = rng.bytes(n);
                bytes.splice(at..at, extra);
            }
            4 => {
                let n = 1 + rng.below(16);
                bytes.extend(rng.bytes(n));
            }
            _ => {
                // Overwrite BODY_SIZE with something near the real one.
                if bytes.len() >= HEADER_SIZE {
                    let size = (bytes.len() - HEADER_SIZE) as i64 + rng.below(9) as i64 - 4;
                    bytes[42..50].copy_from_slice(&(size.max(0) as u64).to_be_bytes());
                }
            }
        }
    }

    fn drain(decoder: &mut Decoder, out: &mut Vec<String>) {
        while let Some(result) = decoder.next_message() {
            if let Ok((_, m)) = result {
                out.push(format!("{m:?}"));
            }
        }
    }

    #[test]
    fn fuzz_random_truncated_and_bit_flipped_messages_never_panic() {
        let mut rng = Rng(0x1234_5678_9ABC_DEF1);
        for round in 0..3000 {
            let message = random_message(&mut rng);
            let options = EncodeOptions {
                header_version: 1 + rng.below(2) as u16,
                timestamp: rng.next(),
                message_id: rng.next() as u32,
            };
            let device = rng.text(20);
            let bytes = message
                .encode(&device, &options)
                .expect("generated messages are valid");
            let (header, decoded) = decode_message(&bytes).expect("valid messages decode");
            assert_eq!(decoded, message, "round {round}");
            assert_eq!(
                (header.device_name.as_str(), header.timestamp),
                (device.as_str(), options.timestamp)
            );

            let mut bad = bytes.clone();
            mutate(&mut rng, &mut bad);
            let _ = decode_message(&bad);

            // A flipped bit in the body is always a CRC error (CRC-64 detects every 1-bit error).
            if bytes.len() > HEADER_SIZE {
                let mut flipped = bytes.clone();
                let at = HEADER_SIZE + rng.below(bytes.len() - HEADER_SIZE);
                flipped[at] ^= 1 << rng.below(8);
                assert!(
                    matches!(decode_message(&flipped), Err(WireError::BadCrc { .. })),
                    "round {round}"
                );
            }

            // Streams: valid, mutated, valid; the decoder in random chunks and read_message must
            // agree on the messages they return.
            let tail = random_message(&mut rng)
                .encode("t", &EncodeOptions::default())
                .expect("valid");
            let mut stream = bytes.clone();
            stream.extend(&bad);
            stream.extend(&tail);
            let mut decoder = Decoder::with_max_body_size(4096);
            let mut from_decoder = Vec::new();
            let mut at = 0;
            while at < stream.len() {
                let n = (1 + rng.below(97)).min(stream.len() - at);
                decoder.feed(&stream[at..at + n]);
                at += n;
                drain(&mut decoder, &mut from_decoder);
            }
            let _ = decoder.finish();
            let mut cursor = Cursor::new(stream);
            let mut from_reader = Vec::new();
            loop {
                match read_message_with_limit(&mut cursor, 4096) {
                    Ok((_, m)) => from_reader.push(format!("{m:?}")),
                    // Like the decoder, go on after every error that leaves the stream readable.
                    Err(WireError::EndOfStream | WireError::Truncated { .. }) => break,
                    Err(_) => {}
                }
            }
            assert_eq!(from_decoder, from_reader, "round {round}");
            assert_eq!(
                from_decoder.first(),
                Some(&format!("{message:?}")),
                "round {round}"
            );
        }
    }

    #[test]
    fn fuzz_content_decoders_with_random_and_mutated_bytes() {
        let mut rng = Rng(42);
        for _ in 0..20_000 {
            let len = rng.below(400);
            let bytes = rng.bytes(len);
            for type_name in ["TRANSFORM", "POINT", "STATUS", "POLYDATA"] {
                let _ = Message::decode_content(type_name, &bytes);
            }
        }
        // Structured: valid POLYDATA contents with one header word replaced. Whatever decodes
        // must re-encode to the same bytes (no field is silently misread).
        for round in 0..5000 {
            let message = loop {
                if let m @ Message::PolyData(_) = random_message(&mut rng) {
                    break m;
                }
            };
            let mut content = message.encode_content().expect("valid");
            let word = rng.below(10) * 4;
            let old = u32::from_be_bytes(content[word..word + 4].try_into().expect("4 bytes"));
            let new = match rng.below(5) {
                0 => old.wrapping_add(1),
                1 => old.wrapping_sub(1),
                2 => old.wrapping_mul(2),
                3 => u32::MAX - rng.below(3) as u32,
                _ => rng.next() as u32 % 64,
            };
            content[word..word + 4].copy_from_slice(&new.to_be_bytes());
            // Also garble one attribute header or name byte now and then.
            if rng.below(4) == 0 && content.len() > 40 {
                let at = 40 + rng.below(content.len() - 40);
                content[at] = rng.next() as u8;
            }
            if let Ok(decoded) = Message::decode_content("POLYDATA", &content) {
                let again = decoded.encode_content().expect("decoded data re-encodes");
                if again != content {
                    // The only byte the decoder does not check is the ATTRIBUTE_NAMES padding.
                    let differing: Vec<usize> = (0..content.len())
                        .filter(|&i| again.get(i) != content.get(i))
                        .collect();
                    assert_eq!(again.len(), content.len(), "round {round}");
                    assert_eq!(differing.len(), 1, "round {round}: {differing:?}");
                }
            }
        }
    }
}
