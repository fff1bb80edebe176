//! LIBR basis and fit (`librplus::register::libr`), checked against facts computed here
//! independently: the farthest-point property of the control points, each column solving the
//! free-body problem `K φ = s f + (rigid-body inertial load)` for a Gaussian traction recomputed
//! here, `E = ΦᵀKΦ` by separate sparse products, exact recovery of a field in the span of the
//! basis plus a known rigid motion from dense noiseless matches, shrinkage under regularization,
//! the disk cache (bit-exact round trip, keys, rebuild of a truncated file) and garbage inputs.
//!
//! Meshes: a jittered 60 × 40 × 30 mm box (fast), and `assets/livers/sofa_liver.vtk` meshed with
//! 10 mm tets (timings are printed; run with `--nocapture` to see them).

mod common;

use librplus::fem::{LinearMaterial, StiffnessSystem, loads};
use librplus::mesh::TetMesh;
use librplus::mesh::procedural::box_mesh;
use librplus::mesh::rigid::Rigid;
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::register::libr::{
    LibrBasis, LibrParams, LinearRefit, LoadWidth, RunLimits, fit_step, linearised_refit,
    mesh_hash, settled, solve, solve_with_limits,
};
use librplus::register::{Match, RegisterError};
use librplus::util::SplitMix64;
use nalgebra::{DMatrix, DVector};
use std::sync::OnceLock;
use std::time::Instant;

fn box_params() -> LibrParams {
    let mut p = LibrParams::default();
    p.basis.control_points = 24;
    p.basis.load_width = LoadWidth::Spacing(1.25);
    p
}

/// The default basis with an almost unregularised fit run to a tight tolerance (exactness checks).
fn exact_fit() -> LibrParams {
    let mut p = LibrParams::default();
    p.fit.regularization = 1e-9;
    p.fit.tolerance_mm = 1e-7;
    p.fit.max_iterations = 30;
    p
}

fn boxed() -> &'static (TetMesh, LibrBasis) {
    static B: OnceLock<(TetMesh, LibrBasis)> = OnceLock::new();
    B.get_or_init(|| {
        let mesh = box_mesh([60.0, 40.0, 30.0], [12, 8, 6], 0.3);
        let basis = LibrBasis::build(&mesh, &box_params()).unwrap();
        (mesh, basis)
    })
}

fn liver() -> &'static TetMesh {
    static L: OnceLock<TetMesh> = OnceLock::new();
    L.get_or_init(|| {
        let s = common::sofa_liver_surface();
        tetrahedralize(&s, &TetraParams::with_edge(10.0)).unwrap()
    })
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn norm(a: [f64; 3]) -> f64 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn column(b: &LibrBasis, j: usize) -> Vec<f64> {
    let m = b.columns();
    (0..3 * b.nodes).map(|r| b.phi[r * m + j]).collect()
}

/// Boundary area by direct summation.
fn boundary_area(mesh: &TetMesh) -> f64 {
    let bd = mesh.boundary().unwrap();
    bd.triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|v| mesh.nodes()[v as usize]);
            0.5 * norm(cross(sub(b, a), sub(c, a)))
        })
        .sum()
}

/// Dense matches: for each boundary triangle, `per` points at fixed barycentric coordinates.
fn triangle_matches(mesh: &TetMesh, per: usize, rng: &mut SplitMix64) -> Vec<Match> {
    let bd = mesh.boundary().unwrap();
    let mut out = Vec::new();
    for t in &bd.triangles {
        for _ in 0..per {
            let (mut r1, mut r2) = (rng.next_f64(), rng.next_f64());
            if r1 + r2 > 1.0 {
                r1 = 1.0 - r1;
                r2 = 1.0 - r2;
            }
            let bary = [1.0 - r1 - r2, r1, r2, 0.0];
            let p = t.map(|v| mesh.nodes()[v as usize]);
            let anchor =
                [0, 1, 2].map(|a| bary[0] * p[0][a] + bary[1] * p[1][a] + bary[2] * p[2][a]);
            out.push(Match {
                point: out.len(),
                anchor,
                nodes: [t[0], t[1], t[2], t[0]],
                bary,
                weight: 1.0,
                normal: [0.0; 3],
            });
        }
    }
    out
}

fn random_alpha(m: usize, amp: f64, rng: &mut SplitMix64) -> Vec<f64> {
    (0..m).map(|_| amp * rng.normal()).collect()
}

#[test]
fn control_points_are_spread_and_deterministic() {
    let (mesh, basis) = boxed();
    let k = basis.control_nodes.len();
    assert_eq!(k, 24);
    let bd = mesh.boundary().unwrap();
    let p = |v: u32| mesh.nodes()[v as usize];
    for &c in &basis.control_nodes {
        assert!(
            bd.nodes.binary_search(&c).is_ok(),
            "control node {c} not on the boundary"
        );
    }
    let mut min_pair = f64::INFINITY;
    for (i, &a) in basis.control_nodes.iter().enumerate() {
        for &b in &basis.control_nodes[i + 1..] {
            min_pair = min_pair.min(norm(sub(p(a), p(b))));
        }
    }
    // Covering radius: farthest boundary node from its nearest control point.
    let cover = bd
        .nodes
        .iter()
        .map(|&v| {
            basis
                .control_nodes
                .iter()
                .map(|&c| norm(sub(p(v), p(c))))
                .fold(f64::INFINITY, f64::min)
        })
        .fold(0.0, f64::max);
    let spacing = (2.0 * boundary_area(mesh) / (3f64.sqrt() * k as f64)).sqrt();
    println!(
        "box: K = {k}, spacing {spacing:.2} mm, min pair {min_pair:.2} mm, cover {cover:.2} mm, σ = {:.2} mm",
        basis.load_width_mm
    );
    // Farthest-point sampling: every pair is at least the final covering radius apart.
    assert!(
        min_pair >= cover - 1e-9,
        "min pair {min_pair} < cover {cover}"
    );
    assert!(
        min_pair >= 0.5 * spacing,
        "min pair {min_pair} vs spacing {spacing}"
    );
    assert!(cover <= 1.5 * spacing, "cover {cover} vs spacing {spacing}");
    assert!((basis.load_width_mm - 1.25 * spacing).abs() < 1e-9 * spacing);
    let again = LibrBasis::build(mesh, &box_params()).unwrap();
    assert_eq!(again.control_nodes, basis.control_nodes);
    assert!(
        again
            .phi
            .iter()
            .zip(&basis.phi)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
    let other = LibrBasis::build(
        mesh,
        &LibrParams {
            basis: librplus::register::libr::BasisParams {
                seed: 7,
                ..box_params().basis
            },
            fit: box_params().fit,
        },
    )
    .unwrap();
    assert_ne!(other.control_nodes[0], basis.control_nodes[0]);
}

#[test]
fn columns_solve_the_free_body_problem_and_are_localized() {
    let (mesh, basis) = boxed();
    let n = mesh.num_nodes();
    let nodes = mesh.nodes();
    let system = StiffnessSystem::linear(mesh, &LinearMaterial::default()).unwrap();
    let bd = mesh.boundary().unwrap();
    // Lumped volumes and area-weighted vertex normals, recomputed here.
    let mut mass = vec![0.0; n];
    for (t, tet) in mesh.tets().iter().enumerate() {
        for &v in tet {
            mass[v as usize] += mesh.tet_volume(t).abs() / 4.0;
        }
    }
    let sigma = basis.load_width_mm;
    let m = basis.columns();
    for j in (0..m).step_by(5) {
        let c = basis.control_nodes[j / 3];
        let axis = j % 3;
        let pc = nodes[c as usize];
        let mut nc = [0.0; 3];
        for t in bd.triangles.iter().filter(|t| t.contains(&c)) {
            let [a, b, d] = t.map(|v| nodes[v as usize]);
            let x = cross(sub(b, a), sub(d, a));
            for k in 0..3 {
                nc[k] += x[k];
            }
        }
        let l = norm(nc);
        nc = nc.map(|x| x / l);
        let traction: Vec<[f64; 3]> = bd
            .triangles
            .iter()
            .map(|t| {
                let [a, b, d] = t.map(|v| nodes[v as usize]);
                let x = [0, 1, 2].map(|k| (a[k] + b[k] + d[k]) / 3.0);
                let nn = cross(sub(b, a), sub(d, a));
                let cosang = (nn[0] * nc[0] + nn[1] * nc[1] + nn[2] * nc[2]) / norm(nn);
                let g = (-norm(sub(x, pc)).powi(2) / (2.0 * sigma * sigma)).exp() * cosang.max(0.0);
                let mut v = [0.0; 3];
                v[axis] = g;
                v
            })
            .collect();
        let mut f = vec![0.0; 3 * n];
        loads::add_traction(&mut f, nodes, &bd.triangles, &traction);
        // K φ = s f + M (a + β × x): fit s, a, β (7 unknowns) by least squares.
        let phi = column(basis, j);
        let kphi = system.apply(&phi);
        let mut a = DMatrix::<f64>::zeros(3 * n, 7);
        for i in 0..n {
            let x = nodes[i];
            for ax in 0..3 {
                let r = 3 * i + ax;
                a[(r, 0)] = f[r];
                a[(r, 1 + ax)] = mass[i];
                for k in 0..3 {
                    let mut ek = [0.0; 3];
                    ek[k] = 1.0;
                    a[(r, 4 + k)] = mass[i] * cross(ek, x)[ax];
                }
            }
        }
        let b = DVector::from_vec(kphi.clone());
        let sol = a.clone().svd(true, true).solve(&b, 1e-14).unwrap();
        let res = (&a * &sol - &b).norm() / b.norm();
        assert!(res < 1e-8, "column {j}: relative residual {res:e}");
        // s is the recorded peak traction for 1 mm, and the force is not itself rigid-body.
        let s = sol[0];
        assert!(
            (s - basis.load_scale[j]).abs() <= 1e-6 * s.abs(),
            "column {j}: s = {s}, load_scale = {}",
            basis.load_scale[j]
        );
        // No rigid part: Σ m_i φ_i = 0 and Σ m_i x_i × φ_i = 0 (relative to Σ m |x||φ|).
        let (mut lin, mut ang, mut scale) = ([0.0; 3], [0.0; 3], 0.0);
        for i in 0..n {
            let u = [phi[3 * i], phi[3 * i + 1], phi[3 * i + 2]];
            let xu = cross(nodes[i], u);
            for k in 0..3 {
                lin[k] += mass[i] * u[k];
                ang[k] += mass[i] * xu[k];
            }
            scale += mass[i] * norm(u) * (1.0 + norm(nodes[i]));
        }
        assert!(norm(lin) < 1e-10 * scale && norm(ang) < 1e-10 * scale);
        // Peak 1 mm, reached near the control point; far from it the response is smaller.
        let disp = |i: usize| norm([phi[3 * i], phi[3 * i + 1], phi[3 * i + 2]]);
        let peak_node = (0..n).max_by(|&a, &b| disp(a).total_cmp(&disp(b))).unwrap();
        assert!((disp(peak_node) - 1.0).abs() < 1e-12);
        let d_peak = norm(sub(nodes[peak_node], pc));
        let far = (0..n)
            .filter(|&i| norm(sub(nodes[i], pc)) > 2.5 * sigma)
            .map(disp)
            .fold(0.0, f64::max);
        if j == 0 {
            println!(
                "column 0: peak at {d_peak:.1} mm from its control point, max beyond 2.5σ {far:.3} mm, residual {res:.1e}"
            );
        }
        assert!(
            d_peak <= 1.0 * sigma,
            "column {j}: peak {d_peak} mm away, σ = {sigma}"
        );
        assert!(far < 0.6, "column {j}: {far} mm beyond 2.5σ");
    }
}

#[test]
fn energy_matrix_is_phi_t_k_phi_symmetric_positive_definite() {
    let (mesh, basis) = boxed();
    let m = basis.columns();
    let system = StiffnessSystem::linear(mesh, &LinearMaterial::default()).unwrap();
    let cols: Vec<Vec<f64>> = (0..m).map(|j| column(basis, j)).collect();
    let kcols: Vec<Vec<f64>> = cols.iter().map(|c| system.apply(c)).collect();
    let mut worst = 0.0f64;
    let diag_max = (0..m).map(|i| basis.energy[i * m + i]).fold(0.0, f64::max);
    let mut e = DMatrix::<f64>::zeros(m, m);
    for i in 0..m {
        for j in 0..m {
            let v: f64 = cols[i].iter().zip(&kcols[j]).map(|(a, b)| a * b).sum();
            worst = worst.max((v - basis.energy[i * m + j]).abs());
            assert_eq!(basis.energy[i * m + j], basis.energy[j * m + i]);
            e[(i, j)] = basis.energy[i * m + j];
        }
    }
    assert!(
        worst <= 1e-10 * diag_max,
        "E differs from ΦᵀKΦ by {worst:e}"
    );
    let eig = e.symmetric_eigenvalues();
    let (lo, hi) = (eig.min(), eig.max());
    println!("box E: eigenvalues in [{lo:.3e}, {hi:.3e}] mN·mm/mm²");
    assert!(lo > 1e-8 * hi, "E not positive definite: {lo:e} .. {hi:e}");
    // Strain energy from E equals ½ uᵀKu of the displacement.
    let mut rng = SplitMix64::new(3);
    let alpha = random_alpha(m, 1.0, &mut rng);
    let u = basis.displacement(&alpha);
    let direct = system.energy(&u);
    assert!((basis.strain_energy(&alpha) - direct).abs() < 1e-9 * direct);
}

/// Fits fixed dense matches to a field in the span of the basis plus a rigid motion.
fn exactness(mesh: &TetMesh, basis: &LibrBasis, per: usize, amp: f64) -> (f64, f64, usize) {
    let mut rng = SplitMix64::new(11);
    let alpha_true = random_alpha(basis.columns(), amp, &mut rng);
    let u_true = basis.displacement(&alpha_true);
    let truth = Rigid::from_axis_angle([0.3, -1.0, 0.5], 4f64.to_radians(), [6.0, -4.0, 3.0]);
    let matches = triangle_matches(mesh, per, &mut rng);
    let measured: Vec<[f64; 3]> = matches
        .iter()
        .map(|m| truth.apply(m.model_point(&u_true)))
        .collect();
    let params = exact_fit();
    let sol = solve(
        mesh,
        basis,
        &params,
        &measured,
        &Rigid::identity(),
        |_, _| Ok(matches.clone()),
    )
    .unwrap();
    let n = mesh.num_nodes();
    let mut err = 0.0;
    for (i, x) in mesh.nodes().iter().enumerate() {
        let want = truth.apply([0, 1, 2].map(|a| x[a] + u_true[3 * i + a]));
        let got = sol
            .image_to_physical
            .apply([0, 1, 2].map(|a| x[a] + sol.u[3 * i + a]));
        err += norm(sub(want, got)) / n as f64;
    }
    let umax = (0..n)
        .map(|i| norm([u_true[3 * i], u_true[3 * i + 1], u_true[3 * i + 2]]))
        .fold(0.0, f64::max);
    println!(
        "exactness: {} matches, max |u*| {umax:.2} mm, mean node error {err:.2e} mm, {} iterations, rms history {:?}",
        matches.len(),
        sol.info.iterations,
        sol.info.rms_history_mm
    );
    assert!(sol.info.converged, "{:?}", sol.info);
    assert!(sol.info.settled, "a converged fit is settled");
    (err, umax, sol.info.iterations)
}

#[test]
fn recovers_a_field_in_the_span_plus_rigid_motion() {
    let (mesh, basis) = boxed();
    let (err, umax, _) = exactness(mesh, basis, 2, 1.0);
    assert!(
        umax > 2.0,
        "the test field is too small to mean anything: {umax}"
    );
    assert!(err <= 1e-3, "mean node error {err} mm");
}

/// Mean distance (mm) between the nodes placed by two (transform, displacement) pairs.
fn mean_node_gap(mesh: &TetMesh, a: (&Rigid, &[f64]), b: (&Rigid, &[f64])) -> f64 {
    let n = mesh.num_nodes();
    mesh.nodes()
        .iter()
        .enumerate()
        .map(|(i, x)| {
            let p = a.0.apply([0, 1, 2].map(|k| x[k] + a.1[3 * i + k]));
            let q = b.0.apply([0, 1, 2].map(|k| x[k] + b.1[3 * i + k]));
            norm(sub(p, q))
        })
        .sum::<f64>()
        / n as f64
}

#[test]
fn a_refit_keeps_its_offset_and_fits_only_what_it_leaves() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(5);
    // An offset the 24 smooth elastic modes cannot reproduce: ripples of a few mm.
    let pi = std::f64::consts::PI;
    let offset: Vec<f64> = mesh
        .nodes()
        .iter()
        .flat_map(|x| {
            let (a, b) = (
                (3.0 * pi * x[0] / 60.0).sin(),
                (2.0 * pi * x[1] / 40.0).sin(),
            );
            [0.5 * b, 0.0, 3.0 * a * b]
        })
        .collect();
    let alpha_true = random_alpha(basis.columns(), 1.0, &mut rng);
    let phi = basis.displacement(&alpha_true);
    let u_true: Vec<f64> = offset.iter().zip(&phi).map(|(a, b)| a + b).collect();
    let truth = Rigid::from_axis_angle([0.3, -1.0, 0.5], 3f64.to_radians(), [4.0, -2.0, 3.0]);
    let matches = triangle_matches(mesh, 2, &mut rng);
    let measured: Vec<[f64; 3]> = matches
        .iter()
        .map(|m| truth.apply(m.model_point(&u_true)))
        .collect();
    let params = exact_fit();
    // LIBR on `data` (fixed matches, identity start), from `offset`.
    let fit = |data: &[[f64; 3]], offset: Option<&[f64]>| {
        solve_with_limits(
            mesh,
            basis,
            &params,
            data,
            &Rigid::identity(),
            RunLimits {
                offset,
                ..RunLimits::default()
            },
            |_, _| Ok(matches.clone()),
        )
    };
    let with = fit(&measured, Some(&offset)).unwrap();
    let without = fit(&measured, None).unwrap();
    let e_with = mean_node_gap(mesh, (&truth, &u_true), (&with.image_to_physical, &with.u));
    let e_without = mean_node_gap(
        mesh,
        (&truth, &u_true),
        (&without.image_to_physical, &without.u),
    );
    println!("offset refit: node error {e_with:.2e} mm; plain LIBR: {e_without:.3} mm");
    assert!(
        e_with <= 1e-3,
        "with the offset: mean node error {e_with} mm"
    );
    assert!(
        e_without >= 0.3,
        "the offset should not be in the basis's span (plain LIBR error {e_without} mm)"
    );
    // The weights are the field's own: Φα is what the offset left.
    let da = with
        .alpha
        .iter()
        .zip(&alpha_true)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    let amax = alpha_true.iter().map(|a| a.abs()).fold(0.0, f64::max);
    assert!(da <= 1e-3 * amax, "weights off by {da} (largest {amax})");
    // Data the offset already explains: the refit changes nothing.
    let explained: Vec<[f64; 3]> = matches.iter().map(|m| m.model_point(&offset)).collect();
    let still = fit(&explained, Some(&offset)).unwrap();
    let moved = mean_node_gap(
        mesh,
        (&Rigid::identity(), &offset),
        (&still.image_to_physical, &still.u),
    );
    assert!(
        moved <= 1e-6,
        "the refit moved explained data by {moved} mm"
    );
    // A wrong-sized or non-finite offset is an error naming it.
    for bad in [vec![0.0; 5], {
        let mut v = offset.clone();
        v[7] = f64::NAN;
        v
    }] {
        let e = fit(&measured, Some(&bad)).unwrap_err();
        assert!(e.to_string().contains("offset"), "{e}");
    }
}

#[test]
fn regularization_shrinks_the_weights() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(5);
    let alpha_true = random_alpha(basis.columns(), 2.0, &mut rng);
    let u_true = basis.displacement(&alpha_true);
    // Sparse data on the top face only (z = 30), with noise.
    let matches: Vec<Match> = triangle_matches(mesh, 1, &mut rng)
        .into_iter()
        .filter(|m| m.anchor[2] > 29.999)
        .enumerate()
        .map(|(i, m)| Match { point: i, ..m })
        .collect();
    let targets: Vec<[f64; 3]> = matches
        .iter()
        .map(|m| m.model_point(&u_true).map(|x| x + 0.3 * rng.normal()))
        .collect();
    let mut last_energy = f64::INFINITY;
    let mut last_rms = 0.0;
    for lambda in [1e-6, 1e-3, 1e-1, 10.0, 1e3] {
        let params = LibrParams {
            basis: box_params().basis,
            fit: librplus::register::libr::FitParams {
                regularization: lambda,
                ..box_params().fit
            },
        };
        let s = fit_step(basis, &matches, &targets, &params).unwrap();
        println!(
            "λ = {lambda:e}: energy {:.4e} µJ, linear rms {:.3} mm, rms {:.3} mm, |α| {:.3}",
            s.strain_energy_uj,
            s.linear_rms_mm,
            s.rms_mm,
            s.alpha.iter().map(|a| a * a).sum::<f64>().sqrt()
        );
        assert!(
            s.strain_energy_uj < last_energy,
            "energy did not shrink at λ = {lambda}"
        );
        assert!(
            s.linear_rms_mm >= last_rms - 1e-12,
            "misfit fell at λ = {lambda}"
        );
        last_energy = s.strain_energy_uj;
        last_rms = s.linear_rms_mm;
    }
    // Very strong regularization: the weights vanish and only the rigid correction remains.
    let s = fit_step(
        basis,
        &matches,
        &targets,
        &LibrParams {
            basis: box_params().basis,
            fit: librplus::register::libr::FitParams {
                regularization: 1e9,
                ..box_params().fit
            },
        },
    )
    .unwrap();
    assert!(
        s.alpha.iter().all(|a| a.abs() < 1e-4),
        "{:?}",
        &s.alpha[..6]
    );
}

#[test]
fn cache_round_trips_and_rebuilds_bad_files() {
    let mesh = box_mesh([30.0, 20.0, 20.0], [6, 4, 4], 0.3);
    let params = LibrParams {
        basis: librplus::register::libr::BasisParams {
            control_points: 10,
            ..LibrParams::default().basis
        },
        fit: LibrParams::default().fit,
    };
    let dir = tempfile::tempdir().unwrap();
    let (built, cached) = LibrBasis::load_or_build(&mesh, &params, dir.path()).unwrap();
    assert!(!cached);
    let path = LibrBasis::cache_path(&mesh, &params, dir.path());
    assert!(path.exists());
    let name = path.file_name().unwrap().to_str().unwrap().to_string();
    assert!(name.contains(&mesh_hash(&mesh)) && name.contains(&params.basis_hash()));
    let (loaded, cached) = LibrBasis::load_or_build(&mesh, &params, dir.path()).unwrap();
    assert!(cached);
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&loaded.phi), bits(&built.phi));
    assert_eq!(bits(&loaded.energy), bits(&built.energy));
    assert_eq!(bits(&loaded.load_scale), bits(&built.load_scale));
    assert_eq!(loaded.control_nodes, built.control_nodes);
    assert_eq!(
        loaded.load_width_mm.to_bits(),
        built.load_width_mm.to_bits()
    );
    assert_eq!(
        (&loaded.mesh_hash, &loaded.params_hash),
        (&built.mesh_hash, &built.params_hash)
    );
    // The fit's parameters do not change the key; the basis's do; so does the mesh.
    let fit_only = LibrParams {
        basis: params.basis,
        fit: librplus::register::libr::FitParams {
            regularization: 5.0,
            max_iterations: 3,
            ..params.fit
        },
    };
    assert_eq!(fit_only.basis_hash(), params.basis_hash());
    for other in [
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                control_points: 11,
                ..params.basis
            },
            fit: params.fit,
        },
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                seed: 1,
                ..params.basis
            },
            fit: params.fit,
        },
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                load_width: LoadWidth::Mm(8.0),
                ..params.basis
            },
            fit: params.fit,
        },
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                material: LinearMaterial::new(5.0, 0.49),
                ..params.basis
            },
            fit: params.fit,
        },
    ] {
        assert_ne!(other.basis_hash(), params.basis_hash(), "{other:?}");
    }
    let moved = box_mesh([30.0, 20.0, 20.1], [6, 4, 4], 0.3);
    assert_ne!(mesh_hash(&moved), mesh_hash(&mesh));
    // A truncated file is rebuilt (and rewritten whole).
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let (again, cached) = LibrBasis::load_or_build(&mesh, &params, dir.path()).unwrap();
    assert!(!cached);
    assert_eq!(bits(&again.phi), bits(&built.phi));
    assert_eq!(std::fs::read(&path).unwrap(), bytes);
    // A file of another mesh under this name is not used.
    let other_mesh = box_mesh([30.0, 20.0, 20.0], [6, 4, 4], 0.25);
    let foreign = LibrBasis::build(&other_mesh, &params)
        .unwrap()
        .to_npz()
        .unwrap();
    std::fs::write(&path, foreign).unwrap();
    let (again, cached) = LibrBasis::load_or_build(&mesh, &params, dir.path()).unwrap();
    assert!(!cached);
    assert_eq!(bits(&again.phi), bits(&built.phi));
}

#[test]
fn garbage_inputs_are_errors() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(1);
    let matches = triangle_matches(mesh, 1, &mut rng);
    let targets: Vec<[f64; 3]> = matches.iter().map(|m| m.anchor).collect();
    let p = box_params();
    let err = |m: &[Match], t: &[[f64; 3]], p: &LibrParams| {
        fit_step(basis, m, t, p).unwrap_err().to_string()
    };
    assert!(matches!(
        fit_step(basis, &[], &targets, &p),
        Err(RegisterError::TooFewMatches { matched: 0 })
    ));
    let mut bad_t = targets.clone();
    bad_t[4][1] = f64::NAN;
    assert!(err(&matches, &bad_t, &p).contains("not finite"));
    assert!(err(&matches[..2], &targets, &p).contains("at least 3"));
    let mut m2 = matches.clone();
    m2[0].nodes[1] = mesh.num_nodes() as u32;
    assert!(err(&m2, &targets, &p).contains("out of range"));
    let mut m3 = matches.clone();
    m3[1].weight = -1.0;
    assert!(err(&m3, &targets, &p).contains("weight"));
    let mut m4 = matches.clone();
    m4[2].point = targets.len();
    assert!(err(&m4, &targets, &p).contains("point"));
    let neg = LibrParams {
        basis: p.basis,
        fit: librplus::register::libr::FitParams {
            regularization: -1.0,
            ..p.fit
        },
    };
    assert!(err(&matches, &targets, &neg).contains("regularization"));
    // Three matches at the same point cannot fix a rotation; without λ nothing holds α.
    let same: Vec<Match> = (0..3).map(|_| matches[0]).collect();
    let zero = LibrParams {
        basis: p.basis,
        fit: librplus::register::libr::FitParams {
            regularization: 0.0,
            ..p.fit
        },
    };
    assert!(err(&same, &targets, &zero).contains("singular"));
    for bad in [
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                control_points: 0,
                ..p.basis
            },
            fit: p.fit,
        },
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                load_width: LoadWidth::Mm(-1.0),
                ..p.basis
            },
            fit: p.fit,
        },
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                material: LinearMaterial::new(0.0, 0.45),
                ..p.basis
            },
            fit: p.fit,
        },
        LibrParams {
            basis: librplus::register::libr::BasisParams {
                control_points: 100_000,
                ..p.basis
            },
            fit: p.fit,
        },
    ] {
        assert!(LibrBasis::build(mesh, &bad).is_err(), "{bad:?}");
    }
}

#[test]
fn liver_basis_timings_and_exactness() {
    let mesh = liver();
    let params = LibrParams::default();
    let t = Instant::now();
    let basis = LibrBasis::build(mesh, &params).unwrap();
    let build_s = t.elapsed().as_secs_f64();
    println!(
        "liver: {} nodes, {} tets, {} columns, σ = {:.1} mm; build {build_s:.2} s ({:?})",
        mesh.num_nodes(),
        mesh.num_tets(),
        basis.columns(),
        basis.load_width_mm,
        basis.timings
    );
    // One step on ~1 match per boundary triangle, timed (dev profile: an upper bound).
    let mut rng = SplitMix64::new(2);
    let matches = triangle_matches(mesh, 1, &mut rng);
    let targets: Vec<[f64; 3]> = matches.iter().map(|m| m.anchor).collect();
    let mut times = Vec::new();
    let mut stages = None;
    for _ in 0..5 {
        let t = Instant::now();
        stages = Some(
            fit_step(&basis, &matches, &targets, &params)
                .unwrap()
                .timings,
        );
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    println!(
        "liver fit_step, {} matches: median {:.1} ms (last: {:?})",
        matches.len(),
        times[2],
        stages.unwrap()
    );
    let (err, umax, _) = exactness(mesh, &basis, 1, 1.0);
    assert!(umax > 2.0);
    assert!(err <= 0.01, "mean node error {err} mm");
}

#[test]
fn the_linearised_refit_predicts_the_refits_first_step() {
    let (mesh, basis) = boxed();
    let mut rng = SplitMix64::new(11);
    let n = basis.nodes;
    let (m, p) = (basis.columns(), basis.columns() + 6);
    // Matches, half point-to-plane (a random unit normal each), data from a deformed and
    // slightly moved truth; the refit starts from an offset outside the basis's span.
    let mut matches = triangle_matches(mesh, 2, &mut rng);
    for mt in matches.iter_mut().step_by(2) {
        let v = [rng.normal(), rng.normal(), rng.normal()];
        let l = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        mt.normal = v.map(|x| x / l);
    }
    let u_true = basis.displacement(&random_alpha(m, 1.0, &mut rng));
    // The refit starts where LIBR converged: the rotation left to correct is small (its product
    // with c is what the first-order model leaves out).
    let truth = Rigid::from_axis_angle([0.3, -1.0, 0.5], 0.1f64.to_radians(), [1.0, -2.0, 0.5]);
    let measured: Vec<[f64; 3]> = matches
        .iter()
        .map(|mt| truth.apply(mt.model_point(&u_true)))
        .collect();
    let offset: Vec<f64> = mesh
        .nodes()
        .iter()
        .flat_map(|x| [0.5 * (x[1] / 15.0).sin(), 0.0, 0.8 * (x[0] / 20.0).cos()])
        .collect();
    let params = LibrParams {
        basis: LibrParams::default().basis,
        fit: librplus::register::libr::FitParams {
            max_iterations: 1,
            ..LibrParams::default().fit
        },
    };
    // One refit iteration from `o` with the matches held: node positions in the start frame.
    let step = |o: &[f64]| {
        let s = solve_with_limits(
            mesh,
            basis,
            &params,
            &measured,
            &Rigid::identity(),
            RunLimits {
                offset: Some(o),
                ..RunLimits::default()
            },
            |_, _| Ok(matches.clone()),
        )
        .unwrap();
        let pos: Vec<f64> = mesh
            .nodes()
            .iter()
            .enumerate()
            .flat_map(|(i, x)| {
                s.image_to_physical
                    .apply([0, 1, 2].map(|a| x[a] + s.u[3 * i + a]))
            })
            .collect();
        (s, pos)
    };
    let centre = [20.0, -5.0, 12.0];
    let lin = linearised_refit(basis, mesh, &matches, &measured, &offset, centre, &params).unwrap();
    assert_eq!(lin.columns, p);
    // The response to a change c: −G·K·Gᵀ·Dᵀ·D·c.
    let g = LinearRefit::modes(basis, mesh, centre);
    let response = |c: &[f64]| -> (Vec<f64>, Vec<f64>) {
        let mut dc = vec![0.0; lin.rows];
        for &(r, col, v) in &lin.d {
            dc[r] += v * c[col];
        }
        let mut w = vec![0.0; 3 * n];
        for &(r, col, v) in &lin.d {
            w[col] += v * dc[r];
        }
        let gw: Vec<f64> = (0..p)
            .map(|j| (0..3 * n).map(|i| g[i * p + j] * w[i]).sum())
            .collect();
        let theta: Vec<f64> = (0..p)
            .map(|i| -(0..p).map(|j| lin.gain[i * p + j] * gw[j]).sum::<f64>())
            .collect();
        let out = (0..3 * n)
            .map(|i| (0..p).map(|j| g[i * p + j] * theta[j]).sum())
            .collect();
        (out, theta)
    };
    let (s0, p0) = step(&offset);
    // The step at c = 0: step0 is where the refit moves the offset's shape, to first order in
    // its small rotation.
    let rest: Vec<f64> = mesh
        .nodes()
        .iter()
        .enumerate()
        .flat_map(|(i, x)| [0, 1, 2].map(|a| x[a] + offset[3 * i + a]))
        .collect();
    let moved: Vec<f64> = p0.iter().zip(&rest).map(|(a, b)| a - b).collect();
    let gap = max_abs_diff(&moved, &lin.step0);
    let size = moved.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    assert!(size > 0.5, "the step should move the shape (by {size} mm)");
    assert!(gap <= 0.05 * size, "step0 off by {gap} mm of {size}");
    // A change c: the weights respond exactly linearly, the positions to first order.
    let c: Vec<f64> = (0..3 * n).map(|_| 0.05 * rng.normal()).collect();
    let oc: Vec<f64> = offset.iter().zip(&c).map(|(a, b)| a + b).collect();
    let (s1, p1) = step(&oc);
    let (pred, theta) = response(&c);
    let da: Vec<f64> = s1.alpha.iter().zip(&s0.alpha).map(|(a, b)| a - b).collect();
    let amax = da.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    assert!(
        max_abs_diff(&da, &theta[..m]) <= 1e-8 * amax.max(1e-12),
        "weights: {:?} vs {:?}",
        &da[..3],
        &theta[..3]
    );
    let actual: Vec<f64> = (0..3 * n).map(|i| p1[i] - p0[i] - c[i]).collect();
    let amp = actual.iter().fold(0.0f64, |a, x| a.max(x.abs()));
    let err = max_abs_diff(&actual, &pred);
    println!("refit response: largest {amp:.4} mm, linear model off by {err:.2e} mm");
    assert!(
        amp > 0.01,
        "the refit should respond to c (largest {amp} mm)"
    );
    // What the model leaves out is second order: the step's rotation change acting on the
    // displacements (it rotates X + u, the linearisation X), here 8 % of the response.
    assert!(err <= 0.1 * amp, "linear model off by {err} mm of {amp}");
    // Errors name what is wrong.
    let e = linearised_refit(
        basis,
        mesh,
        &matches,
        &measured,
        &offset[1..],
        centre,
        &params,
    )
    .unwrap_err();
    assert!(e.to_string().contains("offset"), "{e}");
    let e = linearised_refit(basis, mesh, &[], &measured, &offset, centre, &params).unwrap_err();
    assert!(
        matches!(e, RegisterError::TooFewMatches { matched: 0 }),
        "{e}"
    );
}

fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).fold(0.0, |m, (x, y)| m.max((x - y).abs()))
}

/// `settled` on hand-made histories: a fit whose residual stopped falling while re-matching
/// makes the nodes cycle is settled; one still improving, one running away, one too short or
/// with a NaN is not.
#[test]
fn settled_tells_a_cycling_fit_from_one_still_falling_or_running_away() {
    // Falls, then cycles: RMS within 0.3 % over the last three, movements 0.05-0.2 mm.
    let rms = [4.0, 2.5, 2.0, 1.90, 1.899, 1.901, 1.898, 1.900];
    let mov = [6.0, 2.0, 0.8, 0.2, 0.15, 0.05, 0.2, 0.1];
    assert!(settled(&rms, &mov));
    // Still falling by 5 % in the last three iterations.
    let falling = [4.0, 2.5, 2.0, 1.9, 1.85, 1.80, 1.75, 1.70];
    assert!(!settled(&falling, &mov));
    // Flat residual but the last movement exceeds every earlier one: running away.
    let mut runaway = mov;
    runaway[7] = 7.0;
    assert!(!settled(&rms, &runaway));
    // Too few iterations to judge, mismatched lengths, NaN.
    assert!(!settled(&rms[..3], &mov[..3]));
    assert!(!settled(&rms, &mov[..7]));
    let mut nan = rms;
    nan[6] = f64::NAN;
    assert!(!settled(&nan, &mov));
    // A small absolute improvement (under 0.01 mm) on a tiny residual counts as flat.
    let tiny = [0.5, 0.2, 0.1, 0.05, 0.046, 0.045, 0.044, 0.043];
    assert!(settled(&tiny, &mov));
}
