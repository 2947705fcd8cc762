//! The inputs `u(t, ·)`, one time step at a time: generated from the config's `[input]`, read
//! from an inputs CSV (docs/theory.md §13), which must hold exactly the steps `1..T`, or taken
//! from an array in memory. [`RunInputs`] are the inputs of a whole run known before it starts,
//! which a front end resolves (a file is read at the edge, never opened by a run).

use std::fs::File;
use std::io::Read;
use std::path::Path;
use std::sync::Arc;

use crate::error::{Error, Result};
use crate::io::{StepLayout, StepReader};
use crate::model::{InputSpec, Model};

/// A source of `u(t, ·)`.
pub enum InputStream {
    /// Computed from the config's `[input]` (also the case `m = 0`).
    Generated { spec: InputSpec, m: usize },
    /// Read from a CSV file.
    File(Box<StepReader<Box<dyn Read + Send>>>),
    /// Taken from an array in memory: `per_step` values a step, step after step.
    Table { values: Arc<[f64]>, per_step: usize },
}

/// The inputs of every step of a run, known before it starts: generated from the config's
/// `[input]`, or a table in memory (an inputs file read by the front end, or its own array).
/// Each run reads them through a fresh [`RunInputs::stream`].
#[derive(Debug, Clone)]
pub enum RunInputs {
    Generated { spec: InputSpec, m: usize },
    Table { values: Arc<[f64]>, per_step: usize },
}

impl RunInputs {
    /// The inputs of every run of `model` (`evaluate`): the inputs file its config names,
    /// read for its `T` steps, or the inputs its config generates.
    pub fn of_model(model: &Model) -> Result<Self> {
        match InputStream::path(model, None) {
            Some(_) => Self::read(InputStream::open(model, None)?, model, model.horizon()?),
            None => Self::generated(model),
        }
    }

    /// The inputs the model's `[input]` generates; a model whose inputs are a file is refused,
    /// since the file is the front end's to read ([`RunInputs::read`]).
    pub fn generated(model: &Model) -> Result<Self> {
        if let Some(path) = InputStream::path(model, None) {
            return Err(Error::Usage(format!(
                "the inputs of {} are the file {}: read them first (RunInputs::read) or pass them as an array",
                model.name,
                path.display()
            )));
        }
        Ok(Self::Generated {
            spec: model.input.clone(),
            m: model.dims.m,
        })
    }

    /// The inputs of `model` as an array: `T × N × m` values, step after step and subsystem
    /// after subsystem.
    pub fn table(model: &Model, values: Vec<f64>) -> Result<Self> {
        let per_step = model.subsystems * model.dims.m;
        if per_step == 0 && !values.is_empty()
            || per_step > 0 && !values.len().is_multiple_of(per_step)
        {
            return Err(Error::Usage(format!(
                "u: expected T × N × m values with N = {}, m = {}, found {}",
                model.subsystems,
                model.dims.m,
                values.len()
            )));
        }
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            let m = model.dims.m;
            return Err(Error::Usage(format!(
                "u: t = {}, i = {}, element {}: expected a finite number, found {}",
                k / per_step + 1,
                k / m % model.subsystems + 1,
                k % m + 1,
                values[k]
            )));
        }
        Ok(Self::Table {
            values: values.into(),
            per_step,
        })
    }

    /// The first `steps` steps of `stream` (e.g. the model's inputs file, opened by
    /// [`InputStream::open`]), read into memory as far as the stream goes.
    pub fn read(mut stream: InputStream, model: &Model, steps: usize) -> Result<Self> {
        let per_step = model.subsystems * model.dims.m;
        let mut values = Vec::new();
        if per_step > 0 {
            let mut u = vec![0.0; per_step];
            for t in 1..=steps {
                stream.next(t, &mut u)?;
                values.extend_from_slice(&u);
            }
        }
        Self::table(model, values)
    }

    /// A stream of these inputs from step 1.
    pub fn stream(&self) -> InputStream {
        match self {
            Self::Generated { spec, m } => InputStream::Generated {
                spec: spec.clone(),
                m: *m,
            },
            Self::Table { values, per_step } => InputStream::Table {
                values: values.clone(),
                per_step: *per_step,
            },
        }
    }
}

/// Opens a CSV of the given layout: a path, or `-` for standard input.
pub fn open_csv(
    path: &Path,
    layout: StepLayout,
    subsystems: usize,
) -> Result<StepReader<Box<dyn Read + Send>>> {
    let source: Box<dyn Read + Send> = if path.as_os_str() == "-" {
        Box::new(std::io::stdin())
    } else {
        Box::new(File::open(path).map_err(|e| Error::read(path, e))?)
    };
    let name = if path.as_os_str() == "-" {
        "<stdin>".to_string()
    } else {
        path.display().to_string()
    };
    StepReader::new(&name, source, layout, subsystems)
}

impl InputStream {
    /// Inputs from `file` when given, else as the model's `[input]` says.
    pub fn open(model: &Model, file: Option<&Path>) -> Result<Self> {
        match Self::path(model, file) {
            Some(p) => Ok(InputStream::File(Box::new(open_csv(
                p,
                StepLayout::inputs(model.dims.m),
                model.subsystems,
            )?))),
            None => Ok(InputStream::Generated {
                spec: model.input.clone(),
                m: model.dims.m,
            }),
        }
    }

    /// The file [`InputStream::open`] reads, if any: `file` when given, else the one the
    /// model's `[input]` names; none when the model has no inputs.
    pub fn path<'a>(model: &'a Model, file: Option<&'a Path>) -> Option<&'a Path> {
        match (file, &model.input) {
            _ if model.dims.m == 0 => None,
            (Some(f), _) => Some(f),
            (None, InputSpec::File(f)) => Some(f),
            _ => None,
        }
    }

    /// Fills `u` (`N · m` values) with `u(t, ·)`; steps must be asked for in order.
    pub fn next(&mut self, t: usize, u: &mut [f64]) -> Result<()> {
        match self {
            InputStream::Generated { spec, m } => {
                if *m > 0 {
                    for (k, ui) in u.chunks_mut(*m).enumerate() {
                        ui.fill(spec.generated(t, k + 1).unwrap_or(0.0));
                    }
                }
                Ok(())
            }
            InputStream::Table { values, per_step } => {
                match values.get((t - 1) * *per_step..t * *per_step) {
                    Some(step) => u.copy_from_slice(step),
                    None => {
                        return Err(Error::Usage(format!(
                            "u: holds {} steps, but inputs are needed up to t = {t}",
                            values.len() / (*per_step).max(1)
                        )));
                    }
                }
                Ok(())
            }
            InputStream::File(r) => match r.read_step(u)? {
                Some(_) => Ok(()),
                None => Err(Error::File {
                    file: r.name().to_string(),
                    msg: format!(
                        "ends after t = {}, but inputs are needed up to t = {t} or later",
                        t - 1
                    ),
                }),
            },
        }
    }

    /// The error for a file that held step `steps + 1` (already read by [`InputStream::next`]);
    /// `None` for generated inputs.
    pub fn read_beyond(&self, steps: usize) -> Option<Error> {
        match self {
            InputStream::File(r) => Some(too_long(r.name(), steps)),
            InputStream::Generated { .. } | InputStream::Table { .. } => None,
        }
    }

    /// Checks that a file held no steps beyond `steps` (docs/theory.md §13: exactly `1..T`).
    /// Reads an inputs file to its end, checking every value (a config without `steps`
    /// gives no length to expect).
    pub fn read_to_end(self) -> Result<()> {
        if let InputStream::File(mut r) = self {
            let mut scratch = vec![0.0; r.row_values()];
            while r.read_step(&mut scratch)?.is_some() {}
        }
        Ok(())
    }

    pub fn finish(self, steps: usize) -> Result<()> {
        if let InputStream::File(mut r) = self {
            let mut scratch = vec![0.0; r.row_values()];
            if r.read_step(&mut scratch)?.is_some() {
                return Err(too_long(r.name(), steps));
            }
        }
        Ok(())
    }
}

fn too_long(name: &str, steps: usize) -> Error {
    Error::File {
        file: name.to_string(),
        msg: format!("holds steps beyond t = {steps}; expected exactly the steps 1..{steps}"),
    }
}
