//! Fixed-interval smoothing (docs/theory.md §9): `x̂(t|T)` with `P(t|T)` from every measurement of the
//! run. Each filter has its smoother, run backward over what its forward pass stored:
//! [`distributed`] (per-subsystem RTS on the two-step filter), [`centralized`] (RTS on the
//! lifted filter of docs/theory.md §7, the pseudo-inverse where `T(t+1)` is singular) and [`joint`] (the
//! information form on the joint band-k filter of docs/theory.md §8, linear in `N`).
//!
//! The Nahi model is exact here: with `ν = (Γ − 𝒫) J X + d` the measurements read
//! `Y = 𝒫 J X + R U + ν` with `ν` white, zero-mean and uncorrelated with the states, so the
//! Kalman/RTS smoother of that linear model is the optimal linear smoother.

pub mod centralized;
pub mod distributed;
pub mod joint;
pub mod score;

use std::sync::Arc;

use nalgebra::DMatrix;

use crate::error::Result;
use crate::filter::JointOptions;
use crate::linalg::band::{BandCholesky, GenBand, SymBand};
use crate::linalg::psd_sqrt;
use crate::model::Model;

pub use centralized::CentralizedSmoother;
pub use distributed::DistributedSmoother;
pub use joint::JointSmoother;

/// The smoothed estimates of a whole run.
pub struct Smoothed {
    /// Per step `t = 1..T`: `x̂(t|T)` (`N·n`).
    pub x: Vec<Vec<f64>>,
    /// Per step: the diagonal blocks of `P(t|T)` (`N·n²`, column-major blocks).
    pub p: Vec<Vec<f64>>,
    /// Joint smoother: per step, the band of `P(t|T)` (width `k`).
    pub bands: Option<Vec<SymBand>>,
    /// What the user should know (e.g. the joint smoother ran again with a larger loading),
    /// printed as warnings.
    pub notes: Vec<String>,
    /// With [`Smoother::backward`]`(true)`: the gain of each step `t = 1..T−1`.
    pub gains: Option<Vec<BackwardGain>>,
    /// Set when the backward pass ran on another forward pass than the smoother's own filter
    /// (the joint smoother's rerun with a larger loading): the options of the joint filter
    /// whose means the gains belong to.
    pub forward: Option<JointOptions>,
}

/// A smoother: the forward pass, one time step at a time, then the backward pass. `Send`, as a
/// [`ChainFilter`](crate::filter::ChainFilter) is.
pub trait Smoother: Send {
    /// Runs the filter on `y(t, ·)`, `u(t, ·)` and stores what the backward pass needs.
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()>;
    /// Runs the backward pass over the stored steps; with `keep_gains` the result also holds
    /// the gain of every step (see [`SmootherSchedule`]).
    fn backward(self: Box<Self>, keep_gains: bool) -> Result<Smoothed>;
    /// Runs the backward pass over the stored steps.
    fn finish(self: Box<Self>) -> Result<Smoothed> {
        self.backward(false)
    }
    /// With the mixture update (docs/theory.md §10): `π(t, i)` of the last forward step.
    fn arrival(&self) -> Option<&[f64]> {
        None
    }
    /// The prior of the next forward step: `x̂(t+1|t)` and the diagonal blocks of `T(t+1)`
    /// (before the first step, those of step 1), as [`crate::filter::ChainFilter::predicted`] gives them.
    fn prior(&self) -> (&[f64], &[f64]);
    /// The forward filter's [`ChainFilter::second_moments`] for the next step.
    ///
    /// [`ChainFilter::second_moments`]: crate::filter::ChainFilter::second_moments
    fn prior_second_moments(&self, out: &mut [f64]) -> bool;
}

/// The gain `L_t` of one backward step, which maps what the later data say about `x(t+1)` to
/// a correction of `x(t)`:
///
/// ```text
/// x̂(t|T) = x̂(t|t) + L_t (x̂(t+1|T) − x̂(t+1|t))
/// ```
///
/// `L_t = C_t` for the RTS smoothers (block-diagonal for `distributed`); for `joint`,
/// `L_t e` is the `δ`-part of `𝒥⁻¹ [A_effᵀ; Gᵀ] Λˢ(t+1) e` (docs/theory.md §9 `joint` step 4). In the
/// unknown-dropout mode `L_t` and `P(t|T)` do not depend on the measurements, so the
/// covariance pass can run once for many data sets ([`SmootherSchedule`]).
#[derive(Debug, Clone)]
pub enum BackwardGain {
    /// `distributed`: per subsystem `C_iᵀ` (`N` column-major `n × n` blocks).
    PerSubsystem(Vec<f64>),
    /// `centralized`: `C_tᵀ` of the whole chain.
    Dense(DMatrix<f64>),
    /// `joint`: the Cholesky factor of `𝒥(t)`, `Λˢ(t+1)` and the band of `A_eff(t)`.
    Joint {
        factor: Box<BandCholesky>,
        smoothed_precision: Box<SymBand>,
        a_eff: Arc<GenBand>,
    },
}

/// A [`BackwardGain`] borrowed from a smoother's workspace, so that the backward pass of a
/// single run applies its gains without copying them.
#[derive(Clone, Copy)]
pub enum GainView<'a> {
    PerSubsystem(&'a [f64]),
    Dense(&'a DMatrix<f64>),
    Joint {
        factor: &'a BandCholesky,
        smoothed_precision: &'a SymBand,
        a_eff: &'a GenBand,
    },
}

impl BackwardGain {
    pub fn view(&self) -> GainView<'_> {
        match self {
            Self::PerSubsystem(g) => GainView::PerSubsystem(g),
            Self::Dense(g) => GainView::Dense(g),
            Self::Joint {
                factor,
                smoothed_precision,
                a_eff,
            } => GainView::Joint {
                factor,
                smoothed_precision,
                a_eff,
            },
        }
    }
}

/// The mean half of a backward step, shared by every smoother and by [`SmootherSchedule`]:
/// `x̂(t|T) = x̂(t|t) + L_t (x̂(t+1|T) − x̂(t+1|t))`. Holds the square roots `G_i` of `Q_i`
/// per parameter set (column-major) and the scratch of the `joint` solve.
pub struct MeanPass {
    roots: Vec<Vec<f64>>,
    e: Vec<f64>,
    v: Vec<f64>,
    atv: Vec<f64>,
    rhs: Vec<f64>,
}

impl MeanPass {
    pub fn new(model: &Model) -> Self {
        let (n, big_n) = (model.dims.n, model.subsystems);
        Self {
            roots: model
                .param_sets()
                .iter()
                .map(|p| psd_sqrt(&p.Q).as_slice().to_vec())
                .collect(),
            e: vec![0.0; big_n * n],
            v: vec![0.0; big_n * n],
            atv: vec![0.0; big_n * n],
            rhs: vec![0.0; big_n * 2 * n],
        }
    }

    /// `G_i` of subsystem `i` (0-based) at time `t`, column-major `n × n`.
    pub fn root(&self, model: &Model, t: usize, i: usize) -> &[f64] {
        &self.roots[model.window(t).ids[i] as usize]
    }

    /// `x_out = x̂(t|t) + L_t (x̂(t+1|T) − x̂(t+1|t))`.
    #[allow(clippy::too_many_arguments)]
    pub fn apply(
        &mut self,
        model: &Model,
        t: usize,
        gain: GainView,
        x_filt: &[f64],
        x_pred_next: &[f64],
        xs_next: &[f64],
        x_out: &mut [f64],
    ) {
        let (n, big_n) = (model.dims.n, model.subsystems);
        for ((e, s), p) in self.e.iter_mut().zip(xs_next).zip(x_pred_next) {
            *e = s - p;
        }
        match gain {
            GainView::PerSubsystem(g) => {
                for i in 0..big_n {
                    let gi = &g[i * n * n..(i + 1) * n * n];
                    let e = &self.e[i * n..(i + 1) * n];
                    for r in 0..n {
                        let dx: f64 = (0..n).map(|c| gi[c + r * n] * e[c]).sum();
                        x_out[i * n + r] = x_filt[i * n + r] + dx;
                    }
                }
            }
            GainView::Dense(g) => {
                for (r, x) in x_out.iter_mut().enumerate() {
                    *x = x_filt[r]
                        + g.column(r)
                            .dot(&nalgebra::DVectorView::from_slice(&self.e, big_n * n));
                }
            }
            GainView::Joint {
                factor,
                smoothed_precision,
                a_eff,
            } => {
                // 𝒥 [δ; ξ̂] = [A_effᵀ v; Gᵀ v], v = Λˢ(t+1) e (docs/theory.md §9 `joint` step 4).
                let bs = 2 * n;
                smoothed_precision.mul_vec(&self.e, &mut self.v);
                a_eff.mul_vec_transposed(&self.v, &mut self.atv);
                let ids = &model.window(t).ids;
                for i in 0..big_n {
                    let gi = &self.roots[ids[i] as usize];
                    for r in 0..n {
                        self.rhs[i * bs + r] = self.atv[i * n + r];
                        self.rhs[i * bs + n + r] =
                            (0..n).map(|c| gi[c + r * n] * self.v[i * n + c]).sum();
                    }
                }
                factor.solve_in_place(&mut self.rhs);
                for (q, x) in x_out.iter_mut().enumerate() {
                    *x = x_filt[q] + self.rhs[(q / n) * bs + q % n];
                }
            }
        }
    }
}

/// The covariance pass of a smoother in the unknown-dropout mode, computed once and replayed
/// on the means of any number of runs (it does not depend on the data, docs/theory.md §9):
/// the gains `L_t` and the diagonal blocks of `P(t|T)`.
pub struct SmootherSchedule {
    gains: Vec<BackwardGain>,
    /// Per step, the diagonal blocks of `P(t|T)`.
    pub p: Vec<Vec<f64>>,
    /// The notes of the covariance pass ([`Smoothed::notes`]).
    pub notes: Vec<String>,
    /// The filter whose means the gains belong to, when not the smoother's own
    /// ([`Smoothed::forward`]).
    pub forward: Option<JointOptions>,
}

impl SmootherSchedule {
    /// Runs `smoother` (built for the unknown-dropout mode) on `y = 0` and the inputs `u`;
    /// its covariances and gains do not depend on `y`.
    pub fn new(
        mut smoother: Box<dyn Smoother + '_>,
        model: &Model,
        u: &[Vec<f64>],
    ) -> Result<Self> {
        let y = vec![0.0; model.subsystems * model.dims.q];
        for ut in u {
            smoother.step(&y, ut)?;
        }
        let smoothed = smoother.backward(true)?;
        Ok(Self {
            gains: smoothed.gains.expect("kept"),
            p: smoothed.p,
            notes: smoothed.notes,
            forward: smoothed.forward,
        })
    }

    /// `x̂(t|T)` for every step from the filter's `x̂(t|t)` (`x_filt[t−1]`) and its
    /// predictions `x̂(t+1|t)` (`x_pred_next[t−1]`), by the stored gains.
    pub fn smooth_means(
        &self,
        model: &Model,
        x_filt: &[Vec<f64>],
        x_pred_next: &[Vec<f64>],
    ) -> Vec<Vec<f64>> {
        let steps = x_filt.len();
        assert_eq!(steps, self.gains.len() + 1, "the schedule's horizon");
        let mut pass = MeanPass::new(model);
        let mut xs = x_filt.to_vec();
        for k in (0..steps - 1).rev() {
            let (head, tail) = xs.split_at_mut(k + 1);
            pass.apply(
                model,
                k + 1,
                self.gains[k].view(),
                &x_filt[k],
                &x_pred_next[k],
                &tail[0],
                &mut head[k],
            );
        }
        xs
    }
}

/// Which smoother, for the memory estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SmootherKind {
    Distributed,
    Centralized,
    /// With the band `k`.
    Joint(usize),
}

/// Bytes the stored forward pass and the smoothed output take for `steps` steps (docs/theory.md §9
/// "Memory"): `O(T·N·n²)` for `distributed`, `O(T·N·(k+1)·n²)` for `joint`, `O(T·(Nn)²)` for
/// `centralized`.
pub fn memory_bytes(model: &Model, kind: SmootherKind, steps: usize) -> u64 {
    let (n, big_n) = (model.dims.n as u64, model.subsystems as u64);
    let steps = steps as u64;
    // Output: x̂ and the diagonal blocks per step.
    let output = steps * big_n * (n + n * n) * 8;
    let forward = match kind {
        // x̂(t|t), x̂(t+1|t), P(t|t), T(t+1).
        SmootherKind::Distributed => steps * big_n * (2 * n + 2 * n * n) * 8,
        // x̂(t|t), x̂(t|t−1), Λ⁻ and Λ⁺ (the output band takes the place of Λ⁻), and with
        // the default loading y and u for a rerun.
        SmootherKind::Joint(k) => {
            let k = (k as u64).min(big_n - 1);
            let (q, m) = (model.dims.q as u64, model.dims.m as u64);
            steps * big_n * (2 * n + 2 * (k + 1) * n * n + q + m) * 8
        }
        // P(t|t), T(t+1) of the whole chain and the means per step; A_eff per window.
        SmootherKind::Centralized => {
            let size = big_n * n;
            let windows = model.windows().len() as u64;
            (steps * (2 * size * size + 2 * size) + windows * size * size) * 8
        }
    };
    forward + output
}
