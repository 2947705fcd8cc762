//! Where a run's data come from: the measurements and inputs of each step ([`StepSource`]) and
//! the truth of a simulated run ([`TruthSource`]), from files or from arrays in memory.

use std::io::Read;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

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

/// Sources whose steps hold at least this many values (`N (q + m)`) are handed over a step at
/// a time; shorter steps in batches of about this many values, so that waking either thread
/// costs less than the work it is given.
const READ_AHEAD_VALUES: usize = 2048;

/// A [`StepSource`] read on a thread of its own, ahead of the caller: the parsing of the next
/// steps overlaps the filtering of this one. At most two batches wait (memory flat in `T`);
/// an error of the source comes after every step before it, as from the source itself, and
/// [`StepSource::finish`] runs on the caller's side, on the source given back at its end.
pub struct ReadAhead<S> {
    /// Batches read, then the end of the source.
    read: Receiver<Ahead<S>>,
    /// Batches consumed, back to the reading thread.
    free: SyncSender<StepBatch>,
    /// The batch being consumed, and how many of its steps are.
    current: Option<(StepBatch, usize)>,
    /// The source, once the thread has given it back at its end.
    ended: Option<S>,
    thread: Option<JoinHandle<()>>,
}

/// What the reading thread hands over.
enum Ahead<S> {
    Steps(StepBatch),
    /// The source failed: no step after this.
    Failed(Error),
    /// The source is at its end, given back for [`StepSource::finish`].
    Ended(S),
}

/// Consecutive steps: their `t`, and their `y` and `u` one after the other.
struct StepBatch {
    t: Vec<usize>,
    y: Vec<f64>,
    u: Vec<f64>,
}

impl<S: StepSource + Send + 'static> ReadAhead<S> {
    /// Starts reading `source`, whose steps hold `step_y` measurement and `step_u` input
    /// values. A `live` source (a pipe, a terminal) hands each step over as soon as it is
    /// read; a file in batches.
    pub fn new(mut source: S, step_y: usize, step_u: usize, live: bool) -> Self {
        let per_batch = match live {
            true => 1,
            false => READ_AHEAD_VALUES.div_ceil((step_y + step_u).max(1)),
        };
        let (to_caller, read) = sync_channel::<Ahead<S>>(2);
        let (free, from_caller) = sync_channel::<StepBatch>(2);
        for _ in 0..2 {
            free.send(StepBatch {
                t: Vec::with_capacity(per_batch),
                y: vec![0.0; per_batch * step_y],
                u: vec![0.0; per_batch * step_u],
            })
            .expect("the channel has room");
        }
        let thread = std::thread::Builder::new()
            .name("sisfilt-reader".into())
            .spawn(move || {
                // Ends when the caller is gone (its ends of the channels dropped).
                for mut batch in from_caller {
                    batch.t.clear();
                    let mut end = None;
                    while batch.t.len() < per_batch {
                        let k = batch.t.len();
                        let y = &mut batch.y[k * step_y..(k + 1) * step_y];
                        let u = &mut batch.u[k * step_u..(k + 1) * step_u];
                        match source.next_step(y, u) {
                            Ok(Some(t)) => batch.t.push(t),
                            Ok(None) => {
                                end = Some(Ok(()));
                                break;
                            }
                            Err(e) => {
                                end = Some(Err(e));
                                break;
                            }
                        }
                    }
                    if !batch.t.is_empty() && to_caller.send(Ahead::Steps(batch)).is_err() {
                        return;
                    }
                    match end {
                        None => {}
                        Some(Ok(())) => {
                            let _ = to_caller.send(Ahead::Ended(source));
                            return;
                        }
                        Some(Err(e)) => {
                            let _ = to_caller.send(Ahead::Failed(e));
                            return;
                        }
                    }
                }
            })
            .expect("the reader thread starts");
        Self {
            read,
            free,
            current: None,
            ended: None,
            thread: Some(thread),
        }
    }
}

impl<S: StepSource> StepSource for ReadAhead<S> {
    fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>> {
        loop {
            if let Some((batch, k)) = &mut self.current
                && *k < batch.t.len()
            {
                let (step_y, step_u) = (y.len(), u.len());
                y.copy_from_slice(&batch.y[*k * step_y..(*k + 1) * step_y]);
                u.copy_from_slice(&batch.u[*k * step_u..(*k + 1) * step_u]);
                *k += 1;
                return Ok(Some(batch.t[*k - 1]));
            }
            if let Some((batch, _)) = self.current.take() {
                // The thread may be gone (at the source's end): nothing to give back.
                let _ = self.free.send(batch);
            }
            if self.ended.is_some() {
                return Ok(None);
            }
            match self.read.recv() {
                Ok(Ahead::Steps(batch)) => self.current = Some((batch, 0)),
                Ok(Ahead::Failed(e)) => return Err(e),
                Ok(Ahead::Ended(source)) => self.ended = Some(source),
                // The thread ends without a word only when it panicked: so does the caller.
                Err(_) => match self.thread.take().map(JoinHandle::join) {
                    Some(Err(panic)) => std::panic::resume_unwind(panic),
                    _ => unreachable!("the reading thread ends with Failed or Ended"),
                },
            }
        }
    }

    /// After [`StepSource::next_step`] returned `None`: the source's own `finish`.
    fn finish(&mut self, steps: usize) -> Result<()> {
        let source = self.ended.as_mut();
        source
            .expect("finish comes after the last step")
            .finish(steps)
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

#[cfg(test)]
mod tests {
    use super::*;

    /// Steps `1..=steps` with `y = (t, −t)` and `u = (10 t)`; an error instead of step
    /// `fail_at`, a panic instead of step `panic_at`; `finish` refuses any count but `steps`.
    struct Counting {
        steps: usize,
        fail_at: usize,
        panic_at: usize,
        t: usize,
    }

    impl Counting {
        fn new(steps: usize) -> Self {
            Self {
                steps,
                fail_at: usize::MAX,
                panic_at: usize::MAX,
                t: 0,
            }
        }
    }

    impl StepSource for Counting {
        fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>> {
            if self.t == self.steps {
                return Ok(None);
            }
            self.t += 1;
            let t = self.t;
            assert!(t != self.panic_at, "the source broke at t = {t}");
            if t == self.fail_at {
                return Err(Error::Usage(format!("bad step {t}")));
            }
            (y[0], y[1], u[0]) = (t as f64, -(t as f64), 10.0 * t as f64);
            Ok(Some(t))
        }

        fn finish(&mut self, steps: usize) -> Result<()> {
            match steps == self.steps {
                true => Ok(()),
                false => Err(Error::Usage(format!("finished after {steps}"))),
            }
        }
    }

    /// Every step `(t, y, u)` of `source` until it ends or fails, and how.
    fn drain(source: &mut dyn StepSource) -> (Vec<(usize, [f64; 3])>, Result<()>) {
        let (mut y, mut u) = ([0.0; 2], [0.0; 1]);
        let mut steps = Vec::new();
        loop {
            match source.next_step(&mut y, &mut u) {
                Ok(Some(t)) => steps.push((t, [y[0], y[1], u[0]])),
                Ok(None) => {
                    let last = steps.last().map_or(0, |s| s.0);
                    return (steps, source.finish(last));
                }
                Err(e) => return (steps, Err(e)),
            }
        }
    }

    /// In batches (three of them, the last one short) and step by step, the steps come as
    /// from the source itself, then its end and its own `finish`.
    #[test]
    fn read_ahead_gives_the_steps_of_its_source_in_order() {
        let steps = 2 * READ_AHEAD_VALUES.div_ceil(3) + 5;
        let (expected, end) = drain(&mut Counting::new(steps));
        assert!(end.is_ok());
        assert_eq!(expected.len(), steps);
        for live in [false, true] {
            let mut ahead = ReadAhead::new(Counting::new(steps), 2, 1, live);
            let (got, end) = drain(&mut ahead);
            assert_eq!(got, expected);
            assert!(end.is_ok());
            // Ended: no step more, and finish still asks the source.
            assert!(matches!(
                ahead.next_step(&mut [0.0; 2], &mut [0.0]),
                Ok(None)
            ));
            assert!(ahead.finish(steps - 1).is_err());
        }
    }

    /// An error of the source comes after every step before it, and ends the steps.
    #[test]
    fn read_ahead_gives_an_error_after_the_steps_before_it() {
        for live in [false, true] {
            let source = Counting {
                fail_at: 1000,
                ..Counting::new(5000)
            };
            let (got, end) = drain(&mut ReadAhead::new(source, 2, 1, live));
            assert_eq!(got.len(), 999);
            assert_eq!(got[998].0, 999);
            assert_eq!(end.unwrap_err().to_string(), "bad step 1000");
        }
    }

    /// A panic of the source is the caller's panic, once the steps before it are consumed.
    #[test]
    #[should_panic(expected = "the source broke at t = 7")]
    fn read_ahead_passes_a_panic_of_its_source_on() {
        let source = Counting {
            panic_at: 7,
            ..Counting::new(100)
        };
        let mut ahead = ReadAhead::new(source, 2, 1, true);
        let (got, _) = drain(&mut ahead);
        unreachable!("{} steps and no panic", got.len());
    }

    /// A caller that stops early leaves no thread blocked for ever behind it.
    #[test]
    fn read_ahead_stops_when_its_caller_is_gone() {
        let mut ahead = ReadAhead::new(Counting::new(1_000_000), 2, 1, false);
        assert!(matches!(
            ahead.next_step(&mut [0.0; 2], &mut [0.0]),
            Ok(Some(1))
        ));
        let thread = ahead.thread.take().expect("a reading thread");
        drop(ahead);
        thread.join().expect("the thread ends without a panic");
    }
}
