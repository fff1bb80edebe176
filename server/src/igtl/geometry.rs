//! What the OpenIGTLink bridge knows of space: the peer's patient frame (RAS or LPS), targets
//! from a 3D Slicer markups file, the case's boundary surface with the targets embedded in its
//! mesh, and rigid transforms to and from OpenIGTLink TRANSFORMs.

use super::wire::Transform;
use librplus::mesh::TetMesh;
use librplus::mesh::locate::TetLocator;
use librplus::mesh::rigid::Rigid;
use librplus_proto::v1 as pb;

/// The patient frame the OpenIGTLink peer works in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    /// Right, anterior, superior (3D Slicer's world).
    Ras,
    /// Left, posterior, superior (DICOM, ITK, LIBR+).
    Lps,
}

impl Frame {
    /// Converts a point or vector between this frame and LPS (its own inverse).
    pub fn convert(self, p: [f64; 3]) -> [f64; 3] {
        match self {
            Frame::Ras => [-p[0], -p[1], p[2]],
            Frame::Lps => p,
        }
    }
}

/// A named target in the preoperative image frame (LPS, mm).
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    /// Its label.
    pub name: String,
    /// Position, image frame, LPS, mm.
    pub image_mm: [f64; 3],
}

/// Reads targets from a 3D Slicer markups file (`.mrk.json`, schema 1.0: `markups[].
/// controlPoints[].{label, position}` with `markups[].coordinateSystem` `LPS` or `RAS`, which
/// Slicer writes) into the image frame (LPS).
pub fn read_targets(path: &std::path::Path) -> anyhow::Result<Vec<Target>> {
    use anyhow::Context;
    let text =
        std::fs::read_to_string(path).with_context(|| format!("--targets {}", path.display()))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("--targets {}: not JSON", path.display()))?;
    let bad = |what: String| anyhow::anyhow!("--targets {}: {what}", path.display());
    let markups = v["markups"]
        .as_array()
        .ok_or_else(|| bad("no `markups` array (a 3D Slicer .mrk.json)".into()))?;
    let mut out = Vec::new();
    for (m, mk) in markups.iter().enumerate() {
        let frame = match mk["coordinateSystem"].as_str().unwrap_or("LPS") {
            "LPS" => Frame::Lps,
            "RAS" => Frame::Ras,
            other => {
                return Err(bad(format!(
                    "markups[{m}].coordinateSystem {other:?} is neither LPS nor RAS"
                )));
            }
        };
        for (k, cp) in mk["controlPoints"]
            .as_array()
            .map(Vec::as_slice)
            .unwrap_or_default()
            .iter()
            .enumerate()
        {
            let field = format!("markups[{m}].controlPoints[{k}]");
            let p: Vec<f64> = cp["position"]
                .as_array()
                .map(|a| a.iter().filter_map(serde_json::Value::as_f64).collect())
                .unwrap_or_default();
            if p.len() != 3 || p.iter().any(|x| !x.is_finite()) {
                return Err(bad(format!("{field}.position is not 3 finite numbers")));
            }
            out.push(Target {
                name: cp["label"]
                    .as_str()
                    .map_or_else(|| format!("target-{}", out.len() + 1), str::to_string),
                image_mm: frame.convert([p[0], p[1], p[2]]),
            });
        }
    }
    Ok(out)
}

/// The case as the bridge needs it: nodes, the boundary surface and the targets' embedding.
pub(super) struct CaseGeometry {
    /// Node positions, image frame (LPS), mm.
    pub(super) nodes: Vec<[f64; 3]>,
    /// Boundary nodes (indices into `nodes`).
    pub(super) surface_nodes: Vec<u32>,
    /// Triangles over the boundary nodes (local indices, into `surface_nodes`).
    pub(super) surface_triangles: Vec<[u32; 3]>,
    /// The targets, embedded in the mesh.
    pub(super) targets: Vec<Embedded>,
}

/// A target embedded in the mesh: its name, image position, and the nodes and barycentric
/// weights of the tet it is in (or nearest to).
pub(super) struct Embedded {
    /// Its label.
    pub(super) name: String,
    /// Position, image frame, LPS, mm.
    pub(super) image_mm: [f64; 3],
    /// The nodes of its tet.
    pub(super) nodes: [u32; 4],
    /// Its barycentric weights in that tet.
    pub(super) weights: [f64; 4],
}

impl CaseGeometry {
    /// The geometry of the case `DescribeCase` answered (with its mesh), the targets embedded in
    /// it; an error when the mesh does not check or a target is near no tet.
    pub(super) fn new(d: &pb::DescribeCaseResponse, targets: &[Target]) -> anyhow::Result<Self> {
        let nodes: Vec<[f64; 3]> = d
            .nodes_mm
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect();
        let tets: Vec<[u32; 4]> = d
            .tets
            .chunks_exact(4)
            .map(|c| [c[0], c[1], c[2], c[3]])
            .collect();
        let mesh = TetMesh::new(nodes.clone(), tets)
            .map_err(|e| anyhow::anyhow!("the case's mesh from DescribeCase: {e}"))?;
        let b = mesh
            .boundary()
            .map_err(|e| anyhow::anyhow!("the case's boundary surface: {e}"))?;
        let mut local = vec![u32::MAX; nodes.len()];
        for (k, &n) in b.nodes.iter().enumerate() {
            local[n as usize] = k as u32;
        }
        let surface_triangles = b
            .triangles
            .iter()
            .map(|t| t.map(|n| local[n as usize]))
            .collect();
        let locator = TetLocator::new(&mesh);
        let targets = targets
            .iter()
            .map(|t| {
                let (tet, w) = locator.weights(t.image_mm).ok_or_else(|| {
                    anyhow::anyhow!("target {:?}: no tet of the case near it", t.name)
                })?;
                Ok(Embedded {
                    name: t.name.clone(),
                    image_mm: t.image_mm,
                    nodes: locator.tet(tet),
                    weights: w,
                })
            })
            .collect::<anyhow::Result<_>>()?;
        Ok(Self {
            nodes,
            surface_nodes: b.nodes,
            surface_triangles,
            targets,
        })
    }
}

/// The frame change as a rigid transform (a rotation by 180° about z for RAS ↔ LPS).
pub(super) fn frame_rigid(frame: Frame) -> Rigid {
    let mut r = Rigid::identity();
    if frame == Frame::Ras {
        r.rotation[0][0] = -1.0;
        r.rotation[1][1] = -1.0;
    }
    r
}

/// A TRANSFORM whose rotation part is not a rotation.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("the rotation part is not a rotation (orthonormal, determinant +1, to 1e-3)")]
pub(super) struct NotARotation {
    /// The largest departure of its columns from orthonormal.
    pub(super) departure: f64,
    /// Its determinant (the triple product of its columns; +1 for a rotation).
    pub(super) determinant: f64,
}

/// Why a received TRANSFORM is not a pose.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub(super) enum BadPose {
    /// An entry is not finite, or a translation beyond [`crate::convert::MAX_ABS_MM`].
    #[error("matrix[{row}][{col}] is {value}: {problem}")]
    Entry {
        /// Its row.
        row: usize,
        /// Its column (3: the translation).
        col: usize,
        /// Its value.
        value: f64,
        /// What is wrong with it.
        problem: &'static str,
    },
    /// The rotation part is not a rotation.
    #[error(transparent)]
    NotARotation(NotARotation),
}

/// A received TRANSFORM as a rigid transform: its rotation re-orthonormalised (the wire's
/// float32 rounding), refused when an entry is not finite, a translation is beyond ±10 m, or the
/// rotation part is not a rotation to 1e-3.
pub(super) fn rigid_of(t: &Transform) -> Result<Rigid, BadPose> {
    let m = &t.matrix;
    for (row, r) in m.iter().take(3).enumerate() {
        for (col, &value) in r.iter().enumerate() {
            let problem = if !value.is_finite() {
                "every entry must be finite"
            } else if col == 3 && value.abs() > crate::convert::MAX_ABS_MM {
                "the translation must be within ±10,000 mm"
            } else {
                continue;
            };
            return Err(BadPose::Entry {
                row,
                col,
                value,
                problem,
            });
        }
    }
    let col = |j: usize| [m[0][j], m[1][j], m[2][j]];
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (a, b, c) = (col(0), col(1), col(2));
    let err = [
        (dot(a, a) - 1.0).abs(),
        (dot(b, b) - 1.0).abs(),
        (dot(c, c) - 1.0).abs(),
        dot(a, b).abs(),
        dot(a, c).abs(),
        dot(b, c).abs(),
    ]
    .into_iter()
    .fold(0.0, f64::max);
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let determinant = dot(cross(a, b), c);
    if err.is_nan() || err > 1e-3 || determinant.is_nan() || determinant <= 0.0 {
        return Err(BadPose::NotARotation(NotARotation {
            departure: err,
            determinant,
        }));
    }
    let norm = |v: [f64; 3]| {
        let n = dot(v, v).sqrt();
        v.map(|x| x / n)
    };
    let u = norm(a);
    let w = norm(cross(u, b));
    let v = cross(w, u);
    Ok(Rigid {
        rotation: [[u[0], v[0], w[0]], [u[1], v[1], w[1]], [u[2], v[2], w[2]]],
        translation: [m[0][3], m[1][3], m[2][3]],
    })
}

/// A rigid transform as an OpenIGTLink TRANSFORM.
pub(super) fn transform_of(r: &Rigid) -> Transform {
    let mut m = Transform::IDENTITY.matrix;
    for (i, row) in m.iter_mut().take(3).enumerate() {
        row[..3].copy_from_slice(&r.rotation[i]);
        row[3] = r.translation[i];
    }
    Transform { matrix: m }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_convert_and_transforms_round_trip() {
        assert_eq!(Frame::Ras.convert([1.0, 2.0, 3.0]), [-1.0, -2.0, 3.0]);
        assert_eq!(Frame::Lps.convert([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0]);
        // A rotation about an oblique axis, through the wire's float32 and back.
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        let r = Rigid {
            rotation: [
                [c, -s, 0.0],
                [s * 0.6, c * 0.6, -0.8],
                [s * 0.8, c * 0.8, 0.6],
            ],
            translation: [10.0, -20.5, 300.25],
        };
        let t = Transform::from_wire(&transform_of(&r).to_wire().unwrap());
        let back = rigid_of(&t).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                assert!((back.rotation[i][j] - r.rotation[i][j]).abs() < 1e-6);
            }
            assert!((back.translation[i] - r.translation[i]).abs() < 1e-4);
        }
        // Not a rotation: a scaling, a reflection.
        let mut scaled = transform_of(&r);
        scaled.matrix[0][0] *= 1.1;
        let e = rigid_of(&scaled).unwrap_err();
        assert!(
            matches!(e, BadPose::NotARotation(n) if n.departure > 1e-3 && n.determinant > 0.0),
            "{e:?}"
        );
        let mut reflected = transform_of(&Rigid::identity());
        reflected.matrix[2][2] = -1.0;
        let e = rigid_of(&reflected).unwrap_err();
        assert!(
            matches!(e, BadPose::NotARotation(n) if n.determinant < 0.0),
            "{e:?}"
        );
        // Not finite (all NaN: the rotation check alone let it through), or too far away.
        let nan = Transform {
            matrix: [[f64::NAN; 4]; 4],
        };
        let e = rigid_of(&nan).unwrap_err();
        assert_eq!(
            e.to_string(),
            "matrix[0][0] is NaN: every entry must be finite"
        );
        let mut far = transform_of(&r);
        far.matrix[1][3] = 2e4;
        let e = rigid_of(&far).unwrap_err();
        assert!(e.to_string().starts_with("matrix[1][3] is 20000: "), "{e}");
        // F T F in RAS equals T applied to converted points.
        let f = frame_rigid(Frame::Ras);
        let p = [3.0, -4.0, 5.0];
        let a = f.then(&r).then(&f).apply(Frame::Ras.convert(p));
        let b = Frame::Ras.convert(r.apply(p));
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-12);
        }
    }
}
