//! One meaning per flag (docs/theory.md §13): `-` is standard input or output wherever a file
//! is read or written, and refused where the argument is a folder; `evaluate --out -` writes
//! the JSON alone; runs from other simulations and configs other than the data's are named in
//! warnings; the notes of `evaluate` name only what `evaluate` accepts.

use std::path::Path;
use std::process::Output;

use crate::common::{one_error_line, shipped_config, sisfilt};

fn run(dir: &Path, args: &[&str], stdin: Option<&Path>) -> Output {
    let mut cmd = sisfilt();
    cmd.current_dir(dir).args(args);
    if let Some(path) = stdin {
        cmd.pipe_stdin(path).unwrap();
    }
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn stderr(out: &Output) -> String {
    String::from_utf8(out.stderr.clone()).unwrap()
}

/// The platoon simulated for `steps` steps with `seed` into `dir/name`.
fn simulate(dir: &Path, name: &str, seed: &str) {
    let config = shipped_config("platoon.toml");
    let args = ["-q", "simulate", config.to_str().unwrap(), "--steps", "20"];
    run(
        dir,
        &[&args[..], &["--seed", seed, "--out", name]].concat(),
        None,
    );
}

/// `plot … -` draws from standard input the figure it draws from a file (compared with a file
/// named `standard input`, the name a figure from standard input gives in its title).
#[test]
fn a_dash_reads_standard_input_in_every_plot() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    simulate(dir, "a", "1");
    for format in ["csv", "json"] {
        let file = format!("est.{format}");
        run(
            dir,
            &[
                "-q",
                "estimate",
                "--meas",
                "a/measurements.csv",
                "--nis",
                "--out",
                &file,
            ],
            None,
        );
        if format == "csv" {
            std::fs::copy(dir.join(&file), dir.join("standard input")).unwrap();
        }
    }
    for figure in [
        &["heatmap", "--truth", "a/truth.csv"][..],
        &["heatmap"][..],
        &[
            "series",
            "--subsystem",
            "3",
            "--state",
            "1",
            "--meas",
            "a/measurements.csv",
        ][..],
    ] {
        let draw = |estimates: &str, out: &str, stdin: Option<&str>| {
            let args = [
                &["plot"][..],
                figure,
                &["--estimates", estimates, "--out", out],
            ];
            run(dir, &args.concat(), stdin.map(|f| dir.join(f)).as_deref());
            std::fs::read(dir.join(out)).unwrap()
        };
        let from_file = draw("standard input", "file.svg", None);
        assert!(
            from_file == draw("-", "csv.svg", Some("est.csv")),
            "{figure:?}"
        );
        assert!(
            from_file == draw("-", "json.svg", Some("est.json")),
            "{figure:?}"
        );
    }
    let config = shipped_config("paper.toml");
    let args = ["-q", "evaluate", config.to_str().unwrap(), "--runs", "2"];
    run(
        dir,
        &[&args[..], &["--out", "standard input"]].concat(),
        None,
    );
    let draw = |input: &str, out: &str, stdin: Option<&Path>| {
        run(
            dir,
            &["plot", "evaluate", "--input", input, "--out", out],
            stdin,
        );
        std::fs::read(dir.join(out)).unwrap()
    };
    let from_stdin = draw("-", "e2.svg", Some(&dir.join("standard input")));
    assert!(draw("standard input", "e1.svg", None) == from_stdin);
}

/// `evaluate --out -` writes the JSON alone on standard output (the same as `--out FILE`,
/// clock readings aside) and the table on standard error.
#[test]
fn evaluate_out_dash_writes_only_json() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let config = shipped_config("paper.toml");
    let args = ["evaluate", config.to_str().unwrap(), "--runs", "2", "--out"];
    let piped = run(dir, &[&args[..], &["-"]].concat(), None);
    let json: serde_json::Value = serde_json::from_slice(&piped.stdout).unwrap();
    run(dir, &[&args[..], &["file.json"]].concat(), None);
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("file.json")).unwrap()).unwrap();
    let without_times = |v: &serde_json::Value| {
        v["filters"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| (f["name"].clone(), f["accuracy"].clone()))
            .collect::<Vec<_>>()
    };
    assert_eq!(without_times(&json), without_times(&file));
    assert!(stderr(&piped).contains("RMSE"), "{}", stderr(&piped));
}

#[test]
fn simulate_refuses_a_dash_for_its_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let out = sisfilt()
        .current_dir(tmp.path())
        .args(["simulate"])
        .arg(shipped_config("paper.toml"))
        .args(["--out", "-"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(one_error_line(&out.stderr).contains("--out -: simulate writes a folder"));
    assert!(!tmp.path().join("-").exists());
}

/// `--truth` from another simulation than `--meas`, and a `--config` other than the one that
/// simulated `--meas`, are named in a warning; the same simulation and config are not.
#[test]
fn other_simulations_and_configs_are_named() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    simulate(dir, "a", "1");
    simulate(dir, "b", "2");
    std::fs::create_dir(dir.join("c")).unwrap();
    for file in ["truth.csv", "run.json"] {
        std::fs::copy(dir.join("a").join(file), dir.join("c").join(file)).unwrap();
    }
    let estimate = |extra: &[&str]| {
        let args = [&["estimate", "--meas", "a/measurements.csv"][..], extra];
        stderr(&run(dir, &args.concat(), None))
    };
    let other = estimate(&["--truth", "b/truth.csv"]);
    assert!(
        other.contains("warning: --truth b/truth.csv: from another simulation than --meas a/measurements.csv (their run.json files differ: seed 2 against 1)"),
        "{other}"
    );
    for same in [
        &["--truth", "a/truth.csv"][..],
        &["--truth", "c/truth.csv"][..],
    ] {
        assert!(!estimate(same).contains("warning: --truth"), "{same:?}");
    }
    let platoon = shipped_config("platoon.toml");
    let heat_rod = shipped_config("heat_rod.toml");
    let same = estimate(&["--config", platoon.to_str().unwrap()]);
    assert!(!same.contains("warning: --config"), "{same}");
    // The heat rod's config has other sizes: the run stops, after the warning.
    let out = sisfilt()
        .current_dir(dir)
        .args(["estimate", "--meas", "a/measurements.csv", "--config"])
        .arg(&heat_rod)
        .output()
        .unwrap();
    assert!(
        stderr(&out).starts_with(&format!(
            "warning: --config {}: not the config that simulated --meas a/measurements.csv",
            heat_rod.display()
        )),
        "{}",
        stderr(&out)
    );
}

/// The skipped row of the paper's filter says why without naming an option `evaluate` does
/// not have.
#[test]
fn evaluate_notes_name_no_option_of_another_command() {
    let note = |config: &str, filters: &str| {
        let out = sisfilt()
            .args(["evaluate"])
            .arg(shipped_config(config))
            .args(["--runs", "1", "--filters", filters])
            .output()
            .unwrap();
        let table = String::from_utf8(out.stdout).unwrap();
        let note = table
            .lines()
            .find(|l| l.starts_with("note: distributed-paper"))
            .map(str::to_string);
        note.unwrap_or_else(|| panic!("no note on the paper's row: {table}"))
    };
    let skipped = note("platoon.toml", "distributed,distributed-paper");
    assert!(
        skipped.contains("G22 of subsystem 2 is singular") && !skipped.contains("--solver"),
        "{skipped}"
    );
    // On the long heat rod its transfer solver overflows: said without a flag either.
    let failed = note("heat_rod.toml", "distributed-paper");
    assert!(
        failed.contains("overflowed") && !failed.contains("--"),
        "{failed}"
    );
}

/// A config from standard input (`-`) is the config from its file: `check` says the same but
/// for the name, `simulate` writes the same files.
#[test]
fn a_config_can_come_from_standard_input() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let config = shipped_config("paper.toml");
    let path = config.to_str().unwrap();
    let (from_file, from_stdin) = (
        run(dir, &["check", path], None),
        run(dir, &["check", "-"], Some(&config)),
    );
    let body = |out: &Output| {
        String::from_utf8(out.stdout.clone())
            .unwrap()
            .lines()
            .skip(1)
            .map(str::to_string)
            .collect::<Vec<_>>()
    };
    assert_eq!(body(&from_file), body(&from_stdin));
    run(dir, &["-q", "simulate", path, "--out", "file"], None);
    run(
        dir,
        &["-q", "simulate", "-", "--out", "stdin"],
        Some(&config),
    );
    for name in ["truth.csv", "measurements.csv"] {
        assert!(
            std::fs::read(dir.join("file").join(name)).unwrap()
                == std::fs::read(dir.join("stdin").join(name)).unwrap(),
            "{name}"
        );
    }
}
