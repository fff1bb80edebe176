//! Show (step 4): the misfit before and after per block, and the verdict.

use super::cv::{AmplitudePrior, CvScore, Design, cross_validate};
use super::find::Found;
use super::linearize::{common_rows, subset};
use super::name::Named;
use super::rows::CohortRows;
use super::{CohortDiscovery, RegionMisfit, StageTimings, Sweep, Verdict};
use crate::register::PreopModel;
use std::time::Instant;

/// Step 4: before and after per block, and the verdict.
pub(super) fn show(
    model: &PreopModel,
    sweeps: &[Sweep],
    found: Found,
    named: Named,
    name_s: f64,
    t0: Instant,
) -> CohortDiscovery {
    let Found {
        plain,
        rows,
        a: base_a,
        prior: base_prior,
        base_score,
        noise_floor_mm,
        null_max_mm,
        beyond_noise,
        heldout_at_lambda_mm,
        richer_loads,
        register_s,
        find_s,
        ..
    } = found;
    let Named {
        cur,
        cur_rows,
        records,
        named,
    } = named;
    // Regions: per block, before and after.
    // Before and after on the points both the plain and the final linearization matched.
    let (before_s, after_s) = if named.is_empty() {
        (base_score.clone(), cur.score.clone())
    } else {
        let (ib, ia) = common_rows(&rows, &cur_rows);
        let none = AmplitudePrior::none(base_a.ncols());
        let b = cross_validate(
            &subset(&rows, &ib),
            &Design {
                a: &base_a.select_rows(&ib),
                prior: &base_prior,
                amplitude: &none,
            },
        );
        let f = cross_validate(
            &subset(&cur_rows, &ia),
            &Design {
                a: &cur.a.select_rows(&ia),
                prior: &cur.prior,
                amplitude: &cur.amplitude,
            },
        );
        match (b, f) {
            (Some(b), Some(f)) => (b, f),
            _ => (base_score.clone(), cur.score.clone()),
        }
    };
    let regions = region_table(&rows, model, &before_s, &after_s);
    let verdict = if !named.is_empty() {
        Verdict::Effects
    } else if richer_loads {
        Verdict::RefineLoads
    } else if beyond_noise {
        Verdict::Unexplained
    } else {
        Verdict::None
    };
    CohortDiscovery {
        verdict,
        effects: named,
        physics: cur.physics.clone(),
        heldout_before_mm: before_s.heldout_mse.sqrt(),
        insample_before_mm: (base_score.full_rss / base_score.full_w.max(1e-300)).sqrt(),
        prior_scale_before: base_score.prior_scale,
        heldout_after_mm: after_s.heldout_mse.sqrt(),
        noise_floor_mm,
        null_max_mm,
        beyond_noise,
        heldout_at_lambda_mm,
        richer_loads,
        regions,
        candidates: records,
        rows: rows.rows.len(),
        sweeps: sweeps.len(),
        plain,
        timings: StageTimings {
            register_s,
            find_s,
            name_s,
            total_s: crate::util::secs(t0),
        },
    }
}

/// Per block: held-out RMS before and after, and how systematic the misfit is across sweeps.
fn region_table(
    rows: &CohortRows,
    model: &PreopModel,
    before: &CvScore,
    after: &CvScore,
) -> Vec<RegionMisfit> {
    let nc = rows.clusters;
    (0..nc)
        .map(|c| {
            let rms = |s: &CvScore| {
                let (mut e, mut w) = (0.0, 0.0);
                for sc in 0..rows.scenarios {
                    let u = sc * nc + c;
                    if s.unit_sse[u].is_finite() {
                        e += s.unit_sse[u];
                        w += s.unit_w[u];
                    }
                }
                if w > 0.0 { (e / w).sqrt() } else { f64::NAN }
            };
            let means: Vec<f64> = (0..rows.scenarios)
                .map(|sc| before.unit_mean[sc * nc + c])
                .filter(|x| x.is_finite())
                .collect();
            let n = means.len() as f64;
            let mean = means.iter().sum::<f64>() / n.max(1.0);
            let sd =
                (means.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
            let t = if sd > 0.0 && n > 1.0 {
                mean / (sd / n.sqrt())
            } else {
                0.0
            };
            let center = rows.centers[c];
            let node = (0..model.mesh.num_nodes())
                .filter(|&v| model.anterior[v] || model.posterior[v])
                .min_by(|&a, &b| {
                    crate::mesh::vec3::dist2(model.mesh.nodes()[a], center)
                        .total_cmp(&crate::mesh::vec3::dist2(model.mesh.nodes()[b], center))
                });
            let region = match node {
                Some(v) if model.falciform[v] => "anterior (falciform)",
                Some(v) if model.inferior_ridge[v] => "anterior (inferior ridge)",
                Some(v) if model.anterior[v] => "anterior",
                Some(v) if model.posterior[v] => "posterior",
                _ => "interior",
            };
            RegionMisfit {
                center,
                region: region.into(),
                before_mm: rms(before),
                after_mm: rms(after),
                mean_signed_mm: mean,
                t_across_sweeps: t,
                sweeps: means.len(),
            }
        })
        .collect()
}
