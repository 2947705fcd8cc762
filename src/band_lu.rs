//! LU factorisation with partial pivoting of a general banded matrix, LAPACK `gbtrf`/`gbtrs`
//! style, and a 1-norm condition estimate (Hager–Higham, as LAPACK's `gecon`). Pure linear
//! algebra: it knows nothing of chains or filters.
//!
//! Storage: `A(r, c)` with `c − ku ≤ r ≤ c + kl` lives at `ab[c · ld + kv + r − c]`, where
//! `kv = kl + ku` leaves room for the fill-in that row interchanges cause (`U` gets upper
//! bandwidth `kv`) and `ld = 2 kl + ku + 1`.

/// A banded matrix being assembled, then factorised in place by [`BandLu::factor`].
#[derive(Debug, Clone)]
pub struct BandLu {
    n: usize,
    kl: usize,
    ku: usize,
    ab: Vec<f64>,
    ipiv: Vec<usize>,
    /// `‖A‖₁`, recorded before factorisation.
    norm1: f64,
    /// First column with an exactly zero pivot, if any.
    zero_pivot: Option<usize>,
}

impl BandLu {
    /// A zero `n × n` matrix with `kl` sub- and `ku` super-diagonals.
    pub fn zeros(n: usize, kl: usize, ku: usize) -> Self {
        let ld = 2 * kl + ku + 1;
        Self {
            n,
            kl,
            ku,
            ab: vec![0.0; ld * n],
            ipiv: vec![0; n],
            norm1: 0.0,
            zero_pivot: None,
        }
    }

    /// Order of the matrix.
    pub fn n(&self) -> usize {
        self.n
    }

    fn ld(&self) -> usize {
        2 * self.kl + self.ku + 1
    }

    #[inline]
    fn idx(&self, r: usize, c: usize) -> usize {
        c * self.ld() + self.kl + self.ku + r - c
    }

    /// Sets `A(r, c)` (0-based) before factorisation; `(r, c)` must lie in the band.
    pub fn set(&mut self, r: usize, c: usize, v: f64) {
        assert!(
            r <= c + self.kl && c <= r + self.ku,
            "({r}, {c}) outside the band"
        );
        let k = self.idx(r, c);
        self.ab[k] = v;
    }

    /// Factorises `A = P L U` in place (partial pivoting). A zero pivot does not stop the
    /// factorisation; it is reported by [`BandLu::zero_pivot`].
    pub fn factor(&mut self) {
        let (n, kl, ku) = (self.n, self.kl, self.ku);
        let kv = kl + ku;
        self.norm1 = (0..n)
            .map(|c| {
                (c.saturating_sub(ku)..(c + kl + 1).min(n))
                    .map(|r| self.ab[self.idx(r, c)].abs())
                    .sum::<f64>()
            })
            .fold(0.0, f64::max);
        self.zero_pivot = None;
        let ld = self.ld();
        let mut ju = 0;
        for j in 0..n {
            let km = kl.min(n - 1 - j);
            let col = j * ld + kv;
            let mut jp = 0;
            let mut best = self.ab[col].abs();
            for r in 1..=km {
                if self.ab[col + r].abs() > best {
                    best = self.ab[col + r].abs();
                    jp = r;
                }
            }
            self.ipiv[j] = j + jp;
            if best == 0.0 {
                self.zero_pivot.get_or_insert(j);
                continue;
            }
            ju = ju.max((j + ku + jp).min(n - 1));
            if jp != 0 {
                for c in j..=ju {
                    let (a, b) = (self.idx(j, c), self.idx(j + jp, c));
                    self.ab.swap(a, b);
                }
            }
            let pivot = self.ab[col];
            for r in 1..=km {
                self.ab[col + r] /= pivot;
            }
            for c in j + 1..=ju {
                let a = self.ab[self.idx(j, c)];
                if a != 0.0 {
                    let base = self.idx(j, c);
                    for r in 1..=km {
                        self.ab[base + r] -= self.ab[col + r] * a;
                    }
                }
            }
        }
    }

    /// First column (0-based) whose pivot is exactly zero: the matrix is singular.
    pub fn zero_pivot(&self) -> Option<usize> {
        self.zero_pivot
    }

    /// Solves `A x = b` in place. Requires a factorised matrix without zero pivot.
    pub fn solve(&self, b: &mut [f64]) {
        let (n, kl, kv) = (self.n, self.kl, self.kl + self.ku);
        let ld = self.ld();
        for j in 0..n.saturating_sub(1) {
            let l = self.ipiv[j];
            if l != j {
                b.swap(l, j);
            }
            let bj = b[j];
            if bj != 0.0 {
                let col = j * ld + kv;
                for r in 1..=kl.min(n - 1 - j) {
                    b[j + r] -= self.ab[col + r] * bj;
                }
            }
        }
        for j in (0..n).rev() {
            let col = j * ld + kv;
            b[j] /= self.ab[col];
            let bj = b[j];
            if bj != 0.0 {
                for r in j.saturating_sub(kv)..j {
                    b[r] -= self.ab[col + r - j] * bj;
                }
            }
        }
    }

    /// Solves `Aᵀ x = b` in place.
    pub fn solve_transpose(&self, b: &mut [f64]) {
        let (n, kl, kv) = (self.n, self.kl, self.kl + self.ku);
        let ld = self.ld();
        for j in 0..n {
            let col = j * ld + kv;
            let mut s = b[j];
            for r in j.saturating_sub(kv)..j {
                s -= self.ab[col + r - j] * b[r];
            }
            b[j] = s / self.ab[col];
        }
        for j in (0..n.saturating_sub(1)).rev() {
            let col = j * ld + kv;
            let mut s = b[j];
            for r in 1..=kl.min(n - 1 - j) {
                s -= self.ab[col + r] * b[j + r];
            }
            b[j] = s;
            let l = self.ipiv[j];
            if l != j {
                b.swap(l, j);
            }
        }
    }

    /// Estimate of the 1-norm condition number `‖A‖₁ ‖A⁻¹‖₁` (Hager's method with Higham's
    /// extra test vector, as LAPACK's `dlacn2`); a lower bound, usually within a factor 3.
    /// Infinite when a pivot is zero.
    pub fn condition_estimate(&self) -> f64 {
        let n = self.n;
        if n == 0 {
            return 1.0;
        }
        if self.zero_pivot.is_some() {
            return f64::INFINITY;
        }
        let mut x = vec![1.0 / n as f64; n];
        let mut est = 0.0f64;
        let mut last_j = usize::MAX;
        for iter in 0..5 {
            self.solve(&mut x);
            let new_est: f64 = x.iter().map(|v| v.abs()).sum();
            if iter > 0 && new_est <= est {
                est = est.max(new_est);
                break;
            }
            est = new_est;
            let mut z: Vec<f64> = x
                .iter()
                .map(|&v| if v >= 0.0 { 1.0 } else { -1.0 })
                .collect();
            self.solve_transpose(&mut z);
            let (j, zmax) = z
                .iter()
                .enumerate()
                .map(|(k, v)| (k, v.abs()))
                .fold((0, -1.0), |a, b| if b.1 > a.1 { b } else { a });
            if j == last_j || (iter > 0 && zmax <= z[last_j].abs()) {
                break;
            }
            last_j = j;
            x.iter_mut().for_each(|v| *v = 0.0);
            x[j] = 1.0;
        }
        // Higham's alternating test vector guards against Hager's worst cases.
        let mut alt: Vec<f64> = (0..n)
            .map(|k| {
                let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
                sign * (1.0 + k as f64 / (n.max(2) - 1) as f64)
            })
            .collect();
        self.solve(&mut alt);
        let alt_est = 2.0 * alt.iter().map(|v| v.abs()).sum::<f64>() / (3.0 * n as f64);
        self.norm1 * est.max(alt_est)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use rand::{RngExt, SeedableRng};

    fn random_band(n: usize, kl: usize, ku: usize, seed: u64) -> (BandLu, DMatrix<f64>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut lu = BandLu::zeros(n, kl, ku);
        let mut dense = DMatrix::zeros(n, n);
        for r in 0..n {
            for c in r.saturating_sub(kl)..(r + ku + 1).min(n) {
                // Small diagonal forces pivoting.
                let v: f64 = rng.random_range(-1.0..1.0) * if r == c { 0.01 } else { 1.0 };
                lu.set(r, c, v);
                dense[(r, c)] = v;
            }
        }
        (lu, dense)
    }

    #[test]
    fn solves_match_dense_lu() {
        for (n, kl, ku) in [(1, 0, 0), (5, 1, 2), (30, 3, 1), (40, 4, 4), (7, 6, 6)] {
            let (mut lu, dense) = random_band(n, kl, ku, n as u64);
            lu.factor();
            assert!(lu.zero_pivot().is_none());
            let b = DVector::from_fn(n, |i, _| (i as f64 + 1.0).sin());
            let exact = dense.clone().lu().solve(&b).unwrap();
            let mut x = b.as_slice().to_vec();
            lu.solve(&mut x);
            let exact_t = dense.transpose().lu().solve(&b).unwrap();
            let mut xt = b.as_slice().to_vec();
            lu.solve_transpose(&mut xt);
            for k in 0..n {
                assert!((x[k] - exact[k]).abs() <= 1e-9 * exact.amax().max(1.0));
                assert!((xt[k] - exact_t[k]).abs() <= 1e-9 * exact_t.amax().max(1.0));
            }
        }
    }

    #[test]
    fn condition_estimate_is_close_to_exact() {
        let (mut lu, dense) = random_band(25, 2, 3, 7);
        lu.factor();
        let inv = dense.clone().try_inverse().unwrap();
        let norm1 = |m: &DMatrix<f64>| {
            (0..m.ncols())
                .map(|c| m.column(c).abs().sum())
                .fold(0.0, f64::max)
        };
        let exact = norm1(&dense) * norm1(&inv);
        let est = lu.condition_estimate();
        assert!(
            est <= exact * (1.0 + 1e-9) && est >= exact / 3.0,
            "{est} vs {exact}"
        );
    }

    #[test]
    fn singular_matrix_reports_zero_pivot() {
        let mut lu = BandLu::zeros(3, 1, 1);
        lu.set(0, 0, 1.0);
        lu.set(0, 1, 2.0);
        lu.set(1, 0, 2.0);
        lu.set(1, 1, 4.0);
        lu.set(2, 2, 1.0);
        lu.factor();
        assert_eq!(lu.zero_pivot(), Some(1));
        assert!(lu.condition_estimate().is_infinite());
    }
}
