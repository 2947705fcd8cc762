//! The lifted system of SPEC §5: the whole chain as one linear system
//! `X⁺ = A_eff X + U_eff U + Ω`, with `A_eff = blkdiag(A) + blkdiag(B) L_x`, where
//! `V = L_x X + L_u U` is the interconnection solve of SPEC §2.

use nalgebra::{DMatrix, DVector};

use crate::error::Result;
use crate::interconnect::ChainSolver;
use crate::linalg::mat_vec_add;
use crate::model::Model;

/// Largest `N · n` for which [`spectral_radius`] computes all eigenvalues of a dense `A_eff`;
/// above it, it estimates by power iteration.
pub const EXACT_SPECTRUM_MAX: usize = 1200;

/// Scratch for [`apply_a_eff`].
#[derive(Debug, Default, Clone)]
pub struct LiftedWorkspace {
    z: Vec<f64>,
    v: Vec<f64>,
    rhs: Vec<f64>,
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
    let (n, s, big_n) = (model.dims.n, model.dims.s(), model.subsystems);
    ws.z.clear();
    ws.z.resize(big_n * s, 0.0);
    ws.v.resize(big_n * s, 0.0);
    let window = model.window(t);
    for i in 0..big_n {
        let p = model.param_set(window.ids[i]);
        mat_vec_add(&mut ws.z[i * s..(i + 1) * s], &p.D, &x[i * n..(i + 1) * n]);
    }
    solver.solve(&ws.z, &mut ws.v, &mut ws.rhs);
    out.iter_mut().for_each(|o| *o = 0.0);
    for i in 0..big_n {
        let p = model.param_set(window.ids[i]);
        let oi = &mut out[i * n..(i + 1) * n];
        mat_vec_add(oi, &p.A, &x[i * n..(i + 1) * n]);
        mat_vec_add(oi, &p.B, &ws.v[i * s..(i + 1) * s]);
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

/// The spectral radius of `A_eff` over a time window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpectralRadius {
    pub value: f64,
    /// True when computed from all eigenvalues, false for a power-iteration estimate.
    pub exact: bool,
}

/// Spectral radius of `A_eff(t)`: exact (all eigenvalues of the dense matrix) for
/// `N n ≤ EXACT_SPECTRUM_MAX`, else a power-iteration estimate
/// `ρ ≈ (‖A^K x‖ / ‖A^{K/2} x‖)^{2/K}` from a fixed start vector, `K = power_steps`.
pub fn spectral_radius(model: &Model, t: usize, power_steps: usize) -> Result<SpectralRadius> {
    let solver = ChainSolver::new(model, t)?;
    let size = model.subsystems * model.dims.n;
    if size <= EXACT_SPECTRUM_MAX {
        let a = a_eff_dense(model, t, &solver);
        // nalgebra's Schur iteration can stall on the clustered spectra of long chains;
        // faer's eigenvalue solver uses exceptional shifts and does not.
        let a = faer::Mat::from_fn(size, size, |r, c| a[(r, c)]);
        if let Ok(eigenvalues) = a.eigenvalues() {
            let value = eigenvalues.iter().map(|l| l.norm()).fold(0.0, f64::max);
            return Ok(SpectralRadius { value, exact: true });
        }
    }
    let k_steps = power_steps.max(2);
    let mut x: Vec<f64> = (0..size)
        .map(|k| 1.0 + 0.5 * ((k as f64) * 0.618_033_988_75).fract())
        .collect();
    let mut y = vec![0.0; size];
    let mut ws = LiftedWorkspace::default();
    let mut log_norm = 0.0; // log ‖A^k x₀‖ − log ‖x₀‖, accumulated
    let mut log_half = 0.0;
    for k in 1..=k_steps {
        apply_a_eff(model, t, &solver, &x, &mut y, &mut ws);
        let norm = y.iter().map(|v| v * v).sum::<f64>().sqrt();
        let prev = x.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm == 0.0 {
            return Ok(SpectralRadius {
                value: 0.0,
                exact: false,
            });
        }
        log_norm += (norm / prev).ln();
        for (xi, yi) in x.iter_mut().zip(&y) {
            *xi = yi / norm;
        }
        if k == k_steps / 2 {
            log_half = log_norm;
        }
    }
    Ok(SpectralRadius {
        value: ((log_norm - log_half) / (k_steps - k_steps / 2) as f64).exp(),
        exact: false,
    })
}

/// The dense lifted matrices of SPEC §5 at one time: `X⁺ = A_eff X + U_eff U + Ω`,
/// `Ω ~ N(0, Q_big)`. `O((Nn)²)` memory: for reference filters on moderate chains.
#[derive(Debug, Clone)]
pub struct LiftedSystem {
    /// `A_eff = blkdiag(A) + blkdiag(B) L_x`.
    pub a_eff: DMatrix<f64>,
    /// `A_effᵀ`, kept for `X A_effᵀ` products (nalgebra's `gemm` has no `A Bᵀ` form).
    pub a_eff_tr: DMatrix<f64>,
    /// `U_eff = blkdiag(C) + blkdiag(B) L_u`.
    pub u_eff: DMatrix<f64>,
    /// `blkdiag(Q)`.
    pub q_big: DMatrix<f64>,
    /// The window these matrices belong to.
    pub window: usize,
}

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
            a_eff_tr: a_eff.transpose(),
            a_eff,
            u_eff,
            q_big,
            window: model.window_index(t),
        })
    }

    /// Makes `self` the lifted system of time `t`, rebuilding only in a new window.
    pub fn prepare(&mut self, model: &Model, t: usize) -> Result<()> {
        if model.window_index(t) != self.window {
            *self = Self::new(model, t)?;
        }
        Ok(())
    }
}

/// The exact first and second moments of the lifted state (SPEC §3 `lifted`, §5):
/// `m⁺ = A_eff m + U_eff U`, `P⁺ = A_eff P A_effᵀ + Q_big`, `S_ii = P_ii + m_i m_iᵀ`.
#[derive(Debug, Clone)]
pub struct LiftedMoments {
    pub mean: DVector<f64>,
    pub cov: DMatrix<f64>,
    scratch: DMatrix<f64>,
    mean_scratch: DVector<f64>,
}

impl LiftedMoments {
    /// `m(1) = [m0; …; m0]`, `P(1) = blkdiag(P0)`.
    pub fn initial(model: &Model) -> Self {
        let (n, big_n) = (model.dims.n, model.subsystems);
        let mean = DVector::from_fn(big_n * n, |r, _| model.initial_mean[r % n]);
        let mut cov = DMatrix::zeros(big_n * n, big_n * n);
        for i in 0..big_n {
            cov.view_mut((i * n, i * n), (n, n))
                .copy_from(&model.initial_cov);
        }
        Self {
            scratch: DMatrix::zeros(big_n * n, big_n * n),
            mean_scratch: DVector::zeros(big_n * n),
            mean,
            cov,
        }
    }

    /// `S_ii = P_ii + m_i m_iᵀ` into `out` (`n × n`).
    pub fn second_moment(&self, i: usize, n: usize, out: &mut DMatrix<f64>) {
        out.copy_from(&self.cov.view((i * n, i * n), (n, n)));
        let mi = self.mean.rows(i * n, n);
        out.ger(1.0, &mi, &mi, 1.0);
    }

    /// One step of the moment recursion with inputs `u` (`N·m` values).
    pub fn propagate(&mut self, sys: &LiftedSystem, u: &[f64]) {
        self.mean_scratch.gemv(1.0, &sys.a_eff, &self.mean, 0.0);
        let u = nalgebra::DVectorView::from_slice(u, u.len());
        self.mean_scratch.gemv(1.0, &sys.u_eff, &u, 1.0);
        std::mem::swap(&mut self.mean, &mut self.mean_scratch);
        self.scratch.gemm(1.0, &sys.a_eff, &self.cov, 0.0);
        self.cov.copy_from(&sys.q_big);
        self.cov.gemm(1.0, &self.scratch, &sys.a_eff_tr, 1.0);
    }
}
