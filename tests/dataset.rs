//! `librplus generate --preset small`: deterministic, resumable, shardable, and readable back by the
//! project's readers, by numpy-format decoding and (when `LIBRPLUS_CHECK_PYTHON` names a Python
//! with meshio, vtk and numpy, as CI sets up) by `tests/reference/check_dataset.py`.

use librplus::dataset::read_manifest;
use librplus::mesh::io::npz::read_npz;
use librplus::mesh::io::{self, Unit};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn generate(out: &Path, extra: &[&str]) -> serde_json::Value {
    generate_seed(out, 11, extra)
}

/// `generate --preset small` with a seed.
fn generate_seed(out: &Path, seed: u64, extra: &[&str]) -> serde_json::Value {
    let manifest_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let seed = seed.to_string();
    let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
        .current_dir(&manifest_dir)
        .args([
            "generate", "--preset", "small", "--seed", &seed, "--json", "--out",
        ])
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "generate failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

/// Every file under `dir` with its bytes, by relative path.
fn tree(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.insert(
                    p.strip_prefix(dir).unwrap().to_path_buf(),
                    std::fs::read(&p).unwrap(),
                );
            }
        }
    }
    out
}

fn array<'a>(
    arrays: &'a [librplus::mesh::io::npz::NpyArray],
    name: &str,
) -> &'a librplus::mesh::io::npz::NpyArray {
    arrays
        .iter()
        .find(|a| a.name == name)
        .unwrap_or_else(|| panic!("npz has no {name}"))
}

#[test]
fn small_dataset_is_deterministic_resumable_shardable_and_reads_back() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b, c) = (
        tmp.path().join("a"),
        tmp.path().join("b"),
        tmp.path().join("c"),
    );
    let first = generate(&a, &[]);
    assert_eq!(first["complete"], true, "{first}");
    assert_eq!(first["deformations_written"], 3);
    generate(&b, &[]);
    let (ta, tb) = (tree(&a), tree(&b));
    assert_eq!(ta.keys().collect::<Vec<_>>(), tb.keys().collect::<Vec<_>>());
    for (k, v) in &ta {
        assert!(v == &tb[k], "{} differs between two runs", k.display());
    }
    // Resume: nothing is redone, nothing changes.
    let again = generate(&a, &[]);
    assert_eq!(again["deformations_resumed"], 3);
    assert_eq!(again["deformations_written"], 0);
    assert!(tree(&a) == ta, "a resumed run changed files");
    // Shards into one directory, then a final pass, give the same dataset.
    let s0 = generate(&c, &["--shard", "0/2"]);
    assert_eq!(s0["complete"], false);
    generate(&c, &["--shard", "1/2"]);
    let fin = generate(&c, &[]);
    assert_eq!(fin["deformations_written"], 0);
    assert!(tree(&c) == ta, "sharded run differs from a single run");
    // Another seed gives other data.
    let manifest_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
        .current_dir(&manifest_dir)
        .args([
            "generate", "--preset", "small", "--seed", "12", "--json", "--out",
        ])
        .arg(&a)
        .output()
        .unwrap();
    assert!(
        !o.status.success(),
        "mixing seeds in one directory must be refused"
    );
    assert!(String::from_utf8_lossy(&o.stderr).contains("other parameters"));

    // Read back with the project's own readers.
    let m = read_manifest(&a).unwrap();
    assert_eq!(m.geometries.len(), 2);
    assert_eq!(m.geometries[1].split, "test");
    let patterns: Vec<&str> = m.deformations.iter().map(|d| d.pattern.as_str()).collect();
    assert_eq!(patterns, ["L", "W", "V"]);
    for g in &m.geometries {
        let f = io::read(a.join(&g.preop), Unit::Mm).unwrap();
        assert_eq!((f.nodes.len(), f.tets.len()), (g.nodes, g.tets));
        let mesh = librplus::mesh::TetMesh::from_file(&f).unwrap();
        mesh.validate().unwrap();
        assert!((mesh.volume() / 1000.0 - g.volume_ml).abs() < 1e-6 * g.volume_ml);
        for name in [
            "region",
            "falciform",
            "inferior_ridge",
            "bare_area",
            "target",
            "tumour",
        ] {
            assert!(f.point_array(name).is_some(), "{}: no {name}", g.preop);
        }
        assert!(f.cell_data.iter().any(|c| c.name == "youngs_modulus_kpa"));
        assert!(!g.tumours.is_empty());
    }
    for d in &m.deformations {
        let gt = io::read(a.join(&d.gt), Unit::Mm).unwrap();
        let u = &gt.point_array("displacement").unwrap().values;
        let mean = u
            .chunks_exact(3)
            .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
            .sum::<f64>()
            / (u.len() / 3) as f64;
        assert!((mean - d.mean_displacement_mm).abs() < 1e-9 * mean);
        assert!(d.mean_displacement_mm > 3.0, "{}: {mean}", d.id);
        assert!(d.relative_residual <= 1e-9);
        let arrays = read_npz(&std::fs::read(a.join(&d.npz)).unwrap()).unwrap();
        assert_eq!(&array(&arrays, "displacement").data.to_f64(), u);
        let offsets = array(&arrays, "offsets").data.to_f64();
        assert_eq!(offsets.len(), d.scenarios.len() + 1);
        let points = array(&arrays, "points").data.to_f64();
        for s in &d.scenarios {
            let f = io::read(a.join(&s.file), Unit::Mm).unwrap();
            let (lo, hi) = (offsets[s.index] as usize, offsets[s.index + 1] as usize);
            assert_eq!(f.nodes.len(), hi - lo);
            assert_eq!(
                f.nodes.iter().flatten().copied().collect::<Vec<_>>(),
                points[3 * lo..3 * hi].to_vec()
            );
            assert_eq!(
                f.nodes.len(),
                s.surface_points + s.contour_points + s.vessel_points
            );
            assert!(s.surface_points > 0);
        }
        // Categories cycle through all five.
        let cats: std::collections::BTreeSet<&str> =
            d.scenarios.iter().map(|s| s.category.as_str()).collect();
        assert_eq!(cats.len(), 5);
    }

    // `register` on a scenario of the dataset: TRE against the truth, better than the start.
    let reg = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_librplus"))
            .current_dir(&manifest_dir)
            .arg("register")
            .arg("--data")
            .arg(&a)
            .args(args)
            .output()
            .unwrap()
    };
    let out_vtu = tmp.path().join("reg.vtu");
    for method in ["rigid", "libr"] {
        let o = reg(&[
            "--scenario",
            "g1-W-00/4",
            "--method",
            method,
            "--json",
            "--out",
            out_vtu.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let (t, t0) = (
            v["tre_mm"].as_f64().unwrap(),
            v["tre_initial_alignment_mm"].as_f64().unwrap(),
        );
        eprintln!(
            "register {method}: TRE {t:.2} mm from {t0:.2} mm ({})",
            v["category"]
        );
        assert_eq!(v["category"], "surface+16us");
        assert!(t.is_finite() && t < t0, "{method}: {t} vs start {t0}");
        let f = io::read(&out_vtu, Unit::Mm).unwrap();
        let e = &f.point_array("error_mm").unwrap().values;
        assert!((e.iter().sum::<f64>() / e.len() as f64 - t).abs() < 1e-9 * t.max(1.0));
        // The built-in error estimate: in the JSON and as the .vtu's `uncertainty_mm`.
        let est = &v["error_estimate"];
        let p = est["predicted_tre_mm"].as_f64().unwrap();
        assert!(p > 0.0 && p.is_finite(), "{est}");
        assert_eq!(est["level"], 0.9);
        let b = &f.point_array("uncertainty_mm").unwrap().values;
        assert_eq!(b.len(), e.len());
        assert!(b.iter().all(|x| x.is_finite() && *x >= 0.0));
        let mean_b = b.iter().sum::<f64>() / b.len() as f64;
        assert!((mean_b - est["node_uncertainty_mean_mm"].as_f64().unwrap()).abs() < 1e-9 * mean_b);
        eprintln!(
            "register {method}: predicted TRE {p:.2} mm, mean 90 % node bound {mean_b:.2} mm"
        );
    }
    for (bad, needle) in [
        ("nope/1", "no deformation"),
        ("g1-W-00/99", "has 10 scenarios"),
        ("g1-W-00", "DEFORMATION/INDEX"),
    ] {
        let o = reg(&["--scenario", bad]);
        assert!(!o.status.success());
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(needle), "{bad}: {e}");
    }

    // `evaluate`: the summary.json contract, every category, LIBR no worse than rigid overall.
    let report = tmp.path().join("report");
    let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
        .current_dir(&manifest_dir)
        .args([
            "evaluate",
            "--methods",
            "rigid,libr",
            "--split",
            "all,test",
            "--data",
        ])
        .arg(&a)
        .arg("--out")
        .arg(&report)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(report.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["format"], 1);
    for split in ["all", "test"] {
        for method in ["rigid", "libr"] {
            let s = &summary["splits"][split]["methods"][method];
            for key in [
                "tre_mm",
                "tre_surface_mm",
                "tre_interior_mm",
                "tre_targets_mm",
            ] {
                assert!(
                    s[key].as_f64().unwrap().is_finite(),
                    "{split}/{method}/{key}"
                );
            }
            let cats = s["by_category"].as_object().unwrap();
            assert_eq!(cats.len(), 5, "{split}/{method}: {cats:?}");
        }
    }
    assert_eq!(
        summary["splits"]["all"]["methods"]["rigid"]["scenarios"],
        30
    );
    assert_eq!(
        summary["splits"]["test"]["methods"]["libr"]["scenarios"],
        10
    );
    let (r, l) = (
        summary["splits"]["all"]["methods"]["rigid"]["tre_mm"]
            .as_f64()
            .unwrap(),
        summary["splits"]["all"]["methods"]["libr"]["tre_mm"]
            .as_f64()
            .unwrap(),
    );
    eprintln!("evaluate small: rigid {r:.2} mm, LIBR {l:.2} mm");
    assert!(l < r, "LIBR {l} vs rigid {r}");
    assert!(
        std::fs::read_to_string(report.join("report.md"))
            .unwrap()
            .contains("surface+16us")
    );
    check_plots(&report, &summary);
    check_error_maps(&report, &summary, &m);

    // `calibrate-error` on this dataset, checked on another seed: its in-sample true TRE is
    // evaluate's (the same registrations), its files read back, and the same dataset is refused
    // as the check.
    let held = tmp.path().join("held");
    generate_seed(&held, 12, &[]);
    let model = tmp.path().join("em").join("model.json");
    let cal = |check: &Path| {
        Command::new(env!("CARGO_BIN_EXE_librplus"))
            .current_dir(&manifest_dir)
            .args([
                "calibrate-error",
                "--methods",
                "rigid,libr",
                "--json",
                "--data",
            ])
            .arg(&a)
            .arg("--out")
            .arg(&model)
            .arg("--check")
            .arg(check)
            .output()
            .unwrap()
    };
    let o = cal(&a);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--check is a calibration dataset"));
    let o = cal(&held);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let rep: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let em = librplus::register::uncertainty::ErrorModel::from_json(
        &std::fs::read_to_string(&model).unwrap(),
    )
    .unwrap();
    assert_eq!(em.methods.keys().collect::<Vec<_>>(), ["libr", "rigid"]);
    for method in ["rigid", "libr"] {
        let c = &rep["calibration"]["checks"][method]["all"];
        let h = &rep["held_out"]["checks"][method]["all"];
        assert_eq!(c["registrations"], 30, "{c}");
        assert_eq!(h["registrations"], 30, "{h}");
        let want = summary["splits"]["all"]["methods"][method]["tre_mm"]
            .as_f64()
            .unwrap();
        let got = c["true_tre_mm"].as_f64().unwrap();
        assert!(
            (got - want).abs() < 1e-9 * want,
            "{method}: {got} vs evaluate's {want}"
        );
        let cover = h["coverage"].as_f64().unwrap();
        eprintln!(
            "calibrate-error small, {method}: held-out r {:.2}, MAE {:.2} mm, 90 % bound covers {:.1} %",
            h["r"].as_f64().unwrap_or(f64::NAN),
            h["mae_mm"].as_f64().unwrap(),
            100.0 * cover
        );
        // 30 registrations on two coarse livers: a loose sanity band, not the acceptance.
        assert!((0.6..=1.0).contains(&cover), "{method}: coverage {cover}");
    }
    let csv = std::fs::read_to_string(format!("{}.samples.csv", model.display())).unwrap();
    assert_eq!(csv.lines().count(), 1 + 4 * 30);
    // `--existing`: the written model checked on the held-out seed alone gives the calibration
    // run's held-out figures, and writes no model.
    let again = tmp.path().join("em").join("again");
    let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
        .current_dir(&manifest_dir)
        .args(["calibrate-error", "--methods", "rigid,libr", "--json"])
        .arg("--existing")
        .arg(&model)
        .arg("--data")
        .arg(&held)
        .arg("--out")
        .arg(&again)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let re: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // To rounding: the model is read back from its JSON, and the registrations' last bits may
    // differ between runs.
    for method in ["rigid", "libr"] {
        let (a, b) = (
            &re["held_out"]["checks"][method]["all"],
            &rep["held_out"]["checks"][method]["all"],
        );
        assert_eq!(a["registrations"], b["registrations"]);
        for key in ["true_tre_mm", "predicted_tre_mm", "r", "mae_mm", "coverage"] {
            let (x, y) = (a[key].as_f64().unwrap(), b[key].as_f64().unwrap());
            assert!(
                (x - y).abs() <= 1e-9 * y.abs().max(1.0),
                "--existing {method} {key}: {x} vs the calibration run's {y}"
            );
        }
    }
    assert!(!again.exists(), "--existing wrote a model");
    assert!(
        std::fs::read_to_string(format!("{}.report.md", again.display()))
            .unwrap()
            .contains("checked on")
    );

    // Independent readers (meshio, VTK, numpy) when CI provides them.
    match std::env::var("LIBRPLUS_CHECK_PYTHON") {
        Ok(py) => {
            let script = manifest_dir.join("tests/reference/check_dataset.py");
            let o = Command::new(py).arg(script).arg(&a).output().unwrap();
            eprintln!("{}", String::from_utf8_lossy(&o.stdout));
            assert!(
                o.status.success(),
                "check_dataset.py failed: {}",
                String::from_utf8_lossy(&o.stderr)
            );
        }
        Err(_) => skipped(
            "dataset: the meshio/VTK/numpy check (LIBRPLUS_CHECK_PYTHON not set; .ci/run sets it)",
        ),
    }
}

/// Width and height from a PNG's IHDR chunk, read by hand (signature, then the first chunk).
fn png_header_size(bytes: &[u8]) -> (u32, u32) {
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "not a PNG signature");
    assert_eq!(&bytes[12..16], b"IHDR", "the first chunk is not IHDR");
    let be = |o: usize| u32::from_be_bytes(bytes[o..o + 4].try_into().unwrap());
    (be(16), be(20))
}

/// The PNG plots of every split: present, listed in summary.json, the documented size, and
/// drawn (many distinct colours: fills, anti-aliased text and lines — a blank or single-colour
/// image has one or two).
fn check_plots(report: &Path, summary: &serde_json::Value) {
    for split in ["all", "test"] {
        let listed: Vec<&str> = summary["plots"][split]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        for name in [
            format!("tre_by_category_{split}.png"),
            format!("tre_cdf_{split}.png"),
        ] {
            assert!(listed.contains(&name.as_str()), "{name} not in {listed:?}");
            let bytes = std::fs::read(report.join(&name)).unwrap();
            let (w, h) = librplus::eval::plot::PLOT_SIZE;
            assert_eq!(png_header_size(&bytes), (w, h), "{name}");
            let mut reader = png::Decoder::new(std::io::Cursor::new(&bytes))
                .read_info()
                .unwrap();
            let mut buf = vec![0; reader.output_buffer_size()];
            let info = reader.next_frame(&mut buf).unwrap();
            assert_eq!((info.width, info.height), (w, h));
            assert_eq!(info.color_type, png::ColorType::Rgb, "{name}");
            let pixels = &buf[..info.buffer_size()];
            let colours: std::collections::BTreeSet<&[u8]> = pixels.chunks_exact(3).collect();
            let white = pixels
                .chunks_exact(3)
                .filter(|p| *p == [255, 255, 255])
                .count();
            let total = (w * h) as usize;
            eprintln!(
                "{name}: {} bytes, {} colours, {:.1}% white",
                bytes.len(),
                colours.len(),
                100.0 * white as f64 / total as f64
            );
            assert!(colours.len() > 50, "{name}: only {} colours", colours.len());
            assert!(white < total * 98 / 100, "{name}: almost blank");
        }
    }
}

/// The `.vtu` error maps: one per split, geometry and method, on the preoperative mesh (node
/// count from the manifest), with `tre_mean_mm` whose mean over nodes is the mean TRE of that
/// geometry's scenarios recomputed here from results.json (and equal to summary.json's
/// `by_geometry`), `tre_max_mm` ≥ `tre_mean_mm` and `tre_std_mm` ≥ 0.
fn check_error_maps(report: &Path, summary: &serde_json::Value, m: &librplus::dataset::Manifest) {
    let results: serde_json::Value =
        serde_json::from_slice(&std::fs::read(report.join("results.json")).unwrap()).unwrap();
    for (split, geometries) in [("all", vec!["g1", "g2"]), ("test", vec!["g2"])] {
        let listed = summary["error_maps"][split].as_array().unwrap();
        assert_eq!(listed.len(), 2 * geometries.len(), "{split}: {listed:?}");
        for g in &geometries {
            let nodes = m.geometries.iter().find(|x| x.id == *g).unwrap().nodes;
            for method in ["rigid", "libr"] {
                let path = report.join(format!("error_maps/{split}/{g}_{method}.vtu"));
                let f = io::read(&path, Unit::Mm).unwrap();
                assert_eq!(f.nodes.len(), nodes, "{}", path.display());
                let mean = &f.point_array("tre_mean_mm").unwrap().values;
                let max = &f.point_array("tre_max_mm").unwrap().values;
                let std = &f.point_array("tre_std_mm").unwrap().values;
                assert_eq!(mean.len(), nodes);
                for i in 0..nodes {
                    assert!(mean[i].is_finite() && max[i] >= mean[i] - 1e-12 && std[i] >= 0.0);
                }
                let map_mean = mean.iter().sum::<f64>() / nodes as f64;
                // Independent: the mean of the per-scenario TREs of this geometry and method.
                let tres: Vec<f64> = results[split]
                    .as_array()
                    .unwrap()
                    .iter()
                    .filter(|r| r["geometry"] == *g && r["method"] == method)
                    .filter_map(|r| r["tre"]["tre_mm"].as_f64())
                    .collect();
                let expect = tres.iter().sum::<f64>() / tres.len() as f64;
                assert!(
                    (map_mean - expect).abs() <= 1e-9,
                    "{split}/{g}/{method}: map {map_mean} vs scenarios {expect}"
                );
                let by_geo = &summary["splits"][split]["methods"][method]["by_geometry"][*g];
                assert_eq!(by_geo["scenarios"].as_u64().unwrap() as usize, tres.len());
                assert!((by_geo["tre_mm"].as_f64().unwrap() - map_mean).abs() <= 1e-9);
                let entry = listed
                    .iter()
                    .find(|e| e["geometry"] == *g && e["method"] == method)
                    .unwrap();
                assert_eq!(entry["scenarios"].as_u64().unwrap() as usize, tres.len());
            }
        }
    }
}

/// `--truth linear`: the control dataset's ground truth is the linear homogeneous solution of the
/// same draws. Cross-check: the mean node distance between the nonlinear dataset's truth and the
/// linear dataset's truth equals the gap the nonlinear run reported (computed there from its own
/// linear solve), and the linear run reports no gap.
#[test]
fn linear_truth_control_dataset_is_the_linear_solution_of_the_same_draws() {
    let tmp = tempfile::tempdir().unwrap();
    let (nl, lin) = (tmp.path().join("nl"), tmp.path().join("lin"));
    generate(&nl, &["--scenarios", "5"]);
    generate(&lin, &["--scenarios", "5", "--truth", "linear"]);
    let (mn, ml) = (read_manifest(&nl).unwrap(), read_manifest(&lin).unwrap());
    assert!(
        mn.parameters.get("truth").is_none(),
        "nonlinear is the unmarked default"
    );
    assert_eq!(ml.parameters["truth"], "linear_homogeneous");
    assert_ne!(mn.parameters_hash, ml.parameters_hash);
    assert_eq!(mn.deformations.len(), ml.deformations.len());
    let gt = |dir: &Path, file: &str| -> Vec<f64> {
        let f = io::read(dir.join(file), Unit::Mm).unwrap();
        f.point_data
            .iter()
            .find(|a| a.name == "displacement")
            .unwrap()
            .values
            .clone()
    };
    for (dn, dl) in mn.deformations.iter().zip(&ml.deformations) {
        assert_eq!(dn.id, dl.id);
        assert_eq!(dn.seed, dl.seed, "{}: the same draw", dn.id);
        assert_eq!(dl.linear_homogeneous_gap_mm, 0.0);
        let (un, ul) = (gt(&nl, &dn.gt), gt(&lin, &dl.gt));
        let n = un.len() / 3;
        let gap = (0..n)
            .map(|i| {
                (0..3)
                    .map(|a| (un[3 * i + a] - ul[3 * i + a]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .sum::<f64>()
            / n as f64;
        eprintln!(
            "{}: gap reported {:.6} mm, measured between the datasets {gap:.6} mm",
            dn.id, dn.linear_homogeneous_gap_mm
        );
        assert!(gap > 0.1, "{}: the nonlinear truth differs", dn.id);
        assert!(
            (gap - dn.linear_homogeneous_gap_mm).abs() <= 1e-9 * gap.max(1.0),
            "{}: {gap} vs {}",
            dn.id,
            dn.linear_homogeneous_gap_mm
        );
    }
}

/// `--paired-categories`: the five scenarios of a block share one draw (surface patch, its noise,
/// misalignment, landmarks) and differ only in their ultrasound planes, each category's planes
/// extending the previous one's. Cross-check: the first block draws from stream 0, which is the
/// unpaired dataset's first scenario, so the two datasets' first scenarios are the same.
#[test]
fn paired_categories_share_a_blocks_draw_and_add_planes() {
    use librplus::dataset::read::{ScenarioData, load_scenario_planes, load_scenarios};
    use librplus::register::MeasuredKind;
    let tmp = tempfile::tempdir().unwrap();
    let (pd, ud) = (tmp.path().join("paired"), tmp.path().join("unpaired"));
    generate(&pd, &["--scenarios", "10", "--paired-categories"]);
    generate(&ud, &["--scenarios", "10"]);
    let (mp, mu) = (read_manifest(&pd).unwrap(), read_manifest(&ud).unwrap());
    assert_eq!(mp.parameters["paired_categories"], true);
    assert!(
        mu.parameters.get("paired_categories").is_none(),
        "unpaired is the unmarked default (older datasets keep their hash)"
    );
    assert_ne!(mp.parameters_hash, mu.parameters_hash);
    let surface = |s: &ScenarioData| -> Vec<[f64; 3]> {
        let m = &s.measurements;
        (0..m.points.len())
            .filter(|&i| m.kind[i] == MeasuredKind::Surface)
            .map(|i| m.points[i])
            .collect()
    };
    assert_eq!(mp.deformations.len(), mu.deformations.len());
    for (dp, du) in mp.deformations.iter().zip(&mu.deformations) {
        assert_eq!(dp.seed, du.seed, "{}: the same deformation", dp.id);
        let (sp, su) = (
            load_scenarios(&pd, dp).unwrap(),
            load_scenarios(&ud, du).unwrap(),
        );
        let planes = load_scenario_planes(&pd, dp).unwrap();
        assert_eq!(sp.len(), 10);
        for b in 0..2 {
            let first = &sp[5 * b];
            assert_eq!(first.category, "surface");
            assert!(planes[5 * b].planes.is_empty());
            for k in 1..5 {
                let s = &sp[5 * b + k];
                assert_eq!(surface(s), surface(first), "{}: surface points", s.id);
                let (a, f) = (&s.measurements, &first.measurements);
                assert_eq!(a.initial_alignment, f.initial_alignment, "{}", s.id);
                assert_eq!(
                    s.truth.image_to_physical, first.truth.image_to_physical,
                    "{}: misalignment",
                    s.id
                );
                let (small, large) = (&planes[5 * b + k - 1].planes, &planes[5 * b + k].planes);
                assert!(large.len() > small.len(), "{}: more planes", s.id);
                assert_eq!(&large[..small.len()], &small[..], "{}: planes extend", s.id);
            }
        }
        assert_ne!(surface(&sp[5]), surface(&sp[0]), "{}: blocks differ", dp.id);
        assert_ne!(
            surface(&su[1]),
            surface(&su[0]),
            "{}: unpaired differ",
            du.id
        );
        assert_eq!(
            sp[0].measurements.points, su[0].measurements.points,
            "{}: stream 0 in both",
            dp.id
        );
    }
}

/// `--patterns` adds the augmentation X (random packs or caps) beside the paper's patterns without changing
/// any other deformation (each deformation's seed depends on its geometry, pattern and index
/// only), keeps V for the held-out geometry, and refuses unknown and repeated names by name.
#[test]
fn generate_patterns_adds_x_and_leaves_the_other_deformations_byte_identical() {
    let tmp = tempfile::tempdir().unwrap();
    let (plain, with_x) = (tmp.path().join("plain"), tmp.path().join("x"));
    generate(&plain, &["--scenarios", "2"]);
    generate(&with_x, &["--scenarios", "2", "--patterns", "W,X"]);
    let (mp, mx) = (
        read_manifest(&plain).unwrap(),
        read_manifest(&with_x).unwrap(),
    );
    let ids = |m: &librplus::dataset::Manifest| -> Vec<(String, String)> {
        m.deformations
            .iter()
            .map(|d| (d.id.clone(), d.pattern.clone()))
            .collect()
    };
    let xs = ids(&mx);
    assert!(xs.contains(&("g1-X-00".into(), "X".into())), "{xs:?}");
    assert!(xs.contains(&("g2-V-00".into(), "V".into())), "{xs:?}");
    assert!(!xs.iter().any(|(_, p)| p == "L"), "{xs:?}");
    assert_ne!(mp.parameters_hash, mx.parameters_hash);
    for id in ["g1-W-00", "g2-V-00"] {
        assert!(
            ids(&mp).iter().any(|(d, _)| d == id),
            "{id} in the plain set"
        );
        for file in ["gt.vtu", "scenarios.npz"] {
            let a = std::fs::read(plain.join("deformations").join(id).join(file)).unwrap();
            let b = std::fs::read(with_x.join("deformations").join(id).join(file)).unwrap();
            assert!(a == b, "{id}/{file} changed when X was added");
        }
    }
    let x = mx.deformations.iter().find(|d| d.pattern == "X").unwrap();
    assert!(x.mean_displacement_mm > 1.0, "X deforms: {x:?}");
    for (arg, says) in [
        ("W,", "unknown pattern \"\""),
        ("L,Q", "unknown pattern \"Q\""),
        ("W,W", "named twice"),
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
            .args(["generate", "--preset", "small", "--patterns", arg, "--out"])
            .arg(tmp.path().join("refused"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.contains("--patterns") && err.contains(says),
            "{arg}: {err}"
        );
    }
    assert!(!tmp.path().join("refused").exists());
}

/// The preoperative mesh and its labels as the dataset wrote them (`preop.vtu`).
fn preop(
    dir: &Path,
    g: &librplus::dataset::GeometryEntry,
) -> (
    librplus::mesh::TetMesh,
    librplus::register::anatomy::AnatomyLabels,
) {
    use librplus::register::anatomy::{AnatomyLabels, Region};
    let f = io::read(dir.join(&g.preop), Unit::Mm).unwrap();
    let mesh = librplus::mesh::TetMesh::from_file(&f).unwrap();
    let flags = |name: &str| -> Vec<bool> {
        f.point_array(name)
            .unwrap()
            .values
            .iter()
            .map(|&x| x > 0.5)
            .collect()
    };
    let labels = AnatomyLabels {
        region: f
            .point_array("region")
            .unwrap()
            .values
            .iter()
            .map(|&r| match r as u8 {
                1 => Region::Anterior,
                2 => Region::Posterior,
                _ => Region::Interior,
            })
            .collect(),
        falciform: flags("falciform"),
        inferior_ridge: flags("inferior_ridge"),
        bare_area: flags("bare_area"),
        targets: g.targets.clone(),
    };
    (mesh, labels)
}

/// `--truth libr --hidden-effect gravity` against `--truth libr` alone: the same loads, scenario
/// seeds, misalignments, landmarks and noise draws, the same descriptions, a different truth
/// (by exactly the gap the run reports) and the drawn gravity recorded in the manifest and in
/// `hidden_physics.json`. Without the effect (the negative control) the truth is `forward` with
/// no physics on the case's surface load (pattern L: its retractor as a traction), recomputed
/// here from the dataset's own files.
#[test]
fn libr_truth_with_a_hidden_effect_changes_the_truth_and_no_other_draw() {
    use librplus::fem::LinearMaterial;
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::truth::{LibrSites, libr_base_load};
    use librplus::register::physics::Physics;
    use librplus::register::physics::model::forward;
    let tmp = tempfile::tempdir().unwrap();
    let (plain, hidden) = (tmp.path().join("plain"), tmp.path().join("hidden"));
    generate(&plain, &["--scenarios", "5", "--truth", "libr"]);
    generate(
        &hidden,
        &[
            "--scenarios",
            "5",
            "--truth",
            "libr",
            "--hidden-effect",
            "gravity",
        ],
    );
    let (mp, mh) = (
        read_manifest(&plain).unwrap(),
        read_manifest(&hidden).unwrap(),
    );
    assert_eq!(mp.parameters["truth"], "libr");
    assert!(
        mp.parameters.get("hidden_effects").is_none(),
        "no hidden effect is the unmarked default"
    );
    assert_eq!(
        mh.parameters["hidden_effects"],
        serde_json::json!([{"kind": "gravity", "given": {}}])
    );
    assert_eq!(mh.parameters["hidden_carry"], "supports");
    assert!(mp.parameters.get("hidden_carry").is_none());
    assert_eq!(mp.deformations.len(), 3);
    assert_eq!(mp.deformations.len(), mh.deformations.len());
    let gt = |dir: &Path, file: &str| -> Vec<f64> {
        let f = io::read(dir.join(file), Unit::Mm).unwrap();
        f.point_array("displacement").unwrap().values.clone()
    };
    let f64s = |arrays: &[librplus::mesh::io::npz::NpyArray], name: &str| {
        array(arrays, name).data.to_f64()
    };
    for (dp, dh) in mp.deformations.iter().zip(&mh.deformations) {
        assert_eq!((&dp.id, dp.seed), (&dh.id, dh.seed), "the same draw");
        assert_eq!(dp.description, dh.description, "{}: the same loads", dp.id);
        assert!(dp.description.contains("truth libr"), "{}", dp.description);
        // What is hidden, recorded in the entry and beside it.
        assert_eq!(
            dp.hidden_effects,
            Some(serde_json::json!({"format": 1, "effects": []}))
        );
        let physics = Physics::read(
            &hidden
                .join("deformations")
                .join(&dh.id)
                .join("hidden_physics.json"),
        )
        .unwrap();
        // A lone load is carried by a carrier bed, recorded with its role.
        assert_eq!(physics.kinds(), ["gravity", "bed-support"]);
        let roles = serde_json::json!([{"role": "hidden"}, {"role": "carrier"}]);
        assert_eq!(
            dh.hidden_effects,
            Some(physics.to_value(roles.as_array().unwrap()))
        );
        let m = physics.effects[0].scalar("magnitude");
        assert!((0.8 * 0.0104..=1.2 * 0.0104).contains(&m), "{m}");
        // The truths differ by exactly the gap the hidden run reports (its LIBR-alone solve is
        // the plain run's truth); the plain run reports none.
        let (up, uh) = (gt(&plain, &dp.gt), gt(&hidden, &dh.gt));
        let n = up.len() / 3;
        let gap = (0..n)
            .map(|i| {
                (0..3)
                    .map(|a| (up[3 * i + a] - uh[3 * i + a]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .sum::<f64>()
            / n as f64;
        eprintln!(
            "{}: hidden gravity moves the truth {gap:.3} mm on average (reported {:.3}); {}",
            dp.id,
            dh.linear_homogeneous_gap_mm,
            physics.describe()
        );
        assert_eq!(dp.linear_homogeneous_gap_mm, 0.0);
        assert!(gap > 0.05, "{}: the hidden gravity shows", dp.id);
        assert!((gap - dh.linear_homogeneous_gap_mm).abs() <= 1e-9 * gap.max(1.0));
        // Every scenario draw is the same: seeds, misalignment, landmarks, their noise and the
        // surface points' noise (drawn in order: the common prefix).
        let ap = read_npz(&std::fs::read(plain.join(&dp.npz)).unwrap()).unwrap();
        let ah = read_npz(&std::fs::read(hidden.join(&dh.npz)).unwrap()).unwrap();
        for name in [
            "seed",
            "image_to_physical",
            "landmark_nodes",
            "landmarks_image",
        ] {
            assert!(
                array(&ap, name).data == array(&ah, name).data,
                "{}: {name} bit-identical",
                dp.id
            );
        }
        for (e, s) in dp.scenarios.iter().zip(&dh.scenarios) {
            assert_eq!(e.misalignment_deg, s.misalignment_deg);
            assert_eq!(e.seed, s.seed);
        }
        let noises = |arrays: &[librplus::mesh::io::npz::NpyArray], u: &[f64]| {
            let t = f64s(arrays, "image_to_physical");
            let apply = |k: usize, p: [f64; 3]| -> [f64; 3] {
                let m = &t[16 * k..16 * k + 16];
                [0, 1, 2].map(|r| {
                    m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3]
                })
            };
            let nodes = f64s(arrays, "landmark_nodes");
            let img = f64s(arrays, "landmarks_image");
            let phys = f64s(arrays, "landmarks_physical");
            let per = nodes.len() / 5;
            let mut landmark = Vec::new();
            for (j, &v) in nodes.iter().enumerate() {
                let (k, v) = (j / per, v as usize);
                let x = [0, 1, 2].map(|a| img[3 * j + a] + u[3 * v + a]);
                let q = apply(k, x);
                landmark.push([0, 1, 2].map(|a| phys[3 * j + a] - q[a]));
            }
            let (offsets, kind) = (f64s(arrays, "offsets"), f64s(arrays, "kind"));
            let (points, truth) = (f64s(arrays, "points"), f64s(arrays, "truth_image"));
            let surface: Vec<Vec<[f64; 3]>> = (0..5)
                .map(|k| {
                    (offsets[k] as usize..offsets[k + 1] as usize)
                        .filter(|&i| kind[i] == 0.0)
                        .map(|i| {
                            let q = apply(k, [0, 1, 2].map(|a| truth[3 * i + a]));
                            [0, 1, 2].map(|a| points[3 * i + a] - q[a])
                        })
                        .collect()
                })
                .collect();
            (landmark, surface)
        };
        let ((lp, sp), (lh, sh)) = (noises(&ap, &up), noises(&ah, &uh));
        let close = |a: &[[f64; 3]], b: &[[f64; 3]]| {
            a.iter()
                .zip(b)
                .all(|(p, q)| (0..3).all(|k| (p[k] - q[k]).abs() < 1e-9))
        };
        assert!(close(&lp, &lh), "{}: landmark noise", dp.id);
        assert!(
            lp.iter().any(|e| e.iter().any(|x| x.abs() > 1e-3)),
            "noise is there"
        );
        for (a, b) in sp.iter().zip(&sh) {
            assert!(!a.is_empty() && !b.is_empty());
            assert!(close(a, b), "{}: surface noise", dp.id);
        }
    }
    // The negative control is `forward` with no physics on the base load of LIBR's own kind.
    for d in &mp.deformations {
        let g = mp.geometries.iter().find(|g| g.id == d.geometry).unwrap();
        let (mesh, labels) = preop(&plain, g);
        let pattern = match d.pattern.as_str() {
            "L" => Pattern::L,
            "W" => Pattern::W,
            "V" => Pattern::V,
            other => panic!("pattern {other}"),
        };
        let params = PatternParams::default();
        let case = load_case(&mesh, &labels, pattern, &params, d.seed).unwrap();
        let (base, _) = libr_base_load(&mesh, &case, params.load_scale).unwrap();
        assert!(base.iter().any(|&x| x != 0.0), "{}: a base load", d.id);
        let sites = LibrSites::new(&labels);
        let want = forward(
            &mesh,
            &LinearMaterial::default(),
            sites.sites(),
            &Physics::none(),
            &base,
        )
        .unwrap();
        let got = gt(&plain, &d.gt);
        let scale = want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(scale > 0.1, "{}: it deforms", d.id);
        let err = got
            .iter()
            .zip(&want)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(err <= 1e-9 * scale, "{}: {err} mm off forward", d.id);
    }
}

/// The oracle's detectability is recorded for every deformation that hides an effect, by the
/// naming rule itself (statistic above its threshold, gain above its minimum, BIC falling): a
/// pressure at full insufflation (1.6 kPa) is seen in every deformation, the same pressure at
/// 0.02 kPa (the same direction draw) in none, and in each deformation the strong one's statistic
/// is the larger. A resumed run keeps what is recorded; `--no-detectability` and a dataset with
/// nothing hidden record none.
#[test]
fn oracle_detectability_follows_the_effects_size_and_the_naming_rule() {
    let tmp = tempfile::tempdir().unwrap();
    let (strong, weak, skip) = (
        tmp.path().join("strong"),
        tmp.path().join("weak"),
        tmp.path().join("skip"),
    );
    let run = |dir: &Path, effect: &str, extra: &[&str]| {
        let mut args = vec!["--truth", "libr", "--hidden-effect", effect];
        args.extend_from_slice(extra);
        generate(dir, &args)
    };
    let out = run(&strong, "pressure:magnitude_kpa=1.6", &[]);
    assert_eq!(out["detectability"]["computed"], 3, "{out}");
    run(&weak, "pressure:magnitude_kpa=0.02", &[]);
    let (ms, mw) = (
        read_manifest(&strong).unwrap(),
        read_manifest(&weak).unwrap(),
    );
    for (ds, dw) in ms.deformations.iter().zip(&mw.deformations) {
        let (s, w) = (
            ds.detectability.as_ref().expect("recorded"),
            dw.detectability.as_ref().expect("recorded"),
        );
        eprintln!(
            "{}: 1.6 kPa z {:.2} gain {:.3} ΔBIC {:.0}; 0.02 kPa z {:.2} gain {:.3} ΔBIC {:.0}",
            ds.id, s.statistic, s.gain, s.delta_bic, w.statistic, w.gain, w.delta_bic
        );
        for d in [s, w] {
            assert_eq!(
                d.detectable,
                d.statistic > d.threshold && d.gain > d.min_gain && d.delta_bic < 0.0
            );
            assert_eq!((d.threshold, d.min_gain), (3.0, 0.05));
            assert!(d.sweeps >= 2 && d.rows > 50, "{d:?}");
        }
        assert!(s.detectable, "{}: full insufflation is seen", ds.id);
        assert!(!w.detectable, "{}: 0.02 kPa is not", dw.id);
        assert!(s.statistic > w.statistic && s.gain > w.gain);
        // The entry beside the deformation holds the same.
        let text = std::fs::read_to_string(
            strong
                .join("deformations")
                .join(&ds.id)
                .join("deformation.json"),
        )
        .unwrap();
        let entry: librplus::dataset::DeformationEntry = serde_json::from_str(&text).unwrap();
        assert_eq!(entry.detectability.as_ref(), Some(s));
    }
    // Resumed: nothing computed again, everything kept.
    let again = run(&strong, "pressure:magnitude_kpa=1.6", &[]);
    assert_eq!(again["detectability"]["computed"], 0);
    assert_eq!(again["detectability"]["kept"], 3);
    assert_eq!(
        read_manifest(&strong).unwrap().deformations,
        ms.deformations
    );
    let none = run(&skip, "pressure", &["--no-detectability"]);
    assert!(none.get("detectability").is_none());
    assert!(
        read_manifest(&skip)
            .unwrap()
            .deformations
            .iter()
            .all(|d| d.detectability.is_none() && d.hidden_effects.is_some())
    );
}

/// `--hidden-effect` errors name what is wrong before anything is written: an unknown kind
/// (listing the known ones), an out-of-range parameter (by name), `nonlinear` (not generated
/// yet), and any hidden effect without `--truth libr`.
#[test]
fn hidden_effect_errors_name_the_kind_the_field_and_the_truth() {
    let tmp = tempfile::tempdir().unwrap();
    for (args, says) in [
        (
            &["--truth", "libr", "--hidden-effect", "foo"][..],
            &["\"foo\"", "gravity", "bed-support", "inclusion"][..],
        ),
        (
            &["--truth", "libr", "--hidden-effect", "gravity:magnitude=5"][..],
            &["magnitude", "outside"][..],
        ),
        (
            &["--truth", "libr", "--hidden-effect", "nonlinear"][..],
            &["nonlinear", "not generated"][..],
        ),
        (&["--hidden-effect", "gravity"][..], &["--truth libr"][..]),
        (
            &["--truth", "linear", "--hidden-effect", "gravity"][..],
            &["--truth libr"][..],
        ),
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_librplus"))
            .args(["generate", "--preset", "small", "--out"])
            .arg(tmp.path().join("refused"))
            .args(args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?} was accepted");
        assert!(err.contains("--hidden-effect"), "{args:?}: {err}");
        for s in says {
            assert!(err.contains(s), "{args:?}: {err} does not say {s}");
        }
    }
    assert!(!tmp.path().join("refused").exists());
}

/// Says on the terminal that a check was skipped: written to stderr directly, past the test
/// harness's output capture, so the line shows in `cargo test`'s output even when the test passes.
fn skipped(what: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr(), "SKIPPED {what}");
}
