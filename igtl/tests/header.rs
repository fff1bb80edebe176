//! The 58-byte header (layout, full-width names, errors) and version 2 bodies: extended header,
//! metadata skipped, and their size errors.

mod common;

use common::{decode_err, frame_v1, hex, transform_fixture};
use librplus_igtl::{HEADER_SIZE, Header, Message, WireError, decode_message, timestamp_to_secs};

#[test]
fn header_roundtrip_and_full_width_names() {
    let header = Header {
        version: 2,
        type_name: "ABCDEFGHIJKL".into(), // 12 bytes: no terminator on the wire
        device_name: "D".repeat(20),
        timestamp: 0x0102_0304_0506_0708,
        body_size: 12345,
        crc: 0xDEAD_BEEF_0000_0001,
    };
    let bytes = header.encode().expect("encodes");
    assert_eq!(&bytes[0..2], &[0, 2]);
    assert_eq!(&bytes[2..14], b"ABCDEFGHIJKL");
    assert_eq!(&bytes[42..50], &12345u64.to_be_bytes());
    assert_eq!(Header::parse(&bytes), Ok(header.clone()));
    assert_eq!(header.timestamp_secs(), timestamp_to_secs(header.timestamp));
}

#[test]
fn header_errors() {
    let good = Header {
        version: 1,
        type_name: "POINT".into(),
        device_name: "x".into(),
        timestamp: 0,
        body_size: 0,
        crc: 0,
    };
    let mut bytes = good.encode().expect("encodes");
    bytes[1] = 3;
    assert_eq!(
        Header::parse(&bytes),
        Err(WireError::UnsupportedVersion { version: 3 })
    );
    bytes[1] = 0;
    assert_eq!(
        Header::parse(&bytes),
        Err(WireError::UnsupportedVersion { version: 0 })
    );

    let mut bytes = good.encode().expect("encodes");
    bytes[3] = 0xFF;
    let e = Header::parse(&bytes).expect_err("non-UTF-8 type");
    assert_eq!(
        e.to_string(),
        "header: TYPE is not valid UTF-8 (valid up to byte 1)"
    );
    let mut bytes = good.encode().expect("encodes");
    bytes[14] = 0xC3; // a lone UTF-8 lead byte
    let e = Header::parse(&bytes).expect_err("non-UTF-8 device");
    assert!(
        e.to_string()
            .starts_with("header: DEVICE_NAME is not valid UTF-8"),
        "{e}"
    );

    // Bytes after the terminating NUL are ignored.
    let mut bytes = good.encode().expect("encodes");
    bytes[10] = b'Z';
    assert_eq!(
        Header::parse(&bytes).map(|h| h.type_name),
        Ok("POINT".into())
    );

    let long = Header {
        type_name: "THIRTEEN_CHRS".into(),
        ..good.clone()
    };
    assert_eq!(
        long.encode().expect_err("too long").to_string(),
        "header: TYPE is 13 bytes, at most 12 fit"
    );
    let nul = Header {
        device_name: "a\0b".into(),
        ..good.clone()
    };
    assert_eq!(
        nul.encode().expect_err("NUL").to_string(),
        "header: DEVICE_NAME contains a NUL byte"
    );
    let v3 = Header { version: 3, ..good };
    assert_eq!(
        v3.encode(),
        Err(WireError::UnsupportedVersion { version: 3 })
    );
}

/// A version 2 frame with the given extended header fields, content and metadata bytes.
fn frame_v2(type_name: &str, ext: [u32; 4], content: &[u8], metadata: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend_from_slice(&(ext[0] as u16).to_be_bytes());
    body.extend_from_slice(&(ext[1] as u16).to_be_bytes());
    body.extend_from_slice(&ext[2].to_be_bytes());
    body.extend_from_slice(&ext[3].to_be_bytes());
    body.extend_from_slice(content);
    body.extend_from_slice(metadata);
    let mut out = frame_v1(type_name, "dev", &body);
    out[1] = 2;
    out
}

#[test]
fn version2_metadata_is_skipped() {
    let content = transform_fixture()[HEADER_SIZE..].to_vec();
    // INDEX_COUNT 1: key "Units" (5), encoding 3 (US-ASCII), value "mm" (2).
    let mut meta = hex("0001 0005 0003 00000002");
    meta.extend(b"Unitsmm");
    let bytes = frame_v2("TRANSFORM", [12, 10, 7, 42], &content, &meta);
    let (header, message) = decode_message(&bytes).expect("decodes");
    assert_eq!(header.version, 2);
    assert!(matches!(message, Message::Transform(t) if t.matrix[2][3] == 30.5));
    // A longer extended header (future fields) is skipped too.
    let mut longer = vec![0xAB, 0xCD];
    longer.extend(&content);
    let bytes = frame_v2("TRANSFORM", [14, 10, 7, 42], &longer, &meta);
    assert!(matches!(
        decode_message(&bytes),
        Ok((_, Message::Transform(_)))
    ));
    // Unknown types expose the content only.
    let bytes = frame_v2("GET_STATUS", [12, 10, 7, 1], b"xyz", &meta);
    assert_eq!(
        decode_message(&bytes).map(|(_, m)| m),
        Ok(Message::Unknown {
            type_name: "GET_STATUS".into(),
            body: b"xyz".to_vec()
        })
    );
}

#[test]
fn version2_empty_body_is_empty_content() {
    let mut bytes = frame_v1("GET_STATUS", "dev", &[]);
    bytes[1] = 2;
    assert_eq!(
        decode_message(&bytes).map(|(_, m)| m),
        Ok(Message::Unknown {
            type_name: "GET_STATUS".into(),
            body: vec![]
        })
    );
}

#[test]
fn version2_errors() {
    let content = [0u8; 48];
    let err = |bytes: Vec<u8>| decode_err(&bytes).to_string();
    let mut short = frame_v1("TRANSFORM", "dev", &[0; 11]);
    short[1] = 2;
    assert_eq!(
        err(short),
        "extended header: EXT_HEADER_SIZE, META_HEADER_SIZE, META_SIZE and MSG_ID needs 12 bytes but 11 remain"
    );
    assert_eq!(
        err(frame_v2("TRANSFORM", [8, 2, 0, 0], &content, &[0, 0])),
        "extended header: EXT_HEADER_SIZE is 8, at least 12 expected"
    );
    assert_eq!(
        err(frame_v2("TRANSFORM", [100, 2, 0, 0], &content, &[0, 0])),
        "extended header: EXT_HEADER_SIZE 100 says 88 bytes but 50 remain"
    );
    assert_eq!(
        err(frame_v2("TRANSFORM", [12, 60, 0, 0], &content, &[0, 0])),
        "extended header: META_HEADER_SIZE 60 + META_SIZE 0 says 60 bytes but 50 remain"
    );
    // Sizes that fit the body but not the content show up as a content of the wrong length.
    assert_eq!(
        err(frame_v2("TRANSFORM", [12, 2, 9, 0], &content, &[0, 0])),
        "TRANSFORM: content is 39 bytes, a TRANSFORM has exactly 48 (12 float32)"
    );
}

#[test]
fn version2_metadata_errors() {
    let content = [0u8; 48];
    let err = |bytes: Vec<u8>| decode_err(&bytes).to_string();
    assert_eq!(
        err(frame_v2(
            "TRANSFORM",
            [12, 2, 3, 0],
            &content,
            &hex("0002 616263")
        )),
        "metadata: INDEX_COUNT 2 says 16 bytes but 0 remain"
    );
    assert_eq!(
        err(frame_v2(
            "TRANSFORM",
            [12, 10, 3, 0],
            &content,
            &hex("0001 0002 0003 00000002 616263")
        )),
        "metadata: KEY_SIZE + VALUE_SIZE of 1 entries says 4 bytes but 3 remain"
    );
    assert_eq!(
        err(frame_v2(
            "TRANSFORM",
            [12, 0, 3, 0],
            &content,
            &hex("616263")
        )),
        "metadata: META_SIZE is 3 but META_HEADER_SIZE is 0"
    );
    assert_eq!(
        err(frame_v2("TRANSFORM", [12, 1, 0, 0], &content, &hex("00"))),
        "metadata: INDEX_COUNT needs 2 bytes but 1 remain"
    );
}
