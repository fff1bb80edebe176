//! End-to-end tests of the `librplus` command line on the real livers in `assets/livers`.

use serde_json::Value;
use std::path::PathBuf;
use std::process::Command;

fn data(name: &str) -> String {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("assets/livers")
        .join(name)
        .display()
        .to_string()
}

fn librplus(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_librplus"))
        .args(args)
        .output()
        .expect("run librplus");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn json(args: &[&str]) -> Value {
    let (ok, stdout, stderr) = librplus(args);
    assert!(ok, "librplus {args:?} failed: {stderr}");
    serde_json::from_str(stdout.trim()).unwrap_or_else(|e| panic!("not JSON ({e}): {stdout}"))
}

#[test]
fn mesh_info_reports_the_contract_keys() {
    let v = json(&[
        "mesh",
        "info",
        &data("sofa_liver.msh"),
        "--unit",
        "cm",
        "--json",
    ]);
    assert_eq!(v["nodes"], 181);
    assert_eq!(v["tets"], 596);
    assert_eq!(v["surface_triangles"], 276);
    assert_eq!(v["components"], 1);
    let vol = v["volume_mm3"].as_f64().unwrap();
    assert!((vol - 36_560.0).abs() < 40.0, "{vol}");
    let dihedral = v["min_dihedral_deg"].as_f64().unwrap();
    assert!(dihedral > 0.0 && dihedral < 70.53);
    let size = &v["bbox_mm"]["size"];
    assert!((size[0].as_f64().unwrap() - 64.8259).abs() < 1e-3);
    // Surfaces report enclosed volume and orientation.
    let s = json(&["mesh", "info", &data("sofa_liver.vtk"), "--json"]);
    assert_eq!(s["kind"], "surface");
    assert_eq!(s["orientation"], "inward");
    assert_eq!(s["largest_component"]["triangles"], 9988);
}

#[test]
fn fem_sag_writes_displacement_that_reads_back() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sag.vtu");
    let v = json(&[
        "fem",
        "sag",
        "--mesh",
        &data("sofa_liver.msh"),
        "--unit",
        "cm",
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    let max = v["max_disp_mm"].as_f64().unwrap();
    assert!((max - 3.238790313769437).abs() < 1e-9, "{max}");
    assert_eq!(v["fixed_nodes"], 60);
    let file = librplus::mesh::io::read(&out, librplus::mesh::io::Unit::Mm).unwrap();
    let d = file.point_array("displacement").unwrap();
    assert_eq!((d.components, d.len()), (3, 181));
    let back = d
        .values
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .fold(0.0, f64::max);
    assert!((back - max).abs() < 1e-12);
}

#[test]
fn mesh_convert_round_trips_between_formats() {
    let dir = tempfile::tempdir().unwrap();
    let vtk = dir.path().join("liver2.vtk");
    let stl = dir.path().join("liver2.stl");
    json(&[
        "mesh",
        "convert",
        &data("sofa_liver2.msh"),
        vtk.to_str().unwrap(),
        "--json",
    ]);
    let a = json(&["mesh", "info", &data("sofa_liver2.msh"), "--json"]);
    let b = json(&["mesh", "info", vtk.to_str().unwrap(), "--json"]);
    for key in ["nodes", "tets", "surface_triangles", "components"] {
        assert_eq!(a[key], b[key], "{key}");
    }
    assert!((a["volume_mm3"].as_f64().unwrap() - b["volume_mm3"].as_f64().unwrap()).abs() < 1e-9);
    // A tet mesh written to STL keeps its outward boundary.
    json(&[
        "mesh",
        "convert",
        vtk.to_str().unwrap(),
        stl.to_str().unwrap(),
        "--json",
    ]);
    let s = json(&["mesh", "info", stl.to_str().unwrap(), "--json"]);
    assert_eq!(s["surface_triangles"], 860);
    assert_eq!(s["orientation"], "outward");
    assert!(s["closed"].as_bool().unwrap());
}

#[test]
fn bad_files_fail_with_a_message_naming_the_place() {
    let dir = tempfile::tempdir().unwrap();
    let truncated = dir.path().join("cut.msh");
    let text = std::fs::read_to_string(data("sofa_liver.msh")).unwrap();
    std::fs::write(&truncated, &text[..text.len() / 3]).unwrap();
    let (ok, _, err) = librplus(&["mesh", "info", truncated.to_str().unwrap()]);
    assert!(!ok);
    assert!(err.contains("cut.msh") && err.contains("error:"), "{err}");
    let (ok, _, err) = librplus(&["fem", "sag", "--mesh", &data("sofa_liver.vtk")]);
    assert!(!ok);
    assert!(err.contains("no tetrahedra"), "{err}");
    let (ok, _, err) = librplus(&["mesh", "info", "nowhere.xyz"]);
    assert!(!ok && err.contains("unsupported file extension"), "{err}");
    let (ok, _, err) = librplus(&["mesh", "info", &data("sofa_liver.msh"), "--unit", "inch"]);
    assert!(!ok && err.contains("inch"), "{err}");
    // A device name that is not one, and (in a CPU-only build) a GPU the build cannot use, are
    // refused before any work, naming the flag.
    let (ok, _, err) = librplus(&["--device", "tpu", "mesh", "info", &data("sofa_liver.msh")]);
    assert!(
        !ok && err.contains("--device") && err.contains("expected cpu, gpu or gpu:N"),
        "{err}"
    );
    if !cfg!(feature = "gpu") {
        let (ok, _, err) = librplus(&["mesh", "info", &data("sofa_liver.msh"), "--device", "gpu"]);
        assert!(!ok && err.contains("--features gpu"), "{err}");
    }
    let (ok, out, err) = librplus(&["mesh", "info", &data("sofa_liver.msh"), "--device", "cpu"]);
    assert!(ok && out.contains("nodes"), "{err}");
}

#[test]
fn bench_basis_solves_accurately() {
    let v = json(&[
        "bench",
        "basis",
        "--mesh",
        &data("sofa_liver2.msh"),
        "--rhs",
        "20",
        "--json",
    ]);
    assert_eq!(v["nrhs"], 20);
    assert!(v["max_rel_residual"].as_f64().unwrap() < 1e-9);
    assert!(v["dofs_free"].as_u64().unwrap() > 0);
}

#[test]
fn spare_nodes_are_removed_and_the_sag_is_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let spare = dir.path().join("spare.vtu");
    let mut file =
        librplus::mesh::io::read(data("sofa_liver.msh"), librplus::mesh::io::Unit::Cm).unwrap();
    // A node inside the bounding box, used by no tet (as Gmsh leaves geometry points behind).
    file.nodes.push([-10.0, 30.0, 0.0]);
    librplus::mesh::io::write(&spare, &file, Default::default()).unwrap();
    let (ok, stdout, stderr) =
        librplus(&["fem", "sag", "--mesh", spare.to_str().unwrap(), "--json"]);
    assert!(ok, "{stderr}");
    assert!(stderr.contains("removed 1 nodes"), "{stderr}");
    let v: Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(v["removed_unused_nodes"], 1);
    assert!((v["max_disp_mm"].as_f64().unwrap() - 3.238790313769437).abs() < 1e-9);
    // Writing a volume result to a surface format is refused before any work.
    let (ok, _, err) = librplus(&[
        "fem",
        "sag",
        "--mesh",
        &data("sofa_liver.msh"),
        "--out",
        "x.stl",
    ]);
    assert!(!ok && err.contains("surface format"), "{err}");
}

#[test]
fn mesh_tetra_meshes_a_real_liver_surface() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("smooth.vtu");
    let v = json(&[
        "mesh",
        "tetra",
        &data("sofa_liver-smooth.obj"),
        "--unit",
        "cm",
        "--edge-mm",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(
        v["volume_error_percent"].as_f64().unwrap().abs() < 2.0,
        "{v}"
    );
    assert!(v["min_dihedral_deg"].as_f64().unwrap() >= 8.0, "{v}");
    let info = json(&["mesh", "info", out.to_str().unwrap(), "--json"]);
    assert_eq!(info["nodes"], v["nodes"]);
    assert_eq!(info["inverted_tets"], 0);
    assert_eq!(info["components"], 1);
    assert_eq!(info["surface_closed"], true);
    assert!(info["nodes"].as_u64().unwrap() > 2000);
    // An open surface is refused with the reason.
    let open = dir.path().join("open.obj");
    std::fs::write(
        &open,
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\n",
    )
    .unwrap();
    let (ok, _, err) = librplus(&[
        "mesh",
        "tetra",
        open.to_str().unwrap(),
        "--edge-mm",
        "0.2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!ok && err.contains("open.obj"), "{err}");
}

/// `bench register` on the default dataset (the small preset generated into a temporary
/// directory): a cold basis build then a cache hit, five registrations (one per category), and
/// consistent statistics; `--mesh` measures the preload alone.
#[test]
fn bench_register_times_preload_and_registrations() {
    let v = json(&[
        "bench",
        "register",
        "--scenarios",
        "5",
        "--surface",
        &data("sofa_liver.vtk"),
        "--json",
    ]);
    assert_eq!(v["data_generated"], true);
    assert_eq!(v["geometry"], "g1");
    let p = &v["preload"];
    assert_eq!(p["cold"]["from_cache"], false);
    assert_eq!(p["warm"]["from_cache"], true);
    for key in ["assemble_s", "factor_s", "solve_s", "basis_total_s"] {
        assert!(p["cold"][key].as_f64().unwrap() > 0.0, "cold {key}: {p}");
    }
    assert!(p["warm"]["cache_read_s"].as_f64().unwrap() > 0.0);
    assert_eq!(p["columns"], 75);
    let r = &v["registrations"];
    assert_eq!(r["count"], 5);
    assert_eq!(r["failed"], 0);
    let cats = r["per_category"].as_object().unwrap();
    assert_eq!(cats.len(), 5, "{cats:?}");
    let t = &r["total_s"];
    let (p10, med, p90) = (
        t["p10"].as_f64().unwrap(),
        t["median"].as_f64().unwrap(),
        t["p90"].as_f64().unwrap(),
    );
    assert!(0.0 < p10 && p10 <= med && med <= p90, "{t}");
    let stages = &r["median_s"];
    assert!(stages["wicp"].as_f64().unwrap() > 0.0);
    assert!(stages["libr_matching"].as_f64().unwrap() > 0.0);
    assert!(stages["libr"].as_f64().unwrap() <= stages["total"].as_f64().unwrap() * 1.5);
    assert!(r["libr_iterations_mean"].as_f64().unwrap() >= 1.0);
    assert!(r["tre_mm_mean"].as_f64().unwrap().is_finite());

    // Adaptive LIBR's basis build is reported on stderr: with `--json`, stdout is one object.
    let a = json(&[
        "bench",
        "register",
        "--scenarios",
        "2",
        "--method",
        "adaptive",
        "--surface",
        &data("sofa_liver.vtk"),
        "--json",
    ]);
    assert_eq!(a["registrations"]["count"], 2);
    assert_eq!(a["registrations"]["failed"], 0);

    let m = json(&[
        "bench",
        "register",
        "--mesh",
        &data("sofa_liver.msh"),
        "--unit",
        "cm",
        "--json",
    ]);
    assert_eq!(m["preload"]["nodes"], 181);
    assert_eq!(m["preload"]["warm"]["from_cache"], true);
    assert!(m["registrations"].is_null());
    let (ok, _, err) = librplus(&["bench", "register", "--scenarios", "0"]);
    assert!(!ok && err.contains("--scenarios"), "{err}");
}

/// `discover` on a hidden-effect dataset: the manifest's record of what was hidden is never
/// read (rewriting it to another effect, and deleting the per-deformation files, changes nothing
/// in the output), `register --physics` carries the cohort's physics, and bad files are refused
/// with the field named.
#[test]
fn discover_never_reads_the_hidden_effect_record_and_register_carries_its_physics() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let d = data.display().to_string();
    let (ok, _, err) = librplus(&[
        "generate",
        "--preset",
        "small",
        "--seed",
        "31",
        "--truth",
        "libr",
        "--hidden-effect",
        "gravity",
        "--out",
        &d,
    ]);
    assert!(ok, "{err}");
    let run = |out: &str| -> Value {
        let o = dir.path().join(out).display().to_string();
        let mut v = json(&[
            "discover",
            "--data",
            &d,
            "--cohort",
            "g1-W-00",
            "--max-sweeps",
            "4",
            "--kinds",
            "gravity,pressure",
            "--max-effects",
            "1",
            "--out",
            &o,
            "--json",
        ]);
        for c in v["cohorts"].as_array_mut().unwrap() {
            c.as_object_mut().unwrap().remove("timings");
        }
        v
    };
    let first = run("a");
    assert_eq!(first["format"], 1);
    let c = &first["cohorts"][0];
    assert!(
        ["effects", "none", "refine-loads", "unexplained"]
            .contains(&c["verdict"].as_str().unwrap())
    );
    for k in ["before", "after"] {
        assert!(c["heldout_misfit_mm"][k].as_f64().unwrap().is_finite());
        assert!(c["tre_mm"][k].as_f64().unwrap().is_finite());
    }
    // Rewrite the hidden-effect record and delete the per-deformation copies.
    let manifest = data.join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    let mut m: Value = serde_json::from_str(&text).unwrap();
    for def in m["deformations"].as_array_mut().unwrap() {
        def["hidden_effects"] = serde_json::json!({"format": 1, "effects": [
            {"kind": "bed-support", "parameters": {"stiffness": 0.1}}]});
    }
    std::fs::write(&manifest, serde_json::to_string(&m).unwrap()).unwrap();
    for e in walk(&data) {
        if e.file_name().is_some_and(|n| n == "hidden_physics.json") {
            std::fs::remove_file(e).unwrap();
        }
    }
    let second = run("b");
    assert_eq!(first, second, "discover read the hidden-effect record");
    // The maps open as a mesh with the misfit per node; the plots are PNGs.
    let cohort_dir = dir.path().join("a/g1-W-00");
    let maps =
        librplus::mesh::io::read(cohort_dir.join("misfit.vtu"), librplus::mesh::io::Unit::Mm)
            .unwrap();
    let before = maps.point_array("heldout_before_mm").unwrap();
    assert_eq!(before.values.len(), maps.nodes.len());
    assert!(before.values.iter().any(|v| v.is_finite() && *v > 0.0));
    for png in ["misfit_by_region.png", "candidates.png"] {
        let bytes = std::fs::read(cohort_dir.join(png)).unwrap();
        assert!(bytes.starts_with(b"\x89PNG"), "{png}");
    }
    // The same on a user's own files: the preoperative mesh and one point file per sweep; no
    // truth, so no TRE.
    let own = dir.path().join("own");
    std::fs::create_dir_all(&own).unwrap();
    let scen = data.join("deformations/g1-W-00/scenarios");
    for i in 0..4 {
        let name = format!("{i:04}.vtp");
        std::fs::copy(scen.join(&name), own.join(&name)).unwrap();
    }
    let preop = data.join("geometries/g1/preop.vtu").display().to_string();
    let o3 = dir.path().join("o3").display().to_string();
    let own_s = own.display().to_string();
    let own_args = [
        "discover",
        "--preop",
        &preop,
        "--scenarios",
        &own_s,
        "--out",
        &o3,
    ];
    let v = json(&[&own_args[..], &["--json"]].concat());
    let oc = &v["cohorts"][0];
    assert_eq!(oc["cohort"], "own");
    assert_eq!(oc["sweeps"], 4);
    assert!(oc.get("tre_mm").is_none(), "TRE without truth: {oc}");
    assert!(
        oc["heldout_misfit_mm"]["before"]
            .as_f64()
            .unwrap()
            .is_finite()
    );
    // One sweep is not a cohort: the error names --scenarios.
    for i in 1..4 {
        std::fs::remove_file(own.join(format!("{i:04}.vtp"))).unwrap();
    }
    let (ok, _, err) = librplus(&own_args);
    assert!(!ok && err.contains("--scenarios"), "{err}");
    // A sweep in the wrong units: the error names the sweep and says why, once.
    let far: String = (0..200)
        .map(|i| {
            format!(
                "{} {} {}\n",
                5000.0 + (i % 20) as f64,
                5000.0 + (i / 20) as f64,
                5000.0
            )
        })
        .collect();
    std::fs::write(own.join("far.csv"), far).unwrap();
    let (ok, _, err) = librplus(&own_args);
    assert!(!ok && err.contains("scenario far"), "{err}");
    assert_eq!(err.matches("wrong units").count(), 1, "{err}");
    // register --physics carries the cohort's physics (or none).
    let physics = dir
        .path()
        .join("a/g1-W-00/physics.json")
        .display()
        .to_string();
    let r = json(&[
        "register",
        "--data",
        &d,
        "--scenario",
        "g1-W-00/0",
        "--physics",
        &physics,
        "--json",
    ]);
    let kinds: Vec<&str> = c["effects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["kind"].as_str().unwrap())
        .collect();
    let carried: Vec<&str> = r["physics"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| k.as_str().unwrap())
        .collect();
    assert_eq!(carried, kinds);
    // A bad physics file is refused with the field named.
    let bad = dir.path().join("bad.json");
    std::fs::write(
        &bad,
        r#"{"format": 1, "effects": [{"kind": "gravity", "parameters": {"direction": [0, 1, 0], "magnitude": 7}}]}"#,
    )
    .unwrap();
    let (ok, _, err) = librplus(&[
        "register",
        "--data",
        &d,
        "--scenario",
        "g1-W-00/0",
        "--physics",
        &bad.display().to_string(),
    ]);
    assert!(
        !ok && err.contains("effects[0].parameters.magnitude"),
        "{err}"
    );
    // An unknown kind on the command line.
    let (ok, _, err) = librplus(&["discover", "--data", &d, "--out", &d, "--kinds", "tides"]);
    assert!(
        !ok && err.contains("--kinds") && err.contains("tides"),
        "{err}"
    );
}

fn walk(dir: &std::path::Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

/// `discover-study` by one command (the control left out to keep it short): a dataset per kind
/// and scale, each discovered and scored;
/// study.json holds one point per dataset whose counts add up, the two curves are PNGs, a second
/// run reuses every step, and bad options are refused with the option named.
#[test]
fn discover_study_makes_its_curves_by_one_command() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("study");
    let o = out.display().to_string();
    let args = [
        "discover-study",
        "--out",
        &o,
        "--seed",
        "41",
        "--kinds",
        "gravity",
        "--scales",
        "1",
        "--geometries",
        "1",
        "--deformations",
        "1",
        "--scenarios",
        "3",
        "--no-control",
        "--json",
    ];
    let v = json(&args);
    assert_eq!(v["format"], 1);
    let points = v["points"].as_array().unwrap();
    assert_eq!(points.len(), 1, "gravity at scale 1: {v}");
    let cohorts: u64 = points.iter().map(|p| p["cohorts"].as_u64().unwrap()).sum();
    assert_eq!(
        cohorts as usize,
        v["score"]["cohorts"].as_array().unwrap().len()
    );
    for p in points {
        let (n, d) = (
            p["cohorts"].as_u64().unwrap(),
            p["detectable"].as_u64().unwrap(),
        );
        assert!(n > 0 && d <= n && p["right"].as_u64().unwrap() <= n, "{p}");
    }
    assert_eq!(v["kinds"][0]["kind"], "gravity");
    for f in [
        "study.md",
        "named.png",
        "detectable.png",
        "data/gravity-x1/manifest.json",
    ] {
        assert!(out.join(f).exists(), "{f}");
    }
    // Every step's output exists: the second run only scores, and scores the same.
    let report = out.join("reports/gravity-x1/discover.json");
    let written = std::fs::metadata(&report).unwrap().modified().unwrap();
    assert_eq!(json(&args)["points"], v["points"]);
    assert_eq!(
        std::fs::metadata(&report).unwrap().modified().unwrap(),
        written
    );
    for (bad, field) in [("--scales", "0"), ("--kinds", "nonsense")] {
        let mut a: Vec<&str> = vec!["discover-study", "--out", &o];
        a.extend([bad, field]);
        let (ok, _, err) = librplus(&a);
        assert!(!ok && err.contains(bad), "{err}");
    }
}

/// Deterministic whatever the thread count: a dataset with a Neo-Hookean truth (Newton solves,
/// sparse factorizations, many right-hand sides) and one with a hidden effect and its oracle
/// detectability are byte-identical, every file, with 1, 2 and 5 threads.
#[test]
fn generate_is_byte_identical_whatever_the_thread_count() {
    let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("thread-count-determinism");
    let _ = std::fs::remove_dir_all(&root);
    let runs: [&[&str]; 2] = [
        &[
            "--preset",
            "small",
            "--seed",
            "5",
            "--geometries",
            "1",
            "--deformations",
            "1",
            "--scenarios",
            "3",
        ],
        &[
            "--preset",
            "small",
            "--truth",
            "libr",
            "--hidden-effect",
            "bed-support",
            "--seed",
            "6",
            "--geometries",
            "1",
            "--deformations",
            "1",
            "--scenarios",
            "10",
        ],
    ];
    for (r, args) in runs.iter().enumerate() {
        let mut first: Option<Vec<(PathBuf, Vec<u8>)>> = None;
        for threads in [1, 2, 5] {
            let out = root.join(format!("run{r}-t{threads}"));
            let status = Command::new(env!("CARGO_BIN_EXE_librplus"))
                .arg("generate")
                .args(*args)
                .arg("--out")
                .arg(&out)
                .env("RAYON_NUM_THREADS", threads.to_string())
                .output()
                .expect("run librplus generate");
            assert!(
                status.status.success(),
                "generate {args:?} with {threads} threads: {}",
                String::from_utf8_lossy(&status.stderr)
            );
            let mut files: Vec<(PathBuf, Vec<u8>)> = walk(&out)
                .into_iter()
                .map(|p| {
                    let bytes = std::fs::read(&p).unwrap();
                    (p.strip_prefix(&out).unwrap().to_path_buf(), bytes)
                })
                .collect();
            files.sort();
            assert!(
                files.len() >= 8,
                "only {} files in {}",
                files.len(),
                out.display()
            );
            match &first {
                None => first = Some(files),
                Some(one) => {
                    let names = |f: &[(PathBuf, Vec<u8>)]| {
                        f.iter().map(|x| x.0.clone()).collect::<Vec<_>>()
                    };
                    assert_eq!(
                        names(one),
                        names(&files),
                        "run {r}: other files with {threads} threads"
                    );
                    for ((name, a), (_, b)) in one.iter().zip(&files) {
                        assert!(
                            a == b,
                            "run {r}: {} differs between 1 and {threads} threads",
                            name.display()
                        );
                    }
                }
            }
        }
    }
}
