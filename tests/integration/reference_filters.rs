//! Tests of the lifted system, the centralized reference filters and `evaluate` against
//! independent references: a dense lifted Kalman filter built here from a dense solve of
//! (P2)–(P4), Monte Carlo moments, and the distributed filter where they must agree.

use crate::common::{model_from, shipped_model, simulate_run};
use nalgebra::{DMatrix, DVector};
use sisfilt::choice::Choice;
use sisfilt::evaluate::{Compared, EvaluateOptions, Evaluation, evaluate};
use sisfilt::filter::{
    CentralizedFilter, ChainFilter, Dropouts, JointFilter, JointOptions, SecondMoment,
    TwoStepFilter, TwoStepOptions, Update, two_step,
};
use sisfilt::inputs::RunInputs;
use sisfilt::lifted::{LiftedMoments, LiftedSystem};
use sisfilt::model::Model;

const SINGLE: &str = "
subsystems = 1
steps = 60
[interconnection]
plus = 1
minus = 1
[model]
A = [[0.9, 0.2], [-0.1, 0.8]]
B = [[0.3, 0.1], [0.0, 0.2]]
C = [[0.0], [0.5]]
D = [[1.0, 0.0], [0.0, 1.0]]
G = [[0.2, 0.1], [0.1, 0.2]]
J = [[1.0, 0.3]]
R = [[0.2]]
M = [[0.3]]
Q = [[0.02, 0.0], [0.0, 0.01]]
[dropout]
p = 0.6
[initial]
mean = [0.5, -0.5]
cov = [[1.0, 0.1], [0.1, 0.5]]
[input]
kind = \"sine\"
period = 13.0
";

/// With one subsystem there is no interconnection (`v = 0`) and the lifted system is the
/// subsystem itself, so the centralized and distributed filters must agree (1e−12), in both
/// dropout modes (the known mode on measurements with every fourth one lost).
#[test]
fn centralized_equals_distributed_for_one_subsystem() {
    let model = model_from(SINGLE);
    let run = simulate_run(&model, 3);
    for known in [false, true] {
        let opts = TwoStepOptions {
            dropouts: if known {
                Dropouts::Known
            } else {
                Dropouts::Unknown
            },
            ..TwoStepOptions::default()
        };
        let mut dist = TwoStepFilter::new(&model, opts).unwrap();
        let mut cent = CentralizedFilter::new(&model, known, 100).unwrap();
        for (t, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
            let y = if known && t % 4 == 0 {
                vec![f64::NAN]
            } else {
                y.clone()
            };
            dist.step(&y, u).unwrap();
            cent.step(&y, u).unwrap();
            for (a, b) in [
                (dist.filtered(), cent.filtered()),
                (dist.predicted(), cent.predicted()),
            ] {
                for k in 0..2 {
                    assert!((a.0[k] - b.0[k]).abs() < 1e-12, "known={known} t={t}");
                }
                for k in 0..4 {
                    assert!((a.1[k] - b.1[k]).abs() < 1e-12, "known={known} t={t}");
                }
            }
        }
    }
}

pub const CHAIN: &str = "
subsystems = 4
steps = 25
[interconnection]
plus = 1
minus = 1
[model]
A = [[0.8, 0.2], [-0.1, 0.7]]
B = [[0.2, 0.1], [0.1, 0.3]]
C = [[0.1], [0.4]]
D = [[0.5, 0.1], [0.2, 0.6]]
G = [[0.3, -0.2], [0.25, 0.1]]
H = [[0.2], [-0.1]]
J = [[1.0, 0.0], [0.3, 1.0]]
R = [[0.1], [0.0]]
M = [[0.2, 0.05], [0.05, 0.3]]
Q = [[0.03, 0.0], [0.0, 0.02]]
[dropout]
p = [0.9, 0.6, 0.8, 0.7]
[initial]
mean = [1.0, -0.5]
cov = [[0.8, 0.1], [0.1, 0.6]]
[input]
kind = \"sine\"
period = 7.0
phase = 0.4
[[override]]
subsystems = [2, 3]
steps = [8, 15]
A = [[0.6, 0.3], [0.0, 0.9]]
G = [[0.1, 0.4], [-0.2, 0.2]]
";

/// Independent dense `A_eff`, `U_eff` at time `t`: unknowns `[w(1..N); v(1..N)]` of
/// (P2) `w = D x + G v + H u`, (P3) `v⁺(i) = w⁺(i−1)`, `v⁻(i) = w⁻(i+1)`, (P4) zero ends.
pub fn dense_lifted(model: &Model, t: usize) -> (DMatrix<f64>, DMatrix<f64>) {
    let dims = model.dims;
    let (n, m, s, big_n, p) = (dims.n, dims.m, dims.s(), model.subsystems, dims.plus);
    let size = 2 * big_n * s;
    let mut eq = DMatrix::zeros(size, size);
    let w = |i: usize, k: usize| i * s + k;
    let v = |i: usize, k: usize| big_n * s + i * s + k;
    for i in 0..big_n {
        let g = &model.params(t, i + 1).G;
        for k in 0..s {
            eq[(w(i, k), w(i, k))] = 1.0;
            for c in 0..s {
                eq[(w(i, k), v(i, c))] -= g[(k, c)];
            }
            let row = big_n * s + i * s + k;
            eq[(row, v(i, k))] = 1.0;
            if k < p && i > 0 {
                eq[(row, w(i - 1, k))] = -1.0;
            } else if k >= p && i + 1 < big_n {
                eq[(row, w(i + 1, k))] = -1.0;
            }
        }
    }
    let lu = eq.lu();
    // Columns: response of x(t+1) to a unit x_j(c) or u_j(c).
    let column = |x: &DVector<f64>, u: &DVector<f64>| -> DVector<f64> {
        let mut rhs = DVector::zeros(size);
        for i in 0..big_n {
            let prm = model.params(t, i + 1);
            let z = &prm.D * x.rows(i * n, n) + &prm.H * u.rows(i * m, m);
            rhs.rows_mut(i * s, s).copy_from(&z);
        }
        let sol = lu.solve(&rhs).unwrap();
        let mut out = DVector::zeros(big_n * n);
        for i in 0..big_n {
            let prm = model.params(t, i + 1);
            let vi = sol.rows(big_n * s + i * s, s);
            out.rows_mut(i * n, n)
                .copy_from(&(&prm.A * x.rows(i * n, n) + &prm.B * vi + &prm.C * u.rows(i * m, m)));
        }
        out
    };
    let a = DMatrix::from_fn(big_n * n, big_n * n, |r, c| {
        let mut e = DVector::zeros(big_n * n);
        e[c] = 1.0;
        column(&e, &DVector::zeros(big_n * m))[r]
    });
    let b = DMatrix::from_fn(big_n * n, big_n * m, |r, c| {
        let mut e = DVector::zeros(big_n * m);
        e[c] = 1.0;
        column(&DVector::zeros(big_n * n), &e)[r]
    });
    (a, b)
}

#[test]
fn lifted_matrices_equal_dense_construction() {
    let model = model_from(CHAIN);
    for t in [1, 8, 16] {
        let sys = LiftedSystem::new(&model, t).unwrap();
        let (a, b) = dense_lifted(&model, t);
        assert!((&sys.a_eff.dense - &a).amax() < 1e-13, "A_eff at t = {t}");
        assert!((&sys.u_eff - &b).amax() < 1e-13, "U_eff at t = {t}");
    }
}

/// The centralized known-dropout filter equals a textbook Kalman filter on the dense lifted
/// matrices built above, updating only on the observed elements (each lost on its own).
#[test]
fn centralized_known_equals_dense_lifted_kalman_filter() {
    let model = model_from(CHAIN);
    let run = simulate_run(&model, 9);
    let (n, big_n) = (2, 4);
    let mut cent = CentralizedFilter::new(&model, true, 100).unwrap();
    let mut x = DVector::from_fn(big_n * n, |r, _| [1.0, -0.5][r % n]);
    let mut p = DMatrix::zeros(big_n * n, big_n * n);
    for i in 0..big_n {
        p.view_mut((i * n, i * n), (n, n))
            .copy_from(&DMatrix::from_row_slice(2, 2, &[0.8, 0.1, 0.1, 0.6]));
    }
    for (t0, y) in run.y.iter().enumerate() {
        let t = t0 + 1;
        // Lose elements on their own, in a pattern that covers none, some and all.
        let y: Vec<f64> = y
            .iter()
            .enumerate()
            .map(|(k, &v)| if (k * 7 + t) % 3 == 0 { f64::NAN } else { v })
            .collect();
        cent.step(&y, &run.u[t0]).unwrap();
        dense_kalman_update(&model, t, &y, &run.u[t0], &mut x, &mut p);
        assert_filtered_equal(t, cent.filtered(), &x, &p, n);
        dense_predict(&model, t, &run.u[t0], &mut x, &mut p);
    }
}

/// A filter's `x̂(t|t)` (`N·n`) and diagonal blocks of `P(t|t)` (`N·n²`, column-major) equal
/// the dense `x` and the diagonal blocks of the dense `p` to 1e−10.
pub fn assert_filtered_equal(
    t: usize,
    (xf, pf): (&[f64], &[f64]),
    x: &DVector<f64>,
    p: &DMatrix<f64>,
    n: usize,
) {
    for k in 0..x.len() {
        assert!(
            (xf[k] - x[k]).abs() < 1e-10,
            "t={t} k={k}: {} vs {}",
            xf[k],
            x[k]
        );
    }
    for i in 0..x.len() / n {
        for c in 0..n {
            for r in 0..n {
                let got = pf[i * n * n + c * n + r];
                assert!(
                    (got - p[(i * n + r, i * n + c)]).abs() < 1e-10,
                    "t={t} block {i}"
                );
            }
        }
    }
}

/// The Kalman update of the lifted chain's `N(x, p)` at `t` on the received elements of `y`
/// (NaN: lost), independent of the library's filters (two measured elements, one input).
pub fn dense_kalman_update(
    model: &Model,
    t: usize,
    y: &[f64],
    u: &[f64],
    x: &mut DVector<f64>,
    p: &mut DMatrix<f64>,
) {
    let (n, q, size) = (model.dims.n, model.dims.q, x.len());
    let obs: Vec<usize> = (0..y.len()).filter(|&k| !y[k].is_nan()).collect();
    let hm = DMatrix::from_fn(obs.len(), size, |r, c| {
        let k = obs[r];
        if c / n == k / q {
            model.params(t, k / q + 1).J[(k % q, c % n)]
        } else {
            0.0
        }
    });
    let mm = DMatrix::from_fn(obs.len(), obs.len(), |r, c| {
        let (a, b) = (obs[r], obs[c]);
        if a / q == b / q {
            model.params(t, a / q + 1).M[(a % q, b % q)]
        } else {
            0.0
        }
    });
    let yo = DVector::from_fn(obs.len(), |r, _| {
        let k = obs[r];
        y[k] - model.params(t, k / q + 1).R[(k % q, 0)] * u[k / q]
    });
    if !obs.is_empty() {
        let s = &hm * &*p * hm.transpose() + mm;
        let gain = &*p * hm.transpose() * s.try_inverse().unwrap();
        *x = &*x + &gain * (yo - &hm * &*x);
        *p = (DMatrix::identity(size, size) - &gain * &hm) * &*p;
    }
}

/// The prediction of the lifted chain's `N(x, p)` from `t` to `t + 1` with the dense
/// `A_eff`, `U_eff` of [`dense_lifted`] and `blkdiag(Q)`.
pub fn dense_predict(
    model: &Model,
    t: usize,
    u: &[f64],
    x: &mut DVector<f64>,
    p: &mut DMatrix<f64>,
) {
    let n = model.dims.n;
    let size = x.len();
    let (a, b) = dense_lifted(model, t);
    let qbig = DMatrix::from_fn(size, size, |r, c| {
        if r / n == c / n {
            model.params(t, r / n + 1).Q[(r % n, c % n)]
        } else {
            0.0
        }
    });
    *x = &a * &*x + &b * DVector::from_column_slice(u);
    *p = &a * &*p * a.transpose() + qbig;
}

/// The `lifted` second moments `S_ii = P_ii + m_i m_iᵀ` against a Monte Carlo estimate of
/// `E[x xᵀ]` from 20000 simulated runs, at t = 5 and t = 20. Tolerance: 4 % of the largest
/// entry of each block (the Monte Carlo standard error is about 1 % of it).
#[test]
fn lifted_second_moments_match_monte_carlo() {
    let model = model_from(CHAIN);
    let (n, big_n, runs) = (2, 4, 20000);
    let checks = [5usize, 20];
    let mut mc = vec![DMatrix::<f64>::zeros(big_n * n, n); checks.len()];
    let mut u_run = Vec::new();
    for seed in 0..runs {
        let run = simulate_run(&model, 500 + seed);
        for (c, &t) in checks.iter().enumerate() {
            for i in 0..big_n {
                let xi = DVector::from_column_slice(&run.x[t - 1][i * n..(i + 1) * n]);
                let mut block = mc[c].rows_mut(i * n, n);
                block += &xi * xi.transpose();
            }
        }
        u_run = run.u;
    }
    let mut moments = LiftedMoments::initial(&model);
    let mut sys = LiftedSystem::new(&model, 1).unwrap();
    let mut s_ii = DMatrix::zeros(n, n);
    for t in 1..=20 {
        if let Some(c) = checks.iter().position(|&k| k == t) {
            for i in 0..big_n {
                moments.second_moment(i, n, s_ii.as_mut_slice());
                let est = mc[c].rows(i * n, n) / runs as f64;
                let tol = 0.04 * s_ii.amax();
                assert!(
                    (&est - &s_ii).amax() < tol,
                    "t={t} i={i}: MC {est} vs lifted {s_ii}"
                );
            }
        }
        sys.prepare(&model, t).unwrap();
        moments.propagate(&model, &sys, &u_run[t - 1]);
    }
}

/// On the platoon (100 runs), the distributed filter's RMSE is within 2 % of the optimal
/// centralized filter (measured 1.010) and the naive filter that ignores dropouts is clearly
/// worse (measured 1.23).
#[test]
fn distributed_is_near_optimal_and_naive_is_worse_on_platoon() {
    let model = shipped_model("platoon.toml");
    let opts = EvaluateOptions {
        filters: vec![
            Compared::Distributed,
            Compared::Centralized,
            Compared::CentralizedKnown,
            Compared::Naive,
        ],
        ..EvaluateOptions::new(100, 1)
    };
    let ev = evaluate(
        &model,
        &RunInputs::generated(&model).unwrap(),
        "platoon",
        opts,
        || Ok(()),
    )
    .unwrap();
    let ratio = |name: &str| {
        ev.filters
            .iter()
            .find(|f| f.name.name() == name)
            .unwrap()
            .rmse_ratio
            .unwrap()
    };
    assert!(
        ratio("distributed") < 1.02,
        "distributed / centralized = {}",
        ratio("distributed")
    );
    assert!(ratio("distributed") >= 0.999);
    assert!(
        ratio("naive") > 1.1,
        "naive / centralized = {}",
        ratio("naive")
    );
    assert!(ratio("centralized-known") < 1.0);
}

/// A Monte Carlo of the centralized Nahi filter and the two mixture filters on a shipped
/// config shortened to `steps`, simulated with `true_p` when given.
fn mixture_against_nahi(name: &str, steps: usize, runs: usize, true_p: Option<f64>) -> Evaluation {
    let mut model = shipped_model(name);
    model.steps = Some(steps);
    let opts = EvaluateOptions {
        filters: vec![
            Compared::Centralized,
            Compared::JointMixture,
            Compared::CentralizedMixture,
        ],
        true_p,
        ..EvaluateOptions::new(runs, 1)
    };
    evaluate(
        &model,
        &RunInputs::generated(&model).unwrap(),
        name,
        opts,
        || Ok(()),
    )
    .unwrap()
}

/// The mixture update (docs/theory.md §10) beats the optimal linear filter: on the platoon
/// (`T = 100`, 100 runs) and the heat rod (`T = 150`, 20 runs), the RMSE of the centralized
/// and the joint mixture filters is at most 0.82 of the centralized Nahi filter's on the same
/// realisations, with an ANEES in [0.94, 1.06]. Measured: 0.79 on both chains (the filter
/// told the dropouts: 0.77 and 0.79), ANEES 1.00. Over the long shipped runs the gain is
/// smaller (0.83), the transient from the initial covariance weighing less.
#[test]
fn mixture_update_beats_the_optimal_linear_filter() {
    for (name, steps, runs) in [("platoon.toml", 100, 100), ("heat_rod.toml", 150, 20)] {
        let ev = mixture_against_nahi(name, steps, runs, None);
        for f in ev
            .filters
            .iter()
            .filter(|f| f.name != Compared::Centralized)
        {
            let ratio = f.rmse_ratio.unwrap();
            let anees = f.accuracy.as_ref().unwrap().anees.unwrap();
            assert!(
                ratio <= 0.82,
                "{name} {}: RMSE / centralized {ratio}",
                f.name
            );
            assert!(
                (0.94..=1.06).contains(&anees),
                "{name} {}: ANEES {anees}",
                f.name
            );
            // π tells most lost readings from received ones.
            let d = f.detection.unwrap();
            assert!(
                d.detected_percent() > 50.0 && d.false_alarm_percent() < 5.0,
                "{d:?}"
            );
        }
    }
}

/// With a wrong `p` the data still decide: the platoon's config says `p = 0.85`, the
/// realisations are simulated with `p = 0.6` (100 runs, `T = 100`), and the mixture filters'
/// RMSE is at most 0.6 of the Nahi filter's, whose ANEES is far off. Measured: 0.579, Nahi's
/// ANEES 3.9 against the mixture's 1.21.
#[test]
fn mixture_update_survives_a_wrong_arrival_probability() {
    let ev = mixture_against_nahi("platoon.toml", 100, 100, Some(0.6));
    let nahi = ev.filters.iter().find(|f| f.name == Compared::Centralized);
    assert!(nahi.unwrap().accuracy.as_ref().unwrap().anees.unwrap() > 2.0);
    for f in ev
        .filters
        .iter()
        .filter(|f| f.name != Compared::Centralized)
    {
        let ratio = f.rmse_ratio.unwrap();
        assert!(ratio <= 0.6, "{}: RMSE / centralized {ratio}", f.name);
    }
}

/// Without coupling (`B = 0`) the lifted moments are the local ones, so `--second-moment
/// lifted` and `local` must give the same estimates (1e−12). (With coupling they differ: on
/// this chain `lifted` had a 3 % larger RMSE than `local`, both being heuristics of the
/// two-step filter, which treats `v̂` as exact.)
#[test]
fn lifted_equals_local_second_moment_without_coupling() {
    let model = model_from(&CHAIN.replace(
        "B = [[0.2, 0.1], [0.1, 0.3]]",
        "B = [[0.0, 0.0], [0.0, 0.0]]",
    ));
    let run = simulate_run(&model, 4);
    let mut filters: Vec<TwoStepFilter> = [SecondMoment::Local, SecondMoment::Lifted]
        .into_iter()
        .map(|second_moment| {
            TwoStepFilter::new(
                &model,
                TwoStepOptions {
                    second_moment,
                    ..Default::default()
                },
            )
            .unwrap()
        })
        .collect();
    for t in 0..run.y.len() {
        for f in filters.iter_mut() {
            f.step(&run.y[t], &run.u[t]).unwrap();
        }
        let (a, b) = (filters[0].filtered(), filters[1].filtered());
        for k in 0..a.0.len() {
            assert!(
                (a.0[k] - b.0[k]).abs() < 1e-12,
                "t={t} k={k}: {} vs {}",
                a.0[k],
                b.0[k]
            );
        }
        for k in 0..a.1.len() {
            assert!((a.1[k] - b.1[k]).abs() < 1e-12, "t={t}");
        }
    }
}

/// The distributed filter with the mixture update (docs/theory.md §10) and `options`.
fn mixture_filter(model: &Model) -> TwoStepFilter {
    let opts = TwoStepOptions {
        update: Update::Mixture,
        ..TwoStepOptions::default()
    };
    TwoStepFilter::new(model, opts).unwrap()
}

/// `log N(v; 0, S)` with an explicit inverse and determinant.
fn log_gauss(v: &DVector<f64>, s: &DMatrix<f64>) -> f64 {
    let inv = s.clone().try_inverse().unwrap();
    -0.5 * (v.len() as f64 * (2.0 * std::f64::consts::PI).ln()
        + s.determinant().ln()
        + v.dot(&(inv * v)))
}

/// For one subsystem (no interconnection, `v = 0`) the distributed mixture filter is a
/// textbook filter with the mixture update, written here with dense inverses: per step `π`,
/// the log density, `x̂(t|t)`, `P(t|t)`, `x̂(t+1|t)` and `T(t+1)` agree to 1e−10, with the
/// dynamic and with the fixed-size kernel.
#[test]
fn distributed_mixture_filter_for_one_subsystem_equals_a_dense_mixture_filter() {
    let model = model_from(SINGLE);
    let run = simulate_run(&model, 11);
    let prm = model.param_set(0);
    let (a, c, j, r, m, q) = (&prm.A, &prm.C, &prm.J, &prm.R, &prm.M, &prm.Q);
    let p = 0.6;
    let mut x = model.initial.of(0).mean.clone();
    let mut t_cov = model.initial.of(0).cov.clone();
    let mut dynamic = mixture_filter(&model);
    let mut fixed = two_step(
        &model,
        TwoStepOptions {
            update: Update::Mixture,
            ..TwoStepOptions::default()
        },
    )
    .unwrap();
    let mut undecided = 0;
    for (step, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
        let u_vec = DVector::from_column_slice(u);
        let e0 = DVector::from_column_slice(y) - r * &u_vec;
        let e = &e0 - j * &x;
        let s1 = j * &t_cov * j.transpose() + m;
        let (w1, w0) = (
            p * log_gauss(&e, &s1).exp(),
            (1.0 - p) * log_gauss(&e0, m).exp(),
        );
        let pi = w1 / (w1 + w0);
        let log_density = (w1 + w0).ln();
        undecided += usize::from((0.05..0.95).contains(&pi));
        let k = &t_cov * j.transpose() * s1.clone().try_inverse().unwrap();
        let g = &k * &e;
        let x_filt = &x + &g * pi;
        let p_filt =
            &t_cov - &k * &s1 * k.transpose() * pi + &g * g.transpose() * (pi * (1.0 - pi));
        x = a * &x_filt + c * &u_vec;
        t_cov = a * &p_filt * a.transpose() + q;

        for filter in [&mut dynamic as &mut dyn ChainFilter, fixed.as_mut()] {
            filter.step(y, u).unwrap();
            let arrival = filter.arrival().expect("the mixture update reports π");
            assert!((arrival[0] - pi).abs() < 1e-10, "t = {}: π", step + 1);
            let got = filter
                .log_likelihood()
                .expect("the mixture update has a density");
            assert!(
                (got - log_density).abs() < 1e-10 * log_density.abs().max(1.0),
                "t = {}: log density {got} vs {log_density}",
                step + 1
            );
            let close = |got: &[f64], want: &[f64], what: &str| {
                for (g, w) in got.iter().zip(want) {
                    assert!(
                        (g - w).abs() < 1e-10,
                        "t = {}: {what} {got:?} vs {want:?}",
                        step + 1
                    );
                }
            };
            close(filter.filtered().0, x_filt.as_slice(), "x̂(t|t)");
            close(filter.filtered().1, p_filt.as_slice(), "P(t|t)");
            close(filter.predicted().0, x.as_slice(), "x̂(t+1|t)");
            close(filter.predicted().1, t_cov.as_slice(), "T(t+1)");
        }
    }
    assert!(undecided > 0, "no step left the hypotheses undecided");
}

/// With `p = 1` every measurement arrives and the mixture update is the Kalman update, so the
/// mixture filter equals the linear one (whose Nahi update is Kalman's at `p = 1`); with
/// `p = 0` neither updates, and `x̂(t|t) = x̂(t|t−1)`.
#[test]
fn mixture_filter_at_p_one_is_the_linear_filter_and_at_p_zero_the_open_loop_prediction() {
    let chain = model_from(CHAIN);
    for p in [1.0, 0.0] {
        let model = chain.with_arrival_probability(p);
        let run = simulate_run(&model, 5);
        let mut mixture = mixture_filter(&model);
        let mut linear = TwoStepFilter::new(&model, TwoStepOptions::default()).unwrap();
        for (t, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
            let x_before = mixture.predicted().0.to_vec();
            mixture.step(y, u).unwrap();
            linear.step(y, u).unwrap();
            assert!(mixture.arrival().unwrap().iter().all(|&a| a == p));
            for (a, b) in [
                (mixture.filtered(), linear.filtered()),
                (mixture.predicted(), linear.predicted()),
            ] {
                for (x, y) in a.0.iter().zip(b.0).chain(a.1.iter().zip(b.1)) {
                    assert!((x - y).abs() < 1e-10, "p = {p}, t = {}", t + 1);
                }
            }
            if p == 0.0 {
                assert_eq!(mixture.filtered().0, x_before.as_slice());
            }
        }
    }
}

/// One fixed-seed run of each shipped chain with `Q > 0`: the mixture update, told nothing
/// more than the linear one, has the lower RMSE against the truth (docs/theory.md §10).
#[test]
fn mixture_filter_beats_the_linear_filter_on_the_shipped_chains() {
    for name in ["platoon.toml", "heat_rod.toml"] {
        let model = shipped_model(name);
        let run = simulate_run(&model, 21);
        let rmse = |filter: &mut dyn ChainFilter| {
            let mut sum = 0.0;
            for ((y, u), x) in run.y.iter().zip(&run.u).zip(&run.x) {
                filter.step(y, u).unwrap();
                sum += x
                    .iter()
                    .zip(filter.filtered().0)
                    .map(|(a, b)| (a - b).powi(2))
                    .sum::<f64>();
            }
            (sum / (run.x.len() * run.x[0].len()) as f64).sqrt()
        };
        let mut linear = TwoStepFilter::new(&model, TwoStepOptions::default()).unwrap();
        let (mixture, linear) = (rmse(&mut mixture_filter(&model)), rmse(&mut linear));
        eprintln!(
            "{name}: distributed RMSE mixture {mixture:.4e}, linear {linear:.4e}, ratio {:.3}",
            mixture / linear
        );
        assert!(
            mixture < linear,
            "{name}: mixture {mixture} vs linear {linear}"
        );

        let joint = |update| {
            let opts = JointOptions {
                update,
                ..JointOptions::default()
            };
            JointFilter::new(&model, opts).unwrap()
        };
        let mixture = rmse(&mut joint(Update::Mixture));
        let linear = rmse(&mut joint(Update::Linear));
        eprintln!(
            "{name}: joint RMSE mixture {mixture:.4e}, linear {linear:.4e}, ratio {:.3}",
            mixture / linear
        );
        assert!(
            mixture < linear,
            "{name}: mixture {mixture} vs linear {linear}"
        );

        let central = || CentralizedFilter::new(&model, false, 1000).unwrap();
        let mixture = rmse(&mut central().with_mixture_update().unwrap());
        let linear = rmse(&mut central());
        eprintln!(
            "{name}: centralized RMSE mixture {mixture:.4e}, linear {linear:.4e}, ratio {:.3}",
            mixture / linear
        );
        assert!(
            mixture < linear,
            "{name}: mixture {mixture} vs linear {linear}"
        );
    }
}

/// The centralized mixture filter: for one subsystem it is the distributed one (no
/// interconnection), and at `p = 1` on a chain it is the centralized Kalman filter, i.e. the
/// linear filter at `p = 1` (1e−10).
#[test]
fn centralized_mixture_filter_for_one_subsystem_and_at_p_one() {
    let single = model_from(SINGLE);
    let chain = model_from(CHAIN).with_arrival_probability(1.0);
    for (model, seed) in [(&single, 4), (&chain, 6)] {
        let run = simulate_run(model, seed);
        let mut central = CentralizedFilter::new(model, false, 100)
            .unwrap()
            .with_mixture_update()
            .unwrap();
        let mut other: Box<dyn ChainFilter> = if model.subsystems == 1 {
            Box::new(mixture_filter(model))
        } else {
            Box::new(CentralizedFilter::new(model, false, 100).unwrap())
        };
        for (t, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
            central.step(y, u).unwrap();
            other.step(y, u).unwrap();
            let (a, b) = (central.arrival().unwrap(), other.arrival());
            if let Some(b) = b {
                assert!((a[0] - b[0]).abs() < 1e-10, "t = {}: π", t + 1);
                let (l, m) = (central.log_likelihood(), other.log_likelihood());
                let (l, m) = (l.unwrap(), m.unwrap());
                assert!((l - m).abs() < 1e-10 * m.abs().max(1.0), "t = {}", t + 1);
            }
            for (x, z) in [
                (central.filtered(), other.filtered()),
                (central.predicted(), other.predicted()),
            ] {
                for (g, w) in x.0.iter().zip(z.0).chain(x.1.iter().zip(z.1)) {
                    assert!(
                        (g - w).abs() < 1e-10,
                        "N = {}, t = {}",
                        model.subsystems,
                        t + 1
                    );
                }
            }
        }
    }
    assert!(
        CentralizedFilter::new(&single, true, 100)
            .unwrap()
            .with_mixture_update()
            .is_err()
    );
}

/// One subsystem with two measurement rows, every measurement arriving (`p = 1`).
fn single_two_rows() -> Model {
    model_from(
        &SINGLE
            .replace("J = [[1.0, 0.3]]", "J = [[1.0, 0.3], [0.0, 1.0]]")
            .replace("R = [[0.2]]", "R = [[0.2], [0.0]]")
            .replace("M = [[0.3]]", "M = [[0.3, 0.05], [0.05, 0.2]]")
            .replace("p = 0.6", "p = 1.0"),
    )
}

/// Loses measurement elements on their own, in a pattern that covers none, some and all of
/// a step's.
pub fn lose_some(y: &[f64], t: usize) -> Vec<f64> {
    y.iter()
        .enumerate()
        .map(|(k, &v)| {
            if (k * 7 + t).is_multiple_of(3) {
                f64::NAN
            } else {
                v
            }
        })
        .collect()
}

/// The log-likelihood of the known-dropout filters for `N = 1`, `p = 1`, with some elements
/// lost, is the textbook Kalman filter's innovations log-likelihood `Σ_t log N(ỹ_t; 0, S_t)`
/// over the received elements (written here with dense inverses), step by step, for each of
/// the three filters.
#[test]
fn known_dropout_log_likelihood_is_the_kalman_filters_for_one_subsystem() {
    let model = single_two_rows();
    let run = simulate_run(&model, 3);
    let prm = model.param_set(0);
    let (a, c, j, r, m, q) = (&prm.A, &prm.C, &prm.J, &prm.R, &prm.M, &prm.Q);
    let known_two_step = TwoStepOptions {
        dropouts: Dropouts::Known,
        ..TwoStepOptions::default()
    };
    let mut filters: Vec<(&str, Box<dyn ChainFilter>)> = vec![
        (
            "distributed",
            Box::new(TwoStepFilter::new(&model, known_two_step).unwrap()),
        ),
        (
            "distributed, fixed-size kernel",
            two_step(&model, known_two_step).unwrap(),
        ),
        (
            "centralized",
            Box::new(CentralizedFilter::new(&model, true, 100).unwrap()),
        ),
        (
            "joint",
            Box::new(
                JointFilter::new(
                    &model,
                    JointOptions {
                        dropouts: Dropouts::Known,
                        ..JointOptions::default()
                    },
                )
                .unwrap(),
            ),
        ),
    ];
    let mut x = model.initial.of(0).mean.clone();
    let mut p = model.initial.of(0).cov.clone();
    let (mut total, mut totals) = (0.0, vec![0.0; filters.len()]);
    let mut partial = 0;
    for (t0, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
        let t = t0 + 1;
        let y = lose_some(y, t);
        let u_vec = DVector::from_column_slice(u);
        let obs: Vec<usize> = (0..2).filter(|&k| !y[k].is_nan()).collect();
        partial += usize::from(obs.len() == 1);
        let mut step_density = 0.0;
        if !obs.is_empty() {
            let h = j.select_rows(&obs);
            let e = DVector::from_iterator(obs.len(), obs.iter().map(|&k| y[k] - (r * &u_vec)[k]))
                - &h * &x;
            let s = &h * &p * h.transpose() + m.select_rows(&obs).select_columns(&obs);
            step_density = log_gauss(&e, &s);
            let gain = &p * h.transpose() * s.try_inverse().unwrap();
            x = &x + &gain * e;
            p = (DMatrix::identity(2, 2) - &gain * &h) * &p;
        }
        total += step_density;
        x = a * &x + c * &u_vec;
        p = a * &p * a.transpose() + q;
        for ((name, filter), sum) in filters.iter_mut().zip(&mut totals) {
            filter.step(&y, u).unwrap();
            let got = filter
                .log_likelihood()
                .expect("known dropouts have a density");
            assert!(
                (got - step_density).abs() < 1e-10 * step_density.abs().max(1.0),
                "{name}, t = {t}: {got} vs {step_density}"
            );
            *sum += got;
        }
    }
    assert!(partial > 0, "no step lost one element of two");
    for ((name, _), sum) in filters.iter().zip(&totals) {
        assert!(
            (sum - total).abs() < 1e-9 * total.abs(),
            "{name}: {sum} vs {total}"
        );
    }
}

/// The log density of all the measurements received (`NaN`: not received), a Gaussian built
/// here from the dense lifted matrices: the stacked states `X_1..X_T` have mean
/// `μ_{t+1} = A_t μ_t + U_t u_t` and covariances `Cov(X_{t+1}, X_s) = A_t Cov(X_t, X_s)`,
/// `Var(X_{t+1}) = A_t Var(X_t) A_tᵀ + Q`, and the received elements are `J x + R u + d`.
pub fn dense_log_density(model: &Model, ys: &[Vec<f64>], us: &[Vec<f64>]) -> f64 {
    let (n, q, m, big_n) = (model.dims.n, model.dims.q, model.dims.m, model.subsystems);
    let (size, steps) = (big_n * n, ys.len());
    let mut mean = DVector::zeros(steps * size);
    let mut cov = DMatrix::zeros(steps * size, steps * size);
    for i in 0..big_n {
        mean.rows_mut(i * n, n).copy_from(&model.initial.of(i).mean);
        cov.view_mut((i * n, i * n), (n, n))
            .copy_from(&model.initial.of(i).cov);
    }
    for t0 in 0..steps - 1 {
        let (a, b) = dense_lifted(model, t0 + 1);
        let (now, next) = (t0 * size, (t0 + 1) * size);
        let m_next = &a * mean.rows(now, size) + &b * DVector::from_column_slice(&us[t0]);
        mean.rows_mut(next, size).copy_from(&m_next);
        for s in 0..=t0 {
            let c = &a * cov.view((now, s * size), (size, size));
            cov.view_mut((next, s * size), (size, size)).copy_from(&c);
            cov.view_mut((s * size, next), (size, size))
                .copy_from(&c.transpose());
        }
        let mut v = &a * cov.view((now, now), (size, size)) * a.transpose();
        for i in 0..big_n {
            let qi = &model.params(t0 + 1, i + 1).Q;
            let mut block = v.view_mut((i * n, i * n), (n, n));
            block += qi;
        }
        v = (&v + v.transpose()) * 0.5;
        cov.view_mut((next, next), (size, size)).copy_from(&v);
    }
    // The received elements: (t, k) with k = i·q + row.
    let received: Vec<(usize, usize, f64)> = ys
        .iter()
        .enumerate()
        .flat_map(|(t0, y)| {
            (0..big_n * q)
                .filter(|&k| !y[k].is_nan())
                .map(move |k| (t0, k, y[k]))
        })
        .collect();
    let obs = received.len();
    let mut h = DMatrix::zeros(obs, steps * size);
    let mut noise = DMatrix::zeros(obs, obs);
    let mut e = DVector::zeros(obs);
    for (row, &(t0, k, y)) in received.iter().enumerate() {
        let (i, kk) = (k / q, k % q);
        let prm = model.params(t0 + 1, i + 1);
        for c in 0..n {
            h[(row, t0 * size + i * n + c)] = prm.J[(kk, c)];
        }
        let u_i = DVector::from_column_slice(&us[t0][i * m..(i + 1) * m]);
        e[row] = y - (&prm.R * u_i)[kk];
        for (col, &(t1, k1, _)) in received.iter().enumerate() {
            if t1 == t0 && k1 / q == i {
                noise[(row, col)] = prm.M[(kk, k1 % q)];
            }
        }
    }
    let e = e - &h * &mean;
    let s = &h * &cov * h.transpose() + noise;
    let l = s
        .cholesky()
        .expect("the measurements' covariance is positive definite");
    let log_det: f64 = (0..obs).map(|k| 2.0 * l.l()[(k, k)].ln()).sum();
    let white = l.l().solve_lower_triangular(&e).unwrap();
    -0.5 * (obs as f64 * (2.0 * std::f64::consts::PI).ln() + log_det + white.norm_squared())
}

/// The centralized known-dropout filter's log-likelihood is the log density of all received
/// measurements at once ([`dense_log_density`]).
#[test]
fn centralized_known_log_likelihood_is_the_dense_density_of_all_measurements() {
    assert_centralized_known_log_likelihood_is_dense(&model_from(CHAIN));
}

/// The centralized known-dropout filter's log-likelihood on a run of `model` with
/// [`lose_some`]'s losses, against [`dense_log_density`] (relative 1e-9).
pub fn assert_centralized_known_log_likelihood_is_dense(model: &Model) {
    let run = simulate_run(model, 5);
    let mut filter = CentralizedFilter::new(model, true, 100).unwrap();
    let mut loglik = 0.0;
    let mut ys = Vec::new();
    for (t0, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
        let y = lose_some(y, t0 + 1);
        filter.step(&y, u).unwrap();
        loglik += filter.log_likelihood().unwrap();
        ys.push(y);
    }
    let dense = dense_log_density(model, &ys, &run.u);
    assert!(
        (loglik - dense).abs() < 1e-9 * dense.abs(),
        "filter {loglik} vs dense {dense}"
    );
}

/// The ANEES band of `evaluate` (docs/theory.md §11) holds its stated coverage for the exact
/// centralized filter: over 60 evaluations of 12 runs each (disjoint seeds) on the
/// four-subsystem chain, the band `1 ± t s/√R` from the spread of the runs' own ANEES
/// contains 1 in at least 51 (85 %; 57 expected at 95 %, and fewer than 51 has a probability
/// below 10⁻³ for a band of true 95 % coverage). The band of terms taken as independent,
/// which one run gives, is narrower than the runs' band every time (so it would not hold).
#[test]
fn the_anees_band_of_evaluate_holds_its_coverage() {
    let mut model = model_from(CHAIN);
    model.steps = Some(25);
    let inputs = RunInputs::generated(&model).unwrap();
    let (evaluations, runs) = (60, 12);
    let mut covered = 0;
    for e in 0..evaluations {
        let opts = EvaluateOptions {
            filters: vec![Compared::Centralized],
            ..EvaluateOptions::new(runs, 1 + (e * runs) as u64)
        };
        let result = evaluate(&model, &inputs, "chain", opts, || Ok(())).unwrap();
        let acc = result.filters[0].accuracy.as_ref().unwrap();
        assert_eq!(acc.anees_band_basis, sisfilt::innovations::BandBasis::Runs);
        let [low, high] = acc.anees_band;
        assert!(low < 1.0 && 1.0 < high && (1.0 - low - (high - 1.0)).abs() < 1e-12);
        let anees = acc.anees.unwrap();
        if low <= anees && anees <= high {
            covered += 1;
        }
        let terms = sisfilt::accuracy::chi2_mean_band(acc.nees_terms * 2);
        assert!(
            terms[1] - terms[0] < high - low,
            "{terms:?} against {:?}",
            acc.anees_band
        );
    }
    assert!(covered >= 51, "the band held in {covered} of {evaluations}");
}
