//! Sanity properties every registration must have (issue 26): an undeformed liver measured
//! exactly comes back undeformed, and a rigidly moved undeformed liver comes back moved, not
//! deformed — for LIBR and for LIBR+ (the built-in model), on a phantom liver (the embedded SOFA
//! surface, meshed here) and on the real meshes of `../shared/data` (skipped, with a message, when
//! that folder is not beside the checkout).

mod common;

use librplus::mesh::TetMesh;
use librplus::mesh::io::{self, Unit};
use librplus::mesh::rigid::Rigid;
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::phantom::measure::{Category, MeasureParams, simulate};
use librplus::phantom::vessels::{VesselParams, VesselTree};
use librplus::pipeline::{Method, PipelineParams, Prepared, Registration, register};
use librplus::register::anatomy::{LabelParams, label};
use std::path::PathBuf;
use std::sync::Arc;

/// Mean over nodes of the distance between where a registration puts a node and where it is
/// (the true transform, no deformation), and the mean node displacement it returns (mm).
fn errors(mesh: &TetMesh, r: &Registration, truth: &Rigid) -> (f64, f64) {
    let n = mesh.num_nodes() as f64;
    let (mut placed, mut moved) = (0.0, 0.0);
    for (i, x) in mesh.nodes().iter().enumerate() {
        let u = [r.u[3 * i], r.u[3 * i + 1], r.u[3 * i + 2]];
        let p = r
            .image_to_physical
            .apply([x[0] + u[0], x[1] + u[1], x[2] + u[2]]);
        let q = truth.apply(*x);
        placed += ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
        moved += (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
    }
    (placed / n, moved / n)
}

/// Runs the properties on one liver mesh (mm, LPS).
fn check(name: &str, mesh: TetMesh) {
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let vessels = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
    let model = labels.preop_model(&mesh, &vessels.points, &vessels.segments);
    let params = PipelineParams::default();
    let models = librplus::gcn::io::builtin_models().unwrap();
    let case = Prepared::new(model, Some(&params.libr), None)
        .unwrap()
        .with_models(models.into_iter().map(Arc::new).collect())
        .unwrap();
    let still = vec![0.0; 3 * mesh.num_nodes()];
    // Exact points: no noise; the surface and three ultrasound planes.
    let exact = MeasureParams {
        surface_noise_mm: 0.0,
        us_noise_mm: 0.0,
        ..MeasureParams::default()
    };
    // In place, the navigation start off by 3° and ~4 mm; moved rigidly (up to 15° and 20 mm),
    // the start a fit of landmarks with 4 mm noise, as the navigation system's.
    let off = Rigid::from_axis_angle([0.2, 1.0, -0.3], 3f64.to_radians(), [3.0, -2.0, 2.0]);
    for (what, measure, start) in [
        (
            "undeformed, in place",
            MeasureParams {
                max_rotation_deg: 0.0,
                max_translation_mm: 0.0,
                ..exact
            },
            Some(off),
        ),
        ("undeformed, rigidly moved", exact, None),
    ] {
        for seed in [1, 2, 3] {
            let sc = simulate(
                &mesh,
                &labels,
                &vessels,
                &still,
                Category::Planes3,
                &measure,
                seed,
            )
            .unwrap();
            let meas = common::scenario_measurements(&sc);
            let meas = meas
                .with_alignment(Some(start.unwrap_or(sc.initial_alignment)))
                .unwrap();
            let truth = sc.image_to_physical;
            for method in [Method::Rigid, Method::Libr, Method::LibrPlus] {
                let r = register(&case, &meas, method, &params).unwrap();
                let (placed, moved) = errors(&mesh, &r, &truth);
                eprintln!(
                    "{name}, {what}, seed {seed}, {}: moved {:.1}° and {:.1} mm from the \
                     identity; nodes {placed:.3} mm from where they are, mean displacement \
                     {moved:.3} mm (rotation {:.2}° from the truth)",
                    method.name(),
                    truth.rotation_angle_deg(),
                    {
                        let c = truth.apply([0.0; 3]);
                        (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt()
                    },
                    r.image_to_physical
                        .then(&truth.inverse())
                        .rotation_angle_deg()
                );
                // wICP alone stops when its RMS settles (1e-3 mm per iteration), which
                // point-to-point ICP reaches while still sliding slowly: up to 0.75 mm here on
                // the 181-node liver. LIBR's iterations carry the rigid fit on to the pose.
                let bound = if method == Method::Rigid { 1.0 } else { 0.5 };
                assert!(
                    placed < bound && moved < 0.5,
                    "{name}, {what}, seed {seed}, {}: nodes {placed} mm off (must be < {bound}), \
                     mean displacement {moved} mm (must be < 0.5 mm)",
                    method.name()
                );
            }
        }
    }
}

#[test]
fn undeformed_livers_come_back_undeformed_and_rigid_motion_is_recovered_phantom() {
    let s = common::sofa_liver_surface();
    let mesh = tetrahedralize(&s, &TetraParams::with_edge(10.0)).unwrap();
    check("phantom SOFA liver (10 mm mesh)", mesh);
}

#[test]
fn undeformed_livers_come_back_undeformed_and_rigid_motion_is_recovered_shared_data() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    let path = dir.join("sofa_liver.msh");
    if !path.exists() {
        eprintln!(
            "SKIPPED: {} is not beside the checkout (CI has it); the phantom liver's test ran",
            path.display()
        );
        return;
    }
    let file = io::read(&path, Unit::Cm).unwrap();
    let mesh = TetMesh::from_file(&file).unwrap();
    check("../shared/data/sofa_liver.msh", mesh);
}
