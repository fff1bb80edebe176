//! Framing: the blocking reader and the incremental decoder go on after bad frames, discard
//! oversized bodies without buffering them, and report truncation and I/O errors.

mod common;

use std::io::{self, Cursor, Read};

use common::{frame_v1, sample_points, sample_polydata, transform_fixture};
use librplus_igtl::{
    Decoder, EncodeOptions, HEADER_SIZE, Message, Status, Transform, WireError, read_message,
    read_message_with_limit,
};

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
