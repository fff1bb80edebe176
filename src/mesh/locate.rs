//! Point location in a tet mesh: which tetrahedron contains a point, with its barycentric
//! coordinates, and linear (P1) interpolation of node fields at arbitrary points.
//!
//! [`TetLocator`] bins every tet's bounding box into a uniform grid (cells about the size of an
//! average tet, at most about four times as many cells as tets) and keeps, per tet, the
//! inverse of its edge matrix, so that a query tests only the tets listed in one cell. Points
//! outside the mesh are served by the boundary face closest to them (through a [`TriangleBvh`]),
//! which gives the field's value at the nearest surface point — a continuous extension.

use super::spatial::TriangleBvh;
use super::vec3::sub;
use super::{TetMesh, TriSurface};

/// Finds the tet containing a point (grid or BVH over tet bounding boxes) and barycentric coordinates.
#[derive(Debug, Clone)]
pub struct TetLocator {
    /// Node coordinates of the mesh.
    nodes: Vec<[f64; 3]>,
    /// Tet connectivity.
    tets: Vec<[u32; 4]>,
    /// Per tet: inverse of `[x1−x0, x2−x0, x3−x0]` (row-major; NaN for a degenerate tet).
    inv: Vec<[[f64; 3]; 3]>,
    /// Grid origin, cell size and cell counts.
    origin: [f64; 3],
    cell: f64,
    dims: [usize; 3],
    /// Compressed rows: tets overlapping cell `c` are `cell_tets[cell_start[c]..cell_start[c+1]]`.
    cell_start: Vec<usize>,
    cell_tets: Vec<u32>,
    /// Boundary faces for points outside, and the tet of each.
    boundary: TriangleBvh,
    tet_of_face: Vec<u32>,
    /// Relative tolerance on barycentric coordinates.
    tol: f64,
}

/// Relative tolerance: a point is inside a tet when every barycentric coordinate is ≥ −`TOL`.
const TOL: f64 = 1e-9;

impl TetLocator {
    /// Builds the grid and the boundary hierarchy of `mesh`.
    pub fn new(mesh: &TetMesh) -> Self {
        let nodes = mesh.nodes().to_vec();
        let tets = mesh.tets().to_vec();
        let inv = tets
            .iter()
            .map(|t| {
                let p = t.map(|i| nodes[i as usize]);
                invert_columns(sub(p[1], p[0]), sub(p[2], p[0]), sub(p[3], p[0]))
            })
            .collect();
        let (lo, hi) = mesh.bounding_box();
        let ext = [0, 1, 2].map(|k| (hi[k] - lo[k]).max(0.0));
        // Cell edge: twice the edge of a cube holding the bounding-box volume per tet (so a cell is
        // about the size of a tet's bounding box), enlarged until there are at most ~4 cells per tet.
        let nt = tets.len().max(1) as f64;
        let vol = (ext[0].max(1e-12)) * (ext[1].max(1e-12)) * (ext[2].max(1e-12));
        let mut cell = (vol / nt).cbrt() * 2.0;
        if !(cell > 0.0 && cell.is_finite()) {
            cell = 1.0;
        }
        let mut dims = [0, 1, 2].map(|k| ((ext[k] / cell).floor() as usize + 1).max(1));
        while (dims[0] * dims[1] * dims[2]) as f64 > 4.0 * nt + 64.0 {
            cell *= 1.25;
            dims = [0, 1, 2].map(|k| ((ext[k] / cell).floor() as usize + 1).max(1));
        }
        let origin = lo;
        let cell_of = |v: f64, k: usize| -> usize {
            (((v - origin[k]) / cell).floor().max(0.0) as usize).min(dims[k] - 1)
        };
        let ranges: Vec<[[usize; 2]; 3]> = tets
            .iter()
            .map(|t| {
                let p = t.map(|i| nodes[i as usize]);
                [0, 1, 2].map(|k| {
                    let a = p.iter().map(|q| q[k]).fold(f64::INFINITY, f64::min);
                    let b = p.iter().map(|q| q[k]).fold(f64::NEG_INFINITY, f64::max);
                    let pad = TOL * cell;
                    [cell_of(a - pad, k), cell_of(b + pad, k)]
                })
            })
            .collect();
        let ncell = dims[0] * dims[1] * dims[2];
        let mut count = vec![0usize; ncell + 1];
        let index = |i: usize, j: usize, k: usize| (k * dims[1] + j) * dims[0] + i;
        for r in &ranges {
            for k in r[2][0]..=r[2][1] {
                for j in r[1][0]..=r[1][1] {
                    for i in r[0][0]..=r[0][1] {
                        count[index(i, j, k) + 1] += 1;
                    }
                }
            }
        }
        for c in 0..ncell {
            count[c + 1] += count[c];
        }
        let cell_start = count.clone();
        let mut fill = count;
        let mut cell_tets = vec![0u32; cell_start[ncell]];
        for (t, r) in ranges.iter().enumerate() {
            for k in r[2][0]..=r[2][1] {
                for j in r[1][0]..=r[1][1] {
                    for i in r[0][0]..=r[0][1] {
                        let c = index(i, j, k);
                        cell_tets[fill[c]] = t as u32;
                        fill[c] += 1;
                    }
                }
            }
        }
        let (faces, tet_of_face) = match mesh.boundary() {
            Ok(b) => (b.triangles, b.tet_of_triangle),
            Err(_) => (Vec::new(), Vec::new()),
        };
        let boundary = TriangleBvh::new(&TriSurface::new_unchecked(nodes.clone(), faces));
        Self {
            nodes,
            tets,
            inv,
            origin,
            cell,
            dims,
            cell_start,
            cell_tets,
            boundary,
            tet_of_face,
            tol: TOL,
        }
    }

    /// Barycentric coordinates of `p` in tet `t` (not clamped).
    pub fn barycentric(&self, t: usize, p: [f64; 3]) -> [f64; 4] {
        let x0 = self.nodes[self.tets[t][0] as usize];
        let d = sub(p, x0);
        let m = &self.inv[t];
        let l = [0, 1, 2].map(|i| m[i][0] * d[0] + m[i][1] * d[1] + m[i][2] * d[2]);
        [1.0 - l[0] - l[1] - l[2], l[0], l[1], l[2]]
    }

    /// The tet containing `p` and its barycentric coordinates; `None` outside the mesh (every
    /// coordinate must be ≥ −1e-9). On a shared face the tet with the largest smallest coordinate
    /// wins (the lowest index among ties).
    pub fn locate(&self, p: [f64; 3]) -> Option<(usize, [f64; 4])> {
        if p.iter().any(|c| !c.is_finite()) {
            return None;
        }
        let mut ijk = [0usize; 3];
        for k in 0..3 {
            let f = ((p[k] - self.origin[k]) / self.cell).floor();
            if f < -1.0 || f > self.dims[k] as f64 {
                return None;
            }
            ijk[k] = (f.max(0.0) as usize).min(self.dims[k] - 1);
        }
        let c = (ijk[2] * self.dims[1] + ijk[1]) * self.dims[0] + ijk[0];
        let mut best: Option<(usize, [f64; 4], f64)> = None;
        for &t in &self.cell_tets[self.cell_start[c]..self.cell_start[c + 1]] {
            let b = self.barycentric(t as usize, p);
            // A degenerate tet has NaN coordinates and never passes.
            if !b.iter().all(|&x| x >= -self.tol) {
                continue;
            }
            let m = b.iter().copied().fold(f64::INFINITY, f64::min);
            if best.as_ref().is_none_or(|x| m > x.2) {
                best = Some((t as usize, b, m));
            }
        }
        best.map(|(t, b, _)| (t, b))
    }

    /// Linearly interpolates a node-major 3-vector field (len 3n) at p; points outside use the nearest tet (clamped barycentrics).
    ///
    /// Outside, the nearest tet is the one owning the closest boundary face, and its barycentric
    /// coordinates at the closest boundary point are clamped to [0, 1] and renormalised.
    ///
    /// # Panics
    /// When `field` is shorter than 3 × the number of nodes.
    pub fn interpolate(&self, field: &[f64], p: [f64; 3]) -> [f64; 3] {
        self.interpolate_impl(field, p)
    }

    /// The tet and barycentric weights [`TetLocator::interpolate`] uses at `p`: the containing
    /// tet, or outside the mesh the tet of the closest boundary face with the closest point's
    /// weights (clamped to the tet); `None` when there is neither.
    pub fn weights(&self, p: [f64; 3]) -> Option<(usize, [f64; 4])> {
        match self.locate(p) {
            Some(x) => Some(x),
            None => self.boundary.closest(p, None).map(|c| {
                let t = self.tet_of_face[c.triangle as usize] as usize;
                let mut b = self.barycentric(t, c.point).map(|x| x.clamp(0.0, 1.0));
                let s: f64 = b.iter().sum();
                if s > 0.0 {
                    b = b.map(|x| x / s);
                } else {
                    b = [0.25; 4];
                }
                (t, b)
            }),
        }
    }

    /// The nodes of tet `t`.
    pub fn tet(&self, t: usize) -> [u32; 4] {
        self.tets[t]
    }

    fn interpolate_impl(&self, field: &[f64], p: [f64; 3]) -> [f64; 3] {
        assert!(
            field.len() >= 3 * self.nodes.len(),
            "field has {} values, the mesh needs {}",
            field.len(),
            3 * self.nodes.len()
        );
        let Some((t, b)) = self.weights(p) else {
            return [0.0; 3];
        };
        let tet = self.tets[t];
        let mut out = [0.0; 3];
        for (a, &n) in tet.iter().enumerate() {
            for k in 0..3 {
                out[k] += b[a] * field[3 * n as usize + k];
            }
        }
        out
    }
}

/// Inverse of the matrix with columns `a`, `b`, `c` (NaN when singular).
fn invert_columns(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> [[f64; 3]; 3] {
    // Rows of the inverse are (b×c, c×a, a×b) / det.
    let bc = super::vec3::cross(b, c);
    let ca = super::vec3::cross(c, a);
    let ab = super::vec3::cross(a, b);
    let det = super::vec3::dot(a, bc);
    if det == 0.0 || !det.is_finite() {
        return [[f64::NAN; 3]; 3];
    }
    [bc, ca, ab].map(|r| r.map(|x| x / det))
}
