//! `STATUS`: every code round trips, the content layout, the lenient message terminator, and
//! errors.

mod common;

use common::{content_err, field, hex, roundtrip};
use librplus_igtl::{EncodeOptions, Message, Status, status_code};

#[test]
fn status_roundtrip_and_codes() {
    for code in 0..=19u16 {
        let status = Status {
            code,
            subcode: -(i64::from(code)) * 1_000_000_007,
            error_name: status_code::describe(code)
                .map(|d| d.chars().take(20).collect())
                .unwrap_or_default(),
            message: format!(
                "code {code}: {}",
                status_code::describe(code).unwrap_or("?")
            ),
        };
        roundtrip(&Message::Status(status), &EncodeOptions::default());
    }
    assert_eq!(status_code::describe(20), None);
    assert_eq!(status_code::OK, 1);
    assert_eq!(status_code::ILLEGAL_INSTRUCTION, 12);
    assert_eq!(status_code::SHUT_DOWN, 19);
    let empty = Status {
        code: 1,
        subcode: 0,
        error_name: String::new(),
        message: String::new(),
    };
    let (header, _) = roundtrip(&Message::Status(empty), &EncodeOptions::version2(3));
    assert_eq!(header.body_size, 12 + 31 + 2);
}

#[test]
fn status_layout_and_lenient_message() {
    // Hand-built: C=9, SUB_CODE=-1, ERROR_NAME "CRC", MESSAGE "bad\0".
    let mut content = hex("0009 FFFFFFFFFFFFFFFF");
    content.extend(field(b"CRC", 20));
    content.extend(b"bad\0");
    let expected = Status {
        code: 9,
        subcode: -1,
        error_name: "CRC".into(),
        message: "bad".into(),
    };
    assert_eq!(
        Message::decode_content("STATUS", &content),
        Ok(Message::Status(expected.clone()))
    );
    assert_eq!(
        Message::Status(expected).encode_content(),
        Ok(content.clone())
    );
    // Without the terminator the message is taken whole; with none at all it is empty.
    content.pop();
    assert!(
        matches!(Message::decode_content("STATUS", &content), Ok(Message::Status(s)) if s.message == "bad")
    );
    assert!(
        matches!(Message::decode_content("STATUS", &content[..30]), Ok(Message::Status(s)) if s.message.is_empty())
    );
}

#[test]
fn status_errors() {
    assert_eq!(
        content_err("STATUS", &[0; 29]),
        "STATUS: C, SUB_CODE and ERROR_NAME needs 30 bytes but 29 remain"
    );
    let mut content = vec![0; 30];
    content.extend(b"\xFFoops\0");
    assert_eq!(
        content_err("STATUS", &content),
        "STATUS: MESSAGE is not valid UTF-8 (valid up to byte 0)"
    );
    let status = Status {
        code: 2,
        subcode: 0,
        error_name: "e".repeat(21),
        message: String::new(),
    };
    let e = Message::Status(status).encode_content().expect_err("long");
    assert_eq!(
        e.to_string(),
        "STATUS: ERROR_NAME is 21 bytes, at most 20 fit"
    );
    let status = Status {
        code: 2,
        subcode: 0,
        error_name: String::new(),
        message: "a\0b".into(),
    };
    let e = Message::Status(status).encode_content().expect_err("NUL");
    assert_eq!(e.to_string(), "STATUS: MESSAGE contains a NUL byte");
}
