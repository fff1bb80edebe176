//! The tetrahedral mesher (isosurface stuffing, `librplus::mesh::tetra`) on a generated icosphere
//! and on the real livers in `assets/livers`: every tet positive, smallest dihedral angle ≥ 8°,
//! volume against the surface's enclosed volume (and its fall under refinement), boundary nodes
//! within H/4 of the input surface, a closed genus-0 boundary in one piece; the signed distance
//! against brute force; determinism and orientation independence; the errors for unusable input.
//!
//! Ignored (run in release: `cargo test --release --test mesher -- --ignored --nocapture`):
//! `mesher_large_liver` meshes both livers with more than 60,000 nodes and prints the numbers;
//! `mesher_lattice_size_sweep` meshes them (and a sphere) at 110 lattice sizes.

use librplus::mesh::io::{self, Unit};
use librplus::mesh::spatial::{SignedDistance, TriangleBvh};
use librplus::mesh::tetra::{self, TetraError, TetraParams, TetraReport};
use librplus::mesh::{TetMesh, TriSurface, quality};
use librplus::util::SplitMix64;
use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("assets/livers")
        .join(name)
}

/// The largest component of `sofa_liver.vtk` (mm; its triangles face inward).
fn vtk_liver() -> TriSurface {
    let file = io::read(data("sofa_liver.vtk"), Unit::Mm).unwrap();
    TriSurface::from_file(&file).unwrap().largest_component()
}

/// `sofa_liver-smooth.obj`, read as centimetres so it is in mm (enclosed volume 39,270 mm³).
fn smooth_liver() -> TriSurface {
    let file = io::read(data("sofa_liver-smooth.obj"), Unit::Cm).unwrap();
    TriSurface::from_file(&file).unwrap()
}

/// An icosphere of radius `r` centred at `c`: the icosahedron subdivided `levels` times, projected.
fn icosphere(r: f64, c: [f64; 3], levels: usize) -> TriSurface {
    let g = (1.0 + 5f64.sqrt()) / 2.0;
    let mut nodes: Vec<[f64; 3]> = vec![
        [-1.0, g, 0.0],
        [1.0, g, 0.0],
        [-1.0, -g, 0.0],
        [1.0, -g, 0.0],
        [0.0, -1.0, g],
        [0.0, 1.0, g],
        [0.0, -1.0, -g],
        [0.0, 1.0, -g],
        [g, 0.0, -1.0],
        [g, 0.0, 1.0],
        [-g, 0.0, -1.0],
        [-g, 0.0, 1.0],
    ];
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    let unit = |p: [f64; 3]| {
        let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        p.map(|x| x / l)
    };
    for p in &mut nodes {
        *p = unit(*p);
    }
    for _ in 0..levels {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut next = Vec::with_capacity(tris.len() * 4);
        for t in &tris {
            let mut m = [0u32; 3];
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                m[k] = *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                    let (p, q) = (nodes[a as usize], nodes[b as usize]);
                    nodes.push(unit([p[0] + q[0], p[1] + q[1], p[2] + q[2]]));
                    nodes.len() as u32 - 1
                });
            }
            next.push([t[0], m[0], m[2]]);
            next.push([t[1], m[1], m[0]]);
            next.push([t[2], m[2], m[1]]);
            next.push(m);
        }
        tris = next;
    }
    let nodes = nodes
        .into_iter()
        .map(|p| [c[0] + r * p[0], c[1] + r * p[1], c[2] + r * p[2]])
        .collect();
    TriSurface::new(nodes, tris).unwrap()
}

/// What the checks measured on one mesh.
#[derive(Debug)]
struct Checked {
    nodes: usize,
    min_dihedral: f64,
    /// (mesh volume − reference) / reference.
    volume_error: f64,
    /// Largest distance from a boundary node to the input surface (mm).
    boundary_node_distance: f64,
}

/// Meshes `surface` at `h` and checks: valid (every tet positive, none degenerate), min dihedral
/// ≥ 8°, boundary nodes within H/4 of the surface, a closed, consistently oriented genus-0 boundary,
/// one piece. The volume error is relative to `reference_volume`.
fn mesh_and_check(
    name: &str,
    surface: &TriSurface,
    h: f64,
    reference_volume: f64,
) -> (TetMesh, TetraReport, Checked) {
    let start = Instant::now();
    let (mesh, report) = tetra::tetrahedralize_with_report(surface, &TetraParams::with_edge(h))
        .unwrap_or_else(|e| panic!("{name} at H = {h}: {e}"));
    let seconds = start.elapsed().as_secs_f64();
    mesh.validate().unwrap();
    assert!(mesh.tet_volumes().iter().all(|&v| v > 0.0));
    let q = quality::summary(&mesh);
    let volume_error = (mesh.volume() - reference_volume) / reference_volume;
    let bvh = TriangleBvh::new(surface);
    let b = mesh.boundary().unwrap();
    let boundary_node_distance = b
        .nodes
        .iter()
        .map(|&v| bvh.distance(mesh.nodes()[v as usize]))
        .fold(0.0, f64::max);
    // Informative: how far the boundary triangles' centroids are (the chordal error).
    let centroid_distance = b
        .triangles
        .iter()
        .map(|t| {
            let p = t.map(|v| mesh.nodes()[v as usize]);
            bvh.distance([0, 1, 2].map(|k| (p[0][k] + p[1][k] + p[2][k]) / 3.0))
        })
        .fold(0.0, f64::max);
    let st = mesh.boundary_surface().unwrap().stats();
    println!(
        "{name} H={h} mm: {} nodes, {} tets, dihedral {:.2}°..{:.2}°, volume {:.1} mm³ (error {:+.3}%), \
         max boundary node distance {:.1e}·H, max boundary centroid distance {:.3}·H, {:.2} s \
         (stages {:?}), split pinch vertices {}",
        mesh.num_nodes(),
        mesh.num_tets(),
        q.min_dihedral_deg,
        q.max_dihedral_deg,
        mesh.volume(),
        100.0 * volume_error,
        boundary_node_distance / h,
        centroid_distance / h,
        seconds,
        report.seconds,
        report.split_vertices,
    );
    assert!(
        q.min_dihedral_deg >= 8.0,
        "{name} H={h}: min dihedral {}",
        q.min_dihedral_deg
    );
    assert!(
        boundary_node_distance <= h / 4.0,
        "{name} H={h}: a boundary node is {boundary_node_distance} mm off the surface"
    );
    assert!(
        st.closed && st.consistently_oriented,
        "{name} H={h}: {st:?}"
    );
    assert_eq!(
        (st.genus, st.euler_characteristic),
        (0, 2),
        "{name} H={h}: {st:?}"
    );
    assert_eq!(st.components, 1, "{name} H={h}: {st:?}");
    assert!(st.signed_volume_mm3 > 0.0, "boundary faces outward");
    assert_eq!(mesh.num_components(), 1);
    assert_eq!((report.pinched_edges, report.pinched_vertices), (0, 0));
    assert_eq!(
        (report.nodes, report.tets),
        (mesh.num_nodes(), mesh.num_tets())
    );
    let checked = Checked {
        nodes: mesh.num_nodes(),
        min_dihedral: q.min_dihedral_deg,
        volume_error,
        boundary_node_distance,
    };
    (mesh, report, checked)
}

#[test]
fn sphere_meshes_are_good_and_converge() {
    let r = 1.0;
    let sphere = icosphere(r, [0.1, -0.2, 0.05], 4);
    let exact = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
    let faceted = sphere.signed_volume();
    assert!((faceted - exact).abs() < 0.005 * exact, "{faceted}");
    let (_, _, coarse) = mesh_and_check("icosphere", &sphere, 0.2, exact);
    let (_, _, fine) = mesh_and_check("icosphere", &sphere, 0.1, exact);
    // Chords of the sphere: the volume is a little low and the error falls about 4× per halving.
    assert!(
        coarse.volume_error < 0.0 && coarse.volume_error > -0.03,
        "{coarse:?}"
    );
    assert!(
        fine.volume_error < 0.0 && fine.volume_error > -0.01,
        "{fine:?}"
    );
    assert!(fine.volume_error.abs() < 0.5 * coarse.volume_error.abs());
    assert!(fine.nodes > 5 * coarse.nodes);
    // Cut points are solved to 1e-7·H on the true distance.
    assert!(fine.boundary_node_distance < 1e-6 * 0.1);
}

#[test]
fn sofa_liver_vtk_coarse_and_fine() {
    let surface = vtk_liver();
    let enclosed = surface.signed_volume();
    assert!(enclosed < 0.0, "the file's triangles face inward");
    let (_, coarse_report, coarse) = mesh_and_check("sofa_liver.vtk", &surface, 12.0, -enclosed);
    let (_, _, fine) = mesh_and_check("sofa_liver.vtk", &surface, 6.0, -enclosed);
    assert!((2_000..4_000).contains(&coarse.nodes), "{coarse:?}");
    assert!(fine.nodes > 15_000, "{fine:?}");
    assert!(coarse.volume_error.abs() < 0.02, "{coarse:?}");
    assert!(fine.volume_error.abs() < 0.005, "{fine:?}");
    assert!(fine.volume_error.abs() < coarse.volume_error.abs());
    assert!(fine.min_dihedral >= 8.0 && coarse.min_dihedral >= 8.0);
    // At 12 mm two parts of the liver touch at one vertex; it is unzipped.
    assert!(coarse_report.split_vertices <= 4, "{coarse_report:?}");
    // The whole file (with its three tiny degenerate components, closed) meshes the same.
    let file = io::read(data("sofa_liver.vtk"), Unit::Mm).unwrap();
    let raw = TriSurface::from_file(&file).unwrap();
    assert_eq!(raw.stats().components, 4);
    let mesh = tetra::tetrahedralize(&raw, &TetraParams::with_edge(12.0)).unwrap();
    assert_eq!(mesh.num_nodes(), coarse.nodes);
}

#[test]
fn smooth_liver_obj_coarse_and_fine() {
    let surface = smooth_liver();
    let enclosed = surface.signed_volume();
    assert!((enclosed - 39_270.0).abs() < 10.0, "{enclosed}");
    let (_, _, coarse) = mesh_and_check("sofa_liver-smooth.obj", &surface, 3.0, enclosed);
    let (_, _, fine) = mesh_and_check("sofa_liver-smooth.obj", &surface, 1.5, enclosed);
    assert!(
        coarse.nodes > 2_000 && fine.nodes > 20_000,
        "{coarse:?} {fine:?}"
    );
    assert!(fine.volume_error.abs() < 0.005, "{fine:?}");
    assert!(fine.volume_error.abs() < 0.5 * coarse.volume_error.abs());
}

#[test]
fn signed_distance_matches_brute_force_on_the_liver() {
    // The smooth liver has small folds where a pseudo-normal sign fails; the winding number does not.
    let surface = smooth_liver();
    let sd = SignedDistance::new(&surface).unwrap();
    let (lo, hi) = surface.bounding_box();
    let mut rng = SplitMix64::new(11);
    let nodes = surface.nodes();
    for _ in 0..300 {
        let p = [0, 1, 2].map(|k| lo[k] - 5.0 + (hi[k] - lo[k] + 10.0) * rng.next_f64());
        let f = sd.eval(p);
        // Brute-force distance: the closest of many points sampled on every triangle bounds it
        // from above; the BVH answer must not exceed it and must come close.
        let mut upper = f64::INFINITY;
        for t in surface.triangles() {
            let [a, b, c] = t.map(|v| nodes[v as usize]);
            for (u, v) in [(1.0 / 3.0, 1.0 / 3.0), (1.0, 0.0), (0.0, 1.0), (0.0, 0.0)] {
                let q = [0, 1, 2].map(|k| a[k] + u * (b[k] - a[k]) + v * (c[k] - a[k]));
                let d = ((0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>()).sqrt();
                upper = upper.min(d);
            }
        }
        assert!(f.abs() <= upper + 1e-9, "{p:?}: {f} vs {upper}");
        assert!(f.abs() >= upper - 2.0, "{p:?}: {f} vs {upper}");
        let w = sd.winding_number_exact(p);
        let fast = sd.winding_number(p);
        assert!((w - fast).abs() < 0.05, "{p:?}: {w} vs {fast}");
        assert_eq!(f < 0.0, w > 0.5, "{p:?}: f = {f}, winding number {w}");
    }
}

#[test]
fn inward_surface_and_reruns_give_the_same_mesh() {
    let sphere = icosphere(10.0, [1.0, 2.0, 3.0], 3);
    let params = TetraParams::with_edge(2.0);
    let a = tetra::tetrahedralize(&sphere, &params).unwrap();
    let b = tetra::tetrahedralize(&sphere, &params).unwrap();
    assert!(a == b, "deterministic");
    let mut inward = sphere.clone();
    inward.flip();
    assert!(inward.signed_volume() < 0.0);
    let c = tetra::tetrahedralize(&inward, &params).unwrap();
    // Every triangle computation uses the corners in vertex-index order, so the mesh is identical.
    assert!(a == c, "orientation independent");
}

#[test]
fn unusable_input_is_refused_with_a_reason() {
    let sphere = icosphere(1.0, [0.0; 3], 2);
    let p = TetraParams::with_edge(0.2);
    // Open: one triangle removed.
    let mut tris = sphere.triangles().to_vec();
    tris.pop();
    let open = TriSurface::new(sphere.nodes().to_vec(), tris.clone()).unwrap();
    let e = tetra::tetrahedralize(&open, &p).unwrap_err();
    assert_eq!(
        e,
        TetraError::NotClosed {
            boundary_edges: 3,
            nonmanifold_edges: 0
        }
    );
    assert!(e.to_string().contains("not closed"), "{e}");
    // One triangle flipped.
    let mut tris = sphere.triangles().to_vec();
    tris[0].swap(1, 2);
    let bad = TriSurface::new(sphere.nodes().to_vec(), tris).unwrap();
    assert!(matches!(
        tetra::tetrahedralize(&bad, &p),
        Err(TetraError::NotOriented {
            misoriented_edges: 3
        })
    ));
    // Empty.
    let empty = TriSurface::new(vec![], vec![]).unwrap();
    assert!(matches!(
        tetra::tetrahedralize(&empty, &p),
        Err(TetraError::EmptySurface { .. })
    ));
    // Bad edge lengths and thresholds.
    for h in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        assert!(matches!(
            tetra::tetrahedralize(&sphere, &TetraParams::with_edge(h)),
            Err(TetraError::InvalidEdgeLength { .. })
        ));
    }
    let e = tetra::tetrahedralize(&sphere, &TetraParams::with_edge(1.5)).unwrap_err();
    assert!(matches!(e, TetraError::EdgeTooLarge { .. }), "{e}");
    let mut q = TetraParams::with_edge(0.2);
    q.alpha_short = 0.5;
    assert!(matches!(
        tetra::tetrahedralize(&sphere, &q),
        Err(TetraError::InvalidAlpha { .. })
    ));
    // Memory cap.
    let mut q = TetraParams::with_edge(0.001);
    q.max_lattice_points = 50_000_000;
    let e = tetra::tetrahedralize(&sphere, &q).unwrap_err();
    assert!(matches!(e, TetraError::TooManyLatticePoints { .. }), "{e}");
    assert!(e.to_string().contains("increase the edge length"), "{e}");
}

/// ≥ 60,000 nodes on `sofa_liver.vtk`; prints counts, angles, volume error, boundary distance and
/// time. Run in release: `cargo test --release --test mesher -- --ignored --nocapture`.
#[test]
#[ignore]
fn mesher_large_liver() {
    let surface = vtk_liver();
    let enclosed = -surface.signed_volume();
    for h in [3.8, 3.0] {
        let (_, report, checked) = mesh_and_check("sofa_liver.vtk", &surface, h, enclosed);
        println!("{report:?}");
        assert!(checked.nodes >= 60_000);
        assert!(checked.volume_error.abs() < 0.02);
    }
    let surface = smooth_liver();
    let (_, report, checked) = mesh_and_check("sofa_liver-smooth.obj", &surface, 1.1, 39_270.0);
    println!("{report:?}");
    assert!(checked.nodes >= 60_000);
}

/// Robustness over lattice sizes (ignored: about 40 s in release): 40 sizes on `sofa_liver.vtk`
/// (3.3–20 mm), 40 on the smooth liver (1–6 mm), 30 on a 20 mm sphere. Every mesh valid, dihedral
/// angles within [8°, 165°], volume within 2 % from 2,000 nodes up, no pinched edge left, and the
/// boundary closed and in one piece, a 2-manifold sphere (Euler characteristic 2) unless the report
/// counts pinched vertices (printed).
#[test]
#[ignore]
fn mesher_lattice_size_sweep() {
    let sphere = icosphere(20.0, [0.37, -0.21, 0.13], 4);
    for (name, surface, h0, h1, steps) in [
        ("sofa_liver.vtk", vtk_liver(), 3.3f64, 20.0, 40),
        ("sofa_liver-smooth.obj", smooth_liver(), 1.0, 6.0, 40),
        ("sphere", sphere, 0.9, 8.0, 30),
    ] {
        let enclosed = surface.signed_volume().abs();
        let (mut lo, mut hi, mut worst_volume) = (180.0f64, 0.0f64, 0.0f64);
        let mut pinched = Vec::new();
        for i in 0..steps {
            let h = h0 * (h1 / h0).powf(i as f64 / (steps - 1) as f64);
            let (mesh, r) = tetra::tetrahedralize_with_report(&surface, &TetraParams::with_edge(h))
                .unwrap_or_else(|e| panic!("{name} H={h}: {e}"));
            mesh.validate().unwrap();
            let q = quality::summary(&mesh);
            lo = lo.min(q.min_dihedral_deg);
            hi = hi.max(q.max_dihedral_deg);
            let volume_error = (mesh.volume() / enclosed - 1.0).abs();
            if mesh.num_nodes() >= 2_000 {
                worst_volume = worst_volume.max(volume_error);
            }
            let st = mesh.boundary_surface().unwrap().stats();
            assert_eq!(r.pinched_edges, 0, "{name} H={h}");
            assert!(
                st.closed
                    && st.components == 1
                    && (st.euler_characteristic == 2 || r.pinched_vertices > 0),
                "{name} H={h}: {st:?}"
            );
            if r.pinched_vertices > 0 {
                pinched.push(format!(
                    "H={h:.2} mm ({} nodes): {}",
                    mesh.num_nodes(),
                    r.pinched_vertices
                ));
            }
        }
        println!(
            "{name}: dihedral {lo:.2}°..{hi:.2}°, worst volume error {:.2}% (≥ 2,000 nodes), \
             pinched vertices left: {pinched:?}",
            100.0 * worst_volume
        );
        assert!(lo >= 8.0 && hi <= 165.0 && worst_volume < 0.02);
    }
}

/// Shape variants of the real liver (as `generate` makes them) mesh into valid meshes. Seed
/// 12858875617028935581 at H = 7.6 once proposed the same pinch-closing tetrahedron for two pinched
/// edges of one gap, which made a face shared by three tetrahedra.
#[test]
fn liver_shape_variants_mesh_cleanly() {
    use librplus::phantom::shape::{ShapeVariantParams, variant};
    let mut base = vtk_liver();
    if base.signed_volume() < 0.0 {
        base.flip();
    }
    for (seed, h) in [
        (12858875617028935581u64, 7.6),
        (1, 9.0),
        (2, 11.0),
        (3, 7.6),
    ] {
        let (v, _) = variant(&base, &ShapeVariantParams::default(), seed).unwrap();
        let (mesh, report) = tetra::tetrahedralize_with_report(&v, &TetraParams::with_edge(h))
            .unwrap_or_else(|e| panic!("seed {seed} at H = {h}: {e}"));
        mesh.validate().unwrap();
        let b = mesh.boundary().unwrap();
        let s = TriSurface::new(mesh.nodes().to_vec(), b.triangles).unwrap();
        let st = s.stats();
        assert!(st.closed, "seed {seed}: boundary not closed");
        let enclosed = v.signed_volume().abs();
        assert!((mesh.volume() - enclosed).abs() < 0.02 * enclosed);
        eprintln!(
            "seed {seed} H {h}: {} nodes, {} pinch fills, {} vertex copies",
            mesh.num_nodes(),
            report.pinch_fill_tets,
            report.split_vertices
        );
    }
}

/// A refitted hierarchy answers closest-point queries on the moved surface exactly as one built
/// on it from scratch.
#[test]
fn refitted_bvh_matches_a_rebuilt_one() {
    let s = vtk_liver();
    let mut bvh = TriangleBvh::new(&s);
    let moved: Vec<[f64; 3]> = s
        .nodes()
        .iter()
        .map(|p| {
            [
                p[0] + 0.1 * p[1] + 5.0 * (p[2] / 40.0).sin(),
                p[1] - 0.05 * p[0],
                p[2] + 8.0 * (p[0] / 30.0).cos(),
            ]
        })
        .collect();
    bvh.refit(&moved);
    let fresh = TriangleBvh::new(&TriSurface::new(moved.clone(), s.triangles().to_vec()).unwrap());
    let (lo, hi) = s.bounding_box();
    let mut rng = SplitMix64::new(9);
    for _ in 0..2000 {
        let q = [0, 1, 2].map(|k| lo[k] - 30.0 + (hi[k] - lo[k] + 60.0) * rng.next_f64());
        let (a, b) = (
            bvh.closest(q, None).unwrap(),
            fresh.closest(q, None).unwrap(),
        );
        assert!(
            (a.distance - b.distance).abs() <= 1e-9 * b.distance.max(1.0),
            "{q:?}"
        );
    }
}
