//! Adaptive LIBR: surface tractions resolved finely where the data are.
//!
//! LIBR fits a fixed basis of 25 broad control loads; a tool pushing one spot of a held organ
//! makes a dent no broad load can express. This method fits a richer basis, and only where the
//! data can determine it:
//!
//! - **Several levels of resolution.** The basis has levels of control loads
//!   ([`LibrBasis::build_levels`], default 25 broad and 100 fine patches), and its energy matrix
//!   `E = ΦᵀKΦ` couples them, so `½αᵀEα` is the strain energy of the whole deformation whichever
//!   level expresses it.
//! - **Fine loads only where the data cover them** ([`select_columns`]): the broadest level is
//!   kept whole, a finer load only when the matched points near it span a surface (not a line of
//!   ultrasound contour points). The fit runs on the kept columns, restricted to the nodes that
//!   matching reads ([`restrict`]).
//! - **Coarse to fine** ([`AdaptiveParams::coarse_first`]): the broad level alone until it
//!   settles, then every level on the matches it leaves.
//! - **λ** is LIBR's, normalised by the broadest level's mean mode energy; a narrow patch costs
//!   less energy per millimetre than a broad one, so [`AdaptiveParams::fine_penalty`] can make the
//!   fine part cost more.
//!
//! **An evidence search for λ** ([`AdaptiveParams::lambda_range`] with low < high, off by
//! default): with the data rows `r = Jθ + ε`, `ε ~ N(0, τ²I)` and the prior
//! `α ~ N(0, τ²(λẼ)⁻¹)` (θ = α and the rigid correction, the latter with a flat prior), λ
//! maximises `log p(r | λ) = −½ (N − 6) log Q(λ) − ½ log det A(λ) + ½ p log λ + const` (τ²
//! profiled out), `A(λ) = JᵀJ + λẼ`, `Q(λ) = |r|² − bᵀA⁻¹b`, `b = Jᵀr`, N rows, p regularised
//! columns, on a log grid, one Cholesky factorization per value, every iteration. On data drawn
//! from the prior it recovers the prior's strength (`tests/adaptive.rs`); on registrations it
//! chooses λ far too small, because it counts every matched point as an independent observation
//! while closest-point misfits are strongly correlated along the surface (the fit's λ weighs the
//! *mean* squared misfit, so LIBR's 1e-3 over 500 points is a per-point prior precision of 0.5,
//! far above what independent noise would justify). [`AdaptiveParams::anneal_start`] anneals a
//! floor on λ over the iterations, as non-rigid ICP anneals its stiffness.
//!
//! The iterations are LIBR's ([`super::solve_with_limits`]): re-match on the deformed model, fit,
//! compose the rigid correction; they stop when the model stops moving
//! ([`FitParams::tolerance_mm`](super::FitParams::tolerance_mm)), when the fit has settled ([`super::settled`]), at the
//! iteration cap, or before a deadline.

use super::iterate::{Iterated, Stepper, iterate};
use super::*;
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::register::Match;
use faer::linalg::solvers::Solve;
use faer::{Mat, Side};
use std::time::Instant;

/// Parameters of adaptive LIBR (the fit's other settings, iterations and matching are
/// [`LibrParams`]'; its `regularization` is not read).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AdaptiveParams {
    /// Levels of control loads, broadest first: (count K, patch width). Default 25 and 100
    /// patches, each 1.25 × its level's spacing wide.
    pub levels: Vec<(usize, LoadWidth)>,
    /// A finer level's control load is kept when a matched point lies within `reach` × its
    /// patch width σ. Default 2.
    pub reach: f64,
    /// ... and when those points span a surface: their spread across their second principal
    /// axis is at least `spread` × σ ([`select_columns`]). Default 0.3.
    pub spread: f64,
    /// The evidence is maximised over λ on a log grid from `lambda_range.0` to `lambda_range.1`
    /// (λ as in [`FitParams::regularization`](super::FitParams::regularization), relative to the broadest level's mean mode
    /// energy); equal ends fix λ. Default 1e-3 to 1e-3 (fixed: see the module doc).
    pub lambda_range: (f64, f64),
    /// Grid points per decade. Default 2.
    pub lambda_per_decade: usize,
    /// Stiffness annealing: iteration k (from 0) uses at least `anneal_start × anneal_factor^k`,
    /// so the first fits, on closest-point matches to the undeformed model, are smooth and the
    /// finer detail comes as the matches improve (as in non-rigid ICP). Default 0 (none).
    pub anneal_start: f64,
    /// See `anneal_start`. Default 0.
    pub anneal_factor: f64,
    /// The finer levels' deformation costs this many times its strain energy: the prior is
    /// `λ/ē (αᵀEα + (ρ − 1) α_fᵀE_ffα_f)` with α_f the finer levels' weights and ē the broadest
    /// level's mean energy, so a broad deformation is regularised as in LIBR and a local one ρ
    /// times more than its energy says (a narrow patch costs less energy per millimetre than a
    /// broad one, so the energy alone does not hold fine loads back). Default 1.
    pub fine_penalty: f64,
    /// Coarse to fine: the first iterations fit the broadest level alone until it settles (at
    /// most half the iterations), then the finer levels join, kept near the data as matched
    /// then. Closest-point matches to the undeformed model are poor where the organ moved far,
    /// and fine loads fitted to them lock the error in. Default true.
    pub coarse_first: bool,
}

impl Default for AdaptiveParams {
    fn default() -> Self {
        Self {
            levels: vec![
                (25, LoadWidth::Spacing(1.25)),
                (100, LoadWidth::Spacing(1.25)),
            ],
            reach: 2.0,
            spread: 0.3,
            lambda_range: (1e-3, 1e-3),
            lambda_per_decade: 2,
            anneal_start: 0.0,
            anneal_factor: 0.0,
            fine_penalty: 1.0,
            coarse_first: true,
        }
    }
}

impl AdaptiveParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        if self.levels.is_empty() {
            return Err(RegisterError::Parameter(
                "levels must hold at least one level of control points".into(),
            ));
        }
        for (i, &(k, w)) in self.levels.iter().enumerate() {
            super::BasisParams::default()
                .with_level(k, w)
                .validate()
                .map_err(|e| RegisterError::Parameter(format!("levels[{i}]: {e}")))?;
        }
        if !(self.reach.is_finite() && self.reach > 0.0) {
            return Err(RegisterError::Parameter(format!(
                "reach must be finite and > 0, got {}",
                self.reach
            )));
        }
        if !(self.spread.is_finite() && self.spread >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "spread must be finite and >= 0, got {}",
                self.spread
            )));
        }
        let (lo, hi) = self.lambda_range;
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && hi >= lo) {
            return Err(RegisterError::Parameter(format!(
                "lambda_range must be finite with 0 < low <= high, got ({lo}, {hi})"
            )));
        }
        if !(self.anneal_start.is_finite() && self.anneal_start >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "anneal_start must be finite and >= 0, got {}",
                self.anneal_start
            )));
        }
        if !(self.anneal_factor.is_finite() && (0.0..1.0).contains(&self.anneal_factor)) {
            return Err(RegisterError::Parameter(format!(
                "anneal_factor must be in [0, 1), got {}",
                self.anneal_factor
            )));
        }
        if !(self.fine_penalty.is_finite() && self.fine_penalty >= 1.0) {
            return Err(RegisterError::Parameter(format!(
                "fine_penalty must be finite and >= 1, got {}",
                self.fine_penalty
            )));
        }
        if self.lambda_per_decade == 0 || self.lambda_per_decade > 20 {
            return Err(RegisterError::Parameter(format!(
                "lambda_per_decade must be in 1..=20, got {}",
                self.lambda_per_decade
            )));
        }
        Ok(())
    }

    /// The λ grid (ascending).
    pub fn lambda_grid(&self) -> Vec<f64> {
        let (lo, hi) = self.lambda_range;
        let steps = ((hi / lo).log10() * self.lambda_per_decade as f64).round() as usize;
        (0..=steps)
            .map(|i| lo * 10f64.powf(i as f64 / self.lambda_per_decade as f64))
            .collect()
    }
}

/// The columns of a multi-level basis a registration keeps: every column of the first level's
/// control points (the first `first_level` of them) and of each finer control point whose patch
/// the matched points *cover*: within `reach` × its width σ of it they span a surface, the
/// smaller of their two largest spreads (standard deviations across the principal axes) at
/// least `spread` × σ. A line of points (an ultrasound plane's contour) or a few stray ones do
/// not determine a fine load. The effect columns are always kept. Returns column indices,
/// ascending.
pub fn select_columns(
    basis: &LibrBasis,
    mesh: &TetMesh,
    first_level: usize,
    matches: &[Match],
    reach: f64,
    spread: f64,
) -> Vec<usize> {
    let nodes = mesh.nodes();
    let anchors: Vec<[f64; 3]> = matches
        .iter()
        .filter(|m| m.weight > 0.0)
        .map(|m| m.anchor)
        .collect();
    let mut cols = Vec::new();
    for (k, &c) in basis.control_nodes.iter().enumerate() {
        let keep = k < first_level || {
            let sigma = basis.control_width(k);
            let r = reach * sigma;
            let p = nodes[c as usize];
            let near: Vec<[f64; 3]> = anchors
                .iter()
                .copied()
                .filter(|&a| dist2(a, p) <= r * r)
                .collect();
            near.len() >= 6 && second_spread(&near) >= spread * sigma
        };
        if keep {
            cols.extend(3 * k..3 * k + 3);
        }
    }
    cols.extend(basis.libr_columns()..basis.columns());
    cols
}

/// The standard deviation of points along their second principal axis (mm).
fn second_spread(points: &[[f64; 3]]) -> f64 {
    let n = points.len() as f64;
    let mut c = [0.0; 3];
    for p in points {
        for a in 0..3 {
            c[a] += p[a] / n;
        }
    }
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    for p in points {
        let d = nalgebra::Vector3::new(p[0] - c[0], p[1] - c[1], p[2] - c[2]);
        cov += d * d.transpose() / n;
    }
    let mut e: Vec<f64> = cov.symmetric_eigenvalues().iter().copied().collect();
    e.sort_by(f64::total_cmp);
    e[1].max(0.0).sqrt()
}

/// The basis restricted to some columns and to the rows of some nodes (`rows[i]` becomes node
/// `i` of the result): what one registration's fit reads.
pub fn restrict(basis: &LibrBasis, cols: &[usize], rows: &[u32]) -> LibrBasis {
    let m = basis.columns();
    let q = cols.len();
    let mut phi = vec![0.0; 3 * rows.len() * q];
    for (i, &v) in rows.iter().enumerate() {
        for a in 0..3 {
            let src = &basis.phi[(3 * v as usize + a) * m..(3 * v as usize + a + 1) * m];
            let dst = &mut phi[(3 * i + a) * q..(3 * i + a + 1) * q];
            for (d, &j) in dst.iter_mut().zip(cols) {
                *d = src[j];
            }
        }
    }
    let mut energy = vec![0.0; q * q];
    for (i, &a) in cols.iter().enumerate() {
        for (j, &b) in cols.iter().enumerate() {
            energy[i * q + j] = basis.energy[a * m + b];
        }
    }
    let libr = basis.libr_columns();
    let effect_labels: Vec<String> = cols
        .iter()
        .filter(|&&j| j >= libr)
        .map(|&j| basis.effect_labels[j - libr].clone())
        .collect();
    let control_nodes: Vec<u32> = cols
        .iter()
        .filter(|&&j| j < libr && j % 3 == 0)
        .map(|&j| basis.control_nodes[j / 3])
        .collect();
    LibrBasis {
        control_nodes,
        nodes: rows.len(),
        phi,
        energy,
        load_scale: cols.iter().map(|&j| basis.load_scale[j]).collect(),
        load_width_mm: basis.load_width_mm,
        control_width_mm: Vec::new(),
        effect_labels,
        physics_hash: basis.physics_hash.clone(),
        mesh_hash: basis.mesh_hash.clone(),
        params_hash: basis.params_hash.clone(),
        timings: BasisTimings::default(),
    }
}

/// The evidence-maximising λ of an assembled system with no regularisation in it yet: for each λ
/// of the grid the Cholesky factorization of `A + λ/ē E`, the log evidence (module doc) and the
/// solution. Returns (λ, solution, log evidence) of the best, or an error when no λ gave a
/// definite system.
fn choose_lambda(
    basis: &LibrBasis,
    asm: &Assembled<'_>,
    grid: &[f64],
    escale: f64,
) -> Result<(f64, Mat<f64>, f64), RegisterError> {
    let m = basis.libr_columns();
    let rows = asm.rows as f64 + if asm.prior_rr > 0.0 { 18.0 } else { 0.0 };
    let rr = asm.before + asm.prior_rr;
    let dof = (rows - 6.0).max(1.0);
    let mut best: Option<(f64, Mat<f64>, f64)> = None;
    let mut a = asm.a.clone();
    let q = asm.m;
    for &lambda in grid {
        let f = lambda / escale;
        for i in 0..q {
            for j in 0..=i {
                a[(i, j)] = asm.a[(i, j)] + f * basis.energy[i * q + j];
            }
        }
        let Ok(llt) = a.llt(Side::Lower) else {
            continue;
        };
        let mut x = asm.b.clone();
        llt.solve_in_place(x.as_mut());
        let fit: f64 = (0..asm.p).map(|i| asm.b[(i, 0)] * x[(i, 0)]).sum();
        let qmin = (rr - fit).max(1e-12 * rr.max(1e-300));
        let l = llt.L();
        let logdet: f64 = (0..asm.p).map(|i| 2.0 * l[(i, i)].ln()).sum();
        let ev = -0.5 * dof * qmin.ln() - 0.5 * logdet + 0.5 * m as f64 * f.ln();
        if !ev.is_finite() {
            continue;
        }
        if best.as_ref().is_none_or(|b| ev > b.2) {
            best = Some((lambda, x, ev));
        }
    }
    best.ok_or_else(|| {
        RegisterError::IllConditioned(format!(
            "the normal equations are singular for every λ in [{}, {}]: the {} matches do not determine the fit",
            grid.first().copied().unwrap_or(0.0),
            grid.last().copied().unwrap_or(0.0),
            asm.used.len()
        ))
    })
}

/// One adaptive step on a restricted basis: the system assembled without regularisation, λ by
/// evidence over `grid` (λ relative to `escale`, or the basis's mean energy when None), the
/// step's result and the λ chosen.
pub fn adaptive_step(
    basis: &LibrBasis,
    matches: &[Match],
    targets_image: &[[f64; 3]],
    params: &LibrParams,
    grid: &[f64],
    escale: Option<f64>,
    prior: Option<&PriorPairs>,
) -> Result<(StepResult, f64), RegisterError> {
    let mut unregularised = *params;
    unregularised.fit.regularization = 0.0;
    let asm = assemble(basis, matches, targets_image, &unregularised, prior)?;
    let t2 = Instant::now();
    let escale = escale.unwrap_or_else(|| basis.energy_scale());
    let (lambda, x, _) = choose_lambda(basis, &asm, grid, escale)?;
    Ok((finish(basis, &asm, &x, t2)?, lambda))
}

/// Adaptive LIBR's model: the multi-level basis ([`LibrBasis::build_levels`]), the number of
/// control points of its broadest level, and the adaptive settings.
#[derive(Debug, Clone, Copy)]
pub struct MultiLevel<'a> {
    /// The multi-level basis.
    pub basis: &'a LibrBasis,
    /// The number of control points of its broadest level (its first columns).
    pub first_level: usize,
    /// The adaptive settings.
    pub adaptive: &'a AdaptiveParams,
}

/// Adaptive LIBR (see the module doc): like [`solve_with_limits`] on the multi-level basis
/// `levels`, with the columns kept chosen from the first matching and λ chosen by evidence at
/// every iteration. [`LibrInfo::regularization`] reports the last λ and [`LibrInfo::columns`] the
/// columns kept.
pub fn solve_adaptive(
    mesh: &TetMesh,
    levels: MultiLevel<'_>,
    params: &LibrParams,
    measured_physical: &[[f64; 3]],
    initial: &Rigid,
    run: RunLimits<'_>,
    rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, RegisterError>,
) -> Result<LibrSolution, RegisterError> {
    let MultiLevel {
        basis,
        first_level,
        adaptive,
    } = levels;
    // The rows the fit reads: the active nodes, and any other node a match reads (added when
    // one does, and the restricted basis rebuilt).
    let (rows, row_of) = adaptive_rows(mesh, basis, params, adaptive, &run)?;
    let t0 = Instant::now();
    let mut fit = Kept {
        mesh,
        params,
        adaptive,
        measured_physical,
        run,
        cx: Context::new(mesh, basis, first_level, adaptive),
        grid: adaptive.lambda_grid(),
        rows,
        row_of,
        kept: None,
        alpha: Vec::new(),
        floor: adaptive.anneal_start,
        escale: 1.0,
        lambda: 0.0,
        phases: Phases::new(adaptive),
        u: vec![0.0; 3 * basis.nodes],
    };
    let limits = (run.deadline, run.held_out.is_some());
    let Iterated { t, mut info, last } = iterate(&mut fit, params, initial, limits, rematch)?;
    let kept = fit.kept.expect("at least one iteration ran");
    info.held_out = adaptive_held_out(run.held_out, &kept.1, last.as_ref(), params);
    let (full, u) = adaptive_summary(
        &mut info,
        basis,
        &kept,
        &fit.alpha,
        fit.escale,
        fit.phases.start,
        &run,
    );
    info.total_s = crate::util::secs(t0);
    Ok(LibrSolution {
        alpha: full,
        u,
        image_to_physical: t,
        info,
    })
}

/// Adaptive LIBR's step ([`iterate`]): the rows a match reads added (and the restricted basis
/// rebuilt when they grow or a phase asks), λ chosen by evidence above the annealing floor, the
/// local displacement written back; it stops as its phases say.
struct Kept<'a> {
    mesh: &'a TetMesh,
    params: &'a LibrParams,
    adaptive: &'a AdaptiveParams,
    measured_physical: &'a [[f64; 3]],
    run: RunLimits<'a>,
    cx: Context<'a>,
    grid: Vec<f64>,
    rows: Vec<u32>,
    row_of: Vec<u32>,
    /// The columns kept and the basis restricted to them and to the rows.
    kept: Option<(Vec<usize>, LibrBasis)>,
    alpha: Vec<f64>,
    floor: f64,
    escale: f64,
    /// The last step's λ.
    lambda: f64,
    phases: Phases,
    u: Vec<f64>,
}

impl Stepper for Kept<'_> {
    type Last = (LastSystem, f64, f64);

    fn u(&self) -> &[f64] {
        &self.u
    }

    fn step(
        &mut self,
        matches: Vec<Match>,
        t: &Rigid,
        info: &mut LibrInfo,
    ) -> Result<(StepResult, f64, Self::Last), RegisterError> {
        let before = self.rows.len();
        extend_rows(&matches, &mut self.rows, &mut self.row_of);
        if self.kept.is_none() || self.rows.len() != before || self.phases.rebuild {
            let ta = Instant::now();
            let (cols, r, e) =
                self.cx
                    .rebuild(&mut self.phases, self.kept.as_ref(), &matches, &self.rows);
            (self.kept, self.escale) = (Some((cols, r)), e);
            info.assemble_s += crate::util::secs(ta);
        }
        let (_, reduced) = self.kept.as_ref().expect("set above");
        let (local, targets) = self.cx.local_matches(
            self.measured_physical,
            t,
            self.run.hold,
            matches,
            &self.row_of,
        )?;
        let prior = PriorPairs::of(self.run.rigid_prior, t);
        let g = grid_above(&self.grid, self.floor);
        self.floor *= self.adaptive.anneal_factor;
        let (step, lambda) = adaptive_step(
            reduced,
            &local,
            &targets,
            self.params,
            &g,
            Some(self.escale),
            prior.as_ref(),
        )?;
        let local_u = reduced.displacement(&step.alpha);
        let moved = apply_local(
            self.mesh,
            &self.rows,
            &mut self.u,
            &local_u,
            &step.rigid_correction,
        );
        self.lambda = lambda;
        Ok((step, moved, ((local, targets, prior), lambda, self.escale)))
    }

    fn keep(&mut self, step: StepResult, info: &mut LibrInfo) {
        info.regularization = self.lambda;
        self.alpha = step.alpha;
    }

    fn done(&mut self, info: &mut LibrInfo, moved: f64, params: &LibrParams) -> bool {
        self.phases.advance(info, moved, params)
    }
}

/// The held-out check ([`held_out_of_last`]) of the last system, on the restricted basis, λ and
/// energy scale it was fitted with.
fn adaptive_held_out(
    folds: Option<&Folds>,
    reduced: &LibrBasis,
    last: Option<&(LastSystem, f64, f64)>,
    params: &LibrParams,
) -> Option<Result<HeldOut, String>> {
    let (system, lambda, escale) = last?;
    let model = FitModel::Basis {
        basis: reduced,
        lambda: *lambda,
        escale: *escale,
    };
    held_out_of_last(folds, Some(system), model, params)
}

/// What every adaptive iteration reads and does not change.
struct Context<'a> {
    mesh: &'a TetMesh,
    basis: &'a LibrBasis,
    first_level: usize,
    adaptive: &'a AdaptiveParams,
}

impl<'a> Context<'a> {
    /// The context of one adaptive solve.
    fn new(
        mesh: &'a TetMesh,
        basis: &'a LibrBasis,
        first_level: usize,
        adaptive: &'a AdaptiveParams,
    ) -> Self {
        Self {
            mesh,
            basis,
            first_level,
            adaptive,
        }
    }

    /// The columns to keep ([`Self::columns`]) and the basis restricted to them and to `rows`,
    /// with its energy scale.
    fn rebuild(
        &self,
        phases: &mut Phases,
        kept: Option<&(Vec<usize>, LibrBasis)>,
        matches: &[Match],
        rows: &[u32],
    ) -> (Vec<usize>, LibrBasis, f64) {
        let cols = self.columns(phases, kept, matches);
        let (r, escale) =
            restricted_basis(self.basis, self.first_level, self.adaptive, &cols, rows);
        (cols, r, escale)
    }

    /// The matches with the held pairs appended, their nodes moved onto the restricted rows, and
    /// the targets (the measured points in the image frame of `t`).
    fn local_matches(
        &self,
        measured_physical: &[[f64; 3]],
        t: &Rigid,
        hold: Option<&Hold>,
        matches: Vec<Match>,
        row_of: &[u32],
    ) -> Result<(Vec<Match>, Vec<[f64; 3]>), RegisterError> {
        let inv = t.inverse();
        let mut targets: Vec<[f64; 3]> = measured_physical.iter().map(|&p| inv.apply(p)).collect();
        // The held pairs join after the columns were chosen (they are not data to resolve).
        let mut local = matches;
        if let Some(h) = hold {
            h.append(self.mesh, &mut local, &mut targets, &inv);
        }
        // The matches on the restricted rows.
        for (k, mt) in local.iter_mut().enumerate() {
            for v in &mut mt.nodes {
                let r = row_of.get(*v as usize).copied().unwrap_or(u32::MAX);
                if r == u32::MAX {
                    return Err(RegisterError::Inconsistent(format!(
                        "match {k} reads node {v}, out of range ({} nodes)",
                        self.basis.nodes
                    )));
                }
                *v = r;
            }
        }
        Ok((local, targets))
    }

    /// The columns to keep: the broadest level in the coarse phase, the ones kept while the
    /// fine phase goes on, else those the matches cover; the pending rebuild is done.
    fn columns(
        &self,
        phases: &mut Phases,
        kept: Option<&(Vec<usize>, LibrBasis)>,
        matches: &[Match],
    ) -> Vec<usize> {
        let basis = self.basis;
        let cols = match (kept, phases.phase, phases.rebuild) {
            (_, 0, _) => (0..3 * self.first_level.min(basis.control_nodes.len()))
                .chain(basis.libr_columns()..basis.columns())
                .collect(),
            (Some((c, _)), _, false) => c.clone(),
            _ => select_columns(
                basis,
                self.mesh,
                self.first_level,
                matches,
                self.adaptive.reach,
                self.adaptive.spread,
            ),
        };
        phases.rebuild = false;
        cols
    }
}

/// Validates the run (no offset) and returns the rows the fit starts from (the active and the
/// held nodes) and each node's row (`u32::MAX`: none).
fn adaptive_rows(
    mesh: &TetMesh,
    basis: &LibrBasis,
    params: &LibrParams,
    adaptive: &AdaptiveParams,
    run: &RunLimits<'_>,
) -> Result<(Vec<u32>, Vec<u32>), RegisterError> {
    params.validate()?;
    adaptive.validate()?;
    if run.offset.is_some() {
        return Err(RegisterError::Parameter(
            "adaptive LIBR starts from the undeformed model (no offset)".into(),
        ));
    }
    let mut rows: Vec<u32> = checked_active(mesh, basis, params, run.active)?;
    if let Some(h) = run.hold {
        h.validate(basis.nodes)?;
        rows.extend(&h.nodes);
        rows.sort_unstable();
        rows.dedup();
    }
    let mut row_of = vec![u32::MAX; basis.nodes];
    for (i, &v) in rows.iter().enumerate() {
        row_of[v as usize] = i as u32;
    }
    Ok((rows, row_of))
}

/// Appends to `rows` every node a match reads that has no row yet.
fn extend_rows(matches: &[Match], rows: &mut Vec<u32>, row_of: &mut [u32]) {
    for mt in matches {
        for &v in &mt.nodes {
            if row_of.get(v as usize) == Some(&u32::MAX) {
                row_of[v as usize] = rows.len() as u32;
                rows.push(v);
            }
        }
    }
}

/// The basis restricted to `cols` and `rows`, the finer levels' energy scaled by the fine
/// penalty, and λ's energy scale (the broadest level's mean mode energy).
fn restricted_basis(
    basis: &LibrBasis,
    first_level: usize,
    adaptive: &AdaptiveParams,
    cols: &[usize],
    rows: &[u32],
) -> (LibrBasis, f64) {
    let mut r = restrict(basis, cols, rows);
    // The finer levels' extra cost: E + (ρ − 1) blockdiag(0, E_ff).
    let q = cols.len();
    let fine = |j: usize| cols[j] >= 3 * first_level && cols[j] < basis.libr_columns();
    for i in 0..q {
        for j in 0..q {
            if fine(i) && fine(j) {
                r.energy[i * q + j] *= adaptive.fine_penalty;
            }
        }
    }
    let coarse = 3 * first_level.min(basis.control_nodes.len());
    let escale = (0..coarse)
        .map(|i| basis.energy[i * basis.columns() + i])
        .sum::<f64>()
        / coarse.max(1) as f64;
    (r, escale)
}

/// The grid above the annealing floor (the floor itself when it is above the grid).
fn grid_above(grid: &[f64], floor: f64) -> Vec<f64> {
    let mut g: Vec<f64> = grid.iter().copied().filter(|&l| l >= floor).collect();
    if g.is_empty() || floor > 0.0 && g[0] > floor * 1.0001 {
        g.insert(0, floor);
    }
    g
}

/// Copies the step's displacement of the restricted rows into `u`; returns the largest
/// movement in the image frame of the old estimate, `|δ(X + u_new) − (X + u_old)|`.
fn apply_local(mesh: &TetMesh, rows: &[u32], u: &mut [f64], local_u: &[f64], delta: &Rigid) -> f64 {
    let mut moved = 0.0f64;
    for (i, &v) in rows.iter().enumerate() {
        let x = mesh.nodes()[v as usize];
        let k = 3 * v as usize;
        let old = [0, 1, 2].map(|a| x[a] + u[k + a]);
        let new = delta.apply([0, 1, 2].map(|a| x[a] + local_u[3 * i + a]));
        moved = moved.max(dist2(old, new).sqrt());
        u[k..k + 3].copy_from_slice(&local_u[3 * i..3 * i + 3]);
    }
    moved
}

/// Coarse to fine: phase 0 fits the broadest level alone, phase 1 every level.
struct Phases {
    phase: usize,
    /// The iteration the current phase began at.
    start: usize,
    /// Whether the columns must be chosen again (the fine phase just began).
    rebuild: bool,
}

impl Phases {
    /// The first phase: coarse when asked for and there are finer levels.
    fn new(adaptive: &AdaptiveParams) -> Self {
        let phase = if adaptive.coarse_first && adaptive.levels.len() > 1 {
            0
        } else {
            1
        };
        Self {
            phase,
            start: 0,
            rebuild: false,
        }
    }

    /// After an iteration: the coarse phase hands over to the fine one when it calms down (or
    /// has run half the iterations); returns whether to stop (setting `info.converged`).
    fn advance(&mut self, info: &mut LibrInfo, moved: f64, params: &LibrParams) -> bool {
        let calm = moved <= params.fit.tolerance_mm
            || settled(
                &info.rms_history_mm[self.start..],
                &info.movement_history_mm[self.start..],
            ) && !shrinking(&info.movement_history_mm[self.start..]);
        if self.phase == 0 {
            if calm || info.iterations >= params.fit.max_iterations / 2 {
                self.phase = 1;
                self.start = info.iterations;
                self.rebuild = true;
            }
        } else if calm {
            info.converged = moved <= params.fit.tolerance_mm;
            return true;
        }
        false
    }
}

/// Fills the summary fields of `info` and returns α on the full basis and the displacement.
fn adaptive_summary(
    info: &mut LibrInfo,
    basis: &LibrBasis,
    kept: &(Vec<usize>, LibrBasis),
    alpha: &[f64],
    escale: f64,
    phase_start: usize,
    run: &RunLimits<'_>,
) -> (Vec<f64>, Vec<f64>) {
    info.settled = info.converged
        || settled(
            &info.rms_history_mm[phase_start..],
            &info.movement_history_mm[phase_start..],
        );
    let (cols, reduced) = kept;
    info.prior_mm2 = info.regularization * 2.0 * reduced.strain_energy(alpha) / escale;
    info.columns = cols.len();
    let mut full = vec![0.0; basis.columns()];
    for (&j, &a) in cols.iter().zip(alpha) {
        full[j] = a;
    }
    info.held_nodes = run.hold.map_or(0, |h| h.nodes.len());
    info.strain_energy_uj = basis.strain_energy(&full);
    let u = basis.displacement(&full);
    (full, u)
}
