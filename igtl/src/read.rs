//! Framing over a blocking [`Read`]: one message per call, the whole frame consumed whatever the
//! outcome (an oversized body is read and discarded without being buffered). This module owns the
//! body limit's default and the blocking reader.

use std::io::{self, Read};

use crate::error::WireError;
use crate::header::{HEADER_SIZE, Header, raw_body_size, raw_type_name};
use crate::message::Message;

/// Default limit on `BODY_SIZE` for [`read_message`] and [`Decoder::new`]: 64 MiB.
///
/// [`Decoder::new`]: crate::Decoder::new
pub const DEFAULT_MAX_BODY_SIZE: u64 = 64 * 1024 * 1024;

/// Largest `BODY_SIZE` over the body limit that is skipped (discarded as it arrives) so that the
/// next message can be read: 4 GiB. A header declaring more, and more than the limit, is taken as
/// garbage (any size under 4 GiB written in the wrong byte order reads as more):
/// [`WireError::UntrustedBodySize`], after which the stream cannot be read on.
pub const MAX_DISCARDED_BODY_SIZE: u64 = 1 << 32;

/// Whether a header's `BODY_SIZE` is too large to be a message's, with `max_body_size` the limit
/// in force.
pub(crate) fn untrusted(body_size: u64, max_body_size: u64) -> bool {
    body_size > max_body_size.max(MAX_DISCARDED_BODY_SIZE)
}

/// Reads one message with the default body limit ([`DEFAULT_MAX_BODY_SIZE`]).
/// See [`read_message_with_limit`].
pub fn read_message<R: Read + ?Sized>(reader: &mut R) -> Result<(Header, Message), WireError> {
    read_message_with_limit(reader, DEFAULT_MAX_BODY_SIZE)
}

/// Reads one message: the header, then `BODY_SIZE` bytes, then decodes them.
///
/// Whatever the outcome, the whole frame is consumed, so the next call reads the next message:
/// a body over `max_body_size` is read and discarded without being buffered; a header with a
/// non-UTF-8 name still has its body skipped. After [`WireError::UnsupportedVersion`] and
/// [`WireError::UntrustedBodySize`] only the header was consumed (its size cannot be trusted;
/// close the connection).
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
        // The size field of a header with a foreign version cannot be trusted: do not skip.
        Err(e @ WireError::UnsupportedVersion { .. }) => return Err(e),
        // Nor can a size no message has: do not try to skip it.
        _ if untrusted(body_size, max_body_size) => {
            return Err(WireError::UntrustedBodySize {
                type_name: raw_type_name(&head),
                body_size,
                limit: max_body_size,
            });
        }
        Ok(header) => header,
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
