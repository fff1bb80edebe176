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
        /// Scenarios replayed with in-surgery discovery, side by side with the other sessions
        /// (those with the most points, one deformation after another; 0: every scenario).
        #[arg(long, default_value_t = demo::DISCOVERY_SCENARIOS)]
        discovery_scenarios: usize,
        /// Only make the default case (into --data) and exit: to serve it from elsewhere, e.g.
        /// a container (docs/deploy.md).
        #[arg(long)]
        only_data: bool,
    },
    #[cfg(feature = "igtl")]
    /// OpenIGTLink bridge for navigation software (3D Slicer's OpenIGTLinkIF, PLUS, ...): each
    /// connection is a registration session on the gRPC server; POINT (surface points) and
    /// POLYDATA + TRANSFORM (ultrasound plane points and pose) in; TRANSFORM, target POINT and
    /// liver POLYDATA out after every registration, STATUS on errors (docs/igtl.md).
    Igtl(Box<IgtlArgs>),
    /// Read the audit log: every registration, session and refusal (of a case, since a time),
    /// or export a session's points for `librplus discover`.
    Audit {
        /// The audit database (`--audit` of the server).
        #[arg(long)]
        db: PathBuf,
        /// Only this case.
        #[arg(long)]
        case: Option<String>,
        /// Only records since this time: Unix seconds or YYYY-MM-DD[THH:MM[:SS]] (UTC).
        #[arg(long)]
        since: Option<String>,
        /// JSON lines instead of a table.
        #[arg(long)]
        json: bool,
        /// Write this session's points as a sweep folder (`librplus discover --preop MESH
        /// --scenarios PARENT`) into --out.
        #[arg(long, value_name = "SESSION_ID", requires = "out")]
        export: Option<String>,
        /// Folder of the exported sweep.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    #[cfg(feature = "demo")]
    /// Write a CA, a server certificate for `localhost` and client certificates into a folder
    /// (PEM; for tests, benchmarks and trials, not for a hospital's certificates).
    DevCerts {
        /// The folder (created).
        #[arg(long)]
        out: PathBuf,
        /// A client certificate with this common name (repeatable; default `client`).
        #[arg(long = "client")]
        clients: Vec<String>,
    },
    /// Ask a server's health (grpc.health.v1 Check): exit 0 when it is SERVING (every case
    /// preloaded), 1 otherwise. The image's HEALTHCHECK and the Kubernetes probes; the
    /// LIBRPLUS_HEALTH_* variables set the options in a container.
    Health {
        /// The server (https:// for TLS).
        #[arg(
            long,
            env = "LIBRPLUS_HEALTH_URL",
            default_value = "http://127.0.0.1:50051"
        )]
        url: String,
        /// TLS: the CA certificate (PEM) the server's certificate chains to.
        #[arg(long, env = "LIBRPLUS_HEALTH_CA", value_name = "FILE")]
        ca: Option<PathBuf>,
        /// TLS: the name the server's certificate carries (default: the URL's host).
        #[arg(long, env = "LIBRPLUS_HEALTH_DOMAIN")]
        domain: Option<String>,
        /// A file holding a bearer token (where the auth file closes health).
        #[arg(long, env = "LIBRPLUS_HEALTH_TOKEN_FILE", value_name = "FILE")]
        token_file: Option<PathBuf>,
        /// Liveness: exit 0 whenever the server answers, NOT_SERVING too (preloading or
        /// draining is alive).
        #[arg(long)]
        alive: bool,
        /// Longest wait for the answer, seconds.
        #[arg(long, default_value_t = 3.0)]
        timeout_s: f64,
    },
    /// Make a new random bearer token: prints the token (give it to the client; it is shown
    /// once) and the auth file entry that holds only its SHA-256.
    Token {
        /// The principal the token stands for.
        #[arg(long)]
        principal: String,
        /// Cases it may use: ids, or prefixes ending in `*` (repeatable; default `*`: all).
        #[arg(long = "case")]
        cases: Vec<String>,
        /// Its roles: read, register, manage (repeatable; default register).
        #[arg(long = "role")]
        roles: Vec<String>,
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
    /// V2S model directory (`librplus train --method v2s`) for METHOD_V2S (default: the
    /// built-in V2S model).
    #[arg(long)]
    v2s_model: Option<PathBuf>,
    /// Load no V2S model (METHOD_V2S requests get FAILED_PRECONDITION).
    #[arg(long)]
    no_v2s: bool,
    /// Prepare adaptive LIBR's multi-level basis for every case (the default; kept for older
    /// command lines).
    #[arg(long, conflicts_with = "no_adaptive")]
    adaptive: bool,
    /// Do not prepare adaptive LIBR's basis (a shorter preload, less memory): METHOD_ADAPTIVE is
    /// then FAILED_PRECONDITION and METHOD_AUTO chooses without adaptive LIBR.
    #[arg(long)]
    no_adaptive: bool,
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
    /// Authentication and authorization file (JSON: principals, token hashes, cases, roles;
    /// see docs/service.md). Reloaded on SIGHUP.
    #[arg(long, value_name = "FILE")]
    auth: Option<PathBuf>,
    /// Audit log database (SQLite, created when absent): every registration is recorded before
    /// it is answered; sessions resume from it.
    #[arg(long, value_name = "FILE")]
    audit: Option<PathBuf>,
    /// Session journal folder shared by the replicas (needs --audit): any replica resumes a
    /// session another one served.
    #[arg(long, value_name = "DIR")]
    session_journal: Option<PathBuf>,
    /// Case store folder: cases uploaded over the API (CreateCase) are kept there and reloaded
    /// at start.
    #[arg(long, value_name = "DIR")]
    case_store: Option<PathBuf>,
}

fn config(a: &Args) -> Result<ServerConfig> {
    let mut c = match &a.config {
        // Checked after the flags are applied: a flag may give what the file leaves out.
        Some(p) => ServerConfig::read_file(p)?,
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
    if a.auth.is_some() {
        c.auth = a.auth.clone();
    }
    if a.audit.is_some() {
        c.audit_db = a.audit.clone();
    }
    if a.session_journal.is_some() {
        c.session_journal = a.session_journal.clone();
    }
    if a.case_store.is_some() {
        c.case_store = a.case_store.clone();
    }
    if a.model.is_some() {
        c.model = a.model.clone();
    }
    if a.no_librplus {
        c.librplus = false;
    }
    if a.v2s_model.is_some() {
        c.v2s_model = a.v2s_model.clone();
    }
    if a.no_v2s {
        c.v2s = false;
    }
    if a.adaptive {
        c.adaptive = true;
    }
    if a.no_adaptive {
        c.adaptive = false;
    }
    if a.metrics_listen.is_some() {
        c.metrics_listen = a.metrics_listen.clone();
    }
    if a.cache_dir.is_some() {
        c.cache_dir = a.cache_dir.clone();
    }
    c.log_json |= a.log_json;
    c.validate().map_err(|e| match &a.config {
        Some(p) => anyhow::anyhow!("configuration ({} and the flags): {e}", p.display()),
        None => anyhow::anyhow!("configuration: {e}"),
    })?;
    Ok(c)
}

fn init_tracing(json: bool) {
    init_tracing_level(json, "info");
}

/// `librplus-server igtl`.
#[cfg(feature = "igtl")]
#[derive(clap::Args, Debug)]
struct IgtlArgs {
    /// Address the OpenIGTLink server listens on (18944 is OpenIGTLink's usual port).
    #[arg(long, default_value = "127.0.0.1:18944")]
    listen: std::net::SocketAddr,
    /// The LIBR+ gRPC server.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    server: String,
    /// The case every session registers.
    #[arg(long = "case")]
    case_id: String,
    /// Method: rigid, libr, libr_plus, v2s, default.
    #[arg(long, default_value = "default")]
    method: String,
    /// The peer's patient frame: ras (3D Slicer) or lps (LIBR+, DICOM).
    #[arg(long, default_value = "ras")]
    frame: String,
    /// Targets sent back where each registration puts them: a 3D Slicer markups file
    /// (.mrk.json) in the preoperative image's frame.
    #[arg(long, value_name = "FILE")]
    targets: Option<PathBuf>,
    /// Time budget per registration, ms (0: the server's default).
    #[arg(long, default_value_t = 0)]
    time_budget_ms: u32,
    /// Largest OpenIGTLink message body accepted, bytes.
    #[arg(long, default_value_t = 64 << 20)]
    max_body: u64,
    /// Most OpenIGTLink connections served at once (each holds at most one gRPC session);
    /// more are answered with STATUS 6 (busy) and closed. Keep it below the server's
    /// max_sessions (default 8) so that the bridge cannot take every session slot.
    #[arg(long, default_value_t = librplus_server::igtl::bridge::DEFAULT_MAX_SESSIONS)]
    max_sessions: usize,
    /// A connection with no session yet (no POINT or POLYDATA received: it holds none) that
    /// sends no complete message for this long is sent STATUS 7 (time-out) and closed, s.
    #[arg(long, default_value_t = librplus_server::igtl::bridge::DEFAULT_IDLE_TIMEOUT_S)]
    idle_timeout_s: f64,
    /// The same once its session is open, s (the server's own session_idle_timeout_s also
    /// applies).
    #[arg(long, default_value_t = librplus_server::igtl::bridge::DEFAULT_SESSION_IDLE_TIMEOUT_S)]
    session_idle_timeout_s: f64,
    /// Bearer token for the gRPC server.
    #[arg(long, env = "LIBRPLUS_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// TLS: the CA certificate (PEM) of the gRPC server.
    #[arg(long, value_name = "FILE")]
    ca: Option<PathBuf>,
    /// mTLS: this bridge's certificate (PEM; with --key).
    #[arg(long, value_name = "FILE")]
    cert: Option<PathBuf>,
    /// mTLS: this bridge's private key (PEM).
    #[arg(long, value_name = "FILE")]
    key: Option<PathBuf>,
}

#[cfg(feature = "igtl")]
async fn igtl(a: IgtlArgs) -> anyhow::Result<()> {
    use librplus_server::igtl::bridge::{BridgeConfig, Frame, read_targets, run, timeout_of};
    let frame = match a.frame.to_ascii_lowercase().as_str() {
        "ras" => Frame::Ras,
        "lps" => Frame::Lps,
        other => anyhow::bail!("--frame {other:?}: ras or lps"),
    };
    let cfg = BridgeConfig {
        server: a.server,
        tls: librplus_client::Tls {
            ca: a.ca,
            cert: a.cert,
            key: a.key,
            domain: None,
        },
        token: a.token,
        case_id: a.case_id,
        method: librplus_client::parse_method(&a.method)
            .map_err(|e| anyhow::anyhow!("--method: {e}"))?,
        time_budget_ms: a.time_budget_ms,
        frame,
        targets: match &a.targets {
            Some(p) => read_targets(p)?,
            None => Vec::new(),
        },
        max_body: a.max_body,
        max_sessions: match a.max_sessions {
            0 => anyhow::bail!("--max-sessions 0: at least 1"),
            n => n,
        },
        idle_timeout: timeout_of("--idle-timeout-s", a.idle_timeout_s)?,
        session_idle_timeout: timeout_of("--session-idle-timeout-s", a.session_idle_timeout_s)?,
    };
    eprintln!(
        "OpenIGTLink bridge on {} → {} (case {}, frame {:?}, {} targets; at most {} connections, idle timeout {} s, {} s in session)",
        a.listen,
        cfg.server,
        cfg.case_id,
        cfg.frame,
        cfg.targets.len(),
        cfg.max_sessions,
        cfg.idle_timeout.as_secs_f64(),
        cfg.session_idle_timeout.as_secs_f64()
    );
    run(a.listen, cfg).await
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

/// Runs the command; an error ends the program with its message (its causes on the same line, no
/// backtrace) and exit status 1.
fn main() -> std::process::ExitCode {
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let r = runtime.block_on(cli());
    // A registration still computing (an error cut the command short) is not waited for long.
    runtime.shutdown_timeout(std::time::Duration::from_secs(5));
    match r {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", error_line(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

/// An error and its causes on one line, each said once (a cause whose words are already in the
/// line is left out).
fn error_line(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if text.is_empty() || line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// The command line's command.
async fn cli() -> Result<()> {
    let cli = Cli::parse();
    let args = match cli.command {
        #[cfg(feature = "demo")]
        Some(Command::Demo {
            data,
            surface,
            scenarios,
            json,
            no_discovery,
            discovery_scenarios,
            only_data,
        }) => {
            init_tracing_level(false, "warn");
            let o = demo::DemoOptions {
                data: data.unwrap_or_else(demo::default_data_dir),
                surface,
                scenarios,
                json,
                discovery: !no_discovery,
                discovery_scenarios,
            };
            if only_data {
                return tokio::task::spawn_blocking(move || demo::ensure_dataset(&o)).await?;
            }
            return demo::run(o).await;
        }
        #[cfg(feature = "igtl")]
        Some(Command::Igtl(a)) => {
            init_tracing_level(false, "info");
            return igtl(*a).await;
        }
        Some(Command::Audit {
            db,
            case,
            since,
            json,
            export,
            out,
        }) => return audit(&db, case.as_deref(), since.as_deref(), json, export, out),
        #[cfg(feature = "demo")]
        Some(Command::DevCerts { out, clients }) => {
            std::fs::create_dir_all(&out)?;
            let names: Vec<&str> = if clients.is_empty() {
                vec!["client"]
            } else {
                clients.iter().map(String::as_str).collect()
            };
            let (ca, server, clients) = demo::dev_certs(&out, "LIBR+ development CA", &names)?;
            eprintln!(
                "CA {}, server {} / {}, {} client certificate(s) in {}",
                ca.display(),
                server.0.display(),
                server.1.display(),
                clients.len(),
                out.display()
            );
            return Ok(());
        }
        Some(Command::Token {
            principal,
            cases,
            roles,
        }) => return token(principal, cases, roles),
        Some(Command::Health {
            url,
            ca,
            domain,
            token_file,
            alive,
            timeout_s,
        }) => return health(&url, ca, domain, token_file, alive, timeout_s).await,
        Some(Command::Serve(a)) => *a,
        None => cli.serve,
    };
    let cfg = config(&args)?;
    let (has_tls, has_auth) = (cfg.tls_cert.is_some(), cfg.auth.is_some());
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
    // SIGHUP: read the TLS files (new connections use them; open sessions go on) and the auth
    // file again.
    let mut hup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())?;
    loop {
        tokio::select! {
            _ = term.recv() => break,
            _ = tokio::signal::ctrl_c() => break,
            _ = hup.recv() => {
                if has_tls {
                    match running.reload_tls().await {
                        Ok(()) => eprintln!("SIGHUP: TLS certificate files reloaded"),
                        Err(e) => eprintln!("SIGHUP: TLS reload failed, settings unchanged: {e:#}"),
                    }
                }
                if has_auth {
                    match running.reload_auth() {
                        Ok(()) => eprintln!("SIGHUP: auth file reloaded"),
                        Err(e) => eprintln!("SIGHUP: auth reload failed, principals unchanged: {e:#}"),
                    }
                }
            }
        }
    }
    let left = running.shutdown().await;
    if left > 0 {
        eprintln!("{left} session(s) were still open after the drain grace");
    }
    Ok(())
}

/// `librplus-server health`: grpc.health.v1 Check of the whole server.
async fn health(
    url: &str,
    ca: Option<PathBuf>,
    domain: Option<String>,
    token_file: Option<PathBuf>,
    alive: bool,
    timeout_s: f64,
) -> Result<()> {
    use anyhow::Context;
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    if !(timeout_s.is_finite() && timeout_s > 0.0) {
        anyhow::bail!("--timeout-s must be a positive number of seconds, got {timeout_s}");
    }
    let timeout = std::time::Duration::from_secs_f64(timeout_s);
    let tls = url.starts_with("https://") || ca.is_some();
    let url = match url.strip_prefix("http://") {
        Some(rest) if tls => format!("https://{rest}"),
        _ => url.to_string(),
    };
    let mut ep = tonic::transport::Endpoint::from_shared(url.clone())
        .with_context(|| format!("--url {url:?} is not a URL"))?
        .connect_timeout(timeout)
        .timeout(timeout);
    if tls {
        let ca = ca.context("--ca: TLS needs the CA certificate the server's chains to")?;
        let pem = std::fs::read(&ca).with_context(|| format!("--ca {}", ca.display()))?;
        let mut c = tonic::transport::ClientTlsConfig::new()
            .ca_certificate(tonic::transport::Certificate::from_pem(pem));
        if let Some(d) = domain {
            c = c.domain_name(d);
        }
        ep = ep.tls_config(c).context("TLS settings")?;
    }
    let ch = ep
        .connect()
        .await
        .with_context(|| format!("{url}: no connection"))?;
    let mut req = tonic::Request::new(HealthCheckRequest::default());
    if let Some(f) = token_file {
        let t =
            std::fs::read_to_string(&f).with_context(|| format!("--token-file {}", f.display()))?;
        req.metadata_mut().insert(
            "authorization",
            format!("Bearer {}", t.trim())
                .parse()
                .context("--token-file: the token must be printable ASCII")?,
        );
    }
    match HealthClient::new(ch).check(req).await {
        Ok(r) => {
            let status = r.into_inner().status();
            if status == ServingStatus::Serving || alive {
                println!("{}", status.as_str_name());
                Ok(())
            } else {
                anyhow::bail!("{url}: {}", status.as_str_name())
            }
        }
        // An answer that refuses the caller still shows a live server.
        Err(s) if alive && s.code() != tonic::Code::Unavailable => {
            println!("answered {:?}", s.code());
            Ok(())
        }
        Err(s) => anyhow::bail!("{url}: {:?}: {}", s.code(), s.message()),
    }
}

/// `librplus-server token`: a new token, and its auth file entry (the hash only).
fn token(principal: String, cases: Vec<String>, roles: Vec<String>) -> Result<()> {
    use librplus_server::auth::{AuthFile, PrincipalEntry, Role, new_token};
    let roles = if roles.is_empty() {
        vec!["register".to_string()]
    } else {
        roles
    };
    let roles = roles
        .iter()
        .map(|r| match r.as_str() {
            "read" => Ok(Role::Read),
            "register" => Ok(Role::Register),
            "manage" => Ok(Role::Manage),
            _ => Err(anyhow::anyhow!(
                "--role {r:?}: expected read, register or manage"
            )),
        })
        .collect::<Result<Vec<_>>>()?;
    let (token, hash) = new_token()?;
    let entry = PrincipalEntry {
        principal,
        token_sha256: vec![hash],
        certificate_subjects: Vec::new(),
        cases: if cases.is_empty() {
            vec!["*".into()]
        } else {
            cases
        },
        roles,
        max_sessions: 0,
    };
    // The entry must make a valid file on its own.
    librplus_server::auth::Auth::from_file(AuthFile {
        format: 1,
        open_health: true,
        open_reflection: true,
        principals: vec![entry.clone()],
    })?;
    eprintln!("token (give it to the client; it is not stored anywhere):");
    println!("{token}");
    eprintln!("auth file entry (add it to \"principals\"):");
    eprintln!("{}", serde_json::to_string_pretty(&entry)?);
    Ok(())
}

/// `s` with control characters (C0, DEL, C1) and the invisible characters that reorder or hide
/// text (bidirectional overrides and isolates, zero-width marks) escaped as `\u{..}`, and a
/// backslash doubled, so that a printed line is exactly one line and shows what is stored.
fn printable(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        let hidden = matches!(c, '\u{200b}'..='\u{200f}' | '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}' | '\u{feff}');
        if c == '\\' {
            out.push_str("\\\\");
        } else if c.is_control() || hidden {
            out.push_str(&format!("\\u{{{:x}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}

/// `librplus-server audit`.
fn audit(
    db: &std::path::Path,
    case: Option<&str>,
    since: Option<&str>,
    json: bool,
    export: Option<String>,
    out: Option<PathBuf>,
) -> Result<()> {
    use librplus_server::audit;
    if !db.exists() {
        anyhow::bail!("--db {}: no such file", db.display());
    }
    let c = audit::open_db(db)?;
    if let (Some(id), Some(out)) = (export, out) {
        let e = audit::export_session(&c, &id, &out)?;
        eprintln!(
            "session {} (case {}): {} messages, {} surface, {} contour, {} vessel points -> {}",
            printable(&id),
            printable(&e.case_id),
            e.messages,
            e.surface,
            e.contour,
            e.vessel,
            out.display()
        );
        if json {
            println!("{}", serde_json::to_string(&e)?);
        }
        return Ok(());
    }
    let since = since.map(audit::parse_since).transpose()?;
    let rows = audit::rows(&c, case, since)?;
    for r in &rows {
        if json {
            println!("{}", serde_json::to_string(r)?);
        } else {
            let detail = match r.kind.as_str() {
                "registration" => {
                    let d = &r.detail;
                    format!(
                        "seq {} {} {} {:.1} ms rms {:.2} mm {} pts sha256 {}",
                        d["client_seq"],
                        d["method"].as_str().unwrap_or("?"),
                        d["quality"].as_str().unwrap_or("?"),
                        d["total_ms"].as_f64().unwrap_or(f64::NAN),
                        d["residual_rms_mm"].as_f64().unwrap_or(f64::NAN),
                        d["points"],
                        &d["answer_sha256"].as_str().unwrap_or("")
                            [..12.min(d["answer_sha256"].as_str().map_or(0, str::len))]
                    )
                }
                _ => r.detail_text(),
            };
            // Case ids, principals and details come from clients: control characters (a
            // newline that would forge a line, an escape sequence for the terminal) are shown
            // escaped, as the JSON view does.
            println!(
                "{}  {:<16} {:<14} {:<18} {:<24} {}",
                r.time,
                printable(&r.kind),
                printable(&r.principal),
                printable(r.case_id.as_deref().unwrap_or("-")),
                printable(r.session_id.as_deref().unwrap_or("-")),
                printable(&detail),
            );
        }
    }
    if !json {
        eprintln!("{} records", rows.len());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    /// An error's line names each cause once, outermost first: a cause already said by the
    /// message above it is left out, a new one is added.
    #[test]
    fn an_error_line_says_each_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let e = anyhow::Error::new(io)
            .context("mesh.stl: no such file")
            .context("--surface mesh.stl");
        assert_eq!(
            super::error_line(&e),
            "--surface mesh.stl: mesh.stl: no such file"
        );
        let e = anyhow::anyhow!("the server closed the stream").context("1 of 3 session(s) failed");
        assert_eq!(
            super::error_line(&e),
            "1 of 3 session(s) failed: the server closed the stream"
        );
    }
}
