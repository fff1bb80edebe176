//! Compressible hyperelastic solids, total Lagrangian, P1 tets: the ground-truth mechanics.
//!
//! The default law is the compressible Neo-Hookean solid below; [`MaterialLaw`] adds a
//! compressible Mooney–Rivlin solid and Demiray's exponentially stiffening solid, both reducing to
//! the same linear elasticity at small strain (so they differ from Neo-Hookean only where strains
//! are large: other truths for the same linear model).
//!
//! Strain energy density `W(F) = μ/2 (tr FᵀF − 3) − μ ln J + λ/2 (ln J)²` (Bonet & Wood,
//! "Nonlinear Continuum Mechanics for Finite Element Analysis", §6.4.3), with first Piola–Kirchhoff
//! stress `P = μ (F − F⁻ᵀ) + λ ln J F⁻ᵀ` and the consistent tangent
//! `∂P_iJ/∂F_kL = μ δ_ik δ_JL + λ F⁻¹_Ji F⁻¹_Lk + (μ − λ ln J) F⁻¹_Jk F⁻¹_Li`. At small strain it
//! reduces to linear elasticity with the same Lamé parameters. Loads are dead loads (body forces,
//! tractions and pressure given on the reference configuration), plus linear node springs,
//! unilateral contact springs (a support that pushes but never pulls: [`ContactSpring`]) and
//! prescribed displacements. [`HyperelasticModel::solve`] runs Newton's method with a backtracking
//! line search on the total potential energy and adaptive load stepping; a deformation that does not
//! converge is an error, never a result. The symbolic Cholesky factorization is computed once and
//! reused by every Newton iteration.

use super::assembly::{LameField, assemble_blocks};
use super::element::p1_gradients;
use super::solver::{
    Dirichlet, FemError, NewtonFailure, NodeSpring, ReducedPattern, StiffnessSystem,
};
use crate::mesh::TetMesh;
use faer::Mat;
use rayon::prelude::*;
use std::time::Instant;

mod law;
use law::{M3, TangentTerms, inv_transpose};
pub use law::{MaterialLaw, energy_density, pk1};

/// Parameters of the Newton solver with load stepping.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NewtonParams {
    /// Converged when ‖r_free‖ ≤ `tolerance` · max(‖f_ext‖, ‖f_int‖) (relative force residual).
    /// Default 1e-9.
    pub tolerance: f64,
    /// Newton iterations allowed per load step before the step is cut. Default 30.
    pub max_iterations: usize,
    /// First load increment as a fraction of the full load. Default 0.25.
    pub initial_step: f64,
    /// Smallest load increment before giving up. Default 1e-4.
    pub min_step: f64,
    /// Line-search halvings allowed per iteration. Default 20.
    pub max_halvings: usize,
}

impl Default for NewtonParams {
    fn default() -> Self {
        Self {
            tolerance: 1e-9,
            max_iterations: 30,
            initial_step: 0.25,
            min_step: 1e-4,
            max_halvings: 20,
        }
    }
}

/// What the nonlinear solve did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct NewtonInfo {
    /// Accepted load steps.
    pub load_steps: usize,
    /// Load steps that failed and were cut in half.
    pub cutbacks: usize,
    /// Newton iterations over all steps (accepted and failed).
    pub iterations: usize,
    /// Final relative force residual.
    pub relative_residual: f64,
    /// Time assembling internal forces and tangents (s).
    pub assemble_s: f64,
    /// Time in numeric factorizations (s).
    pub factor_s: f64,
    /// Time in the symbolic factorization (once) (s).
    pub symbolic_s: f64,
    /// Total time (s).
    pub total_s: f64,
}

/// A unilateral (compression-only) support at a node: a penalty contact with a rigid organ bed.
/// With the outward surface normal `n` and the gap closure `g = u·n`, it stores `k/2 · max(g, 0)²`
/// and pushes back with `−k g n` only while the node presses into the bed (`g > 0`); a node pulled
/// away from the bed lifts off freely. A linear model can only represent it as a bilateral spring
/// `k n nᵀ` ([`ContactSpring::bilateral`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ContactSpring {
    /// Node index.
    pub node: u32,
    /// Outward unit normal (towards the bed).
    pub normal: [f64; 3],
    /// Penalty stiffness (mN/mm).
    pub stiffness: f64,
}

impl ContactSpring {
    /// The linear stand-in: a bilateral spring `k n nᵀ` along the normal.
    pub fn bilateral(&self) -> NodeSpring {
        NodeSpring::normal_tangent(self.node, self.normal, self.stiffness, 0.0)
    }

    /// Gap closure `u·n` (mm) for a full displacement vector; positive = pressing into the bed.
    pub fn closure(&self, u: &[f64]) -> f64 {
        let i = 3 * self.node as usize;
        u[i] * self.normal[0] + u[i + 1] * self.normal[1] + u[i + 2] * self.normal[2]
    }
}

/// Per-tet reference geometry.
#[derive(Debug, Clone, Copy)]
struct RefTet {
    g: [[f64; 3]; 4],
    v0: f64,
}

/// A Neo-Hookean model of a mesh: reference geometry, material field, springs and the sparsity
/// pattern; evaluates energy, internal forces and tangents, and solves loaded equilibria.
#[derive(Debug, Clone)]
pub struct HyperelasticModel {
    tets: Vec<[u32; 4]>,
    reference: Vec<RefTet>,
    lame: LameField,
    system: StiffnessSystem,
    contacts: Vec<ContactSpring>,
    law: MaterialLaw,
}

impl HyperelasticModel {
    /// Builds the model; rejects degenerate tets and invalid Lamé parameters (as the linear model).
    pub fn new(mesh: &TetMesh, lame: LameField) -> Result<Self, FemError> {
        let system = StiffnessSystem::linear_field(mesh, &lame)?;
        let reference = (0..mesh.num_tets())
            .map(|t| {
                let (g, v) = p1_gradients(&mesh.tet_points(t)).ok_or(FemError::DegenerateTet {
                    tet: t,
                    volume: mesh.tet_volume(t),
                })?;
                Ok(RefTet { g, v0: v.abs() })
            })
            .collect::<Result<Vec<_>, FemError>>()?;
        Ok(Self {
            tets: mesh.tets().to_vec(),
            reference,
            lame,
            system,
            contacts: Vec::new(),
            law: MaterialLaw::NeoHookean,
        })
    }

    /// The same model with another strain-energy law (Neo-Hookean by default); refuses a law
    /// whose parameter is out of range.
    pub fn with_law(mut self, law: MaterialLaw) -> Result<Self, FemError> {
        law.validate()
            .map_err(|message| FemError::InvalidParameter {
                field: "material law",
                message,
            })?;
        self.law = law;
        Ok(self)
    }

    /// The strain-energy law.
    pub fn law(&self) -> MaterialLaw {
        self.law
    }

    /// Adds linear node springs (e.g. posterior support).
    pub fn add_springs(&mut self, springs: &[NodeSpring]) -> Result<(), FemError> {
        self.system.add_springs(springs)
    }

    /// Adds unilateral contact springs; normals are normalised here. Rejects out-of-range nodes,
    /// zero or non-finite normals and negative or non-finite stiffness.
    pub fn add_contacts(&mut self, contacts: &[ContactSpring]) -> Result<(), FemError> {
        let nodes = self.dofs() / 3;
        for (k, c) in contacts.iter().enumerate() {
            let bad = |message: String| FemError::InvalidParameter {
                field: "contacts",
                message: format!("contact {k} (node {}): {message}", c.node),
            };
            if c.node as usize >= nodes {
                return Err(bad(format!("node out of range ({nodes} nodes)")));
            }
            let len = c.normal.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !(len > 0.0 && len.is_finite()) {
                return Err(bad(format!("normal {:?} has no direction", c.normal)));
            }
            if !(c.stiffness >= 0.0 && c.stiffness.is_finite()) {
                return Err(bad(format!(
                    "stiffness {} must be finite and ≥ 0",
                    c.stiffness
                )));
            }
            self.contacts.push(ContactSpring {
                normal: c.normal.map(|x| x / len),
                ..*c
            });
        }
        Ok(())
    }

    /// The contact springs added so far.
    pub fn contacts(&self) -> &[ContactSpring] {
        &self.contacts
    }

    /// Number of contact springs pressing into the bed at `u` (active set).
    pub fn active_contacts(&self, u: &[f64]) -> usize {
        self.contacts.iter().filter(|c| c.closure(u) > 0.0).count()
    }

    fn contact_energy(&self, u: &[f64]) -> f64 {
        self.contacts
            .iter()
            .map(|c| 0.5 * c.stiffness * c.closure(u).max(0.0).powi(2))
            .sum()
    }

    fn add_contact_forces(&self, u: &[f64], out: &mut [f64]) {
        for c in &self.contacts {
            let g = c.closure(u);
            if g > 0.0 {
                for a in 0..3 {
                    out[3 * c.node as usize + a] += c.stiffness * g * c.normal[a];
                }
            }
        }
    }

    fn add_contact_values(&self, u: &[f64], values: &mut [f64]) {
        let pattern = self.system.pattern();
        for c in &self.contacts {
            if c.closure(u) > 0.0 {
                let i = c.node as usize;
                for a in 0..3 {
                    for b in 0..3 {
                        if let Some(idx) = pattern.value_index(i, a, i, b) {
                            values[idx] += c.stiffness * c.normal[a] * c.normal[b];
                        }
                    }
                }
            }
        }
    }

    /// The linear system with the same pattern, material (at small strain) and springs.
    pub fn linearized(&self) -> &StiffnessSystem {
        &self.system
    }

    /// Number of dofs.
    pub fn dofs(&self) -> usize {
        self.system.dofs()
    }

    #[inline]
    fn lame_at(&self, t: usize) -> (f64, f64) {
        match &self.lame {
            LameField::Uniform(l, m) => (*l, *m),
            LameField::PerTet(v) => v[t],
        }
    }

    /// Deformation gradient of tet `t` for the full displacement `u`.
    #[inline]
    fn deformation_gradient(&self, t: usize, u: &[f64]) -> M3 {
        let g = &self.reference[t].g;
        let tet = self.tets[t];
        let mut f = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        for (i, &n) in tet.iter().enumerate() {
            let n = n as usize;
            for a in 0..3 {
                let ua = u[3 * n + a];
                for b in 0..3 {
                    f[a][b] += ua * g[i][b];
                }
            }
        }
        f
    }

    /// Stored energy (strain + springs) in mN·mm; `None` if any element is inverted.
    pub fn energy(&self, u: &[f64]) -> Option<f64> {
        // Per-tet values in parallel, summed in a fixed order: the same bits on every run.
        let per_tet: Vec<Option<f64>> = (0..self.tets.len())
            .into_par_iter()
            .map(|t| {
                let (l, m) = self.lame_at(t);
                self.law
                    .energy_density(&self.deformation_gradient(t, u), l, m)
                    .map(|w| w * self.reference[t].v0)
            })
            .collect();
        let strain: Option<f64> = per_tet.into_iter().sum();
        let ks = self.system.spring_force(u);
        let springs: f64 = 0.5 * ks.iter().zip(u).map(|(a, b)| a * b).sum::<f64>();
        strain.map(|s| s + springs + self.contact_energy(u))
    }

    /// Internal nodal forces (mN) including springs; `None` if any element is inverted.
    pub fn internal_force(&self, u: &[f64]) -> Option<Vec<f64>> {
        let per_tet: Vec<Option<[[f64; 3]; 4]>> = (0..self.tets.len())
            .into_par_iter()
            .map(|t| {
                let (l, m) = self.lame_at(t);
                let p = self.law.pk1(&self.deformation_gradient(t, u), l, m)?;
                let RefTet { g, v0 } = self.reference[t];
                let mut f = [[0.0; 3]; 4];
                for i in 0..4 {
                    for a in 0..3 {
                        f[i][a] = v0 * (p[a][0] * g[i][0] + p[a][1] * g[i][1] + p[a][2] * g[i][2]);
                    }
                }
                Some(f)
            })
            .collect();
        let mut out = self.system.spring_force(u);
        self.add_contact_forces(u, &mut out);
        for (t, f) in per_tet.into_iter().enumerate() {
            let f = f?;
            for (i, &n) in self.tets[t].iter().enumerate() {
                for a in 0..3 {
                    out[3 * n as usize + a] += f[i][a];
                }
            }
        }
        Some(out)
    }

    /// Tangent stiffness values (mN/mm) on the model's pattern, springs included; `None` if any
    /// element is inverted.
    pub fn tangent_values(&self, u: &[f64]) -> Option<Vec<f64>> {
        if self.law != MaterialLaw::NeoHookean {
            return self.law_tangent_values(u);
        }
        // Per tet: spatial gradients h = F⁻ᵀ g and the coefficient μ − λ ln J.
        let kin: Vec<Option<([[f64; 3]; 4], f64)>> = (0..self.tets.len())
            .into_par_iter()
            .map(|t| {
                let (fit, j) = inv_transpose(&self.deformation_gradient(t, u))?;
                let (l, m) = self.lame_at(t);
                let g = &self.reference[t].g;
                let mut h = [[0.0; 3]; 4];
                for i in 0..4 {
                    for a in 0..3 {
                        h[i][a] = fit[a][0] * g[i][0] + fit[a][1] * g[i][1] + fit[a][2] * g[i][2];
                    }
                }
                Some((h, m - l * j.ln()))
            })
            .collect();
        if kin.iter().any(|k| k.is_none()) {
            return None;
        }
        let mut values = assemble_blocks(self.system.pattern(), &self.tets, |t, lj, li| {
            let (h, c) = kin[t]?;
            let (l, m) = self.lame_at(t);
            let RefTet { g, v0 } = self.reference[t];
            let gg = g[lj][0] * g[li][0] + g[lj][1] * g[li][1] + g[lj][2] * g[li][2];
            let mut k = [[0.0; 3]; 3];
            for a in 0..3 {
                for b in 0..3 {
                    let diag = if a == b { m * gg } else { 0.0 };
                    k[a][b] = v0 * (diag + l * h[lj][a] * h[li][b] + c * h[li][a] * h[lj][b]);
                }
            }
            Some(k)
        });
        self.system.add_spring_values(&mut values);
        self.add_contact_values(u, &mut values);
        Some(values)
    }

    /// [`Self::tangent_values`] for any law, from its [`TangentTerms`].
    fn law_tangent_values(&self, u: &[f64]) -> Option<Vec<f64>> {
        let terms: Vec<Option<TangentTerms>> = (0..self.tets.len())
            .into_par_iter()
            .map(|t| {
                let (l, m) = self.lame_at(t);
                self.law
                    .tangent_terms(&self.deformation_gradient(t, u), l, m)
            })
            .collect();
        if terms.iter().any(|k| k.is_none()) {
            return None;
        }
        let apply = |m: &M3, g: &[f64; 3]| -> [f64; 3] {
            [0, 1, 2].map(|a| m[a][0] * g[0] + m[a][1] * g[1] + m[a][2] * g[2])
        };
        let mut values = assemble_blocks(self.system.pattern(), &self.tets, |t, p, q| {
            let tt = terms[t].as_ref()?;
            let RefTet { g, v0 } = self.reference[t];
            let (gp, gq) = (&g[p], &g[q]);
            let gg = gp[0] * gq[0] + gp[1] * gq[1] + gp[2] * gq[2];
            let (hp, hq) = (apply(&tt.fit, gp), apply(&tt.fit, gq));
            let (fp, fq) = (apply(&tt.f, gp), apply(&tt.f, gq));
            let mut k = [[0.0; 3]; 3];
            for a in 0..3 {
                for b in 0..3 {
                    let diag = if a == b { tt.shear * gg } else { 0.0 };
                    k[a][b] = diag
                        + tt.lambda * hp[a] * hq[b]
                        + tt.cross * hp[b] * hq[a]
                        + tt.ff * fp[a] * fq[b]
                        + tt.ff_swapped * fq[a] * fp[b];
                }
            }
            if let Some((c, bm, k2)) = &tt.c {
                let cgq = apply(c, gq);
                let gcg = gp[0] * cgq[0] + gp[1] * cgq[1] + gp[2] * cgq[2];
                for a in 0..3 {
                    for b in 0..3 {
                        let diag = if a == b { gcg } else { 0.0 };
                        k[a][b] += k2 * (diag + bm[a][b] * gg);
                    }
                }
            }
            Some(k.map(|r| r.map(|x| x * v0)))
        });
        self.system.add_spring_values(&mut values);
        self.add_contact_values(u, &mut values);
        Some(values)
    }

    /// Equilibrium under dead loads `f_ext` (mN, full vector) and prescribed displacements `bc`,
    /// both applied in load steps from zero. Returns the displacement (mm) and what happened.
    pub fn solve(
        &self,
        bc: &Dirichlet,
        f_ext: &[f64],
        params: &NewtonParams,
    ) -> Result<(Vec<f64>, NewtonInfo), FemError> {
        let t0 = Instant::now();
        let n = self.dofs();
        if f_ext.len() != n || bc.len() != n {
            return Err(FemError::InvalidParameter {
                field: "loads",
                message: format!(
                    "{} load values and {} constraint dofs for a {n}-dof model",
                    f_ext.len(),
                    bc.len()
                ),
            });
        }
        if let Some(i) = f_ext.iter().position(|x| !x.is_finite()) {
            return Err(FemError::InvalidParameter {
                field: "loads",
                message: format!("node {} axis {} has a non-finite load", i / 3, i % 3),
            });
        }
        let constrained: Vec<bool> = (0..n).map(|d| bc.get(d).is_some()).collect();
        let target: Vec<f64> = (0..n).map(|d| bc.get(d).unwrap_or(0.0)).collect();
        if let Some(d) = target.iter().position(|x| !x.is_finite()) {
            return Err(FemError::InvalidParameter {
                field: "dirichlet",
                message: format!("node {} axis {} has a non-finite value", d / 3, d % 3),
            });
        }
        let ts = Instant::now();
        let reduced = ReducedPattern::new(&self.system, &constrained)?;
        let mut info = NewtonInfo {
            symbolic_s: ts.elapsed().as_secs_f64(),
            ..Default::default()
        };
        let mut u = vec![0.0; n];
        let mut s = 0.0;
        let mut ds = params.initial_step.clamp(params.min_step, 1.0);
        while s < 1.0 {
            let s_new = (s + ds).min(1.0);
            let trial_start = Instant::now();
            let mut trial = self.predict(&reduced, &u, &constrained, &target, s, s_new);
            info.assemble_s += trial_start.elapsed().as_secs_f64();
            match self.newton(&reduced, &mut trial, f_ext, s_new, params, &mut info) {
                Ok(its) => {
                    u = trial;
                    s = s_new;
                    info.load_steps += 1;
                    if its <= 6 {
                        ds = (ds * 1.5).min(1.0);
                    }
                }
                Err(e) => {
                    info.cutbacks += 1;
                    ds *= 0.5;
                    if ds < params.min_step {
                        return Err(FemError::NotConverged {
                            load_fraction: s,
                            iterations: info.iterations,
                            reason: e,
                        });
                    }
                }
            }
        }
        info.total_s = t0.elapsed().as_secs_f64();
        Ok((u, info))
    }

    /// Start of a load step: the prescribed dofs move to their values at `s_new`, and the free dofs
    /// follow them through the tangent at the converged state (`Δu_f = −K_ff⁻¹ K_fc Δu_c`), so a
    /// retractor pull spreads smoothly instead of crushing the elements next to it. Falls back to
    /// moving only the prescribed dofs when the tangent is unavailable or the prediction inverts.
    fn predict(
        &self,
        reduced: &ReducedPattern,
        u: &[f64],
        constrained: &[bool],
        target: &[f64],
        s: f64,
        s_new: f64,
    ) -> Vec<f64> {
        let mut jump = vec![0.0; u.len()];
        let mut moving = false;
        for d in 0..u.len() {
            if constrained[d] {
                jump[d] = (s_new - s) * target[d];
                moving |= jump[d] != 0.0;
            }
        }
        let mut plain = u.to_vec();
        for d in 0..u.len() {
            plain[d] += jump[d];
        }
        if !moving {
            return plain;
        }
        let Some(values) = self.tangent_values(u) else {
            return plain;
        };
        let Ok(factor) = reduced.factor(&values) else {
            return plain;
        };
        let lift = self.system.apply_values(&values, &jump);
        let free = reduced.free_dofs();
        let mut du = Mat::<f64>::zeros(free.len(), 1);
        for (k, &d) in free.iter().enumerate() {
            du[(k, 0)] = -lift[d];
        }
        factor.solve_in_place(du.as_mut());
        let mut predicted = plain.clone();
        for (k, &d) in free.iter().enumerate() {
            predicted[d] += du[(k, 0)];
        }
        if self.energy(&predicted).is_some() {
            predicted
        } else {
            plain
        }
    }

    /// Newton iterations at load factor `s`; `u` holds the prescribed values already. Returns the
    /// iteration count, or why it failed.
    fn newton(
        &self,
        reduced: &ReducedPattern,
        u: &mut [f64],
        f_ext: &[f64],
        s: f64,
        params: &NewtonParams,
        info: &mut NewtonInfo,
    ) -> Result<usize, NewtonFailure> {
        let free = reduced.free_dofs();
        let potential = |u: &[f64]| -> Option<f64> {
            let e = self.energy(u)?;
            let w: f64 = f_ext.iter().zip(u).map(|(f, x)| s * f * x).sum();
            Some(e - w)
        };
        let residual = |u: &[f64]| -> Option<(Vec<f64>, f64, f64)> {
            let fi = self.internal_force(u)?;
            let r: Vec<f64> = free.iter().map(|&d| fi[d] - s * f_ext[d]).collect();
            let rn = r.iter().map(|x| x * x).sum::<f64>().sqrt();
            let scale = fi
                .iter()
                .map(|x| x * x)
                .sum::<f64>()
                .sqrt()
                .max(s * f_ext.iter().map(|x| x * x).sum::<f64>().sqrt());
            Some((r, rn, scale))
        };
        let ta = Instant::now();
        let (mut r, mut rn, mut scale) =
            residual(u).ok_or(NewtonFailure::Inverted("at the start of the step"))?;
        let mut pi = potential(u).ok_or(NewtonFailure::Inverted("at the start of the step"))?;
        info.assemble_s += ta.elapsed().as_secs_f64();
        for it in 1..=params.max_iterations {
            info.iterations += 1;
            if rn <= params.tolerance * scale.max(f64::MIN_POSITIVE) {
                info.relative_residual = rn / scale.max(f64::MIN_POSITIVE);
                return Ok(it - 1);
            }
            let ta = Instant::now();
            let values = self
                .tangent_values(u)
                .ok_or(NewtonFailure::Inverted("in the tangent"))?;
            info.assemble_s += ta.elapsed().as_secs_f64();
            let tf = Instant::now();
            let factor = reduced.factor(&values).map_err(|e| match e {
                FemError::NotPositiveDefinite { node, axis, .. } => {
                    NewtonFailure::Unstable { node, axis }
                }
                other => NewtonFailure::Factorisation(Box::new(other)),
            })?;
            info.factor_s += tf.elapsed().as_secs_f64();
            let mut du = Mat::<f64>::zeros(free.len(), 1);
            for (k, &x) in r.iter().enumerate() {
                du[(k, 0)] = -x;
            }
            factor.solve_in_place(du.as_mut());
            let slope: f64 = r.iter().enumerate().map(|(k, x)| x * du[(k, 0)]).sum();
            // Backtracking line search on the potential energy (residual decrease accepted too,
            // since energy differences drown in round-off near convergence).
            let mut alpha = 1.0;
            let mut accepted = false;
            let base = u.to_vec();
            for _ in 0..=params.max_halvings {
                for (k, &d) in free.iter().enumerate() {
                    u[d] = base[d] + alpha * du[(k, 0)];
                }
                let ta = Instant::now();
                let trial = potential(u).zip(residual(u));
                info.assemble_s += ta.elapsed().as_secs_f64();
                if let Some((p_new, (r_new, rn_new, scale_new))) = trial
                    && (p_new <= pi + 1e-4 * alpha * slope || rn_new < rn)
                {
                    pi = p_new;
                    r = r_new;
                    rn = rn_new;
                    scale = scale_new;
                    accepted = true;
                    break;
                }
                alpha *= 0.5;
            }
            if !accepted {
                u.copy_from_slice(&base);
                return Err(NewtonFailure::LineSearch { iteration: it });
            }
        }
        if rn <= params.tolerance * scale.max(f64::MIN_POSITIVE) {
            info.relative_residual = rn / scale.max(f64::MIN_POSITIVE);
            return Ok(params.max_iterations);
        }
        Err(NewtonFailure::NoConvergence {
            iterations: params.max_iterations,
            relative_residual: rn / scale.max(f64::MIN_POSITIVE),
        })
    }
}
