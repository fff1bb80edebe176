//! Sparse intraoperative measurements of a deformed liver, as the registration would receive them:
//! this module owns the scenario categories, the simulation of anterior-surface points, ultrasound
//! planes (posterior-contour and vessel-feature points in a fan), the rigid misalignment between the
//! image and the physical frame, and the coarse landmark alignment a navigation system starts from.
//!
//! Everything happens on the deformed geometry `X + u` in the image (preoperative) frame and is then
//! mapped to the physical frame by the true misalignment `T`:
//!
//! - **Surface**: a connected visible patch of anterior boundary triangles (all three nodes labelled
//!   [`Region::Anterior`]) grows from an area-weighted random seed triangle in order of geodesic
//!   distance (Dijkstra over edge-adjacent triangles, centroid to centroid; when its component is
//!   exhausted it jumps to the nearest unvisited anterior triangle) until its area reaches the
//!   drawn coverage × the anterior area. Points are dart-thrown on it: area-weighted random
//!   candidates (10 per `spacing²` of patch area) are kept when no kept point is nearer than
//!   `surface_spacing_mm`. Isotropic Gaussian noise follows. A surface point whose noise-free
//!   position is within `feature_radius_mm` of a (deformed) falciform or inferior-ridge node is
//!   designated on that salient feature, the nearer one winning (surgeons trace them separately for
//!   weighted ICP).
//! - **Ultrasound planes**: probe contacts are anterior nodes spread by farthest-point sampling from a
//!   random start (nodes inside the anterior region are preferred over nodes on its border). The
//!   beam points along the inward vertex normal (`depth_dir`), the lateral direction is random in the
//!   tangent plane. The plane cuts the posterior triangles (all nodes [`Region::Posterior`]) in
//!   polylines, which are sampled every `us_spacing_mm` of arc length from a random phase; vessel
//!   centerline segments, deformed by interpolating `u`, give one point where they cross the plane.
//!   Only points inside the fan (in-plane angle from `depth_dir` ≤ `fan_half_angle_deg`, distance
//!   from the contact ≤ `fan_depth_mm`) are kept. Their noise is Gaussian **within the plane**
//!   (along `depth_dir` and `lateral_dir`), as an ultrasound image has no out-of-plane coordinate.
//! - **Misalignment**: rotation about a uniformly random axis by an angle uniform in
//!   `[0, max_rotation_deg]`, **about the centroid `c` of the mesh nodes**, and a translation of that
//!   centroid uniform in the ball of radius `max_translation_mm`: `T(p) = R (p − c) + c + t`. Noise is
//!   added in the image frame before `T`; since `T` is rigid and the noise isotropic (surface) or
//!   in-plane (ultrasound), this is the same distribution as adding it after.
//! - **Landmarks**: the highest falciform node, the two lateral ends of the inferior ridge, and the
//!   ridge node nearest the falciform plane (the umbilical notch), then farthest anterior nodes when
//!   more are asked for or labels are missing. Measured as `T(X + u)` plus per-axis Gaussian noise;
//!   the coarse start is the rigid fit from their preoperative positions.
//!
//! Each random stage draws from its own stream derived from the seed, so for one seed the surface
//! patch, the misalignment and the landmarks are the same in every category, the first planes of a
//! larger category are those of a smaller one, and noise levels do not change the noise-free
//! geometry.

mod sampling;

use crate::phantom::PhantomError;
use sampling::*;

use crate::mesh::TetMesh;
use crate::mesh::locate::TetLocator;
use crate::mesh::rigid::Rigid;
use crate::mesh::vec3::{add, cross, dot, norm, scale, sub};
use crate::phantom::vessels::VesselTree;
use crate::register::anatomy::{AnatomyLabels, Region};
use crate::util::SplitMix64;

/// What a scenario measures: the anterior surface, plus 0, 1, 2, 3 or 16 ultrasound planes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub enum Category {
    /// Anterior surface points only.
    Surface,
    /// Surface and one ultrasound plane.
    Planes1,
    /// Surface and two ultrasound planes.
    Planes2,
    /// Surface and three ultrasound planes.
    Planes3,
    /// Surface and sixteen ultrasound planes.
    Planes16,
}

impl Category {
    /// All categories, from sparsest to richest.
    pub const ALL: [Category; 5] = [
        Category::Surface,
        Category::Planes1,
        Category::Planes2,
        Category::Planes3,
        Category::Planes16,
    ];

    /// Number of ultrasound planes.
    pub fn planes(self) -> usize {
        match self {
            Category::Surface => 0,
            Category::Planes1 => 1,
            Category::Planes2 => 2,
            Category::Planes3 => 3,
            Category::Planes16 => 16,
        }
    }

    /// Short name for files and tables ("surface", "surface+1us", …).
    pub fn name(self) -> &'static str {
        match self {
            Category::Surface => "surface",
            Category::Planes1 => "surface+1us",
            Category::Planes2 => "surface+2us",
            Category::Planes3 => "surface+3us",
            Category::Planes16 => "surface+16us",
        }
    }
}

/// What a measured point is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[repr(u8)]
pub enum PointKind {
    /// Anterior-surface point (laparoscope or stylus).
    Surface = 0,
    /// Posterior-surface contour point in an ultrasound plane.
    PosteriorContour = 1,
    /// Vessel centerline crossing an ultrasound plane.
    Vessel = 2,
}

/// Which side of the organ the laparoscope sees ([`MeasureParams::visible`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Visible {
    /// The labelled anterior surface (the default: an open or laparoscopic view from the front).
    #[default]
    Anterior,
    /// The half of the boundary facing posterior (+y of the image frame, LPS).
    Posterior,
    /// The half facing superior (+z): the dome under the diaphragm.
    Dome,
    /// The half facing the patient's left (+x).
    Left,
    /// The half facing the patient's right (−x).
    Right,
    /// The half facing a direction drawn uniformly on the sphere per scenario (its own stream).
    Any,
}

impl Visible {
    /// Whether it is the default.
    pub fn is_anterior(&self) -> bool {
        *self == Visible::Anterior
    }
}

/// Parameters of the measurement simulation. Lengths in mm, angles in degrees.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MeasureParams {
    /// Range of the anterior-area fraction covered, drawn uniformly per scenario. Default [0.15, 0.60].
    pub coverage: [f64; 2],
    /// Minimum (≈ typical) spacing of surface points. Default 5.
    pub surface_spacing_mm: f64,
    /// Standard deviation of the isotropic Gaussian noise on surface points. Default 1.
    pub surface_noise_mm: f64,
    /// Arc-length spacing of contour points along a plane's cut of the posterior surface. Default 3.
    pub us_spacing_mm: f64,
    /// Standard deviation of the in-plane Gaussian noise on ultrasound points (per axis). Default 0.5.
    pub us_noise_mm: f64,
    /// Depth of the ultrasound fan. Default 120.
    pub fan_depth_mm: f64,
    /// Half opening angle of the fan, in (0, 90]. Default 35.
    pub fan_half_angle_deg: f64,
    /// Largest misalignment rotation. Default 15.
    pub max_rotation_deg: f64,
    /// Largest misalignment translation (of the mesh centroid). Default 20.
    pub max_translation_mm: f64,
    /// Number of landmarks for the coarse alignment (≥ 3). Default 4.
    pub landmarks: usize,
    /// Standard deviation of the landmark noise per axis. Default 4.
    pub landmark_noise_mm: f64,
    /// A surface point within this distance of a falciform or inferior-ridge node is designated
    /// as on that salient feature (as a surgeon traces them separately). Default 5.
    pub feature_radius_mm: f64,
    /// The navigation system's start is the true alignment (an organ held in place and tracked,
    /// no landmark fit); default false: the rigid fit of noisy landmarks. Left out of the
    /// parameters (and their hash) when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub trusted_start: bool,
    /// A harder navigation start: the start as drawn (the landmark fit, or the true alignment
    /// with `trusted_start`) moved further by a random rotation of up to `[0]` degrees about
    /// where it puts the organ's centroid and a shift of up to `[1]` mm (uniform in the ball),
    /// from a draw of its own (every other draw stays as it was). None (the default): the start
    /// as drawn; left out of the parameters (and their hash) when None.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_error: Option<[f64; 2]>,
    /// The side whose surface the patch is cut from. A side other than the anterior one is the
    /// boundary triangles whose outward normal (on the deformed organ) faces that direction;
    /// the coverage is a fraction of its area. Left out of the parameters (and their hash) for
    /// the default, anterior.
    #[serde(default, skip_serializing_if = "Visible::is_anterior")]
    pub visible: Visible,
}

impl Default for MeasureParams {
    fn default() -> Self {
        Self {
            coverage: [0.15, 0.60],
            surface_spacing_mm: 5.0,
            surface_noise_mm: 1.0,
            us_spacing_mm: 3.0,
            us_noise_mm: 0.5,
            fan_depth_mm: 120.0,
            fan_half_angle_deg: 35.0,
            max_rotation_deg: 15.0,
            max_translation_mm: 20.0,
            landmarks: 4,
            landmark_noise_mm: 4.0,
            feature_radius_mm: 5.0,
            trusted_start: false,
            start_error: None,
            visible: Visible::Anterior,
        }
    }
}

impl MeasureParams {
    /// Checks every parameter, naming the first one out of range.
    pub fn validate(&self) -> Result<(), PhantomError> {
        let [c0, c1] = self.coverage;
        if !(c0 > 0.0 && c0 <= c1 && c1 <= 1.0) {
            return Err(PhantomError::Parameter(format!(
                "coverage must satisfy 0 < min ≤ max ≤ 1, got [{c0}, {c1}]"
            )));
        }
        let positive = [
            ("surface_spacing_mm", self.surface_spacing_mm),
            ("us_spacing_mm", self.us_spacing_mm),
            ("fan_depth_mm", self.fan_depth_mm),
        ];
        for (name, v) in positive {
            if !(v > 0.0 && v.is_finite()) {
                return Err(PhantomError::Parameter(format!(
                    "{name} must be positive and finite, got {v}"
                )));
            }
        }
        let non_negative = [
            ("surface_noise_mm", self.surface_noise_mm),
            ("us_noise_mm", self.us_noise_mm),
            ("max_translation_mm", self.max_translation_mm),
            ("landmark_noise_mm", self.landmark_noise_mm),
            ("feature_radius_mm", self.feature_radius_mm),
        ];
        for (name, v) in non_negative {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(PhantomError::Parameter(format!(
                    "{name} must be ≥ 0 and finite, got {v}"
                )));
            }
        }
        if !(self.fan_half_angle_deg > 0.0 && self.fan_half_angle_deg <= 90.0) {
            return Err(PhantomError::Parameter(format!(
                "fan_half_angle_deg must be in (0, 90], got {}",
                self.fan_half_angle_deg
            )));
        }
        if !(self.max_rotation_deg >= 0.0 && self.max_rotation_deg <= 180.0) {
            return Err(PhantomError::Parameter(format!(
                "max_rotation_deg must be in [0, 180], got {}",
                self.max_rotation_deg
            )));
        }
        if self.landmarks < 3 {
            return Err(PhantomError::Parameter(format!(
                "landmarks must be at least 3 for a rigid fit, got {}",
                self.landmarks
            )));
        }
        if let Some([deg, mm]) = self.start_error {
            if !((0.0..=180.0).contains(&deg) && mm.is_finite() && mm >= 0.0) {
                return Err(PhantomError::Parameter(format!(
                    "start_error must be [degrees in [0, 180], mm ≥ 0 and finite], got [{deg}, {mm}]"
                )));
            }
        }
        Ok(())
    }
}

/// An ultrasound plane in the physical frame: the probe contact and an orthonormal frame.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct UsPlane {
    /// Probe contact on the anterior surface (apex of the fan).
    pub origin: [f64; 3],
    /// Beam direction into the liver (unit).
    pub depth_dir: [f64; 3],
    /// In-plane direction across the beam (unit).
    pub lateral_dir: [f64; 3],
    /// Plane normal, `depth_dir × lateral_dir`.
    pub normal: [f64; 3],
}

impl UsPlane {
    /// Whether `q` (in the plane's frame) lies in the fan of depth `depth` and half angle
    /// `half_angle_deg`, judged from its in-plane components.
    pub fn in_fan(&self, q: [f64; 3], depth: f64, half_angle_deg: f64) -> bool {
        let d = sub(q, self.origin);
        let a = dot(d, self.depth_dir);
        let b = dot(d, self.lateral_dir);
        a * a + b * b <= depth * depth && b.abs().atan2(a) <= half_angle_deg.to_radians()
    }

    /// The plane mapped by a rigid transform.
    pub fn transformed(&self, t: &Rigid) -> UsPlane {
        UsPlane {
            origin: t.apply(self.origin),
            depth_dir: t.apply_vector(self.depth_dir),
            lateral_dir: t.apply_vector(self.lateral_dir),
            normal: t.apply_vector(self.normal),
        }
    }
}

/// One simulated measurement configuration of one deformed liver.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Scenario {
    /// What was measured.
    pub category: Category,
    /// The seed it was simulated with.
    pub seed: u64,
    /// Achieved fraction of the (deformed) anterior area covered by the visible patch.
    pub coverage: f64,
    /// Measured points, physical frame, noisy: all the registration may see.
    pub points: Vec<[f64; 3]>,
    /// Kind of each point.
    pub kind: Vec<PointKind>,
    /// Ultrasound plane of each point, −1 for surface points.
    pub plane: Vec<i32>,
    /// Salient feature a surface point was designated on: 0 none, 1 falciform ligament,
    /// 2 inferior ridge (ultrasound points: 0).
    pub feature: Vec<u8>,
    /// The ultrasound planes (physical frame).
    pub planes: Vec<UsPlane>,
    /// Noise-free position of each point in the deformed image frame (evaluation only).
    pub truth_image: Vec<[f64; 3]>,
    /// The true misalignment, image → physical (evaluation only).
    pub image_to_physical: Rigid,
    /// Mesh nodes used as landmarks.
    pub landmark_nodes: Vec<u32>,
    /// Preoperative landmark positions (image frame, undeformed).
    pub landmarks_image: Vec<[f64; 3]>,
    /// Measured landmark positions: `T(X + u)` plus noise (physical frame).
    pub landmarks_physical: Vec<[f64; 3]>,
    /// Rigid fit of `landmarks_image` to `landmarks_physical`: the navigation system's coarse start.
    pub initial_alignment: Rigid,
}

impl Scenario {
    /// Number of points of a kind.
    pub fn count(&self, kind: PointKind) -> usize {
        self.kind.iter().filter(|&&k| k == kind).count()
    }

    /// Number of posterior-contour points in each plane (zero is possible: the fan missed it).
    pub fn contour_counts(&self) -> Vec<usize> {
        self.per_plane(PointKind::PosteriorContour)
    }

    /// Number of vessel-feature points in each plane.
    pub fn vessel_counts(&self) -> Vec<usize> {
        self.per_plane(PointKind::Vessel)
    }

    fn per_plane(&self, kind: PointKind) -> Vec<usize> {
        let mut c = vec![0; self.planes.len()];
        for (k, &p) in self.kind.iter().zip(&self.plane) {
            if *k == kind && p >= 0 {
                c[p as usize] += 1;
            }
        }
        c
    }
}

/// Stream ids of the random stages.
const STREAM_SURFACE: u64 = 1;
const STREAM_PLANES: u64 = 2;
const STREAM_TRANSFORM: u64 = 3;
const STREAM_LANDMARKS: u64 = 4;
const STREAM_NOISE: u64 = 5;
const STREAM_LANDMARK_NOISE: u64 = 6;
const STREAM_START_ERROR: u64 = 7;
const STREAM_VIEW: u64 = 8;

/// An independent generator for one stage of the simulation.
fn stream(seed: u64, id: u64) -> SplitMix64 {
    let mut g = SplitMix64::new(seed ^ id.wrapping_mul(0xD1B5_4A32_D192_ED03));
    SplitMix64::new(g.next_u64())
}

/// Simulates the sparse measurements of the liver deformed by `displacement` (node-major, `3n`).
///
/// Fails only when simulation is impossible: wrong lengths, non-finite values, invalid parameters,
/// a mesh without boundary or without anterior triangles, or collinear landmarks. A plane whose fan
/// misses the posterior surface is returned with no contour points (see
/// [`Scenario::contour_counts`]).
pub fn simulate(
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    vessels: &VesselTree,
    displacement: &[f64],
    category: Category,
    params: &MeasureParams,
    seed: u64,
) -> Result<Scenario, PhantomError> {
    simulate_focused(
        mesh,
        labels,
        vessels,
        displacement,
        category,
        params,
        None,
        seed,
    )
}

/// [`simulate`] with the surface patch grown from the anterior triangle nearest node `focus`
/// (deformed), where a tool acts and the camera looks, instead of an area-weighted random one.
#[allow(clippy::too_many_arguments)]
pub fn simulate_focused(
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    vessels: &VesselTree,
    displacement: &[f64],
    category: Category,
    params: &MeasureParams,
    focus: Option<u32>,
    seed: u64,
) -> Result<Scenario, PhantomError> {
    check_inputs(mesh, labels, vessels, displacement, params)?;
    let n = mesh.num_nodes();
    let rest = mesh.nodes();
    let deformed: Vec<[f64; 3]> = (0..n)
        .map(|i| add(rest[i], [0, 1, 2].map(|k| displacement[3 * i + k])))
        .collect();
    let boundary = mesh.boundary()?;
    let tris = &boundary.triangles;
    let view = View::new(tris, labels, &deformed, params.visible, seed)?;

    // Surface points on a grown visible patch.
    let mut rng = stream(seed, STREAM_SURFACE);
    let [c0, c1] = params.coverage;
    let target = c0 + (c1 - c0) * rng.next_f64();
    let patch = grow_patch(
        tris,
        &view.anterior,
        &view.ant_areas,
        &deformed,
        [target, c0, c1].map(|c| c * view.ant_total),
        focus.and_then(|v| deformed.get(v as usize).copied()),
        &mut rng,
    );
    let patch_area: f64 = patch.iter().map(|&i| view.ant_areas[i]).sum();
    let coverage = patch_area / view.ant_total;
    let patch_tris: Vec<[[f64; 3]; 3]> = patch
        .iter()
        .map(|&i| tris[view.anterior[i]].map(|v| deformed[v as usize]))
        .collect();
    let patch_areas: Vec<f64> = patch.iter().map(|&i| view.ant_areas[i]).collect();
    let surface = dart_throw(
        &patch_tris,
        &patch_areas,
        params.surface_spacing_mm,
        &mut rng,
    );
    let mut noise_rng = stream(seed, STREAM_NOISE);
    let mut pts = Points {
        feature: surface_features(&surface, labels, &deformed, params),
        truth: surface.clone(),
        kind: vec![PointKind::Surface; surface.len()],
        plane_of: vec![-1i32; surface.len()],
        noisy: surface
            .iter()
            .map(|&p| {
                let e = [0; 3].map(|_| params.surface_noise_mm * noise_rng.normal());
                add(p, e)
            })
            .collect(),
    };

    // Ultrasound planes.
    let nplanes = category.planes();
    let mut planes_image = Vec::with_capacity(nplanes);
    if nplanes > 0 {
        let scan = Scan {
            mesh,
            vessels,
            displacement,
            deformed: &deformed,
            tris,
            view: &view,
            params,
        };
        planes_image = scan.planes(nplanes, seed, &mut noise_rng, &mut pts)?;
    }
    let tf = misalignment(rest, params, seed);
    let marks = landmarks(rest, labels, &deformed, &tf, params, seed)?;
    let Points {
        truth,
        kind,
        plane_of,
        feature,
        noisy,
    } = pts;
    let Landmarks {
        landmark_nodes,
        landmarks_image,
        landmarks_physical,
        initial_alignment,
    } = marks;

    Ok(Scenario {
        category,
        seed,
        coverage,
        points: noisy.iter().map(|&p| tf.apply(p)).collect(),
        kind,
        plane: plane_of,
        feature,
        planes: planes_image.iter().map(|p| p.transformed(&tf)).collect(),
        truth_image: truth,
        image_to_physical: tf,
        landmark_nodes,
        landmarks_image,
        landmarks_physical,
        initial_alignment,
    })
}

/// Checks the inputs of [`simulate_focused`]: the displacement and labels have one entry per
/// node, everything is finite, and the vessel segments name vessel points.
fn check_inputs(
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    vessels: &VesselTree,
    displacement: &[f64],
    params: &MeasureParams,
) -> Result<(), PhantomError> {
    params.validate()?;
    let n = mesh.num_nodes();
    if displacement.len() != 3 * n {
        return Err(PhantomError::Inconsistent(format!(
            "displacement has {} values, the mesh has {n} nodes and needs {}",
            displacement.len(),
            3 * n
        )));
    }
    if let Some(i) = displacement.iter().position(|v| !v.is_finite()) {
        return Err(PhantomError::Inconsistent(format!(
            "displacement of node {} is not finite ({})",
            i / 3,
            displacement[i]
        )));
    }
    for (name, len) in [
        ("region", labels.region.len()),
        ("falciform", labels.falciform.len()),
        ("inferior_ridge", labels.inferior_ridge.len()),
    ] {
        if len != n {
            return Err(PhantomError::Inconsistent(format!(
                "labels.{name} has {len} entries, the mesh has {n} nodes"
            )));
        }
    }
    if let Some(i) = vessels
        .points
        .iter()
        .position(|p| p.iter().any(|c| !c.is_finite()))
    {
        return Err(PhantomError::Inconsistent(format!(
            "vessel point {i} is not finite"
        )));
    }
    if let Some(s) = vessels
        .segments
        .iter()
        .find(|s| s.iter().any(|&i| i as usize >= vessels.points.len()))
    {
        return Err(PhantomError::Inconsistent(format!(
            "vessel segment {s:?} refers past the {} vessel points",
            vessels.points.len()
        )));
    }

    Ok(())
}

/// The deformed boundary as a laparoscope and a probe see it: the triangles the laparoscope
/// sees (`anterior`: the labelled anterior ones, or the side [`MeasureParams::visible`] asks
/// for), the labelled anterior ones (where the ultrasound probe touches) and the posterior ones
/// (indices into the boundary's), the seen ones' areas and their total.
struct View {
    anterior: Vec<usize>,
    probe: Vec<usize>,
    posterior: Vec<usize>,
    ant_areas: Vec<f64>,
    ant_total: f64,
}

impl View {
    fn new(
        tris: &[[u32; 3]],
        labels: &AnatomyLabels,
        deformed: &[[f64; 3]],
        visible: Visible,
        seed: u64,
    ) -> Result<Self, PhantomError> {
        let is = |t: &[u32; 3], r: Region| t.iter().all(|&v| labels.region[v as usize] == r);
        let facing = |d: [f64; 3]| -> Vec<usize> {
            (0..tris.len())
                .filter(|&t| {
                    let p = tris[t].map(|v| deformed[v as usize]);
                    dot(cross(sub(p[1], p[0]), sub(p[2], p[0])), d) > 0.0
                })
                .collect()
        };
        let probe: Vec<usize> = (0..tris.len())
            .filter(|&t| is(&tris[t], Region::Anterior))
            .collect();
        let anterior: Vec<usize> = match visible {
            Visible::Anterior => probe.clone(),
            Visible::Posterior => facing([0.0, 1.0, 0.0]),
            Visible::Dome => facing([0.0, 0.0, 1.0]),
            Visible::Left => facing([1.0, 0.0, 0.0]),
            Visible::Right => facing([-1.0, 0.0, 0.0]),
            Visible::Any => facing(unit_sphere(&mut stream(seed, STREAM_VIEW))),
        };
        let posterior: Vec<usize> = (0..tris.len())
            .filter(|&t| is(&tris[t], Region::Posterior))
            .collect();
        let area = |t: usize| {
            let p = tris[t].map(|v| deformed[v as usize]);
            0.5 * norm(cross(sub(p[1], p[0]), sub(p[2], p[0])))
        };
        let ant_areas: Vec<f64> = anterior.iter().map(|&t| area(t)).collect();
        let ant_total: f64 = ant_areas.iter().sum();
        if probe.is_empty() || anterior.is_empty() || ant_total.is_nan() || ant_total <= 0.0 {
            return Err(PhantomError::Inconsistent(format!(
                "no boundary triangle with positive area on the side a laparoscope sees ({visible:?}; anterior: all three nodes labelled Anterior): nothing for a laparoscope to see"
            )));
        }
        Ok(Self {
            anterior,
            probe,
            posterior,
            ant_areas,
            ant_total,
        })
    }
}

/// Salient features of surface points: the nearest labelled falciform (1) or ridge (2) node
/// within the feature radius, else 0.
fn surface_features(
    surface: &[[f64; 3]],
    labels: &AnatomyLabels,
    deformed: &[[f64; 3]],
    params: &MeasureParams,
) -> Vec<u8> {
    let n = deformed.len();
    let falciform: Vec<[f64; 3]> = (0..n)
        .filter(|&i| labels.falciform[i])
        .map(|i| deformed[i])
        .collect();
    let ridge: Vec<[f64; 3]> = (0..n)
        .filter(|&i| labels.inferior_ridge[i])
        .map(|i| deformed[i])
        .collect();
    let nearest = |set: &[[f64; 3]], p: [f64; 3]| {
        set.iter()
            .map(|&q| norm(sub(p, q)))
            .fold(f64::INFINITY, f64::min)
    };
    surface
        .iter()
        .map(|&p| {
            let (df, dr) = (nearest(&falciform, p), nearest(&ridge, p));
            if df.min(dr) > params.feature_radius_mm {
                0
            } else if df <= dr {
                1
            } else {
                2
            }
        })
        .collect()
}

/// The measured points as they are gathered (image frame): truth, kind, plane, feature and
/// noisy position of each.
struct Points {
    truth: Vec<[f64; 3]>,
    kind: Vec<PointKind>,
    plane_of: Vec<i32>,
    feature: Vec<u8>,
    noisy: Vec<[f64; 3]>,
}

/// What the tracked ultrasound probe scans.
struct Scan<'a> {
    mesh: &'a TetMesh,
    vessels: &'a VesselTree,
    displacement: &'a [f64],
    deformed: &'a [[f64; 3]],
    tris: &'a [[u32; 3]],
    view: &'a View,
    params: &'a MeasureParams,
}

impl Scan<'_> {
    /// `nplanes` planes from contacts spread over the anterior surface, each with its posterior
    /// contour and vessel points added to `pts` (noise from `noise_rng`, in the plane); returns
    /// the planes (image frame).
    fn planes(
        &self,
        nplanes: usize,
        seed: u64,
        noise_rng: &mut SplitMix64,
        pts: &mut Points,
    ) -> Result<Vec<UsPlane>, PhantomError> {
        let (tris, deformed, params) = (self.tris, self.deformed, self.params);
        let mut planes_image = Vec::with_capacity(nplanes);
        let mut rng = stream(seed, STREAM_PLANES);
        let normals =
            crate::mesh::TriSurface::new(deformed.to_vec(), tris.to_vec())?.vertex_normals();
        let contacts = spread_contacts(tris, &self.view.probe, deformed, nplanes, &mut rng);
        let locator = TetLocator::new(self.mesh);
        let vessel_deformed: Vec<[f64; 3]> = self
            .vessels
            .points
            .iter()
            .map(|&p| add(p, locator.interpolate(self.displacement, p)))
            .collect();
        for (j, &node) in contacts.iter().enumerate() {
            let pl = probe_plane(deformed[node as usize], normals[node as usize], &mut rng);
            let mut found =
                contour_points(tris, &self.view.posterior, deformed, &pl, params, &mut rng);
            let contour_len = found.len();
            found.extend(vessel_points(self.vessels, &vessel_deformed, &pl, params));
            for (m, q) in found.into_iter().enumerate() {
                pts.truth.push(q);
                pts.kind.push(if m < contour_len {
                    PointKind::PosteriorContour
                } else {
                    PointKind::Vessel
                });
                pts.plane_of.push(j as i32);
                pts.feature.push(0);
                let e = add(
                    scale(pl.depth_dir, params.us_noise_mm * noise_rng.normal()),
                    scale(pl.lateral_dir, params.us_noise_mm * noise_rng.normal()),
                );
                pts.noisy.push(add(q, e));
            }
            planes_image.push(pl);
        }
        Ok(planes_image)
    }
}

/// A probe's plane at a contact (`origin`, surface normal `nrm`): depth into the organ, the
/// lateral direction turned by a random angle about it.
fn probe_plane(origin: [f64; 3], nrm: [f64; 3], rng: &mut SplitMix64) -> UsPlane {
    let depth_dir = if norm(nrm) > 0.5 {
        scale(nrm, -1.0)
    } else {
        [0.0, 1.0, 0.0]
    };
    let (t1, t2) = tangent_basis(depth_dir);
    let phi = 2.0 * std::f64::consts::PI * rng.next_f64();
    let lateral_dir = add(scale(t1, phi.cos()), scale(t2, phi.sin()));
    UsPlane {
        origin,
        depth_dir,
        lateral_dir,
        normal: cross(depth_dir, lateral_dir),
    }
}

/// The misalignment, about the node centroid: a random rotation up to `max_rotation_deg` and a
/// shift up to `max_translation_mm` (uniform in the ball).
fn misalignment(rest: &[[f64; 3]], params: &MeasureParams, seed: u64) -> Rigid {
    let mut rng = stream(seed, STREAM_TRANSFORM);
    random_rigid(
        centroid(rest),
        params.max_rotation_deg,
        params.max_translation_mm,
        &mut rng,
    )
}

/// The mean of `points`.
fn centroid(points: &[[f64; 3]]) -> [f64; 3] {
    scale(
        points.iter().fold([0.0; 3], |a, &p| add(a, p)),
        1.0 / points.len().max(1) as f64,
    )
}

/// A random rotation of up to `max_deg` about `centre` (axis uniform on the sphere, angle
/// uniform), then a shift of up to `max_mm` (uniform in the ball).
fn random_rigid(centre: [f64; 3], max_deg: f64, max_mm: f64, rng: &mut SplitMix64) -> Rigid {
    let axis = unit_sphere(rng);
    let angle = max_deg.to_radians() * rng.next_f64();
    let shift = scale(unit_sphere(rng), max_mm * rng.next_f64().cbrt());
    let rot = Rigid::from_axis_angle(axis, angle, [0.0; 3]);
    Rigid {
        translation: sub(add(centre, shift), rot.apply_vector(centre)),
        ..rot
    }
}

/// The landmarks the navigation system's start comes from, and the start.
struct Landmarks {
    landmark_nodes: Vec<u32>,
    landmarks_image: Vec<[f64; 3]>,
    landmarks_physical: Vec<[f64; 3]>,
    initial_alignment: Rigid,
}

/// Landmark nodes, their preoperative and (deformed, moved by `tf`, noisy) physical positions,
/// and the rigid fit between them (or `tf` itself for a trusted start).
fn landmarks(
    rest: &[[f64; 3]],
    labels: &AnatomyLabels,
    deformed: &[[f64; 3]],
    tf: &Rigid,
    params: &MeasureParams,
    seed: u64,
) -> Result<Landmarks, PhantomError> {
    let mut rng = stream(seed, STREAM_LANDMARKS);
    let landmark_nodes = choose_landmarks(rest, labels, params.landmarks, &mut rng);
    if landmark_nodes.len() < 3 {
        return Err(PhantomError::Inconsistent(format!(
            "only {} distinct landmark nodes could be chosen; a rigid fit needs 3",
            landmark_nodes.len()
        )));
    }
    let mut lm_rng = stream(seed, STREAM_LANDMARK_NOISE);
    let landmarks_image: Vec<[f64; 3]> = landmark_nodes.iter().map(|&v| rest[v as usize]).collect();
    let landmarks_physical: Vec<[f64; 3]> = landmark_nodes
        .iter()
        .map(|&v| {
            let e = [0; 3].map(|_| params.landmark_noise_mm * lm_rng.normal());
            add(tf.apply(deformed[v as usize]), e)
        })
        .collect();
    let drawn = if params.trusted_start {
        *tf
    } else {
        Rigid::fit(&landmarks_image, &landmarks_physical, None).ok_or_else(|| {
            PhantomError::Geometry(format!(
                "landmark nodes {landmark_nodes:?} are collinear: no rigid fit"
            ))
        })?
    };
    let initial_alignment = match params.start_error {
        Some([deg, mm]) => {
            let mut rng = stream(seed, STREAM_START_ERROR);
            drawn.then(&random_rigid(
                drawn.apply(centroid(rest)),
                deg,
                mm,
                &mut rng,
            ))
        }
        None => drawn,
    };
    Ok(Landmarks {
        landmark_nodes,
        landmarks_image,
        landmarks_physical,
        initial_alignment,
    })
}
