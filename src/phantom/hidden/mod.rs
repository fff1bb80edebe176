//! Hidden effects (`generate --truth libr --hidden-effect KIND[:key=value,...]`): datasets whose
//! ground truth is exactly LIBR's own physics plus named effects of the augmented-model library
//! ([`crate::register::physics`]), for a discovery workflow to find from sparse data.
//!
//! A [`HiddenEffectSpec`] is one `--hidden-effect`: a kind and the parameters the command line
//! fixed. The others are drawn per deformation ([`draw_physics`]) from the effect's own random
//! stream, `derive(draw seed, [8, index])` (the index of the effect among the hidden effects), so
//! every other draw of the dataset (loads, scenarios, their noise and misalignment) is
//! bit-identical to the same command without the effect. Every parameter is drawn, in a fixed
//! order, whether given or not, so fixing one leaves the others' draws unchanged.
//!
//! Drawn ranges (physical; `docs/hidden-effects.md` gives their sources):
//!
//! | kind | drawn parameters |
//! | --- | --- |
//! | `gravity` | `direction` = `tilted_gravity(1, head_up, lateral)`, head-up U(0°, 30°), lateral U(−30°, 30°); `magnitude` = 0.0104 mN/mm³ × U(0.8, 1.2) |
//! | `bed-support` | `stiffness` log-U(0.02, 0.3) kPa/mm |
//! | `fixation` | `center` a posterior boundary node in the superior half; `radius_mm` U(15, 35); `stiffness` log-U(0.2, 2) kPa/mm |
//! | `pressure` | `magnitude_kpa` U(7, 14) mmHg; `direction` anterior (0, −1, 0) turned by U(0°, 20°) |
//! | `pack` | `center` a boundary node off the bare area; `width_mm` U(10, 30); `force_mn` U(2000, 8000) mN along the inward vertex normal turned by U(0°, 30°) |
//! | `ligament` | `stiffness` log-U(0.1, 1) kPa/mm |
//! | `inclusion` | `radius_mm` U(10, 25); `center` an interior node at least the radius deep (else the deepest); `stiffness_ratio` U(3, 10) |
//!
//! "Turned by U(0°, a)" is a uniform angle about a uniform azimuth. `nonlinear` is refused: the
//! augmented model does not carry large-deformation behaviour, so no LIBR-physics truth can
//! contain it.

use super::patterns::{LoadCase, PatternParams, tilted_gravity};
use super::truth::{LibrSites, libr_base_load, solve_libr};
use super::{PhantomError, derive};
use crate::fem::LinearMaterial;
use crate::mesh::spatial::TriangleBvh;
use crate::mesh::vec3::{cross, dist2, unit};
use crate::mesh::{TetMesh, TriSurface};
use crate::register::anatomy::{AnatomyLabels, Region};
#[cfg(doc)]
use crate::register::physics::model::Carry;
use crate::register::physics::model::{BoundaryGeometry, forward_supported_parts};
use crate::register::physics::{Effect, EffectKind, Physics};
use crate::util::SplitMix64;
use std::collections::BTreeMap;

/// Key of the hidden effects' random streams under a draw's seed (`derive(seed, [8, index])`).
pub const HIDDEN_EFFECT_STREAM: u64 = 8;

/// Gravity's body force at the liver's density, ρ·g = 1.06 g/cm³ × 9.81 m/s² (mN/mm³).
pub const LIVER_WEIGHT: f64 = 0.0104;

/// kPa per mmHg (1 mmHg = 0.133322 kPa).
const MMHG_KPA: f64 = 0.133_322;

/// One `--hidden-effect`: the kind and the parameters given on the command line (the rest is
/// drawn per deformation).
#[derive(Debug, Clone, PartialEq)]
pub struct HiddenEffectSpec {
    /// Kind.
    pub kind: EffectKind,
    /// Parameters fixed on the command line, each checked against the kind's valid range.
    pub given: BTreeMap<String, Vec<f64>>,
    /// Multiplies the effect's amplitude, drawn or given ([`scale_amplitude`]; `scale=F` on the
    /// command line, in (0, 10]); 1 by default. For detectability studies.
    pub scale: f64,
}

/// Largest `scale` of a hidden effect.
pub const MAX_SCALE: f64 = 10.0;

/// The effect with its amplitude multiplied by `s`: a load's `magnitude`, `magnitude_kpa` or
/// `force_mn`, a support's `stiffness`, an inclusion's excess stiffness (`stiffness_ratio` − 1).
pub fn scale_amplitude(effect: &mut Effect, s: f64) {
    let (name, excess) = match effect.kind {
        EffectKind::Gravity => ("magnitude", false),
        EffectKind::Pressure => ("magnitude_kpa", false),
        EffectKind::Pack => ("force_mn", false),
        EffectKind::BedSupport | EffectKind::Fixation | EffectKind::Ligament => {
            ("stiffness", false)
        }
        EffectKind::Inclusion => ("stiffness_ratio", true),
        EffectKind::Nonlinear => return,
    };
    if let Some(v) = effect.parameters.get_mut(name) {
        for x in v.iter_mut() {
            *x = if excess { 1.0 + s * (*x - 1.0) } else { s * *x };
        }
    }
}

impl HiddenEffectSpec {
    /// Parses `KIND[:key=value,...]` (vectors as `x/y/z`). Errors name an unknown kind (and list
    /// the known ones), an unknown or out-of-range parameter (by name), and `nonlinear`, which
    /// the generator cannot make yet.
    pub fn parse(text: &str) -> Result<Self, PhantomError> {
        // `scale=F` is the generator's, not the effect's: taken out before the effect's own.
        let (head, rest) = text.split_once(':').unwrap_or((text, ""));
        let mut scale = 1.0;
        let mut kept = Vec::new();
        for item in rest.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            match item.split_once('=') {
                Some(("scale", v)) => {
                    scale = v.trim().parse::<f64>().ok().filter(|x| *x > 0.0 && *x <= MAX_SCALE).ok_or_else(|| {
                        PhantomError::Parameter(format!(
                            "hidden effect {text:?}: scale: {v:?} is not a number in (0, {MAX_SCALE}]"
                        ))
                    })?;
                }
                _ => kept.push(item),
            }
        }
        let effect_text = if kept.is_empty() {
            head.to_string()
        } else {
            format!("{head}:{}", kept.join(","))
        };
        let (kind, given) = Effect::parse_partial(&effect_text).map_err(PhantomError::Model)?;
        if kind == EffectKind::Nonlinear {
            return Err(PhantomError::Parameter(format!(
                "hidden effect {text:?}: `nonlinear` is not generated yet: the augmented model \
                 (register::physics) carries no large-deformation behaviour, so a --truth libr \
                 dataset cannot contain it"
            )));
        }
        for spec in kind.parameters() {
            let Some(v) = given.get(spec.name) else {
                continue;
            };
            let field = format!("hidden effect {text:?}: {}", spec.name);
            spec.check(&field, v)
                .map_err(|e| PhantomError::Parameter(e.to_string()))?;
        }
        Ok(Self { kind, given, scale })
    }

    /// `{"kind", "given": {name: number or [x, y, z]}}`, as the dataset's parameters record it,
    /// with `"scale"` where it is not 1.
    pub fn to_value(&self) -> serde_json::Value {
        let given = crate::register::physics::parameters_json(&self.given);
        let mut v = serde_json::json!({"kind": self.kind.name(), "given": given});
        if self.scale != 1.0 {
            v["scale"] = serde_json::json!(self.scale);
        }
        v
    }
}

impl serde::Serialize for HiddenEffectSpec {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.to_value().serialize(s)
    }
}

/// What one mesh offers the draws, computed once per draw.
struct Context<'a> {
    mesh: &'a TetMesh,
    labels: &'a AnatomyLabels,
    geom: BoundaryGeometry,
}

impl Context<'_> {
    /// The boundary node nearest to `p`.
    fn nearest_boundary_node(&self, p: [f64; 3]) -> u32 {
        let nodes = self.mesh.nodes();
        self.geom
            .nodes
            .iter()
            .copied()
            .min_by(|&a, &b| dist2(nodes[a as usize], p).total_cmp(&dist2(nodes[b as usize], p)))
            .unwrap_or(0)
    }

    /// Interior nodes with their distance to the boundary surface (mm).
    fn interior_depths(&self) -> Result<Vec<(u32, f64)>, PhantomError> {
        let nodes = self.mesh.nodes();
        let surface = TriSurface::new(nodes.to_vec(), self.geom.triangles.clone())?;
        let bvh = TriangleBvh::new(&surface);
        let mut on_boundary = vec![false; nodes.len()];
        for &v in &self.geom.nodes {
            on_boundary[v as usize] = true;
        }
        Ok((0..nodes.len())
            .filter(|&v| !on_boundary[v])
            .map(|v| (v as u32, bvh.distance(nodes[v])))
            .collect())
    }
}

/// The effect's random draws.
struct Draws(SplitMix64);

impl Draws {
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.0.next_f64()
    }

    fn log_uniform(&mut self, lo: f64, hi: f64) -> f64 {
        self.uniform(lo.ln(), hi.ln()).exp()
    }

    /// One draw picking among `n` candidates (`None` when there are none; the draw is made
    /// anyway, so the later draws do not depend on `n`).
    fn pick(&mut self, n: usize) -> Option<usize> {
        let u = self.0.next_f64();
        (n > 0).then(|| ((u * n as f64) as usize).min(n - 1))
    }

    /// `v` (unit) turned by a uniform angle in [0, `max_deg`] about a uniform azimuth.
    fn turned(&mut self, v: [f64; 3], max_deg: f64) -> [f64; 3] {
        let angle = self.uniform(0.0, max_deg).to_radians();
        let azimuth = self.uniform(0.0, std::f64::consts::TAU);
        let least = (0..3)
            .min_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()))
            .unwrap_or(0);
        let mut e = [0.0; 3];
        e[least] = 1.0;
        let p = unit(cross(v, e));
        let q = cross(v, p);
        let (s, c) = angle.sin_cos();
        let (sa, ca) = azimuth.sin_cos();
        unit([0, 1, 2].map(|k| c * v[k] + s * (ca * p[k] + sa * q[k])))
    }
}

/// Draws every parameter of one effect from `seed` (fixed order, whether given or not), then
/// keeps the given ones.
fn draw_effect(
    ctx: &Context<'_>,
    spec: &HiddenEffectSpec,
    seed: u64,
) -> Result<Effect, PhantomError> {
    let mut d = Draws(SplitMix64::new(seed));
    let nodes = ctx.mesh.nodes();
    let given_vector = |name: &str| -> Option<[f64; 3]> {
        spec.given
            .get(name)
            .filter(|v| v.len() == 3)
            .map(|v| [v[0], v[1], v[2]])
    };
    let given_scalar = |name: &str| spec.given.get(name).and_then(|v| v.first().copied());
    let mut drawn: Vec<(&str, Vec<f64>)> = Vec::new();
    let none = |what: &str| {
        PhantomError::Geometry(format!(
            "hidden effect {}: the mesh has no {what} to place it on",
            spec.kind
        ))
    };
    match spec.kind {
        EffectKind::Gravity => {
            let (head_up, lateral) = (d.uniform(0.0, 30.0), d.uniform(-30.0, 30.0));
            let magnitude = LIVER_WEIGHT * d.uniform(0.8, 1.2);
            drawn.push(("direction", tilted_gravity(1.0, head_up, lateral).to_vec()));
            drawn.push(("magnitude", vec![magnitude]));
        }
        EffectKind::BedSupport => {
            drawn.push(("stiffness", vec![d.log_uniform(0.02, 0.3)]));
        }
        EffectKind::Ligament => {
            drawn.push(("stiffness", vec![d.log_uniform(0.1, 1.0)]));
        }
        EffectKind::Fixation => {
            let (lo, hi) = ctx.mesh.bounding_box();
            let mid_z = 0.5 * (lo[2] + hi[2]);
            let posterior: Vec<u32> = ctx
                .geom
                .nodes
                .iter()
                .copied()
                .filter(|&v| ctx.labels.region[v as usize] == Region::Posterior)
                .collect();
            let superior: Vec<u32> = posterior
                .iter()
                .copied()
                .filter(|&v| nodes[v as usize][2] >= mid_z)
                .collect();
            let cands = if superior.is_empty() {
                &posterior
            } else {
                &superior
            };
            let pick = d.pick(cands.len());
            let (radius, stiffness) = (d.uniform(15.0, 35.0), d.log_uniform(0.2, 2.0));
            if given_vector("center").is_none() {
                let v = cands[pick.ok_or_else(|| none("posterior boundary node"))?];
                drawn.push(("center", nodes[v as usize].to_vec()));
            }
            drawn.push(("radius_mm", vec![radius]));
            drawn.push(("stiffness", vec![stiffness]));
        }
        EffectKind::Pressure => {
            let magnitude = d.uniform(7.0, 14.0) * MMHG_KPA;
            let direction = d.turned([0.0, -1.0, 0.0], 20.0);
            drawn.push(("magnitude_kpa", vec![magnitude]));
            drawn.push(("direction", direction.to_vec()));
        }
        EffectKind::Pack => {
            let cands: Vec<u32> = ctx
                .geom
                .nodes
                .iter()
                .copied()
                .filter(|&v| !ctx.labels.bare_area[v as usize])
                .collect();
            let pick = d.pick(cands.len());
            let width = d.uniform(10.0, 30.0);
            let magnitude = d.uniform(2000.0, 8000.0);
            let center = match given_vector("center") {
                Some(c) => c,
                None => {
                    nodes[cands[pick.ok_or_else(|| none("boundary node off the bare area"))?]
                        as usize]
                }
            };
            let at = ctx.nearest_boundary_node(center) as usize;
            let inward = ctx.geom.node_normal[at].map(|x| -x);
            let dir = d.turned(inward, 30.0);
            drawn.push(("center", center.to_vec()));
            drawn.push(("width_mm", vec![width]));
            drawn.push(("force_mn", dir.map(|x| x * magnitude).to_vec()));
        }
        EffectKind::Inclusion => {
            let drawn_radius = d.uniform(10.0, 25.0);
            let radius = given_scalar("radius_mm").unwrap_or(drawn_radius);
            let depths = ctx.interior_depths()?;
            let deep: Vec<u32> = depths
                .iter()
                .filter(|(_, depth)| *depth >= radius)
                .map(|(v, _)| *v)
                .collect();
            let pick = d.pick(deep.len());
            let ratio = d.uniform(3.0, 10.0);
            if given_vector("center").is_none() {
                let v = match pick {
                    Some(k) => deep[k],
                    None => {
                        depths
                            .iter()
                            .max_by(|a, b| a.1.total_cmp(&b.1))
                            .ok_or_else(|| none("interior node"))?
                            .0
                    }
                };
                drawn.push(("center", nodes[v as usize].to_vec()));
            }
            drawn.push(("radius_mm", vec![radius]));
            drawn.push(("stiffness_ratio", vec![ratio]));
        }
        EffectKind::Nonlinear => {
            return Err(PhantomError::Parameter(
                "hidden effect nonlinear: not generated yet (the augmented model does not carry it)"
                    .into(),
            ));
        }
    }
    let mut parameters: BTreeMap<String, Vec<f64>> =
        drawn.into_iter().map(|(k, v)| (k.to_string(), v)).collect();
    for (k, v) in &spec.given {
        parameters.insert(k.clone(), v.clone());
    }
    let mut effect = Effect {
        kind: spec.kind,
        parameters,
    };
    if spec.scale != 1.0 {
        scale_amplitude(&mut effect, spec.scale);
    }
    effect
        .validate(&format!("hidden effect {}", spec.kind))
        .map_err(PhantomError::Model)?;
    Ok(effect)
}

/// The seed of hidden effect `index` of a draw whose seed is `seed`.
pub fn effect_seed(seed: u64, index: usize) -> u64 {
    derive(seed, &[HIDDEN_EFFECT_STREAM, index as u64])
}

/// The hidden effects of one draw: each spec's parameters drawn from [`effect_seed`]`(seed, i)`
/// (see the module doc), given ones kept.
pub fn draw_physics(
    specs: &[HiddenEffectSpec],
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    seed: u64,
) -> Result<Physics, PhantomError> {
    if specs.is_empty() {
        return Ok(Physics::none());
    }
    let ctx = Context {
        mesh,
        labels,
        geom: BoundaryGeometry::new(mesh).map_err(PhantomError::Model)?,
    };
    let effects = specs
        .iter()
        .enumerate()
        .map(|(i, s)| draw_effect(&ctx, s, effect_seed(seed, i)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Physics { effects })
}

/// What an effect of a generated truth is there for, recorded as its `"role"` in
/// `hidden_physics.json`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Asked for with `--hidden-effect`: what a discovery is to name.
    Hidden,
    /// A bed support added to carry hidden loads when no support is hidden (in the body something
    /// always carries a load's net force). Naming it is right, not required.
    Carrier,
    /// The organ's weight added for hidden supports to carry when no load is hidden (a support
    /// shows only by what it carries). Naming it is right, not required.
    Carried,
}

impl Role {
    /// `hidden`, `carrier`, `carried`.
    pub fn name(self) -> &'static str {
        match self {
            Role::Hidden => "hidden",
            Role::Carrier => "carrier",
            Role::Carried => "carried",
        }
    }
}

/// Per effect `{"role": NAME}`, for [`Physics::to_value`]'s extras.
pub fn role_values(roles: &[Role]) -> Vec<serde_json::Value> {
    roles
        .iter()
        .map(|r| serde_json::json!({"role": r.name()}))
        .collect()
}

/// How a hidden-effect truth carries its loads, recorded in the dataset's parameters as
/// `hidden_carry`: the supports carry the effects' net load ([`Carry::Supports`]).
pub const HIDDEN_CARRY: &str = "supports";

/// Index of the carrier bed's random stream under a draw's seed (`derive(seed, [8, 1000])`).
pub const CARRIER_STREAM: u64 = 1000;

/// Index of the carried weight's random stream under a draw's seed (`derive(seed, [8, 1001])`).
pub const CARRIED_STREAM: u64 = 1001;

/// Largest peak displacement (mm, rigid part removed) the hidden loads may add to a truth:
/// beyond it their amplitudes are scaled down to it (and recorded so). Intraoperative liver
/// deformations reach a few centimetres; a linear model carried by a small patch could
/// otherwise swing through tens of centimetres.
pub const EFFECT_PEAK_CAP_MM: f64 = 30.0;

/// The effects of a truth with what carries their loads: a carrier bed when no support is
/// hidden, the organ's weight when no load is (an inclusion alone gets both: a stiffer region
/// shows only in how the loaded organ deforms), each from its own stream, so the hidden
/// effects' draws are unchanged.
fn with_carriers(
    hidden: Physics,
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    seed: u64,
) -> Result<(Physics, Vec<Role>), PhantomError> {
    let mut roles = vec![Role::Hidden; hidden.effects.len()];
    let mut physics = hidden;
    if physics.is_empty() {
        return Ok((physics, roles));
    }
    let loads = physics.effects.iter().any(|e| e.kind.is_load());
    let supports = physics.has_support();
    let ctx = Context {
        mesh,
        labels,
        geom: BoundaryGeometry::new(mesh).map_err(PhantomError::Model)?,
    };
    let mut add = |kind: EffectKind, stream: u64, role: Role| -> Result<(), PhantomError> {
        let spec = HiddenEffectSpec {
            kind,
            given: BTreeMap::new(),
            scale: 1.0,
        };
        let e = draw_effect(&ctx, &spec, derive(seed, &[HIDDEN_EFFECT_STREAM, stream]))?;
        physics.effects.push(e);
        roles.push(role);
        Ok(())
    };
    if !supports {
        add(EffectKind::BedSupport, CARRIER_STREAM, Role::Carrier)?;
    }
    if !loads {
        add(EffectKind::Gravity, CARRIED_STREAM, Role::Carried)?;
    }
    Ok((physics, roles))
}

/// The physics with its load effects' amplitudes multiplied by `s`.
fn scale_loads(physics: &mut Physics, s: f64) {
    for e in physics.effects.iter_mut().filter(|e| e.kind.is_load()) {
        if let Some((name, _)) = e.kind.amplitude()
            && let Some(v) = e.parameters.get_mut(name)
        {
            v.iter_mut().for_each(|x| *x *= s);
        }
    }
}

/// A `--truth libr` ground truth.
#[derive(Debug, Clone)]
pub struct LibrTruth {
    /// LIBR's physics plus the hidden effects under the base load (mm, node-major).
    pub displacement: Vec<f64>,
    /// LIBR's physics alone under the same base load: what LIBR itself would predict with the
    /// true load (equal to `displacement` when nothing is hidden).
    pub libr: Vec<f64>,
    /// The truth's effects with their drawn parameters: the hidden ones, then a carrier or a
    /// carried weight ([`Role`]).
    pub physics: Physics,
    /// What each effect of `physics` is there for.
    pub roles: Vec<Role>,
    /// What the truth left out or replaced, for the deformation's description.
    pub note: String,
}

/// Solves a `--truth libr` ground truth for a load case drawn with `seed`: the base load is
/// [`libr_base_load`] (broad tractions of LIBR's own kind drawn from the case's seed), the
/// material the homogeneous `material`, the supports' sites the labels' ([`LibrSites`]), and
/// the hidden effects [`draw_physics`]`(specs, mesh, labels, seed)`.
///
/// The hidden effects' loads are carried by the supports as in the body ([`Carry::Supports`]:
/// gravity as the organ's weight, a pack or a pressure pushing it against what holds it), a
/// carrier bed added when no support is hidden and the organ's weight when no load is
/// ([`Role`]; a lone inclusion gets both); the base load is balanced by inertia relief as LIBR's
/// own loads are, and the rigid part is removed. When the loads' part peaks above
/// [`EFFECT_PEAK_CAP_MM`] their amplitudes are scaled down to it, and the recorded physics is the
/// scaled one.
pub fn libr_truth(
    mesh: &TetMesh,
    labels: &AnatomyLabels,
    material: &LinearMaterial,
    case: &LoadCase,
    params: &PatternParams,
    specs: &[HiddenEffectSpec],
    seed: u64,
) -> Result<LibrTruth, PhantomError> {
    let (base, replaced) = libr_base_load(mesh, case, params.load_scale)?;
    let hidden = draw_physics(specs, mesh, labels, seed)?;
    let (mut physics, roles) = with_carriers(hidden, mesh, labels, seed)?;
    let sites = LibrSites::new(labels);
    let libr = solve_libr(mesh, material, &sites, &Physics::none(), &base)?;
    let mut note = "truth libr: LIBR's free-floating linear homogeneous model under loads of its \
                    own kind (no gravity, bed or bare-area support)"
        .to_string();
    let displacement = if physics.is_empty() {
        libr.clone()
    } else {
        // Non-empty physics always holds a support here ([`with_carriers`]).
        let [b, e] = forward_supported_parts(mesh, material, sites.sites(), &physics, &base)
            .map_err(PhantomError::Model)?;
        let peak = e
            .chunks_exact(3)
            .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
            .fold(0.0f64, f64::max);
        let s = if peak > EFFECT_PEAK_CAP_MM {
            EFFECT_PEAK_CAP_MM / peak
        } else {
            1.0
        };
        if s < 1.0 {
            scale_loads(&mut physics, s);
            note.push_str(&format!(
                "; the hidden loads scaled by {s:.3} to a {EFFECT_PEAK_CAP_MM} mm peak (drawn: {peak:.1} mm)"
            ));
        }
        b.iter().zip(&e).map(|(x, y)| x + s * y).collect()
    };
    if !replaced.is_empty() {
        note.push_str("; ");
        note.push_str(&replaced);
    }
    Ok(LibrTruth {
        displacement,
        libr,
        physics,
        roles,
        note,
    })
}

#[cfg(test)]
mod tests;
