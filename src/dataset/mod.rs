//! The on-disk dataset format (version [`VERSION`]): the manifest's types and its reader.
//!
//! Shared by the generator (`phantom::dataset`) and everything that reads datasets back
//! (evaluation, training, the service's replay clients), which never import `phantom`. Layout of a
//! dataset directory (paths in the manifest are relative to it):
//!
//! ```text
//! manifest.json                          this file's types, format "librplus-dataset", version 1
//! geometries/<g>/preop.vtu               preoperative tet mesh; point data region (0 interior,
//!                                        1 anterior, 2 posterior), falciform, inferior_ridge,
//!                                        bare_area, target, tumour; cell data tissue (0 parenchyma,
//!                                        1 vessel, 2 tumour), youngs_modulus_kpa
//! geometries/<g>/vessels.vtp             vessel centerline points: radius_mm, parent (−1 root)
//! deformations/<d>/gt.vtu                ground truth: the preop mesh with point array displacement
//! deformations/<d>/scenarios/<k>.vtp     one scenario's measured points (physical frame) with point
//!                                        data kind (0 surface, 1 posterior contour, 2 vessel),
//!                                        plane (−1 for surface points), feature (0 none,
//!                                        1 falciform, 2 inferior ridge), truth_image (evaluation only)
//! deformations/<d>/scenarios.npz         every scenario of the deformation plus the mesh and the
//!                                        ground truth, for numpy (docs/dataset-and-models.md lists the arrays)
//! deformations/<d>/deformation.json      the deformation's manifest entry (written last: marks it
//!                                        complete; used to resume)
//! ```

pub mod read;

use std::path::Path;

/// Value of the manifest's `format` field.
pub const FORMAT: &str = "librplus-dataset";
/// Current format version.
pub const VERSION: u32 = 1;

/// The dataset manifest (`manifest.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Format version ([`VERSION`]).
    pub version: u32,
    /// Preset name (`small`, `paper`).
    pub preset: String,
    /// Master seed.
    pub seed: u64,
    /// Program and version that wrote it.
    pub generator: String,
    /// Length unit of every coordinate (`mm`).
    pub units: String,
    /// Patient frame (`LPS`).
    pub frame: String,
    /// Hash (FNV-1a 64, hex) of `parameters`: a resumed run must match it.
    pub parameters_hash: String,
    /// Every parameter that shaped the data.
    pub parameters: serde_json::Value,
    /// The liver geometries.
    pub geometries: Vec<GeometryEntry>,
    /// Completed deformations, in plan order.
    pub deformations: Vec<DeformationEntry>,
    /// Planned deformations not on disk yet (other shards, or an interrupted run).
    pub missing: Vec<String>,
    /// Draws that did not converge and were replaced by the next attempt (never written as truth).
    pub failed: Vec<FailedEntry>,
    /// True when every planned deformation is complete.
    pub complete: bool,
}

impl Manifest {
    /// Ids of the geometries marked `test` (held out of training: the pattern-V geometry).
    pub fn test_geometries(&self) -> Vec<&str> {
        self.geometries
            .iter()
            .filter(|g| g.split == "test")
            .map(|g| g.id.as_str())
            .collect()
    }
}

/// One liver geometry.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GeometryEntry {
    /// Identifier (`g1`, …).
    pub id: String,
    /// Where the surface came from, and the shape-variant seed if any.
    pub source: String,
    /// Shape-variant seed, `None` for the surface as given.
    pub variant_seed: Option<u64>,
    /// `train` or `test`.
    pub split: String,
    /// Node count.
    pub nodes: usize,
    /// Tet count.
    pub tets: usize,
    /// Volume (mL).
    pub volume_ml: f64,
    /// Target edge length of the mesher (mm).
    pub edge_mm: f64,
    /// Path of `preop.vtu`.
    pub preop: String,
    /// Path of `vessels.vtp`.
    pub vessels: String,
    /// Interior target nodes.
    pub targets: Vec<u32>,
    /// Vessel stiffness multiplier.
    pub vessel_factor: f64,
    /// Tumours: centre (mm), radius (mm), stiffness multiplier.
    pub tumours: Vec<TumourEntry>,
    /// Volume fractions of parenchyma, vessel and tumour tissue.
    pub tissue_fractions: [f64; 3],
}

/// A tumour of a geometry.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TumourEntry {
    /// Centre (mm).
    pub center: [f64; 3],
    /// Radius (mm).
    pub radius_mm: f64,
    /// Young's modulus multiplier.
    pub stiffness_factor: f64,
}

/// Whether the discovery workflow's own held-out test can see a deformation's hidden effects
/// when told everything (`deformation.json`'s `detectability`, written by `generate` for
/// `--truth libr` data with hidden effects): the true effects with their true shapes (their
/// amplitudes fitted) against plain LIBR, on the deformation's scenarios registered from their
/// true poses, by the same paired test of held-out misfits and the same rule that names an
/// effect. An effect the oracle cannot see, no method can be asked to name.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Detectability {
    /// Wilcoxon signed-rank z over the sweep × block units of the held-out misfit the true
    /// model removes (positive: it fits the held-out data better).
    pub statistic: f64,
    /// The z the workflow needs to name an effect.
    pub threshold: f64,
    /// Fraction of plain LIBR's held-out misfit (mean square) the true model removes.
    pub gain: f64,
    /// The fraction the workflow needs.
    pub min_gain: f64,
    /// Change of the Bayesian information criterion (negative favours the true model).
    pub delta_bic: f64,
    /// Whether every part of the rule holds: `statistic > threshold`, `gain > min_gain` and
    /// `delta_bic < 0`.
    pub detectable: bool,
    /// Held-out RMS misfit (mm) of plain LIBR and of the true model, on the points both matched.
    pub heldout_rms_mm: [f64; 2],
    /// Sweeps the test used (a sweep either model cannot register is left out of both).
    pub sweeps: usize,
    /// Rows.
    pub rows: usize,
}

/// One ground-truth deformation and its scenarios.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DeformationEntry {
    /// Identifier (`g1-L-00`, …).
    pub id: String,
    /// Geometry id.
    pub geometry: String,
    /// Pattern (`L`, `R`, `W`, `V`).
    pub pattern: String,
    /// Seed of the load draw that converged.
    pub seed: u64,
    /// The parameters hash it was generated under.
    pub parameters_hash: String,
    /// What was drawn (tilt, retractor, pack, pressure).
    pub description: String,
    /// Path of `gt.vtu`.
    pub gt: String,
    /// Path of `scenarios.npz`.
    pub npz: String,
    /// Mean node displacement (mm).
    pub mean_displacement_mm: f64,
    /// Largest node displacement (mm).
    pub max_displacement_mm: f64,
    /// Mean node distance between the ground truth and the linear homogeneous model under the
    /// same loads and supports (mm): what LIBR's physics misses. Under `--truth libr`: to LIBR's
    /// physics without the hidden effects under the same load (0 when nothing is hidden).
    pub linear_homogeneous_gap_mm: f64,
    /// Newton load steps.
    pub load_steps: usize,
    /// Newton iterations.
    pub newton_iterations: usize,
    /// Final relative residual.
    pub relative_residual: f64,
    /// Bed contacts active at equilibrium, of all.
    pub active_contacts: [usize; 2],
    /// Under `generate --truth libr`: the effects hidden in the truth with their drawn
    /// parameters, as a `physics.json` value (format 1; `"effects": []` when nothing is hidden),
    /// also written beside it as `hidden_physics.json`. Absent for the other truths.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hidden_effects: Option<serde_json::Value>,
    /// Under `generate --truth libr` with hidden effects: whether the workflow's own test sees
    /// them when told the truth ([`Detectability`]). Absent otherwise, and where generation
    /// was told not to compute it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detectability: Option<Detectability>,
    /// Under `generate --families`: the truth family this deformation's truth was drawn from and
    /// its parameters. Absent otherwise (the truth is then the default Neo-Hookean one, or
    /// `--truth`'s).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth_family: Option<TruthFamilyRecord>,
    /// The scenarios.
    pub scenarios: Vec<ScenarioEntry>,
}

impl DeformationEntry {
    /// The truth family's name: the recorded one, else `neo-hookean` for the default nonlinear
    /// truth and `libr` for `--truth libr` data (which record their hidden effects).
    pub fn family(&self) -> &str {
        match (&self.truth_family, &self.hidden_effects) {
            (Some(f), _) => &f.name,
            (None, Some(_)) => "libr",
            (None, None) => "neo-hookean",
        }
    }
}

/// The truth family a deformation was drawn from (`deformation.json`'s `truth_family`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TruthFamilyRecord {
    /// Family name (`neo-hookean`, `mooney-rivlin`, `demiray`, `stiff-vessels`, `sparse-sensor`,
    /// `dense-sensor`).
    pub name: String,
    /// The strain-energy law (`neo-hookean`, `mooney-rivlin`, `demiray`).
    pub law: String,
    /// What was drawn (`i2_share`, `stiffening`, `vessel_factor` and `tumour_factor`).
    pub parameters: serde_json::Value,
}

/// One sparse-measurement scenario.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ScenarioEntry {
    /// Index within the deformation (row of the npz per-scenario arrays).
    pub index: usize,
    /// Category (`surface`, `surface+1us`, `surface+2us`, `surface+3us`, `surface+16us`).
    pub category: String,
    /// Seed.
    pub seed: u64,
    /// Path of the `.vtp`.
    pub file: String,
    /// Anterior-surface coverage achieved.
    pub coverage: f64,
    /// Surface points.
    pub surface_points: usize,
    /// Posterior-contour points.
    pub contour_points: usize,
    /// Vessel-feature points.
    pub vessel_points: usize,
    /// Surface points designated on a salient feature (falciform ligament, inferior ridge).
    pub feature_points: usize,
    /// Misalignment rotation (degrees).
    pub misalignment_deg: f64,
}

/// A draw that did not converge.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FailedEntry {
    /// Deformation id.
    pub id: String,
    /// Seed of the failed draw.
    pub seed: u64,
    /// Why.
    pub error: String,
}

/// Why a dataset (its manifest, meshes or scenario arrays) could not be read.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A file could not be read.
    #[error(transparent)]
    File(#[from] crate::util::FileError),
    /// The manifest is not valid JSON of the expected shape.
    #[error("{}: {source}", path.display())]
    Json {
        /// The manifest.
        path: std::path::PathBuf,
        /// The parser's error.
        source: serde_json::Error,
    },
    /// A mesh file could not be read.
    #[error(transparent)]
    Mesh(#[from] crate::mesh::io::IoError),
    /// A scenario archive could not be decoded.
    #[error("{file}: {source}")]
    Npz {
        /// The archive (relative to the dataset).
        file: String,
        /// The decoder's error.
        source: crate::mesh::io::npz::NpzError,
    },
    /// A file holds something other than this format expects (the message names the file and
    /// what it expects): another format or version, a missing array, an index out of range.
    #[error("{0}")]
    Content(String),
    /// The preoperative mesh's labels or vessels are inconsistent.
    #[error(transparent)]
    Model(#[from] crate::register::RegisterError),
}

/// Reads and checks a manifest (`manifest.json` in `dir`, or the file itself).
pub fn read_manifest(path: &Path) -> Result<Manifest, DatasetError> {
    let file = if path.is_dir() {
        path.join("manifest.json")
    } else {
        path.to_path_buf()
    };
    let text =
        std::fs::read_to_string(&file).map_err(crate::util::FileError::at("reading", &file))?;
    let m: Manifest = serde_json::from_str(&text).map_err(|source| DatasetError::Json {
        path: file.clone(),
        source,
    })?;
    if m.format != FORMAT {
        return Err(DatasetError::Content(format!(
            "{}: format is {:?}, expected {FORMAT:?}",
            file.display(),
            m.format
        )));
    }
    if m.version != VERSION {
        return Err(DatasetError::Content(format!(
            "{}: format version {} is not supported (this program reads version {VERSION})",
            file.display(),
            m.version
        )));
    }
    Ok(m)
}
