//! Fixed-interval smoothing (SPEC §10): `x̂(t|T)` with `P(t|T)` from every measurement of the
//! run. Each filter has its smoother, run backward over what its forward pass stored:
//! [`distributed`] (per-subsystem RTS on the two-step filter), [`centralized`] (RTS on the
//! lifted filter of SPEC §5, with the information form as fallback) and [`joint`] (the
//! information form on the joint band-k filter of SPEC §9, linear in `N`).
//!
//! The Nahi model is exact here: with `ν = (Γ − 𝒫) J X + d` the measurements read
//! `Y = 𝒫 J X + R U + ν` with `ν` white, zero-mean and uncorrelated with the states, so the
//! Kalman/RTS smoother of that linear model is the optimal linear smoother.

pub mod centralized;
pub mod distributed;
pub mod joint;

use crate::band::SymBand;
use crate::error::Result;
use crate::model::Model;

pub use centralized::CentralizedSmoother;
pub use distributed::DistributedSmoother;
pub use joint::JointSmoother;

/// Default `--max-memory`: the stored forward pass may take up to 8 GiB.
pub const DEFAULT_MAX_MEMORY: u64 = 8 << 30;

/// The smoothed estimates of a whole run.
pub struct Smoothed {
    /// Per step `t = 1..T`: `x̂(t|T)` (`N·n`).
    pub x: Vec<Vec<f64>>,
    /// Per step: the diagonal blocks of `P(t|T)` (`N·n²`, column-major blocks).
    pub p: Vec<Vec<f64>>,
    /// Joint smoother: per step, the band of `P(t|T)` (width `k`).
    pub bands: Option<Vec<SymBand>>,
    /// What the user should know (e.g. the centralized smoother fell back to the
    /// information form), printed as warnings.
    pub notes: Vec<String>,
}

/// A smoother: the forward pass, one time step at a time, then the backward pass.
pub trait Smoother {
    /// Runs the filter on `y(t, ·)`, `u(t, ·)` and stores what the backward pass needs.
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()>;
    /// Runs the backward pass over the stored steps.
    fn finish(self: Box<Self>) -> Result<Smoothed>;
}

/// Which smoother, for the memory estimate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SmootherKind {
    Distributed,
    Centralized,
    /// With the band `k`.
    Joint(usize),
}

/// Bytes the stored forward pass and the smoothed output take for `steps` steps (SPEC §10
/// "Memory"): `O(T·N·n²)` for `distributed`, `O(T·N·(k+1)·n²)` for `joint`, `O(T·(Nn)²)` for
/// `centralized`.
pub fn memory_bytes(model: &Model, kind: SmootherKind, steps: usize) -> u64 {
    let (n, big_n) = (model.dims.n as u64, model.subsystems as u64);
    let steps = steps as u64;
    // Output: x̂ and the diagonal blocks per step.
    let output = steps * big_n * (n + n * n) * 8;
    let forward = match kind {
        // x̂(t|t), x̂(t+1|t), P(t|t), T(t+1).
        SmootherKind::Distributed => steps * big_n * (2 * n + 2 * n * n) * 8,
        // x̂(t|t), x̂(t|t−1), Λ⁻, Λ⁺ and the output band.
        SmootherKind::Joint(k) => {
            let k = (k as u64).min(big_n - 1);
            steps * big_n * (2 * n + 3 * (k + 1) * n * n) * 8
        }
        // P(t|t), T(t+1) of the whole chain, the means, y and u.
        SmootherKind::Centralized => {
            let size = big_n * n;
            steps * (2 * size * size + 2 * size) * 8
        }
    };
    forward + output
}

/// Parses `--max-memory`: bytes, or a number with a `K`, `M` or `G` suffix (powers of 1024).
pub fn parse_bytes(text: &str) -> std::result::Result<u64, String> {
    let t = text.trim();
    let (digits, scale) = match t.chars().last() {
        Some('K' | 'k') => (&t[..t.len() - 1], 1u64 << 10),
        Some('M' | 'm') => (&t[..t.len() - 1], 1 << 20),
        Some('G' | 'g') => (&t[..t.len() - 1], 1 << 30),
        _ => (t, 1),
    };
    let value: f64 = digits
        .trim()
        .parse()
        .map_err(|_| format!("`{text}`: expected bytes, or a number with a K, M or G suffix"))?;
    if !value.is_finite() || value < 0.0 {
        return Err(format!("`{text}`: expected a non-negative size"));
    }
    Ok((value * scale as f64) as u64)
}

/// A size in bytes for messages (e.g. `1.5 GiB`).
pub fn human_bytes(bytes: u64) -> String {
    let b = bytes as f64;
    if b >= (1u64 << 30) as f64 {
        format!("{:.1} GiB", b / (1u64 << 30) as f64)
    } else if b >= (1u64 << 20) as f64 {
        format!("{:.1} MiB", b / (1u64 << 20) as f64)
    } else if b >= 1024.0 {
        format!("{:.1} KiB", b / 1024.0)
    } else {
        format!("{bytes} B")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_parse_with_suffixes() {
        assert_eq!(parse_bytes("1024"), Ok(1024));
        assert_eq!(parse_bytes("2K"), Ok(2048));
        assert_eq!(parse_bytes("1.5M"), Ok(3 << 19));
        assert_eq!(parse_bytes("8G"), Ok(8 << 30));
        assert!(parse_bytes("lots").is_err());
        assert!(parse_bytes("-1").is_err());
        assert_eq!(human_bytes(3 << 29), "1.5 GiB");
    }
}
