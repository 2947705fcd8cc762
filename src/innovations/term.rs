//! One term of the innovation check: what the model predicts for the measurement `y(t, i)`
//! from the prior the filter's update starts from, and how far the measurement is from it
//! (docs/theory.md §14).
//!
//! [`TermWorkspace`] is written once over nalgebra's dimensions: with compile-time sizes
//! (`n ≤ 4`, `q ≤ 2`, every matrix on the stack) for the common chains, with runtime sizes
//! for the rest; [`scorer`] picks one for a model.

use nalgebra::allocator::Allocator;
use nalgebra::{
    Cholesky, Const, DefaultAllocator, Dim, Dyn, MatrixView, OMatrix, OVector, U1, VectorView,
};

use crate::filter::kernel::LANES;
use crate::filter::nahi::{Arrival, received_log_density};
use crate::innovations::lanes::LaneTerms;
use crate::model::Params;

/// Which predictive distribution a term is scored against (docs/theory.md §14).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TermKind {
    /// Known dropouts: `y ~ N(J m + R u, S₁)` on the received rows; `NIS ~ χ²_{q_r}`.
    Gaussian,
    /// Nahi's update with unknown dropouts: the two-component measurement, scored with its
    /// mean `μ` and covariance `Σ_y`; the variance of the NIS from the two components.
    Nahi,
    /// The mixture update: the arrival-weighted `NIS_π` and `ε_π`.
    Mixture,
}

/// The figures of one term.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Term {
    /// The normalised innovation squared (`NIS`, or `NIS_π` with the mixture update); its
    /// expected value is `received`. NaN when no row is in the data.
    pub nis: f64,
    /// The variance of `nis` for a model that fits.
    pub variance: f64,
    /// `q_r`, the rows of `y(t, i)` in the data.
    pub received: usize,
    /// `π`, from the prior (unknown dropouts only).
    pub arrival: Option<f64>,
}

impl Term {
    /// A term with no row in the data: not scored.
    pub const UNSCORED: Term = Term {
        nis: f64::NAN,
        variance: 0.0,
        received: 0,
        arrival: None,
    };
}

/// Scores terms: a [`TermWorkspace`] of some sizes.
pub trait TermScorer: Send {
    /// The term of `y` (`q` values, NaN where a row is not in the data) with `R u` = `ru`,
    /// from the prior `N(mean, cov)` of the subsystem (`cov` `n × n`, column-major) and the
    /// arrival probability `p`; with Nahi's update, `moment` is the filter's second moment
    /// `S` (`n × n`), whose `Σ_f` standardises the innovations. `None` when a covariance is
    /// not positive definite.
    #[allow(clippy::too_many_arguments)]
    fn term(
        &mut self,
        kind: TermKind,
        prm: &Params,
        p: f64,
        mean: &[f64],
        cov: &[f64],
        moment: Option<&[f64]>,
        y: &[f64],
        ru: &[f64],
    ) -> Option<Term>;
    /// The standardised innovations of the last term (`q` values, NaN for a row not in the
    /// data).
    fn eps(&self) -> &[f64];
    /// The terms of [`LANES`] consecutive subsystems of parameter set `id`, every row of
    /// their measurements in the data (the formulas of [`TermScorer::term`], four at once;
    /// `p`, `mean`, `cov`, `y` and `ru` one subsystem after the other), read with
    /// [`TermScorer::lane`]. `false` when they are to be scored one at a time: a covariance
    /// not positive definite, or runtime sizes.
    #[allow(clippy::too_many_arguments)]
    fn score_lanes(
        &mut self,
        _kind: TermKind,
        _id: u32,
        _prm: &Params,
        _p: [f64; LANES],
        _mean: &[f64],
        _cov: &[f64],
        _moment: Option<&[f64]>,
        _y: &[f64],
        _ru: &[f64],
    ) -> bool {
        false
    }
    /// Lane `l`'s term and standardised innovations after [`TermScorer::score_lanes`].
    fn lane(&self, _l: usize) -> (Term, &[f64]) {
        (Term::UNSCORED, &[])
    }
}

/// Compile-time sizes: one term at a time by [`TermWorkspace`], lanes by [`LaneTerms`].
struct FixedScorer<const N: usize, const Q: usize> {
    one: TermWorkspace<Const<N>, Const<Q>>,
    lanes: LaneTerms<N, Q>,
}

impl<const N: usize, const Q: usize> TermScorer for FixedScorer<N, Q> {
    fn term(
        &mut self,
        kind: TermKind,
        prm: &Params,
        p: f64,
        mean: &[f64],
        cov: &[f64],
        moment: Option<&[f64]>,
        y: &[f64],
        ru: &[f64],
    ) -> Option<Term> {
        self.one.term(kind, prm, p, mean, cov, moment, y, ru)
    }

    fn eps(&self) -> &[f64] {
        self.one.eps()
    }

    fn score_lanes(
        &mut self,
        kind: TermKind,
        id: u32,
        prm: &Params,
        p: [f64; LANES],
        mean: &[f64],
        cov: &[f64],
        moment: Option<&[f64]>,
        y: &[f64],
        ru: &[f64],
    ) -> bool {
        self.lanes.score(kind, id, prm, p, mean, cov, moment, y, ru)
    }

    fn lane(&self, l: usize) -> (Term, &[f64]) {
        (self.lanes.terms[l], &self.lanes.eps[l])
    }
}

/// The scorer for `n` states and `q` measured elements: compile-time sizes where they are
/// common, runtime sizes otherwise.
pub fn scorer(n: usize, q: usize) -> Box<dyn TermScorer> {
    macro_rules! fixed {
        ($(($n:literal, $q:literal)),*) => {
            match (n, q) {
                $(($n, $q) => Box::new(FixedScorer::<$n, $q> {
                    one: TermWorkspace::new(Const::<$n>, Const::<$q>),
                    lanes: LaneTerms::default(),
                }),)*
                _ => Box::new(TermWorkspace::new(Dyn(n), Dyn(q))),
            }
        };
    }
    fixed!(
        (1, 1),
        (2, 1),
        (3, 1),
        (4, 1),
        (1, 2),
        (2, 2),
        (3, 2),
        (4, 2)
    )
}

/// Scratch for the terms of `N` states and `Q` measured elements: nothing is allocated per
/// term.
pub struct TermWorkspace<N: Dim, Q: Dim>
where
    DefaultAllocator: Allocator<Q, N> + Allocator<N, Q> + Allocator<Q, Q> + Allocator<Q>,
{
    n: N,
    q: Q,
    j: OMatrix<f64, Q, N>,
    j_tr: OMatrix<f64, N, Q>,
    js: OMatrix<f64, Q, N>,
    jm: OVector<f64, Q>,
    e: OVector<f64, Q>,
    e0: OVector<f64, Q>,
    /// `S₁ = J Σ Jᵀ + M` and `M`, with a unit row and column where a row is not in the data.
    s1: OMatrix<f64, Q, Q>,
    m: OMatrix<f64, Q, Q>,
    /// The matrices the factors of `S₁`, `M` and `Σ_y` are made in (taken while a factor
    /// lives).
    factors: [Option<OMatrix<f64, Q, Q>>; 3],
    x: OMatrix<f64, Q, Q>,
    w: OVector<f64, Q>,
    w0: OVector<f64, Q>,
    eps: Vec<f64>,
}

impl<N: Dim, Q: Dim> TermWorkspace<N, Q>
where
    DefaultAllocator: Allocator<Q, N> + Allocator<N, Q> + Allocator<Q, Q> + Allocator<Q>,
{
    pub fn new(n: N, q: Q) -> Self {
        let square = || OMatrix::zeros_generic(q, q);
        let vector = || OVector::zeros_generic(q, U1);
        Self {
            n,
            q,
            j: OMatrix::zeros_generic(q, n),
            j_tr: OMatrix::zeros_generic(n, q),
            js: OMatrix::zeros_generic(q, n),
            jm: vector(),
            e: vector(),
            e0: vector(),
            s1: square(),
            m: square(),
            factors: std::array::from_fn(|_| Some(square())),
            x: square(),
            w: vector(),
            w0: vector(),
            eps: vec![f64::NAN; q.value()],
        }
    }

    /// The Cholesky factor of `of` (copied into the matrix of `slot`, which the factor
    /// takes); `None` when `of` is not positive definite.
    fn factor(&mut self, slot: usize, of: Of) -> Option<Cholesky<f64, Q>> {
        let mut mat = self.factors[slot]
            .take()
            .unwrap_or_else(|| OMatrix::zeros_generic(self.q, self.q));
        match of {
            Of::S1 => mat.copy_from(&self.s1),
            Of::M => mat.copy_from(&self.m),
            Of::Matrix => mat.copy_from(&self.x),
        }
        Cholesky::new(mat)
    }

    fn give_back(&mut self, slot: usize, factor: Cholesky<f64, Q>) {
        self.factors[slot] = Some(factor.unpack_dirty());
    }

    /// Nahi's two-component measurement (docs/theory.md §14): `μ = p J m + R u`,
    /// `Σ_y = p S₁ + (1−p) M + p(1−p) (J m)(J m)ᵀ`, `NIS = νᵀ Σ_y⁻¹ ν` with `ν = y − μ`, and
    /// `Var[NIS]` from the components `N((1−p) J m, S₁)` (probability `p`) and
    /// `N(−p J m, M)`: with `X_h = L⁻¹ C_h L⁻ᵀ`, `μ̃_h = L⁻¹ μ_h` (`Σ_y = L Lᵀ`),
    /// `E_h = tr X_h + |μ̃_h|²`, `V_h = 2 |X_h|²_F + 4 μ̃_hᵀ X_h μ̃_h` and
    /// `Var = p (V₁ + E₁²) + (1−p)(V₀ + E₀²) − q_r²`.
    fn nahi(&mut self, p: f64, y: &[f64], qr: f64) -> Option<(f64, f64)> {
        let q = y.len();
        self.x.copy_from(&self.s1);
        self.x.scale_mut(p);
        self.x.zip_apply(&self.m, |a, b| *a += (1.0 - p) * b);
        self.x.ger(p * (1.0 - p), &self.jm, &self.jm, 1.0);
        let ly = self.factor(2, Of::Matrix)?;
        let l = ly.l_dirty();
        self.w.copy_from(&self.e0);
        self.w.axpy(-p, &self.jm, 1.0);
        l.solve_lower_triangular_mut(&mut self.w);
        self.eps.copy_from_slice(self.w.as_slice());
        let nis = self.w.norm_squared();
        let mut moments = [(0.0, 0.0); 2];
        for (slot, shift) in [(0, 1.0 - p), (1, -p)] {
            self.x.copy_from(if slot == 0 { &self.s1 } else { &self.m });
            for k in (0..q).filter(|&k| y[k].is_nan()) {
                self.x[(k, k)] = 0.0;
            }
            l.solve_lower_triangular_mut(&mut self.x);
            self.x.transpose_mut();
            l.solve_lower_triangular_mut(&mut self.x);
            self.w0.copy_from(&self.jm);
            self.w0.scale_mut(shift);
            l.solve_lower_triangular_mut(&mut self.w0);
            let mut quad = 0.0;
            for r in 0..q {
                for c in 0..q {
                    quad += self.w0[r] * self.x[(r, c)] * self.w0[c];
                }
            }
            let mean = self.x.trace() + self.w0.norm_squared();
            moments[slot] = (mean, 2.0 * self.x.norm_squared() + 4.0 * quad);
        }
        self.give_back(2, ly);
        let [(e1, v1), (e0, v0)] = moments;
        Some((
            nis,
            p * (v1 + e1 * e1) + (1.0 - p) * (v0 + e0 * e0) - qr * qr,
        ))
    }

    /// The standardised innovations `ε = L_f⁻¹ ν` from the matrix Nahi's gain inverts,
    /// `Σ_f = M + p² J Σ Jᵀ + p(1−p) J S Jᵀ` with the filter's own second moment `S`
    /// (docs/theory.md §14), into `eps`: unlike `Σ_y`, whose `(J m)(J m)ᵀ` follows the data,
    /// it leaves a white series white. After [`Self::nahi`], whose `S₁`, `M`, `J m` and `e₀`
    /// it reads; `None` when `Σ_f` is not positive definite.
    fn standardise<S: nalgebra::Storage<f64, N, N>>(
        &mut self,
        p: f64,
        y: &[f64],
        moment: nalgebra::Matrix<f64, N, N, S>,
    ) -> Option<()> {
        self.js.gemm(1.0, &self.j, &moment, 0.0);
        self.x.gemm(p * (1.0 - p), &self.js, &self.j_tr, 0.0);
        self.x.zip_apply(&self.s1, |a, b| *a += p * p * b);
        self.x.zip_apply(&self.m, |a, b| *a += (1.0 - p * p) * b);
        for k in (0..y.len()).filter(|&k| y[k].is_nan()) {
            self.x.row_mut(k).fill(0.0);
            self.x.column_mut(k).fill(0.0);
            self.x[(k, k)] = 1.0;
        }
        let lf = self.factor(2, Of::Matrix)?;
        self.w.copy_from(&self.e0);
        self.w.axpy(-p, &self.jm, 1.0);
        lf.l_dirty().solve_lower_triangular_mut(&mut self.w);
        self.eps.copy_from_slice(self.w.as_slice());
        self.give_back(2, lf);
        Some(())
    }
}

/// Which matrix a factor is made of.
#[derive(Clone, Copy)]
enum Of {
    S1,
    M,
    Matrix,
}

impl<N: Dim, Q: Dim> TermScorer for TermWorkspace<N, Q>
where
    DefaultAllocator: Allocator<Q, N> + Allocator<N, Q> + Allocator<Q, Q> + Allocator<Q>,
    Self: Send,
{
    fn term(
        &mut self,
        kind: TermKind,
        prm: &Params,
        p: f64,
        mean: &[f64],
        cov: &[f64],
        moment: Option<&[f64]>,
        y: &[f64],
        ru: &[f64],
    ) -> Option<Term> {
        let (n, q) = (self.n, self.q);
        let received = y.iter().filter(|v| !v.is_nan()).count();
        self.eps.fill(f64::NAN);
        if received == 0 {
            return Some(Term::UNSCORED);
        }
        self.j.copy_from(&prm.J.generic_view((0, 0), (q, n)));
        self.j_tr.tr_copy_from(&self.j);
        self.jm.gemv(
            1.0,
            &self.j,
            &VectorView::from_slice_generic(mean, n, U1),
            0.0,
        );
        self.js.gemm(
            1.0,
            &self.j,
            &MatrixView::from_slice_generic(cov, n, n),
            0.0,
        );
        self.m.copy_from(&prm.M.generic_view((0, 0), (q, q)));
        self.s1.gemm(1.0, &self.js, &self.j_tr, 0.0);
        self.s1 += &self.m;
        for k in 0..q.value() {
            self.e0[k] = y[k] - ru[k];
            self.e[k] = self.e0[k] - self.jm[k];
        }
        // A row not in the data becomes a unit variance with a zero residual: it adds
        // nothing, and the factor of the rest is that of the received rows alone.
        for k in (0..q.value()).filter(|&k| y[k].is_nan()) {
            for mat in [&mut self.s1, &mut self.m] {
                mat.row_mut(k).fill(0.0);
                mat.column_mut(k).fill(0.0);
                mat[(k, k)] = 1.0;
            }
            self.e[k] = 0.0;
            self.e0[k] = 0.0;
            self.jm[k] = 0.0;
        }
        let l1 = self.factor(0, Of::S1)?;
        self.w.copy_from(&self.e);
        let ell1 = received_log_density(l1.l_dirty(), &mut self.w, q.value() - received);
        self.give_back(0, l1);
        let arrival = if kind == TermKind::Gaussian {
            None
        } else {
            let l0 = self.factor(1, Of::M)?;
            self.w0.copy_from(&self.e0);
            let ell0 = received_log_density(l0.l_dirty(), &mut self.w0, q.value() - received);
            self.give_back(1, l0);
            Some(Arrival::weigh(p, ell0, ell1).probability)
        };
        let qr = received as f64;
        let (nis, variance) = match kind {
            TermKind::Gaussian => {
                self.eps.copy_from_slice(self.w.as_slice());
                (self.w.norm_squared(), 2.0 * qr)
            }
            TermKind::Mixture => {
                let pi = arrival.unwrap_or(1.0);
                for (k, eps) in self.eps.iter_mut().enumerate() {
                    *eps = pi * self.w[k] + (1.0 - pi) * self.w0[k];
                }
                let nis = pi * self.w.norm_squared() + (1.0 - pi) * self.w0.norm_squared();
                (nis, 2.0 * qr)
            }
            TermKind::Nahi => {
                let figures = self.nahi(p, y, qr)?;
                if let Some(moment) = moment {
                    self.standardise(p, y, MatrixView::from_slice_generic(moment, n, n))?;
                }
                figures
            }
        };
        for (eps, v) in self.eps.iter_mut().zip(y) {
            if v.is_nan() {
                *eps = f64::NAN;
            }
        }
        Some(Term {
            nis,
            variance,
            received,
            arrival,
        })
    }

    fn eps(&self) -> &[f64] {
        &self.eps
    }
}
