//! The paper's step-1 solver, `transfer`: the transfer-matrix recursion (P6)–(P19), as
//! corrected in docs/theory.md §6. Kept to reproduce the paper; it needs every interior `G22(k)`
//! invertible and its error grows like `ε ‖φ(N−1)…φ(2)‖`, exponentially in `N`.
//!
//! With `X(k) = [w⁺(k); v⁻(k)] = [a(k); b(k)]`, eliminating `b(k)` from the link equations
//! gives, for `k = 2..N−1`,
//!
//! ```text
//! X(k) = φ(k) X(k−1) + β(k),
//! φ(k) = [ G11 − G12 G22⁻¹ G21   G12 G22⁻¹ ]     β(k) = [ z⁺(k) − G12 G22⁻¹ z⁻(k) ]
//!        [ −G22⁻¹ G21            G22⁻¹     ],            [ −G22⁻¹ z⁻(k)           ]
//! ```
//!
//! (all `G` blocks of subsystem `k`), started from (P17) `X(1) = [G12(1); I] v⁻(1) + [z⁺(1); 0]`
//! and closed by `v⁻(N) = 0`: with `MT = φ(N−1)…φ(2)`, `MC = Σ_{i=2}^{N−1} φ(N−1)…φ(i+1) β(i)`,
//! (P16) `v⁻(1) = K⁻¹ { [−G21(N), I] (MC + MT [z⁺(1); 0]) − z⁻(N) }`,
//! `K = [G21(N), −I] MT [G12(1); I]`. For `N = 2` the products are empty (`MT = I`,
//! `MC = 0`), which gives docs/theory.md §6's `N = 2` formula.

use nalgebra::{DMatrix, DVector, LU};

use crate::error::{Error, Result};
use crate::linalg::mat_vec_add;
use crate::model::Model;

/// `sisfilt` warns when the transfer solver's estimated relative error exceeds this.
pub const TRANSFER_ERROR_WARNING: f64 = 1e-8;

/// The factorised transfer recursion for one set of `G`s.
#[derive(Debug, Clone)]
pub struct TransferSolver {
    plus: usize,
    minus: usize,
    subsystems: usize,
    window: usize,
    g_built: Vec<f64>,
    /// `φ(k)` for `k = 2..N−1` at index `k − 2`.
    phi: Vec<DMatrix<f64>>,
    /// `E(k) = [−G12 G22⁻¹; −G22⁻¹]`, so that `β(k) = [z⁺(k); 0] + E(k) z⁻(k)`.
    e: Vec<DMatrix<f64>>,
    mt: DMatrix<f64>,
    k_lu: Option<LU<f64, nalgebra::Dyn, nalgebra::Dyn>>,
    g12_first: DMatrix<f64>,
    g21_last: DMatrix<f64>,
    error_estimate: f64,
    /// `X(k)`, `k = 1..N−1`, `s` values each.
    x: Vec<f64>,
    c: Vec<f64>,
    c_next: Vec<f64>,
    b1: DVector<f64>,
}

fn one_norm(m: &DMatrix<f64>) -> f64 {
    (0..m.ncols())
        .map(|c| m.column(c).iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max)
}

impl TransferSolver {
    /// Builds the recursion for the `G`s at time `t`.
    pub fn new(model: &Model, t: usize) -> Result<Self> {
        let d = model.dims;
        let s = d.s();
        let mut solver = Self {
            plus: d.plus,
            minus: d.minus,
            subsystems: model.subsystems,
            window: model.window_index(t),
            g_built: Vec::new(),
            phi: Vec::new(),
            e: Vec::new(),
            mt: DMatrix::identity(s, s),
            k_lu: None,
            g12_first: DMatrix::zeros(d.plus, d.minus),
            g21_last: DMatrix::zeros(d.minus, d.plus),
            error_estimate: 0.0,
            x: vec![0.0; model.subsystems.saturating_sub(1) * s],
            c: vec![0.0; s],
            c_next: vec![0.0; s],
            b1: DVector::zeros(d.minus),
        };
        solver.build(model, t)?;
        Ok(solver)
    }

    /// Makes the recursion valid for time `t`; rebuilds only when some `G` changed.
    pub fn prepare(&mut self, model: &Model, t: usize) -> Result<()> {
        let window = model.window_index(t);
        if window != self.window {
            self.window = window;
            let g_now: Vec<f64> = model
                .window(t)
                .ids
                .iter()
                .flat_map(|&id| model.param_set(id).G.as_slice().iter().copied())
                .collect();
            if g_now != self.g_built {
                self.build(model, t)?;
            }
        }
        Ok(())
    }

    fn build(&mut self, model: &Model, t: usize) -> Result<()> {
        let (p, m, n_sub) = (self.plus, self.minus, self.subsystems);
        let s = p + m;
        self.g_built = model
            .window(t)
            .ids
            .iter()
            .flat_map(|&id| model.param_set(id).G.as_slice().iter().copied())
            .collect();
        self.phi.clear();
        self.e.clear();
        self.mt = DMatrix::identity(s, s);
        self.k_lu = None;
        if n_sub < 2 || s == 0 {
            return Ok(());
        }
        let mut growth = 1.0f64;
        for k in 2..n_sub {
            let g = &model.params(t, k).G;
            let g11 = g.view((0, 0), (p, p));
            let g12 = g.view((0, p), (p, m));
            let g21 = g.view((p, 0), (m, p));
            let g22 = g.view((p, p), (m, m)).into_owned();
            let g22_inv = g22
                .clone()
                .try_inverse()
                .filter(|inv| inv.iter().all(|v| v.is_finite()))
                .ok_or_else(|| Error::TransferSolver {
                    file: model.name.clone(),
                    t,
                    subsystem: k,
                })?;
            let g12_g22inv = g12 * &g22_inv;
            let mut phi = DMatrix::zeros(s, s);
            phi.view_mut((0, 0), (p, p))
                .copy_from(&(g11 - &g12_g22inv * g21));
            phi.view_mut((0, p), (p, m)).copy_from(&g12_g22inv);
            phi.view_mut((p, 0), (m, p)).copy_from(&(-&g22_inv * g21));
            phi.view_mut((p, p), (m, m)).copy_from(&g22_inv);
            let mut e = DMatrix::zeros(s, m);
            e.view_mut((0, 0), (p, m)).copy_from(&(-g12_g22inv));
            e.view_mut((p, 0), (m, m)).copy_from(&(-g22_inv));
            self.mt = &phi * &self.mt;
            growth = growth.max(one_norm(&self.mt));
            self.phi.push(phi);
            self.e.push(e);
        }
        let g_first = &model.params(t, 1).G;
        let g_last = &model.params(t, n_sub).G;
        self.g12_first = g_first.view((0, p), (p, m)).into_owned();
        self.g21_last = g_last.view((p, 0), (m, p)).into_owned();
        // K = [G21(N), −I] MT [G12(1); I]
        let mut left = DMatrix::zeros(m, s);
        left.view_mut((0, 0), (m, p)).copy_from(&self.g21_last);
        left.view_mut((0, p), (m, m)).fill_with_identity();
        left.view_mut((0, p), (m, m)).neg_mut();
        let mut right = DMatrix::zeros(s, m);
        right.view_mut((0, 0), (p, m)).copy_from(&self.g12_first);
        right.view_mut((p, 0), (m, m)).fill_with_identity();
        let k_mat = &left * &self.mt * &right;
        let k_inv_norm = k_mat
            .clone()
            .try_inverse()
            .map(|inv| one_norm(&inv))
            .filter(|v| v.is_finite())
            .ok_or_else(|| Error::IllPosed {
                file: model.name.clone(),
                t,
                msg: "the matrix K of (P16) is singular: the interconnection equations have no unique solution"
                    .into(),
            })?;
        // With minus = 0 there is no v⁻ to close the recursion with: K is 0 × 0, and
        // nalgebra's LU solve cannot take an empty system.
        self.k_lu = (m > 0).then(|| k_mat.lu());
        // Rounding errors of size ε are amplified by the transfer products and by K⁻¹ (docs/theory.md §2).
        // Against the banded solve on random chains (G entries ≤ 0.3, N = 3..50) this tracked
        // the actual relative error within a factor 1–20 (e.g. 3e−2 for 1.2e−2 at N = 20).
        self.error_estimate = f64::EPSILON * growth * k_inv_norm.max(1.0);
        Ok(())
    }

    /// Estimated relative error of the solutions (docs/theory.md §2: `ε ‖Π φ‖`, times the closing
    /// solve's amplification).
    pub fn error_estimate(&self) -> f64 {
        self.error_estimate
    }

    /// `β(k) = [z⁺(k); 0] + E(k) z⁻(k)` into `out`.
    fn beta(&self, k: usize, z: &[f64], out: &mut [f64]) {
        let (p, s) = (self.plus, self.plus + self.minus);
        let zk = &z[(k - 1) * s..k * s];
        out.fill(0.0);
        out[..p].copy_from_slice(&zk[..p]);
        mat_vec_add(out, &self.e[k - 2], &zk[p..]);
    }

    /// Solves (P2)–(P4) for `v` from `z` (both `N · s` values).
    pub fn solve(&mut self, z: &[f64], v: &mut [f64]) {
        let (p, m, n_sub) = (self.plus, self.minus, self.subsystems);
        let s = p + m;
        v.fill(0.0);
        if n_sub < 2 || s == 0 {
            return;
        }
        // MC by Horner: C(k) = φ(k) C(k−1) + β(k); then w = MT [z⁺(1); 0] + MC.
        let mut c = std::mem::take(&mut self.c);
        let mut w = std::mem::take(&mut self.c_next);
        c.fill(0.0);
        for k in 2..n_sub {
            self.beta(k, z, &mut w);
            mat_vec_add(&mut w, &self.phi[k - 2], &c);
            std::mem::swap(&mut c, &mut w);
        }
        w.copy_from_slice(&c);
        for col in 0..p {
            for r in 0..s {
                w[r] += self.mt[(r, col)] * z[col];
            }
        }
        // rhs = [−G21(N), I] w − z⁻(N)
        let zn_minus = &z[(n_sub - 1) * s + p..n_sub * s];
        for r in 0..m {
            let mut acc = w[p + r] - zn_minus[r];
            for col in 0..p {
                acc -= self.g21_last[(r, col)] * w[col];
            }
            self.b1[r] = acc;
        }
        if let Some(lu) = &self.k_lu {
            lu.solve_mut(&mut self.b1);
        }
        // X(1) = [G12(1) b(1) + z⁺(1); b(1)], then forward.
        let x1 = &mut self.x[..s];
        x1[..p].copy_from_slice(&z[..p]);
        mat_vec_add(&mut x1[..p], &self.g12_first, self.b1.as_slice());
        x1[p..].copy_from_slice(self.b1.as_slice());
        for k in 2..n_sub {
            self.beta(k, z, &mut w);
            let (done, rest) = self.x.split_at_mut((k - 1) * s);
            let xk = &mut rest[..s];
            xk.copy_from_slice(&w);
            mat_vec_add(xk, &self.phi[k - 2], &done[(k - 2) * s..]);
        }
        for k in 1..n_sub {
            let xk = &self.x[(k - 1) * s..k * s];
            v[k * s..k * s + p].copy_from_slice(&xk[..p]); // v⁺(k+1) = a(k)
            v[(k - 1) * s + p..k * s].copy_from_slice(&xk[p..]); // v⁻(k) = b(k)
        }
        self.c = c;
        self.c_next = w;
    }
}
