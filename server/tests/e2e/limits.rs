//! Admission control (sessions beyond the limit are refused with RESOURCE_EXHAUSTED), health, reflection and metrics.

use crate::common::*;

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
    for _ in 0..500 {
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
