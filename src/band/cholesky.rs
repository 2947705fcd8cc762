//! SPEC §9 update steps 4–6: block-banded Cholesky, solves and selected inversion.

use super::kernels::{cholesky, gemm_acc, invert_lower};
use super::{BandError, SymBand};

/// The factor `L` of `Λ = L Lᵀ` for a symmetric positive definite block-banded `Λ` of
/// bandwidth `k`: `L` is lower block-banded with the same bandwidth. Block `L_{j+d, j}` is
/// stored at `(j, d)`, `d = 0..=k`, with `L_jj⁻¹` kept beside for the solves.
#[derive(Debug, Clone)]
pub struct BandCholesky {
    nb: usize,
    bs: usize,
    k: usize,
    l: Vec<f64>,
    l_diag_inv: Vec<f64>,
    /// Scratch of one block, and of the `k` blocks `E_lj` of one column.
    tmp: Vec<f64>,
    e: Vec<f64>,
}

impl BandCholesky {
    pub fn new(nb: usize, bs: usize, k: usize) -> Self {
        let k = k.min(nb.saturating_sub(1));
        let bb = bs * bs;
        Self {
            nb,
            bs,
            k,
            l: vec![0.0; nb * (k + 1) * bb],
            l_diag_inv: vec![0.0; nb * bb],
            tmp: vec![0.0; bb],
            e: vec![0.0; k * bb],
        }
    }

    pub fn nb(&self) -> usize {
        self.nb
    }

    pub fn bs(&self) -> usize {
        self.bs
    }

    /// The bandwidth `k`.
    pub fn width(&self) -> usize {
        self.k
    }

    #[inline]
    fn at(&self, i: usize, j: usize) -> usize {
        (j * (self.k + 1) + (i - j)) * self.bs * self.bs
    }

    /// `L_{ij}`, `0 ≤ i − j ≤ k`.
    #[inline]
    fn block(&self, i: usize, j: usize) -> &[f64] {
        let o = self.at(i, j);
        &self.l[o..o + self.bs * self.bs]
    }

    #[inline]
    fn diag_inv(&self, j: usize) -> &[f64] {
        let bb = self.bs * self.bs;
        &self.l_diag_inv[j * bb..(j + 1) * bb]
    }

    /// Factorises the band of `a` (`a.width() == k`), block column by block column:
    /// `L_jj L_jjᵀ = Λ_jj − Σ_l L_jl L_jlᵀ`, `L_ij = (Λ_ij − Σ_l L_il L_jlᵀ) L_jj⁻ᵀ`.
    pub fn factor(&mut self, a: &SymBand) -> Result<(), BandError> {
        let (nb, bs, k) = (self.nb, self.bs, self.k);
        let bb = bs * bs;
        debug_assert!(a.width() >= k && a.nb() == nb && a.bs() == bs);
        for j in 0..nb {
            for i in j..=(j + k).min(nb - 1) {
                // S = Λ_ij − Σ_{l = max(i−k, 0)}^{j−1} L_il L_jlᵀ, with Λ_ij = Λ_jiᵀ.
                let src = a.block(j, i - j);
                for c in 0..bs {
                    for r in 0..bs {
                        self.tmp[r + c * bs] = src[c + r * bs];
                    }
                }
                for l in i.saturating_sub(k)..j {
                    let (oi, oj) = (self.at(i, l), self.at(j, l));
                    let (lil, ljl) = (&self.l[oi..oi + bb], &self.l[oj..oj + bb]);
                    gemm_acc(&mut self.tmp, -1.0, lil, false, ljl, true, bs);
                }
                let o = self.at(i, j);
                if i == j {
                    if !cholesky(&mut self.tmp, bs) {
                        return Err(BandError::PivotNotPositiveDefinite { block: j });
                    }
                    self.l[o..o + bb].copy_from_slice(&self.tmp);
                    let inv = &mut self.l_diag_inv[j * bb..(j + 1) * bb];
                    inv.copy_from_slice(&self.tmp);
                    invert_lower(inv, bs);
                } else {
                    let lij = &mut self.l[o..o + bb];
                    lij.fill(0.0);
                    let inv = &self.l_diag_inv[j * bb..(j + 1) * bb];
                    gemm_acc(lij, 1.0, &self.tmp, false, inv, true, bs);
                }
            }
        }
        Ok(())
    }

    /// `x ← Λ⁻¹ x` by forward (`L y = x`) and back (`Lᵀ x = y`) substitution.
    pub fn solve_in_place(&self, x: &mut [f64]) {
        let (nb, bs, k) = (self.nb, self.bs, self.k);
        debug_assert_eq!(x.len(), nb * bs);
        let mut acc = [0.0_f64; 16];
        let mut dyn_acc = Vec::new();
        let acc: &mut [f64] = if bs <= 16 {
            &mut acc[..bs]
        } else {
            dyn_acc.resize(bs, 0.0);
            &mut dyn_acc
        };
        for j in 0..nb {
            acc.copy_from_slice(&x[j * bs..(j + 1) * bs]);
            for l in j.saturating_sub(k)..j {
                let ljl = self.block(j, l);
                for c in 0..bs {
                    let xc = x[l * bs + c];
                    for r in 0..bs {
                        acc[r] -= ljl[r + c * bs] * xc;
                    }
                }
            }
            let inv = self.diag_inv(j);
            for r in 0..bs {
                x[j * bs + r] = (0..=r).map(|c| inv[r + c * bs] * acc[c]).sum();
            }
        }
        for j in (0..nb).rev() {
            acc.copy_from_slice(&x[j * bs..(j + 1) * bs]);
            for i in j + 1..=(j + k).min(nb - 1) {
                let lij = self.block(i, j);
                for c in 0..bs {
                    let mut s = 0.0;
                    for r in 0..bs {
                        s += lij[r + c * bs] * x[i * bs + r];
                    }
                    acc[c] -= s;
                }
            }
            let inv = self.diag_inv(j);
            for r in 0..bs {
                x[j * bs + r] = (r..bs).map(|c| inv[c + r * bs] * acc[c]).sum();
            }
        }
    }

    /// The band `|i − j| ≤ out.width()` (`w ≥ k`) of `P = Λ⁻¹` by block selected inversion
    /// (Takahashi; SPEC §9 update step 6). With `E_lj = L_lj L_jj⁻¹`, for `j = nb−1, …, 0`:
    /// `P_ij = − Σ_{l=j+1}^{j+k} P_il E_lj` for `i = j+1..j+w`, then
    /// `P_jj = L_jj⁻ᵀ L_jj⁻¹ − Σ_{l=j+1}^{j+k} P_ljᵀ E_lj` (symmetrised). Every `P_il` needed
    /// is already known; beyond `k` this is the Gauss–Markov continuation of the band.
    pub fn selected_inverse(&mut self, out: &mut SymBand) {
        let (nb, bs, k) = (self.nb, self.bs, self.k);
        let bb = bs * bs;
        let w = out.width();
        debug_assert!(w >= k && out.nb() == nb && out.bs() == bs);
        self.e.resize(k * bb, 0.0);
        for j in (0..nb).rev() {
            let last_l = (j + k).min(nb - 1);
            let inv = &self.l_diag_inv[j * bb..(j + 1) * bb];
            for l in j + 1..=last_l {
                let o = (j * (k + 1) + (l - j)) * bb;
                let e = &mut self.e[(l - j - 1) * bb..(l - j) * bb];
                e.fill(0.0);
                gemm_acc(e, 1.0, &self.l[o..o + bb], false, inv, false, bs);
            }
            for i in j + 1..=(j + w).min(nb - 1) {
                // P_ij, kept in `tmp` and stored transposed as P_ji at out(j, i − j).
                self.tmp.fill(0.0);
                for l in j + 1..=last_l {
                    let e = &self.e[(l - j - 1) * bb..(l - j) * bb];
                    if i <= l {
                        gemm_acc(
                            &mut self.tmp,
                            -1.0,
                            out.block(i, l - i),
                            false,
                            e,
                            false,
                            bs,
                        );
                    } else {
                        gemm_acc(&mut self.tmp, -1.0, out.block(l, i - l), true, e, false, bs);
                    }
                }
                let dst = out.block_mut(j, i - j);
                for c in 0..bs {
                    for r in 0..bs {
                        dst[r + c * bs] = self.tmp[c + r * bs];
                    }
                }
            }
            // P_jj = L_jj⁻ᵀ L_jj⁻¹ − Σ_l P_ljᵀ E_lj, with P_ljᵀ = P_jl = out(j, l − j).
            self.tmp.fill(0.0);
            gemm_acc(&mut self.tmp, 1.0, inv, true, inv, false, bs);
            for l in j + 1..=last_l {
                let e = &self.e[(l - j - 1) * bb..(l - j) * bb];
                gemm_acc(
                    &mut self.tmp,
                    -1.0,
                    out.block(j, l - j),
                    false,
                    e,
                    false,
                    bs,
                );
            }
            let dst = out.block_mut(j, 0);
            for c in 0..bs {
                for r in 0..bs {
                    dst[r + c * bs] = 0.5 * (self.tmp[r + c * bs] + self.tmp[c + r * bs]);
                }
            }
        }
    }
}
