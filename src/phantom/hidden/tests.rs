use super::*;
use crate::mesh::vec3::dot;
use crate::register::physics::model::{Carry, forward_with};

#[test]
fn turned_directions_keep_their_angle() {
    let mut d = Draws(SplitMix64::new(3));
    for v in [[0.0, -1.0, 0.0], unit([0.3, -0.2, 0.9])] {
        for _ in 0..50 {
            let t = d.turned(v, 20.0);
            let angle = dot(t, v).clamp(-1.0, 1.0).acos().to_degrees();
            assert!((dot(t, t) - 1.0).abs() < 1e-12);
            assert!(angle <= 20.0 + 1e-9, "{angle}");
        }
    }
}

#[test]
fn specs_parse_check_ranges_and_refuse_nonlinear() {
    let s = HiddenEffectSpec::parse("gravity:magnitude=0.01").unwrap();
    assert_eq!(s.kind, EffectKind::Gravity);
    assert_eq!(s.given["magnitude"], vec![0.01]);
    assert_eq!(
        s.to_value(),
        serde_json::json!({"kind": "gravity", "given": {"magnitude": 0.01}})
    );
    let e = HiddenEffectSpec::parse("gravity:magnitude=5")
        .unwrap_err()
        .to_string();
    assert!(e.contains("magnitude") && e.contains("outside"), "{e}");
    let e = HiddenEffectSpec::parse("foo").unwrap_err().to_string();
    assert!(e.contains("\"foo\"") && e.contains("bed-support"), "{e}");
    let e = HiddenEffectSpec::parse("nonlinear")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("nonlinear") && e.contains("not generated"),
        "{e}"
    );
    let e = HiddenEffectSpec::parse("pack:direction=0/1/0")
        .unwrap_err()
        .to_string();
    assert!(e.contains("direction"), "{e}");
}

/// `scale=F` multiplies each kind's amplitude and nothing else (the same draws otherwise); it is
/// recorded with the spec, and a bad value is an error naming `scale`.
#[test]
fn scale_multiplies_the_amplitude_and_nothing_else() {
    let (mesh, labels) = liver();
    let amplitude = |k: EffectKind| match k {
        EffectKind::Gravity => "magnitude",
        EffectKind::Pressure => "magnitude_kpa",
        EffectKind::Pack => "force_mn",
        EffectKind::Inclusion => "stiffness_ratio",
        _ => "stiffness",
    };
    for k in KINDS {
        let one = draw_physics(&[spec(k.name())], mesh, labels, 3).unwrap();
        let half = spec(&format!("{}:scale=0.5", k.name()));
        assert_eq!(half.scale, 0.5);
        assert_eq!(half.to_value()["scale"], 0.5);
        let half = draw_physics(&[half], mesh, labels, 3).unwrap();
        let (a, b) = (&one.effects[0], &half.effects[0]);
        let name = amplitude(k);
        for (key, v) in &a.parameters {
            let w = &b.parameters[key];
            if key == name {
                for (x, y) in v.iter().zip(w) {
                    let want = if k == EffectKind::Inclusion {
                        1.0 + 0.5 * (x - 1.0)
                    } else {
                        0.5 * x
                    };
                    assert!((y - want).abs() <= 1e-12 * want.abs().max(1.0), "{k} {key}");
                }
            } else {
                assert_eq!(v, w, "{k} {key}");
            }
        }
    }
    for bad in ["gravity:scale=0", "gravity:scale=11", "gravity:scale=x"] {
        let e = HiddenEffectSpec::parse(bad).unwrap_err().to_string();
        assert!(e.contains("scale"), "{e}");
    }
    let s = spec("gravity:magnitude=0.01,scale=2");
    assert_eq!(s.given["magnitude"], vec![0.01]);
    assert_eq!(s.scale, 2.0);
}

/// The built-in liver at 14 mm (the small preset's edge), labelled; built once.
fn liver() -> &'static (TetMesh, AnatomyLabels) {
    static LIVER: std::sync::OnceLock<(TetMesh, AnatomyLabels)> = std::sync::OnceLock::new();
    LIVER.get_or_init(|| {
        use crate::mesh::tetra::{TetraParams, tetrahedralize};
        use crate::register::anatomy::{LabelParams, label};
        let surface = crate::assets::default_liver().unwrap();
        let mesh = tetrahedralize(&surface, &TetraParams::with_edge(14.0)).unwrap();
        let labels = label(&mesh, &LabelParams::default()).unwrap();
        (mesh, labels)
    })
}

const KINDS: [EffectKind; 7] = [
    EffectKind::Gravity,
    EffectKind::BedSupport,
    EffectKind::Fixation,
    EffectKind::Pressure,
    EffectKind::Pack,
    EffectKind::Ligament,
    EffectKind::Inclusion,
];

fn spec(text: &str) -> HiddenEffectSpec {
    HiddenEffectSpec::parse(text).unwrap()
}

fn norm(v: [f64; 3]) -> f64 {
    dot(v, v).sqrt()
}

/// Every kind draws parameters that validate, inside the documented ranges, deterministically
/// from the seed, and different ones from another seed.
#[test]
fn effects_draw_valid_parameters_in_their_documented_ranges() {
    let (mesh, labels) = liver();
    let nodes = mesh.nodes();
    let geom = BoundaryGeometry::new(mesh).unwrap();
    let on_boundary = |c: [f64; 3]| geom.nodes.iter().any(|&v| nodes[v as usize] == c);
    let (lo, hi) = mesh.bounding_box();
    let specs: Vec<HiddenEffectSpec> = KINDS.iter().map(|k| spec(k.name())).collect();
    for seed in 0..8u64 {
        let p = draw_physics(&specs, mesh, labels, seed).unwrap();
        p.validate().unwrap();
        assert_eq!(p, draw_physics(&specs, mesh, labels, seed).unwrap());
        assert_ne!(p, draw_physics(&specs, mesh, labels, seed + 100).unwrap());
        let inside = |x: f64, lo: f64, hi: f64| (lo..=hi).contains(&x);
        for e in &p.effects {
            match e.kind {
                EffectKind::Gravity => {
                    let g = e.vector("direction");
                    assert!((norm(g) - 1.0).abs() < 1e-12);
                    // Head-up 0–30°: no superior component; lateral within ±30° of +y.
                    assert!(g[2] <= 1e-12 && g[2] >= -(30f64.to_radians().sin()) - 1e-12);
                    assert!(g[1] > 0.0 && g[0].abs() <= 30f64.to_radians().sin() + 1e-12);
                    let m = e.scalar("magnitude");
                    assert!(inside(m, 0.8 * LIVER_WEIGHT, 1.2 * LIVER_WEIGHT), "{m}");
                }
                EffectKind::BedSupport => assert!(inside(e.scalar("stiffness"), 0.02, 0.3)),
                EffectKind::Ligament => assert!(inside(e.scalar("stiffness"), 0.1, 1.0)),
                EffectKind::Fixation => {
                    let c = e.vector("center");
                    assert!(on_boundary(c));
                    let v = geom
                        .nodes
                        .iter()
                        .find(|&&v| nodes[v as usize] == c)
                        .unwrap();
                    assert_eq!(labels.region[*v as usize], Region::Posterior);
                    assert!(c[2] >= 0.5 * (lo[2] + hi[2]), "superior half: {c:?}");
                    assert!(inside(e.scalar("radius_mm"), 15.0, 35.0));
                    assert!(inside(e.scalar("stiffness"), 0.2, 2.0));
                }
                EffectKind::Pressure => {
                    let m = e.scalar("magnitude_kpa");
                    assert!(inside(m, 0.93, 1.87), "{m}");
                    let d = e.vector("direction");
                    let angle = (-d[1]).clamp(-1.0, 1.0).acos().to_degrees();
                    assert!(angle <= 20.0 + 1e-9, "{angle}");
                }
                EffectKind::Pack => {
                    let c = e.vector("center");
                    let v = *geom
                        .nodes
                        .iter()
                        .find(|&&v| nodes[v as usize] == c)
                        .expect("a boundary node");
                    assert!(!labels.bare_area[v as usize]);
                    assert!(inside(e.scalar("width_mm"), 10.0, 30.0));
                    let f = e.vector("force_mn");
                    assert!(inside(norm(f), 2000.0, 8000.0), "{f:?}");
                    let inward = geom.node_normal[v as usize].map(|x| -x);
                    let angle = (dot(f, inward) / norm(f)).clamp(-1.0, 1.0).acos();
                    assert!(angle.to_degrees() <= 30.0 + 1e-9);
                }
                EffectKind::Inclusion => {
                    let r = e.scalar("radius_mm");
                    assert!(inside(r, 10.0, 25.0));
                    assert!(inside(e.scalar("stiffness_ratio"), 3.0, 10.0));
                    let c = e.vector("center");
                    assert!(!on_boundary(c));
                }
                EffectKind::Nonlinear => unreachable!(),
            }
        }
    }
}

/// A parameter given on the command line replaces its draw and leaves the others' draws alone;
/// a second effect leaves the first one's draws alone.
#[test]
fn given_parameters_and_added_effects_change_no_other_draw() {
    let (mesh, labels) = liver();
    let free = draw_physics(&[spec("fixation")], mesh, labels, 5).unwrap();
    let fixed = draw_physics(&[spec("fixation:radius_mm=25")], mesh, labels, 5).unwrap();
    let (a, b) = (&free.effects[0], &fixed.effects[0]);
    assert_eq!(b.scalar("radius_mm"), 25.0);
    assert_eq!(a.vector("center"), b.vector("center"));
    assert_eq!(a.scalar("stiffness"), b.scalar("stiffness"));
    let two = draw_physics(
        &[spec("fixation"), spec("gravity:direction=0/1/0")],
        mesh,
        labels,
        5,
    )
    .unwrap();
    assert_eq!(two.effects[0], free.effects[0]);
    assert_eq!(two.effects[1].vector("direction"), [0.0, 1.0, 0.0]);
    // The effect's stream is its own: not the seed's first numbers.
    assert_ne!(effect_seed(5, 0), effect_seed(5, 1));
}

/// `--truth libr` without hidden effects is [`forward`](crate::register::physics::model::forward)
/// with no physics on [`libr_base_load`]: broad tractions of LIBR's own kind drawn from the
/// case's seed (the same for every pattern with that seed, none of the pattern's own loads),
/// each a combination of LIBR's control-point loads; a hidden gravity changes the truth by what
/// the model says.
#[test]
fn libr_truth_is_forward_on_the_surface_load() {
    use super::super::patterns::{Pattern, load_case};
    use crate::register::physics::model::forward;
    let (mesh, labels) = liver();
    let params = PatternParams::default();
    let material = LinearMaterial::default();
    let sites = LibrSites::new(labels);
    let w = load_case(mesh, labels, Pattern::W, &params, 3).unwrap();
    let (base, note) = libr_base_load(mesh, &w, params.load_scale).unwrap();
    assert!(note.contains("broad tractions"), "{note}");
    let t = libr_truth(mesh, labels, &material, &w, &params, &[], 3).unwrap();
    let direct = forward(mesh, &material, sites.sites(), &Physics::none(), &base).unwrap();
    assert_eq!(t.displacement, direct);
    assert_eq!(t.libr, direct);
    assert!(t.physics.is_empty());
    let (mean, max) = super::super::truth::magnitude_stats(&direct);
    assert!(mean > 0.5 && max < 80.0, "mean {mean} mm, max {max} mm");
    // The pattern's loads are not used: L (a retractor only) with the same seed has the same base.
    let l = load_case(mesh, labels, Pattern::L, &params, 3).unwrap();
    let (base_l, _) = libr_base_load(mesh, &l, params.load_scale).unwrap();
    assert_eq!(base_l, base);
    // Only boundary nodes are loaded, and another seed draws another load.
    let boundary = mesh.boundary().unwrap();
    let on: std::collections::HashSet<u32> = boundary.nodes.iter().copied().collect();
    for v in 0..mesh.num_nodes() {
        if !on.contains(&(v as u32)) {
            assert!(base[3 * v..3 * v + 3].iter().all(|&x| x == 0.0));
        }
    }
    let w4 = load_case(mesh, labels, Pattern::W, &params, 4).unwrap();
    assert_ne!(
        libr_base_load(mesh, &w4, params.load_scale).unwrap().0,
        base
    );

    let g = libr_truth(mesh, labels, &material, &w, &params, &[spec("gravity")], 3).unwrap();
    assert_eq!(g.libr, t.libr, "LIBR alone does not see the hidden effect");
    // A lone load is carried by a carrier bed; the truth is the supported forward model.
    assert_eq!(g.physics.kinds(), ["gravity", "bed-support"]);
    assert_eq!(g.roles, [Role::Hidden, Role::Carrier]);
    let with = forward_with(
        mesh,
        &material,
        sites.sites(),
        &g.physics,
        &base,
        Carry::Supports,
    )
    .unwrap();
    let d = super::super::truth::mean_distance(&g.displacement, &with);
    assert!(d < 1e-9, "truth vs forward_with: {d} mm");
    let gap = super::super::truth::mean_distance(&g.displacement, &g.libr);
    assert!(gap > 0.01, "a hidden gravity changes the truth: {gap}");
}

/// The truth's effects carry their loads: a lone support gets the organ's weight (its own
/// stream: the support's draw is that of the support alone), a lone load a carrier bed, a lone
/// inclusion both, a support and a load nothing more; the loads' part never peaks above the cap, and when scaled
/// to it the recorded physics reproduces the truth.
#[test]
fn hidden_loads_are_carried_and_capped() {
    use super::super::patterns::{Pattern, load_case};
    let (mesh, labels) = liver();
    let params = PatternParams::default();
    let material = LinearMaterial::default();
    let sites = LibrSites::new(labels);
    let w = load_case(mesh, labels, Pattern::W, &params, 5).unwrap();
    let (base, _) = libr_base_load(mesh, &w, params.load_scale).unwrap();
    let truth = |specs: &[HiddenEffectSpec]| {
        libr_truth(mesh, labels, &material, &w, &params, specs, 5).unwrap()
    };
    let fixation = truth(&[spec("fixation")]);
    assert_eq!(fixation.physics.kinds(), ["fixation", "gravity"]);
    assert_eq!(fixation.roles, [Role::Hidden, Role::Carried]);
    let alone = draw_physics(&[spec("fixation")], mesh, labels, 5).unwrap();
    assert_eq!(fixation.physics.effects[0], alone.effects[0]);
    let both = truth(&[spec("bed-support"), spec("pressure")]);
    assert_eq!(both.physics.kinds(), ["bed-support", "pressure"]);
    assert_eq!(both.roles, [Role::Hidden, Role::Hidden]);
    let inclusion = truth(&[spec("inclusion")]);
    assert_eq!(
        inclusion.physics.kinds(),
        ["inclusion", "bed-support", "gravity"]
    );
    assert_eq!(
        inclusion.roles,
        [Role::Hidden, Role::Carrier, Role::Carried]
    );
    for t in [&fixation, &both, &inclusion] {
        let [b, e] =
            forward_supported_parts(mesh, &material, sites.sites(), &t.physics, &base).unwrap();
        let peak = e
            .chunks_exact(3)
            .map(|c| norm([c[0], c[1], c[2]]))
            .fold(0.0f64, f64::max);
        assert!(peak <= EFFECT_PEAK_CAP_MM * (1.0 + 1e-9), "{peak} mm");
        let sum: Vec<f64> = b.iter().zip(&e).map(|(x, y)| x + y).collect();
        let d = super::super::truth::mean_distance(&t.displacement, &sum);
        assert!(
            d < 1e-9,
            "the recorded physics reproduces the truth: {d} mm"
        );
        assert_eq!(
            t.note.contains("scaled by"),
            peak > EFFECT_PEAK_CAP_MM * (1.0 - 1e-9),
            "{}",
            t.note
        );
    }
}
