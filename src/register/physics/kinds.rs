//! The library of effect kinds, one table: per kind its name, its parameters, how it enters the
//! augmented model (a load, a support, a material), what physics expects of it before the data
//! (the discovery prior) and how discovery searches it. Adding a kind is one line of the list
//! `kinds!` (the variant, in the library's order, and its entry) and its entry, a
//! [`KindSpec`], both here; the generator of hidden effects (`phantom::hidden`) draws its ground truth apart, as
//! surgery-time code never reads how data were made.
//!
//! | kind | what it adds | parameters (image frame, mm, kPa, mN) |
//! | --- | --- | --- |
//! | `gravity` | the organ's weight resting on its dependent surface | `direction` (unit 3-vector), `magnitude` (mN/mm³) |
//! | `bed-support` | the posterior surface on an elastic bed (normal stiffness, a tenth across) | `stiffness` (kPa/mm) |
//! | `fixation` | the organ held on a boundary region (hilum, vena cava, bare area) | `center` (mm), `radius_mm`, `stiffness` (kPa/mm) |
//! | `pressure` | a uniform pressure on the faces turned towards `direction` (insufflation) | `magnitude_kpa`, `direction` |
//! | `pack` | a localized load (packing, retractor, tool) | `center`, `width_mm`, `force_mn` (3-vector) |
//! | `ligament` | tethering along the falciform ligament (isotropic springs) | `stiffness` (kPa/mm) |
//! | `inclusion` | a stiffer sphere (tumour, vessel tree) | `center`, `radius_mm`, `stiffness_ratio` |
//! | `nonlinear` | large-deformation behaviour | none (recognised; the augmented model does not carry it yet) |
//!
//! The physics of each kind is described in [`super::model`]; the priors and the search in the
//! discovery workflow's `prior` and `search` modules. The numbers of both are
//! here, as plain data, so that the layers above ask this table rather than match on kinds.

use super::boundary::{BoundaryGeometry, Sites, nodes_within};
use super::{Effect, ParamSpec};
use crate::fem::loads;
use crate::mesh::TetMesh;
use crate::mesh::vec3::{dist2, dot};
use crate::register::RegisterError;

/// The list of kinds: each variant of [`EffectKind`] with its entry in the table, in the
/// library's order. The enum, [`EffectKind::ALL`] and [`EffectKind::spec`] are made from this one
/// list, so they cannot disagree.
macro_rules! kinds {
    ($($(#[$doc:meta])* $kind:ident => $spec:ident,)*) => {
        /// A kind of effect in the library.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
        pub enum EffectKind {
            $($(#[$doc])* $kind,)*
        }

        impl EffectKind {
            /// Every kind, in the library's order.
            pub const ALL: [EffectKind; [$(stringify!($kind)),*].len()] = [$(EffectKind::$kind),*];

            /// The kind's entry in the table.
            pub fn spec(self) -> &'static KindSpec {
                match self {
                    $(EffectKind::$kind => &$spec,)*
                }
            }
        }
    };
}

kinds! {
    /// The organ's weight resting on its dependent surface.
    Gravity => GRAVITY,
    /// The posterior surface on an elastic bed.
    BedSupport => BED_SUPPORT,
    /// The organ held on a boundary region.
    Fixation => FIXATION,
    /// A uniform pressure on the faces turned towards a direction.
    Pressure => PRESSURE,
    /// A localized surface load.
    Pack => PACK,
    /// Tethering along the falciform ligament.
    Ligament => LIGAMENT,
    /// A stiffer spherical region.
    Inclusion => INCLUSION,
    /// Large-deformation behaviour.
    Nonlinear => NONLINEAR,
}

/// Everything the library knows about one kind ([`EffectKind::spec`]).
#[derive(Debug, Clone, Copy)]
pub struct KindSpec {
    /// Name in files and on the command line.
    pub name: &'static str,
    /// Parameters with the ranges the model accepts (wide, physical; the ranges hidden effects
    /// are drawn from are narrower, see the generator).
    pub parameters: &'static [ParamSpec],
    /// How the kind enters the augmented model.
    pub role: Role,
    /// How discovery searches the kind's parameters.
    pub search: Search,
    /// The shape parameters the search adds to a model besides the fitted amplitudes, for the
    /// information criterion (a direction 2; a pack's centre and width 4; a support's
    /// stiffness 1, with a fixation's site 3; an inclusion's site and ratio 4).
    pub searched: usize,
}

/// How a kind enters the augmented model.
#[derive(Debug, Clone, Copy)]
pub enum Role {
    /// A load: extra basis columns whose amplitudes the fit estimates.
    Load(Load),
    /// A support: springs on boundary nodes (the model is then no longer free-floating).
    Support(Support),
    /// A change of the material the basis is built from.
    Material(Material),
    /// Recognised, but the augmented model does not carry it yet.
    Uncarried,
}

/// A load's unit loads (mN, node-major), one per fitted amplitude, and the amplitudes its
/// parameters give them; the flag asks for gravity's dependent-surface reaction (see
/// the augmented model's `unit_loads_with`).
pub type UnitLoads = fn(
    &TetMesh,
    &BoundaryGeometry,
    &Effect,
    bool,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError>;

/// A load's own check that it finds boundary faces to act on; `usize` is the effect's index
/// in the physics, for the message.
pub type FitsCheck = fn(&TetMesh, &BoundaryGeometry, &Effect, usize) -> Result<(), RegisterError>;

/// The boundary nodes a support holds.
pub type HeldNodes = fn(&TetMesh, &BoundaryGeometry, Sites<'_>, &Effect) -> Vec<u32>;

/// The searched values of one parameter, from the search's grid.
pub type GridValues = fn(&SearchGrid) -> &[f64];

/// How many sites or directions the search's grid asks for.
pub type GridCount = fn(&SearchGrid) -> usize;

/// A load kind: its fitted amplitude, its unit loads, and the discovery prior on its size and
/// direction.
#[derive(Debug, Clone, Copy)]
pub struct Load {
    /// The fitted amplitude's parameter.
    pub amplitude: &'static str,
    /// How many basis columns carry it.
    pub columns: usize,
    /// Its unit loads.
    pub unit_loads: UnitLoads,
    /// Its own check that it fits a mesh; `None`: its unit loads can be made.
    pub fits: Option<FitsCheck>,
    /// The plausible size of the amplitude (a scalar's value, a vector's norm).
    pub plausible: (f64, f64),
    /// The amplitude's lower bound instead when only local supports carry it.
    pub local_floor: Option<f64>,
    /// The cone its direction must lie in: axis and largest angle (degrees).
    pub cone: Option<([f64; 3], f64)>,
    /// The Gaussian prior of its amplitudes.
    pub prior: LoadPrior,
}

/// The Gaussian prior of a load's amplitudes, in the units of its parameter.
#[derive(Debug, Clone, Copy)]
pub enum LoadPrior {
    /// One amplitude: mean and standard deviation.
    Gaussian {
        /// Mean.
        mean: f64,
        /// Standard deviation.
        sd: f64,
    },
    /// A force (three amplitudes) along the inward normal at the boundary node nearest the
    /// effect's `at` parameter: its mean along the normal, standard deviations along and across.
    Inward {
        /// The position parameter.
        at: &'static str,
        /// Mean along the inward normal.
        mean: f64,
        /// Standard deviation along it.
        sd_along: f64,
        /// Standard deviation across it.
        sd_across: f64,
    },
}

/// Whether a support holds the organ in place or carries it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hold {
    /// The organ rests on it (the posterior bed).
    Bed,
    /// It holds the organ at a site (a fixation patch, the falciform ligament).
    Local,
}

/// A support kind: springs of its `stiffness` (per unit boundary area) on the nodes it holds.
#[derive(Debug, Clone, Copy)]
pub struct Support {
    /// Bed or local.
    pub hold: Hold,
    /// The stiffness parameter (kPa/mm).
    pub stiffness: &'static str,
    /// The boundary nodes it holds.
    pub held: HeldNodes,
    /// Isotropic springs (`None`), or along the vertex normal with this fraction across.
    pub across: Option<f64>,
}

/// A material kind: Young's modulus multiplied per tet (ν unchanged).
#[derive(Debug, Clone, Copy)]
pub struct Material {
    /// The factor at a tet's centroid (1 where the effect does not act).
    pub factor: fn(&Effect, [f64; 3]) -> f64,
}

/// How discovery searches a kind.
#[derive(Debug, Clone, Copy)]
pub enum Search {
    /// Not searched.
    None,
    /// Directions over the sphere within the kind's cone, the best three refined, with the
    /// amplitude at `start` (the fit replaces it).
    Directions {
        /// Directions tried.
        count: GridCount,
        /// The direction parameter.
        direction: &'static str,
        /// The amplitude parameter.
        amplitude: &'static str,
        /// The amplitude the candidates are made with.
        start: f64,
    },
    /// A grid: at each site (once without one) each value of `vary`, the rest `fixed`.
    Grid {
        /// Where the effect is centred.
        site: Option<SiteGrid>,
        /// The parameter varied, and its values.
        vary: (&'static str, GridValues),
        /// The parameters held.
        fixed: &'static [(&'static str, &'static [f64])],
    },
}

/// The sites a centred effect is tried at.
#[derive(Debug, Clone, Copy)]
pub struct SiteGrid {
    /// The position parameter.
    pub name: &'static str,
    /// Where the sites lie.
    pub place: Place,
    /// How many.
    pub count: GridCount,
}

/// Where a search's sites lie.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Place {
    /// Boundary nodes (farthest-point samples).
    Boundary,
    /// Nodes at least `depth` mm from the boundary nodes (farthest-point samples).
    Interior {
        /// Smallest distance to the boundary (mm).
        depth: f64,
    },
}

/// How finely each family is searched.
#[derive(Debug, Clone, Copy)]
pub struct SearchGrid {
    /// Directions tried for gravity and pressure (then refined). Default 32.
    pub directions: usize,
    /// Boundary sites tried for packs. Default 24.
    pub pack_sites: usize,
    /// Pack widths (mm). Default 12, 25.
    pub pack_widths: [f64; 2],
    /// Boundary sites tried for fixations. Default 8.
    pub fixation_sites: usize,
    /// Interior sites tried for inclusions. Default 6.
    pub inclusion_sites: usize,
}

impl Default for SearchGrid {
    fn default() -> Self {
        Self {
            directions: 32,
            pack_sites: 24,
            pack_widths: [12.0, 25.0],
            fixation_sites: 8,
            inclusion_sites: 6,
        }
    }
}

impl SearchGrid {
    /// The coarse grid: 16 directions, 8 pack, 4 fixation and 2 inclusion sites.
    pub fn coarse() -> Self {
        Self {
            directions: 16,
            pack_sites: 8,
            pack_widths: [12.0, 25.0],
            fixation_sites: 4,
            inclusion_sites: 2,
        }
    }
}

/// ρg of liver tissue (mN/mm³): gravity's prior mean.
pub const GRAVITY_MAGNITUDE: f64 = 0.0104;
/// Its prior standard deviation (mN/mm³).
pub const GRAVITY_SD: f64 = 0.0031;
/// Insufflation pressure prior: mean and standard deviation (kPa).
pub const PRESSURE_KPA: (f64, f64) = (1.4, 0.6);
/// A pack's force: mean along the inward normal, standard deviation along it and across it
/// (mN).
pub const PACK_FORCE_MN: (f64, f64, f64) = (5000.0, 3000.0, 2500.0);
/// The smallest share of the organ's weight a local support (a fixation patch, the falciform
/// ligament) carries when no bed does: the neighbouring organs carry the rest, up to 90 %.
pub const LOCAL_WEIGHT_SHARE: f64 = 0.1;

const fn scalar(name: &'static str, lo: f64, hi: f64, unit: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        len: 1,
        range: Some((lo, hi)),
        unit,
    }
}

const fn vector(name: &'static str, range: Option<(f64, f64)>, unit: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        len: 3,
        range,
        unit,
    }
}

const DIRECTION: ParamSpec = vector("direction", Some((0.5, 2.0)), "unit vector");
const CENTER: ParamSpec = vector("center", None, "mm");

fn directions(g: &SearchGrid) -> usize {
    g.directions
}

static GRAVITY: KindSpec = KindSpec {
    name: "gravity",
    parameters: &[DIRECTION, scalar("magnitude", 0.0, 0.1, "mN/mm³")],
    role: Role::Load(Load {
        amplitude: "magnitude",
        columns: 1,
        unit_loads: gravity_loads,
        fits: None,
        plausible: (0.8 * GRAVITY_MAGNITUDE / 2.0, 1.2 * GRAVITY_MAGNITUDE * 2.0),
        local_floor: Some(LOCAL_WEIGHT_SHARE * 0.8 * GRAVITY_MAGNITUDE),
        cone: Some(([0.0, 1.0, 0.0], 90.0)),
        prior: LoadPrior::Gaussian {
            mean: GRAVITY_MAGNITUDE,
            sd: GRAVITY_SD,
        },
    }),
    search: Search::Directions {
        count: directions,
        direction: "direction",
        amplitude: "magnitude",
        start: 0.01,
    },
    searched: 2,
};

static BED_SUPPORT: KindSpec = KindSpec {
    name: "bed-support",
    parameters: &[scalar("stiffness", 1e-3, 10.0, "kPa/mm")],
    role: Role::Support(Support {
        hold: Hold::Bed,
        stiffness: "stiffness",
        held: posterior_nodes,
        across: Some(0.1),
    }),
    search: Search::Grid {
        site: None,
        vary: ("stiffness", |_| &[0.02, 0.07, 0.25]),
        fixed: &[],
    },
    searched: 1,
};

static FIXATION: KindSpec = KindSpec {
    name: "fixation",
    parameters: &[
        CENTER,
        scalar("radius_mm", 3.0, 150.0, "mm"),
        scalar("stiffness", 1e-3, 100.0, "kPa/mm"),
    ],
    role: Role::Support(Support {
        hold: Hold::Local,
        stiffness: "stiffness",
        held: region_nodes,
        across: None,
    }),
    search: Search::Grid {
        site: Some(SiteGrid {
            name: "center",
            place: Place::Boundary,
            count: |g| g.fixation_sites,
        }),
        vary: ("stiffness", |_| &[0.3, 1.5]),
        fixed: &[("radius_mm", &[25.0])],
    },
    searched: 3,
};

static PRESSURE: KindSpec = KindSpec {
    name: "pressure",
    parameters: &[scalar("magnitude_kpa", -10.0, 10.0, "kPa"), DIRECTION],
    role: Role::Load(Load {
        amplitude: "magnitude_kpa",
        columns: 1,
        unit_loads: pressure_loads,
        fits: None,
        plausible: (0.93 / 2.0, 1.87 * 2.0),
        local_floor: None,
        cone: Some(([0.0, -1.0, 0.0], 90.0)),
        prior: LoadPrior::Gaussian {
            mean: PRESSURE_KPA.0,
            sd: PRESSURE_KPA.1,
        },
    }),
    search: Search::Directions {
        count: directions,
        direction: "direction",
        amplitude: "magnitude_kpa",
        start: 1.0,
    },
    searched: 2,
};

static PACK: KindSpec = KindSpec {
    name: "pack",
    parameters: &[
        CENTER,
        scalar("width_mm", 3.0, 100.0, "mm"),
        vector("force_mn", Some((0.0, 50_000.0)), "mN"),
    ],
    role: Role::Load(Load {
        amplitude: "force_mn",
        columns: 3,
        unit_loads: pack_loads,
        fits: Some(pack_fits),
        plausible: (2000.0 / 2.0, 8000.0 * 2.0),
        local_floor: None,
        cone: None,
        prior: LoadPrior::Inward {
            at: "center",
            mean: PACK_FORCE_MN.0,
            sd_along: PACK_FORCE_MN.1,
            sd_across: PACK_FORCE_MN.2,
        },
    }),
    search: Search::Grid {
        site: Some(SiteGrid {
            name: "center",
            place: Place::Boundary,
            count: |g| g.pack_sites,
        }),
        vary: ("width_mm", |g| &g.pack_widths),
        fixed: &[("force_mn", &[0.0, 0.0, 1.0])],
    },
    searched: 4,
};

static LIGAMENT: KindSpec = KindSpec {
    name: "ligament",
    parameters: &[scalar("stiffness", 1e-3, 100.0, "kPa/mm")],
    role: Role::Support(Support {
        hold: Hold::Local,
        stiffness: "stiffness",
        held: falciform_nodes,
        across: None,
    }),
    search: Search::Grid {
        site: None,
        vary: ("stiffness", |_| &[0.1, 0.3, 1.0]),
        fixed: &[],
    },
    searched: 1,
};

static INCLUSION: KindSpec = KindSpec {
    name: "inclusion",
    parameters: &[
        CENTER,
        scalar("radius_mm", 2.0, 100.0, "mm"),
        scalar("stiffness_ratio", 1.0, 100.0, "×"),
    ],
    role: Role::Material(Material {
        factor: inclusion_factor,
    }),
    search: Search::Grid {
        site: Some(SiteGrid {
            name: "center",
            place: Place::Interior { depth: 15.0 },
            count: |g| g.inclusion_sites,
        }),
        vary: ("stiffness_ratio", |_| &[5.0]),
        fixed: &[("radius_mm", &[15.0])],
    },
    searched: 4,
};

static NONLINEAR: KindSpec = KindSpec {
    name: "nonlinear",
    parameters: &[],
    role: Role::Uncarried,
    search: Search::None,
    searched: 1,
};

impl EffectKind {
    /// The kind's name in files and on the command line.
    pub fn name(self) -> &'static str {
        self.spec().name
    }

    /// The kind of a name.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// Every kind's name, `, `-joined (for messages).
    pub fn known() -> String {
        Self::ALL.map(|k| k.name()).join(", ")
    }

    /// The kind's parameters with their valid ranges. Ranges are what the model accepts (wide,
    /// physical); the ranges hidden effects are drawn from are narrower (see the generator).
    pub fn parameters(self) -> &'static [ParamSpec] {
        self.spec().parameters
    }

    /// How the kind enters the augmented model.
    pub fn role(self) -> &'static Role {
        &self.spec().role
    }

    /// Whether the augmented model carries the kind (every kind but `nonlinear`).
    pub fn is_carried(self) -> bool {
        !matches!(self.role(), Role::Uncarried)
    }

    /// Whether the effect is a support (springs; the model is then no longer free-floating).
    pub fn is_support(self) -> bool {
        matches!(self.role(), Role::Support(_))
    }

    /// A support's hold (bed or local); `None` for other kinds.
    pub fn hold(self) -> Option<Hold> {
        match self.role() {
            Role::Support(s) => Some(s.hold),
            Role::Load(_) | Role::Material(_) | Role::Uncarried => None,
        }
    }

    /// A load kind's facts; `None` for other kinds.
    pub fn load(self) -> Option<&'static Load> {
        match self.role() {
            Role::Load(l) => Some(l),
            Role::Support(_) | Role::Material(_) | Role::Uncarried => None,
        }
    }

    /// A load effect's fitted amplitude: its parameter's name and how many basis columns carry
    /// it (`gravity`: `magnitude`, 1; `pressure`: `magnitude_kpa`, 1; `pack`: `force_mn`, 3);
    /// `None` for other kinds.
    pub fn amplitude(self) -> Option<(&'static str, usize)> {
        self.load().map(|l| (l.amplitude, l.columns))
    }

    /// Whether the effect is a load (an extra basis column family with a fitted amplitude).
    pub fn is_load(self) -> bool {
        self.load().is_some()
    }
}

/// `bed-support`'s nodes: the posterior boundary nodes.
fn posterior_nodes(_: &TetMesh, geom: &BoundaryGeometry, sites: Sites<'_>, _: &Effect) -> Vec<u32> {
    flagged(geom, sites.posterior)
}

/// `ligament`'s nodes: the falciform boundary nodes.
fn falciform_nodes(_: &TetMesh, geom: &BoundaryGeometry, sites: Sites<'_>, _: &Effect) -> Vec<u32> {
    flagged(geom, sites.falciform)
}

fn flagged(geom: &BoundaryGeometry, flags: &[bool]) -> Vec<u32> {
    geom.nodes
        .iter()
        .copied()
        .filter(|&v| flags.get(v as usize).copied().unwrap_or(false))
        .collect()
}

/// `fixation`'s nodes: the boundary nodes within `radius_mm` of `center`.
fn region_nodes(mesh: &TetMesh, geom: &BoundaryGeometry, _: Sites<'_>, e: &Effect) -> Vec<u32> {
    nodes_within(mesh, geom, e.vector("center"), e.scalar("radius_mm"))
}

/// `inclusion`: `stiffness_ratio` at a centroid within `radius_mm` of `center`, else 1.
fn inclusion_factor(e: &Effect, c: [f64; 3]) -> f64 {
    let r = e.scalar("radius_mm");
    if dist2(c, e.vector("center")) <= r * r {
        e.scalar("stiffness_ratio")
    } else {
        1.0
    }
}

/// `gravity`: one column along `direction` (amplitude `magnitude`), with its dependent-surface
/// reaction or as its body force alone.
fn gravity_loads(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    effect: &Effect,
    reaction: bool,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError> {
    if !reaction {
        let mut f = vec![0.0; 3 * mesh.num_nodes()];
        loads::add_body_force(&mut f, mesh, effect.direction("direction"));
        return Ok((vec![f], vec![effect.scalar("magnitude")]));
    }
    Ok((
        vec![gravity_with_reaction(
            mesh,
            geom,
            effect.direction("direction"),
        )?],
        vec![effect.scalar("magnitude")],
    ))
}

/// Gravity along `g` (unit) with its reaction: the body force, balanced by a traction on the
/// faces that turn towards `g` (in proportion to how much they do), as a dependent surface
/// resting on what is below it.
fn gravity_with_reaction(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    g: [f64; 3],
) -> Result<Vec<f64>, RegisterError> {
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    loads::add_body_force(&mut f, mesh, g);
    let s: Vec<f64> = geom
        .tri_normal
        .iter()
        .map(|nn| dot(*nn, g).max(0.0))
        .collect();
    let support: f64 = s.iter().zip(&geom.tri_area).map(|(s, a)| s * a).sum();
    if support <= 0.0 {
        return Err(RegisterError::Model(
            "gravity: no boundary face turns towards the gravity direction".into(),
        ));
    }
    let c = geom.volume / support;
    let tr: Vec<[f64; 3]> = s.iter().map(|&si| g.map(|x| -c * si * x)).collect();
    loads::add_traction(&mut f, mesh.nodes(), &geom.triangles, &tr);
    Ok(f)
}

/// `pressure`: one column, unit pressure on the faces turned towards `direction` (amplitude
/// `magnitude_kpa`).
fn pressure_loads(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    effect: &Effect,
    _reaction: bool,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError> {
    let n = mesh.num_nodes();
    let d = effect.direction("direction");
    let faces: Vec<[u32; 3]> = geom
        .triangles
        .iter()
        .zip(&geom.tri_normal)
        .filter(|(_, nn)| dot(**nn, d) > 0.0)
        .map(|(t, _)| *t)
        .collect();
    if faces.is_empty() {
        return Err(RegisterError::Model(
            "pressure: no boundary face turns towards the direction".into(),
        ));
    }
    let mut f = vec![0.0; 3 * n];
    loads::add_pressure(&mut f, mesh.nodes(), &faces, 1.0);
    Ok((vec![f], vec![effect.scalar("magnitude_kpa")]))
}

/// `pack`: three columns, a unit force along x, y, z spread over the patch (amplitudes
/// `force_mn`).
fn pack_loads(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    effect: &Effect,
    _reaction: bool,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError> {
    let nodes = mesh.nodes();
    let (c, w) = (effect.vector("center"), effect.scalar("width_mm"));
    let (patch, weights, total) = pack_patch(nodes, geom, c, w);
    if patch.is_empty() || total <= 0.0 {
        return Err(RegisterError::Model(format!(
            "pack: no boundary face within 2 × width_mm = {:.1} mm of center {c:.1?}",
            2.0 * w
        )));
    }
    let cols = (0..3)
        .map(|axis| pack_column(nodes, &patch, &weights, total, axis))
        .collect();
    Ok((cols, effect.vector("force_mn").to_vec()))
}

/// `pack`: a boundary face within 2 × `width_mm` of `center`; the error names
/// `effects[i].parameters.center` and its distance to the surface.
fn pack_fits(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    e: &Effect,
    i: usize,
) -> Result<(), RegisterError> {
    let nodes = mesh.nodes();
    let (c, w) = (e.vector("center"), e.scalar("width_mm"));
    let (patch, _, total) = pack_patch(nodes, geom, c, w);
    if patch.is_empty() || total <= 0.0 {
        let d = geom
            .nodes
            .iter()
            .map(|&v| dist2(nodes[v as usize], c))
            .fold(f64::INFINITY, f64::min)
            .sqrt();
        return Err(RegisterError::Parameter(format!(
            "effects[{i}].parameters.center: [{:.1}, {:.1}, {:.1}] is {d:.1} mm from the organ's surface (its nearest boundary node); a pack needs a boundary face within 2 × width_mm = {:.1} mm of its center",
            c[0],
            c[1],
            c[2],
            2.0 * w
        )));
    }
    Ok(())
}

/// A pack's unit load along `axis`: its patch's weights, normalised by their integral `total`.
fn pack_column(
    nodes: &[[f64; 3]],
    patch: &[[u32; 3]],
    weights: &[f64],
    total: f64,
    axis: usize,
) -> Vec<f64> {
    let tr: Vec<[f64; 3]> = weights
        .iter()
        .map(|wt| {
            let mut v = [0.0; 3];
            v[axis] = wt / total;
            v
        })
        .collect();
    let mut f = vec![0.0; 3 * nodes.len()];
    loads::add_traction(&mut f, nodes, patch, &tr);
    f
}

/// The boundary faces a pack at `c`, `w` mm wide, loads (those whose three nodes lie within
/// `2·w` of `c`), their weights `exp(−½(r/w)²)`, and the weights' area integral.
fn pack_patch(
    nodes: &[[f64; 3]],
    geom: &BoundaryGeometry,
    c: [f64; 3],
    w: f64,
) -> (Vec<[u32; 3]>, Vec<f64>, f64) {
    let mut patch = Vec::new();
    let mut weights = Vec::new();
    let mut total = 0.0;
    for (t, tri) in geom.triangles.iter().enumerate() {
        if tri
            .iter()
            .all(|&v| dist2(nodes[v as usize], c) <= 4.0 * w * w)
        {
            let wt = (-0.5 * dist2(geom.tri_center[t], c) / (w * w)).exp();
            total += wt * geom.tri_area[t];
            patch.push(*tri);
            weights.push(wt);
        }
    }
    (patch, weights, total)
}
