//! Name: the candidate effects of the library, each searched over its parameters on top of the
//! current model and scored by cross-validation ([`super::cv`]).
//!
//! Load effects (`gravity`, `pressure`, `pack`) add columns to the current model's design: the
//! current model's response to the effect's unit loads, so their amplitudes are fitted linearly
//! with the LIBR weights and the poses; their shape parameters (direction, centre, width) are
//! searched on a grid and, for directions, refined. Supports and inclusions change the stiffness
//! the whole basis is built from: each grid point is a rebuilt augmented basis.

use super::DiscoverError;
use super::cv::{AmplitudePrior, CvScore, Design, cross_validate};
use super::prior::{amplitude_prior, coefficient_prior};
use super::rows::CohortRows;
use crate::mesh::TetMesh;
use crate::mesh::vec3::{cross, dist2, unit};
use crate::register::libr::{LibrBasis, LibrParams, farthest_point_sampling};
use crate::register::physics::model::{BoundaryGeometry, ModelSolver, Sites};
use crate::register::physics::{Effect, EffectKind, Physics};
use nalgebra::DMatrix;

/// The current model: its physics, basis, solver, and design over the rows.
pub struct Current {
    /// Physics carried.
    pub physics: Physics,
    /// Its basis.
    pub basis: LibrBasis,
    /// Its solver (for the unit responses of load candidates).
    pub solver: std::sync::Arc<ModelSolver>,
    /// Row values of the basis columns.
    pub a: DMatrix<f64>,
    /// Prior `λ E / ē`.
    pub prior: DMatrix<f64>,
    /// The physical prior of the carried load effects' amplitudes.
    pub amplitude: AmplitudePrior,
    /// Its cross-validated score.
    pub score: CvScore,
}

/// What the search needs of the case.
#[derive(Clone, Copy)]
pub struct SearchContext<'a> {
    /// Preoperative mesh.
    pub mesh: &'a TetMesh,
    /// Support sites.
    pub sites: Sites<'a>,
    /// LIBR parameters (the fit's λ and the basis).
    pub libr: &'a LibrParams,
    /// The cohort's rows.
    pub rows: &'a CohortRows,
    /// Boundary geometry.
    pub geom: &'a BoundaryGeometry,
    /// Noise variance (mm²) the amplitude priors are weighed with.
    pub noise_var: f64,
}

/// The amplitude prior of a basis's effect columns (the load effects of `physics`, in order,
/// after the LIBR columns; see [`LibrBasis::effect_labels`]).
pub fn basis_amplitude_prior(
    ctx: &SearchContext<'_>,
    basis: &LibrBasis,
    physics: &Physics,
) -> AmplitudePrior {
    let m = basis.columns();
    let mut out = AmplitudePrior::none(basis.libr_columns());
    let mut j = basis.libr_columns();
    for e in physics.effects.iter().filter(|e| e.kind.is_load()) {
        let k = e.kind.amplitude().map_or(0, |(_, k)| k);
        let (p, s) = match amplitude_prior(e, ctx.mesh.nodes(), ctx.geom) {
            Some((p, mu)) => {
                coefficient_prior(&p, &mu, &basis.load_scale[j..(j + k).min(m)], ctx.noise_var)
            }
            None => (DMatrix::zeros(k, k), nalgebra::DVector::zeros(k)),
        };
        out = out.extended(&p, &s);
        j += k;
    }
    debug_assert_eq!(j, m, "effect columns of the basis and its physics disagree");
    out
}

/// The parameters an effect of `kind` adds to a model, for the information criterion: a load's
/// fitted amplitudes plus its searched shape (a direction, 2; a pack's centre and width, 4), a
/// support's stiffness (with a fixation's site, 3), an inclusion's site and ratio (4): the
/// amplitudes plus the kind's [`KindSpec::searched`](crate::register::physics::kinds::KindSpec::searched).
pub fn parameter_count(kind: EffectKind) -> usize {
    let amplitudes = kind.amplitude().map_or(0, |(_, k)| k);
    amplitudes + kind.spec().searched
}

/// One evaluated candidate.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The effect with its parameters (amplitudes from the full fit).
    pub effect: Effect,
    /// A support evaluated with it (a load carried by it: a pair, `pair_candidates` in the discover module);
    /// `None` for a single effect.
    pub partner: Option<Effect>,
    /// Cross-validated score of current + this effect.
    pub score: CvScore,
    /// Extra parameters (amplitudes + searched shape parameters), for the information criterion.
    pub parameters: usize,
    /// Standard deviation of each fitted amplitude, in the parameter's unit (by parameter name).
    pub amplitude_sd: Vec<(String, f64)>,
    /// Design columns (for a load effect) to append; empty for a rebuilt model.
    pub columns: Option<(DMatrix<f64>, DMatrix<f64>)>,
    /// The rebuilt basis (supports, inclusion).
    pub basis: Option<LibrBasis>,
    /// The amplitude prior of the candidate's design.
    pub amplitude: Option<AmplitudePrior>,
}

impl Candidate {
    /// Kinds, `+`-joined (the partner first).
    pub fn kinds(&self) -> String {
        match &self.partner {
            Some(p) => format!("{}+{}", p.kind.name(), self.effect.kind.name()),
            None => self.effect.kind.name().to_string(),
        }
    }

    /// The effects, described (the partner first).
    pub fn describe(&self) -> String {
        match &self.partner {
            Some(p) => format!("{} + {}", p.describe(), self.effect.describe()),
            None => self.effect.describe(),
        }
    }
}

/// The candidate of a family that fits the data best (least full-fit misfit: maximum
/// likelihood for its shape parameters).
pub fn best_fit(family: &[Candidate]) -> Option<Candidate> {
    family
        .iter()
        .min_by(|a, b| a.score.full_rss.total_cmp(&b.score.full_rss))
        .cloned()
}

/// The design of a basis over the rows: row values and the prior `λ E / ē`.
pub fn basis_design(
    rows: &CohortRows,
    basis: &LibrBasis,
    lambda: f64,
) -> (DMatrix<f64>, DMatrix<f64>) {
    let m = basis.columns();
    let mut a = DMatrix::<f64>::zeros(rows.rows.len(), m);
    let mut buf = vec![0.0; m];
    for (i, r) in rows.rows.iter().enumerate() {
        r.values_into(&basis.phi, m, &mut buf);
        for j in 0..m {
            a[(i, j)] = buf[j];
        }
    }
    let e = basis.energy_scale();
    let prior = DMatrix::from_fn(m, m, |i, j| lambda * basis.energy[i * m + j] / e);
    (a, prior)
}

/// Evaluates a load effect on top of the current model: appends the current model's responses to
/// the effect's unit loads (scaled to a 1 mm peak) as columns and cross-validates.
pub fn evaluate_load(
    ctx: &SearchContext<'_>,
    cur: &Current,
    effect: &Effect,
) -> Result<Option<Candidate>, DiscoverError> {
    let (loads, _) = cur.solver.effect_unit_loads(ctx.mesh, ctx.geom, effect)?;
    let m = cur.basis.columns();
    let k = loads.len();
    let q = m + k;
    let mut a = DMatrix::<f64>::zeros(ctx.rows.rows.len(), q);
    a.view_mut((0, 0), (ctx.rows.rows.len(), m))
        .copy_from(&cur.a);
    let mut responses = Vec::with_capacity(k);
    let mut scales = Vec::with_capacity(k);
    for l in &loads {
        let u = cur.solver.solve_effect(l);
        let peak = u
            .chunks_exact(3)
            .map(|c| (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt())
            .fold(0.0f64, f64::max);
        if !(peak.is_finite() && peak > 0.0) {
            return Ok(None);
        }
        responses.push(u.iter().map(|x| x / peak).collect::<Vec<f64>>());
        scales.push(1.0 / peak);
    }
    for (j, u) in responses.iter().enumerate() {
        for (i, r) in ctx.rows.rows.iter().enumerate() {
            a[(i, m + j)] = r.value(u);
        }
    }
    // Prior: the current model's; the new effect columns are not under the strain-energy prior
    // (the effect is part of the model) but under the physics' prior of their amplitude
    // ([`super::prior`]).
    let mut prior = DMatrix::<f64>::zeros(q, q);
    prior.view_mut((0, 0), (m, m)).copy_from(&cur.prior);
    let amplitude = match amplitude_prior(effect, ctx.mesh.nodes(), ctx.geom) {
        Some((p, mu)) => {
            let (p, s) = coefficient_prior(&p, &mu, &scales, ctx.noise_var);
            cur.amplitude.extended(&p, &s)
        }
        None => cur
            .amplitude
            .extended(&DMatrix::zeros(k, k), &nalgebra::DVector::zeros(k)),
    };
    let Some(score) = cross_validate(
        ctx.rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &amplitude,
        },
    ) else {
        return Ok(None);
    };
    // Amplitudes (in the effect's unit) and their standard deviations.
    let var = score.full_rss / score.full_w.max(1e-300);
    let amp: Vec<f64> = (0..k).map(|j| score.coef[m + j] * scales[j]).collect();
    let sd: Vec<f64> = (0..k)
        .map(|j| (var * score.inverse[(m + j, m + j)]).sqrt() * scales[j])
        .collect();
    let name = effect.kind.amplitude().map_or("", |(n, _)| n);
    let parameters = parameter_count(effect.kind);
    let Some(effect) = with_amplitudes(effect, amp, &cur.physics) else {
        return Ok(None);
    };
    let amplitude_sd = vec![(
        name.to_string(),
        sd.iter().map(|x| x * x).sum::<f64>().sqrt(),
    )];
    let new_cols = a.columns(m, k).into_owned();
    Ok(Some(Candidate {
        effect,
        partner: None,
        score,
        parameters,
        amplitude_sd,
        columns: Some((new_cols, prior)),
        basis: None,
        amplitude: Some(amplitude),
    }))
}

/// A load effect with its fitted amplitudes (in its parameter's unit), or `None` when they are
/// outside the kind's valid or physically plausible range ([`super::prior`]) for a load carried
/// by `carried_by`'s supports: a negative weight or a force of tons is not that effect.
pub fn with_amplitudes(effect: &Effect, amp: Vec<f64>, carried_by: &Physics) -> Option<Effect> {
    let (name, _) = effect.kind.amplitude()?;
    let mut e = effect.clone();
    e.parameters.insert(name.to_string(), amp);
    (e.validate("candidate").is_ok() && super::prior::amplitude_plausible_on(&e, carried_by))
        .then_some(e)
}

/// Evaluates a stiffness effect (support or inclusion) by rebuilding the basis with it.
pub fn evaluate_rebuilt(
    ctx: &SearchContext<'_>,
    cur: &Current,
    effect: &Effect,
) -> Result<Option<Candidate>, DiscoverError> {
    let mut physics = Physics {
        effects: cur
            .physics
            .effects
            .iter()
            .filter(|e| !e.kind.is_load())
            .cloned()
            .collect(),
    };
    physics.effects.push(effect.clone());
    // Load effects already carried are kept as effect columns of the rebuilt basis.
    physics.effects.extend(
        cur.physics
            .effects
            .iter()
            .filter(|e| e.kind.is_load())
            .cloned(),
    );
    let basis = match LibrBasis::build_with(ctx.mesh, ctx.libr, &physics, ctx.sites) {
        Ok(b) => b,
        // A support that attaches nowhere, or a degenerate column: not a candidate.
        Err(crate::register::RegisterError::Model(_)) => return Ok(None),
        Err(e) => return Err(e.into()),
    };
    let (a, prior) = basis_design(ctx.rows, &basis, ctx.libr.fit.regularization);
    let amplitude = basis_amplitude_prior(ctx, &basis, &physics);
    let Some(score) = cross_validate(
        ctx.rows,
        &Design {
            a: &a,
            prior: &prior,
            amplitude: &amplitude,
        },
    ) else {
        return Ok(None);
    };
    Ok(Some(Candidate {
        effect: effect.clone(),
        partner: None,
        score,
        parameters: parameter_count(effect.kind),
        amplitude_sd: Vec::new(),
        columns: None,
        basis: Some(basis),
        amplitude: Some(amplitude),
    }))
}

/// Unit directions spread over the sphere (Fibonacci lattice).
pub fn sphere_directions(count: usize) -> Vec<[f64; 3]> {
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    (0..count)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / count as f64;
            let r = (1.0 - z * z).sqrt();
            let t = golden * i as f64;
            [r * t.cos(), r * t.sin(), z]
        })
        .collect()
}

/// Directions within `angle` (radians) of `d`: `d` turned by ±angle about two perpendicular axes.
pub fn neighbours(d: [f64; 3], angle: f64) -> Vec<[f64; 3]> {
    let t1 = unit(if d[0].abs() < 0.9 {
        cross(d, [1.0, 0.0, 0.0])
    } else {
        cross(d, [0.0, 1.0, 0.0])
    });
    let t2 = cross(d, t1);
    let (s, c) = angle.sin_cos();
    [t1, t2, t1.map(|x| -x), t2.map(|x| -x)]
        .into_iter()
        .map(|t| unit([0, 1, 2].map(|k| c * d[k] + s * t[k])))
        .collect()
}

/// Angle between two unit vectors (degrees).
pub use crate::mesh::vec3::angle_deg;

/// Boundary sites for centred effects: farthest-point samples of the boundary nodes.
pub fn boundary_sites(mesh: &TetMesh, geom: &BoundaryGeometry, count: usize) -> Vec<[f64; 3]> {
    farthest_point_sampling(mesh.nodes(), &geom.nodes, count, 0)
        .into_iter()
        .map(|v| mesh.nodes()[v as usize])
        .collect()
}

/// Interior sites for inclusions: farthest-point samples of the nodes at least `depth` from the
/// boundary nodes.
pub fn interior_sites(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    depth: f64,
    count: usize,
) -> Vec<[f64; 3]> {
    let b: Vec<[f64; 3]> = geom
        .nodes
        .iter()
        .map(|&v| mesh.nodes()[v as usize])
        .collect();
    let deep: Vec<u32> = (0..mesh.num_nodes() as u32)
        .filter(|&v| {
            let p = mesh.nodes()[v as usize];
            b.iter().all(|q| dist2(*q, p) >= depth * depth)
        })
        .collect();
    farthest_point_sampling(mesh.nodes(), &deep, count, 0)
        .into_iter()
        .map(|v| mesh.nodes()[v as usize])
        .collect()
}
