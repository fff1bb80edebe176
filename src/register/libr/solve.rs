//! LIBR's iterations: re-match, fit a step, compose its rigid correction, until the model stops
//! moving or a deadline comes.

use super::iterate::{Iterated, Stepper, iterate};
use super::*;
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::register::Match;
use crate::register::prior::RigidPrior;
use std::time::Instant;

/// What [`solve`] did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct LibrInfo {
    /// Iterations run (matching + step).
    pub iterations: usize,
    /// True when the largest node movement of the last iteration was below the tolerance.
    pub converged: bool,
    /// True when the fit has settled: it converged, or its objective stopped falling (see
    /// [`settled`]: re-matching can make the nodes cycle by more than the tolerance around a
    /// fit that no longer improves, which is not a failure to converge).
    pub settled: bool,
    /// True when the iterations stopped early because the next one would have passed the
    /// caller's deadline ([`solve_with_limits`]).
    pub stopped_at_deadline: bool,
    /// Weighted residual RMS after each iteration (mm).
    pub rms_history_mm: Vec<f64>,
    /// Largest node movement of each iteration (mm).
    pub movement_history_mm: Vec<f64>,
    /// Final weighted residual RMS (mm).
    pub rms_mm: f64,
    /// Strain energy ½αᵀEα of the fitted deformation Φα (µJ = mN·mm; effect columns carry no
    /// energy): how hard the fit had to bend the organ.
    pub strain_energy_uj: f64,
    /// Total time in the matching function (s).
    pub matching_s: f64,
    /// Total time forming the step's rows and normal equations (s).
    pub assemble_s: f64,
    /// Total time in the step's solves (s).
    pub solve_s: f64,
    /// Total time (s).
    pub total_s: f64,
    /// The strain-energy weight λ of the last iteration: LIBR's fixed
    /// [`FitParams::regularization`](super::FitParams::regularization), or what adaptive LIBR chose ([`solve_adaptive`]); 0 when
    /// not recorded.
    pub regularization: f64,
    /// Basis columns the fit used (adaptive LIBR keeps those near the data; 0 when not
    /// recorded).
    pub columns: usize,
    /// The fit's regularisation term at the end, `λ αᵀẼα` (mm², comparable with the mean squared
    /// misfit; the pipeline's pose choice adds it to the misfit).
    pub prior_mm2: f64,
    /// Nodes a soft hold kept in place ([`Hold`]; 0: none).
    pub held_nodes: usize,
    /// The last step's held-out prediction ([`held_out`]; when [`RunLimits::held_out`] asked),
    /// or why it could not be measured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub held_out: Option<Result<HeldOut, String>>,
}

/// The result of [`solve`].
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
/// `params.tolerance_mm` in an iteration, the fit has [`settled`] without its movement still
/// [`shrinking`], or `params.max_iterations` is reached. `mesh` must be
/// the basis's mesh (its node positions measure the movement).
pub fn solve(
    mesh: &TetMesh,
    basis: &LibrBasis,
    params: &LibrParams,
    measured_physical: &[[f64; 3]],
    initial: &Rigid,
    rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, RegisterError>,
) -> Result<LibrSolution, RegisterError> {
    solve_with_limits(
        mesh,
        basis,
        params,
        measured_physical,
        initial,
        RunLimits::default(),
        rematch,
    )
}

/// What [`solve_with_limits`] updates between matchings and when it must stop.
#[derive(Debug, Clone, Copy, Default)]
pub struct RunLimits<'a> {
    /// Nodes whose displacement `rematch` reads (None: all).
    pub active: Option<&'a [u32]>,
    /// Stop before an iteration that would end past this instant (None: no deadline).
    pub deadline: Option<Instant>,
    /// A displacement the fit starts from and keeps (node-major 3n, image frame; None: zero):
    /// the result is `offset + Φα`, and the strain energy regularises `Φα` alone.
    pub offset: Option<&'a [f64]>,
    /// A prior on the rigid pose (a trusted start, [`crate::register::prior`]): every step's
    /// rigid correction is regularised towards it (None: fitted freely).
    pub rigid_prior: Option<&'a RigidPrior>,
    /// A soft hold on nodes the data do not see ([`Hold`]; None: none).
    pub hold: Option<&'a Hold>,
    /// Measure the final fit's held-out prediction on these folds ([`held_out`]; None: not
    /// measured), reported as [`LibrInfo::held_out`].
    pub held_out: Option<&'a Folds>,
}

/// A soft hold: nodes that should stay where a trusted pose puts them (an organ held in place,
/// the surface far from what the camera sees). Every iteration appends one point-to-point pair
/// per held node, node → its held position mapped into the current image frame, so the held
/// nodes' total movement (deformation and rigid correction together) is penalised like a
/// misfit. The pairs share `weight` × the matches' total weight, so the hold neither drowns the
/// data nor vanishes when there are many points.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Hold {
    /// The held nodes.
    pub nodes: Vec<u32>,
    /// Where each is held (physical frame, mm).
    pub physical: Vec<[f64; 3]>,
    /// Total weight of the held pairs relative to the matches' total weight (> 0).
    pub weight: f64,
}

impl Hold {
    /// Checks the hold against a basis of `nodes` nodes; the message names the field.
    pub fn validate(&self, nodes: usize) -> Result<(), RegisterError> {
        if self.nodes.len() != self.physical.len() {
            return Err(RegisterError::Inconsistent(format!(
                "hold: {} nodes but {} positions",
                self.nodes.len(),
                self.physical.len()
            )));
        }
        if let Some(v) = self.nodes.iter().find(|&&v| v as usize >= nodes) {
            return Err(RegisterError::Inconsistent(format!(
                "hold: node {v} out of range ({nodes} nodes)"
            )));
        }
        if self.physical.iter().flatten().any(|x| !x.is_finite()) {
            return Err(RegisterError::Inconsistent(
                "hold: a held position is not finite".into(),
            ));
        }
        if !(self.weight.is_finite() && self.weight > 0.0) {
            return Err(RegisterError::Parameter(format!(
                "hold weight must be finite and > 0, got {}",
                self.weight
            )));
        }
        Ok(())
    }

    /// Appends the held pairs to `matches` and their targets (image frame of `inv`'s inverse,
    /// i.e. `inv` maps physical → image) to `targets`.
    pub fn append(
        &self,
        mesh: &TetMesh,
        matches: &mut Vec<Match>,
        targets: &mut Vec<[f64; 3]>,
        inv: &Rigid,
    ) {
        if self.nodes.is_empty() {
            return;
        }
        let data: f64 = matches.iter().map(|m| m.weight).sum();
        let w = self.weight * data.max(1e-12) / self.nodes.len() as f64;
        for (&v, &p) in self.nodes.iter().zip(&self.physical) {
            matches.push(Match {
                point: targets.len(),
                anchor: mesh.nodes()[v as usize],
                nodes: [v; 4],
                bary: [1.0, 0.0, 0.0, 0.0],
                weight: w,
                normal: [0.0; 3],
            });
            targets.push(inv.apply(p));
        }
    }
}

/// [`solve`], updating between matchings only the displacement of `active` nodes (those
/// `rematch` reads, e.g. [`crate::register::correspondence::Correspondence::active_nodes`]; `None`: all)
/// and measuring the movement there; the returned `u` is complete. On a 9,000-node liver the
/// boundary and vessel tets are about half the nodes, and `Φα` is the largest cost of an
/// iteration after matching. With a `deadline`, the iterations stop before one that the last
/// one's duration says would end past it ([`LibrInfo::stopped_at_deadline`]); at least one
/// iteration always runs.
pub fn solve_with_limits(
    mesh: &TetMesh,
    basis: &LibrBasis,
    params: &LibrParams,
    measured_physical: &[[f64; 3]],
    initial: &Rigid,
    run: RunLimits<'_>,
    rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, RegisterError>,
) -> Result<LibrSolution, RegisterError> {
    let RunLimits {
        active,
        deadline,
        offset,
        rigid_prior,
        hold,
        held_out: folds,
    } = run;
    check_hold_and_offset(basis, hold, offset)?;
    params.validate()?;
    let active = checked_active(mesh, basis, params, active)?;
    let t0 = Instant::now();
    let mut fit = Whole {
        mesh,
        basis,
        params,
        measured_physical,
        active: &active,
        hold,
        offset,
        rigid_prior,
        u: offset.map_or_else(|| vec![0.0; 3 * basis.nodes], <[f64]>::to_vec),
        alpha: vec![0.0; basis.columns()],
    };
    let limits = (deadline, folds.is_some());
    let Iterated { t, mut info, last } = iterate(&mut fit, params, initial, limits, rematch)?;
    let alpha = fit.alpha;
    finish_info(&mut info, basis, params, hold, &alpha);
    let model = FitModel::Basis {
        basis,
        lambda: params.fit.regularization,
        escale: basis.energy_scale(),
    };
    info.held_out = held_out_of_last(folds, last.as_ref(), model, params);
    let u = full_displacement(basis, &alpha, offset);
    info.total_s = crate::util::secs(t0);
    Ok(LibrSolution {
        alpha,
        u,
        image_to_physical: t,
        info,
    })
}

/// Plain LIBR's step ([`iterate`]): the whole basis, the active nodes' displacement replaced by
/// `Φα` (plus the offset); it stops at the tolerance, or once the fit has [`settled`] without
/// its movement still [`shrinking`].
struct Whole<'a> {
    mesh: &'a TetMesh,
    basis: &'a LibrBasis,
    params: &'a LibrParams,
    measured_physical: &'a [[f64; 3]],
    active: &'a [u32],
    hold: Option<&'a Hold>,
    offset: Option<&'a [f64]>,
    rigid_prior: Option<&'a RigidPrior>,
    u: Vec<f64>,
    alpha: Vec<f64>,
}

impl Stepper for Whole<'_> {
    type Last = LastSystem;

    fn u(&self) -> &[f64] {
        &self.u
    }

    fn step(
        &mut self,
        mut matches: Vec<Match>,
        t: &Rigid,
        _: &mut LibrInfo,
    ) -> Result<(StepResult, f64, LastSystem), RegisterError> {
        let targets = step_targets(
            self.mesh,
            self.measured_physical,
            t,
            self.hold,
            self.offset,
            &mut matches,
        );
        let prior = PriorPairs::of(self.rigid_prior, t);
        let step =
            fit_step_with_prior(self.basis, &matches, &targets, self.params, prior.as_ref())?;
        let u_new =
            stepped_displacement(self.basis, &step.alpha, self.active, &self.u, self.offset);
        let moved = movement(
            self.mesh,
            self.active,
            &self.u,
            &u_new,
            &step.rigid_correction,
        );
        self.u = u_new;
        Ok((step, moved, (matches, targets, prior)))
    }

    fn keep(&mut self, step: StepResult, _: &mut LibrInfo) {
        self.alpha = step.alpha;
    }

    fn done(&mut self, info: &mut LibrInfo, moved: f64, params: &LibrParams) -> bool {
        if moved <= params.fit.tolerance_mm {
            info.converged = true;
            return true;
        }
        // Settled: the objective stopped falling and the model is not running away; what is
        // left is re-matching cycling around the fit (on the paper liver no fit ever reached
        // the tolerance: every registration ran the 20 iterations).
        settled(&info.rms_history_mm, &info.movement_history_mm)
            && !shrinking(&info.movement_history_mm)
    }
}

impl PriorPairs {
    /// The rigid prior's pairs for the pose `t` (None without a prior).
    pub(super) fn of(prior: Option<&RigidPrior>, t: &Rigid) -> Option<Self> {
        prior.map(|p| Self {
            pairs: p.image_pairs(t),
            weight: p.weight(),
        })
    }
}

/// Records an iteration's step (its timings, residual and the movement it made).
pub(super) fn record(info: &mut LibrInfo, step: &StepResult, moved: f64) {
    info.assemble_s += step.timings.rows_s + step.timings.normal_s;
    info.solve_s += step.timings.solve_s;
    info.iterations += 1;
    info.rms_history_mm.push(step.rms_mm);
    info.movement_history_mm.push(moved);
    info.rms_mm = step.rms_mm;
}

/// Whether another iteration, lasting as long as the one begun at `tm`, would end past the
/// deadline (setting [`LibrInfo::stopped_at_deadline`]); the last one's duration predicts the
/// next.
pub(super) fn past_deadline(
    info: &mut LibrInfo,
    deadline: Option<Instant>,
    params: &LibrParams,
    tm: Instant,
) -> bool {
    if let Some(d) = deadline {
        let now = Instant::now();
        if info.iterations < params.fit.max_iterations && now + (now - tm) > d {
            info.stopped_at_deadline = true;
            return true;
        }
    }
    false
}

/// The complete displacement `Φα`, plus the offset.
fn full_displacement(basis: &LibrBasis, alpha: &[f64], offset: Option<&[f64]>) -> Vec<f64> {
    let mut u = basis.displacement(alpha);
    if let Some(o) = offset {
        for (x, y) in u.iter_mut().zip(o) {
            *x += y;
        }
    }
    u
}

/// Checks the hold and the offset (3n finite values) against the basis.
fn check_hold_and_offset(
    basis: &LibrBasis,
    hold: Option<&Hold>,
    offset: Option<&[f64]>,
) -> Result<(), RegisterError> {
    if let Some(h) = hold {
        h.validate(basis.nodes)?;
    }
    if let Some(o) = offset {
        if o.len() != 3 * basis.nodes {
            return Err(RegisterError::Inconsistent(format!(
                "offset has {} values, the basis needs {}",
                o.len(),
                3 * basis.nodes
            )));
        }
        if o.iter().any(|x| !x.is_finite()) {
            return Err(RegisterError::Inconsistent("offset is not finite".into()));
        }
    }
    Ok(())
}

/// The measured points in the image frame of `t`, with the held pairs appended (to `matches`
/// too) and the offset taken off.
pub(super) fn step_targets(
    mesh: &TetMesh,
    measured_physical: &[[f64; 3]],
    t: &Rigid,
    hold: Option<&Hold>,
    offset: Option<&[f64]>,
    matches: &mut Vec<Match>,
) -> Vec<[f64; 3]> {
    let inv = t.inverse();
    let mut targets: Vec<[f64; 3]> = measured_physical.iter().map(|&p| inv.apply(p)).collect();
    if let Some(h) = hold {
        h.append(mesh, matches, &mut targets, &inv);
    }
    if let Some(o) = offset {
        // Fit Φα to what the offset leaves.
        offset_targets(matches, &mut targets, o);
    }
    targets
}

/// `u` with the active nodes' displacement replaced by `Φα` (plus the offset).
fn stepped_displacement(
    basis: &LibrBasis,
    alpha: &[f64],
    active: &[u32],
    u: &[f64],
    offset: Option<&[f64]>,
) -> Vec<f64> {
    let mut u_new = u.to_vec();
    basis.displacement_at(alpha, active, &mut u_new);
    if let Some(o) = offset {
        for &i in active {
            for a in 0..3 {
                let k = 3 * i as usize + a;
                u_new[k] += o[k];
            }
        }
    }
    u_new
}

/// Largest movement of an active node in the image frame of the old estimate:
/// `|δ(X + u_new) − (X + u_old)|`.
pub(super) fn movement(
    mesh: &TetMesh,
    active: &[u32],
    u: &[f64],
    u_new: &[f64],
    delta: &Rigid,
) -> f64 {
    let mut moved = 0.0f64;
    for &i in active {
        let (i, x) = (i as usize, mesh.nodes()[i as usize]);
        let old = [0, 1, 2].map(|a| x[a] + u[3 * i + a]);
        let new = delta.apply([0, 1, 2].map(|a| x[a] + u_new[3 * i + a]));
        moved = moved.max(dist2(old, new).sqrt());
    }
    moved
}

/// Fills the summary fields of `info` after the last iteration.
fn finish_info(
    info: &mut LibrInfo,
    basis: &LibrBasis,
    params: &LibrParams,
    hold: Option<&Hold>,
    alpha: &[f64],
) {
    info.settled = info.converged || settled(&info.rms_history_mm, &info.movement_history_mm);
    info.held_nodes = hold.map_or(0, |h| h.nodes.len());
    info.strain_energy_uj = basis.strain_energy(alpha);
    info.regularization = params.fit.regularization;
    info.columns = basis.columns();
    info.prior_mm2 =
        params.fit.regularization * 2.0 * info.strain_energy_uj / basis.energy_scale().max(1e-300);
}

/// What every LIBR iteration checks before it starts (the mesh is the basis's, at least one
/// iteration, the active nodes in range); returns the active nodes (every node when None).
pub(super) fn checked_active(
    mesh: &TetMesh,
    basis: &LibrBasis,
    params: &LibrParams,
    active: Option<&[u32]>,
) -> Result<Vec<u32>, RegisterError> {
    if let Some(v) = active.and_then(|a| a.iter().find(|&&v| v as usize >= basis.nodes)) {
        return Err(RegisterError::Inconsistent(format!(
            "active node {v} out of range ({} nodes)",
            basis.nodes
        )));
    }
    if mesh.num_nodes() != basis.nodes {
        return Err(RegisterError::Inconsistent(format!(
            "mesh has {} nodes, the basis {}",
            mesh.num_nodes(),
            basis.nodes
        )));
    }
    if params.fit.max_iterations == 0 {
        return Err(RegisterError::Parameter(
            "max_iterations must be at least 1".into(),
        ));
    }
    Ok(active.map_or_else(|| (0..basis.nodes as u32).collect(), <[u32]>::to_vec))
}

/// Iterations over which [`settled`] judges the objective.
pub const SETTLE_WINDOW: usize = 3;

/// Whether an iteration that did not converge has nevertheless settled, from its histories (one
/// value per iteration): the best weighted residual RMS of the last [`SETTLE_WINDOW`] iterations
/// improves on the best before them by less than 1 % (or 0.01 mm), so the objective has stopped
/// falling, and none of those iterations moved the model more than the largest movement before
/// them, so it is not running away. Fewer than `SETTLE_WINDOW + 1` iterations, or a non-finite
/// value, is not settled.
pub fn settled(rms_mm: &[f64], movement_mm: &[f64]) -> bool {
    let n = rms_mm.len();
    if n <= SETTLE_WINDOW
        || movement_mm.len() != n
        || rms_mm.iter().chain(movement_mm).any(|x| !x.is_finite())
    {
        return false;
    }
    let (early, late) = rms_mm.split_at(n - SETTLE_WINDOW);
    let best = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    let most = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
    let (best_early, best_late) = (best(early), best(late));
    let falling = best_early - best_late > (0.01 * best_late).max(0.01);
    let (m_early, m_late) = movement_mm.split_at(n - SETTLE_WINDOW);
    !falling && most(m_late) <= most(m_early)
}

/// Whether the model's movement is still shrinking geometrically: the last iteration moved it
/// less than a tenth of what the iteration [`SETTLE_WINDOW`] before did. A fit converging on
/// exact data settles by the residual long before it reaches the tolerance; one cycling around
/// its fit moves by about as much every iteration. Fewer iterations than the window: false.
pub fn shrinking(movement_mm: &[f64]) -> bool {
    let n = movement_mm.len();
    n > SETTLE_WINDOW && movement_mm[n - 1] < 0.1 * movement_mm[n - 1 - SETTLE_WINDOW]
}

/// A row of Φ times α with four accumulators (vectorizes; the same bits whatever the thread
/// count, since every row is summed in a fixed order).
pub(super) fn dot_row(row: &[f64], alpha: &[f64]) -> f64 {
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
