//! The geometrically nonlinear model of a case: the Neo-Hookean solid of the FEM layer on the
//! case's mesh, material and supports, solved by Newton's method whose tangent systems are solved
//! by conjugate gradients preconditioned with the case's linear factorization ([`ModelSolver`]),
//! so that nothing is factored at surgery time.
//!
//! **Model.** The same body as LIBR's linear model: the same Lamé field and support springs, and
//! every load balanced by inertia relief (`f_b = f − M R G⁻¹ Rᵀ f`, [`ModelSolver::prepare_load`]),
//! as the linear basis's loads are. A free-floating organ is not pinned anywhere: its displacement
//! is sought among those with no (mass-weighted, linearized) rigid part, `u = P v` with
//! `P = I − R G⁻¹ RᵀM`, as the basis's columns are. The answer minimises the total potential
//! energy `Π(u) = W(u) − f_bᵀu` over that subspace, so its residual `Pᵀ(f_b − f_int(u))` vanishes:
//! what the elastic forces leave of the load is a rigid body force `M R c` (the relief, adjusted
//! to the deformed shape). The first try pinned a statically determinate 3-2-1 support instead,
//! as the linear factorization does; with loads that are balanced on the reference shape only,
//! the moment `Σ uᵢ × fᵢ` the deformation adds then fell on the three pinned nodes as point
//! reactions, which dented the organ there (on a 60 mm block under a 1 mm load: 14 % of the
//! displacement, at the pins); balancing the loads on the deformed shape instead made Newton's
//! method converge only linearly (0.85 per iteration). The projection has neither problem:
//! `Pᵀ K_T P` is the exact Jacobian, and `Pᵀ = ` the relief, `P K⁻¹ Pᵀ` the linear model's own
//! solve ([`ModelSolver::solve`]). The second-order rigid part a large deformation keeps (a
//! finite rotation is not orthogonal to the linearized modes) is left to the registration's rigid
//! correction, as LIBR leaves it. A supported organ (springs) is solved as it is.
//!
//! **Solver ([`NonlinearModel::equilibrium`]).** From a warm start (the linear answer, or the last
//! equilibrium), Newton iterations: the residual `r = Pᵀ(f_b − f_int(u))`, the tangent `K_T(u)`
//! assembled on the linear pattern, `Pᵀ K_T P δ = r` solved inexactly by preconditioned conjugate
//! gradients ([`pcg`]) with the linear model's solve as the preconditioner (to a relative
//! residual `eta`: an inexact Newton method), and a backtracking line search on `Π` that also
//! refuses inverted elements. Where `K_T` stops being positive definite (a buckling branch) the CG
//! stops at the last direction of positive curvature, and the line search decides. At small
//! strain `K_T = K` and one CG iteration solves the step exactly. Nothing is factored.
//!
//! Units: mm, kPa, mN. Frames: the image frame, node-major `3n` vectors.

mod map;
mod pcg;

pub use map::{COARSE_ABOVE, COARSE_NODES, NonlinearMap, coarse_edge};
pub use pcg::{Pcg, pcg};

use super::RegisterError;
use super::physics::Physics;
use super::physics::boundary::{BoundaryGeometry, Sites};
use super::physics::model::{ModelSolver, lame_field, support_springs};
use crate::fem::LinearMaterial;
use crate::fem::hyperelastic::HyperelasticModel;
use crate::mesh::TetMesh;
use faer::MatRef;
use std::time::Instant;

/// Parameters of a nonlinear equilibrium solve.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ForwardParams {
    /// Converged when `‖r‖ ≤ tolerance · ‖f‖`. Default 1e-3: a residual force of 1e-3 of the load
    /// moves the answer by about 1e-3 of the displacement (0.04 mm on a 40 mm dent), far below
    /// what the data resolve.
    pub tolerance: f64,
    /// Most Newton iterations. Default 8.
    pub max_newton: usize,
    /// Most CG iterations per Newton step. Default 25.
    pub max_cg: usize,
    /// CG stops at this relative residual of the Newton system (the forcing term). Default 0.1.
    pub eta: f64,
    /// Line-search halvings per Newton step. Default 12.
    pub max_halvings: usize,
    /// No Newton iteration starts past this instant (the solve then ends unconverged, with
    /// [`ForwardInfo::out_of_time`] set); None: no deadline.
    #[serde(skip)]
    pub deadline: Option<Instant>,
}

impl Default for ForwardParams {
    fn default() -> Self {
        Self {
            tolerance: 1e-3,
            max_newton: 8,
            max_cg: 25,
            eta: 0.1,
            max_halvings: 12,
            deadline: None,
        }
    }
}

impl ForwardParams {
    /// Checks the parameters; the message names the bad field.
    pub fn validate(&self) -> Result<(), RegisterError> {
        let bad = |field: &str, v: f64| {
            Err(RegisterError::Parameter(format!(
                "nonlinear {field} must be finite and > 0, got {v}"
            )))
        };
        if !(self.tolerance.is_finite() && self.tolerance > 0.0) {
            return bad("tolerance", self.tolerance);
        }
        if !(self.eta.is_finite() && self.eta > 0.0 && self.eta < 1.0) {
            return Err(RegisterError::Parameter(format!(
                "nonlinear eta must lie in (0, 1), got {}",
                self.eta
            )));
        }
        if self.max_newton == 0 || self.max_cg == 0 {
            return Err(RegisterError::Parameter(
                "nonlinear max_newton and max_cg must be at least 1".into(),
            ));
        }
        Ok(())
    }
}

/// What a nonlinear equilibrium solve did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ForwardInfo {
    /// Newton iterations.
    pub newton: usize,
    /// CG iterations over all Newton steps.
    pub cg: usize,
    /// Newton steps whose CG met negative curvature.
    pub negative_curvature: usize,
    /// Final relative residual `‖r‖ / ‖f‖`.
    pub relative_residual: f64,
    /// Whether the tolerance was met.
    pub converged: bool,
    /// The solve stopped at [`ForwardParams::deadline`] before meeting its tolerance.
    pub out_of_time: bool,
    /// Time assembling forces and tangents (s).
    pub assemble_s: f64,
    /// Time in the preconditioner's solves (s).
    pub precondition_s: f64,
    /// Total time (s).
    pub total_s: f64,
}

/// The nonlinear model of a case (see the module doc): the hyperelastic solid, and the case's
/// factorized linear model as the preconditioner.
pub struct NonlinearModel {
    solid: HyperelasticModel,
    linear: ModelSolver,
    nodes: Vec<[f64; 3]>,
    /// Seconds spent building (the linear factorization included).
    pub build_s: f64,
}

impl NonlinearModel {
    /// Builds the model of `physics` on `mesh` with `material` (the linear model's, factorized
    /// here: about as long as one basis build's factorization).
    pub fn new(
        mesh: &TetMesh,
        material: &LinearMaterial,
        sites: Sites<'_>,
        physics: &Physics,
    ) -> Result<Self, RegisterError> {
        let t0 = Instant::now();
        let linear = ModelSolver::new(mesh, material, sites, physics)?;
        let lame = lame_field(mesh, material, physics);
        let mut solid = HyperelasticModel::new(mesh, lame)?;
        if !linear.is_free() {
            let geom = BoundaryGeometry::new(mesh)?;
            solid.add_springs(&support_springs(mesh, &geom, sites, physics))?;
        }
        Ok(Self {
            solid,
            linear,
            nodes: mesh.nodes().to_vec(),
            build_s: crate::util::secs(t0),
        })
    }

    /// Dofs (3n).
    pub fn dofs(&self) -> usize {
        3 * self.nodes.len()
    }

    /// The linear model it is preconditioned with.
    pub fn linear(&self) -> &ModelSolver {
        &self.linear
    }

    /// The hyperelastic solid.
    pub fn solid(&self) -> &HyperelasticModel {
        &self.solid
    }

    /// The load (mN) behind a linear displacement `u` of this model: `K u` (the linear model's
    /// stiffness, supports included). For a column combination of the case's basis this is the
    /// combination of its balanced loads.
    pub fn load_of(&self, u: &[f64]) -> Vec<f64> {
        self.linear.system().apply(u)
    }

    /// The equilibrium under the load `f` (mN, node-major; balanced by inertia relief here) from
    /// the warm start `start` (mm; zero when None). Returns the displacement (with no
    /// linearized rigid part on a free-floating model) and what the solve did. A solve that does not
    /// reach the tolerance still returns its last iterate, flagged in
    /// [`ForwardInfo::converged`]; an error only for bad input.
    pub fn equilibrium(
        &self,
        f: &[f64],
        start: Option<&[f64]>,
        params: &ForwardParams,
    ) -> Result<(Vec<f64>, ForwardInfo), RegisterError> {
        params.validate()?;
        let t0 = Instant::now();
        let n = self.dofs();
        self.check_inputs(f, start)?;
        let mut fb = f.to_vec();
        self.linear.prepare_load(&mut fb);
        let mut u = start.map_or_else(|| vec![0.0; n], <[f64]>::to_vec);
        self.project(&mut u);
        let potential = |v: &[f64]| -> Option<f64> { Some(self.solid.energy(v)? - dot(&fb, v)) };
        let mut pi = match potential(&u) {
            Some(p) => p,
            None => {
                // The start inverts an element: begin from rest.
                u.iter_mut().for_each(|x| *x = 0.0);
                0.0
            }
        };
        let mut info = ForwardInfo::default();
        let ta = Instant::now();
        let mut r = self.residual(&fb, &u)?;
        info.assemble_s += crate::util::secs(ta);
        let fnorm = norm(&fb).max(1e-300);
        info.relative_residual = norm(&r) / fnorm;
        while info.relative_residual > params.tolerance && info.newton < params.max_newton {
            if params.deadline.is_some_and(|d| Instant::now() >= d) {
                info.out_of_time = true;
                break;
            }
            info.newton += 1;
            let ta = Instant::now();
            let values = self
                .solid
                .tangent_values(&u)
                .ok_or_else(|| RegisterError::Model("an element inverted in the tangent".into()))?;
            info.assemble_s += crate::util::secs(ta);
            let system = self.solid.linearized();
            let apply = |p: &[f64]| {
                let mut q = system.apply_values(&values, p);
                self.linear.prepare_load(&mut q);
                q
            };
            let mut precondition_s = 0.0;
            let precondition = |v: &[f64]| {
                let tp = Instant::now();
                let z = self.precondition(v);
                precondition_s += crate::util::secs(tp);
                z
            };
            let step = pcg(apply, precondition, &r, params.eta, params.max_cg);
            info.precondition_s += precondition_s;
            info.cg += step.iterations;
            info.negative_curvature += usize::from(step.negative_curvature);
            let ta = Instant::now();
            let accepted = self.line_search(&fb, (&u, pi, &r), &step.x, params.max_halvings)?;
            info.assemble_s += crate::util::secs(ta);
            let Some((trial, p, r_t)) = accepted else {
                break;
            };
            (u, pi, r) = (trial, p, r_t);
            info.relative_residual = norm(&r) / fnorm;
        }
        info.converged = info.relative_residual <= params.tolerance;
        info.total_s = crate::util::secs(t0);
        Ok((u, info))
    }

    /// Checks a solve's load and start against the model: lengths and finite values.
    fn check_inputs(&self, f: &[f64], start: Option<&[f64]>) -> Result<(), RegisterError> {
        let n = self.dofs();
        if f.len() != n || start.is_some_and(|s| s.len() != n) {
            return Err(RegisterError::Inconsistent(format!(
                "nonlinear solve: {} load and {} start values for {n} dofs",
                f.len(),
                start.map_or(n, <[f64]>::len)
            )));
        }
        if f.iter().chain(start.unwrap_or(&[])).any(|x| !x.is_finite()) {
            return Err(RegisterError::Inconsistent(
                "nonlinear solve: a load or start value is not finite".into(),
            ));
        }
        Ok(())
    }

    /// Backtracking along the Newton step `dx` from `(u, Π(u), r(u))`: the first point, halving
    /// at most `halvings` times, that meets Armijo's condition on `Π` or lowers the residual
    /// (near convergence the energy drowns in round-off); an inverted element is refused. Returns
    /// the point with its potential and residual, or None.
    #[allow(clippy::type_complexity)]
    fn line_search(
        &self,
        fb: &[f64],
        (u, pi, r): (&[f64], f64, &[f64]),
        dx: &[f64],
        halvings: usize,
    ) -> Result<Option<(Vec<f64>, f64, Vec<f64>)>, RegisterError> {
        let slope = -dot(r, dx);
        let rn = norm(r);
        let mut alpha = 1.0;
        for _ in 0..=halvings {
            let trial: Vec<f64> = u.iter().zip(dx).map(|(a, d)| a + alpha * d).collect();
            if let Some(w) = self.solid.energy(&trial) {
                let p = w - dot(fb, &trial);
                let r_t = self.residual(fb, &trial)?;
                if p <= pi + 1e-4 * alpha * slope || norm(&r_t) < rn {
                    return Ok(Some((trial, p, r_t)));
                }
            }
            alpha *= 0.5;
        }
        Ok(None)
    }

    /// `Pᵀ(f_b − f_int(u))`: the residual with its rigid part balanced by the relief.
    fn residual(&self, fb: &[f64], u: &[f64]) -> Result<Vec<f64>, RegisterError> {
        let fi = self
            .solid
            .internal_force(u)
            .ok_or_else(|| RegisterError::Model("an element inverted in the residual".into()))?;
        let mut r: Vec<f64> = fb.iter().zip(&fi).map(|(a, b)| a - b).collect();
        self.linear.prepare_load(&mut r);
        Ok(r)
    }

    /// `P u` on a free-floating model (the linearized rigid part removed); as it is otherwise.
    pub(crate) fn project(&self, u: &mut [f64]) {
        if self.linear.is_free() {
            self.linear.remove_rigid(u);
        }
    }

    /// The preconditioner: the linear model's solve `P K⁻¹ Pᵀ v` (free-floating), `K⁻¹ v`
    /// (supported).
    fn precondition(&self, v: &[f64]) -> Vec<f64> {
        if self.linear.is_free() {
            return self.linear.solve(v);
        }
        let z = self
            .linear
            .factorized()
            .solve_many_homogeneous(MatRef::from_column_major_slice(v, v.len(), 1));
        (0..v.len()).map(|r| z[(r, 0)]).collect()
    }
}

/// `aᵀb`, summed in order (the same bits on every run).
pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (body, tail) = a.split_at(a.len() - a.len() % 4);
    for (x, y) in body.chunks_exact(4).zip(b.chunks_exact(4)) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (x, y) in tail.iter().zip(&b[body.len()..]) {
        s += x * y;
    }
    s
}

/// `‖a‖₂`.
pub(crate) fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}
