//! A differentiable sparse × dense product `Y = A · X` for burn (the one operation graph
//! convolution needs that burn's generic gather/scatter makes slow): `A` is a constant sparse
//! matrix in CSR form (no gradient), `X` a dense `[cols, C]` tensor, `Y` `[rows, C]`. The backward
//! pass is `dX = Aᵀ · dY` with the transpose precomputed. Implemented as a burn backend extension
//! for the Flex CPU backend and for `Autodiff<B>` over it. On any other device (a GPU, with the
//! `gpu` feature) the same product is a gather, a scale and a scatter-add of burn's own
//! differentiable operations, with the index tensors uploaded once per matrix and device.

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind, binary, unary};
use burn::backend::flex::FlexTensor;
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, backend_extension};
use burn::tensor::{DType, Device, IndexingUpdateOp, Int, Tensor, TensorData};
use rayon::prelude::*;
use std::sync::{Arc, Mutex};

use super::GcnError;

/// A sparse matrix in compressed sparse row form.
#[derive(Debug, Clone, PartialEq)]
pub struct Csr {
    /// Number of rows.
    pub rows: usize,
    /// Number of columns.
    pub cols: usize,
    /// Row `r`'s entries are `indptr[r]..indptr[r+1]`.
    pub indptr: Vec<usize>,
    /// Column of each entry.
    pub indices: Vec<u32>,
    /// Value of each entry.
    pub values: Vec<f32>,
}

impl Csr {
    /// Builds a CSR matrix from (row, col, value) triplets; duplicates are summed. Errors on
    /// out-of-range indices or non-finite values.
    pub fn from_triplets(
        rows: usize,
        cols: usize,
        triplets: &[(usize, usize, f32)],
    ) -> Result<Self, GcnError> {
        if u32::try_from(cols).is_err() {
            return Err(GcnError::Invalid(format!(
                "{cols} columns overflow the index type"
            )));
        }
        let mut count = vec![0usize; rows + 1];
        for (k, &(r, c, v)) in triplets.iter().enumerate() {
            if r >= rows || c >= cols {
                return Err(GcnError::Invalid(format!(
                    "entry {k}: ({r}, {c}) outside a {rows} × {cols} matrix"
                )));
            }
            if !v.is_finite() {
                return Err(GcnError::Invalid(format!(
                    "entry {k}: value {v} is not finite"
                )));
            }
            count[r + 1] += 1;
        }
        for r in 0..rows {
            count[r + 1] += count[r];
        }
        let mut next = count.clone();
        let mut entries = vec![(0u32, 0f32); triplets.len()];
        for &(r, c, v) in triplets {
            entries[next[r]] = (c as u32, v);
            next[r] += 1;
        }
        // Sort each row by column and merge duplicates.
        let mut indptr = Vec::with_capacity(rows + 1);
        let mut indices = Vec::with_capacity(entries.len());
        let mut values = Vec::with_capacity(entries.len());
        indptr.push(0);
        for r in 0..rows {
            let row = &mut entries[count[r]..count[r + 1]];
            row.sort_by_key(|e| e.0);
            for &(c, v) in row.iter() {
                if indices.len() > *indptr.last().unwrap_or(&0) && indices.last() == Some(&c) {
                    *values.last_mut().expect("non-empty") += v;
                } else {
                    indices.push(c);
                    values.push(v);
                }
            }
            indptr.push(indices.len());
        }
        Ok(Self {
            rows,
            cols,
            indptr,
            indices,
            values,
        })
    }

    /// The transpose.
    pub fn transpose(&self) -> Self {
        let mut t = Vec::with_capacity(self.values.len());
        for r in 0..self.rows {
            for k in self.indptr[r]..self.indptr[r + 1] {
                t.push((self.indices[k] as usize, r, self.values[k]));
            }
        }
        Self::from_triplets(self.cols, self.rows, &t).expect("transpose of a valid matrix")
    }

    /// Number of stored entries.
    pub fn nnz(&self) -> usize {
        self.values.len()
    }

    /// `A · X` for row-major `x` of `cols × c`, into row-major `rows × c`.
    pub fn matmul_dense(&self, x: &[f32], c: usize) -> Vec<f32> {
        let mut y = vec![0f32; self.rows * c];
        if c == 0 {
            return y;
        }
        y.par_chunks_mut(c).enumerate().for_each(|(r, out)| {
            for k in self.indptr[r]..self.indptr[r + 1] {
                let v = self.values[k];
                let src = &x[self.indices[k] as usize * c..][..c];
                for (o, s) in out.iter_mut().zip(src) {
                    *o += v * s;
                }
            }
        });
        y
    }
}

/// The matrix's entries as tensors on one device, for the generic product: the row and column
/// of every entry and its value (`[nnz, 1]`).
#[derive(Debug, Clone)]
struct DeviceEntries {
    device: Device,
    rows: Tensor<1, Int>,
    cols: Tensor<1, Int>,
    values: Tensor<2>,
}

/// A sparse matrix and its transpose, shared by the forward and backward passes (cheap to clone:
/// both are reference-counted, and the transposed operator swaps the two without copying).
#[derive(Debug, Clone)]
pub struct SparseOp {
    a: Arc<Csr>,
    t: Arc<Csr>,
    /// `a`'s entries on the last non-Flex device it ran on.
    entries: Arc<Mutex<Option<DeviceEntries>>>,
}

impl SparseOp {
    /// Wraps `a` (and precomputes its transpose).
    pub fn new(a: Csr) -> Self {
        let t = Arc::new(a.transpose());
        Self {
            a: Arc::new(a),
            t,
            entries: Arc::default(),
        }
    }

    /// The matrix.
    pub fn matrix(&self) -> &Csr {
        &self.a
    }

    fn transposed(&self) -> Self {
        Self {
            a: self.t.clone(),
            t: self.a.clone(),
            entries: Arc::default(),
        }
    }

    /// `A · x` from burn's generic operations, for devices without the extension (a GPU):
    /// `y = 0; y[row_e] += value_e · x[col_e]` over the entries `e`, a gather, a scale and a
    /// scatter-add, differentiable through burn's own backward of `select` and `select_assign`.
    /// (Spreading each column's entries instead, so that no backward pass adds many values into
    /// one row, measured no faster on an H100: `BENCHMARKS.md`, "GPU".)
    fn apply_generic(&self, x: Tensor<2>) -> Tensor<2> {
        let [_, c] = x.dims();
        let device = x.device().without_autodiff();
        let e = {
            let mut cache = self.entries.lock().unwrap_or_else(|p| p.into_inner());
            match cache.as_ref() {
                Some(e) if e.device == device => e.clone(),
                _ => {
                    let a = self.matrix();
                    let mut rows = Vec::with_capacity(a.nnz());
                    for r in 0..a.rows {
                        rows.extend((a.indptr[r]..a.indptr[r + 1]).map(|_| r as i64));
                    }
                    let cols: Vec<i64> = a.indices.iter().map(|&j| i64::from(j)).collect();
                    let n = a.nnz();
                    let e = DeviceEntries {
                        rows: Tensor::from_data(TensorData::new(rows, [n]), &device),
                        cols: Tensor::from_data(TensorData::new(cols, [n]), &device),
                        values: Tensor::from_data(
                            TensorData::new(a.values.clone(), [n, 1]),
                            &device,
                        ),
                        device,
                    };
                    *cache = Some(e.clone());
                    e
                }
            }
        };
        let gathered = x.clone().select(0, e.cols) * e.values;
        Tensor::<2>::zeros([self.matrix().rows, c], &x.device()).select_assign(
            0,
            e.rows,
            gathered,
            IndexingUpdateOp::Add,
        )
    }

    /// `A · x` as a differentiable burn operation. `x`: `[cols, C]` → `[rows, C]`.
    pub fn apply(&self, x: Tensor<2>) -> Result<Tensor<2>, GcnError> {
        let [n, _] = x.dims();
        if n != self.matrix().cols {
            return Err(GcnError::Invalid(format!(
                "sparse product: x has {n} rows, the matrix has {} columns",
                self.matrix().cols
            )));
        }
        if x.device().without_autodiff() != Device::flex() {
            return Ok(self.apply_generic(x));
        }
        let out = <Dispatch as SparseBackend>::spmm(x.into_dispatch(), self.clone());
        Ok(Tensor::from_dispatch(out))
    }
}

/// The sparse product as a burn backend extension.
#[backend_extension(Flex, Autodiff)]
pub trait SparseBackend: Backend {
    /// `A · x`.
    fn spmm(x: FloatTensor<Self>, a: SparseOp) -> FloatTensor<Self>;
    /// `z · w` (`[n, k] · [k, c]`), differentiable in both (see [`weight_product`]).
    fn weight_product(z: FloatTensor<Self>, w: FloatTensor<Self>) -> FloatTensor<Self>;
    /// `g · wᵀ` (`[n, c] · [k, c]ᵀ` → `[n, k]`), written straight into the tensor returned.
    fn matmul_nt(g: FloatTensor<Self>, w: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// `z · w` for a tall `z` (`[n, k]`, `n` nodes) and a small `w` (`[k, c]`), differentiable in
/// both. The same product as burn's `matmul`; what differs is its backward pass on the CPU: the
/// gradient `dz = g · wᵀ` (as large as `z`: 288 MB for a 9,000-node mesh with 125 kernel weights
/// of width 64) is computed into the buffer the returned tensor owns, where burn-flex's `matmul`
/// allocates every output twice and copies it once (its empty tensor is a byte vector whose
/// declared alignment never meets the 16 its storage checks for). On other devices, `matmul`.
pub fn weight_product(z: Tensor<2>, w: Tensor<2>) -> Tensor<2> {
    if z.device().without_autodiff() != Device::flex() {
        return z.matmul(w);
    }
    let out = <Dispatch as SparseBackend>::weight_product(z.into_dispatch(), w.into_dispatch());
    Tensor::from_dispatch(out)
}

/// Rows of `g · wᵀ` computed per block in [`Flex`]'s `matmul_nt`: each block is one sequential
/// product, so the bits do not depend on the thread count.
const NT_BLOCK_ROWS: usize = 256;

/// `g · wᵀ` for row-major `g` (`n × c`) and `w` (`k × c`), into row-major `n × k`.
fn matmul_nt_rows(g: &[f32], w: &[f32], n: usize, k: usize, c: usize) -> Vec<f32> {
    let mut out = vec![0f32; n * k];
    if n == 0 || k == 0 {
        return out;
    }
    let wt = faer::MatRef::from_row_major_slice(w, k, c).transpose();
    out.par_chunks_mut(NT_BLOCK_ROWS * k)
        .zip(g.par_chunks(NT_BLOCK_ROWS * c))
        .for_each(|(o, gb)| {
            let rows = gb.len() / c.max(1);
            let dst = faer::MatMut::from_row_major_slice_mut(o, rows, k);
            let lhs = faer::MatRef::from_row_major_slice(gb, rows, c);
            faer::linalg::matmul::matmul(
                dst,
                faer::Accum::Replace,
                lhs,
                wt,
                1.0f32,
                faer::Par::Seq,
            );
        });
    out
}

impl SparseBackend for Flex {
    fn spmm(x: FloatTensor<Self>, a: SparseOp) -> FloatTensor<Self> {
        let x: FlexTensor = x.to_contiguous();
        let dims = x.layout().shape().to_vec();
        let c = dims[1];
        let y = match x.dtype() {
            DType::F32 => a.matrix().matmul_dense(x.storage::<f32>(), c),
            other => panic!("sparse product: unsupported dtype {other:?}"),
        };
        FlexTensor::from_data(TensorData::new(y, [a.matrix().rows, c]))
    }

    fn weight_product(z: FloatTensor<Self>, w: FloatTensor<Self>) -> FloatTensor<Self> {
        <Flex as FloatTensorOps<Flex>>::float_matmul(z, w)
    }

    fn matmul_nt(g: FloatTensor<Self>, w: FloatTensor<Self>) -> FloatTensor<Self> {
        let g: FlexTensor = g.to_contiguous();
        let w: FlexTensor = w.to_contiguous();
        let (gd, wd) = (g.layout().shape().to_vec(), w.layout().shape().to_vec());
        assert!(
            gd.len() == 2 && wd.len() == 2 && gd[1] == wd[1],
            "matmul_nt: shapes {gd:?} and {wd:?} do not match"
        );
        let (n, c, k) = (gd[0], gd[1], wd[0]);
        let y = match (g.dtype(), w.dtype()) {
            (DType::F32, DType::F32) => {
                matmul_nt_rows(g.storage::<f32>(), w.storage::<f32>(), n, k, c)
            }
            other => panic!("matmul_nt: unsupported dtypes {other:?}"),
        };
        FlexTensor::from_data(TensorData::new(y, [n, k]))
    }
}

#[derive(Debug)]
struct WeightProductBackward;

impl<B: Backend + SparseBackend> Backward<B, 2> for WeightProductBackward {
    /// The inputs `z` and `w` (reference-counted on the CPU: no copy).
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _c: &mut Checkpointer) {
        let (z, w) = ops.state;
        binary::<B, _, _>(
            ops.parents,
            ops.node,
            grads,
            |g| B::matmul_nt(g, w),
            |g| B::float_matmul(B::float_transpose(z), g),
        );
    }
}

#[derive(Debug)]
struct SpmmBackward;

impl<B: Backend + SparseBackend> Backward<B, 1> for SpmmBackward {
    type State = SparseOp;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _c: &mut Checkpointer) {
        let t = ops.state.transposed();
        unary::<B, _>(ops.parents, ops.node, grads, |grad| B::spmm(grad, t));
    }
}

impl<B: Backend + SparseBackend, C: CheckpointStrategy> SparseBackend for Autodiff<B, C> {
    fn spmm(x: FloatTensor<Self>, a: SparseOp) -> FloatTensor<Self> {
        match SpmmBackward
            .prepare::<C>([x.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = B::spmm(x.into_primitive(), a.clone());
                prep.finish(a, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(B::spmm(x.into_primitive(), a)),
        }
    }

    fn weight_product(z: FloatTensor<Self>, w: FloatTensor<Self>) -> FloatTensor<Self> {
        match WeightProductBackward
            .prepare::<C>([z.node(), w.node()])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let (zp, wp) = (z.into_primitive(), w.into_primitive());
                let out = B::weight_product(zp.clone(), wp.clone());
                prep.finish((zp, wp), out)
            }
            OpsKind::UnTracked(prep) => {
                prep.finish(B::weight_product(z.into_primitive(), w.into_primitive()))
            }
        }
    }

    fn matmul_nt(g: FloatTensor<Self>, w: FloatTensor<Self>) -> FloatTensor<Self> {
        // Only ever called on the inner backend, inside a backward pass.
        let out = B::matmul_nt(g.into_primitive(), w.into_primitive());
        FloatTensor::<Self>::new(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    fn dense(a: &Csr) -> Vec<Vec<f32>> {
        let mut d = vec![vec![0f32; a.cols]; a.rows];
        for (r, row) in d.iter_mut().enumerate() {
            for k in a.indptr[r]..a.indptr[r + 1] {
                row[a.indices[k] as usize] += a.values[k];
            }
        }
        d
    }

    #[test]
    fn triplets_merge_duplicates_and_transpose_mirrors() {
        let a = Csr::from_triplets(3, 4, &[(0, 3, 1.0), (2, 1, 2.0), (0, 3, 0.5), (1, 0, -1.0)])
            .unwrap();
        assert_eq!(a.nnz(), 3);
        let d = dense(&a);
        assert_eq!(d[0][3], 1.5);
        assert_eq!(d[2][1], 2.0);
        let t = dense(&a.transpose());
        for r in 0..3 {
            for c in 0..4 {
                assert_eq!(d[r][c], t[c][r]);
            }
        }
        assert!(Csr::from_triplets(2, 2, &[(2, 0, 1.0)]).is_err());
        assert!(Csr::from_triplets(2, 2, &[(0, 0, f32::NAN)]).is_err());
    }

    /// A fixed pseudo-random sequence in [0, 1) (a linear congruential generator's high bits).
    fn uniform(seed: u64) -> impl FnMut() -> f32 {
        let mut s = seed;
        move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) as f64 / (1u64 << 31) as f64) as f32
        }
    }

    fn host(t: Tensor<2>) -> Vec<f32> {
        t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap()
    }

    #[test]
    fn weight_product_and_its_gradients_match_dense_algebra() {
        // y = z w; with L = sum(m ⊙ y): dL/dz = m wᵀ, dL/dw = zᵀ m. 600 rows: three blocks of
        // `g · wᵀ`, the last one short.
        let (n, k, c) = (600, 9, 4);
        let mut u = uniform(11);
        let mut rnd = move || u() - 0.5;
        let z: Vec<f32> = (0..n * k).map(|_| rnd()).collect();
        let w: Vec<f32> = (0..k * c).map(|_| rnd()).collect();
        let m: Vec<f32> = (0..n * c).map(|_| rnd()).collect();
        let dev = Device::flex().autodiff();
        let zt = Tensor::<2>::from_data(TensorData::new(z.clone(), [n, k]), &dev).require_grad();
        let wt = Tensor::<2>::from_data(TensorData::new(w.clone(), [k, c]), &dev).require_grad();
        let mt = Tensor::<2>::from_data(TensorData::new(m.clone(), [n, c]), &dev);
        let y = weight_product(zt.clone(), wt.clone());
        let yv = host(y.clone());
        for i in 0..n {
            for j in 0..c {
                let want: f32 = (0..k).map(|q| z[i * k + q] * w[q * c + j]).sum();
                assert!((yv[i * c + j] - want).abs() < 1e-5, "y[{i}, {j}]");
            }
        }
        let g = (y * mt).sum().backward();
        let gz = host(zt.grad(&g).unwrap());
        for i in 0..n {
            for q in 0..k {
                let want: f32 = (0..c).map(|j| m[i * c + j] * w[q * c + j]).sum();
                assert!((gz[i * k + q] - want).abs() < 1e-5, "dz[{i}, {q}]");
            }
        }
        let gw = host(wt.grad(&g).unwrap());
        for q in 0..k {
            for j in 0..c {
                let want: f32 = (0..n).map(|i| z[i * k + q] * m[i * c + j]).sum();
                assert!((gw[q * c + j] - want).abs() < 1e-3, "dw[{q}, {j}]");
            }
        }
        // Without gradients it is burn's matmul, bit for bit.
        let zp = Tensor::<2>::from_data(TensorData::new(z.clone(), [n, k]), &Device::flex());
        let wp = Tensor::<2>::from_data(TensorData::new(w.clone(), [k, c]), &Device::flex());
        assert_eq!(
            host(weight_product(zp.clone(), wp.clone())),
            host(zp.matmul(wp))
        );
    }

    #[test]
    fn product_and_its_gradient_match_dense_algebra() {
        // A random sparse matrix; y = A x and d(sum(w ⊙ y))/dx = Aᵀ w.
        let (rows, cols, c) = (7, 5, 3);
        let mut rnd = uniform(7);
        let trip: Vec<_> = (0..14)
            .map(|_| {
                (
                    (rnd() * rows as f32) as usize,
                    (rnd() * cols as f32) as usize,
                    rnd() - 0.5,
                )
            })
            .collect();
        let a = Csr::from_triplets(rows, cols, &trip).unwrap();
        let d = dense(&a);
        let x: Vec<f32> = (0..cols * c).map(|_| rnd()).collect();
        let w: Vec<f32> = (0..rows * c).map(|_| rnd()).collect();
        let dev = Device::flex().autodiff();
        let xt = Tensor::<2>::from_data(TensorData::new(x.clone(), [cols, c]), &dev).require_grad();
        let wt = Tensor::<2>::from_data(TensorData::new(w.clone(), [rows, c]), &dev);
        let op = SparseOp::new(a);
        let y = op.apply(xt.clone()).unwrap();
        let yv = host(y.clone());
        for r in 0..rows {
            for j in 0..c {
                let want: f32 = (0..cols).map(|k| d[r][k] * x[k * c + j]).sum();
                assert!((yv[r * c + j] - want).abs() < 1e-5);
            }
        }
        let g = (y * wt).sum().backward();
        let gx = host(xt.grad(&g).unwrap());
        for k in 0..cols {
            for j in 0..c {
                let want: f32 = (0..rows).map(|r| d[r][k] * w[r * c + j]).sum();
                assert!((gx[k * c + j] - want).abs() < 1e-5);
            }
        }
        // The generic product (what a GPU runs) gives the same values and gradients, and
        // its entries are uploaded once per device.
        let xg = Tensor::<2>::from_data(TensorData::new(x.clone(), [cols, c]), &dev).require_grad();
        let yg = op.apply_generic(xg.clone());
        let ygv = host(yg.clone());
        for (a, b) in ygv.iter().zip(&yv) {
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
        let gg = (yg * Tensor::<2>::from_data(TensorData::new(w.clone(), [rows, c]), &dev))
            .sum()
            .backward();
        let ggx = host(xg.grad(&gg).unwrap());
        for (a, b) in ggx.iter().zip(&gx) {
            assert!((a - b).abs() < 1e-6, "{a} vs {b}");
        }
        assert!(op.entries.lock().unwrap().is_some());
        // A wrong shape is an error.
        let bad = Tensor::<2>::zeros([cols + 1, c], &Device::flex());
        assert!(op.apply(bad).is_err());
    }
}
