//! SPEC §9 update step 3: the precision of the maximum-entropy completion of a band.

use super::{BandError, SymBand};

/// Preallocated buffers for [`completion_precision`]: one dense clique of `(k+1)·bs`.
#[allow(dead_code)] // stub commit: the fields are used once the bodies land
#[derive(Debug, Clone)]
pub struct CompletionWorkspace {
    nb: usize,
    bs: usize,
    k: usize,
    /// Cholesky factor of the current clique, column-major `(k+1)bs × (k+1)bs`.
    chol: Vec<f64>,
    /// Rows of the clique factor's inverse, `(k+1)bs × (k+1)bs`.
    rows: Vec<f64>,
}

impl CompletionWorkspace {
    /// Buffers for `nb` blocks of size `bs` and bandwidth `k` (clamped to `nb − 1`).
    pub fn new(nb: usize, bs: usize, k: usize) -> Self {
        let k = k.min(nb.saturating_sub(1));
        let m = (k + 1) * bs;
        Self {
            nb,
            bs,
            k,
            chol: vec![0.0; m * m],
            rows: vec![0.0; m * m],
        }
    }
}

/// SPEC §9 update step 3: the precision `Λ` of the maximum-entropy completion of the band
/// `|i − j| ≤ k` of `p` (`p.width() ≥ k`, `k` clamped to `nb − 1`):
/// `Λ = Σ_j pad(P_{C_j C_j}⁻¹) − Σ_j pad(P_{S_j S_j}⁻¹)` with cliques `C_j = {j, …, j+k}`,
/// `j = 0..nb−k`, and separators `S_j = {j+1, …, j+k}`. `out` has width `k`.
/// `k = 0`: `Λ_ii = P_ii⁻¹`; `k = nb − 1`: `Λ = P⁻¹` (one clique).
pub fn completion_precision(
    p: &SymBand,
    k: usize,
    out: &mut SymBand,
    ws: &mut CompletionWorkspace,
) -> Result<(), BandError> {
    let _ = (p, k, out, ws);
    unimplemented!()
}
