//! The joint filter's covariance pass stored once and replayed for every run of `evaluate`
//! (docs/theory.md §8): [`JointSchedule`] and [`ScheduledJoint`].

use super::{JointFilter, JointOptions};
use crate::error::{Error, Result};
use crate::filter::{ChainFilter, Dropouts, SecondMoment, Update, nahi};
use crate::interconnect::ChainSolver;
use crate::lifted::{LiftedWorkspace, propagate_mean};
use crate::linalg::band::BandCholesky;
use crate::model::Model;

/// One step of a [`JointSchedule`].
struct ScheduledStep {
    /// The Cholesky factor of `Λ⁺(t)`, as much of it as solves need.
    chol: BandCholesky,
    /// Every subsystem's `R_i⁻¹ H_i` (`q × n`, column-major), so that `r_i = (R_i⁻¹ H_i)ᵀ ỹ_i`.
    gains: Vec<f64>,
    block_filt: Vec<f64>,
    block_pred: Vec<f64>,
}

/// The covariance pass of the unknown-dropout joint filter with the `band` or `lifted`
/// moment, stored per step. It depends on the model and the inputs only, not on the
/// measurements (docs/theory.md §8), so `evaluate` computes it once and replays it for every run with
/// [`ScheduledJoint`], which costs a banded solve and a chain solve per step.
pub struct JointSchedule {
    model: Model,
    steps: Vec<ScheduledStep>,
}

impl JointSchedule {
    /// Bytes a schedule of `steps` steps needs with band `k`.
    pub fn bytes(model: &Model, k: usize, steps: usize) -> usize {
        let (n, q, big_n) = (model.dims.n, model.dims.q, model.subsystems);
        let per_step = BandCholesky::solve_only_len(big_n, n, k) + big_n * (q * n + 2 * n * n);
        steps * size_of::<f64>() * per_step
    }

    /// Runs the covariance pass for the inputs `u[t]` (`N·m` values per step).
    pub fn new(model: &Model, opts: JointOptions, u: &[Vec<f64>]) -> Result<Self> {
        if opts.dropouts == Dropouts::Known
            || opts.second_moment == SecondMoment::Local
            || opts.update == Update::Mixture
        {
            return Err(Error::Usage(
                "the joint filter's covariance pass depends on the data in the known-dropout mode, with the local moment and with the mixture update".into(),
            ));
        }
        let mut filter = JointFilter::new(model, opts)?;
        let (n, q, big_n) = (model.dims.n, model.dims.q, model.subsystems);
        filter.recorded_gains = Some(vec![0.0; big_n * q * n]);
        let mut y = vec![0.0; big_n * q];
        let mut steps = Vec::with_capacity(u.len());
        for (t0, ut) in u.iter().enumerate() {
            // The rows of subsystems without a sensor are left out of the gains too.
            y.fill(0.0);
            model.blank_unmeasured(t0 + 1, &mut y);
            filter.step(&y, ut)?;
            steps.push(ScheduledStep {
                chol: filter.chol.clone_for_solves(),
                gains: filter.recorded_gains.clone().expect("recording"),
                block_filt: filter.block_filt.clone(),
                block_pred: filter.block_pred.clone(),
            });
        }
        Ok(Self {
            model: model.clone(),
            steps,
        })
    }
}

/// The joint filter replayed from a [`JointSchedule`]: only the means are computed. Equal to
/// [`JointFilter`] with the same options.
pub struct ScheduledJoint<'s> {
    sched: &'s JointSchedule,
    t: usize,
    solver: ChainSolver,
    x_pred: Vec<f64>,
    x_filt: Vec<f64>,
    r: Vec<f64>,
    innov: Vec<f64>,
    lifted_ws: LiftedWorkspace,
}

impl<'s> ScheduledJoint<'s> {
    pub fn new(sched: &'s JointSchedule) -> Result<Self> {
        let model = &sched.model;
        let (n, q, big_n) = (model.dims.n, model.dims.q, model.subsystems);
        let x = model.initial.means();
        Ok(Self {
            sched,
            t: 1,
            solver: ChainSolver::new(model, 1)?,
            x_filt: x.clone(),
            x_pred: x,
            r: vec![0.0; big_n * n],
            innov: vec![0.0; big_n * q],
            lifted_ws: LiftedWorkspace::default(),
        })
    }
}

impl ChainFilter for ScheduledJoint<'_> {
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &self.sched.model;
        let (n, q) = (model.dims.n, model.dims.q);
        let t = self.t;
        let Some(step) = self.sched.steps.get(t - 1) else {
            return Err(Error::Usage(format!(
                "the joint filter's schedule ends before t = {t}"
            )));
        };
        crate::filter::refuse_gaps(model, y, t, "the joint filter's schedule")?;
        nahi::chain_innovations(model, t, y, u, &self.x_pred, &mut self.innov);
        for i in 0..model.subsystems {
            let w = &step.gains[i * q * n..(i + 1) * q * n];
            let innov = &self.innov[i * q..(i + 1) * q];
            for c in 0..n {
                // A row without a sensor has a zero gain and no innovation (NaN).
                self.r[i * n + c] = (0..q)
                    .filter(|&k| !innov[k].is_nan())
                    .map(|k| w[c * q + k] * innov[k])
                    .sum();
            }
        }
        step.chol.solve_in_place(&mut self.r);
        for ((xf, xp), dx) in self.x_filt.iter_mut().zip(&self.x_pred).zip(&self.r) {
            *xf = xp + dx;
        }
        self.solver.prepare(model, t)?;
        propagate_mean(
            model,
            t,
            &self.solver,
            &self.x_filt,
            Some(u),
            &mut self.x_pred,
            &mut self.lifted_ws,
        );
        self.t += 1;
        Ok(())
    }

    fn filtered(&self) -> (&[f64], &[f64]) {
        (&self.x_filt, &self.sched.steps[self.t - 2].block_filt)
    }

    fn predicted(&self) -> (&[f64], &[f64]) {
        (&self.x_pred, &self.sched.steps[self.t - 2].block_pred)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// [`JointSchedule::bytes`], which `evaluate` weighs before building a schedule, is what
    /// a schedule holds: at a narrow band, and at `k = 32`, where each row of the factor gets
    /// a block of padding (`k n² · 8` bytes is a multiple of 1 KiB).
    #[test]
    fn bytes_are_what_the_schedule_holds() {
        let text = "subsystems = 40\nsteps = 3\n[interconnection]\nplus = 1\nminus = 1\n\
                    [model]\nA = [[0.9, 0.1], [0.0, 0.8]]\nB = [[0.1, 0.0], [0.0, 0.1]]\n\
                    D = [[0.3, 0.0], [0.0, 0.3]]\nG = [[0.1, 0.0], [0.0, 0.1]]\n\
                    J = [[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]\nM = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]]\n\
                    Q = [[0.01, 0.0], [0.0, 0.01]]\n[dropout]\np = 0.8\n\
                    [initial]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n";
        let model = Model::from_toml_str("s.toml", Path::new("."), text).unwrap();
        let u = vec![Vec::new(); model.horizon().unwrap()];
        for band in [1, 32] {
            let opts = JointOptions {
                band,
                ..JointOptions::default()
            };
            let sched = JointSchedule::new(&model, opts, &u).unwrap();
            let held: usize = sched
                .steps
                .iter()
                .map(|s| {
                    s.chol.len_held() + s.gains.len() + s.block_filt.len() + s.block_pred.len()
                })
                .sum();
            assert_eq!(
                held * size_of::<f64>(),
                JointSchedule::bytes(&model, band, model.horizon().unwrap()),
                "band {band}"
            );
        }
    }
}
