//! Held-out prediction: how well a fit predicts measured points it did not see.
//!
//! With the matches fixed, one LIBR step is a linear least-squares problem: rows `J`, residuals
//! `r`, the regularised normal matrix `A = JᵀJ + λ/ē·E` (plus the rigid prior's and the hold's
//! rows). [`held_out`] splits the measured points into spatial folds ([`Folds::spatial`]: patches
//! of the measured surface, not random points, because neighbouring closest-point residuals are
//! nearly the same and a random split would only measure the noise), and for each fold solves
//! the system without its rows (`A − J_kᵀJ_k`, `b − J_kᵀr_k`: a downdate, no new matching) and
//! predicts the fold's points. The score is the mean over every measured point of its squared
//! held-out error, each capped at `cap²` (a point the fit left unmatched counts the cap), so a
//! model that explains a patch only by bending into it scores what it predicts there, not what
//! it fitted. Trimmed points are predicted too: a model is not rewarded for the points its own
//! trimming dropped.
//!
//! The same score exists for the rigid answer (six unknowns, [`FitModel::Rigid`]) and for doing
//! nothing ([`FitModel::Fixed`]: no unknowns, the held-out error is the residual), so every
//! candidate of the automatic method is scored on one scale (the pipeline's automatic method).

use super::fit::{RowShape, assemble, match_axis_rows, row_frame, rows_of};
use super::*;
use crate::register::Match;
use faer::Side;
use faer::linalg::solvers::Solve;

/// How the measured points are split for held-out prediction.
#[derive(Debug, Clone, PartialEq)]
pub struct Folds {
    /// The fold of each measured point (indexed as [`Match::point`]).
    pub of_point: Vec<u8>,
    /// Number of folds.
    pub count: usize,
    /// Each point's squared held-out error counts at most `cap_mm²` (mm).
    pub cap_mm: f64,
    /// How many measured points each point stands for in the means (a reduced cloud's
    /// centroids, [`crate::register::Checked::weight`]); empty: one each.
    pub weight: Vec<f64>,
}

impl Folds {
    /// `count` spatial folds of `points`: `count` centres by farthest-point sampling among the
    /// points (the first the point farthest from their centroid; ties to the lowest index), each
    /// point in the fold of its nearest centre. Deterministic. Fewer points than folds give one
    /// fold per point.
    pub fn spatial(points: &[[f64; 3]], count: usize, cap_mm: f64) -> Self {
        let count = count.clamp(1, 255).min(points.len().max(1));
        let n = points.len().max(1) as f64;
        let mut c = [0.0; 3];
        for p in points {
            for a in 0..3 {
                c[a] += p[a] / n;
            }
        }
        let farthest = |d: &[f64]| {
            d.iter()
                .enumerate()
                .fold((0usize, f64::NEG_INFINITY), |b, (i, &x)| {
                    if x > b.1 { (i, x) } else { b }
                })
                .0
        };
        let to_centroid: Vec<f64> = points.iter().map(|&p| dist2(p, c)).collect();
        let mut centres = Vec::with_capacity(count);
        let mut nearest = vec![f64::INFINITY; points.len()];
        let mut of_point = vec![0u8; points.len()];
        if !points.is_empty() {
            centres.push(farthest(&to_centroid));
        }
        while let Some(&last) = centres.last() {
            let k = centres.len() - 1;
            for (i, &p) in points.iter().enumerate() {
                let d = dist2(p, points[last]);
                if d < nearest[i] {
                    nearest[i] = d;
                    of_point[i] = k as u8;
                }
            }
            if centres.len() == count {
                break;
            }
            centres.push(farthest(&nearest));
        }
        Self {
            of_point,
            count,
            cap_mm,
            weight: Vec::new(),
        }
    }

    /// These folds with each point standing for `weight[i]` measured points in the means
    /// (ignored unless as long as the points).
    pub fn weighted(mut self, weight: Vec<f64>) -> Self {
        if weight.len() == self.of_point.len() {
            self.weight = weight;
        }
        self
    }

    /// Point `i`'s weight in the means.
    fn weight_of(&self, i: usize) -> f64 {
        self.weight.get(i).copied().unwrap_or(1.0)
    }
}

/// What a fit predicts of points it did not see ([`held_out`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct HeldOut {
    /// Mean over the measured points of the capped squared held-out error (mm²).
    pub mean_mm2: f64,
    /// The same per fold (mm²; the cap where a fold's system could not be solved).
    pub folds_mm2: Vec<f64>,
    /// The full fit's own mean capped squared error over the same points (mm²).
    pub in_sample_mm2: f64,
}

impl HeldOut {
    /// RMS of the held-out error (mm).
    pub fn rms_mm(&self) -> f64 {
        self.mean_mm2.sqrt()
    }
}

/// The unknowns of a fit whose held-out prediction is measured.
#[derive(Debug, Clone, Copy)]
pub enum FitModel<'a> {
    /// No unknowns: the answer as it stands (doing nothing); the held-out error is the residual.
    Fixed,
    /// The rigid correction alone (six unknowns).
    Rigid,
    /// Basis weights and the rigid correction, the strain energy weighted by `lambda / escale`
    /// (LIBR: its λ and [`LibrBasis::energy_scale`]; adaptive LIBR: the λ it chose and its
    /// broadest level's scale, on its restricted basis).
    Basis {
        /// The basis.
        basis: &'a LibrBasis,
        /// λ.
        lambda: f64,
        /// The energy scale ē λ is relative to.
        escale: f64,
    },
}

/// A basis with no columns on `nodes` nodes: the rows of the rigid unknowns alone.
fn no_columns(nodes: usize) -> LibrBasis {
    LibrBasis {
        control_nodes: Vec::new(),
        nodes,
        phi: Vec::new(),
        energy: Vec::new(),
        load_scale: Vec::new(),
        load_width_mm: 0.0,
        control_width_mm: Vec::new(),
        effect_labels: Vec::new(),
        physics_hash: String::new(),
        mesh_hash: String::new(),
        params_hash: String::new(),
        timings: BasisTimings::default(),
    }
}

/// One match's rows, unscaled by its weight: each row's vector over the unknowns and its
/// residual `y − a` along the row's direction.
fn unscaled_rows(
    basis: &LibrBasis,
    mt: &Match,
    y: [f64; 3],
    sh: &RowShape,
    scratch: &mut [f64],
) -> Vec<(Vec<f64>, f64)> {
    let p = sh.p;
    let r = match_axis_rows(basis, mt, 1.0, y, sh, scratch);
    let frame = row_frame(mt.normal, sh.tw);
    frame
        .iter()
        .take(rows_of(mt, sh.tw))
        .map(|f| {
            let j: Vec<f64> = (0..p)
                .map(|c| f[0] * scratch[c] + f[1] * scratch[p + c] + f[2] * scratch[2 * p + c])
                .collect();
            (j, f[0] * r[0] + f[1] * r[1] + f[2] * r[2])
        })
        .collect()
}

/// A fit's last system (its matches, the targets and the rigid prior's pairs), kept for the
/// held-out check.
pub(super) type LastSystem = (Vec<Match>, Vec<[f64; 3]>, Option<PriorPairs>);

/// [`LibrInfo::held_out`] of a run: [`held_out`] of its last system when `folds` asked for it.
pub(super) fn held_out_of_last(
    folds: Option<&Folds>,
    last: Option<&LastSystem>,
    model: FitModel<'_>,
    params: &LibrParams,
) -> Option<Result<HeldOut, String>> {
    let (folds, (matches, targets, prior)) = (folds?, last?);
    Some(
        held_out(model, matches, targets, params, prior.as_ref(), folds).map_err(|e| e.to_string()),
    )
}

/// The held-out score of a fit (module doc): `matches` are the fit's last matches (held pairs
/// and any match whose point is not a measured point are always fitted, never left out),
/// `targets` the measured points in the image frame of the pose the fit started from, `params`
/// gives the tangential weight, `prior` the rigid prior's pairs. Errors: those of the step's
/// assembly ([`fit_step`]) and a full system that cannot be solved.
pub fn held_out(
    model: FitModel<'_>,
    matches: &[Match],
    targets: &[[f64; 3]],
    params: &LibrParams,
    prior: Option<&PriorPairs>,
    folds: &Folds,
) -> Result<HeldOut, RegisterError> {
    let nodes = matches
        .iter()
        .flat_map(|m| m.nodes)
        .map(|v| v as usize + 1)
        .max()
        .unwrap_or(0);
    let empty;
    let (basis, f) = match model {
        FitModel::Basis {
            basis,
            lambda,
            escale,
        } => (basis, lambda / escale.max(1e-300)),
        _ => {
            empty = no_columns(nodes);
            (&empty, 0.0)
        }
    };
    let sys = System {
        basis,
        f,
        matches,
        targets,
        params,
        prior,
        measured: folds.of_point.len(),
        cap2: folds.cap_mm * folds.cap_mm,
    };
    if let FitModel::Fixed = model {
        // No unknowns: every fold's prediction is the residual as it stands.
        let sh = RowShape {
            m: 0,
            p: 6,
            cen: [0.0; 3],
            radius: 1.0,
            tw: params.fit.tangential_weight.sqrt(),
        };
        let mut err = vec![sys.cap2; sys.measured];
        sys.predict(&sh, &[0.0; 6], &mut err, &|_| true);
        return Ok(summarise(&err, &err, folds));
    }
    let (sh, full) = sys.solve(matches)?.ok_or_else(|| {
        RegisterError::IllConditioned("the held-out check's full system cannot be solved".into())
    })?;
    let mut fitted = vec![sys.cap2; sys.measured];
    sys.predict(&sh, &full, &mut fitted, &|_| true);
    // Each fold: the fit without its points' matches (LIBR's objective on the rest, its mean
    // misfit over the rest), predicting them. A fold whose rest cannot be fitted (too few
    // matches, a singular system) counts the cap.
    let in_fold =
        |mt: &Match, k: usize| mt.point < sys.measured && folds.of_point[mt.point] as usize == k;
    let mut err = vec![sys.cap2; sys.measured];
    for k in 0..folds.count {
        let kept: Vec<Match> = matches.iter().filter(|m| !in_fold(m, k)).cloned().collect();
        let Ok(Some((sh, x))) = sys.solve(&kept) else {
            continue;
        };
        sys.predict(&sh, &x, &mut err, &|m| in_fold(m, k));
    }
    Ok(summarise(&err, &fitted, folds))
}

/// One fit's system, solved on a subset of its matches and predicting the rest.
struct System<'a> {
    basis: &'a LibrBasis,
    /// λ / ē.
    f: f64,
    matches: &'a [Match],
    targets: &'a [[f64; 3]],
    params: &'a LibrParams,
    prior: Option<&'a PriorPairs>,
    /// Number of measured points.
    measured: usize,
    /// The cap on a point's squared error (mm²).
    cap2: f64,
}

impl System<'_> {
    /// The regularised fit of `kept` (None: singular, or not finite) and its row shape.
    fn solve(&self, kept: &[Match]) -> Result<Option<(RowShape, Vec<f64>)>, RegisterError> {
        let mut unregularised = *self.params;
        unregularised.fit.regularization = 0.0;
        let asm = assemble(self.basis, kept, self.targets, &unregularised, self.prior)?;
        let (m, p) = (asm.m, asm.p);
        let mut a = asm.a.clone();
        if self.f > 0.0 {
            for i in 0..m {
                for j in 0..=i {
                    a[(i, j)] += self.f * self.basis.energy[i * m + j];
                }
            }
        }
        let sh = RowShape {
            m,
            p,
            cen: asm.cen,
            radius: asm.radius,
            tw: self.params.fit.tangential_weight.sqrt(),
        };
        let Ok(llt) = a.llt(Side::Lower) else {
            return Ok(None);
        };
        let mut x = asm.b.clone();
        llt.solve_in_place(x.as_mut());
        let x: Vec<f64> = (0..p).map(|i| x[(i, 0)]).collect();
        Ok(x.iter().all(|v| v.is_finite()).then_some((sh, x)))
    }

    /// The capped squared error under the solution `x` at each picked measured point's match.
    fn predict(&self, sh: &RowShape, x: &[f64], out: &mut [f64], pick: &dyn Fn(&Match) -> bool) {
        let mut scratch = vec![0.0; 3 * sh.p];
        for mt in self
            .matches
            .iter()
            .filter(|m| m.point < self.measured && pick(m))
        {
            let rows = unscaled_rows(self.basis, mt, self.targets[mt.point], sh, &mut scratch);
            out[mt.point] = predicted(&rows, x).min(self.cap2);
        }
    }
}

/// The squared error of a point's rows under the solution `x`: `Σ (r − j·x)²`.
fn predicted(rows: &[(Vec<f64>, f64)], x: &[f64]) -> f64 {
    rows.iter()
        .map(|(j, r)| {
            let e = r - j.iter().zip(x).map(|(a, b)| a * b).sum::<f64>();
            e * e
        })
        .sum()
}

/// The means of per-point held-out and fitted errors, overall and per fold.
fn summarise(err: &[f64], fitted: &[f64], folds: &Folds) -> HeldOut {
    let w = |i: usize| folds.weight_of(i);
    let n = if err.is_empty() {
        1.0
    } else {
        (0..err.len()).map(w).sum::<f64>()
    };
    let mut sum = vec![0.0; folds.count];
    let mut count = vec![0.0f64; folds.count];
    for (i, &e) in err.iter().enumerate() {
        let k = folds.of_point[i] as usize;
        sum[k] += w(i) * e;
        count[k] += w(i);
    }
    let mean = |v: &[f64]| v.iter().enumerate().map(|(i, &e)| w(i) * e).sum::<f64>() / n;
    HeldOut {
        mean_mm2: mean(err),
        folds_mm2: sum
            .iter()
            .zip(&count)
            .map(|(s, &c)| if c > 0.0 { s / c } else { 0.0 })
            .collect(),
        in_sample_mm2: mean(fitted),
    }
}
