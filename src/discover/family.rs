//! Candidate families: one effect kind searched over its parameter grid on top of the current
//! model, a support paired with the loads it carries, and how far the shape parameters the data
//! cannot tell apart spread.

use super::SearchGrid;
use super::search::{self, Candidate, Current, SearchContext, basis_design};
use super::stats::paired;
use super::{DiscoverError, prior};
use crate::register::physics::kinds::{GridValues, Place, Search, SiteGrid};
use crate::register::physics::model::ModelSolver;
use crate::register::physics::{Effect, EffectKind, Physics};

/// Searches one kind over its parameter grid on top of the current model, as the kind's
/// [`Search`] in the table of kinds says.
pub(super) fn search_family(
    ctx: &SearchContext<'_>,
    cur: &Current,
    kind: EffectKind,
    grid: &SearchGrid,
) -> Result<Vec<Candidate>, DiscoverError> {
    match kind.spec().search {
        Search::None => Ok(Vec::new()),
        Search::Directions {
            count,
            direction,
            amplitude,
            start,
        } => search_directions(ctx, cur, kind, count(grid), (direction, amplitude, start)),
        Search::Grid { site, vary, fixed } => search_grid(ctx, cur, kind, grid, site, vary, fixed),
    }
}

/// A candidate evaluated as its kind enters the model: a load's columns on top of the current
/// model, or a rebuilt basis.
fn evaluate(
    ctx: &SearchContext<'_>,
    cur: &Current,
    e: &Effect,
) -> Result<Option<Candidate>, DiscoverError> {
    if e.kind.is_load() {
        search::evaluate_load(ctx, cur, e)
    } else {
        search::evaluate_rebuilt(ctx, cur, e)
    }
}

/// [`Search::Directions`]: `count` directions over the sphere (those physics rules out
/// dropped), the best three refined; `(direction, amplitude, start)` name the parameters and
/// the amplitude the candidates are made with.
fn search_directions(
    ctx: &SearchContext<'_>,
    cur: &Current,
    kind: EffectKind,
    count: usize,
    (dir_name, amp, amp_value): (&str, &str, f64),
) -> Result<Vec<Candidate>, DiscoverError> {
    let mut out = Vec::new();
    let mut push = |c: Option<Candidate>| {
        if let Some(c) = c {
            out.push(c);
        }
    };
    let make = |d: [f64; 3]| Effect::new(kind, &[(dir_name, &d), (amp, &[amp_value])]);
    let mut tried = Vec::new();
    // Directions over the sphere, those physics rules out dropped (a prone patient,
    // insufflation behind the organ: see [`prior::direction_cone`]).
    for d in search::sphere_directions(count)
        .into_iter()
        .filter(|d| prior::direction_plausible(kind, *d))
    {
        let e = make(d)?;
        let c = evaluate(ctx, cur, &e)?;
        tried.push((
            d,
            c.as_ref()
                .map(|c| c.score.full_rss)
                .unwrap_or(f64::INFINITY),
        ));
        push(c);
    }
    // Refine the three best grid directions by a pattern search with shrinking turns
    // (a turn is repeated while it improves). Directions are estimated by the full fit's
    // misfit (maximum likelihood, sharper than the held-out score); whether the effect
    // is real is the held-out score's question.
    tried.sort_by(|a, b| a.1.total_cmp(&b.1));
    let starts: Vec<([f64; 3], f64)> = tried.iter().take(3).copied().collect();
    for start in starts {
        let mut best = start;
        for step in [20.0f64, 10.0, 5.0, 2.5, 1.25] {
            let mut moved = true;
            let mut guard = 0;
            while moved && guard < 6 {
                moved = false;
                guard += 1;
                for d in search::neighbours(best.0, step.to_radians())
                    .into_iter()
                    .filter(|d| prior::direction_plausible(kind, *d))
                {
                    let e = make(d)?;
                    let c = evaluate(ctx, cur, &e)?;
                    let s = c
                        .as_ref()
                        .map(|c| c.score.full_rss)
                        .unwrap_or(f64::INFINITY);
                    if s < best.1 {
                        best = (d, s);
                        moved = true;
                    }
                    push(c);
                }
            }
        }
    }
    Ok(out)
}

/// [`Search::Grid`]: at each site (once without one) each value of the varied parameter, the
/// fixed parameters held.
fn search_grid(
    ctx: &SearchContext<'_>,
    cur: &Current,
    kind: EffectKind,
    grid: &SearchGrid,
    site: Option<SiteGrid>,
    (vary, values): (&str, GridValues),
    fixed: &[(&str, &[f64])],
) -> Result<Vec<Candidate>, DiscoverError> {
    let mut out = Vec::new();
    let sites: Vec<Option<(&str, [f64; 3])>> = match site {
        None => vec![None],
        Some(s) => {
            let at = match s.place {
                Place::Boundary => search::boundary_sites(ctx.mesh, ctx.geom, (s.count)(grid)),
                Place::Interior { depth } => {
                    search::interior_sites(ctx.mesh, ctx.geom, depth, (s.count)(grid))
                }
            };
            at.into_iter().map(|c| Some((s.name, c))).collect()
        }
    };
    for site in &sites {
        for v in values(grid) {
            let mut params: Vec<(&str, &[f64])> = Vec::with_capacity(fixed.len() + 2);
            if let Some((name, c)) = site {
                params.push((name, c));
            }
            params.push((vary, std::slice::from_ref(v)));
            params.extend_from_slice(fixed);
            let e = Effect::new(kind, &params)?;
            if let Some(c) = evaluate(ctx, cur, &e)? {
                out.push(c);
            }
        }
    }
    Ok(out)
}

/// The factorized model of `physics` on the case (for load columns on top of it).
pub(super) fn solver_for(
    ctx: &SearchContext<'_>,
    physics: &Physics,
) -> Result<std::sync::Arc<ModelSolver>, DiscoverError> {
    Ok(std::sync::Arc::new(ModelSolver::new(
        ctx.mesh,
        &ctx.libr.basis.material,
        ctx.sites,
        physics,
    )?))
}

/// The pairs of a support candidate `support` (from [`search::evaluate_rebuilt`]) and each load
/// kind of `loads` carried by it: the load's family searched on top of the supported model, its
/// best returned as a candidate with the support as its partner, scored against the current
/// model (both columns' parameters counted).
pub(super) fn pair_candidates(
    ctx: &SearchContext<'_>,
    cur: &Current,
    support: &Candidate,
    loads: &[EffectKind],
    grid: &SearchGrid,
) -> Result<Vec<(Candidate, Vec<Candidate>)>, DiscoverError> {
    let Some(basis) = support.basis.clone() else {
        return Ok(Vec::new());
    };
    let physics = with_effect(&cur.physics, &support.effect);
    let solver = solver_for(ctx, &physics)?;
    let (a, prior) = basis_design(ctx.rows, &basis, ctx.libr.fit.regularization);
    let supported = Current {
        physics,
        basis,
        solver,
        a,
        prior,
        amplitude: support
            .amplitude
            .clone()
            .unwrap_or_else(|| cur.amplitude.clone()),
        score: support.score.clone(),
    };
    let mut out = Vec::new();
    for &kind in loads {
        let family = search_family(ctx, &supported, kind, grid)?;
        let Some(best) = search::best_fit(&family) else {
            continue;
        };
        let top = Candidate {
            partner: Some(support.effect.clone()),
            parameters: best.parameters + support.parameters,
            columns: None,
            basis: None,
            ..best
        };
        out.push((top, family));
    }
    Ok(out)
}

/// The spread of the shape parameters among the family's candidates the data cannot tell apart
/// from the best (paired t below 2 against it), plus the amplitudes' standard deviations.
pub(super) fn shape_uncertainty(top: &Candidate, family: &[Candidate]) -> serde_json::Value {
    let mut out = serde_json::Map::new();
    for (name, sd) in &top.amplitude_sd {
        out.insert(name.clone(), serde_json::json!(sd));
    }
    let close: Vec<&Candidate> = family
        .iter()
        .filter(|c| paired(&c.score, &top.score).0 < 2.0)
        .collect();
    let p = &top.effect.parameters;
    if p.contains_key("direction") {
        let d = top.effect.direction("direction");
        let spread = close
            .iter()
            .map(|c| search::angle_deg(d, c.effect.direction("direction")))
            .fold(0.0, f64::max);
        out.insert("direction_deg".into(), serde_json::json!(spread));
    }
    if p.contains_key("center") {
        let c0 = top.effect.vector("center");
        let spread = close
            .iter()
            .map(|c| crate::mesh::vec3::dist2(c0, c.effect.vector("center")).sqrt())
            .fold(0.0, f64::max);
        out.insert("center_mm".into(), serde_json::json!(spread));
    }
    if p.contains_key("stiffness") {
        let k: Vec<f64> = close.iter().map(|c| c.effect.scalar("stiffness")).collect();
        let (lo, hi) = k
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
        out.insert("stiffness_range".into(), serde_json::json!([lo, hi]));
    }
    serde_json::Value::Object(out)
}

/// The physics of `current` plus `effect`: stiffness effects first, then loads (the order
/// [`search::evaluate_rebuilt`] builds bases in; loads keep theirs, the new one last).
pub(super) fn with_effect(current: &Physics, effect: &Effect) -> Physics {
    let all: Vec<&Effect> = current
        .effects
        .iter()
        .chain(std::iter::once(effect))
        .collect();
    Physics {
        effects: all
            .iter()
            .filter(|e| !e.kind.is_load())
            .chain(all.iter().filter(|e| e.kind.is_load()))
            .map(|e| (*e).clone())
            .collect(),
    }
}
