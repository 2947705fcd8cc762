//! The catalogue of bad inputs (`tests/bad_inputs/`, SPEC §6–§7) and the broken-pipe check.
//!
//! Each folder `NNN_name/` of the catalogue is one case: the files it needs (`config.toml`,
//! `measurements.csv`, …) and a `case.toml` saying how to run the binary and what it must do:
//!
//! ```toml
//! # what is wrong (a comment)
//! args = ["estimate", "--config", "config.toml", "--meas", "measurements.csv", "--out", "out.csv"]
//! exit = 2
//! message = "measurements.csv: line 5"   # a fragment of the error line
//! contains = ["--dropouts known"]        # optional: more fragments
//! stdin = "measurements.csv"             # optional: a file of the case fed to standard input
//! ```
//!
//! The runner copies the folder (without `case.toml`) into a temporary folder, runs `sisfilt`
//! there with `RUST_BACKTRACE=1`, and checks the exit code; that standard output is empty; that
//! standard error is exactly one line, starting with `error: `, holding every fragment and no
//! panic or backtrace; and that the folder is byte-for-byte what it was: no output file and no
//! temporary file was left, and a pre-existing output (an `out.csv` in the case) is intact.
//! Every case runs; the test fails listing all the cases that went wrong.

mod common;

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use common::sisfilt;
use serde::Deserialize;

/// At least this many cases (issue 7).
const MIN_CASES: usize = 40;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Case {
    args: Vec<String>,
    exit: i32,
    message: String,
    #[serde(default)]
    contains: Vec<String>,
    #[serde(default)]
    stdin: Option<String>,
}

fn catalogue_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/bad_inputs")
}

/// The case folders, in name order.
fn case_dirs() -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(catalogue_dir())
        .expect("tests/bad_inputs exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    dirs
}

/// Copies `src` into `dst` recursively, leaving out the top-level `case.toml`.
fn copy_case(src: &Path, dst: &Path, top: bool) {
    std::fs::create_dir_all(dst).unwrap();
    for entry in std::fs::read_dir(src).unwrap() {
        let entry = entry.unwrap();
        let (from, to) = (entry.path(), dst.join(entry.file_name()));
        if top && entry.file_name() == "case.toml" {
            continue;
        }
        if from.is_dir() {
            copy_case(&from, &to, false);
        } else {
            std::fs::copy(&from, &to).unwrap();
        }
    }
}

/// Every file (with its bytes) and folder (`None`) under `dir`, by relative path.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, Option<Vec<u8>>> {
    fn walk(root: &Path, dir: &Path, out: &mut BTreeMap<PathBuf, Option<Vec<u8>>>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            let rel = path.strip_prefix(root).unwrap().to_path_buf();
            if path.is_dir() {
                out.insert(rel, None);
                walk(root, &path, out);
            } else {
                out.insert(rel, Some(std::fs::read(&path).unwrap()));
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// What changed between two snapshots, as one line per path.
fn changes(
    before: &BTreeMap<PathBuf, Option<Vec<u8>>>,
    after: &BTreeMap<PathBuf, Option<Vec<u8>>>,
) -> Vec<String> {
    let mut out = Vec::new();
    for (path, content) in after {
        match before.get(path) {
            None => out.push(format!("created {}", path.display())),
            Some(old) if old != content => out.push(format!("changed {}", path.display())),
            _ => {}
        }
    }
    for path in before.keys().filter(|p| !after.contains_key(*p)) {
        out.push(format!("removed {}", path.display()));
    }
    out
}

/// Runs one case; `Err` lists everything that was wrong.
fn run_case(dir: &Path) -> Result<(), Vec<String>> {
    let spec = std::fs::read_to_string(dir.join("case.toml"))
        .map_err(|e| vec![format!("case.toml: {e}")])?;
    let case: Case = toml::from_str(&spec).map_err(|e| vec![format!("case.toml: {e}")])?;
    if case.message.trim().is_empty() {
        return Err(vec!["case.toml: the message fragment is empty".into()]);
    }
    let tmp = tempfile::tempdir().unwrap();
    let work = tmp.path().join("case");
    copy_case(dir, &work, true);
    let before = snapshot(&work);

    let mut cmd = sisfilt();
    cmd.current_dir(&work)
        .args(&case.args)
        .env("RUST_BACKTRACE", "1")
        .timeout(Duration::from_secs(120));
    match &case.stdin {
        Some(file) => cmd.write_stdin(std::fs::read(work.join(file)).unwrap()),
        None => cmd.write_stdin(Vec::new()),
    };
    let output = cmd.output().map_err(|e| vec![format!("cannot run: {e}")])?;

    let mut problems = Vec::new();
    let stderr = String::from_utf8_lossy(&output.stderr);
    if output.status.code() != Some(case.exit) {
        problems.push(format!(
            "exit code {:?}, expected {}",
            output.status.code(),
            case.exit
        ));
    }
    if !output.stdout.is_empty() {
        problems.push(format!(
            "standard output is not empty: {:?}",
            String::from_utf8_lossy(&output.stdout)
        ));
    }
    let lines: Vec<&str> = stderr.lines().collect();
    if lines.len() != 1 || !stderr.ends_with('\n') {
        problems.push(format!(
            "standard error is not exactly one line: {stderr:?}"
        ));
    }
    if !stderr.starts_with("error: ") {
        problems.push(format!(
            "standard error does not start with `error: `: {stderr:?}"
        ));
    }
    for fragment in std::iter::once(&case.message).chain(&case.contains) {
        if !stderr.contains(fragment.as_str()) {
            problems.push(format!("standard error lacks {fragment:?}: {stderr:?}"));
        }
    }
    for bad in ["panicked", "backtrace", "RUST_BACKTRACE"] {
        if stderr.contains(bad) {
            problems.push(format!("standard error mentions {bad:?}: {stderr:?}"));
        }
    }
    let changed = changes(&before, &snapshot(&work));
    if !changed.is_empty() {
        problems.push(format!("the folder changed: {}", changed.join(", ")));
    }
    if problems.is_empty() {
        Ok(())
    } else {
        Err(problems)
    }
}

#[test]
fn every_bad_input_is_one_error_line_exit_2_and_leaves_files_alone() {
    let dirs = case_dirs();
    assert!(
        dirs.len() >= MIN_CASES,
        "only {} cases in {}",
        dirs.len(),
        catalogue_dir().display()
    );
    let mut failures = Vec::new();
    for dir in &dirs {
        let name = dir.file_name().unwrap().to_string_lossy().to_string();
        if let Err(problems) = run_case(dir) {
            failures.push(format!("{name}:\n    {}", problems.join("\n    ")));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} bad-input cases failed:\n{}",
        failures.len(),
        dirs.len(),
        failures.join("\n")
    );
}

/// The catalogue's folder names are `NNN_name` with distinct numbers, and every folder is a case.
#[test]
fn catalogue_is_well_formed() {
    let mut numbers = std::collections::BTreeSet::new();
    for dir in case_dirs() {
        let name = dir.file_name().unwrap().to_string_lossy().to_string();
        let (num, rest) = name.split_once('_').unwrap_or((&name, ""));
        assert!(
            num.len() == 3 && num.bytes().all(|b| b.is_ascii_digit()) && !rest.is_empty(),
            "{name}: expected NNN_name"
        );
        assert!(numbers.insert(num.to_string()), "{name}: number used twice");
        assert!(dir.join("case.toml").is_file(), "{name}: no case.toml");
    }
}

/// `estimate | head -c 64`: a reader that closes its end early is not an error (SPEC §7: exit
/// 0, nothing on standard error but warnings).
#[test]
fn estimate_into_a_pipe_closed_early_exits_0_quietly() {
    let tmp = tempfile::tempdir().unwrap();
    let config = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/heat_rod.toml");
    let rod = tmp.path().join("rod");
    sisfilt()
        .arg("simulate")
        .arg(&config)
        .arg("--out")
        .arg(&rod)
        .assert()
        .success();
    // 50 subsystems × 300 steps: over a megabyte of estimates, far more than a pipe holds.
    for format in ["csv", "json"] {
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_sisfilt"))
            .arg("estimate")
            .arg("--meas")
            .arg(rod.join("measurements.csv"))
            .args(["--format", format])
            .env_remove("RUST_BACKTRACE")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn sisfilt");
        let mut stdout = child.stdout.take().unwrap();
        let mut head = [0u8; 64];
        stdout.read_exact(&mut head).expect("the first bytes");
        drop(stdout);
        let output = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(
            output.status.success(),
            "{format}: {:?}, stderr {stderr:?}",
            output.status
        );
        assert!(
            !stderr.contains("error") && !stderr.contains("panicked"),
            "{format}: {stderr:?}"
        );
        assert!(
            stderr.lines().all(|l| l.starts_with("warning: ")),
            "{format}: {stderr:?}"
        );
        let head = String::from_utf8_lossy(&head);
        assert!(
            head.starts_with(if format == "csv" { "t,i,x1" } else { "{" }),
            "{head:?}"
        );
    }
}
