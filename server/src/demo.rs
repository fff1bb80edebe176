//! `librplus-server demo`: the main job end to end on a fresh machine. Generates the default case at
//! first run (the `small` phantom preset from the real SOFA liver: two geometries, ground truth,
//! thirty scenarios; cached), starts the server on loopback, replays scenarios through the real
//! client over gRPC for each method (and, side by side with them, a few sessions with in-surgery
//! discovery), and prints TRE, latency, what degraded and why.

use anyhow::{Context, Result, bail};
use librplus::mesh::TetMesh;
use librplus::mesh::io::{self, Unit};
use librplus_client::{ReplayOptions, Selection, pb};
use librplus_server::config::ServerConfig;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Options of the demo.
#[derive(Debug, Clone)]
pub struct DemoOptions {
    /// Dataset directory (generated there at first run).
    pub data: PathBuf,
    /// Source surface of the phantom liver (`None`: the built-in SOFA liver).
    pub surface: Option<PathBuf>,
    /// Scenarios replayed (spread over deformations and categories).
    pub scenarios: usize,
    /// Print JSON instead of tables.
    pub json: bool,
    /// Also replay LIBR with in-surgery discovery.
    pub discovery: bool,
    /// Scenarios replayed with discovery (0: every one), side by side with the other sessions.
    pub discovery_scenarios: usize,
}

/// Scenarios the demo replays with in-surgery discovery by default: one per deformation of the
/// default case (those with the most points).
pub const DISCOVERY_SCENARIOS: usize = 3;

/// The budget of each of the demo's discovery runs: on an idle machine of two cores its runs end
/// in well under half of it; on a busy one (discovery gets only the CPU time left over) a run
/// that has not ended by then is reported out of time, and the demo goes on.
pub const DISCOVERY_BUDGET: Duration = Duration::from_secs(90);

/// Where the demo keeps its case by default: `$XDG_CACHE_HOME/librplus/demo-v1`, else
/// `$HOME/.cache/librplus/demo-v1`, else `./librplus-demo`.
pub fn default_data_dir() -> PathBuf {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")));
    match base {
        Some(b) => b.join("librplus").join("demo-v1"),
        None => PathBuf::from("librplus-demo"),
    }
}

fn complete(dir: &Path) -> bool {
    librplus::eval::open(dir).is_ok_and(|m| m.complete)
}

/// A closed liver surface from a file: its triangles (or a tet mesh's boundary), the largest
/// piece, oriented outward.
fn closed_surface(path: &Path) -> Result<librplus::mesh::TriSurface> {
    let file = io::read(path, Unit::Mm).with_context(|| {
        format!(
            "--surface {}: the demo builds its phantom from this liver surface",
            path.display()
        )
    })?;
    let surface = if !file.triangles.is_empty() {
        librplus::mesh::TriSurface::from_file(&file)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?
    } else {
        let mut m = TetMesh::from_file(&file).with_context(|| path.display().to_string())?;
        m.orient_positive();
        m.boundary_surface()
            .with_context(|| path.display().to_string())?
    };
    surface
        .largest_closed_outward()
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// Generates the default case into `dir` unless it is there already.
pub fn ensure_dataset(o: &DemoOptions) -> Result<()> {
    use librplus::phantom::dataset::{GenerateConfig, Preset, generate};
    if complete(&o.data) {
        eprintln!("default case: {} (cached)", o.data.display());
        return Ok(());
    }
    let (surface, name) = match &o.surface {
        None => (
            librplus::assets::default_liver()?,
            librplus::assets::DEFAULT_LIVER_NAME.to_string(),
        ),
        Some(path) => (
            closed_surface(path)?,
            path.file_name()
                .map(|n| n.to_string_lossy().to_string())
                .unwrap_or_default(),
        ),
    };
    let config = GenerateConfig::preset(Preset::Small, 1, vec![name]);
    std::fs::create_dir_all(&o.data).with_context(|| o.data.display().to_string())?;
    let bar = indicatif::ProgressBar::new(0).with_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} generating the default case: {msg} [{bar:30}] {pos}/{len} ({elapsed})",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    bar.enable_steady_tick(Duration::from_millis(200));
    let progress = |done: usize, total: usize, msg: &str| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
        bar.set_message(msg.to_string());
    };
    let r = generate(&config, &[surface], &o.data, (0, 1), &progress);
    bar.finish_and_clear();
    r.map_err(|e| anyhow::anyhow!("{}: {e}", o.data.display()))?;
    eprintln!("default case generated into {}", o.data.display());
    Ok(())
}

/// The demo's certificates (PEM files in `dir`): a CA made for this run, the server's
/// certificate for `localhost` and one client certificate, both signed by it.
struct DemoTls {
    ca: PathBuf,
    server: (PathBuf, PathBuf),
    client: (PathBuf, PathBuf),
}

fn demo_tls(dir: &Path) -> Result<DemoTls> {
    let (ca, server, mut clients) =
        dev_certs(dir, "LIBR+ demo CA (this run only)", &["demo-client"])?;
    Ok(DemoTls {
        ca,
        server,
        client: clients.remove(0),
    })
}

/// A certificate and its key (PEM files).
pub type CertPair = (PathBuf, PathBuf);

/// A CA (`ca.pem`), a server certificate for `localhost` (`localhost.pem`, `.key`) and one
/// certificate per client name (`NAME.pem`, `NAME.key`, its subject `CN=NAME`), written into
/// `dir`: for tests, benchmarks and trials, never for a hospital (`librplus-server dev-certs`).
pub fn dev_certs(
    dir: &Path,
    ca_name: &str,
    clients: &[&str],
) -> Result<(PathBuf, CertPair, Vec<CertPair>)> {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};
    let ca_key = KeyPair::generate()?;
    let mut ca = CertificateParams::new(Vec::<String>::new())?;
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca.distinguished_name.push(DnType::CommonName, ca_name);
    let ca_pem = ca.self_signed(&ca_key)?.pem();
    let issuer = Issuer::new(ca, ca_key);
    let write = |name: &str, text: &str| -> Result<PathBuf> {
        let p = dir.join(name);
        std::fs::write(&p, text).with_context(|| p.display().to_string())?;
        Ok(p)
    };
    let leaf = |name: &str| -> Result<(PathBuf, PathBuf)> {
        let key = KeyPair::generate()?;
        let mut params = CertificateParams::new(vec![name.to_string()])?;
        params.distinguished_name.push(DnType::CommonName, name);
        let cert = params.signed_by(&key, &issuer)?;
        Ok((
            write(&format!("{name}.pem"), &cert.pem())?,
            write(&format!("{name}.key"), &key.serialize_pem())?,
        ))
    };
    let server = leaf("localhost")?;
    let clients = clients
        .iter()
        .map(|c| leaf(c))
        .collect::<Result<Vec<_>>>()?;
    Ok((write("ca.pem", &ca_pem)?, server, clients))
}

/// Runs the demo.
pub async fn run(o: DemoOptions) -> Result<()> {
    let t0 = Instant::now();
    {
        let o = o.clone();
        tokio::task::spawn_blocking(move || ensure_dataset(&o)).await??;
    }
    // Over mutual TLS, as in an operating room: certificates made for this run.
    let certs_dir =
        tempfile::tempdir().context("a temporary folder for the demo's certificates")?;
    let tls = demo_tls(certs_dir.path())?;
    let config = ServerConfig {
        listen: "127.0.0.1:0".into(),
        cases: vec![o.data.clone()],
        tls_cert: Some(tls.server.0.clone()),
        tls_key: Some(tls.server.1.clone()),
        client_ca: Some(tls.ca.clone()),
        // The demo's discovery sessions search the coarse grid (seconds on its 1,800-node livers).
        discovery_coarse: true,
        // Adaptive LIBR beside LIBR (its multi-level basis is cached with LIBR's).
        adaptive: true,
        ..ServerConfig::default()
    };
    let mut running = librplus_server::start(config).await?;
    eprintln!(
        "server on {} (mutual TLS, certificates made for this run) preloading (LIBR bases are cached after the first run)",
        running.addr
    );
    let pre = running.ready().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let opts = ReplayOptions {
        server: format!("http://{}", running.addr),
        data: o.data.clone(),
        selection: Selection::Spread(o.scenarios),
        // The paper's four methods side by side: the rigid stage alone, the data-driven V2S (the
        // built-in network), LIBR and LIBR+ (the built-in SR-GCN), and adaptive LIBR (fine
        // loads where the data are), and the automatic choice among doing nothing, rigid, LIBR
        // and adaptive LIBR (its table says which model each update chose); then LIBR with
        // in-surgery discovery (the model augmented when the session's points name an effect
        // it lacks).
        methods: vec![
            pb::Method::Rigid,
            pb::Method::V2s,
            pb::Method::Libr,
            pb::Method::LibrPlus,
            pb::Method::Adaptive,
            pb::Method::Auto,
        ],
        discover_with: if o.discovery {
            vec![pb::Method::Libr]
        } else {
            Vec::new()
        },
        discovery: pb::DiscoveryOptions {
            enabled: true,
            budget_ms: DISCOVERY_BUDGET.as_millis() as u32,
            auto_after_points: 0,
        },
        // The discovery sessions all at once, beside the others: each mostly waits for its run,
        // which gets only the CPU time the registrations leave.
        discover_scenarios: o.discovery_scenarios,
        discovery_concurrency: match o.discovery_scenarios {
            0 => o.scenarios.max(1),
            n => n,
        },
        progress: !o.json,
        tls: librplus_client::Tls {
            ca: Some(tls.ca.clone()),
            cert: Some(tls.client.0.clone()),
            key: Some(tls.client.1.clone()),
            domain: Some("localhost".into()),
        },
        ..ReplayOptions::default()
    };
    let summary = librplus_client::replay(&opts).await;
    let left = running.shutdown().await;
    let summary = summary?;
    if o.json {
        let mut v = serde_json::to_value(&summary)?;
        v["preload"] = serde_json::to_value(&pre)?;
        v["seconds"] = serde_json::json!(t0.elapsed().as_secs_f64());
        println!("{v}");
    } else {
        let with_discovery = summary
            .results
            .iter()
            .filter(|r| r.discovery.is_some())
            .count();
        println!(
            "LIBR+ demo: {} case(s) preloaded in {:.1} s; {} scenarios replayed over gRPC per method{}",
            pre.cases.len(),
            pre.seconds,
            summary.scenarios,
            if with_discovery > 0 {
                format!(
                    "; LIBR with in-surgery discovery on {with_discovery} of them, side by side (budget {:.0} s per run)",
                    DISCOVERY_BUDGET.as_secs_f64()
                )
            } else {
                String::new()
            }
        );
        println!("{}", librplus_client::replay_table(&summary));
        println!("done in {:.1} s", t0.elapsed().as_secs_f64());
    }
    if left > 0 {
        bail!("{left} session(s) were still open when the server stopped");
    }
    if summary.failed > 0 {
        bail!("{}", failures(&summary));
    }
    Ok(())
}

/// What failed, in plain words: how many sessions, and each one's scenario, method and reason.
fn failures(s: &librplus_client::ReplaySummary) -> String {
    let failed: Vec<String> = s
        .results
        .iter()
        .filter(|r| r.tre.is_none())
        .map(|r| {
            format!(
                "{} ({}): {}",
                r.scenario,
                r.method,
                r.error.as_deref().unwrap_or("no final registration")
            )
        })
        .collect();
    format!(
        "{} of {} session(s) failed: {}",
        failed.len(),
        s.sessions,
        failed.join("; ")
    )
}
