//! Where a run's data come from: the measurements and inputs of each step ([`StepSource`]) and
//! the truth of a simulated run ([`TruthSource`]), from files or from arrays in memory.

use std::io::Read;

use crate::error::{Error, Result};
use crate::inputs::{InputStream, RunInputs};
use crate::io::StepReader;
use crate::model::Model;

/// Chains at least this long parse the measurement and input files of a step in parallel
/// (shorter steps cost less than waking a thread).
const PARALLEL_READ_MIN: usize = 512;

/// The measurements and inputs of a run, one step at a time.
pub trait StepSource {
    /// Fills `y` (`N·q` values; NaN marks an element not in the data) and `u` (`N·m`)
    /// with the next step and returns its `t`, or `None` after the last step.
    fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>>;
    /// After the last step, `steps`: refuses a run of no step, and inputs that go on beyond
    /// the measurements.
    fn finish(&mut self, steps: usize) -> Result<()>;
}

/// The truth of a simulated run, one step at a time.
pub trait TruthSource {
    /// Fills `out` (`N (n + 1)` values: each subsystem's states, then `γ`) with step `t`'s.
    fn read_truth(&mut self, t: usize, out: &mut [f64]) -> Result<()>;
}

/// A measurement file and the inputs, read step by step.
pub struct FileSource<R: Read> {
    meas: StepReader<R>,
    /// `None` once [`StepSource::finish`] has checked it.
    inputs: Option<InputStream>,
}

impl<R: Read + Send> FileSource<R> {
    pub fn new(meas: StepReader<R>, inputs: InputStream) -> Self {
        Self {
            meas,
            inputs: Some(inputs),
        }
    }
}

impl<R: Read + Send> StepSource for FileSource<R> {
    fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>> {
        let Some(inputs) = self.inputs.as_mut() else {
            return Ok(None);
        };
        let meas = &mut self.meas;
        // The measurement and input files are parsed side by side, on long chains.
        let next_t = meas.next_t();
        let (t, inputs_read) = if meas.subsystems() >= PARALLEL_READ_MIN {
            rayon::join(|| meas.read_step(y), || inputs.next(next_t, u))
        } else {
            (meas.read_step(y), inputs.next(next_t, u))
        };
        let Some(t) = t? else {
            // The inputs were read one step ahead of the measurements' end.
            if let (Ok(()), Some(e)) = (&inputs_read, inputs.read_beyond(next_t - 1)) {
                return Err(e);
            }
            return Ok(None);
        };
        inputs_read?;
        Ok(Some(t))
    }

    fn finish(&mut self, steps: usize) -> Result<()> {
        if steps == 0 {
            return Err(Error::File {
                file: self.meas.name().to_string(),
                msg: "holds no measurement rows".into(),
            });
        }
        match self.inputs.take() {
            Some(inputs) => inputs.finish(steps),
            None => Ok(()),
        }
    }
}

/// Measurements and inputs held in memory: `y` with `T × N × q` values, step after step and
/// subsystem after subsystem, and the inputs of those steps.
pub struct ArraySource<'a> {
    y: &'a [f64],
    inputs: InputStream,
    steps: usize,
    t: usize,
}

impl<'a> ArraySource<'a> {
    /// Refuses arrays whose lengths are not whole steps of `model`, or disagree in `T`. `u`
    /// holds `T × N × m` values; without it, the inputs the model generates (a model whose
    /// inputs are a file needs `u`: [`RunInputs::generated`]).
    pub fn new(model: &Model, y: &'a [f64], u: Option<&[f64]>) -> Result<Self> {
        let big_n = model.subsystems;
        let step_y = big_n * model.dims.q;
        if step_y == 0 || !y.len().is_multiple_of(step_y) {
            return Err(Error::Usage(format!(
                "y: expected T × N × q values with N = {big_n}, q = {}, found {}",
                model.dims.q,
                y.len()
            )));
        }
        let steps = y.len() / step_y;
        let step_u = big_n * model.dims.m;
        if let Some(u) = u
            && u.len() != steps * step_u
        {
            return Err(Error::Usage(format!(
                "u: expected T × N × m = {steps} × {big_n} × {} values (T from y), found {}",
                model.dims.m,
                u.len()
            )));
        }
        let inputs = match u {
            Some(u) => RunInputs::table(model, u.to_vec())?,
            None => RunInputs::generated(model)?,
        };
        Ok(Self {
            y,
            inputs: inputs.stream(),
            steps,
            t: 0,
        })
    }
}

impl StepSource for ArraySource<'_> {
    fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>> {
        if self.t == self.steps {
            return Ok(None);
        }
        let k = self.t;
        self.t += 1;
        y.copy_from_slice(&self.y[k * y.len()..(k + 1) * y.len()]);
        self.inputs.next(self.t, u)?;
        Ok(Some(self.t))
    }

    fn finish(&mut self, steps: usize) -> Result<()> {
        if steps == 0 {
            return Err(Error::Usage("y: holds no step".into()));
        }
        Ok(())
    }
}

/// A truth file, read step by step.
pub struct ReaderTruth<R: Read>(pub StepReader<R>);

impl<R: Read> TruthSource for ReaderTruth<R> {
    /// A truth file that ends before the measurements is bad input.
    fn read_truth(&mut self, t: usize, out: &mut [f64]) -> Result<()> {
        if self.0.read_step(out)?.is_none() {
            return Err(Error::File {
                file: self.0.name().to_string(),
                msg: format!(
                    "ends before t = {t}; the truth must cover every step of the measurements"
                ),
            });
        }
        Ok(())
    }
}

/// A truth held in memory: `T × N × (n + 1)` values, each subsystem's states, then `γ`.
pub struct SliceTruth<'a> {
    values: &'a [f64],
}

impl<'a> SliceTruth<'a> {
    /// Refuses a length that is not whole steps of `model`.
    pub fn new(model: &Model, values: &'a [f64]) -> Result<Self> {
        let step = model.subsystems * (model.dims.n + 1);
        if !values.len().is_multiple_of(step) {
            return Err(Error::Usage(format!(
                "truth: expected T × N × (n + 1) values with N = {}, n = {}, found {}",
                model.subsystems,
                model.dims.n,
                values.len()
            )));
        }
        Ok(Self { values })
    }
}

impl TruthSource for SliceTruth<'_> {
    fn read_truth(&mut self, t: usize, out: &mut [f64]) -> Result<()> {
        match self.values.get((t - 1) * out.len()..t * out.len()) {
            Some(step) => {
                out.copy_from_slice(step);
                Ok(())
            }
            None => Err(Error::Usage(format!(
                "truth: ends before t = {t}; the truth must cover every step of the measurements"
            ))),
        }
    }
}

/// Every step of `source` in memory: `y` (`T × N × q` values) and `u` (`T × N × m`), as
/// [`super::estimate`] and [`super::log_likelihood`] take them (a front end that reads a file
/// whole, as `fit` does).
pub fn read_all(model: &Model, source: &mut dyn StepSource) -> Result<(Vec<f64>, Vec<f64>)> {
    let mut y_t = vec![0.0; model.subsystems * model.dims.q];
    let mut u_t = vec![0.0; model.subsystems * model.dims.m];
    let (mut y, mut u) = (Vec::new(), Vec::new());
    let mut steps = 0;
    while let Some(t) = source.next_step(&mut y_t, &mut u_t)? {
        y.extend_from_slice(&y_t);
        u.extend_from_slice(&u_t);
        steps = t;
    }
    source.finish(steps)?;
    Ok((y, u))
}
