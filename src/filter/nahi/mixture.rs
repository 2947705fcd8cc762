//! The mixture update of one subsystem (docs/theory.md §10): the measurement either carries
//! the state or is pure noise, and the update weighs the two by their densities.

use nalgebra::{Cholesky, DMatrix, DMatrixView, DMatrixViewMut};

use super::{Measurement, Workspace, missing_rows, received_log_density, remove_row};
use crate::linalg::symmetrize;

/// What the mixture update learnt of one measurement `y(t, i)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// `π`: the posterior probability that the measurement arrived.
    pub probability: f64,
    /// `log(p e^ℓ₁ + (1−p) e^ℓ₀)`: the log density of the measurement given the past.
    pub loglik: f64,
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

#[cfg(test)]
mod tests {
    use nalgebra::DVector;

    use super::*;
    use crate::filter::nahi::update;

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
