use librplus::mesh::TriSurface;
use librplus::mesh::io::{self, Unit};
use librplus::phantom::shape::{ShapeVariantParams, variant};
use librplus::util::SplitMix64;
fn derive(seed: u64, keys: &[u64]) -> u64 {
    let mut s = seed;
    for &k in keys {
        s = SplitMix64::new(s ^ k.wrapping_mul(0x9E37_79B9_7F4A_7C15)).next_u64();
    }
    s
}
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let master: u64 = args[1].parse().unwrap();
    let k: u64 = args[2].parse().unwrap();
    let mut s =
        TriSurface::from_file(&io::read("../shared/data/sofa_liver.vtk", Unit::Mm).unwrap())
            .unwrap()
            .largest_component();
    if s.signed_volume() < 0.0 {
        s.flip();
    }
    let (v, _) = variant(&s, &ShapeVariantParams::default(), derive(master, &[1, k])).unwrap();
    io::write(&args[3], &v.to_file(), Default::default()).unwrap();
}
