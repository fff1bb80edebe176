//! The nonlinear refinement of a linear answer ([`refine_nonlinear`]): the same loads, fitted
//! again through the geometrically nonlinear model of the case
//! ([`crate::register::nonlinear::NonlinearModel`]).
//!
//! **Unknowns.** The linear answer's own: the weights α of the basis columns it used (LIBR's
//! whole basis, or the columns adaptive LIBR kept), whose balanced loads are `f(α) = KΦα`, and the
//! rigid pose. The displacement is the nonlinear equilibrium `u(α)` under `f(α)`. The objective
//! is the linear fit's: the weighted mean squared misfit of the matched points (and the hold's
//! pairs) plus `λ αᵀẼα`, with the linear answer's λ, so that the refinement answers the same
//! question with a better forward model.
//!
//! **Iteration (a frozen-Jacobian Gauss–Newton).** `u(α) = Φα + d(α)`, with `d` the nonlinear
//! correction. Each iteration re-matches on the current nonlinear shape, fits α and the rigid
//! correction by the linear step with `d` held at its current value (the targets offset by it,
//! as LIBR+'s refit does), then solves the nonlinear equilibrium under the new loads from a warm
//! start (the last equilibrium plus the linear change). The Jacobian `∂u/∂α = K_T⁻¹KΦ` is
//! replaced by `Φ`: exact at small strain, and a contraction while the tangent stays near the
//! linear stiffness, so no tangent system with `3K` right-hand sides is solved. It stops as
//! LIBR's iterations do (movement below the tolerance, or settled), at the cap, or before the
//! deadline.
//!
//! **Never worse than its start.** The refined answer is kept only when its objective, measured
//! by the same matching and rows as the linear answer's, is lower; otherwise the linear answer is
//! returned unchanged, bit for bit, and [`NonlinearInfo::kept_linear`] says why.

use super::iterate::{Iterated, Stepper, iterate};
use super::solve::{checked_active, movement, step_targets};
use super::*;
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::register::Match;
use crate::register::nonlinear::{ForwardInfo, ForwardParams, NonlinearMap};
use std::time::Instant;

/// Parameters of the nonlinear refinement.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct RefineParams {
    /// The equilibrium solves.
    pub forward: ForwardParams,
    /// Most refinement iterations (each one matching, one step, one equilibrium). Default 6.
    pub max_iterations: usize,
    /// Stops when no node moved more than this in an iteration (mm). Default 0.05.
    pub tolerance_mm: f64,
    /// A case with more nodes than this solves its nonlinear response on a coarse mesh of its
    /// boundary of about `coarse_nodes` nodes ([`NonlinearMap`]); 0: always on its own mesh.
    /// Default [`crate::register::nonlinear::COARSE_ABOVE`].
    pub coarse_above: usize,
    /// See `coarse_above`. Default [`crate::register::nonlinear::COARSE_NODES`].
    pub coarse_nodes: usize,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            forward: REFINE_FORWARD,
            max_iterations: 6,
            tolerance_mm: 0.05,
            coarse_above: crate::register::nonlinear::COARSE_ABOVE,
            coarse_nodes: crate::register::nonlinear::COARSE_NODES,
        }
    }
}

/// The refinement's equilibria: inexact, since each warm-starts from the last and the objective
/// judges every step: at most 3 Newton iterations, each solved by CG to half its residual (on
/// the paper liver's 30 registrations this took the refinement from 422 CG iterations to about
/// 50 at the same answers, `docs/registration.md`).
const REFINE_FORWARD: ForwardParams = ForwardParams {
    tolerance: 1e-3,
    max_newton: 3,
    max_cg: 25,
    eta: 0.5,
    max_halvings: 12,
    deadline: None,
};

impl RefineParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        self.forward.validate()?;
        if self.max_iterations == 0 {
            return Err(RegisterError::Parameter(
                "nonlinear max_iterations must be at least 1".into(),
            ));
        }
        if !(self.tolerance_mm.is_finite() && self.tolerance_mm >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "nonlinear tolerance_mm must be finite and >= 0, got {}",
                self.tolerance_mm
            )));
        }
        Ok(())
    }
}

/// What the refinement did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct NonlinearInfo {
    /// The refinement's iterations (as LIBR's: matching, step, equilibrium).
    pub iterations: LibrInfo,
    /// Equilibrium solves, the first (under the linear answer's loads) included.
    pub solves: usize,
    /// Newton iterations over all solves.
    pub newton: usize,
    /// CG iterations over all solves.
    pub cg: usize,
    /// Solves that stopped short of their tolerance (their last iterate was used).
    pub unconverged_solves: usize,
    /// The relative force residual `‖r‖ / ‖f‖` of the equilibrium behind the refined answer (0
    /// when none was solved).
    pub residual: f64,
    /// Nodes of the coarse mesh the equilibria were solved on (None: the case's own mesh).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coarse_nodes: Option<usize>,
    /// Time in the equilibrium solves (s).
    pub forward_s: f64,
    /// Of it, in the preconditioner's solves (s).
    pub precondition_s: f64,
    /// Of it, assembling forces and tangents (s).
    pub assemble_s: f64,
    /// The linear answer's objective: weighted mean squared misfit plus prior (mm²).
    pub linear_objective_mm2: f64,
    /// The refined answer's objective, measured the same way (mm²).
    pub refined_objective_mm2: f64,
    /// RMS over nodes of how far the refinement moved the linear answer (mm; 0 when kept).
    pub change_rms_mm: f64,
    /// Why the linear answer was kept (None: the refined answer is returned).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kept_linear: Option<String>,
    /// Total time (s).
    pub seconds: f64,
}

/// The linear answer a refinement starts from: its solution on `basis` (the basis it was
/// fitted on, all its columns; adaptive LIBR's weights are zero on the columns it did not keep).
#[derive(Clone, Copy)]
pub struct LinearAnswer<'a> {
    /// The basis the answer's weights are on.
    pub basis: &'a LibrBasis,
    /// The linear answer.
    pub solution: &'a LibrSolution,
}

/// Refines `start` through `model` (see the module doc). Returns the refined solution (its
/// `alpha` on `start`'s basis, its `u` the nonlinear equilibrium, its `info` the refinement's
/// iterations) or `start` unchanged, and what the refinement did. `run` is the linear fit's
/// (hold, rigid prior, active nodes, deadline); its offset must be None.
#[allow(clippy::too_many_arguments)]
pub fn refine_nonlinear(
    mesh: &TetMesh,
    start: LinearAnswer<'_>,
    model: &NonlinearMap,
    params: &LibrParams,
    refine: &RefineParams,
    measured_physical: &[[f64; 3]],
    run: RunLimits<'_>,
    mut rematch: impl FnMut(&[f64], &Rigid) -> Result<Vec<Match>, RegisterError>,
) -> Result<(LibrSolution, NonlinearInfo), RegisterError> {
    let t0 = Instant::now();
    check_start(start, model, refine, &run)?;
    let LinearAnswer { basis, solution } = start;
    let active = checked_active(mesh, basis, params, run.active)?;
    let (cols, reduced, alpha0, weight, fit_params) = restricted(basis, solution, params, refine);
    let mut info = NonlinearInfo::default();
    let cx = (mesh, &reduced, &fit_params, measured_physical, &run);
    let objective_of = |u: &[f64], alpha: &[f64], t: &Rigid, m| objective(cx, (u, alpha, t), m);
    let (lin_u, lin_t) = (&solution.u, &solution.image_to_physical);
    info.linear_objective_mm2 = objective_of(lin_u, &alpha0, lin_t, rematch(lin_u, lin_t)?);
    if cols.is_empty() {
        let why = "the linear answer has no deformation to refine".to_string();
        return Ok((solution.clone(), info.kept(why, t0)));
    }
    // Every equilibrium stops at the run's deadline; one that did is not an answer.
    let forward = ForwardParams {
        deadline: run.deadline,
        ..refine.forward
    };
    let lin = reduced.displacement(&alpha0); // where the iterations start: its nonlinear shape
    let Some((u0, state, f0)) = first_response(model, &lin, &forward, &mut info)? else {
        return Ok((solution.clone(), info.kept(OUT_OF_TIME.into(), t0)));
    };
    let mut fit = Refining {
        mesh,
        basis: &reduced,
        params: &fit_params,
        measured_physical,
        run,
        active: &active,
        model,
        forward: &forward,
        d: u0.iter().zip(&lin).map(|(a, b)| a - b).collect(),
        u: u0,
        state,
        residual: f0.relative_residual,
        alpha: alpha0,
        solves: Vec::new(),
        failure: None,
        stalled: false,
    };
    let limits = (run.deadline, false); // no held-out check of the last step
    let pose = &solution.image_to_physical;
    let Iterated {
        t, info: mut it, ..
    } = iterate(&mut fit, &fit_params, pose, limits, &mut rematch)?;
    fit.solves.iter().for_each(|f| info.add(f));
    let lambda = (fit_params.fit.regularization, weight);
    finish_iterations(&mut it, &reduced, &fit.alpha, lambda, run.hold);
    let refined_matches = rematch(&fit.u, &t)?;
    info.refined_objective_mm2 = objective_of(&fit.u, &fit.alpha, &t, refined_matches);
    info.iterations = it.clone();
    if let Some(why) = kept_reason(&info, fit.failure.as_ref()) {
        return Ok((solution.clone(), info.kept(why, t0)));
    }
    info.seconds = crate::util::secs(t0);
    info.change_rms_mm = rms_change(&solution.u, &fit.u);
    info.residual = fit.residual;
    it.total_s = info.seconds;
    let alpha = widened(&cols, &fit.alpha, basis.columns());
    let sol = LibrSolution {
        alpha,
        u: fit.u,
        image_to_physical: t,
        info: it,
    };
    Ok((sol, info))
}

/// The weights `alpha` of the columns `cols`, as weights of all `columns` (zero elsewhere).
fn widened(cols: &[usize], alpha: &[f64], columns: usize) -> Vec<f64> {
    let mut out = vec![0.0; columns];
    cols.iter().zip(alpha).for_each(|(&j, &a)| out[j] = a);
    out
}

/// A response of the nonlinear model: the displacement of the case's nodes, the model's own
/// equilibrium (the next warm start) and what the solve did ([`NonlinearMap::response`]).
type Response = (Vec<f64>, Vec<f64>, ForwardInfo);

/// The response to the linear answer's own loads, where the iterations start (its solve
/// recorded in `info`); None when the deadline came first.
fn first_response(
    model: &NonlinearMap,
    lin: &[f64],
    forward: &ForwardParams,
    info: &mut NonlinearInfo,
) -> Result<Option<Response>, RegisterError> {
    if forward.deadline.is_some_and(|d| Instant::now() >= d) {
        return Ok(None);
    }
    let (u, state, f) = model.response(lin, None, forward)?;
    info.add(&f);
    info.coarse_nodes = model.coarse_mesh().map(|(n, _)| n);
    Ok((!f.out_of_time).then_some((u, state, f)))
}

/// The refinement's unknowns: the columns the answer used, the basis restricted to them, their
/// weights, the prior weight `λ/ē` it was fitted with, and the fit's parameters with that λ and
/// the refinement's iterations.
fn restricted(
    basis: &LibrBasis,
    solution: &LibrSolution,
    params: &LibrParams,
    refine: &RefineParams,
) -> (Vec<usize>, LibrBasis, Vec<f64>, f64, LibrParams) {
    let cols: Vec<usize> = (0..basis.columns())
        .filter(|&j| solution.alpha[j] != 0.0)
        .collect();
    let all: Vec<u32> = (0..basis.nodes as u32).collect();
    let reduced = restrict(basis, &cols, &all);
    let alpha0: Vec<f64> = cols.iter().map(|&j| solution.alpha[j]).collect();
    let weight = prior_weight(&solution.info, &reduced, params);
    let mut fit_params = *params;
    fit_params.fit.regularization = weight * reduced.energy_scale();
    fit_params.fit.max_iterations = refine.max_iterations;
    fit_params.fit.tolerance_mm = refine.tolerance_mm;
    (cols, reduced, alpha0, weight, fit_params)
}

/// Checks the refinement's inputs: its parameters, no offset, the answer's weights and the
/// model against the basis.
fn check_start(
    start: LinearAnswer<'_>,
    model: &NonlinearMap,
    refine: &RefineParams,
    run: &RunLimits<'_>,
) -> Result<(), RegisterError> {
    refine.validate()?;
    if run.offset.is_some() {
        return Err(RegisterError::Parameter(
            "the nonlinear refinement starts from a linear answer without an offset".into(),
        ));
    }
    let LinearAnswer { basis, solution } = start;
    if solution.alpha.len() != basis.columns() || model.dofs() != 3 * basis.nodes {
        return Err(RegisterError::Inconsistent(format!(
            "nonlinear refinement: {} weights for {} columns, a model of {} dofs for {} nodes",
            solution.alpha.len(),
            basis.columns(),
            model.dofs(),
            basis.nodes
        )));
    }
    Ok(())
}

/// Why the linear answer stands: an equilibrium failed, or the refined objective is not lower.
fn kept_reason(info: &NonlinearInfo, failure: Option<&String>) -> Option<String> {
    if let Some(why) = failure {
        return Some(why.clone());
    }
    let lower = info
        .refined_objective_mm2
        .partial_cmp(&info.linear_objective_mm2)
        == Some(std::cmp::Ordering::Less);
    (!lower).then(|| {
        format!(
            "the refined fit's objective {:.3} mm² is not below the linear answer's {:.3} mm²",
            info.refined_objective_mm2, info.linear_objective_mm2
        )
    })
}

/// The refinement's record of its iterations: the fit's summary fields filled in.
fn finish_iterations(
    it: &mut LibrInfo,
    reduced: &LibrBasis,
    alpha: &[f64],
    (lambda, weight): (f64, f64),
    hold: Option<&Hold>,
) {
    it.strain_energy_uj = reduced.strain_energy(alpha);
    it.regularization = lambda;
    it.columns = reduced.columns();
    it.prior_mm2 = weight * 2.0 * it.strain_energy_uj;
    it.held_nodes = hold.map_or(0, |h| h.nodes.len());
    it.settled = it.converged || settled(&it.rms_history_mm, &it.movement_history_mm);
}

impl NonlinearInfo {
    /// This record with the linear answer kept for `why`, timed from `t0`.
    fn kept(mut self, why: String, t0: Instant) -> Self {
        self.kept_linear = Some(why);
        self.seconds = crate::util::secs(t0);
        self
    }

    fn add(&mut self, f: &ForwardInfo) {
        self.solves += 1;
        self.newton += f.newton;
        self.cg += f.cg;
        self.unconverged_solves += usize::from(!f.converged);
        self.forward_s += f.total_s;
        self.precondition_s += f.precondition_s;
        self.assemble_s += f.assemble_s;
    }
}

/// The prior weight `λ / ē` the answer was fitted with: its recorded prior over its strain
/// energy (adaptive LIBR chooses λ per registration), else LIBR's λ over the basis's scale.
fn prior_weight(info: &LibrInfo, reduced: &LibrBasis, params: &LibrParams) -> f64 {
    if info.strain_energy_uj > 0.0 && info.prior_mm2.is_finite() && info.prior_mm2 >= 0.0 {
        info.prior_mm2 / (2.0 * info.strain_energy_uj)
    } else {
        params.fit.regularization / reduced.energy_scale().max(1e-300)
    }
}

/// RMS over nodes of the distance between two displacements (mm).
fn rms_change(a: &[f64], b: &[f64]) -> f64 {
    let n = (a.len() / 3).max(1) as f64;
    (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / n).sqrt()
}

/// What [`objective`] reads besides the state: the mesh, the restricted basis, the fit's
/// parameters, the measured points and the run's hold.
type ObjectiveContext<'a> = (
    &'a TetMesh,
    &'a LibrBasis,
    &'a LibrParams,
    &'a [[f64; 3]],
    &'a RunLimits<'a>,
);

/// The fit's objective at `(u, α, t)` from `matches` made there: the weighted mean squared
/// misfit of the matched points and the hold's pairs, by the step's rows (point-to-plane with
/// the tangential weight, point-to-point without a normal), plus `λ αᵀẼα`.
fn objective(
    (mesh, basis, params, measured_physical, run): ObjectiveContext<'_>,
    (u, alpha, t): (&[f64], &[f64], &Rigid),
    mut matches: Vec<Match>,
) -> f64 {
    let targets = step_targets(mesh, measured_physical, t, run.hold, None, &mut matches);
    let tw = params.fit.tangential_weight.sqrt();
    let mut wsum = 0.0;
    let mut sum = 0.0;
    for mt in matches.iter().filter(|m| m.weight > 0.0) {
        let q = mt.model_point(u);
        let y = targets[mt.point];
        let r = [0, 1, 2].map(|a| q[a] - y[a]);
        let frame = row_frame(mt.normal, tw);
        let rr: f64 = frame
            .iter()
            .take(rows_of(mt, tw))
            .map(|f| (f[0] * r[0] + f[1] * r[1] + f[2] * r[2]).powi(2))
            .sum();
        wsum += mt.weight;
        sum += mt.weight * rr;
    }
    let misfit = if wsum > 0.0 {
        sum / wsum
    } else {
        f64::INFINITY
    };
    let prior = params.fit.regularization / basis.energy_scale().max(1e-300)
        * 2.0
        * basis.strain_energy(alpha);
    misfit + prior
}

/// The refinement's step ([`iterate`]): the linear step with the nonlinear correction `d` held,
/// then the equilibrium under the new loads.
struct Refining<'a> {
    mesh: &'a TetMesh,
    basis: &'a LibrBasis,
    params: &'a LibrParams,
    measured_physical: &'a [[f64; 3]],
    run: RunLimits<'a>,
    active: &'a [u32],
    model: &'a NonlinearMap,
    forward: &'a ForwardParams,
    /// The nonlinear correction `u − Φα` at the current loads.
    d: Vec<f64>,
    u: Vec<f64>,
    /// The model's equilibrium behind `u` (on its own mesh): the next solve's warm start.
    state: Vec<f64>,
    /// Its relative force residual.
    residual: f64,
    alpha: Vec<f64>,
    solves: Vec<ForwardInfo>,
    /// Why an equilibrium failed (the iterations then stop, and the linear answer stands).
    failure: Option<String>,
    /// No shortened step lowered the objective (the iterations then stop).
    stalled: bool,
}

/// Why the linear answer stands when the deadline stopped the refinement.
const OUT_OF_TIME: &str = "the time budget ran out before the refinement's equilibrium";

/// How many times a refinement step is halved before the refinement stops.
const SHORTENINGS: usize = 3;

impl Refining<'_> {
    /// `Φα`, the response to it and the model's equilibrium behind that, warm-started from the
    /// current one moved by the linear change (`old` = `Φα` of the current weights); None when
    /// the solve failed ([`Refining::failure`] says why).
    fn equilibrium_at(&mut self, alpha: &[f64], old: &[f64]) -> Option<[Vec<f64>; 3]> {
        let lin = self.basis.displacement(alpha);
        let change: Vec<f64> = lin.iter().zip(old).map(|(a, b)| a - b).collect();
        let warm: Vec<f64> = self
            .state
            .iter()
            .zip(self.model.restrict(&change))
            .map(|(s, c)| s + c)
            .collect();
        match self.model.response(&lin, Some(&warm), self.forward) {
            Ok((_, _, f)) if f.out_of_time => {
                self.solves.push(f);
                self.failure = Some(OUT_OF_TIME.into());
                None
            }
            Ok((u, state, f)) => {
                self.solves.push(f);
                Some([lin, u, state])
            }
            Err(e) => {
                self.failure = Some(format!("an equilibrium failed: {e}"));
                None
            }
        }
    }
}

impl Stepper for Refining<'_> {
    type Last = ();

    fn u(&self) -> &[f64] {
        &self.u
    }

    fn step(
        &mut self,
        mut matches: Vec<Match>,
        t: &Rigid,
        _: &mut LibrInfo,
    ) -> Result<(StepResult, f64, ()), RegisterError> {
        let raw = matches.clone();
        let targets = step_targets(
            self.mesh,
            self.measured_physical,
            t,
            self.run.hold,
            Some(&self.d),
            &mut matches,
        );
        let prior = PriorPairs::of(self.run.rigid_prior, t);
        let mut step =
            fit_step_with_prior(self.basis, &matches, &targets, self.params, prior.as_ref())?;
        let run = self.run;
        let cx = (
            self.mesh,
            self.basis,
            self.params,
            self.measured_physical,
            &run,
        );
        let objective_at =
            |u: &[f64], alpha: &[f64], pose: &Rigid| objective(cx, (u, alpha, pose), raw.clone());
        let now = objective_at(&self.u, &self.alpha, t);
        let moved_pose = step.rigid_correction.then(t);
        let old = self.basis.displacement(&self.alpha);
        // The frozen Jacobian's step, shortened while it does not lower the objective on these
        // matches (the nonlinear response may be softer or stiffer than Φ says).
        let mut fraction = 1.0;
        for _ in 0..SHORTENINGS {
            let alpha: Vec<f64> = self
                .alpha
                .iter()
                .zip(&step.alpha)
                .map(|(a, b)| a + fraction * (b - a))
                .collect();
            let Some([lin, u_new, state]) = self.equilibrium_at(&alpha, &old) else {
                return Ok((step, 0.0, ()));
            };
            if objective_at(&u_new, &alpha, &moved_pose) < now {
                let moved = movement(
                    self.mesh,
                    self.active,
                    &self.u,
                    &u_new,
                    &step.rigid_correction,
                );
                self.d = u_new.iter().zip(&lin).map(|(a, b)| a - b).collect();
                self.u = u_new;
                self.state = state;
                self.residual = self.solves.last().map_or(0.0, |f| f.relative_residual);
                step.alpha = alpha;
                return Ok((step, moved, ()));
            }
            fraction *= 0.5;
        }
        // No shortened step lowers the objective: the refinement has gone as far as it can.
        self.stalled = true;
        step.alpha = self.alpha.clone();
        step.rigid_correction = Rigid::identity();
        Ok((step, 0.0, ()))
    }

    fn keep(&mut self, step: StepResult, _: &mut LibrInfo) {
        if self.failure.is_none() && !self.stalled {
            self.alpha = step.alpha;
        }
    }

    fn done(&mut self, info: &mut LibrInfo, moved: f64, params: &LibrParams) -> bool {
        if self.failure.is_some() || self.stalled {
            info.converged = self.stalled;
            return true;
        }
        if moved <= params.fit.tolerance_mm {
            info.converged = true;
            return true;
        }
        settled(&info.rms_history_mm, &info.movement_history_mm)
            && !shrinking(&info.movement_history_mm)
    }
}
