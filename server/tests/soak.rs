//! A soak on loopback, in a test binary of its own so that no other test shares the machine
//! while it measures: a `librplus-server` process with an auth file and a case store serves
//! tenant A's normal work (unary registrations, a streamed session, an upload) on an idle
//! server, then again while tenant B and a peer without credentials do their worst at once:
//! 500 idle HTTP/2 connections kept open (reopened as the server closes them), 8 sessions with
//! a start and no data, and an upload trickled at a byte a second. Tenant A must see no error,
//! and its p99 latency must stay within 2 × the idle server's. Bounded: 500 connections, 8
//! sessions, tenant A's work for two rounds idle and at least 25 s under load, 240 s in all.

#[path = "e2e/common/mod.rs"]
mod common;

use common::*;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Instant;

const TOKEN_A: &str = "token-tenant-a";
const TOKEN_B: &str = "token-tenant-b";

/// Tenant A's work, once: a streamed session of the "surface" scenario (every batch), 12 unary
/// registrations, then an upload of the dataset's mesh as `upload_id` (until it is READY, then
/// deleted). The
/// latency of each update and registration, s, and the errors.
async fn tenant_a(addr: std::net::SocketAddr, upload_id: &str) -> (Vec<f64>, Vec<String>) {
    let mut c = client(addr).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let (mut lat, mut errors) = (Vec::new(), Vec::new());
    match open_stream_as(&mut c, msgs[0].clone(), TOKEN_A).await {
        Err(e) => errors.push(format!("stream: {e:?}")),
        Ok(mut s) => {
            for m in &msgs[1..] {
                let t = Instant::now();
                match s.send(m.clone()).await {
                    Ok(u) => match u.update {
                        Some(pb::stream_update::Update::Registration(_)) => {
                            lat.push(t.elapsed().as_secs_f64())
                        }
                        other => errors.push(format!("update {}: {other:?}", m.client_seq)),
                    },
                    Err(e) => {
                        errors.push(format!("update {}: {e:?}", m.client_seq));
                        break;
                    }
                }
            }
        }
    }
    for k in 0..12 {
        let t = Instant::now();
        let method = if k % 2 == 0 {
            pb::Method::Libr
        } else {
            pb::Method::Rigid
        };
        let r = c
            .register(bearer(
                request(&case, method, measurements_pb(&sc.measurements)),
                TOKEN_A,
            ))
            .await;
        match r {
            Ok(_) => lat.push(t.elapsed().as_secs_f64()),
            Err(e) => errors.push(format!("register {k}: {e:?}")),
        }
    }
    match c
        .create_case(bearer(tokio_stream::iter(mesh_upload(upload_id)), TOKEN_A))
        .await
    {
        Err(e) => errors.push(format!("upload: {e:?}")),
        Ok(_) => {
            let mut w = c
                .watch_case(bearer(
                    pb::WatchCaseRequest {
                        case_id: upload_id.into(),
                    },
                    TOKEN_A,
                ))
                .await
                .unwrap()
                .into_inner();
            let mut last = None;
            while let Ok(Some(st)) = w.message().await {
                last = Some(st.state());
            }
            if last != Some(pb::CaseState::Ready) {
                errors.push(format!("upload {upload_id}: ended {last:?}"));
            }
            // Done with it (a tenant's stored cases are bounded).
            let deleted = c
                .delete_case(bearer(
                    pb::DeleteCaseRequest {
                        case_id: upload_id.into(),
                    },
                    TOKEN_A,
                ))
                .await;
            if let Err(e) = deleted {
                errors.push(format!("delete {upload_id}: {e:?}"));
            }
        }
    }
    (lat, errors)
}

fn p99(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[((v.len() as f64 * 0.99).ceil() as usize).clamp(1, v.len()) - 1]
}

fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Keeps `n` idle HTTP/2 connections open (20 from each of 127.0.0.2, .3, …), reopening the
/// ones the server closes, until `stop`; how many it opened in all.
async fn keep_idle(addr: std::net::SocketAddr, n: usize, stop: Arc<AtomicBool>) -> usize {
    let mut held: Vec<Option<tokio::task::JoinHandle<()>>> = (0..n).map(|_| None).collect();
    let mut opened = 0;
    while !stop.load(Ordering::Relaxed) {
        for (k, h) in held.iter_mut().enumerate() {
            if h.as_ref().is_none_or(|h| h.is_finished()) {
                let ip = std::net::Ipv4Addr::new(127, 0, 0, 2 + (k / 20) as u8);
                *h = idle_h2(ip, addr).await;
                opened += 1;
            }
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    opened
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_tenant_is_served_while_another_and_a_peer_without_credentials_do_their_worst() {
    let run = async {
        let dir = tempfile::tempdir().unwrap();
        let auth = auth_file(
            dir.path(),
            &[
                ("tenant-a", TOKEN_A, &["*"], &["register", "manage"]),
                ("tenant-b", TOKEN_B, &["*"], &["register", "manage"]),
            ],
        );
        let store = dir.path().join("store").display().to_string();
        let p = Proc::start(&[
            "--auth",
            auth.to_str().unwrap(),
            "--case-store",
            &store,
            "--max-sessions",
            "8",
            "--time-budget-ms",
            "10000",
        ]);
        let addr: std::net::SocketAddr = p.addr.parse().unwrap();
        // Warm-up (first-call costs), then the idle server's figures.
        let _ = tenant_a(addr, "a/warm-up").await;
        let (mut idle, idle_errors) = tenant_a(addr, "a/idle-0").await;
        let (more, more_errors) = tenant_a(addr, "a/idle-1").await;
        idle.extend(more);
        assert!(
            idle_errors.is_empty() && more_errors.is_empty(),
            "{idle_errors:?} {more_errors:?}"
        );
        // The hostile load, all at once.
        let stop = Arc::new(AtomicBool::new(false));
        let flood = tokio::spawn(keep_idle(addr, 500, stop.clone()));
        let mut b = client(addr).await;
        let mut b_sessions = Vec::new();
        let case = open(dataset()).unwrap().deformations[0].geometry.clone();
        let (_, sc) = scenario("surface");
        let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
        for _ in 0..8 {
            if let Ok(s) = open_stream_as(&mut b, msgs[0].clone(), TOKEN_B).await {
                b_sessions.push(s);
            }
        }
        let trickled = Arc::new(AtomicUsize::new(0));
        let trickler = {
            let (stop, trickled, mut b) = (stop.clone(), trickled.clone(), b.clone());
            tokio::spawn(async move {
                while !stop.load(Ordering::Relaxed) {
                    let n = trickled.fetch_add(1, Ordering::Relaxed);
                    let _ = b
                        .create_case(bearer(trickle(&format!("b/slow-{n}"), 120), TOKEN_B))
                        .await;
                }
            })
        };
        tokio::time::sleep(Duration::from_secs(3)).await;
        // Tenant B's sessions the server holds (the others were refused at its quota).
        let mut b_held = 0;
        for s in &mut b_sessions {
            if tokio::time::timeout(Duration::from_millis(50), s.rx.message())
                .await
                .is_err()
            {
                b_held += 1;
            }
        }
        // Tenant A's work for at least 25 s under the load: past the connections' idle
        // timeout and the trickle's minimum rate, so that the server closes them meanwhile.
        let t_busy = Instant::now();
        let (mut busy, mut busy_errors) = (Vec::new(), Vec::new());
        let mut rounds = 0;
        while rounds < 2 || t_busy.elapsed() < Duration::from_secs(25) {
            let (l, e) = tenant_a(addr, &format!("a/busy-{rounds}")).await;
            busy.extend(l);
            busy_errors.extend(e);
            rounds += 1;
        }
        stop.store(true, Ordering::Relaxed);
        let opened = flood.await.unwrap();
        trickler.abort();
        eprintln!(
            "tenant A, idle server: {} samples, median {:.3} s, p99 {:.3} s",
            idle.len(),
            median(&idle),
            p99(&idle)
        );
        eprintln!(
            "tenant A, {rounds} rounds in {:.0} s beside 500 idle connections ({opened} opened \
             in all), {b_held} of tenant B's 8 sessions without data held and {} trickled \
             uploads: {} samples, median {:.3} s, p99 {:.3} s, {} errors",
            t_busy.elapsed().as_secs_f64(),
            trickled.load(Ordering::Relaxed),
            busy.len(),
            median(&busy),
            p99(&busy),
            busy_errors.len()
        );
        assert!(busy_errors.is_empty(), "{busy_errors:?}");
        assert_eq!(busy.len(), rounds * idle.len() / 2);
        assert!(
            p99(&busy) <= 2.0 * p99(&idle),
            "p99 {:.3} s against {:.3} s idle",
            p99(&busy),
            p99(&idle)
        );
    };
    tokio::time::timeout(Duration::from_secs(240), run)
        .await
        .expect("the soak ends within 240 s");
}
