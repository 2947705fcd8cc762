//! SPEC §9 update steps 4–6: block-banded Cholesky, solves and selected inversion.

use super::kernels::{
    block_mul_add_body, chol_lower, nt_acc_body, simd_available, symmetrise, tn_multi_neg,
    tri_lower_inv,
};
use super::{BandError, SymBand};

/// Block-banded Cholesky factor `Λ = L Lᵀ` (`L` lower block-banded with bandwidth `k`) of a
/// symmetric positive definite [`SymBand`] of width `k`, with the solves and the block
/// selected inversion of SPEC §9 update steps 4–6.
#[derive(Debug, Clone)]
pub struct BandCholesky {
    nb: usize,
    bs: usize,
    k: usize,
    /// Block column `j` of `L`: `L_{j+d, j}`, `d = 0..=k`, at `(j (k+1) + d) bs²`,
    /// column-major; slots with `j + d ≥ nb` are zero.
    l: Vec<f64>,
    /// `L_jj⁻¹` at `j bs²` (lower triangular).
    l_diag_inv: Vec<f64>,
    /// Selected inversion scratch: `E_{j+d, j}ᵀ` with `E_{j+d, j} = L_{j+d, j} L_jj⁻¹`,
    /// `d = 1..=k`, at `(d−1) bs²`.
    e: Vec<f64>,
    /// Two scratch blocks.
    tmp: Vec<f64>,
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
            l: vec![0.0; nb * (k + 1) * bb],
            l_diag_inv: vec![0.0; nb * bb],
            e: vec![0.0; k * bb],
            tmp: vec![0.0; 2 * bb],
        }
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

    /// Kept for the API: [`BandCholesky::selected_inverse`] writes into its output directly
    /// and needs no buffer that depends on the output width.
    pub fn reserve_width(&mut self, _w: usize) {}

    #[inline]
    fn l_off(&self, i: usize, j: usize) -> usize {
        debug_assert!(j <= i && i - j <= self.k && i < self.nb);
        (j * (self.k + 1) + i - j) * self.bs * self.bs
    }

    /// Block `L_{i,j}` (`0 ≤ i − j ≤ k`) of the factor, column-major.
    #[inline]
    pub fn l_block(&self, i: usize, j: usize) -> &[f64] {
        let o = self.l_off(i, j);
        &self.l[o..o + self.bs * self.bs]
    }

    /// SPEC §9 update step 4: factorises `a = L Lᵀ` (`a.width() == k`) block column by block
    /// column (left-looking), for `j = 0..nb`:
    ///
    /// `L_jj L_jjᵀ = Λ_jj − Σ_{l=j−k}^{j−1} L_{j,l} L_{j,l}ᵀ`,
    /// `L_{i,j} = (Λ_{i,j} − Σ_{l=i−k}^{j−1} L_{i,l} L_{j,l}ᵀ) L_jj⁻ᵀ`, `i = j+1..=j+k`.
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

    /// SPEC §9 update step 5: `x ← Λ⁻¹ x` (`x.len() == nb·bs`) by forward substitution
    /// `y_i = L_ii⁻¹ (x_i − Σ_{j=i−k}^{i−1} L_{i,j} y_j)` and back substitution
    /// `z_i = L_ii⁻ᵀ (y_i − Σ_{l=i+1}^{i+k} L_{l,i}ᵀ z_l)`.
    pub fn solve_in_place(&self, x: &mut [f64]) {
        assert_eq!(x.len(), self.nb * self.bs, "right-hand side length");
        specialise!(self.bs, solve_body(self, x))
    }

    /// SPEC §9 update step 6: the band `|i − j| ≤ w = out.width()` (`w ≥ k`) of `P = Λ⁻¹`,
    /// exact everywhere on it (for `|i − j| > k` it is the Gauss–Markov continuation). From
    /// `P L = L⁻ᵀ`, with `E_{l,j} = L_{l,j} L_jj⁻¹`, for `j = nb−1, …, 0`:
    ///
    /// `P_{j,i} = − Σ_{l=j+1}^{j+k} E_{l,j}ᵀ P_{l,i}`, `i = j+1..=j+w`, then
    /// `P_jj = L_jj⁻ᵀ L_jj⁻¹ − Σ_{l=j+1}^{j+k} P_{j,l} E_{l,j}` (symmetrised).
    ///
    /// Every `P_{l,i}` needed lies in block rows `> j` of the band `w`, already computed; the
    /// output itself is the sliding window. Cost `≈ 2 w k bs³` per block row.
    pub fn selected_inverse(&mut self, out: &mut SymBand) {
        assert_eq!((out.nb(), out.bs()), (self.nb, self.bs), "out shape");
        assert!(
            out.width() >= self.k,
            "selected inversion to a width below the factor's"
        );
        specialise!(self.bs, selected_inverse_body(self, out))
    }
}
#[inline(always)]
fn factor_body(bs: usize, f: &mut BandCholesky, a: &SymBand) -> Result<(), BandError> {
    let (nb, k) = (f.nb, f.k);
    let bb = bs * bs;
    let off = |i: usize, j: usize| (j * (k + 1) + i - j) * bb;
    let (l, l_diag_inv) = (&mut f.l, &mut f.l_diag_inv);
    let (pivot, s) = f.tmp.split_at_mut(bb);
    for j in 0..nb {
        // Pivot: Λ_jj − Σ_l L_{j,l} L_{j,l}ᵀ, Cholesky in place.
        pivot.copy_from_slice(a.block(j, 0));
        for p in j.saturating_sub(k)..j {
            let ljp = &l[off(j, p)..off(j, p) + bb];
            nt_acc_body(bs, pivot, ljp, ljp, -1.0);
        }
        if !chol_lower(bs, pivot) {
            return Err(BandError::PivotNotPositiveDefinite { block: j });
        }
        l[off(j, j)..off(j, j) + bb].copy_from_slice(pivot);
        let inv = &mut l_diag_inv[j * bb..(j + 1) * bb];
        tri_lower_inv(bs, pivot, inv);
        // Off-diagonal blocks of column j.
        for i in j + 1..=(j + k).min(nb - 1) {
            // Λ_{i,j} = (stored Λ_{j,i})ᵀ.
            let aji = a.block(j, i - j);
            for c in 0..bs {
                for r in 0..bs {
                    s[r + c * bs] = aji[c + r * bs];
                }
            }
            for p in i.saturating_sub(k)..j {
                let (oi, oj) = (off(i, p), off(j, p));
                nt_acc_body(bs, s, &l[oi..oi + bb], &l[oj..oj + bb], -1.0);
            }
            let lij = &mut l[off(i, j)..off(i, j) + bb];
            lij.fill(0.0);
            block_mul_add_body(bs, lij, 1.0, s, false, inv, true);
        }
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
    for i in (0..nb).rev() {
        let (head, done) = x.split_at_mut((i + 1) * bs);
        let xi = &mut head[i * bs..];
        for l in i + 1..=(i + k).min(nb - 1) {
            let lli = f.l_block(l, i);
            let zl = &done[(l - i - 1) * bs..(l - i) * bs];
            for c in 0..bs {
                let mut t = 0.0;
                for r in 0..bs {
                    t += lli[r + c * bs] * zl[r];
                }
                xi[c] -= t;
            }
        }
        // xi ← L_ii⁻ᵀ xi, upper triangular: top-down keeps the entries still needed.
        let inv = &f.l_diag_inv[i * bb..(i + 1) * bb];
        for r in 0..bs {
            let mut t = 0.0;
            for c in r..bs {
                t += inv[c + r * bs] * xi[c];
            }
            xi[r] = t;
        }
    }
}

#[inline(always)]
fn selected_inverse_body(bs: usize, f: &mut BandCholesky, out: &mut SymBand) {
    let (nb, k) = (f.nb, f.k);
    let w = out.width();
    let simd = simd_available();
    let bb = bs * bs;
    let strip = (w + 1) * bb;
    for j in (0..nb).rev() {
        let lmax = (j + k).min(nb - 1);
        let nl = lmax - j;
        let inv = &f.l_diag_inv[j * bb..(j + 1) * bb];
        // Eᵀ_{l,j} = L_jj⁻ᵀ L_{l,j}ᵀ for l = j+1..=lmax.
        let et = &mut f.e[..nl * bb];
        for (d, etl) in et.chunks_exact_mut(bb).enumerate() {
            etl.fill(0.0);
            let o = (j * (k + 1) + d + 1) * bb;
            block_mul_add_body(bs, etl, 1.0, inv, true, &f.l[o..o + bb], true);
        }
        let et = &f.e[..nl * bb];
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
        // Diagonal: L_jj⁻ᵀ L_jj⁻¹ − Σ_l P_{j,l} E_{l,j}.
        let (diag, offd) = row_j.split_at_mut(bb);
        block_mul_add_body(bs, diag, 1.0, inv, true, inv, false);
        for (q, etl) in et.chunks_exact(bb).enumerate() {
            let pjl = &offd[q * bb..(q + 1) * bb];
            block_mul_add_body(bs, diag, -1.0, pjl, false, etl, true);
        }
        symmetrise(bs, diag);
    }
}
