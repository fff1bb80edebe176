//! Element quality: dihedral angles and the normalised radius ratio of tetrahedra.

use super::TetMesh;
use super::vec3::{cross, dot, norm, sub, tet_signed_volume};
use rayon::prelude::*;

/// The six interior dihedral angles of a tetrahedron, in degrees (ordered by the edges
/// (0,1), (0,2), (0,3), (1,2), (1,3), (2,3)).
pub fn dihedral_angles_deg(p: &[[f64; 3]; 4]) -> [f64; 6] {
    // Face k is opposite vertex k; its normal n_k points away from vertex k's side... we only need
    // the angle between the two faces meeting at edge (i, j): the faces opposite the other two
    // vertices k, l. With inward area normals m_k, the dihedral angle is π − ∠(m_k, m_l).
    let inward = |k: usize| -> [f64; 3] {
        let others: Vec<usize> = (0..4).filter(|&i| i != k).collect();
        let (a, b, c) = (p[others[0]], p[others[1]], p[others[2]]);
        let n = cross(sub(b, a), sub(c, a));
        // orient toward vertex k
        if dot(n, sub(p[k], a)) < 0.0 {
            [-n[0], -n[1], -n[2]]
        } else {
            n
        }
    };
    let m = [inward(0), inward(1), inward(2), inward(3)];
    let pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
    let mut out = [0.0; 6];
    for (slot, &(i, j)) in pairs.iter().enumerate() {
        let (k, l) = match (i, j) {
            (0, 1) => (2, 3),
            (0, 2) => (1, 3),
            (0, 3) => (1, 2),
            (1, 2) => (0, 3),
            (1, 3) => (0, 2),
            _ => (0, 1),
        };
        let (a, b) = (m[k], m[l]);
        let denom = norm(a) * norm(b);
        let cos = if denom > 0.0 {
            (dot(a, b) / denom).clamp(-1.0, 1.0)
        } else {
            1.0
        };
        out[slot] = 180.0 - cos.acos().to_degrees();
    }
    out
}

/// Normalised radius ratio `3·r_in / r_circ` (1 for a regular tet, 0 for a flat one).
pub fn radius_ratio(p: &[[f64; 3]; 4]) -> f64 {
    let v = tet_signed_volume(p).abs();
    if v == 0.0 {
        return 0.0;
    }
    let face_area = |a: [f64; 3], b: [f64; 3], c: [f64; 3]| 0.5 * norm(cross(sub(b, a), sub(c, a)));
    let s = face_area(p[1], p[2], p[3])
        + face_area(p[0], p[2], p[3])
        + face_area(p[0], p[1], p[3])
        + face_area(p[0], p[1], p[2]);
    let r_in = 3.0 * v / s;
    let (a, b, c) = (sub(p[1], p[0]), sub(p[2], p[0]), sub(p[3], p[0]));
    let w = [
        dot(a, a) * cross(b, c)[0] + dot(b, b) * cross(c, a)[0] + dot(c, c) * cross(a, b)[0],
        dot(a, a) * cross(b, c)[1] + dot(b, b) * cross(c, a)[1] + dot(c, c) * cross(a, b)[1],
        dot(a, a) * cross(b, c)[2] + dot(b, b) * cross(c, a)[2] + dot(c, c) * cross(a, b)[2],
    ];
    let r_circ = norm(w) / (12.0 * v);
    3.0 * r_in / r_circ
}

/// Summary of element quality over a mesh.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct QualitySummary {
    /// Smallest dihedral angle over all tets (degrees).
    pub min_dihedral_deg: f64,
    /// Largest dihedral angle over all tets (degrees).
    pub max_dihedral_deg: f64,
    /// Smallest normalised radius ratio.
    pub min_radius_ratio: f64,
    /// Mean normalised radius ratio.
    pub mean_radius_ratio: f64,
}

/// Quality summary of a mesh (parallel over tets).
pub fn summary(mesh: &TetMesh) -> QualitySummary {
    let (mn, mx, rmin, rsum) = (0..mesh.num_tets())
        .into_par_iter()
        .map(|t| {
            let p = mesh.tet_points(t);
            let d = dihedral_angles_deg(&p);
            let r = radius_ratio(&p);
            (
                d.iter().copied().fold(f64::INFINITY, f64::min),
                d.iter().copied().fold(f64::NEG_INFINITY, f64::max),
                r,
                r,
            )
        })
        .reduce(
            || (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, 0.0),
            |a, b| (a.0.min(b.0), a.1.max(b.1), a.2.min(b.2), a.3 + b.3),
        );
    QualitySummary {
        min_dihedral_deg: mn,
        max_dihedral_deg: mx,
        min_radius_ratio: rmin,
        mean_radius_ratio: rsum / mesh.num_tets().max(1) as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn regular_tet_has_arccos_third_and_ratio_one() {
        let p = [
            [1.0, 1.0, 1.0],
            [1.0, -1.0, -1.0],
            [-1.0, 1.0, -1.0],
            [-1.0, -1.0, 1.0],
        ];
        let expected = (1.0f64 / 3.0).acos().to_degrees(); // 70.5288°
        for a in dihedral_angles_deg(&p) {
            assert!((a - expected).abs() < 1e-10, "{a}");
        }
        assert!((radius_ratio(&p) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn corner_tet_angles() {
        // Trirectangular corner: three right dihedral angles at the edges through the origin,
        // arccos(1/√3) = 54.7356° at the other three (independent closed form).
        let p = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [0., 0., 1.]];
        let d = dihedral_angles_deg(&p);
        for a in &d[..3] {
            assert!((a - 90.0).abs() < 1e-10);
        }
        let e = (1.0f64 / 3f64.sqrt()).acos().to_degrees();
        for a in &d[3..] {
            assert!((a - e).abs() < 1e-10, "{a} vs {e}");
        }
        // 3·r_in/r_circ = 3/(3+√3) · 2/√3 = √3 − 1 for the trirectangular corner.
        assert!((radius_ratio(&p) - (3f64.sqrt() - 1.0)).abs() < 1e-14);
    }

    #[test]
    fn flat_tet_ratio_zero() {
        let p = [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.], [1., 1., 0.]];
        assert_eq!(radius_ratio(&p), 0.0);
    }
}
