//! The audit log: a SQLite database (WAL, `synchronous=FULL`) with every case event, session
//! start and end, accepted stream message, registration and refusal. A writer thread owns the
//! connection and commits what is waiting in one transaction (group commit); a write returns
//! only once its transaction is durable, and the server acknowledges a registration to its
//! client only after that. The session records let a session resume after a reconnect or a
//! crash (`SessionStart.resume_session_id`), and `librplus-server audit` reads it all back.
//!
//! Format 2 (docs/service.md, "Audit log"): tables `meta` (format), `events`, `sessions` (with
//! the version of the case each session started on), `messages` (each accepted
//! StreamRegisterRequest, protobuf-encoded), `registrations`. A format-1 database (no case
//! version) is migrated in place when opened; its sessions resume without the version check.

use crate::journal::Journal;
pub use crate::journal::SessionRecord;
use rusqlite::{Connection, OptionalExtension, params};
use std::path::{Path, PathBuf};
use std::sync::{Arc, mpsc};
use std::time::{SystemTime, UNIX_EPOCH};

/// The audit database format.
pub const FORMAT: u32 = 4;

/// Why the audit log could not be written or read. Cheap to clone: one failed commit is the
/// answer of every write it held.
#[derive(Debug, Clone, thiserror::Error)]
pub enum AuditError {
    /// SQLite refused (a full disk, a corrupt or foreign file, a locked database).
    #[error("audit database {}: {source}", path.display())]
    Sql {
        /// The database.
        path: PathBuf,
        /// SQLite's error.
        source: Arc<rusqlite::Error>,
    },
    /// The session journal refused a record or its fsync.
    #[error("session journal {}: {source}", dir.display())]
    Journal {
        /// The journal's folder.
        dir: PathBuf,
        /// The system's error.
        source: Arc<std::io::Error>,
    },
    /// Messages were written to the session journal, but another replica claimed the session
    /// meanwhile (its takeover may not have read them): they are not answered.
    #[error(
        "session journal {}: session {session_id} was taken over by another replica",
        dir.display()
    )]
    TakenOver {
        /// The journal's folder.
        dir: PathBuf,
        /// The session.
        session_id: String,
    },
    /// The database is of another format.
    #[error("audit database {}: format {found}, this server reads format {FORMAT}", path.display())]
    Format {
        /// The database.
        path: PathBuf,
        /// Its format.
        found: String,
    },
    /// The writer thread has stopped.
    #[error("the audit writer has stopped")]
    Stopped,
}

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// One record to write.
#[derive(Debug, Clone)]
pub enum Record {
    /// A case event, a refusal, anything else worth keeping (`detail`: JSON).
    Event {
        /// `case_created`, `case_deleted`, `refused`, `server_started`, ...
        kind: &'static str,
        /// Who.
        principal: String,
        /// The case, if any.
        case_id: Option<String>,
        /// The session, if any.
        session_id: Option<String>,
        /// What (JSON).
        detail: serde_json::Value,
    },
    /// A session started: its start message (protobuf-encoded `StreamRegisterRequest`).
    SessionStart {
        /// The session.
        session_id: String,
        /// Who.
        principal: String,
        /// The case.
        case_id: String,
        /// The case's content version when the session started.
        case_version: String,
        /// The start message.
        start: Vec<u8>,
    },
    /// Stream messages a session accepted (client_seq, protobuf-encoded message).
    Messages {
        /// The session.
        session_id: String,
        /// The messages.
        messages: Vec<(u64, Vec<u8>)>,
    },
    /// A registration answered.
    Registration(Box<RegistrationRecord>),
    /// This replica took over a session recorded elsewhere (a resume): the session journal's
    /// next epoch, and the session's row here (so that this replica's log holds its start).
    Takeover {
        /// The session.
        session_id: String,
        /// Who started it.
        principal: String,
        /// The case.
        case_id: String,
        /// The case's content version when the session started.
        case_version: String,
        /// The start message.
        start: Vec<u8>,
        /// The last client_seq recorded before the takeover.
        last_seq: u64,
    },
    /// This replica is about to resume a session: with a session journal, its next epoch is
    /// claimed before the session is read (nothing in the database).
    Claim {
        /// The session.
        session_id: String,
    },
    /// A session ended.
    SessionEnd {
        /// The session.
        session_id: String,
        /// `OK` or the status code's name, and its message.
        outcome: String,
    },
}

/// One registration as audited.
#[derive(Debug, Clone, Default)]
pub struct RegistrationRecord {
    /// Who.
    pub principal: String,
    /// The case.
    pub case_id: String,
    /// The session (None: unary).
    pub session_id: Option<String>,
    /// The newest client message it reflects (sessions).
    pub client_seq: u64,
    /// Method used.
    pub method: String,
    /// Quality flag.
    pub quality: String,
    /// Why not OK.
    pub quality_reason: String,
    /// Milliseconds from arrival to answer.
    pub total_ms: f64,
    /// Residual RMS, mm.
    pub residual_rms_mm: f64,
    /// Points registered.
    pub points_total: u64,
    /// The measurements (unary: the protobuf-encoded `Measurements`; sessions: None, their
    /// points are the session's messages).
    pub measurements: Option<Vec<u8>>,
    /// SHA-256 (hex) of the protobuf-encoded `Registration` sent.
    pub answer_sha256: String,
    /// Stage timings (JSON).
    pub timings: String,
    /// How METHOD_AUTO chose (JSON: chosen, runner_up, margin_mm2, margin_se, runner_up_mm and
    /// each candidate's held-out score; None for the other methods).
    pub choice: Option<String>,
    /// The side test (JSON: target, anterior_mm2, boundary_mm2; None when it did not run).
    pub surface: Option<String>,
}

type Reply = tokio::sync::oneshot::Sender<Result<(), AuditError>>;

/// The audit log's writer (cheap to share: a channel to its thread).
#[derive(Debug)]
pub struct Audit {
    tx: std::sync::Mutex<mpsc::Sender<(Vec<Record>, Reply)>>,
    path: PathBuf,
    journal: Option<PathBuf>,
}

/// Writes a batch's session records into the journal: per item, Ok or why not; `touched`
/// collects the sessions whose appended messages still need their fsync.
fn journal_batch(
    j: &mut Journal,
    batch: &[(Vec<Record>, Reply)],
    touched: &mut Vec<(usize, String)>,
) -> Vec<Result<(), AuditError>> {
    let dir = j.dir().to_path_buf();
    batch
        .iter()
        .enumerate()
        .map(|(i, (records, _))| {
            for r in records {
                let res = match r {
                    Record::SessionStart {
                        session_id,
                        principal,
                        case_id,
                        case_version,
                        start,
                    } => j.start(session_id, principal, case_id, case_version, start),
                    Record::Takeover {
                        session_id,
                        last_seq,
                        ..
                    } => j.takeover(session_id, *last_seq),
                    Record::Messages {
                        session_id,
                        messages,
                    } => j.append(session_id, messages).map(|()| {
                        touched.push((i, session_id.clone()));
                    }),
                    Record::Claim { session_id } => j.claim(session_id),
                    Record::SessionEnd { session_id, .. } => {
                        j.end(session_id);
                        Ok(())
                    }
                    Record::Event { .. } | Record::Registration(_) => Ok(()),
                };
                if let Err(e) = res {
                    tracing::error!(error = %e, journal = %dir.display(), "session journal write failed");
                    metrics::counter!("librplus_journal_failures_total").increment(1);
                    return Err(AuditError::Journal {
                        dir: dir.clone(),
                        source: Arc::new(e),
                    });
                }
            }
            Ok(())
        })
        .collect()
}

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS meta(key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS events(
  id INTEGER PRIMARY KEY, t_ms INTEGER NOT NULL, kind TEXT NOT NULL, principal TEXT,
  case_id TEXT, session_id TEXT, detail TEXT);
CREATE TABLE IF NOT EXISTS sessions(
  session_id TEXT PRIMARY KEY, t_ms INTEGER NOT NULL, principal TEXT NOT NULL,
  case_id TEXT NOT NULL, start BLOB NOT NULL, ended_ms INTEGER, outcome TEXT,
  case_version TEXT);
CREATE TABLE IF NOT EXISTS messages(
  session_id TEXT NOT NULL, client_seq INTEGER NOT NULL, t_ms INTEGER NOT NULL,
  msg BLOB NOT NULL, PRIMARY KEY(session_id, client_seq));
CREATE TABLE IF NOT EXISTS registrations(
  id INTEGER PRIMARY KEY, t_ms INTEGER NOT NULL, principal TEXT NOT NULL, case_id TEXT NOT NULL,
  session_id TEXT, client_seq INTEGER, method TEXT, quality TEXT, quality_reason TEXT,
  total_ms REAL, residual_rms_mm REAL, points_total INTEGER, measurements BLOB,
  answer_sha256 TEXT NOT NULL, timings TEXT, choice TEXT, surface TEXT);
CREATE INDEX IF NOT EXISTS registrations_case ON registrations(case_id, t_ms);
CREATE INDEX IF NOT EXISTS registrations_session ON registrations(session_id);
CREATE INDEX IF NOT EXISTS events_time ON events(t_ms);
";

/// Opens (creating when absent) an audit database and checks its format.
pub fn open_db(path: &Path) -> Result<Connection, AuditError> {
    let sql = |source| AuditError::Sql {
        path: path.to_path_buf(),
        source: Arc::new(source),
    };
    let c = Connection::open(path).map_err(sql)?;
    c.busy_timeout(std::time::Duration::from_secs(10))
        .map_err(sql)?;
    c.pragma_update(None, "journal_mode", "WAL").map_err(sql)?;
    c.pragma_update(None, "synchronous", "FULL").map_err(sql)?;
    c.execute_batch(SCHEMA).map_err(sql)?;
    let found: Option<String> = c
        .query_row("SELECT value FROM meta WHERE key = 'format'", [], |r| {
            r.get(0)
        })
        .optional()
        .map_err(sql)?;
    match found {
        None => {
            c.execute(
                "INSERT INTO meta(key, value) VALUES('format', ?1)",
                [FORMAT.to_string()],
            )
            .map_err(sql)?;
        }
        Some(f) if f == FORMAT.to_string() => {}
        Some(f) if f == "1" || f == "2" || f == "3" => {
            // Format 1 had no case version, formats 1 and 2 no model choice, formats 1 to 3 no
            // side test: the columns are added (NULL for the rows before).
            for (table, column) in [
                ("sessions", "case_version"),
                ("registrations", "choice"),
                ("registrations", "surface"),
            ] {
                let has: bool = c
                    .prepare(&format!(
                        "SELECT 1 FROM pragma_table_info('{table}') WHERE name = '{column}'"
                    ))
                    .and_then(|mut st| st.exists([]))
                    .map_err(sql)?;
                if !has {
                    c.execute(&format!("ALTER TABLE {table} ADD COLUMN {column} TEXT"), [])
                        .map_err(sql)?;
                }
            }
            c.execute(
                "UPDATE meta SET value = ?1 WHERE key = 'format'",
                [FORMAT.to_string()],
            )
            .map_err(sql)?;
        }
        Some(f) => {
            return Err(AuditError::Format {
                path: path.to_path_buf(),
                found: f,
            });
        }
    }
    Ok(c)
}

fn write(c: &Connection, r: &Record, t: i64) -> rusqlite::Result<()> {
    match r {
        Record::Event {
            kind,
            principal,
            case_id,
            session_id,
            detail,
        } => {
            c.execute(
                "INSERT INTO events(t_ms, kind, principal, case_id, session_id, detail) \
                 VALUES(?1, ?2, ?3, ?4, ?5, ?6)",
                params![t, kind, principal, case_id, session_id, detail.to_string()],
            )?;
        }
        Record::SessionStart {
            session_id,
            principal,
            case_id,
            case_version,
            start,
        }
        | Record::Takeover {
            session_id,
            principal,
            case_id,
            case_version,
            start,
            ..
        } => {
            c.execute(
                "INSERT OR IGNORE INTO sessions(session_id, t_ms, principal, case_id, start, \
                 case_version) VALUES(?1, ?2, ?3, ?4, ?5, ?6)",
                params![session_id, t, principal, case_id, start, case_version],
            )?;
        }
        Record::Messages {
            session_id,
            messages,
        } => write_messages(c, session_id, messages, t)?,
        Record::Registration(g) => write_registration(c, g, t)?,
        Record::Claim { .. } => {}
        Record::SessionEnd {
            session_id,
            outcome,
        } => {
            c.execute(
                "UPDATE sessions SET ended_ms = ?2, outcome = ?3 WHERE session_id = ?1",
                params![session_id, t, outcome],
            )?;
        }
    }
    Ok(())
}

/// A session's messages, each under its `client_seq`. A client_seq recorded again with other
/// content is refused (the transaction and so the answer fail), never replaced or dropped; the
/// same content again is kept once.
fn write_messages(
    c: &Connection,
    session_id: &str,
    messages: &[(u64, Vec<u8>)],
    t: i64,
) -> rusqlite::Result<()> {
    let mut st = c.prepare_cached(
        "INSERT INTO messages(session_id, client_seq, t_ms, msg) VALUES(?1, ?2, ?3, ?4) \
         ON CONFLICT(session_id, client_seq) DO NOTHING",
    )?;
    let mut same = c.prepare_cached(
        "SELECT msg = ?3 FROM messages WHERE session_id = ?1 AND client_seq = ?2",
    )?;
    for (seq, m) in messages {
        if st.execute(params![session_id, *seq as i64, t, m])? == 0 {
            let equal: bool = same.query_row(params![session_id, *seq as i64, m], |r| r.get(0))?;
            if !equal {
                return Err(rusqlite::Error::ToSqlConversionFailure(
                    format!(
                        "session {session_id}: client_seq {seq} is recorded with other \
                         content; refused"
                    )
                    .into(),
                ));
            }
        }
    }
    Ok(())
}

/// One acknowledged registration.
fn write_registration(c: &Connection, g: &RegistrationRecord, t: i64) -> rusqlite::Result<()> {
    c.execute(
        "INSERT INTO registrations(t_ms, principal, case_id, session_id, client_seq, \
         method, quality, quality_reason, total_ms, residual_rms_mm, points_total, \
         measurements, answer_sha256, timings, choice, surface) \
         VALUES(?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16)",
        params![
            t,
            g.principal,
            g.case_id,
            g.session_id,
            g.client_seq as i64,
            g.method,
            g.quality,
            g.quality_reason,
            g.total_ms,
            g.residual_rms_mm,
            g.points_total as i64,
            g.measurements,
            g.answer_sha256,
            g.timings,
            g.choice,
            g.surface
        ],
    )?;
    Ok(())
}

impl Audit {
    /// Opens the database and starts its writer thread; with `journal`, session records also
    /// go to the shared session journal (journal.rs), durable before the commit is reported.
    pub fn open(path: &Path, journal: Option<Journal>) -> Result<Self, AuditError> {
        let mut conn = open_db(path)?;
        let journal_dir = journal.as_ref().map(|j| j.dir().to_path_buf());
        let mut journal = journal;
        let (tx, rx) = mpsc::channel::<(Vec<Record>, Reply)>();
        let p = path.to_path_buf();
        std::thread::Builder::new()
            .name("audit-writer".into())
            .spawn(move || {
                // Group commit: everything waiting goes into one transaction.
                while let Ok(first) = rx.recv() {
                    let mut batch = vec![first];
                    while batch.len() < 512 {
                        match rx.try_recv() {
                            Ok(x) => batch.push(x),
                            Err(_) => break,
                        }
                    }
                    let t = now_ms();
                    let t0 = std::time::Instant::now();
                    // The journal first (an item it refuses is not logged as accepted), then
                    // one transaction, then the journal's fsyncs; each item answered after all.
                    let mut touched = Vec::new();
                    let mut results = match journal.as_mut() {
                        Some(j) => journal_batch(j, &batch, &mut touched),
                        None => vec![Ok(()); batch.len()],
                    };
                    let result = (|| -> rusqlite::Result<()> {
                        let txn = conn.transaction()?;
                        for ((records, _), ok) in batch.iter().zip(&results) {
                            if ok.is_ok() {
                                for r in records {
                                    write(&txn, r, t)?;
                                }
                            }
                        }
                        txn.commit()
                    })();
                    let result = result.map_err(|e| {
                        tracing::error!(error = %e, db = %p.display(), "audit write failed");
                        metrics::counter!("librplus_audit_failures_total").increment(1);
                        AuditError::Sql {
                            path: p.clone(),
                            source: Arc::new(e),
                        }
                    });
                    if let Some(j) = journal.as_mut() {
                        if let Err(e) = j.sync(touched.iter().map(|(_, s)| s.as_str())) {
                            let e = AuditError::Journal {
                                dir: j.dir().to_path_buf(),
                                source: Arc::new(e),
                            };
                            tracing::error!(error = %e, "session journal fsync failed");
                            for (i, _) in &touched {
                                results[*i] = Err(e.clone());
                            }
                        }
                        // Written, but another replica claimed the session meanwhile: its
                        // takeover may not have read these messages, so they are not answered.
                        for (i, sid) in &touched {
                            if results[*i].is_ok() && !j.still_held(sid) {
                                results[*i] = Err(AuditError::TakenOver {
                                    dir: j.dir().to_path_buf(),
                                    session_id: sid.clone(),
                                });
                            }
                        }
                    }
                    metrics::counter!("librplus_audit_commits_total").increment(1);
                    metrics::histogram!("librplus_audit_commit_seconds")
                        .record(t0.elapsed().as_secs_f64());
                    for ((_, reply), own) in batch.into_iter().zip(results) {
                        let _ = reply.send(result.clone().and(own));
                    }
                }
            })
            .map_err(|_| AuditError::Stopped)?;
        Ok(Self {
            tx: std::sync::Mutex::new(tx),
            path: path.to_path_buf(),
            journal: journal_dir,
        })
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The shared session journal's folder, when sessions are journaled.
    pub fn journal_dir(&self) -> Option<&Path> {
        self.journal.as_deref()
    }

    /// Writes `records` in one transaction; returns once it is committed (durable), or why not.
    pub async fn write(&self, records: Vec<Record>) -> Result<(), AuditError> {
        let (reply, rx) = tokio::sync::oneshot::channel();
        self.tx
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .send((records, reply))
            .map_err(|_| AuditError::Stopped)?;
        rx.await.map_err(|_| AuditError::Stopped)?
    }
}

/// Reads one session's record (None: no such session).
pub fn read_session(c: &Connection, session_id: &str) -> rusqlite::Result<Option<SessionRecord>> {
    let Some((principal, case_id, start, case_version)) = c
        .query_row(
            "SELECT principal, case_id, start, case_version FROM sessions WHERE session_id = ?1",
            [session_id],
            |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
        )
        .optional()?
    else {
        return Ok(None);
    };
    let mut st = c.prepare(
        "SELECT client_seq, msg FROM messages WHERE session_id = ?1 ORDER BY client_seq",
    )?;
    let messages = st
        .query_map([session_id], |r| {
            Ok((r.get::<_, i64>(0)? as u64, r.get(1)?))
        })?
        .collect::<rusqlite::Result<Vec<_>>>()?;
    Ok(Some(SessionRecord {
        principal,
        case_id,
        case_version,
        start,
        messages,
    }))
}

/// Sessions recorded on case `case_id` at version `version` (or before versions were recorded)
/// since `since_ms`: those a client could still resume.
pub fn count_sessions(
    c: &Connection,
    case_id: &str,
    version: &str,
    since_ms: i64,
) -> rusqlite::Result<u64> {
    c.query_row(
        "SELECT COUNT(*) FROM sessions WHERE case_id = ?1 \
         AND (case_version = ?2 OR case_version IS NULL) AND t_ms >= ?3",
        params![case_id, version, since_ms],
        |r| r.get::<_, i64>(0),
    )
    .map(|n| n as u64)
}

/// A `--since` that is neither Unix seconds nor a UTC date and time.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("--since {given:?}: expected Unix seconds or YYYY-MM-DD[THH:MM[:SS]][Z] (UTC)")]
pub struct SinceError {
    /// What was given.
    pub given: String,
}

/// Reads `--since`: Unix seconds, or a UTC date and time `YYYY-MM-DD[THH:MM[:SS]][Z]`; in ms.
pub fn parse_since(s: &str) -> Result<i64, SinceError> {
    if let Ok(x) = s.parse::<f64>()
        && x.is_finite()
    {
        return Ok((x * 1e3) as i64);
    }
    let bad = || SinceError {
        given: s.to_string(),
    };
    let t = s.trim_end_matches('Z');
    let (date, time) = t.split_once(['T', ' ']).unwrap_or((t, "00:00:00"));
    let d: Vec<i64> = date
        .split('-')
        .map(|x| x.parse().map_err(|_| bad()))
        .collect::<Result<_, _>>()?;
    let h: Vec<i64> = time
        .split(':')
        .map(|x| x.parse().map_err(|_| bad()))
        .collect::<Result<_, _>>()?;
    if d.len() != 3 || h.is_empty() || h.len() > 3 {
        return Err(bad());
    }
    let (y, m, day) = (d[0], d[1], d[2]);
    if !(1..=12).contains(&m) || !(1..=31).contains(&day) {
        return Err(bad());
    }
    // Days from 1970-01-01 (H. Hinnant's days_from_civil).
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    let secs = days * 86_400
        + h[0] * 3600
        + h.get(1).copied().unwrap_or(0) * 60
        + h.get(2).copied().unwrap_or(0);
    Ok(secs * 1000)
}

/// A UTC time `YYYY-MM-DDTHH:MM:SS.mmmZ` from ms since the epoch.
pub fn format_ms(ms: i64) -> String {
    let secs = ms.div_euclid(1000);
    let days = secs.div_euclid(86_400);
    let rem = secs.rem_euclid(86_400);
    // H. Hinnant's civil_from_days.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        ms.rem_euclid(1000)
    )
}

/// One row of `librplus-server audit`.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    /// When (ms since the epoch).
    pub t_ms: i64,
    /// When (UTC).
    pub time: String,
    /// `registration`, `session_start`, `session_end`, or an event's kind.
    pub kind: String,
    /// Who.
    pub principal: String,
    /// The case.
    pub case_id: Option<String>,
    /// The session.
    pub session_id: Option<String>,
    /// What (JSON).
    pub detail: serde_json::Value,
}

impl Row {
    /// The detail as the table of `librplus-server audit` shows it: a refusal as its text
    /// (`DescribeCase NOT_FOUND: case_id "x": ...`), so that the table's own escaping is the
    /// only one (as JSON its quotes would be escaped twice); anything else as JSON.
    pub fn detail_text(&self) -> String {
        let text = |k: &str| self.detail.get(k).and_then(serde_json::Value::as_str);
        if self.kind == "refused"
            && let Some(rpc) = text("rpc")
        {
            match (text("code"), text("message"), text("outcome")) {
                (Some(code), Some(message), _) => return format!("{rpc} {code}: {message}"),
                (_, _, Some(outcome)) => return format!("{rpc} {outcome}"),
                _ => {}
            }
        }
        self.detail.to_string()
    }
}

/// Every record of the database (of `case`, since `since_ms`), in time order.
pub fn rows(
    c: &Connection,
    case: Option<&str>,
    since_ms: Option<i64>,
) -> rusqlite::Result<Vec<Row>> {
    let since = since_ms.unwrap_or(i64::MIN);
    let mut out = Vec::new();
    let row = |t_ms: i64, kind: String, principal: String, case_id, session_id, detail| Row {
        t_ms,
        time: format_ms(t_ms),
        kind,
        principal,
        case_id,
        session_id,
        detail,
    };
    let mut st = c.prepare(
        "SELECT t_ms, kind, principal, case_id, session_id, detail FROM events \
         WHERE t_ms >= ?1 AND (?2 IS NULL OR case_id = ?2)",
    )?;
    for r in st.query_map(params![since, case], |r| {
        Ok(row(
            r.get(0)?,
            r.get(1)?,
            r.get::<_, Option<String>>(2)?.unwrap_or_default(),
            r.get(3)?,
            r.get(4)?,
            r.get::<_, Option<String>>(5)?
                .and_then(|d| serde_json::from_str(&d).ok())
                .unwrap_or(serde_json::Value::Null),
        ))
    })? {
        out.push(r?);
    }
    let mut st = c.prepare(
        "SELECT t_ms, principal, case_id, session_id, ended_ms, outcome, \
         (SELECT COUNT(*) FROM messages m WHERE m.session_id = s.session_id) \
         FROM sessions s WHERE t_ms >= ?1 AND (?2 IS NULL OR case_id = ?2)",
    )?;
    for r in st.query_map(params![since, case], |r| {
        let ended: Option<i64> = r.get(4)?;
        let outcome: Option<String> = r.get(5)?;
        let messages: i64 = r.get(6)?;
        Ok((
            row(
                r.get(0)?,
                "session_start".into(),
                r.get(1)?,
                Some(r.get(2)?),
                Some(r.get(3)?),
                serde_json::json!({ "messages": messages }),
            ),
            ended.map(|t| (t, outcome)),
        ))
    })? {
        let (start, end) = r?;
        if let Some((t, outcome)) = end {
            out.push(Row {
                t_ms: t,
                time: format_ms(t),
                kind: "session_end".into(),
                detail: serde_json::json!({ "outcome": outcome }),
                ..start.clone()
            });
        }
        out.push(start);
    }
    let mut st = c.prepare(
        "SELECT t_ms, principal, case_id, session_id, client_seq, method, quality, \
         quality_reason, total_ms, residual_rms_mm, points_total, answer_sha256, timings, \
         measurements IS NOT NULL, choice, surface FROM registrations \
         WHERE t_ms >= ?1 AND (?2 IS NULL OR case_id = ?2)",
    )?;
    for r in st.query_map(params![since, case], |r| {
        Ok(row(
            r.get(0)?,
            "registration".into(),
            r.get(1)?,
            Some(r.get(2)?),
            r.get(3)?,
            serde_json::json!({
                "client_seq": r.get::<_, Option<i64>>(4)?,
                "method": r.get::<_, Option<String>>(5)?,
                "quality": r.get::<_, Option<String>>(6)?,
                "quality_reason": r.get::<_, Option<String>>(7)?,
                "total_ms": r.get::<_, Option<f64>>(8)?,
                "residual_rms_mm": r.get::<_, Option<f64>>(9)?,
                "points": r.get::<_, Option<i64>>(10)?,
                "answer_sha256": r.get::<_, String>(11)?,
                "timings": r.get::<_, Option<String>>(12)?
                    .and_then(|d| serde_json::from_str::<serde_json::Value>(&d).ok()),
                "measurements_recorded": r.get::<_, bool>(13)?,
                "choice": r.get::<_, Option<String>>(14)?
                    .and_then(|d| serde_json::from_str::<serde_json::Value>(&d).ok()),
                "surface": r.get::<_, Option<String>>(15)?
                    .and_then(|d| serde_json::from_str::<serde_json::Value>(&d).ok()),
            }),
        ))
    })? {
        out.push(r?);
    }
    out.sort_by_key(|r| r.t_ms);
    Ok(out)
}

#[path = "audit_export.rs"]
mod export;
pub use export::{ExportError, Exported, export_session};

#[cfg(test)]
#[path = "audit_tests.rs"]
mod tests;
