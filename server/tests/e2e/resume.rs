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

/// The status a resume of `sid` ends with (it must be refused).
async fn refused_resume(c: &mut LibRPlusClient<Channel>, sid: &str) -> tonic::Status {
    open_stream(c, resume_start(sid))
        .await
        .unwrap()
        .rx
        .message()
        .await
        .unwrap_err()
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
    let e = refused_resume(&mut c, "s-no-such-session").await;
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
    let e = refused_resume(&mut c, &sid).await;
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    running.shutdown().await;
}

/// `kill -9` of the server in the middle of 8 streaming sessions, 20 times (restarted on the
/// same port and audit log each time); the clients resume (`run_session` with `resume`). A
/// rival client meanwhile resumes open sessions now and then, takes them over and sends their
/// next message; the owners take them back. Every acknowledged answer, the owners' and the
/// rival's, is in the log and equals the uninterrupted session's answer to the same recorded
/// messages, and the log's messages are the script's.
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
        // The 8 sessions and the rival (a resume of a session whose stream was lost needs a
        // slot of its own).
        "--max-sessions",
        "9",
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
    // The uninterrupted answers: each session's last, and every answer by client_seq.
    let ch = tonic::transport::Endpoint::from_shared(url.clone())
        .unwrap()
        .connect()
        .await
        .unwrap();
    let client = LibRPlusClient::new(ch).max_decoding_message_size(64 << 20);
    let mut reference = Vec::new();
    let mut by_seq: Vec<std::collections::HashMap<u64, pb::Registration>> = Vec::new();
    let mut cfg = SessionConfig::new(Duration::from_secs(120), None).unwrap();
    for msgs in &sessions {
        let mut last = None;
        let mut all = std::collections::HashMap::new();
        let o = run_session(&client, msgs, &cfg, |u, _| {
            if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                last = Some(r.clone());
                all.insert(u.last_client_seq, r.clone());
            }
        })
        .await;
        assert!(o.end.is_completed(), "{}", o.end.describe());
        reference.push(last.unwrap());
        by_seq.push(all);
    }
    // Paced so that the kills land mid-stream; a session taken over by the rival is taken back.
    cfg.rate_hz = Some(8.0);
    cfg.resume = Some(Resume {
        attempts: 40,
        first_backoff: Duration::from_millis(100),
        take_back: true,
    });
    // Each session's id once known, and whether every owner is done.
    let ids = std::sync::Arc::new(std::sync::Mutex::new(vec![None::<String>; sessions.len()]));
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    // The rival: resumes an open session, takes its answer to the recorded messages, sends the
    // session's next message (the script's own) and goes away; (session, sid, seq, answer).
    let rival = {
        let (ids, done, url) = (ids.clone(), done.clone(), url.clone());
        let sessions = sessions.clone();
        tokio::spawn(async move {
            let mut acked: Vec<(usize, String, u64, pb::Registration)> = Vec::new();
            let mut tries = 0;
            let mut k = 0;
            while !done.load(std::sync::atomic::Ordering::SeqCst) {
                tokio::time::sleep(Duration::from_millis(300)).await;
                k = (k + 3) % sessions.len();
                let Some(sid) = ids.lock().unwrap()[k].clone() else {
                    continue;
                };
                tries += 1;
                let run = async {
                    let ch = tonic::transport::Endpoint::from_shared(url.clone())
                        .ok()?
                        .connect()
                        .await
                        .ok()?;
                    let mut c = LibRPlusClient::new(ch).max_decoding_message_size(64 << 20);
                    let mut s = open_stream(&mut c, resume_start(&sid)).await.ok()?;
                    let u = s.rx.message().await.ok()??;
                    let seq = u.last_client_seq;
                    acked.push((k, sid.clone(), seq, registration(&u).clone()));
                    let next = sessions[k].get(seq as usize)?.clone();
                    let u = s.send(next).await.ok()?;
                    if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                        acked.push((k, sid.clone(), u.last_client_seq, r.clone()));
                    }
                    Some(())
                };
                let _ = tokio::time::timeout(Duration::from_secs(10), run).await;
            }
            (tries, acked)
        })
    };
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
    for (k, msgs) in sessions.clone().into_iter().enumerate() {
        let client = client.clone();
        let cfg = cfg.clone();
        let ids = ids.clone();
        tasks.push(tokio::spawn(async move {
            let mut acked: Vec<(String, u64, pb::Registration)> = Vec::new();
            let mut last = None;
            let o = run_session(&client, &msgs, &cfg, |u, _| {
                ids.lock().unwrap()[k].get_or_insert_with(|| u.session_id.clone());
                if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                    acked.push((u.session_id.clone(), u.last_client_seq, r.clone()));
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
    done.store(true, std::sync::atomic::Ordering::SeqCst);
    let (rival_tries, rival_acked) = rival.await.unwrap();
    let restarts = killer.await.unwrap();
    drop(proc.lock().unwrap().take());
    let conn = audit::open_db(&db).unwrap();
    let mut acked_total = 0;
    let mut lost = 0;
    let mut resumed = 0;
    // Every answer acknowledged to anyone: (session, sid, client_seq, answer).
    let mut all_acked: Vec<(usize, String, u64, pb::Registration)> = rival_acked.clone();
    for (k, (_, acked, _)) in outcomes.iter().enumerate() {
        all_acked.extend(
            acked
                .iter()
                .map(|(sid, seq, r)| (k, sid.clone(), *seq, r.clone())),
        );
    }
    // The log's messages are the script's, so an answer equal to the uninterrupted session's
    // answer at the same client_seq is the answer the log gives.
    for (k, sid) in ids.lock().unwrap().iter().enumerate() {
        let sid = sid.as_ref().expect("every session started");
        let rec = audit::read_session(&conn, sid).unwrap().unwrap();
        for (seq, bytes) in &rec.messages {
            assert_eq!(
                bytes,
                &sessions[k][*seq as usize - 1].encode_to_vec(),
                "session {k}: recorded client_seq {seq} is not the script's"
            );
        }
    }
    for (k, _, seq, r) in &all_acked {
        let d = diff(r, &by_seq[*k][seq]);
        assert!(
            d <= 1e-9,
            "session {k}: the answer acknowledged for client_seq {seq} differs by {d} from the \
             answer to the recorded messages"
        );
    }
    for (k, (o, _, last)) in outcomes.iter().enumerate() {
        assert!(o.end.is_completed(), "session {k}: {}", o.end.describe());
        resumed += o.resumed;
        let d = diff(last.as_ref().unwrap(), &reference[k]);
        assert!(d <= 1e-9, "session {k}: last answer differs by {d}");
    }
    for (_, sid, seq, r) in &all_acked {
        let h = librplus_server::auth::hex(&librplus_server::auth::sha256(&r.encode_to_vec()));
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
    eprintln!(
        "kill -9 x{}: {} sessions completed, {resumed} resumes, {rival_tries} resumes by a rival \
         ({} answers to it), {acked_total} acknowledged registrations, {lost} missing from the \
         audit log, all equal to the answers the log gives; restart + preload {:.2} s median",
        restarts.len(),
        outcomes.len(),
        rival_acked.len(),
        {
            let mut r = restarts.clone();
            r.sort_by(f64::total_cmp);
            r[r.len() / 2]
        }
    );
    assert_eq!(lost, 0);
    assert!(resumed > 0, "no session was interrupted");
    assert!(!rival_acked.is_empty(), "the rival took no session over");
}

/// The `google.rpc.ErrorInfo` reason of a status, if any.
fn reason(s: &tonic::Status) -> String {
    s.get_error_details()
        .error_info()
        .map(|i| i.reason.clone())
        .unwrap_or_default()
}

/// `m` with its points moved by `dx` mm along x (other content under the same client_seq).
fn moved(m: &pb::StreamRegisterRequest, dx: f64) -> pb::StreamRegisterRequest {
    use pb::stream_register_request::Msg;
    let mut m = m.clone();
    match &mut m.msg {
        Some(Msg::Surface(s)) => s.xyz_mm.iter_mut().step_by(3).for_each(|x| *x += dx),
        Some(Msg::Ultrasound(u)) => {
            if let Some(p) = u.plane_to_physical.as_mut() {
                p.translation_mm[0] += dx;
            }
        }
        other => panic!("not a message with points: {other:?}"),
    }
    m
}

/// Resuming a session whose stream is still open takes it over: the older stream ends with
/// ABORTED (SESSION_TAKEN_OVER) and answers nothing more; concurrent resumes sending different
/// content under the same client_seq never both get it answered, and every acknowledged answer is
/// what the recorded messages give. (Before the fix, the open stream and every resume were
/// answered, and the log kept only the first content of each client_seq.) Runs the server as a
/// process, so `LIBRPLUS_SERVER_BIN` can point it at an older build.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resume_takes_over_an_open_session_and_nothing_diverges() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db");
    let db_arg = db.display().to_string();
    let p = Proc::start(&["--audit", &db_arg, "--time-budget-ms", "10000"]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let case = open(dataset()).unwrap().deformations[0].geometry.clone();
    let (_, sc) = scenario("surface+2us");
    let (msgs, _) = stream_of(&case, &sc, pb::Method::Rigid);
    assert!(msgs.len() >= 6, "{} messages", msgs.len());
    // Every acknowledged registration, by client_seq.
    let acked = std::sync::Arc::new(std::sync::Mutex::new(Vec::<(u64, pb::Registration)>::new()));
    let ack = |u: &pb::StreamUpdate| {
        if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
            acked.lock().unwrap().push((u.last_client_seq, r.clone()));
        }
    };
    let mut a = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let mut sid = String::new();
    for m in &msgs[1..3] {
        let u = a.send(m.clone()).await.unwrap();
        ack(&u);
        sid = u.session_id.clone();
    }
    // A resume while A is still open: it holds the session from now.
    let mut r = open_stream(&mut c, resume_start(&sid)).await.unwrap();
    let u = r.rx.message().await.unwrap().unwrap();
    assert_eq!(u.last_client_seq, 3);
    ack(&u);
    // A is told at once (its stream has ended), and its next message is not answered.
    let _ = a.tx.send(msgs[3].clone()).await;
    let e = a.rx.message().await.unwrap_err();
    eprintln!("the older stream: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::Aborted, "{e:?}");
    assert_eq!(reason(&e), "SESSION_TAKEN_OVER");
    assert!(
        e.message().contains(&sid) && e.message().contains("taken over"),
        "{e:?}"
    );
    let u = r.send(msgs[3].clone()).await.unwrap();
    assert_eq!(u.last_client_seq, 4);
    ack(&u);
    // Three resumes at once, each sending client_seq 5 with its own content.
    let mut tasks = Vec::new();
    for k in 0..3 {
        let mut c = c.clone();
        let sid = sid.clone();
        let m5 = moved(&msgs[4], 15.0 * (k + 1) as f64);
        tasks.push(tokio::spawn(async move {
            let mut got = Vec::new();
            let mut s = match open_stream(&mut c, resume_start(&sid)).await {
                Ok(s) => s,
                Err(e) => return (got, Some(e)),
            };
            match s.rx.message().await {
                Ok(Some(u)) => got.push(u),
                Ok(None) => return (got, None),
                Err(e) => return (got, Some(e)),
            }
            match s.send(m5).await {
                Ok(u) => got.push(u),
                Err(e) => return (got, Some(e)),
            }
            (got, None)
        }));
    }
    let mut fifth = Vec::new();
    for t in tasks {
        let (got, end) = t.await.unwrap();
        for u in &got {
            ack(u);
            if u.last_client_seq == 5
                && matches!(u.update, Some(pb::stream_update::Update::Registration(_)))
            {
                fifth.push(u.clone());
            }
        }
        if let Some(e) = end {
            eprintln!("a concurrent resume ended: {:?} {}", e.code(), e.message());
            assert!(
                matches!(e.code(), Code::Aborted | Code::ResourceExhausted),
                "{e:?}"
            );
        }
    }
    drop((a, r));
    // The session as recorded, resumed once more: its answer for the last recorded message is
    // every acknowledged answer for it; and no client_seq was answered with two contents.
    let mut last = open_stream(&mut c, resume_start(&sid)).await.unwrap();
    let u = last.rx.message().await.unwrap().unwrap();
    let final_seq = u.last_client_seq;
    let final_reg = registration(&u).clone();
    let acked = acked.lock().unwrap().clone();
    eprintln!(
        "{} acknowledged answers ({} for client_seq 5); the record ends at client_seq {final_seq}",
        acked.len(),
        fifth.len()
    );
    for (seq, r) in &acked {
        for (seq2, r2) in &acked {
            if seq == seq2 {
                let d = diff(r, r2);
                assert!(
                    d <= 1e-9,
                    "client_seq {seq} answered twice, differing by {d} mm"
                );
            }
        }
        if *seq == final_seq {
            let d = diff(r, &final_reg);
            assert!(
                d <= 1e-9,
                "client_seq {seq}: the record gives another answer ({d})"
            );
        }
    }
    assert!(final_seq >= 4);
    // The log holds each client_seq once.
    let conn = audit::open_db(&db).unwrap();
    let n: i64 = conn
        .query_row(
            "SELECT COUNT(*) FROM messages WHERE session_id = ?1",
            [&sid],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(n as u64, final_seq - 1);
}

/// A session resumed after its case was deleted and uploaded again with other content is
/// refused, naming both versions; DeleteCase counts the sessions that can no longer resume.
/// (Before the fix, the resume registered the session's points to the new mesh and answered
/// QUALITY_OK.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resume_on_a_replaced_case_is_refused_naming_both_versions() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("audit.db").display().to_string();
    let store = dir.path().join("store").display().to_string();
    let p = Proc::start(&["--audit", &db, "--case-store", &store]);
    let mut c = client(p.addr.parse().unwrap()).await;
    let m = open(dataset()).unwrap();
    let g = load_geometry(dataset(), &m, &m.deformations[0].geometry).unwrap();
    let mesh = &g.model.mesh;
    let upload = |scale: f64, shift: f64| {
        vec![pb::CreateCaseRequest {
            part: Some(pb::create_case_request::Part::Upload(pb::CaseUpload {
                case_id: "replaced/liver".into(),
                nodes_mm: mesh
                    .nodes()
                    .iter()
                    .flat_map(|p| p.map(|x| x * scale + shift))
                    .collect(),
                tets: mesh.tets().iter().flat_map(|t| *t).collect(),
                ..Default::default()
            })),
        }]
    };
    let ready = |mut c: LibRPlusClient<Channel>| async move {
        let mut s = c
            .watch_case(pb::WatchCaseRequest {
                case_id: "replaced/liver".into(),
            })
            .await
            .unwrap()
            .into_inner();
        let mut last = None;
        while let Some(st) = s.message().await.unwrap() {
            last = Some(st);
        }
        let st = last.unwrap();
        assert_eq!(st.state, pb::CaseState::Ready as i32, "{st:?}");
    };
    let v1 = c
        .create_case(tokio_stream::iter(upload(1.0, 0.0)))
        .await
        .unwrap()
        .into_inner()
        .version;
    ready(c.clone()).await;
    let (_, sc) = scenario("surface+2us");
    let (msgs, _) = stream_of("replaced/liver", &sc, pb::Method::Rigid);
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let mut sid = String::new();
    for m in &msgs[1..3] {
        sid = s.send(m.clone()).await.unwrap().session_id;
    }
    drop(s);
    // Deleted (the response says one session can no longer resume), then other content under
    // the same id: the nodes ×1.1 and moved 20 mm.
    // (Refused while the server has not yet seen the stream end.)
    let mut tries = 0;
    let del = loop {
        match c
            .delete_case(pb::DeleteCaseRequest {
                case_id: "replaced/liver".into(),
            })
            .await
        {
            Ok(r) => break r.into_inner(),
            Err(e) if e.code() == Code::FailedPrecondition && tries < 50 => {
                tries += 1;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("{e:?}"),
        }
    };
    assert_eq!(del.version, v1);
    assert_eq!(del.resumable_sessions, 1, "{del:?}");
    // Deleted and not replaced: refused, naming the case.
    let e = refused_resume(&mut c, &sid).await;
    eprintln!("resume after delete: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    assert!(e.message().contains("no longer exists"), "{e:?}");
    let v2 = c
        .create_case(tokio_stream::iter(upload(1.1, 20.0)))
        .await
        .unwrap()
        .into_inner()
        .version;
    assert_ne!(v1, v2);
    ready(c.clone()).await;
    let e = refused_resume(&mut c, &sid).await;
    eprintln!("resume after replace: {:?} {}", e.code(), e.message());
    assert_eq!(e.code(), Code::FailedPrecondition, "{e:?}");
    assert!(
        e.message().contains(&v1) && e.message().contains(&v2),
        "the message names both versions: {e:?}"
    );
    // A new session on the new content works.
    let mut s = open_stream(&mut c, msgs[0].clone()).await.unwrap();
    let u = s.send(msgs[1].clone()).await.unwrap();
    assert!(matches!(
        u.update,
        Some(pb::stream_update::Update::Registration(_))
    ));
}
