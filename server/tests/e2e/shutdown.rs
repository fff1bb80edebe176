//! Shutdown with streams in flight: in the library (`Running::shutdown`) and in the binary on SIGTERM.

use crate::common::*;

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
