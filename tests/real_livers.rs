//! The real livers in `assets/livers`, read through the same readers a user would use, against the
//! facts in its SOURCES.md; and the sag problem against the committed scikit-fem reference.

use librplus::fem::sag;
use librplus::mesh::io::{self, Unit};
use librplus::mesh::{TetMesh, TriSurface};
use std::path::PathBuf;

fn data(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("assets/livers")
        .join(name)
}

/// Triangles as sorted node triples, sorted: compares triangle sets regardless of winding.
fn as_sets(triangles: &[[u32; 3]]) -> Vec<[u32; 3]> {
    let mut v: Vec<[u32; 3]> = triangles
        .iter()
        .map(|t| {
            let mut s = *t;
            s.sort_unstable();
            s
        })
        .collect();
    v.sort_unstable();
    v
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * b.abs()
}

#[test]
fn sofa_liver_msh_facts() {
    // 181 nodes, 596 tets, all positive; volume 36.56 cm³; boundary 276 triangles on 140 nodes,
    // closed, genus 0.
    let file = io::read(data("sofa_liver.msh"), Unit::Cm).unwrap();
    let mesh = TetMesh::from_file(&file).unwrap();
    assert_eq!((mesh.num_nodes(), mesh.num_tets()), (181, 596));
    mesh.validate().unwrap();
    assert!(mesh.tet_volumes().iter().all(|&v| v > 0.0));
    assert!(close(mesh.volume(), 36_560.0, 1e-3), "{}", mesh.volume());
    let b = mesh.boundary().unwrap();
    assert_eq!((b.triangles.len(), b.nodes.len()), (276, 140));
    let st = mesh.boundary_surface().unwrap().stats();
    assert!(st.closed && st.consistently_oriented);
    assert_eq!(st.genus, 0);
    assert_eq!(mesh.num_components(), 1);
    // The boundary's enclosed volume equals the tet volume (outward orientation).
    assert!(close(st.signed_volume_mm3, mesh.volume(), 1e-12));
}

#[test]
fn sofa_liver2_msh_facts() {
    // 507 nodes, 1,493 tets, 860 boundary triangles, 71 line elements; volume 1.125; ids from 2.
    let file = io::read(data("sofa_liver2.msh"), Unit::Mm).unwrap();
    assert_eq!(file.triangles.len(), 860);
    assert_eq!(file.skipped_cells, 71);
    let mesh = TetMesh::from_file(&file).unwrap();
    assert_eq!((mesh.num_nodes(), mesh.num_tets()), (507, 1493));
    mesh.validate().unwrap();
    assert!(close(mesh.volume(), 1.125, 1e-3), "{}", mesh.volume());
    // The file's own boundary triangles are exactly the mesh boundary (as sets of node triples).
    assert_eq!(
        as_sets(&mesh.boundary().unwrap().triangles),
        as_sets(&file.triangles)
    );
    assert_eq!(mesh.num_components(), 1);
}

#[test]
fn sofa_liver_smooth_obj_facts() {
    // 2,194 vertices, 4,384 triangles, closed, genus 0, outward; enclosed volume 39.27.
    let file = io::read(data("sofa_liver-smooth.obj"), Unit::Mm).unwrap();
    let s = TriSurface::from_file(&file).unwrap();
    let st = s.stats();
    assert_eq!((st.vertices, st.triangles), (2194, 4384));
    assert!(st.closed && st.consistently_oriented);
    assert_eq!(st.genus, 0);
    assert!(st.signed_volume_mm3 > 0.0, "outward");
    assert!(
        close(st.signed_volume_mm3, 39.27, 1e-3),
        "{}",
        st.signed_volume_mm3
    );
    // Same frame as sofa_liver.msh: bounding boxes nearly coincide.
    let tets = TetMesh::from_file(&io::read(data("sofa_liver.msh"), Unit::Mm).unwrap()).unwrap();
    let (a, b) = (s.bounding_box(), tets.bounding_box());
    for k in 0..3 {
        assert!((a.0[k] - b.0[k]).abs() < 0.1 && (a.1[k] - b.1[k]).abs() < 0.1);
    }
}

#[test]
fn sofa_liver_vtk_facts() {
    // 5,008 points, 10,000 triangles; largest component 4,996 vertices / 9,988 triangles, closed,
    // ≈1,477 cm³, bbox ≈194×154×157 mm, faces inward; 3 tiny extra components.
    let file = io::read(data("sofa_liver.vtk"), Unit::Mm).unwrap();
    assert_eq!((file.nodes.len(), file.triangles.len()), (5008, 10000));
    let s = TriSurface::from_file(&file).unwrap();
    assert_eq!(s.components().1, 4);
    let big = s.largest_component();
    let st = big.stats();
    assert_eq!((st.vertices, st.triangles), (4996, 9988));
    assert!(st.closed && st.consistently_oriented);
    assert_eq!(st.genus, 0);
    assert!(st.signed_volume_mm3 < 0.0, "faces inward");
    assert!(
        close(-st.signed_volume_mm3, 1_477_000.0, 2e-3),
        "{}",
        st.signed_volume_mm3
    );
    let (lo, hi) = big.bounding_box();
    let size = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
    for (got, want) in size.iter().zip([194.0, 154.0, 157.0]) {
        assert!((got - want).abs() < 1.0, "{size:?}");
    }
    let mut flipped = big.clone();
    flipped.flip();
    assert!(flipped.signed_volume() > 0.0);
}

/// `fem sag` on sofa_liver.msh (cm) agrees node by node with scikit-fem (tests/reference).
#[test]
fn sag_matches_scikit_fem_reference() {
    let reference: serde_json::Value =
        serde_json::from_str(include_str!("reference/sofa_liver_sag_skfem.json")).unwrap();
    let file = io::read(data("sofa_liver.msh"), Unit::Cm).unwrap();
    let mesh = TetMesh::from_file(&file).unwrap();
    let r = sag::solve(&mesh, &sag::SagParams::default()).unwrap();
    assert_eq!(
        r.fixed_nodes as u64,
        reference["fixed_nodes"].as_u64().unwrap()
    );
    let uref: Vec<[f64; 3]> = reference["displacement_mm"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| {
            let a = v.as_array().unwrap();
            [
                a[0].as_f64().unwrap(),
                a[1].as_f64().unwrap(),
                a[2].as_f64().unwrap(),
            ]
        })
        .collect();
    assert_eq!(uref.len(), mesh.num_nodes());
    let umax = uref
        .iter()
        .map(|u| (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt())
        .fold(0.0, f64::max);
    let mut worst_vs_max = 0.0f64;
    let mut worst_node_rel = 0.0f64;
    for (i, u) in uref.iter().enumerate() {
        let d: f64 = (0..3)
            .map(|k| (r.displacement[3 * i + k] - u[k]).powi(2))
            .sum::<f64>()
            .sqrt();
        let n = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
        worst_vs_max = worst_vs_max.max(d / umax);
        if n > 0.0 {
            worst_node_rel = worst_node_rel.max(d / n);
        } else {
            assert_eq!(d, 0.0, "fixed node {i} must not move");
        }
    }
    eprintln!(
        "sag vs scikit-fem: max |Δu|/|u|max = {worst_vs_max:e}, max per-node rel = {worst_node_rel:e}"
    );
    assert!(worst_vs_max <= 1e-6);
    assert!(worst_node_rel <= 1e-6);
    // Equilibrium: the supports carry exactly the weight (total body force = ρg·V).
    let weight = 0.0104 * mesh.volume();
    assert!((r.applied_load_mn[1] - weight).abs() < 1e-9 * weight);
    for a in 0..3 {
        assert!(
            (r.reaction_mn[a] + r.applied_load_mn[a]).abs() < 1e-9 * weight,
            "axis {a}"
        );
    }
    // The Neo-Hookean counterpart balances the same load (its forces are the reactions).
    let nh =
        sag::solve_neo_hookean(&mesh, &sag::SagParams::default(), &Default::default()).unwrap();
    for a in 0..3 {
        assert!(
            (nh.reaction_mn[a] + nh.applied_load_mn[a]).abs() < 1e-6 * weight,
            "axis {a}"
        );
    }
    assert!(
        nh.max_disp_mm > r.max_disp_mm,
        "large-deformation sag differs from linear"
    );
    let e_ref = reference["strain_energy"].as_f64().unwrap();
    assert!(close(r.strain_energy, e_ref, 1e-6));
    assert!(close(
        r.max_disp_mm,
        reference["max_disp_mm"].as_f64().unwrap(),
        1e-6
    ));
    assert!(close(
        r.mean_disp_mm,
        reference["mean_disp_mm"].as_f64().unwrap(),
        1e-6
    ));
}
