//! The spectral radius of `A_eff` and its bound (docs/theory.md §3), on chains whose radius is
//! known in closed form: a conserving one (radius exactly 1), one just above 1, and a strongly
//! non-normal one (radius 0.9, Ritz values near 1.2). Exact where computed exactly, the bound
//! honoured where estimated, and `check` and `estimate` say the same.

use crate::common::{estimate_simulated, model_from, sisfilt, write_file};
use sisfilt::stability::{RadiusEffort, SpectralRadius, Stability, spectral_radius};

/// Heat diffusion along `big_n` segments with insulated ends: `x⁺(i) = x(i) + α (x(i−1) −
/// 2 x(i) + x(i+1))`, an end's missing neighbour replaced by the end itself, plus `gain x(i)`.
/// `A_eff = (1 + gain) I − α L` with `L` the Neumann Laplacian of the path, whose eigenvalues
/// are `2 − 2 cos(kπ/N)`, `k = 0..N−1`: with `α = 0.2` the radius is exactly `1 + gain`, on
/// the constant vector (the total heat, conserved when `gain = 0`).
fn heat_chain(big_n: usize, gain: f64) -> String {
    let (a, alpha) = (1.0 - 2.0 * 0.2 + gain, 0.2);
    format!(
        "subsystems = {big_n}\nsteps = 20\n[interconnection]\nplus = 1\nminus = 1\n[model]\n\
         A = {a}\nB = [[{alpha}, {alpha}]]\nD = [[1.0], [1.0]]\nJ = 1\nM = 0.05\nQ = 0.01\n\
         [dropout]\np = 0.8\n[initial]\ncov = 1\n\
         [[override]]\nsubsystems = [1, 1]\nA = {end}\n\
         [[override]]\nsubsystems = [{big_n}, {big_n}]\nA = {end}\n",
        end = a + alpha
    )
}

/// A platoon-like chain that passes each state on to the next only (`n⁺ = 1`, `n⁻ = 0`):
/// `A_eff = 0.9 I + 0.3 S` with `S` the down-shift, lower triangular, so its radius is 0.9;
/// but its powers grow as `1.2ᵏ` until what they carry leaves the chain.
fn one_way_chain(big_n: usize) -> String {
    format!(
        "subsystems = {big_n}\nsteps = 20\n[interconnection]\nplus = 1\nminus = 0\n[model]\n\
         A = 0.9\nB = 0.3\nD = 1.0\nG = 0.0\nJ = 1\nM = 0.05\nQ = 0.01\n[dropout]\np = 0.8\n\
         [initial]\ncov = 1\n"
    )
}

fn radius(text: &str, effort: RadiusEffort) -> SpectralRadius {
    let model = model_from(text);
    let solver = sisfilt::interconnect::ChainSolver::new(&model, 1).unwrap();
    spectral_radius(&model, 1, &solver, effort)
}

/// 40 Arnoldi steps and no dense eigenvalues.
const KRYLOV: RadiusEffort = RadiusEffort {
    exact_max: 0,
    krylov: 40,
};

#[test]
fn a_conserving_chain_is_marginal_exact_and_estimated() {
    let exact = radius(&heat_chain(30, 0.0), RadiusEffort::DEFAULT);
    assert!(exact.exact, "{exact:?}");
    assert!((exact.value - 1.0).abs() <= exact.bound, "{exact:?}");
    assert!(exact.bound < 1e-6, "{exact:?}");
    assert_eq!(exact.stability(), Stability::Marginal);

    // A normal A_eff: the Ritz values lie in the hull of the eigenvalues, within the bound of
    // one; the largest is the one at 1.
    let estimate = radius(&heat_chain(600, 0.0), KRYLOV);
    assert!(!estimate.exact, "{estimate:?}");
    assert!(estimate.value <= 1.0 + 1e-12, "{estimate:?}");
    assert!(
        (estimate.value - 1.0).abs() <= estimate.bound,
        "{estimate:?}"
    );
    assert_ne!(estimate.stability(), Stability::Unstable);
}

#[test]
fn a_chain_just_above_one_is_unstable_exact_and_estimated() {
    let gain = 1e-3;
    for (big_n, effort) in [(30, RadiusEffort::DEFAULT), (600, KRYLOV)] {
        let figure = radius(&heat_chain(big_n, gain), effort);
        assert_eq!(figure.exact, big_n == 30, "{figure:?}");
        assert!(
            (figure.value - (1.0 + gain)).abs() <= figure.bound,
            "{figure:?}"
        );
        assert_eq!(figure.stability(), Stability::Unstable, "{figure:?}");
    }
}

/// Exact, the radius is 0.9. Estimated, the Ritz values see the pseudospectrum, near 1.2: the
/// figure is above 1 beyond its bound, and what it then claims — Kreiss's bound, some power
/// of `A_eff` at least `(θ − 1) / bound` in norm — holds: `(A_effᵏ e₁)_j = C(k, j) 0.9^{k−j}
/// 0.3^j` for `j < N`.
#[test]
fn a_strongly_non_normal_chain_honours_its_bound() {
    let exact = radius(&one_way_chain(100), RadiusEffort::DEFAULT);
    assert!(exact.exact);
    assert!((exact.value - 0.9).abs() <= exact.bound, "{exact:?}");
    assert_eq!(exact.stability(), Stability::Stable);

    let big_n = 300;
    let estimate = radius(&one_way_chain(big_n), KRYLOV);
    assert_eq!(estimate.stability(), Stability::Unstable, "{estimate:?}");
    let claimed = estimate.least_growth();
    let power_norm = |k: usize| {
        // ln C(k, j) by sums of logarithms, to keep the terms finite.
        let mut ln_choose = 0.0_f64;
        let mut sum = 0.0_f64;
        for j in 0..big_n.min(k + 1) {
            if j > 0 {
                ln_choose += ((k + 1 - j) as f64).ln() - (j as f64).ln();
            }
            let ln_term = ln_choose + (k - j) as f64 * 0.9_f64.ln() + j as f64 * 0.3_f64.ln();
            sum += (2.0 * ln_term).exp();
        }
        sum.sqrt()
    };
    let largest = (1..4 * big_n).map(power_norm).fold(0.0, f64::max);
    assert!(
        largest >= claimed,
        "‖A^k e₁‖ reaches {largest:e}, below Kreiss's {claimed}"
    );
}

/// The lines `check` and `estimate` print about the radius of the same chain: the same words,
/// exact and estimated.
#[test]
fn check_and_estimate_say_the_same() {
    let dir = tempfile::tempdir().unwrap();
    for (name, text, says) in [
        ("short", heat_chain(30, 0.0), "= 1 (to "),
        ("long", heat_chain(600, 2e-4), "(Krylov), above 1"),
    ] {
        let config = write_file(dir.path(), &format!("{name}.toml"), &text);
        let check = sisfilt().arg("check").arg(&config).output().unwrap();
        assert!(check.status.success());
        let warning = |stderr: &[u8]| {
            let stderr = String::from_utf8(stderr.to_vec()).unwrap();
            let line = stderr
                .lines()
                .find(|l| l.starts_with("warning: ") && l.contains("spectral radius"))
                .unwrap_or_else(|| panic!("{name}: no warning about the radius in {stderr}"))
                .to_string();
            // check names the window (`t = 1..20: `); a run names its start only after the
            // first step.
            line.trim_start_matches("warning: ")
                .trim_start_matches("t = 1..20: ")
                .to_string()
        };
        let from_check = warning(&check.stderr);
        assert!(from_check.contains(says), "{name}: {from_check}");
        let run = estimate_simulated(dir.path(), &config, name);
        assert!(run.status.success());
        assert_eq!(warning(&run.stderr), from_check, "{name}");
    }
}

/// Where no reading can be lost (`p = 1`), no filter weighs the second moment that a
/// conserving or unstable chain grows: `check` prints the radius and neither it nor a run
/// warns (docs/theory.md §3); the same chains with `p = 0.8` are warned of above.
#[test]
fn without_losses_the_radius_is_printed_and_nothing_warns() {
    let dir = tempfile::tempdir().unwrap();
    for (name, text) in [
        ("conserving", heat_chain(30, 0.0)),
        ("above", heat_chain(30, 1e-3)),
    ] {
        let text = text.replace("p = 0.8", "p = 1.0");
        let config = write_file(dir.path(), &format!("{name}.toml"), &text);
        let check = sisfilt().arg("check").arg(&config).output().unwrap();
        assert!(check.status.success());
        let stdout = String::from_utf8(check.stdout).unwrap();
        assert!(
            stdout.contains("spectral radius of A_eff 1.00"),
            "{name}: {stdout}"
        );
        let run = estimate_simulated(dir.path(), &config, name);
        assert!(run.status.success());
        for stderr in [check.stderr, run.stderr] {
            let stderr = String::from_utf8(stderr).unwrap();
            assert!(!stderr.contains("spectral radius"), "{name}: {stderr}");
        }
    }
}
