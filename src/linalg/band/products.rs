//! Banded products for the information-form smoother (docs/theory.md §9 step 2) and band–vector
//! products.

use super::Avx2Fma;
use super::strips::block_strip_acc;
use super::{GenBand, SymBand};

/// One `bs × bs` scratch block: on the stack up to 4 × 4 (the kernels' fixed sizes), else on
/// the heap, so that the products allocate nothing for the common block sizes.
#[derive(Default)]
struct BlockScratch {
    small: [f64; 16],
    big: Vec<f64>,
}

impl BlockScratch {
    fn get(&mut self, bb: usize) -> &mut [f64] {
        if bb <= self.small.len() {
            &mut self.small[..bb]
        } else {
            self.big.resize(bb, 0.0);
            &mut self.big
        }
    }
}

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
/// `out` has half-width `min(k + b, nb − 1)`. Row `l` of the result is `Σ_m S_{l,m} A_{m,·}`:
/// each term is one block times a contiguous segment of block row `m` of `A`.
pub fn sym_times_gen(s: &SymBand, a: &GenBand, out: &mut GenBand) {
    let bs = a.bs();
    debug_assert!(out.half_width() >= (s.width() + a.half_width()).min(a.nb() - 1));
    specialise!(bs, sym_times_gen_body(s, a, out))
}

#[inline(always)]
fn sym_times_gen_body(bs: usize, s: &SymBand, a: &GenBand, out: &mut GenBand) {
    let (nb, k, b) = (a.nb(), s.width(), a.half_width());
    let (hw, bb) = (out.half_width(), bs * bs);
    let simd = Avx2Fma::detect();
    let mut scratch = BlockScratch::default();
    let x = scratch.get(bb);
    out.fill_zero();
    for l in 0..nb {
        let row = out.row_strip_mut(l);
        for m in l.saturating_sub(k)..=(l + k).min(nb - 1) {
            let (slm, tr) = sym_block(s, l, m).expect("inside the band");
            copy_block(bs, slm, tr, x);
            // Columns j = m−b..=m+b of A's row m; they lie within out's row l (|l − j| ≤ k + b).
            let (j0, j1) = (m.saturating_sub(b), (m + b).min(nb - 1));
            let src = &a.row_strip(m)[(j0 + b - m) * bb..(j1 + 1 + b - m) * bb];
            let dst = &mut row[(j0 + hw - l) * bb..(j1 + 1 + hw - l) * bb];
            block_strip_acc(simd, bs, dst, x, src);
        }
    }
}

/// `out = band(Aᵀ W)` for general bands `A` (half-width `b`) and `W`, when the product is
/// symmetric (as `Aᵀ S A` is): the blocks `0 ≤ j − i ≤ out.width()`. Row `i` of the result is
/// `Σ_l A_{l,i}ᵀ W_{l,·}`: each term is one block times a contiguous segment of row `l` of `W`.
pub fn gen_t_times_gen(a: &GenBand, w: &GenBand, out: &mut SymBand) {
    let bs = a.bs();
    specialise!(bs, gen_t_times_gen_body(a, w, out))
}

#[inline(always)]
fn gen_t_times_gen_body(bs: usize, a: &GenBand, w: &GenBand, out: &mut SymBand) {
    let (nb, b, hw) = (a.nb(), a.half_width(), w.half_width());
    let (width, bb) = (out.width(), bs * bs);
    let simd = Avx2Fma::detect();
    let mut scratch = BlockScratch::default();
    let x = scratch.get(bb);
    out.fill_zero();
    for i in 0..nb {
        let row = out.row_strip_mut(i);
        for l in i.saturating_sub(b)..=(i + b).min(nb - 1) {
            // Columns j = max(i, l − hw)..=min(i + width, l + hw) of W's row l.
            let j0 = i.max(l.saturating_sub(hw));
            let j1 = (i + width).min(l + hw).min(nb - 1);
            if j0 > j1 {
                continue;
            }
            copy_block(bs, a.block(l, i), true, x);
            let src = &w.row_strip(l)[(j0 + hw - l) * bb..(j1 + 1 + hw - l) * bb];
            let dst = &mut row[(j0 - i) * bb..(j1 + 1 - i) * bb];
            block_strip_acc(simd, bs, dst, x, src);
        }
    }
}

/// `out = Dᵀ W` for a block-diagonal `D = blkdiag(D_i)` (`d(i)` the column-major block `D_i`)
/// and a general band `W`; `out` has the shape of `W`. Row `i` is `D_iᵀ` times row `i` of `W`,
/// one block times a strip.
pub fn diag_t_times_gen<'a>(d: impl Fn(usize) -> &'a [f64], w: &GenBand, out: &mut GenBand) {
    assert_eq!(
        (out.nb(), out.bs(), out.half_width()),
        (w.nb(), w.bs(), w.half_width()),
        "out shape"
    );
    let bs = w.bs();
    specialise!(bs, diag_t_times_gen_body(&d, w, out))
}

#[inline(always)]
fn diag_t_times_gen_body<'a>(
    bs: usize,
    d: &impl Fn(usize) -> &'a [f64],
    w: &GenBand,
    out: &mut GenBand,
) {
    let bb = bs * bs;
    let simd = Avx2Fma::detect();
    let mut scratch = BlockScratch::default();
    let x = scratch.get(bb);
    for i in 0..w.nb() {
        copy_block(bs, d(i), true, x);
        let row = out.row_strip_mut(i);
        row.fill(0.0);
        block_strip_acc(simd, bs, row, x, w.row_strip(i));
    }
}

/// `x = blk` or `blkᵀ` (column-major `bs × bs`).
#[inline(always)]
fn copy_block(bs: usize, blk: &[f64], transpose: bool, x: &mut [f64]) {
    if transpose {
        for c in 0..bs {
            for r in 0..bs {
                x[r + c * bs] = blk[c + r * bs];
            }
        }
    } else {
        x.copy_from_slice(blk);
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
        v.push((4, 5, 1));
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
                let dg: Vec<DMatrix<f64>> = (0..nb)
                    .map(|_| DMatrix::from_fn(bs, bs, |_, _| rng.random_range(-1.0..1.0)))
                    .collect();
                let mut z = GenBand::zeros(nb, bs, k + b);
                diag_t_times_gen(|i| dg[i].as_slice(), &w, &mut z);
                let mut dd = DMatrix::zeros(n, n);
                for (i, blk) in dg.iter().enumerate() {
                    dd.view_mut((i * bs, i * bs), (bs, bs)).copy_from(blk);
                }
                assert!(
                    rel(&z.to_dense(), &(dd.transpose() * &sd * &ad)) < 1e-12,
                    "Dᵀ S A: {nb} {bs} {k} {b}"
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
