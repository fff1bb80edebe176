//! Sparse-measurement simulation (`librplus::phantom::measure`) and its helpers, the rigid transform
//! (`mesh::rigid`) and the point locator (`mesh::locate`), checked against facts computed here
//! independently: exact recovery of known transforms, exact reproduction of linear fields, points on
//! the deformed anterior / posterior surfaces (by a BVH over those triangles only), in their planes
//! and fans, on the affinely deformed vessel centerlines, the spacing and coverage asked for, the
//! misalignment bounds over many seeds, noise levels within 10%, and determinism.
//!
//! The liver is `assets/livers/sofa_liver.vtk` meshed with 10 mm tets, deformed by a smooth field
//! (a 3° rotation about its centroid plus a bending of a few mm).

use librplus::mesh::io::{self, Unit};
use librplus::mesh::locate::TetLocator;
use librplus::mesh::rigid::Rigid;
use librplus::mesh::spatial::TriangleBvh;
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::mesh::{TetMesh, TriSurface};
use librplus::phantom::measure::{Category, MeasureParams, PointKind, Scenario, simulate};
use librplus::phantom::vessels::{VesselParams, VesselTree};
use librplus::register::anatomy::{AnatomyLabels, LabelParams, Region, label};
use librplus::util::SplitMix64;
use std::path::PathBuf;
use std::sync::OnceLock;

struct Liver {
    mesh: TetMesh,
    labels: AnatomyLabels,
    vessels: VesselTree,
    /// The smooth synthetic displacement.
    u: Vec<f64>,
    centroid: [f64; 3],
}

fn liver() -> &'static Liver {
    static LIVER: OnceLock<Liver> = OnceLock::new();
    LIVER.get_or_init(|| {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/livers/sofa_liver.vtk");
        let surface = TriSurface::from_file(&io::read(path, Unit::Mm).unwrap())
            .unwrap()
            .largest_component();
        let mesh = tetrahedralize(&surface, &TetraParams::with_edge(10.0)).unwrap();
        let labels = label(&mesh, &LabelParams::default()).unwrap();
        let vessels = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
        let centroid = centroid(mesh.nodes());
        let (lo, hi) = mesh.bounding_box();
        let rot = Rigid::from_axis_angle([0.0, 0.0, 1.0], 3f64.to_radians(), [0.0; 3]);
        let mut u = Vec::with_capacity(3 * mesh.num_nodes());
        for &p in mesh.nodes() {
            let d = sub(p, centroid);
            let r = sub(rot.apply_vector(d), d);
            let s = 2.0 * (p[0] - centroid[0]) / (hi[0] - lo[0]);
            let t = 2.0 * (p[2] - centroid[2]) / (hi[2] - lo[2]);
            u.extend([r[0], r[1] + 6.0 * s * s, r[2] + 3.0 * s * t]);
        }
        Liver {
            mesh,
            labels,
            vessels,
            u,
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
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
fn centroid(p: &[[f64; 3]]) -> [f64; 3] {
    let s = p.iter().fold([0.0; 3], |a, &q| add(a, q));
    s.map(|c| c / p.len() as f64)
}

fn noise_free() -> MeasureParams {
    MeasureParams {
        surface_noise_mm: 0.0,
        us_noise_mm: 0.0,
        landmark_noise_mm: 0.0,
        ..MeasureParams::default()
    }
}

fn deformed(l: &Liver, u: &[f64]) -> Vec<[f64; 3]> {
    l.mesh
        .nodes()
        .iter()
        .enumerate()
        .map(|(i, &p)| add(p, [u[3 * i], u[3 * i + 1], u[3 * i + 2]]))
        .collect()
}

/// Boundary triangles whose three nodes are all in `region`.
fn region_triangles(l: &Liver, region: Region) -> Vec<[u32; 3]> {
    l.mesh
        .boundary()
        .unwrap()
        .triangles
        .into_iter()
        .filter(|t| t.iter().all(|&v| l.labels.region[v as usize] == region))
        .collect()
}

fn random_rigid(rng: &mut SplitMix64, max_angle: f64) -> Rigid {
    let axis = [0; 3].map(|_| rng.next_f64() - 0.5);
    let t = [0; 3].map(|_| 100.0 * (rng.next_f64() - 0.5));
    Rigid::from_axis_angle(axis, max_angle * rng.next_f64(), t)
}

fn assert_rigid_close(a: &Rigid, b: &Rigid, tol_r: f64, tol_t: f64) {
    for i in 0..3 {
        for j in 0..3 {
            let d = (a.rotation[i][j] - b.rotation[i][j]).abs();
            assert!(
                d <= tol_r,
                "rotation[{i}][{j}] differs by {d:e}\n{a:?}\n{b:?}"
            );
        }
        let d = (a.translation[i] - b.translation[i]).abs();
        assert!(
            d <= tol_t,
            "translation[{i}] differs by {d:e}\n{a:?}\n{b:?}"
        );
    }
}

#[test]
fn rigid_fit_inverse_composition_and_angle() {
    let mut rng = SplitMix64::new(11);
    for _ in 0..20 {
        let truth = random_rigid(&mut rng, 3.0);
        let src: Vec<[f64; 3]> = (0..12)
            .map(|_| [0; 3].map(|_| 200.0 * rng.next_f64() - 100.0))
            .collect();
        let dst: Vec<[f64; 3]> = src.iter().map(|&p| truth.apply(p)).collect();
        let fit = Rigid::fit(&src, &dst, None).unwrap();
        assert_rigid_close(&fit, &truth, 1e-12, 1e-9);
        // Weights: a wild outlier with weight zero changes nothing.
        let mut dst2 = dst.clone();
        dst2[0] = [1e3, -1e3, 5e2];
        let mut w = vec![1.0; src.len()];
        w[0] = 0.0;
        assert_rigid_close(
            &Rigid::fit(&src, &dst2, Some(&w)).unwrap(),
            &truth,
            1e-12,
            1e-9,
        );
        // A planar set (z = 0) is recovered too, without a reflection.
        let flat: Vec<[f64; 3]> = src.iter().map(|p| [p[0], p[1], 0.0]).collect();
        let flat_dst: Vec<[f64; 3]> = flat.iter().map(|&p| truth.apply(p)).collect();
        assert_rigid_close(
            &Rigid::fit(&flat, &flat_dst, None).unwrap(),
            &truth,
            1e-12,
            1e-9,
        );
        // Inverse and composition.
        let other = random_rigid(&mut rng, 3.0);
        for &p in &src {
            let back = truth.inverse().apply(truth.apply(p));
            assert!(norm(sub(back, p)) <= 1e-12 * 200.0);
            let composed = truth.then(&other).apply(p);
            let stepwise = other.apply(truth.apply(p));
            assert!(norm(sub(composed, stepwise)) <= 1e-12 * 300.0);
            let v = sub(p, src[1]);
            assert!(
                norm(sub(
                    truth.apply_vector(v),
                    sub(truth.apply(p), truth.apply(src[1]))
                )) <= 1e-12 * 300.0
            );
        }
        let id = truth.then(&truth.inverse());
        assert_rigid_close(&id, &Rigid::identity(), 1e-14, 1e-12);
    }
    // A mirrored point set still gives a proper rotation (det +1), never a reflection.
    let src = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 2.0, 0.0],
        [0.0, 0.0, 3.0],
    ];
    let mirrored: Vec<[f64; 3]> = src.iter().map(|p| [-p[0], p[1], p[2]]).collect();
    let r = Rigid::fit(&src, &mirrored, None).unwrap().rotation;
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
        - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    assert!((det - 1.0).abs() < 1e-12, "det {det}");
    // Too few or collinear points: no fit.
    let line = [
        [0.0, 0.0, 0.0],
        [1.0, 1.0, 1.0],
        [2.0, 2.0, 2.0],
        [5.0, 5.0, 5.0],
    ];
    assert!(Rigid::fit(&line, &line, None).is_none());
    assert!(Rigid::fit(&src[..2], &src[..2], None).is_none());
    assert!(Rigid::fit(&src, &src[..3], None).is_none());
    // Angles, small ones included.
    for deg in [0.0, 1e-6, 0.5, 15.0, 90.0, 179.0] {
        let r = Rigid::from_axis_angle([1.0, -2.0, 0.5], f64::to_radians(deg), [0.0; 3]);
        assert!(
            (r.rotation_angle_deg() - deg).abs() < 1e-9 * deg.max(1.0),
            "{deg}"
        );
    }
    let j = serde_json::to_string(&Rigid::identity()).unwrap();
    assert_eq!(
        serde_json::from_str::<Rigid>(&j).unwrap(),
        Rigid::identity()
    );
}

#[test]
fn splitmix_normal_is_standard_and_deterministic() {
    let mut a = SplitMix64::new(3);
    let mut b = SplitMix64::new(3);
    let n = 200_000;
    let (mut s1, mut s2, mut s4) = (0.0, 0.0, 0.0);
    for _ in 0..n {
        let x = a.normal();
        assert_eq!(x.to_bits(), b.normal().to_bits());
        assert!(x.is_finite());
        s1 += x;
        s2 += x * x;
        s4 += x * x * x * x;
    }
    let (m, v, k) = (s1 / n as f64, s2 / n as f64, s4 / n as f64);
    eprintln!("normal: mean {m:.4}, variance {v:.4}, fourth moment {k:.3}");
    // Standard errors: mean 0.0022, variance 0.0032, fourth moment 0.02.
    assert!(m.abs() < 0.01 && (v - 1.0).abs() < 0.015 && (k - 3.0).abs() < 0.1);
}

#[test]
fn locator_reproduces_linear_fields_and_rejects_outside_points() {
    let l = liver();
    let loc = TetLocator::new(&l.mesh);
    let a = [[0.3, -0.2, 0.1], [0.05, 0.4, -0.3], [-0.1, 0.2, 0.25]];
    let b = [1.0, -2.0, 3.0];
    let f = |p: [f64; 3]| [0, 1, 2].map(|i| dot(a[i], p) + b[i]);
    let field: Vec<f64> = l.mesh.nodes().iter().flat_map(|&p| f(p)).collect();
    let mut rng = SplitMix64::new(5);
    let nodes = l.mesh.nodes();
    for _ in 0..500 {
        // A random point of a random tet, from barycentric weights chosen here.
        let t = rng.below(l.mesh.num_tets());
        let mut w = [0; 4].map(|_| rng.next_f64() + 1e-3);
        let s: f64 = w.iter().sum();
        w = w.map(|x| x / s);
        let tet = l.mesh.tets()[t];
        let mut p = [0.0; 3];
        for k in 0..4 {
            p = add(p, nodes[tet[k] as usize].map(|c| c * w[k]));
        }
        let (found, bary) = loc.locate(p).expect("point inside a tet");
        assert!(bary.iter().all(|&x| x >= -1e-9));
        assert!((bary.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        let ft = l.mesh.tets()[found];
        let mut back = [0.0; 3];
        for k in 0..4 {
            back = add(back, nodes[ft[k] as usize].map(|c| c * bary[k]));
        }
        assert!(
            norm(sub(back, p)) < 1e-9,
            "barycentrics reproduce the point"
        );
        let g = loc.interpolate(&field, p);
        assert!(norm(sub(g, f(p))) < 1e-9, "{g:?} vs {:?}", f(p));
    }
    // Far outside: no tet; the field there is its value at the closest boundary point.
    let surface = l.mesh.boundary_surface().unwrap();
    let bvh = TriangleBvh::new(&surface);
    let (lo, hi) = l.mesh.bounding_box();
    for p in [
        add(hi, [5.0, 5.0, 5.0]),
        sub(lo, [30.0, 0.0, 0.0]),
        [l.centroid[0], lo[1] - 12.0, l.centroid[2]],
    ] {
        assert!(loc.locate(p).is_none(), "{p:?} is outside");
        let c = bvh.closest(p, None).unwrap().point;
        let g = loc.interpolate(&field, p);
        assert!(norm(sub(g, f(c))) < 1e-9, "{g:?} vs {:?}", f(c));
    }
    // Brute force over all tets agrees with the grid on points spread over the bounding box.
    let mut inside = 0;
    for _ in 0..300 {
        let p = [0, 1, 2].map(|k| lo[k] + (hi[k] - lo[k]) * rng.next_f64());
        let brute =
            (0..l.mesh.num_tets()).any(|t| loc.barycentric(t, p).iter().all(|&x| x >= -1e-9));
        assert_eq!(loc.locate(p).is_some(), brute, "{p:?}");
        inside += brute as usize;
    }
    eprintln!("locator: {inside}/300 random bounding-box points inside");
    assert!(inside > 50 && inside < 300);
}

#[test]
fn surface_points_lie_on_the_visible_anterior_patch_with_the_requested_spacing() {
    let l = liver();
    let def = deformed(l, &l.u);
    let ant = region_triangles(l, Region::Anterior);
    let ant_surface = TriSurface::new(def.clone(), ant.clone()).unwrap();
    let ant_area = ant_surface.area();
    let max_tri = ant_surface.triangle_areas().into_iter().fold(0.0, f64::max);
    let bvh = TriangleBvh::new(&ant_surface);
    let params = noise_free();
    for (seed, c) in [(1u64, 0.15), (2, 0.3), (3, 0.6)] {
        let p = MeasureParams {
            coverage: [c, c],
            ..params
        };
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Surface,
            &p,
            seed,
        )
        .unwrap();
        let n = sc.points.len();
        assert_eq!(n, sc.count(PointKind::Surface));
        assert!(sc.plane.iter().all(|&j| j == -1));
        // Achieved coverage within one triangle of the asked one.
        assert!(
            (sc.coverage - c).abs() <= max_tri / ant_area + 1e-12,
            "coverage {} asked {c}",
            sc.coverage
        );
        // Points on anterior triangles of the deformed mesh, and the measured ones are T of them.
        let mut hit = vec![false; ant.len()];
        for (q, m) in sc.truth_image.iter().zip(&sc.points) {
            let cl = bvh.closest(*q, None).unwrap();
            assert!(
                cl.distance <= 1e-9,
                "{} mm off the anterior surface",
                cl.distance
            );
            hit[cl.triangle as usize] = true;
            assert!(norm(sub(sc.image_to_physical.apply(*q), *m)) < 1e-9);
        }
        // Spacing: no two points nearer than asked; density between random saturation and the
        // hexagonal-packing bound 2/(√3 s²).
        let s = p.surface_spacing_mm;
        let mut min_d = f64::INFINITY;
        for i in 0..n {
            for j in i + 1..n {
                min_d = min_d.min(norm(sub(sc.truth_image[i], sc.truth_image[j])));
            }
        }
        let patch_area = sc.coverage * ant_area;
        let density = n as f64 * s * s / patch_area;
        // The area of triangles holding a point cannot exceed the patch.
        let areas = ant_surface.triangle_areas();
        let hit_area: f64 = (0..ant.len()).filter(|&t| hit[t]).map(|t| areas[t]).sum();
        assert!(hit_area <= patch_area * (1.0 + 1e-9));
        // Dart throwing near saturation leaves no hole wider than the spacing: the share of the
        // anterior area within one spacing of a point (Monte Carlo, area-weighted samples drawn
        // here) is the coverage plus a band of width s along the patch border, which for a patch
        // of this area is at most three times the perimeter of a disc of that area, times s.
        let mut rng = SplitMix64::new(seed);
        let total: f64 = areas.iter().sum();
        let samples = 20_000;
        let mut near = 0;
        for _ in 0..samples {
            let mut r = rng.next_f64() * total;
            let mut t = 0;
            while t + 1 < areas.len() && r >= areas[t] {
                r -= areas[t];
                t += 1;
            }
            let [a, b, c] = ant[t].map(|v| def[v as usize]);
            let (r1, r2) = (rng.next_f64().sqrt(), rng.next_f64());
            let q = [0, 1, 2].map(|k| (1.0 - r1) * a[k] + r1 * (1.0 - r2) * b[k] + r1 * r2 * c[k]);
            if sc.truth_image.iter().any(|&x| norm(sub(x, q)) <= s) {
                near += 1;
            }
        }
        let f = near as f64 / samples as f64;
        let band = 3.0 * 2.0 * (std::f64::consts::PI * patch_area).sqrt() * s / ant_area;
        eprintln!(
            "seed {seed}: coverage {:.3} (asked {c}), {n} points, min spacing {min_d:.2} mm, \
             density {density:.3}/s², area within s of a point {f:.3} (bounds {:.3}..{:.3})",
            sc.coverage,
            0.95 * sc.coverage,
            sc.coverage + band
        );
        assert!(min_d >= s - 1e-9, "min spacing {min_d}");
        assert!(density > 0.45 && density < 2.0 / 3f64.sqrt(), "{density}");
        assert!(f >= 0.95 * sc.coverage && f <= sc.coverage + band, "{f}");
    }
    // Drawn coverage: spread over [0.15, 0.60] across seeds.
    let covs: Vec<f64> = (0..30)
        .map(|seed| {
            simulate(
                &l.mesh,
                &l.labels,
                &l.vessels,
                &l.u,
                Category::Surface,
                &params,
                100 + seed,
            )
            .unwrap()
            .coverage
        })
        .collect();
    let (lo, hi) = covs
        .iter()
        .fold((1.0f64, 0.0f64), |(a, b), &c| (a.min(c), b.max(c)));
    eprintln!("coverage over 30 seeds: {lo:.3}..{hi:.3}");
    assert!(covs.iter().all(|&c| (0.15..=0.60).contains(&c)));
    assert!(lo < 0.25 && hi > 0.5);
}

/// Physical-frame checks of an ultrasound point: in its plane, inside its fan.
fn check_in_plane_and_fan(sc: &Scenario, i: usize, params: &MeasureParams, tol_plane: f64) {
    let pl = &sc.planes[sc.plane[i] as usize];
    let d = sub(sc.points[i], pl.origin);
    let off = dot(d, pl.normal).abs();
    assert!(off <= tol_plane, "point {i} is {off:e} mm off its plane");
    let (a, b) = (dot(d, pl.depth_dir), dot(d, pl.lateral_dir));
    assert!((a * a + b * b).sqrt() <= params.fan_depth_mm + 1e-9);
    assert!(b.abs().atan2(a).to_degrees() <= params.fan_half_angle_deg + 1e-9);
}

#[test]
fn ultrasound_points_lie_in_their_fans_on_the_posterior_surface_and_vessels() {
    let l = liver();
    let def = deformed(l, &l.u);
    let post =
        TriangleBvh::new(&TriSurface::new(def, region_triangles(l, Region::Posterior)).unwrap());
    let params = noise_free();
    let mut total_contour = 0;
    let mut total_vessel = 0;
    for seed in [4u64, 5] {
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Planes16,
            &params,
            seed,
        )
        .unwrap();
        assert_eq!(sc.planes.len(), 16);
        for pl in &sc.planes {
            for v in [pl.depth_dir, pl.lateral_dir, pl.normal] {
                assert!((norm(v) - 1.0).abs() < 1e-12);
            }
            assert!(dot(pl.depth_dir, pl.lateral_dir).abs() < 1e-12);
            assert!(dot(pl.depth_dir, pl.normal).abs() < 1e-12);
        }
        let counts = sc.contour_counts();
        eprintln!(
            "seed {seed}: contour points per plane {counts:?}, vessel {:?}",
            sc.vessel_counts()
        );
        assert_eq!(
            counts.iter().sum::<usize>(),
            sc.count(PointKind::PosteriorContour)
        );
        assert!(
            counts.iter().filter(|&&c| c > 0).count() >= 8,
            "most fans reach the back"
        );
        for i in 0..sc.points.len() {
            match sc.kind[i] {
                PointKind::Surface => assert_eq!(sc.plane[i], -1),
                PointKind::PosteriorContour => {
                    check_in_plane_and_fan(&sc, i, &params, 1e-9);
                    let d = post.distance(sc.truth_image[i]);
                    assert!(d <= 1e-9, "contour point {d} mm off the posterior surface");
                    total_contour += 1;
                }
                PointKind::Vessel => {
                    check_in_plane_and_fan(&sc, i, &params, 1e-9);
                    total_vessel += 1;
                }
            }
        }
        // Spacing along the contour: each point's nearest neighbour in its plane is about one
        // spacing away (a chord is at most the arc).
        let mut nn = Vec::new();
        for i in 0..sc.points.len() {
            if sc.kind[i] != PointKind::PosteriorContour {
                continue;
            }
            let d = (0..sc.points.len())
                .filter(|&j| {
                    j != i
                        && sc.kind[j] == PointKind::PosteriorContour
                        && sc.plane[j] == sc.plane[i]
                })
                .map(|j| norm(sub(sc.truth_image[i], sc.truth_image[j])))
                .fold(f64::INFINITY, f64::min);
            nn.push(d);
        }
        nn.sort_by(f64::total_cmp);
        let median = nn[nn.len() / 2];
        eprintln!("seed {seed}: median contour neighbour distance {median:.3} mm");
        assert!(median <= params.us_spacing_mm + 1e-9 && median >= 0.8 * params.us_spacing_mm);
    }
    assert!(
        total_contour > 100 && total_vessel > 0,
        "{total_contour} {total_vessel}"
    );
}

#[test]
fn vessel_points_lie_on_the_deformed_centerlines() {
    // An affine displacement: linear interpolation reproduces it exactly, so the deformed
    // centerline is known here without the locator.
    let l = liver();
    let a = [[0.02, -0.01, 0.0], [0.01, 0.03, -0.02], [0.0, 0.015, -0.01]];
    let b = [2.0, -1.0, 0.5];
    let map = |p: [f64; 3]| add(p, [0, 1, 2].map(|i| dot(a[i], p) + b[i]));
    let u: Vec<f64> = l
        .mesh
        .nodes()
        .iter()
        .flat_map(|&p| sub(map(p), p))
        .collect();
    let loc = TetLocator::new(&l.mesh);
    let outside = l
        .vessels
        .points
        .iter()
        .filter(|&&p| loc.locate(p).is_none())
        .count();
    let params = noise_free();
    let mut found = 0;
    for seed in [6u64, 7, 8] {
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &u,
            Category::Planes16,
            &params,
            seed,
        )
        .unwrap();
        for i in 0..sc.points.len() {
            if sc.kind[i] != PointKind::Vessel {
                continue;
            }
            found += 1;
            let q = sc.truth_image[i];
            let d = l
                .vessels
                .segments
                .iter()
                .map(|s| {
                    let (pa, pb) = (
                        map(l.vessels.points[s[0] as usize]),
                        map(l.vessels.points[s[1] as usize]),
                    );
                    librplus::phantom::vessels::point_segment_distance(q, pa, pb).0
                })
                .fold(f64::INFINITY, f64::min);
            assert!(
                d <= 1e-9,
                "vessel point {d:e} mm off the deformed centerline"
            );
        }
    }
    eprintln!(
        "{found} vessel points over 3 × 16 planes; {outside} of {} centerline points outside the mesh",
        l.vessels.points.len()
    );
    assert!(found >= 5);
}

#[test]
fn misalignment_bounds_and_landmark_alignment() {
    let l = liver();
    let params = MeasureParams::default();
    let (mut max_angle, mut max_shift) = (0.0f64, 0.0f64);
    let mut sq = 0.0;
    let mut count = 0;
    let mut align_err = Vec::new();
    let def = deformed(l, &l.u);
    for seed in 0..100u64 {
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Surface,
            &params,
            seed,
        )
        .unwrap();
        let t = sc.image_to_physical;
        let angle = t.rotation_angle_deg();
        let shift = norm(sub(t.apply(l.centroid), l.centroid));
        assert!(
            angle <= 15.0 + 1e-9 && shift <= 20.0 + 1e-9,
            "{angle} {shift}"
        );
        max_angle = max_angle.max(angle);
        max_shift = max_shift.max(shift);
        assert_eq!(sc.landmark_nodes.len(), 4);
        for (k, &v) in sc.landmark_nodes.iter().enumerate() {
            assert_eq!(sc.landmarks_image[k], l.mesh.nodes()[v as usize]);
            let e = sub(sc.landmarks_physical[k], t.apply(def[v as usize]));
            sq += dot(e, e);
            count += 3;
        }
        align_err.push(norm(sub(
            sc.initial_alignment.apply(l.centroid),
            t.apply(l.centroid),
        )));
    }
    let rms = (sq / count as f64).sqrt();
    align_err.sort_by(f64::total_cmp);
    eprintln!(
        "100 seeds: max angle {max_angle:.2}°, max centroid shift {max_shift:.2} mm, landmark noise \
         {rms:.3} mm per axis (asked 4), coarse-alignment error at the centroid median {:.1} mm, max {:.1} mm",
        align_err[50], align_err[99]
    );
    assert!(max_angle > 12.0 && max_shift > 17.0);
    assert!((rms / params.landmark_noise_mm - 1.0).abs() < 0.1, "{rms}");

    // The landmarks are the anatomical ones.
    let sc = simulate(
        &l.mesh,
        &l.labels,
        &l.vessels,
        &l.u,
        Category::Surface,
        &params,
        1,
    )
    .unwrap();
    let x = |v: u32| l.mesh.nodes()[v as usize];
    let fal = AnatomyLabels::nodes_where(&l.labels.falciform);
    let ridge = AnatomyLabels::nodes_where(&l.labels.inferior_ridge);
    let [top, left, right, notch] = [0, 1, 2, 3].map(|k| sc.landmark_nodes[k]);
    assert!(fal.contains(&top) && fal.iter().all(|&v| x(v)[2] <= x(top)[2]));
    assert!(
        ridge
            .iter()
            .all(|&v| x(v)[0] >= x(left)[0] && x(v)[0] <= x(right)[0])
    );
    assert!(ridge.contains(&notch) && notch != left && notch != right);

    // Without deformation and noise the landmark fit is the true transform.
    let zero = vec![0.0; l.u.len()];
    for seed in 0..5 {
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &zero,
            Category::Surface,
            &noise_free(),
            seed,
        )
        .unwrap();
        assert_rigid_close(&sc.initial_alignment, &sc.image_to_physical, 1e-10, 1e-8);
    }
}

#[test]
fn a_harder_start_moves_only_the_start_within_its_bounds() {
    let l = liver();
    let base = MeasureParams::default();
    let hard = MeasureParams {
        start_error: Some([30.0, 30.0]),
        ..base
    };
    let (mut max_angle, mut max_shift) = (0.0f64, 0.0f64);
    for seed in 0..60u64 {
        let run = |p: &MeasureParams| {
            simulate(
                &l.mesh,
                &l.labels,
                &l.vessels,
                &l.u,
                Category::Planes2,
                p,
                seed,
            )
            .unwrap()
        };
        let (a, b) = (run(&base), run(&hard));
        // Every other draw is the same: points, planes, landmarks, the true misalignment.
        assert_eq!(a.points, b.points);
        assert_eq!(a.landmarks_physical, b.landmarks_physical);
        assert_rigid_close(&a.image_to_physical, &b.image_to_physical, 0.0, 0.0);
        // The start moved by a rotation within 30° about where it put the centroid, and that
        // point by at most 30 mm.
        let extra = a.initial_alignment.inverse().then(&b.initial_alignment);
        let angle = extra.rotation_angle_deg();
        let c = a.initial_alignment.apply(l.centroid);
        let shift = norm(sub(b.initial_alignment.apply(l.centroid), c));
        assert!(
            angle <= 30.0 + 1e-9 && shift <= 30.0 + 1e-9,
            "{angle} {shift}"
        );
        max_angle = max_angle.max(angle);
        max_shift = max_shift.max(shift);
    }
    eprintln!(
        "60 seeds: extra start rotation up to {max_angle:.1}°, centroid shift up to {max_shift:.1} mm"
    );
    assert!(
        max_angle > 25.0 && max_shift > 25.0,
        "{max_angle} {max_shift}"
    );
    // Bad bounds name the field.
    let bad = MeasureParams {
        start_error: Some([200.0, 1.0]),
        ..base
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("start_error")
    );
}

#[test]
fn a_patch_cut_from_another_side_lies_on_that_side() {
    use librplus::phantom::measure::Visible;
    let l = liver();
    let def = deformed(l, &l.u);
    let tris = l.mesh.boundary().unwrap().triangles;
    let normal = |t: &[u32; 3]| {
        let p = t.map(|v| def[v as usize]);
        let (a, b) = (sub(p[1], p[0]), sub(p[2], p[0]));
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    // Outward: Σ n·(x − c) over the boundary is 6 × the volume (divergence theorem), > 0.
    let c = centroid(&def);
    let flux: f64 = tris
        .iter()
        .map(|t| dot(normal(t), sub(def[t[0] as usize], c)))
        .sum();
    assert!(flux > 0.0, "boundary normals point inward ({flux})");
    let all = TriSurface::new(def.clone(), tris.clone()).unwrap();
    let all_bvh = TriangleBvh::new(&all);
    // The surface points of a scenario (noise-free, image frame) and the mean outward normal of
    // the boundary triangles they lie on.
    let patch = |side: Visible, seed: u64| {
        let p = MeasureParams {
            visible: side,
            ..noise_free()
        };
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Surface,
            &p,
            seed,
        )
        .unwrap();
        let mut mean = [0.0; 3];
        for q in &sc.truth_image {
            let cl = all_bvh.closest(*q, None).unwrap();
            assert!(
                cl.distance <= 1e-9,
                "{side:?}: {} mm off the boundary",
                cl.distance
            );
            let n = normal(&tris[cl.triangle as usize]);
            mean = add(mean, n.map(|x| x / norm(n)));
        }
        (sc.truth_image.clone(), mean)
    };
    for (side, d) in [
        (Visible::Posterior, [0.0, 1.0, 0.0]),
        (Visible::Dome, [0.0, 0.0, 1.0]),
        (Visible::Left, [1.0, 0.0, 0.0]),
        (Visible::Right, [-1.0, 0.0, 0.0]),
    ] {
        // Exactly on the triangles facing that way.
        let facing: Vec<[u32; 3]> = tris
            .iter()
            .copied()
            .filter(|t| dot(normal(t), d) > 0.0)
            .collect();
        let bvh = TriangleBvh::new(&TriSurface::new(def.clone(), facing).unwrap());
        for seed in 0..4u64 {
            let (pts, _) = patch(side, seed);
            assert!(pts.len() > 10, "{side:?} seed {seed}: {} points", pts.len());
            for q in &pts {
                let cl = bvh.closest(*q, None).unwrap();
                assert!(
                    cl.distance <= 1e-9,
                    "{side:?} seed {seed}: {} mm off its side",
                    cl.distance
                );
            }
        }
    }
    // Any side: a direction per scenario, so the patches face different ways.
    let mut octants = std::collections::BTreeSet::new();
    for seed in 0..12u64 {
        let (_, m) = patch(Visible::Any, seed);
        octants.insert(m.map(|x| x > 0.0));
    }
    assert!(
        octants.len() >= 3,
        "12 patches face only {} octants",
        octants.len()
    );
    // The default (anterior) leaves the parameters as they were: neither key is written.
    let json = serde_json::to_value(MeasureParams::default()).unwrap();
    assert!(json.get("visible").is_none() && json.get("start_error").is_none());
}

#[test]
fn noise_levels_match_the_parameters() {
    // Dense surface points (2.5 mm) over three seeds: thousands of residuals per axis, so the
    // standard error of a measured deviation is about 1%, far inside the 10% allowed.
    let l = liver();
    let params = MeasureParams {
        coverage: [0.6, 0.6],
        surface_spacing_mm: 2.5,
        surface_noise_mm: 1.0,
        us_noise_mm: 0.5,
        ..MeasureParams::default()
    };
    let (mut s_sq, mut s_n) = ([0.0; 3], 0);
    let (mut u_sq, mut u_n, mut out_of_plane) = (0.0, 0, 0.0f64);
    for seed in [9u64, 10, 11] {
        let clean = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Planes16,
            &noise_free(),
            seed,
        )
        .unwrap();
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Planes16,
            &params,
            seed,
        )
        .unwrap();
        // Noise does not move the noise-free geometry: same transform and planes.
        assert_eq!(clean.image_to_physical, sc.image_to_physical);
        assert_eq!(clean.planes, sc.planes);
        let inv = sc.image_to_physical.inverse();
        for i in 0..sc.points.len() {
            let e = sub(inv.apply(sc.points[i]), sc.truth_image[i]);
            if sc.kind[i] == PointKind::Surface {
                for k in 0..3 {
                    s_sq[k] += e[k] * e[k];
                }
                s_n += 1;
            } else {
                let pl = &sc.planes[sc.plane[i] as usize];
                let ep = sc.image_to_physical.apply_vector(e);
                u_sq += dot(ep, pl.depth_dir).powi(2) + dot(ep, pl.lateral_dir).powi(2);
                u_n += 2;
                out_of_plane = out_of_plane.max(dot(ep, pl.normal).abs());
            }
        }
    }
    let s_rms = s_sq.map(|v| (v / s_n as f64).sqrt());
    let u_rms = (u_sq / u_n as f64).sqrt();
    eprintln!(
        "surface noise per axis {s_rms:.3?} over {s_n} points (asked 1), ultrasound in-plane {u_rms:.3} \
         over {u_n} values (asked 0.5), out of plane ≤ {out_of_plane:.1e}"
    );
    assert!(s_n > 3000 && u_n > 1500);
    assert!(s_rms.iter().all(|&r| (r - 1.0).abs() < 0.1));
    assert!((u_rms / 0.5 - 1.0).abs() < 0.1);
    assert!(out_of_plane < 1e-9);
}

#[test]
fn categories_determinism_and_errors() {
    let l = liver();
    let params = MeasureParams::default();
    let names: Vec<&str> = Category::ALL.iter().map(|c| c.name()).collect();
    assert_eq!(
        names,
        [
            "surface",
            "surface+1us",
            "surface+2us",
            "surface+3us",
            "surface+16us"
        ]
    );
    let mut all = Vec::new();
    for (c, want) in Category::ALL.into_iter().zip([0, 1, 2, 3, 16]) {
        assert_eq!(c.planes(), want);
        let sc = simulate(&l.mesh, &l.labels, &l.vessels, &l.u, c, &params, 21).unwrap();
        assert_eq!(sc.planes.len(), want);
        assert_eq!(sc.contour_counts().len(), want);
        assert_eq!(sc.points.len(), sc.kind.len());
        assert_eq!(sc.points.len(), sc.plane.len());
        assert_eq!(sc.points.len(), sc.truth_image.len());
        for (k, &j) in sc.kind.iter().zip(&sc.plane) {
            assert_eq!(*k == PointKind::Surface, j == -1);
            assert!(j < want as i32);
        }
        all.push(sc);
    }
    // One seed: the same surface and transform in every category, planes nested.
    for sc in &all[1..] {
        assert_eq!(sc.coverage, all[0].coverage);
        assert_eq!(sc.image_to_physical, all[0].image_to_physical);
        assert_eq!(
            sc.count(PointKind::Surface),
            all[0].count(PointKind::Surface)
        );
        assert_eq!(sc.planes[..], all[4].planes[..sc.planes.len()]);
    }
    // Determinism: same seed identical, another seed different.
    let again = simulate(
        &l.mesh,
        &l.labels,
        &l.vessels,
        &l.u,
        Category::Planes3,
        &params,
        21,
    )
    .unwrap();
    assert_eq!(
        serde_json::to_string(&again).unwrap(),
        serde_json::to_string(&all[3]).unwrap()
    );
    let other = simulate(
        &l.mesh,
        &l.labels,
        &l.vessels,
        &l.u,
        Category::Planes3,
        &params,
        22,
    )
    .unwrap();
    assert_ne!(other.points, all[3].points);
    assert_ne!(other.image_to_physical, all[3].image_to_physical);

    // Errors name the problem.
    let err = |u: &[f64], labels: &AnatomyLabels, p: &MeasureParams| {
        simulate(&l.mesh, labels, &l.vessels, u, Category::Planes1, p, 0)
            .unwrap_err()
            .to_string()
    };
    let e = err(&l.u[..l.u.len() - 1], &l.labels, &params);
    assert!(e.contains("displacement"), "{e}");
    let mut nan = l.u.clone();
    nan[7] = f64::NAN;
    assert!(err(&nan, &l.labels, &params).contains("node 2"));
    let mut no_front = l.labels.clone();
    for r in &mut no_front.region {
        if *r == Region::Anterior {
            *r = Region::Posterior;
        }
    }
    assert!(err(&l.u, &no_front, &params).contains("anterior"));
    let few = MeasureParams {
        landmarks: 2,
        ..params
    };
    assert!(err(&l.u, &l.labels, &few).contains("landmarks"));
    let wide = MeasureParams {
        fan_half_angle_deg: 100.0,
        ..params
    };
    assert!(err(&l.u, &l.labels, &wide).contains("fan_half_angle_deg"));
    // Labels without falciform or ridge: landmarks fall back to spread anterior nodes.
    let mut bare = l.labels.clone();
    bare.falciform.iter_mut().for_each(|f| *f = false);
    bare.inferior_ridge.iter_mut().for_each(|f| *f = false);
    let sc = simulate(
        &l.mesh,
        &bare,
        &l.vessels,
        &l.u,
        Category::Surface,
        &params,
        0,
    )
    .unwrap();
    assert_eq!(sc.landmark_nodes.len(), 4);
    assert!(
        sc.landmark_nodes
            .iter()
            .all(|&v| bare.region[v as usize] == Region::Anterior)
    );
}

/// Salient-feature designations: a surface point is tagged falciform (1) or ridge (2) exactly when
/// its noise-free position is within the radius of a labelled deformed node of that feature (the
/// nearer feature winning), ultrasound points never are, and broad coverage tags some of each.
#[test]
fn salient_feature_designations_follow_the_labels() {
    let l = liver();
    let def = deformed(l, &l.u);
    let set = |flags: &[bool]| -> Vec<[f64; 3]> {
        (0..flags.len())
            .filter(|&i| flags[i])
            .map(|i| def[i])
            .collect()
    };
    let (falc, ridge) = (set(&l.labels.falciform), set(&l.labels.inferior_ridge));
    let near = |s: &[[f64; 3]], p: [f64; 3]| {
        s.iter()
            .map(|&q| norm(sub(p, q)))
            .fold(f64::INFINITY, f64::min)
    };
    let params = MeasureParams {
        coverage: [0.6, 0.6],
        ..noise_free()
    };
    let (mut tagged, mut kinds) = (0, [0usize; 3]);
    for seed in 1..=6u64 {
        let sc = simulate(
            &l.mesh,
            &l.labels,
            &l.vessels,
            &l.u,
            Category::Planes3,
            &params,
            seed,
        )
        .unwrap();
        assert_eq!(sc.feature.len(), sc.points.len());
        for (i, &f) in sc.feature.iter().enumerate() {
            if sc.kind[i] != PointKind::Surface {
                assert_eq!(f, 0);
                continue;
            }
            let p = sc.truth_image[i];
            let (df, dr) = (near(&falc, p), near(&ridge, p));
            let expect = if df.min(dr) > params.feature_radius_mm {
                0
            } else if df <= dr {
                1
            } else {
                2
            };
            assert_eq!(f, expect, "point {i} of seed {seed}: {df} / {dr}");
            kinds[f as usize] += 1;
            tagged += (f > 0) as usize;
        }
    }
    eprintln!("feature designations over 6 scenarios: {kinds:?}");
    assert!(kinds[1] > 0 && kinds[2] > 0 && tagged < kinds[0]);
}
