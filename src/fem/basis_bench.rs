//! The LIBR preload workload as a benchmark: assemble, factorize once, solve many unit loads.
//!
//! Mirrors `../shared/bench/fem_peer.py` exactly so the two can be compared side by side: linear
//! elasticity (E = 5 kPa, ν = 0.45), nodes above the 80th percentile of y fixed (numpy's linear
//! quantile), `rhs` unit loads at random free dofs.

use super::{Dirichlet, FactorInfo, FemError, LinearMaterial, Ordering, StiffnessSystem};
use crate::mesh::TetMesh;
use crate::util::SplitMix64;
use faer::Mat;
use std::time::Instant;

/// Stage timings and sizes of one basis benchmark run.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BasisBench {
    /// Mesh nodes.
    pub nodes: usize,
    /// Mesh tets.
    pub tets: usize,
    /// Free dofs.
    pub dofs_free: usize,
    /// Right-hand sides solved.
    pub nrhs: usize,
    /// Stiffness assembly (pattern + parallel values), s.
    pub assemble_s: f64,
    /// Constraint elimination + symbolic + numeric Cholesky, s.
    pub factor_s: f64,
    /// Back-substitution of all right-hand sides, s.
    pub solve_all_s: f64,
    /// Sum of the stages, s.
    pub total_s: f64,
    /// Factorization breakdown.
    pub factor: FactorInfo,
    /// Largest scaled residual ‖K_ff x − b‖∞ / (‖K‖∞ ‖x‖∞ + ‖b‖∞) over a sample of right-hand
    /// sides (NaN if any solution is not finite).
    pub max_rel_residual: f64,
}

/// `max` that propagates NaN (a NaN anywhere makes the result NaN).
pub fn nan_max(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() {
        f64::NAN
    } else {
        a.max(b)
    }
}

/// Runs the benchmark on a mesh.
pub fn run(
    mesh: &TetMesh,
    nrhs: usize,
    seed: u64,
    ordering: Ordering,
) -> Result<BasisBench, FemError> {
    let t0 = Instant::now();
    let mut system = StiffnessSystem::linear(mesh, &LinearMaterial::new(5.0, 0.45))?;
    system.set_ordering(ordering);
    let assemble_s = t0.elapsed().as_secs_f64();
    let ys: Vec<f64> = mesh.nodes().iter().map(|p| p[1]).collect();
    let cut = crate::util::quantile(&ys, 0.8);
    let fixed: Vec<u32> = (0..mesh.num_nodes() as u32)
        .filter(|&i| ys[i as usize] > cut)
        .collect();
    let mut bc = Dirichlet::new(mesh.num_nodes());
    bc.fix_nodes(&fixed);
    let t1 = Instant::now();
    let fact = system.factorize(&bc)?;
    let factor_s = t1.elapsed().as_secs_f64();
    let nf = fact.free_dofs().len();
    let mut rng = SplitMix64::new(seed);
    let picks: Vec<usize> = (0..nrhs).map(|_| rng.below(nf)).collect();
    let mut x = Mat::<f64>::zeros(nf, nrhs);
    for (j, &i) in picks.iter().enumerate() {
        x[(i, j)] = 1.0;
    }
    let t2 = Instant::now();
    fact.solve_free_in_place(x.as_mut());
    let solve_all_s = t2.elapsed().as_secs_f64();
    // Residual check on a few columns: K_ff x = e_i, scaled by ‖K‖∞ ‖x‖∞ + ‖b‖∞ (backward error).
    let knorm = system.row_sum_norm();
    let mut max_rel_residual = 0.0f64;
    let free = fact.free_dofs();
    for j in (0..nrhs).step_by((nrhs / 8).max(1)) {
        let mut u = vec![0.0; system.dofs()];
        for (k, &d) in free.iter().enumerate() {
            u[d] = x[(k, j)];
        }
        let r = system.apply(&u);
        let mut worst = 0.0f64;
        let mut xnorm = 0.0f64;
        for (k, &d) in free.iter().enumerate() {
            let b = if k == picks[j] { 1.0 } else { 0.0 };
            worst = nan_max(worst, (r[d] - b).abs());
            xnorm = nan_max(xnorm, u[d].abs());
        }
        max_rel_residual = nan_max(max_rel_residual, worst / (knorm * xnorm + 1.0));
    }
    Ok(BasisBench {
        nodes: mesh.num_nodes(),
        tets: mesh.num_tets(),
        dofs_free: nf,
        nrhs,
        assemble_s,
        factor_s,
        solve_all_s,
        total_s: assemble_s + factor_s + solve_all_s,
        factor: fact.info(),
        max_rel_residual,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_run_solves_accurately() {
        let m = crate::mesh::procedural::box_mesh([2.0, 2.0, 2.0], [4, 4, 4], 0.2);
        for ordering in [Ordering::NestedDissection, Ordering::Amd] {
            let b = run(&m, 12, 1, ordering).unwrap();
            assert_eq!(b.nrhs, 12);
            assert!(b.max_rel_residual < 1e-12, "{}", b.max_rel_residual);
        }
    }
}
