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
mod table;

use compared::COMPARED;
pub use compared::Compared;

use crate::accuracy::{Accuracy, AccuracyReport, Detection, DetectionReport};
use crate::error::{Error, Result};
use crate::filter::centralized::CentralizedLimits;
use crate::filter::joint::{JointSchedule, ScheduledJoint};
use crate::filter::{
    CentralizedSchedule, ChainFilter, JointFilter, JointOptions, ScheduledCentralized, Update,
    check_estimates,
};
use crate::inputs::RunInputs;
use crate::memory::DEFAULT_MAX_MEMORY;
use crate::model::Model;
use crate::simulate::simulate;
use crate::smoother::{Smoother, SmootherSchedule};

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

/// Parts that do not add up to one study ([`merge`]); each names the parts by the names the
/// caller gave them (their files).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MergeError {
    #[error("no parts to merge")]
    NoParts,
    #[error("{part}: not a part of the same study as {first}: {what}")]
    Foreign {
        part: String,
        first: String,
        what: String,
    },
    /// Its shard, runs and sums do not go together (a file edited by hand, or damaged).
    #[error("{part}: not a part written by `evaluate --shard`: {what}")]
    NotAPart { part: String, what: String },
    #[error("{part} and {other} are both shard {shard}")]
    Duplicate {
        part: String,
        other: String,
        shard: Shard,
    },
    /// `shards` lists the first few that are missing, and how many more.
    #[error("missing from the study: {shards} (given: {given})")]
    Missing { shards: String, given: String },
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

/// One simulated realisation, kept in memory for all filters.
struct Realisation {
    x: Vec<Vec<f64>>,
    y: Vec<Vec<f64>>,
    y_known: Vec<Vec<f64>>,
    u: Vec<Vec<f64>>,
    /// `γ(t, i)`: 1 where the measurement arrived, 0 where it was lost.
    gamma: Vec<Vec<f64>>,
}

fn realise(model: &Model, inputs: &RunInputs, seed: u64) -> Result<Realisation> {
    let q = model.dims.q;
    let mut r = Realisation {
        x: vec![],
        y: vec![],
        y_known: vec![],
        u: vec![],
        gamma: vec![],
    };
    simulate(model, model.horizon()?, seed, &mut inputs.stream(), |s| {
        r.x.push(s.x.to_vec());
        r.y.push(s.y.to_vec());
        let mut yk = s.y.to_vec();
        for (i, &g) in s.gamma.iter().enumerate() {
            if !g {
                yk[i * q..(i + 1) * q].fill(f64::NAN);
            }
        }
        r.y_known.push(yk);
        r.u.push(s.u.to_vec());
        r.gamma
            .push(s.gamma.iter().map(|&g| f64::from(u8::from(g))).collect());
        Ok(())
    })?;
    Ok(r)
}

/// How a filter's note starts when it broke down in some run (its row says "failed").
pub(crate) const FAILED: &str = "failed: ";

/// Largest simulated realisation `evaluate` keeps in memory (one per thread at a time): a
/// `steps` far too large is refused rather than aborting the process on allocation.
const MAX_REALISATION_BYTES: usize = 1 << 30;

/// Largest centralized schedule `evaluate` keeps in memory; above it the centralized filter
/// runs in full for every run.
const MAX_SCHEDULE_BYTES: usize = 1 << 30;

/// The covariance passes computed once for all runs (docs/theory.md §7, §8, §9).
#[derive(Default)]
struct Schedules {
    centralized: Option<CentralizedSchedule>,
    joint: Option<JointSchedule>,
    /// Per [`Compared::index`], for the smoothers: the gains and covariances of the backward
    /// pass.
    smoothers: Vec<Option<SmootherSchedule>>,
}

/// Bytes the schedule of the centralized or joint smoother needs: its gains and the diagonal
/// blocks of `P(t|T)` per step (for `joint`, the factor of `𝒥` with blocks `2n × 2n` and
/// bandwidth `κ = k + 2b` with the inverses of its diagonal blocks, and `Λˢ(t+1)` with band
/// `k`; `b` is the first step's).
fn smoother_schedule_bytes(
    model: &Model,
    smoother: Compared,
    opts: &EvaluateOptions,
) -> Result<f64> {
    let (n, big_n) = (model.dims.n as f64, model.subsystems as f64);
    let per_step = match smoother {
        Compared::CentralizedSmoother => (big_n * n).powi(2) + big_n * n * n,
        _ => {
            let filter = JointFilter::new(model, joint_options(opts)?)?;
            let k = filter.band();
            let kappa = (k + 2 * filter.a_eff_half_width()).min(model.subsystems - 1) as f64;
            big_n * ((kappa + 2.0) * 4.0 * n * n + (k as f64 + 2.0) * n * n)
        }
    };
    Ok(8.0 * per_step * model.horizon()? as f64)
}

/// The options of the `joint` row, checked.
fn joint_options(opts: &EvaluateOptions) -> Result<JointOptions> {
    let spec = Compared::Joint.spec(opts).check()?;
    Ok(spec
        .joint_options()
        .expect("the joint row runs the joint filter"))
}

/// The filter `filter`, or for a smoother the filter it smooths (whose means it replays).
fn make_filter<'s>(
    model: &Model,
    filter: Compared,
    opts: &EvaluateOptions,
    schedules: &'s Schedules,
) -> Result<Box<dyn ChainFilter + 's>> {
    let filter = filter.smooths().unwrap_or(filter);
    Ok(match (filter, &schedules.centralized, &schedules.joint) {
        (Compared::Centralized, Some(s), _) => Box::new(ScheduledCentralized::new(s)),
        (Compared::Joint, _, Some(s)) => Box::new(ScheduledJoint::new(s)?),
        _ => filter.spec(opts).check()?.build_filter(model)?,
    })
}

/// The NEES sums of one filter at each time step (see [`Accuracy::nees_totals`]).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct StepNees {
    #[serde(with = "crate::io::json_number::many")]
    sum: Vec<f64>,
    terms: Vec<u64>,
    infinite: Vec<u64>,
}

impl StepNees {
    fn new(steps: usize) -> Self {
        Self {
            sum: vec![0.0; steps],
            terms: vec![0; steps],
            infinite: vec![0; steps],
        }
    }

    fn merge(&mut self, other: &StepNees) {
        for t in 0..self.sum.len() {
            self.sum[t] += other.sum[t];
            self.terms[t] += other.terms[t];
            self.infinite[t] += other.infinite[t];
        }
    }

    fn is_of(&self, steps: usize) -> bool {
        [self.sum.len(), self.terms.len(), self.infinite.len()] == [steps; 3]
    }

    fn averages(&self) -> Vec<Option<f64>> {
        (0..self.sum.len())
            .map(|t| {
                (self.infinite[t] == 0 && self.terms[t] > 0)
                    .then(|| self.sum[t] / self.terms[t] as f64)
            })
            .collect()
    }
}

/// The smoother `smoother` (one of the [`Compared`] smoothers).
fn make_smoother(
    model: &Model,
    smoother: Compared,
    opts: &EvaluateOptions,
) -> Result<Box<dyn Smoother>> {
    smoother.spec(opts).check()?.build_smoother(model)
}

/// The sums of one filter over one run or several.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Scores {
    accuracy: Accuracy,
    per_step: StepNees,
    /// Filled by the mixture rows only.
    detection: Detection,
    /// The runs whose smoother left a note (e.g. it reran with a larger loading), and the
    /// first of those notes.
    noted_runs: usize,
    first_note: Option<String>,
}

impl Scores {
    fn new(model: &Model, steps: usize) -> Self {
        Self {
            accuracy: Accuracy::new(model.dims.n),
            per_step: StepNees::new(steps),
            detection: Detection::default(),
            noted_runs: 0,
            first_note: None,
        }
    }

    /// Adds the sums of later runs (of one closed run, [`Accuracy::close_run`], or of a part).
    fn merge(&mut self, other: &Scores) {
        self.accuracy.merge(&other.accuracy);
        self.per_step.merge(&other.per_step);
        self.detection.merge(&other.detection);
        self.noted_runs += other.noted_runs;
        if self.first_note.is_none() {
            self.first_note.clone_from(&other.first_note);
        }
    }
}

/// Per run and filter: the sums, or the error that stopped the filter, and the time.
/// Per filter: `None` where it is not active, else its scores or its failure, and its time.
type RunResult = Vec<(Option<Result<Scores>>, f64)>;

/// Run `r`: one realisation of `truth` (the model, or with `--true-p` the model simulated
/// with another `p`) and every active filter of `model` on it.
fn run_filters(
    model: &Model,
    inputs: &RunInputs,
    truth: &Model,
    opts: &EvaluateOptions,
    active: &[bool],
    schedules: &Schedules,
    r: usize,
) -> Result<RunResult> {
    let in_run = |error| Error::InRun {
        run: r + 1,
        error: Box::new(error),
    };
    let data = realise(truth, inputs, opts.seed.wrapping_add(r as u64)).map_err(in_run)?;
    let (n, big_n) = (model.dims.n, model.subsystems);
    let mut out = Vec::with_capacity(COMPARED);
    for name in Compared::all() {
        let k = name.index();
        if !active[k] {
            out.push((None, 0.0));
            continue;
        }
        let start = Instant::now();
        let result = (|| -> Result<Scores> {
            let mut acc = Accuracy::new(n);
            let mut per_step = StepNees::new(model.horizon()?);
            let mut detection = Detection::default();
            let mut first_note = None;
            let mut score =
                |t: usize, x_hat: &[f64], p_hat: &[f64], arrival: Option<&[f64]>| -> Result<()> {
                    check_estimates(t + 1, n, x_hat, p_hat)?;
                    if t < opts.burn_in {
                        return Ok(());
                    }
                    for (&pi, &gamma) in arrival.unwrap_or_default().iter().zip(&data.gamma[t]) {
                        detection.add(pi, gamma);
                    }
                    let (sum, terms, infinite) = acc.nees_totals();
                    for i in 0..big_n {
                        acc.add(
                            &data.x[t][i * n..(i + 1) * n],
                            &x_hat[i * n..(i + 1) * n],
                            &p_hat[i * n * n..(i + 1) * n * n],
                        );
                    }
                    let (sum_now, terms_now, infinite_now) = acc.nees_totals();
                    per_step.sum[t] = sum_now - sum;
                    per_step.terms[t] = terms_now - terms;
                    per_step.infinite[t] = infinite_now - infinite;
                    Ok(())
                };
            if let Some(schedule) = schedules.smoothers.get(k).and_then(Option::as_ref) {
                // The filter's means, then the stored backward gains (docs/theory.md §9).
                let mut f = match schedule.forward {
                    Some(opts) => Box::new(JointFilter::new(model, opts)?),
                    None => make_filter(model, name, opts, schedules)?,
                };
                let (mut x_filt, mut x_pred) = (Vec::new(), Vec::new());
                for t in 0..data.y.len() {
                    f.step(&data.y[t], &data.u[t])?;
                    x_filt.push(f.filtered().0.to_vec());
                    x_pred.push(f.predicted().0.to_vec());
                }
                let xs = schedule.smooth_means(model, &x_filt, &x_pred);
                for t in 0..xs.len() {
                    score(t, &xs[t], &schedule.p[t], None)?;
                }
            } else if name.is_smoother() {
                let mut s = make_smoother(model, name, opts)?;
                // The forward pass's π, which the smoother keeps (docs/theory.md §10).
                let mut arrival = Vec::new();
                for t in 0..data.y.len() {
                    s.step(&data.y[t], &data.u[t])?;
                    if let Some(pi) = s.arrival() {
                        arrival.push(pi.to_vec());
                    }
                }
                let smoothed = s.finish()?;
                for t in 0..data.y.len() {
                    let pi = arrival.get(t).map(Vec::as_slice);
                    score(t, &smoothed.x[t], &smoothed.p[t], pi)?;
                }
                first_note = smoothed.notes.into_iter().next();
            } else {
                let mut f = make_filter(model, name, opts, schedules)?;
                let ys = if name == Compared::CentralizedKnown {
                    &data.y_known
                } else {
                    &data.y
                };
                for t in 0..ys.len() {
                    f.step(&ys[t], &data.u[t])?;
                    let (x_hat, p_hat) = f.filtered();
                    score(t, x_hat, p_hat, f.arrival())?;
                }
            }
            acc.close_run();
            Ok(Scores {
                accuracy: acc,
                per_step,
                detection,
                noted_runs: usize::from(first_note.is_some()),
                first_note,
            })
        })();

        out.push((Some(result.map_err(in_run)), start.elapsed().as_secs_f64()));
    }
    Ok(out)
}

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

/// Which of a study's `R` runs a part holds: shard `index` of `count` (from 0), the runs
/// `⌊index·R/count⌋ ..= ⌊(index+1)·R/count⌋ − 1`, with the seeds the whole study gives them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    /// The whole study as one part.
    pub const WHOLE: Shard = Shard { index: 0, count: 1 };

    pub fn new(index: usize, count: usize) -> Result<Shard, EvaluateError> {
        if index < count {
            Ok(Shard { index, count })
        } else {
            Err(EvaluateError::Shard { index, count })
        }
    }

    /// Its runs (0-based) among `total`.
    pub fn runs(self, total: usize) -> Range<usize> {
        let at = |k: usize| (k as u128 * total as u128 / self.count as u128) as usize;
        at(self.index)..at(self.index + 1)
    }
}

/// `K/M`, as `--shard` takes it.
impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// One shard of a study: the JSON of `evaluate --shard K/M --out`, which [`merge`] adds up.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Part {
    pub sisfilt_version: String,
    pub config: String,
    /// SHA-256 of the model as read (every matrix, `p`, the initial conditions, the inputs of
    /// the runs; not the config's name): the parts of one study share it.
    pub model_sha256: String,
    pub options: EvaluateOptions,
    /// The arrival probabilities of `--sweep-p`, or `None` for one evaluation.
    pub sweep_p: Option<Vec<f64>>,
    pub shard: Shard,
    /// Its runs, from the first to one past the last (0-based).
    pub runs: [usize; 2],
    pub subsystems: usize,
    /// The state size `n` of each subsystem.
    pub n: usize,
    pub steps: usize,
    /// One per value of `sweep_p`, or one.
    pub studies: Vec<StudySums>,
    /// Time of the part (seconds).
    pub wall_time_s: f64,
}

/// SHA-256 of what decides a study's figures besides its options: the model (its name
/// aside) and the inputs `u` of its runs.
fn model_digest(model: &Model, u: &[Vec<f64>]) -> String {
    use sha2::Digest;
    let mut unnamed = model.clone();
    unnamed.name.clear();
    let mut digest = sha2::Sha256::new();
    // Debug shows every number with the digits that read back to it.
    digest.update(format!("{:?}", *unnamed).as_bytes());
    for v in u.iter().flatten() {
        digest.update(v.to_le_bytes());
    }
    digest
        .finalize()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Runs shard `shard` of the study that [`evaluate`] (or with `sweep`, [`sweep_p`]) runs in
/// whole, and keeps its sums; `tick` is called once per finished run.
pub fn evaluate_part(
    model: &Model,
    inputs: &RunInputs,
    config: &str,
    opts: EvaluateOptions,
    sweep: Option<&[f64]>,
    shard: Shard,
    tick: impl Fn() -> Result<()> + Sync,
) -> Result<Part> {
    let start = Instant::now();
    let steps = checked_steps(model, &opts)?;
    sweep.map(check_sweep).transpose()?;
    if shard.count > opts.runs {
        return Err(EvaluateError::MoreShardsThanRuns {
            count: shard.count,
            runs: opts.runs,
        }
        .into());
    }
    let runs = shard.runs(opts.runs);
    let u = run_inputs(model, inputs, steps)?;
    let studies = match sweep {
        None => vec![tally(model, inputs, &opts, steps, &u, runs.clone(), &tick)?],
        Some(values) => values
            .iter()
            .map(|&p| {
                let model = model.with_arrival_probability(p);
                tally(&model, inputs, &opts, steps, &u, runs.clone(), &tick)
            })
            .collect::<Result<_>>()?,
    };
    Ok(Part {
        sisfilt_version: env!("CARGO_PKG_VERSION").to_string(),
        config: config.to_string(),
        model_sha256: model_digest(model, &u),
        options: opts,
        sweep_p: sweep.map(<[f64]>::to_vec),
        shard,
        runs: [runs.start, runs.end],
        subsystems: model.subsystems,
        n: model.dims.n,
        steps,
        studies,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// A whole study: what `evaluate` writes, or with `--sweep-p` what `evaluate --sweep-p`
/// writes.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Study {
    Sweep(Sweep),
    Evaluation(Evaluation),
}

impl Study {
    /// The table printed on standard output.
    pub fn table(&self) -> String {
        match self {
            Study::Sweep(s) => s.table(),
            Study::Evaluation(e) => e.table(),
        }
    }
}

/// Adds up the parts of one study, each with the name its errors call it by (its file), in
/// shard order, into the figures of the whole study. Refused: parts of different models,
/// options or versions, two parts of one shard, a shard missing. The wall times are the
/// parts' summed.
pub fn merge(parts: &[(String, Part)]) -> Result<Study, MergeError> {
    let (first_name, first) = parts.first().ok_or(MergeError::NoParts)?;
    let foreign = |name: &str, what: String| MergeError::Foreign {
        part: name.to_string(),
        first: first_name.clone(),
        what,
    };
    let mut by_shard: std::collections::BTreeMap<usize, (&String, &Part)> = Default::default();
    for (name, part) in parts {
        let differ = |what: &str, a: &dyn std::fmt::Debug, b: &dyn std::fmt::Debug| {
            foreign(name, format!("{what} differ ({a:?} and {b:?})"))
        };
        if part.sisfilt_version != first.sisfilt_version {
            return Err(differ(
                "sisfilt versions",
                &part.sisfilt_version,
                &first.sisfilt_version,
            ));
        }
        if part.model_sha256 != first.model_sha256 {
            return Err(foreign(
                name,
                "the models differ (config, --set values or inputs)".into(),
            ));
        }
        if part.options != first.options {
            return Err(foreign(
                name,
                option_difference(&part.options, &first.options),
            ));
        }
        if part.sweep_p != first.sweep_p {
            return Err(differ("--sweep-p values", &part.sweep_p, &first.sweep_p));
        }
        if part.shard.count != first.shard.count {
            return Err(differ(
                "shard counts",
                &part.shard.count,
                &first.shard.count,
            ));
        }
        let checked = Shard::new(part.shard.index, part.shard.count)
            .ok()
            .filter(|s| {
                s.runs(part.options.runs) == (part.runs[0]..part.runs[1])
                    && part.studies.len() == first.studies.len()
                    && part.studies.iter().zip(&first.studies).all(|(a, b)| {
                        names(a) == names(b)
                            && a.filters.iter().all(|f| {
                                f.scores.accuracy.is_of(first.n)
                                    && f.scores.per_step.is_of(first.steps)
                            })
                    })
            })
            .ok_or_else(|| MergeError::NotAPart {
                part: name.clone(),
                what: "its shard, runs and sums do not go together".into(),
            })?;
        if let Some((other, _)) = by_shard.insert(checked.index, (name, part)) {
            return Err(MergeError::Duplicate {
                part: name.clone(),
                other: other.clone(),
                shard: checked,
            });
        }
    }
    let count = first.shard.count;
    if by_shard.len() < count {
        // The count may be far larger than the parts given: name the first few missing.
        const NAMED: usize = 5;
        let mut shards: Vec<String> = (0..count)
            .filter(|k| !by_shard.contains_key(k))
            .take(NAMED)
            .map(|k| format!("shard {k}/{count}"))
            .collect();
        let more = count - by_shard.len() - shards.len();
        if more > 0 {
            shards.push(format!("and {more} more"));
        }
        let given: Vec<String> = parts.iter().map(|(name, _)| name.clone()).collect();
        return Err(MergeError::Missing {
            shards: shards.join(", "),
            given: given.join(", "),
        });
    }
    let mut in_order = by_shard.into_values().map(|(_, part)| part);
    let mut sums = in_order.next().expect("one part at least").studies.clone();
    for part in in_order {
        for (study, later) in sums.iter_mut().zip(&part.studies) {
            study.add(later);
        }
    }
    let figures = |sums: StudySums| {
        evaluation(
            &first.config,
            first.subsystems,
            first.steps,
            first.options.clone(),
            sums,
        )
    };
    Ok(match &first.sweep_p {
        None => Study::Evaluation(figures(sums.remove(0))),
        Some(values) => {
            let total_wall_time_s = sums.iter().map(|s| s.wall_time_s).sum();
            Study::Sweep(Sweep {
                sisfilt_version: first.sisfilt_version.clone(),
                config: first.config.clone(),
                options: first.options.clone(),
                subsystems: first.subsystems,
                steps: first.steps,
                sweep_p: values.clone(),
                evaluations: sums.into_iter().map(figures).collect(),
                total_wall_time_s,
            })
        }
    })
}

/// The first option in which `options` differ from `first`'s, in words.
fn option_difference(options: &EvaluateOptions, first: &EvaluateOptions) -> String {
    let (serde_json::Value::Object(a), serde_json::Value::Object(b)) = (
        serde_json::to_value(options).expect("options serialise"),
        serde_json::to_value(first).expect("options serialise"),
    ) else {
        unreachable!("options serialise as a map")
    };
    a.iter()
        .find(|(key, value)| b.get(*key) != Some(value))
        .map_or_else(
            || "the options differ".into(),
            |(key, value)| {
                let theirs = b.get(key).unwrap_or(&serde_json::Value::Null);
                format!("the options differ: {key} {value} against {theirs}")
            },
        )
}

/// The filters of a part's study, in order.
fn names(sums: &StudySums) -> Vec<Compared> {
    sums.filters.iter().map(|f| f.name).collect()
}
