//! The run through the library on arrays (`sisfilt::run::estimate`) against the command line
//! on the same files: every filter, update, dropout mode, predicted and smoothed output on
//! the shipped configs gives the same estimates, `π`, log-likelihood and accuracy.

use std::path::Path;

use sisfilt::filter::{Dropouts, FilterKind, Update};
use sisfilt::io::estimates::EstimatesDocument;
use sisfilt::run::{RunSpec, estimate};

use crate::common::{shipped_config, shipped_model, sisfilt};

/// Every value of a `t,i,…` CSV after `t` and `i`, row after row (an empty cell is NaN).
fn csv_values(path: &Path) -> Vec<f64> {
    let mut reader = csv::Reader::from_path(path).unwrap();
    let mut out = Vec::new();
    for record in reader.records() {
        for cell in record.unwrap().iter().skip(2) {
            out.push(if cell.is_empty() {
                f64::NAN
            } else {
                cell.parse().unwrap()
            });
        }
    }
    out
}

/// `a` and `b` agree to the last bits a JSON round trip may change.
fn assert_close(a: f64, b: f64, what: &str) {
    let scale = a.abs().max(b.abs());
    assert!(
        (a - b).abs() <= 1e-15 * scale || (a.is_nan() && b.is_nan()),
        "{what}: library {a:e}, command line {b:e}"
    );
}

/// The command line's estimates JSON of `args` on the simulation in `dir`.
fn command_line(config: &Path, dir: &Path, args: &[&str]) -> EstimatesDocument {
    let out = dir.join("estimates.json");
    sisfilt()
        .arg("-q")
        .arg("estimate")
        .arg("--config")
        .arg(config)
        .arg("--meas")
        .arg(dir.join("measurements.csv"))
        .arg("--truth")
        .arg(dir.join("truth.csv"))
        .arg("--out")
        .arg(&out)
        .args(args)
        .assert()
        .success();
    serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap()
}

fn same_runs(config_name: &str) {
    let config = shipped_config(config_name);
    let model = shipped_model(config_name);
    let (n, big_n) = (model.dims.n, model.subsystems);
    let tmp = tempfile::tempdir().unwrap();
    let (unknown, known) = (tmp.path().join("unknown"), tmp.path().join("known"));
    for (dir, mark) in [(&unknown, false), (&known, true)] {
        let mut cmd = sisfilt();
        cmd.arg("-q")
            .arg("simulate")
            .arg(&config)
            .arg("--out")
            .arg(dir);
        if mark {
            cmd.arg("--mark-missing");
        }
        cmd.assert().success();
    }
    let flag = |v: &str| v.to_string();
    let mut cases: Vec<(RunSpec, Vec<String>)> = Vec::new();
    for filter in [
        FilterKind::Distributed,
        FilterKind::Joint,
        FilterKind::Centralized,
    ] {
        let name = sisfilt::choice::Choice::name(filter);
        for update in [Update::Linear, Update::Mixture] {
            let base = RunSpec {
                filter,
                update,
                ..RunSpec::default()
            };
            let update_name = sisfilt::choice::Choice::name(update);
            let args = vec![
                flag("--filter"),
                flag(name),
                flag("--update"),
                flag(update_name),
            ];
            cases.push((base.clone(), args.clone()));
            cases.push((
                RunSpec {
                    predicted: true,
                    ..base.clone()
                },
                [args.clone(), vec![flag("--predicted")]].concat(),
            ));
            cases.push((
                RunSpec {
                    smooth: true,
                    ..base
                },
                [args, vec![flag("--smooth")]].concat(),
            ));
        }
        let known_spec = RunSpec {
            filter,
            dropouts: Dropouts::Known,
            ..RunSpec::default()
        };
        let args = vec![
            flag("--filter"),
            flag(name),
            flag("--dropouts"),
            flag("known"),
        ];
        cases.push((known_spec.clone(), args.clone()));
        cases.push((
            RunSpec {
                smooth: true,
                ..known_spec
            },
            [args, vec![flag("--smooth")]].concat(),
        ));
    }
    for (spec, args) in cases {
        let dir = if spec.dropouts == Dropouts::Known {
            &known
        } else {
            &unknown
        };
        let what = format!("{config_name} {}", args.join(" "));
        let y = csv_values(&dir.join("measurements.csv"));
        let truth = csv_values(&dir.join("truth.csv"));
        let u = (model.dims.m > 0).then(|| csv_values(&dir.join("inputs.csv")));
        let lib = estimate(
            &model,
            &spec.check().unwrap(),
            &y,
            u.as_deref(),
            Some(&truth),
        )
        .unwrap();
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let cli = command_line(&config, dir, &args);
        assert_eq!(cli.estimates.len(), lib.report.steps * big_n, "{what}");
        let arrival_col = cli.columns.iter().position(|c| c == "arrival");
        assert_eq!(arrival_col.is_some(), lib.arrival.is_some(), "{what}");
        for (row, values) in cli.estimates.iter().enumerate() {
            let value = |col: usize| values[col].unwrap();
            for k in 0..n {
                assert_close(lib.x[row * n + k], value(2 + k), &what);
            }
            // The CSV's P columns are the upper triangle, row by row; the blocks are
            // column-major.
            let mut col = 2 + n;
            for r in 0..n {
                for c in r..n {
                    assert_close(lib.p[row * n * n + c * n + r], value(col), &what);
                    col += 1;
                }
            }
            if let (Some(col), Some(pi)) = (arrival_col, &lib.arrival) {
                assert_close(pi[row], value(col), &what);
            }
        }
        let (lib_sum, cli_sum) = (&lib.report.summary, &cli.summary);
        assert_eq!(lib_sum.loglik.is_some(), cli_sum.loglik.is_some(), "{what}");
        if let (Some(a), Some(b)) = (lib_sum.loglik, cli_sum.loglik) {
            assert_close(a, b, &what);
        }
        let (a, b) = (
            lib_sum.accuracy.as_ref().unwrap(),
            cli_sum.accuracy.as_ref().unwrap(),
        );
        assert_close(a.rmse_overall, b.rmse_overall, &what);
        assert_eq!(a.anees.is_some(), b.anees.is_some(), "{what}");
        if let (Some(x), Some(y)) = (a.anees, b.anees) {
            assert_close(x, y, &what);
        }
        assert_eq!(a.terms, b.terms, "{what}");
        assert_eq!(
            lib_sum.detection.is_some(),
            cli_sum.detection.is_some(),
            "{what}"
        );
    }
}

#[test]
fn the_library_run_on_arrays_equals_the_command_line_on_platoon() {
    same_runs("platoon.toml");
}

#[test]
fn the_library_run_on_arrays_equals_the_command_line_on_paper() {
    same_runs("paper.toml");
}

#[test]
fn the_library_run_on_arrays_equals_the_command_line_on_heat_rod() {
    same_runs("heat_rod.toml");
}

/// A spec the library refuses is refused once, before anything runs, with one message.
#[test]
fn an_invalid_spec_is_refused_before_the_run() {
    let spec = RunSpec {
        update: Update::Mixture,
        dropouts: Dropouts::Known,
        ..RunSpec::default()
    };
    let refused = spec.check().unwrap_err();
    assert_eq!(
        refused.to_string(),
        "update = mixture needs dropouts = unknown: with known dropouts there is nothing to detect"
    );
}

/// The chain of [`model_in_code`], as TOML.
const CHAIN_TOML: &str = r#"
subsystems = 4
steps = 5
seed = 3

[interconnection]
plus = 1
minus = 1

[model]
A = [[0.9, 0.1], [0.0, 0.8]]
B = [[0.1, 0.0], [0.0, 0.1]]
D = [[0.5, 0.0], [0.0, 0.5]]
G = [[0.0, 0.0], [0.0, 0.0]]
J = [[1.0, 0.0]]
M = [[0.05]]
Q = [[0.01, 0.0], [0.0, 0.01]]

[dropout]
p = [0.9, 0.8, 0.7, 0.6]

[initial]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[override]]
subsystems = [2, 3]
steps = [2, 4]
M = [[0.2]]
"#;

/// The same chain as [`CHAIN_TOML`], built in code, with `M` as given.
fn model_in_code(m: f64) -> sisfilt::config::RawConfig {
    use sisfilt::config::*;
    RawConfig {
        subsystems: 4,
        steps: Some(5),
        seed: 3,
        interconnection: RawInterconnection { plus: 1, minus: 1 },
        model: RawModel {
            A: RawMatrix(vec![vec![0.9, 0.1], vec![0.0, 0.8]]),
            B: Some(RawMatrix(vec![vec![0.1, 0.0], vec![0.0, 0.1]])),
            C: None,
            D: Some(RawMatrix(vec![vec![0.5, 0.0], vec![0.0, 0.5]])),
            G: None,
            H: None,
            J: RawMatrix(vec![vec![1.0, 0.0]]),
            R: None,
            M: RawMatrix(vec![vec![m]]),
            Q: Some(RawMatrix(vec![vec![0.01, 0.0], vec![0.0, 0.01]])),
        },
        dropout: RawDropout {
            p: RawProbability::PerSubsystem(vec![0.9, 0.8, 0.7, 0.6]),
        },
        initial: RawInitial {
            mean: None,
            cov: RawMatrix(vec![vec![1.0, 0.0], vec![0.0, 1.0]]),
        },
        input: None,
        overrides: vec![RawOverride {
            subsystems: Some(RawRanges::Range([2, 3])),
            steps: Some(RawRanges::Range([2, 4])),
            A: None,
            B: None,
            C: None,
            D: None,
            G: None,
            H: None,
            J: None,
            R: None,
            M: Some(RawMatrix(vec![vec![0.2]])),
            Q: None,
            p: None,
            measured: None,
            initial: None,
        }],
    }
}

/// A model built in code is the model of the same TOML, and is refused with the same message.
#[test]
fn a_model_built_in_code_equals_the_one_read_from_the_same_toml() {
    use sisfilt::model::Model;
    let from_toml = Model::from_toml_str("chain", Path::new("."), CHAIN_TOML).unwrap();
    let in_code = Model::from_raw("chain", model_in_code(0.05)).unwrap();
    assert_eq!(format!("{in_code:?}"), format!("{from_toml:?}"));
    // The TOML it records reads back as the same model.
    let src =
        sisfilt::config::ConfigSource::from_raw("chain", ".".into(), model_in_code(0.05)).unwrap();
    let again = Model::from_toml_str("chain", Path::new("."), &src.text).unwrap();
    assert_eq!(format!("{again:?}"), format!("{from_toml:?}"));

    let bad_toml = CHAIN_TOML.replace("M = [[0.05]]", "M = [[-1.0]]");
    let refused_toml = Model::from_toml_str("chain", Path::new("."), &bad_toml).unwrap_err();
    let refused_code = Model::from_raw("chain", model_in_code(-1.0)).unwrap_err();
    assert_eq!(refused_code.to_string(), refused_toml.to_string());
    assert!(
        refused_code.to_string().starts_with("chain: model.M: "),
        "{refused_code}"
    );
}

/// A filter and a smoother keep a share of their model and borrow nothing: built from a model
/// that is dropped at once, and moved to another thread, they run as the ones built from a
/// model that lives on.
#[test]
fn filters_and_smoothers_outlive_the_model_they_were_built_from() {
    let model = shipped_model("platoon.toml");
    let run = crate::common::simulate_steps(&model, 20, 4);
    let spec = RunSpec {
        filter: FilterKind::Joint,
        update: Update::Mixture,
        ..RunSpec::default()
    }
    .check()
    .unwrap();
    let (mut kept, kept_smoother) = {
        let short_lived = shipped_model("platoon.toml");
        (
            spec.build_filter(&short_lived).unwrap(),
            spec.build_smoother(&short_lived).unwrap(),
        )
    };
    let (mut fresh, mut fresh_smoother) = (
        spec.build_filter(&model).unwrap(),
        spec.build_smoother(&model).unwrap(),
    );
    let (ys, us) = (run.y.clone(), run.u.clone());
    let elsewhere = std::thread::spawn(move || {
        let mut kept_smoother = kept_smoother;
        let mut filtered = Vec::new();
        for (y, u) in ys.iter().zip(&us) {
            kept.step(y, u).unwrap();
            filtered.push(kept.filtered().0.to_vec());
            kept_smoother.step(y, u).unwrap();
        }
        (filtered, kept_smoother.finish().unwrap())
    });
    let (filtered, a) = elsewhere.join().unwrap();
    for ((y, u), kept_x) in run.y.iter().zip(&run.u).zip(&filtered) {
        fresh.step(y, u).unwrap();
        fresh_smoother.step(y, u).unwrap();
        assert_eq!(kept_x.as_slice(), fresh.filtered().0);
    }
    let b = fresh_smoother.finish().unwrap();
    assert_eq!(a.x, b.x);
    assert_eq!(a.p, b.p);
}

/// Inputs given as an array run as the inputs the model generates, and a model whose inputs
/// are a file is not opened by the run: it asks for the array.
#[test]
fn inputs_as_an_array_equal_the_generated_ones_and_files_are_read_at_the_edge() {
    let model = shipped_model("heat_rod.toml");
    let run = crate::common::simulate_steps(&model, 30, 8);
    let y: Vec<f64> = run.y.concat();
    // The config's sine, u(t, i) = a sin(2π t / period + phase i), written out here.
    let (a, period, phase) = (10.0_f64, 100.0_f64, 0.2_f64);
    let m = model.dims.m;
    let mut u = Vec::new();
    for t in 1..=30 {
        for i in 1..=model.subsystems {
            let value =
                a * (2.0 * std::f64::consts::PI * t as f64 / period + phase * i as f64).sin();
            u.extend(std::iter::repeat_n(value, m));
        }
    }
    let spec = RunSpec::default().check().unwrap();
    let generated = estimate(&model, &spec, &y, None, None).unwrap();
    let given = estimate(&model, &spec, &y, Some(&u), None).unwrap();
    for (g, h) in generated.x.iter().zip(&given.x) {
        assert!((g - h).abs() <= 1e-12 * g.abs().max(1.0), "{g} {h}");
    }
    let refused = estimate(&model, &spec, &y, Some(&u[1..]), None).unwrap_err();
    assert!(
        refused.to_string().starts_with("u: expected T × N × m"),
        "{refused}"
    );
    let mut bad_u = u.clone();
    bad_u[m * model.subsystems + 2 * m] = f64::NAN;
    let refused = estimate(&model, &spec, &y, Some(&bad_u), None).unwrap_err();
    assert!(
        refused
            .to_string()
            .starts_with("u: t = 2, i = 3, element 1: expected a finite number"),
        "{refused}"
    );

    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(shipped_config("heat_rod.toml")).unwrap();
    let text = text.replace("kind = \"sine\"", "kind = \"file\"\npath = \"u.csv\"");
    let from_file = sisfilt::model::Model::from_toml_str("rod", tmp.path(), &text).unwrap();
    let refused = estimate(&from_file, &spec, &y, None, None).unwrap_err();
    assert!(refused.to_string().contains("u.csv"), "{refused}");
}

/// `evaluate` on a config whose inputs are a file (read once, at the edge) gives the figures
/// of the same config with the generated inputs that file holds.
#[test]
fn evaluate_reads_an_inputs_file_once_and_scores_as_with_generated_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let config = shipped_config("platoon.toml");
    sisfilt()
        .args(["-q", "simulate"])
        .arg(&config)
        .arg("--out")
        .arg(tmp.path())
        .assert()
        .success();
    let text = std::fs::read_to_string(&config).unwrap();
    let file_config = tmp.path().join("file_inputs.toml");
    std::fs::write(
        &file_config,
        text.replace("kind = \"sine\"", "kind = \"file\"\npath = \"inputs.csv\""),
    )
    .unwrap();
    let figures = |config: &Path, out: &str| -> serde_json::Value {
        let out = tmp.path().join(out);
        sisfilt()
            .args(["-q", "evaluate"])
            .arg(config)
            .args([
                "--runs",
                "3",
                "--filters",
                "distributed,joint-mixture,centralized",
                "--out",
            ])
            .arg(&out)
            .assert()
            .success();
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap();
        json["filters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["accuracy"].clone())
            .collect()
    };
    let (generated, read) = (figures(&config, "g.json"), figures(&file_config, "f.json"));
    assert_eq!(generated, read);
    assert!(generated[0]["rmse_overall"].as_f64().unwrap() > 0.0);
}

/// The notes of a run come as values whose text names settings, not flags: `paper.toml` has
/// `Q = 0` on a coupled chain, which the distributed filter's covariance cannot take.
#[test]
fn a_run_notes_name_settings() {
    use sisfilt::run::Note;
    let model = shipped_model("paper.toml");
    let run = crate::common::simulate_steps(&model, 10, 2);
    let spec = RunSpec::default().check().unwrap();
    let done = estimate(&model, &spec, &run.y.concat(), None, None).unwrap();
    assert_eq!(done.notes, [Note::OverconfidentDistributed]);
    let text = done.notes[0].to_string();
    assert!(
        text.contains("filter = joint") && !text.contains("--"),
        "{text}"
    );
    let joint = RunSpec {
        filter: FilterKind::Joint,
        ..RunSpec::default()
    };
    let quiet = estimate(&model, &joint.check().unwrap(), &run.y.concat(), None, None).unwrap();
    assert!(quiet.notes.is_empty(), "{:?}", quiet.notes);
}

/// Measurements in memory follow the rule of the file: NaN marks an element not in the data
/// (in both dropout modes), and anything else that is not finite is refused naming `t`, `i`
/// and the element.
#[test]
fn measurements_in_memory_are_checked_as_the_file_is() {
    let model = shipped_model("platoon.toml");
    let run = crate::common::simulate_steps(&model, 5, 3);
    let mut y = run.y.concat();
    let q = model.dims.q;
    let (t, i) = (3, 7);
    let first = ((t - 1) * model.subsystems + (i - 1)) * q;
    y[first..first + q].fill(f64::NAN);
    let unknown = RunSpec::default().check().unwrap();
    let gapped = estimate(&model, &unknown, &y, None, None).unwrap();
    assert!(gapped.nis[(t - 1) * model.subsystems + i - 1].is_nan());
    let known = RunSpec {
        dropouts: Dropouts::Known,
        ..RunSpec::default()
    };
    assert!(estimate(&model, &known.check().unwrap(), &y, None, None).is_ok());
    y[0] = f64::INFINITY;
    let refused = estimate(&model, &known.check().unwrap(), &y, None, None).unwrap_err();
    assert!(
        refused
            .to_string()
            .starts_with("y: t = 1, i = 1, element 1: expected a finite number or NaN (not in the data), found inf"),
        "{refused}"
    );
}
