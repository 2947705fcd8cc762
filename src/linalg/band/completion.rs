//! docs/theory.md §8 update step 3: the precision of the maximum-entropy completion of a band.

use super::strips::chol_lower;
use super::{BandError, SymBand};

/// Preallocated buffers for [`completion_precision`]: one dense clique of `m = (k+1)·bs` and
/// the rows of its factor's inverse. Built for `k`, they serve any smaller band.
#[derive(Debug, Clone)]
pub struct CompletionWorkspace {
    bs: usize,
    k: usize,
    /// The clique `P_{C_j C_j}`, then its Cholesky factor, column-major `m × m`.
    chol: Vec<f64>,
    /// Rows `r0..m` of the factor's inverse, row `q` at `q·m` (length `m`).
    rows: Vec<f64>,
    /// Reciprocals of the factor's diagonal.
    dinv: Vec<f64>,
}

impl CompletionWorkspace {
    /// Buffers for `nb` blocks of size `bs` and bandwidth `k` (clamped to `nb − 1`).
    pub fn new(nb: usize, bs: usize, k: usize) -> Self {
        let k = k.min(nb.saturating_sub(1));
        let m = (k + 1) * bs;
        Self {
            bs,
            k,
            chol: vec![0.0; m * m],
            rows: vec![0.0; m * m],
            dinv: vec![0.0; m],
        }
    }
}

/// docs/theory.md §8 update step 3: the precision `Λ` of the maximum-entropy completion of the band
/// `|i − j| ≤ k` of `p` (`p.width() ≥ k`, `k` clamped to `nb − 1`):
///
/// `Λ = Σ_j pad(P_{C_j C_j}⁻¹) − Σ_j pad(P_{S_j S_j}⁻¹)`
///
/// with cliques `C_j = {j, …, j+k}`, `j = 0..nb−k`, and separators `S_j = C_j ∩ C_{j+1}`.
/// `out` (width `k`) is overwritten. `k = 0`: `Λ_ii = P_ii⁻¹`; `k = nb − 1`: `Λ = P⁻¹`.
///
/// Computed without the cancelling difference: with the Cholesky factor
/// `P_{C_j C_j} = L Lᵀ`, the separator `S_{j−1}` is the leading `k` blocks of `C_j`, so its
/// factor is the leading part of `L`, and `P_{C_j}⁻¹ − pad(P_{S_{j−1}}⁻¹) = Xᵀ X` with `X`
/// the last block row of `L⁻¹` (the conditional regression of block `j+k` on the others).
/// The first clique contributes `P_{C_0}⁻¹ = L⁻ᵀ L⁻¹` whole. Cost per block row
/// `≈ ((k+1) bs)³/3`.
///
/// Returns `log det Λ⁻¹`, the log-determinant of the completed covariance: by the same
/// factors, `log det P_{C_0} + Σ_{j ≥ 1} (log det P_{C_j} − log det P_{S_{j−1}})`, twice the
/// sum of the logarithms of `L`'s diagonal entries of block `j + k` (of all of `C_0`).
///
/// Fails with [`BandError::CliqueNotPositiveDefinite`] on the first clique whose block is
/// not numerically positive definite (separators are leading blocks of cliques).
pub fn completion_precision(
    p: &SymBand,
    k: usize,
    out: &mut SymBand,
    ws: &mut CompletionWorkspace,
) -> Result<f64, BandError> {
    let (nb, bs) = (p.nb(), p.bs());
    let k = k.min(nb.saturating_sub(1));
    assert!(p.width() >= k, "the band of P is narrower than k");
    assert_eq!((out.nb(), out.bs(), out.width()), (nb, bs, k), "out shape");
    assert!(
        ws.bs == bs && k <= ws.k,
        "workspace built for another block size or a narrower band"
    );
    out.fill_zero();
    if nb == 0 {
        return Ok(0.0);
    }
    specialise_bk!(bs, k, completion_body(p, out, ws))
}

#[inline(always)]
fn completion_body(
    bs: usize,
    k: usize,
    p: &SymBand,
    out: &mut SymBand,
    ws: &mut CompletionWorkspace,
) -> Result<f64, BandError> {
    let nb = p.nb();
    let mut log_det = 0.0;
    let m = (k + 1) * bs;
    let a = &mut ws.chol[..m * m];
    let rows = &mut ws.rows[..m * m];
    let dinv = &mut ws.dinv[..m];
    for j in 0..nb - k {
        // Gather the lower triangle of the dense clique (block (r, c), r ≥ c, is P_{j+c,j+r}ᵀ).
        for cb in 0..=k {
            let strip = p.row_strip(j + cb);
            for rb in cb..=k {
                let blk = &strip[(rb - cb) * bs * bs..(rb - cb + 1) * bs * bs];
                for c in 0..bs {
                    for r in 0..bs {
                        a[(rb * bs + r) + (cb * bs + c) * m] = blk[c + r * bs];
                    }
                }
            }
        }
        if !chol_lower(m, a) {
            return Err(BandError::CliqueNotPositiveDefinite {
                first: j,
                last: j + k,
            });
        }
        // Independent divisions, off the dependency chains of the solves below.
        for i in 0..m {
            dinv[i] = 1.0 / a[i + i * m];
        }
        // Rows r0..m of L⁻¹: row r solves Lᵀ x = e_r, so x_i = 0 for i > r.
        let r0 = if j == 0 { 0 } else { k * bs };
        log_det -= 2.0 * dinv[r0..m].iter().map(|d| d.ln()).sum::<f64>();
        for r in r0..m {
            let x = &mut rows[(r - r0) * m..(r - r0 + 1) * m];
            for t in r + 1..m {
                x[t] = 0.0;
            }
            x[r] = dinv[r];
            for i in (0..r).rev() {
                let mut acc = 0.0;
                for t in i + 1..=r {
                    acc += a[t + i * m] * x[t];
                }
                x[i] = -acc * dinv[i];
            }
        }
        // Λ_{C_j} += Xᵀ X on the upper blocks.
        let nrows = m - r0;
        for cb in 0..=k {
            for rb in 0..=cb {
                let blk = out.block_mut(j + rb, cb - rb);
                for c in 0..bs {
                    let col = cb * bs + c;
                    for r in 0..bs {
                        let row = rb * bs + r;
                        let mut acc = 0.0;
                        for q in 0..nrows {
                            acc += rows[row + q * m] * rows[col + q * m];
                        }
                        blk[r + c * bs] += acc;
                    }
                }
            }
        }
    }
    Ok(log_det)
}
