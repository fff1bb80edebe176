//! Cases: preoperative models preloaded before surgery (correspondence structures and the LIBR
//! basis, from the on-disk cache when valid), found in dataset directories or mesh folders.

use crate::config::ServerConfig;
use librplus::gcn::io::TrainedModel;
use librplus::mesh::io::{self, MeshFile};
use librplus::pipeline::{Method, PipelineParams, Prepared};
use librplus::register::PreopModel;
use librplus::register::physics::Physics;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Running estimates of a case's stage durations (ms), for planning within a time budget.
#[derive(Debug, Clone, Copy)]
pub struct Estimates {
    /// Rigid stage.
    pub rigid_ms: f64,
    /// One LIBR iteration.
    pub libr_iteration_ms: f64,
    /// LIBR's fixed cost (the final displacement of every node).
    pub libr_fixed_ms: f64,
    /// What a deformable registration spends outside its rigid stage and LIBR's iterations
    /// (the side test's other fits, the fit's score, the error estimate).
    pub other_ms: f64,
    /// METHOD_NONLINEAR's refinement of a linear answer (the nonlinear model's first build
    /// included the first time).
    pub refine_ms: f64,
}

/// A preloaded case.
pub struct Case {
    /// Identifier in requests.
    pub id: String,
    /// Mesh file it came from.
    pub source: PathBuf,
    /// The prepared model (with its LIBR basis).
    pub prepared: Prepared,
    /// The case's parameters: its basis was built with `params.libr.basis`, and every
    /// registration and discovery run on it starts from these (within its request and the time
    /// left).
    pub params: PipelineParams,
    /// Method when a request leaves it unspecified.
    pub default_method: Method,
    /// Stage-duration estimates (exponential moving averages of what was measured).
    pub estimates: Mutex<Estimates>,
    /// Its content's version: uploaded cases the SHA-256 of the upload; others the SHA-256 of
    /// their mesh and physics (a resumed session must find the content it started on).
    pub version: String,
    /// Streamed sessions using it now (a case in use is not deleted).
    pub sessions: std::sync::atomic::AtomicUsize,
    /// When a request last used it (ms since the Unix epoch): an uploaded case idle for
    /// `evict_idle_s` leaves memory.
    pub last_used: std::sync::atomic::AtomicI64,
    /// Set while the case serves from a coarse basis (a large upload whose own basis builds;
    /// [`load_serving_early`]): its figures. Registrations on it are flagged DEGRADED.
    pub coarse: Option<librplus::register::libr::CoarseFigures>,
    /// A coarse case's successor, the same content with its own basis, once it is ready:
    /// sessions on the coarse case swap to it before their next registration.
    pub full: std::sync::OnceLock<Arc<Case>>,
}

impl Case {
    /// Notes a use (now).
    pub fn touch(&self) {
        self.last_used
            .store(crate::audit::now_ms(), std::sync::atomic::Ordering::Relaxed);
    }

    /// Milliseconds since its last use.
    pub fn idle_ms(&self) -> i64 {
        crate::audit::now_ms() - self.last_used.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Current stage-duration estimates.
    pub fn estimates(&self) -> Estimates {
        *self.estimates.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Folds a measured refinement time into its estimate (ms).
    pub fn observe_refine(&self, ms: f64) {
        let mut e = self.estimates.lock().unwrap_or_else(|p| p.into_inner());
        if ms.is_finite() && ms >= 0.0 {
            e.refine_ms = 0.8 * e.refine_ms + 0.2 * ms;
        }
    }

    /// Folds measured durations into the estimates.
    pub fn observe(&self, rigid_ms: f64, libr: Option<(f64, usize)>, other_ms: Option<f64>) {
        let mut e = self.estimates.lock().unwrap_or_else(|p| p.into_inner());
        let a = 0.2;
        if rigid_ms.is_finite() {
            e.rigid_ms = (1.0 - a) * e.rigid_ms + a * rigid_ms;
        }
        if let Some(ms) = other_ms.filter(|m| m.is_finite()) {
            e.other_ms = (1.0 - a) * e.other_ms + a * ms.max(0.0);
        }
        if let Some((ms, it)) = libr
            && it > 0
            && ms.is_finite()
        {
            let per = (ms - e.libr_fixed_ms).max(0.0) / it as f64;
            e.libr_iteration_ms = (1.0 - a) * e.libr_iteration_ms + a * per;
        }
    }
}

/// A case found on disk, before loading.
#[derive(Debug, Clone)]
pub enum CaseSource {
    /// A geometry of a dataset directory.
    Dataset {
        /// Dataset directory.
        dir: PathBuf,
        /// Geometry id.
        geometry: String,
    },
    /// A mesh file in a folder.
    Mesh {
        /// The file.
        path: PathBuf,
    },
    /// A case of the case store (uploaded).
    Stored(Box<crate::store::Stored>),
}

/// Why a case could not be found, read or prepared; each names the directory or file.
#[derive(Debug, thiserror::Error)]
pub enum CaseError {
    /// Two cases have the same id.
    #[error("case id {id:?} appears twice (in {} and before): rename one", dir.display())]
    DuplicateId {
        /// The id.
        id: String,
        /// The second directory holding it.
        dir: PathBuf,
    },
    /// A configured case path holds no case.
    #[error("{}: {problem}", path.display())]
    NoCase {
        /// The path.
        path: PathBuf,
        /// What it holds instead.
        problem: String,
    },
    /// A case directory could not be listed.
    #[error("{}: {source}", path.display())]
    List {
        /// The directory.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// A dataset case could not be read.
    #[error(transparent)]
    Dataset(#[from] librplus::dataset::DatasetError),
    /// A mesh case could not be read.
    #[error(transparent)]
    Mesh(#[from] io::IoError),
    /// A mesh case's model could not be built.
    #[error(transparent)]
    Input(#[from] librplus::input::InputError),
    /// The case could not be prepared (correspondence, basis, SR-GCN).
    #[error("{}: {source}", path.display())]
    Prepare {
        /// The case's file.
        path: PathBuf,
        /// What failed.
        source: librplus::pipeline::PipelineError,
    },
    /// The case's `physics.json` could not be read.
    #[error("{}: {source}", path.display())]
    Physics {
        /// The physics file.
        path: PathBuf,
        /// What was wrong (naming the field).
        source: librplus::register::RegisterError,
    },
    /// The configuration does not fit the case.
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    /// The configured default method needs a model that is not loaded.
    #[error("default_method librplus needs an SR-GCN model (none is loaded)")]
    NoModel,
}

/// Lists the cases under the configured paths (ids must be unique).
pub fn discover(config: &ServerConfig) -> Result<Vec<(String, CaseSource)>, CaseError> {
    let mut out: BTreeMap<String, CaseSource> = BTreeMap::new();
    for dir in &config.cases {
        let mut add = |id: String, src: CaseSource| -> Result<(), CaseError> {
            if out.insert(id.clone(), src).is_some() {
                return Err(CaseError::DuplicateId {
                    id,
                    dir: dir.clone(),
                });
            }
            Ok(())
        };
        if dir.join("manifest.json").is_file() {
            let m = librplus::dataset::read::open(dir)?;
            for g in &m.geometries {
                add(
                    g.id.clone(),
                    CaseSource::Dataset {
                        dir: dir.clone(),
                        geometry: g.id.clone(),
                    },
                )?;
            }
        } else if dir.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
                .map_err(|source| CaseError::List {
                    path: dir.clone(),
                    source,
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    let name = p.to_string_lossy();
                    !name.ends_with(".vessels.vtp")
                        && matches!(
                            p.extension().and_then(|e| e.to_str()),
                            Some("vtu" | "vtk" | "msh")
                        )
                })
                .collect();
            files.sort();
            if files.is_empty() {
                return Err(CaseError::NoCase {
                    path: dir.clone(),
                    problem: "no manifest.json and no .vtu/.vtk/.msh meshes".into(),
                });
            }
            for f in files {
                let id = f
                    .file_stem()
                    .map(|s| s.to_string_lossy().to_string())
                    .unwrap_or_default();
                add(id, CaseSource::Mesh { path: f })?;
            }
        } else {
            return Err(CaseError::NoCase {
                path: dir.clone(),
                problem: "not a directory".into(),
            });
        }
    }
    Ok(out.into_iter().collect())
}

/// The learned models every case gets, loaded once at start: SR-GCN networks for LIBR+ and the
/// V2S network for METHOD_V2S.
#[derive(Debug, Clone, Default)]
pub struct Learned {
    /// LIBR+'s network, or an ensemble's members.
    pub gcn: Option<Vec<Arc<TrainedModel>>>,
    /// The V2S network.
    pub v2s: Option<Arc<librplus::v2s::io::V2sModel>>,
}

/// Loads and prepares one case (correspondence structures and the LIBR basis).
pub fn load(
    id: &str,
    source: &CaseSource,
    config: &ServerConfig,
    learned: &Learned,
) -> Result<Case, CaseError> {
    load_with_progress(id, source, config, learned, &|_, _| {})
}

/// [`load`], telling `progress` each stage ("reading", "labelling", "preparing", "sr-gcn",
/// "v2s") and the fraction done.
pub fn load_with_progress(
    id: &str,
    source: &CaseSource,
    config: &ServerConfig,
    learned: &Learned,
    progress: &dyn Fn(&str, f64),
) -> Result<Case, CaseError> {
    load_serving_early(id, source, config, learned, progress, None)
}

/// [`load_with_progress`] that, for a case `coarse_first` picks, hands `early` a case that
/// serves from a coarse basis (its [`Case::coarse`] set) before the case's own basis builds.
/// A coarse basis that cannot be built is logged and skipped: the case's own still is.
pub fn load_serving_early(
    id: &str,
    source: &CaseSource,
    config: &ServerConfig,
    learned: &Learned,
    progress: &dyn Fn(&str, f64),
    early: Option<&dyn Fn(Case)>,
) -> Result<Case, CaseError> {
    // The library's defaults, made in one place; the case keeps them.
    let params = PipelineParams::default();
    progress("reading", 0.0);
    let read = read_source(source, config, progress)?;
    let prepare = |source| CaseError::Prepare {
        path: read.path.clone(),
        source,
    };
    // The augmented model beside the case (`physics.json`, from `librplus discover`), if any.
    let physics = if read.physics_path.is_file() {
        Physics::read(&read.physics_path).map_err(|source| CaseError::Physics {
            path: read.physics_path.clone(),
            source,
        })?
    } else {
        Physics::none()
    };
    let version = match &read.version {
        Some(v) => v.clone(),
        // A case the server was started with: the SHA-256 of its mesh and physics, so that a
        // session recorded on other content (the files changed across a restart) is not resumed.
        None => content_version(&read.model, &read.physics_path),
    };
    let default_method = config.method()?;
    if let Some(early) = early
        && coarse_first(config, &read, &physics, &params)
    {
        progress("coarse basis", 0.15);
        let edge = config.coarse_basis_edge_mm;
        match Prepared::with_coarse_basis(read.model.clone(), &params.libr, edge) {
            Ok((prepared, figures)) => {
                let prepared = learned_models(prepared, learned, config, &params, None, progress)
                    .map_err(prepare)?;
                let mut c = case(id, &read.path, prepared, &params, default_method, &version);
                c.coarse = Some(figures);
                early(c);
            }
            Err(e) => {
                tracing::warn!(case = %id, error = %e, "no coarse basis; the case's own basis builds")
            }
        }
    }
    progress("preparing", 0.2);
    let prepared =
        Prepared::with_physics(read.model, Some(&params.libr), &physics, Some(&read.cache))
            .map_err(prepare)?;
    let prepared = learned_models(
        prepared,
        learned,
        config,
        &params,
        Some(&read.cache),
        progress,
    )
    .map_err(prepare)?;
    if default_method == Method::LibrPlus && prepared.librplus.is_none() {
        return Err(CaseError::NoModel);
    }
    Ok(case(
        id,
        &read.path,
        prepared,
        &params,
        default_method,
        &version,
    ))
}

/// A case's model as read from its source, and where its files are.
struct Read {
    model: PreopModel,
    /// The mesh file.
    path: PathBuf,
    /// Its basis cache folder.
    cache: PathBuf,
    /// Where its `physics.json` would be.
    physics_path: PathBuf,
    /// Its content version when the source gives one (an upload's).
    version: Option<String>,
}

/// Reads a case's model from its source.
fn read_source(
    source: &CaseSource,
    config: &ServerConfig,
    progress: &dyn Fn(&str, f64),
) -> Result<Read, CaseError> {
    let read = match source {
        CaseSource::Dataset { dir, geometry } => {
            let m = librplus::dataset::read::open(dir)?;
            let g = librplus::dataset::read::load_geometry(dir, &m, geometry)?;
            let entry = m
                .geometries
                .iter()
                .find(|e| &e.id == geometry)
                .ok_or_else(|| CaseError::NoCase {
                    path: dir.clone(),
                    problem: format!("no geometry {geometry}"),
                })?;
            Read {
                model: g.model,
                path: dir.join(&entry.preop),
                cache: dir.join("cache"),
                physics_path: dir.join("physics").join(format!("{geometry}.json")),
                version: None,
            }
        }
        CaseSource::Mesh { path } => {
            let unit = config.unit()?;
            let file = io::read(path, unit)?;
            let model = model_from_mesh_file(path, &file, unit)?;
            let parent = path.parent().unwrap_or(Path::new("."));
            let stem = path
                .file_stem()
                .map(|s| s.to_string_lossy().to_string())
                .unwrap_or_default();
            Read {
                model,
                path: path.clone(),
                cache: parent.join("cache"),
                physics_path: parent.join(format!("{stem}.physics.json")),
                version: None,
            }
        }
        CaseSource::Stored(s) => {
            let path = s.mesh_path();
            let file = io::read(&path, s.unit())?;
            progress("labelling", 0.1);
            let model = model_from_mesh_file(&path, &file, s.unit())?;
            // A stored case keeps its basis in its own folder (deleted with it).
            return Ok(Read {
                model,
                path,
                cache: s.dir.join("cache"),
                physics_path: s.dir.join("mesh.physics.json"),
                version: Some(s.version.clone()),
            });
        }
    };
    Ok(Read {
        cache: config.cache_dir.clone().unwrap_or(read.cache),
        ..read
    })
}

/// Whether a case serves from a coarse basis first: more nodes than
/// `coarse_basis_above_nodes` (0: never), plain physics (a carried basis has no supports or effects), and
/// its own basis not in its cache (a cached one loads in a second).
fn coarse_first(
    config: &ServerConfig,
    read: &Read,
    physics: &Physics,
    params: &PipelineParams,
) -> bool {
    let mesh = &read.model.mesh;
    config.coarse_basis_above_nodes > 0
        && mesh.num_nodes() > config.coarse_basis_above_nodes
        && physics.is_empty()
        && !librplus::register::libr::LibrBasis::cache_path(mesh, &params.libr, &read.cache)
            .is_file()
}

/// `prepared` with the learned models and the error model the server gives every case, and
/// adaptive LIBR's basis when the server prepares it and `cache` is given (a coarse case, given
/// none, answers without adaptive LIBR until its own basis is ready).
fn learned_models(
    prepared: Prepared,
    learned: &Learned,
    config: &ServerConfig,
    params: &PipelineParams,
    cache: Option<&Path>,
    progress: &dyn Fn(&str, f64),
) -> Result<Prepared, librplus::pipeline::PipelineError> {
    let mut prepared = prepared.with_error_model(librplus::register::uncertainty::builtin());
    if let Some(m) = &learned.gcn {
        progress("sr-gcn", 0.9);
        prepared = prepared.with_models(m.clone())?;
    }
    if let Some(m) = &learned.v2s {
        progress("v2s", 0.95);
        prepared = prepared.with_v2s(m.clone())?;
    }
    if config.adaptive
        && let Some(cache) = cache
    {
        progress("adaptive basis", 0.97);
        prepared = prepared.with_adaptive(&params.libr, &params.adaptive, Some(cache))?;
    }
    let nonlinear = config.method().ok() == Some(librplus::pipeline::Method::Nonlinear);
    if nonlinear && cache.is_some() {
        // The nonlinear model built now, not in the first registration's budget.
        progress("nonlinear model", 0.99);
        prepared = prepared.with_nonlinear(&params.libr, &params.nonlinear)?;
    }
    Ok(prepared)
}

/// A case of a prepared model.
fn case(
    id: &str,
    path: &Path,
    prepared: Prepared,
    params: &PipelineParams,
    default_method: Method,
    version: &str,
) -> Case {
    let n = prepared.model.mesh.num_nodes() as f64;
    Case {
        id: id.to_string(),
        source: path.to_path_buf(),
        prepared,
        params: params.clone(),
        default_method,
        // First guesses, per 10,000 nodes on one core of this machine kind (BENCHMARKS.md);
        // replaced by measurements after the first registrations.
        estimates: Mutex::new(Estimates {
            rigid_ms: 25.0 * n / 1e4,
            libr_iteration_ms: 3.0 * n / 1e4,
            libr_fixed_ms: 4.0 * n / 1e4,
            other_ms: 0.0,
            // 0.9 s p50 on the 9,089-node paper liver (BENCHMARKS.md), with the nonlinear
            // model's first build (about as long again) when it was not preloaded.
            refine_ms: 2_000.0 * n / 1e4,
        }),
        version: version.to_string(),
        sessions: Default::default(),
        last_used: crate::audit::now_ms().into(),
        coarse: None,
        full: std::sync::OnceLock::new(),
    }
}

/// SHA-256 (hex) of a prepared case's content: node positions, tetrahedra and the
/// `physics.json` beside it (its bytes, when present).
fn content_version(model: &PreopModel, physics_path: &Path) -> String {
    let mesh = &model.mesh;
    let mut bytes = Vec::with_capacity(mesh.num_nodes() * 24 + mesh.num_tets() * 16 + 64);
    bytes.extend_from_slice(b"librplus-case 1\n");
    for p in mesh.nodes() {
        for x in p {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
    }
    for t in mesh.tets() {
        for i in t {
            bytes.extend_from_slice(&(*i as u64).to_le_bytes());
        }
    }
    if let Ok(p) = std::fs::read(physics_path) {
        bytes.extend_from_slice(&p);
    }
    crate::auth::hex(&crate::auth::sha256(&bytes))
}

/// A preoperative model from a mesh file (see [`librplus::input::preop_model_from_mesh`];
/// a surface is meshed at 7.6 mm, the paper preset's edge length).
fn model_from_mesh_file(
    path: &Path,
    file: &MeshFile,
    unit: io::Unit,
) -> Result<PreopModel, librplus::input::InputError> {
    librplus::input::preop_model_from_mesh(path, file, unit, 7.6)
}
