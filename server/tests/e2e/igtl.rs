//! The OpenIGTLink bridge (`librplus-server igtl`) against the real server: a scenario streamed as
//! POINT messages (surface) and TRANSFORM + POLYDATA (an ultrasound plane) gets back, after every
//! update, the TRANSFORM, target POINT and liver POLYDATA that the gRPC answer to the same points
//! implies (frame RAS; ≤ 1e-4 mm); malformed messages (bad CRC, wrong size, unknown type) are
//! answered with STATUS and the connection goes on. With `LIBRPLUS_CHECK_PYTHON` (CI), pyigtl
//! from PyPI is the peer for the POINT/TRANSFORM path and a POLYDATA decoder written from the
//! specification in Python checks the liver message.

use crate::common::*;
use librplus::mesh::TetMesh;
use librplus::mesh::locate::TetLocator;
use librplus::mesh::rigid::Rigid;
use librplus_server::igtl::bridge::{self, BridgeConfig, Frame, Target};
use librplus_server::igtl::wire::{
    self, AttributeKind, AttributeLocation, EncodeOptions, Message, PointElement, PolyAttribute,
    PolyData, Transform, status_code,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

const BUDGET_MS: u32 = 120_000;

/// One whole message read off the socket by hand (header, then BODY_SIZE bytes): the raw bytes.
async fn read_raw(s: &mut TcpStream) -> Vec<u8> {
    let mut buf = vec![0u8; wire::HEADER_SIZE];
    tokio::time::timeout(Duration::from_secs(300), s.read_exact(&mut buf))
        .await
        .expect("an answer from the bridge within 300 s")
        .unwrap();
    let size = u64::from_be_bytes(buf[42..50].try_into().unwrap()) as usize;
    let mut body = vec![0u8; size];
    s.read_exact(&mut body).await.unwrap();
    buf.extend(body);
    buf
}

/// Messages until one of type `until` has come (returned with the raw bytes of each).
async fn read_until(s: &mut TcpStream, until: &str) -> Vec<(wire::Header, Message, Vec<u8>)> {
    let mut out = Vec::new();
    loop {
        let raw = read_raw(s).await;
        let (h, m) = wire::decode_message(&raw).unwrap();
        let done = h.type_name == until;
        out.push((h, m, raw));
        if done {
            return out;
        }
    }
}

fn ras(p: [f64; 3]) -> [f64; 3] {
    Frame::Ras.convert(p)
}

/// What a registration implies in RAS: F T F, the targets and the boundary nodes where it puts
/// them, and the boundary nodes' displacement F R u.
struct Expected {
    transform: [[f64; 4]; 4],
    targets: Vec<[f64; 3]>,
    surface: Vec<[f64; 3]>,
    displacement: Vec<[f64; 3]>,
    /// The error estimate's bound at the boundary nodes (as sent, f32).
    uncertainty: Vec<f32>,
}

fn expected(
    r: &pb::Registration,
    geo: &GeometryData,
    surface_nodes: &[u32],
    targets: &[([u32; 4], [f64; 4], [f64; 3])],
) -> Expected {
    let t = librplus_client::rigid_from_message(r.image_to_physical.as_ref().unwrap()).unwrap();
    let u: Vec<f64> = r.displacement_mm.iter().map(|&x| f64::from(x)).collect();
    let x = geo.model.mesh.nodes();
    let place = |p: [f64; 3], d: [f64; 3]| ras(t.apply([p[0] + d[0], p[1] + d[1], p[2] + d[2]]));
    let ud = |i: usize| [u[3 * i], u[3 * i + 1], u[3 * i + 2]];
    let mut f = Rigid::identity();
    f.rotation[0][0] = -1.0;
    f.rotation[1][1] = -1.0;
    let ftf = f.then(&t).then(&f);
    let mut m = [
        [0.0, 0.0, 0.0, 0.0],
        [0.0; 4],
        [0.0; 4],
        [0.0, 0.0, 0.0, 1.0],
    ];
    for (i, row) in m.iter_mut().take(3).enumerate() {
        row[..3].copy_from_slice(&ftf.rotation[i]);
        row[3] = ftf.translation[i];
    }
    Expected {
        transform: m,
        targets: targets
            .iter()
            .map(|(tet, w, p)| {
                let mut d = [0.0; 3];
                for k in 0..4 {
                    let n = ud(tet[k] as usize);
                    for a in 0..3 {
                        d[a] += w[k] * n[a];
                    }
                }
                place(*p, d)
            })
            .collect(),
        surface: surface_nodes
            .iter()
            .map(|&i| place(x[i as usize], ud(i as usize)))
            .collect(),
        displacement: surface_nodes
            .iter()
            .map(|&i| ras(t.apply_vector(ud(i as usize))))
            .collect(),
        uncertainty: r
            .error_estimate
            .as_ref()
            .map(|e| {
                surface_nodes
                    .iter()
                    .map(|&i| e.node_uncertainty_mm[i as usize])
                    .collect()
            })
            .unwrap_or_default(),
    }
}

fn worst(a: impl IntoIterator<Item = f64>) -> f64 {
    a.into_iter().fold(0.0, |m, x| m.max(x.abs()))
}

/// Checks a bridge answer (its TRANSFORM, target POINT and liver POLYDATA) against `e`; returns
/// the largest differences (transform translation, target, surface point, mm).
fn check(answer: &[(wire::Header, Message, Vec<u8>)], e: &Expected) -> [f64; 3] {
    let find = |kind: &str, device: &str| {
        answer
            .iter()
            .find(|(h, _, _)| h.type_name == kind && h.device_name == device)
            .unwrap_or_else(|| panic!("no {kind} {device} in the answer"))
    };
    let Message::Transform(t) = &find("TRANSFORM", bridge::DEVICE_TRANSFORM).1 else {
        unreachable!()
    };
    for i in 0..3 {
        for j in 0..3 {
            assert!(
                (t.matrix[i][j] - e.transform[i][j]).abs() < 1e-6,
                "R[{i}][{j}]"
            );
        }
    }
    let dt = worst((0..3).map(|i| t.matrix[i][3] - e.transform[i][3]));
    let Message::Point(p) = &find("POINT", bridge::DEVICE_TARGETS).1 else {
        unreachable!()
    };
    assert_eq!(p.len(), e.targets.len());
    let dp = worst(
        p.iter()
            .zip(&e.targets)
            .flat_map(|(a, b)| (0..3).map(move |k| f64::from(a.position_mm[k]) - b[k])),
    );
    let Message::PolyData(pd) = &find("POLYDATA", bridge::DEVICE_LIVER).1 else {
        unreachable!()
    };
    assert_eq!(pd.points.len(), e.surface.len());
    let ds = worst(
        pd.points
            .iter()
            .zip(&e.surface)
            .flat_map(|(a, b)| (0..3).map(move |k| f64::from(a[k]) - b[k])),
    );
    let disp = pd
        .attributes
        .iter()
        .find(|a| a.name == "displacement")
        .unwrap();
    assert_eq!(disp.kind, AttributeKind::Vector);
    let dd = worst(
        disp.data
            .chunks_exact(3)
            .zip(&e.displacement)
            .flat_map(|(a, b)| (0..3).map(move |k| f64::from(a[k]) - b[k])),
    );
    assert!(dd <= 1e-4, "displacement differs by {dd} mm");
    // The server estimates every registration's error: the bound, node for node.
    assert_eq!(
        e.uncertainty.len(),
        e.surface.len(),
        "no error estimate in the gRPC answer"
    );
    let unc = pd
        .attributes
        .iter()
        .find(|a| a.name == "uncertainty_mm")
        .expect("an uncertainty_mm attribute");
    assert_eq!(unc.kind, AttributeKind::Scalar { components: 1 });
    assert_eq!(unc.data, e.uncertainty);
    [dt, dp, ds]
}

fn point_message(points: &[[f32; 3]], k: usize) -> Vec<u8> {
    let elements = points
        .iter()
        .enumerate()
        .map(|(i, p)| PointElement {
            name: format!("p{i}"),
            group: "Surface".into(),
            rgba: [0, 255, 0, 255],
            position_mm: *p,
            diameter_mm: 1.0,
            owner: String::new(),
        })
        .collect();
    Message::Point(elements)
        .encode(
            "Stylus",
            &EncodeOptions {
                timestamp: wire::timestamp_from_secs(1000.0 + k as f64),
                ..EncodeOptions::default()
            },
        )
        .unwrap()
}

/// The bridge's configuration for `case` on `running` (frame RAS, no targets, 1 MiB bodies, the
/// default limits).
fn bridge_config(
    running: &librplus_server::Running,
    case: &str,
    method: pb::Method,
) -> BridgeConfig {
    BridgeConfig {
        server: format!("http://{}", running.addr),
        tls: Default::default(),
        token: None,
        case_id: case.into(),
        method,
        time_budget_ms: BUDGET_MS,
        frame: Frame::Ras,
        targets: Vec::new(),
        max_body: 1 << 20,
        max_sessions: bridge::DEFAULT_MAX_SESSIONS,
        idle_timeout: Duration::from_secs_f64(bridge::DEFAULT_IDLE_TIMEOUT_S),
        session_idle_timeout: Duration::from_secs_f64(bridge::DEFAULT_SESSION_IDLE_TIMEOUT_S),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bridge_answers_as_the_grpc_session_and_survives_malformed_messages() {
    let (running, mut grpc) = server(4).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (geo, sc) = scenario("surface+1us");
    let x = geo.model.mesh.nodes();
    // Two targets: a labelled target node, and a point inside a tet (interpolated).
    let tet0 = geo.model.mesh.tets()[geo.model.mesh.tets().len() / 2];
    let inside = [0, 1, 2].map(|a| tet0.iter().map(|&n| x[n as usize][a]).sum::<f64>() / 4.0);
    let first = geo.targets.first().map_or(x[0], |&n| x[n as usize]);
    let targets = vec![
        Target {
            name: "tumour".into(),
            image_mm: first,
        },
        Target {
            name: "inside".into(),
            image_mm: inside,
        },
    ];
    let mesh = TetMesh::new(x.to_vec(), geo.model.mesh.tets().to_vec()).unwrap();
    let surface_nodes = mesh.boundary().unwrap().nodes;
    let loc = TetLocator::new(&mesh);
    let embedded: Vec<([u32; 4], [f64; 4], [f64; 3])> = targets
        .iter()
        .map(|t| {
            let (k, w) = loc.weights(t.image_mm).unwrap();
            (loc.tet(k), w, t.image_mm)
        })
        .collect();

    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    tokio::spawn(bridge::serve(
        listener,
        BridgeConfig {
            targets: targets.clone(),
            ..bridge_config(&running, &case, pb::Method::Libr)
        },
    ));
    let mut igtl = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    let start = pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(pb::stream_register_request::Msg::Start(pb::SessionStart {
            case_id: case.clone(),
            method: pb::Method::Libr as i32,
            options: Some(pb::RegisterOptions {
                time_budget_ms: BUDGET_MS,
                ..Default::default()
            }),
            ..Default::default()
        })),
    };
    let mut reference = open_stream(&mut grpc, start).await.unwrap();

    // Surface points, RAS float32 on the wire; the reference gets the same values in LPS.
    let m = &sc.measurements;
    let surf: Vec<[f64; 3]> = (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .map(|i| m.points[i])
        .collect();
    let batches: Vec<Vec<[f32; 3]>> = surf
        .chunks(60)
        .map(|c| c.iter().map(|&p| ras(p).map(|v| v as f32)).collect())
        .collect();
    let mut seq = 1;
    let mut worst_all = [0.0f64; 3];
    let mut expected_updates = Vec::new();
    let mut last_polydata = Vec::new();
    let mut last_expected = None;
    for (k, b) in batches.iter().enumerate() {
        igtl.write_all(&point_message(b, k)).await.unwrap();
        let answer = read_until(&mut igtl, "POLYDATA").await;
        seq += 1;
        let u = reference
            .send(pb::StreamRegisterRequest {
                client_seq: seq,
                msg: Some(pb::stream_register_request::Msg::Surface(
                    pb::SurfaceBatch {
                        acquired_at: Some(prost_types::Timestamp {
                            seconds: 1000 + k as i64,
                            nanos: 0,
                        }),
                        xyz_mm: b.iter().flat_map(|p| ras(p.map(f64::from))).collect(),
                        feature: Vec::new(),
                    },
                )),
            })
            .await
            .unwrap();
        let Some(pb::stream_update::Update::Registration(r)) = u.update else {
            panic!("reference: {u:?}")
        };
        let e = expected(&r, &geo, &surface_nodes, &embedded);
        let d = check(&answer, &e);
        for i in 0..3 {
            worst_all[i] = worst_all[i].max(d[i]);
        }
        last_polydata = answer.last().unwrap().2.clone();
        expected_updates.push(serde_json::json!({
            "transform": e.transform,
            "targets": e.targets,
        }));
        last_expected = Some(e);
    }
    eprintln!(
        "igtl: {} surface updates; worst transform translation {:.2e} mm, target {:.2e} mm, liver point {:.2e} mm",
        batches.len(),
        worst_all[0],
        worst_all[1],
        worst_all[2]
    );
    assert!(
        worst_all.iter().all(|&d| d <= 1e-4),
        "bridge vs gRPC: {worst_all:?} mm"
    );

    // An ultrasound plane: its pose as TRANSFORM "US" (RAS), its contour point as POLYDATA "US"
    // at (u, v) = (0, 0) with kind 0.
    let (ci, _) = (0..m.points.len())
        .map(|i| (i, m.kind[i]))
        .find(|&(_, k)| k == MeasuredKind::PosteriorContour)
        .expect("a contour point in surface+1us");
    let pose_ras = Transform {
        matrix: [
            [-1.0, 0.0, 0.0, f64::from(ras(m.points[ci])[0] as f32)],
            [0.0, -1.0, 0.0, f64::from(ras(m.points[ci])[1] as f32)],
            [0.0, 0.0, 1.0, f64::from(ras(m.points[ci])[2] as f32)],
            [0.0, 0.0, 0.0, 1.0],
        ],
    };
    let opts = EncodeOptions {
        timestamp: wire::timestamp_from_secs(2000.0),
        ..EncodeOptions::default()
    };
    igtl.write_all(&Message::Transform(pose_ras).encode("US", &opts).unwrap())
        .await
        .unwrap();
    let plane = PolyData {
        points: vec![[0.0, 0.0, 0.0]],
        attributes: vec![PolyAttribute {
            name: "kind".into(),
            location: AttributeLocation::Point,
            kind: AttributeKind::Scalar { components: 1 },
            data: vec![0.0],
        }],
        ..PolyData::default()
    };
    igtl.write_all(&Message::PolyData(plane).encode("US", &opts).unwrap())
        .await
        .unwrap();
    let answer = read_until(&mut igtl, "POLYDATA").await;
    seq += 1;
    let t_lps = ras([0, 1, 2].map(|a| pose_ras.matrix[a][3]));
    let u = reference
        .send(pb::StreamRegisterRequest {
            client_seq: seq,
            msg: Some(pb::stream_register_request::Msg::Ultrasound(
                pb::UltrasoundPlane {
                    acquired_at: Some(prost_types::Timestamp {
                        seconds: 2000,
                        nanos: 0,
                    }),
                    plane_to_physical: Some(pb::Rigid {
                        rotation: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                        translation_mm: t_lps.to_vec(),
                    }),
                    contour_uv_mm: vec![0.0, 0.0],
                    vessel_uv_mm: Vec::new(),
                },
            )),
        })
        .await
        .unwrap();
    let Some(pb::stream_update::Update::Registration(r)) = u.update else {
        panic!("reference: {u:?}")
    };
    let d = check(&answer, &expected(&r, &geo, &surface_nodes, &embedded));
    eprintln!("igtl: ultrasound plane update; worst {d:?} mm");
    assert!(d.iter().all(|&x| x <= 1e-4), "{d:?}");

    // Malformed messages: each answered with a STATUS, and the connection goes on.
    let mut bad_crc = point_message(&batches[0][..3], 2500);
    let last = bad_crc.len() - 1;
    bad_crc[last] ^= 0x5a;
    let mut short = Message::Unknown {
        type_name: "POINT".into(),
        body: vec![0u8; 100],
    }
    .encode("Stylus", &EncodeOptions::default())
    .unwrap();
    // A POINT body of 100 bytes (not a multiple of 136), its CRC right.
    assert_eq!(&short[2..7], b"POINT");
    let unknown = Message::Unknown {
        type_name: "IMAGE".into(),
        body: vec![1, 2, 3, 4],
    }
    .encode("Camera", &EncodeOptions::default())
    .unwrap();
    for (bytes, code, what) in [
        (bad_crc, status_code::CHECKSUM_ERROR, "bad CRC"),
        (
            std::mem::take(&mut short),
            status_code::CONFIG_ERROR,
            "wrong size",
        ),
        (unknown, status_code::ILLEGAL_INSTRUCTION, "unknown type"),
    ] {
        igtl.write_all(&bytes).await.unwrap();
        let raw = read_raw(&mut igtl).await;
        let (h, msg) = wire::decode_message(&raw).unwrap();
        let Message::Status(s) = msg else {
            panic!("{what}: a {} instead of STATUS", h.type_name)
        };
        eprintln!(
            "igtl: {what} → STATUS {} {:?}: {}",
            s.code, s.error_name, s.message
        );
        assert_eq!(s.code, code, "{what}: {}", s.message);
        assert_eq!(h.device_name, bridge::DEVICE_STATUS);
    }
    // Still serving: a valid POINT gets its answer.
    igtl.write_all(&point_message(&batches[0], 3000))
        .await
        .unwrap();
    let answer = read_until(&mut igtl, "POLYDATA").await;
    assert!(answer.iter().any(|(h, _, _)| h.type_name == "TRANSFORM"));

    // Independent peers (CI): pyigtl streams the same batches over a new connection; a POLYDATA
    // decoder written from the specification reads the last liver message.
    let Some(py) = std::env::var_os("LIBRPLUS_CHECK_PYTHON") else {
        use std::io::Write;
        let _ = writeln!(
            std::io::stderr(),
            "SKIPPED server: the pyigtl and POLYDATA checks of the OpenIGTLink bridge (LIBRPLUS_CHECK_PYTHON not set; .ci/run sets it)"
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let e = last_expected.unwrap();
    std::fs::write(dir.path().join("liver.bin"), &last_polydata).unwrap();
    std::fs::write(
        dir.path().join("liver.json"),
        serde_json::json!({
            "device": bridge::DEVICE_LIVER,
            "points": e.surface,
            "triangles": mesh.boundary().unwrap().triangles.iter().map(|t| {
                t.map(|n| surface_nodes.binary_search(&n).unwrap() as u32)
            }).collect::<Vec<_>>(),
            "displacement": e.displacement,
            "uncertainty_mm": e.uncertainty,
        })
        .to_string(),
    )
    .unwrap();
    let mut c = std::process::Command::new(&py);
    c.arg(root.join("tests/reference/igtl_polydata.py"))
        .arg(dir.path().join("liver.bin"))
        .arg(dir.path().join("liver.json"));
    eprintln!("{}", run_cmd(c).await);

    let input = dir.path().join("batches.json");
    std::fs::write(
        &input,
        serde_json::json!({ "batches": batches }).to_string(),
    )
    .unwrap();
    let output = dir.path().join("peer.json");
    let mut c = std::process::Command::new(&py);
    c.arg(root.join("tests/reference/igtl_peer.py"))
        .arg(port.to_string())
        .arg(&input)
        .arg(&output);
    eprintln!("{}", run_cmd(c).await);
    let got: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&output).unwrap()).unwrap();
    let got = got["updates"].as_array().unwrap();
    assert_eq!(got.len(), expected_updates.len());
    let num = |v: &serde_json::Value| v.as_f64().unwrap();
    let (mut dt, mut dp) = (0.0f64, 0.0f64);
    for (g, w) in got.iter().zip(&expected_updates) {
        for i in 0..3 {
            for j in 0..3 {
                let d = num(&g["transform"][i][j]) - num(&w["transform"][i][j]);
                assert!(d.abs() < 1e-6, "pyigtl R[{i}][{j}] off by {d}");
            }
            dt = dt.max((num(&g["transform"][i][3]) - num(&w["transform"][i][3])).abs());
        }
        let (gt, wt) = (
            g["targets"].as_array().unwrap(),
            w["targets"].as_array().unwrap(),
        );
        assert_eq!(gt.len(), wt.len());
        for (a, b) in gt.iter().zip(wt) {
            for k in 0..3 {
                dp = dp.max((num(&a[k]) - num(&b[k])).abs());
            }
        }
    }
    eprintln!(
        "igtl: pyigtl peer, {} updates: worst transform translation {dt:.2e} mm, target {dp:.2e} mm against the gRPC answers",
        got.len()
    );
    assert!(dt <= 1e-4 && dp <= 1e-4, "pyigtl: {dt} {dp}");
}

/// The next message from the bridge (None: the end of the stream); panics after `within`.
async fn next_message(s: &mut TcpStream, within: Duration) -> Option<(wire::Header, Message)> {
    use std::io::ErrorKind;
    tokio::time::timeout(within, async {
        let mut raw = vec![0u8; wire::HEADER_SIZE];
        match s.read_exact(&mut raw).await {
            Ok(_) => {}
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::UnexpectedEof | ErrorKind::ConnectionReset
                ) =>
            {
                return None;
            }
            Err(e) => panic!("reading the bridge: {e}"),
        }
        let size = u64::from_be_bytes(raw[42..50].try_into().unwrap()) as usize;
        let mut body = vec![0u8; size];
        s.read_exact(&mut body).await.unwrap();
        raw.extend(body);
        Some(wire::decode_message(&raw).unwrap())
    })
    .await
    .unwrap_or_else(|_| panic!("nothing from the bridge within {within:?}"))
}

/// The STATUS the bridge sends before closing a connection, then the end of the stream.
async fn status_then_end(s: &mut TcpStream, within: Duration, what: &str) -> wire::Status {
    let (h, m) = next_message(s, within)
        .await
        .unwrap_or_else(|| panic!("{what}: closed without a STATUS"));
    let Message::Status(st) = m else {
        panic!("{what}: a {} instead of STATUS", h.type_name)
    };
    assert_eq!(h.device_name, bridge::DEVICE_STATUS);
    assert!(
        next_message(s, Duration::from_secs(10)).await.is_none(),
        "{what}: still open after its STATUS"
    );
    st
}

/// Idle OpenIGTLink sockets must not take the server's session slots (the bridge used to open
/// a gRPC session on every TCP connect): eight silent sockets to the bridge on a server of 8
/// sessions hold none (tenant B still registers over gRPC), one more is over the bridge's cap
/// and is answered STATUS 6 (busy) and closed, the silent ones are answered STATUS 7 (time-out)
/// and closed after the idle timeout, and a peer that sends a POINT gets its session and its
/// answer, and is closed when it falls silent in turn.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_sockets_hold_no_session_and_are_capped_and_timed_out() {
    const SESSIONS: usize = 8;
    let idle = Duration::from_secs(3);
    let (running, mut grpc) = server(SESSIONS).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+1us");
    let m = &sc.measurements;
    let surface: Vec<[f64; 3]> = (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .map(|i| m.points[i])
        .take(60)
        .collect();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let port = listener.local_addr().unwrap().port();
    // The bridge's cap as large as the server's total (an operator's slip): only opening the
    // session on the first data message keeps the server's slots free of silent sockets.
    tokio::spawn(bridge::serve(
        listener,
        BridgeConfig {
            max_sessions: SESSIONS,
            idle_timeout: idle,
            session_idle_timeout: idle,
            ..bridge_config(&running, &case, pb::Method::Rigid)
        },
    ));
    let t0 = std::time::Instant::now();
    let mut silent = Vec::new();
    for _ in 0..SESSIONS {
        silent.push(TcpStream::connect(("127.0.0.1", port)).await.unwrap());
    }
    // One more: its STATUS comes once the bridge has taken the eight before it (checked after
    // tenant B's turn; before the fix no STATUS came to it, and B was refused).
    let mut over = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    let over_first = tokio::time::timeout(
        Duration::from_secs(20),
        next_message(&mut over, Duration::from_secs(30)),
    )
    .await
    .ok()
    .flatten();

    // Tenant B, over gRPC, while the eight silent sockets are connected to the bridge.
    let start = pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(pb::stream_register_request::Msg::Start(pb::SessionStart {
            case_id: case.clone(),
            method: pb::Method::Rigid as i32,
            options: Some(pb::RegisterOptions {
                time_budget_ms: BUDGET_MS,
                ..Default::default()
            }),
            ..Default::default()
        })),
    };
    let mut b = open_stream(&mut grpc, start).await.unwrap();
    let answer = b
        .send(pb::StreamRegisterRequest {
            client_seq: 2,
            msg: Some(pb::stream_register_request::Msg::Surface(
                pb::SurfaceBatch {
                    acquired_at: None,
                    xyz_mm: surface.iter().flatten().copied().collect(),
                    feature: Vec::new(),
                },
            )),
        })
        .await
        .unwrap_or_else(|s| {
            panic!(
                "tenant B with {SESSIONS} silent OpenIGTLink sockets open: {:?}: {}",
                s.code(),
                s.message()
            )
        });
    assert!(
        matches!(
            answer.update,
            Some(pb::stream_update::Update::Registration(_))
        ),
        "tenant B: {answer:?}"
    );
    // The silent sockets were still connected while B registered (nothing to read, no end).
    for (k, s) in silent.iter().enumerate() {
        let e = s
            .try_read(&mut [0u8; 1])
            .expect_err("a silent socket already answered");
        assert_eq!(
            e.kind(),
            std::io::ErrorKind::WouldBlock,
            "silent socket {k}: {e}"
        );
    }
    eprintln!(
        "igtl: tenant B registered over gRPC {:.2} s after {SESSIONS} silent sockets connected (server max_sessions {SESSIONS})",
        t0.elapsed().as_secs_f64()
    );

    // Over the cap: busy, naming the option; then closed.
    let Some((h, Message::Status(busy))) = over_first else {
        panic!(
            "no STATUS for the connection over the cap (got: {:?})",
            over_first.as_ref().map(|(h, _)| &h.type_name)
        )
    };
    eprintln!(
        "igtl: connection {} → STATUS {} {:?}: {}",
        SESSIONS + 1,
        busy.code,
        busy.error_name,
        busy.message
    );
    assert_eq!(h.device_name, bridge::DEVICE_STATUS);
    assert_eq!(busy.code, status_code::BUSY, "{}", busy.message);
    assert!(busy.message.contains("--max-sessions"), "{}", busy.message);
    assert!(
        next_message(&mut over, Duration::from_secs(10))
            .await
            .is_none(),
        "the connection over the cap is still open after its STATUS"
    );

    // The silent sockets: time-out, naming the option, after the idle timeout; then closed.
    for (k, s) in silent.iter_mut().enumerate() {
        let st = status_then_end(s, idle + Duration::from_secs(30), "a silent socket").await;
        let after = t0.elapsed();
        if k == 0 {
            eprintln!(
                "igtl: silent socket closed after {:.2} s (idle timeout {:.0} s): STATUS {} {:?}: {}",
                after.as_secs_f64(),
                idle.as_secs_f64(),
                st.code,
                st.error_name,
                st.message
            );
        }
        assert_eq!(st.code, status_code::TIME_OUT, "{}", st.message);
        assert!(st.message.contains("--idle-timeout-s"), "{}", st.message);
        assert!(after >= idle, "silent socket {k} closed after {after:?}");
    }

    // A peer that sends data: its session opens and it gets its answer; falling silent, it is
    // closed in turn (--session-idle-timeout-s).
    let mut peer = TcpStream::connect(("127.0.0.1", port)).await.unwrap();
    let points: Vec<[f32; 3]> = surface.iter().map(|&p| ras(p).map(|v| v as f32)).collect();
    peer.write_all(&point_message(&points, 0)).await.unwrap();
    let answer = read_until(&mut peer, "POLYDATA").await;
    assert!(
        answer.iter().any(
            |(h, _, _)| h.type_name == "TRANSFORM" && h.device_name == bridge::DEVICE_TRANSFORM
        ),
        "no TRANSFORM in the answer"
    );
    let answered = std::time::Instant::now();
    let st = status_then_end(
        &mut peer,
        idle + Duration::from_secs(30),
        "a peer gone silent",
    )
    .await;
    assert_eq!(st.code, status_code::TIME_OUT, "{}", st.message);
    assert!(
        st.message.contains("--session-idle-timeout-s"),
        "{}",
        st.message
    );
    assert!(answered.elapsed() >= idle - Duration::from_millis(50));
    eprintln!(
        "igtl: a peer silent after its answer closed after {:.2} s: {}",
        answered.elapsed().as_secs_f64(),
        st.message
    );
}

/// The first 60 surface points of the scenario "surface+1us" (RAS, float32, as a peer sends
/// them).
fn some_surface_points() -> Vec<[f32; 3]> {
    let (_, sc) = scenario("surface+1us");
    let m = &sc.measurements;
    (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .take(60)
        .map(|i| ras(m.points[i]).map(|v| v as f32))
        .collect()
}

/// A header whose BODY_SIZE no message has (2^64 − 1) is answered with a STATUS naming it and
/// the connection is closed: before, the bridge set out to discard 2^64 bytes and every later
/// message was lost without an answer. A body over `--max-body` of a size a message may have
/// is still discarded and the next message answered. Against the bridge process, so that
/// `LIBRPLUS_SERVER_BIN` can show the test failing on an older build.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_body_size_that_cannot_be_trusted_closes_the_connection() {
    let p = Proc::start(&[]);
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let bridge = Bridge::start(
        &p.url(),
        &case,
        &["--method", "rigid", "--max-body", "1048576"],
    );
    let points = some_surface_points();

    // 2 MiB of IMAGE over a 1 MiB limit: discarded, and the POINT after it answered.
    let mut s = bridge.connect().await;
    let image = Message::Unknown {
        type_name: "IMAGE".into(),
        body: vec![0; 2 << 20],
    }
    .encode("Camera", &EncodeOptions::default())
    .unwrap();
    s.write_all(&image).await.unwrap();
    s.write_all(&point_message(&points, 0)).await.unwrap();
    let Some((_, Message::Status(st))) = next_message(&mut s, Duration::from_secs(60)).await else {
        panic!("no STATUS for a body over --max-body")
    };
    eprintln!("igtl: 2 MiB body → STATUS {} {}", st.code, st.message);
    assert!(st.message.contains("body discarded"), "{}", st.message);
    let answer = read_until(&mut s, "POLYDATA").await;
    assert!(answer.iter().any(|(h, _, _)| h.type_name == "TRANSFORM"));

    // BODY_SIZE 2^64 − 1, then a valid POINT: a STATUS naming the size, then the end.
    let mut s = bridge.connect().await;
    let mut header = point_message(&points, 1)[..wire::HEADER_SIZE].to_vec();
    header[42..50].copy_from_slice(&u64::MAX.to_be_bytes());
    s.write_all(&header).await.unwrap();
    s.write_all(&point_message(&points, 2)).await.unwrap();
    let Some((h, Message::Status(st))) = next_message(&mut s, Duration::from_secs(30)).await else {
        panic!("no STATUS for a BODY_SIZE of 2^64 − 1")
    };
    eprintln!(
        "igtl: BODY_SIZE 2^64 − 1 → STATUS {} {}",
        st.code, st.message
    );
    assert_eq!(h.device_name, bridge::DEVICE_STATUS);
    // Then the end of the stream (before: silence, the POINT after it swallowed).
    let end = tokio::time::timeout(Duration::from_secs(10), s.read(&mut [0u8; 1])).await;
    let closed = match &end {
        Ok(Ok(0)) => true,
        Ok(Err(e)) => e.kind() == std::io::ErrorKind::ConnectionReset,
        _ => false,
    };
    let log = bridge.log.lock().unwrap().clone();
    assert!(
        closed,
        "still open 10 s after its STATUS ({end:?}); bridge log: {log:?}"
    );
    assert_eq!(st.code, status_code::CONFIG_ERROR, "{}", st.message);
    for needle in [
        "BODY_SIZE 18446744073709551615",
        "cannot be trusted",
        "closed",
    ] {
        assert!(st.message.contains(needle), "{needle:?}: {}", st.message);
    }
}

/// A TRANSFORM of NaN is refused at the TRANSFORM, naming it (its rotation check let NaN
/// through, and the error came at the next POLYDATA from the gRPC server); the plane's next
/// POLYDATA is refused naming the refused pose, never placed with the pose before it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_transform_of_nan_is_refused_at_the_transform() {
    let p = Proc::start(&[]);
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let bridge = Bridge::start(&p.url(), &case, &["--method", "rigid"]);
    let mut s = bridge.connect().await;
    let opts = EncodeOptions::default();
    let pose = Message::Transform(Transform::IDENTITY)
        .encode("US", &opts)
        .unwrap();
    let mut nan = Transform::IDENTITY;
    for row in nan.matrix.iter_mut().take(3) {
        *row = [f64::NAN; 4];
    }
    s.write_all(&pose).await.unwrap();
    s.write_all(&Message::Transform(nan).encode("US", &opts).unwrap())
        .await
        .unwrap();
    let Some((h, Message::Status(st))) = next_message(&mut s, Duration::from_secs(20)).await else {
        panic!("no STATUS for a TRANSFORM of NaN")
    };
    eprintln!("igtl: TRANSFORM of NaN → STATUS {} {}", st.code, st.message);
    assert_eq!(h.device_name, bridge::DEVICE_STATUS);
    assert_eq!(st.code, status_code::CONFIG_ERROR, "{}", st.message);
    assert!(
        st.message
            .starts_with("TRANSFORM \"US\": matrix[0][0] is NaN"),
        "{}",
        st.message
    );
    let plane = PolyData {
        points: vec![[0.0, 0.0, 0.0]],
        ..PolyData::default()
    };
    s.write_all(&Message::PolyData(plane).encode("US", &opts).unwrap())
        .await
        .unwrap();
    let Some((_, Message::Status(st))) = next_message(&mut s, Duration::from_secs(20)).await else {
        panic!("no STATUS for a POLYDATA after a refused pose")
    };
    eprintln!("igtl: then POLYDATA → STATUS {} {}", st.code, st.message);
    assert_eq!(st.code, status_code::CONFIG_ERROR, "{}", st.message);
    assert!(
        st.message.starts_with(
            "POLYDATA \"US\": the last TRANSFORM \"US\" (the plane's pose) was refused"
        ),
        "{}",
        st.message
    );
}
