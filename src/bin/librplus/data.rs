//! `librplus generate` and `librplus phantom effect`, and the liver surfaces they read.

use crate::args::{Common, GenerateArgs, PresetArg, TruthArg};
use crate::mesh::read_surface;
use crate::util::emit;
use anyhow::{Context, Result, bail};
use librplus::mesh::TriSurface;
use librplus::mesh::io::Unit;
use librplus::phantom::dataset::GenerateConfig;
use serde_json::{Value, json};
use std::path::Path;
use std::time::Instant;

/// Reads a closed surface for meshing: its triangles (or a tet mesh's boundary), the largest
/// connected piece, oriented outward.
fn load_closed_surface(path: &Path, unit: Unit) -> Result<TriSurface> {
    read_surface(path, unit)?
        .largest_closed_outward()
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// The closed liver surface of `--surface` ([`load_closed_surface`]), or the built-in default
/// liver when none is given; with the source name a dataset records (the file name).
pub(crate) fn liver_surface(path: Option<&Path>, unit: Unit) -> Result<(TriSurface, String)> {
    match path {
        Some(p) => {
            let s = load_closed_surface(p, unit)
                .with_context(|| format!("--surface {}", p.display()))?;
            let name = p
                .file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_else(|| p.display().to_string());
            Ok((s, name))
        }
        None => Ok((
            librplus::assets::default_liver()?,
            librplus::assets::DEFAULT_LIVER_NAME.to_string(),
        )),
    }
}

pub(crate) fn phantom_effect(
    surface: Option<&Path>,
    edge_mm: f64,
    first_seed: u64,
    seeds: u64,
    c: &Common,
) -> Result<()> {
    use librplus::fem::hyperelastic::NewtonParams;
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::tissue::{Tissue, TissueParams};
    use librplus::phantom::truth::breakdown;
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    use librplus::register::anatomy::{LabelParams, label};
    if !(edge_mm.is_finite() && edge_mm > 0.5) || seeds == 0 {
        bail!("need --edge-mm > 0.5 and --seeds ≥ 1");
    }
    let (s, source) = liver_surface(surface, c.unit)?;
    let mesh = librplus::mesh::tetra::tetrahedralize(
        &s,
        &librplus::mesh::tetra::TetraParams::with_edge(edge_mm),
    )
    .with_context(|| source.clone())?;
    let labels = label(&mesh, &LabelParams::default())?;
    let tree = VesselTree::grow(&mesh, &VesselParams::default())?;
    let tp = TissueParams::default();
    let pp = PatternParams::default();
    let bar = indicatif::ProgressBar::new(4 * seeds).with_message("ground truth and breakdowns");
    let mut rows = Vec::new();
    for seed in first_seed..first_seed + seeds {
        let tissue = Tissue::build(&mesh, &tree, &tp, seed)?;
        let lame = tissue.lame_field();
        for pattern in [Pattern::L, Pattern::R, Pattern::W, Pattern::V, Pattern::X] {
            let case = load_case(&mesh, &labels, pattern, &pp, seed)?;
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
        "surface": source,
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
            "H" | "h" => Pattern::H,
            other => bail!("--patterns: unknown pattern {other:?} (have L, R, W, X, V, H)"),
        };
        if out.contains(&p) {
            bail!("--patterns: {name} is named twice");
        }
        out.push(p);
    }
    Ok(out)
}

/// `librplus generate`: the dataset (or this shard of it) written, then what it holds printed.
pub(crate) fn generate(a: &GenerateArgs) -> Result<()> {
    let shard = parse_shard(a.shard.as_deref())?;
    let paths: Vec<Option<&Path>> = if a.surface.is_empty() {
        vec![None]
    } else {
        a.surface.iter().map(|p| Some(p.as_path())).collect()
    };
    let mut surfaces = Vec::new();
    let mut sources = Vec::new();
    for p in paths {
        let (s, name) = liver_surface(p, a.common.unit)?;
        surfaces.push(s);
        sources.push(name);
    }
    let config = generate_config(a, sources)?;
    std::fs::create_dir_all(&a.out).with_context(|| a.out.display().to_string())?;
    let t0 = Instant::now();
    let mut report = write_dataset(a, &config, &surfaces, shard)?;
    let detect = record_detectability(a, &config, shard, report.manifest.as_ref())?;
    if detect.is_some() {
        report.manifest = Some(librplus::dataset::read_manifest(&a.out)?);
    }
    let out = generate_json(a, &report, shard, detect.as_ref(), t0);
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

/// `--shard i/N` as (i, N); (0, 1) without it.
fn parse_shard(shard: Option<&str>) -> Result<(usize, usize)> {
    let Some(s) = shard else {
        return Ok((0, 1));
    };
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
    Ok((i, n))
}

/// The generator's configuration: the preset's, with what the options change.
fn generate_config(a: &GenerateArgs, sources: Vec<String>) -> Result<GenerateConfig> {
    use librplus::phantom::dataset::{Preset, TruthModel};
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
    if let Some(v) = &a.visible {
        use librplus::phantom::measure::Visible;
        config.measure.visible = match v.as_str() {
            "anterior" => Visible::Anterior,
            "posterior" => Visible::Posterior,
            "dome" => Visible::Dome,
            "left" => Visible::Left,
            "right" => Visible::Right,
            "any" => Visible::Any,
            other => bail!(
                "--visible: unknown side {other:?} (anterior, posterior, dome, left, right, any)"
            ),
        };
    }
    if let Some(h) = a.surface_spacing_mm {
        config.measure.surface_spacing_mm = h;
        config
            .measure
            .validate()
            .map_err(|e| anyhow::anyhow!("--surface-spacing-mm: {e}"))?;
    }
    if let Some(e) = &a.start_error {
        let [deg, mm] = e[..] else {
            bail!(
                "--start-error: DEG,MM (two numbers), got {} value(s)",
                e.len()
            );
        };
        config.measure.start_error = Some([deg, mm]);
        config
            .measure
            .validate()
            .map_err(|e| anyhow::anyhow!("--start-error: {e}"))?;
    }
    config.truth = match a.truth {
        TruthArg::Nonlinear => TruthModel::Nonlinear,
        TruthArg::Linear => TruthModel::LinearHomogeneous,
        TruthArg::Libr => TruthModel::Libr,
    };
    truth_options(a, &mut config)?;
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
    Ok(config)
}

/// The options that go with a truth model: hidden effects (LIBR's truth) and truth families
/// (the nonlinear truth).
fn truth_options(a: &GenerateArgs, config: &mut GenerateConfig) -> Result<()> {
    if !a.hidden_effect.is_empty() && !matches!(a.truth, TruthArg::Libr) {
        bail!(
            "--hidden-effect needs --truth libr: hidden effects are added to LIBR's own physics \
             (the nonlinear and linear truths carry their own loads and supports)"
        );
    }
    config.hidden_effects = a
        .hidden_effect
        .iter()
        .map(|text| {
            librplus::phantom::hidden::HiddenEffectSpec::parse(text)
                .map_err(|e| anyhow::anyhow!("--hidden-effect: {e}"))
        })
        .collect::<Result<_>>()?;
    if let Some(x) = a.load_scale {
        if !(x.is_finite() && x > 0.0) {
            bail!("--load-scale: {x} must be finite and > 0");
        }
        config.patterns.load_scale = x;
    }
    if let Some(f) = &a.families {
        if !matches!(a.truth, TruthArg::Nonlinear) {
            bail!("--families needs the nonlinear truth: the families are other nonlinear solids");
        }
        config.families = librplus::phantom::family::TruthFamily::parse_list(f)
            .map_err(|e| anyhow::anyhow!("--families: {e}"))?;
    }
    Ok(())
}

/// Generates the dataset (this shard of it) into `--out`, with a progress bar.
fn write_dataset(
    a: &GenerateArgs,
    config: &GenerateConfig,
    surfaces: &[TriSurface],
    shard: (usize, usize),
) -> Result<librplus::phantom::dataset::RunReport> {
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
    let result = librplus::phantom::dataset::generate(config, surfaces, &a.out, shard, &progress);
    bar.finish_and_clear();
    result.map_err(|e| anyhow::anyhow!("{}: {e}", a.out.display()))
}

/// What `generate` prints: the dataset's size and draws, per pattern, and the detectability
/// recorded.
fn generate_json(
    a: &GenerateArgs,
    report: &librplus::phantom::dataset::RunReport,
    shard: (usize, usize),
    detect: Option<&librplus::eval::detectability::DetectabilityReport>,
    t0: Instant,
) -> Value {
    let m = report.manifest.as_ref().expect("manifest written");
    let mut out = json!({
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
        "per_pattern": per_pattern(m),
        "seconds_per_deformation_median": if report.seconds.is_empty() { 0.0 } else { librplus::util::median(&report.seconds) },
        "total_s": t0.elapsed().as_secs_f64(),
    });
    if let Some(d) = detect {
        out["detectability"] = json!({
            "computed": d.computed,
            "detectable": d.detectable,
            "kept": d.kept,
            "errors": d.errors,
            "detectable_of_all": m.deformations.iter().filter(|e| e.detectability.as_ref().is_some_and(|x| x.detectable)).count(),
            "recorded_of_all": m.deformations.iter().filter(|e| e.detectability.is_some()).count(),
        });
    }
    out
}

/// Per pattern of the dataset: its deformations and their mean and largest displacements, and
/// the gap to the linear homogeneous solution.
fn per_pattern(m: &librplus::dataset::Manifest) -> serde_json::Map<String, Value> {
    ["L", "R", "W", "V", "X"]
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
        .collect()
}

/// With hidden effects (and not `--no-detectability`, not sharded, the dataset complete):
/// records each deformation's oracle detectability, with a progress bar.
fn record_detectability(
    a: &GenerateArgs,
    config: &GenerateConfig,
    shard: (usize, usize),
    manifest: Option<&librplus::dataset::Manifest>,
) -> Result<Option<librplus::eval::detectability::DetectabilityReport>> {
    if config.hidden_effects.is_empty() || a.no_detectability {
        return Ok(None);
    }
    if shard.1 > 1 || !manifest.is_some_and(|m| m.complete) {
        eprintln!(
            "detectability: not recorded (a sharded or incomplete dataset); run `generate` again \
             with the same options and no --shard once every shard is done"
        );
        return Ok(None);
    }
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} detectability {msg} [{bar:30}] {pos}/{len} deformations, {elapsed} (eta {eta})",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let progress = |done: usize, total: usize, id: &str| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(id.to_string());
    };
    let params = librplus::discover::DiscoverParams {
        seed: config.seed,
        ..Default::default()
    };
    let r = librplus::eval::detectability::record(&a.out, &params, &progress)
        .map_err(|e| anyhow::anyhow!("{}: detectability: {e}", a.out.display()))?;
    bar.finish_and_clear();
    Ok(Some(r))
}
