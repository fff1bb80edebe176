//! The Neo-Hookean ground-truth solver against finite differences, the linear solver at small
//! strain, and the analytic homogeneous uniaxial stretch.

mod common;
use common::{end_traction, on, symmetry_supports};

use librplus::fem::hyperelastic::{
    HyperelasticModel, MaterialLaw, NewtonParams, energy_density, pk1,
};
use librplus::fem::{Dirichlet, FemError, LameField, LinearMaterial, StiffnessSystem};
use librplus::mesh::TetMesh;
use librplus::mesh::procedural::box_mesh;
use librplus::util::SplitMix64;

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn lame() -> (f64, f64) {
    LinearMaterial::new(5.0, 0.45).lame()
}

/// A smooth, moderately large displacement field (strains up to ~15 %).
fn smooth_field(mesh: &TetMesh) -> Vec<f64> {
    mesh.nodes()
        .iter()
        .flat_map(|p| {
            [
                0.12 * p[0] * p[1] + 0.05 * p[2],
                -0.08 * p[1] * p[2] + 0.1 * p[0],
                0.06 * p[0] * p[0] - 0.1 * p[2] * p[1],
            ]
        })
        .collect()
}

#[test]
fn stress_is_the_derivative_of_the_energy() {
    let (l, m) = lame();
    let f = [[1.1, 0.2, -0.05], [0.1, 0.95, 0.15], [-0.1, 0.05, 1.2]];
    let p = pk1(&f, l, m).unwrap();
    let h = 1e-6;
    for a in 0..3 {
        for b in 0..3 {
            let mut fp = f;
            let mut fm = f;
            fp[a][b] += h;
            fm[a][b] -= h;
            let d = (energy_density(&fp, l, m).unwrap() - energy_density(&fm, l, m).unwrap())
                / (2.0 * h);
            assert!(
                (d - p[a][b]).abs() < 1e-7 * p[a][b].abs().max(1.0),
                "P[{a}][{b}] {d} vs {}",
                p[a][b]
            );
        }
    }
    // Stress-free and energy-free at F = I; inverted F has no energy.
    let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    assert!(
        pk1(&id, l, m)
            .unwrap()
            .iter()
            .flatten()
            .all(|x| x.abs() < 1e-15)
    );
    assert_eq!(energy_density(&id, l, m).unwrap(), 0.0);
    let inv = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    assert!(energy_density(&inv, l, m).is_none());
}

/// The laws beside Neo-Hookean, with parameters at the ends of the generator's ranges.
fn other_laws() -> [MaterialLaw; 4] {
    [
        MaterialLaw::MooneyRivlin { i2_share: 0.3 },
        MaterialLaw::MooneyRivlin { i2_share: 1.0 },
        MaterialLaw::Demiray { stiffening: 1.5 },
        MaterialLaw::Demiray { stiffening: 6.0 },
    ]
}

#[test]
fn every_law_is_stress_free_at_rest_and_its_stress_is_the_energy_derivative() {
    let (l, m) = lame();
    let f = [[1.1, 0.2, -0.05], [0.1, 0.95, 0.15], [-0.1, 0.05, 1.2]];
    let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for law in other_laws() {
        let p = law.pk1(&f, l, m).unwrap();
        let h = 1e-6;
        for a in 0..3 {
            for b in 0..3 {
                let (mut fp, mut fm) = (f, f);
                fp[a][b] += h;
                fm[a][b] -= h;
                let d = (law.energy_density(&fp, l, m).unwrap()
                    - law.energy_density(&fm, l, m).unwrap())
                    / (2.0 * h);
                assert!(
                    (d - p[a][b]).abs() < 1e-7 * p[a][b].abs().max(1.0),
                    "{law:?}: P[{a}][{b}] {d} vs {}",
                    p[a][b]
                );
            }
        }
        assert!(
            law.pk1(&id, l, m)
                .unwrap()
                .iter()
                .flatten()
                .all(|x| x.abs() < 1e-14)
        );
        assert!(law.energy_density(&id, l, m).unwrap().abs() < 1e-15);
        let inv = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(law.energy_density(&inv, l, m).is_none() && law.pk1(&inv, l, m).is_none());
        // The same small-strain limit: at strain ε the stress differs from Neo-Hookean's by
        // O(ε²), so the relative difference shrinks tenfold when ε does.
        let rel = |eps: f64| {
            let fe = [
                [1.0 + eps, 0.4 * eps, 0.0],
                [0.0, 1.0 - 0.3 * eps, 0.2 * eps],
                [0.1 * eps, 0.0, 1.0 + 0.5 * eps],
            ];
            let (a, b) = (law.pk1(&fe, l, m).unwrap(), pk1(&fe, l, m).unwrap());
            let d: f64 = a
                .iter()
                .flatten()
                .zip(b.iter().flatten())
                .map(|(x, y)| (x - y).powi(2))
                .sum();
            let n: f64 = b.iter().flatten().map(|x| x * x).sum();
            (d / n).sqrt()
        };
        let (r1, r2) = (rel(1e-2), rel(1e-3));
        assert!(r2 < 0.15 * r1 && r2 < 2e-3, "{law:?}: {r1:e} -> {r2:e}");
    }
    // Mooney-Rivlin with no second-invariant share is Neo-Hookean.
    let mr0 = MaterialLaw::MooneyRivlin { i2_share: 0.0 };
    let (a, b) = (mr0.pk1(&f, l, m).unwrap(), pk1(&f, l, m).unwrap());
    for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
        assert!((x - y).abs() < 1e-12 * y.abs().max(1.0));
    }
    // Out-of-range parameters are refused, naming the law's parameter.
    let mesh = box_mesh([1.0, 1.0, 1.0], [1, 1, 1], 0.0);
    let e = HyperelasticModel::new(&mesh, LameField::Uniform(l, m))
        .unwrap()
        .with_law(MaterialLaw::MooneyRivlin { i2_share: 1.5 })
        .unwrap_err();
    assert!(e.to_string().contains("i2_share"), "{e}");
    assert!(
        HyperelasticModel::new(&mesh, LameField::Uniform(l, m))
            .unwrap()
            .with_law(MaterialLaw::Demiray { stiffening: -1.0 })
            .is_err()
    );
}

#[test]
fn tangent_and_forces_match_finite_differences() {
    let mesh = box_mesh([2.0, 1.5, 1.0], [3, 2, 2], 0.3);
    let (l, m) = lame();
    let model = HyperelasticModel::new(&mesh, LameField::Uniform(l, m)).unwrap();
    check_tangent(&mesh, &model);
    for law in other_laws() {
        eprintln!("{law:?}");
        check_tangent(
            &mesh,
            &HyperelasticModel::new(&mesh, LameField::Uniform(l, m))
                .unwrap()
                .with_law(law)
                .unwrap(),
        );
    }
}

fn check_tangent(mesh: &TetMesh, model: &HyperelasticModel) {
    let u = smooth_field(mesh);
    let mut rng = SplitMix64::new(3);
    let v: Vec<f64> = (0..u.len()).map(|_| rng.next_f64() - 0.5).collect();
    let f = model.internal_force(&u).unwrap();
    // Forces are the gradient of the energy.
    let eps = 1e-6;
    let shifted = |s: f64| -> Vec<f64> { u.iter().zip(&v).map(|(a, b)| a + s * b).collect() };
    let de = (model.energy(&shifted(eps)).unwrap() - model.energy(&shifted(-eps)).unwrap())
        / (2.0 * eps);
    let fv: f64 = f.iter().zip(&v).map(|(a, b)| a * b).sum();
    assert!(
        (de - fv).abs() <= 1e-7 * fv.abs(),
        "energy derivative {de} vs f·v {fv}"
    );
    // Tangent is the derivative of the forces.
    let k = model
        .linearized()
        .pattern()
        .to_matrix(model.tangent_values(&u).unwrap())
        .to_dense();
    let kv: Vec<f64> = (0..u.len())
        .map(|i| (0..u.len()).map(|j| k[(i, j)] * v[j]).sum())
        .collect();
    let fp = model.internal_force(&shifted(eps)).unwrap();
    let fm = model.internal_force(&shifted(-eps)).unwrap();
    let fd: Vec<f64> = fp
        .iter()
        .zip(&fm)
        .map(|(a, b)| (a - b) / (2.0 * eps))
        .collect();
    let err: Vec<f64> = fd.iter().zip(&kv).map(|(a, b)| a - b).collect();
    let rel = norm(&err) / norm(&kv);
    eprintln!("tangent vs central differences: relative error {rel:e}");
    assert!(rel <= 1e-6, "{rel:e}");
    // The tangent is symmetric (hyperelastic, dead loads).
    let n = u.len();
    for i in 0..n {
        for j in 0..n {
            assert!((k[(i, j)] - k[(j, i)]).abs() < 1e-10 * (1.0 + k[(i, i)].abs()));
        }
    }
}

#[test]
fn small_strain_matches_the_linear_solver() {
    // Compact block clamped at x = 0 under an oblique end traction giving ~0.1 % strain. (A
    // slender beam would not do: tension stiffening of its bending is a geometric nonlinearity
    // of a few percent even at this strain.)
    let (len, w) = (1.5, 1.0);
    let mesh = box_mesh([len, w, w], [6, 4, 4], 0.2);
    let mat = LinearMaterial::new(5.0, 0.45);
    let (l, m) = mat.lame();
    let mut bc = Dirichlet::new(mesh.num_nodes());
    for (i, p) in mesh.nodes().iter().enumerate() {
        if on(p[0], 0.0) {
            bc.prescribe_node(i as u32, [0.0; 3]);
        }
    }
    let model = HyperelasticModel::new(&mesh, LameField::Uniform(l, m)).unwrap();
    let linear = StiffnessSystem::linear(&mesh, &mat)
        .unwrap()
        .factorize(&bc)
        .unwrap();
    // Relative difference between the two solutions at a given strain level.
    let difference = |strain: f64| {
        let sigma = strain * mat.youngs_modulus_kpa;
        let f = end_traction(&mesh, len, [sigma, 0.0, 0.3 * sigma]);
        let ul = linear.solve(&f);
        let (u, info) = model.solve(&bc, &f, &NewtonParams::default()).unwrap();
        assert!(info.relative_residual <= 1e-9);
        let diff: Vec<f64> = u.iter().zip(&ul).map(|(a, b)| a - b).collect();
        norm(&diff) / norm(&ul)
    };
    let rel = difference(1e-3);
    let rel_small = difference(1e-4);
    eprintln!("|u_nh - u_lin| / |u_lin|: {rel:e} at 0.1% strain, {rel_small:e} at 0.01%");
    assert!(rel <= 0.01, "{rel}");
    // The difference is a nonlinear effect: first order in the load.
    let ratio = rel / rel_small;
    assert!((8.0..12.0).contains(&ratio), "ratio {ratio}");
}

/// Lateral stretch `b` and nominal stress `P₁₁` of uniaxial stress at axial stretch `a`:
/// `P₂₂ = μ(b − 1/b) + λ ln(a b²)/b = 0`, solved by bisection.
fn uniaxial_analytic(a: f64, l: f64, m: f64) -> (f64, f64) {
    let p22 = |b: f64| m * (b - 1.0 / b) + l * (a * b * b).ln() / b;
    let (mut lo, mut hi) = (0.3, 1.0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if p22(mid) > 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let b = 0.5 * (lo + hi);
    (b, m * (a - 1.0 / a) + l * (a * b * b).ln() / a)
}

/// A 3 × 1 × 1 bar on symmetry supports, its end face pulled to 30 % stretch: the mesh, the
/// supports, its length and width, and the stretch.
fn thirty_percent_stretch() -> (TetMesh, Dirichlet, [f64; 2], f64) {
    let (len, w) = (3.0, 1.0);
    let mesh = box_mesh([len, w, w], [6, 2, 2], 0.2);
    let stretch = 1.3;
    let mut bc = symmetry_supports(&mesh);
    for (i, p) in mesh.nodes().iter().enumerate() {
        if on(p[0], len) {
            bc.prescribe_dof(i as u32, 0, (stretch - 1.0) * len);
        }
    }
    (mesh, bc, [len, w], stretch)
}

#[test]
fn uniaxial_stretch_of_thirty_percent_matches_analytic() {
    let (mesh, bc, [len, w], stretch) = thirty_percent_stretch();
    let (l, m) = lame();
    let model = HyperelasticModel::new(&mesh, LameField::Uniform(l, m)).unwrap();
    let f = vec![0.0; 3 * mesh.num_nodes()];
    let (b, p11) = uniaxial_analytic(stretch, l, m);
    let (reaction, info) = stretched(&model, &mesh, &bc, [len, w], b, "Neo-Hookean");
    let exact = p11 * w * w;
    eprintln!(
        "30% stretch: reaction {reaction:.6} mN vs analytic {exact:.6} (b = {b:.6}); {} steps, {} iterations",
        info.load_steps, info.iterations
    );
    assert!((reaction - exact).abs() <= 0.01 * exact);
    // The linear model misses the stiffening: its reaction differs by more than 1 %.
    let lin = StiffnessSystem::linear(&mesh, &LinearMaterial::new(5.0, 0.45)).unwrap();
    let ul = lin.factorize(&bc).unwrap().solve(&f);
    let rl: f64 = lin
        .apply(&ul)
        .chunks_exact(3)
        .zip(mesh.nodes())
        .filter(|(_, p)| on(p[0], len))
        .map(|(c, _)| c[0])
        .sum();
    assert!((rl - exact).abs() > 0.01 * exact, "linear {rl} vs {exact}");
}

/// Solves the stretched bar (length and width `size`, no body load) and returns the reaction on
/// its loaded face (from the internal forces) and the solver's statistics, after checking the
/// lateral stretch of its free face against `b`.
fn stretched(
    model: &HyperelasticModel,
    mesh: &TetMesh,
    bc: &Dirichlet,
    [len, w]: [f64; 2],
    b: f64,
    what: &str,
) -> (f64, librplus::fem::hyperelastic::NewtonInfo) {
    let f = vec![0.0; 3 * mesh.num_nodes()];
    let (u, info) = model.solve(bc, &f, &NewtonParams::default()).unwrap();
    let fint = model.internal_force(&u).unwrap();
    let mut reaction = 0.0;
    for (i, p) in mesh.nodes().iter().enumerate() {
        if on(p[0], len) {
            reaction += fint[3 * i];
        }
        if on(p[1], w) {
            let b_fem = 1.0 + u[3 * i + 1] / w;
            assert!(
                (b_fem - b).abs() <= 0.01 * (1.0 - b),
                "{what}: lateral stretch {b_fem} vs {b}"
            );
        }
    }
    (reaction, info)
}

/// The homogeneous uniaxial state of `law` at stretch `a`: the lateral stretch `b` where the
/// lateral stress of `diag(a, b, b)` vanishes (bisection), and the axial stress `P₁₁` there.
fn uniaxial_of(law: MaterialLaw, a: f64, l: f64, m: f64) -> (f64, f64) {
    let p = |b: f64| {
        law.pk1(&[[a, 0.0, 0.0], [0.0, b, 0.0], [0.0, 0.0, b]], l, m)
            .unwrap()
    };
    let (mut lo, mut hi) = (0.3, 1.0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if p(mid)[1][1] > 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let b = 0.5 * (lo + hi);
    (b, p(b)[0][0])
}

#[test]
fn every_law_solves_a_thirty_percent_stretch_to_its_homogeneous_state() {
    let (mesh, bc, [len, w], stretch) = thirty_percent_stretch();
    let (l, m) = lame();
    let (_, p_nh) = uniaxial_of(MaterialLaw::NeoHookean, stretch, l, m);
    // The semi-analytic state agrees with the closed form for Neo-Hookean.
    assert!((p_nh - uniaxial_analytic(stretch, l, m).1).abs() < 1e-9 * p_nh);
    for law in other_laws() {
        let model = HyperelasticModel::new(&mesh, LameField::Uniform(l, m))
            .unwrap()
            .with_law(law)
            .unwrap();
        let (b, p11) = uniaxial_of(law, stretch, l, m);
        let (reaction, info) = stretched(&model, &mesh, &bc, [len, w], b, &format!("{law:?}"));
        let exact = p11 * w * w;
        eprintln!(
            "{law:?}: reaction {reaction:.6} mN vs homogeneous {exact:.6} (Neo-Hookean {p_nh:.6}); {} steps, {} iterations",
            info.load_steps, info.iterations
        );
        assert!((reaction - exact).abs() <= 0.01 * exact);
        // Another truth: at 30 % stretch it differs from Neo-Hookean by more than 2 %.
        assert!(
            (exact - p_nh).abs() > 0.02 * p_nh,
            "{law:?}: {exact} vs {p_nh}"
        );
    }
}

#[test]
fn impossible_compression_is_reported_not_returned() {
    // Pushing the end face past the clamped face would invert every element.
    let mesh = box_mesh([1.0, 1.0, 1.0], [2, 2, 2], 0.0);
    let (l, m) = lame();
    let model = HyperelasticModel::new(&mesh, LameField::Uniform(l, m)).unwrap();
    let mut bc = symmetry_supports(&mesh);
    for (i, p) in mesh.nodes().iter().enumerate() {
        if on(p[0], 1.0) {
            bc.prescribe_dof(i as u32, 0, -1.2);
        }
    }
    let err = model
        .solve(
            &bc,
            &vec![0.0; 3 * mesh.num_nodes()],
            &NewtonParams::default(),
        )
        .unwrap_err();
    assert!(matches!(err, FemError::NotConverged { .. }), "{err}");
    assert!(err.to_string().contains("did not converge"));
}

/// Unilateral contacts: forces are the energy's gradient and the tangent the forces' derivative
/// (away from the kink at zero closure), they push only when pressed, and a block pressed onto a
/// contact bed by a load settles where the analytic penalty gives, while pulled it lifts off freely.
#[test]
fn unilateral_contacts_push_but_never_pull() {
    use librplus::fem::{ContactSpring, NodeSpring};
    let mesh = box_mesh([2.0, 1.5, 1.0], [3, 2, 2], 0.3);
    let (l, m) = lame();
    let mut model = HyperelasticModel::new(&mesh, LameField::Uniform(l, m)).unwrap();
    // The z = 0 face rests on a bed below it: outward normal −z.
    let select = |f: &dyn Fn([f64; 3]) -> bool| -> Vec<u32> {
        (0..mesh.num_nodes() as u32)
            .filter(|&n| f(mesh.nodes()[n as usize]))
            .collect()
    };
    let bottom = select(&|p| on(p[2], 0.0));
    let k = 40.0;
    let contacts: Vec<ContactSpring> = bottom
        .iter()
        .map(|&node| ContactSpring {
            node,
            normal: [0.0, 0.0, -2.0],
            stiffness: k,
        })
        .collect();
    model.add_contacts(&contacts).unwrap();
    assert!(
        model
            .contacts()
            .iter()
            .all(|c| c.normal == [0.0, 0.0, -1.0])
    );
    // Derivative checks on a field that presses some bottom nodes and lifts others.
    let mut u = smooth_field(&mesh);
    for n in 0..mesh.num_nodes() {
        u[3 * n + 2] -= 0.1;
    }
    let active = model.active_contacts(&u);
    assert!(
        active > 0 && active < bottom.len(),
        "{active} of {}",
        bottom.len()
    );
    let mut rng = SplitMix64::new(5);
    let v: Vec<f64> = (0..u.len()).map(|_| rng.next_f64() - 0.5).collect();
    let eps = 1e-7;
    let shifted = |s: f64| -> Vec<f64> { u.iter().zip(&v).map(|(a, b)| a + s * b).collect() };
    let f = model.internal_force(&u).unwrap();
    let de = (model.energy(&shifted(eps)).unwrap() - model.energy(&shifted(-eps)).unwrap())
        / (2.0 * eps);
    let fv: f64 = f.iter().zip(&v).map(|(a, b)| a * b).sum();
    assert!((de - fv).abs() <= 1e-6 * fv.abs(), "{de} vs {fv}");
    let kmat = model
        .linearized()
        .pattern()
        .to_matrix(model.tangent_values(&u).unwrap())
        .to_dense();
    let (fp, fm) = (
        model.internal_force(&shifted(eps)).unwrap(),
        model.internal_force(&shifted(-eps)).unwrap(),
    );
    let err: Vec<f64> = (0..u.len())
        .map(|i| {
            let kv: f64 = (0..u.len()).map(|j| kmat[(i, j)] * v[j]).sum();
            (fp[i] - fm[i]) / (2.0 * eps) - kv
        })
        .collect();
    let scale = norm(
        &fp.iter()
            .zip(&fm)
            .map(|(a, b)| (a - b) / (2.0 * eps))
            .collect::<Vec<_>>(),
    );
    assert!(norm(&err) <= 1e-6 * scale, "{}", norm(&err) / scale);
    // Pressed down by a uniform load on the top face, the block sinks by F/(k·N) into the bed
    // (a rigid translation: the bed is the only support but for soft side springs).
    let top = select(&|p| on(p[2], 1.0));
    let soft: Vec<NodeSpring> = (0..mesh.num_nodes() as u32)
        .map(|n| NodeSpring::isotropic(n, 1e-3))
        .collect();
    model.add_springs(&soft).unwrap();
    let mut load = vec![0.0; 3 * mesh.num_nodes()];
    let per_node = -0.5;
    for &n in &top {
        load[3 * n as usize + 2] = per_node;
    }
    let total = per_node * top.len() as f64;
    let bc = Dirichlet::new(mesh.num_nodes());
    let (u, _) = model.solve(&bc, &load, &NewtonParams::default()).unwrap();
    assert!(2 * model.active_contacts(&u) >= bottom.len());
    // The bed's push (k·closure on pressed nodes) and the soft springs balance the load.
    let bed_force: f64 = model
        .contacts()
        .iter()
        .map(|c| -k * c.closure(&u).max(0.0))
        .sum();
    let soft_force: f64 = (0..mesh.num_nodes()).map(|n| 1e-3 * u[3 * n + 2]).sum();
    assert!(
        (bed_force + soft_force - total).abs() < 1e-6 * total.abs(),
        "bed {bed_force} + soft {soft_force} vs load {total}"
    );
    let sink = total / (k * bottom.len() as f64);
    // Pulled up instead, nothing holds it but the soft springs: it lifts F/(1e-3·n) freely.
    let up: Vec<f64> = load.iter().map(|x| -x).collect();
    let (u, _) = model.solve(&bc, &up, &NewtonParams::default()).unwrap();
    assert_eq!(model.active_contacts(&u), 0);
    let rise: f64 = (0..mesh.num_nodes()).map(|n| u[3 * n + 2]).sum::<f64>();
    assert!((1e-3 * rise + total).abs() < 1e-6 * total.abs(), "{rise}");
    // A bilateral stand-in would have held it at −sink instead.
    assert!(rise / mesh.num_nodes() as f64 > 10.0 * sink.abs());
    // Bad contacts are refused by name.
    let bad = ContactSpring {
        node: 0,
        normal: [0.0; 3],
        stiffness: 1.0,
    };
    let e = model.add_contacts(&[bad]).unwrap_err().to_string();
    assert!(e.contains("contacts") && e.contains("normal"), "{e}");
}
