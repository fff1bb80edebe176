//! LIBR: linearized iterative boundary reconstruction (after Heiselman & Miga, IEEE TMI 2020).
//!
//! This module owns the LIBR deformation basis and the regularized least-squares fit of its
//! weights plus a rigid correction to matched sparse data.
//!
//! **Basis.** `K` control points are spread evenly over the boundary by farthest-point sampling
//! (Euclidean, deterministic from [`BasisParams::seed`]). For each control point `c` and axis `a`
//! the load is a smooth, localized surface traction `t(x) = e_a · exp(−|x − c|²/2σ²) ·
//! max(0, n(x)·n_c)` (σ = [`BasisParams::load_width`]; the normal factor keeps a patch from leaking
//! through thin parts of the organ to the opposite face), lumped to nodes by
//! [`loads::add_traction`](crate::fem::loads::add_traction). Column `j` of the basis `Φ` (3n × 3K, node-major rows) is the
//! linear-elastic response to load `j`, all columns from one sparse Cholesky factorization.
//!
//! **Supports (the free-floating body).** The liver in the abdomen is not clamped anywhere we
//! know of, and any rigid motion is a separate unknown of the fit, so the basis must hold pure
//! deformations. We therefore fix nothing physically and use *inertia relief*, the standard
//! treatment of unsupported bodies in structural FEA: each load `f` is replaced by its
//! self-equilibrated part `f_eq = f − M R (RᵀMR)⁻¹ Rᵀ f` (M the lumped nodal volumes, R the six
//! rigid modes), i.e. the unbalanced force and moment are carried by a uniform rigid-body
//! acceleration of the whole volume. `K u = f_eq` is then consistent but singular; it is solved
//! with a statically determinate 3-2-1 support (6 dofs on three far-apart boundary nodes), whose
//! reactions are zero for a self-equilibrated load, so `K u = f_eq` holds at *every* dof, and the
//! rigid part is projected out (`u ⟂_M R`). Unlike weak springs on the boundary this has no
//! stiffness to tune and biases nothing: the columns are exact free-body responses and the rigid
//! motion is left entirely to the fit's rigid unknowns.
//!
//! **Scaling.** Each column is scaled so that its largest node displacement is 1 mm
//! ([`LibrBasis::load_scale`] keeps the traction peak in kPa that gives it), so the weights α
//! are in mm. `E = ΦᵀKΦ` (mN·mm per mm², strain energy `½ αᵀEα` in µJ) is stored with it.
//!
//! **Fit.** [`fit_step`] minimises, over α (3K) and a small rigid correction (rotation ω about
//! the matched anchors' centroid `c̄`, translation τ, linearized),
//! `Σ wᵢ |pᵢ(α) + ω × (aᵢ − c̄) + τ − yᵢ|² / Σ wᵢ + λ αᵀẼα`, with `pᵢ(α) = Match::model_point(Φα)`,
//! `aᵢ` the anchor and `Ẽ = E / ē` where `ē` is the mean diagonal of `E` (the energy of one
//! 1 mm basis mode). The misfit is a weighted mean square in mm² and `αᵀẼα` ≈ `Σ αⱼ²` in mm², so
//! λ ([`FitParams::regularization`]) is dimensionless and independent of mesh size, number of
//! matches and Young's modulus: λ = 1 makes one 1 mm mode cost as much as 1 mm RMS misfit.
//! [`solve`] iterates the step, re-matching through a caller-supplied function, composing the
//! rigid correction exactly (rotation by `exp(ω)`), until the largest node movement of an
//! iteration falls below [`FitParams::tolerance_mm`] or the fit has settled ([`settled`]: its
//! residual stopped falling and the model is not running away, so further iterations only cycle
//! the closest-point matches around the fit; not while the movement is still [`shrinking`]
//! geometrically), at most [`FitParams::max_iterations`].
//!
//! **Cache.** [`LibrBasis::load_or_build`] keeps the basis in `cache_dir` as a NumPy `.npz`
//! named by the mesh hash and the hash of the basis-relevant parameters; an unreadable,
//! truncated or mismatched file is rebuilt and overwritten, never used.
//!
//! Units: mm, kPa, mN, µJ. Frames: the model and `u` in the image frame; see [`crate::register`].

mod adaptive;
mod basis;
mod cache;
mod coarse;
mod cv;
mod fit;
mod iterate;
mod nonlinear;
mod refit;
mod solve;

pub use adaptive::*;
pub use basis::*;
pub use cache::*;
pub use coarse::*;
pub use cv::*;
pub use fit::*;
pub use nonlinear::*;
pub use refit::*;
pub use solve::*;

use super::RegisterError;
use crate::fem::LinearMaterial;
use crate::mesh::vec3::{cross, dist2, dot, sub, unit};
use crate::util::fnv1a_hex;

/// Version of the basis and its cache format; part of the parameter hash.
pub const BASIS_VERSION: u32 = 1;

/// Width σ of each control point's Gaussian traction patch.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum LoadWidth {
    /// σ in mm.
    Mm(f64),
    /// σ as a multiple of the expected control-point spacing `√(2A / (√3 K))` (A the boundary
    /// area: the spacing of K points in a hexagonal packing).
    Spacing(f64),
}

/// What determines a LIBR basis: the control points, their load patches, the material and the
/// sampling seed. A prepared case records these ([`LibrBasis::params_hash`] is their
/// [`BasisParams::hash`]); registering with other ones is a mismatch.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BasisParams {
    /// Number of control points K (the basis has 3K columns). Default 25: on the training split of
    /// the paper preset (`librplus evaluate --split train`), 25 gave 6.9 mm mean TRE, 40 7.4,
    /// 60 7.7 and 120 8.5 (BENCHMARKS.md); fewer, broader modes are better determined by sparse
    /// data and converge in fewer iterations.
    pub control_points: usize,
    /// Width of each control point's traction patch. Default 1.25 × spacing.
    pub load_width: LoadWidth,
    /// Linear-elastic material of the model. Default E = 5 kPa, ν = 0.45.
    pub material: LinearMaterial,
    /// Chooses the first control point of the farthest-point sampling. Default 0.
    pub seed: u64,
}

/// How a LIBR basis is fitted to the data: regularization, matching and iterations. Changing
/// these never changes the basis.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FitParams {
    /// Strain-energy regularization λ (dimensionless, see the module doc). Default 1e-3 (swept
    /// 1e-4 … 1e-1 on the training split).
    pub regularization: f64,
    /// Weight of the misfit along a matched surface (tangentially) relative to across it (1 = plain
    /// point-to-point; 0 = pure point-to-plane, one row per match). Matches without a normal
    /// (vessels) count fully in every direction. Default 0: closest-point pairs say nothing about
    /// where along the surface a point belongs, and pinning them there holds the surface back
    /// from sliding into place (mean TRE on every 28th block of the paper preset: 0.2 → 6.88 mm,
    /// 0.05 → 6.16, 0.001 → 5.78, 0.0001 → 5.77).
    pub tangential_weight: f64,
    /// Floor (mm) of the correspondence trimming during LIBR: a pair is dropped beyond
    /// `trim_factor × median + trim_floor_mm` (the rigid stage keeps its own, tighter floor).
    /// Default 30: deformation moves parts of the organ by tens of millimetres (a retracted lobe),
    /// and trimming those pairs as outliers keeps the fit from ever reaching them (same blocks:
    /// 5 mm → 5.78 mm, 15 → 5.66, 30 → 5.57, no trimming → 5.55), while gross outliers are still
    /// dropped.
    pub trim_floor_mm: f64,
    /// Most iterations of [`solve`]. Default 20.
    pub max_iterations: usize,
    /// [`solve`] stops when no node moved more than this in an iteration (mm). Default 0.01.
    pub tolerance_mm: f64,
    /// LIBR's correspondences are weighted by a robust (Cauchy) kernel instead of trimmed by the
    /// median (`CorrespondenceParams::robust_kernel`). Default false; a held organ's fit uses it
    /// (the held-organ mode). On the paper preset (seed 2) it changed LIBR by −0.04 mm (500
    /// scenarios) and +0.04 mm (every fifth block) but made LIBR+ worse (3.61 → 3.79 mm: its
    /// network learned the trimmed LIBR's residual) and adaptive LIBR slightly (6.61 → 6.65).
    #[serde(default)]
    pub robust_kernel: bool,
}

/// Parameters of the LIBR basis and fit: the two are separate types, since a prepared case's
/// basis fixes the first and a registration may vary the second.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LibrParams {
    /// What the basis is built from.
    #[serde(flatten)]
    pub basis: BasisParams,
    /// How it is fitted.
    #[serde(flatten)]
    pub fit: FitParams,
}

impl Default for BasisParams {
    fn default() -> Self {
        Self {
            control_points: 25,
            load_width: LoadWidth::Spacing(1.25),
            material: LinearMaterial::default(),
            seed: 0,
        }
    }
}

impl Default for FitParams {
    fn default() -> Self {
        Self {
            regularization: 1e-3,
            tangential_weight: 0.0,
            trim_floor_mm: 30.0,
            max_iterations: 20,
            tolerance_mm: 0.01,
            robust_kernel: false,
        }
    }
}

/// The defaults of both parts. Every path (the command line, `evaluate`, the server) takes them
/// through the pipeline's `PipelineParams::default`, which makes them here.
impl Default for LibrParams {
    fn default() -> Self {
        Self {
            basis: BasisParams::default(),
            fit: FitParams::default(),
        }
    }
}

impl BasisParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        if self.control_points == 0 {
            return Err(RegisterError::Parameter(
                "control_points must be at least 1".into(),
            ));
        }
        match self.load_width {
            LoadWidth::Mm(w) | LoadWidth::Spacing(w) if !(w.is_finite() && w > 0.0) => {
                return Err(RegisterError::Parameter(format!(
                    "load_width must be finite and > 0, got {w}"
                )));
            }
            _ => {}
        }
        self.material
            .validate()
            .map_err(|e| RegisterError::Parameter(format!("material: {e}")))
    }

    /// Hash (16 hex digits) of what determines the basis: version, control points, load width,
    /// material, seed.
    pub fn hash(&self) -> String {
        let key = serde_json::json!({
            "version": BASIS_VERSION,
            "control_points": self.control_points,
            "load_width": self.load_width,
            "material": self.material,
            "seed": self.seed,
        });
        fnv1a_hex(key.to_string().as_bytes())
    }

    /// These parameters with the one level `(count, width)` in place of the control points and
    /// their width (one level of a multi-resolution basis).
    pub fn with_level(self, count: usize, width: LoadWidth) -> Self {
        Self {
            control_points: count,
            load_width: width,
            ..self
        }
    }
}

impl FitParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        if !(self.tangential_weight.is_finite()
            && self.tangential_weight >= 0.0
            && self.tangential_weight <= 1.0)
        {
            return Err(RegisterError::Parameter(format!(
                "tangential_weight must be in [0, 1], got {}",
                self.tangential_weight
            )));
        }
        if !(self.regularization.is_finite() && self.regularization >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "regularization must be finite and >= 0, got {}",
                self.regularization
            )));
        }
        if !(self.trim_floor_mm.is_finite() && self.trim_floor_mm >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "trim_floor_mm must be finite and >= 0, got {}",
                self.trim_floor_mm
            )));
        }
        if !(self.tolerance_mm.is_finite() && self.tolerance_mm >= 0.0) {
            return Err(RegisterError::Parameter(format!(
                "tolerance_mm must be finite and >= 0, got {}",
                self.tolerance_mm
            )));
        }
        Ok(())
    }
}

impl LibrParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        self.basis.validate()?;
        self.fit.validate()
    }

    /// [`BasisParams::hash`] of the basis part.
    pub fn basis_hash(&self) -> String {
        self.basis.hash()
    }
}
