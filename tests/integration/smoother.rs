//! The smoothers of docs/theory.md §9 against independent references: a brute-force batch estimator
//! (Gaussian conditioning of all states on all measurements, built here from the model's
//! moments and a dense solve of (P2)–(P4)), a plain RTS smoother written here, and each other
//! where the maths says they agree.

use crate::common::{dense_interconnect, model_from, shipped_config, shipped_model, simulate_run};
use nalgebra::{DMatrix, DVector};
use sisfilt::filter::{
    CentralizedFilter, ChainFilter, Dropouts, JointFilter, JointOptions, SecondMoment,
    TwoStepOptions, Update, two_step,
};
use sisfilt::model::Model;
use sisfilt::smoother::centralized::MAX_CONDITION;
use sisfilt::smoother::{
    CentralizedSmoother, DistributedSmoother, JointSmoother, Smoothed, Smoother, SmootherSchedule,
};

/// A small chain (N·n = 6) with inputs, Q > 0 and overrides in time and space.
pub const SMALL: &str = "
subsystems = 3
steps = 12
seed = 2
[interconnection]
plus = 1
minus = 1
[model]
A = [[0.8, 0.2], [-0.1, 0.9]]
B = [[0.3, 0.1], [0.1, 0.25]]
C = [[0.0], [0.4]]
D = [[0.5, 0.1], [0.2, 0.6]]
G = [[0.2, 0.3], [0.25, 0.15]]
H = [[0.1], [0.0]]
J = [[1.0, 0.5]]
R = [[0.3]]
M = [[0.2]]
Q = [[0.01, 0.0], [0.0, 0.02]]
[dropout]
p = [0.9, 0.5, 0.7]
[initial]
mean = [0.5, -0.3]
cov = [[0.8, 0.1], [0.1, 0.4]]
[input]
kind = \"sine\"
period = 7.0
phase = 0.4
[[override]]
subsystems = [2, 3]
steps = [4, 8]
A = [[0.6, 0.3], [0.0, 0.9]]
G = [[0.1, 0.4], [-0.2, 0.2]]
p = 0.3
";

/// `SMALL` cut to one subsystem (its override then covers that one).
fn one_subsystem() -> Model {
    model_from(
        &SMALL
            .replace("subsystems = 3", "subsystems = 1")
            .replace("[0.9, 0.5, 0.7]", "0.6")
            .replace("subsystems = [2, 3]", "subsystems = [1, 1]"),
    )
}

/// `x(t+1) = A_eff x + U_eff u` at time `t` from the dense interconnection solve.
fn dense_step(model: &Model, t: usize, x: &DVector<f64>, u: &DVector<f64>) -> DVector<f64> {
    let (n, m, big_n) = (model.dims.n, model.dims.m, model.subsystems);
    let g: Vec<DMatrix<f64>> = (1..=big_n).map(|i| model.params(t, i).G.clone()).collect();
    let z: Vec<DVector<f64>> = (1..=big_n)
        .map(|i| {
            let p = model.params(t, i);
            &p.D * x.rows((i - 1) * n, n) + &p.H * u.rows((i - 1) * m, m)
        })
        .collect();
    let v = dense_interconnect(model.dims.plus, model.dims.minus, &g, &z).unwrap();
    let mut out = DVector::zeros(big_n * n);
    for i in 1..=big_n {
        let p = model.params(t, i);
        let next = &p.A * x.rows((i - 1) * n, n) + &p.B * &v[i - 1] + &p.C * u.rows((i - 1) * m, m);
        out.rows_mut((i - 1) * n, n).copy_from(&next);
    }
    out
}

/// The block-diagonal matrix of `blocks` (all of one shape).
fn block_diag(blocks: impl ExactSizeIterator<Item = DMatrix<f64>>) -> DMatrix<f64> {
    let count = blocks.len();
    let mut out = DMatrix::zeros(0, 0);
    for (i, block) in blocks.enumerate() {
        let (r, c) = block.shape();
        if i == 0 {
            out = DMatrix::zeros(r * count, c * count);
        }
        out.view_mut((i * r, i * c), (r, c)).copy_from(&block);
    }
    out
}

/// The lifted model without measurements, per step `t = 1..T` (index `t − 1`): `A_eff(t)`
/// and the prior moments of `X(t)` (its mean and covariance), from the dense chain solve.
struct LiftedPrior {
    a: Vec<DMatrix<f64>>,
    mean: Vec<DVector<f64>>,
    cov: Vec<DMatrix<f64>>,
}

impl LiftedPrior {
    fn new(model: &Model, u: &[Vec<f64>]) -> Self {
        let (n, m, big_n) = (model.dims.n, model.dims.m, model.subsystems);
        let size = big_n * n;
        let steps = u.len();
        let unit = |k: usize, len: usize| DVector::from_fn(len, |r, _| f64::from(r == k));
        // A_eff(t) column by column.
        let a: Vec<DMatrix<f64>> = (1..=steps)
            .map(|t| {
                let zero_u = DVector::zeros(big_n * m);
                DMatrix::from_fn(size, size, |r, c| {
                    dense_step(model, t, &unit(c, size), &zero_u)[r]
                })
            })
            .collect();
        let mut mean = vec![DVector::from_fn(size, |r, _| {
            model.initial.of(r / n).mean[r % n]
        })];
        let mut cov = vec![block_diag(
            (0..big_n).map(|i| model.initial.of(i).cov.clone()),
        )];
        for t in 1..steps {
            let uu = DVector::from_column_slice(&u[t - 1]);
            mean.push(dense_step(model, t, &mean[t - 1], &uu));
            cov.push(&a[t - 1] * &cov[t - 1] * a[t - 1].transpose() + q_big(model, t));
        }
        Self { a, mean, cov }
    }

    /// The noise of subsystem `i`'s measurement (0-based) at step index `k` in the linear
    /// model of unknown dropouts: `M + p(1−p) J S_ii Jᵀ` with the exact moment
    /// `S_ii = P_ii + m_i m_iᵀ`.
    fn nahi_noise(&self, model: &Model, k: usize, i: usize) -> DMatrix<f64> {
        let n = model.dims.n;
        let (prm, p) = (model.params(k + 1, i + 1), model.p(k + 1, i + 1));
        let mi = self.mean[k].rows(i * n, n);
        let s = self.cov[k].view((i * n, i * n), (n, n)) + mi * mi.transpose();
        &prm.M + (&prm.J * s * prm.J.transpose()) * (p * (1.0 - p))
    }
}

/// `blkdiag(Q)` at time `t`.
fn q_big(model: &Model, t: usize) -> DMatrix<f64> {
    block_diag((0..model.subsystems).map(|i| model.params(t, i + 1).Q.clone()))
}

/// The batch estimate: `E[X | Y]` and the diagonal blocks of `Cov[X | Y]` for every step, by
/// Gaussian conditioning on the moments of the lifted linear model (unknown dropouts: the
/// linear model `Y = 𝒫 J X + R U + ν` of docs/theory.md §9; known dropouts: the observed rows).
fn batch_estimate(model: &Model, y: &[Vec<f64>], u: &[Vec<f64>], known: bool) -> Smoothed {
    let (n, q, m, big_n) = (model.dims.n, model.dims.q, model.dims.m, model.subsystems);
    let size = big_n * n;
    let steps = y.len();
    // Means and covariances of X(t); cross-covariances Cov(X(t), X(s)) = Φ(t, s) P(s).
    let prior = LiftedPrior::new(model, &u[..steps]);
    let (a, mean, cov) = (&prior.a, &prior.mean, &prior.cov);
    let total = steps * size;
    let mut sxx = DMatrix::zeros(total, total);
    for s in 0..steps {
        let mut phi = DMatrix::identity(size, size);
        for t in s..steps {
            let block = &phi * &cov[s];
            sxx.view_mut((t * size, s * size), (size, size))
                .copy_from(&block);
            sxx.view_mut((s * size, t * size), (size, size))
                .copy_from(&block.transpose());
            phi = &a[t] * phi;
        }
    }
    // Measurement rows: (t, row of the lifted y), H row, the noise variance.
    let mut rows: Vec<(usize, usize)> = Vec::new();
    for t in 0..steps {
        for r in 0..big_n * q {
            if !known || !y[t][r].is_nan() {
                rows.push((t, r));
            }
        }
    }
    let nr = rows.len();
    let mut h = DMatrix::zeros(nr, total); // E[Y] = H X + R U
    let mut yv = DVector::zeros(nr);
    let mut noise = DMatrix::zeros(nr, nr);
    for (k, &(t, r)) in rows.iter().enumerate() {
        let (i, row) = (r / q, r % q);
        let prm = model.params(t + 1, i + 1);
        let p = if known { 1.0 } else { model.p(t + 1, i + 1) };
        for c in 0..n {
            h[(k, t * size + i * n + c)] = p * prm.J[(row, c)];
        }
        let ru: f64 = (0..m).map(|c| prm.R[(row, c)] * u[t][i * m + c]).sum();
        yv[k] = y[t][r] - ru;
        for (k2, &(t2, r2)) in rows.iter().enumerate() {
            if t2 == t && r2 / q == i {
                noise[(k, k2)] = if known {
                    prm.M[(row, r2 % q)]
                } else {
                    prior.nahi_noise(model, t, i)[(row, r2 % q)]
                };
            }
        }
    }
    let mx = DVector::from_iterator(total, mean.iter().flat_map(|v| v.iter().copied()));
    let syy = &h * &sxx * h.transpose() + noise;
    let sxy = &sxx * h.transpose();
    let chol = syy.cholesky().unwrap();
    let innov = &yv - &h * &mx;
    let xs = &mx + &sxy * chol.solve(&innov);
    let ps = &sxx - &sxy * chol.solve(&sxy.transpose());
    Smoothed {
        x: (0..steps)
            .map(|t| xs.rows(t * size, size).iter().copied().collect())
            .collect(),
        p: (0..steps)
            .map(|t| {
                (0..big_n)
                    .flat_map(|i| {
                        ps.view((t * size + i * n, t * size + i * n), (n, n))
                            .iter()
                            .copied()
                            .collect::<Vec<_>>()
                    })
                    .collect()
            })
            .collect(),
        bands: None,
        notes: vec![],
        gains: None,
        forward: None,
    }
}

/// The largest condition number of `T(t+1) = P(t+1|t)` over `t = 1..T−1`, from a dense
/// Kalman filter of the lifted model in the unknown-dropout mode written here (the
/// measurement noise `M + p(1−p) J S_ii Jᵀ` with the exact prior moment, as in
/// [`batch_estimate`]); its covariances do not depend on `y`.
fn largest_prediction_condition(model: &Model, u: &[Vec<f64>]) -> f64 {
    let big_n = model.subsystems;
    let prior = LiftedPrior::new(model, u);
    let mut pred = prior.cov[0].clone();
    let mut largest = 0.0_f64;
    for t in 1..u.len() {
        let h = block_diag((0..big_n).map(|i| &model.params(t, i + 1).J * model.p(t, i + 1)));
        let noise = block_diag((0..big_n).map(|i| prior.nahi_noise(model, t - 1, i)));
        let gain_tr = (&h * &pred * h.transpose() + noise)
            .cholesky()
            .unwrap()
            .solve(&(&h * &pred));
        let filt = &pred - (&h * &pred).transpose() * gain_tr;
        let a = &prior.a[t - 1];
        pred = a * filt * a.transpose() + q_big(model, t);
        let eig = pred.clone().symmetric_eigen().eigenvalues;
        largest = largest.max(eig.max() / eig.min().max(0.0));
    }
    largest
}

/// The smoothed estimates are the true states and their covariances zero (to 1e−12): a
/// state known exactly with `Q = 0`.
fn assert_truth(smoothed: &Smoothed, run: &crate::common::Run) {
    for (t, (xs, x)) in smoothed.x.iter().zip(&run.x).enumerate() {
        for (a, b) in xs.iter().zip(x) {
            assert!((a - b).abs() < 1e-12, "t = {}: {a} against {b}", t + 1);
        }
    }
    assert!(smoothed.p.iter().flatten().all(|v| v.abs() < 1e-12));
}

fn lose_some(run: &crate::common::Run, q: usize) -> Vec<Vec<f64>> {
    run.y
        .iter()
        .enumerate()
        .map(|(t, y)| {
            y.iter()
                .enumerate()
                .map(|(k, &v)| {
                    if !run.gamma[t][k / q] || (t + k) % 4 == 0 {
                        f64::NAN
                    } else {
                        v
                    }
                })
                .collect()
        })
        .collect()
}

fn smooth(mut s: Box<dyn Smoother + '_>, y: &[Vec<f64>], u: &[Vec<f64>]) -> Smoothed {
    for (y, u) in y.iter().zip(u) {
        s.step(y, u).unwrap();
    }
    s.finish().unwrap()
}

/// Largest relative gaps in `x̂` and `P` between two smoothed runs.
fn gap(a: &Smoothed, b: &Smoothed) -> (f64, f64) {
    let rel = |u: &[Vec<f64>], v: &[Vec<f64>]| {
        let scale = v.iter().flatten().fold(1e-300_f64, |m, x| m.max(x.abs()));
        u.iter()
            .flatten()
            .zip(v.iter().flatten())
            .fold(0.0_f64, |m, (x, y)| m.max((x - y).abs() / scale))
    };
    (rel(&a.x, &b.x), rel(&a.p, &b.p))
}

/// The centralized smoother against the batch estimator on `run`, in both dropout modes
/// (known dropouts with [`lose_some`]): the largest relative gaps in `x̂` and `P`, and that
/// it has nothing to note.
pub fn centralized_against_batch(model: &Model, run: &crate::common::Run, tolerance: f64) {
    for known in [false, true] {
        let y = if known {
            lose_some(run, model.dims.q)
        } else {
            run.y.clone()
        };
        let batch = batch_estimate(model, &y, &run.u, known);
        let rts = smooth(
            Box::new(CentralizedSmoother::new(model, known, 100).unwrap()),
            &y,
            &run.u,
        );
        assert!(rts.notes.is_empty(), "{:?}", rts.notes);
        let (gx, gp) = gap(&rts, &batch);
        assert!(
            gx < tolerance && gp < tolerance,
            "known {known}: x {gx:e}, P {gp:e}"
        );
    }
}

#[test]
fn centralized_smoother_equals_batch_estimator() {
    let model = model_from(SMALL);
    centralized_against_batch(&model, &simulate_run(&model, 5), 1e-10);
    // Without algebraic interconnection (G = 0) on 20 subsystems, A_eff is block tridiagonal
    // (5.8 of its 40 columns a row) and its products go by its rows' envelopes
    // (docs/theory.md §7).
    let banded = SMALL
        .replace("subsystems = 3", "subsystems = 20")
        .replace("p = [0.9, 0.5, 0.7]", "p = 0.7")
        .replace(
            "G = [[0.2, 0.3], [0.25, 0.15]]",
            "G = [[0.0, 0.0], [0.0, 0.0]]",
        )
        .replace(
            "G = [[0.1, 0.4], [-0.2, 0.2]]",
            "G = [[0.0, 0.0], [0.0, 0.0]]",
        );
    let model = model_from(&banded);
    centralized_against_batch(&model, &simulate_run(&model, 5), 1e-10);
}

fn full_band(model: &Model, dropouts: Dropouts, second_moment: SecondMoment) -> JointOptions {
    // Loading 0 too: then the information form is exactly the covariance form.
    JointOptions {
        loading: Some(0.0),
        ..JointOptions::full_band(model, second_moment, dropouts)
    }
}

/// The chains of the full-band comparisons: every shipped config, a small chain with
/// overrides and inputs (also with subsystems that start apart), and chains of 2 and 1
/// subsystems.
fn full_band_models() -> Vec<(String, Model)> {
    let mut models: Vec<(String, Model)> = ["platoon.toml", "heat_rod.toml", "paper.toml"]
        .iter()
        .map(|n| (n.to_string(), shipped_model(n)))
        .collect();
    models.push(("small".into(), model_from(SMALL)));
    models.push((
        "N = 2".into(),
        model_from(
            &SMALL
                .replace("subsystems = 3", "subsystems = 2")
                .replace("[0.9, 0.5, 0.7]", "[0.9, 0.5]")
                .replace("subsystems = [2, 3]", "subsystems = [2, 2]"),
        ),
    ));
    models.push(("N = 1".into(), one_subsystem()));
    models.push((
        "each start its own".into(),
        model_from(&format!("{SMALL}{}", crate::initial::OWN_STARTS)),
    ));
    models
}

/// `--band N−1 --band-tol 0 --loading 0`: the joint smoother is the centralized smoother.
#[test]
fn full_band_joint_smoother_equals_centralized_smoother() {
    for (name, model) in &full_band_models() {
        let run = simulate_run(model, 9);
        let steps = 25.min(run.y.len());
        let (ys, us) = (&run.y[..steps], &run.u[..steps]);
        let y_known = lose_some(&run, model.dims.q);
        for known in [false, true] {
            let ys = if known { &y_known[..steps] } else { ys };
            let dropouts = if known {
                Dropouts::Known
            } else {
                Dropouts::Unknown
            };
            let cent = smooth(
                Box::new(CentralizedSmoother::new(model, known, 1000).unwrap()),
                ys,
                us,
            );
            assert!(cent.notes.is_empty(), "{name}: {:?}", cent.notes);
            let joint = smooth(
                Box::new(
                    JointSmoother::new(model, full_band(model, dropouts, SecondMoment::Lifted))
                        .unwrap(),
                ),
                ys,
                us,
            );
            let (gx, gp) = gap(&joint, &cent);
            assert!(
                gx < 1e-9 && gp < 1e-9,
                "{name}, known {known}: x {gx:e}, P {gp:e}"
            );
        }
    }
}

/// On the mixture filter's moments (docs/theory.md §10) too, the joint smoother at full band
/// is the centralized smoother (1e−9), and with one subsystem the distributed smoother is
/// as well; at `p = 1` every measurement arrives and, for one subsystem, the three mixture
/// smoothers are the textbook Kalman filter and RTS pass written in [`plain_rts`].
#[test]
fn mixture_smoothers_agree_at_full_band() {
    for (name, model) in &full_band_models() {
        let run = simulate_run(model, 9);
        let steps = 25.min(run.y.len());
        let (ys, us) = (&run.y[..steps], &run.u[..steps]);
        let cent = smooth(
            Box::new(
                CentralizedSmoother::new(model, false, 1000)
                    .unwrap()
                    .with_mixture_update()
                    .unwrap(),
            ),
            ys,
            us,
        );
        assert!(cent.notes.is_empty(), "{name}: {:?}", cent.notes);
        let opts = JointOptions {
            update: Update::Mixture,
            ..full_band(model, Dropouts::Unknown, SecondMoment::Band)
        };
        let joint = smooth(Box::new(JointSmoother::new(model, opts).unwrap()), ys, us);
        let (gx, gp) = gap(&joint, &cent);
        assert!(gx < 1e-9 && gp < 1e-9, "{name}: x {gx:e}, P {gp:e}");
        if model.subsystems == 1 {
            let mixture = TwoStepOptions {
                update: Update::Mixture,
                ..TwoStepOptions::default()
            };
            let distributed = smooth(
                Box::new(DistributedSmoother::new(
                    model,
                    two_step(model, mixture).unwrap(),
                )),
                ys,
                us,
            );
            let (gx, gp) = gap(&distributed, &cent);
            assert!(
                gx < 1e-9 && gp < 1e-9,
                "{name}, distributed: x {gx:e}, P {gp:e}"
            );
        }
    }
    let model = one_subsystem().with_arrival_probability(1.0);
    let run = simulate_run(&model, 4);
    let textbook = plain_rts(&model, &run.y, &run.u);
    let mixture = TwoStepOptions {
        update: Update::Mixture,
        ..TwoStepOptions::default()
    };
    let joint = JointOptions {
        update: Update::Mixture,
        ..JointOptions::default()
    };
    let smoothers: Vec<(&str, Box<dyn Smoother>)> = vec![
        (
            "distributed",
            Box::new(DistributedSmoother::new(
                &model,
                two_step(&model, mixture).unwrap(),
            )),
        ),
        (
            "centralized",
            Box::new(
                CentralizedSmoother::new(&model, false, 100)
                    .unwrap()
                    .with_mixture_update()
                    .unwrap(),
            ),
        ),
        (
            "joint",
            Box::new(JointSmoother::new(&model, joint).unwrap()),
        ),
    ];
    for (name, s) in smoothers {
        let out = smooth(s, &run.y, &run.u);
        let (gx, gp) = gap(&out, &textbook);
        assert!(
            gx < 1e-10 && gp < 1e-10,
            "p = 1, {name}: x {gx:e}, P {gp:e}"
        );
    }
}

/// With one subsystem all three smoothers are the plain RTS smoother of the subsystem's
/// Nahi filter, written here from docs/theory.md §4 and §9.
#[test]
fn one_subsystem_smoothers_equal_plain_rts() {
    let model = one_subsystem();
    let run = simulate_run(&model, 3);
    let plain = plain_rts(&model, &run.y, &run.u);
    let opts = TwoStepOptions::default();
    let smoothers: Vec<(&str, Box<dyn Smoother>)> = vec![
        (
            "distributed",
            Box::new(DistributedSmoother::new(
                &model,
                two_step(&model, opts).unwrap(),
            )),
        ),
        (
            "centralized",
            Box::new(CentralizedSmoother::new(&model, false, 10).unwrap()),
        ),
        (
            "joint",
            Box::new(JointSmoother::new(&model, JointOptions::default()).unwrap()),
        ),
    ];
    for (name, s) in smoothers {
        let out = smooth(s, &run.y, &run.u);
        let (gx, gp) = gap(&out, &plain);
        assert!(gx < 1e-10 && gp < 1e-10, "{name}: x {gx:e}, P {gp:e}");
    }
}

/// The plain RTS smoother of a one-subsystem chain's Nahi filter, with the exact moment
/// `S = P + m mᵀ` (`v = 0` for `N = 1`); at `p = 1` the textbook Kalman filter and RTS pass.
fn plain_rts(model: &Model, y: &[Vec<f64>], u: &[Vec<f64>]) -> Smoothed {
    let steps = y.len();
    // Forward: the Nahi filter with the exact moment S = P + m mᵀ (v = 0 for N = 1).
    let prm = |t: usize| model.params(t, 1);
    let mut x = model.initial.of(0).mean.clone();
    let mut t_cov = model.initial.of(0).cov.clone();
    let (mut mm, mut pm) = (x.clone(), t_cov.clone());
    let (mut xf, mut pf, mut xp, mut tp) = (vec![], vec![], vec![], vec![]);
    for t in 1..=steps {
        let (p, a) = (model.p(t, 1), &prm(t).A);
        let j = &prm(t).J;
        let u = DVector::from_column_slice(&u[t - 1]);
        let s = &pm + &mm * mm.transpose();
        let h = j * p;
        let reff = &prm(t).M + j * &s * j.transpose() * (p * (1.0 - p));
        let sig = &h * &t_cov * h.transpose() + &reff;
        let gain = &t_cov * h.transpose() * sig.clone().try_inverse().unwrap();
        let innov = DVector::from_column_slice(&y[t - 1]) - &prm(t).R * &u - &h * &x;
        let x_f = &x + &gain * innov;
        let p_f = &t_cov - &gain * &h * &t_cov;
        x = a * &x_f + &prm(t).C * &u;
        t_cov = a * &p_f * a.transpose() + &prm(t).Q;
        mm = a * &mm + &prm(t).C * &u;
        pm = a * &pm * a.transpose() + &prm(t).Q;
        xf.push(x_f);
        pf.push(p_f);
        xp.push(x.clone());
        tp.push(t_cov.clone());
    }
    let mut xs = xf.clone();
    let mut ps = pf.clone();
    for k in (0..steps - 1).rev() {
        let a = &prm(k + 1).A;
        let c = &pf[k] * a.transpose() * tp[k].clone().try_inverse().unwrap();
        xs[k] = &xf[k] + &c * (&xs[k + 1] - &xp[k]);
        ps[k] = &pf[k] + &c * (&ps[k + 1] - &tp[k]) * c.transpose();
    }
    Smoothed {
        x: xs.iter().map(|v| v.as_slice().to_vec()).collect(),
        p: ps.iter().map(|m| m.as_slice().to_vec()).collect(),
        bands: None,
        notes: vec![],
        gains: None,
        forward: None,
    }
}

/// Monte Carlo (200 runs, fixed seeds) on the platoon (Q > 0): the joint smoother's RMSE is
/// within 0.1 % of the centralized smoother's and below the centralized filter's; its average
/// NEES is within 0.03 of the centralized smoother's.
#[test]
fn joint_smoother_matches_the_optimal_smoother_in_monte_carlo() {
    use sisfilt::accuracy::Accuracy;
    use sisfilt::filter::CentralizedFilter;
    let model = shipped_model("platoon.toml");
    let n = model.dims.n;
    let (mut joint, mut cent, mut filt) = (Accuracy::new(n), Accuracy::new(n), Accuracy::new(n));
    for r in 0..200 {
        let run = simulate_run(&model, 1000 + r);
        let score = |acc: &mut Accuracy, x: &[Vec<f64>], p: &[Vec<f64>]| {
            for t in 0..run.x.len() {
                for i in 0..model.subsystems {
                    acc.add(
                        &run.x[t][i * n..(i + 1) * n],
                        &x[t][i * n..(i + 1) * n],
                        &p[t][i * n * n..(i + 1) * n * n],
                    );
                }
            }
        };
        let s = smooth(
            Box::new(JointSmoother::new(&model, JointOptions::default()).unwrap()),
            &run.y,
            &run.u,
        );
        score(&mut joint, &s.x, &s.p);
        let s = smooth(
            Box::new(CentralizedSmoother::new(&model, false, 1000).unwrap()),
            &run.y,
            &run.u,
        );
        score(&mut cent, &s.x, &s.p);
        let mut f = CentralizedFilter::new(&model, false, 1000).unwrap();
        let (mut xs, mut ps) = (vec![], vec![]);
        for (y, u) in run.y.iter().zip(&run.u) {
            f.step(y, u).unwrap();
            xs.push(f.filtered().0.to_vec());
            ps.push(f.filtered().1.to_vec());
        }
        score(&mut filt, &xs, &ps);
    }
    let (j, c, f) = (joint.report(), cent.report(), filt.report());
    eprintln!(
        "joint smoother {} {:?}, centralized smoother {} {:?}, centralized filter {}",
        j.rmse_overall, j.anees, c.rmse_overall, c.anees, f.rmse_overall
    );
    assert!(j.rmse_overall <= 1.001 * c.rmse_overall);
    assert!(j.rmse_overall < f.rmse_overall);
    assert!((j.anees.unwrap() - c.anees.unwrap()).abs() <= 0.03);
}

/// The command line: `--smooth` with each filter writes the estimates file (JSON with the
/// cross-covariance band for `joint`); the smoothed RMSE is below the filtered one on the
/// platoon; `--smooth --predicted` and a too small `--max-memory` are bad input that write
/// nothing.
#[test]
fn smoothing_on_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let config = crate::common::shipped_config("platoon.toml");
    crate::common::sisfilt()
        .arg("simulate")
        .arg(&config)
        .arg("--out")
        .arg(dir.path())
        .assert()
        .success();
    let meas = dir.path().join("measurements.csv");
    let truth = dir.path().join("truth.csv");
    let rmse = |stderr: &[u8]| -> f64 {
        let text = String::from_utf8_lossy(stderr);
        let at = text.find("(overall ").expect("accuracy line") + "(overall ".len();
        text[at..].split(')').next().unwrap().parse().unwrap()
    };
    for filter in ["distributed", "centralized", "joint"] {
        let run = |smooth: bool, out: &std::path::Path| {
            let mut cmd = crate::common::sisfilt();
            cmd.args(["estimate", "--filter", filter, "--meas"])
                .arg(&meas)
                .arg("--truth")
                .arg(&truth)
                .arg("--out")
                .arg(out);
            if smooth {
                cmd.arg("--smooth");
            }
            let out = cmd.output().unwrap();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            rmse(&out.stderr)
        };
        let smoothed = run(true, &dir.path().join(format!("{filter}.json")));
        let filtered = run(false, &dir.path().join(format!("{filter}_f.csv")));
        assert!(
            smoothed < 0.9 * filtered,
            "{filter}: smoothed {smoothed}, filtered {filtered}"
        );
        let v: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join(format!("{filter}.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(v["options"]["output"], "smoothed");
        assert_eq!(v["estimates"].as_array().unwrap().len(), 20 * 200);
        let width = if filter == "joint" { 7 + 2 * 4 } else { 7 };
        assert_eq!(v["columns"].as_array().unwrap().len(), width, "{filter}");
    }
    for bad in [
        vec!["--smooth", "--predicted"],
        vec!["--smooth", "--max-memory", "10K"],
    ] {
        let out_file = dir.path().join("bad.csv");
        let out = crate::common::sisfilt()
            .arg("estimate")
            .args(&bad)
            .arg("--meas")
            .arg(&meas)
            .arg("--out")
            .arg(&out_file)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{bad:?}");
        crate::common::one_error_line(&out.stderr);
        assert!(!out_file.exists(), "{bad:?} wrote its output");
    }
}

/// `SMALL` with `Q = 0`, no coupling out of the states (`H = 0`, so `A_eff = blkdiag(A)`) and a
/// rank-one `A`: `T(t+1) = A_eff P(t|t) A_effᵀ` is singular, so the centralized RTS form
/// cannot run and docs/theory.md §9's fallback must.
fn singular_prediction() -> Model {
    model_from(&singular_prediction_text())
}

/// The text of [`singular_prediction`].
fn singular_prediction_text() -> String {
    SMALL
        .replace(
            "Q = [[0.01, 0.0], [0.0, 0.02]]",
            "Q = [[0.0, 0.0], [0.0, 0.0]]",
        )
        .replace("H = [[0.1], [0.0]]", "H = [[0.0], [0.0]]")
        .replace(
            "A = [[0.8, 0.2], [-0.1, 0.9]]",
            "A = [[0.8, 0.4], [0.4, 0.2]]",
        )
        .replace(
            "A = [[0.6, 0.3], [0.0, 0.9]]",
            "A = [[0.6, 0.3], [0.4, 0.2]]",
        )
}

/// A singular `T(t+1)`: the centralized smoother's gain takes its Moore–Penrose inverse
/// (docs/theory.md §9) and still matches the batch estimator: on [`singular_prediction`],
/// and on `paper.toml` (`Q = 0`) over 300 steps in both dropout modes (the information form
/// it fell back to before broke down at `t = 298`); on both the condition of some `T(t+1)`
/// passes [`MAX_CONDITION`] (asserted). With the initial state known exactly `T(t+1) = 0`,
/// and the smoothed estimates are the true states.
#[test]
fn centralized_smoother_takes_the_pseudo_inverse_of_a_singular_prediction() {
    let model = singular_prediction();
    let run = simulate_run(&model, 7);
    let condition = largest_prediction_condition(&model, &run.u);
    assert!(condition > MAX_CONDITION, "{condition:e}");
    let batch = batch_estimate(&model, &run.y, &run.u, false);
    let smoothed = smooth(
        Box::new(CentralizedSmoother::new(&model, false, 100).unwrap()),
        &run.y,
        &run.u,
    );
    assert!(smoothed.notes.is_empty(), "{:?}", smoothed.notes);
    // A step whose condition is just below MAX_CONDITION takes the Cholesky solve, wrong by up
    // to about 10¹⁰ · 2⁻⁵² ≈ 2·10⁻⁶ of the largest entry (docs/theory.md §9).
    let (gx, gp) = gap(&smoothed, &batch);
    assert!(gx < 1e-5 && gp < 1e-5, "x {gx:e}, P {gp:e}");

    let paper = std::fs::read_to_string(shipped_config("paper.toml")).unwrap();
    let model = model_from(&paper.replace("steps = 150", "steps = 300"));
    let run = simulate_run(&model, 3);
    let condition = largest_prediction_condition(&model, &run.u);
    assert!(condition > MAX_CONDITION, "{condition:e}");
    centralized_against_batch(&model, &run, 1e-8);

    let known_start = model_from(&paper.replace(
        "cov = [[1.0, 0.0], [0.0, 1.0]]",
        "cov = [[0.0, 0.0], [0.0, 0.0]]",
    ));
    let run = simulate_run(&known_start, 3);
    let smoothed = smooth(
        Box::new(CentralizedSmoother::new(&known_start, false, 100).unwrap()),
        &run.y,
        &run.u,
    );
    assert_truth(&smoothed, &run);
}

/// The distributed smoother on a singular `T(t+1)` (one subsystem of [`singular_prediction`],
/// where it is the optimal smoother since `v = 0`): the RTS gain with the Moore–Penrose
/// inverse of docs/theory.md §9 matches the batch estimator, and so on a chain whose initial
/// state is known exactly (`cov = 0`, `Q = 0`), where the prediction is zero and the smoothed
/// estimates are the true states themselves.
#[test]
fn distributed_smoother_runs_on_a_singular_prediction() {
    let model = model_from(
        &singular_prediction_text()
            .replace("subsystems = 3", "subsystems = 1")
            .replace("[0.9, 0.5, 0.7]", "0.6")
            .replace("subsystems = [2, 3]", "subsystems = [1, 1]"),
    );
    let run = simulate_run(&model, 7);
    let batch = batch_estimate(&model, &run.y, &run.u, false);
    let distributed = |model: &Model| {
        Box::new(DistributedSmoother::new(
            model,
            two_step(model, TwoStepOptions::default()).unwrap(),
        ))
    };
    let smoothed = smooth(distributed(&model), &run.y, &run.u);
    let (gx, gp) = gap(&smoothed, &batch);
    assert!(gx < 1e-9 && gp < 1e-9, "x {gx:e}, P {gp:e}");

    let known = model_from(&singular_prediction_text().replace(
        "cov = [[0.8, 0.1], [0.1, 0.4]]",
        "cov = [[0.0, 0.0], [0.0, 0.0]]",
    ));
    let run = simulate_run(&known, 7);
    let smoothed = smooth(distributed(&known), &run.y, &run.u);
    assert_truth(&smoothed, &run);
}

/// `evaluate` runs the covariance pass of the centralized and the joint smoother once
/// ([`SmootherSchedule`], on `y = 0`) and replays only the means per run: that equals
/// smoothing the run itself, with the centralized fallback too. (The distributed smoother's
/// covariances depend on the data through the two-step filter's local moment.)
#[test]
fn scheduled_backward_pass_equals_smoothing_each_run() {
    for model in [model_from(SMALL), singular_prediction()] {
        let run = simulate_run(&model, 11);
        let opts = JointOptions::default();
        type Make<'a> = Box<dyn Fn() -> (Box<dyn Smoother + 'a>, Box<dyn ChainFilter + 'a>) + 'a>;
        let makers: Vec<(&str, Make)> = vec![
            (
                "centralized",
                Box::new(|| {
                    (
                        Box::new(CentralizedSmoother::new(&model, false, 100).unwrap())
                            as Box<dyn Smoother>,
                        Box::new(CentralizedFilter::new(&model, false, 100).unwrap())
                            as Box<dyn ChainFilter>,
                    )
                }),
            ),
            (
                "joint",
                Box::new(|| {
                    (
                        Box::new(JointSmoother::new(&model, opts).unwrap()) as Box<dyn Smoother>,
                        Box::new(JointFilter::new(&model, opts).unwrap()) as Box<dyn ChainFilter>,
                    )
                }),
            ),
        ];
        for (name, make) in &makers {
            let direct = smooth(make().0, &run.y, &run.u);
            let schedule = SmootherSchedule::new(make().0, &model, &run.u).unwrap();
            let mut filter = match schedule.forward {
                Some(opts) => Box::new(JointFilter::new(&model, opts).unwrap()),
                None => make().1,
            };
            let (mut x_filt, mut x_pred) = (Vec::new(), Vec::new());
            for (y, u) in run.y.iter().zip(&run.u) {
                filter.step(y, u).unwrap();
                x_filt.push(filter.filtered().0.to_vec());
                x_pred.push(filter.predicted().0.to_vec());
            }
            let replayed = Smoothed {
                x: schedule.smooth_means(&model, &x_filt, &x_pred),
                p: schedule.p.clone(),
                bands: None,
                notes: Vec::new(),
                gains: None,
                forward: None,
            };
            let (gx, gp) = gap(&replayed, &direct);
            assert!(gx < 1e-12 && gp < 1e-12, "{name}: x {gx:e}, P {gp:e}");
        }
    }
}

/// With `Q = 0` and the default band 2, the joint smoother of `paper.toml` loses positive
/// definiteness in its backward pass at the default loading 1e−9, with known dropouts and
/// with the mixture update. With the default loading it then reruns with a larger one
/// (docs/theory.md §9): the result is the smoother run with that `--loading` from the start,
/// bit for bit, and a note names it. A loading the user chose is kept, and the failure is
/// an error that says what to raise.
#[test]
fn joint_smoother_reruns_with_a_larger_loading_where_the_default_fails() {
    let model = shipped_model("paper.toml");
    let run = simulate_run(&model, 2);
    let known_y = lose_some(&run, model.dims.q);
    for (opts, y) in [
        (
            JointOptions {
                dropouts: Dropouts::Known,
                ..JointOptions::default()
            },
            &known_y,
        ),
        (
            JointOptions {
                update: Update::Mixture,
                ..JointOptions::default()
            },
            &run.y,
        ),
    ] {
        let what = format!("{:?}, {:?}", opts.dropouts, opts.update);
        let rerun = smooth(
            Box::new(JointSmoother::new(&model, opts).unwrap()),
            y,
            &run.u,
        );
        assert_eq!(rerun.notes.len(), 1, "{what}: {:?}", rerun.notes);
        let note = &rerun.notes[0];
        let loading: f64 = note
            .split("--loading ")
            .nth(1)
            .and_then(|rest| rest.split(' ').next())
            .and_then(|word| word.parse().ok())
            .unwrap_or_else(|| panic!("{what}: no loading in {note}"));
        assert!(loading > 1e-9 && loading <= 1e-5, "{what}: {note}");
        let chosen = JointOptions {
            loading: Some(loading),
            ..opts
        };
        let direct = smooth(
            Box::new(JointSmoother::new(&model, chosen).unwrap()),
            y,
            &run.u,
        );
        assert!(direct.notes.is_empty(), "{what}: {:?}", direct.notes);
        assert_eq!(rerun.x, direct.x, "{what}");
        assert_eq!(rerun.p, direct.p, "{what}");
        let forward = rerun.forward.expect("the rerun's filter");
        assert_eq!(forward.loading, Some(loading), "{what}");
        // The user's own 1e−9 is kept: the same failure, as an error.
        let mut own = Box::new(
            JointSmoother::new(
                &model,
                JointOptions {
                    loading: Some(1e-9),
                    ..opts
                },
            )
            .unwrap(),
        );
        for (y, u) in y.iter().zip(&run.u) {
            own.step(y, u).unwrap();
        }
        let Err(e) = own.finish() else {
            panic!(
                "{what}: the joint smoother with --loading 1e-9 no longer fails on paper.toml; the rerun is untested"
            );
        };
        assert!(e.to_string().contains("raise --loading"), "{what}: {e}");
    }
}
