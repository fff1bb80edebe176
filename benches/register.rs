//! Criterion benchmark of one registration (wICP then LIBR, and wICP alone) on a case of the
//! `small` dataset preset, generated into a temporary directory at setup from
//! `assets/livers/sofa_liver.vtk`. Whole-pipeline figures on the paper preset, with the preload
//! and per-stage timings, come from `librplus bench register` and are recorded in BENCHMARKS.md.

use criterion::{Criterion, criterion_group, criterion_main};
use librplus::eval::{load_geometry, load_scenarios, open};
use librplus::mesh::TriSurface;
use librplus::mesh::io::{self, Unit};
use librplus::phantom::dataset::{GenerateConfig, Preset, generate};
use librplus::pipeline::{Method, PipelineParams, Prepared, register};
use std::hint::black_box;
use std::path::PathBuf;
use std::time::Duration;

fn registration(c: &mut Criterion) {
    let surface_path =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/livers/sofa_liver.vtk");
    let file = io::read(&surface_path, Unit::Mm).expect("assets/livers/sofa_liver.vtk");
    let mut surface = TriSurface::from_file(&file)
        .expect("a triangle surface")
        .largest_component();
    if surface.signed_volume() < 0.0 {
        surface.flip();
    }
    let tmp = tempfile::tempdir().expect("a temporary directory");
    let config = GenerateConfig::preset(Preset::Small, 1, vec!["sofa_liver.vtk".into()]);
    generate(&config, &[surface], tmp.path(), (0, 1), &|_, _, _| {}).expect("small preset");
    let m = open(tmp.path()).expect("manifest");
    let geo = load_geometry(tmp.path(), &m, "g1").expect("geometry g1");
    let d = m
        .deformations
        .iter()
        .find(|d| d.geometry == "g1")
        .expect("a deformation of g1");
    let scenarios = load_scenarios(tmp.path(), d).expect("scenarios");
    // Scenario 4: surface + 16 ultrasound planes (categories cycle through the five).
    let sc = &scenarios[4];
    let params = PipelineParams::default();
    let case = Prepared::new(geo.model.clone(), Some(&params.libr), None).expect("LIBR basis");

    let mut group = c.benchmark_group(format!(
        "register_small_g1_{}_nodes_{}",
        geo.model.mesh.num_nodes(),
        sc.category
    ));
    group.sample_size(10);
    group.warm_up_time(Duration::from_secs(1));
    group.measurement_time(Duration::from_secs(5));
    for method in [Method::Libr, Method::Rigid] {
        group.bench_function(method.name(), |b| {
            b.iter(|| register(&case, black_box(&sc.measurements), method, &params).unwrap())
        });
    }
    group.finish();
}

criterion_group!(benches, registration);
criterion_main!(benches);
