//! `librplus bench`: basis (the LIBR preload workload) and register (the whole pipeline, with
//! the preload printed); `bench gcn` is dispatched in `main`.

use crate::args::{BenchRegisterArgs, Common};
use crate::data::liver_surface;
use crate::mesh::load_volume;
use crate::util::emit;
use anyhow::{Context, Result, bail};
use librplus::eval::bench::{
    BenchScenarios, PreloadBench, RegistrationBench, preload_model, time_in_pool,
};
use librplus::fem;
use librplus::mesh::io::Unit;
use librplus::pipeline::{Method, Prepared};
use serde_json::{Value, json};
use std::path::Path;

pub(crate) fn bench_basis(
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
    let pick = |f: fn(&fem::basis_bench::BasisBench) -> f64| {
        librplus::util::median(&runs.iter().map(f).collect::<Vec<_>>())
    };
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

/// `bench register`: the preload of a case, then registrations timed one at a time.
pub(crate) fn bench_register(a: &BenchRegisterArgs) -> Result<()> {
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
    let tmp = tempfile::Builder::new()
        .prefix("librplus-bench-register-")
        .tempdir()
        .context("a temporary directory for the benchmark's cache")?;
    let cache = tmp.path().join("cache");
    if let Some(path) = &a.mesh {
        return bench_mesh(a, path, &params, &cache);
    }
    let data = match &a.data {
        Some(d) => d.clone(),
        None => {
            let dir = tmp.path().join("data");
            let bar = spinner("generating the small preset (no --data given)");
            let r = small_dataset(&dir, a.surface.as_deref());
            bar.finish_and_clear();
            r?;
            dir
        }
    };
    let scenarios = BenchScenarios::load(&data, a.geometry.as_deref(), a.scenarios)?;
    let (preload, case, method, model_prepare_s) = prepare_case(a, &params, &scenarios, &cache)?;
    let bar =
        indicatif::ProgressBar::new(scenarios.picked.len() as u64).with_message("registrations");
    let asked = librplus::eval::bench::Asked {
        method,
        params: &params,
        progressive: a.progressive,
    };
    let r = time_in_pool(a.threads, &case, &scenarios, asked, &|done, _| {
        bar.set_position(done as u64)
    });
    bar.finish_and_clear();
    let timed = Timed {
        data: &data,
        geometry: &scenarios.geometry,
        method,
        preload: &preload,
        model_prepare_s,
        registrations: &r?,
    };
    if a.common.json {
        println!("{}", timed.to_json(a));
    } else {
        timed.print(a);
    }
    Ok(())
}

/// A spinner saying `msg`.
fn spinner(msg: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new_spinner().with_message(msg.to_string());
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    bar
}

/// `bench register --mesh`: the LIBR basis preload of a bare mesh alone.
fn bench_mesh(
    a: &BenchRegisterArgs,
    path: &Path,
    params: &librplus::pipeline::PipelineParams,
    cache: &Path,
) -> Result<()> {
    let mesh = load_volume(path, a.common.unit)?.mesh;
    if let Some(edge) = a.coarse_edge_mm {
        let c = coarse(&mesh, params, edge)?;
        if a.common.json {
            println!(
                "{}",
                json!({"mesh": path.display().to_string(), "nodes": mesh.num_nodes(), "coarse_basis": coarse_json(&c)})
            );
        }
        return Ok(());
    }
    let bar = spinner("LIBR basis: cold build, then warm load");
    let p = librplus::eval::bench::preload_mesh(&mesh, &params.libr, cache);
    bar.finish_and_clear();
    let p = p?;
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
    Ok(())
}

/// The benchmark's case: its preload timed (cold, then warm), adaptive LIBR's basis when the
/// method needs it (adaptive, auto), the learned model attached (with the seconds that took), and the method.
fn prepare_case(
    a: &BenchRegisterArgs,
    params: &librplus::pipeline::PipelineParams,
    scenarios: &BenchScenarios,
    cache: &Path,
) -> Result<(PreloadBench, Prepared, Method, Option<f64>)> {
    let bar = spinner("preload: LIBR basis cold build, then warm load");
    let physics = librplus::eval::runs::read_physics(a.physics.as_deref())?;
    let pre = preload_model(&scenarios.geo.model, &params.libr, &physics, cache);
    bar.finish_and_clear();
    let (pre, mut case) = pre?;
    let (method, learned) = crate::register::method_and_model(a.method, a.model.as_deref())?;
    if matches!(method, Method::Adaptive | Method::Auto | Method::Nonlinear) {
        let t = std::time::Instant::now();
        case = case.with_adaptive(&params.libr, &params.adaptive, None)?;
        // On stderr: `--json` keeps stdout one JSON object.
        eprintln!(
            "adaptive LIBR's basis ({} columns) built in {:.2} s",
            case.adaptive.as_ref().map_or(0, |b| b.basis.columns()),
            t.elapsed().as_secs_f64()
        );
    }
    if let Some(edge) = a.coarse_edge_mm {
        case.basis = Some(coarse(&case.model.mesh, params, edge)?.basis);
    }
    // The learned model's preparation for the case (SR-GCN graphs; V2S grid and channels).
    let mut model_prepare_s = None;
    if let Some(l) = learned {
        let t = std::time::Instant::now();
        case = l.attach(case)?;
        model_prepare_s = Some(t.elapsed().as_secs_f64());
    }
    Ok((pre, case, method, model_prepare_s))
}

/// What `bench register` measured on a dataset.
struct Timed<'a> {
    data: &'a Path,
    geometry: &'a str,
    method: Method,
    preload: &'a PreloadBench,
    model_prepare_s: Option<f64>,
    registrations: &'a RegistrationBench,
}

impl Timed<'_> {
    /// The measurements as `--json` prints them.
    fn to_json(&self, a: &BenchRegisterArgs) -> Value {
        let r = self.registrations;
        json!({
            "data": self.data.display().to_string(),
            "data_generated": a.data.is_none(),
            "geometry": self.geometry,
            "method": self.method.name(),
            "threads": a.threads,
            "preload": preload_json(self.preload),
            "model_prepare_s": self.model_prepare_s,
            "registrations": {
                "count": r.count,
                "failed": r.failed,
                "per_category": r.per_category,
                "total_s": r.total_s,
                "first_answer_s": r.first_s,
                "answered_twice": r.answered_twice,
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
                    "v2s": r.median.v2s_s,
                    "v2s_network": r.median.v2s_network_s,
                },
                "wicp_iterations_mean": r.wicp_iterations_mean,
                "libr_iterations_mean": r.libr_iterations_mean,
                "libr_converged": r.libr_converged,
                "tre_mm_mean": r.tre_mm_mean,
            },
        })
    }

    /// The measurements as lines for a person.
    fn print(&self, a: &BenchRegisterArgs) {
        let (r, method) = (self.registrations, self.method);
        println!(
            "bench register: geometry {} of {}{}, method {}, {} registrations one at a time in a {}-thread pool",
            self.geometry,
            self.data.display(),
            if a.data.is_none() { " (generated)" } else { "" },
            method.name(),
            r.count,
            a.threads
        );
        print_preload(self.preload);
        if let Some(t) = self.model_prepare_s {
            println!(
                "{} prepared for the case in {t:.3} s",
                if method == Method::V2s {
                    "V2S grid and preoperative channels"
                } else {
                    "SR-GCN graphs"
                }
            );
        }
        print_registrations(r, method);
    }
}

/// The timings of the registrations: their spread, the stage medians and the iterations.
fn print_registrations(r: &RegistrationBench, method: Method) {
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
    if r.answered_twice > 0 || r.first_s != r.total_s {
        println!(
            "first answer (s): median {:.4}, p90 {:.4}, p99 {:.4}, max {:.4}; {} of {} answered twice (a provisional answer, then the pose search's)",
            r.first_s.median,
            r.first_s.p90,
            r.first_s.p99,
            r.first_s.max,
            r.answered_twice,
            r.count
        );
    }
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
    if method == Method::V2s {
        println!(
            "  V2S stage median (s): {:.4} (measured channels on the grid, then network and interpolation {:.4})",
            r.median.v2s_s, r.median.v2s_network_s
        );
    }
    println!(
        "  iterations (mean): wicp {:.1}, libr {:.1} (converged {}/{}); mean TRE {:.2} mm; per category {:?}",
        r.wicp_iterations_mean,
        r.libr_iterations_mean,
        r.libr_converged,
        r.count,
        r.tre_mm_mean,
        r.per_category
    );
}

/// Generates the `small` preset (seed 1) from `surface` into `dir`, quietly.
fn small_dataset(dir: &Path, surface: Option<&Path>) -> Result<()> {
    use librplus::phantom::dataset::{GenerateConfig, Preset};
    let (s, name) = liver_surface(surface, Unit::Mm).context("the default dataset")?;
    let config = GenerateConfig::preset(Preset::Small, 1, vec![name]);
    std::fs::create_dir_all(dir).with_context(|| dir.display().to_string())?;
    librplus::phantom::dataset::generate(&config, &[s], dir, (0, 1), &|_, _, _| {})
        .map_err(|e| anyhow::anyhow!("generating the small preset into {}: {e}", dir.display()))?;
    Ok(())
}

/// The LIBR basis of `mesh` built on its boundary meshed again with `edge` mm tets and carried
/// to its nodes, its times on stderr (`--json` keeps stdout one JSON object).
fn coarse(
    mesh: &librplus::mesh::TetMesh,
    params: &librplus::pipeline::PipelineParams,
    edge: f64,
) -> Result<librplus::register::libr::CoarseBasis> {
    let t = std::time::Instant::now();
    let c = librplus::register::libr::coarse_basis(mesh, &params.libr, edge)?;
    eprintln!(
        "coarse basis: {} nodes meshed again at {edge} mm to {} nodes in {:.2} s, basis {:.2} s, carried to the nodes {:.3} s; {:.2} s in all",
        mesh.num_nodes(),
        c.coarse_nodes,
        c.mesh_s,
        c.basis_s,
        c.transfer_s,
        t.elapsed().as_secs_f64()
    );
    Ok(c)
}

/// A coarse basis's figures as `--json` prints them.
fn coarse_json(c: &librplus::register::libr::CoarseBasis) -> Value {
    json!({
        "edge_mm": c.edge_mm,
        "coarse_nodes": c.coarse_nodes,
        "mesh_s": c.mesh_s,
        "basis_s": c.basis_s,
        "transfer_s": c.transfer_s,
    })
}
