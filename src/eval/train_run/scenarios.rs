//! The scenarios of a split's deformations, read once and picked by reference.

use crate::dataset::Manifest;
use crate::eval::{EvalError, ScenarioData, load_scenarios};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// The scenarios of the deformations a split's references name, by deformation id, and each
/// deformation's geometry.
pub(super) struct SplitScenarios {
    scenarios: BTreeMap<String, Vec<ScenarioData>>,
    geometry_of: BTreeMap<String, String>,
}

impl SplitScenarios {
    /// Reads the scenarios of every deformation of `m` that `refs` name.
    pub(super) fn load<'a>(
        data: &Path,
        m: &Manifest,
        refs: impl Iterator<Item = &'a (String, usize)>,
    ) -> Result<Self, EvalError> {
        let needed: BTreeSet<&str> = refs.map(|(d, _)| d.as_str()).collect();
        let mut scenarios = BTreeMap::new();
        let mut geometry_of = BTreeMap::new();
        for d in m
            .deformations
            .iter()
            .filter(|d| needed.contains(d.id.as_str()))
        {
            scenarios.insert(d.id.clone(), load_scenarios(data, d)?);
            geometry_of.insert(d.id.clone(), d.geometry.clone());
        }
        Ok(Self {
            scenarios,
            geometry_of,
        })
    }

    /// The geometries of the deformations read (one per deformation, in deformation order).
    pub(super) fn geometries(&self) -> Vec<String> {
        self.geometry_of.values().cloned().collect()
    }

    /// The scenarios `refs` name, each with its geometry.
    pub(super) fn pick(&self, refs: &[(String, usize)]) -> Vec<(&ScenarioData, &str)> {
        refs.iter()
            .filter_map(|(d, i)| {
                self.scenarios[d]
                    .get(*i)
                    .map(|s| (s, self.geometry_of[d].as_str()))
            })
            .collect()
    }
}
