//! The joint band-k filter of docs/theory.md §8: the full lifted mean and the lifted covariance on the
//! block band `|i − j| ≤ k`, standing for the rest by its maximum-entropy (Gauss–Markov)
//! completion. It accounts for the error in the interconnection signals that the two-step
//! filter treats as exact, so its covariance stays honest (also with `Q = 0`), and every step
//! is linear in `N`. With `k = N − 1` it is the centralized filter of docs/theory.md §7.
//!
//! One time step, in information form on the band (docs/theory.md §8 update steps 1–7, predict 1–5):
//!
//! ```text
//! Λ⁻   = Σ_cliques pad(P⁻_C⁻¹) − Σ_separators pad(P⁻_S⁻¹)      completion precision
//! Φ_i  = H_iᵀ R_i⁻¹ H_i,  r_i = H_iᵀ R_i⁻¹ ỹ_i,   H_i = p_i J,  R_i = M + p_i(1−p_i) J S_ii Jᵀ
//! Λ⁺   = Λ⁻ + blkdiag(Φ_i) = L Lᵀ,   X̂⁺ = X̂⁻ + (Λ⁺)⁻¹ r
//! P̃⁺   = band of (Λ⁺)⁻¹ to width w = min(k + 2b, N − 1)         selected inversion
//! X̂⁻(t+1) = A_eff X̂⁺ + U_eff u                                  by the chain solve
//! P⁻(t+1) = band_k(A_eff P̃⁺ A_effᵀ) + blkdiag(Q)                 b = half-width of A_eff
//! ```

mod information;
mod loading;
mod moments;
mod schedule;

use information::InfoWorkspace;
pub(crate) use loading::Loading;
use moments::Moments;

pub use schedule::{JointSchedule, ScheduledJoint};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::filter::{ChainFilter, Dropouts, SecondMoment, Update, nahi, reads_second_moment};
use crate::interconnect::ChainSolver;
use crate::lifted::{LiftedMoments, LiftedSystem, LiftedWorkspace, a_eff_band, propagate_mean};
use crate::linalg::band::{
    BandCholesky, BandError, CompletionWorkspace, GenBand, SandwichWorkspace, SymBand,
    completion_precision, sandwich,
};
use crate::memory::DEFAULT_MAX_MEMORY;
use crate::model::Model;
use crate::run::spec::{Setting, SpecError, check_non_negative, check_update};

/// Default `--band K`.
pub const DEFAULT_BAND: usize = 2;
/// Default `--band-tol`: relative size below which blocks of `A_eff` are dropped.
pub const DEFAULT_BAND_TOL: f64 = 1e-9;
/// Default `--loading` when every `Q` is zero or the initial covariance is singular (else 0):
/// docs/theory.md §8 "Loading".
pub const DEFAULT_LOADING_Q_ZERO: f64 = 1e-9;

/// Options of the joint filter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct JointOptions {
    /// `K`: the covariance is kept on the blocks `|i − j| ≤ min(K, N − 1)`.
    pub band: usize,
    /// Relative tolerance of the `A_eff` band (docs/theory.md §8 predict step 2).
    pub band_tol: f64,
    /// Diagonal loading `ε`; `None` means [`JointOptions::loading_for`]'s default.
    pub loading: Option<f64>,
    /// `band` (default), `lifted` or `local`.
    pub second_moment: SecondMoment,
    pub dropouts: Dropouts,
    /// `mixture` (docs/theory.md §10) needs unknown dropouts and no second moment.
    pub update: Update,
    /// The filter refuses to start when [`JointFilter::bytes`] exceed this many bytes.
    #[serde(skip)]
    pub max_memory: u64,
}

impl Default for JointOptions {
    fn default() -> Self {
        Self {
            band: DEFAULT_BAND,
            band_tol: DEFAULT_BAND_TOL,
            loading: None,
            second_moment: SecondMoment::Band,
            dropouts: Dropouts::Unknown,
            update: Update::Linear,
            max_memory: DEFAULT_MAX_MEMORY,
        }
    }
}

impl JointOptions {
    /// The whole lifted covariance (`K = N − 1`) and the exact `A_eff` (tolerance 0): the
    /// centralized filter of docs/theory.md §7, in the information form (default loading).
    pub fn full_band(model: &Model, second_moment: SecondMoment, dropouts: Dropouts) -> Self {
        Self {
            band: model.subsystems - 1,
            band_tol: 0.0,
            loading: None,
            second_moment,
            dropouts,
            update: Update::Linear,
            max_memory: DEFAULT_MAX_MEMORY,
        }
    }

    /// The loading `ε` in force for `model`: the default is 1e−9 where the prior can be
    /// singular (every `Q` zero, or an initial covariance that is not positive definite).
    pub fn loading_for(&self, model: &Model) -> f64 {
        let singular_start =
            (model.initial.sets().iter()).any(|s| s.cov.clone().cholesky().is_none());
        self.loading
            .unwrap_or(if model.q_is_zero() || singular_start {
                DEFAULT_LOADING_Q_ZERO
            } else {
                0.0
            })
    }

    /// Refuses options no model can use: a negative or non-finite `band_tol` or `loading`,
    /// the mixture update with known dropouts.
    pub fn check(&self) -> std::result::Result<(), SpecError> {
        check_update(self.dropouts, self.update)?;
        check_non_negative(Setting::BandTol, self.band_tol)?;
        if let Some(loading) = self.loading {
            check_non_negative(Setting::Loading, loading)?;
        }
        Ok(())
    }
}

/// The leading flop count of one subsystem-step of the joint filter (docs/theory.md §8 "Cost"): predict
/// `2n³[(2b+1)(2k+2b+1) + (k+1)(2b+1)]`, selected inversion `2wkn³`, cliques `(k+1)³n³`,
/// Cholesky `k²n³/2`, with `w = min(k + 2b, N − 1)`; twice that with the `band` moment.
pub fn flops_per_subsystem_step(
    n: usize,
    k: usize,
    b: usize,
    subsystems: usize,
    band_moment: bool,
) -> f64 {
    let (n3, k, b) = ((n * n * n) as f64, k as f64, b as f64);
    let w = (k + 2.0 * b).min(subsystems.saturating_sub(1) as f64);
    let predict =
        2.0 * n3 * ((2.0 * b + 1.0) * (2.0 * k + 2.0 * b + 1.0) + (k + 1.0) * (2.0 * b + 1.0));
    let once = predict + 2.0 * w * k * n3 + (k + 1.0).powi(3) * n3 + k * k * n3 / 2.0;
    if band_moment { 2.0 * once } else { once }
}

/// The band of `A_eff` for the parameters in force, rebuilt only when `A`, `B`, `D` or `G` of
/// some subsystem change (docs/theory.md §8 predict step 2).
pub struct AEffBand {
    band: GenBand,
    built_from: Vec<f64>,
    window: usize,
    tol: f64,
    max_memory: u64,
}

impl AEffBand {
    /// The band of `A_eff(t)`; `solver` must be prepared for `t`.
    pub fn new(
        model: &Model,
        t: usize,
        solver: &ChainSolver,
        tol: f64,
        max_memory: u64,
    ) -> Result<Self> {
        Ok(Self {
            band: a_eff_band(model, t, solver, tol, max_memory)?,
            built_from: Self::coupling_params(model, t),
            window: model.window_index(t),
            tol,
            max_memory,
        })
    }

    fn coupling_params(model: &Model, t: usize) -> Vec<f64> {
        let w = model.window(t);
        w.ids
            .iter()
            .flat_map(|&id| {
                let p = model.param_set(id);
                [&p.A, &p.B, &p.D, &p.G]
                    .into_iter()
                    .flat_map(|m| m.as_slice().iter().copied())
            })
            .collect()
    }

    /// Makes the band valid for `t`; returns true when it was rebuilt.
    pub fn prepare(&mut self, model: &Model, t: usize, solver: &ChainSolver) -> Result<bool> {
        let window = model.window_index(t);
        if window == self.window {
            return Ok(false);
        }
        self.window = window;
        let now = Self::coupling_params(model, t);
        if now == self.built_from {
            return Ok(false);
        }
        self.band = a_eff_band(model, t, solver, self.tol, self.max_memory)?;
        self.built_from = now;
        Ok(true)
    }

    pub fn band(&self) -> &GenBand {
        &self.band
    }

    /// The half-width `b`.
    pub fn half_width(&self) -> usize {
        self.band.half_width()
    }
}

/// Copies the diagonal blocks of `p` into `out` (`N · n²`).
fn diagonal_blocks(p: &SymBand, out: &mut [f64]) {
    let nn = p.bs() * p.bs();
    for i in 0..p.nb() {
        out[i * nn..(i + 1) * nn].copy_from_slice(p.block(i, 0));
    }
}

/// `P = blkdiag(P0_1, …, P0_N)` on a band of width `k`.
fn initial_band(model: &Model, k: usize) -> SymBand {
    let n = model.dims.n;
    let mut p = SymBand::zeros(model.subsystems, n, k);
    for i in 0..model.subsystems {
        p.block_mut(i, 0)
            .copy_from_slice(model.initial.of(i).cov.as_slice());
    }
    p
}

/// The mixture update's state (docs/theory.md §10): `π(t, i)` of the last step and one
/// subsystem's pseudo-measurement `(W, r)`, `R u` and scratch.
struct Mixture {
    arrival: Vec<f64>,
    w: Vec<f64>,
    r: Vec<f64>,
    ru: Vec<f64>,
    ws: Box<nahi::Workspace>,
}

/// The joint band-k filter's state between time steps.
pub struct JointFilter {
    model: Model,
    opts: JointOptions,
    k: usize,
    loading: Loading,
    /// The next time step to process.
    t: usize,
    solver: ChainSolver,
    a_eff: AEffBand,
    /// `X̂⁻` and the band `P⁻` (width `k`) before a step; of `t + 1` after it.
    x_pred: Vec<f64>,
    p_pred: SymBand,
    /// `X̂⁺` and `P̃⁺` (width `w`) of the last step.
    x_filt: Vec<f64>,
    p_filt: SymBand,
    moments: Moments,
    lambda: SymBand,
    chol: BandCholesky,
    completion: CompletionWorkspace,
    sandwich: SandwichWorkspace,
    info: InfoWorkspace,
    lifted_ws: LiftedWorkspace,
    r: Vec<f64>,
    mean_scratch: Vec<f64>,
    block_filt: Vec<f64>,
    block_pred: Vec<f64>,
    /// The mixture update's arrival probabilities and scratch (`--update mixture`).
    mixture: Option<Mixture>,
    /// With known dropouts the information vector `𝒥ᵀ ℳ⁻¹ Ỹ` (before the solve overwrites
    /// `r`) and `Σ_i log N(ỹ_i; 0, M_i)`; with the mixture update, the sum of the subsystems'
    /// densities.
    info_vector: Vec<f64>,
    measurement_log_density: f64,
    /// The log density of the last step's measurements (see
    /// [`ChainFilter::log_likelihood`]).
    log_likelihood: Option<f64>,
    /// When recording a [`JointSchedule`]: every subsystem's `R_i⁻¹ H_i` of the last step.
    recorded_gains: Option<Vec<f64>>,
    /// For the smoother (docs/theory.md §9): `Λ⁻(t)` and `Λ⁺(t)` of the last step.
    pub(crate) kept_precisions: Option<(SymBand, SymBand)>,
}

impl JointFilter {
    /// Starts from `X̂⁻(1) = [m0; …; m0]`, `P⁻(1) = blkdiag(P0)` (and the same moments).
    pub fn new(model: &Model, opts: JointOptions) -> Result<Self> {
        let (n, q, big_n) = (model.dims.n, model.dims.q, model.subsystems);
        opts.check()?;
        let known = opts.dropouts == Dropouts::Known;
        let mixture = opts.update == Update::Mixture;
        let loading = Loading::new(model, opts.loading_for(model));
        let k = opts.band.min(big_n - 1);
        let solver = ChainSolver::new(model, 1)?;
        let a_eff = AEffBand::new(model, 1, &solver, opts.band_tol, opts.max_memory)?;
        Self::check_memory(model, &opts, a_eff.half_width())?;
        let w = (k + 2 * a_eff.half_width()).min(big_n - 1);
        let mean = model.initial.means();
        let moments = match (
            reads_second_moment(opts.dropouts, opts.update),
            opts.second_moment,
        ) {
            (false, _) => Moments::None,
            (true, SecondMoment::Band) => Moments::Band {
                mean: mean.clone(),
                cov: initial_band(model, k),
                completed: SymBand::zeros(big_n, n, w),
                chol: Box::new(BandCholesky::new(big_n, n, k)),
            },
            (true, SecondMoment::Lifted) => Moments::Lifted {
                sys: Box::new(LiftedSystem::new(model, 1)?),
                moments: Box::new(LiftedMoments::initial(model)),
            },
            (true, SecondMoment::Local) => Moments::Local {
                mean: mean.clone(),
                cov: model.initial.covs(),
                scratch: vec![0.0; n * n],
                ws: Box::new(nahi::Workspace::new(n, q)),
            },
            (true, SecondMoment::Paper) => {
                return Err(Error::Usage(
                    "--second-moment paper belongs to the distributed filter; the joint filter takes band, lifted or local".into(),
                ));
            }
        };
        let p_pred = initial_band(model, k);
        let mut block_pred = vec![0.0; big_n * n * n];
        diagonal_blocks(&p_pred, &mut block_pred);
        Ok(Self {
            model: model.clone(),
            opts,
            k,
            loading,
            t: 1,
            sandwich: SandwichWorkspace::new(big_n, n, a_eff.half_width(), k),
            solver,
            a_eff,
            x_filt: mean.clone(),
            x_pred: mean,
            p_filt: SymBand::zeros(big_n, n, w),
            p_pred,
            moments,
            lambda: SymBand::zeros(big_n, n, k),
            chol: BandCholesky::new(big_n, n, k),
            completion: CompletionWorkspace::new(big_n, n, k),
            info: InfoWorkspace::new(n, q),
            lifted_ws: LiftedWorkspace::default(),
            r: vec![0.0; big_n * n],
            mean_scratch: vec![0.0; big_n * n],
            block_filt: block_pred.clone(),
            block_pred,
            info_vector: vec![0.0; if known { big_n * n } else { 0 }],
            measurement_log_density: 0.0,
            log_likelihood: None,
            recorded_gains: None,
            kept_precisions: None,
            mixture: mixture.then(|| Mixture {
                arrival: vec![0.0; big_n],
                w: vec![0.0; q * q],
                r: vec![0.0; q],
                ru: vec![0.0; q],
                ws: Box::new(nahi::Workspace::new(n, q)),
            }),
        })
    }

    /// A bound on the bytes the filter holds with `A_eff`'s half-width `b` (docs/theory.md §12
    /// "Memory"): `8 n²` per subsystem times `5(k+1) + 2(w+1) + 2(2b+1) + 24` (the bands, their
    /// factor, `A_eff` and the vectors), `5(k+1) + 2(w+1)` more with the `band` moment, the
    /// cliques' `6 (k+1)² n²`, and `8 (N n)²` more with the dense `lifted` moment. tests/allocation.rs
    /// holds it against the bytes measured.
    pub fn bytes(model: &Model, opts: &JointOptions, b: usize) -> f64 {
        let (n, big_n) = (model.dims.n as f64, model.subsystems);
        let k = opts.band.min(big_n - 1) as f64;
        let w = (k + 2.0 * b as f64).min((big_n - 1) as f64);
        let big_n = big_n as f64;
        let mut per_subsystem =
            5.0 * (k + 1.0) + 2.0 * (w + 1.0) + 2.0 * (2.0 * b as f64 + 1.0) + 24.0;
        let reads_moment = reads_second_moment(opts.dropouts, opts.update);
        if reads_moment && opts.second_moment == SecondMoment::Band {
            per_subsystem += 5.0 * (k + 1.0) + 2.0 * (w + 1.0);
        }
        let mut values = n * n * (big_n * per_subsystem + 6.0 * (k + 1.0) * (k + 1.0));
        if reads_moment && opts.second_moment == SecondMoment::Lifted {
            values += 8.0 * (big_n * n) * (big_n * n);
        }
        8.0 * values
    }

    /// Refuses a filter whose [`Self::bytes`] exceed `opts.max_memory`.
    fn check_memory(model: &Model, opts: &JointOptions, b: usize) -> Result<()> {
        crate::memory::check(Self::bytes(model, opts, b), opts.max_memory, || {
            format!(
                "the joint filter (band k = {}, A_eff half-width b = {b}, N = {} subsystems)",
                opts.band.min(model.subsystems - 1),
                model.subsystems
            )
        })
    }

    /// Whether the filter is told which measurements were lost.
    fn known(&self) -> bool {
        self.opts.dropouts == Dropouts::Known
    }

    /// The covariance band `k` in use.
    pub fn band(&self) -> usize {
        self.k
    }

    /// The half-width `b` of the current `A_eff` band.
    pub fn a_eff_half_width(&self) -> usize {
        self.a_eff.half_width()
    }

    /// The band of `A_eff` used by the last prediction.
    pub fn a_eff_band(&self) -> &GenBand {
        self.a_eff.band()
    }

    /// The diagonal loading `ε` in force.
    pub fn loading(&self) -> f64 {
        self.loading.eps
    }

    /// The loading in force with its floor.
    pub(crate) fn loading_rule(&self) -> Loading {
        self.loading
    }

    /// The covariance of the last output on the band: `P(t|t)` (width ≥ `k`) after a step,
    /// or `T(t+1)` (width `k`) with `predicted`. Block `(i, i+d)` is `P_{i,i+d}`.
    pub fn covariance_band(&self, predicted: bool) -> &SymBand {
        if predicted {
            &self.p_pred
        } else {
            &self.p_filt
        }
    }

    fn band_error(&self, what: &str, e: BandError) -> Error {
        band_error_at(self.t, self.loading.eps, self.k, what, e)
    }

    /// The information of every subsystem's measurement: `Φ_i` added to `lambda`'s diagonal
    /// blocks and `r_i` into `self.r` (update step 2).
    fn measurement_information(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &self.model.clone();
        let (n, q, m) = (model.dims.n, model.dims.q, model.dims.m);
        let window = model.window(self.t);
        self.measurement_log_density = 0.0;
        if let Some(mix) = &mut self.mixture {
            // The mixture update's pseudo-measurements (docs/theory.md §10): Φ_i = Jᵀ W_i J
            // and Jᵀ r_i, from each subsystem's marginal of the loaded prior band.
            for i in 0..model.subsystems {
                let prm = model.param_set(window.ids[i]);
                mix.ru.fill(0.0);
                crate::linalg::mat_vec_add(&mut mix.ru, &prm.R, &u[i * m..(i + 1) * m]);
                let meas = nahi::Measurement {
                    j: &prm.J,
                    m: &prm.M,
                    y: &y[i * q..(i + 1) * q],
                    ru: &mix.ru,
                    p: window.p[i],
                    known: false,
                };
                let x_i = &self.x_pred[i * n..(i + 1) * n];
                let Some(a) = nahi::mixture_pseudo_measurement(
                    &meas,
                    x_i,
                    self.p_pred.block(i, 0),
                    &mut mix.w,
                    &mut mix.r,
                    &mut mix.ws,
                ) else {
                    return Err(Error::Numerical {
                        t: self.t,
                        i: i + 1,
                        msg:
                            "joint filter: the mixture update's J Σ Jᵀ + M is not positive definite"
                                .into(),
                    });
                };
                mix.arrival[i] = a.probability;
                self.measurement_log_density += a.loglik;
                let phi = self.lambda.block_mut(i, 0);
                let r = &mut self.r[i * n..(i + 1) * n];
                for c in 0..n {
                    let mut rc = 0.0;
                    for k in 0..q {
                        rc += prm.J[(k, c)] * mix.r[k];
                        // (W J)_{k, c}
                        let wj: f64 = (0..q).map(|l| mix.w[l * q + k] * prm.J[(l, c)]).sum();
                        for rr in 0..n {
                            phi[c * n + rr] += prm.J[(k, rr)] * wj;
                        }
                    }
                    r[c] = rc;
                }
            }
            return Ok(());
        }
        let known = self.known();
        for i in 0..model.subsystems {
            let prm = model.param_set(window.ids[i]);
            let p = if known { 1.0 } else { window.p[i] };
            let s = self.info.s.as_mut_slice();
            self.moments.second_moment(i, n, s);
            let log_density = self.info.add(
                prm,
                p,
                known,
                &y[i * q..(i + 1) * q],
                &u[i * m..(i + 1) * m],
                &self.x_pred[i * n..(i + 1) * n],
                self.lambda.block_mut(i, 0),
                &mut self.r[i * n..(i + 1) * n],
            );
            let Some(log_density) = log_density else {
                return Err(Error::Numerical {
                    t: self.t,
                    i: i + 1,
                    msg: "joint filter: the measurement covariance M + p(1−p) J S Jᵀ is not positive definite".into(),
                });
            };
            self.measurement_log_density += log_density;
            if let Some(gains) = &mut self.recorded_gains {
                gains[i * q * n..(i + 1) * q * n].copy_from_slice(self.info.w.as_slice());
            }
        }
        Ok(())
    }
}

/// Adds `Q_i` of time `t` to the diagonal blocks.
fn add_process_noise(model: &Model, t: usize, p: &mut SymBand) {
    let window = model.window(t);
    for i in 0..model.subsystems {
        let q = model.param_set(window.ids[i]).Q.as_slice();
        for (b, qv) in p.block_mut(i, 0).iter_mut().zip(q) {
            *b += qv;
        }
    }
}

/// A band error at time `t` of the joint filter as its error, naming `t`, the block and the
/// remedies of docs/theory.md §8.
fn band_error_at(t: usize, loading: f64, k: usize, what: &str, e: BandError) -> Error {
    band_error("joint filter", t, loading, k, &format!("the {what} "), e)
}

/// A band error at time `t` of `who` (the joint filter or smoother): names `t`, the block
/// (`what` prefixes its description) and the remedies of docs/theory.md §8.
pub(crate) fn band_error(
    who: &str,
    t: usize,
    loading: f64,
    k: usize,
    what: &str,
    e: BandError,
) -> Error {
    let (i, detail) = match e {
        BandError::CliqueNotPositiveDefinite { first, last } => (
            first + 1,
            format!("{what}clique of blocks {}..{}", first + 1, last + 1),
        ),
        BandError::PivotNotPositiveDefinite { block } => (
            block + 1,
            format!("{what}Cholesky pivot of block {}", block + 1),
        ),
    };
    Error::Numerical {
        t,
        i,
        msg: format!(
            "{who}: {detail} is not positive definite; raise --loading (now {loading:e}) or --band (now {k})"
        ),
    }
}

impl ChainFilter for JointFilter {
    fn second_moments(&self, out: &mut [f64]) -> bool {
        let n = self.model.dims.n;
        out.chunks_exact_mut(n * n)
            .enumerate()
            .all(|(i, s)| self.moments.second_moment(i, n, s))
    }

    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &self.model.clone();
        let (n, big_n, t) = (model.dims.n, model.subsystems, self.t);
        // Update (docs/theory.md §8 update steps 1–7).
        self.loading.apply(&mut self.p_pred);
        if let Moments::Band { cov, .. } = &mut self.moments {
            self.loading.apply(cov);
        }
        let prior_log_det =
            completion_precision(&self.p_pred, self.k, &mut self.lambda, &mut self.completion)
                .map_err(|e| self.band_error("prior", e))?;
        if let Some((prior, _)) = &mut self.kept_precisions {
            prior.copy_band_from(&self.lambda);
        }
        self.measurement_information(y, u)?;
        if let Some((_, posterior)) = &mut self.kept_precisions {
            posterior.copy_band_from(&self.lambda);
        }
        self.chol
            .factor(&self.lambda)
            .map_err(|e| self.band_error("posterior", e))?;
        if !self.info_vector.is_empty() {
            self.info_vector.copy_from_slice(&self.r);
        }
        self.chol.solve_in_place(&mut self.r);
        self.log_likelihood = self.step_log_likelihood(prior_log_det);
        for ((xf, xp), dx) in self.x_filt.iter_mut().zip(&self.x_pred).zip(&self.r) {
            *xf = xp + dx;
        }
        // The A_eff of this step fixes the width w the prediction needs.
        self.solver.prepare(model, t)?;
        if self.a_eff.prepare(model, t, &self.solver)? || self.sandwich_stale() {
            let b = self.a_eff.half_width();
            Self::check_memory(model, &self.opts, b)?;
            let w = (self.k + 2 * b).min(big_n - 1);
            self.sandwich = SandwichWorkspace::new(big_n, n, b, self.k);
            self.p_filt = SymBand::zeros(big_n, n, w);
            if let Moments::Band { completed, .. } = &mut self.moments {
                *completed = SymBand::zeros(big_n, n, w);
            }
        }
        self.chol.selected_inverse(&mut self.p_filt);
        diagonal_blocks(&self.p_filt, &mut self.block_filt);

        // Predict (docs/theory.md §8 predict steps 1–5).
        propagate_mean(
            model,
            t,
            &self.solver,
            &self.x_filt,
            Some(u),
            &mut self.x_pred,
            &mut self.lifted_ws,
        );
        sandwich(
            self.a_eff.band(),
            &self.p_filt,
            &mut self.p_pred,
            &mut self.sandwich,
        );
        add_process_noise(model, t, &mut self.p_pred);
        self.propagate_moments(u)?;
        diagonal_blocks(&self.p_pred, &mut self.block_pred);
        self.t += 1;
        Ok(())
    }

    fn filtered(&self) -> (&[f64], &[f64]) {
        (&self.x_filt, &self.block_filt)
    }

    fn predicted(&self) -> (&[f64], &[f64]) {
        (&self.x_pred, &self.block_pred)
    }

    fn covariance_band(&self, predicted: bool) -> Option<(&SymBand, usize)> {
        Some((JointFilter::covariance_band(self, predicted), self.k))
    }

    fn arrival(&self) -> Option<&[f64]> {
        self.mixture.as_ref().map(|m| m.arrival.as_slice())
    }

    fn log_likelihood(&self) -> Option<f64> {
        self.log_likelihood
    }
}

impl JointFilter {
    /// The log density of this step's measurements (docs/theory.md §10), after the solve. With
    /// known dropouts, exact for the filter's prior `N(X̂⁻, Σ̃)` (`Σ̃` the completion of the
    /// band, `Λ⁻ = Σ̃⁻¹`): `S = 𝒥 Σ̃ 𝒥ᵀ + ℳ` has `log det S = log det ℳ + log det Σ̃ +
    /// log det Λ⁺` and `Ỹᵀ S⁻¹ Ỹ = Ỹᵀ ℳ⁻¹ Ỹ − bᵀ (Λ⁺)⁻¹ b` with `b = 𝒥ᵀ ℳ⁻¹ Ỹ`, so
    /// `ℓ = Σ_i log N(ỹ_i; 0, M_i) − ½ (log det Σ̃ + log det Λ⁺ − bᵀ (Λ⁺)⁻¹ b)`.
    fn step_log_likelihood(&self, prior_log_det: f64) -> Option<f64> {
        if self.mixture.is_some() {
            return Some(self.measurement_log_density);
        }
        if !self.known() {
            return None;
        }
        let explained: f64 = self
            .info_vector
            .iter()
            .zip(&self.r)
            .map(|(b, x)| b * x)
            .sum();
        Some(self.measurement_log_density - 0.5 * (prior_log_det + self.chol.log_det() - explained))
    }

    /// True when the posterior band is narrower than the current `A_eff` needs (after a
    /// rebuild elsewhere); kept separate so that the common path tests one integer.
    fn sandwich_stale(&self) -> bool {
        let w = (self.k + 2 * self.a_eff.half_width()).min(self.model.subsystems - 1);
        self.p_filt.width() != w
    }
}
