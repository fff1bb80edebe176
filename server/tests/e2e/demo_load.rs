//! A busy machine: every message of a session gets its answer (flagged when it could not be the
//! full computation in its budget, never silence), while a discovery run the CPU starves is still
//! reported by its budget, with its reason; and a discovery that cannot run says why, down to the
//! replay client's table.

use crate::common::*;
use pb::stream_register_request::Msg;
use pb::stream_update::Update;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Busy threads at normal priority, one per core, until dropped: the machine as busy as a build
/// on every core.
struct Hog {
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Hog {
    fn start() -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let n = std::thread::available_parallelism().map_or(2, |n| n.get());
        let threads = (0..n)
            .map(|_| {
                let stop = stop.clone();
                std::thread::spawn(move || {
                    let mut x = 1u64;
                    while !stop.load(Ordering::Relaxed) {
                        for _ in 0..10_000 {
                            x = std::hint::black_box(
                                x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1),
                            );
                        }
                    }
                })
            })
            .collect();
        Self { stop, threads }
    }
}

impl Drop for Hog {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// Every scenario of the test dataset with its case id.
fn all_scenarios() -> Vec<(String, ScenarioData)> {
    let dir = dataset();
    let m = open(dir).unwrap();
    m.deformations
        .iter()
        .flat_map(|d| {
            load_scenarios(dir, d)
                .unwrap()
                .into_iter()
                .map(|s| (d.geometry.clone(), s))
        })
        .collect()
}

fn surface_count(sc: &ScenarioData) -> usize {
    sc.measurements
        .kind
        .iter()
        .filter(|k| **k == MeasuredKind::Surface)
        .count()
}

/// A server whose sessions may run discovery on the coarse grid, preloaded.
async fn coarse_discovery_server() -> librplus_server::Running {
    let mut running = librplus_server::start(ServerConfig {
        discovery_coarse: true,
        ..config(4)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    running
}

/// With every core busy at normal priority, a session with a 300 ms budget that asked for a
/// discovery run goes on: each message is answered (an answer over its budget flagged DEGRADED
/// with the reason, never OK), and the run, which the busy machine gives no CPU time, is reported
/// OUT_OF_TIME with its reason within its budget plus the report's grace, not left hanging.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_busy_machine_degrades_answers_and_still_reports_discovery() {
    let running = coarse_discovery_server().await;
    let mut client = client(running.addr).await;
    // The scenario with the most surface points: 200 before the run, more after it.
    let (case, sc) = all_scenarios()
        .into_iter()
        .max_by_key(|(_, s)| surface_count(s))
        .unwrap();
    assert!(
        surface_count(&sc) >= 280,
        "{}: {}",
        sc.id,
        surface_count(&sc)
    );
    let (mut msgs, _) = stream_of(&case, &sc, pb::Method::Libr);
    let budget_ms = 300;
    let discovery_budget = Duration::from_secs(2);
    if let Some(Msg::Start(s)) = msgs[0].msg.as_mut() {
        s.options = Some(pb::RegisterOptions {
            time_budget_ms: budget_ms,
            ..Default::default()
        });
        s.discovery = Some(pb::DiscoveryOptions {
            enabled: true,
            budget_ms: discovery_budget.as_millis() as u32,
            auto_after_points: 0,
        });
    }
    let surface: Vec<pb::StreamRegisterRequest> = msgs
        .drain(1..)
        .filter(|m| matches!(m.msg, Some(Msg::Surface(_))))
        .collect();
    let mut stream = open_stream(&mut client, msgs.remove(0)).await.unwrap();
    let mut seq = 1;
    let mut next = |m: &pb::StreamRegisterRequest| {
        seq += 1;
        pb::StreamRegisterRequest {
            client_seq: seq,
            msg: m.msg.clone(),
        }
    };
    let mut points = 0;
    let mut batches = surface.iter();
    for m in batches.by_ref() {
        let u = stream.send(next(m)).await.unwrap();
        assert!(matches!(u.update, Some(Update::Registration(_))), "{u:?}");
        points = u.points_total;
        if points >= 200 {
            break;
        }
    }
    let hog = Hog::start();
    let discover = pb::StreamRegisterRequest {
        client_seq: 0,
        msg: Some(Msg::Discover(pb::DiscoverNow {})),
    };
    let u = stream.send(next(&discover)).await.unwrap();
    let asked = Instant::now();
    let Some(Update::Discovery(started)) = &u.update else {
        panic!("{u:?}")
    };
    assert_eq!(
        started.state,
        pb::DiscoveryState::Running as i32,
        "{}",
        started.message
    );
    assert_eq!(started.points_used, points);
    // Registrations go on beside the starved run, each answered.
    let mut answered = 0;
    let mut report = None;
    for m in batches.take(2) {
        let m = next(m);
        let seq = m.client_seq;
        stream.tx.send(m).await.unwrap();
        loop {
            let u = tokio::time::timeout(Duration::from_secs(120), stream.rx.message())
                .await
                .expect("an answer, not silence")
                .unwrap()
                .unwrap();
            match u.update {
                Some(Update::Registration(r)) => {
                    assert_eq!(u.last_client_seq, seq);
                    let total = r.timings.as_ref().unwrap().total_ms;
                    if total > f64::from(budget_ms) {
                        assert_ne!(r.quality, pb::Quality::Ok as i32, "{total} ms, OK");
                        assert!(
                            r.quality_reason.contains("over its time budget"),
                            "{total} ms: {}",
                            r.quality_reason
                        );
                    }
                    answered += 1;
                    break;
                }
                // The run may end while a registration is on its way.
                Some(Update::Discovery(d)) => report = Some((d, asked.elapsed())),
                other => panic!("{other:?}"),
            }
        }
    }
    assert_eq!(answered, 2);
    let (report, waited) = match report {
        Some(r) => r,
        None => {
            let u = tokio::time::timeout(
                discovery_budget + Duration::from_secs(30),
                stream.rx.message(),
            )
            .await
            .expect("the run reported by its budget")
            .unwrap()
            .unwrap();
            let Some(Update::Discovery(d)) = u.update else {
                panic!("{u:?}")
            };
            (d, asked.elapsed())
        }
    };
    drop(hog);
    assert_eq!(
        report.state,
        pb::DiscoveryState::OutOfTime as i32,
        "{}",
        report.message
    );
    assert!(
        report.message.starts_with("out of time"),
        "{}",
        report.message
    );
    assert!(
        report.message.contains("the model is unchanged"),
        "{}",
        report.message
    );
    // By its budget and the report's grace, with room for a slow test machine; the starved run
    // itself would have taken minutes.
    assert!(
        waited < discovery_budget + Duration::from_secs(15),
        "{waited:?}"
    );
    drop(stream);
    running.shutdown().await;
}

/// A session with too few points for discovery is told so (FAILED, with the numbers), and the
/// replay client shows that reason in its summary and its table.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_discovery_that_cannot_run_says_why() {
    let running = coarse_discovery_server().await;
    let (_, sparse) = all_scenarios()
        .into_iter()
        .min_by_key(|(_, s)| s.measurements.points.len())
        .unwrap();
    let n = sparse.measurements.points.len();
    assert!(
        n < librplus_server::discovery::MIN_POINTS,
        "{}: {n} points",
        sparse.id
    );
    let summary = librplus_client::replay(&librplus_client::ReplayOptions {
        server: format!("http://{}", running.addr),
        data: dataset().to_path_buf(),
        selection: librplus_client::Selection::Ids(vec![sparse.id.clone()]),
        methods: Vec::new(),
        discover_with: vec![pb::Method::Libr],
        discovery: pb::DiscoveryOptions {
            enabled: true,
            ..Default::default()
        },
        ..Default::default()
    })
    .await
    .unwrap();
    running.shutdown().await;
    let r = &summary.results[0];
    assert_eq!(r.end, "completed");
    let d = r.discovery.as_ref().unwrap();
    assert_eq!(d.state, "FAILED");
    let want = format!("holds {n} points; discovery needs at least 200");
    assert!(d.message.contains(&want), "{}", d.message);
    let m = &summary.methods["libr+discovery"];
    assert_eq!(m.discovery.get("failed"), Some(&1));
    assert_eq!(m.discovery_unfinished.len(), 1);
    assert!(m.discovery_unfinished[0].reason.contains(&want));
    let table = librplus_client::replay_table(&summary);
    assert!(
        table.contains(&format!(
            "{} failed: discover: the session {want}",
            sparse.id
        )),
        "{table}"
    );
}
