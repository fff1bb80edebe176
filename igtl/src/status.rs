//! `STATUS`: a status code, a device-specific sub-code, an error name and a NUL-terminated
//! message. This module owns [`Status`], its content encoding and the specification's table of
//! codes ([`status_code`]).

use crate::error::WireError;
use crate::reader::{Reader, check_text, decode_fixed_text, put_fixed_text};

/// Size of the fixed part of a `STATUS` content (code, sub-code, error name).
pub const STATUS_HEADER_SIZE: usize = 30;
/// Width of a `STATUS` message's `ERROR_NAME` field.
pub const STATUS_ERROR_NAME_LEN: usize = 20;

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
    pub(crate) fn encode_content(&self) -> Result<Vec<u8>, WireError> {
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
    pub(crate) fn decode_content(content: &[u8]) -> Result<Status, WireError> {
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
