//! One run of a study: a simulated realisation, and every compared filter and smoother run on
//! it and scored against its truth (docs/theory.md §13 `evaluate`).

use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::{COMPARED, Compared, EvaluateOptions};
use crate::accuracy::{Accuracy, Detection};
use crate::error::{Error, Result};
use crate::filter::joint::{JointSchedule, ScheduledJoint};
use crate::filter::{
    CentralizedSchedule, ChainFilter, JointFilter, JointOptions, ScheduledCentralized,
    check_estimates,
};
use crate::inputs::RunInputs;
use crate::model::Model;
use crate::simulate::simulate;
use crate::smoother::{Smoother, SmootherSchedule};

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

/// The covariance passes computed once for all runs (docs/theory.md §7, §8, §9).
#[derive(Default)]
pub(super) struct Schedules {
    pub(super) centralized: Option<CentralizedSchedule>,
    pub(super) joint: Option<JointSchedule>,
    /// Per [`Compared::index`], for the smoothers: the gains and covariances of the backward
    /// pass.
    pub(super) smoothers: Vec<Option<SmootherSchedule>>,
}

/// Bytes the schedule of the centralized or joint smoother needs: its gains and the diagonal
/// blocks of `P(t|T)` per step (for `joint`, the factor of `𝒥` with blocks `2n × 2n` and
/// bandwidth `κ = k + 2b` with the inverses of its diagonal blocks, and `Λˢ(t+1)` with band
/// `k`; `b` is the first step's).
pub(super) fn smoother_schedule_bytes(
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
pub(super) fn joint_options(opts: &EvaluateOptions) -> Result<JointOptions> {
    let spec = Compared::Joint.spec(opts).check()?;
    Ok(spec
        .joint_options()
        .expect("the joint row runs the joint filter"))
}

/// The filter `filter`, or for a smoother the filter it smooths (whose means it replays).
pub(super) fn make_filter<'s>(
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
pub(super) struct StepNees {
    #[serde(with = "crate::io::json_number::many")]
    sum: Vec<f64>,
    terms: Vec<u64>,
    infinite: Vec<u64>,
}

impl StepNees {
    pub(super) fn new(steps: usize) -> Self {
        Self {
            sum: vec![0.0; steps],
            terms: vec![0; steps],
            infinite: vec![0; steps],
        }
    }

    pub(super) fn merge(&mut self, other: &StepNees) {
        for t in 0..self.sum.len() {
            self.sum[t] += other.sum[t];
            self.terms[t] += other.terms[t];
            self.infinite[t] += other.infinite[t];
        }
    }

    pub(super) fn is_of(&self, steps: usize) -> bool {
        [self.sum.len(), self.terms.len(), self.infinite.len()] == [steps; 3]
    }

    pub(super) fn averages(&self) -> Vec<Option<f64>> {
        (0..self.sum.len())
            .map(|t| {
                (self.infinite[t] == 0 && self.terms[t] > 0)
                    .then(|| self.sum[t] / self.terms[t] as f64)
            })
            .collect()
    }
}

/// The smoother `smoother` (one of the [`Compared`] smoothers).
pub(super) fn make_smoother(
    model: &Model,
    smoother: Compared,
    opts: &EvaluateOptions,
) -> Result<Box<dyn Smoother>> {
    smoother.spec(opts).check()?.build_smoother(model)
}

/// The sums of one filter over one run or several.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct Scores {
    pub(super) accuracy: Accuracy,
    pub(super) per_step: StepNees,
    /// Filled by the mixture rows only.
    pub(super) detection: Detection,
    /// The runs whose smoother left a note (e.g. it reran with a larger loading), and the
    /// first of those notes.
    pub(super) noted_runs: usize,
    pub(super) first_note: Option<String>,
}

impl Scores {
    pub(super) fn new(model: &Model, steps: usize) -> Self {
        Self {
            accuracy: Accuracy::new(model.dims.n),
            per_step: StepNees::new(steps),
            detection: Detection::default(),
            noted_runs: 0,
            first_note: None,
        }
    }

    /// Adds the sums of later runs (of one closed run, [`Accuracy::close_run`], or of a part).
    pub(super) fn merge(&mut self, other: &Scores) {
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
pub(super) type RunResult = Vec<(Option<Result<Scores>>, f64)>;

/// Run `r`: one realisation of `truth` (the model, or with `--true-p` the model simulated
/// with another `p`) and every active filter of `model` on it.
pub(super) fn run_filters(
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
