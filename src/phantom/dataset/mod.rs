//! The dataset writer: geometries, ground-truth deformations and sparse scenarios into a directory
//! in the format of [`crate::dataset`] (read it there).
//!
//! The plan (which geometries, which deformations, which scenarios, every seed) is a pure function
//! of the configuration, so runs are deterministic and byte-identical for a seed, shards (`i/N`
//! takes every N-th deformation) can run on many machines into one directory, and an interrupted
//! run resumes: a deformation whose `deformation.json` exists under the same parameters hash is
//! skipped. Deformations are solved in parallel; every file is written to a temporary name and
//! renamed, so a crash never leaves a half-written file under a final name. A draw that does not
//! converge is recorded in the manifest's `failed` list and redrawn with the next seed, never
//! written as ground truth.

mod files;
use files::{collect_entries, json_bytes, write_geometry, write_scenarios};

use super::family::{FamilyDraw, TruthFamily};
use super::hidden::{HiddenEffectSpec, libr_truth};
use super::measure::{Category, MeasureParams, Scenario, simulate_focused};
use super::patterns::{LoadCase, Pattern, PatternParams, load_case};
use super::shape::{ShapeVariantParams, variant};
use super::tissue::{Tissue, TissueParams};
use super::truth::{
    GroundTruth, LoadParts, magnitude_stats, mean_distance, solve_linear, solve_truth,
    solve_truth_law,
};
use super::vessels::{VesselParams, VesselTree};
use super::{PhantomError, derive};
use crate::dataset::{
    DeformationEntry, FORMAT, FailedEntry, GeometryEntry, Manifest, TumourEntry, VERSION,
};
use crate::fem::LameField;
use crate::fem::hyperelastic::NewtonParams;
use crate::mesh::tetra::{TetraParams, tetrahedralize};
use crate::mesh::{TetMesh, TriSurface};
use crate::register::anatomy::{AnatomyLabels, LabelParams, label};
use crate::util::fnv1a_hex;
use rayon::prelude::*;
use std::path::Path;

/// A named preset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// A few coarse deformations and scenarios: seconds to minutes, for CI and trying things.
    Small,
    /// The LIBR+ paper's design: 3 training geometries × {L, R, W} plus a 4th geometry with V,
    /// 700 scenarios per deformation, ~9,000-node meshes.
    Paper,
}

impl Preset {
    /// Name as on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Small => "small",
            Preset::Paper => "paper",
        }
    }
}

/// Which physics makes the ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TruthModel {
    /// Heterogeneous compressible Neo-Hookean with unilateral bed contact (the default: physics
    /// the LIBR model lacks).
    #[default]
    Nonlinear,
    /// The linear, homogeneous model LIBR itself assumes (the parenchyma's mean material, the bed
    /// as bilateral springs), under the same loads: a control dataset on which the remaining
    /// error of LIBR is its sparse-data error alone, not model error.
    LinearHomogeneous,
    /// LIBR's own physics (free-floating linear homogeneous elasticity, the parenchyma's mean
    /// material) plus the hidden effects ([`GenerateConfig::hidden_effects`]), under the
    /// load of LIBR's own kind ([`super::truth::libr_base_load`]: broad tractions; no gravity,
    /// bed or bare-area support, none of the pattern's own loads). Without hidden effects nothing is
    /// hidden: the negative control of effect discovery.
    Libr,
}

impl TruthModel {
    fn is_nonlinear(&self) -> bool {
        *self == TruthModel::Nonlinear
    }
}

/// Everything that shapes a dataset.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GenerateConfig {
    /// Ground-truth physics. Left out of the parameters (and their hash) when nonlinear, so
    /// datasets made before the option existed keep their hash.
    #[serde(skip_serializing_if = "TruthModel::is_nonlinear")]
    pub truth: TruthModel,
    /// Effects hidden in a [`TruthModel::Libr`] truth (`--hidden-effect`), with the parameters
    /// the command line fixed; the others are drawn per deformation (see [`super::hidden`]). Left
    /// out of the parameters (and their hash) when empty.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub hidden_effects: Vec<HiddenEffectSpec>,
    /// Truth families the deformations cycle through in the plan's order (`--families`,
    /// [`super::family`]); empty for the default Neo-Hookean truth. Left out of the parameters
    /// (and their hash) when empty, so datasets made before the option existed keep their hash.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub families: Vec<TruthFamily>,
    /// Preset it started from.
    pub preset: Preset,
    /// Master seed.
    pub seed: u64,
    /// Source surfaces (closed liver surfaces in mm, LPS) as given; geometries cycle through them
    /// and then through seeded shape variants of them.
    pub sources: Vec<String>,
    /// Number of geometries; the last is the test geometry (pattern V) when `test_geometry`.
    pub geometries: usize,
    /// Whether the last geometry is held out for pattern V only.
    pub test_geometry: bool,
    /// Patterns on the training geometries.
    pub train_patterns: Vec<Pattern>,
    /// Deformations per geometry and pattern.
    pub deformations_per_pattern: usize,
    /// Scenarios per deformation (categories cycle: surface, +1, +2, +3, +16 planes).
    pub scenarios: usize,
    /// Draw the five scenarios of a block (one per category) from one seed, so they share the
    /// surface patch, its noise, the misalignment and the landmarks, and each adds planes to the
    /// previous one's (the first planes of a larger category are those of a smaller one): the
    /// categories then differ only in how many planes they measure, and their comparison is
    /// paired. Left out of the parameters (and their hash) when off, the default, so datasets
    /// made before the option existed keep their hash.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub paired_categories: bool,
    /// Mesher target edge (mm).
    pub edge_mm: f64,
    /// Shape variants.
    pub shape: ShapeVariantParams,
    /// Labels.
    pub labels: LabelParams,
    /// Vessel tree.
    pub vessels: VesselParams,
    /// Tissue.
    pub tissue: TissueParams,
    /// Loads and supports.
    pub patterns: PatternParams,
    /// Measurements.
    pub measure: MeasureParams,
    /// Newton solver.
    pub newton: NewtonParams,
    /// Draws tried per deformation before giving up.
    pub attempts: usize,
}

impl GenerateConfig {
    /// The configuration of a preset with a seed and source surfaces.
    pub fn preset(preset: Preset, seed: u64, sources: Vec<String>) -> Self {
        let base = Self {
            truth: TruthModel::Nonlinear,
            hidden_effects: Vec::new(),
            families: Vec::new(),
            preset,
            seed,
            sources,
            geometries: 4,
            test_geometry: true,
            train_patterns: vec![Pattern::L, Pattern::R, Pattern::W],
            deformations_per_pattern: 1,
            scenarios: 700,
            paired_categories: false,
            edge_mm: 7.6,
            shape: ShapeVariantParams::default(),
            labels: LabelParams::default(),
            vessels: VesselParams::default(),
            tissue: TissueParams::default(),
            patterns: PatternParams::default(),
            measure: MeasureParams::default(),
            newton: NewtonParams::default(),
            attempts: 3,
        };
        match preset {
            Preset::Paper => base,
            Preset::Small => Self {
                geometries: 2,
                train_patterns: vec![Pattern::L, Pattern::W],
                scenarios: 10,
                edge_mm: 14.0,
                ..base
            },
        }
    }
}

/// The random stream of scenario `k` of a deformation: its own, or with `paired` its block's
/// (the five scenarios `5b … 5b + 4`, one per category, share stream `b`).
pub fn scenario_stream(k: usize, paired: bool) -> u64 {
    if paired {
        (k / Category::ALL.len()) as u64
    } else {
        k as u64
    }
}

/// A geometry of the plan.
#[derive(Debug, Clone)]
struct GeometryPlan {
    id: String,
    source: usize,
    variant_seed: Option<u64>,
    split: &'static str,
    seed: u64,
}

/// A deformation of the plan.
#[derive(Debug, Clone)]
struct DeformationPlan {
    id: String,
    geometry: usize,
    pattern: Pattern,
    seed: u64,
    /// The truth family (`--families`), if any.
    family: Option<TruthFamily>,
}

/// A built geometry: mesh, labels, vessels, tissue.
struct Built {
    mesh: TetMesh,
    labels: AnatomyLabels,
    vessels: VesselTree,
    tissue: Tissue,
    lame: LameField,
}

fn plan(config: &GenerateConfig) -> (Vec<GeometryPlan>, Vec<DeformationPlan>) {
    let ns = config.sources.len().max(1);
    let geometries: Vec<GeometryPlan> = (0..config.geometries)
        .map(|k| {
            let seed = derive(config.seed, &[1, k as u64]);
            let test = config.test_geometry && k + 1 == config.geometries && k > 0;
            GeometryPlan {
                id: format!("g{}", k + 1),
                source: k % ns,
                variant_seed: (k >= ns).then_some(seed),
                split: if test { "test" } else { "train" },
                seed,
            }
        })
        .collect();
    let mut deformations = Vec::new();
    for (g, geo) in geometries.iter().enumerate() {
        let patterns = if geo.split == "test" {
            vec![Pattern::V]
        } else {
            config.train_patterns.clone()
        };
        for p in patterns {
            for i in 0..config.deformations_per_pattern {
                let family = (!config.families.is_empty())
                    .then(|| config.families[deformations.len() % config.families.len()]);
                deformations.push(DeformationPlan {
                    id: format!("{}-{p:?}-{i:02}", geo.id),
                    geometry: g,
                    pattern: p,
                    seed: derive(config.seed, &[2, g as u64, p as u64, i as u64]),
                    family,
                });
            }
        }
    }
    (geometries, deformations)
}

fn build_geometry(
    config: &GenerateConfig,
    surfaces: &[TriSurface],
    g: &GeometryPlan,
) -> Result<Built, PhantomError> {
    let base = &surfaces[g.source];
    let surface = match g.variant_seed {
        Some(s) => variant(base, &config.shape, s)?.0,
        None => base.clone(),
    };
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(config.edge_mm))
        .map_err(|e| PhantomError::within(format!("{}: meshing failed", g.id), e))?;
    let labels = label(
        &mesh,
        &LabelParams {
            seed: derive(g.seed, &[3]),
            ..config.labels
        },
    )
    .map_err(|e| PhantomError::within(format!("{}: labelling failed", g.id), e))?;
    let vessels = VesselTree::grow(
        &mesh,
        &VesselParams {
            seed: derive(g.seed, &[4]),
            ..config.vessels
        },
    )
    .map_err(|e| PhantomError::within(format!("{}: vessel tree", g.id), e))?;
    let tissue = Tissue::build(&mesh, &vessels, &config.tissue, derive(g.seed, &[5]))
        .map_err(|e| PhantomError::within(format!("{}: tissue", g.id), e))?;
    let lame = tissue.lame_field();
    Ok(Built {
        mesh,
        labels,
        vessels,
        tissue,
        lame,
    })
}

fn geometry_entry(config: &GenerateConfig, g: &GeometryPlan, b: &Built) -> GeometryEntry {
    GeometryEntry {
        id: g.id.clone(),
        source: match g.variant_seed {
            Some(s) => format!("shape variant {s} of {}", config.sources[g.source]),
            None => config.sources[g.source].clone(),
        },
        variant_seed: g.variant_seed,
        split: g.split.to_string(),
        nodes: b.mesh.num_nodes(),
        tets: b.mesh.num_tets(),
        volume_ml: b.mesh.volume() / 1000.0,
        edge_mm: config.edge_mm,
        preop: format!("geometries/{}/preop.vtu", g.id),
        vessels: format!("geometries/{}/vessels.vtp", g.id),
        targets: b.labels.targets.clone(),
        vessel_factor: b.tissue.vessel_factor,
        tumours: b
            .tissue
            .tumours
            .iter()
            .map(|t| TumourEntry {
                center: t.center,
                radius_mm: t.radius,
                stiffness_factor: t.factor,
            })
            .collect(),
        tissue_fractions: b.tissue.volume_fractions(&b.mesh),
    }
}

/// What a run did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RunReport {
    /// Deformations this run solved and wrote.
    pub written: Vec<String>,
    /// Deformations skipped because they were already complete.
    pub resumed: Vec<String>,
    /// Deformations that failed every attempt (with why).
    pub errors: Vec<String>,
    /// Seconds per written deformation (ground truth + scenarios), in plan order.
    pub seconds: Vec<f64>,
    /// The manifest, as written.
    #[serde(skip)]
    pub manifest: Option<Manifest>,
}

/// Progress callback: `(done, total, message)`.
pub type Progress<'a> = &'a (dyn Fn(usize, usize, &str) + Sync);

/// Generates (or resumes) the dataset in `dir`; `shard = (i, n)` does every n-th deformation from
/// the i-th. Surfaces are the closed source surfaces (mm, LPS) matching `config.sources`.
pub fn generate(
    config: &GenerateConfig,
    surfaces: &[TriSurface],
    dir: &Path,
    shard: (usize, usize),
    progress: Progress<'_>,
) -> Result<RunReport, PhantomError> {
    check_config(config, surfaces, shard)?;
    let (parameters, hash) = parameters_hash(config, dir)?;
    let (geo_plan, def_plan) = plan(config);
    let built: Vec<Built> = geo_plan
        .par_iter()
        .map(|g| build_geometry(config, surfaces, g))
        .collect::<Result<_, _>>()?;
    let geometries: Vec<GeometryEntry> = geo_plan
        .iter()
        .zip(&built)
        .map(|(g, b)| geometry_entry(config, g, b))
        .collect();
    for (e, b) in geometries.iter().zip(&built) {
        write_geometry(dir, e, b)?;
    }
    let entry_path =
        |d: &DeformationPlan| dir.join(format!("deformations/{}/deformation.json", d.id));
    let read_entry = |d: &DeformationPlan| -> Option<DeformationEntry> {
        let text = std::fs::read_to_string(entry_path(d)).ok()?;
        let e: DeformationEntry = serde_json::from_str(&text).ok()?;
        (e.parameters_hash == hash).then_some(e)
    };
    let mine: Vec<&DeformationPlan> = def_plan
        .iter()
        .enumerate()
        .filter(|(k, _)| k % shard.1 == shard.0)
        .map(|(_, d)| d)
        .collect();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = mine.len();
    progress(0, total, "solving ground truth");
    let outcomes: Vec<Outcome> = mine
        .par_iter()
        .map(|d| {
            let out = if read_entry(d).is_some() {
                (d.id.clone(), Ok((false, 0.0)), Vec::new())
            } else {
                let t0 = std::time::Instant::now();
                let mut failed = Vec::new();
                let r = make_deformation(config, dir, &hash, d, &built[d.geometry], &mut failed)
                    .map(|()| (true, t0.elapsed().as_secs_f64()));
                (d.id.clone(), r, failed)
            };
            let k = done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
            progress(k, total, &d.id);
            out
        })
        .collect();
    let mut report = run_report(dir, outcomes)?;
    let (deformations, missing, failed) = collect_entries(dir, &def_plan, &read_entry);
    let manifest = Manifest {
        format: FORMAT.into(),
        version: VERSION,
        preset: config.preset.name().into(),
        seed: config.seed,
        generator: format!("librplus {}", env!("CARGO_PKG_VERSION")),
        units: "mm".into(),
        frame: "LPS".into(),
        parameters_hash: hash,
        parameters,
        geometries,
        complete: missing.is_empty(),
        deformations,
        missing,
        failed,
    };
    crate::util::write_atomic(&dir.join("manifest.json"), &json_bytes(&manifest)?)?;
    report.manifest = Some(manifest);
    Ok(report)
}

/// Checks what [`generate`] is asked: one surface per source, a valid shard, something to
/// generate, valid measurement parameters, and truth options that go together.
fn check_config(
    config: &GenerateConfig,
    surfaces: &[TriSurface],
    shard: (usize, usize),
) -> Result<(), PhantomError> {
    if surfaces.is_empty() || surfaces.len() != config.sources.len() {
        return Err(PhantomError::Parameter(
            "need at least one source surface (and one name per surface)".into(),
        ));
    }
    if shard.1 == 0 || shard.0 >= shard.1 {
        return Err(PhantomError::Parameter(format!(
            "shard {}/{} is invalid: need 0 ≤ i < N",
            shard.0, shard.1
        )));
    }
    if config.geometries == 0 || config.scenarios == 0 {
        return Err(PhantomError::Parameter(
            "need at least one geometry and one scenario per deformation".into(),
        ));
    }
    config.measure.validate()?;
    if !config.families.is_empty() && config.truth != TruthModel::Nonlinear {
        return Err(PhantomError::Parameter(
            "families: truth families are nonlinear truths; they cannot be combined with --truth"
                .into(),
        ));
    }
    if !config.hidden_effects.is_empty() && config.truth != TruthModel::Libr {
        return Err(PhantomError::Parameter(
            "hidden effects need the libr truth (--truth libr): they are added to LIBR's own physics"
                .into(),
        ));
    }
    Ok(())
}

/// The parameters the dataset records and their hash; a directory that holds a dataset made
/// with other parameters is refused rather than mixed.
fn parameters_hash(
    config: &GenerateConfig,
    dir: &Path,
) -> Result<(serde_json::Value, String), PhantomError> {
    let mut parameters = serde_json::to_value(config)?;
    if !config.hidden_effects.is_empty() {
        // How the hidden effects' loads are carried: part of what the data are.
        parameters["hidden_carry"] = serde_json::json!(super::hidden::HIDDEN_CARRY);
    }
    let hash = fnv1a_hex(parameters.to_string().as_bytes());
    if let Ok(old) = crate::dataset::read_manifest(dir)
        && old.parameters_hash != hash
    {
        return Err(PhantomError::Parameter(format!(
            "{} already holds a dataset generated with other parameters (hash {} ≠ {hash}); use another --out",
            dir.display(),
            old.parameters_hash
        )));
    }
    Ok((parameters, hash))
}

/// A draw's outcome: its id, whether it was written (and in how many seconds) or resumed, and
/// the draws that failed on the way.
type Outcome = (String, Result<(bool, f64), PhantomError>, Vec<FailedEntry>);

/// The run's report from its outcomes, the failed draws written beside their deformations (so
/// that shards and resumed runs assemble the same manifest).
fn run_report(dir: &Path, outcomes: Vec<Outcome>) -> Result<RunReport, PhantomError> {
    let mut report = RunReport::default();
    let mut failed_log: Vec<FailedEntry> = Vec::new();
    for (id, r, failed) in outcomes {
        failed_log.extend(failed);
        match r {
            Ok((true, secs)) => {
                report.written.push(id);
                report.seconds.push(secs);
            }
            Ok((false, _)) => report.resumed.push(id),
            Err(e) => report.errors.push(format!("{id}: {e}")),
        }
    }
    for f in &failed_log {
        let path = dir.join(format!("deformations/{}/failed-{}.json", f.id, f.seed));
        crate::util::write_atomic(&path, &json_bytes(f)?)?;
    }
    Ok(report)
}

/// A draw's ground truth, with what it is compared with and recorded beside it.
struct Solved {
    truth: GroundTruth,
    /// The linear homogeneous solution under the same loads (`--truth libr`: LIBR's physics
    /// without the hidden effects).
    linear: Vec<f64>,
    description: String,
    /// The truth's effects and what each is there for (`--truth libr` only).
    hidden: Option<(crate::register::physics::Physics, Vec<super::hidden::Role>)>,
    /// Bed contacts in the truth.
    contacts: usize,
}

/// Solves one deformation (redrawing on non-convergence) and writes its files.
fn make_deformation(
    config: &GenerateConfig,
    dir: &Path,
    hash: &str,
    d: &DeformationPlan,
    b: &Built,
    failed: &mut Vec<FailedEntry>,
) -> Result<(), PhantomError> {
    let mut last_error = String::new();
    for attempt in 0..config.attempts.max(1) {
        let seed = if attempt == 0 {
            d.seed
        } else {
            derive(d.seed, &[6, attempt as u64])
        };
        let case = load_case(&b.mesh, &b.labels, d.pattern, &config.patterns, seed)?;
        let family = d.family.map(|f| f.draw(&b.tissue, derive(seed, &[8])));
        let solved = solve_draw(config, b, &case, family.as_ref(), seed)?;
        let Solved {
            truth,
            linear,
            description,
            hidden,
            contacts,
        } = match solved {
            Ok(s) => s,
            Err(e) => {
                last_error = e.to_string();
                failed.push(FailedEntry {
                    id: d.id.clone(),
                    seed,
                    error: format!("{e} ({})", case.description),
                });
                continue;
            }
        };
        let u = &truth.displacement;
        let (mean, max) = magnitude_stats(u);
        let measure = measure_params(config, d, &case);
        let scenarios: Vec<Scenario> = (0..config.scenarios)
            .into_par_iter()
            .map(|k| {
                let category = Category::ALL[k % Category::ALL.len()];
                simulate_focused(
                    &b.mesh,
                    &b.labels,
                    &b.vessels,
                    u,
                    category,
                    &measure,
                    case.focus,
                    derive(seed, &[7, scenario_stream(k, config.paired_categories)]),
                )
                .map_err(|e| PhantomError::within(format!("scenario {k}"), e))
            })
            .collect::<Result<_, _>>()?;
        let base = format!("deformations/{}", d.id);
        let entries = write_scenarios(dir, &base, b, u, &scenarios)?;
        let hidden_effects =
            hidden.map(|(p, roles)| p.to_value(&super::hidden::role_values(&roles)));
        if let Some(v) = &hidden_effects {
            crate::util::write_atomic(
                &dir.join(format!("{base}/hidden_physics.json")),
                &json_bytes(v)?,
            )?;
        }
        let entry = DeformationEntry {
            id: d.id.clone(),
            geometry: format!("g{}", d.geometry + 1),
            pattern: format!("{:?}", d.pattern),
            seed,
            parameters_hash: hash.to_string(),
            description,
            gt: format!("{base}/gt.vtu"),
            npz: format!("{base}/scenarios.npz"),
            mean_displacement_mm: mean,
            max_displacement_mm: max,
            linear_homogeneous_gap_mm: mean_distance(u, &linear),
            load_steps: truth.info.load_steps,
            newton_iterations: truth.info.iterations,
            relative_residual: truth.info.relative_residual,
            active_contacts: [truth.active_contacts, contacts],
            hidden_effects,
            detectability: None,
            truth_family: family.map(|f| f.record),
            scenarios: entries,
        };
        // Written last: its presence marks the deformation complete.
        return Ok(crate::util::write_atomic(
            &dir.join(format!("{base}/deformation.json")),
            &json_bytes(&entry)?,
        )?);
    }
    Err(PhantomError::Inconsistent(format!(
        "every one of {} draws failed (last: {last_error})",
        config.attempts.max(1)
    )))
}

/// Solves a draw's ground truth: LIBR's physics with the hidden effects (`--truth libr`), or the
/// nonlinear (or control linear) truth with its linear comparison. The inner error is the
/// draw's (another draw is tried); the outer one, the linear comparison's, ends the deformation.
fn solve_draw(
    config: &GenerateConfig,
    b: &Built,
    case: &LoadCase,
    family: Option<&FamilyDraw>,
    seed: u64,
) -> Result<Result<Solved, PhantomError>, PhantomError> {
    if config.truth == TruthModel::Libr {
        return Ok(libr_truth(
            &b.mesh,
            &b.labels,
            &config.tissue.parenchyma,
            case,
            &config.patterns,
            &config.hidden_effects,
            seed,
        )
        .map(|t| Solved {
            truth: GroundTruth {
                displacement: t.displacement,
                info: Default::default(),
                active_contacts: 0,
            },
            // What LIBR's own model gives under the same load: the gap is the hidden effects'.
            linear: t.libr,
            description: format!("{}; {}", case.description, t.note),
            hidden: Some((t.physics, t.roles)),
            contacts: 0,
        }));
    }
    let (lam, mu) = config.tissue.parenchyma.lame();
    let linear = solve_linear(&b.mesh, &LameField::Uniform(lam, mu), case, LoadParts::ALL)
        .map_err(|e| PhantomError::within("linear comparison", e))?;
    let truth = match config.truth {
        // The control: the linear solution is the truth (no Newton; every bed spring acts).
        TruthModel::LinearHomogeneous => Ok(GroundTruth {
            displacement: linear.clone(),
            info: Default::default(),
            active_contacts: case.contacts.len(),
        }),
        _ => match family {
            Some(f) => solve_truth_law(
                &b.mesh,
                f.lame.as_ref().unwrap_or(&b.lame),
                f.law,
                case,
                &config.newton,
            ),
            None => solve_truth(&b.mesh, &b.lame, case, &config.newton),
        }
        .map_err(Into::into),
    };
    Ok(truth.map(|truth| Solved {
        truth,
        linear,
        description: case.description.clone(),
        hidden: None,
        contacts: case.contacts.len(),
    }))
}

/// The measurement parameters of a deformation's scenarios (its truth family's, where it has
/// one). A held organ is measured where it is: no misalignment, the navigation start the true
/// alignment, the camera on the tool's spot.
fn measure_params(config: &GenerateConfig, d: &DeformationPlan, case: &LoadCase) -> MeasureParams {
    let base_measure = d
        .family
        .map_or(config.measure, |f| f.measure(&config.measure));
    if case.held {
        MeasureParams {
            max_rotation_deg: 0.0,
            max_translation_mm: 0.0,
            trusted_start: true,
            ..base_measure
        }
    } else {
        base_measure
    }
}
