//! Liver-like shape variants of the real SOFA liver mesh into valid, distinct tetrahedral livers.

use librplus::mesh::io::{self, Unit};
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::mesh::{TriSurface, quality};
use librplus::phantom::shape::{ShapeVariantParams, variant};
use std::path::PathBuf;

/// The largest component of `assets/livers/sofa_liver.vtk` (mm).
fn liver_surface() -> TriSurface {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/livers/sofa_liver.vtk");
    TriSurface::from_file(&io::read(path, Unit::Mm).unwrap())
        .unwrap()
        .largest_component()
}

#[test]
fn variants_of_the_real_liver_mesh_into_distinct_valid_livers() {
    let surface = liver_surface();
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

#[test]
fn real_liver_gets_every_label_and_they_round_trip_through_vtu() {
    use librplus::register::anatomy::{AnatomyLabels, LabelParams, Region, label};
    let surface = liver_surface();
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(10.0)).unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let ant = labels.nodes_in(Region::Anterior).len() as f64;
    let post = labels.nodes_in(Region::Posterior).len() as f64;
    let share = ant / (ant + post);
    eprintln!(
        "anterior share {share:.2}, ridge {}, falciform {}, bare area {}, targets {}",
        AnatomyLabels::nodes_where(&labels.inferior_ridge).len(),
        AnatomyLabels::nodes_where(&labels.falciform).len(),
        AnatomyLabels::nodes_where(&labels.bare_area).len(),
        labels.targets.len()
    );
    assert!(share > 0.25 && share < 0.75, "{share}");
    assert!(AnatomyLabels::nodes_where(&labels.inferior_ridge).len() >= 10);
    assert!(AnatomyLabels::nodes_where(&labels.falciform).len() >= 5);
    assert!(AnatomyLabels::nodes_where(&labels.bare_area).len() >= 10);
    assert_eq!(labels.targets.len(), 8);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("preop.vtu");
    let mut file = mesh.to_file();
    file.point_data = labels.to_point_data();
    io::write(&out, &file, Default::default()).unwrap();
    let back = io::read(&out, Unit::Mm).unwrap();
    let region = back.point_array("region").unwrap();
    assert_eq!(
        region.values.iter().filter(|&&r| r == 1.0).count() as f64,
        ant
    );
    assert_eq!(
        back.point_array("target")
            .unwrap()
            .values
            .iter()
            .sum::<f64>(),
        8.0
    );
}

#[test]
fn vessel_tree_stays_inside_and_stiffens_its_tets() {
    use librplus::fem::{LameField, LinearMaterial};
    use librplus::mesh::spatial::SignedDistance;
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    let surface = liver_surface();
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(6.0)).unwrap();
    let params = VesselParams::default();
    let tree = VesselTree::grow(&mesh, &params).unwrap();
    assert_eq!(
        tree,
        VesselTree::grow(&mesh, &params).unwrap(),
        "deterministic"
    );
    // A forest of two trees (portal, hepatic): one parent per point but the two roots, parents
    // before children, radii never grow below a root's first segment.
    assert_eq!(tree.segments.len() + 2, tree.points.len());
    let mut has_parent = vec![false; tree.points.len()];
    for s in &tree.segments {
        assert!(!has_parent[s[1] as usize], "point {} has two parents", s[1]);
        has_parent[s[1] as usize] = true;
    }
    let roots: Vec<usize> = (0..tree.points.len()).filter(|&i| !has_parent[i]).collect();
    assert_eq!(roots.len(), 2);
    assert_eq!(roots[0], 0);
    // Portal root inferior, hepatic root superior.
    assert!(tree.points[roots[0]][2] < tree.points[roots[1]][2]);
    assert!(
        tree.segments.len() >= 14,
        "{} segments",
        tree.segments.len()
    );
    for s in &tree.segments {
        assert!(s[0] < s[1]);
        assert!(
            tree.radii[s[1] as usize] <= tree.radii[s[0] as usize] + 1e-12
                || roots.contains(&(s[0] as usize))
        );
    }
    // Every branch end is inside the liver mesh with its radius and margin to spare.
    let sd = SignedDistance::new(&mesh.boundary_surface().unwrap()).unwrap();
    for (i, (p, r)) in tree.points.iter().zip(&tree.radii).enumerate() {
        if roots.contains(&i) {
            continue;
        }
        assert!(
            -sd.eval(*p) >= r + params.margin_mm - 1e-9,
            "point {p:?} too close to the surface"
        );
    }
    let inside = tree.tets_inside(&mesh);
    let vessel_volume: f64 = (0..mesh.num_tets())
        .filter(|&t| inside[t])
        .map(|t| mesh.tet_volume(t))
        .sum();
    let share = vessel_volume / mesh.volume();
    eprintln!(
        "{} segments, vessel volume share {:.3}",
        tree.segments.len(),
        share
    );
    assert!(share > 0.002 && share < 0.2, "{share}");
    let mat = LinearMaterial::default();
    let LameField::PerTet(field) = tree.lame_field(&mesh, &mat, 5.0) else {
        panic!("per-tet field expected")
    };
    let (_, mu) = mat.lame();
    for (t, (_, m)) in field.iter().enumerate() {
        let expected = if inside[t] { 5.0 * mu } else { mu };
        assert!((m - expected).abs() < 1e-12);
    }
}

/// Ground truth for each pattern: Neo-Hookean, heterogeneous tissue (vessels, tumours, parenchyma
/// variation), unilateral bed; versus the linear homogeneous model under the same loads and
/// supports. The gap must be real (≥ 2 mm mean over nodes) and its breakdown must add up.
#[test]
fn patterns_deform_the_liver_and_the_linear_model_misses_it() {
    use librplus::fem::LinearMaterial;
    use librplus::fem::hyperelastic::NewtonParams;
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::tissue::{Tissue, TissueParams};
    use librplus::phantom::truth::breakdown;
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    use librplus::register::anatomy::{LabelParams, label};
    let surface = liver_surface();
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(12.0)).unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let tree = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
    let tp = TissueParams::default();
    let tissue = Tissue::build(&mesh, &tree, &tp, 7).unwrap();
    let lame = tissue.lame_field();
    let fractions = tissue.volume_fractions(&mesh);
    eprintln!(
        "{} nodes; tissue: vessels {:.1}% (x{:.1}), tumours {:.1}% ({} placed)",
        mesh.num_nodes(),
        100.0 * fractions[1],
        tissue.vessel_factor,
        100.0 * fractions[2],
        tissue.tumours.len()
    );
    for pattern in [Pattern::L, Pattern::R, Pattern::W, Pattern::V, Pattern::X] {
        let case = load_case(&mesh, &labels, pattern, &PatternParams::default(), 7).unwrap();
        let b = breakdown(
            &mesh,
            &lame,
            &tp.parenchyma,
            &case,
            &NewtonParams::default(),
        )
        .unwrap_or_else(|e| panic!("{pattern:?}: {e} ({})", case.description));
        eprintln!(
            "{pattern:?}: mean {:.1} mm, max {:.1} mm, gap {:.2} mm; steps {:?}; by load {:?} — {}",
            b.truth_mean_mm,
            b.truth_max_mm,
            b.gap_mm,
            b.steps
                .iter()
                .map(|c| format!("{} {:.2}", c.effect, c.mean_mm))
                .collect::<Vec<_>>(),
            b.by_load
                .iter()
                .map(|c| format!("{} {:.2}", c.effect, c.mean_mm))
                .collect::<Vec<_>>(),
            case.description
        );
        // Typical displacements of a few to tens of mm.
        assert!(
            (5.0..40.0).contains(&b.truth_mean_mm),
            "{pattern:?}: mean displacement {}",
            b.truth_mean_mm
        );
        assert!(
            b.truth_max_mm < 120.0,
            "{pattern:?}: max {}",
            b.truth_max_mm
        );
        // The gap the linear homogeneous model leaves, and the triangle inequality on the ladder.
        assert!(b.gap_mm >= 2.0, "{pattern:?}: gap {}", b.gap_mm);
        let ladder: f64 = b.steps.iter().map(|c| c.mean_mm).sum();
        assert!(
            b.gap_mm <= ladder + 1e-9,
            "{pattern:?}: {} > {ladder}",
            b.gap_mm
        );
    }
    let _ = LinearMaterial::default();
}

/// Timing of one ground-truth deformation on a ~9,000-node liver (run in release:
/// `cargo test --release --test phantom -- --ignored --nocapture`); figures go to BENCHMARKS.md.
#[test]
#[ignore]
fn ground_truth_timing_on_a_9k_node_liver() {
    use librplus::fem::LinearMaterial;
    use librplus::fem::hyperelastic::NewtonParams;
    use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    use librplus::register::anatomy::{LabelParams, label};
    let surface = liver_surface();
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(7.6)).unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let tree = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
    let tissue =
        librplus::phantom::tissue::Tissue::build(&mesh, &tree, &Default::default(), 1).unwrap();
    let lame = tissue.lame_field();
    let _ = LinearMaterial::default();
    for pattern in [Pattern::L, Pattern::R, Pattern::W, Pattern::V] {
        for seed in [1, 2] {
            let t0 = std::time::Instant::now();
            let case = load_case(&mesh, &labels, pattern, &PatternParams::default(), seed).unwrap();
            let r = librplus::phantom::truth::solve_truth(
                &mesh,
                &lame,
                &case,
                &NewtonParams::default(),
            );
            let (u, info) = match r {
                Ok(t) => (t.displacement, t.info),
                Err(e) => {
                    eprintln!(
                        "{pattern:?} seed {seed}: FAILED after {:.2} s: {e}",
                        t0.elapsed().as_secs_f64()
                    );
                    continue;
                }
            };
            let mean = u
                .chunks_exact(3)
                .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
                .sum::<f64>()
                / mesh.num_nodes() as f64;
            eprintln!(
                "{} nodes, {pattern:?} seed {seed}: {:.2} s total ({} steps, {} iterations), mean displacement {mean:.1} mm",
                mesh.num_nodes(),
                t0.elapsed().as_secs_f64(),
                info.load_steps,
                info.iterations
            );
        }
    }
}

/// The tissue field: tumours inside with their margin and stiffer by their factor, vessels by theirs,
/// the parenchyma's ln E with the requested spread around ln E₀, deterministic for a seed; and the
/// tilted gravity keeps its magnitude and points where the tilt says.
#[test]
fn tissue_field_and_tilted_gravity() {
    use librplus::mesh::spatial::SignedDistance;
    use librplus::phantom::patterns::tilted_gravity;
    use librplus::phantom::tissue::{Tissue, TissueKind, TissueParams};
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    let surface = liver_surface();
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(8.0)).unwrap();
    let tree = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
    let tp = TissueParams::default();
    let sd = SignedDistance::new(&mesh.boundary_surface().unwrap()).unwrap();
    let mut log_dev = Vec::new();
    for seed in [1, 2, 3] {
        let t = Tissue::build(&mesh, &tree, &tp, seed).unwrap();
        assert_eq!(t, Tissue::build(&mesh, &tree, &tp, seed).unwrap());
        assert!((tp.tumours[0]..=tp.tumours[1]).contains(&t.tumours.len()));
        assert!((tp.vessel_factor[0]..=tp.vessel_factor[1]).contains(&t.vessel_factor));
        for tm in &t.tumours {
            assert!(-sd.eval(tm.center) >= tm.radius + tp.margin_mm - 1e-9);
            assert!((tp.tumour_factor[0]..=tp.tumour_factor[1]).contains(&tm.factor));
        }
        let f = t.volume_fractions(&mesh);
        assert!((f.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        assert!(f[1] > 0.001 && f[2] > 0.0005, "{f:?}");
        // Tumour tets are stiffer than the parenchyma around them by about their factor.
        let e0 = tp.parenchyma.youngs_modulus_kpa;
        for (k, e) in t.kind.iter().zip(&t.youngs_kpa) {
            if *k == TissueKind::Parenchyma {
                log_dev.push((e / e0).ln());
            }
        }
        let hard: f64 = t
            .kind
            .iter()
            .zip(&t.youngs_kpa)
            .filter(|(k, _)| **k == TissueKind::Tumour)
            .map(|(_, e)| (e / e0).ln())
            .sum::<f64>()
            / t.kind.iter().filter(|k| **k == TissueKind::Tumour).count() as f64;
        let lo = tp.tumour_factor[0].ln() - 3.0 * tp.parenchyma_log_std;
        assert!(hard > lo, "mean ln(E/E0) in tumours {hard}");
    }
    // Over three seeds, ln(E/E₀) in the parenchyma has mean ≈ 0 and std ≈ σ (a smooth field over
    // a few correlation lengths: loose bounds).
    let n = log_dev.len() as f64;
    let mean = log_dev.iter().sum::<f64>() / n;
    let std = (log_dev.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    eprintln!(
        "parenchyma ln(E/E0): mean {mean:.3}, std {std:.3} (σ = {})",
        tp.parenchyma_log_std
    );
    assert!(mean.abs() < 0.15, "{mean}");
    assert!(
        (0.5 * tp.parenchyma_log_std..1.5 * tp.parenchyma_log_std).contains(&std),
        "{std}"
    );
    // Tilted gravity: magnitude kept; level and supine it is +y; head-up adds −z; lateral adds x.
    let g = 0.0104;
    assert_eq!(tilted_gravity(g, 0.0, 0.0), [0.0, g, 0.0]);
    let t = tilted_gravity(g, 30.0, 10.0);
    assert!(((t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt() - g).abs() < 1e-15);
    assert!((t[2] + g * 0.5).abs() < 1e-15 && t[0] > 0.0);
    assert!(tilted_gravity(g, 0.0, -10.0)[0] < 0.0);
}

/// A Gaussian pack puts exactly its force along its direction on the boundary within 2σ of its
/// centre; the augmentation pattern X draws one to three packs or a broad pressure on a cap,
/// differs by seed, repeats for a seed, and loads only boundary nodes.
#[test]
fn random_packs_put_their_force_on_the_surface() {
    use librplus::phantom::patterns::{Pattern, PatternParams, gaussian_patch, load_case};
    use librplus::register::anatomy::{LabelParams, label};
    let surface = liver_surface();
    let mesh = tetrahedralize(&surface, &TetraParams::with_edge(12.0)).unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let boundary = mesh.boundary().unwrap();
    let nodes = mesh.nodes();
    let n = mesh.num_nodes();
    let c = nodes[boundary.nodes[boundary.nodes.len() / 3] as usize];
    let l = (0.3f64 * 0.3 + 1.0 + 0.2 * 0.2).sqrt();
    let dir = [0.3 / l, -1.0 / l, 0.2 / l];
    let mut load = vec![0.0; 3 * n];
    let (tris, peak) =
        gaussian_patch(&mut load, nodes, &boundary.triangles, c, 20.0, dir, 5000.0).unwrap();
    assert!(tris > 3 && peak > 0.0, "{tris} triangles, peak {peak}");
    let net = [0, 1, 2].map(|a| load.chunks_exact(3).map(|f| f[a]).sum::<f64>());
    for a in 0..3 {
        assert!((net[a] - 5000.0 * dir[a]).abs() < 1e-6, "net {net:?}");
    }
    for (i, f) in load.chunks_exact(3).enumerate() {
        if f.iter().any(|&x| x != 0.0) {
            let p = nodes[i];
            let d = ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt();
            assert!(
                d <= 40.0 + 1e-9,
                "node {i} loaded {d:.1} mm from the centre"
            );
        }
    }
    // Far from any surface there is nothing to load.
    let mut none = vec![0.0; 3 * n];
    assert!(
        gaussian_patch(
            &mut none,
            nodes,
            &boundary.triangles,
            [1e4; 3],
            20.0,
            dir,
            1.0
        )
        .is_err()
    );
    let on_boundary: std::collections::HashSet<u32> = boundary.nodes.iter().copied().collect();
    let mut packs = std::collections::BTreeSet::new();
    let mut descriptions = std::collections::HashSet::new();
    for seed in 0..12 {
        let case = load_case(&mesh, &labels, Pattern::X, &PatternParams::default(), seed).unwrap();
        let again = load_case(&mesh, &labels, Pattern::X, &PatternParams::default(), seed).unwrap();
        assert_eq!(case.load, again.load, "seed {seed} repeats");
        assert_eq!(case.dirichlet.count(), 0, "X prescribes no displacement");
        for (i, f) in case.surface.chunks_exact(3).enumerate() {
            if f.iter().any(|&x| x != 0.0) {
                assert!(
                    on_boundary.contains(&(i as u32)),
                    "interior node {i} loaded"
                );
            }
        }
        let total: f64 = case.surface.iter().map(|x| x * x).sum::<f64>().sqrt();
        assert!(total > 0.0 && total.is_finite());
        // A pack count, or 0 for a broad pressure on a cap.
        let k = case.description.matches(" N at ").count();
        assert_eq!(
            k == 0,
            case.description.contains("kPa on"),
            "{}",
            case.description
        );
        packs.insert(k);
        descriptions.insert(case.description.clone());
    }
    assert_eq!(descriptions.len(), 12, "every seed draws its own loads");
    assert!(packs.iter().all(|k| (0..=3).contains(k)), "{packs:?}");
    assert!(
        packs.contains(&0),
        "some draws are broad pressures: {packs:?}"
    );
    assert!(packs.len() >= 3, "and the pack count varies: {packs:?}");
}
