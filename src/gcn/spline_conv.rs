//! The spline convolution layer (SplineCNN) in burn, with `pytorch_spline_conv` semantics:
//!
//! `out_i = agg_{e=(i←j)} x_j · Σ_s basis[e,s] · W[weight_index[e,s]] + x_i · W_root + b`,
//!
//! where edges are `edge_index[0] = i` (target, where messages are summed) and
//! `edge_index[1] = j` (source, whose features are gathered), and `agg` is a sum or a mean over
//! the in-degree clamped at 1. The graph-dependent part (basis, weight indices, gather/scatter
//! indices, in-degrees) is precomputed once per graph on the host as a [`SplineGraph`]; every index
//! in it is validated before it reaches burn's `select`/`select_assign`.
//!
//! Implementation: the (edge, basis function) pairs form a constant sparse matrix `A` `[N·K, N]`
//! (row `i·K + k`, column `j`, value `basis[e,s]`), so `z = A · x` holds
//! `z[i, k, :] = Σ basis[e,s] · x_j` per node and kernel weight; then one matmul with the weight
//! reshaped to `[K·in, out]` applies all kernel weights at once. `A · x` is the differentiable
//! sparse product of [`super::sparse`] (backward `Aᵀ · dz`); burn's generic `select` and
//! `select_assign` did the same 5–10× slower on a 9,000-node mesh. The weight product is
//! [`super::sparse::weight_product`], burn's matmul with a backward pass that writes the large
//! `dz` without burn-flex's extra copy.

use burn::config::Config;
use burn::module::{Initializer, Module, Param};
use burn::tensor::{Device, Tensor, TensorData};

use super::sparse::{Csr, SparseOp};
use super::spline::{SplineKernel, spline_basis};
use super::{GcnError, check_edges};

/// How messages arriving at a node are combined.
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum Aggregation {
    /// Sum of the messages.
    Sum,
    /// Sum divided by the in-degree clamped at 1 (`norm=True` in `pytorch_spline_conv`).
    Mean,
}

/// Configuration of a [`SplineConv`] layer.
#[derive(Config, Debug)]
pub struct SplineConvConfig {
    /// Input feature channels.
    pub in_channels: usize,
    /// Output feature channels.
    pub out_channels: usize,
    /// Kernel size per pseudo-coordinate dimension (its length is the dimension).
    pub kernel_size: Vec<usize>,
    /// Open (`true`) or closed (`false`) B-spline per dimension.
    pub is_open: Vec<bool>,
    /// B-spline degree, 1–3.
    #[config(default = 1)]
    pub degree: usize,
    /// Message aggregation.
    #[config(default = "Aggregation::Mean")]
    pub aggregation: Aggregation,
    /// Whether to add `x · W_root`.
    #[config(default = true)]
    pub root_weight: bool,
    /// Whether to add a bias.
    #[config(default = true)]
    pub bias: bool,
}

/// A spline convolution layer; build it with [`SplineConvConfig::init`].
#[derive(Module, Debug)]
pub struct SplineConv {
    /// Kernel weights `[K, in, out]`, `K = Π kernel_size`.
    pub weight: Param<Tensor<3>>,
    /// Root weight `[in, out]`, if enabled.
    pub root: Option<Param<Tensor<2>>>,
    /// Bias `[out]`, if enabled.
    pub bias: Option<Param<Tensor<1>>>,
    /// Kernel size per dimension.
    #[module(skip)]
    pub kernel_size: Vec<usize>,
    /// Open flag per dimension.
    #[module(skip)]
    pub is_open: Vec<bool>,
    /// B-spline degree.
    #[module(skip)]
    pub degree: usize,
    /// Message aggregation.
    #[module(skip)]
    pub aggregation: Aggregation,
}

impl SplineConvConfig {
    /// The validated spline kernel of this configuration.
    pub fn kernel(&self) -> Result<SplineKernel, GcnError> {
        SplineKernel::new(self.kernel_size.clone(), self.is_open.clone(), self.degree)
    }

    /// Initialises a layer as PyG does: weight and root weight uniform in `±1/√(in·K)` and
    /// `±1/√in`, bias zero. Errors on an invalid kernel or zero channels.
    pub fn init(&self, device: &Device) -> Result<SplineConv, GcnError> {
        let kernel = self.kernel()?;
        if self.in_channels == 0 || self.out_channels == 0 {
            return Err(GcnError::Invalid("channels must be positive".into()));
        }
        let k = kernel.num_weights();
        let (cin, cout) = (self.in_channels, self.out_channels);
        let bound = 1.0 / ((cin * k) as f64).sqrt();
        let weight = Initializer::Uniform {
            min: -bound,
            max: bound,
        }
        .init([k, cin, cout], device);
        let root_bound = 1.0 / (cin as f64).sqrt();
        let root = self.root_weight.then(|| {
            Initializer::Uniform {
                min: -root_bound,
                max: root_bound,
            }
            .init([cin, cout], device)
        });
        let bias = self.bias.then(|| Initializer::Zeros.init([cout], device));
        Ok(SplineConv {
            weight,
            root,
            bias,
            kernel_size: kernel.kernel_size,
            is_open: kernel.is_open,
            degree: kernel.degree,
            aggregation: self.aggregation,
        })
    }
}

/// A graph prepared for spline convolution with one kernel: validated indices and the B-spline
/// basis as tensors on a device. Build once per graph and kernel, reuse across layers and passes.
#[derive(Debug, Clone)]
pub struct SplineGraph {
    /// Number of nodes `N`.
    pub num_nodes: usize,
    /// Number of edges `E`.
    pub num_edges: usize,
    /// The kernel the basis was computed for.
    pub kernel: SplineKernel,
    /// The basis-weighted adjacency `A` `[N·K, N]`: row `target · K + weight_index`, column
    /// `source`, value the basis function's value (duplicates summed).
    op: SparseOp,
    /// `1 / max(in-degree, 1)` per node, `[N, 1]`.
    inv_degree: Tensor<2>,
}

impl SplineGraph {
    /// Prepares a graph: `targets`/`sources` are `edge_index[0]`/`edge_index[1]`, `pseudo` the
    /// row-major `E × D` pseudo-coordinates in `[0, 1]`. Errors on out-of-range node indices,
    /// mismatched lengths or invalid pseudo-coordinates.
    pub fn new(
        num_nodes: usize,
        targets: &[usize],
        sources: &[usize],
        pseudo: &[f64],
        kernel: &SplineKernel,
        device: &Device,
    ) -> Result<Self, GcnError> {
        check_edges(num_nodes, targets, sources)?;
        let e = targets.len();
        if pseudo.len() != e * kernel.dim() {
            return Err(GcnError::Invalid(format!(
                "pseudo has {} values, expected {e} edges × {} dimensions",
                pseudo.len(),
                kernel.dim()
            )));
        }
        let b = spline_basis(pseudo, kernel)?;
        let s = b.num_basis;
        let k = kernel.num_weights();
        if num_nodes
            .checked_mul(k)
            .is_none_or(|v| i32::try_from(v).is_err())
        {
            return Err(GcnError::Invalid(
                "num_nodes × K overflows the index type".into(),
            ));
        }
        let mut triplets = Vec::with_capacity(e * s);
        for edge in 0..e {
            for j in 0..s {
                triplets.push((
                    targets[edge] * k + b.weight_index[edge * s + j],
                    sources[edge],
                    b.basis[edge * s + j] as f32,
                ));
            }
        }
        let op = SparseOp::new(Csr::from_triplets(num_nodes * k, num_nodes, &triplets)?);
        let mut degree = vec![0usize; num_nodes];
        for &t in targets {
            degree[t] += 1;
        }
        let inv: Vec<f32> = degree.iter().map(|&d| 1.0 / d.max(1) as f32).collect();
        Ok(Self {
            num_nodes,
            num_edges: e,
            kernel: kernel.clone(),
            op,
            inv_degree: Tensor::from_data(TensorData::new(inv, [num_nodes, 1]), device),
        })
    }
}

impl SplineGraph {
    /// Prepares a [`super::Graph`] (its edges and pseudo-coordinates) for a kernel.
    pub fn from_graph(
        g: &super::Graph,
        kernel: &SplineKernel,
        device: &Device,
    ) -> Result<Self, GcnError> {
        Self::new(
            g.num_nodes,
            &g.targets,
            &g.sources,
            &g.pseudo,
            kernel,
            device,
        )
    }
}

impl SplineConv {
    /// A layer with given parameters (e.g. from a reference implementation): `weight`
    /// `[K, in, out]`, `root` `[in, out]`, `bias` `[out]`; their presence overrides the config's
    /// `root_weight`/`bias` flags. Errors on shapes that do not match the config.
    pub fn from_tensors(
        config: &SplineConvConfig,
        weight: Tensor<3>,
        root: Option<Tensor<2>>,
        bias: Option<Tensor<1>>,
    ) -> Result<Self, GcnError> {
        let kernel = config.kernel()?;
        let (k, cin, cout) = (
            kernel.num_weights(),
            config.in_channels,
            config.out_channels,
        );
        if weight.dims() != [k, cin, cout] {
            return Err(GcnError::Invalid(format!(
                "weight has shape {:?}, expected [{k}, {cin}, {cout}]",
                weight.dims()
            )));
        }
        if let Some(r) = &root
            && r.dims() != [cin, cout]
        {
            return Err(GcnError::Invalid(format!(
                "root weight has shape {:?}, expected [{cin}, {cout}]",
                r.dims()
            )));
        }
        if let Some(b) = &bias
            && b.dims() != [cout]
        {
            return Err(GcnError::Invalid(format!(
                "bias has shape {:?}, expected [{cout}]",
                b.dims()
            )));
        }
        Ok(Self {
            weight: Param::from_tensor(weight),
            root: root.map(Param::from_tensor),
            bias: bias.map(Param::from_tensor),
            kernel_size: kernel.kernel_size,
            is_open: kernel.is_open,
            degree: kernel.degree,
            aggregation: config.aggregation,
        })
    }

    /// The kernel of this layer.
    pub fn kernel(&self) -> SplineKernel {
        SplineKernel {
            kernel_size: self.kernel_size.clone(),
            is_open: self.is_open.clone(),
            degree: self.degree,
        }
    }

    /// Applies the convolution.
    ///
    /// # Shapes
    /// - `x`: `[N, in]` node features (N = `graph.num_nodes`)
    /// - `graph`: prepared with this layer's kernel (`E` edges, `S = (degree+1)^D` basis
    ///   functions per edge, `K = Π kernel_size` weights)
    /// - returns `[N, out]`
    ///
    /// Internally: `z = A · x` `[N·K, in]` (the basis-weighted adjacency), viewed as `[N, K·in]`,
    /// times the weight `[K·in, out]`.
    ///
    /// Errors when `x` or the graph does not match the layer.
    pub fn forward(&self, x: Tensor<2>, graph: &SplineGraph) -> Result<Tensor<2>, GcnError> {
        let [k, cin, cout] = self.weight.dims();
        let [n, xc] = x.dims();
        if xc != cin {
            return Err(GcnError::Invalid(format!(
                "x has {xc} channels, layer expects {cin}"
            )));
        }
        if n != graph.num_nodes {
            return Err(GcnError::Invalid(format!(
                "x has {n} rows, graph has {} nodes",
                graph.num_nodes
            )));
        }
        if graph.kernel != self.kernel() {
            return Err(GcnError::Invalid(
                "graph was prepared for a different spline kernel".into(),
            ));
        }
        let device = x.device();
        let mut out = if graph.num_edges > 0 {
            let z = graph.op.apply(x.clone())?;
            let agg = super::sparse::weight_product(
                z.reshape([n, k * cin]),
                self.weight.val().reshape([k * cin, cout]),
            );
            match self.aggregation {
                Aggregation::Sum => agg,
                Aggregation::Mean => agg * graph.inv_degree.clone(),
            }
        } else {
            Tensor::<2>::zeros([n, cout], &device)
        };
        if let Some(root) = &self.root {
            out = out + x.matmul(root.val());
        }
        if let Some(bias) = &self.bias {
            out = out + bias.val().unsqueeze_dim::<2>(0);
        }
        Ok(out)
    }
}
