//! Cases over the API: CreateCase (chunks of a mesh file, or arrays), its checks, the case store,
//! WatchCase's progress, DeleteCase refused while a session uses the case, a restart reloading
//! the store with its cached basis, and the roles and tenants of uploads.

use crate::common::*;
use librplus_server::auth::{hex, sha256};

fn principal(name: &str, token: &str, cases: &[&str], roles: &[&str]) -> String {
    format!(
        r#"{{"principal":"{name}","token_sha256":["{}"],"cases":{},"roles":{}}}"#,
        hex(&sha256(token.as_bytes())),
        serde_json::to_string(cases).unwrap(),
        serde_json::to_string(roles).unwrap()
    )
}

/// A request with a bearer token ("": none).
fn with<T>(msg: T, token: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    if !token.is_empty() {
        r.metadata_mut()
            .insert("authorization", format!("Bearer {token}").parse().unwrap());
    }
    r
}

/// The message of an upload that carries its mesh as arrays.
fn array_upload(id: &str, nodes: Vec<f64>, tets: Vec<u32>) -> Vec<pb::CreateCaseRequest> {
    vec![pb::CreateCaseRequest {
        part: Some(pb::create_case_request::Part::Upload(pb::CaseUpload {
            case_id: id.into(),
            nodes_mm: nodes,
            tets,
            ..Default::default()
        })),
    }]
}

async fn create(
    c: &mut LibRPlusClient<Channel>,
    token: &str,
    msgs: Vec<pb::CreateCaseRequest>,
) -> Result<pb::CreateCaseResponse, tonic::Status> {
    c.create_case(with(tokio_stream::iter(msgs), token))
        .await
        .map(|r| r.into_inner())
}

/// Follows a case to READY or FAILED: the states seen.
async fn watch(c: &mut LibRPlusClient<Channel>, token: &str, id: &str) -> Vec<pb::CaseStatus> {
    let mut s = c
        .watch_case(with(pb::WatchCaseRequest { case_id: id.into() }, token))
        .await
        .unwrap()
        .into_inner();
    let mut out = Vec::new();
    while let Some(st) = s.message().await.unwrap() {
        out.push(st);
    }
    out
}

/// Entries of the store folder (not counting what starts with '.').
fn stored(dir: &Path) -> usize {
    std::fs::read_dir(dir)
        .map(|r| {
            r.flatten()
                .filter(|e| !e.file_name().to_string_lossy().starts_with('.'))
                .count()
        })
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cases_are_uploaded_checked_stored_preloaded_and_deleted() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let auth = dir.path().join("auth.json");
    std::fs::write(
        &auth,
        format!(
            r#"{{"format":1,"principals":[{},{},{}]}}"#,
            principal(
                "admin-a",
                "manage-a",
                &["hosp-a/*"],
                &["manage", "register"]
            ),
            principal("nav-a", "nav-a", &["hosp-a/*"], &["register"]),
            principal("admin-b", "manage-b", &["hosp-b/*"], &["manage"]),
        ),
    )
    .unwrap();
    let cfg = ServerConfig {
        case_store: Some(store.clone()),
        auth: Some(auth.clone()),
        max_case_bytes: 8 << 20,
        ..config(4)
    };
    let mut running = librplus_server::start(cfg.clone()).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let (mesh, ext, nodes, tets) = dataset_mesh();

    // Upload, progress, READY.
    let t0 = std::time::Instant::now();
    let r = create(&mut c, "manage-a", file_upload("hosp-a/p1", &ext, &mesh))
        .await
        .unwrap();
    assert!(r.created);
    assert_eq!(r.version.len(), 64);
    let upload_s = t0.elapsed().as_secs_f64();
    let states = watch(&mut c, "nav-a", "hosp-a/p1").await;
    let last = states.last().unwrap();
    assert_eq!(last.state(), pb::CaseState::Ready, "{states:?}");
    let stages: Vec<&str> = states
        .iter()
        .filter(|s| s.state() == pb::CaseState::Loading)
        .map(|s| s.stage.as_str())
        .collect();
    eprintln!(
        "upload of {} bytes ({} nodes): stored in {upload_s:.2} s, READY after {:.2} s; \
         loading stages seen: {stages:?}",
        mesh.len(),
        r.node_count,
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(stored(&store), 1);
    // The same upload again: the same version, nothing new.
    let again = create(&mut c, "manage-a", file_upload("hosp-a/p1", &ext, &mesh))
        .await
        .unwrap();
    assert!(!again.created);
    assert_eq!(again.version, r.version);
    // Other content under the same id is refused.
    let mut other = mesh.clone();
    let pos = other.len() / 2;
    other.insert(pos, b' ');
    let e = create(&mut c, "manage-a", file_upload("hosp-a/p1", &ext, &other))
        .await
        .unwrap_err();
    eprintln!(
        "other content under the same id: {:?} {}",
        e.code(),
        e.message()
    );
    assert_eq!(e.code(), Code::FailedPrecondition);

    // The uploaded case registers like any other.
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of("hosp-a/p1", &sc, pb::Method::Libr);
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(msgs[0].clone()).await.unwrap();
    tx.send(msgs[1].clone()).await.unwrap();
    let mut session = c
        .stream_register(with(
            tokio_stream::wrappers::ReceiverStream::new(rx),
            "nav-a",
        ))
        .await
        .unwrap()
        .into_inner();
    let u = session.message().await.unwrap().unwrap();
    assert!(matches!(
        u.update,
        Some(pb::stream_update::Update::Registration(_))
    ));
    // DeleteCase is refused while the session uses it.
    let del = |t: &'static str, id: &str| with(pb::DeleteCaseRequest { case_id: id.into() }, t);
    let e = c
        .delete_case(del("manage-a", "hosp-a/p1"))
        .await
        .unwrap_err();
    eprintln!("delete while in use: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::FailedPrecondition);
    drop(tx);
    while session.message().await.unwrap().is_some() {}

    // Bad uploads: a clear error naming the problem, nothing stored.
    let mut nan = nodes.clone();
    nan[30] = f64::NAN;
    let mut inverted = tets.clone();
    inverted.swap(4 * 7 + 2, 4 * 7 + 3);
    let corrupt: Vec<u8> = mesh[..mesh.len() / 3].to_vec();
    let bad: Vec<(&str, Vec<pb::CreateCaseRequest>, Code, &str)> = vec![
        (
            "corrupt file",
            file_upload("hosp-a/corrupt", &ext, &corrupt),
            Code::InvalidArgument,
            "mesh",
        ),
        (
            "NaN node",
            array_upload("hosp-a/nan", nan, tets.clone()),
            Code::InvalidArgument,
            "upload.nodes_mm[30]",
        ),
        (
            "inverted tet",
            array_upload("hosp-a/inverted", nodes.clone(), inverted),
            Code::InvalidArgument,
            "tet 7 is inverted",
        ),
        (
            "oversized",
            file_upload("hosp-a/big", &ext, &vec![b' '; 9 << 20]),
            Code::ResourceExhausted,
            "limit",
        ),
        (
            "bad id",
            file_upload("hosp-a/../x", &ext, &mesh),
            Code::InvalidArgument,
            "upload.case_id",
        ),
    ];
    for (what, msgs, code, needle) in bad {
        let e = create(&mut c, "manage-a", msgs).await.unwrap_err();
        eprintln!("{what}: {:?} {}", e.code(), e.message());
        assert_eq!(e.code(), code, "{what}");
        assert!(e.message().contains(needle), "{what}: {}", e.message());
    }
    assert_eq!(stored(&store), 1, "bad uploads left something in the store");
    // The same mesh as arrays is its own case.
    let r2 = create(&mut c, "manage-a", array_upload("hosp-a/p2", nodes, tets))
        .await
        .unwrap();
    assert!(r2.created);
    assert_eq!(
        watch(&mut c, "manage-a", "hosp-a/p2")
            .await
            .last()
            .unwrap()
            .state(),
        pb::CaseState::Ready
    );

    // Roles and tenants.
    let e = create(&mut c, "nav-a", file_upload("hosp-a/p3", &ext, &mesh))
        .await
        .unwrap_err();
    assert_eq!(
        e.code(),
        Code::PermissionDenied,
        "a manage-less token uploads"
    );
    let e = c.delete_case(del("nav-a", "hosp-a/p1")).await.unwrap_err();
    assert_eq!(
        e.code(),
        Code::PermissionDenied,
        "a manage-less token deletes"
    );
    let e = create(&mut c, "manage-b", file_upload("hosp-a/p9", &ext, &mesh))
        .await
        .unwrap_err();
    assert_eq!(
        e.code(),
        Code::PermissionDenied,
        "an upload into another tenant"
    );
    let e = c
        .delete_case(del("manage-b", "hosp-a/p1"))
        .await
        .unwrap_err();
    assert_eq!(
        e.code(),
        Code::NotFound,
        "a delete of another tenant's case"
    );
    let listed = c
        .list_cases(with(pb::ListCasesRequest {}, "manage-b"))
        .await
        .unwrap()
        .into_inner()
        .cases;
    assert!(listed.is_empty(), "{listed:?}");

    // A restart reloads the store, the bases from its cache.
    running.shutdown().await;
    let mut running = librplus_server::start(cfg.clone()).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let d = c
        .describe_case(with(
            pb::DescribeCaseRequest {
                case_id: "hosp-a/p1".into(),
                include_mesh: false,
            },
            "nav-a",
        ))
        .await
        .unwrap()
        .into_inner();
    let summary = d.summary.unwrap();
    assert_eq!(d.status.unwrap().version, r.version);
    assert!(
        summary.basis_from_cache,
        "the basis is read from the case's cache"
    );
    // Deleted when unused; gone from the store and the server.
    let gone = c
        .delete_case(del("manage-a", "hosp-a/p1"))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(gone.version, r.version);
    assert_eq!(stored(&store), 1);
    let e = c
        .describe_case(with(
            pb::DescribeCaseRequest {
                case_id: "hosp-a/p1".into(),
                include_mesh: false,
            },
            "nav-a",
        ))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    running.shutdown().await;
}

/// A full disk (a small tmpfs) turns into a clear error, not a corrupted store; the audit log
/// on a full disk refuses to answer rather than answer unrecorded.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let mnt = dir.path().join("small");
    std::fs::create_dir(&mnt).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=256k", "tmpfs"])
        .arg(&mnt)
        .output()
        .is_ok_and(|o| o.status.success());
    if !mounted {
        eprintln!("SKIPPED a_full_disk_is_a_clear_error: cannot mount a tmpfs here (not root?)");
        return;
    }
    struct Unmount(PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount")
                .arg("-l")
                .arg(&self.0)
                .status();
        }
    }
    let _u = Unmount(mnt.clone());
    let store = mnt.join("store");
    let mut running = librplus_server::start(ServerConfig {
        case_store: Some(store.clone()),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let mesh = std::fs::read(dataset().join(&g.preop)).unwrap();
    assert!(
        mesh.len() > 256 << 10,
        "the mesh must not fit: {} bytes",
        mesh.len()
    );
    let ext = dataset()
        .join(&g.preop)
        .extension()
        .unwrap()
        .to_string_lossy()
        .to_string();
    let e = c
        .create_case(tokio_stream::iter(file_upload("big", &ext, &mesh)))
        .await
        .unwrap_err();
    eprintln!("upload to a full disk: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::ResourceExhausted);
    assert!(e.message().contains("full"), "{}", e.message());
    assert_eq!(stored(&store), 0);
    let leftovers = std::fs::read_dir(&store).unwrap().count();
    assert_eq!(leftovers, 0, "a partial upload was left in the store");
    running.shutdown().await;
    // The audit log fills the disk: registrations are refused, not answered unrecorded.
    let mut running = librplus_server::start(ServerConfig {
        audit_db: Some(mnt.join("audit.db")),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    // Then the disk fills up.
    {
        use std::io::Write;
        let mut f = std::fs::File::create(mnt.join("filler")).unwrap();
        while f.write_all(&[0u8; 4096]).and_then(|_| f.sync_all()).is_ok() {}
    }
    let mut c = client(running.addr).await;
    let case = m.deformations[0].geometry.clone();
    let (_, sc) = scenario("surface");
    let mut refused = None;
    for _ in 0..200 {
        match c
            .register(request(
                &case,
                pb::Method::Rigid,
                measurements_pb(&sc.measurements),
            ))
            .await
        {
            Ok(_) => {}
            Err(e) => {
                refused = Some(e);
                break;
            }
        }
    }
    let e = refused.expect("the audit log never filled the disk");
    eprintln!(
        "registration with a full audit disk: {:?} {}",
        e.code(),
        e.message()
    );
    assert_eq!(e.code(), Code::Unavailable);
    assert!(e.message().contains("audit"), "{}", e.message());
    running.shutdown().await;
    // Space again: the log is intact, and holds what was answered.
    std::fs::remove_file(mnt.join("filler")).unwrap();
    let db = librplus_server::audit::open_db(&mnt.join("audit.db")).unwrap();
    let check: String = db
        .query_row("PRAGMA integrity_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(check, "ok");
}

/// Uploads are held in memory until stored: only a few are received at once, and a stalled one
/// ends after 30 s without a message.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_uploads_are_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = ServerConfig {
        case_store: Some(dir.path().join("store")),
        max_uploads: 2,
        // Stalled, not slow: this test waits for the end of the stream.
        min_upload_bytes_per_s: 0,
        ..config(2)
    };
    let max_uploads = cfg.max_uploads;
    let mut running = librplus_server::start(cfg).await.unwrap();
    running.ready().await.unwrap();
    let c = client(running.addr).await;
    let mut held = Vec::new();
    for k in 0..max_uploads {
        let (tx, rx) = tokio::sync::mpsc::channel(4);
        tx.send(file_upload(&format!("stall-{k}"), "vtu", b"")[0].clone())
            .await
            .unwrap();
        let mut c = c.clone();
        let call = tokio::spawn(async move {
            c.create_case(tokio_stream::wrappers::ReceiverStream::new(rx))
                .await
        });
        held.push((tx, call));
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let mesh = std::fs::read(dataset().join(&g.preop)).unwrap();
    let e = c
        .clone()
        .create_case(tokio_stream::iter(file_upload("third", "vtu", &mesh)))
        .await
        .unwrap_err();
    eprintln!(
        "a third upload while two are received: {:?} {}",
        e.code(),
        e.message()
    );
    assert_eq!(e.code(), Code::ResourceExhausted);
    // The stalled ones end (no mesh), and the slot is free again.
    for (tx, call) in held {
        drop(tx);
        let e = call.await.unwrap().unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    }
    let r = c
        .clone()
        .create_case(tokio_stream::iter(file_upload("third", "vtu", &mesh)))
        .await
        .unwrap();
    assert!(r.into_inner().created);
    running.shutdown().await;
}

/// The dataset's first preoperative mesh: its file's bytes and extension, and its nodes (mm, 3 a
/// node) and tets as arrays.
fn dataset_mesh() -> (Vec<u8>, String, Vec<f64>, Vec<u32>) {
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let bytes = std::fs::read(dataset().join(&g.preop)).unwrap();
    let ext = dataset()
        .join(&g.preop)
        .extension()
        .unwrap()
        .to_string_lossy()
        .to_string();
    let geo = load_geometry(dataset(), &m, &g.id).unwrap();
    let nodes = geo.model.mesh.nodes().iter().flatten().copied().collect();
    let tets = geo.model.mesh.tets().iter().flatten().copied().collect();
    (bytes, ext, nodes, tets)
}

/// `msgs` with a `physics.json` chunk added.
fn with_physics(mut msgs: Vec<pb::CreateCaseRequest>, json: &str) -> Vec<pb::CreateCaseRequest> {
    msgs.push(pb::CreateCaseRequest {
        part: Some(pb::create_case_request::Part::Chunk(pb::CaseChunk {
            file: pb::CaseFile::Physics as i32,
            data: json.as_bytes().to_vec(),
        })),
    });
    msgs
}

/// A `physics.json` of one pack centred at `c`, `width` mm wide.
fn pack(c: [f64; 3], width: f64) -> String {
    format!(
        r#"{{"format": 1, "effects": [{{"kind": "pack", "parameters": {{"center": [{}, {}, {}], "width_mm": {width}, "force_mn": [0, 0, 200]}}}}]}}"#,
        c[0], c[1], c[2]
    )
}

/// What preload refuses is refused at upload, INVALID_ARGUMENT naming the problem, and nothing
/// is stored (before: a node in no tetrahedron, a repeated tet, a pack 40 mm off the surface,
/// `kind: "nonlinear"` and a mesh in the wrong unit were stored with `created` true, then FAILED
/// at preload or, for the unit, READY and refusing every point; a misspelt top-level key of
/// physics.json was ignored). A pack on the surface passes both.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_are_checked_as_preload_checks_them() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let mut running = librplus_server::start(ServerConfig {
        case_store: Some(store.clone()),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let (mesh, ext, nodes, tets) = dataset_mesh();
    let n = nodes.len() / 3;
    // The boundary node farthest along +x: a pack there is on the surface; 40 mm further out it
    // is 40 mm from every node.
    let far = (0..n)
        .max_by(|&a, &b| nodes[3 * a].total_cmp(&nodes[3 * b]))
        .unwrap();
    let on = [nodes[3 * far], nodes[3 * far + 1], nodes[3 * far + 2]];
    let off = [on[0] + 40.0, on[1], on[2]];

    let mut unused = nodes.clone();
    unused.extend_from_slice(&on.map(|x| x + 1.0));
    let mut repeated = tets.clone();
    // Tet 0 again, its nodes turned (an even permutation: the same orientation).
    repeated.extend_from_slice(&[tets[1], tets[2], tets[0], tets[3]]);
    let metres: Vec<f64> = nodes.iter().map(|x| x * 1000.0).collect();
    let mut in_metres = file_upload("in-m", &ext, &mesh);
    if let Some(pb::create_case_request::Part::Upload(u)) = &mut in_metres[0].part {
        u.mesh_unit = "m".into();
    }
    let unused_node = format!("node {n} ");
    let repeated_tet = format!("tet {} ", tets.len() / 4);
    let bad: Vec<(&str, Vec<pb::CreateCaseRequest>, Vec<&str>)> = vec![
        (
            "a node in no tetrahedron",
            array_upload("unused", unused, tets.clone()),
            vec!["upload.nodes_mm", &unused_node, "no tetrahedron"],
        ),
        (
            "a repeated tet",
            array_upload("repeated", nodes.clone(), repeated),
            vec!["upload.tets", &repeated_tet, "repeats tet 0"],
        ),
        (
            "a pack 40 mm off the surface",
            with_physics(file_upload("pack-off", &ext, &mesh), &pack(off, 10.0)),
            vec!["physics.json", "effects[0].parameters.center", "40.0 mm"],
        ),
        (
            "a nonlinear effect",
            with_physics(
                file_upload("nonlinear", &ext, &mesh),
                r#"{"format": 1, "effects": [{"kind": "nonlinear"}]}"#,
            ),
            vec!["physics.json", "effects[0].kind", "nonlinear"],
        ),
        (
            "an unknown kind",
            with_physics(
                file_upload("magnetism", &ext, &mesh),
                r#"{"format": 1, "effects": [{"kind": "magnetism"}]}"#,
            ),
            vec!["physics.json", "effects[0].kind", "magnetism"],
        ),
        (
            "an unknown top-level key in physics.json (a misspelt \"effects\")",
            with_physics(
                file_upload("misspelt", &ext, &mesh),
                r#"{"format": 1, "effects": [], "efects": [{"kind": "gravity"}]}"#,
            ),
            vec!["physics.json", "efects", "unknown key"],
        ),
        (
            "a mesh in mm declared m",
            in_metres,
            vec!["upload.mesh_unit", "\"m\"", "is its unit mm?"],
        ),
        (
            "nodes_mm in micrometres",
            array_upload("in-um", metres, tets.clone()),
            vec!["upload.nodes_mm", "mm"],
        ),
    ];
    for (what, msgs, needles) in bad {
        let e = create(&mut c, "", msgs)
            .await
            .err()
            .unwrap_or_else(|| panic!("{what}: accepted (and stored)"));
        eprintln!("{what}: {:?} {}", e.code(), e.message());
        assert_eq!(e.code(), Code::InvalidArgument, "{what}: {}", e.message());
        for needle in needles {
            assert!(
                e.message().contains(needle),
                "{what}: {needle:?} not in {:?}",
                e.message()
            );
        }
        assert!(
            e.message().len() < 600,
            "{what}: a long message: {}",
            e.message()
        );
        assert!(
            e.get_details_bad_request().is_some(),
            "{what}: no BadRequest"
        );
    }
    assert_eq!(stored(&store), 0, "a refused upload was stored");
    // A pack on the surface passes both the upload's checks and preload.
    let r = create(
        &mut c,
        "",
        with_physics(file_upload("pack-on", &ext, &mesh), &pack(on, 10.0)),
    )
    .await
    .unwrap();
    assert!(r.created);
    let states = watch(&mut c, "", "pack-on").await;
    assert_eq!(
        states.last().unwrap().state(),
        pb::CaseState::Ready,
        "{states:?}"
    );
    running.shutdown().await;
}

/// A case folder as a server with older checks wrote it (no `checks`, no `bytes` in
/// `case.json`): the dataset's mesh under `id`, by `principal`, with `physics` if any.
fn store_as_before(store: &Path, id: &str, principal: &str, physics: Option<&str>) {
    let s = librplus_server::store::Store::open(store).unwrap();
    let dir = s.folder(id);
    std::fs::create_dir_all(&dir).unwrap();
    let (mesh, ext, nodes, tets) = dataset_mesh();
    std::fs::write(dir.join(format!("mesh.{ext}")), &mesh).unwrap();
    if let Some(p) = physics {
        std::fs::write(dir.join("mesh.physics.json"), p).unwrap();
    }
    let case = serde_json::json!({
        "format": 1, "case_id": id, "version": "0".repeat(64), "mesh": format!("mesh.{ext}"),
        "unit": "mm", "principal": principal, "created_ms": 0, "nodes": nodes.len() / 3,
        "tets": tets.len() / 4, "vessels": false, "physics": physics.is_some(),
    });
    std::fs::write(dir.join("case.json"), serde_json::to_vec(&case).unwrap()).unwrap();
}

/// The case store is bounded: cases and bytes per principal and in total, RESOURCE_EXHAUSTED
/// naming the quota (QuotaFailure) with nothing stored, room again once a case is deleted; a
/// stored case preload refuses (stored by a server with weaker checks) is removed at start,
/// not reloaded at every start, and counts toward no quota (before: every upload stayed, and
/// a restart reported `cases=29 failed=14`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_case_store_is_bounded_and_keeps_no_failed_case() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let auth = dir.path().join("auth.json");
    std::fs::write(
        &auth,
        format!(
            r#"{{"format":1,"principals":[{},{},{}]}}"#,
            principal("admin-a", "manage-a", &["hosp-a/*"], &["manage"]),
            principal("admin-b", "manage-b", &["hosp-b/*"], &["manage"]),
            principal("admin-c", "manage-c", &["hosp-c/*"], &["manage"]),
        ),
    )
    .unwrap();
    // Stored before: one case preload refuses (`nonlinear`), by admin-a.
    store_as_before(
        &store,
        "hosp-a/old",
        "admin-a",
        Some(r#"{"format": 1, "effects": [{"kind": "nonlinear"}]}"#),
    );
    assert_eq!(stored(&store), 1);
    let cfg = ServerConfig {
        case_store: Some(store.clone()),
        auth: Some(auth),
        max_stored_cases: 2,
        max_cases_per_principal: 1,
        ..config(2)
    };
    let mut running = librplus_server::start(cfg.clone()).await.unwrap();
    let report = running.ready().await.unwrap();
    // Removed at start (and reported in the log), not loaded and not kept.
    assert!(
        report.failed.iter().all(|(id, _)| id != "hosp-a/old"),
        "{report:?}"
    );
    assert_eq!(stored(&store), 0, "the failed stored case is still stored");
    let mut c = client(running.addr).await;
    let (mesh, ext, _, _) = dataset_mesh();
    let quota = |e: tonic::Status, name: &str| {
        eprintln!("{name}: {:?} {}", e.code(), e.message());
        assert_eq!(e.code(), Code::ResourceExhausted, "{}", e.message());
        assert!(e.message().contains(name), "{}", e.message());
        assert!(e.message().contains("DeleteCase"), "{}", e.message());
        let q = e.get_details_quota_failure().expect("QuotaFailure");
        assert_eq!(q.violations[0].subject, name);
    };
    // admin-a's failed case holds no quota: one case of admin-a's fits.
    let a1 = create(&mut c, "manage-a", file_upload("hosp-a/p1", &ext, &mesh))
        .await
        .unwrap();
    assert!(a1.created);
    let e = create(&mut c, "manage-a", file_upload("hosp-a/p2", &ext, &mesh))
        .await
        .unwrap_err();
    quota(e, "max_cases_per_principal");
    // A retry of the stored case is no new case.
    let again = create(&mut c, "manage-a", file_upload("hosp-a/p1", &ext, &mesh))
        .await
        .unwrap();
    assert!(!again.created);
    create(&mut c, "manage-b", file_upload("hosp-b/p1", &ext, &mesh))
        .await
        .unwrap();
    let e = create(&mut c, "manage-c", file_upload("hosp-c/p1", &ext, &mesh))
        .await
        .unwrap_err();
    quota(e, "max_stored_cases");
    assert_eq!(stored(&store), 2);
    // Deleted (once loaded), the room is free again.
    let states = watch(&mut c, "manage-a", "hosp-a/p1").await;
    assert_eq!(states.last().unwrap().state(), pb::CaseState::Ready);
    c.delete_case(with(
        pb::DeleteCaseRequest {
            case_id: "hosp-a/p1".into(),
        },
        "manage-a",
    ))
    .await
    .unwrap();
    create(&mut c, "manage-c", file_upload("hosp-c/p1", &ext, &mesh))
        .await
        .unwrap();
    for id in ["hosp-b/p1", "hosp-c/p1"] {
        let token = if id.starts_with("hosp-b") {
            "manage-b"
        } else {
            "manage-c"
        };
        let states = watch(&mut c, token, id).await;
        assert_eq!(states.last().unwrap().state(), pb::CaseState::Ready);
    }
    running.shutdown().await;

    // Bytes: the store holds two cases (files and LIBR bases); a limit below what they hold
    // and one principal's below one case refuse more.
    let held: u64 = walk_bytes(&store);
    let mut running = librplus_server::start(ServerConfig {
        max_stored_cases: 10,
        max_cases_per_principal: 10,
        max_stored_bytes: held + mesh.len() as u64 / 2,
        ..cfg.clone()
    })
    .await
    .unwrap();
    let report = running.ready().await.unwrap();
    let uploaded = report.cases.iter().filter(|c| c.0.starts_with("hosp-"));
    assert_eq!(uploaded.count(), 2, "{report:?}");
    let mut c = client(running.addr).await;
    let e = create(&mut c, "manage-a", file_upload("hosp-a/p2", &ext, &mesh))
        .await
        .unwrap_err();
    quota(e, "max_stored_bytes");
    running.shutdown().await;
    let mut running = librplus_server::start(ServerConfig {
        max_stored_cases: 10,
        max_cases_per_principal: 10,
        max_bytes_per_principal: held / 2 + mesh.len() as u64 / 2,
        ..cfg
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let e = create(&mut c, "manage-b", file_upload("hosp-b/p2", &ext, &mesh))
        .await
        .unwrap_err();
    quota(e, "max_bytes_per_principal");
    // Another principal with nothing stored is within its own bytes.
    create(&mut c, "manage-a", file_upload("hosp-a/p2", &ext, &mesh))
        .await
        .unwrap();
    assert_eq!(stored(&store), 3);
    running.shutdown().await;
}

/// Bytes of the files under `path`.
fn walk_bytes(path: &Path) -> u64 {
    let m = std::fs::symlink_metadata(path).unwrap();
    if m.is_dir() {
        std::fs::read_dir(path)
            .unwrap()
            .flatten()
            .map(|e| walk_bytes(&e.path()))
            .sum()
    } else {
        m.len()
    }
}
