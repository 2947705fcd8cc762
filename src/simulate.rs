//! The true system of docs/theory.md §1 with random dropouts: (P1)–(P5) stepped forward from
//! `x(1,i) ~ N(m0, P0)`.
//!
//! Every draw comes from one `ChaCha8Rng` seeded with the run's seed, in a fixed order, so the
//! same seed gives the same data on every platform and crate version: first `x(1,i)` for
//! `i = 1..N` (`n` normals each); then for each `t` and each `i`: the uniform deciding
//! `γ(t,i)`, the `q` normals of `d(t,i)`, the `n` normals of `ω(t,i)`.

use nalgebra::DMatrix;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::error::{Error, Result};
use crate::inputs::InputStream;
use crate::interconnect::ChainSolver;
use crate::linalg::{mat_vec_add, psd_sqrt};
use crate::model::Model;

/// One simulated time step of the whole chain; slices are subsystem by subsystem.
pub struct SimStep<'a> {
    pub t: usize,
    /// `x(t, ·)`, `N · n` values.
    pub x: &'a [f64],
    /// `γ(t, ·)`, `N` values.
    pub gamma: &'a [bool],
    /// `y(t, ·)`, `N · q` values (lost ones hold the noise `R u + d`, as in (P5)).
    pub y: &'a [f64],
    /// `u(t, ·)`, `N · m` values.
    pub u: &'a [f64],
}

/// Runs the system for `steps` steps and hands every step to `sink`.
pub fn simulate(
    model: &Model,
    steps: usize,
    seed: u64,
    inputs: &mut InputStream,
    mut sink: impl FnMut(&SimStep) -> Result<()>,
) -> Result<()> {
    let d = model.dims;
    let (n, q, m, s, big_n) = (d.n, d.q, d.m, d.s(), model.subsystems);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Square roots of the noise covariances, one per parameter set.
    let sqrt_q: Vec<DMatrix<f64>> = model.param_sets().iter().map(|p| psd_sqrt(&p.Q)).collect();
    let sqrt_m: Vec<DMatrix<f64>> = model.param_sets().iter().map(|p| psd_sqrt(&p.M)).collect();
    let sqrt_p0: Vec<DMatrix<f64>> = (model.initial.sets().iter())
        .map(|s| psd_sqrt(&s.cov))
        .collect();

    let mut x = vec![0.0; big_n * n];
    let mut x_next = vec![0.0; big_n * n];
    let mut noise = vec![0.0; n.max(q)];
    for (xi, &id) in x.chunks_mut(n).zip(model.initial.ids()) {
        xi.copy_from_slice(model.initial.sets()[id as usize].mean.as_slice());
        draw_normal(&mut rng, &mut noise[..n]);
        mat_vec_add(xi, &sqrt_p0[id as usize], &noise[..n]);
    }
    let mut u = vec![0.0; big_n * m];
    let mut z = vec![0.0; big_n * s];
    let mut v = vec![0.0; big_n * s];
    let mut y = vec![0.0; big_n * q];
    let mut gamma = vec![false; big_n];
    let mut rhs = Vec::new();
    let mut solver = ChainSolver::new(model, 1)?;

    for t in 1..=steps {
        inputs.next(t, &mut u)?;
        solver.prepare(model, t)?;
        let window = model.window(t);
        // Step 1: the interconnection signals of the true state.
        z.fill(0.0);
        for i in 0..big_n {
            let p = model.param_set(window.ids[i]);
            let zi = &mut z[i * s..(i + 1) * s];
            mat_vec_add(zi, &p.D, &x[i * n..(i + 1) * n]);
            mat_vec_add(zi, &p.H, &u[i * m..(i + 1) * m]);
        }
        solver.solve(&z, &mut v, &mut rhs);

        y.fill(0.0);
        x_next.fill(0.0);
        for i in 0..big_n {
            let id = window.ids[i] as usize;
            let p = model.param_set(window.ids[i]);
            let (xi, ui) = (&x[i * n..(i + 1) * n], &u[i * m..(i + 1) * m]);
            gamma[i] = rng.random::<f64>() < window.p[i];
            let yi = &mut y[i * q..(i + 1) * q];
            if gamma[i] {
                mat_vec_add(yi, &p.J, xi);
            }
            mat_vec_add(yi, &p.R, ui);
            draw_normal(&mut rng, &mut noise[..q]);
            mat_vec_add(yi, &sqrt_m[id], &noise[..q]);

            let xn = &mut x_next[i * n..(i + 1) * n];
            mat_vec_add(xn, &p.A, xi);
            mat_vec_add(xn, &p.B, &v[i * s..(i + 1) * s]);
            mat_vec_add(xn, &p.C, ui);
            draw_normal(&mut rng, &mut noise[..n]);
            mat_vec_add(xn, &sqrt_q[id], &noise[..n]);
        }
        for (values, width, what) in [(&x, n, "state x"), (&y, q, "measurement y")] {
            Error::check_finite(t, width, values, || {
                format!(
                    "the simulated {what} is no longer finite: the chain is unstable (`sisfilt check` prints the spectral radius of A_eff)"
                )
            })?;
        }
        // A subsystem without a sensor: no measurement, and none arrived. Its draws were made
        // all the same, so that the others' values do not depend on it.
        model.blank_unmeasured(t, &mut y);
        for (g, measured) in gamma.iter_mut().zip(&window.measured) {
            *g &= *measured;
        }
        sink(&SimStep {
            t,
            x: &x,
            gamma: &gamma,
            y: &y,
            u: &u,
        })?;
        std::mem::swap(&mut x, &mut x_next);
    }
    Ok(())
}

fn draw_normal(rng: &mut ChaCha8Rng, out: &mut [f64]) {
    for o in out {
        *o = rng.sample(StandardNormal);
    }
}
