//! The session journal: a folder every replica shares (`session_journal`), holding each streamed
//! session's start and accepted messages, so that any replica resumes a session that another
//! one served (a replica killed mid-stream, a rolling restart). The audit log stays each
//! replica's own record; the journal is what resuming reads when it is configured.
//!
//! Layout: `DIR/<session_id>/<epoch>.log`, epochs numbered from 0 (six digits). The replica
//! that starts a session creates epoch 0. A replica that resumes it first claims the next epoch
//! (creates its file, create-new: of two replicas resuming at once, one wins and the other
//! refuses), then reads every epoch, then writes the takeover record into its claimed epoch. A
//! replica appends only to its own epoch, checks before each append that no later epoch exists,
//! and after the append's fsync checks again: an append that a takeover may not have read is
//! never acknowledged (the claim exists before the read, so an append that finds no claim after
//! its fsync was read by any later takeover). So a replica that lost its client without knowing
//! it yet cannot add to, or answer for, a session another replica has taken over. Each record
//! reaches the disk (fsync, and the folder's fsync for a new file) before the client's answer is
//! sent.
//!
//! File format 2: the line `librplus-session-journal 2\n`, then records
//! `[u32 payload length, LE][u32 CRC-32 of the payload, LE][payload]`, the payload a kind byte
//! and its fields:
//! - `1` start: principal, case id and the case's content version (each a u32 LE length and
//!   UTF-8), then the start message (protobuf `StreamRegisterRequest`, the rest);
//! - `2` message: client_seq (u64 LE), then the protobuf `StreamRegisterRequest` (the rest);
//! - `3` takeover (first record of epochs after 0): the last client_seq this epoch continues
//!   from (u64 LE), then the replica's name (UTF-8, the rest).
//!
//! Format 1 (read, not written) is the same without the case version in the start record; such
//! a session resumes without the version check.
//!
//! Reading: a torn record at a file's end (a crash while writing) is ignored (it was never
//! acknowledged); messages of epoch k above epoch k+1's takeover point are ignored (written by a
//! replica that had already lost the session); an epoch claimed and never taken over (a resume
//! that crashed or was refused) holds no record and is skipped.

use std::collections::{BTreeMap, HashMap};
use std::fs::{File, OpenOptions};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

/// The first line of every journal file written.
const MAGIC: &[u8] = b"librplus-session-journal 2\n";
/// The first line of a format-1 file (read only).
const MAGIC_1: &[u8] = b"librplus-session-journal 1\n";
const START: u8 = 1;
const MESSAGE: u8 = 2;
const TAKEOVER: u8 = 3;
/// Largest record accepted when reading (a message is at most a few MiB).
const MAX_RECORD: usize = 256 << 20;

/// Whether `id` can name a journal folder: the server's own session ids (`s` + hex + `-` +
/// digits), nothing a path could be made of.
pub fn valid_id(id: &str) -> bool {
    let Some(rest) = id.strip_prefix('s') else {
        return false;
    };
    let Some((boot, n)) = rest.split_once('-') else {
        return false;
    };
    !boot.is_empty()
        && !n.is_empty()
        && id.len() <= 128
        && boot.bytes().all(|b| b.is_ascii_hexdigit())
        && n.bytes().all(|b| b.is_ascii_digit())
}

/// One replica's writer of the shared journal (used by the audit writer's thread only).
#[derive(Debug)]
pub struct Journal {
    dir: PathBuf,
    replica: String,
    /// Sessions this replica writes: their open epoch file and its number.
    open: HashMap<String, (File, u32)>,
    /// Epochs this replica claimed for a resume, not yet taken over.
    claims: HashMap<String, (File, u32)>,
    /// Session folders untouched this long are removed (sessions end idle long before).
    retention: std::time::Duration,
    last_sweep: std::time::Instant,
}

fn epoch_path(dir: &Path, sid: &str, epoch: u32) -> PathBuf {
    dir.join(sid).join(format!("{epoch:06}.log"))
}

fn record(payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(payload.len() + 8);
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(&crc32fast::hash(payload).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

fn put_str(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(&(s.len() as u32).to_le_bytes());
    out.extend_from_slice(s.as_bytes());
}

/// fsync of a folder, so that a file created in it survives a crash.
fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

impl Journal {
    /// Opens (creating) the shared folder for replica `replica`; session folders untouched for
    /// `retention_h` hours are removed, now and every hour.
    pub fn open(dir: &Path, replica: &str, retention_h: f64) -> io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let j = Self {
            dir: dir.to_path_buf(),
            replica: replica.to_string(),
            open: HashMap::new(),
            claims: HashMap::new(),
            retention: std::time::Duration::from_secs_f64(retention_h.max(0.0) * 3600.0),
            last_sweep: std::time::Instant::now(),
        };
        j.sweep()?;
        Ok(j)
    }

    /// Removes the session folders untouched for longer than the retention.
    fn sweep(&self) -> io::Result<()> {
        let now = std::time::SystemTime::now();
        for e in std::fs::read_dir(&self.dir)?.flatten() {
            let name = e.file_name().to_string_lossy().to_string();
            if !valid_id(&name) || self.open.contains_key(&name) {
                continue;
            }
            let newest = std::fs::read_dir(e.path())
                .into_iter()
                .flatten()
                .flatten()
                .filter_map(|f| f.metadata().and_then(|m| m.modified()).ok())
                .max();
            if newest.is_none_or(|t| now.duration_since(t).is_ok_and(|d| d >= self.retention)) {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        Ok(())
    }

    /// The shared folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Creates epoch `epoch`'s file (create-new) holding the magic line and `first`'s record
    /// (none when empty), durable on return.
    fn create_file(&self, sid: &str, epoch: u32, first: &[u8]) -> io::Result<File> {
        if !valid_id(sid) {
            return Err(io::Error::other(format!("{sid:?} is not a session id")));
        }
        let folder = self.dir.join(sid);
        let new_folder = !folder.exists();
        std::fs::create_dir_all(&folder)?;
        let path = epoch_path(&self.dir, sid, epoch);
        let mut f = OpenOptions::new()
            .append(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| {
                if e.kind() == io::ErrorKind::AlreadyExists {
                    io::Error::new(
                        e.kind(),
                        format!("session {sid} is being resumed by another replica"),
                    )
                } else {
                    e
                }
            })?;
        let mut bytes = MAGIC.to_vec();
        if !first.is_empty() {
            bytes.extend_from_slice(&record(first));
        }
        f.write_all(&bytes)?;
        f.sync_data()?;
        sync_dir(&folder)?;
        if new_folder {
            sync_dir(&self.dir)?;
        }
        Ok(f)
    }

    fn create(&mut self, sid: &str, epoch: u32, first: &[u8]) -> io::Result<()> {
        let f = self.create_file(sid, epoch, first)?;
        self.open.insert(sid.to_string(), (f, epoch));
        Ok(())
    }

    /// Claims the next epoch of a session this replica is about to resume, before it reads the
    /// session (durable on return): from now no other replica acknowledges a message of it.
    /// Err (AlreadyExists) when another replica claimed it at the same time.
    pub fn claim(&mut self, sid: &str) -> io::Result<()> {
        let epoch = epochs(&self.dir, sid)?.last().map_or(0, |e| e + 1);
        let f = self.create_file(sid, epoch, &[])?;
        self.claims.insert(sid.to_string(), (f, epoch));
        Ok(())
    }

    /// A new session: its epoch 0 with the start record (durable on return).
    pub fn start(
        &mut self,
        sid: &str,
        principal: &str,
        case_id: &str,
        case_version: &str,
        start: &[u8],
    ) -> io::Result<()> {
        let mut p = vec![START];
        put_str(&mut p, principal);
        put_str(&mut p, case_id);
        put_str(&mut p, case_version);
        p.extend_from_slice(start);
        self.create(sid, 0, &p)
    }

    /// This replica takes a session over after `last_seq` (durable on return): the epoch after
    /// the newest one. Err (AlreadyExists) when another replica took it at the same time.
    pub fn takeover(&mut self, sid: &str, last_seq: u64) -> io::Result<()> {
        let mut p = vec![TAKEOVER];
        p.extend_from_slice(&last_seq.to_le_bytes());
        p.extend_from_slice(self.replica.as_bytes());
        // Into the epoch claimed before the read, when there is one.
        if let Some((mut f, epoch)) = self.claims.remove(sid) {
            if epoch_path(&self.dir, sid, epoch + 1).exists() {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!("session {sid} is being resumed by another replica"),
                ));
            }
            f.write_all(&record(&p))?;
            f.sync_data()?;
            self.open.insert(sid.to_string(), (f, epoch));
            return Ok(());
        }
        let epoch = epochs(&self.dir, sid)?.last().map_or(0, |e| e + 1);
        self.create(sid, epoch, &p)
    }

    /// Whether this replica still holds `sid` after its appends reached the disk: no later
    /// epoch was claimed. An append is acknowledged only when this holds after its fsync.
    pub fn still_held(&self, sid: &str) -> bool {
        self.open
            .get(sid)
            .is_some_and(|(_, epoch)| !epoch_path(&self.dir, sid, epoch + 1).exists())
    }

    /// Appends accepted messages (written, not yet synced: [`Journal::sync`]). Err when this
    /// replica does not hold the session (another took it over, or it was never started here).
    pub fn append(&mut self, sid: &str, messages: &[(u64, Vec<u8>)]) -> io::Result<()> {
        let Some((f, epoch)) = self.open.get_mut(sid) else {
            return Err(io::Error::other(format!(
                "session {sid} is not held by this replica"
            )));
        };
        if epoch_path(&self.dir, sid, *epoch + 1).exists() {
            self.open.remove(sid);
            return Err(io::Error::other(format!(
                "session {sid} was taken over by another replica"
            )));
        }
        let mut bytes = Vec::new();
        for (seq, m) in messages {
            let mut p = Vec::with_capacity(m.len() + 9);
            p.push(MESSAGE);
            p.extend_from_slice(&seq.to_le_bytes());
            p.extend_from_slice(m);
            bytes.extend_from_slice(&record(&p));
        }
        f.write_all(&bytes)
    }

    /// Makes the appended messages of these sessions durable.
    pub fn sync<'a>(&mut self, sids: impl IntoIterator<Item = &'a str>) -> io::Result<()> {
        for sid in sids {
            if let Some((f, _)) = self.open.get(sid) {
                f.sync_data()?;
            }
        }
        Ok(())
    }

    /// A session ended here: its file is closed (the folder stays until the retention ends:
    /// a client whose stream was lost may still resume it elsewhere).
    pub fn end(&mut self, sid: &str) {
        self.open.remove(sid);
        self.claims.remove(sid);
        if self.last_sweep.elapsed() > std::time::Duration::from_secs(3600) {
            self.last_sweep = std::time::Instant::now();
            let _ = self.sweep();
        }
    }
}

/// The epochs of a session present in the folder, ascending.
fn epochs(dir: &Path, sid: &str) -> io::Result<Vec<u32>> {
    let mut out = Vec::new();
    let folder = dir.join(sid);
    let rd = match std::fs::read_dir(&folder) {
        Ok(rd) => rd,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(out),
        Err(e) => return Err(e),
    };
    for e in rd {
        let name = e?.file_name().to_string_lossy().to_string();
        if let Some(n) = name
            .strip_suffix(".log")
            .and_then(|s| s.parse::<u32>().ok())
        {
            out.push(n);
        }
    }
    out.sort_unstable();
    Ok(out)
}

/// Why a session's record could not be read from the journal.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// A folder or file does not read.
    #[error("{}: {source}", path.display())]
    Io {
        /// The folder or file.
        path: PathBuf,
        /// The system's error.
        source: io::Error,
    },
    /// A file that is not a session journal.
    #[error(
        "{}: not a session journal of format 2 or 1 (first line {first:?})",
        path.display()
    )]
    NotAJournal {
        /// The file.
        path: PathBuf,
        /// Its first bytes (40 at most, lossy UTF-8).
        first: String,
    },
    /// A complete record that is malformed or out of place.
    #[error("{}: {problem}", path.display())]
    Broken {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: Broken,
    },
}

/// What is wrong with a journal file's records.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum Broken {
    /// A record with no kind byte.
    #[error("an empty record")]
    Empty,
    /// A start record cut short.
    #[error("a short start")]
    ShortStart,
    /// A takeover record cut short.
    #[error("a short takeover")]
    ShortTakeover,
    /// A message record cut short.
    #[error("a short message")]
    ShortMessage,
    /// A record whose kind does not belong at its place.
    #[error("record {index} of kind {kind} is out of place")]
    OutOfPlace {
        /// Its index in the file.
        index: usize,
        /// Its kind byte.
        kind: u8,
    },
}

/// The format and complete records of one file (a torn tail ignored).
fn read_records(path: &Path) -> Result<(u32, Vec<Vec<u8>>), ReadError> {
    let mut bytes = Vec::new();
    File::open(path)
        .and_then(|mut f| f.read_to_end(&mut bytes))
        .map_err(|source| ReadError::Io {
            path: path.to_path_buf(),
            source,
        })?;
    let (format, mut rest) = match (bytes.strip_prefix(MAGIC), bytes.strip_prefix(MAGIC_1)) {
        (Some(r), _) => (2, r),
        (None, Some(r)) => (1, r),
        (None, None) => {
            return Err(ReadError::NotAJournal {
                path: path.to_path_buf(),
                first: String::from_utf8_lossy(&bytes[..bytes.len().min(40)]).into_owned(),
            });
        }
    };
    let mut out = Vec::new();
    while rest.len() >= 8 {
        let len = u32::from_le_bytes(rest[0..4].try_into().expect("4 bytes")) as usize;
        let crc = u32::from_le_bytes(rest[4..8].try_into().expect("4 bytes"));
        if len > MAX_RECORD || rest.len() < 8 + len {
            break; // torn
        }
        let payload = &rest[8..8 + len];
        if crc32fast::hash(payload) != crc {
            break; // torn (or damaged): nothing after it was acknowledged either
        }
        out.push(payload.to_vec());
        rest = &rest[8 + len..];
    }
    Ok((format, out))
}

fn take_str(p: &mut &[u8]) -> Option<String> {
    if p.len() < 4 {
        return None;
    }
    let n = u32::from_le_bytes(p[0..4].try_into().ok()?) as usize;
    let s = std::str::from_utf8(p.get(4..4 + n)?).ok()?.to_string();
    *p = &p[4 + n..];
    Some(s)
}

fn take_u64(p: &mut &[u8]) -> Option<u64> {
    let v = u64::from_le_bytes(p.get(0..8)?.try_into().ok()?);
    *p = &p[8..];
    Some(v)
}

/// A recorded session: its principal, case, start message and accepted messages in order.
#[derive(Debug, Clone)]
pub struct SessionRecord {
    /// Who started it.
    pub principal: String,
    /// Its case.
    pub case_id: String,
    /// The case's content version when it started (None: recorded before versions were).
    pub case_version: Option<String>,
    /// The start message (protobuf `StreamRegisterRequest`).
    pub start: Vec<u8>,
    /// (client_seq, protobuf `StreamRegisterRequest`), in client_seq order.
    pub messages: Vec<(u64, Vec<u8>)>,
}

/// Reads a session's record from the shared folder (None: no such session).
pub fn read(dir: &Path, sid: &str) -> Result<Option<SessionRecord>, ReadError> {
    if !valid_id(sid) {
        return Ok(None);
    }
    let list = epochs(dir, sid).map_err(|source| ReadError::Io {
        path: dir.join(sid),
        source,
    })?;
    let mut head: Option<(String, String, Option<String>, Vec<u8>)> = None;
    let mut messages: BTreeMap<u64, Vec<u8>> = BTreeMap::new();
    for epoch in list {
        let path = epoch_path(dir, sid, epoch);
        let broken = |problem: Broken| ReadError::Broken {
            path: path.clone(),
            problem,
        };
        let (format, records) = read_records(&path)?;
        for (i, rec) in records.into_iter().enumerate() {
            let Some((&kind, mut p)) = rec.split_first() else {
                return Err(broken(Broken::Empty));
            };
            match kind {
                START if epoch == 0 && i == 0 => {
                    let principal = take_str(&mut p).ok_or_else(|| broken(Broken::ShortStart))?;
                    let case = take_str(&mut p).ok_or_else(|| broken(Broken::ShortStart))?;
                    let version = match format {
                        1 => None,
                        _ => Some(take_str(&mut p).ok_or_else(|| broken(Broken::ShortStart))?),
                    };
                    head = Some((principal, case, version, p.to_vec()));
                }
                TAKEOVER if epoch > 0 && i == 0 => {
                    let last = take_u64(&mut p).ok_or_else(|| broken(Broken::ShortTakeover))?;
                    // What the previous epochs wrote after the takeover point is void.
                    messages.retain(|&seq, _| seq <= last);
                }
                MESSAGE if i > 0 => {
                    let seq = take_u64(&mut p).ok_or_else(|| broken(Broken::ShortMessage))?;
                    messages.insert(seq, p.to_vec());
                }
                kind => return Err(broken(Broken::OutOfPlace { index: i, kind })),
            }
        }
    }
    let Some((principal, case_id, case_version, start)) = head else {
        return Ok(None);
    };
    Ok(Some(SessionRecord {
        principal,
        case_id,
        case_version,
        start,
        messages: messages.into_iter().collect(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msgs(r: std::ops::RangeInclusive<u64>) -> Vec<(u64, Vec<u8>)> {
        r.map(|s| (s, format!("m{s}").into_bytes())).collect()
    }

    #[test]
    fn ids_that_could_be_paths_are_refused() {
        assert!(valid_id("s18f3a-12"));
        for bad in [
            "", "s-1", "s12-", "s1g-2", "../s1-2", "s1-2/..", "x1-2", "s1-2-3",
        ] {
            assert!(!valid_id(bad), "{bad:?}");
        }
    }

    #[test]
    fn a_session_resumes_across_replicas_and_a_stale_writer_is_fenced() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = Journal::open(dir.path(), "a", 24.0).unwrap();
        let mut b = Journal::open(dir.path(), "b", 24.0).unwrap();
        a.start("s1-1", "alice", "g1", "v1", b"start").unwrap();
        a.append("s1-1", &msgs(1..=3)).unwrap();
        a.sync(["s1-1"]).unwrap();
        let r = read(dir.path(), "s1-1").unwrap().unwrap();
        assert_eq!((r.principal.as_str(), r.case_id.as_str()), ("alice", "g1"));
        assert_eq!(r.start, b"start");
        assert_eq!(r.case_version.as_deref(), Some("v1"));
        assert_eq!(r.messages, msgs(1..=3));
        // b takes over after message 3; a, not knowing, cannot add message 4.
        b.takeover("s1-1", 3).unwrap();
        let e = a.append("s1-1", &msgs(4..=4)).unwrap_err();
        assert!(e.to_string().contains("taken over"), "{e}");
        b.append("s1-1", &msgs(4..=5)).unwrap();
        // A third replica resuming at the same instant as another loses the race cleanly.
        let mut c = Journal::open(dir.path(), "c", 24.0).unwrap();
        let mut d = Journal::open(dir.path(), "d", 24.0).unwrap();
        c.takeover("s1-1", 5).unwrap();
        // d computed the same next epoch: simulate by creating it by hand.
        let e = d.create("s1-1", 2, &[TAKEOVER]).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        assert!(e.to_string().contains("being resumed"), "{e}");
        let r = read(dir.path(), "s1-1").unwrap().unwrap();
        assert_eq!(r.messages, msgs(1..=5));
        // Kept after its end; removed once the retention is over (0 h here).
        c.end("s1-1");
        assert!(read(dir.path(), "s1-1").unwrap().is_some());
        std::fs::create_dir_all(dir.path().join("not-a-session")).unwrap();
        Journal::open(dir.path(), "e", 0.0).unwrap();
        assert!(read(dir.path(), "s1-1").unwrap().is_none());
        assert!(dir.path().join("not-a-session").exists());
    }

    #[test]
    fn a_claim_before_the_read_fences_the_holder_and_a_bare_claim_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = Journal::open(dir.path(), "a", 24.0).unwrap();
        let mut b = Journal::open(dir.path(), "b", 24.0).unwrap();
        a.start("s3-1", "p", "c", "v", b"s").unwrap();
        a.append("s3-1", &msgs(1..=2)).unwrap();
        a.sync(["s3-1"]).unwrap();
        assert!(a.still_held("s3-1"));
        // b claims epoch 1 before reading: a's message 3, written after the claim, is written
        // but a finds after its fsync that it no longer holds the session (not answered).
        b.claim("s3-1").unwrap();
        assert!(!a.still_held("s3-1"));
        assert!(a.append("s3-1", &msgs(3..=3)).is_err());
        // The claimed epoch holds nothing yet: the session reads as before.
        let r = read(dir.path(), "s3-1").unwrap().unwrap();
        assert_eq!(r.messages, msgs(1..=2));
        // A second replica claiming the same epoch at once loses.
        let mut c = Journal::open(dir.path(), "c", 24.0).unwrap();
        let e = c.create_file("s3-1", 1, &[]).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        b.takeover("s3-1", 2).unwrap();
        b.append("s3-1", &[(3, b"b3".to_vec())]).unwrap();
        b.sync(["s3-1"]).unwrap();
        assert!(b.still_held("s3-1"));
        let r = read(dir.path(), "s3-1").unwrap().unwrap();
        assert_eq!(
            r.messages,
            vec![
                (1, b"m1".to_vec()),
                (2, b"m2".to_vec()),
                (3, b"b3".to_vec())
            ]
        );
        // A claim that is never taken over (the resume crashed) is skipped, and the next resume
        // claims the epoch after it; a claim taken over after a newer claim is refused.
        c.claim("s3-1").unwrap();
        assert!(!b.still_held("s3-1"));
        let r = read(dir.path(), "s3-1").unwrap().unwrap();
        assert_eq!(r.messages.len(), 3);
        let mut d = Journal::open(dir.path(), "d", 24.0).unwrap();
        d.claim("s3-1").unwrap();
        assert!(epoch_path(dir.path(), "s3-1", 3).exists());
        let e = c.takeover("s3-1", 3).unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::AlreadyExists);
        d.takeover("s3-1", 3).unwrap();
        d.append("s3-1", &msgs(4..=4)).unwrap();
        let r = read(dir.path(), "s3-1").unwrap().unwrap();
        assert_eq!(r.messages.len(), 4);
    }

    #[test]
    fn writes_after_the_takeover_point_and_torn_tails_are_ignored() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = Journal::open(dir.path(), "a", 24.0).unwrap();
        a.start("s2-7", "p", "c", "v", b"s").unwrap();
        a.append("s2-7", &msgs(1..=2)).unwrap();
        // Replica b took over after message 1 (it had read before message 2 reached the file).
        let mut b = Journal::open(dir.path(), "b", 24.0).unwrap();
        b.takeover("s2-7", 1).unwrap();
        b.append("s2-7", &[(2, b"again".to_vec())]).unwrap();
        // A crash in the middle of b's next record.
        b.append("s2-7", &msgs(3..=3)).unwrap();
        let path = epoch_path(dir.path(), "s2-7", 1);
        let len = std::fs::metadata(&path).unwrap().len();
        OpenOptions::new()
            .write(true)
            .open(&path)
            .unwrap()
            .set_len(len - 2)
            .unwrap();
        let r = read(dir.path(), "s2-7").unwrap().unwrap();
        assert_eq!(
            r.messages,
            vec![(1, b"m1".to_vec()), (2, b"again".to_vec())]
        );
        // A flipped byte in a payload ends the file's records there, too.
        let p0 = epoch_path(dir.path(), "s2-7", 0);
        let mut bytes = std::fs::read(&p0).unwrap();
        let n = bytes.len();
        bytes[n - 1] ^= 0xff;
        std::fs::write(&p0, bytes).unwrap();
        let r = read(dir.path(), "s2-7").unwrap().unwrap();
        assert_eq!(
            r.messages,
            vec![(1, b"m1".to_vec()), (2, b"again".to_vec())]
        );
        // A format-1 file (no case version) is read.
        let mut p = vec![START];
        put_str(&mut p, "p");
        put_str(&mut p, "c");
        p.extend_from_slice(b"s1");
        let mut old = MAGIC_1.to_vec();
        old.extend_from_slice(&record(&p));
        std::fs::write(&p0, old).unwrap();
        let r = read(dir.path(), "s2-7").unwrap().unwrap();
        assert_eq!((r.case_version, r.start), (None, b"s1".to_vec()));
        // Not a journal.
        std::fs::write(&p0, b"hello").unwrap();
        let e = read(dir.path(), "s2-7").unwrap_err();
        assert!(matches!(e, ReadError::NotAJournal { .. }), "{e:?}");
        assert!(e.to_string().contains("not a session journal"), "{e}");
    }
}
