//! `librplus-server`: serve preloaded cases over gRPC (`serve`, the default), or run the demo
//! (`demo`: the default case, the server on loopback and the replay client).
#![forbid(unsafe_code)]

#[global_allocator]
static ALLOCATOR: librplus::GlobalAllocator = librplus::GlobalAllocator;

#[cfg(feature = "demo")]
mod demo;

use anyhow::Result;
use clap::{Parser, Subcommand};
use librplus_server::config::ServerConfig;
use std::path::PathBuf;

/// LIBR+ registration server.
#[derive(Parser, Debug)]
#[command(version, about, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    serve: Args,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Serve preloaded cases over gRPC (the default).
    Serve(Box<Args>),
    #[cfg(feature = "demo")]
    /// The main job on the embedded default case: generate it at first run (cached), start the
    /// server on loopback, replay scenarios through the client over gRPC, print TRE and latency.
    Demo {
        /// Where the default case lives (generated at first run).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Source liver surface of the phantom (default: the built-in SOFA liver).
        #[arg(long)]
        surface: Option<PathBuf>,
        /// Scenarios to replay (spread over deformations and measurement categories).
        #[arg(long, default_value_t = 10)]
        scenarios: usize,
        /// One JSON object on stdout.
        #[arg(long)]
        json: bool,
        /// Leave out the LIBR sessions with in-surgery discovery.
        #[arg(long)]
        no_discovery: bool,
    },
}

/// Serving options.
#[derive(clap::Args, Debug)]
struct Args {
    /// JSON config file (format 1; see docs/service.md). Flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Dataset directory or folder of meshes (repeatable).
    #[arg(long)]
    cases: Vec<PathBuf>,
    /// gRPC listen address.
    #[arg(long)]
    listen: Option<String>,
    /// Prometheus endpoint address (GET /metrics).
    #[arg(long)]
    metrics_listen: Option<String>,
    /// Most concurrent streamed sessions.
    #[arg(long)]
    max_sessions: Option<usize>,
    /// Default time budget per registration, ms.
    #[arg(long)]
    time_budget_ms: Option<u32>,
    /// Registrations computed at once (0: the number of cores).
    #[arg(long)]
    compute_slots: Option<usize>,
    /// LIBR basis cache directory.
    #[arg(long)]
    cache_dir: Option<PathBuf>,
    /// Length unit of plain mesh files (mm, cm, m).
    #[arg(long)]
    mesh_unit: Option<String>,
    /// SR-GCN model or ensemble directory for LIBR+ (default: the built-in model, when there is one).
    #[arg(long)]
    model: Option<PathBuf>,
    /// Method when a request leaves it unspecified (rigid, libr, librplus).
    #[arg(long)]
    default_method: Option<String>,
    /// Load no SR-GCN model (LIBR+ requests get FAILED_PRECONDITION).
    #[arg(long)]
    no_librplus: bool,
    /// Log JSON lines.
    #[arg(long)]
    log_json: bool,
    /// Default wall-clock limit of one in-surgery discovery run, ms.
    #[arg(long)]
    discovery_budget_ms: Option<u32>,
    /// In-surgery discovery on the coarse search grid (about 4× faster).
    #[arg(long)]
    discovery_coarse: bool,
    /// Allow a non-loopback listen address without client authentication.
    #[arg(long)]
    insecure: bool,
    /// Serve TLS with this certificate chain (PEM; needs --tls-key).
    #[arg(long, value_name = "FILE")]
    tls_cert: Option<PathBuf>,
    /// The TLS private key (PEM).
    #[arg(long, value_name = "FILE")]
    tls_key: Option<PathBuf>,
    /// Require client certificates signed by this CA (mTLS; PEM).
    #[arg(long, value_name = "FILE")]
    client_ca: Option<PathBuf>,
}

fn config(a: &Args) -> Result<ServerConfig> {
    let mut c = match &a.config {
        Some(p) => ServerConfig::from_file(p).map_err(anyhow::Error::msg)?,
        None => ServerConfig::default(),
    };
    if !a.cases.is_empty() {
        c.cases = a.cases.clone();
    }
    macro_rules! set {
        ($f:ident) => {
            if let Some(v) = &a.$f {
                c.$f = v.clone();
            }
        };
    }
    set!(listen);
    set!(max_sessions);
    set!(time_budget_ms);
    set!(compute_slots);
    set!(mesh_unit);
    set!(default_method);
    set!(discovery_budget_ms);
    c.discovery_coarse |= a.discovery_coarse;
    c.insecure |= a.insecure;
    if a.tls_cert.is_some() {
        c.tls_cert = a.tls_cert.clone();
    }
    if a.tls_key.is_some() {
        c.tls_key = a.tls_key.clone();
    }
    if a.client_ca.is_some() {
        c.client_ca = a.client_ca.clone();
    }
    if a.model.is_some() {
        c.model = a.model.clone();
    }
    if a.no_librplus {
        c.librplus = false;
    }
    if a.metrics_listen.is_some() {
        c.metrics_listen = a.metrics_listen.clone();
    }
    if a.cache_dir.is_some() {
        c.cache_dir = a.cache_dir.clone();
    }
    c.log_json |= a.log_json;
    c.validate()
        .map_err(|e| anyhow::anyhow!("configuration: {e}"))?;
    Ok(c)
}

fn init_tracing(json: bool) {
    init_tracing_level(json, "info");
}

fn init_tracing_level(json: bool, level: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level));
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr);
    if json {
        b.json().init();
    } else {
        b.init();
    }
}

#[tokio::main]
async fn main() -> Result<()> {
    let cli = Cli::parse();
    let args = match cli.command {
        #[cfg(feature = "demo")]
        Some(Command::Demo {
            data,
            surface,
            scenarios,
            json,
            no_discovery,
        }) => {
            init_tracing_level(false, "warn");
            return demo::run(demo::DemoOptions {
                data: data.unwrap_or_else(demo::default_data_dir),
                surface,
                scenarios,
                json,
                discovery: !no_discovery,
            })
            .await;
        }
        Some(Command::Serve(a)) => *a,
        None => cli.serve,
    };
    let cfg = config(&args)?;
    init_tracing(cfg.log_json);
    let mut running = librplus_server::start(cfg).await?;
    eprintln!("librplus-server listening on {}", running.addr);
    if let Some(m) = running.metrics_addr {
        eprintln!("metrics on http://{m}/metrics");
    }
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    tokio::select! {
        r = running.ready() => match r {
            Ok(rep) => eprintln!("preloaded {} case(s) in {:.1} s; serving", rep.cases.len(), rep.seconds),
            Err(e) => anyhow::bail!("preload failed: {e}"),
        },
        _ = term.recv() => { running.shutdown().await; return Ok(()); }
        _ = tokio::signal::ctrl_c() => { running.shutdown().await; return Ok(()); }
    }
    // SIGHUP: read the TLS files again (new connections use them; open sessions go on).
    let mut hup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())?;
    loop {
        tokio::select! {
            _ = term.recv() => break,
            _ = tokio::signal::ctrl_c() => break,
            _ = hup.recv() => match running.reload_tls().await {
                Ok(()) => eprintln!("SIGHUP: TLS certificate files reloaded"),
                Err(e) => eprintln!("SIGHUP: TLS reload failed, settings unchanged: {e:#}"),
            },
        }
    }
    let left = running.shutdown().await;
    if left > 0 {
        eprintln!("{left} session(s) were still open after the drain grace");
    }
    Ok(())
}
