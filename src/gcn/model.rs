//! SR-GCN, the spline-residual graph network of LIBR+ (Wang et al.): a **bipartite branch** over
//! the graph linking measured points to their nearest LIBR-deformed vertices, and a **mesh
//! branch** over the tetrahedral mesh graph whose convoluter inputs are averaged, at the matched
//! vertices, with the bipartite branch's features of the same layer. Each branch is a spline
//! encoder (input → width, ELU), `convs` spline convoluters (width → width, ELU) and a spline
//! decoder (width → 3, linear). The mesh branch's output is the per-node correction
//! (the residual of LIBR, or the whole displacement for the `Gt` ablations) in the model's
//! output unit; the bipartite branch's output reconstructs its input (stage-1 pretext task).
//!
//! Where the paper's averaging `x ← ½(x + x̃_b)` with `x̃_b = 0` away from the matched vertices
//! would halve every unmatched vertex's features, this averages at the matched vertices only
//! (`x ← x + m ⊙ ½(x̃_b − x)`, `m` the matched-vertex mask), which is what "aggregated with the
//! bipartite features at the corresponding vertices" describes.
//!
//! Departures from the paper, each a switch (format-2 models load with the paper's choice):
//! the mesh branch runs on a cluster level of the mesh (`resolution`, the correction interpolated
//! back to every node), continues as a U-Net over coarser cluster graphs (`levels`), and its
//! width-preserving convolutions are residual blocks (`residual`).

use burn::config::Config;
use burn::module::Module;
use burn::tensor::activation::elu;
use burn::tensor::{Device, Tensor};

use super::sparse::SparseOp;
use super::{GcnError, SplineConv, SplineConvConfig, SplineGraph, SplineKernel};

/// What the mesh branch is trained to predict (the paper's Table 2 loss conditions).
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum Target {
    /// The residual of LIBR to the truth (`L_residual`); LIBR+ = LIBR + prediction.
    Residual,
    /// The whole displacement from the preoperative mesh (`L_gt`); LIBR+ = preop + prediction.
    Gt,
}

/// How a per-node error vector `e` (output units) is penalised.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum Loss {
    /// `|e|²` averaged over nodes and components: the paper's L2 losses.
    Squared,
    /// `√(|e|² + ε²) − ε` with ε = 0.01 (Charbonnier): the mean node distance TRE measures.
    /// Squared losses let the few nodes with large LIBR errors (a retracted lobe) dominate, and
    /// lowering them while most nodes get worse raises TRE.
    Distance,
}

/// Architecture and ablation switches of SR-GCN.
#[derive(Config, Debug)]
pub struct SrGcnConfig {
    /// Feature width of encoders and convoluters (the paper: 1024, on a GPU).
    #[config(default = 32)]
    pub width: usize,
    /// Convoluters per branch (N_c); in the mesh branch at full resolution, before the U-Net.
    /// One is enough there when the U-Net has coarse convolutions (random split, paper preset:
    /// N_c 1 + 3 per coarse level matched N_c 3 + 1 per level in 30% less time).
    #[config(default = 1)]
    pub convs: usize,
    /// The level the mesh branch's convolutions run at: 0 the full mesh (the paper); 1 the first
    /// cluster level (about `1/pool_ratio` of the nodes). At `r ≥ 1` the node inputs are
    /// mean-pooled onto level `r`, the encoder, convoluters and U-Net run from there, and the
    /// decoded correction is interpolated smoothly back to every node
    /// ([`super::coarsen::interpolation`]). LIBR's residual is smooth at that scale, and the
    /// full-resolution layers cost most of the time (training steps about 4× cheaper).
    /// Format-2 model files predate this switch and load with 0.
    #[config(default = 1)]
    pub resolution: usize,
    /// Coarser levels of the mesh branch's U-Net below `resolution` (0: a single-resolution
    /// branch, as the paper's).
    /// After the convoluters the features are mean-pooled level by level (clusters of about
    /// `pool_ratio` nodes, [`super::coarsen`]), convolved on each cluster graph, and brought back
    /// up with skip connections, so the correction sees the whole organ.
    #[config(default = 2)]
    pub levels: usize,
    /// Nodes per cluster from one level to the next.
    #[config(default = 8)]
    pub pool_ratio: usize,
    /// Clusters of the first cluster level, whatever the mesh's resolution (0: `1/pool_ratio`
    /// of the nodes, as format-3 files written before this switch). With a fixed count the
    /// cluster graphs have the same spacing relative to the liver on a coarse or a fine mesh
    /// (inputs are normalised by the liver's RMS radius), so a model trained on ~9,000-node
    /// livers sees on a 1,800-node or a 30,000-node liver the graphs it was trained on, and its
    /// cost no longer grows with the mesh. A mesh with fewer nodes keeps one cluster per node.
    #[config(default = 0)]
    pub clusters: usize,
    /// Spline convolutions on each coarse level on the way down (cheap: a level has
    /// `1/pool_ratio` of the nodes of the one above).
    #[config(default = 3)]
    pub coarse_convs: usize,
    /// Spline kernel size per pseudo-coordinate dimension.
    #[config(default = 3)]
    pub kernel_size: usize,
    /// B-spline degree.
    #[config(default = 1)]
    pub degree: usize,
    /// Nearest LIBR-deformed vertices linked to each measured point (N_top).
    #[config(default = 4)]
    pub n_top: usize,
    /// Whether LIBR's result is a mesh-branch input (Table 2: "LIBR"): the LIBR-deformed
    /// coordinates, normalised, and LIBR's displacement in output units (the same information,
    /// the displacement at a scale the first layer can use without cancelling large numbers).
    #[config(default = true)]
    pub libr_input: bool,
    /// Whether the bipartite branch is used (Table 2: "Bipartite").
    #[config(default = true)]
    pub bipartite: bool,
    /// Whether the mesh branch also gets the measured misfit: at each vertex of a matched model
    /// point, the barycentric-weighted mean of (measured point − LIBR's model point) in output
    /// units, and the summed weight capped at 1 (4 channels; zero away from the data). Not in the
    /// paper; off by default: after LIBR the misfit left at the data is mostly noise (on the small
    /// preset it pointed the way of the true residual at 57 of 116 data vertices, chance level).
    #[config(default = false)]
    pub misfit_input: bool,
    /// Whether the mesh branch also gets each node's place on the organ's boundary: 1 on the
    /// boundary (0 inside) and the area-weighted outward unit normal there (zero inside), 4
    /// channels from the preoperative mesh alone. Not in the paper: where the surface faces
    /// (anterior to a laparoscope, posterior onto the organ bed) says where supports and loads
    /// can act, which the coordinates tell only in one liver's frame.
    #[config(default = false)]
    pub surface_input: bool,
    /// Whether the mesh branch also gets the loads LIBR's displacement implies: `K·u` per node
    /// (3 channels), `K` the linear-elastic stiffness of the preoperative mesh (μ = 1 kPa,
    /// ν = 0.45), in units of μ × output unit × mean edge length. Zero inside the organ where
    /// LIBR's field is in equilibrium, it shows where and how hard LIBR pushed (its control-point
    /// loads) and where its supports held: the loads a correction of the material's response
    /// depends on, in a form not tied to one liver's frame. Not in the paper; off by default.
    #[config(default = false)]
    pub load_input: bool,
    /// **A diagnostic that reproduces a flaw of the LIBR+ paper, never a registration setting.**
    /// The paper linked each measured point to its nearest vertices of the *ground-truth*
    /// deformed mesh, which does not exist in surgery. With this switch the bipartite graph does
    /// the same (the ground truth, in LIBR's image frame), so the training and test figures of
    /// `librplus train --diagnostic-truth-neighbours` show how much of the paper's accuracy that
    /// leak buys. A model made with it cannot register: a registration case refuses it
    /// ([`LibrPlusCase::new`]), and [`SampleData::build`] refuses it without the ground truth,
    /// which inference never has.
    ///
    /// [`SampleData::build`]: super::sample::SampleData::build
    /// [`LibrPlusCase::new`]: super::infer::LibrPlusCase::new
    #[config(default = false)]
    pub diagnostic_truth_neighbours: bool,
    /// Whether the width-preserving convolutions are residual blocks (`x ← x + ELU(conv(x))`, and
    /// on the way up `x ← unpool(x) + ELU(conv([skip, unpool(x)]))`). Not in the paper. Without
    /// them the U-Net is a plain stack of about 15 spline convolutions whose PyG initialisation
    /// shrinks the signal at every layer, and training barely moves (random split, every 32nd
    /// block: training loss 0.86 → 0.815 in 9 epochs). Format-2 model files predate this switch
    /// and load with it off.
    #[config(default = true)]
    pub residual: bool,
    /// Factor on the residual correction at inference, fitted after training on the validation
    /// scenarios (the factor in 0, 0.05, …, 1 with the least validation node error). Where
    /// validation holds out a whole deformation, a correction that does not carry over to unseen
    /// deformations is shrunk towards LIBR's answer instead of making it worse. Not in the paper.
    #[config(default = 1.0)]
    pub correction_scale: f64,
    /// Loss target of the mesh branch.
    #[config(default = "Target::Residual")]
    pub target: Target,
    /// Weight λ of the sparse-measurement loss (0: off).
    #[config(default = 0.1)]
    pub sparse_weight: f64,
    /// Penalty of the residual and sparse losses.
    #[config(default = "Loss::Distance")]
    pub loss: Loss,
}

impl SrGcnConfig {
    /// The spline kernel of every layer (3-D Cartesian pseudo-coordinates, open splines).
    pub fn kernel(&self) -> Result<SplineKernel, GcnError> {
        SplineKernel::new(vec![self.kernel_size; 3], vec![true; 3], self.degree)
    }

    /// Input channels of the mesh branch: preoperative coordinates, plus the LIBR-deformed ones
    /// and LIBR's displacement, plus the misfit, surface and load channels.
    pub fn mesh_inputs(&self) -> usize {
        3 + if self.libr_input { 6 } else { 0 }
            + if self.misfit_input { 4 } else { 0 }
            + if self.surface_input { 4 } else { 0 }
            + if self.load_input { 3 } else { 0 }
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<(), GcnError> {
        if self.width == 0 || self.convs == 0 {
            return Err(GcnError::Invalid("width and convs must be positive".into()));
        }
        if self.levels > 0 && self.coarse_convs == 0 {
            return Err(GcnError::Invalid(
                "coarse_convs must be positive when levels > 0".into(),
            ));
        }
        if self.pool_ratio < 2 || self.levels + self.resolution > 6 {
            return Err(GcnError::Invalid(format!(
                "need pool_ratio ≥ 2 and resolution + levels ≤ 6 (pool_ratio {}, resolution {}, levels {})",
                self.pool_ratio, self.resolution, self.levels
            )));
        }
        if self.n_top == 0 {
            return Err(GcnError::Invalid("n_top must be positive".into()));
        }
        if !(self.correction_scale.is_finite() && (0.0..=2.0).contains(&self.correction_scale)) {
            return Err(GcnError::Invalid(format!(
                "correction_scale must be in [0, 2] (got {})",
                self.correction_scale
            )));
        }
        if !(self.sparse_weight.is_finite() && self.sparse_weight >= 0.0) {
            return Err(GcnError::Invalid(
                "sparse_weight must be finite and ≥ 0".into(),
            ));
        }
        self.kernel().map(|_| ())
    }

    /// Initialises the network (weights from the device's random generator: seed it first).
    pub fn init(&self, device: &Device) -> Result<SrGcn, GcnError> {
        self.validate()?;
        let mesh = self.branch(self.mesh_inputs(), self.levels, device)?;
        let bip = if self.bipartite {
            Some(self.branch(3, 0, device)?)
        } else {
            None
        };
        Ok(SrGcn {
            mesh,
            bip,
            residual: self.residual,
            resolution: self.resolution,
        })
    }

    fn branch(&self, inputs: usize, levels: usize, device: &Device) -> Result<Branch, GcnError> {
        let layer = |cin: usize, cout: usize| {
            SplineConvConfig::new(cin, cout, vec![self.kernel_size; 3], vec![true; 3])
                .with_degree(self.degree)
                .init(device)
        };
        Ok(Branch {
            encoder: layer(inputs, self.width)?,
            convs: (0..self.convs)
                .map(|_| layer(self.width, self.width))
                .collect::<Result<_, _>>()?,
            down: (0..levels * self.coarse_convs)
                .map(|_| layer(self.width, self.width))
                .collect::<Result<_, _>>()?,
            up: (0..levels)
                .map(|_| layer(2 * self.width, self.width))
                .collect::<Result<_, _>>()?,
            decoder: layer(self.width, 3)?,
        })
    }
}

/// One branch: spline encoder, convoluters, decoder.
#[derive(Module, Debug)]
pub struct Branch {
    /// Input → width.
    pub encoder: SplineConv,
    /// Width → width, `N_c` of them.
    pub convs: Vec<SplineConv>,
    /// U-Net descent: `down[l·c .. (l+1)·c]` convolve (width → width) on level `l + 1` after
    /// pooling (`c` = `coarse_convs`).
    pub down: Vec<SplineConv>,
    /// U-Net ascent: `up[l]` convolves (2·width → width) on level `l` the unpooled features of
    /// level `l + 1` concatenated with level `l`'s features from the descent.
    pub up: Vec<SplineConv>,
    /// Width → 3.
    pub decoder: SplineConv,
}

/// The SR-GCN network.
#[derive(Module, Debug)]
pub struct SrGcn {
    /// The mesh branch.
    pub mesh: Branch,
    /// The bipartite branch (None in the ablations without it).
    pub bip: Option<Branch>,
    /// Residual blocks ([`SrGcnConfig::residual`]).
    pub residual: bool,
    /// Level the mesh branch runs at ([`SrGcnConfig::resolution`]).
    pub resolution: usize,
}

/// One coarser level of the mesh graph on a device.
#[derive(Debug, Clone)]
pub struct CoarseLevel {
    /// The cluster graph.
    pub graph: SplineGraph,
    /// Mean pooling from the finer level, `[M, N]`.
    pub pool: SparseOp,
    /// Unpooling to the finer level, `[N, M]`.
    pub unpool: SparseOp,
}

/// The mesh graph and its coarser levels (finest first), prepared for one kernel on a device.
#[derive(Debug, Clone)]
pub struct MeshGraphs {
    /// The full-resolution mesh graph (built only for networks that run at level 0).
    pub fine: Option<SplineGraph>,
    /// Coarser levels, at least the network's `resolution + levels`.
    pub levels: Vec<CoarseLevel>,
    /// Level the operators below lead to and from (0: none).
    pub start: usize,
    /// Mean pooling from the nodes to level `start`, `[V_start, V]`.
    pub to_start: Option<SparseOp>,
    /// Smooth interpolation from level `start` to the nodes, `[V, V_start]`.
    pub from_start: Option<SparseOp>,
}

/// The bipartite part of one input: its graph, node features and where its vertex nodes sit in
/// the mesh.
#[derive(Debug, Clone)]
pub struct BipartiteInput {
    /// The compact bipartite graph (matched vertices, then points).
    pub graph: SplineGraph,
    /// Node features `[Nb, 3]` (normalised positions).
    pub features: Tensor<2>,
    /// Scatter of bipartite node features onto mesh vertices, `[V, Nb]` (a 0/1 matrix).
    pub to_mesh: SparseOp,
    /// 1 at matched mesh vertices, 0 elsewhere, `[V, 1]`.
    pub mask: Tensor<2>,
}

/// Intermediate results of the bipartite branch.
#[derive(Debug, Clone)]
pub struct BipartiteOutput {
    /// Features `x_b^l`, `l = 0..N_c` (encoder output first), each `[Nb, width]`.
    pub features: Vec<Tensor<2>>,
    /// The reconstruction `y_b` `[Nb, 3]`.
    pub reconstruction: Tensor<2>,
}

impl Branch {
    fn decode(&self, x: Tensor<2>, graph: &SplineGraph) -> Result<Tensor<2>, GcnError> {
        self.decoder.forward(x, graph)
    }
}

impl SrGcn {
    /// One width-preserving convolution: `ELU(conv(x))`, plus `x` when residual.
    fn block(
        &self,
        conv: &SplineConv,
        x: Tensor<2>,
        graph: &SplineGraph,
    ) -> Result<Tensor<2>, GcnError> {
        let y = elu(conv.forward(x.clone(), graph)?, 1.0);
        Ok(if self.residual { x + y } else { y })
    }

    /// The bipartite branch on its graph.
    ///
    /// # Shapes
    /// - `input.features`: `[Nb, 3]`
    /// - returns features `N_c + 1` × `[Nb, width]` and the reconstruction `[Nb, 3]`.
    pub fn forward_bipartite(
        &self,
        input: &BipartiteInput,
    ) -> Result<Option<BipartiteOutput>, GcnError> {
        let Some(b) = &self.bip else { return Ok(None) };
        let g = &input.graph;
        let mut x = elu(b.encoder.forward(input.features.clone(), g)?, 1.0);
        let mut features = vec![x.clone()];
        for conv in &b.convs {
            x = elu(conv.forward(x, g)?, 1.0);
            features.push(x.clone());
        }
        let reconstruction = b.decode(x, g)?;
        Ok(Some(BipartiteOutput {
            features,
            reconstruction,
        }))
    }

    /// The mesh branch.
    ///
    /// # Shapes
    /// - `features`: `[V, mesh_inputs]` (preoperative, then LIBR-deformed normalised coordinates
    ///   and LIBR's displacement, then the misfit channels)
    /// - `graphs.fine`: the mesh graph, `V` nodes; `graphs.levels[l]`: `V_{l+1}` clusters, pooled
    ///   `[V_{l+1}, width]` from `[V_l, width]` and unpooled back
    /// - at `resolution` r ≥ 1: features pooled to `[V_r, mesh_inputs]`, everything below runs
    ///   on level r's graph, and the decoded `[V_r, 3]` is interpolated to `[V, 3]`
    /// - U-Net: level `l + 1` features `[V_{l+1}, width]`; on the way up `[V_l, 2·width]` → `[V_l, width]`
    /// - `bipartite`: the bipartite input and the bipartite branch's output (features `[Nb, width]`
    ///   scattered to `[V, width]` by `to_mesh`)
    /// - returns the correction `[V, 3]` in output units.
    pub fn forward_mesh(
        &self,
        features: Tensor<2>,
        graphs: &MeshGraphs,
        bipartite: Option<(&BipartiteInput, &BipartiteOutput)>,
    ) -> Result<Tensor<2>, GcnError> {
        let r = self.resolution;
        let (graph, below) = self.graphs_at(graphs)?;
        let features = if r > 0 {
            start_op(&graphs.to_start)?.apply(features)?
        } else {
            features
        };
        let mut x = elu(self.mesh.encoder.forward(features, graph)?, 1.0);
        for (l, conv) in self.mesh.convs.iter().enumerate() {
            if let Some((input, out)) = bipartite {
                let xb = input.to_mesh.apply(out.features[l].clone())?;
                x = if r == 0 {
                    x.clone() + input.mask.clone() * (xb - x) * 0.5
                } else {
                    // The node rule averaged over each cluster (x constant on it):
                    // x + ½(mean(m ⊙ x̃_b) − mean(m) ⊙ x).
                    let to = start_op(&graphs.to_start)?;
                    let pb = to.apply(xb)?;
                    let pm = to.apply(input.mask.clone())?;
                    x.clone() + (pb - pm * x) * 0.5
                };
            }
            x = self.block(conv, x, graph)?;
        }
        let x = self.unet(x, graph, below)?;
        let y = self.mesh.decode(x, graph)?;
        if r > 0 {
            start_op(&graphs.from_start)?.apply(y)
        } else {
            Ok(y)
        }
    }

    /// The graph the network runs on (the mesh's at resolution 0, else level r's) and the
    /// coarse levels below it; an error when `graphs` were built for another network.
    fn graphs_at<'g>(
        &self,
        graphs: &'g MeshGraphs,
    ) -> Result<(&'g SplineGraph, &'g [CoarseLevel]), GcnError> {
        let m = &self.mesh;
        let r = self.resolution;
        let levels = m.up.len();
        if graphs.levels.len() < r + levels
            || (levels > 0 && m.down.len() % levels != 0)
            || (r > 0 && graphs.start != r)
        {
            return Err(GcnError::Invalid(format!(
                "the network runs at level {r} with {levels} coarse levels ({} convolutions); \
                 the graphs have {} levels and start operators for level {}",
                m.down.len(),
                graphs.levels.len(),
                graphs.start
            )));
        }
        if r > 0 {
            return Ok((&graphs.levels[r - 1].graph, &graphs.levels[r..]));
        }
        let fine = graphs
            .fine
            .as_ref()
            .ok_or_else(|| GcnError::Invalid("graphs lack the full-resolution graph".into()))?;
        Ok((fine, &graphs.levels[..]))
    }

    /// The U-Net below the start graph: pooled level by level through the down blocks, then
    /// unpooled back, each level's skip concatenated on the way up.
    fn unet(
        &self,
        mut x: Tensor<2>,
        graph: &SplineGraph,
        below: &[CoarseLevel],
    ) -> Result<Tensor<2>, GcnError> {
        let m = &self.mesh;
        let levels = m.up.len();
        let per_level = m.down.len().checked_div(levels).unwrap_or(0);
        let mut skips = Vec::with_capacity(m.down.len());
        for (l, level) in below.iter().take(levels).enumerate() {
            let pooled = level.pool.apply(x.clone())?;
            skips.push(x);
            x = pooled;
            for down in &m.down[l * per_level..(l + 1) * per_level] {
                x = self.block(down, x, &level.graph)?;
            }
        }
        for (l, up) in m.up.iter().enumerate().rev() {
            let skip = skips
                .pop()
                .ok_or_else(|| GcnError::Invalid("U-Net skip".into()))?;
            let finer = if l == 0 { graph } else { &below[l - 1].graph };
            let up_x = below[l].unpool.apply(x)?;
            let y = elu(
                up.forward(Tensor::cat(vec![skip, up_x.clone()], 1), finer)?,
                1.0,
            );
            x = if self.residual { up_x + y } else { y };
        }
        Ok(x)
    }
}

/// The start operators of graphs built for a network at a coarse resolution.
fn start_op(o: &Option<SparseOp>) -> Result<&SparseOp, GcnError> {
    o.as_ref()
        .ok_or_else(|| GcnError::Invalid("graphs lack the start operators".into()))
}
