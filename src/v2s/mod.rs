//! V2S: the LIBR+ paper's purely data-driven baseline, after V2S-Net (Pfeiffer et al., "Non-Rigid
//! Volume to Surface Registration using a Data-Driven Biomechanical Model", MICCAI 2020): a 3-D
//! U-Net ([`model`]) reads the preoperative liver and the intraoperative points as fields on a
//! regular grid around the liver ([`grid`]) and outputs a displacement field on that grid, which
//! trilinear interpolation carries to the mesh nodes. It has no physics prior: it is trained on
//! the ground-truth displacement alone (`librplus train --method v2s`).
//!
//! **Rigid alignment first**, as V2S-Net assumes: the measured points are brought into the image
//! frame by the case's wICP result (the same rigid stage every other method starts from), and the
//! network's displacement is in the image frame: node `i` is at `T_wICP(X_i + u_i)`.
//!
//! **Inputs** ([`INPUTS`] channels on the grid, distances divided by [`DISTANCE_UNIT_MM`] and
//! clamped to ±[`DISTANCE_CLAMP`]):
//! 0. the preoperative liver's signed distance (negative inside), as V2S-Net;
//! 1. the distance to the preoperative vessel centrelines (the clamp where the model has none);
//! 2. the distance to the nearest measured anterior-surface point, as V2S-Net's partial-surface
//!    channel;
//! 3. the distance to the nearest ultrasound posterior-contour point;
//! 4. the distance to the nearest ultrasound vessel point.
//!
//! Channels 1, 3 and 4 go beyond V2S-Net (surface only), so that it sees what LIBR sees; a kind
//! absent from the measurements leaves its channel at the clamp.
//!
//! **Output**: `[1, 3, n, n, n]` in [`OUTPUT_UNIT_MM`], interpolated to the nodes by a constant
//! sparse matrix (differentiable, so training's loss is on the nodes, where the truth is).

pub mod grid;
pub mod io;
pub mod model;

use std::sync::Arc;
use std::time::Instant;

use burn::tensor::{Device, Tensor, TensorData};

use crate::gcn::sparse::SparseOp;
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::mesh::spatial::{SignedDistance, point_segment_distance};
use crate::register::{Checked, MeasuredKind};
use grid::Grid;
use io::V2sModel;
use model::V2sConfig;

/// Input channels of the network.
pub const INPUTS: usize = 5;

/// Distances in the inputs are in this unit (mm).
pub const DISTANCE_UNIT_MM: f64 = 20.0;

/// Input distances are clamped to ± this many units (60 mm).
pub const DISTANCE_CLAMP: f64 = 3.0;

/// The network's displacement output is in this unit (mm).
pub const OUTPUT_UNIT_MM: f64 = 10.0;

/// Errors of V2S: inputs, model files, the network's output.
#[derive(Debug, thiserror::Error)]
pub enum V2sError {
    /// Invalid input: shapes, settings, a degenerate mesh.
    #[error("V2S: {0}")]
    Invalid(String),
    /// A model directory or weights file is unreadable or of another format.
    #[error("V2S model: {0}")]
    ModelFile(String),
    /// The network's output came out non-finite.
    #[error("V2S: the network's displacement is not finite")]
    NonFinite,
}

/// One input distance (mm) as the network reads it.
pub fn encode_distance(d_mm: f64) -> f32 {
    (d_mm / DISTANCE_UNIT_MM).clamp(-DISTANCE_CLAMP, DISTANCE_CLAMP) as f32
}

/// The preoperative liver on the grid, built once per case: the grid, the channels that do not
/// change during surgery, and the interpolation to the mesh nodes.
#[derive(Debug, Clone)]
pub struct V2sFrame {
    /// The grid around the preoperative mesh.
    pub grid: Grid,
    /// Channels 0 and 1 (signed distance, vessel distance), encoded, `[2, n³]`.
    pub preop: Vec<f32>,
    /// Trilinear interpolation from the grid to the nodes, `[V, n³]`.
    pub interpolation: SparseOp,
}

impl V2sFrame {
    /// The frame of the preoperative `mesh` (with its vessel centreline segments, possibly none)
    /// for a network of `cfg`.
    pub fn new(
        mesh: &TetMesh,
        vessels: (&[[f64; 3]], &[[u32; 2]]),
        cfg: &V2sConfig,
    ) -> Result<Self, V2sError> {
        cfg.validate()?;
        let grid = Grid::around(mesh.nodes(), cfg.grid, cfg.margin)?;
        let surface = mesh
            .boundary_surface()
            .map_err(|e| V2sError::Invalid(format!("the mesh's boundary: {e}")))?;
        let sd = SignedDistance::new(&surface)
            .map_err(|e| V2sError::Invalid(format!("the mesh's boundary: {e}")))?;
        let mut preop: Vec<f32> = grid
            .signed_distance(&sd)
            .into_iter()
            .map(encode_distance)
            .collect();
        let (vp, vs) = vessels;
        if let Some(s) = vs
            .iter()
            .find(|s| s.iter().any(|&i| i as usize >= vp.len()))
        {
            return Err(V2sError::Invalid(format!(
                "vessel segment {s:?} names a point beyond the {} centreline points",
                vp.len()
            )));
        }
        use rayon::prelude::*;
        let vessel: Vec<f32> = (0..grid.len())
            .into_par_iter()
            .map(|i| {
                let p = grid.point(i);
                let d = vs
                    .iter()
                    .map(|s| point_segment_distance(p, vp[s[0] as usize], vp[s[1] as usize]).0)
                    .fold(f64::INFINITY, f64::min);
                encode_distance(d)
            })
            .collect();
        preop.extend(vessel);
        let interpolation = SparseOp::new(grid.interpolation(mesh.nodes())?);
        Ok(Self {
            grid,
            preop,
            interpolation,
        })
    }

    /// The network's input for measured `points` of `kinds` already in the image frame:
    /// `[INPUTS · n³]`, channel-major.
    pub fn input(&self, points: &[[f64; 3]], kinds: &[MeasuredKind]) -> Vec<f32> {
        let mut x = self.preop.clone();
        for kind in [
            MeasuredKind::Surface,
            MeasuredKind::PosteriorContour,
            MeasuredKind::Vessel,
        ] {
            let pts: Vec<[f64; 3]> = points
                .iter()
                .zip(kinds)
                .filter(|(_, k)| **k == kind)
                .map(|(p, _)| *p)
                .collect();
            match self.grid.distance_to(&pts) {
                Some(d) => x.extend(d.into_iter().map(encode_distance)),
                None => x.extend(std::iter::repeat_n(DISTANCE_CLAMP as f32, self.grid.len())),
            }
        }
        x
    }

    /// The input for `meas` (physical frame) under the rigid `image_to_physical`.
    pub fn input_for(&self, meas: &Checked, image_to_physical: &Rigid) -> Vec<f32> {
        let inv = image_to_physical.inverse();
        let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
        self.input(&pts, &meas.kind)
    }

    /// The input as a tensor `[1, INPUTS, n, n, n]`.
    pub fn tensor(&self, input: Vec<f32>, device: &Device) -> Tensor<5> {
        let n = self.grid.n;
        Tensor::from_data(TensorData::new(input, [1, INPUTS, n, n, n]), device)
    }

    /// The network's grid output `[1, 3, n, n, n]` at the nodes, `[V, 3]` (output units;
    /// differentiable).
    pub fn at_nodes(&self, out: Tensor<5>) -> Result<Tensor<2>, V2sError> {
        let [b, c, n0, n1, n2] = out.dims();
        if b != 1 || c != 3 || n0 * n1 * n2 != self.grid.len() {
            return Err(V2sError::Invalid(format!(
                "grid output {:?} for a {}³ grid",
                out.dims(),
                self.grid.n
            )));
        }
        let flat: Tensor<2> = out.reshape([3, self.grid.len()]).transpose();
        self.interpolation
            .apply(flat)
            .map_err(|e| V2sError::Invalid(format!("interpolation to the nodes: {e}")))
    }
}

/// A trained V2S network ready for one case.
#[derive(Debug)]
pub struct V2sCase {
    /// The network (shared between cases).
    pub model: Arc<V2sModel>,
    /// The case's grid and preoperative channels.
    pub frame: V2sFrame,
}

impl V2sCase {
    /// Prepares `model` for the preoperative `mesh` and its vessel centrelines.
    pub fn new(
        model: Arc<V2sModel>,
        mesh: &TetMesh,
        vessels: (&[[f64; 3]], &[[u32; 2]]),
    ) -> Result<Self, V2sError> {
        let frame = V2sFrame::new(mesh, vessels, &model.config)?;
        Ok(Self { model, frame })
    }

    /// Node displacements (image frame, mm, node-major `3V`) for `meas` after the rigid
    /// `image_to_physical`, and the network's share of the time (s).
    pub fn displacement(
        &self,
        meas: &Checked,
        image_to_physical: &Rigid,
    ) -> Result<(Vec<f64>, f64), V2sError> {
        let device = crate::gcn::device::compute();
        let x = self
            .frame
            .tensor(self.frame.input_for(meas, image_to_physical), &device);
        let t0 = Instant::now();
        let y = self.model.net.forward(x)?;
        let nodes = self.frame.at_nodes(y)?;
        let v = nodes
            .into_data()
            .convert::<f32>()
            .try_to_vec::<f32>()
            .map_err(|e| V2sError::Invalid(format!("{e:?}")))?;
        let seconds = t0.elapsed().as_secs_f64();
        if v.iter().any(|x| !x.is_finite()) {
            return Err(V2sError::NonFinite);
        }
        Ok((
            v.into_iter().map(|x| OUTPUT_UNIT_MM * x as f64).collect(),
            seconds,
        ))
    }
}

#[cfg(test)]
mod tests;
