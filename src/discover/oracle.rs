//! The oracle's detectability: could the workflow's own held-out test see a cohort's effects if it
//! were told everything? For generated data only (the truth is an argument here; nothing at
//! inference calls it): `generate` records it per deformation, so a discovery is judged on what
//! its data can show.
//!
//! The true effects, with their true shapes, are built into the augmented model (their
//! amplitudes fitted, as the workflow fits a named effect's); every sweep is registered with
//! the baseline (plain LIBR plus the effects not under test, e.g. what carries a hidden load) and
//! with the whole true model from the pose its measurements start at (the caller gives the true
//! pose), the misfit linearized at each model's own correspondences, and the two
//! cross-validated on the points both matched, by the paired test and the rule with which
//! [`super::discover_cohort`] names an effect.

use super::cv::{AmplitudePrior, Design, cross_validate};
use super::linearize::{common_rows, linearize, subset};
use super::rows::CohortRows;
use super::search::{SearchContext, basis_amplitude_prior, basis_design, parameter_count};
use super::stats::{bic_change, paired};
use super::{DiscoverError, DiscoverParams, Sweep};
use crate::dataset::Detectability;
use crate::pipeline::Prepared;
use crate::register::physics::Physics;
use crate::register::physics::model::{BoundaryGeometry, Sites};
use crate::register::{PreopModel, RegisterError};
use std::path::Path;

/// The detectability of the effects `truth` adds to `known` (both with their true parameters:
/// `truth` every effect the cohort's data were made with, `known` those of them not under test)
/// in the cohort `sweeps`, whose measurements should start at their true poses. `truth` no
/// larger than `known`: nothing to detect, an error.
pub fn detectability(
    model: &PreopModel,
    sweeps: &[Sweep],
    truth: &Physics,
    known: &Physics,
    params: &DiscoverParams,
    cache_dir: Option<&Path>,
) -> Result<Detectability, DiscoverError> {
    if truth.effects.len() <= known.effects.len() {
        return Err(DiscoverError::Input(
            "truth: no effect beyond the known ones to detect".into(),
        ));
    }
    if sweeps.len() < 2 {
        return Err(DiscoverError::Input(format!(
            "cohort: {} sweeps; cross-validation across sweeps needs at least 2",
            sweeps.len()
        )));
    }
    let libr = &params.pipeline.libr;
    let prepare = |physics: &Physics, what: &str| {
        Prepared::with_physics(model.clone(), Some(libr), physics, cache_dir).map_err(|e| match e {
            crate::pipeline::PipelineError::Libr(RegisterError::Model(m)) => {
                DiscoverError::Input(format!("{what}: the augmented model cannot be built: {m}"))
            }
            e => DiscoverError::Scenario {
                scenario: format!("(case, {what})"),
                cause: e,
            },
        })
    };
    let plain = prepare(known, "known")?;
    let augmented = prepare(truth, "truth")?;
    let (active, rows0, rows1) = linearize_both(&plain, &augmented, sweeps, params)?;
    let (b0, b1) = match (&plain.basis, &augmented.basis) {
        (Some(b0), Some(b1)) => (b0, b1),
        _ => return Err(DiscoverError::Input("the case has no LIBR basis".into())),
    };
    let geom = BoundaryGeometry::new(&model.mesh)?;
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    let (ic, ia) = common_rows(&rows0, &rows1);
    let (r0, r1) = (subset(&rows0, &ic), subset(&rows1, &ia));
    let (a0, p0) = basis_design(&r0, b0, libr.fit.regularization);
    let (a1, p1) = basis_design(&r1, b1, libr.fit.regularization);
    let underdetermined = || {
        DiscoverError::Underdetermined(
            "no fold could be fitted: too few points per sweep and block".into(),
        )
    };
    // The amplitude priors are weighed with plain LIBR's in-sample misfit as the noise.
    let noise_var = {
        let (a, p) = basis_design(&r0, b0, libr.fit.regularization);
        let none = AmplitudePrior::none(b0.libr_columns());
        let (a, p) = (
            a.columns(0, b0.libr_columns()).into_owned(),
            p.view((0, 0), (b0.libr_columns(), b0.libr_columns()))
                .into_owned(),
        );
        let s = cross_validate(
            &r0,
            &Design {
                a: &a,
                prior: &p,
                amplitude: &none,
            },
        )
        .ok_or_else(underdetermined)?;
        s.full_rss / s.full_w.max(1e-300)
    };
    let ctx = SearchContext {
        mesh: &model.mesh,
        sites,
        libr,
        rows: &r0,
        geom: &geom,
        noise_var,
    };
    let amplitude0 = basis_amplitude_prior(&ctx, b0, known);
    let s0 = cross_validate(
        &r0,
        &Design {
            a: &a0,
            prior: &p0,
            amplitude: &amplitude0,
        },
    )
    .ok_or_else(underdetermined)?;
    let amplitude = basis_amplitude_prior(&SearchContext { rows: &r1, ..ctx }, b1, truth);
    let s1 = cross_validate(
        &r1,
        &Design {
            a: &a1,
            prior: &p1,
            amplitude: &amplitude,
        },
    )
    .ok_or_else(underdetermined)?;
    let (z, _, gain) = paired(&s0, &s1);
    let extra: usize = truth
        .effects
        .iter()
        .map(|e| parameter_count(e.kind))
        .sum::<usize>()
        - known
            .effects
            .iter()
            .map(|e| parameter_count(e.kind))
            .sum::<usize>();
    let delta_bic = bic_change(&s0, &s1, extra);
    Ok(Detectability {
        statistic: z,
        threshold: params.z_threshold,
        gain,
        min_gain: params.min_gain,
        delta_bic,
        detectable: z > params.z_threshold && gain > params.min_gain && delta_bic < 0.0,
        heldout_rms_mm: [s0.heldout_mse.sqrt(), s1.heldout_mse.sqrt()],
        sweeps: active.len(),
        rows: r0.rows.len(),
    })
}

/// Both models' linearizations of the cohort, on the same blocks (the plain model's). A sweep
/// either model cannot register is left out of both (and the blocks drawn again); the sweeps
/// kept are returned with the rows.
fn linearize_both(
    plain: &Prepared,
    augmented: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
) -> Result<(Vec<Sweep>, CohortRows, CohortRows), DiscoverError> {
    let quiet = |_: &str, _: usize, _: usize| {};
    let mut active: Vec<Sweep> = sweeps.to_vec();
    loop {
        if active.len() < 2 {
            return Err(DiscoverError::Underdetermined(format!(
                "only {} of {} sweeps register with both models",
                active.len(),
                sweeps.len()
            )));
        }
        let failed = match linearize(plain, &active, params, None, &quiet) {
            Ok((_, _, r0)) => {
                match linearize(augmented, &active, params, Some(&r0.centers), &quiet) {
                    Ok((_, _, r1)) => return Ok((active, r0, r1)),
                    Err(DiscoverError::Scenario { scenario, .. }) => scenario,
                    Err(e) => return Err(e),
                }
            }
            Err(DiscoverError::Scenario { scenario, .. }) => scenario,
            Err(e) => return Err(e),
        };
        let before = active.len();
        active.retain(|s| s.id != failed);
        if active.len() == before {
            return Err(DiscoverError::Input(format!(
                "sweep {failed}: could not be registered"
            )));
        }
    }
}
