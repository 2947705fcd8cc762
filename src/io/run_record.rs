//! `run.json`: what `simulate` records beside its data so that the folder describes itself and
//! `estimate --meas DIR/measurements.csv` can find the config without `--config`.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::config::{ConfigSetting, ConfigSource, RawConfig};
use crate::error::{Error, Result};

/// The record of one `simulate` run.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RunRecord {
    /// Version of the `sisfilt` that wrote the files.
    pub sisfilt_version: String,
    /// The seed of every random draw of the run.
    pub seed: u64,
    /// Chain length `N`.
    pub subsystems: usize,
    /// Horizon `T`.
    pub steps: usize,
    /// Whether lost measurement elements were left empty (`--mark-missing`).
    pub mark_missing: bool,
    /// The config path as given on the command line.
    pub config_path: String,
    /// The config's folder, relative to the folder of this record when both share a root (so
    /// that the data set can move with its configs), else absolute. Relative paths inside the
    /// config (`input.path`) are resolved against it.
    pub config_dir: PathBuf,
    /// The config file verbatim.
    pub config_toml: String,
    /// The values given over it (`--set KEY=VALUE`), in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub settings: Vec<String>,
    /// The config the run used (with the settings), as structured data, for readers of this
    /// file.
    pub config: RawConfig,
    /// The data files written beside this record.
    pub files: Vec<String>,
}

impl RunRecord {
    /// File name of the record.
    pub const FILE: &'static str = "run.json";

    /// Reads `run.json` from `dir`; `None` when there is none.
    pub fn load(dir: &Path) -> Result<Option<Self>> {
        let path = dir.join(Self::FILE);
        let file = match std::fs::File::open(&path) {
            Ok(file) => file,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(Error::read(&path, e)),
        };
        let name = path.display().to_string();
        let text = super::read_text(&name, file, super::MAX_DOCUMENT_BYTES, "run record")?;
        serde_json::from_str(&text).map(Some).map_err(|e| {
            Error::json(
                path.display().to_string(),
                "a run record written by `sisfilt simulate`",
                &e,
            )
        })
    }

    /// The recorded config with its settings, named after the record for messages.
    pub fn config_source(&self, record_path: &Path) -> Result<ConfigSource> {
        let record_dir = record_path.parent().unwrap_or(Path::new("."));
        let name = format!("{} (config of {})", record_path.display(), self.config_path);
        let settings = self
            .settings
            .iter()
            .map(|s| {
                s.parse::<ConfigSetting>().map_err(|msg| Error::Config {
                    file: record_path.display().to_string(),
                    key: "settings".into(),
                    msg,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        ConfigSource::from_text(
            &name,
            record_dir.join(&self.config_dir),
            self.config_toml.clone(),
        )?
        .with_settings(&settings)
    }

    /// `target` relative to `base` (both made absolute), or `target` absolute when that fails.
    pub fn relative_dir(base: &Path, target: &Path) -> PathBuf {
        let (Ok(base), Ok(target)) = (std::fs::canonicalize(base), std::fs::canonicalize(target))
        else {
            return target.to_path_buf();
        };
        let common = base
            .components()
            .zip(target.components())
            .take_while(|(a, b)| a == b)
            .count();
        let mut rel = PathBuf::new();
        for _ in base.components().skip(common) {
            rel.push("..");
        }
        for c in target.components().skip(common) {
            rel.push(c);
        }
        if rel.as_os_str().is_empty() {
            rel.push(".");
        }
        rel
    }
}
