//! OpenIGTLink wire codec: the byte layout of the messages the LIBR+ bridge speaks, and nothing else.
//!
//! This crate turns bytes into typed messages and back. It does no I/O of its own beyond reading
//! from a caller's [`std::io::Read`] ([`read_message`]), keeps no connection state beyond a byte
//! buffer ([`Decoder`]), and depends on `std` only, so it builds and tests on its own
//! (`cargo test -p librplus-igtl`).
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
//! read normally. The exceptions are a header version other than 1 or 2 and a `BODY_SIZE` over
//! both the limit and [`MAX_DISCARDED_BODY_SIZE`] (4 GiB): the size field cannot be trusted, so
//! only the 58 header bytes are consumed and the error comes at once.
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
//!
//! # Layout
//!
//! One module per concern, everything public re-exported here: `crc` (CRC-64), `time`
//! (timestamps), `error` ([`WireError`], [`TextProblem`]), `header` ([`Header`],
//! [`ExtendedHeader`], [`split_body`]), one module per message type (`transform`, `point`,
//! `status`, `polydata`), `message` ([`Message`], [`EncodeOptions`], [`decode_message`]) and the
//! framing: `read` ([`read_message`]) and `decoder` ([`Decoder`]). The tests are in `tests/`,
//! through this public API only.

#![forbid(unsafe_code)]
#![warn(missing_docs)]

mod crc;
mod decoder;
mod error;
mod header;
mod message;
mod point;
mod polydata;
mod read;
mod reader;
mod status;
mod time;
mod transform;

pub use crc::{CRC64_POLY, crc64, crc64_update};
pub use decoder::Decoder;
pub use error::{TextProblem, WireError};
pub use header::{
    BodyParts, DEVICE_NAME_LEN, EXTENDED_HEADER_SIZE, ExtendedHeader, HEADER_SIZE, Header,
    TYPE_NAME_LEN, split_body,
};
pub use message::{EncodeOptions, Message, decode_message};
pub use point::{
    POINT_ELEMENT_SIZE, POINT_GROUP_LEN, POINT_NAME_LEN, POINT_OWNER_LEN, PointElement,
};
pub use polydata::{
    AttributeKind, AttributeLocation, CellArray, MAX_ATTRIBUTE_NAME_LEN,
    POLYDATA_ATTRIBUTE_HEADER_SIZE, POLYDATA_HEADER_SIZE, PolyAttribute, PolyData,
};
pub use read::{
    DEFAULT_MAX_BODY_SIZE, MAX_DISCARDED_BODY_SIZE, read_message, read_message_with_limit,
};
pub use status::{STATUS_ERROR_NAME_LEN, STATUS_HEADER_SIZE, Status, status_code};
pub use time::{timestamp_from_secs, timestamp_from_system_time, timestamp_to_secs};
pub use transform::{TRANSFORM_CONTENT_SIZE, Transform};
