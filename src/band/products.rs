//! Banded products for the information-form smoother (SPEC §10 step 2) and band–vector
//! products.

use super::kernels::gemm_acc;
use super::{GenBand, SymBand};

/// Block `(l, m)` of a symmetric band and whether it is stored transposed; `None` outside.
#[inline]
pub(crate) fn sym_block(p: &SymBand, l: usize, m: usize) -> Option<(&[f64], bool)> {
    if l <= m {
        (m - l <= p.width()).then(|| (p.block(l, m - l), false))
    } else {
        (l - m <= p.width()).then(|| (p.block(m, l - m), true))
    }
}

/// `out = S A` for a symmetric band `S` (width `k`) and a general band `A` (half-width `b`);
/// `out` has half-width `min(k + b, nb − 1)`.
pub fn sym_times_gen(s: &SymBand, a: &GenBand, out: &mut GenBand) {
    let (nb, bs, k, b) = (a.nb(), a.bs(), s.width(), a.half_width());
    let hw = out.half_width();
    debug_assert!(hw >= (k + b).min(nb - 1));
    out.fill_zero();
    for l in 0..nb {
        for j in l.saturating_sub(hw)..=(l + hw).min(nb - 1) {
            let blk = out.block_mut(l, j);
            let lo = l.saturating_sub(k).max(j.saturating_sub(b));
            let hi = (l + k).min(j + b).min(nb - 1);
            for m in lo..=hi {
                if let Some((slm, tr)) = sym_block(s, l, m) {
                    gemm_acc(blk, 1.0, slm, tr, a.block(m, j), false, bs);
                }
            }
        }
    }
}

/// `out = band(Aᵀ W)` for general bands `A` (half-width `b`) and `W`, when the product is
/// symmetric (as `Aᵀ S A` is): the blocks `0 ≤ j − i ≤ out.width()`.
pub fn gen_t_times_gen(a: &GenBand, w: &GenBand, out: &mut SymBand) {
    let (nb, bs, b, hw) = (a.nb(), a.bs(), a.half_width(), w.half_width());
    out.fill_zero();
    for i in 0..nb {
        for j in i..=(i + out.width()).min(nb - 1) {
            let blk = out.block_mut(i, j - i);
            let lo = i.saturating_sub(b).max(j.saturating_sub(hw));
            let hi = (i + b).min(j + hw).min(nb - 1);
            for l in lo..=hi {
                gemm_acc(blk, 1.0, a.block(l, i), true, w.block(l, j), false, bs);
            }
        }
    }
}

impl SymBand {
    /// `out = S x`.
    pub fn mul_vec(&self, x: &[f64], out: &mut [f64]) {
        let (nb, bs, w) = (self.nb(), self.bs(), self.width());
        out.fill(0.0);
        for i in 0..nb {
            for j in i.saturating_sub(w)..=(i + w).min(nb - 1) {
                let (blk, tr) = sym_block(self, i, j).expect("inside the band");
                for c in 0..bs {
                    for r in 0..bs {
                        let v = if tr { blk[c + r * bs] } else { blk[r + c * bs] };
                        out[i * bs + r] += v * x[j * bs + c];
                    }
                }
            }
        }
    }
}

impl GenBand {
    /// `out = Aᵀ x`.
    pub fn mul_vec_transposed(&self, x: &[f64], out: &mut [f64]) {
        let (nb, bs, b) = (self.nb(), self.bs(), self.half_width());
        out.fill(0.0);
        for l in 0..nb {
            for i in l.saturating_sub(b)..=(l + b).min(nb - 1) {
                let blk = self.block(l, i);
                for c in 0..bs {
                    for r in 0..bs {
                        out[i * bs + c] += blk[r + c * bs] * x[l * bs + r];
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_spd(nb: usize, bs: usize, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
        let n = nb * bs;
        let f = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        &f * f.transpose() + DMatrix::identity(n, n) * (n as f64 * 0.1)
    }

    fn rel(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
        (a - b).amax() / b.amax().max(1e-300)
    }

    fn cases() -> Vec<(usize, usize, usize)> {
        let mut v = vec![];
        for nb in [1_usize, 2, 3, 6, 9] {
            for bs in [1, 2, 3] {
                for k in [0, 1, 2, nb - 1] {
                    v.push((nb, bs, k.min(nb - 1)));
                }
            }
        }
        v.push((5, 4, 2));
        v
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
}
