//! The LIBR deformation basis: FEM responses to Gaussian tractions at control points spread by
//! farthest-point sampling over the surface, under 3-2-1 supports with inertia relief.

use super::*;
use crate::fem::loads;
use crate::mesh::TetMesh;
use crate::register::physics::Physics;
use crate::register::physics::model::{BoundaryGeometry, ModelSolver, Sites};
use faer::Mat;
use rayon::prelude::*;
use std::time::Instant;

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
    /// E = ΦᵀKΦ, row-major 3K × 3K (mN·mm per mm²); zero in the rows and columns of effect
    /// columns (their amplitudes are not regularised).
    pub energy: Vec<f64>,
    /// Per column: peak traction (kPa) of the load whose response is the column.
    pub load_scale: Vec<f64>,
    /// Resolved Gaussian width σ of the traction patches (mm); of the first level in a
    /// multi-resolution basis ([`LibrBasis::build_levels`]).
    pub load_width_mm: f64,
    /// Per control point: its patch's width σ (mm) when the basis has several levels of
    /// resolution ([`LibrBasis::build_levels`]); empty when every patch has `load_width_mm`.
    pub control_width_mm: Vec<f64>,
    /// Labels of the augmented model's effect columns, which follow the 3K LIBR columns
    /// (`gravity`, `pack.x`, ...); empty for plain LIBR. An effect column is the model's
    /// response to the effect's unit load, scaled to a 1 mm peak like the LIBR columns
    /// (`load_scale` is the load amplitude per unit weight).
    pub effect_labels: Vec<String>,
    /// [`crate::register::physics::Physics::hash`] of the physics it carries (empty for none).
    pub physics_hash: String,
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

pub use crate::register::equilibrium::lumped_volumes;
pub(crate) use crate::register::equilibrium::{RigidModes, mode_rows};

impl LibrBasis {
    /// Number of basis columns (3K).
    pub fn columns(&self) -> usize {
        self.load_scale.len()
    }

    /// The width σ (mm) of control point `k`'s traction patch.
    pub fn control_width(&self, k: usize) -> f64 {
        self.control_width_mm
            .get(k)
            .copied()
            .unwrap_or(self.load_width_mm)
    }

    /// Builds the basis: control points, loads, one factorization, 3K solves (parallel column
    /// blocks), rigid-mode removal, scaling, `E = ΦᵀKΦ`.
    pub fn build(mesh: &TetMesh, params: &LibrParams) -> Result<Self, RegisterError> {
        let none = vec![false; mesh.num_nodes()];
        let sites = Sites {
            posterior: &none,
            falciform: &none,
        };
        Self::build_with(mesh, params, &Physics::none(), sites)
    }

    /// Builds the basis of an augmented model: the LIBR columns solved with the physics'
    /// supports and material ([`ModelSolver`]), then one column per load-effect amplitude
    /// ([`ModelSolver::effect_unit_loads`]: carried by the supports when the physics has one,
    /// else balanced by inertia relief, [`ModelSolver::solve_effect`], its rigid part removed: the
    /// pose is the registration's), all scaled to a 1 mm peak, with
    /// `E = ΦᵀKΦ` over every column (K with the supports' springs). Plain LIBR when `physics`
    /// is empty; `sites` are only read by supports.
    pub fn build_with(
        mesh: &TetMesh,
        params: &LibrParams,
        physics: &Physics,
        sites: Sites<'_>,
    ) -> Result<Self, RegisterError> {
        Self::build_levels(
            mesh,
            params,
            &[(params.basis.control_points, params.basis.load_width)],
            physics,
            sites,
        )
    }

    /// [`LibrBasis::build_with`] with several levels of resolution: each `(K, width)` level
    /// samples its own K control points by farthest-point sampling (from the same seed) and
    /// loads them with patches of its own width; the columns of all levels follow each other in
    /// the order given (then the effect columns), and `E = ΦᵀKΦ` couples them, so `½αᵀEα` is the
    /// strain energy of the whole deformation whichever levels express it. `params`'
    /// `control_points` and `load_width` are not read.
    pub fn build_levels(
        mesh: &TetMesh,
        params: &LibrParams,
        levels: &[(usize, LoadWidth)],
        physics: &Physics,
        sites: Sites<'_>,
    ) -> Result<Self, RegisterError> {
        check_levels(params, levels)?;
        crate::register::physics::model::check_fits(mesh, sites, physics)?;
        let t0 = Instant::now();
        let nodes = mesh.nodes();
        let n = nodes.len();
        let boundary = mesh.boundary()?;
        if boundary.nodes.len() < 3 {
            return Err(RegisterError::Model(
                "mesh has fewer than 3 boundary nodes".into(),
            ));
        }
        let control = control_nodes(nodes, &boundary.nodes, levels, params.basis.seed)?;
        let (vnormal, area) = vertex_normals(nodes, &boundary.triangles);
        let widths = level_widths(levels, area);
        let t_model = Instant::now();
        let solver = ModelSolver::new(mesh, &params.basis.material, sites, physics)?;
        let model_s = crate::util::secs(t_model);
        let (effect_loads, effect_labels) = effect_loads(&solver, mesh, physics)?;
        let kk = control.len();
        let loads = Loads {
            control: &control,
            normals: &vnormal,
            widths: &widths,
            effects: effect_loads,
        };
        let fmat = loads.matrix(&solver, nodes, &boundary.triangles);
        let loads_s = crate::util::secs(t0) - model_s;
        let t3 = Instant::now();
        let umat = solver.solve_prepared(fmat.as_ref());
        let solve_s = crate::util::secs(t3);
        let t4 = Instant::now();
        let (phi, load_scale) = scaled_columns(mesh, &solver, &umat, &control, &effect_labels)?;
        let energy = strain_energy(&solver, &phi, n, kk);
        let energy_s = crate::util::secs(t4);
        Ok(Self {
            control_nodes: control,
            nodes: n,
            phi,
            energy,
            load_scale,
            load_width_mm: widths[0],
            control_width_mm: if levels.len() > 1 { widths } else { Vec::new() },
            effect_labels,
            physics_hash: physics.hash(),
            mesh_hash: mesh_hash(mesh),
            params_hash: super::levels_key(params, levels),
            timings: BasisTimings {
                loads_s,
                assemble_s: solver.assemble_s,
                factor_s: solver.factor_s,
                solve_s,
                energy_s,
                cache_read_s: 0.0,
                total_s: crate::util::secs(t0),
            },
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

    /// Mean diagonal of E over the LIBR columns: the energy scale ē of one 1 mm mode (λ's
    /// normalisation; effect columns do not change it).
    pub fn energy_scale(&self) -> f64 {
        let m = self.columns();
        let k = self.libr_columns();
        (0..k).map(|i| self.energy[i * m + i]).sum::<f64>() / k as f64
    }

    /// Number of LIBR columns (3K); the effect columns follow them.
    pub fn libr_columns(&self) -> usize {
        self.columns() - self.effect_labels.len()
    }
}

/// Checks the parameters and every level of a multi-level basis.
fn check_levels(params: &LibrParams, levels: &[(usize, LoadWidth)]) -> Result<(), RegisterError> {
    params.validate()?;
    if levels.is_empty() {
        return Err(RegisterError::Parameter(
            "a basis needs at least one level of control points".into(),
        ));
    }
    for &(count, width) in levels {
        params.basis.with_level(count, width).validate()?;
    }
    Ok(())
}

/// Every level's control points, in level order: farthest-point samples of the boundary nodes
/// from the same seed.
fn control_nodes(
    nodes: &[[f64; 3]],
    boundary: &[u32],
    levels: &[(usize, LoadWidth)],
    seed: u64,
) -> Result<Vec<u32>, RegisterError> {
    let mut control = Vec::new();
    for &(count, _) in levels {
        let level = farthest_point_sampling(nodes, boundary, count, seed);
        if level.len() < count {
            return Err(RegisterError::Parameter(format!(
                "control_points = {count} but the boundary has only {} distinct nodes",
                level.len()
            )));
        }
        control.extend(level);
    }
    Ok(control)
}

/// Area-weighted vertex normals (not normalised; zero off the boundary) and the boundary area.
fn vertex_normals(nodes: &[[f64; 3]], triangles: &[[u32; 3]]) -> (Vec<[f64; 3]>, f64) {
    let mut vnormal = vec![[0.0; 3]; nodes.len()];
    let mut area = 0.0;
    for t in triangles {
        let [a, b, c] = t.map(|v| nodes[v as usize]);
        let na = cross(sub(b, a), sub(c, a));
        area += 0.5 * dot(na, na).sqrt();
        for &v in t {
            for k in 0..3 {
                vnormal[v as usize][k] += na[k];
            }
        }
    }
    (vnormal, area)
}

/// The load width of every control point, level by level (a spacing is a multiple of the
/// level's mean control-point spacing over the boundary `area`).
fn level_widths(levels: &[(usize, LoadWidth)], area: f64) -> Vec<f64> {
    levels
        .iter()
        .flat_map(|&(count, w)| {
            let width = match w {
                LoadWidth::Mm(w) => w,
                LoadWidth::Spacing(s) => s * (2.0 * area / (3f64.sqrt() * count as f64)).sqrt(),
            };
            std::iter::repeat_n(width, count)
        })
        .collect()
}

/// The effect loads (unit amplitude) of an augmented model and their column labels, after the
/// LIBR columns, as the model carries them: by its supports when it has one (applied as they
/// are), else balanced by inertia relief.
fn effect_loads(
    solver: &ModelSolver,
    mesh: &TetMesh,
    physics: &Physics,
) -> Result<(Vec<Vec<f64>>, Vec<String>), RegisterError> {
    let mut loads = Vec::new();
    let mut labels = Vec::new();
    if physics.is_empty() {
        return Ok((loads, labels));
    }
    let geom = BoundaryGeometry::new(mesh)?;
    for e in &physics.effects {
        let (cols, _) = solver.effect_unit_loads(mesh, &geom, e)?;
        let count = cols.len();
        for (a, c) in cols.into_iter().enumerate() {
            labels.push(if count == 1 {
                e.kind.name().to_string()
            } else {
                format!("{}.{}", e.kind.name(), ["x", "y", "z"][a])
            });
            loads.push(c);
        }
    }
    Ok((loads, labels))
}

/// The basis's right-hand sides: three tractions per control point, then the effect loads.
struct Loads<'a> {
    control: &'a [u32],
    normals: &'a [[f64; 3]],
    widths: &'a [f64],
    effects: Vec<Vec<f64>>,
}

impl Loads<'_> {
    /// The 3n × (3K + effects) load matrix, each column prepared for the solver.
    fn matrix(self, solver: &ModelSolver, nodes: &[[f64; 3]], triangles: &[[u32; 3]]) -> Mat<f64> {
        let kk = self.control.len();
        let n = nodes.len();
        let m = 3 * kk + self.effects.len();
        let mut fmat = Mat::<f64>::zeros(3 * n, m);
        for (k, &c) in self.control.iter().enumerate() {
            let nc = unit(self.normals[c as usize]);
            for axis in 0..3 {
                let mut f = control_traction(
                    nodes,
                    triangles,
                    nodes[c as usize],
                    nc,
                    axis,
                    self.widths[k],
                );
                solver.prepare_load(&mut f);
                for (r, &x) in f.iter().enumerate() {
                    fmat[(r, 3 * k + axis)] = x;
                }
            }
        }
        for (j, mut f) in self.effects.into_iter().enumerate() {
            if solver.is_free() {
                solver.prepare_load(&mut f);
            }
            for (r, &x) in f.iter().enumerate() {
                fmat[(r, 3 * kk + j)] = x;
            }
        }
        fmat
    }
}

/// Φ (row-major 3n × m) from the solved columns, each scaled to a 1 mm peak, and each column's
/// scale. A supported model's effect columns (loads its supports carry) have their rigid part
/// removed, as a free model's columns are solved without one: the organ's motion on its
/// supports under its weight is the registration's pose. Kept, it dwarfed the deformation (the
/// carried weight sinks the organ into a soft bed by centimetres) and competed with the sweeps'
/// poses: the true supported model cross-validated worse than plain LIBR on generated cohorts
/// (27–33 % more held-out misfit). The LIBR columns of a supported model keep theirs (their
/// loads are balanced; it is small).
fn scaled_columns(
    mesh: &TetMesh,
    solver: &ModelSolver,
    umat: &Mat<f64>,
    control: &[u32],
    effect_labels: &[String],
) -> Result<(Vec<f64>, Vec<f64>), RegisterError> {
    let nodes = mesh.nodes();
    let n = nodes.len();
    let kk = control.len();
    let m = umat.ncols();
    let mut phi = vec![0.0; 3 * n * m];
    let mut load_scale = vec![0.0; m];
    let mut col = vec![0.0; 3 * n];
    let modes = (!solver.is_free())
        .then(|| RigidModes::new(nodes, &lumped_volumes(mesh)))
        .transpose()?;
    for j in 0..m {
        for (r, x) in col.iter_mut().enumerate() {
            *x = umat[(r, j)];
        }
        if let Some(modes) = modes.as_ref().filter(|_| j >= 3 * kk) {
            modes.remove_rigid(nodes, &mut col);
        }
        let peak = (0..n)
            .map(|i| (col[3 * i].powi(2) + col[3 * i + 1].powi(2) + col[3 * i + 2].powi(2)).sqrt())
            .fold(0.0f64, f64::max);
        if !(peak.is_finite() && peak > 0.0) {
            let what = if j < 3 * kk {
                format!("control node {}, axis {}", control[j / 3], j % 3)
            } else {
                format!("effect {}", effect_labels[j - 3 * kk])
            };
            return Err(RegisterError::Model(format!(
                "basis column {j} ({what}) has peak displacement {peak}: the load is empty, self-balanced to nothing, or the solve failed"
            )));
        }
        load_scale[j] = 1.0 / peak;
        for (r, &x) in col.iter().enumerate() {
            phi[r * m + j] = x / peak;
        }
    }
    Ok((phi, load_scale))
}

/// `E = Φᵀ (K Φ)`, symmetrized (K with the supports' springs; row-major m × m). Effect columns
/// (past the `kk` control points' 3kk) are not regularised: the effect is part of the model and
/// its amplitude is estimated freely (their energy is left out of E, so of λαᵀẼα).
fn strain_energy(solver: &ModelSolver, phi: &[f64], n: usize, kk: usize) -> Vec<f64> {
    let m = phi.len() / (3 * n);
    let system = solver.system();
    let mut kphi = Mat::<f64>::zeros(3 * n, m);
    let mut phimat = Mat::<f64>::zeros(3 * n, m);
    let mut col = vec![0.0; 3 * n];
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
            energy[i * m + j] = if i >= 3 * kk || j >= 3 * kk {
                0.0
            } else {
                0.5 * (e[(i, j)] + e[(j, i)])
            };
        }
    }
    energy
}
