//! The local Nahi filter of one subsystem (docs/theory.md §4, (P21); Nahi 1969), in the Joseph form.
//!
//! With `p = p(t,i)`, the prediction `x̂ = x̂(t|t−1)` with error covariance `T`, the raw
//! second moment `S = E[x xᵀ]`, `H = p J` and `R_eff = M + p(1−p) J S Jᵀ`:
//!
//! ```text
//! Σ       = H T Hᵀ + R_eff                          innovation covariance
//! ỹ       = y − R u − H x̂                           innovation
//! L       = T Hᵀ Σ⁻¹                                filter gain (K = A L is ξ₂ of (P21))
//! x̂(t|t)  = x̂ + L ỹ
//! P(t|t)  = (I − L H) T (I − L H)ᵀ + L R_eff Lᵀ      Joseph form
//! x̂(t+1|t) = A x̂(t|t) + B v̂ + C u,   T(t+1) = A P(t|t) Aᵀ + Q
//! ```
//!
//! The prediction equals docs/theory.md §4's `x̂⁺ = A x̂ + K ỹ + ĉ₁` and its Joseph form
//! `T⁺ = (A − pKJ) T (A − pKJ)ᵀ + K R_eff Kᵀ + Q`, since `A − pKJ = A (I − L H)`.
//! `Σ⁻¹` is never formed: `Σ⁻¹ H T` comes from a Cholesky solve.
//!
//! A row of `y` that is not in the data (NaN: a gap, or a lost element in the known-dropout
//! mode, docs/theory.md §5 and §15) is removed without changing sizes: it gets `H_k = 0`,
//! `ỹ_k = 0` and a unit row and column in `R_eff` (`remove_row`), so it contributes nothing
//! to `Σ⁻¹ H T` and exactly the update on the received rows remains; with no row received the
//! subsystem is only predicted.

use nalgebra::allocator::Allocator;
use nalgebra::{
    Cholesky, DMatrix, DMatrixView, DMatrixViewMut, DVector, DefaultAllocator, Dim, Matrix,
    OMatrix, OVector, StorageMut,
};

use crate::linalg::symmetrize;
use crate::model::{Model, Params};

/// The innovation of one subsystem, `ỹ = y − R u − p J x̂` (`H = p J`), written into `out`
/// (`q` values) from `y` (`q`), `u` (`m`) and the prediction `x̂` (`n`); an element lost in
/// the data (NaN) stays NaN.
pub fn innovation(prm: &Params, p: f64, y: &[f64], u: &[f64], x_pred: &[f64], out: &mut [f64]) {
    for (k, o) in out.iter_mut().enumerate() {
        let mut acc = y[k];
        for (c, uc) in u.iter().enumerate() {
            acc -= prm.R[(k, c)] * uc;
        }
        for (c, xc) in x_pred.iter().enumerate() {
            acc -= p * prm.J[(k, c)] * xc;
        }
        *o = acc;
    }
}

/// The innovations of the whole chain at step `t` with the arrival probabilities
/// `p(t, i)`: [`innovation`] of each subsystem, written into `out` (`N·q` values) from `y`
/// (`N·q`), `u` (`N·m`) and the predictions `x̂` (`N·n`).
pub fn chain_innovations(
    model: &Model,
    t: usize,
    y: &[f64],
    u: &[f64],
    x_pred: &[f64],
    out: &mut [f64],
) {
    let (n, q, m) = (model.dims.n, model.dims.q, model.dims.m);
    let window = model.window(t);
    for i in 0..model.subsystems {
        innovation(
            model.param_set(window.ids[i]),
            window.p[i],
            &y[i * q..(i + 1) * q],
            &u[i * m..(i + 1) * m],
            &x_pred[i * n..(i + 1) * n],
            &mut out[i * q..(i + 1) * q],
        );
    }
}

/// Scratch matrices of one local update, sized once for `(n, q)`; reusing them makes the
/// update allocation-free.
#[derive(Debug, Clone)]
pub struct Workspace {
    h: DMatrix<f64>,
    /// `Hᵀ`, and `Jᵀ` before it (nalgebra's `gemm` has no `A Bᵀ` form).
    h_tr: DMatrix<f64>,
    ht: DMatrix<f64>,
    js: DMatrix<f64>,
    reff: DMatrix<f64>,
    sigma: DMatrix<f64>,
    w: DMatrix<f64>,
    f: DMatrix<f64>,
    f_tr: DMatrix<f64>,
    ft: DMatrix<f64>,
    lr: DMatrix<f64>,
    s: DMatrix<f64>,
    nn: DMatrix<f64>,
    innov: DVector<f64>,
    /// A second `q`-vector: the mixture update's `y − R u`.
    noise: DVector<f64>,
    /// The mixture pseudo-measurement's `J Σ Jᵀ` and `B` (`q × q`), and `Jp S₁⁻¹ e` (`q`).
    jp: DMatrix<f64>,
    b: DMatrix<f64>,
    jp_u: DVector<f64>,
    /// Rows removed by [`Workspace::drop_row`] since the measurement model was set.
    dropped: usize,
}

impl Workspace {
    pub fn new(n: usize, q: usize) -> Self {
        Self {
            h: DMatrix::zeros(q, n),
            h_tr: DMatrix::zeros(n, q),
            ht: DMatrix::zeros(q, n),
            js: DMatrix::zeros(q, n),
            reff: DMatrix::zeros(q, q),
            sigma: DMatrix::zeros(q, q),
            w: DMatrix::zeros(q, n),
            f: DMatrix::zeros(n, n),
            f_tr: DMatrix::zeros(n, n),
            ft: DMatrix::zeros(n, n),
            lr: DMatrix::zeros(n, q),
            s: DMatrix::zeros(n, n),
            nn: DMatrix::zeros(n, n),
            innov: DVector::zeros(q),
            noise: DVector::zeros(q),
            jp: DMatrix::zeros(q, q),
            b: DMatrix::zeros(q, q),
            jp_u: DVector::zeros(q),
            dropped: 0,
        }
    }

    /// `W = Σ⁻¹ H T` of the last update: the transposed gain, `L = Wᵀ`.
    pub fn gain_transposed(&self) -> &DMatrix<f64> {
        &self.w
    }

    /// Removes measurement row `k` from the model in the workspace: `H_k = 0`, `ỹ_k = 0` and
    /// a unit row and column in `R_eff` (`remove_row`), so the row contributes nothing to
    /// the update.
    pub fn drop_row(&mut self, k: usize) {
        self.h.row_mut(k).fill(0.0);
        remove_row(&mut self.reff, k);
        self.innov[k] = 0.0;
        self.dropped += 1;
    }

    /// [`Workspace::drop_row`] for every row of `y` that is not in the data (NaN).
    pub fn drop_missing_rows(&mut self, y: &[f64]) {
        for k in missing_rows(y) {
            self.drop_row(k);
        }
    }

    /// The second-moment matrix `S` to fill before [`update`].
    pub fn second_moment_mut(&mut self) -> &mut DMatrix<f64> {
        &mut self.s
    }
}

/// The measurement model of one update.
pub struct Measurement<'a> {
    pub j: &'a DMatrix<f64>,
    pub m: &'a DMatrix<f64>,
    /// `y(t,i)`; a NaN element is not in the data (a gap, or a lost element in the
    /// known-dropout mode) and its row is left out.
    pub y: &'a [f64],
    /// `R u(t,i)`, already computed.
    pub ru: &'a [f64],
    /// Arrival probability used by the filter (1 in the known-dropout mode).
    pub p: f64,
    /// True in the known-dropout mode: `R_eff = M`, with no term for the unknown arrival.
    pub known: bool,
}

/// The Nahi update of one subsystem: from `x̂ = x_pred`, `T = t_pred` and the second moment
/// in `ws` (see [`Workspace::second_moment_mut`]; unused in the known-dropout mode), writes
/// `x̂(t|t)` into `x_filt` and `P(t|t)` into `p_filt`. Returns what [`kalman_update`]
/// returns.
pub fn update(
    meas: &Measurement,
    x_pred: &[f64],
    t_pred: &[f64],
    x_filt: &mut [f64],
    p_filt: &mut [f64],
    ws: &mut Workspace,
) -> Option<f64> {
    let (q, n) = ws.h.shape();
    let p = meas.p;
    ws.h.copy_from(meas.j);
    ws.h.scale_mut(p);
    ws.reff.copy_from(meas.m);
    if !meas.known && p * (1.0 - p) != 0.0 {
        ws.h_tr.tr_copy_from(meas.j);
        ws.js.gemm_tr(1.0, &ws.h_tr, &ws.s, 0.0);
        ws.reff.gemm(p * (1.0 - p), &ws.js, &ws.h_tr, 1.0);
    }
    // ỹ = y − R u − H x̂
    for k in 0..q {
        let mut hx = 0.0;
        for c in 0..n {
            hx += ws.h[(k, c)] * x_pred[c];
        }
        ws.innov[k] = meas.y[k] - meas.ru[k] - hx;
    }
    ws.dropped = 0;
    ws.drop_missing_rows(meas.y);
    kalman_update(x_pred, t_pred, x_filt, p_filt, ws)
}

/// The linear update of one subsystem, shared by the distributed filters, on the model already in
/// `ws` (`H`, `R_eff`, `ỹ`): `Σ = H T Hᵀ + R_eff`, `L = T Hᵀ Σ⁻¹` (Cholesky solve),
/// `x̂(t|t) = x̂ + L ỹ`, and `P(t|t)` in the Joseph form (symmetrised; positive semidefinite
/// whatever the rounding). Returns
/// `log N(ỹ; 0, Σ)` over the rows not dropped ([`Workspace::drop_row`]), the log density of
/// the measurement given the past when it is Gaussian (known dropouts, docs/theory.md §5), or
/// `None` when `Σ` is not positive definite.
pub fn kalman_update(
    x_pred: &[f64],
    t_pred: &[f64],
    x_filt: &mut [f64],
    p_filt: &mut [f64],
    ws: &mut Workspace,
) -> Option<f64> {
    let (q, n) = ws.h.shape();
    let t_mat = DMatrixView::from_slice(t_pred, n, n);
    ws.ht.gemm(1.0, &ws.h, &t_mat, 0.0);
    ws.sigma.copy_from(&ws.reff);
    ws.h_tr.tr_copy_from(&ws.h);
    ws.sigma.gemm(1.0, &ws.ht, &ws.h_tr, 1.0);
    // W = Σ⁻¹ H T by a Cholesky solve; L = Wᵀ.
    ws.w.copy_from(&ws.ht);
    let sigma = std::mem::replace(&mut ws.sigma, DMatrix::zeros(0, 0));
    let Some(chol) = Cholesky::new(sigma) else {
        ws.sigma = DMatrix::zeros(q, q);
        return None;
    };
    chol.solve_mut(&mut ws.w);
    ws.sigma = chol.unpack();
    // x̂(t|t) = x̂ + Wᵀ ỹ
    for c in 0..n {
        let mut acc = x_pred[c];
        for k in 0..q {
            acc += ws.w[(k, c)] * ws.innov[k];
        }
        x_filt[c] = acc;
    }
    let log_density = received_log_density(&ws.sigma, &mut ws.innov, ws.dropped);
    let mut p_mat = DMatrixViewMut::from_slice(p_filt, n, n);
    // Joseph form: F = I − L H, P = F T Fᵀ + L R_eff Lᵀ.
    ws.f.fill_with_identity();
    ws.f.gemm_tr(-1.0, &ws.w, &ws.h, 1.0);
    ws.ft.gemm(1.0, &ws.f, &t_mat, 0.0);
    ws.f_tr.tr_copy_from(&ws.f);
    p_mat.gemm(1.0, &ws.ft, &ws.f_tr, 0.0);
    ws.lr.gemm_tr(1.0, &ws.w, &ws.reff, 0.0);
    p_mat.gemm(1.0, &ws.lr, &ws.w, 1.0);
    symmetrize(&mut p_mat);
    Some(log_density)
}

/// What the mixture update learnt of one measurement `y(t, i)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// `π`: the posterior probability that the measurement arrived.
    pub probability: f64,
    /// `log(p e^ℓ₁ + (1−p) e^ℓ₀)`: the log density of the measurement given the past.
    pub loglik: f64,
}

/// `log 2π`.
pub(crate) const LN_2PI: f64 = 1.837_877_066_409_345_5;

/// The rows of `y` that are not in the data (NaN; docs/theory.md §15).
pub(crate) fn missing_rows(y: &[f64]) -> impl Iterator<Item = usize> + '_ {
    y.iter()
        .enumerate()
        .filter_map(|(k, v)| v.is_nan().then_some(k))
}

/// Removes row `k` from a measurement covariance: a unit row and column, so that with a zero
/// residual and a zero row of `H` the row adds nothing, and the Cholesky factor of the rest
/// is that of the received rows alone (its log density gains only `−½ log 2π`, taken back by
/// [`received_log_density`]).
pub(crate) fn remove_row<D: Dim, S: StorageMut<f64, D, D>>(
    cov: &mut Matrix<f64, D, D, S>,
    k: usize,
) {
    cov.row_mut(k).fill(0.0);
    cov.column_mut(k).fill(0.0);
    cov[(k, k)] = 1.0;
}

/// `log N(v; 0, L Lᵀ)` from the lower Cholesky factor `L` (only its lower triangle is read),
/// at any size; `v` is overwritten by `L⁻¹ v`.
fn log_density<D: Dim>(l: &OMatrix<f64, D, D>, v: &mut OVector<f64, D>) -> f64
where
    DefaultAllocator: Allocator<D, D> + Allocator<D>,
{
    let log_det: f64 = (0..l.nrows()).map(|k| 2.0 * l[(k, k)].ln()).sum();
    l.solve_lower_triangular_mut(v);
    -0.5 * (l.nrows() as f64 * LN_2PI + log_det + v.norm_squared())
}

/// [`log_density`] of a measurement model with `dropped` rows removed as
/// [`Workspace::drop_row`] removes them: such a row is a unit variance with `v_k = 0`, which
/// adds only `−½ log 2π`, taken back here.
pub(crate) fn received_log_density<D: Dim>(
    l: &OMatrix<f64, D, D>,
    v: &mut OVector<f64, D>,
    dropped: usize,
) -> f64
where
    DefaultAllocator: Allocator<D, D> + Allocator<D>,
{
    log_density(l, v) + 0.5 * dropped as f64 * LN_2PI
}

/// The mixture update of one subsystem (docs/theory.md §10): the measurement either carries
/// the state (`y = J x + R u + d`, prior probability `p`) or is pure noise (`y = R u + d`).
/// From the prior `N(x̂, T)`, with `e₀ = y − R u`, `e = e₀ − J x̂`, `S₁ = J T Jᵀ + M`:
///
/// ```text
/// ℓ₁ = log N(e; 0, S₁),  ℓ₀ = log N(e₀; 0, M)
/// π  = p e^ℓ₁ / (p e^ℓ₁ + (1−p) e^ℓ₀)            (0 when p = 0, 1 when p = 1)
/// K  = T Jᵀ S₁⁻¹,   g = K e
/// x̂(t|t) = x̂ + π g
/// P(t|t) = T − π K S₁ Kᵀ + π(1−π) g gᵀ            (the mixture's covariance, symmetrised)
/// ```
///
/// `p = 1` is the Kalman update, `p = 0` leaves the prior. Writes `x̂(t|t)` into `x_filt`
/// and `P(t|t)` into `p_filt`; returns `None` when `S₁` or `M` is not positive definite.
/// The known-dropout mode has nothing to detect: `meas.known` must be false.
pub fn mixture_update(
    meas: &Measurement,
    x_pred: &[f64],
    t_pred: &[f64],
    x_filt: &mut [f64],
    p_filt: &mut [f64],
    ws: &mut Workspace,
) -> Option<Arrival> {
    let (q, n) = ws.h.shape();
    if meas.y.iter().all(|v| v.is_nan()) {
        x_filt.copy_from_slice(x_pred);
        p_filt.copy_from_slice(t_pred);
        return Some(Arrival::NONE_RECEIVED);
    }
    let arrival = mixture_weights(meas, x_pred, t_pred, ws)?;
    let pi = arrival.probability;
    // W = S₁⁻¹ J T = Kᵀ, and g = K e.
    ws.w.copy_from(&ws.ht);
    ws.sigma.solve_lower_triangular_mut(&mut ws.w);
    ws.sigma.tr_solve_lower_triangular_mut(&mut ws.w);
    for c in 0..n {
        x_filt[c] = (0..q).map(|k| ws.w[(k, c)] * ws.innov[k]).sum();
    }
    let t_mat = DMatrixView::from_slice(t_pred, n, n);
    let mut p_mat = DMatrixViewMut::from_slice(p_filt, n, n);
    p_mat.copy_from(&t_mat);
    p_mat.gemm_tr(-pi, &ws.w, &ws.ht, 1.0);
    let spread = pi * (1.0 - pi);
    for c in 0..n {
        for r in 0..n {
            p_mat[(r, c)] += spread * x_filt[r] * x_filt[c];
        }
    }
    symmetrize(&mut p_mat);
    for c in 0..n {
        x_filt[c] = x_pred[c] + pi * x_filt[c];
    }
    Some(arrival)
}

/// Replaces the positive definite `m` by its lower Cholesky factor; `false` (leaving zeros of
/// the same size) when it is not positive definite.
fn factor_in_place(m: &mut DMatrix<f64>) -> bool {
    let q = m.nrows();
    match Cholesky::new(std::mem::replace(m, DMatrix::zeros(0, 0))) {
        Some(chol) => {
            *m = chol.unpack();
            true
        }
        None => {
            *m = DMatrix::zeros(q, q);
            false
        }
    }
}

/// What both forms of the mixture update share: from the prior `N(x̂, T)`, `π` and the log
/// density, leaving `J T` in `ws.ht`, `Jᵀ` in `ws.h_tr`, the lower Cholesky factor of
/// `S₁ = J T Jᵀ + M` in `ws.sigma` and `e = y − R u − J x̂` in `ws.innov`. `None` when `S₁` or
/// `M` is not positive definite.
fn mixture_weights(
    meas: &Measurement,
    x_pred: &[f64],
    t_pred: &[f64],
    ws: &mut Workspace,
) -> Option<Arrival> {
    let (q, n) = ws.h.shape();
    let p = meas.p;
    let t_mat = DMatrixView::from_slice(t_pred, n, n);
    // `J` and `M` without the rows not in the data (docs/theory.md §15).
    ws.h.copy_from(meas.j);
    ws.reff.copy_from(meas.m);
    let mut dropped = 0;
    for k in missing_rows(meas.y) {
        ws.h.row_mut(k).fill(0.0);
        remove_row(&mut ws.reff, k);
        dropped += 1;
    }
    ws.ht.gemm(1.0, &ws.h, &t_mat, 0.0);
    ws.h_tr.tr_copy_from(&ws.h);
    ws.sigma.copy_from(&ws.reff);
    ws.sigma.gemm(1.0, &ws.ht, &ws.h_tr, 1.0);
    for k in 0..q {
        if meas.y[k].is_nan() {
            ws.noise[k] = 0.0;
            ws.innov[k] = 0.0;
            continue;
        }
        ws.noise[k] = meas.y[k] - meas.ru[k];
        let mut jx = 0.0;
        for c in 0..n {
            jx += meas.j[(k, c)] * x_pred[c];
        }
        ws.innov[k] = ws.noise[k] - jx;
    }
    // ℓ₀ from the factor of M (in `reff`), overwriting e₀; ℓ₁ from the factor of S₁ (in
    // `sigma`) on a copy of e.
    if !factor_in_place(&mut ws.reff) || !factor_in_place(&mut ws.sigma) {
        return None;
    }
    let ell0 = received_log_density(&ws.reff, &mut ws.noise, dropped);
    ws.noise.copy_from(&ws.innov);
    let ell1 = received_log_density(&ws.sigma, &mut ws.noise, dropped);
    Some(Arrival::weigh(p, ell0, ell1))
}

impl Arrival {
    /// A measurement with no row in the data (docs/theory.md §15): nothing to weigh, `π`
    /// unknown (NaN, an empty cell), and a log density of 0.
    pub const NONE_RECEIVED: Arrival = Arrival {
        probability: f64::NAN,
        loglik: 0.0,
    };

    /// `π` and `log(p e^ℓ₁ + (1−p) e^ℓ₀)` from the log densities `ℓ₀` (pure noise) and `ℓ₁`
    /// (the state seen), in log space; `π = 0` when `p ≤ 0`, 1 when `p ≥ 1`.
    pub(crate) fn weigh(p: f64, ell0: f64, ell1: f64) -> Self {
        let (probability, loglik) = if p <= 0.0 {
            (0.0, ell0)
        } else if p >= 1.0 {
            (1.0, ell1)
        } else {
            let (a, b) = (p.ln() + ell1, (1.0 - p).ln() + ell0);
            (
                1.0 / (1.0 + (b - a).exp()),
                a.max(b) + (-(a - b).abs()).exp().ln_1p(),
            )
        };
        Self {
            probability,
            loglik,
        }
    }
}

/// The mixture update of one subsystem as a pseudo-measurement, for the filters that update
/// the whole chain at once (docs/theory.md §10): from the prior marginal `N(x̂, Σ)` of the
/// subsystem (`Σ` its `n × n` block, column-major), writes `W` (`q × q`, column-major,
/// symmetric, possibly indefinite) and `r` (`q`) such that adding `Jᵀ W J` to the chain's
/// precision and `Jᵀ r` to its information vector is the update of [`mixture_update`]:
///
/// ```text
/// Jp = J Σ Jᵀ,  S₁ = Jp + M,  C = π S₁ − π(1−π) e eᵀ,  X = S₁⁻¹ C S₁⁻¹
/// W  = X (I − Jp X)⁻¹,   r = π (I + W Jp) S₁⁻¹ e
/// ```
///
/// `W` is computed without inverting anything but two positive definite matrices, from the
/// rank-one structure of `C`: with `B = (1−π) Jp + M`, `f = B⁻¹ e`,
/// `D = 1 + (1−π) eᵀ (B⁻¹ − S₁⁻¹) e ≥ 1` (since `B ≤ S₁`),
/// `W = π B⁻¹ − π(1−π) f fᵀ / D`; `π = 1` gives `M⁻¹`, `π = 0` gives `0`. Allocation-free.
/// Returns `None` when `S₁` or `M` is not positive definite.
pub fn mixture_pseudo_measurement(
    meas: &Measurement,
    x_pred: &[f64],
    sigma: &[f64],
    w_out: &mut [f64],
    r_out: &mut [f64],
    ws: &mut Workspace,
) -> Option<Arrival> {
    let q = ws.h.nrows();
    if meas.y.iter().all(|v| v.is_nan()) {
        w_out.fill(0.0);
        r_out.fill(0.0);
        return Some(Arrival::NONE_RECEIVED);
    }
    let arrival = mixture_weights(meas, x_pred, sigma, ws)?;
    let pi = arrival.probability;
    // Jp = J Σ Jᵀ; u = S₁⁻¹ e (in `noise`) and δ = eᵀ u.
    ws.jp.gemm(1.0, &ws.ht, &ws.h_tr, 0.0);
    ws.noise.copy_from(&ws.innov);
    ws.sigma.solve_lower_triangular_mut(&mut ws.noise);
    ws.sigma.tr_solve_lower_triangular_mut(&mut ws.noise);
    let delta = ws.innov.dot(&ws.noise);
    // B = (1−π) Jp + M = L Lᵀ, ε = eᵀ B⁻¹ e = |L⁻¹ e|², and f = B⁻¹ e (in `innov`).
    ws.b.copy_from(&ws.jp);
    ws.b.scale_mut(1.0 - pi);
    ws.b += meas.m;
    for k in missing_rows(meas.y) {
        remove_row(&mut ws.b, k);
    }
    if !factor_in_place(&mut ws.b) {
        return None;
    }
    ws.b.solve_lower_triangular_mut(&mut ws.innov);
    let eps = ws.innov.norm_squared();
    ws.b.tr_solve_lower_triangular_mut(&mut ws.innov);
    // W = π B⁻¹ − π(1−π) f fᵀ / D.
    let mut w = DMatrixViewMut::from_slice(w_out, q, q);
    w.fill_with_identity();
    ws.b.solve_lower_triangular_mut(&mut w);
    ws.b.tr_solve_lower_triangular_mut(&mut w);
    w.scale_mut(pi);
    let d = 1.0 + (1.0 - pi) * (eps - delta);
    w.ger(-pi * (1.0 - pi) / d, &ws.innov, &ws.innov, 1.0);
    symmetrize(&mut w);
    // A removed row's unit variance gave it `W_kk = π`: it carries no information.
    for k in missing_rows(meas.y) {
        w.row_mut(k).fill(0.0);
        w.column_mut(k).fill(0.0);
    }
    // r = π (u + W Jp u).
    ws.jp_u.gemv(1.0, &ws.jp, &ws.noise, 0.0);
    let mut r = nalgebra::DVectorViewMut::from_slice(r_out, q);
    r.copy_from(&ws.noise);
    r.gemv(1.0, &w, &ws.jp_u, 1.0);
    r.scale_mut(pi);
    Some(arrival)
}

/// `out = F X Fᵀ + Q` (symmetrised), for the covariance predictions.
pub fn propagate_cov(
    f: &DMatrix<f64>,
    x: &[f64],
    q: Option<&DMatrix<f64>>,
    out: &mut [f64],
    ws: &mut Workspace,
) {
    let n = f.nrows();
    let x = DMatrixView::from_slice(x, n, n);
    ws.nn.gemm(1.0, f, &x, 0.0);
    ws.f_tr.tr_copy_from(f);
    let mut out = DMatrixViewMut::from_slice(out, n, n);
    match q {
        Some(q) => out.copy_from(q),
        None => out.fill(0.0),
    }
    out.gemm(1.0, &ws.nn, &ws.f_tr, 1.0);
    symmetrize(&mut out);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scalar system: hand-derived closed forms of docs/theory.md §4.
    #[test]
    fn scalar_gain_and_covariance_match_closed_form() {
        let (a, j, m, p, t, s, x, y) = (0.9, 2.0, 0.5, 0.7, 1.3, 2.9, 0.4, 1.1);
        let mut ws = Workspace::new(1, 1);
        ws.second_moment_mut()[(0, 0)] = s;
        let (jm, mm) = (
            DMatrix::from_element(1, 1, j),
            DMatrix::from_element(1, 1, m),
        );
        let meas = Measurement {
            j: &jm,
            m: &mm,
            y: &[y],
            ru: &[0.0],
            p,
            known: false,
        };
        let (mut xf, mut pf) = ([0.0], [0.0]);
        assert!(update(&meas, &[x], &[t], &mut xf, &mut pf, &mut ws).is_some());
        let sigma = m + p * p * j * j * t + p * (1.0 - p) * j * j * s;
        let gain = p * t * j / sigma; // L; K = a L
        let x_exp = x + gain * (y - p * j * x);
        let p_exp = t - p * p * t * t * j * j / sigma;
        assert!((xf[0] - x_exp).abs() < 1e-14, "{} vs {x_exp}", xf[0]);
        assert!((pf[0] - p_exp).abs() < 1e-14, "{} vs {p_exp}", pf[0]);
        // docs/theory.md §4's one-step form: T⁺ = (A − pKJ) T Aᵀ with K = p A T J / Σ.
        let k = p * a * t * j / sigma;
        let t_next_exp = (a - p * k * j) * t * a;
        let mut t_next = [0.0];
        propagate_cov(
            &DMatrix::from_element(1, 1, a),
            &pf,
            None,
            &mut t_next,
            &mut ws,
        );
        assert!((t_next[0] - t_next_exp).abs() < 1e-14);
    }

    /// Known-dropout mode with one of two rows lost equals the update with that row removed.
    #[test]
    fn lost_row_equals_removed_row() {
        let jm = DMatrix::from_row_slice(2, 2, &[1.0, 0.5, -0.3, 2.0]);
        let mm = DMatrix::from_row_slice(2, 2, &[0.2, 0.05, 0.05, 0.3]);
        let t = [1.0, 0.2, 0.2, 0.8];
        let x = [0.3, -0.1];
        let mut ws = Workspace::new(2, 2);
        let (mut xf, mut pf) = ([0.0; 2], [0.0; 4]);
        let meas = Measurement {
            j: &jm,
            m: &mm,
            y: &[f64::NAN, 0.7],
            ru: &[0.0, 0.1],
            p: 1.0,
            known: true,
        };
        assert!(update(&meas, &x, &t, &mut xf, &mut pf, &mut ws).is_some());
        // Textbook Kalman update on row 2 alone.
        let j2 = jm.row(1).into_owned();
        let tm = DMatrix::from_column_slice(2, 2, &t);
        let s = (&j2 * &tm * j2.transpose())[(0, 0)] + mm[(1, 1)];
        let l = &tm * j2.transpose() / s;
        let innov = 0.7 - 0.1 - (&j2 * DVector::from_column_slice(&x))[0];
        let x_exp = DVector::from_column_slice(&x) + &l * innov;
        let p_exp = &tm - &l * &j2 * &tm;
        for k in 0..2 {
            assert!((xf[k] - x_exp[k]).abs() < 1e-14);
        }
        for k in 0..4 {
            assert!((pf[k] - p_exp.as_slice()[k]).abs() < 1e-14);
        }
    }

    /// A 3-state, 2-measurement subsystem for the mixture update's tests: `J`, `M`, the
    /// prior `N(x, T)` and `R u`.
    struct MixtureCase {
        j: DMatrix<f64>,
        m: DMatrix<f64>,
        t: DMatrix<f64>,
        x: [f64; 3],
        ru: [f64; 2],
    }

    fn mixture_case() -> MixtureCase {
        MixtureCase {
            j: DMatrix::from_row_slice(2, 3, &[1.0, 0.5, 0.0, 0.0, -0.3, 2.0]),
            m: DMatrix::from_row_slice(2, 2, &[0.4, 0.1, 0.1, 0.3]),
            t: DMatrix::from_row_slice(3, 3, &[1.2, 0.3, -0.1, 0.3, 0.8, 0.2, -0.1, 0.2, 0.5]),
            x: [0.4, -1.0, 2.0],
            ru: [0.2, -0.1],
        }
    }

    /// `log N(v; 0, S)` with an explicit inverse and determinant.
    fn dense_log_density(v: &DVector<f64>, s: &DMatrix<f64>) -> f64 {
        let inv = s.clone().try_inverse().unwrap();
        -0.5 * (v.len() as f64 * (2.0 * std::f64::consts::PI).ln()
            + s.determinant().ln()
            + v.dot(&(inv * v)))
    }

    fn run_mixture(
        p: f64,
        y: &[f64; 2],
        ws: &mut Workspace,
    ) -> (Option<Arrival>, Vec<f64>, Vec<f64>) {
        let MixtureCase { j, m, t, x, ru } = mixture_case();
        let meas = Measurement {
            j: &j,
            m: &m,
            y,
            ru: &ru,
            p,
            known: false,
        };
        let (mut xf, mut pf) = (vec![0.0; 3], vec![0.0; 9]);
        let arrival = mixture_update(&meas, &x, t.as_slice(), &mut xf, &mut pf, ws);
        (arrival, xf, pf)
    }

    /// The mixture update is the moment match of the two hypotheses, written out densely
    /// here: with probability π the Kalman posterior `N(x̂ + K e, T − K S₁ Kᵀ)`, else the prior,
    /// with π and the log-likelihood from the two Gaussian densities.
    #[test]
    fn mixture_update_matches_the_two_hypotheses_moments() {
        let MixtureCase { j, m, t, x, ru } = mixture_case();
        let x = DVector::from_column_slice(&x);
        let mut ws = Workspace::new(3, 2);
        // Readings near the prediction, far from it, near pure noise, and between the two
        // (where π(1 − π) widens P); several p.
        let mut undecided = 0;
        for (y, p) in [
            ([0.15, 1.2], 0.5),
            ([0.0, 3.6], 0.7),
            ([4.0, -5.0], 0.7),
            ([0.15, -0.05], 0.9),
            ([0.5, 3.0], 0.2),
        ] {
            let e0 = DVector::from_column_slice(&y) - DVector::from_column_slice(&ru);
            let e = &e0 - &j * &x;
            let s1 = &j * &t * j.transpose() + &m;
            let (l1, l0) = (dense_log_density(&e, &s1), dense_log_density(&e0, &m));
            let (w1, w0) = (p * l1.exp(), (1.0 - p) * l0.exp());
            let pi = w1 / (w1 + w0);
            let k = &t * j.transpose() * s1.clone().try_inverse().unwrap();
            let mean1 = &x + &k * &e;
            let cov1 = &t - &k * &s1 * k.transpose();
            let mean = &mean1 * pi + &x * (1.0 - pi);
            let (d1, d0) = (&mean1 - &mean, &x - &mean);
            let cov = (cov1 + &d1 * d1.transpose()) * pi + (&t + &d0 * d0.transpose()) * (1.0 - pi);

            let (arrival, xf, pf) = run_mixture(p, &y, &mut ws);
            let arrival = arrival.expect("positive definite");
            undecided += usize::from((0.1..0.9).contains(&pi));
            assert!(
                (arrival.probability - pi).abs() < 1e-12,
                "{y:?}: π {arrival:?} vs {pi}"
            );
            assert!((arrival.loglik - (w1 + w0).ln()).abs() < 1e-12, "{y:?}");
            for r in 0..3 {
                assert!((xf[r] - mean[r]).abs() < 1e-12, "{y:?}: x̂ {xf:?} vs {mean}");
                for c in 0..3 {
                    assert!(
                        (pf[r + 3 * c] - cov[(r, c)]).abs() < 1e-12,
                        "{y:?}: P {pf:?} vs {cov}"
                    );
                }
            }
        }
        assert!(undecided > 0, "no reading left the hypotheses undecided");
    }

    /// `p = 1` is the Kalman update ([`update`] with `p = 1`, whose `R_eff` is `M`); `p = 0`
    /// leaves the prior untouched.
    #[test]
    fn mixture_update_with_p_one_is_kalman_and_with_p_zero_keeps_the_prior() {
        let MixtureCase { j, m, t, x, ru } = mixture_case();
        let y = [1.0, 2.5];
        let mut ws = Workspace::new(3, 2);
        let (arrival, xf, pf) = run_mixture(1.0, &y, &mut ws);
        assert_eq!(arrival.unwrap().probability, 1.0);
        let meas = Measurement {
            j: &j,
            m: &m,
            y: &y,
            ru: &ru,
            p: 1.0,
            known: false,
        };
        let (mut xk, mut pk) = (vec![0.0; 3], vec![0.0; 9]);
        assert!(update(&meas, &x, t.as_slice(), &mut xk, &mut pk, &mut ws).is_some());
        for (a, b) in xf.iter().zip(&xk).chain(pf.iter().zip(&pk)) {
            assert!((a - b).abs() < 1e-12, "{xf:?} {pf:?} vs {xk:?} {pk:?}");
        }

        let (arrival, xf, pf) = run_mixture(0.0, &y, &mut ws);
        assert_eq!(arrival.unwrap().probability, 0.0);
        assert_eq!(xf, x);
        assert_eq!(pf, t.as_slice());
    }

    /// A measurement covariance that is not positive definite is refused, not used.
    #[test]
    fn mixture_update_refuses_an_indefinite_m() {
        let MixtureCase { j, t, x, ru, .. } = mixture_case();
        let m = DMatrix::from_row_slice(2, 2, &[0.4, 0.9, 0.9, 0.3]);
        let meas = Measurement {
            j: &j,
            m: &m,
            y: &[0.0, 0.0],
            ru: &ru,
            p: 0.5,
            known: false,
        };
        let (mut xf, mut pf) = (vec![0.0; 3], vec![0.0; 9]);
        let mut ws = Workspace::new(3, 2);
        assert!(mixture_update(&meas, &x, t.as_slice(), &mut xf, &mut pf, &mut ws).is_none());
    }

    /// The pseudo-measurement `(W, r)` applied in covariance form, `G = I + W J Σ Jᵀ`,
    /// `x̂⁺ = x̂ + Σ Jᵀ G⁻¹ r`, `Σ⁺ = Σ − Σ Jᵀ G⁻¹ W J Σ` (dense inverse here), is the mixture
    /// update, also where `W` is indefinite.
    #[test]
    fn mixture_pseudo_measurement_is_the_mixture_update() {
        let MixtureCase { j, m, t, x, ru } = mixture_case();
        let mut ws = Workspace::new(3, 2);
        let mut indefinite = 0;
        for (y, p) in [
            ([0.15, 1.2], 0.5),
            ([0.0, 3.6], 0.7),
            ([0.15, -0.05], 0.9),
            ([0.5, 3.0], 0.2),
            ([0.1, 4.2], 1.0),
        ] {
            let meas = Measurement {
                j: &j,
                m: &m,
                y: &y,
                ru: &ru,
                p,
                known: false,
            };
            let (mut w, mut r) = (vec![0.0; 4], vec![0.0; 2]);
            let a = mixture_pseudo_measurement(&meas, &x, t.as_slice(), &mut w, &mut r, &mut ws)
                .unwrap();
            let w = DMatrix::from_column_slice(2, 2, &w);
            let r = DVector::from_column_slice(&r);
            indefinite += usize::from(w.symmetric_eigenvalues().min() < 0.0);
            let g = DMatrix::identity(2, 2) + &w * &j * &t * j.transpose();
            let g_inv = g.try_inverse().unwrap();
            let x_info = DVector::from_column_slice(&x) + &t * j.transpose() * &g_inv * &r;
            let p_info = &t - &t * j.transpose() * &g_inv * &w * &j * &t;

            let (mut xf, mut pf) = (vec![0.0; 3], vec![0.0; 9]);
            let b = mixture_update(&meas, &x, t.as_slice(), &mut xf, &mut pf, &mut ws).unwrap();
            assert_eq!(a, b, "{y:?}");
            for (got, want) in x_info.iter().zip(&xf).chain(p_info.iter().zip(&pf)) {
                assert!(
                    (got - want).abs() < 1e-11,
                    "{y:?}: {x_info} {p_info} vs {xf:?} {pf:?}"
                );
            }
        }
        assert!(indefinite > 0, "no case with an indefinite W");
    }
}
