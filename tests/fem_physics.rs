//! Physics checks of the linear-elastic FEM against closed-form solutions and invariants.

mod common;
use common::{end_traction, on, symmetry_supports};

use librplus::fem::{
    Dirichlet, FemError, LameField, LinearMaterial, NodeSpring, StiffnessSystem, loads, post,
};
use librplus::mesh::TetMesh;
use librplus::mesh::procedural::box_mesh;

/// Patch test: any linear displacement imposed on the boundary is reproduced exactly inside.
#[test]
fn patch_test_linear_field_reproduced_inside() {
    let mesh = box_mesh([3.0, 2.0, 2.5], [5, 4, 4], 0.35);
    mesh.validate().unwrap();
    let mat = LinearMaterial::new(4.0, 0.45);
    let sys = StiffnessSystem::linear(&mesh, &mat).unwrap();
    let a = [
        [0.02, -0.01, 0.03],
        [0.015, -0.02, 0.01],
        [-0.005, 0.025, 0.01],
    ];
    let c = [0.3, -0.2, 0.1];
    let field = |p: [f64; 3]| -> [f64; 3] {
        let mut u = c;
        for i in 0..3 {
            for j in 0..3 {
                u[i] += a[i][j] * p[j];
            }
        }
        u
    };
    let boundary = mesh.boundary().unwrap().nodes;
    let mut bc = Dirichlet::new(mesh.num_nodes());
    for &n in &boundary {
        bc.prescribe_node(n, field(mesh.nodes()[n as usize]));
    }
    let fact = sys.factorize(&bc).unwrap();
    let u = fact.solve(&vec![0.0; 3 * mesh.num_nodes()]);
    let interior: Vec<usize> = (0..mesh.num_nodes())
        .filter(|i| boundary.binary_search(&(*i as u32)).is_err())
        .collect();
    assert!(interior.len() >= 27, "need interior nodes to test");
    let mut worst = 0.0f64;
    for &i in &interior {
        let e = field(mesh.nodes()[i]);
        for k in 0..3 {
            worst = worst.max((u[3 * i + k] - e[k]).abs() / e[k].abs().max(1e-3));
        }
    }
    eprintln!("patch test: worst relative interior error {worst:e}");
    assert!(worst <= 1e-10, "patch test error {worst:e}");
    // Constant strain in every tet equals sym(A); stress is Hooke's law of it.
    let (l, m) = mat.lame();
    let eps = [
        a[0][0],
        a[1][1],
        a[2][2],
        0.5 * (a[0][1] + a[1][0]),
        0.5 * (a[1][2] + a[2][1]),
        0.5 * (a[0][2] + a[2][0]),
    ];
    let tr = eps[0] + eps[1] + eps[2];
    let sig: Vec<f64> = (0..6)
        .map(|k| 2.0 * m * eps[k] + if k < 3 { l * tr } else { 0.0 })
        .collect();
    for f in post::tet_fields(&mesh, &LameField::Uniform(l, m), &u) {
        for k in 0..6 {
            assert!((f.strain[k] - eps[k]).abs() < 1e-12, "strain {k}");
            assert!((f.stress[k] - sig[k]).abs() < 1e-10, "stress {k}");
        }
    }
}

/// The free stiffness is symmetric and has exactly six zero-energy modes, which are the rigid ones.
#[test]
fn free_stiffness_symmetric_with_six_rigid_modes() {
    let mesh = box_mesh([1.0, 1.2, 0.9], [2, 2, 2], 0.3);
    let sys = StiffnessSystem::linear(&mesh, &LinearMaterial::default()).unwrap();
    let k = sys.matrix().to_dense();
    let n = k.nrows();
    let mut asym = 0.0f64;
    let mut kmax = 0.0f64;
    for i in 0..n {
        for j in 0..n {
            asym = asym.max((k[(i, j)] - k[(j, i)]).abs());
            kmax = kmax.max(k[(i, j)].abs());
        }
    }
    assert!(asym <= 1e-14 * kmax, "asymmetry {asym:e} of {kmax:e}");
    let dense = nalgebra::DMatrix::from_fn(n, n, |i, j| k[(i, j)]);
    let eig = nalgebra::SymmetricEigen::new(dense);
    let mut ev: Vec<f64> = eig.eigenvalues.iter().copied().collect();
    ev.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let top = ev[n - 1];
    let zero = ev.iter().filter(|&&x| x.abs() < 1e-10 * top).count();
    eprintln!("eigenvalues: {:e} .. {:e}; 7th {:e}", ev[0], top, ev[6]);
    assert_eq!(zero, 6, "zero-energy modes");
    assert!(ev[0] > -1e-10 * top, "K is positive semidefinite");
    assert!(ev[6] > 1e-4 * top, "no near-mechanism beyond rigid motion");
    // The six rigid fields have zero force.
    for mode in 0..6 {
        let u: Vec<f64> = mesh
            .nodes()
            .iter()
            .flat_map(|p| {
                if mode < 3 {
                    let mut t = [0.0; 3];
                    t[mode] = 1.0;
                    t
                } else {
                    let mut w = [0.0; 3];
                    w[mode - 3] = 1.0;
                    [
                        w[1] * p[2] - w[2] * p[1],
                        w[2] * p[0] - w[0] * p[2],
                        w[0] * p[1] - w[1] * p[0],
                    ]
                }
            })
            .collect();
        let f = sys.apply(&u);
        let fmax = f.iter().fold(0.0f64, |a, b| a.max(b.abs()));
        assert!(fmax < 1e-12 * kmax, "rigid mode {mode} force {fmax:e}");
    }
}

/// A bar in uniaxial tension with symmetry supports: exact stretch and Poisson contraction.
#[test]
fn uniaxial_tension_bar_matches_analytic() {
    let (len, w) = (4.0, 1.0);
    let mesh = box_mesh([len, w, w], [8, 3, 3], 0.25);
    let mat = LinearMaterial::new(5.0, 0.45);
    let sys = StiffnessSystem::linear(&mesh, &mat).unwrap();
    let sigma = 0.7; // kPa
    let bc = symmetry_supports(&mesh);
    let f = end_traction(&mesh, len, [sigma, 0.0, 0.0]);
    let u = sys.factorize(&bc).unwrap().solve(&f);
    let e = mat.youngs_modulus_kpa;
    let nu = mat.poisson_ratio;
    let mut worst = 0.0f64;
    for (i, p) in mesh.nodes().iter().enumerate() {
        let exact = [
            sigma * p[0] / e,
            -nu * sigma * p[1] / e,
            -nu * sigma * p[2] / e,
        ];
        for k in 0..3 {
            worst = worst.max((u[3 * i + k] - exact[k]).abs());
        }
    }
    let stretch = sigma * len / e;
    eprintln!("tension: stretch {stretch}, worst abs error {worst:e}");
    assert!(worst < 1e-10 * stretch);
    // Energy = σ²/(2E) · V.
    let energy = sys.energy(&u);
    let exact_energy = sigma * sigma / (2.0 * e) * len * w * w;
    assert!((energy - exact_energy).abs() < 1e-10 * exact_energy);
}

/// Hydrostatic pressure on a closed surface: uniform contraction −p/(3K)·x (checks pressure sign).
#[test]
fn hydrostatic_pressure_gives_uniform_contraction() {
    let mesh = box_mesh([2.0, 2.0, 2.0], [3, 3, 3], 0.3);
    let mat = LinearMaterial::new(3.0, 0.3);
    let sys = StiffnessSystem::linear(&mesh, &mat).unwrap();
    let p = 0.2;
    let b = mesh.boundary().unwrap();
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    loads::add_pressure(&mut f, mesh.nodes(), &b.triangles, p);
    let find = |q: [f64; 3]| {
        mesh.nodes()
            .iter()
            .position(|x| (0..3).all(|k| on(x[k], q[k])))
            .unwrap() as u32
    };
    let mut bc = Dirichlet::new(mesh.num_nodes());
    bc.prescribe_node(find([0.0, 0.0, 0.0]), [0.0; 3]);
    bc.prescribe_dof(find([2.0, 0.0, 0.0]), 1, 0.0);
    bc.prescribe_dof(find([2.0, 0.0, 0.0]), 2, 0.0);
    bc.prescribe_dof(find([0.0, 2.0, 0.0]), 2, 0.0);
    let u = sys.factorize(&bc).unwrap().solve(&f);
    let bulk = mat.youngs_modulus_kpa / (3.0 * (1.0 - 2.0 * mat.poisson_ratio));
    let eps = -p / (3.0 * bulk);
    for (i, x) in mesh.nodes().iter().enumerate() {
        for k in 0..3 {
            assert!((u[3 * i + k] - eps * x[k]).abs() < 1e-10, "node {i}");
        }
    }
}

/// Springs alone support a body: equal nodal loads F on springs k translate it by F/k.
#[test]
fn springs_support_without_dirichlet() {
    let mesh = box_mesh([1.0, 1.0, 1.0], [2, 2, 2], 0.2);
    let mut sys = StiffnessSystem::linear(&mesh, &LinearMaterial::default()).unwrap();
    let k = 0.5;
    let springs: Vec<NodeSpring> = (0..mesh.num_nodes() as u32)
        .map(|n| NodeSpring::isotropic(n, k))
        .collect();
    sys.add_springs(&springs).unwrap();
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    for n in 0..mesh.num_nodes() as u32 {
        loads::add_point_load(&mut f, n, [0.1, -0.3, 0.2]);
    }
    let u = sys
        .factorize(&Dirichlet::new(mesh.num_nodes()))
        .unwrap()
        .solve(&f);
    for c in u.chunks_exact(3) {
        assert!(
            (c[0] - 0.2).abs() < 1e-10 && (c[1] + 0.6).abs() < 1e-10 && (c[2] - 0.4).abs() < 1e-10
        );
    }
    // A normal-only spring (sliding support) leaves tangential motion free: not positive definite.
    let mut sliding = StiffnessSystem::linear(&mesh, &LinearMaterial::default()).unwrap();
    let s: Vec<NodeSpring> = (0..mesh.num_nodes() as u32)
        .map(|n| NodeSpring::normal_tangent(n, [0.0, 0.0, 1.0], 1.0, 0.0))
        .collect();
    sliding.add_springs(&s).unwrap();
    assert!(
        sliding
            .factorize(&Dirichlet::new(mesh.num_nodes()))
            .is_err()
    );
}

/// An unconstrained body cannot be factorized; the error says why and where.
#[test]
fn unconstrained_system_is_reported() {
    let mesh = box_mesh([1.0, 1.0, 1.0], [1, 1, 1], 0.0);
    let sys = StiffnessSystem::linear(&mesh, &LinearMaterial::default()).unwrap();
    let err = sys
        .factorize(&Dirichlet::new(mesh.num_nodes()))
        .unwrap_err();
    assert!(err.to_string().contains("move rigidly"), "{err}");
    assert!(StiffnessSystem::linear(&mesh, &LinearMaterial::new(5.0, 0.5)).is_err());
    // Two separate boxes, only the first fixed: the second is reported as a floating part.
    let a = box_mesh([1.0, 1.0, 1.0], [2, 2, 2], 0.1);
    let n = a.num_nodes() as u32;
    let mut nodes = a.nodes().to_vec();
    nodes.extend(a.nodes().iter().map(|p| [p[0] + 3.0, p[1], p[2]]));
    let mut tets = a.tets().to_vec();
    tets.extend(a.tets().iter().map(|t| t.map(|v| v + n)));
    let two = TetMesh::new(nodes, tets).unwrap();
    let sys = StiffnessSystem::linear(&two, &LinearMaterial::default()).unwrap();
    let mut bc = Dirichlet::new(two.num_nodes());
    bc.fix_nodes(&[0, 1, 2, 3, 4, 5, 6, 7, 8]);
    let err = sys.factorize(&bc).unwrap_err();
    assert!(
        matches!(err, FemError::FloatingPart { part: 1, node, .. } if node >= n as usize),
        "{err}"
    );
    // A node no tet uses is named.
    let mut nodes = a.nodes().to_vec();
    nodes.push([9.0, 9.0, 9.0]);
    let spare = TetMesh::new(nodes, a.tets().to_vec()).unwrap();
    let sys = StiffnessSystem::linear(&spare, &LinearMaterial::default()).unwrap();
    let mut bc = Dirichlet::new(spare.num_nodes());
    bc.fix_nodes(&[0]);
    let err = sys.factorize(&bc).unwrap_err();
    assert_eq!(err, FemError::UnusedNode { node: n as usize });
}

/// Heterogeneous stiffness: a bar of two materials in series under end traction stretches by
/// σ(L₁/E₁ + L₂/E₂) (uniaxial stress; ν = 0 so the layers do not constrain each other).
#[test]
fn heterogeneous_bar_in_series() {
    let (len, w) = (4.0, 1.0);
    let mesh = box_mesh([len, w, w], [8, 2, 2], 0.0);
    let (e1, e2) = (2.0, 10.0);
    let lame: Vec<(f64, f64)> = (0..mesh.num_tets())
        .map(|t| {
            let p = mesh.tet_points(t);
            let cx = p.iter().map(|q| q[0]).sum::<f64>() / 4.0;
            let e = if cx < len / 2.0 { e1 } else { e2 };
            LinearMaterial::new(e, 0.0).lame()
        })
        .collect();
    let sys = StiffnessSystem::linear_field(&mesh, &LameField::PerTet(lame)).unwrap();
    let bc = symmetry_supports(&mesh);
    let sigma = 0.5;
    let f = end_traction(&mesh, len, [sigma, 0.0, 0.0]);
    let u = sys.factorize(&bc).unwrap().solve(&f);
    for (i, p) in mesh.nodes().iter().enumerate() {
        let x = p[0];
        let exact = if x <= len / 2.0 {
            sigma * x / e1
        } else {
            sigma * (len / 2.0) / e1 + sigma * (x - len / 2.0) / e2
        };
        assert!((u[3 * i] - exact).abs() < 1e-10, "node {i} at x={x}");
    }
}

/// Tip deflection of a cantilever (clamped at x = 0, shear traction on the end face).
fn cantilever_tip(n: usize, mat: &LinearMaterial, len: f64, h: f64, load: f64) -> f64 {
    let along = (len / h) as usize * n;
    let mesh: TetMesh = box_mesh([len, h, h], [along, n, n], 0.0);
    let sys = StiffnessSystem::linear(&mesh, mat).unwrap();
    let clamped: Vec<u32> = (0..mesh.num_nodes() as u32)
        .filter(|&i| on(mesh.nodes()[i as usize][0], 0.0))
        .collect();
    let mut bc = Dirichlet::new(mesh.num_nodes());
    bc.fix_nodes(&clamped);
    let tau = load / (h * h);
    let f = end_traction(&mesh, len, [0.0, 0.0, tau]);
    let u = sys.factorize(&bc).unwrap().solve(&f);
    // Mean vertical displacement of the end-face nodes.
    let tip: Vec<f64> = (0..mesh.num_nodes())
        .filter(|&i| on(mesh.nodes()[i][0], len))
        .map(|i| u[3 * i + 2])
        .collect();
    tip.iter().sum::<f64>() / tip.len() as f64
}

/// Cantilever converges to Timoshenko beam theory under refinement.
#[test]
fn cantilever_converges_to_timoshenko() {
    let mat = LinearMaterial::new(1000.0, 0.3);
    let (len, h, load): (f64, f64, f64) = (10.0, 1.0, 0.01);
    let e = mat.youngs_modulus_kpa;
    let nu = mat.poisson_ratio;
    let g = e / (2.0 * (1.0 + nu));
    let inertia = h.powi(4) / 12.0;
    let kappa = 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu); // Cowper, rectangular section
    let exact = load * len.powi(3) / (3.0 * e * inertia) + load * len / (kappa * g * h * h);
    let mut errors = Vec::new();
    let mut tips = Vec::new();
    for n in [2, 4, 8, 16] {
        let tip = cantilever_tip(n, &mat, len, h, load);
        tips.push(tip);
        let err = (tip - exact).abs() / exact;
        eprintln!(
            "cantilever n={n}: tip {tip:.6} vs Timoshenko {exact:.6}: error {:.2}%",
            100.0 * err
        );
        errors.push(err);
    }
    for w in errors.windows(2) {
        assert!(w[1] < w[0], "error must fall under refinement: {errors:?}");
    }
    assert!(
        *errors.last().unwrap() < 0.03,
        "finest error {:?}",
        errors.last()
    );
    // Richardson extrapolation of the last three meshes lands on beam theory.
    let (a, b, c) = (tips[1], tips[2], tips[3]);
    let ratio = (b - a) / (c - b);
    let extrapolated = c + (c - b) / (ratio - 1.0);
    let order = ratio.log2();
    let err = (extrapolated - exact).abs() / exact;
    eprintln!(
        "observed order {order:.2}, extrapolated tip {extrapolated:.6}: error {:.2}%",
        100.0 * err
    );
    assert!(order > 1.0, "convergence order {order}");
    assert!(err < 0.01);
}
