//! The per-subsystem arithmetic of the two-step filter behind one trait, with two
//! implementations: [`DynamicKernel`] (any size, nalgebra `DMatrix` with preallocated
//! workspaces) and [`FixedKernel`] (compile-time sizes `n ≤ 4`, `q ≤ 2`, stack-allocated
//! `SMatrix`), which removes the per-call overhead of dynamic sizes for the common cases.
//! Both compute exactly the formulas of [`crate::filter::nahi`] (docs/theory.md §4).
//!
//! [`FixedKernel`] also updates and predicts [`LANES`] subsystems at once
//! ([`LocalKernel::update_lanes`], [`LocalKernel::mixture_lanes`],
//! [`LocalKernel::propagate_lanes`]): the same nalgebra
//! expressions over a scalar that holds one value per subsystem (simba's `WideF64x4`), so
//! each lane gets the bits the one-subsystem path gives it, while the four independent chains
//! of arithmetic run side by side in SIMD registers instead of one after another.

use nalgebra::{Cholesky, Const, DMatrix, SMatrix, SVector, SimdBool, SimdRealField, SimdValue};
use simba::simd::WideF64x4;

use crate::filter::nahi::{self, Measurement, Workspace};
use crate::linalg::symmetrize;
use crate::model::{Model, Params};

/// The local data of one update.
pub struct LocalData<'a> {
    /// `y(t,i)`; NaN marks an element not in the data (docs/theory.md §15).
    pub y: &'a [f64],
    /// `R u(t,i)`.
    pub ru: &'a [f64],
    /// Arrival probability used by the filter (1 in the known-dropout mode).
    pub p: f64,
    pub known: bool,
}

/// The local data of [`LANES`] consecutive subsystems: `y` and `R u` of each, one after the
/// other (`LANES · q` values each), every row in the data.
pub struct LaneData<'a> {
    pub y: &'a [f64],
    pub ru: &'a [f64],
    pub p: [f64; LANES],
    pub known: bool,
}

impl LaneData<'_> {
    /// The data of lane `l`.
    pub fn lane(&self, l: usize) -> LocalData<'_> {
        let q = self.y.len() / LANES;
        LocalData {
            y: &self.y[l * q..(l + 1) * q],
            ru: &self.ru[l * q..(l + 1) * q],
            p: self.p[l],
            known: self.known,
        }
    }
}

/// Local Nahi update and covariance prediction for parameter set `set` of the model.
///
/// The unknown-dropout update splits into a covariance part ([`LocalKernel::covariance_update`]:
/// gain and `P(t|t)` from `T`, `S`, `p`, independent of the data) and a mean part
/// ([`LocalKernel::mean_update`]); [`LocalKernel::update`] is the two together, with the same
/// arithmetic, so a gain computed once and shared by identical subsystems gives the same bits
/// as each subsystem computing its own.
pub trait LocalKernel: Clone + Send + Sync + Sized {
    /// What the mean update needs of the covariance update: `H = p J` and the gain.
    type Gain: Clone + Send + Sync;
    /// Prepares the kernel for every parameter set of `model`.
    fn new(model: &Model) -> Self;
    /// A gain of the right sizes, to be filled by [`LocalKernel::covariance_update`].
    fn new_gain(&self) -> Self::Gain;
    /// The Nahi update ([`nahi::update`]); `s` is the second moment `S` (`n × n`,
    /// column-major; unused in the known-dropout mode). Returns, in the known-dropout mode,
    /// the log density of the received elements of `y` given the past (a value not to be
    /// read in the unknown-dropout mode), or `None` when `Σ` is not positive definite.
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
    ) -> Option<f64>;
    /// The covariance part of the unknown-dropout update: `H = p J`,
    /// `R_eff = M + p(1−p) J S Jᵀ`, the gain `L = T Hᵀ Σ⁻¹` into `gain` and `P(t|t)` (Joseph
    /// form) into `p_filt`. Returns `false` when `Σ` is not positive definite.
    fn covariance_update(
        &mut self,
        set: u32,
        p: f64,
        s: &[f64],
        t_pred: &[f64],
        p_filt: &mut [f64],
        gain: &mut Self::Gain,
    ) -> bool;
    /// The mixture update of docs/theory.md §10 ([`nahi::mixture_update`], unknown dropouts,
    /// `data.p` the prior arrival probability). Returns `π` and the log density, or `None`
    /// when `S₁` or `M` is not positive definite.
    fn mixture_update(
        &mut self,
        set: u32,
        data: &LocalData,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> Option<nahi::Arrival>;
    /// The mean part: `x̂(t|t) = x̂ + L (y − R u − H x̂)`.
    fn mean_update(gain: &Self::Gain, data: &LocalData, x_pred: &[f64], x_filt: &mut [f64]);
    /// `out = A X Aᵀ + Q` (or without `Q`), symmetrised.
    fn propagate(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]);
    /// [`LocalKernel::update`] of [`LANES`] consecutive subsystems of parameter set `set`,
    /// every row of their measurements in the data: lane `l` of `data` and the `l`-th block
    /// of `s`, `x_pred`, `t_pred`, `x_filt`, `p_filt` and `log_densities` are subsystem `l`'s,
    /// each given the bits [`LocalKernel::update`] gives it. Returns `false` when some subsystem's
    /// `Σ` is not positive definite (the outputs are then not to be read). By default one
    /// subsystem after the other.
    #[allow(clippy::too_many_arguments)]
    fn update_lanes(
        &mut self,
        set: u32,
        data: &LaneData,
        s: &[f64],
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
        log_densities: &mut [f64],
    ) -> bool {
        let (n, nn) = (x_pred.len() / LANES, t_pred.len() / LANES);
        let s_len = s.len() / LANES;
        for l in 0..LANES {
            let Some(log_density) = self.update(
                set,
                &data.lane(l),
                &s[l * s_len..(l + 1) * s_len],
                &x_pred[l * n..(l + 1) * n],
                &t_pred[l * nn..(l + 1) * nn],
                &mut x_filt[l * n..(l + 1) * n],
                &mut p_filt[l * nn..(l + 1) * nn],
            ) else {
                return false;
            };
            log_densities[l] = log_density;
        }
        true
    }
    /// [`LocalKernel::mixture_update`] of [`LANES`] consecutive subsystems of parameter set
    /// `set`, every row of their measurements in the data, laid out as in
    /// [`LocalKernel::update_lanes`]; each lane's `π` into `arrival` and log density into
    /// `log_densities`, the bits [`LocalKernel::mixture_update`] gives it. Returns `false`
    /// when `S₁` or `M` is not positive definite in some lane. By default one subsystem after
    /// the other.
    #[allow(clippy::too_many_arguments)]
    fn mixture_lanes(
        &mut self,
        set: u32,
        data: &LaneData,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
        arrival: &mut [f64],
        log_densities: &mut [f64],
    ) -> bool {
        let (n, nn) = (x_pred.len() / LANES, t_pred.len() / LANES);
        for l in 0..LANES {
            let Some(a) = self.mixture_update(
                set,
                &data.lane(l),
                &x_pred[l * n..(l + 1) * n],
                &t_pred[l * nn..(l + 1) * nn],
                &mut x_filt[l * n..(l + 1) * n],
                &mut p_filt[l * nn..(l + 1) * nn],
            ) else {
                return false;
            };
            arrival[l] = a.probability;
            log_densities[l] = a.loglik;
        }
        true
    }
    /// [`LocalKernel::propagate`] of [`LANES`] consecutive subsystems of parameter set `set`
    /// (`x` and `out` hold their blocks one after the other). By default one after the other.
    fn propagate_lanes(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]) {
        let nn = x.len() / LANES;
        for (x, out) in x.chunks_exact(nn).zip(out.chunks_exact_mut(nn)) {
            self.propagate(set, with_q, x, out);
        }
    }
}

/// Subsystems [`LocalKernel::update_lanes`] and [`LocalKernel::propagate_lanes`] take at once.
pub const LANES: usize = 4;

/// One value per lane.
pub(crate) type Lanes = WideF64x4;

/// Any size: nalgebra's dynamic matrices and one reused [`Workspace`].
#[derive(Clone)]
pub struct DynamicKernel {
    sets: std::sync::Arc<[Params]>,
    ws: Workspace,
    /// `max(n, q)` zeros and an `n`-vector of scratch for [`LocalKernel::covariance_update`].
    zeros: Vec<f64>,
    x_scratch: Vec<f64>,
}

/// The gain of [`DynamicKernel`]: `H` (`q × n`) and `W = Σ⁻¹ H T = Lᵀ` (`q × n`).
#[derive(Clone)]
pub struct DynamicGain {
    h: DMatrix<f64>,
    w: DMatrix<f64>,
}

impl LocalKernel for DynamicKernel {
    type Gain = DynamicGain;

    fn new(model: &Model) -> Self {
        let (n, q) = (model.dims.n, model.dims.q);
        Self {
            sets: model.param_sets().into(),
            ws: Workspace::new(n, q),
            zeros: vec![0.0; n.max(q)],
            x_scratch: vec![0.0; n],
        }
    }

    fn new_gain(&self) -> DynamicGain {
        let (q, n) = self.sets[0].J.shape();
        DynamicGain {
            h: DMatrix::zeros(q, n),
            w: DMatrix::zeros(q, n),
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
    ) -> Option<f64> {
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

    fn covariance_update(
        &mut self,
        set: u32,
        p: f64,
        s: &[f64],
        t_pred: &[f64],
        p_filt: &mut [f64],
        gain: &mut DynamicGain,
    ) -> bool {
        let prm = &self.sets[set as usize];
        let (q, n) = prm.J.shape();
        self.ws
            .second_moment_mut()
            .as_mut_slice()
            .copy_from_slice(s);
        // The mean part of nahi::update is discarded: a zero measurement and prediction
        // keep it finite.
        let meas = Measurement {
            j: &prm.J,
            m: &prm.M,
            y: &self.zeros[..q],
            ru: &self.zeros[..q],
            p,
            known: false,
        };
        let ok = nahi::update(
            &meas,
            &self.zeros[..n],
            t_pred,
            &mut self.x_scratch,
            p_filt,
            &mut self.ws,
        );
        gain.h.copy_from(&prm.J);
        gain.h.scale_mut(p);
        gain.w.copy_from(self.ws.gain_transposed());
        ok.is_some()
    }

    fn mixture_update(
        &mut self,
        set: u32,
        data: &LocalData,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> Option<nahi::Arrival> {
        let prm = &self.sets[set as usize];
        let meas = Measurement {
            j: &prm.J,
            m: &prm.M,
            y: data.y,
            ru: data.ru,
            p: data.p,
            known: false,
        };
        nahi::mixture_update(&meas, x_pred, t_pred, x_filt, p_filt, &mut self.ws)
    }

    fn mean_update(gain: &DynamicGain, data: &LocalData, x_pred: &[f64], x_filt: &mut [f64]) {
        // The same operations, in the same order, as nahi::update and kalman_update (the
        // innovation is recomputed per column rather than stored, to stay allocation-free).
        let (q, n) = gain.h.shape();
        let innov = |k: usize| {
            let mut hx = 0.0;
            for c in 0..n {
                hx += gain.h[(k, c)] * x_pred[c];
            }
            data.y[k] - data.ru[k] - hx
        };
        for c in 0..n {
            let mut acc = x_pred[c];
            for k in 0..q {
                acc += gain.w[(k, c)] * innov(k);
            }
            x_filt[c] = acc;
        }
    }

    fn propagate(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]) {
        let prm = &self.sets[set as usize];
        nahi::propagate_cov(&prm.A, x, with_q.then_some(&prm.Q), out, &mut self.ws);
    }
}

/// The matrices of one parameter set at compile-time sizes, over the scalar `T` (`f64`, or
/// [`Lanes`] with the same value in every lane).
#[derive(Clone)]
struct FixedMatrices<T: SimdRealField + Copy, const N: usize, const Q: usize> {
    a: SMatrix<T, N, N>,
    a_tr: SMatrix<T, N, N>,
    j: SMatrix<T, Q, N>,
    j_tr: SMatrix<T, N, Q>,
    m: SMatrix<T, Q, Q>,
    q: SMatrix<T, N, N>,
}

impl<const N: usize, const Q: usize> FixedMatrices<f64, N, Q> {
    fn of(p: &Params) -> Self {
        Self {
            a: fixed(&p.A),
            a_tr: fixed::<N, N>(&p.A).transpose(),
            j: fixed(&p.J),
            j_tr: fixed::<Q, N>(&p.J).transpose(),
            m: fixed(&p.M),
            q: fixed(&p.Q),
        }
    }

    /// The same matrices in every lane.
    fn splat(&self) -> FixedMatrices<Lanes, N, Q> {
        FixedMatrices {
            a: self.a.map(Lanes::splat),
            a_tr: self.a_tr.map(Lanes::splat),
            j: self.j.map(Lanes::splat),
            j_tr: self.j_tr.map(Lanes::splat),
            m: self.m.map(Lanes::splat),
            q: self.q.map(Lanes::splat),
        }
    }
}

impl<T: SimdRealField + Copy, const N: usize, const Q: usize> FixedMatrices<T, N, Q> {
    /// `R_eff = M + p(1−p) J S Jᵀ`; `M` alone where `p(1−p) = 0`.
    #[inline(always)]
    fn reff(&self, p: T, s: &SMatrix<T, N, N>) -> SMatrix<T, Q, Q> {
        let weight = p * (T::one() - p);
        let zero = T::zero();
        if weight.simd_ne(zero).none() {
            return self.m;
        }
        let added = self.m + self.j * s * self.j_tr * weight;
        // Per lane, so that a lane with p(1−p) = 0 keeps M's own bits.
        added.zip_map(&self.m, |added, m| added.select(weight.simd_ne(zero), m))
    }

    /// `A X Aᵀ + Q` (or without `Q`), symmetrised.
    #[inline(always)]
    fn propagate(&self, with_q: bool, x: &SMatrix<T, N, N>) -> SMatrix<T, N, N> {
        let mut r = self.a * x * self.a_tr;
        if with_q {
            r += self.q;
        }
        symmetrize(&mut r);
        r
    }
}

/// The matrices of one parameter set at compile-time sizes, for one subsystem and for lanes.
#[derive(Clone)]
struct FixedSet<const N: usize, const Q: usize> {
    one: FixedMatrices<f64, N, Q>,
    lanes: FixedMatrices<Lanes, N, Q>,
    /// The lower Cholesky factor of `M`, once per parameter set (`None` if `M` is not
    /// positive definite, which a loaded model rules out).
    m_factor: Option<SMatrix<f64, Q, Q>>,
}

/// `n = N`, `q = Q` known at compile time.
#[derive(Clone)]
pub struct FixedKernel<const N: usize, const Q: usize> {
    sets: std::sync::Arc<[FixedSet<N, Q>]>,
}

/// The gain of [`FixedKernel`]: `H` and `L = Wᵀ`.
#[derive(Clone)]
pub struct FixedGain<const N: usize, const Q: usize> {
    h: SMatrix<f64, Q, N>,
    l: SMatrix<f64, N, Q>,
}

fn fixed<const R: usize, const C: usize>(m: &DMatrix<f64>) -> SMatrix<f64, R, C> {
    SMatrix::from_column_slice(m.as_slice())
}

/// `log N(v; 0, L Lᵀ)` from the lower factor `L` (only its lower triangle is read).
fn log_gaussian<const Q: usize>(l: &SMatrix<f64, Q, Q>, v: &SVector<f64, Q>) -> Option<f64> {
    let log_det: f64 = (0..Q).map(|k| 2.0 * l[(k, k)].ln()).sum();
    let white = l.solve_lower_triangular(v)?;
    Some(-0.5 * (Q as f64 * nahi::LN_2PI + log_det + white.norm_squared()))
}

/// The gain `L`, the Joseph-form `P(t|t)` and the Cholesky factor of `Σ`.
type GainAndFactor<T, const N: usize, const Q: usize> =
    (SMatrix<T, N, Q>, SMatrix<T, N, N>, Cholesky<T, Const<Q>>);

/// Gain and Joseph-form `P(t|t)` for the measurement model `H`, `R_eff`; `None` when `Σ` is
/// not positive definite (in some lane). The factor is nalgebra's `Cholesky::new`, step for
/// step, with its check of each pivot made on the factor's diagonal afterwards, so that one
/// function serves `f64` and lanes.
#[inline(always)]
fn gain<T: SimdRealField + Copy, const N: usize, const Q: usize>(
    h: &SMatrix<T, Q, N>,
    reff: &SMatrix<T, Q, Q>,
    t: &SMatrix<T, N, N>,
) -> Option<GainAndFactor<T, N, Q>> {
    let ht = h * t;
    let chol = factor(ht * h.transpose() + reff)?;
    let l = chol.solve(&ht).transpose(); // W = Σ⁻¹ H T, L = Wᵀ
    let f = SMatrix::<T, N, N>::identity() - l * h;
    let mut pf = f * t * f.transpose() + l * reff * l.transpose();
    symmetrize(&mut pf);
    Some((l, pf, chol))
}

/// The mixture update's `x̂(t|t)` and `P(t|t)` from the prior `x̂`, `T`, `J T`, the factor
/// of `S₁`, `e = y − R u − J x̂` and `π` (docs/theory.md §10, as in
/// [`nahi::mixture_update`]): `Kᵀ = S₁⁻¹ J T`, `g = K e`, `x̂ + π g` and
/// `T − π K J T + π(1−π) g gᵀ`, symmetrised.
#[inline(always)]
fn mixture_moments<T: SimdRealField + Copy, const N: usize, const Q: usize>(
    x: &SVector<T, N>,
    t: &SMatrix<T, N, N>,
    jt: &SMatrix<T, Q, N>,
    s1: &Cholesky<T, Const<Q>>,
    e: &SVector<T, Q>,
    pi: T,
) -> (SVector<T, N>, SMatrix<T, N, N>) {
    let k_tr = s1.solve(jt);
    let g = k_tr.transpose() * e;
    let mut pf = t - k_tr.transpose() * jt * pi + g * g.transpose() * (pi * (T::one() - pi));
    symmetrize(&mut pf);
    (x + g * pi, pf)
}

/// The lower Cholesky factor of `a`, as [`gain`] makes it; `None` when `a` is not positive
/// definite in some lane.
#[inline(always)]
pub(crate) fn factor<T: SimdRealField + Copy, const Q: usize>(
    a: SMatrix<T, Q, Q>,
) -> Option<Cholesky<T, Const<Q>>> {
    let chol = Cholesky::new_unchecked(a);
    let zero = T::zero();
    // A pivot that is zero, negative or NaN leaves a diagonal element that is not > 0.
    (0..Q)
        .all(|k| chol.l_dirty()[(k, k)].simd_gt(zero).all())
        .then_some(chol)
}

/// `x̂ + L (y − R u − H x̂)`, the innovation `y − R u − H x̂` beside it.
#[inline(always)]
fn mean<T: SimdRealField + Copy, const N: usize, const Q: usize>(
    h: &SMatrix<T, Q, N>,
    l: &SMatrix<T, N, Q>,
    measured: SVector<T, Q>,
    x: &SVector<T, N>,
) -> (SVector<T, N>, SVector<T, Q>) {
    let innov = measured - h * x;
    (x + l * innov, innov)
}

/// The lanes of `LANES` column-major `R × C` blocks stored one after the other.
#[inline(always)]
pub(crate) fn gather<const R: usize, const C: usize>(blocks: &[f64]) -> SMatrix<Lanes, R, C> {
    SMatrix::from_fn(|r, c| Lanes::from(std::array::from_fn(|l| blocks[l * R * C + c * R + r])))
}

/// The inverse of [`gather`].
#[inline(always)]
fn scatter<const R: usize, const C: usize>(m: &SMatrix<Lanes, R, C>, blocks: &mut [f64]) {
    for c in 0..C {
        for r in 0..R {
            let values: [f64; LANES] = m[(r, c)].into();
            for (l, v) in values.into_iter().enumerate() {
                blocks[l * R * C + c * R + r] = v;
            }
        }
    }
}

/// Lane `l` of a matrix of lanes.
fn lane<const R: usize, const C: usize>(m: &SMatrix<Lanes, R, C>, l: usize) -> SMatrix<f64, R, C> {
    m.map(|v| v.extract(l))
}

impl<const N: usize, const Q: usize> LocalKernel for FixedKernel<N, Q> {
    type Gain = FixedGain<N, Q>;

    fn new(model: &Model) -> Self {
        assert_eq!((model.dims.n, model.dims.q), (N, Q), "kernel size mismatch");
        Self {
            sets: model
                .param_sets()
                .iter()
                .map(|p| {
                    let one = FixedMatrices::<f64, N, Q>::of(p);
                    FixedSet {
                        lanes: one.splat(),
                        m_factor: one.m.cholesky().map(|c| c.unpack()),
                        one,
                    }
                })
                .collect::<Vec<_>>()
                .into(),
        }
    }

    fn new_gain(&self) -> FixedGain<N, Q> {
        FixedGain {
            h: SMatrix::zeros(),
            l: SMatrix::zeros(),
        }
    }

    #[inline]
    fn update(
        &mut self,
        set: u32,
        data: &LocalData,
        s: &[f64],
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> Option<f64> {
        let prm = &self.sets[set as usize].one;
        let t = SMatrix::<f64, N, N>::from_column_slice(t_pred);
        let x = SVector::<f64, N>::from_column_slice(x_pred);
        let measured = SVector::<f64, Q>::from_fn(|k, _| data.y[k] - data.ru[k]);
        let complete = !data.y.iter().any(|v| v.is_nan());
        if !data.known && complete {
            let h = prm.j * data.p;
            let reff = prm.reff(data.p, &SMatrix::from_column_slice(s));
            let (l, pf, _) = gain(&h, &reff, &t)?;
            let (xf, _) = mean(&h, &l, measured, &x);
            x_filt.copy_from_slice(xf.as_slice());
            p_filt.copy_from_slice(pf.as_slice());
            return Some(0.0);
        }
        // A row not in the data gets H_k = 0, ỹ_k = 0 and a unit row and column in R_eff,
        // so it contributes nothing (nahi::remove_row).
        let mut h = prm.j * data.p;
        let mut reff = if data.known {
            prm.m
        } else {
            prm.reff(data.p, &SMatrix::from_column_slice(s))
        };
        let mut measured = measured;
        let mut dropped = 0;
        for k in nahi::missing_rows(data.y) {
            h.row_mut(k).fill(0.0);
            nahi::remove_row(&mut reff, k);
            measured[k] = 0.0;
            dropped += 1;
        }
        let (l, pf, chol) = gain(&h, &reff, &t)?;
        let (xf, innov) = mean(&h, &l, measured, &x);
        x_filt.copy_from_slice(xf.as_slice());
        p_filt.copy_from_slice(pf.as_slice());
        // log N(ỹ; 0, Σ) over the received rows (a dropped row's ỹ_k is 0 − 0·x̂ = 0): it
        // adds only −½ log 2π, taken back (as in nahi::kalman_update).
        Some(log_gaussian(chol.l_dirty(), &innov)? + 0.5 * dropped as f64 * nahi::LN_2PI)
    }

    fn update_lanes(
        &mut self,
        set: u32,
        data: &LaneData,
        s: &[f64],
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
        log_densities: &mut [f64],
    ) -> bool {
        let prm = &self.sets[set as usize].lanes;
        let known = data.known;
        let p = Lanes::from(data.p);
        let t = gather::<N, N>(t_pred);
        let x = gather::<N, 1>(x_pred);
        let measured = gather::<Q, 1>(data.y) - gather::<Q, 1>(data.ru);
        let h = prm.j * p;
        let reff = if known {
            prm.m
        } else {
            prm.reff(p, &gather::<N, N>(s))
        };
        let Some((l, pf, chol)) = gain(&h, &reff, &t) else {
            return false;
        };
        let (xf, innov) = mean(&h, &l, measured, &x);
        scatter(&xf, x_filt);
        scatter(&pf, p_filt);
        for (l, log_density) in log_densities.iter_mut().enumerate() {
            *log_density = if known {
                let Some(density) = log_gaussian(&lane(chol.l_dirty(), l), &lane(&innov, l)) else {
                    return false;
                };
                density
            } else {
                0.0
            };
        }
        true
    }

    fn covariance_update(
        &mut self,
        set: u32,
        p: f64,
        s: &[f64],
        t_pred: &[f64],
        p_filt: &mut [f64],
        gain_out: &mut FixedGain<N, Q>,
    ) -> bool {
        let prm = &self.sets[set as usize].one;
        let t = SMatrix::<f64, N, N>::from_column_slice(t_pred);
        let h = prm.j * p;
        let reff = prm.reff(p, &SMatrix::from_column_slice(s));
        let Some((l, pf, _)) = gain(&h, &reff, &t) else {
            return false;
        };
        gain_out.h = h;
        gain_out.l = l;
        p_filt.copy_from_slice(pf.as_slice());
        true
    }

    fn mixture_update(
        &mut self,
        set: u32,
        data: &LocalData,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
    ) -> Option<nahi::Arrival> {
        let prm = &self.sets[set as usize];
        let t = SMatrix::<f64, N, N>::from_column_slice(t_pred);
        let x = SVector::<f64, N>::from_column_slice(x_pred);
        let mut e0 = SVector::<f64, Q>::from_fn(|k, _| data.y[k] - data.ru[k]);
        let (mut j, mut m, mut m_factor) = (prm.one.j, prm.one.m, prm.m_factor);
        let mut dropped = 0;
        if data.y.iter().any(|v| v.is_nan()) {
            // Only the received rows (docs/theory.md §15), removed as nahi::mixture_weights
            // removes them; with none the subsystem is only predicted.
            if data.y.iter().all(|v| v.is_nan()) {
                x_filt.copy_from_slice(x_pred);
                p_filt.copy_from_slice(t_pred);
                return Some(nahi::Arrival::NONE_RECEIVED);
            }
            for k in nahi::missing_rows(data.y) {
                j.row_mut(k).fill(0.0);
                nahi::remove_row(&mut m, k);
                e0[k] = 0.0;
                dropped += 1;
            }
            m_factor = m.cholesky().map(|c| c.unpack());
        }
        let e = e0 - j * x;
        let jt = j * t;
        let s1 = factor(jt * j.transpose() + m)?;
        let correction = 0.5 * dropped as f64 * nahi::LN_2PI;
        let ell0 = log_gaussian(m_factor.as_ref()?, &e0)? + correction;
        let ell1 = log_gaussian(s1.l_dirty(), &e)? + correction;
        let arrival = nahi::Arrival::weigh(data.p, ell0, ell1);
        let (xf, pf) = mixture_moments(&x, &t, &jt, &s1, &e, arrival.probability);
        p_filt.copy_from_slice(pf.as_slice());
        x_filt.copy_from_slice(xf.as_slice());
        Some(arrival)
    }

    fn mixture_lanes(
        &mut self,
        set: u32,
        data: &LaneData,
        x_pred: &[f64],
        t_pred: &[f64],
        x_filt: &mut [f64],
        p_filt: &mut [f64],
        arrival: &mut [f64],
        log_densities: &mut [f64],
    ) -> bool {
        let FixedSet {
            lanes: prm,
            m_factor: Some(m_factor),
            ..
        } = &self.sets[set as usize]
        else {
            return false;
        };
        let t = gather::<N, N>(t_pred);
        let x = gather::<N, 1>(x_pred);
        let e0 = gather::<Q, 1>(data.y) - gather::<Q, 1>(data.ru);
        let e = e0 - prm.j * x;
        let jt = prm.j * t;
        let Some(s1) = factor(jt * prm.j.transpose() + prm.m) else {
            return false;
        };
        // The log densities per lane, with the one-subsystem path's arithmetic.
        let mut pi = [0.0; LANES];
        for l in 0..LANES {
            let (Some(ell0), Some(ell1)) = (
                log_gaussian(m_factor, &lane(&e0, l)),
                log_gaussian(&lane(s1.l_dirty(), l), &lane(&e, l)),
            ) else {
                return false;
            };
            let a = nahi::Arrival::weigh(data.p[l], ell0, ell1);
            (pi[l], arrival[l], log_densities[l]) = (a.probability, a.probability, a.loglik);
        }
        let (xf, pf) = mixture_moments(&x, &t, &jt, &s1, &e, Lanes::from(pi));
        scatter(&xf, x_filt);
        scatter(&pf, p_filt);
        true
    }

    #[inline]
    fn mean_update(gain: &FixedGain<N, Q>, data: &LocalData, x_pred: &[f64], x_filt: &mut [f64]) {
        let x = SVector::<f64, N>::from_column_slice(x_pred);
        let measured = SVector::<f64, Q>::from_fn(|k, _| data.y[k] - data.ru[k]);
        let (xf, _) = mean(&gain.h, &gain.l, measured, &x);
        x_filt.copy_from_slice(xf.as_slice());
    }

    #[inline]
    fn propagate(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]) {
        let prm = &self.sets[set as usize].one;
        let r = prm.propagate(with_q, &SMatrix::from_column_slice(x));
        out.copy_from_slice(r.as_slice());
    }

    #[inline]
    fn propagate_lanes(&mut self, set: u32, with_q: bool, x: &[f64], out: &mut [f64]) {
        let prm = &self.sets[set as usize].lanes;
        scatter(&prm.propagate(with_q, &gather::<N, N>(x)), out);
    }
}
