//! Step 2 and the filters built on it: the local Nahi update of docs/theory.md §4
//! ([`nahi`]) and the two-step distributed filter that alternates it with the chain solve
//! ([`two_step`](mod@two_step)).

pub mod centralized;
pub mod joint;
pub mod kernel;
pub mod lifted_update;
pub mod nahi;
pub mod two_step;

use serde::{Deserialize, Serialize};

use crate::choice::{Choice, Variant};
use crate::interconnect::SolverKind;
use crate::linalg::band::SymBand;
use crate::model::Model;

pub use centralized::{CentralizedFilter, CentralizedSchedule, ScheduledCentralized};
pub use joint::{JointFilter, JointOptions};
pub use two_step::{Sharing, TwoStepFilter, two_step};

use crate::error::{Error, Result};

/// A filter over the whole chain, one time step at a time. `Send`: a filter owns its model and
/// its state, so it can move to another thread (a scheduler's worker, another language's
/// object).
pub trait ChainFilter: Send {
    /// Processes the next time step: `y(t, ·)` (`N·q` values; NaN marks an element not in the
    /// data, docs/theory.md §15) and `u(t, ·)` (`N·m` values).
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()>;
    /// `x̂(t|t)` (`N·n`) and the diagonal blocks of `P(t|t)` (`N·n²`, column-major blocks).
    fn filtered(&self) -> (&[f64], &[f64]);
    /// After step `t`: `x̂(t+1|t)` and the diagonal blocks of `T(t+1)`.
    fn predicted(&self) -> (&[f64], &[f64]);
    /// With Nahi's update and unknown dropouts ([`reads_second_moment`]): the diagonal blocks
    /// of the second moment `S(t+1)` the next update's gain reads into `out` (`N·n²`,
    /// column-major blocks), and `true`; `false` (nothing written) for the other updates.
    fn second_moments(&self, _out: &mut [f64]) -> bool {
        false
    }
    /// The largest estimated relative error of step 1 so far (`transfer` only; docs/theory.md §2).
    fn solver_error_estimate(&self) -> f64 {
        0.0
    }
    /// For filters that keep a covariance band (the joint filter, docs/theory.md §8): the band of the
    /// last output's covariance (`P(t|t)`, or `T(t+1)` with `predicted`) and its width `k`.
    fn covariance_band(&self, _predicted: bool) -> Option<(&SymBand, usize)> {
        None
    }
    /// With the mixture update (docs/theory.md §10): `π(t, i)` of the last step, the
    /// posterior probability that each subsystem's measurement arrived (`N` values).
    fn arrival(&self) -> Option<&[f64]> {
        None
    }
    /// The log density of the last step's measurements given the past (docs/theory.md §10):
    /// with the mixture update `Σ_i log(p e^ℓ₁ + (1−p) e^ℓ₀)`, with known dropouts the
    /// Gaussian density of the received elements; `None` for Nahi's update with unknown
    /// dropouts, whose measurements have no Gaussian density. Summed over the steps, the
    /// log-likelihood of the measurements.
    fn log_likelihood(&self) -> Option<f64> {
        None
    }
}

/// Whether the update reads the second moment `S = E[x xᵀ]`: only Nahi's update with unknown
/// dropouts does (docs/theory.md §4); the known-dropout update (§5) and the mixture update
/// (§10) need none, so the filters keep no moment recursion for them.
pub fn reads_second_moment(dropouts: Dropouts, update: Update) -> bool {
    dropouts == Dropouts::Unknown && update == Update::Linear
}

/// Checks the estimates of step `t` (`x̂`, `N·n` values, and the diagonal blocks of `P`,
/// `N·n²`) before they are written or scored: an overflow stops the run at the first
/// subsystem it reached, naming `t` and `i`.
pub fn check_estimates(t: usize, n: usize, x: &[f64], p: &[f64]) -> Result<()> {
    let msg = || "the estimate x̂ or its covariance P is no longer finite (overflow)".to_string();
    Error::check_finite(t, n, x, msg)?;
    Error::check_finite(t, n * n, p, msg)
}

/// A covariance pass stored once and replayed (`evaluate`'s schedules) holds the gains of
/// the measurements the model has (all but those of subsystems without a sensor): a step with
/// another row not in the data (docs/theory.md §15) needs its own, so `what` refuses it.
pub(crate) fn refuse_gaps(model: &Model, y: &[f64], t: usize, what: &str) -> Result<()> {
    let q = model.dims.q;
    let measured = &model.window(t).measured;
    match (0..y.len()).position(|k| y[k].is_nan() && measured[k / q]) {
        Some(_) => Err(Error::Usage(format!(
            "{what} was computed for measurements without gaps, and t = {t} has one; run the filter itself"
        ))),
        None => Ok(()),
    }
}

/// The filters `estimate` can run (the meaning of each in [`Choice::VARIANTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FilterKind {
    Distributed,
    Centralized,
    Joint,
}

impl Choice for FilterKind {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Distributed,
            name: "distributed",
            help: "The two-step distributed filter of the paper (docs/theory.md §2, §4)",
        },
        Variant {
            value: Self::Centralized,
            name: "centralized",
            help: "The optimal linear filter on the lifted system (docs/theory.md §7): O((N·n)³) per step, a yardstick; ignores --solver, --second-moment and --interconnect-from",
        },
        Variant {
            value: Self::Joint,
            name: "joint",
            help: "The joint band-k filter (docs/theory.md §8): the lifted covariance on a band of width --band, honest covariances and near-optimal accuracy at a cost linear in N; ignores --solver and --interconnect-from",
        },
    ];
}

/// What the filter uses for the raw second moment `S = E[x xᵀ]` in the Nahi innovation
/// covariance (docs/theory.md §4; the meaning of each in [`Choice::VARIANTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SecondMoment {
    Local,
    Paper,
    Lifted,
    Band,
}

impl Choice for SecondMoment {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Local,
            name: "local",
            help: "Each subsystem propagates its own mean and covariance with the realised input (default)",
        },
        Variant {
            value: Self::Paper,
            name: "paper",
            help: "The paper's S⁺ = A S Aᵀ, right only for an uncoupled subsystem without input and Q = 0",
        },
        Variant {
            value: Self::Lifted,
            name: "lifted",
            help: "The exact diagonal blocks of E[X Xᵀ] of the lifted system: O((N·n)²) memory, for reference on small chains",
        },
        Variant {
            value: Self::Band,
            name: "band",
            help: "The joint filter's own moment band (docs/theory.md §8; its default, joint filter only)",
        },
    ];
}

/// Which estimate of `x(t, ·)` feeds step 1 (docs/theory.md §4; the meaning of each in
/// [`Choice::VARIANTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InterconnectFrom {
    Filtered,
    Predicted,
}

impl Choice for InterconnectFrom {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Filtered,
            name: "filtered",
            help: "x̂(t|t), the filtered estimate (default)",
        },
        Variant {
            value: Self::Predicted,
            name: "predicted",
            help: "x̂(t|t−1), the one-step prediction (the paper's reading)",
        },
    ];
}

/// Whether the filter knows which measurements were lost (docs/theory.md §1; the meaning of
/// each in [`Choice::VARIANTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Dropouts {
    Unknown,
    Known,
}

impl Choice for Dropouts {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Unknown,
            name: "unknown",
            help: "The paper's model: a lost measurement is pure noise and looks like any other",
        },
        Variant {
            value: Self::Known,
            name: "known",
            help: "Lost elements are empty cells in the measurement file; they are skipped",
        },
    ];
}

/// How a measurement updates the estimate (the meaning of each in [`Choice::VARIANTS`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Update {
    #[default]
    Linear,
    Mixture,
}

impl Choice for Update {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Linear,
            name: "linear",
            help: "Nahi's update, the best linear estimator (docs/theory.md §4; the paper's, default)",
        },
        Variant {
            value: Self::Mixture,
            name: "mixture",
            help: "Weighs each measurement by the posterior probability that it arrived (docs/theory.md §10)",
        },
    ];
}

/// Options of the two-step filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct TwoStepOptions {
    pub solver: SolverKind,
    pub second_moment: SecondMoment,
    pub interconnect_from: InterconnectFrom,
    pub dropouts: Dropouts,
    /// `mixture` needs unknown dropouts; it ignores `second_moment`.
    pub update: Update,
}

impl Default for TwoStepOptions {
    fn default() -> Self {
        Self {
            solver: SolverKind::Banded,
            second_moment: SecondMoment::Local,
            interconnect_from: InterconnectFrom::Filtered,
            dropouts: Dropouts::Unknown,
            update: Update::Linear,
        }
    }
}

impl TwoStepOptions {
    /// The paper's algorithm (docs/theory.md §6): `transfer`, `predicted`, `S = paper`.
    pub fn paper() -> Self {
        Self {
            solver: SolverKind::Transfer,
            second_moment: SecondMoment::Paper,
            interconnect_from: InterconnectFrom::Predicted,
            ..Self::default()
        }
    }
}
