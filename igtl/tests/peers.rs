//! Bytes from peers: fixtures packed by pyigtl 0.3.4 (decoded, and re-encoded byte for byte), and
//! the fixture directory of `$IGTL_PEER_FIXTURES` when set.

mod common;

use common::{decode_err, hex};
use librplus_igtl::{
    CellArray, EncodeOptions, ExtendedHeader, HEADER_SIZE, Header, Message, PointElement, Status,
    Transform, decode_message, split_body, status_code, timestamp_from_secs,
};

// Produced by pyigtl 0.3.4 from PyPI (its _version.py says 0.3.2) with numpy: the message
// classes' pack(), called as each constant's comment says. Header version 1 unless noted.

/// TransformMessage(matrix [[0,-1,0,10.5],[1,0,0,-20.25],[0,0,1,300.125]],
/// timestamp=1700000000.25, device_name="ImageToPhysical").
const PYIGTL_TRANSFORM_V1: &str = "\
    00015452414e53464f524d000000496d616765546f506879736963616c00000000006553f1004000000000000000000000302b59975f00d24720000000003f80\
    000000000000bf800000000000000000000000000000000000003f80000041280000c1a2000043961000";

/// The same matrix, header_version=2, message_id=7, metadata {"Units": "mm", "Frame": "RAS"},
/// timestamp=1.5, device_name="Probe".
const PYIGTL_TRANSFORM_V2_META: &str = "\
    00025452414e53464f524d00000050726f62650000000000000000000000000000000000000180000000000000000000005d5d4c0b30a5639fca000c00120000\
    000f00000007000000003f80000000000000bf800000000000000000000000000000000000003f80000041280000c1a200004396100000020005000300000002\
    0005000300000003556e6974736d6d4672616d65524153";

/// PointMessage: ("F-1", "Landmark", rgba 255,0,0,255, (1.5,-2.25,3), diameter 2.5, owner "")
/// and ("tumour centre", "Target", rgba 0,128,255,200, (100,200.5,-300.75), 0, "CT"),
/// timestamp=1234.5, device_name="Fiducials".
const PYIGTL_POINT_V1: &str = "\
    0001504f494e5400000000000000466964756369616c730000000000000000000000000004d28000000000000000000001102963bceb31c91e17462d31000000\
    000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000004c616e646d61\
    726b000000000000000000000000000000000000000000000000ff0000ff3fc00000c01000004040000040200000000000000000000000000000000000000000\
    000074756d6f75722063656e74726500000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000\
    000054617267657400000000000000000000000000000000000000000000000000000080ffc842c8000043488000c39660000000000043540000000000000000\
    00000000000000000000";

/// PolyDataMessage(points 4x3, lines [2,0,3], polygons [3,0,1,2, 3,0,1,3, 4,0,1,2,3]),
/// timestamp=42, device_name="Liver".
const PYIGTL_POLYDATA: &str = "\
    0001504f4c5944415441000000004c697665720000000000000000000000000000000000002a0000000000000000000000981c62ff36b27ab293000000040000\
    000000000000000000010000000c0000000300000034000000000000000000000000000000000000000000000000412000000000000000000000000000004120\
    00000000000000000000000000004120000000000002000000000000000300000003000000000000000100000002000000030000000000000001000000030000\
    000400000000000000010000000200000003";

/// PolyDataMessage(points 4x3, vertices [1, 0, 1, 2]): pyigtl writes vertex cells in host
/// (little-endian) byte order, so NINDICES reads as 0x01000000.
const PYIGTL_POLYDATA_VERTICES_LE: &str = "\
    0001504f4c5944415441000000004c697665720000000000000000000000000000000000002a00000000000000000000006839ceefca74d25675000000040000\
    00020000001000000000000000000000000000000000000000000000000000000000000000000000000000000000412000000000000000000000000000004120\
    00000000000000000000000000004120000001000000000000000100000002000000";

/// STATUS (pyigtl has no STATUS class: header, framing and CRC by pyigtl's MessageBase.pack,
/// content by struct.pack("> H q 20s") + text + NUL): code 12, subcode -3, "UnknownType",
/// "type FOO is not supported", timestamp=5, device_name="LIBR+".
const PYIGTL_STATUS_V1: &str = "\
    00015354415455530000000000004c4942522b00000000000000000000000000000000000005000000000000000000000038276561b1127140f6000cffffffff\
    fffffffd556e6b6e6f776e547970650000000000000000007479706520464f4f206973206e6f7420737570706f7274656400";

#[test]
fn pyigtl_transform_fixtures() {
    let expected = Transform {
        matrix: [
            [0.0, -1.0, 0.0, 10.5],
            [1.0, 0.0, 0.0, -20.25],
            [0.0, 0.0, 1.0, 300.125],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };
    let (header, message) = decode_message(&hex(PYIGTL_TRANSFORM_V1)).expect("decodes");
    assert_eq!(header.version, 1);
    assert_eq!(header.device_name, "ImageToPhysical");
    assert_eq!(header.timestamp_secs(), 1_700_000_000.25);
    assert_eq!(message, Message::Transform(expected));
    // Our encoder produces pyigtl's bytes exactly.
    let options = EncodeOptions {
        timestamp: header.timestamp,
        ..EncodeOptions::default()
    };
    assert_eq!(
        Message::Transform(expected).encode("ImageToPhysical", &options),
        Ok(hex(PYIGTL_TRANSFORM_V1))
    );

    let bytes = hex(PYIGTL_TRANSFORM_V2_META);
    let (header, message) = decode_message(&bytes).expect("decodes");
    assert_eq!(
        (
            header.version,
            header.device_name.as_str(),
            header.timestamp_secs()
        ),
        (2, "Probe", 1.5)
    );
    assert_eq!(message, Message::Transform(expected));
    let parts = split_body(&header, &bytes[HEADER_SIZE..]).expect("splits");
    assert_eq!(
        parts.extended,
        Some(ExtendedHeader {
            ext_header_size: 12,
            meta_header_size: 18,
            meta_size: 15,
            message_id: 7
        })
    );
    assert_eq!(parts.metadata, b"UnitsmmFrameRAS");
}

#[test]
fn pyigtl_point_fixture() {
    let bytes = hex(PYIGTL_POINT_V1);
    let (header, message) = decode_message(&bytes).expect("decodes");
    assert_eq!(header.device_name, "Fiducials");
    assert_eq!(header.timestamp_secs(), 1234.5);
    let expected = vec![
        PointElement {
            name: "F-1".into(),
            group: "Landmark".into(),
            rgba: [255, 0, 0, 255],
            position_mm: [1.5, -2.25, 3.0],
            diameter_mm: 2.5,
            owner: String::new(),
        },
        PointElement {
            name: "tumour centre".into(),
            group: "Target".into(),
            rgba: [0, 128, 255, 200],
            position_mm: [100.0, 200.5, -300.75],
            diameter_mm: 0.0,
            owner: "CT".into(),
        },
    ];
    assert_eq!(message, Message::Point(expected.clone()));
    let options = EncodeOptions {
        timestamp: header.timestamp,
        ..EncodeOptions::default()
    };
    assert_eq!(
        Message::Point(expected).encode("Fiducials", &options),
        Ok(bytes)
    );
}

#[test]
fn pyigtl_polydata_and_status_fixtures() {
    let bytes = hex(PYIGTL_POLYDATA);
    let (_, message) = decode_message(&bytes).expect("decodes");
    let Message::PolyData(poly) = &message else {
        panic!("{message:?}")
    };
    assert_eq!(poly.points.len(), 4);
    assert_eq!(poly.points[3], [0.0, 0.0, 10.0]);
    assert_eq!(poly.lines, CellArray::from_cells([[0u32, 3]]));
    assert_eq!(
        poly.polygons,
        CellArray::from_cells([vec![0u32, 1, 2], vec![0, 1, 3], vec![0, 1, 2, 3]])
    );
    assert!(poly.attributes.is_empty() && poly.vertices.is_empty());
    let options = EncodeOptions {
        timestamp: timestamp_from_secs(42.0),
        ..EncodeOptions::default()
    };
    assert_eq!(message.encode("Liver", &options), Ok(bytes));

    assert_eq!(
        decode_err(&hex(PYIGTL_POLYDATA_VERTICES_LE)).to_string(),
        "POLYDATA: VERTICES cell 0 NINDICES 16777216 says 67108864 bytes but 12 remain"
    );

    let (header, message) = decode_message(&hex(PYIGTL_STATUS_V1)).expect("decodes");
    assert_eq!(header.device_name, "LIBR+");
    let expected = Status {
        code: status_code::ILLEGAL_INSTRUCTION,
        subcode: -3,
        error_name: "UnknownType".into(),
        message: "type FOO is not supported".into(),
    };
    assert_eq!(message, Message::Status(expected.clone()));
    let options = EncodeOptions {
        timestamp: header.timestamp,
        ..EncodeOptions::default()
    };
    assert_eq!(
        Message::Status(expected).encode("LIBR+", &options),
        Ok(hex(PYIGTL_STATUS_V1))
    );
}

/// Canonical text of a decoded message: the `NAME.expect` format a fixture script writes from
/// the values it gave pyigtl (one value per line, f32 as bit patterns, timestamp in seconds
/// compared to 1e-6, a lone `error` line for a message that must be rejected).
fn render(header: &Header, message: &Message) -> Vec<String> {
    let bits = |v: f32| format!("{:08x}", v.to_bits());
    let mut out = vec![
        format!("type {}", header.type_name),
        format!("device {}", header.device_name),
        format!("version {}", header.version),
        format!("timestamp {:.6}", header.timestamp_secs()),
    ];
    match message {
        Message::Transform(t) => {
            for r in 0..3 {
                for c in 0..4 {
                    out.push(format!("m{r}{c} {}", bits(t.matrix[r][c] as f32)));
                }
            }
        }
        Message::Point(points) => {
            for (i, p) in points.iter().enumerate() {
                let [r, g, b, a] = p.rgba;
                let [x, y, z] = p.position_mm;
                out.push(format!("point {i} name={}", p.name));
                out.push(format!("point {i} group={}", p.group));
                out.push(format!("point {i} rgba={r},{g},{b},{a}"));
                out.push(format!("point {i} xyz={},{},{}", bits(x), bits(y), bits(z)));
                out.push(format!("point {i} diameter={}", bits(p.diameter_mm)));
                out.push(format!("point {i} owner={}", p.owner));
            }
        }
        Message::Status(s) => {
            out.push(format!("code {}", s.code));
            out.push(format!("subcode {}", s.subcode));
            out.push(format!("error_name {}", s.error_name));
            out.push(format!("message {}", s.message));
        }
        Message::PolyData(p) => {
            out.push(format!("points {}", p.points.len()));
            for (i, [x, y, z]) in p.points.iter().enumerate() {
                out.push(format!("p {i} {},{},{}", bits(*x), bits(*y), bits(*z)));
            }
            for (name, one, cells) in [
                ("vertices", "vertex", &p.vertices),
                ("lines", "line", &p.lines),
                ("polygons", "polygon", &p.polygons),
                ("triangle_strips", "triangle_strip", &p.triangle_strips),
            ] {
                out.push(format!("{name} {}", cells.len()));
                for (i, cell) in cells.iter().enumerate() {
                    let list: Vec<String> = cell.iter().map(u32::to_string).collect();
                    out.push(format!("{one} {i} {}", list.join(",")));
                }
            }
            out.push(format!("attributes {}", p.attributes.len()));
        }
        Message::Unknown { type_name, body } => {
            out.push(format!("unknown {type_name} {}", body.len()))
        }
    }
    out
}

/// Decodes every `NAME.igtl` in `$IGTL_PEER_FIXTURES` (messages packed by pyigtl) and compares
/// with `NAME.expect` (see [`render`]); skipped when the variable is unset.
#[test]
fn peer_fixtures_from_env() {
    let Some(dir) = std::env::var_os("IGTL_PEER_FIXTURES") else {
        eprintln!(
            "peer_fixtures_from_env: skipped (set IGTL_PEER_FIXTURES to a pyigtl fixture directory)"
        );
        return;
    };
    let mut entries: Vec<_> = std::fs::read_dir(&dir)
        .expect("fixture directory readable")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "igtl"))
        .collect();
    entries.sort();
    assert!(!entries.is_empty(), "no .igtl files in {dir:?}");
    for path in entries {
        let bytes = std::fs::read(&path).expect("fixture readable");
        let expect = std::fs::read_to_string(path.with_extension("expect")).expect("expect file");
        let expect: Vec<&str> = expect.lines().collect();
        let decoded = decode_message(&bytes);
        if expect == ["error"] {
            let e = decoded.expect_err("pyigtl fixture expected to be rejected");
            eprintln!("{}: rejected as expected: {e}", path.display());
            continue;
        }
        let (header, message) = decoded.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let got = render(&header, &message);
        assert_eq!(got.len(), expect.len(), "{}: {got:#?}", path.display());
        for (g, e) in got.iter().zip(&expect) {
            match (g.strip_prefix("timestamp "), e.strip_prefix("timestamp ")) {
                (Some(g), Some(e)) => {
                    let (g, e): (f64, f64) = (g.parse().expect("f64"), e.parse().expect("f64"));
                    assert!(
                        (g - e).abs() <= 1e-6,
                        "{}: timestamp {g} vs {e}",
                        path.display()
                    );
                }
                _ => assert_eq!(g, e, "{}", path.display()),
            }
        }
        eprintln!("{}: {} values equal", path.display(), got.len());
    }
}
