//! What physics knows about a load effect before the data: how large it is and which way it
//! points. Without it, an effect's free amplitude is just one more unregularised mode; sparse
//! data extrapolated by LIBR's strain-energy prior leave smooth misfits that such a mode
//! absorbs at a fraction of the effect's physical size (measured: with nothing hidden, a
//! free gravity column pointing anteriorly at 25–65 % of the organ's weight lowered the
//! held-out misfit by 14–36 %). A candidate must explain the data *at a physically plausible
//! size*; that is what names it.
//!
//! | kind | amplitude prior (Gaussian) | direction | source |
//! | --- | --- | --- | --- |
//! | `gravity` | `magnitude` 0.0104 ± 0.0031 mN/mm³ | within 90° of posterior (+y) | ρg of liver (1.06 g/cm³); ±30 % for density, what neighbours carry, and the model's Young's modulus (a linear model identifies load / E) |
//! | `pressure` | `magnitude_kpa` 1.4 ± 0.6 kPa | faces within 90° of anterior (−y) | pneumoperitoneum 7–14 mmHg (0.93–1.87 kPa) |
//! | `pack` | force along the inward normal 5000 ± 3000 mN, across it 0 ± 2500 mN | – | swabs and retractors push a few newtons (2–8 N) |
//!
//! Gravity carried only by local supports (a fixation patch, the falciform ligament; no bed) may
//! be a share of the weight, down to 10 % of ρg: the neighbouring organs carry the rest.
//!
//! The frame is the product's (LPS: anterior −y). The patient lies supine or on the side during
//! liver surgery, never prone, so the organ's weight points posteriorly within 90°, and the
//! insufflated space is anterior.
//!
//! The numbers are each kind's entry in the table of kinds ([`crate::register::physics::kinds`]);
//! this module reads them.

use crate::register::physics::kinds::{Hold, LoadPrior};
use crate::register::physics::model::BoundaryGeometry;
use crate::register::physics::{Effect, EffectKind};
use nalgebra::{DMatrix, DVector};

pub use crate::register::physics::kinds::{
    GRAVITY_MAGNITUDE, GRAVITY_SD, LOCAL_WEIGHT_SHARE, PACK_FORCE_MN, PRESSURE_KPA,
};

/// The plausible size of a load effect's amplitude (`magnitude`, `magnitude_kpa`, the norm of
/// `force_mn`): the physical range of the table above, widened by a factor of two either way
/// (for the model's Young's modulus, which scales every fitted load). The Gaussian prior alone
/// does not keep a candidate physical: thousands of rows outweigh it, and the rows' misfit is
/// mostly correlated model error that a free amplitude fits at any size; a fitted amplitude
/// outside this range is not the named effect.
pub fn plausible_amplitude(kind: EffectKind) -> Option<(f64, f64)> {
    kind.load().map(|l| l.plausible)
}

/// Whether a load effect's fitted amplitude is of a plausible size (always for other kinds).
pub fn amplitude_plausible(effect: &Effect) -> bool {
    amplitude_plausible_on(effect, &crate::register::physics::Physics::none())
}

/// [`amplitude_plausible`] for a load carried by the supports of `physics`: where only local
/// supports (fixation, ligament) carry it, the weight they carry may be a share of the organ's
/// weight down to [`LOCAL_WEIGHT_SHARE`] of its lower physical value.
pub fn amplitude_plausible_on(
    effect: &Effect,
    physics: &crate::register::physics::Physics,
) -> bool {
    let Some((mut lo, hi)) = plausible_amplitude(effect.kind) else {
        return true;
    };
    let local_only = physics
        .effects
        .iter()
        .any(|e| e.kind.hold() == Some(Hold::Local))
        && !physics
            .effects
            .iter()
            .any(|e| e.kind.hold() == Some(Hold::Bed));
    if let Some(floor) = effect.kind.load().and_then(|l| l.local_floor)
        && local_only
    {
        lo = floor;
    }
    let Some((name, _)) = effect.kind.amplitude() else {
        return true;
    };
    let Some(v) = effect.parameters.get(name) else {
        return false;
    };
    let size = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let signed = if v.len() == 1 { v[0] } else { size };
    signed >= lo && signed <= hi
}

/// The cone a load's direction must lie in: axis and largest angle (degrees); `None` where any
/// direction is plausible.
pub fn direction_cone(kind: EffectKind) -> Option<([f64; 3], f64)> {
    kind.load().and_then(|l| l.cone)
}

/// Whether `d` lies in the kind's direction cone.
pub fn direction_plausible(kind: EffectKind, d: [f64; 3]) -> bool {
    direction_cone(kind).is_none_or(|(axis, max)| {
        crate::mesh::vec3::angle_deg(crate::mesh::vec3::unit(d), axis) <= max + 1e-9
    })
}

/// The prior of an effect's amplitudes in the units of its parameter (`magnitude`,
/// `magnitude_kpa`, `force_mn`): precision (k × k) and mean (k), `k` the effect's columns.
/// `None` for kinds without amplitudes.
pub fn amplitude_prior(
    effect: &Effect,
    mesh_nodes: &[[f64; 3]],
    geom: &BoundaryGeometry,
) -> Option<(DMatrix<f64>, DVector<f64>)> {
    match effect.kind.load()?.prior {
        LoadPrior::Gaussian { mean, sd } => Some((
            DMatrix::from_element(1, 1, 1.0 / (sd * sd)),
            DVector::from_element(1, mean),
        )),
        LoadPrior::Inward {
            at,
            mean,
            sd_along: sd_n,
            sd_across: sd_t,
        } => {
            let c = effect.vector(at);
            let v = geom.nodes.iter().copied().min_by(|&a, &b| {
                crate::mesh::vec3::dist2(mesh_nodes[a as usize], c)
                    .total_cmp(&crate::mesh::vec3::dist2(mesh_nodes[b as usize], c))
            })?;
            let out = crate::mesh::vec3::unit(geom.node_normal[v as usize]);
            let n = DVector::from_iterator(3, out.iter().map(|x| -x));
            let nnt = &n * n.transpose();
            let precision = &nnt / (sd_n * sd_n) + (DMatrix::identity(3, 3) - &nnt) / (sd_t * sd_t);
            Some((precision, n * mean))
        }
    }
}

/// The prior in coefficient space: a column scaled to a 1 mm peak has amplitude
/// `coefficient × scale`, and the misfit is in mm² per unit weight, so the prior's precision is
/// multiplied by the noise variance `noise_var` (a Gaussian prior with the likelihood's own
/// scale). Returns `(P, P μ)` for the effect's columns.
pub fn coefficient_prior(
    precision: &DMatrix<f64>,
    mean: &DVector<f64>,
    scales: &[f64],
    noise_var: f64,
) -> (DMatrix<f64>, DVector<f64>) {
    let k = scales.len();
    let p = DMatrix::from_fn(k, k, |i, j| {
        noise_var * precision[(i, j)] * scales[i] * scales[j]
    });
    let mu = DVector::from_fn(k, |i, _| mean[i] / scales[i]);
    let shift = &p * mu;
    (p, shift)
}
