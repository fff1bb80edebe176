//! Server configuration: a JSON file (`--config`), overridden by command-line flags. Every field
//! has a default; unknown keys are an error that names them.

use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// Configuration of `librplus-server` (JSON file format version 1, see docs/service.md, "Config file").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// Format version of the config file (1).
    pub format: u32,
    /// gRPC listen address. Default `127.0.0.1:50051`; port 0 picks a free port.
    pub listen: String,
    /// Where the cases come from: dataset directories written by `librplus generate` (each
    /// geometry is a case) or folders of preoperative meshes (`.vtu`, `.vtk`, `.msh`: each file
    /// is a case named by its stem).
    pub cases: Vec<PathBuf>,
    /// Unit of lengths in plain mesh files (`mm`, `cm`, `m`). Default `mm`.
    pub mesh_unit: String,
    /// Where the LIBR bases are cached. Default: the dataset's `cache/`, or `cache/` in a mesh
    /// folder.
    pub cache_dir: Option<PathBuf>,
    /// Prometheus text endpoint (`GET /metrics`) address; none: no endpoint.
    pub metrics_listen: Option<String>,
    /// Most concurrent streamed sessions; beyond, RESOURCE_EXHAUSTED. Default 8.
    pub max_sessions: usize,
    /// Registrations computed at once (0: the number of cores). Default 0.
    pub compute_slots: usize,
    /// Most unary registrations waiting for a compute slot; beyond, RESOURCE_EXHAUSTED.
    /// Default 16.
    pub max_queued: usize,
    /// Default time budget of one registration, ms (a request may ask for another). Default 250.
    pub time_budget_ms: u32,
    /// Largest time budget a request may ask for, ms. Default 10,000.
    pub max_time_budget_ms: u32,
    /// Most points in one message. Default 20,000.
    pub max_points_per_message: usize,
    /// Most points a session accumulates. Default 100,000.
    pub max_points_per_session: usize,
    /// Largest gRPC message the server sends, bytes (a described mesh). Default 64 MiB.
    pub max_message_bytes: usize,
    /// Largest gRPC message the server accepts, bytes; 0: derived from
    /// `max_points_per_message` (32 bytes a point, at least 1 MiB, plus 64 KiB), so that a
    /// request is refused by its size before it is decoded. Default 0.
    pub max_request_bytes: usize,
    /// A stream must send its SessionStart within this many seconds, or it ends with
    /// DEADLINE_EXCEEDED (it holds no session slot meanwhile). Default 5.
    pub session_start_timeout_s: f64,
    /// Most sessions one principal holds at once (an auth file entry's `max_sessions`
    /// overrides it). 0: half of `max_sessions` (rounded up) when an auth file names the
    /// principals, so that no tenant takes every slot; all of them without one (every caller
    /// is then the one anonymous principal). Default 0.
    pub max_sessions_per_principal: usize,
    /// A session that has accepted no points this long after its start ends with
    /// DEADLINE_EXCEEDED and frees its slot, s (once it has points, `session_idle_timeout_s`
    /// applies). Default 30.
    pub session_no_data_timeout_s: f64,
    /// Most open client connections; beyond, a new one closes the oldest connection on which
    /// no call was accepted yet, or is closed itself. Default 512.
    pub max_connections: usize,
    /// A connection on which no call was accepted (authenticated, or any call without an auth
    /// file) within this many seconds of its first bytes is closed. Connections of no call
    /// are also at most half of `max_connections`, and at most
    /// `max_unauthenticated_connections_per_address` from one address (beyond, the oldest of
    /// them is closed), so that the other half is kept for clients that authenticate.
    /// Default 10.
    pub connection_idle_timeout_s: f64,
    /// Most connections from one IP address on which no call was accepted yet; a new one
    /// beyond closes the oldest of them. Default 64 (a client's pool of connections opened
    /// before its first calls).
    pub max_unauthenticated_connections_per_address: usize,
    /// Most uploads (`CreateCase`) received at once, each held in memory (up to
    /// `max_case_bytes`) until it is stored. Default 2.
    pub max_uploads: usize,
    /// Most uploads one principal sends at once. Default 1.
    pub max_uploads_per_principal: usize,
    /// An upload slower than this on average, bytes/s, counted from its 10th second, is ended
    /// with DEADLINE_EXCEEDED (a trickle cannot hold an upload slot). 0: no minimum. Default
    /// 65,536 (64 KiB/s).
    pub min_upload_bytes_per_s: u64,
    /// A connection must send its first bytes (the HTTP/2 preface, or the TLS hello) within this
    /// many seconds; silent ones are closed (and the oldest silent ones first when more than
    /// `max_connections` / 4 wait). Default 5.
    pub preface_timeout_s: f64,
    /// Most concurrent streams (calls) on one connection (HTTP/2 MAX_CONCURRENT_STREAMS).
    /// Default 32.
    pub max_streams_per_connection: u32,
    /// HTTP/2 keepalive: a ping after this many seconds without frames; a peer that does not
    /// answer within 20 s is dropped. Default 30.
    pub keepalive_s: f64,
    /// A session with no message for this long ends with DEADLINE_EXCEEDED, s. Default 600.
    pub session_idle_timeout_s: f64,
    /// How long shutdown waits for sessions to finish their update and close, s. Default 10.
    pub drain_grace_s: f64,
    /// Method used when a request leaves it unspecified (`rigid`, `libr`, `auto`, `adaptive`,
    /// `librplus`, `v2s`). Default `auto`.
    pub default_method: String,
    /// SR-GCN model directory (`librplus train`'s output, or an ensemble directory) for LIBR+; every case gets it. None:
    /// the model built into the server, when this build has one.
    pub model: Option<PathBuf>,
    /// Whether cases answer LIBR+ at all (false: no model is loaded). Default true.
    pub librplus: bool,
    /// V2S model directory (`librplus train --method v2s`'s output) for METHOD_V2S, the paper's
    /// data-driven baseline; every case gets it. None: the V2S model built into the server.
    pub v2s_model: Option<PathBuf>,
    /// Whether cases answer METHOD_V2S at all (false: no V2S model is loaded, and METHOD_V2S is
    /// FAILED_PRECONDITION). Default true.
    pub v2s: bool,
    /// Whether cases also prepare adaptive LIBR's multi-level basis, for METHOD_ADAPTIVE and as
    /// a candidate of METHOD_AUTO (its preload costs about four times LIBR's basis, cached beside
    /// it). Default true; false: METHOD_ADAPTIVE is FAILED_PRECONDITION and METHOD_AUTO chooses
    /// without adaptive LIBR.
    pub adaptive: bool,
    /// Log as JSON lines instead of text.
    pub log_json: bool,
    /// Default wall-clock limit of one in-surgery discovery run, ms (a session may ask for
    /// another, up to `max_discovery_budget_ms`). Default 120,000.
    pub discovery_budget_ms: u32,
    /// Largest discovery budget a session may ask for, ms. Default 600,000.
    pub max_discovery_budget_ms: u32,
    /// Listen on an address other machines can reach (not loopback) although no client is
    /// authenticated (no `auth`). Default false: such an address is refused without `auth`.
    pub insecure: bool,
    /// Authentication and authorization file (tokens as SHA-256 hashes, principals, their
    /// cases and roles; docs/service.md, "Authentication"). None: every caller may do anything
    /// (loopback only, unless `insecure`).
    pub auth: Option<PathBuf>,
    /// The audit log (SQLite; docs/service.md, "Audit log"): every registration, session and
    /// refusal, committed before the answer is sent; sessions resume from it. None: no log (and
    /// no resume).
    pub audit_db: Option<PathBuf>,
    /// The session journal (docs/deploy.md, "Replicas"): a folder every replica shares, where
    /// each streamed session's start and accepted messages are written (durable before the
    /// answer) so that any replica resumes a session another one served. Needs `audit_db`
    /// (each replica's own: `{host}` in a path is the host name). None: sessions resume from
    /// the audit log, on this server only.
    pub session_journal: Option<PathBuf>,
    /// Session journal folders untouched this many hours are removed. Default 24.
    pub session_journal_retention_h: f64,
    /// Where cases uploaded over the API (`CreateCase`) are kept (docs/service.md, "Case
    /// store"); reloaded at start. None: no uploads.
    pub case_store: Option<PathBuf>,
    /// Largest upload (all its files), bytes. Default 512 MiB.
    pub max_case_bytes: usize,
    /// Most nodes of an uploaded mesh. Default 1,000,000.
    pub max_case_nodes: usize,
    /// Most cases in the case store; an upload beyond is RESOURCE_EXHAUSTED
    /// `max_stored_cases`. This also bounds the memory uploads take (a READY case is in
    /// memory until it is idle for `evict_idle_s`). Default 32.
    pub max_stored_cases: usize,
    /// An uploaded case no request used for this long (seconds) and no session holds leaves
    /// memory (state STORED); the next request loads it again from the store (its basis from
    /// its cache) and is answered UNAVAILABLE meanwhile. 0: never. Default 21,600 (6 h).
    pub evict_idle_s: f64,
    /// An uploaded case of more nodes than this, whose own LIBR basis is not cached and whose
    /// model carries no physics, first serves from a basis built on its boundary meshed again
    /// with `coarse_basis_edge_mm` tets (about a second at 60,000 nodes), flagged DEGRADED,
    /// while its own basis builds; it swaps to that basis (audited) when it is ready. 0: never.
    /// Default 30,000.
    pub coarse_basis_above_nodes: usize,
    /// The coarse mesh's edge length (mm) of `coarse_basis_above_nodes`. Default 11 (about
    /// 3,300 nodes on an adult liver: TRE within 0.1 mm of the case's own basis, measured).
    pub coarse_basis_edge_mm: f64,
    /// Most bytes in the case store (each case's folder: its files and its LIBR basis cache);
    /// beyond, RESOURCE_EXHAUSTED `max_stored_bytes`. Default 8 GiB.
    pub max_stored_bytes: u64,
    /// Most stored cases one principal uploaded (0: `max_stored_cases`); beyond,
    /// RESOURCE_EXHAUSTED `max_cases_per_principal`. Default 8.
    pub max_cases_per_principal: usize,
    /// Most bytes of the stored cases one principal uploaded (0: `max_stored_bytes`); beyond,
    /// RESOURCE_EXHAUSTED `max_bytes_per_principal`. Default 2 GiB.
    pub max_bytes_per_principal: u64,
    /// TLS: the server's certificate chain (PEM). With `tls_key`, the server speaks only TLS.
    pub tls_cert: Option<PathBuf>,
    /// TLS: the server's private key (PEM).
    pub tls_key: Option<PathBuf>,
    /// mTLS: clients must present a certificate signed by this CA (PEM); needs `tls_cert`.
    pub client_ca: Option<PathBuf>,
    /// In-surgery discovery searches the coarse grid (16 directions, 8 pack and 4 fixation
    /// sites, 5 blocks, 9 bootstrap replicates) instead of `librplus discover`'s full one: about
    /// 4× faster, on slow machines. Default false.
    pub discovery_coarse: bool,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            format: 1,
            listen: "127.0.0.1:50051".into(),
            cases: Vec::new(),
            mesh_unit: "mm".into(),
            cache_dir: None,
            metrics_listen: None,
            max_sessions: 8,
            compute_slots: 0,
            max_queued: 16,
            time_budget_ms: 250,
            max_time_budget_ms: 10_000,
            max_points_per_message: 20_000,
            max_points_per_session: 100_000,
            max_message_bytes: 64 << 20,
            max_request_bytes: 0,
            session_start_timeout_s: 5.0,
            max_sessions_per_principal: 0,
            session_no_data_timeout_s: 30.0,
            max_connections: 512,
            connection_idle_timeout_s: 10.0,
            max_unauthenticated_connections_per_address: 64,
            max_uploads: 2,
            max_uploads_per_principal: 1,
            min_upload_bytes_per_s: 64 << 10,
            preface_timeout_s: 5.0,
            max_streams_per_connection: 32,
            keepalive_s: 30.0,
            session_idle_timeout_s: 600.0,
            drain_grace_s: 10.0,
            default_method: "auto".into(),
            model: None,
            librplus: true,
            v2s_model: None,
            v2s: true,
            adaptive: true,
            log_json: false,
            discovery_budget_ms: 120_000,
            max_discovery_budget_ms: 600_000,
            discovery_coarse: false,
            insecure: false,
            auth: None,
            audit_db: None,
            session_journal: None,
            session_journal_retention_h: 24.0,
            case_store: None,
            max_case_bytes: 512 << 20,
            max_case_nodes: 1_000_000,
            max_stored_cases: 32,
            max_stored_bytes: 8 << 30,
            max_cases_per_principal: 8,
            max_bytes_per_principal: 2 << 30,
            evict_idle_s: 21_600.0,
            coarse_basis_above_nodes: 30_000,
            coarse_basis_edge_mm: 11.0,
            tls_cert: None,
            tls_key: None,
            client_ca: None,
        }
    }
}

/// Why a server configuration is refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: std::path::PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// The file is not JSON of the configuration's shape.
    #[error("{}: {source}", path.display())]
    Json {
        /// The file.
        path: std::path::PathBuf,
        /// The parser's error.
        source: serde_json::Error,
    },
    /// A config file format this server does not read.
    #[error("format {0} is not supported (1)")]
    Format(u32),
    /// Neither a case directory nor a case store.
    #[error("cases: no case directory given (and no case_store for uploads)")]
    NoCases,
    /// A mesh unit other than mm, cm, m.
    #[error("mesh_unit {0:?}: expected mm, cm or m")]
    MeshUnit(String),
    /// A default method that is unknown or switched off.
    #[error(
        "default_method {method:?}: expected rigid, libr, auto{}{}{}",
        if *.adaptive { ", adaptive" } else { " (adaptive is off)" },
        if *.librplus { ", librplus" } else { " (librplus is off)" },
        if *.v2s { ", v2s" } else { " (v2s is off)" }
    )]
    DefaultMethod {
        /// The method given.
        method: String,
        /// Whether adaptive LIBR's basis is prepared (`adaptive`).
        adaptive: bool,
        /// Whether LIBR+ is on (`librplus`).
        librplus: bool,
        /// Whether V2S is on (`v2s`).
        v2s: bool,
    },
    /// A store limit of 0 (`max_stored_cases`, `max_stored_bytes`).
    #[error("{0} must be at least 1 (to take no upload, leave case_store unset)")]
    StoreLimitZero(&'static str),
    /// A count that must be at least 1 is 0.
    #[error("{0} must be at least 1")]
    Zero(&'static str),
    /// `evict_idle_s` is negative or not finite.
    #[error(
        "evict_idle_s must be a finite number of seconds ≥ 0 (0: never), got {}",
        crate::convert::num(*.0)
    )]
    EvictIdle(f64),
    /// `coarse_basis_edge_mm` is not a finite length > 0.
    #[error(
        "coarse_basis_edge_mm must be a finite length > 0 (mm), got {}",
        crate::convert::num(*.0)
    )]
    CoarseEdge(f64),
    /// One of the TLS pair is set without the other.
    #[error("{missing}: missing ({present} is set; TLS needs both)")]
    TlsPair {
        /// The field that is missing.
        missing: &'static str,
        /// The field that is set.
        present: &'static str,
    },
    /// `client_ca` without TLS.
    #[error("client_ca: client certificates (mTLS) need TLS: set tls_cert and tls_key")]
    ClientCaWithoutTls,
    /// `session_journal` without `audit_db`.
    #[error("session_journal: needs audit_db (each replica keeps its own audit log)")]
    JournalWithoutAudit,
    /// `session_journal_retention_h` is negative or not finite.
    #[error("session_journal_retention_h must be finite and ≥ 0, got {0}")]
    JournalRetention(f64),
    /// A budget outside 1..=its maximum (`time_budget_ms`, `discovery_budget_ms`).
    #[error("{field} {value} must be in 1..={max_field} ({max})")]
    Budget {
        /// The field.
        field: &'static str,
        /// Its value.
        value: u32,
        /// The field of its maximum.
        max_field: &'static str,
        /// The maximum.
        max: u32,
    },
    /// A duration in seconds that is not finite and positive.
    #[error("{field} must be finite and > 0, got {value}")]
    NotPositive {
        /// The field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// A value of the file `path` is out of range.
    #[error("{}: {source}", path.display())]
    InFile {
        /// The file.
        path: std::path::PathBuf,
        /// The bad value.
        source: Box<ConfigError>,
    },
}

impl ServerConfig {
    /// Reads a config file (JSON).
    pub fn from_file(path: &std::path::Path) -> Result<Self, ConfigError> {
        let c = Self::read_file(path)?;
        c.validate().map_err(|e| ConfigError::InFile {
            path: path.to_path_buf(),
            source: Box::new(e),
        })?;
        Ok(c)
    }

    /// Reads a config file without checking its values (flags may complete it: the caller
    /// validates the result).
    pub fn read_file(path: &std::path::Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        serde_json::from_str(&text).map_err(|source| ConfigError::Json {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Checks the values; the message names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.format != 1 {
            return Err(ConfigError::Format(self.format));
        }
        if self.cases.is_empty() && self.case_store.is_none() {
            return Err(ConfigError::NoCases);
        }
        self.unit()?;
        self.method()?;
        if self.max_stored_cases == 0 {
            return Err(ConfigError::StoreLimitZero("max_stored_cases"));
        }
        if !(self.evict_idle_s.is_finite() && self.evict_idle_s >= 0.0) {
            return Err(ConfigError::EvictIdle(self.evict_idle_s));
        }
        if self.max_stored_bytes == 0 {
            return Err(ConfigError::StoreLimitZero("max_stored_bytes"));
        }
        if !(self.coarse_basis_edge_mm.is_finite() && self.coarse_basis_edge_mm > 0.0) {
            return Err(ConfigError::CoarseEdge(self.coarse_basis_edge_mm));
        }
        for (name, v) in [
            ("max_sessions", self.max_sessions),
            ("max_points_per_message", self.max_points_per_message),
            ("max_points_per_session", self.max_points_per_session),
            ("max_message_bytes", self.max_message_bytes),
            ("max_connections", self.max_connections),
            (
                "max_unauthenticated_connections_per_address",
                self.max_unauthenticated_connections_per_address,
            ),
            ("max_uploads", self.max_uploads),
            ("max_uploads_per_principal", self.max_uploads_per_principal),
            (
                "max_streams_per_connection",
                self.max_streams_per_connection as usize,
            ),
        ] {
            if v == 0 {
                return Err(ConfigError::Zero(name));
            }
        }
        match (&self.tls_cert, &self.tls_key) {
            (Some(_), None) => {
                return Err(ConfigError::TlsPair {
                    missing: "tls_key",
                    present: "tls_cert",
                });
            }
            (None, Some(_)) => {
                return Err(ConfigError::TlsPair {
                    missing: "tls_cert",
                    present: "tls_key",
                });
            }
            _ => {}
        }
        if self.client_ca.is_some() && self.tls_cert.is_none() {
            return Err(ConfigError::ClientCaWithoutTls);
        }
        if self.session_journal.is_some() && self.audit_db.is_none() {
            return Err(ConfigError::JournalWithoutAudit);
        }
        if !(self.session_journal_retention_h.is_finite()
            && self.session_journal_retention_h >= 0.0)
        {
            return Err(ConfigError::JournalRetention(
                self.session_journal_retention_h,
            ));
        }
        for (field, value, max_field, max) in [
            (
                "discovery_budget_ms",
                self.discovery_budget_ms,
                "max_discovery_budget_ms",
                self.max_discovery_budget_ms,
            ),
            (
                "time_budget_ms",
                self.time_budget_ms,
                "max_time_budget_ms",
                self.max_time_budget_ms,
            ),
        ] {
            if value == 0 || value > max {
                return Err(ConfigError::Budget {
                    field,
                    value,
                    max_field,
                    max,
                });
            }
        }
        for (name, v) in [
            ("session_idle_timeout_s", self.session_idle_timeout_s),
            ("session_no_data_timeout_s", self.session_no_data_timeout_s),
            ("connection_idle_timeout_s", self.connection_idle_timeout_s),
            ("drain_grace_s", self.drain_grace_s),
            ("session_start_timeout_s", self.session_start_timeout_s),
            ("preface_timeout_s", self.preface_timeout_s),
            ("keepalive_s", self.keepalive_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(ConfigError::NotPositive {
                    field: name,
                    value: v,
                });
            }
        }
        Ok(())
    }

    /// A configured path with `{host}` replaced by this machine's host name (a pod's name under
    /// Kubernetes, a container's id under Docker): one file per replica on a shared volume.
    pub fn per_host(path: &std::path::Path) -> PathBuf {
        let s = path.to_string_lossy();
        if s.contains("{host}") {
            PathBuf::from(s.replace("{host}", &host_name()))
        } else {
            path.to_path_buf()
        }
    }

    /// The mesh unit.
    pub fn unit(&self) -> Result<librplus::mesh::io::Unit, ConfigError> {
        use librplus::mesh::io::Unit;
        match self.mesh_unit.as_str() {
            "mm" => Ok(Unit::Mm),
            "cm" => Ok(Unit::Cm),
            "m" => Ok(Unit::M),
            u => Err(ConfigError::MeshUnit(u.to_string())),
        }
    }

    /// The default method.
    pub fn method(&self) -> Result<librplus::pipeline::Method, ConfigError> {
        use librplus::pipeline::Method;
        match self.default_method.as_str() {
            "rigid" => Ok(Method::Rigid),
            "libr" => Ok(Method::Libr),
            "auto" => Ok(Method::Auto),
            "nonlinear" => Ok(Method::Nonlinear),
            "adaptive" if self.adaptive => Ok(Method::Adaptive),
            "librplus" if self.librplus => Ok(Method::LibrPlus),
            "v2s" if self.v2s => Ok(Method::V2s),
            m => Err(ConfigError::DefaultMethod {
                method: m.to_string(),
                adaptive: self.adaptive,
                librplus: self.librplus,
                v2s: self.v2s,
            }),
        }
    }

    /// The largest request the server decodes, bytes.
    pub fn request_bytes(&self) -> usize {
        if self.max_request_bytes > 0 {
            self.max_request_bytes
        } else {
            self.max_points_per_message
                .saturating_mul(32)
                .max(1 << 20)
                .saturating_add(64 << 10)
        }
    }

    /// Most sessions one principal may hold, given its own limit (0: none of its own) and
    /// whether an auth file names the principals (`tenants`).
    pub fn principal_sessions(&self, own: usize, tenants: bool) -> usize {
        match (own, self.max_sessions_per_principal) {
            (0, 0) if tenants => self.max_sessions.div_ceil(2),
            (0, 0) => self.max_sessions,
            (0, n) | (n, _) => n,
        }
    }

    /// Compute slots (the number of cores when 0).
    pub fn slots(&self) -> usize {
        if self.compute_slots > 0 {
            self.compute_slots
        } else {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        }
    }
}

/// This machine's host name (`/proc/sys/kernel/hostname`, else `$HOSTNAME`, else `localhost`),
/// reduced to the characters a file name may safely hold.
pub fn host_name() -> String {
    let raw = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_default();
    let clean: String = raw
        .trim()
        .chars()
        .filter(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        .take(64)
        .collect();
    if clean.is_empty() || clean.starts_with('.') {
        "localhost".into()
    } else {
        clean
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_files_name_bad_keys_and_values() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("c.json");
        std::fs::write(&f, r#"{"format": 1, "cases": ["x"], "max_sesions": 3}"#).unwrap();
        let e = ServerConfig::from_file(&f).unwrap_err();
        assert!(matches!(e, ConfigError::Json { .. }), "{e}");
        assert!(e.to_string().contains("max_sesions"), "{e}");
        std::fs::write(&f, r#"{"format": 1, "cases": ["x"], "time_budget_ms": 0}"#).unwrap();
        assert!(
            ServerConfig::from_file(&f)
                .unwrap_err()
                .to_string()
                .contains("time_budget_ms")
        );
        std::fs::write(&f, r#"{"format": 2, "cases": ["x"]}"#).unwrap();
        assert!(
            ServerConfig::from_file(&f)
                .unwrap_err()
                .to_string()
                .contains("format 2")
        );
        std::fs::write(&f, r#"{"cases": ["x"], "mesh_unit": "in"}"#).unwrap();
        assert!(
            ServerConfig::from_file(&f)
                .unwrap_err()
                .to_string()
                .contains("mesh_unit")
        );
        std::fs::write(
            &f,
            r#"{"cases": ["x"], "max_sessions": 3, "default_method": "rigid"}"#,
        )
        .unwrap();
        let c = ServerConfig::from_file(&f).unwrap();
        assert_eq!((c.max_sessions, c.time_budget_ms), (3, 250));
        assert!(matches!(
            ServerConfig::default().validate(),
            Err(ConfigError::NoCases)
        ));
        // The messages name the field and the value, as they always did.
        for (e, message) in [
            (
                ConfigError::DefaultMethod {
                    method: "v2s".into(),
                    adaptive: true,
                    librplus: true,
                    v2s: false,
                },
                "default_method \"v2s\": expected rigid, libr, auto, adaptive, librplus (v2s is off)",
            ),
            (
                ConfigError::EvictIdle(-1.0),
                "evict_idle_s must be a finite number of seconds ≥ 0 (0: never), got -1",
            ),
            (
                ConfigError::TlsPair {
                    missing: "tls_key",
                    present: "tls_cert",
                },
                "tls_key: missing (tls_cert is set; TLS needs both)",
            ),
            (
                ConfigError::Budget {
                    field: "time_budget_ms",
                    value: 0,
                    max_field: "max_time_budget_ms",
                    max: 10_000,
                },
                "time_budget_ms 0 must be in 1..=max_time_budget_ms (10000)",
            ),
        ] {
            assert_eq!(e.to_string(), message);
        }
        let c = ServerConfig {
            cases: vec!["x".into()],
            keepalive_s: 0.0,
            ..Default::default()
        };
        assert!(matches!(
            c.validate(),
            Err(ConfigError::NotPositive {
                field: "keepalive_s",
                ..
            })
        ));
    }
}
