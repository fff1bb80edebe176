use super::model::*;
use super::*;
use crate::fem::hyperelastic::{HyperelasticModel, NewtonParams};
use crate::fem::{Dirichlet, LameField, LinearMaterial, NodeSpring, loads};
use crate::mesh::TetMesh;
use crate::mesh::procedural::box_mesh;
use crate::register::libr::{LibrBasis, LibrParams};

fn block() -> TetMesh {
    box_mesh([60.0, 40.0, 30.0], [6, 4, 3], 0.0)
}

/// Posterior = the +y face, falciform = the top face's middle line (x = 30).
fn flags(mesh: &TetMesh) -> (Vec<bool>, Vec<bool>) {
    let (_, hi) = mesh.bounding_box();
    let post = mesh.nodes().iter().map(|p| p[1] > hi[1] - 1e-9).collect();
    let falc = mesh
        .nodes()
        .iter()
        .map(|p| p[2] > hi[2] - 1e-9 && (p[0] - 30.0).abs() < 1e-9)
        .collect();
    (post, falc)
}

fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
    let den: f64 = b.iter().map(|y| y * y).sum();
    (num / den).sqrt()
}

/// Boundary triangles (outward) with their unit normals and areas, computed here from the
/// faces used by one tet only (independent of `TetMesh::boundary`).
fn faces(mesh: &TetMesh) -> Vec<([u32; 3], [f64; 3], f64)> {
    let mut count = std::collections::HashMap::new();
    for tet in mesh.tets() {
        for f in [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]] {
            let mut k = f.map(|i| tet[i]);
            k.sort();
            *count.entry(k).or_insert(0) += 1;
        }
    }
    let p = mesh.nodes();
    let mut out = Vec::new();
    for tet in mesh.tets() {
        for (f, other) in [
            ([0, 1, 2], 3),
            ([0, 1, 3], 2),
            ([0, 2, 3], 1),
            ([1, 2, 3], 0),
        ] {
            let mut k = f.map(|i| tet[i]);
            k.sort();
            if count[&k] != 1 {
                continue;
            }
            let t = f.map(|i| tet[i]);
            let [a, b, c] = t.map(|v| p[v as usize]);
            let d = p[tet[other] as usize];
            let ab = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let ac = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let mut n = [
                ab[1] * ac[2] - ab[2] * ac[1],
                ab[2] * ac[0] - ab[0] * ac[2],
                ab[0] * ac[1] - ab[1] * ac[0],
            ];
            let ad = [d[0] - a[0], d[1] - a[1], d[2] - a[2]];
            let (t, sign) = if n[0] * ad[0] + n[1] * ad[1] + n[2] * ad[2] > 0.0 {
                ([t[0], t[2], t[1]], -1.0)
            } else {
                (t, 1.0)
            };
            n = n.map(|x| sign * x);
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            out.push((t, n.map(|x| x / l), 0.5 * l));
        }
    }
    out
}

/// A load's self-equilibrated part (inertia relief with the lumped nodal volumes).
fn equilibrate(mesh: &TetMesh, f: &mut [f64]) {
    let modes = crate::register::libr::RigidModes::new(
        mesh.nodes(),
        &crate::register::libr::lumped_volumes(mesh),
    )
    .unwrap();
    modes.equilibrate(mesh.nodes(), f);
}

fn small_newton() -> NewtonParams {
    NewtonParams {
        tolerance: 1e-7,
        ..NewtonParams::default()
    }
}

#[test]
fn physics_json_round_trips_and_bad_files_name_the_field() {
    let p = Physics {
        effects: vec![
            Effect::new(
                EffectKind::Gravity,
                &[("direction", &[0.0, 1.0, 0.0]), ("magnitude", &[0.0104])],
            )
            .unwrap(),
            Effect::new(EffectKind::BedSupport, &[("stiffness", &[0.08])]).unwrap(),
        ],
    };
    let text = p.to_value(&[]).to_string();
    assert_eq!(Physics::from_json(&text).unwrap(), p);
    assert_ne!(p.hash(), Physics::none().hash());
    let bad = |t: &str| Physics::from_json(t).unwrap_err().to_string();
    let e = bad(r#"{"format": 1, "effects": [{"kind": "magnetism"}]}"#);
    assert!(
        e.contains("effects[0].kind") && e.contains("magnetism") && e.contains("gravity"),
        "{e}"
    );
    let e = bad(
        r#"{"format": 1, "effects": [{"kind": "bed-support", "parameters": {"stiffness": 50}}]}"#,
    );
    assert!(
        e.contains("effects[0].parameters.stiffness") && e.contains("outside"),
        "{e}"
    );
    let e = bad(r#"{"format": 1, "effects": [{"kind": "bed-support", "parameters": {}}]}"#);
    assert!(
        e.contains("effects[0].parameters.stiffness: missing"),
        "{e}"
    );
    let e = bad(
        r#"{"format": 1, "effects": [{"kind": "pack", "parameters": {"center": [1, 2], "width_mm": 10, "force_mn": [0, 0, 1]}}]}"#,
    );
    assert!(
        e.contains("effects[0].parameters.center") && e.contains("3 number"),
        "{e}"
    );
    let e = bad(
        r#"{"format": 1, "effects": [{"kind": "ligament", "parameters": {"stiffness": 1, "colour": 2}}]}"#,
    );
    assert!(e.contains("colour"), "{e}");
    let e = bad(r#"{"format": 2, "effects": []}"#);
    assert!(e.starts_with("format:"), "{e}");
    let e = bad(r#"{"format": 1}"#);
    assert!(e.starts_with("effects:"), "{e}");
    let e = bad(r#"{"format": 1, "effects": [], "efects": [{"kind": "gravity"}]}"#);
    assert!(e.starts_with("efects: unknown key"), "{e}");
    // The command line's form.
    let (k, v) = Effect::parse_partial("pack:width_mm=12,center=1/2/3").unwrap();
    assert_eq!(k, EffectKind::Pack);
    assert_eq!(v["center"], vec![1.0, 2.0, 3.0]);
    assert!(Effect::parse_partial("pack:center=1/2").is_err());
    assert!(Effect::parse_partial("tides").is_err());
}

/// Supports and loads against the hyperelastic code in its small-load limit: the same springs,
/// body force, dependent-surface reaction and pack, built here from the definitions.
#[test]
fn supported_effects_match_a_direct_hyperelastic_solve_at_small_load() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let material = LinearMaterial::default();
    let (g, mag, k_bed, k_lig) = ([0.3, 0.9, -0.2], 2e-5, 0.1, 0.5);
    let pack_c = [30.0, 0.0, 15.0];
    let force = [0.5, 2.0, 0.3];
    let physics = Physics {
        effects: vec![
            Effect::new(EffectKind::BedSupport, &[("stiffness", &[k_bed])]).unwrap(),
            Effect::new(EffectKind::Ligament, &[("stiffness", &[k_lig])]).unwrap(),
            Effect::new(
                EffectKind::Gravity,
                &[("direction", &g), ("magnitude", &[mag])],
            )
            .unwrap(),
            Effect::new(
                EffectKind::Pack,
                &[
                    ("center", &pack_c),
                    ("width_mm", &[10.0]),
                    ("force_mn", &force),
                ],
            )
            .unwrap(),
        ],
    };
    let n = mesh.num_nodes();
    let u = forward(&mesh, &material, sites, &physics, &vec![0.0; 3 * n]).unwrap();
    // The reference, from the definitions.
    let fs = faces(&mesh);
    let mut area = vec![0.0; n];
    let mut normal = vec![[0.0; 3]; n];
    for (t, nn, a) in &fs {
        for &v in t {
            area[v as usize] += a / 3.0;
            for k in 0..3 {
                normal[v as usize][k] += nn[k] * a;
            }
        }
    }
    let mut springs = Vec::new();
    for v in 0..n {
        if post[v] {
            springs.push(NodeSpring::normal_tangent(
                v as u32,
                normal[v],
                k_bed * area[v],
                0.1 * k_bed * area[v],
            ));
        }
    }
    for v in 0..n {
        if falc[v] {
            springs.push(NodeSpring::isotropic(v as u32, k_lig * area[v]));
        }
    }
    let gl = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
    let gh = g.map(|x| x / gl);
    let mut f = vec![0.0; 3 * n];
    loads::add_body_force(&mut f, &mesh, gh.map(|x| mag * x));
    let s: Vec<f64> = fs
        .iter()
        .map(|(_, nn, _)| (nn[0] * gh[0] + nn[1] * gh[1] + nn[2] * gh[2]).max(0.0))
        .collect();
    let support: f64 = s.iter().zip(&fs).map(|(s, f)| s * f.2).sum();
    let c = mag * mesh.volume() / support;
    for ((t, _, a), s) in fs.iter().zip(&s) {
        for &v in t {
            for k in 0..3 {
                f[3 * v as usize + k] -= c * s * gh[k] * a / 3.0;
            }
        }
    }
    let p = mesh.nodes();
    let d2 = |q: [f64; 3]| (0..3).map(|k| (q[k] - pack_c[k]).powi(2)).sum::<f64>();
    let inside: Vec<usize> = (0..fs.len())
        .filter(|&i| fs[i].0.iter().all(|&v| d2(p[v as usize]) <= 400.0))
        .collect();
    let w = |i: usize| {
        let m = [0, 1, 2].map(|k| fs[i].0.iter().map(|&v| p[v as usize][k]).sum::<f64>() / 3.0);
        (-0.5 * d2(m) / 100.0).exp()
    };
    let total: f64 = inside.iter().map(|&i| w(i) * fs[i].2).sum();
    for &i in &inside {
        for &v in &fs[i].0 {
            for k in 0..3 {
                f[3 * v as usize + k] += force[k] * w(i) / total * fs[i].2 / 3.0;
            }
        }
    }
    // Every load is balanced by inertia relief, supported or not (checked on its own in
    // `free_floating_pressure_response_is_balanced_by_inertia_relief`).
    equilibrate(&mesh, &mut f);
    let (lam, mu) = material.lame();
    let mut hyper = HyperelasticModel::new(&mesh, LameField::Uniform(lam, mu)).unwrap();
    hyper.add_springs(&springs).unwrap();
    let (reference, _) = hyper
        .solve(&Dirichlet::new(n), &f, &small_newton())
        .unwrap();
    let peak = u.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(
        peak > 1e-4 && peak < 1e-1,
        "peak {peak}: not a small-load test"
    );
    let d = rel_diff(&u, &reference);
    assert!(d < 2e-3, "forward vs hyperelastic: relative difference {d}");
}

/// Fixation and an inclusion against the hyperelastic code: springs on the boundary nodes
/// within the radius, stiffer tets whose centroid is inside the sphere.
#[test]
fn fixation_and_inclusion_match_a_direct_hyperelastic_solve_at_small_load() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let material = LinearMaterial::default();
    let (fc, fr, fk) = ([0.0, 20.0, 15.0], 16.0, 1.0);
    let (ic, ir, ratio) = ([30.0, 20.0, 15.0], 12.0, 5.0);
    let physics = Physics {
        effects: vec![
            Effect::new(
                EffectKind::Fixation,
                &[("center", &fc), ("radius_mm", &[fr]), ("stiffness", &[fk])],
            )
            .unwrap(),
            Effect::new(
                EffectKind::Inclusion,
                &[
                    ("center", &ic),
                    ("radius_mm", &[ir]),
                    ("stiffness_ratio", &[ratio]),
                ],
            )
            .unwrap(),
        ],
    };
    let n = mesh.num_nodes();
    let mut base = vec![0.0; 3 * n];
    // A point push on the far end.
    let far = (0..n)
        .max_by(|&a, &b| mesh.nodes()[a][0].total_cmp(&mesh.nodes()[b][0]))
        .unwrap();
    loads::add_point_load(&mut base, far as u32, [0.0, -0.2, 0.1]);
    let u = forward(&mesh, &material, sites, &physics, &base).unwrap();
    let fs = faces(&mesh);
    let mut area = vec![0.0; n];
    for (t, _, a) in &fs {
        for &v in t {
            area[v as usize] += a / 3.0;
        }
    }
    let p = mesh.nodes();
    let springs: Vec<NodeSpring> = (0..n)
        .filter(|&v| {
            area[v] > 0.0 && (0..3).map(|k| (p[v][k] - fc[k]).powi(2)).sum::<f64>() <= fr * fr
        })
        .map(|v| NodeSpring::isotropic(v as u32, fk * area[v]))
        .collect();
    assert!(springs.len() >= 3);
    let (lam, mu) = material.lame();
    let mut stiff = 0;
    let per_tet: Vec<(f64, f64)> = mesh
        .tets()
        .iter()
        .map(|t| {
            let c = [0, 1, 2].map(|k| t.iter().map(|&v| p[v as usize][k]).sum::<f64>() / 4.0);
            if (0..3).map(|k| (c[k] - ic[k]).powi(2)).sum::<f64>() <= ir * ir {
                stiff += 1;
                (lam * ratio, mu * ratio)
            } else {
                (lam, mu)
            }
        })
        .collect();
    assert!(stiff > 0 && stiff < mesh.num_tets());
    let mut balanced = base.clone();
    equilibrate(&mesh, &mut balanced);
    let mut hyper = HyperelasticModel::new(&mesh, LameField::PerTet(per_tet)).unwrap();
    hyper.add_springs(&springs).unwrap();
    let (reference, _) = hyper
        .solve(&Dirichlet::new(n), &balanced, &small_newton())
        .unwrap();
    let d = rel_diff(&u, &reference);
    assert!(d < 2e-3, "forward vs hyperelastic: relative difference {d}");
    // The inclusion matters: without it the answer differs by far more than the tolerance.
    let only_fix = Physics {
        effects: vec![physics.effects[0].clone()],
    };
    let u2 = forward(&mesh, &material, sites, &only_fix, &base).unwrap();
    assert!(rel_diff(&u2, &reference) > 10.0 * d.max(1e-4));
}

/// Free-floating: the response to a pressure is a pure deformation (no rigid part, in the mass
/// inner product) that satisfies `K u = f − M a` at every node, with `a` a rigid acceleration
/// field that balances the load's force and moment.
#[test]
fn free_floating_pressure_response_is_balanced_by_inertia_relief() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let material = LinearMaterial::default();
    let physics = Physics {
        effects: vec![
            Effect::new(
                EffectKind::Pressure,
                &[("magnitude_kpa", &[0.2]), ("direction", &[0.0, -1.0, 0.0])],
            )
            .unwrap(),
        ],
    };
    let n = mesh.num_nodes();
    let u = forward(&mesh, &material, sites, &physics, &vec![0.0; 3 * n]).unwrap();
    let system = crate::fem::StiffnessSystem::linear(&mesh, &material).unwrap();
    let ku = system.apply(&u);
    // f: 0.2 kPa on the −y face only (outward normal −y), pushing in +y.
    let mut f = vec![0.0; 3 * n];
    let front: Vec<[u32; 3]> = faces(&mesh)
        .into_iter()
        .filter(|(_, nn, _)| nn[1] < -0.5)
        .map(|(t, _, _)| t)
        .collect();
    loads::add_pressure(&mut f, mesh.nodes(), &front, 0.2);
    // r = f − Ku must be M·(a + α × (x − c)): fit those six numbers by least squares and check
    // the fit is exact.
    let mass = crate::register::libr::lumped_volumes(&mesh);
    let total: f64 = mass.iter().sum();
    let c = [0, 1, 2].map(|k| {
        mesh.nodes()
            .iter()
            .zip(&mass)
            .map(|(p, m)| p[k] * m)
            .sum::<f64>()
            / total
    });
    let mut ata = nalgebra::Matrix6::<f64>::zeros();
    let mut atb = nalgebra::Vector6::<f64>::zeros();
    let rows = |i: usize| {
        let d = [0, 1, 2].map(|k| mesh.nodes()[i][k] - c[k]);
        [
            [1.0, 0.0, 0.0, 0.0, d[2], -d[1]],
            [0.0, 1.0, 0.0, -d[2], 0.0, d[0]],
            [0.0, 0.0, 1.0, d[1], -d[0], 0.0],
        ]
        .map(|r| r.map(|x| x * mass[i]))
    };
    for i in 0..n {
        let r = rows(i);
        for a in 0..3 {
            let res = f[3 * i + a] - ku[3 * i + a];
            for k in 0..6 {
                atb[k] += r[a][k] * res;
                for l in 0..6 {
                    ata[(k, l)] += r[a][k] * r[a][l];
                }
            }
        }
    }
    let coef = ata.try_inverse().unwrap() * atb;
    let mut worst: f64 = 0.0;
    let fmax = f.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    for i in 0..n {
        let r = rows(i);
        for a in 0..3 {
            let fit: f64 = (0..6).map(|k| r[a][k] * coef[k]).sum();
            worst = worst.max((f[3 * i + a] - ku[3 * i + a] - fit).abs());
        }
    }
    assert!(
        worst < 1e-8 * fmax,
        "K u ≠ f − M a: worst {worst} (load peak {fmax})"
    );
    // The net +y force is carried: the acceleration is along +y.
    assert!(coef[1] > 0.0);
    // No rigid part: Rᵀ M u = 0.
    let mut rmu = [0.0; 6];
    for i in 0..n {
        let r = rows(i);
        for a in 0..3 {
            for k in 0..6 {
                rmu[k] += r[a][k] * u[3 * i + a];
            }
        }
    }
    let scale = u.iter().fold(0.0f64, |m, x| m.max(x.abs())) * total * 100.0;
    assert!(rmu.iter().all(|x| x.abs() < 1e-9 * scale), "{rmu:?}");
}

/// The augmented basis: LIBR's columns unchanged, then each effect column is the model's
/// response to the effect's unit load scaled by `load_scale`.
#[test]
fn augmented_basis_columns_are_the_effect_responses() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let params = LibrParams {
        basis: crate::register::libr::BasisParams {
            control_points: 6,
            ..LibrParams::default().basis
        },
        fit: LibrParams::default().fit,
    };
    let gravity = Effect::new(
        EffectKind::Gravity,
        &[("direction", &[0.0, 1.0, 0.0]), ("magnitude", &[0.01])],
    )
    .unwrap();
    let physics = Physics {
        effects: vec![gravity],
    };
    let plain = LibrBasis::build(&mesh, &params).unwrap();
    let aug = LibrBasis::build_with(&mesh, &params, &physics, sites).unwrap();
    assert_eq!(aug.columns(), plain.columns() + 1);
    assert_eq!(aug.libr_columns(), plain.columns());
    assert_eq!(aug.effect_labels, vec!["gravity".to_string()]);
    assert_eq!(aug.energy_scale(), plain.energy_scale());
    let (m, mp) = (aug.columns(), plain.columns());
    for r in 0..3 * mesh.num_nodes() {
        for j in 0..mp {
            assert_eq!(aug.phi[r * m + j], plain.phi[r * mp + j]);
        }
    }
    let n = mesh.num_nodes();
    let u = forward(
        &mesh,
        &params.basis.material,
        sites,
        &physics,
        &vec![0.0; 3 * n],
    )
    .unwrap();
    let col: Vec<f64> = (0..3 * n)
        .map(|r| 0.01 * aug.phi[r * m + mp] / aug.load_scale[mp])
        .collect();
    let d = rel_diff(&col, &u);
    assert!(d < 1e-9, "effect column vs forward: {d}");
    // The npz round trip keeps the effect columns.
    let back = LibrBasis::from_npz(&aug.to_npz().unwrap()).unwrap();
    assert_eq!(back.effect_labels, aug.effect_labels);
    assert_eq!(back.physics_hash, physics.hash());
    assert_eq!(back.phi, aug.phi);
    // `nonlinear` is recognised but not carried: a clear error.
    let nl = Physics {
        effects: vec![Effect::new(EffectKind::Nonlinear, &[]).unwrap()],
    };
    let e = LibrBasis::build_with(&mesh, &params, &nl, sites)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("effects[0].kind") && e.contains("nonlinear"),
        "{e}"
    );
}

/// Bed support and gravity on the block, gravity pulling towards the bed (+y, the posterior face).
fn bed_and_gravity() -> Physics {
    Physics {
        effects: vec![
            Effect::new(EffectKind::BedSupport, &[("stiffness", &[0.08])]).unwrap(),
            Effect::new(
                EffectKind::Gravity,
                &[("direction", &[0.0, 1.0, 0.0]), ("magnitude", &[0.0104])],
            )
            .unwrap(),
        ],
    }
}

#[test]
fn carried_loads_are_balanced_by_the_supports_reactions_not_by_inertia_relief() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let material = LinearMaterial::default();
    let physics = bed_and_gravity();
    let n = mesh.num_nodes();
    // The weight, built here from the body force alone: 0.0104 mN/mm³ along +y.
    let mut f = vec![0.0; 3 * n];
    loads::add_body_force(&mut f, &mesh, [0.0, 0.0104, 0.0]);
    let solver = ModelSolver::new(&mesh, &material, sites, &physics).unwrap();
    let u = solver.solve_carried(&vec![0.0; 3 * n], &f).unwrap();
    // The springs' reactions r = −S u at their nodes.
    let geom = BoundaryGeometry::new(&mesh).unwrap();
    let mut r = vec![0.0; 3 * n];
    for s in support_springs(&mesh, &geom, sites, &physics) {
        let v = s.node as usize;
        for i in 0..3 {
            for j in 0..3 {
                r[3 * v + i] -= s.stiffness[i][j] * u[3 * v + j];
            }
        }
    }
    // Net force and moment: the reactions carry the whole weight.
    let (mut fs, mut rs, mut mf, mut mr) = ([0.0; 3], [0.0; 3], [0.0; 3], [0.0; 3]);
    for (v, p) in mesh.nodes().iter().enumerate() {
        let fv = [f[3 * v], f[3 * v + 1], f[3 * v + 2]];
        let rv = [r[3 * v], r[3 * v + 1], r[3 * v + 2]];
        let (a, b) = (
            crate::mesh::vec3::cross(*p, fv),
            crate::mesh::vec3::cross(*p, rv),
        );
        for k in 0..3 {
            fs[k] += fv[k];
            rs[k] += rv[k];
            mf[k] += a[k];
            mr[k] += b[k];
        }
    }
    let weight = fs[1];
    assert!(weight > 0.0);
    for k in 0..3 {
        assert!(
            (fs[k] + rs[k]).abs() < 1e-8 * weight,
            "force {k}: {fs:?} vs {rs:?}"
        );
        assert!(
            (mf[k] + mr[k]).abs() < 1e-6 * weight * 60.0,
            "moment {k}: {mf:?} vs {mr:?}"
        );
    }
    // The elastic body is in equilibrium under the load and the reactions alone: K u = f + r at
    // every node (no inertia-relief body force left over).
    let ku = crate::fem::StiffnessSystem::linear(&mesh, &material)
        .unwrap()
        .apply(&u);
    let res: Vec<f64> = ku
        .iter()
        .zip(&f)
        .zip(&r)
        .map(|((k, f), r)| k - f - r)
        .collect();
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    assert!(
        norm(&res) < 1e-10 * norm(&r),
        "K u − f − r: {:.2e} against |r| {:.2e}",
        norm(&res),
        norm(&r)
    );
}

#[test]
fn carry_relief_is_forward_and_carry_supports_differs_and_needs_a_support() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let material = LinearMaterial::default();
    let physics = bed_and_gravity();
    let n = mesh.num_nodes();
    let base = vec![0.0; 3 * n];
    let relief = forward(&mesh, &material, sites, &physics, &base).unwrap();
    assert_eq!(
        forward_with(&mesh, &material, sites, &physics, &base, Carry::Relief).unwrap(),
        relief
    );
    let carried = forward_with(&mesh, &material, sites, &physics, &base, Carry::Supports).unwrap();
    // Its rigid part is removed: the mass-weighted mean displacement is zero.
    let mass = crate::register::libr::lumped_volumes(&mesh);
    let total: f64 = mass.iter().sum();
    for k in 0..3 {
        let mean: f64 = (0..n).map(|v| mass[v] * carried[3 * v + k]).sum::<f64>() / total;
        assert!(mean.abs() < 1e-9, "rigid part left along {k}: {mean}");
    }
    // The weight pressed into the bed deforms the organ otherwise than a weight resting on its
    // own lower surface.
    let rms = |u: &[f64]| (u.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt();
    let d: Vec<f64> = carried.iter().zip(&relief).map(|(a, b)| a - b).collect();
    eprintln!(
        "bed + gravity: carried {:.3} mm RMS, relief {:.3} mm RMS, difference {:.3} mm",
        rms(&carried),
        rms(&relief),
        rms(&d)
    );
    assert!(rms(&d) > 0.1 * rms(&relief), "carried ≈ relief");
    // A load with nothing to carry it is refused, naming what is missing.
    let free = Physics {
        effects: vec![physics.effects[1].clone()],
    };
    let e = forward_with(&mesh, &material, sites, &free, &base, Carry::Supports)
        .unwrap_err()
        .to_string();
    assert!(e.contains("needs a support"), "{e}");
}

/// A supported augmented basis carries its load columns as the truth does: the gravity column,
/// scaled to the effect's magnitude, is [`forward_with`]`(Carry::Supports)` (both with their
/// rigid part removed: the organ's motion on its supports is the registration's pose), and
/// [`forward_supported_parts`] adds up to it; the physics' hash marks loads carried so.
#[test]
fn supported_basis_columns_are_the_carried_responses() {
    let mesh = block();
    let (post, falc) = flags(&mesh);
    let sites = Sites {
        posterior: &post,
        falciform: &falc,
    };
    let params = LibrParams {
        basis: crate::register::libr::BasisParams {
            control_points: 6,
            ..LibrParams::default().basis
        },
        fit: LibrParams::default().fit,
    };
    let physics = bed_and_gravity();
    let n = mesh.num_nodes();
    let aug = LibrBasis::build_with(&mesh, &params, &physics, sites).unwrap();
    assert_eq!(aug.effect_labels, vec!["gravity".to_string()]);
    let (m, j) = (aug.columns(), aug.columns() - 1);
    let col: Vec<f64> = (0..3 * n)
        .map(|r| 0.0104 * aug.phi[r * m + j] / aug.load_scale[j])
        .collect();
    // The effect column's mass-weighted mean displacement is zero (no rigid translation).
    let mass = crate::register::libr::lumped_volumes(&mesh);
    let total: f64 = mass.iter().sum();
    for k in 0..3 {
        let mean: f64 = (0..n).map(|v| mass[v] * col[3 * v + k]).sum::<f64>() / total;
        assert!(mean.abs() < 1e-9, "rigid part left along {k}: {mean}");
    }
    let base = vec![0.0; 3 * n];
    let want = forward_with(
        &mesh,
        &params.basis.material,
        sites,
        &physics,
        &base,
        Carry::Supports,
    )
    .unwrap();
    let d = rel_diff(&col, &want);
    assert!(d < 1e-8, "carried column vs forward_with: {d}");
    let [b, e] =
        forward_supported_parts(&mesh, &params.basis.material, sites, &physics, &base).unwrap();
    assert!(
        b.iter().all(|x| x.abs() < 1e-12),
        "no base load, no base part"
    );
    assert!(rel_diff(&e, &want) < 1e-10);
    let alone = Physics {
        effects: vec![physics.effects[0].clone()],
    };
    assert_ne!(physics.hash(), alone.hash());
    assert_eq!(alone.hash().len(), 16);
}
