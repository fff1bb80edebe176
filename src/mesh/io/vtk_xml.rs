//! VTK XML reader/writer (to be written).
use super::{IoError, MeshFile, WriteOptions};
use std::path::Path;
pub(crate) fn read(_bytes: &[u8], path: &Path) -> Result<MeshFile, IoError> { Err(IoError::Content { path: path.to_path_buf(), message: "not yet".into() }) }
pub(crate) fn write_vtu(_file: &MeshFile, _o: WriteOptions) -> Result<Vec<u8>, String> { Err("not yet".into()) }
pub(crate) fn write_vtp(_file: &MeshFile, _o: WriteOptions) -> Result<Vec<u8>, String> { Err("not yet".into()) }
