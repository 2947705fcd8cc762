//! The RTS smoother on the centralized filter of docs/theory.md §7 (docs/theory.md §9 `centralized`; in the
//! known-dropout mode on its Kalman filter). For `t = T−1, …, 1`, with `T(t+1) = P(t+1|t)`:
//!
//! ```text
//! C_t     = P(t|t) A_eff(t)ᵀ T(t+1)⁻¹                (a Cholesky solve with T(t+1))
//! x̂(t|T)  = x̂(t|t) + C_t (x̂(t+1|T) − x̂(t+1|t))
//! P(t|T)  = P(t|t) + C_t (P(t+1|T) − T(t+1)) C_tᵀ     (its lower triangle, mirrored)
//! ```
//!
//! by the dense kernels of [`crate::linalg::dense`] (faer's, on the rayon threads); `A_eff P(t|t)`
//! by `A_eff`'s row envelope where it is narrow ([`Transition::times_symmetric`],
//! docs/theory.md §7).
//!
//! With `Q = 0`, `T(t+1)` can be singular (a state known exactly) or singular to working
//! precision. When its Cholesky factor fails or its condition estimate exceeds
//! [`MAX_CONDITION`], the gain takes its Moore–Penrose inverse, `C_t = P(t|t) A_effᵀ T(t+1)⁺`,
//! which is the RTS gain there: the range of `A_eff P(t|t)` lies in that of `T(t+1)`.

use std::sync::Arc;

use faer::{Accum, MatMut, MatRef};
use nalgebra::{DMatrix, DMatrixView, DVector};

use crate::error::{Error, Result};
use crate::filter::centralized::CentralizedLimits;
use crate::filter::{CentralizedFilter, ChainFilter};
use crate::lifted::Transition;
use crate::linalg::dense::{self, Cholesky};
use crate::model::Model;
use crate::smoother::{BackwardGain, GainView, MeanPass, Smoothed, Smoother};

/// Largest condition estimate of `T(t+1)` for which the RTS form is used (docs/theory.md §9).
pub const MAX_CONDITION: f64 = 1e10;

/// The stored forward pass of the centralized filter.
pub struct CentralizedSmoother {
    model: Model,
    filter: CentralizedFilter,
    x_filt: Vec<DVector<f64>>,
    x_pred: Vec<DVector<f64>>,
    p_filt: Vec<DMatrix<f64>>,
    t_pred: Vec<DMatrix<f64>>,
    /// `A_eff(t)`, shared between the steps of an override window.
    a_eff: Vec<Arc<Transition>>,
}

impl CentralizedSmoother {
    pub fn new(model: &Model, known: bool, limits: impl Into<CentralizedLimits>) -> Result<Self> {
        Ok(Self {
            model: model.clone(),
            filter: CentralizedFilter::new(model, known, limits.into())?,
            x_filt: Vec::new(),
            x_pred: Vec::new(),
            p_filt: Vec::new(),
            t_pred: Vec::new(),
            a_eff: Vec::new(),
        })
    }

    /// The same smoother on the moments of the mixture filter (docs/theory.md §10):
    /// [`CentralizedFilter::with_mixture_update`] forward, the same backward pass.
    pub fn with_mixture_update(mut self) -> Result<Self> {
        self.filter = self.filter.with_mixture_update()?;
        Ok(self)
    }
}

impl Smoother for CentralizedSmoother {
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        self.filter.step(y, u)?;
        let size = self.model.subsystems * self.model.dims.n;
        let (xf, _) = self.filter.filtered();
        let (xp, _) = self.filter.predicted();
        self.x_filt.push(DVector::from_column_slice(xf));
        self.x_pred.push(DVector::from_column_slice(xp));
        self.p_filt.push(DMatrix::from_column_slice(
            size,
            size,
            self.filter.full_filtered_cov(),
        ));
        self.t_pred.push(DMatrix::from_column_slice(
            size,
            size,
            self.filter.full_predicted_cov(),
        ));
        let a_eff = &self.filter.lifted_system().a_eff;
        let shared = match self.a_eff.last() {
            Some(last) if Arc::ptr_eq(last, a_eff) || last.dense == a_eff.dense => Arc::clone(last),
            _ => Arc::clone(a_eff),
        };
        self.a_eff.push(shared);
        Ok(())
    }

    fn arrival(&self) -> Option<&[f64]> {
        self.filter.arrival()
    }

    fn prior(&self) -> (&[f64], &[f64]) {
        self.filter.predicted()
    }

    fn prior_second_moments(&self, out: &mut [f64]) -> bool {
        self.filter.second_moments(out)
    }

    fn backward(self: Box<Self>, keep_gains: bool) -> Result<Smoothed> {
        self.backward_visiting(keep_gains, &mut |_| {})
    }
}

/// What one backward step `t = k+1` of the centralized smoother holds in full (`S = N·n`):
/// the statistics beyond the diagonal blocks of `P(t|T)` that [`crate::smoother::score`]
/// needs, the lag-one covariance `Cov(x(t), x(t+1) | T) = C_t P(t+1|T)` among them.
pub struct BackwardStep<'a> {
    /// 0-based: the step `t = k+1`, whose transition to `t+1` this is.
    pub k: usize,
    /// `A_eff(t)`, the transition from `t` to `t+1`.
    pub a_eff: &'a DMatrix<f64>,
    /// `x̂(t|t)` and `x̂(t+1|t)`.
    pub x_filtered: &'a [f64],
    pub x_predicted_next: &'a [f64],
    /// `x̂(t|T)` and `x̂(t+1|T)`.
    pub x_smoothed: &'a [f64],
    pub x_smoothed_next: &'a [f64],
    /// `P(t|T)` and `P(t+1|T)`, whole.
    pub p_smoothed: &'a DMatrix<f64>,
    pub p_smoothed_next: &'a DMatrix<f64>,
    /// `C_tᵀ`.
    pub gain_transposed: &'a DMatrix<f64>,
}

impl CentralizedSmoother {
    /// The log density of the last forward step's measurements (docs/theory.md §16).
    pub fn log_likelihood(&self) -> Option<f64> {
        self.filter.log_likelihood()
    }

    /// [`Smoother::backward`], showing `visit` every backward step, `t = T−1, …, 1`, once
    /// `P(t|T)` is formed.
    pub fn backward_visiting(
        mut self: Box<Self>,
        keep_gains: bool,
        visit: &mut dyn FnMut(&BackwardStep),
    ) -> Result<Smoothed> {
        let model = &self.model.clone();
        let (n, big_n) = (model.dims.n, model.subsystems);
        let steps = self.x_filt.len();
        let mut xs: Vec<Vec<f64>> = self.x_filt.iter().map(|x| x.as_slice().to_vec()).collect();
        // P(t|T) overwrites P(t|t) in place: ps[k] is still P(k|k) until step k ends.
        let mut ps = std::mem::take(&mut self.p_filt);
        let mut mean = MeanPass::new(model);
        let mut gains = Vec::new();
        let size = big_n * n;
        let mut factor = DMatrix::zeros(size, size);
        let mut cholesky = Cholesky::new(size);
        let (mut diff, mut diff_gain) = (DMatrix::zeros(size, size), DMatrix::zeros(size, size));
        let mut envelope_scratch = Vec::new();
        for k in (0..steps.saturating_sub(1)).rev() {
            let t_next = &self.t_pred[k];
            // Cᵀ = T⁻¹ A_eff P = L⁻ᵀ L⁻¹ (A_eff P), T = L Lᵀ.
            let mut gain_tr = DMatrix::zeros(size, size);
            self.a_eff[k].times_symmetric(
                ps[k].as_slice(),
                gain_tr.as_mut_slice(),
                &mut envelope_scratch,
            );
            factor.copy_from(t_next);
            let factored = cholesky.factor(faer_mut(&mut factor));
            if factored && condition(factor.diagonal().as_slice()) <= MAX_CONDITION {
                let l = faer_ref(&factor);
                dense::solve_lower(l, faer_mut(&mut gain_tr));
                dense::solve_lower_transposed(l, faer_mut(&mut gain_tr));
            } else {
                gain_tr = pseudo_inverse(t_next, k + 1)? * gain_tr;
            }
            let (xs_head, xs_tail) = xs.split_at_mut(k + 1);
            mean.apply(
                model,
                k + 1,
                GainView::Dense(&gain_tr),
                self.x_filt[k].as_slice(),
                self.x_pred[k].as_slice(),
                &xs_tail[0],
                &mut xs_head[k],
            );
            // P(t|T) = P(t|t) + C (P(t+1|T) − T) Cᵀ, of which only the lower triangle is
            // formed (the result is exactly symmetric).
            diff.copy_from(&ps[k + 1]);
            diff -= t_next;
            dense::product(
                faer_mut(&mut diff_gain),
                Accum::Replace,
                faer_ref(&diff),
                faer_ref(&gain_tr),
                1.0,
            );
            dense::symmetric_product(
                faer_mut(&mut ps[k]),
                Accum::Add,
                faer_ref(&gain_tr).transpose(),
                faer_ref(&diff_gain),
                1.0,
            );
            visit(&BackwardStep {
                k,
                a_eff: &self.a_eff[k].dense,
                x_filtered: self.x_filt[k].as_slice(),
                x_predicted_next: self.x_pred[k].as_slice(),
                x_smoothed: &xs[k],
                x_smoothed_next: &xs[k + 1],
                p_smoothed: &ps[k],
                p_smoothed_next: &ps[k + 1],
                gain_transposed: &gain_tr,
            });
            if keep_gains {
                gains.push(BackwardGain::Dense(gain_tr));
            }
        }
        gains.reverse();
        let p = ps
            .iter()
            .map(|m| {
                (0..big_n)
                    .flat_map(|i| {
                        let view: DMatrixView<f64> = m.view((i * n, i * n), (n, n));
                        view.iter().copied().collect::<Vec<_>>()
                    })
                    .collect()
            })
            .collect();
        debug_assert!(xs.iter().all(|x| x.len() == size));
        Ok(Smoothed {
            x: xs,
            p,
            bands: None,
            notes: Vec::new(),
            gains: keep_gains.then_some(gains),
            forward: None,
        })
    }
}

/// `λ_max / λ_min` of `T` from the diagonal of its Cholesky factor (an estimate from below).
fn condition(diagonal: &[f64]) -> f64 {
    let (max, min) = diagonal
        .iter()
        .fold((f64::MIN, f64::MAX), |(max, min), &d| {
            (max.max(d), min.min(d))
        });
    (max / min).powi(2)
}

/// A column-major nalgebra matrix as faer sees it.
fn faer_ref(m: &DMatrix<f64>) -> MatRef<'_, f64> {
    MatRef::from_column_major_slice(m.as_slice(), m.nrows(), m.ncols())
}

fn faer_mut(m: &mut DMatrix<f64>) -> MatMut<'_, f64> {
    let (rows, cols) = m.shape();
    MatMut::from_column_major_slice_mut(m.as_mut_slice(), rows, cols)
}

/// `T⁺`, singular values below `σ_max / MAX_CONDITION` taken as zero (docs/theory.md §9):
/// directions that small are rounding, not information.
fn pseudo_inverse(t_next: &DMatrix<f64>, t: usize) -> Result<DMatrix<f64>> {
    let svd = t_next.clone().svd(true, true);
    let tolerance = svd.singular_values.max() / MAX_CONDITION;
    svd.pseudo_inverse(tolerance).map_err(|_| Error::Numerical {
        t,
        i: 1,
        msg: "centralized smoother: the singular value decomposition of T(t+1) did not converge"
            .into(),
    })
}
