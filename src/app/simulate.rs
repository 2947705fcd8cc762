//! `sisfilt simulate`: one realisation of the chain with random dropouts, written as
//! `truth.csv`, `measurements.csv`, `inputs.csv` (when there are inputs) and `run.json`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use sisfilt::config::ConfigSource;
use sisfilt::error::Error;
use sisfilt::inputs::InputStream;
use sisfilt::interconnect::ChainSolver;
use sisfilt::io::{CsvWriter, Output, Role, RunRecord, StepLayout, check_files};
use sisfilt::messages::info;
use sisfilt::model::Model;
use sisfilt::simulate::simulate;

use super::{SetArgs, config_files};

#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// The TOML config.
    pub config: PathBuf,
    /// Output folder, created when missing (a folder: not `-`).
    #[arg(long, default_value = ".")]
    pub out: PathBuf,
    /// Seed of every random draw (default: the config's `seed`, else 0).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Number of time steps T (default: the config's `steps`; needed when it has none).
    #[arg(long, value_parser = clap::value_parser!(u64).range(1..))]
    pub steps: Option<u64>,
    /// Leave lost measurement elements empty in measurements.csv (for `--dropouts known`);
    /// by default they hold the noise R u + d, as in the paper's model.
    #[arg(long)]
    pub mark_missing: bool,
    #[command(flatten)]
    pub set: SetArgs,
}

/// `sisfilt simulate`: the files of one realisation, all or none.
pub fn run(args: &SimulateArgs) -> Result<()> {
    // The source too: run.json records the config's text.
    let src = ConfigSource::from_file(&args.config)?.with_settings(&args.set.set)?;
    let mut model = Model::from_config(&src)?;
    if let Some(steps) = args.steps {
        model.steps = Some(usize::try_from(steps).unwrap_or(usize::MAX));
    }
    let steps = model.horizon()?;
    // Fail on an ill-posed chain or unusable inputs before creating anything.
    for w in model.windows().iter().filter(|w| w.first <= steps) {
        ChainSolver::new(&model, w.first)?;
    }
    let out_dir = &args.out;
    if out_dir.as_os_str() == "-" {
        return Err(Error::Usage(
            "--out -: simulate writes a folder of files (truth.csv, measurements.csv, inputs.csv, run.json), which standard output cannot hold; name a folder".into(),
        )
        .into());
    }
    let read = config_files(&args.config, &model);
    let written: Vec<PathBuf> = simulation_files(model.dims.m)
        .map(|name| out_dir.join(name))
        .collect();
    let written: Vec<Role> = written.iter().map(|p| Role::new("--out", p)).collect();
    check_files(&read, &written)?;
    let inputs = InputStream::open(&model, None)?;
    if out_dir.exists() && !out_dir.is_dir() {
        return Err(Error::Usage(format!(
            "--out {}: exists and is not a folder",
            out_dir.display()
        ))
        .into());
    }
    // The folders this run creates, innermost first: a failed run removes them again.
    let created: Vec<PathBuf> = out_dir
        .ancestors()
        .take_while(|a| !a.as_os_str().is_empty() && !a.exists())
        .map(Path::to_path_buf)
        .collect();
    std::fs::create_dir_all(out_dir).map_err(|e| {
        Error::Usage(format!(
            "--out {}: cannot create the folder: {e}",
            out_dir.display()
        ))
    })?;
    let result = write_simulation(args, &src, &model, steps, inputs);
    if result.is_err() {
        for dir in &created {
            // Fails, and so keeps the folder, if anything else appeared in it meanwhile.
            if std::fs::remove_dir(dir).is_err() {
                break;
            }
        }
    }
    result
}

/// The files `simulate` writes into its folder, for a model with `m` inputs.
fn simulation_files(m: usize) -> impl Iterator<Item = &'static str> {
    ["truth.csv", "measurements.csv"]
        .into_iter()
        .chain((m > 0).then_some("inputs.csv"))
        .chain([RunRecord::FILE])
}

/// Simulates `steps` steps and writes the files of `simulate` into the existing folder
/// `args.out`; each file appears (atomically) only once every file is complete.
fn write_simulation(
    args: &SimulateArgs,
    src: &ConfigSource,
    model: &Model,
    steps: usize,
    mut inputs: InputStream,
) -> Result<()> {
    let out_dir = &args.out;
    let seed = args.seed.unwrap_or(model.seed);
    let d = model.dims;
    let file = |name: &str| -> Result<Output> { Ok(Output::create(&out_dir.join(name))?) };
    let io_err = |name: &'static str| move |e| Error::io(name, e);
    let mut truth = CsvWriter::new(file("truth.csv")?, &StepLayout::truth(d.n).header())
        .map_err(io_err("truth.csv"))?;
    let mut meas = CsvWriter::new(
        file("measurements.csv")?,
        &StepLayout::measurements(d.q).header(),
    )
    .map_err(io_err("measurements.csv"))?;
    let mut inputs_out = if d.m > 0 {
        Some(
            CsvWriter::new(file("inputs.csv")?, &StepLayout::inputs(d.m).header())
                .map_err(io_err("inputs.csv"))?,
        )
    } else {
        None
    };
    let mut record_out = file(RunRecord::FILE)?;

    let mut y_row = vec![0.0; d.q];
    simulate(model, steps, seed, &mut inputs, |step| {
        for i in 0..model.subsystems {
            let gamma = step.gamma[i];
            truth
                .row(
                    step.t,
                    i + 1,
                    &step.x[i * d.n..(i + 1) * d.n],
                    Some(gamma as u8),
                )
                .map_err(|e| Error::io("truth.csv", e))?;
            y_row.copy_from_slice(&step.y[i * d.q..(i + 1) * d.q]);
            if args.mark_missing && !gamma {
                y_row.fill(f64::NAN);
            }
            meas.row(step.t, i + 1, &y_row, None)
                .map_err(|e| Error::io("measurements.csv", e))?;
            if let Some(w) = inputs_out.as_mut() {
                w.row(step.t, i + 1, &step.u[i * d.m..(i + 1) * d.m], None)
                    .map_err(|e| Error::io("inputs.csv", e))?;
            }
        }
        Ok(())
    })?;
    inputs.finish(steps)?;

    let mut files = vec!["truth.csv".to_string(), "measurements.csv".to_string()];
    if d.m > 0 {
        files.push("inputs.csv".into());
    }
    let config_dir = RunRecord::relative_dir(out_dir, &src.dir);
    let record = RunRecord {
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        seed,
        subsystems: model.subsystems,
        steps,
        mark_missing: args.mark_missing,
        config_path: args.config.display().to_string(),
        config_dir,
        config_toml: src.text.clone(),
        settings: src.settings.iter().map(ToString::to_string).collect(),
        config: src.raw.clone(),
        files,
    };
    serde_json::to_writer_pretty(&mut record_out, &record).context("writing run.json")?;
    std::io::Write::write_all(&mut record_out, b"\n").map_err(|e| Error::io("run.json", e))?;

    truth
        .into_inner()
        .map_err(|e| Error::io("truth.csv", e))?
        .commit()?;
    meas.into_inner()
        .map_err(|e| Error::io("measurements.csv", e))?
        .commit()?;
    if let Some(w) = inputs_out {
        w.into_inner()
            .map_err(|e| Error::io("inputs.csv", e))?
            .commit()?;
    }
    record_out.commit()?;
    info(format!(
        "simulate: T = {steps} steps × N = {} subsystems (seed {seed}) into {}",
        model.subsystems,
        out_dir.display()
    ));
    Ok(())
}
