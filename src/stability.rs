//! The stability of the lifted chain (docs/theory.md §3): the spectral radius of `A_eff`,
//! exact from all eigenvalues of the dense matrix on chains small enough, else a Krylov
//! estimate, each with the error bound that says whether it excludes 1.

use faer::linalg::matmul::matmul;
use faer::{Accum, ColMut, ColRef, MatRef, Par};

use crate::interconnect::ChainSolver;
use crate::lifted::{LiftedWorkspace, a_eff_dense, apply_a_eff};
use crate::model::Model;

/// The spectral radius of `A_eff` over a time window, with its error bound.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SpectralRadius {
    pub value: f64,
    /// True when computed from all eigenvalues, false for a Krylov estimate.
    pub exact: bool,
    /// Exact: the rounding bound `√(size · ε · ‖A_eff‖_F)`, which covers an eigenvalue in a
    /// Jordan block of two (the dense eigenvalues are those of a matrix within
    /// `size · ε · ‖A_eff‖` of `A_eff`). Krylov: the residual `‖A_eff z − θ z‖` of the largest
    /// Ritz pair (`‖z‖ = 1`), so that `θ` is an eigenvalue of a matrix within `bound` of
    /// `A_eff` in the 2-norm (docs/theory.md §3).
    pub bound: f64,
}

/// What a [`SpectralRadius`] says of the chain (docs/theory.md §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stability {
    /// Below 1 beyond its bound (exact), or estimated below 1.
    Stable,
    /// 1 within the bound of an exact radius, or an estimate of at least 1 whose bound reaches
    /// down to 1: the second moment grows at worst like a power of `t`, not exponentially.
    Marginal,
    /// `value − bound > 1`: exact, the moment grows exponentially; estimated, some power of
    /// `A_eff` grows at least `(value − 1) / bound`-fold (Kreiss's bound).
    Unstable,
}

impl SpectralRadius {
    /// An estimate below 1 is taken as it is, although its bound may reach 1: the Ritz values
    /// of a non-normal `A_eff` see beyond its eigenvalues (the 500-car platoon: 0.99990 ± 5e−3
    /// against 0.99797), and those of a normal one lie in the convex hull of its eigenvalues,
    /// so at most its radius.
    pub fn stability(&self) -> Stability {
        let below = if self.exact { self.bound } else { 0.0 };
        if self.value - self.bound > 1.0 {
            Stability::Unstable
        } else if self.value + below >= 1.0 {
            Stability::Marginal
        } else {
            Stability::Stable
        }
    }

    /// Kreiss's lower bound on `sup_k ‖A_effᵏ‖₂` from an estimate above 1: a matrix within
    /// `bound` of `A_eff` has the eigenvalue `θ`, `|θ| = value`, so
    /// `‖(θ I − A_eff)⁻¹‖ ≥ 1 / bound` and `sup_k ‖A_effᵏ‖ ≥ (|θ| − 1) ‖(θ I − A_eff)⁻¹‖`.
    pub fn least_growth(&self) -> f64 {
        (self.value - 1.0) / self.bound
    }
}

/// How much work [`spectral_radius`] does (docs/theory.md §3).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RadiusEffort {
    /// Up to this many lifted states `N · n`, all eigenvalues of the dense `A_eff`.
    pub exact_max: usize,
    /// Above it, the largest Ritz value of an Arnoldi process of this many steps.
    pub krylov: usize,
}

impl RadiusEffort {
    /// The figure of `check` and of every run, so that both say the same: exact up to 400
    /// lifted states (0.1 s), else 40 Arnoldi steps (a few ms; docs/theory.md §3).
    pub const DEFAULT: Self = Self {
        exact_max: 400,
        krylov: 40,
    };
}

/// Spectral radius of `A_eff(t)`: all eigenvalues of the dense matrix for
/// `N n ≤ effort.exact_max`; else the largest `|θ|` over the eigenvalues `θ` (Ritz values) of
/// the Hessenberg matrix `H_k = V_kᵀ A_eff V_k` of `k = effort.krylov` Arnoldi steps from a
/// fixed start vector (docs/theory.md §3). Exact when the Krylov space reaches every state.
/// `solver` must be prepared for `t`.
pub fn spectral_radius(
    model: &Model,
    t: usize,
    solver: &ChainSolver,
    effort: RadiusEffort,
) -> SpectralRadius {
    let size = model.subsystems * model.dims.n;
    if size <= effort.exact_max {
        let a = a_eff_dense(model, t, solver);
        let bound = (size as f64 * f64::EPSILON * a.norm()).sqrt();
        // nalgebra's Schur iteration can stall on the clustered spectra of long chains;
        // faer's eigenvalue solver uses exceptional shifts and does not.
        let a = faer::Mat::from_fn(size, size, |r, c| a[(r, c)]);
        if let Ok(eigenvalues) = a.eigenvalues() {
            let value = eigenvalues.iter().map(|l| l.norm()).fold(0.0, f64::max);
            return SpectralRadius {
                value,
                exact: true,
                bound,
            };
        }
    }
    ritz_radius(model, t, solver, effort.krylov.clamp(1, size))
}

/// The largest Ritz value's modulus after `k ≤ N n` Arnoldi steps on `A_eff(t)`, with
/// classical Gram–Schmidt applied twice (which keeps `V_k` orthonormal to rounding), and its
/// residual `‖A_eff V_k y − θ V_k y‖ = h_{k+1,k} |e_kᵀ y|` (`y` the unit eigenvector of `H_k`),
/// at least the rounding bound of the eigenvalues of `H_k`.
fn ritz_radius(model: &Model, t: usize, solver: &ChainSolver, k: usize) -> SpectralRadius {
    let size = model.subsystems * model.dims.n;
    // `basis` holds v_1 … v_{k+1} one after another (the columns of V); `h` is H_k,
    // column-major with k + 1 rows.
    let mut basis = vec![0.0; (k + 1) * size];
    let mut h = vec![0.0; (k + 1) * k];
    let mut ws = LiftedWorkspace::default();
    let start = &mut basis[..size];
    for (j, v) in start.iter_mut().enumerate() {
        *v = 1.0 + 0.5 * ((j as f64) * 0.618_033_988_75).fract();
    }
    let norm = start.iter().map(|v| v * v).sum::<f64>().sqrt();
    start.iter_mut().for_each(|v| *v /= norm);
    let mut steps = k;
    for j in 0..k {
        let (done, rest) = basis.split_at_mut((j + 1) * size);
        let next = &mut rest[..size];
        apply_a_eff(model, t, solver, &done[j * size..], next, &mut ws);
        let scale = next.iter().map(|v| v * v).sum::<f64>().sqrt();
        let done = MatRef::from_column_major_slice(&done[..], size, j + 1);
        for _pass in 0..2 {
            let coefficients = done.transpose() * ColRef::from_slice(next);
            matmul(
                ColMut::from_slice_mut(next).as_mat_mut(),
                Accum::Add,
                done,
                coefficients.as_mat(),
                -1.0,
                Par::Seq,
            );
            for (i, c) in coefficients.iter().enumerate() {
                h[j * (k + 1) + i] += c;
            }
        }
        let norm = next.iter().map(|v| v * v).sum::<f64>().sqrt();
        h[j * (k + 1) + j + 1] = norm;
        if norm <= 1e-12 * scale.max(f64::MIN_POSITIVE) {
            steps = j + 1;
            break;
        }
        next.iter_mut().for_each(|v| *v /= norm);
    }
    let hk = faer::Mat::from_fn(steps, steps, |r, c| h[c * (k + 1) + r]);
    // h_{k+1,k}, at rounding level on an invariant subspace (the whole space among them),
    // whose Ritz values are eigenvalues of A_eff.
    let next_norm = h[(steps - 1) * (k + 1) + steps];
    let rounding = (steps as f64 * f64::EPSILON * hk.norm_l2()).sqrt();
    let (value, bound) = match hk.eigen() {
        Ok(eigen) => {
            let (values, vectors) = (eigen.S().column_vector(), eigen.U());
            let largest = (0..steps)
                .max_by(|&a, &b| values[a].norm().total_cmp(&values[b].norm()))
                .unwrap_or(0);
            let y = vectors.col(largest);
            let y_norm = y.iter().map(|c| c.norm() * c.norm()).sum::<f64>().sqrt();
            let last = y[steps - 1].norm() / y_norm.max(f64::MIN_POSITIVE);
            (values[largest].norm(), (next_norm * last).max(rounding))
        }
        // The Hessenberg QR did not converge: the norm of H_k bounds its eigenvalues, and
        // nothing bounds their distance to A_eff's.
        Err(_) => (hk.norm_l2(), f64::INFINITY),
    };
    SpectralRadius {
        value,
        exact: steps == size,
        bound,
    }
}
