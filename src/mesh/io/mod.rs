//! Mesh file formats: everything that touches the disk for meshes lives here.
//!
//! Readers turn a file into a [`MeshFile`] (plain data: nodes in millimetres, tetrahedra, triangles,
//! point and cell data arrays); writers take a [`MeshFile`] and write it in one place. Numerical code
//! never sees a file. Supported formats (by extension):
//!
//! | extension | read | write |
//! | --- | --- | --- |
//! | `.vtu` | VTK XML UnstructuredGrid: ascii, inline base64 (UInt32/UInt64 headers, either byte order), zlib-compressed, appended raw or base64 | ascii or base64 binary |
//! | `.vtp` | VTK XML PolyData: polys (fan-triangulated), strips, verts (point sets); same encodings | ascii or base64 binary |
//! | `.vtk` | legacy VTK 2.0–5.1 ASCII and BINARY (big-endian), UNSTRUCTURED_GRID and POLYDATA | ASCII or BINARY (4.2) |
//! | `.msh` | Gmsh v1 (`$NOD`/`$ELM`), v2.2 ASCII, v4.1 ASCII; non-contiguous node ids mapped | v2.2 ASCII |
//! | `.obj` | Wavefront OBJ (`v`, `f` with `v/vt/vn` forms, negative indices, polygons fan-triangulated) | `v`/`f` |
//! | `.stl` | ASCII and binary STL (vertices welded when bit-identical) | binary or ASCII |
//! | `.pvd` | ParaView collection (a time series of the files above): [`read_pvd`] | [`pvd_collection`] |
//!
//! Units: each reader takes the unit of the file ([`Unit`]); coordinates are scaled to millimetres
//! on read, and so are point-data arrays that hold lengths (those named `displacement`,
//! case-insensitive). Files are always written in millimetres.
//!
//! Errors name the file and the line (text formats) or byte offset (binary formats) and say what was
//! expected; no reader panics on any input.

mod common;
mod gmsh;
pub mod npz;
mod obj;
mod stl;
mod vtk_legacy;
mod vtk_xml;

pub use vtk_xml::{PvdEntry, pvd_collection, read_pvd};

use std::path::{Path, PathBuf};

/// Length unit of a file; meshes are held in millimetres.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum Unit {
    /// Millimetres (the internal unit).
    #[default]
    Mm,
    /// Centimetres.
    Cm,
    /// Metres.
    M,
}

impl Unit {
    /// Factor that converts a length in this unit to millimetres.
    pub fn to_mm(self) -> f64 {
        match self {
            Unit::Mm => 1.0,
            Unit::Cm => 10.0,
            Unit::M => 1000.0,
        }
    }
}

impl std::str::FromStr for Unit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "mm" => Ok(Unit::Mm),
            "cm" => Ok(Unit::Cm),
            "m" => Ok(Unit::M),
            other => Err(format!("unknown unit '{other}': expected mm, cm or m")),
        }
    }
}

impl std::fmt::Display for Unit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Unit::Mm => "mm",
            Unit::Cm => "cm",
            Unit::M => "m",
        })
    }
}

/// A named data array attached to points or cells: `values.len() == count * components`.
#[derive(Debug, Clone, PartialEq)]
pub struct DataArray {
    /// Array name as in the file (e.g. `displacement`).
    pub name: String,
    /// Number of components per tuple (1 scalar, 3 vector, ...).
    pub components: usize,
    /// Values, tuple-major (`[x0, y0, z0, x1, ...]`).
    pub values: Vec<f64>,
}

impl DataArray {
    /// Creates an array; `values.len()` must be a multiple of `components`.
    pub fn new(name: impl Into<String>, components: usize, values: Vec<f64>) -> Self {
        Self {
            name: name.into(),
            components,
            values,
        }
    }

    /// Number of tuples.
    pub fn len(&self) -> usize {
        self.values.len().checked_div(self.components).unwrap_or(0)
    }

    /// True when the array holds no tuple.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// True for arrays whose values are lengths and therefore scale with the unit.
    pub fn is_length(&self) -> bool {
        self.name.eq_ignore_ascii_case("displacement")
    }
}

/// Contents of a mesh file as plain data. Cells of kinds other than tetrahedra and triangles
/// (lines, vertices, quads after triangulation aside) are dropped by readers, which record how many
/// in `skipped_cells`.
///
/// Cell data arrays, when present, are tuple-per-cell over the tetrahedra if `tets` is non-empty,
/// otherwise over the triangles.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MeshFile {
    /// Node coordinates in millimetres.
    pub nodes: Vec<[f64; 3]>,
    /// Tetrahedra (0-based node indices).
    pub tets: Vec<[u32; 4]>,
    /// Triangles (0-based node indices).
    pub triangles: Vec<[u32; 3]>,
    /// Point data arrays (one tuple per node).
    pub point_data: Vec<DataArray>,
    /// Cell data arrays (one tuple per tet, or per triangle when there are no tets).
    pub cell_data: Vec<DataArray>,
    /// Number of cells of other kinds that were read and dropped (lines, points, ...).
    pub skipped_cells: usize,
}

impl MeshFile {
    /// The point-data array with this name, if any.
    pub fn point_array(&self, name: &str) -> Option<&DataArray> {
        self.point_data.iter().find(|a| a.name == name)
    }

    /// Multiplies coordinates (and length-valued point arrays) by `factor`.
    pub fn scale(&mut self, factor: f64) {
        for p in &mut self.nodes {
            for c in p.iter_mut() {
                *c *= factor;
            }
        }
        for a in &mut self.point_data {
            if a.is_length() {
                for v in &mut a.values {
                    *v *= factor;
                }
            }
        }
    }
}

/// Errors from reading or writing mesh files. Each names the file and says what was expected.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused to open, read or write the file.
    #[error("{path}: {source}")]
    Os {
        /// File path.
        path: PathBuf,
        /// Underlying error.
        source: std::io::Error,
    },
    /// A text file has a problem on a given line (1-based).
    #[error("{path}:{line}: {message}")]
    Line {
        /// File path.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What was found and what was expected.
        message: String,
    },
    /// A binary file (or binary section) has a problem at a byte offset.
    #[error("{path}: at byte offset {offset}: {message}")]
    Offset {
        /// File path.
        path: PathBuf,
        /// 0-based byte offset in the file.
        offset: u64,
        /// What was found and what was expected.
        message: String,
    },
    /// The file is readable but its content is inconsistent (e.g. a cell index out of range).
    #[error("{path}: {message}")]
    Content {
        /// File path.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The extension is not one of the supported formats.
    #[error("{path}: unsupported file extension (expected .vtu, .vtp, .vtk, .msh, .obj or .stl)")]
    UnknownFormat {
        /// File path.
        path: PathBuf,
    },
}

/// File formats known to the readers and writers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// VTK XML UnstructuredGrid.
    Vtu,
    /// VTK XML PolyData.
    Vtp,
    /// Legacy VTK.
    VtkLegacy,
    /// Gmsh.
    Msh,
    /// Wavefront OBJ.
    Obj,
    /// STL.
    Stl,
}

impl Format {
    /// Format from the file extension (case-insensitive).
    pub fn from_path(path: &Path) -> Result<Self, IoError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        match ext.as_deref() {
            Some("vtu") => Ok(Format::Vtu),
            Some("vtp") => Ok(Format::Vtp),
            Some("vtk") => Ok(Format::VtkLegacy),
            Some("msh") => Ok(Format::Msh),
            Some("obj") => Ok(Format::Obj),
            Some("stl") => Ok(Format::Stl),
            _ => Err(IoError::UnknownFormat {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// Options for writers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteOptions {
    /// Write binary (base64 for XML VTK, big-endian BINARY for legacy VTK, binary STL) instead of ASCII.
    pub binary: bool,
}

impl Default for WriteOptions {
    fn default() -> Self {
        Self { binary: true }
    }
}

/// Reads a mesh file, choosing the format by extension, and scales it from `unit` to millimetres.
pub fn read(path: impl AsRef<Path>, unit: Unit) -> Result<MeshFile, IoError> {
    let path = path.as_ref();
    let format = Format::from_path(path)?;
    let bytes = std::fs::read(path).map_err(|source| IoError::Os {
        path: path.to_path_buf(),
        source,
    })?;
    read_bytes(&bytes, format, path, unit)
}

/// Reads a mesh from bytes already in memory; `path` is only used in error messages.
pub fn read_bytes(
    bytes: &[u8],
    format: Format,
    path: &Path,
    unit: Unit,
) -> Result<MeshFile, IoError> {
    let mut file = match format {
        Format::Vtu | Format::Vtp => vtk_xml::read(bytes, path)?,
        Format::VtkLegacy => vtk_legacy::read(bytes, path)?,
        Format::Msh => gmsh::read(bytes, path)?,
        Format::Obj => obj::read(bytes, path)?,
        Format::Stl => stl::read(bytes, path)?,
    };
    check_indices(&file, path)?;
    let factor = unit.to_mm();
    if factor != 1.0 {
        file.scale(factor);
    }
    Ok(file)
}

/// Writes a mesh file in millimetres, choosing the format by extension.
pub fn write(
    path: impl AsRef<Path>,
    file: &MeshFile,
    options: WriteOptions,
) -> Result<(), IoError> {
    let path = path.as_ref();
    let format = Format::from_path(path)?;
    let bytes = write_bytes(file, format, options, path)?;
    std::fs::write(path, bytes).map_err(|source| IoError::Os {
        path: path.to_path_buf(),
        source,
    })
}

/// Serialises a mesh to bytes in the given format; `path` is only used in error messages.
pub fn write_bytes(
    file: &MeshFile,
    format: Format,
    options: WriteOptions,
    path: &Path,
) -> Result<Vec<u8>, IoError> {
    match format {
        Format::Vtu => vtk_xml::write_vtu(file, options),
        Format::Vtp => vtk_xml::write_vtp(file, options),
        Format::VtkLegacy => vtk_legacy::write(file, options),
        Format::Msh => gmsh::write(file),
        Format::Obj => obj::write(file, path),
        Format::Stl => stl::write(file, options, path),
    }
    .map_err(|m| IoError::Content {
        path: path.to_path_buf(),
        message: m.into(),
    })
}

/// Checks that every cell index refers to an existing node and data arrays have the right length.
fn check_indices(file: &MeshFile, path: &Path) -> Result<(), IoError> {
    let n = file.nodes.len();
    let bad = |kind: &str, i: usize, v: u32| IoError::Content {
        path: path.to_path_buf(),
        message: format!(
            "{kind} {i} refers to node index {v}, but the file has only {n} nodes (0-based)"
        ),
    };
    for (i, t) in file.tets.iter().enumerate() {
        if let Some(&v) = t.iter().find(|&&v| v as usize >= n) {
            return Err(bad("tetrahedron", i, v));
        }
    }
    for (i, t) in file.triangles.iter().enumerate() {
        if let Some(&v) = t.iter().find(|&&v| v as usize >= n) {
            return Err(bad("triangle", i, v));
        }
    }
    for (i, p) in file.nodes.iter().enumerate() {
        if p.iter().any(|c| !c.is_finite()) {
            return Err(IoError::Content {
                path: path.to_path_buf(),
                message: format!("node {i} has a non-finite coordinate {p:?}"),
            });
        }
    }
    let ncells = if file.tets.is_empty() {
        file.triangles.len()
    } else {
        file.tets.len()
    };
    for (arrays, count, kind) in [
        (&file.point_data, n, "point"),
        (&file.cell_data, ncells, "cell"),
    ] {
        for a in arrays {
            if a.components == 0 || a.values.len() != count * a.components {
                return Err(IoError::Content {
                    path: path.to_path_buf(),
                    message: format!(
                        "{kind} data array '{}' has {} values with {} components; expected {} tuples",
                        a.name,
                        a.values.len(),
                        a.components,
                        count
                    ),
                });
            }
        }
    }
    Ok(())
}
