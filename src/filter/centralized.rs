//! The centralized reference filter of docs/theory.md §7: the Nahi filter on the lifted system
//! `X⁺ = A_eff X + U_eff U + Ω`, `Y = Γ blkdiag(J) X + blkdiag(R) U + D_n`, with
//! `H = 𝒫 blkdiag(J)`, `𝒫 = blkdiag(p_i I_q)`, and
//! `R_eff = M_big + blkdiag(p_i(1−p_i) J S_ii Jᵀ)` from the exact lifted moments. It is the
//! optimal linear estimator for the unknown-dropout model; in the known-dropout mode it is the
//! ordinary Kalman filter of the lifted system on the observed rows. `O((Nn)³)` per step: a
//! yardstick for the distributed filter, not the default.

use std::sync::Arc;

use nalgebra::{DMatrix, DMatrixViewMut};

use crate::error::{Error, Result};
use crate::filter::ChainFilter;
use crate::filter::lifted_update::LiftedUpdate;
use crate::filter::nahi::{self, Workspace};
use crate::filter::{Dropouts, Update};
use crate::lifted::{CovarianceScratch, LiftedMoments, LiftedSystem};
use crate::model::Model;
use crate::run::check_update;

/// Default largest lifted state size `N·n` the centralized filter accepts.
pub const DEFAULT_MAX_LIFTED: usize = 1000;

/// The sizes the centralized filter may take: its lifted state `N·n` (its cost, `O((N n)³)` a
/// step) and its memory. A bare `usize` is `max_lifted` with the default memory limit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CentralizedLimits {
    pub max_lifted: usize,
    pub max_memory: u64,
}

impl From<usize> for CentralizedLimits {
    fn from(max_lifted: usize) -> Self {
        Self {
            max_lifted,
            max_memory: crate::memory::DEFAULT_MAX_MEMORY,
        }
    }
}

/// The centralized filter's state.
pub struct CentralizedFilter {
    /// Shared so that a step can read it while it changes the filter's state.
    model: Arc<Model>,
    known: bool,
    t: usize,
    sys: LiftedSystem,
    moments: Option<LiftedMoments>,
    x_pred: Vec<f64>,
    t_pred: Vec<f64>,
    x_filt: Vec<f64>,
    p_filt: Vec<f64>,
    update: LiftedUpdate,
    /// Scratch of the covariance prediction.
    scratch: CovarianceScratch,
    s_ii: DMatrix<f64>,
    js: DMatrix<f64>,
    /// Per-subsystem diagonal blocks of the last output, `N·n²` values.
    block_filt: Vec<f64>,
    block_pred: Vec<f64>,
    /// With the mixture update (docs/theory.md §10): `π(t, i)` of the last step, and the
    /// workspace of one subsystem's pseudo-measurement.
    mixture: Option<(Vec<f64>, Workspace)>,
    /// The log density of the last step's measurements (see
    /// [`ChainFilter::log_likelihood`]).
    log_likelihood: Option<f64>,
}

impl CentralizedFilter {
    /// Starts from `X̂(1) = [m0; …]`, `T(1) = blkdiag(P0)`. Refuses chains with
    /// `N·n > max_lifted`, and a filter whose [`Self::bytes`] exceed `max_memory`.
    pub fn new(model: &Model, known: bool, limits: impl Into<CentralizedLimits>) -> Result<Self> {
        let CentralizedLimits {
            max_lifted,
            max_memory,
        } = limits.into();
        let d = model.dims;
        let (n, big_n) = (d.n, model.subsystems);
        let size = big_n * n;
        if size > max_lifted {
            return Err(Error::Usage(format!(
                "the centralized filter works on the lifted state of size N·n = {size}, above the limit {max_lifted} (it costs O((N·n)³) per step); raise --max-lifted to run it anyway"
            )));
        }
        crate::memory::check(Self::bytes(model), max_memory, || {
            format!("the centralized filter (lifted state of size N·n = {size})")
        })?;
        let init = LiftedMoments::initial(model);
        let x_pred = init.mean.as_slice().to_vec();
        // The update reads T by columns for its rows (T symmetric); a covariance given
        // symmetric up to the config's tolerance is made exactly so.
        let t_pred = ((&init.cov + init.cov.transpose()) * 0.5)
            .as_slice()
            .to_vec();
        // Before the first step, predicted() is the prior of step 1.
        let mut block_pred = vec![0.0; big_n * n * n];
        Self::diagonal_blocks(&t_pred, size, n, &mut block_pred);
        Ok(Self {
            model: Arc::new(model.clone()),
            known,
            t: 1,
            sys: LiftedSystem::new(model, 1)?,
            moments: (!known).then_some(init),
            x_filt: x_pred.clone(),
            p_filt: t_pred.clone(),
            x_pred,
            t_pred,
            update: LiftedUpdate::new(big_n, n, d.q),
            scratch: CovarianceScratch::default(),
            s_ii: DMatrix::zeros(n, n),
            js: DMatrix::zeros(d.q, n),
            block_filt: block_pred.clone(),
            block_pred,
            mixture: None,
            log_likelihood: None,
        })
    }

    /// A bound on the bytes the filter holds (docs/theory.md §12 "Memory"): twenty lifted
    /// `(N n)²` matrices (the lifted system, moments, covariances and their workspace), the
    /// update's `Σ` and `[V  e]`, and the mixture update's `𝒥 T` and the scratch of its LU
    /// solve; tests/allocation.rs holds it against the bytes measured.
    /// Not counted: the packing scratch the dense kernels keep per thread (a few megabytes,
    /// sized by the processor's caches, whatever the chain).
    pub fn bytes(model: &Model) -> f64 {
        let size = (model.subsystems * model.dims.n) as f64;
        let measured = (model.subsystems * model.dims.q) as f64;
        8.0 * (20.0 * size * size + 2.0 * measured * measured + 2.0 * measured * size)
    }

    /// The same filter with the mixture update of docs/theory.md §10 in place of Nahi's: each
    /// subsystem's pseudo-measurement `(W_i, r_i)` from its marginal, then all at once in
    /// covariance form, `G = I + 𝒲 𝒥 T 𝒥ᵀ`, `X̂(t|t) = X̂ + T 𝒥ᵀ G⁻¹ r`,
    /// `P(t|t) = T − T 𝒥ᵀ G⁻¹ 𝒲 𝒥 T`. Unknown dropouts only.
    pub fn with_mixture_update(mut self) -> Result<Self> {
        let dropouts = if self.known {
            Dropouts::Known
        } else {
            Dropouts::Unknown
        };
        check_update(dropouts, Update::Mixture)?;
        let d = self.model.dims;
        self.mixture = Some((vec![0.0; self.model.subsystems], Workspace::new(d.n, d.q)));
        // The mixture update reads no second moment (filter::reads_second_moment): its
        // O((N·n)³) recursion would be wasted.
        self.moments = None;
        Ok(self)
    }

    /// The mixture update of step `t` into `x_filt`, `p_filt` and the arrival
    /// probabilities.
    fn mixture_update(&mut self, t: usize, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &Arc::clone(&self.model);
        let d = model.dims;
        let (n, q, m, big_n) = (d.n, d.q, d.m, model.subsystems);
        let size = big_n * n;
        let Some((arrival, ws)) = self.mixture.as_mut() else {
            return Ok(());
        };
        let window = model.window(t);
        let mut log_likelihood = 0.0;
        let mut ru = vec![0.0; q];
        // The marginals of T(t); `block_pred` is rewritten by the prediction.
        Self::diagonal_blocks(&self.t_pred, size, n, &mut self.block_pred);
        for i in 0..big_n {
            let prm = model.param_set(window.ids[i]);
            let sigma_ii = &self.block_pred[i * n * n..(i + 1) * n * n];
            ru.fill(0.0);
            crate::linalg::mat_vec_add(&mut ru, &prm.R, &u[i * m..(i + 1) * m]);
            let meas = nahi::Measurement {
                j: &prm.J,
                m: &prm.M,
                y: &y[i * q..(i + 1) * q],
                ru: &ru,
                p: window.p[i],
                known: false,
            };
            let x_i = &self.x_pred[i * n..(i + 1) * n];
            let (j_i, w_i, r_i) = self.update.block_mut(i);
            j_i.copy_from_slice(prm.J.as_slice());
            let Some(a) = nahi::mixture_pseudo_measurement(&meas, x_i, sigma_ii, w_i, r_i, ws)
            else {
                return Err(Error::Numerical {
                    t,
                    i: i + 1,
                    msg: "the mixture update's J T Jᵀ + M is not positive definite".into(),
                });
            };
            arrival[i] = a.probability;
            log_likelihood += a.loglik;
        }
        if !self.update.pseudo_update(
            &self.x_pred,
            &self.t_pred,
            &mut self.x_filt,
            &mut self.p_filt,
        ) {
            return Err(Error::Numerical {
                t,
                i: 0,
                msg: "the centralized mixture update's I + 𝒲 𝒥 T 𝒥ᵀ is singular".into(),
            });
        }
        self.log_likelihood = Some(log_likelihood);
        Ok(())
    }

    /// The whole `P(t|t)` of the last step (`Nn × Nn`, column-major), for the smoother.
    pub(crate) fn full_filtered_cov(&self) -> &[f64] {
        &self.p_filt
    }

    /// The whole `T(t+1)` of the last step, for the smoother.
    pub(crate) fn full_predicted_cov(&self) -> &[f64] {
        &self.t_pred
    }

    /// The lifted system of the last step (`A_eff(t)`), for the smoother.
    pub(crate) fn lifted_system(&self) -> &LiftedSystem {
        &self.sys
    }

    /// Nahi's update of step `t` on the lifted system (docs/theory.md §7), with the block
    /// structure of its measurement ([`LiftedUpdate`]).
    fn linear_update(&mut self, t: usize, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &Arc::clone(&self.model);
        let d = model.dims;
        let (n, q, m, big_n) = (d.n, d.q, d.m, model.subsystems);
        let window = model.window(t);
        for i in 0..big_n {
            let prm = model.param_set(window.ids[i]);
            let p = if self.known { 1.0 } else { window.p[i] };
            let (h, r, innov) = self.update.block_mut(i);
            h.iter_mut()
                .zip(prm.J.as_slice())
                .for_each(|(h, j)| *h = p * j);
            let mut rb = DMatrixViewMut::from_slice(r, q, q);
            rb.copy_from(&prm.M);
            if let Some(mom) = &self.moments
                && p * (1.0 - p) != 0.0
            {
                mom.second_moment(i, n, self.s_ii.as_mut_slice());
                self.js.gemm(1.0, &prm.J, &self.s_ii, 0.0);
                rb.gemm(p * (1.0 - p), &self.js, &prm.J.transpose(), 1.0);
            }
            nahi::innovation(
                prm,
                p,
                &y[i * q..(i + 1) * q],
                &u[i * m..(i + 1) * m],
                &self.x_pred[i * n..(i + 1) * n],
                innov,
            );
        }
        let log_density = self
            .update
            .update(
                &self.x_pred,
                &self.t_pred,
                &mut self.x_filt,
                &mut self.p_filt,
            )
            .ok_or_else(|| Error::Numerical {
                t,
                i: 0,
                msg: "the centralized filter's innovation covariance is not positive definite"
                    .into(),
            })?;
        // The lifted innovations are Gaussian only when the filter knows the dropouts.
        self.log_likelihood = self.known.then_some(log_density);
        Ok(())
    }

    fn diagonal_blocks(cov: &[f64], size: usize, n: usize, out: &mut [f64]) {
        for i in 0..size / n {
            for c in 0..n {
                for r in 0..n {
                    out[i * n * n + c * n + r] = cov[(i * n + c) * size + i * n + r];
                }
            }
        }
    }
}

impl ChainFilter for CentralizedFilter {
    fn second_moments(&self, out: &mut [f64]) -> bool {
        let Some(moments) = &self.moments else {
            return false;
        };
        let n = self.model.dims.n;
        for (i, s) in out.chunks_exact_mut(n * n).enumerate() {
            moments.second_moment(i, n, s);
        }
        true
    }

    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &Arc::clone(&self.model);
        let d = model.dims;
        let (n, big_n) = (d.n, model.subsystems);
        let size = big_n * n;
        let t = self.t;
        self.sys.prepare(model, t)?;
        if self.mixture.is_some() {
            self.mixture_update(t, y, u)?;
        } else {
            self.linear_update(t, y, u)?;
        }
        // Predict: X̂⁺ = A_eff X̂(t|t) + U_eff U, T⁺ = A_eff P A_effᵀ + Q_big.
        {
            let mut xp = nalgebra::DVectorViewMut::from_slice(&mut self.x_pred, size);
            let xf = nalgebra::DVectorView::from_slice(&self.x_filt, size);
            xp.gemv(1.0, &self.sys.a_eff.dense, &xf, 0.0);
            let uu = nalgebra::DVectorView::from_slice(u, u.len());
            xp.gemv(1.0, &self.sys.u_eff, &uu, 1.0);
        }
        self.sys
            .covariance_step(model, &self.p_filt, &mut self.t_pred, &mut self.scratch);
        if let Some(mom) = &mut self.moments {
            mom.propagate(model, &self.sys, u);
        }
        Self::diagonal_blocks(&self.p_filt, size, n, &mut self.block_filt);
        Self::diagonal_blocks(&self.t_pred, size, n, &mut self.block_pred);
        Error::check_finite(t, n * n, &self.block_pred, || {
            "the predicted covariance T(t+1) is no longer finite: it overflowed the range of f64 (about 1e308)".into()
        })?;
        self.t += 1;
        Ok(())
    }

    fn filtered(&self) -> (&[f64], &[f64]) {
        (&self.x_filt, &self.block_filt)
    }

    fn predicted(&self) -> (&[f64], &[f64]) {
        (&self.x_pred, &self.block_pred)
    }

    fn arrival(&self) -> Option<&[f64]> {
        self.mixture.as_ref().map(|(a, _)| a.as_slice())
    }

    /// With known dropouts the exact `log N(Ỹ; 0, 𝒥 T 𝒥ᵀ + ℳ)` of the received elements of
    /// the whole chain; with the mixture update the sum of each subsystem's density from its
    /// marginal (docs/theory.md §10).
    fn log_likelihood(&self) -> Option<f64> {
        self.log_likelihood
    }
}

/// The covariance pass of the unknown-dropout centralized filter, stored per step. Its gains
/// and covariances depend only on the model and the inputs, not on the measurements, so
/// `evaluate` computes it once and replays it for every run with [`ScheduledCentralized`].
pub struct CentralizedSchedule {
    model: Model,
    /// Per step: `W(t) = Σ⁻¹ H T` (the transposed gain), and the diagonal blocks of
    /// `P(t|t)` and `T(t+1)`.
    gains: Vec<DMatrix<f64>>,
    p_blocks: Vec<Vec<f64>>,
    t_blocks: Vec<Vec<f64>>,
    /// The lifted system of each step's window, shared between steps.
    systems: Vec<LiftedSystem>,
    system_of_step: Vec<usize>,
}

impl CentralizedSchedule {
    /// Bytes a schedule of `steps` steps needs.
    pub fn bytes(model: &Model, steps: usize) -> usize {
        let (nn, nq) = (
            model.subsystems * model.dims.n,
            model.subsystems * model.dims.q,
        );
        steps * 8 * (nn * nq + 2 * model.subsystems * model.dims.n * model.dims.n)
    }

    /// Runs the covariance pass for the given inputs (`u[t]`, `N·m` values per step).
    pub fn new(
        model: &Model,
        u: &[Vec<f64>],
        limits: impl Into<CentralizedLimits>,
    ) -> Result<Self> {
        let mut filter = CentralizedFilter::new(model, false, limits)?;
        let mut y = vec![0.0; model.subsystems * model.dims.q];
        let mut sched = Self {
            model: model.clone(),
            gains: Vec::with_capacity(u.len()),
            p_blocks: Vec::with_capacity(u.len()),
            t_blocks: Vec::with_capacity(u.len()),
            systems: Vec::new(),
            system_of_step: Vec::with_capacity(u.len()),
        };
        for (t0, ut) in u.iter().enumerate() {
            // The rows of subsystems without a sensor are left out of the gains too.
            y.fill(0.0);
            model.blank_unmeasured(t0 + 1, &mut y);
            filter.step(&y, ut)?;
            if sched
                .systems
                .last()
                .is_none_or(|s| s.window != filter.sys.window)
            {
                sched.systems.push(filter.sys.clone());
            }
            sched.system_of_step.push(sched.systems.len() - 1);
            sched.gains.push(filter.update.gain_transposed());
            sched.p_blocks.push(filter.block_filt.clone());
            sched.t_blocks.push(filter.block_pred.clone());
        }
        Ok(sched)
    }
}

/// The centralized Nahi filter replayed from a [`CentralizedSchedule`]: only the means are
/// computed, `O((Nn)²)` per step. Equal to [`CentralizedFilter`] in the unknown-dropout mode.
pub struct ScheduledCentralized<'s> {
    sched: &'s CentralizedSchedule,
    t: usize,
    x_pred: Vec<f64>,
    x_filt: Vec<f64>,
    innov: Vec<f64>,
}

impl<'s> ScheduledCentralized<'s> {
    pub fn new(sched: &'s CentralizedSchedule) -> Self {
        let big_n = sched.model.subsystems;
        let x_pred = sched.model.initial.means();
        Self {
            sched,
            t: 1,
            x_filt: x_pred.clone(),
            x_pred,
            innov: vec![0.0; big_n * sched.model.dims.q],
        }
    }
}

impl ChainFilter for ScheduledCentralized<'_> {
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &self.sched.model;
        let d = model.dims;
        let (n, big_n) = (d.n, model.subsystems);
        let t = self.t;
        let k = t - 1;
        if k >= self.sched.gains.len() {
            return Err(Error::Usage(format!(
                "the centralized schedule ends before t = {t}"
            )));
        }
        super::refuse_gaps(model, y, t, "the centralized filter's schedule")?;
        nahi::chain_innovations(model, t, y, u, &self.x_pred, &mut self.innov);
        // A row without a sensor has a zero gain and no innovation (NaN).
        for v in self.innov.iter_mut().filter(|v| v.is_nan()) {
            *v = 0.0;
        }
        let size = big_n * n;
        let w = &self.sched.gains[k];
        let mut xf = nalgebra::DVectorViewMut::from_slice(&mut self.x_filt, size);
        xf.copy_from_slice(&self.x_pred);
        let innov = nalgebra::DVectorView::from_slice(&self.innov, self.innov.len());
        xf.gemv_tr(1.0, w, &innov, 1.0);
        let sys = &self.sched.systems[self.sched.system_of_step[k]];
        let mut xp = nalgebra::DVectorViewMut::from_slice(&mut self.x_pred, size);
        xp.gemv(1.0, &sys.a_eff.dense, &xf, 0.0);
        let uu = nalgebra::DVectorView::from_slice(u, u.len());
        xp.gemv(1.0, &sys.u_eff, &uu, 1.0);
        self.t += 1;
        Ok(())
    }

    fn filtered(&self) -> (&[f64], &[f64]) {
        (&self.x_filt, &self.sched.p_blocks[self.t - 2])
    }

    fn predicted(&self) -> (&[f64], &[f64]) {
        (&self.x_pred, &self.sched.t_blocks[self.t - 2])
    }
}
