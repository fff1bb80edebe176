use librplus::fem::hyperelastic::NewtonParams;
use librplus::mesh::TriSurface;
use librplus::mesh::io::{self, Unit};
use librplus::mesh::tetra::{TetraParams, tetrahedralize};
use librplus::phantom::labels::{LabelParams, label};
use librplus::phantom::patterns::{Pattern, PatternParams, load_case};
use librplus::phantom::tissue::{Tissue, TissueParams};
use librplus::phantom::truth::breakdown;
use librplus::phantom::vessels::{VesselParams, VesselTree};
fn env(k: &str, d: f64) -> f64 {
    std::env::var(k)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(d)
}
fn main() {
    let s = TriSurface::from_file(&io::read("../shared/data/sofa_liver.vtk", Unit::Mm).unwrap())
        .unwrap()
        .largest_component();
    let mesh = tetrahedralize(&s, &TetraParams::with_edge(env("H", 12.0))).unwrap();
    let labels = label(&mesh, &LabelParams::default()).unwrap();
    let tree = VesselTree::grow(&mesh, &VesselParams::default()).unwrap();
    let mut tp = TissueParams::default();
    tp.parenchyma_log_std = env("LOGSTD", tp.parenchyma_log_std);
    tp.parenchyma.youngs_modulus_kpa = env("E", 5.0);
    let mut pp = PatternParams::default();
    pp.load_scale = env("LS", 1.0);
    pp.bed_stiffness = env("BED", pp.bed_stiffness);
    pp.attachment_fraction = env("ATT", pp.attachment_fraction);
    pp.bare_area_stiffness = env("BARE", pp.bare_area_stiffness);
    let seeds: Vec<u64> = std::env::var("SEEDS")
        .unwrap_or("7".into())
        .split(',')
        .map(|x| x.parse().unwrap())
        .collect();
    for seed in seeds {
        let tissue = Tissue::build(&mesh, &tree, &tp, seed).unwrap();
        let lame = tissue.lame_field();
        for pattern in [Pattern::L, Pattern::R, Pattern::W, Pattern::V] {
            let case = load_case(&mesh, &labels, pattern, &pp, seed).unwrap();
            match breakdown(
                &mesh,
                &lame,
                &tp.parenchyma,
                &case,
                &NewtonParams::default(),
            ) {
                Ok(b) => println!(
                    "s{seed} {pattern:?}: mean {:.1} max {:.1} gap {:.2} | het {:.2} nl {:.2} contact {:.2} | grav {:.2} pat {:.2}",
                    b.truth_mean_mm,
                    b.truth_max_mm,
                    b.gap_mm,
                    b.steps[0].mean_mm,
                    b.steps[1].mean_mm,
                    b.steps[2].mean_mm,
                    b.by_load[0].mean_mm,
                    b.by_load[1].mean_mm
                ),
                Err(e) => println!("s{seed} {pattern:?}: FAILED {e}"),
            }
        }
    }
}
