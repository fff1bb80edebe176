//! SR-GCN training and LIBR+ inference on a dataset.
//!
//! **Splits** ([`TrainSplit`]), over the dataset's training geometries (pattern V stays unseen
//! except as the `pattern-v` test): `random` (blocks of five consecutive scenarios, one per
//! measurement category, shuffled by the seed; 80 % train, 20 % test), `geo-def` (three whole
//! geometry–pattern deformations held out: the first geometry's first two patterns and the last
//! geometry's third, as the paper's 1-L, 1-R, 3-W), `logo:G` (every deformation of geometry G held
//! out) and `pattern-v` (train on every training deformation, test on the test geometry). A
//! seeded 10 % of the training blocks is kept for validation (early stopping).
//!
//! **Inputs** come from LIBR run on each scenario's measurements (never from the ground truth;
//! the truth only makes the training targets). LIBR solutions are cached under
//! `DATA/cache/libr-solutions/KEY/` (KEY hashes the registration parameters) so retraining or a
//! second split does not rerun LIBR.
//!
//! **Two stages** (the paper's): stage 1 trains the bipartite branch on reconstructing its input
//! (`L_b`); stage 2 freezes it and trains the mesh branch on `L_residual + λ L_sparse` (or `L_gt`
//! in the ablations). Adam; the learning rate either halves when validation stalls, with early
//! stopping ([`Schedule::Plateau`]), or anneals on a cosine over the epoch and time budget
//! ([`Schedule::Cosine`]); the epoch with the best validation node error (mm) is kept.

use super::GcnError;
use super::io::{TrainedModel, save_model};
use super::model::{Loss, MeshGraphs, SrGcn, SrGcnConfig, Target};
use super::sample::{CaseFrame, PositionJitter, SampleData};
use crate::dataset::Manifest;
use crate::dataset::read::{GeometryData, ScenarioData, load_geometry};
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::CorrespondenceParams;
use crate::register::libr;
use crate::register::pipeline::{Method, PipelineParams, Prepared, register};
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Scenarios per block (one per measurement category).
const BLOCK: usize = 5;

/// A train/test split of a dataset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TrainSplit {
    /// Random blocks of scenarios of the training deformations.
    Random,
    /// Whole geometry–pattern deformations held out.
    GeoDef,
    /// Every deformation of one geometry held out.
    Logo(String),
    /// Train on the training deformations, test on the test geometry (pattern V).
    PatternV,
}

impl TrainSplit {
    /// Parses `random`, `geo-def`, `logo:G`, `pattern-v`.
    pub fn parse(s: &str) -> Result<Self, String> {
        match s {
            "random" => Ok(Self::Random),
            "geo-def" => Ok(Self::GeoDef),
            "pattern-v" => Ok(Self::PatternV),
            _ => match s.strip_prefix("logo:") {
                Some(g) if !g.is_empty() => Ok(Self::Logo(g.to_string())),
                _ => Err(format!(
                    "unknown split {s:?}: expected random, geo-def, logo:GEOMETRY or pattern-v"
                )),
            },
        }
    }

    /// Name as parsed.
    pub fn name(&self) -> String {
        match self {
            Self::Random => "random".into(),
            Self::GeoDef => "geo-def".into(),
            Self::Logo(g) => format!("logo:{g}"),
            Self::PatternV => "pattern-v".into(),
        }
    }
}

/// A scenario: deformation id and scenario index.
pub type ScenarioRef = (String, usize);

/// The scenarios of a split.
#[derive(Debug, Clone, Default)]
pub struct SplitSets {
    /// Training scenarios.
    pub train: Vec<ScenarioRef>,
    /// Validation scenarios (from the training deformations).
    pub valid: Vec<ScenarioRef>,
    /// Test scenarios.
    pub test: Vec<ScenarioRef>,
}

/// SplitMix64: a small seeded generator for shuffles.
fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E3779B97F4A7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
    z ^ (z >> 31)
}

fn shuffle<T>(v: &mut [T], seed: u64) {
    let mut s = seed;
    for i in (1..v.len()).rev() {
        let j = (splitmix(&mut s) % (i as u64 + 1)) as usize;
        v.swap(i, j);
    }
}

/// What the validation set holds out of the training scenarios.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Validation {
    /// Whole training deformations (about one in ten, by the seed) where the test holds out
    /// whole deformations or livers; a tenth of the blocks on the random split.
    #[default]
    Deformations,
    /// One whole training liver (by the seed), all its deformations: validation then judges
    /// what the test of an unseen liver judges, generalisation to a new shape, at the price of
    /// that liver's training data. Needs at least three training livers.
    Geometry,
}

impl Validation {
    /// The name used on the command line and in provenance files.
    pub fn name(self) -> &'static str {
        match self {
            Validation::Deformations => "deformations",
            Validation::Geometry => "geometry",
        }
    }
}

/// Assigns scenarios to train, validation and test. `every`: keep every `every`-th block of
/// each deformation (1 = all). `validation`: what validation holds out of the training
/// scenarios (the test set does not depend on it).
pub fn split_scenarios(
    m: &Manifest,
    split: &TrainSplit,
    seed: u64,
    every: usize,
    validation: Validation,
) -> Result<SplitSets, String> {
    let every = every.max(1);
    let test_geos = m.test_geometries();
    let train_defs: Vec<_> = m
        .deformations
        .iter()
        .filter(|d| !test_geos.contains(&d.geometry.as_str()))
        .collect();
    let mut geos: Vec<&str> = train_defs.iter().map(|d| d.geometry.as_str()).collect();
    geos.dedup();
    let mut pats: Vec<&str> = train_defs.iter().map(|d| d.pattern.as_str()).collect();
    pats.sort();
    pats.dedup();
    let blocks = |d: &crate::dataset::DeformationEntry| -> Vec<Vec<ScenarioRef>> {
        (0..d.scenarios.len().div_ceil(BLOCK))
            .filter(|b| b % every == 0)
            .map(|b| {
                (b * BLOCK..((b + 1) * BLOCK).min(d.scenarios.len()))
                    .map(|i| (d.id.clone(), i))
                    .collect()
            })
            .collect()
    };
    let geometry_of: std::collections::HashMap<&str, &str> = m
        .deformations
        .iter()
        .map(|d| (d.id.as_str(), d.geometry.as_str()))
        .collect();
    let mut train_blocks = Vec::new();
    let mut test = Vec::new();
    match split {
        TrainSplit::Random => {
            let mut all: Vec<Vec<ScenarioRef>> =
                train_defs.iter().flat_map(|d| blocks(d)).collect();
            shuffle(&mut all, seed ^ 0x5EED);
            let n_test = (all.len() / 5).max(1).min(all.len().saturating_sub(2));
            for (i, b) in all.into_iter().enumerate() {
                if i < n_test {
                    test.extend(b);
                } else {
                    train_blocks.push(b);
                }
            }
        }
        TrainSplit::GeoDef | TrainSplit::Logo(_) => {
            if let TrainSplit::Logo(g) = split
                && !geos.contains(&g.as_str())
            {
                return Err(format!(
                    "logo:{g}: no training geometry {g} (have {})",
                    geos.join(", ")
                ));
            }
            if matches!(split, TrainSplit::GeoDef) && (geos.len() < 2 || pats.len() < 3) {
                return Err("geo-def needs at least 2 geometries and 3 patterns".into());
            }
            for d in &train_defs {
                let held = match split {
                    TrainSplit::Logo(g) => &d.geometry == g,
                    _ => {
                        let gi = geos.iter().position(|g| *g == d.geometry).unwrap_or(0);
                        let pi = pats.iter().position(|p| *p == d.pattern).unwrap_or(0);
                        (gi == 0 && pi < 2) || (gi == geos.len() - 1 && pi == 2)
                    }
                };
                for b in blocks(d) {
                    if held {
                        test.extend(b);
                    } else {
                        train_blocks.push(b);
                    }
                }
            }
        }
        TrainSplit::PatternV => {
            if test_geos.is_empty() {
                return Err("pattern-v: the dataset has no test geometry".into());
            }
            for d in &m.deformations {
                for b in blocks(d) {
                    if test_geos.contains(&d.geometry.as_str()) {
                        test.extend(b);
                    } else {
                        train_blocks.push(b);
                    }
                }
            }
        }
    }
    shuffle(&mut train_blocks, seed ^ 0xA11D);
    let mut sets = SplitSets {
        test,
        ..Default::default()
    };
    // Validation is like the test: where the test holds out whole deformations, validation is
    // whole training deformations (about one in ten, at least one, chosen by the seed), so early
    // stopping and the learning-rate schedule judge generalisation to unseen deformations, not
    // memorisation of seen ones.
    let mut defs: Vec<&str> = train_blocks
        .iter()
        .filter_map(|b| b.first().map(|r| r.0.as_str()))
        .collect();
    defs.sort();
    defs.dedup();
    let held_out_valid = !matches!(split, TrainSplit::Random) && defs.len() >= 3;
    if validation == Validation::Geometry {
        // The livers left for training, in manifest order, one drawn by the seed.
        let mut livers: Vec<&str> = Vec::new();
        for b in &train_blocks {
            if let Some(g) = b.first().and_then(|r| geometry_of.get(r.0.as_str())) {
                if !livers.contains(g) {
                    livers.push(g);
                }
            }
        }
        livers.sort();
        if livers.len() < 3 {
            return Err(format!(
                "validation by geometry needs at least 3 training livers, split {} leaves {}",
                split.name(),
                livers.len()
            ));
        }
        let mut st = seed ^ 0x6E0;
        let held = livers[(splitmix(&mut st) % livers.len() as u64) as usize];
        for b in train_blocks {
            if b.first()
                .and_then(|r| geometry_of.get(r.0.as_str()))
                .is_some_and(|g| *g == held)
            {
                sets.valid.extend(b);
            } else {
                sets.train.extend(b);
            }
        }
    } else if held_out_valid {
        // Drawn without replacement.
        let mut st = seed ^ 0xDEF0;
        let mut pool = defs;
        let mut held = Vec::new();
        for _ in 0..validation_deformations(pool.len()) {
            let k = (splitmix(&mut st) % pool.len() as u64) as usize;
            held.push(pool.remove(k).to_string());
        }
        for b in train_blocks {
            if b.first().is_some_and(|r| held.contains(&r.0)) {
                sets.valid.extend(b);
            } else {
                sets.train.extend(b);
            }
        }
    } else {
        let n_valid = (train_blocks.len() / 10)
            .max(1)
            .min(train_blocks.len().saturating_sub(1));
        for (i, b) in train_blocks.into_iter().enumerate() {
            if i < n_valid {
                sets.valid.extend(b);
            } else {
                sets.train.extend(b);
            }
        }
    }
    sets.train.sort();
    sets.valid.sort();
    sets.test.sort();
    if sets.train.is_empty() || sets.test.is_empty() {
        return Err(format!(
            "split {} leaves no training or no test scenarios",
            split.name()
        ));
    }
    Ok(sets)
}

/// How many of `n` training deformations validate on held-out-deformation splits: about one in
/// ten, at least one.
pub fn validation_deformations(n: usize) -> usize {
    n.div_ceil(10).max(1).min(n.saturating_sub(1))
}

/// A LIBR solution of one scenario (what LIBR+ starts from).
#[derive(Debug, Clone)]
pub struct LibrSolution {
    /// Image → physical transform.
    pub transform: Rigid,
    /// Node displacements (image frame).
    pub u: Vec<f64>,
}

/// Key of the LIBR solution cache: the registration parameters.
pub fn solution_key(params: &PipelineParams) -> String {
    let text = format!("{:?}|{:?}", params.wicp, params.libr);
    crate::dataset::fnv1a_hex(text.as_bytes())
}

fn encode_solution(s: &Option<LibrSolution>) -> Vec<u8> {
    let mut b = b"LIBRSOL1".to_vec();
    match s {
        None => b.push(0),
        Some(s) => {
            b.push(1);
            for row in s.transform.rotation {
                for v in row {
                    b.extend(v.to_le_bytes());
                }
            }
            for v in s.transform.translation {
                b.extend(v.to_le_bytes());
            }
            b.extend((s.u.len() as u64).to_le_bytes());
            for v in &s.u {
                b.extend(v.to_le_bytes());
            }
        }
    }
    b
}

fn decode_solution(b: &[u8], n3: usize) -> Option<Option<LibrSolution>> {
    let rd = |i: usize| {
        b.get(i..i + 8)
            .map(|s| f64::from_le_bytes(s.try_into().expect("8")))
    };
    if b.get(..8)? != b"LIBRSOL1" {
        return None;
    }
    match *b.get(8)? {
        0 => Some(None),
        1 => {
            let mut rotation = [[0.0; 3]; 3];
            for (k, r) in rotation.iter_mut().flatten().enumerate() {
                *r = rd(9 + 8 * k)?;
            }
            let translation = [rd(81)?, rd(89)?, rd(97)?];
            let n = u64::from_le_bytes(b.get(105..113)?.try_into().ok()?) as usize;
            if n != n3 || b.len() != 113 + 8 * n {
                return None;
            }
            let u = (0..n)
                .map(|i| rd(113 + 8 * i))
                .collect::<Option<Vec<f64>>>()?;
            Some(Some(LibrSolution {
                transform: Rigid {
                    rotation,
                    translation,
                },
                u,
            }))
        }
        _ => None,
    }
}

/// One geometry's registration case and SR-GCN frame.
pub struct GeometryCase {
    /// The geometry (model, surface flags, targets).
    pub geo: GeometryData,
    /// Its prepared registration case (with the LIBR basis).
    pub case: Prepared,
    /// Its SR-GCN frame and mesh graph.
    pub frame: CaseFrame,
}

/// Loads (or builds and caches) the registration case of every geometry named.
pub fn load_cases(
    dir: &Path,
    m: &Manifest,
    geometries: &[String],
    params: &PipelineParams,
) -> Result<BTreeMap<String, GeometryCase>, String> {
    let mut out = BTreeMap::new();
    for g in geometries {
        if out.contains_key(g) {
            continue;
        }
        let geo = load_geometry(dir, m, g)?;
        let case = Prepared::new(
            geo.model.clone(),
            Some(&params.libr),
            Some(&dir.join("cache")),
        )?;
        let frame = CaseFrame::new(&geo.model.mesh).map_err(|e| e.to_string())?;
        out.insert(g.clone(), GeometryCase { geo, case, frame });
    }
    Ok(out)
}

/// LIBR solutions of scenarios (None where LIBR failed), from the cache or computed (in parallel)
/// and cached. `progress(done, total)` is called as they come.
pub fn libr_solutions(
    dir: &Path,
    cases: &BTreeMap<String, GeometryCase>,
    scenarios: &[(&ScenarioData, &str)],
    params: &PipelineParams,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Option<LibrSolution>>, String> {
    let root = dir
        .join("cache")
        .join("libr-solutions")
        .join(solution_key(params));
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = scenarios.len();
    scenarios
        .par_iter()
        .map(|(sc, geometry)| {
            let gc = cases
                .get(*geometry)
                .ok_or_else(|| format!("no case for geometry {geometry}"))?;
            let n3 = 3 * gc.geo.model.mesh.num_nodes();
            let path = root.join(format!("{}.bin", sc.id.replace('/', "__")));
            let cached = std::fs::read(&path)
                .ok()
                .and_then(|b| decode_solution(&b, n3));
            let sol = match cached {
                Some(s) => s,
                None => {
                    let s = register(&gc.case, &sc.measurements, Method::Libr, params)
                        .ok()
                        .map(|r| LibrSolution {
                            transform: r.image_to_physical,
                            u: r.u,
                        });
                    crate::util::write_atomic(&path, &encode_solution(&s))?;
                    s
                }
            };
            progress(
                done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1,
                total,
            );
            Ok(sol)
        })
        .collect()
}

/// True node positions (physical frame) of a scenario.
pub fn truth_positions(geo: &GeometryData, sc: &ScenarioData) -> Vec<[f64; 3]> {
    let t = &sc.truth;
    geo.model
        .mesh
        .nodes()
        .iter()
        .enumerate()
        .map(|(i, x)| {
            t.image_to_physical
                .apply([0, 1, 2].map(|a| x[a] + t.displacement[3 * i + a]))
        })
        .collect()
}

/// The correspondence parameters LIBR ends with (what the sparse loss re-matches with).
pub fn final_cparams(params: &PipelineParams) -> CorrespondenceParams {
    params.libr_correspondence()
}

/// Training settings.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// Network configuration.
    pub config: SrGcnConfig,
    /// Split.
    pub split: TrainSplit,
    /// Keep every `every`-th block of scenarios.
    pub every: usize,
    /// Seed (split, initialisation, sample order).
    pub seed: u64,
    /// Stage-1 epochs (bipartite branch).
    pub epochs_bipartite: usize,
    /// Stage-2 epochs at most (mesh branch).
    pub epochs: usize,
    /// Initial learning rate.
    pub learning_rate: f64,
    /// Epochs without validation improvement before stopping ([`Schedule::Plateau`] only).
    pub patience: usize,
    /// How the stage-2 learning rate changes.
    pub schedule: Schedule,
    /// Train through LIBR+'s refit: the node loss (and validation) scores what the refit,
    /// linearised at each sample's LIBR solution ([`RefitLoss`]), makes of the correction, so
    /// the network learns what the refit will not put back instead of what it will
    /// overwrite. The samples must carry their [`RefitLoss`] ([`build_samples`]).
    pub refit_loss: bool,
    /// Validate and keep an exponential moving average of the stage-2 weights instead of the
    /// weights themselves, over a horizon of this many epochs (decay `1 − 1/(h·steps)` per
    /// step, warmed up over the first steps so the start does not weigh on it; 0 turns it
    /// off). The average smooths the last steps' noise, which a single validation set would
    /// otherwise pick from.
    pub average_epochs: f64,
    /// L2 penalty on the stage-2 weights, added to their gradients before Adam (0: none).
    pub weight_decay: f64,
    /// Strength of a random affine jitter of the normalised position inputs, drawn afresh for
    /// every training step ([`super::sample::PositionJitter`]; validation is never jittered).
    /// 0: none.
    pub position_jitter: f64,
    /// Stage 2 stops before an epoch that would end past this many minutes of training (judged
    /// by the last epoch's duration).
    pub max_minutes: f64,
    /// A model directory whose weights training starts from instead of a seeded initialisation
    /// (its configuration must be `config`'s network). With 0 stage-2 epochs the model is only
    /// validated (and its correction scale fitted again).
    pub init: Option<PathBuf>,
}

impl Default for TrainOptions {
    fn default() -> Self {
        Self {
            config: SrGcnConfig::new(),
            split: TrainSplit::PatternV,
            every: 2,
            seed: 1,
            epochs_bipartite: 2,
            epochs: 12,
            learning_rate: 2e-3,
            patience: 3,
            schedule: Schedule::Plateau,
            refit_loss: false,
            average_epochs: 0.0,
            weight_decay: 0.0,
            position_jitter: 0.0,
            init: None,
            max_minutes: 25.0,
        }
    }
}

/// The stage-2 learning-rate schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Schedule {
    /// Halve the rate after every epoch whose validation error is not the best so far; stop
    /// after `patience` such epochs in a row.
    #[default]
    Plateau,
    /// Cosine annealing over the whole budget, step by step: `lr₀·½(1 + cos πp)`, where `p` is
    /// the larger of the fraction of epochs done and the fraction of `max_minutes` spent, so the
    /// rate reaches its low end whichever limit ends training. No early stop: the best
    /// validation epoch is kept.
    Cosine,
}

impl Schedule {
    /// The rate at budget fraction `p` (clamped to [0, 1]) from the initial rate `lr0`; the
    /// plateau schedule's rate is set by its epochs, so it returns `lr0`.
    pub fn rate(self, lr0: f64, p: f64) -> f64 {
        match self {
            Schedule::Plateau => lr0,
            Schedule::Cosine => {
                lr0 * 0.5 * (1.0 + (std::f64::consts::PI * p.clamp(0.0, 1.0)).cos())
            }
        }
    }
}

/// One epoch's figures.
#[derive(Debug, Clone, serde::Serialize)]
pub struct EpochLog {
    /// Stage (1 bipartite, 2 mesh).
    pub stage: u32,
    /// Epoch within the stage (from 1).
    pub epoch: usize,
    /// Mean training loss.
    pub train_loss: f64,
    /// Validation: mean node error after correction (mm) in stage 2, loss in stage 1.
    pub valid: f64,
    /// Learning rate used.
    pub learning_rate: f64,
    /// Wall time since the start (s).
    pub seconds: f64,
}

/// A prepared sample: its geometry and host data.
pub struct Prepared2 {
    /// Geometry id.
    pub geometry: String,
    /// Inputs and targets.
    pub data: SampleData,
    /// The linearised refit at LIBR's solution, when training through it.
    pub refit: Option<RefitLoss>,
}

/// LIBR+'s refit linearised at a sample's LIBR solution ([`libr::linearised_refit`]), for
/// training through it ([`TrainOptions::refit_loss`]): what the pipeline answers for a correction
/// `y` (output units) is, to first order, `y + step0 − G·K·Gᵀ·Dᵀ·D·y`, with `G` the geometry's
/// [`libr::LinearRefit::modes`] about its frame's centre.
pub struct RefitLoss {
    /// `D` (rows × 3V).
    pub d: super::sparse::Csr,
    /// `K` (p × p, row-major).
    pub gain: Vec<f32>,
    /// The refit's move of LIBR's own shape, `[V, 3]` in output units.
    pub step0: Vec<f32>,
}

/// The [`RefitLoss`] of one LIBR solution: the refit's first step from it, with the matches the
/// refit would make there.
pub fn refit_loss_data(
    gc: &GeometryCase,
    meas: &crate::register::Measurements,
    sol: &LibrSolution,
    params: &PipelineParams,
) -> Result<RefitLoss, String> {
    let basis = gc
        .case
        .basis
        .as_ref()
        .ok_or("the case was prepared without a LIBR basis")?;
    let inv = sol.transform.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&p| inv.apply(p)).collect();
    let (matches, _) =
        gc.case
            .correspondence
            .match_points(&pts, meas, Some(&sol.u), &final_cparams(params))?;
    let mesh = &gc.geo.model.mesh;
    let lin = libr::linearised_refit(
        basis,
        mesh,
        &matches,
        &pts,
        &sol.u,
        gc.frame.center,
        &params.libr,
    )?;
    let trip: Vec<(usize, usize, f32)> = lin.d.iter().map(|&(r, c, v)| (r, c, v as f32)).collect();
    let unit = gc.frame.unit_mm();
    Ok(RefitLoss {
        d: super::sparse::Csr::from_triplets(lin.rows, 3 * mesh.num_nodes(), &trip)
            .map_err(|e| e.to_string())?,
        gain: lin.gain.iter().map(|&x| x as f32).collect(),
        step0: lin.step0.iter().map(|&x| (x / unit) as f32).collect(),
    })
}

/// The geometry's refit modes `G` (`[3V, p]`) on a device.
fn refit_modes(gc: &GeometryCase, device: &Device) -> Result<Tensor<2>, String> {
    let basis = gc
        .case
        .basis
        .as_ref()
        .ok_or("the case was prepared without a LIBR basis")?;
    let g = libr::LinearRefit::modes(basis, &gc.geo.model.mesh, gc.frame.center);
    let p = basis.columns() + 6;
    let rows = g.len() / p;
    Ok(Tensor::<2>::from_data(
        TensorData::new(
            g.into_iter().map(|x| x as f32).collect::<Vec<_>>(),
            [rows, p],
        ),
        device,
    ))
}

/// What the pipeline answers, to first order, for the correction `y` (`[V, 3]` row-major,
/// output units) of a sample of geometry `gc` with linearised refit `r`: the displacement from
/// LIBR's shape, in LIBR's image frame and output units.
pub fn answer_through_refit(
    gc: &GeometryCase,
    r: &RefitLoss,
    y: &[f32],
) -> Result<Vec<f32>, String> {
    let device = super::device::compute();
    let g = refit_modes(gc, &device)?;
    let v = y.len() / 3;
    through_refit(tensor2(y, v, &device), r, &g, &device)
        .map_err(|e| e.to_string())?
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .map_err(|e| format!("{e:?}"))
}

/// What the pipeline answers for the correction `y` (`[V, 3]`, output units) through the
/// linearised refit `r` with the geometry's modes `g`.
fn through_refit(
    y: Tensor<2>,
    r: &RefitLoss,
    g: &Tensor<2>,
    device: &Device,
) -> Result<Tensor<2>, GcnError> {
    let [v, _] = y.dims();
    let p = g.dims()[1];
    if r.d.cols != 3 * v || g.dims()[0] != 3 * v || r.gain.len() != p * p || r.step0.len() != 3 * v
    {
        return Err(GcnError::Invalid(format!(
            "the linearised refit does not fit a {v}-node prediction"
        )));
    }
    let z = super::sparse::SparseOp::new(r.d.clone()).apply(y.clone().reshape([3 * v, 1]))?;
    let w = super::sparse::SparseOp::new(r.d.transpose()).apply(z)?;
    let gw = g.clone().transpose().matmul(w);
    let k = Tensor::<2>::from_data(TensorData::new(r.gain.clone(), [p, p]), device);
    let change = g.clone().matmul(k.matmul(gw)).reshape([v, 3]);
    Ok(y - change + tensor2(&r.step0, v, device))
}

/// Builds the SR-GCN samples of scenarios whose LIBR succeeded (with targets from the truth).
pub fn build_samples(
    cfg: &SrGcnConfig,
    cases: &BTreeMap<String, GeometryCase>,
    items: &[(&ScenarioData, &str, &Option<LibrSolution>)],
    params: &PipelineParams,
    with_truth: bool,
    refit_loss: bool,
) -> Result<Vec<Option<Prepared2>>, String> {
    let cparams = final_cparams(params);
    items
        .par_iter()
        .map(|(sc, g, sol)| {
            let Some(sol) = sol else { return Ok(None) };
            let gc = &cases[*g];
            let truth = with_truth.then(|| truth_positions(&gc.geo, sc));
            let data = SampleData::build(
                cfg,
                &gc.frame,
                &gc.geo.model.mesh,
                &gc.case.correspondence,
                &cparams,
                &sc.measurements,
                &sol.u,
                &sol.transform,
                truth.as_deref(),
            )
            .map_err(|e| format!("{}: {e}", sc.id))?;
            let refit = if refit_loss {
                Some(
                    refit_loss_data(gc, &sc.measurements, sol, params)
                        .map_err(|e| format!("{}: linearised refit: {e}", sc.id))?,
                )
            } else {
                None
            };
            Ok(Some(Prepared2 {
                geometry: g.to_string(),
                data,
                refit,
            }))
        })
        .collect()
}

fn tensor2(v: &[f32], rows: usize, device: &Device) -> Tensor<2> {
    Tensor::<2>::from_data(TensorData::new(v.to_vec(), [rows, 3]), device)
}

/// Mean penalty of per-row error vectors `e` `[n, 3]`.
fn penalty(kind: Loss, e: Tensor<2>) -> Tensor<1> {
    match kind {
        Loss::Squared => e.powi_scalar(2).mean(),
        Loss::Distance => {
            let eps = 0.01f32;
            let d = (e.powi_scalar(2).sum_dim(1) + eps * eps).sqrt() - eps;
            d.mean()
        }
    }
}

/// Stage-2 loss of one sample: the mean penalty ([`Loss`]) of the correction error over nodes, plus
/// λ times the same at the matched measured points. Also returns the answer: the prediction, or
/// with `refit` (the sample's linearised refit and its geometry's modes) what the pipeline's
/// refit makes of it, to first order, which the node loss then scores.
///
/// Stage 2 keeps the bipartite branch fixed: it runs as `frozen` (a copy of the network without
/// autodiff, on `plain`) and its features are copied onto `device`. Running it on the autodiff
/// device and detaching its output would leave its recorded graph, unreachable from the loss,
/// behind at every step (memory grew to 24 GB in one epoch).
#[allow(clippy::too_many_arguments)]
fn mesh_loss(
    net: &SrGcn,
    frozen: &SrGcn,
    cfg: &SrGcnConfig,
    s: &SampleData,
    graph: &MeshGraphs,
    refit: Option<(&RefitLoss, &Tensor<2>)>,
    plain: &Device,
    device: &Device,
) -> Result<(Tensor<1>, Tensor<2>), GcnError> {
    let x = s.tensors_mesh(device);
    let (bip, out) = match s.tensors(cfg, plain)?.1 {
        Some(b) => {
            let o = frozen.forward_bipartite(&b)?;
            let to = |t: Tensor<2>| Tensor::<2>::from_data(t.into_data(), device);
            let o = o.map(|o| super::model::BipartiteOutput {
                features: o.features.into_iter().map(to).collect(),
                reconstruction: to(o.reconstruction),
            });
            let b = super::model::BipartiteInput {
                mask: to(b.mask),
                features: to(b.features),
                ..b
            };
            (Some(b), o)
        }
        None => (None, None),
    };
    let y = net.forward_mesh(x, graph, bip.as_ref().zip(out.as_ref()))?;
    let target = s
        .target
        .as_ref()
        .ok_or_else(|| GcnError::Invalid("sample has no target".into()))?;
    let t = tensor2(target, s.num_nodes, device);
    let answer = match refit {
        Some((r, g)) => through_refit(y.clone(), r, g, device)?,
        None => y.clone(),
    };
    let mut loss = penalty(cfg.loss, answer.clone() - t);
    if cfg.sparse_weight > 0.0 && s.sparse_rows.rows > 0 {
        let op = super::sparse::SparseOp::new(s.sparse_rows.clone());
        let at = op.apply(y.clone())?;
        let ts = tensor2(&s.sparse_target, s.sparse_rows.rows, device);
        loss = loss + penalty(cfg.loss, at - ts) * cfg.sparse_weight;
    }
    Ok((loss, answer))
}

/// Mean node error (mm) of the corrected prediction against the target (both in output units).
fn node_error_mm(y: &Tensor<2>, target: &[f32], unit: f64) -> f64 {
    scaled_errors_mm(y, target, unit, &[1.0])[0]
}

/// Mean node error (mm) of the correction `y` scaled by each factor of `grid`.
fn scaled_errors_mm(y: &Tensor<2>, target: &[f32], unit: f64, grid: &[f64]) -> Vec<f64> {
    let p = y
        .clone()
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .unwrap_or_default();
    let n = target.len() / 3;
    if n == 0 || p.len() != target.len() {
        return vec![f64::NAN; grid.len()];
    }
    let mut out = vec![0.0; grid.len()];
    for (yi, ti) in p.chunks_exact(3).zip(target.chunks_exact(3)) {
        for (o, a) in out.iter_mut().zip(grid) {
            *o += (0..3)
                .map(|c| (a * yi[c] as f64 - ti[c] as f64).powi(2))
                .sum::<f64>()
                .sqrt();
        }
    }
    out.iter().map(|e| e / n as f64 * unit).collect()
}

/// What [`train`] returns.
pub struct TrainReport {
    /// The trained network (best validation epoch), on the plain device.
    pub model: TrainedModel,
    /// Per-epoch figures.
    pub log: Vec<EpochLog>,
    /// Best validation node error (mm).
    pub best_valid_mm: f64,
    /// Validation node error with the fitted correction scale (`model.config.correction_scale`).
    pub scaled_valid_mm: f64,
    /// Validation node error of LIBR alone (mm): the correction's starting point.
    pub libr_valid_mm: f64,
    /// Training samples used.
    pub train_samples: usize,
    /// Validation samples used.
    pub valid_samples: usize,
    /// Training time (s), LIBR solutions excluded.
    pub seconds: f64,
}

/// The float parameters of a module, flattened, in the order [`Module::visit`] gives them.
struct FlatParams(Vec<Tensor<1>>);

impl ModuleVisitor for FlatParams {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val();
        let n = t.shape().num_elements();
        self.0.push(t.reshape([n]));
    }
}

/// Blends a module's float parameters towards others given in the same order:
/// `p ← keep·p + (1 − keep)·q`.
struct Blend {
    towards: std::vec::IntoIter<Tensor<1>>,
    keep: f64,
    mismatch: bool,
}

impl ModuleMapper for Blend {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let Some(q) = self.towards.next() else {
            self.mismatch = true;
            return param;
        };
        let keep = self.keep;
        let mut mismatch = false;
        let out = param.map(|p| {
            let dims = p.dims();
            if q.dims()[0] != dims.iter().product::<usize>() {
                mismatch = true;
                return p;
            }
            p.mul_scalar(keep) + q.reshape(dims).mul_scalar(1.0 - keep)
        });
        self.mismatch |= mismatch;
        out
    }
}

/// An exponential moving average of a network's weights (Polyak averaging): after step `t` the
/// average moves towards the weights by `1 − keep`, with `keep = min(decay, (1 + t)/(10 + t))`,
/// so the first steps, far from where training ends, are soon forgotten.
pub struct WeightAverage {
    net: Option<SrGcn>,
    decay: f64,
    steps: u64,
}

impl WeightAverage {
    /// An average with `decay` per step, in [0, 1).
    pub fn new(decay: f64) -> Result<Self, String> {
        if !(0.0..1.0).contains(&decay) {
            return Err(format!(
                "weight-average decay must be in [0, 1), got {decay}"
            ));
        }
        Ok(Self {
            net: None,
            decay,
            steps: 0,
        })
    }

    /// Takes the weights after a step (a plain-device copy, `SrGcn::valid`).
    pub fn update(&mut self, net: SrGcn) -> Result<(), String> {
        self.steps += 1;
        self.net = Some(match self.net.take() {
            None => net,
            Some(avg) => {
                let mut flat = FlatParams(Vec::new());
                net.visit(&mut flat);
                let t = self.steps as f64;
                let mut blend = Blend {
                    towards: flat.0.into_iter(),
                    keep: self.decay.min((1.0 + t) / (10.0 + t)),
                    mismatch: false,
                };
                let out = avg.map(&mut blend);
                if blend.mismatch || blend.towards.next().is_some() {
                    return Err("internal: the averaged network's parameters differ".into());
                }
                out
            }
        });
        Ok(())
    }

    /// The average so far (`None` before the first update).
    pub fn get(&self) -> Option<&SrGcn> {
        self.net.as_ref()
    }

    /// Steps taken in.
    pub fn steps(&self) -> u64 {
        self.steps
    }
}

/// Trains SR-GCN on prepared samples (`train`, `valid`), writing a checkpoint to `out` after
/// every improving epoch. `progress(stage, epoch, done, total, loss)` reports steps.
#[allow(clippy::too_many_arguments)]
pub fn train(
    opts: &TrainOptions,
    cases: &BTreeMap<String, GeometryCase>,
    train: &[Prepared2],
    valid: &[Prepared2],
    out: &Path,
    provenance: &serde_json::Value,
    progress: &dyn Fn(u32, usize, usize, usize, f64),
) -> Result<TrainReport, String> {
    let cfg = &opts.config;
    cfg.validate().map_err(|e| e.to_string())?;
    if !(opts.weight_decay >= 0.0 && opts.weight_decay.is_finite()) {
        return Err(format!(
            "weight_decay must be finite and ≥ 0, got {}",
            opts.weight_decay
        ));
    }
    if !(opts.position_jitter >= 0.0 && opts.position_jitter.is_finite()) {
        return Err(format!(
            "position_jitter must be finite and ≥ 0, got {}",
            opts.position_jitter
        ));
    }
    if train.is_empty() || valid.is_empty() {
        return Err("no training or no validation samples".into());
    }
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let t0 = Instant::now();
    let plain = super::device::compute();
    let device = plain.clone().autodiff();
    device.seed(opts.seed);
    let mut net = match &opts.init {
        None => cfg.init(&device).map_err(|e| e.to_string())?,
        Some(dir) => {
            let m = super::io::load_model(dir, &device)
                .map_err(|e| format!("initial model {}: {e}", dir.display()))?;
            let (mut a, mut b) = (m.config.clone(), cfg.clone());
            a.correction_scale = 1.0;
            b.correction_scale = 1.0;
            if serde_json::to_value(&a).ok() != serde_json::to_value(&b).ok() {
                return Err(format!(
                    "initial model {}: its network differs from the one asked for",
                    dir.display()
                ));
            }
            m.net
        }
    };
    let mut graphs: BTreeMap<String, (MeshGraphs, MeshGraphs)> = BTreeMap::new();
    for (g, gc) in cases {
        let ad = gc
            .frame
            .mesh_graphs(cfg, &device)
            .map_err(|e| e.to_string())?;
        let pl = gc
            .frame
            .mesh_graphs(cfg, &plain)
            .map_err(|e| e.to_string())?;
        graphs.insert(g.clone(), (ad, pl));
    }
    // The refit modes of every geometry, when training through the refit.
    let mut modes: BTreeMap<String, (Tensor<2>, Tensor<2>)> = BTreeMap::new();
    if opts.refit_loss {
        if let Some(s) = train.iter().chain(valid).find(|s| s.refit.is_none()) {
            return Err(format!(
                "training through the refit needs every sample's linearised refit; a sample of {} has none",
                s.geometry
            ));
        }
        for (g, gc) in cases {
            modes.insert(
                g.clone(),
                (refit_modes(gc, &device)?, refit_modes(gc, &plain)?),
            );
        }
    }
    // A sample's linearised refit with its geometry's modes on the autodiff (0) or plain (1)
    // device.
    fn through<'a>(
        modes: &'a BTreeMap<String, (Tensor<2>, Tensor<2>)>,
        s: &'a Prepared2,
        k: usize,
    ) -> Option<(&'a RefitLoss, &'a Tensor<2>)> {
        let m = modes.get(&s.geometry)?;
        Some((s.refit.as_ref()?, if k == 0 { &m.0 } else { &m.1 }))
    }
    let err = |e: GcnError| e.to_string();
    // A training sample as the network sees it at step (stage, epoch, k): jittered when asked.
    fn seen<'a>(
        opts: &TrainOptions,
        s: &'a SampleData,
        stage: u64,
        epoch: usize,
        k: usize,
    ) -> Cow<'a, SampleData> {
        if opts.position_jitter > 0.0 {
            let seed = opts
                .seed
                .wrapping_mul(0x100_0000_01b3)
                .wrapping_add((stage << 48) ^ ((epoch as u64) << 32) ^ k as u64);
            Cow::Owned(s.jittered(
                &opts.config,
                &PositionJitter::draw(opts.position_jitter, seed),
            ))
        } else {
            Cow::Borrowed(s)
        }
    }
    let mut log = Vec::new();
    let mut order: Vec<usize> = (0..train.len()).collect();
    // Stage 1: the bipartite branch reconstructs its input.
    if cfg.bipartite {
        let mut optim = AdamConfig::new().init();
        for epoch in 1..=opts.epochs_bipartite {
            shuffle(&mut order, opts.seed.wrapping_add(epoch as u64));
            let mut sum = 0.0;
            for (k, &i) in order.iter().enumerate() {
                let (_, bip) = seen(opts, &train[i].data, 1, epoch, k)
                    .tensors(cfg, &device)
                    .map_err(err)?;
                let b = bip.ok_or("internal: no bipartite input")?;
                let o = net
                    .forward_bipartite(&b)
                    .map_err(err)?
                    .ok_or("internal: no bipartite branch")?;
                let loss = (o.reconstruction - b.features.clone())
                    .powi_scalar(2)
                    .mean();
                let l: f64 = loss.clone().into_scalar::<f32>() as f64;
                sum += l;
                let grads = GradientsParams::from_grads(loss.backward(), &net);
                net = optim.step(opts.learning_rate, net, grads);
                progress(1, epoch, k + 1, order.len(), sum / (k + 1) as f64);
            }
            let vnet = net.valid();
            let mut vsum = 0.0;
            for s in valid {
                let (_, bip) = s.data.tensors(cfg, &plain).map_err(err)?;
                let b = bip.ok_or("internal: no bipartite input")?;
                let o = vnet.forward_bipartite(&b).map_err(err)?.ok_or("internal")?;
                vsum += (o.reconstruction - b.features)
                    .powi_scalar(2)
                    .mean()
                    .into_scalar::<f32>() as f64;
            }
            log.push(EpochLog {
                stage: 1,
                epoch,
                train_loss: sum / order.len() as f64,
                valid: vsum / valid.len() as f64,
                learning_rate: opts.learning_rate,
                seconds: t0.elapsed().as_secs_f64(),
            });
        }
    }
    // Stage 2: the mesh branch.
    let unit = |g: &str| cases[g].frame.unit_mm();
    let libr_valid_mm = valid
        .iter()
        .map(|s| {
            let t = s.data.target.as_deref().unwrap_or(&[]);
            let zero = Tensor::<2>::zeros([s.data.num_nodes, 3], &plain);
            match cfg.target {
                Target::Residual => node_error_mm(&zero, t, unit(&s.geometry)),
                Target::Gt => f64::NAN,
            }
        })
        .sum::<f64>()
        / valid.len() as f64;
    let frozen = net.valid();
    let mut optim = AdamConfig::new()
        .with_weight_decay(
            (opts.weight_decay > 0.0)
                .then(|| burn::optim::decay::WeightDecayConfig::new(opts.weight_decay as f32)),
        )
        .init();
    let mut lr = opts.learning_rate;
    let mut best = f64::INFINITY;
    let mut best_net = net.valid();
    // Candidate factors on the correction: 0, 0.05, …, 1 for a residual target.
    let grid: Vec<f64> = if cfg.target == Target::Residual {
        (0..=20).map(|k| k as f64 / 20.0).collect()
    } else {
        vec![1.0]
    };
    // Validation node error at every candidate correction scale (the last is 1).
    let validate = |vnet: &SrGcn| -> Result<Vec<f64>, String> {
        let mut verr = vec![0.0; grid.len()];
        for s in valid {
            let (_, y) = mesh_loss(
                vnet,
                vnet,
                cfg,
                &s.data,
                &graphs[&s.geometry].1,
                through(&modes, s, 1),
                &plain,
                &plain,
            )
            .map_err(err)?;
            let errs = scaled_errors_mm(
                &y,
                s.data.target.as_deref().unwrap_or(&[]),
                unit(&s.geometry),
                &grid,
            );
            for (a, e) in verr.iter_mut().zip(errs) {
                *a += e / valid.len() as f64;
            }
        }
        Ok(verr)
    };
    let mut best_err = vec![f64::INFINITY; grid.len()];
    if opts.epochs == 0 {
        // Nothing to train: the starting network, validated.
        best_err = validate(&best_net)?;
        best = best_err[grid.len() - 1];
    }
    if !(opts.average_epochs >= 0.0 && opts.average_epochs.is_finite()) {
        return Err(format!(
            "average_epochs must be finite and ≥ 0, got {}",
            opts.average_epochs
        ));
    }
    let mut average = if opts.average_epochs > 0.0 {
        let steps = opts.average_epochs * order.len() as f64;
        Some(WeightAverage::new(1.0 - 1.0 / steps.max(1.0))?)
    } else {
        None
    };
    let mut stall = 0;
    for epoch in 1..=opts.epochs {
        shuffle(&mut order, opts.seed.wrapping_add(1000 + epoch as u64));
        let mut sum = 0.0;
        let mut lr_sum = 0.0;
        for (k, &i) in order.iter().enumerate() {
            let s = &train[i];
            let (loss, _) = mesh_loss(
                &net,
                &frozen,
                cfg,
                &seen(opts, &s.data, 2, epoch, k),
                &graphs[&s.geometry].0,
                through(&modes, s, 0),
                &plain,
                &device,
            )
            .map_err(err)?;
            let l: f64 = loss.clone().into_scalar::<f32>() as f64;
            if !l.is_finite() {
                return Err(format!("stage 2, epoch {epoch}: the loss is not finite"));
            }
            sum += l;
            if opts.schedule == Schedule::Cosine {
                let steps = (opts.epochs * order.len()).max(1) as f64;
                let p_steps = ((epoch - 1) * order.len() + k) as f64 / steps;
                let p_time = t0.elapsed().as_secs_f64() / (60.0 * opts.max_minutes).max(1e-9);
                lr = opts.schedule.rate(opts.learning_rate, p_steps.max(p_time));
                lr_sum += lr;
            }
            let grads = GradientsParams::from_grads(loss.backward(), &net);
            net = optim.step(lr, net, grads);
            if let Some(a) = average.as_mut() {
                a.update(net.valid())?;
            }
            progress(2, epoch, k + 1, order.len(), sum / (k + 1) as f64);
        }
        let vnet = match average.as_ref().and_then(WeightAverage::get) {
            Some(a) => a.clone(),
            None => net.valid(),
        };
        let verr = validate(&vnet)?;
        let v = verr[grid.len() - 1];
        log.push(EpochLog {
            stage: 2,
            epoch,
            train_loss: sum / order.len() as f64,
            valid: v,
            // The epoch's mean rate under the cosine schedule.
            learning_rate: if opts.schedule == Schedule::Cosine {
                lr_sum / order.len().max(1) as f64
            } else {
                lr
            },
            seconds: t0.elapsed().as_secs_f64(),
        });
        if v < best {
            best = v;
            best_net = vnet;
            best_err = verr;
            stall = 0;
            let mut prov = provenance.clone();
            prov["checkpoint"] =
                serde_json::json!({"stage": 2, "epoch": epoch, "valid_node_error_mm": v});
            save_model(out, cfg, &best_net, prov)?;
        } else if opts.schedule == Schedule::Plateau {
            stall += 1;
            lr *= 0.5;
            if stall >= opts.patience {
                break;
            }
        }
        // Stop before an epoch that would end past the time limit (judged by the last one).
        let epoch_s = log.last().map_or(0.0, |l: &EpochLog| l.seconds)
            - log
                .iter()
                .rev()
                .nth(1)
                .map_or(0.0, |l: &EpochLog| l.seconds);
        if t0.elapsed().as_secs_f64() + epoch_s > 60.0 * opts.max_minutes {
            break;
        }
    }
    // The correction's scale, fitted on the best epoch's validation errors: the largest factor
    // among the best (ties keep more of the correction).
    let mut config = cfg.clone();
    let (k, scaled_valid_mm) =
        best_err
            .iter()
            .enumerate()
            .rev()
            .fold((grid.len() - 1, best), |acc, (k, e)| {
                if *e < acc.1 - 1e-9 { (k, *e) } else { acc }
            });
    config.correction_scale = grid[k];
    Ok(TrainReport {
        model: TrainedModel {
            config,
            net: best_net,
            provenance: provenance.clone(),
        },
        log,
        scaled_valid_mm,
        best_valid_mm: best,
        libr_valid_mm,
        train_samples: train.len(),
        valid_samples: valid.len(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Candidate correction scales with the data-consistency refit: 0, 0.125, …, 2.
pub fn refit_scale_grid() -> Vec<f64> {
    (0..=16).map(|k| k as f64 / 8.0).collect()
}

/// Fits a residual model's correction scale for LIBR+ as the pipeline runs it, with the
/// data-consistency refit ([`crate::register::pipeline::refit`], `params.refit_iterations` ≥ 1):
/// for each validation scenario (`items`: scenario, geometry, LIBR's solution), the network's
/// correction at every factor of `grid`, refitted, against the truth. Returns the factor with the
/// least mean node error (ties keep the larger) and the mean node error (mm) at every factor.
/// Scenarios whose LIBR failed are skipped; an error if none is left.
pub fn fit_refit_scale(
    model: &TrainedModel,
    cases: &BTreeMap<String, GeometryCase>,
    items: &[(&ScenarioData, &str, &Option<LibrSolution>)],
    params: &PipelineParams,
    grid: &[f64],
) -> Result<(f64, Vec<f64>), String> {
    if model.config.target != Target::Residual {
        return Err("only a residual model's correction has a scale".into());
    }
    if params.refit_iterations == 0 {
        return Err("refit_iterations is 0: nothing to refit".into());
    }
    if grid.is_empty()
        || grid
            .iter()
            .any(|a| !(a.is_finite() && (0.0..=2.0).contains(a)))
    {
        return Err("the scale grid must be non-empty, in [0, 2]".into());
    }
    let unit_model = TrainedModel {
        config: SrGcnConfig {
            correction_scale: 1.0,
            ..model.config.clone()
        },
        net: model.net.clone(),
        provenance: serde_json::Value::Null,
    };
    let plain = super::device::compute();
    let mut graphs = BTreeMap::new();
    for (g, gc) in cases {
        graphs.insert(
            g.clone(),
            gc.frame
                .mesh_graphs(&unit_model.config, &plain)
                .map_err(|e| e.to_string())?,
        );
    }
    // Validation samples carry no truth, except for the paper's leak (a diagnostic).
    let leak = unit_model.config.diagnostic_truth_neighbours;
    let samples = build_samples(&unit_model.config, cases, items, params, leak, false)?;
    let per: Vec<Vec<f64>> = items
        .par_iter()
        .zip(samples.par_iter())
        .filter_map(|((sc, g, sol), sample)| {
            let (sol, sample) = (sol.as_ref()?, sample.as_ref()?);
            Some((sc, *g, sol, sample))
        })
        .map(|(sc, g, sol, sample)| -> Result<Vec<f64>, String> {
            let gc = &cases[g];
            let y = predict(&unit_model, &graphs[g], &sample.data)
                .map_err(|e| format!("{}: {e}", sc.id))?;
            let nodes = gc.geo.model.mesh.nodes();
            grid.iter()
                .map(|&a| {
                    let config = SrGcnConfig {
                        correction_scale: a,
                        ..unit_model.config.clone()
                    };
                    let ua = apply_prediction(&config, &gc.frame, &sol.u, &y)
                        .map_err(|e| format!("{}: {e}", sc.id))?;
                    let r = crate::register::pipeline::refit(
                        &gc.case,
                        &sc.measurements,
                        params,
                        &ua,
                        &sol.transform,
                        None,
                    )
                    .map_err(|e| format!("{}: refit: {e}", sc.id))?;
                    let e = crate::eval::node_errors_mm(
                        nodes,
                        (&r.image_to_physical, &r.u),
                        (&sc.truth.image_to_physical, &sc.truth.displacement),
                    );
                    Ok(e.iter().sum::<f64>() / e.len().max(1) as f64)
                })
                .collect()
        })
        .collect::<Result<_, _>>()?;
    if per.is_empty() {
        return Err("no validation scenario with a LIBR solution".into());
    }
    let mean: Vec<f64> = (0..grid.len())
        .map(|k| per.iter().map(|e| e[k]).sum::<f64>() / per.len() as f64)
        .collect();
    let mut best = grid.len() - 1;
    for k in (0..grid.len()).rev() {
        if mean[k] < mean[best] - 1e-9 {
            best = k;
        }
    }
    Ok((grid[best], mean))
}

/// LIBR+ correction of one sample: node displacements (image frame, mm) to use instead of LIBR's.
/// `u` is LIBR's displacement the sample was built from.
pub fn correct(
    model: &TrainedModel,
    frame: &CaseFrame,
    graph: &MeshGraphs,
    s: &SampleData,
    u: &[f64],
) -> Result<Vec<f64>, GcnError> {
    let y = predict(model, graph, s)?;
    apply_prediction(&model.config, frame, u, &y)
}

/// The network's raw output for one sample (`[n, 3]` row-major, in the frame's output units).
pub fn predict(
    model: &TrainedModel,
    graph: &MeshGraphs,
    s: &SampleData,
) -> Result<Vec<f32>, GcnError> {
    let device = super::device::compute();
    let (x, bip) = s.tensors(&model.config, &device)?;
    let out = match &bip {
        Some(b) => model.net.forward_bipartite(b)?,
        None => None,
    };
    let y = model
        .net
        .forward_mesh(x, graph, bip.as_ref().zip(out.as_ref()))?;
    y.into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .map_err(|e| GcnError::Invalid(format!("{e:?}")))
}

/// Node displacements from a raw prediction `y` ([`predict`]) as `config` says: LIBR's `u` plus
/// `correction_scale` times the residual, or the predicted displacement itself.
pub fn apply_prediction(
    config: &SrGcnConfig,
    frame: &CaseFrame,
    u: &[f64],
    y: &[f32],
) -> Result<Vec<f64>, GcnError> {
    let unit = frame.unit_mm();
    if y.len() != u.len() {
        return Err(GcnError::Invalid(
            "prediction size differs from the mesh".into(),
        ));
    }
    let k = unit * config.correction_scale;
    Ok(match config.target {
        Target::Residual => u.iter().zip(y).map(|(a, b)| a + k * *b as f64).collect(),
        Target::Gt => y.iter().map(|b| unit * *b as f64).collect(),
    })
}

/// Where training writes: the model directory and its extras.
pub fn model_paths(out: &Path) -> (PathBuf, PathBuf) {
    (out.join("model.json"), out.join("training.json"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat(net: &SrGcn) -> Vec<Vec<f32>> {
        let mut f = FlatParams(Vec::new());
        net.visit(&mut f);
        f.0.into_iter()
            .map(|t| t.into_data().try_to_vec::<f32>().unwrap())
            .collect()
    }

    fn net(seed: u64) -> SrGcn {
        let device = Device::flex();
        device.seed(seed);
        SrGcnConfig::new().with_width(8).init(&device).unwrap()
    }

    #[test]
    fn the_weight_average_blends_every_parameter_by_its_warmed_up_decay() {
        let (a, b, c) = (net(1), net(2), net(3));
        // (Parameters initialise lazily: read them once so the clones below share them.)
        let (fa, fb, fc) = (flat(&a), flat(&b), flat(&c));
        let (a2, b2) = (a.clone(), b.clone());
        assert!(
            fa.len() > 4,
            "the network has {} float parameters",
            fa.len()
        );
        assert_ne!(fa, fb, "two seeds gave the same weights");
        let mut avg = WeightAverage::new(0.9).unwrap();
        assert!(avg.get().is_none());
        avg.update(a).unwrap();
        assert_eq!(
            flat(avg.get().unwrap()),
            fa,
            "the first update is the weights"
        );
        avg.update(b).unwrap();
        avg.update(c).unwrap();
        assert_eq!(avg.steps(), 3);
        // Step 2 keeps min(0.9, 3/12) of the average, step 3 min(0.9, 4/13).
        let (k2, k3) = (3.0 / 12.0, 4.0 / 13.0);
        let got = flat(avg.get().unwrap());
        let mut worst = 0.0f64;
        for (((g, a), b), c) in got.iter().zip(&fa).zip(&fb).zip(&fc) {
            assert_eq!(g.len(), a.len());
            for i in 0..g.len() {
                let want = (k3 * (k2 * a[i] as f64 + (1.0 - k2) * b[i] as f64)
                    + (1.0 - k3) * c[i] as f64) as f32;
                worst = worst.max((g[i] - want).abs() as f64 / (1.0 + want.abs() as f64));
            }
        }
        assert!(worst < 1e-6, "largest relative difference {worst}");
        // Late in training the decay rules: keep = 0.9 from step 81 on.
        let mut late = WeightAverage::new(0.9).unwrap();
        for _ in 0..100 {
            late.update(a2.clone()).unwrap();
        }
        late.update(b2).unwrap();
        let got = flat(late.get().unwrap());
        let (p, q, r) = (fa[0][0] as f64, fb[0][0] as f64, got[0][0] as f64);
        // (101 f32 blends: rounding grows to a few 1e-7.)
        let want = 0.9 * p + 0.1 * q;
        assert!(
            (r - want).abs() < 1e-5 * (1.0 + p.abs()),
            "got {r}, want {want} (0.9 × {p} + 0.1 × {q})"
        );
    }

    #[test]
    fn the_weight_average_refuses_a_bad_decay_or_another_network() {
        for d in [1.0, -0.1, f64::NAN] {
            let e = WeightAverage::new(d).err().unwrap();
            assert!(e.contains("decay"), "{e}");
        }
        let mut avg = WeightAverage::new(0.5).unwrap();
        avg.update(net(1)).unwrap();
        let device = Device::flex();
        let other = SrGcnConfig::new().with_width(4).init(&device).unwrap();
        let e = avg.update(other).err().unwrap();
        assert!(e.contains("differ"), "{e}");
    }

    #[test]
    fn training_refuses_a_negative_or_non_finite_weight_decay_or_position_jitter() {
        let with_decay = |x| TrainOptions {
            weight_decay: x,
            ..TrainOptions::default()
        };
        let with_jitter = |x| TrainOptions {
            position_jitter: x,
            ..TrainOptions::default()
        };
        let cases: [(&str, &dyn Fn(f64) -> TrainOptions); 2] = [
            ("weight_decay", &with_decay),
            ("position_jitter", &with_jitter),
        ];
        for (field, options) in cases {
            for x in [-1e-3, f64::NAN, f64::INFINITY] {
                let out = std::env::temp_dir().join("librplus-options-refused");
                let err = match train(
                    &options(x),
                    &BTreeMap::new(),
                    &[],
                    &[],
                    &out,
                    &serde_json::json!({}),
                    &|_, _, _, _, _| {},
                ) {
                    Ok(_) => panic!("{field} {x} accepted"),
                    Err(e) => e,
                };
                assert!(err.contains(field), "{field} {x}: {err}");
            }
        }
    }
}
