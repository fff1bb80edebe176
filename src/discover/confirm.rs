//! Confirmation: a promising candidate checked on its own linearization (every sweep registered
//! again with the augmented model) against the current model on the points both matched.

use super::cv::{CvScore, Design, cross_validate};
use super::family::{search_family, solver_for, with_effect};
use super::linearize::{common_rows, linearize, subset};
use super::rows::CohortRows;
use super::search::{self, Candidate, Current, SearchContext, basis_design};
use super::stats::paired;
use super::{DiscoverError, DiscoverParams, Sweep};
use crate::pipeline::Prepared;
use crate::register::RegisterError;
use crate::register::physics::{Effect, Physics};

/// A candidate confirmed on its own linearization.
pub(super) struct Confirmed {
    /// The augmented model's physics.
    pub(super) physics: Physics,
    /// The augmented model as the next round's current model.
    pub(super) current: Current,
    /// The rows it is linearized at.
    pub(super) rows: CohortRows,
    /// The candidate's effect with its amplitudes fitted on those rows (load effects).
    pub(super) refitted: Option<Effect>,
    /// The current model and the candidate scored on the points both linearizations matched
    /// (each at its own correspondences): the fair comparison.
    pub(super) compared: (CvScore, CvScore),
}

/// Confirms a candidate ([`confirm_once`]), then estimates its shape parameters again on its own
/// linearization (the kind searched afresh on the rows the augmented registrations matched,
/// which lie closer to the truth than plain LIBR's when the effect is large) and, where they
/// moved, confirms the re-estimate too; the better of the two (by the held-out misfit removed)
/// is returned.
pub(super) fn confirm(
    ctx: &SearchContext<'_>,
    prepared: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cur: &Current,
    top: &Candidate,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Option<Confirmed>, DiscoverError> {
    let Some(first) = confirm_once(ctx, prepared, sweeps, params, cur, top, progress)? else {
        return Ok(None);
    };
    if top.partner.is_some() {
        // A pair's load was searched on top of its support: confirmed as found.
        return Ok(Some(first));
    }
    let (a, _) = basis_design(&first.rows, &cur.basis, ctx.libr.fit.regularization);
    let Some(score) = cross_validate(
        &first.rows,
        &Design {
            a: &a,
            prior: &cur.prior,
            amplitude: &cur.amplitude,
        },
    ) else {
        return Ok(Some(first));
    };
    let there = Current {
        physics: cur.physics.clone(),
        basis: cur.basis.clone(),
        solver: cur.solver.clone(),
        a,
        prior: cur.prior.clone(),
        amplitude: cur.amplitude.clone(),
        score,
    };
    let ctx2 = SearchContext {
        rows: &first.rows,
        ..*ctx
    };
    let family = search_family(&ctx2, &there, top.effect.kind, &params.grid)?;
    let Some(top2) = search::best_fit(&family) else {
        return Ok(Some(first));
    };
    if same_shape(&top2.effect, &top.effect) {
        return Ok(Some(first));
    }
    // A rebuilt candidate's basis was built for the plain rows' search; it is the same basis.
    let Some(second) = confirm_once(ctx, prepared, sweeps, params, cur, &top2, progress)? else {
        return Ok(Some(first));
    };
    let gain = |c: &Confirmed| paired(&c.compared.0, &c.compared.1).2;
    Ok(Some(if gain(&second) > gain(&first) {
        second
    } else {
        first
    }))
}

/// Whether two effects of a kind have the same shape parameters (amplitudes aside).
fn same_shape(a: &Effect, b: &Effect) -> bool {
    let amplitude = a.kind.amplitude().map(|(n, _)| n);
    a.kind == b.kind
        && a.parameters
            .iter()
            .filter(|(k, _)| amplitude != Some(k.as_str()))
            .all(|(k, v)| b.parameters.get(k).is_some_and(|w| w == v))
}

/// Registers every sweep again with the current model plus the candidate, linearizes there and
/// cross-validates the augmented model on those rows. `None` when the augmented model cannot
/// be built or a sweep cannot be registered with it (then it is no candidate).
pub(super) fn confirm_once(
    ctx: &SearchContext<'_>,
    prepared: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cur: &Current,
    top: &Candidate,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Option<Confirmed>, DiscoverError> {
    let physics = match &top.partner {
        Some(p) => with_effect(&with_effect(&cur.physics, p), &top.effect),
        None => with_effect(&cur.physics, &top.effect),
    };
    let basis = match &top.basis {
        Some(b) => b.clone(),
        None => match crate::register::libr::LibrBasis::build_with(
            ctx.mesh, ctx.libr, &physics, ctx.sites,
        ) {
            Ok(b) => b,
            Err(RegisterError::Model(_)) => return Ok(None),
            Err(e) => return Err(e.into()),
        },
    };
    let augmented = Prepared {
        model: prepared.model.clone(),
        correspondence: prepared.correspondence.clone(),
        basis: Some(basis.clone()),
        basis_from_cache: false,
        librplus: None,
        v2s: None,
        adaptive: None,
        physics: physics.clone(),
        error_model: None,
        nonlinear: std::sync::OnceLock::new(),
        seconds: 0.0,
    };
    let rows = match linearize(
        &augmented,
        sweeps,
        params,
        Some(&ctx.rows.centers),
        progress,
    ) {
        Ok((_, _, rows)) => rows,
        Err(DiscoverError::Scenario { .. }) => return Ok(None),
        Err(e) => return Err(e),
    };
    let (a, prior) = basis_design(&rows, &basis, ctx.libr.fit.regularization);
    let amplitude = search::basis_amplitude_prior(ctx, &basis, &physics);
    let Some(score) = cross_validate(
        &rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &amplitude,
        },
    ) else {
        return Ok(None);
    };
    // The fair comparison: both models on the points both matched.
    let (ic, ia) = common_rows(ctx.rows, &rows);
    let (rc, ra) = (subset(ctx.rows, &ic), subset(&rows, &ia));
    let (ac, aa) = (cur.a.select_rows(&ic), a.select_rows(&ia));
    let (Some(sc), Some(sa)) = (
        cross_validate(
            &rc,
            &Design {
                a: &ac,
                prior: &cur.prior,
                amplitude: &cur.amplitude,
            },
        ),
        cross_validate(
            &ra,
            &Design {
                a: &aa,
                prior: &prior,
                amplitude: &amplitude,
            },
        ),
    ) else {
        return Ok(None);
    };
    // The new effect's amplitudes on these rows.
    let refitted = if top.effect.kind.is_load() {
        let mut j = basis.libr_columns();
        let mut out = None;
        for e in physics.effects.iter().filter(|e| e.kind.is_load()) {
            let k = e.kind.amplitude().map_or(0, |(_, k)| k);
            if e.kind == top.effect.kind {
                let amp: Vec<f64> = (0..k)
                    .map(|i| score.coef[j + i] * basis.load_scale[j + i])
                    .collect();
                let Some(e) = search::with_amplitudes(e, amp, &physics) else {
                    return Ok(None);
                };
                out = Some(e);
            }
            j += k;
        }
        out
    } else {
        None
    };
    let solver = solver_for(ctx, &physics)?;
    Ok(Some(Confirmed {
        physics: physics.clone(),
        current: Current {
            physics,
            basis,
            solver,
            a,
            prior,
            amplitude,
            score,
        },
        rows,
        refitted,
        compared: (sc, sa),
    }))
}
