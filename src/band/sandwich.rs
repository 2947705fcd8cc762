//! SPEC §9 predict step 4: the band of `A P Aᵀ` for block-banded `A` and `P`.

use super::kernels::gemm_acc;
use super::products::sym_block;
use super::{GenBand, SymBand};

/// The strip `W = A P` on `|i − m| ≤ k + b`.
#[derive(Debug, Clone)]
pub struct SandwichWorkspace {
    /// Half-width of `W`.
    hw: usize,
    w: Vec<f64>,
}

impl SandwichWorkspace {
    pub fn new(nb: usize, bs: usize, b: usize, k: usize) -> Self {
        let hw = (k + b).min(nb.saturating_sub(1));
        Self {
            hw,
            w: vec![0.0; nb * (2 * hw + 1) * bs * bs],
        }
    }
}

/// `out = band_k(A P Aᵀ)` with `k = out.width()`, `A` of half-width `b` and `P` known on the
/// band of width `min(k + 2b, nb − 1)` (blocks beyond `p.width()` are taken as zero): forms
/// `W = A P` on `|i − m| ≤ k + b`, then `W Aᵀ` on the band. `O(nb (k + b) b bs³)`.
pub fn sandwich(a: &GenBand, p: &SymBand, out: &mut SymBand, ws: &mut SandwichWorkspace) {
    let (nb, bs, b, k) = (a.nb(), a.bs(), a.half_width(), out.width());
    let bb = bs * bs;
    let hw = ws.hw;
    debug_assert!(hw >= (k + b).min(nb - 1));
    let stride = (2 * hw + 1) * bb;
    ws.w.fill(0.0);
    for i in 0..nb {
        for m in i.saturating_sub(hw)..=(i + hw).min(nb - 1) {
            let wim = &mut ws.w[i * stride + (m + hw - i) * bb..][..bb];
            for l in i.saturating_sub(b)..=(i + b).min(nb - 1) {
                if let Some((plm, tr)) = sym_block(p, l, m) {
                    gemm_acc(wim, 1.0, a.block(i, l), false, plm, tr, bs);
                }
            }
        }
    }
    out.fill_zero();
    for i in 0..nb {
        for j in i..=(i + k).min(nb - 1) {
            let blk = out.block_mut(i, j - i);
            for m in j.saturating_sub(b)..=(j + b).min(nb - 1) {
                if m.abs_diff(i) > hw {
                    continue;
                }
                let wim = &ws.w[i * stride + (m + hw - i) * bb..][..bb];
                gemm_acc(blk, 1.0, wim, false, a.block(j, m), true, bs);
            }
        }
        let diag = out.block_mut(i, 0);
        for c in 0..bs {
            for r in 0..c {
                let v = 0.5 * (diag[r + c * bs] + diag[c + r * bs]);
                diag[r + c * bs] = v;
                diag[c + r * bs] = v;
            }
        }
    }
}
