//! Discovery on synthetic cohorts made here from the augmented model itself (no phantom): a
//! box-shaped organ, sweeps of its anterior and side faces under a known rigid pose, noise of a
//! known σ. The larger tests on phantom livers are in `tests/discover.rs`.

use super::stats::signed_rank_z;
use super::*;
use crate::mesh::TetMesh;
use crate::mesh::rigid::Rigid;
use crate::register::anatomy::{LabelParams, label};
use crate::register::libr::{LibrParams, control_traction};
use crate::register::physics::model::Sites;
use crate::register::physics::model::forward;
use crate::register::{MeasuredKind, Measurements};
use crate::util::SplitMix64;

/// The embedded default liver, meshed coarsely (fast tests).
fn organ() -> (TetMesh, PreopModel) {
    let surface = crate::assets::default_liver().unwrap();
    let mesh = crate::mesh::tetra::tetrahedralize(
        &surface,
        &crate::mesh::tetra::TetraParams::with_edge(14.0),
    )
    .unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let model = labels.preop_model(&mesh, &[], &[]);
    (mesh, model)
}

/// A broad traction at the anterior node nearest the anterior centroid, along axis `dir`:
/// within LIBR's own physics.
fn broad_load(mesh: &TetMesh, model: &PreopModel, dir: usize, scale: f64) -> Vec<f64> {
    let b = mesh.boundary().unwrap();
    let ant: Vec<usize> = (0..mesh.num_nodes())
        .filter(|&v| model.anterior[v])
        .collect();
    let c =
        [0, 1, 2].map(|k| ant.iter().map(|&v| mesh.nodes()[v][k]).sum::<f64>() / ant.len() as f64);
    let at = ant
        .iter()
        .map(|&v| mesh.nodes()[v])
        .min_by(|a, b| crate::mesh::vec3::dist2(*a, c).total_cmp(&crate::mesh::vec3::dist2(*b, c)))
        .unwrap();
    let mut f = control_traction(mesh.nodes(), &b.triangles, at, [0.0, -1.0, 0.0], dir, 50.0);
    f.iter_mut().for_each(|x| *x *= scale);
    f
}

fn gauss(rng: &mut SplitMix64) -> f64 {
    let (u1, u2) = (rng.next_f64().max(1e-300), rng.next_f64());
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// `sweeps` sweeps of points on the anterior surface, each under its own rigid pose, with
/// Gaussian noise σ.
fn sweeps(
    mesh: &TetMesh,
    model: &PreopModel,
    u: &[f64],
    count: usize,
    sigma: f64,
    seed: u64,
) -> Vec<Sweep> {
    let b = mesh.boundary().unwrap();
    let p = mesh.nodes();
    let faces: Vec<[u32; 3]> = b
        .triangles
        .iter()
        .copied()
        .filter(|t| t.iter().all(|&v| model.anterior[v as usize]))
        .collect();
    let mut rng = SplitMix64::new(seed);
    (0..count)
        .map(|s| {
            let pose = Rigid::from_axis_angle(
                [0.2, 1.0, 0.3],
                (2.0 + s as f64).to_radians(),
                [3.0 * s as f64, -2.0, 4.0],
            );
            let mut points = Vec::new();
            for _ in 0..220 {
                let t = faces[rng.below(faces.len())];
                let (mut r1, mut r2) = (rng.next_f64(), rng.next_f64());
                if r1 + r2 > 1.0 {
                    r1 = 1.0 - r1;
                    r2 = 1.0 - r2;
                }
                let w = [1.0 - r1 - r2, r1, r2];
                let mut q = [0.0; 3];
                for (k, &v) in t.iter().enumerate() {
                    for a in 0..3 {
                        q[a] += w[k] * (p[v as usize][a] + u[3 * v as usize + a]);
                    }
                }
                let q = pose.apply(q);
                points.push([0, 1, 2].map(|a| q[a] + sigma * gauss(&mut rng)));
            }
            Sweep {
                id: format!("sweep-{s}"),
                measurements: Checked::new(Measurements {
                    kind: vec![MeasuredKind::Surface; points.len()],
                    points,
                    feature: Vec::new(),
                    initial_alignment: Some(pose),
                })
                .unwrap(),
            }
        })
        .collect()
}

fn params() -> DiscoverParams {
    DiscoverParams {
        pipeline: PipelineParams {
            libr: LibrParams {
                basis: crate::register::libr::BasisParams {
                    control_points: 12,
                    ..LibrParams::default().basis
                },
                fit: LibrParams::default().fit,
            },
            ..PipelineParams::default()
        },
        ..DiscoverParams::coarse()
    }
}

fn quiet(_: &str, _: usize, _: usize) {}

/// The named model removes most of the misfit: against LIBR at registration's λ, and against
/// LIBR at its own best prior weight (which absorbs part of a smooth effect), more than half the
/// mean-square held-out misfit.
fn explains_most(d: &CohortDiscovery) {
    assert!(d.heldout_after_mm < 0.5 * d.heldout_at_lambda_mm);
    assert!(
        d.heldout_after_mm < 0.7 * d.heldout_before_mm,
        "{} vs {}",
        d.heldout_after_mm,
        d.heldout_before_mm
    );
}

/// Discovery on 4 nearly noise-free sweeps (σ = 0.05 mm) of the truth `effect` on top of a
/// LIBR-scale load: checks the truth moves the organ by a few millimetres to `peak_max`, that
/// an effect is named, and returns the named effect of the same kind with the discovery.
fn hidden_one(effect: Effect, peak_max: f64, seed: u64) -> (Effect, CohortDiscovery) {
    let (mesh, model) = organ();
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    let kind = effect.kind;
    let truth = Physics {
        effects: vec![effect],
    };
    let base = broad_load(&mesh, &model, 1, 0.5);
    let p = params();
    let u = forward(&mesh, &p.pipeline.libr.basis.material, sites, &truth, &base).unwrap();
    let peak = u
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .fold(0.0, f64::max);
    assert!(peak > 3.0 && peak < peak_max, "peak displacement {peak} mm");
    let cohort = sweeps(&mesh, &model, &u, 4, 0.05, seed);
    let d = discover_cohort(&model, &cohort, &p, None, &quiet).unwrap();
    eprintln!("{}", serde_json::to_string_pretty(&d).unwrap());
    assert_eq!(d.verdict, Verdict::Effects, "{:?}", d.candidates);
    let e = d
        .effects
        .iter()
        .map(|n| n.effect.clone())
        .find(|e| e.kind == kind)
        .unwrap_or_else(|| panic!("{kind} not named: {:?}", d.candidates));
    (e, d)
}

/// Hidden gravity: named, its direction within 10° and magnitude within 20 % (the issue's
/// tolerances), the held-out misfit more than halved and near the noise.
#[test]
fn hidden_gravity_is_named_with_its_direction_and_magnitude() {
    let g = crate::mesh::vec3::unit([0.3, 1.0, -0.25]);
    let truth = Effect::new(
        EffectKind::Gravity,
        &[("direction", &g), ("magnitude", &[0.006])],
    )
    .unwrap();
    let (e, d) = hidden_one(truth, 40.0, 7);
    assert_eq!(d.effects[0].effect.kind, EffectKind::Gravity, "named first");
    let angle = search::angle_deg(e.direction("direction"), g);
    assert!(angle < 10.0, "direction off by {angle}°");
    let m = e.scalar("magnitude");
    assert!((m / 0.006 - 1.0).abs() < 0.2, "magnitude {m}");
    explains_most(&d);
    assert!(
        d.heldout_after_mm < 3.0 * d.noise_floor_mm,
        "{} vs floor {}",
        d.heldout_after_mm,
        d.noise_floor_mm
    );
}

/// Hidden insufflation pressure (0.6 kPa, 4.5 mmHg: on this coarse organ 1.2 kPa moves it
/// 76 mm): named, direction within 10°, magnitude within 20 %, the held-out misfit more than
/// halved.
#[test]
fn hidden_pressure_is_named_with_its_direction_and_magnitude() {
    let d_true = crate::mesh::vec3::unit([0.15, -1.0, 0.1]);
    let truth = Effect::new(
        EffectKind::Pressure,
        &[("direction", &d_true), ("magnitude_kpa", &[0.6])],
    )
    .unwrap();
    let (e, d) = hidden_one(truth, 60.0, 5);
    let angle = search::angle_deg(e.direction("direction"), d_true);
    assert!(angle < 10.0, "direction off by {angle}°");
    let m = e.scalar("magnitude_kpa");
    assert!((m / 0.6 - 1.0).abs() < 0.2, "magnitude {m}");
    explains_most(&d);
}

/// The organ's weight pressed into its bed (the bed carries it, as the generator's truths): both
/// named, the bed with the weight (as a pair, or one after the other), gravity's direction
/// within 15°, and the held-out misfit more than halved.
#[test]
fn gravity_carried_by_a_bed_is_named_with_its_bed() {
    use crate::register::physics::model::{Carry, forward_with};
    let (mesh, model) = organ();
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    let g = crate::mesh::vec3::unit([0.2, 1.0, -0.2]);
    let truth = Physics {
        effects: vec![
            Effect::new(EffectKind::BedSupport, &[("stiffness", &[0.07])]).unwrap(),
            Effect::new(
                EffectKind::Gravity,
                &[("direction", &g), ("magnitude", &[0.0104])],
            )
            .unwrap(),
        ],
    };
    let base = broad_load(&mesh, &model, 1, 0.5);
    let p = params();
    let u = forward_with(
        &mesh,
        &p.pipeline.libr.basis.material,
        sites,
        &truth,
        &base,
        Carry::Supports,
    )
    .unwrap();
    let peak = u
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .fold(0.0, f64::max);
    assert!(peak > 3.0 && peak < 60.0, "peak displacement {peak} mm");
    let cohort = sweeps(&mesh, &model, &u, 4, 0.05, 3);
    let d = discover_cohort(&model, &cohort, &p, None, &quiet).unwrap();
    eprintln!("{}", serde_json::to_string_pretty(&d).unwrap());
    let kinds: Vec<EffectKind> = d.effects.iter().map(|n| n.effect.kind).collect();
    assert!(
        kinds.contains(&EffectKind::Gravity) && kinds.contains(&EffectKind::BedSupport),
        "{kinds:?}: {:?}",
        d.candidates
    );
    let e = &d
        .effects
        .iter()
        .find(|n| n.effect.kind == EffectKind::Gravity)
        .unwrap()
        .effect;
    let angle = search::angle_deg(e.direction("direction"), g);
    assert!(angle < 15.0, "direction off by {angle}°");
    explains_most(&d);
}

/// Nothing hidden (the truth is a load LIBR's own basis holds): no missing effect.
#[test]
fn nothing_hidden_names_nothing() {
    let (mesh, model) = organ();
    let sites = Sites {
        posterior: &model.posterior,
        falciform: &model.falciform,
    };
    let base = broad_load(&mesh, &model, 1, 0.5);
    let p = params();
    let u = forward(
        &mesh,
        &p.pipeline.libr.basis.material,
        sites,
        &Physics::none(),
        &base,
    )
    .unwrap();
    let cohort = sweeps(&mesh, &model, &u, 4, 0.3, 11);
    let d = discover_cohort(&model, &cohort, &p, None, &quiet).unwrap();
    eprintln!("{}", serde_json::to_string_pretty(&d).unwrap());
    for (r, s) in d.plain.iter().zip(&cohort) {
        let pose = s.measurements.initial_alignment.unwrap();
        let rel = r.image_to_physical.then(&pose.inverse());
        eprintln!(
            "libr rms {:?} rigid rms {} pose error {:.2}° {:?}",
            r.libr.as_ref().map(|l| l.rms_mm),
            r.rigid.rms_mm,
            rel.rotation_angle_deg(),
            rel.translation
        );
    }
    assert_eq!(d.verdict, Verdict::None, "{:?}", d.candidates);
    assert!(d.physics.is_empty());
}

/// Nothing hidden, but the truth is LIBR's own basis under weights far larger and rougher than
/// its strain-energy prior at λ expects: the data ask for richer loads (a weaker prior), not for
/// a physical effect, and say so (`refine-loads`).
#[test]
fn loads_richer_than_the_prior_ask_for_richer_loads_not_an_effect() {
    let (mesh, model) = organ();
    let p = params();
    let basis = crate::register::libr::LibrBasis::build(&mesh, &p.pipeline.libr).unwrap();
    let mut rng = SplitMix64::new(5);
    let w: Vec<f64> = (0..basis.columns()).map(|_| gauss(&mut rng)).collect();
    let u = basis.displacement(&w);
    let peak = u
        .chunks_exact(3)
        .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
        .fold(0.0f64, f64::max);
    let u: Vec<f64> = u.iter().map(|x| x * 12.0 / peak).collect();
    let cohort = sweeps(&mesh, &model, &u, 4, 0.1, 12);
    let d = discover_cohort(&model, &cohort, &p, None, &quiet).unwrap();
    for c in &d.candidates {
        eprintln!(
            "round {} {} ({}): gain {:.3} z {:.2} dBIC {:.1} significant {}",
            c.round, c.kind, c.effect, c.gain, c.rank_z, c.delta_bic, c.significant
        );
    }
    eprintln!(
        "verdict {:?}: held-out {:.3} mm (prior × {}), at λ {:.3} mm, noise floor {:.3} mm",
        d.verdict,
        d.heldout_before_mm,
        d.prior_scale_before,
        d.heldout_at_lambda_mm,
        d.noise_floor_mm
    );
    assert!(d.physics.is_empty(), "named {}", d.physics.describe());
    assert_eq!(d.verdict, Verdict::RefineLoads);
    assert!(d.prior_scale_before < 1.0);
    assert!(d.heldout_before_mm < 0.95 * d.heldout_at_lambda_mm);
}

/// Bad cohorts get errors naming what is wrong.
#[test]
fn bad_cohorts_are_refused_with_the_field_named() {
    let (mesh, model) = organ();
    let u = vec![0.0; 3 * mesh.num_nodes()];
    let p = params();
    let e = discover_cohort(&model, &[], &p, None, &quiet)
        .unwrap_err()
        .to_string();
    assert!(e.contains("cohort") && e.contains("no scenarios"), "{e}");
    let one = sweeps(&mesh, &model, &u, 1, 0.3, 1);
    let e = discover_cohort(&model, &one, &p, None, &quiet)
        .unwrap_err()
        .to_string();
    assert!(e.contains("only 1 scenario"), "{e}");
    let mut two = sweeps(&mesh, &model, &u, 2, 0.3, 1);
    // A point that is not finite cannot make a sweep's measurements; a sweep without points is
    // refused by name.
    let mut raw = two[1].measurements.clone().into_inner();
    raw.points[5][2] = f64::NAN;
    let e = Checked::new(raw).unwrap_err().to_string();
    assert!(e.contains("points[5]"), "{e}");
    two[1].measurements = Checked::empty(None).unwrap();
    let e = discover_cohort(&model, &two, &p, None, &quiet)
        .unwrap_err()
        .to_string();
    assert!(e.contains("sweep-1") && e.contains("empty"), "{e}");
    let bad = DiscoverParams {
        folds: 1,
        ..params()
    };
    let two = sweeps(&mesh, &model, &u, 2, 0.3, 1);
    let e = discover_cohort(&model, &two, &bad, None, &quiet)
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("folds"), "{e}");
}

/// The signed-rank z against the textbook formulas: all n differences positive gives
/// W+ = n(n+1)/2; a sign-symmetric set gives 0; ties take their mean rank and shrink the
/// variance by Σ(t³ − t)/48.
#[test]
fn signed_rank_z_matches_the_textbook_statistic() {
    let n = 10.0f64;
    let all: Vec<f64> = (1..=10).map(|i| i as f64 * 0.3).collect();
    let expect = (n * (n + 1.0) / 2.0 - n * (n + 1.0) / 4.0)
        / (n * (n + 1.0) * (2.0 * n + 1.0) / 24.0).sqrt();
    assert!((signed_rank_z(&all) - expect).abs() < 1e-12);
    let sym: Vec<f64> = all.iter().flat_map(|x| [*x, -*x]).collect();
    assert!(signed_rank_z(&sym).abs() < 1e-12);
    // Ties: |d| = 1, 1, 2, 3 (ranks 1.5, 1.5, 3, 4); signs +, −, +, +: W+ = 8.5.
    let d = [1.0, -1.0, 2.0, 3.0];
    let var = 4.0 * 5.0 * 9.0 / 24.0 - (8.0 - 2.0) / 48.0;
    let z = (8.5 - 5.0) / f64::sqrt(var);
    assert!((signed_rank_z(&d) - z).abs() < 1e-12);
    // Zeros are dropped: they neither help nor hurt.
    assert!((signed_rank_z(&[0.0, 0.0, 1.0, 2.0]) - signed_rank_z(&[1.0, 2.0])).abs() < 1e-12);
}

/// The coefficient-space prior is the amplitude prior rewritten: for columns scaled so that
/// amplitude = coefficient × scale, σ²(a − μ)ᵀP(a − μ) equals (c − μ_c)ᵀP_c(c − μ_c) for any c.
#[test]
fn coefficient_prior_is_the_amplitude_prior_in_coefficients() {
    use nalgebra::{DMatrix, DVector};
    let p = DMatrix::from_row_slice(3, 3, &[2.0, 0.3, 0.1, 0.3, 1.0, -0.2, 0.1, -0.2, 0.5]);
    let mu = DVector::from_row_slice(&[1.0, -2.0, 0.5]);
    let scales = [0.2, 3.0, 0.05];
    let var = 0.7;
    let (pc, shift) = prior::coefficient_prior(&p, &mu, &scales, var);
    let mu_c = pc.clone().lu().solve(&shift).unwrap();
    let mut rng = SplitMix64::new(3);
    for _ in 0..5 {
        let c = DVector::from_fn(3, |_, _| rng.next_f64() * 4.0 - 2.0);
        let a = DVector::from_fn(3, |i, _| c[i] * scales[i]);
        let lhs = var * (&a - &mu).dot(&(&p * (&a - &mu)));
        let rhs = (&c - &mu_c).dot(&(&pc * (&c - &mu_c)));
        assert!(
            (lhs - rhs).abs() < 1e-9 * lhs.abs().max(1.0),
            "{lhs} vs {rhs}"
        );
    }
}

/// What physics rules out: an anterior weight (a prone patient), insufflation behind the organ,
/// a load far outside its physical size.
#[test]
fn implausible_loads_are_no_candidates() {
    use crate::register::physics::{Effect, EffectKind};
    assert!(prior::direction_plausible(
        EffectKind::Gravity,
        [0.3, 0.9, -0.3]
    ));
    assert!(!prior::direction_plausible(
        EffectKind::Gravity,
        [0.0, -1.0, 0.1]
    ));
    assert!(prior::direction_plausible(
        EffectKind::Pressure,
        [0.2, -0.9, 0.1]
    ));
    assert!(!prior::direction_plausible(
        EffectKind::Pressure,
        [0.0, 1.0, 0.0]
    ));
    assert!(prior::direction_plausible(
        EffectKind::Pack,
        [0.0, 1.0, 0.0]
    ));
    let g = |m: f64| {
        Effect::new(
            EffectKind::Gravity,
            &[("direction", &[0.0, 1.0, 0.0]), ("magnitude", &[m])],
        )
        .unwrap()
    };
    assert!(prior::amplitude_plausible(&g(0.0104)));
    assert!(!prior::amplitude_plausible(&g(0.002)));
    assert!(!prior::amplitude_plausible(&g(0.05)));
    let pack = |f: [f64; 3]| {
        Effect::new(
            EffectKind::Pack,
            &[
                ("center", &[0.0, 0.0, 0.0]),
                ("width_mm", &[20.0]),
                ("force_mn", &f),
            ],
        )
        .unwrap()
    };
    assert!(prior::amplitude_plausible(&pack([3000.0, 0.0, -4000.0])));
    assert!(!prior::amplitude_plausible(&pack([300.0, 0.0, 0.0])));
    // A share of the weight is plausible when only a local support carries it, not on a bed.
    let one = |kind: EffectKind, p: &[(&str, &[f64])]| Physics {
        effects: vec![Effect::new(kind, p).unwrap()],
    };
    let fixation = one(
        EffectKind::Fixation,
        &[
            ("center", &[0.0, 0.0, 0.0]),
            ("radius_mm", &[20.0]),
            ("stiffness", &[1.0]),
        ],
    );
    let bed = one(EffectKind::BedSupport, &[("stiffness", &[0.1])]);
    let share = g(0.2 * prior::GRAVITY_MAGNITUDE);
    assert!(prior::amplitude_plausible_on(&share, &fixation));
    assert!(!prior::amplitude_plausible_on(&share, &bed));
    assert!(!prior::amplitude_plausible_on(
        &g(0.05 * prior::GRAVITY_MAGNITUDE),
        &fixation
    ));
    assert!(!prior::amplitude_plausible_on(&g(0.05), &fixation));
}

/// A session's points as interleaved sweeps: every point in exactly one part, in order, with its
/// kind and feature; every part sees every kind the session has; the alignment is shared.
#[test]
fn a_session_splits_into_interleaved_sweeps() {
    let pose = Rigid::from_axis_angle([0.0, 0.0, 1.0], 0.1, [1.0, 2.0, 3.0]);
    let n = 11;
    let m = Measurements {
        points: (0..n).map(|i| [i as f64, 0.0, 0.0]).collect(),
        kind: (0..n)
            .map(|i| {
                if i < 6 {
                    MeasuredKind::Surface
                } else {
                    MeasuredKind::PosteriorContour
                }
            })
            .collect(),
        feature: (0..n).map(|i| (i % 3) as u8).collect(),
        initial_alignment: Some(pose),
    };
    let m = Checked::new(m).unwrap();
    for parts in [1, 2, 3] {
        let s = session_sweeps(&m, parts);
        assert_eq!(s.len(), parts);
        let mut seen = vec![0; n];
        for sw in &s {
            let x: Vec<usize> = sw
                .measurements
                .points
                .iter()
                .map(|p| p[0] as usize)
                .collect();
            assert!(x.windows(2).all(|w| w[0] < w[1]), "order kept");
            for (j, &i) in x.iter().enumerate() {
                seen[i] += 1;
                assert_eq!(sw.measurements.kind[j], m.kind[i]);
                assert_eq!(sw.measurements.feature[j], m.feature[i]);
            }
            assert_eq!(sw.measurements.initial_alignment, Some(pose));
            assert!(sw.measurements.kind.contains(&MeasuredKind::Surface));
            assert!(
                sw.measurements
                    .kind
                    .contains(&MeasuredKind::PosteriorContour)
            );
        }
        assert!(seen.iter().all(|&c| c == 1), "{seen:?}");
    }
}

/// A deadline already passed stops the workflow with `OutOfTime`, naming the stage.
#[test]
fn a_passed_deadline_stops_discovery() {
    let (mesh, model) = organ();
    let u = broad_load(&mesh, &model, 1, 0.0);
    let cohort = sweeps(&mesh, &model, &u, 2, 0.05, 3);
    let p = DiscoverParams {
        deadline: Some(Instant::now()),
        ..params()
    };
    match discover_cohort(&model, &cohort, &p, None, &quiet) {
        Err(DiscoverError::OutOfTime(stage)) => assert!(stage.contains("sweep"), "{stage}"),
        other => panic!("{:?}", other.map(|d| d.verdict)),
    }
}
