//! The estimates writer on a thread of its own ([`BackgroundWriter`]), so that formatting and
//! writing step `t` overlap the filtering of the next steps.

use std::io::Write;

use super::{EstimatesWriter, RowValues};
use crate::io::Output;
use crate::linalg::band::SymBand;

/// Steps handed to the writer thread together: the first step is `first`, and `x`, `p` hold
/// `count` steps one after the other.
struct StepBatch {
    first: usize,
    count: usize,
    x: Vec<f64>,
    p: Vec<f64>,
    /// One covariance band per step, for a writer with cross-covariance columns.
    bands: Vec<SymBand>,
    /// `π` of `count` steps (NaN for a step without), for a writer with the `arrival`
    /// column; the NIS the same, for a writer with the `nis` column.
    arrival: Vec<f64>,
    nis: Vec<f64>,
}

/// Rows handed to the writer thread at a time, at least (short chains batch several steps, so
/// that waking the thread does not cost more than the work it is given).
const BATCH_MIN_ROWS: usize = 512;

/// An [`EstimatesWriter`] on a thread of its own, behind the caller: formatting and the
/// `write` system calls of step `t` overlap the reading and filtering of the next steps.
/// Two batch buffers go back and forth through bounded channels, so a step allocates nothing.
/// A live writer ([`EstimatesWriter::live`]) gets each step on its own, and passes it on at
/// once.
pub struct BackgroundWriter<W: Write + Send + 'static = Output> {
    to_writer: Option<std::sync::mpsc::SyncSender<StepBatch>>,
    free: std::sync::mpsc::Receiver<StepBatch>,
    /// The batch being filled, if any.
    current: Option<StepBatch>,
    /// Steps per batch, and the numbers of one step.
    per_batch: usize,
    rows: usize,
    step_x: usize,
    step_p: usize,
    thread: Option<std::thread::JoinHandle<std::io::Result<EstimatesWriter<W>>>>,
    /// Time the writer thread spent formatting and writing (not waiting), in nanoseconds.
    busy: std::sync::Arc<std::sync::atomic::AtomicU64>,
}

impl<W: Write + Send + 'static> BackgroundWriter<W> {
    /// Starts the thread for steps of `rows` rows (`N`), with the columns of `writer`.
    pub fn new(mut writer: EstimatesWriter<W>, rows: usize) -> Self {
        use std::sync::atomic::Ordering;
        let columns = writer.columns();
        let n = columns.n;
        let (step_x, step_p) = (rows * n, rows * n * n);
        let per_batch = if writer.live {
            1
        } else {
            BATCH_MIN_ROWS.div_ceil(rows.max(1))
        };
        let (to_writer, from_caller) = std::sync::mpsc::sync_channel::<StepBatch>(2);
        let (to_caller, free) = std::sync::mpsc::sync_channel::<StepBatch>(2);
        for _ in 0..2 {
            let batch = StepBatch {
                first: 0,
                count: 0,
                x: vec![0.0; per_batch * step_x],
                p: vec![0.0; per_batch * step_p],
                bands: if columns.cross > 0 {
                    let band = || SymBand::zeros(rows, n, columns.cross);
                    (0..per_batch).map(|_| band()).collect()
                } else {
                    Vec::new()
                },
                arrival: vec![0.0; if columns.arrival { per_batch * rows } else { 0 }],
                nis: vec![0.0; if columns.nis { per_batch * rows } else { 0 }],
            };
            to_caller.send(batch).expect("the channel has room");
        }
        let busy = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
        let busy_thread = busy.clone();
        let thread = std::thread::Builder::new()
            .name("sisfilt-writer".into())
            .spawn(move || {
                for batch in from_caller {
                    let start = std::time::Instant::now();
                    for k in 0..batch.count {
                        writer.write_step(
                            batch.first + k,
                            &batch.x[k * step_x..(k + 1) * step_x],
                            &batch.p[k * step_p..(k + 1) * step_p],
                            batch.bands.get(k),
                            RowValues {
                                arrival: batch.arrival.get(k * rows..(k + 1) * rows),
                                nis: batch.nis.get(k * rows..(k + 1) * rows),
                            },
                        )?;
                    }
                    busy_thread.fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
                    // The caller may be gone (an error on its side): nothing to give back.
                    let _ = to_caller.send(batch);
                }
                Ok(writer)
            })
            .expect("the writer thread starts");
        Self {
            to_writer: Some(to_writer),
            free,
            current: None,
            per_batch,
            rows,
            step_x,
            step_p,
            thread: Some(thread),
            busy,
        }
    }

    /// Hands the rows `(t, 1..N)` to the writer thread (see [`EstimatesWriter::write_step`]);
    /// steps must come in order. Waits while the thread is two batches behind; an error of
    /// the thread is returned here.
    pub fn write_step(
        &mut self,
        t: usize,
        x: &[f64],
        p: &[f64],
        band: Option<&SymBand>,
        values: RowValues<'_>,
    ) -> std::io::Result<()> {
        let mut batch = match self.current.take() {
            Some(batch) => batch,
            None => {
                let Ok(mut batch) = self.free.recv() else {
                    return Err(self.thread_error());
                };
                batch.first = t;
                batch.count = 0;
                batch
            }
        };
        let k = batch.count;
        batch.x[k * self.step_x..(k + 1) * self.step_x].copy_from_slice(x);
        batch.p[k * self.step_p..(k + 1) * self.step_p].copy_from_slice(p);
        if let (Some(dst), Some(src)) = (batch.bands.get_mut(k), band) {
            dst.copy_band_from(src);
        }
        let rows = k * self.rows..(k + 1) * self.rows;
        for (dst, src) in [
            (batch.arrival.get_mut(rows.clone()), values.arrival),
            (batch.nis.get_mut(rows), values.nis),
        ] {
            match (dst, src) {
                (Some(dst), Some(src)) => dst.copy_from_slice(src),
                (Some(dst), None) => dst.fill(f64::NAN),
                (None, _) => {}
            }
        }
        batch.count += 1;
        if batch.count < self.per_batch {
            self.current = Some(batch);
            return Ok(());
        }
        self.send(batch)
    }

    fn send(&mut self, batch: StepBatch) -> std::io::Result<()> {
        let sent = self
            .to_writer
            .as_ref()
            .is_some_and(|w| w.send(batch).is_ok());
        if sent {
            Ok(())
        } else {
            Err(self.thread_error())
        }
    }

    /// Waits for the thread and returns its error (it stopped early).
    fn thread_error(&mut self) -> std::io::Error {
        self.to_writer = None;
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(Err(e))) => e,
            _ => std::io::Error::other("the writer thread stopped"),
        }
    }

    /// Seconds the writer thread spent formatting and writing.
    fn busy_seconds(&self) -> f64 {
        self.busy.load(std::sync::atomic::Ordering::Relaxed) as f64 * 1e-9
    }

    /// Waits until every step is written; returns the writer and the seconds the thread
    /// spent formatting and writing.
    pub fn finish(mut self) -> std::io::Result<(EstimatesWriter<W>, f64)> {
        if let Some(batch) = self.current.take() {
            self.send(batch)?;
        }
        self.to_writer = None;
        let writer = match self.thread.take().expect("finish once").join() {
            Ok(result) => result?,
            Err(_) => return Err(std::io::Error::other("the writer thread panicked")),
        };
        Ok((writer, self.busy_seconds()))
    }
}

impl<W: Write + Send + 'static> Drop for BackgroundWriter<W> {
    /// On an error path: lets the thread end, so that its output is dropped uncommitted.
    fn drop(&mut self) {
        self.to_writer = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
