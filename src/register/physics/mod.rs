//! Augmented models: LIBR's linear homogeneous free-floating elasticity plus named physical
//! effects with parameters (`physics.json`, format 1).
//!
//! LIBR assumes a free body (inertia relief, see [`crate::register::libr`]) loaded by smooth
//! surface tractions. An *effect* adds one physical ingredient that model lacks; the kinds of
//! effect, their parameters and how each enters the model are one table, [`kinds`].
//!
//! Supports (`bed-support`, `fixation`, `ligament`) are springs per unit boundary area; a model
//! with any support is no longer free-floating: it keeps the rigid motion the springs allow.
//! Every load is balanced by inertia relief in either case (the organ's surroundings hold what
//! pushes it); the supports add stiffness where they act. Load effects (`gravity`, `pressure`, `pack`) become extra basis columns
//! whose amplitudes the fit estimates; the others change the stiffness the basis is built from.
//! The physics of each effect is in [`model`]; the file format in `docs/formats.md`.

pub mod boundary;
pub mod kinds;
pub mod model;

pub use kinds::EffectKind;

use super::RegisterError;
use crate::util::fnv1a_hex;
use std::collections::BTreeMap;

/// Version of `physics.json`.
pub const PHYSICS_FORMAT: u32 = 1;

/// One parameter of an effect kind: name, length (1 or 3), valid range (per component for
/// scalars, of the norm for vectors; `None` for positions), unit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamSpec {
    /// Name in `physics.json`.
    pub name: &'static str,
    /// 1 (scalar) or 3 (vector).
    pub len: usize,
    /// Valid range (scalar value, or vector norm); `None`: any finite value.
    pub range: Option<(f64, f64)>,
    /// Unit, for messages and reports.
    pub unit: &'static str,
}

impl ParamSpec {
    /// Checks one parameter's values: length, finiteness and range (of the value, or of the
    /// vector's length); `field` starts the message.
    pub fn check(&self, field: &str, v: &[f64]) -> Result<(), RegisterError> {
        if v.len() != self.len {
            return Err(RegisterError::Parameter(format!(
                "{field}: expected {} number(s), got {}",
                self.len,
                v.len()
            )));
        }
        if let Some(x) = v.iter().find(|x| !x.is_finite()) {
            return Err(RegisterError::Parameter(format!(
                "{field}: {x} is not finite"
            )));
        }
        let value = if self.len == 1 {
            v[0]
        } else {
            v.iter().map(|x| x * x).sum::<f64>().sqrt()
        };
        if let Some((lo, hi)) = self.range
            && !(lo..=hi).contains(&value)
        {
            let what = if self.len == 1 { "value" } else { "length" };
            return Err(RegisterError::Parameter(format!(
                "{field}: {what} {value} is outside [{lo}, {hi}] {}",
                self.unit
            )));
        }
        Ok(())
    }
}

impl std::fmt::Display for EffectKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Parameters as `physics.json` writes them: scalars as numbers, vectors as `[x, y, z]`.
pub fn parameters_json(
    params: &BTreeMap<String, Vec<f64>>,
) -> serde_json::Map<String, serde_json::Value> {
    params
        .iter()
        .map(|(k, v)| {
            let val = if v.len() == 1 {
                serde_json::json!(v[0])
            } else {
                serde_json::json!(v)
            };
            (k.clone(), val)
        })
        .collect()
}

/// One effect with its parameters (each 1 or 3 numbers, keyed by [`ParamSpec::name`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Effect {
    /// Kind.
    pub kind: EffectKind,
    /// Parameter values.
    pub parameters: BTreeMap<String, Vec<f64>>,
}

impl Effect {
    /// An effect from `(name, values)` pairs, validated.
    pub fn new(kind: EffectKind, values: &[(&str, &[f64])]) -> Result<Self, RegisterError> {
        let e = Self {
            kind,
            parameters: values
                .iter()
                .map(|(k, v)| (k.to_string(), v.to_vec()))
                .collect(),
        };
        e.validate("effect")?;
        Ok(e)
    }

    /// A scalar parameter. Panics if the effect was not validated or lacks it (a bug).
    pub fn scalar(&self, name: &str) -> f64 {
        self.parameters[name][0]
    }

    /// A vector parameter. Panics if the effect was not validated or lacks it (a bug).
    pub fn vector(&self, name: &str) -> [f64; 3] {
        let v = &self.parameters[name];
        [v[0], v[1], v[2]]
    }

    /// A direction parameter, normalised.
    pub fn direction(&self, name: &str) -> [f64; 3] {
        let v = self.vector(name);
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|x| x / l)
    }

    /// Checks names, lengths, finiteness and ranges; `at` prefixes the messages (e.g.
    /// `effects[2]`).
    pub fn validate(&self, at: &str) -> Result<(), RegisterError> {
        let specs = self.kind.parameters();
        for name in self.parameters.keys() {
            if !specs.iter().any(|s| s.name == name) {
                return Err(RegisterError::Parameter(format!(
                    "{at}.parameters.{name}: {} has no parameter {name:?} (it has: {})",
                    self.kind,
                    names(specs)
                )));
            }
        }
        for s in specs {
            let field = format!("{at}.parameters.{}", s.name);
            let Some(v) = self.parameters.get(s.name) else {
                return Err(RegisterError::Parameter(format!(
                    "{field}: missing ({} needs {})",
                    self.kind,
                    names(specs)
                )));
            };
            s.check(&field, v)?;
        }
        Ok(())
    }

    /// `kind(name=value, ...)`, for reports.
    pub fn describe(&self) -> String {
        let parts: Vec<String> = self
            .parameters
            .iter()
            .map(|(k, v)| {
                if v.len() == 1 {
                    format!("{k}={:.4}", v[0])
                } else {
                    format!("{k}=[{:.3}, {:.3}, {:.3}]", v[0], v[1], v[2])
                }
            })
            .collect();
        format!("{}({})", self.kind, parts.join(", "))
    }

    fn to_value(&self) -> serde_json::Value {
        serde_json::json!({"kind": self.kind.name(), "parameters": parameters_json(&self.parameters)})
    }

    /// Parses one effect object (`{"kind", "parameters", ...}`; other keys such as
    /// `uncertainty` and `evidence` are kept by the caller, not here).
    pub fn from_value(v: &serde_json::Value, at: &str) -> Result<Self, RegisterError> {
        let obj = v.as_object().ok_or_else(|| {
            RegisterError::Parameter(format!(
                "{at}: expected an object {{\"kind\", \"parameters\"}}"
            ))
        })?;
        let kind_name = obj.get("kind").and_then(|k| k.as_str()).ok_or_else(|| {
            RegisterError::Parameter(format!("{at}.kind: missing or not a string"))
        })?;
        let kind = EffectKind::from_name(kind_name).ok_or_else(|| {
            RegisterError::Parameter(format!(
                "{at}.kind: unknown kind {kind_name:?} (known: {})",
                EffectKind::known()
            ))
        })?;
        let mut parameters = BTreeMap::new();
        match obj.get("parameters") {
            None | Some(serde_json::Value::Null) => {}
            Some(serde_json::Value::Object(p)) => {
                for (name, val) in p {
                    let field = format!("{at}.parameters.{name}");
                    let nums: Vec<f64> = match val {
                        serde_json::Value::Number(n) => vec![n.as_f64().unwrap_or(f64::NAN)],
                        serde_json::Value::Array(a) => a
                            .iter()
                            .map(|x| {
                                x.as_f64().ok_or_else(|| {
                                    RegisterError::Parameter(format!(
                                        "{field}: {x} is not a number"
                                    ))
                                })
                            })
                            .collect::<Result<_, _>>()?,
                        other => {
                            return Err(RegisterError::Parameter(format!(
                                "{field}: expected a number or an array of numbers, got {other}"
                            )));
                        }
                    };
                    parameters.insert(name.clone(), nums);
                }
            }
            Some(other) => {
                return Err(RegisterError::Parameter(format!(
                    "{at}.parameters: expected an object, got {other}"
                )));
            }
        }
        let e = Self { kind, parameters };
        e.validate(at)?;
        Ok(e)
    }

    /// Parses the command line's `KIND[:key=value,...]` (vectors as `x/y/z`); parameters not
    /// given stay absent (a generator draws them). Not validated against ranges.
    pub fn parse_partial(
        text: &str,
    ) -> Result<(EffectKind, BTreeMap<String, Vec<f64>>), RegisterError> {
        let (kind_name, rest) = text.split_once(':').unwrap_or((text, ""));
        let kind = EffectKind::from_name(kind_name.trim()).ok_or_else(|| {
            RegisterError::Parameter(format!(
                "hidden effect {text:?}: unknown kind {kind_name:?} (known: {})",
                EffectKind::known()
            ))
        })?;
        let specs = kind.parameters();
        let mut out = BTreeMap::new();
        for item in rest.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (k, v) = item.split_once('=').ok_or_else(|| {
                RegisterError::Parameter(format!(
                    "hidden effect {text:?}: {item:?} is not key=value"
                ))
            })?;
            let spec = specs.iter().find(|s| s.name == k).ok_or_else(|| {
                RegisterError::Parameter(format!(
                    "hidden effect {text:?}: {kind} has no parameter {k:?} (it has: {})",
                    names(specs)
                ))
            })?;
            let nums: Vec<f64> = v
                .split('/')
                .map(|x| {
                    x.trim().parse::<f64>().map_err(|_| {
                        RegisterError::Parameter(format!(
                            "hidden effect {text:?}: {k}: {x:?} is not a number"
                        ))
                    })
                })
                .collect::<Result<_, _>>()?;
            if nums.len() != spec.len {
                return Err(RegisterError::Parameter(format!(
                    "hidden effect {text:?}: {k} needs {} number(s) (vectors as x/y/z), got {}",
                    spec.len,
                    nums.len()
                )));
            }
            out.insert(k.to_string(), nums);
        }
        Ok((kind, out))
    }
}

fn names(specs: &[ParamSpec]) -> String {
    if specs.is_empty() {
        "no parameters".into()
    } else {
        specs.iter().map(|s| s.name).collect::<Vec<_>>().join(", ")
    }
}

/// An augmented model's physics: the effects added to LIBR's model (empty: plain LIBR).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Physics {
    /// Effects, in the order they were added.
    pub effects: Vec<Effect>,
}

impl Physics {
    /// Plain LIBR.
    pub fn none() -> Self {
        Self::default()
    }

    /// Whether no effect is added.
    pub fn is_empty(&self) -> bool {
        self.effects.is_empty()
    }

    /// Whether any effect is a support (the model is then not free-floating).
    pub fn has_support(&self) -> bool {
        self.effects.iter().any(|e| e.kind.is_support())
    }

    /// The kinds carried, in order (`["gravity", "bed-support"]`).
    pub fn kinds(&self) -> Vec<&'static str> {
        self.effects.iter().map(|e| e.kind.name()).collect()
    }

    /// Checks every effect, and that a kind whose model is not built yet is absent; messages
    /// name `effects[i]`.
    pub fn validate(&self) -> Result<(), RegisterError> {
        for (i, e) in self.effects.iter().enumerate() {
            e.validate(&format!("effects[{i}]"))?;
        }
        Ok(())
    }

    /// The `physics.json` value (format 1). `extra[i]`, when given, is merged into effect `i`
    /// (e.g. `uncertainty`, `evidence`).
    pub fn to_value(&self, extra: &[serde_json::Value]) -> serde_json::Value {
        let effects: Vec<serde_json::Value> = self
            .effects
            .iter()
            .enumerate()
            .map(|(i, e)| {
                let mut v = e.to_value();
                if let (Some(serde_json::Value::Object(x)), Some(obj)) =
                    (extra.get(i), v.as_object_mut())
                {
                    for (k, val) in x {
                        obj.insert(k.clone(), val.clone());
                    }
                }
                v
            })
            .collect();
        serde_json::json!({"format": PHYSICS_FORMAT, "effects": effects})
    }

    /// Parses `physics.json` text; errors name the field (`effects[1].parameters.stiffness`).
    pub fn from_json(text: &str) -> Result<Self, RegisterError> {
        let v: serde_json::Value = serde_json::from_str(text)
            .map_err(|e| RegisterError::Parameter(format!("physics.json: not JSON: {e}")))?;
        let obj = v
            .as_object()
            .ok_or_else(|| RegisterError::Parameter("physics.json: expected an object".into()))?;
        // A misspelt key would otherwise be ignored silently.
        if let Some(k) = obj
            .keys()
            .find(|k| !matches!(k.as_str(), "format" | "effects"))
        {
            let k: String = k.chars().take(64).collect();
            return Err(RegisterError::Parameter(format!(
                "{k}: unknown key (physics.json holds \"format\" and \"effects\")"
            )));
        }
        match obj.get("format").and_then(|f| f.as_u64()) {
            Some(f) if f == PHYSICS_FORMAT as u64 => {}
            Some(f) => {
                return Err(RegisterError::Parameter(format!(
                    "format: physics.json format {f} is not supported (this build reads {PHYSICS_FORMAT})"
                )));
            }
            None => {
                return Err(RegisterError::Parameter(
                    "format: missing or not an integer".into(),
                ));
            }
        }
        let list = obj
            .get("effects")
            .and_then(|e| e.as_array())
            .ok_or_else(|| RegisterError::Parameter("effects: missing or not an array".into()))?;
        let effects = list
            .iter()
            .enumerate()
            .map(|(i, e)| Effect::from_value(e, &format!("effects[{i}]")))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self { effects })
    }

    /// Reads a `physics.json` file; errors name the file and the field.
    pub fn read(path: &std::path::Path) -> Result<Self, RegisterError> {
        let text = std::fs::read_to_string(path).map_err(|e| {
            RegisterError::Parameter(format!("{}: cannot read: {e}", path.display()))
        })?;
        Self::from_json(&text)
            .map_err(|e| RegisterError::Parameter(format!("{}: {e}", path.display())))
    }

    /// Hash (16 hex digits) of the physics (kinds and parameter bits, in order); empty for none.
    /// A physics whose supports carry its loads (a support and a load effect together) is marked
    /// so, so a basis built before loads were carried so is not mistaken for one now.
    pub fn hash(&self) -> String {
        if self.is_empty() {
            return String::new();
        }
        let mut bytes = Vec::new();
        if self.has_support() && self.effects.iter().any(|e| e.kind.is_load()) {
            bytes.extend_from_slice(b"carried\0");
        }
        for e in &self.effects {
            bytes.extend_from_slice(e.kind.name().as_bytes());
            for (k, v) in &e.parameters {
                bytes.extend_from_slice(k.as_bytes());
                for x in v {
                    bytes.extend_from_slice(&x.to_bits().to_le_bytes());
                }
            }
            bytes.push(0);
        }
        fnv1a_hex(&bytes)
    }

    /// One line: `none` or `gravity(...) + bed-support(...)`.
    pub fn describe(&self) -> String {
        if self.is_empty() {
            "none".into()
        } else {
            self.effects
                .iter()
                .map(Effect::describe)
                .collect::<Vec<_>>()
                .join(" + ")
        }
    }
}

#[cfg(test)]
mod tests;
