//! Whole messages: CRC and body length errors, unknown types, and the errors' `Display` and
//! recoverability.

mod common;

use std::io;

use common::{decode_err, frame_v1, roundtrip, transform_fixture};
use librplus_igtl::{
    EncodeOptions, HEADER_SIZE, Header, Message, WireError, crc64, decode_message,
};

#[test]
fn crc_and_body_length_errors() {
    let mut bytes = transform_fixture();
    bytes[HEADER_SIZE + 5] ^= 0x10;
    assert_eq!(
        decode_err(&bytes).to_string(),
        format!(
            "TRANSFORM from device \"Tracker\": CRC mismatch: header says 0x9C7663F5F9CD7B70, body computes 0x{:016X}",
            crc64(&bytes[HEADER_SIZE..])
        )
    );
    let bytes = transform_fixture();
    let header = Header::parse(bytes.first_chunk().expect("58")).expect("parses");
    assert_eq!(
        Message::decode(&header, &bytes[HEADER_SIZE + 1..])
            .expect_err("short")
            .to_string(),
        "header: BODY_SIZE says 48 bytes but 47 were given"
    );
    let mut long = bytes.clone();
    long.push(0);
    assert_eq!(
        decode_err(&long),
        WireError::BodyLength {
            declared: 48,
            given: 49
        }
    );
    assert_eq!(
        decode_err(&bytes[..57]),
        WireError::Truncated {
            part: "header",
            expected: 58,
            got: 57
        }
    );
}

#[test]
fn unknown_types_decode_to_unknown() {
    let bytes = frame_v1("IMAGE", "US", b"\x01\x02\x03");
    let (_, message) = decode_message(&bytes).expect("decodes");
    assert_eq!(
        message,
        Message::Unknown {
            type_name: "IMAGE".into(),
            body: vec![1, 2, 3]
        }
    );
    assert_eq!(message.type_name(), "IMAGE");
    assert_eq!(
        message
            .clone()
            .require_known()
            .expect_err("unknown")
            .to_string(),
        "message type \"IMAGE\" is not supported"
    );
    roundtrip(&message, &EncodeOptions::default());
    let get = Message::Unknown {
        type_name: "GET_TRANS".into(),
        body: vec![],
    };
    roundtrip(&get, &EncodeOptions::version2(5));
    assert!(Message::Point(vec![]).require_known().is_ok());
    assert_eq!(
        Message::Unknown {
            type_name: "A_VERY_LONG_TYPE".into(),
            body: vec![]
        }
        .encode("d", &EncodeOptions::default())
        .expect_err("long")
        .to_string(),
        "header: TYPE is 16 bytes, at most 12 fit"
    );
    let options = EncodeOptions {
        header_version: 3,
        ..EncodeOptions::default()
    };
    assert_eq!(
        Message::Point(vec![]).encode("d", &options),
        Err(WireError::UnsupportedVersion { version: 3 })
    );
}

#[test]
fn error_display_and_recoverability() {
    let io = WireError::Io {
        kind: io::ErrorKind::ConnectionReset,
        message: "reset".into(),
    };
    assert_eq!(io.to_string(), "I/O error: reset");
    assert!(!io.is_recoverable());
    assert_eq!(
        WireError::EndOfStream.to_string(),
        "stream ended (no further message)"
    );
    assert!(!WireError::EndOfStream.is_recoverable());
    let t = WireError::Truncated {
        part: "body",
        expected: 10,
        got: 3,
    };
    assert_eq!(
        t.to_string(),
        "stream ended inside the message body: 3 of 10 bytes arrived"
    );
    assert!(!t.is_recoverable());
    assert!(!WireError::UnsupportedVersion { version: 9 }.is_recoverable());
    assert!(
        WireError::UnsupportedVersion { version: 9 }
            .to_string()
            .starts_with("header: VERSION 9 is not supported")
    );
    let big = WireError::BodyTooLarge {
        type_name: "IMAGE".into(),
        body_size: 100,
        limit: 10,
    };
    assert_eq!(
        big.to_string(),
        "header: BODY_SIZE 100 of a \"IMAGE\" message exceeds the limit of 10 bytes (body discarded)"
    );
    assert!(big.is_recoverable());
    let crc = WireError::BadCrc {
        type_name: "POINT".into(),
        device_name: "d".into(),
        header_crc: 1,
        computed_crc: 2,
    };
    assert!(crc.is_recoverable());
    let as_dyn: &dyn std::error::Error = &crc;
    assert!(as_dyn.to_string().contains("CRC mismatch"));
}
