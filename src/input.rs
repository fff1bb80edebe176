//! Users' own files for a registration: a preoperative mesh (a tet mesh, or a closed surface that
//! is meshed here) with its anatomical labels when the file carries them, else labelled from the
//! geometry; and measured point sets (`.vtp`/`.vtk` point clouds, `.csv`, `.txt`/`.xyz`).

use crate::mesh::io::{self, MeshFile, Unit};
use crate::mesh::tetra::{TetraParams, tetrahedralize};
use crate::mesh::{TetMesh, TriSurface};
use crate::register::PreopModel;
use crate::register::anatomy::{LabelParams, label};
use crate::register::correspondence::preop_model_from_file;
use std::path::Path;

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
) -> Result<PreopModel, String> {
    let ctx = |e: String| format!("{}: {e}", path.display());
    if !file.tets.is_empty() && file.point_array("region").is_some() {
        let vessels_path = path.with_extension("vessels.vtp");
        let vessels = if vessels_path.is_file() {
            io::read(&vessels_path, unit).map_err(|e| format!("{}: {e}", vessels_path.display()))?
        } else {
            MeshFile::default()
        };
        return preop_model_from_file(file, &vessels).map_err(ctx);
    }
    let mut mesh = if file.tets.is_empty() {
        if file.triangles.is_empty() {
            return Err(ctx(
                "neither tetrahedra nor triangles: not a liver mesh or surface".into(),
            ));
        }
        if !(edge_mm.is_finite() && edge_mm > 0.5) {
            return Err(format!(
                "edge length {edge_mm} mm: need a finite value > 0.5"
            ));
        }
        let mut s = TriSurface::from_file(file)
            .map_err(ctx)?
            .largest_component();
        if !s.stats().closed {
            return Err(ctx(
                "the surface (largest piece) is not closed; a liver surface must enclose a volume"
                    .into(),
            ));
        }
        if s.signed_volume() < 0.0 {
            s.flip();
        }
        tetrahedralize(&s, &TetraParams::with_edge(edge_mm)).map_err(|e| ctx(e.to_string()))?
    } else {
        TetMesh::from_file(file).map_err(|e| ctx(e.to_string()))?
    };
    mesh.orient_positive();
    let labels = label(&mesh, &LabelParams::default()).map_err(ctx)?;
    Ok(labels.preop_model(&mesh, &[], &[]))
}

/// Reads a point set (mm after `unit`): a VTK file's points (`.vtp`, `.vtu`, `.vtk`), or a text
/// table (`.csv`: comma-separated; `.txt`, `.xyz`: whitespace- or comma-separated) whose rows are
/// `x y z` (more columns are ignored). Lines starting with `#`, blank lines and one header line of
/// non-numbers are skipped. Every coordinate must be finite; errors name the file and line.
pub fn read_points(path: &Path, unit: Unit) -> Result<Vec<[f64; 3]>, String> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    let points = match ext.as_str() {
        "vtp" | "vtu" | "vtk" => {
            io::read(path, unit)
                .map_err(|e| format!("{}: {e}", path.display()))?
                .nodes
        }
        "csv" | "txt" | "xyz" => {
            let text =
                std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
            parse_points(&text, unit.to_mm()).map_err(|e| format!("{}: {e}", path.display()))?
        }
        _ => {
            return Err(format!(
                "{}: unknown point file type (use .vtp, .vtk, .csv, .txt or .xyz)",
                path.display()
            ));
        }
    };
    if points.is_empty() {
        return Err(format!("{}: no points", path.display()));
    }
    if let Some(i) = points.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
        return Err(format!("{}: point {i} is not finite", path.display()));
    }
    Ok(points)
}

/// Parses `x y z` rows (see [`read_points`]), scaling by `factor`.
pub fn parse_points(text: &str, factor: f64) -> Result<Vec<[f64; 3]>, String> {
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
            return Err(format!(
                "line {}: {} values, need x y z",
                k + 1,
                fields.len()
            ));
        }
        let mut p = [0.0; 3];
        for a in 0..3 {
            p[a] = nums[a]
                .ok_or_else(|| format!("line {}: {:?} is not a number", k + 1, fields[a]))?
                * factor;
        }
        if !p.iter().all(|x| x.is_finite()) {
            return Err(format!("line {}: not finite", k + 1));
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
        let e = parse_points("1,2,3\n1,2\n", 1.0).unwrap_err();
        assert!(e.contains("line 2"), "{e}");
        let e = parse_points("1,2,3\n1,x,3\n", 1.0).unwrap_err();
        assert!(e.contains("line 2") && e.contains("\"x\""), "{e}");
        let e = parse_points("1,2,nan\n", 1.0).unwrap_err();
        assert!(e.contains("not finite"), "{e}");
    }
}
