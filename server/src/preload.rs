//! Cases loaded in the background after the server started: a new upload, or a stored case
//! evicted while idle and asked for again. Progress goes to the registry (`WatchCase` follows
//! it); a failure leaves the case FAILED with its reason.

use crate::audit::Record;
use crate::cases::{self, CaseSource};
use crate::config::ServerConfig;
use crate::shared::Shared;
use crate::store::Stored;
use librplus::gcn::io::{TrainedModel, builtin_models, load_models_on_device};
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tonic_health::ServingStatus;
use tonic_health::server::HealthReporter;

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
        coarse_basis: false,
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
        // Once a coarse case serves (a large upload, `coarse_basis_above_nodes`), the status
        // stays READY on it while the case's own basis builds.
        let early_case = std::sync::Mutex::new(None::<Arc<cases::Case>>);
        let set = |stage: &str, fraction: f64| {
            let coarse = early_case
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .is_some();
            shared.registry.set(
                pb::CaseStatus {
                    case_id: id.clone(),
                    version: version.clone(),
                    state: if coarse {
                        pb::CaseState::Ready as i32
                    } else {
                        pb::CaseState::Loading as i32
                    },
                    stage: stage.into(),
                    fraction,
                    error: String::new(),
                    seconds: t0.elapsed().as_secs_f64(),
                    coarse_basis: coarse,
                },
                None,
            )
        };
        let early = |c: cases::Case| {
            let c = Arc::new(c);
            tracing::info!(case = %id, seconds = t0.elapsed().as_secs_f64(), nodes, "uploaded case READY on a coarse basis; its own basis builds");
            let mut s = crate::registry::ready_status(&c);
            s.stage = "coarse basis; its own basis builds".into();
            s.seconds = t0.elapsed().as_secs_f64();
            *early_case.lock().unwrap_or_else(|e| e.into_inner()) = Some(c.clone());
            shared.registry.set(s, Some(c));
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
            let r = cases::load_serving_early(
                &id,
                &CaseSource::Stored(Box::new(stored)),
                &shared.config,
                &learned,
                &progress,
                Some(&early),
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
                let coarse = early_case.lock().unwrap_or_else(|e| e.into_inner()).take();
                if let Some(coarse) = &coarse {
                    // Sessions on the coarse case swap to this one before their next update.
                    let _ = coarse.full.set(c.clone());
                }
                shared.registry.set(s, Some(c));
                if let Some(coarse) = coarse {
                    record_swap(
                        &shared,
                        &runtime,
                        &principal,
                        &coarse,
                        t0.elapsed().as_secs_f64(),
                    );
                }
            }
            Err(e) => {
                if early_case
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .take()
                    .is_some()
                {
                    // Its coarse basis served meanwhile; a case that failed is not served.
                    shared.registry.unserve(&id);
                }
                let failed = Failed {
                    id,
                    version,
                    principal,
                    remove: remove_on_failure,
                    seconds: t0.elapsed().as_secs_f64(),
                };
                preload_failed(&shared, &runtime, failed, &e);
            }
        }
    });
    first
}

/// An upload whose preload failed: its id, version, uploader, whether it is removed from the
/// store (a new upload) and the seconds since it was stored.
struct Failed {
    id: String,
    version: String,
    principal: String,
    remove: bool,
    seconds: f64,
}

/// A failed preload: removed from the store when new, FAILED with the reason, audited.
fn preload_failed(
    shared: &Arc<Shared>,
    runtime: &tokio::runtime::Handle,
    f: Failed,
    e: &cases::CaseError,
) {
    let Failed {
        id,
        version,
        principal,
        remove,
        seconds,
    } = f;
    // Removed from the store: it would fail again at every start and hold its
    // quota. Its FAILED status keeps the reason until it is uploaded again.
    let removed = shared
        .store
        .as_ref()
        .filter(|_| remove)
        .map(|s| s.remove_version(&id, Some(&version)));
    let error = match removed {
        Some(Ok(Some(_))) => {
            format!("{e}; the upload was removed from the case store: upload it again once fixed")
        }
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
            seconds,
            ..Default::default()
        },
        None,
    );
    let detail = serde_json::json!({ "version": version, "error": error });
    record_case_event(shared, runtime, "case_failed", principal, id, detail);
}

/// Audits a coarse case's swap to its own basis (`seconds` after the upload was stored).
fn record_swap(
    shared: &Arc<Shared>,
    runtime: &tokio::runtime::Handle,
    principal: &str,
    coarse: &cases::Case,
    seconds: f64,
) {
    let figures = coarse.coarse.expect("a coarse case");
    let detail = serde_json::json!({
        "version": coarse.version,
        "coarse_edge_mm": figures.edge_mm,
        "coarse_nodes": figures.coarse_nodes,
        "coarse_basis_s": figures.seconds,
        "own_basis_after_s": seconds,
    });
    tracing::info!(case = %coarse.id, seconds, "the case's own basis is ready; sessions swap to it");
    let (id, principal) = (coarse.id.clone(), principal.to_string());
    record_case_event(shared, runtime, "case_basis_swapped", principal, id, detail);
}

/// Records a case event of the preload in the audit log, in the background (a failure is
/// logged).
fn record_case_event(
    shared: &Arc<Shared>,
    runtime: &tokio::runtime::Handle,
    kind: &'static str,
    principal: String,
    id: String,
    detail: serde_json::Value,
) {
    let sh = shared.clone();
    runtime.spawn(async move {
        let r = sh
            .record(vec![Record::Event {
                kind,
                principal,
                case_id: Some(id.clone()),
                session_id: None,
                detail,
            }])
            .await;
        if let Err(e) = r {
            tracing::error!(case = %id, kind, error = ?e, "could not record a case event");
        }
    });
}

// The preload at start: every configured and stored case, the learned models, and the
// eviction of idle uploads.

/// What preload did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PreloadReport {
    /// Cases loaded: (id, nodes, seconds, basis from cache).
    pub cases: Vec<(String, usize, f64, bool)>,
    /// Cases that failed: (id, error).
    pub failed: Vec<(String, String)>,
    /// Total seconds.
    pub seconds: f64,
}

/// Why preload failed (the server then stays NOT_SERVING).
#[derive(Debug, thiserror::Error)]
pub enum PreloadError {
    /// The configured case paths could not be listed.
    #[error(transparent)]
    Cases(#[from] cases::CaseError),
    /// The SR-GCN model could not be loaded (`which`: "model" or "built-in model").
    #[error("{which}: {source}")]
    Model {
        /// Which model.
        which: &'static str,
        /// What failed.
        source: librplus::gcn::GcnError,
    },
    /// The V2S model could not be loaded (`v2s_model`, or the built-in one).
    #[error("v2s_model: {0}")]
    V2sModel(#[source] librplus::v2s::V2sError),
    /// Every case failed.
    #[error("no case could be loaded ({found} found): {failed:?}")]
    NoCase {
        /// Cases found.
        found: usize,
        /// (id, error) of each.
        failed: Vec<(String, String)>,
    },
    /// The preload task itself failed (a panic; logged).
    #[error("preload task failed: {0}")]
    Task(#[source] tokio::task::JoinError),
    /// The server stopped before preload finished.
    #[error("preload task ended")]
    Ended,
}

/// What preload came to, once it has: its report, or why it failed.
pub(crate) type Ready = Option<Result<PreloadReport, Arc<PreloadError>>>;

/// The gRPC service whose health is reported beside the server's.
const SERVICE_NAME: &str = "librplus.v1.LibRPlus";

/// Sets the health of the server (`""`) and of the `librplus.v1.LibRPlus` service.
pub(crate) async fn set_health(health: &HealthReporter, status: ServingStatus) {
    health.set_service_status("", status).await;
    health.set_service_status(SERVICE_NAME, status).await;
}

/// Preloads every case in the background; then health SERVING (and, with a case store and
/// `evict_idle_s`, idle uploads evicted), or NOT_SERVING kept when it failed. The report, or
/// why it failed, is sent on `ready`.
pub(crate) fn spawn_preload(
    shared: Arc<Shared>,
    health: HealthReporter,
    ready: watch::Sender<Ready>,
) {
    tokio::spawn(async move {
        let sh = shared.clone();
        let report = tokio::task::spawn_blocking(move || preload_all(&sh)).await;
        let report = match report {
            Ok(Ok(report)) => {
                shared.registry.set_preloaded();
                if shared.store.is_some() && shared.config.evict_idle_s > 0.0 {
                    tokio::spawn(evict_idle(shared.clone()));
                }
                set_health(&health, ServingStatus::Serving).await;
                tracing::info!(
                    cases = report.cases.len(),
                    failed = report.failed.len(),
                    seconds = report.seconds,
                    "preload done; SERVING"
                );
                Ok(report)
            }
            Ok(Err(e)) => {
                tracing::error!(error = %e, "preload failed; staying NOT_SERVING");
                Err(Arc::new(e))
            }
            Err(e) => Err(Arc::new(PreloadError::Task(e))),
        };
        let _ = ready.send(Some(report));
    });
}

/// The SR-GCN model every case gets for LIBR+: the configured directory (a model or an
/// ensemble), else the built-in one; its networks, shared between cases.
fn load_gcn(config: &ServerConfig) -> Result<Option<Vec<Arc<TrainedModel>>>, PreloadError> {
    if !config.librplus {
        return Ok(None);
    }
    let models = match &config.model {
        Some(dir) => load_models_on_device(dir).map_err(|e| PreloadError::Model {
            which: "model",
            source: e,
        })?,
        None => builtin_models().map_err(|e| PreloadError::Model {
            which: "built-in model",
            source: e,
        })?,
    };
    let first = &models[0];
    tracing::info!(
        model = %config.model.as_ref().map_or("built-in".into(), |p| p.display().to_string()),
        networks = models.len(),
        width = first.config.width,
        levels = first.config.levels,
        "SR-GCN model loaded: LIBR+ available"
    );
    Ok(Some(models.into_iter().map(Arc::new).collect()))
}

/// The V2S network every case gets for METHOD_V2S: the configured directory, else the built-in
/// one; none when `v2s` is off.
fn load_v2s(
    config: &ServerConfig,
) -> Result<Option<Arc<librplus::v2s::io::V2sModel>>, PreloadError> {
    if !config.v2s {
        return Ok(None);
    }
    let m = match &config.v2s_model {
        Some(dir) => librplus::v2s::io::load_model_on_device(dir),
        None => librplus::v2s::io::builtin_model(),
    }
    .map_err(PreloadError::V2sModel)?;
    tracing::info!(
        model = %config.v2s_model.as_ref().map_or("built-in".into(), |p| p.display().to_string()),
        grid = m.config.grid,
        width = m.config.width,
        depth = m.config.depth,
        "V2S model loaded: METHOD_V2S available"
    );
    Ok(Some(Arc::new(m)))
}

/// Takes uploaded cases out of memory once idle for `evict_idle_s` (no request used them, no
/// session holds them); they stay in the store, STORED, and load again when asked for.
async fn evict_idle(shared: Arc<Shared>) {
    let idle_ms = (shared.config.evict_idle_s * 1e3).min(1e15) as i64;
    let period = Duration::from_secs_f64((shared.config.evict_idle_s / 4.0).clamp(0.05, 60.0));
    let mut drain = shared.drain.clone();
    loop {
        tokio::select! {
            _ = tokio::time::sleep(period) => {}
            _ = drain.wait_for(|d| *d) => return,
        }
        let Some(store) = &shared.store else {
            return;
        };
        for (id, c) in shared.registry.ready().iter() {
            if c.idle_ms() < idle_ms || c.sessions.load(Ordering::SeqCst) > 0 {
                continue;
            }
            // Only an upload, and only the content the store holds (it loads from there).
            let stored = store.find(id).is_some_and(|s| s.version == c.version);
            if stored && shared.registry.evict(id, c) {
                tracing::info!(case = %id, idle_s = c.idle_ms() as f64 / 1e3, "idle uploaded case left memory (STORED; loaded again when asked for)");
                metrics::counter!("librplus_cases_evicted_total").increment(1);
            }
        }
    }
}

/// Preloads the configured cases and the case store's, into the registry.
fn preload_all(shared: &Shared) -> Result<PreloadReport, PreloadError> {
    let config = &shared.config;
    let t0 = Instant::now();
    let mut found = if config.cases.is_empty() {
        Vec::new()
    } else {
        cases::discover(config)?
    };
    let configured = found.len();
    if let Some(store) = &shared.store {
        match store.list() {
            Ok(list) => {
                for s in list {
                    match s {
                        Ok(s) => {
                            if found.iter().any(|(id, _)| *id == s.case_id) {
                                tracing::error!(case = %s.case_id, "a stored case has the id of a configured case; skipped");
                                continue;
                            }
                            found.push((s.case_id.clone(), cases::CaseSource::Stored(Box::new(s))));
                        }
                        Err(e) => {
                            tracing::error!(error = %e, "a stored case does not read; skipped")
                        }
                    }
                }
            }
            Err(e) => tracing::error!(error = %e, "the case store cannot be listed"),
        }
    }
    let learned = cases::Learned {
        gcn: load_gcn(config)?,
        v2s: load_v2s(config)?,
    };
    let _ = shared.learned.set(learned.clone());
    let mut report = PreloadReport {
        cases: Vec::new(),
        failed: Vec::new(),
        seconds: 0.0,
    };
    let mut loaded_configured = 0;
    for (k, (id, src)) in found.iter().enumerate() {
        match cases::load(id, src, config, &learned) {
            Ok(c) => {
                tracing::info!(
                    case = %id,
                    nodes = c.prepared.model.mesh.num_nodes(),
                    seconds = c.prepared.seconds,
                    basis_from_cache = c.prepared.basis_from_cache,
                    "case preloaded"
                );
                report.cases.push((
                    id.clone(),
                    c.prepared.model.mesh.num_nodes(),
                    c.prepared.seconds,
                    c.prepared.basis_from_cache,
                ));
                let c = Arc::new(c);
                shared
                    .registry
                    .set(crate::registry::ready_status(&c), Some(c));
                loaded_configured += usize::from(k < configured);
            }
            Err(e) => {
                tracing::error!(case = %id, error = %e, "case failed to load; skipped");
                report.failed.push((id.clone(), e.to_string()));
                shared.registry.set(
                    librplus_proto::v1::CaseStatus {
                        case_id: id.clone(),
                        state: librplus_proto::v1::CaseState::Failed as i32,
                        error: e.to_string(),
                        ..Default::default()
                    },
                    None,
                );
            }
        }
    }
    if configured > 0 && loaded_configured == 0 {
        return Err(PreloadError::NoCase {
            found: configured,
            failed: report.failed,
        });
    }
    report.seconds = t0.elapsed().as_secs_f64();
    Ok(report)
}
