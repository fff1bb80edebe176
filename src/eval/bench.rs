//! Whole-pipeline registration benchmark (`librplus bench register`): the preload of a case (LIBR
//! basis built cold, then read back from its cache) and per-registration latency with the stage
//! timings a [`Registration`] reports. Plain data in and out: the caller picks threads, temporary
//! directories and prints.

use super::report::CATEGORY_ORDER;
use super::{GeometryData, ScenarioData, tre};
use crate::eval::EvalError;
use crate::mesh::TetMesh;
use crate::pipeline::PipelineError;
use crate::pipeline::{Method, PipelineParams, Prepared, Registration, register};
use crate::register::PreopModel;
use crate::register::libr::{BasisTimings, LibrBasis, LibrParams};
use std::path::Path;
use std::time::Instant;

/// One preload of a case (seconds).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Preload {
    /// Whether the basis came from the cache.
    pub from_cache: bool,
    /// The basis build or load stages.
    pub basis: BasisTimings,
    /// Correspondence structures (BVHs of the model's surfaces and vessels); None when only a
    /// mesh was given.
    pub correspondence_s: Option<f64>,
    /// Wall time of the whole preload.
    pub total_s: f64,
}

/// The cold and warm preloads of one mesh.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct PreloadBench {
    /// Mesh nodes.
    pub nodes: usize,
    /// Mesh tetrahedra.
    pub tets: usize,
    /// Basis columns (3 × control points).
    pub columns: usize,
    /// Size of the cache file (bytes).
    pub cache_bytes: u64,
    /// Built from scratch (into an empty cache directory).
    pub cold: Preload,
    /// Read back from the cache the cold build wrote.
    pub warm: Preload,
}

/// Measures the preload of `model` (correspondence + LIBR basis, with `physics`) twice with `cache_dir`, which
/// must not yet hold this basis: a cold build that writes the cache, then a warm load from it.
/// Returns the measurements and the warm case (ready for registrations).
pub fn preload_model(
    model: &PreopModel,
    params: &LibrParams,
    physics: &crate::register::physics::Physics,
    cache_dir: &Path,
) -> Result<(PreloadBench, Prepared), EvalError> {
    let path = LibrBasis::cache_path_with(&model.mesh, params, physics, cache_dir);
    if path.exists() {
        return Err(EvalError::Parameter(format!(
            "{} already exists: a cold preload needs an empty cache directory",
            path.display()
        )));
    }
    let mut runs = Vec::new();
    let mut last = None;
    for _ in 0..2 {
        let t0 = Instant::now();
        let case = Prepared::with_physics(model.clone(), Some(params), physics, Some(cache_dir))?;
        let total_s = crate::util::secs(t0);
        let basis = case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
        runs.push(Preload {
            from_cache: case.basis_from_cache,
            basis: basis.timings,
            correspondence_s: Some((case.seconds - basis.timings.total_s).max(0.0)),
            total_s,
        });
        last = Some(case);
    }
    let case = last.ok_or_else(|| EvalError::Internal("no preload ran".into()))?;
    let basis = case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
    let bench = PreloadBench {
        nodes: model.mesh.num_nodes(),
        tets: model.mesh.num_tets(),
        columns: basis.columns(),
        cache_bytes: std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0),
        cold: runs[0],
        warm: runs[1],
    };
    if bench.cold.from_cache || !bench.warm.from_cache {
        return Err(EvalError::Parameter(format!(
            "expected a cold build then a cache hit, got from_cache = {} then {}",
            bench.cold.from_cache, bench.warm.from_cache
        )));
    }
    Ok((bench, case))
}

/// Like [`preload_model`] for a bare tet mesh (no labels, so no correspondence): the LIBR basis
/// only.
pub fn preload_mesh(
    mesh: &TetMesh,
    params: &LibrParams,
    cache_dir: &Path,
) -> Result<PreloadBench, EvalError> {
    let path = LibrBasis::cache_path(mesh, params, cache_dir);
    if path.exists() {
        return Err(EvalError::Parameter(format!(
            "{} already exists: a cold preload needs an empty cache directory",
            path.display()
        )));
    }
    let mut runs = Vec::new();
    let mut columns = 0;
    for _ in 0..2 {
        let t0 = Instant::now();
        let (b, from_cache) = LibrBasis::load_or_build(mesh, params, cache_dir)?;
        runs.push(Preload {
            from_cache,
            basis: b.timings,
            correspondence_s: None,
            total_s: crate::util::secs(t0),
        });
        columns = b.columns();
    }
    Ok(PreloadBench {
        nodes: mesh.num_nodes(),
        tets: mesh.num_tets(),
        columns,
        cache_bytes: std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0),
        cold: runs[0],
        warm: runs[1],
    })
}

/// Indices of up to `n` scenarios spread evenly across the measurement categories: about `n / 5`
/// per category (the first `n % 5` categories of [`CATEGORY_ORDER`] one more), evenly spaced
/// within each category's scenarios (in the order given), then interleaved category by category.
/// A category with too few scenarios gives all it has.
pub fn pick_across_categories(categories: &[&str], n: usize) -> Vec<usize> {
    let k = CATEGORY_ORDER.len();
    let per: Vec<Vec<usize>> = CATEGORY_ORDER
        .iter()
        .enumerate()
        .map(|(ci, c)| {
            let all: Vec<usize> = (0..categories.len())
                .filter(|&i| categories[i] == *c)
                .collect();
            let want = (n / k + usize::from(ci < n % k)).min(all.len());
            (0..want)
                .map(|j| all[((2 * j + 1) * all.len()) / (2 * want)])
                .collect()
        })
        .collect();
    let mut out = Vec::new();
    for j in 0..per.iter().map(Vec::len).max().unwrap_or(0) {
        for p in &per {
            if let Some(&i) = p.get(j) {
                out.push(i);
            }
        }
    }
    out
}

/// A geometry of a dataset and the scenarios `bench register` times on it.
pub struct BenchScenarios {
    /// The geometry's id.
    pub geometry: String,
    /// The geometry: its preoperative model, boundary flags and targets.
    pub geo: GeometryData,
    /// Every scenario of the geometry's deformations, in dataset order.
    pub all: Vec<ScenarioData>,
    /// Indices into [`Self::all`] of the scenarios timed ([`pick_across_categories`]).
    pub picked: Vec<usize>,
}

impl BenchScenarios {
    /// Reads geometry `geometry` (None: the first) of the dataset in `data` with its scenarios,
    /// and picks `n` of them across the measurement categories.
    pub fn load(data: &Path, geometry: Option<&str>, n: usize) -> Result<Self, EvalError> {
        let m = super::open(data)?;
        let geometry = match geometry {
            Some(g) => g.to_string(),
            None => m.geometries.first().map(|g| g.id.clone()).ok_or_else(|| {
                EvalError::Data(format!("{}: the manifest has no geometry", data.display()))
            })?,
        };
        let geo = super::load_geometry(data, &m, &geometry)
            .map_err(|e| EvalError::Parameter(format!("--geometry {geometry:?}: {e}")))?;
        let mut all = Vec::new();
        for d in m.deformations.iter().filter(|d| d.geometry == geometry) {
            all.extend(super::load_scenarios(data, d)?);
        }
        let categories: Vec<&str> = all.iter().map(|s| s.category.as_str()).collect();
        let picked = pick_across_categories(&categories, n);
        if picked.is_empty() {
            return Err(EvalError::Data(format!(
                "{}: geometry {geometry} has no scenarios in the categories {:?}",
                data.display(),
                CATEGORY_ORDER
            )));
        }
        Ok(Self {
            geometry,
            geo,
            all,
            picked,
        })
    }

    /// The scenarios timed.
    pub fn picked(&self) -> Vec<&ScenarioData> {
        self.picked.iter().map(|&i| &self.all[i]).collect()
    }
}

/// [`time_registrations`] of the picked scenarios in a pool of `threads` threads: one
/// registration after another, each with the pool's threads (1: single-registration latency on
/// one core).
pub fn time_in_pool(
    threads: usize,
    case: &Prepared,
    scenarios: &BenchScenarios,
    asked: Asked<'_>,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<RegistrationBench, EvalError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| EvalError::Parameter(format!("building the thread pool: {e}")))?;
    let picked = scenarios.picked();
    let geo = &scenarios.geo;
    pool.install(|| time_registrations(case, &picked, &geo.surface, &geo.targets, asked, progress))
}

/// What each timed registration runs.
#[derive(Clone, Copy)]
pub struct Asked<'a> {
    /// The method.
    pub method: Method,
    /// Its parameters.
    pub params: &'a PipelineParams,
    /// In two answers where the pose search follows
    /// ([`crate::pipeline::register_progressive`]; the time to the first answer is then
    /// [`RegistrationTimings::first_s`]).
    pub progressive: bool,
}

/// Stage timings of one registration (seconds), from what [`Registration`] reports.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct RegistrationTimings {
    /// Whole registration (validation, wICP, LIBR); with two answers, both.
    pub total_s: f64,
    /// Time to the first answer: the provisional one where the pose search followed
    /// ([`Asked::progressive`]), else the whole registration.
    pub first_s: f64,
    /// Whether the registration answered twice (a provisional answer, then the searched one).
    pub answered_twice: bool,
    /// Rigid wICP.
    pub wicp_s: f64,
    /// LIBR: re-matching the points to the deformed model (all iterations).
    pub libr_matching_s: f64,
    /// LIBR: the fit's rows and normal equations.
    pub libr_assemble_s: f64,
    /// LIBR: the fit's solves.
    pub libr_solve_s: f64,
    /// LIBR: the rest (u = Φα, node movement, bookkeeping).
    pub libr_other_s: f64,
    /// LIBR total.
    pub libr_s: f64,
    /// SR-GCN correction (LIBR+; 0 otherwise).
    pub gcn_s: f64,
    /// Of which the network's forward pass.
    pub gcn_network_s: f64,
    /// Of which the data-consistency refit.
    pub gcn_refit_s: f64,
    /// V2S stage: the measured channels on the grid, the network, the interpolation (V2S; 0
    /// otherwise).
    pub v2s_s: f64,
    /// Of which the network and the interpolation to the nodes.
    pub v2s_network_s: f64,
    /// wICP iterations.
    pub wicp_iterations: usize,
    /// LIBR iterations (0 for rigid).
    pub libr_iterations: usize,
}

impl From<&Registration> for RegistrationTimings {
    fn from(r: &Registration) -> Self {
        let l = r.libr.clone().unwrap_or_default();
        Self {
            total_s: r.seconds,
            first_s: r.seconds,
            answered_twice: false,
            wicp_s: r.rigid.seconds,
            libr_matching_s: l.matching_s,
            libr_assemble_s: l.assemble_s,
            libr_solve_s: l.solve_s,
            libr_other_s: (l.total_s - l.matching_s - l.assemble_s - l.solve_s).max(0.0),
            libr_s: l.total_s,
            gcn_s: r.correction.as_ref().map_or(0.0, |c| c.seconds),
            gcn_network_s: r.correction.as_ref().map_or(0.0, |c| c.network_seconds),
            gcn_refit_s: r
                .correction
                .as_ref()
                .and_then(|c| c.refit.as_ref())
                .map_or(0.0, |i| i.total_s),
            v2s_s: r.v2s.map_or(0.0, |v| v.seconds),
            v2s_network_s: r.v2s.map_or(0.0, |v| v.network_seconds),
            wicp_iterations: r.rigid.iterations,
            libr_iterations: l.iterations,
        }
    }
}

/// Spread of a sample: p10, median, p90, mean, max (linear-interpolated quantiles).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Spread {
    /// 10th percentile.
    pub p10: f64,
    /// Median.
    pub median: f64,
    /// 90th percentile.
    pub p90: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Mean.
    pub mean: f64,
    /// Largest.
    pub max: f64,
}

impl Spread {
    /// Of `v` (NaN everywhere when empty).
    pub fn of(v: &[f64]) -> Self {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let q = |p: f64| {
            if s.is_empty() {
                return f64::NAN;
            }
            let h = p * (s.len() - 1) as f64;
            let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
            s[lo] + (h - lo as f64) * (s[hi] - s[lo])
        };
        Self {
            p10: q(0.1),
            median: q(0.5),
            p90: q(0.9),
            p99: q(0.99),
            mean: if s.is_empty() {
                f64::NAN
            } else {
                s.iter().sum::<f64>() / s.len() as f64
            },
            max: s.last().copied().unwrap_or(f64::NAN),
        }
    }
}

/// Summary of the timed registrations.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RegistrationBench {
    /// Registrations timed (the warm-up excluded).
    pub count: usize,
    /// Registrations that returned an error (not timed).
    pub failed: usize,
    /// Timed registrations per category.
    pub per_category: std::collections::BTreeMap<String, usize>,
    /// Total seconds per registration.
    pub total_s: Spread,
    /// Seconds to the first answer ([`RegistrationTimings::first_s`]).
    pub first_s: Spread,
    /// Registrations that answered twice.
    pub answered_twice: usize,
    /// Medians of the stage timings.
    pub median: RegistrationTimings,
    /// Mean wICP iterations.
    pub wicp_iterations_mean: f64,
    /// Mean LIBR iterations.
    pub libr_iterations_mean: f64,
    /// LIBR runs that met the movement tolerance.
    pub libr_converged: usize,
    /// Mean TRE of the timed registrations (mm): a check that they did real work.
    pub tre_mm_mean: f64,
    /// Every timed registration's stage timings, in run order.
    pub runs: Vec<RegistrationTimings>,
}

/// Registers `scenarios` one after another (the first once more beforehand, untimed, as a
/// warm-up) in the calling thread pool and summarises the timings.
pub fn time_registrations(
    case: &Prepared,
    scenarios: &[&ScenarioData],
    surface: &[bool],
    targets: &[u32],
    asked: Asked<'_>,
    progress: &dyn Fn(usize, usize),
) -> Result<RegistrationBench, EvalError> {
    if let Some(first) = scenarios.first() {
        let _ = timed(case, &first.measurements, asked);
    }
    let mut runs = Vec::new();
    let mut failed = 0;
    let mut converged = 0;
    let mut tres = Vec::new();
    let mut per_category = std::collections::BTreeMap::new();
    for (k, sc) in scenarios.iter().enumerate() {
        match timed(case, &sc.measurements, asked) {
            Ok((r, t)) => {
                runs.push(t);
                converged += usize::from(r.libr.as_ref().is_some_and(|l| l.converged));
                *per_category.entry(sc.category.clone()).or_insert(0) += 1;
                tres.push(
                    tre(
                        case.model.mesh.nodes(),
                        (&r.image_to_physical, &r.u),
                        (&sc.truth.image_to_physical, &sc.truth.displacement),
                        surface,
                        targets,
                    )
                    .tre_mm,
                );
            }
            Err(_) => failed += 1,
        }
        progress(k + 1, scenarios.len());
    }
    let med = |f: fn(&RegistrationTimings) -> f64| {
        Spread::of(&runs.iter().map(f).collect::<Vec<_>>()).median
    };
    let mean_of = |f: fn(&RegistrationTimings) -> usize| {
        runs.iter().map(|r| f(r) as f64).sum::<f64>() / runs.len().max(1) as f64
    };
    Ok(RegistrationBench {
        count: runs.len(),
        failed,
        per_category,
        total_s: Spread::of(&runs.iter().map(|r| r.total_s).collect::<Vec<_>>()),
        first_s: Spread::of(&runs.iter().map(|r| r.first_s).collect::<Vec<_>>()),
        answered_twice: runs.iter().filter(|r| r.answered_twice).count(),
        median: RegistrationTimings {
            total_s: med(|r| r.total_s),
            first_s: med(|r| r.first_s),
            answered_twice: false,
            wicp_s: med(|r| r.wicp_s),
            libr_matching_s: med(|r| r.libr_matching_s),
            libr_assemble_s: med(|r| r.libr_assemble_s),
            libr_solve_s: med(|r| r.libr_solve_s),
            libr_other_s: med(|r| r.libr_other_s),
            libr_s: med(|r| r.libr_s),
            gcn_s: med(|r| r.gcn_s),
            gcn_network_s: med(|r| r.gcn_network_s),
            gcn_refit_s: med(|r| r.gcn_refit_s),
            v2s_s: med(|r| r.v2s_s),
            v2s_network_s: med(|r| r.v2s_network_s),
            wicp_iterations: med(|r| r.wicp_iterations as f64).round() as usize,
            libr_iterations: med(|r| r.libr_iterations as f64).round() as usize,
        },
        wicp_iterations_mean: mean_of(|r| r.wicp_iterations),
        libr_iterations_mean: mean_of(|r| r.libr_iterations),
        libr_converged: converged,
        tre_mm_mean: Spread::of(&tres).mean,
        runs,
    })
}

/// One registration as `asked`, with its timings; in two answers, the time to the first and
/// the whole (wall clock, both answers).
fn timed(
    case: &Prepared,
    meas: &crate::register::Checked,
    asked: Asked<'_>,
) -> Result<(Registration, RegistrationTimings), crate::pipeline::PipelineError> {
    if !asked.progressive {
        let r = register(case, meas, asked.method, asked.params)?;
        let t = RegistrationTimings::from(&r);
        return Ok((r, t));
    }
    let t0 = std::time::Instant::now();
    let first_at = std::sync::OnceLock::new();
    let r = crate::pipeline::register_progressive(case, meas, asked.method, asked.params, &|_| {
        let _ = first_at.set(crate::util::secs(t0));
    })?;
    let first = first_at.get().copied();
    let total = crate::util::secs(t0);
    let t = RegistrationTimings {
        total_s: total,
        first_s: first.unwrap_or(total),
        answered_twice: first.is_some(),
        ..RegistrationTimings::from(&r)
    };
    Ok((r, t))
}
