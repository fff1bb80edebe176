//! Evaluation: target registration error against the ground truth, and loading dataset scenarios.
//!
//! TRE is the mean over mesh nodes of the distance between predicted and ground-truth node
//! positions, both in the physical frame: predicted `T_est(X + u_est)`, true `T_true(X + u_true)`.
//! It is also reported for surface nodes, interior nodes and the labelled targets. Evaluation may
//! read the ground truth; registration (`crate::register`) never does — [`ScenarioData`] keeps the
//! two apart (`measurements` vs `truth`).

use crate::mesh::TetMesh;
use crate::mesh::io::{DataArray, MeshFile};
use crate::mesh::rigid::Rigid;

// The dataset readers, where evaluation code has always found them.
pub use crate::dataset::read::{
    GeometryData, PlanePose, ScenarioData, ScenarioPlanes, Truth, load_geometry,
    load_scenario_planes, load_scenarios, open,
};

/// Runs `run` on every kept scenario of the dataset in `dir` (every `every`-th block of five
/// scenarios of each deformation, as `evaluate` keeps them; in parallel within a deformation),
/// each geometry prepared once by `prepare`, and returns what it gives in dataset order.
/// `per_scenario` registrations are counted per scenario in `progress(done, total)`; `run`
/// calls its `tick` once per registration.
pub(crate) fn over_kept_scenarios<C: Sync, T: Send>(
    dir: &std::path::Path,
    every: usize,
    per_scenario: usize,
    prepare: impl Fn(&GeometryData) -> Result<C, EvalError>,
    run: impl Fn(&C, &ScenarioData, &(dyn Fn() + Sync)) -> Vec<T> + Sync,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<T>, EvalError> {
    use rayon::prelude::*;
    let m = open(dir)?;
    let every = every.max(1);
    let block = report::CATEGORY_ORDER.len();
    let keep = |i: usize| (i / block) % every == 0;
    let total: usize = m
        .deformations
        .iter()
        .map(|d| (0..d.scenarios.len()).filter(|&i| keep(i)).count() * per_scenario)
        .sum();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let tick = || {
        let k = done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
        progress(k, total);
    };
    let mut prepared: std::collections::BTreeMap<String, C> = Default::default();
    let mut out = Vec::new();
    for d in &m.deformations {
        if !prepared.contains_key(&d.geometry) {
            let geo = load_geometry(dir, &m, &d.geometry)?;
            prepared.insert(d.geometry.clone(), prepare(&geo)?);
        }
        let case = &prepared[&d.geometry];
        let scenarios = load_scenarios(dir, d)?;
        let picked: Vec<_> = scenarios
            .iter()
            .enumerate()
            .filter(|(i, _)| keep(*i))
            .map(|(_, s)| s)
            .collect();
        let results: Vec<Vec<T>> = picked.par_iter().map(|sc| run(case, sc, &tick)).collect();
        out.extend(results.into_iter().flatten());
    }
    Ok(out)
}

pub mod abstain;
pub mod bench;
pub mod calibrate_error;
pub mod campaign;
pub mod detectability;
pub mod discover_score;
pub mod discover_study;
mod error;
pub use error::EvalError;
pub mod experiments;
pub mod plot;
pub mod report;
pub mod report_dir;
pub mod runs;
pub mod splits;
pub mod train;
pub mod train_run;

/// Target registration errors (mm).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Tre {
    /// Mean over all nodes.
    pub tre_mm: f64,
    /// Mean over boundary nodes.
    pub tre_surface_mm: f64,
    /// Mean over interior nodes.
    pub tre_interior_mm: f64,
    /// Mean over the labelled targets (NaN when there are none).
    pub tre_targets_mm: f64,
    /// Largest node error.
    pub max_mm: f64,
}

/// Per-node distance (mm) between predicted and true node positions, both in the physical frame:
/// `|T_est(X_i + u_est,i) − T_true(X_i + u_true,i)|` for node i. The one definition of the node
/// error that [`tre`], `evaluate`'s error maps and `register --out` share.
pub fn node_errors_mm(
    nodes: &[[f64; 3]],
    predicted: (&Rigid, &[f64]),
    truth: (&Rigid, &[f64]),
) -> Vec<f64> {
    nodes
        .iter()
        .enumerate()
        .map(|(i, x)| {
            let at = |u: &[f64]| [0, 1, 2].map(|a| x[a] + u[3 * i + a]);
            let p = predicted.0.apply(at(predicted.1));
            let q = truth.0.apply(at(truth.1));
            ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
        })
        .collect()
}

/// TRE of a prediction. `surface` flags boundary nodes; `targets` are node ids.
pub fn tre(
    nodes: &[[f64; 3]],
    predicted: (&Rigid, &[f64]),
    truth: (&Rigid, &[f64]),
    surface: &[bool],
    targets: &[u32],
) -> Tre {
    tre_from_errors(&node_errors_mm(nodes, predicted, truth), surface, targets)
}

/// TRE from per-node errors ([`node_errors_mm`]). `surface` flags boundary nodes; `targets` are
/// node ids.
pub fn tre_from_errors(err: &[f64], surface: &[bool], targets: &[u32]) -> Tre {
    let mean = |it: &mut dyn Iterator<Item = f64>| {
        let (s, c) = it.fold((0.0, 0usize), |(s, c), e| (s + e, c + 1));
        if c == 0 { f64::NAN } else { s / c as f64 }
    };
    Tre {
        tre_mm: mean(&mut err.iter().copied()),
        tre_surface_mm: mean(&mut err.iter().zip(surface).filter(|x| *x.1).map(|x| *x.0)),
        tre_interior_mm: mean(&mut err.iter().zip(surface).filter(|x| !*x.1).map(|x| *x.0)),
        tre_targets_mm: mean(&mut targets.iter().map(|&t| err[t as usize])),
        max_mm: err.iter().copied().fold(0.0, f64::max),
    }
}

/// The preoperative mesh as a mesh file carrying per-node arrays (an error map: open it in
/// ParaView or 3D Slicer and colour by an array). Pure: write it with [`crate::mesh::io::write`].
pub fn error_map_file(mesh: &TetMesh, point_data: Vec<DataArray>) -> MeshFile {
    let mut f = mesh.to_file();
    f.point_data = point_data;
    f
}
