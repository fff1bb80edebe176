//! `librplus-server`: the LIBR+ gRPC registration service.
//!
//! [`start`] binds the listen address at once and serves health (NOT_SERVING), reflection (v1 and
//! v1alpha) and the `librplus.v1.LibRPlus` service; it preloads every case in the background
//! (correspondence structures and LIBR bases, from the on-disk cache when valid) and then turns
//! health to SERVING. [`Running::shutdown`] drains: health NOT_SERVING, new calls refused, each open
//! session finishes the update it is computing and ends with UNAVAILABLE, then the transport closes
//! (after `drain_grace_s` at most).
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod cases;
pub mod compute;
pub mod config;
pub mod convert;
pub mod discovery;
pub mod error;
pub mod metrics_http;
pub mod service;

use anyhow::Context;
use cases::Case;
use config::ServerConfig;
use librplus::gcn::io::{TrainedModel, builtin_models, load_models_on_device};
use librplus::register::libr::LibrParams;
use librplus_proto::v1::lib_r_plus_server::LibRPlusServer;
use service::{Shared, Svc};
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};
use tokio::sync::{Semaphore, oneshot, watch};
use tonic::transport::Server;
use tonic_health::ServingStatus;

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
    Task(String),
    /// The server stopped before preload finished.
    #[error("preload task ended")]
    Ended,
}

/// A running server.
pub struct Running {
    /// The gRPC address it listens on.
    pub addr: SocketAddr,
    /// The metrics endpoint's address, if any.
    pub metrics_addr: Option<SocketAddr>,
    shared: Arc<Shared>,
    drain: watch::Sender<bool>,
    stop: Option<oneshot::Sender<()>>,
    serve: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
    reload: tokio::sync::mpsc::Sender<Reload>,
    ready: watch::Receiver<Option<Result<PreloadReport, Arc<PreloadError>>>>,
    health: tonic_health::server::HealthReporter,
}

static PROMETHEUS: OnceLock<Option<metrics_exporter_prometheus::PrometheusHandle>> =
    OnceLock::new();

/// The process's Prometheus recorder (installed on first use; None if another recorder was).
pub fn prometheus() -> Option<&'static metrics_exporter_prometheus::PrometheusHandle> {
    PROMETHEUS
        .get_or_init(|| {
            let buckets = [
                0.005, 0.01, 0.02, 0.05, 0.075, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.75, 1.0,
                2.0, 5.0,
            ];
            metrics_exporter_prometheus::PrometheusBuilder::new()
                .set_buckets(&buckets)
                .ok()?
                .install_recorder()
                .ok()
        })
        .as_ref()
}

const SERVICE_NAME: &str = "librplus.v1.LibRPlus";

/// Binds, serves, and starts preloading. Returns once the port is bound.
pub async fn start(config: ServerConfig) -> anyhow::Result<Running> {
    config.validate().map_err(anyhow::Error::msg)?;
    let prom = prometheus();
    let listener = tokio::net::TcpListener::bind(&config.listen)
        .await
        .with_context(|| format!("listen {}", config.listen))?;
    let addr = listener.local_addr()?;
    if !addr.ip().is_loopback() && !config.insecure {
        anyhow::bail!(
            "listen {}: {addr} is reachable from other machines and no client is authenticated; \
             listen on loopback (127.0.0.1) or pass --insecure (config \"insecure\": true)",
            config.listen
        );
    }
    let metrics_addr = match (&config.metrics_listen, prom) {
        (Some(a), Some(h)) => Some(metrics_http::serve(a, h).await?),
        (Some(_), None) => {
            tracing::warn!("another metrics recorder is installed; no /metrics endpoint");
            None
        }
        _ => None,
    };
    let (health, health_svc) = tonic_health::server::health_reporter();
    health
        .set_service_status("", ServingStatus::NotServing)
        .await;
    health
        .set_service_status(SERVICE_NAME, ServingStatus::NotServing)
        .await;
    let (drain_tx, drain_rx) = watch::channel(false);
    let shared = Arc::new(Shared {
        engine: compute::Engine::new(config.slots(), config.max_queued),
        sessions: Arc::new(Semaphore::new(config.max_sessions)),
        drain: drain_rx,
        next_session: AtomicU64::new(0),
        cases: OnceLock::new(),
        config: config.clone(),
    });
    let svc = LibRPlusServer::new(Svc(shared.clone()))
        .max_decoding_message_size(config.max_message_bytes)
        .max_encoding_message_size(config.max_message_bytes);
    let request_ids = Arc::new(AtomicU64::new(0));
    // The gRPC server is built once per TLS configuration (a "generation"): a certificate reload
    // starts a new generation for new connections while the old one finishes its connections'
    // streams (graceful shutdown: GOAWAY, open sessions go on), so no session is dropped.
    let make = move |tls: Option<tonic::transport::ServerTlsConfig>| -> anyhow::Result<_> {
        let reflection = || {
            tonic_reflection::server::Builder::configure()
                .register_encoded_file_descriptor_set(librplus_proto::FILE_DESCRIPTOR_SET)
                .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        };
        let mut builder = Server::builder();
        if let Some(tls) = tls {
            builder = builder
                .tls_config(tls)
                .context("TLS configuration (--tls-cert, --tls-key, --client-ca)")?;
        }
        let ids = request_ids.clone();
        Ok(builder
            .trace_fn(move |req: &tonic::codegen::http::Request<()>| {
                let id = req
                    .headers()
                    .get("x-request-id")
                    .and_then(|v| v.to_str().ok())
                    .map(|s| s.chars().take(64).collect::<String>())
                    .unwrap_or_else(|| format!("r{}", ids.fetch_add(1, Ordering::Relaxed) + 1));
                tracing::info_span!("rpc", path = %req.uri().path(), request_id = %id)
            })
            .add_service(health_svc.clone())
            .add_service(reflection().build_v1()?)
            .add_service(reflection().build_v1alpha()?)
            .add_service(svc.clone()))
    };
    let first = make(tls_config(&config)?)?;
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let (reload_tx, reload_rx) = tokio::sync::mpsc::channel::<Reload>(1);
    let serve = tokio::spawn(generations::serve(
        listener, first, make, reload_rx, stop_rx,
    ));
    tracing::info!(
        %addr,
        tls = config.tls_cert.is_some(),
        client_certificates = config.client_ca.is_some(),
        "listening (health NOT_SERVING until preload finishes)"
    );
    let (ready_tx, ready_rx) = watch::channel(None);
    {
        let shared = shared.clone();
        let health = health.clone();
        tokio::spawn(async move {
            let cfg = shared.config.clone();
            let report = tokio::task::spawn_blocking(move || preload(&cfg)).await;
            let report = match report {
                Ok(Ok((cases, report))) => {
                    let _ = shared.cases.set(cases);
                    health.set_service_status("", ServingStatus::Serving).await;
                    health
                        .set_service_status(SERVICE_NAME, ServingStatus::Serving)
                        .await;
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
                Err(e) => Err(Arc::new(PreloadError::Task(e.to_string()))),
            };
            let _ = ready_tx.send(Some(report));
        });
    }
    Ok(Running {
        addr,
        metrics_addr,
        shared,
        drain: drain_tx,
        stop: Some(stop_tx),
        serve,
        reload: reload_tx,
        ready: ready_rx,
        health,
    })
}

/// A TLS reload request: the new settings, and where to say whether they took.
type Reload = (
    tonic::transport::ServerTlsConfig,
    oneshot::Sender<Result<(), String>>,
);

mod generations {
    //! One listener, successive gRPC servers ("generations") for successive TLS settings.

    use super::Reload;
    use std::convert::Infallible;
    use tokio::net::{TcpListener, TcpStream};
    use tokio::sync::{mpsc, oneshot};
    use tokio_stream::wrappers::ReceiverStream;
    use tonic::transport::server::Router;

    type Conn = Result<TcpStream, Infallible>;

    /// One generation: its connections' channel, its stop signal and its task.
    struct Generation {
        conns: mpsc::Sender<Conn>,
        stop: oneshot::Sender<()>,
        task: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
    }

    fn spawn(router: Router) -> Generation {
        let (conns, rx) = mpsc::channel::<Conn>(64);
        let (stop, stop_rx) = oneshot::channel::<()>();
        let task = tokio::spawn(router.serve_with_incoming_shutdown(
            ReceiverStream::new(rx),
            async {
                let _ = stop_rx.await;
            },
        ));
        Generation { conns, stop, task }
    }

    /// Accepts connections for the current generation; on a reload, starts the next and lets
    /// the previous finish its connections; on stop, stops them all.
    pub(super) async fn serve(
        listener: TcpListener,
        first: Router,
        make: impl Fn(Option<tonic::transport::ServerTlsConfig>) -> anyhow::Result<Router>,
        mut reload: mpsc::Receiver<Reload>,
        mut stop: oneshot::Receiver<()>,
    ) -> Result<(), tonic::transport::Error> {
        let mut current = spawn(first);
        let mut old: Vec<Generation> = Vec::new();
        loop {
            tokio::select! {
                _ = &mut stop => break,
                r = reload.recv() => {
                    let Some((tls, done)) = r else { break };
                    match make(Some(tls)) {
                        Ok(router) => {
                            let previous = std::mem::replace(&mut current, spawn(router));
                            let _ = previous.stop.send(());
                            old.push(Generation { stop: oneshot::channel().0, ..previous });
                            old.retain(|g| !g.task.is_finished());
                            tracing::info!("TLS settings reloaded; open connections keep the old ones");
                            let _ = done.send(Ok(()));
                        }
                        Err(e) => {
                            tracing::warn!(error = %e, "TLS reload failed; the settings are unchanged");
                            let _ = done.send(Err(format!("{e:#}")));
                        }
                    }
                }
                a = listener.accept() => match a {
                    Ok((s, _)) => {
                        let _ = s.set_nodelay(true);
                        let _ = current.conns.send(Ok(s)).await;
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "accept failed");
                        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
                    }
                }
            }
        }
        let _ = current.stop.send(());
        let mut result = current.task.await.unwrap_or(Ok(()));
        for g in old {
            if let Ok(Err(e)) = g.task.await {
                result = Err(e);
            }
        }
        result
    }
}

/// The server's TLS settings from `tls_cert`/`tls_key` (and `client_ca` for mTLS); None:
/// plaintext. A file that cannot be read is an error naming it.
fn tls_config(config: &ServerConfig) -> anyhow::Result<Option<tonic::transport::ServerTlsConfig>> {
    use tonic::transport::{Certificate, Identity, ServerTlsConfig};
    let (Some(cert), Some(key)) = (&config.tls_cert, &config.tls_key) else {
        return Ok(None);
    };
    let read = |flag: &str, p: &std::path::Path| {
        std::fs::read(p).with_context(|| format!("{flag} {}: cannot read", p.display()))
    };
    let mut tls = ServerTlsConfig::new().identity(Identity::from_pem(
        read("--tls-cert", cert)?,
        read("--tls-key", key)?,
    ));
    if let Some(ca) = &config.client_ca {
        tls = tls.client_ca_root(Certificate::from_pem(read("--client-ca", ca)?));
    }
    Ok(Some(tls))
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

fn preload(
    config: &ServerConfig,
) -> Result<(BTreeMap<String, Arc<Case>>, PreloadReport), PreloadError> {
    let t0 = Instant::now();
    let found = cases::discover(config)?;
    let libr = LibrParams::default();
    let gcn = load_gcn(config)?;
    let mut out = BTreeMap::new();
    let mut report = PreloadReport {
        cases: Vec::new(),
        failed: Vec::new(),
        seconds: 0.0,
    };
    for (id, src) in &found {
        match cases::load(id, src, config, &libr, gcn.as_ref()) {
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
                out.insert(id.clone(), Arc::new(c));
            }
            Err(e) => {
                tracing::error!(case = %id, error = %e, "case failed to load; skipped");
                report.failed.push((id.clone(), e.to_string()));
            }
        }
    }
    if out.is_empty() {
        return Err(PreloadError::NoCase {
            found: found.len(),
            failed: report.failed,
        });
    }
    report.seconds = t0.elapsed().as_secs_f64();
    Ok((out, report))
}

impl Running {
    /// Waits for preload to finish; its report, or why it failed.
    pub async fn ready(&mut self) -> Result<PreloadReport, Arc<PreloadError>> {
        let r = self
            .ready
            .wait_for(|r| r.is_some())
            .await
            .map_err(|_| Arc::new(PreloadError::Ended))?;
        r.clone().expect("checked is_some")
    }

    /// Sessions open now.
    pub fn open_sessions(&self) -> usize {
        self.shared.config.max_sessions - self.shared.sessions.available_permits()
    }

    /// Reads the TLS files again (`tls_cert`, `tls_key`, `client_ca`) and serves new connections
    /// with them; open connections and their sessions go on with the old ones until they end
    /// (SIGHUP in `librplus-server`). An error (a file that does not read, a server without TLS)
    /// changes nothing.
    pub async fn reload_tls(&self) -> anyhow::Result<()> {
        let Some(tls) = tls_config(&self.shared.config)? else {
            anyhow::bail!("the server does not serve TLS (no --tls-cert): nothing to reload");
        };
        let (tx, rx) = oneshot::channel();
        self.reload
            .send((tls, tx))
            .await
            .map_err(|_| anyhow::anyhow!("the server has stopped"))?;
        rx.await
            .map_err(|_| anyhow::anyhow!("the server has stopped"))?
            .map_err(anyhow::Error::msg)
    }

    /// Drains and stops: health NOT_SERVING, sessions end after their current update, the
    /// transport closes (waiting `drain_grace_s` at most). Returns the sessions still open when
    /// the grace ran out (0 on a clean drain).
    pub async fn shutdown(mut self) -> usize {
        tracing::info!("shutting down: draining sessions");
        self.health
            .set_service_status("", ServingStatus::NotServing)
            .await;
        self.health
            .set_service_status(SERVICE_NAME, ServingStatus::NotServing)
            .await;
        let _ = self.drain.send(true);
        let grace = Duration::from_secs_f64(self.shared.config.drain_grace_s);
        let t0 = Instant::now();
        // Sessions end after their update in flight.
        while self.open_sessions() > 0 && t0.elapsed() < grace {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let left = self.open_sessions();
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        let rest = grace
            .saturating_sub(t0.elapsed())
            .max(Duration::from_millis(100));
        match tokio::time::timeout(rest, &mut self.serve).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => tracing::warn!(error = %e, "transport ended with an error"),
            Ok(Err(e)) => tracing::warn!(error = %e, "serve task failed"),
            Err(_) => {
                tracing::warn!("connections still open after the drain grace; closing");
                self.serve.abort();
            }
        }
        tracing::info!(left, "stopped");
        left
    }
}
