//! The analytic gradient of the exact objective with respect to each subsystem's noise
//! variances: the centralized smoother run over arrays held in memory, as
//! [`run::log_likelihood`] runs its filter (docs/theory.md §16, "Each subsystem's own noise").

use crate::error::Result;
use crate::filter::centralized::CentralizedLimits;
use crate::model::Model;
use crate::run::{self, ArraySource, StepSource};
use crate::smoother::score::{NoiseScore, NoiseScorer, ScoreParts};

/// `ℓ` and `∂ℓ/∂Q(i)_kk`, `∂ℓ/∂M(i)_kk` of `model` on the measurements `y` (`T × N × q`, NaN
/// where an element is not received) with inputs `u` (`None`: the model's own), the
/// dropouts known ([`NoiseScorer`]).
pub fn noise_score(
    model: &Model,
    limits: CentralizedLimits,
    parts: ScoreParts,
    y: &[f64],
    u: Option<&[f64]>,
) -> Result<NoiseScore> {
    run::check_measurements(model, y)?;
    let mut source = ArraySource::new(model, y, u)?;
    let mut scorer = NoiseScorer::new(model, parts, limits)?;
    let mut y_t = vec![0.0; model.subsystems * model.dims.q];
    let mut u_t = vec![0.0; model.subsystems * model.dims.m];
    let mut steps = 0;
    while let Some(t) = source.next_step(&mut y_t, &mut u_t)? {
        model.blank_unmeasured(t, &mut y_t);
        scorer.step(&y_t, &u_t)?;
        steps += 1;
    }
    source.finish(steps)?;
    scorer.finish()
}
