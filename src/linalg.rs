//! Small dense kernels on flat slices, shared by the simulator and the filters.

use nalgebra::{DMatrix, SymmetricEigen};

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
