//! The objective's band (docs/theory.md §16 "The band"): the joint filter's log-likelihood
//! drifts from the centralized filter's as its band narrows (on a chain of masses on springs,
//! 100 nats at band 2 of 20 subsystems), so a fit that is not told the band chooses it: the
//! cheapest objective whose log-likelihood at the configured values is within
//! [`LOGLIK_TOL`] of the exact one's (or, where the centralized filter is not affordable, of
//! the next wider band's).

use serde::Serialize;

use crate::error::Result;
use crate::filter::joint::{DEFAULT_BAND, flops_per_subsystem_step};
use crate::filter::{FilterKind, SecondMoment, Update};
use crate::interconnect::ChainSolver;
use crate::lifted::a_eff_band;
use crate::model::Model;
use crate::run::{self, CheckedSpec};

/// Two objectives agree when their log-likelihoods at one point differ by at most this many
/// nats: a twentieth of the 1.92 nats that bound a 95 % likelihood-ratio interval.
pub const LOGLIK_TOL: f64 = 0.1;

/// An objective: the joint filter at a band `k`, or (`band = None`) the centralized filter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Candidate {
    pub band: Option<usize>,
    /// The leading flop count of one step (docs/theory.md §7, §8 "Cost").
    pub flops: f64,
    /// `ℓ` at the configured values, where it was computed.
    pub loglik: Option<f64>,
}

impl Candidate {
    /// `band 4`, `centralized`.
    pub fn name(&self) -> String {
        match self.band {
            Some(k) => format!("band {k}"),
            None => "centralized".to_string(),
        }
    }
}

/// Which objective a fit maximised and why (the `objective` of `fit --format json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ObjectiveChoice {
    /// The joint filter's band, `None` for the centralized filter.
    pub band: Option<usize>,
    /// Chosen by the fit (by the band's log-likelihood, or, with nothing `tried`, for the
    /// exact gradient of each subsystem's own variances); false where `--band` or `--filter
    /// centralized` fixed it.
    pub chosen: bool,
    /// The candidates, cheapest first, up to the one chosen and the one it was checked
    /// against (each with its `ℓ` at the configured values).
    pub tried: Vec<Candidate>,
    /// The next wider objective after the one maximised (`None` for the centralized filter):
    /// its `ℓ` at the estimate minus the objective's, `gap_at_estimate`.
    pub reference: Option<Candidate>,
    pub gap_at_estimate: Option<f64>,
}

impl ObjectiveChoice {
    /// The objective's filter.
    pub fn filter(&self) -> FilterKind {
        match self.band {
            Some(_) => FilterKind::Joint,
            None => FilterKind::Centralized,
        }
    }

    /// A line for the report: what was maximised, how it was chosen, and how far the next
    /// wider objective is at the estimate.
    pub fn line(&self) -> String {
        let objective = match self.band {
            Some(k) => format!("the joint filter at band {k}"),
            None => "the centralized filter (the exact covariances)".to_string(),
        };
        let how = if self.chosen && self.tried.is_empty() {
            ", chosen for its exact gradient of each subsystem's own variances (docs/theory.md §16); --band K fixes the joint filter's band instead".to_string()
        } else if self.chosen {
            let tried: Vec<String> = self
                .tried
                .iter()
                .filter_map(|c| c.loglik.map(|l| format!("{} {l:.3}", c.name())))
                .collect();
            let within = match self.reference.map(|r| r.band) {
                Some(None) => {
                    format!("the cheapest within {LOGLIK_TOL} nat of the centralized filter's")
                }
                Some(Some(_)) => {
                    format!("the cheapest within {LOGLIK_TOL} nat of the next wider band's")
                }
                None => {
                    format!("the exact one: no cheaper candidate is within {LOGLIK_TOL} nat of it")
                }
            };
            format!(
                ", chosen as {within} (log-likelihood at the configured values: {}); --band K fixes it",
                tried.join(", ")
            )
        } else {
            String::new()
        };
        let gap = match (self.reference, self.gap_at_estimate) {
            (Some(reference), Some(gap)) => {
                format!(
                    "; at the estimate {} differs by {gap:+.3} nat",
                    reference.name()
                )
            }
            _ => String::new(),
        };
        format!("objective: {objective}{how}{gap}")
    }

    /// A warning when the next wider objective is more than [`LOGLIK_TOL`] away at the
    /// estimate: the band's log-likelihood has not converged where the fit ended.
    pub fn warning(&self) -> Option<String> {
        let (reference, gap) = (self.reference?, self.gap_at_estimate?);
        (gap.abs() > LOGLIK_TOL).then(|| {
            let band = self.band.map_or(String::new(), |k| format!("band {k}"));
            let wider = match reference.band {
                Some(k) => format!("--band {k}"),
                None => "--filter centralized".to_string(),
            };
            format!(
                "at the estimate the log-likelihood of {band} is {:.2} nat from that of {} (more than {LOGLIK_TOL}): the band has not converged there; fit again with {wider}",
                gap.abs(),
                reference.name()
            )
        })
    }
}

/// The objectives in order of cost: the joint filter at bands 2, 4, 8, … below `N − 1`
/// cheaper than the centralized filter, then the centralized filter where the chain has at
/// most `max_lifted` lifted states, else the joint filter at `N − 1` (exact too).
pub fn ladder(model: &Model, spec: &CheckedSpec) -> Result<Vec<Candidate>> {
    let (big_n, n, q) = (model.subsystems, model.dims.n, model.dims.q);
    let widest = big_n - 1;
    let joint = spec.joint_options().unwrap_or_default();
    let solver = ChainSolver::new(model, 1)?;
    let b = a_eff_band(model, 1, &solver, joint.band_tol, spec.max_memory())?.half_width();
    let band_moment = joint.second_moment == SecondMoment::Band && spec.update() == Update::Linear;
    let joint_flops =
        |k: usize| big_n as f64 * flops_per_subsystem_step(n, k, b, big_n, band_moment);
    let exact = (big_n * n <= spec.max_lifted()).then(|| Candidate {
        band: None,
        flops: centralized_flops(big_n * n, big_n * q),
        loglik: None,
    });
    let ceiling = exact.map_or(f64::INFINITY, |c| c.flops);
    let mut candidates: Vec<Candidate> = std::iter::successors(Some(DEFAULT_BAND), |k| Some(2 * k))
        .take_while(|&k| k < widest)
        .map(|k| Candidate {
            band: Some(k),
            flops: joint_flops(k),
            loglik: None,
        })
        .take_while(|c| c.flops < ceiling)
        .collect();
    candidates.push(exact.unwrap_or(Candidate {
        band: Some(widest),
        flops: joint_flops(widest),
        loglik: None,
    }));
    Ok(candidates)
}

/// The leading flop count of one step of the centralized filter on `size` lifted states and
/// `rows` measurement rows (docs/theory.md §7): the prediction `A_eff P A_effᵀ` by dense
/// products, `2 size³`, and the update's `V = L⁻¹ H T` and `Vᵀ V`, `2 rows size²`.
fn centralized_flops(size: usize, rows: usize) -> f64 {
    let (size, rows) = (size as f64, rows as f64);
    2.0 * size.powi(3) + 2.0 * rows * size * size
}

/// The log-likelihood of `spec` run with `candidate`'s objective.
fn loglik(
    model: &Model,
    spec: &CheckedSpec,
    candidate: &Candidate,
    y: &[f64],
    u: Option<&[f64]>,
) -> Result<f64> {
    Ok(
        run::log_likelihood(model, &spec.with_band(candidate.band), y, u)?
            .iter()
            .sum(),
    )
}

/// The cheapest candidate of the [`ladder`] whose `ℓ` at `model`'s values is within
/// [`LOGLIK_TOL`] of the exact one's where the centralized filter is affordable (one run of it
/// against the hundreds of a fit), else of the next wider candidate's; the last, exact, when
/// none is. Returns it, the candidate it was checked against (its reference at the estimate),
/// and the candidates computed, cheapest first.
pub fn choose(
    model: &Model,
    spec: &CheckedSpec,
    y: &[f64],
    u: Option<&[f64]>,
) -> Result<(Candidate, Option<Candidate>, Vec<Candidate>)> {
    let mut ladder = ladder(model, spec)?;
    let at = |ladder: &mut [Candidate], i: usize| -> Result<f64> {
        if let Some(l) = ladder[i].loglik {
            return Ok(l);
        }
        let l = loglik(model, spec, &ladder[i], y, u)?;
        ladder[i].loglik = Some(l);
        Ok(l)
    };
    let last = ladder.len() - 1;
    let exact = ladder[last].band.is_none();
    let mut found = None;
    for k in 0..last {
        let reference = if exact { last } else { k + 1 };
        let r = at(&mut ladder, reference)?;
        if (at(&mut ladder, k)? - r).abs() <= LOGLIK_TOL {
            found = Some((k, reference));
            break;
        }
    }
    let (chosen, reference) = match found {
        Some((k, reference)) => (ladder[k], Some(ladder[reference])),
        None => {
            at(&mut ladder, last)?;
            (ladder[last], None)
        }
    };
    let tried = ladder.into_iter().filter(|c| c.loglik.is_some()).collect();
    Ok((chosen, reference, tried))
}

/// The objective next wider than a fixed `band` (twice the band, or the exact one when that
/// reaches `N − 1` or costs more), its reference at the estimate.
pub fn wider_than(model: &Model, spec: &CheckedSpec, band: usize) -> Result<Option<Candidate>> {
    if band + 1 >= model.subsystems {
        return Ok(None);
    }
    let ladder = ladder(model, spec)?;
    Ok(ladder
        .iter()
        .find(|c| c.band.is_none_or(|k| k > band))
        .copied())
}

/// `ℓ(reference) − ℓ(objective)` at the fitted model.
pub fn gap(
    fitted: &Model,
    spec: &CheckedSpec,
    reference: &Candidate,
    objective_loglik: f64,
    y: &[f64],
    u: Option<&[f64]>,
) -> Result<f64> {
    Ok(loglik(fitted, spec, reference, y, u)? - objective_loglik)
}
