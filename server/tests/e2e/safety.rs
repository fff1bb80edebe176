//! What an adversarial probe of the service found, each shown fixed: a doubled `authorization`
//! header, control characters from a client in `librplus-server audit`'s table, a config file
//! completed by flags, an overlong id echoed back, and guessable session ids. The servers run as
//! processes, so `LIBRPLUS_SERVER_BIN` can point these tests at an older build to see them fail.

use crate::common::*;
use librplus_server::auth::{hex, sha256};

/// The server binary these tests run (`LIBRPLUS_SERVER_BIN`: another build, as `Proc` runs).
fn server_bin() -> PathBuf {
    std::env::var_os("LIBRPLUS_SERVER_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_librplus-server")))
}

fn list_with(headers: &[&str]) -> tonic::Request<pb::ListCasesRequest> {
    let mut r = tonic::Request::new(pb::ListCasesRequest {});
    for h in headers {
        r.metadata_mut().append("authorization", h.parse().unwrap());
    }
    r
}

/// Two `authorization` headers are refused, whichever comes first (before the fix the first
/// one counted).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_authorization_headers_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let auth = write(
        dir.path(),
        "auth.json",
        &format!(
            r#"{{"format":1,"principals":[{{"principal":"a","token_sha256":["{}"],"cases":["*"],"roles":["read"]}}]}}"#,
            hex(&sha256(b"good-token"))
        ),
    );
    let auth = auth.display().to_string();
    let p = Proc::start(&["--auth", &auth]);
    let mut c = client(p.addr.parse().unwrap()).await;
    c.list_cases(list_with(&["Bearer good-token"]))
        .await
        .expect("one valid header is accepted");
    for headers in [
        ["Bearer good-token", "Bearer forged"],
        ["Bearer forged", "Bearer good-token"],
        ["Bearer good-token", "Bearer good-token"],
    ] {
        let e = c.list_cases(list_with(&headers)).await.unwrap_err();
        eprintln!("{headers:?}: {:?} {}", e.code(), e.message());
        assert_eq!(e.code(), Code::Unauthenticated, "{headers:?}: {e:?}");
        assert!(e.message().contains("more than once"), "{e:?}");
    }
}

/// Case ids are the client's: `librplus-server audit`'s table shows their control characters
/// escaped, so a newline cannot forge a line and an escape sequence never reaches the terminal.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_audit_table_escapes_what_clients_sent() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let db_arg = db.display().to_string();
    let p = Proc::start(&["--audit", &db_arg]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let evil = "x\n2026-01-01 00:00:00.000  forged-line\u{1b}[2J\u{202e}";
    let e = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: evil.into(),
            include_mesh: false,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    // The refusal is recorded without waiting: poll for it.
    let mut out = String::new();
    for _ in 0..50 {
        let mut cmd = std::process::Command::new(server_bin());
        cmd.arg("audit").arg("--db").arg(&db);
        out = run_cmd(cmd).await;
        if out.contains("forged-line") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    eprintln!("{out}");
    assert!(out.contains("forged-line"), "the refusal is in the log");
    assert!(
        !out.lines().any(|l| l.starts_with("2026-01-01")),
        "a forged line"
    );
    assert!(
        !out.contains('\u{1b}') && !out.contains('\u{202e}'),
        "raw control characters"
    );
    assert!(
        out.contains("x\\u{a}2026-01-01"),
        "the newline shown escaped"
    );
    // The JSON view keeps the value exactly (escaped by JSON).
    let mut cmd = std::process::Command::new(server_bin());
    cmd.arg("audit").arg("--db").arg(&db).arg("--json");
    let json = run_cmd(cmd).await;
    let found = json
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .any(|v| v["case_id"].as_str() == Some(evil));
    assert!(found, "{json}");
}

/// A config file without cases, completed by `--cases` on the command line (flags override and
/// complete the file; before the fix the file was checked alone and refused).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flags_complete_a_config_file() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = write(
        dir.path(),
        "server.json",
        r#"{"format": 1, "max_sessions": 3}"#,
    );
    let cfg = cfg.display().to_string();
    // Proc passes --cases (the test dataset) and --max-sessions 4.
    let p = Proc::start(&["--config", &cfg]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let cases = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner()
        .cases;
    assert!(!cases.is_empty());
    // Still refused when neither gives a case, naming the file and the field.
    let out = std::process::Command::new(server_bin())
        .args(["--config", &cfg, "--listen", "127.0.0.1:0"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("server.json") && err.contains("cases:"),
        "{err}"
    );
}

/// NOT_FOUND echoes at most 64 characters of an id; numbers in messages are readable; session ids
/// carry random digits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn echoes_and_numbers_are_short_and_session_ids_are_not_guessable() {
    let p = Proc::start(&[]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let long = "a".repeat(256);
    let e = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: long.clone(),
            include_mesh: false,
        })
        .await
        .unwrap_err();
    eprintln!("{:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::NotFound);
    assert!(!e.message().contains(&"a".repeat(65)), "{e:?}");
    assert!(e.message().contains("(256 bytes)"), "{e:?}");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+2us");
    // A number far out of range is shown in scientific notation, not as 301 digits.
    let mut m = sc.measurements.clone().into_inner();
    m.points[0] = [1e300, 0.0, 0.0];
    let e = c
        .register(request(&case, pb::Method::Rigid, measurements_pb(&m)))
        .await
        .unwrap_err();
    eprintln!("{:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::InvalidArgument);
    let problems: Vec<String> = e
        .get_details_bad_request()
        .unwrap()
        .field_violations
        .into_iter()
        .map(|v| v.description)
        .collect();
    eprintln!("{problems:?}");
    assert!(
        problems[0].starts_with("x = 1e300 is not finite"),
        "{problems:?}"
    );
    assert!(!problems[0].contains("0000000000"), "{problems:?}");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    let mut ids = Vec::new();
    for _ in 0..2 {
        let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
        ids.push(s.send(msgs[1].clone()).await.unwrap().session_id);
    }
    eprintln!("session ids {ids:?}");
    let tail = |id: &str| id.rsplit_once('-').unwrap().1.to_string();
    let (a, b) = (tail(&ids[0]), tail(&ids[1]));
    assert!(a.len() >= 21 && b.len() >= 21, "{ids:?}");
    // Beyond the counter (its first 6 digits) the ids differ at random.
    assert_ne!(a[6..], b[6..], "{ids:?}");
}

/// An uploaded case unused for `evict_idle_s` leaves memory (STORED, still listed) but never while
/// a session holds it; the next request loads it again (UNAVAILABLE meanwhile) and its answers
/// are the same as before.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_uploads_leave_memory_and_load_again_when_asked_for() {
    let dir = tempfile::tempdir().unwrap();
    let mut running = librplus_server::start(ServerConfig {
        case_store: Some(dir.path().join("store")),
        evict_idle_s: 1.0,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let m = open(dataset()).unwrap();
    let g = load_geometry(dataset(), &m, &m.deformations[0].geometry).unwrap();
    let id = "idle/liver";
    c.create_case(tokio_stream::iter(vec![pb::CreateCaseRequest {
        part: Some(pb::create_case_request::Part::Upload(pb::CaseUpload {
            case_id: id.into(),
            nodes_mm: g.model.mesh.nodes().iter().flatten().copied().collect(),
            tets: g.model.mesh.tets().iter().flatten().copied().collect(),
            ..Default::default()
        })),
    }]))
    .await
    .unwrap();
    let state = |mut c: LibRPlusClient<Channel>| async move {
        c.describe_case(pb::DescribeCaseRequest {
            case_id: id.into(),
            include_mesh: false,
        })
        .await
        .unwrap()
        .into_inner()
        .status
        .unwrap()
        .state()
    };
    let c0 = c.clone();
    let wait_for = |want: pb::CaseState| {
        let c = c0.clone();
        async move {
            for _ in 0..200 {
                if state(c.clone()).await == want {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            panic!("never {want:?}");
        }
    };
    let ask = |mut c: LibRPlusClient<Channel>| async move {
        let (_, sc) = scenario("surface+2us");
        c.register(request(
            id,
            pb::Method::Libr,
            measurements_pb(&sc.measurements),
        ))
        .await
    };
    // Ask often enough while loading that its eviction never comes.
    let mut before = None;
    for _ in 0..100 {
        match ask(c.clone()).await {
            Ok(r) => {
                before = Some(r.into_inner());
                break;
            }
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
    let before = before.expect("the upload became READY");
    // A session holds it: not evicted, however long it is idle.
    let (_, sc) = scenario("surface+2us");
    let (msgs, _) = stream_of(id, &sc, pb::Method::Rigid);
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    s.send(msgs[1].clone()).await.unwrap();
    tokio::time::sleep(Duration::from_millis(2500)).await;
    assert_eq!(state(c.clone()).await, pb::CaseState::Ready);
    drop(s);
    // Idle and no session: out of memory, still listed.
    wait_for(pb::CaseState::Stored).await;
    let listed = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner()
        .cases;
    let e = listed.iter().find(|x| x.case_id == id).expect("listed");
    assert_eq!(e.node_count as usize, g.model.mesh.num_nodes());
    assert!(e.source.contains("idle"), "{e:?}");
    // Asked for: UNAVAILABLE while it loads again, then the same answer as before.
    let err = ask(c.clone()).await.unwrap_err();
    eprintln!("asked while evicted: {:?} {}", err.code(), err.message());
    assert_eq!(err.code(), Code::Unavailable);
    assert!(err.message().contains("loaded again"), "{err:?}");
    wait_for(pb::CaseState::Ready).await;
    let after = ask(c.clone()).await.unwrap().into_inner();
    let t = |r: &pb::Registration| r.image_to_physical.clone().unwrap().translation_mm;
    let d = t(&before)
        .iter()
        .zip(t(&after))
        .map(|(a, b)| (a - b).abs())
        .chain(
            before
                .displacement_mm
                .iter()
                .zip(&after.displacement_mm)
                .map(|(a, b)| (a - b).abs() as f64),
        )
        .fold(0.0, f64::max);
    eprintln!("answer after loading again differs by {d:.1e} mm");
    assert!(d <= 1e-9, "{d}");
    running.shutdown().await;
}
