//! Small dense kernels on column-major slices for the block-band operations.

/// `out += α · op(a) · op(b)` for square `n × n` blocks, `op(x) = xᵀ` when the flag is set.
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

/// In-place Cholesky `A = L Lᵀ` of an `m × m` column-major matrix (lower triangle read and
/// written; the strict upper triangle is zeroed). False when `A` is not positive definite.
pub fn cholesky(a: &mut [f64], m: usize) -> bool {
    for j in 0..m {
        let mut d = a[j + j * m];
        for k in 0..j {
            d -= a[j + k * m] * a[j + k * m];
        }
        if d <= 0.0 || !d.is_finite() {
            return false;
        }
        let d = d.sqrt();
        a[j + j * m] = d;
        for i in j + 1..m {
            let mut s = a[i + j * m];
            for k in 0..j {
                s -= a[i + k * m] * a[j + k * m];
            }
            a[i + j * m] = s / d;
        }
        for i in 0..j {
            a[i + j * m] = 0.0;
        }
    }
    true
}

/// `L⁻¹` in place for a lower-triangular `m × m` column-major `L` (nonzero diagonal).
pub fn invert_lower(l: &mut [f64], m: usize) {
    for j in 0..m {
        l[j + j * m] = 1.0 / l[j + j * m];
        for i in j + 1..m {
            let mut s = 0.0;
            for k in j..i {
                s -= l[i + k * m] * l[k + j * m];
            }
            l[i + j * m] = s / l[i + i * m];
        }
    }
}

/// The inverse of a symmetric positive definite `m × m` matrix, in place, with `scratch` of
/// `m²`: `A⁻¹ = L⁻ᵀ L⁻¹`. False when `A` is not positive definite.
pub fn spd_inverse(a: &mut [f64], m: usize, scratch: &mut [f64]) -> bool {
    if !cholesky(a, m) {
        return false;
    }
    invert_lower(a, m);
    let li = &mut scratch[..m * m];
    li.copy_from_slice(&a[..m * m]);
    for c in 0..m {
        for r in c..m {
            // (L⁻ᵀ L⁻¹)_{rc} = Σ_{k ≥ r} L⁻¹_{kr} L⁻¹_{kc}
            let mut s = 0.0;
            for k in r..m {
                s += li[k + r * m] * li[k + c * m];
            }
            a[r + c * m] = s;
            a[c + r * m] = s;
        }
    }
    true
}
