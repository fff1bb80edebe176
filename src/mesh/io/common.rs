//! Helpers shared by the format readers and writers: binary value types, number formatting, the
//! conversion of VTK-style cells into tetrahedra and triangles, and error constructors.

use super::{DataArray, IoError, MeshFile};
use std::fmt::Write as _;
use std::path::Path;

/// What is wrong with a token, a cell or a mesh about to be written, before the reader or writer
/// adds the file and the line or byte offset (it becomes an [`IoError`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub(crate) struct Malformed(pub(crate) String);

impl From<String> for Malformed {
    fn from(m: String) -> Self {
        Self(m)
    }
}

impl From<&str> for Malformed {
    fn from(m: &str) -> Self {
        Self(m.to_string())
    }
}

impl From<Malformed> for String {
    fn from(m: Malformed) -> Self {
        m.0
    }
}

/// Builds an [`IoError::Line`].
pub(super) fn line_err(path: &Path, line: usize, message: impl Into<String>) -> IoError {
    IoError::Line {
        path: path.to_path_buf(),
        line,
        message: message.into(),
    }
}

/// Builds an [`IoError::Offset`].
pub(super) fn offset_err(path: &Path, offset: usize, message: impl Into<String>) -> IoError {
    IoError::Offset {
        path: path.to_path_buf(),
        offset: offset as u64,
        message: message.into(),
    }
}

/// Builds an [`IoError::Content`].
pub(super) fn content_err(path: &Path, message: impl Into<String>) -> IoError {
    IoError::Content {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Shortens a found token for an error message.
pub(super) fn shown(token: &str) -> String {
    let mut s: String = token.chars().take(40).collect();
    if s.len() < token.len() {
        s.push('…');
    }
    s
}

/// Capacity to reserve for `n` items when at most `limit` could follow in the input.
pub(super) fn capped(n: usize, limit: usize) -> usize {
    n.min(limit).min(1 << 20)
}

/// Appends a float in its shortest round-trip form (exponent notation for extreme magnitudes).
pub(super) fn push_f64(out: &mut String, x: f64) {
    let a = x.abs();
    // Writing to a String cannot fail.
    let _ = if a == 0.0 || !a.is_finite() || (1e-5..1e16).contains(&a) {
        write!(out, "{x}")
    } else {
        write!(out, "{x:e}")
    };
}

/// Parses a float token (`1`, `-2.5e3`, ...).
pub(super) fn parse_f64(token: &str) -> Option<f64> {
    token.parse::<f64>().ok()
}

/// Converts a value read from a file into a node index, if it is a non-negative integer that fits.
pub(super) fn to_index(v: f64) -> Option<u32> {
    if v >= 0.0 && v < u32::MAX as f64 && v.fract() == 0.0 {
        Some(v as u32)
    } else {
        None
    }
}

/// Numeric value types of binary data (VTK XML and legacy VTK).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum DType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

/// Copies a slice of exactly `N` bytes into an array (callers pass `chunks_exact(N)` items).
fn arr<const N: usize>(c: &[u8]) -> [u8; N] {
    let mut a = [0u8; N];
    a.copy_from_slice(&c[..N]);
    a
}

macro_rules! decode_as {
    ($bytes:expr, $be:expr, $out:expr, $t:ty, $n:literal) => {
        for c in $bytes.chunks_exact($n) {
            let a = arr::<$n>(c);
            let v = if $be {
                <$t>::from_be_bytes(a)
            } else {
                <$t>::from_le_bytes(a)
            };
            $out.push(v as f64);
        }
    };
}

impl DType {
    /// Type from a VTK XML `type` attribute (`Float32`, `Int64`, ...).
    pub(super) fn from_xml(name: &str) -> Option<Self> {
        Some(match name {
            "Int8" | "Char" => DType::I8,
            "UInt8" | "UChar" => DType::U8,
            "Int16" => DType::I16,
            "UInt16" => DType::U16,
            "Int32" => DType::I32,
            "UInt32" => DType::U32,
            "Int64" => DType::I64,
            "UInt64" => DType::U64,
            "Float32" => DType::F32,
            "Float64" => DType::F64,
            _ => return None,
        })
    }

    /// Type from a legacy VTK type word (`float`, `unsigned_int`, `vtktypeint64`, ...).
    pub(super) fn from_legacy(name: &str) -> Option<Self> {
        Some(match name.to_ascii_lowercase().as_str() {
            "char" | "signed_char" | "vtktypeint8" => DType::I8,
            "unsigned_char" | "vtktypeuint8" => DType::U8,
            "short" | "vtktypeint16" => DType::I16,
            "unsigned_short" | "vtktypeuint16" => DType::U16,
            "int" | "vtkidtype" | "vtktypeint32" => DType::I32,
            "unsigned_int" | "vtktypeuint32" => DType::U32,
            "long" | "long_long" | "vtktypeint64" => DType::I64,
            "unsigned_long" | "unsigned_long_long" | "vtktypeuint64" => DType::U64,
            "float" | "vtktypefloat32" => DType::F32,
            "double" | "vtktypefloat64" => DType::F64,
            _ => return None,
        })
    }

    /// Size of one value in bytes.
    pub(super) fn size(self) -> usize {
        match self {
            DType::I8 | DType::U8 => 1,
            DType::I16 | DType::U16 => 2,
            DType::I32 | DType::U32 | DType::F32 => 4,
            DType::I64 | DType::U64 | DType::F64 => 8,
        }
    }

    /// Decodes whole values from `bytes` (a trailing partial value is ignored) and appends them.
    pub(super) fn decode(self, bytes: &[u8], big_endian: bool, out: &mut Vec<f64>) {
        out.reserve(bytes.len() / self.size());
        match self {
            DType::I8 => out.extend(bytes.iter().map(|&b| b as i8 as f64)),
            DType::U8 => out.extend(bytes.iter().map(|&b| b as f64)),
            DType::I16 => decode_as!(bytes, big_endian, out, i16, 2),
            DType::U16 => decode_as!(bytes, big_endian, out, u16, 2),
            DType::I32 => decode_as!(bytes, big_endian, out, i32, 4),
            DType::U32 => decode_as!(bytes, big_endian, out, u32, 4),
            DType::I64 => decode_as!(bytes, big_endian, out, i64, 8),
            DType::U64 => decode_as!(bytes, big_endian, out, u64, 8),
            DType::F32 => decode_as!(bytes, big_endian, out, f32, 4),
            DType::F64 => decode_as!(bytes, big_endian, out, f64, 8),
        }
    }
}

/// Collects VTK-style cells into tetrahedra and triangles, remembering which source cell each
/// output cell came from so that cell data can follow the kept cells.
#[derive(Debug, Default)]
pub(super) struct CellCollector {
    tets: Vec<[u32; 4]>,
    tet_src: Vec<usize>,
    tris: Vec<[u32; 3]>,
    tri_src: Vec<usize>,
    skipped: usize,
}

/// Name of a VTK cell type for error messages.
fn vtk_type_name(t: u8) -> &'static str {
    match t {
        1 => "vertex",
        3 => "line",
        5 => "triangle",
        8 => "pixel",
        9 => "quad",
        10 => "tetra",
        22 => "quadratic triangle",
        23 => "quadratic quad",
        24 => "quadratic tetra",
        28 => "biquadratic quad",
        _ => "cell",
    }
}

impl CellCollector {
    /// Counts a cell of a kind that is not kept.
    pub(super) fn skip(&mut self) {
        self.skipped += 1;
    }

    fn tri(&mut self, t: [u32; 3], src: usize) {
        self.tris.push(t);
        self.tri_src.push(src);
    }

    /// Adds a VTK cell by type id; types other than triangles, quads and tetrahedra are counted as
    /// skipped. Errors say what node count the type needs.
    pub(super) fn add_vtk(&mut self, vtk_type: u8, n: &[u32], src: usize) -> Result<(), Malformed> {
        let need = match vtk_type {
            5 => 3,
            8..=10 => 4,
            22 => 6,
            23 => 8,
            24 => 10,
            28 => 9,
            6 | 7 => {
                if vtk_type == 6 {
                    self.add_strip(n, src);
                } else {
                    self.add_polygon(n, src);
                }
                return Ok(());
            }
            _ => {
                self.skipped += 1;
                return Ok(());
            }
        };
        if n.len() != need {
            return Err(Malformed(format!(
                "cell {src} of type {vtk_type} ({}) has {} nodes, expected {need}",
                vtk_type_name(vtk_type),
                n.len()
            )));
        }
        match vtk_type {
            5 | 22 => self.tri([n[0], n[1], n[2]], src),
            8 => self.add_polygon(&[n[0], n[1], n[3], n[2]], src),
            9 | 23 | 28 => self.add_polygon(&n[..4], src),
            _ => {
                self.tets.push([n[0], n[1], n[2], n[3]]);
                self.tet_src.push(src);
            }
        }
        Ok(())
    }

    /// Adds a polygon, fan-triangulated; fewer than 3 nodes count as a skipped cell.
    pub(super) fn add_polygon(&mut self, n: &[u32], src: usize) {
        if n.len() < 3 {
            self.skipped += 1;
            return;
        }
        for w in n[1..].windows(2) {
            self.tri([n[0], w[0], w[1]], src);
        }
    }

    /// Adds a triangle strip, keeping a consistent orientation; fewer than 3 nodes are skipped.
    pub(super) fn add_strip(&mut self, n: &[u32], src: usize) {
        if n.len() < 3 {
            self.skipped += 1;
            return;
        }
        for (i, w) in n.windows(3).enumerate() {
            if i % 2 == 0 {
                self.tri([w[0], w[1], w[2]], src);
            } else {
                self.tri([w[1], w[0], w[2]], src);
            }
        }
    }

    /// Builds the mesh. `cell_data` arrays hold one tuple per source cell; the tuples of the kept
    /// cells (tetrahedra if any, else triangles) are gathered in order.
    pub(super) fn finish(
        self,
        nodes: Vec<[f64; 3]>,
        point_data: Vec<DataArray>,
        cell_data: Vec<DataArray>,
    ) -> MeshFile {
        let src = if self.tets.is_empty() {
            &self.tri_src
        } else {
            &self.tet_src
        };
        let cell_data = cell_data
            .into_iter()
            .filter_map(|a| gather(&a, src).map(|v| DataArray::new(a.name, a.components, v)))
            .collect();
        MeshFile {
            nodes,
            tets: self.tets,
            triangles: self.tris,
            point_data,
            cell_data,
            skipped_cells: self.skipped,
        }
    }
}

/// The tuples of `a` at the given indices, or `None` if an index is out of range.
pub(super) fn gather(a: &DataArray, idx: &[usize]) -> Option<Vec<f64>> {
    let c = a.components;
    let mut out = Vec::with_capacity(idx.len() * c);
    for &i in idx {
        out.extend_from_slice(a.values.get(i * c..(i + 1) * c)?);
    }
    Some(out)
}

/// Splits a concatenation of ends-offsets and connectivity into cells, checking the offsets.
pub(super) fn split_cells<'a>(
    offsets: &[f64],
    conn: &'a [u32],
) -> Result<Vec<&'a [u32]>, Malformed> {
    let mut cells = Vec::with_capacity(offsets.len());
    let mut start = 0usize;
    for (i, &o) in offsets.iter().enumerate() {
        let end = to_index(o)
            .map(|e| e as usize)
            .filter(|&e| e >= start && e <= conn.len())
            .ok_or_else(|| {
                format!(
                    "offset {i} is {o}; expected a value between {start} and {} (the connectivity length)",
                    conn.len()
                )
            })?;
        cells.push(&conn[start..end]);
        start = end;
    }
    Ok(cells)
}

/// Converts connectivity values to node indices; the error names the first bad position.
pub(super) fn to_indices(values: &[f64], what: &str) -> Result<Vec<u32>, Malformed> {
    values
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            to_index(v).ok_or_else(|| {
                Malformed(format!(
                    "{what} value {i} is {v}; expected a non-negative integer node index"
                ))
            })
        })
        .collect()
}

/// Face normal of a triangle (unit length, or zero for a degenerate triangle).
pub(super) fn triangle_normal(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [f64; 3] {
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let n = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
    if len > 0.0 && len.is_finite() {
        [n[0] / len, n[1] / len, n[2] / len]
    } else {
        [0.0; 3]
    }
}

/// Error for surface-only formats asked to write a mesh that has only tetrahedra.
pub(super) fn surface_only(file: &MeshFile, format: &str) -> Result<(), Malformed> {
    if file.triangles.is_empty() && !file.tets.is_empty() {
        return Err(Malformed(format!(
            "{format} stores surfaces only, but the mesh has {} tetrahedra and no triangles; \
             extract the boundary surface first or write .vtu, .vtk or .msh",
            file.tets.len()
        )));
    }
    Ok(())
}
