//! Helpers shared by the physics test files.
#![allow(dead_code)]

use librplus::fem::{Dirichlet, loads};
use librplus::mesh::TetMesh;

/// `x` lies on the plane coordinate `v` (to 1e-9 mm).
pub fn on(x: f64, v: f64) -> bool {
    (x - v).abs() < 1e-9
}

/// Boundary triangles on the plane x = `len`.
pub fn end_face(mesh: &TetMesh, len: f64) -> Vec<[u32; 3]> {
    mesh.boundary()
        .unwrap()
        .triangles
        .into_iter()
        .filter(|t| t.iter().all(|&v| on(mesh.nodes()[v as usize][0], len)))
        .collect()
}

/// Symmetry supports of a box at the origin: u_k = 0 on the plane x_k = 0, for each axis.
pub fn symmetry_supports(mesh: &TetMesh) -> Dirichlet {
    let mut bc = Dirichlet::new(mesh.num_nodes());
    for (i, p) in mesh.nodes().iter().enumerate() {
        for (axis, &c) in p.iter().enumerate() {
            if on(c, 0.0) {
                bc.prescribe_dof(i as u32, axis, 0.0);
            }
        }
    }
    bc
}

/// Load vector of a uniform traction `t` (kPa) on the end face x = `len`.
pub fn end_traction(mesh: &TetMesh, len: f64, t: [f64; 3]) -> Vec<f64> {
    let end = end_face(mesh, len);
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    loads::add_traction(&mut f, mesh.nodes(), &end, &vec![t; end.len()]);
    f
}

/// The largest component of `assets/livers/sofa_liver.vtk` (mm), oriented outward.
pub fn sofa_liver_surface() -> librplus::mesh::TriSurface {
    let path =
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/livers/sofa_liver.vtk");
    let file = librplus::mesh::io::read(path, librplus::mesh::io::Unit::Mm).unwrap();
    let mut s = librplus::mesh::TriSurface::from_file(&file)
        .unwrap()
        .largest_component();
    if s.signed_volume() < 0.0 {
        s.flip();
    }
    s
}

/// The registration input of a simulated scenario (what a navigation system would send),
/// checked.
pub fn scenario_measurements(
    sc: &librplus::phantom::measure::Scenario,
) -> librplus::register::Checked {
    checked(raw_measurements(sc))
}

/// Measurements checked ([`librplus::register::Checked::new`]; a test's own points are valid).
pub fn checked(m: librplus::register::Measurements) -> librplus::register::Checked {
    librplus::register::Checked::new(m).expect("a test's measurements")
}

/// [`scenario_measurements`] before the check (for tests that spoil them).
pub fn raw_measurements(
    sc: &librplus::phantom::measure::Scenario,
) -> librplus::register::Measurements {
    librplus::register::Measurements {
        points: sc.points.clone(),
        kind: sc
            .kind
            .iter()
            .map(|&k| librplus::register::MeasuredKind::from_code(k as u8).unwrap())
            .collect(),
        feature: sc.feature.clone(),
        initial_alignment: Some(sc.initial_alignment),
    }
}

/// The SOFA liver meshed with 10 mm tets, labelled and given a vessel tree by the phantom
/// module, and its preoperative model.
pub struct LabelledLiver {
    pub mesh: TetMesh,
    pub labels: librplus::register::anatomy::AnatomyLabels,
    pub vessels: librplus::phantom::vessels::VesselTree,
    pub model: librplus::register::PreopModel,
}

/// [`LabelledLiver`], built once per test binary.
pub fn labelled_liver() -> &'static LabelledLiver {
    use librplus::mesh::tetra::{TetraParams, tetrahedralize};
    use librplus::phantom::vessels::{VesselParams, VesselTree};
    use librplus::register::anatomy::{LabelParams, label};
    static L: std::sync::OnceLock<LabelledLiver> = std::sync::OnceLock::new();
    L.get_or_init(|| {
        let mesh = tetrahedralize(&sofa_liver_surface(), &TetraParams::with_edge(10.0)).unwrap();
        let labels = label(&mesh, &LabelParams::default()).unwrap();
        let vessels = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
        let model = labels.preop_model(&mesh, &vessels.points, &vessels.segments);
        LabelledLiver {
            mesh,
            labels,
            vessels,
            model,
        }
    })
}
