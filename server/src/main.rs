//! `librplus-server`: serve preloaded cases over gRPC (`serve`, the default).

use anyhow::Result;
use clap::Parser;
use librplus_server::config::ServerConfig;
use std::path::PathBuf;

/// LIBR+ registration server.
#[derive(Parser, Debug)]
#[command(version, about)]
struct Args {
    /// JSON config file (format 1; see the README). Flags override it.
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
    /// Log JSON lines.
    #[arg(long)]
    log_json: bool,
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
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let b = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if json {
        b.json().init();
    } else {
        b.init();
    }
}

#[tokio::main]
async fn main() -> Result<()> {
    let args = Args::parse();
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
    tokio::select! {
        _ = term.recv() => {}
        _ = tokio::signal::ctrl_c() => {}
    }
    let left = running.shutdown().await;
    if left > 0 {
        eprintln!("{left} session(s) were still open after the drain grace");
    }
    Ok(())
}
