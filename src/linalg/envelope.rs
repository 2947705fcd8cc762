//! A square matrix kept by the stretch of each row between its first and last nonzero (its
//! row envelope), and its product from the right, `X Aᵀ`, as long column sums: the lifted
//! `A_eff` of a chain without algebraic interconnection (`G = 0`) is block banded, and its
//! covariance step `A_eff X A_effᵀ` then costs `O((N n)²)` instead of a dense product's
//! `O((N n)³)` (docs/theory.md §7).

use faer::MatRef;
use rayon::prelude::*;

use crate::linalg::subnormal::FlushSubnormals;

/// Fewer columns than this are not split between threads: the product would be too short to
/// pay for the hand-over.
const MIN_PARALLEL_SIZE: usize = 128;

/// Columns of the product a thread takes at a time.
const COLUMNS_PER_TASK: usize = 16;

/// The row envelope of a square matrix `A`: row `r`'s entries from column `first[r]` on,
/// `values[offsets[r]..offsets[r + 1]]` (an empty row has none).
#[derive(Debug, Clone)]
pub struct RowEnvelope {
    size: usize,
    first: Vec<usize>,
    offsets: Vec<usize>,
    values: Vec<f64>,
}

impl RowEnvelope {
    /// The envelope of `a` (square): its entries outside it are exactly zero.
    pub fn of(a: MatRef<'_, f64>) -> Self {
        let size = a.nrows();
        assert_eq!(a.ncols(), size, "a square matrix");
        let mut first = Vec::with_capacity(size);
        let mut offsets = Vec::with_capacity(size + 1);
        let mut values = Vec::new();
        offsets.push(0);
        for r in 0..size {
            let nonzero = |&c: &usize| a[(r, c)] != 0.0;
            let lo = (0..size).find(nonzero).unwrap_or(size);
            let hi = (0..size).rev().find(nonzero).map_or(lo, |c| c + 1);
            first.push(lo);
            values.extend((lo..hi).map(|c| a[(r, c)]));
            offsets.push(values.len());
        }
        Self {
            size,
            first,
            offsets,
            values,
        }
    }

    /// The mean number of entries a row keeps.
    pub fn mean_width(&self) -> f64 {
        self.values.len() as f64 / self.size.max(1) as f64
    }

    /// `out ← X Aᵀ` for `X` and `out` column-major `size × size`: column `c` of `out` is
    /// `Σ_k A[c, k] X[:, k]` over row `c`'s envelope, sums of whole columns of `X`. With
    /// `lower`, only the rows `c..` of column `c` are formed (the rest is left as it was);
    /// with `add`, the product is added to `out`. Split by columns over the rayon threads on
    /// large matrices.
    pub fn times_transposed(&self, x: &[f64], out: &mut [f64], lower: bool, add: bool) {
        let size = self.size;
        assert!(x.len() == size * size && out.len() == size * size);
        let column = |c: usize, col: &mut [f64]| {
            let from = if lower { c } else { 0 };
            let col = &mut col[from..];
            if !add {
                col.fill(0.0);
            }
            let row = &self.values[self.offsets[c]..self.offsets[c + 1]];
            let x_col = |k: usize| &x[k * size + from..(k + 1) * size];
            // Four columns of X at a time: one pass over the column of `out` for each four.
            let mut k = self.first[c];
            let mut fours = row.chunks_exact(4);
            for a in fours.by_ref() {
                let len = col.len();
                let (x0, x1) = (&x_col(k)[..len], &x_col(k + 1)[..len]);
                let (x2, x3) = (&x_col(k + 2)[..len], &x_col(k + 3)[..len]);
                for (i, o) in col.iter_mut().enumerate() {
                    *o += a[0] * x0[i] + a[1] * x1[i] + a[2] * x2[i] + a[3] * x3[i];
                }
                k += 4;
            }
            for &a in fours.remainder() {
                for (o, v) in col.iter_mut().zip(x_col(k)) {
                    *o += a * v;
                }
                k += 1;
            }
        };
        if size < MIN_PARALLEL_SIZE {
            let _flush = FlushSubnormals::new();
            for (c, col) in out.chunks_exact_mut(size).enumerate() {
                column(c, col);
            }
            return;
        }
        out.par_chunks_mut(size * COLUMNS_PER_TASK)
            .enumerate()
            .for_each(|(task, cols)| {
                let _flush = FlushSubnormals::new();
                for (k, col) in cols.chunks_exact_mut(size).enumerate() {
                    column(task * COLUMNS_PER_TASK + k, col);
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A banded matrix with a hole in its band and an empty row, and a symmetric `X`.
    fn banded(size: usize) -> faer::Mat<f64> {
        faer::Mat::from_fn(size, size, |r, c| {
            let near = r.abs_diff(c) <= 2 && (r + c) % 5 != 1 && r != 3;
            if near {
                ((r * 7 + c * 3) as f64 * 0.41).sin()
            } else {
                0.0
            }
        })
    }

    /// `X Aᵀ` by the envelope, whole and lower triangle, replaced and added, sequential and
    /// split over threads, against the dense product formed here.
    #[test]
    fn times_transposed_is_the_dense_product() {
        for size in [7, 300] {
            let a = banded(size);
            let env = RowEnvelope::of(a.as_ref());
            assert!(env.mean_width() <= 5.0);
            let x = faer::Mat::from_fn(size, size, |r, c| ((r * 13 + c * 5) as f64 * 0.23).cos());
            let start = faer::Mat::from_fn(size, size, |r, c| (r + 2 * c) as f64);
            let xs: Vec<f64> = (0..size * size).map(|k| x[(k % size, k / size)]).collect();
            for lower in [false, true] {
                for add in [false, true] {
                    let mut out: Vec<f64> = (0..size * size)
                        .map(|k| start[(k % size, k / size)])
                        .collect();
                    env.times_transposed(&xs, &mut out, lower, add);
                    for c in 0..size {
                        for r in 0..size {
                            let dense: f64 = (0..size).map(|k| x[(r, k)] * a[(c, k)]).sum();
                            let want = match (lower && r < c, add) {
                                (true, _) => start[(r, c)],
                                (false, true) => start[(r, c)] + dense,
                                (false, false) => dense,
                            };
                            let got = out[c * size + r];
                            assert!(
                                (got - want).abs() <= 1e-13 * (1.0 + want.abs()),
                                "size {size}, lower {lower}, add {add}: ({r}, {c}) {got} vs {want}"
                            );
                        }
                    }
                }
            }
        }
    }
}
