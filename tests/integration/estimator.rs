//! Numerical tests of the two-step filter against independent references: uncoupled chains
//! against single-subsystem runs, the known-dropout mode against a textbook Kalman filter
//! written here, and Monte Carlo checks of the reported covariance.

use crate::common::{model_from, shipped_model, simulate_run};
use nalgebra::{DMatrix, DVector};
use sisfilt::filter::{
    ChainFilter, Dropouts, InterconnectFrom, SecondMoment, TwoStepFilter, TwoStepOptions, Update,
};
use sisfilt::model::Model;

/// Filtered estimates and covariances of every step.
fn filter_run(
    model: &Model,
    opts: TwoStepOptions,
    y: &[Vec<f64>],
    u: &[Vec<f64>],
) -> Vec<(Vec<f64>, Vec<f64>)> {
    let mut f = TwoStepFilter::new(model, opts).unwrap();
    y.iter()
        .zip(u)
        .map(|(yt, ut)| {
            f.step(yt, ut).unwrap();
            let (x, p) = f.filtered();
            (x.to_vec(), p.to_vec())
        })
        .collect()
}

const UNCOUPLED: &str = "
subsystems = 4
steps = 60
[interconnection]
plus = 1
minus = 1
[model]
A = [[0.9, 0.2], [-0.1, 0.8]]
B = BMAT
C = [[0.0], [0.5]]
D = DMAT
G = [[0.2, 0.1], [0.1, 0.2]]
J = [[1.0, 0.3]]
R = [[0.2]]
M = [[0.3]]
Q = [[0.02, 0.0], [0.0, 0.01]]
[dropout]
p = [0.9, 0.5, 0.7, 1.0]
[initial]
mean = [0.5, -0.5]
cov = [[1.0, 0.1], [0.1, 0.5]]
[input]
kind = \"sine\"
period = 13.0
phase = 0.7
";

/// With `B = 0` or `D = 0` no signal crosses the chain, so each subsystem's estimates must
/// equal those of a one-subsystem model run on its own data.
#[test]
fn uncoupled_chain_equals_single_subsystem_filters() {
    for (b, d) in [
        ("[[0.0, 0.0], [0.0, 0.0]]", "[[1.0, 0.0], [0.0, 1.0]]"),
        ("[[0.3, 0.1], [0.0, 0.2]]", "[[0.0, 0.0], [0.0, 0.0]]"),
    ] {
        let text = UNCOUPLED.replace("BMAT", b).replace("DMAT", d);
        let chain = model_from(&text);
        let run = simulate_run(&chain, 11);
        for second_moment in [SecondMoment::Local, SecondMoment::Paper] {
            let opts = TwoStepOptions {
                second_moment,
                ..TwoStepOptions::default()
            };
            let est = filter_run(&chain, opts, &run.y, &run.u);
            for i in 0..4 {
                let p_i = [0.9, 0.5, 0.7, 1.0][i];
                let single = model_from(
                    &text
                        .replace("subsystems = 4", "subsystems = 1")
                        .replace("p = [0.9, 0.5, 0.7, 1.0]", &format!("p = {p_i}")),
                );
                let y: Vec<Vec<f64>> = run.y.iter().map(|y| vec![y[i]]).collect();
                let u: Vec<Vec<f64>> = run.u.iter().map(|u| vec![u[i]]).collect();
                let alone = filter_run(&single, opts, &y, &u);
                for (t, ((xc, pc), (xs, ps))) in est.iter().zip(&alone).enumerate() {
                    for k in 0..2 {
                        assert!((xc[2 * i + k] - xs[k]).abs() < 1e-12, "t={t} i={i}");
                    }
                    for k in 0..4 {
                        assert!((pc[4 * i + k] - ps[k]).abs() < 1e-12, "t={t} i={i}");
                    }
                }
            }
        }
    }
}

/// `N = 1`, known dropouts with elements lost on their own: the output equals a textbook
/// Kalman filter (predict; update on the observed rows; no update when nothing is observed).
#[test]
fn single_subsystem_known_dropouts_equal_textbook_kalman_filter() {
    let model = model_from(
        "subsystems = 1\nsteps = 80\n[interconnection]\nplus = 0\nminus = 0\n[model]\n\
         A = [[0.95, 0.1], [-0.2, 0.9]]\nB = [[], []]\nC = [[1.0], [0.0]]\nD = []\nG = []\n\
         J = [[1.0, 0.0], [0.5, 1.0]]\nR = [[0.1], [0.0]]\nM = [[0.2, 0.05], [0.05, 0.4]]\n\
         Q = [[0.05, 0.0], [0.0, 0.02]]\n[dropout]\np = 0.123\n[initial]\nmean = [1.0, 2.0]\n\
         cov = [[2.0, 0.3], [0.3, 1.0]]\n[input]\nkind = \"sine\"\nperiod = 9.0\n",
    );
    let run = simulate_run(&model, 5);
    // Lose elements on their own: row 1 every 3rd step, row 2 every 4th (both at t ≡ 0 mod 12).
    let y: Vec<Vec<f64>> = run
        .y
        .iter()
        .enumerate()
        .map(|(t, y)| {
            vec![
                if t % 3 == 0 { f64::NAN } else { y[0] },
                if t % 4 == 0 { f64::NAN } else { y[1] },
            ]
        })
        .collect();
    let opts = TwoStepOptions {
        dropouts: Dropouts::Known,
        ..TwoStepOptions::default()
    };
    let est = filter_run(&model, opts, &y, &run.u);

    let a = DMatrix::from_row_slice(2, 2, &[0.95, 0.1, -0.2, 0.9]);
    let c = DVector::from_column_slice(&[1.0, 0.0]);
    let j = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.5, 1.0]);
    let r = DVector::from_column_slice(&[0.1, 0.0]);
    let m = DMatrix::from_row_slice(2, 2, &[0.2, 0.05, 0.05, 0.4]);
    let q = DMatrix::from_row_slice(2, 2, &[0.05, 0.0, 0.0, 0.02]);
    let mut x = DVector::from_column_slice(&[1.0, 2.0]);
    let mut p = DMatrix::from_row_slice(2, 2, &[2.0, 0.3, 0.3, 1.0]);
    for (t, yt) in y.iter().enumerate() {
        let u = run.u[t][0];
        let obs: Vec<usize> = (0..2).filter(|&k| !yt[k].is_nan()).collect();
        if !obs.is_empty() {
            let jo = DMatrix::from_fn(obs.len(), 2, |a_, b_| j[(obs[a_], b_)]);
            let mo = DMatrix::from_fn(obs.len(), obs.len(), |a_, b_| m[(obs[a_], obs[b_])]);
            let yo = DVector::from_fn(obs.len(), |a_, _| yt[obs[a_]] - r[obs[a_]] * u);
            let s = &jo * &p * jo.transpose() + mo;
            let k = &p * jo.transpose() * s.try_inverse().unwrap();
            x = &x + &k * (yo - &jo * &x);
            p = (DMatrix::identity(2, 2) - &k * &jo) * &p;
        }
        let (xf, pf) = &est[t];
        for k in 0..2 {
            assert!(
                (xf[k] - x[k]).abs() < 1e-10 * (1.0 + x[k].abs()),
                "t={t}: {xf:?} vs {x}"
            );
        }
        for k in 0..4 {
            assert!(
                (pf[k] - p.as_slice()[k]).abs() < 1e-10,
                "t={t}: {pf:?} vs {p}"
            );
        }
        x = &a * &x + &c * u;
        p = &a * &p * a.transpose() + &q;
    }
}

/// Errors `x − x̂(t|t)` and reported covariances over Monte Carlo runs, after a burn-in.
struct MonteCarlo {
    empirical: DMatrix<f64>,
    reported: DMatrix<f64>,
    mse: f64,
    terms: usize,
}

fn monte_carlo(model: &Model, opts: TwoStepOptions, runs: u64, burn_in: usize) -> MonteCarlo {
    let n = model.dims.n;
    let mut mc = MonteCarlo {
        empirical: DMatrix::zeros(n, n),
        reported: DMatrix::zeros(n, n),
        mse: 0.0,
        terms: 0,
    };
    for seed in 0..runs {
        let run = simulate_run(model, 1000 + seed);
        let est = filter_run(model, opts, &run.y, &run.u);
        for (t, (x_hat, p)) in est.iter().enumerate().skip(burn_in) {
            for i in 0..model.subsystems {
                let e = DVector::from_fn(n, |k, _| run.x[t][i * n + k] - x_hat[i * n + k]);
                mc.empirical += &e * e.transpose();
                mc.reported += DMatrix::from_column_slice(n, n, &p[i * n * n..(i + 1) * n * n]);
                mc.mse += e.norm_squared();
                mc.terms += 1;
            }
        }
    }
    mc.empirical /= mc.terms as f64;
    mc.reported /= mc.terms as f64;
    mc.mse /= mc.terms as f64;
    mc
}

fn covariance_ratios(text: &str) -> [f64; 2] {
    let mc = monte_carlo(&model_from(text), TwoStepOptions::default(), 200, 20);
    [0, 1].map(|k| mc.empirical[(k, k)] / mc.reported[(k, k)])
}

fn platoon_text() -> String {
    let path = crate::common::shipped_config("platoon.toml");
    std::fs::read_to_string(path).unwrap()
}

/// The platoon with its coupling cut (`B = 0`): each car's Nahi filter is then the exact
/// linear MMSE filter, so its reported `P` must match the empirical error covariance over
/// 200 runs × 20 cars × 180 steps within 5 % (the Monte Carlo spread is about 1 %).
#[test]
fn reported_covariance_matches_monte_carlo_when_uncoupled() {
    let text = platoon_text().replace(
        "B = [[0.1, 0.0], [0.0, -0.03]]",
        "B = [[0.0, 0.0], [0.0, 0.0]]",
    );
    for (k, ratio) in covariance_ratios(&text).iter().enumerate() {
        assert!(
            (0.95..1.05).contains(ratio),
            "x{}: empirical / reported = {ratio}",
            k + 1
        );
    }
}

/// On the shipped platoon the two-step filter treats the estimated speed of the car ahead
/// as exact (docs/theory.md §4), so its reported gap variance is too small by the variance that error
/// feeds into the gap (measured: empirical / reported = 1.27 for the gap, 1.03 for the speed).
/// The stated tolerance: no entry underestimated by more than 35 %, none overestimated by
/// more than 5 %.
#[test]
fn reported_covariance_on_coupled_platoon_is_close() {
    for (k, ratio) in covariance_ratios(&platoon_text()).iter().enumerate() {
        assert!(
            (0.95..1.35).contains(ratio),
            "x{}: empirical / reported = {ratio}",
            k + 1
        );
    }
}

/// docs/theory.md §4: the paper's `S⁺ = A S Aᵀ` ignores inputs and coupling; on the heat rod (strong
/// sine input) it makes the reported covariance too small and the RMSE worse than `local`.
#[test]
fn paper_second_moment_is_worse_with_inputs() {
    let model = shipped_model("heat_rod.toml");
    let local = monte_carlo(&model, TwoStepOptions::default(), 20, 20);
    let paper_opts = TwoStepOptions {
        second_moment: SecondMoment::Paper,
        ..TwoStepOptions::default()
    };
    let paper = monte_carlo(&model, paper_opts, 20, 20);
    let rmse_ratio = (paper.mse / local.mse).sqrt();
    println!("RMSE paper / local = {rmse_ratio}");
    assert!(rmse_ratio > 1.02, "RMSE paper / local = {rmse_ratio}");
    let honesty = paper.empirical.trace() / paper.reported.trace();
    println!(
        "paper: empirical / reported = {honesty}, local: {}",
        local.empirical.trace() / local.reported.trace()
    );
    assert!(
        honesty > 1.5,
        "paper S: empirical / reported trace = {honesty}"
    );
}

fn matrix(rows: usize, cols: usize, f: impl Fn(usize, usize) -> f64) -> String {
    let rows: Vec<String> = (0..rows)
        .map(|r| {
            format!(
                "[{}]",
                (0..cols)
                    .map(|c| format!("{:?}", f(r, c)))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        })
        .collect();
    format!("[{}]", rows.join(", "))
}

/// The compile-time-size kernels (`n ≤ 4`, `q ≤ 2`) and the dynamic one compute the same
/// filter: equal to 1e−12 on chains of every supported size, in both dropout modes.
#[test]
fn fixed_size_kernels_equal_dynamic_kernel() {
    for n in 1..=4usize {
        for q in 1..=2usize {
            let mean = matrix(1, n, |_, k| 0.5 - 0.2 * k as f64);
            let text = format!(
                "subsystems = 5\nsteps = 30\n[interconnection]\nplus = 1\nminus = 1\n[model]\n\
                 A = {}\nB = {}\nC = {}\nD = {}\nG = [[0.2, 0.1], [0.1, 0.2]]\nJ = {}\nR = {}\nM = {}\nQ = {}\n\
                 [dropout]\np = [0.9, 0.5, 0.7, 1.0, 0.3]\n[initial]\nmean = {}\ncov = {}\n\
                 [input]\nkind = \"sine\"\nperiod = 11.0\nphase = 0.3\n",
                matrix(n, n, |r, c| if r == c {
                    0.7
                } else {
                    0.1 / (1 + r + c) as f64
                }),
                matrix(n, 2, |r, c| 0.1 * (r + c + 1) as f64),
                matrix(n, 1, |r, _| 0.2 * r as f64),
                matrix(2, n, |r, c| 0.3 / (1 + r + c) as f64),
                matrix(q, n, |r, c| if r == c { 1.0 } else { 0.2 }),
                matrix(q, 1, |r, _| 0.1 * (r + 1) as f64),
                matrix(q, q, |r, c| if r == c { 0.4 } else { 0.05 }),
                matrix(n, n, |r, c| if r == c { 0.02 } else { 0.0 }),
                &mean[1..mean.len() - 1],
                matrix(n, n, |r, c| if r == c { 1.0 } else { 0.1 }),
            );
            let model = model_from(&text);
            let run = simulate_run(&model, 21);
            for dropouts in [Dropouts::Unknown, Dropouts::Known] {
                let opts = TwoStepOptions {
                    dropouts,
                    ..TwoStepOptions::default()
                };
                let mut fast = sisfilt::filter::two_step(&model, opts).unwrap();
                let mut slow = TwoStepFilter::new(&model, opts).unwrap();
                for (t, (y, u)) in run.y.iter().zip(&run.u).enumerate() {
                    let y: Vec<f64> = y
                        .iter()
                        .enumerate()
                        .map(|(k, &v)| {
                            if dropouts == Dropouts::Known && (k + t) % 4 == 0 {
                                f64::NAN
                            } else {
                                v
                            }
                        })
                        .collect();
                    fast.step(&y, u).unwrap();
                    slow.step(&y, u).unwrap();
                    for (a, b) in [
                        (fast.filtered(), slow.filtered()),
                        (fast.predicted(), slow.predicted()),
                    ] {
                        for (k, (va, vb)) in
                            a.0.iter().chain(a.1).zip(b.0.iter().chain(b.1)).enumerate()
                        {
                            assert!(
                                (va - vb).abs() <= 1e-12 * (1.0 + vb.abs()),
                                "n={n} q={q} t={t} k={k}: {va} vs {vb}"
                            );
                        }
                    }
                }
            }
        }
    }
}

/// The fixed-size kernel's lanes (`LANES` subsystems at once) give each subsystem the bits of
/// its one-subsystem update (Nahi's in both dropout modes, the mixture update) and
/// prediction, with arrival probabilities that differ between lanes (`p = 1` among them); a
/// lane whose `Σ` or `S₁` is not positive definite fails the lanes, and the one-subsystem
/// update names it.
#[test]
fn kernel_lanes_equal_one_subsystem_at_a_time() {
    use sisfilt::filter::kernel::{FixedKernel, LANES, LaneData, LocalKernel};
    let model = model_from(
        "subsystems = 4\n[interconnection]\nplus = 1\nminus = 1\n[model]\n\
         A = [[0.9, 0.2], [-0.1, 0.8]]\nB = [[0.3, 0.1], [0.0, 0.2]]\nC = [[0.0], [0.5]]\n\
         D = [[0.4, 0.1], [0.2, 0.3]]\nG = [[0.2, 0.1], [0.1, 0.2]]\nJ = [[1.0, 0.3], [-0.4, 0.7]]\n\
         R = [[0.2], [0.1]]\nM = [[0.3, 0.05], [0.05, 0.2]]\nQ = [[0.02, 0.0], [0.0, 0.01]]\n\
         [dropout]\np = 0.8\n[initial]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n",
    );
    let (n, q) = (2, 2);
    // Symmetric positive definite blocks that differ per lane.
    let spd = |l: usize, scale: f64| {
        let (a, b, c) = (
            1.0 + 0.3 * l as f64,
            0.2 - 0.1 * l as f64,
            0.7 + 0.05 * l as f64,
        );
        [scale * a, scale * b, scale * b, scale * c]
    };
    let t_pred: Vec<f64> = (0..LANES).flat_map(|l| spd(l, 1.0)).collect();
    let s: Vec<f64> = (0..LANES).flat_map(|l| spd(l, 2.5)).collect();
    let x_pred: Vec<f64> = (0..LANES * n).map(|k| 0.3 - 0.17 * k as f64).collect();
    let y: Vec<f64> = (0..LANES * q).map(|k| 1.1 - 0.4 * k as f64).collect();
    let ru: Vec<f64> = (0..LANES * q).map(|k| 0.05 * k as f64).collect();
    let p = [0.8, 1.0, 0.35, 0.6];
    let mut kernel = FixedKernel::<2, 2>::new(&model);
    for known in [false, true] {
        let data = LaneData {
            y: &y,
            ru: &ru,
            p: if known { [1.0; LANES] } else { p },
            known,
        };
        let (mut xf, mut pf, mut ld) = (vec![0.0; LANES * n], vec![0.0; LANES * n * n], [0.0; 4]);
        assert!(kernel.update_lanes(0, &data, &s, &x_pred, &t_pred, &mut xf, &mut pf, &mut ld));
        for l in 0..LANES {
            let (v, m) = (l * n..(l + 1) * n, l * n * n..(l + 1) * n * n);
            let (mut x1, mut p1) = ([0.0; 2], [0.0; 4]);
            let density = kernel
                .update(
                    0,
                    &data.lane(l),
                    &s[m.clone()],
                    &x_pred[v.clone()],
                    &t_pred[m.clone()],
                    &mut x1,
                    &mut p1,
                )
                .unwrap();
            let bits =
                |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(
                bits(&xf[v], &x1) && bits(&pf[m], &p1),
                "known={known} lane {l}"
            );
            if known {
                assert_eq!(ld[l].to_bits(), density.to_bits(), "lane {l}");
            }
        }
        // A lane whose Σ = H T Hᵀ + R_eff is not positive definite: T negative definite.
        let mut broken = t_pred.clone();
        broken[2 * n * n..3 * n * n]
            .iter_mut()
            .for_each(|v| *v *= -10.0);
        assert!(!kernel.update_lanes(0, &data, &s, &x_pred, &broken, &mut xf, &mut pf, &mut ld));
        let m = 2 * n * n..3 * n * n;
        let (mut x1, mut p1) = ([0.0; 2], [0.0; 4]);
        assert!(
            kernel
                .update(
                    0,
                    &data.lane(2),
                    &s[m.clone()],
                    &x_pred[4..6],
                    &broken[m],
                    &mut x1,
                    &mut p1
                )
                .is_none()
        );
    }
    // The mixture update (unknown dropouts): the same bits, π and log density per lane.
    let data = LaneData {
        y: &y,
        ru: &ru,
        p,
        known: false,
    };
    let (mut xf, mut pf) = (vec![0.0; LANES * n], vec![0.0; LANES * n * n]);
    let (mut pi, mut ld) = ([0.0; LANES], [0.0; LANES]);
    assert!(kernel.mixture_lanes(
        0, &data, &x_pred, &t_pred, &mut xf, &mut pf, &mut pi, &mut ld
    ));
    for l in 0..LANES {
        let (v, m) = (l * n..(l + 1) * n, l * n * n..(l + 1) * n * n);
        let (mut x1, mut p1) = ([0.0; 2], [0.0; 4]);
        let a = kernel
            .mixture_update(
                0,
                &data.lane(l),
                &x_pred[v.clone()],
                &t_pred[m.clone()],
                &mut x1,
                &mut p1,
            )
            .unwrap();
        let bits = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(bits(&xf[v], &x1) && bits(&pf[m], &p1), "mixture lane {l}");
        assert!(
            bits(&[pi[l], ld[l]], &[a.probability, a.loglik]),
            "mixture lane {l}"
        );
    }
    let mut broken = t_pred.clone();
    broken[n * n..2 * n * n]
        .iter_mut()
        .for_each(|v| *v *= -10.0);
    assert!(!kernel.mixture_lanes(
        0, &data, &x_pred, &broken, &mut xf, &mut pf, &mut pi, &mut ld
    ));
    for with_q in [false, true] {
        let mut out = vec![0.0; LANES * n * n];
        kernel.propagate_lanes(0, with_q, &t_pred, &mut out);
        for (x, lanes) in t_pred.chunks_exact(n * n).zip(out.chunks_exact(n * n)) {
            let mut one = [0.0; 4];
            kernel.propagate(0, with_q, x, &mut one);
            assert!(
                one.iter()
                    .zip(lanes)
                    .all(|(a, b)| a.to_bits() == b.to_bits())
            );
        }
    }
}

/// Long chains run the local phases in parallel and solve step 1 in two halves, each half's
/// updates, solve and predictions on one thread: every output must have the same bits with
/// one thread and with two (6000 subsystems, above both thresholds), for both moments, both
/// dropout modes, both updates and `z` from either estimate. On a chain whose parameters change
/// across the subsystem the halves share (the 3000th: the first half holds 2999 of the 5999
/// links), with rows missing from the data, that subsystem's among them; and on the same chain
/// without either, where the covariance recursions are shared.
#[test]
fn parallel_steps_are_bitwise_identical() {
    let uniform = UNCOUPLED
        .replace("subsystems = 4", "subsystems = 6000")
        .replace("steps = 60", "steps = 4")
        .replace("p = [0.9, 0.5, 0.7, 1.0]", "p = 0.8")
        .replace("BMAT", "[[0.3, 0.1], [0.0, 0.2]]")
        .replace("DMAT", "[[1.0, 0.0], [0.0, 1.0]]");
    let varying = uniform.clone()
        + "[[override]]\nsubsystems = [2990, 3000]\nA = [[0.8, 0.1], [-0.2, 0.85]]\n\
           [[override]]\nsubsystems = [3001, 3200]\nJ = [[0.9, 0.2]]\n";
    let mut cases = Vec::new();
    for second_moment in [SecondMoment::Local, SecondMoment::Paper] {
        for dropouts in [Dropouts::Unknown, Dropouts::Known] {
            cases.push(TwoStepOptions {
                second_moment,
                dropouts,
                ..TwoStepOptions::default()
            });
        }
    }
    cases.push(TwoStepOptions {
        update: Update::Mixture,
        ..TwoStepOptions::default()
    });
    cases.push(TwoStepOptions {
        interconnect_from: InterconnectFrom::Predicted,
        ..TwoStepOptions::default()
    });
    for (text, gaps) in [(varying, true), (uniform, false)] {
        let model = model_from(&text);
        assert!(
            sisfilt::interconnect::ChainSolver::new(&model, 1)
                .unwrap()
                .halves()
                .is_some_and(|h| h.boundary() == 2999),
            "the test chain must be solved in two halves"
        );
        let mut run = simulate_run(&model, 2);
        if gaps {
            for (t, y) in run.y.iter_mut().enumerate() {
                for i in [2999, 17 + 1000 * t, 5999 - t] {
                    y[i] = f64::NAN;
                }
            }
        }
        let estimate = |threads: usize, opts: TwoStepOptions| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut f = sisfilt::filter::two_step(&model, opts).unwrap();
                let mut out = Vec::new();
                for (y, u) in run.y.iter().zip(&run.u) {
                    f.step(y, u).unwrap();
                    let ((x, p), (xp, tp)) = (f.filtered(), f.predicted());
                    // (π is NaN for a subsystem whose whole row is missing.)
                    assert!(x.iter().chain(p).all(|v| v.is_finite()));
                    for part in [x, p, xp, tp, f.arrival().unwrap_or(&[])] {
                        out.extend_from_slice(part);
                    }
                    out.extend(f.log_likelihood());
                }
                out
            })
        };
        for &opts in &cases {
            let (one, two) = (estimate(1, opts), estimate(2, opts));
            assert_eq!(one.len(), two.len());
            assert!(
                one.iter()
                    .zip(&two)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "{opts:?}, gaps {gaps}"
            );
        }
    }
}

const SHARED: &str = "
subsystems = 7
steps = 25
[interconnection]
plus = 1
minus = 1
[model]
A = [[0.9, 0.2], [-0.1, 0.8]]
B = [[0.3, 0.1], [0.0, 0.2]]
C = [[0.0], [0.5]]
D = [[0.4, 0.1], [0.2, 0.3]]
G = [[0.2, 0.1], [0.1, 0.2]]
J = [[1.0, 0.3]]
R = [[0.2]]
M = [[0.3]]
Q = [[0.02, 0.0], [0.0, 0.01]]
[dropout]
p = PVAL
[initial]
mean = [0.5, -0.5]
cov = [[1.0, 0.1], [0.1, 0.5]]
[input]
kind = \"sine\"
period = 13.0
phase = 0.7
[[override]]
steps = [5, 9]
A = [[0.8, 0.1], [-0.2, 0.85]]
";

/// Covariance recursions shared by identical subsystems (computed once per step) give the
/// same bits as every subsystem computing its own; chains whose subsystems differ in a
/// parameter the recursion uses do not share it.
#[test]
fn shared_recursions_equal_per_subsystem_ones() {
    let scalar_p = SHARED.replace("PVAL", "0.8");
    let cases: Vec<(&str, String, [bool; 2], [bool; 2])> = vec![
        // (name, config, (moment, gain) sharing for local, for paper)
        ("homogeneous", scalar_p.clone(), [true, false], [true, true]),
        (
            "p varies",
            SHARED.replace("PVAL", "[0.9, 0.5, 0.7, 1.0, 0.3, 0.8, 0.8]"),
            [true, false],
            [true, false],
        ),
        (
            "A varies",
            scalar_p.clone() + "[[override]]\nsubsystems = [2, 3]\nA = [[0.7, 0.0], [0.1, 0.6]]\n",
            [false, false],
            [false, false],
        ),
        (
            "J varies",
            scalar_p.clone() + "[[override]]\nsubsystems = [4, 4]\nJ = [[0.5, 1.0]]\n",
            [true, false],
            [true, false],
        ),
        (
            "same A in an override",
            scalar_p.clone()
                + "[[override]]\nsubsystems = [2, 2]\nsteps = [1, 4]\nA = [[0.9, 0.2], [-0.1, 0.8]]\nB = [[0.1, 0.1], [0.1, 0.1]]\n",
            [true, false],
            [true, true],
        ),
    ];
    for (name, text, local, paper) in cases {
        let model = model_from(&text);
        let run = simulate_run(&model, 5);
        for (second_moment, expected) in
            [(SecondMoment::Local, local), (SecondMoment::Paper, paper)]
        {
            let opts = TwoStepOptions {
                second_moment,
                ..TwoStepOptions::default()
            };
            type Fixed = TwoStepFilter<sisfilt::filter::kernel::FixedKernel<2, 1>>;
            let fixed = Fixed::with_kernel(&model, opts).unwrap();
            let sharing = fixed.sharing();
            assert_eq!(
                [sharing.moment, sharing.gain],
                expected,
                "{name} {second_moment:?}"
            );
            let filters: Vec<Box<dyn ChainFilter>> = vec![
                Box::new(fixed),
                Box::new(Fixed::with_kernel(&model, opts).unwrap().without_sharing()),
                Box::new(TwoStepFilter::new(&model, opts).unwrap()),
                Box::new(TwoStepFilter::new(&model, opts).unwrap().without_sharing()),
            ];
            let mut filters = filters;
            for (y, u) in run.y.iter().zip(&run.u) {
                let mut outputs = Vec::new();
                for f in filters.iter_mut() {
                    f.step(y, u).unwrap();
                    let ((x, p), (xp, tp)) = (f.filtered(), f.predicted());
                    outputs.push([x, p, xp, tp].concat());
                }
                for pair in [(0, 1), (2, 3)] {
                    let (a, b) = (&outputs[pair.0], &outputs[pair.1]);
                    assert!(
                        a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits()),
                        "{name} {second_moment:?}: shared and per-subsystem differ"
                    );
                }
                // The fixed-size and dynamic kernels agree to rounding.
                for (a, b) in outputs[0].iter().zip(&outputs[2]) {
                    assert!(
                        (a - b).abs() <= 1e-12 * (1.0 + b.abs()),
                        "{name}: {a} vs {b}"
                    );
                }
            }
        }
    }
}
