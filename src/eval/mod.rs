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

pub mod abstain;
pub mod bench;
pub mod calibrate_error;
mod error;
pub use error::EvalError;
pub mod experiments;
pub mod plot;
pub mod report;
pub mod splits;
pub mod train;

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
