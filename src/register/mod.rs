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
