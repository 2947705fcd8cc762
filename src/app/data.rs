//! The data of a run on a measurement file (`estimate`, `fit`): the measurements, the config
//! (given, or the one `simulate` recorded beside them) and the inputs file, resolved once.

use std::path::{Path, PathBuf};

use anyhow::Result;

use sisfilt::config::{ConfigSetting, ConfigSource};
use sisfilt::error::Error;
use sisfilt::inputs::InputStream;
use sisfilt::io::{Role, RunRecord, folder_of};
use sisfilt::model::Model;

/// `--config`, `--meas` and `--inputs`, as every command on a measurement file takes them.
#[derive(Debug, clap::Args)]
pub struct DataArgs {
    /// The TOML config. May be left out when --meas was written by `simulate`: the config
    /// recorded in run.json beside it is used.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Measurement CSV (`t,i,y1..yq`; an empty cell is a value not in the data), or - for
    /// standard input.
    #[arg(long)]
    pub meas: PathBuf,
    /// Inputs CSV (`t,i,u1..um`); default: inputs.csv beside a simulated --meas, else the
    /// config's input table.
    #[arg(long)]
    pub inputs: Option<PathBuf>,
}

/// What [`DataArgs`] name, resolved: the config (with `--set`), its model, the run record it
/// came from (when `--config` was left out) and the inputs file (`None`: the config's own).
pub struct Data {
    pub src: ConfigSource,
    pub model: Model,
    pub record: Option<PathBuf>,
    pub inputs_file: Option<PathBuf>,
}

impl DataArgs {
    /// The config (`set` over it), its model and the inputs file.
    pub fn load(&self, set: &[ConfigSetting]) -> Result<Data> {
        let (src, run_dir) = data_config(self.config.as_deref(), &self.meas, set)?;
        let model = Model::from_config(&src)?;
        let inputs_file = data_inputs(&model, self.inputs.as_deref(), run_dir.as_deref())?;
        Ok(Data {
            src,
            model,
            record: run_dir.map(|dir| dir.join(RunRecord::FILE)),
            inputs_file,
        })
    }

    /// The files the run reads, by the names messages give them: `--config` or the run
    /// record, `--meas`, and the inputs file.
    pub fn roles<'a>(&'a self, data: &'a Data) -> Vec<Role<'a>> {
        let mut read: Vec<Role> = (self.config.iter().map(|p| Role::new("--config", p)))
            .chain(data.record.iter().map(|p| Role::new("the run record", p)))
            .collect();
        read.push(Role::new("--meas", &self.meas));
        if let Some(path) = InputStream::path(&data.model, data.inputs_file.as_deref()) {
            let what = if self.inputs.is_some() {
                "--inputs"
            } else {
                "the inputs file"
            };
            read.push(Role::new(what, path));
        }
        read
    }
}

/// The config of a run on a measurement file (`estimate`, `fit`): `config`, else the
/// `run.json` beside `meas`, with `set` over it. Also returns the folder of that run record,
/// if one was used.
fn data_config(
    config: Option<&Path>,
    meas: &Path,
    set: &[ConfigSetting],
) -> Result<(ConfigSource, Option<PathBuf>)> {
    if let Some(path) = config {
        return Ok((ConfigSource::from_file(path)?.with_settings(set)?, None));
    }
    let missing = || {
        Error::Usage(format!(
            "--config is required: {} has no {} beside it (one written by `sisfilt simulate`)",
            meas.display(),
            RunRecord::FILE
        ))
    };
    if meas.as_os_str() == "-" {
        return Err(Error::Usage(
            "--config is required when the measurements come from standard input".into(),
        )
        .into());
    }
    let dir = folder_of(meas).to_path_buf();
    let record = RunRecord::load(&dir)?.ok_or_else(missing)?;
    let src = record.config_source(&dir.join(RunRecord::FILE))?;
    Ok((src.with_settings(set)?, Some(dir)))
}

/// The inputs file of a run on a measurement file: `inputs`, else `inputs.csv` beside a
/// simulated `meas` (in `run_dir`); `None` with the config's own inputs. `--inputs` for a
/// model without inputs is refused.
fn data_inputs(
    model: &Model,
    inputs: Option<&Path>,
    run_dir: Option<&Path>,
) -> Result<Option<PathBuf>> {
    if model.dims.m == 0
        && let Some(path) = inputs
    {
        return Err(Error::Usage(format!(
            "--inputs {}: the model has no inputs (m = 0), so the file would never be read; leave --inputs out",
            path.display()
        ))
        .into());
    }
    Ok(inputs.map(Path::to_path_buf).or_else(|| {
        run_dir
            .map(|dir| dir.join("inputs.csv"))
            .filter(|p| model.dims.m > 0 && p.is_file())
    }))
}
