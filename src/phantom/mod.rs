//! Liver phantoms for ground truth: geometries and their variants (later: anatomical labels, load
//! patterns, ground-truth simulation, sparse measurements and the dataset writer).
//!
//! Only data generation uses this module; `register` and `gcn` never import it, since what runs in
//! surgery cannot see how the ground truth was made.

pub mod dataset;
pub mod measure;
pub mod patterns;
pub mod shape;
pub mod tissue;
pub mod truth;
pub mod vessels;
