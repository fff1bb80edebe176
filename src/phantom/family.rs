//! Truth families: the physics a deformation's ground truth is made with.
//!
//! A network trained on one simulator learns that simulator's residual; whether it holds on
//! physics it never saw can only be measured on truths made otherwise. A dataset generated with
//! `--families` draws each deformation's truth from one of these families (cycling through them
//! in the plan's order) and records it in `deformation.json` as `truth_family`; the split
//! `family:NAME` then holds one family out of training entirely.
//!
//! Every family keeps the same small-strain physics (the same Lamé field as the geometry's drawn
//! tissue, or a different map of it), so the linear model LIBR fits is equally right or wrong at
//! small strain; they differ where strains are large or where the stiffness map differs:
//! - `neo-hookean`: today's truth (compressible Neo-Hookean, the drawn tissue field).
//! - `mooney-rivlin`: a compressible Mooney–Rivlin solid, a share `s` ∈ [0.3, 0.8] of the shear
//!   modulus on the second invariant (liver fits in the literature put much of it there).
//! - `demiray`: Demiray's exponential soft-tissue law, stiffening `b` ∈ [1.5, 5] (strain
//!   stiffening as measured on liver in indentation).
//! - `stiff-vessels`: Neo-Hookean with another stiffness map: the vessel tree a further
//!   3–8 × stiffer than drawn (calcified or fibrotic portal tracts) and tumours 2–4 × stiffer.
//!
//! Two families keep the default truth and change the sensor instead (what a navigation
//! system other than the generator's measures):
//! - `sparse-sensor`: surface points 8 mm apart with 2 mm noise over 10–35 % of the anterior
//!   surface, ultrasound contours 1 mm noisy (a coarse tracked stylus or a noisy stereo camera).
//! - `dense-sensor`: surface points 3 mm apart with 0.5 mm noise over 30–80 % (a laser or
//!   structured-light scanner).

use super::PhantomError;
use super::measure::MeasureParams;
use super::tissue::{Tissue, TissueKind};
use crate::fem::hyperelastic::MaterialLaw;
use crate::fem::{LameField, LinearMaterial};
use crate::util::SplitMix64;

/// A family of ground truths.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TruthFamily {
    /// Compressible Neo-Hookean on the drawn tissue field (the default truth).
    NeoHookean,
    /// Compressible Mooney–Rivlin on the drawn tissue field.
    MooneyRivlin,
    /// Demiray's exponential law on the drawn tissue field.
    Demiray,
    /// Neo-Hookean with a much stiffer vessel tree and stiffer tumours.
    StiffVessels,
    /// The default truth, measured sparser and noisier over less of the surface.
    SparseSensor,
    /// The default truth, measured denser and less noisy over more of the surface.
    DenseSensor,
}

/// One deformation's draw from a family: the law, the Lamé field to use instead of the
/// geometry's (if any), and what was drawn (recorded in `deformation.json`).
#[derive(Debug, Clone)]
pub struct FamilyDraw {
    /// The strain-energy law.
    pub law: MaterialLaw,
    /// A Lamé field replacing the geometry's drawn one.
    pub lame: Option<LameField>,
    /// The family's name and drawn parameters.
    pub record: crate::dataset::TruthFamilyRecord,
}

impl TruthFamily {
    /// Every family, in the order `--families all` cycles through them.
    pub const ALL: [TruthFamily; 6] = [
        TruthFamily::NeoHookean,
        TruthFamily::MooneyRivlin,
        TruthFamily::Demiray,
        TruthFamily::StiffVessels,
        TruthFamily::SparseSensor,
        TruthFamily::DenseSensor,
    ];

    /// The family's name (`neo-hookean`, `mooney-rivlin`, `demiray`, `stiff-vessels`,
    /// `sparse-sensor`, `dense-sensor`).
    pub fn name(self) -> &'static str {
        match self {
            Self::NeoHookean => "neo-hookean",
            Self::MooneyRivlin => "mooney-rivlin",
            Self::Demiray => "demiray",
            Self::StiffVessels => "stiff-vessels",
            Self::SparseSensor => "sparse-sensor",
            Self::DenseSensor => "dense-sensor",
        }
    }

    /// The measurement settings of this family's scenarios, from the dataset's.
    pub fn measure(self, base: &MeasureParams) -> MeasureParams {
        match self {
            Self::SparseSensor => MeasureParams {
                coverage: [0.10, 0.35],
                surface_spacing_mm: 8.0,
                surface_noise_mm: 2.0,
                us_noise_mm: 1.0,
                ..*base
            },
            Self::DenseSensor => MeasureParams {
                coverage: [0.30, 0.80],
                surface_spacing_mm: 3.0,
                surface_noise_mm: 0.5,
                ..*base
            },
            _ => *base,
        }
    }

    /// Parses a comma-separated list of names, or `all`.
    pub fn parse_list(s: &str) -> Result<Vec<TruthFamily>, PhantomError> {
        if s.trim() == "all" {
            return Ok(Self::ALL.to_vec());
        }
        let mut out = Vec::new();
        for name in s.split(',').map(str::trim) {
            let f = Self::ALL
                .into_iter()
                .find(|f| f.name() == name)
                .ok_or_else(|| {
                    PhantomError::Parameter(format!(
                        "families: unknown truth family {name:?}; expected all or a list of {}",
                        Self::ALL.map(|f| f.name()).join(", ")
                    ))
                })?;
            if out.contains(&f) {
                return Err(PhantomError::Parameter(format!(
                    "families: {name} is listed twice"
                )));
            }
            out.push(f);
        }
        Ok(out)
    }

    /// Draws this family's parameters for one deformation from `seed`.
    pub fn draw(self, tissue: &Tissue, seed: u64) -> FamilyDraw {
        let mut rng = SplitMix64::new(seed ^ 0x0FA3_11E5_0000_0008);
        let mut uniform = |lo: f64, hi: f64| lo + (hi - lo) * rng.next_f64();
        let (law, lame, parameters) = match self {
            Self::NeoHookean => (MaterialLaw::NeoHookean, None, serde_json::json!({})),
            Self::SparseSensor | Self::DenseSensor => {
                let m = self.measure(&MeasureParams::default());
                (
                    MaterialLaw::NeoHookean,
                    None,
                    serde_json::json!({
                        "coverage": m.coverage,
                        "surface_spacing_mm": m.surface_spacing_mm,
                        "surface_noise_mm": m.surface_noise_mm,
                        "us_noise_mm": m.us_noise_mm,
                    }),
                )
            }
            Self::MooneyRivlin => {
                let s = uniform(0.3, 0.8);
                (
                    MaterialLaw::MooneyRivlin { i2_share: s },
                    None,
                    serde_json::json!({ "i2_share": s }),
                )
            }
            Self::Demiray => {
                let b = uniform(1.5, 5.0);
                (
                    MaterialLaw::Demiray { stiffening: b },
                    None,
                    serde_json::json!({ "stiffening": b }),
                )
            }
            Self::StiffVessels => {
                let vessel = uniform(3.0, 8.0);
                let tumour = uniform(2.0, 4.0);
                let field = LameField::PerTet(
                    tissue
                        .youngs_kpa
                        .iter()
                        .zip(&tissue.kind)
                        .map(|(&e, k)| {
                            let f = match k {
                                TissueKind::Parenchyma => 1.0,
                                TissueKind::Vessel => vessel,
                                TissueKind::Tumour => tumour,
                            };
                            LinearMaterial::new(e * f, tissue.poisson_ratio).lame()
                        })
                        .collect(),
                );
                (
                    MaterialLaw::NeoHookean,
                    Some(field),
                    serde_json::json!({ "vessel_factor": vessel, "tumour_factor": tumour }),
                )
            }
        };
        FamilyDraw {
            law,
            lame,
            record: crate::dataset::TruthFamilyRecord {
                name: self.name().into(),
                law: law.name().into(),
                parameters,
            },
        }
    }
}
