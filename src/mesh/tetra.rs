//! Tetrahedral meshing of a closed triangle surface by isosurface stuffing.
//!
//! This module owns the volume mesher: a closed, consistently oriented [`TriSurface`] (from any
//! reader, in millimetres, facing in or out) becomes a [`TetMesh`] of nearly uniform tetrahedra of
//! edge length about `H` ([`TetraParams::edge_mm`]) whose boundary nodes lie on the surface. The
//! method is F. Labelle and J. R. Shewchuk, "Isosurface Stuffing: Fast Tetrahedral Meshes with Good
//! Dihedral Angles", ACM Transactions on Graphics 26(3), SIGGRAPH 2007, in its uniform (ungraded)
//! form:
//!
//! 1. **Lattice.** A body-centred cubic (BCC) lattice covers the surface's bounding box with a margin
//!    of at least one cube: cube corners spaced `H` apart plus the cube centres. Its edges are *long*
//!    ("black", length `H`: corner–corner and centre–centre along an axis) or *short* ("red",
//!    length `√3/2·H`: corner–centre). Each BCC tetrahedron joins two face-adjacent cube centres with
//!    one edge of the square they share: four tetrahedra per pair of adjacent cubes, twelve per cube.
//! 2. **Implicit function.** `f` is the signed distance to the surface, negative inside
//!    ([`SignedDistance`]: closest triangle through a bounding-volume hierarchy, sign from the
//!    generalized winding number, so neither the surface's orientation nor small folds and
//!    self-intersections matter). It is evaluated along lattice rows in parallel; since `f` is
//!    1-Lipschitz, a point farther than `H` from the surface by the bound from an earlier exact value
//!    in its row only takes that value's sign (no edge of such a point can cross the surface).
//! 3. **Cut points.** On every lattice edge whose ends have strictly opposite signs, the zero of the
//!    true `f` is found by safeguarded regula falsi (Illinois) to `|f| ≤ 1e-7·H`, so cut points lie
//!    on the input surface (the paper interpolates `f` linearly instead).
//! 4. **Warping.** A lattice vertex closer to a cut point on one of its edges than `α` times that
//!    edge's length (`α_long` on long edges, `α_short` on short ones) moves onto the closest such cut
//!    point and gets `f = 0`; cut points on edges touching a warped vertex disappear. All vertices are
//!    tested against the cut points of the unwarped lattice. The paper proves two bounds: with
//!    `(α_long, α_short) = (0.24999, 0.41189)` dihedral angles lie in [10.7°, 164.8°] for tetrahedra
//!    with a vertex off the surface, and with `(0.21509, 0.35900)` in [8.9°, 158.8°] including the
//!    tetrahedra whose four vertices are all on the surface (kept below when inside). The defaults are
//!    the second pair: on the SOFA livers and spheres the smallest angle measured is 13–15° with it,
//!    7.8° with the first pair (from all-on-surface tetrahedra).
//! 5. **Stencils.** Each BCC tetrahedron is replaced by its part inside the surface, according to
//!    the signs (−, 0, +) of its vertices: kept whole without a + vertex; dropped without a −
//!    vertex, except that one with four 0 vertices is kept when its centroid is inside; otherwise the
//!    polytope spanned by its −/0 vertices and cut points (a tetrahedron, a pyramid or a triangular
//!    prism, as in the paper's Figure 3) is split into tetrahedra. Quadrilaterals on lattice faces —
//!    shared with the neighbouring BCC tetrahedron — are split by rules that depend on the face alone,
//!    so neighbours agree and the mesh conforms: when the two inside vertices form a short edge, the
//!    diagonal ends at the cut point on the face's long edge; when they form a long edge, the paper's
//!    parity rule chooses the diagonal (from a lattice vertex to a cut point) whose direction has an
//!    odd number of negative coordinates between two cube corners, an even number between two cube
//!    centres. Among the triangulations that respect those diagonals (a pulling from each admissible
//!    polytope vertex, with either diagonal of a quadrilateral cut face), the one with the largest
//!    smallest dihedral angle is taken; the paper's stencil is one of them.
//! 6. **Finishing.** Unused lattice vertices are dropped (nodes keep lattice order, then cut-point
//!    order, so the output is deterministic and independent of thread count and of the surface's
//!    orientation). Where the shape is thinner than the lattice, two parts of the mesh can touch at a
//!    vertex or along an edge ("pinches"). A pinched vertex is unzipped into coincident copies, one
//!    per fan of tetrahedra around it; an edge whose fans still meet around both ends is closed by
//!    one tetrahedron in the gap between two of its boundary triangles (it has only surface nodes
//!    and is accepted only with dihedral angles of at least 8.9°). The boundary is then a closed
//!    2-manifold ([`TetraParams::repair_pinches`]), except at a vertex where the outside touches
//!    itself while the tetrahedra around it form a ring (a crevice of the surface closed off at
//!    that vertex): those are counted in the report (rare: one coarse lattice size of forty tried
//!    on the SOFA livers). Optionally only the largest face-connected piece is kept.
//!    The mesh is then checked: every tetrahedron positively oriented and non-degenerate.

use super::spatial::SignedDistance;
use super::tet_mesh::TET_FACES;
use super::vec3::{add, cross, dot, scale, sub, tet_signed_volume};
use super::{TetMesh, TriSurface, quality};
use rayon::prelude::*;
use std::time::Instant;

/// Parameters of [`tetrahedralize`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TetraParams {
    /// Target edge length `H` in mm: the spacing of the cube corners of the BCC lattice (long edges
    /// have length `H`, short ones `√3/2·H`; interior tets are the BCC ones, boundary tets smaller).
    pub edge_mm: f64,
    /// Warp threshold on long (axis-parallel) lattice edges, as a fraction of the edge length
    /// (default 0.21509; see the module docs for the paper's two parameter pairs).
    pub alpha_long: f64,
    /// Warp threshold on short (corner–centre) lattice edges, as a fraction (default 0.35900).
    pub alpha_short: f64,
    /// Most lattice points accepted (memory bound: about 13 bytes each, plus the mesh).
    pub max_lattice_points: usize,
    /// Keep only the largest face-connected piece (drops bits of thin features cut off at this `H`;
    /// turn it off to mesh a surface made of several closed parts).
    pub keep_largest_component: bool,
    /// Repair pinches — where the shape is thinner than the lattice and parts of the mesh touch at
    /// a vertex or along an edge — so the boundary is a closed 2-manifold: a pinched vertex gets a
    /// coincident copy per extra fan of tets; a pinched edge is closed by one tetrahedron of good
    /// angles (see the module docs).
    pub repair_pinches: bool,
}

impl Default for TetraParams {
    /// `H` = 5 mm, the paper's (0.21509, 0.35900) warp thresholds, at most 50 M lattice points,
    /// pinches unzipped, largest piece only.
    fn default() -> Self {
        Self {
            edge_mm: 5.0,
            alpha_long: 0.21509,
            alpha_short: 0.35900,
            max_lattice_points: 50_000_000,
            keep_largest_component: true,
            repair_pinches: true,
        }
    }
}

impl TetraParams {
    /// Default parameters with the given target edge length (mm).
    pub fn with_edge(edge_mm: f64) -> Self {
        Self {
            edge_mm,
            ..Self::default()
        }
    }
}

/// Why a surface could not be meshed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TetraError {
    /// The surface has no triangles, or they enclose no area.
    #[error("the surface is empty ({triangles} triangles, area {area_mm2} mm²): nothing to mesh")]
    EmptySurface {
        /// Triangle count.
        triangles: usize,
        /// Total area (mm²).
        area_mm2: f64,
    },
    /// Some edges do not have exactly two triangles.
    #[error(
        "the surface is not closed: {boundary_edges} edges belong to one triangle (holes) and {nonmanifold_edges} to more than two; isosurface stuffing needs a watertight surface (fill the holes; if the file holds stray pieces, mesh TriSurface::largest_component)"
    )]
    NotClosed {
        /// Edges with one triangle.
        boundary_edges: usize,
        /// Edges with three or more triangles.
        nonmanifold_edges: usize,
    },
    /// Neighbouring triangles disagree on orientation, so inside and outside are undefined.
    #[error(
        "the surface is not consistently oriented: {misoriented_edges} edges are traversed in the same direction by both of their triangles (reorient the faces)"
    )]
    NotOriented {
        /// Edges whose two triangles traverse them the same way.
        misoriented_edges: usize,
    },
    /// `edge_mm` is zero, negative or not finite.
    #[error("the target edge length must be a positive finite number of mm, got {edge_mm}")]
    InvalidEdgeLength {
        /// The value given.
        edge_mm: f64,
    },
    /// `edge_mm` exceeds half the largest extent of the surface.
    #[error(
        "the target edge length {edge_mm} mm is too large for a surface whose bounding box is {extent_mm:?} mm: use at most {max_mm} mm (half the largest extent)"
    )]
    EdgeTooLarge {
        /// The value given.
        edge_mm: f64,
        /// Bounding-box size (mm).
        extent_mm: [f64; 3],
        /// Largest accepted edge length (mm).
        max_mm: f64,
    },
    /// A warp threshold lies outside `[0, 0.5)`.
    #[error(
        "warp thresholds must lie in [0, 0.5): alpha_long = {alpha_long}, alpha_short = {alpha_short}"
    )]
    InvalidAlpha {
        /// Threshold on long edges.
        alpha_long: f64,
        /// Threshold on short edges.
        alpha_short: f64,
    },
    /// The lattice would exceed [`TetraParams::max_lattice_points`].
    #[error(
        "the lattice would have {points:.3e} points at H = {edge_mm} mm, above the limit of {limit}: increase the edge length (or TetraParams::max_lattice_points if memory allows)"
    )]
    TooManyLatticePoints {
        /// Lattice points needed.
        points: f64,
        /// Target edge length (mm).
        edge_mm: f64,
        /// The limit.
        limit: usize,
    },
    /// No lattice vertex lies inside the surface.
    #[error(
        "no tetrahedron was produced at H = {edge_mm} mm: the shape is thinner than the lattice; decrease the edge length"
    )]
    NoTetrahedra {
        /// Target edge length (mm).
        edge_mm: f64,
    },
    /// An internal invariant failed (a bug): the message names it.
    #[error("internal error in the tetrahedral mesher (please report with the surface): {0}")]
    Internal(String),
}

/// Seconds spent in each stage of [`tetrahedralize_with_report`].
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct TetraTimings {
    /// Checks and the distance structure (BVH, pseudo-normals).
    pub setup: f64,
    /// Signed distance at the lattice points.
    pub distance: f64,
    /// Cut points (root finding on the lattice edges that cross the surface).
    pub cut_points: f64,
    /// Warping lattice vertices onto the surface.
    pub warp: f64,
    /// Stencils: filling the BCC tetrahedra.
    pub fill: f64,
    /// Compaction, component filtering, orientation and validation.
    pub finish: f64,
    /// Everything.
    pub total: f64,
}

/// Facts about one run of the mesher.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TetraReport {
    /// Target edge length `H` (mm).
    pub edge_mm: f64,
    /// Lattice cubes per axis.
    pub lattice_cubes: [usize; 3],
    /// Lattice points (corners and centres).
    pub lattice_points: usize,
    /// Lattice points whose signed distance was computed (the others are farther than `H`).
    pub distance_queries: usize,
    /// Lattice edges crossing the surface (cut points computed).
    pub cut_points: usize,
    /// Lattice vertices warped onto the surface.
    pub warped_vertices: usize,
    /// BCC tetrahedra with all four vertices on the surface kept because their centroid is inside.
    pub all_on_surface_tets: usize,
    /// Boundary vertices copied to unzip pinches (parts of the mesh touching at a vertex; see
    /// [`TetraParams::repair_pinches`]).
    pub split_vertices: usize,
    /// Tetrahedra added to close pinched edges (parts touching along an edge).
    pub pinch_fill_tets: usize,
    /// Boundary edges left in more than two boundary triangles (0 unless unrepairable or disabled).
    pub pinched_edges: usize,
    /// Boundary vertices where the boundary is not one fan of triangles (the outside touches itself
    /// while the tets around form a ring; left as they are — a slightly different edge length
    /// usually avoids them).
    pub pinched_vertices: usize,
    /// Tetrahedra dropped with the smaller face-connected pieces.
    pub dropped_tets: usize,
    /// Face-connected pieces before filtering.
    pub pieces: usize,
    /// Output nodes.
    pub nodes: usize,
    /// Output tetrahedra.
    pub tets: usize,
    /// Stage timings (s).
    pub seconds: TetraTimings,
}

/// Meshes the inside of a closed surface with tetrahedra of edge length about `params.edge_mm`.
pub fn tetrahedralize(surface: &TriSurface, params: &TetraParams) -> Result<TetMesh, TetraError> {
    tetrahedralize_with_report(surface, params).map(|(mesh, _)| mesh)
}

/// Long lattice edges from a lattice point, in doubled coordinates.
const LONG: [[i64; 3]; 6] = [
    [-2, 0, 0],
    [2, 0, 0],
    [0, -2, 0],
    [0, 2, 0],
    [0, 0, -2],
    [0, 0, 2],
];
/// Short lattice edges from a lattice point, in doubled coordinates.
const SHORT: [[i64; 3]; 8] = [
    [-1, -1, -1],
    [1, -1, -1],
    [-1, 1, -1],
    [1, 1, -1],
    [-1, -1, 1],
    [1, -1, 1],
    [-1, 1, 1],
    [1, 1, 1],
];

/// The BCC lattice: cube corners at `lo + h·(i, j, k)`, centres at `lo + h·(i + ½, j + ½, k + ½)`.
/// Points are addressed by "doubled" integer coordinates (corners even, centres odd on every axis)
/// and numbered corners first, then centres, x fastest.
struct Lattice {
    h: f64,
    lo: [f64; 3],
    /// Cubes per axis.
    n: [usize; 3],
    num_corners: usize,
    num_points: usize,
}

impl Lattice {
    fn doubled(&self, idx: u32) -> [i64; 3] {
        let idx = idx as usize;
        if idx < self.num_corners {
            let (nx, ny) = (self.n[0] + 1, self.n[1] + 1);
            let (i, r) = (idx % nx, idx / nx);
            let (j, k) = (r % ny, r / ny);
            [2 * i as i64, 2 * j as i64, 2 * k as i64]
        } else {
            let r = idx - self.num_corners;
            let (nx, ny) = (self.n[0], self.n[1]);
            let (i, r) = (r % nx, r / nx);
            let (j, k) = (r % ny, r / ny);
            [2 * i as i64 + 1, 2 * j as i64 + 1, 2 * k as i64 + 1]
        }
    }

    fn index(&self, d: [i64; 3]) -> Option<u32> {
        let odd = d.map(|x| x.rem_euclid(2) == 1);
        if odd.iter().all(|&o| !o) {
            let c = [d[0] / 2, d[1] / 2, d[2] / 2];
            if (0..3).all(|a| c[a] >= 0 && c[a] <= self.n[a] as i64) {
                let (nx, ny) = (self.n[0] + 1, self.n[1] + 1);
                return Some((c[0] as usize + nx * (c[1] as usize + ny * c[2] as usize)) as u32);
            }
        } else if odd.iter().all(|&o| o) {
            let c = [(d[0] - 1) / 2, (d[1] - 1) / 2, (d[2] - 1) / 2];
            if (0..3).all(|a| c[a] >= 0 && c[a] < self.n[a] as i64) {
                let (nx, ny) = (self.n[0], self.n[1]);
                return Some(
                    (self.num_corners + c[0] as usize + nx * (c[1] as usize + ny * c[2] as usize))
                        as u32,
                );
            }
        }
        None
    }

    fn is_centre(&self, idx: u32) -> bool {
        idx as usize >= self.num_corners
    }

    fn position_of_doubled(&self, d: [i64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| self.lo[a] + 0.5 * self.h * d[a] as f64)
    }

    fn position(&self, idx: u32) -> [f64; 3] {
        self.position_of_doubled(self.doubled(idx))
    }

    /// Neighbours of a point: `(index, long)` for each lattice edge.
    fn neighbours(&self, idx: u32) -> impl Iterator<Item = (u32, bool)> + '_ {
        let d = self.doubled(idx);
        LONG.iter()
            .map(|o| (o, true))
            .chain(SHORT.iter().map(|o| (o, false)))
            .filter_map(move |(o, long)| {
                self.index([d[0] + o[0], d[1] + o[1], d[2] + o[2]])
                    .map(|q| (q, long))
            })
    }
}

/// A cut point on the lattice edge `key = (a << 32) | b`, `a < b`, at fraction `t` from `a`.
#[derive(Debug, Clone, Copy)]
struct Cut {
    key: u64,
    t: f64,
    pos: [f64; 3],
}

#[inline]
fn edge_key(a: u32, b: u32) -> u64 {
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    ((lo as u64) << 32) | hi as u64
}

#[inline]
fn sign_of(v: f64) -> i8 {
    if v < 0.0 {
        -1
    } else if v > 0.0 {
        1
    } else {
        0
    }
}

/// Zero of the signed distance on the segment `a → b` (`fa < 0 < fb` or the reverse): safeguarded
/// regula falsi (Illinois), to `|f| ≤ tol` or an interval below `1e-12` of the edge.
fn find_zero(
    sd: &SignedDistance,
    a: [f64; 3],
    fa: f64,
    b: [f64; 3],
    fb: f64,
    hint: Option<u32>,
    tol: f64,
) -> f64 {
    let ab = sub(b, a);
    let (mut t0, mut f0, mut t1, mut f1) = (0.0f64, fa, 1.0f64, fb);
    let mut hint = hint;
    let mut side = 0i8;
    let mut t = 0.5;
    for _ in 0..60 {
        t = (t0 * f1 - t1 * f0) / (f1 - f0);
        let width = t1 - t0;
        if !t.is_finite() || t <= t0 + 1e-3 * width || t >= t1 - 1e-3 * width {
            // Keep the secant step strictly inside the bracket (bisect if it is not a number); the
            // Illinois halving below keeps one end from sticking.
            t = if t.is_finite() {
                t.clamp(t0 + 1e-3 * width, t1 - 1e-3 * width)
            } else {
                0.5 * (t0 + t1)
            };
        }
        let (ft, h) = sd.eval_with_hint(add(a, scale(ab, t)), hint);
        hint = Some(h);
        if ft.abs() <= tol {
            return t;
        }
        if (ft < 0.0) == (f0 < 0.0) {
            t0 = t;
            f0 = ft;
            if side == -1 {
                f1 *= 0.5;
            }
            side = -1;
        } else {
            t1 = t;
            f1 = ft;
            if side == 1 {
                f0 *= 0.5;
            }
            side = 1;
        }
        if t1 - t0 <= 1e-12 {
            return 0.5 * (t0 + t1);
        }
    }
    t
}

/// Meshes the inside of a closed surface and reports what was done (see the module docs).
pub fn tetrahedralize_with_report(
    surface: &TriSurface,
    params: &TetraParams,
) -> Result<(TetMesh, TetraReport), TetraError> {
    let start = Instant::now();
    let mut seconds = TetraTimings::default();
    let h = params.edge_mm;
    if !(h.is_finite() && h > 0.0) {
        return Err(TetraError::InvalidEdgeLength { edge_mm: h });
    }
    let (al, as_) = (params.alpha_long, params.alpha_short);
    if !((0.0..0.5).contains(&al) && (0.0..0.5).contains(&as_)) {
        return Err(TetraError::InvalidAlpha {
            alpha_long: al,
            alpha_short: as_,
        });
    }
    let stats = surface.stats();
    if stats.triangles == 0 || stats.area_mm2 <= 0.0 {
        return Err(TetraError::EmptySurface {
            triangles: stats.triangles,
            area_mm2: stats.area_mm2,
        });
    }
    if !stats.closed {
        return Err(TetraError::NotClosed {
            boundary_edges: stats.boundary_edges,
            nonmanifold_edges: stats.nonmanifold_edges,
        });
    }
    if !stats.consistently_oriented {
        return Err(TetraError::NotOriented {
            misoriented_edges: stats.misoriented_edges,
        });
    }
    let (bmin, bmax) = surface.bounding_box();
    let extent = [0, 1, 2].map(|a| bmax[a] - bmin[a]);
    let max_extent = extent.iter().copied().fold(0.0, f64::max);
    if h > 0.5 * max_extent {
        return Err(TetraError::EdgeTooLarge {
            edge_mm: h,
            extent_mm: extent,
            max_mm: 0.5 * max_extent,
        });
    }
    // Cubes per axis: the box plus at least one cube of margin on each side, centred on the box.
    let cubes_f = extent.map(|e| (e / h).ceil() + 2.0);
    let points_f =
        cubes_f.iter().map(|c| c + 1.0).product::<f64>() + cubes_f.iter().product::<f64>();
    // (Finite: h > 0 and the box is finite; global node ids must stay below u32::MAX with cuts.)
    if points_f > params.max_lattice_points as f64 || points_f >= u32::MAX as f64 / 8.0 {
        return Err(TetraError::TooManyLatticePoints {
            points: points_f,
            edge_mm: h,
            limit: params.max_lattice_points,
        });
    }
    let n = cubes_f.map(|c| c as usize);
    let lo = [0, 1, 2].map(|a| 0.5 * (bmin[a] + bmax[a]) - 0.5 * h * n[a] as f64);
    let num_corners = (n[0] + 1) * (n[1] + 1) * (n[2] + 1);
    let lat = Lattice {
        h,
        lo,
        n,
        num_corners,
        num_points: num_corners + n[0] * n[1] * n[2],
    };
    let sd = SignedDistance::new(surface).map_err(TetraError::Internal)?;
    seconds.setup = start.elapsed().as_secs_f64();

    // 1. Signed distance at the lattice points, row by row (x fastest); a point whose distance
    //    bound from the last exact value along its row exceeds H only gets the sign.
    let t = Instant::now();
    let mut f = vec![0.0f64; lat.num_points];
    let mut hint = vec![u32::MAX; lat.num_points];
    let skip = h * (1.0 + 1e-6);
    let eval_row = |first: usize, fr: &mut [f64], hr: &mut [u32]| -> usize {
        let mut last: Option<(usize, f64, u32)> = None;
        let mut queries = 0;
        for i in 0..fr.len() {
            let mut seed = None;
            if let Some((li, lf, lh)) = last {
                let bound = lf.abs() - (i - li) as f64 * h;
                if bound > skip {
                    fr[i] = lf.signum() * bound;
                    continue;
                }
                seed = Some(lh);
            }
            let (v, tri) = sd.eval_with_hint(lat.position((first + i) as u32), seed);
            fr[i] = v;
            hr[i] = tri;
            last = Some((i, v, tri));
            queries += 1;
        }
        queries
    };
    let (fc, fm) = f.split_at_mut(num_corners);
    let (hc, hm) = hint.split_at_mut(num_corners);
    let rx_c = n[0] + 1;
    let mut distance_queries: usize = fc
        .par_chunks_mut(rx_c)
        .zip(hc.par_chunks_mut(rx_c))
        .enumerate()
        .map(|(r, (fr, hr))| eval_row(r * rx_c, fr, hr))
        .sum();
    distance_queries += fm
        .par_chunks_mut(n[0])
        .zip(hm.par_chunks_mut(n[0]))
        .enumerate()
        .map(|(r, (fr, hr))| eval_row(num_corners + r * n[0], fr, hr))
        .sum::<usize>();
    seconds.distance = t.elapsed().as_secs_f64();

    // 2. Cut points on lattice edges with strictly opposite signs (both ends are exact: |f| ≤ H).
    let t = Instant::now();
    let near = |p: u32| hint[p as usize] != u32::MAX && f[p as usize].abs() <= skip;
    let mut edges: Vec<(u32, u32)> = (0..lat.num_points as u32)
        .into_par_iter()
        .with_min_len(4096)
        .flat_map_iter(|p| {
            let sp = sign_of(f[p as usize]);
            let candidates: Vec<(u32, u32)> = if sp != 0 && near(p) {
                lat.neighbours(p)
                    .filter(|&(q, _)| q > p && sign_of(f[q as usize]) == -sp)
                    .map(|(q, _)| (p, q))
                    .collect()
            } else {
                Vec::new()
            };
            candidates
        })
        .collect();
    edges.sort_unstable();
    let tol = 1e-7 * h;
    let cuts: Vec<Cut> = edges
        .par_iter()
        .with_min_len(64)
        .map(|&(a, b)| {
            let (pa, pb) = (lat.position(a), lat.position(b));
            let (fa, fb) = (f[a as usize], f[b as usize]);
            let seed = [hint[a as usize], hint[b as usize]]
                .into_iter()
                .find(|&s| s != u32::MAX);
            let t = find_zero(&sd, pa, fa, pb, fb, seed, tol);
            Cut {
                key: edge_key(a, b),
                t,
                pos: add(pa, scale(sub(pb, pa), t)),
            }
        })
        .collect();
    let find_cut = |a: u32, b: u32| -> Option<usize> {
        cuts.binary_search_by_key(&edge_key(a, b), |c| c.key).ok()
    };
    seconds.cut_points = t.elapsed().as_secs_f64();

    // 3. Warping: a vertex violated by a cut point on one of its edges moves to the closest one.
    let t = Instant::now();
    let short_len = 0.5 * 3f64.sqrt() * h;
    let warped: Vec<(u32, [f64; 3])> = (0..lat.num_points as u32)
        .into_par_iter()
        .with_min_len(4096)
        .filter_map(|p| {
            let sp = sign_of(f[p as usize]);
            if sp == 0 || !near(p) {
                return None;
            }
            let mut best: Option<(f64, [f64; 3])> = None;
            for (q, long) in lat.neighbours(p) {
                if sign_of(f[q as usize]) != -sp {
                    continue;
                }
                let c = cuts[find_cut(p, q)?];
                let frac = if p < q { c.t } else { 1.0 - c.t };
                let (alpha, len) = if long { (al, h) } else { (as_, short_len) };
                if frac < alpha && best.is_none_or(|(d, _)| frac * len < d) {
                    best = Some((frac * len, c.pos));
                }
            }
            best.map(|(_, pos)| (p, pos))
        })
        .collect();
    let mut sign: Vec<i8> = f.par_iter().map(|&v| sign_of(v)).collect();
    for &(p, _) in &warped {
        sign[p as usize] = 0;
    }
    seconds.warp = t.elapsed().as_secs_f64();

    // 4. Stencils, per pair of face-adjacent cube centres (each centre owns its +x, +y, +z pairs).
    let t = Instant::now();
    let ctx = Fill {
        lat: &lat,
        sign: &sign,
        cuts: &cuts,
        warped: &warped,
        sd: &sd,
    };
    let num_centres = lat.num_points - num_corners;
    let pieces: Vec<(Vec<[u32; 4]>, usize, Option<String>)> = (0..num_centres)
        .into_par_iter()
        .with_min_len(256)
        .fold(
            || (Vec::new(), 0usize, None),
            |(mut out, mut all_on, mut err), c| {
                if err.is_none() {
                    err = ctx
                        .centre((num_corners + c) as u32, &mut out, &mut all_on)
                        .err();
                }
                (out, all_on, err)
            },
        )
        .collect();
    let mut all_on_surface_tets = 0;
    let mut global_tets: Vec<[u32; 4]> = Vec::new();
    for (out, all_on, err) in pieces {
        if let Some(e) = err {
            return Err(TetraError::Internal(e));
        }
        all_on_surface_tets += all_on;
        global_tets.extend_from_slice(&out);
    }
    seconds.fill = t.elapsed().as_secs_f64();
    if global_tets.is_empty() {
        return Err(TetraError::NoTetrahedra { edge_mm: h });
    }

    // 5. Compact: nodes are the used lattice points (warped where warped) then the used cut points.
    let t = Instant::now();
    let mut used: Vec<u32> = global_tets.iter().flatten().copied().collect();
    used.par_sort_unstable();
    used.dedup();
    let nodes: Vec<[f64; 3]> = used.par_iter().map(|&g| ctx.node_position(g)).collect();
    let local = |g: u32| used.binary_search(&g).map(|i| i as u32);
    let tets: Vec<[u32; 4]> = global_tets
        .par_iter()
        .map(|tet| {
            let mut out = [0u32; 4];
            for k in 0..4 {
                out[k] = local(tet[k]).unwrap_or(u32::MAX);
            }
            out
        })
        .collect();
    drop(global_tets);
    let mut mesh = TetMesh::new(nodes, tets).map_err(|e| TetraError::Internal(e.to_string()))?;
    let pinches = if params.repair_pinches {
        repair_pinches(&mut mesh)?
    } else {
        PinchRepair::default()
    };
    let (labels, pieces) = mesh.face_components();
    let mut dropped_tets = 0;
    if params.keep_largest_component && pieces > 1 {
        let mut sizes = vec![0usize; pieces];
        for &l in &labels {
            sizes[l as usize] += 1;
        }
        let best = (0..pieces)
            .max_by_key(|&c| (sizes[c], usize::MAX - c))
            .unwrap_or(0) as u32;
        let kept: Vec<[u32; 4]> = mesh
            .tets()
            .iter()
            .zip(&labels)
            .filter(|(_, l)| **l == best)
            .map(|(t, _)| *t)
            .collect();
        dropped_tets = mesh.num_tets() - kept.len();
        mesh = TetMesh::new(mesh.nodes().to_vec(), kept)
            .map_err(|e| TetraError::Internal(e.to_string()))?;
        mesh.remove_unused_nodes();
    }
    let flipped = mesh.orient_positive();
    if flipped > 0 {
        return Err(TetraError::Internal(format!(
            "{flipped} stencil tetrahedra came out inverted"
        )));
    }
    mesh.validate()
        .map_err(|e| TetraError::Internal(format!("the stuffed mesh is invalid: {e}")))?;
    seconds.finish = t.elapsed().as_secs_f64();
    seconds.total = start.elapsed().as_secs_f64();
    let report = TetraReport {
        edge_mm: h,
        lattice_cubes: n,
        lattice_points: lat.num_points,
        distance_queries,
        cut_points: cuts.len(),
        warped_vertices: warped.len(),
        all_on_surface_tets,
        split_vertices: pinches.copies,
        pinch_fill_tets: pinches.fills,
        pinched_edges: pinches.left,
        pinched_vertices: pinches.left_vertices,
        dropped_tets,
        pieces,
        nodes: mesh.num_nodes(),
        tets: mesh.num_tets(),
        seconds,
    };
    Ok((mesh, report))
}

/// Labels of face-connected groups among `tets` (indices into `all`), where two tets are joined
/// when they share a key from `keys` (a face through the pinch candidate); labels in first-seen order.
fn groups(tets: &[u32], keys: impl Fn(u32, &mut Vec<u64>)) -> Vec<usize> {
    let mut pairs: Vec<(u64, usize)> = Vec::with_capacity(tets.len() * 3);
    let mut buf = Vec::with_capacity(3);
    for (i, &t) in tets.iter().enumerate() {
        buf.clear();
        keys(t, &mut buf);
        pairs.extend(buf.iter().map(|&k| (k, i)));
    }
    pairs.sort_unstable();
    let mut parent: Vec<usize> = (0..tets.len()).collect();
    fn root(parent: &mut [usize], mut x: usize) -> usize {
        while parent[x] != x {
            parent[x] = parent[parent[x]];
            x = parent[x];
        }
        x
    }
    for w in pairs.windows(2) {
        if w[0].0 == w[1].0 {
            let (a, b) = (root(&mut parent, w[0].1), root(&mut parent, w[1].1));
            if a != b {
                parent[a.max(b)] = a.min(b);
            }
        }
    }
    let mut label_of_root = vec![usize::MAX; tets.len()];
    let mut next = 0;
    (0..tets.len())
        .map(|i| {
            let r = root(&mut parent, i);
            if label_of_root[r] == usize::MAX {
                label_of_root[r] = next;
                next += 1;
            }
            label_of_root[r]
        })
        .collect()
}

/// What [`repair_pinches`] did.
#[derive(Debug, Default, Clone, Copy)]
struct PinchRepair {
    copies: usize,
    fills: usize,
    left: usize,
    left_vertices: usize,
}

/// Smallest dihedral angle accepted for a tetrahedron that closes a pinched edge (the paper's bound
/// for the default warp thresholds).
const FILL_MIN_DIHEDRAL: f64 = 8.9;

/// Repairs pinches — places where the shape is thinner than the lattice and two parts of the mesh
/// touch (stuffing warps the vertices between them onto both sides of the surface):
///
/// * a boundary vertex whose tets fall into several fans (face-connected through faces at the
///   vertex) gets a copy, at the same position, for every fan but the largest, which keeps the
///   parts apart as they are in the surface and changes no position, volume or angle;
/// * an edge still shared by more than two boundary triangles (its fans meet again around both
///   ends) is closed by one tetrahedron spanning the edge and the far corners of two boundary
///   triangles of different fans, in the gap between them;
///
/// The added tetrahedra have only surface nodes and are accepted only with dihedral angles of at
/// least [`FILL_MIN_DIHEDRAL`]. Rounds repeat until nothing changes (at most 8). A vertex where
/// the outside touches itself while its tets form one ring is left and counted
/// ([`count_pinched_vertices`]).
fn repair_pinches(mesh: &mut TetMesh) -> Result<PinchRepair, TetraError> {
    let internal = |e: super::MeshError| TetraError::Internal(e.to_string());
    let mut done = PinchRepair::default();
    for _round in 0..8 {
        let b = mesh.boundary().map_err(internal)?;
        let (offsets, incident) = mesh.node_to_tets();
        let mut tets = mesh.tets().to_vec();
        let mut nodes = mesh.nodes().to_vec();
        let mut changed = false;
        for &v in &b.nodes {
            let fan = &incident[offsets[v as usize]..offsets[v as usize + 1]];
            let labels = groups(fan, |t, out| {
                // The three faces through v, keyed by their other two nodes.
                let tet = tets[t as usize];
                for (i, j) in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)] {
                    let (x, y) = (tet[i], tet[j]);
                    if x != v && y != v {
                        out.push(((x.min(y) as u64) << 32) | x.max(y) as u64);
                    }
                }
            });
            let count = labels.iter().copied().max().map_or(0, |m| m + 1);
            if count < 2 {
                continue;
            }
            let mut sizes = vec![0usize; count];
            for &l in &labels {
                sizes[l] += 1;
            }
            let keep = (0..count)
                .max_by_key(|&c| (sizes[c], usize::MAX - c))
                .unwrap_or(0);
            let mut copy_of = vec![u32::MAX; count];
            for (&t, &l) in fan.iter().zip(&labels) {
                if l == keep {
                    continue;
                }
                if copy_of[l] == u32::MAX {
                    copy_of[l] = nodes.len() as u32;
                    nodes.push(nodes[v as usize]);
                    done.copies += 1;
                }
                for x in tets[t as usize].iter_mut() {
                    if *x == v {
                        *x = copy_of[l];
                    }
                }
            }
            changed = true;
        }
        if !changed {
            let fills = accept_fills(mesh, pinch_fills(mesh, &b, &incident, &offsets));
            done.left = count_pinched_edges(&b) - fills.len();
            done.left_vertices = count_pinched_vertices(&b);
            if fills.is_empty() {
                return Ok(done);
            }
            done.fills += fills.len();
            tets.extend(fills);
        }
        *mesh = TetMesh::new(nodes, tets).map_err(internal)?;
    }
    let b = mesh.boundary().map_err(internal)?;
    done.left = count_pinched_edges(&b);
    done.left_vertices = count_pinched_vertices(&b);
    Ok(done)
}

/// Keeps the closing tetrahedra that fit together: in plan order, a fill is dropped when it repeats
/// one already kept (two pinched edges of one gap can propose the same tetrahedron) or when one of
/// its faces would then be shared by more than two tetrahedra.
fn accept_fills(mesh: &TetMesh, fills: Vec<[u32; 4]>) -> Vec<[u32; 4]> {
    use std::collections::HashMap;
    let key = |mut f: [u32; 3]| {
        f.sort_unstable();
        f
    };
    let faces_of = |t: &[u32; 4]| TET_FACES.map(|f| key([t[f[0]], t[f[1]], t[f[2]]]));
    let touched: std::collections::HashSet<u32> = fills.iter().flatten().copied().collect();
    let mut count: HashMap<[u32; 3], usize> = HashMap::new();
    for t in mesh.tets() {
        if t.iter().filter(|v| touched.contains(v)).count() >= 3 {
            for f in faces_of(t) {
                *count.entry(f).or_default() += 1;
            }
        }
    }
    let mut kept: Vec<[u32; 4]> = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for t in fills {
        let mut sorted = t;
        sorted.sort_unstable();
        if !seen.insert(sorted) {
            continue;
        }
        let faces = faces_of(&t);
        if faces
            .iter()
            .any(|f| count.get(f).copied().unwrap_or(0) >= 2)
        {
            continue;
        }
        for f in faces {
            *count.entry(f).or_default() += 1;
        }
        kept.push(t);
    }
    kept
}

/// Boundary vertices whose boundary triangles form more than one fan (their far edges form more
/// than one connected piece): the outside touches itself there, e.g. a crevice of the surface
/// closed off at that vertex at this lattice size. Vertex copies cannot separate such a vertex
/// (its tets form one ring) and no single tetrahedron closes it safely, so it is only counted.
fn count_pinched_vertices(b: &super::BoundarySurface) -> usize {
    let mut at: Vec<(u32, usize)> = b
        .triangles
        .iter()
        .enumerate()
        .flat_map(|(i, t)| t.iter().map(move |&v| (v, i)))
        .collect();
    at.sort_unstable();
    let mut pinched = 0;
    for run in at.chunk_by(|x, y| x.0 == y.0) {
        let v = run[0].0;
        let link: Vec<(u32, u32)> = run
            .iter()
            .map(|&(_, i)| {
                let t = b.triangles[i];
                let k = t.iter().position(|&x| x == v).unwrap_or(0);
                (t[(k + 1) % 3], t[(k + 2) % 3])
            })
            .collect();
        let mut verts: Vec<u32> = link.iter().flat_map(|&(x, y)| [x, y]).collect();
        verts.sort_unstable();
        verts.dedup();
        let idx = |x: u32| verts.binary_search(&x).unwrap_or(0);
        let mut parent: Vec<usize> = (0..verts.len()).collect();
        fn root(parent: &mut [usize], mut x: usize) -> usize {
            while parent[x] != x {
                parent[x] = parent[parent[x]];
                x = parent[x];
            }
            x
        }
        let mut pieces = verts.len();
        for &(x, y) in &link {
            let (rx, ry) = (root(&mut parent, idx(x)), root(&mut parent, idx(y)));
            if rx != ry {
                parent[rx.max(ry)] = rx.min(ry);
                pieces -= 1;
            }
        }
        if pieces > 1 {
            pinched += 1;
        }
    }
    pinched
}

/// For every boundary edge in more than two boundary triangles, the best closing tetrahedron (see
/// [`repair_pinches`]), positively oriented; edges without an acceptable one are left.
fn pinch_fills(
    mesh: &TetMesh,
    b: &super::BoundarySurface,
    incident: &[u32],
    offsets: &[usize],
) -> Vec<[u32; 4]> {
    let nodes = mesh.nodes();
    let tets = mesh.tets();
    let mut by_edge: Vec<((u32, u32), usize)> = b
        .triangles
        .iter()
        .enumerate()
        .flat_map(|(i, t)| {
            (0..3).map(move |k| ((t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3])), i))
        })
        .collect();
    by_edge.sort_unstable();
    let mut fills = Vec::new();
    for run in by_edge.chunk_by(|x, y| x.0 == y.0) {
        if run.len() <= 2 {
            continue;
        }
        let (a, c) = run[0].0;
        // Fans of tets around the edge, to pair boundary triangles of different fans.
        let around: Vec<u32> = incident[offsets[a as usize]..offsets[a as usize + 1]]
            .iter()
            .copied()
            .filter(|&t| tets[t as usize].contains(&c))
            .collect();
        let labels = groups(&around, |t, out| {
            out.extend(
                tets[t as usize]
                    .iter()
                    .filter(|&&x| x != a && x != c)
                    .map(|&x| x as u64),
            )
        });
        let fan_of = |tri: usize| -> Option<usize> {
            let t = b.tet_of_triangle[tri];
            around.iter().position(|&x| x == t).map(|i| labels[i])
        };
        let third = |tri: usize| -> u32 {
            b.triangles[tri]
                .iter()
                .copied()
                .find(|&x| x != a && x != c)
                .unwrap_or(a)
        };
        let normal = |tri: usize| -> [f64; 3] {
            let [p, q, r] = b.triangles[tri].map(|v| nodes[v as usize]);
            cross(sub(q, p), sub(r, p))
        };
        let pa = nodes[a as usize];
        let mut best: Option<(f64, [u32; 4])> = None;
        for (i, &(_, ti)) in run.iter().enumerate() {
            for &(_, tj) in &run[i + 1..] {
                let (x, y) = (third(ti), third(tj));
                if x == y || fan_of(ti).is_none() || fan_of(ti) == fan_of(tj) {
                    continue;
                }
                // Each far corner lies outside the other triangle: the tet sits in the gap.
                let (px, py) = (nodes[x as usize], nodes[y as usize]);
                if dot(normal(ti), sub(py, pa)) <= 0.0 || dot(normal(tj), sub(px, pa)) <= 0.0 {
                    continue;
                }
                // Its two new faces must not already be shared by two tets.
                let shared = |u: u32| {
                    incident[offsets[u as usize]..offsets[u as usize + 1]]
                        .iter()
                        .filter(|&&t| {
                            tets[t as usize].contains(&x) && tets[t as usize].contains(&y)
                        })
                        .count()
                };
                if shared(a) >= 2 || shared(c) >= 2 {
                    continue;
                }
                let mut tet = [a, c, x, y];
                let mut p = tet.map(|v| nodes[v as usize]);
                if tet_signed_volume(&p) < 0.0 {
                    tet.swap(2, 3);
                    p.swap(2, 3);
                }
                let lmax = super::tet_mesh::longest_edge(&p);
                if tet_signed_volume(&p) <= 1e-9 * lmax * lmax * lmax {
                    continue;
                }
                let q = quality::dihedral_angles_deg(&p)
                    .iter()
                    .copied()
                    .fold(f64::INFINITY, f64::min);
                if q >= FILL_MIN_DIHEDRAL && best.is_none_or(|(bq, _)| q > bq) {
                    best = Some((q, tet));
                }
            }
        }
        if let Some((_, tet)) = best {
            fills.push(tet);
        }
    }
    fills
}

/// Boundary edges shared by more than two boundary triangles (parts touching along an edge).
fn count_pinched_edges(b: &super::BoundarySurface) -> usize {
    let mut edges: Vec<(u32, u32)> = b
        .triangles
        .iter()
        .flat_map(|t| (0..3).map(move |k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]))))
        .collect();
    edges.sort_unstable();
    edges
        .chunk_by(|x, y| x == y)
        .filter(|run| run.len() > 2)
        .count()
}

/// Everything the stencil stage reads. Output node ids ("global"): lattice point `p` is `p`, cut
/// point `i` is `num_points + i`.
struct Fill<'a> {
    lat: &'a Lattice,
    sign: &'a [i8],
    cuts: &'a [Cut],
    warped: &'a [(u32, [f64; 3])],
    sd: &'a SignedDistance,
}

/// Up to six polytope vertices (inside/on-surface lattice vertices and cut points).
const MAX_PV: usize = 8;

/// A face of the inside polytope of one BCC tetrahedron, oriented outward.
#[derive(Clone, Copy)]
struct PFace {
    v: [u8; 4],
    len: u8,
    /// Quadrilateral diagonal fixed by the lattice-face rules (as polytope vertex indices), if any.
    diag: Option<(u8, u8)>,
}

impl Fill<'_> {
    fn node_position(&self, g: u32) -> [f64; 3] {
        let np = self.lat.num_points as u32;
        if g >= np {
            return self.cuts[(g - np) as usize].pos;
        }
        self.lattice_vertex_position(g)
    }

    fn lattice_vertex_position(&self, p: u32) -> [f64; 3] {
        if self.sign[p as usize] == 0 {
            if let Ok(i) = self.warped.binary_search_by_key(&p, |w| w.0) {
                return self.warped[i].1;
            }
        }
        self.lat.position(p)
    }

    /// The BCC tetrahedra between centre `c` and its +x, +y, +z neighbour centres.
    fn centre(&self, c: u32, out: &mut Vec<[u32; 4]>, all_on: &mut usize) -> Result<(), String> {
        let d = self.lat.doubled(c);
        for axis in 0..3 {
            let mut d2 = d;
            d2[axis] += 2;
            let Some(c2) = self.lat.index(d2) else {
                continue;
            };
            let (b, cc) = ((axis + 1) % 3, (axis + 2) % 3);
            let ring = [(-1, -1), (1, -1), (1, 1), (-1, 1)];
            let mut corners = [0u32; 4];
            let mut corner_d = [[0i64; 3]; 4];
            for (m, &(ob, oc)) in ring.iter().enumerate() {
                let mut k = d;
                k[axis] += 1;
                k[b] += ob;
                k[cc] += oc;
                corner_d[m] = k;
                corners[m] = self
                    .lat
                    .index(k)
                    .ok_or_else(|| format!("corner {k:?} of centre {d:?} is off the lattice"))?;
            }
            for m in 0..4 {
                let m2 = (m + 1) % 4;
                let mut tet = [c, c2, corners[m], corners[m2]];
                // Positive orientation in exact integer coordinates.
                let (e1, e2, e3) = (
                    [0, 1, 2].map(|a| d2[a] - d[a]),
                    [0, 1, 2].map(|a| corner_d[m][a] - d[a]),
                    [0, 1, 2].map(|a| corner_d[m2][a] - d[a]),
                );
                let det = e1[0] * (e2[1] * e3[2] - e2[2] * e3[1])
                    - e1[1] * (e2[0] * e3[2] - e2[2] * e3[0])
                    + e1[2] * (e2[0] * e3[1] - e2[1] * e3[0]);
                if det < 0 {
                    tet.swap(2, 3);
                }
                self.stuff(tet, out, all_on)?;
            }
        }
        Ok(())
    }

    /// Fills one positively oriented BCC tetrahedron `[centre, centre, corner, corner]`.
    fn stuff(
        &self,
        v: [u32; 4],
        out: &mut Vec<[u32; 4]>,
        all_on: &mut usize,
    ) -> Result<(), String> {
        let s = v.map(|p| self.sign[p as usize]);
        let n_in = s.iter().filter(|&&x| x < 0).count();
        let n_out = s.iter().filter(|&&x| x > 0).count();
        if n_in == 0 {
            if n_out == 0 {
                // Four vertices on the surface: keep the tetrahedron if its centroid is inside.
                let p = v.map(|q| self.lattice_vertex_position(q));
                let centroid = scale(add(add(p[0], p[1]), add(p[2], p[3])), 0.25);
                let lmax = super::tet_mesh::longest_edge(&p);
                if tet_signed_volume(&p) > 1e-9 * lmax * lmax * lmax && self.sd.eval(centroid) < 0.0
                {
                    out.push(v);
                    *all_on += 1;
                }
            }
            return Ok(());
        }
        if n_out == 0 {
            out.push(v);
            return Ok(());
        }
        self.stuff_crossing(v, s, out)
    }

    /// A BCC tetrahedron with inside and outside vertices: triangulates its inside polytope.
    fn stuff_crossing(
        &self,
        v: [u32; 4],
        s: [i8; 4],
        out: &mut Vec<[u32; 4]>,
    ) -> Result<(), String> {
        let np = self.lat.num_points as u32;
        // Polytope vertices: global ids and positions.
        let mut ids = [0u32; MAX_PV];
        let mut pos = [[0.0f64; 3]; MAX_PV];
        let mut count = 0usize;
        let mut of_lattice = [u8::MAX; 4];
        for i in 0..4 {
            if s[i] <= 0 {
                of_lattice[i] = count as u8;
                ids[count] = v[i];
                pos[count] = self.lattice_vertex_position(v[i]);
                count += 1;
            }
        }
        let mut of_cut = [[u8::MAX; 4]; 4];
        for i in 0..4 {
            for j in (i + 1)..4 {
                if s[i] * s[j] < 0 {
                    let key = edge_key(v[i], v[j]);
                    let ci = self
                        .cuts
                        .binary_search_by_key(&key, |c| c.key)
                        .map_err(|_| format!("no cut point on lattice edge {:?}", (v[i], v[j])))?;
                    of_cut[i][j] = count as u8;
                    of_cut[j][i] = count as u8;
                    ids[count] = np + ci as u32;
                    pos[count] = self.cuts[ci].pos;
                    count += 1;
                }
            }
        }
        // Faces on the four lattice faces (outward, clipped in order).
        let mut faces: Vec<PFace> = Vec::with_capacity(5);
        for lf in TET_FACES {
            let mut poly = [0u8; 4];
            let mut len = 0usize;
            let mut n_in = 0;
            for e in 0..3 {
                let (x, y) = (lf[e], lf[(e + 1) % 3]);
                if s[x] < 0 {
                    n_in += 1;
                }
                if s[x] <= 0 && len < 4 {
                    poly[len] = of_lattice[x];
                    len += 1;
                }
                if s[x] * s[y] < 0 && len < 4 {
                    poly[len] = of_cut[x][y];
                    len += 1;
                }
            }
            if n_in == 0 || len < 3 {
                continue;
            }
            let diag = if len == 4 {
                // Two inside lattice vertices u, v and one outside w on this face.
                let ins: Vec<usize> = lf.iter().copied().filter(|&x| s[x] < 0).collect();
                let w = lf
                    .iter()
                    .copied()
                    .find(|&x| s[x] > 0)
                    .ok_or("quad without outside")?;
                let (u, vv) = (ins[0], ins[1]);
                let (pu, pv, pw) = (v[u], v[vv], v[w]);
                let from_u = self.diagonal_from_first(pu, pv, pw);
                Some(if from_u {
                    (of_lattice[u], of_cut[vv][w])
                } else {
                    (of_lattice[vv], of_cut[u][w])
                })
            } else {
                None
            };
            faces.push(PFace {
                v: poly,
                len: len as u8,
                diag,
            });
        }
        // The cut face: on-surface vertices and cut points, oriented toward the outside vertices.
        let mut cut_face = [0u8; 4];
        let mut clen = 0usize;
        let ins: Vec<usize> = (0..4).filter(|&i| s[i] < 0).collect();
        let outs: Vec<usize> = (0..4).filter(|&i| s[i] > 0).collect();
        for i in 0..4 {
            if s[i] == 0 && clen < 4 {
                cut_face[clen] = of_lattice[i];
                clen += 1;
            }
        }
        if ins.len() == 2 && outs.len() == 2 {
            let (a, b, c, d) = (ins[0], ins[1], outs[0], outs[1]);
            cut_face = [of_cut[a][c], of_cut[a][d], of_cut[b][d], of_cut[b][c]];
            clen = 4;
        } else {
            for &i in &ins {
                for &o in &outs {
                    if clen < 4 {
                        cut_face[clen] = of_cut[i][o];
                        clen += 1;
                    }
                }
            }
        }
        if clen >= 3 {
            let q = |k: usize| pos[cut_face[k] as usize];
            let normal = if clen == 4 {
                cross(sub(q(2), q(0)), sub(q(3), q(1)))
            } else {
                cross(sub(q(1), q(0)), sub(q(2), q(0)))
            };
            let mut outside = [0.0; 3];
            for &o in &outs {
                outside = add(outside, self.lat.position(v[o]));
            }
            outside = scale(outside, 1.0 / outs.len() as f64);
            if dot(normal, sub(outside, q(0))) < 0.0 {
                cut_face[..clen].reverse();
            }
            faces.push(PFace {
                v: cut_face,
                len: clen as u8,
                diag: None,
            });
        }
        // Pulling triangulations from each admissible vertex; keep the best.
        let free_quad = clen == 4;
        let mut best: Option<(f64, Vec<[u32; 4]>)> = None;
        let mut tets: Vec<[u32; 4]> = Vec::with_capacity(4);
        for apex in 0..count as u8 {
            let contains = |f: &PFace, x: u8| f.v[..f.len as usize].contains(&x);
            let admissible = faces.iter().all(|f| match f.diag {
                Some((x, y)) if contains(f, apex) => x == apex || y == apex,
                _ => true,
            });
            if !admissible {
                continue;
            }
            let options = if free_quad && !contains(&faces[faces.len() - 1], apex) {
                2
            } else {
                1
            };
            for option in 0..options {
                tets.clear();
                let mut min_angle = f64::INFINITY;
                let mut valid = true;
                for (fi, f) in faces.iter().enumerate() {
                    if contains(f, apex) {
                        continue;
                    }
                    let fv = &f.v[..f.len as usize];
                    let mut tris: [[u8; 3]; 2] = [[0; 3]; 2];
                    let ntri = if f.len == 3 {
                        tris[0] = [fv[0], fv[1], fv[2]];
                        1
                    } else {
                        // Split along the diagonal through slot `k` and `k + 2`.
                        let k = match f.diag {
                            Some((x, _)) => fv.iter().position(|&y| y == x).unwrap_or(0) % 2,
                            None => {
                                if fi == faces.len() - 1 {
                                    option
                                } else {
                                    0
                                }
                            }
                        };
                        tris[0] = [fv[k], fv[k + 1], fv[(k + 2) % 4]];
                        tris[1] = [fv[k], fv[(k + 2) % 4], fv[(k + 3) % 4]];
                        2
                    };
                    for tri in &tris[..ntri] {
                        let p = [
                            pos[tri[0] as usize],
                            pos[tri[2] as usize],
                            pos[tri[1] as usize],
                            pos[apex as usize],
                        ];
                        let vol = tet_signed_volume(&p);
                        let lmax = super::tet_mesh::longest_edge(&p);
                        if vol <= 1e-9 * lmax * lmax * lmax {
                            valid = false;
                            break;
                        }
                        let angles = quality::dihedral_angles_deg(&p);
                        min_angle = angles.iter().copied().fold(min_angle, f64::min);
                        tets.push([
                            ids[tri[0] as usize],
                            ids[tri[2] as usize],
                            ids[tri[1] as usize],
                            ids[apex as usize],
                        ]);
                    }
                    if !valid {
                        break;
                    }
                }
                if valid && best.as_ref().is_none_or(|(b, _)| min_angle > *b) {
                    best = Some((min_angle, tets.clone()));
                }
            }
        }
        match best {
            Some((_, t)) => {
                out.extend_from_slice(&t);
                Ok(())
            }
            None => Err(format!(
                "no valid triangulation of BCC tetrahedron {v:?} with signs {s:?}"
            )),
        }
    }

    /// For a lattice face with inside vertices `u`, `v` and outside vertex `w`: true when the
    /// quadrilateral's diagonal runs from `u` to the cut point on `vw` (else from `v` to the cut
    /// point on `uw`). Short `uv`: the diagonal ends at the cut point on the long edge. Long `uv`:
    /// the parity rule.
    fn diagonal_from_first(&self, u: u32, v: u32, w: u32) -> bool {
        let (cu, cv, cw) = (
            self.lat.is_centre(u),
            self.lat.is_centre(v),
            self.lat.is_centre(w),
        );
        if cu != cv {
            // Short uv: the long edge is vw (v, w of one kind) or uw.
            return cv == cw;
        }
        let (du, dv, dw) = (
            self.lat.doubled(u),
            self.lat.doubled(v),
            self.lat.doubled(w),
        );
        let mut negative = 0;
        for k in 0..3 {
            let step = if dv[k] != du[k] {
                dv[k] - du[k]
            } else {
                dw[k] - dv[k]
            };
            if step < 0 {
                negative += 1;
            }
        }
        // Corners: the diagonal with an odd count; centres: even.
        let odd = negative % 2 == 1;
        cu != odd
    }
}
