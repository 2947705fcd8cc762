//! `fit` (docs/theory.md §16) against independent references: a maximum-likelihood fit done
//! here on the dense Gaussian density of all the measurements with Newton's method, the
//! recovery of the values a simulation used, a parameter on its boundary, and candidates that
//! are no model.

use std::process::Output;

use nalgebra::{DMatrix, DVector};
use sisfilt::filter::{Dropouts, FilterKind};
use sisfilt::fit::{FitSpec, ParamGroup, fit};

use crate::common::{Csv, model_from, platoon_with_gaps, shipped_config, simulate_run, sisfilt};
use crate::reference_filters::{CHAIN, dense_log_density, lose_some};

/// `CHAIN` with every measurement arriving, over 40 steps, with the diagonals of `Q` and `M`
/// given (the off-diagonal `M₁₂ = 0.05` kept).
fn chain_with(q: [f64; 2], m: [f64; 2]) -> String {
    CHAIN
        .replace("steps = 25", "steps = 40")
        .replace("p = [0.9, 0.6, 0.8, 0.7]", "p = 1.0")
        .replace(
            "M = [[0.2, 0.05], [0.05, 0.3]]",
            &format!("M = [[{:?}, 0.05], [0.05, {:?}]]", m[0], m[1]),
        )
        .replace(
            "Q = [[0.03, 0.0], [0.0, 0.02]]",
            &format!("Q = [[{:?}, 0.0], [0.0, {:?}]]", q[0], q[1]),
        )
}

/// Central-difference gradient and Hessian of `f` at `x`.
pub fn derivatives(f: &dyn Fn(&[f64]) -> f64, x: &[f64]) -> (DVector<f64>, DMatrix<f64>) {
    let d = x.len();
    let at = |steps: &[(usize, f64)]| {
        let mut p = x.to_vec();
        for &(k, h) in steps {
            p[k] += h;
        }
        f(&p)
    };
    let (hg, hh) = (1e-5, 1e-3);
    let g = DVector::from_fn(d, |k, _| (at(&[(k, hg)]) - at(&[(k, -hg)])) / (2.0 * hg));
    let centre = f(x);
    let h = DMatrix::from_fn(d, d, |j, k| {
        if j == k {
            (at(&[(k, hh)]) - 2.0 * centre + at(&[(k, -hh)])) / (hh * hh)
        } else {
            (at(&[(j, hh), (k, hh)]) - at(&[(j, hh), (k, -hh)]) - at(&[(j, -hh), (k, hh)])
                + at(&[(j, -hh), (k, -hh)]))
                / (4.0 * hh * hh)
        }
    });
    (g, h)
}

/// Newton's method with Levenberg damping, maximising `f` from `x`: the step solves
/// `(λ I − H) s = g` with `λ` raised until the step is an ascent, lowered after one.
fn newton_maximum(f: &dyn Fn(&[f64]) -> f64, mut x: Vec<f64>) -> Vec<f64> {
    let mut lambda = 1e-3;
    for _ in 0..200 {
        let (g, h) = derivatives(f, &x);
        let here = f(&x);
        loop {
            let damped = DMatrix::identity(x.len(), x.len()) * lambda - &h;
            if let Some(c) = damped.cholesky() {
                let step = c.solve(&g);
                let trial: Vec<f64> = x.iter().zip(&step).map(|(a, s)| a + s).collect();
                if f(&trial) >= here {
                    x = trial;
                    lambda = (lambda / 10.0).max(1e-12);
                    if step.amax() < 1e-9 {
                        return x;
                    }
                    break;
                }
            }
            lambda *= 10.0;
            if lambda > 1e12 {
                return x;
            }
        }
    }
    x
}

/// With `p = 1` and known dropouts (some elements lost), `fit` of the diagonals of `Q` and
/// `M` by the centralized filter equals the maximum of the dense density of all the received
/// measurements found here by Newton's method on the same `θ = log variances` (1e−4
/// relative), its log-likelihoods equal the dense density at the configured values and at the
/// optimum, and its standard errors equal those of the dense Hessian (1e−3 relative).
#[test]
fn fit_equals_newton_on_the_dense_density() {
    let truth = model_from(&chain_with([0.03, 0.02], [0.2, 0.3]));
    let run = simulate_run(&truth, 11);
    let ys: Vec<Vec<f64>> = (run.y.iter().enumerate())
        .map(|(t0, y)| lose_some(y, t0 + 1))
        .collect();
    let configured = ([0.09, 0.01], [0.1, 0.6]);
    let model = model_from(&chain_with(configured.0, configured.1));
    let dense = |theta: &[f64]| {
        let v: Vec<f64> = theta.iter().map(|t| t.exp()).collect();
        dense_log_density(
            &model_from(&chain_with([v[0], v[1]], [v[2], v[3]])),
            &ys,
            &run.u,
        )
    };
    let start: Vec<f64> = [configured.0, configured.1]
        .concat()
        .iter()
        .map(|v: &f64| v.ln())
        .collect();
    // From the values simulated, which the fit never sees.
    let best = newton_maximum(&dense, [0.03f64, 0.02, 0.2, 0.3].map(f64::ln).to_vec());

    let spec = FitSpec {
        params: vec![ParamGroup::Q, ParamGroup::M],
        filter: FilterKind::Centralized,
        dropouts: Dropouts::Known,
        ..FitSpec::default()
    }
    .check()
    .unwrap();
    let y: Vec<f64> = ys.concat();
    let u: Vec<f64> = run.u.concat();
    let fitted = fit(&model, &spec, &y, Some(&u), None).unwrap();
    let report = &fitted.report;
    let names: Vec<&str> = report.parameters.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["Q11", "Q22", "M11", "M22"]);
    let close = |a: f64, b: f64, tol: f64| (a - b).abs() <= tol * b.abs();
    assert!(
        close(report.loglik_start, dense(&start), 1e-9),
        "{} vs {}",
        report.loglik_start,
        dense(&start)
    );
    assert!(
        close(report.loglik, dense(&best), 1e-9),
        "{} vs {}",
        report.loglik,
        dense(&best)
    );
    let (_, h) = derivatives(&dense, &best);
    let covariance = (-h).cholesky().expect("a maximum").inverse();
    for (k, p) in report.parameters.iter().enumerate() {
        let value = best[k].exp();
        assert!(
            close(p.estimate, value, 1e-4),
            "{}: {} vs {value}",
            p.name,
            p.estimate
        );
        let se = covariance[(k, k)].sqrt() * value;
        let got = p.se.expect("an interior optimum has a standard error");
        assert!(close(got, se, 1e-3), "{}: se {got} vs {se}", p.name);
        let (lo, hi) = (p.ci_low.unwrap(), p.ci_high.unwrap());
        assert!(
            lo < p.estimate && p.estimate < hi,
            "{}: [{lo}, {hi}]",
            p.name
        );
    }
    // The fitted model is the config with the estimates in place, and reads back as such.
    let raw = sisfilt::config::ConfigSource::from_text(
        "chain.toml",
        ".".into(),
        chain_with(configured.0, configured.1),
    )
    .unwrap()
    .raw;
    let written = sisfilt::model::Model::from_raw("fitted", fitted.fitted_config(&raw)).unwrap();
    assert_eq!(written.param_sets(), fitted.model.param_sets());
    assert_eq!(written.param_set(0).M[(0, 1)], 0.05);
}

/// Runs `sisfilt` with `args` in `dir`.
fn run_in(dir: &std::path::Path, args: &[&str]) -> Output {
    sisfilt().current_dir(dir).args(args).output().unwrap()
}

fn json(out: &Output) -> serde_json::Value {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

/// The platoon simulated with `p = 0.6`, `Q × 2`, `M × 0.5` against its config, fitted from
/// the config: `p` within 0.01 of the sample's own arrival rate (the estimate follows the
/// sample), each variance within 3.5 standard errors of the value simulated; the JSON has
/// the documented names, the fitted config runs `estimate`, and its innovation check passes.
#[test]
fn fit_recovers_what_the_platoon_was_simulated_with() {
    let dir = tempfile::tempdir().unwrap();
    let config = shipped_config("platoon.toml");
    let config = config.to_str().unwrap();
    let out = run_in(
        dir.path(),
        &[
            "simulate",
            config,
            "--out",
            "sim",
            "--set",
            "dropout.p=0.6",
            "--set",
            "model.Q=[[0.0002, 0.0], [0.0, 0.0008]]",
            "--set",
            "model.M=[[0.02, 0.0], [0.0, 0.005]]",
        ],
    );
    assert!(out.status.success());
    let out = run_in(
        dir.path(),
        &[
            "fit",
            "--config",
            config,
            "--meas",
            "sim/measurements.csv",
            "--format",
            "json",
            "--out",
            "fitted.toml",
        ],
    );
    let report = json(&out);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("innovations of the fitted model: ") && !stderr.contains("do not fit"),
        "{stderr}"
    );
    for key in [
        "loglik_start",
        "loglik",
        "evaluations",
        "iterations",
        "correlation",
        "filter",
        "objective",
        "dropouts",
    ] {
        assert!(report.get(key).is_some(), "{key} missing: {report}");
    }
    // Without --band the fit chooses its objective: a band of the joint filter, or the
    // centralized filter where that is cheaper (tests/integration/fit_band.rs).
    assert_eq!(report["objective"]["chosen"], true, "{report}");
    let filter = match report["objective"]["band"] {
        serde_json::Value::Null => "centralized",
        _ => "joint",
    };
    assert_eq!(report["filter"], filter);
    assert_eq!(report["dropouts"], "unknown");
    assert!(report["loglik"].as_f64() > report["loglik_start"].as_f64());

    let truth = Csv::read(&dir.path().join("sim/truth.csv"));
    let gamma = truth.header.iter().position(|h| h == "gamma").unwrap();
    let arrived = truth.rows.iter().filter(|r| r[gamma] == "1").count() as f64;
    let share = arrived / truth.rows.len() as f64;
    let simulated = [
        ("Q11", 0.0002),
        ("Q22", 0.0008),
        ("M11", 0.02),
        ("M22", 0.005),
    ];
    let parameters = report["parameters"].as_array().unwrap();
    assert_eq!(parameters.len(), 5);
    for p in parameters {
        let name = p["name"].as_str().unwrap();
        let estimate = p["estimate"].as_f64().unwrap();
        let se = p["se"].as_f64().unwrap();
        assert!(p["robust_se"].as_f64().unwrap() > 0.0);
        assert!(p["ci_low"].as_f64().unwrap() < estimate);
        assert!(p["ci_high"].as_f64().unwrap() > estimate);
        if name == "p" {
            assert_eq!(p["configured"], 0.85);
            assert!(
                (estimate - share).abs() < 0.01,
                "p {estimate}, share {share}"
            );
        } else {
            let (_, value) = simulated.iter().find(|(n, _)| *n == name).unwrap();
            assert!(
                (estimate - value).abs() < 3.5 * se,
                "{name}: {estimate} ± {se} against {value}"
            );
        }
    }
    let correlation = report["correlation"].as_array().unwrap();
    assert_eq!(correlation.len(), 5);
    for (k, row) in correlation.iter().enumerate() {
        assert_eq!(row[k].as_f64(), Some(1.0));
    }
    let out = run_in(
        dir.path(),
        &[
            "estimate",
            "--config",
            "fitted.toml",
            "--meas",
            "sim/measurements.csv",
            "--out",
            "est.csv",
        ],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Data where nothing is lost, fitted with `p` free: `p` ends on the boundary of its range,
/// near 1, without an interval (`null`, never NaN), with a warning naming it; the other
/// parameters keep theirs.
#[test]
fn p_on_its_boundary_has_no_interval() {
    let dir = tempfile::tempdir().unwrap();
    let config = shipped_config("platoon.toml");
    let config = config.to_str().unwrap();
    let out = run_in(
        dir.path(),
        &[
            "simulate",
            config,
            "--out",
            "sim",
            "--steps",
            "100",
            "--set",
            "dropout.p=1.0",
        ],
    );
    assert!(out.status.success());
    let out = run_in(
        dir.path(),
        &[
            "fit",
            "--meas",
            "sim/measurements.csv",
            "--params",
            "p,M",
            "--format",
            "json",
            "--set",
            "dropout.p=0.9",
        ],
    );
    let report = json(&out);
    let stderr = String::from_utf8_lossy(&out.stderr);
    let p = &report["parameters"][0];
    assert_eq!(p["name"], "p");
    assert!(p["estimate"].as_f64().unwrap() > 0.999, "{p}");
    for key in ["ci_low", "ci_high", "se", "robust_se"] {
        assert!(p[key].is_null(), "{key}: {p}");
    }
    assert!(
        stderr.contains("warning: p: on the boundary of its range"),
        "{stderr}"
    );
    for m in &report["parameters"].as_array().unwrap()[1..] {
        assert!(m["se"].as_f64().unwrap() > 0.0, "{m}");
    }
    assert!(report["correlation"][0][1].is_null());
}

/// A configured `M` whose off-diagonal entry makes small diagonals indefinite, on data whose
/// `M₁₁` is smaller still: the candidates past the edge are no model (`ℓ = −∞`), the fit
/// stops at the edge with finite figures and does not fail.
#[test]
fn candidates_that_are_no_model_are_handled() {
    let truth = model_from(&chain_with([0.03, 0.02], [0.02, 0.3]).replace(
        "M = [[0.02, 0.05], [0.05, 0.3]]",
        "M = [[0.02, 0.0], [0.0, 0.3]]",
    ));
    let run = simulate_run(&truth, 4);
    let model = model_from(
        &chain_with([0.03, 0.02], [0.2, 0.3])
            .replace("[[0.2, 0.05], [0.05, 0.3]]", "[[0.2, 0.2], [0.2, 0.3]]"),
    );
    let spec = FitSpec {
        params: vec![ParamGroup::M],
        filter: FilterKind::Centralized,
        dropouts: Dropouts::Known,
        ..FitSpec::default()
    }
    .check()
    .unwrap();
    let fitted = fit(&model, &spec, &run.y.concat(), Some(&run.u.concat()), None).unwrap();
    let m = &fitted.report.parameters;
    // M₁₁ M₂₂ > 0.2²: positive definite at the estimate.
    assert!(m[0].estimate * m[1].estimate > 0.04, "{m:?}");
    assert!(fitted.report.loglik.is_finite() && fitted.report.loglik >= fitted.report.loglik_start);
    assert!(fitted.model.param_set(0).M.clone().cholesky().is_some());
}

/// Gaps are read and skipped as `estimate` does: on the platoon with empty cells, `fit`'s
/// log-likelihood at the configured values is the one `estimate` reports for the same filter
/// and update (1e−12 relative), and the fit runs to an interior optimum.
#[test]
fn fit_reads_gaps_as_estimate_does() {
    let dir = tempfile::tempdir().unwrap();
    let meas = platoon_with_gaps(dir.path(), 60, "gaps.csv", |t, i| {
        [(t + i) % 5 == 0, (t * i) % 7 == 3]
    });
    let meas = meas.to_str().unwrap();
    let estimated = json(&run_in(
        dir.path(),
        &[
            "estimate", "--meas", meas, "--filter", "joint", "--update", "mixture", "--format",
            "json",
        ],
    ));
    let report = json(&run_in(
        dir.path(),
        &[
            "fit", "--meas", meas, "--params", "p,M", "--format", "json", "-q",
        ],
    ));
    let (start, loglik) = (
        report["loglik_start"].as_f64().unwrap(),
        estimated["loglik"].as_f64().unwrap(),
    );
    assert!(
        (start - loglik).abs() <= 1e-12 * loglik.abs(),
        "{start} vs {loglik}"
    );
    assert!(report["loglik"].as_f64().unwrap() >= start);
    for p in report["parameters"].as_array().unwrap() {
        assert!(p["se"].as_f64().is_some(), "{p}");
    }
}

/// A config whose `p` varies (a list per subsystem, and overrides) is fitted with one `p`,
/// and the report says so.
#[test]
fn a_p_that_varies_is_fitted_as_one_value_with_a_warning() {
    let model = model_from(CHAIN);
    let run = simulate_run(&model, 2);
    let spec = FitSpec {
        params: vec![ParamGroup::P],
        filter: FilterKind::Centralized,
        max_iter: 3,
        ..FitSpec::default()
    }
    .check()
    .unwrap();
    let fitted = fit(&model, &spec, &run.y.concat(), Some(&run.u.concat()), None).unwrap();
    assert!(
        fitted.report.warnings[0].starts_with("p varies in the config (across subsystems)"),
        "{:?}",
        fitted.report.warnings
    );
    let p = fitted.report.parameters[0].estimate;
    for t in 1..=25 {
        for i in 1..=4 {
            assert_eq!(fitted.model.p(t, i), p);
        }
    }
}
