//! The report of a fit (docs/theory.md §16): the JSON for scripts and the table for people.

use serde::Serialize;

use crate::choice::{Choice, Variant};
use crate::filter::{Dropouts, FilterKind};
use crate::fit::ObjectiveChoice;
use crate::innovations::InnovationReport;

/// How `fit` reports: a table, or JSON for scripts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ReportFormat {
    Text,
    Json,
}

impl Choice for ReportFormat {
    const VARIANTS: &'static [Variant<Self>] = &[
        Variant {
            value: Self::Text,
            name: "text",
            help: "",
        },
        Variant {
            value: Self::Json,
            name: "json",
            help: "",
        },
    ];
}

/// One fitted parameter in the report (docs/theory.md §16). The interval, `se` and
/// `robust_se` are `None` (`null` in JSON) when unavailable: the estimate is on the boundary
/// of its range, or the Hessian there is not positive definite.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FittedParameter {
    /// `p`, `Q11`, `Q22`, …, `M11`, … (1-based diagonal indices).
    pub name: String,
    pub configured: f64,
    pub estimate: f64,
    /// The 95 % interval, from `θ̂ ± 1.96 se(θ̂)` mapped back (inside `(0, 1)` for `p`,
    /// `(0, ∞)` for a variance).
    pub ci_low: Option<f64>,
    pub ci_high: Option<f64>,
    /// Standard error of the estimate from the inverse Hessian (delta method from `θ`).
    pub se: Option<f64>,
    /// Robust (sandwich) standard error, `H⁻¹ B H⁻¹` (delta method from `θ`).
    pub robust_se: Option<f64>,
}

/// What `fit` found (the JSON report of `sisfilt fit`; these names do not change).
#[derive(Debug, Clone, Serialize)]
pub struct FitReport {
    pub parameters: Vec<FittedParameter>,
    /// `ℓ` at the configured values and at the optimum.
    pub loglik_start: f64,
    pub loglik: f64,
    /// Filter runs of the objective (the Hessian's and the scores' included).
    pub evaluations: usize,
    pub iterations: u64,
    /// Correlations of the estimates (of `θ`), in the order of `parameters`; `None` where a
    /// parameter has no interval.
    pub correlation: Vec<Vec<Option<f64>>>,
    /// The Hessian of `−ℓ` in `θ` at the optimum, in the order of `parameters`.
    pub hessian: Vec<Vec<f64>>,
    /// The filter whose log-likelihood was maximised (the centralized one where the fit chose
    /// it over the joint filter's bands).
    pub filter: FilterKind,
    /// Which objective, and how it was chosen (docs/theory.md §16 "The band"); `None` for the
    /// distributed filter.
    pub objective: Option<ObjectiveChoice>,
    pub dropouts: Dropouts,
    /// Measurement elements in the data (gaps left out).
    pub observations: usize,
    /// Why the optimiser stopped.
    pub termination: String,
    pub seconds: f64,
    /// What the user should know: parameters on their boundary, a `p` that varied in the
    /// config and is fitted as one value, a variance configured as 0.
    pub warnings: Vec<String>,
    /// The innovation check of the fitted model on the data (docs/theory.md §14).
    pub innovations: Option<InnovationReport>,
}

impl FitReport {
    /// The name of the filter whose log-likelihood was maximised.
    pub fn filter_name(&self) -> &'static str {
        self.filter.name()
    }

    /// `unknown` or `known`.
    pub fn dropouts_name(&self) -> &'static str {
        self.dropouts.name()
    }

    /// The report as a table: one row per parameter (configured, estimate, 95 % interval,
    /// standard error, robust standard error; `–` where unavailable), the log-likelihood at
    /// the start and at the optimum with the work done, and the correlations.
    pub fn table(&self) -> String {
        let number = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.4e}"));
        let width = self
            .parameters
            .iter()
            .map(|p| p.name.len())
            .max()
            .unwrap_or(0)
            .max("parameter".len());
        let mut text = format!(
            "{:<width$}  {:>11}  {:>11}  {:>25}  {:>11}  {:>11}\n",
            "parameter", "configured", "estimate", "95 % interval", "se", "robust se"
        );
        for p in &self.parameters {
            let interval = match (p.ci_low, p.ci_high) {
                (Some(lo), Some(hi)) => format!("[{lo:.4e}, {hi:.4e}]"),
                _ => "–".to_string(),
            };
            text += &format!(
                "{:<width$}  {:>11}  {:>11}  {:>25}  {:>11}  {:>11}\n",
                p.name,
                format!("{:.4e}", p.configured),
                format!("{:.4e}", p.estimate),
                interval,
                number(p.se),
                number(p.robust_se)
            );
        }
        text += &format!(
            "\nlog-likelihood: {:.6} at the configured values, {:.6} fitted ({} filter, {} dropouts, {} observations)\n",
            self.loglik_start,
            self.loglik,
            self.filter_name(),
            self.dropouts_name(),
            self.observations
        );
        if let Some(objective) = &self.objective {
            text += &objective.line();
            text += "\n";
        }
        text += &format!(
            "optimiser: {} iterations, {} filter runs, {:.2} s; {}\n",
            self.iterations, self.evaluations, self.seconds, self.termination
        );
        if self.parameters.len() > 1 {
            text += "\ncorrelations:\n";
            text += &format!("{:<width$}", "");
            for p in &self.parameters {
                text += &format!("  {:>7}", p.name);
            }
            text += "\n";
            for (p, row) in self.parameters.iter().zip(&self.correlation) {
                text += &format!("{:<width$}", p.name);
                for c in row {
                    text += &match c {
                        Some(c) => format!("  {c:>7.3}"),
                        None => format!("  {:>7}", "–"),
                    };
                }
                text += "\n";
            }
        }
        text
    }
}
