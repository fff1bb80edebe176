//! `librplus-client`: replay recorded dataset scenarios against a LIBR+ server, or load-test it.
#![forbid(unsafe_code)]

#[global_allocator]
static ALLOCATOR: librplus::GlobalAllocator = librplus::GlobalAllocator;

use anyhow::{Result, bail};
use clap::{Args, Parser, Subcommand};
use librplus_client::{
    LoadOptions, ReplayOptions, Selection, load, load_table, parse_method, parse_methods, pb,
    replay, replay_table,
};
use std::path::PathBuf;
use std::time::Duration;

/// LIBR+ gRPC client: replay of recorded scenarios and load test.
#[derive(Parser)]
#[command(name = "librplus-client", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Streams dataset scenarios (one session per scenario and method, in lockstep) and prints
    /// TRE and latency.
    Replay(ReplayArgs),
    /// Runs concurrent sessions for a fixed time; prints throughput, latency and errors by code.
    Load(LoadArgs),
    /// Uploads a preoperative case (a tetrahedral mesh, optional vessels and physics.json) and
    /// follows its preload to READY.
    Upload(UploadArgs),
    /// Deletes an uploaded case.
    Delete(DeleteArgs),
}

/// How to reach the server (every command).
#[derive(Args)]
struct Conn {
    /// Server URL. `replay` also takes replicas, comma-separated: sessions spread over them,
    /// and with --resume a lost session goes on on the next one.
    #[arg(long, default_value = "http://127.0.0.1:50051")]
    server: String,
    /// TLS: the CA certificate (PEM) the server's certificate chains to (turns TLS on; an
    /// http:// URL is then read as https://).
    #[arg(long, value_name = "FILE")]
    ca: Option<PathBuf>,
    /// mTLS: this client's certificate (PEM; with --key).
    #[arg(long, value_name = "FILE")]
    cert: Option<PathBuf>,
    /// mTLS: this client's private key (PEM).
    #[arg(long, value_name = "FILE")]
    key: Option<PathBuf>,
    /// TLS: the name the server's certificate must carry (default: the URL's host).
    #[arg(long)]
    tls_domain: Option<String>,
    /// Bearer token sent as `authorization` metadata.
    #[arg(long)]
    token: Option<String>,
}

impl Conn {
    fn tls(&self) -> librplus_client::Tls {
        librplus_client::Tls {
            ca: self.ca.clone(),
            cert: self.cert.clone(),
            key: self.key.clone(),
            domain: self.tls_domain.clone(),
        }
    }
}

#[derive(Args)]
struct UploadArgs {
    #[command(flatten)]
    conn: Conn,
    /// The case id (A-Z a-z 0-9 . _ - /).
    #[arg(long = "case")]
    case_id: String,
    /// Tetrahedral mesh (.vtu, .vtk, .msh; labels as its point data, as `librplus` writes them).
    #[arg(long)]
    mesh: PathBuf,
    /// Vessel centerlines (.vtp).
    #[arg(long)]
    vessels: Option<PathBuf>,
    /// The augmented model (`physics.json` of `librplus discover`).
    #[arg(long)]
    physics: Option<PathBuf>,
    /// Length unit of the mesh and vessels (mm, cm, m).
    #[arg(long, default_value = "mm")]
    unit: String,
    /// Return once stored, without following the preload.
    #[arg(long)]
    no_wait: bool,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct DeleteArgs {
    #[command(flatten)]
    conn: Conn,
    /// The case id.
    #[arg(long = "case")]
    case_id: String,
}

/// Options of both commands.
#[derive(Args)]
struct Common {
    #[command(flatten)]
    conn: Conn,
    /// Dataset directory (as written by `librplus generate`).
    #[arg(long)]
    data: PathBuf,
    /// Scenario ids DEFORMATION_ID/INDEX, comma-separated, or `all` (default: --limit of them,
    /// spread over deformations and categories).
    #[arg(long)]
    scenarios: Option<String>,
    /// Number of scenarios when --scenarios is not given.
    #[arg(long, default_value_t = 10)]
    limit: usize,
    /// Surface points per SurfaceBatch message (0: all in one).
    #[arg(long, default_value_t = 100)]
    batch: usize,
    /// Time budget per registration sent in SessionStart, ms (default: the server's).
    #[arg(long)]
    time_budget_ms: Option<u32>,
    /// The initial alignment is trusted to this uncertainty (mm, RMS over the organ): the
    /// server regularises the rigid motion towards it (an organ held in place).
    #[arg(long, value_name = "MM")]
    trusted_alignment: Option<f64>,
    /// The organ is held in place and the start trusted: the server trusts the start (to 5 mm
    /// unless --trusted-alignment says otherwise), skips the pose search and holds the surface
    /// the points do not come near
    #[arg(long)]
    held: bool,
    /// METHOD_NONLINEAR answers once, with the refined answer, instead of the linear answer
    /// at once and its refinement after it
    #[arg(long)]
    single_answer: bool,
    /// Resume a session whose stream is lost (the server restarted or the network dropped):
    /// reconnect with backoff and go on from what the server recorded (it needs --audit).
    #[arg(long)]
    resume: bool,
    /// Most reconnections of one session in a row without an answer (replay, with --resume).
    #[arg(long, default_value_t = 10)]
    resume_attempts: u32,
    /// Longest wait for a stream to open and for each answer, seconds.
    #[arg(long, default_value_t = 120.0)]
    timeout_s: f64,
    /// Print one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct ReplayArgs {
    #[command(flatten)]
    common: Common,
    /// Methods, comma-separated: rigid, libr, libr_plus, default.
    #[arg(long, default_value = "libr")]
    methods: String,
    /// At most this many messages per second.
    #[arg(long)]
    rate: Option<f64>,
    /// Methods replayed once more with in-surgery discovery (comma-separated; reported as
    /// `METHOD+discovery`): after its last points the session asks the server to discover on
    /// all of them and takes the augmented model when an effect is named.
    #[arg(long, default_value = "")]
    discover_with: String,
    /// Time limit of each discovery run, ms (0: the server's default).
    #[arg(long, default_value_t = 0)]
    discovery_budget_ms: u32,
    /// Replay the sessions with discovery on this many of the scenarios only (those with the
    /// most points, one deformation after another; 0: every one).
    #[arg(long, default_value_t = 0)]
    discover_scenarios: usize,
    /// Sessions with discovery replayed at once, beside the others (they still send in turn
    /// with them, `--concurrency` at a time, and wait for their runs side by side); 0: one
    /// after another with the others.
    #[arg(long, default_value_t = 0)]
    discovery_concurrency: usize,
    /// Sessions replayed at once.
    #[arg(long, default_value_t = 1)]
    concurrency: usize,
    /// Write each session's registrations as a ParaView time series into this directory: one
    /// `.vtu` per update (nodes at their registered positions; `displacement`, `error_mm`) and
    /// `SCENARIO-METHOD.pvd` (time = acquisition time, s).
    #[arg(long, value_name = "DIR")]
    series: Option<PathBuf>,
}

#[derive(Args)]
struct LoadArgs {
    #[command(flatten)]
    common: Common,
    /// Concurrent clients.
    #[arg(long, default_value_t = 4)]
    concurrency: usize,
    /// Duration of the test, seconds.
    #[arg(long, default_value_t = 10.0)]
    duration: f64,
    /// Method: rigid, libr, libr_plus, default.
    #[arg(long, default_value = "libr")]
    method: String,
    /// At most this many messages per second per client (default: a closed loop, each client
    /// sending its next message as soon as the previous one is answered).
    #[arg(long)]
    rate: Option<f64>,
    /// HTTP/2 connections shared by the clients.
    #[arg(long, default_value_t = 1)]
    connections: usize,
}

fn seconds(name: &str, s: f64) -> Result<Duration> {
    if !(s.is_finite() && s > 0.0) {
        bail!("{name} must be a positive number of seconds, got {s}");
    }
    Ok(Duration::from_secs_f64(s))
}

fn options(c: &Common) -> Option<pb::RegisterOptions> {
    let any = c.time_budget_ms.is_some() || c.trusted_alignment.is_some();
    (any || c.held || c.single_answer).then(|| pb::RegisterOptions {
        time_budget_ms: c.time_budget_ms.unwrap_or(0),
        omit_displacements: false,
        trusted_alignment_mm: c.trusted_alignment.unwrap_or(0.0),
        held: c.held,
        single_answer: c.single_answer,
    })
}

fn print<T: serde::Serialize>(
    json: bool,
    value: &T,
    table: impl FnOnce(&T) -> String,
) -> Result<()> {
    if json {
        println!("{}", serde_json::to_string(value)?);
    } else {
        print!("{}", table(value));
    }
    Ok(())
}

async fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Upload(a) => {
            let s = librplus_client::upload(&librplus_client::UploadOptions {
                server: a.conn.server.clone(),
                tls: a.conn.tls(),
                token: a.conn.token.clone(),
                case_id: a.case_id,
                mesh: a.mesh,
                vessels: a.vessels,
                physics: a.physics,
                unit: a.unit,
                wait: !a.no_wait,
                progress: !a.json,
            })
            .await?;
            if a.json {
                println!("{}", serde_json::to_string(&s)?);
            }
            if s.state == "CASE_STATE_FAILED" {
                bail!("case {} failed to preload: {}", s.case_id, s.error);
            }
        }
        Command::Delete(a) => {
            let (v, sessions) =
                librplus_client::delete(&a.conn.server, &a.conn.tls(), &a.conn.token, &a.case_id)
                    .await?;
            eprintln!("deleted case {} (version {v})", a.case_id);
            if sessions > 0 {
                eprintln!(
                    "{sessions} session(s) recorded on it can no longer be resumed (a resume is \
                     refused naming the case and its version)"
                );
            }
        }
        Command::Replay(a) => {
            if let Some(r) = a.rate
                && !(r.is_finite() && r > 0.0)
            {
                bail!("--rate must be a positive number of messages per second, got {r}");
            }
            let opts = ReplayOptions {
                server: a.common.conn.server.clone(),
                data: a.common.data.clone(),
                selection: Selection::parse(a.common.scenarios.as_deref(), a.common.limit),
                methods: parse_methods(&a.methods)?,
                rate_hz: a.rate,
                batch: a.common.batch,
                options: options(&a.common),
                token: a.common.conn.token.clone(),
                resume: a.common.resume,
                timeout: seconds("--timeout-s", a.common.timeout_s)?,
                progress: true,
                discover_with: if a.discover_with.trim().is_empty() {
                    Vec::new()
                } else {
                    parse_methods(&a.discover_with)?
                },
                discovery: pb::DiscoveryOptions {
                    enabled: true,
                    budget_ms: a.discovery_budget_ms,
                    auto_after_points: 0,
                },
                discover_scenarios: a.discover_scenarios,
                discovery_concurrency: a.discovery_concurrency,
                tls: a.common.conn.tls(),
                concurrency: a.concurrency,
                resume_attempts: a.common.resume_attempts,
                series: a.series.clone(),
            };
            let s = replay(&opts).await?;
            print(a.common.json, &s, replay_table)?;
            if s.failed > 0 {
                bail!("{} of {} sessions failed (see above)", s.failed, s.sessions);
            }
        }
        Command::Load(a) => {
            if let Some(r) = a.rate
                && !(r.is_finite() && r > 0.0)
            {
                bail!("--rate must be a positive number of messages per second, got {r}");
            }
            let opts = LoadOptions {
                rate_hz: a.rate,
                server: a.common.conn.server.clone(),
                data: a.common.data.clone(),
                selection: Selection::parse(a.common.scenarios.as_deref(), a.common.limit),
                method: parse_method(&a.method)?,
                concurrency: a.concurrency,
                duration: seconds("--duration", a.duration)?,
                connections: a.connections,
                batch: a.common.batch,
                options: options(&a.common),
                token: a.common.conn.token.clone(),
                resume: a.common.resume,
                timeout: seconds("--timeout-s", a.common.timeout_s)?,
                progress: !a.common.json,
                tls: a.common.conn.tls(),
                ..Default::default()
            };
            let s = load(&opts).await?;
            print(a.common.json, &s, load_table)?;
            if s.requests == 0 {
                bail!("no request was answered (errors: {:?})", s.errors);
            }
        }
    }
    Ok(())
}

#[tokio::main]
async fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli).await {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
