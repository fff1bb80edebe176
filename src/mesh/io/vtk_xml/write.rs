//! The VTK XML writer: version 1.0, `header_type="UInt64"`, little-endian, ascii or base64 binary.

use super::*;

/// Values of one array to write.
enum Vals<'a> {
    F64(&'a [f64]),
    I64(Vec<i64>),
    U8(Vec<u8>),
}

/// Builds the XML text of a file.
pub(super) struct XmlOut {
    s: String,
    binary: bool,
}

pub(super) fn escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&apos;"),
            c => o.push(c),
        }
    }
    o
}

impl XmlOut {
    fn line(&mut self, indent: usize, text: &str) {
        for _ in 0..indent {
            self.s.push_str("  ");
        }
        self.s.push_str(text);
        self.s.push('\n');
    }

    fn array(&mut self, indent: usize, name: &str, comps: usize, vals: Vals) {
        let (ty, count) = match &vals {
            Vals::F64(v) => ("Float64", v.len()),
            Vals::I64(v) => ("Int64", v.len()),
            Vals::U8(v) => ("UInt8", v.len()),
        };
        let format = if self.binary { "binary" } else { "ascii" };
        let comps_attr = if comps > 1 {
            format!(" NumberOfComponents=\"{comps}\"")
        } else {
            String::new()
        };
        self.line(
            indent,
            &format!(
                "<DataArray type=\"{ty}\" Name=\"{}\"{comps_attr} format=\"{format}\">",
                escape(name)
            ),
        );
        let pad = "  ".repeat(indent + 1);
        if self.binary {
            let mut raw = Vec::with_capacity(8 + count * 8);
            let size = match &vals {
                Vals::U8(_) => count,
                _ => count * 8,
            };
            raw.extend_from_slice(&(size as u64).to_le_bytes());
            match &vals {
                Vals::F64(v) => v
                    .iter()
                    .for_each(|x| raw.extend_from_slice(&x.to_le_bytes())),
                Vals::I64(v) => v
                    .iter()
                    .for_each(|x| raw.extend_from_slice(&x.to_le_bytes())),
                Vals::U8(v) => raw.extend_from_slice(v),
            }
            self.s.push_str(&pad);
            self.s
                .push_str(&base64::engine::general_purpose::STANDARD.encode(&raw));
            self.s.push('\n');
        } else {
            let per_line = if comps > 1 { comps } else { 6 };
            let mut i = 0;
            while i < count {
                self.s.push_str(&pad);
                for k in i..(i + per_line).min(count) {
                    if k > i {
                        self.s.push(' ');
                    }
                    match &vals {
                        Vals::F64(v) => push_f64(&mut self.s, v[k]),
                        Vals::I64(v) => self.s.push_str(&v[k].to_string()),
                        Vals::U8(v) => self.s.push_str(&v[k].to_string()),
                    }
                }
                self.s.push('\n');
                i += per_line;
            }
        }
        self.line(indent, "</DataArray>");
    }

    fn data(&mut self, section: &str, n: usize, arrays: &[DataArray]) -> Result<(), Malformed> {
        if arrays.is_empty() {
            return Ok(());
        }
        self.line(3, &format!("<{section}>"));
        for a in arrays {
            if a.components == 0 || Some(a.values.len()) != n.checked_mul(a.components) {
                return Err(Malformed(format!(
                    "data array '{}' has {} values; expected {n} tuples of {} components",
                    a.name,
                    a.values.len(),
                    a.components
                )));
            }
            self.array(4, &a.name, a.components, Vals::F64(&a.values));
        }
        self.line(3, &format!("</{section}>"));
        Ok(())
    }

    fn head(&mut self, kind: &str, piece_attrs: &str) {
        self.s.push_str("<?xml version=\"1.0\"?>\n");
        self.line(
            0,
            &format!("<VTKFile type=\"{kind}\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">"),
        );
        self.line(1, &format!("<{kind}>"));
        self.line(2, &format!("<Piece {piece_attrs}>"));
    }

    fn points(&mut self, nodes: &[[f64; 3]]) {
        let pts: Vec<f64> = nodes.iter().flatten().copied().collect();
        self.line(3, "<Points>");
        self.array(4, "Points", 3, Vals::F64(&pts));
        self.line(3, "</Points>");
    }

    fn cells(&mut self, section: &str, conn: Vec<i64>, k: usize, types: Option<u8>) {
        let n = conn.len() / k.max(1);
        let offsets: Vec<i64> = (1..=n as i64).map(|i| i * k as i64).collect();
        self.line(3, &format!("<{section}>"));
        self.array(4, "connectivity", 1, Vals::I64(conn));
        self.array(4, "offsets", 1, Vals::I64(offsets));
        if let Some(t) = types {
            self.array(4, "types", 1, Vals::U8(vec![t; n]));
        }
        self.line(3, &format!("</{section}>"));
    }

    fn finish(mut self, kind: &str) -> Vec<u8> {
        self.line(2, "</Piece>");
        self.line(1, &format!("</{kind}>"));
        self.line(0, "</VTKFile>");
        self.s.into_bytes()
    }
}

pub(super) fn flat<const K: usize>(cells: &[[u32; K]]) -> Vec<i64> {
    cells.iter().flatten().map(|&i| i as i64).collect()
}

/// Writes a `.vtu`: the tetrahedra (type 10), or the triangles (type 5) when there are none.
pub(crate) fn write_vtu(file: &MeshFile, o: WriteOptions) -> Result<Vec<u8>, Malformed> {
    let (conn, k, t) = if file.tets.is_empty() {
        (flat(&file.triangles), 3, 5)
    } else {
        (flat(&file.tets), 4, 10)
    };
    let nc = conn.len() / k;
    let mut x = XmlOut {
        s: String::new(),
        binary: o.binary,
    };
    x.head(
        "UnstructuredGrid",
        &format!(
            "NumberOfPoints=\"{}\" NumberOfCells=\"{nc}\"",
            file.nodes.len()
        ),
    );
    x.data("PointData", file.nodes.len(), &file.point_data)?;
    x.data("CellData", nc, &file.cell_data)?;
    x.points(&file.nodes);
    x.cells("Cells", conn, k, Some(t));
    Ok(x.finish("UnstructuredGrid"))
}

/// Writes a `.vtp`: the triangles as `Polys`, or one vertex per point (`Verts`) for a point set.
pub(crate) fn write_vtp(file: &MeshFile, o: WriteOptions) -> Result<Vec<u8>, Malformed> {
    surface_only(file, "VTK PolyData (.vtp)")?;
    let np = file.nodes.len();
    let mut x = XmlOut {
        s: String::new(),
        binary: o.binary,
    };
    let polys = !file.triangles.is_empty();
    let (nv, npoly) = if polys {
        (0, file.triangles.len())
    } else {
        (np, 0)
    };
    x.head(
        "PolyData",
        &format!(
            "NumberOfPoints=\"{np}\" NumberOfVerts=\"{nv}\" NumberOfLines=\"0\" NumberOfStrips=\"0\" NumberOfPolys=\"{npoly}\""
        ),
    );
    x.data("PointData", np, &file.point_data)?;
    if polys && file.tets.is_empty() {
        x.data("CellData", npoly, &file.cell_data)?;
    }
    x.points(&file.nodes);
    if polys {
        x.cells("Polys", flat(&file.triangles), 3, None);
    } else if np > 0 {
        x.cells("Verts", (0..np as i64).collect(), 1, None);
    }
    Ok(x.finish("PolyData"))
}
