//! ParaView data collections (`.pvd`): a time series as a list of dataset files, each with its
//! time step. ParaView (`vtkPVDReader`) and VTK (`vtkXMLCollectionReader`) open it and play the
//! files in time order; file names are relative to the `.pvd`'s directory.
//!
//! Written: `<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">` with one
//! `<DataSet timestep=".." group="" part="0" file=".."/>` per entry, in the order given.

use super::{line_of, parse_xml, write::escape};
use crate::mesh::io::IoError;
use crate::mesh::io::common::line_err;
use std::path::Path;

/// One file of a collection.
#[derive(Debug, Clone, PartialEq)]
pub struct PvdEntry {
    /// Time of the dataset (the collection's unit; LIBR+ writes seconds).
    pub timestep: f64,
    /// File name, relative to the collection's directory (`/` separated).
    pub file: String,
}

/// The text of a `.pvd` collection of `entries`. Times are written with Rust's shortest
/// round-trip formatting, so they read back bit for bit; a non-finite time is written as 0.
pub fn pvd_collection(entries: &[PvdEntry]) -> String {
    let mut s = String::from(
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\" \
         byte_order=\"LittleEndian\">\n  <Collection>\n",
    );
    for e in entries {
        let t = if e.timestep.is_finite() {
            e.timestep
        } else {
            0.0
        };
        s.push_str(&format!(
            "    <DataSet timestep=\"{t:?}\" group=\"\" part=\"0\" file=\"{}\"/>\n",
            escape(&e.file)
        ));
    }
    s.push_str("  </Collection>\n</VTKFile>\n");
    s
}

/// Reads a `.pvd` collection's entries (in file order); `path` names the file in errors.
pub fn read_pvd(bytes: &[u8], path: &Path) -> Result<Vec<PvdEntry>, IoError> {
    let root = parse_xml(bytes, path)?;
    let vtk = root
        .child("VTKFile")
        .filter(|v| v.attr("type") == Some("Collection"))
        .ok_or_else(|| line_err(path, 1, "expected a <VTKFile type=\"Collection\"> root"))?;
    let coll = vtk.child("Collection").ok_or_else(|| {
        line_err(
            path,
            line_of(bytes, vtk.pos),
            "VTKFile has no <Collection> element",
        )
    })?;
    coll.children("DataSet")
        .map(|d| {
            let line = line_of(bytes, d.pos);
            let file = d
                .attr("file")
                .ok_or_else(|| line_err(path, line, "DataSet has no file attribute"))?;
            let t = d.attr("timestep").unwrap_or("0");
            let timestep = t.trim().parse::<f64>().map_err(|_| {
                line_err(
                    path,
                    line,
                    format!("DataSet timestep {t:?} is not a number"),
                )
            })?;
            Ok(PvdEntry {
                timestep,
                file: file.to_string(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_times_and_names_with_markup_characters() {
        let entries = vec![
            PvdEntry {
                timestep: 0.0,
                file: "a/update-0001.vtu".into(),
            },
            PvdEntry {
                timestep: 0.1 + 0.2,
                file: "a&b/<odd> \"name\".vtu".into(),
            },
            PvdEntry {
                timestep: 1e-300,
                file: "c.vtu".into(),
            },
        ];
        let text = pvd_collection(&entries);
        let back = read_pvd(text.as_bytes(), Path::new("t.pvd")).unwrap();
        assert_eq!(back, entries);
        assert!(
            text.contains("a&amp;b/&lt;odd&gt; &quot;name&quot;.vtu"),
            "{text}"
        );
    }

    #[test]
    fn errors_name_what_is_missing() {
        let p = Path::new("bad.pvd");
        let e = read_pvd(b"<VTKFile type=\"UnstructuredGrid\"/>", p).unwrap_err();
        assert!(e.to_string().contains("Collection"), "{e}");
        let e = read_pvd(
            b"<VTKFile type=\"Collection\"><Collection><DataSet timestep=\"x\" file=\"a.vtu\"/></Collection></VTKFile>",
            p,
        )
        .unwrap_err();
        assert!(e.to_string().contains("timestep \"x\""), "{e}");
        let e = read_pvd(
            b"<VTKFile type=\"Collection\"><Collection><DataSet timestep=\"1\"/></Collection></VTKFile>",
            p,
        )
        .unwrap_err();
        assert!(e.to_string().contains("no file attribute"), "{e}");
    }
}
