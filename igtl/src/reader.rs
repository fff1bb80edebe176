//! Byte helpers the message decoders and encoders share: [`Reader`], a bounds-checked big-endian
//! reader over a byte slice whose every shortfall is a [`WireError`], and the fixed-width text and
//! `float32` helpers. Nothing here is public outside the crate.

use crate::error::{TextProblem, WireError};

/// A bounds-checked big-endian reader over a byte slice; every shortfall is a [`WireError`].
pub(crate) struct Reader<'a> {
    bytes: &'a [u8],
    section: &'static str,
}

impl<'a> Reader<'a> {
    pub(crate) fn new(bytes: &'a [u8], section: &'static str) -> Self {
        Reader { bytes, section }
    }

    pub(crate) fn remaining(&self) -> usize {
        self.bytes.len()
    }

    pub(crate) fn rest(&self) -> &'a [u8] {
        self.bytes
    }

    /// Takes `n` bytes of a fixed-size part.
    pub(crate) fn take(&mut self, n: usize, field: &str) -> Result<&'a [u8], WireError> {
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
    pub(crate) fn take_declared(
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

    pub(crate) fn array<const N: usize>(&mut self, field: &str) -> Result<[u8; N], WireError> {
        let bytes = self.take(N, field)?;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        Ok(out)
    }

    pub(crate) fn u8(&mut self, field: &str) -> Result<u8, WireError> {
        Ok(u8::from_be_bytes(self.array(field)?))
    }
    pub(crate) fn u16(&mut self, field: &str) -> Result<u16, WireError> {
        Ok(u16::from_be_bytes(self.array(field)?))
    }
    pub(crate) fn u32(&mut self, field: &str) -> Result<u32, WireError> {
        Ok(u32::from_be_bytes(self.array(field)?))
    }
    pub(crate) fn u64(&mut self, field: &str) -> Result<u64, WireError> {
        Ok(u64::from_be_bytes(self.array(field)?))
    }
    pub(crate) fn i64(&mut self, field: &str) -> Result<i64, WireError> {
        Ok(i64::from_be_bytes(self.array(field)?))
    }
    pub(crate) fn f32(&mut self, field: &str) -> Result<f32, WireError> {
        Ok(f32::from_be_bytes(self.array(field)?))
    }

    /// A fixed-width, NUL-padded text field.
    pub(crate) fn fixed_text(&mut self, width: usize, field: &str) -> Result<String, WireError> {
        let bytes = self.take(width, field)?;
        decode_fixed_text(bytes, self.section, || field.to_owned())
    }
}

pub(crate) fn decode_fixed_text(
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
pub(crate) fn put_fixed_text(
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

pub(crate) fn check_text(
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
pub(crate) fn word(bytes: &[u8]) -> [u8; 4] {
    bytes.first_chunk::<4>().copied().unwrap_or_default()
}

/// Big-endian `float32` triples; a partial triple at the end is ignored (callers size exactly).
pub(crate) fn be_f32_triples(bytes: &[u8]) -> Vec<[f32; 3]> {
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
pub(crate) fn be_f32s(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|w| f32::from_be_bytes(word(w)))
        .collect()
}

pub(crate) fn u32_count(n: usize, section: &'static str, field: &str) -> Result<u32, WireError> {
    u32::try_from(n).map_err(|_| WireError::Value {
        section,
        field: field.to_owned(),
        problem: format!("would be {n}, more than a uint32 holds"),
    })
}
