//! The information-form smoother on the joint band-k filter (docs/theory.md §9 `joint`), linear in `N`.
//!
//! The forward pass is the joint filter of docs/theory.md §8, storing per `t`: `x̂(t|t−1)`, `x̂(t|t)`,
//! the prior precision band `Λ⁻(t)` (after loading), `Λ⁺(t) = Λ⁻(t) + blkdiag(Φ_i)` and the
//! band of `A_eff(t)` (once per override window). With `Q_i = G_i G_iᵀ` and `Λˢ(T) = Λ⁺(T)`,
//! for `t = T−1, …, 1`:
//!
//! ```text
//! I_b = Λˢ(t+1) − Λ⁻(t+1)                      what y(t+1..T) tells about x(t+1)
//! 𝒥   = [ Λ⁺(t) + A_effᵀ I_b A_eff    A_effᵀ I_b G ]   precision of z_i = [δ_i; ξ_i]
//!       [ Gᵀ I_b A_eff                I + Gᵀ I_b G ]   (δ = x(t) − x̂(t|t), ξ the noise)
//! 𝒥 [δ; ξ̂] = [A_effᵀ v; Gᵀ v],  v = Λˢ(t+1) (x̂(t+1|T) − x̂(t+1|t)),  x̂(t|T) = x̂(t|t) + δ
//! P(t|T) = x-part of the band k of 𝒥⁻¹ (selected inversion to κ = min(k + 2b, N − 1))
//! Λˢ(t)  = the clique/separator precision of that band (with the filter's loading)
//! ```
//!
//! `𝒥` is block-banded with `2n × 2n` blocks and bandwidth `κ`, formed by band products.
//! At `k = N − 1` this is the centralized smoother.

use std::sync::Arc;

use crate::error::{Error, Result};
use crate::filter::joint::{Loading, band_error};
use crate::filter::{ChainFilter, JointFilter, JointOptions};
use crate::linalg::band::{
    BandCholesky, BandError, CompletionWorkspace, GenBand, SymBand, completion_precision,
    diag_t_times_gen, gemm_acc, gen_t_times_gen, sym_times_gen,
};
use crate::model::Model;
use crate::smoother::{BackwardGain, GainView, MeanPass, Smoothed, Smoother};

/// The stored forward pass of the joint filter.
pub struct JointSmoother {
    model: Model,
    filter: JointFilter,
    x_pred: Vec<Vec<f64>>,
    x_filt: Vec<Vec<f64>>,
    prior: Vec<SymBand>,
    posterior: Vec<SymBand>,
    /// The `A_eff` band of each step, shared between the steps of a window.
    a_eff: Vec<Arc<GenBand>>,
    opts: JointOptions,
    /// With the default loading: every step's `y` and `u`, to run again with a larger
    /// loading if the backward pass loses positive definiteness (docs/theory.md §9).
    data: Option<Recorded>,
}

/// Every step's `y` and `u`, as given to [`Smoother::step`].
#[derive(Default)]
struct Recorded {
    y: Vec<Vec<f64>>,
    u: Vec<Vec<f64>>,
}

/// The loadings a joint smoother with the default loading tries, in this order, when its
/// backward pass fails (docs/theory.md §9). At 1e−5 the smoother of `paper.toml` still has
/// the centralized smoother's RMSE to three digits.
const RETRY_LOADINGS: [f64; 3] = [1e-7, 1e-6, 1e-5];

impl JointSmoother {
    pub fn new(model: &Model, opts: JointOptions) -> Result<Self> {
        let mut filter = JointFilter::new(model, opts)?;
        let (n, big_n, k) = (model.dims.n, model.subsystems, filter.band());
        filter.kept_precisions = Some((SymBand::zeros(big_n, n, k), SymBand::zeros(big_n, n, k)));
        let retry = opts.loading.is_none() && filter.loading() < RETRY_LOADINGS[0];
        Ok(Self {
            model: model.clone(),
            filter,
            x_pred: Vec::new(),
            x_filt: Vec::new(),
            prior: Vec::new(),
            posterior: Vec::new(),
            a_eff: Vec::new(),
            opts,
            data: retry.then(Default::default),
        })
    }
}

impl Smoother for JointSmoother {
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        if let Some(data) = &mut self.data {
            data.y.push(y.to_vec());
            data.u.push(u.to_vec());
        }
        self.x_pred.push(self.filter.predicted().0.to_vec());
        self.filter.step(y, u)?;
        self.x_filt.push(self.filter.filtered().0.to_vec());
        let (prior, posterior) = self.filter.kept_precisions.as_ref().expect("kept");
        self.prior.push(prior.clone());
        self.posterior.push(posterior.clone());
        let band = self.filter.a_eff_band();
        match self.a_eff.last() {
            Some(last) if **last == *band => {
                let shared = Arc::clone(last);
                self.a_eff.push(shared);
            }
            _ => self.a_eff.push(Arc::new(band.clone())),
        }
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

    /// The backward pass; if it fails with the default loading, the whole smoother again
    /// with the loadings 1e−7, 1e−6 and 1e−5 until one succeeds, and a note says which.
    fn backward(mut self: Box<Self>, keep_gains: bool) -> Result<Smoothed> {
        let data = self.data.take();
        let (model, opts) = (self.model.clone(), self.opts);
        let loading = self.filter.loading();
        let failure = match self.backward_pass(keep_gains) {
            Ok(smoothed) => return Ok(smoothed),
            Err(e) => e,
        };
        let Some(data) = data else {
            return Err(failure);
        };
        for retry in RETRY_LOADINGS {
            let opts = JointOptions {
                loading: Some(retry),
                ..opts
            };
            let mut smoother = JointSmoother::new(&model, opts)?;
            for (y, u) in data.y.iter().zip(&data.u) {
                smoother.step(y, u)?;
            }
            if let Ok(mut smoothed) = Box::new(smoother).backward_pass(keep_gains) {
                let place = match &failure {
                    Error::Numerical { t, i, .. } => format!("at t = {t}, i = {i}"),
                    other => other.to_string(),
                };
                smoothed.notes.push(format!(
                    "joint smoother: with the default loading {loading:e} the backward pass lost positive definiteness ({place}); smoothed with --loading {retry:e} instead, its forward pass included (docs/theory.md §9)"
                ));
                smoothed.forward = Some(opts);
                return Ok(smoothed);
            }
        }
        Err(failure)
    }
}

impl JointSmoother {
    /// The backward pass of docs/theory.md §9 `joint` over the stored forward pass.
    fn backward_pass(self: Box<Self>, keep_gains: bool) -> Result<Smoothed> {
        let model = &self.model.clone();
        let (n, big_n) = (model.dims.n, model.subsystems);
        let k = self.filter.band();
        let loading = self.filter.loading();
        let steps = self.x_filt.len();
        let JointSmoother {
            filter,
            x_pred,
            x_filt,
            mut prior,
            posterior,
            a_eff,
            ..
        } = *self;
        let mut xs = vec![vec![0.0; big_n * n]; steps];
        xs[steps - 1].copy_from_slice(&x_filt[steps - 1]);
        let mut lam_s = posterior[steps - 1].clone();
        let mut ws = Backward::new(model, k);
        let mut gains = Vec::new();
        // The band of P(t|T) is written into a scratch band that then trades places with
        // Λ⁻(t+1), which is no longer needed: after the pass, prior[t] holds P(t−1|T) for
        // t ≥ 1, so the output takes no memory beyond the stored forward pass.
        let mut band = SymBand::zeros(big_n, n, k);
        for idx in (0..steps - 1).rev() {
            let t = idx + 1;
            let (xs_head, xs_tail) = xs.split_at_mut(idx + 1);
            ws.step(
                model,
                t,
                &a_eff[idx],
                &posterior[idx],
                &prior[idx + 1],
                &lam_s,
                &x_filt[idx],
                &x_pred[idx + 1],
                &xs_tail[0],
                &mut xs_head[idx],
                &mut band,
            )
            .map_err(|e| smoother_error(t, loading, k, e))?;
            if keep_gains {
                gains.push(BackwardGain::Joint {
                    factor: Box::new(ws.chol.clone_for_solves()),
                    smoothed_precision: Box::new(lam_s.clone()),
                    a_eff: Arc::clone(&a_eff[idx]),
                });
            }
            ws.smoothed_precision(&band, filter.loading_rule(), &mut lam_s)
                .map_err(|e| smoother_error(t, loading, k, e))?;
            std::mem::swap(&mut band, &mut prior[idx + 1]);
        }
        gains.reverse();
        // prior[0] (Λ⁻(1)) was never needed: it becomes the band of P(T|T).
        let mut bands = prior;
        bands[0].copy_band_from(filter.covariance_band(false));
        bands.rotate_left(1);
        let p = bands
            .iter()
            .map(|b| {
                (0..big_n)
                    .flat_map(|i| b.block(i, 0).iter().copied())
                    .collect()
            })
            .collect();
        Ok(Smoothed {
            x: xs,
            p,
            bands: Some(bands),
            notes: Vec::new(),
            gains: keep_gains.then_some(gains),
            forward: None,
        })
    }
}

fn smoother_error(t: usize, loading: f64, k: usize, e: BandError) -> Error {
    band_error("joint smoother", t, loading, k, "the ", e)
}

/// Scratch of the backward pass, sized for the current `A_eff` half-width `b` (resized only
/// when `b` changes), and the square roots `G_i` of `Q_i` per parameter set (column-major).
struct Backward {
    /// The mean half of the step (step 4), with the roots `G_i`.
    mean: MeanPass,
    /// The `b` the buffers below are sized for.
    b: Option<usize>,
    ib: SymBand,
    w: GenBand,
    /// `Z = Gᵀ W` (half-width of `W`): the `ξ–δ` blocks of `𝒥`.
    z: GenBand,
    m: SymBand,
    jm: SymBand,
    chol: BandCholesky,
    inv: SymBand,
    loaded: SymBand,
    completion: CompletionWorkspace,
    /// Two `n × n` scratch blocks.
    tmp: Vec<f64>,
    tmp2: Vec<f64>,
}

impl Backward {
    fn new(model: &Model, k: usize) -> Self {
        let (n, big_n) = (model.dims.n, model.subsystems);
        Self {
            mean: MeanPass::new(model),
            b: None,
            ib: SymBand::zeros(big_n, n, k),
            w: GenBand::zeros(big_n, n, 0),
            z: GenBand::zeros(big_n, n, 0),
            m: SymBand::zeros(big_n, n, 0),
            jm: SymBand::zeros(big_n, 2 * n, 0),
            chol: BandCholesky::new(big_n, 2 * n, 0),
            inv: SymBand::zeros(big_n, 2 * n, 0),
            loaded: SymBand::zeros(big_n, n, k),
            completion: CompletionWorkspace::new(big_n, n, k),
            tmp: vec![0.0; n * n],
            tmp2: vec![0.0; n * n],
        }
    }

    /// Sizes the buffers for `A_eff` half-width `b`.
    fn prepare(&mut self, nb: usize, n: usize, k: usize, b: usize) {
        if self.b == Some(b) {
            return;
        }
        let kappa = (k + 2 * b).min(nb - 1);
        self.w = GenBand::zeros(nb, n, k + b);
        self.z = GenBand::zeros(nb, n, k + b);
        self.m = SymBand::zeros(nb, n, kappa);
        self.jm = SymBand::zeros(nb, 2 * n, kappa);
        self.chol = BandCholesky::new(nb, 2 * n, kappa);
        self.inv = SymBand::zeros(nb, 2 * n, kappa);
        self.b = Some(b);
    }

    /// One backward step at time `t` (docs/theory.md §9 `joint` steps 1–5): `x̂(t|T)` into `x_out` and
    /// the band `k` of `P(t|T)` into `band_out`.
    #[allow(clippy::too_many_arguments)]
    fn step(
        &mut self,
        model: &Model,
        t: usize,
        a: &GenBand,
        lam_post: &SymBand,
        lam_prior_next: &SymBand,
        lam_s_next: &SymBand,
        x_filt: &[f64],
        x_pred_next: &[f64],
        xs_next: &[f64],
        x_out: &mut [f64],
        band_out: &mut SymBand,
    ) -> std::result::Result<(), BandError> {
        let (n, big_n) = (model.dims.n, model.subsystems);
        let (k, b) = (lam_post.width(), a.half_width());
        self.prepare(big_n, n, k, b);
        let kappa = self.jm.width();
        let bs = 2 * n;
        let mean = &self.mean;
        let g = |i: usize| mean.root(model, t, i);
        // 1. I_b = Λˢ(t+1) − Λ⁻(t+1).
        self.ib.copy_band_from(lam_s_next);
        for i in 0..big_n {
            for d in 0..=k.min(big_n - 1 - i) {
                let src = lam_prior_next.block(i, d);
                for (o, s) in self.ib.block_mut(i, d).iter_mut().zip(src) {
                    *o -= s;
                }
            }
        }
        // 2. W = I_b A_eff, M = A_effᵀ I_b A_eff and Z = Gᵀ W, then 𝒥 block by block:
        //    [Λ⁺ + M, A_effᵀ I_b G; Gᵀ I_b A_eff, I + Gᵀ I_b G] with (A_effᵀ I_b G)_ij = Z_jiᵀ.
        sym_times_gen(&self.ib, a, &mut self.w);
        gen_t_times_gen(a, &self.w, &mut self.m);
        diag_t_times_gen(g, &self.w, &mut self.z);
        let hw = self.w.half_width();
        for i in 0..big_n {
            for d in 0..=kappa.min(big_n - 1 - i) {
                let j = i + d;
                let blk = self.jm.block_mut(i, d);
                blk.fill(0.0);
                // Top left: Λ⁺_ij + M_ij.
                let m_ij = self.m.block(i, d);
                for c in 0..n {
                    blk[c * bs..c * bs + n].copy_from_slice(&m_ij[c * n..(c + 1) * n]);
                }
                if d <= k {
                    let lp = lam_post.block(i, d);
                    for c in 0..n {
                        for r in 0..n {
                            blk[r + c * bs] += lp[r + c * n];
                        }
                    }
                }
                if d <= hw {
                    // Top right Z_jiᵀ, bottom left Z_ij.
                    let (z_ji, z_ij) = (self.z.block(j, i), self.z.block(i, j));
                    for c in 0..n {
                        for r in 0..n {
                            blk[r + (n + c) * bs] = z_ji[c + r * n];
                            blk[(n + r) + c * bs] = z_ij[r + c * n];
                        }
                    }
                }
                // Bottom right: δ_ij I + G_iᵀ I_b,ij G_j.
                if d <= k {
                    self.tmp.fill(0.0);
                    gemm_acc(
                        &mut self.tmp,
                        1.0,
                        self.ib.block(i, d),
                        false,
                        g(j),
                        false,
                        n,
                    );
                    self.tmp2.fill(0.0);
                    gemm_acc(&mut self.tmp2, 1.0, g(i), true, &self.tmp, false, n);
                    for c in 0..n {
                        for r in 0..n {
                            blk[(n + r) + (n + c) * bs] = self.tmp2[r + c * n];
                        }
                    }
                }
                if d == 0 {
                    for r in 0..n {
                        blk[(n + r) + (n + r) * bs] += 1.0;
                    }
                }
            }
        }
        // 3. Block-banded Cholesky of 𝒥.
        self.chol.factor(&self.jm)?;
        // 4. Mean: 𝒥 [δ; ξ̂] = [A_effᵀ v; Gᵀ v], v = Λˢ(t+1) e.
        let gain = GainView::Joint {
            factor: &self.chol,
            smoothed_precision: lam_s_next,
            a_eff: a,
        };
        self.mean
            .apply(model, t, gain, x_filt, x_pred_next, xs_next, x_out);
        // 5. Covariance: the x-parts of the band k of 𝒥⁻¹.
        self.chol.selected_inverse(&mut self.inv);
        for i in 0..big_n {
            for d in 0..=k.min(big_n - 1 - i) {
                let src = self.inv.block(i, d);
                let dst = band_out.block_mut(i, d);
                for c in 0..n {
                    for r in 0..n {
                        dst[r + c * n] = src[r + c * bs];
                    }
                }
            }
        }
        Ok(())
    }

    /// `Λˢ(t)`: the clique/separator precision of the loaded band of `P(t|T)` (step 6).
    fn smoothed_precision(
        &mut self,
        band: &SymBand,
        loading: Loading,
        out: &mut SymBand,
    ) -> std::result::Result<(), BandError> {
        self.loaded.copy_band_from(band);
        loading.apply(&mut self.loaded);
        completion_precision(&self.loaded, band.width(), out, &mut self.completion).map(|_| ())
    }
}
