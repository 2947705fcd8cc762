//! The lifted system of docs/theory.md §3: the whole chain as one linear system
//! `X⁺ = A_eff X + U_eff U + Ω`, with `A_eff = blkdiag(A) + blkdiag(B) L_x`, where
//! `V = L_x X + L_u U` is the interconnection solve of docs/theory.md §2.

use std::sync::Arc;

use faer::{Accum, MatMut, MatRef};
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use crate::error::Result;
use crate::interconnect::ChainSolver;
use crate::linalg::band::GenBand;
use crate::linalg::dense;
use crate::linalg::envelope::RowEnvelope;
use crate::linalg::{mat_vec_add, mat_vec_add_blocks, mat_vec_blocks};
use crate::model::Model;

/// Scratch for [`apply_a_eff`] and [`propagate_mean`].
#[derive(Debug, Default, Clone)]
pub struct LiftedWorkspace {
    z: Vec<f64>,
    v: Vec<f64>,
    rhs: Vec<f64>,
}

impl LiftedWorkspace {
    /// The interconnection signals `v` (`N · (n⁺+n⁻)` values) of the last product.
    pub fn interconnection(&self) -> &[f64] {
        &self.v
    }
}

/// `out = A_eff(t) x`: `z(i) = D x(i)`, `v` from the chain solve, `out(i) = A x(i) + B v(i)`.
/// `solver` must be prepared for `t`.
pub fn apply_a_eff(
    model: &Model,
    t: usize,
    solver: &ChainSolver,
    x: &[f64],
    out: &mut [f64],
    ws: &mut LiftedWorkspace,
) {
    propagate_mean(model, t, solver, x, None, out, ws);
}

/// `out = A_eff(t) x + U_eff(t) u` without forming either matrix (docs/theory.md §3, §8 predict step
/// 1): `z(i) = D x(i) + H u(i)`, `v` from the chain solve of docs/theory.md §2, and
/// `out(i) = A x(i) + B v(i) + C u(i)`. `u = None` means no input. The `v` used is left in
/// [`LiftedWorkspace::interconnection`]. `solver` must be prepared for `t`.
pub fn propagate_mean(
    model: &Model,
    t: usize,
    solver: &ChainSolver,
    x: &[f64],
    u: Option<&[f64]>,
    out: &mut [f64],
    ws: &mut LiftedWorkspace,
) {
    let (n, m, s, big_n) = (model.dims.n, model.dims.m, model.dims.s(), model.subsystems);
    ws.z.resize(big_n * s, 0.0);
    ws.v.resize(big_n * s, 0.0);
    let window = model.window(t);
    // A run of subsystems with one parameter set at a time (the same sums per subsystem).
    for (run, id) in window.runs() {
        let p = model.param_set(id);
        let z = &mut ws.z[run.start * s..run.end * s];
        mat_vec_blocks(z, &p.D, &x[run.start * n..run.end * n]);
        if let Some(u) = u {
            mat_vec_add_blocks(z, &p.H, &u[run.start * m..run.end * m]);
        }
    }
    solver.solve(&ws.z, &mut ws.v, &mut ws.rhs);
    for (run, id) in window.runs() {
        let p = model.param_set(id);
        let o = &mut out[run.start * n..run.end * n];
        mat_vec_blocks(o, &p.A, &x[run.start * n..run.end * n]);
        mat_vec_add_blocks(o, &p.B, &ws.v[run.start * s..run.end * s]);
        if let Some(u) = u {
            mat_vec_add_blocks(o, &p.C, &u[run.start * m..run.end * m]);
        }
    }
}

/// The dense `A_eff(t)`, `Nn × Nn`, column by column.
pub fn a_eff_dense(model: &Model, t: usize, solver: &ChainSolver) -> DMatrix<f64> {
    let size = model.subsystems * model.dims.n;
    let mut a = DMatrix::zeros(size, size);
    let mut e = vec![0.0; size];
    let mut col = vec![0.0; size];
    let mut ws = LiftedWorkspace::default();
    for c in 0..size {
        e[c] = 1.0;
        apply_a_eff(model, t, solver, &e, &mut col, &mut ws);
        a.column_mut(c).copy_from_slice(&col);
        e[c] = 0.0;
    }
    a
}

/// First trial half-width of [`a_eff_band`] (docs/theory.md §8 predict step 2).
const FIRST_TRIAL_HALF_WIDTH: usize = 16;

/// The block band of `A_eff(t)` by column compression (Curtis–Powell–Reid; docs/theory.md §8 predict
/// step 2). For a trial half-width `b_m` and period `p = 2 b_m + 1`, each of the `p·n` probes
/// `Z^{(r,c)}` has block `j` equal to `e_c` when `j ≡ r (mod p)`, so that
/// `A_eff(i, j)[:, c] = (A_eff Z^{(j mod p, c)})_i` for `|i − j| ≤ b_m`: only one such `j`
/// lies within `b_m` of `i`. With `ν_d = max_i max |A_eff(i, i+d)|` the kept half-width is
/// `b = max{|d| : ν_d > tol · max_d ν_d}`; when `b` reaches `b_m < N − 1` the blocks may not
/// have decayed yet and `b_m` is doubled. With `tol = 0` the result is the exact `A_eff`
/// whenever its band ends before `N − 1`, and always at `b_m = N − 1` (one probe per column).
/// `solver` must be prepared for `t`. A trial band larger than `max_memory` is refused before
/// it is allocated.
pub fn a_eff_band(
    model: &Model,
    t: usize,
    solver: &ChainSolver,
    tol: f64,
    max_memory: u64,
) -> Result<GenBand> {
    let (n, big_n) = (model.dims.n, model.subsystems);
    let mut ws = LiftedWorkspace::default();
    let (mut probe, mut col) = (vec![0.0; big_n * n], vec![0.0; big_n * n]);
    let mut trial = FIRST_TRIAL_HALF_WIDTH.min(big_n - 1);
    loop {
        let period = 2 * trial + 1;
        let need = 8.0 * (big_n * n * n) as f64 * period as f64;
        crate::memory::check(need, max_memory, || {
            format!(
                "the band of A_eff at t = {t} (trial half-width {trial} of N = {big_n} subsystems)"
            )
        })?;
        let mut band = GenBand::zeros(big_n, n, trial);
        for r in 0..period.min(big_n) {
            for c in 0..n {
                probe.fill(0.0);
                for j in (r..big_n).step_by(period) {
                    probe[j * n + c] = 1.0;
                }
                apply_a_eff(model, t, solver, &probe, &mut col, &mut ws);
                for i in 0..big_n {
                    // The one column block j ≡ r (mod period) with |i − j| ≤ trial.
                    let lo = i.saturating_sub(trial);
                    let j = lo + (r + period - lo % period) % period;
                    if j < big_n && j <= i + trial {
                        band.block_mut(i, j)[c * n..(c + 1) * n]
                            .copy_from_slice(&col[i * n..(i + 1) * n]);
                    }
                }
            }
        }
        // ν_d for d = −trial..=trial, at index d + trial.
        let mut nu = vec![0.0_f64; 2 * trial + 1];
        for i in 0..big_n {
            for j in i.saturating_sub(trial)..=(i + trial).min(big_n - 1) {
                let d = j + trial - i;
                let amax = band.block(i, j).iter().fold(0.0_f64, |a, v| a.max(v.abs()));
                nu[d] = nu[d].max(amax);
            }
        }
        let largest = nu.iter().copied().fold(0.0, f64::max);
        let kept = (0..=trial)
            .rev()
            .find(|&d| nu[trial + d].max(nu[trial - d]) > tol * largest)
            .unwrap_or(0);
        if kept == trial && trial < big_n - 1 {
            trial = (2 * trial).min(big_n - 1);
            continue;
        }
        if kept == trial {
            return Ok(band);
        }
        let mut narrow = GenBand::zeros(big_n, n, kept);
        for i in 0..big_n {
            for j in i.saturating_sub(kept)..=(i + kept).min(big_n - 1) {
                narrow.block_mut(i, j).copy_from_slice(band.block(i, j));
            }
        }
        return Ok(narrow);
    }
}

/// The dense lifted matrices of docs/theory.md §3 at one time: `X⁺ = A_eff X + U_eff U + Ω`,
/// `Ω ~ N(0, Q_big)`. `O((Nn)²)` memory: for reference filters on moderate chains.
#[derive(Debug, Clone)]
pub struct LiftedSystem {
    /// `A_eff = blkdiag(A) + blkdiag(B) L_x`, shared with the smoother's stored steps.
    pub a_eff: Arc<Transition>,
    /// `U_eff = blkdiag(C) + blkdiag(B) L_u`.
    pub u_eff: DMatrix<f64>,
    /// `blkdiag(Q)`.
    pub q_big: DMatrix<f64>,
    /// The window these matrices belong to.
    pub window: usize,
    /// A step of that window, and its interconnection solve: `A_eff` applied without the
    /// dense matrix ([`Self::covariance_step`]).
    t: usize,
    solver: ChainSolver,
}

/// `A_eff(t)` as its products take it: the dense matrix, and its rows' nonzero stretches
/// when they are narrow enough for the products to take them instead (at most 15 % of a row
/// on average; docs/theory.md §7).
#[derive(Debug, Clone)]
pub struct Transition {
    pub dense: DMatrix<f64>,
    rows: Option<RowEnvelope>,
}

impl Transition {
    fn new(dense: DMatrix<f64>) -> Self {
        let size = dense.nrows();
        let rows = RowEnvelope::of(MatRef::from_column_major_slice(
            dense.as_slice(),
            size,
            size,
        ));
        let narrow = rows.mean_width() <= ENVELOPE_MAX_WIDTH * size as f64;
        Self {
            dense,
            rows: narrow.then_some(rows),
        }
    }

    /// `out = A_eff X` for a symmetric `X` (`Nn × Nn`, column-major): with a narrow row
    /// envelope, the transpose of `X A_effᵀ` (formed in `scratch`), `O((Nn)² w̄)`; otherwise
    /// one dense product.
    pub fn times_symmetric(&self, x: &[f64], out: &mut [f64], scratch: &mut Vec<f64>) {
        let size = self.dense.nrows();
        let Some(rows) = &self.rows else {
            dense::product(
                MatMut::from_column_major_slice_mut(out, size, size),
                Accum::Replace,
                MatRef::from_column_major_slice(self.dense.as_slice(), size, size),
                MatRef::from_column_major_slice(x, size, size),
                1.0,
            );
            return;
        };
        scratch.resize(size * size, 0.0);
        rows.times_transposed(x, scratch, false, false);
        MatMut::from_column_major_slice_mut(out, size, size)
            .copy_from(MatRef::from_column_major_slice(scratch, size, size).transpose());
    }

    /// `out += Y A_effᵀ` where the sum is known to be symmetric (`Y = A_eff X` for a symmetric
    /// `X`, `out` symmetric): only the lower triangle is formed, by the row envelope where it
    /// is narrow, else by one dense product, then mirrored.
    fn add_symmetric_product(&self, y: &[f64], out: &mut [f64]) {
        let size = self.dense.nrows();
        match &self.rows {
            Some(rows) => {
                rows.times_transposed(y, out, true, true);
                dense::mirror_lower(MatMut::from_column_major_slice_mut(out, size, size));
            }
            None => dense::symmetric_product(
                MatMut::from_column_major_slice_mut(out, size, size),
                Accum::Add,
                MatRef::from_column_major_slice(y, size, size),
                MatRef::from_column_major_slice(self.dense.as_slice(), size, size).transpose(),
                1.0,
            ),
        }
    }
}

/// Scratch of [`LiftedSystem::covariance_step`]: `A_eff X` (`Nn × Nn`), with the row
/// envelope `X A_effᵀ` as well, and one chain-solve workspace per thread, sized at the first
/// step.
#[derive(Debug, Clone, Default)]
pub struct CovarianceScratch {
    a_x: Vec<f64>,
    x_at: Vec<f64>,
    chains: Vec<LiftedWorkspace>,
}

/// The products by `A_eff` take it by its rows' nonzero stretches ([`RowEnvelope`]) when
/// they keep on average at most this share of a row: `A_eff X A_effᵀ` then costs two sums of
/// `w̄` columns per column (`O((Nn)² w̄)`) against the dense products' `O((Nn)³)`, which run
/// several times faster per operation; one product `X A_effᵀ` on one thread breaks even near
/// this share at 40, 200 and 800 states. (The platoon, `G = 0`, keeps 5.8 of 40 states.)
const ENVELOPE_MAX_WIDTH: f64 = 0.15;

/// Fewer lifted states than this take `A_eff X` as a dense product: the chain solve costs
/// `O(N)` a column against the product's `O(N²)`, and on the platoon (`n = 2`) they break even
/// near 400 states (1.2 times faster at 800).
const CHAIN_SOLVE_MIN_STATES: usize = 400;

impl LiftedSystem {
    /// Builds the lifted matrices at time `t`, column by column from the chain solve.
    pub fn new(model: &Model, t: usize) -> Result<Self> {
        let d = model.dims;
        let (n, m, s, big_n) = (d.n, d.m, d.s(), model.subsystems);
        let solver = ChainSolver::new(model, t)?;
        let a_eff = a_eff_dense(model, t, &solver);
        let window = model.window(t);
        let mut u_eff = DMatrix::zeros(big_n * n, big_n * m);
        let (mut z, mut v, mut rhs) = (vec![0.0; big_n * s], vec![0.0; big_n * s], Vec::new());
        for j in 0..big_n {
            let pj = model.param_set(window.ids[j]);
            for k in 0..m {
                z.fill(0.0);
                for r in 0..s {
                    z[j * s + r] = pj.H[(r, k)];
                }
                solver.solve(&z, &mut v, &mut rhs);
                let col = j * m + k;
                for i in 0..big_n {
                    let pi = model.param_set(window.ids[i]);
                    let block = &mut u_eff.as_mut_slice()[col * big_n * n + i * n..][..n];
                    mat_vec_add(block, &pi.B, &v[i * s..(i + 1) * s]);
                    if i == j {
                        for r in 0..n {
                            block[r] += pi.C[(r, k)];
                        }
                    }
                }
            }
        }
        let mut q_big = DMatrix::zeros(big_n * n, big_n * n);
        for i in 0..big_n {
            q_big
                .view_mut((i * n, i * n), (n, n))
                .copy_from(&model.param_set(window.ids[i]).Q);
        }
        Ok(Self {
            a_eff: Arc::new(Transition::new(a_eff)),
            u_eff,
            q_big,
            window: model.window_index(t),
            t,
            solver,
        })
    }

    /// `out = A_eff X A_effᵀ + Q_big` for a symmetric `X` (`Nn × Nn`, column-major): the
    /// covariance step of the lifted chain (docs/theory.md §3, §7). With a narrow row envelope
    /// of `A_eff` (a chain with `G = 0`), both products are sums of the envelope's columns:
    /// `X A_effᵀ`, transposed to `A_eff X`, and the lower triangle of `(A_eff X) A_effᵀ`.
    /// Otherwise `A_eff X` is a chain solve per column of `X` on long chains (`O(N)` each, so
    /// `O(N²)` in all, on the threads) or a dense product on short ones, and `(A_eff X) A_effᵀ`
    /// one dense product of which only the lower triangle is formed.
    pub fn covariance_step(
        &self,
        model: &Model,
        x: &[f64],
        out: &mut [f64],
        scratch: &mut CovarianceScratch,
    ) {
        let size = self.a_eff.dense.nrows();
        scratch.a_x.resize(size * size, 0.0);
        let a_x = &mut scratch.a_x;
        if self.a_eff.rows.is_some() || size < CHAIN_SOLVE_MIN_STATES {
            self.a_eff.times_symmetric(x, a_x, &mut scratch.x_at);
        } else {
            let threads = rayon::current_num_threads();
            scratch
                .chains
                .resize_with(threads, LiftedWorkspace::default);
            let chunk = size.div_ceil(threads) * size;
            a_x.par_chunks_mut(chunk)
                .zip(x.par_chunks(chunk))
                .zip(scratch.chains.par_iter_mut())
                .for_each(|((out, x), ws)| {
                    for (out, x) in out.chunks_exact_mut(size).zip(x.chunks_exact(size)) {
                        apply_a_eff(model, self.t, &self.solver, x, out, ws);
                    }
                });
        }
        out.copy_from_slice(self.q_big.as_slice());
        self.a_eff.add_symmetric_product(a_x, out);
    }

    /// Makes `self` the lifted system of time `t`, rebuilding only in a new window.
    pub fn prepare(&mut self, model: &Model, t: usize) -> Result<()> {
        if model.window_index(t) != self.window {
            *self = Self::new(model, t)?;
        }
        Ok(())
    }
}

/// The exact first and second moments of the lifted state (docs/theory.md §4 `lifted`, §3):
/// `m⁺ = A_eff m + U_eff U`, `P⁺ = A_eff P A_effᵀ + Q_big`, `S_ii = P_ii + m_i m_iᵀ`.
#[derive(Debug, Clone)]
pub struct LiftedMoments {
    pub mean: DVector<f64>,
    pub cov: DMatrix<f64>,
    /// The next covariance, and the scratch of its step.
    next: DMatrix<f64>,
    scratch: CovarianceScratch,
    mean_scratch: DVector<f64>,
}

impl LiftedMoments {
    /// `m(1) = [m0_1; …; m0_N]`, `P(1) = blkdiag(P0_1, …, P0_N)`.
    pub fn initial(model: &Model) -> Self {
        let (n, big_n) = (model.dims.n, model.subsystems);
        let mean = DVector::from_vec(model.initial.means());
        let mut cov = DMatrix::zeros(big_n * n, big_n * n);
        for i in 0..big_n {
            cov.view_mut((i * n, i * n), (n, n))
                .copy_from(&model.initial.of(i).cov);
        }
        Self {
            next: DMatrix::zeros(big_n * n, big_n * n),
            scratch: CovarianceScratch::default(),
            mean_scratch: DVector::zeros(big_n * n),
            mean,
            cov,
        }
    }

    /// `S_ii = P_ii + m_i m_iᵀ` into `out` (`n × n`, column-major).
    pub fn second_moment(&self, i: usize, n: usize, out: &mut [f64]) {
        let mut out = nalgebra::DMatrixViewMut::from_slice(out, n, n);
        out.copy_from(&self.cov.view((i * n, i * n), (n, n)));
        let mi = self.mean.rows(i * n, n);
        out.ger(1.0, &mi, &mi, 1.0);
    }

    /// One step of the moment recursion with inputs `u` (`N·m` values).
    pub fn propagate(&mut self, model: &Model, sys: &LiftedSystem, u: &[f64]) {
        self.mean_scratch
            .gemv(1.0, &sys.a_eff.dense, &self.mean, 0.0);
        let u = nalgebra::DVectorView::from_slice(u, u.len());
        self.mean_scratch.gemv(1.0, &sys.u_eff, &u, 1.0);
        std::mem::swap(&mut self.mean, &mut self.mean_scratch);
        sys.covariance_step(
            model,
            self.cov.as_slice(),
            self.next.as_mut_slice(),
            &mut self.scratch,
        );
        std::mem::swap(&mut self.cov, &mut self.next);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::interconnect::test_support::{banded_model, random_model};

    /// The covariance step through a chain solve per column (450 lifted states, `G` varying
    /// along the chain, so `A_eff` is dense), through the dense product (20 states) and
    /// through `A_eff`'s row envelope (`G = 0`: 40 and 300 lifted states, the latter split
    /// over the threads) against `A_eff X A_effᵀ + Q_big` formed here with nalgebra, on a
    /// symmetric `X`.
    #[test]
    fn covariance_step_is_the_dense_congruence() {
        let cases = [
            (random_model(20, 1, 2, 5, true, 0.0), false),
            (random_model(450, 1, 2, 5, true, 0.0), false),
            (banded_model(20), true),
            (banded_model(150), true),
        ];
        for (model, narrow) in cases {
            let n_sub = model.subsystems;
            let sys = LiftedSystem::new(&model, 3).unwrap();
            assert_eq!(sys.a_eff.rows.is_some(), narrow, "N = {n_sub}");
            let size = sys.a_eff.dense.nrows();
            let f = DMatrix::from_fn(size, size, |r, c| ((r * 31 + c * 17) as f64 * 0.37).sin());
            let x = &f * f.transpose();
            let q = DMatrix::from_fn(size, size, |r, c| if r == c { 0.5 } else { 0.0 });
            let sys = LiftedSystem {
                q_big: q.clone(),
                ..sys
            };
            let a = &sys.a_eff.dense;
            let expected = a * &x * a.transpose() + q;
            let mut out = vec![0.0; size * size];
            sys.covariance_step(
                &model,
                x.as_slice(),
                &mut out,
                &mut CovarianceScratch::default(),
            );
            let out = DMatrix::from_column_slice(size, size, &out);
            let scale = expected.amax();
            assert!((&out - &expected).amax() < 1e-12 * scale, "N = {n_sub}");
            assert_eq!(out, out.transpose(), "N = {n_sub}");
        }
    }
}
