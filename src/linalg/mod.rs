//! The linear algebra of `sisfilt`, in one tree: the dense helpers below (on flat slices and
//! nalgebra matrices), [`band_lu`] (the banded LU of the chain solve, docs/theory.md §2) and
//! [`band`] (the block-banded symmetric and general matrices of the joint filter and its
//! smoother, docs/theory.md §8–§9).

pub mod band;
pub mod band_lu;
pub mod dense;
pub mod envelope;
pub mod subnormal;

use nalgebra::{DMatrix, Dim, Matrix, SimdRealField, StorageMut, SymmetricEigen};

/// `M ← (M + Mᵀ) / 2` for a square matrix of any size and storage: every covariance is
/// symmetrised after it is formed, since rounding leaves it slightly asymmetric
/// (docs/theory.md §12). A flat column-major block is symmetrised through a view,
/// `symmetrize(&mut DMatrixViewMut::from_slice(c, m, m))`. Any real scalar, `f64` or one
/// holding several subsystems' values (the two-step filter's lanes).
pub fn symmetrize<T, D, S>(m: &mut Matrix<T, D, D, S>)
where
    T: SimdRealField + Copy,
    D: Dim,
    S: StorageMut<T, D, D>,
{
    let n = m.nrows();
    let half: T = nalgebra::convert(0.5);
    for c in 0..n {
        for r in c + 1..n {
            let v = half * (m[(r, c)] + m[(c, r)]);
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

/// Whether every value is finite: `Σ 0·v` is `±0` when they all are and NaN when one is
/// infinite or NaN. Eight independent sums and no early exit, so that the loop runs on
/// vectors: the per-step check that no estimate has overflowed costs a fraction of a pass.
pub fn all_finite(values: &[f64]) -> bool {
    let mut sums = [0.0; 8];
    let mut chunks = values.chunks_exact(8);
    for chunk in &mut chunks {
        for (s, &v) in sums.iter_mut().zip(chunk) {
            *s += 0.0 * v;
        }
    }
    let rest = chunks.remainder().iter().map(|&v| 0.0 * v);
    sums.into_iter().chain(rest).sum::<f64>() == 0.0
}

/// The first block (0-based) of `width` values that holds a value that is not finite, if any:
/// one [`all_finite`] pass when every value is finite, the search block by block only
/// otherwise.
pub fn first_non_finite_block(values: &[f64], width: usize) -> Option<usize> {
    if all_finite(values) {
        return None;
    }
    values
        .chunks(width.max(1))
        .position(|block| !block.iter().all(|v| v.is_finite()))
}

/// `out_b += A x_b` for every block `b` of `out` (`A.nrows()` values each) and of `x`
/// (`A.ncols()` each): many subsystems' [`mat_vec_add`] with one matrix, each element of
/// each block given the same operations in the same order; compile-time sizes up to 4 × 4.
/// Unlike [`mat_vec_add`] it does not skip the zero elements of `x` (a branch per element
/// that keeps the loop from running blocks side by side); with a finite `A`, adding their
/// `±0` products changes no bit of an `out` that holds no `−0`.
pub fn mat_vec_add_blocks(out: &mut [f64], a: &DMatrix<f64>, x: &[f64]) {
    mat_vec_blocks_with::<true>(out, a, x);
}

/// `out_b = A x_b` for every block: [`mat_vec_add_blocks`] on a zeroed `out` (the same bits,
/// each sum starts from `0`) without a pass to zero it.
pub fn mat_vec_blocks(out: &mut [f64], a: &DMatrix<f64>, x: &[f64]) {
    mat_vec_blocks_with::<false>(out, a, x);
}

/// [`mat_vec_add_blocks`] (`ADD`) or [`mat_vec_blocks`].
fn mat_vec_blocks_with<const ADD: bool>(out: &mut [f64], a: &DMatrix<f64>, x: &[f64]) {
    macro_rules! fixed {
        ($(($r:literal, $c:literal)),*) => {
            match a.shape() {
                $(($r, $c) => blocks_fixed::<$r, $c, ADD>(out, a, x),)*
                (rows, cols) if rows > 0 && cols > 0 => {
                    let blocks = out.chunks_exact_mut(rows).zip(x.chunks_exact(cols));
                    blocks.for_each(|(out, x)| {
                        if !ADD {
                            out.fill(0.0);
                        }
                        mat_vec_add(out, a, x)
                    });
                }
                _ if !ADD => out.fill(0.0),
                _ => {}
            }
        };
    }
    fixed!(
        (1, 1),
        (1, 2),
        (1, 3),
        (1, 4),
        (2, 1),
        (2, 2),
        (2, 3),
        (2, 4),
        (3, 1),
        (3, 2),
        (3, 3),
        (3, 4),
        (4, 1),
        (4, 2),
        (4, 3),
        (4, 4)
    )
}

/// [`mat_vec_blocks_with`] for an `R × C` matrix.
fn blocks_fixed<const R: usize, const C: usize, const ADD: bool>(
    out: &mut [f64],
    a: &DMatrix<f64>,
    x: &[f64],
) {
    let a: [[f64; R]; C] = std::array::from_fn(|c| std::array::from_fn(|r| a[(r, c)]));
    for (out, x) in out.chunks_exact_mut(R).zip(x.chunks_exact(C)) {
        let mut sum: [f64; R] = if ADD {
            (*out).try_into().expect("R values")
        } else {
            [0.0; R]
        };
        for (col, &xc) in a.iter().zip(x) {
            for (s, &arc) in sum.iter_mut().zip(col) {
                *s += arc * xc;
            }
        }
        out.copy_from_slice(&sum);
    }
}

/// `S_b = C_b + m_b m_bᵀ` for every column-major `n × n` block `S_b` of `s`, `C_b` of `cov`
/// (or the one block `cov` for every `b`, when it holds one block) and `n`-block `m_b` of `m`:
/// a second moment from a covariance and a mean, each element `C + m_r m_c`, in one pass;
/// compile-time sizes up to 4.
pub fn moment_blocks(s: &mut [f64], cov: &[f64], m: &[f64], n: usize) {
    fn blocks<'a, const N: usize>(
        s: &mut [f64],
        cov: impl Iterator<Item = &'a [f64]>,
        m: &[f64],
        n: usize,
    ) {
        // `N = 0` stands for a size known only at run time.
        let n = if N == 0 { n } else { N };
        for ((s, cov), m) in s.chunks_exact_mut(n * n).zip(cov).zip(m.chunks_exact(n)) {
            for c in 0..n {
                for r in 0..n {
                    s[c * n + r] = cov[c * n + r] + m[r] * m[c];
                }
            }
        }
    }
    fn fixed<const N: usize>(s: &mut [f64], cov: &[f64], m: &[f64], n: usize) {
        if cov.len() == s.len() {
            blocks::<N>(s, cov.chunks_exact(n * n), m, n);
        } else {
            blocks::<N>(s, std::iter::repeat(cov), m, n);
        }
    }
    debug_assert!(cov.len() == n * n || cov.len() == s.len());
    match n {
        1 => fixed::<1>(s, cov, m, n),
        2 => fixed::<2>(s, cov, m, n),
        3 => fixed::<3>(s, cov, m, n),
        4 => fixed::<4>(s, cov, m, n),
        _ => fixed::<0>(s, cov, m, n),
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

    /// Each block is nalgebra's `C + m mᵀ` to the bit (a product and a sum per element), with
    /// a covariance per block and with one for all, at every compile-time size and past them.
    #[test]
    fn moment_blocks_equal_covariance_plus_outer_product() {
        let blocks = 5;
        for n in 1..=5 {
            let nn = n * n;
            let value = |k: usize, seed: f64| ((k as f64 + seed) * 0.77).sin();
            let cov: Vec<f64> = (0..blocks * nn).map(|k| value(k, 0.3)).collect();
            let m: Vec<f64> = (0..blocks * n).map(|k| value(k, 1.9)).collect();
            for shared in [false, true] {
                let cov_of = |b: usize| {
                    if shared {
                        &cov[..nn]
                    } else {
                        &cov[b * nn..(b + 1) * nn]
                    }
                };
                let mut s = vec![f64::NAN; blocks * nn];
                moment_blocks(&mut s, if shared { &cov[..nn] } else { &cov }, &m, n);
                for b in 0..blocks {
                    let mb = nalgebra::DVector::from_column_slice(&m[b * n..(b + 1) * n]);
                    let want = DMatrix::from_column_slice(n, n, cov_of(b)) + &mb * mb.transpose();
                    let got = &s[b * nn..(b + 1) * nn];
                    let bits = |v: &[f64]| v.iter().map(|e| e.to_bits()).collect::<Vec<_>>();
                    assert_eq!(
                        bits(got),
                        bits(want.as_slice()),
                        "n = {n}, shared {shared}, block {b}"
                    );
                }
            }
        }
    }

    /// Against `iter().all(is_finite)` on every length to 20, with an infinity, a NaN or a
    /// largest finite value at each place, and zeros of both signs.
    #[test]
    fn all_finite_agrees_with_is_finite() {
        for len in 0..20 {
            let base: Vec<f64> = (0..len)
                .map(|k| match k % 3 {
                    0 => -0.0,
                    1 => 0.0,
                    _ => (k as f64).sin() * 1e300,
                })
                .collect();
            assert!(all_finite(&base), "{len}");
            for at in 0..len {
                for bad in [
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                    f64::NAN,
                    f64::MAX,
                    -f64::MAX,
                ] {
                    let mut v = base.clone();
                    v[at] = bad;
                    let want = v.iter().all(|x| x.is_finite());
                    assert_eq!(all_finite(&v), want, "{len}, {bad} at {at}");
                }
            }
        }
    }

    #[test]
    fn mat_vec_add_matches_nalgebra() {
        let a = DMatrix::from_row_slice(2, 3, &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let mut out = [1.0, 1.0];
        mat_vec_add(&mut out, &a, &[1.0, 0.5, -1.0]);
        assert_eq!(out, [1.0 + 1.0 + 1.0 - 3.0, 1.0 + 4.0 + 2.5 - 6.0]);
    }

    /// Every shape with a compile-time loop and past them, inputs with zeros of both signs:
    /// each block has the bits of `mat_vec_add` on it (which skips the zeros), and is within
    /// rounding of nalgebra's product; `mat_vec_blocks` on a block of NaNs has the same bits
    /// (and zeros for a matrix without columns).
    #[test]
    fn mat_vec_add_blocks_equals_mat_vec_add_per_block() {
        let blocks = 7;
        for rows in 1..=3 {
            let mut set = vec![f64::NAN; blocks * rows];
            mat_vec_blocks(&mut set, &DMatrix::zeros(rows, 0), &[]);
            assert!(set.iter().all(|&v| v.to_bits() == 0), "{rows}×0");
        }
        for rows in 1..=5 {
            for cols in 1..=5 {
                let a = DMatrix::from_fn(rows, cols, |r, c| ((r * 7 + c * 3) as f64 * 0.9).sin());
                let x: Vec<f64> = (0..blocks * cols)
                    .map(|k| match k % 4 {
                        0 => 0.0,
                        1 => -0.0,
                        _ => (k as f64 * 1.3).cos(),
                    })
                    .collect();
                let mut out = vec![0.0; blocks * rows];
                mat_vec_add_blocks(&mut out, &a, &x);
                let mut set = vec![f64::NAN; blocks * rows];
                mat_vec_blocks(&mut set, &a, &x);
                for b in 0..blocks {
                    let xb = &x[b * cols..(b + 1) * cols];
                    let mut one = vec![0.0; rows];
                    mat_vec_add(&mut one, &a, xb);
                    let got = &out[b * rows..(b + 1) * rows];
                    let bits = |v: &[f64]| v.iter().map(|e| e.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(got), bits(&one), "{rows}×{cols}, block {b}");
                    let got_set = &set[b * rows..(b + 1) * rows];
                    assert_eq!(bits(got_set), bits(&one), "set, {rows}×{cols}, block {b}");
                    let exact = &a * nalgebra::DVector::from_column_slice(xb);
                    for (g, e) in got.iter().zip(exact.iter()) {
                        assert!((g - e).abs() <= 1e-14, "{rows}×{cols}, block {b}");
                    }
                }
            }
        }
    }
}
