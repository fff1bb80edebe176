//! The held-out check of a fit (`librplus::register::libr::held_out`), against facts computed
//! here independently: a field in the basis's span is predicted exactly where the fit did not
//! see it (and the rigid model cannot predict it); every fold's prediction equals a separate fit
//! on the rest made with `fit_step` and the exact rigid correction; doing nothing's score is its
//! residual; the spatial folds are patches; and an overfitted fit scores worse held out than a
//! regularised one although it fits its own points better.

use librplus::mesh::TetMesh;
use librplus::mesh::procedural::box_mesh;
use librplus::register::Match;
use librplus::register::libr::{
    FitModel, Folds, LibrBasis, LibrParams, LoadWidth, fit_step, held_out,
};
use librplus::util::SplitMix64;
use std::sync::OnceLock;

fn boxed() -> &'static (TetMesh, LibrBasis) {
    static B: OnceLock<(TetMesh, LibrBasis)> = OnceLock::new();
    B.get_or_init(|| {
        let mesh = box_mesh([60.0, 40.0, 30.0], [12, 8, 6], 0.3);
        let params = LibrParams {
            basis: librplus::register::libr::BasisParams {
                control_points: 24,
                load_width: LoadWidth::Spacing(1.25),
                ..LibrParams::default().basis
            },
            fit: LibrParams::default().fit,
        };
        let basis = LibrBasis::build(&mesh, &params).unwrap();
        (mesh, basis)
    })
}

/// `per` matches on each boundary triangle, point-to-point, at random barycentric points.
fn triangle_matches(mesh: &TetMesh, per: f64, rng: &mut SplitMix64) -> Vec<Match> {
    let bd = mesh.boundary().unwrap();
    let mut out = Vec::new();
    for t in &bd.triangles {
        if rng.next_f64() >= per {
            continue;
        }
        let (mut r1, mut r2) = (rng.next_f64(), rng.next_f64());
        if r1 + r2 > 1.0 {
            r1 = 1.0 - r1;
            r2 = 1.0 - r2;
        }
        let bary = [1.0 - r1 - r2, r1, r2, 0.0];
        let p = t.map(|v| mesh.nodes()[v as usize]);
        let anchor = [0, 1, 2].map(|a| bary[0] * p[0][a] + bary[1] * p[1][a] + bary[2] * p[2][a]);
        out.push(Match {
            point: out.len(),
            anchor,
            nodes: [t[0], t[1], t[2], t[0]],
            bary,
            weight: 1.0,
            normal: [0.0; 3],
        });
    }
    out
}

/// Targets: the matched points under `u`, plus Gaussian noise of `noise` mm per axis.
fn targets(matches: &[Match], u: &[f64], noise: f64, rng: &mut SplitMix64) -> Vec<[f64; 3]> {
    matches
        .iter()
        .map(|m| m.model_point(u).map(|x| x + noise * rng.normal()))
        .collect()
}

fn field(basis: &LibrBasis, amp: f64, rng: &mut SplitMix64) -> Vec<f64> {
    let alpha: Vec<f64> = (0..basis.columns()).map(|_| amp * rng.normal()).collect();
    basis.displacement(&alpha)
}

fn params(lambda: f64) -> LibrParams {
    let mut p = LibrParams::default();
    p.fit.regularization = lambda;
    p
}

fn anchors(matches: &[Match]) -> Vec<[f64; 3]> {
    matches.iter().map(|m| m.anchor).collect()
}

fn dist2(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum()
}

#[test]
fn a_field_in_the_span_is_predicted_where_it_was_not_seen() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(3);
    let matches = triangle_matches(mesh, 1.0, &mut rng);
    let u = field(basis, 1.5, &mut rng);
    let y = targets(&matches, &u, 0.0, &mut rng);
    let folds = Folds::spatial(&anchors(&matches), 5, 10.0);
    let p = params(1e-9);
    let model = FitModel::Basis {
        basis,
        lambda: 1e-9,
        escale: basis.energy_scale(),
    };
    let libr = held_out(model, &matches, &y, &p, None, &folds).unwrap();
    let rigid = held_out(FitModel::Rigid, &matches, &y, &p, None, &folds).unwrap();
    let fixed = held_out(FitModel::Fixed, &matches, &y, &p, None, &folds).unwrap();
    // Doing nothing: the held-out error is the residual, computed here directly.
    let direct: f64 = matches
        .iter()
        .map(|m| dist2(m.anchor, y[m.point]).min(100.0))
        .sum::<f64>()
        / matches.len() as f64;
    println!(
        "{} points: held out LIBR {:.2e}, rigid {:.3}, nothing {:.3} (direct {:.3}) mm²",
        matches.len(),
        libr.mean_mm2,
        rigid.mean_mm2,
        fixed.mean_mm2,
        direct
    );
    assert!((fixed.mean_mm2 - direct).abs() < 1e-12 * direct.max(1.0));
    assert_eq!(fixed.mean_mm2, fixed.in_sample_mm2);
    assert!(libr.mean_mm2 < 1e-4, "{libr:?}");
    assert!(libr.in_sample_mm2 < 1e-6, "{libr:?}");
    assert!(
        rigid.mean_mm2 > 100.0 * libr.mean_mm2 && rigid.mean_mm2 > 0.05,
        "the rigid model cannot predict a deformation: {rigid:?}"
    );
    // A least-squares fit never leaves its own points worse than doing nothing (held out it can:
    // a rigid motion fitted to a deformation elsewhere can move a patch the wrong way).
    assert!(rigid.in_sample_mm2 <= fixed.in_sample_mm2 + 1e-9);
}

#[test]
fn every_fold_is_predicted_as_a_separate_fit_on_the_rest_predicts_it() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(5);
    let matches = triangle_matches(mesh, 1.0, &mut rng);
    let u = field(basis, 1.0, &mut rng);
    let y = targets(&matches, &u, 0.4, &mut rng);
    let folds = Folds::spatial(&anchors(&matches), 4, 3.0);
    let lambda = 1e-3;
    let p = params(lambda);
    let model = FitModel::Basis {
        basis,
        lambda,
        escale: basis.energy_scale(),
    };
    let h = held_out(model, &matches, &y, &p, None, &folds).unwrap();
    for k in 0..folds.count {
        let rest: Vec<Match> = matches
            .iter()
            .filter(|m| folds.of_point[m.point] as usize != k)
            .cloned()
            .collect();
        let step = fit_step(basis, &rest, &y, &p).unwrap();
        let uk = basis.displacement(&step.alpha);
        let (mut sum, mut n) = (0.0, 0usize);
        for m in matches
            .iter()
            .filter(|m| folds.of_point[m.point] as usize == k)
        {
            let q = step.rigid_correction.apply(m.model_point(&uk));
            sum += dist2(q, y[m.point]).min(9.0);
            n += 1;
        }
        let want = sum / n as f64;
        let got = h.folds_mm2[k];
        println!("fold {k}: {n} points, held out {got:.5} mm², separate fit {want:.5} mm²");
        assert!(
            (got - want).abs() <= 0.01 * want + 1e-6,
            "fold {k}: {got} vs {want}"
        );
    }
}

#[test]
fn spatial_folds_are_patches_and_deterministic() {
    let (mesh, _) = boxed();
    let mut rng = SplitMix64::new(7);
    let pts = anchors(&triangle_matches(mesh, 1.0, &mut rng));
    let f = Folds::spatial(&pts, 5, 10.0);
    assert_eq!(f, Folds::spatial(&pts, 5, 10.0));
    assert_eq!(f.of_point.len(), pts.len());
    let mean_pair = |sel: &dyn Fn(usize, usize) -> bool| {
        let (mut s, mut n) = (0.0, 0usize);
        for i in (0..pts.len()).step_by(3) {
            for j in (0..pts.len()).step_by(5) {
                if i != j && sel(i, j) {
                    s += dist2(pts[i], pts[j]).sqrt();
                    n += 1;
                }
            }
        }
        s / n as f64
    };
    for k in 0..5u8 {
        assert!(f.of_point.contains(&k), "fold {k} is empty");
    }
    let within = mean_pair(&|i, j| f.of_point[i] == f.of_point[j]);
    let across = mean_pair(&|i, j| f.of_point[i] != f.of_point[j]);
    println!("mean distance within a fold {within:.1} mm, across folds {across:.1} mm");
    assert!(within < 0.7 * across, "{within} vs {across}");
    // Fewer points than folds: one fold each.
    let few = Folds::spatial(&pts[..3], 5, 10.0);
    assert_eq!(few.count, 3);
    let mut seen = few.of_point.clone();
    seen.sort();
    assert_eq!(seen, vec![0, 1, 2]);
}

#[test]
fn an_overfitted_fit_scores_worse_held_out_though_it_fits_its_points_better() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(9);
    // Sparse noisy points: a quarter of the triangles, 1.5 mm of noise, a smooth field.
    let matches = triangle_matches(mesh, 0.25, &mut rng);
    let u = field(basis, 1.0, &mut rng);
    let y = targets(&matches, &u, 1.5, &mut rng);
    let folds = Folds::spatial(&anchors(&matches), 5, 10.0);
    let score = |lambda: f64| {
        let model = FitModel::Basis {
            basis,
            lambda,
            escale: basis.energy_scale(),
        };
        held_out(model, &matches, &y, &params(lambda), None, &folds).unwrap()
    };
    let (loose, firm) = (score(1e-9), score(1e-2));
    println!(
        "{} points: λ 1e-9 in sample {:.3}, held out {:.3}; λ 1e-2 in sample {:.3}, held out {:.3} mm²",
        matches.len(),
        loose.in_sample_mm2,
        loose.mean_mm2,
        firm.in_sample_mm2,
        firm.mean_mm2
    );
    assert!(loose.in_sample_mm2 < firm.in_sample_mm2);
    assert!(loose.mean_mm2 > firm.mean_mm2);
    // Held out is never better than in sample for the fit's own points, on average.
    assert!(loose.mean_mm2 > loose.in_sample_mm2 && firm.mean_mm2 > firm.in_sample_mm2);
}
