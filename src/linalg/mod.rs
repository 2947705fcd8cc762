//! The linear algebra of `sisfilt`, in one tree: the dense helpers below (on flat slices and
//! nalgebra matrices), [`band_lu`] (the banded LU of the chain solve, docs/theory.md §2) and
//! [`band`] (the block-banded symmetric and general matrices of the joint filter and its
//! smoother, docs/theory.md §8–§9).

pub mod band;
pub mod band_lu;

use nalgebra::{DMatrix, Dim, Matrix, StorageMut, SymmetricEigen};

/// `M ← (M + Mᵀ) / 2` for a square matrix of any size and storage: every covariance is
/// symmetrised after it is formed, since rounding leaves it slightly asymmetric
/// (docs/theory.md §12). A flat column-major block is symmetrised through a view,
/// `symmetrize(&mut DMatrixViewMut::from_slice(c, m, m))`.
pub fn symmetrize<D: Dim, S: StorageMut<f64, D, D>>(m: &mut Matrix<f64, D, D, S>) {
    let n = m.nrows();
    for c in 0..n {
        for r in c + 1..n {
            let v = 0.5 * (m[(r, c)] + m[(c, r)]);
            m[(r, c)] = v;
            m[(c, r)] = v;
        }
    }
}

/// `out += A x` for a column-major `A` (`out.len() = A.nrows()`, `x.len() = A.ncols()`).
#[inline]
pub fn mat_vec_add(out: &mut [f64], a: &DMatrix<f64>, x: &[f64]) {
    let rows = a.nrows();
    debug_assert_eq!(out.len(), rows);
    debug_assert_eq!(x.len(), a.ncols());
    for (c, &xc) in x.iter().enumerate() {
        if xc != 0.0 {
            let col = &a.as_slice()[c * rows..(c + 1) * rows];
            for (o, &acol) in out.iter_mut().zip(col) {
                *o += acol * xc;
            }
        }
    }
}

/// A square root `F` with `F Fᵀ = S` of a symmetric positive semidefinite `S`, from its
/// eigendecomposition (`F = U √Λ`, negative rounding-level eigenvalues set to zero). Unlike a
/// Cholesky factor it exists for singular `S` (e.g. `Q = 0`).
pub fn psd_sqrt(s: &DMatrix<f64>) -> DMatrix<f64> {
    if s.is_empty() || s.amax() == 0.0 {
        return DMatrix::zeros(s.nrows(), s.ncols());
    }
    let eig = SymmetricEigen::new(s.clone());
    let mut f = eig.eigenvectors;
    for (k, &l) in eig.eigenvalues.iter().enumerate() {
        let r = l.max(0.0).sqrt();
        f.column_mut(k).scale_mut(r);
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psd_sqrt_reproduces_matrix() {
        let s = DMatrix::from_row_slice(3, 3, &[4.0, 2.0, 0.0, 2.0, 2.0, 0.0, 0.0, 0.0, 0.0]);
        let f = psd_sqrt(&s);
        assert!((&f * f.transpose() - &s).amax() < 1e-14);
    }

    #[test]
    fn mat_vec_add_matches_nalgebra() {
        let a = DMatrix::from_row_slice(2, 3, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let mut out = [1.0, 1.0];
        mat_vec_add(&mut out, &a, &[1.0, 0.5, -1.0]);
        assert_eq!(out, [1.0 + 1.0 + 1.0 - 3.0, 1.0 + 4.0 + 2.5 - 6.0]);
    }
}
