//! A held organ (`PipelineParams::held`, `librplus::pipeline::hold`), checked for the sanity
//! properties a navigation system relies on when it says the organ is held and its start
//! trusted: on a held organ pushed by a tool the hold does better than trusting the start
//! without it (LIBR and adaptive LIBR; whether either beats doing nothing there is printed, not
//! asserted: not yet); an undeformed held organ stays where it is; an organ that moved rigidly
//! after all is answered no worse than doing nothing; LIBR+ leaves a held organ to LIBR. The hold
//! itself holds exactly the boundary nodes no measured point comes near.
//!
//! Data: `assets/livers/sofa_liver.vtk` meshed with 10 mm tets, labelled and given a vessel tree
//! by the phantom module. The truth of a held organ is computed here: linear elasticity with the
//! bare area fixed and an anterior spot pushed 20 mm inwards (cosine taper over 25 mm), an
//! independent FEM solve with Dirichlet conditions, not LIBR's free-floating basis. Its surface
//! is measured by `phantom::measure::simulate_focused` with the camera on the tool's spot and
//! the navigation start the true alignment.

mod common;

use librplus::fem::{Dirichlet, LinearMaterial, StiffnessSystem};
use librplus::mesh::TetMesh;
use librplus::mesh::rigid::Rigid;
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::phantom::measure::{Category, MeasureParams, simulate_focused};
use librplus::phantom::vessels::{VesselParams, VesselTree};
use librplus::pipeline::hold::{HoldParams, hold};
use librplus::pipeline::{Method, PipelineParams, Prepared, register, register_progressive};
use librplus::register::Checked;
use librplus::register::anatomy::{AnatomyLabels, LabelParams, label};
use librplus::register::libr::{AdaptiveParams, LibrParams};
use std::sync::OnceLock;

struct Case {
    mesh: TetMesh,
    labels: AnatomyLabels,
    vessels: VesselTree,
    prepared: Prepared,
    /// The tool's node.
    tool: u32,
    /// The held organ's displacement (image frame).
    u: Vec<f64>,
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
}

fn case() -> &'static Case {
    static C: OnceLock<Case> = OnceLock::new();
    C.get_or_init(|| {
        let surface = common::sofa_liver_surface();
        let mesh = tetrahedralize(&surface, &TetraParams::with_edge(10.0)).unwrap();
        let labels = label(&mesh, &LabelParams::default()).unwrap();
        let vessels = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
        let model = labels.preop_model(&mesh, &vessels.points, &vessels.segments);
        let n = mesh.num_nodes();
        let x = mesh.nodes();
        let held: Vec<u32> = (0..n as u32)
            .filter(|&i| labels.bare_area[i as usize])
            .collect();
        assert!(held.len() >= 10, "{} bare-area nodes", held.len());
        let hc = centroid(&held.iter().map(|&i| x[i as usize]).collect::<Vec<_>>());
        let c = centroid(x);
        // The tool: the anterior node farthest from the hold, pushed towards the centroid.
        let tool = labels
            .nodes_in(librplus::register::anatomy::Region::Anterior)
            .into_iter()
            .max_by(|&a, &b| {
                dist(x[a as usize], hc)
                    .total_cmp(&dist(x[b as usize], hc))
                    .then(b.cmp(&a))
            })
            .unwrap();
        let t = x[tool as usize];
        let len = dist(t, c);
        let dir = [0, 1, 2].map(|k| (c[k] - t[k]) / len);
        let mut bc = Dirichlet::new(n);
        bc.fix_nodes(&held);
        let boundary = model.boundary_flags();
        let mut pushed = 0;
        for (i, &b) in boundary.iter().enumerate() {
            let r = dist(x[i], t);
            if b && r <= 40.0 && !labels.bare_area[i] {
                let f = 0.5 * (1.0 + (std::f64::consts::PI * r / 40.0).cos());
                bc.prescribe_node(i as u32, dir.map(|d| 40.0 * f * d));
                pushed += 1;
            }
        }
        assert!(pushed >= 3, "the tool pushes {pushed} nodes");
        let system = StiffnessSystem::linear(&mesh, &LinearMaterial::default()).unwrap();
        let u = system.factorize(&bc).unwrap().solve(&vec![0.0; 3 * n]);
        let prepared = Prepared::new(model, Some(&LibrParams::default()), None)
            .unwrap()
            .with_adaptive(&LibrParams::default(), &AdaptiveParams::default(), None)
            .unwrap()
            .with_models(
                librplus::gcn::io::builtin_models()
                    .unwrap()
                    .into_iter()
                    .map(std::sync::Arc::new)
                    .collect(),
            )
            .unwrap();
        Case {
            mesh,
            labels,
            vessels,
            prepared,
            tool,
            u,
        }
    })
}

fn centroid(p: &[[f64; 3]]) -> [f64; 3] {
    let n = p.len() as f64;
    [0, 1, 2].map(|a| p.iter().map(|q| q[a]).sum::<f64>() / n)
}

/// Surface points of the organ under `u`, the camera on the tool's spot, the navigation start the
/// true alignment; returns the measurements and the true image → physical transform.
fn measured(u: &[f64], seed: u64) -> (Checked, Rigid) {
    let c = case();
    let params = MeasureParams {
        coverage: [0.4, 0.4],
        max_rotation_deg: 0.0,
        max_translation_mm: 0.0,
        trusted_start: true,
        ..MeasureParams::default()
    };
    let sc = simulate_focused(
        &c.mesh,
        &c.labels,
        &c.vessels,
        u,
        Category::Surface,
        &params,
        Some(c.tool),
        seed,
    )
    .unwrap();
    (common::scenario_measurements(&sc), sc.image_to_physical)
}

/// Mean node distance between the registration's organ and the truth (`u` under `truth`).
fn tre(r: &librplus::pipeline::Registration, u: &[f64], truth: &Rigid) -> f64 {
    let x = case().mesh.nodes();
    let n = x.len();
    (0..n)
        .map(|i| {
            let at = |v: &[f64], t: &Rigid| t.apply([0, 1, 2].map(|a| x[i][a] + v[3 * i + a]));
            dist(at(&r.u, &r.image_to_physical), at(u, truth))
        })
        .sum::<f64>()
        / n as f64
}

fn held_params() -> PipelineParams {
    PipelineParams {
        held: true,
        ..PipelineParams::default()
    }
}

#[test]
fn the_hold_helps_on_a_held_organ_pushed_by_a_tool() {
    let c = case();
    let mut rows = Vec::new();
    for seed in [1, 2] {
        let (meas, truth) = measured(&c.u, seed);
        let held = held_params();
        let mut trusted = PipelineParams::default();
        trusted.wicp.trusted_alignment_mm = Some(5.0);
        let run = |m: Method, p: &PipelineParams| {
            let r = register(&c.prepared, &meas, m, p).unwrap();
            (tre(&r, &c.u, &truth), r)
        };
        let (e0, _) = run(Method::Initial, &held);
        let (libr_held, r) = run(Method::Libr, &held);
        let (libr_trusted, _) = run(Method::Libr, &trusted);
        let (ad_held, ra) = run(Method::Adaptive, &held);
        let (ad_trusted, _) = run(Method::Adaptive, &trusted);
        eprintln!(
            "seed {seed}: doing nothing {e0:.2} mm; held: LIBR {libr_held:.2}, adaptive {ad_held:.2} ({} nodes held); the start trusted without the hold: LIBR {libr_trusted:.2}, adaptive {ad_trusted:.2}",
            r.libr.as_ref().unwrap().held_nodes
        );
        for reg in [&r, &ra] {
            assert!(reg.libr.as_ref().unwrap().held_nodes > 0, "nothing held");
            assert!(
                reg.pose.is_none(),
                "a held organ's start is trusted: no pose search"
            );
        }
        rows.push([e0, libr_held, libr_trusted, ad_held, ad_trusted]);
    }
    let mean = |k: usize| rows.iter().map(|r| r[k]).sum::<f64>() / rows.len() as f64;
    let [e0, libr_held, libr_trusted, ad_held, ad_trusted] = [0, 1, 2, 3, 4].map(mean);
    assert!(e0 > 1.0, "the tool moved the organ by {e0} mm on average");
    // The hold helps both methods; adaptive LIBR, which can make the dent, beats doing nothing.
    assert!(
        libr_held < libr_trusted,
        "LIBR held {libr_held:.2} mm, trusted alone {libr_trusted:.2}"
    );
    assert!(
        ad_held < ad_trusted,
        "adaptive held {ad_held:.2} mm, trusted alone {ad_trusted:.2}"
    );
    // Not yet true, and said in the output rather than asserted: on this linear dent (40 mm deep,
    // 40 mm wide, 1.6 mm mean over the organ) neither method makes the dent near the tool, and
    // both stay above doing nothing (adaptive about 2.0 mm, LIBR about 2.5; on the Neo-Hookean
    // held organs of pattern H adaptive held is 0.55–0.63 × doing nothing, docs/registration.md).
    eprintln!(
        "NOT YET MET (measured, not asserted): better than doing nothing on a linear local dent: adaptive held {ad_held:.2} mm, LIBR held {libr_held:.2}, doing nothing {e0:.2}"
    );
}

#[test]
fn an_undeformed_held_organ_stays_where_it_is() {
    let c = case();
    let zero = vec![0.0; c.u.len()];
    let (meas, truth) = measured(&zero, 3);
    let r = register(&c.prepared, &meas, Method::Libr, &held_params()).unwrap();
    let e = tre(&r, &zero, &truth);
    eprintln!("undeformed, held: the answer moves the organ {e:.2} mm on average (1 mm noise)");
    assert!(
        e < 1.0,
        "an undeformed held organ moved {e:.2} mm on average"
    );
}

#[test]
fn an_organ_that_moved_rigidly_is_answered_no_worse_than_doing_nothing() {
    let c = case();
    let zero = vec![0.0; c.u.len()];
    let (meas, truth) = measured(&zero, 4);
    // The organ moved 4 mm after all; the navigation start still says where it was.
    let shift = [2.0, -2.0, 2.0 * 2f64.sqrt()];
    let mut meas = meas.into_inner();
    for p in &mut meas.points {
        for a in 0..3 {
            p[a] += shift[a];
        }
    }
    let meas = common::checked(meas);
    let moved = truth.then(&Rigid {
        rotation: Rigid::identity().rotation,
        translation: shift,
    });
    let nothing = register(&c.prepared, &meas, Method::Initial, &held_params()).unwrap();
    let r = register(&c.prepared, &meas, Method::Libr, &held_params()).unwrap();
    let (e0, e1) = (tre(&nothing, &zero, &moved), tre(&r, &zero, &moved));
    eprintln!("moved 4 mm rigidly, held: doing nothing {e0:.2} mm, held LIBR {e1:.2}");
    assert!(
        (e0 - 4.0).abs() < 0.5,
        "doing nothing is {e0:.2} mm off, not 4"
    );
    assert!(e1 <= e0, "held LIBR {e1:.2} mm, doing nothing {e0:.2}");
}

#[test]
fn the_hold_is_the_boundary_no_measured_point_comes_near() {
    let c = case();
    let (meas, truth) = measured(&c.u, 5);
    // Every node the clearance leaves (no cap on their number).
    let p = HoldParams {
        max_nodes: 0,
        ..HoldParams::default()
    };
    let h = hold(&c.prepared.model, &meas, &truth, &p).unwrap();
    let inv = truth.inverse();
    let pts: Vec<[f64; 3]> = meas.points.iter().map(|&q| inv.apply(q)).collect();
    let boundary = c.prepared.model.boundary_flags();
    let x = c.mesh.nodes();
    let far = |i: usize| pts.iter().all(|&q| dist(q, x[i]) > p.clearance_mm);
    let want: Vec<u32> = (0..x.len())
        .filter(|&i| boundary[i] && far(i))
        .map(|i| i as u32)
        .collect();
    assert_eq!(h.nodes, want);
    assert!(!want.is_empty() && want.len() < boundary.iter().filter(|&&b| b).count());
    // Capped: a subset of them, spread evenly, held where the full hold holds them.
    let k = want.len() / 4;
    let capped = hold(
        &c.prepared.model,
        &meas,
        &truth,
        &HoldParams { max_nodes: k, ..p },
    )
    .unwrap();
    assert_eq!(capped.nodes.len(), k);
    assert!(capped.nodes.iter().all(|v| want.binary_search(v).is_ok()));
    for (&v, q) in capped.nodes.iter().zip(&capped.physical) {
        assert!(dist(truth.apply(x[v as usize]), *q) < 1e-9);
    }
    // Farthest-point sampling: no held node lies farther from the kept ones than the closest
    // two kept ones lie from each other (else it would have been kept before the later one).
    let kept: Vec<[f64; 3]> = capped.nodes.iter().map(|&v| x[v as usize]).collect();
    let nearest = |y: [f64; 3], skip: Option<usize>| {
        kept.iter()
            .enumerate()
            .filter(|&(j, _)| Some(j) != skip)
            .map(|(_, &z)| dist(y, z))
            .fold(f64::INFINITY, f64::min)
    };
    let cover = want
        .iter()
        .map(|&v| nearest(x[v as usize], None))
        .fold(0.0, f64::max);
    let separation = (0..k)
        .map(|j| nearest(kept[j], Some(j)))
        .fold(f64::INFINITY, f64::min);
    assert!(
        cover <= separation + 1e-9,
        "a held node {cover:.2} mm from the kept ones, kept ones {separation:.2} mm apart"
    );
    eprintln!(
        "{} of {} held nodes kept: every held node within {cover:.1} mm of one, the kept ones at least {separation:.1} mm apart",
        k,
        want.len()
    );
    for (&v, q) in h.nodes.iter().zip(&h.physical) {
        assert!(dist(truth.apply(x[v as usize]), *q) < 1e-9);
    }
    // Bad parameters name the field.
    for (bad, field) in [
        (
            HoldParams {
                clearance_mm: 0.0,
                ..p
            },
            "clearance_mm",
        ),
        (
            HoldParams {
                weight: f64::NAN,
                ..p
            },
            "weight",
        ),
    ] {
        let e = hold(&c.prepared.model, &meas, &truth, &bad)
            .unwrap_err()
            .to_string();
        assert!(e.contains(field), "{e}");
    }
}

/// LIBR+ leaves a held organ to LIBR: its network learned the residual of free-floating LIBR on
/// organs that are not held, so the held fit's answer stands (the correction skipped, saying
/// why), while the same points without the flag are corrected.
#[test]
fn librplus_leaves_a_held_organ_to_libr() {
    let c = case();
    let (meas, _) = measured(&c.u, 6);
    let held = held_params();
    let plus = register(&c.prepared, &meas, Method::LibrPlus, &held).unwrap();
    let libr = register(&c.prepared, &meas, Method::Libr, &held).unwrap();
    let corr = plus.correction.as_ref().unwrap();
    assert!(!corr.applied);
    let why = corr.skipped.as_deref().unwrap();
    assert!(why.contains("held"), "{why}");
    assert_eq!(plus.u, libr.u);
    assert_eq!(plus.image_to_physical, libr.image_to_physical);
    // The abstention rule is left out here (its own tests are in `gcn::abstain` and
    // `pipeline`): this case's LIBR residual lies near its in-family limit.
    let free = register(
        &c.prepared,
        &meas,
        Method::LibrPlus,
        &PipelineParams {
            abstain: false,
            ..PipelineParams::default()
        },
    )
    .unwrap();
    let fc = free.correction.unwrap();
    assert!(
        fc.applied,
        "without the flag LIBR+ corrects: {:?}",
        fc.skipped
    );
}

#[test]
fn auto_with_a_trusted_start_weighs_held_and_free_fits_and_does_no_worse_than_the_free_ones() {
    use librplus::pipeline::auto::Candidate;
    let c = case();
    let mut trusted = PipelineParams::default();
    trusted.wicp.trusted_alignment_mm = Some(5.0);
    let (mut auto_sum, mut free_sum, mut nothing_sum) = (0.0, 0.0, 0.0);
    for seed in [1, 2] {
        let (meas, truth) = measured(&c.u, seed);
        let run = |m: Method| register(&c.prepared, &meas, m, &trusted).unwrap();
        let auto = run(Method::Auto);
        let info = auto.auto.as_ref().expect("auto says how it chose");
        let names: Vec<Candidate> = info.candidates.iter().map(|s| s.candidate).collect();
        assert_eq!(
            names,
            [
                Candidate::Initial,
                Candidate::Rigid,
                Candidate::LibrHeld,
                Candidate::AdaptiveHeld,
                Candidate::Libr,
                Candidate::Adaptive
            ],
            "a trusted start adds the held fits"
        );
        // The answer is the chosen candidate's own.
        let (_, t, u) = info
            .answers
            .iter()
            .find(|(k, _, _)| *k == info.chosen)
            .unwrap();
        assert_eq!((t, u), (&auto.image_to_physical, &auto.u));
        assert_eq!(auto.method, Method::Auto);
        let free =
            tre(&run(Method::Libr), &c.u, &truth).min(tre(&run(Method::Adaptive), &c.u, &truth));
        let e_auto = tre(&auto, &c.u, &truth);
        let e0 = tre(&run(Method::Initial), &c.u, &truth);
        eprintln!(
            "seed {seed}: auto chose {} (runner-up {:?}, margin {:?} SE, ambiguous {:?}): {e_auto:.2} mm; free fits at best {free:.2}; doing nothing {e0:.2}",
            info.chosen, info.runner_up, info.margin_se, info.ambiguous
        );
        for s in &info.candidates {
            eprintln!(
                "  {:14} held out {:?} mm², in sample {:?}",
                s.candidate.name(),
                s.held_out_mm2,
                s.in_sample_mm2
            );
        }
        auto_sum += e_auto;
        free_sum += free;
        nothing_sum += e0;
    }
    assert!(
        auto_sum <= free_sum + 0.2,
        "auto {:.2} mm against the better free fit's {:.2} (doing nothing {:.2})",
        auto_sum / 2.0,
        free_sum / 2.0,
        nothing_sum / 2.0
    );
}

/// Without a trusted start the hold is a hypothesis: the held fits are tried but rank after the
/// free ones (so a held fit is chosen only when it predicts the unseen points clearly better,
/// which the one-standard-error rule checks on the same scores); they are not tried when the
/// hypothesis is turned off, and the free candidates' scores do not depend on it.
#[test]
fn without_a_trusted_start_the_hold_is_a_hypothesis_ranked_after_the_free_fits() {
    use librplus::pipeline::auto::Candidate;
    let c = case();
    let (meas, truth) = measured(&c.u, 1);
    let on = PipelineParams::default();
    let mut off = PipelineParams::default();
    off.auto.hypothesise_hold = false;
    let with = register(&c.prepared, &meas, Method::Auto, &on).unwrap();
    let without = register(&c.prepared, &meas, Method::Auto, &off).unwrap();
    let (a, b) = (with.auto.as_ref().unwrap(), without.auto.as_ref().unwrap());
    let names = |i: &librplus::pipeline::auto::AutoInfo| -> Vec<Candidate> {
        i.candidates.iter().map(|s| s.candidate).collect()
    };
    use Candidate::*;
    assert_eq!(
        names(a),
        [Initial, Rigid, Libr, Adaptive, LibrHeld, AdaptiveHeld]
    );
    assert!(a.hold_hypothesis && !b.hold_hypothesis);
    assert_eq!(names(b), [Initial, Rigid, Libr, Adaptive]);
    for s in &b.candidates {
        let t = a
            .candidates
            .iter()
            .find(|x| x.candidate == s.candidate)
            .unwrap();
        assert_eq!(t.held_out_mm2, s.held_out_mm2, "{}", s.candidate.name());
    }
    // Ranked after the free fits, a held fit that does not score best changes nothing: the
    // best score, hence every candidate's reach, is the same, and the first within reach too.
    if a.best_scoring == b.best_scoring {
        assert_eq!(a.chosen, b.chosen);
    }
    eprintln!(
        "hypothesis: chose {} ({:.2} mm), without it {} ({:.2} mm); doing nothing {:.2} mm; ambiguous: {:?}",
        a.chosen,
        tre(&with, &c.u, &truth),
        b.chosen,
        tre(&without, &c.u, &truth),
        tre(
            &register(&c.prepared, &meas, Method::Initial, &on).unwrap(),
            &c.u,
            &truth
        ),
        a.ambiguous
    );
}

/// The nonlinear refinement ([`Method::Nonlinear`]) on the held organ: it returns the refined
/// answer only where its objective (misfit plus prior, measured the same way) is lower than the
/// adaptive fit it started from, and that fit bit for bit otherwise. Answered in two
/// ([`register_progressive`]), the first answer is the adaptive fit bit for bit, flagged as
/// followed by its refinement, and the second [`register`]'s.
#[test]
fn the_nonlinear_refinement_never_fits_worse_than_its_linear_start() {
    let c = case();
    for seed in [11, 12] {
        let (meas, truth) = measured(&c.u, seed);
        let linear = register(&c.prepared, &meas, Method::Adaptive, &held_params()).unwrap();
        let first = OnceLock::new();
        let r = register_progressive(
            &c.prepared,
            &meas,
            Method::Nonlinear,
            &held_params(),
            &|a| {
                assert!(first.set(a.clone()).is_ok(), "one linear answer");
            },
        )
        .unwrap();
        let first = first
            .into_inner()
            .expect("the linear answer was handed over");
        assert!(first.refinement_follows && !r.refinement_follows);
        assert_eq!(first.method, Method::Adaptive);
        assert_eq!(first.u, linear.u, "the first answer is the adaptive fit");
        assert_eq!(first.image_to_physical, linear.image_to_physical);
        let whole = register(&c.prepared, &meas, Method::Nonlinear, &held_params()).unwrap();
        assert_eq!(
            r.u, whole.u,
            "the second answer is the one-piece registration's"
        );
        let n = r.nonlinear.as_ref().expect("the refinement's record");
        eprintln!(
            "pushed 40 mm, held, seed {seed}: adaptive {:.2} mm, refined {:.2} mm; objective {:.3} -> {:.3} mm², {} solves, {} Newton, {} CG, {:.2} s{}",
            tre(&linear, &c.u, &truth),
            tre(&r, &c.u, &truth),
            n.linear_objective_mm2,
            n.refined_objective_mm2,
            n.solves,
            n.newton,
            n.cg,
            n.seconds,
            n.kept_linear
                .as_ref()
                .map_or(String::new(), |w| format!("; kept the linear answer: {w}"))
        );
        match &n.kept_linear {
            Some(_) => {
                assert_eq!(r.u, linear.u, "a kept linear answer must be the same bits");
                assert_eq!(r.image_to_physical, linear.image_to_physical);
            }
            None => assert!(
                n.refined_objective_mm2 < n.linear_objective_mm2,
                "{} >= {}",
                n.refined_objective_mm2,
                n.linear_objective_mm2
            ),
        }
    }
}

#[test]
fn the_nonlinear_refinement_leaves_an_undeformed_or_rigidly_moved_organ_unbent() {
    let c = case();
    let zero = vec![0.0; c.u.len()];
    let (meas, truth) = measured(&zero, 3);
    let r = register(&c.prepared, &meas, Method::Nonlinear, &held_params()).unwrap();
    let e = tre(&r, &zero, &truth);
    eprintln!("undeformed, held, refined: the answer moves the organ {e:.2} mm on average");
    assert!(
        e < 1.0,
        "an undeformed held organ moved {e:.2} mm on average"
    );
    let shift = [2.0, -2.0, 2.0 * 2f64.sqrt()];
    let (meas, truth) = measured(&zero, 4);
    let mut meas = meas.into_inner();
    for p in &mut meas.points {
        for a in 0..3 {
            p[a] += shift[a];
        }
    }
    let meas = common::checked(meas);
    let moved = truth.then(&Rigid {
        rotation: Rigid::identity().rotation,
        translation: shift,
    });
    let nothing = register(&c.prepared, &meas, Method::Initial, &held_params()).unwrap();
    let r = register(&c.prepared, &meas, Method::Nonlinear, &held_params()).unwrap();
    let (e0, e1) = (tre(&nothing, &zero, &moved), tre(&r, &zero, &moved));
    eprintln!("moved 4 mm rigidly, held, refined: doing nothing {e0:.2} mm, refined {e1:.2}");
    assert!(e1 <= e0, "refined {e1:.2} mm, doing nothing {e0:.2}");
}
