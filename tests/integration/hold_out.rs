//! Readings held out of the filter (docs/theory.md §17): the figures against a run on the
//! data without those readings, computed here; the standardised squares of the true model
//! against their expectation 1 (Monte Carlo); the command line's line, JSON and refusals.

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sisfilt::accuracy::HeldOutReport;
use sisfilt::filter::FilterKind;
use sisfilt::model::Model;
use sisfilt::run::{RunSpec, estimate};

use crate::common::{model_from, one_error_line, shipped_config, simulate_steps, sisfilt};

/// A chain with inputs in its measurements (`R ≠ 0`) and two readings per subsystem.
const CHAIN: &str = r#"
    subsystems = 5
    [interconnection]
    plus = 1
    minus = 1
    [model]
    A = [[0.9, 0.1], [-0.1, 0.8]]
    B = [[0.1, 0.0], [0.0, 0.1]]
    C = [[0.0], [0.2]]
    D = [[1.0, 0.0], [0.0, 1.0]]
    J = [[1.0, 0.0], [0.5, 1.0]]
    R = [[0.3], [0.0]]
    M = [[0.04, 0.0], [0.0, 0.09]]
    Q = [[0.01, 0.0], [0.0, 0.02]]
    [dropout]
    p = 1.0
    [initial]
    mean = [0.0, 0.0]
    cov = [[1.0, 0.0], [0.0, 1.0]]
    [input]
    kind = "sine"
    amplitude = 1.0
    period = 20.0
    phase = 0.5
"#;

/// `y` (`T × N × q`) and `u` of `steps` simulated steps, with some elements not in the data.
fn data_with_gaps(model: &Model, steps: usize, seed: u64) -> (Vec<f64>, Vec<f64>) {
    let run = simulate_steps(model, steps, seed);
    let mut y: Vec<f64> = run.y.concat();
    for (k, v) in y.iter_mut().enumerate() {
        if k % 7 == 3 {
            *v = f64::NAN;
        }
    }
    (y, run.u.concat())
}

/// The figures of docs/theory.md §17, computed here from scratch: the readings held out by
/// the documented draw, a run of `spec` without them, and the interpolation of each sensor.
fn expected_figures(
    model: &Model,
    spec: &RunSpec,
    y: &[f64],
    u: &[f64],
    share: f64,
    seed: u64,
) -> (HeldOutReport, Vec<f64>) {
    let (n, q, m, big_n) = (model.dims.n, model.dims.q, model.dims.m, model.subsystems);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut kept = y.to_vec();
    let mut held = Vec::new();
    for (k, v) in kept.iter_mut().enumerate() {
        if !v.is_nan() && rng.random::<f64>() < share {
            held.push(k);
            *v = f64::NAN;
        }
    }
    let run = estimate(model, &spec.clone().check().unwrap(), &kept, Some(u), None).unwrap();
    let (mut sq, mut sq_interp, mut sq_last, mut standardised) = (0.0, 0.0, 0.0, 0.0);
    for &k in &held {
        let (t, i, e) = (k / (big_n * q), k / q % big_n, k % q);
        let params = model.params(t + 1, i + 1);
        let x = &run.x[(t * big_n + i) * n..][..n];
        let p = &run.p[(t * big_n + i) * n * n..][..n * n];
        let mut predicted = 0.0;
        for a in 0..n {
            predicted += params.J[(e, a)] * x[a];
        }
        for j in 0..m {
            predicted += params.R[(e, j)] * u[(t * big_n + i) * m + j];
        }
        let mut claimed = params.M[(e, e)];
        for a in 0..n {
            for b in 0..n {
                claimed += params.J[(e, a)] * p[b * n + a] * params.J[(e, b)];
            }
        }
        // The same sensor's kept readings, nearest before and after.
        let reading = |s: usize| kept[(s * big_n + i) * q + e];
        let before = (0..t).rev().find(|&s| !reading(s).is_nan());
        let after = (t + 1..kept.len() / (big_n * q)).find(|&s| !reading(s).is_nan());
        let (interpolated, last) = match (before, after) {
            (Some(s0), Some(s1)) => (
                reading(s0) + (reading(s1) - reading(s0)) * (t - s0) as f64 / (s1 - s0) as f64,
                reading(s0),
            ),
            (Some(s), None) | (None, Some(s)) => (reading(s), reading(s)),
            (None, None) => unreachable!("every sensor has kept readings here"),
        };
        let error = y[k] - predicted;
        sq += error * error;
        sq_interp += (y[k] - interpolated).powi(2);
        sq_last += (y[k] - last).powi(2);
        standardised += error * error / claimed;
    }
    let count = held.len() as f64;
    let half = 1.959_963_984_540_054 * (2.0 / count).sqrt();
    let report = HeldOutReport {
        share,
        seed,
        readings: held.len(),
        unscored: 0,
        rmse: (sq / count).sqrt(),
        interpolation_rmse: (sq_interp / count).sqrt(),
        last_reading_rmse: (sq_last / count).sqrt(),
        standardised: standardised / count,
        band: (1.0 - half, 1.0 + half),
    };
    (report, run.x)
}

fn held_out_run(
    model: &Model,
    spec: &RunSpec,
    y: &[f64],
    u: &[f64],
    (share, seed): (f64, u64),
) -> (HeldOutReport, Vec<f64>) {
    let spec = RunSpec {
        hold_out: Some(share),
        hold_out_seed: seed,
        ..spec.clone()
    };
    let run = estimate(model, &spec.check().unwrap(), y, Some(u), None).unwrap();
    let report = run.report.summary.held_out.expect("a held-out report");
    (report, run.x)
}

fn assert_close(what: &str, got: f64, want: f64) {
    assert!(
        (got - want).abs() <= 1e-12 * want.abs().max(1e-300),
        "{what}: {got} against {want}"
    );
}

#[test]
fn the_figures_are_those_of_a_run_without_the_held_out_readings() {
    let model = model_from(CHAIN);
    let (y, u) = data_with_gaps(&model, 120, 4);
    let specs = [
        RunSpec::default(),
        RunSpec {
            filter: FilterKind::Joint,
            smooth: true,
            ..RunSpec::default()
        },
        RunSpec {
            filter: FilterKind::Centralized,
            update: sisfilt::filter::Update::Mixture,
            ..RunSpec::default()
        },
    ];
    for spec in &specs {
        let (share, seed) = (0.15, 9);
        let (got, got_x) = held_out_run(&model, spec, &y, &u, (share, seed));
        let (want, want_x) = expected_figures(&model, spec, &y, &u, share, seed);
        let what = format!("{:?} smooth {}", spec.filter, spec.smooth);
        assert_eq!(got.readings, want.readings, "{what}");
        assert!(got.readings > 80, "{what}: {} held out", got.readings);
        assert_eq!(got.unscored, 0, "{what}");
        assert_eq!(
            got_x, want_x,
            "{what}: the estimates are a run's without the readings"
        );
        assert_close(&format!("{what} rmse"), got.rmse, want.rmse);
        assert_close(
            &format!("{what} interpolation"),
            got.interpolation_rmse,
            want.interpolation_rmse,
        );
        assert_close(
            &format!("{what} last reading"),
            got.last_reading_rmse,
            want.last_reading_rmse,
        );
        assert_close(
            &format!("{what} standardised"),
            got.standardised,
            want.standardised,
        );
        assert_close(&format!("{what} band"), got.band.1, want.band.1);
    }
}

/// Under the true model each `e²/s²` has expectation 1; under a model whose `M` is four times
/// the truth's, about a quarter (the claimed variance is mostly `M` here). The tolerance is
/// eight standard errors of independent terms (their correlation in time widens it a little).
#[test]
fn the_true_model_claims_the_variance_of_its_errors() {
    let truth = model_from(CHAIN);
    let (y, u) = data_with_gaps(&truth, 1500, 11);
    let wrong = model_from(&CHAIN.replace(
        "M = [[0.04, 0.0], [0.0, 0.09]]",
        "M = [[0.16, 0.0], [0.0, 0.36]]",
    ));
    let hold = (0.2, 3);
    let spec = RunSpec {
        filter: FilterKind::Joint,
        ..RunSpec::default()
    };
    let (right, _) = held_out_run(&truth, &spec, &y, &u, hold);
    let tolerance = 8.0 * (2.0 / right.readings as f64).sqrt();
    assert!(
        (right.standardised - 1.0).abs() < tolerance,
        "true model: {right:?}"
    );
    // Readings noisier than the state moves between steps: the model's estimate beats the
    // interpolation of the noisy readings.
    assert!(right.rmse < right.interpolation_rmse, "{right:?}");
    assert!(right.rmse < right.last_reading_rmse, "{right:?}");
    let (too_large, _) = held_out_run(&wrong, &spec, &y, &u, hold);
    assert!(
        too_large.standardised < 0.5,
        "M four times too large: {too_large:?}"
    );
}

#[test]
fn the_command_line_prints_and_keeps_the_scores_and_refuses_bad_shares() {
    let dir = tempfile::tempdir().unwrap();
    let config = shipped_config("platoon.toml");
    let meas = dir.path().join("run");
    let simulated = sisfilt()
        .args(["-q", "simulate"])
        .arg(&config)
        .arg("--out")
        .arg(&meas)
        .output()
        .unwrap();
    assert!(simulated.status.success());
    let estimate_with = |args: &[&str]| {
        sisfilt()
            .arg("estimate")
            .arg("--meas")
            .arg(meas.join("measurements.csv"))
            .args(args)
            .output()
            .unwrap()
    };
    let json = dir.path().join("e.json");
    let out = estimate_with(&[
        "--hold-out",
        "0.2",
        "--seed",
        "5",
        "--out",
        json.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stderr = String::from_utf8(out.stderr).unwrap();
    let line = stderr
        .lines()
        .find(|l| l.starts_with("held out: "))
        .unwrap_or_else(|| panic!("no held-out line in {stderr}"));
    assert!(
        line.contains("seed 5") && line.contains("linear interpolation"),
        "{line}"
    );
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let held: HeldOutReport = serde_json::from_value(doc["held_out"].clone()).unwrap();
    assert_eq!((held.share, held.seed), (0.2, 5));
    // 20 cars × 200 steps × 2 readings, of which about 85 % arrived and a fifth are held out.
    assert!((1000..2400).contains(&held.readings), "{held:?}");
    assert!(
        line.contains(&format!("{} readings", held.readings)),
        "{line}"
    );

    let again = estimate_with(&["--hold-out", "0.2", "--seed", "5", "--format", "json"]);
    let again: serde_json::Value = serde_json::from_slice(&again.stdout).unwrap();
    assert_eq!(
        again["held_out"], doc["held_out"],
        "the same seed, the same readings"
    );
    let other = estimate_with(&["--hold-out", "0.2", "--seed", "6", "--format", "json"]);
    let other: serde_json::Value = serde_json::from_slice(&other.stdout).unwrap();
    assert_ne!(other["held_out"]["rmse"], doc["held_out"]["rmse"]);
    let plain = estimate_with(&["--format", "json"]);
    let plain: serde_json::Value = serde_json::from_slice(&plain.stdout).unwrap();
    assert!(plain.get("held_out").is_none(), "no key without --hold-out");

    for (args, names) in [
        (&["--hold-out", "1.5"][..], "--hold-out"),
        (&["--hold-out", "0"][..], "--hold-out"),
        (&["--hold-out", "many"][..], "--hold-out"),
        (&["--seed", "3"][..], "--hold-out"),
        (&["--hold-out", "0.1", "--predicted"][..], "--predicted"),
    ] {
        let out = estimate_with(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let line = one_error_line(&out.stderr);
        assert!(line.contains(names), "{args:?}: {line}");
    }
}
