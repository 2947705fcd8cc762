//! The two-step distributed filter (SPEC §2–§4): at each time step every subsystem runs its
//! local Nahi update, step 1 solves the interconnection signals `v̂` along the chain from the
//! estimates, and every subsystem predicts with `v̂` taken as a known input.
//!
//! State is kept in flat arrays, subsystem after subsystem (`N·n` means, `N·n²` column-major
//! covariances). The local updates and predictions of long chains run in parallel over chunks
//! of subsystems (rayon); each subsystem's arithmetic is the same whatever the thread count,
//! so the results are too. Step 1 is a sequential sweep.

use nalgebra::DMatrix;
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::filter::kernel::{DynamicKernel, FixedKernel, LocalData, LocalKernel};
use crate::filter::{ChainFilter, Dropouts, InterconnectFrom, SecondMoment, TwoStepOptions};
use crate::interconnect::Interconnect;
use crate::lifted::{LiftedMoments, LiftedSystem};
use crate::linalg::mat_vec_add;
use crate::model::Model;

/// Chains at least this long run step 2 in parallel, in chunks of [`CHUNK`] subsystems.
const PARALLEL_MIN: usize = 4096;
const CHUNK: usize = 1024;

/// The filter's state between time steps; `K` does the per-subsystem arithmetic (use
/// [`two_step`] to get the fastest kernel for the model's sizes).
pub struct TwoStepFilter<'m, K: LocalKernel = DynamicKernel> {
    model: &'m Model,
    opts: TwoStepOptions,
    solver: Interconnect,
    /// The next time step to process.
    t: usize,
    /// `x̂(t|t−1)` and `T(t)` before a step, `x̂(t+1|t)` and `T(t+1)` after it.
    x_pred: Vec<f64>,
    t_pred: Vec<f64>,
    /// `x̂(t|t)`, `P(t|t)` of the last step.
    x_filt: Vec<f64>,
    p_filt: Vec<f64>,
    /// `local`: the mean `m` and covariance `Pₓ` of `x`; `paper`: `S` in `moment_cov`.
    moment_mean: Vec<f64>,
    moment_cov: Vec<f64>,
    /// `lifted`: the exact moments of the lifted system.
    lifted: Option<(LiftedSystem, LiftedMoments)>,
    z: Vec<f64>,
    v: Vec<f64>,
    solve_scratch: Vec<f64>,
    kernel: K,
    scratch: Scratch,
    solver_error: f64,
}

/// Per-thread scratch of the local work.
#[derive(Clone)]
struct Scratch {
    /// `S` of the current subsystem (`n × n`), and a matrix for the lifted moments.
    s_buf: Vec<f64>,
    s_mat: DMatrix<f64>,
    ru: Vec<f64>,
    cov: Vec<f64>,
    mean: Vec<f64>,
}

impl Scratch {
    fn new(n: usize, q: usize) -> Self {
        Self {
            s_buf: vec![0.0; n * n],
            s_mat: DMatrix::zeros(n, n),
            ru: vec![0.0; q],
            cov: vec![0.0; n * n],
            mean: vec![0.0; n],
        }
    }
}

/// What the local updates read at time `t`.
struct UpdateInputs<'a> {
    model: &'a Model,
    t: usize,
    known: bool,
    second_moment: SecondMoment,
    lifted: Option<&'a LiftedMoments>,
    x_pred: &'a [f64],
    t_pred: &'a [f64],
    moment_mean: &'a [f64],
    moment_cov: &'a [f64],
    y: &'a [f64],
    u: &'a [f64],
}

/// The Nahi updates of subsystems `first..first + x_filt.len() / n` (0-based).
fn update_range<K: LocalKernel>(
    inp: &UpdateInputs,
    kernel: &mut K,
    sc: &mut Scratch,
    first: usize,
    x_filt: &mut [f64],
    p_filt: &mut [f64],
) -> Result<()> {
    let model = inp.model;
    let d = model.dims;
    let (n, q, m) = (d.n, d.q, d.m);
    let window = model.window(inp.t);
    for (k, (xf, pf)) in x_filt
        .chunks_mut(n)
        .zip(p_filt.chunks_mut(n * n))
        .enumerate()
    {
        let i = first + k;
        let prm = model.param_set(window.ids[i]);
        let (nn, vi) = (i * n * n..(i + 1) * n * n, i * n..(i + 1) * n);
        if let Some(moments) = inp.lifted {
            moments.second_moment(i, n, &mut sc.s_mat);
            sc.s_buf.copy_from_slice(sc.s_mat.as_slice());
        } else if !inp.known {
            sc.s_buf.copy_from_slice(&inp.moment_cov[nn.clone()]);
            if inp.second_moment == SecondMoment::Local {
                let mean = &inp.moment_mean[vi.clone()];
                for c in 0..n {
                    for r in 0..n {
                        sc.s_buf[c * n + r] += mean[r] * mean[c];
                    }
                }
            }
        }
        sc.ru.fill(0.0);
        mat_vec_add(&mut sc.ru, &prm.R, &inp.u[i * m..(i + 1) * m]);
        let data = LocalData {
            y: &inp.y[i * q..(i + 1) * q],
            ru: &sc.ru,
            p: if inp.known { 1.0 } else { window.p[i] },
            known: inp.known,
        };
        let ok = kernel.update(
            window.ids[i],
            &data,
            &sc.s_buf,
            &inp.x_pred[vi],
            &inp.t_pred[nn],
            xf,
            pf,
        );
        if !ok {
            return Err(Error::Numerical {
                t: inp.t,
                i: i + 1,
                msg: "the innovation covariance Σ is not positive definite".into(),
            });
        }
    }
    Ok(())
}

/// What the local predictions read at time `t`.
struct PredictInputs<'a> {
    model: &'a Model,
    t: usize,
    known: bool,
    second_moment: SecondMoment,
    x_filt: &'a [f64],
    p_filt: &'a [f64],
    v: &'a [f64],
    u: &'a [f64],
}

/// The outputs of the local predictions of a range of subsystems.
struct PredictOutputs<'a> {
    x_pred: &'a mut [f64],
    t_pred: &'a mut [f64],
    moment_mean: &'a mut [f64],
    moment_cov: &'a mut [f64],
}

/// `x̂⁺ = A x̂(t|t) + B v̂ + C u`, `T⁺ = A P Aᵀ + Q` and the moments, for subsystems from
/// `first` on (0-based).
fn predict_range<K: LocalKernel>(
    inp: &PredictInputs,
    kernel: &mut K,
    sc: &mut Scratch,
    first: usize,
    out: PredictOutputs,
) {
    let model = inp.model;
    let d = model.dims;
    let (n, m, s) = (d.n, d.m, d.s());
    let window = model.window(inp.t);
    let count = out.x_pred.len() / n;
    for k in 0..count {
        let i = first + k;
        let prm = model.param_set(window.ids[i]);
        let set = window.ids[i];
        let (nn, vi) = (i * n * n..(i + 1) * n * n, i * n..(i + 1) * n);
        let (kn, kv) = (k * n * n..(k + 1) * n * n, k * n..(k + 1) * n);
        let (vv, ui) = (&inp.v[i * s..(i + 1) * s], &inp.u[i * m..(i + 1) * m]);
        let xp = &mut out.x_pred[kv.clone()];
        xp.fill(0.0);
        mat_vec_add(xp, &prm.A, &inp.x_filt[vi]);
        mat_vec_add(xp, &prm.B, vv);
        mat_vec_add(xp, &prm.C, ui);
        kernel.propagate(set, true, &inp.p_filt[nn], &mut out.t_pred[kn.clone()]);
        if inp.known {
            continue;
        }
        let cov = &mut out.moment_cov[kn];
        sc.cov.copy_from_slice(cov);
        match inp.second_moment {
            SecondMoment::Local => {
                kernel.propagate(set, true, &sc.cov, cov);
                let mean = &mut out.moment_mean[kv];
                sc.mean.copy_from_slice(mean);
                mean.fill(0.0);
                mat_vec_add(mean, &prm.A, &sc.mean);
                mat_vec_add(mean, &prm.B, vv);
                mat_vec_add(mean, &prm.C, ui);
            }
            SecondMoment::Paper => kernel.propagate(set, false, &sc.cov, cov),
            SecondMoment::Lifted => {}
        }
    }
}

/// The two-step filter with the fastest kernel for the model's `(n, q)`: compile-time sizes
/// for `n ≤ 4`, `q ≤ 2`, dynamic sizes otherwise.
pub fn two_step<'m>(model: &'m Model, opts: TwoStepOptions) -> Result<Box<dyn ChainFilter + 'm>> {
    macro_rules! fixed {
        ($(($n:literal, $q:literal)),*) => {
            match (model.dims.n, model.dims.q) {
                $(($n, $q) => Box::new(TwoStepFilter::<FixedKernel<$n, $q>>::with_kernel(model, opts)?),)*
                _ => Box::new(TwoStepFilter::new(model, opts)?),
            }
        };
    }
    Ok(fixed!(
        (1, 1),
        (1, 2),
        (2, 1),
        (2, 2),
        (3, 1),
        (3, 2),
        (4, 1),
        (4, 2)
    ))
}

impl<'m> TwoStepFilter<'m, DynamicKernel> {
    /// The filter with dynamic sizes (any `n`, `q`); see [`two_step`] for the fast path.
    pub fn new(model: &'m Model, opts: TwoStepOptions) -> Result<Self> {
        Self::with_kernel(model, opts)
    }
}

impl<'m, K: LocalKernel> TwoStepFilter<'m, K> {
    /// Initial values of SPEC §3: `x̂(1) = m0`, `T(1) = P0`, `S(1) = P0 + m0 m0ᵀ`.
    pub fn with_kernel(model: &'m Model, opts: TwoStepOptions) -> Result<Self> {
        let d = model.dims;
        let (n, big_n) = (d.n, model.subsystems);
        let m0 = model.initial_mean.as_slice();
        let p0 = model.initial_cov.as_slice();
        let x_pred: Vec<f64> = m0.iter().copied().cycle().take(big_n * n).collect();
        let t_pred: Vec<f64> = p0.iter().copied().cycle().take(big_n * n * n).collect();
        let mut moment_cov = t_pred.clone();
        if opts.second_moment == SecondMoment::Paper {
            for cov in moment_cov.chunks_mut(n * n) {
                for r in 0..n {
                    for c in 0..n {
                        cov[c * n + r] += m0[r] * m0[c];
                    }
                }
            }
        }
        let solver = Interconnect::new(opts.solver, model, 1)?;
        let solver_error = solver.error_estimate();
        let lifted = if opts.second_moment == SecondMoment::Lifted {
            Some((LiftedSystem::new(model, 1)?, LiftedMoments::initial(model)))
        } else {
            None
        };
        Ok(Self {
            model,
            opts,
            solver,
            t: 1,
            x_filt: x_pred.clone(),
            p_filt: t_pred.clone(),
            moment_mean: x_pred.clone(),
            x_pred,
            t_pred,
            moment_cov,
            lifted,
            z: vec![0.0; big_n * d.s()],
            v: vec![0.0; big_n * d.s()],
            solve_scratch: Vec::new(),
            kernel: K::new(model),
            scratch: Scratch::new(n, d.q),
            solver_error,
        })
    }
}

impl<K: LocalKernel> ChainFilter for TwoStepFilter<'_, K> {
    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = self.model;
        let d = model.dims;
        let (n, m, s, big_n) = (d.n, d.m, d.s(), model.subsystems);
        let t = self.t;
        self.solver.prepare(model, t)?;
        self.solver_error = self.solver_error.max(self.solver.error_estimate());
        let window = model.window(t);
        let known = self.opts.dropouts == Dropouts::Known;
        let parallel = big_n >= PARALLEL_MIN && rayon::current_num_threads() > 1;

        let inp = UpdateInputs {
            model,
            t,
            known,
            second_moment: self.opts.second_moment,
            lifted: self.lifted.as_ref().map(|(_, mom)| mom),
            x_pred: &self.x_pred,
            t_pred: &self.t_pred,
            moment_mean: &self.moment_mean,
            moment_cov: &self.moment_cov,
            y,
            u,
        };
        if parallel {
            let (kernel, scratch) = (&self.kernel, &self.scratch);
            self.x_filt
                .par_chunks_mut(CHUNK * n)
                .zip(self.p_filt.par_chunks_mut(CHUNK * n * n))
                .enumerate()
                .try_for_each_init(
                    || (kernel.clone(), scratch.clone()),
                    |(k, sc), (c, (xf, pf))| update_range(&inp, k, sc, c * CHUNK, xf, pf),
                )?;
        } else {
            update_range(
                &inp,
                &mut self.kernel,
                &mut self.scratch,
                0,
                &mut self.x_filt,
                &mut self.p_filt,
            )?;
        }

        // Step 1: v̂ from z = D x̂ + H u.
        let source = match self.opts.interconnect_from {
            InterconnectFrom::Filtered => &self.x_filt,
            InterconnectFrom::Predicted => &self.x_pred,
        };
        self.z.fill(0.0);
        for i in 0..big_n {
            let prm = model.param_set(window.ids[i]);
            let zi = &mut self.z[i * s..(i + 1) * s];
            mat_vec_add(zi, &prm.D, &source[i * n..(i + 1) * n]);
            mat_vec_add(zi, &prm.H, &u[i * m..(i + 1) * m]);
        }
        self.solver
            .solve(&self.z, &mut self.v, &mut self.solve_scratch);

        let inp = PredictInputs {
            model,
            t,
            known,
            second_moment: self.opts.second_moment,
            x_filt: &self.x_filt,
            p_filt: &self.p_filt,
            v: &self.v,
            u,
        };
        if parallel {
            let (kernel, scratch) = (&self.kernel, &self.scratch);
            self.x_pred
                .par_chunks_mut(CHUNK * n)
                .zip(self.t_pred.par_chunks_mut(CHUNK * n * n))
                .zip(self.moment_mean.par_chunks_mut(CHUNK * n))
                .zip(self.moment_cov.par_chunks_mut(CHUNK * n * n))
                .enumerate()
                .for_each_init(
                    || (kernel.clone(), scratch.clone()),
                    |(k, sc), (c, (((xp, tp), mm), mc))| {
                        let out = PredictOutputs {
                            x_pred: xp,
                            t_pred: tp,
                            moment_mean: mm,
                            moment_cov: mc,
                        };
                        predict_range(&inp, k, sc, c * CHUNK, out)
                    },
                );
        } else {
            let out = PredictOutputs {
                x_pred: &mut self.x_pred,
                t_pred: &mut self.t_pred,
                moment_mean: &mut self.moment_mean,
                moment_cov: &mut self.moment_cov,
            };
            predict_range(&inp, &mut self.kernel, &mut self.scratch, 0, out);
        }
        if let Some((sys, moments)) = &mut self.lifted {
            sys.prepare(model, t)?;
            moments.propagate(sys, u);
        }
        // A blown-up step 1 (e.g. the transfer solver on a long chain) must not pass as data.
        let n2 = n * n;
        if let Some(i) = (0..model.subsystems).find(|&i| {
            !self.x_pred[i * n..(i + 1) * n]
                .iter()
                .all(|v| v.is_finite())
                || !self.t_pred[i * n2..(i + 1) * n2]
                    .iter()
                    .all(|v| v.is_finite())
        }) {
            let hint = if self.solver_error > crate::interconnect::TRANSFER_ERROR_WARNING {
                format!(
                    " (the transfer solver's estimated relative error is {:.1e}; use --solver banded)",
                    self.solver_error
                )
            } else {
                String::new()
            };
            let what = if self.t_pred[i * n2..(i + 1) * n2]
                .iter()
                .all(|v| v.is_finite())
            {
                "the predicted estimate x̂(t+1|t)"
            } else {
                "the predicted covariance T(t+1)"
            };
            return Err(Error::Numerical {
                t,
                i: i + 1,
                msg: format!(
                    "{what} is no longer finite: it overflowed the range of f64 (about 1e308){hint}"
                ),
            });
        }
        self.t += 1;
        Ok(())
    }

    fn filtered(&self) -> (&[f64], &[f64]) {
        (&self.x_filt, &self.p_filt)
    }

    fn predicted(&self) -> (&[f64], &[f64]) {
        (&self.x_pred, &self.t_pred)
    }

    fn solver_error_estimate(&self) -> f64 {
        self.solver_error
    }
}
