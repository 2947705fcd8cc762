//! Readings held out of the filter (docs/theory.md §17): a seeded share of the readings in the
//! data is hidden from the run, to which each is a gap (§15), and each is then compared with
//! what the run's estimate of its time says the sensor should read, `J x̂ + R u`, with the
//! variance the run claims for that reading, `J P Jᵀ + M`, and with baselines that need no
//! model: the sensor's own readings interpolated linearly in time, and its last reading
//! before (what a causal filter must beat).
//!
//! This is what can be scored on a recording without a truth: a model whose held-out errors
//! beat the interpolation and whose standardised squares average 1 predicts readings it has
//! not seen, as well as it says it does.

use std::cell::RefCell;

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::CheckedSpec;
use super::{EstimateSink, Note, RunReport, StepEstimates, StepSource, TruthSource};
use crate::accuracy::{HeldOutReport, Z_95};
use crate::error::Result;
use crate::model::Model;

/// Which readings a run keeps from its filter: each reading in the data independently with
/// probability `share`, drawn from a `ChaCha8Rng` seeded with `seed` in the order of the data
/// (step after step, subsystem after subsystem, element after element), so the same data and
/// seed hold out the same readings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoldOut {
    share: f64,
    seed: u64,
}

impl HoldOut {
    /// Holds out each reading with probability `share`; `None` unless `0 < share < 1`.
    pub(super) fn new(share: f64, seed: u64) -> Option<Self> {
        (share > 0.0 && share < 1.0).then_some(Self { share, seed })
    }
}

/// A reading kept from the run: where, its value and the input's part of it, `(R u)_k`.
#[derive(Debug, Clone, Copy)]
struct HeldReading {
    t: usize,
    i: usize,
    k: usize,
    y: f64,
    input: f64,
}

/// What the source hides and the scorer needs: the held readings in the order drawn, and
/// every sensor's readings that the run saw, `(t, y)` in time order.
struct Held {
    rng: ChaCha8Rng,
    share: f64,
    readings: Vec<HeldReading>,
    seen: Vec<Vec<(usize, f64)>>,
}

/// A source that hides the held-out readings of the source it wraps.
struct HidingSource<'a> {
    source: &'a mut dyn StepSource,
    held: &'a RefCell<Held>,
    model: &'a Model,
}

impl StepSource for HidingSource<'_> {
    fn next_step(&mut self, y: &mut [f64], u: &mut [f64]) -> Result<Option<usize>> {
        let Some(t) = self.source.next_step(y, u)? else {
            return Ok(None);
        };
        // A subsystem without a sensor at t has no reading to hold out.
        self.model.blank_unmeasured(t, y);
        let (q, m) = (self.model.dims.q, self.model.dims.m);
        let held = &mut *self.held.borrow_mut();
        for (i, y_i) in y.chunks_exact_mut(q).enumerate() {
            let r = &self.model.params(t, i + 1).R;
            let u_i = &u[i * m..(i + 1) * m];
            for (k, y_ik) in y_i.iter_mut().enumerate().filter(|(_, v)| !v.is_nan()) {
                if held.rng.random::<f64>() < held.share {
                    let input = (0..m).map(|j| r[(k, j)] * u_i[j]).sum();
                    held.readings.push(HeldReading {
                        t,
                        i,
                        k,
                        y: *y_ik,
                        input,
                    });
                    *y_ik = f64::NAN;
                } else {
                    held.seen[i * q + k].push((t, *y_ik));
                }
            }
        }
        Ok(Some(t))
    }

    fn finish(&mut self, steps: usize) -> Result<()> {
        self.source.finish(steps)
    }
}

/// A sink that scores each step's estimates on the readings held out of it, then hands the
/// step on.
struct Scorer<'a> {
    sink: &'a mut dyn EstimateSink,
    held: &'a RefCell<Held>,
    model: &'a Model,
    /// The first held reading not yet scored.
    next: usize,
    /// Per held reading, `(error, claimed variance)` of the run's estimate.
    scored: Vec<(f64, f64)>,
}

impl EstimateSink for Scorer<'_> {
    fn step(&mut self, step: &StepEstimates<'_>) -> Result<()> {
        let n = self.model.dims.n;
        let held = self.held.borrow();
        while let Some(r) = held.readings.get(self.next).filter(|r| r.t <= step.t) {
            let params = self.model.params(r.t, r.i + 1);
            let (j, x) = (&params.J, &step.x[r.i * n..(r.i + 1) * n]);
            let p = &step.p[r.i * n * n..(r.i + 1) * n * n];
            let predicted: f64 = (0..n).map(|a| j[(r.k, a)] * x[a]).sum::<f64>() + r.input;
            // P's block is column-major: P[a, b] = p[b n + a].
            let claimed: f64 = (0..n)
                .flat_map(|a| (0..n).map(move |b| (a, b)))
                .map(|(a, b)| j[(r.k, a)] * p[b * n + a] * j[(r.k, b)])
                .sum::<f64>()
                + params.M[(r.k, r.k)];
            self.scored.push((r.y - predicted, claimed));
            self.next += 1;
        }
        drop(held);
        self.sink.step(step)
    }

    fn note(&mut self, note: Note) {
        self.sink.note(note);
    }
}

/// The baselines at `t` from a sensor's readings `seen` (in time order): their linear
/// interpolation, and the last reading before `t` (a causal filter's counterpart); where there
/// is none on one side, the nearest reading for both. `None` without any.
fn baselines(seen: &[(usize, f64)], t: usize) -> Option<(f64, f64)> {
    let after = seen.partition_point(|&(s, _)| s < t);
    match (after.checked_sub(1).map(|b| seen[b]), seen.get(after)) {
        (Some((t0, y0)), Some(&(t1, y1))) => {
            Some((y0 + (y1 - y0) * (t - t0) as f64 / (t1 - t0) as f64, y0))
        }
        (Some((_, y)), None) | (None, Some(&(_, y))) => Some((y, y)),
        (None, None) => None,
    }
}

/// [`super::stream`] with the readings of `hold` kept from the run and scored against its
/// estimates (docs/theory.md §17): the report's `summary.held_out`. The estimates handed to
/// `sink`, and every other figure of the report, are those of the data without the held-out
/// readings.
pub(super) fn stream_held_out(
    model: &Model,
    spec: &CheckedSpec,
    hold: HoldOut,
    source: &mut dyn StepSource,
    truth: Option<&mut dyn TruthSource>,
    sink: &mut dyn EstimateSink,
) -> Result<RunReport> {
    let held = RefCell::new(Held {
        rng: ChaCha8Rng::seed_from_u64(hold.seed),
        share: hold.share,
        readings: Vec::new(),
        seen: vec![Vec::new(); model.subsystems * model.dims.q],
    });
    let mut hiding = HidingSource {
        source,
        held: &held,
        model,
    };
    let mut scorer = Scorer {
        sink,
        held: &held,
        model,
        next: 0,
        scored: Vec::new(),
    };
    let mut report = super::stream_all(model, spec, &mut hiding, truth, &mut scorer)?;
    let scored = scorer.scored;
    let held = held.into_inner();
    let q = model.dims.q;
    let (mut sq, mut sq_interp, mut sq_last, mut standardised) = (0.0, 0.0, 0.0, 0.0);
    let mut readings = 0usize;
    for (r, (error, claimed)) in held.readings.iter().zip(scored) {
        let Some((interpolated, last)) = baselines(&held.seen[r.i * q + r.k], r.t) else {
            continue;
        };
        sq += error * error;
        sq_interp += (r.y - interpolated).powi(2);
        sq_last += (r.y - last).powi(2);
        standardised += error * error / claimed;
        readings += 1;
    }
    let count = readings.max(1) as f64;
    let half_width = Z_95 * (2.0 / count).sqrt();
    report.summary.held_out = Some(HeldOutReport {
        share: hold.share,
        seed: hold.seed,
        readings,
        unscored: held.readings.len() - readings,
        rmse: (sq / count).sqrt(),
        interpolation_rmse: (sq_interp / count).sqrt(),
        last_reading_rmse: (sq_last / count).sqrt(),
        standardised: standardised / count,
        band: (1.0 - half_width, 1.0 + half_width),
    });
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn interpolates_between_and_takes_the_nearest_at_the_ends() {
        let seen = [(2, 1.0), (6, 3.0)];
        assert_eq!(baselines(&seen, 3), Some((1.5, 1.0)));
        assert_eq!(baselines(&seen, 1), Some((1.0, 1.0)));
        assert_eq!(baselines(&seen, 9), Some((3.0, 3.0)));
        assert_eq!(baselines(&[], 4), None);
    }

    #[test]
    fn a_share_outside_zero_to_one_is_refused() {
        for share in [0.0, 1.0, -0.1, 1.5, f64::NAN] {
            assert!(HoldOut::new(share, 1).is_none(), "{share}");
        }
        assert!(HoldOut::new(0.1, 1).is_some());
    }
}
