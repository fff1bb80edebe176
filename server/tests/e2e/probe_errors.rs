//! Errors that name the right thing: points in metres said to look like metres, a mesh with a
//! coincident copy of a node refused naming the nodes, one violation per bad point, and the
//! audit table showing a refusal's message escaped once. Against a server process, so that
//! `LIBRPLUS_SERVER_BIN` can show each test failing on an older build.

use crate::common::*;
use librplus::mesh::TetMesh;

/// Points in metres sent as millimetres (every coordinate ÷ 1000) are said to look like metres
/// (before, the answer was only "collinear (spread 0.054 mm …)").
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn points_in_metres_are_said_to_look_like_metres() {
    let p = Proc::start(&[]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let (_, sc) = scenario("surface");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let mut m = measurements_pb(&sc.measurements);
    for x in &mut m.xyz_mm {
        *x /= 1000.0;
    }
    let text = match c.register(request(&case, pb::Method::Libr, m)).await {
        Ok(r) => {
            let r = r.into_inner();
            assert_ne!(r.quality(), pb::Quality::Ok, "{r:?}");
            format!("{:?}: {}", r.quality(), r.quality_reason)
        }
        Err(e) => format!("{:?}: {}", e.code(), e.message()),
    };
    eprintln!("points ÷ 1000: {text}");
    assert!(text.contains("metres sent as millimetres"), "{text}");
}

/// A mesh in which one tet uses a coincident copy of an interior node (a crack inside the
/// mesh) is refused at upload, naming both nodes (before, it passed every check and was stored).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mesh_with_a_coincident_copy_of_a_node_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let store_arg = store.display().to_string();
    let p = Proc::start(&["--case-store", &store_arg]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let m = open(dataset()).unwrap();
    let geo = load_geometry(dataset(), &m, &m.geometries[0].id).unwrap();
    let (x, tets) = (geo.model.mesh.nodes(), geo.model.mesh.tets());
    let mesh = TetMesh::new(x.to_vec(), tets.to_vec()).unwrap();
    let boundary = mesh.boundary().unwrap().nodes;
    let inner = (0..x.len() as u32)
        .find(|n| boundary.binary_search(n).is_err())
        .expect("an interior node");
    let copy = x.len() as u32;
    let mut nodes: Vec<f64> = x.iter().flatten().copied().collect();
    nodes.extend_from_slice(&x[inner as usize]);
    let mut cracked = tets.to_vec();
    let tet = cracked.iter().position(|t| t.contains(&inner)).unwrap();
    for v in &mut cracked[tet] {
        if *v == inner {
            *v = copy;
        }
    }
    let upload = pb::CreateCaseRequest {
        part: Some(pb::create_case_request::Part::Upload(pb::CaseUpload {
            case_id: "cracked".into(),
            nodes_mm: nodes,
            tets: cracked.into_iter().flatten().collect(),
            ..Default::default()
        })),
    };
    let e = c
        .create_case(tokio_stream::iter([upload]))
        .await
        .expect_err("a mesh with a coincident copy of a node was accepted");
    eprintln!("coincident nodes: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::InvalidArgument, "{}", e.message());
    for needle in [
        "upload.nodes_mm".to_string(),
        format!("nodes {inner} and {copy} are at the same position"),
        format!("node {copy} in tet {tet}"),
    ] {
        assert!(e.message().contains(&needle), "{needle:?}: {}", e.message());
    }
}

/// One point with three bad coordinates is one violation naming the point (before: the same
/// field three times), over Register and in a stream.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_bad_point_is_one_violation() {
    let p = Proc::start(&[]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let (_, sc) = scenario("surface");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let mut m = measurements_pb(&sc.measurements);
    m.xyz_mm[..3].copy_from_slice(&[f64::NAN, f64::INFINITY, 2e4]);
    let e = c
        .register(request(&case, pb::Method::Libr, m))
        .await
        .unwrap_err();
    eprintln!("Register: {} {:?}", e.message(), violations(&e));
    assert_eq!(e.code(), Code::InvalidArgument);
    assert_eq!(violations(&e), ["measurements.points[0]"]);

    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let mut bad = msgs[1].clone();
    if let Some(pb::stream_register_request::Msg::Surface(b)) = bad.msg.as_mut() {
        b.xyz_mm[..3].copy_from_slice(&[f64::NAN; 3]);
    }
    let u = s.send(bad).await.unwrap();
    let Some(pb::stream_update::Update::Rejection(r)) = u.update else {
        panic!("a bad point accepted: {u:?}")
    };
    let fields: Vec<&str> = r.violations.iter().map(|v| v.field.as_str()).collect();
    eprintln!("SurfaceBatch: {} {fields:?}", r.message);
    assert_eq!(fields, ["surface.points[0]"]);
    assert!(
        r.violations[0]
            .description
            .starts_with("x = NaN, y = NaN, z = NaN are not finite"),
        "{}",
        r.violations[0].description
    );
}

/// `librplus-server audit` shows a refusal's message escaped once: its quotes as they are
/// (before: JSON's `\"`, escaped again by the table as `\\"`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_audit_table_shows_a_refusal_escaped_once() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let db_arg = db.display().to_string();
    let p = Proc::start(&["--audit", &db_arg]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let e = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: "no-such-case".into(),
            include_mesh: false,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    assert!(e.message().contains("no case \"no-such-case\""), "{e:?}");
    // The refusal is recorded without waiting: poll for it.
    let mut line = None;
    for _ in 0..50 {
        let mut cmd = std::process::Command::new(server_exe());
        cmd.arg("audit").arg("--db").arg(&db);
        let out = run_cmd(cmd).await;
        line = out
            .lines()
            .find(|l| l.contains("refused") && l.contains("no-such-case"))
            .map(str::to_string);
        if line.is_some() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let line = line.expect("the refusal in the audit table");
    eprintln!("{line}");
    assert!(
        line.contains("DescribeCase NOT_FOUND: case_id: no case \"no-such-case\""),
        "{line}"
    );
    assert!(!line.contains('\\'), "escaped: {line}");
}
