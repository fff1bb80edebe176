//! Which dataset scenarios a client replays ([`Selection`]) and reading them: measurements, truth,
//! ultrasound planes and (for TRE) the geometries.

use anyhow::{Context, Result, bail};
use librplus::dataset::Manifest;
use librplus::eval::{GeometryData, ScenarioData, ScenarioPlanes};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// Which scenarios of a dataset to replay.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Selection {
    /// Every scenario, in manifest order.
    All,
    /// These scenario ids (`DEFORMATION_ID/INDEX`), in this order.
    Ids(Vec<String>),
    /// Up to this many, spread evenly over deformations and measurement categories.
    Spread(usize),
}

impl Selection {
    /// From the command line: `--scenarios all`, `--scenarios ID,ID,...`, or (absent) `--limit N`.
    pub fn parse(scenarios: Option<&str>, limit: usize) -> Selection {
        match scenarios.map(str::trim) {
            Some("all") => Selection::All,
            Some(list) => Selection::Ids(
                list.split(',')
                    .map(|s| s.trim().to_string())
                    .filter(|s| !s.is_empty())
                    .collect(),
            ),
            None => Selection::Spread(limit),
        }
    }
}

/// A scenario of the manifest: deformation position in `Manifest::deformations` and the
/// scenario's `index`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ScenarioRef {
    /// Position of the deformation in the manifest.
    pub deformation: usize,
    /// The scenario's index within its deformation.
    pub index: usize,
}

/// The scenarios a selection names, in replay order. `Spread(n)` takes pick k from deformation
/// `k mod D` and category `(k + ⌊k / lcm(D, C)⌋) mod C` (C categories in order of first
/// appearance), the lowest unused index there, falling back to the next category and then the
/// next deformation when that one is used up; so every deformation and category gets its share.
pub fn select(m: &Manifest, sel: &Selection) -> Result<Vec<ScenarioRef>> {
    let all = || {
        m.deformations.iter().enumerate().flat_map(|(d, e)| {
            e.scenarios.iter().map(move |s| ScenarioRef {
                deformation: d,
                index: s.index,
            })
        })
    };
    match sel {
        Selection::All => Ok(all().collect()),
        Selection::Ids(ids) => ids
            .iter()
            .map(|id| {
                let (def, idx) = id
                    .rsplit_once('/')
                    .with_context(|| format!("--scenarios: {id:?} is not DEFORMATION_ID/INDEX"))?;
                let idx: usize = idx
                    .parse()
                    .with_context(|| format!("--scenarios: {id:?}: index {idx:?}"))?;
                let d = m
                    .deformations
                    .iter()
                    .position(|e| e.id == def)
                    .with_context(|| {
                        format!("--scenarios: the dataset has no deformation {def:?}")
                    })?;
                if !m.deformations[d].scenarios.iter().any(|s| s.index == idx) {
                    bail!("--scenarios: deformation {def:?} has no scenario {idx}");
                }
                Ok(ScenarioRef {
                    deformation: d,
                    index: idx,
                })
            })
            .collect(),
        Selection::Spread(limit) => {
            let mut categories: Vec<&str> = Vec::new();
            for e in &m.deformations {
                for s in &e.scenarios {
                    if !categories.contains(&s.category.as_str()) {
                        categories.push(&s.category);
                    }
                }
            }
            let (nd, nc) = (m.deformations.len(), categories.len());
            // Per deformation and category, the scenario indices not yet taken (lowest first).
            let mut left: Vec<Vec<std::collections::VecDeque<usize>>> = m
                .deformations
                .iter()
                .map(|e| {
                    categories
                        .iter()
                        .map(|c| {
                            let mut v: Vec<usize> = e
                                .scenarios
                                .iter()
                                .filter(|s| s.category == *c)
                                .map(|s| s.index)
                                .collect();
                            v.sort_unstable();
                            v.into()
                        })
                        .collect()
                })
                .collect();
            let total: usize = m.deformations.iter().map(|e| e.scenarios.len()).sum();
            let want = (*limit).min(total);
            let lcm = if nd == 0 || nc == 0 {
                1
            } else {
                nd / gcd(nd, nc) * nc
            };
            let mut out = Vec::with_capacity(want);
            let mut k = 0usize;
            while out.len() < want {
                let (d0, c0) = (k % nd, (k + k / lcm) % nc);
                'pick: for dd in 0..nd {
                    let d = (d0 + dd) % nd;
                    for cc in 0..nc {
                        let c = (c0 + cc) % nc;
                        if let Some(index) = left[d][c].pop_front() {
                            out.push(ScenarioRef {
                                deformation: d,
                                index,
                            });
                            break 'pick;
                        }
                    }
                }
                k += 1;
            }
            Ok(out)
        }
    }
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 { a } else { gcd(b, a % b) }
}

/// A scenario ready to replay.
#[derive(Debug, Clone)]
pub struct Replayable {
    /// The server's case: the deformation's geometry id.
    pub case_id: String,
    /// Measurements and truth.
    pub scenario: ScenarioData,
    /// Its ultrasound planes.
    pub planes: ScenarioPlanes,
}

/// Selected scenarios and, when asked for, their geometries by id.
#[derive(Debug, Clone)]
pub struct Loaded {
    /// The manifest.
    pub manifest: Manifest,
    /// The selected scenarios, in selection order.
    pub scenarios: Vec<Replayable>,
    /// Geometries by id (empty unless asked for).
    pub geometries: BTreeMap<String, GeometryData>,
}

/// Reads the selected scenarios of the dataset in `dir` (each deformation's `scenarios.npz` once)
/// and, with `geometries`, the geometries they belong to.
pub fn load_selection(dir: &Path, sel: &Selection, geometries: bool) -> Result<Loaded> {
    let manifest = librplus::eval::open(dir)
        .with_context(|| format!("reading the dataset manifest in {}", dir.display()))?;
    let refs = select(&manifest, sel)?;
    let mut cache: HashMap<usize, HashMap<usize, (ScenarioData, ScenarioPlanes)>> = HashMap::new();
    for r in &refs {
        if cache.contains_key(&r.deformation) {
            continue;
        }
        let d = &manifest.deformations[r.deformation];
        let ctx = || format!("{} (deformation {})", dir.join(&d.npz).display(), d.id);
        let sc = librplus::eval::load_scenarios(dir, d).with_context(ctx)?;
        let pl = librplus::eval::load_scenario_planes(dir, d).with_context(ctx)?;
        let by_index = d
            .scenarios
            .iter()
            .map(|s| s.index)
            .zip(sc.into_iter().zip(pl))
            .collect();
        cache.insert(r.deformation, by_index);
    }
    let scenarios = refs
        .iter()
        .map(|r| {
            let d = &manifest.deformations[r.deformation];
            let (scenario, planes) = cache[&r.deformation][&r.index].clone();
            Replayable {
                case_id: d.geometry.clone(),
                scenario,
                planes,
            }
        })
        .collect::<Vec<_>>();
    let mut geos = BTreeMap::new();
    if geometries {
        for s in &scenarios {
            if !geos.contains_key(&s.case_id) {
                let g = librplus::eval::load_geometry(dir, &manifest, &s.case_id).with_context(
                    || format!("reading geometry {} in {}", s.case_id, dir.display()),
                )?;
                geos.insert(s.case_id.clone(), g);
            }
        }
    }
    Ok(Loaded {
        manifest,
        scenarios,
        geometries: geos,
    })
}
