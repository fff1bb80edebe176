//! B-spline basis of spline convolution (SplineCNN, Fey et al. 2018), computed in plain Rust
//! exactly as `pytorch_spline_conv`'s `spline_basis`, and PyG's Cartesian pseudo-coordinates.
//!
//! For an edge with pseudo-coordinates `u ∈ [0, 1]^D`, each dimension `d` contributes `degree + 1`
//! B-spline pieces: `v = u_d · (kernel_size[d] − degree · is_open[d])`, the piece `k` sits at
//! kernel index `(trunc(v) + k) mod kernel_size[d]` with value `N_k(v − floor(v))`. The
//! `S = (degree + 1)^D` products of one piece per dimension are the edge's basis values; their
//! flat kernel indices are dimension-0 fastest. Everything here is f64 and host-side: the basis is
//! computed once per graph and handed to [`super::SplineConv`] as tensors.

use super::GcnError;

/// Tolerance on pseudo-coordinates outside `[0, 1]` (rounding in their normalisation).
pub const PSEUDO_TOLERANCE: f64 = 1e-9;

/// Shape of a spline kernel: per-dimension kernel sizes, open/closed flags and the B-spline degree.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SplineKernel {
    /// Number of kernel weights along each pseudo-coordinate dimension.
    pub kernel_size: Vec<usize>,
    /// Whether each dimension is open (`true`) or closed/periodic (`false`).
    pub is_open: Vec<bool>,
    /// B-spline degree, 1 (linear), 2 (quadratic) or 3 (cubic).
    pub degree: usize,
}

impl SplineKernel {
    /// A validated kernel; errors on a dimension mismatch, degree outside 1–3 or a kernel size
    /// too small for the degree.
    pub fn new(
        kernel_size: Vec<usize>,
        is_open: Vec<bool>,
        degree: usize,
    ) -> Result<Self, GcnError> {
        if kernel_size.is_empty() {
            return Err(GcnError::Invalid(
                "spline kernel needs at least one dimension".into(),
            ));
        }
        if kernel_size.len() != is_open.len() {
            return Err(GcnError::Invalid(format!(
                "kernel_size has {} dimensions but is_open has {}",
                kernel_size.len(),
                is_open.len()
            )));
        }
        if !(1..=3).contains(&degree) {
            return Err(GcnError::Invalid(format!(
                "B-spline degree must be 1, 2 or 3, got {degree}"
            )));
        }
        for (d, (&ks, &open)) in kernel_size.iter().zip(&is_open).enumerate() {
            // An open dimension needs at least degree + 1 weights; a closed one must not wrap a
            // piece onto itself (fewer than degree + 1 distinct indices).
            if ks < degree + 1 {
                return Err(GcnError::Invalid(format!(
                    "kernel_size[{d}] = {ks} is too small for degree {degree} ({} dimension needs ≥ {})",
                    if open { "open" } else { "closed" },
                    degree + 1
                )));
            }
        }
        Ok(Self {
            kernel_size,
            is_open,
            degree,
        })
    }

    /// Number of pseudo-coordinate dimensions `D`.
    pub fn dim(&self) -> usize {
        self.kernel_size.len()
    }

    /// Total number of kernel weights `K = Π kernel_size[d]`.
    pub fn num_weights(&self) -> usize {
        self.kernel_size.iter().product()
    }

    /// Number of non-zero basis functions per edge `S = (degree + 1)^D`.
    pub fn num_basis(&self) -> usize {
        (self.degree + 1).pow(self.dim() as u32)
    }
}

/// Basis values and kernel-weight indices of a set of edges, row-major `E × S`.
#[derive(Debug, Clone, PartialEq)]
pub struct SplineBasis {
    /// Number of edges `E`.
    pub num_edges: usize,
    /// Basis functions per edge `S`.
    pub num_basis: usize,
    /// Basis values, `basis[e * S + s]`.
    pub basis: Vec<f64>,
    /// Kernel-weight indices in `0..K`, `weight_index[e * S + s]`.
    pub weight_index: Vec<usize>,
}

/// The 1-D uniform B-spline piece `k` (0..=degree) of the given degree at local coordinate `t`.
fn piece(degree: usize, k: usize, t: f64) -> f64 {
    match (degree, k) {
        (1, 0) => 1.0 - t,
        (1, _) => t,
        (2, 0) => 0.5 * t * t - t + 0.5,
        (2, 1) => -t * t + t + 0.5,
        (2, _) => 0.5 * t * t,
        (3, 0) => (1.0 - t) * (1.0 - t) * (1.0 - t) / 6.0,
        (3, 1) => (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0,
        (3, 2) => (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0,
        _ => t * t * t / 6.0,
    }
}

/// B-spline basis of `E` edges from row-major pseudo-coordinates `pseudo` (`E × D`, in `[0, 1]`).
///
/// Errors when `pseudo.len()` is not a multiple of `D` or a value is outside `[0, 1]` by more than
/// [`PSEUDO_TOLERANCE`] (or not finite); values within the tolerance are clamped.
pub fn spline_basis(pseudo: &[f64], kernel: &SplineKernel) -> Result<SplineBasis, GcnError> {
    let dim = kernel.dim();
    if pseudo.len() % dim != 0 {
        return Err(GcnError::Invalid(format!(
            "pseudo has {} values, not a multiple of the kernel dimension {dim}",
            pseudo.len()
        )));
    }
    let num_edges = pseudo.len() / dim;
    let s_count = kernel.num_basis();
    let m = kernel.degree + 1;
    let mut basis = Vec::with_capacity(num_edges * s_count);
    let mut weight_index = Vec::with_capacity(num_edges * s_count);
    // Per edge and dimension: the scaled coordinate split into integer part and fraction.
    let mut lo = vec![0usize; dim];
    let mut frac = vec![0f64; dim];
    for e in 0..num_edges {
        for d in 0..dim {
            let u = pseudo[e * dim + d];
            if !u.is_finite() || !(-PSEUDO_TOLERANCE..=1.0 + PSEUDO_TOLERANCE).contains(&u) {
                return Err(GcnError::Invalid(format!(
                    "pseudo[{e}][{d}] = {u} is outside [0, 1]"
                )));
            }
            let u = u.clamp(0.0, 1.0);
            let open = usize::from(kernel.is_open[d]);
            let v = u * (kernel.kernel_size[d] - kernel.degree * open) as f64;
            // v ≥ 0, so trunc = floor.
            lo[d] = v as usize;
            frac[d] = v - v.floor();
        }
        for s in 0..s_count {
            let mut k = s;
            let mut wi = 0usize;
            let mut offset = 1usize;
            let mut b = 1.0f64;
            for d in 0..dim {
                let k_mod = k % m;
                k /= m;
                let ks = kernel.kernel_size[d];
                wi += ((lo[d] + k_mod) % ks) * offset;
                offset *= ks;
                b *= piece(kernel.degree, k_mod, frac[d]);
            }
            basis.push(b);
            weight_index.push(wi);
        }
    }
    Ok(SplineBasis {
        num_edges,
        num_basis: s_count,
        basis,
        weight_index,
    })
}

/// PyG's `Cartesian` pseudo-coordinates: `cart_e = pos[target_e] − pos[source_e]`, normalised as
/// `cart / (2 · max|cart|) + 0.5` with the maximum absolute component over the whole graph.
///
/// `pos` is row-major `N × dim`; `targets`/`sources` are `edge_index[0]`/`edge_index[1]`.
/// Returns row-major `E × dim` values in `[0, 1]`. A graph without extent (all `cart` zero) gives
/// 0.5 everywhere. Errors on length mismatches or out-of-range node indices.
pub fn cartesian_pseudo(
    pos: &[f64],
    dim: usize,
    targets: &[usize],
    sources: &[usize],
) -> Result<Vec<f64>, GcnError> {
    if dim == 0 || pos.len() % dim != 0 {
        return Err(GcnError::Invalid(format!(
            "pos has {} values, not a multiple of dimension {dim}",
            pos.len()
        )));
    }
    let n = pos.len() / dim;
    super::check_edges(n, targets, sources)?;
    let mut cart = Vec::with_capacity(targets.len() * dim);
    let mut max_abs = 0f64;
    for (&t, &s) in targets.iter().zip(sources) {
        for d in 0..dim {
            let c = pos[t * dim + d] - pos[s * dim + d];
            if !c.is_finite() {
                return Err(GcnError::Invalid("non-finite node position".into()));
            }
            max_abs = max_abs.max(c.abs());
        }
        cart.extend((0..dim).map(|d| pos[t * dim + d] - pos[s * dim + d]));
    }
    let scale = if max_abs > 0.0 { 0.5 / max_abs } else { 0.0 };
    for c in &mut cart {
        *c = *c * scale + 0.5;
    }
    Ok(cart)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_bad_kernels_and_pseudo() {
        assert!(SplineKernel::new(vec![5], vec![true], 0).is_err());
        assert!(SplineKernel::new(vec![5], vec![true], 4).is_err());
        assert!(SplineKernel::new(vec![3], vec![true], 3).is_err());
        assert!(SplineKernel::new(vec![5, 5], vec![true], 1).is_err());
        let k = SplineKernel::new(vec![5, 5], vec![true, false], 1).unwrap();
        assert!(spline_basis(&[0.5, 0.5, 0.5], &k).is_err());
        assert!(spline_basis(&[0.5, 1.1], &k).is_err());
        assert!(spline_basis(&[f64::NAN, 0.5], &k).is_err());
        assert!(spline_basis(&[-1e-12, 1.0 + 1e-12], &k).is_ok());
    }

    #[test]
    fn basis_is_a_partition_of_unity() {
        for degree in 1..=3 {
            let k = SplineKernel::new(vec![5, 4, 6], vec![true, false, true], degree).unwrap();
            let pseudo: Vec<f64> = (0..60).map(|i| ((i * 37) % 101) as f64 / 100.0).collect();
            let b = spline_basis(&pseudo, &k).unwrap();
            for e in 0..b.num_edges {
                let sum: f64 = b.basis[e * b.num_basis..(e + 1) * b.num_basis].iter().sum();
                assert!((sum - 1.0).abs() < 1e-12, "degree {degree}: {sum}");
            }
            assert!(b.weight_index.iter().all(|&w| w < k.num_weights()));
        }
    }

    #[test]
    fn cartesian_rejects_bad_indices() {
        assert!(cartesian_pseudo(&[0.0, 1.0], 1, &[0], &[2]).is_err());
        assert!(cartesian_pseudo(&[0.0, 1.0], 1, &[0, 1], &[1]).is_err());
        let c = cartesian_pseudo(&[0.0, 1.0], 1, &[0, 1], &[1, 0]).unwrap();
        assert_eq!(c, vec![0.0, 1.0]);
    }
}
