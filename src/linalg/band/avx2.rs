//! The AVX2/FMA kernels of the block-band operations (`bs = 2` and `4`), the one module of the
//! crate with `unsafe` code. They run only through [`Avx2Fma`], a token that can be made only
//! by [`Avx2Fma::detect`] on a CPU that has both features, so a safe caller cannot reach an
//! instruction its CPU lacks; each method checks the lengths its kernel relies on.

/// Proof that this CPU runs AVX2 and FMA instructions: made only by [`Avx2Fma::detect`].
#[cfg(target_arch = "x86_64")]
#[derive(Debug, Clone, Copy)]
pub struct Avx2Fma {
    _detected: (),
}

/// No AVX2 off x86-64: the token cannot exist, and its methods cannot be called.
#[cfg(not(target_arch = "x86_64"))]
#[derive(Debug, Clone, Copy)]
pub enum Avx2Fma {}

#[cfg(target_arch = "x86_64")]
impl Avx2Fma {
    /// The token, when the CPU supports AVX2 and FMA (`std` caches the detection).
    #[inline]
    pub fn detect() -> Option<Self> {
        (std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma"))
            .then_some(Self { _detected: () })
    }

    /// `C += sign · X Yᵀ` for `bs × n` strips `X`, `Y` and a `bs × bs` block `C`, `bs` 2 or 4.
    #[inline]
    pub fn nt_acc(self, bs: usize, c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
        assert!(x.len() == y.len() && x.len().is_multiple_of(bs) && c.len() == bs * bs);
        // SAFETY: `self` certifies AVX2 and FMA; the lengths are checked above.
        unsafe {
            match bs {
                2 => x86::nt_acc_2(c, x, y, sign),
                4 => x86::nt_acc_4(c, x, y, sign),
                _ => panic!("AVX2 kernels for bs = 2 and 4 only, not {bs}"),
            }
        }
    }

    /// `out[:, c] = −Σ_q M_qᵀ S_q[:, c]` (see `strips::tn_multi_neg`), `bs` 2 or 4.
    #[inline]
    pub fn tn_multi_neg(self, bs: usize, out: &mut [f64], mt: &[f64], base: &[f64], stride: usize) {
        let nq = mt.len() / (bs * bs);
        assert!(nq > 0 && out.len().is_multiple_of(bs), "whole columns");
        assert!(
            base.len() >= (nq - 1) * stride + out.len(),
            "strips out of range"
        );
        // SAFETY: `self` certifies AVX2 and FMA; the strip range is checked above.
        unsafe {
            match bs {
                2 => x86::tn_multi_neg_2(out, mt, base, stride),
                4 => x86::tn_multi_neg_4(out, mt, base, stride),
                _ => panic!("AVX2 kernels for bs = 2 and 4 only, not {bs}"),
            }
        }
    }

    /// `out += X S` for a `bs × bs` block `X` and strips `S`, `bs` 2 or 4.
    #[inline]
    pub fn block_strip_acc(self, bs: usize, out: &mut [f64], x: &[f64], s: &[f64]) {
        assert!(out.len() == s.len() && out.len().is_multiple_of(bs) && x.len() == bs * bs);
        // SAFETY: `self` certifies AVX2 and FMA; the lengths are checked above.
        unsafe {
            match bs {
                2 => x86::block_strip_acc_2(out, x, s),
                4 => x86::block_strip_acc_4(out, x, s),
                _ => panic!("AVX2 kernels for bs = 2 and 4 only, not {bs}"),
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
impl Avx2Fma {
    #[inline]
    pub fn detect() -> Option<Self> {
        None
    }

    pub fn nt_acc(self, _: usize, _: &mut [f64], _: &[f64], _: &[f64], _: f64) {
        match self {}
    }

    pub fn tn_multi_neg(self, _: usize, _: &mut [f64], _: &[f64], _: &[f64], _: usize) {
        match self {}
    }

    pub fn block_strip_acc(self, _: usize, _: &mut [f64], _: &[f64], _: &[f64]) {
        match self {}
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// `C += sign · X Yᵀ` for `2 × n` strips and a `2 × 2` block. Two columns per 256-bit
    /// vector `v = [v₀(c), v₁(c), v₀(c+1), v₁(c+1)]`: `X · dup_even(Y)` accumulates
    /// `(C₀₀, C₁₀)` and `X · dup_odd(Y)` accumulates `(C₀₁, C₁₁)`, each twice over (lanes
    /// 0–1 and 2–3), in four independent chains to hide the FMA latency.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; `x.len() == y.len()` is even and `c.len() == 4`.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn nt_acc_2(c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
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
    pub(super) unsafe fn nt_acc_4(c: &mut [f64], x: &[f64], y: &[f64], sign: f64) {
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
    pub(super) unsafe fn tn_multi_neg_4(out: &mut [f64], mt: &[f64], base: &[f64], stride: usize) {
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
    pub(super) unsafe fn block_strip_acc_2(out: &mut [f64], x: &[f64], s: &[f64]) {
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
    pub(super) unsafe fn block_strip_acc_4(out: &mut [f64], x: &[f64], s: &[f64]) {
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
    pub(super) unsafe fn tn_multi_neg_2(out: &mut [f64], mt: &[f64], base: &[f64], stride: usize) {
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
