//! Find (steps 1 and 2): the plain model's registrations and cross-validated misfit, the noise
//! floor, the bootstrap null, and whether richer loads explain more.

use super::cv::{
    self, AmplitudePrior, CvScore, Design, cross_validate, cross_validate_rhs, fitted,
};
use super::linearize::linearize;
use super::rows::CohortRows;
use super::search::basis_design;
use super::stats::{gaussian, paired};
use super::{CandidateRecord, DiscoverError, DiscoverParams, Sweep, in_time, noise};
use crate::pipeline::Prepared;
use crate::register::physics::model::BoundaryGeometry;
use crate::register::{MeasuredKind, PreopModel};
use rayon::prelude::*;
use std::path::Path;
use std::time::Instant;

/// What the find stage leaves for naming: the plain model's registrations, rows and
/// cross-validated score, the noise floor, and whether the data disagree beyond noise.
pub(super) struct Found {
    pub(super) prepared: Prepared,
    pub(super) plain: Vec<crate::pipeline::Registration>,
    pub(super) rows: CohortRows,
    pub(super) geom: BoundaryGeometry,
    pub(super) basis: crate::register::libr::LibrBasis,
    pub(super) a: nalgebra::DMatrix<f64>,
    pub(super) prior: nalgebra::DMatrix<f64>,
    pub(super) base_score: CvScore,
    pub(super) noise_floor_mm: f64,
    pub(super) noise_var: f64,
    pub(super) null_max_mm: f64,
    pub(super) beyond_noise: bool,
    pub(super) heldout_at_lambda_mm: f64,
    pub(super) richer_loads: bool,
    /// The `refine-loads` record, where LIBR's loads cross-validate best under a weaker prior.
    pub(super) refine_record: Option<CandidateRecord>,
    pub(super) register_s: f64,
    pub(super) find_s: f64,
}

/// Steps 1 and 2: registers every sweep with plain LIBR, linearizes, cross-validates plain LIBR,
/// estimates the noise floor and the bootstrap null, and asks whether richer loads explain more.
pub(super) fn find(
    model: &PreopModel,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    cache_dir: Option<&Path>,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<Found, DiscoverError> {
    let t0 = Instant::now();
    check_cohort(sweeps, params)?;
    // 1. Register each sweep with plain LIBR.
    let prepared =
        Prepared::new(model.clone(), Some(&params.pipeline.libr), cache_dir).map_err(|e| {
            DiscoverError::Scenario {
                scenario: "(case)".into(),
                cause: e,
            }
        })?;
    let (plain, images, rows) = linearize(&prepared, sweeps, params, None, progress)?;
    let register_s = crate::util::secs(t0);
    let t1 = Instant::now();
    in_time(params, "registering the sweeps")?;
    if rows.rows.len() < 50 {
        return Err(DiscoverError::Underdetermined(format!(
            "the cohort's {} sweeps give only {} matched rows; discovery needs at least 50",
            sweeps.len(),
            rows.rows.len()
        )));
    }
    // Noise floor: median over sweeps of the local-quadric estimate on surface points.
    let local_floor = local_noise_floor(sweeps, &images);
    // Base model.
    let geom = BoundaryGeometry::new(&model.mesh)?;
    let libr = &params.pipeline.libr;
    let basis = prepared
        .basis
        .clone()
        .ok_or_else(|| DiscoverError::Input("the case has no LIBR basis".into()))?;
    let (a, prior) = basis_design(&rows, &basis, libr.fit.regularization);
    let no_amplitude = AmplitudePrior::none(a.ncols());
    let base_score = cross_validate(
        &rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &no_amplitude,
        },
    )
    .ok_or_else(|| {
        DiscoverError::Underdetermined(
            "no fold could be fitted: too few points per sweep and block".into(),
        )
    })?;
    // The noise floor: the smaller of two estimates that can only overstate it, the local
    // quadrics (curvature the quadric misses) and plain LIBR's in-sample misfit corrected for its
    // degrees of freedom (model error it cannot fit).
    let dof = (rows.rows.len() as f64 - a.ncols() as f64 - 6.0 * sweeps.len() as f64).max(1.0);
    let insample_floor =
        (base_score.full_rss / base_score.full_w.max(1e-300) * rows.rows.len() as f64 / dof).sqrt();
    let noise_floor_mm = local_floor.min(insample_floor);
    progress("bootstrap", 0, params.bootstrap);
    let noise_var = noise_floor_mm * noise_floor_mm;
    let null = bootstrap_null(&rows, &a, &prior, &base_score, noise_floor_mm, params);
    let null_max_mm = null.iter().copied().fold(0.0, f64::max);
    let before_rms = base_score.heldout_mse.sqrt();
    let beyond_noise = before_rms > null_max_mm && before_rms > 1.25 * noise_floor_mm;
    let find_s = crate::util::secs(t1);
    in_time(params, "testing the misfit against noise")?;
    let (refine_record, richer_loads, heldout_at_lambda_mm) =
        refine_loads(&rows, &a, &prior, &base_score, params);
    Ok(Found {
        prepared,
        plain,
        rows,
        geom,
        basis,
        a,
        prior,
        base_score,
        noise_floor_mm,
        noise_var,
        null_max_mm,
        beyond_noise,
        heldout_at_lambda_mm,
        richer_loads,
        refine_record,
        register_s,
        find_s,
    })
}

/// Checks a cohort before discovery: at least two sweeps, two folds, and points in every sweep
/// (their measurements were checked when made).
fn check_cohort(sweeps: &[Sweep], params: &DiscoverParams) -> Result<(), DiscoverError> {
    if sweeps.is_empty() {
        return Err(DiscoverError::Input(
            "cohort: no scenarios (a cohort needs at least 2 sweeps of one deformed state)".into(),
        ));
    }
    if sweeps.len() < 2 {
        return Err(DiscoverError::Input(format!(
            "cohort: only 1 scenario ({}); cross-validation across sweeps needs at least 2",
            sweeps[0].id
        )));
    }
    if params.folds < 2 {
        return Err(DiscoverError::Input(format!(
            "folds: {} (at least 2 spatial blocks are needed to hold one out)",
            params.folds
        )));
    }
    for s in sweeps {
        crate::register::measured::not_empty(&s.measurements)
            .map_err(|e| DiscoverError::Input(format!("scenario {}: measurements: {e}", s.id)))?;
    }
    Ok(())
}

/// The median over sweeps of the local-quadric noise estimate on each sweep's surface points
/// (`images`: the points in the image frame); infinity when no sweep gives one.
fn local_noise_floor(sweeps: &[Sweep], images: &[Vec<[f64; 3]>]) -> f64 {
    let mut floors: Vec<f64> = sweeps
        .iter()
        .zip(images)
        .filter_map(|(s, pts)| {
            let surf: Vec<[f64; 3]> = pts
                .iter()
                .zip(&s.measurements.kind)
                .filter(|(_, k)| **k == MeasuredKind::Surface)
                .map(|(p, _)| *p)
                .collect();
            noise::noise_floor(&surf).map(|(s, _)| s)
        })
        .collect();
    floors.sort_by(f64::total_cmp);
    if floors.is_empty() {
        f64::INFINITY
    } else {
        floors[floors.len() / 2]
    }
}

/// The bootstrap null, posterior-predictive: if plain LIBR were right, the truth would be a
/// draw of its weights from their posterior (the fit plus what the sparse data leave open, at
/// the prior's scale), seen with noise at the floor. Cross-validating such replicates the same
/// way gives the held-out misfit (RMS, mm) that noise *and* sparse extrapolation explain, one
/// per replicate that could be fitted.
fn bootstrap_null(
    rows: &CohortRows,
    a: &nalgebra::DMatrix<f64>,
    prior: &nalgebra::DMatrix<f64>,
    base_score: &CvScore,
    noise_floor_mm: f64,
    params: &DiscoverParams,
) -> Vec<f64> {
    let null_prior = prior * base_score.prior_scale;
    let no_amplitude = AmplitudePrior::none(a.ncols());
    let posterior = (&base_score.inverse * (noise_floor_mm * noise_floor_mm)).cholesky();
    (0..params.bootstrap)
        .into_par_iter()
        .filter_map(|k| {
            let mut rng = crate::util::SplitMix64::new(
                params.seed ^ (k as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            );
            let mut draw = base_score.clone();
            if let Some(ch) = &posterior {
                let z = nalgebra::DVector::from_fn(draw.coef.len(), |_, _| gaussian(&mut rng));
                draw.coef += ch.l() * z;
            }
            let fit = fitted(rows, a, &draw);
            let b: Vec<f64> = fit
                .iter()
                .map(|f| f + noise_floor_mm * gaussian(&mut rng))
                .collect();
            cross_validate_rhs(
                rows,
                &Design {
                    a,
                    prior: &null_prior,
                    amplitude: &no_amplitude,
                },
                &b,
            )
            .map(|s| s.heldout_mse.sqrt())
        })
        .collect()
}

/// Richer loads: does plain LIBR under a weaker prior than registration's λ explain more? The
/// `refine-loads` record (when the cross-validated prior is weaker than λ), whether it passes
/// the rule, and the held-out misfit at λ (mm).
fn refine_loads(
    rows: &CohortRows,
    a: &nalgebra::DMatrix<f64>,
    prior: &nalgebra::DMatrix<f64>,
    base_score: &CvScore,
    params: &DiscoverParams,
) -> (Option<CandidateRecord>, bool, f64) {
    let before_rms = base_score.heldout_mse.sqrt();
    let at_lambda = cv::cross_validate_at(
        rows,
        &Design {
            a,
            prior,
            amplitude: &AmplitudePrior::none(a.ncols()),
        },
        1.0,
    );
    let mut record = None;
    let mut richer_loads = false;
    if let Some(l) = at_lambda.as_ref().filter(|_| base_score.prior_scale < 1.0) {
        let (z, t, gain) = paired(l, base_score);
        richer_loads = z > params.z_threshold && gain > params.min_gain;
        record = Some(CandidateRecord {
            round: 0,
            kind: "refine-loads".into(),
            effect: format!("LIBR's loads at {} × λ (against λ)", base_score.prior_scale),
            heldout_rms_mm: before_rms,
            gain,
            rank_z: z,
            t,
            delta_bic: f64::NAN,
            relinearized: false,
            significant: richer_loads,
        });
    }
    let heldout_at_lambda_mm = at_lambda.map_or(before_rms, |l| l.heldout_mse.sqrt());
    (record, richer_loads, heldout_at_lambda_mm)
}
