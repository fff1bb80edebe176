//! Users' own files for a registration: a preoperative mesh (a tet mesh, or a closed surface that
//! is meshed here) with its anatomical labels when the file carries them, else labelled from the
//! geometry; and measured point sets (`.vtp`/`.vtk` point clouds, `.csv`, `.txt`/`.xyz`).

use crate::mesh::io::{self, MeshFile, Unit};
use crate::mesh::tetra::{TetraParams, tetrahedralize};
use crate::mesh::{TetMesh, TriSurface};
use crate::register::PreopModel;
use crate::register::anatomy::{LabelParams, label};
use crate::register::correspondence::preop_model_from_file;
use std::path::{Path, PathBuf};

/// Why a user's mesh or point file could not be used; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// The file could not be read as a mesh (its own message names the file).
    #[error(transparent)]
    Read(#[from] io::IoError),
    /// The file could not be read at all.
    #[error(transparent)]
    File(#[from] crate::util::FileError),
    /// The file was read but does not hold what is needed; the problem says what.
    #[error("{}: {problem}", path.display())]
    Content {
        /// The file.
        path: PathBuf,
        /// What is wrong and what is expected.
        problem: String,
    },
    /// A row of a point table is not `x y z`.
    #[error("line {line}: {problem}")]
    Row {
        /// 1-based line.
        line: usize,
        /// What is wrong.
        problem: String,
    },
    /// A row of the point table `path` is not `x y z`.
    #[error("{}: {source}", path.display())]
    Table {
        /// The file.
        path: PathBuf,
        /// The row's problem.
        source: Box<InputError>,
    },
    /// The mesh's labels or vessels are inconsistent, or the labeller failed.
    #[error("{}: {source}", path.display())]
    Model {
        /// The file.
        path: PathBuf,
        /// What the model builder found.
        source: crate::register::RegisterError,
    },
    /// The file's surface is not one a liver mesh can be made from.
    #[error("{}: {source}", path.display())]
    Surface {
        /// The file.
        path: PathBuf,
        /// What is wrong with the surface.
        source: crate::mesh::SurfaceError,
    },
    /// The surface could not be tetrahedralised.
    #[error("{}: {source}", path.display())]
    Tetrahedralize {
        /// The file.
        path: PathBuf,
        /// The mesher's error.
        source: crate::mesh::tetra::TetraError,
    },
    /// The file's tetrahedra do not make a valid mesh.
    #[error("{}: {source}", path.display())]
    Mesh {
        /// The file.
        path: PathBuf,
        /// The mesh check's error.
        source: crate::mesh::MeshError,
    },
    /// The tetrahedralisation edge length is not usable.
    #[error("edge length {edge_mm} mm: need a finite value > 0.5")]
    EdgeLength {
        /// The value given (mm).
        edge_mm: f64,
    },
}

/// A preoperative model from a mesh file already read (`path` for messages and to find
/// `STEM.vessels.vtp` beside it).
///
/// - A tet mesh with the point arrays `region` (0 interior, 1 anterior, 2 posterior) and, when
///   present, `falciform` and `inferior_ridge` (as a dataset's `preop.vtu`) uses them, with
///   vessel centerlines from `STEM.vessels.vtp` when that file exists.
/// - Any other tet mesh is labelled from its geometry (LPS frame assumed: anterior is −y) and has
///   no vessels.
/// - A triangle surface (OBJ, STL, a VTK surface) is tetrahedralised at `edge_mm` first (its
///   largest closed piece, oriented outwards).
pub fn preop_model_from_mesh(
    path: &Path,
    file: &MeshFile,
    unit: Unit,
    edge_mm: f64,
) -> Result<PreopModel, InputError> {
    let model = |source| InputError::Model {
        path: path.to_path_buf(),
        source,
    };
    let path_buf = || path.to_path_buf();
    if !file.tets.is_empty() && file.point_array("region").is_some() {
        let vessels_path = path.with_extension("vessels.vtp");
        let vessels = if vessels_path.is_file() {
            io::read(&vessels_path, unit)?
        } else {
            MeshFile::default()
        };
        return preop_model_from_file(file, &vessels).map_err(model);
    }
    let mut mesh = if file.tets.is_empty() {
        if file.triangles.is_empty() {
            return Err(InputError::Content {
                path: path.to_path_buf(),
                problem: "neither tetrahedra nor triangles: not a liver mesh or surface".into(),
            });
        }
        if !(edge_mm.is_finite() && edge_mm > 0.5) {
            return Err(InputError::EdgeLength { edge_mm });
        }
        let s = TriSurface::from_file(file)
            .and_then(|s| s.largest_closed_outward())
            .map_err(|source| InputError::Surface {
                path: path_buf(),
                source,
            })?;
        tetrahedralize(&s, &TetraParams::with_edge(edge_mm)).map_err(|source| {
            InputError::Tetrahedralize {
                path: path_buf(),
                source,
            }
        })?
    } else {
        TetMesh::from_file(file).map_err(|source| InputError::Mesh {
            path: path_buf(),
            source,
        })?
    };
    mesh.orient_positive();
    let labels = label(&mesh, &LabelParams::default()).map_err(model)?;
    Ok(labels.preop_model(&mesh, &[], &[]))
}

/// Reads a point set (mm after `unit`): a VTK file's points (`.vtp`, `.vtu`, `.vtk`), or a text
/// table (`.csv`: comma-separated; `.txt`, `.xyz`: whitespace- or comma-separated) whose rows are
/// `x y z` (more columns are ignored). Lines starting with `#`, blank lines and one header line of
/// non-numbers are skipped. Every coordinate must be finite; errors name the file and line.
pub fn read_points(path: &Path, unit: Unit) -> Result<Vec<[f64; 3]>, InputError> {
    let content = |problem: String| InputError::Content {
        path: path.to_path_buf(),
        problem,
    };
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    let points = match ext.as_str() {
        "vtp" | "vtu" | "vtk" => io::read(path, unit)?.nodes,
        "csv" | "txt" | "xyz" => {
            let text = std::fs::read_to_string(path)
                .map_err(crate::util::FileError::at("reading", path))?;
            parse_points(&text, unit.to_mm()).map_err(|e| InputError::Table {
                path: path.to_path_buf(),
                source: Box::new(e),
            })?
        }
        _ => {
            return Err(content(
                "unknown point file type (use .vtp, .vtk, .csv, .txt or .xyz)".into(),
            ));
        }
    };
    if points.is_empty() {
        return Err(content("no points".into()));
    }
    if let Some(i) = points.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
        return Err(content(format!("point {i} is not finite")));
    }
    Ok(points)
}

/// Parses `x y z` rows (see [`read_points`]), scaling by `factor`.
pub fn parse_points(text: &str, factor: f64) -> Result<Vec<[f64; 3]>, InputError> {
    let mut out = Vec::new();
    let mut header_seen = false;
    for (k, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line
            .split(|c: char| c == ',' || c == ';' || c.is_whitespace())
            .filter(|f| !f.is_empty())
            .collect();
        let nums: Vec<Option<f64>> = fields.iter().map(|f| f.parse::<f64>().ok()).collect();
        if out.is_empty() && !header_seen && nums.iter().all(|x| x.is_none()) {
            header_seen = true;
            continue;
        }
        if fields.len() < 3 {
            return Err(InputError::Row {
                line: k + 1,
                problem: format!("{} values, need x y z", fields.len()),
            });
        }
        let mut p = [0.0; 3];
        for a in 0..3 {
            p[a] = nums[a].ok_or_else(|| InputError::Row {
                line: k + 1,
                problem: format!("{:?} is not a number", fields[a]),
            })? * factor;
        }
        if !p.iter().all(|x| x.is_finite()) {
            return Err(InputError::Row {
                line: k + 1,
                problem: "not finite".into(),
            });
        }
        out.push(p);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_points_parse_with_header_comments_and_units() {
        let t = "# exported\nx,y,z\n1,2,3\n\n4.5, -6 ,7e1\n";
        assert_eq!(
            parse_points(t, 10.0).unwrap(),
            vec![[10.0, 20.0, 30.0], [45.0, -60.0, 700.0]]
        );
        assert_eq!(
            parse_points("1 2 3 0.9\n4\t5\t6\n", 1.0).unwrap(),
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
        );
        let e = parse_points("1,2,3\n1,2\n", 1.0).unwrap_err().to_string();
        assert!(e.contains("line 2"), "{e}");
        let e = parse_points("1,2,3\n1,x,3\n", 1.0).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("\"x\""), "{e}");
        let e = parse_points("1,2,nan\n", 1.0).unwrap_err().to_string();
        assert!(e.contains("not finite"), "{e}");
    }
}
