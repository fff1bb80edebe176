//! Recording the oracle's detectability ([`crate::discover::oracle`]) in a `--truth libr` dataset
//! with hidden effects: per deformation, the cohort of all its scenarios, each starting at its
//! true pose: the effects hidden (role `hidden`) tested on top of those that carry them or that
//! they carry (roles `carrier`, `carried`), which both models hold. Written into
//! `deformation.json` and the manifest as
//! `detectability`; deformations that already hold it are kept (a resumed run computes only the
//! rest).

use crate::dataset::{DeformationEntry, Manifest, read_manifest};
use crate::discover::DiscoverParams;
use crate::discover::oracle::detectability;
use crate::register::physics::Physics;
use std::path::Path;

/// What a recording pass did.
#[derive(Debug, Clone, Default)]
pub struct DetectabilityReport {
    /// Deformations whose detectability was computed now.
    pub computed: usize,
    /// Of those, the detectable.
    pub detectable: usize,
    /// Deformations that already had it.
    pub kept: usize,
    /// Deformations it could not be computed for, with why.
    pub errors: Vec<String>,
}

/// The truth's physics of a deformation (its `hidden_effects`) and the part of it that is not
/// under test (the effects whose `role` is not `hidden`: a carrier bed, a carried weight);
/// `None` when nothing is hidden.
pub fn truth_physics(d: &DeformationEntry) -> Result<Option<(Physics, Physics)>, String> {
    let Some(v) = &d.hidden_effects else {
        return Ok(None);
    };
    let p =
        Physics::from_json(&v.to_string()).map_err(|e| format!("{}: hidden_effects: {e}", d.id))?;
    if p.is_empty() {
        return Ok(None);
    }
    let roles: Vec<&str> = v["effects"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|e| e["role"].as_str().unwrap_or("hidden"))
                .collect()
        })
        .unwrap_or_default();
    let known = Physics {
        effects: p
            .effects
            .iter()
            .zip(&roles)
            .filter(|(_, r)| **r != "hidden")
            .map(|(e, _)| e.clone())
            .collect(),
    };
    Ok(Some((p, known)))
}

/// Computes and records the detectability of every deformation of the dataset in `dir` that
/// hides effects and does not hold it yet. `progress(done, total, id)` after each. The manifest
/// is rewritten after each deformation, so an interrupted pass loses at most one.
pub fn record(
    dir: &Path,
    params: &DiscoverParams,
    progress: &(dyn Fn(usize, usize, &str) + Sync),
) -> Result<DetectabilityReport, String> {
    let mut m: Manifest = read_manifest(dir).map_err(|e| e.to_string())?;
    let cache = dir.join("cache");
    let todo: Vec<usize> = (0..m.deformations.len())
        .filter(|&i| {
            m.deformations[i].hidden_effects.is_some() && m.deformations[i].detectability.is_none()
        })
        .collect();
    let mut report = DetectabilityReport {
        kept: m
            .deformations
            .iter()
            .filter(|d| d.detectability.is_some())
            .count(),
        ..Default::default()
    };
    for (k, &i) in todo.iter().enumerate() {
        let d = m.deformations[i].clone();
        progress(k, todo.len(), &d.id);
        let Some((truth, known)) = truth_physics(&d)? else {
            continue;
        };
        let geo =
            crate::dataset::read::load_geometry(dir, &m, &d.geometry).map_err(|e| e.to_string())?;
        let scenarios = crate::dataset::read::load_scenarios(dir, &d).map_err(|e| e.to_string())?;
        let sweeps: Vec<crate::discover::Sweep> = scenarios
            .iter()
            .map(|s| {
                let measurements = s
                    .measurements
                    .with_alignment(Some(s.truth.image_to_physical))
                    .map_err(|e| format!("{}: {e}", s.id))?;
                Ok(crate::discover::Sweep {
                    id: s.id.clone(),
                    measurements,
                })
            })
            .collect::<Result<_, String>>()?;
        match detectability(&geo.model, &sweeps, &truth, &known, params, Some(&cache)) {
            Ok(det) => {
                report.computed += 1;
                report.detectable += usize::from(det.detectable);
                let mut entry = d.clone();
                entry.detectability = Some(det);
                let base = Path::new(&entry.npz)
                    .parent()
                    .ok_or_else(|| format!("{}: npz path {:?} has no folder", d.id, entry.npz))?
                    .to_path_buf();
                write_json(&dir.join(base).join("deformation.json"), &entry)?;
                m.deformations[i] = entry;
                write_json(&dir.join("manifest.json"), &m)?;
            }
            Err(e) => report.errors.push(format!("{}: {e}", d.id)),
        }
    }
    progress(todo.len(), todo.len(), "");
    Ok(report)
}

fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<(), String> {
    let mut s = serde_json::to_string_pretty(value).map_err(|e| e.to_string())?;
    s.push('\n');
    crate::util::write_atomic(path, s.as_bytes()).map_err(|e| e.to_string())
}
