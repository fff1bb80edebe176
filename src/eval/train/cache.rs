//! LIBR solutions of a dataset's scenarios (what LIBR+ starts from), computed once and cached
//! under `DATA/cache/libr-solutions/KEY/`, and the prepared geometries they belong to.

use crate::dataset::Manifest;
use crate::dataset::read::{GeometryData, ScenarioData, load_geometry};
use crate::eval::EvalError;
use crate::gcn::sample::CaseFrame;
use crate::mesh::rigid::Rigid;
use crate::pipeline::{Method, PipelineParams, Prepared, register};
use crate::register::correspondence::CorrespondenceParams;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

/// A LIBR solution of one scenario (what LIBR+ starts from).
#[derive(Debug, Clone)]
pub struct LibrSolution {
    /// Image → physical transform.
    pub transform: Rigid,
    /// Node displacements (image frame).
    pub u: Vec<f64>,
}

/// Key of the LIBR solution cache: the registration parameters and the physics LIBR carries.
pub fn solution_key(
    params: &PipelineParams,
    physics: &crate::register::physics::Physics,
) -> String {
    let text = format!("{:?}|{:?}", params.wicp, params.libr);
    let text = if physics.is_empty() {
        text
    } else {
        format!("{text}|{}", physics.hash())
    };
    crate::util::fnv1a_hex(text.as_bytes())
}

pub(super) fn encode_solution(s: &Option<LibrSolution>) -> Vec<u8> {
    let mut b = b"LIBRSOL1".to_vec();
    match s {
        None => b.push(0),
        Some(s) => {
            b.push(1);
            for row in s.transform.rotation {
                for v in row {
                    b.extend(v.to_le_bytes());
                }
            }
            for v in s.transform.translation {
                b.extend(v.to_le_bytes());
            }
            b.extend((s.u.len() as u64).to_le_bytes());
            for v in &s.u {
                b.extend(v.to_le_bytes());
            }
        }
    }
    b
}

pub(super) fn decode_solution(b: &[u8], n3: usize) -> Option<Option<LibrSolution>> {
    let rd = |i: usize| {
        b.get(i..i + 8)
            .map(|s| f64::from_le_bytes(s.try_into().expect("8")))
    };
    if b.get(..8)? != b"LIBRSOL1" {
        return None;
    }
    match *b.get(8)? {
        0 => Some(None),
        1 => {
            let mut rotation = [[0.0; 3]; 3];
            for (k, r) in rotation.iter_mut().flatten().enumerate() {
                *r = rd(9 + 8 * k)?;
            }
            let translation = [rd(81)?, rd(89)?, rd(97)?];
            let n = u64::from_le_bytes(b.get(105..113)?.try_into().ok()?) as usize;
            if n != n3 || b.len() != 113 + 8 * n {
                return None;
            }
            let u = (0..n)
                .map(|i| rd(113 + 8 * i))
                .collect::<Option<Vec<f64>>>()?;
            Some(Some(LibrSolution {
                transform: Rigid {
                    rotation,
                    translation,
                },
                u,
            }))
        }
        _ => None,
    }
}

/// One geometry's registration case and SR-GCN frame.
pub struct GeometryCase {
    /// The geometry (model, surface flags, targets).
    pub geo: GeometryData,
    /// Its prepared registration case (with the LIBR basis).
    pub case: Prepared,
    /// Its SR-GCN frame and mesh graph.
    pub frame: CaseFrame,
}

/// Loads (or builds and caches) the registration case of every geometry named, its LIBR
/// carrying `physics` (empty: plain LIBR).
pub fn load_cases(
    dir: &Path,
    m: &Manifest,
    geometries: &[String],
    params: &PipelineParams,
    physics: &crate::register::physics::Physics,
) -> Result<BTreeMap<String, GeometryCase>, EvalError> {
    let mut out = BTreeMap::new();
    for g in geometries {
        if out.contains_key(g) {
            continue;
        }
        let geo = load_geometry(dir, m, g)?;
        let case = Prepared::with_physics(
            geo.model.clone(),
            Some(&params.libr),
            physics,
            Some(&dir.join("cache")),
        )?;
        let frame = CaseFrame::new(&geo.model.mesh)?;
        out.insert(g.clone(), GeometryCase { geo, case, frame });
    }
    Ok(out)
}

/// LIBR solutions of scenarios (None where LIBR failed), from the cache or computed (in parallel)
/// and cached. `progress(done, total)` is called as they come.
pub fn libr_solutions(
    dir: &Path,
    cases: &BTreeMap<String, GeometryCase>,
    scenarios: &[(&ScenarioData, &str)],
    params: &PipelineParams,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Vec<Option<LibrSolution>>, EvalError> {
    // Every geometry's case carries the same physics (`load_cases`).
    let physics = cases
        .values()
        .next()
        .map(|c| c.case.physics.clone())
        .unwrap_or_default();
    let root = dir
        .join("cache")
        .join("libr-solutions")
        .join(solution_key(params, &physics));
    let done = std::sync::atomic::AtomicUsize::new(0);
    let total = scenarios.len();
    scenarios
        .par_iter()
        .map(|(sc, geometry)| {
            let gc = cases
                .get(*geometry)
                .ok_or_else(|| EvalError::Internal(format!("no case for geometry {geometry}")))?;
            let n3 = 3 * gc.geo.model.mesh.num_nodes();
            let path = root.join(format!("{}.bin", sc.id.replace('/', "__")));
            let cached = std::fs::read(&path)
                .ok()
                .and_then(|b| decode_solution(&b, n3));
            let sol = match cached {
                Some(s) => s,
                None => {
                    let s = register(&gc.case, &sc.measurements, Method::Libr, params)
                        .ok()
                        .map(|r| LibrSolution {
                            transform: r.image_to_physical,
                            u: r.u,
                        });
                    crate::util::write_atomic(&path, &encode_solution(&s))?;
                    s
                }
            };
            progress(
                done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1,
                total,
            );
            Ok(sol)
        })
        .collect()
}

/// True node positions (physical frame) of a scenario.
pub fn truth_positions(geo: &GeometryData, sc: &ScenarioData) -> Vec<[f64; 3]> {
    let t = &sc.truth;
    geo.model
        .mesh
        .nodes()
        .iter()
        .enumerate()
        .map(|(i, x)| {
            t.image_to_physical
                .apply([0, 1, 2].map(|a| x[a] + t.displacement[3 * i + a]))
        })
        .collect()
}

/// The correspondence parameters LIBR ends with (what the sparse loss re-matches with).
pub fn final_cparams(params: &PipelineParams) -> CorrespondenceParams {
    params.libr_correspondence()
}
