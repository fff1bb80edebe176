//! Criterion benchmarks of the linear FEM kernels on a procedural box mesh (~9K nodes), so they run
//! anywhere without data files. Whole-pipeline figures (real liver meshes, side by side with the
//! Python peer) come from `librplus bench basis` and are recorded in BENCHMARKS.md.

use criterion::{Criterion, criterion_group, criterion_main};
use faer::Mat;
use librplus::fem::{Dirichlet, LinearMaterial, StiffnessSystem};
use librplus::mesh::procedural::box_mesh;
use std::hint::black_box;

fn fem(c: &mut Criterion) {
    let mesh = box_mesh([100.0, 80.0, 60.0], [24, 20, 16], 0.3);
    let mat = LinearMaterial::default();
    let mut group = c.benchmark_group("linear_fem_box_9k_nodes");
    group.sample_size(10);
    group.bench_function("assemble", |b| {
        b.iter(|| StiffnessSystem::linear(black_box(&mesh), &mat).unwrap())
    });
    let sys = StiffnessSystem::linear(&mesh, &mat).unwrap();
    let fixed: Vec<u32> = (0..mesh.num_nodes() as u32)
        .filter(|&i| mesh.nodes()[i as usize][1] > 64.0)
        .collect();
    let mut bc = Dirichlet::new(mesh.num_nodes());
    bc.fix_nodes(&fixed);
    group.bench_function("factorize", |b| {
        b.iter(|| sys.factorize(black_box(&bc)).unwrap())
    });
    let fact = sys.factorize(&bc).unwrap();
    let nf = fact.free_dofs().len();
    group.bench_function("solve_300_rhs", |b| {
        b.iter(|| {
            let mut x = Mat::<f64>::zeros(nf, 300);
            for j in 0..300 {
                x[((j * 7919) % nf, j)] = 1.0;
            }
            fact.solve_free_in_place(x.as_mut());
            x
        })
    });
    group.finish();
}

criterion_group!(benches, fem);
criterion_main!(benches);
