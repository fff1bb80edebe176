//! Correspondence: which model point each measured point corresponds to.
//!
//! [`Correspondence`] is built once per [`PreopModel`]. It holds the model's boundary triangles
//! (outward) split into target sets, each with a closest-point hierarchy ([`TriangleBvh`]):
//!
//! - **anterior** triangles (all three nodes anterior; the whole boundary when there are none):
//!   targets of anterior-surface points;
//! - **posterior** triangles (all three nodes posterior; the whole boundary when there are none):
//!   targets of ultrasound posterior-contour points;
//! - **falciform** and **inferior-ridge** neighbourhoods: the anterior triangles with a node within
//!   [`CorrespondenceParams::feature_neighbourhood_mm`] of a node labelled on that feature. A surface
//!   point the surgeon designated on a salient feature (`Measurements::feature` 1 or 2) is matched to
//!   the closest point of that neighbourhood — not of the whole anterior surface — and its pair
//!   weight is multiplied by [`CorrespondenceParams::feature_weight`]. This is what makes the salient
//!   features constrain sliding along the surface (Clements et al. 2008). When the model has no node
//!   on that feature, the point is matched like any surface point and gets no extra weight.
//!   Designations on points that are not surface points are ignored.
//! - **vessel centerlines**: segments between centerline points; a vessel point is matched to the
//!   closest point of the (deformed) segments. The deformed centerline point is the centerline point
//!   moved by `u` interpolated with [`TetLocator`].
//!
//! Every [`Match`] is linear in the node displacements `u`: a surface or contour match carries the
//! barycentric coordinates of its closest point in the (deformed) triangle, so that
//! `Match::model_point(u)` is that closest point; a vessel match carries the tet containing the
//! undeformed centerline point `q` and its barycentric coordinates, so that `model_point(u) =
//! q + u(q)` (exactly on the deformed centerline where `u` is affine, to second order otherwise).
//!
//! **Trimming**: a pair is dropped when its distance exceeds `trim_factor × median + trim_floor_mm`
//! (the median over all matched pairs) or the absolute cap `max_distance_mm`. Kept pairs have weight
//! `kind weight × feature weight × the point's own weight` (1, or the number of points a reduced
//! cloud's centroid stands for: [`super::reduce`]).
//!
//! Surgery code: this module never sees how the ground truth was made (no `phantom`).

use super::RegisterError;
pub use super::preop_file::preop_model_from_file;
use super::{Checked, Match, MeasuredKind, Measurements, PreopModel};
use crate::mesh::TriSurface;
use crate::mesh::locate::TetLocator;
use crate::mesh::spatial::{Certificate, TriangleBvh};
use crate::mesh::vec3::{add, cross, dot, norm, sub};

/// Weights and trimming of correspondences.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CorrespondenceParams {
    /// Weight of anterior-surface pairs. Default 1.
    pub surface_weight: f64,
    /// Weight of ultrasound posterior-contour pairs. Default 1.
    pub contour_weight: f64,
    /// Weight of vessel pairs. Default 1.
    pub vessel_weight: f64,
    /// Extra factor for surface points designated on a salient feature. Default 3.
    pub feature_weight: f64,
    /// A salient feature's target is the anterior triangles with a node within this distance (mm)
    /// of a node on the feature. Default 15 (1.5 edges of a 10 mm mesh).
    pub feature_neighbourhood_mm: f64,
    /// Pairs farther than `trim_factor × median distance + trim_floor_mm` are dropped. Default 3.
    pub trim_factor: f64,
    /// See `trim_factor` (mm). Default 5.
    pub trim_floor_mm: f64,
    /// Pairs farther than this (mm) are always dropped and counted as far. Default 500.
    pub max_distance_mm: f64,
    /// A robust kernel instead of the trimming: every pair within `max_distance_mm` is kept,
    /// weighted by the Cauchy kernel `1 / (1 + (d/c)²)` with `c` half the trimming threshold (a
    /// pair at the threshold counts a fifth). Default false (trimming).
    #[serde(default)]
    pub robust_kernel: bool,
    /// Which model triangles surface points are matched to: the anterior surface (default; what
    /// a laparoscope sees from the front) or the whole boundary (a patch seen from another side,
    /// or a model whose anterior labels cannot be trusted).
    #[serde(default)]
    pub surface_target: SurfaceTarget,
}

/// The model triangles surface points are matched to ([`CorrespondenceParams::surface_target`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SurfaceTarget {
    /// The anterior triangles (the whole boundary when the model has none).
    #[default]
    Anterior,
    /// Every boundary triangle.
    Boundary,
}

impl SurfaceTarget {
    /// Its name in files, on the command line and on the wire (`anterior`, `boundary`).
    pub fn name(self) -> &'static str {
        match self {
            Self::Anterior => "anterior",
            Self::Boundary => "boundary",
        }
    }
}

impl Default for CorrespondenceParams {
    fn default() -> Self {
        Self {
            surface_weight: 1.0,
            contour_weight: 1.0,
            vessel_weight: 1.0,
            feature_weight: 3.0,
            feature_neighbourhood_mm: 15.0,
            trim_factor: 3.0,
            trim_floor_mm: 5.0,
            max_distance_mm: 500.0,
            robust_kernel: false,
            surface_target: SurfaceTarget::Anterior,
        }
    }
}

impl CorrespondenceParams {
    /// Checks that every weight and distance is finite and non-negative (and the cap positive).
    pub fn validate(&self) -> Result<(), RegisterError> {
        for (name, v) in [
            ("surface_weight", self.surface_weight),
            ("contour_weight", self.contour_weight),
            ("vessel_weight", self.vessel_weight),
            ("feature_weight", self.feature_weight),
            ("feature_neighbourhood_mm", self.feature_neighbourhood_mm),
            ("trim_factor", self.trim_factor),
            ("trim_floor_mm", self.trim_floor_mm),
            ("max_distance_mm", self.max_distance_mm),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(RegisterError::Parameter(format!(
                    "correspondence parameter {name} must be finite and ≥ 0, got {v}"
                )));
            }
        }
        if self.max_distance_mm <= 0.0 {
            return Err(RegisterError::Parameter(
                "correspondence parameter max_distance_mm must be > 0".into(),
            ));
        }
        Ok(())
    }
}

/// Summary of one matching.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct MatchStats {
    /// Pairs kept.
    pub kept: usize,
    /// Pairs dropped by the median rule or the absolute cap (includes `far`).
    pub trimmed: usize,
    /// Pairs dropped because they were farther than `max_distance_mm`.
    pub far: usize,
    /// Points with nothing to match (e.g. vessel points and a model without vessels).
    pub unmatched: usize,
    /// Root mean square distance of the kept pairs (mm; 0 when none).
    pub rms_mm: f64,
    /// Largest distance of a kept pair (mm; 0 when none).
    pub max_mm: f64,
    /// Median distance over all matched pairs before trimming (mm; 0 when none).
    pub median_mm: f64,
    /// The trimming threshold used (mm).
    pub threshold_mm: f64,
}

/// A set of boundary triangles with its closest-point hierarchy.
#[derive(Debug, Clone)]
struct TargetSet {
    /// Indices into the boundary triangles.
    tris: Vec<u32>,
    /// Hierarchy over those triangles on the undeformed nodes.
    bvh: TriangleBvh,
}

/// Closest-point targets of a [`PreopModel`]; build once, match many times.
#[derive(Debug, Clone)]
pub struct Correspondence {
    nodes: Vec<[f64; 3]>,
    /// Boundary triangles (outward).
    tris: Vec<[u32; 3]>,
    anterior: TargetSet,
    posterior: TargetSet,
    whole: TargetSet,
    /// Falciform and inferior-ridge neighbourhoods (empty when the feature has no node); built
    /// with the default neighbourhood radius and rebuilt on demand for another.
    features: [TargetSet; 2],
    feature_radius: f64,
    /// Per boundary node distance to the nearest falciform / ridge node (∞ when none).
    feature_distance: [Vec<f64>; 2],
    vessel_points: Vec<[f64; 3]>,
    vessel_segments: Vec<[u32; 2]>,
    locator: TetLocator,
    tets: Vec<[u32; 4]>,
    /// Boundary triangle → its tet (fallback location of centerline points outside the mesh).
    tet_of_triangle: Vec<u32>,
    /// Nodes whose displacement [`Correspondence::match_points`] reads (sorted).
    active: Vec<u32>,
}

impl TargetSet {
    fn new(nodes: &[[f64; 3]], all: &[[u32; 3]], tris: Vec<u32>) -> Self {
        let sub_tris = tris.iter().map(|&t| all[t as usize]).collect();
        let bvh = TriangleBvh::new(&TriSurface::new_unchecked(nodes.to_vec(), sub_tris));
        Self { tris, bvh }
    }
}

/// Checks a preoperative model before its target sets are built: a mesh, one flag per node in
/// every flag set, finite vessel points and segments within them.
fn check_model(model: &PreopModel) -> Result<(), RegisterError> {
    let mesh = &model.mesh;
    let n = mesh.num_nodes();
    if n == 0 || mesh.num_tets() == 0 {
        return Err(RegisterError::Model(
            "preoperative model: the mesh is empty".into(),
        ));
    }
    for (name, len) in [
        ("anterior", model.anterior.len()),
        ("posterior", model.posterior.len()),
        ("falciform", model.falciform.len()),
        ("inferior_ridge", model.inferior_ridge.len()),
    ] {
        if len != n {
            return Err(RegisterError::Model(format!(
                "preoperative model: {name} has {len} entries, the mesh has {n} nodes"
            )));
        }
    }
    if let Some(i) = model
        .vessel_points
        .iter()
        .position(|p| p.iter().any(|c| !c.is_finite()))
    {
        return Err(RegisterError::Model(format!(
            "preoperative model: vessel point {i} is not finite"
        )));
    }
    if let Some((k, s)) = model
        .vessel_segments
        .iter()
        .enumerate()
        .find(|(_, s)| s.iter().any(|&i| i as usize >= model.vessel_points.len()))
    {
        return Err(RegisterError::Model(format!(
            "preoperative model: vessel segment {k} {s:?} refers past the {} vessel points",
            model.vessel_points.len()
        )));
    }
    Ok(())
}

/// Per node: the distance of each node in `at` to the nearest flagged node (infinity elsewhere,
/// and everywhere when no node is flagged).
fn distance_to_flagged(nodes: &[[f64; 3]], flags: &[bool], at: &[u32]) -> Vec<f64> {
    let on: Vec<[f64; 3]> = (0..nodes.len())
        .filter(|&i| flags[i])
        .map(|i| nodes[i])
        .collect();
    let mut d = vec![f64::INFINITY; nodes.len()];
    for &v in at {
        let p = nodes[v as usize];
        d[v as usize] = on
            .iter()
            .map(|&q| norm(sub(p, q)))
            .fold(f64::INFINITY, f64::min);
    }
    d
}

/// Per node: whether matching reads its displacement. The boundary (target surfaces) and the
/// tets along the vessel centerlines (vertices, and samples every 0.5 mm along each segment).
fn reading_nodes(model: &PreopModel, tris: &[[u32; 3]], locator: &TetLocator) -> Vec<bool> {
    let mut is_active = vec![false; model.mesh.num_nodes()];
    for t in tris {
        for &v in t {
            is_active[v as usize] = true;
        }
    }
    let mut mark = |p: [f64; 3]| {
        if let Some((t, _)) = locator.weights(p) {
            for v in locator.tet(t) {
                is_active[v as usize] = true;
            }
        }
    };
    for &p in &model.vessel_points {
        mark(p);
    }
    for s in &model.vessel_segments {
        let (a, b) = (
            model.vessel_points[s[0] as usize],
            model.vessel_points[s[1] as usize],
        );
        let steps = (norm(sub(b, a)) / 0.5).ceil().clamp(1.0, 1e5) as usize;
        for k in 1..steps {
            let f = k as f64 / steps as f64;
            mark([0, 1, 2].map(|c| a[c] + f * (b[c] - a[c])));
        }
    }
    is_active
}

impl Correspondence {
    /// Builds the target sets of `model`. Fails when the flags do not have one entry per node, the
    /// mesh has no boundary, or a vessel point or segment is invalid.
    pub fn new(model: &PreopModel) -> Result<Self, RegisterError> {
        let mesh = &model.mesh;
        let n = mesh.num_nodes();
        check_model(model)?;
        let boundary = mesh.boundary().map_err(|e| {
            RegisterError::Model(format!(
                "preoperative model: cannot take the mesh boundary: {e}"
            ))
        })?;
        let nodes = mesh.nodes().to_vec();
        let tris = boundary.triangles;
        let all_of = |flags: &[bool]| -> Vec<u32> {
            (0..tris.len() as u32)
                .filter(|&t| tris[t as usize].iter().all(|&v| flags[v as usize]))
                .collect()
        };
        let everything: Vec<u32> = (0..tris.len() as u32).collect();
        let mut anterior = all_of(&model.anterior);
        if anterior.is_empty() {
            anterior = everything.clone();
        }
        let mut posterior = all_of(&model.posterior);
        if posterior.is_empty() {
            posterior = everything.clone();
        }
        // Distance of each boundary node to the nearest node of each feature.
        let feature_distance = [&model.falciform, &model.inferior_ridge]
            .map(|flags| distance_to_flagged(&nodes, flags, &boundary.nodes));
        let radius = CorrespondenceParams::default().feature_neighbourhood_mm;
        let features = [0, 1].map(|f| {
            let set = feature_set(&tris, &anterior, &feature_distance[f], radius);
            TargetSet::new(&nodes, &tris, set)
        });
        let locator = TetLocator::new(mesh);
        let is_active = reading_nodes(model, &tris, &locator);
        let active = (0..n as u32).filter(|&i| is_active[i as usize]).collect();
        Ok(Self {
            active,
            anterior: TargetSet::new(&nodes, &tris, anterior),
            posterior: TargetSet::new(&nodes, &tris, posterior),
            whole: TargetSet::new(&nodes, &tris, everything),
            features,
            feature_radius: radius,
            feature_distance,
            vessel_points: model.vessel_points.clone(),
            vessel_segments: model.vessel_segments.clone(),
            locator,
            tets: mesh.tets().to_vec(),
            tet_of_triangle: boundary.tet_of_triangle,
            nodes,
            tris,
        })
    }

    /// The nodes whose displacement [`Correspondence::match_points`] reads (sorted): the boundary
    /// and the tets along the vessel centerlines. An iterative fit need only update these between
    /// matchings.
    pub fn active_nodes(&self) -> &[u32] {
        &self.active
    }

    /// Number of mesh nodes.
    pub fn num_nodes(&self) -> usize {
        self.nodes.len()
    }

    /// How many triangles plain surface points are matched to under `params` (the anterior
    /// surface's, or the whole boundary's).
    pub fn surface_triangles(&self, params: &CorrespondenceParams) -> usize {
        self.surface_set(params).tris.len()
    }

    /// The mean edge length of the boundary triangles (mm): the resolution at which the model's
    /// surface can follow the data.
    pub fn mean_boundary_edge_mm(&self) -> f64 {
        let mut sum = 0.0;
        for t in &self.tris {
            for k in 0..3 {
                sum += norm(sub(
                    self.nodes[t[k] as usize],
                    self.nodes[t[(k + 1) % 3] as usize],
                ));
            }
        }
        sum / (3 * self.tris.len()).max(1) as f64
    }

    /// Distance from `p` (image frame) to the undeformed boundary surface (mm).
    pub fn distance_to_boundary(&self, p: [f64; 3]) -> f64 {
        self.whole.bvh.distance(p)
    }

    /// Matches measured points already mapped into the image frame against the model deformed by
    /// `u` (node-major, `3n`; `None` = undeformed). See the module doc for targets, weights and
    /// trimming. Returns the kept matches in point order and the statistics.
    ///
    /// The measurements were checked when they were made ([`Checked`]; the initial alignment is
    /// not used here). Fails when `points_image` is not as long as `meas.points` or not finite,
    /// `u` has the wrong length or is not finite, or the parameters are invalid.
    pub fn match_points(
        &self,
        points_image: &[[f64; 3]],
        meas: &Checked,
        u: Option<&[f64]>,
        params: &CorrespondenceParams,
    ) -> Result<(Vec<Match>, MatchStats), RegisterError> {
        self.match_points_hinted(points_image, meas, u, params, &mut Hints::default())
    }

    /// [`Correspondence::match_points`], starting each point's closest-triangle search from the
    /// triangle `hints` holds for it (the last call's answer: an iteration's points move little)
    /// and leaving this call's answers there. The matches are the same with or without hints
    /// (the search's ties go to the lower triangle index whatever the start); hints only
    /// prune the search, which is most of an iteration's matching time.
    pub fn match_points_hinted(
        &self,
        points_image: &[[f64; 3]],
        meas: &Checked,
        u: Option<&[f64]>,
        params: &CorrespondenceParams,
        hints: &mut Hints,
    ) -> Result<(Vec<Match>, MatchStats), RegisterError> {
        super::measured::not_empty(meas)?;
        params.validate()?;
        if points_image.len() != meas.points.len() {
            return Err(RegisterError::Inconsistent(format!(
                "points_image has {} points, measurements.points has {}",
                points_image.len(),
                meas.points.len()
            )));
        }
        if let Some(i) = points_image
            .iter()
            .position(|p| p.iter().any(|c| !c.is_finite()))
        {
            return Err(RegisterError::Inconsistent(format!(
                "points_image[{i}] is not finite"
            )));
        }
        let n = self.nodes.len();
        if let Some(u) = u {
            if u.len() != 3 * n {
                return Err(RegisterError::Inconsistent(format!(
                    "displacement has {} values, the model has {n} nodes and needs {}",
                    u.len(),
                    3 * n
                )));
            }
            if let Some(i) = u.iter().position(|v| !v.is_finite()) {
                return Err(RegisterError::Inconsistent(format!(
                    "displacement of node {} is not finite",
                    i / 3
                )));
            }
        }
        let deformed: Option<Vec<[f64; 3]>> = u.map(|u| {
            (0..n)
                .map(|i| add(self.nodes[i], [u[3 * i], u[3 * i + 1], u[3 * i + 2]]))
                .collect()
        });
        let call = Call {
            u,
            params,
            geometry: deformed.as_deref().unwrap_or(&self.nodes),
            targets: self.call_targets(meas, u, params, deformed.as_deref()),
        };
        hints.fit(points_image.len());
        let (candidates, unmatched) = self.match_candidates(points_image, meas, &call, hints);
        Ok(trim_candidates(candidates, unmatched, params))
    }

    /// Whether the anterior triangles are a proper part of the boundary (else matching to the
    /// anterior surface is matching to the whole boundary).
    pub fn anterior_is_part(&self) -> bool {
        self.anterior.tris.len() < self.whole.tris.len()
    }

    /// The triangles plain surface points are matched to under `params`.
    fn surface_set(&self, params: &CorrespondenceParams) -> &TargetSet {
        match params.surface_target {
            SurfaceTarget::Anterior => &self.anterior,
            SurfaceTarget::Boundary => &self.whole,
        }
    }

    /// The per-call targets: feature sets for another radius, trees refitted to `deformed`.
    fn call_targets(
        &self,
        meas: &Measurements,
        u: Option<&[f64]>,
        params: &CorrespondenceParams,
        deformed: Option<&[[f64; 3]]>,
    ) -> CallTargets {
        let geometry: &[[f64; 3]] = deformed.unwrap_or(&self.nodes);
        // Which targets are needed.
        let need_feature =
            |f: usize| (0..meas.points.len()).any(|i| designated(meas, i) == Some(f));
        // A neighbourhood radius other than the prebuilt one: rebuilt for this call.
        let feature_sets: [Option<TargetSet>; 2] = [0, 1].map(|f| {
            if need_feature(f) && params.feature_neighbourhood_mm != self.feature_radius {
                let tris = feature_set(
                    &self.tris,
                    &self.anterior.tris,
                    &self.feature_distance[f],
                    params.feature_neighbourhood_mm,
                );
                Some(TargetSet::new(&self.nodes, &self.tris, tris))
            } else {
                None
            }
        });
        let feature_target = |f: usize| feature_sets[f].as_ref().unwrap_or(&self.features[f]);
        let need = |k: MeasuredKind| meas.kind.contains(&k);
        // Hierarchies on the deformed geometry (the undeformed ones are prebuilt).
        let rebuild = |set: &TargetSet, needed: bool| -> Option<TriangleBvh> {
            if !needed || deformed.is_none() {
                return None;
            }
            // The prebuilt tree over the same triangles, refitted to the deformed nodes.
            let mut bvh = set.bvh.clone();
            bvh.refit(geometry);
            Some(bvh)
        };
        let vessel_deformed: Option<Vec<[f64; 3]>> = if need(MeasuredKind::Vessel) {
            Some(match u {
                Some(u) => self
                    .vessel_points
                    .iter()
                    .map(|&p| add(p, self.locator.interpolate(u, p)))
                    .collect(),
                None => self.vessel_points.clone(),
            })
        } else {
            None
        };
        CallTargets {
            ant_bvh: rebuild(self.surface_set(params), need(MeasuredKind::Surface)),
            post_bvh: rebuild(&self.posterior, need(MeasuredKind::PosteriorContour)),
            feat_bvh: [0, 1].map(|f| rebuild(feature_target(f), need_feature(f))),
            vessel_deformed,
            feature_sets,
        }
    }

    /// Each point's closest model point and its distance, untrimmed; and how many have none. Clouds
    /// of [`PARALLEL_MATCH_POINTS`] points or more are matched in parallel (same result).
    fn match_candidates(
        &self,
        points_image: &[[f64; 3]],
        meas: &Checked,
        call: &Call<'_>,
        hints: &mut Hints,
    ) -> (Vec<(Match, f64)>, usize) {
        let one = |(i, (&p, hint)): (usize, (&[f64; 3], &mut PointHint))| {
            self.match_one(i, p, meas, call, hint)
        };
        let found: Vec<Option<(Match, f64)>> = if points_image.len() >= PARALLEL_MATCH_POINTS {
            use rayon::prelude::*;
            points_image
                .par_iter()
                .zip(hints.0.par_iter_mut())
                .enumerate()
                .with_min_len(PARALLEL_MATCH_POINTS / 4)
                .map(one)
                .collect()
        } else {
            points_image
                .iter()
                .zip(hints.0.iter_mut())
                .enumerate()
                .map(one)
                .collect()
        };
        let unmatched = found.iter().filter(|f| f.is_none()).count();
        (found.into_iter().flatten().collect(), unmatched)
    }

    /// Point `i` (at `p`) matched to its closest model point, with the distance; the triangle it
    /// matched, if any, is left in `hint` for the next call.
    fn match_one(
        &self,
        i: usize,
        p: [f64; 3],
        meas: &Checked,
        call: &Call<'_>,
        hint: &mut PointHint,
    ) -> Option<(Match, f64)> {
        let Call {
            u,
            params,
            geometry,
            targets: call,
        } = call;
        let u = *u;
        let feature_target = |f: usize| call.feature_sets[f].as_ref().unwrap_or(&self.features[f]);
        let (set, bvh, w) = match meas.kind[i] {
            MeasuredKind::Surface => match designated(meas, i) {
                Some(f) if !feature_target(f).tris.is_empty() => (
                    feature_target(f),
                    call.feat_bvh[f].as_ref(),
                    params.surface_weight * params.feature_weight,
                ),
                _ => (
                    self.surface_set(params),
                    call.ant_bvh.as_ref(),
                    params.surface_weight,
                ),
            },
            MeasuredKind::PosteriorContour => (
                &self.posterior,
                call.post_bvh.as_ref(),
                params.contour_weight,
            ),
            MeasuredKind::Vessel => {
                let vd = call.vessel_deformed.as_deref().unwrap_or(&[]);
                return self.match_vessel(p, vd).map(|mut m| {
                    m.point = i;
                    m.weight = params.vessel_weight * meas.weight(i);
                    let d = norm(sub(p, m.model_point_or_anchor(u)));
                    (m, d)
                });
            }
        };
        let target = Target {
            set,
            // A tree refitted to this call's geometry moves every call: no certificates.
            certify: bvh.is_none(),
            bvh: bvh.unwrap_or(&set.bvh),
            // A reduced cloud's centroid counts for the points it stands for.
            weight: w * meas.weight(i),
        };
        let (m, tri) = self.match_triangle(i, p, &target, geometry, hint)?;
        hint.triangle = Some(tri);
        let d = norm(sub(p, m.model_point_or_anchor(u)));
        Some((m, d))
    }

    /// Point `i` (at `p`) matched to the closest point of `target` (the search started from
    /// triangle `hint` of its set), and that triangle.
    fn match_triangle(
        &self,
        i: usize,
        p: [f64; 3],
        target: &Target<'_>,
        geometry: &[[f64; 3]],
        hint: &mut PointHint,
    ) -> Option<(Match, u32)> {
        let Target {
            set,
            bvh,
            certify,
            weight: w,
        } = *target;
        // A certificate names its tree's geometry: one from another tree is never used.
        let c = if certify {
            bvh.closest_certified(p, &mut hint.certificate)?
        } else {
            bvh.closest(p, hint.triangle)?
        };
        let tri = self.tris[set.tris[c.triangle as usize] as usize];
        let corners = tri.map(|v| geometry[v as usize]);
        let b = triangle_barycentric(c.point, corners);
        let rest = tri.map(|v| self.nodes[v as usize]);
        let anchor = [0, 1, 2].map(|a| b[0] * rest[0][a] + b[1] * rest[1][a] + b[2] * rest[2][a]);
        let e1 = sub(corners[1], corners[0]);
        let e2 = sub(corners[2], corners[0]);
        let nrm = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let len = norm(nrm);
        let m = Match {
            point: i,
            anchor,
            nodes: [tri[0], tri[1], tri[2], tri[0]],
            bary: [b[0], b[1], b[2], 0.0],
            weight: w,
            normal: if len > 0.0 {
                nrm.map(|x| x / len)
            } else {
                [0.0; 3]
            },
        };
        Some((m, c.triangle))
    }

    /// The closest point of the (deformed) centerline to `p`: the undeformed point `q` at the same
    /// segment parameter, located in its tet. `None` without vessel segments.
    fn match_vessel(&self, p: [f64; 3], deformed: &[[f64; 3]]) -> Option<Match> {
        let mut best: Option<(f64, usize, f64)> = None;
        for (k, s) in self.vessel_segments.iter().enumerate() {
            let (a, b) = (deformed[s[0] as usize], deformed[s[1] as usize]);
            let (d2, t) = point_segment(p, a, b);
            if best.is_none_or(|x| d2 < x.0) {
                best = Some((d2, k, t));
            }
        }
        let (_, k, t) = best?;
        let s = self.vessel_segments[k];
        let (a, b) = (
            self.vessel_points[s[0] as usize],
            self.vessel_points[s[1] as usize],
        );
        let q = [0, 1, 2].map(|c| a[c] + t * (b[c] - a[c]));
        let (tet, bary) = match self.locator.locate(q) {
            Some(x) => x,
            None => {
                // Outside the mesh (a centerline grazing the surface): the tet of the closest
                // boundary face, with unclamped (extrapolating) coordinates so that the anchor is q.
                let c = self.whole.bvh.closest(q, None)?;
                let tri = self.whole.tris[c.triangle as usize] as usize;
                let tet = self.tet_of_triangle[tri] as usize;
                (tet, self.locator.barycentric(tet, q))
            }
        };
        if bary.iter().any(|x| !x.is_finite()) {
            return None;
        }
        Some(Match {
            point: 0,
            anchor: q,
            nodes: self.tets[tet],
            bary,
            weight: 1.0,
            normal: [0.0; 3],
        })
    }
}

/// Clouds with at least this many points are matched in parallel (below it the threads' start-up
/// costs more than it saves).
const PARALLEL_MATCH_POINTS: usize = 1024;

/// Where each measured point's closest-triangle search starts ([`Correspondence::match_points_hinted`]):
/// the triangle (of the point's target set) it matched last time. Start empty and pass the same
/// hints to every call of one loop over the same measurements.
#[derive(Debug, Clone, Default)]
pub struct Hints(Vec<PointHint>);

/// One point's hint: the triangle it matched last, and what that search learnt (on a tree that
/// does not move between calls: the undeformed model's).
#[derive(Debug, Clone, Copy, Default)]
struct PointHint {
    triangle: Option<u32>,
    certificate: Option<Certificate>,
}

impl Hints {
    /// One slot per point: kept when the count is unchanged, else cleared.
    fn fit(&mut self, points: usize) {
        if self.0.len() != points {
            self.0.clear();
            self.0.resize(points, PointHint::default());
        }
    }
}

/// Per-call targets of [`Correspondence::match_points`]: rebuilt feature sets, refitted trees.
/// One matching call: the displacement, the settings, the geometry (deformed by `u`, or the
/// model's) and the targets every point is matched against.
struct Call<'a> {
    u: Option<&'a [f64]>,
    params: &'a CorrespondenceParams,
    geometry: &'a [[f64; 3]],
    targets: CallTargets,
}

/// Where one surface or contour point is matched: the target triangles, their hierarchy on this
/// call's geometry, and the pair's weight.
#[derive(Clone, Copy)]
struct Target<'a> {
    set: &'a TargetSet,
    bvh: &'a TriangleBvh,
    /// Whether the search keeps a [`Certificate`] (a tree that does not move between calls).
    certify: bool,
    weight: f64,
}

struct CallTargets {
    feature_sets: [Option<TargetSet>; 2],
    ant_bvh: Option<TriangleBvh>,
    post_bvh: Option<TriangleBvh>,
    feat_bvh: [Option<TriangleBvh>; 2],
    vessel_deformed: Option<Vec<[f64; 3]>>,
}

/// The salient feature (0 or 1) surface point `i` is designated on, if any.
fn designated(meas: &Measurements, i: usize) -> Option<usize> {
    match meas.feature.get(i) {
        Some(&f) if f > 0 && meas.kind[i] == MeasuredKind::Surface => Some(f as usize - 1),
        _ => None,
    }
}

/// Trimming of [`Correspondence::match_points`] (or the robust kernel's down-weighting).
fn trim_candidates(
    candidates: Vec<(Match, f64)>,
    unmatched: usize,
    params: &CorrespondenceParams,
) -> (Vec<Match>, MatchStats) {
    let mut ds: Vec<f64> = candidates.iter().map(|c| c.1).collect();
    ds.sort_by(f64::total_cmp);
    let median = if ds.is_empty() {
        0.0
    } else if ds.len() % 2 == 1 {
        ds[ds.len() / 2]
    } else {
        0.5 * (ds[ds.len() / 2 - 1] + ds[ds.len() / 2])
    };
    let threshold =
        (params.trim_factor * median + params.trim_floor_mm).min(params.max_distance_mm);
    let mut stats = MatchStats {
        unmatched,
        median_mm: median,
        threshold_mm: threshold,
        ..Default::default()
    };
    let mut kept = Vec::with_capacity(candidates.len());
    let mut sum2 = 0.0;
    let c = 0.5 * threshold.max(1e-9);
    for (mut m, d) in candidates {
        if d > params.max_distance_mm {
            stats.far += 1;
            stats.trimmed += 1;
        } else if params.robust_kernel {
            m.weight /= 1.0 + (d / c) * (d / c);
            sum2 += d * d;
            stats.max_mm = stats.max_mm.max(d);
            kept.push(m);
        } else if d > threshold {
            stats.trimmed += 1;
        } else {
            sum2 += d * d;
            stats.max_mm = stats.max_mm.max(d);
            kept.push(m);
        }
    }
    stats.kept = kept.len();
    if !kept.is_empty() {
        stats.rms_mm = (sum2 / kept.len() as f64).sqrt();
    }
    (kept, stats)
}

impl Match {
    fn model_point_or_anchor(&self, u: Option<&[f64]>) -> [f64; 3] {
        match u {
            Some(u) => self.model_point(u),
            None => self.anchor,
        }
    }
}

/// Anterior triangles with a node within `radius` of the feature (empty when the feature has no
/// node).
fn feature_set(tris: &[[u32; 3]], anterior: &[u32], distance: &[f64], radius: f64) -> Vec<u32> {
    anterior
        .iter()
        .copied()
        .filter(|&t| {
            tris[t as usize]
                .iter()
                .any(|&v| distance[v as usize] <= radius)
        })
        .collect()
}

/// Squared distance from `p` to the segment `a`–`b` and the parameter of the closest point.
fn point_segment(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> (f64, f64) {
    let (d, t) = crate::mesh::spatial::point_segment_distance(p, a, b);
    (d * d, t)
}

/// Barycentric coordinates of `q` (a point of the triangle) in triangle `p`, clamped to the
/// triangle; for a degenerate triangle, weight 1 on the nearest corner.
fn triangle_barycentric(q: [f64; 3], p: [[f64; 3]; 3]) -> [f64; 3] {
    let e1 = sub(p[1], p[0]);
    let e2 = sub(p[2], p[0]);
    let n = cross(e1, e2);
    let nn = dot(n, n);
    let scale2 = dot(e1, e1).max(dot(e2, e2));
    if nn.is_nan() || nn <= 1e-24 * scale2 * scale2 {
        let k = (0..3)
            .min_by(|&a, &b| norm(sub(q, p[a])).total_cmp(&norm(sub(q, p[b]))))
            .unwrap_or(0);
        let mut b = [0.0; 3];
        b[k] = 1.0;
        return b;
    }
    let d = sub(q, p[0]);
    let b1 = dot(cross(d, e2), n) / nn;
    let b2 = dot(cross(e1, d), n) / nn;
    let mut b = [1.0 - b1 - b2, b1, b2].map(|x| x.max(0.0));
    let s: f64 = b.iter().sum();
    b = b.map(|x| x / s);
    b
}
