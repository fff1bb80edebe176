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

fn with<T>(msg: T, token: &str) -> tonic::Request<T> {
    let mut r = tonic::Request::new(msg);
    r.metadata_mut()
        .insert("authorization", format!("Bearer {token}").parse().unwrap());
    r
}

/// The messages of an upload of a mesh file's bytes, in 256 KiB chunks.
fn file_upload(id: &str, format: &str, bytes: &[u8]) -> Vec<pb::CreateCaseRequest> {
    use pb::create_case_request::Part;
    let mut out = vec![pb::CreateCaseRequest {
        part: Some(Part::Upload(pb::CaseUpload {
            case_id: id.into(),
            mesh_format: format.into(),
            total_bytes: bytes.len() as u64,
            ..Default::default()
        })),
    }];
    for c in bytes.chunks(256 << 10) {
        out.push(pb::CreateCaseRequest {
            part: Some(Part::Chunk(pb::CaseChunk {
                file: pb::CaseFile::Mesh as i32,
                data: c.to_vec(),
            })),
        });
    }
    out
}

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
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let mesh = std::fs::read(dataset().join(&g.preop)).unwrap();
    let ext = dataset()
        .join(&g.preop)
        .extension()
        .unwrap()
        .to_string_lossy()
        .to_string();

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
    let (nodes, tets) = {
        let geo = load_geometry(dataset(), &m, &g.id).unwrap();
        (
            geo.model
                .mesh
                .nodes()
                .iter()
                .flatten()
                .copied()
                .collect::<Vec<f64>>(),
            geo.model
                .mesh
                .tets()
                .iter()
                .flatten()
                .copied()
                .collect::<Vec<u32>>(),
        )
    };
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
    let mut running = librplus_server::start(ServerConfig {
        case_store: Some(dir.path().join("store")),
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let c = client(running.addr).await;
    let mut held = Vec::new();
    for k in 0..librplus_server::service::MAX_UPLOADS {
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
