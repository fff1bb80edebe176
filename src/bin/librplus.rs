//! `librplus`: the command-line entry point. Thin: parses arguments, calls the library, prints.

#[global_allocator]
static ALLOCATOR: librplus::GlobalAllocator = librplus::GlobalAllocator;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use librplus::fem::{self, LameField, sag};
use librplus::mesh::io::{self, DataArray, MeshFile, Unit, WriteOptions};
use librplus::mesh::{TetMesh, TriSurface, quality};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(Parser)]
#[command(
    name = "librplus",
    version,
    about = "LIBR+ intraoperative liver registration"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Where SR-GCN training and inference compute: cpu, or (in a build with the `gpu` or
    /// `vulkan` feature) gpu or gpu:N. wICP, LIBR and the FEM always run on the CPU.
    #[arg(long, global = true, default_value = "cpu")]
    device: String,
}

#[derive(Subcommand)]
enum Command {
    /// Inspect and convert meshes.
    #[command(subcommand)]
    Mesh(MeshCmd),
    /// Finite-element reference problems.
    #[command(subcommand)]
    Fem(FemCmd),
    /// Whole-pipeline benchmarks with stage timings.
    #[command(subcommand)]
    Bench(BenchCmd),
    /// Generates a dataset: liver phantoms, ground-truth deformations and sparse scenarios
    /// (format in the README; deterministic for a seed, resumable, shardable).
    Generate(GenerateArgs),
    /// Liver phantoms: what the ground truth contains that the linear model lacks.
    #[command(subcommand)]
    Phantom(PhantomCmd),
    /// Registers one dataset scenario (rigid wICP, or wICP then LIBR) and reports its TRE.
    Register(RegisterArgs),
    /// Evaluates methods over a dataset split: summary.json, report.md, per-scenario results.
    Evaluate(EvaluateArgs),
    /// Trains SR-GCN (LIBR+) on a dataset split, then tests LIBR and LIBR+ on the held-out
    /// scenarios: MODEL_DIR/model.json + weights.bin (+ provenance), training.json, test.json,
    /// loss curves (PNG).
    Train(TrainArgs),
    /// Runs the paper's experiments in one go: `train` on every split (random, geometry-
    /// deformation hold-out, each leave-one-geometry-out, pattern V) and the Table 2 ablations,
    /// then writes OUT/RESULTS.md (tables), OUT/results.json and OUT/ratios.png.
    Experiments(ExperimentsArgs),
    /// Makes an ensemble directory from trained model directories: LIBR+ with it averages the
    /// members' corrections (README, "SR-GCN ensemble directory"). Usable wherever `--model` is.
    Ensemble(EnsembleArgs),
}

#[derive(Args)]
struct EnsembleArgs {
    /// The new ensemble directory (must not exist, or be empty).
    #[arg(long)]
    out: PathBuf,
    /// Model directories (from `librplus train`); an ensemble directory adds its members.
    #[arg(required = true)]
    models: Vec<PathBuf>,
}

#[derive(Args)]
struct ExperimentsArgs {
    /// Dataset directory (from `librplus generate`).
    #[arg(long)]
    data: PathBuf,
    /// Output directory: one model directory per run under `runs/`, and the reports.
    #[arg(long)]
    out: PathBuf,
    /// Splits, comma-separated: random, geo-def, logo (every geometry), logo:G, pattern-v.
    #[arg(long, default_value = "random,geo-def,logo,pattern-v")]
    splits: String,
    /// Table 2 settings to run on `--ablation-split` (comma-separated, 1-6; empty: none).
    #[arg(long, default_value = "1,2,3,4,5,6")]
    ablations: String,
    /// The split the ablations run on (the paper: random).
    #[arg(long, default_value = "random")]
    ablation_split: String,
    /// Use every k-th block of five scenarios, in every run.
    #[arg(long, default_value_t = 16)]
    every: usize,
    /// Training time limit per run (minutes; stage 2 stops before an epoch would pass it).
    #[arg(long, default_value_t = 6.0)]
    minutes: f64,
    /// Seed of every run.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// More `librplus train` options for every run, as one string (e.g. "--width 48").
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    train_args: String,
    /// Keep runs whose directory already has test.json (resume an interrupted campaign).
    #[arg(long)]
    resume: bool,
}

#[derive(Parser)]
struct TrainOnly {
    #[command(flatten)]
    args: TrainArgs,
}

#[derive(Args)]
struct TrainArgs {
    #[command(flatten)]
    libr: LibrOpts,
    /// Dataset directory (from `librplus generate`).
    #[arg(long)]
    data: PathBuf,
    /// random, geo-def, logo:GEOMETRY or pattern-v.
    #[arg(long, default_value = "pattern-v")]
    split: String,
    /// Model directory to write.
    #[arg(long)]
    out: PathBuf,
    /// Use every k-th block of five scenarios (train and test).
    #[arg(long, default_value_t = 2)]
    every: usize,
    /// Seed (split, initialisation, sample order).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Stage-2 epochs at most.
    #[arg(long, default_value_t = 12)]
    epochs: usize,
    /// Stage-1 (bipartite branch) epochs.
    #[arg(long, default_value_t = 2)]
    epochs_bipartite: usize,
    /// Initial Adam learning rate.
    #[arg(long, default_value_t = 2e-3)]
    lr: f64,
    /// Feature width.
    #[arg(long, default_value_t = 32)]
    width: usize,
    /// Convoluters per branch (N_c; the mesh branch's at full resolution).
    #[arg(long, default_value_t = 1)]
    convs: usize,
    /// Spline kernel size per dimension.
    #[arg(long, default_value_t = 3)]
    kernel_size: usize,
    /// Level the mesh branch runs at: 0 the full mesh (as the paper), 1 the first cluster level
    /// (inputs pooled, the correction interpolated back to every node).
    #[arg(long, default_value_t = 1)]
    resolution: usize,
    /// Coarse levels of the mesh branch's U-Net below `--resolution` (0: single resolution).
    #[arg(long, default_value_t = 2)]
    levels: usize,
    /// Nodes per cluster from one U-Net level to the next.
    #[arg(long, default_value_t = 8)]
    pool_ratio: usize,
    /// Clusters of the first cluster level whatever the mesh's resolution, so coarse and fine
    /// meshes give the network the same graphs (0: `1/pool_ratio` of the nodes).
    #[arg(long, default_value_t = 1024)]
    clusters: usize,
    /// Spline convolutions per coarse level on the way down.
    #[arg(long, default_value_t = 3)]
    coarse_convs: usize,
    /// Nearest LIBR-deformed vertices per measured point (N_top).
    #[arg(long, default_value_t = 4)]
    n_top: usize,
    /// Weight λ of the sparse-measurement loss.
    #[arg(long)]
    sparse_weight: Option<f64>,
    /// The paper's Table 2 setting 1-6 (inputs and losses; 6 = the full model).
    #[arg(long, default_value_t = 6)]
    ablation: u32,
    /// Add the measured-misfit input channels to the mesh branch (not in the paper).
    #[arg(long)]
    misfit_input: bool,
    /// Add the surface input channels to the mesh branch: a boundary flag and the outward
    /// normal of each node, from the preoperative mesh (not in the paper)
    #[arg(long)]
    surface_input: bool,
    /// Add the loads LIBR's displacement implies (K·u of the preoperative mesh's linear
    /// stiffness, 3 channels) to the mesh branch (not in the paper)
    #[arg(long)]
    load_input: bool,
    /// DIAGNOSTIC, not a registration setting: link each measured point to its nearest
    /// ground-truth vertices, as the LIBR+ paper did (a leak: surgery has no ground truth). The
    /// training and test figures then show what that leak buys; the model cannot register.
    #[arg(long)]
    diagnostic_truth_neighbours: bool,
    /// Plain convolutions in the mesh branch instead of residual blocks (as format-2 models).
    #[arg(long)]
    no_residual: bool,
    /// Stage 2 stops before an epoch that would end past this many minutes.
    #[arg(long, default_value_t = 25.0)]
    max_minutes: f64,
    /// Stage 2 stops after this many epochs in a row without a better validation error (the
    /// learning rate halves at each; plateau schedule only)
    #[arg(long, default_value_t = 3)]
    patience: usize,
    /// Stage-2 learning-rate schedule: `cosine` anneals it from `--lr` to 0 over `--epochs` or
    /// `--max-minutes`, whichever ends first, and keeps the best epoch; `plateau` (before
    /// session 10) halves it when validation stalls and stops after `--patience` stalls
    #[arg(long, value_enum, default_value_t = ScheduleArg::Cosine)]
    schedule: ScheduleArg,
    /// Train on the raw correction instead of through LIBR+'s refit (by default, with the refit
    /// on and a residual target, the node loss scores what the refit, linearised at each
    /// scenario's LIBR solution, makes of the correction)
    #[arg(long)]
    no_refit_loss: bool,
    /// Validate and keep an exponential moving average of the stage-2 weights over this many
    /// epochs instead of the weights themselves (0: off)
    #[arg(long, default_value_t = 0.0)]
    average_epochs: f64,
    /// L2 penalty on the mesh branch's weights (stage 2), added to the gradients before Adam
    /// (0: none)
    #[arg(long, default_value_t = 0.0)]
    weight_decay: f64,
    /// Jitter the normalised position inputs (preoperative and LIBR-deformed coordinates,
    /// bipartite features) of every training step by a random affine map of this strength
    /// (rotation, shear, scaling and translation up to about this fraction of the liver's RMS
    /// radius; 0: none). Validation and inference are never jittered
    #[arg(long, default_value_t = 0.0)]
    position_jitter: f64,
    /// What validation (early stopping, the correction scale) holds out of the training
    /// scenarios: `deformations` (about one in ten whole deformations; on the random split a
    /// tenth of the blocks) or `geometry` (one whole training liver, judging generalisation to
    /// a new shape as the leave-one-geometry-out and pattern-V tests do; needs 3 training
    /// livers)
    #[arg(long, value_enum, default_value_t = ValidationArg::Deformations)]
    validation: ValidationArg,
    /// Start from this model's weights and network (its model.json replaces the network
    /// options); with `--epochs 0 --epochs-bipartite 0` the model is only validated, its
    /// correction scale fitted again and tested
    #[arg(long)]
    init: Option<PathBuf>,
}

/// LIBR options shared by `register` and `evaluate`.
#[derive(Args, Clone)]
struct LibrOpts {
    /// LIBR strain-energy regularization λ (dimensionless; default 1e-3).
    #[arg(long)]
    lambda: Option<f64>,
    /// Most LIBR iterations (default 20).
    #[arg(long)]
    iterations: Option<usize>,
    /// LIBR control points (default 25; changes the cached basis).
    #[arg(long)]
    control_points: Option<usize>,
    /// Width σ of each control point's load, as a multiple of the control-point spacing
    /// (default 1.25; changes the cached basis).
    #[arg(long)]
    load_width: Option<f64>,
    /// LIBR+ only: most LIBR iterations of the data-consistency refit after the SR-GCN
    /// correction (default 5; 0: none)
    #[arg(long)]
    refit_iterations: Option<usize>,
    /// The rigid stage (wICP) registers the anterior-surface points alone, as Clements et al.
    /// and the LIBR+ paper's wICP baseline do; ultrasound points are then used by LIBR only
    #[arg(long)]
    wicp_surface_only: bool,
}

impl LibrOpts {
    fn params(&self) -> librplus::register::pipeline::PipelineParams {
        let mut p = librplus::register::pipeline::PipelineParams::default();
        if let Some(l) = self.lambda {
            p.libr.regularization = l;
        }
        if let Some(i) = self.iterations {
            p.libr.max_iterations = i;
        }
        if let Some(k) = self.control_points {
            p.libr.control_points = k;
        }
        if let Some(w) = self.load_width {
            p.libr.load_width = librplus::register::libr::LoadWidth::Spacing(w);
        }
        if let Some(k) = self.refit_iterations {
            p.refit_iterations = k;
        }
        p.wicp.surface_only = self.wicp_surface_only;
        p
    }
}

#[derive(Args)]
struct EvaluateArgs {
    #[command(flatten)]
    libr: LibrOpts,
    /// Dataset directory.
    #[arg(long)]
    data: PathBuf,
    /// Comma-separated methods: rigid, libr, librplus (--model, or the built-in model).
    #[arg(long, default_value = "rigid,libr")]
    methods: String,
    /// A trained SR-GCN model directory (from `librplus train`), or an ensemble directory (from
    /// `librplus ensemble`): evaluates LIBR+ and restricts every method to the model's held-out
    /// test scenarios (an ensemble: those every member held out; its split replaces --split).
    #[arg(long)]
    model: Option<PathBuf>,
    /// Comma-separated splits: all, train, test (the held-out geometry with pattern V).
    #[arg(long, default_value = "all")]
    split: String,
    /// Evaluate every k-th scenario of each deformation.
    #[arg(long, default_value_t = 1)]
    every: usize,
    /// Report directory (summary.json, report.md, results.json, PNG plots, error_maps/).
    #[arg(long)]
    out: PathBuf,
    /// Print summary.json on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct RegisterArgs {
    #[command(flatten)]
    libr: LibrOpts,
    /// Dataset directory (from `librplus generate`), with --scenario.
    #[arg(long, requires = "scenario", required_unless_present = "preop")]
    data: Option<PathBuf>,
    /// Scenario: `DEFORMATION/INDEX`, e.g. `g1-L-00/3`.
    #[arg(long, requires = "data")]
    scenario: Option<String>,
    /// Your own preoperative liver instead of a dataset: a tet mesh (.vtu .vtk .msh; labelled
    /// from its `region`/`falciform`/`inferior_ridge` point arrays when present, else from its
    /// geometry, LPS frame) or a closed surface (.obj .stl .vtp .vtk), meshed at --edge-mm.
    #[arg(long, conflicts_with_all = ["data", "scenario"], requires = "surface")]
    preop: Option<PathBuf>,
    /// With --preop: anterior-surface points (physical frame; .vtp .vtk .csv .txt .xyz).
    #[arg(long)]
    surface: Option<PathBuf>,
    /// With --preop: ultrasound posterior-contour points (repeatable, one file per plane or all).
    #[arg(long)]
    ultrasound: Vec<PathBuf>,
    /// With --preop: ultrasound vessel-feature points (repeatable).
    #[arg(long)]
    vessel_points: Vec<PathBuf>,
    /// With --preop: the navigation system's coarse alignment image → physical, a JSON file
    /// `{"rotation": [[r00, r01, r02], [r10, ...], [...]], "translation": [tx, ty, tz]}` (in --unit);
    /// default identity (points already near the preoperative model).
    #[arg(long)]
    initial_alignment: Option<PathBuf>,
    /// With --preop: length unit of the mesh and point files (mm, cm or m).
    #[arg(long, default_value = "mm")]
    unit: Unit,
    /// With --preop and a surface file: tet edge length (mm).
    #[arg(long, default_value_t = 7.6)]
    edge_mm: f64,
    /// rigid (wICP), libr (wICP then LIBR) or librplus (then the SR-GCN correction).
    #[arg(long, default_value = "libr")]
    method: MethodArg,
    /// SR-GCN model directory (from `librplus train`) or ensemble directory (from `librplus
    /// ensemble`) for --method librplus (default: the built-in model).
    #[arg(long)]
    model: Option<PathBuf>,
    /// Write the preoperative mesh with the registered `displacement` (image frame) and the
    /// per-node `error_mm` against the ground truth (.vtu).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Where the LIBR basis is cached (default DATA/cache).
    #[arg(long)]
    cache: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct BenchRegisterArgs {
    #[command(flatten)]
    libr: LibrOpts,
    /// Dataset directory (from `librplus generate`). Default: the `small` preset (seed 1)
    /// generated from --surface into a temporary directory, so the benchmark runs anywhere.
    #[arg(long)]
    data: Option<PathBuf>,
    /// A tet mesh instead of a dataset: only the LIBR basis preload is measured (a bare mesh has
    /// no anatomical labels, so no correspondence and no registrations).
    #[arg(long, conflicts_with_all = ["data", "geometry"])]
    mesh: Option<PathBuf>,
    /// Closed liver surface for the default dataset.
    #[arg(long, default_value = "../shared/data/sofa_liver.vtk")]
    surface: PathBuf,
    /// Geometry id of the dataset (default: the first).
    #[arg(long)]
    geometry: Option<String>,
    /// Registrations to time, taken evenly across the five measurement categories.
    #[arg(long, default_value_t = 50)]
    scenarios: usize,
    /// Threads of the pool the registrations run in, one after another (1: single-registration
    /// latency on one core, the surgical metric). The preload uses every core.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// rigid (wICP), libr (wICP then LIBR) or librplus (then the SR-GCN correction).
    #[arg(long, default_value = "libr")]
    method: MethodArg,
    /// SR-GCN model or ensemble directory for --method librplus (default: the built-in model).
    #[arg(long)]
    model: Option<PathBuf>,
    #[command(flatten)]
    common: Common,
}

/// `train --validation`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum ValidationArg {
    Deformations,
    Geometry,
}

impl ValidationArg {
    fn get(self) -> librplus::gcn::train::Validation {
        match self {
            ValidationArg::Deformations => librplus::gcn::train::Validation::Deformations,
            ValidationArg::Geometry => librplus::gcn::train::Validation::Geometry,
        }
    }
}

/// `train --schedule`.
#[derive(Clone, Copy, clap::ValueEnum)]
enum ScheduleArg {
    Plateau,
    Cosine,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum MethodArg {
    /// Salient-feature weighted rigid ICP.
    Rigid,
    /// wICP, then LIBR.
    Libr,
    /// wICP, LIBR, then the SR-GCN correction (--model, or the built-in model).
    Librplus,
}

#[derive(Subcommand)]
enum PhantomCmd {
    /// For each pattern and seed: the gap between the ground truth and the linear homogeneous
    /// model under the same loads and supports, and what contributes (heterogeneity, nonlinear
    /// material and geometry, unilateral bed contact; gravity vs the pattern's own load).
    Effect {
        /// Closed liver surface (LPS). Default: ../shared/data/sofa_liver.vtk (largest piece).
        #[arg(long)]
        surface: Option<PathBuf>,
        /// Mesher target edge (mm).
        #[arg(long, default_value_t = 12.0)]
        edge_mm: f64,
        /// Seeds: first..=last draws of loads and tissue.
        #[arg(long, default_value_t = 1)]
        first_seed: u64,
        /// Number of seeds.
        #[arg(long, default_value_t = 10)]
        seeds: u64,
        #[command(flatten)]
        common: Common,
    },
}

#[derive(Args)]
struct GenerateArgs {
    /// small (CI-sized: 2 coarse geometries, 3 deformations, 10 scenarios each) or paper (3 training
    /// geometries × L, R, W plus a 4th with V, 700 scenarios each, ~9,000-node meshes).
    #[arg(long, default_value = "small")]
    preset: PresetArg,
    /// Output directory (created; an interrupted run resumes into it).
    #[arg(long)]
    out: PathBuf,
    /// Master seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Do the i-th of N shares of the deformations (`--shard 0/4`); run once more without
    /// `--shard` (it skips finished work) to write the complete manifest.
    #[arg(long)]
    shard: Option<String>,
    /// Closed liver surface(s) in LPS (repeatable); geometries cycle through them, then through
    /// seeded shape variants. Default: ../shared/data/sofa_liver.vtk (largest component).
    #[arg(long)]
    surface: Vec<PathBuf>,
    /// Override: number of geometries (the last one is the held-out V geometry).
    #[arg(long)]
    geometries: Option<usize>,
    /// Override: deformations per geometry and pattern.
    #[arg(long)]
    deformations: Option<usize>,
    /// Override: scenarios per deformation.
    #[arg(long)]
    scenarios: Option<usize>,
    /// Override: the patterns of the training geometries, comma-separated from L, R, W (the
    /// paper's, the default), X (random packs anywhere on the surface: a training augmentation,
    /// not in the paper) and V (a diagnostic: the held-out geometry's pattern seen in training, so
    /// that pattern-v measures an unseen liver alone). The held-out geometry keeps V only.
    #[arg(long, value_delimiter = ',')]
    patterns: Vec<String>,
    /// Override: mesher target edge length (mm).
    #[arg(long)]
    edge_mm: Option<f64>,
    /// Ground-truth physics: nonlinear (heterogeneous Neo-Hookean with unilateral bed contact) or
    /// linear (the linear homogeneous model LIBR assumes, same loads: a control dataset).
    #[arg(long, value_enum, default_value = "nonlinear")]
    truth: TruthArg,
    /// The five scenarios of each block (one per category) share the surface patch, noise,
    /// misalignment and landmarks and differ only in their ultrasound planes, so the categories
    /// are compared on the same draws (off by default: every scenario is drawn on its own).
    #[arg(long)]
    paired_categories: bool,
    #[command(flatten)]
    common: Common,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum TruthArg {
    /// Heterogeneous compressible Neo-Hookean, unilateral bed contact.
    Nonlinear,
    /// Linear homogeneous elasticity, bilateral bed springs.
    Linear,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum PresetArg {
    /// CI-sized.
    Small,
    /// The paper's design.
    Paper,
}

#[derive(Args, Clone)]
struct Common {
    /// Length unit of input files (mm, cm or m); meshes are held in millimetres.
    #[arg(long, default_value = "mm")]
    unit: Unit,
    /// Print one JSON object on stdout instead of human-readable text.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
enum MeshCmd {
    /// Counts, volume, quality, components and bounding box of a mesh or surface file.
    Info {
        /// Mesh file (.vtu .vtp .vtk .msh .obj .stl).
        file: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Converts between formats (by extension); output in millimetres.
    Convert {
        /// Input file.
        input: PathBuf,
        /// Output file (.vtu .vtp .vtk .msh .obj .stl); a tet mesh written to a surface format
        /// writes its boundary.
        output: PathBuf,
        #[command(flatten)]
        common: Common,
        /// Write ASCII instead of binary where the format has both.
        #[arg(long)]
        ascii: bool,
    },
    /// Tetrahedralizes a closed surface (isosurface stuffing on a BCC lattice).
    Tetra {
        /// Closed triangle surface (.obj .stl .vtk .vtp .vtu; a tet mesh is re-meshed from its
        /// boundary).
        surface: PathBuf,
        /// Target edge length in mm.
        #[arg(long)]
        edge_mm: f64,
        /// Output tet mesh (.vtu .vtk .msh).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        common: Common,
        /// Keep every face-connected piece (default: the largest only).
        #[arg(long)]
        all_pieces: bool,
    },
}

#[derive(Subcommand)]
enum FemCmd {
    /// Gravity sag: E = 5 kPa, ν = 0.45, 0.0104 mN/mm³ along +y, top 20% of the y-range fixed.
    Sag {
        /// Tetrahedral mesh file.
        #[arg(long)]
        mesh: PathBuf,
        #[command(flatten)]
        common: Common,
        /// Write the mesh with `displacement` (mm) and `fixed` point data (.vtu, .vtk, ...).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Material model: linear elasticity, or compressible Neo-Hookean (same E, ν; also
        /// reports its difference from the linear solution).
        #[arg(long, default_value = "linear")]
        model: ModelArg,
        /// Multiplies the body force (e.g. 3 for a stronger load to show nonlinearity).
        #[arg(long, default_value_t = 1.0)]
        load_scale: f64,
    },
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum ModelArg {
    /// Linear elasticity.
    Linear,
    /// Compressible Neo-Hookean, total Lagrangian, Newton with line search and load stepping.
    NeoHookean,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum OrderingArg {
    /// Geometric nested dissection.
    Nd,
    /// Approximate minimum degree.
    Amd,
}

impl From<OrderingArg> for fem::Ordering {
    fn from(o: OrderingArg) -> Self {
        match o {
            OrderingArg::Nd => fem::Ordering::NestedDissection,
            OrderingArg::Amd => fem::Ordering::Amd,
        }
    }
}

#[derive(Subcommand)]
enum BenchCmd {
    /// Whole registration pipeline: the case preload (LIBR basis built cold, then read from its
    /// cache) and single-registration latency with stage timings over scenarios spread across
    /// the measurement categories.
    Register(BenchRegisterArgs),
    /// A spline-convolution stack on the graph of `../shared/bench/splineconv_peer.py` (random
    /// points, symmetric kNN, Cartesian pseudo-coordinates; layers 6 → hidden … → 3): inference
    /// and one training step, medians in ms, as the peer prints them.
    Gcn {
        /// Nodes.
        #[arg(long, default_value_t = 9000)]
        nodes: usize,
        /// Target mean in-degree.
        #[arg(long, default_value_t = 14)]
        avg_degree: usize,
        /// Kernel size per dimension (3-D).
        #[arg(long, default_value_t = 5)]
        kernel: usize,
        /// Hidden width.
        #[arg(long, default_value_t = 64)]
        hidden: usize,
        /// Layers.
        #[arg(long, default_value_t = 4)]
        layers: usize,
        /// Threads (rayon pool).
        #[arg(long, default_value_t = 2)]
        threads: usize,
        /// Seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Untimed repetitions.
        #[arg(long, default_value_t = 2)]
        warmup: usize,
        /// Timed repetitions.
        #[arg(long, default_value_t = 10)]
        repeats: usize,
    },
    /// LIBR preload workload: assemble, factorize once, solve `rhs` unit-load right-hand sides.
    Basis {
        /// Tetrahedral mesh file.
        #[arg(long)]
        mesh: PathBuf,
        #[command(flatten)]
        common: Common,
        /// Number of right-hand sides.
        #[arg(long, default_value_t = 300)]
        rhs: usize,
        /// Repetitions; medians are reported.
        #[arg(long, default_value_t = 1)]
        repeat: usize,
        /// Seed for the random load positions.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Fill-reducing ordering: nd (geometric nested dissection) or amd.
        #[arg(long, default_value = "nd")]
        ordering: OrderingArg,
    },
}

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let device: librplus::gcn::device::ComputeDevice = cli
        .device
        .parse()
        .map_err(|e: String| anyhow::anyhow!("--device: {e}"))?;
    librplus::gcn::device::select(device).map_err(|e| anyhow::anyhow!("--device: {e}"))?;
    match cli.command {
        Command::Mesh(MeshCmd::Info { file, common }) => mesh_info(&file, &common),
        Command::Mesh(MeshCmd::Convert {
            input,
            output,
            common,
            ascii,
        }) => mesh_convert(&input, &output, &common, ascii),
        Command::Mesh(MeshCmd::Tetra {
            surface,
            edge_mm,
            out,
            common,
            all_pieces,
        }) => mesh_tetra(&surface, edge_mm, &out, &common, all_pieces),
        Command::Fem(FemCmd::Sag {
            mesh,
            common,
            out,
            model,
            load_scale,
        }) => fem_sag(&mesh, &common, out.as_deref(), model, load_scale),
        Command::Bench(BenchCmd::Basis {
            mesh,
            common,
            rhs,
            repeat,
            seed,
            ordering,
        }) => bench_basis(&mesh, &common, rhs, repeat, seed, ordering.into()),
        Command::Bench(BenchCmd::Register(args)) => bench_register(&args),
        Command::Bench(BenchCmd::Gcn {
            nodes,
            avg_degree,
            kernel,
            hidden,
            layers,
            threads,
            seed,
            warmup,
            repeats,
        }) => (|| -> Result<()> {
            let b = librplus::gcn::bench::StackBench {
                nodes,
                avg_degree,
                kernel,
                hidden,
                layers,
                seed,
                warmup,
                repeats,
            };
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads.max(1))
                .build()
                .context("building the thread pool")?;
            let t = pool
                .install(|| librplus::gcn::bench::run(&b))
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            let mut v = serde_json::to_value(&t)?;
            v["impl"] = json!(match librplus::gcn::device::chosen() {
                librplus::gcn::device::ComputeDevice::Cpu =>
                    "librplus (burn 0.22.1 flex, CSR sparse product)".to_string(),
                d => format!("librplus (burn 0.22.1 on {d}, gather/scatter-add product)"),
            });
            v["nodes"] = json!(nodes);
            v["hidden"] = json!(hidden);
            v["layers"] = json!(layers);
            v["kernel"] = json!(kernel);
            v["threads"] = json!(threads);
            v["repeats"] = json!(repeats);
            println!("{v}");
            Ok(())
        })(),
        Command::Generate(args) => generate(&args),
        Command::Register(args) if args.preop.is_some() => register_files(&args),
        Command::Register(args) => register_scenario(&args),
        Command::Evaluate(args) => evaluate(&args),
        Command::Train(args) => train(&args).map(|_| ()),
        Command::Experiments(args) => experiments(&args),
        Command::Ensemble(args) => ensemble(&args),
        Command::Phantom(PhantomCmd::Effect {
            surface,
            edge_mm,
            first_seed,
            seeds,
            common,
        }) => phantom_effect(surface.as_deref(), edge_mm, first_seed, seeds, &common),
    }
}

/// Reads a surface file's triangles, or a tet mesh file's outward boundary, as a surface.
fn read_surface(path: &Path, unit: Unit) -> Result<TriSurface> {
    let file = read_file(path, unit)?;
    let triangles = if !file.triangles.is_empty() {
        file.triangles.clone()
    } else if !file.tets.is_empty() {
        let mut m = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
        m.orient_positive();
        m.boundary()
            .with_context(|| path.display().to_string())?
            .triangles
    } else {
        bail!("{}: has no triangles or tetrahedra to mesh", path.display());
    };
    TriSurface::new(file.nodes, triangles).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// Reads a closed surface for meshing: its triangles (or a tet mesh's boundary), the largest
/// connected piece, oriented outward.
fn load_closed_surface(path: &Path, unit: Unit) -> Result<TriSurface> {
    let mut surface = read_surface(path, unit)?.largest_component();
    let stats = surface.stats();
    if !stats.closed {
        bail!(
            "{}: the surface (largest piece) is not closed; a liver surface must enclose a volume",
            path.display()
        );
    }
    if surface.signed_volume() < 0.0 {
        surface.flip();
    }
    Ok(surface)
}

fn ensemble(a: &EnsembleArgs) -> Result<()> {
    let command: Vec<String> = std::env::args().collect();
    let names = librplus::gcn::io::make_ensemble(
        &a.out,
        &a.models,
        json!({ "command": command.join(" ") }),
    )
    .map_err(anyhow::Error::msg)?;
    let models = librplus::gcn::io::load_models_on_device(&a.out).map_err(anyhow::Error::msg)?;
    println!("{}: ensemble of {} networks", a.out.display(), names.len());
    for (name, m) in names.iter().zip(&models) {
        let p = &m.provenance;
        println!(
            "  {name}: split {}, correction scale {}, test LIBR {} → LIBR+ {} mm",
            p["split"].as_str().unwrap_or("?"),
            m.config.correction_scale,
            p["metrics"]["test_libr_tre_mm"]
                .as_f64()
                .map_or("?".into(), |x| format!("{x:.3}")),
            p["metrics"]["test_librplus_tre_mm"]
                .as_f64()
                .map_or("?".into(), |x| format!("{x:.3}")),
        );
    }
    Ok(())
}

fn evaluate(a: &EvaluateArgs) -> Result<()> {
    use librplus::eval::report::{self, Split};
    use librplus::register::pipeline::Method;
    let m = librplus::eval::open(&a.data).map_err(anyhow::Error::msg)?;
    let mut want_plus = false;
    let mut methods = Vec::new();
    for x in a.methods.split(',') {
        match x.trim() {
            "rigid" => methods.push(Method::Rigid),
            "libr" => methods.push(Method::Libr),
            "librplus" => want_plus = true,
            other => bail!("--methods: unknown method {other:?} (rigid, libr, librplus)"),
        }
    }
    let model = match (&a.model, want_plus) {
        (Some(dir), _) => Some(shared_models(
            librplus::gcn::io::load_models_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
        )),
        (None, true) => Some(shared_models(
            librplus::gcn::io::builtin_models()
                .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?,
        )),
        (None, false) => None,
    };
    if model.is_some() && !methods.contains(&Method::Libr) {
        // LIBR+ corrects LIBR's result: LIBR runs (and is reported) with it.
        methods.push(Method::Libr);
    }
    // With a model: its held-out scenarios, under its split's name; with an ensemble, the
    // scenarios every member held out.
    let model_test = match &model {
        Some(members) => {
            let mut names = Vec::new();
            let mut common: Option<std::collections::BTreeSet<(String, usize)>> = None;
            for mm in members {
                let p = &mm.provenance;
                let split = p["split"].as_str().unwrap_or("");
                let sp = librplus::gcn::train::TrainSplit::parse(split)
                    .map_err(|e| anyhow::anyhow!("--model provenance: {e}"))?;
                let seed = p["seed"].as_u64().unwrap_or(1);
                let every = p["every"].as_u64().unwrap_or(1) as usize;
                // The test set does not depend on how the model was validated.
                let sets = librplus::gcn::train::split_scenarios(
                    &m,
                    &sp,
                    seed,
                    every,
                    librplus::gcn::train::Validation::Deformations,
                )
                .map_err(|e| anyhow::anyhow!("--model split on this dataset: {e}"))?;
                let test: std::collections::BTreeSet<_> = sets.test.into_iter().collect();
                common = Some(match common {
                    None => test,
                    Some(c) => c.intersection(&test).cloned().collect(),
                });
                if !names.contains(&sp.name()) {
                    names.push(sp.name());
                }
            }
            Some((names.join("+"), common.unwrap_or_default()))
        }
        None => None,
    };
    let splits = match &model_test {
        Some(_) => vec![Split::All],
        None => a
            .split
            .split(',')
            .map(|s| Split::parse(s.trim()).map_err(|e| anyhow::anyhow!("--split: {e}")))
            .collect::<Result<Vec<_>>>()?,
    };
    std::fs::create_dir_all(&a.out).with_context(|| a.out.display().to_string())?;
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    let mut summaries = std::collections::BTreeMap::new();
    let mut all_results = serde_json::Map::new();
    let mut plots = serde_json::Map::new();
    let mut error_maps = serde_json::Map::new();
    for split in splits {
        let bar = indicatif::ProgressBar::new(0).with_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} split {msg} [{bar:30}] {pos}/{len} registrations, {elapsed} (eta {eta})",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        let name: String = match &model_test {
            Some((n, _)) => n.clone(),
            None => split.name().to_string(),
        };
        let name = name.as_str();
        bar.set_message(name.to_string());
        let progress = |done: usize, total: usize| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        };
        let plus = model.as_ref().map(|mm| report::LibrPlusEval {
            models: mm,
            only: model_test.as_ref().map(|t| &t.1),
        });
        let results = report::evaluate(
            &a.data, &m, split, &methods, a.every, &params, plus, &progress,
        );
        bar.finish_and_clear();
        let ev = results.map_err(anyhow::Error::msg)?;
        let mut split_plots = Vec::new();
        for (file, png) in [
            (
                format!("tre_by_category_{name}.png"),
                librplus::eval::plot::tre_by_category_png(name, &ev.results),
            ),
            (
                format!("tre_cdf_{name}.png"),
                librplus::eval::plot::tre_cdf_png(name, &ev.results),
            ),
        ] {
            let png = png.map_err(|e| anyhow::anyhow!("plot {file}: {e}"))?;
            let path = a.out.join(&file);
            std::fs::write(&path, png).with_context(|| path.display().to_string())?;
            split_plots.push(file);
        }
        let dir = a.out.join("error_maps").join(name);
        std::fs::create_dir_all(&dir).with_context(|| dir.display().to_string())?;
        let mut split_maps = Vec::new();
        for map in &ev.error_maps {
            if map.scenarios == 0 {
                continue;
            }
            let mesh = &ev.meshes[&map.geometry];
            let file = format!("error_maps/{name}/{}_{}.vtu", map.geometry, map.method);
            let f = map.to_file(mesh).map_err(anyhow::Error::msg)?;
            io::write(a.out.join(&file), &f, WriteOptions::default())?;
            let mean = map.mean_mm();
            split_maps.push(json!({
                "file": file,
                "geometry": map.geometry,
                "method": map.method,
                "scenarios": map.scenarios,
                "nodes": mean.len(),
                "tre_mm": mean.iter().sum::<f64>() / mean.len().max(1) as f64,
            }));
        }
        plots.insert(name.to_string(), json!(split_plots));
        error_maps.insert(name.to_string(), Value::Array(split_maps));
        summaries.insert(name.to_string(), report::summarize(&ev.results));
        all_results.insert(name.to_string(), serde_json::to_value(&ev.results)?);
    }
    let summary = json!({
        "format": 1,
        "data": a.data.display().to_string(),
        "every": a.every,
        "splits": summaries.iter().map(|(k, v)| (k.clone(), json!({"methods": v}))).collect::<serde_json::Map<_, _>>(),
        "plots": plots,
        "error_maps": error_maps,
    });
    std::fs::write(
        a.out.join("summary.json"),
        serde_json::to_string_pretty(&summary)? + "\n",
    )?;
    std::fs::write(
        a.out.join("results.json"),
        serde_json::to_string_pretty(&Value::Object(all_results))? + "\n",
    )?;
    std::fs::write(a.out.join("report.md"), report::markdown(&summaries))?;
    if a.json {
        println!("{summary}");
    } else {
        print!("{}", report::markdown(&summaries));
        println!(
            "\nwritten: {}/summary.json, report.md, results.json, tre_by_category_SPLIT.png, tre_cdf_SPLIT.png, error_maps/SPLIT/GEOMETRY_METHOD.vtu",
            a.out.display()
        );
    }
    Ok(())
}

/// The method of `register` and the model it needs, loaded.
fn register_method(
    a: &RegisterArgs,
) -> Result<(
    librplus::register::pipeline::Method,
    Option<Vec<std::sync::Arc<librplus::gcn::io::TrainedModel>>>,
)> {
    use librplus::register::pipeline::Method;
    let method = match a.method {
        MethodArg::Rigid => Method::Rigid,
        MethodArg::Libr => Method::Libr,
        MethodArg::Librplus => Method::LibrPlus,
    };
    let model = match (&a.model, method) {
        (Some(dir), Method::LibrPlus) => Some(shared_models(
            librplus::gcn::io::load_models_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
        )),
        (None, Method::LibrPlus) => Some(shared_models(
            librplus::gcn::io::builtin_models()
                .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?,
        )),
        (Some(_), _) => bail!("--model is only used with --method librplus"),
        (None, _) => None,
    };
    Ok((method, model))
}

fn registration_json(r: &librplus::register::pipeline::Registration) -> Value {
    let libr = r.libr.as_ref();
    json!({
        "rigid": {
            "rms_mm": r.rigid.rms_mm,
            "iterations": r.rigid.iterations,
            "matched": r.rigid.matched,
            "trimmed": r.rigid.trimmed,
            "degenerate": r.rigid.degenerate,
            "seconds": r.rigid.seconds,
        },
        "libr": libr.map(|i| json!({
            "iterations": i.iterations,
            "converged": i.converged,
            "rms_mm": i.rms_mm,
            "matching_s": i.matching_s,
            "assemble_s": i.assemble_s,
            "solve_s": i.solve_s,
            "total_s": i.total_s,
        })),
        "correction": r.correction.as_ref().map(|c| json!({
            "applied": c.applied,
            "skipped": c.skipped,
            "seconds": c.seconds,
            "network_seconds": c.network_seconds,
            "refit": c.refit.as_ref().map(|i| json!({
                "iterations": i.iterations,
                "rms_mm": i.rms_mm,
                "total_s": i.total_s,
            })),
            "refit_error": c.refit_error,
        })),
    })
}

/// The case of a `register` run: the LIBR basis unless rigid (cached in `cache`), and the SR-GCN
/// when given.
fn prepare_case(
    preop: librplus::register::PreopModel,
    method: librplus::register::pipeline::Method,
    params: &librplus::register::pipeline::PipelineParams,
    cache: &Path,
    gcn: Option<Vec<std::sync::Arc<librplus::gcn::io::TrainedModel>>>,
) -> std::result::Result<librplus::register::pipeline::Prepared, String> {
    use librplus::register::pipeline::{Method, Prepared};
    let case = Prepared::new(
        preop,
        (method != Method::Rigid).then_some(&params.libr),
        Some(cache),
    )?;
    match gcn {
        Some(m) => case.with_models(m),
        None => Ok(case),
    }
}

/// Models (one, or an ensemble's members) shared between cases.
fn shared_models(
    models: Vec<librplus::gcn::io::TrainedModel>,
) -> Vec<std::sync::Arc<librplus::gcn::io::TrainedModel>> {
    models.into_iter().map(std::sync::Arc::new).collect()
}

/// `register --preop`: a user's own mesh and point files.
fn register_files(a: &RegisterArgs) -> Result<()> {
    use librplus::register::pipeline::register;
    use librplus::register::{MeasuredKind, Measurements};
    let preop = a.preop.as_ref().context("--preop")?;
    let (method, model) = register_method(a)?;
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    let t0 = Instant::now();
    let bar = indicatif::ProgressBar::new_spinner()
        .with_message("reading and preparing the preoperative model");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let file = io::read(preop, a.unit).with_context(|| format!("--preop {}", preop.display()));
    let model_r = file.and_then(|f| {
        librplus::input::preop_model_from_mesh(preop, &f, a.unit, a.edge_mm)
            .map_err(anyhow::Error::msg)
    });
    let mut meas = Measurements {
        points: Vec::new(),
        kind: Vec::new(),
        feature: Vec::new(),
        initial_alignment: None,
    };
    let mut add = |path: &Path, kind: MeasuredKind, flag: &str| -> Result<()> {
        let p = librplus::input::read_points(path, a.unit)
            .map_err(|e| anyhow::anyhow!("--{flag}: {e}"))?;
        meas.kind.extend(std::iter::repeat_n(kind, p.len()));
        meas.points.extend(p);
        Ok(())
    };
    let surface = a.surface.as_ref().context("--preop needs --surface")?;
    add(surface, MeasuredKind::Surface, "surface")?;
    for p in &a.ultrasound {
        add(p, MeasuredKind::PosteriorContour, "ultrasound")?;
    }
    for p in &a.vessel_points {
        add(p, MeasuredKind::Vessel, "vessel-points")?;
    }
    if let Some(p) = &a.initial_alignment {
        let text = std::fs::read_to_string(p)
            .with_context(|| format!("--initial-alignment {}", p.display()))?;
        let mut t: librplus::mesh::rigid::Rigid = serde_json::from_str(&text)
            .with_context(|| format!("--initial-alignment {}: expected {{\"rotation\": [[3×3]], \"translation\": [3]}}", p.display()))?;
        t.translation = t.translation.map(|x| x * a.unit.to_mm());
        meas.initial_alignment = Some(t);
    }
    let model_pre = model_r?;
    let cache = preop.parent().unwrap_or(Path::new(".")).join("cache");
    let case = prepare_case(model_pre, method, &params, &cache, model);
    bar.finish_and_clear();
    let case = case.map_err(anyhow::Error::msg)?;
    let prepare_s = t0.elapsed().as_secs_f64();
    let r = register(&case, &meas, method, &params).map_err(anyhow::Error::msg)?;
    if let Some(out) = &a.out {
        let nodes = case.model.mesh.nodes();
        let deformed: Vec<f64> = nodes
            .iter()
            .enumerate()
            .flat_map(|(i, x)| {
                r.image_to_physical
                    .apply([0, 1, 2].map(|k| x[k] + r.u[3 * i + k]))
            })
            .collect();
        let f = librplus::eval::error_map_file(
            &case.model.mesh,
            vec![
                DataArray::new("displacement", 3, r.u.clone()),
                DataArray::new("position_physical_mm", 3, deformed),
            ],
        );
        io::write(out, &f, WriteOptions::default())?;
    }
    let mut out = json!({
        "preop": preop.display().to_string(),
        "nodes": case.model.mesh.num_nodes(),
        "method": method.name(),
        "points": meas.points.len(),
        "image_to_physical": r.image_to_physical,
        "max_displacement_mm": r.u.chunks_exact(3).map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()).fold(0.0, f64::max),
        "basis_from_cache": case.basis_from_cache,
        "prepare_s": prepare_s,
        "register_s": r.seconds,
        "out": a.out.as_ref().map(|p| p.display().to_string()),
    });
    if let (Value::Object(o), Value::Object(extra)) = (&mut out, registration_json(&r)) {
        o.extend(extra);
    }
    emit(a.json, &out);
    Ok(())
}

fn register_scenario(a: &RegisterArgs) -> Result<()> {
    use librplus::register::pipeline::register;
    let data = a.data.as_ref().context("--data")?;
    let scenario = a.scenario.as_deref().context("--scenario")?;
    let m = librplus::eval::open(data).map_err(anyhow::Error::msg)?;
    let (def_id, index) = scenario.rsplit_once('/').with_context(|| {
        format!(
            "--scenario {:?}: expected DEFORMATION/INDEX, e.g. g1-L-00/3",
            scenario
        )
    })?;
    let index: usize = index
        .parse()
        .with_context(|| format!("--scenario {:?}: index is not a number", scenario))?;
    let d = m
        .deformations
        .iter()
        .find(|d| d.id == def_id)
        .with_context(|| {
            format!(
                "--scenario {:?}: no deformation {def_id:?} in {} (have: {})",
                scenario,
                data.display(),
                m.deformations
                    .iter()
                    .map(|d| d.id.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })?;
    if index >= d.scenarios.len() {
        bail!(
            "--scenario {:?}: deformation {def_id} has {} scenarios (0..{})",
            scenario,
            d.scenarios.len(),
            d.scenarios.len()
        );
    }
    let geo = librplus::eval::load_geometry(data, &m, &d.geometry).map_err(anyhow::Error::msg)?;
    let scenarios = librplus::eval::load_scenarios(data, d).map_err(anyhow::Error::msg)?;
    let sc = &scenarios[index];
    let (method, model) = register_method(a)?;
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    let cache = a.cache.clone().unwrap_or_else(|| data.join("cache"));
    let t0 = Instant::now();
    let bar = indicatif::ProgressBar::new_spinner().with_message("preparing the case (LIBR basis)");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let case = prepare_case(geo.model.clone(), method, &params, &cache, model);
    bar.finish_and_clear();
    let case = case.map_err(anyhow::Error::msg)?;
    let prepare_s = t0.elapsed().as_secs_f64();
    let r = register(&case, &sc.measurements, method, &params).map_err(anyhow::Error::msg)?;
    let nodes = geo.model.mesh.nodes();
    let t = librplus::eval::tre(
        nodes,
        (&r.image_to_physical, &r.u),
        (&sc.truth.image_to_physical, &sc.truth.displacement),
        &geo.surface,
        &geo.targets,
    );
    let start = librplus::eval::tre(
        nodes,
        (
            sc.measurements
                .initial_alignment
                .as_ref()
                .expect("datasets carry a start"),
            &vec![0.0; r.u.len()],
        ),
        (&sc.truth.image_to_physical, &sc.truth.displacement),
        &geo.surface,
        &geo.targets,
    );
    if let Some(out) = &a.out {
        let err = librplus::eval::node_errors_mm(
            nodes,
            (&r.image_to_physical, &r.u),
            (&sc.truth.image_to_physical, &sc.truth.displacement),
        );
        let f = librplus::eval::error_map_file(
            &geo.model.mesh,
            vec![
                DataArray::new("displacement", 3, r.u.clone()),
                DataArray::new("error_mm", 1, err),
            ],
        );
        io::write(out, &f, WriteOptions::default())?;
    }
    let mut out = json!({
        "scenario": sc.id,
        "category": sc.category,
        "method": method.name(),
        "points": sc.measurements.points.len(),
        "tre_mm": t.tre_mm,
        "tre_surface_mm": t.tre_surface_mm,
        "tre_interior_mm": t.tre_interior_mm,
        "tre_targets_mm": t.tre_targets_mm,
        "tre_max_mm": t.max_mm,
        "tre_initial_alignment_mm": start.tre_mm,
        "basis_from_cache": case.basis_from_cache,
        "prepare_s": prepare_s,
        "register_s": r.seconds,
    });
    if let (Value::Object(o), Value::Object(extra)) = (&mut out, registration_json(&r)) {
        o.extend(extra);
    }
    emit(a.json, &out);
    Ok(())
}

fn phantom_effect(
    surface: Option<&Path>,
    edge_mm: f64,
    first_seed: u64,
    seeds: u64,
    c: &Common,
) -> Result<()> {
    use librplus::fem::hyperelastic::NewtonParams;
    use librplus::phantom::labels::{LabelParams, label};
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::tissue::{Tissue, TissueParams};
    use librplus::phantom::truth::breakdown;
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    if !(edge_mm.is_finite() && edge_mm > 0.5) || seeds == 0 {
        bail!("need --edge-mm > 0.5 and --seeds ≥ 1");
    }
    let path = surface.map_or_else(
        || PathBuf::from("../shared/data/sofa_liver.vtk"),
        Path::to_path_buf,
    );
    let s = load_closed_surface(&path, c.unit)?;
    let mesh = librplus::mesh::tetra::tetrahedralize(
        &s,
        &librplus::mesh::tetra::TetraParams::with_edge(edge_mm),
    )
    .with_context(|| path.display().to_string())?;
    let labels = label(&mesh, &LabelParams::default()).map_err(anyhow::Error::msg)?;
    let tree = VesselTree::grow(&mesh, &VesselParams::default()).map_err(anyhow::Error::msg)?;
    let tp = TissueParams::default();
    let pp = PatternParams::default();
    let bar = indicatif::ProgressBar::new(4 * seeds).with_message("ground truth and breakdowns");
    let mut rows = Vec::new();
    for seed in first_seed..first_seed + seeds {
        let tissue = Tissue::build(&mesh, &tree, &tp, seed).map_err(anyhow::Error::msg)?;
        let lame = tissue.lame_field();
        for pattern in [Pattern::L, Pattern::R, Pattern::W, Pattern::V, Pattern::X] {
            let case = load_case(&mesh, &labels, pattern, &pp, seed).map_err(anyhow::Error::msg)?;
            let b = breakdown(
                &mesh,
                &lame,
                &tp.parenchyma,
                &case,
                &NewtonParams::default(),
            );
            bar.inc(1);
            match b {
                Ok(b) => rows.push((pattern, seed, b)),
                Err(e) => eprintln!("{pattern:?} seed {seed}: did not converge ({e}); skipped"),
            }
        }
    }
    bar.finish_and_clear();
    let mut per = serde_json::Map::new();
    for pattern in [Pattern::L, Pattern::R, Pattern::W, Pattern::V, Pattern::X] {
        let r: Vec<_> = rows
            .iter()
            .filter(|r| r.0 == pattern)
            .map(|r| &r.2)
            .collect();
        if r.is_empty() {
            continue;
        }
        let n = r.len() as f64;
        let avg = |f: &dyn Fn(&librplus::phantom::truth::Breakdown) -> f64| {
            r.iter().map(|b| f(b)).sum::<f64>() / n
        };
        let gaps: Vec<f64> = r.iter().map(|b| b.gap_mm).collect();
        per.insert(
            format!("{pattern:?}"),
            json!({
                "draws": r.len(),
                "mean_displacement_mm": avg(&|b| b.truth_mean_mm),
                "max_displacement_mm": r.iter().map(|b| b.truth_max_mm).fold(0.0, f64::max),
                "gap_mm_mean": avg(&|b| b.gap_mm),
                "gap_mm_min": gaps.iter().copied().fold(f64::INFINITY, f64::min),
                "gap_mm_max": gaps.iter().copied().fold(0.0, f64::max),
                "step_heterogeneity_mm": avg(&|b| b.steps[0].mean_mm),
                "step_nonlinearity_mm": avg(&|b| b.steps[1].mean_mm),
                "step_unilateral_bed_mm": avg(&|b| b.steps[2].mean_mm),
                "gap_gravity_only_mm": avg(&|b| b.by_load[0].mean_mm),
                "gap_pattern_load_only_mm": avg(&|b| b.by_load[1].mean_mm),
            }),
        );
    }
    let out = json!({
        "surface": path.display().to_string(),
        "nodes": mesh.num_nodes(),
        "seeds": format!("{first_seed}..={}", first_seed + seeds - 1),
        "per_pattern": Value::Object(per),
        "draws": rows.iter().map(|(p, s, b)| json!({"pattern": format!("{p:?}"), "seed": s, "breakdown": b})).collect::<Vec<_>>(),
    });
    if c.json {
        println!("{out}");
    } else {
        println!(
            "{} nodes, seeds {}",
            mesh.num_nodes(),
            out["seeds"].as_str().unwrap_or("")
        );
        println!(
            "pattern  mean(mm)  gap mean [min, max]   heterog.  nonlin.  unilat.  | gravity-only  pattern-only"
        );
        for (p, v) in out["per_pattern"].as_object().into_iter().flatten() {
            let f = |k: &str| v[k].as_f64().unwrap_or(f64::NAN);
            println!(
                "{p:7}  {:8.1}  {:5.2} [{:5.2}, {:5.2}]  {:8.2}  {:7.2}  {:7.2}  | {:12.2}  {:12.2}",
                f("mean_displacement_mm"),
                f("gap_mm_mean"),
                f("gap_mm_min"),
                f("gap_mm_max"),
                f("step_heterogeneity_mm"),
                f("step_nonlinearity_mm"),
                f("step_unilateral_bed_mm"),
                f("gap_gravity_only_mm"),
                f("gap_pattern_load_only_mm"),
            );
        }
    }
    Ok(())
}

/// The training patterns named by `generate --patterns`, each once.
fn train_patterns(names: &[String]) -> Result<Vec<librplus::phantom::patterns::Pattern>> {
    use librplus::phantom::patterns::Pattern;
    let mut out = Vec::new();
    for name in names {
        let p = match name.trim() {
            "L" | "l" => Pattern::L,
            "R" | "r" => Pattern::R,
            "W" | "w" => Pattern::W,
            "X" | "x" => Pattern::X,
            "V" | "v" => Pattern::V,
            other => bail!("--patterns: unknown pattern {other:?} (have L, R, W, X, V)"),
        };
        if out.contains(&p) {
            bail!("--patterns: {name} is named twice");
        }
        out.push(p);
    }
    Ok(out)
}

fn generate(a: &GenerateArgs) -> Result<()> {
    use librplus::phantom::dataset::{GenerateConfig, Preset};
    let shard = match &a.shard {
        None => (0, 1),
        Some(s) => {
            let (i, n) = s
                .split_once('/')
                .with_context(|| format!("--shard {s:?}: expected i/N, e.g. 0/4"))?;
            let (i, n): (usize, usize) = (
                i.trim()
                    .parse()
                    .with_context(|| format!("--shard {s:?}: i is not a number"))?,
                n.trim()
                    .parse()
                    .with_context(|| format!("--shard {s:?}: N is not a number"))?,
            );
            if n == 0 || i >= n {
                bail!("--shard {s:?}: need 0 ≤ i < N");
            }
            (i, n)
        }
    };
    let paths = if a.surface.is_empty() {
        vec![PathBuf::from("../shared/data/sofa_liver.vtk")]
    } else {
        a.surface.clone()
    };
    let mut surfaces = Vec::new();
    for p in &paths {
        surfaces.push(
            load_closed_surface(p, a.common.unit)
                .with_context(|| format!("--surface {}", p.display()))?,
        );
    }
    let sources = paths
        .iter()
        .map(|p| {
            p.file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_else(|| p.display().to_string())
        })
        .collect();
    let preset = match a.preset {
        PresetArg::Small => Preset::Small,
        PresetArg::Paper => Preset::Paper,
    };
    let mut config = GenerateConfig::preset(preset, a.seed, sources);
    if let Some(g) = a.geometries {
        if g == 0 {
            bail!("--geometries must be at least 1");
        }
        config.geometries = g;
    }
    if let Some(d) = a.deformations {
        config.deformations_per_pattern = d;
    }
    if !a.patterns.is_empty() {
        config.train_patterns = train_patterns(&a.patterns)?;
    }
    config.paired_categories = a.paired_categories;
    config.truth = match a.truth {
        TruthArg::Nonlinear => librplus::phantom::dataset::TruthModel::Nonlinear,
        TruthArg::Linear => librplus::phantom::dataset::TruthModel::LinearHomogeneous,
    };
    if let Some(s) = a.scenarios {
        if s == 0 {
            bail!("--scenarios must be at least 1");
        }
        config.scenarios = s;
    }
    if let Some(h) = a.edge_mm {
        if !(h.is_finite() && h > 0.5) {
            bail!("--edge-mm {h}: must be a length above 0.5 mm");
        }
        config.edge_mm = h;
    }
    std::fs::create_dir_all(&a.out).with_context(|| a.out.display().to_string())?;
    let t0 = Instant::now();
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} {msg} [{bar:30}] {pos}/{len} deformations, {elapsed} (eta {eta})",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.set_message("meshing and labelling geometries");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let progress = |done: usize, total: usize, msg: &str| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(msg.to_string());
    };
    let result = librplus::phantom::dataset::generate(&config, &surfaces, &a.out, shard, &progress);
    bar.finish_and_clear();
    let report = result.map_err(|e| anyhow::anyhow!("{}: {e}", a.out.display()))?;
    let m = report.manifest.as_ref().expect("manifest written");
    let per_pattern: serde_json::Map<String, Value> = ["L", "R", "W", "V", "X"]
        .iter()
        .filter_map(|p| {
            let d: Vec<_> = m.deformations.iter().filter(|d| d.pattern == *p).collect();
            (!d.is_empty()).then(|| {
                let n = d.len() as f64;
                (
                    p.to_string(),
                    json!({
                        "deformations": d.len(),
                        "mean_displacement_mm": d.iter().map(|d| d.mean_displacement_mm).sum::<f64>() / n,
                        "max_displacement_mm": d.iter().map(|d| d.max_displacement_mm).fold(0.0, f64::max),
                        "linear_homogeneous_gap_mm": d.iter().map(|d| d.linear_homogeneous_gap_mm).sum::<f64>() / n,
                    }),
                )
            })
        })
        .collect();
    let out = json!({
        "out": a.out.display().to_string(),
        "preset": m.preset,
        "seed": m.seed,
        "shard": format!("{}/{}", shard.0, shard.1),
        "geometries": m.geometries.len(),
        "nodes": m.geometries.iter().map(|g| g.nodes).collect::<Vec<_>>(),
        "deformations_written": report.written.len(),
        "deformations_resumed": report.resumed.len(),
        "deformations_missing": m.missing.len(),
        "scenarios": m.deformations.iter().map(|d| d.scenarios.len()).sum::<usize>(),
        "failed_draws": m.failed.len(),
        "complete": m.complete,
        "per_pattern": per_pattern,
        "seconds_per_deformation_median": if report.seconds.is_empty() { 0.0 } else { median(report.seconds.clone()) },
        "total_s": t0.elapsed().as_secs_f64(),
    });
    emit(a.common.json, &out);
    if !report.errors.is_empty() {
        bail!(
            "{} deformation(s) failed every draw: {}",
            report.errors.len(),
            report.errors.join("; ")
        );
    }
    Ok(())
}

/// Prints `value` as JSON, or as `key: value` lines.
fn emit(json: bool, value: &Value) {
    if json {
        println!("{value}");
        return;
    }
    if let Value::Object(map) = value {
        for (k, v) in map {
            match v {
                Value::Object(inner) => {
                    println!("{k}:");
                    for (ik, iv) in inner {
                        println!("  {ik}: {}", human(iv));
                    }
                }
                _ => println!("{k}: {}", human(v)),
            }
        }
    }
}

fn human(v: &Value) -> String {
    match v {
        Value::Number(n) => match n.as_f64() {
            Some(x) if n.is_f64() && x != 0.0 && x.abs() < 1e-3 => format!("{x:.3e}"),
            Some(x) if n.is_f64() => format!("{x:.6}"),
            _ => n.to_string(),
        },
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

fn read_file(path: &Path, unit: Unit) -> Result<MeshFile> {
    Ok(io::read(path, unit)?)
}

/// A volume mesh prepared for FEM, with what was changed on the way.
struct Volume {
    mesh: TetMesh,
    flipped: usize,
    removed_unused: usize,
}

/// Reads a volume mesh for FEM: flips inverted tets (with a note; a warning when orientation is
/// mixed, which often means a tangled mesh), removes nodes no tet uses, rejects degenerate,
/// duplicate and non-manifold tets, naming the file and the tet.
fn load_volume(path: &Path, unit: Unit) -> Result<Volume> {
    let file = read_file(path, unit)?;
    if file.tets.is_empty() {
        bail!(
            "{}: has no tetrahedra ({} triangles): a volume mesh is needed",
            path.display(),
            file.triangles.len()
        );
    }
    let mut mesh = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
    let flipped = mesh.orient_positive();
    if flipped == mesh.num_tets() {
        eprintln!(
            "note: {}: all {flipped} tets were negatively oriented and have been flipped",
            path.display()
        );
    } else if flipped > 0 {
        eprintln!(
            "warning: {}: {flipped} of {} tets were negatively oriented (mixed orientation) and have been flipped; if the mesh is tangled the results are wrong",
            path.display(),
            mesh.num_tets()
        );
    }
    let removed_unused = mesh.num_nodes() - mesh.used_nodes().iter().filter(|&&u| u).count();
    if removed_unused > 0 {
        mesh.remove_unused_nodes();
        eprintln!(
            "note: {}: removed {removed_unused} nodes that no tetrahedron uses (outputs use the remaining {} nodes, in file order)",
            path.display(),
            mesh.num_nodes()
        );
    }
    if let Some(p) = mesh.problems(1).into_iter().next() {
        bail!("{}: {p}", path.display());
    }
    mesh.boundary()
        .with_context(|| path.display().to_string())?;
    Ok(Volume {
        mesh,
        flipped,
        removed_unused,
    })
}

fn bbox_json(lo: [f64; 3], hi: [f64; 3]) -> Value {
    json!({"min": lo, "max": hi, "size": [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]]})
}

fn mesh_info(path: &Path, c: &Common) -> Result<()> {
    let file = read_file(path, c.unit)?;
    let out = if !file.tets.is_empty() {
        let mesh = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
        let problems = mesh.problems(usize::MAX);
        let count =
            |f: fn(&librplus::mesh::MeshError) -> bool| problems.iter().filter(|p| f(p)).count();
        let inverted = count(|p| matches!(p, librplus::mesh::MeshError::InvertedTet { .. }));
        let degenerate = count(|p| matches!(p, librplus::mesh::MeshError::DegenerateTet { .. }));
        let unused = count(|p| matches!(p, librplus::mesh::MeshError::UnusedNode { .. }));
        let mut oriented = mesh.clone();
        oriented.orient_positive();
        // A broken boundary (non-manifold or overlapping tets) is reported, not fatal, here.
        let (st, surface_error) = match oriented.boundary_surface() {
            Ok(surface) => (Some(surface.stats()), None),
            Err(e) => (None, Some(e.to_string())),
        };
        let q = quality::summary(&mesh);
        let (lo, hi) = mesh.bounding_box();
        let st_val = |f: fn(&librplus::mesh::SurfaceStats) -> Value| {
            st.as_ref().map(f).unwrap_or(Value::Null)
        };
        json!({
            "file": path.display().to_string(),
            "kind": "tetrahedral",
            "unit_in": c.unit.to_string(),
            "nodes": mesh.num_nodes(),
            "tets": mesh.num_tets(),
            "surface_triangles": st_val(|s| s.triangles.into()),
            "surface_nodes": st_val(|s| s.vertices.into()),
            "volume_mm3": mesh.tet_volumes().iter().map(|v| v.abs()).sum::<f64>(),
            "signed_volume_mm3": mesh.volume(),
            "min_dihedral_deg": q.min_dihedral_deg,
            "max_dihedral_deg": q.max_dihedral_deg,
            "min_radius_ratio": q.min_radius_ratio,
            "mean_radius_ratio": q.mean_radius_ratio,
            "components": mesh.num_components(),
            "inverted_tets": inverted,
            "degenerate_tets": degenerate,
            "unused_nodes": unused,
            "surface_closed": st_val(|s| s.closed.into()),
            "surface_genus": st_val(|s| s.genus.into()),
            "surface_area_mm2": st_val(|s| s.area_mm2.into()),
            "surface_error": surface_error,
            "other_triangles_in_file": file.triangles.len(),
            "skipped_cells": file.skipped_cells,
            "point_data": file.point_data.iter().map(|a| &a.name).collect::<Vec<_>>(),
            "bbox_mm": bbox_json(lo, hi),
        })
    } else if !file.triangles.is_empty() {
        let s =
            TriSurface::from_file(&file).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let st = s.stats();
        let (lo, hi) = s.bounding_box();
        let largest = s.largest_component().stats();
        json!({
            "file": path.display().to_string(),
            "kind": "surface",
            "unit_in": c.unit.to_string(),
            "nodes": file.nodes.len(),
            "tets": 0,
            "surface_triangles": st.triangles,
            "surface_nodes": st.vertices,
            "volume_mm3": st.signed_volume_mm3.abs(),
            "signed_volume_mm3": st.signed_volume_mm3,
            "orientation": if st.signed_volume_mm3 >= 0.0 { "outward" } else { "inward" },
            "min_dihedral_deg": Value::Null,
            "components": st.components,
            "closed": st.closed,
            "consistently_oriented": st.consistently_oriented,
            "genus": st.genus,
            "area_mm2": st.area_mm2,
            "largest_component": largest,
            "skipped_cells": file.skipped_cells,
            "bbox_mm": bbox_json(lo, hi),
        })
    } else {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &file.nodes {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        json!({
            "file": path.display().to_string(),
            "kind": "points",
            "nodes": file.nodes.len(),
            "tets": 0,
            "surface_triangles": 0,
            "skipped_cells": file.skipped_cells,
            "bbox_mm": bbox_json(lo, hi),
        })
    };
    emit(c.json, &out);
    Ok(())
}

fn mesh_convert(input: &Path, output: &Path, c: &Common, ascii: bool) -> Result<()> {
    let mut file = read_file(input, c.unit)?;
    let surface_out = matches!(
        io::Format::from_path(output)?,
        io::Format::Obj | io::Format::Stl | io::Format::Vtp
    );
    if surface_out && file.triangles.is_empty() && !file.tets.is_empty() {
        let mut mesh = TetMesh::from_file(&file).with_context(|| input.display().to_string())?;
        mesh.orient_positive();
        file.triangles = mesh
            .boundary()
            .with_context(|| input.display().to_string())?
            .triangles;
        file.tets.clear();
        file.cell_data.clear();
    }
    io::write(output, &file, WriteOptions { binary: !ascii })?;
    emit(
        c.json,
        &json!({
            "input": input.display().to_string(),
            "output": output.display().to_string(),
            "nodes": file.nodes.len(),
            "tets": file.tets.len(),
            "triangles": file.triangles.len(),
            "point_data": file.point_data.iter().map(|a| &a.name).collect::<Vec<_>>(),
        }),
    );
    Ok(())
}

fn mesh_tetra(path: &Path, edge_mm: f64, out: &Path, c: &Common, all_pieces: bool) -> Result<()> {
    if matches!(
        io::Format::from_path(out)?,
        io::Format::Obj | io::Format::Stl | io::Format::Vtp
    ) {
        bail!(
            "{}: a surface format cannot hold a tet mesh; use .vtu, .vtk or .msh",
            out.display()
        );
    }
    let surface = read_surface(path, c.unit)?;
    let enclosed = surface.signed_volume().abs();
    let params = librplus::mesh::tetra::TetraParams {
        keep_largest_component: !all_pieces,
        ..librplus::mesh::tetra::TetraParams::with_edge(edge_mm)
    };
    let bar = indicatif::ProgressBar::new_spinner().with_message("isosurface stuffing");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let result = librplus::mesh::tetra::tetrahedralize_with_report(&surface, &params);
    bar.finish_and_clear();
    let (mesh, report) = result.with_context(|| path.display().to_string())?;
    if report.pinched_vertices > 0 {
        eprintln!(
            "warning: {} boundary vertices where the surface touches itself at this edge length; a slightly different --edge-mm usually avoids them",
            report.pinched_vertices
        );
    }
    io::write(out, &mesh.to_file(), WriteOptions::default())?;
    let q = quality::summary(&mesh);
    let volume = mesh.volume();
    emit(
        c.json,
        &json!({
            "surface": path.display().to_string(),
            "out": out.display().to_string(),
            "edge_mm": edge_mm,
            "nodes": mesh.num_nodes(),
            "tets": mesh.num_tets(),
            "volume_mm3": volume,
            "surface_volume_mm3": enclosed,
            "volume_error_percent": 100.0 * (volume - enclosed) / enclosed,
            "min_dihedral_deg": q.min_dihedral_deg,
            "max_dihedral_deg": q.max_dihedral_deg,
            "report": report,
        }),
    );
    Ok(())
}

fn fem_sag(
    path: &Path,
    c: &Common,
    out: Option<&Path>,
    model: ModelArg,
    load_scale: f64,
) -> Result<()> {
    if !load_scale.is_finite() {
        bail!("--load-scale must be finite, got {load_scale}");
    }
    if let Some(out) = out
        && matches!(
            io::Format::from_path(out)?,
            io::Format::Obj | io::Format::Stl | io::Format::Vtp
        )
    {
        bail!(
            "{}: a surface format cannot hold the volume result; use .vtu, .vtk or .msh",
            out.display()
        );
    }
    let t0 = Instant::now();
    let Volume {
        mesh,
        flipped,
        removed_unused,
    } = load_volume(path, c.unit)?;
    let read_s = t0.elapsed().as_secs_f64();
    let mut params = sag::SagParams::default();
    params.body_force = params.body_force.map(|b| b * load_scale);
    let bar = indicatif::ProgressBar::new_spinner().with_message(match model {
        ModelArg::Linear => "solving linear sag",
        ModelArg::NeoHookean => "solving Neo-Hookean sag (Newton, load steps)",
    });
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let r = match model {
        ModelArg::Linear => sag::solve(&mesh, &params)?,
        ModelArg::NeoHookean => {
            sag::solve_neo_hookean(&mesh, &params, &fem::hyperelastic::NewtonParams::default())?
        }
    };
    // The nonlinear result is reported together with its difference from the linear one.
    let vs_linear = if model == ModelArg::NeoHookean {
        let lin = sag::solve(&mesh, &params)?;
        let d: Vec<f64> = r
            .displacement
            .chunks_exact(3)
            .zip(lin.displacement.chunks_exact(3))
            .map(|(a, b)| {
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            })
            .collect();
        Some(json!({
            "linear_max_disp_mm": lin.max_disp_mm,
            "linear_mean_disp_mm": lin.mean_disp_mm,
            "mean_node_difference_mm": d.iter().sum::<f64>() / d.len().max(1) as f64,
            "max_node_difference_mm": d.iter().copied().fold(0.0, f64::max),
        }))
    } else {
        None
    };
    bar.finish_and_clear();
    if let Some(out) = out {
        let fixed = sag::fixed_nodes(&mesh, params.fixed_fraction);
        let mut mask = vec![0.0; mesh.num_nodes()];
        for &n in &fixed {
            mask[n as usize] = 1.0;
        }
        let (l, m) = params.material.lame();
        // Small-strain fields (for Neo-Hookean results these are the linearized measures).
        let fields = fem::post::tet_fields(&mesh, &LameField::Uniform(l, m), &r.displacement);
        let mut file = mesh.to_file();
        file.point_data = vec![
            DataArray::new("displacement", 3, r.displacement.clone()),
            DataArray::new("fixed", 1, mask),
        ];
        if !file.tets.is_empty() {
            file.cell_data = vec![
                DataArray::new(
                    "von_mises_kpa",
                    1,
                    fields.iter().map(|f| f.von_mises_kpa).collect(),
                ),
                DataArray::new(
                    "strain_energy",
                    1,
                    fields.iter().map(|f| f.energy).collect(),
                ),
            ];
        }
        io::write(out, &file, WriteOptions::default())?;
    }
    let out_json = json!({
        "mesh": path.display().to_string(),
        "nodes": mesh.num_nodes(),
        "tets": mesh.num_tets(),
        "flipped_tets": flipped,
        "removed_unused_nodes": removed_unused,
        "fixed_nodes": r.fixed_nodes,
        "model": match model {
            ModelArg::Linear => "linear",
            ModelArg::NeoHookean => "neo-hookean",
        },
        "free_dofs": r.free_dofs,
        "E_kPa": params.material.youngs_modulus_kpa,
        "nu": params.material.poisson_ratio,
        "body_force_mN_per_mm3": params.body_force,
        "newton": r.newton,
        "vs_linear": vs_linear,
        "max_disp_mm": r.max_disp_mm,
        "mean_disp_mm": r.mean_disp_mm,
        "strain_energy": r.strain_energy,
        "applied_load_mN": r.applied_load_mn,
        "reaction_mN": r.reaction_mn,
        "strain_energy_unit": "mN·mm",
        "timings_s": {
            "read": read_s,
            "assemble": r.timings.assemble_s,
            "factor": r.timings.factor_s,
            "solve": r.timings.solve_s,
            "total": t0.elapsed().as_secs_f64(),
        },
        "out": out.map(|p| p.display().to_string()),
    });
    emit(c.json, &out_json);
    Ok(())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n == 0 {
        f64::NAN
    } else if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn bench_basis(
    path: &Path,
    c: &Common,
    rhs: usize,
    repeat: usize,
    seed: u64,
    ordering: fem::Ordering,
) -> Result<()> {
    if rhs == 0 {
        bail!("--rhs must be at least 1");
    }
    let mesh = load_volume(path, c.unit)?.mesh;
    let rhs_bytes = 3.0 * mesh.num_nodes() as f64 * rhs as f64 * 8.0;
    if rhs_bytes > 8.0 * (1u64 << 30) as f64 {
        bail!(
            "--rhs {rhs} on {} nodes needs {:.1} GiB for the right-hand sides alone (limit 8 GiB); use fewer",
            mesh.num_nodes(),
            rhs_bytes / (1u64 << 30) as f64
        );
    }
    let bar = indicatif::ProgressBar::new(repeat.max(1) as u64).with_message("bench basis");
    let mut runs = Vec::new();
    for _ in 0..repeat.max(1) {
        runs.push(fem::basis_bench::run(&mesh, rhs, seed, ordering)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let pick = |f: fn(&fem::basis_bench::BasisBench) -> f64| median(runs.iter().map(f).collect());
    let first = &runs[0];
    let out = json!({
        "mesh": path.display().to_string(),
        "nodes": first.nodes,
        "tets": first.tets,
        "dofs_free": first.dofs_free,
        "nrhs": rhs,
        "repeat": runs.len(),
        "threads": rayon::current_num_threads(),
        "assemble_s": pick(|r| r.assemble_s),
        "factor_s": pick(|r| r.factor_s),
        "factor_symbolic_s": pick(|r| r.factor.symbolic_s),
        "factor_numeric_s": pick(|r| r.factor.numeric_s),
        "solve_all_s": pick(|r| r.solve_all_s),
        "solve_per_rhs_ms": 1e3 * pick(|r| r.solve_all_s) / rhs as f64,
        "total_s": pick(|r| r.total_s),
        "nnz_lower": first.factor.nnz_lower,
        "nnz_factor": first.factor.nnz_factor,
        "ordering": first.factor.ordering,
        "max_rel_residual": runs.iter().map(|r| r.max_rel_residual).fold(0.0, f64::max),
    });
    emit(c.json, &out);
    Ok(())
}

/// A directory under the system temporary directory, removed (with its contents) when dropped.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Result<Self> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let p = std::env::temp_dir().join(format!("librplus-{tag}-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&p).with_context(|| p.display().to_string())?;
        Ok(Self(p))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn preload_json(p: &librplus::eval::bench::PreloadBench) -> Value {
    let one = |x: &librplus::eval::bench::Preload| {
        json!({
            "from_cache": x.from_cache,
            "loads_s": x.basis.loads_s,
            "assemble_s": x.basis.assemble_s,
            "factor_s": x.basis.factor_s,
            "solve_s": x.basis.solve_s,
            "energy_s": x.basis.energy_s,
            "cache_read_s": x.basis.cache_read_s,
            "basis_total_s": x.basis.total_s,
            "correspondence_s": x.correspondence_s,
            "total_s": x.total_s,
        })
    };
    json!({
        "nodes": p.nodes,
        "tets": p.tets,
        "columns": p.columns,
        "cache_bytes": p.cache_bytes,
        "threads": rayon::current_num_threads(),
        "cold": one(&p.cold),
        "warm": one(&p.warm),
    })
}

fn print_preload(p: &librplus::eval::bench::PreloadBench) {
    println!(
        "preload: {} nodes, {} tets, {} basis columns, cache file {:.1} MB, {} threads",
        p.nodes,
        p.tets,
        p.columns,
        p.cache_bytes as f64 / 1e6,
        rayon::current_num_threads()
    );
    println!(
        "  {:<5} {:>8} {:>9} {:>8} {:>8} {:>8} {:>11} {:>9} {:>15} {:>8}",
        "(s)",
        "loads",
        "assemble",
        "factor",
        "solve",
        "energy",
        "cache read",
        "basis",
        "correspondence",
        "total"
    );
    for (name, x) in [("cold", &p.cold), ("warm", &p.warm)] {
        println!(
            "  {:<5} {:>8.3} {:>9.3} {:>8.3} {:>8.3} {:>8.3} {:>11.3} {:>9.3} {:>15} {:>8.3}",
            name,
            x.basis.loads_s,
            x.basis.assemble_s,
            x.basis.factor_s,
            x.basis.solve_s,
            x.basis.energy_s,
            x.basis.cache_read_s,
            x.basis.total_s,
            x.correspondence_s
                .map_or_else(|| "–".to_string(), |c| format!("{c:.3}")),
            x.total_s
        );
    }
}

fn bench_register(a: &BenchRegisterArgs) -> Result<()> {
    use librplus::eval::bench::{
        pick_across_categories, preload_mesh, preload_model, time_registrations,
    };
    use librplus::register::pipeline::Method;
    if a.threads == 0 {
        bail!("--threads must be at least 1");
    }
    if a.scenarios == 0 {
        bail!("--scenarios must be at least 1");
    }
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    let tmp = TempDir::new("bench-register")?;
    let cache = tmp.0.join("cache");
    let spinner = |msg: &str| {
        let bar = indicatif::ProgressBar::new_spinner().with_message(msg.to_string());
        bar.enable_steady_tick(std::time::Duration::from_millis(200));
        bar
    };
    if let Some(path) = &a.mesh {
        let mesh = load_volume(path, a.common.unit)?.mesh;
        let bar = spinner("LIBR basis: cold build, then warm load");
        let p = preload_mesh(&mesh, &params.libr, &cache);
        bar.finish_and_clear();
        let p = p.map_err(anyhow::Error::msg)?;
        if a.common.json {
            println!(
                "{}",
                json!({"mesh": path.display().to_string(), "preload": preload_json(&p), "registrations": Value::Null})
            );
        } else {
            println!(
                "bench register: {} (mesh only: preload, no registrations)",
                path.display()
            );
            print_preload(&p);
        }
        return Ok(());
    }
    let data = match &a.data {
        Some(d) => d.clone(),
        None => {
            let dir = tmp.0.join("data");
            let bar = spinner("generating the small preset (no --data given)");
            let r = small_dataset(&dir, &a.surface);
            bar.finish_and_clear();
            r?;
            dir
        }
    };
    let m = librplus::eval::open(&data).map_err(anyhow::Error::msg)?;
    let geometry = match &a.geometry {
        Some(g) => g.clone(),
        None => m
            .geometries
            .first()
            .map(|g| g.id.clone())
            .with_context(|| format!("{}: the manifest has no geometry", data.display()))?,
    };
    let geo = librplus::eval::load_geometry(&data, &m, &geometry)
        .map_err(|e| anyhow::anyhow!("--geometry {geometry:?}: {e}"))?;
    let mut scenarios = Vec::new();
    for d in m.deformations.iter().filter(|d| d.geometry == geometry) {
        scenarios.extend(librplus::eval::load_scenarios(&data, d).map_err(anyhow::Error::msg)?);
    }
    let cats: Vec<&str> = scenarios.iter().map(|s| s.category.as_str()).collect();
    let picked: Vec<&librplus::eval::ScenarioData> = pick_across_categories(&cats, a.scenarios)
        .into_iter()
        .map(|i| &scenarios[i])
        .collect();
    if picked.is_empty() {
        bail!(
            "{}: geometry {geometry} has no scenarios in the categories {:?}",
            data.display(),
            librplus::eval::report::CATEGORY_ORDER
        );
    }
    let bar = spinner("preload: LIBR basis cold build, then warm load");
    let pre = preload_model(&geo.model, &params.libr, &cache);
    bar.finish_and_clear();
    let (pre, mut case) = pre.map_err(anyhow::Error::msg)?;
    let method = match a.method {
        MethodArg::Rigid => Method::Rigid,
        MethodArg::Libr => Method::Libr,
        MethodArg::Librplus => Method::LibrPlus,
    };
    match (&a.model, method) {
        (Some(dir), Method::LibrPlus) => {
            let m = librplus::gcn::io::load_models_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?;
            case = case
                .with_models(shared_models(m))
                .map_err(anyhow::Error::msg)?;
        }
        (None, Method::LibrPlus) => {
            let m = librplus::gcn::io::builtin_models()
                .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?;
            case = case
                .with_models(shared_models(m))
                .map_err(anyhow::Error::msg)?;
        }
        (Some(_), _) => bail!("--model is only used with --method librplus"),
        (None, _) => {}
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(a.threads)
        .build()
        .context("building the thread pool")?;
    let bar = indicatif::ProgressBar::new(picked.len() as u64).with_message("registrations");
    let progress = |done: usize, _: usize| bar.set_position(done as u64);
    let r = pool.install(|| {
        time_registrations(
            &case,
            &picked,
            &geo.surface,
            &geo.targets,
            method,
            &params,
            &progress,
        )
    });
    bar.finish_and_clear();
    let r = r.map_err(anyhow::Error::msg)?;
    let out = json!({
        "data": data.display().to_string(),
        "data_generated": a.data.is_none(),
        "geometry": geometry,
        "method": method.name(),
        "threads": a.threads,
        "preload": preload_json(&pre),
        "registrations": {
            "count": r.count,
            "failed": r.failed,
            "per_category": r.per_category,
            "total_s": r.total_s,
            "median_s": {
                "total": r.median.total_s,
                "wicp": r.median.wicp_s,
                "libr": r.median.libr_s,
                "libr_matching": r.median.libr_matching_s,
                "libr_assemble": r.median.libr_assemble_s,
                "libr_solve": r.median.libr_solve_s,
                "libr_other": r.median.libr_other_s,
                "gcn": r.median.gcn_s,
                "gcn_network": r.median.gcn_network_s,
                "gcn_refit": r.median.gcn_refit_s,
            },
            "wicp_iterations_mean": r.wicp_iterations_mean,
            "libr_iterations_mean": r.libr_iterations_mean,
            "libr_converged": r.libr_converged,
            "tre_mm_mean": r.tre_mm_mean,
        },
    });
    if a.common.json {
        println!("{out}");
        return Ok(());
    }
    println!(
        "bench register: geometry {geometry} of {}{}, method {}, {} registrations one at a time in a {}-thread pool",
        data.display(),
        if a.data.is_none() { " (generated)" } else { "" },
        method.name(),
        r.count,
        a.threads
    );
    print_preload(&pre);
    println!(
        "registration (s): median {:.4}, p10 {:.4}, p90 {:.4}, p99 {:.4}, mean {:.4}, max {:.4}; failed {}",
        r.total_s.median,
        r.total_s.p10,
        r.total_s.p90,
        r.total_s.p99,
        r.total_s.mean,
        r.total_s.max,
        r.failed
    );
    println!(
        "  stage medians (s): wicp {:.4}, libr {:.4} (matching {:.4}, assemble {:.4}, solve {:.4}, other {:.4}), gcn {:.4} (network {:.4}, refit {:.4})",
        r.median.wicp_s,
        r.median.libr_s,
        r.median.libr_matching_s,
        r.median.libr_assemble_s,
        r.median.libr_solve_s,
        r.median.libr_other_s,
        r.median.gcn_s,
        r.median.gcn_network_s,
        r.median.gcn_refit_s
    );
    println!(
        "  iterations (mean): wicp {:.1}, libr {:.1} (converged {}/{}); mean TRE {:.2} mm; per category {:?}",
        r.wicp_iterations_mean,
        r.libr_iterations_mean,
        r.libr_converged,
        r.count,
        r.tre_mm_mean,
        r.per_category
    );
    Ok(())
}

/// Generates the `small` preset (seed 1) from `surface` into `dir`, quietly.
fn small_dataset(dir: &Path, surface: &Path) -> Result<()> {
    use librplus::phantom::dataset::{GenerateConfig, Preset};
    let s = load_closed_surface(surface, Unit::Mm)
        .with_context(|| format!("--surface {} (for the default dataset)", surface.display()))?;
    let name = surface
        .file_name()
        .map(|n| n.to_string_lossy().to_string())
        .unwrap_or_else(|| surface.display().to_string());
    let config = GenerateConfig::preset(Preset::Small, 1, vec![name]);
    std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
    librplus::phantom::dataset::generate(&config, &[s], dir, (0, 1), &|_, _, _| {})
        .map_err(|e| anyhow::anyhow!("generating the small preset into {}: {e}", dir.display()))?;
    Ok(())
}

/// The paper's Table 2 settings as configurations: (LIBR input, bipartite, target, sparse loss).
fn ablation_config(
    mut cfg: librplus::gcn::model::SrGcnConfig,
    setting: u32,
    sparse: f64,
) -> Result<librplus::gcn::model::SrGcnConfig> {
    use librplus::gcn::model::Target;
    let (libr, bip, target, sp) = match setting {
        1 => (false, false, Target::Gt, false),
        2 => (false, false, Target::Residual, false),
        3 => (true, false, Target::Residual, false),
        4 => (true, true, Target::Residual, false),
        5 => (true, true, Target::Gt, true),
        6 => (true, true, Target::Residual, true),
        other => bail!("--ablation {other}: settings are 1-6 (the paper's Table 2)"),
    };
    cfg.libr_input = libr;
    cfg.bipartite = bip;
    // The measured misfit is measurement information, like the bipartite branch.
    cfg.misfit_input = cfg.misfit_input && bip;
    cfg.target = target;
    cfg.sparse_weight = if sp { sparse } else { 0.0 };
    Ok(cfg)
}

fn git_commit() -> String {
    std::process::Command::new("git")
        .args(["rev-parse", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_else(|| "unknown".into())
}

/// Trains and tests one model; returns its test.json (without per-scenario rows) and a
/// summary of its training.
fn train(a: &TrainArgs) -> Result<Value> {
    use librplus::eval::{load_scenarios, node_errors_mm, tre_from_errors};
    use librplus::gcn::model::SrGcnConfig;
    use librplus::gcn::train::{self as tr, TrainOptions, TrainSplit};
    let t_all = Instant::now();
    let m = librplus::eval::open(&a.data).map_err(anyhow::Error::msg)?;
    let split = TrainSplit::parse(&a.split).map_err(|e| anyhow::anyhow!("--split: {e}"))?;
    let base = SrGcnConfig::new()
        .with_misfit_input(a.misfit_input)
        .with_surface_input(a.surface_input)
        .with_load_input(a.load_input)
        .with_diagnostic_truth_neighbours(a.diagnostic_truth_neighbours)
        .with_width(a.width)
        .with_convs(a.convs)
        .with_kernel_size(a.kernel_size)
        .with_levels(a.levels)
        .with_resolution(a.resolution)
        .with_pool_ratio(a.pool_ratio)
        .with_clusters(a.clusters)
        .with_coarse_convs(a.coarse_convs)
        .with_residual(!a.no_residual)
        .with_n_top(a.n_top);
    let sparse = a.sparse_weight.unwrap_or(base.sparse_weight);
    let (cfg, init_provenance) = match &a.init {
        None => (ablation_config(base, a.ablation, sparse)?, Value::Null),
        Some(dir) => {
            let m = librplus::gcn::io::load_model(dir, &librplus::gcn::device::compute())
                .map_err(|e| anyhow::anyhow!("--init: {e}"))?;
            eprintln!(
                "--init {}: its network and settings replace the network options",
                dir.display()
            );
            (
                SrGcnConfig {
                    correction_scale: 1.0,
                    ..m.config
                },
                json!({"dir": dir.display().to_string(), "provenance": m.provenance}),
            )
        }
    };
    cfg.validate()
        .map_err(|e| anyhow::anyhow!("network options: {e}"))?;
    let params = a.libr.params();
    params
        .libr
        .validate()
        .map_err(|e| anyhow::anyhow!("LIBR options: {e}"))?;
    // Training through the refit needs a refit, and a correction of LIBR's shape to refit.
    let refit_loss = !a.no_refit_loss
        && params.refit_iterations > 0
        && cfg.target == librplus::gcn::model::Target::Residual;
    let opts = TrainOptions {
        config: cfg.clone(),
        split: split.clone(),
        every: a.every,
        seed: a.seed,
        epochs_bipartite: a.epochs_bipartite,
        epochs: a.epochs,
        learning_rate: a.lr,
        max_minutes: a.max_minutes,
        init: a.init.clone(),
        patience: a.patience,
        refit_loss,
        average_epochs: a.average_epochs,
        weight_decay: a.weight_decay,
        position_jitter: a.position_jitter,
        schedule: match a.schedule {
            ScheduleArg::Plateau => tr::Schedule::Plateau,
            ScheduleArg::Cosine => tr::Schedule::Cosine,
        },
    };
    let sets = tr::split_scenarios(&m, &split, a.seed, a.every, a.validation.get())
        .map_err(anyhow::Error::msg)?;
    eprintln!(
        "split {}: {} training, {} validation, {} test scenarios",
        split.name(),
        sets.train.len(),
        sets.valid.len(),
        sets.test.len()
    );
    // Scenarios of every deformation used.
    let mut needed: std::collections::BTreeSet<&str> = std::collections::BTreeSet::new();
    for (d, _) in sets.train.iter().chain(&sets.valid).chain(&sets.test) {
        needed.insert(d.as_str());
    }
    let mut scen = std::collections::BTreeMap::new();
    let mut geom_of = std::collections::BTreeMap::new();
    for d in m
        .deformations
        .iter()
        .filter(|d| needed.contains(d.id.as_str()))
    {
        scen.insert(
            d.id.clone(),
            load_scenarios(&a.data, d).map_err(anyhow::Error::msg)?,
        );
        geom_of.insert(d.id.clone(), d.geometry.clone());
    }
    let geos: Vec<String> = geom_of.values().cloned().collect();
    let spinner =
        indicatif::ProgressBar::new_spinner().with_message("preparing cases (LIBR bases)");
    spinner.enable_steady_tick(std::time::Duration::from_millis(200));
    let cases = tr::load_cases(&a.data, &m, &geos, &params).map_err(anyhow::Error::msg)?;
    spinner.finish_and_clear();
    let pick = |refs: &[(String, usize)]| -> Vec<(&librplus::eval::ScenarioData, &str)> {
        refs.iter()
            .filter_map(|(d, i)| scen[d].get(*i).map(|s| (s, geom_of[d].as_str())))
            .collect()
    };
    let bar_style = |what: &str| {
        indicatif::ProgressStyle::with_template(&format!(
            "{{spinner}} {what} [{{bar:30}}] {{pos}}/{{len}} {{msg}} {{elapsed}} (eta {{eta}})"
        ))
        .expect("valid template")
        .progress_chars("=> ")
    };
    let solve = |items: &[(&librplus::eval::ScenarioData, &str)],
                 what: &str|
     -> Result<Vec<Option<tr::LibrSolution>>> {
        let bar = indicatif::ProgressBar::new(items.len() as u64).with_style(bar_style(what));
        let r = tr::libr_solutions(&a.data, &cases, items, &params, &|d, _| {
            bar.set_position(d as u64)
        });
        bar.finish_and_clear();
        r.map_err(anyhow::Error::msg)
    };
    let t_libr = Instant::now();
    let train_items = pick(&sets.train);
    let valid_items = pick(&sets.valid);
    let train_sol = solve(&train_items, "LIBR on training scenarios")?;
    let valid_sol = solve(&valid_items, "LIBR on validation scenarios")?;
    let libr_seconds = t_libr.elapsed().as_secs_f64();
    let samples = |items: &[(&librplus::eval::ScenarioData, &str)],
                   sols: &[Option<tr::LibrSolution>]|
     -> Result<Vec<tr::Prepared2>> {
        let z: Vec<_> = items
            .iter()
            .zip(sols)
            .map(|((s, g), o)| (*s, *g, o))
            .collect();
        Ok(
            tr::build_samples(&cfg, &cases, &z, &params, true, refit_loss)
                .map_err(anyhow::Error::msg)?
                .into_iter()
                .flatten()
                .collect(),
        )
    };
    let train_s = samples(&train_items, &train_sol)?;
    let valid_s = samples(&valid_items, &valid_sol)?;
    let command = shell_command();
    let provenance = json!({
        "command": command,
        "data": a.data.display().to_string(),
        "data_preset": m.preset,
        "data_seed": m.seed,
        "data_parameters_hash": m.parameters_hash,
        "split": split.name(),
        "every": a.every,
        "validation": a.validation.get().name(),
        "seed": a.seed,
        "ablation": a.ablation,
        "init": init_provenance,
        "commit": git_commit(),
        "libr_solution_key": tr::solution_key(&params),
        "train_scenarios": sets.train.len(),
        "valid_scenarios": sets.valid.len(),
        "test_scenarios": sets.test.len(),
    });
    let bar = indicatif::ProgressBar::new(0).with_style(bar_style("training"));
    let t_train = Instant::now();
    let progress = |stage: u32, epoch: usize, done: usize, total: usize, loss: f64| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(format!("stage {stage} epoch {epoch} loss {loss:.4}"));
        if done == total {
            bar.suspend(|| {
                eprintln!(
                    "stage {stage} epoch {epoch}: {total} steps, training loss {loss:.5}, {:.0} s",
                    t_train.elapsed().as_secs_f64()
                )
            });
        }
    };
    let mut report = tr::train(
        &opts,
        &cases,
        &train_s,
        &valid_s,
        &a.out,
        &provenance,
        &progress,
    )
    .map_err(anyhow::Error::msg)?;
    bar.finish_and_clear();
    for l in &report.log {
        eprintln!(
            "stage {} epoch {:>2}: train loss {:.5}, validation {:.4}{}, lr {:.1e}, {:.0} s",
            l.stage,
            l.epoch,
            l.train_loss,
            l.valid,
            if l.stage == 2 { " mm" } else { "" },
            l.learning_rate,
            l.seconds
        );
    }
    eprintln!(
        "correction scale {:.2} (validation node error {:.4} mm; {:.4} mm at scale 1, LIBR {:.4} mm)",
        report.model.config.correction_scale,
        report.scaled_valid_mm,
        report.best_valid_mm,
        report.libr_valid_mm
    );
    // With the data-consistency refit (as LIBR+ runs), the scale is fitted again on the
    // validation scenarios through the refit.
    let scale_without_refit = report.model.config.correction_scale;
    let mut refit_fit = serde_json::Value::Null;
    if report.model.config.target == librplus::gcn::model::Target::Residual
        && params.refit_iterations > 0
    {
        let spinner = indicatif::ProgressBar::new_spinner()
            .with_message("fitting the correction scale through the refit (validation)");
        spinner.enable_steady_tick(std::time::Duration::from_millis(200));
        let z: Vec<_> = valid_items
            .iter()
            .zip(&valid_sol)
            .map(|((s, g), o)| (*s, *g, o))
            .collect();
        let grid = tr::refit_scale_grid();
        let (scale, errs) = tr::fit_refit_scale(&report.model, &cases, &z, &params, &grid)
            .map_err(anyhow::Error::msg)?;
        spinner.finish_and_clear();
        let k = grid.iter().position(|&g| g == scale).unwrap_or(0);
        eprintln!(
            "with the refit ({} iterations): correction scale {scale:.3}, validation node error {:.4} mm ({:.4} mm without the correction)",
            params.refit_iterations, errs[k], errs[0]
        );
        report.model.config.correction_scale = scale;
        report.scaled_valid_mm = errs[k];
        refit_fit = json!({
            "refit_iterations": params.refit_iterations,
            "grid": grid,
            "valid_node_error_mm": errs,
            "scale_without_refit": scale_without_refit,
        });
    }
    // Test: LIBR and LIBR+ on the held-out scenarios.
    let test_items = pick(&sets.test);
    let test_sol = solve(&test_items, "LIBR on test scenarios")?;
    let z: Vec<_> = test_items
        .iter()
        .zip(&test_sol)
        .map(|((s, g), o)| (*s, *g, o))
        .collect();
    let t_inf = Instant::now();
    let test_s =
        // Test samples never carry the truth, except for the paper's leak (a diagnostic).
        tr::build_samples(
            &cfg,
            &cases,
            &z,
            &params,
            cfg.diagnostic_truth_neighbours,
            false,
        )
        .map_err(anyhow::Error::msg)?;
    let plain = librplus::gcn::device::compute();
    let mut graphs = std::collections::BTreeMap::new();
    for (g, gc) in &cases {
        graphs.insert(
            g.clone(),
            gc.frame
                .mesh_graphs(&cfg, &plain)
                .map_err(|e| anyhow::anyhow!("{e}"))?,
        );
    }
    let mut rows = Vec::new();
    let bar = indicatif::ProgressBar::new(test_items.len() as u64)
        .with_style(bar_style("LIBR+ on test scenarios"));
    for (((sc, g), sol), sample) in test_items.iter().zip(&test_sol).zip(&test_s) {
        bar.inc(1);
        let gc = &cases[*g];
        let (Some(sol), Some(sample)) = (sol, sample) else {
            rows.push(json!({"scenario": sc.id, "category": sc.category, "error": "LIBR failed"}));
            continue;
        };
        let nodes = gc.geo.model.mesh.nodes();
        let truth = (
            &sc.truth.image_to_physical,
            sc.truth.displacement.as_slice(),
        );
        let e_libr = node_errors_mm(nodes, (&sol.transform, &sol.u), truth);
        let u_plus = tr::correct(&report.model, &gc.frame, &graphs[*g], &sample.data, &sol.u)
            .map_err(|e| anyhow::anyhow!("{}: {e}", sc.id))?;
        let (u_plus, t_plus) = if params.refit_iterations > 0 {
            let r = librplus::register::pipeline::refit(
                &gc.case,
                &sc.measurements,
                &params,
                &u_plus,
                &sol.transform,
                None,
            )
            .map_err(|e| anyhow::anyhow!("{}: refit: {e}", sc.id))?;
            (r.u, r.image_to_physical)
        } else {
            (u_plus, sol.transform)
        };
        let e_plus = node_errors_mm(nodes, (&t_plus, &u_plus), truth);
        let t_l = tre_from_errors(&e_libr, &gc.geo.surface, &gc.geo.targets);
        let t_p = tre_from_errors(&e_plus, &gc.geo.surface, &gc.geo.targets);
        rows.push(json!({"scenario": sc.id, "geometry": g, "category": sc.category, "libr": t_l, "librplus": t_p}));
    }
    bar.finish_and_clear();
    let inference_seconds = t_inf.elapsed().as_secs_f64();
    // Aggregate.
    let mut by_cat: std::collections::BTreeMap<String, (f64, f64, usize)> = Default::default();
    let (mut sl, mut sp, mut n) = (0.0, 0.0, 0usize);
    for r in &rows {
        if let (Some(l), Some(p)) = (
            r["libr"]["tre_mm"].as_f64(),
            r["librplus"]["tre_mm"].as_f64(),
        ) {
            sl += l;
            sp += p;
            n += 1;
            let e = by_cat
                .entry(r["category"].as_str().unwrap_or("?").to_string())
                .or_default();
            e.0 += l;
            e.1 += p;
            e.2 += 1;
        }
    }
    let nn = n.max(1) as f64;
    let test = json!({
        "format": 1,
        "split": split.name(),
        "scenarios": n,
        "failed": rows.len() - n,
        "libr_tre_mm": sl / nn,
        "librplus_tre_mm": sp / nn,
        "ratio": if sl > 0.0 { sp / sl } else { f64::NAN },
        "by_category": by_cat.iter().map(|(k, v)| (k.clone(), json!({"libr_tre_mm": v.0 / v.2 as f64, "librplus_tre_mm": v.1 / v.2 as f64, "scenarios": v.2}))).collect::<serde_json::Map<_, _>>(),
        "results": rows,
    });
    std::fs::write(
        a.out.join("test.json"),
        serde_json::to_string_pretty(&test)?,
    )?;
    let training = json!({
        "format": 1,
        "log": report.log,
        "best_valid_node_error_mm": report.best_valid_mm,
        "correction_scale": report.model.config.correction_scale,
        "scaled_valid_node_error_mm": report.scaled_valid_mm,
        "refit_scale_fit": refit_fit,
        "libr_valid_node_error_mm": report.libr_valid_mm,
        "train_samples": report.train_samples,
        "valid_samples": report.valid_samples,
        "train_seconds": report.seconds,
        "libr_solution_seconds": libr_seconds,
        "test_inference_seconds": inference_seconds,
        "total_seconds": t_all.elapsed().as_secs_f64(),
    });
    std::fs::write(
        a.out.join("training.json"),
        serde_json::to_string_pretty(&training)?,
    )?;
    // Final model with full provenance (metrics included).
    let mut prov = provenance.clone();
    prov["metrics"] = json!({
        "valid_node_error_mm": report.best_valid_mm,
        "correction_scale": report.model.config.correction_scale,
        "libr_valid_node_error_mm": report.libr_valid_mm,
        "test_libr_tre_mm": sl / nn,
        "test_librplus_tre_mm": sp / nn,
        "train_seconds": report.seconds,
    });
    librplus::gcn::io::save_model(&a.out, &report.model.config, &report.model.net, prov)
        .map_err(anyhow::Error::msg)?;
    // Loss curves.
    let series =
        |stage: u32, f: &dyn Fn(&librplus::gcn::train::EpochLog) -> f64| -> Vec<(f64, f64)> {
            report
                .log
                .iter()
                .filter(|l| l.stage == stage)
                .map(|l| (l.epoch as f64, f(l)))
                .collect()
        };
    let png = librplus::eval::plot::line_chart_png(
        "SR-GCN stage 2 (mesh branch)",
        "epoch",
        "validation node error (mm) / training loss",
        &[
            ("validation node error (mm)".into(), series(2, &|l| l.valid)),
            ("training loss".into(), series(2, &|l| l.train_loss)),
            (
                "LIBR alone (mm)".into(),
                series(2, &|_| report.libr_valid_mm),
            ),
        ],
    )
    .map_err(anyhow::Error::msg)?;
    std::fs::write(a.out.join("loss_stage2.png"), png)?;
    if cfg.bipartite {
        let png = librplus::eval::plot::line_chart_png(
            "SR-GCN stage 1 (bipartite reconstruction)",
            "epoch",
            "loss",
            &[
                ("training".into(), series(1, &|l| l.train_loss)),
                ("validation".into(), series(1, &|l| l.valid)),
            ],
        )
        .map_err(anyhow::Error::msg)?;
        std::fs::write(a.out.join("loss_stage1.png"), png)?;
    }
    println!(
        "split {}: test LIBR {:.3} mm, LIBR+ {:.3} mm (ratio {:.3}) over {n} scenarios; training {:.0} s, LIBR solutions {:.0} s",
        split.name(),
        sl / nn,
        sp / nn,
        sp / sl.max(1e-12),
        report.seconds,
        libr_seconds
    );
    for (k, v) in &by_cat {
        println!(
            "  {k:<12} LIBR {:.3}  LIBR+ {:.3}  ({} scenarios)",
            v.0 / v.2 as f64,
            v.1 / v.2 as f64,
            v.2
        );
    }
    let mut summary = test;
    if let Some(o) = summary.as_object_mut() {
        o.remove("results");
        o.insert("training".into(), training);
    }
    Ok(summary)
}

/// `librplus experiments`: every split and ablation as `librplus train` runs, then the reports.
fn experiments(a: &ExperimentsArgs) -> Result<()> {
    use librplus::eval::experiments::{RunOutcome, results_markdown, scenario_results};
    let t0 = Instant::now();
    let m = librplus::eval::open(&a.data).map_err(anyhow::Error::msg)?;
    let test_geos = m.test_geometries();
    let mut train_geos: Vec<String> = m
        .deformations
        .iter()
        .filter(|d| !test_geos.contains(&d.geometry.as_str()))
        .map(|d| d.geometry.clone())
        .collect();
    train_geos.sort();
    train_geos.dedup();
    // (split, setting) of every run, the full model's splits first.
    let mut plan: Vec<(String, u32)> = Vec::new();
    for s in a.splits.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        if s == "logo" {
            plan.extend(train_geos.iter().map(|g| (format!("logo:{g}"), 6)));
        } else {
            librplus::gcn::train::TrainSplit::parse(s)
                .map_err(|e| anyhow::anyhow!("--splits: {e}"))?;
            plan.push((s.to_string(), 6));
        }
    }
    let ablation_split = a.ablation_split.trim().to_string();
    for t in a
        .ablations
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
    {
        let k: u32 = t
            .parse()
            .ok()
            .filter(|k| (1..=6).contains(k))
            .ok_or_else(|| anyhow::anyhow!("--ablations: {t:?} is not a setting 1-6"))?;
        if !plan.contains(&(ablation_split.clone(), k)) {
            plan.push((ablation_split.clone(), k));
        }
    }
    let extra: Vec<String> = a.train_args.split_whitespace().map(String::from).collect();
    for reserved in [
        "--data",
        "--split",
        "--out",
        "--every",
        "--seed",
        "--ablation",
    ] {
        if extra
            .iter()
            .any(|x| x == reserved || x.starts_with(&format!("{reserved}=")))
        {
            bail!("--train-args: {reserved} is set by `experiments` itself");
        }
    }
    std::fs::create_dir_all(a.out.join("runs")).with_context(|| a.out.display().to_string())?;
    eprintln!(
        "experiments: {} runs, about {:.0} minutes of training each",
        plan.len(),
        a.minutes
    );
    let mut outcomes: Vec<RunOutcome> = Vec::new();
    for (i, (split, setting)) in plan.iter().enumerate() {
        let name = format!("{}-ablation{setting}", split.replace(':', "-"));
        let dir = a.out.join("runs").join(&name);
        let test_path = dir.join("test.json");
        if !(a.resume && test_path.exists()) {
            eprintln!(
                "\n[{}/{}] {split}, setting {setting} → {}",
                i + 1,
                plan.len(),
                dir.display()
            );
            let mut argv: Vec<String> = vec![
                "train".into(),
                "--data".into(),
                a.data.display().to_string(),
                "--split".into(),
                split.clone(),
                "--out".into(),
                dir.display().to_string(),
                "--every".into(),
                a.every.to_string(),
                "--seed".into(),
                a.seed.to_string(),
                "--ablation".into(),
                setting.to_string(),
                "--max-minutes".into(),
                a.minutes.to_string(),
            ];
            argv.extend(extra.iter().cloned());
            let args = TrainOnly::try_parse_from(&argv)
                .map_err(|e| anyhow::anyhow!("--train-args: {e}"))?
                .args;
            train(&args).with_context(|| format!("run {name}"))?;
        }
        let test: Value = serde_json::from_str(
            &std::fs::read_to_string(&test_path)
                .with_context(|| test_path.display().to_string())?,
        )
        .with_context(|| test_path.display().to_string())?;
        let png = librplus::eval::plot::tre_by_category_png(split, &scenario_results(&test))
            .map_err(anyhow::Error::msg)?;
        std::fs::write(a.out.join(format!("tre_by_category_{name}.png")), png)?;
        outcomes.push(RunOutcome {
            name,
            split: split.clone(),
            ablation: *setting,
            test,
        });
    }
    let main: Vec<RunOutcome> = outcomes
        .iter()
        .filter(|r| r.ablation == 6)
        .cloned()
        .collect();
    let mut abl: Vec<RunOutcome> = outcomes
        .iter()
        .filter(|r| r.split == ablation_split && plan.contains(&(r.split.clone(), r.ablation)))
        .filter(|r| {
            a.ablations
                .split(',')
                .any(|t| t.trim() == r.ablation.to_string())
        })
        .cloned()
        .collect();
    abl.sort_by_key(|r| r.ablation);
    let command = shell_command();
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let header = format!(
        "# LIBR+ results\n\nMade by one command (commit `{}`):\n\n```\n{}\n```\n\n\
         - Data: `{}` (preset {}, seed {}, parameters {}); every {}th block of five scenarios.\n\
         - Each run is `librplus train` with a training limit of {} minutes; its model, \
         `training.json` and `test.json` are under `runs/`.\n\
         - Machine: {cpu}, {threads} threads. Total wall time {:.0} minutes.\n\
         - TRE: mean distance over mesh nodes between the registered and the true deformed \
         liver (physical frame), averaged over the held-out scenarios.\n",
        git_commit(),
        command,
        a.data.display(),
        m.preset,
        m.seed,
        m.parameters_hash,
        a.every,
        a.minutes,
        t0.elapsed().as_secs_f64() / 60.0
    );
    let md = results_markdown(&header, &main, &abl);
    std::fs::write(a.out.join("RESULTS.md"), &md)?;
    let runs: Vec<Value> = outcomes
        .iter()
        .map(|r| {
            json!({"name": r.name, "split": r.split, "ablation": r.ablation,
                   "figures": librplus::eval::experiments::figures(&r.test)})
        })
        .collect();
    std::fs::write(
        a.out.join("results.json"),
        serde_json::to_string_pretty(&json!({"format": 1, "command": command, "runs": runs}))?,
    )?;
    println!("{md}");
    eprintln!("wrote {}", a.out.join("RESULTS.md").display());
    Ok(())
}

/// This process's command line as a shell would need it: an empty argument or one holding a space
/// or a shell character in single quotes, so a recorded command runs again when pasted.
fn shell_command() -> String {
    std::env::args()
        .map(|a| {
            let plain = !a.is_empty()
                && a.chars()
                    .all(|c| c.is_ascii_alphanumeric() || "-_=./,:@%+".contains(c));
            if plain {
                a
            } else {
                format!("'{}'", a.replace('\'', "'\\''"))
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}
