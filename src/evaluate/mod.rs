//! Monte Carlo comparison of filters (docs/theory.md §4, §7, §13 `evaluate`): every filter runs on the
//! same simulated realisations; RMSE, RMSE ratio to the centralized Nahi filter (the optimal
//! linear estimator) and average NEES with its 95 % band are reported per filter.
//!
//! Run `r` (0-based) is simulated with seed `seed + r`. Runs execute in parallel (rayon), and
//! their sums are added in run order as they finish (memory holds the runs in flight, not
//! every run's), so every figure except the clock readings is the same for any thread count.
//!
//! A study may be cut into shards ([`evaluate_part`]): each runs its block of runs, with the
//! seeds the whole study gives them, and keeps the sums behind every figure ([`Part`]);
//! [`merge`] adds the parts in shard order and reports what one run of the whole study
//! reports (the same sums added in another grouping: equal to rounding, docs/theory.md §11).

use std::ops::Range;
use std::time::Instant;

use serde::{Deserialize, Serialize};

mod compared;
mod one_run;
mod shard;
mod table;

use compared::COMPARED;
pub use compared::Compared;
use one_run::{
    RunResult, Schedules, Scores, joint_options, make_filter, make_smoother, run_filters,
    smoother_schedule_bytes,
};
pub use shard::{MergeError, Part, Shard, Study, evaluate_part, merge};

use crate::accuracy::{AccuracyReport, DetectionReport};
use crate::error::{Error, Result};
use crate::filter::centralized::CentralizedLimits;
use crate::filter::joint::JointSchedule;
use crate::filter::{CentralizedSchedule, Update};
use crate::inputs::RunInputs;
use crate::memory::DEFAULT_MAX_MEMORY;
use crate::model::Model;
use crate::smoother::SmootherSchedule;

/// Settings of an evaluation that cannot serve, named by their fields (a front end may put
/// them in its own words).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EvaluateError {
    #[error("runs must be at least 1")]
    NoRuns,
    /// RMSE and ANEES over no terms would read as a perfect score.
    #[error(
        "burn_in = {burn_in} leaves no step to score: {config} has T = {steps} steps; choose a burn-in below T"
    )]
    NothingAfterBurnIn {
        burn_in: usize,
        config: String,
        steps: usize,
    },
    #[error("true_p: expected a probability in [0, 1], found {0}")]
    TrueP(f64),
    #[error("sweep_p: expected at least one value")]
    EmptySweep,
    #[error("sweep_p: expected probabilities in [0, 1], found {0}")]
    SweepP(f64),
    #[error(
        "shard {index}/{count}: expected a shard index below the count, and a count of at least 1"
    )]
    Shard { index: usize, count: usize },
    /// A shard with no run would be a part that says nothing.
    #[error("{count} shards of {runs} runs: expected at most one shard per run")]
    MoreShardsThanRuns { count: usize, runs: usize },
}

/// Settings of an evaluation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluateOptions {
    pub runs: usize,
    pub seed: u64,
    /// Time steps `t ≤ burn_in` are not scored.
    pub burn_in: usize,
    /// Largest lifted size `N·n` for the centralized filters.
    pub max_lifted: usize,
    /// The joint filter's `--band K`.
    pub band: usize,
    /// The joint filter's `--loading ε`; `None` for its default.
    #[serde(default)]
    pub loading: Option<f64>,
    /// The filters to run; empty means all filters, and the smoothers too with `smooth`.
    pub filters: Vec<Compared>,
    /// Also run the smoothers (docs/theory.md §9).
    pub smooth: bool,
    /// Simulate with this arrival probability at every `(t, i)` while the filters keep the
    /// config's `p`: what a wrong `p` costs each filter.
    #[serde(default)]
    pub true_p: Option<f64>,
    /// The memory each filter may hold ([`crate::memory`]); a filter above it is skipped with
    /// a note.
    #[serde(default = "default_max_memory")]
    pub max_memory: u64,
}

fn default_max_memory() -> u64 {
    DEFAULT_MAX_MEMORY
}

impl EvaluateOptions {
    /// `runs` runs from `seed`, every other setting at its default: all filters, no smoothers,
    /// no burn-in, the default `max_lifted`, band, loading and `max_memory`.
    pub fn new(runs: usize, seed: u64) -> Self {
        Self {
            runs,
            seed,
            burn_in: 0,
            max_lifted: crate::filter::centralized::DEFAULT_MAX_LIFTED,
            band: crate::filter::joint::DEFAULT_BAND,
            loading: None,
            filters: Vec::new(),
            smooth: false,
            true_p: None,
            max_memory: DEFAULT_MAX_MEMORY,
        }
    }

    /// `R runs (seeds s..s+R−1)`, for the tables' first line.
    pub(crate) fn runs_and_seeds(&self) -> String {
        let last = self.seed.wrapping_add(self.runs as u64 - 1);
        format!("{} runs (seeds {}..{last})", self.runs, self.seed)
    }
}

/// The figures of one filter over all runs.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FilterResult {
    pub name: Compared,
    /// What the filter is.
    pub description: String,
    /// `None` when the filter ran; else why it was skipped or failed.
    pub skipped: Option<String>,
    pub accuracy: Option<AccuracyReport>,
    /// Overall RMSE divided by the centralized Nahi filter's (for a smoother: by the
    /// centralized smoother's).
    pub rmse_ratio: Option<f64>,
    /// For a smoother: overall RMSE divided by the centralized (optimal) filter's.
    pub rmse_ratio_to_filter: Option<f64>,
    /// With the mixture update: how well `π(t, i)` tells lost measurements from received
    /// ones, over every run and scored `(t, i)`.
    #[serde(default)]
    pub detection: Option<DetectionReport>,
    /// Time spent in this filter, summed over runs (seconds).
    pub wall_time_s: f64,
    /// The average NEES at each time step `t = 1..T` over runs and subsystems (`null` where
    /// infinite or where every term fell under the resolution floor, or before the burn-in).
    pub nees_per_step: Vec<Option<f64>>,
    /// What the user should know about this filter's run (e.g. the joint smoother ran again
    /// with a larger loading), printed as warnings.
    pub notes: Vec<String>,
}

/// The result of an evaluation: the JSON of `evaluate --out`, which `plot evaluate` reads.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Evaluation {
    pub sisfilt_version: String,
    pub config: String,
    pub options: EvaluateOptions,
    pub subsystems: usize,
    pub steps: usize,
    pub filters: Vec<FilterResult>,
    /// Time of the whole evaluation (seconds).
    pub total_wall_time_s: f64,
}

/// How a filter's note starts when it broke down in some run (its row says "failed").
pub(crate) const FAILED: &str = "failed: ";

/// Largest simulated realisation `evaluate` keeps in memory (one per thread at a time): a
/// `steps` far too large is refused rather than aborting the process on allocation.
const MAX_REALISATION_BYTES: usize = 1 << 30;

/// Largest centralized schedule `evaluate` keeps in memory; above it the centralized filter
/// runs in full for every run.
const MAX_SCHEDULE_BYTES: usize = 1 << 30;

/// The sums of one filter over some of a study's runs: what a [`Part`] carries, and what the
/// parts of a study add up to.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FilterSums {
    pub name: Compared,
    /// Why it did not run, or its first failure among these runs (`failed: run r, …`).
    pub skipped: Option<String>,
    /// RMSE per state element, NEES overall, per run and per step, detection.
    scores: Scores,
    /// Time spent in it over these runs (seconds).
    pub wall_time_s: f64,
    /// What its covariance schedule noted (the same in every part).
    pub notes: Vec<String>,
}

/// The sums of every selected filter, in table order, over some of a study's runs.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StudySums {
    pub filters: Vec<FilterSums>,
    /// Time of these runs and their set-up (seconds).
    pub wall_time_s: f64,
}

impl StudySums {
    /// Adds the sums of the runs that follow these (the next part): the first failure in
    /// run order is the one reported.
    fn add(&mut self, later: &StudySums) {
        for (sums, later) in self.filters.iter_mut().zip(&later.filters) {
            sums.scores.merge(&later.scores);
            sums.wall_time_s += later.wall_time_s;
            if sums.skipped.is_none() {
                sums.skipped.clone_from(&later.skipped);
            }
        }
        self.wall_time_s += later.wall_time_s;
    }
}

/// Checks the options of an evaluation against `model`; its `T`.
fn checked_steps(model: &Model, opts: &EvaluateOptions) -> Result<usize> {
    let steps = model.horizon()?;
    if opts.runs == 0 {
        return Err(EvaluateError::NoRuns.into());
    }
    if opts.burn_in >= steps {
        return Err(EvaluateError::NothingAfterBurnIn {
            burn_in: opts.burn_in,
            config: model.name.clone(),
            steps,
        }
        .into());
    }
    if let Some(p) = opts.true_p.filter(|p| !(0.0..=1.0).contains(p)) {
        return Err(EvaluateError::TrueP(p).into());
    }
    joint_options(opts)?;
    let d = model.dims;
    // x, y, y with the losses marked, u, and a vector header for each, per step.
    let per_step = (model.subsystems * (d.n + 2 * d.q + d.m) + 12) * std::mem::size_of::<f64>();
    let realisation_bytes = (steps as f64) * (per_step as f64);
    if realisation_bytes > MAX_REALISATION_BYTES as f64 {
        return Err(Error::Config {
            file: model.name.clone(),
            key: "steps".into(),
            msg: format!(
                "evaluate keeps every step of a run in memory: {} steps need about {realisation_bytes:.1e} bytes per run, expected at most {MAX_REALISATION_BYTES}",
                steps
            ),
        });
    }
    Ok(steps)
}

/// The values of `--sweep-p`, checked.
fn check_sweep(values: &[f64]) -> Result<()> {
    if values.is_empty() {
        return Err(EvaluateError::EmptySweep.into());
    }
    if let Some(&bad) = values.iter().find(|p| !(0.0..=1.0).contains(*p)) {
        return Err(EvaluateError::SweepP(bad).into());
    }
    Ok(())
}

/// The inputs `u(t)` of every run, `t = 1..T`: the same in every run.
fn run_inputs(model: &Model, inputs: &RunInputs, steps: usize) -> Result<Vec<Vec<f64>>> {
    let mut stream = inputs.stream();
    let mut u = vec![vec![0.0; model.subsystems * model.dims.m]; steps];
    for (t, ut) in u.iter_mut().enumerate() {
        stream.next(t + 1, ut)?;
    }
    Ok(u)
}

/// Runs `runs` of the study (checked options, `T = steps`, the inputs `u` of every run, from
/// [`run_inputs`]) and adds up their sums in run order; `tick` is called once per finished run.
fn tally(
    model: &Model,
    inputs: &RunInputs,
    opts: &EvaluateOptions,
    steps: usize,
    u: &[Vec<f64>],
    runs: Range<usize>,
    tick: impl Fn() -> Result<()> + Sync,
) -> Result<StudySums> {
    let start = Instant::now();
    let truth = opts.true_p.map(|p| model.with_arrival_probability(p));
    let truth = truth.as_ref().unwrap_or(model);
    let selected: Vec<bool> = Compared::all()
        .map(|f| {
            if opts.filters.is_empty() {
                opts.smooth || !f.is_smoother()
            } else {
                opts.filters.contains(&f)
            }
        })
        .collect();
    // A filter that cannot be built for this model (too large, G22 singular) is skipped.
    let none = Schedules::default();
    let mut skipped: Vec<Option<String>> = Compared::all()
        .zip(&selected)
        .map(|(name, &chosen)| {
            if !chosen {
                return Some("not selected".to_string());
            }
            if name.is_smoother() {
                make_smoother(model, name, opts).err()
            } else {
                make_filter(model, name, opts, &none).err()
            }
            .map(|e| match e {
                Error::TransferSolver { .. } => format!(
                    "{e}: the paper's filter runs on the transfer solver; the other two-step rows use the banded one"
                ),
                e => format!("{e}"),
            })
        })
        .collect();
    let active: Vec<bool> = skipped.iter().map(Option::is_none).collect();
    // The unknown-dropout covariance passes of the centralized and the joint filter do not
    // depend on the data (the inputs are the same in every run): compute them once.
    // A smoother replays the means of its filter, so that filter's schedule is needed too.
    // A pass that breaks down is left to the runs, which report the error as that filter's
    // failure (run, t, i) while the others complete.
    let needed = |filter: Compared| {
        Compared::all().any(|f| active[f.index()] && f.smooths().unwrap_or(f) == filter)
    };
    let joint_opts = joint_options(opts)?;
    let mut schedules = Schedules {
        centralized: (needed(Compared::Centralized)
            && CentralizedSchedule::bytes(model, steps) <= MAX_SCHEDULE_BYTES)
            .then(|| {
                let limits = CentralizedLimits {
                    max_lifted: opts.max_lifted,
                    max_memory: opts.max_memory,
                };
                CentralizedSchedule::new(model, u, limits).ok()
            })
            .flatten(),
        joint: (needed(Compared::Joint)
            && JointSchedule::bytes(model, opts.band, steps) <= MAX_SCHEDULE_BYTES)
            .then(|| JointSchedule::new(model, joint_opts, u).ok())
            .flatten(),
        smoothers: Vec::new(),
    };
    for name in Compared::all() {
        let k = name.index();
        // A smoother whose backward pass fails is left to the runs, which report the error.
        // The two-step filter's covariances depend on the data (its local moment propagates
        // the realised `B v̂`, docs/theory.md §4), and so do the mixture update's (its `π`):
        // those smoothers run in full every time.
        let schedule = if active[k]
            && name.is_smoother()
            && name != Compared::DistributedSmoother
            && name.update() == Update::Linear
            && smoother_schedule_bytes(model, name, opts)? <= MAX_SCHEDULE_BYTES as f64
        {
            SmootherSchedule::new(make_smoother(model, name, opts)?, model, u).ok()
        } else {
            None
        };
        schedules.smoothers.push(schedule);
    }
    let mut sums: Vec<Scores> = (0..COMPARED).map(|_| Scores::new(model, steps)).collect();
    let mut times = [0.0; COMPARED];
    let mut first_failure = None;
    in_run_order(
        runs,
        |r| {
            let res = run_filters(model, inputs, truth, opts, &active, &schedules, r);
            tick()?;
            res
        },
        |run: RunResult| {
            for (k, (res, time)) in run.into_iter().enumerate() {
                times[k] += time;
                match res {
                    Some(Ok(scores)) => sums[k].merge(&scores),
                    Some(Err(e)) if skipped[k].is_none() => {
                        skipped[k] = Some(format!("{FAILED}{e}"));
                        first_failure.get_or_insert(e);
                    }
                    _ => {}
                }
            }
        },
    )?;
    // A table of failures says less than the first of them.
    if let Some(e) = first_failure
        && (0..COMPARED).all(|k| !active[k] || skipped[k].is_some())
    {
        return Err(e);
    }
    let filters = Compared::all()
        .zip(sums)
        .filter(|(f, _)| selected[f.index()])
        .map(|(name, scores)| {
            let k = name.index();
            FilterSums {
                name,
                skipped: skipped[k].take(),
                scores,
                wall_time_s: times[k],
                notes: schedules
                    .smoothers
                    .get(k)
                    .and_then(Option::as_ref)
                    .map_or_else(Vec::new, |s| s.notes.clone()),
            }
        })
        .collect();
    Ok(StudySums {
        filters,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// Runs `run(r)` for every `r` in `runs` on the threads of rayon's pool, handing the runs out
/// in order, and gives each result to `add` in run order as soon as the runs before it have
/// been added: memory holds the runs in flight and the few that finished ahead of a slower
/// one, not every run's result, and what `add` sees does not depend on the thread count. The
/// first error stops the handing out; the runs in flight finish.
fn in_run_order<T: Send>(
    runs: Range<usize>,
    run: impl Fn(usize) -> Result<T> + Sync,
    add: impl FnMut(T) + Send,
) -> Result<()> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

    /// The next run to add, the results that came before their turn, the first error.
    struct Ordered<T, F> {
        next: usize,
        early: std::collections::BTreeMap<usize, T>,
        error: Option<Error>,
        add: F,
    }
    let handed_out = AtomicUsize::new(runs.start);
    let stopped = AtomicBool::new(false);
    let ordered = Mutex::new(Ordered {
        next: runs.start,
        early: Default::default(),
        error: None,
        add,
    });
    rayon::scope(|scope| {
        for _ in 0..rayon::current_num_threads() {
            scope.spawn(|_| {
                while !stopped.load(Ordering::Relaxed) {
                    let r = handed_out.fetch_add(1, Ordering::Relaxed);
                    if r >= runs.end {
                        break;
                    }
                    let result = run(r);
                    let mut guard = ordered.lock().expect("no run panicked while adding");
                    let o = &mut *guard;
                    match result {
                        Ok(value) => {
                            o.early.insert(r, value);
                            while let Some(value) = o.early.remove(&o.next) {
                                (o.add)(value);
                                o.next += 1;
                            }
                        }
                        Err(e) => {
                            stopped.store(true, Ordering::Relaxed);
                            o.error.get_or_insert(e);
                        }
                    }
                }
            });
        }
    });
    let ordered = ordered.into_inner().expect("no run panicked while adding");
    ordered.error.map_or(Ok(()), Err)
}

/// The figures of a study from the sums of all its runs.
fn evaluation(
    config: &str,
    subsystems: usize,
    steps: usize,
    opts: EvaluateOptions,
    sums: StudySums,
) -> Evaluation {
    let reports: Vec<(Compared, Option<AccuracyReport>)> = sums
        .filters
        .iter()
        .map(|f| {
            (
                f.name,
                f.skipped.is_none().then(|| f.scores.accuracy.report()),
            )
        })
        .collect();
    let rmse = |f: Compared| {
        let (_, report) = reports.iter().find(|(name, _)| *name == f)?;
        Some(report.as_ref()?.rmse_overall)
    };
    let ratio = |f: Compared, to: Compared| Some(rmse(f)? / rmse(to)?);
    let filters = sums
        .filters
        .into_iter()
        .zip(reports.iter().map(|(_, r)| r.clone()))
        .map(|(f, accuracy)| {
            let name = f.name;
            let ran = f.skipped.is_none();
            FilterResult {
                name,
                description: name.description().to_string(),
                rmse_ratio: ratio(name, name.reference()),
                rmse_ratio_to_filter: name
                    .is_smoother()
                    .then(|| ratio(name, Compared::Centralized))
                    .flatten(),
                accuracy,
                detection: (ran && name.update() == Update::Mixture)
                    .then(|| f.scores.detection.report()),
                wall_time_s: f.wall_time_s,
                nees_per_step: if ran {
                    f.scores.per_step.averages()
                } else {
                    Vec::new()
                },
                notes: f
                    .notes
                    .into_iter()
                    .chain(f.scores.first_note.as_ref().map(|note| {
                        format!(
                            "{} of {} runs; the first: {note}",
                            f.scores.noted_runs, opts.runs
                        )
                    }))
                    .collect(),
                skipped: f.skipped,
            }
        })
        .collect();
    Evaluation {
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        config: config.to_string(),
        subsystems,
        steps,
        options: opts,
        filters,
        total_wall_time_s: sums.wall_time_s,
    }
}

/// Runs the Monte Carlo comparison with the inputs `inputs` in every run (at least `T` steps of
/// them); `tick` is called once per finished run, and an error it returns (an interrupt)
/// stops the study once the runs in progress finish.
pub fn evaluate(
    model: &Model,
    inputs: &RunInputs,
    config: &str,
    opts: EvaluateOptions,
    tick: impl Fn() -> Result<()> + Sync,
) -> Result<Evaluation> {
    let start = Instant::now();
    let steps = checked_steps(model, &opts)?;
    let u = run_inputs(model, inputs, steps)?;
    let mut sums = tally(model, inputs, &opts, steps, &u, 0..opts.runs, tick)?;
    sums.wall_time_s = start.elapsed().as_secs_f64();
    Ok(evaluation(config, model.subsystems, steps, opts, sums))
}

/// `evaluate --sweep-p`: one evaluation per arrival probability, each on the same seeds (the
/// JSON of `evaluate --sweep-p --out`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Sweep {
    pub sisfilt_version: String,
    pub config: String,
    pub options: EvaluateOptions,
    pub subsystems: usize,
    pub steps: usize,
    /// The arrival probabilities in the order given; each replaces `p` at every `(t, i)`.
    pub sweep_p: Vec<f64>,
    /// One evaluation per value of `sweep_p`.
    pub evaluations: Vec<Evaluation>,
    /// Time of the whole sweep (seconds).
    pub total_wall_time_s: f64,
}

/// Runs [`evaluate`] once per arrival probability in `values`, each replacing the config's `p`
/// everywhere ([`Model::with_arrival_probability`]): in the simulation and in the filters, or
/// with `opts.true_p` in the filters only; `tick` is called once per finished run (as
/// [`evaluate`] calls it).
pub fn sweep_p(
    model: &Model,
    inputs: &RunInputs,
    config: &str,
    opts: EvaluateOptions,
    values: &[f64],
    tick: impl Fn() -> Result<()> + Sync,
) -> Result<Sweep> {
    let start = Instant::now();
    check_sweep(values)?;
    let evaluations = values
        .iter()
        .map(|&p| {
            evaluate(
                &model.with_arrival_probability(p),
                inputs,
                config,
                opts.clone(),
                &tick,
            )
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Sweep {
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        config: config.to_string(),
        options: opts,
        subsystems: model.subsystems,
        steps: model.horizon()?,
        sweep_p: values.to_vec(),
        evaluations,
        total_wall_time_s: start.elapsed().as_secs_f64(),
    })
}
