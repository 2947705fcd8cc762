//! Dense kernels of the lifted (centralized) filter and smoother (docs/theory.md §7) on
//! column-major matrices: faer's blocked products, triangular solves, Cholesky and LU factors,
//! each product and solve split by columns over the rayon threads (faer's own parallelism
//! would bring a scheduler and its dependency tree of its own). Each kernel runs with subnormal
//! numbers flushed to zero ([`FlushSubnormals`], docs/theory.md §7).

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::{cholesky_in_place, cholesky_in_place_scratch};
use faer::linalg::lu::partial_pivoting::factor::{lu_in_place, lu_in_place_scratch};
use faer::linalg::lu::partial_pivoting::solve::{
    solve_in_place as lu_solve_in_place, solve_in_place_scratch as lu_solve_scratch,
};
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::reborrow::ReborrowMut;
use faer::{Accum, MatMut, MatRef, Par};

use crate::linalg::subnormal::FlushSubnormals;

/// Fewer columns than this are not split between threads: the product would be too short to
/// pay for the hand-over.
const MIN_SPLIT_COLUMNS: usize = 64;

/// `dst ← α lhs rhs`, or `dst ← dst + α lhs rhs` with `Accum::Add`, on the rayon threads.
pub fn product(
    dst: MatMut<'_, f64>,
    accum: Accum,
    lhs: MatRef<'_, f64>,
    rhs: MatRef<'_, f64>,
    alpha: f64,
) {
    product_in(dst, accum, lhs, rhs, alpha, rayon::current_num_threads());
}

fn product_in(
    dst: MatMut<'_, f64>,
    accum: Accum,
    lhs: MatRef<'_, f64>,
    rhs: MatRef<'_, f64>,
    alpha: f64,
    pieces: usize,
) {
    by_columns(dst, 0, pieces, &|dst, first| {
        let rhs = rhs.subcols(first, dst.ncols());
        matmul(dst, accum, lhs, rhs, alpha, Par::Seq);
    });
}

/// `work(part, first)` on `pieces` parts of `dst`'s columns (`first` the part's first column
/// in `dst`, offset by `offset`), on the rayon threads, with subnormal numbers flushed.
fn by_columns(
    dst: MatMut<'_, f64>,
    offset: usize,
    pieces: usize,
    work: &(dyn Fn(MatMut<'_, f64>, usize) + Sync),
) {
    let cols = dst.ncols();
    if pieces < 2 || cols < 2 * MIN_SPLIT_COLUMNS {
        let _flush = FlushSubnormals::new();
        work(dst, offset);
        return;
    }
    let first = pieces / 2;
    let split = cols * first / pieces;
    let (d1, d2) = dst.split_at_col_mut(split);
    rayon::join(
        || by_columns(d1, offset, first, work),
        || by_columns(d2, offset + split, pieces - first, work),
    );
}

/// `rhs ← L⁻¹ rhs` for a lower triangular `L` (only its lower triangle is read), on the rayon
/// threads.
pub fn solve_lower(l: MatRef<'_, f64>, rhs: MatMut<'_, f64>) {
    solve_in(l, rhs, rayon::current_num_threads(), false);
}

/// `rhs ← L⁻ᵀ rhs` for a lower triangular `L` (only its lower triangle is read), on the
/// rayon threads.
pub fn solve_lower_transposed(l: MatRef<'_, f64>, rhs: MatMut<'_, f64>) {
    solve_in(l, rhs, rayon::current_num_threads(), true);
}

/// `rhs ← L⁻¹ rhs`, or `L⁻ᵀ rhs` when `transposed`, in `pieces` parts of `rhs`'s columns.
fn solve_in(l: MatRef<'_, f64>, rhs: MatMut<'_, f64>, pieces: usize, transposed: bool) {
    by_columns(rhs, 0, pieces, &|rhs, _| match transposed {
        false => solve_lower_triangular_in_place(l, rhs, Par::Seq),
        true => solve_upper_triangular_in_place(l.transpose(), rhs, Par::Seq),
    });
}

/// `dst ← α lhs rhs`, or `dst ← dst + α lhs rhs` with `Accum::Add`, for a square `dst`
/// known to be symmetric (as is `P − Vᵀ V` or `(A P) Aᵀ`): only its lower triangle is
/// computed, on the rayon threads, and then copied to the upper one: half the work of
/// [`product`], and an exactly symmetric result.
pub fn symmetric_product(
    mut dst: MatMut<'_, f64>,
    accum: Accum,
    lhs: MatRef<'_, f64>,
    rhs: MatRef<'_, f64>,
    alpha: f64,
) {
    lower_product_in(
        dst.rb_mut(),
        accum,
        lhs,
        rhs,
        alpha,
        rayon::current_num_threads(),
    );
    mirror_lower(dst);
}

/// Copies the strict lower triangle of a square `dst` to its upper one.
pub fn mirror_lower(mut dst: MatMut<'_, f64>) {
    for c in 0..dst.ncols() {
        for r in c + 1..dst.nrows() {
            dst[(c, r)] = dst[(r, c)];
        }
    }
}

/// The lower triangle of `dst` (square) in `pieces` parts of equal work: the first `c`
/// columns (a triangle and the rectangle below it) and the triangle right of them.
fn lower_product_in(
    dst: MatMut<'_, f64>,
    accum: Accum,
    lhs: MatRef<'_, f64>,
    rhs: MatRef<'_, f64>,
    alpha: f64,
    pieces: usize,
) {
    let k = dst.ncols();
    if pieces < 2 || k < 2 * MIN_SPLIT_COLUMNS {
        let _flush = FlushSubnormals::new();
        triangular::matmul(
            dst,
            BlockStructure::TriangularLower,
            accum,
            lhs,
            BlockStructure::Rectangular,
            rhs,
            BlockStructure::Rectangular,
            alpha,
            Par::Seq,
        );
        return;
    }
    let first = pieces / 2;
    // The first c columns hold the share first / pieces of the triangle's k² / 2 entries:
    // c² / 2 + (k − c) c = (first / pieces) k² / 2.
    let share = first as f64 / pieces as f64;
    let c = ((k as f64 * (1.0 - (1.0 - share).sqrt())).round() as usize).clamp(1, k - 1);
    let (top_left, _, bottom_left, bottom_right) = dst.split_at_mut(c, c);
    let (lhs_top, lhs_bottom) = lhs.split_at_row(c);
    let (rhs_left, rhs_right) = rhs.split_at_col(c);
    rayon::join(
        || {
            lower_product_in(top_left, accum, lhs_top, rhs_left, alpha, first);
            product_in(bottom_left, accum, lhs_bottom, rhs_left, alpha, first);
        },
        || {
            lower_product_in(
                bottom_right,
                accum,
                lhs_bottom,
                rhs_right,
                alpha,
                pieces - first,
            )
        },
    );
}

/// The lower Cholesky factor `L` of a symmetric positive definite matrix, in place (its lower
/// triangle; the strict upper one is left as it was), with its scratch kept between calls.
pub struct Cholesky {
    scratch: MemBuffer,
    dim: usize,
}

impl Cholesky {
    /// Scratch for matrices up to `dim × dim`.
    pub fn new(dim: usize) -> Self {
        Self {
            scratch: MemBuffer::new(cholesky_in_place_scratch::<f64>(
                dim,
                Par::Seq,
                Default::default(),
            )),
            dim,
        }
    }

    /// Factors `a` in place; `false` when it is not positive definite (a pivot ≤ 0).
    pub fn factor(&mut self, a: MatMut<'_, f64>) -> bool {
        assert!(
            a.nrows() <= self.dim,
            "Cholesky scratch sized for {}",
            self.dim
        );
        let stack = MemStack::new(&mut self.scratch);
        let _flush = FlushSubnormals::new();
        cholesky_in_place(a, Default::default(), Par::Seq, stack, Default::default()).is_ok()
    }
}

impl std::fmt::Debug for Cholesky {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Cholesky").field("dim", &self.dim).finish()
    }
}

impl Clone for Cholesky {
    fn clone(&self) -> Self {
        Self::new(self.dim)
    }
}

/// The LU factor with partial pivoting `A = Π L U` of a square matrix, in place (`L` unit
/// lower below the diagonal, `U` on and above it), with its permutation and scratch kept
/// between calls, and the solves by it.
pub struct Lu {
    scratch: MemBuffer,
    perm: Vec<usize>,
    perm_inv: Vec<usize>,
    dim: usize,
    rhs_cols: usize,
}

impl Lu {
    /// Scratch for matrices up to `dim × dim` and right-hand sides of up to `rhs_cols`
    /// columns.
    pub fn new(dim: usize, rhs_cols: usize) -> Self {
        Self {
            scratch: MemBuffer::new(StackReq::any_of(&[
                lu_in_place_scratch::<usize, f64>(dim, dim, Par::Seq, Default::default()),
                lu_solve_scratch::<usize, f64>(dim, rhs_cols, Par::Seq),
            ])),
            perm: vec![0; dim],
            perm_inv: vec![0; dim],
            dim,
            rhs_cols,
        }
    }

    /// Factors `a` in place and solves `a x = rhs` into `rhs`; `false` (and `rhs` untouched)
    /// when `a` is singular (a zero on `U`'s diagonal).
    pub fn factor_and_solve(&mut self, mut a: MatMut<'_, f64>, rhs: MatMut<'_, f64>) -> bool {
        let dim = a.nrows();
        assert!(
            dim <= self.dim && rhs.ncols() <= self.rhs_cols,
            "LU scratch sized for {} × {} and {} columns",
            self.dim,
            self.dim,
            self.rhs_cols
        );
        let _flush = FlushSubnormals::new();
        let (_, perm) = lu_in_place(
            a.rb_mut(),
            &mut self.perm[..dim],
            &mut self.perm_inv[..dim],
            Par::Seq,
            MemStack::new(&mut self.scratch),
            Default::default(),
        );
        let lu = a.as_ref();
        if (0..dim).any(|k| lu[(k, k)] == 0.0) {
            return false;
        }
        lu_solve_in_place(
            lu,
            lu,
            perm,
            rhs,
            Par::Seq,
            MemStack::new(&mut self.scratch),
        );
        true
    }
}

impl std::fmt::Debug for Lu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Lu").field("dim", &self.dim).finish()
    }
}

impl Clone for Lu {
    fn clone(&self) -> Self {
        Self::new(self.dim, self.rhs_cols)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fixed, well-conditioned test matrix.
    fn matrix(rows: usize, cols: usize, seed: f64) -> faer::Mat<f64> {
        faer::Mat::from_fn(rows, cols, |r, c| ((r * 7 + c * 13) as f64 * seed).sin())
    }

    #[test]
    fn split_products_and_solves_match_the_dense_definitions() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        let (a, b) = (matrix(150, 90, 0.37), matrix(90, 200, 0.11));
        let mut c = matrix(150, 200, 0.53);
        let expected = &c + (&a * &b) * 2.0;
        pool.install(|| product(c.as_mut(), Accum::Add, a.as_ref(), b.as_ref(), 2.0));
        assert!((&c - &expected).norm_max() < 1e-12);

        // A symmetric result from its lower triangle, split in three parts: S − 2 Vᵀ V.
        let v = matrix(90, 200, 0.23);
        let s = v.transpose() * &v + faer::Mat::<f64>::identity(200, 200);
        let mut sym = s.clone();
        pool.install(|| {
            symmetric_product(sym.as_mut(), Accum::Add, v.transpose(), v.as_ref(), -2.0)
        });
        let expected = &s - (v.transpose() * &v) * 2.0;
        assert!((&sym - &expected).norm_max() < 1e-12);
        assert!((&sym - sym.transpose()).norm_max() == 0.0);

        // L = lower triangle with a dominant diagonal; check L (L⁻¹ B) = B.
        let l = faer::Mat::from_fn(90, 90, |r, c| match r.cmp(&c) {
            std::cmp::Ordering::Equal => 3.0 + (r as f64).cos(),
            std::cmp::Ordering::Greater => 0.1 * ((r * c) as f64).sin(),
            std::cmp::Ordering::Less => f64::NAN,
        });
        let mut x = b.clone();
        pool.install(|| solve_lower(l.as_ref(), x.as_mut()));
        let l_lower = faer::Mat::from_fn(90, 90, |r, c| if r >= c { l[(r, c)] } else { 0.0 });
        assert!((&l_lower * &x - &b).norm_max() < 1e-12);
        // And Lᵀ (L⁻ᵀ B) = B.
        let mut x = b.clone();
        pool.install(|| solve_lower_transposed(l.as_ref(), x.as_mut()));
        assert!((l_lower.transpose() * &x - &b).norm_max() < 1e-12);

        // The factor of S = M Mᵀ + I reproduces S; an indefinite matrix is refused.
        let m = matrix(40, 40, 0.29);
        let s = &m * m.transpose() + faer::Mat::<f64>::identity(40, 40);
        let mut f = s.clone();
        assert!(Cholesky::new(40).factor(f.as_mut()));
        let low = faer::Mat::from_fn(40, 40, |r, c| if r >= c { f[(r, c)] } else { 0.0 });
        assert!((&low * low.transpose() - &s).norm_max() < 1e-12);
        let mut indefinite = -s;
        assert!(!Cholesky::new(40).factor(indefinite.as_mut()));
    }
}
