//! `POLYDATA`: VTK polydata on the wire (points, four cell sections and point and cell
//! attributes), with every count and size checked against the bytes that remain. This module owns
//! [`PolyData`], [`CellArray`], the attribute types and the content encoding.

use crate::error::{TextProblem, WireError};
use crate::reader::{
    Reader, be_f32_triples, be_f32s, check_text, decode_fixed_text, u32_count, word,
};

/// Size of the `POLYDATA` content header (ten `uint32`).
pub const POLYDATA_HEADER_SIZE: usize = 40;
/// Size of one `POLYDATA` attribute header (type byte, components byte, `uint32` count).
pub const POLYDATA_ATTRIBUTE_HEADER_SIZE: usize = 6;
/// Longest `POLYDATA` attribute name, in bytes, without its terminator.
pub const MAX_ATTRIBUTE_NAME_LEN: usize = 255;

/// Cells of a `POLYDATA` section (vertices, lines, polygons or triangle strips): each cell a
/// list of point indices, stored flat.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct CellArray {
    /// End of each cell in `indices`.
    ends: Vec<usize>,
    indices: Vec<u32>,
}

impl CellArray {
    /// An empty array.
    pub fn new() -> CellArray {
        CellArray::default()
    }

    /// From a list of cells, e.g. `CellArray::from_cells([[0, 1, 2], [2, 1, 3]])`.
    pub fn from_cells<I, C>(cells: I) -> CellArray
    where
        I: IntoIterator<Item = C>,
        C: AsRef<[u32]>,
    {
        let mut array = CellArray::new();
        for cell in cells {
            array.push(cell.as_ref());
        }
        array
    }

    /// Appends a cell.
    pub fn push(&mut self, cell: &[u32]) {
        self.indices.extend_from_slice(cell);
        self.ends.push(self.indices.len());
    }

    /// Number of cells.
    pub fn len(&self) -> usize {
        self.ends.len()
    }

    /// Whether there are no cells.
    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }

    /// The point indices of cell `i`.
    pub fn get(&self, i: usize) -> Option<&[u32]> {
        let end = *self.ends.get(i)?;
        let start = if i == 0 { 0 } else { *self.ends.get(i - 1)? };
        self.indices.get(start..end)
    }

    /// The cells in order.
    pub fn iter(&self) -> impl Iterator<Item = &[u32]> + '_ {
        (0..self.len()).filter_map(move |i| self.get(i))
    }

    /// All point indices, cell after cell.
    pub fn indices(&self) -> &[u32] {
        &self.indices
    }

    /// The section's wire size in bytes: one `NINDICES` and the indices per cell.
    pub fn wire_size(&self) -> usize {
        4 * (self.ends.len() + self.indices.len())
    }
}

/// Whether an attribute belongs to points or to cells.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttributeLocation {
    /// `POINT_DATA` (type bit 4 clear).
    Point,
    /// `CELL_DATA` (type bit 4 set).
    Cell,
}

/// What an attribute holds; the number of `float32` per point or cell follows from it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AttributeKind {
    /// Scalars (type 0x00) with 1 to 127 components.
    Scalar {
        /// Components per tuple (1–127).
        components: u8,
    },
    /// Vectors (type 0x01), 3 components.
    Vector,
    /// Normals (type 0x02), 3 components.
    Normal,
    /// Tensors (type 0x03), 9 components.
    Tensor,
    /// RGBA colours (type 0x04), 4 components in \[0, 1\].
    Rgba,
}

impl AttributeKind {
    /// Components per point or cell.
    pub fn components(self) -> u8 {
        match self {
            AttributeKind::Scalar { components } => components,
            AttributeKind::Vector | AttributeKind::Normal => 3,
            AttributeKind::Tensor => 9,
            AttributeKind::Rgba => 4,
        }
    }

    fn code(self) -> u8 {
        match self {
            AttributeKind::Scalar { .. } => 0x00,
            AttributeKind::Vector => 0x01,
            AttributeKind::Normal => 0x02,
            AttributeKind::Tensor => 0x03,
            AttributeKind::Rgba => 0x04,
        }
    }
}

/// A `POLYDATA` dataset attribute (a VTK point or cell data array).
///
/// The specification does not tie the tuple count to `NPOINTS` or the number of cells, so the
/// decoder does not either: check `tuple_count()` before using the data per point or cell.
#[derive(Clone, Debug, PartialEq)]
pub struct PolyAttribute {
    /// Name (at most 255 bytes, no NUL).
    pub name: String,
    /// Point or cell data.
    pub location: AttributeLocation,
    /// Kind and number of components.
    pub kind: AttributeKind,
    /// Values, tuple after tuple: `tuple_count() * kind.components()` of them.
    pub data: Vec<f32>,
}

impl PolyAttribute {
    /// Number of tuples (points or cells) the data covers.
    pub fn tuple_count(&self) -> usize {
        self.data.len() / usize::from(self.kind.components().max(1))
    }

    /// The wire type byte: the kind in bits 0–3, bit 4 set for cell data.
    pub fn type_byte(&self) -> u8 {
        let cell = match self.location {
            AttributeLocation::Point => 0x00,
            AttributeLocation::Cell => 0x10,
        };
        cell | self.kind.code()
    }

    /// The specification's `TYPE_ATTRIBUTE` read as a big-endian `uint16`: type byte high,
    /// components low.
    pub fn type_attribute(&self) -> u16 {
        u16::from_be_bytes([self.type_byte(), self.kind.components()])
    }
}

/// `POLYDATA`: points, four cell sections and dataset attributes (VTK polydata).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PolyData {
    /// Point coordinates in millimetres.
    pub points: Vec<[f32; 3]>,
    /// Vertex cells.
    pub vertices: CellArray,
    /// Line (polyline) cells.
    pub lines: CellArray,
    /// Polygon cells.
    pub polygons: CellArray,
    /// Triangle strip cells.
    pub triangle_strips: CellArray,
    /// Point and cell data.
    pub attributes: Vec<PolyAttribute>,
}

const CELL_SECTIONS: [&str; 4] = ["VERTICES", "LINES", "POLYGONS", "TRIANGLE_STRIPS"];

impl PolyData {
    fn cell_sections(&self) -> [&CellArray; 4] {
        [
            &self.vertices,
            &self.lines,
            &self.polygons,
            &self.triangle_strips,
        ]
    }

    pub(crate) fn encode_content(&self) -> Result<Vec<u8>, WireError> {
        const S: &str = "POLYDATA";
        let npoints = u32_count(self.points.len(), S, "NPOINTS")?;
        let mut header = Vec::with_capacity(POLYDATA_HEADER_SIZE);
        header.extend_from_slice(&npoints.to_be_bytes());
        for (name, cells) in CELL_SECTIONS.iter().zip(self.cell_sections()) {
            let count = u32_count(cells.len(), S, &format!("N{name}"))?;
            let size = u32_count(cells.wire_size(), S, &format!("SIZE_{name}"))?;
            for (c, cell) in cells.iter().enumerate() {
                if let Some(index) = cell.iter().find(|&&index| index >= npoints) {
                    return Err(WireError::Value {
                        section: S,
                        field: format!("{name} cell {c}"),
                        problem: format!(
                            "has point index {index}, out of range (NPOINTS {npoints})"
                        ),
                    });
                }
            }
            header.extend_from_slice(&count.to_be_bytes());
            header.extend_from_slice(&size.to_be_bytes());
        }
        let nattributes = u32_count(self.attributes.len(), S, "NATTRIBUTES")?;
        header.extend_from_slice(&nattributes.to_be_bytes());

        let mut out = header;
        for p in &self.points {
            for v in p {
                out.extend_from_slice(&v.to_be_bytes());
            }
        }
        for cells in self.cell_sections() {
            for cell in cells.iter() {
                out.extend_from_slice(&(cell.len() as u32).to_be_bytes());
                for index in cell {
                    out.extend_from_slice(&index.to_be_bytes());
                }
            }
        }
        for (i, a) in self.attributes.iter().enumerate() {
            let components = a.kind.components();
            if let AttributeKind::Scalar {
                components: 0 | 128..,
            } = a.kind
            {
                return Err(WireError::Value {
                    section: S,
                    field: format!("attribute {i} {:?} NCOMPONENTS", a.name),
                    problem: format!("is {components}; scalars have 1 to 127 components"),
                });
            }
            if a.data.len() % usize::from(components) != 0 {
                return Err(WireError::Value {
                    section: S,
                    field: format!("attribute {i} {:?} data", a.name),
                    problem: format!(
                        "has {} values, not a multiple of its {components} components",
                        a.data.len()
                    ),
                });
            }
            let n = u32_count(a.tuple_count(), S, &format!("NATTRIBUTE_{i}"))?;
            out.push(a.type_byte());
            out.push(components);
            out.extend_from_slice(&n.to_be_bytes());
        }
        let mut names_len = 0usize;
        for (i, a) in self.attributes.iter().enumerate() {
            check_text(&a.name, MAX_ATTRIBUTE_NAME_LEN, S, || {
                format!("NAME_ATTRIBUTE_{i}")
            })?;
            out.extend_from_slice(a.name.as_bytes());
            out.push(0);
            names_len += a.name.len() + 1;
        }
        if names_len % 2 == 1 {
            out.push(0);
        }
        for a in &self.attributes {
            for v in &a.data {
                out.extend_from_slice(&v.to_be_bytes());
            }
        }
        Ok(out)
    }

    pub(crate) fn decode_content(content: &[u8]) -> Result<PolyData, WireError> {
        const S: &str = "POLYDATA";
        let mut r = Reader::new(content, S);
        let mut h = Reader::new(
            r.take(POLYDATA_HEADER_SIZE, "header (NPOINTS ... NATTRIBUTES)")?,
            S,
        );
        let npoints = h.u32("NPOINTS")?;
        let mut counts = [(0u32, 0u32); 4];
        for (count, name) in counts.iter_mut().zip(CELL_SECTIONS) {
            *count = (h.u32(name)?, h.u32(name)?);
        }
        let nattributes = h.u32("NATTRIBUTES")?;

        let point_bytes =
            r.take_declared(u64::from(npoints) * 12, || format!("NPOINTS {npoints}"))?;
        let points = be_f32_triples(point_bytes);

        let mut sections: [CellArray; 4] = Default::default();
        for ((cells, (count, size)), name) in sections.iter_mut().zip(counts).zip(CELL_SECTIONS) {
            *cells = decode_cells(&mut r, name, count, size, npoints)?;
        }
        let [vertices, lines, polygons, triangle_strips] = sections;

        let headers = r.take_declared(
            u64::from(nattributes) * POLYDATA_ATTRIBUTE_HEADER_SIZE as u64,
            || format!("NATTRIBUTES {nattributes}"),
        )?;
        let mut kinds = Vec::with_capacity(headers.len() / POLYDATA_ATTRIBUTE_HEADER_SIZE);
        for (i, header) in headers
            .chunks_exact(POLYDATA_ATTRIBUTE_HEADER_SIZE)
            .enumerate()
        {
            let mut h = Reader::new(header, S);
            let type_byte = h.u8("TYPE_ATTRIBUTE")?;
            let components = h.u8("TYPE_ATTRIBUTE")?;
            let n = h.u32("NATTRIBUTE")?;
            kinds.push((attribute_kind(i, type_byte, components)?, n));
        }

        let mut names = Vec::with_capacity(kinds.len());
        let mut names_len = 0usize;
        for i in 0..kinds.len() {
            let rest = r.rest();
            let window = &rest[..rest.len().min(MAX_ATTRIBUTE_NAME_LEN + 1)];
            let Some(len) = window.iter().position(|&b| b == 0) else {
                let problem = if rest.len() > MAX_ATTRIBUTE_NAME_LEN {
                    TextProblem::TooLongUnterminated {
                        max: MAX_ATTRIBUTE_NAME_LEN,
                    }
                } else {
                    TextProblem::Unterminated
                };
                return Err(WireError::Text {
                    section: S,
                    field: format!("NAME_ATTRIBUTE_{i}"),
                    problem,
                });
            };
            let bytes = r.take(len + 1, "NAME_ATTRIBUTE")?;
            names.push(decode_fixed_text(bytes, S, || {
                format!("NAME_ATTRIBUTE_{i}")
            })?);
            names_len += len + 1;
        }
        if names_len % 2 == 1 {
            r.take(1, "ATTRIBUTE_NAMES padding")?;
        }

        let mut attributes = Vec::with_capacity(kinds.len());
        for (i, (((location, kind), n), name)) in kinds.into_iter().zip(names).enumerate() {
            let components = kind.components();
            let bytes = r.take_declared(u64::from(n) * u64::from(components) * 4, || {
                format!("attribute {i} {name:?} NATTRIBUTE {n} x {components} components")
            })?;
            attributes.push(PolyAttribute {
                name,
                location,
                kind,
                data: be_f32s(bytes),
            });
        }
        if r.remaining() > 0 {
            let after = match attributes.len() {
                0 => "TRIANGLE_STRIPS (NATTRIBUTES 0)".to_owned(),
                n => format!("the data of attribute {}", n - 1),
            };
            return Err(WireError::Trailing {
                section: S,
                after,
                extra: r.remaining() as u64,
            });
        }
        Ok(PolyData {
            points,
            vertices,
            lines,
            polygons,
            triangle_strips,
            attributes,
        })
    }
}

fn attribute_kind(
    i: usize,
    type_byte: u8,
    components: u8,
) -> Result<(AttributeLocation, AttributeKind), WireError> {
    let value_error = |problem: String| WireError::Value {
        section: "POLYDATA",
        field: format!("attribute {i} TYPE_ATTRIBUTE 0x{type_byte:02X}{components:02X}"),
        problem,
    };
    let location = match type_byte >> 4 {
        0 => AttributeLocation::Point,
        1 => AttributeLocation::Cell,
        _ => {
            return Err(value_error(
                "has a type other than POINT_DATA (0x0_) or CELL_DATA (0x1_)".into(),
            ));
        }
    };
    let (kind, kind_name) = match type_byte & 0x0F {
        0x00 => (AttributeKind::Scalar { components }, "scalar"),
        0x01 => (AttributeKind::Vector, "vector"),
        0x02 => (AttributeKind::Normal, "normal"),
        0x03 => (AttributeKind::Tensor, "tensor"),
        0x04 => (AttributeKind::Rgba, "RGBA"),
        0x05 => {
            return Err(value_error(
                "is texture coordinates (0x05), which the specification does not define".into(),
            ));
        }
        other => {
            return Err(value_error(format!(
                "has unknown attribute type 0x{other:02X}"
            )));
        }
    };
    let (fits, allowed) = match kind {
        AttributeKind::Scalar { .. } => ((1..=127).contains(&components), "1 to 127".to_owned()),
        other => (
            other.components() == components,
            other.components().to_string(),
        ),
    };
    if !fits {
        let hint = if components == 9 {
            " (the reference C library writes 9 for cell and RGBA attributes, OpenIGTLink issue #36)"
        } else {
            ""
        };
        return Err(value_error(format!(
            "has {components} components where a {kind_name} has {allowed}{hint}"
        )));
    }
    Ok((location, kind))
}

fn decode_cells(
    r: &mut Reader<'_>,
    name: &str,
    count: u32,
    size: u32,
    npoints: u32,
) -> Result<CellArray, WireError> {
    const S: &str = "POLYDATA";
    if size % 4 != 0 {
        return Err(WireError::Value {
            section: S,
            field: format!("SIZE_{name}"),
            problem: format!("is {size}, not a multiple of 4 (uint32 indices)"),
        });
    }
    let bytes = r.take_declared(u64::from(size), || format!("SIZE_{name}"))?;
    let words: Vec<u32> = bytes
        .chunks_exact(4)
        .map(|w| u32::from_be_bytes(word(w)))
        .collect();
    let mut cells = CellArray {
        ends: Vec::with_capacity((count as usize).min(words.len())),
        indices: Vec::with_capacity(words.len()),
    };
    let mut at = 0usize;
    for c in 0..count {
        let Some(&nindices) = words.get(at) else {
            return Err(WireError::Value {
                section: S,
                field: format!("N{name}"),
                problem: format!("is {count} but SIZE_{name} ({size} bytes) holds only {c} cells"),
            });
        };
        at += 1;
        let left = words.len() - at;
        let cell = usize::try_from(nindices)
            .ok()
            .and_then(|n| words.get(at..at.checked_add(n)?))
            .ok_or_else(|| WireError::CountMismatch {
                section: S,
                field: format!("{name} cell {c} NINDICES {nindices}"),
                declared: u64::from(nindices) * 4,
                remaining: left as u64 * 4,
            })?;
        at += cell.len();
        for &index in cell {
            if index >= npoints {
                return Err(WireError::Value {
                    section: S,
                    field: format!("{name} cell {c}"),
                    problem: format!("has point index {index}, out of range (NPOINTS {npoints})"),
                });
            }
            cells.indices.push(index);
        }
        cells.ends.push(cells.indices.len());
    }
    if at != words.len() {
        return Err(WireError::Value {
            section: S,
            field: format!("SIZE_{name}"),
            problem: format!(
                "is {size} bytes but its N{name} {count} cells use {}",
                at * 4
            ),
        });
    }
    Ok(cells)
}
