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

pub mod access;
pub mod audit;
pub mod auth;
pub mod cases;
pub mod compute;
pub mod config;
pub mod connections;
pub mod convert;
pub mod counted;
pub mod discovery;
pub mod error;
pub mod fuzz;
pub mod igtl;
pub mod journal;
pub mod live;
pub mod metrics_http;
pub mod preload;
pub mod refine;
pub mod registry;
pub mod service;
pub(crate) mod session;
pub mod shared;
pub mod store;
pub mod upload;

pub use preload::{PreloadError, PreloadReport};
use preload::{Ready, set_health, spawn_preload};

use anyhow::Context;
use config::ServerConfig;
use librplus_proto::v1::lib_r_plus_server::LibRPlusServer;
use service::Svc;
use shared::Shared;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};
use tokio::sync::{oneshot, watch};
use tonic::transport::server::Router;
use tonic::transport::{Server, ServerTlsConfig};
use tonic_health::ServingStatus;
use tonic_health::pb::health_server::{Health, HealthServer};
use tonic_health::server::HealthReporter;

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
    ready: watch::Receiver<Ready>,
    health: HealthReporter,
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

/// Binds, serves, and starts preloading. Returns once the port is bound.
pub async fn start(config: ServerConfig) -> anyhow::Result<Running> {
    config.validate()?;
    let prom = prometheus();
    let listener = tokio::net::TcpListener::bind(&config.listen)
        .await
        .with_context(|| format!("listen {}", config.listen))?;
    let addr = listener.local_addr()?;
    let auth = load_auth(&config, addr)?;
    let metrics_addr = match (&config.metrics_listen, prom) {
        (Some(a), Some(h)) => Some(metrics_http::serve(a, h).await?),
        (Some(_), None) => {
            tracing::warn!("another metrics recorder is installed; no /metrics endpoint");
            None
        }
        _ => None,
    };
    let (health, health_svc) = tonic_health::server::health_reporter();
    set_health(&health, ServingStatus::NotServing).await;
    let (drain_tx, drain_rx) = watch::channel(false);
    let shared = open_shared(&config, auth, drain_rx)?;
    let make = router_maker(&config, &shared, health_svc);
    let first = make(tls_config(&config)?)?;
    let (stop_tx, stop_rx) = oneshot::channel::<()>();
    let (reload_tx, reload_rx) = tokio::sync::mpsc::channel::<Reload>(1);
    let gate = generations::Gate::new(
        shared.connections.clone(),
        config.max_connections,
        Duration::from_secs_f64(config.preface_timeout_s),
    );
    let serve = tokio::spawn(generations::serve(
        listener, gate, first, make, reload_rx, stop_rx,
    ));
    tracing::info!(
        %addr,
        tls = config.tls_cert.is_some(),
        client_certificates = config.client_ca.is_some(),
        auth = config.auth.is_some(),
        audit = config.audit_db.is_some(),
        "listening (health NOT_SERVING until preload finishes)"
    );
    let (ready_tx, ready_rx) = watch::channel(None);
    spawn_preload(shared.clone(), health.clone(), ready_tx);
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

/// Reads the auth file (`auth`, if any), and refuses to serve an address other machines reach
/// with no client authenticated unless `insecure` says so.
fn load_auth(config: &ServerConfig, addr: SocketAddr) -> anyhow::Result<Option<auth::Auth>> {
    let auth = config
        .auth
        .as_deref()
        .map(auth::Auth::load)
        .transpose()
        .context("--auth")?;
    if !addr.ip().is_loopback() && !config.insecure && auth.is_none() {
        anyhow::bail!(
            "listen {}: {addr} is reachable from other machines and no client is authenticated; \
             give an auth file (--auth), listen on loopback (127.0.0.1), or pass --insecure \
             (config \"insecure\": true)",
            config.listen
        );
    }
    Ok(auth)
}

/// Opens what every request shares: the session journal, the audit log (its folder created),
/// the case store, the compute engine, with `auth` and the drain signal.
fn open_shared(
    config: &ServerConfig,
    auth: Option<auth::Auth>,
    drain: watch::Receiver<bool>,
) -> anyhow::Result<Arc<Shared>> {
    let journal = config
        .session_journal
        .as_deref()
        .map(|d| {
            journal::Journal::open(d, &config::host_name(), config.session_journal_retention_h)
                .with_context(|| format!("session_journal {}", d.display()))
        })
        .transpose()?;
    let audit = config
        .audit_db
        .as_deref()
        .map(|p| {
            let p = ServerConfig::per_host(p);
            if let Some(dir) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)
                    .with_context(|| format!("audit_db: creating {}", dir.display()))?;
            }
            audit::Audit::open(&p, journal).context("--audit")
        })
        .transpose()?;
    let store = config
        .case_store
        .as_deref()
        .map(store::Store::open)
        .transpose()
        .context("--case-store")?;
    Ok(Arc::new(Shared::new(
        config.clone(),
        auth,
        audit,
        store,
        compute::Engine::new(config.slots(), config.max_queued),
        drain,
    )))
}

/// The function that builds the gRPC server for a TLS configuration (None: plaintext): health,
/// reflection (v1 and v1alpha) and the `librplus.v1.LibRPlus` service, each call in a span
/// named by its request id.
///
/// The gRPC server is built once per TLS configuration (a "generation"): a certificate reload
/// starts a new generation for new connections while the old one finishes its connections'
/// streams (graceful shutdown: GOAWAY, open sessions go on), so no session is dropped.
fn router_maker<H: Health>(
    config: &ServerConfig,
    shared: &Arc<Shared>,
    health_svc: HealthServer<H>,
) -> impl Fn(Option<ServerTlsConfig>) -> anyhow::Result<Router> + Send + 'static {
    // Requests are refused by their size before they are decoded (a few hundred kilobytes for
    // the point limits); replies (a described mesh) may be larger.
    let svc = LibRPlusServer::new(Svc(shared.clone()))
        .max_decoding_message_size(config.request_bytes())
        .max_encoding_message_size(config.max_message_bytes);
    // Health and reflection answer without credentials unless the auth file closes them.
    let gate = |health: bool| {
        let shared = shared.clone();
        move |req: tonic::Request<()>| -> Result<tonic::Request<()>, tonic::Status> {
            // A call without credentials keeps its connection from the idle timeout, not from
            // the bounds on unauthenticated connections.
            let (peer, calls) = (req.remote_addr(), &shared.connections);
            let Some(a) = shared.auth() else {
                calls.called(peer, false);
                return Ok(req);
            };
            if (health && a.open_health) || (!health && a.open_reflection) {
                calls.called(peer, false);
                return Ok(req);
            }
            let certs = req.peer_certs();
            let who = a.authenticate(req.metadata(), certs.as_deref().map(Vec::as_slice));
            calls.called(peer, who.is_ok());
            who.map_err(|e| e.to_status())?;
            Ok(req)
        }
    };
    let (health_gate, reflection_gate) = (gate(true), gate(false));
    let h2 = (
        config.max_streams_per_connection,
        Duration::from_secs_f64(config.keepalive_s),
    );
    let request_ids = Arc::new(AtomicU64::new(0));
    move |tls: Option<ServerTlsConfig>| -> anyhow::Result<_> {
        let reflection = || {
            tonic_reflection::server::Builder::configure()
                .register_encoded_file_descriptor_set(librplus_proto::FILE_DESCRIPTOR_SET)
                .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        };
        use tonic::service::interceptor::InterceptedService;
        let mut builder = Server::builder()
            .max_concurrent_streams(Some(h2.0))
            .http2_keepalive_interval(Some(h2.1))
            .http2_keepalive_timeout(Some(Duration::from_secs(20)));
        if let Some(tls) = tls {
            builder = builder
                .tls_config(tls)
                .context("TLS configuration (--tls-cert, --tls-key, --client-ca)")?;
        }
        let ids = request_ids.clone();
        Ok(builder
            .trace_fn(move |req: &tonic::codegen::http::Request<()>| rpc_span(&ids, req))
            .add_service(InterceptedService::new(
                health_svc.clone(),
                health_gate.clone(),
            ))
            .add_service(InterceptedService::new(
                reflection().build_v1()?,
                reflection_gate.clone(),
            ))
            .add_service(InterceptedService::new(
                reflection().build_v1alpha()?,
                reflection_gate.clone(),
            ))
            .add_service(svc.clone()))
    }
}

/// The span of one call: its path and request id (the caller's `x-request-id`, at most 64
/// characters, else the next of `ids`: `r1`, `r2`, ...).
fn rpc_span(ids: &AtomicU64, req: &tonic::codegen::http::Request<()>) -> tracing::Span {
    let id = req
        .headers()
        .get("x-request-id")
        .and_then(|v| v.to_str().ok())
        .map(|s| s.chars().take(64).collect::<String>())
        .unwrap_or_else(|| format!("r{}", ids.fetch_add(1, Ordering::Relaxed) + 1));
    tracing::info_span!("rpc", path = %req.uri().path(), request_id = %id)
}

/// A TLS reload request: the new settings, and where to say whether they took (or why not).
type Reload = (
    tonic::transport::ServerTlsConfig,
    oneshot::Sender<anyhow::Result<()>>,
);

mod generations;

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
    }

    /// Reads the auth file again (`auth`): later calls use the new principals; open sessions
    /// keep the principal they started with. An error (a file that does not read or check, a
    /// server without `--auth`) changes nothing.
    pub fn reload_auth(&self) -> anyhow::Result<()> {
        let (Some(path), Some(lock)) = (&self.shared.config.auth, &self.shared.auth) else {
            anyhow::bail!("the server has no auth file (no --auth): nothing to reload");
        };
        let a = auth::Auth::load(path)?;
        *lock.write().unwrap_or_else(|e| e.into_inner()) = Arc::new(a);
        tracing::info!(file = %path.display(), "auth file reloaded");
        Ok(())
    }

    /// Drains and stops: health NOT_SERVING, sessions end after their current update, the
    /// transport closes (waiting `drain_grace_s` at most). Returns the sessions still open when
    /// the grace ran out (0 on a clean drain).
    pub async fn shutdown(mut self) -> usize {
        tracing::info!("shutting down: draining sessions");
        set_health(&self.health, ServingStatus::NotServing).await;
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
