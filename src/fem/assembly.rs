//! Sparse assembly: the 3×3-block sparsity pattern of a tet mesh and parallel stiffness assembly.
//!
//! The pattern is built once per mesh (node adjacency through tet edges plus the diagonal) and holds
//! the full symmetric matrix in compressed-column form with dof `3·node + axis`. Assembly runs in
//! parallel over node columns: each node gathers the contributions of its incident tets into its
//! own three columns, so no two threads ever write the same entry and the result is deterministic.

use super::element::{p1_gradients, stiffness_block};
use crate::mesh::TetMesh;
use faer::sparse::{SparseColMat, SymbolicSparseColMat};
use rayon::prelude::*;

/// Compressed-column pattern of the 3n×3n stiffness matrix of a tet mesh.
#[derive(Debug, Clone)]
pub struct BlockPattern {
    /// Number of nodes.
    pub nodes: usize,
    /// `node_ptr[i]..node_ptr[i+1]` indexes `block_rows` for node column `i`.
    pub node_ptr: Vec<usize>,
    /// Sorted node rows of each node column (its neighbours and itself).
    pub block_rows: Vec<u32>,
    /// Column pointers of the scalar matrix (length 3n + 1).
    pub col_ptr: Vec<usize>,
    /// Row indices of the scalar matrix.
    pub row_idx: Vec<usize>,
    /// Node-to-tet incidence: `tet_ptr[i]..tet_ptr[i+1]` indexes `tet_of_node`.
    pub tet_ptr: Vec<usize>,
    /// Tets incident to each node.
    pub tet_of_node: Vec<u32>,
}

impl BlockPattern {
    /// Builds the pattern of a mesh.
    pub fn new(mesh: &TetMesh) -> Self {
        let adj = mesh.node_adjacency();
        let n = mesh.num_nodes();
        let mut node_ptr = Vec::with_capacity(n + 1);
        let mut block_rows = Vec::with_capacity(adj.neighbors.len() + n);
        node_ptr.push(0);
        for i in 0..n {
            let nb = adj.of(i);
            let split = nb.partition_point(|&j| (j as usize) < i);
            block_rows.extend_from_slice(&nb[..split]);
            block_rows.push(i as u32);
            block_rows.extend_from_slice(&nb[split..]);
            node_ptr.push(block_rows.len());
        }
        let mut col_ptr = Vec::with_capacity(3 * n + 1);
        let mut row_idx = Vec::with_capacity(9 * block_rows.len());
        col_ptr.push(0);
        for i in 0..n {
            let rows = &block_rows[node_ptr[i]..node_ptr[i + 1]];
            for _axis in 0..3 {
                for &j in rows {
                    let j = j as usize;
                    row_idx.extend_from_slice(&[3 * j, 3 * j + 1, 3 * j + 2]);
                }
                col_ptr.push(row_idx.len());
            }
        }
        let (tet_ptr, tet_of_node) = mesh.node_to_tets();
        Self {
            nodes: n,
            node_ptr,
            block_rows,
            col_ptr,
            row_idx,
            tet_ptr,
            tet_of_node,
        }
    }

    /// Number of stored entries.
    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }

    /// Index into the values of entry (row dof `3j + b`, column dof `3i + a`), if in the pattern.
    pub fn value_index(&self, i: usize, a: usize, j: usize, b: usize) -> Option<usize> {
        let rows = &self.block_rows[self.node_ptr[i]..self.node_ptr[i + 1]];
        let k = rows.binary_search(&(j as u32)).ok()?;
        Some(self.col_ptr[3 * i + a] + 3 * k + b)
    }

    /// A sparse matrix with this pattern and the given values.
    pub fn to_matrix(&self, values: Vec<f64>) -> SparseColMat<usize, f64> {
        let n = 3 * self.nodes;
        // The pattern is sorted and in range by construction.
        let symbolic = SymbolicSparseColMat::new_checked(
            n,
            n,
            self.col_ptr.clone(),
            None,
            self.row_idx.clone(),
        );
        SparseColMat::new(symbolic, values)
    }
}

/// Lamé parameters per tet: either one pair for all, or a pair per tet (heterogeneous material).
#[derive(Debug, Clone)]
pub enum LameField {
    /// Same (λ, μ) in kPa everywhere.
    Uniform(f64, f64),
    /// (λ, μ) in kPa per tet.
    PerTet(Vec<(f64, f64)>),
}

impl LameField {
    #[inline]
    fn at(&self, t: usize) -> (f64, f64) {
        match self {
            LameField::Uniform(l, m) => (*l, *m),
            LameField::PerTet(v) => v[t],
        }
    }
}

/// Assembles the linear-elastic stiffness values (mN/mm) on `pattern` in parallel over nodes.
/// Degenerate tets contribute nothing (validate the mesh first to reject them).
pub fn assemble_linear_stiffness(
    mesh: &TetMesh,
    pattern: &BlockPattern,
    lame: &LameField,
) -> Vec<f64> {
    // Per-tet gradients and |V| once, in parallel.
    let geo: Vec<Option<([[f64; 3]; 4], f64)>> = (0..mesh.num_tets())
        .into_par_iter()
        .map(|t| p1_gradients(&mesh.tet_points(t)).map(|(g, v)| (g, v.abs())))
        .collect();
    assemble_blocks(pattern, mesh.tets(), |t, lj, li| {
        let (g, v) = geo[t]?;
        let (lambda, mu) = lame.at(t);
        Some(stiffness_block(g[lj], g[li], v, lambda, mu))
    })
}

/// Assembles a block matrix on `pattern` in parallel over node columns. `block(t, lj, li)` returns
/// the 3×3 block of tet `t` coupling its local node `lj` (rows) to local node `li` (columns), or
/// `None` to skip the tet. Each node column is written by one thread only, in a fixed order, so the
/// result is deterministic.
pub fn assemble_blocks<F>(pattern: &BlockPattern, tets: &[[u32; 4]], block: F) -> Vec<f64>
where
    F: Fn(usize, usize, usize) -> Option<[[f64; 3]; 3]> + Sync,
{
    let mut values = vec![0.0; pattern.nnz()];
    // Split the value array into one slice per node (its three columns are contiguous).
    let mut slices: Vec<&mut [f64]> = Vec::with_capacity(pattern.nodes);
    let mut rest: &mut [f64] = &mut values;
    for i in 0..pattern.nodes {
        let len = pattern.col_ptr[3 * i + 3] - pattern.col_ptr[3 * i];
        let (head, tail) = rest.split_at_mut(len);
        slices.push(head);
        rest = tail;
    }
    slices.into_par_iter().enumerate().for_each(|(i, out)| {
        let rows = &pattern.block_rows[pattern.node_ptr[i]..pattern.node_ptr[i + 1]];
        let stride = 3 * rows.len();
        for &t in &pattern.tet_of_node[pattern.tet_ptr[i]..pattern.tet_ptr[i + 1]] {
            let t = t as usize;
            let tet = tets[t];
            let Some(li) = tet.iter().position(|&x| x as usize == i) else {
                continue;
            };
            for (lj, &j) in tet.iter().enumerate() {
                // Block (row node j, column node i).
                let Some(k) = block(t, lj, li) else { break };
                let Ok(pos) = rows.binary_search(&j) else {
                    continue;
                };
                for a in 0..3 {
                    for b in 0..3 {
                        out[a * stride + 3 * pos + b] += k[b][a];
                    }
                }
            }
        }
    });
    values
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fem::element::element_stiffness;
    use crate::mesh::procedural::box_mesh;

    #[test]
    fn parallel_assembly_matches_naive_dense_assembly() {
        let mesh = box_mesh([2.0, 1.0, 1.5], [2, 2, 2], 0.1);
        let pattern = BlockPattern::new(&mesh);
        let (l, m) = (2.0, 0.7);
        let k = pattern.to_matrix(assemble_linear_stiffness(
            &mesh,
            &pattern,
            &LameField::Uniform(l, m),
        ));
        let dense = k.to_dense();
        let n = 3 * mesh.num_nodes();
        let mut naive = vec![0.0; n * n];
        for t in 0..mesh.num_tets() {
            let ke = element_stiffness(&mesh.tet_points(t), l, m).unwrap();
            let tet = mesh.tets()[t];
            for i in 0..4 {
                for j in 0..4 {
                    for a in 0..3 {
                        for b in 0..3 {
                            let (r, c) = (3 * tet[i] as usize + a, 3 * tet[j] as usize + b);
                            naive[r * n + c] += ke[3 * i + a][3 * j + b];
                        }
                    }
                }
            }
        }
        for r in 0..n {
            for c in 0..n {
                assert!((dense[(r, c)] - naive[r * n + c]).abs() < 1e-12);
            }
        }
        assert_eq!(pattern.value_index(0, 0, 0, 0), Some(0));
    }
}
