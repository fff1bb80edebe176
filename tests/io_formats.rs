//! Mesh file formats: round trips, hand-written samples of each variant, error messages on
//! malformed and truncated input, robustness against corrupted files, and the real liver files.

use base64::Engine as _;
use librplus::mesh::io::*;
use proptest::prelude::*;
use std::io::Write as _;
use std::path::Path;

const B64: base64::engine::GeneralPurpose = base64::engine::general_purpose::STANDARD;

fn read_as(bytes: &[u8], format: Format) -> Result<MeshFile, IoError> {
    read_bytes(bytes, format, Path::new("test"), Unit::Mm)
}

fn read_ok(bytes: &[u8], format: Format) -> MeshFile {
    match read_as(bytes, format) {
        Ok(m) => m,
        Err(e) => panic!("reading {format:?} failed: {e}"),
    }
}

fn read_err(bytes: &[u8], format: Format) -> String {
    match read_as(bytes, format) {
        Ok(m) => panic!("expected an error, got {} nodes", m.nodes.len()),
        Err(e) => e.to_string(),
    }
}

fn write_as(file: &MeshFile, format: Format, binary: bool) -> Vec<u8> {
    write_bytes(file, format, WriteOptions { binary }, Path::new("out")).expect("write")
}

/// Two tetrahedra sharing the face (1, 2, 3), with a displacement, a scalar and a cell array.
fn two_tets() -> MeshFile {
    let nodes = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
    ];
    let disp: Vec<f64> = (0..15).map(|i| 0.1 * i as f64 - 0.3).collect();
    MeshFile {
        nodes,
        tets: vec![[0, 1, 2, 3], [1, 2, 3, 4]],
        triangles: vec![],
        point_data: vec![
            DataArray::new("displacement", 3, disp),
            DataArray::new("temperature", 1, vec![36.5, 37.0, 1e-9, -2.5, 1e20]),
        ],
        cell_data: vec![DataArray::new("region", 1, vec![1.0, 2.0])],
        skipped_cells: 0,
    }
}

/// The boundary of the two tetrahedra (6 triangles), with point data and a per-triangle array.
fn surface() -> MeshFile {
    let mut m = two_tets();
    m.tets.clear();
    m.triangles = vec![
        [0, 2, 1],
        [0, 1, 3],
        [0, 3, 2],
        [1, 2, 4],
        [1, 4, 3],
        [2, 3, 4],
    ];
    m.cell_data = vec![DataArray::new("patch", 1, (0..6).map(f64::from).collect())];
    m
}

fn coords_of(m: &MeshFile) -> Vec<[[f64; 3]; 3]> {
    m.triangles
        .iter()
        .map(|t| t.map(|i| m.nodes[i as usize]))
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Round trips

#[test]
fn vtu_round_trip_ascii_and_binary() {
    let m = two_tets();
    for binary in [false, true] {
        let bytes = write_as(&m, Format::Vtu, binary);
        let text = String::from_utf8(bytes.clone()).unwrap();
        assert!(text.contains(
            r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64">"#
        ));
        assert_eq!(read_ok(&bytes, Format::Vtu), m, "binary={binary}");
    }
}

#[test]
fn vtu_writes_triangles_when_there_are_no_tets() {
    let m = surface();
    let back = read_ok(&write_as(&m, Format::Vtu, true), Format::Vtu);
    assert_eq!(back, m);
}

#[test]
fn vtp_round_trip_surface_and_point_set() {
    let s = surface();
    for binary in [false, true] {
        assert_eq!(read_ok(&write_as(&s, Format::Vtp, binary), Format::Vtp), s);
    }
    let mut points = two_tets();
    points.tets.clear();
    points.cell_data.clear();
    let back = read_ok(&write_as(&points, Format::Vtp, true), Format::Vtp);
    assert_eq!(back.nodes, points.nodes);
    assert_eq!(back.point_data, points.point_data);
    assert_eq!(back.skipped_cells, 5, "one Verts cell per point");
    // A tet-only mesh has no PolyData representation.
    let err = write_bytes(
        &two_tets(),
        Format::Vtp,
        WriteOptions::default(),
        Path::new("x.vtp"),
    );
    assert!(err.unwrap_err().to_string().contains("surfaces only"));
}

#[test]
fn vtk_legacy_round_trip() {
    let m = two_tets();
    for binary in [false, true] {
        let bytes = write_as(&m, Format::VtkLegacy, binary);
        assert!(bytes.starts_with(b"# vtk DataFile Version 4.2\n"));
        assert_eq!(read_ok(&bytes, Format::VtkLegacy), m, "binary={binary}");
    }
    let s = surface();
    for binary in [false, true] {
        assert_eq!(
            read_ok(&write_as(&s, Format::VtkLegacy, binary), Format::VtkLegacy),
            s
        );
    }
    // Arrays with more than 4 components go to a FIELD block; names with spaces survive.
    let mut wide = two_tets();
    wide.point_data = vec![DataArray::new(
        "stress tensor",
        6,
        (0..30).map(f64::from).collect(),
    )];
    for binary in [false, true] {
        assert_eq!(
            read_ok(
                &write_as(&wide, Format::VtkLegacy, binary),
                Format::VtkLegacy
            ),
            wide
        );
    }
}

#[test]
fn msh_round_trip() {
    let m = two_tets();
    let bytes = write_as(&m, Format::Msh, false);
    assert!(bytes.starts_with(b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n"));
    assert_eq!(read_ok(&bytes, Format::Msh), m);
    // With tets and triangles, cell data (over the tets) is not written: $ElementData would not
    // cover every element.
    let mut both = two_tets();
    both.triangles = surface().triangles;
    let back = read_ok(&write_as(&both, Format::Msh, false), Format::Msh);
    both.cell_data.clear();
    assert_eq!(back, both);
    let s = surface();
    assert_eq!(read_ok(&write_as(&s, Format::Msh, false), Format::Msh), s);
}

#[test]
fn obj_round_trip() {
    let s = surface();
    let back = read_ok(&write_as(&s, Format::Obj, false), Format::Obj);
    assert_eq!(back.nodes, s.nodes);
    assert_eq!(back.triangles, s.triangles);
    let err = write_bytes(
        &two_tets(),
        Format::Obj,
        WriteOptions::default(),
        Path::new("x.obj"),
    );
    assert!(err.unwrap_err().to_string().contains("surfaces only"));
}

#[test]
fn stl_round_trip_binary_and_ascii() {
    let s = surface();
    for binary in [false, true] {
        let bytes = write_as(&s, Format::Stl, binary);
        if binary {
            assert_eq!(bytes.len(), 84 + 50 * 6);
        } else {
            assert!(bytes.starts_with(b"solid"));
        }
        let back = read_ok(&bytes, Format::Stl);
        assert_eq!(back.nodes.len(), 5, "welded, binary={binary}");
        assert_eq!(coords_of(&back), coords_of(&s));
    }
}

#[test]
fn write_and_read_files_on_disk_with_units() {
    let dir = tempfile::tempdir().unwrap();
    let m = two_tets();
    for ext in ["vtu", "vtk", "msh"] {
        let path = dir.path().join(format!("mesh.{ext}"));
        write(&path, &m, WriteOptions::default()).unwrap();
        let back = read(&path, Unit::Cm).unwrap();
        for (a, b) in back.nodes.iter().zip(&m.nodes) {
            for k in 0..3 {
                assert!((a[k] - 10.0 * b[k]).abs() < 1e-12, "{ext}");
            }
        }
        let d0 = m.point_array("displacement").unwrap();
        let d1 = back.point_array("displacement").unwrap();
        for (a, b) in d1.values.iter().zip(&d0.values) {
            assert!((a - 10.0 * b).abs() < 1e-12, "{ext}");
        }
        // Non-length arrays are not scaled.
        assert_eq!(
            back.point_array("temperature"),
            m.point_array("temperature")
        );
    }
}

// ---------------------------------------------------------------------------------------------
// VTK XML samples

const VTU_ASCII: &str = r#"<?xml version="1.0"?>
<!-- a tetra, a quad, a line and a triangle -->
<VTKFile type="UnstructuredGrid" version="0.1" byte_order="LittleEndian">
  <UnstructuredGrid>
    <Piece NumberOfPoints="5" NumberOfCells="4">
      <PointData Scalars="t">
        <DataArray type="Float32" Name="t" format="ascii">0 1 2 3 4</DataArray>
        <DataArray type="String" Name="labels" format="ascii">97 0</DataArray>
      </PointData>
      <CellData>
        <DataArray type="Int32" Name="id" format="ascii">10 20 30 40</DataArray>
      </CellData>
      <Points>
        <DataArray type="Float64" NumberOfComponents="3" format="ascii">
          0 0 0  1 0 0  0 1 0  0 0 1  1 1 0
        </DataArray>
      </Points>
      <Cells>
        <DataArray type="Int64" Name="connectivity" format="ascii">0 1 2 3  0 1 4 2  0 1  1 4 2</DataArray>
        <DataArray type="Int64" Name="offsets" format="ascii">4 8 10 13</DataArray>
        <DataArray type="UInt8" Name="types" format="ascii">10 9 3 5</DataArray>
      </Cells>
    </Piece>
  </UnstructuredGrid>
</VTKFile>
"#;

#[test]
fn vtu_ascii_sample() {
    let m = read_ok(VTU_ASCII.as_bytes(), Format::Vtu);
    assert_eq!(m.nodes.len(), 5);
    assert_eq!(m.tets, vec![[0, 1, 2, 3]]);
    assert_eq!(m.triangles, vec![[0, 1, 4], [0, 4, 2], [1, 4, 2]]);
    assert_eq!(m.skipped_cells, 1);
    assert_eq!(m.point_data.len(), 1, "String arrays are skipped");
    assert_eq!(m.point_data[0].values, vec![0.0, 1.0, 2.0, 3.0, 4.0]);
    // Cell data follow the kept tetrahedra.
    assert_eq!(m.cell_data, vec![DataArray::new("id", 1, vec![10.0])]);
}

/// The three arrays of a one-tet grid: points (Float32), connectivity (Int32), offsets, types.
struct TetArrays {
    points: Vec<u8>,
    conn: Vec<u8>,
    offsets: Vec<u8>,
    types: Vec<u8>,
    disp: Vec<u8>,
}

fn tet_arrays(big_endian: bool) -> TetArrays {
    let f32s = |v: &[f32]| -> Vec<u8> {
        v.iter()
            .flat_map(|x| {
                if big_endian {
                    x.to_be_bytes()
                } else {
                    x.to_le_bytes()
                }
            })
            .collect()
    };
    let i32s = |v: &[i32]| -> Vec<u8> {
        v.iter()
            .flat_map(|x| {
                if big_endian {
                    x.to_be_bytes()
                } else {
                    x.to_le_bytes()
                }
            })
            .collect()
    };
    TetArrays {
        points: f32s(&[0., 0., 0., 1., 0., 0., 0., 1., 0., 0., 0., 1.]),
        conn: i32s(&[0, 1, 2, 3]),
        offsets: i32s(&[4]),
        types: vec![10],
        disp: f32s(&[0.5; 12]),
    }
}

fn header(n: u64, h64: bool, big_endian: bool) -> Vec<u8> {
    match (h64, big_endian) {
        (true, false) => n.to_le_bytes().to_vec(),
        (true, true) => n.to_be_bytes().to_vec(),
        (false, false) => (n as u32).to_le_bytes().to_vec(),
        (false, true) => (n as u32).to_be_bytes().to_vec(),
    }
}

/// Base64 of header + data as one stream (how VTK writes uncompressed arrays).
fn b64_joined(data: &[u8], h64: bool, be: bool) -> String {
    let mut raw = header(data.len() as u64, h64, be);
    raw.extend_from_slice(data);
    B64.encode(raw)
}

/// Base64 of header, then base64 of data (separately padded).
fn b64_split(data: &[u8], h64: bool, be: bool) -> String {
    B64.encode(header(data.len() as u64, h64, be)) + &B64.encode(data)
}

fn zlib(data: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(data).unwrap();
    e.finish().unwrap()
}

/// VTK zlib layout, blocks of `block` bytes: base64(header) + base64(compressed blocks).
fn b64_zlib(data: &[u8], block: usize, h64: bool, be: bool) -> String {
    let chunks: Vec<&[u8]> = data.chunks(block).collect();
    let compressed: Vec<Vec<u8>> = chunks.iter().map(|c| zlib(c)).collect();
    let last = chunks
        .last()
        .map_or(0, |c| if c.len() == block { 0 } else { c.len() });
    let mut hdr = header(chunks.len() as u64, h64, be);
    hdr.extend(header(block as u64, h64, be));
    hdr.extend(header(last as u64, h64, be));
    for c in &compressed {
        hdr.extend(header(c.len() as u64, h64, be));
    }
    B64.encode(hdr) + &B64.encode(compressed.concat())
}

fn vtu_inline(attrs: &str, enc: &dyn Fn(&[u8]) -> String, a: &TetArrays) -> String {
    format!(
        r#"<?xml version="1.0"?>
<VTKFile type="UnstructuredGrid" version="1.0" {attrs}>
<UnstructuredGrid><Piece NumberOfPoints="4" NumberOfCells="1">
<PointData><DataArray type="Float32" Name="displacement" NumberOfComponents="3" format="binary">
  {}
</DataArray></PointData>
<Points><DataArray type="Float32" NumberOfComponents="3" format="binary">{}</DataArray></Points>
<Cells>
<DataArray type="Int32" Name="connectivity" format="binary">{}</DataArray>
<DataArray type="Int32" Name="offsets" format="binary">{}</DataArray>
<DataArray type="UInt8" Name="types" format="binary">{}</DataArray>
</Cells></Piece></UnstructuredGrid></VTKFile>
"#,
        enc(&a.disp),
        enc(&a.points),
        enc(&a.conn),
        enc(&a.offsets),
        enc(&a.types)
    )
}

fn check_tet(m: &MeshFile) {
    assert_eq!(
        m.nodes,
        vec![[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]]
    );
    assert_eq!(m.tets, vec![[0, 1, 2, 3]]);
    assert_eq!(m.point_array("displacement").unwrap().values, vec![0.5; 12]);
}

#[test]
fn vtu_binary_variants() {
    for be in [false, true] {
        let a = tet_arrays(be);
        let order = if be { "BigEndian" } else { "LittleEndian" };
        for h64 in [false, true] {
            let ht = if h64 { "UInt64" } else { "UInt32" };
            let attrs = format!(r#"byte_order="{order}" header_type="{ht}""#);
            let joined = vtu_inline(&attrs, &|d| b64_joined(d, h64, be), &a);
            check_tet(&read_ok(joined.as_bytes(), Format::Vtu));
            let split = vtu_inline(&attrs, &|d| b64_split(d, h64, be), &a);
            check_tet(&read_ok(split.as_bytes(), Format::Vtu));
            let z_attrs = format!(r#"{attrs} compressor="vtkZLibDataCompressor""#);
            for block in [5, 16, 1 << 15] {
                let z = vtu_inline(&z_attrs, &|d| b64_zlib(d, block, h64, be), &a);
                check_tet(&read_ok(z.as_bytes(), Format::Vtu));
            }
        }
    }
    // header_type defaults to UInt32.
    let a = tet_arrays(false);
    let plain = vtu_inline(
        r#"byte_order="LittleEndian""#,
        &|d| b64_joined(d, false, false),
        &a,
    );
    check_tet(&read_ok(plain.as_bytes(), Format::Vtu));
}

/// A one-tet vtu with all arrays in an AppendedData section.
fn vtu_appended(base64: bool, compressed: bool) -> Vec<u8> {
    let a = tet_arrays(false);
    let arrays = [&a.disp, &a.points, &a.conn, &a.offsets, &a.types];
    let mut blocks: Vec<Vec<u8>> = Vec::new();
    for d in arrays {
        let block = if compressed {
            let c = zlib(d);
            let mut h = Vec::new();
            for v in [1u64, d.len() as u64, d.len() as u64, c.len() as u64] {
                h.extend(v.to_le_bytes());
            }
            if base64 {
                (B64.encode(h) + &B64.encode(c)).into_bytes()
            } else {
                [h, c].concat()
            }
        } else if base64 {
            b64_joined(d, true, false).into_bytes()
        } else {
            [(d.len() as u64).to_le_bytes().to_vec(), d.to_vec()].concat()
        };
        blocks.push(block);
    }
    let mut offsets = Vec::new();
    let mut at = 0;
    for b in &blocks {
        offsets.push(at);
        at += b.len();
    }
    let comp = if compressed {
        r#" compressor="vtkZLibDataCompressor""#
    } else {
        ""
    };
    let enc = if base64 { "base64" } else { "raw" };
    let mut out = format!(
        r#"<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" header_type="UInt64"{comp}>
<UnstructuredGrid><Piece NumberOfPoints="4" NumberOfCells="1">
<PointData><DataArray type="Float32" Name="displacement" NumberOfComponents="3" format="appended" offset="{}"/></PointData>
<Points><DataArray type="Float32" NumberOfComponents="3" format="appended" offset="{}"/></Points>
<Cells>
<DataArray type="Int32" Name="connectivity" format="appended" offset="{}"/>
<DataArray type="Int32" Name="offsets" format="appended" offset="{}"/>
<DataArray type="UInt8" Name="types" format="appended" offset="{}"/>
</Cells></Piece></UnstructuredGrid>
<AppendedData encoding="{enc}">
   _"#,
        offsets[0], offsets[1], offsets[2], offsets[3], offsets[4]
    )
    .into_bytes();
    out.extend(blocks.concat());
    out.extend_from_slice(b"\n</AppendedData>\n</VTKFile>\n");
    out
}

#[test]
fn vtu_appended_raw_and_base64() {
    for base64 in [false, true] {
        for compressed in [false, true] {
            check_tet(&read_ok(&vtu_appended(base64, compressed), Format::Vtu));
        }
    }
}

const VTP_SAMPLE: &str = r#"<VTKFile type="PolyData" version="0.1" byte_order="LittleEndian">
<PolyData>
<Piece NumberOfPoints="5" NumberOfVerts="1" NumberOfLines="1" NumberOfStrips="1" NumberOfPolys="2">
<CellData><DataArray type="Float64" Name="c" format="ascii">1 2 3 4 5</DataArray></CellData>
<Points><DataArray type="Float32" NumberOfComponents="3" format="ascii">0 0 0 1 0 0 1 1 0 0 1 0 2 2 2</DataArray></Points>
<Verts><DataArray type="Int32" Name="connectivity" format="ascii">4</DataArray>
<DataArray type="Int32" Name="offsets" format="ascii">1</DataArray></Verts>
<Lines><DataArray type="Int32" Name="connectivity" format="ascii">0 4</DataArray>
<DataArray type="Int32" Name="offsets" format="ascii">2</DataArray></Lines>
<Polys><DataArray type="Int32" Name="connectivity" format="ascii">0 1 2 3  1 2 4</DataArray>
<DataArray type="Int32" Name="offsets" format="ascii">4 7</DataArray></Polys>
<Strips><DataArray type="Int32" Name="connectivity" format="ascii">0 1 3 2</DataArray>
<DataArray type="Int32" Name="offsets" format="ascii">4</DataArray></Strips>
</Piece></PolyData></VTKFile>"#;

#[test]
fn vtp_sample_polys_strips_verts_lines() {
    let m = read_ok(VTP_SAMPLE.as_bytes(), Format::Vtp);
    assert_eq!(m.nodes.len(), 5);
    assert_eq!(
        m.triangles,
        vec![[0, 1, 2], [0, 2, 3], [1, 2, 4], [0, 1, 3], [3, 1, 2]]
    );
    assert_eq!(m.skipped_cells, 2);
    // Cell order is verts, lines, polys, strips: the polygons have values 3 and 4, the strip 5.
    assert_eq!(m.cell_data[0].values, vec![3.0, 3.0, 4.0, 5.0, 5.0]);
}

// ---------------------------------------------------------------------------------------------
// Legacy VTK samples

const VTK_ASCII_UG: &str = "# vtk DataFile Version 3.0
a tet, a triangle and a vertex
ASCII
DATASET UNSTRUCTURED_GRID
FIELD FieldData 1
TIME 1 1 double
0.5
POINTS 5 float
0 0 0 1 0 0 0 1 0
0 0 1 1 1 1
CELLS 3 11
4 0 1 2 3
3 1 2 4
1 4
CELL_TYPES 3
10
5
1
POINT_DATA 5
SCALARS temperature float
LOOKUP_TABLE default
1 2 3 4 5
VECTORS displacement double
1 0 0 0 1 0 0 0 1 1 1 1 0 0 0
CELL_DATA 3
SCALARS region%20id int 2
LOOKUP_TABLE default
7 8 9 10 11 12
FIELD FieldData 1
pressure 1 3 float
0.1 0.2 0.3
";

#[test]
fn vtk_legacy_ascii_unstructured_grid() {
    let m = read_ok(VTK_ASCII_UG.as_bytes(), Format::VtkLegacy);
    assert_eq!(m.nodes.len(), 5);
    assert_eq!(m.tets, vec![[0, 1, 2, 3]]);
    assert_eq!(m.triangles, vec![[1, 2, 4]]);
    assert_eq!(m.skipped_cells, 1);
    assert_eq!(
        m.point_array("temperature").unwrap().values,
        vec![1., 2., 3., 4., 5.]
    );
    assert_eq!(m.point_array("displacement").unwrap().components, 3);
    assert_eq!(
        m.cell_data[0],
        DataArray::new("region id", 2, vec![7.0, 8.0])
    );
    assert_eq!(
        m.cell_data[1].values,
        vec![0.1],
        "ASCII keeps the written value"
    );
}

const VTK_51: &str = "# vtk DataFile Version 5.1
vtk output
ASCII
DATASET UNSTRUCTURED_GRID
POINTS 5 double
0 0 0 1 0 0 0 1 0 0 0 1 1 1 1

METADATA
INFORMATION 0

CELLS 3 8
OFFSETS vtktypeint64
0 4 8
CONNECTIVITY vtktypeint64
0 1 2 3 1 2 3 4
CELL_TYPES 2
10
10

CELL_DATA 2
FIELD FieldData 1
region 1 2 int
1 2
METADATA
INFORMATION 1
NAME L2_NORM_RANGE LOCATION vtkDataArray
DATA 2 1 2

POINT_DATA 5
NORMALS n float
0 0 1 0 0 1 0 0 1 0 0 1 0 0 1
";

#[test]
fn vtk_legacy_51_offsets_connectivity() {
    let m = read_ok(VTK_51.as_bytes(), Format::VtkLegacy);
    assert_eq!(m.tets, vec![[0, 1, 2, 3], [1, 2, 3, 4]]);
    assert_eq!(m.cell_data[0].values, vec![1.0, 2.0]);
    assert_eq!(m.point_data[0].name, "n");
}

/// A binary POLYDATA: two polygons (a triangle and a quad), a strip, a line, with scalars.
fn vtk_binary_polydata() -> Vec<u8> {
    let mut b =
        b"# vtk DataFile Version 3.0\nvtk output\nBINARY\nDATASET POLYDATA\nPOINTS 5 float\n"
            .to_vec();
    for x in [
        0f32, 0., 0., 1., 0., 0., 1., 1., 0., 0., 1., 0., 10., 32., 13.,
    ] {
        b.extend(x.to_be_bytes());
    }
    b.extend(b"\nPOLYGONS 2 9\n");
    for v in [3i32, 0, 1, 2, 4, 0, 1, 2, 3] {
        b.extend(v.to_be_bytes());
    }
    b.extend(b"\nLINES 1 3\n");
    for v in [2i32, 0, 4] {
        b.extend(v.to_be_bytes());
    }
    b.extend(b"\nTRIANGLE_STRIPS 1 5\n");
    for v in [4i32, 0, 1, 3, 2] {
        b.extend(v.to_be_bytes());
    }
    b.extend(b"\nPOINT_DATA 5\nSCALARS s double 1\nLOOKUP_TABLE default\n");
    for x in [1f64, 2., 3., 4., 5.] {
        b.extend(x.to_be_bytes());
    }
    b.extend(b"\nCELL_DATA 4\nSCALARS c unsigned_char\nLOOKUP_TABLE default\n");
    b.extend([10u8, 32, 13, 9]);
    b.push(b'\n');
    b
}

#[test]
fn vtk_legacy_binary_polydata() {
    let m = read_ok(&vtk_binary_polydata(), Format::VtkLegacy);
    assert_eq!(m.nodes.len(), 5);
    assert_eq!(
        m.nodes[4],
        [10.0, 32.0, 13.0],
        "binary data may hold whitespace bytes"
    );
    assert_eq!(
        m.triangles,
        vec![[0, 1, 2], [0, 1, 2], [0, 2, 3], [0, 1, 3], [3, 1, 2]]
    );
    assert_eq!(m.skipped_cells, 1);
    assert_eq!(m.point_data[0].values, vec![1., 2., 3., 4., 5.]);
    // Cell order: lines (10), polygons (32, 13), strips (9).
    assert_eq!(m.cell_data[0].values, vec![32., 13., 13., 9., 9.]);
}

// ---------------------------------------------------------------------------------------------
// Gmsh samples

const MSH_V1: &str = "$NOD
5
10 0 0 0
20 1 0 0
30 0 1 0
40 0 0 1
55 1 1 1
$ENDNOD
$ELM
4
1 4 1 1 4 10 20 30 40
2 4 1 1 4 20 30 40 55
3 2 2 2 3 20 30 55
4 1 3 3 2 10 55
$ENDELM
";

#[test]
fn msh_v1_sample() {
    let m = read_ok(MSH_V1.as_bytes(), Format::Msh);
    assert_eq!(m.nodes.len(), 5);
    assert_eq!(m.tets, vec![[0, 1, 2, 3], [1, 2, 3, 4]]);
    assert_eq!(m.triangles, vec![[1, 2, 4]]);
    assert_eq!(m.skipped_cells, 1);
}

const MSH_V22: &str = "$MeshFormat
2.2 0 8
$EndMeshFormat
$PhysicalNames
1
3 1 \"liver\"
$EndPhysicalNames
$Nodes
5
3 0 0 0
1 1 0 0
7 0 1 0
2 0 0 1
9 1 1 1
$EndNodes
$Elements
5
1 15 2 0 1 3
2 4 2 1 1 3 1 7 2
3 11 2 1 1 1 7 2 9 3 3 3 3 3 3
4 3 2 0 5 3 1 9 7
5 1 2 0 1 3 9
$EndElements
$NodeData
1
\"pressure\"
1
0.0
3
0
1
5
1 10
2 20
3 30
7 70
9 90
$EndNodeData
";

#[test]
fn msh_v22_sample() {
    let m = read_ok(MSH_V22.as_bytes(), Format::Msh);
    assert_eq!(m.nodes[0], [0.0, 0.0, 0.0]);
    // Node ids 3 1 7 2 9 map to indices 0..5 in file order.
    assert_eq!(
        m.tets,
        vec![[0, 1, 2, 3], [1, 2, 3, 4]],
        "tet10 keeps its corners"
    );
    assert_eq!(m.triangles, vec![[0, 1, 4], [0, 4, 2]], "the quad is split");
    assert_eq!(m.skipped_cells, 2);
    assert_eq!(
        m.point_data,
        vec![DataArray::new("pressure", 1, vec![30., 10., 70., 20., 90.])]
    );
}

const MSH_V41: &str = "$MeshFormat
4.1 0 8
$EndMeshFormat
$Entities
1 0 0 1
1 0 0 0
2 0 0 0 1 1 1 0
$EndEntities
$Nodes
2 5 100 504
0 1 0 1
100
0 0 0
3 1 0 4
500
501
502
504
1 0 0
0 1 0
0 0 1
1 1 1
$EndNodes
$Elements
3 4 1 4
0 1 15 1
1 100
2 1 2 1
2 500 501 504
3 1 4 2
3 100 500 501 502
4 500 501 502 504
$EndElements
";

#[test]
fn msh_v41_sample_with_noncontiguous_ids() {
    let m = read_ok(MSH_V41.as_bytes(), Format::Msh);
    assert_eq!(m.nodes.len(), 5);
    assert_eq!(m.nodes[4], [1.0, 1.0, 1.0]);
    assert_eq!(m.tets, vec![[0, 1, 2, 3], [1, 2, 3, 4]]);
    assert_eq!(m.triangles, vec![[1, 2, 4]]);
    assert_eq!(m.skipped_cells, 1);
}

// ---------------------------------------------------------------------------------------------
// OBJ and STL samples

const OBJ_SAMPLE: &str = "# a quad and triangles
mtllib x.mtl
o thing
v 0 0 0
v 1 0 0 1.0
v 1 1 0 0.5 0.5 0.5
v 0 1 0
vn 0 0 1
vt 0 0
g group
s off
usemtl red
f 1//1 2//1 3//1 4//1
f -4/1 -2/1 -1/1
f 2/1/1 3/1/1 4/1/1
l 1 2
unknown statement here
";

#[test]
fn obj_sample() {
    let m = read_ok(OBJ_SAMPLE.as_bytes(), Format::Obj);
    assert_eq!(m.nodes.len(), 4);
    assert_eq!(
        m.triangles,
        vec![[0, 1, 2], [0, 2, 3], [0, 2, 3], [1, 2, 3]]
    );
    assert_eq!(m.skipped_cells, 1);
}

const STL_ASCII: &str = "solid cube corner
  facet normal 0 0 -1
    outer loop
      vertex 0 0 0
      vertex 0 1 0
      vertex 1 0 0
    endloop
  endfacet
  facet normal 0 -1 0
    outer loop
      vertex 0 0 0
      vertex 1 0 0
      vertex 0 0 1
    endloop
  endfacet
endsolid cube corner
";

#[test]
fn stl_ascii_sample_welds() {
    let m = read_ok(STL_ASCII.as_bytes(), Format::Stl);
    assert_eq!(m.nodes.len(), 4);
    assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
}

fn stl_binary(header: &[u8]) -> Vec<u8> {
    let mut b = header.to_vec();
    b.resize(80, b' ');
    b.extend(2u32.to_le_bytes());
    let tris = [
        [[0f32, 0., 0.], [0., 1., 0.], [1., 0., 0.]],
        [[0., 0., 0.], [1., 0., 0.], [-0., 0., 1.]],
    ];
    for t in tris {
        b.extend([0u8; 12]);
        for p in t {
            for x in p {
                b.extend(x.to_le_bytes());
            }
        }
        b.extend([0u8; 2]);
    }
    b
}

#[test]
fn stl_binary_sample_even_when_it_starts_with_solid() {
    for header in [&b"binary stl"[..], b"solid written by some exporter"] {
        let m = read_ok(&stl_binary(header), Format::Stl);
        assert_eq!(m.nodes.len(), 4);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }
}

// ---------------------------------------------------------------------------------------------
// Errors: every reader names the line or offset and says what was expected

#[test]
fn obj_errors() {
    let e = read_err(b"# x\nv 1 2 3\nv 1 2\n", Format::Obj);
    assert!(
        e.contains(":3:") && e.contains("expected 3 coordinates after 'v', found 2"),
        "{e}"
    );
    let e = read_err(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", Format::Obj);
    assert!(e.contains(":4:") && e.contains("found 'x'"), "{e}");
    let e = read_err(b"v 0 0 0\nf 1 -3 1\n", Format::Obj);
    assert!(
        e.contains(":2:") && e.contains("relative vertex index -3"),
        "{e}"
    );
    let e = read_err(b"v 0 0 0\nv 1 0 0\nf 1 2 9\n", Format::Obj);
    assert!(e.contains(":3:") && e.contains("vertex 9"), "{e}");
    let e = read_err(b"v 0 0 0\nf 1 1\n", Format::Obj);
    assert!(
        e.contains(":2:") && e.contains("at least 3 vertices"),
        "{e}"
    );
}

#[test]
fn msh_errors() {
    let truncated: String = MSH_V1.lines().take(5).map(|l| format!("{l}\n")).collect();
    let e = read_err(truncated.as_bytes(), Format::Msh);
    assert!(
        e.contains("file ended while reading node 4 of 5 in $NOD section"),
        "{e}"
    );
    let bad_id = MSH_V1.replace("3 2 2 2 3 20 30 55", "3 2 2 2 3 20 30 56");
    let e = read_err(bad_id.as_bytes(), Format::Msh);
    assert!(e.contains(":13:") && e.contains("node 56"), "{e}");
    let e = read_err(
        MSH_V1.replace("40 0 0 1", "40 0 zero 1").as_bytes(),
        Format::Msh,
    );
    assert!(e.contains(":6:") && e.contains("found 'zero'"), "{e}");
    let e = read_err(b"$MeshFormat\n2.2 1 8\n$EndMeshFormat\n", Format::Msh);
    assert!(e.contains(":2:") && e.contains("binary .msh"), "{e}");
    let e = read_err(
        MSH_V41
            .replace("3 100 500 501 502", "3 100 500 501")
            .as_bytes(),
        Format::Msh,
    );
    assert!(
        e.contains(":31:") && e.contains("has 3 nodes, expected 4"),
        "{e}"
    );
    let e = read_err(
        MSH_V22.replace("$EndNodes", "$EndNode").as_bytes(),
        Format::Msh,
    );
    assert!(
        e.contains(":15:") && e.contains("expected $EndNodes"),
        "{e}"
    );
}

#[test]
fn vtk_legacy_errors() {
    let cut = &VTK_ASCII_UG[..VTK_ASCII_UG.find("0 0 1 1 1 1").unwrap()];
    let e = read_err(cut.as_bytes(), Format::VtkLegacy);
    assert!(
        e.contains("file ended while reading POINTS") && e.contains(":9:"),
        "{e}"
    );
    let e = read_err(
        VTK_ASCII_UG.replace("4 0 1 2 3", "4 0 1 two 3").as_bytes(),
        Format::VtkLegacy,
    );
    assert!(e.contains(":12:") && e.contains("found 'two'"), "{e}");
    let e = read_err(
        b"# vtk DataFile Version 3.0\nx\nASCII\nDATASET STRUCTURED_POINTS\n",
        Format::VtkLegacy,
    );
    assert!(e.contains("STRUCTURED_POINTS"), "{e}");
    let e = read_err(b"hello\n", Format::VtkLegacy);
    assert!(e.contains(":1:") && e.contains("DataFile Version"), "{e}");
    let bin = vtk_binary_polydata();
    let e = read_err(&bin[..120], Format::VtkLegacy);
    assert!(
        e.contains("offset") && e.contains("file ended while reading"),
        "{e}"
    );
}

#[test]
fn vtk_xml_errors() {
    let e = read_err(
        VTU_ASCII
            .replace("0 1 2 3 4</DataArray>", "0 1 2 3</DataArray>")
            .as_bytes(),
        Format::Vtu,
    );
    assert!(
        e.contains(":7:") && e.contains("'t' has 4 tuples, expected 5"),
        "{e}"
    );
    let e = read_err(
        VTU_ASCII.replace("</Cells>", "</Cellz>").as_bytes(),
        Format::Vtu,
    );
    assert!(e.contains("malformed XML"), "{e}");
    let a = tet_arrays(false);
    let broken = vtu_inline(
        r#"byte_order="LittleEndian""#,
        &|d| b64_joined(d, false, false),
        &a,
    )
    .replacen("format=\"binary\">\n  ", "format=\"binary\">\n  !!", 1);
    let e = read_err(broken.as_bytes(), Format::Vtu);
    assert!(e.contains("displacement") && e.contains("base64"), "{e}");
    let mut raw = vtu_appended(false, false);
    raw.truncate(raw.len() - 60);
    let e = read_err(&raw, Format::Vtu);
    assert!(e.contains("offset") && e.contains("appended"), "{e}");
    let e = read_err(b"<VTKFile type=\"ImageData\"></VTKFile>", Format::Vtu);
    assert!(e.contains("ImageData"), "{e}");
}

#[test]
fn stl_errors() {
    let e = read_err(
        STL_ASCII.replace("vertex 0 1 0", "vertex 0 1").as_bytes(),
        Format::Stl,
    );
    assert!(
        e.contains(":5:") && e.contains("expected 3 coordinates after 'vertex', found 2"),
        "{e}"
    );
    let cut = &STL_ASCII[..STL_ASCII.find("endsolid").unwrap()];
    let e = read_err(cut.as_bytes(), Format::Stl);
    assert!(e.contains("file ended early"), "{e}");
    let b = stl_binary(b"bin");
    let e = read_err(&b[..150], Format::Stl);
    assert!(
        e.contains("offset 150") && e.contains("facet 2 of 2"),
        "{e}"
    );
    let e = read_err(&b[..40], Format::Stl);
    assert!(e.contains("offset 40"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Robustness: corrupted files never panic

fn samples() -> Vec<(Format, Vec<u8>)> {
    let m = two_tets();
    let s = surface();
    vec![
        (Format::Vtu, VTU_ASCII.as_bytes().to_vec()),
        (Format::Vtu, write_as(&m, Format::Vtu, true)),
        (Format::Vtu, vtu_appended(false, true)),
        (Format::Vtu, vtu_appended(true, false)),
        (
            Format::Vtu,
            vtu_inline(
                r#"header_type="UInt32" compressor="vtkZLibDataCompressor""#,
                &|d| b64_zlib(d, 16, false, false),
                &tet_arrays(false),
            )
            .into_bytes(),
        ),
        (Format::Vtp, VTP_SAMPLE.as_bytes().to_vec()),
        (Format::VtkLegacy, VTK_ASCII_UG.as_bytes().to_vec()),
        (Format::VtkLegacy, VTK_51.as_bytes().to_vec()),
        (Format::VtkLegacy, vtk_binary_polydata()),
        (Format::VtkLegacy, write_as(&m, Format::VtkLegacy, true)),
        (Format::Msh, MSH_V1.as_bytes().to_vec()),
        (Format::Msh, MSH_V22.as_bytes().to_vec()),
        (Format::Msh, MSH_V41.as_bytes().to_vec()),
        (Format::Obj, OBJ_SAMPLE.as_bytes().to_vec()),
        (Format::Stl, STL_ASCII.as_bytes().to_vec()),
        (Format::Stl, write_as(&s, Format::Stl, true)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn readers_never_panic_on_truncation(which in 0usize..16, cut in 0.0f64..1.0) {
        let all = samples();
        let (format, bytes) = &all[which % all.len()];
        let n = (bytes.len() as f64 * cut) as usize;
        let _ = read_as(&bytes[..n], *format);
    }

    #[test]
    fn readers_never_panic_on_byte_flips(
        which in 0usize..16,
        flips in prop::collection::vec((0.0f64..1.0, any::<u8>()), 1..8),
    ) {
        let all = samples();
        let (format, bytes) = &all[which % all.len()];
        let mut b = bytes.clone();
        for (at, v) in flips {
            let i = ((b.len() as f64 * at) as usize).min(b.len() - 1);
            b[i] = v;
        }
        let _ = read_as(&b, *format);
        // The same corrupted bytes read as every other format must not panic either.
        for f in [Format::Vtu, Format::VtkLegacy, Format::Msh, Format::Obj, Format::Stl] {
            let _ = read_as(&b, f);
        }
    }

    #[test]
    fn readers_never_panic_on_random_bytes(b in prop::collection::vec(any::<u8>(), 0..400)) {
        for f in [Format::Vtu, Format::Vtp, Format::VtkLegacy, Format::Msh, Format::Obj, Format::Stl] {
            let _ = read_as(&b, f);
        }
    }
}

#[test]
fn huge_declared_counts_do_not_allocate_or_panic() {
    let e = read_err(b"$NOD\n18446744073709551615\n1 0 0 0\n", Format::Msh);
    assert!(e.contains("file ended while reading node 2"), "{e}");
    let e = read_err(
        b"# vtk DataFile Version 3.0\nx\nBINARY\nDATASET POLYDATA\nPOINTS 6148914691236517205 float\n",
        Format::VtkLegacy,
    );
    assert!(e.contains("file ended"), "{e}");
    let mut b = vec![b' '; 80];
    b.extend(u32::MAX.to_le_bytes());
    let e = read_err(&b, Format::Stl);
    assert!(e.contains("facet 1 of 4294967295"), "{e}");
    let z = vtu_inline(
        r#"compressor="vtkZLibDataCompressor" header_type="UInt64""#,
        &|_| {
            B64.encode(
                [
                    u64::MAX.to_le_bytes(),
                    1u64.to_le_bytes(),
                    0u64.to_le_bytes(),
                ]
                .concat(),
            )
        },
        &tet_arrays(false),
    );
    let e = read_err(z.as_bytes(), Format::Vtu);
    assert!(e.contains("blocks"), "{e}");
}

// ---------------------------------------------------------------------------------------------
// Real files

macro_rules! data {
    ($name:literal) => {
        concat!(env!("CARGO_MANIFEST_DIR"), "/assets/livers/", $name)
    };
}

#[test]
fn real_sofa_liver_msh() {
    let m = read(data!("sofa_liver.msh"), Unit::Mm).unwrap();
    assert_eq!(m.nodes.len(), 181);
    assert_eq!(m.tets.len(), 596);
    assert_eq!(m.triangles.len(), 0);
}

#[test]
fn real_sofa_liver2_msh() {
    let m = read(data!("sofa_liver2.msh"), Unit::Mm).unwrap();
    assert_eq!(m.nodes.len(), 507);
    assert_eq!(m.tets.len(), 1493);
    assert_eq!(m.triangles.len(), 860);
    assert_eq!(m.skipped_cells, 71);
}

#[test]
fn real_sofa_liver_obj() {
    let m = read(data!("sofa_liver-smooth.obj"), Unit::Mm).unwrap();
    assert_eq!(m.nodes.len(), 2194);
    assert_eq!(m.triangles.len(), 4384);
}

#[test]
fn real_sofa_liver_vtk() {
    let m = read(data!("sofa_liver.vtk"), Unit::Mm).unwrap();
    assert_eq!(m.nodes.len(), 5008);
    assert_eq!(m.triangles.len(), 10000);
    assert_eq!(m.skipped_cells, 0);
}

#[test]
fn real_files_survive_a_round_trip_through_every_format() {
    let liver = read(data!("sofa_liver2.msh"), Unit::Cm).unwrap();
    for (format, binary) in [
        (Format::Vtu, true),
        (Format::Vtu, false),
        (Format::VtkLegacy, true),
        (Format::VtkLegacy, false),
        (Format::Msh, false),
    ] {
        let back = read_ok(&write_as(&liver, format, binary), format);
        assert_eq!(back.nodes, liver.nodes, "{format:?}");
        assert_eq!(back.tets, liver.tets, "{format:?}");
    }
    let surf = read(data!("sofa_liver.vtk"), Unit::Mm).unwrap();
    for (format, binary) in [
        (Format::Vtp, true),
        (Format::Obj, false),
        (Format::Stl, false),
    ] {
        let back = read_ok(&write_as(&surf, format, binary), format);
        assert_eq!(back.triangles.len(), surf.triangles.len(), "{format:?}");
        assert_eq!(coords_of(&back), coords_of(&surf), "{format:?}");
    }
}
