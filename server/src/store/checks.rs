//! The checks an upload passes before it is stored ([`check`]: its form, then [`validate`]:
//! every check preload makes short of the LIBR basis), and the content's version (SHA-256).

use super::{MeshSource, ORGAN_MM, Upload, unit};
use crate::error::{Internal, ServiceError};
use librplus::mesh::io::{self, Format, MeshFile, Unit};
use librplus::mesh::{MeshError, TetMesh};
use librplus::register::physics::Physics;
use std::path::Path;

/// The tetrahedralisation edge of a surface mesh, mm (as preload's: the paper preset's).
const EDGE_MM: f64 = 7.6;

/// What the checks made of an upload: the mesh file to store (its name and bytes) and its size.
#[derive(Debug)]
pub struct Checked {
    /// File name in the case folder (`mesh.vtu`, ...).
    pub mesh_name: String,
    /// Its bytes.
    pub mesh_bytes: Vec<u8>,
    /// Nodes.
    pub nodes: usize,
    /// Tets.
    pub tets: usize,
    /// The content's SHA-256 (hex): the case version.
    pub version: String,
}

/// An INVALID_ARGUMENT naming field `f` and problem `p`.
pub(super) fn field(f: impl Into<String>, p: impl Into<String>) -> ServiceError {
    ServiceError::field(f, p)
}

/// Checks an upload: its form (unit, format, arrays: finite nodes, indices in range), the node
/// limit (`max_nodes`), then [`validate`]. Errors are INVALID_ARGUMENT naming the field (and
/// the tet or node), or RESOURCE_EXHAUSTED for the node limit.
pub fn check(u: &Upload, max_nodes: usize) -> Result<Checked, ServiceError> {
    let unit = unit(&u.unit).map_err(|e| field("upload.mesh_unit", e.to_string()))?;
    let arrays = matches!(u.mesh, MeshSource::Arrays { .. });
    if arrays && unit != Unit::Mm {
        return Err(field(
            "upload.mesh_unit",
            format!(
                "{:?} with nodes_mm: the arrays are millimetres; leave mesh_unit empty (or send the mesh as a file in its unit)",
                u.unit
            ),
        ));
    }
    let (mesh_name, mesh_bytes, file) = match &u.mesh {
        MeshSource::File { bytes, format } => {
            let (fmt, ext) = match format.as_str() {
                "vtu" => (Format::Vtu, "vtu"),
                "vtk" => (Format::VtkLegacy, "vtk"),
                "msh" => (Format::Msh, "msh"),
                f => {
                    return Err(field(
                        "upload.mesh_format",
                        format!("{f:?}: expected vtu, vtk or msh (a tetrahedral mesh)"),
                    ));
                }
            };
            let name = format!("mesh.{ext}");
            let file = io::read_bytes(bytes, fmt, Path::new(&name), unit)
                .map_err(|e| field("mesh", e.to_string()))?;
            (name, bytes.clone(), file)
        }
        MeshSource::Arrays { nodes, tets } => {
            if nodes.len() % 3 != 0 {
                return Err(field(
                    "upload.nodes_mm",
                    format!("{} values: not 3 per node", nodes.len()),
                ));
            }
            if tets.len() % 4 != 0 {
                return Err(field(
                    "upload.tets",
                    format!("{} values: not 4 per tet", tets.len()),
                ));
            }
            if let Some(i) = nodes.iter().position(|x| !x.is_finite()) {
                return Err(field(
                    format!("upload.nodes_mm[{i}]"),
                    format!("{} is not finite (node {})", nodes[i], i / 3),
                ));
            }
            let n = nodes.len() / 3;
            if let Some(i) = tets.iter().position(|&v| v as usize >= n) {
                return Err(field(
                    format!("upload.tets[{i}]"),
                    format!(
                        "node {} of tet {} is out of range ({n} nodes)",
                        tets[i],
                        i / 4
                    ),
                ));
            }
            let file = MeshFile {
                nodes: nodes.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect(),
                tets: tets
                    .chunks_exact(4)
                    .map(|c| [c[0], c[1], c[2], c[3]])
                    .collect(),
                ..Default::default()
            };
            let bytes = io::write_bytes(
                &file,
                Format::Vtu,
                io::WriteOptions::default(),
                Path::new("mesh.vtu"),
            )
            .map_err(Internal::MeshWrite)?;
            ("mesh.vtu".to_string(), bytes, file)
        }
    };
    if file.nodes.len() > max_nodes {
        return Err(ServiceError::Quota {
            message: format!(
                "mesh: {} nodes, above the server's limit of {max_nodes}",
                file.nodes.len()
            ),
            subject: "case_nodes",
            description: format!("at most {max_nodes} nodes per case"),
        });
    }
    let (nodes, tets) = validate(&Content {
        file: &file,
        unit,
        unit_name: &u.unit,
        arrays,
        vessels: u.vessels.as_deref(),
        physics: u.physics.as_deref(),
    })?;
    Ok(Checked {
        version: version(u, &mesh_name, &mesh_bytes),
        mesh_name,
        mesh_bytes,
        nodes,
        tets,
    })
}

/// A case's content as [`validate`] reads it.
#[derive(Debug, Clone, Copy)]
pub struct Content<'a> {
    /// The mesh, read (mm).
    pub file: &'a MeshFile,
    /// The unit it was read in.
    pub unit: Unit,
    /// The unit as declared (`upload.mesh_unit`; "" is mm).
    pub unit_name: &'a str,
    /// Whether the mesh came as `nodes_mm`/`tets` arrays (errors name those fields).
    pub arrays: bool,
    /// Vessel centerlines (.vtp bytes).
    pub vessels: Option<&'a [u8]>,
    /// `physics.json` bytes.
    pub physics: Option<&'a [u8]>,
}

/// The checks a case passes before it is stored (and, for a case stored with older checks,
/// before it is loaded at start): every check preload makes short of building the LIBR basis,
/// through the functions preload uses. In order:
///
/// 1. tetrahedra (a surface is not a case);
/// 2. the organ's size: the largest side of the bounding box, in mm after the unit, within
///    [`ORGAN_MM`] (else the error names the unit and the one that fits);
/// 3. the tets: none degenerate, one orientation throughout (a mesh entirely negative is flipped
///    as preload does; a mixed one is tangled), every node in a tet (preload's elasticity
///    model has no stiffness at a free node), no two nodes at one position (a tet on a copy of a
///    node: a crack inside the mesh), no tet twice (the same 4 nodes in any order), a manifold
///    boundary;
/// 4. the vessels file reads;
/// 5. the preoperative model preload builds (labels from the file's `region` arrays or from the
///    geometry) and its correspondence structures;
/// 6. `physics.json` through preload's parser (format, kinds, parameters and ranges) and the
///    augmented model's fit check ([`librplus::register::physics::model::check_fits`]: no kind
///    it does not carry, such as `nonlinear`; a pack within reach of the surface; supports
///    attached).
///
/// Errors are INVALID_ARGUMENT naming the field (`upload.mesh_unit`, `upload.nodes_mm`,
/// `upload.tets`, `mesh`, `vessels`, `physics.json`) and the problem. The node and tet counts.
pub fn validate(c: &Content<'_>) -> Result<(usize, usize), ServiceError> {
    let file = c.file;
    let (nodes_field, tets_field) = if c.arrays {
        ("upload.nodes_mm", "upload.tets")
    } else {
        ("mesh", "mesh")
    };
    if file.tets.is_empty() {
        return Err(field(
            "mesh",
            format!(
                "no tetrahedra ({} nodes, {} triangles): a case needs a tetrahedral mesh",
                file.nodes.len(),
                file.triangles.len()
            ),
        ));
    }
    let mesh = TetMesh::from_file(file).map_err(|e| field(tets_field, e.to_string()))?;
    organ_size(&mesh, c)?;
    // Degenerate tets, and one orientation throughout (a mesh entirely negative is flipped as
    // the command line does; a mixed one is tangled).
    let volumes = mesh.tet_volumes();
    let negative = volumes.iter().filter(|v| **v < 0.0).count();
    let mut unused = Vec::new();
    for p in mesh.problems(usize::MAX) {
        match p {
            MeshError::InvertedTet { tet, volume } => {
                if negative * 2 <= volumes.len() {
                    return Err(field(
                        tets_field,
                        format!(
                            "tet {tet} is inverted (signed volume {volume:.3e} mm³ while {} of {} tets are positive): a tangled mesh",
                            volumes.len() - negative,
                            volumes.len()
                        ),
                    ));
                }
            }
            MeshError::UnusedNode { node } => unused.push(node),
            other => return Err(field(tets_field, other.to_string())),
        }
    }
    if negative * 2 > volumes.len() && negative < volumes.len() {
        let t = volumes.iter().position(|v| *v > 0.0).unwrap_or(0);
        return Err(field(
            tets_field,
            format!(
                "tet {t} has the opposite orientation of {negative} of {} tets: a tangled mesh",
                volumes.len()
            ),
        ));
    }
    if let Some(&first) = unused.first() {
        return Err(field(
            nodes_field,
            format!(
                "node {first} is in no tetrahedron ({} of {} nodes are in none): the elasticity model needs every node in a tet; remove the unused nodes",
                unused.len(),
                mesh.num_nodes()
            ),
        ));
    }
    if let Some((a, b)) = coincident_nodes(mesh.nodes()) {
        let tet_of = |n: usize| mesh.tets().iter().position(|t| t.contains(&(n as u32)));
        let p = mesh.nodes()[a];
        return Err(field(
            nodes_field,
            format!(
                "nodes {a} and {b} are at the same position ({}, {}, {}) mm, node {a} in tet {} and node {b} in tet {}: a tet on a copy of a node leaves a crack inside the mesh; merge them",
                number(p[0]),
                number(p[1]),
                number(p[2]),
                tet_of(a).unwrap_or_default(),
                tet_of(b).unwrap_or_default(),
            ),
        ));
    }
    if let Some((tet, other)) = repeated_tet(mesh.tets()) {
        return Err(field(
            tets_field,
            format!(
                "tet {tet} repeats tet {other} (the same 4 nodes {:?}): each tet must appear once",
                mesh.tets()[other]
            ),
        ));
    }
    mesh.boundary().map_err(|e| {
        field(
            tets_field,
            format!("the mesh's boundary is not a closed surface: {e}"),
        )
    })?;
    let vessels = match c.vessels {
        Some(v) => io::read_bytes(v, Format::Vtp, Path::new("mesh.vessels.vtp"), c.unit)
            .map_err(|e| field("vessels", e.to_string()))?,
        None => MeshFile::default(),
    };
    // The model preload builds (cases.rs, through `preop_model_from_mesh`): a labelled file's
    // labels and vessels, or labels from the geometry.
    let model = if file.point_array("region").is_some() {
        librplus::register::correspondence::preop_model_from_file(file, &vessels)
            .map_err(|e| field("mesh", e.to_string()))?
    } else {
        librplus::input::preop_model_from_mesh(Path::new("mesh"), file, c.unit, EDGE_MM)
            .map_err(|e| field("mesh", e.to_string()))?
    };
    librplus::register::correspondence::Correspondence::new(&model)
        .map_err(|e| field("mesh", e.to_string()))?;
    if let Some(p) = c.physics {
        let physics_error =
            |e: librplus::register::RegisterError| field("physics.json", e.to_string());
        let text = std::str::from_utf8(p).map_err(|_| field("physics.json", "not UTF-8 text"))?;
        let physics = Physics::from_json(text).map_err(physics_error)?;
        let sites = librplus::register::physics::model::Sites {
            posterior: &model.posterior,
            falciform: &model.falciform,
        };
        librplus::register::physics::model::check_fits(&model.mesh, sites, &physics)
            .map_err(physics_error)?;
    }
    Ok((mesh.num_nodes(), mesh.num_tets()))
}

/// Nodes closer than this are one position (mm).
const COINCIDENT_MM: f64 = 1e-6;

/// The first pair of distinct nodes at one position (within [`COINCIDENT_MM`]): (lower, higher
/// index), the lowest such pair.
fn coincident_nodes(nodes: &[[f64; 3]]) -> Option<(usize, usize)> {
    use std::collections::HashMap;
    // Cells of COINCIDENT_MM: a node's twin lies in its cell or a neighbouring one.
    let cell = |p: &[f64; 3]| p.map(|x| (x / COINCIDENT_MM).floor() as i64);
    let mut grid: HashMap<[i64; 3], Vec<usize>> = HashMap::with_capacity(nodes.len());
    for (i, p) in nodes.iter().enumerate() {
        grid.entry(cell(p)).or_default().push(i);
    }
    nodes.iter().enumerate().find_map(|(i, p)| {
        let c = cell(p);
        (0..27i64)
            .flat_map(|d| {
                let key = [c[0] + d % 3 - 1, c[1] + d / 3 % 3 - 1, c[2] + d / 9 - 1];
                grid.get(&key).into_iter().flatten().copied()
            })
            .filter(|&j| j > i && (0..3).all(|k| (p[k] - nodes[j][k]).abs() <= COINCIDENT_MM))
            .min()
            .map(|j| (i, j))
    })
}

/// The first tet whose 4 nodes (in any order) an earlier tet has: (it, the earlier one).
fn repeated_tet(tets: &[[u32; 4]]) -> Option<(usize, usize)> {
    let mut keyed: Vec<([u32; 4], usize)> = tets
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let mut k = *t;
            k.sort_unstable();
            (k, i)
        })
        .collect();
    keyed.sort_unstable();
    keyed
        .windows(2)
        .filter(|w| w[0].0 == w[1].0)
        .map(|w| (w[1].1, w[0].1))
        .min()
}

/// Millimetres per unit.
fn unit_mm(u: Unit) -> f64 {
    match u {
        Unit::Mm => 1.0,
        Unit::Cm => 10.0,
        Unit::M => 1000.0,
    }
}

/// A length or size for messages: grouped digits ("200,000"), a few significant digits below
/// 100, powers of ten beyond 10^9 (never hundreds of digits).
pub fn number(x: f64) -> String {
    if !x.is_finite() {
        return format!("{x}");
    }
    let a = x.abs();
    if a >= 1e9 {
        return format!("{x:.2e}");
    }
    if a >= 100.0 {
        let digits = format!("{:.0}", a);
        let mut out = String::new();
        for (i, ch) in digits.chars().enumerate() {
            if i > 0 && (digits.len() - i) % 3 == 0 {
                out.push(',');
            }
            out.push(ch);
        }
        return if x < 0.0 { format!("-{out}") } else { out };
    }
    if a >= 1.0 || a == 0.0 {
        return format!("{x:.1}");
    }
    if a >= 1e-3 {
        return format!("{x:.3}");
    }
    format!("{x:.2e}")
}

/// Bytes for messages (`1.5 MiB`).
pub fn bytes(b: u64) -> String {
    const UNITS: [&str; 4] = ["KiB", "MiB", "GiB", "TiB"];
    if b < 1024 {
        return format!("{b} bytes");
    }
    let mut v = b as f64 / 1024.0;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    format!("{v:.1} {}", UNITS[u])
}

/// The organ's size check (see [`ORGAN_MM`]); the error names the unit declared and the one
/// that would fit.
fn organ_size(mesh: &TetMesh, c: &Content<'_>) -> Result<(), ServiceError> {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in mesh.nodes() {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let extent = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
    let (min, max) = ORGAN_MM;
    if (min..=max).contains(&extent) {
        return Ok(());
    }
    // Of the candidates (a tag, the size it gives), the fitting one nearest a liver's size
    // (170 mm) on a log scale.
    fn nearest<T>(candidates: impl Iterator<Item = (T, f64)>) -> Option<(T, f64)> {
        let (min, max) = ORGAN_MM;
        candidates
            .filter(|(_, mm)| (min..=max).contains(mm))
            .min_by(|a, b| {
                (a.1 / 170.0)
                    .ln()
                    .abs()
                    .total_cmp(&(b.1 / 170.0).ln().abs())
            })
    }
    let spans = format!(
        "the mesh spans {} mm (the largest side of its bounding box); an organ spans {min:.0} to {max:.0} mm",
        number(extent)
    );
    if c.arrays {
        let hint = nearest(
            (-3..=3i32)
                .filter(|k| *k != 0)
                .map(|k| (k, extent * 10f64.powi(k))),
        )
        .map_or_else(
            || "no power of ten makes it an organ's size".to_string(),
            |(k, _)| {
                let f = number(10f64.powi(k.abs()));
                if k < 0 {
                    format!("these look {f} times too large (in µm or another unit?)")
                } else {
                    format!("these look {f} times too small (in cm or m?)")
                }
            },
        );
        return Err(field(
            "upload.nodes_mm",
            format!("{spans}: nodes_mm must be millimetres, and {hint}"),
        ));
    }
    let declared = if c.unit_name.is_empty() {
        "\"\" (mm)".to_string()
    } else {
        format!("{:?}", c.unit_name)
    };
    let raw = extent / unit_mm(c.unit);
    let hint = nearest(
        [("mm", Unit::Mm), ("cm", Unit::Cm), ("m", Unit::M)]
            .into_iter()
            .filter(|(_, u)| *u != c.unit)
            .map(|(name, u)| (name, raw * unit_mm(u))),
    )
    .map_or_else(
        || "no unit (mm, cm, m) makes it an organ's size: check the mesh".to_string(),
        |(name, mm)| format!("is its unit {name}? (it would span {} mm)", number(mm)),
    );
    Err(field(
        "upload.mesh_unit",
        format!("{spans}, with mesh_unit {declared}: {hint}"),
    ))
}

/// The content's SHA-256: every part named and length-prefixed.
fn version(u: &Upload, mesh_name: &str, mesh: &[u8]) -> String {
    let mut ctx = ring::digest::Context::new(&ring::digest::SHA256);
    let mut part = |name: &str, bytes: &[u8]| {
        ctx.update(name.as_bytes());
        ctx.update(&(bytes.len() as u64).to_le_bytes());
        ctx.update(bytes);
    };
    part("librplus-case-1", &[]);
    part(mesh_name, mesh);
    part(
        "unit",
        unit(&u.unit)
            .map_or_else(|_| "mm".to_string(), |x| x.to_string())
            .as_bytes(),
    );
    if let Some(v) = &u.vessels {
        part("vessels", v);
    }
    if let Some(p) = &u.physics {
        part("physics", p);
    }
    crate::auth::hex(ctx.finish().as_ref())
}
