//! The linear update of the centralized filter (docs/theory.md §7) with the structure the
//! chain gives its lifted measurement: `H = blkdiag(H_i)` (`H_i = p_i J_i`, `q × n`) and
//! `R_eff = blkdiag(R_i)`, so that `H T` is a gather of `T`'s block rows and `H T Hᵀ` one of
//! its blocks, with no product by a mostly-zero `H`. On the `r` rows received (a row not in
//! the data is left out, docs/theory.md §15):
//!
//! ```text
//! Σ = H T Hᵀ + R_eff = L Lᵀ       one Cholesky factor
//! V = L⁻¹ H T,  e = L⁻¹ ỹ          one triangular solve
//! x̂(t|t) = x̂ + Vᵀ e
//! P(t|t) = T − Vᵀ V                one product (the rank-r downdate)
//! log N(ỹ; 0, Σ) = −½ (r log 2π + 2 Σ_k log L_kk + |e|²)
//! ```
//!
//! This is `L = T Hᵀ Σ⁻¹`, `P = T − L H T` of docs/theory.md §4 (the gain `L = Vᵀ L⁻¹`,
//! formed only when asked for: [`LiftedUpdate::gain_transposed`]).

use faer::{Accum, MatMut, MatRef};
use nalgebra::DMatrix;

use crate::filter::nahi::LN_2PI;
use crate::linalg::dense::{Cholesky, Lu, solve_lower, symmetric_product};

/// The measurement model of one step and the scratch of the update, sized once for a chain
/// of `blocks` subsystems of state size `n` and measurement size `q`.
#[derive(Debug, Clone)]
pub struct LiftedUpdate {
    n: usize,
    q: usize,
    blocks: usize,
    /// `H_i`, `q × n` column-major, one after another.
    h: Vec<f64>,
    /// `R_i`, `q × q` column-major, one after another.
    r: Vec<f64>,
    /// `ỹ`, `N q` values; NaN where the row is not in the data.
    innov: Vec<f64>,
    /// The rows received, in order: `(row, block, k)`, row `k` of block `block`.
    received: Vec<(usize, usize, usize)>,
    /// Those rows of `H`, `n` values each.
    h_rows: Vec<f64>,
    /// `[H T  ỹ]` on the received rows (`r × (Nn + 1)`), then `[V  e] = L⁻¹ [H T  ỹ]`; the
    /// mixture update's `[𝒲 𝒥 T  r]`, then its solution.
    v: Vec<f64>,
    /// `Σ` on the received rows (`r × r`), then its factor `L` in its lower triangle.
    sigma: Vec<f64>,
    chol: Cholesky,
    /// The mixture update's `𝒥 T` (`Nq × Nn`) and LU factor, made at its first step.
    jt: Vec<f64>,
    lu: Option<Lu>,
}

impl LiftedUpdate {
    pub fn new(blocks: usize, n: usize, q: usize) -> Self {
        let rows = blocks * q;
        Self {
            n,
            q,
            blocks,
            h: vec![0.0; blocks * q * n],
            r: vec![0.0; blocks * q * q],
            innov: vec![0.0; rows],
            received: Vec::with_capacity(rows),
            h_rows: Vec::with_capacity(rows * n),
            v: Vec::with_capacity(rows * (blocks * n + 1)),
            sigma: Vec::with_capacity(rows * rows),
            chol: Cholesky::new(rows),
            jt: Vec::new(),
            lu: None,
        }
    }

    /// Subsystem `i`'s part of the measurement model to fill: `H_i` (`q × n`) and `R_i`
    /// (`q × q`), column-major, and its innovation `ỹ_i` (`q`, NaN where not in the data).
    pub fn block_mut(&mut self, i: usize) -> (&mut [f64], &mut [f64], &mut [f64]) {
        let (n, q) = (self.n, self.q);
        (
            &mut self.h[i * q * n..(i + 1) * q * n],
            &mut self.r[i * q * q..(i + 1) * q * q],
            &mut self.innov[i * q..(i + 1) * q],
        )
    }

    /// The update of the prediction `x̂ = x_pred`, `T = t_pred` (`Nn × Nn` column-major,
    /// symmetric) on the model filled by [`Self::block_mut`]: writes `x̂(t|t)` and `P(t|t)`
    /// (symmetrised) and returns `log N(ỹ; 0, Σ)` over the received rows (0 with none), or
    /// `None` when `Σ` is not positive definite.
    pub fn update(
        &mut self,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> Option<f64> {
        let (n, q) = (self.n, self.q);
        let size = self.blocks * n;
        self.received.clear();
        self.received.extend(
            (0..self.innov.len())
                .filter(|&row| !self.innov[row].is_nan())
                .map(|row| (row, row / q, row % q)),
        );
        let rows = self.received.len();
        if rows == 0 {
            x_filt.copy_from_slice(x_pred);
            p_filt.copy_from_slice(t_pred);
            return Some(0.0);
        }
        // H T on the received rows, and Σ = (H T) Hᵀ + R_eff.
        gather_rows(&self.received, &self.h, n, q, &mut self.h_rows);
        self.v.clear();
        self.v.resize(rows * size, 0.0);
        rows_of_product(t_pred, size, &self.received, &self.h_rows, &mut self.v);
        self.sigma.clear();
        self.sigma.resize(rows * rows, 0.0);
        times_transposed(&self.v, &self.received, &self.h_rows, n, &mut self.sigma);
        for (b, &(_, j, kb)) in self.received.iter().enumerate() {
            // The rows of subsystem j lie within q of row b (the received rows are sorted).
            for a in b.saturating_sub(q)..(b + q).min(rows) {
                let (_, i, ka) = self.received[a];
                if i == j {
                    self.sigma[b * rows + a] += self.r[j * q * q + ka + kb * q];
                }
            }
        }
        if !self.chol.factor(MatMut::from_column_major_slice_mut(
            &mut self.sigma,
            rows,
            rows,
        )) {
            return None;
        }
        let l = MatRef::from_column_major_slice(&self.sigma, rows, rows);
        // [V  e] = L⁻¹ [H T  ỹ] in one solve.
        self.v
            .extend(self.received.iter().map(|&(row, _, _)| self.innov[row]));
        solve_lower(
            l,
            MatMut::from_column_major_slice_mut(&mut self.v, rows, size + 1),
        );
        let (v, e) = self.v.split_at(rows * size);
        correct(x_pred, t_pred, v, v, e, x_filt, p_filt);
        let log_det = 2.0 * log_product((0..rows).map(|k| l[(k, k)]));
        let norm: f64 = e.iter().map(|e| e * e).sum();
        Some(-0.5 * (rows as f64 * LN_2PI + log_det + norm))
    }

    /// The mixture update (docs/theory.md §10) of the prediction `x̂ = x_pred`, `T = t_pred`
    /// (symmetric) from every subsystem's pseudo-measurement, filled by [`Self::block_mut`]:
    /// `J_i` in place of `H_i`, `W_i` (symmetric, possibly indefinite) in place of `R_i` and
    /// `r_i` in place of `ỹ_i`. With `𝒥 = blkdiag(J_i)` and `𝒲 = blkdiag(W_i)`:
    ///
    /// ```text
    /// G = I + 𝒲 𝒥 T 𝒥ᵀ = Π L U            one LU factor (partial pivoting: G is not symmetric)
    /// [Z  z] = G⁻¹ [𝒲 𝒥 T  r]              one solve
    /// x̂(t|t) = x̂ + (𝒥 T)ᵀ z,   P(t|t) = T − (𝒥 T)ᵀ Z
    /// ```
    ///
    /// `(𝒥 T)ᵀ Z = T 𝒥ᵀ 𝒲 (I + 𝒥 T 𝒥ᵀ 𝒲)⁻¹ 𝒥 T` is symmetric: only its lower triangle is
    /// formed. `false` when `G` is singular.
    pub fn pseudo_update(
        &mut self,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> bool {
        let (n, q) = (self.n, self.q);
        let (rows, size) = (self.blocks * q, self.blocks * n);
        self.received.clear();
        self.received
            .extend((0..rows).map(|row| (row, row / q, row % q)));
        gather_rows(&self.received, &self.h, n, q, &mut self.h_rows);
        self.jt.clear();
        self.jt.resize(rows * size, 0.0);
        rows_of_product(t_pred, size, &self.received, &self.h_rows, &mut self.jt);
        // [𝒲 𝒥 T  r]: 𝒲's blocks against 𝒥 T's block rows, column by column.
        self.v.clear();
        self.v.resize(rows * size, 0.0);
        for (jt_col, v_col) in self
            .jt
            .chunks_exact(rows)
            .zip(self.v.chunks_exact_mut(rows))
        {
            for (i, (w_i, out)) in self
                .r
                .chunks_exact(q * q)
                .zip(v_col.chunks_exact_mut(q))
                .enumerate()
            {
                let x = &jt_col[i * q..(i + 1) * q];
                for (ka, o) in out.iter_mut().enumerate() {
                    *o = (0..q).map(|kb| w_i[ka + kb * q] * x[kb]).sum();
                }
            }
        }
        self.v.extend_from_slice(&self.innov);
        // G = I + (𝒲 𝒥 T) 𝒥ᵀ.
        self.sigma.clear();
        self.sigma.resize(rows * rows, 0.0);
        times_transposed(&self.v, &self.received, &self.h_rows, n, &mut self.sigma);
        for k in 0..rows {
            self.sigma[k * rows + k] += 1.0;
        }
        let lu = self.lu.get_or_insert_with(|| Lu::new(rows, size + 1));
        if !lu.factor_and_solve(
            MatMut::from_column_major_slice_mut(&mut self.sigma, rows, rows),
            MatMut::from_column_major_slice_mut(&mut self.v, rows, size + 1),
        ) {
            return false;
        }
        let (gain, z) = self.v.split_at(rows * size);
        correct(x_pred, t_pred, &self.jt, gain, z, x_filt, p_filt);
        true
    }

    /// The transposed gain of the last update, `W = Σ⁻¹ H T = L⁻ᵀ V` (`N q × N n`), with
    /// zero rows for the rows not received.
    pub fn gain_transposed(&self) -> DMatrix<f64> {
        let (rows, size) = (self.received.len(), self.blocks * self.n);
        let mut w = faer::Mat::from_fn(rows, size, |r, c| self.v[c * rows + r]);
        let l = MatRef::from_column_major_slice(&self.sigma, rows, rows);
        faer::linalg::triangular_solve::solve_upper_triangular_in_place(
            l.transpose(),
            w.as_mut(),
            faer::Par::Seq,
        );
        let mut out = DMatrix::zeros(self.innov.len(), size);
        for (a, &(row, _, _)) in self.received.iter().enumerate() {
            for c in 0..size {
                out[(row, c)] = w[(a, c)];
            }
        }
        out
    }
}

/// The corrected moments of both updates: `x̂(t|t) = x̂ + Aᵀ z` and `P(t|t) = T − Aᵀ B` for
/// `A`, `B` `r × Nn` (column-major) with `Aᵀ B` symmetric, of which only the lower triangle is
/// formed.
fn correct(
    x_pred: &[f64],
    t_pred: &[f64],
    a: &[f64],
    b: &[f64],
    z: &[f64],
    x_filt: &mut [f64],
    p_filt: &mut [f64],
) {
    let (rows, size) = (z.len(), x_pred.len());
    for ((xf, xp), a_col) in x_filt.iter_mut().zip(x_pred).zip(a.chunks_exact(rows)) {
        *xf = xp + a_col.iter().zip(z).map(|(a, z)| a * z).sum::<f64>();
    }
    p_filt.copy_from_slice(t_pred);
    symmetric_product(
        MatMut::from_column_major_slice_mut(p_filt, size, size),
        Accum::Add,
        MatRef::from_column_major_slice(a, rows, size).transpose(),
        MatRef::from_column_major_slice(b, rows, size),
        -1.0,
    );
}

/// The rows `(row, i, k)` of `H = blkdiag(H_i)` (`H_i` `q × n`, column-major, one after
/// another in `h`): row `k` of `H_i` for each, `n` values, into `out`.
fn gather_rows(rows: &[(usize, usize, usize)], h: &[f64], n: usize, q: usize, out: &mut Vec<f64>) {
    out.clear();
    for &(_, i, k) in rows {
        let h_i = &h[i * q * n..(i + 1) * q * n];
        out.extend((0..n).map(|l| h_i[k + l * q]));
    }
}

/// `out += H T` on the given rows of `H` (`out` `rows × Nn`, column-major; `h_rows` from
/// [`gather_rows`]). Row `(i, k)` of `H T` is `Σ_l H_i[k, l] T[i n + l, :]`, which is
/// `Σ_l H_i[k, l] T[:, i n + l]ᵀ` for a symmetric `T`: a sum of `T`'s contiguous columns.
fn rows_of_product(
    t: &[f64],
    size: usize,
    rows: &[(usize, usize, usize)],
    h_rows: &[f64],
    out: &mut [f64],
) {
    let (count, n) = (rows.len(), h_rows.len() / rows.len().max(1));
    for (a, (&(_, i, _), h_row)) in rows.iter().zip(h_rows.chunks_exact(n)).enumerate() {
        for (l, &h) in h_row.iter().enumerate() {
            let t_col = &t[(i * n + l) * size..(i * n + l + 1) * size];
            let out_row = out[a..].iter_mut().step_by(count);
            out_row.zip(t_col).for_each(|(o, t)| *o += h * t);
        }
    }
}

/// `out += X Hᵀ` on the given rows of `H` (`X` `rows × Nn` and `out` `rows × rows`,
/// column-major): column `(j, k)` of `out` takes `H_j`'s row `k` against `X`'s block column
/// `j`.
fn times_transposed(
    x: &[f64],
    rows: &[(usize, usize, usize)],
    h_rows: &[f64],
    n: usize,
    out: &mut [f64],
) {
    let count = rows.len();
    for (b, (&(_, j, _), h_row)) in rows.iter().zip(h_rows.chunks_exact(n)).enumerate() {
        let col = &mut out[b * count..(b + 1) * count];
        for (l, &h) in h_row.iter().enumerate() {
            if h != 0.0 {
                let x_col = &x[(j * n + l) * count..(j * n + l + 1) * count];
                col.iter_mut().zip(x_col).for_each(|(o, x)| *o += h * x);
            }
        }
    }
}

/// `Σ log d` of positive finite numbers with a logarithm per hundred or so of them instead of
/// one each: the running product is moved into the sum when it leaves `[1e-100, 1e100]`,
/// before it could overflow or lose digits (a factor is at most `√f64::MAX ≈ 1.3e154`).
fn log_product(factors: impl Iterator<Item = f64>) -> f64 {
    let (mut sum, mut product) = (0.0, 1.0_f64);
    for d in factors {
        product *= d;
        if !(1e-100..=1e100).contains(&product) {
            sum += product.ln();
            product = 1.0;
        }
    }
    sum + product.ln()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DVector;

    /// A fixed smooth sequence of test values.
    fn f(k: usize, s: f64) -> f64 {
        ((k as f64 + 1.0) * s).sin()
    }

    /// A fixed prior `N(x, T)` of `size` states, `T` symmetric positive definite.
    fn prior(size: usize) -> (DMatrix<f64>, DVector<f64>) {
        let a = DMatrix::from_fn(size, size, |r, c| f(r * size + c, 0.7));
        let t = &a * a.transpose() + DMatrix::identity(size, size);
        (t, DVector::from_fn(size, |r, _| f(r, 1.3)))
    }

    /// Three subsystems, `n = 3`, `q = 2`, one row of the second lost: the update against the
    /// dense formulas on the received rows (`Σ = H T Hᵀ + R`, `L = T Hᵀ Σ⁻¹`, `P = T − L H T`).
    #[test]
    fn block_update_matches_the_dense_kalman_update_on_the_received_rows() {
        let (blocks, n, q) = (3, 3, 2);
        let (size, rows) = (blocks * n, blocks * q);
        let (t, x) = prior(size);
        let mut upd = LiftedUpdate::new(blocks, n, q);
        let (mut h_big, mut r_big) = (DMatrix::zeros(rows, size), DMatrix::zeros(rows, rows));
        let y = DVector::from_fn(rows, |r, _| f(r, 2.1));
        let lost = 3;
        for i in 0..blocks {
            let h = DMatrix::from_fn(q, n, |r, c| f(i * 11 + r * n + c, 0.9));
            let m = DMatrix::from_fn(q, q, |r, c| if r == c { 0.5 + i as f64 } else { 0.1 });
            h_big.view_mut((i * q, i * n), (q, n)).copy_from(&h);
            r_big.view_mut((i * q, i * q), (q, q)).copy_from(&m);
            let (hb, rb, innov) = upd.block_mut(i);
            hb.copy_from_slice(h.as_slice());
            rb.copy_from_slice(m.as_slice());
            for k in 0..q {
                let row = i * q + k;
                innov[k] = if row == lost {
                    f64::NAN
                } else {
                    y[row] - (h.row(k) * x.rows(i * n, n))[0]
                };
            }
        }
        let (mut xf, mut pf) = (vec![0.0; size], vec![0.0; size * size]);
        let log_density = upd
            .update(x.as_slice(), t.as_slice(), &mut xf, &mut pf)
            .unwrap();

        let kept: Vec<usize> = (0..rows).filter(|&r| r != lost).collect();
        let h = h_big.select_rows(&kept);
        let r = r_big.select_rows(&kept).select_columns(&kept);
        let sigma = &h * &t * h.transpose() + r;
        let sigma_inv = sigma.clone().try_inverse().unwrap();
        let gain = &t * h.transpose() * &sigma_inv;
        let innov = y.select_rows(&kept) - &h * &x;
        let x_expected = &x + &gain * &innov;
        let p_expected = &t - &gain * &h * &t;
        let expected_density = -0.5
            * (kept.len() as f64 * LN_2PI
                + sigma.determinant().ln()
                + (innov.transpose() * &sigma_inv * &innov)[0]);
        assert!((DVector::from_column_slice(&xf) - x_expected).amax() < 1e-12);
        assert!((DMatrix::from_column_slice(size, size, &pf) - p_expected).amax() < 1e-12);
        assert!((log_density - expected_density).abs() < 1e-12);

        let w = upd.gain_transposed();
        assert_eq!(w.shape(), (rows, size));
        assert!(w.row(lost).iter().all(|&v| v == 0.0));
        assert!((w.select_rows(&kept) - gain.transpose()).amax() < 1e-12);
    }

    /// Three subsystems, `n = 3`, `q = 2`, `W_i` indefinite: the pseudo-measurement update
    /// against the dense formulas (`G = I + 𝒲 𝒥 T 𝒥ᵀ`, `x̂ + (𝒥 T)ᵀ G⁻¹ r`,
    /// `T − (𝒥 T)ᵀ G⁻¹ 𝒲 𝒥 T`), and a singular `G` refused.
    #[test]
    fn pseudo_update_matches_the_dense_mixture_formulas() {
        let (blocks, n, q) = (3, 3, 2);
        let (size, rows) = (blocks * n, blocks * q);
        let (t, x) = prior(size);
        let r = DVector::from_fn(rows, |r, _| f(r, 2.1));
        let mut upd = LiftedUpdate::new(blocks, n, q);
        let (mut j_big, mut w_big) = (DMatrix::zeros(rows, size), DMatrix::zeros(rows, rows));
        for i in 0..blocks {
            let j = DMatrix::from_fn(q, n, |r, c| f(i * 11 + r * n + c, 0.9));
            // Symmetric with eigenvalues of both signs, small enough for a well-conditioned G.
            let w = DMatrix::from_row_slice(q, q, &[0.8 - i as f64, 0.3, 0.3, -0.5]) * 0.05;
            j_big.view_mut((i * q, i * n), (q, n)).copy_from(&j);
            w_big.view_mut((i * q, i * q), (q, q)).copy_from(&w);
            let (jb, wb, rb) = upd.block_mut(i);
            jb.copy_from_slice(j.as_slice());
            wb.copy_from_slice(w.as_slice());
            rb.copy_from_slice(r.rows(i * q, q).as_slice());
        }
        let (mut xf, mut pf) = (vec![0.0; size], vec![0.0; size * size]);
        assert!(upd.pseudo_update(x.as_slice(), t.as_slice(), &mut xf, &mut pf));

        let jt = &j_big * &t;
        let k = DMatrix::identity(rows, rows) + &w_big * &jt * j_big.transpose();
        let k_inv = k.try_inverse().unwrap();
        let x_expected = &x + jt.transpose() * &k_inv * &r;
        let p_expected = &t - jt.transpose() * &k_inv * &w_big * &jt;
        assert!((DVector::from_column_slice(&xf) - x_expected).amax() < 1e-12);
        assert!((DMatrix::from_column_slice(size, size, &pf) - p_expected).amax() < 1e-12);

        // One scalar subsystem with w = −1 / (j² T): G = 1 + w j² T = 0.
        let mut upd = LiftedUpdate::new(1, 1, 1);
        let (jb, wb, rb) = upd.block_mut(0);
        (jb[0], wb[0], rb[0]) = (2.0, -1.0 / 8.0, 1.0);
        let (mut xf, mut pf) = ([0.0], [0.0]);
        assert!(!upd.pseudo_update(&[0.5], &[2.0], &mut xf, &mut pf));
    }

    #[test]
    fn log_product_is_the_sum_of_the_logarithms() {
        let factors: Vec<f64> = (0..500)
            .map(|k| 10f64.powf(((k * 37) % 61) as f64 - 30.0) * 1.7)
            .collect();
        let expected: f64 = factors.iter().map(|d| d.ln()).sum();
        assert!(
            (log_product(factors.into_iter()) - expected).abs() < 1e-10 * expected.abs().max(1.0)
        );
        // Factors at the ends of the range: no overflow, no subnormal product.
        let extremes: [f64; 6] = [1.3e154, 1.2e154, 1e-160, 2e-160, 3.0, 1.3e154];
        let expected: f64 = extremes.iter().map(|d| d.ln()).sum();
        assert!((log_product(extremes.into_iter()) - expected).abs() < 1e-12 * expected.abs());
    }

    #[test]
    fn nothing_received_leaves_the_prediction() {
        let mut upd = LiftedUpdate::new(2, 1, 1);
        for i in 0..2 {
            upd.block_mut(i).2[0] = f64::NAN;
        }
        let (x, t) = ([1.0, 2.0], [2.0, 0.5, 0.5, 3.0]);
        let (mut xf, mut pf) = ([0.0; 2], [0.0; 4]);
        assert_eq!(upd.update(&x, &t, &mut xf, &mut pf), Some(0.0));
        assert_eq!((xf, pf), (x, t));
        assert_eq!(upd.gain_transposed(), DMatrix::zeros(2, 2));
    }
}
