//! The two-step distributed filter (docs/theory.md §2, §4): at each time step every subsystem runs its
//! local Nahi update, step 1 solves the interconnection signals `v̂` along the chain from the
//! estimates, and every subsystem predicts with `v̂` taken as a known input.
//!
//! State is kept in flat arrays, subsystem after subsystem (`N·n` means, `N·n²` column-major
//! covariances). A time step is three phases: the local updates (which also form
//! `z = D x̂ + H u` for step 1), the step-1 solve (a sequential sweep along the chain), and the
//! local predictions. On long chains the two local phases run in parallel over fixed chunks of
//! subsystems (rayon), each chunk with its own preallocated kernel and scratch, so a step
//! allocates nothing; each subsystem's arithmetic is the same whatever the thread count, so
//! the results are too. Where step 1 is solved in two halves (docs/theory.md §2), each half
//! of the chain is one task from its updates to its predictions: it updates its subsystems,
//! forward-solves its half, and after the seam between the halves back-substitutes and
//! predicts its subsystems. A step then waits for the threads twice (at the seam and at its
//! end) instead of at each phase, which costs tens of microseconds each where waking a parked
//! thread is slow, and each half's data stays with the core that works on it.
//!
//! **Shared recursions.** The covariance recursions do not depend on the data, so subsystems
//! with the same parameters share them (computed once per step, the same bits as computing
//! them per subsystem):
//! - `local` moment: `Pₓ⁺ = A Pₓ Aᵀ + Q` from `Pₓ(1) = P0` is one matrix when every subsystem
//!   has the same `A` and `Q` at every time (only the means `m` differ);
//! - `paper` moment: `S⁺ = A S Aᵀ` is one matrix when `A` is the same everywhere; when also
//!   `J`, `M`, `Q` and `p` are, the whole covariance recursion (`T`, the gain, `P(t|t)`) is,
//!   and only the means are per subsystem — until a step has a gap (a row not in the data,
//!   docs/theory.md §15), after which every subsystem keeps its own.

use crate::error::{Error, Result};
use crate::filter::kernel::{DynamicKernel, FixedKernel, LocalKernel};
use crate::filter::{
    ChainFilter, Dropouts, InterconnectFrom, SecondMoment, TwoStepOptions, Update,
    reads_second_moment,
};
use crate::interconnect::Interconnect;
use crate::lifted::{LiftedMoments, LiftedSystem};
use crate::linalg::moment_blocks;
use crate::model::Model;
use crate::run::check_update;

mod local;
use local::{
    PredictInputs, Predicted, UpdateInputs, Updated, Worker, join_halves, predict_chunks,
    predict_range, split_workers, update_chunks, update_range,
};

/// Chains at least this long run the local phases in parallel, in chunks of [`CHUNK`]
/// subsystems (fixed, so that the work of a chunk does not depend on the thread count).
/// Small enough that two threads balance within a few per cent (on W, N = 10⁴, 256 gave
/// 1.75–1.86× on two threads against 1.70× with 1024 and 1.23–1.37× with two halves).
const PARALLEL_MIN: usize = 4096;
const CHUNK: usize = 256;

/// Which covariance recursions all subsystems share (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sharing {
    /// The moment covariance (`Pₓ` for `local`, `S` for `paper`) is one matrix.
    pub moment: bool,
    /// `T`, the gain and `P(t|t)` are one each (`paper` only).
    pub gain: bool,
}

impl Sharing {
    const NONE: Sharing = Sharing {
        moment: false,
        gain: false,
    };

    fn of(model: &Model, opts: &TwoStepOptions) -> Sharing {
        // The mixture update's covariance depends on each subsystem's reading, and every
        // recursion on the subsystem's own start.
        if opts.dropouts == Dropouts::Known
            || opts.update == Update::Mixture
            || !model.initial.shared()
        {
            return Sharing::NONE;
        }
        // Compared by value: two parameter sets may hold the same matrices.
        let same = |keys: &[&str], with_p: bool| {
            model.windows().iter().all(|w| {
                let first = model.param_set(w.ids[0]);
                w.ids.iter().zip(&w.p).all(|(&id, &p)| {
                    let set = model.param_set(id);
                    (id == w.ids[0] || keys.iter().all(|k| set.get(k) == first.get(k)))
                        && (!with_p || p == w.p[0])
                })
            })
        };
        match opts.second_moment {
            SecondMoment::Local => Sharing {
                moment: same(&["A", "Q"], false),
                gain: false,
            },
            SecondMoment::Paper => {
                let moment = same(&["A"], false);
                Sharing {
                    moment,
                    gain: moment && same(&["A", "J", "M", "Q"], true),
                }
            }
            SecondMoment::Lifted | SecondMoment::Band => Sharing::NONE,
        }
    }
}

/// The filter's state between time steps; `K` does the per-subsystem arithmetic (use
/// [`two_step`] to get the fastest kernel for the model's sizes).
pub struct TwoStepFilter<K: LocalKernel = DynamicKernel> {
    model: Model,
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
    /// `local`: the means `m` of `x` (`N·n`; unused otherwise).
    moment_mean: Vec<f64>,
    /// `local`: the covariances `Pₓ`; `paper`: `S`. Per subsystem (`N·n²`), or empty when
    /// shared.
    moment_cov: Vec<f64>,
    /// The shared moment covariance (`n²`), when [`Sharing::moment`].
    moment_shared: Vec<f64>,
    /// The shared `T` and `P(t|t)` (`n²` each) and gain, when [`Sharing::gain`].
    t_shared: Vec<f64>,
    p_shared: Vec<f64>,
    gain: K::Gain,
    sharing: Sharing,
    /// `lifted`: the exact moments of the lifted system.
    lifted: Option<(LiftedSystem, LiftedMoments)>,
    z: Vec<f64>,
    v: Vec<f64>,
    solve_scratch: Vec<f64>,
    /// One kernel and scratch per chunk of [`CHUNK`] subsystems (the first also serves the
    /// sequential path).
    workers: Vec<Worker<K>>,
    solver_error: f64,
    /// The mixture update's `π(t, i)` (`N`; empty with the linear update).
    arrival: Vec<f64>,
    /// The log density of each subsystem's last measurement given the past (`N`), summed in
    /// subsystem order by [`ChainFilter::log_likelihood`].
    log_densities: Vec<f64>,
}

/// The two-step filter with the fastest kernel for the model's `(n, q)`: compile-time sizes
/// for `n ≤ 4`, `q ≤ 2`, dynamic sizes otherwise.
pub fn two_step(model: &Model, opts: TwoStepOptions) -> Result<Box<dyn ChainFilter>> {
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

impl TwoStepFilter<DynamicKernel> {
    /// The filter with dynamic sizes (any `n`, `q`); see [`two_step`] for the fast path.
    pub fn new(model: &Model, opts: TwoStepOptions) -> Result<Self> {
        Self::with_kernel(model, opts)
    }
}

impl<K: LocalKernel> TwoStepFilter<K> {
    /// Initial values of docs/theory.md §4: `x̂(1) = m0`, `T(1) = P0`, `S(1) = P0 + m0 m0ᵀ`.
    pub fn with_kernel(model: &Model, opts: TwoStepOptions) -> Result<Self> {
        let d = model.dims;
        let (n, big_n) = (d.n, model.subsystems);
        if opts.second_moment == SecondMoment::Band {
            return Err(Error::Usage(
                "--second-moment band belongs to the joint filter (--filter joint); the distributed filter takes local, paper or lifted".into(),
            ));
        }
        let x_pred = model.initial.means();
        let t_pred = model.initial.covs();
        // local: Pₓ(1) = P0; paper: S(1) = P0 + m0 m0ᵀ (per subsystem).
        let moment_of = |mean: &[f64], cov: &[f64]| {
            let mut moment = cov.to_vec();
            if opts.second_moment == SecondMoment::Paper {
                moment_blocks(&mut moment, cov, mean, n);
            }
            moment
        };
        let first = model.initial.of(0);
        let moment_one = moment_of(first.mean.as_slice(), first.cov.as_slice());
        let sharing = Sharing::of(model, &opts);
        let uses_second_moment = reads_second_moment(opts.dropouts, opts.update);
        let per_subsystem_moment =
            uses_second_moment && !sharing.moment && opts.second_moment != SecondMoment::Lifted;
        let moment_cov = if per_subsystem_moment {
            moment_of(&x_pred, &t_pred)
        } else {
            Vec::new()
        };
        let solver = Interconnect::new(opts.solver, model, 1)?;
        let solver_error = solver.error_estimate();
        let lifted = if uses_second_moment && opts.second_moment == SecondMoment::Lifted {
            Some((LiftedSystem::new(model, 1)?, LiftedMoments::initial(model)))
        } else {
            None
        };
        check_update(opts.dropouts, opts.update)?;
        let worker = Worker::<K>::new(model);
        let gain = worker.kernel.new_gain();
        Ok(Self {
            model: model.clone(),
            opts,
            solver,
            t: 1,
            x_filt: x_pred.clone(),
            p_filt: t_pred.clone(),
            moment_mean: x_pred.clone(),
            x_pred,
            t_pred,
            moment_cov,
            moment_shared: moment_one,
            t_shared: first.cov.as_slice().to_vec(),
            p_shared: first.cov.as_slice().to_vec(),
            gain,
            sharing,
            lifted,
            z: vec![0.0; big_n * d.s()],
            v: vec![0.0; big_n * d.s()],
            solve_scratch: Vec::with_capacity(big_n * d.s()),
            // One per chunk, one for the subsystem two halves share (split_workers), and one
            // for the shorter last chunk a half may add.
            workers: vec![worker; big_n.div_ceil(CHUNK) + 2],
            solver_error,
            arrival: match opts.update {
                Update::Mixture => vec![0.0; big_n],
                Update::Linear => Vec::new(),
            },
            log_densities: vec![0.0; big_n],
        })
    }

    /// Turns the shared recursions off: every subsystem computes its own covariances, as on
    /// a chain with different parameters. For tests and benchmarks of the sharing.
    pub fn without_sharing(mut self) -> Self {
        if self.sharing.moment {
            let n2 = self.moment_shared.len();
            self.moment_cov = self
                .moment_shared
                .iter()
                .copied()
                .cycle()
                .take(self.model.subsystems * n2)
                .collect();
        }
        self.sharing = Sharing::NONE;
        self
    }

    /// Which recursions this filter shares between subsystems.
    pub fn sharing(&self) -> Sharing {
        self.sharing
    }

    fn numerical(&self, t: usize, i: usize, msg: &str) -> Error {
        let hint = if self.solver_error > crate::interconnect::TRANSFER_ERROR_WARNING {
            format!(
                " (the transfer solver's estimated relative error is {:.1e}; use --solver banded)",
                self.solver_error
            )
        } else {
            String::new()
        };
        Error::Numerical {
            t,
            i: i + 1,
            msg: format!("{msg}{hint}"),
        }
    }
}

impl<K: LocalKernel> ChainFilter for TwoStepFilter<K> {
    fn second_moments(&self, out: &mut [f64]) -> bool {
        if !reads_second_moment(self.opts.dropouts, self.opts.update) {
            return false;
        }
        let n = self.model.dims.n;
        if let Some((_, moments)) = &self.lifted {
            for (i, s) in out.chunks_exact_mut(n * n).enumerate() {
                moments.second_moment(i, n, s);
            }
            return true;
        }
        // One matrix for all subsystems, or one each (moment_blocks takes either).
        let cov = match self.moment_cov.is_empty() {
            true => &self.moment_shared,
            false => &self.moment_cov,
        };
        match self.opts.second_moment {
            SecondMoment::Local => moment_blocks(out, cov, &self.moment_mean, n),
            _ if cov.len() == out.len() => out.copy_from_slice(cov),
            _ => out
                .chunks_exact_mut(n * n)
                .for_each(|s| s.copy_from_slice(cov)),
        }
        true
    }

    fn step(&mut self, y: &[f64], u: &[f64]) -> Result<()> {
        let model = &self.model.clone();
        let d = model.dims;
        let (n, s, big_n) = (d.n, d.s(), model.subsystems);
        let t = self.t;
        self.solver.prepare(model, t)?;
        self.solver_error = self.solver_error.max(self.solver.error_estimate());
        let window = model.window(t);
        let known = self.opts.dropouts == Dropouts::Known;
        let parallel = big_n >= PARALLEL_MIN && rayon::current_num_threads() > 1;
        const NOT_PD: &str = "the innovation covariance Σ is not positive definite";

        // A subsystem with a row not in the data has its own gain from now on
        // (docs/theory.md §15): the covariances are no longer the same everywhere.
        if self.sharing.gain && y.iter().any(|v| v.is_nan()) {
            self.sharing.gain = false;
        }
        // The shared covariance update, once for all subsystems.
        if self.sharing.gain {
            let ok = self.workers[0].kernel.covariance_update(
                window.ids[0],
                window.p[0],
                &self.moment_shared,
                &self.t_shared,
                &mut self.p_shared,
                &mut self.gain,
            );
            if !ok {
                return Err(self.numerical(t, 0, NOT_PD));
            }
        }

        let inp = UpdateInputs {
            model,
            t,
            known,
            mixture: self.opts.update == Update::Mixture,
            second_moment: self.opts.second_moment,
            from_predicted: self.opts.interconnect_from == InterconnectFrom::Predicted,
            lifted: self.lifted.as_ref().map(|(_, mom)| mom),
            x_pred: &self.x_pred,
            t_pred: &self.t_pred,
            moment_mean: &self.moment_mean,
            moment_cov: &self.moment_cov,
            moment_shared: &self.moment_shared,
            shared: self
                .sharing
                .gain
                .then_some((&self.gain, self.p_shared.as_slice())),
            y,
            u,
        };
        // On long chains each half of the split step-1 solve runs on the thread that
        // updates and predicts its subsystems (docs/theory.md §2): two joins a step, and
        // each half's data stays with one core. Subsystem `b`, whose `z` and `v` both halves
        // read, is updated before them and predicted after them.
        let halves = if parallel { self.solver.halves() } else { None };
        let updated = Updated {
            x_filt: &mut self.x_filt,
            p_filt: &mut self.p_filt,
            z: &mut self.z,
            arrival: &mut self.arrival,
            log_densities: &mut self.log_densities,
        };
        let failed = match &halves {
            None => update_chunks(&inp, &mut self.workers, 0, updated, parallel),
            Some(h) => {
                let b = h.boundary();
                let [rhs1, rhs2, _] = h.scratch(&mut self.solve_scratch);
                let (w_shared, w1, w2) = split_workers(&mut self.workers, b);
                let (mut head, rest) = updated.split_at(b, d);
                let (mut shared, mut tail) = rest.split_at(1, d);
                let failed = update_range(&inp, w_shared, b, shared.reborrow());
                let z_shared = &*shared.z;
                let (f1, f2) = join_halves(
                    || {
                        let failed = update_chunks(&inp, w1, 0, head.reborrow(), true);
                        h.forward_first(head.z, z_shared, rhs1);
                        failed
                    },
                    || {
                        let failed = update_chunks(&inp, w2, b + 1, tail.reborrow(), true);
                        h.forward_second(z_shared, tail.z, rhs2);
                        failed
                    },
                );
                [failed, f1, f2].into_iter().flatten().min()
            }
        };
        if let Some(i) = failed {
            return Err(self.numerical(t, i, NOT_PD));
        }

        if self.sharing.gain {
            let set = window.ids[0];
            self.workers[0]
                .kernel
                .propagate(set, true, &self.p_shared, &mut self.t_shared);
        }
        let inp = PredictInputs {
            model,
            t,
            known,
            second_moment: self.opts.second_moment,
            x_filt: &self.x_filt,
            p_filt: &self.p_filt,
            t_shared: self.sharing.gain.then_some(self.t_shared.as_slice()),
            u,
        };
        let predicted = Predicted {
            x_pred: &mut self.x_pred,
            t_pred: &mut self.t_pred,
            moment_mean: &mut self.moment_mean,
            moment_cov: &mut self.moment_cov,
        };
        let failed = match &halves {
            None => {
                // Step 1: v̂ from z = D x̂ + H u.
                self.solver
                    .solve(&self.z, &mut self.v, &mut self.solve_scratch);
                predict_chunks(&inp, &mut self.workers, 0, &self.v, predicted, parallel)
            }
            Some(h) => {
                let b = h.boundary();
                let [rhs1, rhs2, seam] = h.scratch(&mut self.solve_scratch);
                h.seam(rhs1, rhs2, seam);
                let (w_shared, w1, w2) = split_workers(&mut self.workers, b);
                let (head, rest) = predicted.split_at(b, d);
                let (shared, tail) = rest.split_at(1, d);
                // The first half's `v` ends with v⁺(b), the second's starts with v⁻(b).
                let (v1, v2) = self.v.split_at_mut(b * s + d.plus);
                let (f1, f2) = join_halves(
                    || {
                        h.finish_first(rhs1, seam, v1);
                        predict_chunks(&inp, w1, 0, v1, head, true)
                    },
                    || {
                        h.finish_second(rhs2, seam, v2);
                        let v = &v2[s - d.plus..];
                        predict_chunks(&inp, w2, b + 1, v, tail, true)
                    },
                );
                let v = &self.v[b * s..(b + 1) * s];
                let failed = predict_range(&inp, w_shared, b, v, shared);
                [failed, f1, f2].into_iter().flatten().min()
            }
        };
        if self.sharing.moment {
            let set = window.ids[0];
            let with_q = self.opts.second_moment == SecondMoment::Local;
            let wk = &mut self.workers[0];
            let before = &mut wk.cov[..n * n];
            before.copy_from_slice(&self.moment_shared);
            wk.kernel
                .propagate(set, with_q, before, &mut self.moment_shared);
        }
        if let Some((sys, moments)) = &mut self.lifted {
            sys.prepare(model, t)?;
            moments.propagate(model, sys, u);
        }
        // A blown-up step 1 (e.g. the transfer solver on a long chain) must not pass as data.
        if let Some(i) = failed {
            let n2 = n * n;
            let what = if self.t_pred[i * n2..(i + 1) * n2]
                .iter()
                .all(|v| v.is_finite())
            {
                "the predicted estimate x̂(t+1|t)"
            } else {
                "the predicted covariance T(t+1)"
            };
            return Err(self.numerical(
                t,
                i,
                &format!(
                    "{what} is no longer finite: it overflowed the range of f64 (about 1e308)"
                ),
            ));
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

    fn arrival(&self) -> Option<&[f64]> {
        (self.opts.update == Update::Mixture).then_some(self.arrival.as_slice())
    }

    /// Each subsystem's own density, summed: with the mixture update `Σ_i log(p e^ℓ₁ +
    /// (1−p) e^ℓ₀)`, with known dropouts `Σ_i log N(ỹ_i; 0, Σ_i)` over the received rows
    /// (docs/theory.md §10) — a composite of marginals, since the filter keeps no
    /// cross-covariances.
    fn log_likelihood(&self) -> Option<f64> {
        let has_density =
            self.opts.update == Update::Mixture || self.opts.dropouts == Dropouts::Known;
        has_density.then(|| self.log_densities.iter().sum())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each half's result comes back in its place, on a pool of one thread (where the first
    /// half's thread runs the second itself after it, so the first must not wait for it) and
    /// of two, with halves of unequal length either way round.
    #[test]
    fn join_halves_returns_both_halves_on_one_thread_and_two() {
        let work = |len: u64| (0..len * 1000).fold(0u64, |a, k| a.wrapping_mul(31).wrapping_add(k));
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for (a, b) in [(1, 50), (50, 1), (20, 20)] {
                let got = pool.install(|| join_halves(|| (a, work(a)), || (b, work(b))));
                assert_eq!(
                    got,
                    ((a, work(a)), (b, work(b))),
                    "{threads} threads, {a} and {b}"
                );
            }
        }
    }
}
