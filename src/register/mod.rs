//! Registration: what runs in surgery. From the preoperative model and sparse intraoperative
//! measurements to a rigid transform and per-node displacements.
//!
//! This module owns correspondence (closest points on the model's surfaces and vessel centerlines,
//! with robust trimming), rigid salient-feature weighted ICP (`wicp`, after Clements et al. 2008)
//! and LIBR (`libr`, linearized iterative boundary reconstruction after Heiselman & Miga, IEEE TMI
//! 2020). It never imports `phantom`: at surgery time there is no ground truth, only
//! [`PreopModel`] (built from the preoperative mesh and its labels, e.g. a dataset's `preop.vtu`)
//! and [`Measurements`].
//!
//! Frames: the model lives in the image frame; measurements arrive in the physical frame.
//! A registration returns `image_to_physical` (rigid) and node displacements `u` in the image frame,
//! so the intraoperative position of node i is `image_to_physical.apply(X_i + u_i)`.

pub mod accelerate;
pub mod anatomy;
pub mod correspondence;
pub mod equilibrium;
mod error;
pub mod libr;
pub mod measured;
pub mod nonlinear;
pub mod physics;
mod preop_file;
pub mod prior;
pub mod reduce;
pub mod uncertainty;
pub mod wicp;

pub use error::RegisterError;
pub use measured::Checked;

use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;

/// Kind of a measured point (the dataset's `kind` values).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[repr(u8)]
pub enum MeasuredKind {
    /// Anterior-surface point (stylus, stereo laparoscope).
    Surface = 0,
    /// Ultrasound: posterior-surface contour point.
    PosteriorContour = 1,
    /// Ultrasound: vessel-feature point (a vessel centreline crossing the image plane).
    Vessel = 2,
}

impl MeasuredKind {
    /// From the dataset's numeric code.
    pub fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Self::Surface),
            1 => Some(Self::PosteriorContour),
            2 => Some(Self::Vessel),
            _ => None,
        }
    }
}

/// The preoperative model as registration sees it (image frame, mm).
#[derive(Debug, Clone)]
pub struct PreopModel {
    /// The preoperative tet mesh.
    pub mesh: TetMesh,
    /// Per node: on the anterior (visible) surface.
    pub anterior: Vec<bool>,
    /// Per node: on the posterior surface.
    pub posterior: Vec<bool>,
    /// Per node: on the falciform ligament (salient feature).
    pub falciform: Vec<bool>,
    /// Per node: on the inferior ridge (salient feature).
    pub inferior_ridge: Vec<bool>,
    /// Vessel centerline points (mm) and segments `[a, b]` between them.
    pub vessel_points: Vec<[f64; 3]>,
    /// Vessel centerline segments.
    pub vessel_segments: Vec<[u32; 2]>,
}

impl PreopModel {
    /// Per node: on the boundary (the anterior or the posterior surface).
    pub fn boundary_flags(&self) -> Vec<bool> {
        self.anterior
            .iter()
            .zip(&self.posterior)
            .map(|(a, p)| *a || *p)
            .collect()
    }
}

/// Sparse intraoperative measurements (physical frame, mm).
#[derive(Debug, Clone, Default)]
pub struct Measurements {
    /// Points.
    pub points: Vec<[f64; 3]>,
    /// Kind of each point.
    pub kind: Vec<MeasuredKind>,
    /// Per point: the surgeon designated it as on a salient feature (0 none, 1 falciform
    /// ligament, 2 inferior ridge). Empty when not available.
    pub feature: Vec<u8>,
    /// The navigation system's coarse initial alignment, image → physical.
    pub initial_alignment: Option<Rigid>,
}

impl Measurements {
    /// The points `keep` (indices into these measurements), in that order, with their kinds and
    /// features and the same initial alignment.
    pub fn subset(&self, keep: &[usize]) -> Measurements {
        Measurements {
            points: keep.iter().map(|&i| self.points[i]).collect(),
            kind: keep.iter().map(|&i| self.kind[i]).collect(),
            feature: if self.feature.is_empty() {
                Vec::new()
            } else {
                keep.iter().map(|&i| self.feature[i]).collect()
            },
            initial_alignment: self.initial_alignment,
        }
    }
}

/// A measured point matched to the model: the model point it corresponds to is
/// `anchor + Σ_k bary[k] · u[nodes[k]]` for node displacements `u` (image frame) — linear in `u`,
/// which is what LIBR's least squares needs. Surface and contour matches interpolate a boundary
/// triangle (`bary[3] = 0`, `nodes[3] = nodes[0]`); vessel matches interpolate the tet containing
/// the centreline point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    /// Index of the measured point.
    pub point: usize,
    /// Position of the matched model point on the undeformed model (image frame, mm).
    pub anchor: [f64; 3],
    /// Nodes whose displacements move the matched point.
    pub nodes: [u32; 4],
    /// Interpolation weights of those nodes (sum 1).
    pub bary: [f64; 4],
    /// Weight of the pair in the misfit (kind weight × feature weight × robust weight).
    pub weight: f64,
    /// Unit normal of the matched surface at the current estimate (image frame), or zero. With a
    /// normal, LIBR weighs the misfit along it fully and across it by `tangential_weight`
    /// (point-to-plane: a point may slide along the surface it lies on, which is what closest-point
    /// correspondences cannot pin down); without, the full distance counts (point-to-point).
    pub normal: [f64; 3],
}

impl Match {
    /// The matched model point under node displacements `u` (node-major, 3n).
    pub fn model_point(&self, u: &[f64]) -> [f64; 3] {
        let mut p = self.anchor;
        for (k, &n) in self.nodes.iter().enumerate() {
            for a in 0..3 {
                p[a] += self.bary[k] * u[3 * n as usize + a];
            }
        }
        p
    }
}
