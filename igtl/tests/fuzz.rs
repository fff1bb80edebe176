//! Deterministic fuzzing: random valid messages, truncated, mutated and bit-flipped, through
//! `decode_message`, the reader and the decoder (which must agree), and random bytes through the
//! content decoders.

mod common;

use std::io::Cursor;

use common::Rng;
use librplus_igtl::{
    AttributeKind, AttributeLocation, CellArray, Decoder, EncodeOptions, HEADER_SIZE, Message,
    PointElement, PolyAttribute, PolyData, Status, Transform, WireError, decode_message,
    read_message_with_limit,
};

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
            let (vertices, lines, polygons, triangle_strips) = (cells(), cells(), cells(), cells());
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
