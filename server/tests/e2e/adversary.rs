//! What an adversarial client found (issue 27, point 7), each against a real `librplus-server`
//! process on loopback (its memory measured from /proc): floods of silent connections, silent
//! streams, huge strings, huge and concurrent requests, bytes that are not protobuf, a burst
//! from one client beside another's small request, a 1 ms budget on 20,000 points, and an
//! ultrasound frame with no points as a session's only message.

use crate::common::*;

async fn connect(url: &str) -> LibRPlusClient<Channel> {
    let ch = tonic::transport::Endpoint::from_shared(url.to_string())
        .unwrap()
        .connect_timeout(Duration::from_secs(10))
        .connect()
        .await
        .unwrap();
    LibRPlusClient::new(ch)
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(128 << 20)
}

/// A real surgery's session: start, one surface batch; the first update's registration and
/// the seconds it took.
async fn real_session(url: &str) -> (pb::Registration, f64) {
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let mut c = connect(url).await;
    let t0 = std::time::Instant::now();
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let u = s.send(msgs[1].clone()).await.unwrap();
    let Some(pb::stream_update::Update::Registration(r)) = u.update else {
        panic!("expected a registration, got {u:?}");
    };
    (r, t0.elapsed().as_secs_f64())
}

async fn try_real_session(url: &str) -> Result<(pb::Registration, f64), String> {
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let t0 = std::time::Instant::now();
    let ch = tonic::transport::Endpoint::from_shared(url.to_string())
        .unwrap()
        .connect_timeout(Duration::from_secs(10))
        .connect()
        .await
        .map_err(|e| format!("connect: {e:?}"))?;
    let mut c = LibRPlusClient::new(ch);
    let mut s = open_stream(&mut c, msgs[0].clone())
        .await
        .map_err(|e| format!("open: {e:?}"))?;
    let u = s
        .send(msgs[1].clone())
        .await
        .map_err(|e| format!("send: {e:?}"))?;
    let Some(pb::stream_update::Update::Registration(r)) = u.update else {
        return Err(format!("expected a registration, got {u:?}"));
    };
    Ok((r, t0.elapsed().as_secs_f64()))
}

/// `n` points near the liver (the scenario's surface points, repeated).
fn points(n: usize) -> pb::Measurements {
    let (_, sc) = scenario("surface");
    let m = &sc.measurements;
    let idx: Vec<usize> = (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .collect();
    let pick = |k: usize| idx[k % idx.len()];
    pb::Measurements {
        xyz_mm: (0..n).flat_map(|k| m.points[pick(k)]).collect(),
        kind: vec![pb::PointKind::Surface as i32; n],
        feature: Vec::new(),
        initial_alignment: m.initial_alignment.as_ref().map(rigid_pb),
    }
}

fn open_files_limit() -> usize {
    std::fs::read_to_string("/proc/self/limits")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("Max open files"))
                .and_then(|l| l.split_whitespace().nth(3))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(1024)
}

/// Findings 7.1 and 7.2: silent TCP connections (as many as this process may open, up to
/// 20,000) and 8 streams that never start do not keep a real session out, nor grow the
/// server's memory without bound.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn floods_of_silent_connections_and_streams_leave_room_for_a_surgery() {
    let p = Proc::start(&["--time-budget-ms", "10000"]);
    let idle_rss = p.rss_mb();
    // Leaves a fifth of this process's open-file limit to the tests running beside it.
    let n = 20_000.min((open_files_limit() * 4 / 5).saturating_sub(200));
    if n < 20_000 {
        eprintln!(
            "open-files limit {}: {n} silent connections instead of 20,000",
            open_files_limit()
        );
    }
    let mut silent = Vec::with_capacity(n);
    let t0 = std::time::Instant::now();
    for _ in 0..n {
        match tokio::net::TcpStream::connect(&p.addr).await {
            Ok(s) => silent.push(s),
            Err(e) => panic!("connect {}: {e}", silent.len()),
        }
    }
    eprintln!(
        "{n} silent connections opened in {:.1} s; server RSS {:.0} MB (idle {idle_rss:.0} MB)",
        t0.elapsed().as_secs_f64(),
        p.rss_mb()
    );
    let mut tries = 0;
    let t1 = std::time::Instant::now();
    let (r, s) = loop {
        tries += 1;
        match try_real_session(&p.url()).await {
            Ok(x) => break x,
            Err(e) => {
                eprintln!("try {tries} at {:.2} s: {e}", t1.elapsed().as_secs_f64());
                if tries >= 3 {
                    let log = p.log.lock().unwrap();
                    for l in log.iter().rev().take(30) {
                        eprintln!("server: {l}");
                    }
                    panic!("no session after {tries} tries");
                }
                tokio::time::sleep(Duration::from_millis(300)).await;
            }
        }
    };
    eprintln!(
        "real session beside them: answered in {s:.2} s, quality {:?}, {tries} tries",
        r.quality()
    );
    // Health answers too.
    let ch = tonic::transport::Endpoint::from_shared(p.url())
        .unwrap()
        .connect()
        .await
        .unwrap();
    tonic_health::pb::health_client::HealthClient::new(ch)
        .check(tonic_health::pb::HealthCheckRequest::default())
        .await
        .unwrap();
    let flood_rss = p.rss_mb();
    drop(silent);
    // 8 streams that never send their start, beside 4 session slots.
    let mut c = connect(&p.url()).await;
    let mut streams = Vec::new();
    for _ in 0..8 {
        let (tx, rx) = tokio::sync::mpsc::channel::<pb::StreamRegisterRequest>(1);
        let s = c
            .stream_register(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap();
        streams.push((tx, s));
    }
    let (r, s) = real_session(&p.url()).await;
    eprintln!(
        "real session beside 8 silent streams: answered in {s:.2} s, quality {:?}; server RSS \
         {:.0} MB during the connection flood",
        r.quality(),
        flood_rss
    );
    assert!(flood_rss < idle_rss + 256.0, "RSS {flood_rss:.0} MB");
}

/// Findings 7.3, 7.4 and 7.7: a huge case id is refused without being echoed or logged whole;
/// requests are refused by their size before they are decoded (32 concurrent 8 MiB requests
/// do not raise the server's memory); 32 concurrent maximum-size requests are bounded; bytes
/// that are not protobuf are INVALID_ARGUMENT.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn huge_and_malformed_requests_are_refused_cheaply() {
    let p = Proc::start(&["--time-budget-ms", "10000"]);
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let mut c = connect(&p.url()).await;
    let idle_rss = p.rss_mb();
    // 16 MiB case id: over the request limit.
    let huge = "x".repeat(16 << 20);
    let e = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: huge.clone(),
            include_mesh: false,
        })
        .await
        .unwrap_err();
    eprintln!("16 MiB case_id: {:?} {}", e.code(), e.message());
    assert!(
        matches!(e.code(), Code::OutOfRange | Code::ResourceExhausted),
        "{e:?}"
    );
    assert!(e.message().len() < 1000);
    // 200 KB case id: under the limit; refused naming the field, not echoed.
    let e = c
        .describe_case(pb::DescribeCaseRequest {
            case_id: "y".repeat(200_000),
            include_mesh: false,
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().contains("case_id") && e.message().len() < 1000);
    let e = c
        .register(request(&"z".repeat(200_000), pb::Method::Rigid, points(10)))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().len() < 1000);
    // 32 concurrent 8 MiB requests (8 times the limit; 64 MiB each would take this test
    // process 4 GB to encode).
    let big = request(&case, pb::Method::Rigid, points((8 << 20) / 24));
    let t0 = std::time::Instant::now();
    let mut tasks = Vec::new();
    for _ in 0..32 {
        let mut c = connect(&p.url()).await;
        let req = big.clone();
        tasks.push(tokio::spawn(async move {
            c.register(req).await.err().map(|e| e.code())
        }));
    }
    let mut peak = 0.0f64;
    for t in tasks {
        let code = t.await.unwrap();
        assert!(
            matches!(code, Some(Code::OutOfRange | Code::ResourceExhausted)),
            "{code:?}"
        );
        peak = peak.max(p.rss_mb());
    }
    eprintln!(
        "32 concurrent 8 MiB requests refused in {:.1} s; server RSS peak {peak:.0} MB (idle {idle_rss:.0})",
        t0.elapsed().as_secs_f64()
    );
    assert!(peak < idle_rss + 256.0, "RSS {peak:.0} MB");
    // 32 concurrent maximum-size requests (20,000 points each), each from its own connection:
    // answered or refused by the queue, and a real session beside them is answered.
    let max = request(&case, pb::Method::Rigid, points(20_000));
    let mut tasks = Vec::new();
    for _ in 0..32 {
        let mut c = connect(&p.url()).await;
        let req = max.clone();
        tasks.push(tokio::spawn(async move {
            c.register(req).await.err().map(|e| e.code())
        }));
    }
    let (r, s) = real_session(&p.url()).await;
    let mut peak = p.rss_mb();
    let (mut ok, mut refused) = (0, 0);
    for t in tasks {
        match t.await.unwrap() {
            None => ok += 1,
            Some(Code::ResourceExhausted) => refused += 1,
            Some(c) => panic!("{c:?}"),
        }
        peak = peak.max(p.rss_mb());
    }
    eprintln!(
        "32 concurrent 20,000-point requests: {ok} answered, {refused} refused (queue); a real \
         session beside them answered in {s:.2} s ({:?}); server RSS peak {peak:.0} MB",
        r.quality()
    );
    assert!(peak < idle_rss + 512.0, "RSS {peak:.0} MB");
    // Bytes that are not protobuf: INVALID_ARGUMENT, not INTERNAL.
    let e = raw_register(&p.url(), vec![0xff; 64]).await;
    eprintln!("undecodable request: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    let longest = p.longest_log_line();
    eprintln!("longest server log line: {longest} bytes");
    assert!(longest < 4096, "a log line of {longest} bytes");
}

/// Finding 7.6: a 1 ms budget on 20,000 points is answered and says it is over budget; a burst
/// of requests from one client does not crowd out another client's small request.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn budgets_are_kept_or_explained_and_clients_are_served_fairly() {
    let p = Proc::start(&["--compute-slots", "1"]);
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let mut c = connect(&p.url()).await;
    let mut req = request(&case, pb::Method::Rigid, points(20_000));
    req.options = Some(pb::RegisterOptions {
        time_budget_ms: 1,
        ..Default::default()
    });
    let t0 = std::time::Instant::now();
    let r = c.register(req).await.unwrap().into_inner();
    eprintln!(
        "1 ms budget, 20,000 points: {:.0} ms, {:?}: {}",
        t0.elapsed().as_secs_f64() * 1e3,
        r.quality(),
        r.quality_reason
    );
    // The rigid stage stops at the deadline: the answer is about the start, flagged DEGRADED,
    // or LIKELY_FAILED when the error estimate reads the start as far off; either way the
    // reason names the budget.
    assert!(
        matches!(
            r.quality(),
            pb::Quality::Degraded | pb::Quality::LikelyFailed
        ),
        "{:?}: {}",
        r.quality(),
        r.quality_reason
    );
    assert!(
        r.quality_reason.contains("time budget"),
        "{}",
        r.quality_reason
    );
    // A burst of 12 large requests on one connection, then another client's small one.
    let big = request(&case, pb::Method::Rigid, points(20_000));
    let mut tasks = Vec::new();
    for _ in 0..12 {
        let mut c = c.clone();
        let req = big.clone();
        tasks.push(tokio::spawn(async move { c.register(req).await.err() }));
    }
    tokio::time::sleep(Duration::from_millis(50)).await;
    let mut other = connect(&p.url()).await;
    let small = other
        .register(request(&case, pb::Method::Rigid, points(50)))
        .await;
    assert!(small.is_ok(), "the other client's request: {small:?}");
    let mut refused = 0;
    for t in tasks {
        if let Some(e) = t.await.unwrap() {
            assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
            refused += 1;
        }
    }
    eprintln!(
        "burst of 12 from one client: {refused} refused (per-client limit); the other client answered"
    );
    assert!(refused > 0);
}

/// Finding 7.7: an ultrasound frame with no points as a session's only message is answered
/// (the starting pose, flagged), as the proto says.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_empty_ultrasound_frame_is_answered() {
    let (running, mut c) = server(2).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let u = s
        .send(pb::StreamRegisterRequest {
            client_seq: 2,
            msg: Some(pb::stream_register_request::Msg::Ultrasound(
                pb::UltrasoundPlane {
                    acquired_at: None,
                    plane_to_physical: Some(rigid_pb(&librplus::mesh::rigid::Rigid::identity())),
                    contour_uv_mm: vec![],
                    vessel_uv_mm: vec![],
                },
            )),
        })
        .await
        .unwrap();
    let Some(pb::stream_update::Update::Registration(r)) = u.update else {
        panic!("expected a registration, got {u:?}");
    };
    assert_eq!(r.quality(), pb::Quality::Degenerate);
    assert_eq!(r.points_used, 0);
    let want = rigid_pb(&sc.measurements.initial_alignment.unwrap_or_default());
    assert_eq!(r.image_to_physical, Some(want));
    // Then points come, and the session goes on.
    let mut next = msgs[1].clone();
    next.client_seq = 3;
    let u = s.send(next).await.unwrap();
    assert!(matches!(
        u.update,
        Some(pb::stream_update::Update::Registration(_))
    ));
    drop(s);
    running.shutdown().await;
}

/// Register with a raw body (bytes sent as the message).
async fn raw_register(url: &str, body: Vec<u8>) -> tonic::Status {
    use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};
    #[derive(Default)]
    struct Raw;
    struct Enc;
    struct Dec;
    impl Encoder for Enc {
        type Item = Vec<u8>;
        type Error = tonic::Status;
        fn encode(&mut self, item: Vec<u8>, buf: &mut EncodeBuf<'_>) -> Result<(), tonic::Status> {
            use bytes::BufMut;
            buf.put_slice(&item);
            Ok(())
        }
    }
    impl Decoder for Dec {
        type Item = Vec<u8>;
        type Error = tonic::Status;
        fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<Vec<u8>>, tonic::Status> {
            use bytes::Buf;
            let mut v = vec![0; buf.remaining()];
            buf.copy_to_slice(&mut v);
            Ok(Some(v))
        }
    }
    impl Codec for Raw {
        type Encode = Vec<u8>;
        type Decode = Vec<u8>;
        type Encoder = Enc;
        type Decoder = Dec;
        fn encoder(&mut self) -> Enc {
            Enc
        }
        fn decoder(&mut self) -> Dec {
            Dec
        }
    }
    let ch = tonic::transport::Endpoint::from_shared(url.to_string())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut g = tonic::client::Grpc::new(ch);
    g.ready().await.unwrap();
    g.unary(
        tonic::Request::new(body),
        "/librplus.v1.LibRPlus/Register".parse().unwrap(),
        Raw,
    )
    .await
    .unwrap_err()
}
