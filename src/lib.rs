//! `sisfilt`: distributed recursive filtering for spatially interconnected systems with
//! randomly occurring missing measurements (the paper by Bai Li, with its errata corrected).
//!
//! The maths lives in `docs/theory.md`, rendered here as the module [`theory`]: the model,
//! both steps of the paper's filter, the centralized and joint band-k filters, the smoothers,
//! the accuracy figures and the numerical safeguards, in numbered sections that the code cites
//! as `docs/theory.md §n`.
//!
//! # Notation (docs/theory.md §1)
//! A chain of `N` subsystems `i = 1..N` over time `t = 1..T`; subsystem `i` has state
//! `x ∈ Rⁿ`, input `u ∈ Rᵐ`, measurement `y ∈ R^q` and interconnection signals
//! `v = [v⁺; v⁻]` (in), `w = [w⁺; w⁻]` (out):
//!
//! ```text
//! x(t+1,i) = A x + B v + C u + ω,   ω ~ N(0, Q)                       (P1)
//! w(t,i)   = D x + G v + H u                                          (P2)
//! v⁺(t,i)  = w⁺(t,i−1), v⁻(t,i) = w⁻(t,i+1), v⁺(t,1) = 0, v⁻(t,N) = 0   (P3, P4)
//! y(t,i)   = γ J x + R u + d,   d ~ N(0, M),   γ ~ Bernoulli(p)        (P5)
//! ```
//!
//! `S` denotes the raw second moment `E[x xᵀ]` of docs/theory.md §4, never the chain length.
//!
//! # Modules, in data-flow order
//! - [`config`]: the TOML as written; [`model`]: the validated model and its parameters at `(t, i)`;
//!   [`check`]: what `check` finds in a model, as a value.
//! - [`inputs`]: the inputs `u(t, ·)`, generated or read; [`simulate`]: the true system with
//!   dropouts.
//! - [`interconnect`]: step 1, the chain solve, on [`linalg::band_lu`] (banded LU with a
//!   condition estimate); [`lifted`]: the whole chain as one system and its `A_eff`;
//!   [`stability`]: the spectral radius of `A_eff`, with its error bound.
//! - [`filter`]: the Nahi update, the two-step distributed filter, the centralized and the joint
//!   band-`k` filters, on [`linalg::band`] (the block-banded matrices of the joint filter,
//!   docs/theory.md §8).
//! - [`linalg`]: the linear algebra the rest builds on: dense helpers, the banded LU, the
//!   block-band matrices.
//! - [`smoother`]: the fixed-interval smoother of each filter (docs/theory.md §9).
//! - [`accuracy`]: RMSE and NEES against a known truth; [`evaluate`]: the Monte Carlo comparison
//!   of the filters.
//! - [`io`]: CSV reader and writer, atomic output files, the estimates file, `run.json`;
//!   [`memory`]: the limit every large array is checked against before it is allocated.
//! - [`plot`]: SVG figures from those files.
//! - [`choice`]: the named options (filter, solver, format…) a front end offers;
//!   [`messages`]: the one format of standard error; [`error`]: typed errors and their exit codes.
//! - [`theory`]: `docs/theory.md`, the maths that the modules above cite.
//!
//! The command line (`src/main.rs` and `src/app/`, a file per command) is the binary's own:
//! this library knows nothing of it.

// `unsafe` lives in one module, linalg::band::avx2, behind a token of detected CPU support.
#![deny(unsafe_code)]
// Index loops mirror the formulas of docs/theory.md; iterator chains would hide them.
#![allow(clippy::needless_range_loop)]

pub mod accuracy;
pub mod check;
pub mod choice;
pub mod config;
pub mod error;
pub mod evaluate;
pub mod filter;
pub mod fit;
pub mod innovations;
pub mod inputs;
pub mod interconnect;
pub mod io;
pub mod lifted;
pub mod linalg;
pub mod memory;
pub mod messages;
pub mod model;
pub mod plot;
pub mod run;
pub mod simulate;
pub mod smoother;
pub mod stability;

/// The document `docs/theory.md`, included so that `cargo doc` holds it beside the code.
#[doc = include_str!("../docs/theory.md")]
pub mod theory {}

pub use error::{Error, Result};
