//! The case store: cases uploaded over the API (`CreateCase`), one folder each, written
//! atomically (a temporary folder, every file and the folder fsynced, then renamed into place)
//! and content-addressed (a case's version is the SHA-256 of its content). A restart reloads
//! every stored case; its LIBR basis is cached in its folder.
//!
//! Layout (format 1; docs/service.md, "Case store"): `STORE/<first 24 hex digits of
//! SHA-256(case id)>/` holding `case.json` (format, case id, version, unit, principal, time, mesh
//! size), `mesh.vtu|vtk|msh`, optionally `mesh.vessels.vtp` and `mesh.physics.json`, and
//! `cache/` (LIBR bases). Folders starting with `.` are in progress or being deleted.

use crate::error::ServiceError;
use librplus::mesh::io::{self, Format, MeshFile, Unit};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The store's format.
pub const FORMAT: u32 = 1;
/// Longest case id, characters.
pub const MAX_ID: usize = 128;

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
}

impl StoreError {
    fn io(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
        move |source| StoreError::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// As the service's error: a full disk is RESOURCE_EXHAUSTED, a taken id ALREADY_EXISTS
    /// (as a precondition), the rest UNAVAILABLE.
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

/// Checks an upload as the command line checks a mesh (it reads, its tets are valid: finite
/// nodes, indices in range, no repeated node, none degenerate, one orientation throughout), and
/// its vessels and physics; errors name the field (and the tet or node). At most `max_nodes`
/// nodes.
pub fn check(u: &Upload, max_nodes: usize) -> Result<Checked, ServiceError> {
    let unit = unit(&u.unit).map_err(|e| field("upload.mesh_unit", e))?;
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
    let mesh =
        librplus::mesh::TetMesh::from_file(&file).map_err(|e| field("mesh", e.to_string()))?;
    // Degenerate tets, and one orientation throughout (a mesh entirely negative is flipped as
    // the command line does; a mixed one is tangled).
    let volumes = mesh.tet_volumes();
    let negative = volumes.iter().filter(|v| **v < 0.0).count();
    for p in mesh.problems(usize::MAX) {
        match p {
            librplus::mesh::MeshError::InvertedTet { tet, volume } => {
                if negative * 2 <= volumes.len() {
                    return Err(field(
                        "mesh",
                        format!(
                            "tet {tet} is inverted (signed volume {volume:.3e} mm³ while {} of {} tets are positive): a tangled mesh",
                            volumes.len() - negative,
                            volumes.len()
                        ),
                    ));
                }
            }
            librplus::mesh::MeshError::UnusedNode { .. } => {}
            other => return Err(field("mesh", other.to_string())),
        }
    }
    if negative * 2 > volumes.len() && negative < volumes.len() {
        let t = volumes.iter().position(|v| *v > 0.0).unwrap_or(0);
        return Err(field(
            "mesh",
            format!(
                "tet {t} has the opposite orientation of {negative} of {} tets: a tangled mesh",
                volumes.len()
            ),
        ));
    }
    if let Some(v) = &u.vessels {
        io::read_bytes(v, Format::Vtp, Path::new("mesh.vessels.vtp"), unit)
            .map_err(|e| field("vessels", e.to_string()))?;
    }
    if let Some(p) = &u.physics {
        let text = std::str::from_utf8(p).map_err(|_| field("physics", "not UTF-8 text"))?;
        librplus::register::physics::Physics::from_json(text)
            .map_err(|e| field("physics", e.to_string()))?;
    }
    Ok(Checked {
        version: version(u, &mesh_name, &mesh_bytes),
        mesh_name,
        mesh_bytes,
        nodes: mesh.num_nodes(),
        tets: mesh.num_tets(),
    })
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

    /// Every stored case (or why one does not read).
    pub fn list(&self) -> Result<Vec<Result<Stored, StoreError>>, StoreError> {
        let mut out = Vec::new();
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(&self.dir)
            .map_err(StoreError::io(&self.dir))?
            .flatten()
            .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
            .map(|e| e.path())
            .filter(|p| p.is_dir())
            .collect();
        dirs.sort();
        for d in dirs {
            out.push(Self::read(&d));
        }
        Ok(out)
    }

    /// Stores a checked upload; (the stored case, whether it is new). The same content under
    /// the same id is not written again.
    pub fn put(
        &self,
        u: &Upload,
        c: &Checked,
        principal: &str,
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
        let _g = self.lock.lock().unwrap_or_else(|e| e.into_inner());
        let Some(s) = self.find(id) else {
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

    fn cube() -> (Vec<f64>, Vec<u32>) {
        // Two positive tets sharing a face.
        let nodes = vec![
            0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 0.0, 10.0, 0.0, 0.0, 0.0, 10.0, 10.0, 10.0, 10.0,
        ];
        let tets = vec![0, 1, 2, 3, 1, 2, 3, 4];
        (nodes, tets)
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
        let mut vols = librplus::mesh::TetMesh::new(
            n.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            t.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
        )
        .unwrap()
        .tet_volumes();
        vols.sort_by(f64::total_cmp);
        assert!(vols[0] > 0.0, "both test tets are positive: {vols:?}");
        let c = check(&upload("a", n.clone(), t.clone()), 100).unwrap();
        assert_eq!((c.nodes, c.tets), (5, 2));
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
        flipped.swap(6, 7); // the second tet inverted, the first not: tangled
        let e = msg(upload("a", n.clone(), flipped));
        assert!(e.contains("tet 1 is inverted"), "{e}");
        let mut out = t.clone();
        out[7] = 9;
        assert!(msg(upload("a", n.clone(), out)).contains("upload.tets[7]"));
        let mut flat = n.clone();
        flat[14] = 0.0; // node 4 into the plane z = 0 ... and tet 1 with it
        flat[11] = 0.0;
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
        let physics = Upload {
            physics: Some(br#"{"format": 1, "effects": [{"kind": "magnetism"}]}"#.to_vec()),
            ..upload("a", n, t)
        };
        assert!(msg(physics).contains("physics"));
    }

    #[test]
    fn the_store_writes_atomically_and_is_content_addressed() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let (n, t) = cube();
        let u = upload("hospital-a/p1", n.clone(), t.clone());
        let c = check(&u, 100).unwrap();
        let (s, created) = store.put(&u, &c, "or-a").unwrap();
        assert!(created);
        assert!(s.mesh_path().is_file());
        let (again, created) = store.put(&u, &c, "or-a").unwrap();
        assert!(!created);
        assert_eq!(again.version, s.version);
        let mut moved = n;
        moved[0] = -1.0;
        let other = upload("hospital-a/p1", moved, t);
        let e = store
            .put(&other, &check(&other, 100).unwrap(), "or-a")
            .unwrap_err();
        assert!(matches!(e, StoreError::Exists { .. }), "{e}");
        // A leftover of an interrupted upload is cleared at open; the case reads back.
        std::fs::create_dir(dir.path().join(".upload-dead")).unwrap();
        let store = Store::open(dir.path()).unwrap();
        assert!(!dir.path().join(".upload-dead").exists());
        let all = store.list().unwrap();
        assert_eq!(all.len(), 1);
        assert_eq!(all[0].as_ref().unwrap().case_id, "hospital-a/p1");
        assert!(store.remove("hospital-a/p1").unwrap().is_some());
        assert!(store.find("hospital-a/p1").is_none());
        assert!(store.list().unwrap().is_empty());
    }
}
