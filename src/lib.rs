//! LIBR+: intraoperative liver registration.
//!
//! Layers, bottom to top (dependencies point one way; `tests/architecture.rs` keeps them):
//!
//! - [`util`], [`assets`], [`mesh`]: small helpers, the built-in liver, tet meshes, surfaces,
//!   file formats, the mesher;
//! - [`fem`]: linear and Neo-Hookean elasticity, loads, supports, sparse Cholesky;
//! - [`register`]: what runs in surgery below the network: correspondence, anatomical labels,
//!   wICP, LIBR; [`input`]: the preoperative model from files;
//! - [`dataset`]: the dataset format and its reader (shared by evaluation, server and clients);
//!   [`phantom`]: ground truth and the dataset generator (never imported by surgery-time code);
//! - [`gcn`]: spline convolution, SR-GCN, inference; [`v2s`]: the V2S-Net-style volumetric
//!   baseline (3-D U-Net on a grid), beside it;
//! - [`pipeline`]: one registration: method, deadlines, wICP → LIBR → LIBR+ → refit;
//! - [`eval`]: TRE, splits, reports, plots, training orchestration;
//! - the `librplus` command line and the `librplus-server` crate on top.
//!
//! Units: millimetres, kPa, mN; frame LPS.
#![warn(missing_docs)]
#![forbid(unsafe_code)]
// Index loops read like the formulas in numerical kernels; iterator rewrites would obscure them.
#![allow(clippy::needless_range_loop)]

pub mod assets;
pub mod dataset;
pub mod discover;
pub mod eval;
pub mod fem;
pub mod gcn;
pub mod input;
pub mod mesh;
pub mod phantom;
pub mod pipeline;
pub mod register;
pub mod util;
pub mod v2s;

/// The global allocator the binaries install (`#[global_allocator] static A: GlobalAllocator =
/// GlobalAllocator;`): graph convolution allocates and frees tens of MB per layer, which glibc's
/// allocator returns to the kernel each time (fresh zeroed pages, 2–3× slower training).
pub use mimalloc::MiMalloc as GlobalAllocator;
