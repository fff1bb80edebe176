//! Tetrahedral meshes: the mesh type, validation, boundary surface, topology, quality and files.
//!
//! [`TetMesh`] holds f64 node coordinates in millimetres and u32 tetrahedra with positive orientation
//! (signed volume `det[x1−x0, x2−x0, x3−x0] / 6 > 0`). [`TriSurface`] is a triangle surface (a boundary
//! extracted from a tet mesh, or a surface read from OBJ/STL/VTK) with areas, normals, enclosed volume,
//! closedness and genus. [`quality`] measures tetrahedra (dihedral angles, radius ratio). File formats
//! live in [`io`]; nothing else in this module touches the disk.

pub mod io;
pub mod locate;
pub mod procedural;
pub mod quality;
pub mod rigid;
pub mod spatial;
mod surface;
mod tet_mesh;
pub mod tetra;
pub(crate) mod union_find;
pub(crate) mod vec3;

pub use surface::{SurfaceError, SurfaceStats, TriSurface};
pub use tet_mesh::{
    BoundarySurface, DEGENERATE_REL, MeshError, NodeAdjacency, TetMesh, longest_edge,
};
