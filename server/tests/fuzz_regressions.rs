//! The fuzz targets (`librplus_server::fuzz`) under `cargo test`: each over its seeds (made here),
//! its corpus (`fuzz/corpus/TARGET/`), the inputs that once crashed it (`fuzz/regressions/TARGET/`)
//! and a fixed number of seeded mutations of those (`LIBRPLUS_FUZZ_RUNS`, default 3,000 per
//! target). The long campaigns (≥ 10^6 runs per target, coverage-guided) are libFuzzer's: `cargo
//! fuzz run TARGET` in `fuzz/` (docs/fuzzing.md).

use librplus::mesh::io::{Format, MeshFile, WriteOptions, write_bytes};
use librplus_proto::v1 as pb;
use librplus_server::fuzz::{TARGETS, run};
use prost::Message;
use std::path::{Path, PathBuf};

fn tiny() -> MeshFile {
    MeshFile {
        nodes: vec![
            [0.0, 0.0, 0.0],
            [10.0, 0.0, 0.0],
            [0.0, 10.0, 0.0],
            [0.0, 0.0, 10.0],
            [10.0, 10.0, 10.0],
        ],
        tets: vec![[0, 1, 2, 3], [1, 2, 3, 4]],
        ..Default::default()
    }
}

fn surface() -> MeshFile {
    MeshFile {
        nodes: vec![
            [0.0, 0.0, 0.0],
            [10.0, 0.0, 0.0],
            [0.0, 10.0, 0.0],
            [0.0, 0.0, 10.0],
        ],
        triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        ..Default::default()
    }
}

fn written(file: &MeshFile, format: Format, name: &str) -> Vec<Vec<u8>> {
    [true, false]
        .iter()
        .filter_map(|&binary| {
            write_bytes(file, format, WriteOptions { binary }, Path::new(name)).ok()
        })
        .collect()
}

fn with_kind(kind: u8, msg: impl Message) -> Vec<u8> {
    let mut v = vec![kind];
    v.extend(msg.encode_to_vec());
    v
}

/// Seeds of each target, made here from the writers and the messages.
fn seeds(target: &str) -> Vec<Vec<u8>> {
    use pb::stream_register_request::Msg;
    let rigid = pb::Rigid {
        rotation: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        translation_mm: vec![1.0, 2.0, 3.0],
    };
    match target {
        "vtk_xml" => {
            let mut v = written(&tiny(), Format::Vtu, "a.vtu");
            v.extend(written(&surface(), Format::Vtp, "a.vtp"));
            v
        }
        "vtk_legacy" => {
            let mut v = written(&tiny(), Format::VtkLegacy, "a.vtk");
            v.extend(written(&surface(), Format::VtkLegacy, "a.vtk"));
            v
        }
        "gmsh" => {
            let mut v = written(&tiny(), Format::Msh, "a.msh");
            v.push(
                b"$MeshFormat\n2.2 0 8\n$EndMeshFormat\n$Nodes\n4\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n$EndNodes\n$Elements\n1\n1 4 2 0 1 1 2 3 4\n$EndElements\n"
                    .to_vec(),
            );
            v
        }
        "stl" => {
            let mut v = written(&surface(), Format::Stl, "a.stl");
            v.push(b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n".to_vec());
            v
        }
        "obj" => {
            let mut v = written(&surface(), Format::Obj, "a.obj");
            v.push(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_vec());
            v
        }
        "physics_json" => vec![
            br#"{"format": 1, "effects": [{"kind": "gravity", "parameters": {"direction": [0, 1, 0], "magnitude": 0.01}}]}"#.to_vec(),
            br#"{"format": 1, "effects": [{"kind": "bed-support", "parameters": {"stiffness": 0.08}}]}"#.to_vec(),
        ],
        "requests" => vec![
            with_kind(
                0,
                pb::RegisterRequest {
                    case_id: "g1".into(),
                    method: 2,
                    measurements: Some(pb::Measurements {
                        xyz_mm: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.5],
                        kind: vec![1, 2, 3],
                        feature: vec![0, 1, 0],
                        initial_alignment: Some(rigid.clone()),
                    }),
                    options: None,
                },
            ),
            with_kind(
                1,
                pb::StreamRegisterRequest {
                    client_seq: 2,
                    msg: Some(Msg::Surface(pb::SurfaceBatch {
                        acquired_at: None,
                        xyz_mm: vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
                        feature: vec![1, 0],
                    })),
                },
            ),
            with_kind(
                1,
                pb::StreamRegisterRequest {
                    client_seq: 3,
                    msg: Some(Msg::Ultrasound(pb::UltrasoundPlane {
                        acquired_at: None,
                        plane_to_physical: Some(rigid.clone()),
                        contour_uv_mm: vec![1.0, 2.0],
                        vessel_uv_mm: vec![3.0, 4.0],
                    })),
                },
            ),
            with_kind(
                5,
                pb::StreamRegisterRequest {
                    client_seq: 1,
                    msg: Some(Msg::Start(pb::SessionStart {
                        case_id: "g1".into(),
                        initial_alignment: Some(rigid),
                        resume_session_id: "s1-000001".into(),
                        ..Default::default()
                    })),
                },
            ),
            with_kind(
                3,
                pb::CreateCaseRequest {
                    part: Some(pb::create_case_request::Part::Upload(pb::CaseUpload {
                        case_id: "hosp-a/p1".into(),
                        nodes_mm: tiny().nodes.iter().flatten().copied().collect(),
                        tets: tiny().tets.iter().flatten().copied().collect(),
                        ..Default::default()
                    })),
                },
            ),
            with_kind(4, pb::WatchCaseRequest { case_id: "a/b".into() }),
            {
                let mut v = vec![6u8];
                v.extend(br#"{"format":1,"principals":[{"principal":"a","token_sha256":["ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"],"cases":["x/*"],"roles":["read"]}]}"#);
                v
            },
        ],
        _ => Vec::new(),
    }
}

fn files(dir: &Path) -> Vec<Vec<u8>> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut paths: Vec<PathBuf> = rd
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_file())
        .collect();
    paths.sort();
    paths.iter().filter_map(|p| std::fs::read(p).ok()).collect()
}

/// A packed corpus: gzip of "LIBRPLUS-CORPUS-1\n" then each input as a u32 (LE) length and its
/// bytes.
fn pack_path(target: &str) -> PathBuf {
    fuzz_dir()
        .join("corpus")
        .join(format!("{target}.corpus.gz"))
}

const PACK_MAGIC: &[u8] = b"LIBRPLUS-CORPUS-1\n";

fn read_pack(target: &str) -> Vec<Vec<u8>> {
    use std::io::Read;
    let Ok(f) = std::fs::File::open(pack_path(target)) else {
        return Vec::new();
    };
    let mut raw = Vec::new();
    flate2::read::GzDecoder::new(f)
        .read_to_end(&mut raw)
        .unwrap_or_else(|e| panic!("{}: {e}", pack_path(target).display()));
    assert!(raw.starts_with(PACK_MAGIC), "{target}: not a corpus pack");
    let mut out = Vec::new();
    let mut at = PACK_MAGIC.len();
    while at + 4 <= raw.len() {
        let n = u32::from_le_bytes(raw[at..at + 4].try_into().unwrap()) as usize;
        at += 4;
        assert!(at + n <= raw.len(), "{target}: truncated corpus pack");
        out.push(raw[at..at + n].to_vec());
        at += n;
    }
    out
}

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz")
}

/// xorshift64*.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

/// One mutation of `a` (with `b` for splices).
fn mutate(r: &mut Rng, a: &[u8], b: &[u8]) -> Vec<u8> {
    const SPECIAL: &[&[u8]] = &[
        b"0",
        b"-1",
        b"1e308",
        b"NaN",
        b"inf",
        b"4294967295",
        b"18446744073709551616",
        b"\"",
        b"<",
        b">",
        b"\n",
        b" ",
        b"\0",
        b"$EndNodes",
        b"</DataArray>",
        b"99999999",
    ];
    let mut v = a.to_vec();
    for _ in 0..1 + r.below(4) {
        let n = v.len();
        match r.below(8) {
            0 if n > 0 => {
                let i = r.below(n);
                v[i] ^= 1 << r.below(8);
            }
            1 if n > 0 => {
                let i = r.below(n);
                v[i] = r.next() as u8;
            }
            2 => {
                let i = r.below(n + 1);
                let s = SPECIAL[r.below(SPECIAL.len())];
                v.splice(i..i, s.iter().copied());
            }
            3 if n > 0 => {
                let i = r.below(n);
                let j = (i + 1 + r.below(16)).min(n);
                v.drain(i..j);
            }
            4 if n > 0 => {
                let i = r.below(n);
                let j = (i + 1 + r.below(64)).min(n);
                let chunk = v[i..j].to_vec();
                let at = r.below(n + 1);
                v.splice(at..at, chunk);
            }
            5 => v.truncate(r.below(n + 1)),
            6 if !b.is_empty() => {
                let cut = r.below(n + 1);
                let from = r.below(b.len());
                v.truncate(cut);
                v.extend_from_slice(&b[from..]);
            }
            _ => {
                // A run of one byte: big counts, long numbers.
                let i = r.below(n + 1);
                let byte = b"90 ,;"[r.below(5)];
                v.splice(i..i, std::iter::repeat_n(byte, 1 + r.below(40)));
            }
        }
    }
    v
}

#[test]
fn every_fuzz_target_survives_its_corpus_regressions_and_mutations() {
    let runs: usize = std::env::var("LIBRPLUS_FUZZ_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3000);
    for (k, target) in TARGETS.iter().enumerate() {
        let mut inputs = seeds(target);
        let made = inputs.len();
        assert!(made > 0, "{target}: no seeds");
        let mut corpus = read_pack(target);
        corpus.extend(files(&fuzz_dir().join("corpus").join(target)));
        let regressions = files(&fuzz_dir().join("regressions").join(target));
        let (nc, nr) = (corpus.len(), regressions.len());
        inputs.extend(corpus);
        inputs.extend(regressions);
        let t0 = std::time::Instant::now();
        for i in &inputs {
            run(target, i);
        }
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15 ^ (k as u64 + 1));
        for _ in 0..runs {
            let a = &inputs[rng.below(inputs.len())];
            let b = &inputs[rng.below(inputs.len())];
            let m = mutate(&mut rng, a, b);
            run(target, &m);
        }
        eprintln!(
            "{target:<13} {made} seeds, {nc} corpus, {nr} regressions, {runs} mutations: no crash ({:.2} s)",
            t0.elapsed().as_secs_f64()
        );
    }
}

/// Writes the seeds into `fuzz/corpus/TARGET/` (libFuzzer's starting corpus):
/// `cargo test -p librplus-server --test fuzz_regressions -- --ignored write_seeds`.
#[test]
#[ignore = "writes files into fuzz/corpus"]
fn write_seeds() {
    for target in TARGETS {
        let dir = fuzz_dir().join("corpus").join(target);
        std::fs::create_dir_all(&dir).unwrap();
        for (i, s) in seeds(target).iter().enumerate() {
            std::fs::write(dir.join(format!("seed-{i}")), s).unwrap();
        }
    }
}

/// Packs each `fuzz/corpus/TARGET/` folder (a libFuzzer corpus, minimized with `-merge=1`) into
/// `fuzz/corpus/TARGET.corpus.gz`, the form that is committed:
/// `cargo test -p librplus-server --test fuzz_regressions -- --ignored pack_corpus`.
#[test]
#[ignore = "writes fuzz/corpus/*.corpus.gz"]
fn pack_corpus() {
    use std::io::Write;
    for target in TARGETS {
        let inputs = files(&fuzz_dir().join("corpus").join(target));
        if inputs.is_empty() {
            continue;
        }
        let mut raw = PACK_MAGIC.to_vec();
        for i in &inputs {
            raw.extend((i.len() as u32).to_le_bytes());
            raw.extend(i);
        }
        let mut gz = flate2::write::GzEncoder::new(
            std::fs::File::create(pack_path(target)).unwrap(),
            flate2::Compression::best(),
        );
        gz.write_all(&raw).unwrap();
        gz.finish().unwrap();
        assert_eq!(read_pack(target), inputs);
        eprintln!("{target}: {} inputs packed", inputs.len());
    }
}

/// Unpacks the committed corpora into `fuzz/corpus/TARGET/` for `cargo fuzz run`:
/// `cargo test -p librplus-server --test fuzz_regressions -- --ignored unpack_corpus`.
#[test]
#[ignore = "writes files into fuzz/corpus"]
fn unpack_corpus() {
    for target in TARGETS {
        let dir = fuzz_dir().join("corpus").join(target);
        std::fs::create_dir_all(&dir).unwrap();
        for (i, input) in read_pack(target).iter().enumerate() {
            std::fs::write(dir.join(format!("packed-{i:05}")), input).unwrap();
        }
    }
}
