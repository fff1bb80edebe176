//! The command line: clap's parser, the commands and their arguments, and the value enums.

use clap::{Args, Parser, Subcommand};
use librplus::fem;
use librplus::mesh::io::Unit;
use std::path::PathBuf;

mod libr;
mod train;
pub(crate) use libr::LibrOpts;
pub(crate) use train::TrainArgs;

#[derive(Parser)]
#[command(
    name = "librplus",
    version,
    about = "LIBR+ intraoperative liver registration"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Command,
    /// Where SR-GCN training and inference compute: cpu, or (in a build with the `gpu` or
    /// `vulkan` feature) gpu or gpu:N. wICP, LIBR and the FEM always run on the CPU.
    #[arg(long, global = true, default_value = "cpu")]
    pub(crate) device: String,
}

#[derive(Subcommand)]
pub(crate) enum Command {
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
    /// (format in docs/dataset-and-models.md; deterministic for a seed, resumable, shardable).
    Generate(GenerateArgs),
    /// Liver phantoms: what the ground truth contains that the linear model lacks.
    #[command(subcommand)]
    Phantom(PhantomCmd),
    /// Registers one dataset scenario (rigid wICP, or wICP then LIBR) and reports its TRE.
    Register(RegisterArgs),
    /// Evaluates methods over a dataset split: summary.json, report.md, per-scenario results.
    Evaluate(EvaluateArgs),
    /// Calibrates the per-registration error estimate (predicted mean TRE and per-node bound) on
    /// a generated dataset, and checks it on another (`--check`): FILE (the model) and
    /// FILE.report.md / FILE.report.json.
    CalibrateError(CalibrateErrorArgs),
    /// Sets when LIBR+ abstains (answers LIBR's result, flagged) from its signals on in-family
    /// data (a fresh seed of the networks' generator): DIR/abstain.json beside the networks.
    CalibrateAbstain(CalibrateAbstainArgs),
    /// Trains SR-GCN (LIBR+) on a dataset split, then tests LIBR and LIBR+ on the held-out
    /// scenarios: MODEL_DIR/model.json + weights.safetensors (+ provenance), training.json, test.json,
    /// loss curves (PNG).
    Train(TrainArgs),
    /// Runs the paper's experiments in one go: `train` on every split (random, geometry-
    /// deformation hold-out, each leave-one-geometry-out, pattern V) and the Table 2 ablations,
    /// then writes OUT/RESULTS.md (tables), OUT/results.json and OUT/ratios.png.
    Experiments(ExperimentsArgs),
    /// Makes an ensemble directory from trained model directories: LIBR+ with it averages the
    /// members' corrections (docs/dataset-and-models.md, "SR-GCN ensemble directory"). Usable wherever `--model` is.
    Ensemble(EnsembleArgs),
    /// The model-discrepancy workflow: per cohort (one deformed state's sweeps), finds where
    /// LIBR's model and the data disagree, names the missing effect, adds it and shows the gap
    /// shrink: OUT/discover.json, OUT/report.md, OUT/COHORT/physics.json.
    Discover(DiscoverArgs),
    /// Scores `discover` runs against the truth of hidden-effect datasets (`generate --truth
    /// libr --hidden-effect ...`): per hidden kind and oracle detectability, how often the right
    /// kind was named, and the confusion matrix of hidden against named: OUT.json and OUT.md.
    DiscoverScore(DiscoverScoreArgs),
    /// Detectability curves: for each kind and amplitude scale, generates a hidden-effect dataset
    /// (and one with nothing hidden), runs `discover` on it and scores it: OUT/study.json,
    /// OUT/study.md (with the confusion matrix), OUT/named.png and OUT/detectable.png.
    DiscoverStudy(DiscoverStudyArgs),
}

#[derive(Args)]
pub(crate) struct DiscoverStudyArgs {
    /// Output directory (datasets under data/, discover reports under reports/; both are kept,
    /// and a step whose output exists is not run again).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Dataset preset (`small` or `paper`).
    #[arg(long, default_value = "small")]
    pub(crate) preset: String,
    /// Seed of every dataset (use one not used in development).
    #[arg(long, default_value_t = 9001)]
    pub(crate) seed: u64,
    /// Kinds, comma-separated (default: every kind the generator makes).
    #[arg(long)]
    pub(crate) kinds: Option<String>,
    /// Amplitude scales, comma-separated (`--hidden-effect KIND:scale=F`).
    #[arg(long, default_value = "0.25,0.5,1,2")]
    pub(crate) scales: String,
    /// Geometries per dataset.
    #[arg(long, default_value_t = 2)]
    pub(crate) geometries: usize,
    /// Deformations (cohorts) per geometry.
    #[arg(long, default_value_t = 3)]
    pub(crate) deformations: usize,
    /// Scenarios (sweeps) per cohort.
    #[arg(long, default_value_t = 10)]
    pub(crate) scenarios: usize,
    /// Skip the dataset with nothing hidden (the negative control).
    #[arg(long)]
    pub(crate) no_control: bool,
    /// Print the study's JSON on stdout instead of the Markdown tables.
    #[arg(long)]
    pub(crate) json: bool,
}

#[derive(Args)]
pub(crate) struct DiscoverScoreArgs {
    /// A dataset directory; repeatable, each paired with the --report at the same place.
    #[arg(long, required = true)]
    pub(crate) data: Vec<PathBuf>,
    /// The `discover --out` directory of the dataset at the same place (its discover.json).
    #[arg(long, required = true)]
    pub(crate) report: Vec<PathBuf>,
    /// Output path without extension: OUT.json (the score, format 1) and OUT.md.
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Print the score's JSON on stdout instead of the Markdown tables.
    #[arg(long)]
    pub(crate) json: bool,
}

#[derive(Args)]
pub(crate) struct DiscoverArgs {
    /// Dataset directory (from `librplus generate`).
    #[arg(long, required_unless_present = "preop")]
    pub(crate) data: Option<PathBuf>,
    /// A cohort: a deformation id (its scenarios are the sweeps); repeatable. Default: every
    /// deformation of the dataset.
    #[arg(long, requires = "data")]
    pub(crate) cohort: Vec<String>,
    /// Your own preoperative liver instead of a dataset (as `register --preop`: a tet mesh or a
    /// closed surface meshed at --edge-mm); the sweeps of one cohort are in --scenarios.
    #[arg(long, conflicts_with = "data", requires = "scenarios")]
    pub(crate) preop: Option<PathBuf>,
    /// With --preop: the cohort's sweeps, one per entry of this directory (in name order): a
    /// point file (.csv .txt .xyz .vtp .vtu .vtk: surface points), or a folder holding `surface.*` and
    /// optionally `ultrasound*.*` (posterior contours), `vessel*.*` (vessel points) and
    /// `initial_alignment.json`.
    #[arg(long, requires = "preop")]
    pub(crate) scenarios: Option<PathBuf>,
    /// With --preop: length unit of the mesh and point files (mm, cm or m).
    #[arg(long, default_value = "mm")]
    pub(crate) unit: Unit,
    /// With --preop and a surface file: tet edge length (mm).
    #[arg(long, default_value_t = 7.6)]
    pub(crate) edge_mm: f64,
    /// Report directory.
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Spatial blocks held out in turn.
    #[arg(long, default_value_t = 6)]
    pub(crate) folds: usize,
    /// Kinds searched, comma-separated (default: every kind the augmented model carries).
    #[arg(long)]
    pub(crate) kinds: Option<String>,
    /// Most effects named per cohort.
    #[arg(long, default_value_t = 3)]
    pub(crate) max_effects: usize,
    /// At most this many sweeps per cohort (the first ones; 0 = all).
    #[arg(long, default_value_t = 0)]
    pub(crate) max_sweeps: usize,
    /// Where LIBR bases are cached (default DATA/cache, or `cache` beside --preop).
    #[arg(long)]
    pub(crate) cache: Option<PathBuf>,
    /// Print the discover.json object on stdout instead of text.
    #[arg(long)]
    pub(crate) json: bool,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}

#[derive(Args)]
pub(crate) struct EnsembleArgs {
    /// The new ensemble directory (must not exist, or be empty).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Model directories (from `librplus train`); an ensemble directory adds its members.
    #[arg(required = true)]
    pub(crate) models: Vec<PathBuf>,
}

#[derive(Args)]
pub(crate) struct ExperimentsArgs {
    /// Dataset directory (from `librplus generate`).
    #[arg(long)]
    pub(crate) data: PathBuf,
    /// Output directory: one model directory per run under `runs/`, and the reports.
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Splits, comma-separated: random, geo-def, logo (every geometry), logo:G, pattern-v,
    /// family (every truth family held out in turn; `generate --families`), family:NAME.
    #[arg(long, default_value = "random,geo-def,logo,pattern-v")]
    pub(crate) splits: String,
    /// Table 2 settings to run on `--ablation-split` (comma-separated, 1-6; empty: none).
    #[arg(long, default_value = "1,2,3,4,5,6")]
    pub(crate) ablations: String,
    /// The split the ablations run on (the paper: random).
    #[arg(long, default_value = "random")]
    pub(crate) ablation_split: String,
    /// Use every k-th block of five scenarios, in every run.
    #[arg(long, default_value_t = 16)]
    pub(crate) every: usize,
    /// Training time limit per run (minutes; stage 2 stops before an epoch would pass it).
    #[arg(long, default_value_t = 6.0)]
    pub(crate) minutes: f64,
    /// Seed of every run.
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// More `librplus train` options for every run, as one string (e.g. "--width 48"); not the
    /// ones this command sets (--data, --split, --out, --every, --seed, --ablation, --max-minutes).
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub(crate) train_args: String,
    /// Keep runs whose directory already has test.json (resume an interrupted campaign).
    #[arg(long)]
    pub(crate) resume: bool,
    /// Leave out the V2S runs (by default every split of the full model also trains and tests
    /// V2S, `librplus train --method v2s`, for the four-method tables).
    #[arg(long)]
    pub(crate) no_v2s: bool,
    /// More `librplus train --method v2s` options for every V2S run (e.g. "--grid 64").
    #[arg(long, default_value = "", allow_hyphen_values = true)]
    pub(crate) v2s_args: String,
    /// Training time limit per V2S run (minutes; default --minutes).
    #[arg(long)]
    pub(crate) v2s_minutes: Option<f64>,
}

#[derive(Parser)]
pub(crate) struct TrainOnly {
    #[command(flatten)]
    pub(crate) args: TrainArgs,
}

/// `train --method`.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum TrainMethod {
    /// SR-GCN, LIBR's learned residual (LIBR+).
    Srgcn,
    /// The V2S-Net-style volumetric network.
    V2s,
}

#[derive(Args)]
pub(crate) struct EvaluateArgs {
    /// Dataset directory.
    #[arg(long)]
    pub(crate) data: PathBuf,
    /// Comma-separated methods: initial (the navigation start, unregistered: the baseline),
    /// rigid, libr, adaptive (adaptive LIBR), auto (chosen per registration from the data),
    /// v2s (--v2s-model), librplus (--model, or the built-in model).
    #[arg(long, default_value = "initial,rigid,libr,adaptive,auto")]
    pub(crate) methods: String,
    /// A trained SR-GCN model directory (from `librplus train`), or an ensemble directory (from
    /// `librplus ensemble`): evaluates LIBR+ and restricts every method to the model's held-out
    /// test scenarios (an ensemble: those every member held out; its split replaces --split).
    #[arg(long)]
    pub(crate) model: Option<PathBuf>,
    /// A V2S model directory (from `librplus train --method v2s`) for method v2s (default: the
    /// built-in V2S model); like --model, one trained on this dataset restricts every method to
    /// its held-out test scenarios.
    #[arg(long)]
    pub(crate) v2s_model: Option<PathBuf>,
    /// Comma-separated splits: all, train, test (the held-out geometry with pattern V).
    #[arg(long, default_value = "all")]
    pub(crate) split: String,
    /// Evaluate every k-th scenario of each deformation.
    #[arg(long, default_value_t = 1)]
    pub(crate) every: usize,
    /// Report directory (summary.json, report.md, results.json, PNG plots, error_maps/).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// An augmented model (`physics.json`, from `librplus discover` or written by hand): LIBR
    /// and LIBR+ register with its effects (a `fixation` or `ligament` effect also trusts the
    /// start, see --trusted-alignment)
    #[arg(long, value_name = "FILE")]
    pub(crate) physics: Option<PathBuf>,
    /// Each deformation (a cohort) gets its own physics: `librplus discover` on its held-in
    /// scenarios (the even kept blocks of five), LIBR with it scored as method
    /// `libr-discovered` on the held-out ones (the odd blocks), where every method then runs
    #[arg(long, conflicts_with = "physics")]
    pub(crate) discover: bool,
    /// Print summary.json on stdout.
    #[arg(long)]
    pub(crate) json: bool,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}

#[derive(Args)]
pub(crate) struct CalibrateErrorArgs {
    /// Calibration dataset (from `librplus generate`; its truth is read); repeatable: the
    /// model is calibrated on them all.
    #[arg(long, required = true)]
    pub(crate) data: Vec<PathBuf>,
    /// The error model written (JSON, docs/error-estimate.md).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Comma-separated methods calibrated: initial, rigid, libr, librplus, adaptive (every
    /// method the service answers with; auto's answers carry their chosen candidate's).
    #[arg(long, default_value = "initial,rigid,libr,librplus,adaptive")]
    pub(crate) methods: String,
    /// The SR-GCN model or ensemble directory LIBR+ uses (default: the built-in ensemble, the
    /// one the service serves).
    #[arg(long)]
    pub(crate) model: Option<PathBuf>,
    /// Use every k-th block of five scenarios of each deformation.
    #[arg(long, default_value_t = 1)]
    pub(crate) every: usize,
    /// Level of the per-node bound the model reports (the fraction of nodes it should cover).
    #[arg(long, default_value_t = 0.9)]
    pub(crate) level: f64,
    /// Ridge penalty of the mean-TRE regression (standardised regressors).
    #[arg(long, default_value_t = 1.0)]
    pub(crate) ridge: f64,
    /// A registration whose true mean TRE exceeds this counts as failed (mm): the model learns
    /// the probability of a failure and a law for failed registrations beside the law for the
    /// rest (when at least 10 calibration registrations failed); 0: one law for all.
    #[arg(long, default_value_t = 20.0, value_name = "MM")]
    pub(crate) failure_threshold: f64,
    /// A held-out dataset (another seed; never read for calibration) the model is checked on.
    #[arg(long)]
    pub(crate) check: Option<PathBuf>,
    /// --every for the held-out dataset.
    #[arg(long, default_value_t = 1)]
    pub(crate) check_every: usize,
    /// Check this error model (e.g. `assets/models/error/model.json`) on every --data instead
    /// of calibrating one: --out then names the report (OUT.report.md, .report.json,
    /// .samples.csv) and no model is written.
    #[arg(long, value_name = "MODEL_JSON", conflicts_with = "check")]
    pub(crate) existing: Option<PathBuf>,
    /// Print the report as JSON on stdout.
    #[arg(long)]
    pub(crate) json: bool,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}

#[derive(Args)]
pub(crate) struct CalibrateAbstainArgs {
    /// In-family dataset(s) (from `librplus generate` with the networks' generator and preset,
    /// a seed they never saw; the truth is not read); repeatable.
    #[arg(long, required = true)]
    pub(crate) data: Vec<PathBuf>,
    /// The SR-GCN model or ensemble directory (default: the built-in ensemble).
    #[arg(long)]
    pub(crate) model: Option<PathBuf>,
    /// Where abstain.json is written (a directory; default: --model's).
    #[arg(long)]
    pub(crate) out: Option<PathBuf>,
    /// The in-family abstention rate the thresholds are set for (their bound).
    #[arg(long, default_value_t = 0.05)]
    pub(crate) alpha: f64,
    /// Use every k-th block of five scenarios of each deformation.
    #[arg(long, default_value_t = 1)]
    pub(crate) every: usize,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}

#[derive(Args)]
pub(crate) struct RegisterArgs {
    /// Dataset directory (from `librplus generate`), with --scenario.
    #[arg(long, requires = "scenario", required_unless_present = "preop")]
    pub(crate) data: Option<PathBuf>,
    /// Scenario: `DEFORMATION/INDEX`, e.g. `g1-L-00/3`.
    #[arg(long, requires = "data")]
    pub(crate) scenario: Option<String>,
    /// Your own preoperative liver instead of a dataset: a tet mesh (.vtu .vtk .msh; labelled
    /// from its `region`/`falciform`/`inferior_ridge` point arrays when present, else from its
    /// geometry, LPS frame) or a closed surface (.obj .stl .vtp .vtk), meshed at --edge-mm.
    #[arg(long, conflicts_with_all = ["data", "scenario"], requires = "surface")]
    pub(crate) preop: Option<PathBuf>,
    /// With --preop: anterior-surface points (physical frame; .vtp .vtk .csv .txt .xyz).
    #[arg(long)]
    pub(crate) surface: Option<PathBuf>,
    /// With --preop: ultrasound posterior-contour points (repeatable, one file per plane or all).
    #[arg(long)]
    pub(crate) ultrasound: Vec<PathBuf>,
    /// With --preop: ultrasound vessel-feature points (repeatable).
    #[arg(long)]
    pub(crate) vessel_points: Vec<PathBuf>,
    /// With --preop: the navigation system's coarse alignment image → physical, a JSON file
    /// `{"rotation": [[r00, r01, r02], [r10, ...], [...]], "translation": [tx, ty, tz]}` (in --unit);
    /// default identity (points already near the preoperative model).
    #[arg(long)]
    pub(crate) initial_alignment: Option<PathBuf>,
    /// With --preop: length unit of the mesh and point files (mm, cm or m).
    #[arg(long, default_value = "mm")]
    pub(crate) unit: Unit,
    /// With --preop and a surface file: tet edge length (mm).
    #[arg(long, default_value_t = 7.6)]
    pub(crate) edge_mm: f64,
    /// auto (chosen per registration from the data among doing nothing, rigid, LIBR and
    /// adaptive LIBR, and their held variants with a trusted start), rigid (wICP), libr (wICP
    /// then LIBR), adaptive (wICP then adaptive LIBR), librplus (LIBR then the SR-GCN
    /// correction) or v2s (wICP then the V2S network).
    #[arg(long, default_value = "auto")]
    pub(crate) method: MethodArg,
    /// SR-GCN model directory (from `librplus train`) or ensemble directory (from `librplus
    /// ensemble`) for --method librplus (default: the built-in model); a V2S model directory
    /// (from `librplus train --method v2s`) for --method v2s (default: the built-in V2S model).
    #[arg(long)]
    pub(crate) model: Option<PathBuf>,
    /// Write the preoperative mesh with the registered `displacement` (image frame), the
    /// per-node `error_mm` against the ground truth (a dataset scenario) and the estimate's
    /// per-node `uncertainty_mm` (its 90 % bound, without the truth) (.vtu).
    #[arg(long)]
    pub(crate) out: Option<PathBuf>,
    /// Where the LIBR basis is cached (default DATA/cache).
    #[arg(long)]
    pub(crate) cache: Option<PathBuf>,
    /// An augmented model (`physics.json`, e.g. from `librplus discover`): LIBR's model carries
    /// its effects (supports, loads, inclusions); the basis is built and cached per physics.
    #[arg(long)]
    pub(crate) physics: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub(crate) json: bool,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}

#[derive(Args)]
pub(crate) struct BenchRegisterArgs {
    /// Dataset directory (from `librplus generate`). Default: the `small` preset (seed 1)
    /// generated from --surface into a temporary directory, so the benchmark runs anywhere.
    #[arg(long)]
    pub(crate) data: Option<PathBuf>,
    /// A tet mesh instead of a dataset: only the LIBR basis preload is measured (a bare mesh has
    /// no anatomical labels, so no correspondence and no registrations).
    #[arg(long, conflicts_with_all = ["data", "geometry"])]
    pub(crate) mesh: Option<PathBuf>,
    /// Closed liver surface for the default dataset (default: the built-in SOFA liver).
    #[arg(long)]
    pub(crate) surface: Option<PathBuf>,
    /// Geometry id of the dataset (default: the first).
    #[arg(long)]
    pub(crate) geometry: Option<String>,
    /// Registrations to time, taken evenly across the five measurement categories.
    #[arg(long, default_value_t = 50)]
    pub(crate) scenarios: usize,
    /// Threads of the pool the registrations run in, one after another (1: single-registration
    /// latency on one core, the surgical metric). The preload uses every core.
    #[arg(long, default_value_t = 1)]
    pub(crate) threads: usize,
    /// rigid (wICP), libr (wICP then LIBR), adaptive (wICP then adaptive LIBR), auto (the
    /// model chosen per registration), librplus (LIBR then the SR-GCN correction) or v2s.
    #[arg(long, default_value = "libr")]
    pub(crate) method: MethodArg,
    /// SR-GCN model or ensemble directory for --method librplus (default: the built-in model);
    /// V2S model directory for --method v2s (default: the built-in V2S model).
    #[arg(long)]
    pub(crate) model: Option<PathBuf>,
    /// An augmented model (`physics.json`): LIBR's basis carries its effects.
    #[arg(long, value_name = "FILE")]
    pub(crate) physics: Option<PathBuf>,
    /// Answer in two where the pose search follows (the navigation start's fit first, flagged
    /// provisional, then the searched answer): times the first answer as well as the whole.
    #[arg(long)]
    pub(crate) progressive: bool,
    /// Register with a LIBR basis built on the case's boundary meshed again with tets of this
    /// edge (mm) and carried to its nodes, as a large case answers while its own basis builds;
    /// its build time is reported (with --mesh: that alone)
    #[arg(long, value_name = "MM")]
    pub(crate) coarse_edge_mm: Option<f64>,
    #[command(flatten)]
    pub(crate) common: Common,
    // Last: `--help` shows these under their own heading, after the command's own options.
    #[command(flatten)]
    pub(crate) libr: LibrOpts,
}

/// `train --validation`.
#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum ValidationArg {
    Deformations,
    Geometry,
}

impl ValidationArg {
    pub(crate) fn get(self) -> librplus::eval::train::Validation {
        match self {
            ValidationArg::Deformations => librplus::eval::train::Validation::Deformations,
            ValidationArg::Geometry => librplus::eval::train::Validation::Geometry,
        }
    }
}

/// `train --schedule`.
#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum ScheduleArg {
    Plateau,
    Cosine,
}

impl ScheduleArg {
    pub(crate) fn get(self) -> librplus::eval::train::Schedule {
        match self {
            ScheduleArg::Plateau => librplus::eval::train::Schedule::Plateau,
            ScheduleArg::Cosine => librplus::eval::train::Schedule::Cosine,
        }
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum MethodArg {
    /// Salient-feature weighted rigid ICP.
    Rigid,
    /// wICP, then LIBR.
    Libr,
    /// wICP, LIBR, then the SR-GCN correction (--model, or the built-in model).
    Librplus,
    /// wICP, then the V2S network's displacement (--v2s-model, or the built-in one).
    V2s,
    /// wICP, then adaptive LIBR (control loads resolved where the data are, the prior's
    /// strength chosen by the data).
    Adaptive,
    /// The method chosen per registration from the data: doing nothing, rigid, LIBR, adaptive
    /// LIBR and (with a trusted start) their held variants, each scored by how well it predicts
    /// the points it did not see.
    Auto,
    /// wICP, adaptive LIBR, then the nonlinear refinement: the same loads fitted again through
    /// the case's Neo-Hookean model (the linear answer kept unless the refinement fits better).
    Nonlinear,
}

#[derive(Subcommand)]
pub(crate) enum PhantomCmd {
    /// For each pattern and seed: the gap between the ground truth and the linear homogeneous
    /// model under the same loads and supports, and what contributes (heterogeneity, nonlinear
    /// material and geometry, unilateral bed contact; gravity vs the pattern's own load).
    Effect {
        /// Closed liver surface (LPS). Default: the built-in SOFA liver (largest piece).
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
pub(crate) struct GenerateArgs {
    /// small (CI-sized: 2 coarse geometries, 3 deformations, 10 scenarios each) or paper (3 training
    /// geometries × L, R, W plus a 4th with V, 700 scenarios each, ~9,000-node meshes).
    #[arg(long, default_value = "small")]
    pub(crate) preset: PresetArg,
    /// Output directory (created; an interrupted run resumes into it).
    #[arg(long)]
    pub(crate) out: PathBuf,
    /// Master seed.
    #[arg(long, default_value_t = 0)]
    pub(crate) seed: u64,
    /// Do the i-th of N shares of the deformations (`--shard 0/4`); run once more without
    /// `--shard` (it skips finished work) to write the complete manifest.
    #[arg(long)]
    pub(crate) shard: Option<String>,
    /// Closed liver surface(s) in LPS (repeatable); geometries cycle through them, then through
    /// seeded shape variants. Default: the built-in SOFA liver (largest component).
    #[arg(long)]
    pub(crate) surface: Vec<PathBuf>,
    /// Override: number of geometries (the last one is the held-out V geometry).
    #[arg(long)]
    pub(crate) geometries: Option<usize>,
    /// Override: deformations per geometry and pattern.
    #[arg(long)]
    pub(crate) deformations: Option<usize>,
    /// Override: scenarios per deformation.
    #[arg(long)]
    pub(crate) scenarios: Option<usize>,
    /// Override: the patterns of the training geometries, comma-separated from L, R, W (the
    /// paper's, the default), X (random packs anywhere on the surface: a training augmentation,
    /// not in the paper) and V (a diagnostic: the held-out geometry's pattern seen in training, so
    /// that pattern-v measures an unseen liver alone). The held-out geometry keeps V only.
    #[arg(long, value_delimiter = ',')]
    pub(crate) patterns: Vec<String>,
    /// Override: mesher target edge length (mm).
    #[arg(long)]
    pub(crate) edge_mm: Option<f64>,
    /// Override: the typical spacing of the simulated laparoscope's surface points (mm; default
    /// 5): 2.5 gives a navigation system's few thousand points, 0.8 a stereo camera's dense
    /// cloud of tens of thousands.
    #[arg(long, value_name = "MM")]
    pub(crate) surface_spacing_mm: Option<f64>,
    /// Ground-truth physics: nonlinear (heterogeneous Neo-Hookean with unilateral bed contact),
    /// linear (the linear homogeneous model LIBR assumes, same loads: a control dataset) or libr
    /// (LIBR's own free-floating model under the pattern's surface load, plus --hidden-effect).
    #[arg(long, value_enum, default_value = "nonlinear")]
    pub(crate) truth: TruthArg,
    /// An effect hidden in a `--truth libr` ground truth (repeatable): KIND[:key=value,...] with
    /// KIND gravity, bed-support, fixation, pressure, pack, ligament or inclusion and vectors as
    /// x/y/z (e.g. `gravity`, `fixation:radius_mm=25`); parameters not given are drawn per
    /// deformation (docs/hidden-effects.md).
    #[arg(long = "hidden-effect", value_name = "KIND[:key=value,...]")]
    pub(crate) hidden_effect: Vec<String>,
    /// With --hidden-effect: do not record each deformation's oracle detectability (whether the
    /// discovery workflow's own test sees the hidden effects when told the truth; it registers
    /// every scenario twice). Recorded by default, after generation, when not sharded.
    #[arg(long)]
    pub(crate) no_detectability: bool,
    /// Truth families the deformations cycle through (nonlinear truth only): `all` or a
    /// comma-separated list of neo-hookean, mooney-rivlin, demiray, stiff-vessels, sparse-sensor,
    /// dense-sensor (docs/dataset-and-models.md); recorded per
    /// deformation as `truth_family`, so `--split family:NAME` can hold one out of training.
    #[arg(long, value_name = "all|NAME,...")]
    pub(crate) families: Option<String>,
    /// Multiplies every pattern's load magnitudes (the left lobe's lift, pack forces, pressures,
    /// a held organ's tool depth; not gravity), e.g. 1.5 for larger deformations, where the
    /// linear model's error shows (default 1)
    #[arg(long, value_name = "X")]
    pub(crate) load_scale: Option<f64>,
    /// The five scenarios of each block (one per category) share the surface patch, noise,
    /// misalignment and landmarks and differ only in their ultrasound planes, so the categories
    /// are compared on the same draws (off by default: every scenario is drawn on its own).
    #[arg(long)]
    pub(crate) paired_categories: bool,
    /// Harder navigation starts: each scenario's start (the landmark fit; a held organ's, the
    /// true alignment) moved further by a random rotation of up to DEG degrees about the organ's
    /// centroid and a shift of up to MM mm, e.g. `30,30` (a draw of its own: the rest of the
    /// dataset stays as without it)
    #[arg(long, value_delimiter = ',', value_name = "DEG,MM", num_args = 1)]
    pub(crate) start_error: Option<Vec<f64>>,
    /// The side whose surface the laparoscope sees: anterior (the labelled anterior surface,
    /// the default), posterior, dome, left, right (the half of the boundary facing that way), or
    /// any (a direction drawn per scenario)
    #[arg(long, value_name = "SIDE")]
    pub(crate) visible: Option<String>,
    #[command(flatten)]
    pub(crate) common: Common,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum TruthArg {
    /// Heterogeneous compressible Neo-Hookean, unilateral bed contact.
    Nonlinear,
    /// Linear homogeneous elasticity, bilateral bed springs.
    Linear,
    /// LIBR's own physics (free-floating, surface load only) plus the hidden effects.
    Libr,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum PresetArg {
    /// CI-sized.
    Small,
    /// The paper's design.
    Paper,
}

#[derive(Args, Clone)]
pub(crate) struct Common {
    /// Length unit of input files (mm, cm or m); meshes are held in millimetres.
    #[arg(long, default_value = "mm")]
    pub(crate) unit: Unit,
    /// Print one JSON object on stdout instead of human-readable text.
    #[arg(long)]
    pub(crate) json: bool,
}

#[derive(Subcommand)]
pub(crate) enum MeshCmd {
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
pub(crate) enum FemCmd {
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
pub(crate) enum ModelArg {
    /// Linear elasticity.
    Linear,
    /// Compressible Neo-Hookean, total Lagrangian, Newton with line search and load stepping.
    NeoHookean,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub(crate) enum OrderingArg {
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
pub(crate) enum BenchCmd {
    /// Whole registration pipeline: the case preload (LIBR basis built cold, then read from its
    /// cache) and single-registration latency with stage timings over scenarios spread across
    /// the measurement categories.
    Register(Box<BenchRegisterArgs>),
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
