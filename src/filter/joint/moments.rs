//! The raw second moments `S_ii = E[x_i x_iᵀ]` that the unknown-dropout update reads
//! (docs/theory.md §8 update step 1, predict step 5): from the band of the moment covariance,
//! the exact lifted moments, or the two-step filter's per-subsystem moments.

use super::{JointFilter, add_process_noise, band_error_at};
use crate::error::Result;
use crate::filter::nahi;
use crate::lifted::{LiftedMoments, LiftedSystem, propagate_mean};
use crate::linalg::band::{BandCholesky, SymBand, completion_precision, sandwich};
use crate::linalg::mat_vec_add;

/// What the filter uses for the raw second moments `S_ii` (docs/theory.md §8 update step 1).
pub(super) enum Moments {
    /// Known-dropout mode: not needed.
    None,
    /// The moment mean and the band of the moment covariance, with its completion to width `w`.
    Band {
        mean: Vec<f64>,
        cov: SymBand,
        completed: SymBand,
        /// The factor of the moment's completion precision (the filter's own factor is kept
        /// for [`JointSchedule`]).
        chol: Box<BandCholesky>,
    },
    /// The exact dense lifted moments (docs/theory.md §3), for tests on small chains.
    Lifted {
        sys: Box<LiftedSystem>,
        moments: Box<LiftedMoments>,
    },
    /// The two-step filter's per-subsystem moments with the filter's own `v̂` (docs/theory.md §4).
    Local {
        mean: Vec<f64>,
        cov: Vec<f64>,
        scratch: Vec<f64>,
        ws: Box<nahi::Workspace>,
    },
}

impl Moments {
    /// Writes `S_ii` of subsystem `i` (0-based, `n` states) into `s`; false where the filter
    /// keeps no moments (known dropouts).
    pub(super) fn second_moment(&self, i: usize, n: usize, s: &mut [f64]) -> bool {
        match self {
            Moments::None => return false,
            Moments::Band { mean, cov, .. } => {
                second_moment(cov.block(i, 0), &mean[i * n..(i + 1) * n], s)
            }
            Moments::Local { mean, cov, .. } => second_moment(
                &cov[i * n * n..(i + 1) * n * n],
                &mean[i * n..(i + 1) * n],
                s,
            ),
            Moments::Lifted { moments, .. } => moments.second_moment(i, n, s),
        }
        true
    }
}

impl JointFilter {
    /// Predict step 5 (`band` moments) and the other moment recursions, from `t` to `t + 1`.
    pub(super) fn propagate_moments(&mut self, u: &[f64]) -> Result<()> {
        let model = &self.model.clone();
        let (n, t) = (model.dims.n, self.t);
        match &mut self.moments {
            Moments::None => {}
            Moments::Band {
                mean,
                cov,
                completed,
                chol,
            } => {
                propagate_mean(
                    model,
                    t,
                    &self.solver,
                    mean,
                    Some(u),
                    &mut self.mean_scratch,
                    &mut self.lifted_ws,
                );
                mean.copy_from_slice(&self.mean_scratch);
                completion_precision(cov, self.k, &mut self.lambda, &mut self.completion)
                    .map_err(|e| (e, "moment"))
                    .and_then(|_| chol.factor(&self.lambda).map_err(|e| (e, "moment")))
                    .map_err(|(e, what)| band_error_at(t, self.loading.eps, self.k, what, e))?;
                chol.selected_inverse(completed);
                sandwich(self.a_eff.band(), completed, cov, &mut self.sandwich);
                add_process_noise(model, t, cov);
            }
            Moments::Lifted { sys, moments } => {
                sys.prepare(model, t)?;
                moments.propagate(model, sys, u);
            }
            Moments::Local {
                mean,
                cov,
                scratch,
                ws,
            } => {
                // v̂ of the mean prediction, left in the workspace by `step`.
                let s = model.dims.s();
                let m = model.dims.m;
                let v = self.lifted_ws.interconnection();
                let window = model.window(t);
                for i in 0..model.subsystems {
                    let prm = model.param_set(window.ids[i]);
                    let mi = &mut self.mean_scratch[i * n..(i + 1) * n];
                    mi.fill(0.0);
                    mat_vec_add(mi, &prm.A, &mean[i * n..(i + 1) * n]);
                    mat_vec_add(mi, &prm.B, &v[i * s..(i + 1) * s]);
                    mat_vec_add(mi, &prm.C, &u[i * m..(i + 1) * m]);
                    let ci = &mut cov[i * n * n..(i + 1) * n * n];
                    scratch.copy_from_slice(ci);
                    nahi::propagate_cov(&prm.A, scratch, Some(&prm.Q), ci, ws);
                }
                mean.copy_from_slice(&self.mean_scratch);
            }
        }
        Ok(())
    }
}

/// `S = P + m mᵀ` (`n × n`, column-major).
fn second_moment(cov: &[f64], mean: &[f64], s: &mut [f64]) {
    let n = mean.len();
    s.copy_from_slice(cov);
    for c in 0..n {
        for r in 0..n {
            s[c * n + r] += mean[r] * mean[c];
        }
    }
}
