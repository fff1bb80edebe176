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

mod checks;
#[cfg(test)]
mod tests;

use crate::error::{ServiceError, Unavailable};
use checks::field;
pub use checks::{Checked, Content, bytes, check, number, validate};
use librplus::mesh::io::{self, Unit};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The store's format.
pub const FORMAT: u32 = 1;
/// Longest case id, characters.
pub const MAX_ID: usize = 128;
/// The version of [`validate`]'s checks a case passed when stored (`case.json`'s `checks`): 1
/// before the unused-node, repeated-tet, organ-size, labelled-model and physics-fit checks,
/// 2 with them, 3 with the coincident-node check. A case stored with older checks is checked
/// again at start.
pub const CHECKS: u32 = 3;
/// The sizes an organ's mesh may span, mm (the largest side of its bounding box, after the
/// unit): a liver spans 100–300 mm, a child's or a phantom's less; a mesh outside this range
/// is in the wrong unit (a 200 mm liver declared in m spans 200,000 mm, in cm 2,000 mm; one
/// in cm declared mm spans 20 mm).
pub const ORGAN_MM: (f64, f64) = (40.0, 600.0);

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
    /// Bytes its LIBR bases will take in its cache ([`basis_cache_bytes`]), counted against the
    /// quotas from the moment it is stored, before the preload writes them. 0 in a store
    /// written before it was recorded.
    #[serde(default)]
    pub cache_reserve: u64,
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
    pub fn validate(&self) -> Result<(), Recheck> {
        let mesh = self.mesh_path();
        let file = io::read(&mesh, self.unit())
            .map_err(|e| Recheck::Invalid(field("mesh", e.to_string())))?;
        let read = |name: &str| -> Result<Option<Vec<u8>>, Recheck> {
            let path = self.dir.join(name);
            if !path.is_file() {
                return Ok(None);
            }
            std::fs::read(&path)
                .map(Some)
                .map_err(|source| Recheck::Unreadable { path, source })
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
        .map_err(Recheck::Invalid)
    }
}

/// Why a stored case fails [`Stored::validate`].
#[derive(Debug, thiserror::Error)]
pub enum Recheck {
    /// One of its files does not read (the case is not at fault: it stays stored).
    #[error("{}: {source}", path.display())]
    Unreadable {
        /// The file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// Its content fails the upload checks (the message names the field).
    #[error("{0}")]
    Invalid(#[source] ServiceError),
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
    /// A file of a stored case does not read when the case is checked again (it stays stored).
    #[error("case store {}: {}: {source}", dir.display(), path.display())]
    Unreadable {
        /// The case's folder.
        dir: PathBuf,
        /// The file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
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
        /// What is wrong (its text names the field).
        #[source]
        problem: Box<ServiceError>,
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
    /// naming it), a taken id FAILED_PRECONDITION, the rest UNAVAILABLE (keeping this error as
    /// its source).
    pub fn into_service(self) -> ServiceError {
        match &self {
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
            _ => Unavailable::Store(Box::new(self)).into(),
        }
    }
}

/// A mesh unit that is none of `mm`, `cm`, `m`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{unit:?}: expected mm, cm or m")]
pub struct UnknownUnit {
    /// The unit given.
    pub unit: String,
}

/// The mesh unit named by `s` ("" is mm).
pub fn unit(s: &str) -> Result<Unit, UnknownUnit> {
    match s {
        "" | "mm" => Ok(Unit::Mm),
        "cm" => Ok(Unit::Cm),
        "m" => Ok(Unit::M),
        u => Err(UnknownUnit {
            unit: u.to_string(),
        }),
    }
}

/// Why a case id is refused ([`check_id`]); its text is the problem in words.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CaseIdError {
    /// Empty, or longer than [`MAX_ID`] characters.
    #[error("must be 1 to {MAX_ID} characters")]
    Length {
        /// Its length, characters.
        chars: usize,
    },
    /// A character outside `A-Z a-z 0-9 . _ - /`.
    #[error("{0:?} is not allowed (A-Z a-z 0-9 . _ - /)")]
    Character(char),
    /// A path segment that is empty, `.` or `..` (a leading or trailing `/` included).
    #[error("path segments must be non-empty and not . or ..")]
    Segment,
}

/// Checks a case id's form.
pub fn check_id(id: &str) -> Result<(), CaseIdError> {
    let chars = id.chars().count();
    if id.is_empty() || chars > MAX_ID {
        return Err(CaseIdError::Length { chars });
    }
    if let Some(c) = id
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-' | '/')))
    {
        return Err(CaseIdError::Character(c));
    }
    if id.starts_with('/')
        || id.ends_with('/')
        || id.split('/').any(|p| p.is_empty() || p == "." || p == "..")
    {
        return Err(CaseIdError::Segment);
    }
    Ok(())
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
    /// Columns of each basis the server builds for a case (LIBR's, and adaptive LIBR's when
    /// configured; 0: none), one cache file each: what its cache will hold
    /// ([`basis_cache_bytes`]).
    pub basis_columns: [usize; 2],
}

/// Bytes a case's basis cache takes for a mesh of `nodes` nodes and bases of `columns` columns
/// in all: each basis file holds the displacement basis (3·nodes × m) and its energy matrix
/// (m × m) as 8-byte floats, with a few small arrays and headers.
pub fn basis_cache_bytes(nodes: usize, columns: usize) -> u64 {
    let (n, m) = (nodes as u64, columns as u64);
    8 * (3 * n * m + m * m + 4 * m) + 4096
}

impl Quotas {
    /// No limit.
    pub const NONE: Quotas = Quotas {
        cases: usize::MAX,
        bytes: u64::MAX,
        cases_per_principal: usize::MAX,
        bytes_per_principal: u64::MAX,
        basis_columns: [0, 0],
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
            basis_columns: basis_columns(c.adaptive),
        }
    }
}

/// Columns of the bases the server builds for each case: LIBR's (3 a control point), and
/// adaptive LIBR's multi-level basis when `adaptive` (else 0).
fn basis_columns(adaptive: bool) -> [usize; 2] {
    let defaults = librplus::pipeline::PipelineParams::default();
    let libr = 3 * defaults.libr.basis.control_points;
    let levels = defaults.adaptive.levels;
    let multi: usize = levels.iter().map(|l| 3 * l.0).sum();
    [libr, if adaptive { multi } else { 0 }]
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

/// What an upload of `adding` bytes does to a quota, in words (0: its size is not known yet).
fn adding_words(adding: u64) -> String {
    match adding {
        0 => ", no room for another upload: it reaches".into(),
        n => format!(
            "; this upload's {} (with its LIBR bases, once they are known) would pass",
            bytes(n)
        ),
    }
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
            Err(Recheck::Unreadable { path, source }) => Err(StoreError::Unreadable {
                dir: s.dir.clone(),
                path,
                source,
            }),
            Err(Recheck::Invalid(e)) => {
                self.remove(&s.case_id)?;
                Err(StoreError::Invalid {
                    id: s.case_id,
                    version: s.version,
                    principal: s.principal,
                    problem: Box::new(e),
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
            // What it will occupy once its bases are cached, or what it holds when more.
            let b = disk_bytes(&d).max(s.bytes.saturating_add(s.cache_reserve));
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
                    "principal {principal:?}'s stored cases hold {} (their files and LIBR bases){}, the {} one principal may keep (max_bytes_per_principal): delete one of them (DeleteCase) first",
                    bytes(u.principal_bytes),
                    adding_words(adding),
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
                    "the case store holds {} (cases' files and LIBR bases){}, its {} (max_stored_bytes): delete a case (DeleteCase) first",
                    bytes(u.bytes),
                    adding_words(adding),
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
        let cache_reserve: u64 = quotas
            .basis_columns
            .iter()
            .filter(|&&m| m > 0)
            .map(|&m| basis_cache_bytes(c.nodes, m))
            .sum();
        self.check_quota(principal, size.saturating_add(cache_reserve), quotas)?;
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
                cache_reserve,
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
