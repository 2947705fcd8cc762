//! The shipped real recording (`data/sparkling/`, the README's "A real recording"): the file
//! is what its SOURCE.md says, and the README's steps on it give what the README says: `check`
//! warns of nothing (p = 1), the joint filter scores as the exact centralized one on readings
//! held out of both, the verdict names the noise that differs by depth, and the model `fit`
//! gives each depth's own `Q` (`--params 'Q[i],M'`) no longer does, and claims honest
//! variances.

use std::path::{Path, PathBuf};

use sisfilt::accuracy::HeldOutReport;

use crate::common::{Csv, sisfilt};

fn lake(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("data/sparkling")
        .join(name)
}

/// Each sensor's readings, `readings[i][t]` (NaN where the file has none).
fn readings() -> Vec<Vec<f64>> {
    let csv = Csv::read(&lake("measurements.csv"));
    csv.assert_index(3000, 20);
    let mut readings = vec![vec![f64::NAN; 3000]; 20];
    for row in &csv.rows {
        let (t, i): (usize, usize) = (row[0].parse().unwrap(), row[1].parse().unwrap());
        if !row[2].is_empty() {
            readings[i - 1][t - 1] = row[2].parse().unwrap();
        }
    }
    readings
}

#[test]
fn the_recording_is_what_its_source_says() {
    let readings = readings();
    let missing: usize = readings
        .iter()
        .map(|r| r.iter().filter(|v| v.is_nan()).count())
        .sum();
    assert_eq!(missing, 2963, "4.94 % of 60 000 cells");
    let outage = |t: usize| readings.iter().all(|r| r[t - 1].is_nan());
    let outages: Vec<usize> = (1..=3000).filter(|&t| outage(t)).collect();
    let expected: Vec<usize> = (175..=192).chain(223..=286).collect();
    assert_eq!(outages, expected, "two outages of the whole chain");
    // The first readings are the model's initial means.
    let model = std::fs::read_to_string(lake("model.toml")).unwrap();
    assert!(model.contains("[[6.555], [6.552], [6.445]"), "{model}");
    assert_eq!(readings[0][0], 6.555);
    assert_eq!(readings[19][0], 4.615);
}

/// `model.toml` with each depth's own `Q`, and `M`, as the README's `fit --params 'Q[i],M'`
/// gives it: the fitted config and the report.
fn by_depth(dir: &Path) -> (PathBuf, serde_json::Value) {
    let path = dir.join("by-depth.toml");
    let out = sisfilt()
        .arg("fit")
        .arg("--config")
        .arg(lake("model.toml"))
        .arg("--meas")
        .arg(lake("measurements.csv"))
        .args(["--params", "Q[i],M", "--format", "json", "-q", "--out"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    (path, serde_json::from_slice(&out.stdout).unwrap())
}

/// `estimate --hold-out 0.1` of `config` with `filter`: its held-out scores and its warnings.
fn held_out(config: &Path, filter: &str, dir: &Path) -> (HeldOutReport, Vec<String>) {
    let json = dir.join(format!("{filter}.json"));
    let out = sisfilt()
        .arg("estimate")
        .arg("--config")
        .arg(config)
        .arg("--meas")
        .arg(lake("measurements.csv"))
        .args(["--filter", filter, "--hold-out", "0.1", "--out"])
        .arg(&json)
        .output()
        .unwrap();
    let stderr = String::from_utf8(out.stderr).unwrap();
    assert!(out.status.success(), "{stderr}");
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let report = serde_json::from_value(doc["held_out"].clone()).unwrap();
    let warnings = stderr
        .lines()
        .filter(|l| l.starts_with("warning: "))
        .map(str::to_string)
        .collect();
    (report, warnings)
}

#[test]
fn the_readmes_steps_on_the_lake_give_what_it_says() {
    let dir = tempfile::tempdir().unwrap();
    let check = sisfilt()
        .arg("check")
        .arg(lake("model.toml"))
        .output()
        .unwrap();
    assert!(check.status.success());
    let stdout = String::from_utf8(check.stdout).unwrap();
    assert!(
        stdout.contains("spectral radius of A_eff 1.000000 (exact"),
        "{stdout}"
    );
    assert!(check.stderr.is_empty(), "p = 1: nothing to warn of");

    let (joint, warnings) = held_out(&lake("model.toml"), "joint", dir.path());
    let (exact, _) = held_out(&lake("model.toml"), "centralized", dir.path());
    assert_eq!(joint.readings, exact.readings);
    assert!(
        (joint.rmse - exact.rmse).abs() < 1e-3 * exact.rmse,
        "joint {joint:?}, centralized {exact:?}"
    );
    let form = |w: &&String| w.contains("(its form, not its noise levels)");
    let stand_out = |w: &&String| w.contains("some subsystems stand out from the others: i = 2");
    assert!(warnings.iter().any(|w| form(&w)), "{warnings:?}");
    assert!(warnings.iter().any(|w| stand_out(&w)), "{warnings:?}");
    assert_eq!(warnings.len(), 2, "{warnings:?}");

    let (by_depth, report) = by_depth(dir.path());
    // Each depth's own Q, with an interval, from 2.7e-4 at 18 m to 6.9e-2 in the thermocline.
    let parameters = report["parameters"].as_array().unwrap();
    let q: Vec<f64> = (parameters.iter().skip(1))
        .map(|p| p["estimate"].as_f64().unwrap())
        .collect();
    assert_eq!(q.len(), 20);
    assert!(parameters.iter().skip(1).all(|p| p["ci_low"].is_f64()));
    let (lo, hi) = q
        .iter()
        .fold((f64::MAX, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(lo < 1e-3 && hi > 5e-2, "{q:?}");
    let loglik = report["loglik"].as_f64().unwrap();
    assert!(loglik > 42_000.0, "{loglik}");
    let (own, warnings) = held_out(&by_depth, "joint", dir.path());
    assert_eq!(
        warnings.len(),
        1,
        "only the form is left with each depth's own Q: {warnings:?}"
    );
    assert!(form(&&warnings[0]), "{warnings:?}");
    assert!(
        (own.standardised - 1.0).abs() < 0.05,
        "the claimed variances are honest: {own:?}"
    );
    assert!(own.rmse <= joint.rmse, "{own:?} against {joint:?}");
}
