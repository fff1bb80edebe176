//! Wavefront OBJ reader and writer.
//!
//! Reads `v x y z [w]` (extra components such as vertex colours are ignored) and `f` statements
//! in the forms `a`, `a/b`, `a//c` and `a/b/c`, with positive or negative (relative) indices;
//! polygons are fan-triangulated. `l` and `p` elements are counted as skipped cells; every other
//! statement (`vn`, `vt`, `o`, `g`, `s`, `usemtl`, `mtllib`, ...) and comments are ignored.
//! Writes `v` and `f` lines.

use super::common::{Malformed, line_err, parse_f64, push_f64, shown, surface_only};
use super::{IoError, MeshFile};
use std::path::Path;

/// Reads an OBJ file.
pub(crate) fn read(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    let text = String::from_utf8_lossy(bytes);
    let mut file = MeshFile::default();
    // Largest positive index seen and its line: forward references are checked at the end.
    let mut max_ref: Option<(u32, usize)> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let content = raw.split('#').next().unwrap_or("");
        let mut tokens = content.split_ascii_whitespace();
        match tokens.next() {
            Some("v") => {
                let p = read_vertex(tokens).map_err(|m| line_err(path, line, m))?;
                file.nodes.push(p);
            }
            Some("f") => {
                let face =
                    read_face(tokens, file.nodes.len()).map_err(|m| line_err(path, line, m))?;
                if let Some(&m) = face.iter().max() {
                    if max_ref.is_none_or(|(old, _)| m > old) {
                        max_ref = Some((m, line));
                    }
                }
                for w in face[1..].windows(2) {
                    file.triangles.push([face[0], w[0], w[1]]);
                }
            }
            Some("l") => file.skipped_cells += 1,
            Some("p") => file.skipped_cells += tokens.count(),
            _ => {}
        }
    }
    if let Some((m, line)) = max_ref {
        if m as usize >= file.nodes.len() {
            return Err(line_err(
                path,
                line,
                format!(
                    "face refers to vertex {}, but the file has only {} vertices",
                    m as u64 + 1,
                    file.nodes.len()
                ),
            ));
        }
    }
    Ok(file)
}

/// Parses the coordinates after `v`.
fn read_vertex<'a>(tokens: impl Iterator<Item = &'a str>) -> Result<[f64; 3], Malformed> {
    let mut p = [0.0; 3];
    let mut n = 0;
    for t in tokens.take(3) {
        p[n] = parse_f64(t).ok_or_else(|| {
            format!(
                "expected a number for coordinate {} after 'v', found '{}'",
                n + 1,
                shown(t)
            )
        })?;
        n += 1;
    }
    if n < 3 {
        return Err(Malformed(format!(
            "expected 3 coordinates after 'v', found {n}"
        )));
    }
    Ok(p)
}

/// Parses the vertex references after `f` into 0-based indices.
fn read_face<'a>(
    tokens: impl Iterator<Item = &'a str>,
    nverts: usize,
) -> Result<Vec<u32>, Malformed> {
    let mut face = Vec::new();
    for t in tokens {
        let first = t.split('/').next().unwrap_or("");
        let k: i64 = first.parse().map_err(|_| {
            format!(
                "expected a vertex index (forms a, a/b, a//c, a/b/c) after 'f', found '{}'",
                shown(t)
            )
        })?;
        let idx = if k > 0 {
            k - 1
        } else if k < 0 {
            let idx = nverts as i64 + k;
            if idx < 0 {
                return Err(Malformed(format!(
                    "relative vertex index {k} points before the first vertex ({nverts} vertices defined so far)"
                )));
            }
            idx
        } else {
            return Err(Malformed(
                "vertex index 0 is invalid: OBJ indices start at 1".into(),
            ));
        };
        let idx = u32::try_from(idx)
            .ok()
            .filter(|&i| i < u32::MAX)
            .ok_or_else(|| format!("vertex index {k} is too large"))?;
        face.push(idx);
    }
    if face.len() < 3 {
        return Err(Malformed(format!(
            "expected at least 3 vertices after 'f', found {}",
            face.len()
        )));
    }
    Ok(face)
}

/// Writes the triangles (and all nodes) as `v` and `f` lines; tetrahedra are not representable.
pub(crate) fn write(file: &MeshFile, path: &Path) -> Result<Vec<u8>, Malformed> {
    surface_only(file, "OBJ")?;
    let mut out = String::with_capacity(40 * file.nodes.len() + 30 * file.triangles.len());
    out.push_str("# written by LIBR+ (units: mm)\n");
    if let Some(stem) = path.file_stem().and_then(|s| s.to_str()) {
        let name: String = stem.chars().filter(|c| !c.is_whitespace()).collect();
        if !name.is_empty() {
            out.push_str("o ");
            out.push_str(&name);
            out.push('\n');
        }
    }
    for p in &file.nodes {
        out.push('v');
        for &c in p {
            out.push(' ');
            push_f64(&mut out, c);
        }
        out.push('\n');
    }
    for t in &file.triangles {
        out.push_str(&format!(
            "f {} {} {}\n",
            t[0] as u64 + 1,
            t[1] as u64 + 1,
            t[2] as u64 + 1
        ));
    }
    Ok(out.into_bytes())
}
