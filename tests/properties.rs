//! Numerical robustness of the distributed filter (issue 7): on random stable chains every
//! reported covariance is finite, symmetric and positive semidefinite; the extremes `p = 0`,
//! `p = 1`, a nearly singular `M` and states of size 1e6 or 1e-6 work; and a long run on an
//! uncoupled chain, where the filter is the exact linear MMSE filter, stays consistent.
#![allow(non_snake_case)]

use std::path::PathBuf;

use nalgebra::{DMatrix, SymmetricEigen};
use proptest::prelude::*;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sisfilt::config::ConfigSource;
use sisfilt::filter::{
    ChainFilter, Dropouts, InterconnectFrom, SecondMoment, TwoStepFilter, TwoStepOptions,
};
use sisfilt::inputs::InputStream;
use sisfilt::interconnect::SolverKind;
use sisfilt::model::Model;
use sisfilt::simulate::simulate;

// ---------------------------------------------------------------------------------------------
// Building configs and running the filter
// ---------------------------------------------------------------------------------------------

/// A matrix as a TOML list of rows (`{:?}` keeps every digit and a valid float form).
fn toml_matrix(m: &DMatrix<f64>) -> String {
    let rows: Vec<String> = (0..m.nrows())
        .map(|r| {
            let row: Vec<String> = (0..m.ncols()).map(|c| format!("{:?}", m[(r, c)])).collect();
            format!("[{}]", row.join(", "))
        })
        .collect();
    format!("[{}]", rows.join(", "))
}

fn toml_vector(v: &[f64]) -> String {
    let items: Vec<String> = v.iter().map(|x| format!("{x:?}")).collect();
    format!("[{}]", items.join(", "))
}

/// Everything a chain config needs; turned into TOML by [`Chain::toml`].
#[derive(Debug, Clone)]
struct Chain {
    subsystems: usize,
    plus: usize,
    minus: usize,
    A: DMatrix<f64>,
    B: DMatrix<f64>,
    /// `None`: no input (`m = 0`); else `C`, `H`, `R` with one input column and a sine input.
    CHR: Option<(DMatrix<f64>, DMatrix<f64>, DMatrix<f64>)>,
    D: DMatrix<f64>,
    G: DMatrix<f64>,
    J: DMatrix<f64>,
    M: DMatrix<f64>,
    Q: DMatrix<f64>,
    p: Vec<f64>,
    mean: Vec<f64>,
    cov: DMatrix<f64>,
}

impl Chain {
    fn toml(&self) -> String {
        let mut t = format!(
            "subsystems = {}\nsteps = 10\nseed = 1\n\n[interconnection]\nplus = {}\nminus = {}\n\n[model]\n",
            self.subsystems, self.plus, self.minus
        );
        for (key, m) in [
            ("A", &self.A),
            ("B", &self.B),
            ("D", &self.D),
            ("G", &self.G),
        ] {
            t += &format!("{key} = {}\n", toml_matrix(m));
        }
        if let Some((C, H, R)) = &self.CHR {
            // With plus = minus = 0, H has no rows and is left out: `H = []` would say m = 0.
            for (key, m) in [("C", C), ("H", H), ("R", R)] {
                if m.nrows() > 0 {
                    t += &format!("{key} = {}\n", toml_matrix(m));
                }
            }
        }
        for (key, m) in [("J", &self.J), ("M", &self.M), ("Q", &self.Q)] {
            t += &format!("{key} = {}\n", toml_matrix(m));
        }
        t += &format!("\n[dropout]\np = {}\n", toml_vector(&self.p));
        t += &format!(
            "\n[initial]\nmean = {}\ncov = {}\n",
            toml_vector(&self.mean),
            toml_matrix(&self.cov)
        );
        if self.CHR.is_some() {
            t += "\n[input]\nkind = \"sine\"\namplitude = 1.0\nperiod = 17.0\nphase = 0.3\n";
        }
        t
    }

    fn model(&self) -> Model {
        let text = self.toml();
        let src = ConfigSource::from_text("property.toml", PathBuf::from("."), text.clone())
            .unwrap_or_else(|e| panic!("{e}\n{text}"));
        Model::from_config(&src).unwrap_or_else(|e| panic!("{e}\n{text}"))
    }
}

/// One simulated run: per step `y(t, ·)`, `u(t, ·)`, `x(t, ·)` and `γ(t, ·)`.
struct Run {
    y: Vec<Vec<f64>>,
    u: Vec<Vec<f64>>,
    x: Vec<Vec<f64>>,
    gamma: Vec<Vec<bool>>,
}

fn simulate_run(model: &Model, steps: usize, seed: u64) -> Run {
    let mut inputs = InputStream::open(model, None).unwrap();
    let mut run = Run {
        y: Vec::new(),
        u: Vec::new(),
        x: Vec::new(),
        gamma: Vec::new(),
    };
    simulate(model, steps, seed, &mut inputs, |s| {
        run.y.push(s.y.to_vec());
        run.u.push(s.u.to_vec());
        run.x.push(s.x.to_vec());
        run.gamma.push(s.gamma.to_vec());
        Ok(())
    })
    .unwrap();
    run
}

/// The measurements as the filter sees them: in the known-dropout mode a lost element is NaN.
fn filter_input(model: &Model, run: &Run, t: usize, dropouts: Dropouts) -> Vec<f64> {
    let q = model.dims.q;
    let mut y = run.y[t].clone();
    if dropouts == Dropouts::Known {
        for (i, &g) in run.gamma[t].iter().enumerate() {
            if !g {
                y[i * q..(i + 1) * q].fill(f64::NAN);
            }
        }
    }
    y
}

/// Checks one covariance block (`n × n`, column-major): finite, symmetric and positive
/// semidefinite up to rounding at its own scale.
fn check_covariance(block: &[f64], n: usize, what: &str) -> Result<(), String> {
    if let Some(v) = block.iter().find(|v| !v.is_finite()) {
        return Err(format!("{what}: non-finite entry {v} in {block:?}"));
    }
    let p = DMatrix::from_column_slice(n, n, block);
    let scale = p.amax();
    for r in 0..n {
        for c in 0..r {
            if (p[(r, c)] - p[(c, r)]).abs() > 1e-9 * scale {
                return Err(format!("{what}: not symmetric: {p}"));
            }
        }
    }
    let min = SymmetricEigen::new(p.clone()).eigenvalues.min();
    if min < -1e-9 * scale {
        return Err(format!(
            "{what}: eigenvalue {min:e} below −1e-9 · {scale:e}: {p}"
        ));
    }
    Ok(())
}

/// Runs the two-step filter over a simulated run and checks every reported estimate and
/// covariance (filtered and predicted). Returns the filtered `(x̂, P)` of every step.
#[allow(clippy::type_complexity)]
fn run_filter(
    model: &Model,
    run: &Run,
    opts: TwoStepOptions,
) -> Result<Vec<(Vec<f64>, Vec<f64>)>, String> {
    let (n, big_n) = (model.dims.n, model.subsystems);
    let mut filter = TwoStepFilter::new(model, opts).map_err(|e| format!("new: {e}"))?;
    let mut out = Vec::with_capacity(run.y.len());
    for t in 0..run.y.len() {
        let y = filter_input(model, run, t, opts.dropouts);
        filter
            .step(&y, &run.u[t])
            .map_err(|e| format!("t = {}: {e}", t + 1))?;
        for (kind, (x, p)) in [
            ("filtered", filter.filtered()),
            ("predicted", filter.predicted()),
        ] {
            if let Some(v) = x.iter().find(|v| !v.is_finite()) {
                return Err(format!("t = {}: {kind} estimate {v}", t + 1));
            }
            for i in 0..big_n {
                check_covariance(
                    &p[i * n * n..(i + 1) * n * n],
                    n,
                    &format!("t = {}, i = {}, {kind}", t + 1, i + 1),
                )?;
            }
        }
        let (x, p) = filter.filtered();
        out.push((x.to_vec(), p.to_vec()));
    }
    Ok(out)
}

/// Average NEES `eᵀ P⁻¹ e / n` over every `(t, i)` of a run.
fn average_nees(model: &Model, run: &Run, estimates: &[(Vec<f64>, Vec<f64>)]) -> f64 {
    let n = model.dims.n;
    let (mut sum, mut terms) = (0.0, 0usize);
    for (t, (x_hat, p)) in estimates.iter().enumerate() {
        for i in 0..model.subsystems {
            let e = nalgebra::DVector::from_fn(n, |k, _| run.x[t][i * n + k] - x_hat[i * n + k]);
            let p_i = DMatrix::from_column_slice(n, n, &p[i * n * n..(i + 1) * n * n]);
            let chol = p_i.cholesky().expect("P(t|t) positive definite");
            sum += e.dot(&chol.solve(&e)) / n as f64;
            terms += 1;
        }
    }
    sum / terms as f64
}

// ---------------------------------------------------------------------------------------------
// Random stable chains
// ---------------------------------------------------------------------------------------------

/// A `rows × cols` matrix of entries uniform in `[-a, a]`.
fn uniform(rows: usize, cols: usize, a: f64, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
    DMatrix::from_fn(rows, cols, |_, _| rng.random_range(-a..=a))
}

/// A random chain from a seed: `N ≤ 6`, `n ≤ 3`, `q ≤ 2`, `plus, minus ≤ 1`, `A` scaled to a
/// spectral radius below 0.95, weak coupling, `M` SPD, `Q` and `P0` PSD (possibly singular),
/// `p` in `[0, 1]` with the ends included.
fn random_chain(seed: u64) -> Chain {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let big_n = rng.random_range(1..=6usize);
    let n = rng.random_range(1..=3usize);
    let q = rng.random_range(1..=2usize);
    let (plus, minus) = (rng.random_range(0..=1usize), rng.random_range(0..=1usize));
    let s = plus + minus;
    let mut A = uniform(n, n, 1.0, &mut rng);
    let rho = A
        .complex_eigenvalues()
        .iter()
        .map(|z| z.norm())
        .fold(0.0, f64::max);
    let target = rng.random_range(0.0..0.95);
    if rho > 0.0 {
        A *= target / rho;
    }
    let B = uniform(n, s, 0.3, &mut rng);
    let D = uniform(s, n, 0.3, &mut rng);
    let G = uniform(s, s, 0.2, &mut rng);
    let J = uniform(q, n, 1.0, &mut rng);
    let CHR = rng.random_bool(0.5).then(|| {
        (
            uniform(n, 1, 0.5, &mut rng),
            uniform(s, 1, 0.2, &mut rng),
            uniform(q, 1, 0.5, &mut rng),
        )
    });
    let L = uniform(q, q, 1.0, &mut rng);
    let M = &L * L.transpose() + DMatrix::identity(q, q) * rng.random_range(1e-3..1.0);
    // Q and P0 of random rank (0..=n), so singular ones are covered too.
    let psd = |rng: &mut ChaCha8Rng| {
        let rank = rng.random_range(0..=n);
        let K = uniform(n, rank, 0.5, rng);
        &K * K.transpose()
    };
    let Q = psd(&mut rng);
    let cov = psd(&mut rng) + DMatrix::identity(n, n) * rng.random_range(0.0..0.5);
    let p = (0..big_n)
        .map(|_| match rng.random_range(0..6) {
            0 => 0.0,
            1 => 1.0,
            _ => rng.random_range(0.0..=1.0),
        })
        .collect();
    let mean = (0..n).map(|_| rng.random_range(-2.0..2.0)).collect();
    Chain {
        subsystems: big_n,
        plus,
        minus,
        A,
        B,
        CHR,
        D,
        G,
        J,
        M,
        Q,
        p,
        mean,
        cov,
    }
}

fn options(solver: u8, moment: u8, from: u8, known: bool) -> TwoStepOptions {
    TwoStepOptions {
        solver: if solver == 0 {
            SolverKind::Banded
        } else {
            SolverKind::Transfer
        },
        second_moment: match moment {
            0 => SecondMoment::Local,
            1 => SecondMoment::Paper,
            _ => SecondMoment::Lifted,
        },
        interconnect_from: if from == 0 {
            InterconnectFrom::Filtered
        } else {
            InterconnectFrom::Predicted
        },
        dropouts: if known {
            Dropouts::Known
        } else {
            Dropouts::Unknown
        },
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, .. ProptestConfig::default() })]

    /// On a random stable chain, with any combination of the filter's options, every reported
    /// covariance is finite, symmetric and positive semidefinite, and every estimate finite.
    #[test]
    fn covariances_stay_symmetric_psd_and_finite(
        chain_seed in any::<u64>(),
        run_seed in any::<u64>(),
        steps in 1usize..60,
        solver in 0u8..2,
        moment in 0u8..3,
        from in 0u8..2,
        known in any::<bool>(),
    ) {
        let chain = random_chain(chain_seed);
        let model = chain.model();
        let rho = sisfilt::lifted::spectral_radius(&model, 1, 400).unwrap();
        prop_assume!(rho.value < 0.99, "A_eff not stable: {}", rho.value);
        let opts = options(solver, moment, from, known);
        // Known bug, left to the interconnect's owner: see
        // `transfer_solver_with_minus_0_does_not_panic` below.
        prop_assume!(opts.solver == SolverKind::Banded || chain.minus > 0);
        // The transfer solver may refuse a chain whose G22 is singular; that is not the point.
        prop_assume!(TwoStepFilter::new(&model, opts).is_ok());
        let run = simulate_run(&model, steps, run_seed);
        if let Err(e) = run_filter(&model, &run, opts) {
            prop_assert!(false, "{e}\nconfig:\n{}", chain.toml());
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Extremes
// ---------------------------------------------------------------------------------------------

/// A coupled chain of 4 second-order subsystems with process noise.
fn coupled_chain(p: f64) -> Chain {
    let m = |rows: usize, cols: usize, data: &[f64]| DMatrix::from_row_slice(rows, cols, data);
    Chain {
        subsystems: 4,
        plus: 1,
        minus: 1,
        A: m(2, 2, &[0.8, 0.2, -0.1, 0.7]),
        B: m(2, 2, &[0.1, 0.05, 0.05, 0.1]),
        CHR: None,
        D: m(2, 2, &[0.3, 0.1, 0.1, 0.3]),
        G: m(2, 2, &[0.2, 0.1, 0.1, 0.2]),
        J: m(1, 2, &[1.0, 0.5]),
        M: m(1, 1, &[0.1]),
        Q: m(2, 2, &[0.01, 0.0, 0.0, 0.02]),
        p: vec![p; 4],
        mean: vec![1.0, -1.0],
        cov: DMatrix::identity(2, 2),
    }
}

fn every_option() -> Vec<TwoStepOptions> {
    let mut out = Vec::new();
    for solver in 0..2 {
        for moment in 0..3 {
            for from in 0..2 {
                for known in [false, true] {
                    out.push(options(solver, moment, from, known));
                }
            }
        }
    }
    out
}

#[test]
fn p_0_and_p_1_run_and_stay_finite() {
    for p in [0.0, 1.0] {
        let chain = coupled_chain(p);
        let model = chain.model();
        let run = simulate_run(&model, 300, 11);
        for opts in every_option() {
            run_filter(&model, &run, opts).unwrap_or_else(|e| panic!("p = {p}, {opts:?}: {e}"));
        }
        // With p = 0 nothing arrives: the estimate is the prior propagated forward, so its
        // covariance does not shrink below the stationary prior covariance.
        if p == 0.0 {
            let est = run_filter(&model, &run, TwoStepOptions::default()).unwrap();
            let (_, p_last) = est.last().unwrap();
            assert!(p_last[0] > 0.01, "P(T|T) = {p_last:?}");
        }
    }
}

#[test]
fn nearly_singular_measurement_noise_works() {
    // q = 2, M with the eigenvalues 1 and 1e-12, rotated so that it is not diagonal.
    let (c, s) = (0.6f64, 0.8f64);
    let rot = DMatrix::from_row_slice(2, 2, &[c, -s, s, c]);
    let M = &rot * DMatrix::from_diagonal(&nalgebra::dvector![1.0, 1e-12]) * rot.transpose();
    let mut chain = coupled_chain(0.8);
    chain.J = DMatrix::from_row_slice(2, 2, &[1.0, 0.0, 0.3, 1.0]);
    chain.M = (&M + M.transpose()) * 0.5;
    let model = chain.model();
    let run = simulate_run(&model, 200, 5);
    for opts in every_option() {
        run_filter(&model, &run, opts).unwrap_or_else(|e| panic!("{opts:?}: {e}"));
    }
}

/// Scaling the state (and with it every noise and the measurements) by `k` scales the
/// estimates by `k` and the covariances by `k²`: the filter has no absolute thresholds that
/// break at 1e6 or 1e-6.
#[test]
fn states_of_size_1e6_and_1e_6_work_and_scale() {
    let base = coupled_chain(0.8);
    let model = base.model();
    let run = simulate_run(&model, 200, 9);
    let reference = run_filter(&model, &run, TwoStepOptions::default()).unwrap();
    for k in [1e6, 1e-6] {
        let mut chain = base.clone();
        chain.M *= k * k;
        chain.Q *= k * k;
        chain.cov *= k * k;
        chain.mean.iter_mut().for_each(|m| *m *= k);
        let scaled_model = chain.model();
        let scaled_run = Run {
            y: run
                .y
                .iter()
                .map(|y| y.iter().map(|v| v * k).collect())
                .collect(),
            u: run.u.clone(),
            x: run
                .x
                .iter()
                .map(|x| x.iter().map(|v| v * k).collect())
                .collect(),
            gamma: run.gamma.clone(),
        };
        for opts in every_option() {
            let est = run_filter(&scaled_model, &scaled_run, opts)
                .unwrap_or_else(|e| panic!("k = {k:e}, {opts:?}: {e}"));
            if opts != TwoStepOptions::default() {
                continue;
            }
            for (t, ((x, p), (x0, p0))) in est.iter().zip(&reference).enumerate() {
                let x_scale = x0.iter().fold(1.0f64, |a, v| a.max(v.abs()));
                for (a, b) in x.iter().zip(x0) {
                    assert!(
                        (a / k - b).abs() <= 1e-7 * x_scale,
                        "k = {k:e}, t = {}: x̂ {} vs {b}",
                        t + 1,
                        a / k
                    );
                }
                let p_scale = p0.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                for (a, b) in p.iter().zip(p0) {
                    assert!(
                        (a / (k * k) - b).abs() <= 1e-7 * p_scale,
                        "k = {k:e}, t = {}: P {} vs {b}",
                        t + 1,
                        a / (k * k)
                    );
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Long runs
// ---------------------------------------------------------------------------------------------

/// Two uncoupled subsystems (`B = 0`): each is a linear system with unknown dropouts, for which
/// the Nahi filter is the exact linear MMSE filter, so its covariance is the true error
/// covariance and the average NEES tends to 1.
fn uncoupled_chain() -> Chain {
    let mut chain = coupled_chain(0.8);
    chain.subsystems = 2;
    chain.p = vec![0.8, 0.6];
    chain.B = DMatrix::zeros(2, 2);
    chain.Q = DMatrix::from_row_slice(2, 2, &[0.05, 0.01, 0.01, 0.08]);
    chain.mean = vec![0.0, 0.0];
    chain
}

fn long_run(steps: usize) {
    let chain = uncoupled_chain();
    let model = chain.model();
    let run = simulate_run(&model, steps, 2024);
    let est = run_filter(&model, &run, TwoStepOptions::default()).unwrap();
    let nees = average_nees(&model, &run, &est);
    eprintln!("{steps} steps: average NEES {nees:.4}");
    assert!(
        (0.9..=1.1).contains(&nees),
        "{steps} steps: average NEES {nees}"
    );
}

#[test]
fn long_run_2e4_steps_stays_finite_and_consistent() {
    long_run(20_000);
}

#[test]
fn long_run_1e5_steps_stays_finite_and_consistent() {
    long_run(100_000);
}

/// `--solver transfer` on a chain with `minus = 0`: the transfer solver's `K`
/// of (P16) is then 0 × 0 and its LU solve panics inside nalgebra (src/interconnect/transfer.rs,
/// `TransferSolver::solve`) instead of solving the (trivial) link equations. Found by the
/// property test above; kept here until the solver handles empty signal directions.
#[test]
#[ignore = "known bug: TransferSolver::solve panics when minus = 0"]
fn transfer_solver_with_minus_0_does_not_panic() {
    for (plus, minus) in [(0, 1), (1, 0), (0, 0)] {
        let mut chain = coupled_chain(0.8);
        chain.subsystems = 3;
        chain.p = vec![0.8; 3];
        chain.plus = plus;
        chain.minus = minus;
        let s = plus + minus;
        chain.B = DMatrix::from_element(2, s, 0.1);
        chain.D = DMatrix::from_element(s, 2, 0.3);
        chain.G = DMatrix::identity(s, s) * 0.2;
        let model = chain.model();
        let run = simulate_run(&model, 5, 1);
        let opts = TwoStepOptions {
            solver: SolverKind::Transfer,
            ..TwoStepOptions::default()
        };
        run_filter(&model, &run, opts).unwrap();
    }
}
