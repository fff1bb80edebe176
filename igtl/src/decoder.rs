//! Framing for non-blocking I/O: [`Decoder`], fed bytes as they arrive and asked for the next
//! complete message, buffering at most one header and one body. This module owns the incremental
//! decoder.

use crate::error::WireError;
use crate::header::{HEADER_SIZE, Header, raw_body_size, raw_type_name};
use crate::message::Message;
use crate::read::{DEFAULT_MAX_BODY_SIZE, untrusted};

/// An incremental decoder for non-blocking I/O: [`Decoder::feed`] it the bytes as they arrive,
/// then call [`Decoder::next_message`] until it returns `None`.
///
/// It buffers at most one header and one body (bounded by the body limit) plus what the last
/// `feed` brought; a body over the limit is dropped as it arrives (up to
/// [`MAX_DISCARDED_BODY_SIZE`]). Each `Some` result consumes one whole frame, so an error (bad
/// CRC, malformed content, oversized body) is followed by the next message as usual (but see
/// [`WireError::is_recoverable`]).
///
/// [`MAX_DISCARDED_BODY_SIZE`]: crate::MAX_DISCARDED_BODY_SIZE
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
            // The size field of a header with a foreign version cannot be trusted: drop the
            // header only.
            Err(e @ WireError::UnsupportedVersion { .. }) => {
                self.discard(0);
                return Some(Err(e));
            }
            // Nor can a size no message has (skipping it would swallow the stream): drop the
            // header only.
            _ if untrusted(body_size, self.max_body_size) => {
                self.discard(0);
                return Some(Err(WireError::UntrustedBodySize {
                    type_name: raw_type_name(&head),
                    body_size,
                    limit: self.max_body_size,
                }));
            }
            Ok(header) => header,
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
