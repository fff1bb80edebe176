//! Liver-like shape variants of the real SOFA liver mesh into valid, distinct tetrahedral livers.

use librplus::mesh::io::{self, Unit};
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::mesh::{TriSurface, quality};
use librplus::phantom::shape::{ShapeVariantParams, variant};
use std::path::PathBuf;

#[test]
fn variants_of_the_real_liver_mesh_into_distinct_valid_livers() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/sofa_liver.vtk");
    let surface = TriSurface::from_file(&io::read(path, Unit::Mm).unwrap())
        .unwrap()
        .largest_component();
    let base = surface.signed_volume().abs();
    let mut volumes = Vec::new();
    for seed in [1, 2, 3] {
        let (v, _) = variant(&surface, &ShapeVariantParams::default(), seed).unwrap();
        let st = v.stats();
        assert!(st.closed && st.consistently_oriented && st.genus == 0);
        let mesh = tetrahedralize(&v, &TetraParams::with_edge(12.0)).unwrap();
        mesh.validate().unwrap();
        let q = quality::summary(&mesh);
        assert!(
            q.min_dihedral_deg >= 8.0,
            "seed {seed}: {}",
            q.min_dihedral_deg
        );
        let enclosed = v.signed_volume().abs();
        assert!((mesh.volume() - enclosed).abs() < 0.02 * enclosed);
        eprintln!(
            "seed {seed}: {} nodes, volume {:.0} cm³ (base {:.0}), min dihedral {:.1}°",
            mesh.num_nodes(),
            enclosed / 1000.0,
            base / 1000.0,
            q.min_dihedral_deg
        );
        volumes.push(enclosed);
    }
    // Distinct shapes, still liver-sized.
    assert!((volumes[0] - volumes[1]).abs() > 0.01 * base);
    assert!(volumes.iter().all(|v| *v > 0.5 * base && *v < 1.6 * base));
}
