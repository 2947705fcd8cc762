//! The gradient of the exact Gaussian log-likelihood with respect to each subsystem's noise
//! variances, `∂ℓ/∂Q(i)_kk` and `∂ℓ/∂M(i)_kk`, from one run of the centralized smoother
//! (docs/theory.md §16, "Each subsystem's own noise").
//!
//! Fisher's identity: the score of the measurements' density is the expected score of the
//! joint density of states and measurements given all the measurements,
//! `∂ℓ/∂θ = E[∂ log p(X, Y; θ)/∂θ | Y]`. In that joint density `Q(t, i)` enters only through
//! `ω(t, i) = x(t+1, i) − (A_eff(t) x(t) + c(t))_i ~ N(0, Q(t, i))` and `M(t, i)` only through
//! the received elements `o` of `d(t, i) = y_o − (J x(t, i) + R u(t, i))_o ~ N(0, M_oo)`, so
//! with `W = E[ω ωᵀ | Y]` and `E = E[d_o d_oᵀ | Y]`
//!
//! ```text
//! ∂ℓ/∂Q_kk = −½ Σ_t ((Q⁻¹)_kk − (Q⁻¹ W Q⁻¹)_kk)
//! ∂ℓ/∂M_kk = −½ Σ_t ((M_oo⁻¹)_kk − (M_oo⁻¹ E M_oo⁻¹)_kk)      (k received at t)
//! W = e eᵀ + P(t+1|T) − F C_t P(t+1|T) − (F C_t P(t+1|T))ᵀ + F P(t|T) Fᵀ   (block i)
//! e = (x̂(t+1|T) − x̂(t+1|t)) − F (x̂(t|T) − x̂(t|t)),   F = A_eff(t)
//! E = r rᵀ + J P(t|T)_ii Jᵀ,   r = y_o − (J x̂(t|T)_i + R u)_o
//! ```
//!
//! where `Cov(x(t), x(t+1) | Y) = C_t P(t+1|T)` with the RTS gain `C_t`, and
//! `c(t) = x̂(t+1|t) − F x̂(t|t)` holds the inputs. The filter runs in the known-dropout mode,
//! whose log-likelihood is the exact Gaussian density of the elements received (with `p = 1`
//! at every sensor it is also the unknown-dropout mixture's).

use nalgebra::{DMatrix, DVector};

use crate::error::{Error, Result};
use crate::filter::centralized::CentralizedLimits;
use crate::model::Model;
use crate::smoother::Smoother;
use crate::smoother::centralized::{BackwardStep, CentralizedSmoother};

/// The log-likelihood and its gradient with respect to each subsystem's noise variances.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseScore {
    /// `ℓ = Σ_t log p(y(t) | y(1..t−1))` over the elements received.
    pub log_likelihood: f64,
    /// `∂ℓ/∂Q(i)_kk` at `i·n + k` (0-based), `Q(i)_kk` one value over every step; empty when
    /// not asked for.
    pub q: Vec<f64>,
    /// `∂ℓ/∂M(i)_kk` at `i·q + k`; empty when not asked for.
    pub m: Vec<f64>,
}

/// Which parts of the gradient to compute (the `Q` part costs `O((N n)³)` a step).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ScoreParts {
    pub q: bool,
    pub m: bool,
}

/// The forward pass of [`NoiseScore`]: the centralized smoother with what the `M` part needs.
pub struct NoiseScorer {
    model: Model,
    smoother: Box<CentralizedSmoother>,
    parts: ScoreParts,
    /// Per step, `y(t, ·)` (NaN where not received) and `R u(t, ·)`.
    y: Vec<f64>,
    input_term: Vec<f64>,
    log_likelihood: f64,
}

impl NoiseScorer {
    pub fn new(model: &Model, parts: ScoreParts, limits: CentralizedLimits) -> Result<Self> {
        Ok(Self {
            model: model.clone(),
            smoother: Box::new(CentralizedSmoother::new(model, true, limits)?),
            parts,
            y: Vec::new(),
            input_term: Vec::new(),
            log_likelihood: 0.0,
        })
    }

    /// One step `t`, `y(t, ·)` with NaN where an element is not received.
    pub fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        self.smoother.step(y, u)?;
        self.log_likelihood += self.smoother.log_likelihood().unwrap_or(0.0);
        let t = self.y.len() / y.len().max(1) + 1;
        self.y.extend_from_slice(y);
        let (m, q) = (self.model.dims.m, self.model.dims.q);
        for i in 0..self.model.subsystems {
            let r = &self.model.params(t, i + 1).R;
            let ru = r * DVector::from_column_slice(&u[i * m..(i + 1) * m]);
            debug_assert_eq!(ru.len(), q);
            self.input_term.extend_from_slice(ru.as_slice());
        }
        Ok(())
    }

    /// The backward pass and the gradient.
    pub fn finish(self) -> Result<NoiseScore> {
        let model = &self.model;
        let (n, q, big_n) = (model.dims.n, model.dims.q, model.subsystems);
        let q_inverses = inverses(model, "Q", self.parts.q)?;
        let mut grad_q = vec![0.0; if self.parts.q { big_n * n } else { 0 }];
        let smoothed = if self.parts.q {
            self.smoother.backward_visiting(false, &mut |step| {
                add_transition_score(model, &q_inverses, step, &mut grad_q);
            })?
        } else {
            self.smoother.backward(false)?
        };
        let mut grad_m = vec![0.0; if self.parts.m { big_n * q } else { 0 }];
        if self.parts.m {
            for (k, (x, p)) in smoothed.x.iter().zip(&smoothed.p).enumerate() {
                let cells = k * big_n * q..(k + 1) * big_n * q;
                add_measurement_score(
                    model,
                    k + 1,
                    (x, p),
                    &self.y[cells.clone()],
                    &self.input_term[cells],
                    &mut grad_m,
                )?;
            }
        }
        Ok(NoiseScore {
            log_likelihood: self.log_likelihood,
            q: grad_q,
            m: grad_m,
        })
    }
}

/// The inverse of `key` (`Q` or `M`) of every parameter set, when `wanted`.
fn inverses(model: &Model, key: &str, wanted: bool) -> Result<Vec<DMatrix<f64>>> {
    if !wanted {
        return Ok(Vec::new());
    }
    model
        .param_sets()
        .iter()
        .map(|set| {
            set.get(key)
                .clone()
                .cholesky()
                .map(|c| c.inverse())
                .ok_or_else(|| Error::Numerical {
                    t: 1,
                    i: 1,
                    msg: format!("the score of {key}: {key} is not positive definite"),
                })
        })
        .collect()
}

/// Adds the `Q` part of step `t = k+1`'s transition to `grad`.
fn add_transition_score(
    model: &Model,
    q_inverses: &[DMatrix<f64>],
    step: &BackwardStep,
    grad: &mut [f64],
) {
    let n = model.dims.n;
    let f = step.a_eff;
    let size = f.nrows();
    let difference =
        |a: &[f64], b: &[f64]| DVector::from_iterator(size, a.iter().zip(b).map(|(a, b)| a - b));
    let delta = difference(step.x_smoothed, step.x_filtered);
    let delta_next = difference(step.x_smoothed_next, step.x_predicted_next);
    let e = delta_next - f * delta;
    // F C_t, C_t = (C_tᵀ)ᵀ, and F P(t|T).
    let f_gain = f * step.gain_transposed.transpose();
    let f_p = f * step.p_smoothed;
    let p_next = step.p_smoothed_next;
    let window = model.window(step.k + 1);
    for i in 0..model.subsystems {
        let r = i * n;
        let w = DMatrix::from_fn(n, n, |a, b| {
            let (ra, rb) = (r + a, r + b);
            let (mut cross_ab, mut cross_ba, mut fpf) = (0.0, 0.0, 0.0);
            for j in 0..size {
                cross_ab += f_gain[(ra, j)] * p_next[(j, rb)];
                cross_ba += f_gain[(rb, j)] * p_next[(j, ra)];
                fpf += f_p[(ra, j)] * f[(rb, j)];
            }
            e[ra] * e[rb] + p_next[(ra, rb)] - cross_ab - cross_ba + fpf
        });
        let q_inverse = &q_inverses[window.ids[i] as usize];
        let weighted = q_inverse * w * q_inverse;
        for kk in 0..n {
            grad[r + kk] -= 0.5 * (q_inverse[(kk, kk)] - weighted[(kk, kk)]);
        }
    }
}

/// Adds the `M` part of step `t`'s received elements to `grad`: `smoothed` holds `x̂(t|T)`
/// and the diagonal blocks of `P(t|T)`.
fn add_measurement_score(
    model: &Model,
    t: usize,
    smoothed: (&[f64], &[f64]),
    y: &[f64],
    input_term: &[f64],
    grad: &mut [f64],
) -> Result<()> {
    let (n, q) = (model.dims.n, model.dims.q);
    let (x, p) = smoothed;
    for i in 0..model.subsystems {
        let received: Vec<usize> = (0..q).filter(|&k| y[i * q + k].is_finite()).collect();
        if received.is_empty() {
            continue;
        }
        let set = model.params(t, i + 1);
        let j = set.J.select_rows(&received);
        let x_i = DVector::from_column_slice(&x[i * n..(i + 1) * n]);
        let p_i = DMatrix::from_column_slice(n, n, &p[i * n * n..(i + 1) * n * n]);
        let residual = DVector::from_iterator(
            received.len(),
            received
                .iter()
                .map(|&k| y[i * q + k] - input_term[i * q + k]),
        ) - &j * x_i;
        let expected = &residual * residual.transpose() + &j * p_i * j.transpose();
        let m_inverse = set
            .M
            .select_rows(&received)
            .select_columns(&received)
            .cholesky()
            .ok_or_else(|| Error::Numerical {
                t,
                i: i + 1,
                msg: "the score of M: M is not positive definite".into(),
            })?
            .inverse();
        let weighted = &m_inverse * expected * &m_inverse;
        for (a, &k) in received.iter().enumerate() {
            grad[i * q + k] -= 0.5 * (m_inverse[(a, a)] - weighted[(a, a)]);
        }
    }
    Ok(())
}
