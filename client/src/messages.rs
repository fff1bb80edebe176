//! Between dataset scenarios and the wire: the message sequence of a streamed session
//! ([`stream_messages`]), the measurement set of a unary call ([`measurements_message`]), and the
//! measurement set a server should reconstruct from a stream ([`measurements_from_stream`]).

use crate::pb;
use crate::pb::stream_register_request::Msg;
use librplus::eval::{ScenarioData, ScenarioPlanes};
use librplus::mesh::rigid::Rigid;
use librplus::register::{MeasuredKind, Measurements};

/// Seconds since the Unix epoch of the first message's `acquired_at` (2026-01-01T00:00:00Z);
/// message `client_seq = k` is acquired `k − 2` seconds later (the first data message is seq 2).
pub const EPOCH_UNIX_S: i64 = 1_767_225_600;

/// A library rigid transform as a wire `Rigid` (rotation row-major).
pub fn rigid_message(r: &Rigid) -> pb::Rigid {
    pb::Rigid {
        rotation: r.rotation.iter().flatten().copied().collect(),
        translation_mm: r.translation.to_vec(),
    }
}

/// A field of a server message the client cannot use: the field's path and the problem.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} {problem}")]
pub struct MessageError {
    /// Field path (e.g. `registration.image_to_physical.rotation`).
    pub field: String,
    /// What is wrong.
    pub problem: String,
}

impl MessageError {
    /// The same problem, in a field of the message `parent`.
    pub fn within(self, parent: &str) -> Self {
        Self {
            field: format!("{parent}.{}", self.field),
            problem: self.problem,
        }
    }
}

/// A wire `Rigid` as a library transform; an error names the field with the wrong length.
pub fn rigid_from_message(r: &pb::Rigid) -> Result<Rigid, MessageError> {
    let pb::Rigid {
        rotation,
        translation_mm,
    } = r;
    if rotation.len() != 9 {
        return Err(MessageError {
            field: "rotation".into(),
            problem: format!("has {} values, expected 9", rotation.len()),
        });
    }
    if translation_mm.len() != 3 {
        return Err(MessageError {
            field: "translation_mm".into(),
            problem: format!("has {} values, expected 3", translation_mm.len()),
        });
    }
    let m = &r.rotation;
    Ok(Rigid {
        rotation: [[m[0], m[1], m[2]], [m[3], m[4], m[5]], [m[6], m[7], m[8]]],
        translation: [
            r.translation_mm[0],
            r.translation_mm[1],
            r.translation_mm[2],
        ],
    })
}

/// The wire kind of a measured point.
pub fn kind_message(k: MeasuredKind) -> pb::PointKind {
    match k {
        MeasuredKind::Surface => pb::PointKind::Surface,
        MeasuredKind::PosteriorContour => pb::PointKind::PosteriorContour,
        MeasuredKind::Vessel => pb::PointKind::Vessel,
    }
}

/// A complete measurement set as the wire message of a unary `Register` call (features per point
/// when the set has them, else empty).
pub fn measurements_message(m: &Measurements) -> pb::Measurements {
    pb::Measurements {
        xyz_mm: m.points.iter().flatten().copied().collect(),
        kind: m.kind.iter().map(|&k| kind_message(k) as i32).collect(),
        feature: m.feature.iter().map(|&f| i32::from(f)).collect(),
        initial_alignment: m.initial_alignment.as_ref().map(rigid_message),
    }
}

fn timestamp(client_seq: u64) -> prost_types::Timestamp {
    prost_types::Timestamp {
        seconds: EPOCH_UNIX_S + client_seq as i64 - 2,
        nanos: 0,
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The message sequence of a streamed session replaying one scenario:
///
/// 1. `SessionStart` (case, method, options, the scenario's initial alignment);
/// 2. the surface points in file order, `surface_batch` per `SurfaceBatch` (0: all in one), with
///    their salient-feature designations when the scenario has them;
/// 3. one `UltrasoundPlane` per plane in index order (also a plane without points), its contour
///    then vessel points as `(u, v) = ((p − o)·lateral, (p − o)·depth)`, and `plane_to_physical`
///    with rotation columns (lateral, depth, lateral × depth) and translation o, so that
///    `plane_to_physical((u, v, 0)) = p` for a point in the plane. The third column is
///    `lateral × depth`, which is minus the dataset's `normal = depth × lateral`: (lateral, depth,
///    normal) would be a reflection (determinant −1).
///
/// `client_seq` runs 1, 2, 3, ...; `acquired_at` is [`EPOCH_UNIX_S`] + (seq − 2) s.
///
/// # Panics
/// When `planes.plane_of_point` does not have one entry per measured point, or an ultrasound
/// point's plane index is out of range ([`librplus::eval::load_scenario_planes`] checks both).
pub fn stream_messages(
    case_id: &str,
    method: pb::Method,
    options: Option<pb::RegisterOptions>,
    sc: &ScenarioData,
    planes: &ScenarioPlanes,
    surface_batch: usize,
) -> Vec<pb::StreamRegisterRequest> {
    let m = &sc.measurements;
    assert_eq!(
        planes.plane_of_point.len(),
        m.points.len(),
        "scenario {}: one plane index per measured point",
        sc.id
    );
    for (i, (&p, &k)) in planes.plane_of_point.iter().zip(&m.kind).enumerate() {
        assert!(
            k == MeasuredKind::Surface || (p >= 0 && (p as usize) < planes.planes.len()),
            "scenario {}: point {i} ({k:?}) in plane {p} of {}",
            sc.id,
            planes.planes.len()
        );
    }
    let mut out = vec![pb::StreamRegisterRequest {
        client_seq: 1,
        msg: Some(Msg::Start(pb::SessionStart {
            case_id: case_id.to_string(),
            method: method as i32,
            options,
            initial_alignment: m.initial_alignment.as_ref().map(rigid_message),
            discovery: None,
            resume_session_id: String::new(),
        })),
    }];
    let mut push = |msg: Msg| {
        let client_seq = out.len() as u64 + 1;
        out.push(pb::StreamRegisterRequest {
            client_seq,
            msg: Some(match msg {
                Msg::Surface(mut s) => {
                    s.acquired_at = Some(timestamp(client_seq));
                    Msg::Surface(s)
                }
                Msg::Ultrasound(mut u) => {
                    u.acquired_at = Some(timestamp(client_seq));
                    Msg::Ultrasound(u)
                }
                other => other,
            }),
        });
    };
    let surface: Vec<usize> = (0..m.points.len())
        .filter(|&i| m.kind[i] == MeasuredKind::Surface)
        .collect();
    let batch = if surface_batch == 0 {
        surface.len().max(1)
    } else {
        surface_batch
    };
    for chunk in surface.chunks(batch) {
        push(Msg::Surface(pb::SurfaceBatch {
            acquired_at: None,
            xyz_mm: chunk.iter().flat_map(|&i| m.points[i]).collect(),
            feature: if m.feature.is_empty() {
                Vec::new()
            } else {
                chunk.iter().map(|&i| i32::from(m.feature[i])).collect()
            },
        }));
    }
    for (j, pl) in planes.planes.iter().enumerate() {
        let uv = |kind: MeasuredKind| -> Vec<f64> {
            (0..m.points.len())
                .filter(|&i| planes.plane_of_point[i] == j as i32 && m.kind[i] == kind)
                .flat_map(|i| {
                    let d = sub(m.points[i], pl.origin);
                    [dot(d, pl.lateral_dir), dot(d, pl.depth_dir)]
                })
                .collect()
        };
        let (l, d) = (pl.lateral_dir, pl.depth_dir);
        let n = cross(l, d);
        push(Msg::Ultrasound(pb::UltrasoundPlane {
            acquired_at: None,
            plane_to_physical: Some(pb::Rigid {
                rotation: vec![l[0], d[0], n[0], l[1], d[1], n[1], l[2], d[2], n[2]],
                translation_mm: pl.origin.to_vec(),
            }),
            contour_uv_mm: uv(MeasuredKind::PosteriorContour),
            vessel_uv_mm: uv(MeasuredKind::Vessel),
        }));
    }
    out
}

/// What a server should reconstruct from a message sequence: the start's initial alignment, the
/// surface points of every `SurfaceBatch`, then per `UltrasoundPlane` its contour points then its
/// vessel points mapped by `plane_to_physical((u, v, 0))`, all in message order; one feature per
/// point (0 where a batch carries none, and for ultrasound points). Messages that do not parse
/// (wrong lengths) are skipped.
pub fn measurements_from_stream(msgs: &[pb::StreamRegisterRequest]) -> Measurements {
    let mut m = Measurements {
        points: Vec::new(),
        kind: Vec::new(),
        feature: Vec::new(),
        initial_alignment: None,
    };
    for msg in msgs {
        match &msg.msg {
            Some(Msg::Start(s)) => {
                m.initial_alignment = s
                    .initial_alignment
                    .as_ref()
                    .and_then(|r| rigid_from_message(r).ok());
            }
            Some(Msg::Surface(s)) => {
                if s.xyz_mm.len() % 3 != 0
                    || (!s.feature.is_empty() && 3 * s.feature.len() != s.xyz_mm.len())
                {
                    continue;
                }
                for (j, c) in s.xyz_mm.chunks_exact(3).enumerate() {
                    m.points.push([c[0], c[1], c[2]]);
                    m.kind.push(MeasuredKind::Surface);
                    m.feature
                        .push(s.feature.get(j).map_or(0, |&f| f.clamp(0, 255) as u8));
                }
            }
            Some(Msg::Ultrasound(u)) => {
                let Some(t) = u
                    .plane_to_physical
                    .as_ref()
                    .and_then(|r| rigid_from_message(r).ok())
                else {
                    continue;
                };
                if u.contour_uv_mm.len() % 2 != 0 || u.vessel_uv_mm.len() % 2 != 0 {
                    continue;
                }
                for (uv, kind) in [
                    (&u.contour_uv_mm, MeasuredKind::PosteriorContour),
                    (&u.vessel_uv_mm, MeasuredKind::Vessel),
                ] {
                    for c in uv.chunks_exact(2) {
                        m.points.push(t.apply([c[0], c[1], 0.0]));
                        m.kind.push(kind);
                        m.feature.push(0);
                    }
                }
            }
            Some(Msg::Discover(_)) | None => {}
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;
    use librplus::eval::{PlanePose, Truth};

    fn normalize(v: [f64; 3]) -> [f64; 3] {
        let n = dot(v, v).sqrt();
        [v[0] / n, v[1] / n, v[2] / n]
    }

    /// A scenario with 7 surface points (2 designated), and two planes holding 3 + 1 and 0 + 2
    /// ultrasound points, interleaved in the file; a third plane without points.
    fn scenario() -> (ScenarioData, ScenarioPlanes) {
        let plane = |o: [f64; 3], d: [f64; 3], l0: [f64; 3]| {
            let depth_dir = normalize(d);
            let lateral_dir = normalize(cross(cross(depth_dir, l0), depth_dir));
            PlanePose {
                origin: o,
                lateral_dir,
                depth_dir,
                normal: cross(depth_dir, lateral_dir),
            }
        };
        let planes = vec![
            plane([10.0, -20.0, 5.0], [0.2, 1.0, -0.1], [1.0, 0.3, 0.0]),
            plane([-40.0, 3.0, 60.0], [-0.5, 0.8, 0.3], [0.0, 0.2, 1.0]),
            plane([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]),
        ];
        let at = |j: usize, u: f64, v: f64| {
            let p = &planes[j];
            [0, 1, 2].map(|a| p.origin[a] + u * p.lateral_dir[a] + v * p.depth_dir[a])
        };
        use MeasuredKind::*;
        let mut points = Vec::new();
        let mut kind = Vec::new();
        let mut plane_of = Vec::new();
        let mut feature = Vec::new();
        for i in 0..7 {
            let x = i as f64;
            points.push([x * 3.1, -x * x, 17.0 + x]);
            kind.push(Surface);
            plane_of.push(-1);
            feature.push([0, 1, 0, 0, 2, 0, 0][i]);
        }
        for (j, k, u, v) in [
            (1, Vessel, 4.0, 30.0),
            (0, PosteriorContour, -12.5, 80.25),
            (1, Vessel, -7.0, 41.0),
            (0, Vessel, 3.0, 55.0),
            (0, PosteriorContour, 0.5, 90.0),
            (0, PosteriorContour, 9.0, 85.0),
        ] {
            points.push(at(j, u, v));
            kind.push(k);
            plane_of.push(j as i32);
            feature.push(0);
        }
        let t = Rigid {
            rotation: [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
            translation: [1.0, 2.0, 3.0],
        };
        (
            ScenarioData {
                id: "d/0".into(),
                category: "us2".into(),
                measurements: librplus::register::Checked::new(Measurements {
                    points,
                    kind,
                    feature,
                    initial_alignment: Some(t),
                })
                .unwrap(),
                truth: Truth {
                    displacement: vec![],
                    image_to_physical: t,
                },
            },
            ScenarioPlanes {
                plane_of_point: plane_of,
                planes,
            },
        )
    }

    /// Points of one kind, sorted, with their features.
    fn sorted(m: &Measurements, k: MeasuredKind) -> Vec<([f64; 3], u8)> {
        let mut v: Vec<_> = (0..m.points.len())
            .filter(|&i| m.kind[i] == k)
            .map(|i| (m.points[i], m.feature.get(i).copied().unwrap_or(0)))
            .collect();
        v.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap());
        v
    }

    #[test]
    fn messages_count_sequence_and_round_trip() {
        let (sc, pl) = scenario();
        let opts = pb::RegisterOptions {
            time_budget_ms: 300,
            omit_displacements: false,
            trusted_alignment_mm: 0.0,
            held: false,
            single_answer: false,
        };
        let msgs = stream_messages("liver", pb::Method::Libr, Some(opts), &sc, &pl, 3);
        // Start, ceil(7 / 3) = 3 surface batches, 3 planes.
        assert_eq!(msgs.len(), 1 + 3 + 3);
        let seqs: Vec<u64> = msgs.iter().map(|m| m.client_seq).collect();
        assert_eq!(seqs, (1..=7).collect::<Vec<_>>());
        let Some(Msg::Start(s)) = &msgs[0].msg else {
            panic!("first message is not a start")
        };
        assert_eq!(s.case_id, "liver");
        assert_eq!(s.method, pb::Method::Libr as i32);
        assert_eq!(s.options, Some(opts));
        let mut last = None;
        let mut sizes = Vec::new();
        for m in &msgs[1..] {
            let at = match &m.msg {
                Some(Msg::Surface(b)) => {
                    sizes.push(b.xyz_mm.len() / 3);
                    assert_eq!(b.feature.len() * 3, b.xyz_mm.len());
                    b.acquired_at
                }
                Some(Msg::Ultrasound(u)) => {
                    // A proper rotation: orthonormal with determinant +1.
                    let r = rigid_from_message(u.plane_to_physical.as_ref().unwrap()).unwrap();
                    let c = |j: usize| [r.rotation[0][j], r.rotation[1][j], r.rotation[2][j]];
                    let det = dot(c(0), cross(c(1), c(2)));
                    assert!((det - 1.0).abs() < 1e-12, "det {det}");
                    u.acquired_at
                }
                _ => panic!("unexpected message"),
            }
            .unwrap();
            assert!(last.is_none_or(|l: prost_types::Timestamp| at.seconds > l.seconds));
            last = Some(at);
        }
        assert_eq!(sizes, vec![3, 3, 1]);
        let Some(Msg::Ultrasound(u0)) = &msgs[4].msg else {
            panic!()
        };
        let close = |a: &[f64], b: &[f64]| {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9)
        };
        assert!(close(
            &u0.contour_uv_mm,
            &[-12.5, 80.25, 0.5, 90.0, 9.0, 85.0]
        ));
        assert!(close(&u0.vessel_uv_mm, &[3.0, 55.0]));
        let Some(Msg::Ultrasound(u2)) = &msgs[6].msg else {
            panic!()
        };
        assert!(u2.contour_uv_mm.is_empty() && u2.vessel_uv_mm.is_empty());

        let back = measurements_from_stream(&msgs);
        assert_eq!(back.points.len(), sc.measurements.points.len());
        assert_eq!(back.initial_alignment, sc.measurements.initial_alignment);
        for k in [
            MeasuredKind::Surface,
            MeasuredKind::PosteriorContour,
            MeasuredKind::Vessel,
        ] {
            let (a, b) = (sorted(&back, k), sorted(&sc.measurements, k));
            assert_eq!(a.len(), b.len(), "{k:?}");
            for ((p, f), (q, g)) in a.iter().zip(&b) {
                assert_eq!(f, g);
                for i in 0..3 {
                    assert!((p[i] - q[i]).abs() < 1e-9, "{k:?}: {p:?} vs {q:?}");
                }
            }
        }
        // The canonical order: surface, then per plane contour then vessel.
        use MeasuredKind::*;
        assert_eq!(
            back.kind,
            [
                vec![Surface; 7],
                vec![PosteriorContour; 3],
                vec![Vessel, Vessel, Vessel]
            ]
            .concat()
        );
        // Batch 0 puts every surface point in one message.
        assert_eq!(
            stream_messages("c", pb::Method::Rigid, None, &sc, &pl, 0).len(),
            5
        );
    }

    #[test]
    fn unary_measurements_carry_every_point() {
        let (sc, _) = scenario();
        let m = measurements_message(&sc.measurements);
        assert_eq!(m.xyz_mm.len(), 3 * 13);
        assert_eq!(m.kind.len(), 13);
        assert_eq!(m.kind[0], pb::PointKind::Surface as i32);
        assert_eq!(m.kind[7], pb::PointKind::Vessel as i32);
        assert_eq!(m.kind[8], pb::PointKind::PosteriorContour as i32);
        assert_eq!(m.feature[1], pb::SalientFeature::Falciform as i32);
        assert_eq!(m.feature[4], pb::SalientFeature::InferiorRidge as i32);
        let t = rigid_from_message(m.initial_alignment.as_ref().unwrap()).unwrap();
        assert_eq!(Some(t), sc.measurements.initial_alignment);
        assert!(rigid_from_message(&pb::Rigid::default()).is_err());
    }
}
