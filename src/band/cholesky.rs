//! SPEC §9 update steps 4–6: block-banded Cholesky, solves and selected inversion.

use super::{BandError, SymBand};

/// Block-banded Cholesky factor `Λ = L Lᵀ` (`L` lower block-banded with bandwidth `k`) of a
/// symmetric positive definite [`SymBand`] of width `k`, with the solves and the block
/// selected inversion of SPEC §9 update steps 4–6.
#[allow(dead_code)] // stub commit: the fields are used once the bodies land
#[derive(Debug, Clone)]
pub struct BandCholesky {
    nb: usize,
    bs: usize,
    k: usize,
    /// `L_{j+d, j}`, `d = 0..=k`, at `(j (k+1) + d) bs²`, column-major; slots past `nb` zero.
    l: Vec<f64>,
    /// `L_jj⁻¹` at `j bs²`.
    l_diag_inv: Vec<f64>,
}

impl BandCholesky {
    /// A factor for `nb` blocks of size `bs` and bandwidth `k` (clamped to `nb − 1`).
    pub fn new(nb: usize, bs: usize, k: usize) -> Self {
        let k = k.min(nb.saturating_sub(1));
        let bb = bs * bs;
        Self {
            nb,
            bs,
            k,
            l: vec![0.0; nb * (k + 1) * bb],
            l_diag_inv: vec![0.0; nb * bb],
        }
    }

    /// Number of block rows.
    pub fn nb(&self) -> usize {
        self.nb
    }

    /// Block size.
    pub fn bs(&self) -> usize {
        self.bs
    }

    /// Bandwidth `k` of the factor.
    pub fn width(&self) -> usize {
        self.k
    }

    /// Reserves the buffers [`BandCholesky::selected_inverse`] needs up to width `w`.
    pub fn reserve_width(&mut self, w: usize) {
        let _ = w;
    }

    /// SPEC §9 update step 4: factorises `a = L Lᵀ` (`a.width() == k`). Fails with
    /// [`BandError::PivotNotPositiveDefinite`] naming the first pivot block that is not
    /// positive definite.
    pub fn factor(&mut self, a: &SymBand) -> Result<(), BandError> {
        let _ = a;
        unimplemented!()
    }

    /// SPEC §9 update step 5: `x ← Λ⁻¹ x` by forward then back substitution
    /// (`x.len() == nb·bs`).
    pub fn solve_in_place(&self, x: &mut [f64]) {
        let _ = x;
        unimplemented!()
    }

    /// SPEC §9 update step 6: the band `|i − j| ≤ out.width()` (`≥ k`) of `P = Λ⁻¹`.
    pub fn selected_inverse(&mut self, out: &mut SymBand) {
        let _ = out;
        unimplemented!()
    }
}
