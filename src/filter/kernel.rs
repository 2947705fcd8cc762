//! The per-subsystem arithmetic of the two-step filter behind one trait, with two
//! implementations: [`DynamicKernel`] (any size, nalgebra `DMatrix` with preallocated
//! workspaces) and [`FixedKernel`] (compile-time sizes `n ≤ 4`, `q ≤ 2`, stack-allocated
//! `SMatrix`), which removes the per-call overhead of dynamic sizes for the common cases.
//! Both compute exactly the formulas of [`crate::filter::nahi`] (SPEC §3).

use nalgebra::{DMatrix, SMatrix, SVector};

use crate::filter::nahi::{self, Measurement, Workspace};
use crate::model::{Model, Params};

/// The local data of one update.
pub struct LocalData<'a> {
    /// `y(t,i)`; NaN marks a lost element in the known-dropout mode.
    pub y: &'a [f64],
    /// `R u(t,i)`.
    pub ru: &'a [f64],
    /// Arrival probability used by the filter (1 in the known-dropout mode).
    pub p: f64,
    pub known: bool,
}

/// Local Nahi update and covariance prediction for parameter set `set` of the model.
pub trait LocalKernel: Clone + Send + Sync + Sized {
    /// Prepares the kernel for every parameter set of `model`.
    fn new(model: &Model) -> Self;
    /// The Nahi update ([`nahi::update`]); `s` is the second moment `S` (`n × n`,
    /// column-major; unused in the known-dropout mode). Returns `false` when `Σ` is not
    /// positive definite.
    #[allow(clippy::too_many_arguments)]
    fn update(
        &mut self,
        set: u32,
        data: &LocalData,
        s: &[f64],
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> bool;
    /// `out = A X Aᵀ + Q` (or without `Q`), symmetrised.
    fn propagate(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]);
}

/// Any size: nalgebra's dynamic matrices and one reused [`Workspace`].
#[derive(Clone)]
pub struct DynamicKernel {
    sets: std::sync::Arc<[Params]>,
    ws: Workspace,
}

impl LocalKernel for DynamicKernel {
    fn new(model: &Model) -> Self {
        Self {
            sets: model.param_sets().into(),
            ws: Workspace::new(model.dims.n, model.dims.q),
        }
    }

    fn update(
        &mut self,
        set: u32,
        data: &LocalData,
        s: &[f64],
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> bool {
        let prm = &self.sets[set as usize];
        self.ws
            .second_moment_mut()
            .as_mut_slice()
            .copy_from_slice(s);
        let meas = Measurement {
            j: &prm.J,
            m: &prm.M,
            y: data.y,
            ru: data.ru,
            p: data.p,
            known: data.known,
        };
        nahi::update(&meas, x_pred, t_pred, x_filt, p_filt, &mut self.ws)
    }

    fn propagate(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]) {
        let prm = &self.sets[set as usize];
        nahi::propagate_cov(&prm.A, x, with_q.then_some(&prm.Q), out, &mut self.ws);
    }
}

/// The matrices of one parameter set at compile-time sizes.
#[derive(Clone)]
struct FixedSet<const N: usize, const Q: usize> {
    a: SMatrix<f64, N, N>,
    a_tr: SMatrix<f64, N, N>,
    j: SMatrix<f64, Q, N>,
    m: SMatrix<f64, Q, Q>,
    q: SMatrix<f64, N, N>,
}

/// `n = N`, `q = Q` known at compile time.
#[derive(Clone)]
pub struct FixedKernel<const N: usize, const Q: usize> {
    sets: std::sync::Arc<[FixedSet<N, Q>]>,
}

fn fixed<const R: usize, const C: usize>(m: &DMatrix<f64>) -> SMatrix<f64, R, C> {
    SMatrix::from_column_slice(m.as_slice())
}

fn symmetrize<const N: usize>(m: &mut SMatrix<f64, N, N>) {
    for r in 0..N {
        for c in 0..r {
            let v = 0.5 * (m[(r, c)] + m[(c, r)]);
            m[(r, c)] = v;
            m[(c, r)] = v;
        }
    }
}

impl<const N: usize, const Q: usize> LocalKernel for FixedKernel<N, Q> {
    fn new(model: &Model) -> Self {
        assert_eq!((model.dims.n, model.dims.q), (N, Q), "kernel size mismatch");
        Self {
            sets: model
                .param_sets()
                .iter()
                .map(|p| FixedSet {
                    a: fixed(&p.A),
                    a_tr: fixed::<N, N>(&p.A).transpose(),
                    j: fixed(&p.J),
                    m: fixed(&p.M),
                    q: fixed(&p.Q),
                })
                .collect::<Vec<_>>()
                .into(),
        }
    }

    fn update(
        &mut self,
        set: u32,
        data: &LocalData,
        s: &[f64],
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> bool {
        let prm = &self.sets[set as usize];
        let p = data.p;
        let t = SMatrix::<f64, N, N>::from_column_slice(t_pred);
        let x = SVector::<f64, N>::from_column_slice(x_pred);
        let mut h = prm.j * p;
        let mut reff = prm.m;
        if !data.known && p * (1.0 - p) != 0.0 {
            let s = SMatrix::<f64, N, N>::from_column_slice(s);
            reff += prm.j * s * prm.j.transpose() * (p * (1.0 - p));
        }
        let mut innov = SVector::<f64, Q>::from_fn(|k, _| data.y[k] - data.ru[k]) - h * x;
        if data.known {
            for k in 0..Q {
                if data.y[k].is_nan() {
                    h.row_mut(k).fill(0.0);
                    reff.row_mut(k).fill(0.0);
                    reff.column_mut(k).fill(0.0);
                    reff[(k, k)] = 1.0;
                    innov[k] = 0.0;
                }
            }
        }
        let ht = h * t;
        let Some(chol) = (ht * h.transpose() + reff).cholesky() else {
            return false;
        };
        let w = chol.solve(&ht); // W = Σ⁻¹ H T, L = Wᵀ
        let xf = x + w.transpose() * innov;
        let f = SMatrix::<f64, N, N>::identity() - w.transpose() * h;
        let mut pf = f * t * f.transpose() + w.transpose() * reff * w;
        symmetrize(&mut pf);
        x_filt.copy_from_slice(xf.as_slice());
        p_filt.copy_from_slice(pf.as_slice());
        true
    }

    fn propagate(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]) {
        let prm = &self.sets[set as usize];
        let x = SMatrix::<f64, N, N>::from_column_slice(x);
        let mut r = prm.a * x * prm.a_tr;
        if with_q {
            r += prm.q;
        }
        symmetrize(&mut r);
        out.copy_from_slice(r.as_slice());
    }
}
