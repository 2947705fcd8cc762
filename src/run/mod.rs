//! A whole run, as every front end makes it (docs/theory.md §13): a [`RunSpec`] checked once
//! into a [`CheckedSpec`], which builds the filter or smoother it describes; then the run
//! itself, which takes the measurements and inputs step by step from a [`StepSource`], scores
//! the estimates against a truth when one is given, and hands each step's estimates to an
//! [`EstimateSink`] as soon as they are known.
//!
//! - [`stream`]: the run over any source, into any sink, with memory flat in `T` (but for the
//!   smoother, which keeps its forward pass);
//! - [`estimate`]: the run over arrays in memory, into arrays (a thin layer over [`stream`]).

pub mod hold_out;
mod score;
mod source;
pub mod spec;

use std::time::{Duration, Instant};

use crate::error::{Error, Result};
use crate::filter::{ChainFilter, Dropouts, FilterKind, check_estimates, reads_second_moment};
use crate::innovations::{InnovationCheck, InnovationReport};
use crate::interconnect::{ChainSolver, TRANSFER_ERROR_WARNING};
use crate::io::estimates::{EstimateKind, EstimatesSummary};
use crate::linalg::band::SymBand;
use crate::memory::human_bytes;
use crate::model::Model;
use crate::smoother::{Smoother, memory_bytes};
use crate::stability::{RadiusEffort, SpectralRadius, Stability, spectral_radius};

pub use hold_out::HoldOut;
use score::Scores;
pub use source::{
    ArraySource, FileSource, ReadAhead, ReaderTruth, SliceTruth, StepSource, TruthSource, read_all,
};
pub use spec::{CheckedSpec, RunSpec, Setting, SpecError, check_update};

/// Above this many lifted states a run skips its stability check (`check` still does it).
const STABILITY_CHECK_MAX: usize = 100_000;

/// A run that cannot go on for a reason its settings name (exit 2 on the command line).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunError {
    /// The smoother's stored forward pass outgrew `max_memory`.
    #[error(
        "smooth: the stored forward pass needs {} by t = {t} ({need} bytes), above max_memory {} ({limit} bytes); raise max_memory, or smooth a shorter file",
        human_bytes(*need),
        human_bytes(*limit)
    )]
    OverMaxMemory { t: usize, need: u64, limit: u64 },
    /// A truth was given, but no estimate could be scored against it.
    #[error(
        "truth: no step could be scored (with predicted, row t is scored against the truth at t + 1, and the measurements hold one step)"
    )]
    NothingScored,
}

/// What a run tells the user as it goes (a warning on a command line). Its text names the
/// run's settings; a front end may put it in its own words.
#[derive(Debug, Clone, PartialEq)]
pub enum Note {
    /// `Q = 0` on a coupled chain: the distributed filter takes the estimated interconnection
    /// signals as exact, so its `P` is far too small (docs/theory.md §4).
    OverconfidentDistributed,
    /// …and its smoother can be worse than the filter (docs/theory.md §9).
    OverconfidentDistributedSmoother,
    /// The spectral radius of `A_eff` is not below 1 from step `first` on: 1 within its bound,
    /// or above (docs/theory.md §3).
    Unstable {
        first: usize,
        spectral_radius: SpectralRadius,
    },
    /// The transfer solver's estimated relative error passed the warning level at `t`
    /// (docs/theory.md §2).
    InaccurateTransfer { error: f64, t: usize },
    /// What the smoother had to do, in its own words (docs/theory.md §9).
    Smoother(String),
}

impl std::fmt::Display for Note {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::OverconfidentDistributed => f.write_str(
                "Q = 0 on a coupled chain: the distributed filter treats the estimated interconnection signals as exact, so its reported covariance P is far too small (docs/theory.md §4); filter = joint keeps it honest (docs/theory.md §8)",
            ),
            Self::OverconfidentDistributedSmoother => f.write_str(
                "Q = 0: the per-subsystem smoother trusts x(t+1) = A x + B v̂ exactly and can be worse than its own filter (docs/theory.md §9); filter = joint with smooth is the remedy",
            ),
            Self::Unstable {
                first: 1,
                spectral_radius,
            } => f.write_str(&crate::check::instability(spectral_radius)),
            Self::Unstable {
                first,
                spectral_radius,
            } => write!(
                f,
                "from t = {first}, {}",
                crate::check::instability(spectral_radius)
            ),
            Self::InaccurateTransfer { error, t } => write!(
                f,
                "the transfer solver's estimated relative error is {error:.1e} (> {TRANSFER_ERROR_WARNING:e}) from t = {t} on: its interconnection signals are inaccurate; use solver = banded"
            ),
            Self::Smoother(note) => f.write_str(note),
        }
    }
}

/// One step's estimates, as a run hands them to its [`EstimateSink`]: `x̂` (`N·n`), the
/// diagonal blocks of `P` (`N·n²`, column-major blocks), the covariance band when the filter
/// keeps one (the joint filter), `π(t, ·)` with the mixture update, and the NIS of each
/// subsystem's measurement (`N` values, NaN where none was received; docs/theory.md §14).
#[derive(Clone, Copy)]
pub struct StepEstimates<'a> {
    pub t: usize,
    pub x: &'a [f64],
    pub p: &'a [f64],
    pub band: Option<&'a SymBand>,
    pub arrival: Option<&'a [f64]>,
    pub nis: &'a [f64],
}

/// Where a run's estimates go, step after step, and what the user should know.
pub trait EstimateSink {
    /// The estimates of one step; steps come in order.
    fn step(&mut self, step: &StepEstimates<'_>) -> Result<()>;
    /// A note for the user (a warning on a command line), as soon as it is known.
    fn note(&mut self, note: Note);
}

/// Wall-clock time a run spent in each phase: reading the inputs (source and truth), filtering,
/// scoring the innovations (docs/theory.md §14) and handing the estimates to the sink.
#[derive(Debug, Clone, Copy, Default)]
pub struct Timings {
    pub read: Duration,
    pub filter: Duration,
    /// The innovation check, which every run makes beside its filter: its running sums, and
    /// their set-up and report.
    pub check: Duration,
    pub write: Duration,
}

impl Timings {
    fn time<R>(slot: &mut Duration, f: impl FnOnce() -> R) -> R {
        let start = Instant::now();
        let r = f();
        *slot += start.elapsed();
        r
    }

    fn read<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.read, f)
    }

    fn filter<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.filter, f)
    }

    fn check<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.check, f)
    }

    /// Times `f` as time spent handing estimates on (a front end adds its own writing).
    pub fn write<R>(&mut self, f: impl FnOnce() -> R) -> R {
        Self::time(&mut self.write, f)
    }
}

/// What a run found besides its estimates.
#[derive(Debug, Clone)]
pub struct RunReport {
    /// The steps run, `1..=steps`.
    pub steps: usize,
    /// Accuracy and detection against the truth, when one was given; the log-likelihood of
    /// the measurements, when the filter has one; whether the measurements fit the model
    /// (docs/theory.md §14).
    pub summary: EstimatesSummary,
    pub timings: Timings,
}

/// Runs `spec` on `model` over the steps of `source`, scoring against `truth` when given, and
/// hands each step's estimates to `sink`: as each step is filtered, or with
/// `smooth` after the backward pass (docs/theory.md §9), which keeps the forward pass of every
/// step (refused once it would exceed `max_memory`). With `predicted`, row `t` holds
/// `x̂(t+1|t)`, `T(t+1)` and is scored against the truth at `t + 1`. The warnings a run
/// deserves (an untrustworthy covariance, an unstable chain, an inaccurate transfer solver,
/// what the smoother had to do) go to [`EstimateSink::note`]. With readings held out
/// ([`CheckedSpec::hold_out`]), the run is that of the data without them, and the report
/// scores its estimates on them (docs/theory.md §17).
pub fn stream(
    model: &Model,
    spec: &CheckedSpec,
    source: &mut dyn StepSource,
    truth: Option<&mut dyn TruthSource>,
    sink: &mut dyn EstimateSink,
) -> Result<RunReport> {
    match spec.hold_out() {
        Some(hold) => hold_out::stream_held_out(model, spec, hold, source, truth, sink),
        None => stream_all(model, spec, source, truth, sink),
    }
}

/// [`stream`] over every reading of `source`.
fn stream_all(
    model: &Model,
    spec: &CheckedSpec,
    source: &mut dyn StepSource,
    truth: Option<&mut dyn TruthSource>,
    sink: &mut dyn EstimateSink,
) -> Result<RunReport> {
    if spec.output() == EstimateKind::Smoothed {
        let smoother = advised(spec, model, sink, || spec.build_smoother(model))?;
        return run_smoother(model, spec, smoother, source, truth, sink);
    }
    let filter = advised(spec, model, sink, || spec.build_filter(model))?;
    let predicted = spec.output() == EstimateKind::Predicted;
    run_filter(model, spec, filter, predicted, source, truth, sink)
}

/// Builds a run's filter or smoother with `build` while its [`advice`] is worked out beside
/// it (the stability estimate and the setup are independent: side by side they take the
/// longer of the two instead of their sum), then hands the advice to `sink`.
fn advised<T: Send>(
    spec: &CheckedSpec,
    model: &Model,
    sink: &mut dyn EstimateSink,
    build: impl FnOnce() -> Result<T> + Send,
) -> Result<T> {
    let (notes, built) = rayon::join(|| advice(spec, model), build);
    notes?.into_iter().for_each(|note| sink.note(note));
    built
}

/// The innovation check of a run of `spec` (docs/theory.md §14).
fn innovation_check(model: &Model, spec: &CheckedSpec) -> InnovationCheck {
    InnovationCheck::new(
        model,
        spec.dropouts(),
        spec.update(),
        spec.filter_kind() == FilterKind::Distributed,
    )
}

/// The warnings a run of `spec` on `model` deserves before it starts: a distributed filter
/// whose covariance cannot be trusted, a chain that is not stable where readings may be lost
/// (with `p = 1` everywhere, or known dropouts, no filter weighs the second moment).
pub fn advice(spec: &CheckedSpec, model: &Model) -> Result<Vec<Note>> {
    let mut notes = Vec::new();
    if spec.filter_kind() == FilterKind::Distributed && model.q_is_zero() && model.is_coupled() {
        notes.push(Note::OverconfidentDistributed);
        if spec.output() == EstimateKind::Smoothed {
            notes.push(Note::OverconfidentDistributedSmoother);
        }
    }
    if spec.dropouts() == Dropouts::Unknown
        && model.loses_readings()
        && model.subsystems * model.dims.n <= STABILITY_CHECK_MAX
    {
        // One estimate per chain, which windows differing only in p or sensors share.
        let chains = (0..model.windows().len()).filter(|&k| model.first_window_of_chain(k) == k);
        for w in chains.map(|k| &model.windows()[k]) {
            let solver = ChainSolver::new(model, w.first)?;
            let rho = spectral_radius(model, w.first, &solver, RadiusEffort::DEFAULT);
            if rho.stability() != Stability::Stable {
                notes.push(Note::Unstable {
                    first: w.first,
                    spectral_radius: rho,
                });
                break;
            }
        }
    }
    Ok(notes)
}

/// The filtered (or predicted) run: each step is read, filtered, handed on and scored.
fn run_filter(
    model: &Model,
    spec: &CheckedSpec,
    mut filter: Box<dyn ChainFilter>,
    predicted: bool,
    source: &mut dyn StepSource,
    mut truth: Option<&mut dyn TruthSource>,
    sink: &mut dyn EstimateSink,
) -> Result<RunReport> {
    let (n, big_n) = (model.dims.n, model.subsystems);
    let mut y = vec![0.0; big_n * model.dims.q];
    let mut u = vec![0.0; big_n * model.dims.m];
    let mut x_true = vec![0.0; big_n * (n + 1)];
    let mut scores = Scores::new(n);
    let mut loglik = 0.0;
    // With predicted, row t is scored against the truth at t + 1.
    let (mut prev_x, mut prev_p) = (vec![0.0; big_n * n], vec![0.0; big_n * n * n]);
    let mut warned_transfer = false;
    let mut steps = 0;
    let mut timings = Timings::default();
    let mut check = timings.check(|| innovation_check(model, spec));
    // The second moments S the filter's gain reads, which standardise the innovations
    // (docs/theory.md §14): only Nahi's update has them.
    let mut moments = match reads_second_moment(spec.dropouts(), spec.update()) {
        true => vec![0.0; big_n * n * n],
        false => Vec::new(),
    };
    while let Some(t) = timings.read(|| source.next_step(&mut y, &mut u))? {
        model.blank_unmeasured(t, &mut y);
        let (mean, cov) = filter.predicted();
        let moment = filter
            .second_moments(&mut moments)
            .then_some(moments.as_slice());
        timings.check(|| check.step(t, mean, cov, moment, &y, &u))?;
        timings.filter(|| filter.step(&y, &u))?;
        loglik += filter.log_likelihood().unwrap_or(0.0);
        if !warned_transfer && filter.solver_error_estimate() > TRANSFER_ERROR_WARNING {
            warned_transfer = true;
            sink.note(Note::InaccurateTransfer {
                error: filter.solver_error_estimate(),
                t,
            });
        }
        let (x, p) = if predicted {
            filter.predicted()
        } else {
            filter.filtered()
        };
        check_estimates(t, n, x, p)?;
        let step = StepEstimates {
            t,
            x,
            p,
            band: filter.covariance_band(predicted).map(|(b, _)| b),
            arrival: filter.arrival(),
            nis: check.nis(),
        };
        timings.write(|| sink.step(&step))?;
        if let Some(truth) = truth.as_deref_mut() {
            timings.read(|| truth.read_truth(t, &mut x_true))?;
            let scored = match (predicted, t > 1) {
                (false, _) => Some((x, p)),
                (true, true) => Some((prev_x.as_slice(), prev_p.as_slice())),
                (true, false) => None,
            };
            // π(t, i) is scored against γ(t, i), whichever estimate row t holds.
            scores.add(&x_true, scored, filter.arrival());
            if predicted {
                prev_x.copy_from_slice(x);
                prev_p.copy_from_slice(p);
            }
        }
        steps = t;
    }
    timings.read(|| source.finish(steps))?;
    let summary = EstimatesSummary {
        loglik: filter.log_likelihood().map(|_| loglik),
        innovations: Some(timings.check(|| check.report())),
        ..scores.summary(truth.is_some(), filter.arrival().is_some())?
    };
    Ok(RunReport {
        steps,
        summary,
        timings,
    })
}

/// The smoothed run: the forward pass over every step (refused once its stored steps exceed
/// `max_memory`), the backward pass, then every row.
fn run_smoother(
    model: &Model,
    spec: &CheckedSpec,
    mut smoother: Box<dyn Smoother>,
    source: &mut dyn StepSource,
    mut truth: Option<&mut dyn TruthSource>,
    sink: &mut dyn EstimateSink,
) -> Result<RunReport> {
    let (n, big_n) = (model.dims.n, model.subsystems);
    let (kind, limit) = (spec.smoother_kind(), spec.max_memory());
    let mut y = vec![0.0; big_n * model.dims.q];
    let mut u = vec![0.0; big_n * model.dims.m];
    let mut truth_rows: Vec<Vec<f64>> = Vec::new();
    // The forward pass's π of every step (the mixture update) and its NIS: kept for the rows.
    let mut arrival: Vec<Vec<f64>> = Vec::new();
    let mut nis: Vec<f64> = Vec::new();
    let mut steps = 0;
    let mut timings = Timings::default();
    let mut check = timings.check(|| innovation_check(model, spec));
    // The second moments S the filter's gain reads, which standardise the innovations
    // (docs/theory.md §14): only Nahi's update has them.
    let mut moments = match reads_second_moment(spec.dropouts(), spec.update()) {
        true => vec![0.0; big_n * n * n],
        false => Vec::new(),
    };
    while let Some(t) = timings.read(|| source.next_step(&mut y, &mut u))? {
        model.blank_unmeasured(t, &mut y);
        let need = memory_bytes(model, kind, t);
        if need > limit {
            return Err(RunError::OverMaxMemory { t, need, limit }.into());
        }
        let (mean, cov) = smoother.prior();
        let moment = smoother
            .prior_second_moments(&mut moments)
            .then_some(moments.as_slice());
        timings.check(|| check.step(t, mean, cov, moment, &y, &u))?;
        timings.filter(|| smoother.step(&y, &u))?;
        nis.extend_from_slice(check.nis());
        if let Some(pi) = smoother.arrival() {
            arrival.push(pi.to_vec());
        }
        if let Some(truth) = truth.as_deref_mut() {
            let mut row = vec![0.0; big_n * (n + 1)];
            timings.read(|| truth.read_truth(t, &mut row))?;
            truth_rows.push(row);
        }
        steps = t;
    }
    timings.read(|| source.finish(steps))?;
    let smoothed = timings.filter(|| smoother.finish())?;
    for note in &smoothed.notes {
        sink.note(Note::Smoother(note.clone()));
    }
    let mut scores = Scores::new(n);
    for (idx, (x, p)) in smoothed.x.iter().zip(&smoothed.p).enumerate() {
        check_estimates(idx + 1, n, x, p)?;
        let step = StepEstimates {
            t: idx + 1,
            x,
            p,
            band: smoothed.bands.as_ref().map(|b| &b[idx]),
            arrival: arrival.get(idx).map(Vec::as_slice),
            nis: &nis[idx * big_n..(idx + 1) * big_n],
        };
        timings.write(|| sink.step(&step))?;
        if let Some(row) = truth_rows.get(idx) {
            scores.add(row, Some((x, p)), step.arrival);
        }
    }
    let innovations = timings.check(|| check.report());
    Ok(RunReport {
        steps,
        summary: EstimatesSummary {
            innovations: Some(innovations),
            ..scores.summary(truth.is_some(), !arrival.is_empty())?
        },
        timings,
    })
}

/// The estimates of a whole run, in memory ([`estimate`]): `x[t][i][·]` flattened as
/// `x[((t − 1) N + i − 1) n + k]`, and so on.
#[derive(Debug, Clone)]
pub struct Estimates {
    /// `T × N × n` values of `x̂`.
    pub x: Vec<f64>,
    /// `T × N × n × n` values: the diagonal blocks of `P`, each column-major.
    pub p: Vec<f64>,
    /// `T × N` values of `π(t, i)`, with the mixture update.
    pub arrival: Option<Vec<f64>>,
    /// `T × N` values of the NIS (NaN where nothing was received; docs/theory.md §14).
    pub nis: Vec<f64>,
    /// The steps, the log-likelihood, accuracy and detection against the truth.
    pub report: RunReport,
    /// What the user should know (the notes of [`stream`]).
    pub notes: Vec<Note>,
}

/// A source that asks `interrupt` before each step whether to stop.
struct Interruptible<'a, S> {
    source: S,
    interrupt: &'a mut dyn FnMut() -> Result<()>,
}

impl<S: StepSource> StepSource for Interruptible<'_, S> {
    fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>> {
        (self.interrupt)()?;
        self.source.next_step(y, u)
    }

    fn finish(&mut self, steps: usize) -> Result<()> {
        self.source.finish(steps)
    }
}

/// Gathers the steps of a run into [`Estimates`].
struct Collect {
    x: Vec<f64>,
    p: Vec<f64>,
    arrival: Option<Vec<f64>>,
    nis: Vec<f64>,
    notes: Vec<Note>,
}

impl EstimateSink for Collect {
    fn step(&mut self, step: &StepEstimates<'_>) -> Result<()> {
        self.x.extend_from_slice(step.x);
        self.p.extend_from_slice(step.p);
        self.nis.extend_from_slice(step.nis);
        if let Some(pi) = step.arrival {
            self.arrival
                // One value per subsystem and step, as the NIS.
                .get_or_insert_with(|| Vec::with_capacity(self.nis.capacity()))
                .extend_from_slice(pi);
        }
        Ok(())
    }

    fn note(&mut self, note: Note) {
        self.notes.push(note);
    }
}

/// The log density of each step's measurements given the steps before, `log p(y(t) | y(1..t−1))`
/// under `model`, as the filter of `spec` computes it (docs/theory.md §10: the mixture update's
/// `Σ_i log(p e^{ℓ₁} + (1 − p) e^{ℓ₀})`, or with known dropouts the Gaussian innovations
/// density of the elements received): `T` values, over measurements and inputs in memory as
/// [`estimate`] takes them. Nothing else of a run is done (no estimates kept, no checks, no
/// warnings): this is what `fit` evaluates hundreds of times (docs/theory.md §16). A filter
/// without a density (Nahi's linear update with unknown dropouts) is refused.
pub fn log_likelihood(
    model: &Model,
    spec: &CheckedSpec,
    y: &[f64],
    u: Option<&[f64]>,
) -> Result<Vec<f64>> {
    check_measurements(model, y)?;
    let mut source = ArraySource::new(model, y, u)?;
    let mut filter = spec.build_filter(model)?;
    let mut y_t = vec![0.0; model.subsystems * model.dims.q];
    let mut u_t = vec![0.0; model.subsystems * model.dims.m];
    let mut densities = Vec::with_capacity(y.len() / y_t.len().max(1));
    while let Some(t) = source.next_step(&mut y_t, &mut u_t)? {
        model.blank_unmeasured(t, &mut y_t);
        filter.step(&y_t, &u_t)?;
        densities.push(filter.log_likelihood().ok_or_else(|| {
            Error::Usage(
                "log-likelihood: the linear update with unknown dropouts has no density; use update = mixture or dropouts = known".into(),
            )
        })?);
    }
    source.finish(densities.len())?;
    Ok(densities)
}

/// Takes a run's estimates and notes and keeps nothing ([`innovation_report`]).
struct Discard;

impl EstimateSink for Discard {
    fn step(&mut self, _: &StepEstimates<'_>) -> Result<()> {
        Ok(())
    }

    fn note(&mut self, _: Note) {}
}

/// The innovation check (docs/theory.md §14) of a run of `spec` on arrays held in memory, as
/// [`estimate`] takes them, without keeping its estimates: whether the data fit `model`
/// (`fit` reports it of the fitted model).
pub fn innovation_report(
    model: &Model,
    spec: &CheckedSpec,
    y: &[f64],
    u: Option<&[f64]>,
) -> Result<Option<InnovationReport>> {
    check_measurements(model, y)?;
    let mut source = ArraySource::new(model, y, u)?;
    let report = stream(model, spec, &mut source, None, &mut Discard)?;
    Ok(report.summary.innovations)
}

/// Refuses a measurement that is neither a finite number nor NaN (an element not in the
/// data, docs/theory.md §15).
pub fn check_measurements(model: &Model, y: &[f64]) -> Result<()> {
    let Some(k) = y.iter().position(|v| v.is_infinite()) else {
        return Ok(());
    };
    let (q, big_n) = (model.dims.q, model.subsystems);
    Err(Error::Usage(format!(
        "y: t = {}, i = {}, element {}: expected a finite number or NaN (not in the data), found {}",
        k / (big_n * q) + 1,
        k / q % big_n + 1,
        k % q + 1,
        y[k]
    )))
}

/// Runs `spec` on `model` over measurements and inputs held in memory, the whole run into
/// memory: [`stream`] from an [`ArraySource`] (and a [`SliceTruth`]) into arrays.
///
/// `y` holds `T × N × q` values, step after step and subsystem after subsystem (NaN marks an
/// element not in the data, docs/theory.md §15); `u` holds `T × N × m` (`None`: the model's own inputs);
/// `truth`, when given, `T × N × (n + 1)`: each subsystem's states, then `γ`.
///
/// ```
/// use sisfilt::model::Model;
/// use sisfilt::run::{RunSpec, estimate};
///
/// let toml = r#"
///     subsystems = 3
///     steps = 4
///     [interconnection]
///     plus = 1
///     minus = 1
///     [model]
///     A = [[0.9]]
///     B = [[0.1, 0.1]]
///     D = [[0.5], [0.5]]
///     G = [[0.0, 0.0], [0.0, 0.0]]
///     J = [[1.0]]
///     M = [[0.05]]
///     Q = [[0.01]]
///     [dropout]
///     p = 0.8
///     [initial]
///     mean = [0.0]
///     cov = [[1.0]]
/// "#;
/// let model = Model::from_toml_str("chain.toml", std::path::Path::new("."), toml)?;
/// // Four steps of the three subsystems' measurements (q = 1).
/// let y = [0.1, 0.2, 0.3, 0.1, 0.0, 0.2, 0.2, 0.1, 0.1, 0.0, 0.3, 0.2];
/// let spec = RunSpec { filter: sisfilt::filter::FilterKind::Joint, ..RunSpec::default() };
/// let run = estimate(&model, &spec.check()?, &y, None, None)?;
/// assert_eq!(run.report.steps, 4);
/// assert_eq!(run.x.len(), 4 * 3); // T × N × n
/// assert!(run.p.iter().all(|&v| v.is_finite()));
/// # Ok::<(), sisfilt::Error>(())
/// ```
pub fn estimate(
    model: &Model,
    spec: &CheckedSpec,
    y: &[f64],
    u: Option<&[f64]>,
    truth: Option<&[f64]>,
) -> Result<Estimates> {
    estimate_interruptible(model, spec, y, u, truth, &mut || Ok(()))
}

/// [`estimate`], asking `interrupt` before each step is read whether to stop: its error
/// (e.g. [`Error::Interrupted`]) ends the run (a front end's Ctrl-C), also in a smoother's
/// forward pass (its backward pass is one call).
pub fn estimate_interruptible(
    model: &Model,
    spec: &CheckedSpec,
    y: &[f64],
    u: Option<&[f64]>,
    truth: Option<&[f64]>,
    interrupt: &mut dyn FnMut() -> Result<()>,
) -> Result<Estimates> {
    check_measurements(model, y)?;
    let mut source = Interruptible {
        source: ArraySource::new(model, y, u)?,
        interrupt,
    };
    let mut truth = truth.map(|t| SliceTruth::new(model, t)).transpose()?;
    // Room for every step at once: growing by doubling would copy and fault in twice the
    // memory (a third of a 10⁴-subsystem run's time beyond the filter).
    let (n, big_n) = (model.dims.n, model.subsystems);
    let steps = y.len() / (big_n * model.dims.q).max(1);
    let mut sink = Collect {
        x: Vec::with_capacity(steps * big_n * n),
        p: Vec::with_capacity(steps * big_n * n * n),
        arrival: None,
        nis: Vec::with_capacity(steps * big_n),
        notes: Vec::new(),
    };
    let report = stream(
        model,
        spec,
        &mut source,
        truth.as_mut().map(|t| t as &mut dyn TruthSource),
        &mut sink,
    )?;
    Ok(Estimates {
        x: sink.x,
        p: sink.p,
        arrival: sink.arrival,
        nis: sink.nis,
        report,
        notes: sink.notes,
    })
}
