//! The V2S model directory (format 1): `model.json` (`"kind": "v2s"`, format, configuration,
//! the input encoding's constants, provenance) and `weights.safetensors` (every tensor F32,
//! row-major, under its name: `encoder.L.K.conv.weight`, `encoder.L.K.conv.bias`,
//! `encoder.L.K.norm.gamma`, `encoder.L.K.norm.beta`, `down.L.conv.weight`, `up.L.conv.weight`,
//! `decoder.L.K.conv.weight`, `head.weight`, … as [`named_tensors`] lists them; the
//! encoding of [`crate::gcn::io::encode`]). Reading refuses another kind (an SR-GCN directory),
//! another format, other input constants, a missing tensor, a wrong shape and non-finite
//! values, naming the file.

use super::model::{V2sConfig, V2sNet};
use super::{DISTANCE_CLAMP, DISTANCE_UNIT_MM, INPUTS, OUTPUT_UNIT_MM, V2sError};
use crate::gcn::io::{NamedTensor, decode, encode};
use burn::module::Param;
use burn::tensor::{Device, Tensor, TensorData};
use std::path::Path;

/// The V2S model directory format this build reads and writes.
pub const V2S_FORMAT: u32 = 1;

/// The weights file of a V2S model directory.
pub const WEIGHTS_FILE: &str = "weights.safetensors";

/// How the inputs and outputs are encoded (stored in `model.json`, checked on reading: a model
/// trained with other constants would read its inputs wrongly).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Encoding {
    /// Input channels.
    pub inputs: usize,
    /// Distances are divided by this (mm).
    pub distance_unit_mm: f64,
    /// ... and clamped to ± this.
    pub distance_clamp: f64,
    /// The output's unit (mm).
    pub output_unit_mm: f64,
}

impl Encoding {
    /// This build's encoding.
    pub fn current() -> Self {
        Self {
            inputs: INPUTS,
            distance_unit_mm: DISTANCE_UNIT_MM,
            distance_clamp: DISTANCE_CLAMP,
            output_unit_mm: OUTPUT_UNIT_MM,
        }
    }
}

/// `model.json` of a V2S model directory.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct V2sModelFile {
    /// Always `"v2s"`.
    pub kind: String,
    /// Format version ([`V2S_FORMAT`]).
    pub format: u32,
    /// The network and grid.
    pub config: V2sConfig,
    /// The input and output encoding.
    pub encoding: Encoding,
    /// Weights file, relative to the directory.
    pub weights: String,
    /// How the model was made: command, data, split, seed, commit, metrics (free-form JSON).
    pub provenance: serde_json::Value,
}

/// A trained V2S network.
#[derive(Debug)]
pub struct V2sModel {
    /// Its configuration.
    pub config: V2sConfig,
    /// The network.
    pub net: V2sNet,
    /// Its provenance.
    pub provenance: serde_json::Value,
}

impl V2sModel {
    /// A network of `config` with freshly initialised weights (seeded) on the compute device:
    /// what training starts from; for tests of the plumbing around a model.
    pub fn untrained(config: V2sConfig, seed: u64) -> Result<Self, V2sError> {
        let device = crate::gcn::device::compute();
        device.seed(seed);
        let net = config.init(&device)?;
        Ok(Self {
            config,
            net,
            provenance: serde_json::json!({"untrained": true, "seed": seed}),
        })
    }
}

fn values<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
    t.clone()
        .into_data()
        .convert::<f32>()
        .try_to_vec::<f32>()
        .expect("f32 data")
}

/// Every parameter of the network, in a fixed order.
pub fn named_tensors(net: &V2sNet) -> Vec<NamedTensor> {
    let mut out: Vec<NamedTensor> = Vec::new();
    macro_rules! push {
        ($name:expr, $layer:expr) => {{
            let w = $layer.weight.val();
            out.push((format!("{}.weight", $name), w.dims().to_vec(), values(&w)));
            if let Some(b) = &$layer.bias {
                let b = b.val();
                out.push((format!("{}.bias", $name), b.dims().to_vec(), values(&b)));
            }
        }};
    }
    // A block: its convolution, then its normalisation's scale and shift.
    macro_rules! block {
        ($name:expr, $b:expr) => {{
            let name = $name;
            push!(format!("{name}.conv"), $b.conv);
            if let Some(n) = &$b.norm {
                for (what, p) in [("gamma", &n.gamma), ("beta", &n.beta)] {
                    if let Some(p) = p {
                        let v = p.val();
                        out.push((format!("{name}.norm.{what}"), v.dims().to_vec(), values(&v)));
                    }
                }
            }
        }};
    }
    for (l, convs) in net.encoder.iter().enumerate() {
        for (k, c) in convs.iter().enumerate() {
            block!(format!("encoder.{l}.{k}"), c);
        }
    }
    for (l, c) in net.down.iter().enumerate() {
        block!(format!("down.{l}"), c);
    }
    for (l, c) in net.up.iter().enumerate() {
        block!(format!("up.{l}"), c);
    }
    for (l, convs) in net.decoder.iter().enumerate() {
        for (k, c) in convs.iter().enumerate() {
            block!(format!("decoder.{l}.{k}"), c);
        }
    }
    push!("head".to_string(), net.head);
    out
}

/// Builds a network of `cfg` and overwrites its parameters with `tensors` (every parameter must
/// be present with its shape; extra tensors are refused too).
pub fn load_net(
    cfg: &V2sConfig,
    tensors: &[NamedTensor],
    device: &Device,
) -> Result<V2sNet, V2sError> {
    let mut net = cfg.init(device)?;
    let expected = named_tensors(&net);
    if let Some(extra) = tensors
        .iter()
        .find(|t| !expected.iter().any(|e| e.0 == t.0))
    {
        return Err(V2sError::ModelFile(format!(
            "the weights have a tensor {} that this configuration does not",
            extra.0
        )));
    }
    let find = |name: &str, dims: &[usize]| -> Result<Vec<f32>, V2sError> {
        let (_, d, v) = tensors
            .iter()
            .find(|t| t.0 == name)
            .ok_or_else(|| V2sError::ModelFile(format!("weights lack {name}")))?;
        if d.as_slice() != dims {
            return Err(V2sError::ModelFile(format!(
                "{name}: shape {d:?}, the configuration needs {dims:?}"
            )));
        }
        Ok(v.clone())
    };
    macro_rules! set {
        ($name:expr, $layer:expr) => {{
            let name = $name;
            let dims: [usize; 5] = $layer.weight.dims();
            let v = find(&format!("{name}.weight"), &dims)?;
            $layer.weight =
                Param::from_tensor(Tensor::<5>::from_data(TensorData::new(v, dims), device));
            if let Some(b) = &$layer.bias {
                let dims: [usize; 1] = b.dims();
                let v = find(&format!("{name}.bias"), &dims)?;
                $layer.bias = Some(Param::from_tensor(Tensor::<1>::from_data(
                    TensorData::new(v, dims),
                    device,
                )));
            }
        }};
    }
    let vector = |name: String, dims: [usize; 1]| -> Result<Param<Tensor<1>>, V2sError> {
        let v = find(&name, &dims)?;
        Ok(Param::from_tensor(Tensor::<1>::from_data(
            TensorData::new(v, dims),
            device,
        )))
    };
    macro_rules! set_block {
        ($name:expr, $b:expr) => {{
            let name = $name;
            set!(format!("{name}.conv"), $b.conv);
            if let Some(n) = &mut $b.norm {
                if let Some(g) = &n.gamma {
                    n.gamma = Some(vector(format!("{name}.norm.gamma"), g.dims())?);
                }
                if let Some(b) = &n.beta {
                    n.beta = Some(vector(format!("{name}.norm.beta"), b.dims())?);
                }
            }
        }};
    }
    for (l, convs) in net.encoder.iter_mut().enumerate() {
        for (k, c) in convs.iter_mut().enumerate() {
            set_block!(format!("encoder.{l}.{k}"), c);
        }
    }
    for (l, c) in net.down.iter_mut().enumerate() {
        set_block!(format!("down.{l}"), c);
    }
    for (l, c) in net.up.iter_mut().enumerate() {
        set_block!(format!("up.{l}"), c);
    }
    for (l, convs) in net.decoder.iter_mut().enumerate() {
        for (k, c) in convs.iter_mut().enumerate() {
            set_block!(format!("decoder.{l}.{k}"), c);
        }
    }
    set!("head", net.head);
    Ok(net)
}

/// Writes a V2S model directory (format [`V2S_FORMAT`]).
pub fn save_model(
    dir: &Path,
    cfg: &V2sConfig,
    net: &V2sNet,
    provenance: serde_json::Value,
) -> Result<(), V2sError> {
    std::fs::create_dir_all(dir)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", dir.display())))?;
    let wpath = dir.join(WEIGHTS_FILE);
    let bytes = encode(&named_tensors(net))
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", wpath.display())))?;
    crate::util::write_atomic(&wpath, &bytes)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", wpath.display())))?;
    let file = V2sModelFile {
        kind: "v2s".into(),
        format: V2S_FORMAT,
        config: cfg.clone(),
        encoding: Encoding::current(),
        weights: WEIGHTS_FILE.into(),
        provenance,
    };
    let j = serde_json::to_string_pretty(&file).map_err(|e| V2sError::ModelFile(e.to_string()))?;
    crate::util::write_atomic(&dir.join("model.json"), j.as_bytes())
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", dir.display())))
}

/// Parses `model.json` text and weights bytes (`json_path` and `weights_path` name them in
/// errors).
pub fn model_from_parts(
    json: &str,
    weights: &[u8],
    device: &Device,
    json_path: &Path,
    weights_path: &Path,
) -> Result<V2sModel, V2sError> {
    let value: serde_json::Value = serde_json::from_str(json)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", json_path.display())))?;
    match value.get("kind").and_then(|k| k.as_str()) {
        Some("v2s") => {}
        Some(other) => {
            return Err(V2sError::ModelFile(format!(
                "{}: kind {other:?}, not a V2S model",
                json_path.display()
            )));
        }
        None => {
            return Err(V2sError::ModelFile(format!(
                "{}: no \"kind\": not a V2S model (an SR-GCN model directory?)",
                json_path.display()
            )));
        }
    }
    let file: V2sModelFile = serde_json::from_value(value)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", json_path.display())))?;
    if file.format != V2S_FORMAT {
        return Err(V2sError::ModelFile(format!(
            "{}: V2S model format {} (this build reads {V2S_FORMAT})",
            json_path.display(),
            file.format
        )));
    }
    if file.encoding != Encoding::current() {
        return Err(V2sError::ModelFile(format!(
            "{}: input encoding {:?}, this build encodes {:?}",
            json_path.display(),
            file.encoding,
            Encoding::current()
        )));
    }
    file.config
        .validate()
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", json_path.display())))?;
    let tensors = decode(weights)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", weights_path.display())))?;
    let net = load_net(&file.config, &tensors, device)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", weights_path.display())))?;
    Ok(V2sModel {
        config: file.config,
        net,
        provenance: file.provenance,
    })
}

/// Reads a V2S model directory onto `device`.
pub fn load_model(dir: &Path, device: &Device) -> Result<V2sModel, V2sError> {
    let jpath = dir.join("model.json");
    let json = std::fs::read_to_string(&jpath)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", jpath.display())))?;
    let value: serde_json::Value = serde_json::from_str(&json)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", jpath.display())))?;
    let wname = value
        .get("weights")
        .and_then(|w| w.as_str())
        .unwrap_or(WEIGHTS_FILE);
    if wname.contains('/') || wname.contains('\\') || wname.contains("..") {
        return Err(V2sError::ModelFile(format!(
            "{}: weights {wname:?} must name a file inside the directory",
            jpath.display()
        )));
    }
    let wpath = dir.join(wname);
    let weights = std::fs::read(&wpath)
        .map_err(|e| V2sError::ModelFile(format!("{}: {e}", wpath.display())))?;
    model_from_parts(&json, &weights, device, &jpath, &wpath)
}

/// `model.json` of the V2S model built into this crate (`assets/models/v2s/`).
const BUILTIN_JSON: &str = include_str!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/assets/models/v2s/model.json"
));

/// Its weights.
const BUILTIN_WEIGHTS: &[u8] = include_bytes!(concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/assets/models/v2s/weights.safetensors"
));

/// The V2S model built into this crate (`assets/models/v2s/`, trained by the command in its
/// provenance and README), on the compute device; its provenance has `"builtin": true`.
pub fn builtin_model() -> Result<V2sModel, V2sError> {
    let mut m = model_from_parts(
        BUILTIN_JSON,
        BUILTIN_WEIGHTS,
        &crate::gcn::device::compute(),
        Path::new("<built-in>/v2s/model.json"),
        Path::new("<built-in>/v2s/weights.safetensors"),
    )?;
    m.provenance["builtin"] = serde_json::json!(true);
    Ok(m)
}

/// Reads a V2S model directory onto the compute device ([`crate::gcn::device::compute`]).
pub fn load_model_on_device(dir: &Path) -> Result<V2sModel, V2sError> {
    load_model(dir, &crate::gcn::device::compute())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_model_loads_with_its_provenance() {
        let m = builtin_model().unwrap();
        assert_eq!(m.provenance["builtin"], true);
        assert_eq!(m.provenance["method"], "v2s");
        assert!(
            m.provenance["command"]
                .as_str()
                .unwrap()
                .contains("--method v2s")
        );
        // Trained: the head is not its zero initialisation.
        assert!(values(&m.net.head.weight.val()).iter().any(|x| *x != 0.0));
    }

    #[test]
    fn a_saved_model_reads_back_bit_for_bit_and_bad_files_are_refused_by_name() {
        let cfg = V2sConfig::new().with_grid(8).with_width(2).with_depth(2);
        let mut m = V2sModel::untrained(cfg.clone(), 3).unwrap();
        // A non-zero head, so the round trip is not of zeros only.
        let device = Device::flex();
        let dims = m.net.head.weight.dims();
        m.net.head.weight = Param::from_tensor(Tensor::<5>::random(
            dims,
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        ));
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("v2s");
        save_model(&dir, &cfg, &m.net, serde_json::json!({"seed": 3})).unwrap();
        let back = load_model(&dir, &device).unwrap();
        assert_eq!(back.config, cfg);
        assert_eq!(back.provenance["seed"], 3);
        let (a, b) = (named_tensors(&m.net), named_tensors(&back.net));
        assert_eq!(a, b);
        assert!(a.iter().any(|t| t.0 == "decoder.1.0.conv.weight"));
        assert!(a.iter().any(|t| t.0 == "up.0.conv.bias"));
        assert!(a.iter().any(|t| t.0 == "encoder.2.1.norm.gamma"));
        // An SR-GCN model.json, another format, another encoding: refused, naming the file.
        let json = std::fs::read_to_string(dir.join("model.json")).unwrap();
        let mut v: serde_json::Value = serde_json::from_str(&json).unwrap();
        for (field, value, says) in [
            ("kind", serde_json::Value::Null, "not a V2S model"),
            ("format", serde_json::json!(9), "format 9"),
            (
                "encoding",
                serde_json::json!({"inputs": 4, "distance_unit_mm": 5.0, "distance_clamp": 3.0, "output_unit_mm": 10.0}),
                "encoding",
            ),
        ] {
            let old = v[field].clone();
            if value.is_null() {
                v.as_object_mut().unwrap().remove(field);
            } else {
                v[field] = value;
            }
            std::fs::write(dir.join("model.json"), v.to_string()).unwrap();
            let e = load_model(&dir, &device).unwrap_err().to_string();
            assert!(e.contains(says) && e.contains("model.json"), "{field}: {e}");
            v[field] = old;
        }
        std::fs::write(dir.join("model.json"), v.to_string()).unwrap();
        load_model(&dir, &device).unwrap();
        // A network of another width: the shapes differ.
        let other = V2sConfig::new().with_grid(8).with_width(3).with_depth(2);
        let e = load_net(&other, &a, &device).unwrap_err().to_string();
        assert!(e.contains("shape"), "{e}");
        // A truncated weights file.
        let w = std::fs::read(dir.join(WEIGHTS_FILE)).unwrap();
        std::fs::write(dir.join(WEIGHTS_FILE), &w[..w.len() / 2]).unwrap();
        let e = load_model(&dir, &device).unwrap_err().to_string();
        assert!(e.contains(WEIGHTS_FILE), "{e}");
    }
}
