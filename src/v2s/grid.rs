//! The regular grid V2S works on: a cube of `n³` points around the preoperative liver, the
//! signed distance to the liver's surface sampled on it, distances to measured points, and
//! trilinear interpolation from grid values to arbitrary points (the mesh nodes).
//!
//! Grid point `(i, j, k)` (`i` along x, `j` along y, `k` along z) is at
//! `origin + spacing · (i, j, k)` and has the flat index `(i·n + j)·n + k`: a burn tensor
//! `[1, C, n, n, n]` holds channel `c` at `c·n³ + index`.

use super::V2sError;
use crate::gcn::sparse::Csr;
use crate::mesh::spatial::SignedDistance;
use rayon::prelude::*;

/// A cubic grid of `n³` points.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Grid {
    /// Position of point `(0, 0, 0)` (mm, image frame).
    pub origin: [f64; 3],
    /// Distance between neighbouring points (mm).
    pub spacing: f64,
    /// Points per axis.
    pub n: usize,
}

impl Grid {
    /// The grid of `n` points per axis around `nodes`: a cube centred on their bounding box,
    /// whose side is the box's longest edge times `1 + 2·margin` (room for the deformed organ
    /// and the measured points beside it).
    pub fn around(nodes: &[[f64; 3]], n: usize, margin: f64) -> Result<Self, V2sError> {
        if n < 2 {
            return Err(V2sError::Invalid(format!(
                "grid: {n} points per axis (at least 2)"
            )));
        }
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(V2sError::Invalid(format!(
                "grid margin {margin} (a finite fraction ≥ 0)"
            )));
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in nodes {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        if !(extent.is_finite() && extent > 0.0) {
            return Err(V2sError::Invalid(
                "grid: the mesh has no extent (or non-finite coordinates)".into(),
            ));
        }
        let side = extent * (1.0 + 2.0 * margin);
        let spacing = side / (n - 1) as f64;
        let origin = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]) - 0.5 * side);
        Ok(Self { origin, spacing, n })
    }

    /// Number of points, `n³`.
    pub fn len(&self) -> usize {
        self.n * self.n * self.n
    }

    /// Whether the grid has no points (never for a grid made by [`Grid::around`]).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Flat index of point `(i, j, k)`.
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        (i * self.n + j) * self.n + k
    }

    /// Position of the point with flat index `idx` (mm).
    pub fn point(&self, idx: usize) -> [f64; 3] {
        let n = self.n;
        let ijk = [idx / (n * n), (idx / n) % n, idx % n];
        [0, 1, 2].map(|a| self.origin[a] + self.spacing * ijk[a] as f64)
    }

    /// The eight grid points around `p` and their trilinear weights (sum 1). A point outside
    /// the grid takes the values at the nearest boundary cell's face (coordinates clamped).
    pub fn trilinear(&self, p: [f64; 3]) -> [(usize, f64); 8] {
        let last = (self.n - 1) as f64;
        let mut base = [0usize; 3];
        let mut frac = [0.0; 3];
        for a in 0..3 {
            let t = ((p[a] - self.origin[a]) / self.spacing).clamp(0.0, last);
            let t = if t.is_finite() { t } else { 0.0 };
            let b = (t.floor() as usize).min(self.n - 2);
            base[a] = b;
            frac[a] = t - b as f64;
        }
        let mut out = [(0usize, 0.0); 8];
        for (c, o) in out.iter_mut().enumerate() {
            let d = [c >> 2 & 1, c >> 1 & 1, c & 1];
            let w: f64 = (0..3)
                .map(|a| if d[a] == 1 { frac[a] } else { 1.0 - frac[a] })
                .product();
            *o = (
                self.index(base[0] + d[0], base[1] + d[1], base[2] + d[2]),
                w,
            );
        }
        out
    }

    /// Trilinear interpolation of the grid values `field` (one per point) at `p`.
    pub fn interpolate(&self, field: &[f64], p: [f64; 3]) -> f64 {
        self.trilinear(p).iter().map(|&(i, w)| w * field[i]).sum()
    }

    /// The interpolation matrix `[points, n³]`: row r holds the trilinear weights of
    /// `points[r]`, so `A · F` interpolates grid fields `F` (`[n³, C]`) at the points.
    pub fn interpolation(&self, points: &[[f64; 3]]) -> Result<Csr, V2sError> {
        let mut triplets = Vec::with_capacity(8 * points.len());
        for (r, &p) in points.iter().enumerate() {
            for (i, w) in self.trilinear(p) {
                if w != 0.0 {
                    triplets.push((r, i, w as f32));
                }
            }
        }
        Csr::from_triplets(points.len(), self.len(), &triplets)
            .map_err(|e| V2sError::Invalid(format!("interpolation matrix: {e}")))
    }

    /// The signed distance to a closed surface at every grid point (mm, negative inside).
    pub fn signed_distance(&self, sd: &SignedDistance) -> Vec<f64> {
        (0..self.len())
            .into_par_iter()
            .map(|i| sd.eval(self.point(i)))
            .collect()
    }

    /// The distance from every grid point to the nearest of `points` (mm); None without points.
    pub fn distance_to(&self, points: &[[f64; 3]]) -> Option<Vec<f64>> {
        if points.is_empty() {
            return None;
        }
        let tree: kiddo::ImmutableKdTree<f64, 3> = kiddo::ImmutableKdTree::new_from_slice(points);
        Some(
            (0..self.len())
                .into_par_iter()
                .map(|i| {
                    let p = self.point(i);
                    tree.nearest_one::<kiddo::SquaredEuclidean>(&p)
                        .distance
                        .sqrt()
                })
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*seed >> 11) as f64 / (1u64 << 53) as f64
    }

    #[test]
    fn the_grid_is_a_cube_around_the_nodes_with_the_margin() {
        let nodes = [[0.0, 0.0, 0.0], [100.0, 40.0, 20.0], [50.0, 10.0, 5.0]];
        let g = Grid::around(&nodes, 11, 0.1).unwrap();
        // Side 100 · 1.2 = 120 over 10 intervals.
        assert!((g.spacing - 12.0).abs() < 1e-12);
        assert_eq!(g.origin, [-10.0, -40.0, -50.0]);
        assert_eq!(g.len(), 1331);
        let last = g.point(g.index(10, 10, 10));
        assert!((last[0] - 110.0).abs() < 1e-9 && (last[1] - 80.0).abs() < 1e-9);
        assert_eq!(g.point(g.index(1, 2, 3)), [2.0, -16.0, -14.0]);
        for bad in [
            Grid::around(&nodes, 1, 0.1),
            Grid::around(&nodes, 8, -0.1),
            Grid::around(&[[1.0; 3]], 8, 0.1),
        ] {
            assert!(matches!(bad, Err(V2sError::Invalid(_))));
        }
    }

    #[test]
    fn trilinear_interpolation_is_exact_on_linear_fields_and_its_matrix_agrees() {
        let g = Grid::around(&[[-30.0, 5.0, 2.0], [60.0, 70.0, 40.0]], 9, 0.2).unwrap();
        let f = |p: [f64; 3]| 3.0 - 0.7 * p[0] + 0.25 * p[1] + 1.5 * p[2];
        let field: Vec<f64> = (0..g.len()).map(|i| f(g.point(i))).collect();
        let mut seed = 7;
        let mut pts = Vec::new();
        for _ in 0..200 {
            // Inside the grid (and on its faces).
            let p = [0, 1, 2].map(|a| g.origin[a] + g.spacing * 8.0 * lcg(&mut seed));
            let got = g.interpolate(&field, p);
            assert!((got - f(p)).abs() < 1e-9 * (1.0 + f(p).abs()), "{p:?}");
            let w: f64 = g.trilinear(p).iter().map(|x| x.1).sum();
            assert!((w - 1.0).abs() < 1e-12);
            pts.push(p);
        }
        // Bilinear, not only linear: x·y is reproduced too (trilinear is exact on it).
        let fxy = |p: [f64; 3]| p[0] * p[1];
        let field2: Vec<f64> = (0..g.len()).map(|i| fxy(g.point(i))).collect();
        for p in &pts {
            assert!((g.interpolate(&field2, *p) - fxy(*p)).abs() < 1e-8 * (1.0 + fxy(*p).abs()));
        }
        // The matrix applied to the field gives the same values.
        let a = g.interpolation(&pts).unwrap();
        let f32s: Vec<f32> = field.iter().map(|&x| x as f32).collect();
        let y = a.matmul_dense(&f32s, 1);
        for (p, y) in pts.iter().zip(&y) {
            assert!((*y as f64 - f(*p)).abs() < 1e-3 * (1.0 + f(*p).abs()));
        }
        // Outside: clamped to the boundary face.
        let out = [g.origin[0] - 50.0, g.origin[1] + 3.0, g.origin[2] + 4.0];
        let on = [g.origin[0], g.origin[1] + 3.0, g.origin[2] + 4.0];
        assert!((g.interpolate(&field, out) - f(on)).abs() < 1e-9);
    }

    #[test]
    fn distances_to_points_match_a_direct_search() {
        let g = Grid::around(&[[0.0; 3], [50.0, 30.0, 20.0]], 7, 0.1).unwrap();
        let mut seed = 3;
        let pts: Vec<[f64; 3]> = (0..40)
            .map(|_| [0, 1, 2].map(|_| 60.0 * lcg(&mut seed) - 5.0))
            .collect();
        let d = g.distance_to(&pts).unwrap();
        for (i, d) in d.iter().enumerate() {
            let p = g.point(i);
            let want = pts
                .iter()
                .map(|q| (0..3).map(|a| (p[a] - q[a]).powi(2)).sum::<f64>().sqrt())
                .fold(f64::INFINITY, f64::min);
            assert!((d - want).abs() < 1e-9, "point {i}: {d} vs {want}");
        }
        assert!(g.distance_to(&[]).is_none());
    }
}
