//! A recorded session exported as a sweep folder `librplus discover` reads (the audit log's
//! `librplus-server audit --export`).

use super::read_session;
use rusqlite::Connection;
use std::path::{Path, PathBuf};

/// Why a recorded session could not be exported ([`export_session`]).
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The audit database could not be read.
    #[error("{0}")]
    Sql(#[from] rusqlite::Error),
    /// No session of that id is recorded.
    #[error("no recorded session {id:?}")]
    NoSession {
        /// The id asked for.
        id: String,
    },
    /// The record does not decode, or does not begin with a start.
    #[error(transparent)]
    Record(#[from] crate::error::Unreplayable),
    /// A recorded message's points or the start's initial alignment fail the server's checks.
    #[error("{0:?}")]
    Invalid(#[source] crate::error::ServiceError),
    /// A folder or file could not be written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The folder or file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// The initial alignment could not be written as JSON.
    #[error("{0}")]
    Json(#[from] serde_json::Error),
}

/// What [`export_session`] wrote.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Exported {
    /// The session's case.
    pub case_id: String,
    /// Surface points.
    pub surface: usize,
    /// Posterior-contour points.
    pub contour: usize,
    /// Vessel points.
    pub vessel: usize,
    /// Messages replayed.
    pub messages: usize,
}

/// Writes a recorded session's points as one sweep folder `librplus discover --preop MESH
/// --scenarios DIR` reads: `surface.csv`, `ultrasound.csv` (posterior contours), `vessel.csv`
/// and `initial_alignment.json`, in `dir` (created). The points are those the server took, in
/// its order (salient-feature designations are not kept in these files).
pub fn export_session(c: &Connection, id: &str, dir: &Path) -> Result<Exported, ExportError> {
    use crate::convert::{plane_points, points3, rigid_from_pb};
    use crate::error::Unreplayable;
    use librplus_proto::v1 as pb;
    use pb::stream_register_request::Msg;
    use prost::Message;
    let rec = read_session(c, id)?.ok_or_else(|| ExportError::NoSession { id: id.to_string() })?;
    let start = pb::StreamRegisterRequest::decode(&rec.start[..]).map_err(Unreplayable::Start)?;
    let start = match start.msg {
        Some(Msg::Start(s)) => s,
        _ => return Err(Unreplayable::NotAStart.into()),
    };
    let (mut surface, mut contour, mut vessel) = (Vec::new(), Vec::new(), Vec::new());
    for (seq, b) in &rec.messages {
        let m = pb::StreamRegisterRequest::decode(&b[..])
            .map_err(|source| Unreplayable::Decode { seq: *seq, source })?;
        match m.msg {
            Some(Msg::Surface(sb)) => surface.extend(
                points3(&sb.xyz_mm, &format!("message {seq}"), usize::MAX)
                    .map_err(ExportError::Invalid)?,
            ),
            Some(Msg::Ultrasound(u)) => {
                let (c, v) = plane_points(&u, usize::MAX).map_err(ExportError::Invalid)?;
                contour.extend(c);
                vessel.extend(v);
            }
            _ => {}
        }
    }
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| ExportError::Io { path, source }
    };
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let csv = |name: &str, pts: &[[f64; 3]]| -> Result<(), ExportError> {
        if pts.is_empty() {
            return Ok(());
        }
        let mut text = String::from("x_mm,y_mm,z_mm\n");
        for p in pts {
            text.push_str(&format!("{},{},{}\n", p[0], p[1], p[2]));
        }
        let f = dir.join(name);
        std::fs::write(&f, text).map_err(io(&f))
    };
    csv("surface.csv", &surface)?;
    csv("ultrasound.csv", &contour)?;
    csv("vessel.csv", &vessel)?;
    if let Some(r) = &start.initial_alignment {
        let r = rigid_from_pb(r, "start.initial_alignment").map_err(ExportError::Invalid)?;
        let f = dir.join("initial_alignment.json");
        std::fs::write(&f, serde_json::to_string_pretty(&r)?).map_err(io(&f))?;
    }
    Ok(Exported {
        case_id: rec.case_id,
        surface: surface.len(),
        contour: contour.len(),
        vessel: vessel.len(),
        messages: rec.messages.len(),
    })
}
