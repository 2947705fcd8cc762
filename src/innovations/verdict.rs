//! The verdict of the innovation check: what its tests found, the likely causes, and the
//! warnings that name them (docs/theory.md §14).

use serde::{Deserialize, Serialize};

use super::whiteness::{Pooled, Portmanteau};
use super::{BandBasis, LjungBox, ReceivedShare, Statistic, SubsystemFigures, WorstSubsystem};

/// A correlation is named only where the Bartlett-weighted autocorrelation `|ρ_w|` is above
/// this: a long chain's pooled sums pass their thresholds on correlations too small to matter
/// (the band-2 joint filter's own, −0.003 to −0.007), where every wrong model measured gave
/// 0.016 or more.
const RHO_MIN: f64 = 0.01;
/// The model's form is named only where some lag's `|ρ_k|` is above this: the band-2 joint
/// filter's own correlation reaches −0.011 at lag 1 on a chain of masses on springs
/// (`N = 2000`), where a missing state measured 0.05 to 0.24.
const FORM_RHO_MIN: f64 = 0.02;
/// A received share at least this high says that the data show no dropouts.
const ALL_RECEIVED: f64 = 0.99;

/// What the data say is likely wrong with the model (docs/theory.md §14).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cause {
    QTooSmall,
    QTooLarge,
    /// …or `p` too high.
    MTooSmall,
    MTooLarge,
    MOrQTooLarge,
    PWrong,
    /// Some subsystems' NIS stand out from the rest.
    Subsystems,
    /// The innovations are not white in a way no noise level explains, or a misfit is left
    /// after the noise levels were fitted: the model's form is wrong (missing dynamics,
    /// correlated noise).
    Form,
}

impl Cause {
    /// The parameters the cause names, `(p, Q, M)`.
    fn names(self) -> (bool, bool, bool) {
        match self {
            Cause::QTooSmall | Cause::QTooLarge => (false, true, false),
            Cause::MTooSmall | Cause::MTooLarge => (false, false, true),
            Cause::MOrQTooLarge => (false, true, true),
            Cause::PWrong => (true, false, false),
            Cause::Subsystems | Cause::Form => (false, false, false),
        }
    }
}

/// The parameters a fit has just estimated: a cause that names only these is a misfit of the
/// model's form, not of their values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Fitted {
    pub p: bool,
    pub q: bool,
    pub m: bool,
}

/// What each test of the family found, at its own level (docs/theory.md §14).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(super) struct Findings {
    /// The critical value of each test.
    z: f64,
    /// The chain's average NIS above (`Some(true)`) or below its band.
    nis: Option<bool>,
    /// The innovations correlated in time (`Some(true)`) or alternating in sign.
    correlation: Option<bool>,
    /// The portmanteau rejects whiteness.
    portmanteau: bool,
    share: bool,
    /// The share is at least [`ALL_RECEIVED`] and above `p`: the data show no dropouts.
    all_received: bool,
    subsystems: bool,
}

impl Findings {
    pub(super) fn of(
        z: f64,
        level: f64,
        nis: Option<bool>,
        pooled: Option<&Pooled>,
        share: Option<&ReceivedShare>,
        subsystems: bool,
    ) -> Self {
        let correlation = pooled.and_then(|p| {
            let guarded = z * p.spatial_factor.map_or(1.0, |l| l.max(1.0).sqrt());
            // A lag 1 beyond the threshold against the sign of the weighted sum: correlations
            // of both signs (an oscillation), which no noise level makes.
            let mixed = p.z1.abs() > guarded && (p.z1 > 0.0) != (p.z_w > 0.0);
            (p.z_w.abs() > guarded && p.rho_w.abs() > RHO_MIN && !mixed).then_some(p.z_w > 0.0)
        });
        Self {
            z,
            nis,
            correlation,
            portmanteau: pooled.is_some_and(|p| {
                let q = &p.portmanteau;
                q.p_value < level && q.lag_rho.iter().any(|r| r.abs() > FORM_RHO_MIN)
            }),
            share: share.is_some_and(|s| s.rejected),
            all_received: share.is_some_and(|s| s.share >= ALL_RECEIVED && s.share > s.expected),
            subsystems,
        }
    }

    /// The causes, by the rules of docs/theory.md §14; a wrong `p`, which disturbs every other
    /// figure, first.
    pub(super) fn causes(&self) -> Vec<Cause> {
        let mut causes = Vec::new();
        match (self.nis, self.correlation) {
            (Some(true), Some(true)) => causes.push(Cause::QTooSmall),
            (Some(true), _) => causes.push(Cause::MTooSmall),
            (Some(false), Some(false)) => causes.push(Cause::QTooLarge),
            (Some(false), Some(true)) => causes.push(Cause::MTooLarge),
            (Some(false), None) => causes.push(Cause::MOrQTooLarge),
            (None, Some(true)) => causes.push(Cause::QTooSmall),
            (None, Some(false)) => causes.push(Cause::QTooLarge),
            (None, None) => {}
        }
        // A rejected whiteness that no noise level explains is a cause of its own.
        let named = causes
            .iter()
            .any(|c| matches!(c, Cause::QTooSmall | Cause::QTooLarge | Cause::MTooLarge));
        if self.portmanteau && !named {
            causes.push(Cause::Form);
        }
        if self.subsystems {
            causes.push(Cause::Subsystems);
        }
        if self.share {
            causes.insert(0, Cause::PWrong);
        }
        causes
    }
}

/// The figures and the verdict of a run's innovation check (docs/theory.md §14). The fields
/// added since the first release default when a file written before them is read.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InnovationReport {
    pub statistic: Statistic,
    /// `Σ q_r`, the received measurement elements scored.
    pub terms: u64,
    /// The rows of measured subsystems not in the data (gaps).
    #[serde(default)]
    pub gaps: u64,
    pub average_nis: Option<f64>,
    /// The 95 % band of a model that fits.
    pub band: Option<[f64; 2]>,
    pub band_basis: BandBasis,
    pub ljung_box: Option<LjungBox>,
    /// The pooled lag-1 statistic `A₁/√B₁`, standard normal for white innovations.
    pub z1: Option<f64>,
    /// The Bartlett-weighted pooled statistic over the lags `1..=h`, standard normal for white
    /// innovations: its sign tells too small a `Q` (positive) from too large a one (negative).
    #[serde(default)]
    pub z_w: Option<f64>,
    /// The weighted autocorrelation `z_w` stands for.
    #[serde(default)]
    pub rho_w: Option<f64>,
    /// `λ`, the spatial guard on `z_w`'s threshold (at least 40 measured subsystems).
    #[serde(default)]
    pub spatial_factor: Option<f64>,
    /// The portmanteau `Q_acf` with `z_k` at each lag.
    #[serde(default)]
    pub portmanteau: Option<Portmanteau>,
    pub worst_subsystem: Option<WorstSubsystem>,
    pub received_share: Option<ReceivedShare>,
    /// Empty when the data agree with the model.
    pub verdict: Vec<Cause>,
    /// The family-wise level of the verdict.
    pub level: f64,
    /// The parameters a fit had estimated before this check, if any.
    #[serde(default)]
    pub fitted: Option<Fitted>,
    #[serde(skip)]
    pub(super) distributed: bool,
    #[serde(skip)]
    pub(super) findings: Findings,
    pub per_subsystem: Vec<SubsystemFigures>,
}

impl InnovationReport {
    /// The check of a model whose `fitted` parameters were just estimated from these data: a
    /// cause that names only fitted parameters becomes the model's form.
    pub fn after_fit(mut self, fitted: Fitted) -> Self {
        let is_fitted = |c: &Cause| {
            let (p, q, m) = c.names();
            (p || q || m) && (!p || fitted.p) && (!q || fitted.q) && (!m || fitted.m)
        };
        let mut causes: Vec<Cause> = Vec::new();
        for cause in &self.verdict {
            let cause = if is_fitted(cause) {
                Cause::Form
            } else {
                *cause
            };
            if !causes.contains(&cause) {
                causes.push(cause);
            }
        }
        self.verdict = causes;
        self.fitted = Some(fitted);
        self
    }

    /// One line for standard error (after `innovations: `).
    pub fn summary(&self) -> String {
        let Some(average) = self.average_nis else {
            return "no measurement received".into();
        };
        let band = self.band.unwrap_or([f64::NAN; 2]);
        let mut line = format!(
            "average {} {average:.4} over {} terms (95 % band of a model that fits [{:.4}, {:.4}], {})",
            match self.statistic {
                Statistic::Nis => "NIS",
                Statistic::NisPi => "NIS_π",
            },
            self.terms,
            band[0],
            band[1],
            match self.band_basis {
                BandBasis::IndependentTerms => "terms taken as independent",
                BandBasis::Blocks => "from blocks of 25 steps",
                BandBasis::Runs => "from the spread of runs",
            }
        );
        if let Some(lb) = &self.ljung_box {
            line += &format!(
                "; whiteness: Ljung–Box {:.1} on {} dof, p = {:.3}",
                lb.statistic, lb.dof, lb.p_value
            );
        }
        if let Some(q) = &self.portmanteau {
            line += &format!(
                ", Q_acf {:.1} on {} dof, p = {:.3}",
                q.statistic, q.dof, q.p_value
            );
        }
        if let Some(z1) = self.z1 {
            line += &format!(", z₁ = {z1:.2}");
        }
        if let Some(z) = self.z_w {
            line += &format!(", z_w = {z:.2}");
        }
        if let Some(s) = &self.received_share {
            line += &format!(
                "; received share {:.4} (p {:.4}, band [{:.4}, {:.4}])",
                s.share, s.expected, s.band[0], s.band[1]
            );
        }
        line + &format!("; warnings at a family-wise {}", self.level)
    }

    /// What the verdict says, a line each, naming the figure, its band and the likely cause
    /// (docs/theory.md §14); a wrong `p` first, since the rest may follow from it.
    pub fn warnings(&self) -> Vec<String> {
        let average = self.average_nis.unwrap_or(f64::NAN);
        let [low, high] = self.band.unwrap_or([f64::NAN; 2]);
        let z = self.z_w.unwrap_or(f64::NAN);
        let nis = format!("the average NIS is {average:.3} (95 % band [{low:.3}, {high:.3}])");
        let sign = if z > 0.0 {
            format!("the innovations are correlated in time (z_w {z:.1})")
        } else {
            format!("the innovations alternate in sign (z_w {z:.1})")
        };
        let p_wrong = self.verdict.contains(&Cause::PWrong);
        let mut lines: Vec<String> = self
            .verdict
            .iter()
            .map(|cause| {
                let (figures, likely) = match cause {
                    Cause::QTooSmall => (format!("{sign}; {nis}"), "Q is likely too small".into()),
                    Cause::QTooLarge => (format!("{sign}; {nis}"), "Q is likely too large".into()),
                    Cause::MTooSmall => {
                        (nis.clone(), "M is likely too small (or p too high)".into())
                    }
                    Cause::MTooLarge => {
                        (format!("{nis}, and {sign}"), "M is likely too large".into())
                    }
                    Cause::MOrQTooLarge => (nis.clone(), "M or Q is likely too large".into()),
                    Cause::PWrong => self.p_warning(),
                    Cause::Subsystems => {
                        let named: Vec<String> = self
                            .per_subsystem
                            .iter()
                            .filter(|s| s.stands_out)
                            .take(5)
                            .map(|s| {
                                format!(
                                    "i = {} (average NIS {:.3})",
                                    s.i,
                                    s.average_nis.unwrap_or(f64::NAN)
                                )
                            })
                            .collect();
                        let figures = format!(
                            "some subsystems stand out from the others: {}",
                            named.join(", ")
                        );
                        (figures, "a faulty sensor there, or noise (M or Q) that differs there from the rest of the chain: an override gives those subsystems their own".into())
                    }
                    Cause::Form => self.form_warning(&nis, &sign),
                };
                let follows = if p_wrong && *cause != Cause::PWrong {
                    " (this may follow from the wrong p: set p first)"
                } else {
                    ""
                };
                format!("the data do not fit the model: {figures}: {likely}{follows}")
            })
            .collect();
        if self.distributed && !lines.is_empty() {
            lines.push("the distributed filter's own overconfidence on a coupled chain also shows as a model error: run the joint filter to tell the two apart".into());
        }
        lines
    }

    /// The figures and the likely cause of a wrong `p`: the share is pulled towards the
    /// configured `p`, so the true one is beyond it.
    fn p_warning(&self) -> (String, String) {
        let s = self.received_share.expect("a share");
        let figures = format!(
            "the share of readings that arrived is about {:.3} (pulled towards the configured p, so a bound), outside the band [{:.3}, {:.3}] of p = {:.3}",
            s.share, s.band[0], s.band[1], s.expected
        );
        if s.share < s.expected {
            return (
                figures,
                format!(
                    "p is likely lower than {:.3} (sisfilt fit estimates it)",
                    s.expected
                ),
            );
        }
        let mut likely = match self.findings.all_received {
            true => "the data show no dropouts: p = 1 is likely".to_string(),
            false => format!(
                "p is likely higher than {:.3} (sisfilt fit estimates it)",
                s.expected
            ),
        };
        if self.gaps > 0 {
            likely += &format!(
                "; if the only losses are the {} gaps (values missing from the file), p = 1, or the dropouts known, fits",
                self.gaps
            );
        }
        (figures, likely)
    }

    /// The figures and the likely cause of a misfit of the model's form: what the tests saw.
    fn form_warning(&self, nis: &str, sign: &str) -> (String, String) {
        let mut seen = Vec::new();
        if self.findings.nis.is_some() {
            seen.push(nis.to_string());
        }
        if self.findings.correlation.is_some() {
            seen.push(sign.to_string());
        }
        if let (true, Some(q)) = (self.findings.portmanteau, &self.portmanteau) {
            let mut lags: Vec<(usize, f64, f64)> = q
                .lag_z
                .iter()
                .enumerate()
                .zip(&q.lag_rho)
                .map(|((k, z), rho)| (k + 1, *z, *rho))
                .filter(|(_, z, _)| z.abs() > self.findings.z)
                .collect();
            let which = if lags.is_empty() {
                "no single lag stands out".to_string()
            } else {
                lags.truncate(5);
                let named: Vec<String> = lags
                    .iter()
                    .map(|(k, z, rho)| format!("{k} (z {z:+.1}, ρ {rho:+.3})"))
                    .collect();
                format!("at lag {}", named.join(", "))
            };
            seen.push(format!(
                "the innovations are not white (Q_acf {:.1} on {} dof, p = {:.1e}; {which})",
                q.statistic, q.dof, q.p_value
            ));
        }
        if seen.is_empty() {
            seen.push(nis.to_string());
        }
        let likely = match self.fitted {
            Some(f) => {
                let names: Vec<&str> = [(f.p, "p"), (f.q, "Q"), (f.m, "M")]
                    .iter()
                    .filter_map(|(on, name)| on.then_some(*name))
                    .collect();
                format!(
                    "left after fitting {}, the misfit is one of the model's form (missing dynamics, correlated noise), not of its noise levels",
                    names.join(" and ")
                )
            }
            None => {
                "the model misses dynamics or correlated noise (its form, not its noise levels)"
                    .into()
            }
        };
        (seen.join("; "), likely)
    }
}
