//! The physics of each effect: its supports (springs), its material field, its loads, and the
//! augmented model's elastic solve ([`ModelSolver`]) that LIBR's basis and the hidden-effect
//! generator share.
//!
//! - `gravity`: body force `m·ĝ` on every tet, carried by a reaction on the dependent surface
//!   (boundary faces with `s = n·ĝ > 0`, traction `−c·s·ĝ`, `c` so that the reaction balances the
//!   weight): the organ's weight resting on what lies below it. On a free body the remaining
//!   moment goes to inertia relief.
//! - `bed-support`: on every posterior boundary node a spring of `stiffness·A` along the vertex
//!   normal and a tenth of it across (A the node's lumped boundary area).
//! - `fixation`: isotropic springs `stiffness·A` on the boundary nodes within `radius_mm` of
//!   `center`.
//! - `ligament`: isotropic springs `stiffness·A` on the falciform-ligament nodes.
//! - `pressure`: `magnitude_kpa` on the boundary faces whose outward normal has `n·d > 0`.
//! - `pack`: a traction falling off as `exp(−½(r/width)²)` from `center` on faces within
//!   `2·width`, scaled so the forces add up to `force_mn` (as the phantom's packs).
//! - `inclusion`: Young's modulus × `stiffness_ratio` in tets whose centroid is within
//!   `radius_mm` of `center` (ν unchanged).
//!
//! LIBR's own loads (the control loads, and the base load of a generated truth) are replaced by
//! their self-equilibrated part (inertia relief), as LIBR's basis: the organ's surroundings hold
//! what pushes it. Free-floating (no support): solved under a statically determinate 3-2-1
//! support, and the rigid part is removed, exactly as LIBR's basis. Supported: the springs add
//! the stiffness that holds the organ where they act; no constraint is added and the rigid part
//! is kept (it is the organ moving on its supports). The supports do not carry LIBR's loads'
//! net force: a fixation patch or the falciform line carrying a surgeon's push would let the
//! linear model swing through metres (measured: 80–3000 mm mean displacement under the
//! generator's base load before this rule).
//!
//! The effects' loads are carried as in the body ([`Carry::Supports`]): on a supported model
//! the supports carry their net force and moment (gravity as its weight alone, a pack, a
//! pressure), in the augmented basis ([`ModelSolver::solve_effect`]) and in the generator's
//! truth ([`forward_with`]) alike. A free-floating model cannot carry a net load: there gravity
//! rests on its dependent surface and inertia relief balances the rest ([`forward`]).

pub use super::boundary::{BoundaryGeometry, Sites, nodes_within};
use super::kinds::{Material, Role};
use super::{Effect, Physics};
use crate::fem::{
    Dirichlet, FactorizedSystem, LameField, LinearMaterial, NodeSpring, StiffnessSystem,
};
use crate::mesh::TetMesh;
use crate::register::RegisterError;
use crate::register::equilibrium::{RigidModes, lumped_volumes, support_321};
use faer::{Mat, MatRef};

/// The springs of the physics' supports on a mesh (see the module doc).
pub fn support_springs(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    sites: Sites<'_>,
    physics: &Physics,
) -> Vec<NodeSpring> {
    let mut out = Vec::new();
    for e in &physics.effects {
        let Role::Support(s) = e.kind.role() else {
            continue;
        };
        let k = e.scalar(s.stiffness);
        for v in (s.held)(mesh, geom, sites, e) {
            let a = geom.node_area[v as usize];
            out.push(match s.across {
                Some(t) => {
                    NodeSpring::normal_tangent(v, geom.node_normal[v as usize], k * a, t * k * a)
                }
                None => NodeSpring::isotropic(v, k * a),
            });
        }
    }
    out
}

/// The Lamé field of the physics' material: homogeneous, or stiffer inside inclusions.
pub fn lame_field(mesh: &TetMesh, material: &LinearMaterial, physics: &Physics) -> LameField {
    let (lam, mu) = material.lame();
    let inclusions: Vec<(&Effect, &Material)> = physics
        .effects
        .iter()
        .filter_map(|e| match e.kind.role() {
            Role::Material(m) => Some((e, m)),
            Role::Load(_) | Role::Support(_) | Role::Uncarried => None,
        })
        .collect();
    if inclusions.is_empty() {
        return LameField::Uniform(lam, mu);
    }
    let per_tet = (0..mesh.num_tets())
        .map(|t| {
            let p = mesh.tet_points(t);
            let c = [0, 1, 2].map(|k| p.iter().map(|q| q[k]).sum::<f64>() / 4.0);
            let mut f = 1.0;
            for (e, m) in &inclusions {
                f *= (m.factor)(e, c);
            }
            (lam * f, mu * f)
        })
        .collect();
    LameField::PerTet(per_tet)
}

/// The unit loads of a load effect (mN, node-major), one per fitted amplitude, and the
/// amplitudes the effect's parameters give them: `gravity` one (magnitude), `pressure` one
/// (magnitude_kpa), `pack` three (the force's x, y, z in mN). Other kinds have none.
pub fn unit_loads(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    effect: &Effect,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError> {
    unit_loads_with(mesh, geom, effect, true)
}

/// [`unit_loads`], with gravity's dependent-surface reaction (`reaction`) or as its body force
/// alone (what supports carry under [`Carry::Supports`]; see [`ModelSolver::effect_unit_loads`]).
pub fn unit_loads_with(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    effect: &Effect,
    reaction: bool,
) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError> {
    match effect.kind.role() {
        Role::Load(l) => (l.unit_loads)(mesh, geom, effect, reaction),
        Role::Support(_) | Role::Material(_) | Role::Uncarried => Ok((Vec::new(), Vec::new())),
    }
}

/// Refuses a kind the augmented model does not carry yet (`nonlinear`), naming its field.
fn refuse_uncarried(physics: &Physics) -> Result<(), RegisterError> {
    if let Some(i) = physics.effects.iter().position(|e| !e.kind.is_carried()) {
        return Err(RegisterError::Parameter(format!(
            "effects[{i}].kind: the augmented model cannot carry `{}` yet (only the generator makes such data)",
            physics.effects[i].kind
        )));
    }
    Ok(())
}

/// Checks, before anything is assembled, that the augmented model carries `physics` on `mesh`:
/// every effect valid, no kind it does not carry (`nonlinear`), every load with boundary faces
/// to act on (a pack needs a face within 2 × `width_mm` of its center: the error names
/// `effects[i].parameters.center` and its distance to the surface), and the supports attached
/// to some node. One pass over the boundary: the server runs it on an upload before storing it,
/// and [`crate::register::libr::LibrBasis::build_with`] before building, so both refuse the
/// same physics with the same message.
pub fn check_fits(
    mesh: &TetMesh,
    sites: Sites<'_>,
    physics: &Physics,
) -> Result<(), RegisterError> {
    physics.validate()?;
    refuse_uncarried(physics)?;
    if physics.is_empty() {
        return Ok(());
    }
    let geom = BoundaryGeometry::new(mesh)?;
    for (i, e) in physics.effects.iter().enumerate() {
        let Some(load) = e.kind.load() else {
            continue;
        };
        match load.fits {
            Some(fits) => fits(mesh, &geom, e, i)?,
            None => {
                unit_loads(mesh, &geom, e)
                    .map_err(|err| RegisterError::Parameter(format!("effects[{i}]: {err}")))?;
            }
        }
    }
    if physics.has_support() && support_springs(mesh, &geom, sites, physics).is_empty() {
        return Err(RegisterError::Parameter(
            "effects: the physics' supports attach to no node (no posterior, falciform or fixation-region nodes)".into(),
        ));
    }
    Ok(())
}

/// The total load of the physics' load effects at their parameters (mN, node-major).
pub fn effect_load(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    physics: &Physics,
) -> Result<Vec<f64>, RegisterError> {
    effect_load_with(mesh, geom, physics, true)
}

/// [`effect_load`], with gravity's dependent-surface reaction or without ([`unit_loads_with`]).
fn effect_load_with(
    mesh: &TetMesh,
    geom: &BoundaryGeometry,
    physics: &Physics,
    reaction: bool,
) -> Result<Vec<f64>, RegisterError> {
    let mut f = vec![0.0; 3 * mesh.num_nodes()];
    for e in &physics.effects {
        let (cols, amps) = unit_loads_with(mesh, geom, e, reaction)?;
        for (c, a) in cols.iter().zip(&amps) {
            for (x, y) in f.iter_mut().zip(c) {
                *x += a * y;
            }
        }
    }
    Ok(f)
}

/// The augmented model's factorized elastic system: solves `K u = f` as the module doc says
/// (free-floating with inertia relief, or carried by the supports).
pub struct ModelSolver {
    system: StiffnessSystem,
    fact: FactorizedSystem,
    /// Inertia relief (every load is balanced by it).
    relief: RigidModes,
    /// Free-floating: no support, the rigid part of a solution is removed.
    free: bool,
    nodes: Vec<[f64; 3]>,
    /// Seconds spent assembling (stiffness and springs).
    pub assemble_s: f64,
    /// Seconds spent factorizing.
    pub factor_s: f64,
}

impl ModelSolver {
    /// Assembles and factorizes the model of `physics` on `mesh` with `material`. A kind whose
    /// model is not built yet (`nonlinear`) is an error naming it.
    pub fn new(
        mesh: &TetMesh,
        material: &LinearMaterial,
        sites: Sites<'_>,
        physics: &Physics,
    ) -> Result<Self, RegisterError> {
        physics.validate()?;
        refuse_uncarried(physics)?;
        let n = mesh.num_nodes();
        if sites.posterior.len() != n || sites.falciform.len() != n {
            return Err(RegisterError::Inconsistent(format!(
                "sites: {} posterior and {} falciform flags for {n} nodes",
                sites.posterior.len(),
                sites.falciform.len()
            )));
        }
        let t0 = std::time::Instant::now();
        let geom = BoundaryGeometry::new(mesh)?;
        let lame = lame_field(mesh, material, physics);
        let mut system = match &lame {
            LameField::Uniform(..) => StiffnessSystem::linear(mesh, material)?,
            LameField::PerTet(_) => StiffnessSystem::linear_field(mesh, &lame)?,
        };
        let nodes = mesh.nodes().to_vec();
        let mut assemble_s = crate::util::secs(t0);
        let factor_s;
        let t1 = std::time::Instant::now();
        let relief = RigidModes::new(&nodes, &lumped_volumes(mesh))?;
        let fact = if physics.has_support() {
            let s = support_springs(mesh, &geom, sites, physics);
            if s.is_empty() {
                return Err(RegisterError::Model(
                    "the physics' supports attach to no node (no posterior, falciform or fixation-region nodes)".into(),
                ));
            }
            system.add_springs(&s)?;
            assemble_s += crate::util::secs(t1);
            let t2 = std::time::Instant::now();
            let f = system.factorize(&Dirichlet::new(n))?;
            factor_s = crate::util::secs(t2);
            f
        } else {
            let bc = support_321(&nodes, &geom.nodes, relief.center())?;
            assemble_s += crate::util::secs(t1);
            let t2 = std::time::Instant::now();
            let f = system.factorize(&bc)?;
            factor_s = crate::util::secs(t2);
            f
        };
        Ok(Self {
            system,
            fact,
            free: !physics.has_support(),
            relief,
            nodes,
            assemble_s,
            factor_s,
        })
    }

    /// Whether the model is free-floating (no support).
    pub fn is_free(&self) -> bool {
        self.free
    }

    /// The unit loads of a load effect as this model carries them ([`unit_loads_with`]): on a
    /// supported model the supports carry the effect's net load, so gravity is its body force
    /// alone; on a free-floating one gravity rests on its dependent surface (the reaction) and
    /// inertia relief balances the rest.
    pub fn effect_unit_loads(
        &self,
        mesh: &TetMesh,
        geom: &BoundaryGeometry,
        effect: &Effect,
    ) -> Result<(Vec<Vec<f64>>, Vec<f64>), RegisterError> {
        unit_loads_with(mesh, geom, effect, self.free)
    }

    /// The response (mm, node-major, rigid part removed) to an effect's load from
    /// [`Self::effect_unit_loads`], as a column of the augmented basis: on a supported model the
    /// load is applied as it is and the supports carry its net force and moment
    /// ([`Carry::Supports`]); on a free-floating one it is [`Self::solve`] (inertia relief).
    pub fn solve_effect(&self, f: &[f64]) -> Vec<f64> {
        if self.free {
            return self.solve(f);
        }
        let u = self
            .fact
            .solve_many_homogeneous(MatRef::from_column_major_slice(f, f.len(), 1));
        let mut u: Vec<f64> = (0..f.len()).map(|r| u[(r, 0)]).collect();
        self.relief.remove_rigid(&self.nodes, &mut u);
        u
    }

    /// Removes the mass-weighted rigid part of a displacement (mm, node-major).
    pub fn remove_rigid(&self, u: &mut [f64]) {
        self.relief.remove_rigid(&self.nodes, u);
    }

    /// The assembled stiffness (with the support springs).
    pub fn system(&self) -> &StiffnessSystem {
        &self.system
    }

    /// The factorized system (the 3-2-1 support's dofs constrained on a free-floating model):
    /// the preconditioner of the nonlinear model ([`crate::register::nonlinear`]).
    pub fn factorized(&self) -> &FactorizedSystem {
        &self.fact
    }

    /// Prepares a load for the solve: its self-equilibrated part (inertia relief). Every load
    /// is balanced so, as LIBR's own model assumes: what pushes the organ is held by its
    /// surroundings. A support adds the stiffness that holds the organ where it acts; it does not
    /// carry a load's net force alone (a fixation patch or a ligament line carrying the net force
    /// of a surgeon's push would swing the linear model through metres).
    pub fn prepare_load(&self, f: &mut [f64]) {
        self.relief.equilibrate(&self.nodes, f);
    }

    /// Solves for the columns of `f` (3n × m, already prepared by [`Self::prepare_load`]) and
    /// removes the rigid part of each when free-floating.
    pub fn solve_prepared(&self, f: MatRef<'_, f64>) -> Mat<f64> {
        let mut u = self.fact.solve_many_homogeneous(f);
        if self.free {
            let m = &self.relief;
            let mut col = vec![0.0; u.nrows()];
            for j in 0..u.ncols() {
                for (r, x) in col.iter_mut().enumerate() {
                    *x = u[(r, j)];
                }
                m.remove_rigid(&self.nodes, &mut col);
                for (r, &x) in col.iter().enumerate() {
                    u[(r, j)] = x;
                }
            }
        }
        u
    }

    /// The displacement (mm, node-major) under one load (mN, node-major).
    pub fn solve(&self, f: &[f64]) -> Vec<f64> {
        let mut f = f.to_vec();
        self.prepare_load(&mut f);
        let fm = MatRef::from_column_major_slice(&f, f.len(), 1);
        let u = self.solve_prepared(fm);
        (0..f.len()).map(|r| u[(r, 0)]).collect()
    }

    /// The displacement (mm, node-major, its rigid part kept) of a supported organ under
    /// `base` balanced by inertia relief plus `carried` applied as it is: the supports' springs
    /// carry `carried`'s net force and moment ([`Carry::Supports`]). A free-floating model
    /// (no support) cannot carry a net load: an error.
    pub fn solve_carried(&self, base: &[f64], carried: &[f64]) -> Result<Vec<f64>, RegisterError> {
        if self.free {
            return Err(RegisterError::Parameter(
                "physics: a load carried by supports needs a support (bed-support, fixation or ligament)".into(),
            ));
        }
        let dofs = 3 * self.nodes.len();
        if base.len() != dofs || carried.len() != dofs {
            return Err(RegisterError::Inconsistent(format!(
                "loads of {} and {} entries for {dofs} dofs",
                base.len(),
                carried.len()
            )));
        }
        let mut f = base.to_vec();
        self.prepare_load(&mut f);
        for (x, y) in f.iter_mut().zip(carried) {
            *x += y;
        }
        let u = self
            .fact
            .solve_many_homogeneous(MatRef::from_column_major_slice(&f, dofs, 1));
        Ok((0..dofs).map(|r| u[(r, 0)]).collect())
    }
}

/// What carries the loads of [`forward_with`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Carry {
    /// Every load balanced by inertia relief, as LIBR's basis ([`forward`]).
    Relief,
    /// The physics' supports carry the effects' loads, as in the body: the effects' loads are
    /// applied unbalanced (gravity as its body force alone, without the dependent-surface
    /// reaction), the base load is balanced by inertia relief as LIBR's own loads are, and the
    /// mass-weighted rigid part of the result (the organ moving on its supports) is removed.
    /// Needs a support.
    Supports,
}

/// The augmented model's displacement under `base_load` plus the physics' own loads: what the
/// hidden-effect generator uses as the ground truth.
pub fn forward(
    mesh: &TetMesh,
    material: &LinearMaterial,
    sites: Sites<'_>,
    physics: &Physics,
    base_load: &[f64],
) -> Result<Vec<f64>, RegisterError> {
    let geom = BoundaryGeometry::new(mesh)?;
    let mut f = effect_load(mesh, &geom, physics)?;
    if base_load.len() != f.len() {
        return Err(RegisterError::Inconsistent(format!(
            "base load has {} entries for {} dofs",
            base_load.len(),
            f.len()
        )));
    }
    for (x, y) in f.iter_mut().zip(base_load) {
        *x += y;
    }
    Ok(ModelSolver::new(mesh, material, sites, physics)?.solve(&f))
}

/// [`forward_with`]`(…, Carry::Supports)` in its two parts, each with its rigid part removed:
/// the response to `base_load` (balanced by inertia relief) and the response to the effects'
/// loads (carried by the supports). Their sum is the whole; the hidden-effect generator scales
/// the second to cap the effects' peak displacement.
pub fn forward_supported_parts(
    mesh: &TetMesh,
    material: &LinearMaterial,
    sites: Sites<'_>,
    physics: &Physics,
    base_load: &[f64],
) -> Result<[Vec<f64>; 2], RegisterError> {
    let geom = BoundaryGeometry::new(mesh)?;
    let carried = effect_load_with(mesh, &geom, physics, false)?;
    let solver = ModelSolver::new(mesh, material, sites, physics)?;
    let zero = vec![0.0; carried.len()];
    let mut base = solver.solve_carried(base_load, &zero)?;
    let mut effects = solver.solve_carried(&zero, &carried)?;
    solver.relief.remove_rigid(&solver.nodes, &mut base);
    solver.relief.remove_rigid(&solver.nodes, &mut effects);
    Ok([base, effects])
}

/// [`forward`] with the effects' loads carried as `carry` says: [`Carry::Relief`] is
/// [`forward`] itself; [`Carry::Supports`] lets the physics' supports carry them
/// ([`ModelSolver::solve_carried`]) and removes the rigid part of the result.
pub fn forward_with(
    mesh: &TetMesh,
    material: &LinearMaterial,
    sites: Sites<'_>,
    physics: &Physics,
    base_load: &[f64],
    carry: Carry,
) -> Result<Vec<f64>, RegisterError> {
    if carry == Carry::Relief {
        return forward(mesh, material, sites, physics, base_load);
    }
    let geom = BoundaryGeometry::new(mesh)?;
    let carried = effect_load_with(mesh, &geom, physics, false)?;
    let solver = ModelSolver::new(mesh, material, sites, physics)?;
    let mut u = solver.solve_carried(base_load, &carried)?;
    solver.relief.remove_rigid(&solver.nodes, &mut u);
    Ok(u)
}
