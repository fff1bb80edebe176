//! Replicas that take over: two server processes share a session journal (each with its own
//! audit log); 6 streaming sessions spread over both; one of them `kill -9`ed at a time, 6 times
//! (restarted on its port); every session completes with the uninterrupted run's last answer,
//! sessions move between the replicas, and every acknowledged registration is in one of the two
//! audit logs. (The container version with three replicas and a rolling restart is
//! deploy/test-replicas.sh.)

use crate::common::*;
use librplus_server::audit;
use prost::Message as _;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replica_takes_over_the_sessions_of_a_killed_one() {
    use librplus_client::{Resume, SessionConfig, run_session};
    let dir = tempfile::tempdir().unwrap();
    let journal = dir.path().join("sessions");
    let journal_arg = journal.display().to_string();
    let names = ["a", "b"];
    let args: Vec<Vec<String>> = names
        .iter()
        .map(|n| {
            let port = free_port();
            [
                "--listen",
                &format!("127.0.0.1:{port}"),
                "--audit",
                &dir.path().join(format!("{n}.db")).display().to_string(),
                "--session-journal",
                &journal_arg,
                "--max-sessions",
                "8",
                // No update cut short by the time budget while other tests load the cores: the
                // results must not depend on timing.
                "--time-budget-ms",
                "10000",
            ]
            .iter()
            .map(|s| s.to_string())
            .collect()
        })
        .collect();
    let args = std::sync::Arc::new(args);
    let start = {
        let args = args.clone();
        move |k: usize| {
            let a: Vec<&str> = args[k].iter().map(String::as_str).collect();
            Proc::start(&a)
        }
    };
    let procs = std::sync::Arc::new(std::sync::Mutex::new(vec![Some(start(0)), Some(start(1))]));
    let urls: Vec<String> = args.iter().map(|a| format!("http://{}", a[1])).collect();
    let replicas =
        librplus_client::connect_replicas(&urls.join(","), &librplus_client::Tls::default())
            .unwrap();
    let m = open(dataset()).unwrap();
    let case = m.deformations[0].geometry.clone();
    let scenarios = load_scenarios(dataset(), &m.deformations[0]).unwrap();
    let sessions: Vec<Vec<pb::StreamRegisterRequest>> = (0..6)
        .map(|k| {
            let method = if k % 2 == 0 {
                pb::Method::Libr
            } else {
                pb::Method::Rigid
            };
            stream_of(&case, &scenarios[k % scenarios.len()], method).0
        })
        .collect();
    // The uninterrupted answers, on replica a.
    let mut cfg = SessionConfig::new(Duration::from_secs(120), None).unwrap();
    let mut reference = Vec::new();
    for msgs in &sessions {
        let mut last = None;
        let o = run_session(&replicas[0], msgs, &cfg, |u, _| {
            if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                last = Some(librplus_client::result_sha256(r));
            }
        })
        .await;
        assert!(o.end.is_completed(), "{}", o.end.describe());
        reference.push(last.unwrap());
    }
    cfg.rate_hz = Some(8.0);
    cfg.resume = Some(Resume {
        attempts: 40,
        first_backoff: Duration::from_millis(100),
        take_back: false,
    });
    cfg.replicas = replicas.clone();
    let killer = {
        let procs = procs.clone();
        tokio::task::spawn_blocking(move || {
            for i in 0..6 {
                std::thread::sleep(Duration::from_millis(500));
                let k = i % 2;
                let old = procs.lock().unwrap()[k].take();
                if let Some(mut old) = old {
                    let _ = old.child.kill(); // SIGKILL
                    let _ = old.child.wait();
                }
                let p = start(k);
                procs.lock().unwrap()[k] = Some(p);
            }
        })
    };
    let mut tasks = Vec::new();
    for (k, msgs) in sessions.iter().cloned().enumerate() {
        let mut cfg = cfg.clone();
        cfg.first_replica = k;
        let client = replicas[0].clone();
        tasks.push(tokio::spawn(async move {
            let mut acked: Vec<(String, u64, String)> = Vec::new();
            let mut last = None;
            let o = run_session(&client, &msgs, &cfg, |u, _| {
                if let Some(pb::stream_update::Update::Registration(r)) = &u.update {
                    acked.push((
                        u.session_id.clone(),
                        u.last_client_seq,
                        librplus_client::sha256_hex(&r.encode_to_vec()),
                    ));
                    // The result without its timings: equal for equal results.
                    last = Some(librplus_client::result_sha256(r));
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
    killer.await.unwrap();
    drop(procs.lock().unwrap().drain(..).collect::<Vec<_>>());
    let dbs: Vec<_> = names
        .iter()
        .map(|n| audit::open_db(&dir.path().join(format!("{n}.db"))).unwrap())
        .collect();
    let (mut acked_total, mut lost, mut resumed, mut moved) = (0, 0, 0, 0);
    for (k, (o, acked, last)) in outcomes.iter().enumerate() {
        assert!(o.end.is_completed(), "session {k}: {}", o.end.describe());
        resumed += o.resumed;
        assert_eq!(
            last.as_ref().unwrap(),
            &reference[k],
            "session {k}: the last answer differs from the uninterrupted run's"
        );
        let mut on = [false; 2];
        for (sid, seq, h) in acked {
            acked_total += 1;
            let mut found = false;
            for (i, c) in dbs.iter().enumerate() {
                let n: i64 = c
                    .query_row(
                        "SELECT COUNT(*) FROM registrations WHERE session_id = ?1 AND \
                         client_seq = ?2 AND answer_sha256 = ?3",
                        rusqlite::params![sid, *seq as i64, h],
                        |r| r.get(0),
                    )
                    .unwrap();
                if n > 0 {
                    found = true;
                    on[i] = true;
                }
            }
            lost += usize::from(!found);
        }
        moved += usize::from(on[0] && on[1]);
    }
    eprintln!(
        "2 replicas, 6 kill -9: {} sessions completed with the uninterrupted answers, {resumed} \
         resumes, {moved} sessions answered by both replicas, {acked_total} acknowledged \
         registrations, {lost} in neither audit log",
        outcomes.len()
    );
    assert_eq!(lost, 0);
    assert!(moved > 0, "no session moved to the other replica");
}
