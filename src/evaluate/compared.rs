//! The filters and smoothers that `evaluate` compares, each with its name, its description,
//! the filter a smoother smooths and the row its RMSE is divided by.

use serde::{Deserialize, Serialize};

use super::EvaluateOptions;
use crate::choice::{Choice, Variant};
use crate::filter::{Dropouts, FilterKind, Update};
use crate::run::RunSpec;

/// A filter or smoother that `evaluate` compares (docs/theory.md §11). The declaration order
/// is the tables' order; the smoothers (docs/theory.md §9) run with `--smooth`. Each of the
/// three filters of `estimate` also runs with the mixture update (docs/theory.md §10).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Compared {
    Distributed,
    DistributedPaper,
    Joint,
    Centralized,
    CentralizedKnown,
    Naive,
    DistributedMixture,
    JointMixture,
    CentralizedMixture,
    DistributedSmoother,
    JointSmoother,
    CentralizedSmoother,
    DistributedMixtureSmoother,
    JointMixtureSmoother,
    CentralizedMixtureSmoother,
}

impl Choice for Compared {
    /// Each with the description that ends the table.
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Distributed,
            name: "distributed",
            help: "two-step filter, default options (banded, local S, filtered)",
        },
        Variant {
            value: Self::DistributedPaper,
            name: "distributed-paper",
            help: "two-step filter as printed in the paper (estimate --paper)",
        },
        Variant {
            value: Self::Joint,
            name: "joint",
            help: "joint band-k filter (--filter joint): banded lifted covariance, linear in N",
        },
        Variant {
            value: Self::Centralized,
            name: "centralized",
            help: "centralized Nahi filter on the lifted system: the optimal linear estimator",
        },
        Variant {
            value: Self::CentralizedKnown,
            name: "centralized-known",
            help: "centralized Kalman filter that knows which measurements were lost: a lower bound",
        },
        Variant {
            value: Self::Naive,
            name: "naive",
            help: "per-subsystem Kalman filter that treats every measurement as present",
        },
        Variant {
            value: Self::DistributedMixture,
            name: "distributed-mixture",
            help: "two-step filter with the mixture update (--update mixture): detects lost measurements",
        },
        Variant {
            value: Self::JointMixture,
            name: "joint-mixture",
            help: "joint band-k filter with the mixture update (--filter joint --update mixture)",
        },
        Variant {
            value: Self::CentralizedMixture,
            name: "centralized-mixture",
            help: "centralized filter with the mixture update: not linear, beats the optimal linear one",
        },
        Variant {
            value: Self::DistributedSmoother,
            name: "distributed-smoother",
            help: "per-subsystem RTS smoother on the two-step filter (--smooth)",
        },
        Variant {
            value: Self::JointSmoother,
            name: "joint-smoother",
            help: "information-form smoother on the joint filter (--filter joint --smooth)",
        },
        Variant {
            value: Self::CentralizedSmoother,
            name: "centralized-smoother",
            help: "RTS smoother on the centralized filter: the optimal linear smoother",
        },
        Variant {
            value: Self::DistributedMixtureSmoother,
            name: "distributed-mixture-smoother",
            help: "per-subsystem RTS smoother on the two-step mixture filter",
        },
        Variant {
            value: Self::JointMixtureSmoother,
            name: "joint-mixture-smoother",
            help: "information-form smoother on the joint mixture filter",
        },
        Variant {
            value: Self::CentralizedMixtureSmoother,
            name: "centralized-mixture-smoother",
            help: "RTS smoother on the centralized mixture filter",
        },
    ];
}

impl Compared {
    /// Every filter and smoother, in table order.
    pub fn all() -> impl Iterator<Item = Self> {
        Self::VARIANTS.iter().map(|v| v.value)
    }

    /// Its line in the description that ends the table.
    pub fn description(self) -> &'static str {
        self.help()
    }

    /// For a smoother, the filter whose estimates it smooths.
    pub fn smooths(self) -> Option<Self> {
        match self {
            Self::DistributedSmoother => Some(Self::Distributed),
            Self::JointSmoother => Some(Self::Joint),
            Self::CentralizedSmoother => Some(Self::Centralized),
            Self::DistributedMixtureSmoother => Some(Self::DistributedMixture),
            Self::JointMixtureSmoother => Some(Self::JointMixture),
            Self::CentralizedMixtureSmoother => Some(Self::CentralizedMixture),
            _ => None,
        }
    }

    /// How its measurements update the estimate: the mixture rows weigh each reading by
    /// `π(t, i)`, which `evaluate` scores against the truth's `γ(t, i)`.
    pub fn update(self) -> Update {
        match self.smooths().unwrap_or(self) {
            Self::DistributedMixture | Self::JointMixture | Self::CentralizedMixture => {
                Update::Mixture
            }
            _ => Update::Linear,
        }
    }

    /// The run this row makes: the filter of `estimate` it is, with its update and dropout
    /// mode; a smoother's is the run of its filter with `smooth`. The joint rows take the
    /// evaluation's band and loading, the centralized rows its `max_lifted`; every row its
    /// `max_memory`.
    pub fn spec(self, opts: &EvaluateOptions) -> RunSpec {
        let mut spec = RunSpec {
            update: self.update(),
            smooth: self.is_smoother(),
            max_lifted: opts.max_lifted,
            max_memory: Some(opts.max_memory),
            ..RunSpec::default()
        };
        match self.smooths().unwrap_or(self) {
            Self::Joint | Self::JointMixture => {
                spec.filter = FilterKind::Joint;
                spec.band = Some(opts.band);
                spec.loading = opts.loading;
            }
            Self::Centralized | Self::CentralizedMixture => spec.filter = FilterKind::Centralized,
            Self::CentralizedKnown => {
                spec.filter = FilterKind::Centralized;
                spec.dropouts = Dropouts::Known;
            }
            // Told that every measurement arrived: the known-dropout filter on data without
            // a lost element.
            Self::Naive => spec.dropouts = Dropouts::Known,
            Self::DistributedPaper => spec.paper = true,
            _ => {}
        }
        spec
    }

    pub fn is_smoother(self) -> bool {
        self.smooths().is_some()
    }

    /// What its RMSE is divided by in the `/ central` column: the optimal linear filter, or
    /// for a smoother the optimal linear smoother.
    pub fn reference(self) -> Self {
        if self.is_smoother() {
            Self::CentralizedSmoother
        } else {
            Self::Centralized
        }
    }

    /// Its place in the tables, which indexes the per-filter figures of a run.
    pub(super) fn index(self) -> usize {
        self as usize
    }
}

/// Its name, padded as the tables ask.
impl std::fmt::Display for Compared {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.pad(self.name())
    }
}

/// The number of [`Compared`] values.
pub(super) const COMPARED: usize = Compared::VARIANTS.len();

#[cfg(test)]
mod tests {
    use super::*;
    use crate::choice::Choice;

    #[test]
    fn each_smoother_smooths_the_filter_it_is_named_after_and_is_compared_with_its_peer() {
        for f in Compared::all() {
            let name = f.name();
            match f.smooths() {
                Some(filter) => {
                    assert_eq!(name, format!("{}-smoother", filter.name()));
                    assert!(!filter.is_smoother());
                    assert_eq!(f.reference(), Compared::CentralizedSmoother);
                    assert_eq!(f.update(), filter.update(), "{name}");
                }
                None => {
                    assert!(!name.ends_with("-smoother"), "{name}");
                    assert_eq!(f.reference(), Compared::Centralized);
                }
            }
            assert_eq!(
                f.update() == Update::Mixture,
                name.contains("-mixture"),
                "{name}"
            );
            assert!(!f.description().is_empty(), "{name}");
            assert_eq!(Compared::all().nth(f.index()), Some(f), "{name}");
        }
        assert_eq!(Compared::all().count(), COMPARED);
    }
}
