//! What keeps a registration's cost from growing with what it is sent: Anderson-accelerated
//! ICP (`register::accelerate`) reaches plain ICP's pose in a fraction of its iterations, and a
//! dense surface cloud reduced to weighted cell centroids (`register::reduce`) registers as the
//! whole cloud does.
//!
//! Data: the SOFA liver meshed with 10 mm tets and labelled by the phantom module; scenarios
//! from `phantom::measure::simulate` on the undeformed liver, whose true pose is known.

mod common;

use librplus::mesh::rigid::Rigid;
use librplus::phantom::measure::{Category, MeasureParams, Scenario, simulate};
use librplus::pipeline::{Method, PipelineParams, Prepared, register};
use librplus::register::correspondence::Correspondence;
use librplus::register::wicp::{WicpParams, wicp};

fn scenario(category: Category, params: &MeasureParams, seed: u64) -> Scenario {
    let l = common::labelled_liver();
    let u = vec![0.0; 3 * l.mesh.num_nodes()];
    simulate(&l.mesh, &l.labels, &l.vessels, &u, category, params, seed).unwrap()
}

/// RMS over the mesh nodes of the distance between two placements `t(X + u)` (mm).
fn gap(t: &Rigid, u: &[f64], s: &Rigid, v: &[f64]) -> f64 {
    let nodes = common::labelled_liver().mesh.nodes();
    let sum: f64 = nodes
        .iter()
        .enumerate()
        .map(|(i, &x)| {
            let a = t.apply([0, 1, 2].map(|k| x[k] + u[3 * i + k]));
            let b = s.apply([0, 1, 2].map(|k| x[k] + v[3 * i + k]));
            (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>()
        })
        .sum();
    (sum / nodes.len() as f64).sqrt()
}

#[test]
fn accelerated_icp_reaches_the_plain_fixed_point_in_fewer_iterations() {
    let l = common::labelled_liver();
    let corr = Correspondence::new(&l.model).unwrap();
    let zero = vec![0.0; 3 * l.mesh.num_nodes()];
    // Converged to the fixed point: a tolerance far below the noise.
    let tight = WicpParams {
        max_iterations: 2000,
        tolerance_mm: 1e-7,
        ..WicpParams::default()
    };
    let (mut plain_its, mut fast_its) = (0, 0);
    for (category, seed) in [
        (Category::Surface, 31),
        (Category::Planes1, 32),
        (Category::Planes3, 33),
        (Category::Surface, 34),
    ] {
        let params = MeasureParams {
            max_rotation_deg: 25.0,
            ..MeasureParams::default()
        };
        let s = scenario(category, &params, seed);
        let meas = common::scenario_measurements(&s);
        let run = |accelerate| {
            let p = WicpParams {
                accelerate,
                ..tight
            };
            wicp(&l.model, &corr, &meas, &p).unwrap()
        };
        let (plain, fast) = (run(false), run(true));
        let apart = gap(
            &plain.image_to_physical,
            &zero,
            &fast.image_to_physical,
            &zero,
        );
        let err = gap(&fast.image_to_physical, &zero, &s.image_to_physical, &zero);
        eprintln!(
            "{} seed {seed}: plain {} iterations (converged {}), accelerated {} ({}); the poses \
             {apart:.4} mm apart, {err:.2} mm from the truth",
            category.name(),
            plain.iterations,
            plain.converged,
            fast.iterations,
            fast.converged
        );
        assert!(plain.converged && fast.converged);
        assert!(apart < 0.1, "{apart} mm between the two fixed points");
        // The same fit: its residual within a hundredth of a millimetre.
        assert!(
            (fast.rms_mm - plain.rms_mm).abs() < 1e-2,
            "{} vs {}",
            fast.rms_mm,
            plain.rms_mm
        );
        plain_its += plain.iterations;
        fast_its += fast.iterations;
    }
    assert!(
        2 * fast_its <= plain_its,
        "accelerated {fast_its} iterations against plain {plain_its}"
    );
}

#[test]
fn a_dense_cloud_reduced_registers_as_the_whole_cloud() {
    let l = common::labelled_liver();
    let params = PipelineParams::default();
    let case = Prepared::new(l.model.clone(), Some(&params.libr), None).unwrap();
    let dense = MeasureParams {
        coverage: [0.5, 0.5],
        surface_spacing_mm: 1.0,
        ..MeasureParams::default()
    };
    for (category, seed) in [(Category::Surface, 41), (Category::Planes3, 42)] {
        let s = scenario(category, &dense, seed);
        let meas = common::scenario_measurements(&s);
        let whole = register(
            &case,
            &meas,
            Method::Libr,
            &PipelineParams {
                reduce_above: 0.0,
                ..params.clone()
            },
        )
        .unwrap();
        let reduced = register(&case, &meas, Method::Libr, &params).unwrap();
        let info = reduced.points.expect("a 1 mm cloud is reduced");
        assert!(whole.points.is_none());
        assert_eq!(info.received, meas.points.len());
        let zero = vec![0.0; whole.u.len()];
        let truth = |r: &librplus::pipeline::Registration| {
            gap(&r.image_to_physical, &r.u, &s.image_to_physical, &zero)
        };
        let apart = gap(
            &whole.image_to_physical,
            &whole.u,
            &reduced.image_to_physical,
            &reduced.u,
        );
        eprintln!(
            "{} seed {seed}: {} points reduced to {} (cells {:.1} mm); error {:.3} mm whole, \
             {:.3} reduced, {apart:.3} mm apart",
            category.name(),
            info.received,
            info.used,
            info.cell_mm,
            truth(&whole),
            truth(&reduced)
        );
        // Within the budget: the floor of 4,000 points (the model's half-triangle count is below).
        assert!(
            info.used <= 4200 && 2 * info.used < info.received,
            "{info:?}"
        );
        assert!(apart < 0.5, "the answers are {apart} mm apart");
        assert!((truth(&whole) - truth(&reduced)).abs() < 0.25);
    }
}
