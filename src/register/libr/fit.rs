//! One LIBR step: the weighted least-squares system of basis weights and a rigid correction,
//! regularised by strain energy, assembled and solved.

use super::*;
use crate::mesh::rigid::Rigid;
use crate::register::Match;
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{BlockStructure, matmul as tri_matmul};
use faer::linalg::solvers::Solve;
use faer::{Accum, Mat, Par, Side};
use std::time::Instant;

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

/// A rigid prior's pose pairs in the image frame of the current pose (anchor, target: see
/// [`crate::register::prior::RigidPrior::image_pairs`]) and its weight κ against the weighted mean
/// squared misfit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PriorPairs {
    /// Pose point and its trusted position.
    pub pairs: [([f64; 3], [f64; 3]); 6],
    /// κ: each pair counts `κ / 6`.
    pub weight: f64,
}

pub(super) fn normalize3(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    if l > 0.0 { a.map(|x| x / l) } else { a }
}

/// The weighted least-squares system of one LIBR step ([`fit_step`]): rows, right-hand side,
/// and the regularised normal matrix (lower triangle), with what built them.
pub(super) struct Assembled<'a> {
    pub(super) used: Vec<&'a Match>,
    /// The targets (image frame) the matches' points are fitted to.
    pub(super) targets: &'a [[f64; 3]],
    pub(super) wsum: f64,
    pub(super) cen: [f64; 3],
    pub(super) radius: f64,
    pub(super) m: usize,
    pub(super) p: usize,
    pub(super) rows: usize,
    /// Jᵀ, p × rows.
    pub(super) jt: Mat<f64>,
    pub(super) rhs: Mat<f64>,
    /// The frame vector (times √(w/W)) of each row, and its match.
    pub(super) row_frames: Vec<([f64; 3], usize)>,
    pub(super) before: f64,
    /// Squared residual of the rigid prior's rows at the current pose (0 without a prior).
    pub(super) prior_rr: f64,
    /// JᵀJ + damping + λ/e·E, lower triangle.
    pub(super) a: Mat<f64>,
    /// Jᵀr.
    pub(super) b: Mat<f64>,
    pub(super) rows_s: f64,
    pub(super) normal_s: f64,
}

/// Checks λ and every match against the basis and the targets (see [`fit_step`] for the errors).
fn validate_matches(
    basis: &LibrBasis,
    matches: &[Match],
    targets_image: &[[f64; 3]],
    params: &LibrParams,
) -> Result<(), RegisterError> {
    let lambda = params.fit.regularization;
    if !(lambda.is_finite() && lambda >= 0.0) {
        return Err(RegisterError::Parameter(format!(
            "regularization must be finite and >= 0, got {lambda}"
        )));
    }
    if matches.is_empty() {
        return Err(RegisterError::TooFewMatches { matched: 0 });
    }
    let n = basis.nodes;
    for (k, mt) in matches.iter().enumerate() {
        if mt.point >= targets_image.len() {
            return Err(RegisterError::Inconsistent(format!(
                "match {k}: point {} out of range ({} targets)",
                mt.point,
                targets_image.len()
            )));
        }
        if let Some(&v) = mt.nodes.iter().find(|&&v| v as usize >= n) {
            return Err(RegisterError::Inconsistent(format!(
                "match {k}: node {v} out of range ({n} nodes)"
            )));
        }
        if !(mt.weight.is_finite() && mt.weight >= 0.0) {
            return Err(RegisterError::Inconsistent(format!(
                "match {k}: weight {} is not finite and >= 0",
                mt.weight
            )));
        }
        if !mt.bary.iter().chain(&mt.anchor).all(|x| x.is_finite()) {
            return Err(RegisterError::Inconsistent(format!(
                "match {k}: non-finite anchor or barycentric weight"
            )));
        }
        if mt.weight > 0.0 && !targets_image[mt.point].iter().all(|x| x.is_finite()) {
            return Err(RegisterError::Inconsistent(format!(
                "match {k}: target {} is not finite: {:?}",
                mt.point, targets_image[mt.point]
            )));
        }
    }
    Ok(())
}

/// Weighted centroid and RMS radius (at least 1) of the used matches' anchors.
fn anchor_centre(used: &[&Match], wsum: f64) -> ([f64; 3], f64) {
    let mut cen = [0.0; 3];
    for mt in used {
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
    (cen, radius)
}

/// Rows a match contributes: one on a surface under pure point-to-plane (`tw == 0`), else three.
pub(super) fn rows_of(mt: &Match, tw: f64) -> usize {
    if tw == 0.0 && dot(mt.normal, mt.normal) > 0.0 {
        1
    } else {
        3
    }
}

/// The unknowns' geometry shared by every row: basis columns `m`, unknowns `p`, the anchors'
/// centre and radius, and √ of the tangential weight.
pub(super) struct RowShape {
    pub(super) m: usize,
    pub(super) p: usize,
    pub(super) cen: [f64; 3],
    pub(super) radius: f64,
    pub(super) tw: f64,
}

/// Fills `axis_rows` (3 × p) with the x, y, z rows of one match scaled by `s`, and returns the
/// scaled residuals `s (y − a)`.
pub(super) fn match_axis_rows(
    basis: &LibrBasis,
    mt: &Match,
    s: f64,
    y: [f64; 3],
    sh: &RowShape,
    axis_rows: &mut [f64],
) -> [f64; 3] {
    let (m, p) = (sh.m, sh.p);
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
        let rot = mode_rows(mt.anchor, sh.cen)[a];
        for k in 0..3 {
            dst[m + k] = s * rot[3 + k] / sh.radius;
            dst[m + 3 + k] = if k == a { s } else { 0.0 };
        }
        r[a] = s * (y[a] - mt.anchor[a]);
    }
    r
}

/// The row frame of a match: (n, t1, t2) with the tangential ones scaled by `tw` for a match
/// with a normal (point-to-plane), the axes otherwise (point-to-point).
pub(super) fn row_frame(normal: [f64; 3], tw: f64) -> [[f64; 3]; 3] {
    let len = dot(normal, normal).sqrt();
    if len > 0.0 {
        let nn = normal.map(|x| x / len);
        let helper = if nn[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let t1 = normalize3(cross(nn, helper));
        let t2 = cross(nn, t1);
        [nn, t1.map(|x| tw * x), t2.map(|x| tw * x)]
    } else {
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    }
}

/// The weighted rows of the used matches: Jᵀ (p × rows), r, the squared residual before the
/// step, and each row's scaled frame vector and match.
type Rows = (Mat<f64>, Mat<f64>, f64, Vec<([f64; 3], usize)>);

/// Builds the weighted rows J (stored transposed) and r = y − a, scaled by √(w/W).
fn build_rows(
    basis: &LibrBasis,
    used: &[&Match],
    targets_image: &[[f64; 3]],
    wsum: f64,
    sh: &RowShape,
    rows: usize,
) -> Rows {
    let p = sh.p;
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
        let r = match_axis_rows(basis, mt, s, y, sh, &mut axis_rows);
        // Point-to-plane: rotate the three axis rows into (n, t1, t2), the tangential ones
        // down-weighted; without a normal, the axis rows as they are (point-to-point).
        let frame = row_frame(mt.normal, sh.tw);
        for f in frame.iter().take(rows_of(mt, sh.tw)) {
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
    (jt, rhs, before, row_frames)
}

/// The lower triangle of JᵀJ and Jᵀr, sequentially (bit-stable).
fn normal_equations(jt: &Mat<f64>, rhs: &Mat<f64>, p: usize) -> (Mat<f64>, Mat<f64>) {
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
    (a, b)
}

/// Adds the rigid prior's rows to the normal equations and returns their squared residual.
fn add_prior(a: &mut Mat<f64>, b: &mut Mat<f64>, prior: Option<&PriorPairs>, sh: &RowShape) -> f64 {
    let m = sh.m;
    let mut prior_rr = 0.0;
    // The rigid prior: each pose pair a point-to-point row on the rigid unknowns alone (the
    // prior is on the pose, not the deformation), scaled by √(κ/6).
    if let Some(pr) = prior {
        let s = (pr.weight / 6.0).sqrt();
        for &(q, target) in &pr.pairs {
            let rot = mode_rows(q, sh.cen);
            for ax in 0..3 {
                let mut g = [0.0; 6];
                for k in 0..3 {
                    g[k] = s * rot[ax][3 + k] / sh.radius;
                    g[3 + k] = if k == ax { s } else { 0.0 };
                }
                let r = s * (target[ax] - q[ax]);
                prior_rr += r * r;
                for i in 0..6 {
                    for j in 0..=i {
                        a[(m + i, m + j)] += g[i] * g[j];
                    }
                    b[(m + i, 0)] += g[i] * r;
                }
            }
        }
    }
    prior_rr
}

/// Damps the rigid unknowns slightly and adds the strain-energy regularisation λ/e·E.
fn damp_and_regularize(a: &mut Mat<f64>, basis: &LibrBasis, lambda: f64, m: usize, p: usize) {
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
}

/// Validates the matches and builds the step's system (see [`fit_step`] for the errors).
pub(super) fn assemble<'a>(
    basis: &LibrBasis,
    matches: &'a [Match],
    targets_image: &'a [[f64; 3]],
    params: &LibrParams,
    prior: Option<&PriorPairs>,
) -> Result<Assembled<'a>, RegisterError> {
    let t0 = Instant::now();
    let lambda = params.fit.regularization;
    validate_matches(basis, matches, targets_image, params)?;
    let used: Vec<&Match> = matches.iter().filter(|m| m.weight > 0.0).collect();
    if used.len() < 3 {
        return Err(RegisterError::TooFewMatches {
            matched: used.len(),
        });
    }
    let wsum: f64 = used.iter().map(|m| m.weight).sum();
    if !(wsum.is_finite() && wsum > 0.0) {
        return Err(RegisterError::IllConditioned(format!(
            "total match weight is {wsum}"
        )));
    }
    let m = basis.columns();
    let p = m + 6;
    // Centroid and radius of the anchors: rotation centre and scale of the ω unknowns.
    let (cen, radius) = anchor_centre(&used, wsum);
    // Weighted rows: J (R × p) and r = y − a (R), scaled by √(w/W): one row per match on a
    // surface when the tangential weight is 0 (pure point-to-plane), three otherwise.
    let tw = params.fit.tangential_weight.sqrt();
    let sh = RowShape {
        m,
        p,
        cen,
        radius,
        tw,
    };
    let rows: usize = used.iter().map(|mt| rows_of(mt, tw)).sum();
    let (jt, rhs, before, row_frames) = build_rows(basis, &used, targets_image, wsum, &sh, rows);
    let rows_s = crate::util::secs(t0);
    let t1 = Instant::now();
    let (mut a, mut b) = normal_equations(&jt, &rhs, p);
    let rhs0 = rhs;
    let prior_rr = add_prior(&mut a, &mut b, prior, &sh);
    damp_and_regularize(&mut a, basis, lambda, m, p);
    let normal_s = crate::util::secs(t1);
    Ok(Assembled {
        used,
        targets: targets_image,
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
        prior_rr,
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
) -> Result<StepResult, RegisterError> {
    fit_step_with_prior(basis, matches, targets_image, params, None)
}

/// [`fit_step`] with the rigid correction regularised by a prior on the pose: the objective
/// gains `κ/6 Σ |δ(qₖ) − zₖ|²` over the prior's pose pairs (linearized like the data rows).
pub fn fit_step_with_prior(
    basis: &LibrBasis,
    matches: &[Match],
    targets_image: &[[f64; 3]],
    params: &LibrParams,
    prior: Option<&PriorPairs>,
) -> Result<StepResult, RegisterError> {
    let asm = assemble(basis, matches, targets_image, params, prior)?;
    let t2 = Instant::now();
    let mut b = asm.b.clone();
    let llt = asm.a.llt(Side::Lower).map_err(|e| {
        RegisterError::IllConditioned(format!(
            "the normal equations are singular ({e:?}): the {} matches do not determine the basis weights and rigid correction (use λ > 0, or more spread-out matches)",
            asm.used.len()
        ))
    })?;
    llt.solve_in_place(b.as_mut());
    finish(basis, &asm, &b, t2)
}

/// The step's result from the solution `x` (p × 1: α, then the scaled rotation and the
/// translation) of an assembled system; `t_solve` is when its solve began (for the timings).
pub(super) fn finish(
    basis: &LibrBasis,
    asm: &Assembled<'_>,
    x: &Mat<f64>,
    t_solve: Instant,
) -> Result<StepResult, RegisterError> {
    let Assembled {
        used,
        cen,
        radius,
        m,
        p,
        rows,
        jt,
        rhs: rhs0,
        before,
        rows_s,
        normal_s,
        ..
    } = asm;
    let (cen, radius, m, p, rows) = (*cen, *radius, *m, *p, *rows);
    let b = x;
    if !(0..p).all(|i| b[(i, 0)].is_finite()) {
        return Err(RegisterError::IllConditioned(
            "the step produced non-finite values (ill-conditioned data)".into(),
        ));
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
    let lin = lin - rhs0;
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
    let after = residual_after(basis, asm, &alpha, &rigid_correction);
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
            rows_s: *rows_s,
            normal_s: *normal_s,
            solve_s: crate::util::secs(t_solve),
        },
    })
}

/// The weighted mean square residual of the used matches after the step: the model deformed by
/// `Φ α`, moved by the exact rigid correction, against the matches' targets (mm²).
fn residual_after(
    basis: &LibrBasis,
    asm: &Assembled<'_>,
    alpha: &[f64],
    rigid_correction: &Rigid,
) -> f64 {
    let m = asm.m;
    let mut after = 0.0;
    for mt in &asm.used {
        let mut q = mt.anchor;
        for (k, &v) in mt.nodes.iter().enumerate() {
            if mt.bary[k] == 0.0 {
                continue;
            }
            let base = 3 * v as usize;
            for ax in 0..3 {
                let row = &basis.phi[(base + ax) * m..(base + ax + 1) * m];
                q[ax] += mt.bary[k] * row.iter().zip(alpha).map(|(x, y)| x * y).sum::<f64>();
            }
        }
        let r = sub(rigid_correction.apply(q), targets_image_of(asm, mt));
        after += mt.weight / asm.wsum * dot(r, r);
    }
    after
}

fn targets_image_of(asm: &Assembled<'_>, mt: &Match) -> [f64; 3] {
    asm.targets[mt.point]
}
