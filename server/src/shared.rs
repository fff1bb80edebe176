//! The state every request shares ([`Shared`]: configuration, cases, compute slots, sessions,
//! auth, audit log) and the admission of sessions and uploads (counted in [`crate::counted`],
//! released on drop). Below every module that serves a request: the service,
//! sessions, uploads and case access all use it, and it uses none of them.

use crate::audit::{Audit, Record};
use crate::auth::{Auth, Principal};
use crate::compute::Engine;
use crate::config::ServerConfig;
use crate::convert::code_name;
use crate::counted::{Admission, KeyHold, PerKey};
use crate::error::{ServiceError, Unavailable, short};
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tokio::sync::{OwnedSemaphorePermit, Semaphore, watch};
use tonic::Code;

/// How long a new session waits for a slot before RESOURCE_EXHAUSTED.
const ADMISSION_GRACE: Duration = Duration::from_millis(100);

/// State shared by every request.
pub struct Shared {
    /// Configuration.
    pub config: ServerConfig,
    /// The cases: ready ones, and the state of each.
    pub registry: crate::registry::Registry,
    /// The case store (uploads), when configured.
    pub store: Option<crate::store::Store>,
    /// Uploads received at once (each is held in memory until it is checked and stored).
    pub uploads: Arc<Semaphore>,
    /// The learned models every case gets (set by the preload at start).
    pub learned: OnceLock<crate::cases::Learned>,
    /// Compute slots.
    pub engine: Engine,
    /// Session admission.
    pub sessions: Arc<Semaphore>,
    /// Becomes true when the server starts draining.
    pub drain: watch::Receiver<bool>,
    /// Session counter (ids).
    pub next_session: AtomicU64,
    /// The auth file's principals (None: no `--auth`, every caller is [`Shared::anonymous`]);
    /// replaced on reload.
    pub auth: Option<std::sync::RwLock<Arc<Auth>>>,
    /// The principal of every call when there is no auth file.
    pub anonymous: Arc<Principal>,
    /// Sessions open per principal.
    pub(crate) per_principal: Arc<PerKey>,
    /// Uploads being received per principal.
    pub(crate) uploads_per_principal: Arc<PerKey>,
    /// The open client connections (what the connection gate admits, and which of them had a
    /// call accepted).
    pub connections: Arc<crate::connections::Connections>,
    /// The audit log, when kept (`audit_db`).
    pub audit: Option<Arc<Audit>>,
    /// This run's prefix of session ids (unique across restarts).
    pub boot: String,
    /// Which stream holds each live session (one stream per session id).
    pub live: Arc<crate::live::Live>,
}

impl Shared {
    /// Shared state for `config` with `auth` (None: no auth file).
    pub fn new(
        config: ServerConfig,
        auth: Option<Auth>,
        audit: Option<Audit>,
        store: Option<crate::store::Store>,
        engine: Engine,
        drain: watch::Receiver<bool>,
    ) -> Self {
        Self {
            store,
            uploads: Arc::new(Semaphore::new(config.max_uploads)),
            registry: Default::default(),
            learned: OnceLock::new(),
            audit: audit.map(Arc::new),
            // Unique across replicas sharing a session journal: the start time and 32 random
            // bits (two replicas starting in the same millisecond).
            boot: format!("{:x}{:08x}", crate::audit::now_ms(), boot_nonce()),
            engine,
            sessions: Arc::new(Semaphore::new(config.max_sessions)),
            drain,
            next_session: AtomicU64::new(0),
            auth: auth.map(|a| std::sync::RwLock::new(Arc::new(a))),
            anonymous: Principal::anonymous(),
            per_principal: Default::default(),
            uploads_per_principal: Default::default(),
            connections: Arc::new(crate::connections::Connections::new(&config)),
            live: Default::default(),
            config,
        }
    }

    /// Writes audit records and waits for their commit (nothing without an audit log). An
    /// error is UNAVAILABLE: nothing is acknowledged that is not recorded.
    pub async fn record(&self, records: Vec<Record>) -> Result<(), ServiceError> {
        let Some(a) = &self.audit else {
            return Ok(());
        };
        a.write(records)
            .await
            .map_err(|e| Unavailable::AuditLog(Box::new(e)).into())
    }

    /// Records a refusal without waiting for it.
    pub fn refused(&self, rpc: &str, who: &str, case: Option<&str>, e: &ServiceError) {
        let Some(a) = self.audit.clone() else {
            return;
        };
        let (code, message, _) = e.parts();
        let r = Record::Event {
            kind: "refused",
            principal: who.to_string(),
            case_id: case.map(|c| short(c, 64).into_owned()),
            session_id: None,
            detail: serde_json::json!({
                "rpc": rpc,
                "code": code_name(code),
                "message": short(&message, 300),
            }),
        };
        tokio::spawn(async move {
            let _ = a.write(vec![r]).await;
        });
    }

    /// The current auth file, if any.
    pub fn auth(&self) -> Option<Arc<Auth>> {
        self.auth
            .as_ref()
            .map(|a| a.read().unwrap_or_else(|e| e.into_inner()).clone())
    }

    /// The caller of a request: anonymous without an auth file, else its token's or client
    /// certificate's principal (UNAUTHENTICATED otherwise).
    pub fn caller(
        &self,
        md: &tonic::metadata::MetadataMap,
        certs: Option<&[tonic::transport::CertificateDer<'static>]>,
    ) -> Result<Arc<Principal>, ServiceError> {
        match self.auth() {
            None => Ok(self.anonymous.clone()),
            Some(a) => a.authenticate(md, certs),
        }
    }
}

/// Longest case id, bytes.
pub const MAX_CASE_ID: usize = 256;

/// An upload's hold on a server upload slot and on its principal's; released on drop.
pub(crate) struct UploadSlot {
    _permit: OwnedSemaphorePermit,
    _principal: KeyHold,
}

impl Shared {
    /// An upload slot for `who`: at most `max_uploads_per_principal` of its own (with an auth
    /// file), then one of the server's `max_uploads` (so that one principal cannot hold every
    /// upload slot).
    pub(crate) fn admit_upload(&self, who: &Principal) -> Result<UploadSlot, ServiceError> {
        // Without an auth file every caller is the one anonymous principal.
        let limit = match self.auth.is_some() {
            true => self.config.max_uploads_per_principal,
            false => self.config.max_uploads,
        };
        let own = self.uploads_per_principal.try_hold(&who.name, limit).map_err(|n| {
            metrics::counter!("librplus_refused_total", "reason" => "principal_uploads")
                .increment(1);
            ServiceError::Quota {
                message: format!(
                    "principal {:?} is sending {n} upload(s), its limit (max_uploads_per_principal = {limit}); retry when one is done",
                    who.name
                ),
                subject: "principal_uploads",
                description: format!(
                    "at most {limit} uploads per principal at once (max_uploads_per_principal)"
                ),
            }
        })?;
        let max = self.config.max_uploads;
        let permit = self.uploads.clone().try_acquire_owned().map_err(|_| {
            metrics::counter!("librplus_refused_total", "reason" => "uploads").increment(1);
            ServiceError::Quota {
                message: format!(
                    "{max} uploads are being received (max_uploads); retry when one is done"
                ),
                subject: "uploads",
                description: format!("at most {max} uploads are received at once (max_uploads)"),
            }
        })?;
        Ok(UploadSlot {
            _permit: permit,
            _principal: own,
        })
    }

    /// A session slot for `who`: its principal's quota, then the server's (waiting briefly for
    /// a slot a session just released).
    pub(crate) async fn admit(
        self: &Arc<Self>,
        who: &Principal,
    ) -> Result<Admission, ServiceError> {
        let limit = self
            .config
            .principal_sessions(who.max_sessions, self.auth.is_some());
        // A quota of its own only when it is below the server's.
        let quota = if limit < self.config.max_sessions {
            let hold = self.per_principal.try_hold(&who.name, limit).map_err(|n| {
                metrics::counter!("librplus_refused_total", "reason" => "principal_sessions")
                    .increment(1);
                ServiceError::Quota {
                    message: format!(
                        "principal {:?} holds {n} sessions, its limit; retry after one ends",
                        who.name
                    ),
                    subject: "principal_sessions",
                    description: format!(
                        "at most {limit} streamed sessions per principal; retry after one ends"
                    ),
                }
            })?;
            Some(hold)
        } else {
            None
        };
        let sessions = self.sessions.clone();
        let permit = match sessions.clone().try_acquire_owned() {
            Ok(p) => Ok(p),
            Err(_) => tokio::time::timeout(ADMISSION_GRACE, sessions.acquire_owned())
                .await
                .map_err(|_| ())
                .and_then(|r| r.map_err(|_| ())),
        };
        match permit {
            Ok(p) => Ok(Admission::new(p, quota)),
            Err(()) => {
                // `quota` is released as it drops here.
                metrics::counter!("librplus_refused_total", "reason" => "sessions").increment(1);
                Err(ServiceError::Quota {
                    message: format!(
                        "session limit reached ({} open); retry later",
                        self.config.max_sessions
                    ),
                    subject: "sessions",
                    description: format!(
                        "{} streamed sessions are open, the server's limit; retry after one ends",
                        self.config.max_sessions
                    ),
                })
            }
        }
    }
}

/// Counts a failed request by its status code (`librplus_errors_total`).
pub(crate) fn count_error(code: Code) {
    metrics::counter!("librplus_errors_total", "code" => code_name(code)).increment(1);
}

/// How many sessions recorded on case `case_id` at `version` a client could still resume (this
/// server's audit log; sessions older than the journal's retention are no longer resumable).
/// None without an audit log (no session resumes) or when it cannot be read.
pub(crate) async fn resumable_sessions(
    shared: &Shared,
    case_id: &str,
    version: &str,
) -> Option<u64> {
    let audit = shared.audit.as_ref()?;
    let path = audit.path().to_path_buf();
    let since = match audit.journal_dir() {
        Some(_) => {
            crate::audit::now_ms()
                - (shared.config.session_journal_retention_h * 3.6e6).min(1e15) as i64
        }
        None => 0,
    };
    let (id, v) = (case_id.to_string(), version.to_string());
    tokio::task::spawn_blocking(move || {
        let c = crate::audit::open_db(&path).ok()?;
        crate::audit::count_sessions(&c, &id, &v, since).ok()
    })
    .await
    .ok()
    .flatten()
}

/// 32 random bits for the session ids of this run.
fn boot_nonce() -> u32 {
    random_u64() as u32
}

/// 64 bits from the system's secure random source.
pub(crate) fn random_u64() -> u64 {
    use ring::rand::SecureRandom;
    let mut b = [0u8; 8];
    let _ = ring::rand::SystemRandom::new().fill(&mut b);
    u64::from_le_bytes(b)
}
