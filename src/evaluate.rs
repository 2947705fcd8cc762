//! Monte Carlo comparison of filters (SPEC §3, §5, §7 `evaluate`): every filter runs on the
//! same simulated realisations; RMSE, RMSE ratio to the centralized Nahi filter (the optimal
//! linear estimator) and average NEES with its 95 % band are reported per filter.
//!
//! Run `r` (0-based) is simulated with seed `seed + r`. Runs execute in parallel (rayon), and
//! their sums are merged in run order afterwards, so every figure except the clock readings
//! is the same for any thread count.

use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use crate::accuracy::{Accuracy, AccuracyReport};
use crate::error::{Error, Result};
use crate::filter::{
    CentralizedFilter, CentralizedSchedule, ChainFilter, Dropouts, ScheduledCentralized,
    TwoStepOptions, two_step,
};
use crate::inputs::InputStream;
use crate::model::Model;
use crate::simulate::simulate;

/// The filters compared, in table order.
pub const FILTERS: [&str; 5] = [
    "distributed",
    "distributed-paper",
    "centralized",
    "centralized-known",
    "naive",
];

/// Settings of an evaluation.
#[derive(Debug, Clone, Serialize)]
pub struct EvaluateOptions {
    pub runs: usize,
    pub seed: u64,
    /// Time steps `t ≤ burn_in` are not scored.
    pub burn_in: usize,
    /// Largest lifted size `N·n` for the centralized filters.
    pub max_lifted: usize,
}

/// The figures of one filter over all runs.
#[derive(Debug, Clone, Serialize)]
pub struct FilterResult {
    pub name: &'static str,
    /// What the filter is.
    pub description: &'static str,
    /// `None` when the filter ran; else why it was skipped or failed.
    pub skipped: Option<String>,
    pub accuracy: Option<AccuracyReport>,
    /// Overall RMSE divided by the centralized Nahi filter's.
    pub rmse_ratio: Option<f64>,
    /// Time spent in this filter, summed over runs (seconds).
    pub wall_time_s: f64,
}

/// The result of an evaluation.
#[derive(Debug, Clone, Serialize)]
pub struct Evaluation {
    pub sisfilt_version: &'static str,
    pub config: String,
    pub options: EvaluateOptions,
    pub subsystems: usize,
    pub steps: usize,
    pub filters: Vec<FilterResult>,
    /// Time of the whole evaluation (seconds).
    pub total_wall_time_s: f64,
}

fn describe(name: &str) -> &'static str {
    match name {
        "distributed" => "two-step filter, default options (banded, local S, filtered)",
        "distributed-paper" => "two-step filter as printed in the paper (--paper)",
        "centralized" => {
            "centralized Nahi filter on the lifted system: the optimal linear estimator"
        }
        "centralized-known" => {
            "centralized Kalman filter that knows which measurements were lost: a lower bound"
        }
        "naive" => "per-subsystem Kalman filter that treats every measurement as present",
        _ => "",
    }
}

/// One simulated realisation, kept in memory for all filters.
struct Realisation {
    x: Vec<Vec<f64>>,
    y: Vec<Vec<f64>>,
    y_known: Vec<Vec<f64>>,
    u: Vec<Vec<f64>>,
}

fn realise(model: &Model, seed: u64) -> Result<Realisation> {
    let q = model.dims.q;
    let mut r = Realisation {
        x: vec![],
        y: vec![],
        y_known: vec![],
        u: vec![],
    };
    let mut inputs = InputStream::open(model, None)?;
    simulate(model, model.steps, seed, &mut inputs, |s| {
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
        Ok(())
    })?;
    Ok(r)
}

/// Largest simulated realisation `evaluate` keeps in memory (one per thread at a time): a
/// `steps` far too large is refused rather than aborting the process on allocation.
const MAX_REALISATION_BYTES: usize = 1 << 30;

/// Largest centralized schedule `evaluate` keeps in memory; above it the centralized filter
/// runs in full for every run.
const MAX_SCHEDULE_BYTES: usize = 1 << 30;

fn make_filter<'a>(
    model: &'a Model,
    name: &str,
    max_lifted: usize,
    schedule: Option<&'a CentralizedSchedule<'a>>,
) -> Result<Box<dyn ChainFilter + 'a>> {
    Ok(match name {
        "centralized" if schedule.is_some() => {
            Box::new(ScheduledCentralized::new(schedule.expect("checked")))
        }
        "distributed" => two_step(model, TwoStepOptions::default())?,
        "distributed-paper" => two_step(model, TwoStepOptions::paper())?,
        "centralized" => Box::new(CentralizedFilter::new(model, false, max_lifted)?),
        "centralized-known" => Box::new(CentralizedFilter::new(model, true, max_lifted)?),
        "naive" => two_step(
            model,
            TwoStepOptions {
                dropouts: Dropouts::Known,
                ..TwoStepOptions::default()
            },
        )?,
        _ => unreachable!(),
    })
}

/// Per run and filter: the accuracy sums, or the error that stopped the filter, and the time.
type RunResult = Vec<(Result<Accuracy, String>, f64)>;

fn run_filters(
    model: &Model,
    opts: &EvaluateOptions,
    active: &[bool],
    schedule: Option<&CentralizedSchedule>,
    r: usize,
) -> Result<RunResult> {
    let data = realise(model, opts.seed.wrapping_add(r as u64))?;
    let (n, big_n) = (model.dims.n, model.subsystems);
    let mut out = Vec::with_capacity(FILTERS.len());
    for (k, name) in FILTERS.iter().enumerate() {
        if !active[k] {
            out.push((Err(String::new()), 0.0));
            continue;
        }
        let start = Instant::now();
        let result = (|| -> Result<Accuracy> {
            let mut f = make_filter(model, name, opts.max_lifted, schedule)?;
            let mut acc = Accuracy::new(n);
            let ys = if *name == "centralized-known" {
                &data.y_known
            } else {
                &data.y
            };
            for t in 0..ys.len() {
                f.step(&ys[t], &data.u[t])?;
                if t + 1 > opts.burn_in {
                    let (x_hat, p_hat) = f.filtered();
                    for i in 0..big_n {
                        acc.add(
                            &data.x[t][i * n..(i + 1) * n],
                            &x_hat[i * n..(i + 1) * n],
                            &p_hat[i * n * n..(i + 1) * n * n],
                        );
                    }
                }
            }
            Ok(acc)
        })();
        out.push((
            result.map_err(|e| format!("{e}")),
            start.elapsed().as_secs_f64(),
        ));
    }
    Ok(out)
}

/// Runs the Monte Carlo comparison; `tick` is called once per finished run.
pub fn evaluate(
    model: &Model,
    config: &str,
    opts: EvaluateOptions,
    tick: impl Fn() + Sync,
) -> Result<Evaluation> {
    let start = Instant::now();
    if opts.runs == 0 {
        return Err(Error::Usage("--runs must be at least 1".into()));
    }
    let d = model.dims;
    // x, y, y with the losses marked, u, and a vector header for each, per step.
    let per_step = (model.subsystems * (d.n + 2 * d.q + d.m) + 12) * std::mem::size_of::<f64>();
    let realisation_bytes = (model.steps as f64) * (per_step as f64);
    if realisation_bytes > MAX_REALISATION_BYTES as f64 {
        return Err(Error::Config {
            file: model.name.clone(),
            key: "steps".into(),
            msg: format!(
                "evaluate keeps every step of a run in memory: {} steps need about {realisation_bytes:.1e} bytes per run, expected at most {MAX_REALISATION_BYTES}",
                model.steps
            ),
        });
    }
    // A filter that cannot be built for this model (too large, G22 singular) is skipped.
    let mut skipped: Vec<Option<String>> = FILTERS
        .iter()
        .map(|name| {
            make_filter(model, name, opts.max_lifted, None)
                .err()
                .map(|e| format!("{e}"))
        })
        .collect();
    let active: Vec<bool> = skipped.iter().map(Option::is_none).collect();
    // The unknown-dropout centralized covariance pass does not depend on the data (the
    // inputs are the same in every run): compute it once.
    let schedule =
        if active[2] && CentralizedSchedule::bytes(model, model.steps) <= MAX_SCHEDULE_BYTES {
            let mut inputs = InputStream::open(model, None)?;
            let mut u = vec![vec![0.0; model.subsystems * model.dims.m]; model.steps];
            for (t, ut) in u.iter_mut().enumerate() {
                inputs.next(t + 1, ut)?;
            }
            Some(CentralizedSchedule::new(model, &u, opts.max_lifted)?)
        } else {
            None
        };
    let results: Vec<RunResult> = (0..opts.runs)
        .into_par_iter()
        .map(|r| {
            let res = run_filters(model, &opts, &active, schedule.as_ref(), r);
            tick();
            res
        })
        .collect::<Result<_>>()?;

    let n = model.dims.n;
    let mut sums: Vec<Accuracy> = (0..FILTERS.len()).map(|_| Accuracy::new(n)).collect();
    let mut times = vec![0.0; FILTERS.len()];
    for run in &results {
        for (k, (res, time)) in run.iter().enumerate() {
            times[k] += time;
            match res {
                Ok(acc) => sums[k].merge(acc),
                Err(e) if active[k] && skipped[k].is_none() => {
                    skipped[k] = Some(format!("failed: {e}"));
                }
                Err(_) => {}
            }
        }
    }
    let reports: Vec<Option<AccuracyReport>> = (0..FILTERS.len())
        .map(|k| skipped[k].is_none().then(|| sums[k].report()))
        .collect();
    let reference = reports[2].as_ref().map(|r| r.rmse_overall);
    let filters = FILTERS
        .iter()
        .enumerate()
        .map(|(k, name)| FilterResult {
            name,
            description: describe(name),
            skipped: skipped[k].clone(),
            rmse_ratio: match (&reports[k], reference) {
                (Some(r), Some(c)) => Some(r.rmse_overall / c),
                _ => None,
            },
            accuracy: reports[k].clone(),
            wall_time_s: times[k],
        })
        .collect();
    Ok(Evaluation {
        sisfilt_version: env!("CARGO_PKG_VERSION"),
        config: config.to_string(),
        subsystems: model.subsystems,
        steps: model.steps,
        options: opts,
        filters,
        total_wall_time_s: start.elapsed().as_secs_f64(),
    })
}

impl Evaluation {
    /// The table printed on standard output.
    pub fn table(&self) -> String {
        let o = &self.options;
        let mut s = format!(
            "{}: {} runs (seeds {}..{}) × T = {} × N = {}; scored t > {}\n\n",
            self.config,
            o.runs,
            o.seed,
            o.seed.wrapping_add(o.runs as u64 - 1),
            self.steps,
            self.subsystems,
            o.burn_in
        );
        let n = self
            .filters
            .iter()
            .find_map(|f| f.accuracy.as_ref())
            .map_or(0, |a| a.rmse.len());
        s += &format!("{:<18} {:>10}", "filter", "RMSE");
        for k in 1..=n {
            s += &format!(" {:>10}", format!("RMSE x{k}"));
        }
        s += &format!(
            " {:>9} {:>10} {:>17} {:>8} {:>9}\n",
            "/ central", "ANEES", "95 % band", "left out", "time (s)"
        );
        let mut notes = Vec::new();
        for f in &self.filters {
            match (&f.accuracy, &f.skipped) {
                (Some(a), _) => {
                    if !a.rmse_overall.is_finite() {
                        notes.push(format!(
                            "{}: its estimates overflowed (with --paper this is the transfer solver on a long chain, SPEC §2)",
                            f.name
                        ));
                    }
                    s += &format!("{:<18} {:>10.4e}", f.name, a.rmse_overall);
                    for r in &a.rmse {
                        s += &format!(" {r:>10.4e}");
                    }
                    let ratio = f.rmse_ratio.map_or("-".into(), |r| format!("{r:.4}"));
                    let anees = a.anees.map_or("inf".into(), |v| {
                        if v < 1e4 {
                            format!("{v:.4}")
                        } else {
                            format!("{v:.3e}")
                        }
                    });
                    s += &format!(
                        " {ratio:>9} {anees:>10} {:>17} {:>8} {:>9.2}\n",
                        format!("[{:.3}, {:.3}]", a.anees_band[0], a.anees_band[1]),
                        a.nees_left_out,
                        f.wall_time_s
                    );
                }
                (None, Some(why)) => {
                    s += &format!("{:<18} skipped (see note)\n", f.name);
                    notes.push(format!("{}: {why}", f.name));
                }
                (None, None) => {}
            }
        }
        s += "\n";
        for f in &self.filters {
            s += &format!("{:<18} {}\n", f.name, f.description);
        }
        for note in notes {
            s += &format!("note: {note}\n");
        }
        s
    }
}
