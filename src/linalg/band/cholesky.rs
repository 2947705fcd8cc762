//! docs/theory.md §8 update steps 4–6: block-banded Cholesky, solves and selected inversion.

use super::strips::{block_mul_add_body, chol_lower, nt_acc_fast, tn_multi_neg, tri_lower_inv};
use nalgebra::DMatrixViewMut;

use super::{Avx2Fma, BandError, SymBand};
use crate::linalg::symmetrize;

/// Block-banded Cholesky factor `Λ = L Lᵀ` (`L` lower block-banded with bandwidth `k`) of a
/// symmetric positive definite [`SymBand`] of width `k`, with the solves and the block
/// selected inversion of docs/theory.md §8 update steps 4–6.
#[derive(Debug, Clone)]
pub struct BandCholesky {
    nb: usize,
    bs: usize,
    k: usize,
    /// Block row `i` of `L` as a strip: `L_{i, i−k+d}`, `d = 0..=k`, at
    /// `i·padded_len(k+1, bs²) + d bs²`, column-major; slots with `i − k + d < 0` are zero.
    l: Vec<f64>,
    /// `L_jj⁻¹` at `j bs²` (lower triangular).
    l_diag_inv: Vec<f64>,
    /// `U_j = L_jj⁻ᵀ L_jj⁻¹`, the inverse of pivot `j`, at `j bs²`.
    pivot_inv: Vec<f64>,
    /// Block column `j` of `E = L blkdiag(L_jj)⁻¹`, transposed, for the selected inversion:
    /// `E_{j+d, j}ᵀ = L_jj⁻ᵀ L_{j+d, j}ᵀ`, `d = 1..=k`, at `(j k + d − 1) bs²`. Written by the
    /// factorisation, so that the backward sweep reads one contiguous stream instead of a
    /// column of `L` (one block from each of `k` rows).
    et: Vec<f64>,
    /// Two scratch blocks.
    tmp: Vec<f64>,
    /// Window of whole rows of `P` for the selected inversion of wide factors (sized on
    /// first use).
    rows: Vec<f64>,
}

impl BandCholesky {
    /// A factor for `nb` blocks of size `bs` and bandwidth `k` (clamped to `nb − 1`).
    pub fn new(nb: usize, bs: usize, k: usize) -> Self {
        let k = k.min(nb.saturating_sub(1));
        let bb = bs * bs;
        Self {
            nb,
            bs,
            k,
            l: vec![0.0; nb * padded_len(k + 1, bb)],
            l_diag_inv: vec![0.0; nb * bb],
            pivot_inv: vec![0.0; nb * bb],
            et: vec![0.0; nb * k * bb],
            tmp: vec![0.0; 2 * bb],
            rows: Vec::new(),
        }
    }

    /// The numbers a [`clone_for_solves`](Self::clone_for_solves) of a factor with `nb`
    /// blocks of size `bs` and bandwidth `k` (clamped to `nb − 1`) keeps.
    pub fn solve_only_len(nb: usize, bs: usize, k: usize) -> usize {
        let (k, bb) = (k.min(nb.saturating_sub(1)), bs * bs);
        nb * (padded_len(k + 1, bb) + bb)
    }

    /// The numbers this factor holds, its workspaces included.
    pub fn len_held(&self) -> usize {
        [
            &self.l,
            &self.l_diag_inv,
            &self.pivot_inv,
            &self.et,
            &self.tmp,
            &self.rows,
        ]
        .iter()
        .map(|v| v.len())
        .sum()
    }

    /// Number of block rows.
    pub fn nb(&self) -> usize {
        self.nb
    }

    /// Block size.
    pub fn bs(&self) -> usize {
        self.bs
    }

    /// Bandwidth `k` of the factor.
    pub fn width(&self) -> usize {
        self.k
    }

    #[inline]
    fn l_off(&self, i: usize, j: usize) -> usize {
        debug_assert!(j <= i && i - j <= self.k && i < self.nb);
        let bb = self.bs * self.bs;
        i * padded_len(self.k + 1, bb) + (self.k + j - i) * bb
    }

    /// Block `L_{i,j}` (`0 ≤ i − j ≤ k`) of the factor, column-major.
    #[inline]
    pub fn l_block(&self, i: usize, j: usize) -> &[f64] {
        let o = self.l_off(i, j);
        &self.l[o..o + self.bs * self.bs]
    }

    /// docs/theory.md §8 update step 4: factorises `a = L Lᵀ` (`a.width() == k`) block row by block
    /// row (up-looking), for `i = 0..nb`:
    ///
    /// `L_{i,j} = (Λ_{i,j} − Σ_{p=i−k}^{j−1} L_{i,p} L_{j,p}ᵀ) L_jj⁻ᵀ`, `j = i−k..i−1`, then
    /// `L_ii L_iiᵀ = Λ_ii − Σ_{p=i−k}^{i−1} L_{i,p} L_{i,p}ᵀ`.
    ///
    /// With `L` stored by block rows each sum is the product `X Yᵀ` of two contiguous row
    /// segments, one long kernel call (AVX2/FMA for `bs = 2, 4`) instead of one per block.
    ///
    /// Fails with [`BandError::PivotNotPositiveDefinite`] naming the first pivot block whose
    /// Schur complement is not numerically positive definite. Cost `≈ (k²/2 + 2k) bs³` per
    /// block row.
    pub fn factor(&mut self, a: &SymBand) -> Result<(), BandError> {
        assert_eq!(
            (a.nb(), a.bs(), a.width()),
            (self.nb, self.bs, self.k),
            "matrix shape"
        );
        specialise!(self.bs, factor_body(self, a))
    }

    /// `log det Λ = 2 Σ_i Σ_r log (L_ii)_rr` of the last factored matrix.
    pub fn log_det(&self) -> f64 {
        let bs = self.bs;
        (0..self.nb)
            .map(|i| {
                let lii = self.l_block(i, i);
                (0..bs).map(|r| 2.0 * lii[r * bs + r].ln()).sum::<f64>()
            })
            .sum()
    }

    /// A copy that can only [`solve_in_place`](Self::solve_in_place): `L` and the inverses
    /// of its diagonal blocks, without the selected inversion's `Eᵀ`, pivot inverses and
    /// window (about half the memory of a full clone), for keeping many factors.
    pub fn clone_for_solves(&self) -> Self {
        Self {
            l: self.l.clone(),
            l_diag_inv: self.l_diag_inv.clone(),
            pivot_inv: Vec::new(),
            et: Vec::new(),
            tmp: Vec::new(),
            rows: Vec::new(),
            ..*self
        }
    }

    /// docs/theory.md §8 update step 5: `x ← Λ⁻¹ x` (`x.len() == nb·bs`) by forward substitution
    /// `y_i = L_ii⁻¹ (x_i − Σ_{j=i−k}^{i−1} L_{i,j} y_j)` and back substitution
    /// `z_i = L_ii⁻ᵀ (y_i − Σ_{l=i+1}^{i+k} L_{l,i}ᵀ z_l)` (the sum accumulated row by row of
    /// `L`, as it is stored).
    pub fn solve_in_place(&self, x: &mut [f64]) {
        assert_eq!(x.len(), self.nb * self.bs, "right-hand side length");
        specialise!(self.bs, solve_body(self, x))
    }

    /// docs/theory.md §8 update step 6: the band `|i − j| ≤ w = out.width()` (`w ≥ k`) of `P = Λ⁻¹`,
    /// exact everywhere on it (for `|i − j| > k` it is the Gauss–Markov continuation). From
    /// `P L = L⁻ᵀ`, with `E_{l,j} = L_{l,j} L_jj⁻¹`, for `j = nb−1, …, 0`:
    ///
    /// `P_{j,i} = − Σ_{l=j+1}^{j+k} E_{l,j}ᵀ P_{l,i}`, `i = j+1..=j+w`, then
    /// `P_jj = L_jj⁻ᵀ L_jj⁻¹ − Σ_{l=j+1}^{j+k} P_{j,l} E_{l,j}` (symmetrised).
    ///
    /// Every `P_{l,i}` needed lies in block rows `> j` of the band `w`, already computed. When
    /// few of them lie below the diagonal (`k ≪ w`, the filter) the output itself is the
    /// sliding window; otherwise (`k = w`, the smoother's `𝒥`) a window of whole rows of `P`
    /// makes each block row one product of `k` strips. Cost `≈ 2 w k bs³` per block row.
    pub fn selected_inverse(&mut self, out: &mut SymBand) {
        assert_eq!((out.nb(), out.bs()), (self.nb, self.bs), "out shape");
        assert!(
            out.width() >= self.k,
            "selected inversion to a width below the factor's"
        );
        specialise!(self.bs, selected_inverse_body(self, out))
    }
}

/// Length of a strip of `blocks` blocks of `bb` entries, plus one block of padding when the
/// step from one strip to the next minus one block (the stride of a walk down a block
/// column) is a multiple of 1 KiB: such a walk would map every block to the same few cache
/// sets (κ = 32, bs = 4 gives exactly 4 KiB).
#[inline]
fn padded_len(blocks: usize, bb: usize) -> usize {
    let len = blocks * bb;
    if blocks > 1 && ((len - bb) * size_of::<f64>()).is_multiple_of(1024) {
        len + bb
    } else {
        len
    }
}

#[inline(always)]
fn factor_body(bs: usize, f: &mut BandCholesky, a: &SymBand) -> Result<(), BandError> {
    let (nb, k) = (f.nb, f.k);
    let simd = Avx2Fma::detect();
    let bb = bs * bs;
    let row_len = padded_len(k + 1, bb);
    let off = |i: usize, j: usize| i * row_len + (k + j - i) * bb;
    let (l, l_diag_inv, et) = (&mut f.l, &mut f.l_diag_inv, &mut f.et);
    let pivot_inv = &mut f.pivot_inv;
    let (pivot, s) = f.tmp.split_at_mut(bb);
    for i in 0..nb {
        // Row i is found left to right; every sum over p is one product of two row segments.
        let j0 = i.saturating_sub(k);
        // Block row i of `a` (Λ_{i,i+d}, read in storage order) goes transposed into the
        // slots L_{i+d,i} of the rows below, which hold Λ_{i+d,i} until row i+d is found:
        // reading column i of `a` instead (one block from each of k rows, a new page each)
        // costs a cache miss per block.
        for d in 1..=k.min(nb - 1 - i) {
            let aid = a.block(i, d);
            let dst = &mut l[off(i + d, i)..off(i + d, i) + bb];
            for c in 0..bs {
                for r in 0..bs {
                    dst[r + c * bs] = aid[c + r * bs];
                }
            }
        }
        for j in j0..i {
            s.copy_from_slice(&l[off(i, j)..off(i, j) + bb]);
            if j > j0 {
                nt_acc_fast(
                    simd,
                    bs,
                    s,
                    &l[off(i, j0)..off(i, j)],
                    &l[off(j, j0)..off(j, j)],
                    -1.0,
                );
            }
            // L_{i,j} = s L_jj⁻ᵀ and E_{i,j}ᵀ = (L_{i,j} L_jj⁻¹)ᵀ = U_j sᵀ, both X Yᵀ products.
            let lij = &mut l[off(i, j)..off(i, j) + bb];
            lij.fill(0.0);
            nt_acc_fast(simd, bs, lij, s, &l_diag_inv[j * bb..(j + 1) * bb], 1.0);
            let etij = &mut et[(j * k + i - j - 1) * bb..(j * k + i - j) * bb];
            etij.fill(0.0);
            nt_acc_fast(simd, bs, etij, &pivot_inv[j * bb..(j + 1) * bb], s, 1.0);
        }
        // Pivot: Λ_ii − Σ_p L_{i,p} L_{i,p}ᵀ, Cholesky in place.
        pivot.copy_from_slice(a.block(i, 0));
        if i > j0 {
            let row = &l[off(i, j0)..off(i, i)];
            nt_acc_fast(simd, bs, pivot, row, row, -1.0);
        }
        if !chol_lower(bs, pivot) {
            return Err(BandError::PivotNotPositiveDefinite { block: i });
        }
        l[off(i, i)..off(i, i) + bb].copy_from_slice(pivot);
        let inv = &mut l_diag_inv[i * bb..(i + 1) * bb];
        tri_lower_inv(bs, pivot, inv);
        let u = &mut pivot_inv[i * bb..(i + 1) * bb];
        u.fill(0.0);
        block_mul_add_body(bs, u, 1.0, inv, true, inv, false);
    }
    Ok(())
}

#[inline(always)]
fn solve_body(bs: usize, f: &BandCholesky, x: &mut [f64]) {
    let (nb, k) = (f.nb, f.k);
    let bb = bs * bs;
    for i in 0..nb {
        let (done, rest) = x.split_at_mut(i * bs);
        let xi = &mut rest[..bs];
        for j in i.saturating_sub(k)..i {
            let lij = f.l_block(i, j);
            let yj = &done[j * bs..(j + 1) * bs];
            for c in 0..bs {
                let y = yj[c];
                for r in 0..bs {
                    xi[r] -= lij[r + c * bs] * y;
                }
            }
        }
        // xi ← L_ii⁻¹ xi, lower triangular: bottom-up keeps the entries still needed.
        let inv = &f.l_diag_inv[i * bb..(i + 1) * bb];
        for r in (0..bs).rev() {
            let mut t = 0.0;
            for c in 0..=r {
                t += inv[r + c * bs] * xi[c];
            }
            xi[r] = t;
        }
    }
    // Back substitution by rows of L (the storage order): once z_i is final, its terms
    // L_{i,j}ᵀ z_i leave the entries j = i−k..i−1 still to be solved.
    for i in (0..nb).rev() {
        let (head, tail) = x.split_at_mut(i * bs);
        let xi = &mut tail[..bs];
        // xi ← L_ii⁻ᵀ xi, upper triangular: top-down keeps the entries still needed.
        let inv = &f.l_diag_inv[i * bb..(i + 1) * bb];
        for r in 0..bs {
            let mut t = 0.0;
            for c in r..bs {
                t += inv[c + r * bs] * xi[c];
            }
            xi[r] = t;
        }
        for j in i.saturating_sub(k)..i {
            let lij = f.l_block(i, j);
            let xj = &mut head[j * bs..(j + 1) * bs];
            for c in 0..bs {
                let mut t = 0.0;
                for r in 0..bs {
                    t += lij[r + c * bs] * xi[r];
                }
                xj[c] -= t;
            }
        }
    }
}

#[inline(always)]
fn selected_inverse_body(bs: usize, f: &mut BandCholesky, out: &mut SymBand) {
    let (k, w) = (f.k, out.width());
    // Row j needs P_{l,i} for l = j+1..j+k, i = j+1..j+w; about k²/2 of them lie below the
    // diagonal and are stored as P_{i,l}ᵀ. When those dominate (as in the smoother, where
    // w = k), whole rows of P are kept in a window so that every source is a plain strip.
    if k > 1 && k * (k - 1) * bs >= 2 * w {
        selected_inverse_rows(bs, f, out)
    } else {
        selected_inverse_band(bs, f, out)
    }
}

/// Diagonal block `P_jj = L_jj⁻ᵀ L_jj⁻¹ − Σ_l P_{j,l} E_{l,j}` (symmetrised) from the
/// blocks `P_{j,j+1..j+nl}` (`offd`, a strip) and `Eᵀ` (`et`): one `X Yᵀ` product.
#[inline(always)]
fn diagonal_block(
    bs: usize,
    simd: Option<Avx2Fma>,
    u: &[f64],
    offd: &[f64],
    et: &[f64],
    diag: &mut [f64],
) {
    diag.copy_from_slice(u);
    if !et.is_empty() {
        nt_acc_fast(simd, bs, diag, &offd[..et.len()], et, -1.0);
    }
    symmetrize(&mut DMatrixViewMut::from_slice(diag, bs, bs));
}

/// Selected inversion reading the band rows of `out` itself (few blocks below the diagonal).
#[inline(always)]
fn selected_inverse_band(bs: usize, f: &mut BandCholesky, out: &mut SymBand) {
    let (nb, k) = (f.nb, f.k);
    let w = out.width();
    let simd = Avx2Fma::detect();
    let bb = bs * bs;
    let strip = (w + 1) * bb;
    for j in (0..nb).rev() {
        let lmax = (j + k).min(nb - 1);
        let nl = lmax - j;
        let u = &f.pivot_inv[j * bb..(j + 1) * bb];
        let et = &f.et[j * k * bb..(j * k + nl) * bb];
        let (head, rows_below) = out.data_mut().split_at_mut((j + 1) * strip);
        let row_j = &mut head[j * strip..];
        let imax = (j + w).min(nb - 1);
        // Blocks i = lmax..=imax: every P_{l,i} (l ≤ lmax ≤ i) is in row l's strip, at
        // block offset i − l, so the sources are equally spaced: row l = j+1+q starts
        // its part at q (strip − bs²) + (lmax − j − 1) bs² of `rows_below`.
        if nl > 0 {
            tn_multi_neg(
                simd,
                bs,
                &mut row_j[nl * bb..(imax + 1 - j) * bb],
                et,
                &rows_below[(nl - 1) * bb..],
                strip - bb,
            );
            row_j[..nl * bb].fill(0.0);
        } else {
            // k = 0 or the last block row: P_{j,i} = 0 for i > j.
            row_j[..(imax + 1 - j) * bb].fill(0.0);
        }
        row_j[(imax + 1 - j) * bb..].fill(0.0);
        // Blocks i = j+1..lmax−1 (k > 1 only): P_{l,i} = P_{i,l}ᵀ for l > i.
        for i in j + 1..lmax {
            let out_ji = &mut row_j[(i - j) * bb..(i - j + 1) * bb];
            for (q, etl) in et.chunks_exact(bb).enumerate() {
                let l = j + 1 + q;
                if l <= i {
                    let pli = &rows_below[(l - j - 1) * strip + (i - l) * bb..][..bb];
                    block_mul_add_body(bs, out_ji, -1.0, etl, false, pli, false);
                } else {
                    let pil = &rows_below[(i - j - 1) * strip + (l - i) * bb..][..bb];
                    block_mul_add_body(bs, out_ji, -1.0, etl, false, pil, true);
                }
            }
        }
        let (diag, offd) = row_j.split_at_mut(bb);
        diagonal_block(bs, simd, u, offd, et, diag);
    }
}

/// Selected inversion through whole rows of `P`: row `l` is kept as the strip
/// `P_{l, l−w..l+w}` (block column `c` at slot `c − l + w`) in a window of rows, so the
/// blocks `P_{l, j+1..j+w}` that row `j` needs from rows `l = j+1+q` start at slot `w − q`
/// of row `l`, equally spaced, and the off-diagonal part of row `j` is one
/// [`tn_multi_neg`] over `k` strips of `w` blocks. The lower blocks of a row
/// (`P_{l,i} = P_{i,l}ᵀ`, `0 < l − i < k`) are written when row `i` is done. The window
/// holds `min(4(k+1), nb)` rows and slides by copying the `k` rows still needed to its end.
#[inline(always)]
fn selected_inverse_rows(bs: usize, f: &mut BandCholesky, out: &mut SymBand) {
    let (nb, k) = (f.nb, f.k);
    let w = out.width();
    let simd = Avx2Fma::detect();
    let bb = bs * bs;
    let fw = padded_len(2 * w + 1, bb);
    let cap = (4 * (k + 1)).min(nb);
    let mut rows = std::mem::take(&mut f.rows);
    if rows.len() < cap * fw {
        rows.resize(cap * fw, 0.0);
    }
    let mut base = nb - cap;
    for j in (0..nb).rev() {
        let lmax = (j + k).min(nb - 1);
        let nl = lmax - j;
        if j < base {
            // Rows j+1..=lmax sit in slots 0..nl; move them to the end.
            let new_base = (j + 1 + nl).saturating_sub(cap);
            rows.copy_within(0..nl * fw, (j + 1 - new_base) * fw);
            base = new_base;
        }
        let u = &f.pivot_inv[j * bb..(j + 1) * bb];
        let et = &f.et[j * k * bb..(j * k + nl) * bb];
        let slot = j - base;
        let (head, below) = rows.split_at_mut((slot + 1) * fw);
        // P_{j, j..j+w}: w + 1 blocks.
        let upper = &mut head[slot * fw + w * bb..slot * fw + (2 * w + 1) * bb];
        let (diag, offd) = upper.split_at_mut(bb);
        if nl > 0 {
            tn_multi_neg(simd, bs, offd, et, &below[w * bb..], fw - bb);
        } else {
            // The last block row: P_{j,i} = 0 for i > j.
            offd.fill(0.0);
        }
        diagonal_block(bs, simd, u, offd, et, diag);
        out.row_strip_mut(j).copy_from_slice(upper);
        // Lower blocks P_{j+d, j} = P_{j, j+d}ᵀ of the rows below, at slot w − d.
        for d in 1..k.min(nb - j) {
            let src = &upper[d * bb..(d + 1) * bb];
            let dst = &mut below[(d - 1) * fw + (w - d) * bb..][..bb];
            for c in 0..bs {
                for r in 0..bs {
                    dst[r + c * bs] = src[c + r * bs];
                }
            }
        }
    }
    f.rows = rows;
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    /// A symmetric block-banded matrix of bandwidth `k`, positive definite by strict diagonal
    /// dominance.
    fn band_spd(nb: usize, bs: usize, k: usize) -> DMatrix<f64> {
        let n = nb * bs;
        let mut a = DMatrix::from_fn(n, n, |r, c| {
            if (r / bs).abs_diff(c / bs) > k {
                0.0
            } else {
                ((r * 31 + c * 17) as f64 * 0.37).sin() + ((r + c) as f64 * 0.11).cos()
            }
        });
        a = &a + a.transpose();
        for r in 0..n {
            let off: f64 = a.row(r).iter().map(|v| v.abs()).sum::<f64>() - a[(r, r)].abs();
            a[(r, r)] = off + 0.5;
        }
        a
    }

    /// Long chains so that the row window of the selected inversion slides (`nb > 4(k+1)`),
    /// with both the row-window and the band path, and with padded strips (`bs = 4, k = 8`:
    /// rows of `L` and, for `w = 8, 24`, of the window), against the dense inverse and solve.
    #[test]
    fn selected_inverse_on_long_chains_matches_dense_inverse() {
        let shapes = [
            (30, 4, 3),
            (30, 2, 3),
            (23, 4, 5),
            (40, 1, 4),
            (25, 5, 3),
            (40, 4, 8),
        ];
        assert!(padded_len(9, 16) > 9 * 16 && padded_len(17, 16) > 17 * 16);
        for (nb, bs, k) in shapes {
            let a = band_spd(nb, bs, k);
            let inv = a.clone().try_inverse().unwrap();
            let mut chol = BandCholesky::new(nb, bs, k);
            chol.factor(&SymBand::from_dense(&a, bs, k)).unwrap();
            let rhs: Vec<f64> = (0..nb * bs).map(|e| (0.7 * e as f64).sin()).collect();
            let mut x = rhs.clone();
            chol.solve_in_place(&mut x);
            let expect = &inv * nalgebra::DVector::from_column_slice(&rhs);
            let err = (nalgebra::DVector::from_vec(x) - &expect).amax();
            assert!(
                err < 1e-12 * expect.amax(),
                "solve {:?}: {err:e}",
                (nb, bs, k)
            );
            for w in [k, k + 2, 3 * k] {
                let mut out = SymBand::zeros(nb, bs, w);
                out.data_mut().fill(f64::NAN);
                chol.selected_inverse(&mut out);
                let dense = out.to_dense();
                for r in 0..nb * bs {
                    for c in 0..nb * bs {
                        let expect = if (r / bs).abs_diff(c / bs) <= w {
                            inv[(r, c)]
                        } else {
                            0.0
                        };
                        assert!(
                            (dense[(r, c)] - expect).abs() < 1e-12 * inv.amax(),
                            "{:?} at ({r}, {c})",
                            (nb, bs, k, w)
                        );
                    }
                }
            }
        }
    }
}
