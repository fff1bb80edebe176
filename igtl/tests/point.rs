//! `POINT`: the specification's fixture byte for byte, round trips, and text field errors.

mod common;

use common::{content_err, field, hex, roundtrip, sample_points};
use librplus_igtl::{EncodeOptions, HEADER_SIZE, Message, PointElement, decode_message};

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
