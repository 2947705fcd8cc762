//! The TOML config of docs/theory.md §13, read as it is written. These raw structs only mirror the file
//! (unknown keys are rejected); [`crate::model::Model::from_config`] checks them once and turns
//! them into a validated model. Nothing downstream reads these structs again.
#![allow(non_snake_case)]

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::folder_of;

/// A matrix as the TOML writes it: a list of rows.
pub type RawMatrix = Vec<Vec<f64>>;

/// The whole config file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawConfig {
    /// Chain length `N`.
    pub subsystems: i64,
    /// Horizon `T` for `simulate` and `evaluate` (`estimate` takes it from its data).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<i64>,
    /// Default seed of the random draws.
    #[serde(default)]
    pub seed: u64,
    pub interconnection: RawInterconnection,
    pub model: RawModel,
    pub dropout: RawDropout,
    pub initial: RawInitial,
    #[serde(default)]
    pub input: Option<RawInput>,
    #[serde(default, rename = "override", skip_serializing_if = "Vec::is_empty")]
    pub overrides: Vec<RawOverride>,
}

/// `[interconnection]`: the sizes `n⁺`, `n⁻` of the signals passed right and left.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawInterconnection {
    pub plus: i64,
    pub minus: i64,
}

/// `[model]`: the matrices of (P1), (P2), (P5) and the noise covariances.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawModel {
    pub A: RawMatrix,
    pub B: RawMatrix,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub C: Option<RawMatrix>,
    pub D: RawMatrix,
    pub G: RawMatrix,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub H: Option<RawMatrix>,
    pub J: RawMatrix,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub R: Option<RawMatrix>,
    pub M: RawMatrix,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub Q: Option<RawMatrix>,
}

/// `[dropout]`: the arrival probability `p`, one value or one per subsystem.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawDropout {
    pub p: RawProbability,
}

/// `p = 0.8` or `p = [0.8, 0.9, …]`.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum RawProbability {
    All(f64),
    PerSubsystem(Vec<f64>),
}

/// By hand rather than `#[serde(untagged)]`, whose error for anything else ("data did not
/// match any variant …") does not say what was expected.
impl<'de> Deserialize<'de> for RawProbability {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = RawProbability;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a probability or a list of probabilities, one per subsystem")
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Self::Value, E> {
                Ok(RawProbability::All(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Self::Value, E> {
                Ok(RawProbability::All(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Self::Value, E> {
                Ok(RawProbability::All(v as f64))
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Self::Value, A::Error> {
                let mut ps = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 16));
                while let Some(p) = seq.next_element::<f64>()? {
                    ps.push(p);
                }
                Ok(RawProbability::PerSubsystem(ps))
            }
        }
        de.deserialize_any(Visitor)
    }
}

/// `[initial]`: `x(1,i) ~ N(mean, cov)`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawInitial {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean: Option<Vec<f64>>,
    pub cov: RawMatrix,
}

/// `[input]`: how `u(t,i)` is generated.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawInput {
    pub kind: InputKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub amplitude: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub period: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<String>,
}

/// The input generators of docs/theory.md §13.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InputKind {
    Zero,
    Constant,
    Sine,
    File,
}

/// One `[[override]]` table: parameters that apply on a rectangle of `(t, i)`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawOverride {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub subsystems: Option<[i64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<[i64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub A: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub B: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub C: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub D: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub G: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub H: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub J: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub R: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub M: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub Q: Option<RawMatrix>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub p: Option<f64>,
}

/// A config as read from its source: the parsed tables plus where it came from.
#[derive(Debug, Clone)]
pub struct ConfigSource {
    /// The name used in messages (the path as the user gave it).
    pub name: String,
    /// The folder that relative paths in the config (`input.path`) are resolved against.
    pub dir: PathBuf,
    /// The TOML text, kept verbatim so that `run.json` can record it.
    pub text: String,
    pub raw: RawConfig,
}

impl ConfigSource {
    /// Reads and parses a config file.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let dir = folder_of(path).to_path_buf();
        Self::from_text(&path.display().to_string(), dir, text)
    }

    /// A config built in code (a front end's arrays): the same tables as the TOML, and the
    /// TOML text written from them, which a run record keeps; `name` appears in every
    /// message.
    pub fn from_raw(name: &str, dir: PathBuf, raw: RawConfig) -> Result<Self> {
        let text = toml::to_string(&raw).map_err(|e| Error::Config {
            file: name.to_string(),
            key: "config".into(),
            msg: format!("cannot be written as TOML: {e}"),
        })?;
        // Read back as any config is: the tables kept are those of the text a record keeps.
        Self::from_text(name, dir, text)
    }

    /// Parses TOML text; `name` appears in every message.
    pub fn from_text(name: &str, dir: PathBuf, text: String) -> Result<Self> {
        let raw: RawConfig = toml::from_str(&text).map_err(|e| {
            let line = e
                .span()
                .map(|s| text[..s.start.min(text.len())].lines().count().max(1))
                .unwrap_or(1);
            // A span that starts right after a newline counts one line short.
            let line = match e.span() {
                Some(s) if s.start > 0 && text.as_bytes().get(s.start - 1) == Some(&b'\n') => {
                    line + 1
                }
                _ => line,
            };
            Error::ConfigSyntax {
                file: name.to_string(),
                line,
                msg: e.message().trim().replace('\n', " "),
            }
        })?;
        Ok(Self {
            name: name.to_string(),
            dir,
            text,
            raw,
        })
    }
}
