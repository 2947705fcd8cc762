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
mod objective;
mod parameter;
mod report;

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use argmin::core::observers::{Observe, ObserverMode};
use argmin::core::{Executor, IterState, KV, State};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;

use crate::accuracy::Z_95;
use crate::config::RawConfig;
use crate::error::{Error, Result};
use crate::filter::{Dropouts, FilterKind, Update};
use crate::innovations::Fitted;
use crate::model::Model;
use crate::run::{self, CheckedSpec, RunSpec, SpecError};

use objective::{NoInterval, Objective};

pub use band::ObjectiveChoice;
pub use gradient::noise_score;
pub use parameter::{ParamGroup, Parameter};
pub use report::{FitReport, FittedParameter, ReportFormat};

/// Default iteration limit of the optimiser.
pub const DEFAULT_MAX_ITER: usize = 200;
/// `logit p` stays within `±LOGIT_BOUND` (`p` within about `3e−7` of 0 and 1).
const LOGIT_BOUND: f64 = 15.0;
/// L-BFGS history length.
const LBFGS_MEMORY: usize = 10;

/// A fit that cannot run for a reason its settings name (exit 2 on the command line).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FitError {
    /// A name in `params` that is not `p`, `Q` or `M`.
    #[error("params: unknown parameter `{0}`: expected a list of p, Q, M, Q[i] and M[i]")]
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
    /// `Q` and `Q[i]` (or `M` and `M[i]`) both name the diagonal.
    #[error("params: {0} and {0}[i] both name the diagonal of {0}: give one of them")]
    SharedAndEach(&'static str),
    /// `Q[i]` or `M[i]` with a matrix that varies in time: one value per subsystem would
    /// overwrite it at every step.
    #[error(
        "params: {0}[i] fits one {0} for each subsystem over every step, but the config's {0} varies in time (an override with steps): fit {0} instead, or give each subsystem one {0}"
    )]
    EachVariesInTime(&'static str),
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
        if self.filter == FilterKind::Distributed
            && self.params.iter().any(|g| g.key() == Some("Q"))
        {
            return Err(FitError::DistributedQ.into());
        }
        for (shared, each, key) in [
            (ParamGroup::Q, ParamGroup::QEach, "Q"),
            (ParamGroup::M, ParamGroup::MEach, "M"),
        ] {
            if self.params.contains(&shared) && self.params.contains(&each) {
                return Err(FitError::SharedAndEach(key).into());
            }
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
    /// Whether the fit follows the exact gradient of the smoother ([`NoiseScorer`]) rather
    /// than differences of filter runs: it fits some subsystem's own variances (`Q[i]`,
    /// `M[i]`: hundreds of parameters on a long chain) and nothing else than variances, by
    /// the exact Gaussian likelihood — the centralized filter (chosen for it when the joint
    /// filter's band was left to the fit and the chain is small enough), with known dropouts
    /// or `p = 1` at every sensor.
    ///
    /// [`NoiseScorer`]: crate::smoother::score::NoiseScorer
    fn follows_score(&self, model: &Model) -> bool {
        let exact = match self.run.filter_kind() {
            FilterKind::Centralized => true,
            FilterKind::Joint => {
                self.choose_band && model.subsystems * model.dims.n <= self.run.max_lifted()
            }
            FilterKind::Distributed => false,
        };
        exact
            && self.params.iter().any(ParamGroup::per_subsystem)
            && !self.params.contains(&ParamGroup::P)
            && (self.run.dropouts() == Dropouts::Known || !model.loses_readings())
    }

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
        if self.follows_score(model) {
            let choice = ObjectiveChoice {
                chosen: self.choose_band,
                ..fixed(None, None)
            };
            return Ok((self.run.with_band(None), Some(choice)));
        }
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
        for key in ["Q", "M"] {
            let each = |(p, _): &(Parameter, f64)| p.per_subsystem() && p.key() == Some(key);
            if self.estimates.iter().any(each) {
                parameter::write_per_subsystem(&mut raw, &self.model, key);
            }
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
    for group in spec.params.iter().filter(|g| g.per_subsystem()) {
        let key = group.key().expect("a variance");
        if model.variation(key).0 {
            return Err(FitError::EachVariesInTime(key).into());
        }
    }
    let parameters = Parameter::all(model, &spec.params);
    let mut warnings = parameter::start_warnings(model, &parameters);
    let score = spec.follows_score(model);
    if spec.params.iter().any(ParamGroup::per_subsystem) && !score {
        warnings.push(format!(
            "{} parameters by differences of filter runs, {} runs a gradient: the exact gradient needs the centralized filter on at most {} lifted states, known dropouts or p = 1 at every sensor, and p left out of params",
            parameters.len(),
            2 * parameters.len(),
            spec.run.max_lifted()
        ));
    }
    let (objective_spec, mut choice) = spec.objective(model, y, u)?;
    let objective = Objective::new(model, &objective_spec, &parameters, y, u, score)?;
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
            let robust_theta = robust
                .as_ref()
                .filter(|_| available[k])
                .map(|r| r[(k, k)].max(0.0).sqrt());
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
        q: spec.params.iter().any(|g| g.key() == Some("Q")),
        m: spec.params.iter().any(|g| g.key() == Some("M")),
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
