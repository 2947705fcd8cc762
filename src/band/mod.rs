//! Block-banded matrices and the operations of the joint band-`k` filter (SPEC §9) and its
//! smoother (SPEC §10): the precision of the maximum-entropy (Gauss–Markov) completion of a
//! band, the block-banded Cholesky factorisation with its solves, block selected inversion
//! (Takahashi) to any bandwidth, and the banded sandwich product `band_k(A P Aᵀ)`.
//!
//! Pure linear algebra: it knows nothing of chains or filters. Indices are 0-based. A matrix
//! of `nb × nb` blocks of size `bs × bs`; every block is stored column-major and contiguous,
//! and the blocks of one block row are adjacent, so a block row of a band is itself a
//! column-major `bs × (width+1)·bs` strip. Every operation costs `O(nb)` and allocates nothing
//! once its workspace exists (they run once per time step with `nb` up to 10⁵).

mod cholesky;
mod completion;
mod kernels;
mod products;
mod sandwich;

pub use cholesky::BandCholesky;
pub use completion::{CompletionWorkspace, completion_precision};
pub use products::{gen_t_times_gen, sym_times_gen};
pub use sandwich::{SandwichWorkspace, sandwich};

use nalgebra::DMatrix;

/// Why a block-band operation failed. Indices are 0-based in the fields and 1-based in the
/// message (they name subsystems of the chain).
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum BandError {
    /// The dense block `P_{C_j C_j}` of the clique of blocks `first..=last` (or a separator
    /// within it) is not positive definite.
    #[error("clique of blocks {}..{} is not positive definite", first + 1, last + 1)]
    CliqueNotPositiveDefinite { first: usize, last: usize },
    /// Pivot block `block` of the block-banded Cholesky factorisation is not positive definite.
    #[error("Cholesky pivot block {} is not positive definite", block + 1)]
    PivotNotPositiveDefinite { block: usize },
}

/// Symmetric block-banded matrix: `nb` block rows of `bs × bs` blocks, bandwidth `w`
/// (clamped to `nb − 1`), i.e. blocks `(i, j)` with `|i − j| ≤ w`. Stores the upper blocks
/// `(i, i+d)`, `d = 0..=w`: block row `i` is the column-major strip
/// `[A_{i,i} A_{i,i+1} … A_{i,i+w}]` of `bs × (w+1)·bs`. Slots with `i + d ≥ nb` exist in
/// storage, are ignored and kept zero.
#[derive(Debug, Clone, PartialEq)]
pub struct SymBand {
    nb: usize,
    bs: usize,
    w: usize,
    data: Vec<f64>,
}

impl SymBand {
    /// The zero matrix of `nb × nb` blocks of size `bs`, bandwidth `min(w, nb − 1)`.
    pub fn zeros(nb: usize, bs: usize, w: usize) -> Self {
        let w = w.min(nb.saturating_sub(1));
        Self {
            nb,
            bs,
            w,
            data: vec![0.0; nb * (w + 1) * bs * bs],
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

    /// Bandwidth `w` in blocks (`A_{i,j} = 0` for `|i − j| > w`).
    pub fn width(&self) -> usize {
        self.w
    }

    #[inline]
    fn offset(&self, i: usize, d: usize) -> usize {
        debug_assert!(
            d <= self.w && i + d < self.nb,
            "block ({i}, {i}+{d}) outside"
        );
        (i * (self.w + 1) + d) * self.bs * self.bs
    }

    /// Block `(i, i+d)`, column-major. Panics (debug) if `d > width` or `i + d ≥ nb`.
    #[inline]
    pub fn block(&self, i: usize, d: usize) -> &[f64] {
        let o = self.offset(i, d);
        &self.data[o..o + self.bs * self.bs]
    }

    /// Block `(i, i+d)`, column-major, mutable. Panics (debug) if `d > width` or `i + d ≥ nb`.
    #[inline]
    pub fn block_mut(&mut self, i: usize, d: usize) -> &mut [f64] {
        let o = self.offset(i, d);
        let bb = self.bs * self.bs;
        &mut self.data[o..o + bb]
    }

    /// Block row `i` as the column-major `bs × (w+1)·bs` strip `[A_{i,i} … A_{i,i+w}]`
    /// (slots past the last block column are zero).
    #[inline]
    pub fn row_strip(&self, i: usize) -> &[f64] {
        let len = (self.w + 1) * self.bs * self.bs;
        &self.data[i * len..(i + 1) * len]
    }

    /// Block row `i` as a mutable strip; see [`SymBand::row_strip`]. Keep the slots past the
    /// last block column zero.
    #[inline]
    pub fn row_strip_mut(&mut self, i: usize) -> &mut [f64] {
        let len = (self.w + 1) * self.bs * self.bs;
        &mut self.data[i * len..(i + 1) * len]
    }

    /// Sets every entry to zero.
    pub fn fill_zero(&mut self) {
        self.data.fill(0.0);
    }

    /// Copies the blocks with `d ≤ min(self.width, src.width)`; the others become zero.
    pub fn copy_band_from(&mut self, src: &SymBand) {
        assert_eq!((self.nb, self.bs), (src.nb, src.bs), "shape mismatch");
        if self.w == src.w {
            self.data.copy_from_slice(&src.data);
            return;
        }
        let d = self.w.min(src.w);
        let bb = self.bs * self.bs;
        let (ls, lt) = ((src.w + 1) * bb, (self.w + 1) * bb);
        for i in 0..self.nb {
            let t = &mut self.data[i * lt..(i + 1) * lt];
            t[..(d + 1) * bb].copy_from_slice(&src.data[i * ls..i * ls + (d + 1) * bb]);
            t[(d + 1) * bb..].fill(0.0);
        }
    }

    /// The full symmetric `nb·bs × nb·bs` matrix (zeros outside the band).
    pub fn to_dense(&self) -> DMatrix<f64> {
        let (bs, n) = (self.bs, self.nb * self.bs);
        let mut a = DMatrix::zeros(n, n);
        for i in 0..self.nb {
            for d in 0..=self.w.min(self.nb - 1 - i) {
                let blk = self.block(i, d);
                for c in 0..bs {
                    for r in 0..bs {
                        let v = blk[r + c * bs];
                        a[(i * bs + r, (i + d) * bs + c)] = v;
                        a[((i + d) * bs + c, i * bs + r)] = v;
                    }
                }
            }
        }
        a
    }

    /// Reads the band `|i − j| ≤ w` of a dense matrix from its upper blocks (the matrix is
    /// assumed symmetric; its lower blocks are not read).
    pub fn from_dense(a: &DMatrix<f64>, bs: usize, w: usize) -> Self {
        assert!(bs > 0 && a.nrows() == a.ncols() && a.nrows() % bs == 0);
        let mut s = Self::zeros(a.nrows() / bs, bs, w);
        for i in 0..s.nb {
            for d in 0..=s.w.min(s.nb - 1 - i) {
                let blk = s.block_mut(i, d);
                for c in 0..bs {
                    for r in 0..bs {
                        blk[r + c * bs] = a[(i * bs + r, (i + d) * bs + c)];
                    }
                }
            }
        }
        s
    }
}

/// General (non-symmetric) block-banded matrix of `nb × nb` blocks of size `bs`, half-width
/// `b` (clamped to `nb − 1`): blocks `(i, j)` with `|i − j| ≤ b`. Block row `i` is the
/// column-major strip `[A_{i,i−b} … A_{i,i+b}]` of `bs × (2b+1)·bs`; slots with `j < 0` or
/// `j ≥ nb` exist in storage, are ignored and kept zero.
#[derive(Debug, Clone, PartialEq)]
pub struct GenBand {
    nb: usize,
    bs: usize,
    b: usize,
    data: Vec<f64>,
}

impl GenBand {
    /// The zero matrix of `nb × nb` blocks of size `bs`, half-width `min(b, nb − 1)`.
    pub fn zeros(nb: usize, bs: usize, b: usize) -> Self {
        let b = b.min(nb.saturating_sub(1));
        Self {
            nb,
            bs,
            b,
            data: vec![0.0; nb * (2 * b + 1) * bs * bs],
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

    /// Half-width `b` in blocks (`A_{i,j} = 0` for `|i − j| > b`).
    pub fn half_width(&self) -> usize {
        self.b
    }

    #[inline]
    fn offset(&self, i: usize, j: usize) -> usize {
        debug_assert!(
            i < self.nb && j < self.nb && i.abs_diff(j) <= self.b,
            "block ({i}, {j}) outside"
        );
        (i * (2 * self.b + 1) + j + self.b - i) * self.bs * self.bs
    }

    /// Block `(i, j)`, `|i − j| ≤ b`, column-major.
    #[inline]
    pub fn block(&self, i: usize, j: usize) -> &[f64] {
        let o = self.offset(i, j);
        &self.data[o..o + self.bs * self.bs]
    }

    /// Block `(i, j)`, `|i − j| ≤ b`, column-major, mutable.
    #[inline]
    pub fn block_mut(&mut self, i: usize, j: usize) -> &mut [f64] {
        let o = self.offset(i, j);
        let bb = self.bs * self.bs;
        &mut self.data[o..o + bb]
    }

    /// Block row `i` as the column-major strip `[A_{i,i−b} … A_{i,i+b}]` of
    /// `bs × (2b+1)·bs` (slots outside the matrix are zero).
    #[inline]
    pub fn row_strip(&self, i: usize) -> &[f64] {
        let len = (2 * self.b + 1) * self.bs * self.bs;
        &self.data[i * len..(i + 1) * len]
    }

    /// Sets every entry to zero.
    pub fn fill_zero(&mut self) {
        self.data.fill(0.0);
    }

    /// The dense `nb·bs × nb·bs` matrix (zeros outside the band).
    pub fn to_dense(&self) -> DMatrix<f64> {
        let (bs, n) = (self.bs, self.nb * self.bs);
        let mut a = DMatrix::zeros(n, n);
        for i in 0..self.nb {
            for j in i.saturating_sub(self.b)..(i + self.b + 1).min(self.nb) {
                let blk = self.block(i, j);
                for c in 0..bs {
                    for r in 0..bs {
                        a[(i * bs + r, j * bs + c)] = blk[r + c * bs];
                    }
                }
            }
        }
        a
    }

    /// Reads the blocks `|i − j| ≤ b` of a dense matrix.
    pub fn from_dense(a: &DMatrix<f64>, bs: usize, b: usize) -> Self {
        assert!(bs > 0 && a.nrows() == a.ncols() && a.nrows() % bs == 0);
        let mut g = Self::zeros(a.nrows() / bs, bs, b);
        for i in 0..g.nb {
            for j in i.saturating_sub(g.b)..(i + g.b + 1).min(g.nb) {
                let blk = g.block_mut(i, j);
                for c in 0..bs {
                    for r in 0..bs {
                        blk[r + c * bs] = a[(i * bs + r, j * bs + c)];
                    }
                }
            }
        }
        g
    }
}

#[cfg(test)]
mod tests {
    //! Every operation against dense nalgebra on random SPD block-band matrices.
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random SPD matrix of `nb × nb` blocks of size `bs` (dense, full).
    fn random_spd(nb: usize, bs: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
        let n = nb * bs;
        let f = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        &f * f.transpose() + DMatrix::identity(n, n) * (n as f64 * 0.1)
    }

    /// The block band of width `w` of `a`, zero elsewhere (dense).
    fn band_of(a: &DMatrix<f64>, bs: usize, w: usize) -> DMatrix<f64> {
        SymBand::from_dense(a, bs, w).to_dense()
    }

    fn rel(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
        (a - b).amax() / b.amax().max(1e-300)
    }

    fn cases() -> Vec<(usize, usize, usize)> {
        let mut v = vec![];
        for nb in [1_usize, 2, 3, 6, 9] {
            for bs in [1, 2, 3] {
                for k in [0, 1, 2, nb.saturating_sub(1)] {
                    v.push((nb, bs, k.min(nb - 1)));
                }
            }
        }
        v.push((5, 4, 2));
        v
    }

    #[test]
    fn completion_inverse_agrees_with_band_and_is_banded() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for (nb, bs, k) in cases() {
            let p = random_spd(nb, bs, &mut rng);
            let band = SymBand::from_dense(&p, bs, k);
            let mut lam = SymBand::zeros(nb, bs, k);
            let mut ws = CompletionWorkspace::new(nb, bs, k);
            completion_precision(&band, k, &mut lam, &mut ws).unwrap();
            let dense_lam = lam.to_dense();
            let completed = dense_lam.clone().try_inverse().unwrap();
            // The completion agrees with P on the band (Λ is banded by construction).
            let err = rel(&band_of(&completed, bs, k), &band_of(&p, bs, k));
            assert!(err < 1e-10, "nb {nb} bs {bs} k {k}: {err:e}");
        }
    }

    #[test]
    fn cholesky_solve_and_selected_inverse_match_dense() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for (nb, bs, k) in cases() {
            // A banded SPD Λ: the completion precision of a random SPD band.
            let p = random_spd(nb, bs, &mut rng);
            let mut lam = SymBand::zeros(nb, bs, k);
            let mut ws = CompletionWorkspace::new(nb, bs, k);
            completion_precision(&SymBand::from_dense(&p, bs, k), k, &mut lam, &mut ws).unwrap();
            let dense = lam.to_dense();
            let mut chol = BandCholesky::new(nb, bs, k);
            chol.factor(&lam).unwrap();
            let x: Vec<f64> = (0..nb * bs).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut y = x.clone();
            chol.solve_in_place(&mut y);
            let expect = dense
                .clone()
                .lu()
                .solve(&nalgebra::DVector::from_vec(x))
                .unwrap();
            let err = (nalgebra::DVector::from_vec(y) - &expect).amax() / expect.amax();
            assert!(err < 1e-10, "solve nb {nb} bs {bs} k {k}: {err:e}");
            let inv = dense.try_inverse().unwrap();
            for w in k..nb {
                let mut out = SymBand::zeros(nb, bs, w);
                chol.selected_inverse(&mut out);
                let err = rel(&out.to_dense(), &band_of(&inv, bs, w));
                assert!(
                    err < 1e-10,
                    "selected inverse nb {nb} bs {bs} k {k} w {w}: {err:e}"
                );
            }
        }
    }

    #[test]
    fn sandwich_matches_dense_product() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for (nb, bs, k) in cases() {
            for b in [0, 1, 3] {
                let n = nb * bs;
                let a_full = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
                let a = GenBand::from_dense(&a_full, bs, b);
                let a_dense = a.to_dense();
                let p = random_spd(nb, bs, &mut rng);
                let w = (k + 2 * b).min(nb - 1);
                let pb = SymBand::from_dense(&p, bs, w);
                let mut out = SymBand::zeros(nb, bs, k);
                let mut ws = SandwichWorkspace::new(nb, bs, b, k);
                sandwich(&a, &pb, &mut out, &mut ws);
                // Only the band w of P can reach the band k of A P Aᵀ: compare with full P.
                let expect = band_of(&(&a_dense * &p * a_dense.transpose()), bs, k);
                let err = rel(&out.to_dense(), &expect);
                assert!(err < 1e-12, "nb {nb} bs {bs} k {k} b {b}: {err:e}");
            }
        }
    }

    #[test]
    fn smoother_products_match_dense() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for (nb, bs, k) in cases() {
            for b in [0, 1, 2] {
                let n = nb * bs;
                let a = GenBand::from_dense(
                    &DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0)),
                    bs,
                    b,
                );
                let s = SymBand::from_dense(&random_spd(nb, bs, &mut rng), bs, k);
                let (ad, sd) = (a.to_dense(), s.to_dense());
                let mut w = GenBand::zeros(nb, bs, k + b);
                sym_times_gen(&s, &a, &mut w);
                assert!(
                    rel(&w.to_dense(), &(&sd * &ad)) < 1e-12,
                    "S A: {nb} {bs} {k} {b}"
                );
                let mut m = SymBand::zeros(nb, bs, k + 2 * b);
                gen_t_times_gen(&a, &w, &mut m);
                let expect = ad.transpose() * &sd * &ad;
                assert!(
                    rel(&m.to_dense(), &expect) < 1e-12,
                    "Aᵀ S A: {nb} {bs} {k} {b}"
                );
                let x: Vec<f64> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
                let xv = nalgebra::DVector::from_column_slice(&x);
                let mut out = vec![0.0; n];
                s.mul_vec(&x, &mut out);
                assert!((nalgebra::DVector::from_vec(out.clone()) - &sd * &xv).amax() < 1e-12);
                a.mul_vec_transposed(&x, &mut out);
                assert!((nalgebra::DVector::from_vec(out) - ad.transpose() * &xv).amax() < 1e-12);
            }
        }
    }

    #[test]
    fn non_positive_definite_inputs_name_the_block() {
        let nb = 4;
        let mut p = SymBand::zeros(nb, 1, 1);
        for i in 0..nb {
            p.block_mut(i, 0)[0] = 1.0;
        }
        for i in 0..nb - 1 {
            p.block_mut(i, 1)[0] = 0.5;
        }
        p.block_mut(2, 1)[0] = 2.0; // clique {2, 3}: [[1, 2], [2, 1]] is indefinite
        let mut lam = SymBand::zeros(nb, 1, 1);
        let mut ws = CompletionWorkspace::new(nb, 1, 1);
        assert_eq!(
            completion_precision(&p, 1, &mut lam, &mut ws),
            Err(BandError::CliqueNotPositiveDefinite { first: 2, last: 3 })
        );
        let mut a = SymBand::zeros(nb, 1, 1);
        for i in 0..nb {
            a.block_mut(i, 0)[0] = if i == 1 { -1.0 } else { 2.0 };
        }
        let mut chol = BandCholesky::new(nb, 1, 1);
        assert_eq!(
            chol.factor(&a),
            Err(BandError::PivotNotPositiveDefinite { block: 1 })
        );
    }
}
