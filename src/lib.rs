//! LIBR+: intraoperative liver registration.
//!
//! Layers (dependencies point one way): [`mesh`] (tet meshes, surfaces, file formats) ←
//! [`fem`] (linear elasticity, loads, constraints, sparse Cholesky). Later issues add `phantom`,
//! `register`, `gcn`, `eval`, `discover`. Units: millimetres, kPa, mN; frame LPS.
#![forbid(unsafe_code)]
// Index loops read like the formulas in numerical kernels; iterator rewrites would obscure them.
#![allow(clippy::needless_range_loop)]

pub mod dataset;
pub mod eval;
pub mod fem;
pub mod gcn;
pub mod mesh;
pub mod phantom;
pub mod register;
pub mod util;
