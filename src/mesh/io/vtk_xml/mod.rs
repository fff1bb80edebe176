//! VTK XML reader and writer: `.vtu` (UnstructuredGrid) and `.vtp` (PolyData).
//!
//! Reads `DataArray`s in `format="ascii"`, `"binary"` (base64; `header_type` UInt32 or UInt64;
//! `byte_order` LittleEndian or BigEndian; optionally `compressor="vtkZLibDataCompressor"`) and
//! `"appended"` (the `AppendedData` section with `encoding="raw"` or `"base64"`), for the types
//! Int8–Int64, UInt8–UInt64, Float32 and Float64. Base64 text may be one stream for header and
//! data or separately padded pieces (as VTK writes compressed arrays); both decode the same.
//!
//! UnstructuredGrid cells: tetrahedra (10, and the corners of quadratic tetrahedra 24) are kept,
//! triangles (5, 22) kept, quads (9, 23, 28), pixels (8), polygons (7) and strips (6) become
//! triangles; other types are counted as skipped. PolyData: `Polys` and `Strips` become
//! triangles, `Verts` and `Lines` are counted as skipped. Cell data follow the kept cells.
//!
//! Writes version 1.0 with `header_type="UInt64"`, little-endian, ascii or base64 binary: Float64
//! points and data, Int64 connectivity and offsets, UInt8 types.

mod pvd;
mod write;

use crate::mesh::io::common::{
    CellCollector, DType, Malformed, capped, line_err, offset_err, push_f64, shown, split_cells,
    surface_only, to_index, to_indices,
};
use crate::mesh::io::{DataArray, IoError, MeshFile, WriteOptions};
use base64::Engine as _;
use base64::alphabet;
use base64::engine::{DecodePaddingMode, GeneralPurpose, GeneralPurposeConfig};
pub use pvd::{PvdEntry, pvd_collection, read_pvd};
use quick_xml::events::{BytesStart, Event};
use std::io::Read as _;
use std::path::Path;
pub(crate) use write::{write_vtp, write_vtu};

/// Lenient base64: padding optional, non-zero trailing bits accepted.
const B64: GeneralPurpose = GeneralPurpose::new(
    &alphabet::STANDARD,
    GeneralPurposeConfig::new()
        .with_decode_padding_mode(DecodePaddingMode::Indifferent)
        .with_decode_allow_trailing_bits(true),
);

/// Deepest element nesting accepted (VTK files nest about six levels).
const MAX_DEPTH: usize = 64;

/// An XML element with its attributes, text (kept for `DataArray` only) and children.
#[derive(Debug, Default)]
struct El {
    name: String,
    attrs: Vec<(String, String)>,
    text: Vec<u8>,
    children: Vec<El>,
    pos: usize,
}

impl El {
    fn attr(&self, key: &str) -> Option<&str> {
        self.attrs
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.as_str())
    }

    fn child(&self, name: &str) -> Option<&El> {
        self.children.iter().find(|c| c.name == name)
    }

    fn children<'s>(&'s self, name: &'s str) -> impl Iterator<Item = &'s El> + 's {
        self.children.iter().filter(move |c| c.name == name)
    }

    /// The `DataArray` child with this `Name`.
    fn named_array(&self, name: &str) -> Option<&El> {
        self.children("DataArray")
            .find(|c| c.attr("Name") == Some(name))
    }
}

/// 1-based line of a byte offset.
fn line_of(bytes: &[u8], pos: usize) -> usize {
    1 + bytes[..pos.min(bytes.len())]
        .iter()
        .filter(|&&b| b == b'\n')
        .count()
}

/// Builds an element from a start tag.
fn element(e: &BytesStart, pos: usize, bytes: &[u8], path: &Path) -> Result<El, IoError> {
    let mut el = El {
        name: String::from_utf8_lossy(e.local_name().as_ref()).into_owned(),
        pos,
        ..El::default()
    };
    for a in e.attributes() {
        let a = a.map_err(|err| {
            line_err(
                path,
                line_of(bytes, pos),
                format!("malformed attribute in <{}>: {err}", el.name),
            )
        })?;
        let key = String::from_utf8_lossy(a.key.local_name().as_ref()).into_owned();
        let value = a
            .unescape_value()
            .map_err(|err| {
                line_err(
                    path,
                    line_of(bytes, pos),
                    format!("malformed attribute '{key}': {err}"),
                )
            })?
            .into_owned();
        el.attrs.push((key, value));
    }
    Ok(el)
}

/// Parses the XML part of the file into a tree under a synthetic document element.
fn parse_xml(xml: &[u8], path: &Path) -> Result<El, IoError> {
    let mut reader = quick_xml::Reader::from_reader(xml);
    let mut stack = vec![El::default()];
    loop {
        let pos = reader.buffer_position() as usize;
        let event = reader.read_event().map_err(|e| {
            let at = reader.error_position() as usize;
            line_err(path, line_of(xml, at), format!("malformed XML: {e}"))
        })?;
        match event {
            Event::Start(e) => {
                if stack.len() > MAX_DEPTH {
                    return Err(line_err(
                        path,
                        line_of(xml, pos),
                        "XML elements nested too deeply",
                    ));
                }
                stack.push(element(&e, pos, xml, path)?);
            }
            Event::Empty(e) => {
                let el = element(&e, pos, xml, path)?;
                if let Some(top) = stack.last_mut() {
                    top.children.push(el);
                }
            }
            Event::End(_) => close(&mut stack),
            Event::Text(t) => push_text(&mut stack, &t),
            Event::CData(t) => push_text(&mut stack, &t),
            Event::Eof => break,
            _ => {}
        }
    }
    while stack.len() > 1 {
        close(&mut stack);
    }
    Ok(stack.pop().unwrap_or_default())
}

fn close(stack: &mut Vec<El>) {
    if stack.len() > 1 {
        if let Some(el) = stack.pop() {
            if let Some(top) = stack.last_mut() {
                top.children.push(el);
            }
        }
    }
}

fn push_text(stack: &mut [El], t: &[u8]) {
    if let Some(top) = stack.last_mut().filter(|e| e.name == "DataArray") {
        top.text.extend_from_slice(t);
    }
}

/// Decodes base64 text that may be several separately padded streams, ignoring whitespace.
fn b64_decode(text: &[u8]) -> Result<Vec<u8>, Malformed> {
    let clean: Vec<u8> = text
        .iter()
        .filter(|c| !c.is_ascii_whitespace())
        .copied()
        .collect();
    let mut out = Vec::with_capacity(clean.len() / 4 * 3 + 3);
    let mut rest = &clean[..];
    let mut at = 0usize;
    while !rest.is_empty() {
        let end = match rest.iter().position(|&c| c == b'=') {
            Some(p) => p + rest[p..].iter().take_while(|&&c| c == b'=').count(),
            None => rest.len(),
        };
        B64.decode_vec(&rest[..end], &mut out)
            .map_err(|e| format!("invalid base64 at character {}: {e}", at))?;
        at += end;
        rest = &rest[end..];
    }
    Ok(out)
}

/// The appended-data section.
struct Appended<'a> {
    base64: bool,
    data: &'a [u8],
    /// File offset of `data`.
    start: usize,
    /// Sorted array offsets (to find where a base64 block ends).
    offsets: Vec<usize>,
}

/// Splits the file at `<AppendedData`: the XML before it and the data after the `_` marker.
fn split_appended<'a>(
    bytes: &'a [u8],
    path: &Path,
) -> Result<(&'a [u8], Option<Appended<'a>>), IoError> {
    const TAG: &[u8] = b"<AppendedData";
    let Some(p) = bytes.windows(TAG.len()).position(|w| w == TAG) else {
        return Ok((bytes, None));
    };
    let gt = bytes[p..]
        .iter()
        .position(|&c| c == b'>')
        .map(|g| p + g)
        .ok_or_else(|| offset_err(path, p, "file ended inside the <AppendedData> tag"))?;
    let tag = parse_xml(&bytes[p..=gt], path)?;
    let encoding = tag
        .child("AppendedData")
        .and_then(|t| t.attr("encoding"))
        .unwrap_or("raw")
        .to_string();
    let base64 = match encoding.as_str() {
        "raw" => false,
        "base64" => true,
        other => {
            return Err(line_err(
                path,
                line_of(bytes, p),
                format!(
                    "AppendedData encoding '{}' is not supported: expected raw or base64",
                    shown(other)
                ),
            ));
        }
    };
    let mut u = gt + 1;
    while bytes.get(u).is_some_and(|c| c.is_ascii_whitespace()) {
        u += 1;
    }
    if bytes.get(u) != Some(&b'_') {
        return Err(offset_err(
            path,
            u,
            "expected '_' at the start of the AppendedData content",
        ));
    }
    let start = u + 1;
    let mut data = &bytes[start..];
    if base64 {
        const END: &[u8] = b"</AppendedData";
        if let Some(e) = data.windows(END.len()).position(|w| w == END) {
            data = &data[..e];
        }
        data = data.trim_ascii_end();
    }
    Ok((
        &bytes[..p],
        Some(Appended {
            base64,
            data,
            start,
            offsets: Vec::new(),
        }),
    ))
}

/// File-wide decoding settings.
struct Ctx<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    big_endian: bool,
    header64: bool,
    compressed: bool,
    appended: Option<Appended<'a>>,
}

impl Ctx<'_> {
    fn err(&self, el: &El, msg: impl Into<String>) -> IoError {
        line_err(self.path, line_of(self.bytes, el.pos), msg)
    }

    /// Reads header value `i` (UInt32 or UInt64).
    fn header(&self, b: &[u8], i: usize) -> Result<usize, Malformed> {
        let h = if self.header64 { 8 } else { 4 };
        let Some(s) = i.checked_mul(h).and_then(|a| b.get(a..a + h)) else {
            return Err(Malformed(format!(
                "data ended in the {}-byte block header (value {} needs bytes up to {}, have {})",
                h,
                i + 1,
                (i as u128 + 1) * h as u128,
                b.len()
            )));
        };
        let v = match (s.len(), self.big_endian) {
            (8, false) => u64::from_le_bytes(std::array::from_fn(|i| s[i])),
            (8, true) => u64::from_be_bytes(std::array::from_fn(|i| s[i])),
            (_, false) => u32::from_le_bytes(std::array::from_fn(|i| s[i])) as u64,
            (_, true) => u32::from_be_bytes(std::array::from_fn(|i| s[i])) as u64,
        };
        usize::try_from(v).map_err(|_| Malformed(format!("block header value {v} is too large")))
    }

    /// Decodes header + data bytes (uncompressed or zlib blocks) into values.
    fn unpack(&self, b: &[u8], dtype: DType) -> Result<Vec<f64>, Malformed> {
        let h = if self.header64 { 8 } else { 4 };
        let raw: std::borrow::Cow<[u8]> = if !self.compressed {
            let n = self.header(b, 0)?;
            let data = b.get(h..).unwrap_or(&[]);
            match data.get(..n) {
                Some(d) => d.into(),
                None => {
                    return Err(Malformed(format!(
                        "the header declares {n} bytes of data, but only {} follow",
                        data.len()
                    )));
                }
            }
        } else {
            self.inflate(b)?.into()
        };
        if raw.len() % dtype.size() != 0 {
            return Err(Malformed(format!(
                "{} bytes of data is not a whole number of {}-byte values",
                raw.len(),
                dtype.size()
            )));
        }
        let mut out = Vec::new();
        dtype.decode(&raw, self.big_endian, &mut out);
        Ok(out)
    }

    /// Inflates zlib-compressed blocks: header `nblocks, blocksize, lastblocksize, sizes...`.
    fn inflate(&self, b: &[u8]) -> Result<Vec<u8>, Malformed> {
        let h = if self.header64 { 8 } else { 4 };
        let nblocks = self.header(b, 0)?;
        let block = self.header(b, 1)?;
        let last = self.header(b, 2)?;
        if nblocks > b.len() / h {
            return Err(Malformed(format!(
                "the compression header declares {nblocks} blocks, more than the data can hold"
            )));
        }
        let mut at = h * (3 + nblocks);
        let mut out = Vec::new();
        for i in 0..nblocks {
            let size = self.header(b, 3 + i)?;
            let Some(comp) = at.checked_add(size).and_then(|e| b.get(at..e)) else {
                return Err(Malformed(format!(
                    "data ended in compressed block {} of {nblocks} ({size} bytes declared, {} available)",
                    i + 1,
                    b.len().saturating_sub(at)
                )));
            };
            let expect = if i + 1 == nblocks && last != 0 {
                last
            } else {
                block
            };
            let before = out.len();
            flate2::read::ZlibDecoder::new(comp)
                .take(expect as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| format!("compressed block {} of {nblocks}: {e}", i + 1))?;
            if out.len() - before != expect {
                return Err(Malformed(format!(
                    "compressed block {} of {nblocks} inflates to {} bytes, expected {expect}",
                    i + 1,
                    out.len() - before
                )));
            }
            at += size;
        }
        Ok(out)
    }

    /// Reads the values of an appended array at `offset`.
    fn appended(&self, el: &El, label: &str, dtype: DType) -> Result<Vec<f64>, IoError> {
        let Some(app) = &self.appended else {
            return Err(self.err(
                el,
                format!(
                    "{label} has format=\"appended\" but the file has no <AppendedData> section"
                ),
            ));
        };
        let off_text = el.attr("offset").unwrap_or("");
        let offset: usize = off_text.trim().parse().map_err(|_| {
            self.err(
                el,
                format!(
                    "{label}: expected an integer offset attribute, found '{}'",
                    shown(off_text)
                ),
            )
        })?;
        let file_off = app.start.saturating_add(offset);
        let Some(rest) = app.data.get(offset..) else {
            return Err(offset_err(
                self.path,
                file_off,
                format!(
                    "{label}: appended offset {offset} is past the end of the appended data ({} bytes)",
                    app.data.len()
                ),
            ));
        };
        let result = if app.base64 {
            let end = app
                .offsets
                .iter()
                .find(|&&o| o > offset)
                .map_or(rest.len(), |&o| (o - offset).min(rest.len()));
            b64_decode(&rest[..end]).and_then(|raw| self.unpack(&raw, dtype))
        } else {
            self.unpack(rest, dtype)
        };
        result.map_err(|m| offset_err(self.path, file_off, format!("{label} (appended data): {m}")))
    }

    /// Reads a `DataArray`, checking the tuple count when one is expected.
    fn array(&self, el: &El, expected: Option<usize>) -> Result<DataArray, IoError> {
        let name = el.attr("Name").unwrap_or("").to_string();
        let label = format!("DataArray '{}'", shown(&name));
        let tname = el
            .attr("type")
            .ok_or_else(|| self.err(el, format!("{label} has no type attribute")))?;
        let dtype = DType::from_xml(tname).ok_or_else(|| {
            self.err(el, format!("{label} has type '{}': expected Int8..Int64, UInt8..UInt64, Float32 or Float64", shown(tname)))
        })?;
        let comps = match el.attr("NumberOfComponents") {
            None => 1,
            Some(s) => s
                .trim()
                .parse::<usize>()
                .ok()
                .filter(|c| (1..=4096).contains(c))
                .ok_or_else(|| {
                    self.err(
                        el,
                        format!(
                            "{label}: NumberOfComponents '{}' is not between 1 and 4096",
                            shown(s)
                        ),
                    )
                })?,
        };
        let values = match el.attr("format").unwrap_or("ascii") {
            "ascii" => self.ascii(el, &label)?,
            "binary" => b64_decode(&el.text)
                .and_then(|raw| self.unpack(&raw, dtype))
                .map_err(|m| self.err(el, format!("{label} (binary): {m}")))?,
            "appended" => self.appended(el, &label, dtype)?,
            other => {
                return Err(self.err(
                    el,
                    format!(
                        "{label}: format '{}' is not one of ascii, binary, appended",
                        shown(other)
                    ),
                ));
            }
        };
        if values.len() % comps != 0 {
            return Err(self.err(
                el,
                format!(
                    "{label} has {} values, not a multiple of its {comps} components",
                    values.len()
                ),
            ));
        }
        if let Some(n) = expected {
            if n.checked_mul(comps) != Some(values.len()) {
                return Err(self.err(
                    el,
                    format!("{label} has {} tuples, expected {n}", values.len() / comps),
                ));
            }
        }
        Ok(DataArray::new(name, comps, values))
    }

    fn ascii(&self, el: &El, label: &str) -> Result<Vec<f64>, IoError> {
        let mut out = Vec::with_capacity(capped(el.text.len() / 2, usize::MAX));
        for (k, t) in el
            .text
            .split(|c| c.is_ascii_whitespace())
            .filter(|t| !t.is_empty())
            .enumerate()
        {
            let v = std::str::from_utf8(t)
                .ok()
                .and_then(|s| s.parse::<f64>().ok());
            out.push(v.ok_or_else(|| {
                self.err(
                    el,
                    format!(
                        "{label}: expected a number (value {}), found '{}'",
                        k + 1,
                        shown(&String::from_utf8_lossy(t))
                    ),
                )
            })?);
        }
        Ok(out)
    }

    /// Reads a `DataArray` named `name` from `section` as node indices.
    fn indices(
        &self,
        section: &El,
        name: &str,
        expected: Option<usize>,
    ) -> Result<Vec<f64>, IoError> {
        let el = section.named_array(name).ok_or_else(|| {
            self.err(
                section,
                format!("<{}> has no DataArray named '{name}'", section.name),
            )
        })?;
        Ok(self.array(el, expected)?.values)
    }

    /// Point data or cell data arrays with `n` tuples each (String arrays are skipped).
    fn data(&self, piece: &El, section: &str, n: usize) -> Result<Vec<DataArray>, IoError> {
        let Some(sec) = piece.child(section) else {
            return Ok(Vec::new());
        };
        sec.children("DataArray")
            .filter(|a| a.attr("type") != Some("String"))
            .map(|a| self.array(a, Some(n)))
            .collect()
    }

    fn count(&self, el: &El, key: &str, required: bool) -> Result<usize, IoError> {
        match el.attr(key) {
            None if !required => Ok(0),
            None => Err(self.err(el, format!("<{}> has no {key} attribute", el.name))),
            Some(s) => s.trim().parse().map_err(|_| {
                self.err(
                    el,
                    format!(
                        "{key} of <{}> is '{}', expected a non-negative integer",
                        el.name,
                        shown(s)
                    ),
                )
            }),
        }
    }

    fn points(&self, piece: &El, n: usize) -> Result<Vec<[f64; 3]>, IoError> {
        let Some(el) = piece.child("Points").and_then(|p| p.child("DataArray")) else {
            if n == 0 {
                return Ok(Vec::new());
            }
            return Err(self.err(piece, "<Piece> has no <Points> DataArray"));
        };
        let a = self.array(el, Some(n))?;
        if a.components != 3 {
            return Err(self.err(
                el,
                format!(
                    "Points DataArray has {} components, expected 3",
                    a.components
                ),
            ));
        }
        Ok(a.values
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect())
    }
}

/// Collects `offset` attributes of appended arrays (sorted) for base64 block ends.
fn collect_offsets(el: &El, out: &mut Vec<usize>) {
    if el.attr("format") == Some("appended") {
        if let Some(o) = el.attr("offset").and_then(|s| s.trim().parse().ok()) {
            out.push(o);
        }
    }
    for c in &el.children {
        collect_offsets(c, out);
    }
}

/// Reads a `.vtu` or `.vtp` file.
pub(crate) fn read(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    let (xml, mut appended) = split_appended(bytes, path)?;
    let root = parse_xml(xml, path)?;
    let Some(vtk) = root.child("VTKFile") else {
        return Err(line_err(path, 1, "expected a <VTKFile> root element"));
    };
    if let Some(app) = &mut appended {
        collect_offsets(vtk, &mut app.offsets);
        app.offsets.sort_unstable();
    }
    let bad = |key: &str, v: &str, want: &str| {
        line_err(
            path,
            line_of(bytes, vtk.pos),
            format!(
                "VTKFile {key} '{}' is not supported: expected {want}",
                shown(v)
            ),
        )
    };
    let big_endian = match vtk.attr("byte_order").unwrap_or("LittleEndian") {
        "LittleEndian" => false,
        "BigEndian" => true,
        v => return Err(bad("byte_order", v, "LittleEndian or BigEndian")),
    };
    let header64 = match vtk.attr("header_type").unwrap_or("UInt32") {
        "UInt32" => false,
        "UInt64" => true,
        v => return Err(bad("header_type", v, "UInt32 or UInt64")),
    };
    let compressed = match vtk.attr("compressor") {
        None | Some("") => false,
        Some("vtkZLibDataCompressor") => true,
        Some(v) => return Err(bad("compressor", v, "vtkZLibDataCompressor (or none)")),
    };
    let ctx = Ctx {
        path,
        bytes,
        big_endian,
        header64,
        compressed,
        appended,
    };
    let kind = vtk.attr("type").unwrap_or("");
    if kind != "UnstructuredGrid" && kind != "PolyData" {
        return Err(bad("type", kind, "UnstructuredGrid or PolyData"));
    }
    let grid = vtk.child(kind).ok_or_else(|| {
        ctx.err(
            vtk,
            format!("<VTKFile type=\"{kind}\"> has no <{kind}> element"),
        )
    })?;
    let pieces: Vec<&El> = grid.children("Piece").collect();
    let [piece] = pieces[..] else {
        return Err(ctx.err(
            grid,
            format!("expected exactly one <Piece>, found {}", pieces.len()),
        ));
    };
    if kind == "UnstructuredGrid" {
        read_vtu(&ctx, piece)
    } else {
        read_vtp(&ctx, piece)
    }
}

fn read_vtu(ctx: &Ctx, piece: &El) -> Result<MeshFile, IoError> {
    let np = ctx.count(piece, "NumberOfPoints", true)?;
    let nc = ctx.count(piece, "NumberOfCells", true)?;
    let nodes = ctx.points(piece, np)?;
    let mut cc = CellCollector::default();
    if nc > 0 {
        let cells = piece.child("Cells").ok_or_else(|| {
            ctx.err(
                piece,
                format!("<Piece> declares {nc} cells but has no <Cells>"),
            )
        })?;
        let conn = to_indices(&ctx.indices(cells, "connectivity", None)?, "connectivity")
            .map_err(|m| ctx.err(cells, m))?;
        let offsets = ctx.indices(cells, "offsets", Some(nc))?;
        let types = ctx.indices(cells, "types", Some(nc))?;
        let split = split_cells(&offsets, &conn).map_err(|m| ctx.err(cells, m))?;
        for (i, (cell, &t)) in split.iter().zip(&types).enumerate() {
            let t = to_index(t)
                .and_then(|t| u8::try_from(t).ok())
                .ok_or_else(|| {
                    ctx.err(
                        cells,
                        format!("types value {i} is {t}, not a VTK cell type"),
                    )
                })?;
            cc.add_vtk(t, cell, i).map_err(|m| ctx.err(cells, m))?;
        }
    }
    let pd = ctx.data(piece, "PointData", np)?;
    let cd = ctx.data(piece, "CellData", nc)?;
    Ok(cc.finish(nodes, pd, cd))
}

fn read_vtp(ctx: &Ctx, piece: &El) -> Result<MeshFile, IoError> {
    let np = ctx.count(piece, "NumberOfPoints", true)?;
    let nodes = ctx.points(piece, np)?;
    let mut cc = CellCollector::default();
    let mut src = 0usize;
    for (section, key) in [
        ("Verts", "NumberOfVerts"),
        ("Lines", "NumberOfLines"),
        ("Polys", "NumberOfPolys"),
        ("Strips", "NumberOfStrips"),
    ] {
        let n = ctx.count(piece, key, false)?;
        if n == 0 {
            continue;
        }
        let sec = piece.child(section).ok_or_else(|| {
            ctx.err(
                piece,
                format!("<Piece> declares {key}=\"{n}\" but has no <{section}>"),
            )
        })?;
        let conn = to_indices(&ctx.indices(sec, "connectivity", None)?, "connectivity")
            .map_err(|m| ctx.err(sec, m))?;
        let offsets = ctx.indices(sec, "offsets", Some(n))?;
        for cell in split_cells(&offsets, &conn).map_err(|m| ctx.err(sec, m))? {
            match section {
                "Polys" => cc.add_polygon(cell, src),
                "Strips" => cc.add_strip(cell, src),
                _ => cc.skip(),
            }
            src += 1;
        }
    }
    let pd = ctx.data(piece, "PointData", np)?;
    let cd = ctx.data(piece, "CellData", src)?;
    Ok(cc.finish(nodes, pd, cd))
}
