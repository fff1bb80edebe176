//! A large upload serves from a coarse basis while its own builds: READY on the coarse basis
//! first (WatchCase goes on), answers flagged DEGRADED and `coarse_basis`, near the answers of
//! its own basis; then READY on its own basis, a session started on the coarse case swapped to
//! it before its next update, and both swaps in the audit log.

use crate::common::*;

/// The dataset's first mesh as an upload of arrays.
fn upload(id: &str) -> Vec<pb::CreateCaseRequest> {
    let m = open(dataset()).unwrap();
    let geo = load_geometry(dataset(), &m, &m.geometries[0].id).unwrap();
    vec![pb::CreateCaseRequest {
        part: Some(pb::create_case_request::Part::Upload(pb::CaseUpload {
            case_id: id.into(),
            nodes_mm: geo.model.mesh.nodes().iter().flatten().copied().collect(),
            tets: geo.model.mesh.tets().iter().flatten().copied().collect(),
            ..Default::default()
        })),
    }]
}

/// Mean distance between two answers' displaced nodes (mm).
fn mean_gap(a: &pb::Registration, b: &pb::Registration) -> f64 {
    let n = a.displacement_mm.len() / 3;
    assert_eq!(a.displacement_mm.len(), b.displacement_mm.len());
    (0..n)
        .map(|i| {
            (0..3)
                .map(|k| (a.displacement_mm[3 * i + k] - b.displacement_mm[3 * i + k]) as f64)
                .map(|d| d * d)
                .sum::<f64>()
                .sqrt()
        })
        .sum::<f64>()
        / n as f64
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_large_upload_serves_from_a_coarse_basis_then_swaps_to_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let audit = dir.path().join("audit.db");
    let cfg = ServerConfig {
        case_store: Some(dir.path().join("store")),
        audit_db: Some(audit.clone()),
        // Every upload serves coarse first; a mesh far coarser than the small dataset's, so
        // that its basis is ready long before the case's own (and adaptive LIBR's).
        coarse_basis_above_nodes: 1,
        coarse_basis_edge_mm: 24.0,
        ..config(4)
    };
    let mut running = librplus_server::start(cfg).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let id = "uploads/large";
    let t0 = std::time::Instant::now();
    c.create_case(tokio_stream::iter(upload(id))).await.unwrap();
    let mut w = c
        .watch_case(pb::WatchCaseRequest { case_id: id.into() })
        .await
        .unwrap()
        .into_inner();
    // Up to the first READY: it is the coarse basis's.
    let mut first = None;
    while let Some(s) = w.message().await.unwrap() {
        assert_ne!(s.state(), pb::CaseState::Failed, "{s:?}");
        if s.state() == pb::CaseState::Ready {
            first = Some(s);
            break;
        }
    }
    let first = first.expect("READY");
    assert!(first.coarse_basis, "{first:?}");
    let first_s = t0.elapsed().as_secs_f64();

    // A session started on the coarse case, and a unary registration: both coarse.
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(id, &sc, pb::Method::Libr);
    let last = msgs.len() - 1;
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let unary = |c: &mut LibRPlusClient<Channel>| {
        let req = request(id, pb::Method::Libr, measurements_pb(&sc.measurements));
        let mut c = c.clone();
        async move { c.register(req).await.unwrap().into_inner() }
    };
    let coarse_answer = unary(&mut c).await;
    let mut streamed = None;
    for m in &msgs[1..last] {
        streamed = Some(s.send(m.clone()).await.unwrap());
    }
    let Some(pb::stream_update::Update::Registration(before_swap)) =
        streamed.and_then(|u| u.update)
    else {
        panic!("a registration")
    };
    for r in [&coarse_answer, &before_swap] {
        assert!(r.coarse_basis, "{:?} {}", r.quality(), r.quality_reason);
        assert_eq!(r.quality(), pb::Quality::Degraded, "{}", r.quality_reason);
        assert!(
            r.quality_reason.contains("own basis is still building")
                && r.quality_reason.contains("24 mm"),
            "{}",
            r.quality_reason
        );
    }

    // The rest of the watch: READY on the case's own basis ends it.
    let mut own = None;
    while let Some(st) = w.message().await.unwrap() {
        assert_ne!(st.state(), pb::CaseState::Failed, "{st:?}");
        own = Some(st);
    }
    let own = own.expect("a status after the coarse READY");
    assert_eq!(own.state(), pb::CaseState::Ready, "{own:?}");
    assert!(!own.coarse_basis, "{own:?}");
    let own_s = t0.elapsed().as_secs_f64();

    // After the swap: the same session's next update and a unary one on the case's own basis.
    let Some(pb::stream_update::Update::Registration(after_swap)) =
        s.send(msgs[last].clone()).await.unwrap().update
    else {
        panic!("a registration")
    };
    let own_answer = unary(&mut c).await;
    for r in [&after_swap, &own_answer] {
        assert!(!r.coarse_basis, "{}", r.quality_reason);
        assert!(
            !r.quality_reason.contains("own basis"),
            "{}",
            r.quality_reason
        );
    }
    // The coarse answer is an answer of the same deformation: near the case's own (the
    // dataset's partial cut; the coarse mesh has 24 mm tets).
    let gap = mean_gap(&coarse_answer, &own_answer);
    let moved = mean_gap(
        &own_answer,
        &pb::Registration {
            displacement_mm: vec![0.0; own_answer.displacement_mm.len()],
            ..Default::default()
        },
    );
    eprintln!(
        "coarse READY after {first_s:.2} s, own basis READY after {own_s:.2} s; coarse answer \
         {gap:.2} mm from its own basis's on average (which moves the nodes {moved:.2} mm)"
    );
    assert!(
        gap < 0.5 * moved.max(1.0),
        "gap {gap:.2} mm, moved {moved:.2} mm"
    );
    drop(s);
    running.shutdown().await;

    // Both swaps are audited: the case's, and the session's before the update it changed.
    let db = rusqlite::Connection::open(&audit).unwrap();
    let kinds: Vec<String> = db
        .prepare("SELECT kind FROM events WHERE case_id = ?1 ORDER BY id")
        .unwrap()
        .query_map([id], |r| r.get(0))
        .unwrap()
        .map(Result::unwrap)
        .collect();
    for k in ["case_basis_swapped", "session_basis_swapped"] {
        assert!(kinds.iter().any(|x| x == k), "{k} missing from {kinds:?}");
    }
}
