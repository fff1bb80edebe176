//! Train/validation/test splits of a dataset's scenarios for SR-GCN training (`random`,
//! `geo-def`, `logo:G`, `pattern-v`, `family:NAME`), with a seeded validation set.

use crate::dataset::{DeformationEntry, Manifest};
use crate::eval::EvalError;
use crate::util::SplitMix64;

/// Scenarios per block (one per measurement category).
const BLOCK: usize = 5;

/// A train/test split of a dataset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TrainSplit {
    /// Random blocks of scenarios of the training deformations.
    Random,
    /// Whole geometry–pattern deformations held out.
    GeoDef,
    /// Every deformation of one geometry held out.
    Logo(String),
    /// Train on the training deformations, test on the test geometry (pattern V).
    PatternV,
    /// Every deformation of one truth family held out (on every liver, the test liver's
    /// pattern V included); training on the other families' training deformations.
    Family(String),
}

impl TrainSplit {
    /// Parses `random`, `geo-def`, `logo:G`, `pattern-v`, `family:NAME`.
    pub fn parse(s: &str) -> Result<Self, EvalError> {
        match s {
            "random" => Ok(Self::Random),
            "geo-def" => Ok(Self::GeoDef),
            "pattern-v" => Ok(Self::PatternV),
            _ => match (s.strip_prefix("logo:"), s.strip_prefix("family:")) {
                (Some(g), _) if !g.is_empty() => Ok(Self::Logo(g.to_string())),
                (_, Some(f)) if !f.is_empty() => Ok(Self::Family(f.to_string())),
                _ => Err(EvalError::Parameter(format!(
                    "unknown split {s:?}: expected random, geo-def, logo:GEOMETRY, pattern-v or \
                     family:NAME"
                ))),
            },
        }
    }

    /// Name as parsed.
    pub fn name(&self) -> String {
        match self {
            Self::Random => "random".into(),
            Self::GeoDef => "geo-def".into(),
            Self::Logo(g) => format!("logo:{g}"),
            Self::PatternV => "pattern-v".into(),
            Self::Family(f) => format!("family:{f}"),
        }
    }
}

/// A scenario: deformation id and scenario index.
pub type ScenarioRef = (String, usize);

/// The scenarios of a split.
#[derive(Debug, Clone, Default)]
pub struct SplitSets {
    /// Training scenarios.
    pub train: Vec<ScenarioRef>,
    /// Validation scenarios (from the training deformations).
    pub valid: Vec<ScenarioRef>,
    /// Test scenarios.
    pub test: Vec<ScenarioRef>,
}

pub(crate) fn shuffle<T>(v: &mut [T], seed: u64) {
    let mut rng = SplitMix64::new(seed);
    for i in (1..v.len()).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        v.swap(i, j);
    }
}

/// What the validation set holds out of the training scenarios.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Validation {
    /// Whole training deformations (about one in ten, by the seed) where the test holds out
    /// whole deformations or livers; a tenth of the blocks on the random split.
    #[default]
    Deformations,
    /// One whole training liver (by the seed), all its deformations: validation then judges
    /// what the test of an unseen liver judges, generalisation to a new shape, at the price of
    /// that liver's training data. Needs at least three training livers.
    Geometry,
}

impl Validation {
    /// The name used on the command line and in provenance files.
    pub fn name(self) -> &'static str {
        match self {
            Validation::Deformations => "deformations",
            Validation::Geometry => "geometry",
        }
    }
}

/// Assigns scenarios to train, validation and test. `every`: keep every `every`-th block of
/// each deformation (1 = all). `validation`: what validation holds out of the training
/// scenarios (the test set does not depend on it).
pub fn split_scenarios(
    m: &Manifest,
    split: &TrainSplit,
    seed: u64,
    every: usize,
    validation: Validation,
) -> Result<SplitSets, EvalError> {
    let (test, mut train_blocks) = Splitting::new(m, every.max(1)).assign(split, seed)?;
    shuffle(&mut train_blocks, seed ^ 0xA11D);
    let geometry_of: std::collections::HashMap<&str, &str> = m
        .deformations
        .iter()
        .map(|d| (d.id.as_str(), d.geometry.as_str()))
        .collect();
    let first_of = |b: &[ScenarioRef]| b.first().map(|r| r.0.clone());
    // Validation is like the test: where the test holds out whole deformations, validation is
    // whole training deformations (about one in ten, at least one, chosen by the seed), so early
    // stopping and the learning-rate schedule judge generalisation to unseen deformations, not
    // memorisation of seen ones.
    let mut defs: Vec<&str> = train_blocks
        .iter()
        .filter_map(|b| b.first().map(|r| r.0.as_str()))
        .collect();
    defs.sort();
    defs.dedup();
    let held_out_valid = !matches!(split, TrainSplit::Random) && defs.len() >= 3;
    let valid: Vec<bool> = if validation == Validation::Geometry {
        let held = validation_geometry(&train_blocks, &geometry_of, split, seed)?;
        train_blocks
            .iter()
            .map(|b| {
                first_of(b)
                    .and_then(|d| geometry_of.get(d.as_str()).copied())
                    .is_some_and(|g| g == held)
            })
            .collect()
    } else if held_out_valid {
        // Drawn without replacement.
        let mut rng = SplitMix64::new(seed ^ 0xDEF0);
        let mut pool = defs;
        let mut held = Vec::new();
        for _ in 0..validation_deformations(pool.len()) {
            let k = (rng.next_u64() % pool.len() as u64) as usize;
            held.push(pool.remove(k).to_string());
        }
        train_blocks
            .iter()
            .map(|b| first_of(b).is_some_and(|d| held.contains(&d)))
            .collect()
    } else {
        let n_valid = (train_blocks.len() / 10)
            .max(1)
            .min(train_blocks.len().saturating_sub(1));
        (0..train_blocks.len()).map(|i| i < n_valid).collect()
    };
    let mut sets = SplitSets {
        test,
        ..Default::default()
    };
    for (b, v) in train_blocks.into_iter().zip(valid) {
        if v {
            sets.valid.extend(b);
        } else {
            sets.train.extend(b);
        }
    }
    sets.train.sort();
    sets.valid.sort();
    sets.test.sort();
    if sets.train.is_empty() || sets.test.is_empty() {
        return Err(EvalError::Data(format!(
            "split {} leaves no training or no test scenarios",
            split.name()
        )));
    }
    Ok(sets)
}

/// The training liver validation holds out: the livers left for training (sorted), one drawn
/// by the seed; at least three are needed.
fn validation_geometry<'a>(
    train_blocks: &[Vec<ScenarioRef>],
    geometry_of: &std::collections::HashMap<&str, &'a str>,
    split: &TrainSplit,
    seed: u64,
) -> Result<&'a str, EvalError> {
    let mut livers: Vec<&str> = Vec::new();
    for b in train_blocks {
        if let Some(g) = b.first().and_then(|r| geometry_of.get(r.0.as_str())) {
            if !livers.contains(g) {
                livers.push(g);
            }
        }
    }
    livers.sort();
    if livers.len() < 3 {
        return Err(EvalError::Data(format!(
            "validation by geometry needs at least 3 training livers, split {} leaves {}",
            split.name(),
            livers.len()
        )));
    }
    let mut rng = SplitMix64::new(seed ^ 0x6E0);
    Ok(livers[(rng.next_u64() % livers.len() as u64) as usize])
}

/// The test set and the training blocks of a split, before validation is drawn.
struct Splitting<'a> {
    m: &'a Manifest,
    every: usize,
    test_geos: Vec<&'a str>,
    /// The training geometries' deformations.
    train_defs: Vec<&'a DeformationEntry>,
}

/// The test scenarios and the training blocks.
type Assigned = (Vec<ScenarioRef>, Vec<Vec<ScenarioRef>>);

impl<'a> Splitting<'a> {
    fn new(m: &'a Manifest, every: usize) -> Self {
        let test_geos = m.test_geometries();
        let train_defs = m
            .deformations
            .iter()
            .filter(|d| !test_geos.contains(&d.geometry.as_str()))
            .collect();
        Self {
            m,
            every,
            test_geos,
            train_defs,
        }
    }

    /// Every `every`-th block of consecutive scenarios of a deformation.
    fn blocks(&self, d: &DeformationEntry) -> Vec<Vec<ScenarioRef>> {
        (0..d.scenarios.len().div_ceil(BLOCK))
            .filter(|b| b % self.every == 0)
            .map(|b| {
                (b * BLOCK..((b + 1) * BLOCK).min(d.scenarios.len()))
                    .map(|i| (d.id.clone(), i))
                    .collect()
            })
            .collect()
    }

    /// Each deformation of `defs`, whole: to the test where `held`, else to training.
    fn by_deformation<'d>(
        &self,
        defs: impl IntoIterator<Item = &'d DeformationEntry>,
        held: impl Fn(&DeformationEntry) -> bool,
    ) -> Assigned {
        let (mut test, mut train_blocks) = (Vec::new(), Vec::new());
        for d in defs {
            let h = held(d);
            for b in self.blocks(d) {
                if h {
                    test.extend(b);
                } else {
                    train_blocks.push(b);
                }
            }
        }
        (test, train_blocks)
    }

    fn assign(&self, split: &TrainSplit, seed: u64) -> Result<Assigned, EvalError> {
        match split {
            TrainSplit::Random => Ok(self.random(seed)),
            TrainSplit::GeoDef | TrainSplit::Logo(_) => self.geometry_pattern(split),
            TrainSplit::Family(f) => self.family(f),
            TrainSplit::PatternV => {
                if self.test_geos.is_empty() {
                    return Err(EvalError::Data(
                        "pattern-v: the dataset has no test geometry".into(),
                    ));
                }
                let test_geos = &self.test_geos;
                Ok(self.by_deformation(&self.m.deformations, |d| {
                    test_geos.contains(&d.geometry.as_str())
                }))
            }
        }
    }

    /// `random`: the training deformations' blocks shuffled by the seed, a fifth to the test.
    fn random(&self, seed: u64) -> Assigned {
        let mut all: Vec<Vec<ScenarioRef>> = self
            .train_defs
            .iter()
            .flat_map(|d| self.blocks(d))
            .collect();
        shuffle(&mut all, seed ^ 0x5EED);
        let n_test = (all.len() / 5).max(1).min(all.len().saturating_sub(2));
        let (mut test, mut train_blocks) = (Vec::new(), Vec::new());
        for (i, b) in all.into_iter().enumerate() {
            if i < n_test {
                test.extend(b);
            } else {
                train_blocks.push(b);
            }
        }
        (test, train_blocks)
    }

    /// `geo-def` (the first geometry's first two patterns and the last geometry's third held
    /// out) and `logo:G` (every deformation of geometry G held out).
    fn geometry_pattern(&self, split: &TrainSplit) -> Result<Assigned, EvalError> {
        let mut geos: Vec<&str> = self
            .train_defs
            .iter()
            .map(|d| d.geometry.as_str())
            .collect();
        geos.dedup();
        let mut pats: Vec<&str> = self.train_defs.iter().map(|d| d.pattern.as_str()).collect();
        pats.sort();
        pats.dedup();
        if let TrainSplit::Logo(g) = split
            && !geos.contains(&g.as_str())
        {
            return Err(EvalError::Data(format!(
                "logo:{g}: no training geometry {g} (have {})",
                geos.join(", ")
            )));
        }
        if matches!(split, TrainSplit::GeoDef) && (geos.len() < 2 || pats.len() < 3) {
            return Err(EvalError::Data(
                "geo-def needs at least 2 geometries and 3 patterns".into(),
            ));
        }
        Ok(
            self.by_deformation(self.train_defs.iter().copied(), |d| match split {
                TrainSplit::Logo(g) => &d.geometry == g,
                _ => {
                    let gi = geos.iter().position(|g| *g == d.geometry).unwrap_or(0);
                    let pi = pats.iter().position(|p| *p == d.pattern).unwrap_or(0);
                    (gi == 0 && pi < 2) || (gi == geos.len() - 1 && pi == 2)
                }
            }),
        )
    }

    /// `family:F`: every deformation of truth family F held out; the other families'
    /// deformations of the test geometries left out.
    fn family(&self, f: &str) -> Result<Assigned, EvalError> {
        let mut names: Vec<&str> = self.m.deformations.iter().map(|d| d.family()).collect();
        names.sort();
        names.dedup();
        if !names.contains(&f) {
            return Err(EvalError::Data(format!(
                "family:{f}: no deformation of truth family {f} (the dataset has {})",
                names.join(", ")
            )));
        }
        let test_geos = &self.test_geos;
        let defs = self
            .m
            .deformations
            .iter()
            .filter(|d| d.family() == f || !test_geos.contains(&d.geometry.as_str()));
        Ok(self.by_deformation(defs, |d| d.family() == f))
    }
}

/// How many of `n` training deformations validate on held-out-deformation splits: about one in
/// ten, at least one.
pub fn validation_deformations(n: usize) -> usize {
    n.div_ceil(10).max(1).min(n.saturating_sub(1))
}
