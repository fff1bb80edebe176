//! `librplus register --preop` on a user's own files: a labelled tet mesh, point tables in CSV and
//! whitespace text, a VTK point file, an alignment JSON, and a bare surface meshed on the fly. The
//! result must equal the library's registration of the same measurements on the same model.

use librplus::eval::{load_geometry, load_scenarios, open};
use librplus::pipeline::{Method, PipelineParams, Prepared, register};
use librplus::register::{MeasuredKind, Measurements};
use std::path::{Path, PathBuf};
use std::process::Command;

fn run(args: &[&str]) -> (bool, String, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(args)
        .output()
        .unwrap();
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stdout).to_string(),
        String::from_utf8_lossy(&o.stderr).to_string(),
    )
}

fn dataset(tmp: &Path) -> PathBuf {
    let out = tmp.join("small");
    let (ok, _, err) = run(&[
        "generate",
        "--preset",
        "small",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    out
}

#[test]
fn own_files_register_like_the_library() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = dataset(tmp.path());
    let m = open(&dir).unwrap();
    let d = &m.deformations[0];
    let geo = load_geometry(&dir, &m, &d.geometry).unwrap();
    let sc = load_scenarios(&dir, d)
        .unwrap()
        .into_iter()
        .find(|s| s.category == "surface+2us")
        .unwrap();
    // The user's files: the labelled preoperative mesh, surface points as CSV (with a header),
    // contour points as whitespace text, the alignment as JSON.
    let user = tmp.path().join("user");
    std::fs::create_dir_all(&user).unwrap();
    let entry = m.geometries.iter().find(|g| g.id == d.geometry).unwrap();
    std::fs::copy(dir.join(&entry.preop), user.join("liver.vtu")).unwrap();
    std::fs::copy(dir.join(&entry.vessels), user.join("liver.vessels.vtp")).unwrap();
    let meas = &sc.measurements;
    let pick = |k: MeasuredKind| -> Vec<[f64; 3]> {
        meas.points
            .iter()
            .zip(&meas.kind)
            .filter(|(_, kk)| **kk == k)
            .map(|(p, _)| *p)
            .collect()
    };
    let surface = pick(MeasuredKind::Surface);
    let contour = pick(MeasuredKind::PosteriorContour);
    assert!(!surface.is_empty() && !contour.is_empty());
    let mut csv = String::from("x_mm,y_mm,z_mm\n");
    for p in &surface {
        csv += &format!("{:.17e},{:.17e},{:.17e}\n", p[0], p[1], p[2]);
    }
    std::fs::write(user.join("surface.csv"), csv).unwrap();
    let mut txt = String::from("# ultrasound contour\n");
    for p in &contour {
        txt += &format!("{:.17e} {:.17e} {:.17e}\n", p[0], p[1], p[2]);
    }
    std::fs::write(user.join("us.txt"), txt).unwrap();
    let start = meas.initial_alignment.unwrap();
    std::fs::write(
        user.join("align.json"),
        serde_json::to_string(&start).unwrap(),
    )
    .unwrap();
    let out = user.join("result.vtu");
    let args = |method: &'static str| -> Vec<String> {
        [
            "register",
            "--preop",
            user.join("liver.vtu").to_str().unwrap(),
            "--surface",
            user.join("surface.csv").to_str().unwrap(),
            "--ultrasound",
            user.join("us.txt").to_str().unwrap(),
            "--initial-alignment",
            user.join("align.json").to_str().unwrap(),
            "--unit",
            "mm",
            "--method",
            method,
            "--out",
            out.to_str().unwrap(),
            "--json",
        ]
        .map(String::from)
        .to_vec()
    };
    // The library on the same measurements (surface first, then contour, no feature flags).
    let mut points = surface.clone();
    points.extend(&contour);
    let mut kind = vec![MeasuredKind::Surface; surface.len()];
    kind.extend(vec![MeasuredKind::PosteriorContour; contour.len()]);
    let want_meas = librplus::register::Checked::new(Measurements {
        points,
        kind,
        feature: Vec::new(),
        initial_alignment: Some(start),
    })
    .unwrap();
    let p = PipelineParams::default();
    let case = Prepared::new(geo.model.clone(), Some(&p.libr), None).unwrap();
    let truth = (
        &sc.truth.image_to_physical,
        sc.truth.displacement.as_slice(),
    );
    let nodes = geo.model.mesh.nodes();
    let mut tres = Vec::new();
    for method in ["rigid", "libr"] {
        let a = args(method);
        let (ok, stdout, err) = run(&a.iter().map(String::as_str).collect::<Vec<_>>());
        assert!(ok, "{err}");
        let j: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
        assert_eq!(j["points"], surface.len() + contour.len());
        let got: librplus::mesh::rigid::Rigid =
            serde_json::from_value(j["image_to_physical"].clone()).unwrap();
        let f = librplus::mesh::io::read(&out, librplus::mesh::io::Unit::Mm).unwrap();
        let u = f.point_array("displacement").unwrap().values.clone();
        let t = librplus::eval::tre(nodes, (&got, &u), truth, &geo.surface, &geo.targets);
        tres.push(t.tre_mm);
        if method == "rigid" {
            // Rigid wICP is well conditioned: the same transform to rounding.
            let want = register(&case, &want_meas, Method::Rigid, &p).unwrap();
            for i in 0..3 {
                let dt = (got.translation[i] - want.image_to_physical.translation[i]).abs();
                assert!(dt < 1e-6, "translation {i} differs by {dt} mm");
                for k in 0..3 {
                    let dr = (got.rotation[i][k] - want.image_to_physical.rotation[i][k]).abs();
                    assert!(dr < 1e-9, "rotation differs by {dr}");
                }
            }
            assert!(u.iter().all(|&x| x == 0.0));
        } else {
            // LIBR re-matches its correspondences every iteration and on sparse data settles into
            // a cycle of a few mm, so rounding-level differences between processes (allocation
            // alignment in SIMD kernels) can move its last iterate: compare accuracy, not bits.
            let want = register(&case, &want_meas, Method::Libr, &p).unwrap();
            let tw = librplus::eval::tre(
                nodes,
                (&want.image_to_physical, &want.u),
                truth,
                &geo.surface,
                &geo.targets,
            );
            eprintln!(
                "LIBR TRE: command {:.3} mm, library {:.3} mm",
                t.tre_mm, tw.tre_mm
            );
            assert!((t.tre_mm - tw.tre_mm).abs() < 0.25 * tw.tre_mm);
        }
    }
    assert!(tres[1] < tres[0], "LIBR did not improve on rigid: {tres:?}");
    // A bare closed surface (legacy VTK, inward-facing, with stray pieces) is meshed and labelled from its geometry; a VTK point file
    // works as well; the result moves the model.
    let (ok, stdout, err) = run(&[
        "register",
        "--preop",
        "assets/livers/sofa_liver.vtk",
        "--edge-mm",
        "12",
        "--surface",
        dir.join(&d.scenarios[0].file).to_str().unwrap(),
        "--method",
        "rigid",
        "--json",
    ]);
    assert!(ok, "{err}");
    let j: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    assert!(j["nodes"].as_u64().unwrap() > 100, "{j}");
    // Bad files get errors that name them.
    std::fs::write(user.join("bad.csv"), "1,2,3\n4,five,6\n").unwrap();
    let (ok, _, err) = run(&[
        "register",
        "--preop",
        user.join("liver.vtu").to_str().unwrap(),
        "--surface",
        user.join("bad.csv").to_str().unwrap(),
    ]);
    assert!(
        !ok && err.contains("bad.csv") && err.contains("line 2"),
        "{err}"
    );
    let (ok, _, err) = run(&[
        "register",
        "--preop",
        user.join("liver.vtu").to_str().unwrap(),
        "--surface",
        user.join("surface.csv").to_str().unwrap(),
        "--method",
        "libr",
        "--model",
        user.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("--model"), "{err}");
}
