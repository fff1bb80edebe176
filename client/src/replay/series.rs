//! A replayed session's registrations as a ParaView time series ([`write_series`]).

use librplus::eval::{GeometryData, ScenarioData};
use librplus::mesh::rigid::Rigid;
use std::path::PathBuf;

/// One registration of a session, kept for its time series.
pub(super) struct SeriesStep {
    /// The newest message it reflects.
    pub(super) client_seq: u64,
    /// Its transform.
    pub(super) image_to_physical: Rigid,
    /// Its node displacements (image frame, mm).
    pub(super) displacement: Vec<f64>,
    /// The error estimate's per-node bound, when the server sent it for every node.
    pub(super) uncertainty: Option<Vec<f64>>,
}

/// Why a session's time series could not be written ([`write_series`]).
#[derive(Debug, thiserror::Error)]
pub enum SeriesError {
    /// A registration's mesh could not be serialised as VTU.
    #[error("{0}")]
    Mesh(#[from] librplus::mesh::io::IoError),
    /// A file could not be written.
    #[error("{0}")]
    Write(#[from] librplus::util::FileError),
}

/// A file-name-safe name for a session's series: `SCENARIO-METHOD` with every character outside
/// `A-Z a-z 0-9 . _ + -` replaced by `_` (a scenario id `g1-L-00/3` becomes `g1-L-00_3`).
pub fn series_name(scenario: &str, method: &str) -> String {
    format!("{scenario}-{method}")
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "._+-".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Writes a session's registrations as a ParaView time series: `DIR/NAME/update-KKKK.vtu`, one
/// per registration in arrival order, and `DIR/NAME.pvd`, whose time steps are the acquisition
/// times of the newest message each registration reflects (seconds after the session's first
/// data message, [`crate::messages::EPOCH_UNIX_S`]). Each `.vtu` is the preoperative
/// tetrahedral mesh with its nodes at their **registered** positions (physical frame, mm), and
/// point data `displacement` (the registration's node displacement, image frame, mm: the nodes
/// are already moved, so do not warp by it again) and `error_mm` (distance from the registered
/// to the true node position: the dataset's ground truth, which only a replay has). Files are
/// written atomically; returns the `.pvd`'s path.
pub(super) fn write_series(
    dir: &std::path::Path,
    name: &str,
    geo: &GeometryData,
    sc: &ScenarioData,
    steps: &[SeriesStep],
) -> Result<PathBuf, SeriesError> {
    use librplus::mesh::io::{DataArray, MeshFile, PvdEntry, WriteOptions, pvd_collection};
    let mesh = &geo.model.mesh;
    let x = mesh.nodes();
    let place = |t: &Rigid, u: &[f64]| -> Vec<[f64; 3]> {
        x.iter()
            .enumerate()
            .map(|(i, p)| t.apply([0, 1, 2].map(|a| p[a] + u[3 * i + a])))
            .collect()
    };
    let truth = place(&sc.truth.image_to_physical, &sc.truth.displacement);
    let mut entries = Vec::with_capacity(steps.len());
    for (k, s) in steps.iter().enumerate() {
        let nodes = place(&s.image_to_physical, &s.displacement);
        let error: Vec<f64> = nodes
            .iter()
            .zip(&truth)
            .map(|(p, q)| {
                ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
            })
            .collect();
        let file = MeshFile {
            nodes,
            tets: mesh.tets().to_vec(),
            point_data: [
                DataArray::new("displacement", 3, s.displacement.clone()),
                DataArray::new("error_mm", 1, error),
            ]
            .into_iter()
            .chain(
                s.uncertainty
                    .as_ref()
                    .map(|b| DataArray::new("uncertainty_mm", 1, b.clone())),
            )
            .collect(),
            ..MeshFile::default()
        };
        let rel = format!("{name}/update-{:04}.vtu", k + 1);
        let bytes = librplus::mesh::io::write_bytes(
            &file,
            librplus::mesh::io::Format::Vtu,
            WriteOptions::default(),
            &dir.join(&rel),
        )?;
        librplus::util::write_atomic(&dir.join(&rel), &bytes)?;
        entries.push(PvdEntry {
            timestep: (s.client_seq as f64 - 2.0).max(0.0),
            file: rel,
        });
    }
    let pvd = dir.join(format!("{name}.pvd"));
    librplus::util::write_atomic(&pvd, pvd_collection(&entries).as_bytes())?;
    Ok(pvd)
}
