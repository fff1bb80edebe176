//! Correspondence (`librplus::register::correspondence`) and salient-feature weighted rigid ICP
//! (`librplus::register::wicp`), checked against facts that do not come from the code under test:
//! the known misalignment of simulated scenarios (exact recovery without noise, target registration
//! error with noise), points placed exactly on triangles and on affinely deformed vessel
//! centerlines, injected outliers, garbage inputs and determinism.
//!
//! Data: `assets/livers/sofa_liver.vtk` meshed with 10 mm tets, labelled and given a vessel tree
//! by the phantom module; scenarios from `phantom::measure::simulate` on the undeformed liver.

mod common;

use librplus::mesh::TetMesh;
use librplus::mesh::io::{DataArray, MeshFile};
use librplus::mesh::rigid::Rigid;
use librplus::mesh::spatial::{Certificate, TriangleBvh};
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::phantom::measure::{Category, MeasureParams, Scenario, simulate};
use librplus::phantom::vessels::{VesselParams, VesselTree};
use librplus::register::anatomy::{AnatomyLabels, LabelParams, Region, label};
use librplus::register::correspondence::{
    Correspondence, CorrespondenceParams, preop_model_from_file,
};
use librplus::register::wicp::{WicpParams, WicpResult};
use librplus::register::{Checked, MeasuredKind, Measurements, PreopModel, RegisterError};

/// wICP of measurements checked first, as every edge checks them (the error of whichever
/// refused them).
fn wicp(
    model: &PreopModel,
    corr: &Correspondence,
    meas: &Measurements,
    params: &WicpParams,
) -> Result<WicpResult, RegisterError> {
    librplus::register::wicp::wicp(model, corr, &Checked::new(meas.clone())?, params)
}
use librplus::util::SplitMix64;
use std::sync::OnceLock;

struct Liver {
    mesh: TetMesh,
    labels: AnatomyLabels,
    vessels: VesselTree,
    model: PreopModel,
    corr: Correspondence,
    centroid: [f64; 3],
}

fn liver() -> &'static Liver {
    static LIVER: OnceLock<Liver> = OnceLock::new();
    LIVER.get_or_init(|| {
        let surface = common::sofa_liver_surface();
        let mesh = tetrahedralize(&surface, &TetraParams::with_edge(10.0)).unwrap();
        let labels = label(&mesh, &LabelParams::default()).unwrap();
        let vessels = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
        let model = PreopModel {
            mesh: mesh.clone(),
            anterior: labels
                .region
                .iter()
                .map(|&r| r == Region::Anterior)
                .collect(),
            posterior: labels
                .region
                .iter()
                .map(|&r| r == Region::Posterior)
                .collect(),
            falciform: labels.falciform.clone(),
            inferior_ridge: labels.inferior_ridge.clone(),
            vessel_points: vessels.points.clone(),
            vessel_segments: vessels.segments.clone(),
        };
        let corr = Correspondence::new(&model).unwrap();
        let centroid = centroid(mesh.nodes());
        Liver {
            mesh,
            labels,
            vessels,
            model,
            corr,
            centroid,
        }
    })
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn norm(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}
fn lerp(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    [0, 1, 2].map(|k| a[k] + t * (b[k] - a[k]))
}
fn centroid(p: &[[f64; 3]]) -> [f64; 3] {
    let s = p.iter().fold([0.0; 3], |a, &q| add(a, q));
    s.map(|c| c / p.len() as f64)
}

fn scenario(category: Category, params: &MeasureParams, seed: u64) -> Scenario {
    let l = liver();
    let u = vec![0.0; 3 * l.mesh.num_nodes()];
    simulate(&l.mesh, &l.labels, &l.vessels, &u, category, params, seed).unwrap()
}

fn measurements(s: &Scenario) -> Measurements {
    common::raw_measurements(s)
}

/// Mean and largest distance over the mesh nodes between the two transforms' images.
fn tre(a: &Rigid, b: &Rigid) -> (f64, f64) {
    let nodes = liver().mesh.nodes();
    let d: Vec<f64> = nodes
        .iter()
        .map(|&x| norm(sub(a.apply(x), b.apply(x))))
        .collect();
    (
        d.iter().sum::<f64>() / d.len() as f64,
        d.iter().copied().fold(0.0, f64::max),
    )
}

/// Rotation angle (degrees) of `a` relative to `b`.
fn angle_between(a: &Rigid, b: &Rigid) -> f64 {
    a.then(&b.inverse()).rotation_angle_deg()
}

fn run(meas: &Measurements, params: &WicpParams) -> WicpResult {
    let l = liver();
    wicp(&l.model, &l.corr, meas, params).unwrap()
}

/// Measurement simulation without tracking or ultrasound noise.
fn noise_free() -> MeasureParams {
    MeasureParams {
        surface_noise_mm: 0.0,
        us_noise_mm: 0.0,
        ..MeasureParams::default()
    }
}

fn tight() -> WicpParams {
    WicpParams {
        max_iterations: 1000,
        tolerance_mm: 1e-9,
        ..WicpParams::default()
    }
}

fn assert_finite(r: &WicpResult) {
    let t = &r.image_to_physical;
    assert!(
        t.rotation
            .iter()
            .flatten()
            .chain(&t.translation)
            .chain([&r.rms_mm, &r.initial_rms_mm])
            .all(|c| c.is_finite()),
        "non-finite result {r:?}"
    );
}

#[test]
fn noise_free_scenarios_recover_the_true_transform() {
    let params = noise_free();
    for (category, seed) in [
        (Category::Planes3, 1),
        (Category::Planes16, 2),
        (Category::Planes1, 3),
        (Category::Surface, 4),
    ] {
        let s = scenario(category, &params, seed);
        let r = run(&measurements(&s), &tight());
        let angle = angle_between(&r.image_to_physical, &s.image_to_physical);
        let (mean, max) = tre(&r.image_to_physical, &s.image_to_physical);
        let (mean0, _) = tre(&s.initial_alignment, &s.image_to_physical);
        eprintln!(
            "noise-free {} seed {seed}: {} points, angle error {angle:.2e}°, node error mean \
             {mean:.2e} max {max:.2e} mm (start {mean0:.2} mm), rms {:.2e} mm, {} iterations, \
             {} trimmed, {:.2} s",
            category.name(),
            s.points.len(),
            r.rms_mm,
            r.iterations,
            r.trimmed,
            r.seconds
        );
        assert!(r.degenerate.is_none(), "{:?}", r.degenerate);
        // Point-to-point ICP slides slowly along a surface patch alone (linear convergence in its
        // weakly constrained directions): surface-only data need not reach 1e-9 mm within 1000
        // iterations, but must be accurate.
        if category != Category::Surface {
            assert!(r.converged);
        }
        assert!(angle < 0.1, "angle error {angle}°");
        assert!(max < 0.2, "largest node error {max} mm");
        assert!(r.rms_mm < 0.05, "rms {}", r.rms_mm);
    }
}

#[test]
fn noisy_scenarios_have_small_target_registration_error() {
    let mut worst: f64 = 0.0;
    for (category, seed) in [
        (Category::Surface, 11),
        (Category::Planes1, 12),
        (Category::Planes3, 13),
        (Category::Planes16, 14),
        (Category::Planes3, 15),
        (Category::Surface, 16),
    ] {
        let s = scenario(category, &MeasureParams::default(), seed);
        let r = run(&measurements(&s), &WicpParams::default());
        assert_finite(&r);
        let (mean, max) = tre(&r.image_to_physical, &s.image_to_physical);
        let (mean0, _) = tre(&s.initial_alignment, &s.image_to_physical);
        eprintln!(
            "noisy {} seed {seed} (coverage {:.2}, {} points): TRE mean {mean:.2} max {max:.2} mm, \
             start {mean0:.2} mm; rms {:.2} (start {:.2}) mm, {} iterations, converged {}, {} kept, \
             {} trimmed, {:.2} s",
            category.name(),
            s.coverage,
            s.points.len(),
            r.rms_mm,
            r.initial_rms_mm,
            r.iterations,
            r.converged,
            r.matched,
            r.trimmed,
            r.seconds
        );
        assert!(r.degenerate.is_none(), "{:?}", r.degenerate);
        assert!(mean < 2.0, "TRE {mean} mm");
        assert!(mean < 0.5 * mean0, "TRE {mean} mm vs start {mean0} mm");
        // Noise of 1 mm (surface) and 0.5 mm in-plane (ultrasound): the residual is noise-sized.
        assert!(r.rms_mm < 1.5, "rms {}", r.rms_mm);
        // The reported rms and counts belong to the returned transform.
        let image: Vec<[f64; 3]> = s
            .points
            .iter()
            .map(|&p| r.image_to_physical.inverse().apply(p))
            .collect();
        let (_, again) = liver()
            .corr
            .match_points(
                &image,
                &common::checked(measurements(&s)),
                None,
                &CorrespondenceParams::default(),
            )
            .unwrap();
        assert!((again.rms_mm - r.rms_mm).abs() < 1e-9);
        assert_eq!((again.kept, again.trimmed), (r.matched, r.trimmed));
        worst = worst.max(mean);
    }
    eprintln!("worst TRE {worst:.2} mm");
}

#[test]
fn a_point_on_a_triangle_matches_itself_under_deformation() {
    let l = liver();
    let n = l.mesh.num_nodes();
    // A smooth non-affine displacement of a few mm.
    let (lo, hi) = l.mesh.bounding_box();
    let mut u = Vec::with_capacity(3 * n);
    for &p in l.mesh.nodes() {
        let s = (p[0] - lo[0]) / (hi[0] - lo[0]);
        let t = (p[2] - lo[2]) / (hi[2] - lo[2]);
        u.extend([2.0 * s * t, 5.0 * s * s, -3.0 * t * s]);
    }
    let def = |v: u32| {
        add(
            l.mesh.nodes()[v as usize],
            [0, 1, 2].map(|k| u[3 * v as usize + k]),
        )
    };
    let tris = l.mesh.boundary().unwrap().triangles;
    let mut rng = SplitMix64::new(5);
    let mut points = Vec::new();
    let mut kind = Vec::new();
    for (region, k) in [
        (Region::Anterior, MeasuredKind::Surface),
        (Region::Posterior, MeasuredKind::PosteriorContour),
    ] {
        let set: Vec<&[u32; 3]> = tris
            .iter()
            .filter(|t| t.iter().all(|&v| l.labels.region[v as usize] == region))
            .collect();
        for _ in 0..40 {
            let t = set[(rng.next_f64() * set.len() as f64) as usize];
            let (mut a, mut b) = (rng.next_f64(), rng.next_f64());
            if a + b > 1.0 {
                (a, b) = (1.0 - a, 1.0 - b);
            }
            let p = [0, 1, 2]
                .map(|c| (1.0 - a - b) * def(t[0])[c] + a * def(t[1])[c] + b * def(t[2])[c]);
            points.push(p);
            kind.push(k);
        }
    }
    let meas = Measurements {
        points: points.clone(),
        kind,
        ..Default::default()
    };
    let params = CorrespondenceParams::default();
    let (m, stats) = l
        .corr
        .match_points(&points, &common::checked(meas.clone()), Some(&u), &params)
        .unwrap();
    assert_eq!(m.len(), points.len());
    assert_eq!(stats.trimmed, 0);
    assert!(stats.max_mm < 1e-9, "largest distance {}", stats.max_mm);
    for mm in &m {
        let q = mm.model_point(&u);
        assert!(norm(sub(q, points[mm.point])) < 1e-9);
        assert!((mm.bary.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert_eq!(mm.bary[3], 0.0);
        assert!(mm.bary.iter().all(|&b| b >= 0.0));
        // The anchor is the same combination on the undeformed triangle.
        let zero = vec![0.0; 3 * n];
        assert!(norm(sub(mm.model_point(&zero), mm.anchor)) < 1e-12);
    }
    // Undeformed matching of the deformed points: distances are the gap, not zero.
    let (_, s0) = l
        .corr
        .match_points(&points, &common::checked(meas.clone()), None, &params)
        .unwrap();
    assert!(s0.rms_mm > 0.1, "rms {}", s0.rms_mm);
}

#[test]
fn vessel_matches_lie_on_the_deformed_centerline() {
    let l = liver();
    let n = l.mesh.num_nodes();
    // An affine displacement: linear interpolation reproduces it exactly, so the deformed centerline
    // is the affine image of the undeformed one.
    let a = [
        [0.02, -0.01, 0.015],
        [0.01, 0.03, -0.02],
        [-0.015, 0.02, 0.01],
    ];
    let b = [1.5, -2.0, 3.0];
    let affine = |p: [f64; 3]| {
        let d = sub(p, l.centroid);
        [0, 1, 2].map(|i| a[i][0] * d[0] + a[i][1] * d[1] + a[i][2] * d[2] + b[i])
    };
    let u: Vec<f64> = l.mesh.nodes().iter().flat_map(|&p| affine(p)).collect();
    let mut rng = SplitMix64::new(9);
    let segs = &l.vessels.segments;
    let mut points = Vec::new();
    for _ in 0..60 {
        let s = segs[(rng.next_f64() * segs.len() as f64) as usize];
        let q = lerp(
            l.vessels.points[s[0] as usize],
            l.vessels.points[s[1] as usize],
            rng.next_f64(),
        );
        points.push(add(q, affine(q)));
    }
    let meas = Measurements {
        points: points.clone(),
        kind: vec![MeasuredKind::Vessel; points.len()],
        ..Default::default()
    };
    let (m, stats) = l
        .corr
        .match_points(
            &points,
            &common::checked(meas.clone()),
            Some(&u),
            &CorrespondenceParams::default(),
        )
        .unwrap();
    eprintln!(
        "vessel matches: {} of {} kept, largest distance {:.1e} mm ({} segments)",
        m.len(),
        points.len(),
        stats.max_mm,
        segs.len()
    );
    assert_eq!(m.len(), points.len());
    assert!(stats.max_mm < 1e-9, "largest distance {}", stats.max_mm);
    for mm in &m {
        assert!(norm(sub(mm.model_point(&u), points[mm.point])) < 1e-9);
        assert!((mm.bary.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        // The tet's nodes interpolate the anchor exactly.
        let x = l.mesh.nodes();
        let q = [0, 1, 2].map(|c| {
            (0..4)
                .map(|k| mm.bary[k] * x[mm.nodes[k] as usize][c])
                .sum()
        });
        assert!(norm(sub(q, mm.anchor)) < 1e-9);
    }
    // Points off the centerline: the match is on the undeformed centerline and no centerline point
    // sampled finely is nearer.
    let probes: Vec<[f64; 3]> = (0..20)
        .map(|i| {
            let p = l.vessels.points[(i * 37) % l.vessels.points.len()];
            add(p, [0; 3].map(|_| 6.0 * (rng.next_f64() - 0.5)))
        })
        .collect();
    let meas = Measurements {
        points: probes.clone(),
        kind: vec![MeasuredKind::Vessel; probes.len()],
        ..Default::default()
    };
    let params = CorrespondenceParams {
        trim_floor_mm: 100.0,
        ..Default::default()
    };
    let (m, _) = l
        .corr
        .match_points(&probes, &common::checked(meas.clone()), None, &params)
        .unwrap();
    assert_eq!(m.len(), probes.len());
    let zero = vec![0.0; 3 * n];
    for mm in &m {
        let p = probes[mm.point];
        let d = norm(sub(mm.model_point(&zero), p));
        let mut best = f64::INFINITY;
        let mut on_line = f64::INFINITY;
        for s in segs {
            let (a, b) = (
                l.vessels.points[s[0] as usize],
                l.vessels.points[s[1] as usize],
            );
            for k in 0..=50 {
                best = best.min(norm(sub(lerp(a, b, k as f64 / 50.0), p)));
            }
            // Distance of the anchor to this segment, by dense sampling.
            for k in 0..=200 {
                on_line = on_line.min(norm(sub(lerp(a, b, k as f64 / 200.0), mm.anchor)));
            }
        }
        assert!(d <= best + 1e-9, "match at {d} mm, a sample at {best} mm");
        assert!(on_line < 0.2, "anchor {on_line} mm off the centerline");
    }
}

#[test]
fn designated_feature_points_get_the_feature_weight_and_region() {
    let l = liver();
    let s = scenario(Category::Surface, &MeasureParams::default(), 21);
    let meas = measurements(&s);
    let designated = s.feature.iter().filter(|&&f| f > 0).count();
    assert!(designated > 0, "the scenario has no designated point");
    let image: Vec<[f64; 3]> = s
        .points
        .iter()
        .map(|&p| s.image_to_physical.inverse().apply(p))
        .collect();
    let feature_nodes = [&l.labels.falciform, &l.labels.inferior_ridge].map(|f| {
        (0..f.len())
            .filter(|&i| f[i])
            .map(|i| l.mesh.nodes()[i])
            .collect::<Vec<_>>()
    });
    let mut checked = 0;
    // The prebuilt neighbourhood (15 mm) and one rebuilt on demand (0: triangles touching the
    // feature itself).
    for radius in [15.0, 0.0] {
        let params = CorrespondenceParams {
            feature_neighbourhood_mm: radius,
            ..Default::default()
        };
        let (m, _) = l
            .corr
            .match_points(&image, &common::checked(meas.clone()), None, &params)
            .unwrap();
        for mm in &m {
            let f = s.feature[mm.point];
            if f == 0 {
                assert_eq!(mm.weight, params.surface_weight);
                continue;
            }
            assert_eq!(mm.weight, params.surface_weight * params.feature_weight);
            // The matched triangle has a node near the designated feature.
            let near = (0..3).any(|k| {
                let x = l.mesh.nodes()[mm.nodes[k] as usize];
                feature_nodes[f as usize - 1]
                    .iter()
                    .any(|&q| norm(sub(x, q)) <= params.feature_neighbourhood_mm + 1e-9)
            });
            assert!(near, "point {} matched away from feature {f}", mm.point);
            checked += 1;
        }
    }
    eprintln!("{designated} designated points, {checked} matched on their feature");
    assert!(checked > 0);
}

#[test]
fn trimming_removes_injected_outliers() {
    let l = liver();
    let s = scenario(Category::Planes3, &MeasureParams::default(), 31);
    let clean = run(&measurements(&s), &WicpParams::default());
    let mut meas = measurements(&s);
    // Move every 20th point 100 mm away from the liver (radially from the centroid, physical frame).
    let c = s.image_to_physical.apply(l.centroid);
    let mut outliers = Vec::new();
    for i in (0..meas.points.len()).step_by(20) {
        let p = meas.points[i];
        let d = sub(p, c);
        let k = 100.0 / norm(d);
        meas.points[i] = add(p, d.map(|x| x * k));
        outliers.push(i);
    }
    let r = run(&meas, &WicpParams::default());
    let (mean, _) = tre(&r.image_to_physical, &s.image_to_physical);
    let (mean_clean, _) = tre(&clean.image_to_physical, &s.image_to_physical);
    eprintln!(
        "{} outliers of {} points: TRE {mean:.2} mm (without outliers {mean_clean:.2} mm), \
         {} trimmed, rms {:.2} mm",
        outliers.len(),
        meas.points.len(),
        r.trimmed,
        r.rms_mm
    );
    assert!(r.trimmed >= outliers.len());
    assert!(mean < 2.0, "TRE {mean}");
    assert!((mean - mean_clean).abs() < 0.5);
    // None of the outliers is among the final matches.
    let image: Vec<[f64; 3]> = meas
        .points
        .iter()
        .map(|&p| r.image_to_physical.inverse().apply(p))
        .collect();
    let (m, _) = l
        .corr
        .match_points(
            &image,
            &common::checked(meas.clone()),
            None,
            &CorrespondenceParams::default(),
        )
        .unwrap();
    assert!(m.iter().all(|mm| !outliers.contains(&mm.point)));
    // Without trimming, the same outliers pull the registration off.
    let untrimmed = WicpParams {
        correspondence: CorrespondenceParams {
            trim_floor_mm: 1000.0,
            ..Default::default()
        },
        ..Default::default()
    };
    let bad = run(&meas, &untrimmed);
    let (mean_bad, _) = tre(&bad.image_to_physical, &s.image_to_physical);
    eprintln!("without trimming: TRE {mean_bad:.2} mm");
    assert!(mean_bad > mean + 1.0);
}

#[test]
fn garbage_inputs_give_errors_or_degenerate_flags() {
    let l = liver();
    let s = scenario(Category::Planes1, &MeasureParams::default(), 41);
    let good = measurements(&s);
    let p = WicpParams::default();
    let err = |m: &Measurements| wicp(&l.model, &l.corr, m, &p).unwrap_err().to_string();

    let e = err(&Measurements::default());
    assert!(e.contains("points") && e.contains("empty"), "{e}");

    let mut m = good.clone();
    m.points[3][1] = f64::NAN;
    let e = err(&m);
    assert!(e.contains("points[3]"), "{e}");

    let mut m = good.clone();
    m.kind.pop();
    let e = err(&m);
    assert!(e.contains("kind"), "{e}");

    let mut m = good.clone();
    m.feature = vec![0; 2];
    let e = err(&m);
    assert!(e.contains("feature"), "{e}");

    let mut m = good.clone();
    m.feature[5] = 7;
    let e = err(&m);
    assert!(e.contains("feature[5]"), "{e}");

    // Everything 1 m away (e.g. metres read as millimetres the other way round).
    let mut m = good.clone();
    for q in &mut m.points {
        q[0] += 1000.0;
    }
    let e = err(&m);
    assert!(e.contains("mm from the model"), "{e}");
    assert!(matches!(
        wicp(&l.model, &l.corr, &m, &p),
        Err(RegisterError::FarFromModel { .. })
    ));

    // A few points 1 m away: dropped, flagged, the rest registers.
    let mut m = good.clone();
    m.points[0][2] += 1000.0;
    m.points[7][0] -= 1000.0;
    let r = wicp(&l.model, &l.corr, &m, &p).unwrap();
    assert_eq!(r.far, 2);
    assert!(
        r.warnings.iter().any(|w| w.contains("points[0]")),
        "{:?}",
        r.warnings
    );
    assert!(r.degenerate.is_none());
    let (mean, _) = tre(&r.image_to_physical, &s.image_to_physical);
    let (mean0, _) = tre(&s.initial_alignment, &s.image_to_physical);
    // As the other noisy scenarios (1 mm surface noise, one ultrasound plane): well inside the
    // start's error.
    assert!(
        mean < 3.0 && mean < 0.5 * mean0,
        "TRE {mean} (start {mean0})"
    );

    // All points on one spot.
    let mut m = good.clone();
    let spot = m.points[0];
    m.points.iter_mut().for_each(|q| *q = spot);
    let r = wicp(&l.model, &l.corr, &m, &p).unwrap();
    assert_finite(&r);
    let why = r.degenerate.as_deref().unwrap();
    assert!(why.contains("one spot"), "{why}");
    assert_eq!(r.image_to_physical, s.initial_alignment);
    assert_eq!(r.iterations, 0);

    // Collinear points.
    let mut m = good.clone();
    let (a, b) = (m.points[0], m.points[1]);
    let k = m.points.len() as f64;
    m.points
        .iter_mut()
        .enumerate()
        .for_each(|(i, q)| *q = lerp(a, b, i as f64 / k));
    let r = wicp(&l.model, &l.corr, &m, &p).unwrap();
    assert_finite(&r);
    assert!(r.degenerate.as_deref().unwrap().contains("collinear"));
    assert_eq!(r.image_to_physical, s.initial_alignment);

    // Two points.
    let m = Measurements {
        points: good.points[..2].to_vec(),
        kind: good.kind[..2].to_vec(),
        feature: Vec::new(),
        initial_alignment: good.initial_alignment,
    };
    let r = wicp(&l.model, &l.corr, &m, &p).unwrap();
    assert!(r.degenerate.as_deref().unwrap().contains("at least 3"));

    // A non-rotation as initial alignment, non-finite parameters.
    let mut m = good.clone();
    m.initial_alignment = Some(Rigid {
        rotation: [[2.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [0.0; 3],
    });
    assert!(err(&m).contains("initial_alignment"));
    let bad = WicpParams {
        tolerance_mm: f64::NAN,
        ..WicpParams::default()
    };
    assert!(wicp(&l.model, &l.corr, &good, &bad).is_err());
    let bad = WicpParams {
        correspondence: CorrespondenceParams {
            trim_factor: -1.0,
            ..Default::default()
        },
        ..WicpParams::default()
    };
    let e = wicp(&l.model, &l.corr, &good, &bad)
        .unwrap_err()
        .to_string();
    assert!(e.contains("trim_factor"), "{e}");

    // Correspondence: wrong displacement length, wrong flag lengths.
    let e = l
        .corr
        .match_points(
            &good.points,
            &common::checked(good.clone()),
            Some(&[0.0; 5]),
            &CorrespondenceParams::default(),
        )
        .unwrap_err()
        .to_string();
    assert!(e.contains("displacement"), "{e}");
    let mut model = l.model.clone();
    model.posterior.pop();
    let e = Correspondence::new(&model).unwrap_err().to_string();
    assert!(e.contains("posterior"), "{e}");
    let mut model = l.model.clone();
    model.vessel_segments.push([0, 1_000_000]);
    assert!(
        Correspondence::new(&model)
            .unwrap_err()
            .to_string()
            .contains("vessel segment")
    );
}

#[test]
fn registration_is_deterministic() {
    let s = scenario(Category::Planes2, &MeasureParams::default(), 51);
    let meas = measurements(&s);
    let a = run(&meas, &WicpParams::default());
    let b = run(&meas, &WicpParams::default());
    assert_eq!(a.image_to_physical, b.image_to_physical);
    assert_eq!(a.rms_mm.to_bits(), b.rms_mm.to_bits());
    assert_eq!(
        (a.iterations, a.matched, a.trimmed),
        (b.iterations, b.matched, b.trimmed)
    );
    let l = liver();
    let c = Correspondence::new(&l.model).unwrap();
    let r = wicp(&l.model, &c, &meas, &WicpParams::default()).unwrap();
    assert_eq!(r.image_to_physical, a.image_to_physical);
}

#[test]
fn preop_model_reads_back_from_dataset_arrays() {
    let l = liver();
    let mut file = l.mesh.to_file();
    file.point_data = l.labels.to_point_data();
    let mut parent = vec![-1.0; l.vessels.points.len()];
    for s in &l.vessels.segments {
        parent[s[1] as usize] = s[0] as f64;
    }
    let vessels = MeshFile {
        nodes: l.vessels.points.clone(),
        point_data: vec![DataArray::new("parent", 1, parent.clone())],
        ..Default::default()
    };
    let m = preop_model_from_file(&file, &vessels).unwrap();
    assert_eq!(m.mesh, l.model.mesh);
    assert_eq!(m.anterior, l.model.anterior);
    assert_eq!(m.posterior, l.model.posterior);
    assert_eq!(m.falciform, l.model.falciform);
    assert_eq!(m.inferior_ridge, l.model.inferior_ridge);
    assert_eq!(m.vessel_points, l.model.vessel_points);
    let mut a = m.vessel_segments.clone();
    let mut b = l.model.vessel_segments.clone();
    a.sort_unstable();
    b.sort_unstable();
    assert_eq!(a, b);

    let mut f = file.clone();
    f.point_data.retain(|a| a.name != "region");
    assert!(
        preop_model_from_file(&f, &vessels)
            .unwrap_err()
            .to_string()
            .contains("region")
    );
    let mut f = file.clone();
    f.point_data[0].values[4] = 3.0;
    assert!(
        preop_model_from_file(&f, &vessels)
            .unwrap_err()
            .to_string()
            .contains("region[4]")
    );
    let mut v = vessels.clone();
    v.point_data[0].values[2] = 1e9;
    assert!(
        preop_model_from_file(&file, &v)
            .unwrap_err()
            .to_string()
            .contains("parent[2]")
    );
    let mut v = vessels.clone();
    v.point_data.clear();
    assert!(
        preop_model_from_file(&file, &v)
            .unwrap_err()
            .to_string()
            .contains("parent")
    );
    // No vessels at all is fine.
    let m = preop_model_from_file(&file, &MeshFile::default()).unwrap();
    assert!(m.vessel_segments.is_empty());
}

#[test]
fn surface_only_registration_ignores_the_ultrasound_points() {
    let params = noise_free();
    let s = scenario(Category::Planes3, &params, 61);
    let mut meas = measurements(&s);
    // The posterior moved 15 mm since imaging: the ultrasound points disagree with a rigid fit.
    let mut moved = 0;
    for (p, k) in meas.points.iter_mut().zip(&meas.kind) {
        if *k != MeasuredKind::Surface {
            p[1] -= 15.0;
            moved += 1;
        }
    }
    assert!(moved >= 10, "{moved} ultrasound points");
    let only = WicpParams {
        surface_only: true,
        ..tight()
    };
    let r = run(&meas, &only);
    assert!(r.degenerate.is_none() && r.warnings.is_empty(), "{r:?}");
    let (mean, max) = tre(&r.image_to_physical, &s.image_to_physical);
    assert!(max < 0.2, "surface only: largest node error {max} mm");
    // The same as registering the surface points given alone.
    let keep: Vec<usize> = (0..meas.points.len())
        .filter(|&i| meas.kind[i] == MeasuredKind::Surface)
        .collect();
    let alone = Measurements {
        points: keep.iter().map(|&i| meas.points[i]).collect(),
        kind: vec![MeasuredKind::Surface; keep.len()],
        feature: keep.iter().map(|&i| meas.feature[i]).collect(),
        initial_alignment: meas.initial_alignment,
    };
    assert_eq!(run(&alone, &tight()).image_to_physical, r.image_to_physical);
    // Every point: the moved ones pull the fit away.
    let all = run(&meas, &tight());
    let (mean_all, _) = tre(&all.image_to_physical, &s.image_to_physical);
    assert!(
        mean_all > 1.0 && mean_all > 10.0 * mean,
        "all points {mean_all} mm, surface only {mean} mm"
    );
    // Fewer than 3 surface points: every point, with a warning.
    let mut few = meas.clone();
    let mut seen = 0;
    for k in few.kind.iter_mut() {
        if *k == MeasuredKind::Surface {
            seen += 1;
            if seen > 2 {
                *k = MeasuredKind::PosteriorContour;
            }
        }
    }
    let r = run(&few, &only);
    assert!(
        r.warnings.iter().any(|w| w.contains("2 anterior-surface")),
        "{:?}",
        r.warnings
    );
}

/// A trusted start holds the organ: with exact data of a pose 3° and ~4 mm from the start, the
/// rigid stage moves the organ from the start the less the smaller the declared uncertainty —
/// all the way to the data's pose when it is large, and not at all when it is tiny.
#[test]
fn a_trusted_start_is_left_in_proportion_to_its_uncertainty() {
    let sc = scenario(Category::Planes3, &noise_free(), 11);
    let truth = sc.image_to_physical;
    let off = Rigid::from_axis_angle([0.2, 1.0, -0.3], 3f64.to_radians(), [3.0, -2.0, 2.0]);
    let meas = Measurements {
        initial_alignment: Some(off.then(&truth)),
        ..measurements(&sc)
    };
    let free = run(&meas, &tight());
    assert!(free.prior.is_none());
    let apart = free.moved_from_start_mm;
    assert!(apart > 3.0, "the start is {apart} mm from the data's pose");
    let mut last = 0.0;
    for sigma in [0.001, 0.3, 1.0, 3.0, 10.0, 1e4] {
        let r = run(
            &meas,
            &WicpParams {
                trusted_alignment_mm: Some(sigma),
                ..tight()
            },
        );
        assert_eq!(r.prior.map(|p| p.sigma_mm), Some(sigma));
        let moved = r.moved_from_start_mm;
        eprintln!("trusted to {sigma} mm: moved {moved:.3} mm of {apart:.3}");
        assert!(moved >= last - 1e-6, "σ {sigma}: moved {moved} < {last}");
        last = moved;
        if sigma <= 0.001 {
            assert!(moved < 0.01, "σ {sigma}: moved {moved} mm");
        }
        if sigma >= 1e4 {
            let (mean, _) = tre(&r.image_to_physical, &free.image_to_physical);
            assert!(mean < 0.01, "σ {sigma}: {mean} mm from the free fit");
        }
    }
    let bad = WicpParams {
        trusted_alignment_mm: Some(-1.0),
        ..tight()
    };
    let l = liver();
    let e = wicp(&l.model, &l.corr, &meas, &bad)
        .unwrap_err()
        .to_string();
    assert!(e.contains("trusted_alignment_mm"), "{e}");
}

/// Points on one flat face of a box leave two translations and a rotation free: the
/// conditioning says so (against a box measured on three faces), the start is trusted, and the
/// result is flagged with a warning.
#[test]
fn a_flat_patch_is_flagged_ill_posed_and_does_not_move_the_organ() {
    use librplus::mesh::procedural::box_mesh;
    let mesh = box_mesh([100.0, 60.0, 80.0], [10, 6, 8], 0.0);
    let n = mesh.num_nodes();
    let boundary: Vec<bool> = {
        let mut b = vec![false; n];
        for v in mesh.boundary().unwrap().nodes {
            b[v as usize] = true;
        }
        b
    };
    let model = PreopModel {
        mesh: mesh.clone(),
        anterior: boundary.clone(),
        posterior: vec![false; n],
        falciform: vec![false; n],
        inferior_ridge: vec![false; n],
        vessel_points: Vec::new(),
        vessel_segments: Vec::new(),
    };
    let corr = Correspondence::new(&model).unwrap();
    let mut g = SplitMix64::new(4);
    let face = |g: &mut SplitMix64| -> Vec<[f64; 3]> {
        (0..200)
            .map(|_| [10.0 + 80.0 * g.next_f64(), 0.0, 10.0 + 60.0 * g.next_f64()])
            .collect()
    };
    let start = Rigid::from_axis_angle([0.0, 1.0, 0.0], 2f64.to_radians(), [2.0, 0.0, -3.0]);
    let measure = |pts: Vec<[f64; 3]>| Measurements {
        kind: vec![MeasuredKind::Surface; pts.len()],
        points: pts,
        feature: Vec::new(),
        initial_alignment: Some(start),
    };
    // One face (y = 0): ill-posed.
    let flat = measure(face(&mut g));
    let r = wicp(&model, &corr, &flat, &WicpParams::default()).unwrap();
    assert!(r.ill_posed, "conditioning {}", r.conditioning);
    assert!(r.conditioning < 1e-3, "{}", r.conditioning);
    assert_eq!(r.prior.map(|p| p.sigma_mm), Some(10.0));
    assert!(
        r.warnings
            .iter()
            .any(|w| w.contains("do not fix the rigid motion")),
        "{:?}",
        r.warnings
    );
    assert!(r.moved_from_start_mm < 1.0, "{}", r.moved_from_start_mm);
    // Three faces (y = 0, x = 0, z = 0): well-posed, not flagged.
    let mut pts = face(&mut g);
    pts.extend((0..200).map(|_| [0.0, 5.0 + 50.0 * g.next_f64(), 5.0 + 70.0 * g.next_f64()]));
    pts.extend((0..200).map(|_| [5.0 + 90.0 * g.next_f64(), 5.0 + 50.0 * g.next_f64(), 0.0]));
    let r = wicp(&model, &corr, &measure(pts), &WicpParams::default()).unwrap();
    assert!(!r.ill_posed && r.prior.is_none(), "{}", r.conditioning);
    assert!(r.conditioning > 1e-2, "{}", r.conditioning);
}

/// The closest-triangle searches of a matching loop start from the last call's triangles
/// (`match_points_hinted`): the matches must be those of a search from nothing, bit for bit,
/// whether the hints are fresh (the points moved a little), stale (moved a lot), or belong to
/// other points entirely (the list reversed), on the undeformed and on a deformed model.
#[test]
fn hinted_matching_gives_the_matches_of_an_unhinted_one() {
    use librplus::register::correspondence::Hints;
    let l = liver();
    let s = scenario(Category::Planes3, &MeasureParams::default(), 17);
    let meas = measurements(&s);
    let cparams = CorrespondenceParams::default();
    let n = l.mesh.num_nodes();
    // A smooth deformation of a few millimetres, to exercise the refitted trees too.
    let u: Vec<f64> = (0..3 * n)
        .map(|k| {
            let x = l.mesh.nodes()[k / 3];
            3.0 * ((x[0] * 0.03 + k as f64 % 3.0).sin() + (x[1] * 0.02).cos())
        })
        .collect();
    let mut rng = SplitMix64::new(5);
    for deformed in [None, Some(&u[..])] {
        let mut hints = Hints::default();
        for step in 0..8 {
            // Steps 0-3 move the points by up to 0.5 mm, 4-5 by up to 20 mm, 6-7 reverse them.
            let amp = if step < 4 { 0.5 } else { 20.0 };
            let mut pts: Vec<[f64; 3]> = meas
                .points
                .iter()
                .map(|&p| p.map(|c| c + amp * (rng.next_f64() - 0.5)))
                .collect();
            let mut m = meas.clone();
            if step >= 6 {
                pts.reverse();
                m.points.reverse();
                m.kind.reverse();
                m.feature.reverse();
            }
            let plain = l
                .corr
                .match_points(&pts, &common::checked(m.clone()), deformed, &cparams)
                .unwrap();
            let hinted = l
                .corr
                .match_points_hinted(
                    &pts,
                    &common::checked(m.clone()),
                    deformed,
                    &cparams,
                    &mut hints,
                )
                .unwrap();
            assert_eq!(plain.0, hinted.0, "step {step}: the matches differ");
            assert_eq!(plain.1, hinted.1, "step {step}: the statistics differ");
            assert!(!plain.0.is_empty());
        }
    }
}

/// A deadline stops the iterations where they are and says so: one already past runs none (the
/// answer is the start, not converged); one far away changes nothing.
#[test]
fn a_deadline_stops_the_iterations_and_says_so() {
    use std::time::{Duration, Instant};
    let s = scenario(Category::Surface, &MeasureParams::default(), 21);
    let meas = measurements(&s);
    let free = run(&meas, &WicpParams::default());
    assert!(free.converged && !free.stopped_at_deadline, "{free:?}");
    assert!(free.iterations > 1, "{free:?}");
    let past = run(
        &meas,
        &WicpParams {
            deadline: Some(Instant::now()),
            ..WicpParams::default()
        },
    );
    assert!(past.stopped_at_deadline && !past.converged, "{past:?}");
    assert_eq!(past.iterations, 0);
    assert_eq!(past.image_to_physical, s.initial_alignment);
    let far = run(
        &meas,
        &WicpParams {
            deadline: Some(Instant::now() + Duration::from_secs(3600)),
            ..WicpParams::default()
        },
    );
    assert!(!far.stopped_at_deadline);
    assert_eq!(far.iterations, free.iterations);
    assert_eq!(far.image_to_physical, free.image_to_physical);
    eprintln!(
        "deadline: none {} iterations (rms {:.3} mm), past 0 (rms {:.3} mm, the start's), an hour away {}",
        free.iterations, free.rms_mm, past.rms_mm, far.iterations
    );
}

/// Points wandering near the real liver's surface (where closest points often sit on shared
/// edges and vertices, so several triangles tie): the certified query gives the plain query's
/// answer bit for bit at every step, answers most small steps from its certificate, and never
/// uses a certificate issued before the tree was refitted.
#[test]
fn certified_query_is_the_plain_query_bit_for_bit() {
    let surface = librplus::assets::default_liver().unwrap();
    let mut bvh = TriangleBvh::new(&surface);
    let nodes = surface.nodes();
    let mut rng = librplus::util::SplitMix64::new(11);
    let (mut hits, mut queries) = (0usize, 0usize);
    let mut check = |bvh: &TriangleBvh, p: [f64; 3], cert: &mut Option<Certificate>| {
        let before = *cert;
        let c = bvh.closest_certified(p, cert).unwrap();
        assert_eq!(c, bvh.closest(p, None).unwrap(), "at {p:?}");
        queries += 1;
        if before.is_some() && *cert == before {
            hits += 1;
        }
    };
    for walk in 0..200 {
        let v = nodes[rng.below(nodes.len())];
        let mut p = v.map(|x| x + 6.0 * rng.next_f64() - 3.0);
        let mut cert = None;
        // Steps from 2 mm down to a micrometre, as an ICP run's points move.
        for step in 0..40 {
            let size = 2.0 * 0.75f64.powi(step) + if walk % 2 == 0 { 0.0 } else { 1e-3 };
            p = p.map(|x| x + size * (2.0 * rng.next_f64() - 1.0));
            check(&bvh, p, &mut cert);
        }
        // A moved geometry: the old certificate names the old tree and is not used.
        if walk % 50 == 0 {
            let moved: Vec<[f64; 3]> = nodes
                .iter()
                .map(|q| [q[0] + 0.3, q[1], q[2] - 0.2])
                .collect();
            bvh.refit(&moved);
            let stale = cert;
            check(&bvh, p, &mut cert);
            assert_ne!(
                cert, stale,
                "a certificate of the tree before the refit was used"
            );
            bvh = TriangleBvh::new(&surface);
        }
    }
    assert!(
        hits * 2 > queries,
        "certificates answered {hits} of {queries} queries: the small steps should mostly be \
         answered without a search"
    );
}
