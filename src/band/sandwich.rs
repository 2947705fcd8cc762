//! SPEC §9 predict step 4: the band of `A P Aᵀ` for block-banded `A` and `P`.

use super::kernels::{nt_acc_fast, simd_available, symmetrise};
use super::{GenBand, SymBand};

/// Preallocated buffers for [`sandwich`]: a ring of full block rows of `P` and one block
/// row of `W = A P`.
#[derive(Debug, Clone)]
pub struct SandwichWorkspace {
    nb: usize,
    bs: usize,
    b: usize,
    k: usize,
    /// Width of `P` that enters: `min(k + 2b, nb − 1)`.
    wp: usize,
    /// Ring of `k + 2b + 1` full block rows of `P`: row `m` at slot `m mod ring`, the strip
    /// `[P_{m,m−wp} … P_{m,m+wp}]` of `bs × (2wp+1)·bs` (zero outside the matrix).
    rows: Vec<f64>,
    ring: usize,
    /// Block row `i` of `W = A P`, blocks `m = i−b..=i+b+k` at `(m + b − i) bs²`.
    w_row: Vec<f64>,
}

impl SandwichWorkspace {
    /// Buffers for `nb` blocks of size `bs`, `A` of half-width `b` and output width `k`
    /// (both clamped to `nb − 1`).
    pub fn new(nb: usize, bs: usize, b: usize, k: usize) -> Self {
        let top = nb.saturating_sub(1);
        let (b, k) = (b.min(top), k.min(top));
        let wp = (k + 2 * b).min(top);
        let ring = (k + 2 * b + 1).min(nb.max(1));
        let bb = bs * bs;
        Self {
            nb,
            bs,
            b,
            k,
            wp,
            rows: vec![0.0; ring * (2 * wp + 1) * bb],
            ring,
            w_row: vec![0.0; (k + 2 * b + 1) * bb],
        }
    }
}

/// SPEC §9 predict step 4: `out = band_k(A P Aᵀ)`, `k = out.width()`, for `A` of half-width
/// `b` and symmetric `P` of width `≥ min(k + 2b, nb − 1)` (only that band of `P` enters):
///
/// `W_{i,m} = Σ_{l=i−b}^{i+b} A_{i,l} P_{l,m}` for `m = i−b..=i+b+k`, then
/// `out_{i,j} = Σ_{m=j−b}^{j+b} W_{i,m} A_{j,m}ᵀ` for `j = i..=i+k` (diagonal symmetrised).
///
/// Both are products of two block-row strips (`W_{i,m} = A_{i,·} (P_{m,·})ᵀ` over the
/// columns `l`), so each block is one contiguous dot-product kernel. Block row `m` of `P` is
/// assembled in full (`P_{m,l} = P_{l,m}ᵀ` for `l < m`) once, into a ring buffer of the
/// `k + 2b + 1` rows in use. Cost `≈ 2 bs³ (2b+1)(k+2b+2)` per block row. The caller adds `Q`.
pub fn sandwich(a: &GenBand, p: &SymBand, out: &mut SymBand, ws: &mut SandwichWorkspace) {
    let (nb, bs, b, k, wp) = (ws.nb, ws.bs, ws.b, ws.k, ws.wp);
    assert_eq!((a.nb(), a.bs(), a.half_width()), (nb, bs, b), "A shape");
    assert_eq!((out.nb(), out.bs(), out.width()), (nb, bs, k), "out shape");
    assert_eq!((p.nb(), p.bs()), (nb, bs), "P shape");
    assert!(
        p.width() >= wp,
        "the band of P is narrower than min(k + 2b, nb − 1)"
    );
    let bb = bs * bs;
    let row_len = (2 * wp + 1) * bb;
    let simd = simd_available();
    let mut next_row = 0; // first row of P not yet in the ring
    for i in 0..nb {
        let m_lo = i.saturating_sub(b);
        let m_hi = (i + b + k).min(nb - 1);
        while next_row <= m_hi {
            let slot = next_row % ws.ring;
            full_row(
                p,
                next_row,
                wp,
                &mut ws.rows[slot * row_len..(slot + 1) * row_len],
            );
            next_row += 1;
        }
        // W_{i,m} = A_{i,·} (P_{m,·})ᵀ over l = l_lo..=l_hi.
        let (l_lo, l_hi) = (i.saturating_sub(b), (i + b).min(nb - 1));
        let ncols = (l_hi + 1 - l_lo) * bb;
        let a_row = &a.row_strip(i)[(l_lo + b - i) * bb..][..ncols];
        ws.w_row.fill(0.0);
        for m in m_lo..=m_hi {
            let slot = m % ws.ring;
            let p_row = &ws.rows[slot * row_len..(slot + 1) * row_len];
            let p_cols = &p_row[(l_lo + wp - m) * bb..][..ncols];
            let w_im = &mut ws.w_row[(m + b - i) * bb..(m + b - i + 1) * bb];
            nt_acc_fast(simd, bs, w_im, a_row, p_cols, 1.0);
        }
        // out_{i,j} = W_{i,·} (A_{j,·})ᵀ over m = j−b..=j+b.
        let out_row = out.row_strip_mut(i);
        for j in i..=(i + k).min(nb - 1) {
            let (lo, hi) = (j.saturating_sub(b), (j + b).min(nb - 1));
            let n = (hi + 1 - lo) * bb;
            let w_cols = &ws.w_row[(lo + b - i) * bb..][..n];
            let a_cols = &a.row_strip(j)[(lo + b - j) * bb..][..n];
            let o = &mut out_row[(j - i) * bb..(j - i + 1) * bb];
            o.fill(0.0);
            nt_acc_fast(simd, bs, o, w_cols, a_cols, 1.0);
        }
        symmetrise(bs, &mut out_row[..bb]);
    }
}

/// Block row `m` of the symmetric `P` in full: `dst` = `[P_{m,m−wp} … P_{m,m+wp}]`, zero
/// outside the matrix.
fn full_row(p: &SymBand, m: usize, wp: usize, dst: &mut [f64]) {
    let (nb, bs) = (p.nb(), p.bs());
    let bb = bs * bs;
    dst.fill(0.0);
    // l ≥ m: the stored strip of row m.
    let n_up = (m + wp).min(nb - 1) + 1 - m;
    dst[wp * bb..(wp + n_up) * bb].copy_from_slice(&p.row_strip(m)[..n_up * bb]);
    // l < m: P_{m,l} = P_{l,m}ᵀ.
    for l in m.saturating_sub(wp)..m {
        let src = p.block(l, m - l);
        let blk = &mut dst[(l + wp - m) * bb..(l + wp - m + 1) * bb];
        for c in 0..bs {
            for r in 0..bs {
                blk[r + c * bs] = src[c + r * bs];
            }
        }
    }
}
