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
mod verdict;
mod whiteness;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use statrs::distribution::{ChiSquared, ContinuousCDF, Normal, StudentsT};

use crate::error::{Error, Result};
use crate::filter::kernel::LANES;
use crate::filter::{Dropouts, Update};
use crate::linalg::mat_vec_blocks;
use crate::model::Model;

pub use term::{Term, TermKind, TermScorer, TermWorkspace, scorer};
pub use verdict::{Cause, Fitted, InnovationReport};

use verdict::Findings;
pub use whiteness::{LjungBox, MAX_LAG, Portmanteau};

use whiteness::Series;
/// The steps of a block whose NIS sums estimate the variance of the average NIS
/// (docs/theory.md §14: the terms of neighbouring steps are correlated).
pub const BLOCK_STEPS: usize = 25;
/// The family-wise level of the verdict: a model that fits is rejected in at most this
/// share of runs.
pub const FAMILY_LEVEL: f64 = 0.001;
/// The level of the bands reported beside the figures.
const BAND_LEVEL: f64 = 0.05;
/// The received share is called wrong only where it is further than this share of
/// `min(p, 1 − p)` from `p`.
const SHARE_MARGIN: f64 = 0.05;
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
    /// The rows of a measured subsystem that were not in the data.
    gaps: u64,
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
            chain.gaps += s.gaps;
        }
        chain
    }
}

/// What the terms of one step are scored from.
struct StepData<'a> {
    model: &'a Model,
    kind: TermKind,
    t: usize,
    mean: &'a [f64],
    cov: &'a [f64],
    /// The filter's second moments `S` (`N·n²`), read by Nahi's update's terms.
    moment: Option<&'a [f64]>,
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
                        step.moment.map(|s| &s[i * nn..(i + LANES) * nn]),
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
            let moment = step.moment.map(|s| &s[i * nn..(i + 1) * nn]);
            let term = match self
                .scorer
                .term(step.kind, prm, p, mean, cov, moment, y, ru)
            {
                Some(term) => term,
                // A prior that is no longer finite is the filter's breakdown, which the run
                // reports as such: the term is not scored.
                None if !mean.iter().chain(cov).all(|v| v.is_finite()) => Term::UNSCORED,
                None => return Some(i + 1),
            };
            if window.measured[i] {
                tallies[k].gaps += (q - term.received) as u64;
            }
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
    /// the diagonal blocks of its covariance (`N·n²`, column-major); with Nahi's update, the
    /// diagonal blocks of the second moment `S` its gain reads at `t` (`N·n²`), which
    /// standardise the whiteness series (docs/theory.md §14). Steps come in order.
    /// Long chains are scored in parallel, in chunks; the sums over the chain are added in
    /// chunk order, so the figures do not depend on the thread count.
    pub fn step(
        &mut self,
        t: usize,
        mean: &[f64],
        cov: &[f64],
        moment: Option<&[f64]>,
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
            moment: moment.filter(|_| self.kind == TermKind::Nahi),
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
        // The tests of the family: the chain's NIS, the correlation z_w, the portmanteau,
        // the received share, and the subsystems' NIS (one test at level α / N each).
        let tests = 4 + usize::from(unknown);
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
        let pooled = whiteness::pooled(&self.series, q, lags);
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
        let findings = Findings::of(
            at_level.z,
            level,
            nis.rejected,
            pooled.as_ref(),
            received_share.as_ref(),
            per_subsystem.iter().any(|s| s.stands_out),
        );
        InnovationReport {
            statistic: if self.kind == TermKind::Mixture {
                Statistic::NisPi
            } else {
                Statistic::Nis
            },
            terms: chain.received as u64,
            gaps: chain.gaps,
            average_nis: nis.average,
            band: nis.band,
            band_basis: nis.basis,
            ljung_box,
            z1: pooled.as_ref().map(|p| p.z1),
            z_w: pooled.as_ref().map(|p| p.z_w),
            rho_w: pooled.as_ref().map(|p| p.rho_w),
            spatial_factor: pooled.as_ref().and_then(|p| p.spatial_factor),
            portmanteau: pooled.map(|p| p.portmanteau),
            worst_subsystem,
            received_share,
            verdict: findings.causes(),
            level: FAMILY_LEVEL,
            fitted: None,
            distributed: self.distributed,
            findings,
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

/// The share of readings the data say arrived, `Σ π / terms`, against the band of `p`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReceivedShare {
    pub share: f64,
    /// The mean configured `p` over the terms.
    pub expected: f64,
    /// The 95 % binomial band of the share for the configured `p`.
    pub band: [f64; 2],
    /// Outside its band at the test's level, and beyond the margin.
    #[serde(skip)]
    pub(crate) rejected: bool,
}

impl ReceivedShare {
    fn of(tally: &Tally, shown: Critical, at_level: Critical) -> Option<Self> {
        if tally.arrival_terms == 0 {
            return None;
        }
        let terms = tally.arrival_terms as f64;
        let (share, expected) = (tally.arrival / terms, tally.p / terms);
        let sd = tally.p_variance.sqrt() / terms;
        // A share within a few per cent of p is not called wrong however long the run:
        // the share's own estimate is biased by about 0.001 (docs/theory.md §14).
        let margin = SHARE_MARGIN * expected.min(1.0 - expected);
        let (half, verdict) = (shown.z * sd, (at_level.z * sd).max(margin));
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
