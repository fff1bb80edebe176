//! `POLYDATA`: the specification's fixture, every attribute kind round trip, and the count,
//! attribute and encoding errors.

mod common;

use common::{be_f32_bytes, be_u32_bytes, content_err, hex, roundtrip, sample_polydata};
use librplus_igtl::{AttributeKind, AttributeLocation, EncodeOptions, Message, PolyData, crc64};

/// Hand-built from the POLYDATA tables: 3 points, one triangle, a 1-component point scalar
/// "u" and a point vector "disp"; names "u\0disp\0" (7 bytes) padded to 8. CRC from crcmod.
fn polydata_fixture_content() -> Vec<u8> {
    let mut c = be_u32_bytes(&[3, 0, 0, 0, 0, 1, 16, 0, 0, 2]);
    c.extend(be_f32_bytes(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]));
    c.extend(be_u32_bytes(&[3, 0, 1, 2]));
    c.extend(hex("00 01 00000003")); // POINT_DATA scalar, 1 component, 3 tuples
    c.extend(hex("01 03 00000003")); // POINT_DATA vector, 3 components, 3 tuples
    c.extend(b"u\0disp\0\0");
    c.extend(be_f32_bytes(&[0.5, 1.5, 2.5]));
    c.extend(be_f32_bytes(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0]));
    assert_eq!(c.len(), 160);
    c
}

#[test]
fn polydata_fixture_from_the_specification() {
    let content = polydata_fixture_content();
    assert_eq!(crc64(&content), 0xAD21_92C9_69CB_F549);
    let decoded = Message::decode_content("POLYDATA", &content).expect("decodes");
    let Message::PolyData(poly) = &decoded else {
        panic!("not POLYDATA: {decoded:?}")
    };
    assert_eq!(
        poly.points,
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    );
    assert_eq!(
        poly.polygons.iter().collect::<Vec<_>>(),
        vec![&[0u32, 1, 2][..]]
    );
    assert!(poly.vertices.is_empty() && poly.lines.is_empty() && poly.triangle_strips.is_empty());
    assert_eq!(poly.attributes.len(), 2);
    assert_eq!(poly.attributes[0].name, "u");
    assert_eq!(
        poly.attributes[0].kind,
        AttributeKind::Scalar { components: 1 }
    );
    assert_eq!(poly.attributes[0].type_attribute(), 0x0001);
    assert_eq!(poly.attributes[1].kind, AttributeKind::Vector);
    assert_eq!(poly.attributes[1].location, AttributeLocation::Point);
    assert_eq!(poly.attributes[1].type_attribute(), 0x0103);
    assert_eq!(poly.attributes[1].tuple_count(), 3);
    assert_eq!(decoded.encode_content(), Ok(content));
}

#[test]
fn polydata_roundtrip_all_attribute_kinds() {
    let poly = sample_polydata();
    let (_, decoded) = roundtrip(&Message::PolyData(poly.clone()), &EncodeOptions::default());
    roundtrip(&decoded, &EncodeOptions::version2(77));
    // Cell data sets bit 4 of the type byte.
    assert_eq!(poly.attributes[3].type_attribute(), 0x1309);
    assert_eq!(poly.attributes[4].type_attribute(), 0x1404);
    assert_eq!(poly.attributes[5].type_attribute(), 0x1004);
    // Even total name length: no padding byte.
    let mut even = poly.clone();
    even.attributes.truncate(1); // "uncertainty_mm\0" is 15 bytes: padded
    let odd_len = Message::PolyData(even.clone())
        .encode_content()
        .expect("ok")
        .len();
    even.attributes[0].name = "uncertainty_m".into(); // 14 bytes with NUL: no padding
    let even_len = Message::PolyData(even.clone())
        .encode_content()
        .expect("ok")
        .len();
    assert_eq!(odd_len, even_len + 2);
    roundtrip(&Message::PolyData(even), &EncodeOptions::default());
    roundtrip(
        &Message::PolyData(PolyData::default()),
        &EncodeOptions::default(),
    );
    // CellArray accessors.
    assert_eq!(poly.lines.get(1), Some(&[][..]));
    assert_eq!(poly.lines.get(2), None);
    assert_eq!(poly.polygons.indices().len(), 9);
    assert_eq!(poly.polygons.wire_size(), 4 * 12);
}

/// A POLYDATA content with the given header words and a tail.
fn polydata_with(header: [u32; 10], tail: &[u8]) -> Vec<u8> {
    let mut c = be_u32_bytes(&header);
    c.extend_from_slice(tail);
    c
}

#[test]
fn polydata_count_errors() {
    assert_eq!(
        content_err("POLYDATA", &[0; 39]),
        "POLYDATA: header (NPOINTS ... NATTRIBUTES) needs 40 bytes but 39 remain"
    );
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([2, 0, 0, 0, 0, 0, 0, 0, 0, 0], &[0; 20])
        ),
        "POLYDATA: NPOINTS 2 says 24 bytes but 20 remain"
    );
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([0, 0, 0, 0, 0, 1, 400, 0, 0, 0], &[0; 120])
        ),
        "POLYDATA: SIZE_POLYGONS says 400 bytes but 120 remain"
    );
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([0, 0, 0, 1, 6, 0, 0, 0, 0, 0], &[0; 8])
        ),
        "POLYDATA: SIZE_LINES is 6, not a multiple of 4 (uint32 indices)"
    );
    // Two strips announced, the section holds one.
    let tail = be_u32_bytes(&[0]);
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([0, 0, 0, 0, 0, 0, 0, 2, 4, 0], &tail)
        ),
        "POLYDATA: NTRIANGLE_STRIPS is 2 but SIZE_TRIANGLE_STRIPS (4 bytes) holds only 1 cells"
    );
    // A cell whose NINDICES runs past the section.
    let mut tail = be_f32_bytes(&[0.0; 9]);
    tail.extend(be_u32_bytes(&[5, 0, 1]));
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([3, 0, 0, 0, 0, 1, 12, 0, 0, 0], &tail)
        ),
        "POLYDATA: POLYGONS cell 0 NINDICES 5 says 20 bytes but 8 remain"
    );
    // An index past NPOINTS.
    let mut tail = be_f32_bytes(&[0.0; 9]);
    tail.extend(be_u32_bytes(&[3, 0, 1, 3]));
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([3, 0, 0, 0, 0, 1, 16, 0, 0, 0], &tail)
        ),
        "POLYDATA: POLYGONS cell 0 has point index 3, out of range (NPOINTS 3)"
    );
    // A section larger than its cells.
    let tail = be_u32_bytes(&[0, 0]);
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([0, 1, 8, 0, 0, 0, 0, 0, 0, 0], &tail)
        ),
        "POLYDATA: SIZE_VERTICES is 8 bytes but its NVERTICES 1 cells use 4"
    );
    // Huge counts never allocate: they fail on the size check.
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([u32::MAX, 0, 0, 0, 0, 0, 0, 0, 0, 0], &[])
        ),
        "POLYDATA: NPOINTS 4294967295 says 51539607540 bytes but 0 remain"
    );
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([0, u32::MAX, 0, 0, 0, 0, 0, 0, 0, 0], &[])
        ),
        "POLYDATA: NVERTICES is 4294967295 but SIZE_VERTICES (0 bytes) holds only 0 cells"
    );
    assert_eq!(
        content_err(
            "POLYDATA",
            &polydata_with([0, 0, 0, 0, 0, 0, 0, 0, 0, u32::MAX], &[0; 12])
        ),
        "POLYDATA: NATTRIBUTES 4294967295 says 25769803770 bytes but 12 remain"
    );
    // Bytes after the last attribute / after the cells.
    let mut content = polydata_fixture_content();
    content.extend([0, 0, 0, 0]);
    assert_eq!(
        content_err("POLYDATA", &content),
        "POLYDATA: 4 unexplained bytes after the data of attribute 1"
    );
    assert_eq!(
        content_err("POLYDATA", &polydata_with([0; 10], &[1])),
        "POLYDATA: 1 unexplained bytes after TRIANGLE_STRIPS (NATTRIBUTES 0)"
    );
    // Attribute data shorter than NATTRIBUTE x components.
    let content = polydata_fixture_content();
    assert_eq!(
        content_err("POLYDATA", &content[..content.len() - 4]),
        "POLYDATA: attribute 1 \"disp\" NATTRIBUTE 3 x 3 components says 36 bytes but 32 remain"
    );
}

#[test]
fn polydata_attribute_errors() {
    // Offset of the first attribute header in the fixture: 40 + 36 + 16.
    const AT: usize = 92;
    let edit = |offset: usize, bytes: &[u8]| {
        let mut c = polydata_fixture_content();
        c[AT + offset..AT + offset + bytes.len()].copy_from_slice(bytes);
        content_err("POLYDATA", &c)
    };
    assert_eq!(
        edit(0, &[0x20]),
        "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x2001 has a type other than POINT_DATA (0x0_) or CELL_DATA (0x1_)"
    );
    assert_eq!(
        edit(0, &[0x07]),
        "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0701 has unknown attribute type 0x07"
    );
    assert_eq!(
        edit(0, &[0x05, 0x03]),
        "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0503 is texture coordinates (0x05), which the specification does not define"
    );
    assert_eq!(
        edit(1, &[0x00]),
        "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0000 has 0 components where a scalar has 1 to 127"
    );
    assert_eq!(
        edit(1, &[0x80]),
        "POLYDATA: attribute 0 TYPE_ATTRIBUTE 0x0080 has 128 components where a scalar has 1 to 127"
    );
    assert_eq!(
        edit(6, &[0x12, 0x09]),
        "POLYDATA: attribute 1 TYPE_ATTRIBUTE 0x1209 has 9 components where a normal has 3 (the reference \
         C library writes 9 for cell and RGBA attributes, OpenIGTLink issue #36)"
    );
    assert_eq!(
        edit(6, &[0x03, 0x03]),
        "POLYDATA: attribute 1 TYPE_ATTRIBUTE 0x0303 has 3 components where a tensor has 9"
    );
    assert_eq!(
        edit(12, &[0xFF]),
        "POLYDATA: NAME_ATTRIBUTE_0 is not valid UTF-8 (valid up to byte 0)"
    );
    // Scalars may have more than one component (the data must then be longer).
    assert_eq!(
        edit(1, &[0x02]),
        "POLYDATA: attribute 1 \"disp\" NATTRIBUTE 3 x 3 components says 36 bytes but 24 remain"
    );

    // Names: unterminated, longer than 255, missing padding.
    let mut c = polydata_fixture_content();
    c.truncate(AT + 12);
    c.extend(b"u\0disp");
    assert_eq!(
        content_err("POLYDATA", &c),
        "POLYDATA: NAME_ATTRIBUTE_1 has no NUL terminator before the content ends"
    );
    let mut c = polydata_fixture_content();
    c.truncate(AT + 12);
    c.extend(vec![b'a'; 300]);
    assert_eq!(
        content_err("POLYDATA", &c),
        "POLYDATA: NAME_ATTRIBUTE_0 has no NUL terminator within 256 bytes (at most 255 allowed)"
    );
    let mut c = polydata_fixture_content();
    c.truncate(AT + 12 + 7);
    assert_eq!(
        content_err("POLYDATA", &c),
        "POLYDATA: ATTRIBUTE_NAMES padding needs 1 bytes but 0 remain"
    );
}

#[test]
fn polydata_encode_errors() {
    let encode = |poly: PolyData| {
        Message::PolyData(poly)
            .encode_content()
            .expect_err("invalid")
            .to_string()
    };
    let mut p = sample_polydata();
    p.polygons.push(&[0, 4]);
    assert_eq!(
        encode(p),
        "POLYDATA: POLYGONS cell 3 has point index 4, out of range (NPOINTS 4)"
    );
    let mut p = sample_polydata();
    p.attributes[0].kind = AttributeKind::Scalar { components: 0 };
    assert_eq!(
        encode(p),
        "POLYDATA: attribute 0 \"uncertainty_mm\" NCOMPONENTS is 0; scalars have 1 to 127 components"
    );
    let mut p = sample_polydata();
    p.attributes[1].data.pop();
    assert_eq!(
        encode(p),
        "POLYDATA: attribute 1 \"displacement\" data has 11 values, not a multiple of its 3 components"
    );
    let mut p = sample_polydata();
    p.attributes[2].name = "x".repeat(256);
    assert_eq!(
        encode(p),
        "POLYDATA: NAME_ATTRIBUTE_2 is 256 bytes, at most 255 fit"
    );
    let mut p = sample_polydata();
    p.attributes[2].name = "a\0".into();
    assert_eq!(encode(p), "POLYDATA: NAME_ATTRIBUTE_2 contains a NUL byte");
}
