//! `librplus train`'s arguments (SR-GCN and V2S).

use super::{LibrOpts, ScheduleArg, TrainMethod, ValidationArg};
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub(crate) struct TrainArgs {
    /// Dataset directory (from `librplus generate`).
    #[arg(long)]
    pub(crate) data: PathBuf,
    /// An augmented model (`physics.json`) for every geometry: the network learns the residual
    /// of LIBR with these effects (its inputs and the refit use it), and LIBR+ applies it only to
    /// a LIBR with the same physics (recorded as `physics_hash` in the provenance)
    #[arg(long, value_name = "FILE")]
    pub(crate) physics: Option<PathBuf>,
    /// random, geo-def, logo:GEOMETRY or pattern-v.
    #[arg(long, default_value = "pattern-v")]
    pub(crate) split: String,
    /// Model directory to write.
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Use every k-th block of five scenarios (train and test).
    #[arg(long, default_value_t = 2)]
    pub(crate) every: usize,
    /// Seed (split, initialisation, sample order).
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// Stage-2 epochs at most.
    #[arg(long, default_value_t = 12)]
    pub(crate) epochs: usize,
    /// Stage-1 (bipartite branch) epochs.
    #[arg(long, default_value_t = 2)]
    pub(crate) epochs_bipartite: usize,
    /// Initial Adam learning rate.
    #[arg(long, default_value_t = 2e-3)]
    pub(crate) lr: f64,
    /// Feature width.
    #[arg(long, default_value_t = 32)]
    pub(crate) width: usize,
    /// Convoluters per branch (N_c; the mesh branch's at full resolution).
    #[arg(long, default_value_t = 1)]
    pub(crate) convs: usize,
    /// Spline kernel size per dimension.
    #[arg(long, default_value_t = 3)]
    pub(crate) kernel_size: usize,
    /// Level the mesh branch runs at: 0 the full mesh (as the paper), 1 the first cluster level
    /// (inputs pooled, the correction interpolated back to every node).
    #[arg(long, default_value_t = 1)]
    pub(crate) resolution: usize,
    /// Coarse levels of the mesh branch's U-Net below `--resolution` (0: single resolution).
    #[arg(long, default_value_t = 2)]
    pub(crate) levels: usize,
    /// Nodes per cluster from one U-Net level to the next.
    #[arg(long, default_value_t = 8)]
    pub(crate) pool_ratio: usize,
    /// Clusters of the first cluster level whatever the mesh's resolution, so coarse and fine
    /// meshes give the network the same graphs (0: `1/pool_ratio` of the nodes).
    #[arg(long, default_value_t = 1024)]
    pub(crate) clusters: usize,
    /// Spline convolutions per coarse level on the way down.
    #[arg(long, default_value_t = 3)]
    pub(crate) coarse_convs: usize,
    /// Nearest LIBR-deformed vertices per measured point (N_top).
    #[arg(long, default_value_t = 4)]
    pub(crate) n_top: usize,
    /// Weight λ of the sparse-measurement loss.
    #[arg(long)]
    pub(crate) sparse_weight: Option<f64>,
    /// The paper's Table 2 setting 1-6 (inputs and losses; 6 = the full model).
    #[arg(long, default_value_t = 6)]
    pub(crate) ablation: u32,
    /// Add the measured-misfit input channels to the mesh branch (not in the paper).
    #[arg(long)]
    pub(crate) misfit_input: bool,
    /// Add the surface input channels to the mesh branch: a boundary flag and the outward
    /// normal of each node, from the preoperative mesh (not in the paper)
    #[arg(long)]
    pub(crate) surface_input: bool,
    /// Add the loads LIBR's displacement implies (K·u of the preoperative mesh's linear
    /// stiffness, 3 channels) to the mesh branch (not in the paper)
    #[arg(long)]
    pub(crate) load_input: bool,
    /// DIAGNOSTIC, not a registration setting: link each measured point to its nearest
    /// ground-truth vertices, as the LIBR+ paper did (a leak: surgery has no ground truth). The
    /// training and test figures then show what that leak buys; the model cannot register.
    #[arg(long)]
    pub(crate) diagnostic_truth_neighbours: bool,
    /// Plain convolutions in the mesh branch instead of residual blocks (as format-2 models).
    #[arg(long)]
    pub(crate) no_residual: bool,
    /// Stage 2 stops before an epoch that would end past this many minutes.
    #[arg(long, default_value_t = 25.0)]
    pub(crate) max_minutes: f64,
    /// Stage 2 stops after this many epochs in a row without a better validation error (the
    /// learning rate halves at each; plateau schedule only)
    #[arg(long, default_value_t = 3)]
    pub(crate) patience: usize,
    /// Stage-2 learning-rate schedule: `cosine` anneals it from `--lr` to 0 over `--epochs` or
    /// `--max-minutes`, whichever ends first, and keeps the best epoch; `plateau` (before
    /// session 10) halves it when validation stalls and stops after `--patience` stalls
    #[arg(long, value_enum, default_value_t = ScheduleArg::Cosine)]
    pub(crate) schedule: ScheduleArg,
    /// Train on the raw correction instead of through LIBR+'s refit (by default, with the refit
    /// on and a residual target, the node loss scores what the refit, linearised at each
    /// scenario's LIBR solution, makes of the correction)
    #[arg(long)]
    pub(crate) no_refit_loss: bool,
    /// Validate and keep an exponential moving average of the stage-2 weights over this many
    /// epochs instead of the weights themselves (0: off)
    #[arg(long, default_value_t = 0.0)]
    pub(crate) average_epochs: f64,
    /// L2 penalty on the mesh branch's weights (stage 2), added to the gradients before Adam
    /// (0: none)
    #[arg(long, default_value_t = 0.0)]
    pub(crate) weight_decay: f64,
    /// Jitter the normalised position inputs (preoperative and LIBR-deformed coordinates,
    /// bipartite features) of every training step by a random affine map of this strength
    /// (rotation, shear, scaling and translation up to about this fraction of the liver's RMS
    /// radius; 0: none). Validation and inference are never jittered
    #[arg(long, default_value_t = 0.0)]
    pub(crate) position_jitter: f64,
    /// What validation (early stopping, the correction scale) holds out of the training
    /// scenarios: `deformations` (about one in ten whole deformations; on the random split a
    /// tenth of the blocks) or `geometry` (one whole training liver, judging generalisation to
    /// a new shape as the leave-one-geometry-out and pattern-V tests do; needs 3 training
    /// livers)
    #[arg(long, value_enum, default_value_t = ValidationArg::Deformations)]
    pub(crate) validation: ValidationArg,
    /// Start from this model's weights and network (its model.json replaces the network
    /// options); with `--epochs 0 --epochs-bipartite 0` the model is only validated, its
    /// correction scale fitted again and tested
    #[arg(long)]
    pub(crate) init: Option<PathBuf>,
    /// What to train: `srgcn` (LIBR+'s residual network) or `v2s` (the paper's data-driven
    /// baseline, a 3-D U-Net on a grid supervised by the true displacement alone; it uses
    /// --epochs, --patience, --max-minutes, --seed, --split, --every and the --v2s-* options)
    #[arg(long, value_enum, default_value_t = TrainMethod::Srgcn)]
    pub(crate) method: TrainMethod,
    /// V2S: grid points per axis (the paper: 64; a multiple of 2^--v2s-depth; 16 trains 7× as
    /// many epochs as 32 in the same time on a CPU)
    #[arg(long, default_value_t = 16)]
    pub(crate) grid: usize,
    /// V2S: channels at full resolution (doubled at each level down)
    #[arg(long, default_value_t = 8)]
    pub(crate) v2s_width: usize,
    /// V2S: down-sampling steps of the U-Net
    #[arg(long, default_value_t = 2)]
    pub(crate) v2s_depth: usize,
    /// V2S: 3³ convolutions per level on each side of the U
    #[arg(long, default_value_t = 2)]
    pub(crate) v2s_convs: usize,
    /// V2S: initial Adam learning rate (annealed by --schedule)
    #[arg(long, default_value_t = 3e-3)]
    pub(crate) v2s_lr: f64,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}
