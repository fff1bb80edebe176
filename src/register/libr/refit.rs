//! The linearised LIBR refit: the fit's answer as a linear map of target offsets, for the
//! refit-aware training loss and the data-consistency refit.

use super::*;
use crate::mesh::TetMesh;
use crate::register::Match;
use faer::linalg::solvers::Solve;
use faer::{Mat, Side};

/// The first step of a LIBR refit ([`solve_with_limits`] with an offset), linearised in a change
/// `c` of the offset with the matches held: the refit's node displacement (image frame, the
/// rigid correction to first order about the undeformed nodes) is
/// `offset + c + step0 − G·K·Gᵀ·Dᵀ·D·c`, where `G` (3n × p) holds, per node, the basis rows, the
/// rotations `e_k × (X − centre)` and the translations ([`LinearRefit::modes`]), `K` is
/// the step's gain in those coordinates, and `D` maps a displacement to the step's weighted rows
/// (each row: √(w/W) times its direction, on the matched point's barycentric nodes). A network
/// trained through this map learns only what the refit will not put back ([`solve_with_limits`]
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

/// T: identity but for the rotations, ω_G = ω'/radius and τ_G = τ − ω_G × (cen − centre): the
/// change from the step's scaled rotation about `cen` to `G`'s rotation about `centre` (`m`
/// basis weights, `p` unknowns in all).
fn rotation_change(m: usize, p: usize, radius: f64, cen: [f64; 3], centre: [f64; 3]) -> Mat<f64> {
    let mut t = Mat::<f64>::identity(p, p);
    for k in 0..3 {
        t[(m + k, m + k)] = 1.0 / radius;
        let mut e = [0.0; 3];
        e[k] = 1.0;
        let c = cross(e, sub(cen, centre));
        for a in 0..3 {
            t[(m + 3 + a, m + k)] = -c[a] / radius;
        }
    }
    t
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
) -> Result<LinearRefit, RegisterError> {
    if offset.len() != 3 * basis.nodes || offset.iter().any(|x| !x.is_finite()) {
        return Err(RegisterError::Inconsistent(format!(
            "offset must hold 3 × {} finite values, has {}",
            basis.nodes,
            offset.len()
        )));
    }
    if mesh.num_nodes() != basis.nodes {
        return Err(RegisterError::Inconsistent(format!(
            "mesh has {} nodes, the basis {}",
            mesh.num_nodes(),
            basis.nodes
        )));
    }
    params.validate()?;
    let mut targets = measured_image.to_vec();
    offset_targets(matches, &mut targets, offset);
    let asm = assemble(basis, matches, &targets, params, None)?;
    let (m, p) = (asm.m, asm.p);
    let llt = asm.a.llt(Side::Lower).map_err(|e| {
        RegisterError::IllConditioned(format!(
            "the normal equations are singular ({e:?}): the {} matches do not determine the basis weights and rigid correction",
            asm.used.len()
        ))
    })?;
    let t = rotation_change(m, p, asm.radius, asm.cen, centre);
    let mut ninv_tt = t.transpose().to_owned();
    llt.solve_in_place(ninv_tt.as_mut());
    let k = &t * &ninv_tt;
    let mut b = asm.b.clone();
    llt.solve_in_place(b.as_mut());
    let theta = &t * &b;
    if !(0..p).all(|i| theta[(i, 0)].is_finite()) {
        return Err(RegisterError::IllConditioned(
            "the step produced non-finite values (ill-conditioned data)".into(),
        ));
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
