//! What the server's end-to-end tests share (one file per concern beside this folder, as tonic's
//! own integration tests): the dataset, servers on 127.0.0.1:0, clients, and messages built from
//! the dataset's scenarios.
#![allow(dead_code, unused_imports)]

pub use librplus::eval::{GeometryData, ScenarioData, load_geometry, load_scenarios, open};
pub use librplus::pipeline::{Method, PipelineParams, Prepared, register};
pub use librplus::register::MeasuredKind;
pub use librplus::register::libr::LibrParams;
pub use librplus_proto::v1 as pb;
pub use librplus_server::config::ServerConfig;
pub use pb::lib_r_plus_client::LibRPlusClient;
pub use std::path::{Path, PathBuf};
pub use std::sync::OnceLock;
pub use std::time::Duration;
pub use tonic::Code;
pub use tonic::transport::Channel;
pub use tonic_types::StatusExt;

mod hostile;
pub use hostile::*;

/// A small dataset (2 geometries, 10 scenarios per deformation) with its LIBR bases cached.
/// Generated once per `cargo test` run and shared by its tests (and by any other test binary of
/// the same run): under `CARGO_TARGET_TMPDIR`, keyed by the parent process, made in a private
/// folder and renamed into place when complete.
pub fn dataset() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let root = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("server-tests");
        let dir = root.join(format!("small-{}", std::os::unix::process::parent_id()));
        if open(&dir).is_ok_and(|m| m.complete) {
            return dir;
        }
        std::fs::create_dir_all(&root).unwrap();
        remove_stale(&root);
        let tmp = root.join(format!("making-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        make_dataset(&tmp);
        if std::fs::rename(&tmp, &dir).is_err() {
            // Another binary finished first: use its copy.
            let _ = std::fs::remove_dir_all(&tmp);
            assert!(open(&dir).is_ok_and(|m| m.complete), "{}", dir.display());
        }
        dir
    })
}

/// Removes the datasets of earlier runs (over a day old).
fn remove_stale(root: &Path) {
    let Ok(entries) = std::fs::read_dir(root) else {
        return;
    };
    for e in entries.flatten() {
        let old = e
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age > Duration::from_secs(86_400));
        if old {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Generates the small preset from the built-in liver into `dir` and builds its LIBR bases into
/// the cache, so servers started in parallel only read them.
fn make_dataset(dir: &Path) {
    use librplus::phantom::dataset::{GenerateConfig, Preset, generate};
    let s = librplus::assets::default_liver().unwrap();
    let config = GenerateConfig::preset(
        Preset::Small,
        1,
        vec![librplus::assets::DEFAULT_LIVER_NAME.into()],
    );
    generate(&config, &[s], dir, (0, 1), &|_, _, _| {}).unwrap();
    let m = open(dir).unwrap();
    for g in &m.geometries {
        let geo = load_geometry(dir, &m, &g.id).unwrap();
        Prepared::new(
            geo.model,
            Some(&LibrParams::default()),
            Some(&dir.join("cache")),
        )
        .unwrap();
    }
}

pub fn config(max_sessions: usize) -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".into(),
        cases: vec![dataset().to_path_buf()],
        max_sessions,
        // Generous: debug builds are slow, and these tests compare against undegraded results.
        time_budget_ms: 60_000,
        max_time_budget_ms: 120_000,
        max_points_per_message: 5_000,
        drain_grace_s: 20.0,
        // No SR-GCN and no V2S unless a test asks (LIBR+ and V2S requests are then
        // FAILED_PRECONDITION).
        librplus: false,
        v2s: false,
        ..ServerConfig::default()
    }
}

pub async fn server(max_sessions: usize) -> (librplus_server::Running, LibRPlusClient<Channel>) {
    let mut running = librplus_server::start(ServerConfig {
        metrics_listen: Some("127.0.0.1:0".into()),
        ..config(max_sessions)
    })
    .await
    .unwrap();
    running.ready().await.unwrap();
    let client = client(running.addr).await;
    (running, client)
}

pub async fn client(addr: std::net::SocketAddr) -> LibRPlusClient<Channel> {
    let ch = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .unwrap();
    LibRPlusClient::new(ch).max_decoding_message_size(64 << 20)
}

/// A scenario with ultrasound points (the first of its deformation with 1–3 planes) and its
/// geometry.
pub fn scenario(category: &str) -> (GeometryData, ScenarioData) {
    let dir = dataset();
    let m = open(dir).unwrap();
    let d = &m.deformations[0];
    let geo = load_geometry(dir, &m, &d.geometry).unwrap();
    let sc = load_scenarios(dir, d)
        .unwrap()
        .into_iter()
        .find(|s| s.category == category)
        .unwrap();
    (geo, sc)
}

pub fn rigid_pb(r: &librplus::mesh::rigid::Rigid) -> pb::Rigid {
    pb::Rigid {
        rotation: r.rotation.iter().flatten().copied().collect(),
        translation_mm: r.translation.to_vec(),
    }
}

pub fn measurements_pb(m: &librplus::register::Measurements) -> pb::Measurements {
    pb::Measurements {
        xyz_mm: m.points.iter().flatten().copied().collect(),
        kind: m.kind.iter().map(|&k| k as i32 + 1).collect(),
        feature: m.feature.iter().map(|&f| f as i32).collect(),
        initial_alignment: m.initial_alignment.as_ref().map(rigid_pb),
    }
}

pub fn request(case: &str, method: pb::Method, m: pb::Measurements) -> pb::RegisterRequest {
    pb::RegisterRequest {
        case_id: case.into(),
        method: method as i32,
        measurements: Some(m),
        options: None,
    }
}

/// The library's answer on the same case and measurements.
pub fn direct(
    geo: &GeometryData,
    meas: &librplus::register::Checked,
    method: Method,
) -> librplus::pipeline::Registration {
    let case = Prepared::new(
        geo.model.clone(),
        Some(&LibrParams::default()),
        Some(&dataset().join("cache")),
    )
    .unwrap()
    .with_error_model(librplus::register::uncertainty::builtin());
    register(&case, meas, method, &PipelineParams::default()).unwrap()
}

/// Largest difference between the wire registration and the library's (transform entries and
/// displacements, mm).
pub fn difference(r: &pb::Registration, lib: &librplus::pipeline::Registration) -> (f64, f64) {
    let t = r.image_to_physical.as_ref().unwrap();
    let want = rigid_pb(&lib.image_to_physical);
    let dt = t
        .rotation
        .iter()
        .zip(&want.rotation)
        .chain(t.translation_mm.iter().zip(&want.translation_mm))
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert_eq!(r.displacement_mm.len(), lib.u.len());
    let du = r
        .displacement_mm
        .iter()
        .zip(&lib.u)
        .map(|(&a, &b)| (a as f64 - b).abs())
        .fold(0.0, f64::max);
    (dt, du)
}

/// The stream's messages for a scenario: start, surface points in batches of 40, then each
/// ultrasound point as its own plane message (pose at the point, (u, v) = (0, 0)); and the
/// measurements in the order the server accumulates them.
pub fn stream_of(
    case: &str,
    sc: &ScenarioData,
    method: pb::Method,
) -> (Vec<pb::StreamRegisterRequest>, librplus::register::Checked) {
    use pb::stream_register_request::Msg;
    let m = &sc.measurements;
    let mut msgs = vec![pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(Msg::Start(pb::SessionStart {
            case_id: case.into(),
            method: method as i32,
            options: None,
            initial_alignment: m.initial_alignment.as_ref().map(rigid_pb),
            discovery: None,
            resume_session_id: String::new(),
        })),
    }];
    let mut ordered = librplus::register::Measurements {
        initial_alignment: m.initial_alignment,
        ..Default::default()
    };
    let surf: Vec<usize> = (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .collect();
    for (b, chunk) in surf.chunks(40).enumerate() {
        msgs.push(pb::StreamRegisterRequest {
            client_seq: msgs.len() as u64 + 1,
            msg: Some(Msg::Surface(pb::SurfaceBatch {
                acquired_at: Some(prost_types::Timestamp {
                    seconds: 100 + b as i64,
                    nanos: 0,
                }),
                xyz_mm: chunk.iter().flat_map(|&i| m.points[i]).collect(),
                feature: chunk.iter().map(|&i| m.feature[i] as i32).collect(),
            })),
        });
        for &i in chunk {
            ordered.points.push(m.points[i]);
            ordered.kind.push(m.kind[i]);
            ordered.feature.push(m.feature[i]);
        }
    }
    for i in (0..m.points.len()).filter(|&i| m.kind[i] != MeasuredKind::Surface) {
        let p = m.points[i];
        let uv = vec![0.0, 0.0];
        let contour = m.kind[i] == MeasuredKind::PosteriorContour;
        msgs.push(pb::StreamRegisterRequest {
            client_seq: msgs.len() as u64 + 1,
            msg: Some(Msg::Ultrasound(pb::UltrasoundPlane {
                acquired_at: Some(prost_types::Timestamp {
                    seconds: 1000 + i as i64,
                    nanos: 0,
                }),
                plane_to_physical: Some(pb::Rigid {
                    rotation: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    translation_mm: p.to_vec(),
                }),
                contour_uv_mm: if contour { uv.clone() } else { vec![] },
                vessel_uv_mm: if contour { vec![] } else { uv },
            })),
        });
        ordered.points.push(p);
        ordered.kind.push(m.kind[i]);
        ordered.feature.push(0);
    }
    let ordered = librplus::register::Checked::new(ordered).expect("a dataset's points");
    (msgs, ordered)
}

/// A session handle: send one message, get the update it produced.
pub struct Stream {
    pub tx: tokio::sync::mpsc::Sender<pb::StreamRegisterRequest>,
    pub rx: tonic::Streaming<pb::StreamUpdate>,
}

impl Stream {
    pub async fn send(
        &mut self,
        m: pb::StreamRegisterRequest,
    ) -> Result<pb::StreamUpdate, tonic::Status> {
        // The server may have gone away (killed, restarted) since the stream opened: its end of
        // the request channel is closed then, an error like any other of a dead stream.
        self.tx
            .send(m)
            .await
            .map_err(|_| tonic::Status::unavailable("the stream's request side is closed"))?;
        match self.rx.message().await? {
            Some(u) => Ok(u),
            None => Err(tonic::Status::unknown("stream ended")),
        }
    }
}

pub async fn open_stream(
    c: &mut LibRPlusClient<Channel>,
    start: pb::StreamRegisterRequest,
) -> Result<Stream, tonic::Status> {
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tx.send(start).await.unwrap();
    let resp = c
        .stream_register(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await?;
    Ok(Stream {
        tx,
        rx: resp.into_inner(),
    })
}

pub fn violations(s: &tonic::Status) -> Vec<String> {
    s.get_details_bad_request()
        .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default()
}

/// Runs a command to completion on a blocking thread; its stdout (panics with stderr on failure).
pub async fn run_cmd(mut cmd: std::process::Command) -> String {
    let shown = format!("{cmd:?}");
    let out = tokio::task::spawn_blocking(move || cmd.output())
        .await
        .unwrap()
        .unwrap_or_else(|e| panic!("{shown}: {e}"));
    assert!(
        out.status.success(),
        "{shown}: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

// Certificates for the TLS tests, made here (rcgen).

use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};

/// A CA: its certificate (PEM) and its issuer.
pub fn ca(name: &str) -> (String, Issuer<'static, KeyPair>) {
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.distinguished_name.push(DnType::CommonName, name);
    let cert = params.self_signed(&key).unwrap();
    (cert.pem(), Issuer::new(params, key))
}

/// A certificate for `names` signed by `issuer`: (certificate PEM, key PEM).
pub fn leaf(names: &[&str], issuer: &Issuer<'static, KeyPair>) -> (String, String) {
    let key = KeyPair::generate().unwrap();
    let mut params =
        CertificateParams::new(names.iter().map(|s| s.to_string()).collect::<Vec<_>>()).unwrap();
    params.distinguished_name.push(DnType::CommonName, names[0]);
    let cert = params.signed_by(&key, issuer).unwrap();
    (cert.pem(), key.serialize_pem())
}

/// [`leaf`] valid only from `from` to `to` (year, month, day).
pub fn leaf_valid(
    names: &[&str],
    issuer: &Issuer<'static, KeyPair>,
    from: (i32, u8, u8),
    to: (i32, u8, u8),
) -> (String, String) {
    let key = KeyPair::generate().unwrap();
    let mut params =
        CertificateParams::new(names.iter().map(|s| s.to_string()).collect::<Vec<_>>()).unwrap();
    params.distinguished_name.push(DnType::CommonName, names[0]);
    params.not_before = rcgen::date_time_ymd(from.0, from.1, from.2);
    params.not_after = rcgen::date_time_ymd(to.0, to.1, to.2);
    let cert = params.signed_by(&key, issuer).unwrap();
    (cert.pem(), key.serialize_pem())
}

pub fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

// A `librplus-server` process (the binary this package builds), for tests that measure its
// memory, flood it, or kill it.

use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};

/// A free loopback port.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A server process: its address, its stderr lines (collected), and the child.
pub struct Proc {
    pub child: Child,
    pub addr: String,
    pub log: Arc<Mutex<Vec<String>>>,
}

impl Proc {
    pub fn start(extra: &[&str]) -> Self {
        let mut child = Command::new(server_exe())
            .arg("--cases")
            .arg(dataset())
            .arg("--no-librplus")
            .args(if extra.contains(&"--max-sessions") {
                &[][..]
            } else {
                &["--max-sessions", "4"][..]
            })
            .args(if extra.contains(&"--listen") {
                &[][..]
            } else {
                &["--listen", "127.0.0.1:0"][..]
            })
            .args(extra)
            .env("RUST_LOG", "info")
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let log = Arc::new(Mutex::new(Vec::new()));
        let (tx, rx) = std::sync::mpsc::channel();
        let stderr = child.stderr.take().unwrap();
        {
            let log = log.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(stderr).lines() {
                    let Ok(line) = line else { break };
                    if let Some(a) = line.strip_prefix("librplus-server listening on ") {
                        let _ = tx.send(Ok(a.trim().to_string()));
                    }
                    if line.starts_with("preloaded ") {
                        let _ = tx.send(Err(()));
                    }
                    log.lock().unwrap().push(line);
                }
            });
        }
        let addr = match rx.recv_timeout(Duration::from_secs(120)) {
            Ok(a) => a.unwrap(),
            Err(e) => {
                std::thread::sleep(Duration::from_millis(200));
                panic!("no server address ({e}): {:?}", log.lock().unwrap());
            }
        };
        // Then preload.
        rx.recv_timeout(Duration::from_secs(300))
            .expect("server preloaded")
            .unwrap_err();
        Self { child, addr, log }
    }

    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Resident memory, MB.
    pub fn rss_mb(&self) -> f64 {
        let s = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        let kb: f64 = s
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap();
        kb / 1024.0
    }

    pub fn longest_log_line(&self) -> usize {
        self.log
            .lock()
            .unwrap()
            .iter()
            .map(String::len)
            .max()
            .unwrap_or(0)
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The server binary: `LIBRPLUS_SERVER_BIN` (another build, to show a test failing before its
/// fix) or the one this package builds.
pub fn server_exe() -> PathBuf {
    std::env::var_os("LIBRPLUS_SERVER_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_librplus-server")))
}

/// An OpenIGTLink bridge process (`librplus-server igtl`, of [`server_exe`]) for `case` on the
/// gRPC server at `url`, listening on a free loopback port; its stderr lines collected.
pub struct Bridge {
    pub child: Child,
    pub port: u16,
    pub log: Arc<Mutex<Vec<String>>>,
}

impl Bridge {
    pub fn start(url: &str, case: &str, extra: &[&str]) -> Self {
        let port = free_port();
        let mut child = Command::new(server_exe())
            .arg("igtl")
            .args(["--server", url, "--case", case])
            .arg("--listen")
            .arg(format!("127.0.0.1:{port}"))
            .args(extra)
            .env("RUST_LOG", "info")
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let log = Arc::new(Mutex::new(Vec::new()));
        let stderr = child.stderr.take().unwrap();
        {
            let log = log.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(stderr).lines() {
                    let Ok(line) = line else { break };
                    log.lock().unwrap().push(line);
                }
            });
        }
        Self { child, port, log }
    }

    /// A connection to the bridge, once it listens (60 s at most).
    pub async fn connect(&self) -> tokio::net::TcpStream {
        for _ in 0..600 {
            if let Ok(s) = tokio::net::TcpStream::connect(("127.0.0.1", self.port)).await {
                return s;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!(
            "the bridge is not listening on {}: {:?}",
            self.port,
            self.log.lock().unwrap()
        );
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
