//! The statistics discovery decides by: paired comparisons of held-out misfits (Wilcoxon's
//! signed-rank z, the paired t), the change of the Bayesian information criterion, and normal
//! draws for the bootstrap.

use super::cv::CvScore;

pub(super) fn gaussian(rng: &mut crate::util::SplitMix64) -> f64 {
    let (u1, u2) = (rng.next_f64().max(1e-300), rng.next_f64());
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Paired comparison over the units both scored: the Wilcoxon signed-rank test's z for
/// `sse_cur − sse_cand` (normal approximation with tie correction; ranks make it robust to the
/// heavy tails of per-unit misfits, and unlike a sign test it weighs a large improvement above a
/// small worsening), the t statistic of the differences, and the fraction of the current
/// held-out misfit removed.
pub(super) fn paired(cur: &CvScore, cand: &CvScore) -> (f64, f64, f64) {
    let d: Vec<f64> = cur
        .unit_sse
        .iter()
        .zip(&cand.unit_sse)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| a - b)
        .collect();
    let total: f64 = cur.unit_sse.iter().filter(|x| x.is_finite()).sum();
    if d.len() < 2 || total <= 0.0 {
        return (0.0, 0.0, 0.0);
    }
    let rank_z = signed_rank_z(&d);
    let n = d.len() as f64;
    let mean = d.iter().sum::<f64>() / n;
    let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let t = if var > 0.0 {
        mean / (var / n).sqrt()
    } else if mean > 0.0 {
        f64::INFINITY
    } else {
        0.0
    };
    (rank_z, t, d.iter().sum::<f64>() / total)
}

/// Wilcoxon signed-rank z of differences (zeros dropped, tied magnitudes get their mean rank).
pub(super) fn signed_rank_z(d: &[f64]) -> f64 {
    let mut nz: Vec<f64> = d.iter().copied().filter(|x| *x != 0.0).collect();
    let n = nz.len();
    if n == 0 {
        return 0.0;
    }
    nz.sort_by(|a, b| a.abs().total_cmp(&b.abs()));
    let (mut w_plus, mut tie) = (0.0, 0.0);
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && nz[j + 1].abs() == nz[i].abs() {
            j += 1;
        }
        let rank = (i + j) as f64 / 2.0 + 1.0;
        let t = (j - i + 1) as f64;
        tie += t * t * t - t;
        for x in &nz[i..=j] {
            if *x > 0.0 {
                w_plus += rank;
            }
        }
        i = j + 1;
    }
    let nf = n as f64;
    let mean = nf * (nf + 1.0) / 4.0;
    let var = nf * (nf + 1.0) * (2.0 * nf + 1.0) / 24.0 - tie / 48.0;
    if var <= 0.0 {
        0.0
    } else {
        (w_plus - mean) / var.sqrt()
    }
}

/// Change of the Bayesian information criterion from `cur` to `cand` (negative favours
/// `cand`), each by its own mean-square misfit, `extra` parameters added.
pub(super) fn bic_change(cur: &CvScore, cand: &CvScore, extra: usize) -> f64 {
    let n = cand.rows as f64;
    let ms = |s: &CvScore| s.full_rss / s.full_w.max(1e-300);
    n * (ms(cand) / ms(cur)).ln() + extra as f64 * n.ln()
}
