//! Helpers the integration tests share: hex and field builders, hand-built frames with a CRC
//! computed bit by bit (independent of the crate's table), the spec's TRANSFORM fixture, sample
//! messages, round-trip and error helpers, and a deterministic generator for the fuzz tests.
#![allow(dead_code)] // each test file uses a part of these

use librplus_igtl::{
    AttributeKind, AttributeLocation, CRC64_POLY, CellArray, EncodeOptions, HEADER_SIZE, Header,
    Message, PointElement, PolyAttribute, PolyData, WireError, decode_message,
};

/// Bytes from a hex string; whitespace ignored.
pub fn hex(text: &str) -> Vec<u8> {
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
pub fn field(text: &[u8], width: usize) -> Vec<u8> {
    let mut out = text.to_vec();
    out.resize(width, 0);
    out
}

pub fn be_f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_be_bytes()).collect()
}

pub fn be_u32_bytes(values: &[u32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_be_bytes()).collect()
}

/// A version 1 frame around `body` with a correct CRC (computed by the bitwise reference).
pub fn frame_v1(type_name: &str, device: &str, body: &[u8]) -> Vec<u8> {
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
pub fn crc64_bitwise(bytes: &[u8]) -> u64 {
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

pub fn decode_err(bytes: &[u8]) -> WireError {
    match decode_message(bytes) {
        Ok(ok) => panic!("expected an error, decoded {ok:?}"),
        Err(e) => e,
    }
}

pub fn content_err(type_name: &str, content: &[u8]) -> String {
    match Message::decode_content(type_name, content) {
        Ok(ok) => panic!("expected an error, decoded {ok:?}"),
        Err(e) => e.to_string(),
    }
}

pub fn roundtrip(message: &Message, options: &EncodeOptions) -> (Header, Message) {
    let bytes = message.encode("dev", options).expect("encodes");
    let (header, decoded) = decode_message(&bytes).expect("decodes");
    assert_eq!(&decoded, message);
    assert_eq!(header.version, options.header_version);
    assert_eq!(header.type_name, message.type_name());
    assert_eq!(header.body_size as usize, bytes.len() - HEADER_SIZE);
    (header, decoded)
}

pub fn sample_points() -> Vec<PointElement> {
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

pub fn sample_polydata() -> PolyData {
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

/// Hand-built from the header table and the TRANSFORM table of the specification: a 90°
/// rotation about z and a translation of (10, -20, 30.5) mm, elements R11 R21 R31 R12 R22 R32
/// R13 R23 R33 TX TY TZ. CRC computed with crcmod (the function pyigtl uses), not with this
/// crate.
pub fn transform_fixture() -> Vec<u8> {
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

/// xorshift64* (deterministic, no dependency).
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
    pub fn bytes(&mut self, n: usize) -> Vec<u8> {
        (0..n).map(|_| self.next() as u8).collect()
    }
    pub fn text(&mut self, max: usize) -> String {
        let n = self.below(max + 1);
        (0..n)
            .map(|_| (b'a' + self.below(26) as u8) as char)
            .collect()
    }
    pub fn f32(&mut self) -> f32 {
        (self.next() % 2_000_001) as f32 / 1000.0 - 1000.0
    }
}
