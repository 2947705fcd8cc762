//! `fit` of each subsystem's own noise variances, `Q[i]` and `M[i]` (docs/theory.md §16,
//! "Each subsystem's own noise"): against the dense Gaussian density of all the measurements
//! built in the test, the coverage of its intervals over seeds, and the command line's
//! fitted config and refusals.

use nalgebra::DVector;
use sisfilt::filter::{Dropouts, FilterKind};
use sisfilt::fit::{FitSpec, ParamGroup, fit};

use crate::common::{model_from, one_error_line, run_ok_in, simulate_steps, sisfilt, write_file};
use crate::fit::derivatives;
use crate::reference_filters::{dense_log_density, lose_some};

const Z_95: f64 = 1.959963984540054;

/// On a chain of five subsystems with their own `Q` and `M` (100 steps, a third of the
/// readings missing), the fit of the ten variances `Q[i]`, `M[i]` (the joint filter's band left
/// to it: it takes the centralized filter and its exact gradient) lands on the maximum of the
/// dense density of all the readings: the Newton step there is under 1e−3 of a standard error,
/// its log-likelihoods are the dense density's (1e−9), its standard errors those of the dense
/// Hessian (1e−3 relative) where it gives one (a variance the data do not bound has none),
/// and its fitted config reads back as the fitted model.
#[test]
fn each_subsystems_noise_is_fitted_at_the_maximum_of_the_dense_density() {
    let base = model_from(FIVE);
    let at = |v: &[f64]| {
        base.with_diagonals_per_subsystem("Q", &v[..5])
            .with_diagonals_per_subsystem("M", &v[5..])
    };
    let run = simulate_steps(&at(&[Q_TRUE, M_TRUE].concat()), 100, 3);
    let ys: Vec<Vec<f64>> = (run.y.iter().enumerate())
        .map(|(t0, y)| lose_some(y, t0 + 1))
        .collect();
    let dense = |theta: &[f64]| {
        let v: Vec<f64> = theta.iter().map(|t| t.exp()).collect();
        dense_log_density(&at(&v), &ys, &run.u)
    };
    let spec = FitSpec {
        params: vec![ParamGroup::QEach, ParamGroup::MEach],
        dropouts: Dropouts::Known,
        ..FitSpec::default()
    }
    .check()
    .unwrap();
    let fitted = fit(&base, &spec, &ys.concat(), None, None).unwrap();
    let report = &fitted.report;
    assert_eq!(report.filter, FilterKind::Centralized);
    let names: Vec<&str> = report.parameters.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(&names[..2], ["Q11[i=1]", "Q11[i=2]"]);
    assert_eq!(names[9], "M11[i=5]");
    let theta: Vec<f64> = report.parameters.iter().map(|p| p.estimate.ln()).collect();
    let start: Vec<f64> = [[0.03; 5], [0.1; 5]]
        .concat()
        .iter()
        .map(|v: &f64| v.ln())
        .collect();
    let close = |a: f64, b: f64, tol: f64| (a - b).abs() <= tol * b.abs();
    assert!(close(report.loglik_start, dense(&start), 1e-9));
    assert!(close(report.loglik, dense(&theta), 1e-9));
    let (g, h) = derivatives(&dense, &theta);
    let covariance = (-h).cholesky().expect("a maximum").inverse();
    let newton: DVector<f64> = &covariance * g;
    let with_interval = report.parameters.iter().filter(|p| p.se.is_some()).count();
    assert!(with_interval >= 8, "{with_interval} of 10 with an interval");
    for (k, p) in report.parameters.iter().enumerate() {
        let se_theta = covariance[(k, k)].sqrt();
        assert!(
            newton[k].abs() < 1e-3 * se_theta,
            "{}: the dense maximum is {} standard errors away",
            p.name,
            newton[k] / se_theta
        );
        let se = se_theta * p.estimate;
        let Some(got) = p.se else {
            // No interval: the data do not bound it inside its range (the fit's box is 25
            // either side of the start in log θ).
            assert!(
                Z_95 * se_theta > 25.0,
                "{}: dense se in log {se_theta}",
                p.name
            );
            continue;
        };
        assert!(close(got, se, 1e-3), "{}: se {got} vs {se}", p.name);
        assert_eq!(p.robust_se, None, "{}", p.name);
    }
    let raw = sisfilt::config::ConfigSource::from_text("five.toml", ".".into(), FIVE.to_string())
        .unwrap()
        .raw;
    let written = sisfilt::model::Model::from_raw("fitted", fitted.fitted_config(&raw)).unwrap();
    assert!(written.same_parameters(&fitted.model));
}

/// A chain of five random walks mixing with their neighbours, each with its own `Q` and `M`.
const FIVE: &str = "
subsystems = 5
steps = 300
[interconnection]
plus = 1
minus = 1
[model]
A = 0.7
B = [[0.1, 0.1]]
D = [[1.0], [1.0]]
J = 1.0
M = 0.1
Q = 0.03
[dropout]
p = 1.0
[initial]
mean = [0.0]
cov = 1.0
";

/// The variances `FIVE`'s subsystems are simulated with.
const Q_TRUE: [f64; 5] = [0.02, 0.05, 0.01, 0.03, 0.04];
const M_TRUE: [f64; 5] = [0.1, 0.05, 0.2, 0.08, 0.12];

/// Over 30 seeds of a chain whose subsystems have their own `Q` and `M` (300 steps), the
/// 95 % intervals of the ten variances cover the values simulated in 90–99 % of the 300
/// cases (the binomial's standard deviation is 1.3 %).
#[test]
fn each_subsystems_intervals_cover_what_was_simulated() {
    let base = model_from(FIVE);
    let truth = base
        .with_diagonals_per_subsystem("Q", &Q_TRUE)
        .with_diagonals_per_subsystem("M", &M_TRUE);
    let spec = FitSpec {
        params: vec![ParamGroup::QEach, ParamGroup::MEach],
        filter: FilterKind::Centralized,
        ..FitSpec::default()
    }
    .check()
    .unwrap();
    let (mut covered, mut total) = (0, 0);
    for seed in 0..30 {
        let run = simulate_steps(&truth, 300, 100 + seed);
        let fitted = fit(&base, &spec, &run.y.concat(), None, None).unwrap();
        for (p, &value) in fitted
            .report
            .parameters
            .iter()
            .zip(Q_TRUE.iter().chain(&M_TRUE))
        {
            total += 1;
            if let (Some(lo), Some(hi)) = (p.ci_low, p.ci_high) {
                covered += usize::from(lo <= value && value <= hi);
            }
        }
    }
    let share = covered as f64 / total as f64;
    assert!(
        (0.90..=0.99).contains(&share),
        "coverage {share} ({covered} of {total})"
    );
}

/// From the command line: `--params 'Q[i],M'` writes a config with one override per
/// subsystem that `estimate` runs and that reads back as the fit; `Q` with `Q[i]`, and `Q[i]`
/// where the config's `Q` varies in time, are refused (exit 2, one line).
#[test]
fn the_command_line_fits_each_subsystems_noise() {
    let dir = tempfile::tempdir().unwrap();
    write_file(dir.path(), "five.toml", FIVE);
    let run = |args: &[&str]| {
        sisfilt()
            .current_dir(dir.path())
            .args(args)
            .output()
            .unwrap()
    };
    assert!(
        run(&["simulate", "five.toml", "--out", "sim"])
            .status
            .success()
    );
    let fitted = run(&[
        "fit",
        "--config",
        "five.toml",
        "--meas",
        "sim/measurements.csv",
        "--params",
        "Q[i],M",
        "--format",
        "json",
        "--out",
        "fitted.toml",
        "-q",
    ]);
    assert!(
        fitted.status.success(),
        "{}",
        String::from_utf8_lossy(&fitted.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&fitted.stdout).unwrap();
    let names: Vec<&str> = (report["parameters"].as_array().unwrap().iter())
        .map(|p| p["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        names,
        [
            "M11", "Q11[i=1]", "Q11[i=2]", "Q11[i=3]", "Q11[i=4]", "Q11[i=5]"
        ]
    );
    let text = std::fs::read_to_string(dir.path().join("fitted.toml")).unwrap();
    assert_eq!(text.matches("[[override]]").count(), 5, "{text}");
    run_ok_in(
        dir.path(),
        &[
            "estimate",
            "--config",
            "fitted.toml",
            "--meas",
            "sim/measurements.csv",
            "--out",
            "e.csv",
        ],
    );
    let fit_of = |config: &str, params: &str| {
        let args = ["fit", "--config", config, "--meas", "sim/measurements.csv"];
        run(&[&args[..], &["--params", params]].concat())
    };

    let both = fit_of("five.toml", "Q,Q[i]");
    assert_eq!(both.status.code(), Some(2));
    let line = one_error_line(&both.stderr);
    assert!(
        line.starts_with("error: --params: Q and Q[i] both name the diagonal of Q"),
        "{line}"
    );

    write_file(
        dir.path(),
        "in_time.toml",
        &format!("{FIVE}[[override]]\nsteps = [1, 10]\nQ = 0.05\n"),
    );
    let in_time = fit_of("in_time.toml", "M[i]");
    assert!(
        in_time.status.success(),
        "{}",
        String::from_utf8_lossy(&in_time.stderr)
    );
    let in_time = fit_of("in_time.toml", "Q[i]");
    assert_eq!(in_time.status.code(), Some(2));
    let line = one_error_line(&in_time.stderr);
    assert!(
        line.starts_with("error: --params: Q[i] fits one Q for each subsystem over every step"),
        "{line}"
    );
}
