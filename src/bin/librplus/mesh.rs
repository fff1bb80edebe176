//! `librplus mesh`: info, convert, tetra; and reading mesh files (a volume mesh for the FEM).

use crate::args::Common;
use crate::util::emit;
use anyhow::{Context, Result, bail};
use librplus::mesh::io::{self, MeshFile, Unit, WriteOptions};
use librplus::mesh::{TetMesh, TriSurface, quality};
use serde_json::{Value, json};
use std::path::Path;

pub(crate) fn read_file(path: &Path, unit: Unit) -> Result<MeshFile> {
    Ok(io::read(path, unit)?)
}

/// Reads a surface file's triangles, or a tet mesh file's outward boundary, as a surface.
pub(crate) fn read_surface(path: &Path, unit: Unit) -> Result<TriSurface> {
    let file = read_file(path, unit)?;
    let triangles = if !file.triangles.is_empty() {
        file.triangles.clone()
    } else if !file.tets.is_empty() {
        let mut m = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
        m.orient_positive();
        m.boundary()
            .with_context(|| path.display().to_string())?
            .triangles
    } else {
        bail!("{}: has no triangles or tetrahedra to mesh", path.display());
    };
    TriSurface::new(file.nodes, triangles).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// A volume mesh prepared for FEM, with what was changed on the way.
pub(crate) struct Volume {
    pub(crate) mesh: TetMesh,
    pub(crate) flipped: usize,
    pub(crate) removed_unused: usize,
}

/// Reads a volume mesh for FEM: flips inverted tets (with a note; a warning when orientation is
/// mixed, which often means a tangled mesh), removes nodes no tet uses, rejects degenerate,
/// duplicate and non-manifold tets, naming the file and the tet.
pub(crate) fn load_volume(path: &Path, unit: Unit) -> Result<Volume> {
    let file = read_file(path, unit)?;
    if file.tets.is_empty() {
        bail!(
            "{}: has no tetrahedra ({} triangles): a volume mesh is needed",
            path.display(),
            file.triangles.len()
        );
    }
    let mut mesh = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
    let flipped = mesh.orient_positive();
    if flipped == mesh.num_tets() {
        eprintln!(
            "note: {}: all {flipped} tets were negatively oriented and have been flipped",
            path.display()
        );
    } else if flipped > 0 {
        eprintln!(
            "warning: {}: {flipped} of {} tets were negatively oriented (mixed orientation) and have been flipped; if the mesh is tangled the results are wrong",
            path.display(),
            mesh.num_tets()
        );
    }
    let removed_unused = mesh.num_nodes() - mesh.used_nodes().iter().filter(|&&u| u).count();
    if removed_unused > 0 {
        mesh.remove_unused_nodes();
        eprintln!(
            "note: {}: removed {removed_unused} nodes that no tetrahedron uses (outputs use the remaining {} nodes, in file order)",
            path.display(),
            mesh.num_nodes()
        );
    }
    if let Some(p) = mesh.problems(1).into_iter().next() {
        bail!("{}: {p}", path.display());
    }
    mesh.boundary()
        .with_context(|| path.display().to_string())?;
    Ok(Volume {
        mesh,
        flipped,
        removed_unused,
    })
}

fn bbox_json(lo: [f64; 3], hi: [f64; 3]) -> Value {
    json!({"min": lo, "max": hi, "size": [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]]})
}

pub(crate) fn mesh_info(path: &Path, c: &Common) -> Result<()> {
    let file = read_file(path, c.unit)?;
    let out = if !file.tets.is_empty() {
        let mesh = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
        let problems = mesh.problems(usize::MAX);
        let count =
            |f: fn(&librplus::mesh::MeshError) -> bool| problems.iter().filter(|p| f(p)).count();
        let inverted = count(|p| matches!(p, librplus::mesh::MeshError::InvertedTet { .. }));
        let degenerate = count(|p| matches!(p, librplus::mesh::MeshError::DegenerateTet { .. }));
        let unused = count(|p| matches!(p, librplus::mesh::MeshError::UnusedNode { .. }));
        let mut oriented = mesh.clone();
        oriented.orient_positive();
        // A broken boundary (non-manifold or overlapping tets) is reported, not fatal, here.
        let (st, surface_error) = match oriented.boundary_surface() {
            Ok(surface) => (Some(surface.stats()), None),
            Err(e) => (None, Some(e.to_string())),
        };
        let q = quality::summary(&mesh);
        let (lo, hi) = mesh.bounding_box();
        let st_val = |f: fn(&librplus::mesh::SurfaceStats) -> Value| {
            st.as_ref().map(f).unwrap_or(Value::Null)
        };
        json!({
            "file": path.display().to_string(),
            "kind": "tetrahedral",
            "unit_in": c.unit.to_string(),
            "nodes": mesh.num_nodes(),
            "tets": mesh.num_tets(),
            "surface_triangles": st_val(|s| s.triangles.into()),
            "surface_nodes": st_val(|s| s.vertices.into()),
            "volume_mm3": mesh.tet_volumes().iter().map(|v| v.abs()).sum::<f64>(),
            "signed_volume_mm3": mesh.volume(),
            "min_dihedral_deg": q.min_dihedral_deg,
            "max_dihedral_deg": q.max_dihedral_deg,
            "min_radius_ratio": q.min_radius_ratio,
            "mean_radius_ratio": q.mean_radius_ratio,
            "components": mesh.num_components(),
            "inverted_tets": inverted,
            "degenerate_tets": degenerate,
            "unused_nodes": unused,
            "surface_closed": st_val(|s| s.closed.into()),
            "surface_genus": st_val(|s| s.genus.into()),
            "surface_area_mm2": st_val(|s| s.area_mm2.into()),
            "surface_error": surface_error,
            "other_triangles_in_file": file.triangles.len(),
            "skipped_cells": file.skipped_cells,
            "point_data": file.point_data.iter().map(|a| &a.name).collect::<Vec<_>>(),
            "bbox_mm": bbox_json(lo, hi),
        })
    } else if !file.triangles.is_empty() {
        let s =
            TriSurface::from_file(&file).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let st = s.stats();
        let (lo, hi) = s.bounding_box();
        let largest = s.largest_component().stats();
        json!({
            "file": path.display().to_string(),
            "kind": "surface",
            "unit_in": c.unit.to_string(),
            "nodes": file.nodes.len(),
            "tets": 0,
            "surface_triangles": st.triangles,
            "surface_nodes": st.vertices,
            "volume_mm3": st.signed_volume_mm3.abs(),
            "signed_volume_mm3": st.signed_volume_mm3,
            "orientation": if st.signed_volume_mm3 >= 0.0 { "outward" } else { "inward" },
            "min_dihedral_deg": Value::Null,
            "components": st.components,
            "closed": st.closed,
            "consistently_oriented": st.consistently_oriented,
            "genus": st.genus,
            "area_mm2": st.area_mm2,
            "largest_component": largest,
            "skipped_cells": file.skipped_cells,
            "bbox_mm": bbox_json(lo, hi),
        })
    } else {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &file.nodes {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        json!({
            "file": path.display().to_string(),
            "kind": "points",
            "nodes": file.nodes.len(),
            "tets": 0,
            "surface_triangles": 0,
            "skipped_cells": file.skipped_cells,
            "bbox_mm": bbox_json(lo, hi),
        })
    };
    emit(c.json, &out);
    Ok(())
}

pub(crate) fn mesh_convert(input: &Path, output: &Path, c: &Common, ascii: bool) -> Result<()> {
    let mut file = read_file(input, c.unit)?;
    let surface_out = matches!(
        io::Format::from_path(output)?,
        io::Format::Obj | io::Format::Stl | io::Format::Vtp
    );
    if surface_out && file.triangles.is_empty() && !file.tets.is_empty() {
        let mut mesh = TetMesh::from_file(&file).with_context(|| input.display().to_string())?;
        mesh.orient_positive();
        file.triangles = mesh
            .boundary()
            .with_context(|| input.display().to_string())?
            .triangles;
        file.tets.clear();
        file.cell_data.clear();
    }
    io::write(output, &file, WriteOptions { binary: !ascii })?;
    emit(
        c.json,
        &json!({
            "input": input.display().to_string(),
            "output": output.display().to_string(),
            "nodes": file.nodes.len(),
            "tets": file.tets.len(),
            "triangles": file.triangles.len(),
            "point_data": file.point_data.iter().map(|a| &a.name).collect::<Vec<_>>(),
        }),
    );
    Ok(())
}

pub(crate) fn mesh_tetra(
    path: &Path,
    edge_mm: f64,
    out: &Path,
    c: &Common,
    all_pieces: bool,
) -> Result<()> {
    if matches!(
        io::Format::from_path(out)?,
        io::Format::Obj | io::Format::Stl | io::Format::Vtp
    ) {
        bail!(
            "{}: a surface format cannot hold a tet mesh; use .vtu, .vtk or .msh",
            out.display()
        );
    }
    let surface = read_surface(path, c.unit)?;
    let enclosed = surface.signed_volume().abs();
    let params = librplus::mesh::tetra::TetraParams {
        keep_largest_component: !all_pieces,
        ..librplus::mesh::tetra::TetraParams::with_edge(edge_mm)
    };
    let bar = indicatif::ProgressBar::new_spinner().with_message("isosurface stuffing");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let result = librplus::mesh::tetra::tetrahedralize_with_report(&surface, &params);
    bar.finish_and_clear();
    let (mesh, report) = result.with_context(|| path.display().to_string())?;
    if report.pinched_vertices > 0 {
        eprintln!(
            "warning: {} boundary vertices where the surface touches itself at this edge length; a slightly different --edge-mm usually avoids them",
            report.pinched_vertices
        );
    }
    io::write(out, &mesh.to_file(), WriteOptions::default())?;
    let q = quality::summary(&mesh);
    let volume = mesh.volume();
    emit(
        c.json,
        &json!({
            "surface": path.display().to_string(),
            "out": out.display().to_string(),
            "edge_mm": edge_mm,
            "nodes": mesh.num_nodes(),
            "tets": mesh.num_tets(),
            "volume_mm3": volume,
            "surface_volume_mm3": enclosed,
            "volume_error_percent": 100.0 * (volume - enclosed) / enclosed,
            "min_dihedral_deg": q.min_dihedral_deg,
            "max_dihedral_deg": q.max_dihedral_deg,
            "report": report,
        }),
    );
    Ok(())
}
