//! The diagonal loading of the joint filter's covariance band (docs/theory.md §8 "Loading").

use crate::linalg::band::SymBand;
use crate::model::Model;

/// How far below the variance one reading resolves the loading's floor lies.
const FLOOR_SCALE: f64 = 1e-100;

/// The diagonal loading of docs/theory.md §8 "Loading": `P_ii += ε max(tr P_ii / n, σ²_f) I`
/// on every diagonal block, with the floor `σ²_f` of [`Loading::floor_of`], so that a block
/// whose variance is zero (a state known exactly) or has decayed to nothing still gets one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Loading {
    pub eps: f64,
    pub floor: f64,
}

impl Loading {
    /// The loading `eps` on `model`.
    pub fn new(model: &Model, eps: f64) -> Self {
        Self {
            eps,
            floor: Self::floor_of(model),
        }
    }

    /// `σ²_f = 10⁻¹⁰⁰ min tr M / tr(Jᵀ J)` over the parameter sets that measure anything:
    /// the variance of a state element as one reading resolves it, scaled far below any
    /// variance that matters and far above where products of two variances underflow (0 when
    /// nothing is measured).
    pub fn floor_of(model: &Model) -> f64 {
        let floor = model
            .param_sets()
            .iter()
            .filter_map(|p| {
                let resolved = p.J.norm_squared();
                (resolved > 0.0).then(|| p.M.trace() / resolved)
            })
            .fold(f64::INFINITY, f64::min);
        if floor.is_finite() {
            FLOOR_SCALE * floor
        } else {
            0.0
        }
    }

    /// Loads every diagonal block of `p`.
    pub fn apply(&self, p: &mut SymBand) {
        if self.eps == 0.0 {
            return;
        }
        let n = p.bs();
        for i in 0..p.nb() {
            let b = p.block_mut(i, 0);
            let trace: f64 = (0..n).map(|c| b[c * n + c]).sum();
            let added = self.eps * (trace / n as f64).max(self.floor);
            for c in 0..n {
                b[c * n + c] += added;
            }
        }
    }
}
