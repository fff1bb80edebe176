//! What can go wrong reading or writing OpenIGTLink bytes: [`WireError`], whose `Display` names
//! the section, the field and the problem, and [`TextProblem`] for text fields. This module owns
//! the error types and their messages; the decoders build them.

use std::fmt;
use std::io;

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
    /// `BODY_SIZE` exceeds the configured limit and [`MAX_DISCARDED_BODY_SIZE`] too: no message
    /// is that large (usually garbage, or a size written in the wrong byte order), so the stream's
    /// framing cannot be trusted. Only the header was consumed.
    ///
    /// [`MAX_DISCARDED_BODY_SIZE`]: crate::MAX_DISCARDED_BODY_SIZE
    UntrustedBodySize {
        /// The header's message type.
        type_name: String,
        /// The header's `BODY_SIZE`.
        body_size: u64,
        /// The limit in force.
        limit: u64,
    },
    /// [`Message::decode`] was given a body whose length differs from the header's `BODY_SIZE`.
    ///
    /// [`Message::decode`]: crate::Message::decode
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
    ///
    /// [`Message::require_known`]: crate::Message::require_known
    UnknownType {
        /// The header's message type.
        type_name: String,
    },
}

impl WireError {
    /// Whether the stream's framing is still trustworthy after this error, so that reading the
    /// next message makes sense. `false` for I/O errors, the end of the stream, truncation, an
    /// unsupported header version (the bytes are probably not OpenIGTLink) and a `BODY_SIZE` too
    /// large to skip: close the connection.
    pub fn is_recoverable(&self) -> bool {
        !matches!(
            self,
            WireError::Io { .. }
                | WireError::EndOfStream
                | WireError::Truncated { .. }
                | WireError::UnsupportedVersion { .. }
                | WireError::UntrustedBodySize { .. }
        )
    }

    pub(crate) fn from_io(error: &io::Error) -> WireError {
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
            WireError::UntrustedBodySize {
                type_name,
                body_size,
                limit,
            } => write!(
                f,
                "header: BODY_SIZE {body_size} of a {type_name:?} message exceeds the limit of \
                 {limit} bytes and is too large to skip (over {} bytes: garbage, or a size in the \
                 wrong byte order?): the stream's framing cannot be trusted",
                crate::MAX_DISCARDED_BODY_SIZE
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
