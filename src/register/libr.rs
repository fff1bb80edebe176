//! LIBR: linearized iterative boundary reconstruction (after Heiselman & Miga, IEEE TMI 2020).
//!
//! This module owns the LIBR deformation basis and the regularized least-squares fit of its
//! weights plus a rigid correction to matched sparse data.
//!
//! **Basis.** `K` control points are spread evenly over the boundary by farthest-point sampling
//! (Euclidean, deterministic from [`LibrParams::seed`]). For each control point `c` and axis `a`
//! the load is a smooth, localized surface traction `t(x) = e_a · exp(−|x − c|²/2σ²) ·
//! max(0, n(x)·n_c)` (σ = [`LibrParams::load_width`]; the normal factor keeps a patch from leaking
//! through thin parts of the organ to the opposite face), lumped to nodes by
//! [`loads::add_traction`]. Column `j` of the basis `Φ` (3n × 3K, node-major rows) is the
//! linear-elastic response to load `j`, all columns from one sparse Cholesky factorization.
//!
//! **Supports (the free-floating body).** The liver in the abdomen is not clamped anywhere we
//! know of, and any rigid motion is a separate unknown of the fit, so the basis must hold pure
//! deformations. We therefore fix nothing physically and use *inertia relief*, the standard
//! treatment of unsupported bodies in structural FEA: each load `f` is replaced by its
//! self-equilibrated part `f_eq = f − M R (RᵀMR)⁻¹ Rᵀ f` (M the lumped nodal volumes, R the six
//! rigid modes), i.e. the unbalanced force and moment are carried by a uniform rigid-body
//! acceleration of the whole volume. `K u = f_eq` is then consistent but singular; it is solved
//! with a statically determinate 3-2-1 support (6 dofs on three far-apart boundary nodes), whose
//! reactions are zero for a self-equilibrated load, so `K u = f_eq` holds at *every* dof, and the
//! rigid part is projected out (`u ⟂_M R`). Unlike weak springs on the boundary this has no
//! stiffness to tune and biases nothing: the columns are exact free-body responses and the rigid
//! motion is left entirely to the fit's rigid unknowns.
//!
//! **Scaling.** Each column is scaled so that its largest node displacement is 1 mm
//! ([`LibrBasis::load_scale`] keeps the traction peak in kPa that gives it), so the weights α
//! are in mm. `E = ΦᵀKΦ` (mN·mm per mm², strain energy `½ αᵀEα` in µJ) is stored with it.
//!
//! **Fit.** [`fit_step`] minimises, over α (3K) and a small rigid correction (rotation ω about
//! the matched anchors' centroid `c̄`, translation τ, linearized),
//! `Σ wᵢ |pᵢ(α) + ω × (aᵢ − c̄) + τ − yᵢ|² / Σ wᵢ + λ αᵀẼα`, with `pᵢ(α) = Match::model_point(Φα)`,
//! `aᵢ` the anchor and `Ẽ = E / ē` where `ē` is the mean diagonal of `E` (the energy of one
//! 1 mm basis mode). The misfit is a weighted mean square in mm² and `αᵀẼα` ≈ `Σ αⱼ²` in mm², so
//! λ ([`LibrParams::regularization`]) is dimensionless and independent of mesh size, number of
//! matches and Young's modulus: λ = 1 makes one 1 mm mode cost as much as 1 mm RMS misfit.
//! [`register`] iterates the step, re-matching through a caller-supplied function, composing the
//! rigid correction exactly (rotation by `exp(ω)`), until the largest node movement of an
//! iteration falls below [`LibrParams::tolerance_mm`].
//!
//! **Cache.** [`LibrBasis::load_or_build`] keeps the basis in `cache_dir` as a NumPy `.npz`
//! named by the mesh hash and the hash of the basis-relevant parameters; an unreadable,
//! truncated or mismatched file is rebuilt and overwritten, never used.
//!
//! Units: mm, kPa, mN, µJ. Frames: the model and `u` in the image frame; see [`crate::register`].

use super::Match;
use crate::dataset::fnv1a_hex;
use crate::fem::{Dirichlet, LinearMaterial, StiffnessSystem, loads};
use crate::mesh::TetMesh;
use crate::mesh::io::npz::{NpyArray, NpyData, read_npz, write_npz};
use crate::mesh::rigid::Rigid;
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{BlockStructure, matmul as tri_matmul};
use faer::linalg::solvers::Solve;
use faer::{Accum, Mat, Par, Side};
use nalgebra::{Matrix6, Vector6};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Version of the basis and its cache format; part of the parameter hash.
pub const BASIS_VERSION: u32 = 1;

/// Width σ of each control point's Gaussian traction patch.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum LoadWidth {
    /// σ in mm.
    Mm(f64),
    /// σ as a multiple of the expected control-point spacing `√(2A / (√3 K))` (A the boundary
    /// area: the spacing of K points in a hexagonal packing).
    Spacing(f64),
}

/// Parameters of the LIBR basis and fit.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LibrParams {
    /// Number of control points K (the basis has 3K columns). Default 25: on the training split of
    /// the paper preset (`librplus evaluate --split train`), 25 gave 6.9 mm mean TRE, 40 7.4,
    /// 60 7.7 and 120 8.5 (BENCHMARKS.md); fewer, broader modes are better determined by sparse
    /// data and converge in fewer iterations.
    pub control_points: usize,
    /// Width of each control point's traction patch. Default 1.25 × spacing.
    pub load_width: LoadWidth,
    /// Linear-elastic material of the model. Default E = 5 kPa, ν = 0.45.
    pub material: LinearMaterial,
    /// Strain-energy regularization λ (dimensionless, see the module doc). Default 1e-3 (swept
    /// 1e-4 … 1e-1 on the training split).
    pub regularization: f64,
    /// Weight of the misfit along a matched surface (tangentially) relative to across it (1 = plain
    /// point-to-point; 0 = pure point-to-plane, one row per match). Matches without a normal
    /// (vessels) count fully in every direction. Default 0: closest-point pairs say nothing about
    /// where along the surface a point belongs, and pinning them there holds the surface back
    /// from sliding into place (mean TRE on every 28th block of the paper preset: 0.2 → 6.88 mm,
    /// 0.05 → 6.16, 0.001 → 5.78, 0.0001 → 5.77).
    pub tangential_weight: f64,
    /// Floor (mm) of the correspondence trimming during LIBR: a pair is dropped beyond
    /// `trim_factor × median + trim_floor_mm` (the rigid stage keeps its own, tighter floor).
    /// Default 30: deformation moves parts of the organ by tens of millimetres (a retracted lobe),
    /// and trimming those pairs as outliers keeps the fit from ever reaching them (same blocks:
    /// 5 mm → 5.78 mm, 15 → 5.66, 30 → 5.57, no trimming → 5.55), while gross outliers are still
    /// dropped.
    pub trim_floor_mm: f64,
    /// Most iterations of [`register`]. Default 20.
    pub max_iterations: usize,
    /// [`register`] stops when no node moved more than this in an iteration (mm). Default 0.01.
    pub tolerance_mm: f64,
    /// Chooses the first control point of the farthest-point sampling. Default 0.
    pub seed: u64,
}

impl Default for LibrParams {
    fn default() -> Self {
        Self {
            control_points: 25,
            load_width: LoadWidth::Spacing(1.25),
            material: LinearMaterial::default(),
            regularization: 1e-3,
            tangential_weight: 0.0,
            trim_floor_mm: 30.0,
            max_iterations: 20,
            tolerance_mm: 0.01,
            seed: 0,
        }
    }
}

impl LibrParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        if self.control_points == 0 {
            return Err("control_points must be at least 1".into());
        }
        match self.load_width {
            LoadWidth::Mm(w) | LoadWidth::Spacing(w) if !(w.is_finite() && w > 0.0) => {
                return Err(format!("load_width must be finite and > 0, got {w}"));
            }
            _ => {}
        }
        self.material
            .validate()
            .map_err(|e| format!("material: {e}"))?;
        if !(self.tangential_weight.is_finite()
            && self.tangential_weight >= 0.0
            && self.tangential_weight <= 1.0)
        {
            return Err(format!(
                "tangential_weight must be in [0, 1], got {}",
                self.tangential_weight
            ));
        }
        if !(self.regularization.is_finite() && self.regularization >= 0.0) {
            return Err(format!(
                "regularization must be finite and >= 0, got {}",
                self.regularization
            ));
        }
        if !(self.trim_floor_mm.is_finite() && self.trim_floor_mm >= 0.0) {
            return Err(format!(
                "trim_floor_mm must be finite and >= 0, got {}",
                self.trim_floor_mm
            ));
        }
        if !(self.tolerance_mm.is_finite() && self.tolerance_mm >= 0.0) {
            return Err(format!(
                "tolerance_mm must be finite and >= 0, got {}",
                self.tolerance_mm
            ));
        }
        Ok(())
    }

    /// Hash (16 hex digits) of what determines the basis: version, control points, load width,
    /// material, seed (not the fit's regularization, iterations or tolerance).
    pub fn basis_hash(&self) -> String {
        let key = serde_json::json!({
            "version": BASIS_VERSION,
            "control_points": self.control_points,
            "load_width": self.load_width,
            "material": self.material,
            "seed": self.seed,
        });
        fnv1a_hex(key.to_string().as_bytes())
    }
}

/// Hash (16 hex digits) of a mesh's node coordinates (exact bits) and tets.
pub fn mesh_hash(mesh: &TetMesh) -> String {
    let mut bytes = Vec::with_capacity(24 * mesh.num_nodes() + 16 * mesh.num_tets() + 16);
    bytes.extend_from_slice(&(mesh.num_nodes() as u64).to_le_bytes());
    for p in mesh.nodes() {
        for c in p {
            bytes.extend_from_slice(&c.to_bits().to_le_bytes());
        }
    }
    bytes.extend_from_slice(&(mesh.num_tets() as u64).to_le_bytes());
    for t in mesh.tets() {
        for v in t {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    fnv1a_hex(&bytes)
}

/// Stage timings of a basis build or load (seconds).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct BasisTimings {
    /// Control-point sampling and load assembly.
    pub loads_s: f64,
    /// Stiffness assembly.
    pub assemble_s: f64,
    /// Sparse Cholesky factorization.
    pub factor_s: f64,
    /// All 3K solves.
    pub solve_s: f64,
    /// Rigid-mode projection, scaling and the energy matrix.
    pub energy_s: f64,
    /// Reading the cache file (zero when built).
    pub cache_read_s: f64,
    /// Total.
    pub total_s: f64,
}

/// The LIBR basis of one mesh: control points, displacement responses and their energy matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct LibrBasis {
    /// Control points (boundary node indices), in sampling order.
    pub control_nodes: Vec<u32>,
    /// Mesh nodes n.
    pub nodes: usize,
    /// Φ, row-major 3n × 3K: row `3·node + axis`, column `3·k + axis'` (control point k, load
    /// axis axis'); unit: mm per unit weight.
    pub phi: Vec<f64>,
    /// E = ΦᵀKΦ, row-major 3K × 3K (mN·mm per mm²).
    pub energy: Vec<f64>,
    /// Per column: peak traction (kPa) of the load whose response is the column.
    pub load_scale: Vec<f64>,
    /// Resolved Gaussian width σ of the traction patches (mm).
    pub load_width_mm: f64,
    /// [`mesh_hash`] of the mesh the basis belongs to.
    pub mesh_hash: String,
    /// [`LibrParams::basis_hash`] of the parameters it was built with.
    pub params_hash: String,
    /// How long building (or loading) took.
    pub timings: BasisTimings,
}

/// Farthest-point sampling of `count` boundary nodes (Euclidean). The first is chosen by `seed`;
/// ties go to the lowest node index. Returns fewer when the boundary has fewer nodes.
pub fn farthest_point_sampling(
    nodes: &[[f64; 3]],
    candidates: &[u32],
    count: usize,
    seed: u64,
) -> Vec<u32> {
    if candidates.is_empty() || count == 0 {
        return Vec::new();
    }
    let mut rng = crate::util::SplitMix64::new(seed);
    let first = rng.below(candidates.len());
    let mut chosen = vec![candidates[first]];
    let mut dist: Vec<f64> = candidates
        .iter()
        .map(|&v| dist2(nodes[v as usize], nodes[candidates[first] as usize]))
        .collect();
    while chosen.len() < count.min(candidates.len()) {
        let mut best = 0usize;
        for (i, &d) in dist.iter().enumerate() {
            if d > dist[best] {
                best = i;
            }
        }
        if dist[best] <= 0.0 {
            break;
        }
        let c = nodes[candidates[best] as usize];
        chosen.push(candidates[best]);
        for (i, &v) in candidates.iter().enumerate() {
            dist[i] = dist[i].min(dist2(nodes[v as usize], c));
        }
    }
    chosen
}

/// The raw (not equilibrated) traction load of a control point: on each boundary triangle the
/// traction `e_axis · exp(−|x_t − c|²/2σ²) · max(0, n_t·n_c)` (kPa, peak 1) with `x_t` the
/// triangle's centroid and `n_t` its unit outward normal, lumped by [`loads::add_traction`].
pub fn control_traction(
    nodes: &[[f64; 3]],
    triangles: &[[u32; 3]],
    center: [f64; 3],
    normal: [f64; 3],
    axis: usize,
    width_mm: f64,
) -> Vec<f64> {
    let mut tr = Vec::with_capacity(triangles.len());
    for t in triangles {
        let [a, b, c] = t.map(|v| nodes[v as usize]);
        let x = [0, 1, 2].map(|k| (a[k] + b[k] + c[k]) / 3.0);
        let n = unit(cross(sub(b, a), sub(c, a)));
        let g = (-dist2(x, center) / (2.0 * width_mm * width_mm)).exp() * dot(n, normal).max(0.0);
        let mut v = [0.0; 3];
        v[axis] = g;
        tr.push(v);
    }
    let mut f = vec![0.0; 3 * nodes.len()];
    loads::add_traction(&mut f, nodes, triangles, &tr);
    f
}

/// Lumped nodal volumes (mm³): each node gets a quarter of each of its tets' volume.
pub fn lumped_volumes(mesh: &TetMesh) -> Vec<f64> {
    let mut m = vec![0.0; mesh.num_nodes()];
    for (t, tet) in mesh.tets().iter().enumerate() {
        let v = mesh.tet_volume(t).abs() / 4.0;
        for &i in tet {
            m[i as usize] += v;
        }
    }
    m
}

/// The six rigid modes of a node set (3 translations, 3 rotations about `center`) and their
/// mass matrix `RᵀMR`, for projections.
struct RigidModes {
    center: [f64; 3],
    mass: Vec<f64>,
    ginv: Matrix6<f64>,
}

impl RigidModes {
    fn new(nodes: &[[f64; 3]], mass: &[f64]) -> Result<Self, String> {
        let total: f64 = mass.iter().sum();
        let mut center = [0.0; 3];
        for (p, &w) in nodes.iter().zip(mass) {
            for a in 0..3 {
                center[a] += w * p[a] / total;
            }
        }
        let mut g = Matrix6::<f64>::zeros();
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, center);
            for a in 0..3 {
                for k in 0..6 {
                    for l in 0..6 {
                        g[(k, l)] += mass[i] * r[a][k] * r[a][l];
                    }
                }
            }
        }
        let ginv = g
            .try_inverse()
            .ok_or("the mesh's rigid-mode mass matrix is singular (zero volume?)")?;
        Ok(Self {
            center,
            mass: mass.to_vec(),
            ginv,
        })
    }

    /// `Rᵀ v` (6) for a node-major vector, optionally weighted by the lumped mass.
    fn project(&self, nodes: &[[f64; 3]], v: &[f64], weighted: bool) -> Vector6<f64> {
        let mut s = Vector6::zeros();
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, self.center);
            let w = if weighted { self.mass[i] } else { 1.0 };
            for a in 0..3 {
                for k in 0..6 {
                    s[k] += w * r[a][k] * v[3 * i + a];
                }
            }
        }
        s
    }

    /// `f − M R G⁻¹ Rᵀ f`: the self-equilibrated part of a load (inertia relief).
    fn equilibrate(&self, nodes: &[[f64; 3]], f: &mut [f64]) {
        let c = self.ginv * self.project(nodes, f, false);
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, self.center);
            for a in 0..3 {
                let acc: f64 = (0..6).map(|k| r[a][k] * c[k]).sum();
                f[3 * i + a] -= self.mass[i] * acc;
            }
        }
    }

    /// `u − R G⁻¹ RᵀM u`: removes the (mass-weighted) rigid part of a displacement.
    fn remove_rigid(&self, nodes: &[[f64; 3]], u: &mut [f64]) {
        let c = self.ginv * self.project(nodes, u, true);
        for (i, p) in nodes.iter().enumerate() {
            let r = mode_rows(*p, self.center);
            for a in 0..3 {
                let acc: f64 = (0..6).map(|k| r[a][k] * c[k]).sum();
                u[3 * i + a] -= acc;
            }
        }
    }
}

/// Rows (per axis) of the rigid modes at point p: translations e_a, rotations e_k × (p − c).
fn mode_rows(p: [f64; 3], c: [f64; 3]) -> [[f64; 6]; 3] {
    let d = sub(p, c);
    // e_k × d: k=0 → (0, −d_z, d_y); k=1 → (d_z, 0, −d_x); k=2 → (−d_y, d_x, 0)
    [
        [1.0, 0.0, 0.0, 0.0, d[2], -d[1]],
        [0.0, 1.0, 0.0, -d[2], 0.0, d[0]],
        [0.0, 0.0, 1.0, d[1], -d[0], 0.0],
    ]
}

/// A statically determinate 3-2-1 support on boundary nodes: node a fixed, node b fixed across
/// the a→b direction's dominant axis, node c fixed along the axis that best stops rotation
/// about a–b.
fn support_321(
    nodes: &[[f64; 3]],
    boundary: &[u32],
    center: [f64; 3],
) -> Result<Dirichlet, String> {
    let far = |from: [f64; 3]| -> u32 {
        let mut best = boundary[0];
        for &v in boundary {
            if dist2(nodes[v as usize], from) > dist2(nodes[best as usize], from) {
                best = v;
            }
        }
        best
    };
    let a = far(center);
    let pa = nodes[a as usize];
    let b = far(pa);
    let d = sub(nodes[b as usize], pa);
    let dn = unit(d);
    let mut c = boundary[0];
    let mut best = -1.0;
    for &v in boundary {
        let e = sub(nodes[v as usize], pa);
        let off = cross(dn, e);
        let l = dot(off, off);
        if l > best {
            best = l;
            c = v;
        }
    }
    let moment = cross(dn, sub(nodes[c as usize], pa));
    if dot(d, d) <= 0.0 || best <= 1e-12 * dot(d, d) {
        return Err("the boundary is degenerate (all nodes on a line): cannot support it".into());
    }
    let free_b = argmax_abs(d);
    let fix_c = argmax_abs(moment);
    let mut bc = Dirichlet::new(nodes.len());
    bc.prescribe_node(a, [0.0; 3]);
    for axis in 0..3 {
        if axis != free_b {
            bc.prescribe_dof(b, axis, 0.0);
        }
    }
    bc.prescribe_dof(c, fix_c, 0.0);
    Ok(bc)
}

fn argmax_abs(v: [f64; 3]) -> usize {
    let mut k = 0;
    for a in 1..3 {
        if v[a].abs() > v[k].abs() {
            k = a;
        }
    }
    k
}

impl LibrBasis {
    /// Number of basis columns (3K).
    pub fn columns(&self) -> usize {
        self.load_scale.len()
    }

    /// Builds the basis: control points, loads, one factorization, 3K solves (parallel column
    /// blocks), rigid-mode removal, scaling, `E = ΦᵀKΦ`.
    pub fn build(mesh: &TetMesh, params: &LibrParams) -> Result<Self, String> {
        params.validate()?;
        let t0 = Instant::now();
        let nodes = mesh.nodes();
        let n = nodes.len();
        let boundary = mesh.boundary().map_err(|e| format!("mesh boundary: {e}"))?;
        if boundary.nodes.len() < 3 {
            return Err("mesh has fewer than 3 boundary nodes".into());
        }
        let control =
            farthest_point_sampling(nodes, &boundary.nodes, params.control_points, params.seed);
        if control.len() < params.control_points {
            return Err(format!(
                "control_points = {} but the boundary has only {} distinct nodes",
                params.control_points,
                control.len()
            ));
        }
        // Area-weighted vertex normals and the boundary area.
        let mut vnormal = vec![[0.0; 3]; n];
        let mut area = 0.0;
        for t in &boundary.triangles {
            let [a, b, c] = t.map(|v| nodes[v as usize]);
            let na = cross(sub(b, a), sub(c, a));
            area += 0.5 * dot(na, na).sqrt();
            for &v in t {
                for k in 0..3 {
                    vnormal[v as usize][k] += na[k];
                }
            }
        }
        let kk = control.len();
        let width = match params.load_width {
            LoadWidth::Mm(w) => w,
            LoadWidth::Spacing(s) => s * (2.0 * area / (3f64.sqrt() * kk as f64)).sqrt(),
        };
        let modes = RigidModes::new(nodes, &lumped_volumes(mesh))?;
        let m = 3 * kk;
        let mut fmat = Mat::<f64>::zeros(3 * n, m);
        for (k, &c) in control.iter().enumerate() {
            let nc = unit(vnormal[c as usize]);
            for axis in 0..3 {
                let mut f = control_traction(
                    nodes,
                    &boundary.triangles,
                    nodes[c as usize],
                    nc,
                    axis,
                    width,
                );
                modes.equilibrate(nodes, &mut f);
                for (r, &x) in f.iter().enumerate() {
                    fmat[(r, 3 * k + axis)] = x;
                }
            }
        }
        let loads_s = crate::util::secs(t0);
        let t1 = Instant::now();
        let system = StiffnessSystem::linear(mesh, &params.material).map_err(|e| e.to_string())?;
        let assemble_s = crate::util::secs(t1);
        let t2 = Instant::now();
        let bc = support_321(nodes, &boundary.nodes, modes.center)?;
        let fact = system.factorize(&bc).map_err(|e| e.to_string())?;
        let factor_s = crate::util::secs(t2);
        let t3 = Instant::now();
        let umat = fact.solve_many_homogeneous(fmat.as_ref());
        let solve_s = crate::util::secs(t3);
        let t4 = Instant::now();
        let mut phi = vec![0.0; 3 * n * m];
        let mut load_scale = vec![0.0; m];
        let mut col = vec![0.0; 3 * n];
        for j in 0..m {
            for (r, x) in col.iter_mut().enumerate() {
                *x = umat[(r, j)];
            }
            modes.remove_rigid(nodes, &mut col);
            let peak = (0..n)
                .map(|i| {
                    (col[3 * i].powi(2) + col[3 * i + 1].powi(2) + col[3 * i + 2].powi(2)).sqrt()
                })
                .fold(0.0f64, f64::max);
            if !(peak.is_finite() && peak > 0.0) {
                return Err(format!(
                    "basis column {j} (control node {}, axis {}) has peak displacement {peak}: the load patch is empty or the solve failed",
                    control[j / 3],
                    j % 3
                ));
            }
            load_scale[j] = 1.0 / peak;
            for (r, &x) in col.iter().enumerate() {
                phi[r * m + j] = x / peak;
            }
        }
        // E = Φᵀ (K Φ), symmetrized.
        let mut kphi = Mat::<f64>::zeros(3 * n, m);
        let mut phimat = Mat::<f64>::zeros(3 * n, m);
        for j in 0..m {
            for r in 0..3 * n {
                col[r] = phi[r * m + j];
                phimat[(r, j)] = col[r];
            }
            let kc = system.apply(&col);
            for (r, &x) in kc.iter().enumerate() {
                kphi[(r, j)] = x;
            }
        }
        let e = phimat.transpose() * &kphi;
        let mut energy = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..m {
                energy[i * m + j] = 0.5 * (e[(i, j)] + e[(j, i)]);
            }
        }
        let energy_s = crate::util::secs(t4);
        Ok(Self {
            control_nodes: control,
            nodes: n,
            phi,
            energy,
            load_scale,
            load_width_mm: width,
            mesh_hash: mesh_hash(mesh),
            params_hash: params.basis_hash(),
            timings: BasisTimings {
                loads_s,
                assemble_s,
                factor_s,
                solve_s,
                energy_s,
                cache_read_s: 0.0,
                total_s: crate::util::secs(t0),
            },
        })
    }

    /// The cache file of a mesh and parameters in `cache_dir`.
    pub fn cache_path(mesh: &TetMesh, params: &LibrParams, cache_dir: &Path) -> PathBuf {
        cache_dir.join(format!(
            "libr_basis_{}_{}.npz",
            mesh_hash(mesh),
            params.basis_hash()
        ))
    }

    /// Loads the basis from `cache_dir` if a valid file for this mesh and these parameters is
    /// there, otherwise builds it and writes the file (atomically: temporary file + rename).
    /// Returns the basis and whether it came from the cache. A corrupt, truncated or mismatched
    /// file is rebuilt and overwritten; failure to write the cache is an error.
    pub fn load_or_build(
        mesh: &TetMesh,
        params: &LibrParams,
        cache_dir: &Path,
    ) -> Result<(Self, bool), String> {
        params.validate()?;
        let path = Self::cache_path(mesh, params, cache_dir);
        let t0 = Instant::now();
        if let Ok(bytes) = std::fs::read(&path)
            && let Ok(mut b) = Self::from_npz(&bytes)
            && b.mesh_hash == mesh_hash(mesh)
            && b.params_hash == params.basis_hash()
            && b.nodes == mesh.num_nodes()
            && b.control_nodes.len() == params.control_points
        {
            b.timings = BasisTimings {
                cache_read_s: crate::util::secs(t0),
                total_s: crate::util::secs(t0),
                ..Default::default()
            };
            return Ok((b, true));
        }
        let b = Self::build(mesh, params)?;
        crate::util::write_atomic(&path, &b.to_npz()?)?;
        Ok((b, false))
    }

    /// The basis as `.npz` bytes: `phi` (3n, 3K) f8, `energy` (3K, 3K) f8, `control_nodes` (K)
    /// i8, `load_scale` (3K) f8, `load_width_mm` (1) f8, `version` (1) i8, `mesh_hash` and
    /// `params_hash` (16 ASCII bytes each, u1).
    pub fn to_npz(&self) -> Result<Vec<u8>, String> {
        let m = self.columns();
        let arrays = vec![
            NpyArray::new("phi", &[3 * self.nodes, m], NpyData::F64(self.phi.clone()))?,
            NpyArray::new("energy", &[m, m], NpyData::F64(self.energy.clone()))?,
            NpyArray::new(
                "control_nodes",
                &[self.control_nodes.len()],
                NpyData::I64(self.control_nodes.iter().map(|&v| v as i64).collect()),
            )?,
            NpyArray::new("load_scale", &[m], NpyData::F64(self.load_scale.clone()))?,
            NpyArray::new(
                "load_width_mm",
                &[1],
                NpyData::F64(vec![self.load_width_mm]),
            )?,
            NpyArray::new("version", &[1], NpyData::I64(vec![BASIS_VERSION as i64]))?,
            NpyArray::new(
                "mesh_hash",
                &[self.mesh_hash.len()],
                NpyData::U8(self.mesh_hash.as_bytes().to_vec()),
            )?,
            NpyArray::new(
                "params_hash",
                &[self.params_hash.len()],
                NpyData::U8(self.params_hash.as_bytes().to_vec()),
            )?,
        ];
        write_npz(&arrays)
    }

    /// Reads what [`LibrBasis::to_npz`] wrote; checks names, dtypes, shapes and finiteness.
    pub fn from_npz(bytes: &[u8]) -> Result<Self, String> {
        let arrays = read_npz(bytes)?;
        let get = |name: &str| {
            arrays
                .iter()
                .find(|a| a.name == name)
                .ok_or_else(|| format!("basis file has no array {name}"))
        };
        let f64s = |name: &str| -> Result<(Vec<usize>, Vec<f64>), String> {
            let a = get(name)?;
            match &a.data {
                NpyData::F64(v) => Ok((a.shape.clone(), v.clone())),
                _ => Err(format!("basis array {name} is not f8")),
            }
        };
        let text = |name: &str| -> Result<String, String> {
            match &get(name)?.data {
                NpyData::U8(v) => String::from_utf8(v.clone()).map_err(|e| format!("{name}: {e}")),
                _ => Err(format!("basis array {name} is not u1")),
            }
        };
        match &get("version")?.data {
            NpyData::I64(v) if v.as_slice() == [BASIS_VERSION as i64] => {}
            _ => return Err(format!("basis file version is not {BASIS_VERSION}")),
        }
        let (ps, phi) = f64s("phi")?;
        let (es, energy) = f64s("energy")?;
        let (ls, load_scale) = f64s("load_scale")?;
        let (_, width) = f64s("load_width_mm")?;
        let control_nodes: Vec<u32> = match &get("control_nodes")?.data {
            NpyData::I64(v) => v
                .iter()
                .map(|&x| u32::try_from(x).map_err(|_| format!("control node {x} out of range")))
                .collect::<Result<_, _>>()?,
            _ => return Err("basis array control_nodes is not i8".into()),
        };
        let m = 3 * control_nodes.len();
        if ps.len() != 2
            || ps[1] != m
            || ps[0] % 3 != 0
            || es != [m, m]
            || ls != [m]
            || width.len() != 1
        {
            return Err(format!(
                "basis arrays have inconsistent shapes (phi {ps:?}, energy {es:?}, load_scale {ls:?}, {} control nodes)",
                control_nodes.len()
            ));
        }
        let nodes = ps[0] / 3;
        if control_nodes.iter().any(|&c| c as usize >= nodes) {
            return Err("a control node is out of range".into());
        }
        if !phi
            .iter()
            .chain(&energy)
            .chain(&load_scale)
            .chain(&width)
            .all(|x| x.is_finite())
        {
            return Err("basis file holds non-finite values".into());
        }
        Ok(Self {
            control_nodes,
            nodes,
            phi,
            energy,
            load_scale,
            load_width_mm: width[0],
            mesh_hash: text("mesh_hash")?,
            params_hash: text("params_hash")?,
            timings: BasisTimings::default(),
        })
    }

    /// Node displacements `u = Φ α` (node-major 3n, mm). Panics if `alpha.len() != 3K`.
    pub fn displacement(&self, alpha: &[f64]) -> Vec<f64> {
        let m = self.columns();
        assert_eq!(
            alpha.len(),
            m,
            "displacement: alpha must have 3K = {m} entries"
        );
        // Rows in parallel, each a dot product with four accumulators (vectorizes; the same bits
        // whatever the thread count, since every row is summed in a fixed order).
        let dot = |row: &[f64]| dot_row(row, alpha);
        let mut out = vec![0.0; self.phi.len() / m.max(1)];
        out.par_chunks_mut(256)
            .zip(self.phi.par_chunks(256 * m))
            .for_each(|(o, rows)| {
                for (x, row) in o.iter_mut().zip(rows.chunks_exact(m)) {
                    *x = dot(row);
                }
            });
        out
    }

    /// Writes `u = Φ α` at the given nodes only into `out` (node-major 3n; other entries are left
    /// as they are). Panics if `alpha.len() != 3K`, `out.len() != 3n` or a node is out of range.
    pub fn displacement_at(&self, alpha: &[f64], nodes: &[u32], out: &mut [f64]) {
        let m = self.columns();
        assert_eq!(
            alpha.len(),
            m,
            "displacement_at: alpha must have 3K = {m} entries"
        );
        assert_eq!(
            out.len(),
            3 * self.nodes,
            "displacement_at: out must have 3n entries"
        );
        let rows: Vec<[f64; 3]> = nodes
            .par_chunks(256)
            .flat_map_iter(|chunk| {
                chunk.iter().map(|&v| {
                    [0, 1, 2].map(|a| {
                        let r = 3 * v as usize + a;
                        dot_row(&self.phi[r * m..(r + 1) * m], alpha)
                    })
                })
            })
            .collect();
        for (&v, r) in nodes.iter().zip(rows) {
            out[3 * v as usize..3 * v as usize + 3].copy_from_slice(&r);
        }
    }

    /// Strain energy `½ αᵀEα` (µJ). Panics if `alpha.len() != 3K`.
    pub fn strain_energy(&self, alpha: &[f64]) -> f64 {
        let m = self.columns();
        assert_eq!(
            alpha.len(),
            m,
            "strain_energy: alpha must have 3K = {m} entries"
        );
        let mut s = 0.0;
        for i in 0..m {
            for j in 0..m {
                s += alpha[i] * self.energy[i * m + j] * alpha[j];
            }
        }
        0.5 * s
    }

    /// Mean diagonal of E: the energy scale ē of one 1 mm mode (λ's normalisation).
    pub fn energy_scale(&self) -> f64 {
        let m = self.columns();
        (0..m).map(|i| self.energy[i * m + i]).sum::<f64>() / m as f64
    }
}

/// Stage timings of one [`fit_step`] (seconds).
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StepTimings {
    /// Gathering Φ rows at the matched nodes and the residuals.
    pub rows_s: f64,
    /// Forming the normal equations (JᵀWJ + λẼ).
    pub normal_s: f64,
    /// Cholesky solve and the residual after the step.
    pub solve_s: f64,
}

/// The result of one regularized least-squares step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepResult {
    /// Basis weights α (3K, mm).
    pub alpha: Vec<f64>,
    /// Rigid correction δ in the image frame: the corrected model point is `δ(model_point)`; the
    /// new image→physical transform is `δ.then(&old)`.
    pub rigid_correction: Rigid,
    /// Rotation angle of δ (degrees) and its translation at the anchors' centroid (mm).
    pub correction_deg: f64,
    /// Length of τ (mm).
    pub correction_mm: f64,
    /// Weighted RMS of `δ(pᵢ(α)) − yᵢ` after the step (exact rotation), mm.
    pub rms_mm: f64,
    /// Weighted RMS of the linearized model's residual at the solution (the misfit the step
    /// minimises; non-decreasing in λ), mm.
    pub linear_rms_mm: f64,
    /// Weighted RMS of `aᵢ − yᵢ` before the step (α = 0, no correction), mm.
    pub rms_before_mm: f64,
    /// Strain energy `½ αᵀEα` (µJ).
    pub strain_energy_uj: f64,
    /// Matches with positive weight that entered the fit.
    pub matches_used: usize,
    /// Stage timings.
    pub timings: StepTimings,
}

fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize3(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    if l > 0.0 { a.map(|x| x / l) } else { a }
}

/// The weighted least-squares system of one LIBR step ([`fit_step`]): rows, right-hand side,
/// and the regularised normal matrix (lower triangle), with what built them.
struct Assembled<'a> {
    used: Vec<&'a Match>,
    wsum: f64,
    cen: [f64; 3],
    radius: f64,
    m: usize,
    p: usize,
    rows: usize,
    /// Jᵀ, p × rows.
    jt: Mat<f64>,
    rhs: Mat<f64>,
    /// The frame vector (times √(w/W)) of each row, and its match.
    row_frames: Vec<([f64; 3], usize)>,
    before: f64,
    /// JᵀJ + damping + λ/e·E, lower triangle.
    a: Mat<f64>,
    /// Jᵀr.
    b: Mat<f64>,
    rows_s: f64,
    normal_s: f64,
}

/// Validates the matches and builds the step's system (see [`fit_step`] for the errors).
fn assemble<'a>(
    basis: &LibrBasis,
    matches: &'a [Match],
    targets_image: &[[f64; 3]],
    params: &LibrParams,
) -> Result<Assembled<'a>, String> {
    let t0 = Instant::now();
    let lambda = params.regularization;
    if !(lambda.is_finite() && lambda >= 0.0) {
        return Err(format!(
            "regularization must be finite and >= 0, got {lambda}"
        ));
    }
    if matches.is_empty() {
        return Err("no matches".into());
    }
    let n = basis.nodes;
    for (k, mt) in matches.iter().enumerate() {
        if mt.point >= targets_image.len() {
            return Err(format!(
                "match {k}: point {} out of range ({} targets)",
                mt.point,
                targets_image.len()
            ));
        }
        if let Some(&v) = mt.nodes.iter().find(|&&v| v as usize >= n) {
            return Err(format!("match {k}: node {v} out of range ({n} nodes)"));
        }
        if !(mt.weight.is_finite() && mt.weight >= 0.0) {
            return Err(format!(
                "match {k}: weight {} is not finite and >= 0",
                mt.weight
            ));
        }
        if !mt.bary.iter().chain(&mt.anchor).all(|x| x.is_finite()) {
            return Err(format!(
                "match {k}: non-finite anchor or barycentric weight"
            ));
        }
        if mt.weight > 0.0 && !targets_image[mt.point].iter().all(|x| x.is_finite()) {
            return Err(format!(
                "match {k}: target {} is not finite: {:?}",
                mt.point, targets_image[mt.point]
            ));
        }
    }
    let used: Vec<&Match> = matches.iter().filter(|m| m.weight > 0.0).collect();
    if used.len() < 3 {
        return Err(format!(
            "{} matches with positive weight; at least 3 are needed to fix the rigid correction",
            used.len()
        ));
    }
    let wsum: f64 = used.iter().map(|m| m.weight).sum();
    if !(wsum.is_finite() && wsum > 0.0) {
        return Err(format!("total match weight is {wsum}"));
    }
    let m = basis.columns();
    let p = m + 6;
    // Centroid and radius of the anchors: rotation centre and scale of the ω unknowns.
    let mut cen = [0.0; 3];
    for mt in &used {
        for a in 0..3 {
            cen[a] += mt.weight * mt.anchor[a] / wsum;
        }
    }
    let radius = (used
        .iter()
        .map(|mt| mt.weight * dist2(mt.anchor, cen))
        .sum::<f64>()
        / wsum)
        .sqrt()
        .max(1.0);
    // Weighted rows: J (R × p) and r = y − a (R), scaled by √(w/W): one row per match on a
    // surface when the tangential weight is 0 (pure point-to-plane), three otherwise.
    let tw = params.tangential_weight.sqrt();
    let rows_of = |mt: &Match| -> usize {
        if tw == 0.0 && dot(mt.normal, mt.normal) > 0.0 {
            1
        } else {
            3
        }
    };
    let rows: usize = used.iter().map(|mt| rows_of(mt)).sum();
    // Stored transposed (p × 3N, column-major) so each row of J is contiguous.
    let mut jt = Mat::<f64>::zeros(p, rows);
    let mut rhs = Mat::<f64>::zeros(rows, 1);
    let mut before = 0.0;
    let mut axis_rows = vec![0.0; 3 * p];
    let mut row = 0usize;
    let mut row_frames = Vec::with_capacity(rows);
    for (ui, mt) in used.iter().enumerate() {
        let s = (mt.weight / wsum).sqrt();
        let y = targets_image[mt.point];
        axis_rows.iter_mut().for_each(|x| *x = 0.0);
        let mut r = [0.0; 3];
        for a in 0..3 {
            let dst = &mut axis_rows[a * p..(a + 1) * p];
            for (k, &v) in mt.nodes.iter().enumerate() {
                let b = mt.bary[k];
                if b == 0.0 {
                    continue;
                }
                let src = &basis.phi[(3 * v as usize + a) * m..(3 * v as usize + a + 1) * m];
                for (j, &x) in src.iter().enumerate() {
                    dst[j] += s * b * x;
                }
            }
            // ω × d = −[d]× ω; unknowns ω' = ω·radius.
            let rot = mode_rows(mt.anchor, cen)[a];
            for k in 0..3 {
                dst[m + k] = s * rot[3 + k] / radius;
                dst[m + 3 + k] = if k == a { s } else { 0.0 };
            }
            r[a] = s * (y[a] - mt.anchor[a]);
        }
        // Point-to-plane: rotate the three axis rows into (n, t1, t2), the tangential ones
        // down-weighted; without a normal, the axis rows as they are (point-to-point).
        let len = dot(mt.normal, mt.normal).sqrt();
        let frame: [[f64; 3]; 3] = if len > 0.0 {
            let nn = mt.normal.map(|x| x / len);
            let helper = if nn[0].abs() < 0.9 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            let t1 = normalize3(cross3(nn, helper));
            let t2 = cross3(nn, t1);
            [nn, t1.map(|x| tw * x), t2.map(|x| tw * x)]
        } else {
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        };
        for f in frame.iter().take(rows_of(mt)) {
            let dst = jt
                .col_mut(row)
                .try_as_col_major_mut()
                .expect("a column of a column-major matrix is contiguous")
                .as_slice_mut();
            for j in 0..p {
                dst[j] =
                    f[0] * axis_rows[j] + f[1] * axis_rows[p + j] + f[2] * axis_rows[2 * p + j];
            }
            let rr = f[0] * r[0] + f[1] * r[1] + f[2] * r[2];
            rhs[(row, 0)] = rr;
            before += rr * rr;
            row_frames.push((f.map(|x| s * x), ui));
            row += 1;
        }
    }
    debug_assert_eq!(row, rows);
    let rows_s = crate::util::secs(t0);
    let t1 = Instant::now();
    // Lower triangle of JᵀJ only (what the Cholesky factorization reads).
    let mut a = Mat::<f64>::zeros(p, p);
    tri_matmul(
        a.as_mut(),
        BlockStructure::TriangularLower,
        Accum::Replace,
        jt.as_ref(),
        BlockStructure::Rectangular,
        jt.transpose(),
        BlockStructure::Rectangular,
        1.0,
        // Sequential: the matrices are small (p ≈ 80 columns), and a parallel reduction would
        // make the bits depend on the thread count.
        Par::Seq,
    );
    let mut b = Mat::<f64>::zeros(p, 1);
    matmul(
        b.as_mut(),
        Accum::Replace,
        jt.as_ref(),
        rhs.as_ref(),
        1.0,
        Par::Seq,
    );
    let rhs0 = rhs;
    // A vanishing damping of the rigid unknowns keeps the system definite when the data leave
    // a rigid direction free (a flat patch under pure point-to-plane): there Jᵀr = 0, so the
    // step along it is zero instead of a failed factorization.
    let damp = 1e-12 * (m..p).map(|i| a[(i, i)]).fold(0.0f64, f64::max).max(1e-300);
    for i in m..p {
        a[(i, i)] += damp;
    }
    let escale = basis.energy_scale();
    if lambda > 0.0 {
        let f = lambda / escale;
        for i in 0..m {
            for j in 0..=i {
                a[(i, j)] += f * basis.energy[i * m + j];
            }
        }
    }
    let normal_s = crate::util::secs(t1);
    Ok(Assembled {
        used,
        wsum,
        cen,
        radius,
        m,
        p,
        rows,
        jt,
        rhs: rhs0,
        row_frames,
        before,
        a,
        b,
        rows_s,
        normal_s,
    })
}

/// One regularized weighted least-squares step (see the module doc). `targets_image[i]` is the
/// measured point `i` (the index in [`Match::point`]) mapped into the image frame by the current
/// rigid estimate. Unknowns: α (3K) and a linearized rigid correction about the anchors'
/// centroid; minimises `Σ wᵢ |δ(pᵢ(α)) − yᵢ|² / Σ wᵢ + λ αᵀẼα` to first order in δ.
///
/// Errors (naming the item): no matches, a match out of range or with non-finite or negative
/// weight, a non-finite target or anchor, fewer than 3 weighted matches, zero total weight,
/// an invalid λ, or data that do not determine the rigid correction.
pub fn fit_step(
    basis: &LibrBasis,
    matches: &[Match],
    targets_image: &[[f64; 3]],
    params: &LibrParams,
) -> Result<StepResult, String> {
    let Assembled {
        used,
        wsum,
        cen,
        radius,
        m,
        p,
        rows,
        jt,
        rhs: rhs0,
        before,
        a,
        mut b,
        rows_s,
        normal_s,
        ..
    } = assemble(basis, matches, targets_image, params)?;
    let t2 = Instant::now();
    let llt = a.llt(Side::Lower).map_err(|e| {
        format!(
            "the normal equations are singular ({e:?}): the {} matches do not determine the basis weights and rigid correction (use λ > 0, or more spread-out matches)",
            used.len()
        )
    })?;
    llt.solve_in_place(b.as_mut());
    if !(0..p).all(|i| b[(i, 0)].is_finite()) {
        return Err("the step produced non-finite values (ill-conditioned data)".into());
    }
    let mut lin = Mat::<f64>::zeros(rows, 1);
    matmul(
        lin.as_mut(),
        Accum::Replace,
        jt.transpose(),
        b.as_ref(),
        1.0,
        Par::Seq,
    );
    let lin = lin - &rhs0;
    let linear_rms_mm = (0..rows).map(|i| lin[(i, 0)].powi(2)).sum::<f64>().sqrt();
    let alpha: Vec<f64> = (0..m).map(|i| b[(i, 0)]).collect();
    let omega = [0, 1, 2].map(|k| b[(m + k, 0)] / radius);
    let tau = [0, 1, 2].map(|k| b[(m + 3 + k, 0)]);
    let angle = dot(omega, omega).sqrt();
    let rot = Rigid::from_axis_angle(omega, angle, [0.0; 3]);
    let rc = rot.apply_vector(cen);
    let rigid_correction = Rigid {
        rotation: rot.rotation,
        translation: [0, 1, 2].map(|k| cen[k] + tau[k] - rc[k]),
    };
    // Residual after the step with the exact rotation, over all weighted matches.
    let mut after = 0.0;
    for mt in &used {
        let mut q = mt.anchor;
        for (k, &v) in mt.nodes.iter().enumerate() {
            if mt.bary[k] == 0.0 {
                continue;
            }
            let base = 3 * v as usize;
            for ax in 0..3 {
                let row = &basis.phi[(base + ax) * m..(base + ax + 1) * m];
                q[ax] += mt.bary[k] * row.iter().zip(&alpha).map(|(x, y)| x * y).sum::<f64>();
            }
        }
        let r = sub(rigid_correction.apply(q), targets_image[mt.point]);
        after += mt.weight / wsum * dot(r, r);
    }
    let strain_energy_uj = basis.strain_energy(&alpha);
    Ok(StepResult {
        alpha,
        rigid_correction,
        correction_deg: angle.to_degrees(),
        correction_mm: dot(tau, tau).sqrt(),
        rms_mm: after.sqrt(),
        linear_rms_mm,
        rms_before_mm: before.sqrt(),
        strain_energy_uj,
        matches_used: used.len(),
        timings: StepTimings {
            rows_s,
            normal_s,
            solve_s: crate::util::secs(t2),
        },
    })
}

/// The first step of a LIBR refit ([`register_active`] with an offset), linearised in a change
/// `c` of the offset with the matches held: the refit's node displacement (image frame, the
/// rigid correction to first order about the undeformed nodes) is
/// `offset + c + step0 − G·K·Gᵀ·Dᵀ·D·c`, where `G` (3n × p) holds, per node, the basis rows, the
/// rotations `e_k × (X − centre)` and the translations ([`LinearRefit::modes`]), `K` is
/// the step's gain in those coordinates, and `D` maps a displacement to the step's weighted rows
/// (each row: √(w/W) times its direction, on the matched point's barycentric nodes). A network
/// trained through this map learns only what the refit will not put back ([`register_active`]
/// re-solves its weights from zero each iteration, so the map is the whole first iteration).
#[derive(Debug, Clone, PartialEq)]
pub struct LinearRefit {
    /// Columns p: the basis's, 3 rotations, 3 translations.
    pub columns: usize,
    /// `K = T N⁻¹ Tᵀ` (p × p, row-major, symmetric), with `N` the step's regularised normal
    /// matrix and `T` the change from the step's centred, radius-scaled rigid unknowns to `G`'s.
    pub gain: Vec<f64>,
    /// The step's node displacement with `c = 0` (3n, mm; near 0 when LIBR has converged with
    /// λ = 0).
    pub step0: Vec<f64>,
    /// Rows of `D`.
    pub rows: usize,
    /// `D`'s entries (row, 3·node + axis, value).
    pub d: Vec<(usize, usize, f64)>,
}

impl LinearRefit {
    /// Row `3i + a` of `G` (p values, row-major 3n × p): node i's basis row on axis a, then
    /// `(e_k × (X_i − centre))_a`, then `δ_{a,k}`. A centre within the organ keeps the rotation
    /// columns the size of the organ (no cancellation against the translations in f32).
    pub fn modes(basis: &LibrBasis, mesh: &TetMesh, centre: [f64; 3]) -> Vec<f64> {
        let m = basis.columns();
        let p = m + 6;
        let mut g = vec![0.0; 3 * basis.nodes * p];
        for (i, x) in mesh.nodes().iter().enumerate().take(basis.nodes) {
            let rot = mode_rows(*x, centre);
            for a in 0..3 {
                let r = 3 * i + a;
                let dst = &mut g[r * p..(r + 1) * p];
                dst[..m].copy_from_slice(&basis.phi[r * m..(r + 1) * m]);
                for k in 0..3 {
                    dst[m + k] = rot[a][3 + k];
                    dst[m + 3 + k] = rot[a][k];
                }
            }
        }
        g
    }
}

/// Each matched point's image-frame target less what `offset` moves its model point by (a point
/// matched twice keeps its first match's offset): what LIBR fits `Φα` to when it starts from
/// `offset` ([`RunLimits::offset`]).
pub fn offset_targets(matches: &[Match], targets: &mut [[f64; 3]], offset: &[f64]) {
    let mut done = vec![false; targets.len()];
    for m in matches {
        if m.point < targets.len() && !done[m.point] {
            done[m.point] = true;
            let d = m.model_point(offset);
            for a in 0..3 {
                targets[m.point][a] -= d[a] - m.anchor[a];
            }
        }
    }
}

/// The refit's first step at `offset`, linearised ([`LinearRefit`]): `matches` and
/// `measured_image` (the measured points in the image frame) as the refit would use them there;
/// `centre` is that of `G`'s rotations. Errors as [`fit_step`]'s, and when `offset` does not fit
/// the basis or is not finite.
pub fn linearised_refit(
    basis: &LibrBasis,
    mesh: &TetMesh,
    matches: &[Match],
    measured_image: &[[f64; 3]],
    offset: &[f64],
    centre: [f64; 3],
    params: &LibrParams,
) -> Result<LinearRefit, String> {
    if offset.len() != 3 * basis.nodes || offset.iter().any(|x| !x.is_finite()) {
        return Err(format!(
            "offset must hold 3 × {} finite values, has {}",
            basis.nodes,
            offset.len()
        ));
    }
    if mesh.num_nodes() != basis.nodes {
        return Err(format!(
            "mesh has {} nodes, the basis {}",
            mesh.num_nodes(),
            basis.nodes
        ));
    }
    params.validate()?;
    let mut targets = measured_image.to_vec();
    offset_targets(matches, &mut targets, offset);
    let asm = assemble(basis, matches, &targets, params)?;
    let (m, p) = (asm.m, asm.p);
    let llt = asm.a.llt(Side::Lower).map_err(|e| {
        format!(
            "the normal equations are singular ({e:?}): the {} matches do not determine the basis weights and rigid correction",
            asm.used.len()
        )
    })?;
    // T: identity but for the rotations, ω_G = ω'/radius and τ_G = τ − ω_G × (cen − centre).
    let mut t = Mat::<f64>::identity(p, p);
    for k in 0..3 {
        t[(m + k, m + k)] = 1.0 / asm.radius;
        let mut e = [0.0; 3];
        e[k] = 1.0;
        let c = cross3(e, sub(asm.cen, centre));
        for a in 0..3 {
            t[(m + 3 + a, m + k)] = -c[a] / asm.radius;
        }
    }
    let mut ninv_tt = t.transpose().to_owned();
    llt.solve_in_place(ninv_tt.as_mut());
    let k = &t * &ninv_tt;
    let mut b = asm.b.clone();
    llt.solve_in_place(b.as_mut());
    let theta = &t * &b;
    if !(0..p).all(|i| theta[(i, 0)].is_finite()) {
        return Err("the step produced non-finite values (ill-conditioned data)".into());
    }
    let g = LinearRefit::modes(basis, mesh, centre);
    let step0 = g
        .chunks_exact(p)
        .map(|row| (0..p).map(|j| row[j] * theta[(j, 0)]).sum())
        .collect();
    let mut d = Vec::new();
    for (r, (f, ui)) in asm.row_frames.iter().enumerate() {
        let mt = asm.used[*ui];
        for (kk, &v) in mt.nodes.iter().enumerate() {
            if mt.bary[kk] != 0.0 {
                for a in 0..3 {
                    if f[a] != 0.0 {
                        d.push((r, 3 * v as usize + a, f[a] * mt.bary[kk]));
                    }
                }
            }
        }
    }
    Ok(LinearRefit {
        columns: p,
        gain: (0..p * p).map(|i| k[(i / p, i % p)]).collect(),
        step0,
        rows: asm.rows,
        d,
    })
}

/// What [`register`] did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LibrInfo {
    /// Iterations run (matching + step).
    pub iterations: usize,
    /// True when the largest node movement of the last iteration was below the tolerance.
    pub converged: bool,
    /// True when the iterations stopped early because the next one would have passed the
    /// caller's deadline ([`register_active`]).
    pub stopped_at_deadline: bool,
    /// Weighted residual RMS after each iteration (mm).
    pub rms_history_mm: Vec<f64>,
    /// Largest node movement of each iteration (mm).
    pub movement_history_mm: Vec<f64>,
    /// Final weighted residual RMS (mm).
    pub rms_mm: f64,
    /// Total time in the matching function (s).
    pub matching_s: f64,
    /// Total time forming the step's rows and normal equations (s).
    pub assemble_s: f64,
    /// Total time in the step's solves (s).
    pub solve_s: f64,
    /// Total time (s).
    pub total_s: f64,
}

/// The result of [`register`].
#[derive(Debug, Clone, PartialEq)]
pub struct LibrSolution {
    /// Basis weights α (3K, mm).
    pub alpha: Vec<f64>,
    /// Node displacements `u = Φα` (image frame, node-major 3n, mm).
    pub u: Vec<f64>,
    /// Image → physical transform: node i is at `image_to_physical.apply(X_i + u_i)`.
    pub image_to_physical: Rigid,
    /// Iterations, residuals, timings.
    pub info: LibrInfo,
}

/// The LIBR iteration: starting from `initial` (image → physical) and u = 0, repeatedly calls
/// `rematch(u, image_to_physical)` for matches of the measured points (`measured_physical`,
/// physical frame) to the current model, maps the measured points into the image frame, takes
/// one [`fit_step`] and composes its rigid correction, until no node moves more than
/// `params.tolerance_mm` in an iteration or `params.max_iterations` is reached. `mesh` must be
/// the basis's mesh (its node positions measure the movement).
pub fn register(
    mesh: &TetMesh,
    basis: &LibrBasis,
    params: &LibrParams,
    measured_physical: &[[f64; 3]],
    initial: &Rigid,
    rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, String>,
) -> Result<LibrSolution, String> {
    register_active(
        mesh,
        basis,
        params,
        measured_physical,
        initial,
        RunLimits::default(),
        rematch,
    )
}

/// What [`register_active`] updates between matchings and when it must stop.
#[derive(Debug, Clone, Copy, Default)]
pub struct RunLimits<'a> {
    /// Nodes whose displacement `rematch` reads (None: all).
    pub active: Option<&'a [u32]>,
    /// Stop before an iteration that would end past this instant (None: no deadline).
    pub deadline: Option<Instant>,
    /// A displacement the fit starts from and keeps (node-major 3n, image frame; None: zero):
    /// the result is `offset + Φα`, and the strain energy regularises `Φα` alone.
    pub offset: Option<&'a [f64]>,
}

/// [`register`], updating between matchings only the displacement of `active` nodes (those
/// `rematch` reads, e.g. [`super::correspondence::Correspondence::active_nodes`]; `None`: all)
/// and measuring the movement there; the returned `u` is complete. On a 9,000-node liver the
/// boundary and vessel tets are about half the nodes, and `Φα` is the largest cost of an
/// iteration after matching. With a `deadline`, the iterations stop before one that the last
/// one's duration says would end past it ([`LibrInfo::stopped_at_deadline`]); at least one
/// iteration always runs.
pub fn register_active(
    mesh: &TetMesh,
    basis: &LibrBasis,
    params: &LibrParams,
    measured_physical: &[[f64; 3]],
    initial: &Rigid,
    run: RunLimits<'_>,
    mut rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, String>,
) -> Result<LibrSolution, String> {
    let RunLimits {
        active,
        deadline,
        offset,
    } = run;
    if let Some(o) = offset {
        if o.len() != 3 * basis.nodes {
            return Err(format!(
                "offset has {} values, the basis needs {}",
                o.len(),
                3 * basis.nodes
            ));
        }
        if o.iter().any(|x| !x.is_finite()) {
            return Err("offset is not finite".into());
        }
    }
    params.validate()?;
    if let Some(v) = active.and_then(|a| a.iter().find(|&&v| v as usize >= basis.nodes)) {
        return Err(format!(
            "active node {v} out of range ({} nodes)",
            basis.nodes
        ));
    }
    let all: Vec<u32>;
    let active = match active {
        Some(a) => a,
        None => {
            all = (0..basis.nodes as u32).collect();
            &all
        }
    };
    if mesh.num_nodes() != basis.nodes {
        return Err(format!(
            "mesh has {} nodes, the basis {}",
            mesh.num_nodes(),
            basis.nodes
        ));
    }
    if params.max_iterations == 0 {
        return Err("max_iterations must be at least 1".into());
    }
    let t0 = Instant::now();
    let mut info = LibrInfo::default();
    let mut t = *initial;
    let mut alpha = vec![0.0; basis.columns()];
    let mut u = offset.map_or_else(|| vec![0.0; 3 * basis.nodes], <[f64]>::to_vec);
    for _ in 0..params.max_iterations {
        let tm = Instant::now();
        let matches = rematch(&u, &t)?;
        info.matching_s += crate::util::secs(tm);
        let inv = t.inverse();
        let mut targets: Vec<[f64; 3]> = measured_physical.iter().map(|&p| inv.apply(p)).collect();
        if let Some(o) = offset {
            // Fit Φα to what the offset leaves.
            offset_targets(&matches, &mut targets, o);
        }
        let step = fit_step(basis, &matches, &targets, params)?;
        info.assemble_s += step.timings.rows_s + step.timings.normal_s;
        info.solve_s += step.timings.solve_s;
        let mut u_new = u.clone();
        basis.displacement_at(&step.alpha, active, &mut u_new);
        if let Some(o) = offset {
            for &i in active {
                for a in 0..3 {
                    let k = 3 * i as usize + a;
                    u_new[k] += o[k];
                }
            }
        }
        // Movement in the image frame of the old estimate: δ(X + u_new) − (X + u_old).
        let mut moved = 0.0f64;
        for &i in active {
            let (i, x) = (i as usize, mesh.nodes()[i as usize]);
            let old = [0, 1, 2].map(|a| x[a] + u[3 * i + a]);
            let new = step
                .rigid_correction
                .apply([0, 1, 2].map(|a| x[a] + u_new[3 * i + a]));
            moved = moved.max(dist2(old, new).sqrt());
        }
        t = step.rigid_correction.then(&t);
        alpha = step.alpha;
        u = u_new;
        info.iterations += 1;
        info.rms_history_mm.push(step.rms_mm);
        info.movement_history_mm.push(moved);
        info.rms_mm = step.rms_mm;
        if moved <= params.tolerance_mm {
            info.converged = true;
            break;
        }
        // Stop before an iteration that would end past the deadline (the last one's duration
        // predicts the next).
        if let Some(d) = deadline {
            let now = Instant::now();
            if info.iterations < params.max_iterations && now + (now - tm) > d {
                info.stopped_at_deadline = true;
                break;
            }
        }
    }
    let mut u = basis.displacement(&alpha);
    if let Some(o) = offset {
        for (x, y) in u.iter_mut().zip(o) {
            *x += y;
        }
    }
    info.total_s = crate::util::secs(t0);
    Ok(LibrSolution {
        alpha,
        u,
        image_to_physical: t,
        info,
    })
}

/// A row of Φ times α with four accumulators (vectorizes; the same bits whatever the thread
/// count, since every row is summed in a fixed order).
fn dot_row(row: &[f64], alpha: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (body, tail) = row.split_at(row.len() - row.len() % 4);
    for (r, a) in body.chunks_exact(4).zip(alpha.chunks_exact(4)) {
        for k in 0..4 {
            acc[k] += r[k] * a[k];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (r, a) in tail.iter().zip(&alpha[body.len()..]) {
        s += r * a;
    }
    s
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

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    dot(d, d)
}

fn unit(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    if l > 0.0 { a.map(|x| x / l) } else { [0.0; 3] }
}
