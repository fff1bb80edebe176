//! The audit log and sessions that survive: a lost stream and a server restart resume from the
//! recorded messages, and the next update equals the uninterrupted session's; `kill -9` of the
//! server in the middle of 8 streaming sessions, 20 times: every acknowledged registration is in
//! the audit log, every session resumes and ends with the uninterrupted run's answers.

use crate::common::*;
use librplus_server::audit;
use prost::Message;

fn resume_start(id: &str) -> pb::StreamRegisterRequest {
    pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(pb::stream_register_request::Msg::Start(pb::SessionStart {
            resume_session_id: id.into(),
            ..Default::default()
        })),
    }
}

fn registration(u: &pb::StreamUpdate) -> &pb::Registration {
    match &u.update {
        Some(pb::stream_update::Update::Registration(r)) => r,
        other => panic!("expected a registration, got {other:?}"),
    }
}

/// Largest difference of two registrations (transform entries and displacements).
fn diff(a: &pb::Registration, b: &pb::Registration) -> f64 {
    let (ta, tb) = (
        a.image_to_physical.as_ref().unwrap(),
        b.image_to_physical.as_ref().unwrap(),
    );
    ta.rotation
        .iter()
        .zip(&tb.rotation)
        .chain(ta.translation_mm.iter().zip(&tb.translation_mm))
        .map(|(x, y)| (x - y).abs())
        .chain(
            a.displacement_mm
                .iter()
                .zip(&b.displacement_mm)
                .map(|(x, y)| (x - y).abs() as f64),
        )
        .fold(0.0, f64::max)
}

/// The answers of an uninterrupted session over `msgs`, by client_seq.
async fn uninterrupted(
    c: &mut LibRPlusClient<Channel>,
    msgs: &[pb::StreamRegisterRequest],
) -> Vec<pb::Registration> {
    let mut s = open_stream(c, msgs[0].clone()).await.unwrap();
    let mut out = Vec::new();
    for m in &msgs[1..] {
        out.push(registration(&s.send(m.clone()).await.unwrap()).clone());
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_resume_after_a_lost_stream_and_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let cfg = ServerConfig {
        audit_db: Some(db.clone()),
        // Results independent of timing (no update cut short while other tests run).
        time_budget_ms: 10_000,
        ..config(4)
    };
    let mut running = librplus_server::start(cfg.clone()).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+2us");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let n = msgs.len().min(8);
    assert!(n >= 5, "{n} messages");
    let msgs = &msgs[..n];
    let reference = uninterrupted(&mut c, msgs).await;

    // A session that loses its stream after 3 answered messages.
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let mut sid = String::new();
    for m in &msgs[1..4] {
        let u = s.send(m.clone()).await.unwrap();
        sid = u.session_id.clone();
    }
    drop(s);
    // Resumed: the first update answers the recorded messages again (client_seq 4), equal to
    // the uninterrupted session's; then the next message's answer equals it too.
    let mut r = open_stream(&mut c, resume_start(&sid)).await.unwrap();
    let u = r.rx.message().await.unwrap().unwrap();
    assert_eq!(
        (u.session_id.as_str(), u.last_client_seq),
        (sid.as_str(), 4)
    );
    let d = diff(registration(&u), &reference[2]);
    eprintln!("resumed after a lost stream: first update differs by {d:.3e}");
    assert!(d <= 1e-9, "{d}");
    let u = r.send(msgs[4].clone()).await.unwrap();
    let d = diff(registration(&u), &reference[3]);
    eprintln!("next update differs by {d:.3e}");
    assert!(d <= 1e-9, "{d}");
    drop(r);

    // Restart the server (same audit log): the session resumes there too.
    running.shutdown().await;
    let mut running = librplus_server::start(cfg.clone()).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let mut r = open_stream(&mut c, resume_start(&sid)).await.unwrap();
    let u = r.rx.message().await.unwrap().unwrap();
    assert_eq!(u.last_client_seq, 5);
    assert!(diff(registration(&u), &reference[3]) <= 1e-9);
    for (k, m) in msgs.iter().enumerate().skip(5) {
        let u = r.send(m.clone()).await.unwrap();
        let d = diff(registration(&u), &reference[k - 1]);
        assert!(d <= 1e-9, "message {}: {d}", m.client_seq);
    }
    drop(r);
    // Unknown and malformed resumes.
    let e = open_stream(&mut c, resume_start("s-no-such-session"))
        .await
        .unwrap()
        .rx
        .message()
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound, "{e:?}");
    running.shutdown().await;

    // Every registration sent is in the log, with the hash of what was sent.
    let conn = audit::open_db(&db).unwrap();
    let rows = audit::rows(&conn, None, None).unwrap();
    let regs: Vec<_> = rows.iter().filter(|r| r.kind == "registration").collect();
    let sessions = rows.iter().filter(|r| r.kind == "session_start").count();
    eprintln!(
        "audit log: {} records, {} registrations, {sessions} sessions",
        rows.len(),
        regs.len()
    );
    // Reference n-1, first run 3, resume 1+1, after restart 1 + (n-5).
    assert_eq!(regs.len(), (n - 1) + 3 + 2 + 1 + (n - 5));
    assert_eq!(sessions, 2);
    let sha = librplus_server::auth::hex(&librplus_server::auth::sha256(
        &reference[0].encode_to_vec(),
    ));
    assert!(
        regs.iter()
            .any(|r| r.detail["answer_sha256"].as_str() == Some(sha.as_str())),
        "the first answer's hash is recorded"
    );
    // The recorded session exports as a sweep `librplus discover` reads.
    let out = dir.path().join("sweep");
    let e = audit::export_session(&conn, &sid, &out).unwrap();
    assert_eq!(e.messages, n - 1);
    assert!(out.join("surface.csv").exists());
    let pts = librplus::input::read_points(&out.join("surface.csv"), librplus::mesh::io::Unit::Mm)
        .unwrap();
    assert_eq!(pts.len(), e.surface);
    // `librplus-server audit` reads the same, as JSON lines and filtered by case and time.
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_librplus-server"));
    cmd.arg("audit").arg("--db").arg(&db).args([
        "--json",
        "--case",
        &case,
        "--since",
        "2000-01-01",
    ]);
    let out = run_cmd(cmd).await;
    let lines: Vec<serde_json::Value> = out
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(
        lines.iter().filter(|l| l["kind"] == "registration").count(),
        regs.len()
    );
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_librplus-server"));
    cmd.arg("audit")
        .arg("--db")
        .arg(&db)
        .args(["--since", "2999-01-01"]);
    assert_eq!(run_cmd(cmd).await.lines().count(), 0);
    // Without an audit log there is nothing to resume from.
    let mut running = librplus_server::start(config(2)).await.unwrap();
    running.ready().await.unwrap();
    let mut c = client(running.addr).await;
    let e = open_stream(&mut c, resume_start(&sid))
        .await
        .unwrap()
        .rx
        .message()
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    running.shutdown().await;
}

/// `kill -9` of the server in the middle of 8 streaming sessions, 20 times (restarted on the
/// same port and audit log each time); the clients resume (`run_session` with `resume`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_nine_loses_nothing_acknowledged() {
    use librplus_client::{Resume, SessionConfig, run_session};
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let port = free_port();
    let listen = format!("127.0.0.1:{port}");
    let db_arg = db.display().to_string();
    let args = [
        "--listen",
        listen.as_str(),
        "--audit",
        db_arg.as_str(),
        "--max-sessions",
        "8",
        // No update cut short by the time budget while other tests load the cores: the results
        // must not depend on timing.
        "--time-budget-ms",
        "10000",
    ];
    let proc = std::sync::Arc::new(std::sync::Mutex::new(Some(Proc::start(&args))));
    let url = format!("http://{listen}");
    let m = open(dataset()).unwrap();
    let case = m.deformations[0].geometry.clone();
    let scenarios = load_scenarios(dataset(), &m.deformations[0]).unwrap();
    let sessions: Vec<Vec<pb::StreamRegisterRequest>> = (0..8)
        .map(|k| {
            let sc = &scenarios[k % scenarios.len()];
            let method = if k % 2 == 0 {
                pb::Method::Libr
            } else {
                pb::Method::Rigid
            };
            stream_of(&case, sc, method).0
        })
        .collect();
    // The uninterrupted answers (last update of each session).
    let ch = tonic::transport::Endpoint::from_shared(url.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let client = LibRPlusClient::new(ch).max_decoding_message_size(64 << 20);
    let mut reference = Vec::new();
    let mut cfg = SessionConfig::new(Duration::from_secs(120), None).unwrap();
    for msgs in &sessions {
        let mut last = None;
        let o = run_session(&client, msgs, &cfg, |u, _| {
            if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                last = Some(r.clone());
            }
        })
        .await;
        assert!(o.end.is_completed(), "{}", o.end.describe());
        reference.push(last.unwrap());
    }
    // Paced so that the kills land mid-stream.
    cfg.rate_hz = Some(8.0);
    cfg.resume = Some(Resume {
        attempts: 40,
        first_backoff: Duration::from_millis(100),
    });
    let killer = {
        let proc = proc.clone();
        let args: Vec<String> = args.iter().map(|s| s.to_string()).collect();
        tokio::task::spawn_blocking(move || {
            let mut restarts = Vec::new();
            for _ in 0..20 {
                std::thread::sleep(Duration::from_millis(400));
                let mut p = proc.lock().unwrap();
                if let Some(mut old) = p.take() {
                    let _ = old.child.kill(); // SIGKILL
                    let _ = old.child.wait();
                }
                let t0 = std::time::Instant::now();
                let a: Vec<&str> = args.iter().map(String::as_str).collect();
                *p = Some(Proc::start(&a));
                restarts.push(t0.elapsed().as_secs_f64());
            }
            restarts
        })
    };
    let mut tasks = Vec::new();
    for msgs in sessions.clone() {
        let client = client.clone();
        let cfg = cfg.clone();
        tasks.push(tokio::spawn(async move {
            let mut acked: Vec<(String, u64, String)> = Vec::new();
            let mut last = None;
            let o = run_session(&client, &msgs, &cfg, |u, _| {
                if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                    let h = librplus_server::auth::hex(&librplus_server::auth::sha256(
                        &r.encode_to_vec(),
                    ));
                    acked.push((u.session_id.clone(), u.last_client_seq, h));
                    last = Some(r.clone());
                }
            })
            .await;
            (o, acked, last)
        }));
    }
    let mut outcomes = Vec::new();
    for t in tasks {
        outcomes.push(t.await.unwrap());
    }
    let restarts = killer.await.unwrap();
    drop(proc.lock().unwrap().take());
    let conn = audit::open_db(&db).unwrap();
    let mut acked_total = 0;
    let mut lost = 0;
    let mut resumed = 0;
    for (k, (o, acked, last)) in outcomes.iter().enumerate() {
        assert!(o.end.is_completed(), "session {k}: {}", o.end.describe());
        resumed += o.resumed;
        let d = diff(last.as_ref().unwrap(), &reference[k]);
        assert!(d <= 1e-9, "session {k}: last answer differs by {d}");
        for (sid, seq, h) in acked {
            acked_total += 1;
            let n: i64 = conn
                .query_row(
                    "SELECT COUNT(*) FROM registrations WHERE session_id = ?1 AND client_seq = ?2 \
                     AND answer_sha256 = ?3",
                    rusqlite::params![sid, *seq as i64, h],
                    |r| r.get(0),
                )
                .unwrap();
            if n == 0 {
                lost += 1;
            }
        }
    }
    eprintln!(
        "kill -9 x{}: {} sessions completed, {resumed} resumes, {acked_total} acknowledged \
         registrations, {lost} missing from the audit log; restart + preload {:.2} s median",
        restarts.len(),
        outcomes.len(),
        {
            let mut r = restarts.clone();
            r.sort_by(f64::total_cmp);
            r[r.len() / 2]
        }
    );
    assert_eq!(lost, 0);
    assert!(resumed > 0, "no session was interrupted");
}
