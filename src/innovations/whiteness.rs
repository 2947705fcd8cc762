//! Whiteness of the standardised innovations (docs/theory.md §14): running sums per series
//! (one element of one subsystem), and the figures pooled over the chain from them.
//!
//! Per series `s` and lag `k`, over the pairs present, with `ē` the series' mean and
//! `c₀ = Σ (ε − ē)² / T_r`:
//!
//! ```text
//! a_{k,s} = Σ (ε_t − ē)(ε_{t−k} − ē) + n_k c₀ / T_r      mean 0 for a white series
//! b_{k,s} = Σ ε_t² ε_{t−k}²                               its variance, self-normalised
//! A_k = Σ_s a_{k,s},  B_k = Σ_s b_{k,s},  w_k = 1 − (k − 1)/h   (Bartlett)
//! z_k = A_k / √B_k,   z_w = Σ_k w_k A_k / √(Σ_k w_k² B_k),   Q_acf = Σ_k z_k²  ~ χ²_h
//! ```
//!
//! No series is divided by its own sample variance: over thousands of series that division's
//! small bias, not a correlation, would decide the test. The Ljung–Box statistic per subsystem
//! and for the chain is information beside them.

use serde::{Deserialize, Serialize};

use super::chi_squared_sf;

/// The largest lag of the whiteness tests (`h = min(10, ⌊T/5⌋)`).
pub const MAX_LAG: usize = 10;
/// The spatial guard is made where at least this many subsystems are measured.
const GUARD_MIN_SUBSYSTEMS: usize = 40;
/// The spatial guard's neighbours on each side.
const GUARD_DISTANCE: usize = 10;

/// Running sums of one series: enough to demean it and form its lag sums at `1..=MAX_LAG`
/// at the end.
#[derive(Debug, Clone)]
pub(super) struct Series {
    /// The last `MAX_LAG` values, the latest first (NaN where a term was not in the data).
    recent: [f64; MAX_LAG],
    sum: f64,
    squares: f64,
    count: u64,
    /// Per lag `k`: `Σ ε_t ε_{t−k}`, the pairs, `Σ ε_{t−k}`, `Σ ε_t` and `Σ ε_t² ε_{t−k}²`
    /// over them.
    products: [f64; MAX_LAG],
    pairs: [u64; MAX_LAG],
    firsts: [f64; MAX_LAG],
    seconds: [f64; MAX_LAG],
    fourths: [f64; MAX_LAG],
}

impl Default for Series {
    fn default() -> Self {
        Self {
            recent: [f64::NAN; MAX_LAG],
            sum: 0.0,
            squares: 0.0,
            count: 0,
            products: [0.0; MAX_LAG],
            pairs: [0; MAX_LAG],
            firsts: [0.0; MAX_LAG],
            seconds: [0.0; MAX_LAG],
            fourths: [0.0; MAX_LAG],
        }
    }
}

/// The lag sums of one series at one lag.
#[derive(Debug, Clone, Copy)]
struct LagSum {
    /// `a_{k,s}` and `b_{k,s}`.
    a: f64,
    b: f64,
    /// `n_k c₀`: what `a` would be for a correlation of one.
    scale: f64,
}

impl Series {
    /// Adds the next value of the series (NaN: not in the data).
    pub(super) fn add(&mut self, value: f64) {
        if !value.is_nan() {
            // Every lag at once, without a branch per lag: a pair that is not there adds
            // -0.0, which leaves every sum as it was (x + -0.0 = x, for x = ±0 too).
            let square = value * value;
            for k in 0..MAX_LAG {
                let before = self.recent[k];
                let present = !before.is_nan();
                self.products[k] += if present { before * value } else { -0.0 };
                self.pairs[k] += u64::from(present);
                self.firsts[k] += if present { before } else { -0.0 };
                self.seconds[k] += if present { value } else { -0.0 };
                self.fourths[k] += if present {
                    before * before * square
                } else {
                    -0.0
                };
            }
            self.sum += value;
            self.squares += square;
            self.count += 1;
        }
        self.recent.copy_within(..MAX_LAG - 1, 1);
        self.recent[0] = value;
    }

    /// The mean and `c₀` of the series, where it has two values and some spread.
    fn moments(&self) -> Option<(f64, f64)> {
        let count = self.count as f64;
        let mean = self.sum / count;
        let c0 = self.squares / count - mean * mean;
        (self.count >= 2 && c0 > 0.0).then_some((mean, c0))
    }

    fn lag_sum(&self, k: usize) -> Option<LagSum> {
        let (mean, c0) = self.moments()?;
        let pairs = self.pairs[k - 1];
        if pairs == 0 {
            return None;
        }
        let n = pairs as f64;
        let centred = self.products[k - 1] - mean * (self.firsts[k - 1] + self.seconds[k - 1])
            + n * mean * mean;
        Some(LagSum {
            a: centred + n * c0 / self.count as f64,
            b: self.fourths[k - 1],
            scale: n * c0,
        })
    }

    /// The autocorrelation at lag `k` of the demeaned series over the pairs present,
    /// `ρ_k = (Σ_pairs (ε_t − ē)(ε_{t−k} − ē) / n_k) / c₀`, and `n_k`.
    fn autocorrelation(&self, k: usize) -> Option<(f64, u64)> {
        let (mean, c0) = self.moments()?;
        let pairs = self.pairs[k - 1];
        if pairs == 0 {
            return None;
        }
        let n = pairs as f64;
        let ck = (self.products[k - 1] - mean * (self.firsts[k - 1] + self.seconds[k - 1])) / n
            + mean * mean;
        Some((ck / c0, pairs))
    }

    /// The Ljung–Box statistic over lags `1..=lags` with the lags it counted:
    /// `Q = Σ_k n_k (T_r + 2) / T_r · ρ_k²`.
    fn ljung_box(&self, lags: usize) -> (f64, usize) {
        let count = self.count as f64;
        (1..=lags)
            .filter_map(|k| self.autocorrelation(k))
            .fold((0.0, 0), |(q, dof), (rho, n)| {
                (q + n as f64 * (count + 2.0) / count * rho * rho, dof + 1)
            })
    }
}

/// The Ljung–Box test of a set of series.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LjungBox {
    pub statistic: f64,
    pub dof: usize,
    pub lags: usize,
    pub p_value: f64,
}

impl LjungBox {
    pub(super) fn of(series: &[Series], lags: usize) -> Option<Self> {
        let (statistic, dof) = series
            .iter()
            .map(|s| s.ljung_box(lags))
            .fold((0.0, 0), |(q, d), (sq, sd)| (q + sq, d + sd));
        (dof > 0).then(|| Self {
            statistic,
            dof,
            lags,
            p_value: chi_squared_sf(statistic, dof as f64),
        })
    }
}

/// The portmanteau test of the pooled lag sums: `Q_acf = Σ_k z_k²` against `χ²_h`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Portmanteau {
    pub statistic: f64,
    pub dof: usize,
    pub p_value: f64,
    /// `z_k` at the lags `1..=h`, each standard normal for white innovations.
    pub lag_z: Vec<f64>,
    /// The autocorrelation `ρ_k = A_k / Σ_s n_{k,s} c₀,s` each `z_k` stands for.
    #[serde(default)]
    pub lag_rho: Vec<f64>,
}

/// The whiteness figures pooled over the chain.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Pooled {
    pub z1: f64,
    /// The Bartlett-weighted sum over the lags, standardised.
    pub z_w: f64,
    /// The correlation `z_w` stands for: `ρ_w = Σ_k w_k A_k / Σ_k w_k Σ_s n_{k,s} c₀,s`.
    pub rho_w: f64,
    /// The spatial guard `λ` where enough subsystems are measured: the factor by which the
    /// correlation between neighbouring subsystems inflates the variance of `z_w`'s sum.
    pub spatial_factor: Option<f64>,
    pub portmanteau: Portmanteau,
}

/// The pooled figures of the chain's series (`q` a subsystem, in chain order) over
/// `1..=lags`; `None` before any lag has a pair.
pub(super) fn pooled(series: &[Series], q: usize, lags: usize) -> Option<Pooled> {
    if lags == 0 {
        return None;
    }
    let weight = |k: usize| 1.0 - (k - 1) as f64 / lags as f64;
    let (mut a, mut b, mut scale) = (vec![0.0; lags], vec![0.0; lags], vec![0.0; lags]);
    // Per subsystem, Z_i = Σ_{s∈i,k} w_k a_{k,s}, where it has a lag sum.
    let mut by_subsystem: Vec<Option<f64>> = Vec::with_capacity(series.len() / q.max(1));
    for subsystem in series.chunks(q) {
        let mut z = None;
        for s in subsystem {
            for k in 1..=lags {
                if let Some(sum) = s.lag_sum(k) {
                    a[k - 1] += sum.a;
                    b[k - 1] += sum.b;
                    scale[k - 1] += sum.scale;
                    *z.get_or_insert(0.0) += weight(k) * sum.a;
                }
            }
        }
        by_subsystem.push(z);
    }
    if b[0] <= 0.0 {
        return None;
    }
    let lag_z: Vec<f64> = a
        .iter()
        .zip(&b)
        .map(|(a, b)| if *b > 0.0 { a / b.sqrt() } else { 0.0 })
        .collect();
    let statistic: f64 = lag_z.iter().map(|z| z * z).sum();
    let weighted = |v: &[f64], power: i32| -> f64 {
        v.iter()
            .enumerate()
            .map(|(k, x)| weight(k + 1).powi(power) * x)
            .sum()
    };
    let variance = weighted(&b, 2);
    Some(Pooled {
        z1: lag_z[0],
        z_w: weighted(&a, 1) / variance.sqrt(),
        rho_w: weighted(&a, 1) / weighted(&scale, 1),
        spatial_factor: spatial_factor(&by_subsystem, variance),
        portmanteau: Portmanteau {
            statistic,
            dof: lags,
            p_value: chi_squared_sf(statistic, lags as f64),
            lag_z,
            lag_rho: a.iter().zip(&scale).map(|(a, s)| a / s).collect(),
        },
    })
}

/// `λ = [Σ_i Z_i² + 2 Σ_{d=1..10} (1 − d/11) Σ_i Z_i Z_{i+d}] / Σ_k w_k² B_k`, the `Z_i`
/// demeaned over the measured subsystems (an unmeasured one counts as zero); `None` where
/// fewer than 40 are measured.
fn spatial_factor(by_subsystem: &[Option<f64>], variance: f64) -> Option<f64> {
    let measured = by_subsystem.iter().flatten().count();
    if measured < GUARD_MIN_SUBSYSTEMS {
        return None;
    }
    let mean = by_subsystem.iter().flatten().sum::<f64>() / measured as f64;
    let z: Vec<f64> = by_subsystem
        .iter()
        .map(|v| v.map_or(0.0, |v| v - mean))
        .collect();
    let lagged = |d: usize| -> f64 { z.iter().zip(&z[d..]).map(|(x, y)| x * y).sum() };
    let neighbours: f64 = (1..=GUARD_DISTANCE)
        .map(|d| (1.0 - d as f64 / (GUARD_DISTANCE + 1) as f64) * lagged(d))
        .sum();
    Some((lagged(0) + 2.0 * neighbours) / variance)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series_of(values: &[f64]) -> Series {
        let mut s = Series::default();
        values.iter().for_each(|v| s.add(*v));
        s
    }

    /// The lag sums from the running sums equal the sums written out, gaps included.
    #[test]
    fn lag_sums_equal_the_sums_written_out() {
        let values = [
            0.3,
            -1.2,
            f64::NAN,
            0.7,
            2.1,
            -0.4,
            f64::NAN,
            f64::NAN,
            1.5,
            -0.9,
        ];
        let s = series_of(&values);
        let present: Vec<f64> = values.iter().copied().filter(|v| !v.is_nan()).collect();
        let count = present.len() as f64;
        let mean = present.iter().sum::<f64>() / count;
        let c0 = present.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / count;
        for k in 1..=4 {
            let pairs: Vec<(f64, f64)> = (k..values.len())
                .map(|t| (values[t], values[t - k]))
                .filter(|(x, y)| !x.is_nan() && !y.is_nan())
                .collect();
            let n = pairs.len() as f64;
            let a: f64 = pairs
                .iter()
                .map(|(x, y)| (x - mean) * (y - mean))
                .sum::<f64>()
                + n * c0 / count;
            let b: f64 = pairs.iter().map(|(x, y)| x * x * y * y).sum();
            let sum = s.lag_sum(k).unwrap();
            assert!((sum.a - a).abs() < 1e-12, "lag {k}: {} {a}", sum.a);
            assert!((sum.b - b).abs() < 1e-12, "lag {k}");
            assert!((sum.scale - n * c0).abs() < 1e-12, "lag {k}");
        }
    }

    /// An alternating series gives a negative z at lag 1 and a positive one at lag 2; a
    /// moving average correlated at lag 1 and anti-correlated at lags 2 and 3 has a rejected
    /// portmanteau, each lag with its own sign.
    #[test]
    fn pooled_figures_see_the_sign_of_each_lag() {
        use rand::{RngExt, SeedableRng};
        let alternating: Vec<f64> = (0..400)
            .map(|t| if t % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let p = pooled(&[series_of(&alternating)], 1, 4).unwrap();
        assert!(
            p.portmanteau.lag_z[0] < -10.0 && p.portmanteau.lag_z[1] > 10.0,
            "{p:?}"
        );
        // ε_t = e_t + 0.5 e_{t−1} − 0.5 e_{t−2} − 0.5 e_{t−3}, e white: autocovariances
        // +0.5, −0.75 and −0.5 at lags 1, 2, 3 (of 1.75), none beyond.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let e: Vec<f64> = (0..4000).map(|_| rng.random::<f64>() - 0.5).collect();
        let eps: Vec<f64> = (3..e.len())
            .map(|t| e[t] + 0.5 * e[t - 1] - 0.5 * e[t - 2] - 0.5 * e[t - 3])
            .collect();
        let p = pooled(&[series_of(&eps)], 1, 10).unwrap();
        assert!(p.portmanteau.p_value < 1e-20, "{p:?}");
        let z = &p.portmanteau.lag_z;
        assert!(z[0] > 5.0 && z[1] < -5.0 && z[2] < -5.0, "{p:?}");
        assert!(z[3..].iter().all(|z| z.abs() < 4.0), "{p:?}");
    }
}
