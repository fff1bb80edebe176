//! The server end to end over loopback (127.0.0.1:0): unary and streamed registrations equal the
//! library called directly, bad input of every kind gets its status and field while the session and
//! the server go on, admission control, health and reflection, and shutdown with streams in flight.

use librplus::eval::{GeometryData, ScenarioData, load_geometry, load_scenarios, open};
use librplus::register::MeasuredKind;
use librplus::register::libr::LibrParams;
use librplus::register::pipeline::{Method, PipelineParams, Prepared, register};
use librplus_proto::v1 as pb;
use librplus_server::config::ServerConfig;
use pb::lib_r_plus_client::LibRPlusClient;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Duration;
use tonic::Code;
use tonic::transport::Channel;
use tonic_types::StatusExt;

/// A small dataset (2 geometries, 10 scenarios per deformation) with its LIBR bases cached,
/// generated once per test binary.
fn dataset() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        use librplus::phantom::dataset::{GenerateConfig, Preset, generate};
        let dir = std::env::temp_dir().join(format!("librplus-server-e2e-{}", std::process::id()));
        let path =
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/sofa_liver.vtk");
        let file = librplus::mesh::io::read(&path, librplus::mesh::io::Unit::Mm).unwrap();
        let mut s = librplus::mesh::TriSurface::from_file(&file)
            .unwrap()
            .largest_component();
        if s.signed_volume() < 0.0 {
            s.flip();
        }
        let config = GenerateConfig::preset(Preset::Small, 1, vec!["sofa_liver.vtk".into()]);
        generate(&config, &[s], &dir, (0, 1), &|_, _, _| {}).unwrap();
        // Build the bases into the cache once, so servers started in parallel only read it.
        let m = open(&dir).unwrap();
        for g in &m.geometries {
            let geo = load_geometry(&dir, &m, &g.id).unwrap();
            Prepared::new(
                geo.model,
                Some(&LibrParams::default()),
                Some(&dir.join("cache")),
            )
            .unwrap();
        }
        dir
    })
}

fn config(max_sessions: usize) -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".into(),
        cases: vec![dataset().to_path_buf()],
        max_sessions,
        // Generous: debug builds are slow, and these tests compare against undegraded results.
        time_budget_ms: 60_000,
        max_time_budget_ms: 120_000,
        max_points_per_message: 5_000,
        drain_grace_s: 20.0,
        // No SR-GCN unless a test asks (LIBR+ requests are then FAILED_PRECONDITION).
        librplus: false,
        ..ServerConfig::default()
    }
}

async fn server(max_sessions: usize) -> (librplus_server::Running, LibRPlusClient<Channel>) {
    let mut running = librplus_server::start(ServerConfig {
        metrics_listen: Some("127.0.0.1:0".into()),
        ..config(max_sessions)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let client = client(running.addr).await;
    (running, client)
}

async fn client(addr: std::net::SocketAddr) -> LibRPlusClient<Channel> {
    let ch = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    LibRPlusClient::new(ch).max_decoding_message_size(64 << 20)
}

/// A scenario with ultrasound points (the first of its deformation with 1–3 planes) and its
/// geometry.
fn scenario(category: &str) -> (GeometryData, ScenarioData) {
    let dir = dataset();
    let m = open(dir).unwrap();
    let d = &m.deformations[0];
    let geo = load_geometry(dir, &m, &d.geometry).unwrap();
    let sc = load_scenarios(dir, d)
        .unwrap()
        .into_iter()
        .find(|s| s.category == category)
        .unwrap();
    (geo, sc)
}

fn rigid_pb(r: &librplus::mesh::rigid::Rigid) -> pb::Rigid {
    pb::Rigid {
        rotation: r.rotation.iter().flatten().copied().collect(),
        translation_mm: r.translation.to_vec(),
    }
}

fn measurements_pb(m: &librplus::register::Measurements) -> pb::Measurements {
    pb::Measurements {
        xyz_mm: m.points.iter().flatten().copied().collect(),
        kind: m.kind.iter().map(|&k| k as i32 + 1).collect(),
        feature: m.feature.iter().map(|&f| f as i32).collect(),
        initial_alignment: m.initial_alignment.as_ref().map(rigid_pb),
    }
}

fn request(case: &str, method: pb::Method, m: pb::Measurements) -> pb::RegisterRequest {
    pb::RegisterRequest {
        case_id: case.into(),
        method: method as i32,
        measurements: Some(m),
        options: None,
    }
}

/// The library's answer on the same case and measurements.
fn direct(
    geo: &GeometryData,
    meas: &librplus::register::Measurements,
    method: Method,
) -> librplus::register::pipeline::Registration {
    let case = Prepared::new(
        geo.model.clone(),
        Some(&LibrParams::default()),
        Some(&dataset().join("cache")),
    )
    .unwrap();
    register(&case, meas, method, &PipelineParams::default()).unwrap()
}

/// Largest difference between the wire registration and the library's (transform entries and
/// displacements, mm).
fn difference(
    r: &pb::Registration,
    lib: &librplus::register::pipeline::Registration,
) -> (f64, f64) {
    let t = r.image_to_physical.as_ref().unwrap();
    let want = rigid_pb(&lib.image_to_physical);
    let dt = t
        .rotation
        .iter()
        .zip(&want.rotation)
        .chain(t.translation_mm.iter().zip(&want.translation_mm))
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert_eq!(r.displacement_mm.len(), lib.u.len());
    let du = r
        .displacement_mm
        .iter()
        .zip(&lib.u)
        .map(|(&a, &b)| (a as f64 - b).abs())
        .fold(0.0, f64::max);
    (dt, du)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unary_register_equals_the_library() {
    let (running, mut c) = server(4).await;
    let cases = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(cases.cases.len(), 2, "{cases:?}");
    assert!(
        cases
            .cases
            .iter()
            .all(|s| s.libr_ready && s.basis_from_cache)
    );
    let (geo, sc) = scenario("surface+2us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let desc = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: case.clone(),
            include_mesh: true,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(desc.nodes_mm.len(), 3 * geo.model.mesh.num_nodes());
    assert_eq!(desc.tets.len(), 4 * geo.model.mesh.num_tets());
    let anterior = desc.node_labels.iter().filter(|&&l| l & 1 != 0).count();
    assert_eq!(anterior, geo.model.anterior.iter().filter(|&&a| a).count());
    for (method, pm) in [
        (Method::Rigid, pb::Method::Rigid),
        (Method::Libr, pb::Method::Libr),
    ] {
        let r = c
            .register(request(&case, pm, measurements_pb(&sc.measurements)))
            .await
            .unwrap()
            .into_inner();
        let lib = direct(&geo, &sc.measurements, method);
        let (dt, du) = difference(&r, &lib);
        eprintln!(
            "unary {method:?}: quality {:?} ({}), |Δtransform| {dt:.1e}, |Δu| {du:.1e} mm, {:.0} ms",
            r.quality(),
            r.quality_reason,
            r.timings.as_ref().unwrap().total_ms
        );
        assert_eq!(r.method_used, pm as i32);
        assert_ne!(r.quality(), pb::Quality::Degraded);
        assert!(dt < 1e-9, "transform differs by {dt}");
        // f32 on the wire: displacements of tens of mm round at ~1e-6 relative.
        assert!(du < 1e-4, "displacements differ by {du} mm");
        if method == Method::Libr {
            assert!(
                lib.u.iter().any(|&x| x.abs() > 0.5),
                "LIBR deformed nothing"
            );
        }
    }
    assert_eq!(running.shutdown().await, 0);
}

/// The stream's messages for a scenario: start, surface points in batches of 40, then each
/// ultrasound point as its own plane message (pose at the point, (u, v) = (0, 0)); and the
/// measurements in the order the server accumulates them.
fn stream_of(
    case: &str,
    sc: &ScenarioData,
    method: pb::Method,
) -> (
    Vec<pb::StreamRegisterRequest>,
    librplus::register::Measurements,
) {
    use pb::stream_register_request::Msg;
    let m = &sc.measurements;
    let mut msgs = vec![pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(Msg::Start(pb::SessionStart {
            case_id: case.into(),
            method: method as i32,
            options: None,
            initial_alignment: m.initial_alignment.as_ref().map(rigid_pb),
        })),
    }];
    let mut ordered = librplus::register::Measurements {
        initial_alignment: m.initial_alignment,
        ..Default::default()
    };
    let surf: Vec<usize> = (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .collect();
    for (b, chunk) in surf.chunks(40).enumerate() {
        msgs.push(pb::StreamRegisterRequest {
            client_seq: msgs.len() as u64 + 1,
            msg: Some(Msg::Surface(pb::SurfaceBatch {
                acquired_at: Some(prost_types::Timestamp {
                    seconds: 100 + b as i64,
                    nanos: 0,
                }),
                xyz_mm: chunk.iter().flat_map(|&i| m.points[i]).collect(),
                feature: chunk.iter().map(|&i| m.feature[i] as i32).collect(),
            })),
        });
        for &i in chunk {
            ordered.points.push(m.points[i]);
            ordered.kind.push(m.kind[i]);
            ordered.feature.push(m.feature[i]);
        }
    }
    for i in (0..m.points.len()).filter(|&i| m.kind[i] != MeasuredKind::Surface) {
        let p = m.points[i];
        let uv = vec![0.0, 0.0];
        let contour = m.kind[i] == MeasuredKind::PosteriorContour;
        msgs.push(pb::StreamRegisterRequest {
            client_seq: msgs.len() as u64 + 1,
            msg: Some(Msg::Ultrasound(pb::UltrasoundPlane {
                acquired_at: Some(prost_types::Timestamp {
                    seconds: 1000 + i as i64,
                    nanos: 0,
                }),
                plane_to_physical: Some(pb::Rigid {
                    rotation: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    translation_mm: p.to_vec(),
                }),
                contour_uv_mm: if contour { uv.clone() } else { vec![] },
                vessel_uv_mm: if contour { vec![] } else { uv },
            })),
        });
        ordered.points.push(p);
        ordered.kind.push(m.kind[i]);
        ordered.feature.push(0);
    }
    (msgs, ordered)
}

/// A session handle: send one message, get the update it produced.
struct Stream {
    tx: tokio::sync::mpsc::Sender<pb::StreamRegisterRequest>,
    rx: tonic::Streaming<pb::StreamUpdate>,
}

async fn open_stream(
    c: &mut LibRPlusClient<Channel>,
    start: pb::StreamRegisterRequest,
) -> Result<Stream, tonic::Status> {
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tx.send(start).await.unwrap();
    let resp = c
        .stream_register(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?;
    Ok(Stream {
        tx,
        rx: resp.into_inner(),
    })
}

impl Stream {
    async fn send(
        &mut self,
        m: pb::StreamRegisterRequest,
    ) -> Result<pb::StreamUpdate, tonic::Status> {
        self.tx.send(m).await.unwrap();
        match self.rx.message().await? {
            Some(u) => Ok(u),
            None => Err(tonic::Status::unknown("stream ended")),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_session_equals_the_library_on_the_points_so_far() {
    let (running, mut c) = server(4).await;
    let (geo, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (msgs, ordered) = stream_of(&case, &sc, pb::Method::Libr);
    assert!(msgs.len() >= 3);
    let mut msgs = msgs.into_iter();
    let mut s = open_stream(&mut c, msgs.next().unwrap()).await.unwrap();
    let mut last = None;
    let mut seq = 0;
    for m in msgs {
        let cs = m.client_seq;
        let u = s.send(m).await.unwrap();
        seq += 1;
        assert_eq!(u.sequence, seq);
        assert_eq!(u.last_client_seq, cs);
        assert!(u.session_id.starts_with('s'));
        last = Some(u);
    }
    let last = last.unwrap();
    assert_eq!(last.points_total as usize, ordered.points.len());
    let Some(pb::stream_update::Update::Registration(r)) = last.update else {
        panic!("expected a registration, got {:?}", last.update);
    };
    let lib = direct(&geo, &ordered, Method::Libr);
    let (dt, du) = difference(&r, &lib);
    eprintln!(
        "stream: {} updates, final |Δtransform| {dt:.1e}, |Δu| {du:.1e} mm",
        seq
    );
    assert!(dt < 1e-9 && du < 1e-4, "{dt} {du}");
    drop(s);
    assert_eq!(running.shutdown().await, 0);
}

fn violations(s: &tonic::Status) -> Vec<String> {
    s.get_details_bad_request()
        .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_unary_input_gets_its_status_and_field() {
    let (running, mut c) = server(4).await;
    let (_, sc) = scenario("surface");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let good = measurements_pb(&sc.measurements);
    let mut cases: Vec<(&str, pb::RegisterRequest, Code, Option<&str>)> = Vec::new();
    let mut nan = good.clone();
    nan.xyz_mm[4] = f64::NAN;
    cases.push((
        "NaN",
        request(&case, pb::Method::Libr, nan),
        Code::InvalidArgument,
        Some("measurements.xyz_mm[4]"),
    ));
    let empty = pb::Measurements {
        xyz_mm: vec![],
        kind: vec![],
        ..good.clone()
    };
    cases.push((
        "empty",
        request(&case, pb::Method::Libr, empty),
        Code::InvalidArgument,
        Some("measurements.xyz_mm"),
    ));
    let mut ragged = good.clone();
    ragged.xyz_mm.pop();
    cases.push((
        "ragged",
        request(&case, pb::Method::Libr, ragged),
        Code::InvalidArgument,
        Some("measurements.xyz_mm"),
    ));
    let mut kinds = good.clone();
    kinds.kind.pop();
    cases.push((
        "kind count",
        request(&case, pb::Method::Libr, kinds),
        Code::InvalidArgument,
        Some("measurements.kind"),
    ));
    let mut unspecified = good.clone();
    unspecified.kind[0] = 0;
    cases.push((
        "kind unspecified",
        request(&case, pb::Method::Libr, unspecified),
        Code::InvalidArgument,
        Some("measurements.kind[0]"),
    ));
    let mut many = good.clone();
    while many.xyz_mm.len() / 3 <= 5_000 {
        many.xyz_mm.extend_from_slice(&good.xyz_mm);
        many.kind.extend_from_slice(&good.kind);
    }
    many.feature.clear();
    cases.push((
        "too many points",
        request(&case, pb::Method::Libr, many),
        Code::InvalidArgument,
        Some("measurements.xyz_mm"),
    ));
    let mut rot = good.clone();
    rot.initial_alignment.as_mut().unwrap().rotation[0] = 2.0;
    cases.push((
        "not a rotation",
        request(&case, pb::Method::Libr, rot),
        Code::InvalidArgument,
        Some("measurements.initial_alignment.rotation"),
    ));
    cases.push((
        "unknown case",
        request("nope", pb::Method::Libr, good.clone()),
        Code::NotFound,
        Some("case_id"),
    ));
    cases.push((
        "LIBR+ without weights",
        request(&case, pb::Method::LibrPlus, good.clone()),
        Code::FailedPrecondition,
        None,
    ));
    let mut bad_method = request(&case, pb::Method::Libr, good.clone());
    bad_method.method = 17;
    cases.push((
        "unknown method",
        bad_method,
        Code::InvalidArgument,
        Some("method"),
    ));
    let mut far = good.clone();
    for x in far.xyz_mm.iter_mut() {
        *x += 1000.0;
    }
    cases.push((
        "points 1 m away",
        request(&case, pb::Method::Libr, far),
        Code::FailedPrecondition,
        None,
    ));
    let mut budget = request(&case, pb::Method::Libr, good.clone());
    budget.options = Some(pb::RegisterOptions {
        time_budget_ms: 1_000_000,
        omit_displacements: false,
    });
    cases.push((
        "budget too large",
        budget,
        Code::InvalidArgument,
        Some("options.time_budget_ms"),
    ));
    for (name, req, code, field) in cases {
        let e = c.register(req).await.expect_err(name);
        eprintln!(
            "{name}: {:?} {:?} {:?}",
            e.code(),
            e.message(),
            violations(&e)
        );
        assert_eq!(e.code(), code, "{name}: {e:?}");
        if let Some(f) = field {
            assert!(
                violations(&e).iter().any(|v| v == f),
                "{name}: {:?}",
                violations(&e)
            );
        }
    }
    // All points on one spot: a flagged degenerate rigid result, not a deformation.
    let mut spot = good.clone();
    let p0 = [spot.xyz_mm[0], spot.xyz_mm[1], spot.xyz_mm[2]];
    for c3 in spot.xyz_mm.chunks_exact_mut(3) {
        c3.copy_from_slice(&p0);
    }
    let r = c
        .register(request(&case, pb::Method::Libr, spot))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.quality(), pb::Quality::Degenerate, "{}", r.quality_reason);
    assert_eq!(r.method_used(), pb::Method::Rigid);
    assert!(r.displacement_mm.iter().all(|&x| x == 0.0));
    // The server is alive and answers a good request.
    let ok = c
        .register(request(&case, pb::Method::Rigid, good))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(ok.method_used(), pb::Method::Rigid);
    assert_eq!(running.shutdown().await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_stream_input_is_rejected_and_the_session_goes_on() {
    use pb::stream_register_request::Msg;
    let (running, mut c) = server(4).await;
    let (_, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    // A session must start with a SessionStart; an unknown case ends it with NOT_FOUND.
    let mut not_start = msgs[1].clone();
    not_start.client_seq = 1;
    let e = match open_stream(&mut c, not_start).await {
        Err(e) => e,
        Ok(mut s) => s.rx.message().await.expect_err("must fail"),
    };
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    let mut unknown = msgs[0].clone();
    if let Some(Msg::Start(st)) = unknown.msg.as_mut() {
        st.case_id = "nope".into();
    }
    let e = match open_stream(&mut c, unknown).await {
        Err(e) => e,
        Ok(mut s) => s.rx.message().await.expect_err("must fail"),
    };
    assert_eq!(e.code(), Code::NotFound, "{e:?}");

    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let first = msgs[1].clone();
    let u = s.send(first.clone()).await.unwrap();
    assert!(
        matches!(u.update, Some(pb::stream_update::Update::Registration(_))),
        "{u:?}"
    );
    let reject = |u: pb::StreamUpdate| -> pb::Rejection {
        match u.update {
            Some(pb::stream_update::Update::Rejection(r)) => r,
            other => panic!("expected a rejection, got {other:?}"),
        }
    };
    let mut next_seq = 10u64;
    let mut with_seq = |mut m: pb::StreamRegisterRequest| {
        next_seq += 1;
        m.client_seq = next_seq;
        m
    };
    // Duplicate and out-of-order client_seq.
    let r = reject(s.send(first.clone()).await.unwrap());
    assert_eq!(
        (r.code.as_str(), r.violations[0].field.as_str()),
        ("FAILED_PRECONDITION", "client_seq")
    );
    let mut older = first.clone();
    older.client_seq = 1;
    let r = reject(s.send(older).await.unwrap());
    assert_eq!(r.code, "FAILED_PRECONDITION");
    // NaN in a surface batch.
    let mut nan = with_seq(first.clone());
    if let Some(Msg::Surface(b)) = nan.msg.as_mut() {
        b.xyz_mm[2] = f64::INFINITY;
        b.acquired_at = Some(prost_types::Timestamp {
            seconds: 200,
            nanos: 0,
        });
    }
    let r = reject(s.send(nan).await.unwrap());
    assert_eq!(
        (r.code.as_str(), r.violations[0].field.as_str()),
        ("INVALID_ARGUMENT", "surface.xyz_mm[2]")
    );
    // A frame acquired before the previous one.
    let mut late = with_seq(first.clone());
    if let Some(Msg::Surface(b)) = late.msg.as_mut() {
        b.acquired_at = Some(prost_types::Timestamp {
            seconds: 1,
            nanos: 0,
        });
    }
    let r = reject(s.send(late).await.unwrap());
    assert_eq!(
        (r.code.as_str(), r.violations[0].field.as_str()),
        ("FAILED_PRECONDITION", "surface.acquired_at")
    );
    // A second start, an empty message, an empty batch, a plane without a pose.
    let r = reject(s.send(with_seq(msgs[0].clone())).await.unwrap());
    assert_eq!(r.code, "FAILED_PRECONDITION");
    let r = reject(
        s.send(with_seq(pb::StreamRegisterRequest {
            client_seq: 0,
            msg: None,
        }))
        .await
        .unwrap(),
    );
    assert_eq!(r.violations[0].field, "msg");
    let empty = pb::StreamRegisterRequest {
        client_seq: 0,
        msg: Some(Msg::Surface(pb::SurfaceBatch {
            acquired_at: None,
            xyz_mm: vec![],
            feature: vec![],
        })),
    };
    let r = reject(s.send(with_seq(empty)).await.unwrap());
    assert_eq!(r.violations[0].field, "surface.xyz_mm");
    let poseless = pb::StreamRegisterRequest {
        client_seq: 0,
        msg: Some(Msg::Ultrasound(pb::UltrasoundPlane {
            acquired_at: None,
            plane_to_physical: None,
            contour_uv_mm: vec![1.0, 2.0],
            vessel_uv_mm: vec![],
        })),
    };
    let r = reject(s.send(with_seq(poseless)).await.unwrap());
    assert_eq!(r.violations[0].field, "ultrasound.plane_to_physical");
    // The session goes on: the next good message registers all points accepted so far.
    let mut good = with_seq(msgs[2].clone());
    if let Some(Msg::Surface(b)) = good.msg.as_mut() {
        b.acquired_at = Some(prost_types::Timestamp {
            seconds: 300,
            nanos: 0,
        });
    }
    if let Some(Msg::Ultrasound(p)) = good.msg.as_mut() {
        p.acquired_at = Some(prost_types::Timestamp {
            seconds: 300,
            nanos: 0,
        });
    }
    let u = s.send(good).await.unwrap();
    assert!(
        matches!(u.update, Some(pb::stream_update::Update::Registration(_))),
        "{u:?}"
    );
    drop(s);
    assert_eq!(running.shutdown().await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_beyond_the_limit_are_refused_and_health_and_reflection_answer() {
    let (running, mut c) = server(2).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    let mut a = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let mut b = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    // Both are admitted (their first update arrives).
    a.send(msgs[1].clone()).await.unwrap();
    b.send(msgs[1].clone()).await.unwrap();
    let e = match open_stream(&mut c, msgs[0].clone()).await {
        Err(e) => e,
        Ok(mut s) => {
            s.rx.message()
                .await
                .expect_err("third session must be refused")
        }
    };
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.get_details_quota_failure().is_some());
    // Unary calls still work beside the full sessions.
    let r = c
        .register(request(
            &case,
            pb::Method::Rigid,
            measurements_pb(&sc.measurements),
        ))
        .await
        .unwrap();
    assert_eq!(r.into_inner().method_used(), pb::Method::Rigid);
    // When one ends, a new one is admitted.
    drop(a);
    let mut ok = None;
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(20)).await;
        if let Ok(mut s) = open_stream(&mut c, msgs[0].clone()).await
            && s.send(msgs[1].clone()).await.is_ok()
        {
            ok = Some(s);
            break;
        }
    }
    assert!(ok.is_some(), "no session admitted after one ended");

    // Health: SERVING for the server and the service.
    let ch = tonic::transport::Endpoint::from_shared(format!("http://{}", running.addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(ch.clone());
    for service in ["", "librplus.v1.LibRPlus"] {
        let h = health
            .check(tonic_health::pb::HealthCheckRequest {
                service: service.into(),
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(
            h.status(),
            tonic_health::pb::health_check_response::ServingStatus::Serving
        );
    }
    // Reflection v1 lists the services.
    use tonic_reflection::pb::v1::{
        ServerReflectionRequest, server_reflection_client::ServerReflectionClient,
        server_reflection_request::MessageRequest, server_reflection_response::MessageResponse,
    };
    let mut refl = ServerReflectionClient::new(ch);
    let req = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut resp = refl
        .server_reflection_info(tokio_stream::iter(vec![req]))
        .await
        .unwrap()
        .into_inner();
    let Some(MessageResponse::ListServicesResponse(list)) =
        resp.message().await.unwrap().unwrap().message_response
    else {
        panic!("no list");
    };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    assert!(
        names.iter().any(|n| n == "librplus.v1.LibRPlus"),
        "{names:?}"
    );
    assert!(
        names.iter().any(|n| n == "grpc.health.v1.Health"),
        "{names:?}"
    );
    drop((b, ok));
    // Prometheus text: latency histograms per stage, session and error counters.
    let metrics = {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut sock = tokio::net::TcpStream::connect(running.metrics_addr.unwrap())
            .await
            .unwrap();
        sock.write_all(b"GET /metrics HTTP/1.1\r\nhost: x\r\n\r\n")
            .await
            .unwrap();
        let mut body = String::new();
        sock.read_to_string(&mut body).await.unwrap();
        body
    };
    assert!(metrics.starts_with("HTTP/1.1 200"), "{metrics}");
    for needle in [
        "librplus_stage_seconds_bucket{stage=\"rigid\"",
        "librplus_stage_seconds_bucket{stage=\"total\"",
        "librplus_refused_total{reason=\"sessions\"}",
        "librplus_errors_total{code=\"RESOURCE_EXHAUSTED\"}",
        "librplus_sessions_active",
    ] {
        assert!(metrics.contains(needle), "{needle} missing from\n{metrics}");
    }
    assert_eq!(running.shutdown().await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_drains_streams_in_flight() {
    let (running, mut c) = server(4).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+3us");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let mut streams = Vec::new();
    for _ in 0..3 {
        let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
        s.send(msgs[1].clone()).await.unwrap();
        streams.push(s);
    }
    // Messages in flight when shutdown begins: each session finishes its update, then ends with
    // UNAVAILABLE; shutdown returns with no session left.
    for s in &mut streams {
        s.tx.send(msgs[2].clone()).await.unwrap();
    }
    let addr = running.addr;
    let t0 = std::time::Instant::now();
    let left = running.shutdown().await;
    assert_eq!(left, 0);
    eprintln!("drained in {:.0} ms", t0.elapsed().as_secs_f64() * 1e3);
    for mut s in streams {
        let mut got_update = false;
        loop {
            match s.rx.message().await {
                Ok(Some(_)) => got_update = true,
                Ok(None) => panic!("stream ended without a status"),
                Err(e) => {
                    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
                    break;
                }
            }
        }
        let _ = got_update;
    }
    // The port is closed: new connections fail.
    let again = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect_timeout(Duration::from_secs(1))
        .connect()
        .await;
    assert!(again.is_err());
}

/// Runs a command to completion on a blocking thread; its stdout (panics with stderr on failure).
async fn run_cmd(mut cmd: std::process::Command) -> String {
    let shown = format!("{cmd:?}");
    let out = tokio::task::spawn_blocking(move || cmd.output())
        .await
        .unwrap()
        .unwrap_or_else(|e| panic!("{shown}: {e}"));
    assert!(
        out.status.success(),
        "{shown}: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// Clients nobody here wrote: Python grpcio with stubs generated by grpcio-tools from the proto
/// streams a session (same displacements as the library), and grpcurl lists the services by
/// reflection (v1alpha: grpcurl 1.8.6) and calls the health check. Needs the Python environment
/// `.ci/run` installs (`LIBRPLUS_CHECK_PYTHON`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_grpcio_client_and_grpcurl() {
    let Some(py) = std::env::var_os("LIBRPLUS_CHECK_PYTHON") else {
        eprintln!("note: LIBRPLUS_CHECK_PYTHON not set; the grpcio/grpcurl check runs in .ci/run");
        return;
    };
    let py = PathBuf::from(py);
    let (running, _) = server(4).await;
    let addr = running.addr.to_string();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let stubs = tempfile::tempdir().unwrap();
    let mut c = std::process::Command::new(&py);
    c.args([
        "-c",
        "import grpc_tools, os; print(os.path.join(os.path.dirname(grpc_tools.__file__), '_proto'))",
    ]);
    let wkt = run_cmd(c).await.trim().to_string();
    let mut c = std::process::Command::new(&py);
    c.arg("-m")
        .arg("grpc_tools.protoc")
        .arg(format!("-I{}", root.join("proto").display()))
        .arg(format!("-I{wkt}"))
        .arg(format!("--python_out={}", stubs.path().display()))
        .arg(format!("--grpc_python_out={}", stubs.path().display()))
        .arg("librplus/v1/librplus.proto");
    run_cmd(c).await;

    let (geo, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let m = &sc.measurements;
    let ia = m.initial_alignment.unwrap();
    let json = serde_json::json!({
        "case_id": case,
        "points": m.points,
        "kind": m.kind.iter().map(|&k| k as i32 + 1).collect::<Vec<_>>(),
        "feature": m.feature,
        "initial_alignment": {"rotation": ia.rotation.iter().flatten().collect::<Vec<_>>(), "translation_mm": ia.translation},
    });
    let scenario_file = stubs.path().join("scenario.json");
    std::fs::write(&scenario_file, json.to_string()).unwrap();
    let mut c = std::process::Command::new(&py);
    c.arg(root.join("server/tests/py/stream_client.py"))
        .arg(stubs.path())
        .arg(&addr)
        .arg(&scenario_file);
    let out: serde_json::Value = serde_json::from_str(&run_cmd(c).await).unwrap();
    // The library on the points in the order the stream delivered them (surface, then planes).
    let (_, ordered) = stream_of(&case, &sc, pb::Method::Libr);
    let lib = direct(&geo, &ordered, Method::Libr);
    let u: Vec<f64> = serde_json::from_value(out["displacement_mm"].clone()).unwrap();
    let du = u
        .iter()
        .zip(&lib.u)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let t: Vec<f64> =
        serde_json::from_value(out["image_to_physical"]["translation_mm"].clone()).unwrap();
    let dt = t
        .iter()
        .zip(&lib.image_to_physical.translation)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    eprintln!(
        "python grpcio: {} updates, {} registrations, {} points, {} / {}, |Δu| {du:.1e} mm, |Δt| {dt:.1e} mm, rejection {}",
        out["updates"],
        out["registrations"],
        out["points_total"],
        out["method_used"],
        out["quality"],
        out["rejection"]
    );
    assert_eq!(u.len(), lib.u.len());
    assert!(du < 1e-4 && dt < 1e-9, "{du} {dt}");
    assert_eq!(
        out["points_total"].as_u64().unwrap() as usize,
        m.points.len()
    );
    assert_eq!(out["method_used"], "METHOD_LIBR");
    assert_eq!(out["rejection"]["code"], "INVALID_ARGUMENT");
    assert_eq!(out["rejection"]["fields"][0], "surface.xyz_mm[0]");
    assert_eq!(out["after_rejection"], "registration");
    assert_eq!(out["trailing_updates"], 0);

    // grpcurl (reflection v1alpha, health).
    let grpcurl = py.parent().unwrap().join("grpcurl");
    let mut c = std::process::Command::new(&grpcurl);
    c.args(["-plaintext", &addr, "list"]);
    let list = run_cmd(c).await;
    eprintln!("grpcurl list:\n{list}");
    for s in ["librplus.v1.LibRPlus", "grpc.health.v1.Health"] {
        assert!(
            list.lines().any(|l| l.trim() == s),
            "{s} missing from {list}"
        );
    }
    let mut c = std::process::Command::new(&grpcurl);
    c.args([
        "-plaintext",
        "-d",
        "{\"service\": \"\"}",
        &addr,
        "grpc.health.v1.Health/Check",
    ]);
    let health = run_cmd(c).await;
    assert!(health.contains("\"SERVING\""), "{health}");
    let mut c = std::process::Command::new(&grpcurl);
    c.args([
        "-plaintext",
        "-d",
        "{}",
        &addr,
        "librplus.v1.LibRPlus/ListCases",
    ]);
    let cases = run_cmd(c).await;
    assert!(cases.contains(&format!("\"{case}\"")), "{cases}");
    assert_eq!(running.shutdown().await, 0);
}

/// The project's own clients against the real server: `replay` scores every selected scenario
/// (TRE below the initial alignment's for LIBR), and `load` beyond the session limit counts the
/// refused sessions as RESOURCE_EXHAUSTED while the admitted ones see no error.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_and_load_clients_against_the_server() {
    let (running, _) = server(2).await;
    let url = format!("http://{}", running.addr);
    let summary = librplus_client::replay(&librplus_client::ReplayOptions {
        server: url.clone(),
        data: dataset().to_path_buf(),
        selection: librplus_client::Selection::Spread(5),
        methods: vec![pb::Method::Rigid, pb::Method::Libr],
        ..Default::default()
    })
    .await
    .unwrap();
    eprintln!(
        "replay: {} updates, TRE {:?}, rejections {}",
        summary.updates, summary.tre_mm, summary.rejections
    );
    assert_eq!(
        (summary.scenarios, summary.failed, summary.rejections),
        (5, 0, 0)
    );
    let (rigid, libr) = (summary.tre_mm["rigid"], summary.tre_mm["libr"]);
    assert!(libr < rigid, "LIBR {libr} vs rigid {rigid}");
    let load = librplus_client::load(&librplus_client::LoadOptions {
        server: url,
        data: dataset().to_path_buf(),
        selection: librplus_client::Selection::Spread(4),
        method: pb::Method::Rigid,
        concurrency: 4,
        duration: Duration::from_secs(3),
        ..Default::default()
    })
    .await
    .unwrap();
    eprintln!(
        "load: {} requests, errors {:?}, sessions {:?}",
        load.requests, load.errors, load.sessions
    );
    assert!(load.requests > 0);
    assert!(
        load.errors.get("RESOURCE_EXHAUSTED").copied().unwrap_or(0) > 0,
        "{:?}",
        load.errors
    );
    assert!(
        load.errors.keys().all(|k| k == "RESOURCE_EXHAUSTED"),
        "errors other than admission: {:?}",
        load.errors
    );
    assert_eq!(running.shutdown().await, 0);
}

/// A client that sends faster than registrations complete: messages waiting when a registration
/// ends are folded into the next one (latest wins), every update answers the newest message it
/// saw, and the last one registers every point (equal to the library).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_sent_faster_than_answers_are_folded_into_the_newest_state() {
    let (running, mut c) = server(4).await;
    let (geo, sc) = scenario("surface+16us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (msgs, ordered) = stream_of(&case, &sc, pb::Method::Libr);
    let last_seq = msgs.last().unwrap().client_seq;
    let n = msgs.len();
    let (tx, rx) = tokio::sync::mpsc::channel(n);
    for m in msgs {
        tx.send(m).await.unwrap();
    }
    drop(tx);
    let mut updates = c
        .stream_register(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut got = Vec::new();
    while let Some(u) = updates.message().await.unwrap() {
        got.push(u);
    }
    eprintln!("{} messages, {} updates", n - 1, got.len());
    assert!(
        !got.is_empty() && got.len() < n - 1,
        "{} updates for {} messages",
        got.len(),
        n - 1
    );
    assert!(
        got.windows(2)
            .all(|w| w[0].last_client_seq < w[1].last_client_seq)
    );
    let last = got.pop().unwrap();
    assert_eq!(last.last_client_seq, last_seq);
    assert_eq!(last.points_total as usize, ordered.points.len());
    let Some(pb::stream_update::Update::Registration(r)) = last.update else {
        panic!("expected a registration");
    };
    let (dt, du) = difference(&r, &direct(&geo, &ordered, Method::Libr));
    assert!(dt < 1e-9 && du < 1e-4, "{dt} {du}");
    assert_eq!(running.shutdown().await, 0);
}

/// `--cases` also takes a folder of preoperative meshes: a labelled `.vtu` (with its vessels
/// beside it) keeps its labels, a bare tet mesh is labelled from its geometry; each file is a case
/// named by its stem.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_folder_of_meshes_is_a_set_of_cases() {
    let m = open(dataset()).unwrap();
    let g = &m.geometries[0];
    let folder = tempfile::tempdir().unwrap();
    std::fs::copy(dataset().join(&g.preop), folder.path().join("labelled.vtu")).unwrap();
    std::fs::copy(
        dataset().join(&g.vessels),
        folder.path().join("labelled.vessels.vtp"),
    )
    .unwrap();
    let geo = load_geometry(dataset(), &m, &g.id).unwrap();
    librplus::mesh::io::write(
        folder.path().join("bare.vtu"),
        &geo.model.mesh.to_file(),
        Default::default(),
    )
    .unwrap();
    let mut running = librplus_server::start(ServerConfig {
        cases: vec![folder.path().to_path_buf()],
        ..config(2)
    })
    .await
    .unwrap();
    let report = running.ready().await.unwrap();
    assert_eq!(report.cases.len(), 2, "{report:?}");
    let mut c = client(running.addr).await;
    let list = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    let ids: Vec<&str> = list.cases.iter().map(|c| c.case_id.as_str()).collect();
    assert_eq!(ids, ["bare", "labelled"]);
    let describe = |id: &str| pb::DescribeCaseRequest {
        case_id: id.into(),
        include_mesh: true,
    };
    let labelled = c
        .describe_case(describe("labelled"))
        .await
        .unwrap()
        .into_inner();
    let bare = c
        .describe_case(describe("bare"))
        .await
        .unwrap()
        .into_inner();
    let count = |d: &pb::DescribeCaseResponse, bit: u32| {
        d.node_labels.iter().filter(|&&l| l & bit != 0).count()
    };
    assert_eq!(
        count(&labelled, 1),
        geo.model.anterior.iter().filter(|&&a| a).count()
    );
    assert_eq!(
        labelled.vessel_segments.len(),
        2 * geo.model.vessel_segments.len()
    );
    assert!(bare.vessel_points_mm.is_empty());
    // Automatic labels on the same geometry: the anterior and posterior sets are most of the
    // boundary, as the dataset's own labels (made by the same labeller) are.
    assert_eq!(count(&bare, 1), count(&labelled, 1));
    assert_eq!(count(&bare, 2), count(&labelled, 2));
    let (_, sc) = scenario("surface");
    let mut meas = sc.measurements.clone();
    let keep: Vec<usize> = (0..meas.points.len())
        .filter(|&i| meas.kind[i] != MeasuredKind::Vessel)
        .collect();
    meas.points = keep.iter().map(|&i| meas.points[i]).collect();
    meas.kind = keep.iter().map(|&i| meas.kind[i]).collect();
    meas.feature = keep.iter().map(|&i| meas.feature[i]).collect();
    let r = c
        .register(request("bare", pb::Method::Libr, measurements_pb(&meas)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.method_used(), pb::Method::Libr);
    assert_eq!(r.node_count as usize, geo.model.mesh.num_nodes());
    assert_eq!(running.shutdown().await, 0);
}

/// The binary: `librplus-server --cases DIR --listen 127.0.0.1:0` serves, and SIGTERM drains a
/// stream in flight (it ends with UNAVAILABLE) and exits 0.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_binary_drains_on_sigterm() {
    use std::io::BufRead;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_librplus-server"))
        .arg("--cases")
        .arg(dataset())
        .args(["--listen", "127.0.0.1:0"])
        .env("RUST_LOG", "warn")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (addr_tx, addr_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut sent = false;
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            if !sent && let Some(a) = line.strip_prefix("librplus-server listening on ") {
                addr_tx.send(a.trim().to_string()).unwrap();
                sent = true;
            }
        }
    });
    let addr: std::net::SocketAddr = addr_rx
        .recv_timeout(Duration::from_secs(60))
        .unwrap()
        .parse()
        .unwrap();
    let ch = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(ch.clone());
    let serving = tonic_health::pb::health_check_response::ServingStatus::Serving;
    let mut up = false;
    for _ in 0..600 {
        let h = health
            .check(tonic_health::pb::HealthCheckRequest {
                service: String::new(),
            })
            .await
            .unwrap()
            .into_inner();
        if h.status() == serving {
            up = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(up, "never SERVING");
    let mut c = LibRPlusClient::new(ch);
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+1us");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    s.send(msgs[1].clone()).await.unwrap();
    let kill = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let e = loop {
        match s.rx.message().await {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("stream ended without a status"),
            Err(e) => break e,
        }
    };
    assert_eq!(e.code(), Code::Unavailable, "{e:?}");
    let status = tokio::task::spawn_blocking(move || child.wait())
        .await
        .unwrap()
        .unwrap();
    assert!(status.success(), "{status}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn librplus_answers_through_the_same_api_as_the_library() {
    use librplus::gcn::io::{TrainedModel, save_model};
    use librplus::gcn::model::SrGcnConfig;
    let tmp = tempfile::tempdir().unwrap();
    let cfg = SrGcnConfig::new()
        .with_width(8)
        .with_convs(1)
        .with_levels(2);
    let model = TrainedModel::untrained(cfg, 7).unwrap();
    save_model(
        tmp.path(),
        &model.config,
        &model.net,
        model.provenance.clone(),
    )
    .unwrap();
    let mut running = librplus_server::start(ServerConfig {
        model: Some(tmp.path().to_path_buf()),
        librplus: true,
        ..config(2)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let cases = c
        .list_cases(pb::ListCasesRequest {})
        .await
        .unwrap()
        .into_inner();
    assert!(cases.cases.iter().all(|s| s.libr_plus_ready), "{cases:?}");
    let (geo, sc) = scenario("surface+1us");
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let r = c
        .register(request(
            &case,
            pb::Method::LibrPlus,
            measurements_pb(&sc.measurements),
        ))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.method_used, pb::Method::LibrPlus as i32, "{r:?}");
    assert_ne!(r.quality(), pb::Quality::Degraded, "{}", r.quality_reason);
    let t = r.timings.as_ref().unwrap();
    assert!(
        t.gcn_ms > 0.0 && t.refit_ms > 0.0 && t.refit_ms < t.gcn_ms,
        "{t:?}"
    );
    assert!(t.refit_iterations >= 1, "{t:?}");
    let prepared = Prepared::new(
        geo.model.clone(),
        Some(&LibrParams::default()),
        Some(&dataset().join("cache")),
    )
    .unwrap()
    .with_model(std::sync::Arc::new(
        librplus::gcn::io::load_model_on_device(tmp.path()).unwrap(),
    ))
    .unwrap();
    let p = PipelineParams::default();
    let lib = register(&prepared, &sc.measurements, Method::LibrPlus, &p).unwrap();
    let (dt, du) = difference(&r, &lib);
    assert!(
        dt < 1e-9 && du < 1e-4,
        "transform {dt}, displacements {du} mm"
    );
    // The fit figures are the refit's, the answer's last stage.
    let refit = lib.correction.as_ref().unwrap().refit.as_ref().unwrap();
    assert_eq!(t.refit_iterations as usize, refit.iterations);
    assert!((r.residual_rms_mm - refit.rms_mm).abs() < 1e-6, "{r:?}");
    let libr = register(&prepared, &sc.measurements, Method::Libr, &p).unwrap();
    assert_ne!(lib.u, libr.u);
    assert_eq!(running.shutdown().await, 0);
}
