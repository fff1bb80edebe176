//! `CreateCase` and `DeleteCase`: an upload received in chunks, checked (every check preload
//! makes short of the LIBR basis, [`store::validate`]), stored within the store's quotas
//! ([`store::Quotas`]) and preloaded in the background; a stored case deleted when no session
//! uses it. An upload that passes the checks and still fails to preload is removed from the
//! store (its FAILED status keeps the reason), so that it is not reloaded at every start and
//! holds no quota.

use crate::access;
use crate::audit::Record;
use crate::auth::Principal;
use crate::error::{Deadline, Internal, PermissionDenied, ServiceError, Unavailable};
use crate::preload::preload;
use crate::shared::{Shared, UploadSlot};
use crate::store::{self, MeshSource, StoreError, Upload};
use librplus_proto::v1 as pb;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tonic::Streaming;

/// Longest wait for the next message of an upload.
const CHUNK_WAIT: Duration = Duration::from_secs(30);

/// An upload's minimum average rate is enforced from this long after its start.
const RATE_GRACE: Duration = Duration::from_secs(10);

/// An upload's pace: its bytes so far against the server's minimum rate
/// (`min_upload_bytes_per_s`), so that a trickle ends instead of holding an upload slot.
struct Pace {
    start: Instant,
    bytes: u64,
    min_per_s: u64,
}

impl Pace {
    fn new(min_per_s: u64) -> Self {
        Self {
            start: Instant::now(),
            bytes: 0,
            min_per_s,
        }
    }

    fn add(&mut self, n: usize) {
        self.bytes = self.bytes.saturating_add(n as u64);
    }

    /// When the upload falls below the minimum rate unless more bytes come (None: no
    /// minimum).
    fn too_slow_at(&self) -> Option<Instant> {
        (self.min_per_s > 0).then(|| {
            let due = Duration::from_secs_f64(self.bytes as f64 / self.min_per_s as f64);
            self.start + due.max(RATE_GRACE)
        })
    }

    fn too_slow(&self) -> ServiceError {
        Deadline::UploadSlow {
            received: self.bytes,
            after: self.start.elapsed(),
            min_per_s: self.min_per_s,
        }
        .into()
    }
}

fn no_store() -> ServiceError {
    ServiceError::precondition(
        "CASE",
        "upload",
        "the server keeps no case store",
        "this server keeps no case store (case_store, --case-store): cases cannot be uploaded or deleted",
    )
}

/// The next part of an upload: within [`CHUNK_WAIT`], and before the upload falls below its
/// minimum rate.
async fn next(
    inbound: &mut Streaming<pb::CreateCaseRequest>,
    pace: &Pace,
) -> Result<Option<pb::create_case_request::Part>, ServiceError> {
    let idle_at = Instant::now() + CHUNK_WAIT;
    let slow_at = pace.too_slow_at().filter(|&t| t < idle_at);
    let until = slow_at.unwrap_or(idle_at);
    match tokio::time::timeout_at(until.into(), inbound.message()).await {
        Err(_) if slow_at.is_some() => Err(pace.too_slow()),
        Err(_) => Err(Deadline::UploadIdle { waited: CHUNK_WAIT }.into()),
        Ok(Err(s)) => Err(ServiceError::Received {
            code: s.code(),
            message: format!("receiving the upload: {}", s.message()),
        }),
        Ok(Ok(None)) => Ok(None),
        Ok(Ok(Some(m))) => match m.part {
            Some(p) => Ok(Some(p)),
            None => Err(ServiceError::field(
                "part",
                "is empty: set upload (first) or chunk",
            )),
        },
    }
}

/// Receives, checks, stores and starts preloading an upload.
pub async fn create(
    shared: &Arc<Shared>,
    who: &Arc<Principal>,
    mut inbound: Streaming<pb::CreateCaseRequest>,
) -> Result<pb::CreateCaseResponse, ServiceError> {
    let _slot = admit(shared, who)?;
    let mut pace = Pace::new(shared.config.min_upload_bytes_per_s);
    let Some(pb::create_case_request::Part::Upload(up)) = next(&mut inbound, &pace).await? else {
        return Err(ServiceError::field(
            "part",
            "the first message of an upload must be a CaseUpload",
        ));
    };
    let pb::CaseUpload {
        case_id,
        mesh_format,
        mesh_unit,
        nodes_mm,
        tets,
        total_bytes,
    } = up;
    let array_bytes = (nodes_mm.len() * 8 + tets.len() * 4) as u64;
    let quotas = check_header(shared, who, &case_id, total_bytes.max(array_bytes))?;
    let arrays = !nodes_mm.is_empty() || !tets.is_empty();
    if arrays && !mesh_format.is_empty() {
        return Err(ServiceError::field(
            "upload.mesh_format",
            "is set while nodes_mm/tets carry the mesh: send one or the other",
        ));
    }
    let mut received = array_bytes;
    pace.add(received as usize);
    let files = receive(
        &mut inbound,
        arrays,
        (&mut received, &mut pace),
        shared.config.max_case_bytes,
    )
    .await?;
    check_not_configured(shared, &case_id)?;
    let upload = Upload {
        case_id: case_id.clone(),
        mesh: if arrays {
            MeshSource::Arrays {
                nodes: nodes_mm,
                tets,
            }
        } else {
            MeshSource::File {
                bytes: files.mesh,
                format: mesh_format,
            }
        },
        unit: mesh_unit,
        vessels: files.vessels,
        physics: files.physics,
    };
    let (stored, created) = put(shared, who, upload, quotas).await?;
    if created {
        record_created(shared, who, &case_id, &stored, received).await?;
    }
    let status = match shared.registry.status(&case_id) {
        // A new copy in the store is preloaded (also after a failed one of the same content).
        Some(s) if s.version == stored.version && !created => s,
        _ => preload(shared.clone(), stored.clone()),
    };
    Ok(pb::CreateCaseResponse {
        case_id,
        version: stored.version,
        created,
        status: Some(status),
        node_count: stored.nodes as u32,
        tet_count: stored.tets as u32,
    })
}

/// Admits an upload: the server keeps a case store and is not shutting down, the cases can be
/// listed, and `who` and the server receive fewer uploads than their limits (each is held in
/// memory until stored: a few at once, [`Shared::admit_upload`]). The slot it holds.
fn admit(shared: &Arc<Shared>, who: &Principal) -> Result<UploadSlot, ServiceError> {
    if shared.store.is_none() {
        return Err(no_store());
    }
    if *shared.drain.borrow() {
        return Err(Unavailable::ShuttingDown.into());
    }
    access::cases(shared)?;
    shared.admit_upload(who)
}

/// An upload of `n` bytes, above the server's `max` (`max_case_bytes`).
fn too_big(n: u64, max: usize) -> ServiceError {
    ServiceError::Quota {
        message: format!("upload: {n} bytes, above the server's limit of {max} bytes"),
        subject: "case_bytes",
        description: format!("at most {max} bytes per upload (max_case_bytes)"),
    }
}

/// Checks what the first message says before the upload is received: the case id's form, that
/// `who` may use it, the bytes it announces or carries against `max_case_bytes`, and the store's
/// quotas (checked again, under the store's lock, when the case is stored; a retry of a stored
/// case is no new case). The quotas in force.
fn check_header(
    shared: &Arc<Shared>,
    who: &Arc<Principal>,
    case_id: &str,
    total_bytes: u64,
) -> Result<store::Quotas, ServiceError> {
    store::check_id(case_id).map_err(|e| ServiceError::field("upload.case_id", e.to_string()))?;
    if !who.may_use(case_id) {
        return Err(PermissionDenied::CaseOutside {
            principal: who.name.clone(),
            case_id: case_id.to_string(),
        }
        .into());
    }
    let cfg = &shared.config;
    let max = cfg.max_case_bytes;
    if total_bytes > max as u64 {
        return Err(too_big(total_bytes, max));
    }
    let quotas = store::Quotas::from_config(cfg);
    let store = shared.store.as_ref().expect("checked");
    if store.find(case_id).is_none() {
        store
            .check_quota(&who.name, total_bytes, &quotas)
            .map_err(StoreError::into_service)?;
    }
    Ok(quotas)
}

/// The files of an upload, as received in its chunks.
struct Files {
    /// The mesh file's bytes (empty when the arrays carry the mesh).
    mesh: Vec<u8>,
    /// Vessel centerlines (.vtp bytes), if sent.
    vessels: Option<Vec<u8>>,
    /// physics.json bytes, if sent.
    physics: Option<Vec<u8>>,
}

/// Receives the upload's chunks to the end of the stream, counting their bytes in `received`
/// (at most `max`) and in its `pace`. `arrays`: the first message carried the mesh, so no mesh chunk may come;
/// else a mesh must.
async fn receive(
    inbound: &mut Streaming<pb::CreateCaseRequest>,
    arrays: bool,
    (received, pace): (&mut u64, &mut Pace),
    max: usize,
) -> Result<Files, ServiceError> {
    let (mut mesh, mut vessels, mut physics) = (Vec::new(), None::<Vec<u8>>, None::<Vec<u8>>);
    while let Some(part) = next(inbound, pace).await? {
        let pb::create_case_request::Part::Chunk(pb::CaseChunk { file, data }) = part else {
            return Err(ServiceError::field(
                "part",
                "a second CaseUpload: only the first message describes the upload",
            ));
        };
        *received += data.len() as u64;
        pace.add(data.len());
        if *received > max as u64 {
            return Err(too_big(*received, max));
        }
        match pb::CaseFile::try_from(file) {
            Ok(pb::CaseFile::Mesh) if arrays => {
                return Err(ServiceError::field(
                    "chunk.file",
                    "CASE_FILE_MESH chunks while nodes_mm/tets carry the mesh",
                ));
            }
            Ok(pb::CaseFile::Mesh) => mesh.extend_from_slice(&data),
            Ok(pb::CaseFile::Vessels) => vessels.get_or_insert_with(Vec::new).extend(data),
            Ok(pb::CaseFile::Physics) => physics.get_or_insert_with(Vec::new).extend(data),
            _ => {
                return Err(ServiceError::field(
                    "chunk.file",
                    format!(
                        "{file}: expected CASE_FILE_MESH, CASE_FILE_VESSELS or CASE_FILE_PHYSICS"
                    ),
                ));
            }
        }
    }
    if !arrays && mesh.is_empty() {
        return Err(ServiceError::field(
            "chunk",
            "no mesh: send CASE_FILE_MESH chunks (with upload.mesh_format) or upload.nodes_mm and upload.tets",
        ));
    }
    Ok(Files {
        mesh,
        vessels,
        physics,
    })
}

/// Refuses the id of a case the server was started with (it keeps its id; an upload that failed
/// and was removed from the store does not).
fn check_not_configured(shared: &Arc<Shared>, case_id: &str) -> Result<(), ServiceError> {
    let store = shared.store.as_ref().expect("checked");
    if shared.registry.status(case_id).is_some()
        && !shared.registry.is_uploaded(case_id)
        && store.find(case_id).is_none()
    {
        return Err(ServiceError::precondition(
            "CASE",
            "upload.case_id",
            format!("case {case_id} exists"),
            format!(
                "upload.case_id: the server was started with a case {case_id:?}; choose another id"
            ),
        ));
    }
    Ok(())
}

/// Checks the upload ([`store::check`], up to `max_case_nodes`) and stores it within `quotas`,
/// off the async threads; (the stored case, whether it is new).
async fn put(
    shared: &Arc<Shared>,
    who: &Arc<Principal>,
    upload: Upload,
    quotas: store::Quotas,
) -> Result<(store::Stored, bool), ServiceError> {
    let sh = shared.clone();
    let principal = who.name.clone();
    let max_nodes = shared.config.max_case_nodes;
    tokio::task::spawn_blocking(move || {
        let checked = store::check(&upload, max_nodes)?;
        let store = sh.store.as_ref().expect("checked");
        store
            .put(&upload, &checked, &principal, &quotas)
            .map_err(StoreError::into_service)
    })
    .await
    .map_err(|source| Internal::Task {
        doing: "storing the upload",
        source,
    })?
}

/// Records a new case in the audit log (the upload is acknowledged once recorded) and logs it.
async fn record_created(
    shared: &Arc<Shared>,
    who: &Arc<Principal>,
    case_id: &str,
    stored: &store::Stored,
    received: u64,
) -> Result<(), ServiceError> {
    shared
        .record(vec![Record::Event {
            kind: "case_created",
            principal: who.name.clone(),
            case_id: Some(case_id.to_string()),
            session_id: None,
            detail: serde_json::json!({
                "version": stored.version, "nodes": stored.nodes, "tets": stored.tets,
                "bytes": received, "vessels": stored.vessels, "physics": stored.physics,
            }),
        }])
        .await?;
    tracing::info!(case = %case_id, version = %stored.version, nodes = stored.nodes, principal = %who.name, "case uploaded; preloading");
    Ok(())
}

/// Deletes an uploaded case no session uses.
pub async fn delete(
    shared: &Arc<Shared>,
    who: &Arc<Principal>,
    case_id: &str,
) -> Result<pb::DeleteCaseResponse, ServiceError> {
    let Some(store) = &shared.store else {
        return Err(no_store());
    };
    let status = access::visible(case_id, who)
        .then(|| shared.registry.status(case_id))
        .flatten();
    let Some(status) = status else {
        return Err(access::not_found(shared, case_id, "case_id", who));
    };
    if status.state == pb::CaseState::Loading as i32 {
        return Err(ServiceError::precondition(
            "CASE",
            "case_id",
            "the case is loading",
            format!(
                "case_id: case {case_id:?} is still loading; delete it when it is READY or FAILED"
            ),
        ));
    }
    let Some(stored) = store.find(case_id) else {
        if shared.registry.is_uploaded(case_id) {
            // An upload that failed to preload, already removed from the store: its FAILED
            // status is forgotten.
            shared.registry.remove(case_id);
            shared
                .record(vec![Record::Event {
                    kind: "case_deleted",
                    principal: who.name.clone(),
                    case_id: Some(case_id.to_string()),
                    session_id: None,
                    detail: serde_json::json!({ "version": status.version, "failed": true }),
                }])
                .await?;
            return Ok(pb::DeleteCaseResponse {
                case_id: case_id.to_string(),
                version: status.version,
                ..Default::default()
            });
        }
        return Err(ServiceError::precondition(
            "CASE",
            "case_id",
            "not an uploaded case",
            format!(
                "case_id: the server was started with case {case_id:?}; only uploaded cases are deleted over the API"
            ),
        ));
    };
    let in_use = |c: &crate::cases::Case| c.sessions.load(Ordering::SeqCst);
    let busy = |n: usize| {
        ServiceError::precondition(
            "CASE",
            "case_id",
            "sessions use the case",
            format!("case_id: {n} session(s) use case {case_id:?}; delete it when they have ended"),
        )
    };
    let ready = shared.registry.ready().get(case_id).cloned();
    if let Some(c) = &ready
        && in_use(c) > 0
    {
        return Err(busy(in_use(c)));
    }
    shared.registry.remove(case_id);
    // A session that started meanwhile keeps it.
    if let Some(c) = &ready
        && in_use(c) > 0
    {
        shared
            .registry
            .set(crate::registry::ready_status(c), Some(c.clone()));
        return Err(busy(in_use(c)));
    }
    let sh = shared.clone();
    let id = case_id.to_string();
    let removed = tokio::task::spawn_blocking(move || {
        sh.store
            .as_ref()
            .expect("checked")
            .remove(&id)
            .map_err(StoreError::into_service)
    })
    .await
    .map_err(|source| Internal::Task {
        doing: "deleting",
        source,
    })?;
    if let Err(e) = removed {
        // Still stored: served again.
        if let Some(c) = ready {
            shared
                .registry
                .set(crate::registry::ready_status(&c), Some(c));
        } else {
            shared.registry.set(status, None);
        }
        return Err(e);
    }
    // Sessions recorded on it can no longer be resumed (a resume is refused naming the case).
    let resumable = crate::shared::resumable_sessions(shared, case_id, &stored.version)
        .await
        .unwrap_or(0);
    shared
        .record(vec![Record::Event {
            kind: "case_deleted",
            principal: who.name.clone(),
            case_id: Some(case_id.to_string()),
            session_id: None,
            detail: serde_json::json!({
                "version": stored.version,
                "resumable_sessions": resumable,
            }),
        }])
        .await?;
    tracing::info!(case = %case_id, principal = %who.name, resumable_sessions = resumable, "case deleted; its recorded sessions can no longer be resumed");
    Ok(pb::DeleteCaseResponse {
        case_id: case_id.to_string(),
        version: stored.version,
        resumable_sessions: resumable.min(u32::MAX as u64) as u32,
    })
}
