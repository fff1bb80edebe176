//! [`super::register`]: one registration of a prepared case, stage by stage. The rigid stage (from the
//! navigation start, or every start of the pose search), then either the rigid methods' answer
//! (the baseline, wICP, V2S) or the deformable fit from every candidate pose, the best kept, and
//! LIBR+'s correction on it.

use super::{
    CorrectionInfo, FirstAnswer, LibrAnswer, Method, PipelineError, PipelineParams, Prepared,
    Registration, V2sInfo, correct_libr, held_at, pose, rigid_params,
};
use crate::gcn::infer::LibrPlusCase;
use crate::mesh::rigid::Rigid;
use crate::register::correspondence::{CorrespondenceParams, Hints};
use crate::register::libr::{self, Folds, LibrSolution};
use crate::register::measured::not_empty;
use crate::register::wicp::{WicpParams, WicpResult, wicp};
use crate::register::{Checked, Match, RegisterError};
use crate::util::secs;
use crate::v2s::V2sCase;
use std::time::{Duration, Instant};

/// What [`register_scored`] may share with other registrations of the same measurements.
#[derive(Default, Clone, Copy)]
pub(super) struct Shared<'a> {
    /// The folds the deformable fit's held-out prediction is measured on
    /// ([`crate::register::libr::held_out`]; None: not measured).
    pub folds: Option<&'a Folds>,
    /// The rigid stage from the navigation start, already run with these parameters' rigid
    /// settings ([`rigid_params`]); used where the run starts from the navigation start alone.
    pub start: Option<&'a WicpResult>,
    /// Where [`Method::Nonlinear`]'s linear answer goes before its refinement runs (None: it
    /// is not handed over).
    pub first: Option<FirstAnswer<'a>>,
}

/// [`super::register`] with one method (not [`Method::Auto`]), with what it shares.
pub(super) fn register_scored(
    case: &Prepared,
    meas: &Checked,
    method: Method,
    params: &PipelineParams,
    shared: Shared<'_>,
) -> Result<Registration, PipelineError> {
    let t0 = Instant::now();
    not_empty(meas).map_err(PipelineError::Rigid)?;
    let mut run = Run::new(case, meas, method, params, t0);
    run.folds = shared.folds;
    run.start = shared.start;
    run.first = shared.first;
    let v2s = match method {
        Method::V2s => Some(case.v2s.as_ref().ok_or(PipelineError::NoV2sModel)?),
        _ => None,
    };
    let t_rigid = Instant::now();
    let candidates = run.start_candidates()?;
    let search_seconds = secs(t_rigid);
    if run.rigid_only() {
        return run.rigid_answer(candidates, search_seconds, v2s);
    }
    run.deformable_answer(candidates, search_seconds)
}

/// One registration under way: its inputs and the settings every stage reads.
struct Run<'a> {
    case: &'a Prepared,
    meas: &'a Checked,
    method: Method,
    params: &'a PipelineParams,
    /// The rigid stage's parameters ([`rigid_params`]; no iterations for the baseline).
    rigid: WicpParams,
    /// The correspondence settings of LIBR's iterations.
    cparams: CorrespondenceParams,
    t0: Instant,
    /// The navigation start's fit score when the gate would have searched but no search was
    /// configured ([`Registration::search_skipped_mm2`]).
    search_skipped: std::sync::OnceLock<f64>,
    /// The folds the deformable fit's held-out prediction is measured on (None: not measured).
    folds: Option<&'a Folds>,
    /// The rigid stage from the navigation start, run already ([`Shared::start`]).
    start: Option<&'a WicpResult>,
    /// Where the linear answer goes before the refinement ([`Shared::first`]).
    first: Option<FirstAnswer<'a>>,
}

/// The deformable fits of every candidate pose: each pose's solution and score (None and
/// infinity where a start other than the navigation start failed), and their prior energies.
struct Fitted {
    sols: Vec<Option<LibrSolution>>,
    scores: Vec<f64>,
    priors: Vec<f64>,
}

impl<'a> Run<'a> {
    fn new(
        case: &'a Prepared,
        meas: &'a Checked,
        method: Method,
        params: &'a PipelineParams,
        t0: Instant,
    ) -> Self {
        let wparams = rigid_params(case, params);
        let rigid = if method == Method::Initial {
            // No iterations: the start, with its match statistics.
            WicpParams {
                max_iterations: 0,
                min_conditioning: 0.0,
                ..wparams
            }
        } else {
            wparams
        };
        Self {
            case,
            meas,
            method,
            params,
            rigid,
            cparams: params.libr_correspondence(),
            t0,
            search_skipped: std::sync::OnceLock::new(),
            folds: None,
            start: None,
            first: None,
        }
    }

    /// The methods with no deformable fit: the baseline, wICP and V2S.
    fn rigid_only(&self) -> bool {
        matches!(self.method, Method::Rigid | Method::Initial | Method::V2s)
    }

    /// With a gate on the search, a deformable method first fits from the navigation start
    /// alone and searches only when that fit scores badly.
    fn gated(&self) -> bool {
        self.params.pose.search_above_mm2 > 0.0 && !self.rigid_only()
    }

    /// The rigid stage: from the navigation start alone for the baseline (and a gated search),
    /// else from every start of the pose search (distinct poses, the navigation start's first).
    fn start_candidates(&self) -> Result<pose::Candidates, PipelineError> {
        let case = self.case;
        if self.method == Method::Initial || self.gated() {
            let r = match self.start {
                Some(r) if self.method != Method::Initial => r.clone(),
                _ => wicp(&case.model, &case.correspondence, self.meas, &self.rigid)
                    .map_err(PipelineError::Rigid)?,
            };
            return Ok(pose::Candidates {
                poses: vec![r],
                starts: 1,
                distinct: 1,
            });
        }
        match self.start {
            // The side test's fit from the navigation start is this run's first.
            Some(r) => pose::candidates_from(
                r.clone(),
                &case.model,
                &case.correspondence,
                self.meas,
                &self.rigid,
                &self.params.pose,
            ),
            None => pose::rigid_candidates(
                &case.model,
                &case.correspondence,
                self.meas,
                &self.rigid,
                &self.params.pose,
            ),
        }
        .map_err(PipelineError::Rigid)
    }

    /// A registration with this run's method and times, its error estimated.
    fn answer(&self, r: Answer) -> Registration {
        Registration {
            method: self.method,
            image_to_physical: r.image_to_physical,
            u: r.u,
            rigid: r.rigid,
            pose: r.pose,
            libr: r.libr,
            correction: r.correction,
            v2s: r.v2s,
            nonlinear: r.nonlinear,
            error: None,
            auto: None,
            search_skipped_mm2: self.search_skipped.get().copied(),
            search_follows: false,
            refinement_follows: false,
            surface: None,
            points: None,
            seconds: secs(self.t0),
        }
        .estimated(self.case, self.meas)
    }

    /// The answer of a method without a deformable fit: the best rigid pose, with V2S's
    /// displacement or none.
    fn rigid_answer(
        &self,
        candidates: pose::Candidates,
        search_seconds: f64,
        v2s: Option<&V2sCase>,
    ) -> Result<Registration, PipelineError> {
        let (rigid, pose) = self.choose_rigid(candidates, search_seconds)?;
        let n = self.case.model.mesh.num_nodes();
        let (u, v2s) = match v2s {
            // V2S reads the points after the rigid stage, as V2S-Net assumes a rigid alignment.
            Some(v) => {
                let t1 = Instant::now();
                let (u, network_seconds) = v
                    .displacement(self.meas, &rigid.image_to_physical)
                    .map_err(PipelineError::V2s)?;
                let info = V2sInfo {
                    seconds: secs(t1),
                    network_seconds,
                };
                (u, Some(info))
            }
            None => (vec![0.0; 3 * n], None),
        };
        Ok(self.answer(Answer {
            image_to_physical: rigid.image_to_physical,
            u,
            rigid,
            pose,
            libr: None,
            correction: None,
            v2s,
            nonlinear: None,
        }))
    }

    /// With no deformable fit to score the poses by, their rigid scores decide.
    fn choose_rigid(
        &self,
        candidates: pose::Candidates,
        search_seconds: f64,
    ) -> Result<(WicpResult, Option<pose::PoseInfo>), PipelineError> {
        if candidates.poses.len() <= 1 {
            let rigid = candidates.poses.into_iter().next().expect("one pose");
            return Ok((rigid, None));
        }
        let scores = candidates
            .poses
            .iter()
            .map(|r| {
                pose::score(
                    &self.case.correspondence,
                    self.meas,
                    &self.rigid.correspondence,
                    None,
                    &r.image_to_physical,
                    self.params.pose.cap_mm,
                )
                .map_err(PipelineError::Rigid)
            })
            .collect::<Result<Vec<f64>, _>>()?;
        let poses: Vec<Rigid> = candidates
            .poses
            .iter()
            .map(|r| r.image_to_physical)
            .collect();
        let info = pose::choose(
            &self.case.model,
            &poses,
            &scores,
            &vec![0.0; scores.len()],
            candidates.starts,
            candidates.distinct,
            &self.params.pose,
        );
        let info = pose::PoseInfo {
            rigid_seconds: search_seconds,
            ..info
        };
        let mut c = candidates.poses;
        Ok((c.swap_remove(info.chosen), Some(info)))
    }

    /// The deformable methods' answer: the fit from every candidate pose (after the gate), the
    /// best kept, then LIBR+'s correction on it.
    fn deformable_answer(
        &self,
        candidates: pose::Candidates,
        search_seconds: f64,
    ) -> Result<Registration, PipelineError> {
        if let Some(reason) = &candidates.poses[0].degenerate {
            return Err(PipelineError::Degenerate {
                reason: reason.clone(),
            });
        }
        let gcn = match self.method {
            Method::LibrPlus => Some(self.case.librplus.as_ref().ok_or(PipelineError::NoModel)?),
            _ => None,
        };
        // LIBR+ leaves the correction its expected time before the deadline.
        let deadline = match (self.params.deadline, gcn) {
            (Some(d), Some(g)) => Some(
                d.checked_sub(Duration::from_secs_f64(g.expected_seconds()))
                    .unwrap_or(d),
            ),
            (d, _) => d,
        };
        let (candidates, first_fit, search_seconds) =
            self.gate(candidates, search_seconds, deadline)?;
        let (rigid, sol, pose) = self.best(candidates, first_fit, search_seconds, deadline)?;
        Ok(self.corrected(gcn, rigid, sol, pose))
    }

    /// The gate: the navigation start's fit, kept when it scores well (or no search can run);
    /// else the search's candidates, the navigation start's first with its fit.
    fn gate(
        &self,
        mut candidates: pose::Candidates,
        mut search_seconds: f64,
        deadline: Option<Instant>,
    ) -> Result<(pose::Candidates, Option<LibrSolution>, f64), PipelineError> {
        if !self.gated() {
            return Ok((candidates, None, search_seconds));
        }
        let sol = self.deform(&candidates.poses[0], deadline)?;
        let searchable = pose::searchable(&candidates.poses[0], &self.rigid, &self.params.pose);
        // A search turned off (no extra starts: a tight time budget, or asked) is still judged,
        // so that an answer the gate would have searched says so.
        let off = self.params.pose.start_angles_deg.is_empty();
        let score = if searchable || off {
            self.fitted_score(&sol)?
        } else {
            0.0
        };
        if off && score > self.params.pose.search_above_mm2 {
            let _ = self.search_skipped.set(score);
        }
        if searchable && score > self.params.pose.search_above_mm2 {
            let t = Instant::now();
            let first = candidates.poses.swap_remove(0);
            // The search keeps the navigation start's wICP first: its fit is the one just made.
            candidates = pose::candidates_from(
                first,
                &self.case.model,
                &self.case.correspondence,
                self.meas,
                &self.rigid,
                &self.params.pose,
            )
            .map_err(PipelineError::Rigid)?;
            search_seconds += secs(t);
        }
        Ok((candidates, Some(sol), search_seconds))
    }

    /// Every candidate pose through the fit, scored on what it leaves; the best wins.
    fn best(
        &self,
        candidates: pose::Candidates,
        first_fit: Option<LibrSolution>,
        search_seconds: f64,
        deadline: Option<Instant>,
    ) -> Result<(WicpResult, LibrSolution, Option<pose::PoseInfo>), PipelineError> {
        if candidates.poses.len() == 1 {
            let rigid = candidates.poses.into_iter().next().expect("one pose");
            let sol = match first_fit {
                Some(s) => s,
                None => self.deform(&rigid, deadline)?,
            };
            return Ok((rigid, sol, None));
        }
        let Fitted {
            mut sols,
            scores,
            priors,
        } = self.fit_all(&candidates.poses, first_fit, deadline)?;
        let poses: Vec<Rigid> = sols
            .iter()
            .zip(&candidates.poses)
            .map(|(s, r)| {
                s.as_ref()
                    .map_or(r.image_to_physical, |s| s.image_to_physical)
            })
            .collect();
        let info = pose::choose(
            &self.case.model,
            &poses,
            &scores,
            &priors,
            candidates.starts,
            candidates.distinct,
            &self.params.pose,
        );
        let info = pose::PoseInfo {
            rigid_seconds: search_seconds,
            ..info
        };
        let mut rs = candidates.poses;
        let rigid = rs.swap_remove(info.chosen);
        let sol = sols
            .swap_remove(info.chosen)
            .expect("the chosen pose was fitted");
        Ok((rigid, sol, Some(info)))
    }

    /// The fit from every pose, in parallel (the navigation start's is `first_fit` when the
    /// gate made it). The navigation start's fit failing fails the registration; another
    /// start's failure only drops that start.
    fn fit_all(
        &self,
        poses: &[WicpResult],
        first_fit: Option<LibrSolution>,
        deadline: Option<Instant>,
    ) -> Result<Fitted, PipelineError> {
        use rayon::prelude::*;
        let fitted: Vec<Result<(LibrSolution, f64), PipelineError>> = poses
            .par_iter()
            .enumerate()
            .map(|(k, r)| {
                let sol = match (k, &first_fit) {
                    (0, Some(s)) => s.clone(),
                    _ => self.deform(r, deadline)?,
                };
                let score = self.fitted_score(&sol)?;
                Ok((sol, score))
            })
            .collect();
        let mut out = Fitted {
            sols: Vec::new(),
            scores: Vec::new(),
            priors: Vec::new(),
        };
        for (k, f) in fitted.into_iter().enumerate() {
            match f {
                Ok((sol, score)) => {
                    out.scores.push(score);
                    out.priors.push(sol.info.prior_mm2);
                    out.sols.push(Some(sol));
                }
                Err(e) if k == 0 => return Err(e),
                Err(_) => {
                    out.scores.push(f64::INFINITY);
                    out.priors.push(0.0);
                    out.sols.push(None);
                }
            }
        }
        Ok(out)
    }

    /// The measured points re-matched on the model deformed by `u` and placed by `t`.
    /// The searches start from the triangles of the last matching (`hints`: same matches).
    fn rematch(
        &self,
        u: &[f64],
        t: &Rigid,
        hints: &mut Hints,
    ) -> Result<Vec<Match>, RegisterError> {
        let inv = t.inverse();
        let pts: Vec<[f64; 3]> = self.meas.points.iter().map(|&p| inv.apply(p)).collect();
        self.case
            .correspondence
            .match_points_hinted(&pts, self.meas, Some(u), &self.cparams, hints)
            .map(|(m, _)| m)
    }

    /// The deformable fit from one rigid pose: LIBR, or adaptive LIBR.
    fn deform(
        &self,
        rigid: &WicpResult,
        deadline: Option<Instant>,
    ) -> Result<LibrSolution, PipelineError> {
        let case = self.case;
        let held = held_at(case, self.meas, self.params, &rigid.image_to_physical)?;
        let run = self.limits(rigid, held.as_ref(), deadline, self.folds);
        let mut hints = Hints::default();
        let rematch = |u: &[f64], t: &Rigid| self.rematch(u, t, &mut hints);
        if self.fits_adaptive() {
            let ad = case
                .adaptive
                .as_ref()
                .ok_or(PipelineError::NoAdaptiveBasis)?;
            let levels = libr::MultiLevel {
                basis: &ad.basis,
                first_level: ad.params.levels[0].0,
                adaptive: &ad.params,
            };
            libr::solve_adaptive(
                &case.model.mesh,
                levels,
                &self.params.libr,
                &self.meas.points,
                &rigid.image_to_physical,
                run,
                rematch,
            )
        } else {
            let basis = case.basis.as_ref().ok_or(PipelineError::NoBasis)?;
            libr::solve_with_limits(
                &case.model.mesh,
                basis,
                &self.params.libr,
                &self.meas.points,
                &rigid.image_to_physical,
                run,
                rematch,
            )
        }
        .map_err(PipelineError::Libr)
    }

    /// What a deformable fit from `rigid` reads besides its data: the active nodes, the
    /// deadline, the hold and the pose prior, and the folds of its held-out check.
    fn limits<'b>(
        &'b self,
        rigid: &'b WicpResult,
        held: Option<&'b libr::Hold>,
        deadline: Option<Instant>,
        folds: Option<&'b Folds>,
    ) -> libr::RunLimits<'b> {
        libr::RunLimits {
            active: Some(self.case.correspondence.active_nodes()),
            deadline,
            offset: None,
            // A held organ is anchored by its hold: the fit's rigid correction is then free to
            // carry the rigid part the free-floating basis leaves out of a dent (a trusted
            // pose prior against it made the held fits worse than doing nothing).
            rigid_prior: if held.is_some() {
                None
            } else {
                rigid.prior.as_ref()
            },
            hold: held,
            held_out: folds,
        }
    }

    /// Whether the deformable fit is adaptive LIBR: for adaptive LIBR, and for the nonlinear
    /// refinement of a case with adaptive LIBR's basis.
    fn fits_adaptive(&self) -> bool {
        match self.method {
            Method::Adaptive => true,
            Method::Nonlinear => self.case.adaptive.is_some(),
            _ => false,
        }
    }

    /// The nonlinear refinement of the chosen fit ([`libr::refine_nonlinear`]) from the pose it
    /// reached, with its hold and prior; its time counts against the deadline.
    fn refine(
        &self,
        rigid: &WicpResult,
        sol: &LibrSolution,
    ) -> Result<(LibrSolution, libr::NonlinearInfo), PipelineError> {
        let case = self.case;
        let basis = if self.fits_adaptive() {
            &case
                .adaptive
                .as_ref()
                .ok_or(PipelineError::NoAdaptiveBasis)?
                .basis
        } else {
            case.basis.as_ref().ok_or(PipelineError::NoBasis)?
        };
        let model =
            case.nonlinear_model(&self.params.libr.basis.material, &self.params.nonlinear)?;
        let held = held_at(case, self.meas, self.params, &rigid.image_to_physical)?;
        let deadline = self.params.refine_deadline.or(self.params.deadline);
        let run = self.limits(rigid, held.as_ref(), deadline, None);
        let mut hints = Hints::default();
        libr::refine_nonlinear(
            &case.model.mesh,
            libr::LinearAnswer {
                basis,
                solution: sol,
            },
            model,
            &self.params.libr,
            &self.params.nonlinear,
            &self.meas.points,
            run,
            |u: &[f64], t: &Rigid| self.rematch(u, t, &mut hints),
        )
        .map_err(PipelineError::Nonlinear)
    }

    /// The linear fit [`Method::Nonlinear`] refines, as an answer of its own method with the
    /// refinement to follow.
    fn linear_answer(
        &self,
        rigid: &WicpResult,
        sol: &LibrSolution,
        pose: Option<pose::PoseInfo>,
    ) -> Registration {
        let mut r = self.answer(Answer {
            image_to_physical: sol.image_to_physical,
            u: sol.u.clone(),
            rigid: rigid.clone(),
            pose,
            libr: Some(sol.info.clone()),
            correction: None,
            v2s: None,
            nonlinear: None,
        });
        r.method = match self.fits_adaptive() {
            true => Method::Adaptive,
            false => Method::Libr,
        };
        r.refinement_follows = true;
        r
    }

    /// What a fit leaves: the capped residual of its matches plus its prior energy, weighted.
    fn fitted_score(&self, sol: &LibrSolution) -> Result<f64, PipelineError> {
        let s = pose::score(
            &self.case.correspondence,
            self.meas,
            &self.cparams,
            Some(&sol.u),
            &sol.image_to_physical,
            self.params.pose.cap_mm,
        )
        .map_err(PipelineError::Libr)?;
        Ok(s + self.params.pose.energy_weight * sol.info.prior_mm2)
    }

    /// The chosen fit as the answer, with LIBR+'s correction on it for LIBR+.
    fn corrected(
        &self,
        gcn: Option<&LibrPlusCase>,
        rigid: WicpResult,
        sol: LibrSolution,
        pose: Option<pose::PoseInfo>,
    ) -> Registration {
        if self.method == Method::Nonlinear
            && let Some(first) = self.first
        {
            first(&self.linear_answer(&rigid, &sol, pose.clone()));
        }
        let (sol, nonlinear) = match self.method {
            Method::Nonlinear => match self.refine(&rigid, &sol) {
                Ok((refined, info)) => (refined, Some(info)),
                Err(e) => {
                    let info = libr::NonlinearInfo {
                        kept_linear: Some(e.to_string()),
                        ..Default::default()
                    };
                    (sol, Some(info))
                }
            },
            _ => (sol, None),
        };
        let mut u = sol.u;
        let mut image_to_physical = sol.image_to_physical;
        let correction: Option<CorrectionInfo> = gcn.map(|g| {
            let libr = LibrAnswer {
                u: &u,
                image_to_physical: &image_to_physical,
                info: &sol.info,
                rigid_prior: rigid.prior.as_ref(),
            };
            let out = correct_libr(g, self.case, self.meas, self.params, libr);
            u = out.u;
            image_to_physical = out.image_to_physical;
            out.info
        });
        self.answer(Answer {
            image_to_physical,
            u,
            rigid,
            pose,
            libr: Some(sol.info),
            correction,
            v2s: None,
            nonlinear,
        })
    }
}

/// The parts of a [`Registration`] a stage decides; [`Run::answer`] adds the rest.
struct Answer {
    image_to_physical: Rigid,
    u: Vec<f64>,
    rigid: WicpResult,
    pose: Option<pose::PoseInfo>,
    libr: Option<libr::LibrInfo>,
    correction: Option<CorrectionInfo>,
    v2s: Option<V2sInfo>,
    nonlinear: Option<libr::NonlinearInfo>,
}
