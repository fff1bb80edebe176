//! Errors from building or solving an elastic system, and why a Newton solve failed.

/// Why one Newton solve of a load step failed (the load step is then halved).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NewtonFailure {
    /// An element is inverted (J ≤ 0) in the state the step starts from or its tangent.
    #[error("an element is inverted ({0})")]
    Inverted(&'static str),
    /// The tangent stiffness is not positive definite.
    #[error(
        "tangent stiffness not positive definite at node {node}, axis {axis}: a structural instability under this load, or too little support"
    )]
    Unstable {
        /// Node of the first bad pivot.
        node: usize,
        /// Axis of that pivot.
        axis: usize,
    },
    /// The tangent could not be factorised for another reason.
    #[error("tangent factorisation failed: {0}")]
    Factorisation(Box<FemError>),
    /// No step length lowered the energy or the residual.
    #[error("line search failed at iteration {iteration}")]
    LineSearch {
        /// Newton iteration.
        iteration: usize,
    },
    /// The residual stayed above the tolerance.
    #[error(
        "no convergence in {iterations} iterations (relative residual {relative_residual:.2e})"
    )]
    NoConvergence {
        /// Iterations run.
        iterations: usize,
        /// Final relative residual.
        relative_residual: f64,
    },
}

/// Errors from building or solving an elastic system; each says how to fix the input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FemError {
    /// A parameter is out of range.
    #[error("invalid parameter {field}: {message}")]
    InvalidParameter {
        /// The parameter's name.
        field: &'static str,
        /// What is wrong.
        message: String,
    },
    /// A tet has (numerically) zero volume, so its stiffness is undefined.
    #[error(
        "tet {tet} is degenerate (volume {volume:e} mm³, below 1e-10 × its longest edge cubed); fix or remove it before solving"
    )]
    DegenerateTet {
        /// Tet index.
        tet: usize,
        /// Its signed volume (mm³).
        volume: f64,
    },
    /// The constrained stiffness is not positive definite: rigid motion is not prevented.
    #[error(
        "stiffness matrix is not positive definite after constraints ({free} free dofs; first bad pivot at node {node}, axis {axis}): the constraints and springs do not prevent rigid motion of every part of the mesh"
    )]
    NotPositiveDefinite {
        /// Free dofs.
        free: usize,
        /// Node of the first non-positive pivot (the part that can still move rigidly).
        node: usize,
        /// Axis (0, 1, 2) of that pivot.
        axis: usize,
    },
    /// A face-connected part of the mesh has no constrained dof and no spring: it can move freely.
    #[error(
        "mesh part {part} ({tets} tets, containing node {node}) has no constrained dof and no spring, so it can move rigidly; fix some of its nodes or add springs"
    )]
    FloatingPart {
        /// Part index (face-connected component).
        part: usize,
        /// Number of tets in it.
        tets: usize,
        /// One of its nodes.
        node: usize,
    },
    /// A node belongs to no tetrahedron and is not constrained: its stiffness is zero.
    #[error(
        "node {node} belongs to no tetrahedron and is not constrained (remove unused nodes, e.g. TetMesh::remove_unused_nodes, or fix them)"
    )]
    UnusedNode {
        /// Node index.
        node: usize,
    },
    /// A nonlinear solve did not converge even with the smallest load step.
    #[error(
        "nonlinear solve did not converge: reached {load_fraction:.4} of the load after {iterations} Newton iterations ({reason})"
    )]
    NotConverged {
        /// Fraction of the load reached (last converged step).
        load_fraction: f64,
        /// Newton iterations spent.
        iterations: usize,
        /// Why the last step failed.
        reason: NewtonFailure,
    },
    /// Every dof is constrained: nothing to solve.
    #[error("every degree of freedom is constrained; nothing to solve")]
    NothingFree,
    /// The factorization failed for another reason (e.g. out of memory).
    #[error("sparse factorization failed: {0}")]
    Factorization(String),
}
