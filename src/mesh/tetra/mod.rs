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

mod pinch;
mod stencil;

use pinch::*;
use stencil::*;

use super::spatial::SignedDistance;
use super::vec3::{add, scale, sub};
use super::{TetMesh, TriSurface};
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
    /// No triangulation of a BCC tetrahedron's inside part passed the stencil's validity checks
    /// (a bug: the stencils cover every sign pattern).
    #[error(
        "internal error in the tetrahedral mesher (please report with the surface): no valid triangulation of BCC tetrahedron {lattice_tet:?} with signs {signs:?}"
    )]
    NoValidStencil {
        /// The lattice tetrahedron's points.
        lattice_tet: [u32; 4],
        /// Their signs (−1 inside, 0 on, +1 outside).
        signs: [i8; 4],
    },
    /// The surface could not be prepared for the signed distance.
    #[error("the surface cannot be meshed: {0}")]
    Surface(#[from] crate::mesh::SurfaceError),
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

/// `mesh`'s boundary meshed again with tets of `edge_mm`: another mesh of the same organ (a
/// coarse one for a large case's quick basis or nonlinear response). The message names the step
/// that failed: the boundary, or the meshing.
pub fn remesh(mesh: &TetMesh, edge_mm: f64) -> Result<TetMesh, String> {
    let surface = mesh
        .boundary_surface()
        .map_err(|e| format!("the case's boundary: {e}"))?;
    tetrahedralize(&surface, &TetraParams::with_edge(edge_mm))
        .map_err(|e| format!("meshing the boundary with {edge_mm} mm tets: {e}"))
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
    let lat = lattice(surface, params)?;
    let h = lat.h;
    let sd = SignedDistance::new(surface)?;
    seconds.setup = start.elapsed().as_secs_f64();

    let t = Instant::now();
    let (f, hint, distance_queries) = distances(&lat, &sd);
    seconds.distance = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let cuts = cut_points(&lat, &sd, &f, &hint);
    seconds.cut_points = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let (warped, sign) = warp(&lat, &f, &hint, &cuts, params);
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
    let (global_tets, all_on_surface_tets) = stencils(&ctx)?;
    seconds.fill = t.elapsed().as_secs_f64();
    if global_tets.is_empty() {
        return Err(TetraError::NoTetrahedra { edge_mm: h });
    }

    let t = Instant::now();
    let mesh = compact(&ctx, global_tets)?;
    let (mesh, pinches, pieces, dropped_tets) = clean(mesh, params)?;
    seconds.finish = t.elapsed().as_secs_f64();
    seconds.total = start.elapsed().as_secs_f64();
    let report = TetraReport {
        edge_mm: h,
        lattice_cubes: lat.n,
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

/// Checks the parameters and the surface (closed, consistently oriented, not smaller than two
/// edges across) and lays the body-centred cubic lattice over it: the box plus at least one
/// cube of margin on each side, centred on the box.
fn lattice(surface: &TriSurface, params: &TetraParams) -> Result<Lattice, TetraError> {
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
    Ok(Lattice {
        h,
        lo,
        n,
        num_corners,
        num_points: num_corners + n[0] * n[1] * n[2],
    })
}

/// The distance beyond which a lattice point only gets the sign of its signed distance.
fn skip_distance(h: f64) -> f64 {
    h * (1.0 + 1e-6)
}

/// 1. Signed distance at the lattice points, row by row (x fastest); a point whose distance
///    bound from the last exact value along its row exceeds H only gets the sign. Returns the
///    values, each exact point's nearest triangle (`u32::MAX` where only bounded) and the
///    number of exact queries.
fn distances(lat: &Lattice, sd: &SignedDistance) -> (Vec<f64>, Vec<u32>, usize) {
    let (h, n, num_corners) = (lat.h, lat.n, lat.num_corners);
    let mut f = vec![0.0f64; lat.num_points];
    let mut hint = vec![u32::MAX; lat.num_points];
    let skip = skip_distance(h);
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
    let mut queries: usize = fc
        .par_chunks_mut(rx_c)
        .zip(hc.par_chunks_mut(rx_c))
        .enumerate()
        .map(|(r, (fr, hr))| eval_row(r * rx_c, fr, hr))
        .sum();
    queries += fm
        .par_chunks_mut(n[0])
        .zip(hm.par_chunks_mut(n[0]))
        .enumerate()
        .map(|(r, (fr, hr))| eval_row(num_corners + r * n[0], fr, hr))
        .sum::<usize>();
    (f, hint, queries)
}

/// Whether lattice point `p` got an exact distance of at most H.
fn near(f: &[f64], hint: &[u32], p: u32, skip: f64) -> bool {
    hint[p as usize] != u32::MAX && f[p as usize].abs() <= skip
}

/// 2. Cut points on lattice edges with strictly opposite signs (both ends are exact: |f| ≤ H),
///    sorted by edge.
fn cut_points(lat: &Lattice, sd: &SignedDistance, f: &[f64], hint: &[u32]) -> Vec<Cut> {
    let skip = skip_distance(lat.h);
    let mut edges: Vec<(u32, u32)> = (0..lat.num_points as u32)
        .into_par_iter()
        .with_min_len(4096)
        .flat_map_iter(|p| {
            let sp = sign_of(f[p as usize]);
            let candidates: Vec<(u32, u32)> = if sp != 0 && near(f, hint, p, skip) {
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
    let tol = 1e-7 * lat.h;
    edges
        .par_iter()
        .with_min_len(64)
        .map(|&(a, b)| {
            let (pa, pb) = (lat.position(a), lat.position(b));
            let (fa, fb) = (f[a as usize], f[b as usize]);
            let seed = [hint[a as usize], hint[b as usize]]
                .into_iter()
                .find(|&s| s != u32::MAX);
            let t = find_zero(sd, pa, fa, pb, fb, seed, tol);
            Cut {
                key: edge_key(a, b),
                t,
                pos: add(pa, scale(sub(pb, pa), t)),
            }
        })
        .collect()
}

/// 3. Warping: a vertex violated by a cut point on one of its edges moves to the closest one.
///    Returns the warped vertices with their positions, and every lattice point's sign (0 where
///    warped).
#[allow(clippy::type_complexity)]
fn warp(
    lat: &Lattice,
    f: &[f64],
    hint: &[u32],
    cuts: &[Cut],
    params: &TetraParams,
) -> (Vec<(u32, [f64; 3])>, Vec<i8>) {
    let h = lat.h;
    let skip = skip_distance(h);
    let (al, as_) = (params.alpha_long, params.alpha_short);
    let find_cut = |a: u32, b: u32| -> Option<usize> {
        cuts.binary_search_by_key(&edge_key(a, b), |c| c.key).ok()
    };
    let short_len = 0.5 * 3f64.sqrt() * h;
    let warped: Vec<(u32, [f64; 3])> = (0..lat.num_points as u32)
        .into_par_iter()
        .with_min_len(4096)
        .filter_map(|p| {
            let sp = sign_of(f[p as usize]);
            if sp == 0 || !near(f, hint, p, skip) {
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
    (warped, sign)
}

/// The stencil tetrahedra of every cube centre (global node ids), and how many lie wholly on
/// the surface.
fn stencils(ctx: &Fill<'_>) -> Result<(Vec<[u32; 4]>, usize), TetraError> {
    let num_corners = ctx.lat.num_corners;
    let num_centres = ctx.lat.num_points - num_corners;
    let pieces: Vec<(Vec<[u32; 4]>, usize, Option<TetraError>)> = (0..num_centres)
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
            return Err(e);
        }
        all_on_surface_tets += all_on;
        global_tets.extend_from_slice(&out);
    }
    Ok((global_tets, all_on_surface_tets))
}

/// 5. Compact: nodes are the used lattice points (warped where warped) then the used cut points.
fn compact(ctx: &Fill<'_>, global_tets: Vec<[u32; 4]>) -> Result<TetMesh, TetraError> {
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
    TetMesh::new(nodes, tets).map_err(|e| TetraError::Internal(e.to_string()))
}

/// The pinches repaired (when asked), the largest face-connected piece kept (when asked), every
/// tetrahedron checked positive and the mesh validated. Returns the mesh, the repair, the
/// number of pieces and the tetrahedra dropped with the smaller pieces.
fn clean(
    mut mesh: TetMesh,
    params: &TetraParams,
) -> Result<(TetMesh, PinchRepair, usize, usize), TetraError> {
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
    Ok((mesh, pinches, pieces, dropped_tets))
}
