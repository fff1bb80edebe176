//! Gmsh `.msh` reader (v1, v2.x ASCII, v4.0/v4.1 ASCII) and writer (v2.2 ASCII).
//!
//! Node ids may be non-contiguous and need not start at 1: they are mapped to 0-based indices in
//! file order. Element types kept: triangles (2, and the corners of higher-order triangles 9, 20–25),
//! quadrangles (3, 10, 16; split into two triangles) and tetrahedra (4, and the corners of
//! higher-order tetrahedra 11, 29–31). Other elements (points, lines, hexahedra, ...) are counted
//! as skipped. `$NodeData` and `$ElementData` blocks become point and cell data when they cover
//! every node (every kept cell); the last block of a name wins. Other sections (`$Entities`,
//! `$PhysicalNames`, ...) are skipped. Binary `.msh` files are rejected with a clear message.

use super::common::{Malformed, capped, gather, line_err, parse_f64, push_f64, shown};
use super::{DataArray, IoError, MeshFile};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

/// Non-blank lines with 1-based numbers.
struct Lines<'a> {
    it: std::iter::Enumerate<std::str::Lines<'a>>,
    last: usize,
    /// Length of the text (bounds allocations).
    len: usize,
    path: &'a Path,
}

impl<'a> Lines<'a> {
    fn next(&mut self) -> Option<(usize, &'a str)> {
        for (i, l) in self.it.by_ref() {
            self.last = i + 1;
            let t = l.trim();
            if !t.is_empty() {
                return Some((i + 1, t));
            }
        }
        None
    }

    /// The next line, or an error saying the file ended while reading `what`.
    fn need(&mut self, what: impl FnOnce() -> String) -> Result<(usize, &'a str), IoError> {
        let last = self.last;
        self.next().ok_or_else(|| {
            line_err(
                self.path,
                last.max(1),
                format!("file ended while reading {}", what()),
            )
        })
    }

    /// Reads the end marker of a section.
    fn end(&mut self, marker: &str, after: &str) -> Result<(), IoError> {
        let (line, l) = self.need(|| format!("{marker} (after {after})"))?;
        if l.eq_ignore_ascii_case(marker) {
            Ok(())
        } else {
            Err(line_err(
                self.path,
                line,
                format!("expected {marker} after {after}, found '{}'", shown(l)),
            ))
        }
    }

    /// Skips lines up to and including `$End<name>`.
    fn skip_section(&mut self, name: &str, line: usize) -> Result<(), IoError> {
        let marker = format!("$End{name}");
        while let Some((_, l)) = self.next() {
            if l.eq_ignore_ascii_case(&marker) {
                return Ok(());
            }
        }
        Err(line_err(
            self.path,
            self.last.max(line),
            format!(
                "file ended inside the ${name} section started on line {line}: expected {marker}"
            ),
        ))
    }
}

/// Parses an integer token; `what` names the expected value.
fn int<T: std::str::FromStr>(
    tok: Option<&str>,
    path: &Path,
    line: usize,
    what: &str,
) -> Result<T, IoError> {
    match tok {
        Some(t) => t.parse().map_err(|_| {
            line_err(
                path,
                line,
                format!("expected {what} (an integer), found '{}'", shown(t)),
            )
        }),
        None => Err(line_err(
            path,
            line,
            format!("expected {what}, found end of line"),
        )),
    }
}

/// Parses a float token; `what` names the expected value.
fn float(tok: Option<&str>, path: &Path, line: usize, what: &str) -> Result<f64, IoError> {
    match tok {
        Some(t) => parse_f64(t).ok_or_else(|| {
            line_err(
                path,
                line,
                format!("expected {what} (a number), found '{}'", shown(t)),
            )
        }),
        None => Err(line_err(
            path,
            line,
            format!("expected {what}, found end of line"),
        )),
    }
}

/// File format versions.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Version {
    V1,
    V2,
    V40,
    V41,
}

/// A `$NodeData`/`$ElementData` block before it is matched to nodes or cells.
struct RawData {
    name: String,
    components: usize,
    tags: HashMap<u64, usize>,
    values: Vec<f64>,
}

/// Reader state.
#[derive(Default)]
struct Msh {
    version: Option<Version>,
    ids: HashMap<u64, u32>,
    node_tags: Vec<u64>,
    nodes: Vec<[f64; 3]>,
    tets: Vec<[u32; 4]>,
    tet_tags: Vec<u64>,
    tris: Vec<[u32; 3]>,
    tri_tags: Vec<u64>,
    skipped: usize,
    node_data: Vec<RawData>,
    elem_data: Vec<RawData>,
}

/// How an element type is kept: kind and number of nodes.
#[derive(Clone, Copy)]
enum Kind {
    Tri(usize),
    Quad(usize),
    Tet(usize),
}

fn kind(etype: u64) -> Option<Kind> {
    Some(match etype {
        2 => Kind::Tri(3),
        9 => Kind::Tri(6),
        20 => Kind::Tri(9),
        21 => Kind::Tri(10),
        22 => Kind::Tri(12),
        23 | 24 => Kind::Tri(15),
        25 => Kind::Tri(21),
        3 => Kind::Quad(4),
        10 => Kind::Quad(9),
        16 => Kind::Quad(8),
        4 => Kind::Tet(4),
        11 => Kind::Tet(10),
        29 => Kind::Tet(20),
        30 => Kind::Tet(35),
        31 => Kind::Tet(56),
        _ => return None,
    })
}

/// Reads a Gmsh file.
pub(crate) fn read(bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> {
    let text = String::from_utf8_lossy(bytes);
    let mut lines = Lines {
        it: text.lines().enumerate(),
        last: 0,
        len: text.len(),
        path,
    };
    let mut m = Msh::default();
    while let Some((line, l)) = lines.next() {
        let Some(name) = l.strip_prefix('$') else {
            return Err(line_err(
                path,
                line,
                format!(
                    "expected a section header such as $MeshFormat, $Nodes or $NOD, found '{}'",
                    shown(l)
                ),
            ));
        };
        match name {
            "MeshFormat" => m.format(&mut lines, line)?,
            "NOD" | "NOE" => {
                m.set_version(Version::V1);
                m.nodes_v1_v2(&mut lines, &format!("${name}"), &format!("$END{name}"))?;
            }
            "ELM" => {
                m.set_version(Version::V1);
                m.elements_v1_v2(&mut lines)?;
            }
            "Nodes" => match m.set_version(Version::V2) {
                Version::V40 | Version::V41 => m.nodes_v4(&mut lines)?,
                _ => m.nodes_v1_v2(&mut lines, "$Nodes", "$EndNodes")?,
            },
            "Elements" => match m.set_version(Version::V2) {
                Version::V40 | Version::V41 => m.elements_v4(&mut lines)?,
                _ => m.elements_v1_v2(&mut lines)?,
            },
            "NodeData" | "ElementData" => {
                let d = read_data(&mut lines, name)?;
                let list = if name == "NodeData" {
                    &mut m.node_data
                } else {
                    &mut m.elem_data
                };
                list.retain(|o| o.name != d.name);
                list.push(d);
            }
            _ => lines.skip_section(name, line)?,
        }
    }
    Ok(m.finish())
}

impl Msh {
    /// The version, defaulting to `v` when no `$MeshFormat` was seen.
    fn set_version(&mut self, v: Version) -> Version {
        *self.version.get_or_insert(v)
    }

    /// `$MeshFormat`: version, file type (0 = ASCII), data size.
    fn format(&mut self, lines: &mut Lines, line: usize) -> Result<(), IoError> {
        let path = lines.path;
        let (line, l) = lines.need(|| format!("the version line of $MeshFormat (line {line})"))?;
        let mut t = l.split_ascii_whitespace();
        let version = float(t.next(), path, line, "the format version (1, 2.2, 4.1)")?;
        let file_type: u32 = int(t.next(), path, line, "the file type (0 for ASCII)")?;
        if file_type != 0 {
            return Err(line_err(
                path,
                line,
                format!(
                    "binary .msh (file-type {file_type}) is not supported; re-save the mesh as ASCII \
                     (in Gmsh: File > Export, format 'Version 2 ASCII' or 'Version 4 ASCII')"
                ),
            ));
        }
        self.version = Some(if version < 3.0 {
            Version::V2
        } else if (4.0..4.05).contains(&version) {
            Version::V40
        } else if (4.05..5.0).contains(&version) {
            Version::V41
        } else {
            return Err(line_err(
                path,
                line,
                format!(
                    "Gmsh format version {version} is not supported; expected 1, 2.x, 4.0 or 4.1"
                ),
            ));
        });
        lines.end("$EndMeshFormat", "the version line")
    }

    fn add_node(&mut self, id: u64, p: [f64; 3], path: &Path, line: usize) -> Result<(), IoError> {
        let idx =
            u32::try_from(self.nodes.len()).map_err(|_| line_err(path, line, "too many nodes"))?;
        if self.ids.insert(id, idx).is_some() {
            return Err(line_err(
                path,
                line,
                format!("node id {id} is defined twice"),
            ));
        }
        self.node_tags.push(id);
        self.nodes.push(p);
        Ok(())
    }

    /// Reads `x y z` from tokens.
    fn coords<'a>(
        t: &mut impl Iterator<Item = &'a str>,
        path: &Path,
        line: usize,
        node: u64,
    ) -> Result<[f64; 3], IoError> {
        let mut p = [0.0; 3];
        for (c, axis) in p.iter_mut().zip(["x", "y", "z"]) {
            *c = float(
                t.next(),
                path,
                line,
                &format!("the {axis} coordinate of node {node}"),
            )?;
        }
        Ok(p)
    }

    /// `$NOD` (v1) or `$Nodes` (v2): count, then `id x y z` lines.
    fn nodes_v1_v2(&mut self, lines: &mut Lines, section: &str, end: &str) -> Result<(), IoError> {
        let path = lines.path;
        let (line, l) = lines.need(|| format!("the node count of the {section} section"))?;
        let n: usize = int(
            l.split_ascii_whitespace().next(),
            path,
            line,
            "the number of nodes",
        )?;
        self.nodes.reserve(capped(n, lines.len / 8));
        for k in 0..n {
            let (line, l) = lines.need(|| format!("node {} of {n} in {section} section", k + 1))?;
            let mut t = l.split_ascii_whitespace();
            let id: u64 = int(t.next(), path, line, "a node id")?;
            let p = Self::coords(&mut t, path, line, id)?;
            self.add_node(id, p, path, line)?;
        }
        lines.end(end, &format!("{n} nodes"))
    }

    /// `$Nodes` (v4.0/v4.1): entity blocks.
    fn nodes_v4(&mut self, lines: &mut Lines) -> Result<(), IoError> {
        let path = lines.path;
        let v41 = self.version == Some(Version::V41);
        let (line, l) = lines.need(|| "the header of the $Nodes section".to_string())?;
        let mut t = l.split_ascii_whitespace();
        let blocks: usize = int(t.next(), path, line, "the number of entity blocks")?;
        let total: usize = int(t.next(), path, line, "the number of nodes")?;
        self.nodes.reserve(capped(total, lines.len / 8));
        for b in 0..blocks {
            let (line, l) = lines.need(|| {
                format!(
                    "the header of node block {} of {blocks} in $Nodes section",
                    b + 1
                )
            })?;
            let mut t = l.split_ascii_whitespace();
            let what = "a node block header (entityDim entityTag parametric numNodes)";
            for _ in 0..3 {
                int::<i64>(t.next(), path, line, what)?;
            }
            let n: usize = int(t.next(), path, line, "the number of nodes in the block")?;
            if v41 {
                let mut tags = Vec::with_capacity(capped(n, 1 << 16));
                while tags.len() < n {
                    let (line, l) = lines.need(|| {
                        format!(
                            "node tag {} of {n} in block {} of $Nodes section",
                            tags.len() + 1,
                            b + 1
                        )
                    })?;
                    for tok in l.split_ascii_whitespace() {
                        tags.push(int::<u64>(Some(tok), path, line, "a node tag")?);
                    }
                }
                for (k, &id) in tags.iter().enumerate() {
                    let (line, l) = lines.need(|| {
                        format!(
                            "the coordinates of node {} of {n} in block {} of $Nodes section",
                            k + 1,
                            b + 1
                        )
                    })?;
                    let p = Self::coords(&mut l.split_ascii_whitespace(), path, line, id)?;
                    self.add_node(id, p, path, line)?;
                }
            } else {
                for k in 0..n {
                    let (line, l) = lines.need(|| {
                        format!("node {} of {n} in block {} of $Nodes section", k + 1, b + 1)
                    })?;
                    let mut t = l.split_ascii_whitespace();
                    let id: u64 = int(t.next(), path, line, "a node tag")?;
                    let p = Self::coords(&mut t, path, line, id)?;
                    self.add_node(id, p, path, line)?;
                }
            }
        }
        if self.nodes.len() != total {
            return Err(line_err(
                path,
                lines.last,
                format!(
                    "the $Nodes header declares {total} nodes, but the blocks hold {}",
                    self.nodes.len()
                ),
            ));
        }
        lines.end("$EndNodes", &format!("{blocks} node blocks"))
    }

    /// `$ELM` (v1: `num type phys elem nnodes nodes...`) or `$Elements` (v2: `num type ntags tags... nodes...`).
    fn elements_v1_v2(&mut self, lines: &mut Lines) -> Result<(), IoError> {
        let path = lines.path;
        let v1 = self.version == Some(Version::V1);
        let (section, end) = if v1 {
            ("$ELM", "$ENDELM")
        } else {
            ("$Elements", "$EndElements")
        };
        let (line, l) = lines.need(|| format!("the element count of the {section} section"))?;
        let n: usize = int(
            l.split_ascii_whitespace().next(),
            path,
            line,
            "the number of elements",
        )?;
        for k in 0..n {
            let (line, l) =
                lines.need(|| format!("element {} of {n} in {section} section", k + 1))?;
            let toks: Vec<&str> = l.split_ascii_whitespace().collect();
            let num: u64 = int(toks.first().copied(), path, line, "an element number")?;
            let etype: u64 = int(toks.get(1).copied(), path, line, "an element type")?;
            let nodes = if v1 {
                let nn: usize = int(
                    toks.get(4).copied(),
                    path,
                    line,
                    "the number of nodes of the element",
                )?;
                let rest = toks.get(5..).unwrap_or(&[]);
                if rest.len() != nn {
                    return Err(line_err(
                        path,
                        line,
                        format!("element {num} declares {nn} nodes but lists {}", rest.len()),
                    ));
                }
                rest
            } else {
                let ntags: usize = int(toks.get(2).copied(), path, line, "the number of tags")?;
                toks.get(3 + ntags.min(toks.len())..).ok_or_else(|| {
                    line_err(
                        path,
                        line,
                        format!("element {num} declares {ntags} tags but the line ends early"),
                    )
                })?
            };
            self.add_element(num, etype, nodes, path, line)?;
        }
        lines.end(end, &format!("{n} elements"))
    }

    /// `$Elements` (v4.0/v4.1): entity blocks of `tag nodes...` lines.
    fn elements_v4(&mut self, lines: &mut Lines) -> Result<(), IoError> {
        let path = lines.path;
        let (line, l) = lines.need(|| "the header of the $Elements section".to_string())?;
        let mut t = l.split_ascii_whitespace();
        let blocks: usize = int(t.next(), path, line, "the number of entity blocks")?;
        for b in 0..blocks {
            let (line, l) = lines.need(|| {
                format!(
                    "the header of element block {} of {blocks} in $Elements section",
                    b + 1
                )
            })?;
            let mut t = l.split_ascii_whitespace();
            let what = "an element block header (entityDim entityTag elementType numElements)";
            for _ in 0..2 {
                int::<i64>(t.next(), path, line, what)?;
            }
            let etype: u64 = int(t.next(), path, line, "the element type of the block")?;
            let n: usize = int(t.next(), path, line, "the number of elements in the block")?;
            for k in 0..n {
                let (line, l) = lines.need(|| {
                    format!(
                        "element {} of {n} in block {} of $Elements section",
                        k + 1,
                        b + 1
                    )
                })?;
                let toks: Vec<&str> = l.split_ascii_whitespace().collect();
                let num: u64 = int(toks.first().copied(), path, line, "an element tag")?;
                self.add_element(num, etype, toks.get(1..).unwrap_or(&[]), path, line)?;
            }
        }
        lines.end("$EndElements", &format!("{blocks} element blocks"))
    }

    /// Maps node ids and keeps or skips the element.
    fn add_element(
        &mut self,
        num: u64,
        etype: u64,
        ids: &[&str],
        path: &Path,
        line: usize,
    ) -> Result<(), IoError> {
        let mut n = Vec::with_capacity(ids.len());
        for tok in ids {
            let id: u64 = int(
                Some(tok),
                path,
                line,
                &format!("a node id in element {num}"),
            )?;
            let idx = self.ids.get(&id).ok_or_else(|| {
                line_err(path, line, format!("element {num} refers to node {id}, which is not defined in the nodes section"))
            })?;
            n.push(*idx);
        }
        let Some(k) = kind(etype) else {
            self.skipped += 1;
            return Ok(());
        };
        let (need, name) = match k {
            Kind::Tri(c) => (c, "triangle"),
            Kind::Quad(c) => (c, "quadrangle"),
            Kind::Tet(c) => (c, "tetrahedron"),
        };
        if n.len() != need {
            return Err(line_err(
                path,
                line,
                format!(
                    "element {num} of type {etype} ({name}) has {} nodes, expected {need}",
                    n.len()
                ),
            ));
        }
        match k {
            Kind::Tri(_) => {
                self.tris.push([n[0], n[1], n[2]]);
                self.tri_tags.push(num);
            }
            Kind::Quad(_) => {
                self.tris.push([n[0], n[1], n[2]]);
                self.tris.push([n[0], n[2], n[3]]);
                self.tri_tags.extend([num, num]);
            }
            Kind::Tet(_) => {
                self.tets.push([n[0], n[1], n[2], n[3]]);
                self.tet_tags.push(num);
            }
        }
        Ok(())
    }

    /// Builds the mesh, matching data blocks to nodes and kept cells.
    fn finish(self) -> MeshFile {
        let resolve = |raw: Vec<RawData>, tags: &[u64]| -> Vec<DataArray> {
            raw.into_iter()
                .filter_map(|d| {
                    let rows: Option<Vec<usize>> =
                        tags.iter().map(|t| d.tags.get(t).copied()).collect();
                    let a = DataArray::new(d.name, d.components, d.values);
                    let values = gather(&a, &rows?)?;
                    Some(DataArray::new(a.name, a.components, values))
                })
                .collect()
        };
        let point_data = resolve(self.node_data, &self.node_tags);
        let cell_tags = if self.tets.is_empty() {
            &self.tri_tags
        } else {
            &self.tet_tags
        };
        let cell_data = resolve(self.elem_data, cell_tags);
        MeshFile {
            nodes: self.nodes,
            tets: self.tets,
            triangles: self.tris,
            point_data,
            cell_data,
            skipped_cells: self.skipped,
        }
    }
}

/// Reads a `$NodeData`/`$ElementData` block: string tags (name), real tags, integer tags
/// (time step, components, count), then `tag values...` lines.
fn read_data(lines: &mut Lines, section: &str) -> Result<RawData, IoError> {
    let path = lines.path;
    let mut tag_list = |kind: &str| -> Result<Vec<(usize, &str)>, IoError> {
        let (line, l) = lines.need(|| format!("the number of {kind} tags in ${section}"))?;
        let n: usize = int(
            l.split_ascii_whitespace().next(),
            path,
            line,
            &format!("the number of {kind} tags"),
        )?;
        (0..n.min(64))
            .map(|k| lines.need(|| format!("{kind} tag {} of {n} in ${section}", k + 1)))
            .collect()
    };
    let strings = tag_list("string")?;
    let name = strings
        .first()
        .map(|(_, s)| s.trim_matches('"').to_string())
        .unwrap_or_else(|| section.to_string());
    tag_list("real")?;
    let ints = tag_list("integer")?;
    let int_tag = |i: usize, what: &str, default: usize| -> Result<usize, IoError> {
        match ints.get(i) {
            Some(&(line, l)) => int(l.split_ascii_whitespace().next(), path, line, what),
            None => Ok(default),
        }
    };
    let components = int_tag(1, "the number of components", 1)?;
    let count = int_tag(2, "the number of entries", 0)?;
    if components == 0 || components > 1024 {
        let line = ints.get(1).map_or(lines.last, |&(l, _)| l);
        return Err(line_err(
            path,
            line,
            format!("expected 1 to 1024 components in ${section}, found {components}"),
        ));
    }
    let mut d = RawData {
        name,
        components,
        tags: HashMap::new(),
        values: Vec::with_capacity(capped(count, 1 << 16) * components),
    };
    for k in 0..count {
        let (line, l) =
            lines.need(|| format!("entry {} of {count} in ${section} '{}'", k + 1, d.name))?;
        let mut t = l.split_ascii_whitespace();
        let tag: u64 = int(t.next(), path, line, "a node or element tag")?;
        for c in 0..components {
            let v = float(
                t.next(),
                path,
                line,
                &format!("value {} of {components} for tag {tag}", c + 1),
            )?;
            d.values.push(v);
        }
        d.tags.insert(tag, k);
    }
    lines.end(&format!("$End{section}"), &format!("{count} entries"))?;
    Ok(d)
}

/// Writes Gmsh v2.2 ASCII: nodes, tetrahedra (type 4), triangles (type 2), point data as
/// `$NodeData`, and cell data as `$ElementData` when the mesh has only one kind of cell.
pub(crate) fn write(file: &MeshFile) -> Result<Vec<u8>, Malformed> {
    let mut o = String::with_capacity(
        60 * file.nodes.len() + 40 * (file.tets.len() + file.triangles.len()),
    );
    o.push_str("$MeshFormat\n2.2 0 8\n$EndMeshFormat\n");
    let _ = writeln!(o, "$Nodes\n{}", file.nodes.len());
    for (i, p) in file.nodes.iter().enumerate() {
        let _ = write!(o, "{}", i + 1);
        push_xyz(&mut o, p);
    }
    o.push_str("$EndNodes\n");
    let _ = writeln!(o, "$Elements\n{}", file.tets.len() + file.triangles.len());
    let mut num = 0usize;
    for t in &file.tets {
        num += 1;
        let _ = writeln!(
            o,
            "{num} 4 2 1 1 {} {} {} {}",
            t[0] as u64 + 1,
            t[1] as u64 + 1,
            t[2] as u64 + 1,
            t[3] as u64 + 1
        );
    }
    let first_tri = num + 1;
    for t in &file.triangles {
        num += 1;
        let _ = writeln!(
            o,
            "{num} 2 2 2 2 {} {} {}",
            t[0] as u64 + 1,
            t[1] as u64 + 1,
            t[2] as u64 + 1
        );
    }
    o.push_str("$EndElements\n");
    for a in &file.point_data {
        write_data(&mut o, "NodeData", a, 1)?;
    }
    // Readers such as meshio expect `$ElementData` to cover every element, so cell data (which
    // belongs to the tetrahedra, or to the triangles when there are none) is written only when
    // the file holds one kind of element.
    let first = if file.tets.is_empty() { first_tri } else { 1 };
    let one_kind = file.tets.is_empty() || file.triangles.is_empty();
    for a in file.cell_data.iter().filter(|_| one_kind) {
        write_data(&mut o, "ElementData", a, first)?;
    }
    Ok(o.into_bytes())
}

fn push_xyz(o: &mut String, p: &[f64; 3]) {
    for &c in p {
        o.push(' ');
        push_f64(o, c);
    }
    o.push('\n');
}

/// Writes one data block whose tuples belong to tags `first`, `first + 1`, ...
fn write_data(o: &mut String, section: &str, a: &DataArray, first: usize) -> Result<(), Malformed> {
    if a.components == 0 || a.values.len() % a.components != 0 {
        return Err(Malformed(format!(
            "data array '{}' has {} values, not a multiple of {} components",
            a.name,
            a.values.len(),
            a.components
        )));
    }
    let name = a.name.replace('"', "'");
    let _ = writeln!(
        o,
        "${section}\n1\n\"{name}\"\n1\n0\n3\n0\n{}\n{}",
        a.components,
        a.len()
    );
    for (k, tuple) in a.values.chunks_exact(a.components).enumerate() {
        let _ = write!(o, "{}", first + k);
        for &v in tuple {
            o.push(' ');
            push_f64(o, v);
        }
        o.push('\n');
    }
    let _ = writeln!(o, "$End{section}");
    Ok(())
}
