//! The per-subsystem RTS smoother on the two-step filter (docs/theory.md §9 `distributed`): `v̂` is
//! taken as a known input, as the filter does, so each subsystem is smoothed on its own in
//! `O(n³)` per step, without communication. For each `i` and `t = T−1, …, 1`:
//!
//! ```text
//! T_i     = A P_i(t|t) Aᵀ + Q                       (the filter's own T(t+1))
//! C_i     = P_i(t|t) Aᵀ T_i⁻¹                        (a Cholesky solve; never an inverse)
//! x̂_i(t|T) = x̂_i(t|t) + C_i (x̂_i(t+1|T) − x̂_i(t+1|t))
//! P_i(t|T) = P_i(t|t) + C_i (P_i(t+1|T) − T_i) C_iᵀ  (symmetrised)
//! ```
//!
//! It inherits the two-step filter's overconfidence and, with `Q = 0`, can be worse than its
//! own filter (it trusts `x(t+1) = A x + B v̂` exactly).

use nalgebra::{Cholesky, DMatrix, DMatrixView};

use crate::error::{Error, Result};
use crate::filter::ChainFilter;
use crate::model::Model;
use crate::smoother::{BackwardGain, GainView, MeanPass, Smoothed, Smoother};

/// The forward pass of a filter that predicts each subsystem with `x̂⁺ = A x̂ + …`,
/// `T⁺ = A P Aᵀ + Q`, stored for the per-subsystem RTS pass.
pub struct DistributedSmoother {
    model: Model,
    filter: Box<dyn ChainFilter>,
    x_filt: Vec<Vec<f64>>,
    p_filt: Vec<Vec<f64>>,
    x_pred: Vec<Vec<f64>>,
    t_pred: Vec<Vec<f64>>,
}

impl DistributedSmoother {
    pub fn new(model: &Model, filter: Box<dyn ChainFilter>) -> Self {
        Self {
            model: model.clone(),
            filter,
            x_filt: Vec::new(),
            p_filt: Vec::new(),
            x_pred: Vec::new(),
            t_pred: Vec::new(),
        }
    }
}

/// Scratch of one RTS step of an `n`-state subsystem.
struct Rts {
    t_mat: DMatrix<f64>,
    ap: DMatrix<f64>,
    gain_tr: DMatrix<f64>,
    diff: DMatrix<f64>,
    tmp: DMatrix<f64>,
}

impl Rts {
    fn new(n: usize) -> Self {
        Self {
            t_mat: DMatrix::zeros(n, n),
            ap: DMatrix::zeros(n, n),
            gain_tr: DMatrix::zeros(n, n),
            diff: DMatrix::zeros(n, n),
            tmp: DMatrix::zeros(n, n),
        }
    }

    /// The covariance half of one RTS step: `C_iᵀ` into `gain_tr` and `P_i(t|T)` into `ps`;
    /// false when `T` is not positive definite.
    fn step(
        &mut self,
        a: &DMatrix<f64>,
        p: &[f64],
        t_next: &[f64],
        ps_next: &[f64],
        gain_tr: &mut [f64],
        ps: &mut [f64],
    ) -> bool {
        let n = a.nrows();
        let p = DMatrixView::from_slice(p, n, n);
        // Cᵀ = T⁻¹ A P.
        self.ap.gemm(1.0, a, &p, 0.0);
        self.t_mat.copy_from_slice(t_next);
        let t_mat = std::mem::replace(&mut self.t_mat, DMatrix::zeros(0, 0));
        match Cholesky::new(t_mat) {
            Some(chol) => {
                self.gain_tr.copy_from(&self.ap);
                chol.solve_mut(&mut self.gain_tr);
                self.t_mat = chol.unpack();
            }
            None => {
                // A singular T (a state known exactly, Q = 0): the gain with the
                // Moore–Penrose inverse, which is the RTS gain there (docs/theory.md §9).
                let t_mat = DMatrixView::from_slice(t_next, n, n).into_owned();
                let scale = t_mat.amax();
                let Ok(pinv) = t_mat.pseudo_inverse(scale * n as f64 * f64::EPSILON) else {
                    self.t_mat = DMatrix::zeros(n, n);
                    return false;
                };
                self.gain_tr.gemm(1.0, &pinv, &self.ap, 0.0);
                self.t_mat = DMatrix::zeros(n, n);
            }
        }
        gain_tr.copy_from_slice(self.gain_tr.as_slice());
        // P(t|T) = P + C (P(t+1|T) − T) Cᵀ.
        for k in 0..n * n {
            self.diff.as_mut_slice()[k] = ps_next[k] - t_next[k];
        }
        self.tmp.gemm(1.0, &self.diff, &self.gain_tr, 0.0); // (Ps − T) Cᵀ
        let mut out = nalgebra::DMatrixViewMut::from_slice(ps, n, n);
        out.copy_from(&p);
        out.gemm_tr(1.0, &self.gain_tr, &self.tmp, 1.0);
        crate::linalg::symmetrize(&mut out);
        true
    }
}

impl Smoother for DistributedSmoother {
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        self.filter.step(y, u)?;
        let (xf, pf) = self.filter.filtered();
        let (xp, tp) = self.filter.predicted();
        self.x_filt.push(xf.to_vec());
        self.p_filt.push(pf.to_vec());
        self.x_pred.push(xp.to_vec());
        self.t_pred.push(tp.to_vec());
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
        let model = &self.model.clone();
        let (n, big_n) = (model.dims.n, model.subsystems);
        let steps = self.x_filt.len();
        let mut xs = self.x_filt.clone();
        let mut ps = self.p_filt.clone();
        let mut rts = Rts::new(n);
        let mut mean = MeanPass::new(model);
        let mut gain = vec![0.0; big_n * n * n];
        let mut gains = Vec::new();
        for k in (0..steps.saturating_sub(1)).rev() {
            let t = k + 1;
            let (ps_head, ps_tail) = ps.split_at_mut(k + 1);
            for i in 0..big_n {
                let b = i * n * n..(i + 1) * n * n;
                if !rts.step(
                    &model.params(t, i + 1).A,
                    &self.p_filt[k][b.clone()],
                    &self.t_pred[k][b.clone()],
                    &ps_tail[0][b.clone()],
                    &mut gain[b.clone()],
                    &mut ps_head[k][b],
                ) {
                    return Err(Error::Numerical {
                        t,
                        i: i + 1,
                        msg: "distributed smoother: the predicted covariance T(t+1) is not positive definite".into(),
                    });
                }
            }
            let (xs_head, xs_tail) = xs.split_at_mut(k + 1);
            mean.apply(
                model,
                t,
                GainView::PerSubsystem(&gain),
                &self.x_filt[k],
                &self.x_pred[k],
                &xs_tail[0],
                &mut xs_head[k],
            );
            if keep_gains {
                gains.push(BackwardGain::PerSubsystem(gain.clone()));
            }
        }
        gains.reverse();
        Ok(Smoothed {
            x: xs,
            p: ps,
            bands: None,
            notes: Vec::new(),
            gains: keep_gains.then_some(gains),
            forward: None,
        })
    }
}
