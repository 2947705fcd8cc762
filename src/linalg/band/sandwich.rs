//! docs/theory.md §8 predict step 4: the band of `A P Aᵀ` for block-banded `A` and `P`.

use super::Avx2Fma;
use super::strips::nt_acc_fast;
use super::{GenBand, SymBand};

/// Preallocated buffers for [`sandwich`]: a ring of half block rows of `P` and one block
/// row of `V = A U`.
#[derive(Debug, Clone)]
pub struct SandwichWorkspace {
    nb: usize,
    bs: usize,
    /// Largest half-width of `A` and output width the buffers serve.
    b_max: usize,
    k_max: usize,
    /// Ring of `k + 2b + 1` half block rows of `P`: row `m` at slot `m mod ring`, the strip
    /// `[P_{m,m−wp} … P_{m,m−1} ½P_{m,m}]` of `bs × (wp+1)·bs` (zero outside the matrix),
    /// `wp = min(k + 2b, nb − 1)`.
    rows: Vec<f64>,
    /// Block row `i` of `V = A U`, blocks `m = i−b..=i+b+k` at `(m + b − i) bs²`.
    v_row: Vec<f64>,
    /// One block of `Y = V Aᵀ`.
    y: Vec<f64>,
}

/// `(wp, ring)` for half-width `b` and output width `k`: the width of `P` that enters and the
/// number of its rows in use at once.
fn shape(nb: usize, b: usize, k: usize) -> (usize, usize) {
    (
        (k + 2 * b).min(nb.saturating_sub(1)),
        (k + 2 * b + 1).min(nb.max(1)),
    )
}

impl SandwichWorkspace {
    /// Buffers for `nb` blocks of size `bs`, `A` of half-width up to `b` and output width up
    /// to `k` (both clamped to `nb − 1`).
    pub fn new(nb: usize, bs: usize, b: usize, k: usize) -> Self {
        let top = nb.saturating_sub(1);
        let (b, k) = (b.min(top), k.min(top));
        let (wp, ring) = shape(nb, b, k);
        let bb = bs * bs;
        Self {
            nb,
            bs,
            b_max: b,
            k_max: k,
            rows: vec![0.0; ring * (wp + 1) * bb],
            v_row: vec![0.0; (k + 2 * b + 1) * bb],
            y: vec![0.0; bb],
        }
    }
}

/// docs/theory.md §8 predict step 4: `out = band_k(A P Aᵀ)`, `k = out.width()`, for `A` of half-width
/// `b` and symmetric `P` of width `≥ min(k + 2b, nb − 1)` (only that band of `P` enters).
///
/// With `P = U + Uᵀ`, `U` the upper block triangle of `P` with its diagonal blocks halved,
/// `A P Aᵀ = Y + Yᵀ` for `Y = A U Aᵀ`, and the triangular `U` halves the work of the
/// first product. Per block row `i`:
///
/// `V_{i,m} = Σ_{l=i−b}^{min(i+b, m)} A_{i,l} U_{l,m}` for `m = i−b..=i+b+k`,
/// `Y_{i,j} = Σ_{m=j−b}^{j+b} V_{i,m} A_{j,m}ᵀ` for `j = i−k..=i+k`,
///
/// and `Y_{i,j}` goes to `out_{i,j}` (`j ≥ i`) or, transposed, to `out_{j,i}` (`j ≤ i`).
/// Both sums are products of two block-row strips (`U_{l,m} = (P_{m,l})ᵀ` over the columns
/// `l ≤ m` of block row `m`), each one contiguous dot-product kernel. The half rows
/// `[P_{m,m−wp} … ½P_{m,m}]` are assembled once each into a ring of the `k + 2b + 1` in use.
/// Cost per block row `≈ 2 bs³ [(2b+1)(b+1) + k(2b+1) + (2k+1)(2b+1)]` flops, against
/// `2 bs³ (2b+1)(2k+2b+2)` for `W = A P` then `W Aᵀ`. The caller adds `Q`. A workspace
/// built for `(b, k)` serves any smaller half-width and band.
pub fn sandwich(a: &GenBand, p: &SymBand, out: &mut SymBand, ws: &mut SandwichWorkspace) {
    let (nb, bs) = (ws.nb, ws.bs);
    assert_eq!((a.nb(), a.bs()), (nb, bs), "A shape");
    assert_eq!((out.nb(), out.bs()), (nb, bs), "out shape");
    assert_eq!((p.nb(), p.bs()), (nb, bs), "P shape");
    let (b, k) = (a.half_width(), out.width());
    assert!(
        b <= ws.b_max && k <= ws.k_max,
        "workspace built for a narrower A or band"
    );
    let (wp, _) = shape(nb, b, k);
    assert!(
        p.width() >= wp,
        "the band of P is narrower than min(k + 2b, nb − 1)"
    );
    specialise!(bs, sandwich_body(a, p, out, ws))
}

#[inline(always)]
fn sandwich_body(
    bs: usize,
    a: &GenBand,
    p: &SymBand,
    out: &mut SymBand,
    ws: &mut SandwichWorkspace,
) {
    let (nb, b, k) = (ws.nb, a.half_width(), out.width());
    let (wp, ring) = shape(nb, b, k);
    let simd = Avx2Fma::detect();
    let bb = bs * bs;
    let row_len = (wp + 1) * bb;
    out.fill_zero();
    let mut next_row = 0; // first row of P not yet in the ring
    for i in 0..nb {
        let m_lo = i.saturating_sub(b);
        let m_hi = (i + b + k).min(nb - 1);
        while next_row <= m_hi {
            let slot = next_row % ring;
            let dst = &mut ws.rows[slot * row_len..(slot + 1) * row_len];
            half_row(bs, p, next_row, wp, dst);
            next_row += 1;
        }
        // V_{i,m} = A_{i,·} (U_{·,m})ᵀ over l = l_lo..=min(l_hi, m).
        let (l_lo, l_hi) = (i.saturating_sub(b), (i + b).min(nb - 1));
        let a_row = a.row_strip(i);
        for m in m_lo..=m_hi {
            let n = (l_hi.min(m) + 1 - l_lo) * bb;
            let a_cols = &a_row[(l_lo + b - i) * bb..][..n];
            let slot = m % ring;
            let u_cols = &ws.rows[slot * row_len + (l_lo + wp - m) * bb..][..n];
            let v_im = &mut ws.v_row[(m + b - i) * bb..(m + b - i + 1) * bb];
            v_im.fill(0.0);
            nt_acc_fast(simd, bs, v_im, a_cols, u_cols, 1.0);
        }
        // Y_{i,j} = V_{i,·} (A_{j,·})ᵀ over m = max(j−b, i−b)..=min(j+b, nb−1).
        for j in i.saturating_sub(k)..=(i + k).min(nb - 1) {
            let (lo, hi) = (j.saturating_sub(b).max(m_lo), (j + b).min(nb - 1));
            if hi < lo {
                continue; // |i − j| > 2b: Y_{i,j} = 0
            }
            let n = (hi + 1 - lo) * bb;
            let v_cols = &ws.v_row[(lo + b - i) * bb..][..n];
            let a_cols = &a.row_strip(j)[(lo + b - j) * bb..][..n];
            let y = &mut ws.y[..];
            y.fill(0.0);
            nt_acc_fast(simd, bs, y, v_cols, a_cols, 1.0);
            if j >= i {
                let o = out.block_mut(i, j - i);
                for e in 0..bb {
                    o[e] += y[e];
                }
            }
            if j <= i {
                let o = out.block_mut(j, i - j);
                for c in 0..bs {
                    for r in 0..bs {
                        o[r + c * bs] += y[c + r * bs];
                    }
                }
            }
        }
    }
}

/// The left half of block row `m` of the symmetric `P`, diagonal halved:
/// `dst = [P_{m,m−wp} … P_{m,m−1} ½P_{m,m}]`, zero outside the matrix.
#[inline(always)]
fn half_row(bs: usize, p: &SymBand, m: usize, wp: usize, dst: &mut [f64]) {
    let bb = bs * bs;
    let first = m.saturating_sub(wp);
    dst[..(first + wp - m) * bb].fill(0.0);
    // l < m: P_{m,l} = P_{l,m}ᵀ.
    for l in first..m {
        let src = p.block(l, m - l);
        let blk = &mut dst[(l + wp - m) * bb..(l + wp - m + 1) * bb];
        for c in 0..bs {
            for r in 0..bs {
                blk[r + c * bs] = src[c + r * bs];
            }
        }
    }
    let diag = p.block(m, 0);
    for (d, s) in dst[wp * bb..].iter_mut().zip(diag) {
        *d = 0.5 * s;
    }
}
