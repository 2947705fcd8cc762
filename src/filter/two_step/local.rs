//! The local phases of a two-step time step (docs/theory.md §4): every subsystem's update and
//! prediction, over runs of subsystems that share their parameters, in chunks of [`CHUNK`]
//! subsystems that run in parallel on long chains, and the rendezvous of a step's two halves.

use rayon::iter::Either;
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use super::CHUNK;
use crate::filter::SecondMoment;
use crate::filter::kernel::{LANES, LaneData, LocalData, LocalKernel};
use crate::lifted::LiftedMoments;
use crate::linalg::{first_non_finite_block, mat_vec_add_blocks, mat_vec_blocks, moment_blocks};
use crate::model::{Dims, Model};

/// The preallocated state of one chunk's local work.
#[derive(Clone)]
pub(super) struct Worker<K> {
    pub(super) kernel: K,
    /// `S` of the current run of subsystems (`n × n` each).
    pub(super) s_buf: Vec<f64>,
    /// `R u` of the run.
    pub(super) ru: Vec<f64>,
    /// The run's moment covariances and means before their prediction.
    pub(super) cov: Vec<f64>,
    pub(super) mean: Vec<f64>,
}

impl<K: LocalKernel> Worker<K> {
    pub(super) fn new(model: &Model) -> Self {
        let (n, q) = (model.dims.n, model.dims.q);
        let run = run_limit(n);
        Self {
            kernel: K::new(model),
            s_buf: vec![0.0; run * n * n],
            ru: vec![0.0; run * q],
            cov: vec![0.0; run * n * n],
            mean: vec![0.0; run * n],
        }
    }
}

/// What a failed local update reports: the 0-based subsystem.
type FirstFailure = Option<usize>;

/// What the local updates read at time `t`.
pub(super) struct UpdateInputs<'a, G> {
    pub(super) model: &'a Model,
    pub(super) t: usize,
    pub(super) known: bool,
    pub(super) mixture: bool,
    pub(super) second_moment: SecondMoment,
    pub(super) from_predicted: bool,
    pub(super) lifted: Option<&'a LiftedMoments>,
    pub(super) x_pred: &'a [f64],
    pub(super) t_pred: &'a [f64],
    pub(super) moment_mean: &'a [f64],
    /// Per subsystem, or empty when `moment_shared` holds the one matrix.
    pub(super) moment_cov: &'a [f64],
    pub(super) moment_shared: &'a [f64],
    /// The shared gain and `P(t|t)`, when every subsystem uses them.
    pub(super) shared: Option<(&'a G, &'a [f64])>,
    pub(super) y: &'a [f64],
    pub(super) u: &'a [f64],
}

/// The longest run of subsystems [`update_range`] and [`predict_range`] take at once: one
/// parameter set, and at most this many values of `n × n` blocks in the worker's scratch
/// (at least [`LANES`] subsystems, at most [`CHUNK`]).
const RUN_VALUES: usize = 1024;

/// The length of the run of subsystems from `i` (0-based) that share `ids[i]`, at most
/// `limit`.
fn run_length(ids: &[u32], i: usize, limit: usize) -> usize {
    ids[i..i + limit]
        .iter()
        .take_while(|&&id| id == ids[i])
        .count()
}

/// The most subsystems of `n` states in one run.
fn run_limit(n: usize) -> usize {
    (RUN_VALUES / (n * n)).clamp(LANES, CHUNK)
}

/// The second moments `S` of the `len` subsystems from `i` (0-based) into the worker's
/// `s_buf`, where the update reads them.
fn second_moments<K: LocalKernel>(
    inp: &UpdateInputs<K::Gain>,
    wk: &mut Worker<K>,
    i: usize,
    len: usize,
) {
    if inp.known || inp.mixture || inp.shared.is_some() {
        return;
    }
    let n = inp.model.dims.n;
    let nn = n * n;
    let s_run = &mut wk.s_buf[..len * nn];
    if let Some(moments) = inp.lifted {
        for (j, s) in s_run.chunks_exact_mut(nn).enumerate() {
            moments.second_moment(i + j, n, s);
        }
        return;
    }
    let cov = match inp.moment_cov.is_empty() {
        true => inp.moment_shared,
        false => &inp.moment_cov[i * nn..(i + len) * nn],
    };
    match inp.second_moment {
        SecondMoment::Local => moment_blocks(s_run, cov, &inp.moment_mean[i * n..(i + len) * n], n),
        _ if cov.len() == s_run.len() => s_run.copy_from_slice(cov),
        _ => s_run
            .chunks_exact_mut(nn)
            .for_each(|s| s.copy_from_slice(cov)),
    }
}

/// What the local updates write for a range of subsystems: per subsystem `x̂(t|t)`, `P(t|t)`,
/// `z = D x̂ + H u` (`n`, `n²`, `s` values), the mixture update's `π` and the log density of
/// the measurement (one each). `z` is empty when `s = 0`, `arrival` with the linear update.
pub(super) struct Updated<'a> {
    pub(super) x_filt: &'a mut [f64],
    pub(super) p_filt: &'a mut [f64],
    pub(super) z: &'a mut [f64],
    pub(super) arrival: &'a mut [f64],
    pub(super) log_densities: &'a mut [f64],
}

impl<'a> Updated<'a> {
    pub(super) fn reborrow(&mut self) -> Updated<'_> {
        Updated {
            x_filt: self.x_filt,
            p_filt: self.p_filt,
            z: self.z,
            arrival: self.arrival,
            log_densities: self.log_densities,
        }
    }

    /// The first `i` subsystems and the rest.
    pub(super) fn split_at(self, i: usize, d: Dims) -> (Self, Self) {
        let (n, s) = (d.n, d.s());
        let (x1, x2) = self.x_filt.split_at_mut(i * n);
        let (p1, p2) = self.p_filt.split_at_mut(i * n * n);
        let (z1, z2) = split_or_empty(self.z, i * s);
        let (a1, a2) = split_or_empty(self.arrival, i);
        let (l1, l2) = self.log_densities.split_at_mut(i);
        (
            Updated {
                x_filt: x1,
                p_filt: p1,
                z: z1,
                arrival: a1,
                log_densities: l1,
            },
            Updated {
                x_filt: x2,
                p_filt: p2,
                z: z2,
                arrival: a2,
                log_densities: l2,
            },
        )
    }

    /// Consecutive chunks of `size` subsystems (the last may be shorter).
    pub(super) fn par_chunks(
        self,
        size: usize,
        d: Dims,
    ) -> impl IndexedParallelIterator<Item = Updated<'a>> {
        let (n, s) = (d.n, d.s());
        let count = self.log_densities.len().div_ceil(size);
        self.x_filt
            .par_chunks_mut(size * n)
            .zip(self.p_filt.par_chunks_mut(size * n * n))
            .zip(par_chunks_or_empty(self.z, size * s, count))
            .zip(par_chunks_or_empty(self.arrival, size, count))
            .zip(self.log_densities.par_chunks_mut(size))
            .map(
                |((((x_filt, p_filt), z), arrival), log_densities)| Updated {
                    x_filt,
                    p_filt,
                    z,
                    arrival,
                    log_densities,
                },
            )
    }
}

/// What the local predictions write for a range of subsystems: per subsystem `x̂(t+1|t)`,
/// `T(t+1)` and the moment mean and covariance (`n`, `n²`, `n`, `n²` values); `moment_cov`
/// is empty when it is shared or unused.
pub(super) struct Predicted<'a> {
    pub(super) x_pred: &'a mut [f64],
    pub(super) t_pred: &'a mut [f64],
    pub(super) moment_mean: &'a mut [f64],
    pub(super) moment_cov: &'a mut [f64],
}

impl<'a> Predicted<'a> {
    /// The first `i` subsystems and the rest.
    pub(super) fn split_at(self, i: usize, d: Dims) -> (Self, Self) {
        let n = d.n;
        let (x1, x2) = self.x_pred.split_at_mut(i * n);
        let (t1, t2) = self.t_pred.split_at_mut(i * n * n);
        let (m1, m2) = self.moment_mean.split_at_mut(i * n);
        let (c1, c2) = split_or_empty(self.moment_cov, i * n * n);
        (
            Predicted {
                x_pred: x1,
                t_pred: t1,
                moment_mean: m1,
                moment_cov: c1,
            },
            Predicted {
                x_pred: x2,
                t_pred: t2,
                moment_mean: m2,
                moment_cov: c2,
            },
        )
    }

    /// Consecutive chunks of `size` subsystems (the last may be shorter).
    pub(super) fn par_chunks(
        self,
        size: usize,
        d: Dims,
    ) -> impl IndexedParallelIterator<Item = Predicted<'a>> {
        let n = d.n;
        let count = self.x_pred.len().div_ceil(size * n);
        self.x_pred
            .par_chunks_mut(size * n)
            .zip(self.t_pred.par_chunks_mut(size * n * n))
            .zip(self.moment_mean.par_chunks_mut(size * n))
            .zip(par_chunks_or_empty(self.moment_cov, size * n * n, count))
            .map(|(((x_pred, t_pred), moment_mean), moment_cov)| Predicted {
                x_pred,
                t_pred,
                moment_mean,
                moment_cov,
            })
    }
}

/// `v.split_at_mut(at)`, or two empty slices when `v` is empty.
fn split_or_empty(v: &mut [f64], at: usize) -> (&mut [f64], &mut [f64]) {
    if v.is_empty() {
        (&mut [], &mut [])
    } else {
        v.split_at_mut(at)
    }
}

/// [`update_range`] of the subsystems in `out` (from `first`, 0-based): in parallel, in
/// chunks of [`CHUNK`] subsystems with a worker each, or on the first worker alone.
pub(super) fn update_chunks<K: LocalKernel>(
    inp: &UpdateInputs<K::Gain>,
    workers: &mut [Worker<K>],
    first: usize,
    out: Updated<'_>,
    parallel: bool,
) -> FirstFailure {
    if !parallel {
        return update_range(inp, &mut workers[0], first, out);
    }
    workers
        .par_iter_mut()
        .zip(out.par_chunks(CHUNK, inp.model.dims))
        .enumerate()
        .filter_map(|(c, (wk, out))| update_range(inp, wk, first + c * CHUNK, out))
        .min()
}

/// [`predict_range`] of the subsystems in `out` (from `first`, 0-based; `v` from `first`
/// on), as [`update_chunks`] divides them.
pub(super) fn predict_chunks<K: LocalKernel>(
    inp: &PredictInputs,
    workers: &mut [Worker<K>],
    first: usize,
    v: &[f64],
    out: Predicted<'_>,
    parallel: bool,
) -> FirstFailure {
    if !parallel {
        return predict_range(inp, &mut workers[0], first, v, out);
    }
    let s = inp.model.dims.s();
    workers
        .par_iter_mut()
        .zip(out.par_chunks(CHUNK, inp.model.dims))
        .enumerate()
        .filter_map(|(c, (wk, out))| {
            let v = &v[(c * CHUNK * s).min(v.len())..];
            predict_range(inp, wk, first + c * CHUNK, v, out)
        })
        .min()
}

/// The local updates (Nahi's, or the mixture update with its `π` into `arrival`), each
/// measurement's log density into `log_densities`, and `z = D x̂ + H u`, of the subsystems
/// in `out` (from `first`, 0-based). The subsystems are taken in runs of one parameter set,
/// and in each run [`LANES`] at a time where every row is in the data
/// ([`LocalKernel::update_lanes`], [`LocalKernel::mixture_lanes`]: the same bits). Returns
/// the first subsystem whose `Σ` is not positive definite.
pub(super) fn update_range<K: LocalKernel>(
    inp: &UpdateInputs<K::Gain>,
    wk: &mut Worker<K>,
    first: usize,
    out: Updated<'_>,
) -> FirstFailure {
    let Updated {
        x_filt,
        p_filt,
        z,
        arrival,
        log_densities,
    } = out;
    let model = inp.model;
    let d = model.dims;
    let (n, q, m, s) = (d.n, d.q, d.m, d.s());
    let nn = n * n;
    let window = model.window(inp.t);
    let p = |i: usize| if inp.known { 1.0 } else { window.p[i] };
    let count = x_filt.len() / n;
    let in_lanes = inp.shared.is_none();
    let mut k = 0;
    while k < count {
        let start = first + k;
        let len = run_length(&window.ids, start, (count - k).min(run_limit(n)));
        let set = window.ids[start];
        let prm = model.param_set(set);
        let u = &inp.u[start * m..(start + len) * m];
        mat_vec_blocks(&mut wk.ru[..len * q], &prm.R, u);
        second_moments(inp, wk, start, len);
        let mut j = 0;
        while j < len {
            let (i, k) = (start + j, k + j);
            let lanes = in_lanes
                && j + LANES <= len
                && !inp.y[i * q..(i + LANES) * q].iter().any(|v| v.is_nan());
            let done = if lanes && {
                let data = LaneData {
                    y: &inp.y[i * q..(i + LANES) * q],
                    ru: &wk.ru[j * q..(j + LANES) * q],
                    p: match inp.known {
                        true => [1.0; LANES],
                        false => window.p[i..i + LANES].try_into().expect("LANES values"),
                    },
                    known: inp.known,
                };
                let (x_pred, t_pred) = (
                    &inp.x_pred[i * n..(i + LANES) * n],
                    &inp.t_pred[i * nn..(i + LANES) * nn],
                );
                let xf = &mut x_filt[k * n..(k + LANES) * n];
                let pf = &mut p_filt[k * nn..(k + LANES) * nn];
                let densities = &mut log_densities[k..k + LANES];
                if inp.mixture {
                    let arrival = &mut arrival[k..k + LANES];
                    let kernel = &mut wk.kernel;
                    kernel.mixture_lanes(set, &data, x_pred, t_pred, xf, pf, arrival, densities)
                } else {
                    let s = &wk.s_buf[j * nn..(j + LANES) * nn];
                    wk.kernel
                        .update_lanes(set, &data, s, x_pred, t_pred, xf, pf, densities)
                }
            } {
                LANES
            } else {
                // One subsystem; after failed lanes this finds the one that failed.
                let data = LocalData {
                    y: &inp.y[i * q..(i + 1) * q],
                    ru: &wk.ru[j * q..(j + 1) * q],
                    p: p(i),
                    known: inp.known,
                };
                let x_pred = &inp.x_pred[i * n..(i + 1) * n];
                let t_pred = &inp.t_pred[i * nn..(i + 1) * nn];
                let xf = &mut x_filt[k * n..(k + 1) * n];
                let pf = &mut p_filt[k * nn..(k + 1) * nn];
                if inp.mixture {
                    match wk.kernel.mixture_update(set, &data, x_pred, t_pred, xf, pf) {
                        Some(a) => {
                            arrival[k] = a.probability;
                            log_densities[k] = a.loglik;
                        }
                        None => return Some(i),
                    }
                } else if let Some((gain, p_shared)) = inp.shared {
                    K::mean_update(gain, &data, x_pred, xf);
                    pf.copy_from_slice(p_shared);
                } else {
                    let s = &wk.s_buf[j * nn..(j + 1) * nn];
                    match wk.kernel.update(set, &data, s, x_pred, t_pred, xf, pf) {
                        Some(log_density) => log_densities[k] = log_density,
                        None => return Some(i),
                    }
                }
                1
            };
            j += done;
        }
        // Step 1's right-hand side, from the estimate that feeds it (docs/theory.md §4).
        let source = if inp.from_predicted {
            &inp.x_pred[start * n..(start + len) * n]
        } else {
            &x_filt[k * n..(k + len) * n]
        };
        let z_run = &mut z[k * s..(k + len) * s];
        mat_vec_blocks(z_run, &prm.D, source);
        mat_vec_add_blocks(z_run, &prm.H, u);
        k += len;
    }
    None
}

/// What the local predictions read at time `t`.
pub(super) struct PredictInputs<'a> {
    pub(super) model: &'a Model,
    pub(super) t: usize,
    pub(super) known: bool,
    pub(super) second_moment: SecondMoment,
    pub(super) x_filt: &'a [f64],
    pub(super) p_filt: &'a [f64],
    /// The shared `T(t+1)`, when every subsystem uses it.
    pub(super) t_shared: Option<&'a [f64]>,
    pub(super) u: &'a [f64],
}

/// `x̂⁺ = A x̂(t|t) + B v̂ + C u`, `T⁺ = A P Aᵀ + Q` and the moments, of the subsystems in
/// `out` (from `first`, 0-based; `v̂` of the same subsystems in `v`). Returns the first
/// subsystem whose prediction is not finite.
pub(super) fn predict_range<K: LocalKernel>(
    inp: &PredictInputs,
    wk: &mut Worker<K>,
    first: usize,
    v: &[f64],
    out: Predicted<'_>,
) -> FirstFailure {
    let Predicted {
        x_pred,
        t_pred,
        moment_mean,
        moment_cov,
    } = out;
    let model = inp.model;
    let d = model.dims;
    let (n, m, s) = (d.n, d.m, d.s());
    let nn = n * n;
    let window = model.window(inp.t);
    let count = x_pred.len() / n;
    // The moment covariance's recursion: `local` with Q, `paper` without; none otherwise.
    let moment_q = match inp.second_moment {
        _ if inp.known || moment_cov.is_empty() => None,
        SecondMoment::Local => Some(true),
        SecondMoment::Paper => Some(false),
        SecondMoment::Lifted | SecondMoment::Band => None,
    };
    let mut failed = None;
    let mut k = 0;
    while k < count {
        let start = first + k;
        let len = run_length(&window.ids, start, (count - k).min(run_limit(n)));
        let set = window.ids[start];
        let prm = model.param_set(set);
        let (own, all) = (k * nn..(k + len) * nn, start * nn..(start + len) * nn);
        match inp.t_shared {
            Some(shared) => t_pred[own.clone()]
                .chunks_exact_mut(nn)
                .for_each(|tp| tp.copy_from_slice(shared)),
            None => propagate_run(
                &mut wk.kernel,
                set,
                true,
                nn,
                &inp.p_filt[all],
                &mut t_pred[own.clone()],
            ),
        }
        if let Some(with_q) = moment_q {
            let before = &mut wk.cov[..len * nn];
            before.copy_from_slice(&moment_cov[own.clone()]);
            propagate_run(
                &mut wk.kernel,
                set,
                with_q,
                nn,
                before,
                &mut moment_cov[own.clone()],
            );
        }
        let (v, u) = (
            &v[k * s..(k + len) * s],
            &inp.u[start * m..(start + len) * m],
        );
        let xp = &mut x_pred[k * n..(k + len) * n];
        mat_vec_blocks(xp, &prm.A, &inp.x_filt[start * n..(start + len) * n]);
        mat_vec_add_blocks(xp, &prm.B, v);
        mat_vec_add_blocks(xp, &prm.C, u);
        if failed.is_none() {
            let x = first_non_finite_block(xp, n);
            let t = first_non_finite_block(&t_pred[own], nn);
            failed = x.into_iter().chain(t).min().map(|j| start + j);
        }
        if !inp.known && inp.second_moment == SecondMoment::Local {
            let mean = &mut moment_mean[k * n..(k + len) * n];
            let before = &mut wk.mean[..len * n];
            before.copy_from_slice(mean);
            mat_vec_blocks(mean, &prm.A, before);
            mat_vec_add_blocks(mean, &prm.B, v);
            mat_vec_add_blocks(mean, &prm.C, u);
        }
        k += len;
    }
    failed
}

/// [`LocalKernel::propagate`] of the `n × n` blocks (`nn` values each) of `x` into those of
/// `out`, [`LANES`] at a time where they fit.
fn propagate_run<K: LocalKernel>(
    kernel: &mut K,
    set: u32,
    with_q: bool,
    nn: usize,
    x: &[f64],
    out: &mut [f64],
) {
    let mut xs = x.chunks_exact(LANES * nn);
    let mut outs = out.chunks_exact_mut(LANES * nn);
    for (x, out) in (&mut xs).zip(&mut outs) {
        kernel.propagate_lanes(set, with_q, x, out);
    }
    let rest = xs.remainder().chunks_exact(nn);
    for (x, out) in rest.zip(outs.into_remainder().chunks_exact_mut(nn)) {
        kernel.propagate(set, with_q, x, out);
    }
}

/// The longest a half of a step waits, spinning, for the other to finish.
const RENDEZVOUS_SPIN: Duration = Duration::from_micros(200);

/// `rayon::join` of a step's two halves, each of which waits at its end, spinning (at most
/// [`RENDEZVOUS_SPIN`]), for the other. A rayon thread left without work sleeps after some
/// 20 µs, and waking it takes 30–60 µs on these machines (an empty join with a 20 µs gap
/// before it: 1 µs without, 35 µs median with a sleep), more than the few µs by which two
/// halves usually differ; a step joins twice, so the thread that finishes first would
/// otherwise fall asleep between the joins of a step. The first half waits only once the
/// second has started (until then the first half's thread may run it itself), so nothing
/// waits for work that no thread has taken.
pub(super) fn join_halves<RA: Send, RB: Send>(
    first: impl FnOnce() -> RA + Send,
    second: impl FnOnce() -> RB + Send,
) -> (RA, RB) {
    let second_started = AtomicBool::new(false);
    let arrived = AtomicUsize::new(0);
    let arrive = |is_first: bool| {
        if arrived.fetch_add(1, Ordering::AcqRel) == 1
            || (is_first && !second_started.load(Ordering::Acquire))
        {
            return;
        }
        let start = Instant::now();
        while arrived.load(Ordering::Acquire) < 2 && start.elapsed() < RENDEZVOUS_SPIN {
            std::hint::spin_loop();
        }
    };
    rayon::join(
        || {
            let out = first();
            arrive(true);
            out
        },
        || {
            second_started.store(true, Ordering::Release);
            let out = second();
            arrive(false);
            out
        },
    )
}

/// The workers of a step in halves split at subsystem `b`: the one for `b`, those of the
/// first half's chunks and those of the second's.
pub(super) fn split_workers<K>(
    workers: &mut [Worker<K>],
    b: usize,
) -> (&mut Worker<K>, &mut [Worker<K>], &mut [Worker<K>]) {
    let (shared, rest) = workers.split_first_mut().expect("workers");
    let (first, second) = rest.split_at_mut(b.div_ceil(CHUNK));
    (shared, first, second)
}

/// `v.par_chunks_mut(size)`, or `count` empty slices when `v` is empty.
fn par_chunks_or_empty(
    v: &mut [f64],
    size: usize,
    count: usize,
) -> impl IndexedParallelIterator<Item = &mut [f64]> {
    if v.is_empty() {
        Either::Right(
            (0..count)
                .into_par_iter()
                .map(|_| -> &mut [f64] { &mut [] }),
        )
    } else {
        Either::Left(v.par_chunks_mut(size))
    }
}
