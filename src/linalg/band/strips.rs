//! Small dense kernels on column-major slices for the block-band operations.
//!
//! A "strip" is a column-major `bs × n` matrix with leading dimension `bs`, i.e. `n`
//! consecutive columns of `bs` entries; a block row of a [`super::SymBand`] or
//! [`super::GenBand`] is one. The kernels take the block size at run time; the `_body`
//! versions are `#[inline(always)]`, so an operation specialised once per call on a constant
//! block size (see `specialise!` in the parent module) gets unrolled copies with the
//! accumulators in registers.

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

/// Whether the AVX2 + FMA kernels of [`nt_acc_fast`] can run on this CPU (checked once per
/// operation by the caller; `std` caches the detection).
#[inline]
pub fn simd_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// [`nt_acc`] for long strips: with `simd` (from [`simd_available`]) and `bs = 2` or `4` it
/// runs an AVX2/FMA kernel, otherwise the portable one.
#[inline]
pub fn nt_acc_fast(simd: bool, bs: usize, c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
    #[cfg(target_arch = "x86_64")]
    if simd && (bs == 2 || bs == 4) {
        assert!(x.len() == y.len() && x.len() % bs == 0 && c.len() == bs * bs);
        // SAFETY: `simd` certifies AVX2 and FMA (see `simd_available`); lengths checked above.
        unsafe {
            if bs == 2 {
                avx2::nt_acc_2(c, x, y, sign)
            } else {
                avx2::nt_acc_4(c, x, y, sign)
            }
        };
        return;
    }
    let _ = simd;
    nt_acc(bs, c, x, y, sign)
}

/// `out[:, c] = −Σ_{q<nq} M_qᵀ S_q[:, c]` for `bs × bs` blocks `M_q = mt[q bs²..]` given
/// transposed (`mt` holds `M_qᵀ`, column-major) and strips `S_q = base[q·stride..]` of the
/// same length as `out`; `nq = mt.len() / bs²`. With `simd` and `bs = 2` or `4` an AVX2/FMA
/// kernel.
#[inline]
pub fn tn_multi_neg(
    simd: bool,
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
    #[cfg(target_arch = "x86_64")]
    if simd && (bs == 2 || bs == 4) {
        assert_eq!(out.len() % bs, 0, "whole columns");
        // SAFETY: `simd` certifies AVX2 and FMA; the strip range is checked above.
        unsafe {
            if bs == 2 {
                avx2::tn_multi_neg_2(out, mt, base, stride)
            } else {
                avx2::tn_multi_neg_4(out, mt, base, stride)
            }
        };
        return;
    }
    let _ = simd;
    specialise!(bs, tn_multi_neg_body(out, mt, base, stride))
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

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    /// `C += sign · X Yᵀ` for `2 × n` strips and a `2 × 2` block. Two columns per 256-bit
    /// vector `v = [v₀(c), v₁(c), v₀(c+1), v₁(c+1)]`: `X · dup_even(Y)` accumulates
    /// `(C₀₀, C₁₀)` and `X · dup_odd(Y)` accumulates `(C₀₁, C₁₁)`, each twice over (lanes
    /// 0–1 and 2–3), in four independent chains to hide the FMA latency.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `x.len() == y.len()` is even and `c.len() == 4`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn nt_acc_2(c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
        let n = x.len();
        let (xp, yp) = (x.as_ptr(), y.as_ptr());
        let mut ev = [_mm256_setzero_pd(); 4];
        let mut od = [_mm256_setzero_pd(); 4];
        let mut i = 0;
        // SAFETY (all loads): every index read is below `n` by the loop conditions.
        unsafe {
            while i + 16 <= n {
                for u in 0..4 {
                    let xv = _mm256_loadu_pd(xp.add(i + 4 * u));
                    let yv = _mm256_loadu_pd(yp.add(i + 4 * u));
                    ev[u] = _mm256_fmadd_pd(xv, _mm256_movedup_pd(yv), ev[u]);
                    od[u] = _mm256_fmadd_pd(xv, _mm256_permute_pd::<0b1111>(yv), od[u]);
                }
                i += 16;
            }
            let mut u = 0;
            while i + 4 <= n {
                let xv = _mm256_loadu_pd(xp.add(i));
                let yv = _mm256_loadu_pd(yp.add(i));
                ev[u] = _mm256_fmadd_pd(xv, _mm256_movedup_pd(yv), ev[u]);
                od[u] = _mm256_fmadd_pd(xv, _mm256_permute_pd::<0b1111>(yv), od[u]);
                i += 4;
                u += 1;
            }
        }
        let e = _mm256_add_pd(_mm256_add_pd(ev[0], ev[1]), _mm256_add_pd(ev[2], ev[3]));
        let o = _mm256_add_pd(_mm256_add_pd(od[0], od[1]), _mm256_add_pd(od[2], od[3]));
        let mut lo = [0.0f64; 2];
        let mut hi = [0.0f64; 2];
        // SAFETY: stores into local arrays of two f64.
        unsafe {
            let e2 = _mm_add_pd(_mm256_castpd256_pd128(e), _mm256_extractf128_pd::<1>(e));
            let o2 = _mm_add_pd(_mm256_castpd256_pd128(o), _mm256_extractf128_pd::<1>(o));
            _mm_storeu_pd(lo.as_mut_ptr(), e2);
            _mm_storeu_pd(hi.as_mut_ptr(), o2);
        }
        if i < n {
            // One column left.
            lo[0] += x[i] * y[i];
            lo[1] += x[i + 1] * y[i];
            hi[0] += x[i] * y[i + 1];
            hi[1] += x[i + 1] * y[i + 1];
        }
        c[0] += sign * lo[0];
        c[1] += sign * lo[1];
        c[2] += sign * hi[0];
        c[3] += sign * hi[1];
    }

    /// `C += sign · X Yᵀ` for `4 × n` strips and a `4 × 4` block: one column of `X` per
    /// 256-bit vector, `C[:, s] += X[:, c] · Y[s, c]` (broadcast), even and odd columns in two
    /// sets of four accumulators so that eight independent chains hide the FMA latency.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `x.len() == y.len()` is a multiple of 4 and
    /// `c.len() == 16`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn nt_acc_4(c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
        let ncols = x.len() / 4;
        let (xp, yp, cp) = (x.as_ptr(), y.as_ptr(), c.as_mut_ptr());
        let mut even = [_mm256_setzero_pd(); 4];
        let mut odd = [_mm256_setzero_pd(); 4];
        let mut col = 0;
        // SAFETY (all accesses): column indices stay below `ncols`, `c` holds 16 entries.
        unsafe {
            while col + 2 <= ncols {
                let x0 = _mm256_loadu_pd(xp.add(4 * col));
                let x1 = _mm256_loadu_pd(xp.add(4 * col + 4));
                for s in 0..4 {
                    let y0 = _mm256_broadcast_sd(&*yp.add(4 * col + s));
                    let y1 = _mm256_broadcast_sd(&*yp.add(4 * col + 4 + s));
                    even[s] = _mm256_fmadd_pd(x0, y0, even[s]);
                    odd[s] = _mm256_fmadd_pd(x1, y1, odd[s]);
                }
                col += 2;
            }
            if col < ncols {
                let x0 = _mm256_loadu_pd(xp.add(4 * col));
                for s in 0..4 {
                    let y0 = _mm256_broadcast_sd(&*yp.add(4 * col + s));
                    even[s] = _mm256_fmadd_pd(x0, y0, even[s]);
                }
            }
            let sv = _mm256_set1_pd(sign);
            for s in 0..4 {
                let sum = _mm256_add_pd(even[s], odd[s]);
                let old = _mm256_loadu_pd(cp.add(4 * s));
                _mm256_storeu_pd(cp.add(4 * s), _mm256_fmadd_pd(sv, sum, old));
            }
        }
    }

    /// [`super::tn_multi_neg`] for `bs = 4`: `out[:, c] = −Σ_q X_q S_q[:, c]` with the four
    /// columns of `X_q` (`mt` block `q`) in registers, four output columns at a time, each
    /// with two accumulators (even and odd terms), eight independent chains.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `mt.len()` is a positive multiple of 16, `out.len()`
    /// a multiple of 4 and `base.len() ≥ (mt.len()/16 − 1)·stride + out.len()`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn tn_multi_neg_4(out: &mut [f64], mt: &[f64], base: &[f64], stride: usize) {
        let (ncols, nq) = (out.len() / 4, mt.len() / 16);
        let (op, bp, mp) = (out.as_mut_ptr(), base.as_ptr(), mt.as_ptr());
        let mut c = 0;
        // SAFETY (all accesses): indices are below the lengths stated in the contract.
        unsafe {
            while c + 4 <= ncols {
                let mut acc0 = [_mm256_setzero_pd(); 4];
                let mut acc1 = [_mm256_setzero_pd(); 4];
                for q in 0..nq {
                    let m = mp.add(16 * q);
                    let (m0, m1) = (_mm256_loadu_pd(m), _mm256_loadu_pd(m.add(4)));
                    let (m2, m3) = (_mm256_loadu_pd(m.add(8)), _mm256_loadu_pd(m.add(12)));
                    let s = bp.add(q * stride + 4 * c);
                    for u in 0..4 {
                        let su = s.add(4 * u);
                        acc0[u] = _mm256_fmadd_pd(m0, _mm256_broadcast_sd(&*su), acc0[u]);
                        acc1[u] = _mm256_fmadd_pd(m1, _mm256_broadcast_sd(&*su.add(1)), acc1[u]);
                        acc0[u] = _mm256_fmadd_pd(m2, _mm256_broadcast_sd(&*su.add(2)), acc0[u]);
                        acc1[u] = _mm256_fmadd_pd(m3, _mm256_broadcast_sd(&*su.add(3)), acc1[u]);
                    }
                }
                for u in 0..4 {
                    let sum = _mm256_add_pd(acc0[u], acc1[u]);
                    _mm256_storeu_pd(op.add(4 * (c + u)), _mm256_sub_pd(_mm256_setzero_pd(), sum));
                }
                c += 4;
            }
            while c < ncols {
                let (mut acc0, mut acc1) = (_mm256_setzero_pd(), _mm256_setzero_pd());
                for q in 0..nq {
                    let m = mp.add(16 * q);
                    let s = bp.add(q * stride + 4 * c);
                    acc0 = _mm256_fmadd_pd(_mm256_loadu_pd(m), _mm256_broadcast_sd(&*s), acc0);
                    acc1 = _mm256_fmadd_pd(
                        _mm256_loadu_pd(m.add(4)),
                        _mm256_broadcast_sd(&*s.add(1)),
                        acc1,
                    );
                    acc0 = _mm256_fmadd_pd(
                        _mm256_loadu_pd(m.add(8)),
                        _mm256_broadcast_sd(&*s.add(2)),
                        acc0,
                    );
                    acc1 = _mm256_fmadd_pd(
                        _mm256_loadu_pd(m.add(12)),
                        _mm256_broadcast_sd(&*s.add(3)),
                        acc1,
                    );
                }
                let sum = _mm256_add_pd(acc0, acc1);
                _mm256_storeu_pd(op.add(4 * c), _mm256_sub_pd(_mm256_setzero_pd(), sum));
                c += 1;
            }
        }
    }

    /// [`super::block_strip_acc`] for `bs = 2`: two columns per vector
    /// `v = [s₀(c), s₁(c), s₀(c+1), s₁(c+1)]`,
    /// `out += [x₀₀ x₁₀ x₀₀ x₁₀]·dup_even(v) + [x₀₁ x₁₁ x₀₁ x₁₁]·dup_odd(v)`.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `out.len() == s.len()` is even, `x.len() == 4`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn block_strip_acc_2(out: &mut [f64], x: &[f64], s: &[f64]) {
        let n = out.len();
        let (op, sp, xp) = (out.as_mut_ptr(), s.as_ptr(), x.as_ptr());
        let mut c = 0;
        // SAFETY (all accesses): indices are below the lengths stated in the contract.
        unsafe {
            let (x0, x1) = (_mm_loadu_pd(xp), _mm_loadu_pd(xp.add(2)));
            let (x0, x1) = (_mm256_set_m128d(x0, x0), _mm256_set_m128d(x1, x1));
            while c + 4 <= n {
                let v = _mm256_loadu_pd(sp.add(c));
                let o = _mm256_loadu_pd(op.add(c));
                let o = _mm256_fmadd_pd(x0, _mm256_movedup_pd(v), o);
                let o = _mm256_fmadd_pd(x1, _mm256_permute_pd::<0b1111>(v), o);
                _mm256_storeu_pd(op.add(c), o);
                c += 4;
            }
            if c < n {
                let (s0, s1) = (*sp.add(c), *sp.add(c + 1));
                *op.add(c) += *xp * s0 + *xp.add(2) * s1;
                *op.add(c + 1) += *xp.add(1) * s0 + *xp.add(3) * s1;
            }
        }
    }

    /// [`super::block_strip_acc`] for `bs = 4`: the columns of `X` in registers, one column
    /// of `out` per vector, `out[:, c] += Σ_t X[:, t] s_t(c)` (broadcast).
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `out.len() == s.len()` is a multiple of 4,
    /// `x.len() == 16`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn block_strip_acc_4(out: &mut [f64], x: &[f64], s: &[f64]) {
        let ncols = out.len() / 4;
        let (op, sp, xp) = (out.as_mut_ptr(), s.as_ptr(), x.as_ptr());
        // SAFETY (all accesses): indices are below the lengths stated in the contract.
        unsafe {
            let (x0, x1) = (_mm256_loadu_pd(xp), _mm256_loadu_pd(xp.add(4)));
            let (x2, x3) = (_mm256_loadu_pd(xp.add(8)), _mm256_loadu_pd(xp.add(12)));
            for c in 0..ncols {
                let sc = sp.add(4 * c);
                let a = _mm256_fmadd_pd(
                    x0,
                    _mm256_broadcast_sd(&*sc),
                    _mm256_loadu_pd(op.add(4 * c)),
                );
                let b = _mm256_mul_pd(x1, _mm256_broadcast_sd(&*sc.add(1)));
                let a = _mm256_fmadd_pd(x2, _mm256_broadcast_sd(&*sc.add(2)), a);
                let b = _mm256_fmadd_pd(x3, _mm256_broadcast_sd(&*sc.add(3)), b);
                _mm256_storeu_pd(op.add(4 * c), _mm256_add_pd(a, b));
            }
        }
    }

    /// [`super::tn_multi_neg`] for `bs = 2`: per pair of columns
    /// `v = [s₀(c), s₁(c), s₀(c+1), s₁(c+1)]`,
    /// `out −= [m₀₀ m₁₀ m₀₀ m₁₀]·dup_even(v) + [m₀₁ m₁₁ m₀₁ m₁₁]·dup_odd(v)` (with `m = Mᵀ`).
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `mt.len()` is a positive multiple of 4, `out.len()`
    /// is even and `base.len() ≥ (mt.len()/4 − 1)·stride + out.len()`.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn tn_multi_neg_2(out: &mut [f64], mt: &[f64], base: &[f64], stride: usize) {
        let (n, nq) = (out.len(), mt.len() / 4);
        let (op, bp, mp) = (out.as_mut_ptr(), base.as_ptr(), mt.as_ptr());
        let mut c = 0;
        // SAFETY (all accesses): indices are below the lengths stated in the contract.
        unsafe {
            while c + 4 <= n {
                let mut acc = _mm256_setzero_pd();
                for q in 0..nq {
                    let v = _mm256_loadu_pd(bp.add(q * stride + c));
                    let m0 = _mm_loadu_pd(mp.add(4 * q));
                    let m1 = _mm_loadu_pd(mp.add(4 * q + 2));
                    let (m0, m1) = (_mm256_set_m128d(m0, m0), _mm256_set_m128d(m1, m1));
                    acc = _mm256_fmadd_pd(m0, _mm256_movedup_pd(v), acc);
                    acc = _mm256_fmadd_pd(m1, _mm256_permute_pd::<0b1111>(v), acc);
                }
                _mm256_storeu_pd(op.add(c), _mm256_sub_pd(_mm256_setzero_pd(), acc));
                c += 4;
            }
            if c < n {
                let (mut o0, mut o1) = (0.0, 0.0);
                for q in 0..nq {
                    let (s0, s1) = (*bp.add(q * stride + c), *bp.add(q * stride + c + 1));
                    let m = mp.add(4 * q);
                    o0 += *m * s0 + *m.add(2) * s1;
                    o1 += *m.add(1) * s0 + *m.add(3) * s1;
                }
                *op.add(c) = -o0;
                *op.add(c + 1) = -o1;
            }
        }
    }
}

/// `out += X S` for a `bs × bs` block `X` (column-major) and strips `S`, `out` of equal length:
/// one block times a block-row segment, the step of the band products. With `simd` and
/// `bs = 2` or `4` an AVX2/FMA kernel.
#[inline]
pub fn block_strip_acc(simd: bool, bs: usize, out: &mut [f64], x: &[f64], s: &[f64]) {
    #[cfg(target_arch = "x86_64")]
    if simd && (bs == 2 || bs == 4) {
        assert!(out.len() == s.len() && out.len() % bs == 0 && x.len() == bs * bs);
        // SAFETY: `simd` certifies AVX2 and FMA; lengths checked above.
        unsafe {
            if bs == 2 {
                avx2::block_strip_acc_2(out, x, s)
            } else {
                avx2::block_strip_acc_4(out, x, s)
            }
        };
        return;
    }
    let _ = simd;
    specialise!(bs, block_strip_acc_body(out, x, s))
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
        for (simd, bs) in [false, simd_available()]
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
        for (simd, bs) in [false, simd_available()]
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
        for (simd, bs) in [false, simd_available()]
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
