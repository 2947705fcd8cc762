//! One subsystem's measurement information for the joint filter's update (docs/theory.md
//! §8 update step 2): `Φ = Hᵀ R⁻¹ H`, `r = Hᵀ R⁻¹ ỹ`, and the measurement's log density.

use nalgebra::{Cholesky, DMatrix, DVector};

use crate::filter::nahi;
use crate::model::Params;

/// Dense scratch of one subsystem's measurement information (update step 2).
pub(super) struct InfoWorkspace {
    h: DMatrix<f64>,
    h_tr: DMatrix<f64>,
    js: DMatrix<f64>,
    reff: DMatrix<f64>,
    /// `R⁻¹ H` of the last call (recorded by a schedule).
    pub(super) w: DMatrix<f64>,
    /// The second moment `S` to fill before [`InfoWorkspace::add`] (unknown dropouts).
    pub(super) s: DMatrix<f64>,
    innov: DVector<f64>,
    /// `L⁻¹ ỹ` with `R = L Lᵀ`, for the log density.
    white: DVector<f64>,
}

impl InfoWorkspace {
    pub(super) fn new(n: usize, q: usize) -> Self {
        Self {
            h: DMatrix::zeros(q, n),
            h_tr: DMatrix::zeros(n, q),
            js: DMatrix::zeros(q, n),
            reff: DMatrix::zeros(q, q),
            w: DMatrix::zeros(q, n),
            s: DMatrix::zeros(n, n),
            innov: DVector::zeros(q),
            white: DVector::zeros(q),
        }
    }

    /// Adds `Φ = Hᵀ R⁻¹ H` to `phi` (`n × n`) and writes `r = Hᵀ R⁻¹ ỹ`, with `H = p J`,
    /// `R = M + p(1−p) J S Jᵀ` (`S` in `self.s`, unknown dropouts) and `ỹ = y − R u − H x̂⁻`.
    /// A NaN element of `y` (not in the data, docs/theory.md §15) removes its row. Returns
    /// `log N(ỹ; 0, R)` over the rows kept, or `None` when `R` is not positive definite.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn add(
        &mut self,
        prm: &Params,
        p: f64,
        known: bool,
        y: &[f64],
        u: &[f64],
        x: &[f64],
        phi: &mut [f64],
        r: &mut [f64],
    ) -> Option<f64> {
        let (q, n) = self.h.shape();
        self.h.copy_from(&prm.J);
        self.h.scale_mut(p);
        self.reff.copy_from(&prm.M);
        if !known && p * (1.0 - p) != 0.0 {
            self.h_tr.tr_copy_from(&prm.J);
            self.js.gemm_tr(1.0, &self.h_tr, &self.s, 0.0);
            self.reff.gemm(p * (1.0 - p), &self.js, &self.h_tr, 1.0);
        }
        nahi::innovation(prm, p, y, u, x, self.innov.as_mut_slice());
        let mut dropped = 0;
        for k in nahi::missing_rows(y) {
            dropped += 1;
            self.h.row_mut(k).fill(0.0);
            nahi::remove_row(&mut self.reff, k);
            self.innov[k] = 0.0;
        }
        // W = R⁻¹ H by a Cholesky solve (allocation-free: the factor reuses `reff`).
        self.w.copy_from(&self.h);
        let reff = std::mem::replace(&mut self.reff, DMatrix::zeros(0, 0));
        let Some(chol) = Cholesky::new(reff) else {
            self.reff = DMatrix::zeros(q, q);
            return None;
        };
        chol.solve_mut(&mut self.w);
        self.reff = chol.unpack();
        self.white.copy_from(&self.innov);
        let log_density = nahi::received_log_density(&self.reff, &mut self.white, dropped);
        for c in 0..n {
            for rr in 0..n {
                let mut acc = 0.0;
                for k in 0..q {
                    acc += self.h[(k, rr)] * self.w[(k, c)];
                }
                phi[c * n + rr] += acc;
            }
            let mut acc = 0.0;
            for k in 0..q {
                acc += self.w[(k, c)] * self.innov[k];
            }
            r[c] = acc;
        }
        Some(log_density)
    }
}
