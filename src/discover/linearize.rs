//! A cohort's registrations linearized: every sweep registered with a model, its misfit turned
//! into rows at the converged correspondences, over spatial blocks; and the rows two
//! linearizations share.

use super::rows::{CohortRows, cluster_centers, nearest, scenario_rows};
use super::{DiscoverError, DiscoverParams, Sweep, in_time};
use crate::pipeline::{Method, PipelineError, Prepared, register};
use rayon::prelude::*;

/// Registers every sweep with `prepared`'s model (wICP, then LIBR with the physics it carries)
/// and linearizes the misfit at the converged correspondences: one row per match along its
/// direction, over the spatial blocks `centers` (k-means of the pooled points when `None`).
/// Returns the registrations, each sweep's points in the image frame, and the rows.
#[allow(clippy::type_complexity)]
pub(super) fn linearize(
    prepared: &Prepared,
    sweeps: &[Sweep],
    params: &DiscoverParams,
    centers: Option<&[[f64; 3]]>,
    progress: &(dyn Fn(&str, usize, usize) + Sync),
) -> Result<
    (
        Vec<crate::pipeline::Registration>,
        Vec<Vec<[f64; 3]>>,
        CohortRows,
    ),
    DiscoverError,
> {
    let stage = if prepared.physics.is_empty() {
        "registering sweeps".to_string()
    } else {
        format!("registering sweeps with {}", prepared.physics.describe())
    };
    progress(&stage, 0, sweeps.len());
    let done = std::sync::atomic::AtomicUsize::new(0);
    let regs: Vec<crate::pipeline::Registration> =
        sweeps
            .par_iter()
            .map(|s| {
                in_time(params, &format!("registering sweep {}", s.id))?;
                let r = register(prepared, &s.measurements, Method::Libr, &params.pipeline)
                    .map_err(|e| DiscoverError::Scenario {
                        scenario: s.id.clone(),
                        cause: e,
                    });
                let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                progress(&stage, d, sweeps.len());
                r
            })
            .collect::<Result<_, _>>()?;
    let cparams = params.pipeline.libr_correspondence();
    let mut images: Vec<Vec<[f64; 3]>> = Vec::with_capacity(sweeps.len());
    let mut all_matches = Vec::with_capacity(sweeps.len());
    for (s, reg) in sweeps.iter().zip(&regs) {
        let inv = reg.image_to_physical.inverse();
        let pts: Vec<[f64; 3]> = s
            .measurements
            .points
            .iter()
            .map(|&p| inv.apply(p))
            .collect();
        let (m, _) = prepared
            .correspondence
            .match_points(&pts, &s.measurements, Some(&reg.u), &cparams)
            .map_err(|e| DiscoverError::Scenario {
                scenario: s.id.clone(),
                cause: PipelineError::Libr(e),
            })?;
        images.push(pts);
        all_matches.push(m);
    }
    let centers = match centers {
        Some(c) => c.to_vec(),
        None => {
            let pooled: Vec<[f64; 3]> = images.iter().flatten().copied().collect();
            cluster_centers(&pooled, params.folds)
        }
    };
    let mut rows_v = Vec::new();
    for (s, (m, pts)) in all_matches.iter().zip(&images).enumerate() {
        scenario_rows(s, m, pts, |p| nearest(&centers, p), &mut rows_v);
    }
    let rows = CohortRows {
        rows: rows_v,
        scenarios: sweeps.len(),
        clusters: centers.len(),
        centers,
    };
    Ok((regs, images, rows))
}

/// The rows of `a` and of `b` whose (sweep, point) both have: the same measured points, each at
/// its own model's correspondences (trimming keeps different points for different fits).
pub(super) fn common_rows(a: &CohortRows, b: &CohortRows) -> (Vec<usize>, Vec<usize>) {
    use std::collections::HashSet;
    let ka: HashSet<(usize, usize)> = a.rows.iter().map(|r| (r.scenario, r.point)).collect();
    let kb: HashSet<(usize, usize)> = b.rows.iter().map(|r| (r.scenario, r.point)).collect();
    let pick = |rows: &CohortRows, other: &HashSet<(usize, usize)>| {
        rows.rows
            .iter()
            .enumerate()
            .filter(|(_, r)| other.contains(&(r.scenario, r.point)))
            .map(|(i, _)| i)
            .collect::<Vec<usize>>()
    };
    (pick(a, &kb), pick(b, &ka))
}

/// A subset of the rows (same blocks).
pub(super) fn subset(rows: &CohortRows, idx: &[usize]) -> CohortRows {
    CohortRows {
        rows: idx.iter().map(|&i| rows.rows[i]).collect(),
        scenarios: rows.scenarios,
        clusters: rows.clusters,
        centers: rows.centers.clone(),
    }
}
