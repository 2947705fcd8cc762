//! The terms of [`LANES`] consecutive subsystems at once (compile-time sizes, every row of
//! their measurements in the data): the formulas of [`super::term`] over a scalar that holds
//! one value per subsystem, so that the square roots and divisions of the four factors run
//! side by side instead of one chain after another (docs/theory.md §14).

use nalgebra::{SMatrix, SVector, SimdValue};

use crate::filter::kernel::{self, LANES, Lanes, gather};
use crate::model::Params;

use super::term::{Term, TermKind};

/// The matrices of one parameter set in every lane.
struct LaneSet<const N: usize, const Q: usize> {
    id: u32,
    j: SMatrix<Lanes, Q, N>,
    j_tr: SMatrix<Lanes, N, Q>,
    m: SMatrix<Lanes, Q, Q>,
    /// The lower Cholesky factor of `M`.
    m_factor: SMatrix<Lanes, Q, Q>,
}

/// The terms of the last [`LaneTerms::score`] and the parameter set they were scored with.
pub struct LaneTerms<const N: usize, const Q: usize> {
    set: Option<LaneSet<N, Q>>,
    /// The terms of the lanes.
    pub terms: [Term; LANES],
    /// The standardised innovations of each lane.
    pub eps: [[f64; Q]; LANES],
}

/// `b ← L⁻¹ b` for a lower triangular `L` (forward substitution, column by column).
fn forward<const Q: usize, const C: usize>(l: &SMatrix<Lanes, Q, Q>, b: &mut SMatrix<Lanes, Q, C>) {
    for c in 0..C {
        for i in 0..Q {
            let coeff = b[(i, c)] / l[(i, i)];
            b[(i, c)] = coeff;
            for r in i + 1..Q {
                b[(r, c)] -= l[(r, i)] * coeff;
            }
        }
    }
}

/// The lower Cholesky factor of `a` in every lane (its upper triangle not to be read), or
/// `None` when `a` is not positive definite in some lane.
fn factor<const Q: usize>(a: SMatrix<Lanes, Q, Q>) -> Option<SMatrix<Lanes, Q, Q>> {
    kernel::factor(a).map(|chol| chol.unpack_dirty())
}

/// `π = p e^ℓ₁ / (p e^ℓ₁ + (1−p) e^ℓ₀)` from the factors `L₁` of `S₁` and `L₀` of `M` and the
/// squared norms `|L₁⁻¹ e|²`, `|L₀⁻¹ e₀|²` (docs/theory.md §10, as `Arrival::weigh` gives
/// it): with `ℓ₀ − ℓ₁ = ½(|L₁⁻¹ e|² − |L₀⁻¹ e₀|²) + log(∏ L₁,kk / ∏ L₀,kk)`,
/// `π = 1 / (1 + (1−p)/p · ∏ L₁,kk / ∏ L₀,kk · exp(½(|L₁⁻¹ e|² − |L₀⁻¹ e₀|²)))`, one
/// exponential per lane instead of logarithms and exponentials; 0 for `p ≤ 0`, 1 for `p ≥ 1`.
fn arrival<const Q: usize>(
    p: [f64; LANES],
    l1: &SMatrix<Lanes, Q, Q>,
    l0: &SMatrix<Lanes, Q, Q>,
    white1: Lanes,
    white0: Lanes,
) -> Lanes {
    let ratio = l1.diagonal().product() / l0.diagonal().product();
    let half = (white1 - white0) * Lanes::splat(0.5);
    Lanes::from(std::array::from_fn(|l| {
        let p = p[l];
        if p <= 0.0 {
            0.0
        } else if p >= 1.0 {
            1.0
        } else {
            1.0 / (1.0 + (1.0 - p) / p * ratio.extract(l) * half.extract(l).exp())
        }
    }))
}

impl<const N: usize, const Q: usize> Default for LaneTerms<N, Q> {
    fn default() -> Self {
        Self {
            set: None,
            terms: [Term::UNSCORED; LANES],
            eps: [[f64::NAN; Q]; LANES],
        }
    }
}

impl<const N: usize, const Q: usize> LaneTerms<N, Q> {
    /// The matrices of parameter set `id` (kept while consecutive calls use the same set);
    /// `None` when `M` is not positive definite.
    fn set(&mut self, id: u32, prm: &Params) -> Option<&LaneSet<N, Q>> {
        if self.set.as_ref().is_none_or(|s| s.id != id) {
            let j = SMatrix::<f64, Q, N>::from_column_slice(prm.J.as_slice());
            let m = SMatrix::<f64, Q, Q>::from_column_slice(prm.M.as_slice());
            let m_factor = m.cholesky()?.unpack();
            self.set = Some(LaneSet {
                id,
                j: j.map(Lanes::splat),
                j_tr: j.transpose().map(Lanes::splat),
                m: m.map(Lanes::splat),
                m_factor: m_factor.map(Lanes::splat),
            });
        }
        self.set.as_ref()
    }

    /// The terms of `LANES` consecutive subsystems of parameter set `id` ([`super::term`]'s
    /// formulas, docs/theory.md §14) into [`Self::terms`] and [`Self::eps`]: `p` their
    /// arrival probabilities, `mean`, `cov`, `y` and `ru` their priors, measurements (every
    /// row in the data) and `R u`, one subsystem after the other. `false` when a covariance
    /// is not positive definite in some lane (nothing is written then).
    #[allow(clippy::too_many_arguments)]
    pub fn score(
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
        let Some(set) = self.set(id, prm) else {
            return false;
        };
        let jm = set.j * gather::<N, 1>(mean);
        let s1 = set.j * gather::<N, N>(cov) * set.j_tr + set.m;
        let e0 = gather::<Q, 1>(y) - gather::<Q, 1>(ru);
        let mut w = e0 - jm;
        let Some(l1) = factor(s1) else {
            return false;
        };
        forward(&l1, &mut w);
        let two_q = Lanes::splat(2.0 * Q as f64);
        let (nis, variance, eps, arrival) = match kind {
            TermKind::Gaussian => (w.norm_squared(), two_q, w, None),
            TermKind::Nahi | TermKind::Mixture => {
                let mut w0 = e0;
                forward(&set.m_factor, &mut w0);
                let (white1, white0) = (w.norm_squared(), w0.norm_squared());
                let pi = arrival(p, &l1, &set.m_factor, white1, white0);
                let one = Lanes::splat(1.0);
                if kind == TermKind::Mixture {
                    let eps = w * pi + w0 * (one - pi);
                    (pi * white1 + (one - pi) * white0, two_q, eps, Some(pi))
                } else {
                    let moment = moment.map(gather::<N, N>);
                    let Some((nis, variance, eps)) =
                        nahi(set, Lanes::from(p), &s1, &jm, &e0, moment)
                    else {
                        return false;
                    };
                    (nis, variance, eps, Some(pi))
                }
            }
        };
        for l in 0..LANES {
            self.terms[l] = Term {
                nis: nis.extract(l),
                variance: variance.extract(l),
                received: Q,
                arrival: arrival.map(|a| a.extract(l)),
            };
            self.eps[l] = std::array::from_fn(|k| eps[k].extract(l));
        }
        true
    }
}

/// Nahi's two-component measurement ([`super::term`], docs/theory.md §14): the NIS against
/// `Σ_y = p S₁ + (1−p) M + p(1−p) (J m)(J m)ᵀ`, its variance from the two components, and the
/// standardised innovation, from `Σ_f = M + p² J Σ Jᵀ + p(1−p) J S Jᵀ` where the filter's
/// second moment `S` is given (else from `Σ_y`).
fn nahi<const N: usize, const Q: usize>(
    set: &LaneSet<N, Q>,
    p: Lanes,
    s1: &SMatrix<Lanes, Q, Q>,
    jm: &SVector<Lanes, Q>,
    e0: &SVector<Lanes, Q>,
    moment: Option<SMatrix<Lanes, N, N>>,
) -> Option<(Lanes, Lanes, SVector<Lanes, Q>)> {
    let one = Lanes::splat(1.0);
    let sigma_y = s1 * p + set.m * (one - p) + jm * jm.transpose() * (p * (one - p));
    let ly = factor(sigma_y)?;
    let mut w = e0 - jm * p;
    forward(&ly, &mut w);
    let mut moments = [(Lanes::splat(0.0), Lanes::splat(0.0)); 2];
    for (slot, (c, shift)) in [(s1, one - p), (&set.m, -p)].into_iter().enumerate() {
        let mut x = *c;
        forward(&ly, &mut x);
        x = x.transpose();
        forward(&ly, &mut x);
        let mut w0 = jm * shift;
        forward(&ly, &mut w0);
        let quad = (w0.transpose() * x * w0)[(0, 0)];
        moments[slot] = (
            x.trace() + w0.norm_squared(),
            Lanes::splat(2.0) * x.norm_squared() + Lanes::splat(4.0) * quad,
        );
    }
    let [(e1, v1), (e0m, v0)] = moments;
    let q = Lanes::splat(Q as f64);
    let variance = p * (v1 + e1 * e1) + (one - p) * (v0 + e0m * e0m) - q * q;
    let nis = w.norm_squared();
    if let Some(s) = moment {
        let sigma_f = (s1 - set.m) * (p * p) + set.m + set.j * s * set.j_tr * (p * (one - p));
        let lf = factor(sigma_f)?;
        w = e0 - jm * p;
        forward(&lf, &mut w);
    }
    Some((nis, variance, w))
}
