//! STL reader and writer (ASCII and binary).
//!
//! A file is binary when its size is exactly `84 + 50 n` for the facet count `n` in its header
//! (some binary files begin with the word `solid`), ASCII when it begins with `solid` followed by
//! facets or `endsolid`, and binary otherwise. Vertices with bit-identical coordinates are welded
//! into one node, so the result is an indexed mesh. Writes binary or ASCII with normals computed
//! from the triangles.

use super::common::{
    Malformed, line_err, offset_err, parse_f64, push_f64, shown, surface_only, triangle_normal,
};
use super::{IoError, MeshFile, WriteOptions};
use std::collections::HashMap;
use std::path::Path;

/// Welds vertices with identical coordinates (`-0.0` and `0.0` count as equal).
#[derive(Default)]
struct Welder {
    nodes: Vec<[f64; 3]>,
    index: HashMap<[u64; 3], u32>,
}

impl Welder {
    fn node(&mut self, p: [f64; 3]) -> u32 {
        let p = p.map(|c| c + 0.0);
        let key = p.map(f64::to_bits);
        let next = self.nodes.len() as u32;
        *self.index.entry(key).or_insert_with(|| {
            self.nodes.push(p);
            next
        })
    }
}

/// Reads an STL file.
pub(crate) fn read(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    if is_binary(bytes) {
        read_binary(bytes, path)
    } else {
        read_ascii(bytes, path)
    }
}

/// Decides between binary and ASCII STL.
fn is_binary(bytes: &[u8]) -> bool {
    if let Some(count) = bytes.get(80..84) {
        let n = u32::from_le_bytes([count[0], count[1], count[2], count[3]]) as u64;
        if 84 + 50 * n == bytes.len() as u64 {
            return true;
        }
    }
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(bytes.len());
    let head = &bytes[start..];
    if !head
        .get(..5)
        .is_some_and(|h| h.eq_ignore_ascii_case(b"solid"))
    {
        return true;
    }
    let window = &head[..head.len().min(1024)];
    let text = String::from_utf8_lossy(window).to_ascii_lowercase();
    !(text.contains("facet") || text.contains("endsolid"))
}

/// Reads a binary STL: 80-byte header, facet count, 50 bytes per facet.
fn read_binary(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    let Some(count) = bytes.get(80..84) else {
        return Err(offset_err(
            path,
            bytes.len(),
            format!(
                "file ended after {} bytes; a binary STL needs an 80-byte header and a 4-byte facet count",
                bytes.len()
            ),
        ));
    };
    let n = u32::from_le_bytes([count[0], count[1], count[2], count[3]]) as usize;
    let mut w = Welder::default();
    let mut triangles = Vec::with_capacity(n.min((bytes.len() - 84) / 50));
    for k in 0..n {
        let at = 84 + 50 * k;
        let Some(facet) = bytes.get(at..at + 50) else {
            return Err(offset_err(
                path,
                bytes.len(),
                format!(
                    "file ended while reading facet {} of {n} (a binary STL with {n} facets has {} bytes, this one {})",
                    k + 1,
                    84 + 50 * n as u64,
                    bytes.len()
                ),
            ));
        };
        let f = |i: usize| {
            let b = &facet[12 + 4 * i..16 + 4 * i];
            f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64
        };
        let mut t = [0u32; 3];
        for (v, slot) in t.iter_mut().enumerate() {
            *slot = w.node([f(3 * v), f(3 * v + 1), f(3 * v + 2)]);
        }
        triangles.push(t);
    }
    Ok(MeshFile {
        nodes: w.nodes,
        triangles,
        ..MeshFile::default()
    })
}

/// Whitespace-separated tokens with their 1-based line numbers.
struct Tokens<'a> {
    tokens: Vec<(usize, &'a str)>,
    pos: usize,
    last_line: usize,
}

impl<'a> Tokens<'a> {
    fn new(text: &'a str) -> Self {
        let tokens: Vec<(usize, &str)> = text
            .lines()
            .enumerate()
            .flat_map(|(i, l)| l.split_ascii_whitespace().map(move |t| (i + 1, t)))
            .collect();
        let last_line = text.lines().count().max(1);
        Self {
            tokens,
            pos: 0,
            last_line,
        }
    }

    fn next(&mut self) -> Option<(usize, &'a str)> {
        let t = self.tokens.get(self.pos).copied();
        self.pos += 1;
        t
    }

    /// Skips the rest of the line of the token just read.
    fn skip_line(&mut self, line: usize) {
        while self.tokens.get(self.pos).is_some_and(|&(l, _)| l == line) {
            self.pos += 1;
        }
    }

    fn peek(&self) -> Option<&'a str> {
        self.tokens.get(self.pos).map(|&(_, t)| t)
    }
}

/// Reads an ASCII STL (one or more `solid` ... `endsolid` blocks).
fn read_ascii(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    let text = String::from_utf8_lossy(bytes);
    let mut tk = Tokens::new(&text);
    let mut w = Welder::default();
    let mut triangles = Vec::new();
    let mut facets = 0usize;
    let expect = |tk: &mut Tokens, word: &str, context: &str| -> Result<usize, IoError> {
        match tk.next() {
            Some((line, t)) if t.eq_ignore_ascii_case(word) => Ok(line),
            Some((line, t)) => Err(line_err(
                path,
                line,
                format!("expected '{word}' {context}, found '{}'", shown(t)),
            )),
            None => Err(line_err(
                path,
                tk.last_line,
                format!("file ended early: expected '{word}' {context}"),
            )),
        }
    };
    let line = expect(&mut tk, "solid", "at the start of an ASCII STL")?;
    tk.skip_line(line);
    loop {
        let Some((line, t)) = tk.next() else {
            return Err(line_err(
                path,
                tk.last_line,
                format!("file ended early after {facets} facets: expected 'facet' or 'endsolid'"),
            ));
        };
        if t.eq_ignore_ascii_case("endsolid") {
            tk.skip_line(line);
            match tk.peek() {
                None => break,
                Some(_) => {
                    let line = expect(&mut tk, "solid", "after 'endsolid'")?;
                    tk.skip_line(line);
                    continue;
                }
            }
        }
        if !t.eq_ignore_ascii_case("facet") {
            return Err(line_err(
                path,
                line,
                format!("expected 'facet' or 'endsolid', found '{}'", shown(t)),
            ));
        }
        facets += 1;
        let context = format!("in facet {facets}");
        let line = expect(&mut tk, "normal", &context)?;
        coords(&mut tk, path, line, "normal")?;
        expect(&mut tk, "outer", &context)?;
        expect(&mut tk, "loop", &context)?;
        let mut poly = Vec::with_capacity(3);
        while tk.peek().is_some_and(|t| t.eq_ignore_ascii_case("vertex")) {
            let line = tk.next().map_or(0, |(l, _)| l);
            let p = coords(&mut tk, path, line, "vertex")?;
            poly.push(w.node(p));
        }
        let line = expect(
            &mut tk,
            "endloop",
            &format!("after the vertices of facet {facets}"),
        )?;
        if poly.len() < 3 {
            return Err(line_err(
                path,
                line,
                format!("facet {facets} has {} vertices, expected 3", poly.len()),
            ));
        }
        for v in poly[1..].windows(2) {
            triangles.push([poly[0], v[0], v[1]]);
        }
        expect(&mut tk, "endfacet", &context)?;
    }
    Ok(MeshFile {
        nodes: w.nodes,
        triangles,
        ..MeshFile::default()
    })
}

/// Reads three numbers that must follow on the same line as the keyword `after`.
fn coords(tk: &mut Tokens, path: &Path, line: usize, after: &str) -> Result<[f64; 3], IoError> {
    let mut p = [0.0; 3];
    for (k, c) in p.iter_mut().enumerate() {
        match tk.tokens.get(tk.pos) {
            Some(&(l, t)) if l == line => {
                tk.pos += 1;
                *c = parse_f64(t).ok_or_else(|| {
                    line_err(
                        path,
                        line,
                        format!("expected a number after '{after}', found '{}'", shown(t)),
                    )
                })?;
            }
            _ => {
                return Err(line_err(
                    path,
                    line,
                    format!("expected 3 coordinates after '{after}', found {k}"),
                ));
            }
        }
    }
    Ok(p)
}

/// Writes the triangles as binary (per `options.binary`) or ASCII STL.
pub(crate) fn write(
    file: &MeshFile,
    options: WriteOptions,
    _path: &Path,
) -> Result<Vec<u8>, Malformed> {
    surface_only(file, "STL")?;
    let corners = |t: &[u32; 3]| -> Result<[[f64; 3]; 3], Malformed> {
        let p = |i: u32| {
            file.nodes.get(i as usize).copied().ok_or_else(|| {
                format!(
                    "triangle refers to node {i}, but the mesh has {} nodes",
                    file.nodes.len()
                )
            })
        };
        Ok([p(t[0])?, p(t[1])?, p(t[2])?])
    };
    if options.binary {
        let n = u32::try_from(file.triangles.len())
            .map_err(|_| "too many triangles for STL".to_string())?;
        let mut out = Vec::with_capacity(84 + 50 * file.triangles.len());
        let mut header = b"LIBR+ binary STL, units mm".to_vec();
        header.resize(80, b' ');
        out.extend_from_slice(&header);
        out.extend_from_slice(&n.to_le_bytes());
        for t in &file.triangles {
            let [a, b, c] = corners(t)?;
            for v in [triangle_normal(a, b, c), a, b, c] {
                for x in v {
                    out.extend_from_slice(&(x as f32).to_le_bytes());
                }
            }
            out.extend_from_slice(&[0, 0]);
        }
        return Ok(out);
    }
    let mut out = String::from("solid librplus\n");
    let push3 = |out: &mut String, v: [f64; 3]| {
        for x in v {
            out.push(' ');
            push_f64(out, x);
        }
        out.push('\n');
    };
    for t in &file.triangles {
        let [a, b, c] = corners(t)?;
        out.push_str("  facet normal");
        push3(&mut out, triangle_normal(a, b, c));
        out.push_str("    outer loop\n");
        for p in [a, b, c] {
            out.push_str("      vertex");
            push3(&mut out, p);
        }
        out.push_str("    endloop\n  endfacet\n");
    }
    out.push_str("endsolid librplus\n");
    Ok(out.into_bytes())
}
