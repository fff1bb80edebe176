//! From a LIBR registration to SR-GCN inputs (and, for training, targets). Everything here is
//! host-side data (plain vectors); [`SampleData::tensors`] moves one sample to a device.
//!
//! Frame: the **registered preoperative (image) frame**. LIBR returns node displacements `u` in
//! the image frame and a rigid transform `T` image → physical; the measured points are mapped
//! back by `T⁻¹`. So the network sees the preoperative mesh, the LIBR-deformed mesh `X + u` and the
//! points in one frame that does not depend on where the patient lies, and its correction `y` is
//! added to `u` (LIBR+ node `i` is at `T(X_i + u_i + y_i)`).
//!
//! Normalisation per case: coordinates `(p − c) / s` with `c` the preoperative centroid and `s`
//! the RMS distance of the nodes from it; corrections in units of `s / 10` ([`CaseFrame::unit_mm`]).

use super::coarsen::{compose_assign, hierarchy, interpolation, mean_pool};
use super::graph::Graph;
use super::model::{BipartiteInput, CoarseLevel, MeshGraphs, SrGcnConfig, Target};
use super::sparse::{Csr, SparseOp};
use super::{GcnError, SplineGraph, cartesian_pseudo, mesh_graph};
use crate::fem::{FemError, LameField, StiffnessSystem};
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::{Correspondence, CorrespondenceParams};
use crate::register::{Checked, Match};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

/// One LIBR registration as the SR-GCN reads it: the case's mesh and matching, the measurements,
/// and LIBR's answer `(u, transform)`.
#[derive(Debug, Clone, Copy)]
pub struct Registered<'a> {
    /// The preoperative mesh.
    pub mesh: &'a TetMesh,
    /// The correspondence built from that mesh.
    pub correspondence: &'a Correspondence,
    /// The correspondence settings of LIBR's last iteration.
    pub cparams: &'a CorrespondenceParams,
    /// The measurements (physical frame).
    pub meas: &'a Checked,
    /// LIBR's node displacements (image frame, mm, node-major `3V`).
    pub u: &'a [f64],
    /// LIBR's rigid transform, image → physical.
    pub transform: &'a Rigid,
}

/// Per-case normalisation and the mesh graph (computed once per preoperative mesh).
#[derive(Debug, Clone)]
pub struct CaseFrame {
    /// Preoperative centroid (mm).
    pub center: [f64; 3],
    /// RMS node distance from the centroid (mm).
    pub scale: f64,
    /// The mesh graph (tet edges both ways, pseudo-coordinates of the preoperative nodes).
    pub graph: Graph,
    /// Normalised preoperative coordinates, `[V, 3]` row-major.
    pub preop: Vec<f32>,
    /// Per node: 1 on the boundary (else 0) and the area-weighted outward unit normal there
    /// (zero inside), `[V, 4]` row-major ([`SrGcnConfig::surface_input`]).
    pub surface: Vec<f32>,
    /// The unit-modulus stiffness of the preoperative mesh and its mean edge length (mm), built
    /// on first use by [`SrGcnConfig::load_input`].
    stiffness: std::sync::Arc<std::sync::OnceLock<Result<(StiffnessSystem, f64), FemError>>>,
}

impl CaseFrame {
    /// Builds the frame of a preoperative mesh.
    pub fn new(mesh: &TetMesh) -> Result<Self, GcnError> {
        let nodes = mesh.nodes();
        if nodes.is_empty() {
            return Err(GcnError::Invalid("the mesh has no nodes".into()));
        }
        let n = nodes.len() as f64;
        let mut center = [0.0; 3];
        for p in nodes {
            for a in 0..3 {
                center[a] += p[a] / n;
            }
        }
        let scale = (nodes
            .iter()
            .map(|p| (0..3).map(|a| (p[a] - center[a]).powi(2)).sum::<f64>())
            .sum::<f64>()
            / n)
            .sqrt();
        if !(scale.is_finite() && scale > 0.0) {
            return Err(GcnError::Invalid("the mesh has no extent".into()));
        }
        let mut frame = Self {
            center,
            scale,
            graph: mesh_graph(mesh)?,
            preop: Vec::new(),
            surface: Vec::new(),
            stiffness: Default::default(),
        };
        frame.preop = nodes.iter().flat_map(|p| frame.normalise(*p)).collect();
        let boundary = mesh
            .boundary_surface()
            .map_err(|e| GcnError::Invalid(format!("the mesh's boundary: {e}")))?;
        // Outward for positively oriented tets; flipped if the mesh is wound the other way.
        let sign = if boundary.signed_volume() < 0.0 {
            -1.0
        } else {
            1.0
        };
        frame.surface = boundary
            .vertex_normals()
            .iter()
            .flat_map(|n| {
                let on = n.iter().any(|x| *x != 0.0);
                [
                    if on { 1.0 } else { 0.0 },
                    (sign * n[0]) as f32,
                    (sign * n[1]) as f32,
                    (sign * n[2]) as f32,
                ]
            })
            .collect();
        Ok(frame)
    }

    /// Mean length of the mesh graph's edges (mm; 1 for a mesh without edges).
    pub fn mean_edge_mm(&self, mesh: &TetMesh) -> f64 {
        let (g, nodes) = (&self.graph, mesh.nodes());
        if g.targets.is_empty() {
            return 1.0;
        }
        let sum: f64 = g
            .targets
            .iter()
            .zip(&g.sources)
            .map(|(&i, &j)| {
                (0..3)
                    .map(|a| (nodes[i][a] - nodes[j][a]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .sum();
        sum / g.targets.len() as f64
    }

    /// `K·u` per node in units of μ × output unit × mean edge length, `[V, 3]` row-major
    /// ([`SrGcnConfig::load_input`]; `u` in mm, image frame).
    pub fn implied_loads(&self, mesh: &TetMesh, u: &[f64]) -> Result<Vec<f32>, GcnError> {
        let built = self.stiffness.get_or_init(|| {
            let (mu, nu) = (1.0, 0.45);
            let lambda = 2.0 * mu * nu / (1.0 - 2.0 * nu);
            let k = StiffnessSystem::linear_field(mesh, &LameField::Uniform(lambda, mu))?;
            Ok((k, self.mean_edge_mm(mesh)))
        });
        let (k, h) = built
            .as_ref()
            .map_err(|e| GcnError::LoadStiffness(e.clone()))?;
        if u.len() != k.dofs() {
            return Err(GcnError::Invalid(format!(
                "u has {} values, the stiffness {} unknowns",
                u.len(),
                k.dofs()
            )));
        }
        let s = 1.0 / (self.unit_mm() * h);
        Ok(k.apply(u).into_iter().map(|f| (f * s) as f32).collect())
    }

    /// The unit of the network's corrections (mm).
    pub fn unit_mm(&self) -> f64 {
        0.1 * self.scale
    }

    /// A point in normalised coordinates.
    pub fn normalise(&self, p: [f64; 3]) -> [f32; 3] {
        [0, 1, 2].map(|a| ((p[a] - self.center[a]) / self.scale) as f32)
    }

    /// The mesh graph and the `cfg.levels` coarser levels of the network's U-Net, prepared for
    /// its kernel on a device.
    pub fn mesh_graphs(&self, cfg: &SrGcnConfig, device: &Device) -> Result<MeshGraphs, GcnError> {
        let kernel = cfg.kernel()?;
        let positions: Vec<[f64; 3]> = self
            .preop
            .chunks_exact(3)
            .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64])
            .collect();
        let h = hierarchy(
            &self.graph,
            &positions,
            cfg.resolution + cfg.levels,
            cfg.pool_ratio,
            (cfg.clusters > 0).then_some(cfg.clusters),
        )?;
        let (to_start, from_start) = if cfg.resolution > 0 {
            let a = compose_assign(&h, cfg.resolution);
            let c = &h[cfg.resolution - 1];
            (
                Some(SparseOp::new(mean_pool(&a, c.graph.num_nodes)?)),
                Some(SparseOp::new(interpolation(&a, &positions, c)?)),
            )
        } else {
            (None, None)
        };
        let levels = h
            .iter()
            .map(|c| {
                Ok(CoarseLevel {
                    graph: SplineGraph::from_graph(&c.graph, &kernel, device)?,
                    pool: SparseOp::new(c.pool()?),
                    unpool: SparseOp::new(c.unpool()?),
                })
            })
            .collect::<Result<_, GcnError>>()?;
        Ok(MeshGraphs {
            fine: if cfg.resolution == 0 {
                Some(SplineGraph::from_graph(&self.graph, &kernel, device)?)
            } else {
                None
            },
            levels,
            start: cfg.resolution,
            to_start,
            from_start,
        })
    }
}

/// A random affine map `p ↦ A p + t` of normalised coordinates, `A = I + s·G` and `t = s·h`
/// with the entries of `G` and `h` uniform in [−1, 1] (`s` the strength): rotation, shear,
/// scaling and translation of up to about `s` (a fraction of the case's RMS radius).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionJitter {
    /// The linear part, row-major.
    pub a: [[f32; 3]; 3],
    /// The translation.
    pub t: [f32; 3],
}

impl PositionJitter {
    /// Draws a map of strength `strength` from `seed` (deterministic).
    pub fn draw(strength: f64, seed: u64) -> Self {
        let mut rng = crate::util::SplitMix64::new(seed);
        let mut uniform = move || 2.0 * rng.next_f64() - 1.0;
        let mut a = [[0f32; 3]; 3];
        for (i, row) in a.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = (if i == j { 1.0 } else { 0.0 } + strength * uniform()) as f32;
            }
        }
        let t = [0; 3].map(|_| (strength * uniform()) as f32);
        Self { a, t }
    }

    /// Maps one point `[x, y, z]` in place.
    pub fn apply(&self, p: &mut [f32]) {
        let q = [p[0], p[1], p[2]];
        for (i, x) in p.iter_mut().take(3).enumerate() {
            *x = self.a[i][0] * q[0] + self.a[i][1] * q[1] + self.a[i][2] * q[2] + self.t[i];
        }
    }
}

/// The compact bipartite graph of one sample (host side).
#[derive(Debug, Clone)]
pub struct BipartiteData {
    /// Graph over the matched vertices (nodes `0..vertices.len()`) then the points.
    pub graph: Graph,
    /// Mesh vertex of each vertex node.
    pub vertices: Vec<usize>,
    /// Normalised positions, `[Nb, 3]`: LIBR-deformed vertices, then points.
    pub features: Vec<f32>,
}

/// One SR-GCN input (and its targets when built for training), host side.
#[derive(Debug, Clone)]
pub struct SampleData {
    /// Number of mesh nodes.
    pub num_nodes: usize,
    /// Mesh-branch input `[V, channels]` ([`SrGcnConfig::mesh_inputs`]).
    pub node_features: Vec<f32>,
    /// Input channels of `node_features`.
    pub channels: usize,
    /// The bipartite graph, when the configuration uses it.
    pub bipartite: Option<BipartiteData>,
    /// Sparse-loss interpolation `[M, V]`: row m holds the barycentric weights of the model point
    /// matched to measured point m.
    pub sparse_rows: Csr,
    /// Sparse-loss targets `[M, 3]` in output units: where the correction must move each matched
    /// model point (to its measured point).
    pub sparse_target: Vec<f32>,
    /// Training target `[V, 3]` in output units (residual or whole displacement), when known.
    pub target: Option<Vec<f32>>,
}

/// The `k` nearest of `nodes` to each of `points` (exact; all of them when `k` ≥ their count),
/// nearest first by squared Euclidean distance, exact ties in the order of the node index (the
/// lower index first, at the k-th place too). A k-d tree (`kiddo`) finds the candidates; their
/// distances are recomputed here, so the order depends on the coordinates alone.
pub fn knn(nodes: &[[f64; 3]], points: &[[f64; 3]], k: usize) -> Vec<Vec<usize>> {
    let k = k.min(nodes.len());
    let Some(k1) = std::num::NonZero::new(k) else {
        return vec![Vec::new(); points.len()];
    };
    let d2 = |p: &[f64; 3], i: usize| (0..3).map(|a| (nodes[i][a] - p[a]).powi(2)).sum::<f64>();
    // Nearest first, ties by index; the first k.
    let order = |mut c: Vec<(f64, usize)>| -> Vec<usize> {
        c.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        c.into_iter().take(k).map(|(_, i)| i).collect()
    };
    if k == nodes.len() {
        return points
            .par_iter()
            .map(|p| order((0..nodes.len()).map(|i| (d2(p, i), i)).collect()))
            .collect();
    }
    let tree: kiddo::ImmutableKdTree<f64, 3> = kiddo::ImmutableKdTree::new_from_slice(nodes);
    // One more than k: when the (k+1)-th is clearly farther than the k-th, the k nearest are
    // those k; otherwise (a tie, or a near-tie within round-off, at the k-th place) every node
    // within the k-th distance, widened by a relative 1e-9, competes by (distance, index).
    let more = k1.saturating_add(1);
    points
        .par_iter()
        .map(|p| {
            let near = tree.nearest_n::<kiddo::SquaredEuclidean>(p, more);
            let kth = near[k - 1].distance;
            let candidates: Vec<usize> = if !kth.is_finite() {
                // A point with a non-finite coordinate: every node, as (NaN, index) orders them.
                (0..nodes.len()).collect()
            } else if near[k].distance > kth * (1.0 + 1e-9) {
                near[..k].iter().map(|n| n.item as usize).collect()
            } else {
                let r = kth * (1.0 + 1e-9) + f64::MIN_POSITIVE;
                tree.within_unsorted::<kiddo::SquaredEuclidean>(p, r)
                    .iter()
                    .map(|n| n.item as usize)
                    .collect()
            };
            order(candidates.into_iter().map(|i| (d2(p, i), i)).collect())
        })
        .collect()
}

impl SampleData {
    /// Builds the input of one registration: the preoperative model, its LIBR result (`u`,
    /// image → physical `transform`) and the measurements. The bipartite graph links each measured
    /// point to its nearest LIBR-deformed vertices. The sample carries no training target.
    pub fn build(
        cfg: &SrGcnConfig,
        frame: &CaseFrame,
        libr: &Registered<'_>,
    ) -> Result<Self, GcnError> {
        Self::build_linking(cfg, frame, libr, None)
    }

    /// As [`SampleData::build`], but where `cfg.diagnostic_truth_neighbours` is set the bipartite
    /// graph links each measured point to its nearest `neighbour_positions` (physical frame, one
    /// per node) instead of LIBR's deformed vertices. A diagnostic of training only (the LIBR+
    /// paper's ground-truth neighbours); such a model needs them and cannot register.
    pub fn build_linking(
        cfg: &SrGcnConfig,
        frame: &CaseFrame,
        libr: &Registered<'_>,
        neighbour_positions: Option<&[[f64; 3]]>,
    ) -> Result<Self, GcnError> {
        let Registered {
            mesh,
            correspondence,
            cparams,
            meas,
            u,
            transform,
        } = *libr;
        let nodes = mesh.nodes();
        let v = nodes.len();
        if u.len() != 3 * v || u.iter().any(|x| !x.is_finite()) {
            return Err(GcnError::Invalid(format!(
                "u must hold 3 × {v} finite values, has {}",
                u.len()
            )));
        }
        if let Some(t) = neighbour_positions
            && t.len() != v
        {
            return Err(GcnError::Invalid(format!(
                "truth has {} positions, the mesh {v} nodes",
                t.len()
            )));
        }
        let deformed: Vec<[f64; 3]> = (0..v)
            .map(|i| [0, 1, 2].map(|a| nodes[i][a] + u[3 * i + a]))
            .collect();
        let inv = transform.inverse();
        let points: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
        let bipartite =
            Self::bipartite_linking(cfg, frame, &deformed, &points, &inv, neighbour_positions)?;
        // Sparse loss: the model point matched to each measured point on the LIBR-deformed model.
        let unit = frame.unit_mm();
        let (matches, _) = correspondence.match_points(&points, meas, Some(u), cparams)?;
        let (sparse_rows, sparse_target) = Self::sparse_loss(cfg, &matches, &points, u, v, unit)?;
        let misfit = Self::measured_misfit(cfg, &matches, &points, u, v, unit);
        let loads = if cfg.load_input {
            frame.implied_loads(mesh, u)?
        } else {
            Vec::new()
        };
        let channels = cfg.mesh_inputs();
        let node_features =
            Self::mesh_node_features(cfg, frame, &deformed, u, &misfit, &loads, unit);
        Ok(Self {
            num_nodes: v,
            node_features,
            channels,
            bipartite,
            sparse_rows,
            sparse_target,
            target: None,
        })
    }

    /// The bipartite graph of [`SampleData::build_linking`] (`None` unless `cfg.bipartite`): each
    /// point to its `n_top` nearest LIBR-deformed vertices (the paper's diagnostic: nearest
    /// ground-truth vertices, see `SrGcnConfig::diagnostic_truth_neighbours`).
    fn bipartite_linking(
        cfg: &SrGcnConfig,
        frame: &CaseFrame,
        deformed: &[[f64; 3]],
        points: &[[f64; 3]],
        inv: &Rigid,
        neighbour_positions: Option<&[[f64; 3]]>,
    ) -> Result<Option<BipartiteData>, GcnError> {
        if !cfg.bipartite {
            return Ok(None);
        }
        let v = deformed.len();
        let near = if cfg.diagnostic_truth_neighbours {
            let Some(truth) = neighbour_positions else {
                return Err(GcnError::Invalid(
                    "this model was trained with --diagnostic-truth-neighbours (the LIBR+ paper's ground-truth leak): it needs the ground truth and cannot register".into(),
                ));
            };
            let truth_image: Vec<[f64; 3]> = truth.iter().map(|&p| inv.apply(p)).collect();
            knn(&truth_image, points, cfg.n_top)
        } else {
            knn(deformed, points, cfg.n_top)
        };
        let mut local = vec![usize::MAX; v];
        let mut vertices = Vec::new();
        for list in &near {
            for &i in list {
                if local[i] == usize::MAX {
                    local[i] = vertices.len();
                    vertices.push(i);
                }
            }
        }
        let nv = vertices.len();
        let mut targets = Vec::new();
        let mut sources = Vec::new();
        for (p, list) in near.iter().enumerate() {
            for &i in list {
                targets.extend([local[i], nv + p]);
                sources.extend([nv + p, local[i]]);
            }
        }
        let mut pos: Vec<f64> = vertices.iter().flat_map(|&i| deformed[i]).collect();
        pos.extend(points.iter().flatten());
        let pseudo = cartesian_pseudo(&pos, 3, &targets, &sources)?;
        let mut features: Vec<f32> = vertices
            .iter()
            .flat_map(|&i| frame.normalise(deformed[i]))
            .collect();
        features.extend(points.iter().flat_map(|&p| frame.normalise(p)));
        Ok(Some(BipartiteData {
            graph: Graph {
                num_nodes: nv + points.len(),
                targets,
                sources,
                pseudo,
            },
            vertices,
            features,
        }))
    }

    /// The sparse-loss operator (one row of barycentric weights per match, over `v` nodes) and
    /// its targets: measured point minus the `cfg.target` base point, in units of `unit` mm.
    fn sparse_loss(
        cfg: &SrGcnConfig,
        matches: &[Match],
        points: &[[f64; 3]],
        u: &[f64],
        v: usize,
        unit: f64,
    ) -> Result<(Csr, Vec<f32>), GcnError> {
        let mut trip = Vec::new();
        let mut sparse_target = Vec::with_capacity(3 * matches.len());
        for (row, m) in matches.iter().enumerate() {
            for k in 0..4 {
                if m.bary[k] != 0.0 {
                    trip.push((row, m.nodes[k] as usize, m.bary[k] as f32));
                }
            }
            let base = match cfg.target {
                Target::Residual => m.model_point(u),
                Target::Gt => m.anchor,
            };
            let p = points[m.point];
            sparse_target.extend((0..3).map(|a| ((p[a] - base[a]) / unit) as f32));
        }
        let sparse_rows = Csr::from_triplets(matches.len(), v, &trip)?;
        Ok((sparse_rows, sparse_target))
    }

    /// Measured misfit per vertex: barycentric-weighted sums of `(p − q) / unit` over the matches
    /// it carries, and the weight sum in `[3]` (empty unless `cfg.misfit_input`).
    fn measured_misfit(
        cfg: &SrGcnConfig,
        matches: &[Match],
        points: &[[f64; 3]],
        u: &[f64],
        v: usize,
        unit: f64,
    ) -> Vec<[f64; 4]> {
        let mut misfit = vec![[0f64; 4]; if cfg.misfit_input { v } else { 0 }];
        if cfg.misfit_input {
            for m in matches {
                let q = m.model_point(u);
                let p = points[m.point];
                for k in 0..4 {
                    let w = m.bary[k];
                    if w != 0.0 {
                        let acc = &mut misfit[m.nodes[k] as usize];
                        for a in 0..3 {
                            acc[a] += w * (p[a] - q[a]) / unit;
                        }
                        acc[3] += w;
                    }
                }
            }
        }
        misfit
    }

    /// The mesh-branch input, `[V, cfg.mesh_inputs()]` row-major.
    fn mesh_node_features(
        cfg: &SrGcnConfig,
        frame: &CaseFrame,
        deformed: &[[f64; 3]],
        u: &[f64],
        misfit: &[[f64; 4]],
        loads: &[f32],
        unit: f64,
    ) -> Vec<f32> {
        let v = deformed.len();
        let channels = cfg.mesh_inputs();
        let mut node_features = Vec::with_capacity(v * channels);
        for i in 0..v {
            node_features.extend_from_slice(&frame.preop[3 * i..3 * i + 3]);
            if cfg.libr_input {
                node_features.extend(frame.normalise(deformed[i]));
                node_features.extend((0..3).map(|a| (u[3 * i + a] / unit) as f32));
            }
            if cfg.misfit_input {
                let m = misfit[i];
                let w = m[3];
                let mean = |a: usize| if w > 0.0 { (m[a] / w) as f32 } else { 0.0 };
                node_features.extend([mean(0), mean(1), mean(2), w.min(1.0) as f32]);
            }
            if cfg.surface_input {
                node_features.extend_from_slice(&frame.surface[4 * i..4 * i + 4]);
            }
            if cfg.load_input {
                node_features.extend_from_slice(&loads[3 * i..3 * i + 3]);
            }
        }
        node_features
    }

    /// A copy whose normalised **position** channels (the preoperative and LIBR-deformed node
    /// coordinates, and every bipartite feature) are mapped by `jitter`; the displacement,
    /// misfit and target channels are left as they are. A training augmentation: the network
    /// cannot tie a correction to where a node sits in the normalised frame to better than the
    /// jitter, and must read it from the shape and the LIBR displacement instead.
    pub fn jittered(&self, cfg: &SrGcnConfig, jitter: &PositionJitter) -> Self {
        let mut out = self.clone();
        let c = self.channels;
        let position_channels: &[usize] = if cfg.libr_input { &[0, 3] } else { &[0] };
        for row in out.node_features.chunks_exact_mut(c) {
            for &k in position_channels {
                jitter.apply(&mut row[k..k + 3]);
            }
        }
        if let Some(b) = out.bipartite.as_mut() {
            for p in b.features.chunks_exact_mut(3) {
                jitter.apply(p);
            }
        }
        out
    }

    /// The mesh-branch input `[V, channels]` on a device.
    pub fn tensors_mesh(&self, device: &Device) -> Tensor<2> {
        Tensor::<2>::from_data(
            TensorData::new(self.node_features.clone(), [self.num_nodes, self.channels]),
            device,
        )
    }

    /// The network inputs on a device.
    pub fn tensors(
        &self,
        cfg: &SrGcnConfig,
        device: &Device,
    ) -> Result<(Tensor<2>, Option<BipartiteInput>), GcnError> {
        let x = self.tensors_mesh(device);
        let bip = match &self.bipartite {
            None => None,
            Some(b) => {
                let g = &b.graph;
                let graph = SplineGraph::from_graph(g, &cfg.kernel()?, device)?;
                let features = Tensor::<2>::from_data(
                    TensorData::new(b.features.clone(), [g.num_nodes, 3]),
                    device,
                );
                let trip: Vec<_> = b
                    .vertices
                    .iter()
                    .enumerate()
                    .map(|(l, &i)| (i, l, 1.0))
                    .collect();
                let to_mesh =
                    SparseOp::new(Csr::from_triplets(self.num_nodes, g.num_nodes, &trip)?);
                let mut mask = vec![0f32; self.num_nodes];
                for &i in &b.vertices {
                    mask[i] = 1.0;
                }
                let mask =
                    Tensor::<2>::from_data(TensorData::new(mask, [self.num_nodes, 1]), device);
                Some(BipartiteInput {
                    graph,
                    features,
                    to_mesh,
                    mask,
                })
            }
        };
        Ok((x, bip))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `K·u` against elasticity: zero for rigid motions (translation, infinitesimal rotation);
    /// for a uniaxial stretch (σ_xx = E·ε, the lateral faces free) zero at interior nodes and on
    /// the free faces, and on the stretched end face a total of E·ε·A along x (linear fields are
    /// exact for linear tets, so the figures hold to round-off).
    #[test]
    fn implied_loads_vanish_for_rigid_motion_and_balance_a_uniform_stretch() {
        let size = [40.0, 30.0, 20.0];
        let mesh = crate::mesh::procedural::box_mesh(size, [8, 6, 4], 0.0);
        let frame = CaseFrame::new(&mesh).unwrap();
        let nodes = mesh.nodes();
        let field = |f: &dyn Fn([f64; 3]) -> [f64; 3]| -> Vec<f64> {
            nodes.iter().flat_map(|&p| f(p)).collect()
        };
        let max_abs = |v: &[f32]| v.iter().fold(0f32, |m, x| m.max(x.abs()));
        let shift = frame
            .implied_loads(&mesh, &field(&|_| [1.5, -2.0, 0.7]))
            .unwrap();
        assert!(max_abs(&shift) < 1e-9, "translation: {}", max_abs(&shift));
        let w = [0.01, -0.02, 0.015];
        let turn = frame
            .implied_loads(
                &mesh,
                &field(&|p| {
                    [
                        w[1] * p[2] - w[2] * p[1],
                        w[2] * p[0] - w[0] * p[2],
                        w[0] * p[1] - w[1] * p[0],
                    ]
                }),
            )
            .unwrap();
        assert!(max_abs(&turn) < 1e-9, "rotation: {}", max_abs(&turn));
        let (eps, nu, mu) = (0.01, 0.45, 1.0);
        let e = 2.0 * mu * (1.0 + nu);
        let f = frame
            .implied_loads(
                &mesh,
                &field(&|p| [eps * p[0], -nu * eps * p[1], -nu * eps * p[2]]),
            )
            .unwrap();
        // Back to mN: the channels are in units of μ × output unit × mean edge length.
        let to_mn = mu * frame.unit_mm() * frame.mean_edge_mm(&mesh);
        let (mut end, mut start) = (0.0, 0.0);
        for (p, fi) in nodes.iter().zip(f.chunks_exact(3)) {
            let fx = fi[0] as f64 * to_mn;
            if (p[0] - size[0]).abs() < 1e-9 {
                end += fx;
            } else if p[0].abs() < 1e-9 {
                start += fx;
            } else {
                // Interior and the free lateral faces carry nothing along x.
                assert!(fx.abs() < 1e-6, "{p:?}: {fx}");
            }
            // Nor across: the lateral faces are traction-free.
            assert!((fi[1] as f64 * to_mn).abs() < 1e-6, "{p:?}: {fi:?}");
            assert!((fi[2] as f64 * to_mn).abs() < 1e-6, "{p:?}: {fi:?}");
        }
        let want = e * eps * size[1] * size[2];
        assert!(
            (end - want).abs() < 1e-4 * want,
            "end face {end} mN, want {want}"
        );
        assert!((start + want).abs() < 1e-4 * want, "start face {start} mN");
    }

    #[test]
    fn the_surface_channels_flag_the_boundary_and_point_outwards() {
        // A box from 0 to (40, 30, 20) mm; every node of a face centre's neighbourhood has the
        // face's normal, the corners a diagonal one, and interior nodes nothing.
        let mesh = crate::mesh::procedural::box_mesh([40.0, 30.0, 20.0], [4, 3, 2], 0.0);
        let frame = CaseFrame::new(&mesh).unwrap();
        assert_eq!(frame.surface.len(), 4 * mesh.num_nodes());
        let mut flagged = 0;
        for (p, s) in mesh.nodes().iter().zip(frame.surface.chunks_exact(4)) {
            let on = [0, 1, 2].iter().any(|&a| {
                let hi = [40.0, 30.0, 20.0][a];
                p[a].abs() < 1e-9 || (p[a] - hi).abs() < 1e-9
            });
            let n = [s[1] as f64, s[2] as f64, s[3] as f64];
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if on {
                flagged += 1;
                assert_eq!(s[0], 1.0);
                assert!((len - 1.0).abs() < 1e-6, "{p:?}: |n| = {len}");
                // Outward: the normal points away from the box centre.
                let c = [20.0, 15.0, 10.0];
                let out: f64 = (0..3).map(|a| n[a] * (p[a] - c[a])).sum();
                assert!(out > 0.0, "{p:?}: {n:?} points inwards");
            } else {
                assert_eq!(s, &[0.0; 4], "{p:?} is inside");
            }
        }
        assert_eq!(flagged, 5 * 4 * 3 - 3 * 2);
        // The node at the middle of the x = 40 face (x = 40, y = 10 or 20, z = 10).
        let i = mesh
            .nodes()
            .iter()
            .position(|p| *p == [40.0, 10.0, 10.0])
            .unwrap();
        let s = &frame.surface[4 * i..4 * i + 4];
        assert!((s[1] - 1.0).abs() < 1e-6 && s[2].abs() < 1e-6 && s[3].abs() < 1e-6);
        // Winding the tets the other way (a mirrored mesh reads so) still points outwards.
        let flipped = TetMesh::new(
            mesh.nodes().to_vec(),
            mesh.tets()
                .iter()
                .map(|t| [t[1], t[0], t[2], t[3]])
                .collect(),
        )
        .unwrap();
        let f2 = CaseFrame::new(&flipped).unwrap();
        assert_eq!(&f2.surface[4 * i..4 * i + 4], s);
    }

    #[test]
    fn knn_equals_brute_force() {
        let mut s = 3u64;
        let mut rnd = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let nodes: Vec<[f64; 3]> = (0..500)
            .map(|_| [rnd() * 100.0, rnd() * 50.0, rnd() * 10.0])
            .collect();
        // Points inside, near and far outside the cloud.
        let points: Vec<[f64; 3]> = (0..60)
            .map(|i| {
                let f = if i % 3 == 0 { 3.0 } else { 1.0 };
                [rnd() * 100.0 * f - 50.0, rnd() * 50.0 * f, rnd() * 10.0 * f]
            })
            .collect();
        for k in [1, 4, 9] {
            let got = knn(&nodes, &points, k);
            for (p, list) in points.iter().zip(&got) {
                assert_eq!(list, &brute_force_knn(&nodes, p, k));
            }
        }
    }

    /// The `k` nearest of `nodes` to `p`: nearest first, ties by index.
    fn brute_force_knn(nodes: &[[f64; 3]], p: &[f64; 3], k: usize) -> Vec<usize> {
        let mut all: Vec<(f64, usize)> = nodes
            .iter()
            .enumerate()
            .map(|(i, q)| ((0..3).map(|a| (q[a] - p[a]).powi(2)).sum::<f64>(), i))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.iter().take(k).map(|x| x.1).collect()
    }

    #[test]
    fn knn_breaks_exact_ties_by_node_index() {
        // A regular 7 × 6 × 5 grid of 2-mm spacing, its nodes in a scrambled order: a cell
        // centre has 8 nodes at one distance, a face centre 4, an edge midpoint 2, a node 6 at
        // the spacing, so most k cut through a tie.
        let mut nodes: Vec<[f64; 3]> = Vec::new();
        for z in 0..5 {
            for y in 0..6 {
                for x in 0..7 {
                    nodes.push([2.0 * x as f64, 2.0 * y as f64, 2.0 * z as f64]);
                }
            }
        }
        let n = nodes.len();
        let nodes: Vec<[f64; 3]> = (0..n).map(|i| nodes[(i * 97) % n]).collect();
        let mut points: Vec<[f64; 3]> = Vec::new();
        for (x, y, z) in [(0, 0, 0), (3, 2, 1), (6, 5, 4), (2, 4, 3)] {
            let c = [2.0 * x as f64, 2.0 * y as f64, 2.0 * z as f64];
            points.push(c);
            points.push([c[0] + 1.0, c[1] + 1.0, c[2] + 1.0]);
            points.push([c[0] + 1.0, c[1] + 1.0, c[2]]);
            points.push([c[0] + 1.0, c[1], c[2]]);
            points.push([c[0] - 1.0, c[1] - 1.0, c[2] - 1.0]);
        }
        // Outside the grid, level with a face: a square of ties.
        points.push([-5.0, 5.0, 3.0]);
        for k in [1, 2, 3, 4, 5, 6, 7, 8, 9, 13, 27, n - 1, n, n + 3] {
            let got = knn(&nodes, &points, k);
            for (p, list) in points.iter().zip(&got) {
                let want = brute_force_knn(&nodes, p, k);
                assert_eq!(list, &want, "k {k}, point {p:?}");
            }
        }
        assert!(knn(&nodes, &points, 0).iter().all(|l| l.is_empty()));
        assert!(knn(&[], &points, 3).iter().all(|l| l.is_empty()));
    }
}
