//! Tests of the case store (`store/`).

use super::*;
use librplus::mesh::io::{Format, MeshFile};

/// A 120 × 90 × 60 mm box of 144 positive tets (60 nodes).
fn cube() -> (Vec<f64>, Vec<u32>) {
    let m = librplus::mesh::procedural::box_mesh([120.0, 90.0, 60.0], [4, 3, 2], 0.2);
    (
        m.nodes().iter().flatten().copied().collect(),
        m.tets().iter().flatten().copied().collect(),
    )
}

fn upload(id: &str, nodes: Vec<f64>, tets: Vec<u32>) -> Upload {
    Upload {
        case_id: id.into(),
        mesh: MeshSource::Arrays { nodes, tets },
        unit: String::new(),
        vessels: None,
        physics: None,
    }
}

#[test]
fn ids_are_checked() {
    for ok in ["a", "hospital-a/p001", "P.1_x"] {
        assert!(check_id(ok).is_ok(), "{ok}");
    }
    for bad in [
        "",
        "/a",
        "a/",
        "a//b",
        "a/../b",
        "..",
        "a b",
        "ä",
        &"x".repeat(129),
    ] {
        assert!(check_id(bad).is_err(), "{bad:?}");
    }
    assert_eq!(check_id("a b"), Err(CaseIdError::Character(' ')));
    assert_eq!(check_id("a//b"), Err(CaseIdError::Segment));
    assert_eq!(
        check_id("").unwrap_err().to_string(),
        "must be 1 to 128 characters"
    );
    assert_eq!(
        unit("in").unwrap_err().to_string(),
        "\"in\": expected mm, cm or m"
    );
}

#[test]
fn uploads_are_checked_naming_the_problem() {
    let (n, t) = cube();
    let c = check(&upload("a", n.clone(), t.clone()), 100).unwrap();
    assert_eq!((c.nodes, c.tets), (60, 144));
    // The same content has the same version; another content another.
    assert_eq!(
        c.version,
        check(&upload("b", n.clone(), t.clone()), 100)
            .unwrap()
            .version
    );
    let mut moved = n.clone();
    moved[0] = -1.0;
    assert_ne!(
        c.version,
        check(&upload("a", moved, t.clone()), 100).unwrap().version
    );
    let msg = |u: Upload| {
        check(&u, 100)
            .unwrap_err()
            .to_status()
            .message()
            .to_string()
    };
    let mut nan = n.clone();
    nan[4] = f64::NAN;
    assert!(msg(upload("a", nan, t.clone())).contains("upload.nodes_mm[4]"));
    let mut flipped = t.clone();
    flipped.swap(6, 7); // tet 1 inverted, the others not: tangled
    let e = msg(upload("a", n.clone(), flipped));
    assert!(e.contains("tet 1 is inverted"), "{e}");
    let mut out = t.clone();
    out[7] = 999;
    assert!(msg(upload("a", n.clone(), out)).contains("upload.tets[7]"));
    // Tet 0's last node onto its first: tet 0 flat.
    let mut flat = n.clone();
    let (a, d) = (t[0] as usize, t[3] as usize);
    for k in 0..3 {
        flat[3 * d + k] = flat[3 * a + k];
    }
    let e = msg(upload("a", flat, t.clone()));
    assert!(e.contains("degenerate"), "{e}");
    let e = check(&upload("a", n.clone(), t.clone()), 4).unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted);
    let corrupt = Upload {
        mesh: MeshSource::File {
            bytes: b"<VTKFile type=\"UnstructuredGrid\"><Piece".to_vec(),
            format: "vtu".into(),
        },
        ..upload("a", vec![], vec![])
    };
    assert!(msg(corrupt).starts_with("mesh:"));
    let physics = |json: &str| Upload {
        physics: Some(json.as_bytes().to_vec()),
        ..upload("a", n.clone(), t.clone())
    };
    let e = msg(physics(
        r#"{"format": 1, "effects": [{"kind": "magnetism"}]}"#,
    ));
    assert!(e.starts_with("physics.json: effects[0].kind"), "{e}");
    // What preload refused after the upload was stored (issue: upload checks weaker than
    // preload's).
    let e = msg(physics(
        r#"{"format": 1, "effects": [{"kind": "nonlinear"}]}"#,
    ));
    assert!(
        e.starts_with("physics.json: effects[0].kind") && e.contains("nonlinear"),
        "{e}"
    );
    // A pack by the corner (120, 0, 0): on it, and 40 mm beyond.
    let pack = |x: f64, width: f64| {
        format!(
            r#"{{"format": 1, "effects": [{{"kind": "gravity", "parameters": {{"direction": [0, 0, -1], "magnitude": 0.01}}}}, {{"kind": "pack", "parameters": {{"center": [{x}, 0, 0], "width_mm": {width}, "force_mn": [-100, 0, 0]}}}}]}}"#
        )
    };
    let e = msg(physics(&pack(160.0, 15.0)));
    assert!(
        e.starts_with("physics.json: effects[1].parameters.center")
            && e.contains("40.0 mm from the organ's surface")
            && e.contains("30.0 mm"),
        "{e}"
    );
    check(&physics(&pack(120.0, 25.0)), 100).unwrap();
    let mut unused = n.clone();
    unused.extend([60.0, 45.0, 30.0]);
    let e = msg(upload("a", unused, t.clone()));
    assert!(
        e.starts_with("upload.nodes_mm: node 60 is in no tetrahedron"),
        "{e}"
    );
    let mut twice = t.clone();
    twice.extend([t[5], t[6], t[4], t[7]]);
    let e = msg(upload("a", n.clone(), twice));
    assert!(e.starts_with("upload.tets: tet 144 repeats tet 1"), "{e}");
    // Sizes: in µm as nodes_mm, in mm declared m or cm, in cm declared mm.
    let scaled = |f: f64| n.iter().map(|x| x * f).collect::<Vec<f64>>();
    let e = msg(upload("a", scaled(1000.0), t.clone()));
    assert!(
        e.contains("spans 120,000 mm") && e.contains("1,000 times too large"),
        "{e}"
    );
    let file = |nodes: Vec<f64>, unit: &str| {
        let m = MeshFile {
            nodes: nodes.chunks(3).map(|c| [c[0], c[1], c[2]]).collect(),
            tets: t.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect(),
            ..Default::default()
        };
        Upload {
            mesh: MeshSource::File {
                bytes: io::write_bytes(
                    &m,
                    Format::Vtu,
                    io::WriteOptions::default(),
                    Path::new("m.vtu"),
                )
                .unwrap(),
                format: "vtu".into(),
            },
            unit: unit.into(),
            ..upload("a", vec![], vec![])
        }
    };
    let e = msg(file(n.clone(), "m"));
    assert!(
        e.starts_with("upload.mesh_unit: the mesh spans 120,000 mm")
            && e.contains("mesh_unit \"m\": is its unit mm?"),
        "{e}"
    );
    let e = msg(file(n.clone(), "cm"));
    assert!(e.contains("is its unit mm?"), "{e}");
    let e = msg(file(scaled(0.1), ""));
    assert!(
        e.contains("spans 12.0 mm") && e.contains("is its unit cm?"),
        "{e}"
    );
    assert!(check(&file(scaled(0.1), "cm"), 100).is_ok());
    let e = msg(upload("a", scaled(1e300), t.clone()));
    assert!(e.contains("1.20e302 mm") && e.len() < 300, "{e}");
    let e = msg(Upload {
        unit: "m".into(),
        ..upload("a", n.clone(), t.clone())
    });
    assert!(e.starts_with("upload.mesh_unit"), "{e}");
}

#[test]
fn numbers_and_sizes_read_well() {
    assert_eq!(number(200_000.0), "200,000");
    assert_eq!(number(1234.4), "1,234");
    assert_eq!(number(40.04), "40.0");
    assert_eq!(number(0.25), "0.250");
    assert_eq!(number(1e300), "1.00e300");
    assert_eq!(bytes(12), "12 bytes");
    assert_eq!(bytes(3 << 20), "3.0 MiB");
}

#[test]
fn the_store_writes_atomically_and_is_content_addressed() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let (n, t) = cube();
    let u = upload("hospital-a/p1", n.clone(), t.clone());
    let c = check(&u, 100).unwrap();
    let (s, created) = store.put(&u, &c, "or-a", &Quotas::NONE).unwrap();
    assert!(created);
    assert!(s.mesh_path().is_file());
    assert_eq!((s.checks, s.bytes), (CHECKS, c.mesh_bytes.len() as u64));
    let (again, created) = store.put(&u, &c, "or-a", &Quotas::NONE).unwrap();
    assert!(!created);
    assert_eq!(again.version, s.version);
    let mut moved = n;
    moved[0] = -1.0;
    let other = upload("hospital-a/p1", moved, t);
    let e = store
        .put(&other, &check(&other, 100).unwrap(), "or-a", &Quotas::NONE)
        .unwrap_err();
    assert!(matches!(e, StoreError::Exists { .. }), "{e}");
    // A leftover of an interrupted upload is cleared at open; the case reads back.
    std::fs::create_dir(dir.path().join(".upload-dead")).unwrap();
    let store = Store::open(dir.path()).unwrap();
    assert!(!dir.path().join(".upload-dead").exists());
    let all = store.list().unwrap();
    assert_eq!(all.len(), 1);
    assert_eq!(all[0].as_ref().unwrap().case_id, "hospital-a/p1");
    assert!(
        store
            .remove_version("hospital-a/p1", Some("other"))
            .unwrap()
            .is_none()
    );
    assert!(store.remove("hospital-a/p1").unwrap().is_some());
    assert!(store.find("hospital-a/p1").is_none());
    assert!(store.list().unwrap().is_empty());
}

#[test]
fn quotas_bound_the_store_per_principal_and_in_total() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let (n, t) = cube();
    let put = |id: &str, who: &str, q: &Quotas| {
        let mut nodes = n.clone();
        nodes[0] = -(id.len() as f64); // other content, another version
        let u = upload(id, nodes, t.clone());
        store.put(&u, &check(&u, 100).unwrap(), who, q)
    };
    let size = check(&upload("x", n.clone(), t.clone()), 100)
        .unwrap()
        .mesh_bytes
        .len() as u64;
    let q = Quotas {
        cases: 3,
        bytes: 10 * size,
        cases_per_principal: 2,
        bytes_per_principal: 10 * size,
        basis_columns: [0, 0],
    };
    put("a1", "a", &q).unwrap();
    put("a22", "a", &q).unwrap();
    let quota = |r: Result<(Stored, bool), StoreError>| match r {
        Err(StoreError::Quota { quota, message }) => {
            let s = StoreError::Quota { quota, message }
                .into_service()
                .to_status();
            assert_eq!(s.code(), tonic::Code::ResourceExhausted);
            assert!(s.message().contains(quota), "{}", s.message());
            quota
        }
        other => panic!("{other:?}"),
    };
    assert_eq!(quota(put("a333", "a", &q)), "max_cases_per_principal");
    put("b1", "b", &q).unwrap();
    assert_eq!(quota(put("c1", "c", &q)), "max_stored_cases");
    // The same content again is no new case.
    assert!(!put("a1", "a", &q).unwrap().1);
    store.remove("a1").unwrap();
    let u = store.usage("a").unwrap();
    assert_eq!((u.cases, u.principal_cases), (2, 1));
    let small = Quotas {
        bytes_per_principal: u.principal_bytes + size / 2,
        ..q
    };
    assert_eq!(quota(put("a1", "a", &small)), "max_bytes_per_principal");
    let small = Quotas {
        bytes: u.bytes + size / 2,
        ..q
    };
    assert_eq!(quota(put("a1", "a", &small)), "max_stored_bytes");
    put("a1", "a", &q).unwrap();
    assert_eq!(store.list().unwrap().len(), 3);
}

#[test]
fn a_stored_case_older_checks_refuse_is_removed_when_listed() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let (n, t) = cube();
    let good = upload("good", n.clone(), t.clone());
    store
        .put(&good, &check(&good, 100).unwrap(), "a", &Quotas::NONE)
        .unwrap();
    // As a server with older checks stored them: a `nonlinear` physics, and a good one.
    let bad = Upload {
        physics: Some(br#"{"format": 1, "effects": [{"kind": "nonlinear"}]}"#.to_vec()),
        ..upload("bad", n, t)
    };
    let c = Checked {
        mesh_name: "mesh.vtu".into(),
        mesh_bytes: check(&good, 100).unwrap().mesh_bytes,
        nodes: 60,
        tets: 144,
        version: "0".repeat(64),
    };
    store.put(&bad, &c, "a", &Quotas::NONE).unwrap();
    for id in ["good", "bad"] {
        let f = store.folder(id).join("case.json");
        let mut v: serde_json::Value = serde_json::from_slice(&std::fs::read(&f).unwrap()).unwrap();
        let o = v.as_object_mut().unwrap();
        o.remove("checks");
        o.remove("bytes");
        std::fs::write(&f, serde_json::to_vec(&v).unwrap()).unwrap();
    }
    let listed = store.list().unwrap();
    assert_eq!(listed.len(), 2);
    let errors: Vec<String> = listed
        .iter()
        .filter_map(|r| r.as_ref().err().map(|e| e.to_string()))
        .collect();
    assert_eq!(errors.len(), 1, "{errors:?}");
    assert!(
        errors[0].contains("\"bad\"")
            && errors[0].contains("removed from the case store")
            && errors[0].contains("effects[0].kind"),
        "{}",
        errors[0]
    );
    assert!(store.find("bad").is_none());
    let good = store.find("good").unwrap();
    assert_eq!(good.checks, CHECKS);
    assert!(good.bytes > 0);
    assert_eq!(store.list().unwrap().len(), 1);
}

/// A case counts against the quotas with the LIBR bases its preload will cache from the moment
/// it is stored: back-to-back uploads cannot pass a byte quota before their caches are written.
#[test]
fn a_stored_case_counts_its_basis_cache_before_it_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path()).unwrap();
    let (n, t) = cube();
    let columns = basis_columns(false);
    assert_eq!(
        columns,
        [
            3 * librplus::pipeline::PipelineParams::default()
                .libr
                .basis
                .control_points,
            0
        ]
    );
    let with_adaptive = basis_columns(true);
    assert_eq!(with_adaptive[0], columns[0]);
    assert!(with_adaptive[1] > columns[0], "{with_adaptive:?}");
    let put = |id: &str, q: &Quotas| {
        let mut nodes = n.clone();
        nodes[0] = -(id.len() as f64);
        let u = upload(id, nodes, t.clone());
        store.put(&u, &check(&u, 100).unwrap(), "a", q)
    };
    let files = check(&upload("x", n.clone(), t.clone()), 100)
        .unwrap()
        .mesh_bytes
        .len() as u64;
    let nodes = n.len() / 3;
    let reserve = basis_cache_bytes(nodes, columns[0]);
    assert!(reserve > files, "{reserve} vs {files}");
    // Room for two cases with their caches, not three.
    let q = Quotas {
        bytes_per_principal: 2 * (files + reserve) + reserve / 2,
        basis_columns: columns,
        ..Quotas::NONE
    };
    let (s1, _) = put("a1", &q).unwrap();
    assert_eq!(s1.cache_reserve, reserve);
    let u = store.usage("a").unwrap();
    assert_eq!(u.principal_bytes, files + reserve, "nothing cached yet");
    put("a22", &q).unwrap();
    match put("a333", &q) {
        Err(StoreError::Quota { quota, message }) => {
            assert_eq!(quota, "max_bytes_per_principal");
            assert!(message.contains("LIBR bases"), "{message}");
        }
        other => panic!("a third case fits: {other:?}"),
    }
    // Once the cache is written, the folder's own size counts (here larger than reserved).
    let cache = s1.dir.join("cache");
    std::fs::create_dir_all(&cache).unwrap();
    std::fs::write(cache.join("basis.npz"), vec![0u8; 2 * reserve as usize]).unwrap();
    let u2 = store.usage("a").unwrap();
    assert!(u2.principal_bytes >= u.principal_bytes + 2 * reserve);
}

/// The estimate of a basis cache against the file the library writes (a stored `.npz` of the
/// basis, its energy matrix and small arrays): within a few kilobytes of it, never below.
#[test]
fn the_basis_cache_estimate_matches_a_written_cache() {
    use librplus::register::libr::{LibrBasis, LibrParams};
    let mesh = librplus::mesh::procedural::box_mesh([120.0, 90.0, 60.0], [6, 5, 4], 0.2);
    let dir = tempfile::tempdir().unwrap();
    let (basis, _) = LibrBasis::load_or_build(&mesh, &LibrParams::default(), dir.path()).unwrap();
    let written: u64 = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    let estimate = basis_cache_bytes(mesh.num_nodes(), basis.columns());
    assert_eq!(basis.columns(), basis_columns(false)[0]);
    eprintln!(
        "{} nodes, {} columns: cache {written} bytes, estimate {estimate}",
        mesh.num_nodes(),
        basis.columns()
    );
    assert!(estimate >= written, "{estimate} < {written}");
    assert!(estimate - written < 8192, "{estimate} vs {written}");
}

/// The same for adaptive LIBR's multi-level basis, the second file of a case's cache when the
/// server prepares it (the default): its columns are the ones the quota reserves.
#[test]
fn the_adaptive_basis_cache_estimate_matches_its_written_file() {
    use librplus::register::libr::{AdaptiveParams, LibrBasis, LibrParams};
    use librplus::register::physics::{Physics, model::Sites};
    let mesh = librplus::mesh::procedural::box_mesh([120.0, 90.0, 60.0], [6, 5, 4], 0.2);
    let dir = tempfile::tempdir().unwrap();
    let levels = AdaptiveParams::default().levels;
    let none = vec![false; mesh.num_nodes()];
    let sites = Sites {
        posterior: &none,
        falciform: &none,
    };
    let (basis, _) = LibrBasis::load_or_build_levels(
        &mesh,
        &LibrParams::default(),
        &levels,
        &Physics::none(),
        sites,
        dir.path(),
    )
    .unwrap();
    let written: u64 = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().metadata().unwrap().len())
        .sum();
    assert_eq!(basis.columns(), basis_columns(true)[1]);
    let estimate = basis_cache_bytes(mesh.num_nodes(), basis.columns());
    eprintln!("adaptive basis: cache {written} bytes, estimate {estimate}");
    assert!(estimate >= written, "{estimate} < {written}");
    assert!(estimate - written < 16384, "{estimate} vs {written}");
}
