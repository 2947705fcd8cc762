//! The figures of a run scored against its truth: the accuracy of the estimates
//! (docs/theory.md §11) and how well `π` detects the lost measurements (§10).

use super::RunError;
use crate::accuracy::{Accuracy, Detection};
use crate::error::Result;
use crate::io::estimates::EstimatesSummary;

pub(super) struct Scores {
    n: usize,
    accuracy: Accuracy,
    detection: Detection,
}

impl Scores {
    pub(super) fn new(n: usize) -> Self {
        Self {
            n,
            accuracy: Accuracy::new(n),
            detection: Detection::default(),
        }
    }

    /// Scores one step against its truth (`N (n + 1)` values: each subsystem's states, then
    /// `γ`): the estimates `(x̂, P)` (`N·n` and `N·n²`), when given, and `π`, when given.
    pub(super) fn add(
        &mut self,
        truth: &[f64],
        estimates: Option<(&[f64], &[f64])>,
        arrival: Option<&[f64]>,
    ) {
        let n = self.n;
        for (i, row) in truth.chunks_exact(n + 1).enumerate() {
            if let Some((x, p)) = estimates {
                self.accuracy.add(
                    &row[..n],
                    &x[i * n..(i + 1) * n],
                    &p[i * n * n..(i + 1) * n * n],
                );
            }
            if let Some(pi) = arrival {
                self.detection.add(pi[i], row[n]);
            }
        }
    }

    /// The summary of a run: the accuracy with a truth, the detection with a truth and `π`.
    /// Not one scored term is an error, since figures over nothing would read as a perfect
    /// score.
    pub(super) fn summary(&self, truth: bool, arrival: bool) -> Result<EstimatesSummary> {
        if !truth {
            return Ok(EstimatesSummary::default());
        }
        let accuracy = self.accuracy.report();
        if accuracy.terms == 0 {
            return Err(RunError::NothingScored.into());
        }
        Ok(EstimatesSummary {
            accuracy: Some(accuracy),
            detection: arrival.then(|| self.detection.report()),
            loglik: None,
            innovations: None,
            held_out: None,
        })
    }
}
