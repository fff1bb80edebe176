//! `TRANSFORM`: the specification's fixture byte for byte, round trips in header versions 1
//! and 2, and errors.

mod common;

use common::{content_err, hex, roundtrip, transform_fixture};
use librplus_igtl::{
    EncodeOptions, HEADER_SIZE, Header, Message, Transform, decode_message, split_body,
    timestamp_from_secs,
};

#[test]
fn transform_fixture_from_the_specification() {
    let bytes = transform_fixture();
    let (header, message) = decode_message(&bytes).expect("decodes");
    assert_eq!(header.type_name, "TRANSFORM");
    assert_eq!(header.device_name, "Tracker");
    assert_eq!(header.timestamp_secs(), 1.5);
    let expected = Transform {
        matrix: [
            [0.0, -1.0, 0.0, 10.0],
            [1.0, 0.0, 0.0, -20.0],
            [0.0, 0.0, 1.0, 30.5],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };
    assert_eq!(message, Message::Transform(expected));
    // And the encoder writes exactly those bytes.
    let options = EncodeOptions {
        timestamp: timestamp_from_secs(1.5),
        ..EncodeOptions::default()
    };
    assert_eq!(
        Message::Transform(expected).encode("Tracker", &options),
        Ok(bytes)
    );
}

#[test]
fn transform_roundtrip_v1_and_v2() {
    let mut t = Transform::IDENTITY;
    t.matrix[0] = [0.5, -0.25, 0.125, 100.0];
    t.matrix[2][3] = -0.75;
    roundtrip(&Message::Transform(t), &EncodeOptions::default());
    let (header, _) = roundtrip(&Message::Transform(t), &EncodeOptions::version2(9));
    assert_eq!(header.body_size, 12 + 48 + 2);
    // The v2 frame: extended header {12, 2, 0, 9}, content, INDEX_COUNT 0. CRC from crcmod.
    let bytes = Message::Transform(t)
        .encode("dev", &EncodeOptions::version2(9))
        .expect("encodes");
    assert_eq!(
        &bytes[HEADER_SIZE..HEADER_SIZE + 12],
        &hex("000C 0002 00000000 00000009")
    );
    assert_eq!(&bytes[bytes.len() - 2..], &[0, 0]);
    let v2 = Message::decode_content("TRANSFORM", &transform_fixture()[HEADER_SIZE..])
        .expect("ok")
        .encode("dev", &EncodeOptions::version2(9))
        .expect("encodes");
    assert_eq!(&v2[50..58], &hex("C613EA0A 4F4072AC"));
    let parts = split_body(
        &Header::parse(v2.first_chunk().expect("58")).expect("h"),
        &v2[HEADER_SIZE..],
    )
    .expect("splits");
    assert_eq!(parts.extended.map(|e| e.message_id), Some(9));
    assert_eq!(parts.content.len(), 48);
    assert_eq!(parts.metadata_header, &[0, 0]);
}

#[test]
fn transform_errors() {
    assert_eq!(
        content_err("TRANSFORM", &[0; 47]),
        "TRANSFORM: content is 47 bytes, a TRANSFORM has exactly 48 (12 float32)"
    );
    assert!(content_err("TRANSFORM", &[0; 52]).contains("is 52 bytes"));
    let mut projective = Transform::IDENTITY;
    projective.matrix[3][0] = 0.1;
    let e = Message::Transform(projective)
        .encode("d", &EncodeOptions::default())
        .expect_err("row 4");
    assert!(
        e.to_string()
            .starts_with("TRANSFORM: matrix row 4 is [0.1, 0.0, 0.0, 1.0]"),
        "{e}"
    );
}
