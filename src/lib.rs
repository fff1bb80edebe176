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
pub mod input;
pub mod mesh;
pub mod phantom;
pub mod register;
pub mod util;

/// The global allocator the binaries install (`#[global_allocator] static A: GlobalAllocator =
/// GlobalAllocator;`): graph convolution allocates and frees tens of MB per layer, which glibc's
/// allocator returns to the kernel each time (fresh zeroed pages, 2–3× slower training).
pub use mimalloc::MiMalloc as GlobalAllocator;
