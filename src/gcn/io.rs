//! The SR-GCN model directory (format 4): `model.json` (format, configuration, normalisation
//! rule, provenance) and `weights.safetensors`, the parameters in the
//! [safetensors](https://github.com/huggingface/safetensors) format (read and written by the
//! `safetensors` crate): every tensor F32, row-major, under its name (`mesh.encoder.weight`,
//! `mesh.convs.0.root`, `mesh.down.1.weight`, `mesh.up.0.bias`, `bip.decoder.bias`, …, as
//! [`named_tensors`] lists them) with its shape. Reading refuses a missing tensor, a wrong shape,
//! another dtype than F32 and non-finite values, naming the file and the tensor.
//!
//! `model.json`'s `format` says how the weights file is encoded: 4 is safetensors; 3 and 2 are
//! the earlier `weights.bin`, still read (a private reader of its layout: little-endian, magic
//! `SRGCNW01`, u32 tensor count, then per tensor u32 name length, UTF-8 name, u32 rank, u64 dims,
//! f32 values row-major). [`convert_model_dir`] rewrites a format-2/3 directory as format 4, bit
//! for bit. Format 2 (the multi-scale mesh branch, and LIBR's displacement as input) replaced
//! format 1; a format-1 model is refused with a request to retrain.

use super::GcnError;
use super::SplineConv;
use super::model::{Branch, SrGcn, SrGcnConfig};
use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use std::path::Path;

/// The model directory format this build writes (it reads 2 to 4): 4, whose weights file is
/// safetensors.
pub const MODEL_FORMAT: u32 = 4;

/// The weights file of a format-4 model directory.
pub const WEIGHTS_FILE: &str = "weights.safetensors";

/// The weights file of a format-2/3 model directory.
const LEGACY_WEIGHTS_FILE: &str = "weights.bin";

/// A named parameter: name, shape, values.
pub type NamedTensor = (String, Vec<usize>, Vec<f32>);

fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.clone()
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("f32 data")
}

fn conv_tensors(prefix: &str, c: &SplineConv, out: &mut Vec<NamedTensor>) {
    let w = c.weight.val();
    out.push((format!("{prefix}.weight"), w.dims().to_vec(), values(&w)));
    if let Some(r) = &c.root {
        let r = r.val();
        out.push((format!("{prefix}.root"), r.dims().to_vec(), values(&r)));
    }
    if let Some(b) = &c.bias {
        let b = b.val();
        out.push((format!("{prefix}.bias"), b.dims().to_vec(), values(&b)));
    }
}

fn branch_tensors(prefix: &str, b: &Branch, out: &mut Vec<NamedTensor>) {
    conv_tensors(&format!("{prefix}.encoder"), &b.encoder, out);
    for (i, c) in b.convs.iter().enumerate() {
        conv_tensors(&format!("{prefix}.convs.{i}"), c, out);
    }
    for (i, c) in b.down.iter().enumerate() {
        conv_tensors(&format!("{prefix}.down.{i}"), c, out);
    }
    for (i, c) in b.up.iter().enumerate() {
        conv_tensors(&format!("{prefix}.up.{i}"), c, out);
    }
    conv_tensors(&format!("{prefix}.decoder"), &b.decoder, out);
}

/// Every parameter of the network, in a fixed order.
pub fn named_tensors(net: &SrGcn) -> Vec<NamedTensor> {
    let mut out = Vec::new();
    branch_tensors("mesh", &net.mesh, &mut out);
    if let Some(b) = &net.bip {
        branch_tensors("bip", b, &mut out);
    }
    out
}

/// Serialises parameters as safetensors (format 4's `weights.safetensors`): F32, row-major.
pub fn encode(tensors: &[NamedTensor]) -> Result<Vec<u8>, GcnError> {
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|(_, _, v)| v.iter().flat_map(|x| x.to_le_bytes()).collect())
        .collect();
    let views = tensors
        .iter()
        .zip(&bytes)
        .map(|((name, dims, _), b)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, dims.clone(), b)
                .map(|v| (name.as_str(), v))
                .map_err(|e| GcnError::ModelFile(format!("{name}: {e}")))
        })
        .collect::<Result<Vec<_>, GcnError>>()?;
    safetensors::serialize(views, None).map_err(|e| GcnError::ModelFile(e.to_string()))
}

/// Parses parameters written by [`encode`] (a safetensors file): every tensor must be F32 and
/// finite. Tensors come in the file's order.
pub fn decode(bytes: &[u8]) -> Result<Vec<NamedTensor>, GcnError> {
    let st = safetensors::SafeTensors::deserialize(bytes)
        .map_err(|e| GcnError::ModelFile(format!("not a safetensors weights file: {e}")))?;
    st.iter()
        .map(|(name, view)| {
            if view.dtype() != safetensors::Dtype::F32 {
                return Err(GcnError::ModelFile(format!(
                    "{name}: dtype {:?} (SR-GCN weights are F32)",
                    view.dtype()
                )));
            }
            let vals = view
                .data()
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
                .collect::<Vec<f32>>();
            if vals.iter().any(|v| !v.is_finite()) {
                return Err(GcnError::ModelFile(format!("{name}: non-finite weights")));
            }
            Ok((name.to_string(), view.shape().to_vec(), vals))
        })
        .collect()
}

/// The magic of the format-2/3 weights file (`weights.bin`).
const LEGACY_MAGIC: &[u8; 8] = b"SRGCNW01";

/// Writes the format-2/3 weights file (tests of the legacy reader only).
#[cfg(test)]
fn encode_legacy(tensors: &[NamedTensor]) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(LEGACY_MAGIC);
    b.extend((tensors.len() as u32).to_le_bytes());
    for (name, dims, vals) in tensors {
        b.extend((name.len() as u32).to_le_bytes());
        b.extend(name.as_bytes());
        b.extend((dims.len() as u32).to_le_bytes());
        for &d in dims {
            b.extend((d as u64).to_le_bytes());
        }
        for v in vals {
            b.extend(v.to_le_bytes());
        }
    }
    b
}

/// Parses the format-2/3 weights file (`weights.bin`): little-endian, magic `SRGCNW01`, u32
/// tensor count, then per tensor u32 name length, UTF-8 name, u32 rank, u64 dims, f32 values.
fn decode_legacy(bytes: &[u8]) -> Result<Vec<NamedTensor>, GcnError> {
    let mut at = 0usize;
    let mut take = |n: usize| -> Result<&[u8], GcnError> {
        let s = bytes
            .get(at..at + n)
            .ok_or_else(|| GcnError::ModelFile(format!("weights file truncated at byte {at}")))?;
        at += n;
        Ok(s)
    };
    if take(8)? != LEGACY_MAGIC {
        return Err(GcnError::ModelFile(
            "not an SR-GCN weights file (bad magic)".into(),
        ));
    }
    let u32_ = |s: &[u8]| u32::from_le_bytes(s.try_into().expect("4 bytes")) as usize;
    let count = u32_(take(4)?);
    let mut out = Vec::with_capacity(count.min(1024));
    for _ in 0..count {
        let len = u32_(take(4)?);
        let name = String::from_utf8(take(len)?.to_vec())
            .map_err(|_| GcnError::ModelFile("bad tensor name".into()))?;
        let rank = u32_(take(4)?);
        if rank > 8 {
            return Err(GcnError::ModelFile(format!("{name}: rank {rank}")));
        }
        let mut dims = Vec::with_capacity(rank);
        for _ in 0..rank {
            dims.push(u64::from_le_bytes(take(8)?.try_into().expect("8 bytes")) as usize);
        }
        let n = dims
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .filter(|&n| n <= bytes.len() / 4)
            .ok_or_else(|| GcnError::ModelFile(format!("{name}: impossible shape {dims:?}")))?;
        let raw = take(4 * n)?;
        let vals = raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect::<Vec<f32>>();
        if vals.iter().any(|v| !v.is_finite()) {
            return Err(GcnError::ModelFile(format!("{name}: non-finite weights")));
        }
        out.push((name, dims, vals));
    }
    Ok(out)
}

/// The parameters of a weights file of model format `format` (4: safetensors; 2, 3: the
/// legacy `weights.bin`).
fn decode_weights(format: u64, bytes: &[u8]) -> Result<Vec<NamedTensor>, GcnError> {
    if format >= 4 {
        decode(bytes)
    } else {
        decode_legacy(bytes)
    }
}

/// Looks a parameter up by name and shape.
type Finder<'a> = dyn Fn(&str, &[usize]) -> Result<Tensor<1>, GcnError> + 'a;

/// Builds a network of `cfg` and overwrites its parameters with `tensors` (every parameter must
/// be present with its shape).
pub fn load_net(
    cfg: &SrGcnConfig,
    tensors: &[NamedTensor],
    device: &Device,
) -> Result<SrGcn, GcnError> {
    let mut net = cfg
        .init(device)
        .map_err(|e| GcnError::ModelFile(e.to_string()))?;
    let find = |name: &str, dims: &[usize]| -> Result<Tensor<1>, GcnError> {
        let (_, d, v) = tensors
            .iter()
            .find(|t| t.0 == name)
            .ok_or_else(|| GcnError::ModelFile(format!("weights lack {name}")))?;
        if d.as_slice() != dims {
            return Err(GcnError::ModelFile(format!(
                "{name}: shape {d:?}, the configuration needs {dims:?}"
            )));
        }
        Ok(Tensor::<1>::from_data(
            TensorData::new(v.clone(), [v.len()]),
            device,
        ))
    };
    fn set_conv(prefix: &str, c: &mut SplineConv, find: &Finder) -> Result<(), GcnError> {
        let [k, i, o] = c.weight.dims();
        c.weight =
            Param::from_tensor(find(&format!("{prefix}.weight"), &[k, i, o])?.reshape([k, i, o]));
        if let Some(r) = &c.root {
            let [i, o] = r.dims();
            c.root = Some(Param::from_tensor(
                find(&format!("{prefix}.root"), &[i, o])?.reshape([i, o]),
            ));
        }
        if let Some(b) = &c.bias {
            let [o] = b.dims();
            c.bias = Some(Param::from_tensor(find(&format!("{prefix}.bias"), &[o])?));
        }
        Ok(())
    }
    fn set_branch(prefix: &str, b: &mut Branch, find: &Finder) -> Result<(), GcnError> {
        set_conv(&format!("{prefix}.encoder"), &mut b.encoder, find)?;
        for (i, c) in b.convs.iter_mut().enumerate() {
            set_conv(&format!("{prefix}.convs.{i}"), c, find)?;
        }
        for (i, c) in b.down.iter_mut().enumerate() {
            set_conv(&format!("{prefix}.down.{i}"), c, find)?;
        }
        for (i, c) in b.up.iter_mut().enumerate() {
            set_conv(&format!("{prefix}.up.{i}"), c, find)?;
        }
        set_conv(&format!("{prefix}.decoder"), &mut b.decoder, find)
    }
    set_branch("mesh", &mut net.mesh, &find)?;
    if let Some(b) = &mut net.bip {
        set_branch("bip", b, &find)?;
    }
    Ok(net)
}

/// `model.json` of a model directory.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ModelFile {
    /// Format version ([`MODEL_FORMAT`]).
    pub format: u32,
    /// The network configuration.
    pub config: SrGcnConfig,
    /// Weights file, relative to the directory.
    pub weights: String,
    /// How the model was made: command, data, split, seed, commit, metrics (free-form JSON).
    pub provenance: serde_json::Value,
}

/// A trained model, loaded for inference.
#[derive(Debug)]
pub struct TrainedModel {
    /// Its configuration.
    pub config: SrGcnConfig,
    /// The network.
    pub net: SrGcn,
    /// Its provenance.
    pub provenance: serde_json::Value,
    /// When LIBR+ with this network (or its ensemble) abstains: the directory's `abstain.json`
    /// ([`super::abstain`]); None: never.
    pub abstain: Option<std::sync::Arc<super::abstain::AbstainRule>>,
}

impl TrainedModel {
    /// A network of `config` with freshly initialised weights (seeded) on the compute device
    /// ([`super::device::compute`]): what training starts from; for tests of the plumbing around
    /// a model.
    pub fn untrained(config: SrGcnConfig, seed: u64) -> Result<Self, GcnError> {
        let device = super::device::compute();
        device.seed(seed);
        let net = config
            .init(&device)
            .map_err(|e| GcnError::ModelFile(e.to_string()))?;
        Ok(Self {
            config,
            net,
            provenance: serde_json::json!({"untrained": true, "seed": seed}),
            abstain: None,
        })
    }
}

/// Writes a model directory (format [`MODEL_FORMAT`]: `model.json` and [`WEIGHTS_FILE`]).
pub fn save_model(
    dir: &Path,
    cfg: &SrGcnConfig,
    net: &SrGcn,
    provenance: serde_json::Value,
) -> Result<(), GcnError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", dir.display())))?;
    let wpath = dir.join(WEIGHTS_FILE);
    let bytes = encode(&named_tensors(net))
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", wpath.display())))?;
    std::fs::write(&wpath, bytes)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", wpath.display())))?;
    let file = ModelFile {
        format: MODEL_FORMAT,
        config: cfg.clone(),
        weights: WEIGHTS_FILE.into(),
        provenance,
    };
    let j = serde_json::to_string_pretty(&file).map_err(|e| GcnError::ModelFile(e.to_string()))?;
    std::fs::write(dir.join("model.json"), j)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", dir.display())))
}

/// Reads a model directory onto the compute device ([`super::device::compute`]: the CPU unless
/// `librplus --device` chose a GPU).
pub fn load_model_on_device(dir: &Path) -> Result<TrainedModel, GcnError> {
    load_model(dir, &super::device::compute())
}

/// `ensemble.json` of the model built into this crate (`assets/models/default/`).
const BUILTIN_ENSEMBLE: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/assets/models/default/ensemble.json"
));

/// `abstain.json` of the built-in model: when LIBR+ abstains ([`super::abstain`]).
const BUILTIN_ABSTAIN: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/assets/models/default/abstain.json"
));

/// The members of the built-in ensemble: name, `model.json`, weights (in `ensemble.json`'s order;
/// a unit test checks the two lists agree).
const BUILTIN_MEMBERS: [(&str, &str, &[u8]); 2] = [
    (
        "rich7v-pattern-v",
        include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/assets/models/default/rich7v-pattern-v/model.json"
        )),
        include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/assets/models/default/rich7v-pattern-v/weights.safetensors"
        )),
    ),
    (
        "rich13v-pattern-v",
        include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/assets/models/default/rich13v-pattern-v/model.json"
        )),
        include_bytes!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/assets/models/default/rich13v-pattern-v/weights.safetensors"
        )),
    ),
];

/// The default SR-GCN built into this crate (`assets/models/default/`, an ensemble directory,
/// since session 15 of two networks trained on the paper preset's patterns by the commands in
/// `ensemble.json` and its provenance; see `assets/models/default/README.md`), on the CPU: its
/// members, whose corrections LIBR+ averages. Each member's provenance has `"builtin": true` and its name
/// under `"member"`.
pub fn builtin_models() -> Result<Vec<TrainedModel>, GcnError> {
    let file: EnsembleFile = serde_json::from_str(BUILTIN_ENSEMBLE)
        .map_err(|e| GcnError::ModelFile(format!("<built-in>/ensemble.json: {e}")))?;
    let names: Vec<&str> = BUILTIN_MEMBERS.iter().map(|m| m.0).collect();
    if file.members != names {
        return Err(GcnError::ModelFile(format!(
            "<built-in>/ensemble.json lists {:?}, the crate embeds {names:?}",
            file.members
        )));
    }
    let abstain = std::sync::Arc::new(
        super::abstain::AbstainRule::parse(BUILTIN_ABSTAIN)
            .map_err(|e| GcnError::ModelFile(format!("<built-in>/{e}")))?,
    );
    BUILTIN_MEMBERS
        .iter()
        .map(|(name, json, weights)| {
            let mut m = model_from_parts(
                json,
                weights,
                &super::device::compute(),
                &Path::new("<built-in>").join(name).join("model.json"),
                &Path::new("<built-in>").join(name).join(WEIGHTS_FILE),
            )?;
            m.provenance["builtin"] = serde_json::json!(true);
            m.provenance["member"] = serde_json::json!(name);
            m.abstain = Some(abstain.clone());
            Ok(m)
        })
        .collect()
}

/// The ensemble file format this build writes and reads.
pub const ENSEMBLE_FORMAT: u32 = 1;

/// `ensemble.json` of an ensemble directory: the members, each a model directory (format 4, or
/// the 2 and 3 still read) inside it, whose corrections LIBR+ averages ([`crate::gcn::infer::LibrPlusCase`]).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct EnsembleFile {
    /// Format version ([`ENSEMBLE_FORMAT`]).
    pub format: u32,
    /// The members: names of model directories inside the ensemble directory.
    pub members: Vec<String>,
    /// How the ensemble was made (free-form JSON).
    #[serde(default)]
    pub provenance: serde_json::Value,
}

/// Writes an ensemble directory's `ensemble.json` over member directories already in `dir`
/// (each is read back, so a broken member is refused here rather than at preload).
pub fn save_ensemble(
    dir: &Path,
    members: &[String],
    provenance: serde_json::Value,
) -> Result<(), GcnError> {
    let file = EnsembleFile {
        format: ENSEMBLE_FORMAT,
        members: members.to_vec(),
        provenance,
    };
    check_members(dir, &file)?;
    for m in members {
        load_model_on_device(&dir.join(m))?;
    }
    let j = serde_json::to_string_pretty(&file).map_err(|e| GcnError::ModelFile(e.to_string()))?;
    let p = dir.join("ensemble.json");
    std::fs::write(&p, j).map_err(|e| GcnError::ModelFile(format!("{}: {e}", p.display())))
}

fn check_members(dir: &Path, file: &EnsembleFile) -> Result<(), GcnError> {
    let p = dir.join("ensemble.json");
    if file.format != ENSEMBLE_FORMAT {
        return Err(GcnError::ModelFile(format!(
            "{}: ensemble format {} (this build reads {ENSEMBLE_FORMAT})",
            p.display(),
            file.format
        )));
    }
    if file.members.is_empty() {
        return Err(GcnError::ModelFile(format!(
            "{}: members is empty",
            p.display()
        )));
    }
    for (k, m) in file.members.iter().enumerate() {
        if m.is_empty() || m == "." || m == ".." || m.contains(['/', '\\']) {
            return Err(GcnError::ModelFile(format!(
                "{}: members[{k}] {m:?} must be the name of a directory inside the ensemble directory",
                p.display()
            )));
        }
    }
    Ok(())
}

/// Makes the ensemble directory `out` from model directories (an ensemble directory among
/// `sources` contributes its members): each member's files are copied into `out/NAME`, NAME the
/// source directory's name (made unique with `-2`, `-3`, …), and `ensemble.json` written with
/// `provenance` plus each member's source. `out` must not exist or be empty. Returns the member
/// names.
pub fn make_ensemble(
    out: &Path,
    sources: &[std::path::PathBuf],
    provenance: serde_json::Value,
) -> Result<Vec<String>, GcnError> {
    if sources.is_empty() {
        return Err(GcnError::ModelFile("no model directories given".into()));
    }
    if out.exists() {
        let mut entries = std::fs::read_dir(out)
            .map_err(|e| GcnError::ModelFile(format!("{}: {e}", out.display())))?;
        if entries.next().is_some() {
            return Err(GcnError::ModelFile(format!(
                "{}: exists and is not empty (an ensemble is written into a new directory)",
                out.display()
            )));
        }
    }
    // Every member directory, with ensembles flattened; each is read before anything is written.
    let mut dirs: Vec<std::path::PathBuf> = Vec::new();
    for src in sources {
        match read_ensemble(src)? {
            Some(file) => dirs.extend(file.members.iter().map(|m| src.join(m))),
            None => dirs.push(src.clone()),
        }
    }
    for d in &dirs {
        load_model_on_device(d)?;
    }
    let mut names: Vec<String> = Vec::new();
    let mut sources_json = serde_json::Map::new();
    for d in &dirs {
        let canonical = std::fs::canonicalize(d).unwrap_or_else(|_| d.clone());
        let base = canonical
            .file_name()
            .and_then(|n| n.to_str())
            .filter(|n| !n.is_empty() && *n != "." && *n != "..")
            .unwrap_or("member")
            .to_string();
        let mut name = base.clone();
        let mut k = 2;
        while names.contains(&name) {
            name = format!("{base}-{k}");
            k += 1;
        }
        let dst = out.join(&name);
        std::fs::create_dir_all(&dst)
            .map_err(|e| GcnError::ModelFile(format!("{}: {e}", dst.display())))?;
        for entry in std::fs::read_dir(d)
            .map_err(|e| GcnError::ModelFile(format!("{}: {e}", d.display())))?
        {
            let entry = entry.map_err(|e| GcnError::ModelFile(format!("{}: {e}", d.display())))?;
            let path = entry.path();
            if path.is_file() {
                std::fs::copy(&path, dst.join(entry.file_name()))
                    .map_err(|e| GcnError::ModelFile(format!("{}: {e}", path.display())))?;
            }
        }
        sources_json.insert(name.clone(), d.display().to_string().into());
        names.push(name);
    }
    let mut provenance = provenance;
    if !provenance.is_object() {
        provenance = serde_json::json!({ "note": provenance });
    }
    provenance["sources"] = serde_json::Value::Object(sources_json);
    save_ensemble(out, &names, provenance)?;
    Ok(names)
}

/// `dir`'s `ensemble.json`, checked, or None when `dir` has none (a model directory).
fn read_ensemble(dir: &Path) -> Result<Option<EnsembleFile>, GcnError> {
    let p = dir.join("ensemble.json");
    if !p.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&p)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", p.display())))?;
    let file: EnsembleFile = serde_json::from_str(&text)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", p.display())))?;
    check_members(dir, &file)?;
    Ok(Some(file))
}

/// Reads a model directory, or an ensemble directory (`ensemble.json` and its member model
/// directories), onto the compute device ([`super::device::compute`]): the networks LIBR+ runs, one for a model directory.
/// The directory's `abstain.json`, if any, goes with every network ([`TrainedModel::abstain`]).
pub fn load_models_on_device(dir: &Path) -> Result<Vec<TrainedModel>, GcnError> {
    let abstain = super::abstain::AbstainRule::read(dir)?.map(std::sync::Arc::new);
    let mut models = match read_ensemble(dir)? {
        None => vec![load_model_on_device(dir)?],
        Some(file) => file
            .members
            .iter()
            .map(|m| {
                load_model_on_device(&dir.join(m))
                    .map_err(|e| GcnError::ModelFile(format!("ensemble member {m}: {e}")))
            })
            .collect::<Result<_, _>>()?,
    };
    for m in &mut models {
        m.abstain = abstain.clone();
    }
    Ok(models)
}

/// Reads a model directory.
pub fn load_model(dir: &Path, device: &Device) -> Result<TrainedModel, GcnError> {
    let mpath = dir.join("model.json");
    if !mpath.exists() && dir.join("ensemble.json").exists() {
        return Err(GcnError::ModelFile(format!(
            "{} is an ensemble directory (ensemble.json): this needs one model, give one of its members",
            dir.display()
        )));
    }
    let text = std::fs::read_to_string(&mpath)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    let head: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    let weights = head.get("weights").and_then(|w| w.as_str()).unwrap_or(
        if head.get("format").and_then(|f| f.as_u64()) < Some(MODEL_FORMAT as u64) {
            LEGACY_WEIGHTS_FILE
        } else {
            WEIGHTS_FILE
        },
    );
    if weights.contains(['/', '\\']) || weights == ".." || weights.is_empty() {
        return Err(GcnError::ModelFile(format!(
            "{}: weights {weights:?} must be a file name in the model directory",
            mpath.display()
        )));
    }
    let wpath = dir.join(weights);
    let bytes = std::fs::read(&wpath)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", wpath.display())))?;
    model_from_parts(&text, &bytes, device, &mpath, &wpath)
}

/// Rewrites the model directory `dir` of format 2 or 3 (`weights.bin`) as format 4: writes
/// [`WEIGHTS_FILE`] (safetensors) with the same tensors, names, shapes and f32 values, checks bit
/// for bit that it reads back as the old file and that the directory then loads with exactly the
/// old parameters, updates `model.json` (`format` 4, `weights`, and `converted_from` in the
/// provenance; a format-2 configuration gains the `residual: false`, `resolution: 0` it was read
/// with; nothing else changes) and deletes the old weights file. Returns the number of f32
/// values converted, or `None` when `dir` is already format 4. Ensemble directories are
/// converted member by member.
pub fn convert_model_dir(dir: &Path) -> Result<Option<usize>, GcnError> {
    let mpath = dir.join("model.json");
    let text = std::fs::read_to_string(&mpath)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    let head: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    let format = head.get("format").and_then(|f| f.as_u64());
    if format == Some(MODEL_FORMAT as u64) {
        return Ok(None);
    }
    // The directory as this build reads it: refuses format 1 and broken files.
    let device = Device::flex();
    let old = load_model(dir, &device)?;
    let format = format.expect("load_model accepted it");
    let old_name = head["weights"]
        .as_str()
        .unwrap_or(LEGACY_WEIGHTS_FILE)
        .to_string();
    let old_path = dir.join(&old_name);
    let bytes = std::fs::read(&old_path)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", old_path.display())))?;
    let tensors = decode_legacy(&bytes)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", old_path.display())))?;
    let new_path = dir.join(WEIGHTS_FILE);
    let new_bytes = encode(&tensors)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", new_path.display())))?;
    if !same_tensors(&decode(&new_bytes)?, &tensors) {
        return Err(GcnError::ModelFile(format!(
            "{}: does not read back as {}",
            new_path.display(),
            old_path.display()
        )));
    }
    let json = converted_head(head, format, &old_name)?;
    crate::util::write_atomic(&new_path, &new_bytes)?;
    crate::util::write_atomic(&mpath, json.as_bytes())?;
    let restore = |e: GcnError| {
        // Put the old model.json back: the old weights file is still there.
        let _ = crate::util::write_atomic(&mpath, text.as_bytes());
        let _ = std::fs::remove_file(&new_path);
        e
    };
    let new = load_model(dir, &device).map_err(restore)?;
    let config = |m: &TrainedModel| {
        serde_json::to_value(&m.config).map_err(|e| GcnError::ModelFile(e.to_string()))
    };
    if !same_tensors(&named_tensors(&new.net), &named_tensors(&old.net))
        || config(&new).map_err(restore)? != config(&old).map_err(restore)?
    {
        return Err(restore(GcnError::ModelFile(format!(
            "{}: the converted model differs from the old one",
            dir.display()
        ))));
    }
    if old_name != WEIGHTS_FILE {
        std::fs::remove_file(&old_path)
            .map_err(|e| GcnError::ModelFile(format!("{}: {e}", old_path.display())))?;
    }
    Ok(Some(tensors.iter().map(|t| t.2.len()).sum()))
}

/// Whether two sets of named tensors hold the same names, shapes and f32 values bit for bit.
fn same_tensors(a: &[NamedTensor], b: &[NamedTensor]) -> bool {
    a.len() == b.len()
        && a.iter().all(|(name, dims, vals)| {
            b.iter().any(|(n, d, v)| {
                n == name
                    && d == dims
                    && v.len() == vals.len()
                    && v.iter().zip(vals).all(|(x, y)| x.to_bits() == y.to_bits())
            })
        })
}

/// The `model.json` of a converted model directory (format `format`, weights `old_name`
/// before): format 4, the new weights file, `converted_from` in the provenance; a format-2
/// configuration gains the `residual: false`, `resolution: 0` it was read with.
fn converted_head(
    mut head: serde_json::Value,
    format: u64,
    old_name: &str,
) -> Result<String, GcnError> {
    if format == 2 {
        if let Some(c) = head["config"].as_object_mut() {
            c.insert("residual".into(), false.into());
            c.insert("resolution".into(), 0.into());
        }
    }
    if !head["provenance"].is_object() {
        head["provenance"] = serde_json::json!({ "note": head["provenance"].take() });
    }
    head["provenance"]["converted_from"] = format!("{old_name} (format {format})").into();
    /// `model.json` in the order [`save_model`] writes it.
    #[derive(serde::Serialize)]
    struct Head<'a> {
        format: u32,
        config: &'a serde_json::Value,
        weights: &'a str,
        provenance: &'a serde_json::Value,
    }
    serde_json::to_string_pretty(&Head {
        format: MODEL_FORMAT,
        config: &head["config"],
        weights: WEIGHTS_FILE,
        provenance: &head["provenance"],
    })
    .map_err(|e| GcnError::ModelFile(e.to_string()))
}

/// A model from the text of its `model.json` and the bytes of its weights (paths for messages).
fn model_from_parts(
    text: &str,
    bytes: &[u8],
    device: &Device,
    mpath: &Path,
    wpath: &Path,
) -> Result<TrainedModel, GcnError> {
    let head: serde_json::Value = serde_json::from_str(text)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    let format = head.get("format").and_then(|f| f.as_u64());
    let Some(format) = format.filter(|f| (2..=MODEL_FORMAT as u64).contains(f)) else {
        return Err(GcnError::ModelFile(format!(
            "{}: model format {} (this build reads 2 to {MODEL_FORMAT}; retrain with `librplus train`)",
            mpath.display(),
            format.map_or("missing".to_string(), |f| f.to_string()),
        )));
    };
    let mut head = head;
    if let Some(c) = head.get_mut("config").and_then(|c| c.as_object_mut()) {
        if format == 2 {
            // Format 2 predates residual blocks and coarse-resolution branches.
            c.insert("residual".into(), false.into());
            c.insert("resolution".into(), 0.into());
        }
        // Files without a fitted correction scale apply the whole correction.
        c.entry("correction_scale").or_insert(1.0.into());
        // Files without a first-level cluster count coarsen by `pool_ratio`.
        c.entry("clusters").or_insert(0.into());
        // Files from before the surface channels (session 15) do not read them.
        c.entry("surface_input").or_insert(false.into());
        // Files from before the load channels (session 17) do not read them.
        c.entry("load_input").or_insert(false.into());
        // Files from before the paper's ground-truth-neighbour diagnostic (session 17).
        c.entry("diagnostic_truth_neighbours")
            .or_insert(false.into());
    }
    let file: ModelFile = serde_json::from_value(head)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    file.config
        .validate()
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", mpath.display())))?;
    let tensors = decode_weights(format, bytes)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", wpath.display())))?;
    let net = load_net(&file.config, &tensors, device)
        .map_err(|e| GcnError::ModelFile(format!("{}: {e}", wpath.display())))?;
    Ok(TrainedModel {
        config: file.config,
        net,
        provenance: file.provenance,
        abstain: None,
    })
}

#[cfg(test)]
#[path = "io_tests.rs"]
mod tests;
