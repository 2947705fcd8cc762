//! The TOML config of docs/theory.md §13, read as it is written. These raw structs only mirror the file
//! (unknown keys are rejected); [`crate::model::Model::from_config`] checks them once and turns
//! them into a validated model. Nothing downstream reads these structs again.
#![allow(non_snake_case)]

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::{folder_of, read_text};

/// A matrix as the TOML writes it: a list of rows, or a number for a `1 × 1` matrix.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(transparent)]
pub struct RawMatrix(pub Vec<Vec<f64>>);

impl std::ops::Deref for RawMatrix {
    type Target = Vec<Vec<f64>>;

    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

impl From<Vec<Vec<f64>>> for RawMatrix {
    fn from(rows: Vec<Vec<f64>>) -> Self {
        Self(rows)
    }
}

impl<'de> Deserialize<'de> for RawMatrix {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Written {
            Number(f64),
            Rows(Vec<Vec<f64>>),
        }
        match Written::deserialize(de) {
            Ok(Written::Number(x)) => Ok(Self(vec![vec![x]])),
            Ok(Written::Rows(rows)) => Ok(Self(rows)),
            // A required matrix left out is said as such.
            Err(e) if e.to_string().starts_with("missing field") => Err(e),
            Err(_) => Err(serde::de::Error::custom(
                "expected a matrix as a list of rows of numbers, [[…], …], or a number for a 1 × 1 matrix",
            )),
        }
    }
}

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
    /// Zero when left out, which only a chain without coupling allows (`n⁺ + n⁻ = 0` or
    /// `N = 1`); the same for `D`.
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
    pub mean: Option<RawMean>,
    pub cov: RawMatrix,
}

/// `mean = [0.0, 1.0]` (every subsystem's) or `mean = [[0.0, 1.0], [0.2, 1.1], …]` (one per
/// subsystem, as a recording's first readings give them).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub enum RawMean {
    All(Vec<f64>),
    PerSubsystem(Vec<Vec<f64>>),
}

/// One entry of a mean: a number, or one subsystem's list of numbers.
enum MeanEntry {
    Number(f64),
    List(Vec<f64>),
}

impl<'de> Deserialize<'de> for MeanEntry {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = MeanEntry;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a number, or a list of numbers (one subsystem's mean)")
            }
            fn visit_f64<E: serde::de::Error>(self, v: f64) -> Result<Self::Value, E> {
                Ok(MeanEntry::Number(v))
            }
            fn visit_i64<E: serde::de::Error>(self, v: i64) -> Result<Self::Value, E> {
                Ok(MeanEntry::Number(v as f64))
            }
            fn visit_u64<E: serde::de::Error>(self, v: u64) -> Result<Self::Value, E> {
                Ok(MeanEntry::Number(v as f64))
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Self::Value, A::Error> {
                let mut v = Vec::with_capacity(seq.size_hint().unwrap_or(0).min(1 << 16));
                while let Some(x) = seq.next_element::<f64>()? {
                    v.push(x);
                }
                Ok(MeanEntry::List(v))
            }
        }
        de.deserialize_any(Visitor)
    }
}

/// By hand, as [`RawProbability`], so that anything else is refused saying what was expected.
impl<'de> Deserialize<'de> for RawMean {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = RawMean;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a list of n numbers, or a list of such lists, one per subsystem")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Self::Value, A::Error> {
                use serde::de::Error;
                let (mut numbers, mut lists) = (Vec::new(), Vec::new());
                while let Some(entry) = seq.next_element::<MeanEntry>()? {
                    match entry {
                        MeanEntry::Number(x) => numbers.push(x),
                        MeanEntry::List(v) => lists.push(v),
                    }
                    if !numbers.is_empty() && !lists.is_empty() {
                        return Err(A::Error::custom(
                            "expected numbers or lists of numbers (one per subsystem), not both",
                        ));
                    }
                }
                Ok(if lists.is_empty() {
                    RawMean::All(numbers)
                } else {
                    RawMean::PerSubsystem(lists)
                })
            }
        }
        de.deserialize_any(Visitor)
    }
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

/// Where an override applies along one axis: one inclusive range `[first, last]`, or a list
/// of them, `[[1, 1], [11, 11], [21, 30]]`. A flat list of any other length is refused: it
/// would read as a range by its first two numbers.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(untagged)]
pub enum RawRanges {
    Range([i64; 2]),
    List(Vec<[i64; 2]>),
}

impl RawRanges {
    /// The ranges, in the order written.
    pub fn ranges(&self) -> &[[i64; 2]] {
        match self {
            RawRanges::Range(r) => std::slice::from_ref(r),
            RawRanges::List(list) => list,
        }
    }
}

impl<'de> Deserialize<'de> for RawRanges {
    fn deserialize<D: serde::Deserializer<'de>>(de: D) -> Result<Self, D::Error> {
        use serde::de::Error as _;
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Item {
            Number(i64),
            Range(Vec<i64>),
        }
        const EXPECTED: &str = "expected [first, last], or a list of ranges [[first, last], …] (several single ones: [[1, 1], [11, 11], [21, 21]])";
        let items = Vec::<Item>::deserialize(de)
            .map_err(|_| D::Error::custom(format!("{EXPECTED}, of integers")))?;
        let numbers: Vec<i64> = items
            .iter()
            .filter_map(|i| match i {
                Item::Number(v) => Some(*v),
                Item::Range(_) => None,
            })
            .collect();
        if numbers.len() == items.len() {
            return match numbers[..] {
                [first, last] => Ok(RawRanges::Range([first, last])),
                _ => Err(D::Error::custom(format!(
                    "{EXPECTED}, found a list of {} numbers",
                    numbers.len()
                ))),
            };
        }
        items
            .into_iter()
            .map(|i| match i {
                Item::Range(r) if r.len() == 2 => Ok([r[0], r[1]]),
                Item::Range(r) => Err(D::Error::custom(format!(
                    "{EXPECTED}, found a range of {} numbers",
                    r.len()
                ))),
                Item::Number(_) => Err(D::Error::custom(format!(
                    "{EXPECTED}, found numbers and ranges mixed"
                ))),
            })
            .collect::<Result<Vec<_>, _>>()
            .map(RawRanges::List)
    }
}

/// One `[[override]]` table: parameters that apply on rectangles of `(t, i)`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawOverride {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub subsystems: Option<RawRanges>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<RawRanges>,
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
    /// `false`: these subsystems have no sensor (docs/theory.md §15): `simulate` leaves their
    /// measurements empty and every filter takes them as gaps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured: Option<bool>,
    /// These subsystems' own initial condition (at `t = 1`, so not with `steps`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub initial: Option<RawOverrideInitial>,
}

impl RawOverride {
    /// The noise matrix `Q` or `M` the override sets.
    pub fn noise_mut(&mut self, key: &str) -> &mut Option<RawMatrix> {
        match key {
            "Q" => &mut self.Q,
            _ => &mut self.M,
        }
    }

    /// True when the override sets no value (it names only where it applies).
    pub fn sets_nothing(&self) -> bool {
        let matrices = [
            &self.A, &self.B, &self.C, &self.D, &self.G, &self.H, &self.J, &self.R, &self.M,
            &self.Q,
        ];
        matrices.iter().all(|m| m.is_none())
            && self.p.is_none()
            && self.measured.is_none()
            && self.initial.is_none()
    }
}

/// `initial.mean`, `initial.cov` in an override: either, or both; what is left out is the
/// subsystem's initial condition without this override.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawOverrideInitial {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean: Option<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cov: Option<RawMatrix>,
}

/// One config value given beside the file (`--set KEY=VALUE`, docs/theory.md §13): the key
/// by its dotted path as messages name it (`dropout.p`, `model.M`, `override[2].p`), the
/// value in TOML syntax (`0.7`, `[[0.02]]`; a bare word is a string, `sine`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ConfigSetting {
    pub key: String,
    pub value: String,
}

impl std::str::FromStr for ConfigSetting {
    type Err = String;

    /// `KEY=VALUE`.
    fn from_str(text: &str) -> std::result::Result<Self, String> {
        match text.split_once('=') {
            Some((key, value)) if !key.trim().is_empty() => Ok(Self {
                key: key.trim().to_string(),
                value: value.trim().to_string(),
            }),
            _ => Err(format!(
                "expected KEY=VALUE with a config key by its dotted path, e.g. dropout.p=0.7, found `{}`",
                crate::messages::excerpt(text)
            )),
        }
    }
}

impl std::fmt::Display for ConfigSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, "{}={}", self.key, self.value)
    }
}

impl ConfigSetting {
    /// Whether a message about `key` concerns this setting's value: the key itself or a part
    /// of it (`model.M` for `model`, `override[2].p` for `override[2]`).
    pub fn covers(&self, key: &str) -> bool {
        key.strip_prefix(self.key.as_str())
            .is_some_and(|rest| rest.is_empty() || rest.starts_with(['.', '[']))
    }

    /// The value as TOML; a bare word that is not TOML (`sine`) is a string.
    fn toml_value(&self) -> std::result::Result<toml::Value, String> {
        let parsed = toml::from_str::<toml::Table>(&format!("value = {}", self.value))
            .map_err(|e| crate::messages::parser_message(e.message()))
            .and_then(|mut t| t.remove("value").ok_or_else(|| "no value".to_string()));
        match parsed {
            Ok(v) => Ok(v),
            Err(_)
                if !self.value.is_empty()
                    && self
                        .value
                        .chars()
                        .all(|c| c.is_alphanumeric() || c == '_' || c == '-') =>
            {
                Ok(toml::Value::String(self.value.clone()))
            }
            Err(e) => Err(format!("`{}` is not a TOML value: {e}", self.value)),
        }
    }

    /// Puts the value into `table` at the key's path: tables on the way are made when missing,
    /// `name[k]` is the `k`-th (from 1) table of the array `name` (`k` one past its end appends
    /// one).
    fn apply(&self, table: &mut toml::Table) -> std::result::Result<(), String> {
        let value = self.toml_value()?;
        let parts: Vec<&str> = self.key.split('.').collect();
        let mut here = table;
        for (depth, part) in parts.iter().enumerate() {
            let (name, index) = match part.split_once('[') {
                Some((name, rest)) => {
                    let k = rest
                        .strip_suffix(']')
                        .and_then(|k| k.parse::<usize>().ok())
                        .filter(|&k| k >= 1)
                        .ok_or_else(|| format!("`{part}`: expected name[k] with k ≥ 1"))?;
                    (name, Some(k))
                }
                None => (*part, None),
            };
            if name.is_empty() {
                return Err("expected a dotted path such as model.M".into());
            }
            let last = depth + 1 == parts.len();
            let slot = match index {
                None if last => {
                    here.insert(name.to_string(), value);
                    return Ok(());
                }
                None => here
                    .entry(name.to_string())
                    .or_insert_with(|| toml::Value::Table(toml::Table::new())),
                Some(k) => {
                    let list = here
                        .entry(name.to_string())
                        .or_insert_with(|| toml::Value::Array(Vec::new()))
                        .as_array_mut()
                        .ok_or_else(|| format!("`{name}` is not a list of tables"))?;
                    if k == list.len() + 1 {
                        list.push(toml::Value::Table(toml::Table::new()));
                    }
                    let len = list.len();
                    let item = list
                        .get_mut(k - 1)
                        .ok_or_else(|| format!("`{name}` has {len} tables, not {k}"))?;
                    if last {
                        *item = value;
                        return Ok(());
                    }
                    item
                }
            };
            here = slot
                .as_table_mut()
                .ok_or_else(|| format!("`{}` is not a table", parts[..=depth].join(".")))?;
        }
        Ok(())
    }
}

/// The key of a deserialisation error's path as messages name keys (`model.Q`,
/// `override[2].p`: overrides from 1), without the position inside a value; `None` at the top.
fn key_of(path: &serde_path_to_error::Path) -> Option<String> {
    use serde_path_to_error::Segment;
    let mut key = String::new();
    for segment in path.iter() {
        match segment {
            Segment::Map { key: name } | Segment::Enum { variant: name } => {
                if !key.is_empty() {
                    key.push('.');
                }
                key.push_str(name);
            }
            // Only `[[override]]` is a list of tables; inside a value, the key is enough.
            Segment::Seq { index } if key == "override" => key += &format!("[{}]", index + 1),
            Segment::Seq { .. } => break,
            Segment::Unknown => {}
        }
    }
    (!key.is_empty()).then_some(key)
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
    /// The values given beside the text ([`ConfigSource::with_settings`]), in order; `raw`
    /// holds them.
    pub settings: Vec<ConfigSetting>,
    pub raw: RawConfig,
}

/// The largest config read: a list of `p` or of any value per subsystem for the largest chain
/// (10⁷ subsystems) fits many times over; a file of gigabytes (or `/dev/zero`) is refused
/// before the parser holds it.
pub const MAX_CONFIG_BYTES: u64 = 256 << 20;

impl ConfigSource {
    /// Reads and parses a config file; `-` is standard input (its relative paths resolve
    /// against the working folder).
    pub fn from_file(path: &Path) -> Result<Self> {
        if path.as_os_str() == "-" {
            let stdin = std::io::stdin().lock();
            let text = read_text("<stdin>", stdin, MAX_CONFIG_BYTES, "config")?;
            return Self::from_text("<stdin>", PathBuf::from("."), text);
        }
        let file = std::fs::File::open(path).map_err(|e| Error::read(path, e))?;
        let text = read_text(
            &path.display().to_string(),
            file,
            MAX_CONFIG_BYTES,
            "config",
        )?;
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

    /// Parses TOML text; `name` appears in every message, with the line and, for a value of
    /// the wrong type, its key.
    pub fn from_text(name: &str, dir: PathBuf, text: String) -> Result<Self> {
        let syntax = |e: &toml::de::Error, key: Option<String>| {
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
            let msg = crate::messages::parser_message(e.message());
            Error::ConfigSyntax {
                file: name.to_string(),
                line,
                msg: match key {
                    Some(key) => format!("{key}: {msg}"),
                    None => msg,
                },
            }
        };
        let de = toml::Deserializer::parse(&text).map_err(|e| syntax(&e, None))?;
        let raw: RawConfig = serde_path_to_error::deserialize(de).map_err(|e| {
            // An unknown key is named by the message: the key is the table it sits in.
            let key = key_of(e.path()).and_then(|key| {
                if e.inner().message().starts_with("unknown field") {
                    key.rsplit_once('.').map(|(table, _)| table.to_string())
                } else {
                    Some(key)
                }
            });
            syntax(e.inner(), key)
        })?;
        Ok(Self {
            name: name.to_string(),
            dir,
            text,
            settings: Vec::new(),
            raw,
        })
    }

    /// The config with `settings` applied over its text, in order (a later one wins), each
    /// read as the file is: a value of the wrong type, an unknown key or a value the model
    /// refuses names the key and says that it came from `--set`.
    pub fn with_settings(mut self, settings: &[ConfigSetting]) -> Result<Self> {
        if settings.is_empty() {
            return Ok(self);
        }
        let mut table: toml::Table = toml::from_str(&self.text).map_err(|e| Error::Config {
            file: self.name.clone(),
            key: "config".into(),
            msg: crate::messages::parser_message(e.message()),
        })?;
        for setting in settings {
            let refused = |msg: String| Error::Config {
                file: self.name.clone(),
                key: format!("{} (from --set)", setting.key),
                msg,
            };
            setting.apply(&mut table).map_err(refused)?;
            // Read back after each, so that a value of the wrong type names its own key.
            self.raw = serde_path_to_error::deserialize(table.clone()).map_err(
                |e: serde_path_to_error::Error<toml::de::Error>| {
                    refused(crate::messages::parser_message(e.inner().message()))
                },
            )?;
            self.settings.push(setting.clone());
        }
        Ok(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(text: &str) -> ConfigSetting {
        text.parse().unwrap()
    }

    /// A setting puts its TOML value at its path: tables made on the way, `name[k]` the
    /// `k`-th table (one past the end appends), a bare word a string.
    #[test]
    fn settings_put_their_value_at_their_path() {
        let mut table: toml::Table = toml::from_str("a = 1\n[[o]]\nx = 2\n").unwrap();
        for s in [
            "b.c = [[0.5]]",
            "o[1].x=3",
            "o[2].y=true",
            "k=sine",
            "s=\"two words\"",
        ] {
            set(s).apply(&mut table).unwrap();
        }
        let want: toml::Table = toml::from_str(
            "a = 1\nk = \"sine\"\ns = \"two words\"\n[b]\nc = [[0.5]]\n[[o]]\nx = 3\n[[o]]\ny = true\n",
        )
        .unwrap();
        assert_eq!(table, want);
        for (bad, says) in [
            ("o[4].x=1", "has 2 tables, not 4"),
            ("a.b=1", "`a` is not a table"),
            ("o[0].x=1", "k ≥ 1"),
            ("b.c=[1", "is not a TOML value"),
        ] {
            let err = set(bad).apply(&mut table).unwrap_err();
            assert!(err.contains(says), "{bad}: {err}");
        }
        assert!("novalue".parse::<ConfigSetting>().is_err());
        assert!("=1".parse::<ConfigSetting>().is_err());
    }

    /// A message about a key concerns the settings of that key and of the tables above it.
    #[test]
    fn a_setting_covers_its_key_and_what_is_inside() {
        let s = set("override[2]={p = 0.5}");
        assert!(s.covers("override[2]") && s.covers("override[2].p"));
        assert!(!s.covers("override[21].p") && !s.covers("override"));
        assert!(set("model=1").covers("model.M") && !set("model.M=1").covers("model.MM"));
    }
}
