//! V2S's grid inputs against independent computations on the embedded liver.

use super::*;
use crate::mesh::locate::TetLocator;
use crate::register::Measurements;

/// The embedded default liver, meshed coarsely (fast tests).
fn liver() -> TetMesh {
    let surface = crate::assets::default_liver().unwrap();
    crate::mesh::tetra::tetrahedralize(&surface, &crate::mesh::tetra::TetraParams::with_edge(14.0))
        .unwrap()
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Distance from `p` to triangle `abc` by cases: the foot of the perpendicular when it falls
/// inside (all three edge tests agree with the normal), else the nearest of the three edges.
fn triangle_distance(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let seg = |a: [f64; 3], b: [f64; 3]| {
        let ab = sub(b, a);
        let t = (dot(sub(p, a), ab) / dot(ab, ab)).clamp(0.0, 1.0);
        let q = [a[0] + t * ab[0], a[1] + t * ab[1], a[2] + t * ab[2]];
        dot(sub(p, q), sub(p, q)).sqrt()
    };
    let n = cross(sub(b, a), sub(c, a));
    let nn = dot(n, n).sqrt();
    if nn > 0.0 {
        let n = [n[0] / nn, n[1] / nn, n[2] / nn];
        let h = dot(sub(p, a), n);
        let f = [p[0] - h * n[0], p[1] - h * n[1], p[2] - h * n[2]];
        let inside = [(a, b), (b, c), (c, a)]
            .iter()
            .all(|&(u, v)| dot(cross(sub(v, u), sub(f, u)), n) >= 0.0);
        if inside {
            return h.abs();
        }
    }
    seg(a, b).min(seg(b, c)).min(seg(c, a))
}

/// The exact signed distance to the mesh's boundary: the nearest boundary triangle by brute
/// force, negative where a tet contains the point.
fn exact_signed_distance(mesh: &TetMesh, locator: &TetLocator, p: [f64; 3]) -> f64 {
    let b = mesh.boundary().unwrap();
    let x = mesh.nodes();
    let d = b
        .triangles
        .iter()
        .map(|t| triangle_distance(p, x[t[0] as usize], x[t[1] as usize], x[t[2] as usize]))
        .fold(f64::INFINITY, f64::min);
    if locator.locate(p).is_some() { -d } else { d }
}

fn lcg(seed: &mut u64) -> f64 {
    *seed = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    (*seed >> 11) as f64 / (1u64 << 53) as f64
}

#[test]
fn the_signed_distance_channel_is_the_exact_signed_distance_and_interpolates_within_its_bound() {
    let mesh = liver();
    let locator = TetLocator::new(&mesh);
    let cfg = V2sConfig::new().with_grid(16).with_depth(2);
    let frame = V2sFrame::new(&mesh, (&[], &[]), &cfg).unwrap();
    let g = frame.grid;
    let surface = mesh.boundary_surface().unwrap();
    let sd = SignedDistance::new(&surface).unwrap();
    let grid_sd = g.signed_distance(&sd);
    // At the grid points: the exact value (sign by point location in the tets).
    let mut inside = 0;
    let mut worst = 0.0f64;
    for i in (0..g.len()).step_by(7) {
        let want = exact_signed_distance(&mesh, &locator, g.point(i));
        if want < 0.0 {
            inside += 1;
        }
        worst = worst.max((grid_sd[i] - want).abs());
        // The encoded channel is the same distance in units, clamped.
        let enc = frame.preop[i] as f64;
        let want_enc = (want / DISTANCE_UNIT_MM).clamp(-DISTANCE_CLAMP, DISTANCE_CLAMP);
        assert!(
            (enc - want_enc).abs() < 1e-5,
            "point {i}: {enc} vs {want_enc}"
        );
    }
    assert!(worst < 1e-9, "largest difference at grid points {worst} mm");
    assert!(
        inside > 20,
        "only {inside} sampled grid points inside the liver"
    );
    // At random points: the trilinear interpolation of a 1-Lipschitz field differs from it by at
    // most the distance to the farthest cell corner, √3·h.
    let mut seed = 11;
    let bound = 3f64.sqrt() * g.spacing;
    let mut worst_rel = 0.0f64;
    for _ in 0..300 {
        let p = [0, 1, 2].map(|a| g.origin[a] + g.spacing * (g.n - 1) as f64 * lcg(&mut seed));
        let want = exact_signed_distance(&mesh, &locator, p);
        let got = g.interpolate(&grid_sd, p);
        worst_rel = worst_rel.max((got - want).abs() / bound);
    }
    assert!(worst_rel <= 1.0, "interpolation error {worst_rel} × √3·h");
    // The interpolation to the nodes: every node lies inside the grid; the signed distance there
    // is ≤ 0 up to the interpolation bound.
    let n = mesh.num_nodes();
    assert_eq!(frame.interpolation.matrix().rows, n);
    let field: Vec<f32> = grid_sd.iter().map(|&d| d as f32).collect();
    let at_nodes = frame.interpolation.matrix().matmul_dense(&field, 1);
    assert!(at_nodes.iter().all(|&d| (d as f64) < bound));
}

#[test]
fn measured_point_channels_and_the_node_interpolation_through_burn_agree_with_direct_sums() {
    let mesh = liver();
    let cfg = V2sConfig::new().with_grid(16).with_depth(2);
    // One vessel segment through the liver's centre.
    let x = mesh.nodes();
    let c = [0, 1, 2].map(|a| x.iter().map(|p| p[a]).sum::<f64>() / x.len() as f64);
    let vp = vec![[c[0] - 20.0, c[1], c[2]], [c[0] + 20.0, c[1], c[2]]];
    let vs = vec![[0u32, 1u32]];
    let frame = V2sFrame::new(&mesh, (&vp, &vs), &cfg).unwrap();
    let g = frame.grid;
    // The vessel channel at a grid point: distance to the segment, encoded.
    for i in (0..g.len()).step_by(97) {
        let p = g.point(i);
        let t = ((p[0] - vp[0][0]) / 40.0).clamp(0.0, 1.0);
        let q = [vp[0][0] + 40.0 * t, c[1], c[2]];
        let d = dot(sub(p, q), sub(p, q)).sqrt();
        assert!((frame.preop[g.len() + i] - encode_distance(d)).abs() < 1e-5);
    }
    // Measurements: two surface points, one vessel point, no contour.
    let pts = vec![x[0], x[5], c];
    let kinds = vec![
        MeasuredKind::Surface,
        MeasuredKind::Surface,
        MeasuredKind::Vessel,
    ];
    let input = frame.input(&pts, &kinds);
    let len = g.len();
    assert_eq!(input.len(), INPUTS * len);
    for i in (0..len).step_by(53) {
        let p = g.point(i);
        let d = |q: [f64; 3]| dot(sub(p, q), sub(p, q)).sqrt();
        assert!((input[2 * len + i] - encode_distance(d(x[0]).min(d(x[5])))).abs() < 1e-5);
        assert_eq!(
            input[3 * len + i],
            DISTANCE_CLAMP as f32,
            "no contour points"
        );
        assert!((input[4 * len + i] - encode_distance(d(c))).abs() < 1e-5);
    }
    // A rigid transform: the points are taken to the image frame first.
    let t = Rigid {
        rotation: [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        translation: [5.0, -3.0, 2.0],
    };
    let meas = Checked::new(Measurements {
        points: pts.iter().map(|&p| t.apply(p)).collect(),
        kind: kinds.clone(),
        ..Default::default()
    })
    .unwrap();
    let moved = frame.input_for(&meas, &t);
    let worst = moved
        .iter()
        .zip(&input)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-5, "{worst}");
    // A linear displacement field on the grid reaches the nodes exactly through the burn path.
    let device = Device::flex();
    let field = |p: [f64; 3], k: usize| 0.01 * (k as f64 + 1.0) * p[k] - 0.002 * p[(k + 1) % 3];
    let mut out = vec![0.0f32; 3 * len];
    for k in 0..3 {
        for i in 0..len {
            out[k * len + i] = field(g.point(i), k) as f32;
        }
    }
    let n = g.n;
    let y = Tensor::<5>::from_data(TensorData::new(out, [1, 3, n, n, n]), &device);
    let at = frame.at_nodes(y).unwrap();
    assert_eq!(at.dims(), [mesh.num_nodes(), 3]);
    let at = at.into_data().try_to_vec::<f32>().unwrap();
    for (i, p) in x.iter().enumerate() {
        for k in 0..3 {
            let want = field(*p, k);
            assert!(
                (at[3 * i + k] as f64 - want).abs() < 1e-4 * (1.0 + want.abs()),
                "node {i} component {k}"
            );
        }
    }
    // A segment naming a missing point is an error.
    let bad = V2sFrame::new(&mesh, (&vp, &[[0, 2]]), &cfg);
    assert!(matches!(bad, Err(V2sError::Invalid(_))));
}

#[test]
fn an_untrained_case_answers_the_rigid_registration() {
    let mesh = liver();
    let cfg = V2sConfig::new().with_grid(16).with_width(4).with_depth(2);
    let model = Arc::new(V2sModel::untrained(cfg, 2).unwrap());
    let case = V2sCase::new(model, &mesh, (&[], &[])).unwrap();
    let meas = Checked::new(Measurements {
        points: mesh.nodes()[..20].to_vec(),
        kind: vec![MeasuredKind::Surface; 20],
        ..Default::default()
    })
    .unwrap();
    let (u, _) = case.displacement(&meas, &Rigid::identity()).unwrap();
    assert_eq!(u.len(), 3 * mesh.num_nodes());
    assert!(u.iter().all(|x| *x == 0.0));
}
