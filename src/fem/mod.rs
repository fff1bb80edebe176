//! Finite elements: P1 tetrahedra, linear elasticity, loads, constraints and sparse solvers.
//!
//! Units: lengths mm, stresses kPa, forces mN, energies mN·mm (µJ). Vectors over nodes are
//! node-major (`3·node + axis`). [`StiffnessSystem`] assembles once per mesh (in parallel over node
//! columns), [`StiffnessSystem::factorize`] eliminates Dirichlet dofs and factorizes the free block
//! with faer's supernodal sparse Cholesky once (geometric nested-dissection ordering, see
//! [`ordering`]; AMD selectable); [`FactorizedSystem`] then solves any number of
//! load cases. [`sag`] is the project's reference problem (gravity sag of a liver).

pub mod assembly;
pub mod basis_bench;
pub mod element;
mod error;
pub mod hyperelastic;
pub mod loads;
mod material;
pub mod ordering;
pub mod post;
pub mod sag;
mod solver;

pub use assembly::{BlockPattern, LameField};
pub use hyperelastic::ContactSpring;
pub use material::LinearMaterial;
pub use solver::{
    CholeskyFactor, Dirichlet, FactorInfo, FactorizedSystem, FemError, NewtonFailure, NodeSpring,
    Ordering, ReducedPattern, StiffnessSystem,
};
