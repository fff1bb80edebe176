//! A dense surface cloud reduced to what the model can use: the anterior-surface points binned
//! in cubic cells, each cell's points replaced by their centroid standing for all of them
//! (its weight, [`Checked::weight`], is their number), the cells as small as a point budget
//! allows ([`reduce_to_budget`]).
//!
//! A stereo laparoscope sends tens of thousands of points where the model's boundary has a
//! triangle every few millimetres: the points beyond one or two per triangle add nothing the
//! piecewise-linear model can follow, yet every iteration of every stage matches each of them.
//! Replacing a cell's `k` points by their centroid `p̄` with weight `k` keeps each stage's
//! least squares: for points matched to one model point `q`, `Σ |p_i − q|² = k |p̄ − q|² +
//! Σ |p_i − p̄|²`, the same objective up to a constant (to a plane, the same holds of the normal
//! component), and the centroid's noise is the points' over `√k`, which its weight `k` already
//! counts. So the answer of a reduced cloud is nearly that of the whole one, at a cost that
//! stops growing with the cloud's density once cells hold several points.
//!
//! Only surface points are binned: ultrasound contours and vessel points come a few per plane.
//! A cell's points are grouped by their feature code too, so a traced ligament stays a
//! ligament. The cells come out in the order of their first point, so the reduction is
//! deterministic and a cloud with one point per cell is returned as it was.

use super::{Checked, MeasuredKind, Measurements, RegisterError};
use std::collections::HashMap;

/// What a reduction did.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Reduction {
    /// Points received.
    pub received: usize,
    /// Points the registration used (after merging).
    pub used: usize,
    /// The cells' edge (mm).
    pub cell_mm: f64,
}

/// `meas` reduced to at most about `budget` surface points ([`reduce_surface`] with the
/// smallest cell, from `start_mm()` up, whose count of occupied cells is within the budget);
/// None when the surface points are within it already (`start_mm` is then not called). Fails
/// on a start that is not finite and positive.
pub fn reduce_to_budget(
    meas: &Checked,
    budget: usize,
    start_mm: impl FnOnce() -> f64,
) -> Result<Option<(Checked, Reduction)>, RegisterError> {
    let surface = meas
        .kind
        .iter()
        .filter(|k| **k == MeasuredKind::Surface)
        .count();
    if surface <= budget.max(1) {
        return Ok(None);
    }
    let budget = budget.max(1);
    let mut cell = start_mm();
    // Occupied cells fall about as 1 / cell² on a surface: a few steps reach the budget.
    for _ in 0..32 {
        let count = occupied(meas, cell)?;
        if count <= budget {
            break;
        }
        cell *= (count as f64 / budget as f64).sqrt().clamp(1.02, 4.0);
    }
    reduce_surface(meas, cell)
}

/// How many cells of edge `cell_mm` the surface points occupy (by feature code, as
/// [`reduce_surface`] bins them).
fn occupied(meas: &Checked, cell_mm: f64) -> Result<usize, RegisterError> {
    if !(cell_mm.is_finite() && cell_mm > 0.0) {
        return Err(RegisterError::Parameter(format!(
            "the point reduction's cell_mm must be finite and > 0, got {cell_mm}"
        )));
    }
    let mut cells = std::collections::HashSet::new();
    for (i, p) in meas.points.iter().enumerate() {
        if meas.kind[i] == MeasuredKind::Surface {
            let f = meas.feature.get(i).copied().unwrap_or(0);
            cells.insert((p.map(|c| (c / cell_mm).floor() as i64), f));
        }
    }
    Ok(cells.len())
}

/// `meas`'s surface points merged per cell of edge `cell_mm` (see the module doc); the other
/// points as they are, after them. None when no cell holds two points (nothing to merge).
/// Fails when `cell_mm` is not finite and positive.
pub fn reduce_surface(
    meas: &Checked,
    cell_mm: f64,
) -> Result<Option<(Checked, Reduction)>, RegisterError> {
    if !(cell_mm.is_finite() && cell_mm > 0.0) {
        return Err(RegisterError::Parameter(format!(
            "the point reduction's cell_mm must be finite and > 0, got {cell_mm}"
        )));
    }
    let n = meas.points.len();
    let feature = |i: usize| meas.feature.get(i).copied().unwrap_or(0);
    // Cell of each surface point, in the order first seen.
    let mut cell_of: HashMap<([i64; 3], u8), usize> = HashMap::new();
    let mut groups: Vec<Vec<usize>> = Vec::new();
    let mut others = Vec::new();
    for i in 0..n {
        if meas.kind[i] != MeasuredKind::Surface {
            others.push(i);
            continue;
        }
        let key = (
            meas.points[i].map(|c| (c / cell_mm).floor() as i64),
            feature(i),
        );
        let g = *cell_of.entry(key).or_insert_with(|| {
            groups.push(Vec::new());
            groups.len() - 1
        });
        groups[g].push(i);
    }
    if groups.iter().all(|g| g.len() == 1) {
        return Ok(None);
    }
    let mut out = Measurements {
        initial_alignment: meas.initial_alignment,
        ..Default::default()
    };
    let keep_features = !meas.feature.is_empty();
    let mut weight = Vec::with_capacity(groups.len() + others.len());
    for g in &groups {
        let w: f64 = g.iter().map(|&i| meas.weight(i)).sum();
        let mut c = [0.0; 3];
        for &i in g {
            let wi = meas.weight(i) / w;
            for a in 0..3 {
                c[a] += wi * meas.points[i][a];
            }
        }
        out.points.push(c);
        out.kind.push(MeasuredKind::Surface);
        if keep_features {
            out.feature.push(feature(g[0]));
        }
        weight.push(w);
    }
    for &i in &others {
        out.points.push(meas.points[i]);
        out.kind.push(meas.kind[i]);
        if keep_features {
            out.feature.push(feature(i));
        }
        weight.push(meas.weight(i));
    }
    let used = out.points.len();
    let reduced = Checked::weighted(out, weight)?;
    Ok(Some((
        reduced,
        Reduction {
            received: n,
            used,
            cell_mm,
        },
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(points: Vec<[f64; 3]>, kind: Vec<MeasuredKind>) -> Checked {
        Checked::new(Measurements {
            points,
            kind,
            feature: Vec::new(),
            initial_alignment: None,
        })
        .unwrap()
    }

    #[test]
    fn merged_points_are_their_centroid_and_weigh_their_count() {
        use MeasuredKind::*;
        let c = cloud(
            vec![
                [0.1, 0.1, 0.0],
                [0.9, 0.3, 0.0],
                [5.2, 0.0, 0.0],
                [0.5, 0.8, 0.0],
                [0.2, 0.2, 0.2],
            ],
            vec![Surface, Surface, Surface, Surface, PosteriorContour],
        );
        let (r, info) = reduce_surface(&c, 1.0)
            .unwrap()
            .expect("a cell holds three points");
        assert_eq!((info.received, info.used), (5, 3));
        // The first cell: the mean of points 0, 1 and 3, weight 3; then the lone surface point;
        // the contour point last, untouched.
        let m = r.points[0];
        for (a, want) in [(0.5, 0), (0.4, 1), (0.0, 2)] {
            assert!((m[want] - a).abs() < 1e-12, "{m:?}");
        }
        assert_eq!((r.weight(0), r.weight(1), r.weight(2)), (3.0, 1.0, 1.0));
        assert_eq!(r.points[2], [0.2, 0.2, 0.2]);
        assert_eq!(r.kind[2], PosteriorContour);
        assert_eq!(r.represented(), 5.0);
    }

    #[test]
    fn a_cloud_with_one_point_per_cell_is_left_as_it_is() {
        let c = cloud(
            vec![[0.0; 3], [3.0, 0.0, 0.0], [0.0, 3.0, 0.0]],
            vec![MeasuredKind::Surface; 3],
        );
        assert!(reduce_surface(&c, 2.0).unwrap().is_none());
        assert!(reduce_surface(&c, 0.0).is_err());
        assert!(reduce_surface(&c, f64::NAN).is_err());
    }

    #[test]
    fn a_cloud_over_its_budget_is_reduced_to_within_it() {
        // A 1 mm grid over a 60 × 60 mm patch: 3,721 points.
        let points: Vec<[f64; 3]> = (0..61)
            .flat_map(|i| (0..61).map(move |j| [i as f64, j as f64, 0.3]))
            .collect();
        let n = points.len();
        let c = cloud(points, vec![MeasuredKind::Surface; n]);
        assert!(
            reduce_to_budget(&c, n, || unreachable!())
                .unwrap()
                .is_none()
        );
        let (r, info) = reduce_to_budget(&c, 400, || 0.5).unwrap().unwrap();
        assert!(info.used <= 400 && info.used > 150, "{info:?}");
        assert_eq!(r.represented(), n as f64);
        // The centroid of the whole patch is kept: the weighted mean of the centroids.
        let mean = |k: usize| {
            (0..r.points.len())
                .map(|i| r.weight(i) * r.points[i][k])
                .sum::<f64>()
                / n as f64
        };
        assert!((mean(0) - 30.0).abs() < 1e-9 && (mean(1) - 30.0).abs() < 1e-9);
    }

    #[test]
    fn designated_features_stay_apart_and_a_second_reduction_keeps_the_total_weight() {
        let mut m = Measurements {
            points: vec![
                [0.1, 0.0, 0.0],
                [0.2, 0.0, 0.0],
                [0.3, 0.0, 0.0],
                [0.4, 0.0, 0.0],
            ],
            kind: vec![MeasuredKind::Surface; 4],
            feature: vec![0, 1, 0, 1],
            initial_alignment: None,
        };
        let (r, _) = reduce_surface(&Checked::new(m.clone()).unwrap(), 1.0)
            .unwrap()
            .unwrap();
        assert_eq!(r.feature, vec![0, 1]);
        assert_eq!((r.weight(0), r.weight(1)), (2.0, 2.0));
        // Coarser cells merge the merged points again, weighted by what they stand for.
        m.feature = Vec::new();
        m.points.push([0.35, 0.0, 0.0]);
        m.kind.push(MeasuredKind::Surface);
        let (fine, _) = reduce_surface(&Checked::new(m).unwrap(), 0.25)
            .unwrap()
            .unwrap();
        let (coarse, _) = reduce_surface(&fine, 10.0).unwrap().unwrap();
        assert_eq!(coarse.points.len(), 1);
        assert_eq!(coarse.represented(), 5.0);
        let mean = (0.1 + 0.2 + 0.3 + 0.4 + 0.35) / 5.0;
        assert!((coarse.points[0][0] - mean).abs() < 1e-12);
    }
}
