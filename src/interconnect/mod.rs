//! Step 1 of the two-step filter (docs/theory.md §2): the interconnection signals `v(t, ·)` along the
//! chain from `z(t,i) = D x(t,i) + H u(t,i)`.
//!
//! With the link unknowns `a(i) = w⁺(i) = v⁺(i+1)` and `b(i) = v⁻(i) = w⁻(i+1)`, `i = 1..N−1`,
//! (P2)–(P4) (with the corrected boundary conditions of docs/theory.md §6) read
//!
//! ```text
//! a(i) − G11(i) a(i−1) − G12(i) b(i)       = z⁺(i),     a(0) = 0
//! b(i) − G21(i+1) a(i) − G22(i+1) b(i+1)   = z⁻(i+1),   b(N) = 0
//! ```
//!
//! and then `v(i) = [a(i−1); b(i)]` with `a(0) = 0`, `b(N) = 0`. Two solvers:
//! [`ChainSolver`] (`banded`, default) and [`TransferSolver`] (`transfer`, the paper's
//! recursion (P6)–(P19) as corrected in docs/theory.md §6).

mod banded;
mod transfer;

pub use banded::{ChainHalves, ChainSolver, MAX_CONDITION};
pub use transfer::{TRANSFER_ERROR_WARNING, TransferSolver};

use crate::choice::{Choice, Variant};
use crate::error::Result;
use crate::model::Model;

/// Which step-1 solver to use (the meaning of each in [`Choice::VARIANTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SolverKind {
    Banded,
    Transfer,
}

impl Choice for SolverKind {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Banded,
            name: "banded",
            help: "Block-banded LU with partial pivoting: stable, O(N) per step (default)",
        },
        Variant {
            value: Self::Transfer,
            name: "transfer",
            help: "The paper's transfer-matrix recursion: needs interior G22 invertible and loses accuracy exponentially with the chain length",
        },
    ];
}

/// A step-1 solver of either kind, prepared for some time step.
#[derive(Debug, Clone)]
pub enum Interconnect {
    Banded(ChainSolver),
    Transfer(Box<TransferSolver>),
}

impl Interconnect {
    /// Builds the solver for time `t`.
    pub fn new(kind: SolverKind, model: &Model, t: usize) -> Result<Self> {
        Ok(match kind {
            SolverKind::Banded => Interconnect::Banded(ChainSolver::new(model, t)?),
            SolverKind::Transfer => {
                Interconnect::Transfer(Box::new(TransferSolver::new(model, t)?))
            }
        })
    }

    /// Makes the solver valid for time `t` (refactorises only when `G` changed).
    pub fn prepare(&mut self, model: &Model, t: usize) -> Result<()> {
        match self {
            Interconnect::Banded(s) => s.prepare(model, t),
            Interconnect::Transfer(s) => s.prepare(model, t),
        }
    }

    /// Solves for `v` (`N · s` values) from `z` (`N · s` values); `scratch` is reused.
    pub fn solve(&mut self, z: &[f64], v: &mut [f64], scratch: &mut Vec<f64>) {
        match self {
            Interconnect::Banded(s) => s.solve(z, v, scratch),
            Interconnect::Transfer(s) => s.solve(z, v),
        }
    }

    /// The banded solver's split solve in its parts, on chains long enough to have one.
    pub fn halves(&self) -> Option<ChainHalves<'_>> {
        match self {
            Interconnect::Banded(s) => s.halves(),
            Interconnect::Transfer(_) => None,
        }
    }

    /// For `transfer`, the estimated relative error of its solutions (docs/theory.md §2); 0 for `banded`.
    pub fn error_estimate(&self) -> f64 {
        match self {
            Interconnect::Banded(_) => 0.0,
            Interconnect::Transfer(s) => s.error_estimate(),
        }
    }
}

#[cfg(test)]
pub(crate) mod test_support {
    use crate::config::ConfigSource;
    use crate::model::Model;
    use rand::{RngExt, SeedableRng};

    fn matrix_toml(rows: usize, cols: usize, f: &mut impl FnMut() -> f64) -> String {
        let rows: Vec<String> = (0..rows)
            .map(|_| {
                let r: Vec<String> = (0..cols).map(|_| format!("{:?}", f())).collect();
                format!("[{}]", r.join(", "))
            })
            .collect();
        format!("[{}]", rows.join(", "))
    }

    /// A random chain with `G` entries of size ≤ 0.3, `g22_diag` added to the diagonal of
    /// `G22` (to keep it away from singular for the transfer solver), and optionally a
    /// time- and space-varying `G`.
    pub fn random_model(
        n_sub: usize,
        plus: usize,
        minus: usize,
        seed: u64,
        vary: bool,
        g22_diag: f64,
    ) -> Model {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let s = plus + minus;
        let mut k = 0;
        let mut g = || {
            let (r, c) = (k / s % s, k % s);
            k += 1;
            let diag = if r == c && r >= plus { g22_diag } else { 0.0 };
            rng.random_range(-0.3..0.3) + diag
        };
        let mut text = format!(
            "subsystems = {n_sub}\nsteps = 10\n[interconnection]\nplus = {plus}\nminus = {minus}\n\
             [model]\nA = [[0.5]]\nB = {}\nD = {}\nG = {}\nJ = [[1.0]]\nM = [[1.0]]\n\
             [dropout]\np = 1.0\n[initial]\ncov = [[1.0]]\n",
            matrix_toml(1, s, &mut || 0.1),
            matrix_toml(s, 1, &mut || 0.1),
            matrix_toml(s, s, &mut g),
        );
        if vary {
            text += &format!(
                "[[override]]\nsteps = [3, 4]\nsubsystems = [1, {}]\nG = {}\n",
                n_sub.div_ceil(2),
                matrix_toml(s, s, &mut g)
            );
        }
        let src = ConfigSource::from_text("test.toml", ".".into(), text).unwrap();
        Model::from_config(&src).unwrap()
    }

    /// A chain of `n_sub` two-state subsystems without algebraic interconnection (`G = 0`),
    /// so that `A_eff` is block tridiagonal.
    pub fn banded_model(n_sub: usize) -> Model {
        let text = format!(
            "subsystems = {n_sub}\nsteps = 10\n[interconnection]\nplus = 1\nminus = 1\n\
             [model]\nA = [[0.9, 0.1], [-0.2, 0.7]]\nB = [[0.3, 0.0], [0.1, -0.2]]\n\
             D = [[0.5, 0.4], [-0.3, 0.6]]\nG = [[0.0, 0.0], [0.0, 0.0]]\n\
             J = [[1.0, 0.0]]\nM = [[1.0]]\n[dropout]\np = 1.0\n\
             [initial]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n"
        );
        let src = ConfigSource::from_text("test.toml", ".".into(), text).unwrap();
        Model::from_config(&src).unwrap()
    }
}

#[cfg(test)]
mod tests {
    use super::test_support::random_model;
    use super::*;

    #[test]
    fn transfer_equals_banded_on_short_chains() {
        let mut seed = 100;
        for n_sub in 1..=10 {
            for (plus, minus) in [(1, 1), (2, 1), (1, 2), (2, 2)] {
                seed += 1;
                let model = random_model(n_sub, plus, minus, seed, n_sub > 2, 0.6);
                let s = plus + minus;
                let mut banded = Interconnect::new(SolverKind::Banded, &model, 1).unwrap();
                let mut transfer = Interconnect::new(SolverKind::Transfer, &model, 1).unwrap();
                let (mut v1, mut v2) = (vec![0.0; n_sub * s], vec![0.0; n_sub * s]);
                let mut scratch = Vec::new();
                for t in 1..=5 {
                    banded.prepare(&model, t).unwrap();
                    transfer.prepare(&model, t).unwrap();
                    let z: Vec<f64> = (0..n_sub * s).map(|k| ((k + 3 * t) as f64).cos()).collect();
                    banded.solve(&z, &mut v1, &mut scratch);
                    transfer.solve(&z, &mut v2, &mut scratch);
                    let scale = v1.iter().fold(1.0f64, |a, b| a.max(b.abs()));
                    for k in 0..v1.len() {
                        assert!(
                            (v1[k] - v2[k]).abs() <= 1e-10 * scale,
                            "N={n_sub} plus={plus} minus={minus} t={t}: {} vs {}",
                            v1[k],
                            v2[k]
                        );
                    }
                    assert!(transfer.error_estimate() < TRANSFER_ERROR_WARNING);
                }
            }
        }
    }

    #[test]
    fn transfer_error_estimate_flags_long_chains() {
        let model = random_model(60, 1, 1, 5, false, 0.0);
        let transfer = Interconnect::new(SolverKind::Transfer, &model, 1).unwrap();
        assert!(transfer.error_estimate() > TRANSFER_ERROR_WARNING);
    }
}
