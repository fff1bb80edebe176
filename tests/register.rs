//! The registration pipeline end to end on phantom data: exact when the model is right (ground
//! truth in the span of the LIBR basis, dense noiseless data), and the residual it leaves, on the
//! same data, when the truth is the phantom's physics (linear homogeneous or nonlinear
//! heterogeneous under the phantom's loads).

mod common;

use librplus::eval::tre;
use librplus::mesh::TetMesh;
use librplus::mesh::rigid::Rigid;
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::phantom::measure::{Category, MeasureParams, Scenario, simulate};
use librplus::phantom::vessels::{VesselParams, VesselTree};
use librplus::pipeline::{Method, PipelineParams, Prepared, register};
use librplus::register::anatomy::{AnatomyLabels, LabelParams, Region, label};
use librplus::register::{Checked, PreopModel};
use librplus::util::SplitMix64;

fn liver(h: f64) -> (TetMesh, AnatomyLabels, VesselTree) {
    let s = common::sofa_liver_surface();
    let mesh = tetrahedralize(&s, &TetraParams::with_edge(h)).unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let vessels = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
    (mesh, labels, vessels)
}

fn model(mesh: &TetMesh, labels: &AnatomyLabels, vessels: &VesselTree) -> PreopModel {
    labels.preop_model(mesh, &vessels.points, &vessels.segments)
}

fn measurements(sc: &Scenario) -> Checked {
    common::scenario_measurements(sc)
}

/// Dense noiseless surface and ultrasound sampling (full anterior coverage, 3 mm surface and 2 mm
/// contour spacing).
fn dense() -> MeasureParams {
    MeasureParams {
        coverage: [1.0, 1.0],
        surface_spacing_mm: 3.0,
        surface_noise_mm: 0.0,
        us_noise_mm: 0.0,
        us_spacing_mm: 2.0,
        ..MeasureParams::default()
    }
}

/// Boundary flag per node.
fn boundary_flags(labels: &AnatomyLabels) -> Vec<bool> {
    labels
        .region
        .iter()
        .map(|r| *r != Region::Interior)
        .collect()
}

/// Ground truth made by the linear model itself (u* = Φα*: eight loads at anterior control points)
/// and dense noiseless surface + 16-plane data. Loads along the surface normal (as contact loads
/// on an organ are): LIBR TRE ≤ 0.5 mm. Loads in random directions push material along the
/// surface, which closest-point data cannot see (only the regularization decides it): LIBR still
/// removes most of the error (< 0.3 × rigid) but not to 0.5 mm.
#[test]
fn libr_recovers_ground_truth_in_its_span() {
    let normal = recover_in_span(false);
    assert!(normal.0 <= 0.5, "LIBR TRE {} (normal loads)", normal.0);
    let random = recover_in_span(true);
    assert!(
        random.0 < 0.3 * random.1,
        "LIBR {} vs rigid {}",
        random.0,
        random.1
    );
}

/// Returns (LIBR TRE, rigid TRE).
fn recover_in_span(random_dir: bool) -> (f64, f64) {
    let (mesh, labels, vessels) = liver(10.0);
    // Noiseless data warrant little regularization.
    let mut params = PipelineParams::default();
    params.libr.fit.max_iterations = 60;
    params.libr.fit.regularization = 1e-4;
    let case = Prepared::new(model(&mesh, &labels, &vessels), Some(&params.libr), None).unwrap();
    let basis = case.basis.as_ref().unwrap();
    // A few loads at control points on the anterior surface (which the data cover), pressing or
    // pulling along the surface normal, or along random directions.
    let mut rng = SplitMix64::new(3);
    let mut alpha = vec![0.0; basis.columns()];
    let normals = mesh.boundary_surface().unwrap().vertex_normals();
    let anterior_cps: Vec<usize> = (0..basis.control_nodes.len())
        .filter(|&k| labels.region[basis.control_nodes[k] as usize] == Region::Anterior)
        .collect();
    for _ in 0..8 {
        let k = anterior_cps[rng.below(anterior_cps.len())];
        let n = normals[basis.control_nodes[k] as usize];
        let c = 18.0 * (rng.next_f64() - 0.5);
        for a in 0..3 {
            alpha[3 * k + a] += if random_dir {
                18.0 * (rng.next_f64() - 0.5)
            } else {
                c * n[a]
            };
        }
    }
    let u_true = basis.displacement(&alpha);
    let mean_u = u_true
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .sum::<f64>()
        / mesh.num_nodes() as f64;
    let dense = dense();
    let sc = simulate(
        &mesh,
        &labels,
        &vessels,
        &u_true,
        Category::Planes16,
        &dense,
        5,
    )
    .unwrap();
    let meas = measurements(&sc);
    let surface = boundary_flags(&labels);
    let truth = (&sc.image_to_physical, u_true.as_slice());
    let rigid = register(&case, &meas, Method::Rigid, &params).unwrap();
    let t_rigid = tre(
        mesh.nodes(),
        (&rigid.image_to_physical, &rigid.u),
        truth,
        &surface,
        &labels.targets,
    );
    let libr = register(&case, &meas, Method::Libr, &params).unwrap();
    let t_libr = tre(
        mesh.nodes(),
        (&libr.image_to_physical, &libr.u),
        truth,
        &surface,
        &labels.targets,
    );
    let info = libr.libr.as_ref().unwrap();
    eprintln!(
        "{} loads: {} nodes, {} points; |u*| mean {mean_u:.1} mm; TRE rigid {:.2} mm, LIBR {:.3} mm (surface {:.3}, interior {:.3}, targets {:.3}) in {} iterations, rms {:.3} mm, {:.0} ms",
        if random_dir {
            "random-direction"
        } else {
            "normal"
        },
        mesh.num_nodes(),
        meas.points.len(),
        t_rigid.tre_mm,
        t_libr.tre_mm,
        t_libr.tre_surface_mm,
        t_libr.tre_interior_mm,
        t_libr.tre_targets_mm,
        info.iterations,
        info.rms_mm,
        1000.0 * libr.seconds
    );
    assert!(mean_u > 3.0, "the test field must deform: {mean_u}");

    // TRE is zero for the truth itself and sees a pure misalignment in full.
    let zero = tre(mesh.nodes(), truth, truth, &surface, &labels.targets);
    assert_eq!(zero.tre_mm, 0.0);
    let shifted = Rigid {
        translation: [
            sc.image_to_physical.translation[0] + 2.0,
            sc.image_to_physical.translation[1],
            sc.image_to_physical.translation[2],
        ],
        ..sc.image_to_physical
    };
    let two = tre(
        mesh.nodes(),
        (&shifted, &u_true),
        truth,
        &surface,
        &labels.targets,
    );
    assert!((two.tre_mm - 2.0).abs() < 1e-9 && (two.max_mm - 2.0).abs() < 1e-9);
    (t_libr.tre_mm, t_rigid.tre_mm)
}

/// LIBR on dense noiseless surface + 16-plane data (the exactness test's data), with the truth
/// made by a linear field in the basis span, by the linear homogeneous model under phantom loads,
/// and by the nonlinear heterogeneous phantom under the same loads. Same data, different physics:
/// the error the nonlinear truth leaves is the model residual LIBR+ is to learn, and it stays well
/// above the in-span error. One draw of each pattern L, R, W, V (2026-11-22: in-span 0.39 mm,
/// linear homogeneous 1.62 mm, nonlinear 1.67 mm): under the phantom's loads the linear
/// homogeneous truth leaves as much as the nonlinear one, so what LIBR misses there is the loads
/// and supports outside its basis, not the material's nonlinearity.
#[test]
fn libr_residual_on_nonlinear_truth_is_well_above_its_linear_error() {
    use librplus::fem::LameField;
    use librplus::fem::hyperelastic::NewtonParams;
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::tissue::{Tissue, TissueParams};
    use librplus::phantom::truth::{LoadParts, solve_linear, solve_truth};

    let (mesh, labels, vessels) = liver(10.0);
    let mut params = PipelineParams::default();
    params.libr.fit.max_iterations = 60;
    params.libr.fit.regularization = 1e-4;
    let case = Prepared::new(model(&mesh, &labels, &vessels), Some(&params.libr), None).unwrap();
    let dense = dense();
    let surface = boundary_flags(&labels);
    let run = |u_true: &[f64], seed: u64| -> (f64, f64) {
        let sc = simulate(
            &mesh,
            &labels,
            &vessels,
            u_true,
            Category::Planes16,
            &dense,
            seed,
        )
        .unwrap();
        let meas = measurements(&sc);
        let truth = (&sc.image_to_physical, u_true);
        let libr = register(&case, &meas, Method::Libr, &params).unwrap();
        let t = tre(
            mesh.nodes(),
            (&libr.image_to_physical, &libr.u),
            truth,
            &surface,
            &labels.targets,
        );
        let mean_u = u_true
            .chunks_exact(3)
            .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
            .sum::<f64>()
            / mesh.num_nodes() as f64;
        (t.tre_mm, mean_u)
    };
    let tissue = Tissue::build(&mesh, &vessels, &TissueParams::default(), 7).unwrap();
    let (lam, mu) = TissueParams::default().parenchyma.lame();
    let mut lin_hom = Vec::new();
    let mut nonlin = Vec::new();
    for (k, pattern) in [Pattern::L, Pattern::R, Pattern::W, Pattern::V]
        .into_iter()
        .enumerate()
    {
        let lc = load_case(
            &mesh,
            &labels,
            pattern,
            &PatternParams::default(),
            11 + k as u64,
        )
        .unwrap();
        let u_lin = solve_linear(&mesh, &LameField::Uniform(lam, mu), &lc, LoadParts::ALL).unwrap();
        let u_nl = solve_truth(&mesh, &tissue.lame_field(), &lc, &NewtonParams::default())
            .unwrap()
            .displacement;
        let (e_lin, m_lin) = run(&u_lin, 21 + k as u64);
        let (e_nl, m_nl) = run(&u_nl, 21 + k as u64);
        eprintln!(
            "{pattern:?}: linear homogeneous truth (|u| {m_lin:.1} mm): LIBR {e_lin:.2} mm; nonlinear heterogeneous truth (|u| {m_nl:.1} mm): LIBR {e_nl:.2} mm"
        );
        lin_hom.push(e_lin);
        nonlin.push(e_nl);
    }
    let in_span = recover_in_span(false).0;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    eprintln!(
        "dense noiseless data, mean LIBR TRE: in-span linear {in_span:.2} mm, linear homogeneous {:.2} mm, nonlinear {:.2} mm",
        mean(&lin_hom),
        mean(&nonlin)
    );
    assert!(
        mean(&nonlin) > 3.0 * in_span,
        "nonlinear {} vs in-span {in_span}",
        mean(&nonlin)
    );
}

/// A basis built on the boundary meshed again with coarser tets and carried to the case's nodes
/// (`libr::coarse_basis`): on the linear homogeneous truth under the phantom's loads (dense
/// noiseless data) LIBR with it is far better than rigid and close to LIBR with the case's own
/// basis; its columns are interpolations (no larger than the coarse columns' 1 mm peak) on every
/// node of the case, and its energy matrix is the coarse mesh's.
#[test]
fn a_basis_from_a_coarser_mesh_registers_nearly_as_well_as_the_cases_own() {
    use librplus::fem::LameField;
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::tissue::TissueParams;
    use librplus::phantom::truth::{LoadParts, solve_linear};
    use librplus::register::libr::coarse_basis;

    let (mesh, labels, vessels) = liver(8.0);
    let params = PipelineParams::default();
    let full = Prepared::new(model(&mesh, &labels, &vessels), Some(&params.libr), None).unwrap();
    let fb = full.basis.as_ref().unwrap();
    let (lam, mu) = TissueParams::default().parenchyma.lame();
    let surface = boundary_flags(&labels);
    for edge in [16.0, 12.0] {
        let c = coarse_basis(&mesh, &params.libr, edge).unwrap();
        let cb = &c.basis;
        assert!(
            c.coarse_nodes < mesh.num_nodes() / 2,
            "{} nodes",
            c.coarse_nodes
        );
        assert_eq!(cb.nodes, mesh.num_nodes());
        assert_eq!(cb.phi.len(), 3 * mesh.num_nodes() * cb.columns());
        assert_eq!(cb.columns(), fb.columns());
        assert_ne!(
            cb.params_hash, fb.params_hash,
            "a carried basis passes for the case's own"
        );
        let peak = cb.phi.iter().fold(0.0f64, |m, &x| m.max(x.abs()));
        assert!(peak <= 1.0 + 1e-9 && peak > 0.5, "carried peak {peak} mm");
        let mut coarse = Prepared::new(model(&mesh, &labels, &vessels), None, None).unwrap();
        coarse.basis = Some(c.basis.clone());
        for (k, pattern) in [Pattern::L, Pattern::R].into_iter().enumerate() {
            let lc = load_case(
                &mesh,
                &labels,
                pattern,
                &PatternParams::default(),
                31 + k as u64,
            )
            .unwrap();
            let u = solve_linear(&mesh, &LameField::Uniform(lam, mu), &lc, LoadParts::ALL).unwrap();
            let sc = simulate(
                &mesh,
                &labels,
                &vessels,
                &u,
                Category::Planes16,
                &dense(),
                41 + k as u64,
            )
            .unwrap();
            let meas = measurements(&sc);
            let truth = (&sc.image_to_physical, u.as_slice());
            let e = |case: &Prepared, m: Method| {
                let r = register(case, &meas, m, &params).unwrap();
                let t = tre(
                    mesh.nodes(),
                    (&r.image_to_physical, &r.u),
                    truth,
                    &surface,
                    &labels.targets,
                );
                t.tre_mm
            };
            let (rigid, own, carried) = (
                e(&full, Method::Rigid),
                e(&full, Method::Libr),
                e(&coarse, Method::Libr),
            );
            eprintln!(
                "{pattern:?}, coarse {edge} mm ({} nodes against {}): TRE rigid {rigid:.2} mm, LIBR own basis {own:.2}, carried basis {carried:.2} (coarse mesh {:.2} s, basis {:.2} s, carried over {:.3} s)",
                c.coarse_nodes,
                mesh.num_nodes(),
                c.mesh_s,
                c.basis_s,
                c.transfer_s
            );
            assert!(
                carried < 0.6 * rigid,
                "carried {carried} against rigid {rigid}"
            );
            assert!(
                carried < 1.5 * own + 0.5,
                "carried {carried} against own {own}"
            );
        }
    }
}
