//! Between the wire (`librplus.v1`) and the library: checks every field of what a client sends
//! and names the field of each problem; builds the replies.

use crate::error::ServiceError;
use librplus::mesh::rigid::Rigid;
use librplus::register::{Checked, MeasuredKind, Measurements};
use librplus_proto::v1 as pb;

/// Coordinates beyond this (mm) are rejected as nonsense (10 m).
pub const MAX_ABS_MM: f64 = 1e4;

/// The canonical name of a status code (as in grpc's status codes), shared with the clients.
pub use librplus_proto::code_name;

/// A rigid transform from the wire.
pub fn rigid_from_pb(r: &pb::Rigid, field: &str) -> Result<Rigid, ServiceError> {
    let pb::Rigid {
        rotation: _,
        translation_mm: _,
    } = r; // every field is checked below
    if r.rotation.len() != 9 {
        return Err(ServiceError::field(
            format!("{field}.rotation"),
            format!(
                "has {} values, expected 9 (row-major 3×3)",
                r.rotation.len()
            ),
        ));
    }
    if r.translation_mm.len() != 3 {
        return Err(ServiceError::field(
            format!("{field}.translation_mm"),
            format!("has {} values, expected 3", r.translation_mm.len()),
        ));
    }
    if let Some(i) = r.rotation.iter().position(|x| !x.is_finite()) {
        return Err(ServiceError::field(
            format!("{field}.rotation[{i}]"),
            "is not finite",
        ));
    }
    if let Some(i) = r
        .translation_mm
        .iter()
        .position(|x| !(x.is_finite() && x.abs() <= MAX_ABS_MM))
    {
        return Err(ServiceError::field(
            format!("{field}.translation_mm[{i}]"),
            format!(
                "{} is not finite or beyond ±{MAX_ABS_MM} mm",
                num(r.translation_mm[i])
            ),
        ));
    }
    let m = |i: usize, j: usize| r.rotation[3 * i + j];
    let mut err = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let d: f64 = (0..3).map(|k| m(k, i) * m(k, j)).sum();
            err = err.max((d - if i == j { 1.0 } else { 0.0 }).abs());
        }
    }
    let det = m(0, 0) * (m(1, 1) * m(2, 2) - m(1, 2) * m(2, 1))
        - m(0, 1) * (m(1, 0) * m(2, 2) - m(1, 2) * m(2, 0))
        + m(0, 2) * (m(1, 0) * m(2, 1) - m(1, 1) * m(2, 0));
    if err > 1e-6 || det <= 0.0 {
        return Err(ServiceError::field(
            format!("{field}.rotation"),
            format!("is not a rotation (|RᵀR − I| = {err:.2e}, det = {det:.6})"),
        ));
    }
    Ok(Rigid {
        rotation: [
            [m(0, 0), m(0, 1), m(0, 2)],
            [m(1, 0), m(1, 1), m(1, 2)],
            [m(2, 0), m(2, 1), m(2, 2)],
        ],
        translation: [
            r.translation_mm[0],
            r.translation_mm[1],
            r.translation_mm[2],
        ],
    })
}

/// A rigid transform to the wire.
pub fn rigid_to_pb(r: &Rigid) -> pb::Rigid {
    pb::Rigid {
        rotation: r.rotation.iter().flatten().copied().collect(),
        translation_mm: r.translation.to_vec(),
    }
}

/// A client's number as a message shows it: plain when it reads well, else in scientific
/// notation (never the 309 digits `{}` prints for 1e308).
pub fn num(x: f64) -> String {
    if x == 0.0 || (x.is_finite() && (1e-3..1e7).contains(&x.abs())) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// Points packed 3 per point (`field`), checked: length, finite, within ±10 m.
pub fn points3(v: &[f64], field: &str, max_points: usize) -> Result<Vec<[f64; 3]>, ServiceError> {
    if v.len() % 3 != 0 {
        return Err(ServiceError::field(
            field,
            format!(
                "has {} values, not a multiple of 3 (x, y, z per point)",
                v.len()
            ),
        ));
    }
    if v.len() / 3 > max_points {
        return Err(ServiceError::invalid(
            format!(
                "{field}: {} points, more than the {max_points} allowed in one message",
                v.len() / 3
            ),
            vec![(
                field.to_string(),
                format!("{} points; at most {max_points} per message", v.len() / 3),
            )],
        ));
    }
    // A bad coordinate is named by its point: `measurements.points[17]` for a NaN anywhere in
    // `measurements.xyz_mm[51..54]`, once per point however many of its coordinates are bad.
    let points = field.strip_suffix(".xyz_mm").unwrap_or(field);
    let mut bad = Vec::new();
    for (i, p) in v.chunks_exact(3).enumerate() {
        let wrong: Vec<usize> = (0..3)
            .filter(|&k| !(p[k].is_finite() && p[k].abs() <= MAX_ABS_MM))
            .collect();
        if wrong.is_empty() {
            continue;
        }
        let values: Vec<String> = wrong
            .iter()
            .map(|&k| format!("{} = {}", ["x", "y", "z"][k], num(p[k])))
            .collect();
        let at: Vec<String> = wrong
            .iter()
            .map(|&k| format!("{field}[{}]", 3 * i + k))
            .collect();
        bad.push((
            format!("{points}.points[{i}]"),
            format!(
                "{} {} not finite or beyond ±{MAX_ABS_MM} mm ({})",
                values.join(", "),
                if wrong.len() == 1 { "is" } else { "are" },
                at.join(", "),
            ),
        ));
        if bad.len() == 10 {
            break;
        }
    }
    if !bad.is_empty() {
        return Err(ServiceError::invalid(
            format!("{field}: {} bad point(s), first {}", bad.len(), bad[0].0),
            bad,
        ));
    }
    Ok(v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
}

/// Salient-feature designations (`field`): empty, or one valid value per point.
pub fn features(v: &[i32], n: usize, field: &str) -> Result<Vec<u8>, ServiceError> {
    if v.is_empty() {
        return Ok(vec![0; n]);
    }
    if v.len() != n {
        return Err(ServiceError::field(
            field,
            format!(
                "has {} values for {n} points (give none or one per point)",
                v.len()
            ),
        ));
    }
    v.iter()
        .enumerate()
        .map(|(i, &f)| match pb::SalientFeature::try_from(f) {
            Ok(x) => Ok(x as u8),
            Err(_) => Err(ServiceError::field(
                format!("{field}[{i}]"),
                format!("{f} is not a SalientFeature (0 none, 1 falciform, 2 inferior ridge)"),
            )),
        })
        .collect()
}

/// A complete measurement set from the wire.
pub fn measurements_from_pb(
    m: &pb::Measurements,
    field: &str,
    max_points: usize,
) -> Result<Checked, ServiceError> {
    let pb::Measurements {
        xyz_mm,
        kind,
        feature,
        initial_alignment,
    } = m;
    let points = points3(xyz_mm, &format!("{field}.xyz_mm"), max_points)?;
    let n = points.len();
    if n == 0 {
        return Err(ServiceError::field(
            format!("{field}.xyz_mm"),
            "is empty: no points",
        ));
    }
    if kind.len() != n {
        return Err(ServiceError::field(
            format!("{field}.kind"),
            format!("has {} values for {n} points (one per point)", kind.len()),
        ));
    }
    let kind = kind
        .iter()
        .enumerate()
        .map(|(i, &k)| {
            kind_from_pb(k).ok_or_else(|| {
                ServiceError::field(
                    format!("{field}.kind[{i}]"),
                    format!("{k} is not a point kind (1 surface, 2 posterior contour, 3 vessel)"),
                )
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let feature = features(feature, n, &format!("{field}.feature"))?;
    if let Some(i) = (0..n).find(|&i| feature[i] != 0 && kind[i] != MeasuredKind::Surface) {
        return Err(ServiceError::field(
            format!("{field}.feature[{i}]"),
            "only surface points can be designated on a salient feature",
        ));
    }
    let initial_alignment = initial_alignment
        .as_ref()
        .map(|r| rigid_from_pb(r, &format!("{field}.initial_alignment")))
        .transpose()?;
    // The one check the registration's stages rely on (they do not check again).
    Checked::new(Measurements {
        points,
        kind,
        feature,
        initial_alignment,
    })
    .map_err(|e| ServiceError::field(field, e.to_string()))
}

/// A point kind from the wire (`UNSPECIFIED` and unknown values: None).
pub fn kind_from_pb(k: i32) -> Option<MeasuredKind> {
    match pb::PointKind::try_from(k).ok()? {
        pb::PointKind::Unspecified => None,
        pb::PointKind::Surface => Some(MeasuredKind::Surface),
        pb::PointKind::PosteriorContour => Some(MeasuredKind::PosteriorContour),
        pb::PointKind::Vessel => Some(MeasuredKind::Vessel),
    }
}

/// Points in the physical frame (mm).
pub type Points = Vec<[f64; 3]>;

/// Points of one ultrasound plane in the physical frame: (contour points, vessel points).
pub fn plane_points(
    p: &pb::UltrasoundPlane,
    max_points: usize,
) -> Result<(Points, Points), ServiceError> {
    let pb::UltrasoundPlane {
        acquired_at: _, // checked by the session (ordering)
        plane_to_physical,
        contour_uv_mm,
        vessel_uv_mm,
    } = p;
    let pose = plane_to_physical
        .as_ref()
        .ok_or_else(|| ServiceError::field("ultrasound.plane_to_physical", "is missing"))?;
    let pose = rigid_from_pb(pose, "ultrasound.plane_to_physical")?;
    let uv = |v: &[f64], field: &str| -> Result<Vec<[f64; 3]>, ServiceError> {
        if v.len() % 2 != 0 {
            return Err(ServiceError::field(
                field,
                format!(
                    "has {} values, not a multiple of 2 (u, v per point)",
                    v.len()
                ),
            ));
        }
        if let Some(i) = v
            .iter()
            .position(|x| !(x.is_finite() && x.abs() <= MAX_ABS_MM))
        {
            // Named by its point, as for 3-D points: `ultrasound.contour_points[2]` for a bad
            // `ultrasound.contour_uv_mm[5]`.
            let points = field.replace("_uv_mm", "_points");
            return Err(ServiceError::field(
                format!("{points}[{}]", i / 2),
                format!(
                    "{} = {} is not finite or beyond ±{MAX_ABS_MM} mm ({field}[{i}])",
                    ["u", "v"][i % 2],
                    num(v[i])
                ),
            ));
        }
        Ok(v.chunks_exact(2)
            .map(|c| pose.apply([c[0], c[1], 0.0]))
            .collect())
    };
    let contour = uv(contour_uv_mm, "ultrasound.contour_uv_mm")?;
    let vessels = uv(vessel_uv_mm, "ultrasound.vessel_uv_mm")?;
    let n = contour.len() + vessels.len();
    if n > max_points {
        return Err(ServiceError::field(
            "ultrasound",
            format!("{n} points; at most {max_points} per message"),
        ));
    }
    Ok((contour, vessels))
}

/// A method from the wire, given the case's default; LIBR_PLUS is refused when the case has no
/// SR-GCN model.
pub fn method_from_pb(
    m: i32,
    default: librplus::pipeline::Method,
    has_model: bool,
    has_v2s: bool,
    field: &str,
) -> Result<librplus::pipeline::Method, ServiceError> {
    use librplus::pipeline::Method;
    match pb::Method::try_from(m) {
        Ok(pb::Method::Unspecified) => Ok(default),
        Ok(pb::Method::Rigid) => Ok(Method::Rigid),
        Ok(pb::Method::Libr) => Ok(Method::Libr),
        Ok(pb::Method::LibrPlus) if has_model => Ok(Method::LibrPlus),
        Ok(pb::Method::LibrPlus) => Err(ServiceError::precondition(
            "CASE",
            field,
            "METHOD_LIBR_PLUS needs a case with an SR-GCN model",
            format!(
                "{field}: METHOD_LIBR_PLUS needs an SR-GCN model, and this case has none (use METHOD_LIBR)"
            ),
        )),
        Ok(pb::Method::V2s) if has_v2s => Ok(Method::V2s),
        Ok(pb::Method::V2s) => Err(ServiceError::precondition(
            "CASE",
            field,
            "METHOD_V2S needs a case with a V2S model",
            format!(
                "{field}: METHOD_V2S needs a V2S model, and this server loaded none (v2s is off)"
            ),
        )),
        // Whether the case has adaptive LIBR's basis is checked with the case.
        Ok(pb::Method::Adaptive) => Ok(Method::Adaptive),
        Ok(pb::Method::Auto) => Ok(Method::Auto),
        Ok(pb::Method::Nonlinear) => Ok(Method::Nonlinear),
        Err(_) => Err(ServiceError::field(
            field,
            format!(
                "{m} is not a Method (0 default, 1 rigid, 2 LIBR, 3 LIBR+, 4 V2S, 5 adaptive, 6 auto, 7 nonlinear)"
            ),
        )),
    }
}

/// A library method to the wire.
pub fn method_to_pb(m: librplus::pipeline::Method) -> pb::Method {
    match m {
        // A baseline of the library's evaluation; the service never registers with it.
        librplus::pipeline::Method::Initial => pb::Method::Unspecified,
        librplus::pipeline::Method::Rigid => pb::Method::Rigid,
        librplus::pipeline::Method::Libr => pb::Method::Libr,
        librplus::pipeline::Method::LibrPlus => pb::Method::LibrPlus,
        librplus::pipeline::Method::V2s => pb::Method::V2s,
        librplus::pipeline::Method::Adaptive => pb::Method::Adaptive,
        librplus::pipeline::Method::Auto => pb::Method::Auto,
        librplus::pipeline::Method::Nonlinear => pb::Method::Nonlinear,
    }
}

/// How the automatic method chose, for the wire.
pub fn choice_to_pb(a: &librplus::pipeline::auto::AutoInfo) -> pb::ModelChoice {
    pb::ModelChoice {
        chosen: a.chosen.name().to_string(),
        best_scoring: a.best_scoring.name().to_string(),
        runner_up: a
            .runner_up
            .map_or_else(String::new, |c| c.name().to_string()),
        margin_mm2: a.margin_mm2.unwrap_or(0.0),
        margin_se: a.margin_se.unwrap_or(0.0),
        runner_up_mm: a.runner_up_mm.unwrap_or(0.0),
        candidates: a
            .candidates
            .iter()
            .map(|c| pb::CandidateScore {
                name: c.candidate.name().to_string(),
                held_out_mm2: c.held_out_mm2,
                in_sample_mm2: c.in_sample_mm2,
                predicted_tre_mm: c.predicted_tre_mm,
                failed: c.failed.clone().unwrap_or_default(),
            })
            .collect(),
    }
}

/// The side test's outcome, for the wire.
pub fn side_to_pb(s: &librplus::pipeline::side::SideInfo) -> pb::SurfaceSide {
    pb::SurfaceSide {
        target: s.target.name().to_string(),
        anterior_mm2: s.anterior_mm2,
        boundary_mm2: s.boundary_mm2,
    }
}

/// The named effects a model carries.
pub fn effects(p: &librplus::pipeline::Prepared) -> Vec<String> {
    p.physics.kinds().into_iter().map(str::to_string).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bad coordinate is named by its point, with the axis and the flat index in the text.
    #[test]
    fn a_bad_coordinate_names_its_point() {
        let mut v = vec![1.0; 3 * 20];
        v[3 * 17 + 1] = f64::NAN;
        let r = points3(&v, "measurements.xyz_mm", 100)
            .unwrap_err()
            .to_rejection(0);
        assert_eq!(r.violations[0].field, "measurements.points[17]");
        let text = &r.violations[0].description;
        assert!(
            text.starts_with("y = NaN") && text.contains("measurements.xyz_mm[52]"),
            "{text}"
        );
        let mut p = pb::UltrasoundPlane {
            plane_to_physical: Some(rigid_to_pb(&Rigid::identity())),
            contour_uv_mm: vec![0.0; 8],
            ..Default::default()
        };
        // One violation per point, naming each of its bad coordinates.
        v[0] = f64::NAN;
        v[1] = f64::INFINITY;
        v[2] = -2e4;
        let r = points3(&v, "surface.xyz_mm", 100)
            .unwrap_err()
            .to_rejection(0);
        let fields: Vec<&str> = r.violations.iter().map(|v| v.field.as_str()).collect();
        assert_eq!(fields, ["surface.points[0]", "surface.points[17]"]);
        assert_eq!(
            r.violations[0].description,
            "x = NaN, y = inf, z = -20000 are not finite or beyond ±10000 mm (surface.xyz_mm[0], surface.xyz_mm[1], surface.xyz_mm[2])"
        );
        p.contour_uv_mm[5] = f64::INFINITY;
        let r = plane_points(&p, 100).unwrap_err().to_rejection(0);
        assert_eq!(r.violations[0].field, "ultrasound.contour_points[2]");
        assert!(
            r.violations[0].description.starts_with("v = inf")
                && r.violations[0]
                    .description
                    .contains("ultrasound.contour_uv_mm[5]"),
            "{}",
            r.violations[0].description
        );
    }

    #[test]
    fn rigid_transforms_round_trip_and_non_rotations_are_refused() {
        let r = Rigid::from_axis_angle([0.3, -0.2, 0.9], 0.7, [1.0, 2.0, 3.0]);
        let back = rigid_from_pb(&rigid_to_pb(&r), "t").unwrap();
        assert_eq!(back.rotation, r.rotation);
        assert_eq!(back.translation, r.translation);
        let mut m = rigid_to_pb(&r);
        // A reflection (det −1) is orthonormal but not a rotation.
        for k in 0..3 {
            m.rotation[k] = -m.rotation[k];
        }
        assert!(
            rigid_from_pb(&m, "t")
                .unwrap_err()
                .to_status()
                .message()
                .contains("not a rotation")
        );
        let mut m = rigid_to_pb(&r);
        m.translation_mm[1] = f64::NAN;
        assert_eq!(
            rigid_from_pb(&m, "t")
                .unwrap_err()
                .to_rejection(0)
                .violations[0]
                .field,
            "t.translation_mm[1]"
        );
        let mut m = rigid_to_pb(&r);
        m.rotation.pop();
        assert_eq!(
            rigid_from_pb(&m, "t")
                .unwrap_err()
                .to_rejection(0)
                .violations[0]
                .field,
            "t.rotation"
        );
    }

    #[test]
    fn plane_coordinates_map_through_the_pose() {
        let pose = Rigid::from_axis_angle(
            [0.0, 0.0, 1.0],
            std::f64::consts::FRAC_PI_2,
            [10.0, 0.0, 0.0],
        );
        let p = pb::UltrasoundPlane {
            acquired_at: None,
            plane_to_physical: Some(rigid_to_pb(&pose)),
            contour_uv_mm: vec![1.0, 2.0],
            vessel_uv_mm: vec![],
        };
        let (c, v) = plane_points(&p, 10).unwrap();
        assert!(v.is_empty());
        let want = pose.apply([1.0, 2.0, 0.0]);
        assert!(
            (0..3).all(|k| (c[0][k] - want[k]).abs() < 1e-12),
            "{c:?} {want:?}"
        );
        let mut odd = p.clone();
        odd.contour_uv_mm.push(3.0);
        assert_eq!(
            plane_points(&odd, 10)
                .unwrap_err()
                .to_rejection(0)
                .violations[0]
                .field,
            "ultrasound.contour_uv_mm"
        );
        assert!(plane_points(&p, 0).is_err());
    }
}
