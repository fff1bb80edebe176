//! The SR-GCN model directory (format 2): `model.json` (format, configuration, normalisation
//! rule, provenance) and `weights.bin`, the parameters as little-endian f32:
//! magic `SRGCNW01`, u32 tensor count, then per tensor u32 name length, name (UTF-8), u32 rank,
//! u64 dims, f32 values (row-major). Names are `mesh.encoder.weight`, `mesh.convs.0.root`,
//! `mesh.down.1.weight`, `mesh.up.0.bias`, `bip.decoder.bias`, … .
//!
//! Format 2 (the multi-scale mesh branch, and LIBR's displacement as input) replaced format 1;
//! a format-1 model is refused with a request to retrain.

use super::SplineConv;
use super::model::{Branch, SrGcn, SrGcnConfig};
use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use std::path::Path;

const MAGIC: &[u8; 8] = b"SRGCNW01";

/// The model directory format this build writes and reads.
pub const MODEL_FORMAT: u32 = 3;

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

/// Serialises parameters.
pub fn encode(tensors: &[NamedTensor]) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(MAGIC);
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

/// Parses parameters written by [`encode`].
pub fn decode(bytes: &[u8]) -> Result<Vec<NamedTensor>, String> {
    let mut at = 0usize;
    let mut take = |n: usize| -> Result<&[u8], String> {
        let s = bytes
            .get(at..at + n)
            .ok_or_else(|| format!("weights file truncated at byte {at}"))?;
        at += n;
        Ok(s)
    };
    if take(8)? != MAGIC {
        return Err("not an SR-GCN weights file (bad magic)".into());
    }
    let u32_ = |s: &[u8]| u32::from_le_bytes(s.try_into().expect("4 bytes")) as usize;
    let count = u32_(take(4)?);
    let mut out = Vec::with_capacity(count.min(1024));
    for _ in 0..count {
        let len = u32_(take(4)?);
        let name = String::from_utf8(take(len)?.to_vec()).map_err(|_| "bad tensor name")?;
        let rank = u32_(take(4)?);
        if rank > 8 {
            return Err(format!("{name}: rank {rank}"));
        }
        let mut dims = Vec::with_capacity(rank);
        for _ in 0..rank {
            dims.push(u64::from_le_bytes(take(8)?.try_into().expect("8 bytes")) as usize);
        }
        let n = dims
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .filter(|&n| n <= bytes.len() / 4)
            .ok_or_else(|| format!("{name}: impossible shape {dims:?}"))?;
        let raw = take(4 * n)?;
        let vals = raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect::<Vec<f32>>();
        if vals.iter().any(|v| !v.is_finite()) {
            return Err(format!("{name}: non-finite weights"));
        }
        out.push((name, dims, vals));
    }
    Ok(out)
}

/// Looks a parameter up by name and shape.
type Finder<'a> = dyn Fn(&str, &[usize]) -> Result<Tensor<1>, String> + 'a;

/// Builds a network of `cfg` and overwrites its parameters with `tensors` (every parameter must
/// be present with its shape).
pub fn load_net(
    cfg: &SrGcnConfig,
    tensors: &[NamedTensor],
    device: &Device,
) -> Result<SrGcn, String> {
    let mut net = cfg.init(device).map_err(|e| e.to_string())?;
    let find = |name: &str, dims: &[usize]| -> Result<Tensor<1>, String> {
        let (_, d, v) = tensors
            .iter()
            .find(|t| t.0 == name)
            .ok_or_else(|| format!("weights lack {name}"))?;
        if d.as_slice() != dims {
            return Err(format!(
                "{name}: shape {d:?}, the configuration needs {dims:?}"
            ));
        }
        Ok(Tensor::<1>::from_data(
            TensorData::new(v.clone(), [v.len()]),
            device,
        ))
    };
    fn set_conv(prefix: &str, c: &mut SplineConv, find: &Finder) -> Result<(), String> {
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
    fn set_branch(prefix: &str, b: &mut Branch, find: &Finder) -> Result<(), String> {
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
}

impl TrainedModel {
    /// A network of `config` with freshly initialised weights (seeded) on the compute device
    /// ([`super::device::compute`]): what training starts from; for tests of the plumbing around
    /// a model.
    pub fn untrained(config: SrGcnConfig, seed: u64) -> Result<Self, String> {
        let device = super::device::compute();
        device.seed(seed);
        let net = config.init(&device).map_err(|e| e.to_string())?;
        Ok(Self {
            config,
            net,
            provenance: serde_json::json!({"untrained": true, "seed": seed}),
        })
    }
}

/// Writes a model directory.
pub fn save_model(
    dir: &Path,
    cfg: &SrGcnConfig,
    net: &SrGcn,
    provenance: serde_json::Value,
) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let bytes = encode(&named_tensors(net));
    let wpath = dir.join("weights.bin");
    std::fs::write(&wpath, bytes).map_err(|e| format!("{}: {e}", wpath.display()))?;
    let file = ModelFile {
        format: MODEL_FORMAT,
        config: cfg.clone(),
        weights: "weights.bin".into(),
        provenance,
    };
    let j = serde_json::to_string_pretty(&file).map_err(|e| e.to_string())?;
    std::fs::write(dir.join("model.json"), j).map_err(|e| format!("{}: {e}", dir.display()))
}

/// Reads a model directory onto the compute device ([`super::device::compute`]: the CPU unless
/// `librplus --device` chose a GPU).
pub fn load_model_on_device(dir: &Path) -> Result<TrainedModel, String> {
    load_model(dir, &super::device::compute())
}

/// `ensemble.json` of the model built into this crate (`assets/models/default/`).
const BUILTIN_ENSEMBLE: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/assets/models/default/ensemble.json"
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
            "/assets/models/default/rich7v-pattern-v/weights.bin"
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
            "/assets/models/default/rich13v-pattern-v/weights.bin"
        )),
    ),
];

/// The default SR-GCN built into this crate (`assets/models/default/`, an ensemble directory,
/// since session 15 of two networks trained on the paper preset's patterns by the commands in
/// `ensemble.json` and its provenance; see `assets/models/default/README.md`), on the CPU: its
/// members, whose corrections LIBR+ averages. Each member's provenance has `"builtin": true` and its name
/// under `"member"`.
pub fn builtin_models() -> Result<Vec<TrainedModel>, String> {
    let file: EnsembleFile = serde_json::from_str(BUILTIN_ENSEMBLE)
        .map_err(|e| format!("<built-in>/ensemble.json: {e}"))?;
    let names: Vec<&str> = BUILTIN_MEMBERS.iter().map(|m| m.0).collect();
    if file.members != names {
        return Err(format!(
            "<built-in>/ensemble.json lists {:?}, the crate embeds {names:?}",
            file.members
        ));
    }
    BUILTIN_MEMBERS
        .iter()
        .map(|(name, json, weights)| {
            let mut m = model_from_parts(
                json,
                weights,
                &super::device::compute(),
                &Path::new("<built-in>").join(name).join("model.json"),
                &Path::new("<built-in>").join(name).join("weights.bin"),
            )?;
            m.provenance["builtin"] = serde_json::json!(true);
            m.provenance["member"] = serde_json::json!(name);
            Ok(m)
        })
        .collect()
}

/// The ensemble file format this build writes and reads.
pub const ENSEMBLE_FORMAT: u32 = 1;

/// `ensemble.json` of an ensemble directory: the members, each a model directory (format 3)
/// inside it, whose corrections LIBR+ averages ([`crate::gcn::infer::LibrPlusCase`]).
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
) -> Result<(), String> {
    let file = EnsembleFile {
        format: ENSEMBLE_FORMAT,
        members: members.to_vec(),
        provenance,
    };
    check_members(dir, &file)?;
    for m in members {
        load_model_on_device(&dir.join(m))?;
    }
    let j = serde_json::to_string_pretty(&file).map_err(|e| e.to_string())?;
    let p = dir.join("ensemble.json");
    std::fs::write(&p, j).map_err(|e| format!("{}: {e}", p.display()))
}

fn check_members(dir: &Path, file: &EnsembleFile) -> Result<(), String> {
    let p = dir.join("ensemble.json");
    if file.format != ENSEMBLE_FORMAT {
        return Err(format!(
            "{}: ensemble format {} (this build reads {ENSEMBLE_FORMAT})",
            p.display(),
            file.format
        ));
    }
    if file.members.is_empty() {
        return Err(format!("{}: members is empty", p.display()));
    }
    for (k, m) in file.members.iter().enumerate() {
        if m.is_empty() || m == "." || m == ".." || m.contains(['/', '\\']) {
            return Err(format!(
                "{}: members[{k}] {m:?} must be the name of a directory inside the ensemble directory",
                p.display()
            ));
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
) -> Result<Vec<String>, String> {
    if sources.is_empty() {
        return Err("no model directories given".into());
    }
    if out.exists() {
        let mut entries = std::fs::read_dir(out).map_err(|e| format!("{}: {e}", out.display()))?;
        if entries.next().is_some() {
            return Err(format!(
                "{}: exists and is not empty (an ensemble is written into a new directory)",
                out.display()
            ));
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
        std::fs::create_dir_all(&dst).map_err(|e| format!("{}: {e}", dst.display()))?;
        for entry in std::fs::read_dir(d).map_err(|e| format!("{}: {e}", d.display()))? {
            let entry = entry.map_err(|e| format!("{}: {e}", d.display()))?;
            let path = entry.path();
            if path.is_file() {
                std::fs::copy(&path, dst.join(entry.file_name()))
                    .map_err(|e| format!("{}: {e}", path.display()))?;
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
fn read_ensemble(dir: &Path) -> Result<Option<EnsembleFile>, String> {
    let p = dir.join("ensemble.json");
    if !p.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&p).map_err(|e| format!("{}: {e}", p.display()))?;
    let file: EnsembleFile =
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", p.display()))?;
    check_members(dir, &file)?;
    Ok(Some(file))
}

/// Reads a model directory, or an ensemble directory (`ensemble.json` and its member model
/// directories), onto the compute device ([`super::device::compute`]): the networks LIBR+ runs, one for a model directory.
pub fn load_models_on_device(dir: &Path) -> Result<Vec<TrainedModel>, String> {
    let Some(file) = read_ensemble(dir)? else {
        return Ok(vec![load_model_on_device(dir)?]);
    };
    file.members
        .iter()
        .map(|m| {
            load_model_on_device(&dir.join(m)).map_err(|e| format!("ensemble member {m}: {e}"))
        })
        .collect()
}

/// Reads a model directory.
pub fn load_model(dir: &Path, device: &Device) -> Result<TrainedModel, String> {
    let mpath = dir.join("model.json");
    if !mpath.exists() && dir.join("ensemble.json").exists() {
        return Err(format!(
            "{} is an ensemble directory (ensemble.json): this needs one model, give one of its members",
            dir.display()
        ));
    }
    let text = std::fs::read_to_string(&mpath).map_err(|e| format!("{}: {e}", mpath.display()))?;
    let head: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| format!("{}: {e}", mpath.display()))?;
    let weights = head
        .get("weights")
        .and_then(|w| w.as_str())
        .unwrap_or("weights.bin");
    if weights.contains(['/', '\\']) || weights == ".." || weights.is_empty() {
        return Err(format!(
            "{}: weights {weights:?} must be a file name in the model directory",
            mpath.display()
        ));
    }
    let wpath = dir.join(weights);
    let bytes = std::fs::read(&wpath).map_err(|e| format!("{}: {e}", wpath.display()))?;
    model_from_parts(&text, &bytes, device, &mpath, &wpath)
}

/// A model from the text of its `model.json` and the bytes of its weights (paths for messages).
fn model_from_parts(
    text: &str,
    bytes: &[u8],
    device: &Device,
    mpath: &Path,
    wpath: &Path,
) -> Result<TrainedModel, String> {
    let head: serde_json::Value =
        serde_json::from_str(text).map_err(|e| format!("{}: {e}", mpath.display()))?;
    let format = head.get("format").and_then(|f| f.as_u64());
    if !matches!(format, Some(f) if f == 2 || f == MODEL_FORMAT as u64) {
        return Err(format!(
            "{}: model format {} (this build reads 2 and {MODEL_FORMAT}; retrain with `librplus train`)",
            mpath.display(),
            format.map_or("missing".to_string(), |f| f.to_string()),
        ));
    }
    let mut head = head;
    if let Some(c) = head.get_mut("config").and_then(|c| c.as_object_mut()) {
        if format == Some(2) {
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
    let file: ModelFile =
        serde_json::from_value(head).map_err(|e| format!("{}: {e}", mpath.display()))?;
    file.config
        .validate()
        .map_err(|e| format!("{}: {e}", mpath.display()))?;
    let tensors = decode(bytes).map_err(|e| format!("{}: {e}", wpath.display()))?;
    let net = load_net(&file.config, &tensors, device)
        .map_err(|e| format!("{}: {e}", wpath.display()))?;
    Ok(TrainedModel {
        config: file.config,
        net,
        provenance: file.provenance,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_2_files_load_as_plain_full_resolution_networks() {
        let cfg = SrGcnConfig::new()
            .with_width(4)
            .with_levels(1)
            .with_coarse_convs(1)
            .with_resolution(0)
            .with_residual(false);
        let m = TrainedModel::untrained(cfg.clone(), 3).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        save_model(tmp.path(), &cfg, &m.net, serde_json::json!({})).unwrap();
        // A format-3 file keeps its switches.
        let back = load_model_on_device(tmp.path()).unwrap();
        assert!(!back.config.residual && back.config.resolution == 0);
        // Rewrite it as format 2 did: no `residual`, no `resolution`.
        let p = tmp.path().join("model.json");
        let mut j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        j["format"] = 2.into();
        let c = j["config"].as_object_mut().unwrap();
        c.remove("residual");
        c.remove("resolution");
        c.remove("clusters");
        std::fs::write(&p, j.to_string()).unwrap();
        let old = load_model_on_device(tmp.path()).unwrap();
        assert!(!old.config.residual, "format 2 has no residual blocks");
        assert_eq!(old.config.resolution, 0, "format 2 runs on the full mesh");
        assert_eq!(
            old.config.clusters, 0,
            "no cluster count: coarsened by ratio"
        );
        assert_eq!(named_tensors(&old.net), named_tensors(&m.net));
        // The defaults of a new configuration are the format-3 network.
        let d = SrGcnConfig::new();
        assert!(d.residual && d.resolution == 1);
        // Format 1 is refused with a request to retrain.
        j["format"] = 1.into();
        std::fs::write(&p, j.to_string()).unwrap();
        let e = load_model_on_device(tmp.path()).unwrap_err();
        assert!(e.contains("retrain"), "{e}");
    }

    #[test]
    fn ensemble_directories_load_their_members_and_refuse_bad_lists() {
        let tmp = tempfile::tempdir().unwrap();
        let cfg = SrGcnConfig::new().with_width(4).with_levels(1);
        let a = TrainedModel::untrained(cfg.clone(), 1).unwrap();
        let b = TrainedModel::untrained(cfg.clone().with_correction_scale(0.5), 2).unwrap();
        for (name, m) in [("a", &a), ("b", &b)] {
            save_model(
                &tmp.path().join(name),
                &m.config,
                &m.net,
                serde_json::json!({}),
            )
            .unwrap();
        }
        // A plain model directory is one network.
        assert_eq!(
            load_models_on_device(&tmp.path().join("a")).unwrap().len(),
            1
        );
        let names = vec!["a".to_string(), "b".to_string()];
        save_ensemble(tmp.path(), &names, serde_json::json!({"what": "test"})).unwrap();
        let both = load_models_on_device(tmp.path()).unwrap();
        assert_eq!(both.len(), 2);
        assert_eq!(named_tensors(&both[0].net), named_tensors(&a.net));
        assert_eq!(named_tensors(&both[1].net), named_tensors(&b.net));
        assert_eq!(both[1].config.correction_scale, 0.5);
        // Bad lists are refused, naming the problem.
        let p = tmp.path().join("ensemble.json");
        for (members, format, want) in [
            (serde_json::json!([]), 1, "members is empty"),
            (serde_json::json!(["../a"]), 1, "members[0]"),
            (serde_json::json!(["a", ".."]), 1, "members[1]"),
            (serde_json::json!(["a", "c"]), 1, "ensemble member c"),
            (serde_json::json!(["a"]), 2, "ensemble format 2"),
        ] {
            let j = serde_json::json!({"format": format, "members": members});
            std::fs::write(&p, j.to_string()).unwrap();
            let e = load_models_on_device(tmp.path()).unwrap_err();
            assert!(e.contains(want), "{members}: {e}");
        }
        // What needs one model names an ensemble for what it is.
        save_ensemble(tmp.path(), &names, serde_json::json!({})).unwrap();
        let e = load_model_on_device(tmp.path()).unwrap_err();
        assert!(e.contains("ensemble directory"), "{e}");
        // An ensemble made from model directories and another ensemble: members flattened,
        // names made unique, sources recorded; the same networks come back.
        let out = tmp.path().join("made");
        let made = make_ensemble(
            &out,
            &[tmp.path().join("a"), tmp.path().to_path_buf()],
            serde_json::json!({"command": "test"}),
        )
        .unwrap();
        assert_eq!(made, ["a", "a-2", "b"]);
        let back = load_models_on_device(&out).unwrap();
        assert_eq!(named_tensors(&back[1].net), named_tensors(&a.net));
        assert_eq!(named_tensors(&back[2].net), named_tensors(&b.net));
        let j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("ensemble.json")).unwrap())
                .unwrap();
        assert_eq!(j["provenance"]["command"], "test");
        assert!(
            j["provenance"]["sources"]["b"]
                .as_str()
                .unwrap()
                .ends_with("b")
        );
        // Not over a directory with files in it, not from nothing, not from a broken member.
        let e = make_ensemble(&out, &[tmp.path().join("a")], serde_json::json!({})).unwrap_err();
        assert!(e.contains("not empty"), "{e}");
        let e = make_ensemble(&tmp.path().join("x"), &[], serde_json::json!({})).unwrap_err();
        assert!(e.contains("no model"), "{e}");
        let e = make_ensemble(
            &tmp.path().join("y"),
            &[tmp.path().join("missing")],
            serde_json::json!({}),
        )
        .unwrap_err();
        assert!(e.contains("missing"), "{e}");
        assert!(
            !tmp.path().join("y").exists(),
            "nothing written for a broken member"
        );
        // Writing one over a missing member is refused before the file is written.
        let e = save_ensemble(tmp.path(), &["a".into(), "c".into()], serde_json::json!({}))
            .unwrap_err();
        assert!(e.contains("model.json"), "{e}");
    }
}
