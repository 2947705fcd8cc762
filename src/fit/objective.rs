//! The objective of a fit (docs/theory.md §16): `f(θ) = −ℓ(θ) / n_obs` on the scale `θ`, its
//! gradient (central differences of filter runs, or the smoother's exact one), and at the
//! optimum the Hessian and the intervals it gives.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};

use argmin::core::{CostFunction, Gradient};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use super::parameter::{self, Parameter};
use super::{LOGIT_BOUND, noise_score};
use crate::accuracy::Z_95;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::run::{self, CheckedSpec};
use crate::smoother::score::ScoreParts;

/// Each log variance stays within `±LOG_RANGE` of its starting value.
const LOG_RANGE: f64 = 25.0;
/// Step in `θ` of the gradient's central differences (and of the per-step scores).
const GRADIENT_STEP: f64 = 1e-5;
/// Step in `θ` of the Hessian's central differences.
const HESSIAN_STEP: f64 = 1e-3;
/// Step in `θ` of the central differences of the exact gradient that give the Hessian.
const SCORE_HESSIAN_STEP: f64 = 1e-4;
/// Weight of the quadratic wall outside the box, per unit of `θ` squared.
const WALL: f64 = 1e3;
/// `θ_k` within this of a bound of its box is on the boundary: no interval.
const ON_BOUNDARY: f64 = 1e-3;
/// A candidate whose `Q` or `M` is not a covariance, or whose filter breaks down, costs this
/// much more than the start (the log-likelihood there is `−∞`; a finite cliff keeps the line
/// search going).
const CLIFF: f64 = 1e6;

/// `f(θ) = −ℓ(θ) / n_obs` over the data, with a quadratic wall outside the box.
pub(super) struct Objective<'a> {
    model: &'a Model,
    run: &'a CheckedSpec,
    parameters: &'a [Parameter],
    y: &'a [f64],
    u: Option<&'a [f64]>,
    pub(super) theta0: Vec<f64>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    pub(super) observations: usize,
    /// `f(θ₀)`, the cost at the start; `f(θ₀) + CLIFF` is the cost where `ℓ = −∞`.
    pub(super) start_cost: f64,
    pub(super) evaluations: Arc<AtomicUsize>,
    /// Where the fit follows the smoother's exact gradient ([`CheckedFit::follows_score`]):
    /// the parts it needs, and the last point's `ℓ` and `∂ℓ/∂θ` (the optimiser asks for the
    /// cost and then the gradient at each point, one smoother run for both).
    score: Option<ScoreMode>,
}

/// The smoother's exact gradient ([`noise_score`]) as the objective's.
struct ScoreMode {
    parts: ScoreParts,
    last: std::sync::Mutex<Option<(Vec<f64>, Option<Scored>)>>,
}

/// `ℓ` and `∂ℓ/∂θ` at a point.
type Scored = (f64, Vec<f64>);

impl ScoreMode {
    /// `∂(−ℓ)/∂θ` at `θ` (inside the box); `None` where `ℓ = −∞`.
    fn cost_gradient(&self, objective: &Objective, theta: &[f64]) -> Option<Vec<f64>> {
        let (_, gradient) = objective.scored(self, theta)?;
        Some(gradient.iter().map(|g| -g).collect())
    }
}

impl<'a> Objective<'a> {
    /// The objective at `model`'s values; an error of the configured model itself (bad
    /// inputs, a filter that breaks down) is the fit's error.
    pub(super) fn new(
        model: &'a Model,
        run_spec: &'a CheckedSpec,
        parameters: &'a [Parameter],
        y: &'a [f64],
        u: Option<&'a [f64]>,
        follows_score: bool,
    ) -> Result<Self> {
        let theta0: Vec<f64> = parameters.iter().map(|p| p.start(model)).collect();
        let of = |key: &str| parameters.iter().any(|p| p.key() == Some(key));
        let score = follows_score.then(|| ScoreMode {
            parts: ScoreParts {
                q: of("Q"),
                m: of("M"),
            },
            last: std::sync::Mutex::new(None),
        });
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
            score,
        };
        let start = objective
            .model_at(&objective.theta0)
            .ok_or_else(|| Error::Usage("fit: the configured Q or M is not a covariance".into()))?;
        let mut loglik: f64 = run::log_likelihood(&start, run_spec, y, u)?.iter().sum();
        objective.evaluations.fetch_add(1, Ordering::Relaxed);
        if let Some(mode) = &objective.score {
            // The objective is the smoother's ℓ, the same density computed once more.
            loglik = objective
                .scored(mode, &objective.theta0)
                .map_or(f64::NEG_INFINITY, |(l, _)| l);
        }
        objective.start_cost = -loglik / observations as f64;
        Ok(objective)
    }

    /// `θ` moved into the box.
    pub(super) fn clamp(&self, theta: &[f64]) -> Vec<f64> {
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
    pub(super) fn model_at(&self, theta: &[f64]) -> Option<Model> {
        let values = self.parameters.iter().zip(theta);
        let model = Parameter::set_all(self.model, values.map(|(p, &t)| (*p, p.value(t))));
        parameter::noise_is_valid(&model).then_some(model)
    }

    /// `ℓ` and `∂ℓ/∂θ` at `θ` (inside the box) by the smoother ([`noise_score`]); `None` where
    /// `ℓ = −∞`.
    fn scored(&self, mode: &ScoreMode, theta: &[f64]) -> Option<Scored> {
        if let Ok(last) = mode.last.lock()
            && let Some((at, value)) = last.as_ref()
            && at.as_slice() == theta
        {
            return value.clone();
        }
        self.evaluations.fetch_add(1, Ordering::Relaxed);
        let value = self.model_at(theta).and_then(|model| {
            let limits = self.run.centralized_limits();
            let score = noise_score(&model, limits, mode.parts, self.y, self.u).ok()?;
            let (n, q) = (model.dims.n, model.dims.q);
            let gradient = self
                .parameters
                .iter()
                .zip(theta)
                .map(|(p, &t)| {
                    let d_value = match *p {
                        Parameter::Q(k) => score.q.iter().skip(k).step_by(n).sum(),
                        Parameter::M(k) => score.m.iter().skip(k).step_by(q).sum(),
                        Parameter::QOf { i, k } => score.q[i * n + k],
                        Parameter::MOf { i, k } => score.m[i * q + k],
                        Parameter::P => unreachable!("p is not fitted by the score"),
                    };
                    d_value * p.slope(t)
                })
                .collect();
            Some((score.log_likelihood, gradient))
                .filter(|(l, g): &Scored| l.is_finite() && g.iter().all(|v| v.is_finite()))
        });
        if let Ok(mut last) = mode.last.lock() {
            *last = Some((theta.to_vec(), value.clone()));
        }
        value
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
    pub(super) fn cost(&self, theta: &[f64]) -> f64 {
        let inside = self.clamp(theta);
        let wall: f64 = theta
            .iter()
            .zip(&inside)
            .map(|(t, c)| 0.5 * WALL * (t - c).powi(2))
            .sum();
        let loglik = match &self.score {
            Some(mode) => self.scored(mode, &inside).map(|(l, _)| l),
            None => self.step_logliks(&inside).map(|l| l.iter().sum()),
        };
        let f = loglik.map_or(self.start_cost + CLIFF, |l| -l / self.observations as f64);
        f + wall
    }

    /// `∂f/∂θ` from the smoother's exact gradient: `−(∂ℓ/∂θ) / n_obs` inside the box (zero
    /// where `ℓ = −∞`, on the cliff), the wall's slope outside it.
    fn score_gradient(&self, mode: &ScoreMode, theta: &[f64]) -> Vec<f64> {
        let inside = self.clamp(theta);
        let scored = self.scored(mode, &inside);
        (0..theta.len())
            .map(|k| {
                if theta[k] != inside[k] {
                    WALL * (theta[k] - inside[k])
                } else {
                    scored
                        .as_ref()
                        .map_or(0.0, |(_, g)| -g[k] / self.observations as f64)
                }
            })
            .collect()
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
    /// `∂ℓ_t/∂θ` (step `GRADIENT_STEP`), every filter run in parallel; where the fit follows
    /// the smoother's exact gradient, the Hessian is its central differences (step
    /// `SCORE_HESSIAN_STEP`, `2d` smoother runs) and there are no scores of each step.
    pub(super) fn curvature(&self, theta: &[f64]) -> Curvature {
        if let Some(mode) = &self.score {
            return self.score_curvature(mode, theta);
        }
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
        Curvature {
            hessian,
            scores: Some(scores),
        }
    }

    /// The Hessian of `−ℓ` by central differences of the exact gradient, made symmetric.
    fn score_curvature(&self, mode: &ScoreMode, theta: &[f64]) -> Curvature {
        let d = theta.len();
        let h = SCORE_HESSIAN_STEP;
        let gradients: Vec<Option<Vec<f64>>> = Self::plus_minus(theta, h)
            .par_iter()
            .map(|p| {
                let inside = self.clamp(p);
                let gradient = mode.cost_gradient(self, &inside);
                gradient.filter(|_| inside == *p)
            })
            .collect();
        let mut hessian = DMatrix::from_element(d, d, f64::NAN);
        for k in 0..d {
            if let (Some(plus), Some(minus)) = (&gradients[2 * k], &gradients[2 * k + 1]) {
                for j in 0..d {
                    hessian[(j, k)] = (plus[j] - minus[j]) / (2.0 * h);
                }
            }
        }
        let hessian = (&hessian + hessian.transpose()) * 0.5;
        Curvature {
            hessian,
            scores: None,
        }
    }
}

/// The Hessian of `−ℓ` and the per-step scores at the optimum.
pub(super) struct Curvature {
    pub(super) hessian: DMatrix<f64>,
    /// `T × d`: row `t` is `∂ℓ_t/∂θ` (`None` where the Hessian comes from the exact
    /// gradient: no robust figures).
    scores: Option<DMatrix<f64>>,
}

impl Curvature {
    /// Why each parameter has no interval (`None`: it has one), the covariance `H⁻¹` of `θ̂`
    /// and the robust one `H⁻¹ B H⁻¹` (`B = Σ_t s_t s_tᵀ`), over the parameters with an
    /// interval (zero elsewhere). A parameter on the boundary of its box has none, and so has
    /// one whose interval would reach past the box (the data do not bound it inside its
    /// range); while the Hessian of the others is not positive definite, the one that weighs
    /// most in its least curved direction has none either. One parameter is set aside at a
    /// time, and the others' figures are those without it.
    pub(super) fn covariances(
        &self,
        objective: &Objective,
        theta: &[f64],
    ) -> (Vec<Option<NoInterval>>, DMatrix<f64>, Option<DMatrix<f64>>) {
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
                return (missing, DMatrix::zeros(d, d), None);
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
            let spread = |m: &DMatrix<f64>| {
                let mut full = DMatrix::zeros(d, d);
                for (a, &j) in kept.iter().enumerate() {
                    for (c, &k) in kept.iter().enumerate() {
                        full[(j, k)] = m[(a, c)];
                    }
                }
                full
            };
            let robust = self.scores.as_ref().map(|scores| {
                let s = scores.select_columns(&kept);
                spread(&(&inverse * (s.transpose() * &s) * &inverse))
            });
            return (missing, spread(&inverse), robust);
        }
    }
}

/// Why a parameter has no interval.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum NoInterval {
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

    /// The smoother's exact gradient where the fit follows it, else central differences,
    /// the `2d` filter runs in parallel.
    fn gradient(&self, theta: &Self::Param) -> std::result::Result<Vec<f64>, argmin::core::Error> {
        if let Some(mode) = &self.score {
            return Ok(self.score_gradient(mode, theta));
        }
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
