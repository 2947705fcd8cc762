//! SPEC §9 predict step 4: the band of `A P Aᵀ` for block-banded `A` and `P`.

use super::{GenBand, SymBand};

/// Preallocated buffers for [`sandwich`].
#[allow(dead_code)] // stub commit: the fields are used once the bodies land
#[derive(Debug, Clone)]
pub struct SandwichWorkspace {
    nb: usize,
    bs: usize,
    b: usize,
    k: usize,
}

impl SandwichWorkspace {
    /// Buffers for `nb` blocks of size `bs`, `A` of half-width `b`, output width `k`.
    pub fn new(nb: usize, bs: usize, b: usize, k: usize) -> Self {
        Self { nb, bs, b, k }
    }
}

/// SPEC §9 predict step 4: `out = band_k(A P Aᵀ)` with `k = out.width()`, `A` of half-width
/// `b` and `P` of width `≥ min(k + 2b, nb − 1)`.
pub fn sandwich(a: &GenBand, p: &SymBand, out: &mut SymBand, ws: &mut SandwichWorkspace) {
    let _ = (a, p, out, ws);
    unimplemented!()
}
