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
    /// Convoluters per branch (N_c).
    #[config(default = 3)]
    pub convs: usize,
    /// Spline kernel size per pseudo-coordinate dimension.
    #[config(default = 3)]
    pub kernel_size: usize,
    /// B-spline degree.
    #[config(default = 1)]
    pub degree: usize,
    /// Nearest LIBR-deformed vertices linked to each measured point (N_top).
    #[config(default = 4)]
    pub n_top: usize,
    /// Whether the LIBR-deformed coordinates are a mesh-branch input (Table 2: "LIBR").
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

    /// Input channels of the mesh branch: preoperative coordinates, plus the LIBR-deformed ones,
    /// plus the misfit channels.
    pub fn mesh_inputs(&self) -> usize {
        3 + if self.libr_input { 3 } else { 0 } + if self.misfit_input { 4 } else { 0 }
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<(), GcnError> {
        if self.width == 0 || self.convs == 0 {
            return Err(GcnError::Invalid("width and convs must be positive".into()));
        }
        if self.n_top == 0 {
            return Err(GcnError::Invalid("n_top must be positive".into()));
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
        let mesh = self.branch(self.mesh_inputs(), device)?;
        let bip = if self.bipartite {
            Some(self.branch(3, device)?)
        } else {
            None
        };
        Ok(SrGcn { mesh, bip })
    }

    fn branch(&self, inputs: usize, device: &Device) -> Result<Branch, GcnError> {
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
    /// - `features`: `[V, 3 or 6]` (preoperative, then LIBR-deformed normalised coordinates)
    /// - `graph`: the mesh graph, `V` nodes
    /// - `bipartite`: the bipartite input and the bipartite branch's output (features `[Nb, width]`
    ///   scattered to `[V, width]` by `to_mesh`)
    /// - returns the correction `[V, 3]` in output units.
    pub fn forward_mesh(
        &self,
        features: Tensor<2>,
        graph: &SplineGraph,
        bipartite: Option<(&BipartiteInput, &BipartiteOutput)>,
    ) -> Result<Tensor<2>, GcnError> {
        let m = &self.mesh;
        let mut x = elu(m.encoder.forward(features, graph)?, 1.0);
        for (l, conv) in m.convs.iter().enumerate() {
            if let Some((input, out)) = bipartite {
                let xb = input.to_mesh.apply(out.features[l].clone())?;
                x = x.clone() + input.mask.clone() * (xb - x) * 0.5;
            }
            x = elu(conv.forward(x, graph)?, 1.0);
        }
        m.decode(x, graph)
    }
}
