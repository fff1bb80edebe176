//! Legacy VTK (`.vtk`) reader and writer.
//!
//! Reads versions 2.0–5.1, ASCII and BINARY (big-endian), `DATASET UNSTRUCTURED_GRID` and
//! `DATASET POLYDATA`: `POINTS`; `CELLS` in both the counted form (`n size`, each cell prefixed by
//! its node count) and the 5.x form (`OFFSETS`/`CONNECTIVITY`); `CELL_TYPES`; `POLYGONS`,
//! `TRIANGLE_STRIPS` (both triangulated), `LINES` and `VERTICES` (counted as skipped);
//! `POINT_DATA`/`CELL_DATA` with `SCALARS`, `VECTORS`, `NORMALS`, `TEXTURE_COORDINATES`, `TENSORS`,
//! `COLOR_SCALARS` and `FIELD` arrays. `LOOKUP_TABLE` and `METADATA` blocks are skipped.
//!
//! Writes version 4.2 (`CELLS` with counts): `UNSTRUCTURED_GRID` with the tetrahedra when there
//! are any, else `POLYDATA` with the triangles (or one vertex per point for a point set).

use super::common::{
    CellCollector, DType, Malformed, capped, content_err, line_err, offset_err, push_f64, shown,
    split_cells, to_index, to_indices,
};
use super::{DataArray, IoError, MeshFile, WriteOptions};
use std::path::Path;

/// Byte cursor over the file that tracks line numbers while the file is text.
struct Cur<'a> {
    b: &'a [u8],
    pos: usize,
    line: usize,
    binary: bool,
    binary_seen: bool,
    /// Line of the last token read (where the file ended, for text files).
    tok_line: usize,
    path: &'a Path,
}

fn lossy(b: &[u8]) -> String {
    shown(&String::from_utf8_lossy(b))
}

impl<'a> Cur<'a> {
    /// Error at the current position: a line number until binary data was read, then an offset.
    fn err(&self, msg: impl Into<String>) -> IoError {
        if self.binary_seen {
            offset_err(self.path, self.pos, msg)
        } else {
            line_err(self.path, self.line, msg)
        }
    }

    fn skip_ws(&mut self) {
        while let Some(&c) = self.b.get(self.pos) {
            if !c.is_ascii_whitespace() {
                break;
            }
            if c == b'\n' {
                self.line += 1;
            }
            self.pos += 1;
        }
    }

    /// Error for a file that ended early, at the line of the last token.
    fn eof(&self, msg: impl Into<String>) -> IoError {
        if self.binary_seen {
            offset_err(self.path, self.b.len(), msg)
        } else {
            line_err(self.path, self.tok_line, msg)
        }
    }

    /// Next whitespace-separated token.
    fn token(&mut self) -> Option<&'a [u8]> {
        self.skip_ws();
        if self.pos < self.b.len() {
            self.tok_line = self.line;
        }
        let start = self.pos;
        while self
            .b
            .get(self.pos)
            .is_some_and(|c| !c.is_ascii_whitespace())
        {
            self.pos += 1;
        }
        (self.pos > start).then(|| &self.b[start..self.pos])
    }

    /// True when the next token (after whitespace) starts with `word`, case-insensitively.
    fn peek_is(&self, word: &str) -> bool {
        let rest = self.b.get(self.pos..).unwrap_or(&[]);
        let start = rest
            .iter()
            .position(|c| !c.is_ascii_whitespace())
            .unwrap_or(rest.len());
        rest[start..]
            .get(..word.len())
            .is_some_and(|w| w.eq_ignore_ascii_case(word.as_bytes()))
    }

    /// The rest of the current line (without the newline, which is consumed).
    fn rest_of_line(&mut self) -> &'a [u8] {
        let start = self.pos;
        while let Some(&c) = self.b.get(self.pos) {
            self.pos += 1;
            if c == b'\n' {
                self.line += 1;
                let end = if self.pos >= 2 && self.b[self.pos - 2] == b'\r' {
                    self.pos - 2
                } else {
                    self.pos - 1
                };
                return &self.b[start..end];
            }
        }
        &self.b[start..]
    }

    /// A token that must be present; `what` says what was expected.
    fn word(&mut self, what: &str) -> Result<String, IoError> {
        match self.token() {
            Some(t) => Ok(String::from_utf8_lossy(t).into_owned()),
            None => Err(self.eof(format!("file ended early: expected {what}"))),
        }
    }

    /// A non-negative integer token.
    fn count(&mut self, what: &str) -> Result<usize, IoError> {
        let t = self.word(what)?;
        t.parse().map_err(|_| {
            self.err(format!(
                "expected {what} (a non-negative integer), found '{}'",
                shown(&t)
            ))
        })
    }

    /// Reads `n` values of type `dtype` (text tokens or big-endian binary).
    fn values(&mut self, n: usize, dtype: DType, what: &str) -> Result<Vec<f64>, IoError> {
        let remaining = self.b.len().saturating_sub(self.pos);
        if self.binary {
            let need = n.checked_mul(dtype.size()).filter(|&k| k <= remaining).ok_or_else(|| {
                offset_err(
                    self.path,
                    self.b.len(),
                    format!(
                        "file ended while reading {what}: {n} values of {} bytes need {} bytes, only {remaining} remain",
                        dtype.size(),
                        n as u128 * dtype.size() as u128
                    ),
                )
            })?;
            let mut out = Vec::with_capacity(n);
            dtype.decode(&self.b[self.pos..self.pos + need], true, &mut out);
            self.pos += need;
            self.binary_seen = true;
            return Ok(out);
        }
        let mut out = Vec::with_capacity(capped(n, remaining / 2 + 1));
        for k in 0..n {
            let Some(t) = self.token() else {
                return Err(self.eof(format!(
                    "file ended while reading {what}: value {} of {n}",
                    k + 1
                )));
            };
            let v = std::str::from_utf8(t)
                .ok()
                .and_then(|s| s.parse::<f64>().ok());
            out.push(v.ok_or_else(|| {
                self.err(format!(
                    "expected a number in {what} (value {} of {n}), found '{}'",
                    k + 1,
                    lossy(t)
                ))
            })?);
        }
        Ok(out)
    }

    /// Skips a `METADATA` block: lines up to the first blank line.
    fn skip_metadata(&mut self) {
        self.rest_of_line();
        while self.pos < self.b.len() {
            if self.rest_of_line().trim_ascii().is_empty() {
                break;
            }
        }
    }
}

/// Cells as ends-offsets and connectivity.
#[derive(Default)]
struct Cells {
    offsets: Vec<f64>,
    conn: Vec<u32>,
}

/// Where attribute arrays go.
#[derive(Clone, Copy, PartialEq)]
enum Target {
    None,
    Point(usize),
    Cell(usize),
}

/// Everything read before the mesh is assembled.
struct Parsed {
    polydata: bool,
    points: Vec<f64>,
    cells: Option<Cells>,
    types: Option<Vec<f64>>,
    /// VERTICES, LINES, POLYGONS, TRIANGLE_STRIPS (VTK's cell order in polydata).
    poly: [Option<Cells>; 4],
    target: Target,
    point_n: Option<usize>,
    cell_n: Option<usize>,
    point_data: Vec<DataArray>,
    cell_data: Vec<DataArray>,
}

/// Decodes `%XX` escapes that VTK uses for spaces and other characters in array names.
fn decode_name(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = b
            .get(i + 1..i + 3)
            .and_then(|h| std::str::from_utf8(h).ok());
        match (b[i], hex.and_then(|h| u8::from_str_radix(h, 16).ok())) {
            (b'%', Some(v)) => {
                out.push(v);
                i += 3;
            }
            (c, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// Reads a legacy VTK file.
pub(crate) fn read(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    let mut c = Cur {
        b: bytes,
        pos: 0,
        line: 1,
        binary: false,
        binary_seen: false,
        tok_line: 1,
        path,
    };
    let polydata = header(&mut c)?;
    let mut p = Parsed {
        polydata,
        points: Vec::new(),
        cells: None,
        types: None,
        poly: [None, None, None, None],
        target: Target::None,
        point_n: None,
        cell_n: None,
        point_data: Vec::new(),
        cell_data: Vec::new(),
    };
    while let Some(tok) = c.token() {
        let key = String::from_utf8_lossy(tok).to_ascii_uppercase();
        section(&mut c, &mut p, &key)?;
    }
    assemble(p, path)
}

/// Reads the four header lines; returns whether the dataset is POLYDATA.
fn header(c: &mut Cur) -> Result<bool, IoError> {
    let first = String::from_utf8_lossy(c.rest_of_line()).into_owned();
    let lower = first.to_ascii_lowercase();
    let Some(at) = lower.find("datafile version") else {
        return Err(line_err(
            c.path,
            1,
            format!(
                "expected '# vtk DataFile Version x.y', found '{}'",
                shown(first.trim())
            ),
        ));
    };
    let version = first[at + "datafile version".len()..].trim();
    let major: u32 = version
        .split('.')
        .next()
        .and_then(|m| m.parse().ok())
        .unwrap_or(0);
    if !(1..=5).contains(&major) {
        return Err(line_err(
            c.path,
            1,
            format!(
                "unsupported legacy VTK version '{}': expected 2.0 to 5.1",
                shown(version)
            ),
        ));
    }
    if c.pos >= c.b.len() {
        return Err(c.eof("file ended early: expected a title line"));
    }
    c.rest_of_line();
    let mode = c.word("ASCII or BINARY")?;
    c.binary = match mode.to_ascii_uppercase().as_str() {
        "ASCII" => false,
        "BINARY" => true,
        _ => {
            return Err(c.err(format!(
                "expected ASCII or BINARY, found '{}'",
                shown(&mode)
            )));
        }
    };
    c.rest_of_line();
    let kw = c.word("DATASET")?;
    if !kw.eq_ignore_ascii_case("DATASET") {
        return Err(c.err(format!("expected DATASET, found '{}'", shown(&kw))));
    }
    let kind = c.word("a dataset type")?.to_ascii_uppercase();
    c.rest_of_line();
    match kind.as_str() {
        "UNSTRUCTURED_GRID" => Ok(false),
        "POLYDATA" => Ok(true),
        _ => Err(c.err(format!(
            "DATASET {} is not supported: expected UNSTRUCTURED_GRID or POLYDATA",
            shown(&kind)
        ))),
    }
}

/// Data type word, checked.
fn dtype(c: &mut Cur, what: &str) -> Result<DType, IoError> {
    let t = c.word(&format!("the data type of {what}"))?;
    DType::from_legacy(&t).ok_or_else(|| {
        c.err(format!(
            "unsupported data type '{}' for {what}: expected float, double, int, long, char, short or their unsigned forms",
            shown(&t)
        ))
    })
}

/// Reads one keyword section.
fn section(c: &mut Cur, p: &mut Parsed, key: &str) -> Result<(), IoError> {
    match key {
        "POINTS" => {
            let n = c.count("the number of points")?;
            let t = dtype(c, "POINTS")?;
            c.rest_of_line();
            let n3 = n
                .checked_mul(3)
                .ok_or_else(|| c.err("point count too large"))?;
            p.points = c.values(n3, t, "POINTS")?;
        }
        "CELLS" => p.cells = Some(cells(c, "CELLS")?),
        "CELL_TYPES" => {
            let n = c.count("the number of cell types")?;
            c.rest_of_line();
            p.types = Some(c.values(n, DType::I32, "CELL_TYPES")?);
        }
        "VERTICES" | "LINES" | "POLYGONS" | "TRIANGLE_STRIPS" => {
            let slot = ["VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS"]
                .iter()
                .position(|k| *k == key)
                .unwrap_or(0);
            p.poly[slot] = Some(cells(c, key)?);
        }
        "POINT_DATA" | "CELL_DATA" => {
            let n = c.count(&format!("the number of tuples after {key}"))?;
            c.rest_of_line();
            if key == "POINT_DATA" {
                p.target = Target::Point(n);
                p.point_n = Some(n);
            } else {
                p.target = Target::Cell(n);
                p.cell_n = Some(n);
            }
        }
        "FIELD" => field(c, p)?,
        "METADATA" => c.skip_metadata(),
        "LOOKUP_TABLE" => {
            c.word("a lookup table name")?;
            let n = c.count("the lookup table size")?;
            c.rest_of_line();
            let n4 = n
                .checked_mul(4)
                .ok_or_else(|| c.err("lookup table too large"))?;
            let t = if c.binary { DType::U8 } else { DType::F64 };
            c.values(n4, t, "LOOKUP_TABLE")?;
        }
        "SCALARS"
        | "VECTORS"
        | "NORMALS"
        | "TEXTURE_COORDINATES"
        | "TENSORS"
        | "TENSORS6"
        | "COLOR_SCALARS" => attribute(c, p, key)?,
        _ => {
            return Err(c.err(format!(
                "unexpected keyword '{}': expected POINTS, CELLS, CELL_TYPES, POLYGONS, POINT_DATA, CELL_DATA, SCALARS, VECTORS or FIELD",
                shown(key)
            )));
        }
    }
    Ok(())
}

/// Reads a cell section in the counted form or the 5.x OFFSETS/CONNECTIVITY form.
fn cells(c: &mut Cur, key: &str) -> Result<Cells, IoError> {
    let n = c.count(&format!("the number of cells after {key}"))?;
    let size = c.count(&format!("the size of {key}"))?;
    c.rest_of_line();
    if c.peek_is("OFFSETS") {
        c.token();
        let t = dtype(c, "OFFSETS")?;
        c.rest_of_line();
        let offs = c.values(n, t, &format!("{key} OFFSETS"))?;
        let kw = c.word("CONNECTIVITY")?;
        if !kw.eq_ignore_ascii_case("CONNECTIVITY") {
            return Err(c.err(format!(
                "expected CONNECTIVITY after the {key} offsets, found '{}'",
                shown(&kw)
            )));
        }
        let t = dtype(c, "CONNECTIVITY")?;
        c.rest_of_line();
        let conn = c.values(size, t, &format!("{key} CONNECTIVITY"))?;
        let conn = to_indices(&conn, &format!("{key} CONNECTIVITY")).map_err(|m| c.err(m))?;
        if offs.first().is_some_and(|&o| o != 0.0) {
            return Err(c.err(format!("{key} OFFSETS must start at 0, found {}", offs[0])));
        }
        let offsets = offs.get(1..).unwrap_or(&[]).to_vec();
        split_cells(&offsets, &conn).map_err(|m| c.err(format!("{key}: {m}")))?;
        return Ok(Cells { offsets, conn });
    }
    let data = c.values(size, DType::I32, key)?;
    let mut out = Cells {
        offsets: Vec::with_capacity(capped(n, size)),
        conn: Vec::with_capacity(size),
    };
    let mut k = 0usize;
    for i in 0..n {
        let cnt = data.get(k).and_then(|&v| to_index(v)).map(|v| v as usize);
        let nodes = cnt.and_then(|cnt| data.get(k + 1..k + 1 + cnt));
        let Some(nodes) = nodes else {
            return Err(c.err(format!(
                "{key}: cell {i} of {n} does not fit in the declared size {size} (or its node count is invalid)"
            )));
        };
        out.conn
            .extend(to_indices(nodes, &format!("{key} cell {i}")).map_err(|m| c.err(m))?);
        out.offsets.push(out.conn.len() as f64);
        k += 1 + nodes.len();
    }
    if k != size {
        return Err(c.err(format!(
            "{key}: the {n} cells use {k} values, but the declared size is {size}"
        )));
    }
    Ok(out)
}

/// The tuple count of the current attribute target, or an error if there is none.
fn target_count(c: &Cur, p: &Parsed, key: &str) -> Result<usize, IoError> {
    match p.target {
        Target::Point(n) | Target::Cell(n) => Ok(n),
        Target::None => Err(c.err(format!("{key} found before POINT_DATA or CELL_DATA"))),
    }
}

fn push_array(p: &mut Parsed, a: DataArray) {
    match p.target {
        Target::Point(_) => p.point_data.push(a),
        Target::Cell(_) => p.cell_data.push(a),
        Target::None => {}
    }
}

/// Reads SCALARS, VECTORS, NORMALS, TEXTURE_COORDINATES, TENSORS or COLOR_SCALARS.
fn attribute(c: &mut Cur, p: &mut Parsed, key: &str) -> Result<(), IoError> {
    let n = target_count(c, p, key)?;
    let line = String::from_utf8_lossy(c.rest_of_line()).into_owned();
    let words: Vec<&str> = line.split_ascii_whitespace().collect();
    let Some(name) = words.first().map(|w| decode_name(w)) else {
        return Err(c.err(format!("expected an array name after {key}")));
    };
    let word = |i: usize, what: &str| -> Result<&str, IoError> {
        words
            .get(i)
            .copied()
            .ok_or_else(|| c.err(format!("expected {what} after {key} {}", shown(&name))))
    };
    let parse_count = |s: &str, what: &str| -> Result<usize, IoError> {
        s.parse::<usize>()
            .ok()
            .filter(|&k| (1..=1024).contains(&k))
            .ok_or_else(|| c.err(format!("expected {what} (1 to 1024), found '{}'", shown(s))))
    };
    let type_of = |s: &str| -> Result<DType, IoError> {
        DType::from_legacy(s).ok_or_else(|| {
            c.err(format!(
                "unsupported data type '{}' for {key} {}",
                shown(s),
                shown(&name)
            ))
        })
    };
    let (comps, t, scale) = match key {
        "SCALARS" => {
            let t = type_of(word(1, "a data type")?)?;
            let comps = match words.get(2) {
                Some(s) => parse_count(s, "the number of components")?,
                None => 1,
            };
            if c.peek_is("LOOKUP_TABLE") {
                c.token();
                c.rest_of_line();
            }
            (comps, t, 1.0)
        }
        "VECTORS" | "NORMALS" => (3, type_of(word(1, "a data type")?)?, 1.0),
        "TEXTURE_COORDINATES" => (
            parse_count(word(1, "a dimension")?, "the texture dimension")?,
            type_of(word(2, "a data type")?)?,
            1.0,
        ),
        "TENSORS" => (9, type_of(word(1, "a data type")?)?, 1.0),
        "TENSORS6" => (6, type_of(word(1, "a data type")?)?, 1.0),
        _ => {
            let comps = parse_count(word(1, "the number of values")?, "the number of values")?;
            if c.binary {
                (comps, DType::U8, 1.0 / 255.0)
            } else {
                (comps, DType::F64, 1.0)
            }
        }
    };
    let total = n
        .checked_mul(comps)
        .ok_or_else(|| c.err("array too large"))?;
    let mut values = c.values(total, t, &format!("{key} {}", name))?;
    if scale != 1.0 {
        values.iter_mut().for_each(|v| *v *= scale);
    }
    push_array(p, DataArray::new(name, comps, values));
    Ok(())
}

/// Reads a FIELD block; its arrays join the current attribute target (dataset-level fields are
/// read and dropped).
fn field(c: &mut Cur, p: &mut Parsed) -> Result<(), IoError> {
    c.word("a field name")?;
    let k = c.count("the number of field arrays")?;
    c.rest_of_line();
    for i in 0..k {
        let name = c.word(&format!("field array {} of {k}", i + 1))?;
        if name == "NULL_ARRAY" {
            continue;
        }
        let name = decode_name(&name);
        let comps = c.count(&format!(
            "the number of components of field array '{}'",
            shown(&name)
        ))?;
        let tuples = c.count(&format!(
            "the number of tuples of field array '{}'",
            shown(&name)
        ))?;
        let t = dtype(c, &format!("field array '{}'", shown(&name)))?;
        c.rest_of_line();
        let total = comps
            .checked_mul(tuples)
            .ok_or_else(|| c.err("field array too large"))?;
        let values = c.values(total, t, &format!("field array '{}'", shown(&name)))?;
        if c.peek_is("METADATA") {
            c.token();
            c.skip_metadata();
        }
        match p.target {
            Target::Point(n) | Target::Cell(n) if comps > 0 => {
                if tuples != n {
                    return Err(c.err(format!(
                        "field array '{}' has {tuples} tuples, expected {n}",
                        shown(&name)
                    )));
                }
                push_array(p, DataArray::new(name, comps, values));
            }
            _ => {}
        }
    }
    Ok(())
}

/// Turns the parsed sections into a mesh.
fn assemble(p: Parsed, path: &Path) -> Result<MeshFile, IoError> {
    let nodes: Vec<[f64; 3]> = p
        .points
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2]])
        .collect();
    let mut cc = CellCollector::default();
    let mut ncells = 0usize;
    let err = |m: Malformed| content_err(path, m);
    let say = |m: String| content_err(path, m);
    if p.polydata {
        for (slot, cells) in p.poly.iter().enumerate() {
            let Some(cells) = cells else { continue };
            for cell in split_cells(&cells.offsets, &cells.conn).map_err(err)? {
                match slot {
                    0 | 1 => cc.skip(),
                    2 => cc.add_polygon(cell, ncells),
                    _ => cc.add_strip(cell, ncells),
                }
                ncells += 1;
            }
        }
    } else if let Some(cells) = &p.cells {
        let cells = split_cells(&cells.offsets, &cells.conn).map_err(err)?;
        let types = p.types.as_deref().unwrap_or(&[]);
        if types.len() != cells.len() {
            return Err(say(format!(
                "CELLS has {} cells but CELL_TYPES has {} entries",
                cells.len(),
                types.len()
            )));
        }
        for (i, (cell, &t)) in cells.iter().zip(types).enumerate() {
            let t = to_index(t)
                .and_then(|t| u8::try_from(t).ok())
                .ok_or_else(|| say(format!("CELL_TYPES entry {i} is {t}, not a VTK cell type")))?;
            cc.add_vtk(t, cell, i).map_err(err)?;
        }
        ncells = cells.len();
    }
    if let Some(n) = p.point_n.filter(|&n| n != nodes.len()) {
        return Err(say(format!(
            "POINT_DATA declares {n} tuples, but POINTS has {} points",
            nodes.len()
        )));
    }
    if let Some(n) = p.cell_n.filter(|&n| n != ncells) {
        return Err(say(format!(
            "CELL_DATA declares {n} tuples, but the file has {ncells} cells"
        )));
    }
    Ok(cc.finish(nodes, p.point_data, p.cell_data))
}

/// Output buffer for ASCII or big-endian binary sections.
struct Out {
    buf: Vec<u8>,
    binary: bool,
}

impl Out {
    fn text(&mut self, s: &str) {
        self.buf.extend_from_slice(s.as_bytes());
    }

    fn f64s(&mut self, v: &[f64], per_line: usize) {
        if self.binary {
            for x in v {
                self.buf.extend_from_slice(&x.to_be_bytes());
            }
            self.buf.push(b'\n');
            return;
        }
        let mut s = String::with_capacity(v.len() * 20);
        for row in v.chunks(per_line.max(1)) {
            for (i, &x) in row.iter().enumerate() {
                if i > 0 {
                    s.push(' ');
                }
                push_f64(&mut s, x);
            }
            s.push('\n');
        }
        self.text(&s);
    }

    fn i32s(&mut self, v: &[i32], per_line: usize) {
        if self.binary {
            for x in v {
                self.buf.extend_from_slice(&x.to_be_bytes());
            }
            self.buf.push(b'\n');
            return;
        }
        let mut s = String::with_capacity(v.len() * 8);
        for row in v.chunks(per_line.max(1)) {
            let words: Vec<String> = row.iter().map(|x| x.to_string()).collect();
            s.push_str(&words.join(" "));
            s.push('\n');
        }
        self.text(&s);
    }
}

/// Encodes an array name the way VTK does (`%20` for spaces, etc.).
fn encode_name(name: &str) -> String {
    let mut s = String::new();
    for b in name.bytes() {
        if b.is_ascii_graphic() && b != b'%' {
            s.push(b as char);
        } else {
            s.push_str(&format!("%{b:02X}"));
        }
    }
    if s.is_empty() { "unnamed".into() } else { s }
}

/// Cells with a count prefix, as i32.
fn counted<const K: usize>(cells: &[[u32; K]]) -> Result<Vec<i32>, Malformed> {
    let mut v = Vec::with_capacity(cells.len() * (K + 1));
    for c in cells {
        v.push(K as i32);
        for &i in c {
            v.push(
                i32::try_from(i)
                    .map_err(|_| format!("node index {i} does not fit the legacy VTK int type"))?,
            );
        }
    }
    Ok(v)
}

/// Writes attribute arrays: VECTORS for 3 components, SCALARS for 1, 2 or 4, FIELD otherwise.
fn write_arrays(o: &mut Out, key: &str, n: usize, arrays: &[DataArray]) -> Result<(), Malformed> {
    if arrays.is_empty() {
        return Ok(());
    }
    o.text(&format!("{key} {n}\n"));
    let mut field = Vec::new();
    for a in arrays {
        if a.components == 0 || a.values.len() != n * a.components {
            return Err(Malformed(format!(
                "data array '{}' has {} values; expected {n} tuples of {}",
                a.name,
                a.values.len(),
                a.components
            )));
        }
        match a.components {
            3 => o.text(&format!("VECTORS {} double\n", encode_name(&a.name))),
            1 | 2 | 4 => o.text(&format!(
                "SCALARS {} double {}\nLOOKUP_TABLE default\n",
                encode_name(&a.name),
                a.components
            )),
            _ => {
                field.push(a);
                continue;
            }
        }
        o.f64s(&a.values, a.components);
    }
    if !field.is_empty() {
        o.text(&format!("FIELD FieldData {}\n", field.len()));
        for a in field {
            o.text(&format!(
                "{} {} {n} double\n",
                encode_name(&a.name),
                a.components
            ));
            o.f64s(&a.values, a.components);
        }
    }
    Ok(())
}

/// Writes legacy VTK 4.2, ASCII or BINARY per `options`.
pub(crate) fn write(file: &MeshFile, options: WriteOptions) -> Result<Vec<u8>, Malformed> {
    let mut o = Out {
        buf: Vec::new(),
        binary: options.binary,
    };
    let mode = if options.binary { "BINARY" } else { "ASCII" };
    let ug = !file.tets.is_empty();
    let kind = if ug { "UNSTRUCTURED_GRID" } else { "POLYDATA" };
    o.text(&format!(
        "# vtk DataFile Version 4.2\nLIBR+ mesh (units: mm)\n{mode}\nDATASET {kind}\nPOINTS {} double\n",
        file.nodes.len()
    ));
    let pts: Vec<f64> = file.nodes.iter().flatten().copied().collect();
    o.f64s(&pts, 3);
    let ncells;
    if ug {
        ncells = file.tets.len();
        o.text(&format!("CELLS {ncells} {}\n", ncells * 5));
        o.i32s(&counted(&file.tets)?, 5);
        o.text(&format!("CELL_TYPES {ncells}\n"));
        o.i32s(&vec![10; ncells], 1);
    } else if !file.triangles.is_empty() {
        ncells = file.triangles.len();
        o.text(&format!("POLYGONS {ncells} {}\n", ncells * 4));
        o.i32s(&counted(&file.triangles)?, 4);
    } else {
        ncells = 0;
        if !file.nodes.is_empty() {
            let verts: Vec<[u32; 1]> = (0..file.nodes.len() as u32).map(|i| [i]).collect();
            o.text(&format!("VERTICES {} {}\n", verts.len(), verts.len() * 2));
            o.i32s(&counted(&verts)?, 2);
        }
    }
    write_arrays(&mut o, "POINT_DATA", file.nodes.len(), &file.point_data)?;
    if ncells > 0 {
        write_arrays(&mut o, "CELL_DATA", ncells, &file.cell_data)?;
    }
    Ok(o.buf)
}
