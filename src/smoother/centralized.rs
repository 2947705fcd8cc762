//! The RTS smoother on the centralized filter of docs/theory.md §7 (docs/theory.md §9 `centralized`; in the
//! known-dropout mode on its Kalman filter). For `t = T−1, …, 1`, with `T(t+1) = P(t+1|t)`:
//!
//! ```text
//! C_t     = P(t|t) A_eff(t)ᵀ T(t+1)⁻¹                (a Cholesky solve with T(t+1))
//! x̂(t|T)  = x̂(t|t) + C_t (x̂(t+1|T) − x̂(t+1|t))
//! P(t|T)  = P(t|t) + C_t (P(t+1|T) − T(t+1)) C_tᵀ     (symmetrised)
//! ```
//!
//! With `Q = 0`, `T(t+1)` can be singular to working precision and this form can diverge.
//! When the Cholesky factor of some `T(t+1)` fails or its condition estimate exceeds
//! [`MAX_CONDITION`], the whole run is smoothed instead by the information form at full band
//! (the joint smoother with `k = N − 1`, exact `A_eff` and §9's loading), and a note says so.

use nalgebra::{Cholesky, DMatrix, DMatrixView, DVector};

use crate::error::Result;
use crate::filter::centralized::CentralizedLimits;
use crate::filter::{CentralizedFilter, ChainFilter, Dropouts, JointOptions, SecondMoment, Update};
use crate::model::Model;
use crate::smoother::{
    BackwardGain, ForwardPass, GainView, JointSmoother, MeanPass, Smoothed, Smoother,
};

/// Largest condition estimate of `T(t+1)` for which the RTS form is used (docs/theory.md §9).
pub const MAX_CONDITION: f64 = 1e12;

/// The stored forward pass of the centralized filter.
pub struct CentralizedSmoother {
    model: Model,
    known: bool,
    update: Update,
    limits: CentralizedLimits,
    filter: CentralizedFilter,
    x_filt: Vec<DVector<f64>>,
    x_pred: Vec<DVector<f64>>,
    p_filt: Vec<DMatrix<f64>>,
    t_pred: Vec<DMatrix<f64>>,
    a_eff: Vec<DMatrix<f64>>,
    /// The data, to rerun the forward pass in the information form if needed.
    y: Vec<Vec<f64>>,
    u: Vec<Vec<f64>>,
}

impl CentralizedSmoother {
    pub fn new(model: &Model, known: bool, limits: impl Into<CentralizedLimits>) -> Result<Self> {
        let limits = limits.into();
        Ok(Self {
            model: model.clone(),
            known,
            update: Update::Linear,
            limits,
            filter: CentralizedFilter::new(model, known, limits)?,
            x_filt: Vec::new(),
            x_pred: Vec::new(),
            p_filt: Vec::new(),
            t_pred: Vec::new(),
            a_eff: Vec::new(),
            y: Vec::new(),
            u: Vec::new(),
        })
    }

    /// The same smoother on the moments of the mixture filter (docs/theory.md §10):
    /// [`CentralizedFilter::with_mixture_update`] forward, the same backward pass.
    pub fn with_mixture_update(mut self) -> Result<Self> {
        self.filter = self.filter.with_mixture_update()?;
        self.update = Update::Mixture;
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
        self.a_eff.push(self.filter.lifted_system().a_eff.clone());
        self.y.push(y.to_vec());
        self.u.push(u.to_vec());
        Ok(())
    }

    fn arrival(&self) -> Option<&[f64]> {
        self.filter.arrival()
    }

    fn prior(&self) -> (&[f64], &[f64]) {
        self.filter.predicted()
    }

    fn backward(mut self: Box<Self>, keep_gains: bool) -> Result<Smoothed> {
        let model = &self.model.clone();
        let (n, big_n) = (model.dims.n, model.subsystems);
        let steps = self.x_filt.len();
        let mut xs: Vec<Vec<f64>> = self.x_filt.iter().map(|x| x.as_slice().to_vec()).collect();
        // P(t|T) overwrites P(t|t) in place: ps[k] is still P(k|k) until step k ends.
        let mut ps = std::mem::take(&mut self.p_filt);
        let mut mean = MeanPass::new(model);
        let mut gains = Vec::new();
        for k in (0..steps.saturating_sub(1)).rev() {
            let t_next = &self.t_pred[k];
            let chol = Cholesky::new(t_next.clone());
            let condition = chol.as_ref().map_or(f64::INFINITY, |c| {
                let d = c.l_dirty().diagonal();
                (d.max() / d.min()).powi(2)
            });
            let Some(chol) = chol.filter(|_| condition <= MAX_CONDITION) else {
                return self.information_form_fallback(k + 1, condition, keep_gains);
            };
            // Cᵀ = T⁻¹ A_eff P.
            let gain_tr = chol.solve(&(&self.a_eff[k] * &ps[k]));
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
            let diff = &ps[k + 1] - t_next;
            let mut p = &ps[k] + gain_tr.tr_mul(&(diff * &gain_tr));
            p = (&p + p.transpose()) * 0.5;
            ps[k] = p;
            if keep_gains {
                gains.push(BackwardGain::Dense(gain_tr));
            }
        }
        gains.reverse();
        let size = big_n * n;
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

impl CentralizedSmoother {
    /// Smooths the stored data by the information form at full band (docs/theory.md §9 fallback).
    fn information_form_fallback(
        &self,
        t: usize,
        condition: f64,
        keep_gains: bool,
    ) -> Result<Smoothed> {
        let model = &self.model.clone();
        let dropouts = if self.known {
            Dropouts::Known
        } else {
            Dropouts::Unknown
        };
        let opts = JointOptions {
            update: self.update,
            max_memory: self.limits.max_memory,
            ..JointOptions::full_band(model, SecondMoment::Lifted, dropouts)
        };
        let mut joint: Box<dyn Smoother> =
            Box::new(JointSmoother::new(model, opts)?.loading_as_noise());
        for (y, u) in self.y.iter().zip(&self.u) {
            joint.step(y, u)?;
        }
        let mut out = joint.backward(keep_gains)?;
        out.bands = None;
        // The joint smoother may itself have rerun with a larger loading.
        out.forward.get_or_insert(ForwardPass {
            opts,
            loading_as_noise: true,
        });
        out.notes.push(format!(
            "centralized smoother: T({}) is numerically singular (condition estimate {condition:.1e} > {MAX_CONDITION:e}); smoothed by the information form at full band with loading {:e} instead (docs/theory.md §9)",
            t + 1,
            opts.loading_for(model)
        ));
        Ok(out)
    }
}
