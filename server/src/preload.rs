//! Cases loaded in the background after the server started: a new upload, or a stored case
//! evicted while idle and asked for again. Progress goes to the registry (`WatchCase` follows
//! it); a failure leaves the case FAILED with its reason.

use crate::audit::Record;
use crate::cases::{self, CaseSource};
use crate::shared::Shared;
use crate::store::Stored;
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

/// Starts preloading a new upload in the background; its first status. An upload that fails
/// is removed from the store.
pub fn preload(shared: Arc<Shared>, stored: Stored) -> pb::CaseStatus {
    preload_with(shared, stored, true)
}

/// Loads evicted case `id` again (its state STORED) in the background, when this caller is the
/// first to ask; a failure leaves it in the store, FAILED with the reason.
pub fn reload(shared: &Arc<Shared>, id: &str) {
    if !shared.registry.begin_reload(id) {
        return;
    }
    match shared.store.as_ref().and_then(|s| s.find(id)) {
        Some(stored) => {
            tracing::info!(case = %id, "an evicted case is asked for: loading it again");
            preload_with(shared.clone(), stored, false);
        }
        None => {
            shared.registry.remove(id);
        }
    }
}

/// Starts preloading a stored case in the background; its first status. `remove_on_failure`:
/// a new upload that fails is removed from the store (a case loaded again is not).
fn preload_with(shared: Arc<Shared>, stored: Stored, remove_on_failure: bool) -> pb::CaseStatus {
    let t0 = Instant::now();
    let status = |stage: &str, fraction: f64| pb::CaseStatus {
        case_id: stored.case_id.clone(),
        version: stored.version.clone(),
        state: pb::CaseState::Loading as i32,
        stage: stage.into(),
        fraction,
        error: String::new(),
        seconds: t0.elapsed().as_secs_f64(),
    };
    let first = status("queued", 0.0);
    shared.registry.set_uploaded(&stored.case_id);
    shared.registry.set(first.clone(), None);
    let runtime = tokio::runtime::Handle::current();
    tokio::task::spawn_blocking(move || {
        let principal = stored.principal.clone();
        let id = stored.case_id.clone();
        let version = stored.version.clone();
        let nodes = stored.nodes;
        let set = |stage: &str, fraction: f64| {
            shared.registry.set(
                pb::CaseStatus {
                    case_id: id.clone(),
                    version: version.clone(),
                    state: pb::CaseState::Loading as i32,
                    stage: stage.into(),
                    fraction,
                    error: String::new(),
                    seconds: t0.elapsed().as_secs_f64(),
                },
                None,
            )
        };
        // The `preparing` stage (correspondence and LIBR basis) reports no progress of its own:
        // its fraction moves with the time it is expected to take (measured here: 5.5 s for
        // 9,089 nodes, 22 s for 60,835, about nodes^0.73), never past 0.85 before it ends.
        let expected = 5.5 * (nodes as f64 / 9089.0).max(0.01).powf(0.73);
        let preparing = std::sync::Mutex::new(None::<Instant>);
        let progress = |stage: &str, fraction: f64| {
            *preparing.lock().unwrap_or_else(|e| e.into_inner()) =
                (stage == "preparing").then(Instant::now);
            set(stage, fraction);
        };
        let done = std::sync::atomic::AtomicBool::new(false);
        let learned = shared.learned.get().cloned().unwrap_or_default();
        let r = std::thread::scope(|scope| {
            scope.spawn(|| {
                while !done.load(Ordering::Acquire) {
                    std::thread::sleep(Duration::from_millis(500));
                    let since = *preparing.lock().unwrap_or_else(|e| e.into_inner());
                    if let Some(since) = since
                        && !done.load(Ordering::Acquire)
                    {
                        let f = (since.elapsed().as_secs_f64() / expected).min(1.0);
                        set("preparing", 0.2 + 0.65 * f);
                    }
                }
            });
            let r = cases::load_with_progress(
                &id,
                &CaseSource::Stored(Box::new(stored)),
                &shared.config,
                &learned,
                &progress,
            );
            done.store(true, Ordering::Release);
            r
        });
        match r {
            Ok(c) => {
                tracing::info!(case = %id, seconds = t0.elapsed().as_secs_f64(), "uploaded case READY");
                let c = Arc::new(c);
                let mut s = crate::registry::ready_status(&c);
                s.seconds = t0.elapsed().as_secs_f64();
                shared.registry.set(s, Some(c));
            }
            Err(e) => {
                // Removed from the store: it would fail again at every start and hold its
                // quota. Its FAILED status keeps the reason until it is uploaded again.
                let removed = shared
                    .store
                    .as_ref()
                    .filter(|_| remove_on_failure)
                    .map(|s| s.remove_version(&id, Some(&version)));
                let error = match removed {
                    Some(Ok(Some(_))) => format!(
                        "{e}; the upload was removed from the case store: upload it again once fixed"
                    ),
                    Some(Err(r)) => {
                        tracing::error!(case = %id, error = %r, "could not remove the failed upload from the case store");
                        e.to_string()
                    }
                    _ => e.to_string(),
                };
                tracing::error!(case = %id, error = %error, "uploaded case failed to preload");
                shared.registry.set(
                    pb::CaseStatus {
                        case_id: id.clone(),
                        version: version.clone(),
                        state: pb::CaseState::Failed as i32,
                        error: error.clone(),
                        seconds: t0.elapsed().as_secs_f64(),
                        ..Default::default()
                    },
                    None,
                );
                let sh = shared.clone();
                runtime.spawn(async move {
                    let r = sh
                        .record(vec![Record::Event {
                            kind: "case_failed",
                            principal,
                            case_id: Some(id.clone()),
                            session_id: None,
                            detail: serde_json::json!({ "version": version, "error": error }),
                        }])
                        .await;
                    if let Err(e) = r {
                        tracing::error!(case = %id, error = ?e, "could not record the failed preload");
                    }
                });
            }
        }
    });
    first
}
