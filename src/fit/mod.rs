//! `fit`: maximum-likelihood estimates of the arrival probability `p` and the diagonals of
//! `Q` and `M`, with intervals (docs/theory.md §16).
//!
//! The objective is the log-likelihood the filters already compute ([`run::log_likelihood`]):
//! the mixture update's with unknown dropouts, the Gaussian innovations density of the
//! received elements with known ones. The optimiser (L-BFGS of the `argmin` crate) works on
//! `θ = (logit p, log Q_kk, log M_kk)`, which keeps every candidate a probability and a
//! variance, with central-difference gradients whose filter runs go in parallel. At the
//! optimum, the Hessian of `−ℓ` by central differences gives the standard errors and the
//! correlations, and the per-step scores the robust (sandwich) ones.

pub mod band;
mod gradient;
mod parameter;
mod report;

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use argmin::core::observers::{Observe, ObserverMode};
use argmin::core::{CostFunction, Executor, Gradient, IterState, KV, State};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use crate::accuracy::Z_95;
use crate::config::RawConfig;
use crate::error::{Error, Result};
use crate::filter::{Dropouts, FilterKind, Update};
use crate::innovations::Fitted;
use crate::model::Model;
use crate::run::{self, CheckedSpec, RunSpec, SpecError};

pub use band::ObjectiveChoice;
pub use gradient::noise_score;
pub use parameter::{ParamGroup, Parameter};
pub use report::{FitReport, FittedParameter, ReportFormat};

/// Default iteration limit of the optimiser.
pub const DEFAULT_MAX_ITER: usize = 200;
/// `logit p` stays within `±LOGIT_BOUND` (`p` within about `3e−7` of 0 and 1).
const LOGIT_BOUND: f64 = 15.0;
/// Each log variance stays within `±LOG_RANGE` of its starting value.
const LOG_RANGE: f64 = 25.0;
/// Step in `θ` of the gradient's central differences (and of the per-step scores).
const GRADIENT_STEP: f64 = 1e-5;
/// Step in `θ` of the Hessian's central differences.
const HESSIAN_STEP: f64 = 1e-3;
/// Weight of the quadratic wall outside the box, per unit of `θ` squared.
const WALL: f64 = 1e3;
/// `θ_k` within this of a bound of its box is on the boundary: no interval.
const ON_BOUNDARY: f64 = 1e-3;
/// A candidate whose `Q` or `M` is not a covariance, or whose filter breaks down, costs this
/// much more than the start (the log-likelihood there is `−∞`; a finite cliff keeps the line
/// search going).
const CLIFF: f64 = 1e6;
/// L-BFGS history length.
const LBFGS_MEMORY: usize = 10;

/// A fit that cannot run for a reason its settings name (exit 2 on the command line).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    /// A name in `params` that is not `p`, `Q` or `M`.
    #[error("params: unknown parameter `{0}`: expected a list of p, Q and M")]
    UnknownParameter(String),
    /// `params` names nothing.
    #[error("params: expected at least one of p, Q and M")]
    NoParameters,
    /// The distributed filter's log-likelihood ignores the uncertainty of the neighbours'
    /// states, and `Q` absorbs it (docs/theory.md §16).
    #[error(
        "filter = distributed cannot fit Q: its log-likelihood ignores the uncertainty of the neighbours' states, which Q then absorbs (docs/theory.md §16); use filter = joint or centralized, or leave Q out of params"
    )]
    DistributedQ,
    /// With known dropouts, `p` does not enter the density of the measurements received.
    #[error(
        "dropouts = known: p does not enter the likelihood of the measurements received (the lost ones are given); leave p out of params, or fit with dropouts = unknown"
    )]
    PWithKnownDropouts,
    /// `max_iter = 0`.
    #[error("max_iter: expected at least 1 iteration")]
    NoIterations,
}

/// What to fit and how, as asked for; [`FitSpec::check`] makes it a [`CheckedFit`].
#[derive(Debug, Clone, PartialEq)]
pub struct FitSpec {
    /// The groups of parameters fitted: `p`, the diagonal of `Q`, the diagonal of `M`.
    pub params: Vec<ParamGroup>,
    /// The filter whose log-likelihood is maximised.
    pub filter: FilterKind,
    /// The joint filter's band `K`; `None`: the fit chooses it ([`band`]).
    pub band: Option<usize>,
    pub dropouts: Dropouts,
    pub max_iter: usize,
    /// The memory the filter may hold ([`crate::memory`]; default 8 GiB).
    pub max_memory: Option<u64>,
}

impl Default for FitSpec {
    /// `p`, `Q` and `M` by the joint filter's log-likelihood, unknown dropouts.
    fn default() -> Self {
        Self {
            params: vec![ParamGroup::P, ParamGroup::Q, ParamGroup::M],
            filter: FilterKind::Joint,
            band: None,
            dropouts: Dropouts::Unknown,
            max_iter: DEFAULT_MAX_ITER,
            max_memory: None,
        }
    }
}

/// A [`FitSpec`] whose settings go together: made only by [`FitSpec::check`].
#[derive(Debug, Clone, PartialEq)]
pub struct CheckedFit {
    params: Vec<ParamGroup>,
    run: CheckedSpec,
    /// The joint filter without a band given: the fit chooses it ([`band`]).
    choose_band: bool,
    max_iter: usize,
}

impl FitSpec {
    /// Every rule of a fit, in one place: `params` not empty, no `Q` for the distributed
    /// filter, no `p` with known dropouts; the run is the filter with the mixture update
    /// (unknown dropouts) or the known-dropout update, whose log-likelihoods are the objective.
    pub fn check(&self) -> std::result::Result<CheckedFit, Error> {
        if self.params.is_empty() {
            return Err(FitError::NoParameters.into());
        }
        if self.max_iter == 0 {
            return Err(FitError::NoIterations.into());
        }
        if self.filter == FilterKind::Distributed && self.params.contains(&ParamGroup::Q) {
            return Err(FitError::DistributedQ.into());
        }
        if self.dropouts == Dropouts::Known && self.params.contains(&ParamGroup::P) {
            return Err(FitError::PWithKnownDropouts.into());
        }
        let update = match self.dropouts {
            Dropouts::Unknown => Update::Mixture,
            Dropouts::Known => Update::Linear,
        };
        let run = RunSpec {
            filter: self.filter,
            update,
            dropouts: self.dropouts,
            band: self.band,
            max_memory: self.max_memory,
            ..RunSpec::default()
        }
        .check()
        .map_err(|e: SpecError| Error::from(e))?;
        let mut params = self.params.clone();
        params.sort();
        params.dedup();
        Ok(CheckedFit {
            params,
            run,
            choose_band: self.filter == FilterKind::Joint && self.band.is_none(),
            max_iter: self.max_iter,
        })
    }
}

impl CheckedFit {
    /// The objective of a fit of `model` to `y`: the run whose log-likelihood is maximised
    /// (and whose innovation check judges the fit), the joint filter's band chosen where none
    /// was given ([`band::choose`]), with the next wider objective to compare at the estimate.
    fn objective(
        &self,
        model: &Model,
        y: &[f64],
        u: Option<&[f64]>,
    ) -> Result<(CheckedSpec, Option<ObjectiveChoice>)> {
        let fixed = |band: Option<usize>, reference| ObjectiveChoice {
            band,
            chosen: false,
            tried: Vec::new(),
            reference,
            gap_at_estimate: None,
        };
        Ok(match self.run.filter_kind() {
            FilterKind::Joint if self.choose_band => {
                let (chosen, reference, tried) = band::choose(model, &self.run, y, u)?;
                let choice = ObjectiveChoice {
                    band: chosen.band,
                    chosen: true,
                    tried,
                    reference,
                    gap_at_estimate: None,
                };
                (self.run.with_band(chosen.band), Some(choice))
            }
            FilterKind::Joint => {
                let k = self.run.joint_options().map_or(0, |j| j.band);
                let k = k.min(model.subsystems - 1);
                let reference = band::wider_than(model, &self.run, k)?;
                (self.run, Some(fixed(Some(k), reference)))
            }
            FilterKind::Centralized => (self.run, Some(fixed(None, None))),
            FilterKind::Distributed => (self.run, None),
        })
    }
}

/// A fit: the report and the fitted model.
#[derive(Debug, Clone)]
pub struct Fit {
    pub report: FitReport,
    pub model: Model,
    /// The scalars fitted, in the order of the report's `parameters`, and their estimates.
    pub estimates: Vec<(Parameter, f64)>,
}

impl Fit {
    /// The config `raw` with the estimates in place (in the base and in every override that
    /// sets them), which reads back as [`Fit::model`].
    pub fn fitted_config(&self, raw: &RawConfig) -> RawConfig {
        let mut raw = raw.clone();
        for &(parameter, value) in &self.estimates {
            parameter.write(&mut raw, value);
        }
        raw
    }
}

/// One iteration of the optimiser, for a progress line.
#[derive(Debug, Clone, Copy)]
pub struct FitProgress {
    pub iteration: u64,
    /// The best log-likelihood so far.
    pub loglik: f64,
    pub evaluations: usize,
}

/// A progress callback, called once per iteration of the optimiser; an error (e.g.
/// [`Error::Interrupted`], a front end's Ctrl-C) stops the fit with that error.
pub type ProgressFn = Box<dyn FnMut(&FitProgress) -> Result<()> + Send>;

/// Fits the parameters of `spec` to the measurements `y` (`T × N × q`, NaN where a value is
/// not in the data) with inputs `u` (`T × N × m`; `None`: the model's own), starting from
/// `model`'s values (docs/theory.md §16).
pub fn fit(
    model: &Model,
    spec: &CheckedFit,
    y: &[f64],
    u: Option<&[f64]>,
    progress: Option<ProgressFn>,
) -> Result<Fit> {
    let started = Instant::now();
    let parameters = Parameter::all(model, &spec.params);
    let mut warnings = parameter::start_warnings(model, &parameters);
    let (objective_spec, mut choice) = spec.objective(model, y, u)?;
    let objective = Objective::new(model, &objective_spec, &parameters, y, u)?;
    let theta0 = objective.theta0.clone();
    let f0 = objective.start_cost;

    let counter = Arc::clone(&objective.evaluations);
    let linesearch = MoreThuenteLineSearch::new();
    let solver = LBFGS::new(linesearch, LBFGS_MEMORY)
        .with_tolerance_grad(1e-9)
        .and_then(|s| s.with_tolerance_cost(1e-13))
        .map_err(|e| Error::Usage(format!("fit: {e}")))?;
    let mut executor = Executor::new(&objective, solver)
        .configure(|state| state.param(theta0.clone()).max_iters(spec.max_iter as u64));
    let stopped: Arc<std::sync::Mutex<Option<Error>>> = Arc::default();
    if let Some(progress) = progress {
        executor = executor.add_observer(
            Progress {
                callback: progress,
                evaluations: counter,
                observations: objective.observations as f64,
                stopped: Arc::clone(&stopped),
            },
            ObserverMode::Always,
        );
    }
    let result = executor.run().map_err(|e| {
        let stopped = stopped.lock().ok().and_then(|mut s| s.take());
        stopped.unwrap_or_else(|| Error::Usage(format!("fit: the optimiser failed: {e}")))
    })?;
    let state = result.state();
    let iterations = state.get_iter();
    let termination = state
        .get_termination_reason()
        .map_or_else(|| "stopped".to_string(), |r| r.text().to_string());
    let mut theta = objective.clamp(state.get_best_param().unwrap_or(&theta0));
    let mut f = objective.cost(&theta);
    if f > f0 {
        // The optimiser never returns worse than its start; a point clamped back into the box
        // might be.
        (theta, f) = (theta0.clone(), f0);
    }
    let loglik = -f * objective.observations as f64;
    let loglik_start = -f0 * objective.observations as f64;

    let curvature = objective.curvature(&theta);
    let (missing, covariance, robust) = curvature.covariances(&objective, &theta);
    for (k, p) in parameters.iter().enumerate() {
        if let Some(why) = missing[k] {
            warnings.push(format!(
                "{}: {} (estimate {}): no interval",
                p.name(),
                match why {
                    NoInterval::Boundary => "on the boundary of its range",
                    NoInterval::Flat => "the log-likelihood is flat or not concave there",
                },
                match p {
                    Parameter::P => format!("{:.7}", p.value(theta[k])),
                    _ => format!("{:.4e}", p.value(theta[k])),
                }
            ));
        }
    }
    let available: Vec<bool> = missing.iter().map(Option::is_none).collect();
    let fitted_params: Vec<FittedParameter> = parameters
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let estimate = p.value(theta[k]);
            let se_theta = available[k].then(|| covariance[(k, k)].sqrt());
            let robust_theta = available[k].then(|| robust[(k, k)].max(0.0).sqrt());
            FittedParameter {
                name: p.name(),
                configured: p.configured(model),
                estimate,
                ci_low: se_theta.map(|s| p.value(theta[k] - Z_95 * s)),
                ci_high: se_theta.map(|s| p.value(theta[k] + Z_95 * s)),
                se: se_theta.map(|s| s * p.slope(theta[k])),
                robust_se: robust_theta.map(|s| s * p.slope(theta[k])),
            }
        })
        .collect();
    let d = parameters.len();
    let correlation = (0..d)
        .map(|j| {
            (0..d)
                .map(|k| {
                    (available[j] && available[k]).then(|| {
                        covariance[(j, k)] / (covariance[(j, j)] * covariance[(k, k)]).sqrt()
                    })
                })
                .collect()
        })
        .collect();
    let hessian = (0..d)
        .map(|j| (0..d).map(|k| curvature.hessian[(j, k)]).collect())
        .collect();
    let fitted = objective
        .model_at(&theta)
        .ok_or_else(|| Error::Usage("fit: the fitted model is not valid".into()))?;
    // What the fit estimated is not what its check may blame (docs/theory.md §14).
    let estimated = Fitted {
        p: spec.params.contains(&ParamGroup::P),
        q: spec.params.contains(&ParamGroup::Q),
        m: spec.params.contains(&ParamGroup::M),
    };
    if let Some(choice) = choice.as_mut() {
        if let Some(reference) = choice.reference {
            choice.gap_at_estimate = Some(band::gap(
                &fitted,
                &objective_spec,
                &reference,
                loglik,
                y,
                u,
            )?);
        }
        warnings.extend(choice.warning());
    }
    let innovations =
        run::innovation_report(&fitted, &objective_spec, y, u)?.map(|r| r.after_fit(estimated));
    Ok(Fit {
        report: FitReport {
            parameters: fitted_params,
            loglik_start,
            loglik,
            evaluations: objective.evaluations.load(Ordering::Relaxed),
            iterations,
            correlation,
            hessian,
            filter: objective_spec.filter_kind(),
            objective: choice,
            dropouts: objective_spec.dropouts(),
            observations: objective.observations,
            termination,
            seconds: started.elapsed().as_secs_f64(),
            warnings,
            innovations,
        },
        model: fitted,
        estimates: parameters
            .iter()
            .enumerate()
            .map(|(k, p)| (*p, p.value(theta[k])))
            .collect(),
    })
}

/// `f(θ) = −ℓ(θ) / n_obs` over the data, with a quadratic wall outside the box.
struct Objective<'a> {
    model: &'a Model,
    run: &'a CheckedSpec,
    parameters: &'a [Parameter],
    y: &'a [f64],
    u: Option<&'a [f64]>,
    theta0: Vec<f64>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    observations: usize,
    /// `f(θ₀)`, the cost at the start; `f(θ₀) + CLIFF` is the cost where `ℓ = −∞`.
    start_cost: f64,
    evaluations: Arc<AtomicUsize>,
}

impl<'a> Objective<'a> {
    /// The objective at `model`'s values; an error of the configured model itself (bad
    /// inputs, a filter that breaks down) is the fit's error.
    fn new(
        model: &'a Model,
        run_spec: &'a CheckedSpec,
        parameters: &'a [Parameter],
        y: &'a [f64],
        u: Option<&'a [f64]>,
    ) -> Result<Self> {
        let theta0: Vec<f64> = parameters.iter().map(|p| p.start(model)).collect();
        let (lower, upper) = parameters
            .iter()
            .zip(&theta0)
            .map(|(p, &t)| match p {
                Parameter::P => (-LOGIT_BOUND, LOGIT_BOUND),
                _ => (t - LOG_RANGE, t + LOG_RANGE),
            })
            .unzip();
        let observations = y.iter().filter(|v| !v.is_nan()).count();
        if observations == 0 {
            return Err(Error::Usage(
                "fit: the measurements hold no value (every cell is a gap)".into(),
            ));
        }
        let mut objective = Self {
            model,
            run: run_spec,
            parameters,
            y,
            u,
            theta0,
            lower,
            upper,
            observations,
            start_cost: f64::INFINITY,
            evaluations: Arc::new(AtomicUsize::new(0)),
        };
        let start = objective
            .model_at(&objective.theta0)
            .ok_or_else(|| Error::Usage("fit: the configured Q or M is not a covariance".into()))?;
        let loglik: f64 = run::log_likelihood(&start, run_spec, y, u)?.iter().sum();
        objective.evaluations.fetch_add(1, Ordering::Relaxed);
        objective.start_cost = -loglik / observations as f64;
        Ok(objective)
    }

    /// `θ` moved into the box.
    fn clamp(&self, theta: &[f64]) -> Vec<f64> {
        theta
            .iter()
            .zip(self.lower.iter().zip(&self.upper))
            .map(|(&t, (&lo, &hi))| t.clamp(lo, hi))
            .collect()
    }

    fn on_boundary(&self, theta: &[f64], k: usize) -> bool {
        theta[k] - self.lower[k] < ON_BOUNDARY || self.upper[k] - theta[k] < ON_BOUNDARY
    }

    /// The model with the values `θ` (inside the box), when its `Q` and `M` are covariances.
    fn model_at(&self, theta: &[f64]) -> Option<Model> {
        let mut model = self.model.clone();
        for (p, &t) in self.parameters.iter().zip(theta) {
            model = p.set(&model, p.value(t));
        }
        parameter::noise_is_valid(&model).then_some(model)
    }

    /// Each step's log density at `θ` (inside the box); `None` where `ℓ = −∞` (a candidate
    /// that is no model, a filter that breaks down).
    fn step_logliks(&self, theta: &[f64]) -> Option<Vec<f64>> {
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let model = self.model_at(theta)?;
        run::log_likelihood(&model, self.run, self.y, self.u)
            .ok()
            .filter(|l| l.iter().all(|v| v.is_finite()))
    }

    /// `f(θ)`: `−ℓ / n_obs` at `θ` moved into the box, plus the wall outside it.
    fn cost(&self, theta: &[f64]) -> f64 {
        let inside = self.clamp(theta);
        let wall: f64 = theta
            .iter()
            .zip(&inside)
            .map(|(t, c)| 0.5 * WALL * (t - c).powi(2))
            .sum();
        let f = self
            .step_logliks(&inside)
            .map_or(self.start_cost + CLIFF, |l| {
                -l.iter().sum::<f64>() / self.observations as f64
            });
        f + wall
    }

    /// The points `θ ± h e_k`, `k = 0..d`, in that order.
    fn plus_minus(theta: &[f64], h: f64) -> Vec<Vec<f64>> {
        (0..theta.len())
            .flat_map(|k| {
                [h, -h].map(|step| {
                    let mut point = theta.to_vec();
                    point[k] += step;
                    point
                })
            })
            .collect()
    }

    /// The Hessian of `−ℓ` at `θ` (step `HESSIAN_STEP`) and the scores of each step,
    /// `∂ℓ_t/∂θ` (step `GRADIENT_STEP`), every filter run in parallel.
    fn curvature(&self, theta: &[f64]) -> Curvature {
        let d = theta.len();
        let h = HESSIAN_STEP;
        let mut points = vec![theta.to_vec()];
        points.extend(Self::plus_minus(theta, h));
        let pairs: Vec<(usize, usize)> = (0..d)
            .flat_map(|j| (j + 1..d).map(move |k| (j, k)))
            .collect();
        for &(j, k) in &pairs {
            for (sj, sk) in [(h, h), (h, -h), (-h, h), (-h, -h)] {
                let mut point = theta.to_vec();
                point[j] += sj;
                point[k] += sk;
                points.push(point);
            }
        }
        points.extend(Self::plus_minus(theta, GRADIENT_STEP));
        let values: Vec<Option<Vec<f64>>> = points
            .par_iter()
            .map(|p| self.step_logliks(&self.clamp(p)))
            .collect();
        let total = |v: &Option<Vec<f64>>| v.as_ref().map_or(f64::NEG_INFINITY, |l| l.iter().sum());
        let centre = total(&values[0]);
        let mut hessian = DMatrix::zeros(d, d);
        for k in 0..d {
            let (plus, minus) = (total(&values[1 + 2 * k]), total(&values[2 + 2 * k]));
            hessian[(k, k)] = -(plus - 2.0 * centre + minus) / (h * h);
        }
        let mut at = 1 + 2 * d;
        for &(j, k) in &pairs {
            let [pp, pm, mp, mm] = [0, 1, 2, 3].map(|o| total(&values[at + o]));
            hessian[(j, k)] = -(pp - pm - mp + mm) / (4.0 * h * h);
            hessian[(k, j)] = hessian[(j, k)];
            at += 4;
        }
        let steps = values[0].as_ref().map_or(0, Vec::len);
        let mut scores = DMatrix::zeros(steps, d);
        for k in 0..d {
            if let (Some(plus), Some(minus)) = (&values[at + 2 * k], &values[at + 2 * k + 1]) {
                for t in 0..steps {
                    scores[(t, k)] = (plus[t] - minus[t]) / (2.0 * GRADIENT_STEP);
                }
            }
        }
        Curvature { hessian, scores }
    }
}

/// The Hessian of `−ℓ` and the per-step scores at the optimum.
struct Curvature {
    hessian: DMatrix<f64>,
    /// `T × d`: row `t` is `∂ℓ_t/∂θ`.
    scores: DMatrix<f64>,
}

impl Curvature {
    /// Why each parameter has no interval (`None`: it has one), the covariance `H⁻¹` of `θ̂`
    /// and the robust one `H⁻¹ B H⁻¹` (`B = Σ_t s_t s_tᵀ`), over the parameters with an
    /// interval (zero elsewhere). A parameter on the boundary of its box has none, and so has
    /// one whose interval would reach past the box (the data do not bound it inside its
    /// range); while the Hessian of the others is not positive definite, the one that weighs
    /// most in its least curved direction has none either. One parameter is set aside at a
    /// time, and the others' figures are those without it.
    fn covariances(
        &self,
        objective: &Objective,
        theta: &[f64],
    ) -> (Vec<Option<NoInterval>>, DMatrix<f64>, DMatrix<f64>) {
        let d = theta.len();
        let finite = self.hessian.iter().all(|v| v.is_finite());
        let mut missing: Vec<Option<NoInterval>> = (0..d)
            .map(|k| {
                if objective.on_boundary(theta, k) {
                    Some(NoInterval::Boundary)
                } else if !finite {
                    Some(NoInterval::Flat)
                } else {
                    None
                }
            })
            .collect();
        loop {
            let kept: Vec<usize> = (0..d).filter(|&k| missing[k].is_none()).collect();
            if kept.is_empty() {
                return (missing, DMatrix::zeros(d, d), DMatrix::zeros(d, d));
            }
            let h = self.hessian.select_rows(&kept).select_columns(&kept);
            let Some(chol) = h.clone().cholesky() else {
                let eigen = h.symmetric_eigen();
                let weakest = eigen.eigenvalues.imin();
                let column: DVector<f64> = eigen.eigenvectors.column(weakest).into();
                missing[kept[column.iamax()]] = Some(NoInterval::Flat);
                continue;
            };
            let inverse = chol.inverse();
            let unbounded = kept.iter().enumerate().find(|&(a, &k)| {
                let half = Z_95 * inverse[(a, a)].sqrt();
                theta[k] - half < objective.lower[k] || theta[k] + half > objective.upper[k]
            });
            if let Some((_, &k)) = unbounded {
                missing[k] = Some(NoInterval::Boundary);
                continue;
            }
            let s = self.scores.select_columns(&kept);
            let robust = &inverse * (s.transpose() * &s) * &inverse;
            let mut covariance = DMatrix::zeros(d, d);
            let mut sandwich = DMatrix::zeros(d, d);
            for (a, &j) in kept.iter().enumerate() {
                for (c, &k) in kept.iter().enumerate() {
                    covariance[(j, k)] = inverse[(a, c)];
                    sandwich[(j, k)] = robust[(a, c)];
                }
            }
            return (missing, covariance, sandwich);
        }
    }
}

/// Why a parameter has no interval.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum NoInterval {
    /// At the edge of its range, or so weakly bounded by the data that its interval would
    /// reach past it (`p → 1` where nothing is lost, a variance `→ 0`).
    Boundary,
    /// The log-likelihood is flat or not concave in a direction it weighs most in.
    Flat,
}

impl CostFunction for &Objective<'_> {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, theta: &Self::Param) -> std::result::Result<f64, argmin::core::Error> {
        Ok(Objective::cost(self, theta))
    }
}

impl Gradient for &Objective<'_> {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;

    /// Central differences, the `2d` filter runs in parallel.
    fn gradient(&self, theta: &Self::Param) -> std::result::Result<Vec<f64>, argmin::core::Error> {
        let points = Objective::plus_minus(theta, GRADIENT_STEP);
        let costs: Vec<f64> = points
            .par_iter()
            .map(|p| Objective::cost(self, p))
            .collect();
        Ok(costs
            .chunks(2)
            .map(|pm| (pm[0] - pm[1]) / (2.0 * GRADIENT_STEP))
            .collect())
    }
}

/// Calls the progress callback after each iteration; its error stops the optimiser and is
/// kept in `stopped` for the fit to return.
struct Progress {
    callback: ProgressFn,
    evaluations: Arc<AtomicUsize>,
    observations: f64,
    stopped: Arc<std::sync::Mutex<Option<Error>>>,
}

impl Observe<IterState<Vec<f64>, Vec<f64>, (), (), (), f64>> for Progress {
    fn observe_iter(
        &mut self,
        state: &IterState<Vec<f64>, Vec<f64>, (), (), (), f64>,
        _kv: &KV,
    ) -> std::result::Result<(), argmin::core::Error> {
        let progress = FitProgress {
            iteration: state.get_iter(),
            loglik: -state.get_best_cost() * self.observations,
            evaluations: self.evaluations.load(Ordering::Relaxed),
        };
        (self.callback)(&progress).map_err(|e| {
            let message = e.to_string();
            if let Ok(mut stopped) = self.stopped.lock() {
                *stopped = Some(e);
            }
            argmin::core::Error::msg(message)
        })
    }
}
