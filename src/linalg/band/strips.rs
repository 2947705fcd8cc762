//! Small dense kernels on column-major slices for the block-band operations.
//!
//! A "strip" is a column-major `bs × n` matrix with leading dimension `bs`, i.e. `n`
//! consecutive columns of `bs` entries; a block row of a [`super::SymBand`] or
//! [`super::GenBand`] is one. The kernels take the block size at run time; the `_body`
//! versions are `#[inline(always)]`, so an operation specialised once per call on a constant
//! block size (see `specialise!` in the parent module) gets unrolled copies with the
//! accumulators in registers.

use super::avx2::Avx2Fma;

/// Largest block size with register accumulators.
const MAX_FIXED: usize = 4;

/// `C += sign · X Yᵀ` for strips `X`, `Y` of `bs × n` (`x.len() == y.len()`) and a
/// `bs × bs` block `C`: `C = Σ_c X[:, c] Y[:, c]ᵀ`, the product of two block rows.
#[inline]
pub fn nt_acc(bs: usize, c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
    specialise!(bs, nt_acc_body(c, x, y, sign))
}

#[inline(always)]
pub(super) fn nt_acc_body(bs: usize, c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
    debug_assert_eq!(x.len(), y.len());
    debug_assert_eq!(c.len(), bs * bs);
    if bs > MAX_FIXED {
        for (xc, yc) in x.chunks_exact(bs).zip(y.chunks_exact(bs)) {
            for s in 0..bs {
                let ys = sign * yc[s];
                for r in 0..bs {
                    c[r + s * bs] += xc[r] * ys;
                }
            }
        }
        return;
    }
    // Two sets of accumulators (even and odd columns) break the dependency chains.
    let mut acc0 = [0.0f64; MAX_FIXED * MAX_FIXED];
    let mut acc1 = [0.0f64; MAX_FIXED * MAX_FIXED];
    let mut xs = x.chunks_exact(2 * bs);
    let mut ys = y.chunks_exact(2 * bs);
    for (xc, yc) in (&mut xs).zip(&mut ys) {
        for s in 0..bs {
            for r in 0..bs {
                acc0[r + s * bs] += xc[r] * yc[s];
                acc1[r + s * bs] += xc[bs + r] * yc[bs + s];
            }
        }
    }
    let (xr, yr) = (xs.remainder(), ys.remainder());
    if !xr.is_empty() {
        for s in 0..bs {
            for r in 0..bs {
                acc0[r + s * bs] += xr[r] * yr[s];
            }
        }
    }
    for e in 0..bs * bs {
        c[e] += sign * (acc0[e] + acc1[e]);
    }
}

/// [`nt_acc`] for long strips: with the AVX2/FMA kernels (`simd`, from
/// [`Avx2Fma::detect`]) and `bs = 2` or `4` a vector kernel, otherwise the portable one.
#[inline]
pub fn nt_acc_fast(
    simd: Option<Avx2Fma>,
    bs: usize,
    c: &mut [f64],
    x: &[f64],
    y: &[f64],
    sign: f64,
) {
    match simd {
        Some(cpu) if bs == 2 || bs == 4 => cpu.nt_acc(bs, c, x, y, sign),
        _ => nt_acc(bs, c, x, y, sign),
    }
}

/// `out[:, c] = −Σ_{q<nq} M_qᵀ S_q[:, c]` for `bs × bs` blocks `M_q = mt[q bs²..]` given
/// transposed (`mt` holds `M_qᵀ`, column-major) and strips `S_q = base[q·stride..]` of the
/// same length as `out`; `nq = mt.len() / bs²`. With `simd` and `bs = 2` or `4` an AVX2/FMA
/// kernel.
#[inline]
pub fn tn_multi_neg(
    simd: Option<Avx2Fma>,
    bs: usize,
    out: &mut [f64],
    mt: &[f64],
    base: &[f64],
    stride: usize,
) {
    let nq = mt.len() / (bs * bs);
    if nq == 0 {
        out.fill(0.0);
        return;
    }
    assert!(
        base.len() >= (nq - 1) * stride + out.len(),
        "strips out of range"
    );
    match simd {
        Some(cpu) if bs == 2 || bs == 4 => cpu.tn_multi_neg(bs, out, mt, base, stride),
        _ => specialise!(bs, tn_multi_neg_body(out, mt, base, stride)),
    }
}

#[inline(always)]
fn tn_multi_neg_body(bs: usize, out: &mut [f64], mt: &[f64], base: &[f64], stride: usize) {
    let bb = bs * bs;
    out.fill(0.0);
    for (q, m) in mt.chunks_exact(bb).enumerate() {
        let s = &base[q * stride..q * stride + out.len()];
        for (oc, sc) in out.chunks_exact_mut(bs).zip(s.chunks_exact(bs)) {
            for t in 0..bs {
                let st = sc[t];
                for r in 0..bs {
                    oc[r] -= m[r + t * bs] * st;
                }
            }
        }
    }
}

/// `out += X S` for a `bs × bs` block `X` (column-major) and strips `S`, `out` of equal length:
/// one block times a block-row segment, the step of the band products. With `simd` and
/// `bs = 2` or `4` an AVX2/FMA kernel.
#[inline]
pub fn block_strip_acc(simd: Option<Avx2Fma>, bs: usize, out: &mut [f64], x: &[f64], s: &[f64]) {
    match simd {
        Some(cpu) if bs == 2 || bs == 4 => cpu.block_strip_acc(bs, out, x, s),
        _ => specialise!(bs, block_strip_acc_body(out, x, s)),
    }
}

#[inline(always)]
pub(super) fn block_strip_acc_body(bs: usize, out: &mut [f64], x: &[f64], s: &[f64]) {
    debug_assert_eq!(out.len(), s.len());
    for (oc, sc) in out.chunks_exact_mut(bs).zip(s.chunks_exact(bs)) {
        for t in 0..bs {
            let st = sc[t];
            for r in 0..bs {
                oc[r] += x[r + t * bs] * st;
            }
        }
    }
}

/// `C += alpha · op(A) op(B)` for `bs × bs` blocks, `op(X) = Xᵀ` when the flag is set.
#[inline(always)]
pub(super) fn block_mul_add_body(
    bs: usize,
    c: &mut [f64],
    alpha: f64,
    a: &[f64],
    ta: bool,
    b: &[f64],
    tb: bool,
) {
    for j in 0..bs {
        for i in 0..bs {
            let mut acc = 0.0;
            for t in 0..bs {
                let aij = if ta { a[t + i * bs] } else { a[i + t * bs] };
                let btj = if tb { b[j + t * bs] } else { b[t + j * bs] };
                acc += aij * btj;
            }
            c[i + j * bs] += alpha * acc;
        }
    }
}

/// In-place lower Cholesky factor `A = L Lᵀ` of a column-major `m × m` symmetric matrix whose
/// lower triangle is read; on return the lower triangle holds `L` and the strict upper
/// triangle is zero. Returns `false` when a pivot is not positive (or not finite): the matrix
/// is not numerically positive definite.
#[inline(always)]
pub fn chol_lower(m: usize, a: &mut [f64]) -> bool {
    let a = &mut a[..m * m];
    for j in 0..m {
        // L_jj² = A_jj − Σ_p L_jp², then L_ij = (A_ij − Σ_p L_ip L_jp) / L_jj.
        let mut d = a[j + j * m];
        for p in 0..j {
            d -= a[j + p * m] * a[j + p * m];
        }
        if d.is_nan() || d <= 0.0 || d.is_infinite() {
            return false;
        }
        let l = d.sqrt();
        let inv = 1.0 / l;
        a[j + j * m] = l;
        for i in j + 1..m {
            let mut v = a[i + j * m];
            for p in 0..j {
                v -= a[i + p * m] * a[j + p * m];
            }
            a[i + j * m] = v * inv;
            a[j + i * m] = 0.0;
        }
    }
    true
}

/// `Linv = L⁻¹` for a column-major lower triangular `m × m` `L` with positive diagonal
/// (forward substitution column by column; the strict upper triangle of `Linv` is zero).
#[inline(always)]
pub fn tri_lower_inv(m: usize, l: &[f64], linv: &mut [f64]) {
    linv.fill(0.0);
    for c in 0..m {
        // Solve L x = e_c; x[i] = 0 for i < c.
        let col = &mut linv[c * m..(c + 1) * m];
        col[c] = 1.0 / l[c + c * m];
        for i in c + 1..m {
            let mut acc = 0.0;
            for t in c..i {
                acc += l[i + t * m] * col[t];
            }
            col[i] = -acc / l[i + i * m];
        }
    }
}

/// `out += α · op(a) · op(b)` for square `n × n` blocks, `op(x) = xᵀ` when the flag is set
/// (the general block product of the smoother's band products).
#[inline]
pub fn gemm_acc(out: &mut [f64], alpha: f64, a: &[f64], ta: bool, b: &[f64], tb: bool, n: usize) {
    for c in 0..n {
        for k in 0..n {
            let bkc = alpha * if tb { b[c + k * n] } else { b[k + c * n] };
            if bkc == 0.0 {
                continue;
            }
            if ta {
                for r in 0..n {
                    out[r + c * n] += a[k + r * n] * bkc;
                }
            } else {
                let col = &a[k * n..(k + 1) * n];
                for (o, &av) in out[c * n..(c + 1) * n].iter_mut().zip(col) {
                    *o += av * bkc;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::DMatrix;

    fn mat(bs: usize, seed: u64) -> DMatrix<f64> {
        DMatrix::from_fn(bs, bs, |r, c| {
            ((seed as f64 + 1.3 * r as f64 + 0.7 * c as f64).sin() * 10.0).fract()
        })
    }

    #[test]
    fn nt_acc_matches_dense_for_every_block_size() {
        for bs in 1..=6 {
            for ncols in [1, 2, 3, 7] {
                let x = DMatrix::from_fn(bs, ncols * bs, |r, c| (r as f64 - 0.3 * c as f64).sin());
                let y = DMatrix::from_fn(bs, ncols * bs, |r, c| (0.5 * r as f64 + c as f64).cos());
                let c0 = mat(bs, 3);
                let mut c = c0.clone();
                nt_acc(bs, c.as_mut_slice(), x.as_slice(), y.as_slice(), -1.0);
                let expect = &c0 - &x * y.transpose();
                assert!((c - expect).amax() < 1e-13, "bs {bs}");
            }
        }
    }

    #[test]
    fn nt_acc_fast_matches_dense_for_every_length() {
        for (simd, bs) in [None, Avx2Fma::detect()]
            .into_iter()
            .flat_map(|s| (1..=5).map(move |b| (s, b)))
        {
            for ncols in 0..=21 {
                let x = DMatrix::from_fn(bs, ncols, |r, c| (r as f64 - 0.3 * c as f64).sin());
                let y = DMatrix::from_fn(bs, ncols, |r, c| (0.5 * r as f64 + c as f64).cos());
                let c0 = mat(bs, 3);
                let mut c = c0.clone();
                nt_acc_fast(simd, bs, c.as_mut_slice(), x.as_slice(), y.as_slice(), -1.0);
                let expect = &c0 - &x * y.transpose();
                assert!((c - expect).amax() < 1e-13, "bs {bs}, {ncols} columns");
            }
        }
    }

    #[test]
    fn tn_multi_neg_matches_dense() {
        for (simd, bs) in [None, Avx2Fma::detect()]
            .into_iter()
            .flat_map(|s| (1..=5).map(move |b| (s, b)))
        {
            for nq in 0..=3 {
                for ncols in [1, 2, 3, 4, 5, 7, 8, 13] {
                    let stride = ncols * bs + 3;
                    let base: Vec<f64> = (0..nq * stride + ncols * bs)
                        .map(|e| (0.37 * e as f64).sin())
                        .collect();
                    let ms: Vec<DMatrix<f64>> = (0..nq).map(|q| mat(bs, 10 + q as u64)).collect();
                    let mt: Vec<f64> = ms
                        .iter()
                        .flat_map(|m| m.transpose().as_slice().to_vec())
                        .collect();
                    let mut expect = DMatrix::zeros(bs, ncols);
                    for (q, m) in ms.iter().enumerate() {
                        let sq = DMatrix::from_column_slice(
                            bs,
                            ncols,
                            &base[q * stride..][..ncols * bs],
                        );
                        expect -= m.transpose() * sq;
                    }
                    let mut out = vec![f64::NAN; ncols * bs];
                    tn_multi_neg(simd, bs, &mut out, &mt, &base, stride);
                    let got = DMatrix::from_column_slice(bs, ncols, &out);
                    assert!(
                        (got - expect).amax() < 1e-13,
                        "bs {bs} nq {nq} ncols {ncols}"
                    );
                }
            }
        }
    }

    #[test]
    fn block_strip_acc_matches_dense() {
        for (simd, bs) in [None, Avx2Fma::detect()]
            .into_iter()
            .flat_map(|s| (1..=5).map(move |b| (s, b)))
        {
            for ncols in [0, 1, 2, 3, 4, 5, 9] {
                let s = DMatrix::from_fn(bs, ncols * bs, |r, c| (r as f64 - 0.3 * c as f64).sin());
                let o0 = DMatrix::from_fn(bs, ncols * bs, |r, c| (0.5 * r as f64 + c as f64).cos());
                let x = mat(bs, 7);
                let mut o = o0.clone();
                block_strip_acc(simd, bs, o.as_mut_slice(), x.as_slice(), s.as_slice());
                assert!(
                    (o - (&o0 + &x * &s)).amax() < 1e-13,
                    "bs {bs}, {ncols} blocks"
                );
            }
        }
    }

    #[test]
    fn block_mul_add_matches_dense() {
        for bs in 1..=6 {
            let (a, b, c0) = (mat(bs, 4), mat(bs, 5), mat(bs, 6));
            for (ta, tb) in [(false, false), (true, false), (false, true), (true, true)] {
                let mut c = c0.clone();
                block_mul_add_body(
                    bs,
                    c.as_mut_slice(),
                    -2.0,
                    a.as_slice(),
                    ta,
                    b.as_slice(),
                    tb,
                );
                let oa = if ta { a.transpose() } else { a.clone() };
                let ob = if tb { b.transpose() } else { b.clone() };
                assert!((c - (&c0 - 2.0 * oa * ob)).amax() < 1e-13);
            }
        }
    }

    #[test]
    fn cholesky_and_triangular_inverse_match_dense() {
        let m = 5;
        let g = DMatrix::from_fn(m, m, |r, c| ((r * 7 + c * 3) as f64).sin());
        let a = &g * g.transpose() + DMatrix::identity(m, m);
        let mut l = a.clone();
        assert!(chol_lower(m, l.as_mut_slice()));
        assert!((&l * l.transpose() - &a).amax() < 1e-12);
        let mut linv = DMatrix::zeros(m, m);
        tri_lower_inv(m, l.as_slice(), linv.as_mut_slice());
        assert!((&linv * &l - DMatrix::identity(m, m)).amax() < 1e-12);
        let mut bad = -a;
        assert!(!chol_lower(m, bad.as_mut_slice()));
    }
}
