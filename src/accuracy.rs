//! Accuracy figures against a known truth (docs/theory.md §11): RMSE per state element and the average
//! NEES with its resolution floor; how well the mixture update detects lost measurements
//! (docs/theory.md §10).

use crate::innovations::{BandBasis, t_quantile};
use nalgebra::{DMatrix, SMatrix, SVector, SymmetricEigen};
use serde::{Deserialize, Deserializer, Serialize};

/// Running sums over the scored `(t, i)` terms; in JSON, the sums a part of a Monte Carlo
/// study carries (exact, [`crate::io::json_number`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Accuracy {
    n: usize,
    #[serde(with = "crate::io::json_number::many")]
    sum_sq: Vec<f64>,
    terms: u64,
    #[serde(with = "crate::io::json_number::one")]
    nees_sum: f64,
    nees_terms: u64,
    left_out: u64,
    infinite: u64,
    /// Over the closed runs ([`Accuracy::close_run`]) whose ANEES is finite: their count,
    /// and the sum and the sum of squares of their ANEES.
    runs: u64,
    #[serde(with = "crate::io::json_number::one")]
    run_sum: f64,
    #[serde(with = "crate::io::json_number::one")]
    run_squares: f64,
    /// Scratch: the error `x − x̂` and, per eigenpair of `P`, `(u_kᵀ e, λ_k)`.
    #[serde(skip)]
    e: Vec<f64>,
    #[serde(skip)]
    proj: Vec<(f64, f64)>,
}

/// `(u_kᵀ e, λ_k)` for the eigenpairs of `P` (`N × N`, column-major), on the stack.
macro_rules! projections {
    ($n:literal, $e:expr, $p:expr, $out:expr) => {{
        let eig = SymmetricEigen::new(SMatrix::<f64, $n, $n>::from_column_slice($p));
        let e = SVector::<f64, $n>::from_column_slice($e);
        for k in 0..$n {
            $out[k] = (eig.eigenvectors.column(k).dot(&e), eig.eigenvalues[k]);
        }
    }};
}

/// The accuracy of one run (or many), as reported. JSON has no infinity: an RMSE that
/// overflowed is written as `null` and read back as NaN.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AccuracyReport {
    /// RMSE of each state element over every scored `(t, i)`.
    #[serde(deserialize_with = "nan_for_nulls")]
    pub rmse: Vec<f64>,
    /// `sqrt(mean ‖x − x̂‖² / n)`.
    #[serde(deserialize_with = "nan_for_null")]
    pub rmse_overall: f64,
    /// Average NEES over the resolved terms; `None` (JSON `null`) when infinite.
    pub anees: Option<f64>,
    /// 95 % band of the ANEES of a consistent filter: over two runs or more, `1 ± t s / √R`
    /// from the spread `s` of the `R` runs' own ANEES (what is independent); else
    /// `χ²_{Kn}(0.025, 0.975) / (Kn)`, as if the `K` terms were independent, which they are
    /// not (only indicative). `anees_band_basis` says which.
    pub anees_band: [f64; 2],
    /// `runs` or `independent_terms` (files from before it: the latter).
    #[serde(default)]
    pub anees_band_basis: BandBasis,
    /// Number of scored `(t, i)`.
    pub terms: u64,
    /// Terms in the ANEES.
    pub nees_terms: u64,
    /// Terms left out under the resolution floor (docs/theory.md §11).
    pub nees_left_out: u64,
    /// Terms with a resolved error against a zero claimed variance.
    pub nees_infinite: u64,
}

/// A number that JSON may hold as `null` (not finite when written): NaN.
fn nan_for_null<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Numbers that JSON may hold as `null`: NaN for each.
fn nan_for_nulls<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f64>, D::Error> {
    let values = Vec::<Option<f64>>::deserialize(d)?;
    Ok(values.into_iter().map(|v| v.unwrap_or(f64::NAN)).collect())
}

impl Accuracy {
    pub fn new(n: usize) -> Self {
        Self {
            n,
            sum_sq: vec![0.0; n],
            terms: 0,
            nees_sum: 0.0,
            nees_terms: 0,
            left_out: 0,
            infinite: 0,
            runs: 0,
            run_sum: 0.0,
            run_squares: 0.0,
            e: Vec::with_capacity(n),
            proj: vec![(0.0, 0.0); n],
        }
    }

    /// Scores one estimate `x̂` with reported covariance `P` (column-major `n × n`) against
    /// the true `x`. The NEES term is `Σ_k c_k² / λ_k / n` with `P = Σ λ_k u_k u_kᵀ`,
    /// `c_k = u_kᵀ (x − x̂)`; it is left out when some `k` has `|c_k| < ρ` and `λ_k < ρ²`,
    /// `ρ = 10³ ε max(1, ‖x‖∞)`, and infinite when a resolved `c_k` meets `λ_k ≤ 0`.
    pub fn add(&mut self, x: &[f64], x_hat: &[f64], p: &[f64]) {
        let n = self.n;
        // Sums read from JSON come without their scratch.
        self.proj.resize(n, (0.0, 0.0));
        self.e.clear();
        self.e.extend(x.iter().zip(x_hat).map(|(a, b)| a - b));
        for k in 0..n {
            self.sum_sq[k] += self.e[k] * self.e[k];
        }
        self.terms += 1;
        // Stack-allocated eigendecompositions for the common sizes.
        match n {
            1 => projections!(1, &self.e, p, self.proj),
            2 => projections!(2, &self.e, p, self.proj),
            3 => projections!(3, &self.e, p, self.proj),
            4 => projections!(4, &self.e, p, self.proj),
            _ => {
                let eig = SymmetricEigen::new(DMatrix::from_column_slice(n, n, p));
                for k in 0..n {
                    let c = eig
                        .eigenvectors
                        .column(k)
                        .iter()
                        .zip(&self.e)
                        .map(|(u, e)| u * e)
                        .sum();
                    self.proj[k] = (c, eig.eigenvalues[k]);
                }
            }
        }
        let rho = 1e3 * f64::EPSILON * x.iter().fold(1.0f64, |a, v| a.max(v.abs()));
        let mut nees = 0.0;
        let mut infinite = false;
        for &(c, lambda) in &self.proj {
            if c.abs() < rho && lambda < rho * rho {
                self.left_out += 1;
                return;
            }
            if lambda <= 0.0 {
                infinite = true;
            } else {
                nees += c * c / lambda;
            }
        }
        if infinite {
            self.infinite += 1;
        } else {
            self.nees_sum += nees / n as f64;
            self.nees_terms += 1;
        }
    }

    /// Whether these are sums over states of `n` elements (sums read from a file may not be).
    pub fn is_of(&self, n: usize) -> bool {
        self.n == n && self.sum_sq.len() == n
    }

    /// The NEES sums so far: the sum over resolved terms, their count, and the count of
    /// infinite terms (for per-step averages taken as differences).
    pub fn nees_totals(&self) -> (f64, u64, u64) {
        (self.nees_sum, self.nees_terms, self.infinite)
    }

    /// Adds another set of sums (e.g. from another Monte Carlo run).
    pub fn merge(&mut self, other: &Accuracy) {
        for (a, b) in self.sum_sq.iter_mut().zip(&other.sum_sq) {
            *a += b;
        }
        self.terms += other.terms;
        self.nees_sum += other.nees_sum;
        self.nees_terms += other.nees_terms;
        self.left_out += other.left_out;
        self.infinite += other.infinite;
        self.runs += other.runs;
        self.run_sum += other.run_sum;
        self.run_squares += other.run_squares;
    }

    /// Ends the sums of one independent run, whose own ANEES then counts for the band of
    /// [`AccuracyReport::anees_band`] in the sums it is merged into.
    pub fn close_run(&mut self) {
        debug_assert_eq!(self.runs, 0, "the sums of one run");
        if self.infinite == 0 && self.nees_terms > 0 {
            let anees = self.nees_sum / self.nees_terms as f64;
            self.runs = 1;
            self.run_sum = anees;
            self.run_squares = anees * anees;
        }
    }

    /// The 95 % band of a consistent filter's ANEES and what it rests on.
    fn anees_band(&self) -> ([f64; 2], BandBasis) {
        if self.runs < 2 {
            return (
                chi2_mean_band(self.nees_terms * self.n as u64),
                BandBasis::IndependentTerms,
            );
        }
        let r = self.runs as f64;
        let mean = self.run_sum / r;
        let variance = ((self.run_squares - r * mean * mean) / (r - 1.0)).max(0.0);
        let half = t_quantile(0.975, r - 1.0) * (variance / r).sqrt();
        ([(1.0 - half).max(0.0), 1.0 + half], BandBasis::Runs)
    }

    pub fn report(&self) -> AccuracyReport {
        let k = self.terms.max(1) as f64;
        let rmse: Vec<f64> = self.sum_sq.iter().map(|s| (s / k).sqrt()).collect();
        let rmse_overall = (self.sum_sq.iter().sum::<f64>() / (k * self.n as f64)).sqrt();
        let (anees_band, anees_band_basis) = self.anees_band();
        let anees = if self.infinite > 0 {
            None
        } else {
            Some(self.nees_sum / self.nees_terms.max(1) as f64)
        };
        AccuracyReport {
            rmse,
            rmse_overall,
            anees,
            anees_band,
            anees_band_basis,
            terms: self.terms,
            nees_terms: self.nees_terms,
            nees_left_out: self.left_out,
            nees_infinite: self.infinite,
        }
    }
}

/// The 95 % band of `χ²_k / k` by the Wilson–Hilferty approximation
/// `(1 − 2/(9k) ± 1.96 √(2/(9k)))³` (relative error below 1e−3 for `k ≥ 30`).
pub fn chi2_mean_band(k: u64) -> [f64; 2] {
    if k == 0 {
        return [f64::NAN, f64::NAN];
    }
    let a = 2.0 / (9.0 * k as f64);
    let z = Z_95;
    [
        (1.0 - a - z * a.sqrt()).max(0.0).powi(3),
        (1.0 - a + z * a.sqrt()).powi(3),
    ]
}

impl AccuracyReport {
    /// One line for standard error.
    pub fn summary(&self) -> String {
        let rmse: Vec<String> = self
            .rmse
            .iter()
            .enumerate()
            .map(|(k, r)| format!("x{} {r:.4e}", k + 1))
            .collect();
        let anees = match self.anees {
            Some(a) => format!("{a:.4}"),
            None => "inf".into(),
        };
        let [low, high] = self.anees_band;
        let band = match self.anees_band_basis {
            BandBasis::Runs => format!(
                "95 % band of a consistent filter [{low:.4}, {high:.4}], from the spread of the runs' own averages"
            ),
            _ => format!(
                "95 % band of a consistent filter [{low:.4}, {high:.4}] if the terms were independent; they are correlated in time and along the chain, so only indicative"
            ),
        };
        format!(
            "RMSE {} (overall {:.4e}) over {} terms; average NEES {anees} ({band})",
            rmse.join(", "),
            self.rmse_overall,
            self.terms,
        )
    }
}

/// Running sums of how well the mixture update's `π(t, i)` (docs/theory.md §10) tells lost
/// measurements from received ones, against the true indicator `γ(t, i)`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Detection {
    #[serde(with = "crate::io::json_number::one")]
    abs_error_sum: f64,
    lost: u64,
    detected: u64,
    received: u64,
    false_alarms: u64,
}

/// The detection figures of a run: a measurement counts as detected lost when `π < 0.5`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DetectionReport {
    /// Mean `|π − γ|` over every scored `(t, i)`.
    pub mean_abs_error: f64,
    /// Lost measurements (`γ = 0`), and those with `π < 0.5`.
    pub lost: u64,
    pub detected: u64,
    /// Received measurements (`γ = 1`), and those with `π < 0.5`.
    pub received: u64,
    pub false_alarms: u64,
}

impl Detection {
    /// Scores one `π` against the true `γ` (0 or 1); a `π` of NaN (no row in the data,
    /// docs/theory.md §15: nothing to detect) is not scored.
    pub fn add(&mut self, arrival: f64, gamma: f64) {
        if arrival.is_nan() {
            return;
        }
        self.abs_error_sum += (arrival - gamma).abs();
        let flagged = arrival < 0.5;
        if gamma == 0.0 {
            self.lost += 1;
            self.detected += u64::from(flagged);
        } else {
            self.received += 1;
            self.false_alarms += u64::from(flagged);
        }
    }

    /// Adds the sums of another run.
    pub fn merge(&mut self, other: &Detection) {
        self.abs_error_sum += other.abs_error_sum;
        self.lost += other.lost;
        self.detected += other.detected;
        self.received += other.received;
        self.false_alarms += other.false_alarms;
    }

    pub fn report(&self) -> DetectionReport {
        let terms = (self.lost + self.received).max(1);
        DetectionReport {
            mean_abs_error: self.abs_error_sum / terms as f64,
            lost: self.lost,
            detected: self.detected,
            received: self.received,
            false_alarms: self.false_alarms,
        }
    }
}

impl DetectionReport {
    /// One line for standard error.
    pub fn summary(&self) -> String {
        format!(
            "mean |π − γ| {:.4}; {} of {} lost measurements detected ({:.1} %), {} false alarms among {} received ({:.2} %)",
            self.mean_abs_error,
            self.detected,
            self.lost,
            self.detected_percent(),
            self.false_alarms,
            self.received,
            self.false_alarm_percent()
        )
    }

    /// Detected lost measurements, per cent of the lost ones (0 when none was lost).
    pub fn detected_percent(&self) -> f64 {
        100.0 * self.detected as f64 / self.lost.max(1) as f64
    }

    /// False alarms, per cent of the received measurements.
    pub fn false_alarm_percent(&self) -> f64 {
        100.0 * self.false_alarms as f64 / self.received.max(1) as f64
    }
}

/// The 97.5 % point of the standard normal distribution.
pub(crate) const Z_95: f64 = 1.959_963_984_540_054;

/// How the held-out readings compare with the run's estimates and with the interpolation
/// (docs/theory.md §17, [`crate::run::hold_out`]). Every figure is over the same readings: those whose sensor has a
/// reading the run saw, before or after, to interpolate from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HeldOutReport {
    /// The share of readings asked for, and the seed of the draw.
    pub share: f64,
    pub seed: u64,
    /// The readings held out and scored.
    pub readings: usize,
    /// Held out but not scored: their sensor has no reading the run saw.
    pub unscored: usize,
    /// `√ mean (y − J x̂ − R u)²`: the run's estimates' error on the readings they did not see.
    pub rmse: f64,
    /// `√ mean (y − ỹ)²`, `ỹ` the linear interpolation in time of the same sensor's readings
    /// the run saw (the nearest one where there is none on one side).
    pub interpolation_rmse: f64,
    /// `√ mean (y − y_last)²`, `y_last` the same sensor's last reading the run saw before
    /// (the nearest after where there is none): the baseline of a filter, which sees only the
    /// past.
    pub last_reading_rmse: f64,
    /// `mean (y − J x̂ − R u)² / (J P Jᵀ + M)_kk`: 1 where the claimed variance is right.
    pub standardised: f64,
    /// The 95 % band of `standardised` if its terms were independent `χ²₁` (they are
    /// correlated in time, so only indicative).
    pub band: (f64, f64),
}

impl HeldOutReport {
    /// One line: what was held out and how it scored.
    pub fn summary(&self) -> String {
        let band = self.band;
        let unscored = match self.unscored {
            0 => String::new(),
            k => format!(" ({k} more left unscored: nothing to interpolate from)"),
        };
        format!(
            "{} readings ({:.1} %, seed {}) kept from the filter{unscored}: RMSE {:.4e} against {:.4e} for linear interpolation in time ({:.3}×) and {:.4e} for the sensor's last reading ({:.3}×); mean standardised square {:.4} (95 % band of an honest variance [{:.4}, {:.4}] if the terms were independent)",
            self.readings,
            100.0 * self.share,
            self.seed,
            self.rmse,
            self.interpolation_rmse,
            self.rmse / self.interpolation_rmse,
            self.last_reading_rmse,
            self.rmse / self.last_reading_rmse,
            self.standardised,
            band.0,
            band.1
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chi2_band_matches_tables() {
        // χ²_100 quantiles 74.222 and 129.561 (standard tables).
        let [lo, hi] = chi2_mean_band(100);
        assert!(
            (lo - 0.74222).abs() < 2e-3 && (hi - 1.29561).abs() < 2e-3,
            "{lo} {hi}"
        );
    }

    #[test]
    fn nees_of_known_terms() {
        let mut acc = Accuracy::new(2);
        // P = diag(4, 1), e = (2, 1): NEES = (1 + 1) / 2 = 1.
        acc.add(&[3.0, 1.0], &[1.0, 0.0], &[4.0, 0.0, 0.0, 1.0]);
        // Unresolved: zero error and zero variance in one direction.
        acc.add(&[1.0, 1.0], &[1.0, 1.0], &[0.0, 0.0, 0.0, 1.0]);
        let r = acc.report();
        assert_eq!((r.nees_terms, r.nees_left_out, r.nees_infinite), (1, 1, 0));
        assert!((r.anees.unwrap() - 1.0).abs() < 1e-15);
        // A resolved error against a zero variance is an infinite overconfidence.
        acc.add(&[1.0, 1.0], &[0.0, 1.0], &[0.0, 0.0, 0.0, 1.0]);
        assert_eq!(acc.report().anees, None);
        assert!((acc.report().rmse[0] - (5.0f64 / 3.0).sqrt()).abs() < 1e-15);
    }

    #[test]
    fn detection_counts() {
        let mut d = Detection::default();
        for (pi, gamma) in [(0.1, 0.0), (0.7, 0.0), (0.9, 1.0), (0.2, 1.0), (1.0, 1.0)] {
            d.add(pi, gamma);
        }
        let r = d.report();
        assert_eq!(
            (r.lost, r.detected, r.received, r.false_alarms),
            (2, 1, 3, 1)
        );
        // (0.1 + 0.7 + 0.1 + 0.8 + 0) / 5.
        assert!((r.mean_abs_error - 0.34).abs() < 1e-15);
    }
}
