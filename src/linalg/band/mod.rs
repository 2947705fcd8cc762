//! Block-banded matrices and the operations of the joint band-`k` filter (docs/theory.md §8) and its
//! smoother (docs/theory.md §9): the precision of the maximum-entropy (Gauss–Markov) completion of a
//! band, the block-banded Cholesky factorisation with its solves, block selected inversion
//! (Takahashi) to any bandwidth, and the banded sandwich product `band_k(A P Aᵀ)`.
//!
//! Pure linear algebra: it knows nothing of chains or filters. Indices are 0-based. A matrix
//! of `nb × nb` blocks of size `bs × bs`; every block is stored column-major and contiguous,
//! and the blocks of one block row are adjacent, so a block row of a band is itself a
//! column-major `bs × (width+1)·bs` strip. Every operation costs `O(nb)` and allocates nothing
//! once its workspace exists (they run once per time step with `nb` up to 10⁵).

/// Calls `$body` (an `#[inline(always)]` fn whose first argument is the block size) with a
/// constant block size for `bs = 1..=4`, so each gets its own unrolled copy.
macro_rules! specialise {
    ($bs:expr, $body:ident($($arg:expr),*)) => {
        match $bs {
            1 => $body(1, $($arg),*),
            2 => $body(2, $($arg),*),
            3 => $body(3, $($arg),*),
            4 => $body(4, $($arg),*),
            bs => $body(bs, $($arg),*),
        }
    };
}

/// Calls `$body` (an `#[inline(always)]` fn whose first two arguments are the block size and
/// the bandwidth) with constants for `bs = 1..=4`, `k = 0..=3`.
macro_rules! specialise_bk {
    ($bs:expr, $k:expr, $body:ident($($arg:expr),*)) => {
        match ($bs, $k) {
            (1, 0) => $body(1, 0, $($arg),*),
            (1, 1) => $body(1, 1, $($arg),*),
            (1, 2) => $body(1, 2, $($arg),*),
            (1, 3) => $body(1, 3, $($arg),*),
            (2, 0) => $body(2, 0, $($arg),*),
            (2, 1) => $body(2, 1, $($arg),*),
            (2, 2) => $body(2, 2, $($arg),*),
            (2, 3) => $body(2, 3, $($arg),*),
            (3, 0) => $body(3, 0, $($arg),*),
            (3, 1) => $body(3, 1, $($arg),*),
            (3, 2) => $body(3, 2, $($arg),*),
            (3, 3) => $body(3, 3, $($arg),*),
            (4, 0) => $body(4, 0, $($arg),*),
            (4, 1) => $body(4, 1, $($arg),*),
            (4, 2) => $body(4, 2, $($arg),*),
            (4, 3) => $body(4, 3, $($arg),*),
            (bs, k) => $body(bs, k, $($arg),*),
        }
    };
}

// The one module with `unsafe` code: the AVX2 kernels, reached only through a detected token.
#[allow(unsafe_code)]
mod avx2;
mod cholesky;
mod completion;
mod products;
mod sandwich;
mod strips;

pub use avx2::Avx2Fma;
pub use cholesky::BandCholesky;
pub use completion::{CompletionWorkspace, completion_precision};
pub use products::{diag_t_times_gen, gen_t_times_gen, sym_times_gen};
pub use sandwich::{SandwichWorkspace, sandwich};
pub use strips::gemm_acc;

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

    /// All block rows, one strip after the other (see [`SymBand::row_strip`]).
    #[inline]
    pub(crate) fn data_mut(&mut self) -> &mut [f64] {
        &mut self.data
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
        assert!(bs > 0 && a.nrows() == a.ncols() && a.nrows().is_multiple_of(bs));
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

    /// Block row `i` as a mutable strip; see [`GenBand::row_strip`]. Keep the slots outside
    /// the matrix zero.
    #[inline]
    pub fn row_strip_mut(&mut self, i: usize) -> &mut [f64] {
        let len = (2 * self.b + 1) * self.bs * self.bs;
        &mut self.data[i * len..(i + 1) * len]
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
        assert!(bs > 0 && a.nrows() == a.ncols() && a.nrows().is_multiple_of(bs));
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
