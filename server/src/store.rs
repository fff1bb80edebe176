//! The case store: cases uploaded over the API (`CreateCase`), one folder each, written
//! atomically (a temporary folder, every file and the folder fsynced, then renamed into place)
//! and content-addressed (a case's version is the SHA-256 of its content). A restart reloads
//! every stored case; its LIBR basis is cached in its folder.
//!
//! Layout (format 1; docs/service.md, "Case store"): `STORE/<first 24 hex digits of
//! SHA-256(case id)>/` holding `case.json` (format, case id, version, unit, principal, time, mesh
//! size, bytes, the checks it passed), `mesh.vtu|vtk|msh`, optionally `mesh.vessels.vtp` and
//! `mesh.physics.json`, and `cache/` (LIBR bases). Folders starting with `.` are in progress or
//! being deleted.
//!
//! An upload passes [`validate`] before it is stored: every check preload makes that does not
//! need the LIBR basis (the mesh's topology, the organ's size in mm, the labelled model and its
//! correspondence structures, `physics.json` through the parser and the fit check preload uses).
//! A case stored by a server whose checks were older ([`CHECKS`]) is checked again when the store
//! is listed at start, and removed if it fails. What the store holds is bounded by [`Quotas`]
//! (cases and bytes, per principal and in total), checked under the store's lock when a case is
//! put.

use crate::error::ServiceError;
use librplus::mesh::io::{self, Format, MeshFile, Unit};
use librplus::mesh::{MeshError, TetMesh};
use librplus::register::physics::Physics;
use std::io::Write;
use std::path::{Path, PathBuf};

/// The store's format.
pub const FORMAT: u32 = 1;
/// Longest case id, characters.
pub const MAX_ID: usize = 128;
/// The version of [`validate`]'s checks a case passed when stored (`case.json`'s `checks`): 1
/// before the unused-node, repeated-tet, organ-size, labelled-model and physics-fit checks,
/// 2 with them. A case stored with older checks is checked again at start.
pub const CHECKS: u32 = 2;
/// The sizes an organ's mesh may span, mm (the largest side of its bounding box, after the
/// unit): a liver spans 100–300 mm, a child's or a phantom's less; a mesh outside this range
/// is in the wrong unit (a 200 mm liver declared in m spans 200,000 mm, in cm 2,000 mm; one
/// in cm declared mm spans 20 mm).
pub const ORGAN_MM: (f64, f64) = (40.0, 600.0);
/// The tetrahedralisation edge of a surface mesh, mm (as preload's: the paper preset's).
const EDGE_MM: f64 = 7.6;

/// The mesh of an upload.
#[derive(Debug, Clone)]
pub enum MeshSource {
    /// A file's bytes and its format (`vtu`, `vtk`, `msh`).
    File {
        /// The bytes.
        bytes: Vec<u8>,
        /// The extension.
        format: String,
    },
    /// Arrays: nodes (3 per node) and tets (4 per tet).
    Arrays {
        /// Node coordinates, mm.
        nodes: Vec<f64>,
        /// Node indices.
        tets: Vec<u32>,
    },
}

/// An upload, as received.
#[derive(Debug, Clone)]
pub struct Upload {
    /// The case id.
    pub case_id: String,
    /// The mesh.
    pub mesh: MeshSource,
    /// Length unit of the mesh and vessel files.
    pub unit: String,
    /// Vessel centerlines (.vtp bytes).
    pub vessels: Option<Vec<u8>>,
    /// physics.json bytes.
    pub physics: Option<Vec<u8>>,
}

/// A stored case (`case.json`).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Stored {
    /// Store format (1).
    pub format: u32,
    /// The case id.
    pub case_id: String,
    /// SHA-256 of the content (hex).
    pub version: String,
    /// The mesh file's name in the folder.
    pub mesh: String,
    /// Length unit of the mesh and vessel files.
    pub unit: String,
    /// Who uploaded it.
    pub principal: String,
    /// When (ms since the epoch).
    pub created_ms: i64,
    /// Mesh size.
    pub nodes: usize,
    /// Mesh size.
    pub tets: usize,
    /// Whether vessels and physics came with it.
    pub vessels: bool,
    /// Whether physics came with it.
    pub physics: bool,
    /// Bytes of its files as uploaded (mesh as stored, vessels, physics; not the basis cache).
    /// 0 in a store written before it was recorded.
    #[serde(default)]
    pub bytes: u64,
    /// The version of the checks it passed ([`CHECKS`]; 0 in a store written before they were
    /// versioned).
    #[serde(default)]
    pub checks: u32,
    /// The folder (not stored; set when read).
    #[serde(skip)]
    pub dir: PathBuf,
}

impl Stored {
    /// The mesh file's path.
    pub fn mesh_path(&self) -> PathBuf {
        self.dir.join(&self.mesh)
    }

    /// The unit.
    pub fn unit(&self) -> Unit {
        unit(&self.unit).unwrap_or(Unit::Mm)
    }

    /// Checks the stored content again with [`validate`] (a case stored with older checks).
    pub fn validate(&self) -> Result<(), ServiceError> {
        let mesh = self.mesh_path();
        let file = io::read(&mesh, self.unit()).map_err(|e| field("mesh", e.to_string()))?;
        let read = |name: &str| -> Result<Option<Vec<u8>>, ServiceError> {
            let p = self.dir.join(name);
            if !p.is_file() {
                return Ok(None);
            }
            std::fs::read(&p)
                .map(Some)
                .map_err(|e| ServiceError::Unavailable(format!("{}: {e}", p.display())))
        };
        validate(&Content {
            file: &file,
            unit: self.unit(),
            unit_name: &self.unit,
            arrays: false,
            vessels: read("mesh.vessels.vtp")?.as_deref(),
            physics: read("mesh.physics.json")?.as_deref(),
        })
        .map(|_| ())
    }
}

/// Why the store could not do something.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file operation failed (`no_space`: the disk is full).
    #[error("case store {}: {source}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// The id is taken by other content.
    #[error("case {id:?} exists with version {version}; delete it first to upload other content")]
    Exists {
        /// The id.
        id: String,
        /// Its version.
        version: String,
    },
    /// A `case.json` does not read.
    #[error("case store {}: {problem}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
    /// A stored case failed the checks of this server (it was stored by one with older checks)
    /// and was removed from the store.
    #[error(
        "stored case {id:?} (version {version}, uploaded by {principal:?}) fails the upload checks and was removed from the case store: {problem}"
    )]
    Invalid {
        /// The id.
        id: String,
        /// Its version.
        version: String,
        /// Who uploaded it.
        principal: String,
        /// What is wrong (naming the field).
        problem: String,
    },
    /// A quota of the store would be passed; nothing was stored.
    #[error("{message}")]
    Quota {
        /// The config field of the quota (`max_cases_per_principal`, ...).
        quota: &'static str,
        /// What is held, the limit and what to do.
        message: String,
    },
}

impl StoreError {
    fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
        move |source| StoreError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// As the service's error: a full disk or a quota is RESOURCE_EXHAUSTED (QuotaFailure
    /// naming it), a taken id FAILED_PRECONDITION, the rest UNAVAILABLE.
    pub fn to_service(&self) -> ServiceError {
        match self {
            StoreError::Io { source, .. } if source.raw_os_error() == Some(28) => {
                ServiceError::Quota {
                    message: format!("the case store is full: {self}; nothing was stored"),
                    subject: "case_store",
                    description: "no space left on the case store's disk".into(),
                }
            }
            StoreError::Exists { id, .. } => ServiceError::precondition(
                "CASE",
                "upload.case_id",
                format!("case {id} exists"),
                self.to_string(),
            ),
            StoreError::Quota { quota, message } => ServiceError::Quota {
                message: format!("{message}; nothing was stored"),
                subject: quota,
                description: format!(
                    "{quota}: the case store's limit was reached; delete a case (DeleteCase) to upload another"
                ),
            },
            _ => ServiceError::Unavailable(format!("{self}; nothing was stored")),
        }
    }
}

/// The mesh unit named by `s` ("" is mm).
pub fn unit(s: &str) -> Result<Unit, String> {
    match s {
        "" | "mm" => Ok(Unit::Mm),
        "cm" => Ok(Unit::Cm),
        "m" => Ok(Unit::M),
        u => Err(format!("{u:?}: expected mm, cm or m")),
    }
}

/// Checks a case id's form; the problem in words.
pub fn check_id(id: &str) -> Result<(), String> {
    if id.is_empty() || id.chars().count() > MAX_ID {
        return Err(format!("must be 1 to {MAX_ID} characters"));
    }
    if let Some(c) = id
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-' | '/')))
    {
        return Err(format!("{c:?} is not allowed (A-Z a-z 0-9 . _ - /)"));
    }
    if id.starts_with('/')
        || id.ends_with('/')
        || id.split('/').any(|p| p.is_empty() || p == "." || p == "..")
    {
        return Err("path segments must be non-empty and not . or ..".into());
    }
    Ok(())
}

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

fn field(f: impl Into<String>, p: impl Into<String>) -> ServiceError {
    ServiceError::field(f, p)
}

/// Checks an upload: its form (unit, format, arrays: finite nodes, indices in range), the node
/// limit (`max_nodes`), then [`validate`]. Errors are INVALID_ARGUMENT naming the field (and
/// the tet or node), or RESOURCE_EXHAUSTED for the node limit.
pub fn check(u: &Upload, max_nodes: usize) -> Result<Checked, ServiceError> {
    let unit = unit(&u.unit).map_err(|e| field("upload.mesh_unit", e))?;
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
            .map_err(|e| ServiceError::Internal(format!("writing the mesh: {e}")))?;
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
///    model has no stiffness at a free node), no tet twice (the same 4 nodes in any order), a
///    manifold boundary;
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

/// Limits on what the store holds (config `max_stored_cases`, `max_stored_bytes`,
/// `max_cases_per_principal`, `max_bytes_per_principal`). A case's bytes are its folder's on
/// disk (its files and its LIBR basis cache) once stored, its files while it is being put.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Quotas {
    /// Most cases in the store.
    pub cases: usize,
    /// Most bytes in the store.
    pub bytes: u64,
    /// Most cases one principal uploaded.
    pub cases_per_principal: usize,
    /// Most bytes of the cases one principal uploaded.
    pub bytes_per_principal: u64,
}

impl Quotas {
    /// No limit.
    pub const NONE: Quotas = Quotas {
        cases: usize::MAX,
        bytes: u64::MAX,
        cases_per_principal: usize::MAX,
        bytes_per_principal: u64::MAX,
    };

    /// The configured quotas (a per-principal 0: the total's).
    pub fn from_config(c: &crate::config::ServerConfig) -> Self {
        Quotas {
            cases: c.max_stored_cases,
            bytes: c.max_stored_bytes,
            cases_per_principal: match c.max_cases_per_principal {
                0 => c.max_stored_cases,
                n => n,
            },
            bytes_per_principal: match c.max_bytes_per_principal {
                0 => c.max_stored_bytes,
                n => n,
            },
        }
    }
}

/// What the store holds: cases and bytes, in total and of one principal.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Usage {
    /// Cases stored.
    pub cases: usize,
    /// Their bytes on disk.
    pub bytes: u64,
    /// Cases the principal uploaded.
    pub principal_cases: usize,
    /// Their bytes on disk.
    pub principal_bytes: u64,
}

/// Bytes of the files under `path` (0 for what does not read).
fn disk_bytes(path: &Path) -> u64 {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.is_dir() => std::fs::read_dir(path)
            .map(|r| r.flatten().map(|e| disk_bytes(&e.path())).sum())
            .unwrap_or(0),
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

/// The case store.
#[derive(Debug)]
pub struct Store {
    dir: PathBuf,
    lock: std::sync::Mutex<()>,
}

fn write_synced(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let mut f = std::fs::File::create(path).map_err(StoreError::io(path))?;
    f.write_all(bytes).map_err(StoreError::io(path))?;
    f.sync_all().map_err(StoreError::io(path))
}

fn sync_dir(path: &Path) -> Result<(), StoreError> {
    std::fs::File::open(path)
        .and_then(|f| f.sync_all())
        .map_err(StoreError::io(path))
}

fn random_hex() -> String {
    use ring::rand::SecureRandom;
    let mut b = [0u8; 8];
    let _ = ring::rand::SystemRandom::new().fill(&mut b);
    crate::auth::hex(&b)
}

impl Store {
    /// Opens (creating) a store; removes what an interrupted upload or deletion left.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(StoreError::io(dir))?;
        for e in std::fs::read_dir(dir)
            .map_err(StoreError::io(dir))?
            .flatten()
        {
            if e.file_name().to_string_lossy().starts_with('.') {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            lock: Default::default(),
        })
    }

    /// The folder of case `id`.
    pub fn folder(&self, id: &str) -> PathBuf {
        let h = crate::auth::hex(&crate::auth::sha256(id.as_bytes()));
        self.dir.join(&h[..24])
    }

    fn read(folder: &Path) -> Result<Stored, StoreError> {
        let f = folder.join("case.json");
        let text = std::fs::read_to_string(&f).map_err(StoreError::io(&f))?;
        let mut s: Stored = serde_json::from_str(&text).map_err(|e| StoreError::Corrupt {
            path: f.clone(),
            problem: e.to_string(),
        })?;
        if s.format != FORMAT {
            return Err(StoreError::Corrupt {
                path: f,
                problem: format!("format {} (this server reads {FORMAT})", s.format),
            });
        }
        s.dir = folder.to_path_buf();
        Ok(s)
    }

    /// The stored case `id`, if any.
    pub fn find(&self, id: &str) -> Option<Stored> {
        let folder = self.folder(id);
        folder
            .is_dir()
            .then(|| Self::read(&folder).ok())
            .flatten()
            .filter(|s| s.case_id == id)
    }

    /// The stored cases' folders (not those in progress).
    fn folders(&self) -> Result<Vec<PathBuf>, StoreError> {
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(&self.dir)
            .map_err(StoreError::io(&self.dir))?
            .flatten()
            .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
            .map(|e| e.path())
            .filter(|p| p.is_dir())
            .collect();
        dirs.sort();
        Ok(dirs)
    }

    /// Every stored case (or why one does not read). A case stored with older checks than
    /// [`CHECKS`] is checked again ([`Stored::validate`]): passing, its `case.json` records it
    /// (and its bytes); failing, it is removed from the store and listed as
    /// [`StoreError::Invalid`], so that a case preload would refuse is not reloaded at every
    /// start.
    pub fn list(&self) -> Result<Vec<Result<Stored, StoreError>>, StoreError> {
        let mut out = Vec::new();
        for d in self.folders()? {
            out.push(Self::read(&d).and_then(|s| self.recheck(s)));
        }
        Ok(out)
    }

    /// Checks a case stored with older checks again (see [`Self::list`]).
    fn recheck(&self, mut s: Stored) -> Result<Stored, StoreError> {
        if s.checks >= CHECKS {
            return Ok(s);
        }
        match s.validate() {
            Ok(()) => {
                s.checks = CHECKS;
                if s.bytes == 0 {
                    s.bytes = [s.mesh.as_str(), "mesh.vessels.vtp", "mesh.physics.json"]
                        .iter()
                        .map(|f| disk_bytes(&s.dir.join(f)))
                        .sum();
                }
                // Recorded so that it is checked once; it loads either way.
                let path = s.dir.join("case.json");
                match serde_json::to_vec_pretty(&s) {
                    Ok(json) => {
                        let tmp = s.dir.join(".case.json.tmp");
                        let r = write_synced(&tmp, &json).and_then(|_| {
                            std::fs::rename(&tmp, &path).map_err(StoreError::io(&path))
                        });
                        if let Err(e) = r {
                            tracing::warn!(case = %s.case_id, error = %e, "could not record the stored case's checks; it is checked again at the next start");
                        }
                    }
                    Err(e) => {
                        tracing::warn!(case = %s.case_id, error = %e, "could not record the stored case's checks")
                    }
                }
                Ok(s)
            }
            Err(ServiceError::Unavailable(problem)) => Err(StoreError::Corrupt {
                path: s.dir.clone(),
                problem,
            }),
            Err(e) => {
                let problem = e.to_status().message().to_string();
                self.remove(&s.case_id)?;
                Err(StoreError::Invalid {
                    id: s.case_id,
                    version: s.version,
                    principal: s.principal,
                    problem,
                })
            }
        }
    }

    /// What the store holds now, in total and of `principal` (each case's folder on disk: its
    /// files and its basis cache).
    pub fn usage(&self, principal: &str) -> Result<Usage, StoreError> {
        let mut u = Usage::default();
        for d in self.folders()? {
            let Ok(s) = Self::read(&d) else {
                continue;
            };
            let b = disk_bytes(&d);
            u.cases += 1;
            u.bytes += b;
            if s.principal == principal {
                u.principal_cases += 1;
                u.principal_bytes += b;
            }
        }
        Ok(u)
    }

    /// Whether one more case of `adding` bytes by `principal` fits the quotas: the first quota
    /// it would pass, as [`StoreError::Quota`].
    pub fn check_quota(&self, principal: &str, adding: u64, q: &Quotas) -> Result<(), StoreError> {
        let u = self.usage(principal)?;
        let quota =
            |quota: &'static str, message: String| Err(StoreError::Quota { quota, message });
        if u.principal_cases >= q.cases_per_principal {
            return quota(
                "max_cases_per_principal",
                format!(
                    "principal {principal:?} keeps {} stored case(s), the most one principal may (max_cases_per_principal = {}): delete one of them (DeleteCase) to upload another",
                    u.principal_cases, q.cases_per_principal
                ),
            );
        }
        if u.principal_bytes.saturating_add(adding) > q.bytes_per_principal {
            return quota(
                "max_bytes_per_principal",
                format!(
                    "principal {principal:?}'s stored cases hold {} (their files and LIBR bases); this upload's {} would pass the {} one principal may keep (max_bytes_per_principal): delete one of them (DeleteCase) first",
                    bytes(u.principal_bytes),
                    bytes(adding),
                    bytes(q.bytes_per_principal)
                ),
            );
        }
        if u.cases >= q.cases {
            return quota(
                "max_stored_cases",
                format!(
                    "the case store holds {} case(s), its most (max_stored_cases = {}): delete a case (DeleteCase) to upload another",
                    u.cases, q.cases
                ),
            );
        }
        if u.bytes.saturating_add(adding) > q.bytes {
            return quota(
                "max_stored_bytes",
                format!(
                    "the case store holds {} (cases' files and LIBR bases); this upload's {} would pass its {} (max_stored_bytes): delete a case (DeleteCase) first",
                    bytes(u.bytes),
                    bytes(adding),
                    bytes(q.bytes)
                ),
            );
        }
        Ok(())
    }

    /// Stores a checked upload within `quotas`; (the stored case, whether it is new). The same
    /// content under the same id is not written again (nor counted again).
    pub fn put(
        &self,
        u: &Upload,
        c: &Checked,
        principal: &str,
        quotas: &Quotas,
    ) -> Result<(Stored, bool), StoreError> {
        let _g = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(s) = self.find(&u.case_id) {
            if s.version == c.version {
                return Ok((s, false));
            }
            return Err(StoreError::Exists {
                id: u.case_id.clone(),
                version: s.version,
            });
        }
        let size = (c.mesh_bytes.len()
            + u.vessels.as_ref().map_or(0, Vec::len)
            + u.physics.as_ref().map_or(0, Vec::len)) as u64;
        self.check_quota(principal, size, quotas)?;
        let tmp = self.dir.join(format!(".upload-{}", random_hex()));
        let result = (|| {
            std::fs::create_dir(&tmp).map_err(StoreError::io(&tmp))?;
            write_synced(&tmp.join(&c.mesh_name), &c.mesh_bytes)?;
            if let Some(v) = &u.vessels {
                write_synced(&tmp.join("mesh.vessels.vtp"), v)?;
            }
            if let Some(p) = &u.physics {
                write_synced(&tmp.join("mesh.physics.json"), p)?;
            }
            let stored = Stored {
                format: FORMAT,
                case_id: u.case_id.clone(),
                version: c.version.clone(),
                mesh: c.mesh_name.clone(),
                unit: unit(&u.unit).map_or_else(|_| "mm".to_string(), |x| x.to_string()),
                principal: principal.to_string(),
                created_ms: crate::audit::now_ms(),
                nodes: c.nodes,
                tets: c.tets,
                vessels: u.vessels.is_some(),
                physics: u.physics.is_some(),
                bytes: size,
                checks: CHECKS,
                dir: PathBuf::new(),
            };
            let json = serde_json::to_vec_pretty(&stored).map_err(|e| StoreError::Corrupt {
                path: tmp.join("case.json"),
                problem: e.to_string(),
            })?;
            write_synced(&tmp.join("case.json"), &json)?;
            sync_dir(&tmp)?;
            let folder = self.folder(&u.case_id);
            std::fs::rename(&tmp, &folder).map_err(StoreError::io(&folder))?;
            sync_dir(&self.dir)?;
            Ok(Stored {
                dir: folder,
                ..stored
            })
        })();
        match result {
            Ok(s) => Ok((s, true)),
            Err(e) => {
                let _ = std::fs::remove_dir_all(&tmp);
                Err(e)
            }
        }
    }

    /// Removes case `id` from the store (renamed aside, synced, then deleted).
    pub fn remove(&self, id: &str) -> Result<Option<Stored>, StoreError> {
        self.remove_version(id, None)
    }

    /// Removes case `id` if it is at `version` (any version: None); what was removed.
    pub fn remove_version(
        &self,
        id: &str,
        version: Option<&str>,
    ) -> Result<Option<Stored>, StoreError> {
        let _g = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let Some(s) = self
            .find(id)
            .filter(|s| version.is_none_or(|v| v == s.version))
        else {
            return Ok(None);
        };
        let aside = self.dir.join(format!(".deleted-{}", random_hex()));
        std::fs::rename(&s.dir, &aside).map_err(StoreError::io(&s.dir))?;
        sync_dir(&self.dir)?;
        let _ = std::fs::remove_dir_all(&aside);
        Ok(Some(s))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 120 × 90 × 60 mm box of 144 positive tets (60 nodes).
    fn cube() -> (Vec<f64>, Vec<u32>) {
        let m = librplus::mesh::procedural::box_mesh([120.0, 90.0, 60.0], [4, 3, 2], 0.2);
        (
            m.nodes().iter().flatten().copied().collect(),
            m.tets().iter().flatten().copied().collect(),
        )
    }

    fn upload(id: &str, nodes: Vec<f64>, tets: Vec<u32>) -> Upload {
        Upload {
            case_id: id.into(),
            mesh: MeshSource::Arrays { nodes, tets },
            unit: String::new(),
            vessels: None,
            physics: None,
        }
    }

    #[test]
    fn ids_are_checked() {
        for ok in ["a", "hospital-a/p001", "P.1_x"] {
            assert!(check_id(ok).is_ok(), "{ok}");
        }
        for bad in [
            "",
            "/a",
            "a/",
            "a//b",
            "a/../b",
            "..",
            "a b",
            "ä",
            &"x".repeat(129),
        ] {
            assert!(check_id(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn uploads_are_checked_naming_the_problem() {
        let (n, t) = cube();
        let c = check(&upload("a", n.clone(), t.clone()), 100).unwrap();
        assert_eq!((c.nodes, c.tets), (60, 144));
        // The same content has the same version; another content another.
        assert_eq!(
            c.version,
            check(&upload("b", n.clone(), t.clone()), 100)
                .unwrap()
                .version
        );
        let mut moved = n.clone();
        moved[0] = -1.0;
        assert_ne!(
            c.version,
            check(&upload("a", moved, t.clone()), 100).unwrap().version
        );
        let msg = |u: Upload| {
            check(&u, 100)
                .unwrap_err()
                .to_status()
                .message()
                .to_string()
        };
        let mut nan = n.clone();
        nan[4] = f64::NAN;
        assert!(msg(upload("a", nan, t.clone())).contains("upload.nodes_mm[4]"));
        let mut flipped = t.clone();
        flipped.swap(6, 7); // tet 1 inverted, the others not: tangled
        let e = msg(upload("a", n.clone(), flipped));
        assert!(e.contains("tet 1 is inverted"), "{e}");
        let mut out = t.clone();
        out[7] = 999;
        assert!(msg(upload("a", n.clone(), out)).contains("upload.tets[7]"));
        // Tet 0's last node onto its first: tet 0 flat.
        let mut flat = n.clone();
        let (a, d) = (t[0] as usize, t[3] as usize);
        for k in 0..3 {
            flat[3 * d + k] = flat[3 * a + k];
        }
        let e = msg(upload("a", flat, t.clone()));
        assert!(e.contains("degenerate"), "{e}");
        let e = check(&upload("a", n.clone(), t.clone()), 4).unwrap_err();
        assert_eq!(e.code(), tonic::Code::ResourceExhausted);
        let corrupt = Upload {
            mesh: MeshSource::File {
                bytes: b"<VTKFile type=\"UnstructuredGrid\"><Piece".to_vec(),
                format: "vtu".into(),
            },
            ..upload("a", vec![], vec![])
        };
        assert!(msg(corrupt).starts_with("mesh:"));
        let physics = |json: &str| Upload {
            physics: Some(json.as_bytes().to_vec()),
            ..upload("a", n.clone(), t.clone())
        };
        let e = msg(physics(
            r#"{"format": 1, "effects": [{"kind": "magnetism"}]}"#,
        ));
        assert!(e.starts_with("physics.json: effects[0].kind"), "{e}");
        // What preload refused after the upload was stored (issue: upload checks weaker than
        // preload's).
        let e = msg(physics(
            r#"{"format": 1, "effects": [{"kind": "nonlinear"}]}"#,
        ));
        assert!(
            e.starts_with("physics.json: effects[0].kind") && e.contains("nonlinear"),
            "{e}"
        );
        // A pack by the corner (120, 0, 0): on it, and 40 mm beyond.
        let pack = |x: f64, width: f64| {
            format!(
                r#"{{"format": 1, "effects": [{{"kind": "gravity", "parameters": {{"direction": [0, 0, -1], "magnitude": 0.01}}}}, {{"kind": "pack", "parameters": {{"center": [{x}, 0, 0], "width_mm": {width}, "force_mn": [-100, 0, 0]}}}}]}}"#
            )
        };
        let e = msg(physics(&pack(160.0, 15.0)));
        assert!(
            e.starts_with("physics.json: effects[1].parameters.center")
                && e.contains("40.0 mm from the organ's surface")
                && e.contains("30.0 mm"),
            "{e}"
        );
        check(&physics(&pack(120.0, 25.0)), 100).unwrap();
        let mut unused = n.clone();
        unused.extend([60.0, 45.0, 30.0]);
        let e = msg(upload("a", unused, t.clone()));
        assert!(
            e.starts_with("upload.nodes_mm: node 60 is in no tetrahedron"),
            "{e}"
        );
        let mut twice = t.clone();
        twice.extend([t[5], t[6], t[4], t[7]]);
        let e = msg(upload("a", n.clone(), twice));
        assert!(e.starts_with("upload.tets: tet 144 repeats tet 1"), "{e}");
        // Sizes: in µm as nodes_mm, in mm declared m or cm, in cm declared mm.
        let scaled = |f: f64| n.iter().map(|x| x * f).collect::<Vec<f64>>();
        let e = msg(upload("a", scaled(1000.0), t.clone()));
        assert!(
            e.contains("spans 120,000 mm") && e.contains("1,000 times too large"),
            "{e}"
        );
        let file = |nodes: Vec<f64>, unit: &str| {
            let m = MeshFile {
                nodes: nodes.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
                tets: t.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
                ..Default::default()
            };
            Upload {
                mesh: MeshSource::File {
                    bytes: io::write_bytes(
                        &m,
                        Format::Vtu,
                        io::WriteOptions::default(),
                        Path::new("m.vtu"),
                    )
                    .unwrap(),
                    format: "vtu".into(),
                },
                unit: unit.into(),
                ..upload("a", vec![], vec![])
            }
        };
        let e = msg(file(n.clone(), "m"));
        assert!(
            e.starts_with("upload.mesh_unit: the mesh spans 120,000 mm")
                && e.contains("mesh_unit \"m\": is its unit mm?"),
            "{e}"
        );
        let e = msg(file(n.clone(), "cm"));
        assert!(e.contains("is its unit mm?"), "{e}");
        let e = msg(file(scaled(0.1), ""));
        assert!(
            e.contains("spans 12.0 mm") && e.contains("is its unit cm?"),
            "{e}"
        );
        assert!(check(&file(scaled(0.1), "cm"), 100).is_ok());
        let e = msg(upload("a", scaled(1e300), t.clone()));
        assert!(e.contains("1.20e302 mm") && e.len() < 300, "{e}");
        let e = msg(Upload {
            unit: "m".into(),
            ..upload("a", n.clone(), t.clone())
        });
        assert!(e.starts_with("upload.mesh_unit"), "{e}");
    }

    #[test]
    fn numbers_and_sizes_read_well() {
        assert_eq!(number(200_000.0), "200,000");
        assert_eq!(number(1234.4), "1,234");
        assert_eq!(number(40.04), "40.0");
        assert_eq!(number(0.25), "0.250");
        assert_eq!(number(1e300), "1.00e300");
        assert_eq!(bytes(12), "12 bytes");
        assert_eq!(bytes(3 << 20), "3.0 MiB");
    }

    #[test]
    fn the_store_writes_atomically_and_is_content_addressed() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let (n, t) = cube();
        let u = upload("hospital-a/p1", n.clone(), t.clone());
        let c = check(&u, 100).unwrap();
        let (s, created) = store.put(&u, &c, "or-a", &Quotas::NONE).unwrap();
        assert!(created);
        assert!(s.mesh_path().is_file());
        assert_eq!((s.checks, s.bytes), (CHECKS, c.mesh_bytes.len() as u64));
        let (again, created) = store.put(&u, &c, "or-a", &Quotas::NONE).unwrap();
        assert!(!created);
        assert_eq!(again.version, s.version);
        let mut moved = n;
        moved[0] = -1.0;
        let other = upload("hospital-a/p1", moved, t);
        let e = store
            .put(&other, &check(&other, 100).unwrap(), "or-a", &Quotas::NONE)
            .unwrap_err();
        assert!(matches!(e, StoreError::Exists { .. }), "{e}");
        // A leftover of an interrupted upload is cleared at open; the case reads back.
        std::fs::create_dir(dir.path().join(".upload-dead")).unwrap();
        let store = Store::open(dir.path()).unwrap();
        assert!(!dir.path().join(".upload-dead").exists());
        let all = store.list().unwrap();
        assert_eq!(all.len(), 1);
        assert_eq!(all[0].as_ref().unwrap().case_id, "hospital-a/p1");
        assert!(
            store
                .remove_version("hospital-a/p1", Some("other"))
                .unwrap()
                .is_none()
        );
        assert!(store.remove("hospital-a/p1").unwrap().is_some());
        assert!(store.find("hospital-a/p1").is_none());
        assert!(store.list().unwrap().is_empty());
    }

    #[test]
    fn quotas_bound_the_store_per_principal_and_in_total() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let (n, t) = cube();
        let put = |id: &str, who: &str, q: &Quotas| {
            let mut nodes = n.clone();
            nodes[0] = -(id.len() as f64); // other content, another version
            let u = upload(id, nodes, t.clone());
            store.put(&u, &check(&u, 100).unwrap(), who, q)
        };
        let size = check(&upload("x", n.clone(), t.clone()), 100)
            .unwrap()
            .mesh_bytes
            .len() as u64;
        let q = Quotas {
            cases: 3,
            bytes: 10 * size,
            cases_per_principal: 2,
            bytes_per_principal: 10 * size,
        };
        put("a1", "a", &q).unwrap();
        put("a22", "a", &q).unwrap();
        let quota = |r: Result<(Stored, bool), StoreError>| match r {
            Err(StoreError::Quota { quota, message }) => {
                let s = StoreError::Quota { quota, message }
                    .to_service()
                    .to_status();
                assert_eq!(s.code(), tonic::Code::ResourceExhausted);
                assert!(s.message().contains(quota), "{}", s.message());
                quota
            }
            other => panic!("{other:?}"),
        };
        assert_eq!(quota(put("a333", "a", &q)), "max_cases_per_principal");
        put("b1", "b", &q).unwrap();
        assert_eq!(quota(put("c1", "c", &q)), "max_stored_cases");
        // The same content again is no new case.
        assert!(!put("a1", "a", &q).unwrap().1);
        store.remove("a1").unwrap();
        let u = store.usage("a").unwrap();
        assert_eq!((u.cases, u.principal_cases), (2, 1));
        let small = Quotas {
            bytes_per_principal: u.principal_bytes + size / 2,
            ..q
        };
        assert_eq!(quota(put("a1", "a", &small)), "max_bytes_per_principal");
        let small = Quotas {
            bytes: u.bytes + size / 2,
            ..q
        };
        assert_eq!(quota(put("a1", "a", &small)), "max_stored_bytes");
        put("a1", "a", &q).unwrap();
        assert_eq!(store.list().unwrap().len(), 3);
    }

    #[test]
    fn a_stored_case_older_checks_refuse_is_removed_when_listed() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let (n, t) = cube();
        let good = upload("good", n.clone(), t.clone());
        store
            .put(&good, &check(&good, 100).unwrap(), "a", &Quotas::NONE)
            .unwrap();
        // As a server with older checks stored them: a `nonlinear` physics, and a good one.
        let bad = Upload {
            physics: Some(br#"{"format": 1, "effects": [{"kind": "nonlinear"}]}"#.to_vec()),
            ..upload("bad", n, t)
        };
        let c = Checked {
            mesh_name: "mesh.vtu".into(),
            mesh_bytes: check(&good, 100).unwrap().mesh_bytes,
            nodes: 60,
            tets: 144,
            version: "0".repeat(64),
        };
        store.put(&bad, &c, "a", &Quotas::NONE).unwrap();
        for id in ["good", "bad"] {
            let f = store.folder(id).join("case.json");
            let mut v: serde_json::Value =
                serde_json::from_slice(&std::fs::read(&f).unwrap()).unwrap();
            let o = v.as_object_mut().unwrap();
            o.remove("checks");
            o.remove("bytes");
            std::fs::write(&f, serde_json::to_vec(&v).unwrap()).unwrap();
        }
        let listed = store.list().unwrap();
        assert_eq!(listed.len(), 2);
        let errors: Vec<String> = listed
            .iter()
            .filter_map(|r| r.as_ref().err().map(|e| e.to_string()))
            .collect();
        assert_eq!(errors.len(), 1, "{errors:?}");
        assert!(
            errors[0].contains("\"bad\"")
                && errors[0].contains("removed from the case store")
                && errors[0].contains("effects[0].kind"),
            "{}",
            errors[0]
        );
        assert!(store.find("bad").is_none());
        let good = store.find("good").unwrap();
        assert_eq!(good.checks, CHECKS);
        assert!(good.bytes > 0);
        assert_eq!(store.list().unwrap().len(), 1);
    }
}
