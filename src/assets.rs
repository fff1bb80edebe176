//! Data shipped inside the library and its binaries, so that the demo and the defaults of the
//! command line work in a fresh clone and from an installed binary, whatever the current
//! directory: the default liver surface. (The built-in SR-GCN models are embedded by the
//! SR-GCN's model files, `gcn::io`.)
//!
//! The default liver is the SOFA framework's `liver.vtk` (LGPL-2.1-or-later; notice and
//! attribution in `assets/livers/README.md` and `assets/livers/LICENSE-LGPL-2.1.txt`).

use crate::mesh::TriSurface;
use crate::mesh::io::{self, Format, IoError, Unit};
use std::path::Path;

/// The file name the default liver goes by (recorded as the source of generated datasets, as a
/// copy read from disk would be).
pub const DEFAULT_LIVER_NAME: &str = "sofa_liver.vtk";

/// `assets/livers/sofa_liver.vtk`: legacy VTK, binary, a liver surface at real scale (mm, LPS).
static DEFAULT_LIVER_VTK: &[u8] = include_bytes!("../assets/livers/sofa_liver.vtk");

/// What can go wrong with a built-in asset (only a damaged build: the files are checked by tests).
#[derive(Debug, thiserror::Error)]
pub enum AssetError {
    /// The embedded file does not parse.
    #[error("the built-in {name} does not parse: {source}")]
    Read {
        /// The asset's file name.
        name: &'static str,
        /// The reader's error.
        source: IoError,
    },
    /// The embedded file is not a closed surface.
    #[error("the built-in {name} is not a closed surface: {source}")]
    NotClosed {
        /// The asset's file name.
        name: &'static str,
        /// Why.
        source: crate::mesh::SurfaceError,
    },
}

/// The default liver as the file reader gives it (every component, mm).
pub fn default_liver_file() -> Result<io::MeshFile, AssetError> {
    io::read_bytes(
        DEFAULT_LIVER_VTK,
        Format::VtkLegacy,
        Path::new(DEFAULT_LIVER_NAME),
        Unit::Mm,
    )
    .map_err(|source| AssetError::Read {
        name: DEFAULT_LIVER_NAME,
        source,
    })
}

/// The default liver surface ready for meshing: its largest connected component (the file has
/// three tiny degenerate pieces besides the liver), closed, oriented outward (mm, LPS).
pub fn default_liver() -> Result<TriSurface, AssetError> {
    let file = default_liver_file()?;
    let not_closed = |source| AssetError::NotClosed {
        name: DEFAULT_LIVER_NAME,
        source,
    };
    TriSurface::from_file(&file)
        .and_then(|s| s.largest_closed_outward())
        .map_err(not_closed)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_liver_is_the_sofa_liver_at_real_scale() {
        // Facts from assets/livers/README.md: largest component 4,996 vertices and 9,988
        // triangles, closed, about 1,477 cm³, bounding box about 194 × 154 × 157 mm.
        let s = default_liver().unwrap();
        let st = s.stats();
        assert!(st.closed);
        assert_eq!((st.vertices, st.triangles), (4996, 9988));
        let cm3 = s.signed_volume() / 1000.0;
        assert!((cm3 - 1477.0).abs() < 5.0, "volume {cm3} cm³");
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in s.nodes() {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        for (a, want) in [194.0, 154.0, 157.0].into_iter().enumerate() {
            assert!(
                (hi[a] - lo[a] - want).abs() < 2.0,
                "extent {a}: {}",
                hi[a] - lo[a]
            );
        }
    }
}
