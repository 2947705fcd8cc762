//! The catalogue of bad inputs (`tests/bad_inputs/`, docs/theory.md §13), and what happens when a run
//! is cut short: a reader that closes its pipe early, a run killed in the middle.
//!
//! Each folder `NNN_name/` of the catalogue is one case: the files it needs (`config.toml`,
//! `measurements.csv`, …) and a `case.toml` saying how to run the binary and what it must do:
//!
//! ```toml
//! # what is wrong (a comment)
//! args = ["estimate", "--config", "config.toml", "--meas", "measurements.csv", "--out", "out.csv"]
//! exit = 2                               # 1 for a valid input on which the maths breaks down
//! message = "measurements.csv: line 5"   # a fragment of the error line
//! contains = ["--dropouts known"]        # optional: more fragments
//! stdin = "measurements.csv"             # optional: a file of the case fed to standard input
//! ```
//!
//! The runner copies the folder (without `case.toml`) into a temporary folder, runs `sisfilt`
//! there with `RUST_BACKTRACE=1` under a 2 GiB cap on its address space, and checks the exit code; that standard output is empty; that
//! standard error is exactly one line, starting with `error: `, holding every fragment and no
//! panic or backtrace; and that the folder is byte-for-byte what it was: no output file and no
//! temporary file was left, and every file that was there (inputs, a previous `out.csv`) keeps
//! its bytes and its mode, every symbolic link its target.
//! Every case runs; the test fails listing all the cases that went wrong.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::Duration;

use crate::common::sisfilt;
use serde::Deserialize;

/// At least this many cases (issue 7).
const MIN_CASES: usize = 40;

/// The address space every case runs in (`ulimit -v`, KiB): 2 GiB.
const MEMORY_CAP_KIB: u64 = 2 << 20;

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

/// Copies `src` into `dst` recursively, leaving out the top-level `case.toml`; symbolic links
/// are copied as links.
fn copy_case(src: &Path, dst: &Path, top: bool) {
    std::fs::create_dir_all(dst).unwrap();
    for entry in std::fs::read_dir(src).unwrap() {
        let entry = entry.unwrap();
        let (from, to) = (entry.path(), dst.join(entry.file_name()));
        if top && entry.file_name() == "case.toml" {
            continue;
        }
        let kind = entry.file_type().unwrap();
        if kind.is_symlink() {
            std::os::unix::fs::symlink(std::fs::read_link(&from).unwrap(), &to).unwrap();
        } else if kind.is_dir() {
            copy_case(&from, &to, false);
        } else {
            std::fs::copy(&from, &to).unwrap();
        }
    }
}

/// What a path under a case folder is: a folder, a symbolic link (its target), or a file (its
/// bytes); with its permission bits.
#[derive(PartialEq, Debug)]
enum Entry {
    Folder(u32),
    Link(PathBuf),
    File(Vec<u8>, u32),
}

type Snapshot = BTreeMap<PathBuf, Entry>;

/// Every entry under `dir`, by relative path.
fn snapshot(dir: &Path) -> Snapshot {
    use std::os::unix::fs::PermissionsExt;
    fn walk(root: &Path, dir: &Path, out: &mut Snapshot) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            let rel = path.strip_prefix(root).unwrap().to_path_buf();
            let meta = std::fs::symlink_metadata(&path).unwrap();
            let mode = meta.permissions().mode() & 0o7777;
            if meta.file_type().is_symlink() {
                out.insert(rel, Entry::Link(std::fs::read_link(&path).unwrap()));
            } else if meta.is_dir() {
                out.insert(rel, Entry::Folder(mode));
                walk(root, &path, out);
            } else {
                out.insert(rel, Entry::File(std::fs::read(&path).unwrap(), mode));
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// What changed between two snapshots, as one line per path.
fn changes(before: &Snapshot, after: &Snapshot) -> Vec<String> {
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

    // Under an address-space cap, so that a size the binary fails to refuse cannot take the
    // machine down: it aborts, and the case fails.
    let mut cmd = assert_cmd::Command::new("sh");
    cmd.current_dir(&work)
        .arg("-c")
        .arg(format!("ulimit -v {MEMORY_CAP_KIB} && exec \"$0\" \"$@\""))
        .arg(assert_cmd::cargo::cargo_bin("sisfilt"))
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
fn every_bad_input_is_one_error_line_with_its_exit_code_and_leaves_files_alone() {
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

/// `estimate | head -c 64`: a reader that closes its end early is not an error (docs/theory.md §13: exit
/// 0, nothing on standard error but warnings).
#[test]
fn estimate_into_a_pipe_closed_early_exits_0_quietly() {
    let tmp = tempfile::tempdir().unwrap();
    let config = crate::common::shipped_config("heat_rod.toml");
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

/// Spawns `sisfilt args` with standard output and standard error piped; the caller closes the
/// ends it wants closed right away, long before the child has parsed its config and written
/// anything (it has only just been exec'd when `spawn` returns).
fn spawn(args: &[&std::ffi::OsStr]) -> std::process::Child {
    std::process::Command::new(env!("CARGO_BIN_EXE_sisfilt"))
        .args(args)
        .env_remove("RUST_BACKTRACE")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn sisfilt")
}

fn assert_quiet_success(what: &str, output: &std::process::Output) {
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "{what}: {:?}, stderr {stderr:?}",
        output.status
    );
    assert!(
        stderr.lines().all(|l| l.starts_with("warning: ")),
        "{what}: {stderr:?}"
    );
}

/// `check` and `evaluate` print to standard output too: a reader that is already gone when
/// they print (`sisfilt check c.toml | true`) ends them quietly with exit 0, and `evaluate`
/// still writes its `--out` file.
#[test]
fn check_and_evaluate_into_a_closed_pipe_exit_0_quietly() {
    let configs = crate::common::configs_dir();
    let tmp = tempfile::tempdir().unwrap();
    let json = tmp.path().join("eval.json");
    let (rod, paper) = (configs.join("heat_rod.toml"), configs.join("paper.toml"));
    let runs: [Vec<&std::ffi::OsStr>; 2] = [
        vec!["check".as_ref(), rod.as_os_str()],
        vec![
            "evaluate".as_ref(),
            paper.as_os_str(),
            "--runs".as_ref(),
            "2".as_ref(),
            "--out".as_ref(),
            json.as_os_str(),
        ],
    ];
    for args in runs {
        let mut child = spawn(&args);
        drop(child.stdout.take());
        let output = child.wait_with_output().unwrap();
        assert_quiet_success(&format!("{args:?}"), &output);
    }
    let text = std::fs::read_to_string(&json).expect("evaluate wrote its JSON");
    let value: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert!(value.get("filters").is_some(), "{text}");
}

/// A closed standard error (`2>&-` into a dead pipe) loses the warnings and the accuracy line
/// but not the run: exit 0 and the estimates written (`eprintln!` would panic, exit 101).
#[test]
fn estimate_with_a_closed_standard_error_still_writes_its_output() {
    let tmp = tempfile::tempdir().unwrap();
    let config = crate::common::shipped_config("paper.toml");
    let run = tmp.path().join("run");
    sisfilt()
        .arg("simulate")
        .arg(&config)
        .arg("--out")
        .arg(&run)
        .assert()
        .success();
    let out = tmp.path().join("est.csv");
    let mut child = spawn(&[
        "estimate".as_ref(),
        "--meas".as_ref(),
        run.join("measurements.csv").as_os_str(),
        "--truth".as_ref(),
        run.join("truth.csv").as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    drop(child.stderr.take());
    let output = child.wait_with_output().unwrap();
    assert!(output.status.success(), "{:?}", output.status);
    let text = std::fs::read_to_string(&out).unwrap();
    // paper.toml: 6 subsystems × 150 steps, and the header.
    assert_eq!(text.lines().count(), 6 * 150 + 1);
}

/// Starts `estimate --meas - --out out.csv` in `dir` (which holds `config.toml` and a previous
/// `out.csv`), feeds it 20 000 steps of measurements through a pipe that stays open, and
/// returns once the run is under way (its temporary file exists): it is then waiting for more
/// input, so a signal sent now lands for certain in the middle of the run.
fn start_estimate_on_an_open_pipe(dir: &Path) -> (std::process::Child, std::process::ChildStdin) {
    use std::io::Write;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_sisfilt"))
        .current_dir(dir)
        .args(["estimate", "--config", "config.toml", "--meas", "-"])
        .args(["--out", "out.csv"])
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn sisfilt");
    let mut stdin = child.stdin.take().unwrap();
    let mut rows = String::from("t,i,y1\n");
    for t in 1..=20_000 {
        for i in 1..=3 {
            rows += &format!("{t},{i},{}\n", 0.01 * (t % 17) as f64 - 0.05 * i as f64);
        }
    }
    stdin.write_all(rows.as_bytes()).unwrap();
    stdin.flush().unwrap();
    let start = std::time::Instant::now();
    while temp_files(dir).is_empty() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "no temporary file appeared"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    (child, stdin)
}

/// The hidden temporary output files (`.sisfilt-*`) in `dir`.
fn temp_files(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with(".sisfilt-")
        })
        .collect()
}

/// A folder with the config of a 3-subsystem chain and the output of a previous run.
fn folder_with_previous_output() -> (tempfile::TempDir, &'static [u8]) {
    let tmp = tempfile::tempdir().unwrap();
    let case = catalogue_dir().join("055_csv_missing_row");
    std::fs::copy(case.join("config.toml"), tmp.path().join("config.toml")).unwrap();
    let previous: &[u8] = b"t,i,x1,x2,P1_1,P1_2,P2_2\nthe previous run\n";
    std::fs::write(tmp.path().join("out.csv"), previous).unwrap();
    (tmp, previous)
}

/// A run killed in the middle with SIGKILL (no chance to clean up) leaves the previous output
/// byte for byte as it was: `estimate` writes into a temporary file in the same folder and
/// renames it over `--out` only at the end. The temporary file stays behind, hidden and
/// recognisable by its name.
#[test]
fn estimate_killed_with_sigkill_leaves_the_previous_output_intact() {
    let (tmp, previous) = folder_with_previous_output();
    let (mut child, stdin) = start_estimate_on_an_open_pipe(tmp.path());
    child.kill().unwrap(); // SIGKILL
    let status = child.wait().unwrap();
    drop(stdin);
    assert!(!status.success());
    assert_eq!(std::fs::read(tmp.path().join("out.csv")).unwrap(), previous);
    for p in temp_files(tmp.path()) {
        assert!(p.to_string_lossy().ends_with(".tmp"), "{}", p.display());
    }
}

/// SIGINT (Ctrl-C) and SIGTERM in the middle of a run: the previous output is intact, the
/// temporary file is removed, and the exit code is 130.
#[test]
fn estimate_interrupted_by_sigint_or_sigterm_cleans_up_and_keeps_the_previous_output() {
    for signal in ["INT", "TERM"] {
        let (tmp, previous) = folder_with_previous_output();
        let (child, stdin) = start_estimate_on_an_open_pipe(tmp.path());
        let sent = std::process::Command::new("kill")
            .args([format!("-{signal}"), child.id().to_string()])
            .status()
            .expect("run kill");
        assert!(sent.success());
        let output = child.wait_with_output().unwrap();
        drop(stdin);
        assert_eq!(output.status.code(), Some(130), "SIG{signal}: {output:?}");
        assert_eq!(
            std::fs::read(tmp.path().join("out.csv")).unwrap(),
            previous,
            "SIG{signal}"
        );
        assert_eq!(temp_files(tmp.path()), Vec::<PathBuf>::new(), "SIG{signal}");
    }
}

/// A folder with a small chain simulated into `sim/` and its estimates in `e.csv`, and the
/// command line of every command that writes a file, writing to `out` (a path relative to the
/// folder; `simulate` writes `out/truth.csv` and its siblings, so `out` names a folder there).
fn writers(dir: &Path) -> Vec<(&'static str, Vec<String>)> {
    let config = catalogue_dir().join("055_csv_missing_row/config.toml");
    std::fs::copy(config, dir.join("config.toml")).unwrap();
    let run = |args: &[&str]| {
        sisfilt().current_dir(dir).args(args).assert().success();
    };
    run(&["simulate", "config.toml", "--out", "sim"]);
    run(&[
        "estimate",
        "--meas",
        "sim/measurements.csv",
        "--out",
        "e.csv",
    ]);
    let args = |list: &[&str]| list.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    vec![
        (
            "estimate",
            args(&["estimate", "--meas", "sim/measurements.csv"]),
        ),
        (
            "evaluate",
            args(&["evaluate", "config.toml", "--runs", "1"]),
        ),
        (
            "plot",
            args(&[
                "plot",
                "heatmap",
                "--truth",
                "sim/truth.csv",
                "--estimates",
                "e.csv",
            ]),
        ),
        ("simulate", args(&["simulate", "config.toml"])),
    ]
}

/// Runs `args --out out` in `dir` under the shell's `umask`.
fn run_with_umask(dir: &Path, umask: &str, args: &[String], out: &str) {
    let output = std::process::Command::new("sh")
        .current_dir(dir)
        .arg("-c")
        .arg(format!("umask {umask} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_sisfilt"))
        .args(args)
        .args(["--out", out])
        .stdout(Stdio::null())
        .output()
        .expect("run sh");
    assert!(output.status.success(), "{args:?} --out {out}: {output:?}");
}

/// The file `simulate` (which writes a folder) or any other command writes for `--out out`.
fn written(dir: &Path, name: &str, out: &str) -> PathBuf {
    if name == "simulate" {
        dir.join(out).join("truth.csv")
    } else {
        dir.join(out)
    }
}

fn mode(path: &Path) -> u32 {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path).unwrap().permissions().mode() & 0o777
}

/// A new output gets `0666 & !umask`, as a shell's `>` would give it; a replaced one keeps its
/// mode whatever the umask, so a result made private stays private. For every command that
/// writes.
#[test]
fn outputs_follow_the_umask_when_new_and_keep_their_mode_when_replaced() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    for (name, args) in writers(tmp.path()) {
        for (umask, expected) in [("077", 0o600), ("022", 0o644), ("002", 0o664)] {
            let out = format!("new-{umask}-{name}");
            run_with_umask(tmp.path(), umask, &args, &out);
            let file = written(tmp.path(), name, &out);
            assert_eq!(mode(&file), expected, "{name} under umask {umask}");
        }
        for (umask, kept) in [("022", 0o600), ("077", 0o644)] {
            let out = format!("kept-{umask}-{name}");
            run_with_umask(tmp.path(), "022", &args, &out);
            let file = written(tmp.path(), name, &out);
            std::fs::set_permissions(&file, std::fs::Permissions::from_mode(kept)).unwrap();
            run_with_umask(tmp.path(), umask, &args, &out);
            assert_eq!(mode(&file), kept, "{name} replaced under umask {umask}");
        }
    }
}

/// An output that is a symbolic link is written through: the file it points to gets the new
/// bytes, the link stays a link, and no temporary file is left in either folder.
#[test]
fn outputs_that_are_symbolic_links_are_written_through() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::create_dir(dir.join("kept")).unwrap();
    for (name, args) in writers(dir) {
        // A first run gives the bytes to expect; the target then holds something else.
        let out = format!("plain-{name}");
        run_with_umask(dir, "022", &args, &out);
        let expected = std::fs::read(written(dir, name, &out)).unwrap();
        let (link, target) = if name == "simulate" {
            std::fs::create_dir(dir.join("link-sim")).unwrap();
            (dir.join("link-sim/truth.csv"), dir.join("kept/truth.csv"))
        } else {
            (
                dir.join(format!("link-{name}")),
                dir.join(format!("kept/{name}")),
            )
        };
        std::fs::write(&target, "the previous result\n").unwrap();
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let out = if name == "simulate" {
            "link-sim".to_string()
        } else {
            format!("link-{name}")
        };
        run_with_umask(dir, "022", &args, &out);
        assert!(
            std::fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink(),
            "{name}: the link was replaced"
        );
        let got = std::fs::read(&target).unwrap();
        if name == "evaluate" {
            // Its JSON records wall times: compare the figures.
            let figures = |b: &[u8]| {
                let v: serde_json::Value = serde_json::from_slice(b).unwrap();
                v["filters"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|f| (f["name"].clone(), f["accuracy"].clone()))
                    .collect::<Vec<_>>()
            };
            assert_eq!(figures(&got), figures(&expected), "{name}");
        } else {
            assert_eq!(got, expected, "{name}: the target did not get the output");
        }
        for folder in [dir.to_path_buf(), dir.join("kept"), dir.join("link-sim")] {
            if folder.is_dir() {
                assert_eq!(temp_files(&folder), Vec::<PathBuf>::new(), "{name}");
            }
        }
    }
}

/// A cell, a header, a config value or a JSON value of 10 MB is quoted by an excerpt (its first
/// characters and its length) in a short error line, not whole: each case exits 2 with one
/// line of at most 400 bytes that still names the file and the line or key (a `--set` value
/// of 100 KB, the most an argument holds).
#[test]
fn a_huge_cell_or_value_is_quoted_by_an_excerpt() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let big = "9".repeat(10_000_000);
    let config = crate::common::shipped_config("platoon.toml");
    let shipped = std::fs::read_to_string(&config).unwrap();
    sisfilt()
        .args(["-q", "simulate"])
        .arg(&config)
        .args(["--steps", "3", "--out"])
        .arg(d.join("run"))
        .assert()
        .success();
    let rows = std::fs::read_to_string(d.join("run/measurements.csv")).unwrap();
    let mut lines: Vec<String> = rows.lines().map(str::to_string).collect();
    let mut cells: Vec<String> = lines[3].split(',').map(str::to_string).collect();
    cells[2] = format!("x{big}");
    lines[3] = cells.join(",");
    let write = |name: &str, text: &str| crate::common::write_file(d, name, text);
    write("cell.csv", &(lines.join("\n") + "\n"));
    write("header.csv", &format!("t,i,y{big}\n1,1,0.5\n"));
    write(
        "variant.toml",
        &shipped.replace("kind = \"sine\"", &format!("kind = \"s{big}\"")),
    );
    write("part.json", &format!("{{\"shard\": \"{big}\"}}"));
    // An argument holds at most 128 KiB.
    let long_setting = format!("input.kind=q{}", &big[..100_000]);
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "estimate".into(),
                "--config".into(),
                config.display().to_string(),
                "--meas".into(),
                "cell.csv".into(),
            ],
            "cell.csv: line 4: column `y",
        ),
        (
            vec![
                "estimate".into(),
                "--config".into(),
                config.display().to_string(),
                "--meas".into(),
                "header.csv".into(),
            ],
            "header.csv: line 1: expected the header",
        ),
        (
            vec!["check".into(), "variant.toml".into()],
            "variant.toml: line",
        ),
        (
            vec![
                "check".into(),
                config.display().to_string(),
                "--set".into(),
                long_setting,
            ],
            "input.kind (from --set): unknown variant",
        ),
        (
            vec!["evaluate-merge".into(), "part.json".into()],
            "part.json: line 1",
        ),
    ];
    for (args, fragment) in cases {
        let out = sisfilt()
            .current_dir(d)
            .arg("-q")
            .args(&args)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(
            out.status.code(),
            Some(2),
            "{fragment}: {}",
            &stderr[..stderr.len().min(500)]
        );
        assert!(
            stderr.len() <= 400,
            "{fragment}: {} bytes: {}",
            stderr.len(),
            &stderr[..500]
        );
        assert_eq!(stderr.lines().count(), 1, "{stderr}");
        assert!(
            stderr.contains(fragment) && stderr.contains("bytes)"),
            "{stderr}"
        );
    }
}

/// An input the operating system will not open — a loop of symbolic links, a name too long,
/// a socket, a folder — is bad input (exit 2) naming it, in every command that reads one (a
/// loop, a long name and a socket were internal failures, exit 1).
#[test]
fn an_input_the_system_will_not_open_is_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::os::unix::fs::symlink(d.join("loop-b"), d.join("loop-a")).unwrap();
    std::os::unix::fs::symlink(d.join("loop-a"), d.join("loop-b")).unwrap();
    let _socket = std::os::unix::net::UnixListener::bind(d.join("socket")).unwrap();
    std::fs::create_dir(d.join("folder")).unwrap();
    let long = "n".repeat(300);
    let config = crate::common::shipped_config("paper.toml");
    let config = config.to_str().unwrap();
    for input in ["loop-a", long.as_str(), "socket", "folder"] {
        let commands: [Vec<&str>; 4] = [
            vec!["check", input],
            vec!["estimate", "--config", config, "--meas", input],
            vec!["plot", "evaluate", "--input", input, "--out", "figure.svg"],
            vec!["evaluate-merge", input],
        ];
        for args in commands {
            let out = sisfilt().current_dir(d).args(&args).output().unwrap();
            let stderr = String::from_utf8_lossy(&out.stderr);
            let shown = &input[..input.len().min(20)];
            assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
            assert!(out.stdout.is_empty(), "{args:?}");
            assert_eq!(stderr.lines().count(), 1, "{args:?}: {stderr}");
            assert!(
                stderr.starts_with("error: ") && stderr.contains(shown),
                "{args:?}: {stderr}"
            );
        }
    }
    assert!(!d.join("figure.svg").exists());
}
