//! SPEC §9 update step 3: the precision of the maximum-entropy completion of a band.

use super::kernels::spd_inverse;
use super::{BandError, SymBand};

/// Dense scratch for one clique of `(k + 1)` blocks.
#[derive(Debug, Clone)]
pub struct CompletionWorkspace {
    dense: Vec<f64>,
    scratch: Vec<f64>,
}

impl CompletionWorkspace {
    pub fn new(nb: usize, bs: usize, k: usize) -> Self {
        let m = (k.min(nb.saturating_sub(1)) + 1) * bs;
        Self {
            dense: vec![0.0; m * m],
            scratch: vec![0.0; m * m],
        }
    }
}

/// The precision `Λ` of the maximum-entropy (Gauss–Markov) completion of the band
/// `|i − j| ≤ k` of `p` (`p.width() ≥ k`), by the clique/separator formula
/// `Λ = Σ_j pad(P_{C_j C_j}⁻¹) − Σ_j pad(P_{S_j S_j}⁻¹)` with cliques `C_j = {j, …, j+k}` and
/// separators `S_j = C_j ∩ C_{j+1}`. `Λ` is block-banded with bandwidth `k` and its inverse
/// agrees with `p` on the band. `k = 0` gives `Λ_ii = P_ii⁻¹`; `k = nb − 1`, `Λ = P⁻¹`.
/// `out` (width `k`) is overwritten.
pub fn completion_precision(
    p: &SymBand,
    k: usize,
    out: &mut SymBand,
    ws: &mut CompletionWorkspace,
) -> Result<(), BandError> {
    let nb = p.nb();
    let k = k.min(nb.saturating_sub(1));
    debug_assert!(p.width() >= k && out.width() == k);
    out.fill_zero();
    for first in 0..nb - k {
        add_clique_inverse(p, first, k + 1, 1.0, out, ws)?;
        if k > 0 && first + 1 < nb - k {
            add_clique_inverse(p, first + 1, k, -1.0, out, ws)?;
        }
    }
    Ok(())
}

/// `out += sign · pad(P_{C C}⁻¹)` for the clique `C = {first, …, first + size − 1}`.
fn add_clique_inverse(
    p: &SymBand,
    first: usize,
    size: usize,
    sign: f64,
    out: &mut SymBand,
    ws: &mut CompletionWorkspace,
) -> Result<(), BandError> {
    let bs = p.bs();
    let m = size * bs;
    let dense = &mut ws.dense[..m * m];
    for a in 0..size {
        for b in a..size {
            let blk = p.block(first + a, b - a);
            for c in 0..bs {
                for r in 0..bs {
                    let v = blk[r + c * bs];
                    dense[(a * bs + r) + (b * bs + c) * m] = v;
                    dense[(b * bs + c) + (a * bs + r) * m] = v;
                }
            }
        }
    }
    if !spd_inverse(dense, m, &mut ws.scratch) {
        return Err(BandError::CliqueNotPositiveDefinite {
            first,
            last: first + size - 1,
        });
    }
    for a in 0..size {
        for b in a..size {
            let blk = out.block_mut(first + a, b - a);
            for c in 0..bs {
                for r in 0..bs {
                    blk[r + c * bs] += sign * dense[(a * bs + r) + (b * bs + c) * m];
                }
            }
        }
    }
    Ok(())
}
