//! Cases over the API: upload a preoperative mesh (CreateCase, in 1 MiB chunks) and follow its
//! preload (WatchCase) to READY; delete an uploaded case.

use crate::pb;
use crate::session::{Tls, connect_with};
use anyhow::{Context, Result, bail};
use std::path::PathBuf;
use std::time::Instant;

/// What to upload.
#[derive(Debug, Clone, Default)]
pub struct UploadOptions {
    /// Server URL.
    pub server: String,
    /// TLS settings.
    pub tls: Tls,
    /// Bearer token.
    pub token: Option<String>,
    /// The case id.
    pub case_id: String,
    /// The tetrahedral mesh (.vtu, .vtk, .msh).
    pub mesh: PathBuf,
    /// Vessel centerlines (.vtp).
    pub vessels: Option<PathBuf>,
    /// physics.json.
    pub physics: Option<PathBuf>,
    /// Length unit of the mesh and vessels (mm, cm, m).
    pub unit: String,
    /// Follow the preload to READY or FAILED.
    pub wait: bool,
    /// Print progress on stderr.
    pub progress: bool,
}

/// What an upload did.
#[derive(Debug, Clone, serde::Serialize)]
pub struct UploadSummary {
    /// The case id.
    pub case_id: String,
    /// Its version (SHA-256 of the content).
    pub version: String,
    /// False: the server already had this content.
    pub created: bool,
    /// Bytes sent.
    pub bytes: u64,
    /// Nodes and tets.
    pub nodes: u32,
    /// Tets.
    pub tets: u32,
    /// Seconds until the server stored it.
    pub upload_s: f64,
    /// Seconds until READY (or FAILED), with `wait`: on the case's own basis.
    pub ready_s: Option<f64>,
    /// Seconds until it first answered, with `wait`: READY on a coarse basis while its own
    /// built (a large upload), else the same as `ready_s`.
    pub first_ready_s: Option<f64>,
    /// The last state.
    pub state: String,
    /// Why FAILED.
    pub error: String,
}

fn request<T>(msg: T, token: &Option<String>) -> Result<tonic::Request<T>> {
    let mut r = tonic::Request::new(msg);
    if let Some(t) = token {
        r.metadata_mut().insert(
            "authorization",
            format!("Bearer {t}")
                .parse()
                .context("--token must be printable ASCII")?,
        );
    }
    Ok(r)
}

/// Uploads a case and (with `wait`) follows it to READY.
pub async fn upload(o: &UploadOptions) -> Result<UploadSummary> {
    use pb::create_case_request::Part;
    let format = o
        .mesh
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    if !matches!(format.as_str(), "vtu" | "vtk" | "msh") {
        bail!(
            "--mesh {}: expected a .vtu, .vtk or .msh tetrahedral mesh",
            o.mesh.display()
        );
    }
    let read = |flag: &str, p: &PathBuf| {
        std::fs::read(p).with_context(|| format!("{flag} {}: cannot read", p.display()))
    };
    let mut files = vec![(pb::CaseFile::Mesh, read("--mesh", &o.mesh)?)];
    if let Some(v) = &o.vessels {
        files.push((pb::CaseFile::Vessels, read("--vessels", v)?));
    }
    if let Some(p) = &o.physics {
        files.push((pb::CaseFile::Physics, read("--physics", p)?));
    }
    let total: u64 = files.iter().map(|(_, b)| b.len() as u64).sum();
    let mut msgs = vec![pb::CreateCaseRequest {
        part: Some(Part::Upload(pb::CaseUpload {
            case_id: o.case_id.clone(),
            mesh_format: format,
            mesh_unit: o.unit.clone(),
            total_bytes: total,
            ..Default::default()
        })),
    }];
    for (file, bytes) in files {
        for c in bytes.chunks(1 << 20) {
            msgs.push(pb::CreateCaseRequest {
                part: Some(Part::Chunk(pb::CaseChunk {
                    file: file as i32,
                    data: c.to_vec(),
                })),
            });
        }
    }
    let mut client = connect_with(&o.server, &o.tls).await?;
    let t0 = Instant::now();
    if o.progress {
        eprintln!(
            "uploading {} ({total} bytes in {} messages) as case {:?}",
            o.mesh.display(),
            msgs.len(),
            o.case_id
        );
    }
    let r = client
        .create_case(request(tokio_stream::iter(msgs), &o.token)?)
        .await
        .map_err(|s| {
            anyhow::anyhow!(
                "CreateCase: {}: {}",
                crate::code_name(s.code()),
                s.message()
            )
        })?
        .into_inner();
    let upload_s = t0.elapsed().as_secs_f64();
    let mut out = UploadSummary {
        case_id: r.case_id.clone(),
        version: r.version.clone(),
        created: r.created,
        bytes: total,
        nodes: r.node_count,
        tets: r.tet_count,
        upload_s,
        ready_s: None,
        first_ready_s: None,
        state: r
            .status
            .as_ref()
            .map_or("UNKNOWN", |s| s.state().as_str_name())
            .to_string(),
        error: String::new(),
    };
    if o.progress {
        eprintln!(
            "stored in {upload_s:.2} s: version {}, {} nodes, {} tets{}",
            &r.version[..12.min(r.version.len())],
            r.node_count,
            r.tet_count,
            if r.created {
                ""
            } else {
                " (the server already had it)"
            }
        );
    }
    if !o.wait {
        return Ok(out);
    }
    follow(&mut client, o, &r.case_id, t0, &mut out).await?;
    out.ready_s = Some(t0.elapsed().as_secs_f64());
    if o.progress {
        eprintln!(
            "  {:>6.2} s  {}{}",
            t0.elapsed().as_secs_f64(),
            out.state,
            if out.error.is_empty() {
                String::new()
            } else {
                format!(": {}", out.error)
            }
        );
    }
    Ok(out)
}

/// Follows an upload's preload (WatchCase) to READY on its own basis or FAILED, into `out`
/// (its last state and error, when it first answered), with progress on stderr.
async fn follow(
    client: &mut crate::session::Client,
    o: &UploadOptions,
    case_id: &str,
    t0: Instant,
    out: &mut UploadSummary,
) -> Result<()> {
    let mut w = client
        .watch_case(request(
            pb::WatchCaseRequest {
                case_id: case_id.to_string(),
            },
            &o.token,
        )?)
        .await
        .map_err(|s| anyhow::anyhow!("WatchCase: {}: {}", crate::code_name(s.code()), s.message()))?
        .into_inner();
    let mut last_shown = (String::new(), -1.0f64);
    while let Some(s) = w.message().await.map_err(|s| {
        anyhow::anyhow!("WatchCase: {}: {}", crate::code_name(s.code()), s.message())
    })? {
        out.state = s.state().as_str_name().to_string();
        out.error = s.error.clone();
        if s.state() == pb::CaseState::Ready && out.first_ready_s.is_none() {
            out.first_ready_s = Some(t0.elapsed().as_secs_f64());
            if o.progress && s.coarse_basis {
                eprintln!(
                    "  {:>6.2} s  READY on a coarse basis (answers DEGRADED); its own basis builds",
                    t0.elapsed().as_secs_f64()
                );
            }
        }
        // Each stage, and every 10 % within one.
        if o.progress
            && s.state() == pb::CaseState::Loading
            && (s.stage != last_shown.0 || s.fraction >= last_shown.1 + 0.1)
        {
            eprintln!(
                "  {:>6.2} s  loading: {} ({:.0} %)",
                t0.elapsed().as_secs_f64(),
                s.stage,
                100.0 * s.fraction
            );
            last_shown = (s.stage.clone(), s.fraction);
        }
    }
    Ok(())
}

/// Deletes an uploaded case; its version and how many sessions recorded on it can no longer be
/// resumed.
pub async fn delete(
    server: &str,
    tls: &Tls,
    token: &Option<String>,
    case_id: &str,
) -> Result<(String, u32)> {
    let mut client = connect_with(server, tls).await?;
    let r = client
        .delete_case(request(
            pb::DeleteCaseRequest {
                case_id: case_id.into(),
            },
            token,
        )?)
        .await
        .map_err(|s| {
            anyhow::anyhow!(
                "DeleteCase: {}: {}",
                crate::code_name(s.code()),
                s.message()
            )
        })?;
    let r = r.into_inner();
    Ok((r.version, r.resumable_sessions))
}
