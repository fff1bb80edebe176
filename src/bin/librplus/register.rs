//! `librplus register`: one dataset scenario, or a user's own mesh and point files.

use crate::args::{MethodArg, RegisterArgs};
use crate::util::emit;
use anyhow::{Context, Result, bail};
use librplus::mesh::io::{self, DataArray, WriteOptions};
use serde_json::{Value, json};
use std::path::Path;
use std::time::Instant;

/// The learned model a method needs: SR-GCN networks for LIBR+, a V2S network for V2S.
pub(crate) enum Learned {
    /// LIBR+'s network, or an ensemble's members.
    Gcn(Vec<std::sync::Arc<librplus::gcn::io::TrainedModel>>),
    /// The V2S network.
    V2s(std::sync::Arc<librplus::v2s::io::V2sModel>),
}

impl Learned {
    /// Adds the model to a prepared case.
    pub(crate) fn attach(
        self,
        case: librplus::pipeline::Prepared,
    ) -> std::result::Result<librplus::pipeline::Prepared, librplus::pipeline::PipelineError> {
        match self {
            Learned::Gcn(m) => case.with_models(m),
            Learned::V2s(m) => case.with_v2s(m),
        }
    }
}

/// The pipeline method of `--method`, and the model it needs (from `model`, else the built-in
/// SR-GCN for LIBR+).
pub(crate) fn method_and_model(
    arg: MethodArg,
    model: Option<&Path>,
) -> Result<(librplus::pipeline::Method, Option<Learned>)> {
    use librplus::pipeline::Method;
    let method = match arg {
        MethodArg::Rigid => Method::Rigid,
        MethodArg::Libr => Method::Libr,
        MethodArg::Librplus => Method::LibrPlus,
        MethodArg::V2s => Method::V2s,
        MethodArg::Adaptive => Method::Adaptive,
        MethodArg::Nonlinear => Method::Nonlinear,
        MethodArg::Auto => Method::Auto,
    };
    let learned = match (model, method) {
        (Some(dir), Method::LibrPlus) => Some(Learned::Gcn(shared_models(
            librplus::gcn::io::load_models_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
        ))),
        (None, Method::LibrPlus) => Some(Learned::Gcn(shared_models(
            librplus::gcn::io::builtin_models()
                .map_err(|e| anyhow::anyhow!("built-in model: {e}"))?,
        ))),
        (Some(dir), Method::V2s) => Some(Learned::V2s(std::sync::Arc::new(
            librplus::v2s::io::load_model_on_device(dir)
                .map_err(|e| anyhow::anyhow!("--model: {e}"))?,
        ))),
        (None, Method::V2s) => Some(Learned::V2s(std::sync::Arc::new(
            librplus::v2s::io::builtin_model()
                .map_err(|e| anyhow::anyhow!("built-in V2S model: {e}"))?,
        ))),
        (Some(_), _) => bail!("--model is only used with --method librplus or v2s"),
        (None, _) => None,
    };
    Ok((method, learned))
}

/// The method of `register` and the model it needs, loaded.
fn register_method(a: &RegisterArgs) -> Result<(librplus::pipeline::Method, Option<Learned>)> {
    method_and_model(a.method, a.model.as_deref())
}

/// What `--json` says of a registration run with `params`: its quality flag and reason (as the
/// service would answer them), then each stage.
fn registration_json(
    r: &librplus::pipeline::Registration,
    params: &librplus::pipeline::PipelineParams,
) -> Value {
    let libr = r.libr.as_ref();
    let judged = r.quality(params);
    json!({
        "quality": judged.quality,
        "quality_reason": judged.reason,
        "rigid": {
            "rms_mm": r.rigid.rms_mm,
            "iterations": r.rigid.iterations,
            "matched": r.rigid.matched,
            "trimmed": r.rigid.trimmed,
            "degenerate": r.rigid.degenerate,
            "conditioning": r.rigid.conditioning,
            "ill_posed": r.rigid.ill_posed,
            "trusted_alignment_mm": r.rigid.prior.map(|p| p.sigma_mm),
            "moved_from_start_mm": r.rigid.moved_from_start_mm,
            "warnings": r.rigid.warnings,
            "seconds": r.rigid.seconds,
        },
        "pose": r.pose,
        "surface": r.surface,
        "reduced": r.points,
        "auto": r.auto,
        "libr": libr.map(|i| json!({
            "iterations": i.iterations,
            "converged": i.converged,
            "settled": i.settled,
            "rms_mm": i.rms_mm,
            "rms_history_mm": i.rms_history_mm,
            "movement_history_mm": i.movement_history_mm,
            "regularization": i.regularization,
            "columns": i.columns,
            "held_nodes": i.held_nodes,
            "strain_energy_uj": i.strain_energy_uj,
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
            "abstained": c.abstained,
            "outside": c.signals,
        })),
        "v2s": r.v2s.map(|v| json!({
            "seconds": v.seconds,
            "network_seconds": v.network_seconds,
        })),
        // The per-node bound is in the .vtu (--out), not here.
        "error_estimate": r.error.as_ref().map(|e| json!({
            "predicted_tre_mm": e.predicted_tre_mm,
            "level": e.level,
            "node_uncertainty_mean_mm": e.node_bound_mm.iter().sum::<f64>() / e.node_bound_mm.len().max(1) as f64,
            "node_uncertainty_max_mm": e.node_bound_mm.iter().copied().fold(0.0, f64::max),
            "failure_probability": e.failure_probability,
            "failure_threshold_mm": e.failure_threshold_mm,
            "features": e.features,
            "seconds": e.seconds,
        })),
    })
}

/// The registration's per-node error bound as a point array (`uncertainty_mm`), when it has
/// an estimate.
fn uncertainty_array(r: &librplus::pipeline::Registration) -> Option<DataArray> {
    r.error
        .as_ref()
        .map(|e| DataArray::new("uncertainty_mm", 1, e.node_bound_mm.clone()))
}

/// The case of a `register` run: the LIBR basis unless rigid (cached in `cache`), and the SR-GCN
/// when given.
fn prepare_case(
    preop: librplus::register::PreopModel,
    method: librplus::pipeline::Method,
    params: &librplus::pipeline::PipelineParams,
    cache: &Path,
    learned: Option<Learned>,
    physics: &librplus::register::physics::Physics,
) -> std::result::Result<librplus::pipeline::Prepared, librplus::pipeline::PipelineError> {
    use librplus::pipeline::{Method, Prepared};
    let case = Prepared::with_physics(
        preop,
        matches!(method, Method::Libr | Method::LibrPlus | Method::Auto).then_some(&params.libr),
        physics,
        Some(cache),
    )?
    .with_error_model(librplus::register::uncertainty::builtin());
    let case = if matches!(method, Method::Adaptive | Method::Auto | Method::Nonlinear) {
        case.with_adaptive(&params.libr, &params.adaptive, Some(cache))?
    } else {
        case
    };
    match learned {
        Some(m) => m.attach(case),
        None => Ok(case),
    }
}

/// The `--physics` file, or plain LIBR.
fn read_physics(a: &RegisterArgs) -> Result<librplus::register::physics::Physics> {
    match &a.physics {
        None => Ok(librplus::register::physics::Physics::none()),
        Some(p) => librplus::register::physics::Physics::read(p)
            .map_err(|e| anyhow::anyhow!("--physics: {e}")),
    }
}

/// Models (one, or an ensemble's members) shared between cases.
pub(crate) fn shared_models(
    models: Vec<librplus::gcn::io::TrainedModel>,
) -> Vec<std::sync::Arc<librplus::gcn::io::TrainedModel>> {
    models.into_iter().map(std::sync::Arc::new).collect()
}

/// `register --preop`: a user's own mesh and point files.
pub(crate) fn register_files(a: &RegisterArgs) -> Result<()> {
    use librplus::pipeline::register;
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
    let physics = read_physics(a)?;
    let case = prepare_case(model_pre, method, &params, &cache, model, &physics);
    bar.finish_and_clear();
    let case = case?;
    let prepare_s = t0.elapsed().as_secs_f64();
    let meas = librplus::register::Checked::new(meas)?;
    let r = register(&case, &meas, method, &params)?;
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
            [
                DataArray::new("displacement", 3, r.u.clone()),
                DataArray::new("position_physical_mm", 3, deformed),
            ]
            .into_iter()
            .chain(uncertainty_array(&r))
            .collect(),
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
        "physics": case.physics.kinds(),
        "prepare_s": prepare_s,
        "register_s": r.seconds,
        "out": a.out.as_ref().map(|p| p.display().to_string()),
    });
    if let (Value::Object(o), Value::Object(extra)) = (&mut out, registration_json(&r, &params)) {
        o.extend(extra);
    }
    emit(a.json, &out);
    Ok(())
}

pub(crate) fn register_scenario(a: &RegisterArgs) -> Result<()> {
    use librplus::pipeline::register;
    let data = a.data.as_ref().context("--data")?;
    let scenario = a.scenario.as_deref().context("--scenario")?;
    let m = librplus::eval::open(data)?;
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
    let geo = librplus::eval::load_geometry(data, &m, &d.geometry)?;
    let scenarios = librplus::eval::load_scenarios(data, d)?;
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
    let physics = read_physics(a)?;
    let case = prepare_case(geo.model.clone(), method, &params, &cache, model, &physics);
    bar.finish_and_clear();
    let case = case?;
    let prepare_s = t0.elapsed().as_secs_f64();
    let r = register(&case, &sc.measurements, method, &params)?;
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
            [
                DataArray::new("displacement", 3, r.u.clone()),
                DataArray::new("error_mm", 1, err),
            ]
            .into_iter()
            .chain(uncertainty_array(&r))
            .collect(),
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
        "physics": case.physics.kinds(),
        "prepare_s": prepare_s,
        "register_s": r.seconds,
    });
    if let (Value::Object(o), Value::Object(extra)) = (&mut out, registration_json(&r, &params)) {
        o.extend(extra);
    }
    emit(a.json, &out);
    Ok(())
}
