//! The on-disk cache of LIBR bases: one `.npz` per mesh and basis-relevant parameters, named by
//! their hashes; an unreadable, truncated or mismatched file is rebuilt and overwritten.

use super::*;
use crate::mesh::TetMesh;
use crate::mesh::io::npz::{NpyArray, NpyData, read_npz, write_npz};
use crate::register::physics::Physics;
use crate::register::physics::model::Sites;
use crate::util::fnv1a_hex;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Hash (16 hex digits) of a mesh's node coordinates (exact bits) and tets.
pub fn mesh_hash(mesh: &TetMesh) -> String {
    let mut bytes = Vec::with_capacity(24 * mesh.num_nodes() + 16 * mesh.num_tets() + 16);
    bytes.extend_from_slice(&(mesh.num_nodes() as u64).to_le_bytes());
    for p in mesh.nodes() {
        for c in p {
            bytes.extend_from_slice(&c.to_bits().to_le_bytes());
        }
    }
    bytes.extend_from_slice(&(mesh.num_tets() as u64).to_le_bytes());
    for t in mesh.tets() {
        for v in t {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    fnv1a_hex(&bytes)
}

/// Hash (16 hex digits) of a multi-resolution basis's parameters: what [`LibrParams::basis_hash`]
/// hashes, with the levels in place of the single control-point count and width.
pub fn levels_hash(params: &LibrParams, levels: &[(usize, LoadWidth)]) -> String {
    let key = serde_json::json!({
        "version": BASIS_VERSION,
        "levels": levels,
        "material": params.basis.material,
        "seed": params.basis.seed,
    });
    fnv1a_hex(key.to_string().as_bytes())
}

/// The parameters hash a basis of `levels` carries: [`LibrParams::basis_hash`] of the one level
/// (so a one-level basis is LIBR's own), else [`levels_hash`].
pub fn levels_key(params: &LibrParams, levels: &[(usize, LoadWidth)]) -> String {
    match levels {
        [(count, width)] => params.basis.with_level(*count, *width).hash(),
        _ => levels_hash(params, levels),
    }
}

impl LibrBasis {
    /// The cache file of a mesh and parameters in `cache_dir`.
    pub fn cache_path(mesh: &TetMesh, params: &LibrParams, cache_dir: &Path) -> PathBuf {
        Self::cache_path_with(mesh, params, &Physics::none(), cache_dir)
    }

    /// The cache file of an augmented model: the plain name with `_` and the physics hash
    /// before the extension (plain LIBR keeps its name).
    pub fn cache_path_with(
        mesh: &TetMesh,
        params: &LibrParams,
        physics: &Physics,
        cache_dir: &Path,
    ) -> PathBuf {
        let ph = physics.hash();
        let suffix = if ph.is_empty() {
            String::new()
        } else {
            format!("_{ph}")
        };
        cache_dir.join(format!(
            "libr_basis_{}_{}{suffix}.npz",
            mesh_hash(mesh),
            params.basis_hash()
        ))
    }

    /// Loads the basis from `cache_dir` if a valid file for this mesh and these parameters is
    /// there, otherwise builds it and writes the file (atomically: temporary file + rename).
    /// Returns the basis and whether it came from the cache. A corrupt, truncated or mismatched
    /// file is rebuilt and overwritten; failure to write the cache is an error.
    pub fn load_or_build(
        mesh: &TetMesh,
        params: &LibrParams,
        cache_dir: &Path,
    ) -> Result<(Self, bool), RegisterError> {
        let none = vec![false; mesh.num_nodes()];
        let sites = Sites {
            posterior: &none,
            falciform: &none,
        };
        Self::load_or_build_with(mesh, params, &Physics::none(), sites, cache_dir)
    }

    /// [`Self::load_or_build`] for an augmented model ([`Self::build_with`]), cached under
    /// [`Self::cache_path_with`].
    pub fn load_or_build_with(
        mesh: &TetMesh,
        params: &LibrParams,
        physics: &Physics,
        sites: Sites<'_>,
        cache_dir: &Path,
    ) -> Result<(Self, bool), RegisterError> {
        Self::load_or_build_levels(
            mesh,
            params,
            &[(params.basis.control_points, params.basis.load_width)],
            physics,
            sites,
            cache_dir,
        )
    }

    /// [`Self::load_or_build_with`] for a multi-resolution basis ([`Self::build_levels`]),
    /// cached under the hash of the parameters and the levels (one level: the plain name).
    pub fn load_or_build_levels(
        mesh: &TetMesh,
        params: &LibrParams,
        levels: &[(usize, LoadWidth)],
        physics: &Physics,
        sites: Sites<'_>,
        cache_dir: &Path,
    ) -> Result<(Self, bool), RegisterError> {
        params.validate()?;
        physics.validate()?;
        let key = levels_key(params, levels);
        let ph = physics.hash();
        let suffix = if ph.is_empty() {
            String::new()
        } else {
            format!("_{ph}")
        };
        let path = cache_dir.join(format!("libr_basis_{}_{key}{suffix}.npz", mesh_hash(mesh)));
        let total: usize = levels.iter().map(|l| l.0).sum();
        let t0 = Instant::now();
        if let Ok(bytes) = std::fs::read(&path)
            && let Ok(mut b) = Self::from_npz(&bytes)
            && b.mesh_hash == mesh_hash(mesh)
            && b.params_hash == key
            && b.nodes == mesh.num_nodes()
            && b.control_nodes.len() == total
            && b.physics_hash == ph
        {
            b.timings = BasisTimings {
                cache_read_s: crate::util::secs(t0),
                total_s: crate::util::secs(t0),
                ..Default::default()
            };
            return Ok((b, true));
        }
        let b = Self::build_levels(mesh, params, levels, physics, sites)?;
        crate::util::write_atomic(&path, &b.to_npz()?)?;
        Ok((b, false))
    }

    /// The basis as `.npz` bytes: `phi` (3n, 3K) f8, `energy` (3K, 3K) f8, `control_nodes` (K)
    /// i8, `load_scale` (3K) f8, `load_width_mm` (1) f8, `version` (1) i8, `mesh_hash` and
    /// `params_hash` (16 ASCII bytes each, u1); a multi-resolution basis adds `control_width_mm`
    /// (K) f8, an augmented model `effect_labels` (JSON, u1) and `physics_hash` (u1).
    pub fn to_npz(&self) -> Result<Vec<u8>, RegisterError> {
        let m = self.columns();
        let arrays = vec![
            NpyArray::new("phi", &[3 * self.nodes, m], NpyData::F64(self.phi.clone()))?,
            NpyArray::new("energy", &[m, m], NpyData::F64(self.energy.clone()))?,
            NpyArray::new(
                "control_nodes",
                &[self.control_nodes.len()],
                NpyData::I64(self.control_nodes.iter().map(|&v| v as i64).collect()),
            )?,
            NpyArray::new("load_scale", &[m], NpyData::F64(self.load_scale.clone()))?,
            NpyArray::new(
                "load_width_mm",
                &[1],
                NpyData::F64(vec![self.load_width_mm]),
            )?,
            NpyArray::new("version", &[1], NpyData::I64(vec![BASIS_VERSION as i64]))?,
            NpyArray::new(
                "mesh_hash",
                &[self.mesh_hash.len()],
                NpyData::U8(self.mesh_hash.as_bytes().to_vec()),
            )?,
            NpyArray::new(
                "params_hash",
                &[self.params_hash.len()],
                NpyData::U8(self.params_hash.as_bytes().to_vec()),
            )?,
        ];
        let mut arrays = arrays;
        if !self.control_width_mm.is_empty() {
            arrays.push(NpyArray::new(
                "control_width_mm",
                &[self.control_width_mm.len()],
                NpyData::F64(self.control_width_mm.clone()),
            )?);
        }
        if !self.effect_labels.is_empty() {
            let labels = serde_json::to_string(&self.effect_labels)
                .map_err(|e| RegisterError::BasisFile(format!("effect_labels: {e}")))?;
            arrays.push(NpyArray::new(
                "effect_labels",
                &[labels.len()],
                NpyData::U8(labels.into_bytes()),
            )?);
            arrays.push(NpyArray::new(
                "physics_hash",
                &[self.physics_hash.len()],
                NpyData::U8(self.physics_hash.as_bytes().to_vec()),
            )?);
        }
        Ok(write_npz(&arrays)?)
    }

    /// Reads what [`LibrBasis::to_npz`] wrote; checks names, dtypes, shapes and finiteness.
    pub fn from_npz(bytes: &[u8]) -> Result<Self, RegisterError> {
        let file = BasisArrays(read_npz(bytes)?);
        match &file.get("version")?.data {
            NpyData::I64(v) if v.as_slice() == [BASIS_VERSION as i64] => {}
            _ => {
                return Err(RegisterError::BasisFile(format!(
                    "basis file version is not {BASIS_VERSION}"
                )));
            }
        }
        let (ps, phi) = file.f64s("phi")?;
        let (es, energy) = file.f64s("energy")?;
        let (ls, load_scale) = file.f64s("load_scale")?;
        let (_, width) = file.f64s("load_width_mm")?;
        let control_nodes = file.control_nodes()?;
        // Optional (augmented models): the effect columns' labels as JSON, and the physics hash.
        let effect_labels: Vec<String> = if file.has("effect_labels") {
            serde_json::from_str(&file.text("effect_labels")?)
                .map_err(|e| RegisterError::BasisFile(format!("effect_labels: {e}")))?
        } else {
            Vec::new()
        };
        let control_width_mm = file.control_widths(control_nodes.len())?;
        let physics_hash = if file.has("physics_hash") {
            file.text("physics_hash")?
        } else {
            String::new()
        };
        let m = 3 * control_nodes.len() + effect_labels.len();
        if ps.len() != 2
            || ps[1] != m
            || ps[0] % 3 != 0
            || es != [m, m]
            || ls != [m]
            || width.len() != 1
        {
            return Err(RegisterError::BasisFile(format!(
                "basis arrays have inconsistent shapes (phi {ps:?}, energy {es:?}, load_scale {ls:?}, {} control nodes)",
                control_nodes.len()
            )));
        }
        let nodes = ps[0] / 3;
        if control_nodes.iter().any(|&c| c as usize >= nodes) {
            return Err(RegisterError::BasisFile(
                "a control node is out of range".into(),
            ));
        }
        if !phi
            .iter()
            .chain(&energy)
            .chain(&load_scale)
            .chain(&width)
            .all(|x| x.is_finite())
        {
            return Err(RegisterError::BasisFile(
                "basis file holds non-finite values".into(),
            ));
        }
        Ok(Self {
            control_nodes,
            nodes,
            phi,
            energy,
            load_scale,
            load_width_mm: width[0],
            control_width_mm,
            effect_labels,
            physics_hash,
            mesh_hash: file.text("mesh_hash")?,
            params_hash: file.text("params_hash")?,
            timings: BasisTimings::default(),
        })
    }
}

/// The arrays of a basis file, read by name.
struct BasisArrays(Vec<NpyArray>);

impl BasisArrays {
    fn has(&self, name: &str) -> bool {
        self.0.iter().any(|a| a.name == name)
    }

    fn get(&self, name: &str) -> Result<&NpyArray, RegisterError> {
        self.0
            .iter()
            .find(|a| a.name == name)
            .ok_or_else(|| RegisterError::BasisFile(format!("no array {name}")))
    }

    /// An f8 array's shape and values.
    fn f64s(&self, name: &str) -> Result<(Vec<usize>, Vec<f64>), RegisterError> {
        let a = self.get(name)?;
        match &a.data {
            NpyData::F64(v) => Ok((a.shape.clone(), v.clone())),
            _ => Err(RegisterError::BasisFile(format!(
                "basis array {name} is not f8"
            ))),
        }
    }

    /// A u1 array as UTF-8 text.
    fn text(&self, name: &str) -> Result<String, RegisterError> {
        match &self.get(name)?.data {
            NpyData::U8(v) => String::from_utf8(v.clone())
                .map_err(|e| RegisterError::BasisFile(format!("{name}: {e}"))),
            _ => Err(RegisterError::BasisFile(format!(
                "basis array {name} is not u1"
            ))),
        }
    }

    /// The control nodes (i8 array `control_nodes`, each a u32).
    fn control_nodes(&self) -> Result<Vec<u32>, RegisterError> {
        match &self.get("control_nodes")?.data {
            NpyData::I64(v) => v
                .iter()
                .map(|&x| {
                    u32::try_from(x).map_err(|_| {
                        RegisterError::BasisFile(format!("control node {x} out of range"))
                    })
                })
                .collect(),
            _ => Err(RegisterError::BasisFile(
                "basis array control_nodes is not i8".into(),
            )),
        }
    }

    /// Optional (multi-resolution bases): each control point's patch width, finite and > 0.
    fn control_widths(&self, controls: usize) -> Result<Vec<f64>, RegisterError> {
        if !self.has("control_width_mm") {
            return Ok(Vec::new());
        }
        let (shape, w) = self.f64s("control_width_mm")?;
        if shape != [controls] || w.iter().any(|x| !(x.is_finite() && *x > 0.0)) {
            return Err(RegisterError::BasisFile(format!(
                "control_width_mm has shape {shape:?} for {controls} control nodes, or a width that is not finite and > 0"
            )));
        }
        Ok(w)
    }
}
