//! Fuzz targets: what a client's bytes reach before a case does. Each takes arbitrary bytes and
//! must return (an error is fine) without panicking, hanging or allocating without bound. They
//! are run by libFuzzer (the `fuzz/` crate, `cargo fuzz run TARGET`) and, over their corpora and
//! a fixed number of seeded mutations, by `cargo test` (`server/tests/fuzz_regressions.rs`).

use crate::convert::{features, measurements_from_pb, plane_points, points3, rigid_from_pb};
use librplus::mesh::io::{Format, Unit, read_bytes};
use librplus_proto::v1 as pb;
use prost::Message;
use std::path::Path;

/// The targets, by name (the `fuzz/` crate's binaries and the corpus folders).
pub const TARGETS: &[&str] = &[
    "requests",
    "vtk_xml",
    "vtk_legacy",
    "gmsh",
    "stl",
    "obj",
    "physics_json",
];

/// Runs target `name` on `data`. Unknown names do nothing.
pub fn run(name: &str, data: &[u8]) {
    match name {
        "requests" => requests(data),
        "vtk_xml" => mesh(Format::Vtu, data),
        "vtk_legacy" => mesh(Format::VtkLegacy, data),
        "gmsh" => mesh(Format::Msh, data),
        "stl" => mesh(Format::Stl, data),
        "obj" => mesh(Format::Obj, data),
        "physics_json" => physics(data),
        _ => {}
    }
}

/// Limits as the server's defaults (small enough to keep each run fast).
const MAX_POINTS: usize = 20_000;

/// Protobuf decode and the server's checks of every request message: the first byte picks the
/// message type, the rest is its encoding.
pub fn requests(data: &[u8]) {
    let Some((&kind, rest)) = data.split_first() else {
        return;
    };
    match kind % 7 {
        0 => {
            if let Ok(r) = pb::RegisterRequest::decode(rest) {
                let _ = crate::error::short(&r.case_id, 64);
                if let Some(m) = &r.measurements {
                    // The edge's conversion is the one check (it makes the checked measurements).
                    let _ = measurements_from_pb(m, "measurements", MAX_POINTS);
                }
            }
        }
        1 => {
            if let Ok(r) = pb::StreamRegisterRequest::decode(rest) {
                stream_message(&r);
            }
        }
        2 => {
            let _ = pb::DescribeCaseRequest::decode(rest);
            let _ = pb::ListCasesRequest::decode(rest);
        }
        3 => {
            if let Ok(r) = pb::CreateCaseRequest::decode(rest) {
                upload(r);
            }
        }
        4 => {
            let _ = pb::WatchCaseRequest::decode(rest).map(|r| crate::store::check_id(&r.case_id));
            let _ = pb::DeleteCaseRequest::decode(rest).map(|r| crate::store::check_id(&r.case_id));
        }
        5 => {
            // A stored session message as `resume` replays it.
            if let Ok(r) = pb::StreamRegisterRequest::decode(rest)
                && let Some(pb::stream_register_request::Msg::Start(s)) = &r.msg
            {
                let _ = crate::store::check_id(&s.resume_session_id);
                stream_message(&r);
            }
        }
        _ => {
            // The auth file's JSON.
            if let Ok(text) = std::str::from_utf8(rest)
                && let Ok(f) = serde_json::from_str::<crate::auth::AuthFile>(text)
            {
                let _ = crate::auth::Auth::from_file(f);
            }
        }
    }
}

fn stream_message(r: &pb::StreamRegisterRequest) {
    use pb::stream_register_request::Msg;
    match &r.msg {
        Some(Msg::Start(s)) => {
            if let Some(a) = &s.initial_alignment {
                let _ = rigid_from_pb(a, "start.initial_alignment");
            }
        }
        Some(Msg::Surface(b)) => {
            if let Ok(p) = points3(&b.xyz_mm, "surface.xyz_mm", MAX_POINTS) {
                let _ = features(&b.feature, p.len(), "surface.feature");
            }
        }
        Some(Msg::Ultrasound(u)) => {
            let _ = plane_points(u, MAX_POINTS);
        }
        Some(Msg::Discover(_)) | None => {}
    }
}

fn upload(r: pb::CreateCaseRequest) {
    use pb::create_case_request::Part;
    match r.part {
        Some(Part::Upload(u)) => {
            let _ = crate::store::check_id(&u.case_id);
            // Arrays as uploaded, through the same checks (small meshes only: the checks are
            // linear, and a fuzzer's 10^6 runs must stay fast).
            if u.nodes_mm.len() <= 3000 && u.tets.len() <= 4000 {
                let up = crate::store::Upload {
                    case_id: u.case_id,
                    mesh: crate::store::MeshSource::Arrays {
                        nodes: u.nodes_mm,
                        tets: u.tets,
                    },
                    unit: u.mesh_unit,
                    vessels: None,
                    physics: None,
                };
                let _ = crate::store::check(&up, 1000);
            }
        }
        Some(Part::Chunk(_)) | None => {}
    }
}

/// A mesh reader on bytes, then the tetrahedral mesh checks when it has tets.
pub fn mesh(format: Format, data: &[u8]) {
    if let Ok(f) = read_bytes(data, format, Path::new("fuzz"), Unit::Mm)
        && !f.tets.is_empty()
        && let Ok(m) = librplus::mesh::TetMesh::from_file(&f)
    {
        let _ = m.problems(8);
    }
}

/// `physics.json`.
pub fn physics(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = librplus::register::physics::Physics::from_json(text);
    }
}
