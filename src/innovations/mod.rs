//! Innovation checks: does the model fit the data? No truth is needed (docs/theory.md §14).
//!
//! Every term `(t, i)` compares the measurement with what the model predicts for it from the
//! prior the filter's update starts from ([`term`]); [`InnovationCheck`] keeps running sums
//! of the terms (memory flat in `T`) and [`InnovationCheck::report`] turns them into the
//! figures and the verdict of docs/theory.md §14: the average NIS against its band, the
//! whiteness of the standardised innovations (Ljung–Box, and the pooled lag-1 statistic
//! `z₁`), the share of readings the data say arrived against the band of `p`, per subsystem
//! and over the chain.

mod lanes;
pub mod term;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use statrs::distribution::{ChiSquared, ContinuousCDF, Normal, StudentsT};

use crate::error::{Error, Result};
use crate::filter::kernel::LANES;
use crate::filter::{Dropouts, Update};
use crate::linalg::mat_vec_blocks;
use crate::model::Model;

pub use term::{Term, TermKind, TermScorer, TermWorkspace, scorer};

/// The largest lag of the whiteness test (`h = min(10, ⌊T/5⌋)`).
pub const MAX_LAG: usize = 10;
/// The steps of a block whose NIS sums estimate the variance of the average NIS
/// (docs/theory.md §14: the terms of neighbouring steps are correlated).
pub const BLOCK_STEPS: usize = 25;
/// The family-wise level of the verdict: a model that fits is rejected in at most this
/// share of runs.
pub const FAMILY_LEVEL: f64 = 0.001;
/// The level of the bands reported beside the figures.
const BAND_LEVEL: f64 = 0.05;
/// Chains at least this long are scored in parallel, in chunks of [`CHUNK`] subsystems (as
/// the two-step filter runs its local phases).
const PARALLEL_MIN: usize = 4096;
const CHUNK: usize = 256;

/// The sums `Σ (NIS − q_r)` over blocks of [`BLOCK_STEPS`] steps: the current block's, and
/// the count, sum and sum of squares of the finished ones.
#[derive(Debug, Clone, Default)]
struct Blocks {
    current: f64,
    count: u64,
    sum: f64,
    squares: f64,
}

impl Blocks {
    fn end(&mut self) {
        self.count += 1;
        self.sum += self.current;
        self.squares += self.current * self.current;
        self.current = 0.0;
    }

    /// The standard deviation of the whole run's sum, from the spread of the finished blocks
    /// (at least two): `√(s_B² T / 25)`.
    fn sd_of_total(&self, steps: usize) -> Option<f64> {
        (self.count >= 2).then(|| {
            let nb = self.count as f64;
            let s2 = (self.squares - self.sum * self.sum / nb) / (nb - 1.0);
            (s2.max(0.0) * steps as f64 / BLOCK_STEPS as f64).sqrt()
        })
    }
}

/// Running sums of the NIS terms of one subsystem or of the chain.
#[derive(Debug, Clone, Default)]
struct Tally {
    /// `Σ NIS`, `Σ q_r` and `Σ Var[NIS]` over the terms.
    nis: f64,
    received: f64,
    variance: f64,
    blocks: Blocks,
    /// `Σ π`, `Σ p` and `Σ p (1 − p)` over the terms with unknown dropouts.
    arrival: f64,
    p: f64,
    p_variance: f64,
    arrival_terms: u64,
}

impl Tally {
    /// The chain's tally: the subsystems' sums, with the chain's own `blocks` (the spread of
    /// a sum is not the sum of the spreads).
    fn chain(subsystems: &[Tally], blocks: &Blocks) -> Self {
        let mut chain = Tally {
            blocks: blocks.clone(),
            ..Tally::default()
        };
        for s in subsystems {
            chain.nis += s.nis;
            chain.received += s.received;
            chain.variance += s.variance;
            chain.arrival += s.arrival;
            chain.p += s.p;
            chain.p_variance += s.p_variance;
            chain.arrival_terms += s.arrival_terms;
        }
        chain
    }
}

/// Running sums of one series (one element of one subsystem's standardised innovations):
/// enough to demean it and compute its autocorrelations at lags `1..=MAX_LAG` at the end.
#[derive(Debug, Clone)]
struct Series {
    /// The last `MAX_LAG` values, the latest first (NaN where a term was not in the data).
    recent: [f64; MAX_LAG],
    sum: f64,
    squares: f64,
    count: u64,
    /// Per lag `k`: `Σ ε_t ε_{t+k}`, the pairs, `Σ ε_t` and `Σ ε_{t+k}` over them.
    products: [f64; MAX_LAG],
    pairs: [u64; MAX_LAG],
    firsts: [f64; MAX_LAG],
    seconds: [f64; MAX_LAG],
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
        }
    }
}

impl Series {
    /// Adds the next value of the series (NaN: not in the data).
    fn add(&mut self, value: f64) {
        if !value.is_nan() {
            // Every lag at once, without a branch per lag: a pair that is not there adds
            // -0.0, which leaves every sum as it was (x + -0.0 = x, for x = ±0 too).
            for k in 0..MAX_LAG {
                let before = self.recent[k];
                let present = !before.is_nan();
                self.products[k] += if present { before * value } else { -0.0 };
                self.pairs[k] += u64::from(present);
                self.firsts[k] += if present { before } else { -0.0 };
                self.seconds[k] += if present { value } else { -0.0 };
            }
            self.sum += value;
            self.squares += value * value;
            self.count += 1;
        }
        self.recent.copy_within(..MAX_LAG - 1, 1);
        self.recent[0] = value;
    }

    /// The autocorrelation at lag `k` of the demeaned series over the pairs present:
    /// `ρ_k = (Σ_pairs ε_t ε_{t+k} / n_k) / (Σ ε² / T_r)`, and `n_k`.
    fn autocorrelation(&self, k: usize) -> Option<(f64, u64)> {
        let count = self.count as f64;
        let mean = self.sum / count;
        let c0 = self.squares / count - mean * mean;
        let pairs = self.pairs[k - 1];
        if self.count < 2 || pairs == 0 || c0 <= 0.0 {
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

    /// `√n_k (ρ_k + 1/T_r)`, standard normal for a white series.
    fn lag_z(&self, k: usize) -> Option<f64> {
        let (rho, n) = self.autocorrelation(k)?;
        Some((n as f64).sqrt() * (rho + 1.0 / self.count as f64))
    }
}

/// What the terms of one step are scored from.
struct StepData<'a> {
    model: &'a Model,
    kind: TermKind,
    t: usize,
    mean: &'a [f64],
    cov: &'a [f64],
    y: &'a [f64],
    u: &'a [f64],
}

/// The scratch of one chunk of subsystems, and its share of the chain's block sum.
struct Worker {
    scorer: Box<dyn TermScorer>,
    ru: Vec<f64>,
    block: f64,
}

impl Worker {
    /// Scores the subsystems `first + 1 ..` of `step` (as many as `nis` holds) into their
    /// NIS, tallies and series, [`LANES`] at a time where they share a parameter set and
    /// every row is in the data; the 1-based subsystem whose term broke down, if any.
    fn score(
        &mut self,
        step: &StepData,
        first: usize,
        nis: &mut [f64],
        tallies: &mut [Tally],
        series: &mut [Series],
    ) -> Option<usize> {
        let dims = step.model.dims;
        let (n, q, m) = (dims.n, dims.q, dims.m);
        let nn = n * n;
        let window = step.model.window(step.t);
        let count = nis.len();
        let mut k = 0;
        while k < count {
            let i = first + k;
            let id = window.ids[i];
            let prm = step.model.param_set(id);
            let lanes = k + LANES <= count
                && window.ids[i..i + LANES].iter().all(|&other| other == id)
                && !step.y[i * q..(i + LANES) * q].iter().any(|v| v.is_nan())
                && {
                    let ru = &mut self.ru[..LANES * q];
                    mat_vec_blocks(ru, &prm.R, &step.u[i * m..(i + LANES) * m]);
                    let p = window.p[i..i + LANES].try_into().expect("LANES values");
                    self.scorer.score_lanes(
                        step.kind,
                        id,
                        prm,
                        p,
                        &step.mean[i * n..(i + LANES) * n],
                        &step.cov[i * nn..(i + LANES) * nn],
                        &step.y[i * q..(i + LANES) * q],
                        ru,
                    )
                };
            if lanes {
                for l in 0..LANES {
                    let (term, eps) = self.scorer.lane(l);
                    let k = k + l;
                    let series = &mut series[k * q..(k + 1) * q];
                    let tally = &mut tallies[k];
                    nis[k] = record(window.p[i + l], &term, eps, tally, series, &mut self.block);
                }
                k += LANES;
                continue;
            }
            // One subsystem: a gap, a run shorter than the lanes, or a covariance that is not
            // positive definite somewhere in the lanes.
            let ru = &mut self.ru[..q];
            ru.fill(0.0);
            crate::linalg::mat_vec_add(ru, &prm.R, &step.u[i * m..(i + 1) * m]);
            let mean = &step.mean[i * n..(i + 1) * n];
            let cov = &step.cov[i * nn..(i + 1) * nn];
            let y = &step.y[i * q..(i + 1) * q];
            let p = window.p[i];
            let term = match self.scorer.term(step.kind, prm, p, mean, cov, y, ru) {
                Some(term) => term,
                // A prior that is no longer finite is the filter's breakdown, which the run
                // reports as such: the term is not scored.
                None if !mean.iter().chain(cov).all(|v| v.is_finite()) => Term::UNSCORED,
                None => return Some(i + 1),
            };
            let series = &mut series[k * q..(k + 1) * q];
            nis[k] = record(
                p,
                &term,
                self.scorer.eps(),
                &mut tallies[k],
                series,
                &mut self.block,
            );
            k += 1;
        }
        None
    }
}

/// Adds a term with arrival probability `p` and standardised innovations `eps` (of the step
/// after the last one recorded) to its subsystem's tally and series and to the chunk's block
/// sum; returns its NIS.
fn record(
    p: f64,
    term: &Term,
    eps: &[f64],
    tally: &mut Tally,
    series: &mut [Series],
    block: &mut f64,
) -> f64 {
    for (e, s) in eps.iter().zip(series) {
        s.add(*e);
    }
    if term.received == 0 {
        return term.nis;
    }
    let excess = term.nis - term.received as f64;
    tally.nis += term.nis;
    tally.received += term.received as f64;
    tally.variance += term.variance;
    tally.blocks.current += excess;
    *block += excess;
    if let Some(pi) = term.arrival {
        tally.arrival += pi;
        tally.p += p;
        tally.p_variance += p * (1.0 - p);
        tally.arrival_terms += 1;
    }
    term.nis
}

/// The innovation check of one run: fed the prior, the measurements and the inputs of each
/// step before the filter updates with them, it gives each term's NIS ([`Self::nis`]) and, at
/// the end, the figures and the verdict ([`Self::report`]).
pub struct InnovationCheck {
    model: Model,
    kind: TermKind,
    /// Whether the run's filter is the distributed one, whose own overconfidence looks
    /// like a model error (docs/theory.md §14).
    distributed: bool,
    /// One per chunk of [`CHUNK`] subsystems (one in all on a short chain).
    workers: Vec<Worker>,
    nis: Vec<f64>,
    /// The chain's block sums (its other sums are the subsystems', added up in the report).
    chain: Blocks,
    subsystems: Vec<Tally>,
    series: Vec<Series>,
    steps: usize,
}

impl InnovationCheck {
    /// The check of a run with these dropouts and update; `distributed` when the filter is
    /// the distributed one.
    pub fn new(model: &Model, dropouts: Dropouts, update: Update, distributed: bool) -> Self {
        let (n, q, big_n) = (model.dims.n, model.dims.q, model.subsystems);
        let kind = match (dropouts, update) {
            (Dropouts::Known, _) => TermKind::Gaussian,
            (Dropouts::Unknown, Update::Linear) => TermKind::Nahi,
            (Dropouts::Unknown, Update::Mixture) => TermKind::Mixture,
        };
        Self {
            model: model.clone(),
            kind,
            distributed,
            workers: (0..big_n.div_ceil(CHUNK).max(1))
                .map(|_| Worker {
                    scorer: scorer(n, q),
                    ru: vec![0.0; LANES * q],
                    block: 0.0,
                })
                .collect(),
            nis: vec![f64::NAN; big_n],
            chain: Blocks::default(),
            subsystems: vec![Tally::default(); big_n],
            series: vec![Series::default(); big_n * q],
            steps: 0,
        }
    }

    /// Scores the measurements `y(t, ·)` (`N·q`, NaN where an element is not in the data)
    /// with inputs `u(t, ·)` (`N·m`) against the prior of step `t`: `x̂(t|t−1)` (`N·n`) and
    /// the diagonal blocks of its covariance (`N·n²`, column-major). Steps come in order.
    /// Long chains are scored in parallel, in chunks; the sums over the chain are added in
    /// chunk order, so the figures do not depend on the thread count.
    pub fn step(
        &mut self,
        t: usize,
        mean: &[f64],
        cov: &[f64],
        y: &[f64],
        u: &[f64],
    ) -> Result<()> {
        let q = self.model.dims.q;
        let step = StepData {
            model: &self.model,
            kind: self.kind,
            t,
            mean,
            cov,
            y,
            u,
        };
        let failed = if self.model.subsystems >= PARALLEL_MIN {
            self.workers
                .par_iter_mut()
                .zip(self.nis.par_chunks_mut(CHUNK))
                .zip(self.subsystems.par_chunks_mut(CHUNK))
                .zip(self.series.par_chunks_mut(CHUNK * q))
                .enumerate()
                .filter_map(|(c, (((worker, nis), tallies), series))| {
                    worker.score(&step, c * CHUNK, nis, tallies, series)
                })
                .min()
        } else {
            self.workers[0].score(
                &step,
                0,
                &mut self.nis,
                &mut self.subsystems,
                &mut self.series,
            )
        };
        if let Some(i) = failed {
            return Err(Error::Numerical {
                t,
                i,
                msg: "the predicted covariance of the measurement is not positive definite (innovation check)".into(),
            });
        }
        self.chain.current += self
            .workers
            .iter_mut()
            .map(|w| std::mem::take(&mut w.block))
            .sum::<f64>();
        if t.is_multiple_of(BLOCK_STEPS) {
            self.chain.end();
            self.subsystems.iter_mut().for_each(|s| s.blocks.end());
        }
        self.steps = t;
        Ok(())
    }

    /// The NIS of each subsystem at the last step (`N` values; NaN where nothing was
    /// received); `NIS_π` with the mixture update.
    pub fn nis(&self) -> &[f64] {
        &self.nis
    }

    /// The figures and the verdict over the steps so far.
    pub fn report(&self) -> InnovationReport {
        let (q, big_n) = (self.model.dims.q, self.model.subsystems);
        let lags = MAX_LAG.min(self.steps / 5);
        let unknown = self.kind != TermKind::Gaussian;
        // The tests of the family: the chain's NIS, z₁, the received share, and the
        // subsystems' NIS (one test at level α / N each).
        let tests = 3 + usize::from(unknown);
        let level = FAMILY_LEVEL / tests as f64;
        // Every tally has finished the same blocks.
        let blocks = self.chain.count;
        let shown = Critical::at(BAND_LEVEL, blocks);
        let at_level = Critical::at(level, blocks);
        let subsystem_level = Critical::at(level / big_n as f64, blocks);
        let chain = Tally::chain(&self.subsystems, &self.chain);
        let subsystem_nis: Vec<NisFigures> = self
            .subsystems
            .iter()
            .map(|tally| NisFigures::of(tally, self.steps, shown, subsystem_level))
            .collect();
        // A subsystem stands out from the others, whatever the chain's own fit: against the
        // median of the subsystems' averages.
        let mut averages: Vec<f64> = subsystem_nis.iter().filter_map(|s| s.average).collect();
        averages.sort_by(f64::total_cmp);
        let median = averages.get(averages.len() / 2).copied().unwrap_or(1.0);
        let per_subsystem: Vec<SubsystemFigures> = subsystem_nis
            .iter()
            .zip(&self.subsystems)
            .enumerate()
            .map(|(i, (nis, tally))| {
                let series = &self.series[i * q..(i + 1) * q];
                SubsystemFigures {
                    i: i + 1,
                    stands_out: nis
                        .average
                        .is_some_and(|a| (a / median - 1.0).abs() > nis.verdict_half_width),
                    average_nis: nis.average,
                    band: nis.band,
                    ljung_box: LjungBox::of(series, lags),
                    received_share: ReceivedShare::of(tally, shown, at_level),
                }
            })
            .collect();
        let nis = NisFigures::of(&chain, self.steps, shown, at_level);
        let ljung_box = LjungBox::of(&self.series, lags);
        let z1 = pooled_z(self.series.iter().filter_map(|s| s.lag_z(1)));
        let z_lags = pooled_z(
            self.series
                .iter()
                .flat_map(|s| (1..=lags).filter_map(|k| s.lag_z(k))),
        );
        let worst_subsystem = per_subsystem
            .iter()
            .filter_map(|s| Some((s.i, s.ljung_box.as_ref()?.p_value)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(i, p)| WorstSubsystem {
                i,
                p_value: p,
                corrected_p_value: (p * big_n as f64).min(1.0),
            });
        let received_share = ReceivedShare::of(&chain, shown, at_level);
        let verdict = verdict(
            &nis,
            z_lags.or(z1),
            at_level.z,
            received_share.as_ref(),
            &per_subsystem,
        );
        InnovationReport {
            statistic: if self.kind == TermKind::Mixture {
                Statistic::NisPi
            } else {
                Statistic::Nis
            },
            terms: chain.received as u64,
            average_nis: nis.average,
            band: nis.band,
            band_basis: nis.basis,
            ljung_box,
            z1,
            z_lags,
            worst_subsystem,
            received_share,
            verdict,
            level: FAMILY_LEVEL,
            distributed: self.distributed,
            per_subsystem,
        }
    }
}

/// The average NIS of a tally with its 95 % band, and whether it is outside its band at
/// `level`.
struct NisFigures {
    average: Option<f64>,
    band: Option<[f64; 2]>,
    basis: BandBasis,
    /// The half-width of the band at `level`, relative to 1.
    verdict_half_width: f64,
    /// `Some(true)` above the band at `level`, `Some(false)` below.
    rejected: Option<bool>,
}

impl NisFigures {
    /// `ā = Σ NIS / Σ q_r` and its band `1 ± h / Σ q_r`, `h = max(z √(Σ Var),
    /// t_{n_b−1} √(s_B² T / 25))` (docs/theory.md §14).
    fn of(tally: &Tally, steps: usize, shown: Critical, at_level: Critical) -> Self {
        if tally.received == 0.0 {
            return Self {
                average: None,
                band: None,
                basis: BandBasis::IndependentTerms,
                verdict_half_width: f64::INFINITY,
                rejected: None,
            };
        }
        let average = tally.nis / tally.received;
        let independent = tally.variance.sqrt();
        let blocks = tally.blocks.sd_of_total(steps);
        let half_width = |critical: Critical| {
            let by_terms = critical.z * independent;
            let by_blocks = blocks.map_or(0.0, |sd| critical.t * sd);
            (
                by_terms.max(by_blocks) / tally.received,
                by_blocks > by_terms,
            )
        };
        let (shown, by_blocks) = half_width(shown);
        let (verdict, _) = half_width(at_level);
        Self {
            average: Some(average),
            band: Some([(1.0 - shown).max(0.0), 1.0 + shown]),
            basis: if by_blocks {
                BandBasis::Blocks
            } else {
                BandBasis::IndependentTerms
            },
            verdict_half_width: verdict,
            rejected: ((average - 1.0).abs() > verdict).then_some(average > 1.0),
        }
    }
}

/// Which normalised innovation squared a report averages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Statistic {
    /// `νᵀ Σ_y⁻¹ ν`.
    Nis,
    /// The arrival-weighted `NIS_π` of the mixture update.
    NisPi,
}

/// What a band was built from (docs/theory.md §11, §14).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BandBasis {
    /// The terms' own variances, as if independent: only indicative where they are not.
    #[default]
    IndependentTerms,
    /// The spread of the sums over blocks of 25 steps, which sees their correlation in time.
    Blocks,
    /// The spread of independent runs' averages (`evaluate`).
    Runs,
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
    fn of(series: &[Series], lags: usize) -> Option<Self> {
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

/// The share of readings the data say arrived, `Σ π / terms`, against the band of `p`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReceivedShare {
    pub share: f64,
    /// The mean configured `p` over the terms.
    pub expected: f64,
    /// The 95 % binomial band of the share for the configured `p`.
    pub band: [f64; 2],
    #[serde(skip)]
    rejected: bool,
}

impl ReceivedShare {
    fn of(tally: &Tally, shown: Critical, at_level: Critical) -> Option<Self> {
        if tally.arrival_terms == 0 {
            return None;
        }
        let terms = tally.arrival_terms as f64;
        let (share, expected) = (tally.arrival / terms, tally.p / terms);
        let sd = tally.p_variance.sqrt() / terms;
        let (half, verdict) = (shown.z * sd, at_level.z * sd);
        Some(Self {
            share,
            expected,
            band: [(expected - half).max(0.0), (expected + half).min(1.0)],
            rejected: (share - expected).abs() > verdict + 1e-12,
        })
    }
}

/// The subsystem whose innovations are the least white.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WorstSubsystem {
    pub i: usize,
    pub p_value: f64,
    /// Bonferroni-corrected over the subsystems.
    pub corrected_p_value: f64,
}

/// The figures of one subsystem.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SubsystemFigures {
    pub i: usize,
    pub average_nis: Option<f64>,
    pub band: Option<[f64; 2]>,
    pub ljung_box: Option<LjungBox>,
    pub received_share: Option<ReceivedShare>,
    /// Its average NIS is outside its band at the family-wise level (Bonferroni over the
    /// subsystems): a faulty sensor, or a local `M`.
    pub stands_out: bool,
}

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
}

/// The figures and the verdict of a run's innovation check (docs/theory.md §14).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct InnovationReport {
    pub statistic: Statistic,
    /// `Σ q_r`, the received measurement elements scored.
    pub terms: u64,
    pub average_nis: Option<f64>,
    /// The 95 % band of a model that fits.
    pub band: Option<[f64; 2]>,
    pub band_basis: BandBasis,
    pub ljung_box: Option<LjungBox>,
    /// The pooled lag-1 statistic, standard normal for white innovations.
    pub z1: Option<f64>,
    /// The same pooled over the lags `1..=h` of the Ljung–Box test, standard normal for white
    /// innovations; its sign tells too small a `Q` (positive) from too large a one (negative)
    /// in the verdict, with more power than `z1` where the correlation lasts.
    pub z_lags: Option<f64>,
    pub worst_subsystem: Option<WorstSubsystem>,
    pub received_share: Option<ReceivedShare>,
    /// Empty when the data agree with the model.
    pub verdict: Vec<Cause>,
    /// The family-wise level of the verdict.
    pub level: f64,
    #[serde(skip)]
    distributed: bool,
    pub per_subsystem: Vec<SubsystemFigures>,
}

/// `Σ z_k / √K` of statistics `z_k` each standard normal for white innovations.
fn pooled_z(zs: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, count) = zs.fold((0.0, 0usize), |(s, c), z| (s + z, c + 1));
    (count > 0).then(|| sum / (count as f64).sqrt())
}

/// The rules of docs/theory.md §14, at the critical value `z` of each test; `z_time` is the
/// pooled autocorrelation statistic.
fn verdict(
    nis: &NisFigures,
    z_time: Option<f64>,
    z: f64,
    share: Option<&ReceivedShare>,
    subsystems: &[SubsystemFigures],
) -> Vec<Cause> {
    let correlated = z_time.is_some_and(|v| v > z);
    let anti_correlated = z_time.is_some_and(|v| v < -z);
    let mut causes = Vec::new();
    match nis.rejected {
        Some(true) if correlated => causes.push(Cause::QTooSmall),
        Some(true) => causes.push(Cause::MTooSmall),
        Some(false) if anti_correlated => causes.push(Cause::QTooLarge),
        Some(false) if correlated => causes.push(Cause::MTooLarge),
        Some(false) => causes.push(Cause::MOrQTooLarge),
        None if correlated => causes.push(Cause::QTooSmall),
        None if anti_correlated => causes.push(Cause::QTooLarge),
        None => {}
    }
    // Too small an M makes every reading look less likely to carry the state, so it lowers
    // the share as too high a p does: the one cause "M too small (or p too high)" says both.
    let explained = causes.contains(&Cause::MTooSmall);
    if share.is_some_and(|s| s.rejected && !(explained && s.share < s.expected)) {
        causes.push(Cause::PWrong);
    }
    if subsystems.iter().any(|s| s.stands_out) {
        causes.push(Cause::Subsystems);
    }
    causes
}

impl InnovationReport {
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
        if let Some(z1) = self.z1 {
            line += &format!(", z₁ = {z1:.2}");
        }
        if let Some(z) = self.z_lags {
            line += &format!(", z over lags {z:.2}");
        }
        if let Some(s) = &self.received_share {
            line += &format!(
                "; received share {:.4} (p {:.4}, band [{:.4}, {:.4}])",
                s.share, s.expected, s.band[0], s.band[1]
            );
        }
        line
    }

    /// What the verdict says, a line each, naming the figure, its band and the likely cause
    /// (docs/theory.md §14).
    pub fn warnings(&self) -> Vec<String> {
        let average = self.average_nis.unwrap_or(f64::NAN);
        let [low, high] = self.band.unwrap_or([f64::NAN; 2]);
        let z = self.z_lags.or(self.z1).unwrap_or(f64::NAN);
        let nis = format!("the average NIS is {average:.3} (95 % band [{low:.3}, {high:.3}])");
        let sign = if z > 0.0 {
            format!("the innovations are correlated in time (z over lags {z:.1})")
        } else {
            format!("the innovations alternate in sign (z over lags {z:.1})")
        };
        let p_too = self.verdict.contains(&Cause::PWrong);
        let mut lines: Vec<String> = self
            .verdict
            .iter()
            .map(|cause| {
                let (figures, likely) = match cause {
                    Cause::QTooSmall => (format!("{sign}; {nis}"), "Q is likely too small"),
                    Cause::QTooLarge => (format!("{sign}; {nis}"), "Q is likely too large"),
                    Cause::MTooSmall => (nis.clone(), "M is likely too small (or p too high)"),
                    Cause::MTooLarge => (format!("{nis}, and {sign}"), "M is likely too large"),
                    Cause::MOrQTooLarge => (nis.clone(), "M or Q is likely too large"),
                    Cause::PWrong => {
                        let s = self.received_share.expect("a share");
                        let figures = format!(
                            "the share of readings that arrived is about {:.3} (pulled towards the configured p, so a bound), outside the band [{:.3}, {:.3}] of p = {:.3}",
                            s.share, s.band[0], s.band[1], s.expected
                        );
                        (figures, "p is likely wrong")
                    }
                    Cause::Subsystems => {
                        let named: Vec<String> = self
                            .per_subsystem
                            .iter()
                            .filter(|s| s.stands_out)
                            .take(5)
                            .map(|s| format!("i = {} (average NIS {:.3})", s.i, s.average_nis.unwrap_or(f64::NAN)))
                            .collect();
                        let figures = format!("some subsystems stand out from the others: {}", named.join(", "));
                        (figures, "a faulty sensor, or M wrong there")
                    }
                };
                let first = if p_too && !matches!(cause, Cause::PWrong | Cause::Subsystems) {
                    " (a wrong p disturbs these figures too: set p first)"
                } else {
                    ""
                };
                format!("the data do not fit the model: {figures}: {likely}{first}")
            })
            .collect();
        if self.distributed && !lines.is_empty() {
            lines.push("the distributed filter's own overconfidence on a coupled chain also shows as a model error: run the joint filter to tell the two apart".into());
        }
        lines
    }
}

/// The two-sided critical values of a test at some level: the standard normal's, and
/// Student's t with `n_b − 1` degrees of freedom for the block sums of (14.3).
#[derive(Debug, Clone, Copy)]
struct Critical {
    z: f64,
    t: f64,
}

impl Critical {
    fn at(level: f64, blocks: u64) -> Self {
        let p = 1.0 - level / 2.0;
        Self {
            z: Normal::standard().inverse_cdf(p),
            t: t_quantile(p, blocks as f64 - 1.0),
        }
    }
}

/// The `p`-quantile of Student's t with `dof` degrees of freedom (infinite without any).
pub(crate) fn t_quantile(p: f64, dof: f64) -> f64 {
    StudentsT::new(0.0, 1.0, dof).map_or(f64::INFINITY, |d| d.inverse_cdf(p))
}

fn chi_squared_sf(x: f64, dof: f64) -> f64 {
    ChiSquared::new(dof).map_or(f64::NAN, |d| d.sf(x))
}
