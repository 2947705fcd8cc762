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

mod mixture;
pub use mixture::{Arrival, mixture_pseudo_measurement, mixture_update};

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
}
