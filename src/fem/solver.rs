//! Linear-elastic systems: stiffness with springs, Dirichlet constraints, and a sparse Cholesky
//! factorization (faer, supernodal when worthwhile; nested-dissection or AMD fill-reducing
//! ordering) that is computed once and reused for any number of right-hand sides.

use super::assembly::{BlockPattern, LameField, assemble_linear_stiffness};
use super::material::LinearMaterial;
use super::ordering::nested_dissection;
use crate::mesh::NodeAdjacency;
use crate::mesh::TetMesh;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    LltRef, SymbolicCholesky, SymmetricOrdering, factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use faer::{Conj, Mat, MatMut, MatRef, Par, Side};
use std::sync::Arc;
use std::time::Instant;

/// Fill-reducing ordering used by the sparse Cholesky factorization.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub enum Ordering {
    /// Geometric nested dissection on the mesh nodes (default; least fill on 3-D meshes).
    #[default]
    NestedDissection,
    /// faer's approximate minimum degree.
    Amd,
}

pub use super::error::{FemError, NewtonFailure};

/// A linear spring from a node to its rest position: force `−K·u` with `K` a 3×3 SPD matrix (mN/mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeSpring {
    /// Node index.
    pub node: u32,
    /// Spring stiffness matrix (mN/mm).
    pub stiffness: [[f64; 3]; 3],
}

impl NodeSpring {
    /// Isotropic spring of stiffness `k` (mN/mm).
    pub fn isotropic(node: u32, k: f64) -> Self {
        Self {
            node,
            stiffness: [[k, 0.0, 0.0], [0.0, k, 0.0], [0.0, 0.0, k]],
        }
    }

    /// Spring with stiffness `k_normal` along the unit normal `n` and `k_tangent` across it (mN/mm):
    /// `K = k_t I + (k_n − k_t) n nᵀ` (a sliding support when `k_tangent = 0`); `n` is normalised
    /// here (a zero `n` gives an isotropic spring `k_tangent`).
    pub fn normal_tangent(node: u32, n: [f64; 3], k_normal: f64, k_tangent: f64) -> Self {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let n = if len > 0.0 {
            n.map(|x| x / len)
        } else {
            [0.0; 3]
        };
        let mut s = [[0.0; 3]; 3];
        for a in 0..3 {
            for b in 0..3 {
                s[a][b] =
                    (k_normal - k_tangent) * n[a] * n[b] + if a == b { k_tangent } else { 0.0 };
            }
        }
        Self { node, stiffness: s }
    }
}

/// Dirichlet constraints: a prescribed value (mm) for some degrees of freedom `3·node + axis`.
#[derive(Debug, Clone, PartialEq)]
pub struct Dirichlet {
    value: Vec<Option<f64>>,
}

impl Dirichlet {
    /// No constraint on a mesh of `nodes` nodes.
    pub fn new(nodes: usize) -> Self {
        Self {
            value: vec![None; 3 * nodes],
        }
    }

    /// Fixes all three components of each node to zero. Panics if a node is out of range (the
    /// caller builds node lists from the mesh; user-facing code validates first).
    pub fn fix_nodes(&mut self, nodes: &[u32]) -> &mut Self {
        for &n in nodes {
            self.prescribe_node(n, [0.0; 3]);
        }
        self
    }

    /// Prescribes a node's displacement (mm).
    pub fn prescribe_node(&mut self, node: u32, u: [f64; 3]) -> &mut Self {
        for (a, &ua) in u.iter().enumerate() {
            self.value[3 * node as usize + a] = Some(ua);
        }
        self
    }

    /// Prescribes one component (`axis` 0, 1, 2) of a node's displacement (mm).
    pub fn prescribe_dof(&mut self, node: u32, axis: usize, value: f64) -> &mut Self {
        self.value[3 * node as usize + axis] = Some(value);
        self
    }

    /// Prescribed value of a dof, if constrained.
    pub fn get(&self, dof: usize) -> Option<f64> {
        self.value[dof]
    }

    /// Number of constrained dofs.
    pub fn count(&self) -> usize {
        self.value.iter().filter(|v| v.is_some()).count()
    }

    /// Number of dofs (3 × nodes).
    pub fn len(&self) -> usize {
        self.value.len()
    }

    /// True when there are no dofs at all.
    pub fn is_empty(&self) -> bool {
        self.value.is_empty()
    }
}

/// The assembled stiffness of a mesh (full symmetric, springs included), in mN/mm.
#[derive(Debug, Clone)]
pub struct StiffnessSystem {
    pattern: BlockPattern,
    values: Vec<f64>,
    coords: Vec<[f64; 3]>,
    ordering: Ordering,
    /// Face-connected parts: (tet count, nodes).
    parts: Vec<(usize, Vec<u32>)>,
    /// Nodes that carry a spring.
    sprung: Vec<bool>,
    /// Springs added so far.
    springs: Vec<NodeSpring>,
}

impl StiffnessSystem {
    /// Assembles homogeneous linear elasticity. Rejects invalid materials and degenerate tets.
    pub fn linear(mesh: &TetMesh, material: &LinearMaterial) -> Result<Self, FemError> {
        material.validate()?;
        let (l, m) = material.lame();
        Self::linear_field(mesh, &LameField::Uniform(l, m))
    }

    /// Assembles linear elasticity with Lamé parameters given per tet (or uniform).
    pub fn linear_field(mesh: &TetMesh, lame: &LameField) -> Result<Self, FemError> {
        if let LameField::PerTet(v) = lame
            && v.len() != mesh.num_tets()
        {
            return Err(FemError::InvalidParameter {
                field: "lame",
                message: format!("{} per-tet values for {} tets", v.len(), mesh.num_tets()),
            });
        }
        let check = |field: &'static str, l: f64, m: f64| {
            if l.is_finite() && m.is_finite() && m > 0.0 && 3.0 * l + 2.0 * m > 0.0 {
                Ok(())
            } else {
                Err(FemError::InvalidParameter {
                    field,
                    message: format!(
                        "Lamé parameters (λ = {l}, μ = {m}) must be finite with μ > 0 and 3λ + 2μ > 0"
                    ),
                })
            }
        };
        match lame {
            LameField::Uniform(l, m) => check("lame", *l, *m)?,
            LameField::PerTet(v) => {
                for &(l, m) in v {
                    check("lame (per tet)", l, m)?;
                }
            }
        }
        for t in 0..mesh.num_tets() {
            let p = mesh.tet_points(t);
            let v = crate::mesh::vec3::tet_signed_volume(&p);
            let lmax = crate::mesh::longest_edge(&p);
            if v.abs() <= crate::mesh::DEGENERATE_REL * lmax.powi(3) || !v.is_finite() {
                return Err(FemError::DegenerateTet { tet: t, volume: v });
            }
        }
        let pattern = BlockPattern::new(mesh);
        let values = assemble_linear_stiffness(mesh, &pattern, lame);
        let (part_of_tet, nparts) = mesh.face_components();
        let mut parts: Vec<(usize, Vec<u32>)> = vec![(0, Vec::new()); nparts];
        for (t, &c) in part_of_tet.iter().enumerate() {
            parts[c as usize].0 += 1;
            parts[c as usize].1.extend_from_slice(&mesh.tets()[t]);
        }
        for p in &mut parts {
            p.1.sort_unstable();
            p.1.dedup();
        }
        Ok(Self {
            pattern,
            values,
            coords: mesh.nodes().to_vec(),
            ordering: Ordering::default(),
            parts,
            sprung: vec![false; mesh.num_nodes()],
            springs: Vec::new(),
        })
    }

    /// Checks that every free dof has stiffness and every face-connected part is held by some
    /// constraint or spring (otherwise the factorization would fail or be meaningless).
    fn check_supported(&self, free_of_dof: &[usize]) -> Result<(), FemError> {
        let p = &self.pattern;
        for node in 0..p.nodes {
            let touched = p.tet_ptr[node + 1] > p.tet_ptr[node];
            let free = (0..3).any(|a| free_of_dof[3 * node + a] != usize::MAX);
            if !touched && free && !self.sprung[node] {
                return Err(FemError::UnusedNode { node });
            }
        }
        for (k, (tets, nodes)) in self.parts.iter().enumerate() {
            let held = nodes.iter().any(|&v| {
                let v = v as usize;
                self.sprung[v] || (0..3).any(|a| free_of_dof[3 * v + a] == usize::MAX)
            });
            if !held {
                return Err(FemError::FloatingPart {
                    part: k,
                    tets: *tets,
                    node: nodes.first().copied().unwrap_or(0) as usize,
                });
            }
        }
        Ok(())
    }

    /// Chooses the fill-reducing ordering for later factorizations.
    pub fn set_ordering(&mut self, ordering: Ordering) {
        self.ordering = ordering;
    }

    /// Permutation of the free dofs (`fwd[new] = old`) for the chosen ordering, if not AMD.
    fn free_permutation(
        &self,
        free_of_dof: &[usize],
        nf: usize,
    ) -> Option<(Vec<usize>, Vec<usize>)> {
        match self.ordering {
            Ordering::Amd => None,
            Ordering::NestedDissection => {
                // Pattern rows include the node itself; harmless for the ordering (a node is never
                // on the other side of a cut from itself).
                let adj = NodeAdjacency {
                    offsets: self.pattern.node_ptr.clone(),
                    neighbors: self.pattern.block_rows.clone(),
                };
                let active: Vec<bool> = (0..self.pattern.nodes)
                    .map(|i| (0..3).any(|a| free_of_dof[3 * i + a] != usize::MAX))
                    .collect();
                let order = nested_dissection(&self.coords, &adj, &active);
                let mut fwd = Vec::with_capacity(nf);
                for node in order {
                    for a in 0..3 {
                        let f = free_of_dof[3 * node as usize + a];
                        if f != usize::MAX {
                            fwd.push(f);
                        }
                    }
                }
                let mut inv = vec![0usize; nf];
                for (new, &old) in fwd.iter().enumerate() {
                    inv[old] = new;
                }
                Some((fwd, inv))
            }
        }
    }

    /// Adds node springs to the diagonal blocks. Each spring matrix must be finite, symmetric and
    /// positive semidefinite (checked: symmetric to 1e-12 relative, non-negative diagonal).
    pub fn add_springs(&mut self, springs: &[NodeSpring]) -> Result<(), FemError> {
        for (k, s) in springs.iter().enumerate() {
            let i = s.node as usize;
            let bad = |message: String| FemError::InvalidParameter {
                field: "springs",
                message: format!("spring {k} (node {}): {message}", s.node),
            };
            if i >= self.pattern.nodes {
                return Err(bad(format!(
                    "node out of range ({} nodes)",
                    self.pattern.nodes
                )));
            }
            let m = &s.stiffness;
            let scale = m.iter().flatten().fold(0.0f64, |a, b| a.max(b.abs()));
            if !m.iter().flatten().all(|x| x.is_finite()) {
                return Err(bad(format!("non-finite stiffness {m:?}")));
            }
            for a in 0..3 {
                if m[a][a] < 0.0 {
                    return Err(bad(format!("negative diagonal stiffness {m:?}")));
                }
                for b in 0..3 {
                    if (m[a][b] - m[b][a]).abs() > 1e-12 * scale {
                        return Err(bad(format!("stiffness matrix is not symmetric {m:?}")));
                    }
                }
            }
            if scale > 0.0 {
                self.sprung[i] = true;
            }
            self.springs.push(*s);
            for a in 0..3 {
                for b in 0..3 {
                    let idx = self
                        .pattern
                        .value_index(i, a, i, b)
                        .expect("diagonal block is always in the pattern");
                    self.values[idx] += s.stiffness[b][a];
                }
            }
        }
        Ok(())
    }

    /// Number of dofs (3 × nodes).
    pub fn dofs(&self) -> usize {
        3 * self.pattern.nodes
    }

    /// The sparsity pattern.
    pub fn pattern(&self) -> &BlockPattern {
        &self.pattern
    }

    /// The matrix as a faer sparse matrix (copies the values).
    pub fn matrix(&self) -> SparseColMat<usize, f64> {
        self.pattern.to_matrix(self.values.clone())
    }

    /// `K·u` (mN) for a full displacement vector (mm).
    pub fn apply(&self, u: &[f64]) -> Vec<f64> {
        self.apply_values(&self.values, u)
    }

    /// `A·u` for another matrix `A` with this system's pattern (e.g. a tangent stiffness).
    pub fn apply_values(&self, values: &[f64], u: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.dofs()];
        let p = &self.pattern;
        for col in 0..self.dofs() {
            let uc = u[col];
            if uc == 0.0 {
                continue;
            }
            for k in p.col_ptr[col]..p.col_ptr[col + 1] {
                out[p.row_idx[k]] += values[k] * uc;
            }
        }
        out
    }

    /// Reaction forces `K·u − f` (mN) at every dof: zero (to round-off) at free dofs in
    /// equilibrium, the support forces at constrained dofs.
    pub fn reactions(&self, u: &[f64], f: &[f64]) -> Vec<f64> {
        let mut r = self.apply(u);
        for (ri, fi) in r.iter_mut().zip(f) {
            *ri -= fi;
        }
        r
    }

    /// ‖K‖∞: the largest absolute row sum (mN/mm), for scaled residuals.
    pub fn row_sum_norm(&self) -> f64 {
        let mut rows = vec![0.0f64; self.dofs()];
        for col in 0..self.dofs() {
            for k in self.pattern.col_ptr[col]..self.pattern.col_ptr[col + 1] {
                rows[self.pattern.row_idx[k]] += self.values[k].abs();
            }
        }
        rows.into_iter().fold(0.0, f64::max)
    }

    /// Strain (+ spring) energy `uᵀKu/2` in mN·mm (= µJ).
    pub fn energy(&self, u: &[f64]) -> f64 {
        0.5 * self.apply(u).iter().zip(u).map(|(a, b)| a * b).sum::<f64>()
    }

    /// Factorizes the free-free block under the given constraints.
    pub fn factorize(&self, bc: &Dirichlet) -> Result<FactorizedSystem, FemError> {
        let n = self.dofs();
        if bc.len() != n {
            return Err(FemError::InvalidParameter {
                field: "dirichlet",
                message: format!("{} dofs in constraints for a {n}-dof system", bc.len()),
            });
        }
        for d in 0..n {
            if let Some(v) = bc.get(d)
                && !v.is_finite()
            {
                return Err(FemError::InvalidParameter {
                    field: "dirichlet",
                    message: format!("node {} axis {} has non-finite value {v}", d / 3, d % 3),
                });
            }
        }
        let constrained: Vec<bool> = (0..n).map(|d| bc.get(d).is_some()).collect();
        let reduced = ReducedPattern::new(self, &constrained)?;
        let t2 = Instant::now();
        let llt = reduced.factor(&self.values)?;
        let numeric_s = t2.elapsed().as_secs_f64();
        // Lift of the prescribed values: K·u_c restricted to free dofs.
        let mut uc = vec![0.0; n];
        let mut any = false;
        for (d, v) in uc.iter_mut().enumerate() {
            if let Some(x) = bc.get(d) {
                *v = x;
                any |= x != 0.0;
            }
        }
        let lift = if any { self.apply(&uc) } else { vec![0.0; n] };
        let info = FactorInfo {
            dofs: n,
            free_dofs: reduced.free.len(),
            nnz_lower: reduced.row_idx.len(),
            nnz_factor: llt.symbolic.len_val(),
            ordering: self.ordering,
            extract_s: reduced.extract_s,
            symbolic_s: reduced.symbolic_s,
            numeric_s,
        };
        Ok(FactorizedSystem {
            reduced: Arc::new(reduced),
            llt,
            prescribed: uc,
            lift,
            info,
        })
    }

    /// The springs added so far.
    pub fn springs(&self) -> &[NodeSpring] {
        &self.springs
    }

    /// Adds the springs' stiffness into a value array laid out on this system's pattern.
    pub fn add_spring_values(&self, values: &mut [f64]) {
        for s in &self.springs {
            let i = s.node as usize;
            for a in 0..3 {
                for b in 0..3 {
                    if let Some(idx) = self.pattern.value_index(i, a, i, b) {
                        values[idx] += s.stiffness[b][a];
                    }
                }
            }
        }
    }

    /// Spring forces `K_s u` (mN) for a full displacement (mm).
    pub fn spring_force(&self, u: &[f64]) -> Vec<f64> {
        let mut f = vec![0.0; self.dofs()];
        for s in &self.springs {
            let i = s.node as usize;
            for a in 0..3 {
                for b in 0..3 {
                    f[3 * i + a] += s.stiffness[a][b] * u[3 * i + b];
                }
            }
        }
        f
    }
}

/// The free-free block of a stiffness pattern under a set of constrained dofs, with its symbolic
/// Cholesky factorization (ordering, elimination tree, supernodes). Computed once and reused for
/// every matrix on the same pattern, e.g. each Newton iteration of a nonlinear solve.
#[derive(Debug, Clone)]
pub struct ReducedPattern {
    free: Vec<usize>,
    free_of_dof: Vec<usize>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    /// For each stored entry of the reduced lower triangle, its index in the full values.
    source: Vec<usize>,
    symbolic: Arc<SymbolicCholesky<usize>>,
    extract_s: f64,
    symbolic_s: f64,
}

impl ReducedPattern {
    /// Eliminates the constrained dofs (`constrained[dof]`) of `system`'s pattern, checks that
    /// what remains is held, and computes the symbolic factorization with the system's ordering.
    pub fn new(system: &StiffnessSystem, constrained: &[bool]) -> Result<Self, FemError> {
        let t0 = Instant::now();
        let n = system.dofs();
        let mut free_of_dof = vec![usize::MAX; n];
        let mut free = Vec::with_capacity(n);
        for (d, slot) in free_of_dof.iter_mut().enumerate() {
            if !constrained[d] {
                *slot = free.len();
                free.push(d);
            }
        }
        if free.is_empty() {
            return Err(FemError::NothingFree);
        }
        system.check_supported(&free_of_dof)?;
        // Lower triangle of K_ff.
        let p = &system.pattern;
        let mut col_ptr = Vec::with_capacity(free.len() + 1);
        let mut row_idx = Vec::new();
        let mut source = Vec::new();
        col_ptr.push(0);
        for (fc, &c) in free.iter().enumerate() {
            for k in p.col_ptr[c]..p.col_ptr[c + 1] {
                let fr = free_of_dof[p.row_idx[k]];
                if fr != usize::MAX && fr >= fc {
                    row_idx.push(fr);
                    source.push(k);
                }
            }
            col_ptr.push(row_idx.len());
        }
        let nf = free.len();
        let sym_mat =
            SymbolicSparseColMat::new_checked(nf, nf, col_ptr.clone(), None, row_idx.clone());
        let extract_s = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let perm = system.free_permutation(&free_of_dof, nf);
        let ord = match &perm {
            Some((fwd, inv)) => SymmetricOrdering::Custom(PermRef::new_checked(fwd, inv, nf)),
            None => SymmetricOrdering::Amd,
        };
        let symbolic =
            factorize_symbolic_cholesky(sym_mat.as_ref(), Side::Lower, ord, Default::default())
                .map_err(|e| FemError::Factorization(format!("{e:?}")))?;
        Ok(Self {
            free,
            free_of_dof,
            col_ptr,
            row_idx,
            source,
            symbolic: Arc::new(symbolic),
            extract_s,
            symbolic_s: t1.elapsed().as_secs_f64(),
        })
    }

    /// Free dofs in order (`free[k]` is the global dof of free unknown `k`).
    pub fn free_dofs(&self) -> &[usize] {
        &self.free
    }

    /// Index of a global dof among the free unknowns, or `None` if constrained.
    pub fn free_index(&self, dof: usize) -> Option<usize> {
        self.free_of_dof
            .get(dof)
            .copied()
            .filter(|&i| i != usize::MAX)
    }

    /// Numeric Cholesky factorization of the free block of `values` (laid out on the full
    /// pattern); names the node of a non-positive pivot.
    pub fn factor(&self, values: &[f64]) -> Result<CholeskyFactor, FemError> {
        let nf = self.free.len();
        let vals: Vec<f64> = self.source.iter().map(|&k| values[k]).collect();
        let sym = SymbolicSparseColMat::new_checked(
            nf,
            nf,
            self.col_ptr.clone(),
            None,
            self.row_idx.clone(),
        );
        let kff = SparseColMat::new(sym, vals);
        CholeskyFactor::numeric(self.symbolic.clone(), kff.as_ref()).map_err(|e| match e {
            faer::sparse::linalg::LltError::Numeric(
                faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index },
            ) => {
                // Map the pivot back through the fill-reducing permutation to a node and axis.
                let original = self
                    .symbolic
                    .perm()
                    .map(|p| p.arrays().0.get(index).copied().unwrap_or(index))
                    .unwrap_or(index);
                let dof = self.free.get(original).copied().unwrap_or(0);
                FemError::NotPositiveDefinite {
                    free: nf,
                    node: dof / 3,
                    axis: dof % 3,
                }
            }
            other => FemError::Factorization(format!("{other:?}")),
        })
    }
}

/// What the factorization did, with stage timings (seconds).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct FactorInfo {
    /// Total dofs.
    pub dofs: usize,
    /// Free (unconstrained) dofs.
    pub free_dofs: usize,
    /// Stored entries of the lower triangle of K_ff.
    pub nnz_lower: usize,
    /// Stored entries of the Cholesky factor L (fill-in included).
    pub nnz_factor: usize,
    /// Ordering used.
    pub ordering: Ordering,
    /// Time to extract K_ff.
    pub extract_s: f64,
    /// Time for the symbolic factorization (ordering, elimination tree, supernodes).
    pub symbolic_s: f64,
    /// Time for the numeric Cholesky factorization.
    pub numeric_s: f64,
}

/// A factorized constrained system; solve it for as many load vectors as needed.
#[derive(Debug, Clone)]
pub struct FactorizedSystem {
    reduced: Arc<ReducedPattern>,
    llt: CholeskyFactor,
    prescribed: Vec<f64>,
    lift: Vec<f64>,
    info: FactorInfo,
}

impl FactorizedSystem {
    /// Factorization facts and timings.
    pub fn info(&self) -> FactorInfo {
        self.info
    }

    /// Free dofs in order (`free[k]` is the global dof of free unknown `k`).
    pub fn free_dofs(&self) -> &[usize] {
        &self.reduced.free
    }

    /// Index of a global dof among the free unknowns, or `None` if constrained.
    pub fn free_index(&self, dof: usize) -> Option<usize> {
        self.reduced.free_index(dof)
    }

    /// The reduced pattern with its symbolic factorization (shareable for refactorizations).
    pub fn reduced(&self) -> &Arc<ReducedPattern> {
        &self.reduced
    }

    /// Solves for the full displacement (mm) under a full load vector `f` (mN, 3 × nodes):
    /// constrained dofs take their prescribed values.
    pub fn solve(&self, f: &[f64]) -> Vec<f64> {
        let mut rhs = Mat::<f64>::zeros(self.reduced.free.len(), 1);
        for (k, &d) in self.reduced.free.iter().enumerate() {
            rhs[(k, 0)] = f[d] - self.lift[d];
        }
        self.llt.solve_in_place(rhs.as_mut());
        let mut u = self.prescribed.clone();
        for (k, &d) in self.reduced.free.iter().enumerate() {
            u[d] = rhs[(k, 0)];
        }
        u
    }

    /// Solves `K_ff X = B` in place for many right-hand sides given on the free dofs only
    /// (rows = free unknowns, one column per load case; homogeneous constraints).
    pub fn solve_free_in_place(&self, rhs: MatMut<'_, f64>) {
        self.llt.solve_in_place(rhs);
    }

    /// The Cholesky factor (shared symbolic part + numeric values).
    pub fn factor(&self) -> &CholeskyFactor {
        &self.llt
    }

    /// Solves for many full load vectors (columns of `f`, 3n rows) with homogeneous constraints
    /// (prescribed values are not applied); returns full displacements, one column per load.
    pub fn solve_many_homogeneous(&self, f: MatRef<'_, f64>) -> Mat<f64> {
        let mut rhs = Mat::<f64>::zeros(self.reduced.free.len(), f.ncols());
        for j in 0..f.ncols() {
            for (k, &d) in self.reduced.free.iter().enumerate() {
                rhs[(k, j)] = f[(d, j)];
            }
        }
        self.llt.solve_in_place(rhs.as_mut());
        let mut u = Mat::<f64>::zeros(f.nrows(), f.ncols());
        for j in 0..f.ncols() {
            for (k, &d) in self.reduced.free.iter().enumerate() {
                u[(d, j)] = rhs[(k, j)];
            }
        }
        u
    }
}

/// The parallel degree of the numeric Cholesky factorization, whatever the thread count (a
/// single thread runs the same splits one after the other, to the same bits).
pub const FACTOR_PAR_DEGREE: usize = 2;

/// Right-hand sides solved together in one sequential sweep of the factor by
/// `CholeskyFactor::solve_in_place`; blocks run in parallel.
pub const SOLVE_BLOCK_COLS: usize = 16;

/// A sparse Cholesky factor `P K Pᵀ = L Lᵀ`: the symbolic part (ordering, elimination tree,
/// supernodes) is shared by `Arc` so it can be reused for new values with the same pattern.
#[derive(Debug, Clone)]
pub struct CholeskyFactor {
    symbolic: Arc<SymbolicCholesky<usize>>,
    values: Vec<f64>,
}

impl CholeskyFactor {
    /// Numeric factorization of `a` (lower triangle stored) with a precomputed symbolic part.
    pub fn numeric(
        symbolic: Arc<SymbolicCholesky<usize>>,
        a: faer::sparse::SparseColMatRef<'_, usize, f64>,
    ) -> Result<Self, faer::sparse::linalg::LltError> {
        // A fixed degree, not the pool's thread count: faer splits its sums by the degree, so
        // the last bits depend on it, and results must not depend on the thread count.
        let par = Par::rayon(FACTOR_PAR_DEGREE);
        let mut values = vec![0.0; symbolic.len_val()];
        let mut mem = MemBuffer::try_new(
            symbolic.factorize_numeric_llt_scratch::<f64>(par, Default::default()),
        )
        .map_err(faer::sparse::FaerError::from)?;
        symbolic.factorize_numeric_llt::<f64>(
            &mut values,
            a,
            Side::Lower,
            Default::default(),
            par,
            MemStack::new(&mut mem),
            Default::default(),
        )?;
        Ok(Self { symbolic, values })
    }

    /// The shared symbolic factorization.
    pub fn symbolic(&self) -> &Arc<SymbolicCholesky<usize>> {
        &self.symbolic
    }

    /// Solves `K X = B` in place (one column per right-hand side). Many columns are solved in
    /// parallel in blocks of `SOLVE_BLOCK_COLS` (16), each block sequentially: the blocks are the
    /// same whatever the thread count, so the answer is the same to the last bit.
    pub fn solve_in_place(&self, rhs: MatMut<'_, f64>) {
        let blocks = rhs.ncols().div_ceil(SOLVE_BLOCK_COLS);
        self.solve_blocks(rhs, blocks);
    }

    /// Solves `blocks` consecutive blocks of `SOLVE_BLOCK_COLS` (16) columns (the last may be
    /// narrower), halving the range in parallel.
    fn solve_blocks(&self, rhs: MatMut<'_, f64>, blocks: usize) {
        if blocks <= 1 {
            self.solve_block(rhs, Par::Seq);
            return;
        }
        let left = blocks / 2;
        let (a, b) = rhs.split_at_col_mut(left * SOLVE_BLOCK_COLS);
        rayon::join(
            || self.solve_blocks(a, left),
            || self.solve_blocks(b, blocks - left),
        );
    }

    fn solve_block(&self, rhs: MatMut<'_, f64>, par: Par) {
        let mut mem = MemBuffer::new(
            self.symbolic
                .solve_in_place_scratch::<f64>(rhs.ncols(), par),
        );
        LltRef::new(&self.symbolic, &self.values).solve_in_place_with_conj(
            Conj::No,
            rhs,
            par,
            MemStack::new(&mut mem),
        );
    }
}
