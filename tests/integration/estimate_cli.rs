//! `sisfilt estimate` from the command line (docs/theory.md §4, §6, §13): the estimates file and its
//! JSON form, the shortest workflow through `run.json`, determinism, bad measurement files,
//! atomic output, known dropouts, `--paper`, `--solver transfer`, `--predicted` and piping.
//!
//! Every test works in its own temporary folder.

use std::path::{Path, PathBuf};
use std::process::Output;

use assert_cmd::Command;
use sha2::Digest;
use tempfile::TempDir;

use crate::common::{shipped_config, shipped_configs, sisfilt};

// ------------------------------------------------------------------------------ helpers

fn tmp() -> TempDir {
    tempfile::tempdir().expect("a temporary folder")
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8(bytes.to_vec()).expect("utf-8 output")
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn write(path: &Path, content: impl AsRef<[u8]>) {
    std::fs::write(path, content).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// Describes a finished command for assertion messages.
fn describe(out: &Output) -> String {
    format!(
        "status {:?}\n--- stderr:\n{}--- stdout (first 400 bytes):\n{}",
        out.status.code(),
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout[..out.stdout.len().min(400)])
    )
}

/// Runs the command and asserts exit 0.
fn ok(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("sisfilt runs");
    assert!(out.status.success(), "expected success: {}", describe(&out));
    out
}

/// Runs the command and asserts the exit code.
fn fails(cmd: &mut Command, code: i32) -> Output {
    let out = cmd.output().expect("sisfilt runs");
    assert_eq!(
        out.status.code(),
        Some(code),
        "expected exit {code}: {}",
        describe(&out)
    );
    out
}

/// `sisfilt simulate CONFIG --out DIR [extra…]`, asserted to succeed.
fn simulate(config: &Path, dir: &Path, extra: &[&str]) {
    ok(sisfilt()
        .arg("simulate")
        .arg(config)
        .arg("--out")
        .arg(dir)
        .args(extra));
    assert!(dir.join("measurements.csv").is_file());
    assert!(dir.join("truth.csv").is_file());
    assert!(dir.join("run.json").is_file());
}

/// `sisfilt estimate --config CONFIG --meas MEAS [extra…]` (not run yet).
fn estimate(config: &Path, meas: &Path, extra: &[&str]) -> Command {
    let mut cmd = sisfilt();
    cmd.arg("estimate")
        .arg("--config")
        .arg(config)
        .arg("--meas")
        .arg(meas)
        .args(extra);
    cmd
}

/// The lines of standard error.
fn stderr_lines(out: &Output) -> Vec<String> {
    text(&out.stderr).lines().map(str::to_string).collect()
}

/// The `warning: ` lines of standard error.
fn warnings(out: &Output) -> Vec<String> {
    stderr_lines(out)
        .into_iter()
        .filter(|l| l.starts_with("warning: "))
        .collect()
}

/// Asserts that standard error is exactly one line starting with `error: ` (docs/theory.md §13) and
/// returns it.
fn one_error_line(out: &Output) -> String {
    let err = text(&out.stderr);
    let lines: Vec<&str> = err.lines().collect();
    assert_eq!(lines.len(), 1, "expected one stderr line, got {err:?}");
    assert!(
        lines[0].starts_with("error: "),
        "stderr does not start with `error: `: {err:?}"
    );
    assert!(
        err.ends_with('\n'),
        "stderr not newline-terminated: {err:?}"
    );
    lines[0].to_string()
}

/// Whether `msg` says `line N` for exactly this `N` (not `line N0…`).
fn names_line(msg: &str, n: usize) -> bool {
    let needle = format!("line {n}");
    msg.match_indices(&needle).any(|(at, _)| {
        !msg[at + needle.len()..]
            .chars()
            .next()
            .is_some_and(|c| c.is_ascii_digit())
    })
}

/// A CSV file (or output) as its header and rows of raw cells; every record must have the
/// header's width.
struct Csv {
    header: Vec<String>,
    rows: Vec<Vec<String>>,
}

impl Csv {
    fn parse(bytes: &[u8]) -> Csv {
        let mut r = csv::ReaderBuilder::new()
            .has_headers(false)
            .from_reader(bytes);
        let mut records = r
            .records()
            .map(|rec| {
                rec.expect("a well-formed CSV")
                    .iter()
                    .map(str::to_string)
                    .collect()
            })
            .collect::<Vec<Vec<String>>>()
            .into_iter();
        let header = records.next().expect("a header line");
        Csv {
            header,
            rows: records.collect(),
        }
    }

    fn read(path: &Path) -> Csv {
        Csv::parse(&read(path))
    }

    /// The same table without its last column.
    fn without_last_column(&self) -> Csv {
        let drop_last = |r: &Vec<String>| r[..r.len() - 1].to_vec();
        Csv {
            header: drop_last(&self.header),
            rows: self.rows.iter().map(drop_last).collect(),
        }
    }

    /// The `(t, i)` of every row.
    fn indices(&self) -> Vec<(usize, usize)> {
        self.rows
            .iter()
            .map(|r| (r[0].parse().unwrap(), r[1].parse().unwrap()))
            .collect()
    }

    /// The value cells of every row (all but `t, i`) as numbers.
    fn values(&self) -> Vec<Vec<f64>> {
        self.rows
            .iter()
            .map(|r| {
                r[2..]
                    .iter()
                    .map(|c| {
                        c.parse::<f64>()
                            .unwrap_or_else(|_| panic!("not a number: {c:?} in {r:?}"))
                    })
                    .collect()
            })
            .collect()
    }
}

/// The header of an estimates file: `t,i,x1..xn,P1_1,P1_2..Pn_n` (docs/theory.md §13).
fn estimates_header(n: usize) -> Vec<String> {
    let mut h = vec!["t".to_string(), "i".to_string()];
    h.extend((1..=n).map(|k| format!("x{k}")));
    for r in 1..=n {
        for c in r..=n {
            h.push(format!("P{r}_{c}"));
        }
    }
    h
}

/// Position of `P{k}_{k}` among the value cells (after `t, i`) of an estimates row.
fn diag_positions(n: usize) -> Vec<usize> {
    let h = estimates_header(n);
    (1..=n)
        .map(|k| {
            h.iter()
                .position(|c| *c == format!("P{k}_{k}"))
                .expect("diagonal column")
                - 2
        })
        .collect()
}

/// `(N, T, n)` of a simulated run, from its truth file `t,i,x1..xn,gamma`.
fn dims_of_run(dir: &Path) -> (usize, usize, usize) {
    let truth = Csv::read(&dir.join("truth.csv"));
    let n = truth.header.len() - 3;
    let idx = truth.indices();
    let big_n = idx.iter().map(|p| p.1).max().unwrap();
    let steps = idx.iter().map(|p| p.0).max().unwrap();
    assert_eq!(idx.len(), big_n * steps);
    (big_n, steps, n)
}

/// Every `(t, i)`, ordered by `t` then `i`.
fn all_indices(big_n: usize, steps: usize) -> Vec<(usize, usize)> {
    (1..=steps)
        .flat_map(|t| (1..=big_n).map(move |i| (t, i)))
        .collect()
}

/// Checks an estimates CSV: header, one row per `(t, i)` in order, finite numbers and a
/// positive covariance diagonal.
fn check_estimates(est: &Csv, big_n: usize, steps: usize, n: usize) {
    assert_eq!(est.header, estimates_header(n));
    assert_eq!(est.indices(), all_indices(big_n, steps));
    let diag = diag_positions(n);
    for (row, vals) in est.rows.iter().zip(est.values()) {
        assert_eq!(vals.len(), n + n * (n + 1) / 2, "row {row:?}");
        assert!(vals.iter().all(|v| v.is_finite()), "row {row:?}");
        for &k in &diag {
            assert!(vals[k] > 0.0, "non-positive variance in row {row:?}");
        }
    }
}

/// Whether the config's process noise `Q` is absent or zero (the paper's setting).
fn q_is_zero(config: &Path) -> bool {
    let value: toml::Value = toml::from_str(&String::from_utf8(read(config)).unwrap()).unwrap();
    let Some(q) = value.get("model").and_then(|m| m.get("Q")) else {
        return true;
    };
    q.as_array().unwrap().iter().all(|row| {
        row.as_array().unwrap().iter().all(|v| {
            v.as_float()
                .or_else(|| v.as_integer().map(|k| k as f64))
                .unwrap()
                == 0.0
        })
    })
}

fn sha256_hex(bytes: &[u8]) -> String {
    sha2::Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// A JSON value whose numbers are kept as their text, so that they can be parsed with the
/// correctly rounded `str::parse::<f64>` (serde_json without `float_roundtrip` may be off by
/// one unit in the last place).
#[derive(Debug, Clone, PartialEq)]
enum Json {
    Null,
    Bool(bool),
    Num(String),
    Str(String),
    Arr(Vec<Json>),
    Obj(Vec<(String, Json)>),
}

impl Json {
    fn parse(text: &str) -> Json {
        let b = text.as_bytes();
        let mut pos = 0;
        let v = Self::value(b, &mut pos);
        Self::ws(b, &mut pos);
        assert_eq!(pos, b.len(), "trailing characters after the JSON document");
        v
    }

    fn ws(b: &[u8], pos: &mut usize) {
        while *pos < b.len() && b[*pos].is_ascii_whitespace() {
            *pos += 1;
        }
    }

    fn value(b: &[u8], pos: &mut usize) -> Json {
        Self::ws(b, pos);
        match b[*pos] {
            b'n' => Self::lit(b, pos, "null", Json::Null),
            b't' => Self::lit(b, pos, "true", Json::Bool(true)),
            b'f' => Self::lit(b, pos, "false", Json::Bool(false)),
            b'"' => Json::Str(Self::string(b, pos)),
            b'[' => {
                *pos += 1;
                let mut items = Vec::new();
                Self::ws(b, pos);
                if b[*pos] == b']' {
                    *pos += 1;
                    return Json::Arr(items);
                }
                loop {
                    items.push(Self::value(b, pos));
                    Self::ws(b, pos);
                    *pos += 1;
                    match b[*pos - 1] {
                        b',' => continue,
                        b']' => return Json::Arr(items),
                        c => panic!("unexpected {:?} in an array", c as char),
                    }
                }
            }
            b'{' => {
                *pos += 1;
                let mut fields = Vec::new();
                Self::ws(b, pos);
                if b[*pos] == b'}' {
                    *pos += 1;
                    return Json::Obj(fields);
                }
                loop {
                    Self::ws(b, pos);
                    let key = Self::string(b, pos);
                    Self::ws(b, pos);
                    assert_eq!(b[*pos], b':');
                    *pos += 1;
                    fields.push((key, Self::value(b, pos)));
                    Self::ws(b, pos);
                    *pos += 1;
                    match b[*pos - 1] {
                        b',' => continue,
                        b'}' => return Json::Obj(fields),
                        c => panic!("unexpected {:?} in an object", c as char),
                    }
                }
            }
            _ => {
                let start = *pos;
                while *pos < b.len()
                    && matches!(b[*pos], b'0'..=b'9' | b'-' | b'+' | b'.' | b'e' | b'E')
                {
                    *pos += 1;
                }
                assert!(*pos > start, "unexpected character at byte {start}");
                Json::Num(String::from_utf8(b[start..*pos].to_vec()).unwrap())
            }
        }
    }

    fn lit(b: &[u8], pos: &mut usize, word: &str, v: Json) -> Json {
        assert!(b[*pos..].starts_with(word.as_bytes()), "bad literal");
        *pos += word.len();
        v
    }

    fn string(b: &[u8], pos: &mut usize) -> String {
        assert_eq!(b[*pos], b'"');
        *pos += 1;
        let start = *pos;
        while b[*pos] != b'"' {
            *pos += if b[*pos] == b'\\' { 2 } else { 1 };
        }
        *pos += 1;
        // Escapes are kept raw; good enough for keys and comparisons here.
        String::from_utf8(b[start..*pos - 1].to_vec()).unwrap()
    }

    fn get(&self, key: &str) -> Option<&Json> {
        match self {
            Json::Obj(fields) => fields.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }
}

/// The `estimates` rows of a JSON output, each number parsed from its exact text.
fn json_estimates(doc: &str) -> Vec<Vec<f64>> {
    let Some(Json::Arr(rows)) = Json::parse(doc).get("estimates").cloned() else {
        panic!("no `estimates` array");
    };
    rows.iter()
        .map(|row| match row {
            Json::Arr(cells) => cells
                .iter()
                .map(|c| match c {
                    Json::Num(s) => s.parse::<f64>().expect("a JSON number"),
                    other => panic!("not a number: {other:?}"),
                })
                .collect(),
            other => panic!("estimates row is not an array: {other:?}"),
        })
        .collect()
}

/// Asserts that JSON estimate rows carry exactly the numbers of the CSV rows (same bits).
fn assert_json_rows_match_csv(json_rows: &[Vec<f64>], csv: &Csv) {
    assert_eq!(json_rows.len(), csv.rows.len(), "row count");
    for (j, c) in json_rows.iter().zip(&csv.rows) {
        assert_eq!(j.len(), c.len(), "row width: {c:?}");
        assert_eq!(j[0], c[0].parse::<usize>().unwrap() as f64, "t of {c:?}");
        assert_eq!(j[1], c[1].parse::<usize>().unwrap() as f64, "i of {c:?}");
        for (a, b) in j[2..].iter().zip(&c[2..]) {
            let b: f64 = b.parse().unwrap();
            assert_eq!(a.to_bits(), b.to_bits(), "{a} vs {b} in row {c:?}");
        }
    }
}

/// The largest absolute difference between the value cells of two estimate files with the
/// same rows.
fn max_abs_diff(a: &Csv, b: &Csv) -> f64 {
    assert_eq!(a.header, b.header);
    assert_eq!(a.indices(), b.indices());
    a.values()
        .iter()
        .zip(b.values())
        .flat_map(|(x, y)| {
            x.iter()
                .zip(y)
                .map(|(p, q)| (p - q).abs())
                .collect::<Vec<_>>()
        })
        .fold(0.0, f64::max)
}

// ----------------------------------------------------------------------------- 1. round trip

#[test]
fn round_trip_on_every_shipped_config() {
    for config in shipped_configs() {
        let dir = tmp();
        let run = dir.path().join("run");
        simulate(&config, &run, &[]);
        let (big_n, steps, n) = dims_of_run(&run);
        let est_path = run.join("est.csv");
        let out = ok(estimate(&config, &run.join("measurements.csv"), &[])
            .arg("--truth")
            .arg(run.join("truth.csv"))
            .arg("--out")
            .arg(&est_path));
        let name = config.display();
        assert!(out.stdout.is_empty(), "{name}: data on stdout with --out");
        check_estimates(&Csv::read(&est_path), big_n, steps, n);

        let lines = stderr_lines(&out);
        assert!(
            lines
                .iter()
                .all(|l| ["warning: ", "accuracy: ", "innovations: "]
                    .iter()
                    .any(|kind| l.starts_with(kind))),
            "{name}: unexpected stderr {lines:?}"
        );
        let accuracy: Vec<&String> = lines
            .iter()
            .filter(|l| l.starts_with("accuracy: "))
            .collect();
        assert_eq!(accuracy.len(), 1, "{name}: {lines:?}");
        assert!(accuracy[0].contains("RMSE"), "{name}: {lines:?}");

        let q_warning = warnings(&out).iter().any(|w| w.contains("Q = 0"));
        if config.file_name().unwrap() == "paper.toml" {
            assert!(q_is_zero(&config));
            assert!(
                q_warning,
                "{name}: no `warning: ` line about Q = 0: {lines:?}"
            );
        }
        if !q_is_zero(&config) {
            assert!(!q_warning, "{name}: Q > 0 but warned about Q = 0");
        }
    }
}

// -------------------------------------------------------------- 2. the shortest workflow

#[test]
fn config_and_inputs_come_from_run_json() {
    // platoon has inputs (inputs.csv is written), paper has none.
    for name in ["platoon.toml", "paper.toml"] {
        let config = shipped_config(name);
        let dir = tmp();
        let run = dir.path().join("data");
        simulate(&config, &run, &[]);
        let has_inputs = run.join("inputs.csv").is_file();
        assert_eq!(has_inputs, name == "platoon.toml");

        let short =
            ok(sisfilt()
                .current_dir(&run)
                .args(["estimate", "--meas", "measurements.csv"]));
        let mut explicit = estimate(&config, &run.join("measurements.csv"), &[]);
        if has_inputs {
            explicit.arg("--inputs").arg(run.join("inputs.csv"));
        }
        let explicit = ok(&mut explicit);
        assert!(!short.stdout.is_empty());
        assert!(
            short.stdout == explicit.stdout,
            "{name}: `estimate --meas measurements.csv` differs from the explicit run"
        );
        // The same from another folder, with the measurement file's folder in its path.
        let elsewhere = ok(sisfilt()
            .current_dir(dir.path())
            .args(["estimate", "--meas"])
            .arg(Path::new("data").join("measurements.csv")));
        assert!(
            elsewhere.stdout == explicit.stdout,
            "{name}: data/measurements.csv"
        );
        let (big_n, steps, n) = dims_of_run(&run);
        check_estimates(&Csv::parse(&short.stdout), big_n, steps, n);
    }
}

#[test]
fn without_run_json_config_is_required() {
    let dir = tmp();
    let run = dir.path().join("run");
    simulate(&shipped_config("platoon.toml"), &run, &[]);
    let lone = dir.path().join("lone");
    std::fs::create_dir(&lone).unwrap();
    std::fs::copy(run.join("measurements.csv"), lone.join("measurements.csv")).unwrap();

    let out = fails(
        sisfilt()
            .current_dir(&lone)
            .args(["estimate", "--meas", "measurements.csv"]),
        2,
    );
    assert!(out.stdout.is_empty());
    let line = one_error_line(&out);
    assert!(line.contains("--config"), "{line}");

    let out = fails(
        sisfilt()
            .args(["estimate", "--meas"])
            .arg(lone.join("measurements.csv")),
        2,
    );
    assert!(out.stdout.is_empty());
    assert!(one_error_line(&out).contains("--config"));

    // Standard input has no folder, so no run.json, even when the data came from simulate.
    let out = fails(
        sisfilt()
            .current_dir(&run)
            .args(["estimate", "--meas", "-"])
            .write_stdin(read(&run.join("measurements.csv"))),
        2,
    );
    assert!(out.stdout.is_empty());
    assert!(one_error_line(&out).contains("--config"));
}

// --------------------------------------------------------------------------------- 3. JSON

#[test]
fn json_output_carries_the_csv_numbers_and_metadata() {
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    let run = dir.path().join("run");
    simulate(&config, &run, &[]);
    let meas = run.join("measurements.csv");
    let truth = run.join("truth.csv");
    let (_, _, n) = dims_of_run(&run);

    let csv_out = ok(&mut estimate(&config, &meas, &[]));
    let csv = Csv::parse(&csv_out.stdout);
    let config_sha = sha256_hex(&read(&config));

    for with_truth in [false, true] {
        let mut cmd = estimate(&config, &meas, &["--format", "json"]);
        if with_truth {
            cmd.arg("--truth").arg(&truth);
        }
        let out = ok(&mut cmd);
        let doc = text(&out.stdout);
        let v: serde_json::Value = serde_json::from_str(&doc).expect("valid JSON");

        let columns: Vec<String> = serde_json::from_value(v["columns"].clone()).unwrap();
        assert_eq!(columns, csv.header);
        assert_json_rows_match_csv(&json_estimates(&doc), &csv);
        assert_eq!(
            v["estimates"].as_array().unwrap().len(),
            csv.rows.len(),
            "serde_json sees the same rows"
        );

        assert_eq!(
            v["sisfilt_version"].as_str(),
            Some(env!("CARGO_PKG_VERSION"))
        );
        let sha = v["config"]["sha256"].as_str().expect("config.sha256");
        assert_eq!(sha.len(), 64, "{sha}");
        assert!(
            sha.chars()
                .all(|c| c.is_ascii_digit() || ('a'..='f').contains(&c)),
            "{sha}"
        );
        assert_eq!(sha, config_sha, "sha256 of the config file");
        let options = v["options"].as_object().expect("an `options` object");
        for (key, default) in [
            ("solver", "banded"),
            ("second_moment", "local"),
            ("interconnect_from", "filtered"),
            ("dropouts", "unknown"),
        ] {
            assert_eq!(options[key].as_str(), Some(default), "options.{key}");
        }

        // One library type describes the file: it reads every field back, and writes the
        // same metadata again.
        let typed: sisfilt::io::estimates::EstimatesDocument =
            serde_json::from_str(&doc).expect("an EstimatesDocument");
        assert_eq!(typed.columns, csv.header);
        assert_eq!(typed.estimates.len(), csv.rows.len());
        assert_eq!(typed.summary.accuracy.is_some(), with_truth);
        assert_eq!(typed.metadata.n, n);
        assert_eq!(typed.metadata.config.sha256, config_sha);
        let mut metadata = v.as_object().unwrap().clone();
        for key in [
            "columns",
            "estimates",
            "accuracy",
            "detection",
            "loglik",
            "innovations",
        ] {
            metadata.remove(key);
        }
        assert_eq!(
            serde_json::to_value(&typed.metadata).unwrap(),
            serde_json::Value::Object(metadata)
        );

        let accuracy = v.get("accuracy").expect("an `accuracy` key");
        if with_truth {
            let rmse = accuracy["rmse"].as_array().expect("accuracy.rmse");
            assert_eq!(rmse.len(), n);
            assert!(rmse.iter().all(|r| r.as_f64().is_some_and(|r| r > 0.0)));
            let anees = accuracy.get("anees").expect("accuracy.anees");
            assert!(anees.is_null() || anees.as_f64().is_some_and(|a| a > 0.0));
            // platoon has Q > 0: its ANEES is finite.
            assert!(anees.is_f64(), "{anees}");
        } else {
            assert!(accuracy.is_null(), "accuracy without --truth: {accuracy}");
        }
    }

    // `--out x.json` means JSON: the same document as `--format json` on standard output.
    let stdout_json = ok(&mut estimate(&config, &meas, &["--format", "json"])).stdout;
    let file = dir.path().join("x.json");
    let out = ok(estimate(&config, &meas, &[]).arg("--out").arg(&file));
    assert!(out.stdout.is_empty());
    assert!(
        read(&file) == stdout_json,
        "--out x.json differs from --format json"
    );
    // An explicit --format wins over the extension.
    let file = dir.path().join("y.json");
    ok(estimate(&config, &meas, &["--format", "csv"])
        .arg("--out")
        .arg(&file));
    assert!(read(&file) == csv_out.stdout, "--format csv --out y.json");
}

#[test]
fn json_from_run_json_hashes_the_same_config() {
    let config = shipped_config("paper.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let out = ok(sisfilt().current_dir(dir.path()).args([
        "estimate",
        "--meas",
        "measurements.csv",
        "--format",
        "json",
    ]));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        v["config"]["sha256"].as_str(),
        Some(sha256_hex(&read(&config)).as_str())
    );
}

// -------------------------------------------------------------------------- 4. determinism

#[test]
fn two_runs_give_identical_output() {
    let config = shipped_config("heat_rod.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");
    let truth = dir.path().join("truth.csv");
    for format in ["csv", "json"] {
        let run = || {
            ok(estimate(&config, &meas, &["--format", format])
                .arg("--truth")
                .arg(&truth))
        };
        let (a, b) = (run(), run());
        assert!(!a.stdout.is_empty());
        assert!(
            a.stdout == b.stdout,
            "{format}: stdout differs between runs"
        );
        assert_eq!(a.stderr, b.stderr, "{format}: stderr differs between runs");
    }
    // And through files.
    let (fa, fb) = (dir.path().join("a.csv"), dir.path().join("b.csv"));
    ok(estimate(&config, &meas, &[]).arg("--out").arg(&fa));
    ok(estimate(&config, &meas, &[]).arg("--out").arg(&fb));
    assert!(read(&fa) == read(&fb));
}

/// `--timings` splits the run into its phases: read, filter, the innovation check, write and
/// the rest, which add up to the total, and counts the rows written.
#[test]
fn timings_split_the_run_into_its_phases() {
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let out = ok(estimate(
        &config,
        &dir.path().join("measurements.csv"),
        &["--timings"],
    )
    .arg("--out")
    .arg(dir.path().join("estimates.csv")));
    let stderr = text(&out.stderr);
    let line = stderr
        .lines()
        .find_map(|l| l.strip_prefix("timings: "))
        .unwrap_or_else(|| panic!("no timings line in: {stderr}"));
    let fields: Vec<&str> = line.split(", ").collect();
    let seconds = |name: &str| -> f64 {
        let field = fields
            .iter()
            .find_map(|f| f.strip_prefix(name)?.strip_prefix(' '))
            .unwrap_or_else(|| panic!("no {name} in: {line}"));
        let value = field
            .strip_suffix(" s")
            .unwrap_or_else(|| panic!("{field}"));
        value.parse().unwrap_or_else(|e| panic!("{field}: {e}"))
    };
    let phases = ["read", "filter", "check", "write", "other"].map(seconds);
    assert!(phases.iter().all(|&s| s >= 0.0), "{line}");
    // Each figure is rounded to the millisecond.
    let total = seconds("total");
    assert!(
        (phases.iter().sum::<f64>() - total).abs() <= 0.003,
        "{line}"
    );
    assert!(fields.contains(&"4000 rows"), "{line}");
}

// -------------------------------------------------------------- 5. bad measurement files

/// A simulated platoon run (Q > 0, stable: no warnings) and its measurement lines.
struct BadFileSetup {
    dir: TempDir,
    config: PathBuf,
    lines: Vec<String>,
}

impl BadFileSetup {
    fn new() -> Self {
        let dir = tmp();
        let config = shipped_config("platoon.toml");
        simulate(&config, &dir.path().join("run"), &[]);
        let lines = text(&read(&dir.path().join("run").join("measurements.csv")))
            .lines()
            .map(str::to_string)
            .collect();
        BadFileSetup { dir, config, lines }
    }

    /// Writes `name` with the given lines (each followed by a newline).
    fn file(&self, name: &str, lines: &[String]) -> PathBuf {
        let path = self.dir.path().join(name);
        let mut body = lines.join("\n");
        body.push('\n');
        write(&path, body);
        path
    }
}

/// Line 45 of a platoon measurement file (N = 20) is the row t = 3, i = 4.
const BAD: usize = 45;

/// The lines with line `at` (1-based) changed by `f`.
fn edit_line(lines: &[String], at: usize, f: impl Fn(&str) -> String) -> Vec<String> {
    let mut out = lines.to_vec();
    out[at - 1] = f(&lines[at - 1]);
    out
}

/// Replaces the last cell of a CSV line.
fn last_cell(line: &str, cell: &str) -> String {
    let cut = line.rfind(',').unwrap();
    format!("{},{cell}", &line[..cut])
}

#[test]
fn bad_measurement_files_name_file_and_line() {
    let s = BadFileSetup::new();
    let l = &s.lines;
    assert_eq!(
        l[BAD - 1].split(',').take(2).collect::<Vec<_>>(),
        ["3", "4"]
    );
    let last = l.len();

    let mut header = l.clone();
    header[0] = "t,i,y1,z2".into();
    let mut missing = l.clone();
    missing.remove(BAD - 1);
    let mut duplicated = l.clone();
    duplicated.insert(BAD, l[BAD - 1].clone());
    let mut swapped = l.clone();
    swapped.swap(BAD - 1, BAD);

    // (file name, lines, the line the error must name, something the message must say)
    let cases: Vec<(&str, Vec<String>, usize, Option<&str>)> = vec![
        ("wrong_header.csv", header, 1, None),
        ("missing_row.csv", missing, BAD, None),
        ("duplicated_row.csv", duplicated, BAD + 1, None),
        ("out_of_order.csv", swapped, BAD, None),
        (
            "extra_column.csv",
            edit_line(l, BAD, |x| format!("{x},0.5")),
            BAD,
            None,
        ),
        (
            "missing_column.csv",
            edit_line(l, BAD, |x| x[..x.rfind(',').unwrap()].to_string()),
            BAD,
            None,
        ),
        (
            "not_a_number.csv",
            edit_line(l, BAD, |x| last_cell(x, "abc")),
            BAD,
            None,
        ),
        (
            "inf.csv",
            edit_line(l, BAD, |x| last_cell(x, "inf")),
            BAD,
            None,
        ),
        (
            "minus_inf.csv",
            edit_line(l, BAD, |x| last_cell(x, "-inf")),
            BAD,
            None,
        ),
        (
            "infinity.csv",
            edit_line(l, BAD, |x| last_cell(x, "infinity")),
            BAD,
            None,
        ),
        (
            "overflow.csv",
            edit_line(l, BAD, |x| last_cell(x, "1e999")),
            BAD,
            None,
        ),
        (
            "bad_t.csv",
            edit_line(l, BAD, |x| format!("3.5{}", &x[1..])),
            BAD,
            None,
        ),
    ];
    for (name, lines, line, says) in cases {
        let path = s.file(name, &lines);
        let out = fails(&mut estimate(&s.config, &path, &[]), 2);
        let msg = one_error_line(&out);
        assert!(msg.contains(name), "{name}: file not named: {msg}");
        assert!(
            names_line(&msg, line),
            "{name}: expected `line {line}`: {msg}"
        );
        if let Some(says) = says {
            assert!(msg.contains(says), "{name}: should mention {says}: {msg}");
        }
    }

    // A truncated last line: the file stops in the middle of the last row, without newline.
    let path = s.dir.path().join("truncated.csv");
    let mut body = l[..last - 1].join("\n");
    body.push('\n');
    body.push_str(&l[last - 1][..l[last - 1].rfind(',').unwrap()]);
    write(&path, body);
    let out = fails(&mut estimate(&s.config, &path, &[]), 2);
    let msg = one_error_line(&out);
    assert!(msg.contains("truncated.csv"), "{msg}");
    assert!(names_line(&msg, last), "expected `line {last}`: {msg}");

    // A file that stops after a complete row in the middle of a time step.
    let path = s.file("short_step.csv", &l[..BAD]);
    let msg = one_error_line(&fails(&mut estimate(&s.config, &path, &[]), 2));
    assert!(msg.contains("short_step.csv"), "{msg}");

    // No such file.
    let path = s.dir.path().join("no_such_file.csv");
    let out = fails(&mut estimate(&s.config, &path, &[]), 2);
    assert!(out.stdout.is_empty());
    assert!(one_error_line(&out).contains("no_such_file.csv"));

    // Only a header.
    let path = s.file("header_only.csv", &l[..1]);
    let msg = one_error_line(&fails(&mut estimate(&s.config, &path, &[]), 2));
    assert!(msg.contains("header_only.csv"), "{msg}");

    // An empty file.
    let path = s.dir.path().join("empty.csv");
    write(&path, "");
    let msg = one_error_line(&fails(&mut estimate(&s.config, &path, &[]), 2));
    assert!(msg.contains("empty.csv"), "{msg}");
}

/// Errors found before the output is opened print nothing on standard output.
#[test]
fn early_errors_leave_stdout_empty() {
    let s = BadFileSetup::new();
    let mut header = s.lines.clone();
    header[0] = "t,i,y1".into();
    let path = s.file("wrong_header.csv", &header);
    let out = fails(&mut estimate(&s.config, &path, &[]), 2);
    assert!(out.stdout.is_empty(), "{}", describe(&out));
    let out = fails(
        &mut estimate(&s.config, &s.dir.path().join("none.csv"), &[]),
        2,
    );
    assert!(out.stdout.is_empty(), "{}", describe(&out));
}

/// docs/theory.md §13: standard output carries only data. Into a pipe (here), each step goes
/// out as it is filtered, so a run that fails on bad input at step `t` has written the
/// steps before `t`, whole, and nothing of step `t` (into a regular file, nothing at all:
/// see the tests of atomic output).
#[test]
fn mid_file_errors_leave_only_whole_steps_on_a_pipe() {
    let s = BadFileSetup::new();
    let mut missing = s.lines.clone();
    missing.remove(BAD - 1);
    let path = s.file("missing_row.csv", &missing);
    let out = fails(&mut estimate(&s.config, &path, &[]), 2);
    // Line 45 is the row t = 3, i = 4: steps 1 and 2 went out.
    let rows = text(&out.stdout);
    assert_eq!(rows.lines().count(), 1 + 2 * 20, "{}", describe(&out));
    assert!(rows.ends_with('\n'));

    let inf = edit_line(&s.lines, s.lines.len() - 3, |x| last_cell(x, "inf"));
    let path = s.file("late_inf.csv", &inf);
    let out = fails(&mut estimate(&s.config, &path, &["--format", "csv"]), 2);
    assert_eq!(
        text(&out.stdout).lines().count(),
        1 + 199 * 20,
        "{}",
        describe(&out)
    );
}

#[test]
fn out_into_a_missing_folder_is_bad_input() {
    let s = BadFileSetup::new();
    let meas = s.dir.path().join("run").join("measurements.csv");
    let missing = s.dir.path().join("no_such_folder");
    let out = fails(
        estimate(&s.config, &meas, &[])
            .arg("--out")
            .arg(missing.join("est.csv")),
        2,
    );
    assert!(out.stdout.is_empty());
    let msg = one_error_line(&out);
    assert!(msg.contains("no_such_folder"), "{msg}");
    assert!(!missing.exists(), "estimate created the folder");
}

#[test]
fn failed_run_keeps_the_old_output_file() {
    let s = BadFileSetup::new();
    let bad_at = s.lines.len() / 2;
    let bad = edit_line(&s.lines, bad_at, |x| last_cell(x, "oops"));
    let meas = s.file("bad_middle.csv", &bad);
    let out_dir = s.dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();

    for name in ["est.csv", "est.json"] {
        let dest = out_dir.join(name);
        let old = b"old content\nthat must survive\n";
        write(&dest, old);
        let out = fails(estimate(&s.config, &meas, &[]).arg("--out").arg(&dest), 2);
        assert!(out.stdout.is_empty());
        let msg = one_error_line(&out);
        assert!(names_line(&msg, bad_at), "{msg}");
        assert_eq!(read(&dest), old, "{name}: the old file was touched");
    }
    // No temporary file is left behind.
    let mut names: Vec<String> = std::fs::read_dir(&out_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["est.csv", "est.json"]);

    // A good run replaces the file.
    let good = s.dir.path().join("run").join("measurements.csv");
    let dest = out_dir.join("est.csv");
    ok(estimate(&s.config, &good, &[]).arg("--out").arg(&dest));
    let (big_n, steps, n) = dims_of_run(&s.dir.path().join("run"));
    check_estimates(&Csv::read(&dest), big_n, steps, n);
}

// ------------------------------------------------------------------------ 6. known dropouts

#[test]
fn known_dropouts_read_marked_measurements() {
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &["--mark-missing"]);
    let meas = dir.path().join("measurements.csv");
    let (big_n, steps, n) = dims_of_run(dir.path());

    let lines: Vec<String> = text(&read(&meas)).lines().map(str::to_string).collect();
    assert!(
        lines.iter().any(|l| l.split(',').any(str::is_empty)),
        "--mark-missing left some cell empty"
    );

    let out = ok(estimate(&config, &meas, &["--dropouts", "known"])
        .arg("--truth")
        .arg(dir.path().join("truth.csv")));
    check_estimates(&Csv::parse(&out.stdout), big_n, steps, n);
    assert!(
        stderr_lines(&out)
            .iter()
            .any(|l| l.starts_with("accuracy: "))
    );

    // The default unknown mode reads the empty cells as gaps (docs/theory.md §15): the
    // subsystem is updated with what is there, or only predicted.
    let unknown = ok(&mut estimate(&config, &meas, &[]));
    check_estimates(&Csv::parse(&unknown.stdout), big_n, steps, n);
    assert!(
        unknown.stdout != out.stdout,
        "p plays a part in the unknown mode"
    );

    // The run.json route works in known mode too.
    let short = ok(sisfilt().current_dir(dir.path()).args([
        "estimate",
        "--meas",
        "measurements.csv",
        "--dropouts",
        "known",
    ]));
    let explicit = ok(estimate(&config, &meas, &["--dropouts", "known"])
        .arg("--inputs")
        .arg(dir.path().join("inputs.csv")));
    assert!(short.stdout == explicit.stdout);
}

// ------------------------------------------------------------------ 7. --paper and solvers

#[test]
fn paper_preset_runs_and_differs_from_default() {
    let config = shipped_config("paper.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");
    let (big_n, steps, n) = dims_of_run(dir.path());

    let default = ok(&mut estimate(&config, &meas, &[]));
    let paper = ok(&mut estimate(&config, &meas, &["--paper"]));
    let paper_csv = Csv::parse(&paper.stdout);
    assert_eq!(paper_csv.header, estimates_header(n));
    assert_eq!(paper_csv.indices(), all_indices(big_n, steps));
    assert!(paper.stdout != default.stdout, "--paper changed nothing");

    // The preset's choices, and an explicit option winning over it (docs/theory.md §6).
    let json = |extra: &[&str]| -> serde_json::Value {
        let mut args = vec!["--format", "json"];
        args.extend_from_slice(extra);
        serde_json::from_slice(&ok(&mut estimate(&config, &meas, &args)).stdout).unwrap()
    };
    let v = json(&["--paper"]);
    assert_eq!(v["options"]["solver"], "transfer");
    assert_eq!(v["options"]["interconnect_from"], "predicted");
    assert_eq!(v["options"]["second_moment"], "paper");
    let v = json(&["--paper", "--solver", "banded"]);
    assert_eq!(v["options"]["solver"], "banded");
    assert_eq!(v["options"]["interconnect_from"], "predicted");
    // The output stays x̂(t|t) under --paper.
    assert_eq!(v["options"]["output"], "filtered");
}

/// A config of a long chain whose transfer recursion blows up (docs/theory.md §2).
const LONG_CHAIN: &str = "\
subsystems = 60
steps = 30
seed = 5

[interconnection]
plus = 1
minus = 1

[model]
A = [[0.7, 0.1], [-0.1, 0.6]]
B = [[0.1, 0.1], [0.0, 0.1]]
D = [[1.0, 0.0], [0.0, 1.0]]
G = [[0.25, -0.3], [0.28, 0.12]]
J = [[1.0, 0.0]]
M = [[0.05]]
Q = [[0.01, 0.0], [0.0, 0.01]]

[dropout]
p = 0.8

[initial]
cov = [[1.0, 0.0], [0.0, 1.0]]
";

#[test]
fn transfer_solver_warns_on_a_long_chain() {
    let dir = tmp();
    let config = dir.path().join("long.toml");
    write(&config, LONG_CHAIN);
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");

    let out = ok(&mut estimate(&config, &meas, &["--solver", "transfer"]));
    let w = warnings(&out);
    assert!(
        w.iter().any(|l| l.contains("transfer")),
        "no `warning: ` line mentioning transfer: {w:?}"
    );
    let banded = ok(&mut estimate(&config, &meas, &["--solver", "banded"]));
    assert!(
        !warnings(&banded).iter().any(|l| l.contains("transfer")),
        "banded solver warned about transfer"
    );
}

#[test]
fn transfer_solver_matches_banded_where_it_is_accurate() {
    let dir = tmp();
    // paper.toml (N = 6), and platoon with an invertible G22 (its own G is 0, on which the
    // transfer recursion is undefined).
    let platoon_g22 = dir.path().join("platoon_g22.toml");
    let platoon = text(&read(&shipped_config("platoon.toml")));
    assert!(platoon.contains("\nG = [[0.0, 0.0], [0.0, 0.0]]\n"));
    write(
        &platoon_g22,
        platoon.replace(
            "\nG = [[0.0, 0.0], [0.0, 0.0]]\n",
            "\nG = [[0.0, 0.0], [0.0, 0.8]]\n",
        ),
    );
    for config in [shipped_config("paper.toml"), platoon_g22] {
        let run = dir
            .path()
            .join(config.file_stem().unwrap().to_string_lossy().into_owned());
        simulate(&config, &run, &[]);
        let meas = run.join("measurements.csv");
        let transfer = ok(&mut estimate(&config, &meas, &["--solver", "transfer"]));
        let banded = ok(&mut estimate(&config, &meas, &["--solver", "banded"]));
        assert!(
            !warnings(&transfer).iter().any(|l| l.contains("transfer")),
            "{}: {:?}",
            config.display(),
            warnings(&transfer)
        );
        let diff = max_abs_diff(&Csv::parse(&transfer.stdout), &Csv::parse(&banded.stdout));
        assert!(
            diff <= 1e-9,
            "{}: transfer vs banded {diff:e}",
            config.display()
        );
    }
}

#[test]
fn transfer_solver_rejects_singular_g22_on_platoon() {
    // platoon.toml has G = 0: every interior G22 is singular, which the transfer solver
    // cannot handle (docs/theory.md §2); that is bad input, and the message points to banded.
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let out = fails(
        &mut estimate(
            &config,
            &dir.path().join("measurements.csv"),
            &["--solver", "transfer"],
        ),
        2,
    );
    let msg = one_error_line(&out);
    assert!(msg.contains("G22") && msg.contains("banded"), "{msg}");
}

// ---------------------------------------------------------------------------- 8. --predicted

#[test]
fn predicted_output() {
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");
    let truth = dir.path().join("truth.csv");
    let (big_n, steps, n) = dims_of_run(dir.path());

    let filtered = Csv::parse(&ok(&mut estimate(&config, &meas, &[])).stdout);
    let out = ok(estimate(&config, &meas, &["--predicted"])
        .arg("--truth")
        .arg(&truth));
    let mut predicted = Csv::parse(&out.stdout);
    // The first column says the rows hold predicted estimates; the rest are those of any
    // estimates file.
    assert_eq!(predicted.header[0], "t_given");
    predicted.header[0] = "t".into();
    check_estimates(&predicted, big_n, steps, n);
    assert_eq!(predicted.rows.len(), filtered.rows.len());

    let (fv, pv) = (filtered.values(), predicted.values());
    for (k, (f, p)) in fv.iter().zip(&pv).enumerate() {
        assert!(
            f[..n] != p[..n],
            "row {:?}: predicted estimate equals the filtered one",
            predicted.rows[k]
        );
    }
    // Row t holds T(t+1); the filtered P(t+1|t+1) = T(t+1) − (a PSD term) is no larger on the
    // diagonal.
    let diag = diag_positions(n);
    for k in 0..(steps - 1) * big_n {
        for &d in &diag {
            let (prior, post) = (pv[k][d], fv[k + big_n][d]);
            assert!(
                post <= prior * (1.0 + 1e-12),
                "row {:?}: P(t+1|t+1) {post} > T(t+1) {prior}",
                predicted.rows[k]
            );
        }
    }

    assert!(
        stderr_lines(&out)
            .iter()
            .any(|l| l.starts_with("accuracy: ") && l.contains("RMSE")),
        "{}",
        describe(&out)
    );
    // In JSON, the last row is not scored: (T − 1)·N terms.
    let out = ok(
        estimate(&config, &meas, &["--predicted", "--format", "json"])
            .arg("--truth")
            .arg(&truth),
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["options"]["output"], "predicted");
    assert_eq!(v["columns"][0], "t_given");
    let acc = &v["accuracy"];
    assert!(acc["rmse"].is_array(), "{acc}");
    if let Some(terms) = acc.get("terms") {
        assert_eq!(terms.as_u64(), Some(((steps - 1) * big_n) as u64));
    }
}

// ----------------------------------------------------------------------------- 9. piping

#[test]
fn measurements_from_standard_input() {
    let config = shipped_config("heat_rod.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");
    let truth = dir.path().join("truth.csv");

    let from_file = ok(estimate(&config, &meas, &[]).arg("--truth").arg(&truth));
    let piped = ok(estimate(&config, Path::new("-"), &[])
        .arg("--truth")
        .arg(&truth)
        .write_stdin(read(&meas)));
    assert!(!piped.stdout.is_empty());
    assert!(
        piped.stdout == from_file.stdout,
        "stdin differs from the file"
    );
    assert_eq!(piped.stderr, from_file.stderr);

    // `--out -` is standard output too.
    let dashed = ok(estimate(&config, Path::new("-"), &["--out", "-"]).write_stdin(read(&meas)));
    assert!(dashed.stdout == from_file.stdout);

    // Errors in piped data still name the line.
    let lines: Vec<String> = text(&read(&meas)).lines().map(str::to_string).collect();
    let bad = edit_line(&lines, 30, |x| last_cell(x, "x"));
    let out = fails(
        estimate(&config, Path::new("-"), &[]).write_stdin(bad.join("\n") + "\n"),
        2,
    );
    let msg = one_error_line(&out);
    assert!(names_line(&msg, 30), "{msg}");
}

// ---------------------------------------------------------------- 10. the mixture update

/// The detection figures recomputed from the `arrival` column and the truth's `gamma`:
/// `(Σ|π − γ|, lost, detected, received, false alarms)`.
fn detection_from_files(arrival: &[f64], truth: &Csv) -> (f64, u64, u64, u64, u64) {
    assert_eq!(arrival.len(), truth.rows.len());
    let mut d = (0.0, 0, 0, 0, 0);
    for (pi, row) in arrival.iter().zip(&truth.rows) {
        assert!((0.0..=1.0).contains(pi), "π = {pi}");
        let gamma: f64 = row.last().unwrap().parse().unwrap();
        d.0 += (pi - gamma).abs();
        if gamma == 0.0 {
            d.1 += 1;
            d.2 += u64::from(*pi < 0.5);
        } else {
            d.3 += 1;
            d.4 += u64::from(*pi < 0.5);
        }
    }
    d
}

/// On every shipped config with `Q > 0`, each filter with `--update mixture` writes `π` in a
/// last column `arrival`, reports detection figures that agree with that column and the
/// truth, and has a lower RMSE than the same filter with `--update linear`.
#[test]
fn mixture_update_detects_lost_measurements() {
    for config in shipped_configs().into_iter().filter(|c| !q_is_zero(c)) {
        let name = config.file_name().unwrap().to_string_lossy().to_string();
        let dir = tmp();
        simulate(&config, dir.path(), &[]);
        let meas = dir.path().join("measurements.csv");
        let truth_path = dir.path().join("truth.csv");
        let truth = Csv::read(&truth_path);
        let (_, _, n) = dims_of_run(dir.path());
        for filter in ["distributed", "joint", "centralized"] {
            let what = format!("{name}, {filter}");
            let run = |update: &str, format: &str| {
                ok(
                    estimate(&config, &meas, &["--filter", filter, "--update", update])
                        .args(["--format", format, "--truth"])
                        .arg(&truth_path),
                )
            };
            let rmse = |doc: &serde_json::Value| doc["accuracy"]["rmse_overall"].as_f64().unwrap();
            let linear = run("linear", "json");
            let linear: serde_json::Value = serde_json::from_slice(&linear.stdout).unwrap();
            let out = run("mixture", "json");
            let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
            assert!(
                rmse(&doc) < rmse(&linear),
                "{what}: mixture RMSE {} against linear {}",
                rmse(&doc),
                rmse(&linear)
            );
            assert_eq!(doc["options"]["update"], "mixture", "{what}");
            assert_eq!(linear["options"]["update"], "linear", "{what}");
            assert!(linear["detection"].is_null(), "{what}: linear has no π");
            // Nahi's update with unknown dropouts has no density; the mixture update has one.
            assert!(linear["loglik"].is_null(), "{what}");
            assert!(doc["loglik"].as_f64().is_some_and(f64::is_finite), "{what}");

            let columns = doc["columns"].as_array().unwrap();
            assert_eq!(columns.last().unwrap(), "arrival", "{what}");
            // The CSV carries the JSON's numbers (serde_json may be off by one unit in the
            // last place), `arrival` last and no cross-covariances.
            let csv = Csv::parse(&run("mixture", "csv").stdout);
            let mut header = estimates_header(n);
            header.push("arrival".into());
            assert_eq!(csv.header, header, "{what}");
            let width = 2 + n + n * (n + 1) / 2;
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-15 * a.abs().max(1.0);
            for (row, json_row) in csv.rows.iter().zip(doc["estimates"].as_array().unwrap()) {
                let json_row = json_row.as_array().unwrap();
                for (cell, v) in row[..width].iter().zip(json_row) {
                    let (a, b) = (cell.parse::<f64>().unwrap(), v.as_f64().unwrap());
                    assert!(close(a, b), "{what}: {a} against {b}");
                }
                let pi: f64 = row.last().unwrap().parse().unwrap();
                let json_pi = json_row.last().unwrap().as_f64().unwrap();
                assert!(close(pi, json_pi), "{what}: {pi} against {json_pi}");
            }
            let arrival: Vec<f64> = csv
                .rows
                .iter()
                .map(|row| row.last().unwrap().parse().unwrap())
                .collect();
            let (abs_sum, lost, detected, received, false_alarms) =
                detection_from_files(&arrival, &truth);
            let det = &doc["detection"];
            assert_eq!(det["lost"].as_u64(), Some(lost), "{what}");
            assert_eq!(det["detected"].as_u64(), Some(detected), "{what}");
            assert_eq!(det["received"].as_u64(), Some(received), "{what}");
            assert_eq!(det["false_alarms"].as_u64(), Some(false_alarms), "{what}");
            let mean = abs_sum / (lost + received) as f64;
            assert!(
                (det["mean_abs_error"].as_f64().unwrap() - mean).abs() < 1e-12,
                "{what}"
            );
            // Far better than chance: a lost measurement is flagged far more often than a
            // received one.
            let rate = |k: u64, of: u64| k as f64 / of as f64;
            assert!(
                rate(detected, lost) > 4.0 * rate(false_alarms, received),
                "{what}: {detected} of {lost} detected, {false_alarms} of {received} false alarms"
            );
            let line = stderr_lines(&out)
                .into_iter()
                .find(|l| l.starts_with("detection: "))
                .unwrap_or_else(|| panic!("{what}: no detection line"));
            assert!(line.contains(&format!("{detected} of {lost}")), "{line}");
        }
    }
}

/// A single subsystem with inputs and a `p` list: the three filters with the mixture
/// update are the same filter, and write the same estimates and `π`.
#[test]
fn mixture_update_agrees_across_filters_on_one_subsystem() {
    let dir = tmp();
    let config = dir.path().join("one.toml");
    write(
        &config,
        "subsystems = 1\nsteps = 80\nseed = 5\n\n[interconnection]\nplus = 1\nminus = 1\n\n\
         [model]\nA = [[0.95, 0.1], [-0.1, 0.9]]\nB = [[0.1, 0.0], [0.0, 0.1]]\n\
         C = [[0.3], [0.0]]\nD = [[0.5, 0.0], [0.0, 0.5]]\nG = [[0.2, 0.0], [0.0, 0.2]]\n\
         J = [[1.0, 0.5]]\nR = [[0.2]]\nM = [[0.04]]\nQ = [[0.02, 0.0], [0.0, 0.01]]\n\n\
         [dropout]\np = [0.6]\n\n[initial]\nmean = [1.0, 0.0]\ncov = [[1.0, 0.0], [0.0, 1.0]]\n\n\
         [input]\nkind = \"sine\"\nperiod = 11.0\n",
    );
    let run = dir.path().join("run");
    simulate(&config, &run, &[]);
    let meas = run.join("measurements.csv");
    let mixture = |filter: &str| {
        let out = ok(&mut estimate(
            &config,
            &meas,
            &["--filter", filter, "--update", "mixture"],
        ));
        Csv::parse(&out.stdout)
    };
    let distributed = mixture("distributed");
    for filter in ["joint", "centralized"] {
        let other = mixture(filter);
        let diff = max_abs_diff(&distributed, &other);
        assert!(diff < 1e-9, "{filter}: {diff}");
    }
    let linear = Csv::parse(&ok(&mut estimate(&config, &meas, &[])).stdout);
    assert!(max_abs_diff(&linear, &distributed.without_last_column()) > 1e-3);
}

/// `--update mixture` with `--dropouts known` is bad input: there is nothing to detect.
#[test]
fn mixture_update_refuses_known_dropouts() {
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");
    let out = fails(
        &mut estimate(
            &config,
            &meas,
            &["--update", "mixture", "--dropouts", "known"],
        ),
        2,
    );
    let msg = one_error_line(&out);
    assert!(msg.contains("nothing to detect"), "{msg}");
}

/// `--update mixture --smooth`: each smoother runs on the mixture filter's moments, keeps
/// the forward pass's `π` in the `arrival` column (the same as the filter's) with the same
/// detection figures, and has a lower RMSE than the filter.
#[test]
fn mixture_update_smooths() {
    let config = shipped_config("heat_rod.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &[]);
    let meas = dir.path().join("measurements.csv");
    let truth = dir.path().join("truth.csv");
    for filter in ["distributed", "joint", "centralized"] {
        let run = |extra: &[&str]| {
            let out = ok(
                estimate(&config, &meas, &["--filter", filter, "--update", "mixture"])
                    .args(["--format", "json", "--truth"])
                    .arg(&truth)
                    .args(extra),
            );
            serde_json::from_slice::<serde_json::Value>(&out.stdout).unwrap()
        };
        let (filtered, smoothed) = (run(&[]), run(&["--smooth"]));
        let arrival = |doc: &serde_json::Value| -> Vec<serde_json::Value> {
            doc["estimates"]
                .as_array()
                .unwrap()
                .iter()
                .map(|row| row.as_array().unwrap().last().unwrap().clone())
                .collect()
        };
        assert_eq!(
            smoothed["columns"].as_array().unwrap().last().unwrap(),
            "arrival"
        );
        assert!(arrival(&smoothed) == arrival(&filtered), "{filter}: π");
        assert_eq!(smoothed["detection"], filtered["detection"], "{filter}");
        assert_eq!(smoothed["options"]["output"], "smoothed", "{filter}");
        let rmse = |doc: &serde_json::Value| doc["accuracy"]["rmse_overall"].as_f64().unwrap();
        assert!(
            rmse(&smoothed) < rmse(&filtered),
            "{filter}: smoothed {} against filtered {}",
            rmse(&smoothed),
            rmse(&filtered)
        );
    }
}

/// With known dropouts the log-likelihood of the measurements is in the JSON and, with
/// `--verbose`, on an `info:` line; the joint filter at full band gives the centralized
/// filter's (exact) value.
#[test]
fn known_dropout_log_likelihood_is_reported() {
    let config = shipped_config("platoon.toml");
    let dir = tmp();
    simulate(&config, dir.path(), &["--mark-missing"]);
    let meas = dir.path().join("measurements.csv");
    let loglik = |extra: &[&str]| {
        let out = ok(estimate(
            &config,
            &meas,
            &["--dropouts", "known", "--format", "json", "-v"],
        )
        .args(extra));
        let doc: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let value = doc["loglik"].as_f64().expect("a loglik number");
        let line = stderr_lines(&out)
            .into_iter()
            .find(|l| l.starts_with("info: log-likelihood of the measurements: "))
            .expect("an info line");
        assert!(
            line.contains(&format!("{value:.6e}")),
            "{line} against {value}"
        );
        value
    };
    let central = loglik(&["--filter", "centralized"]);
    let joint = loglik(&[
        "--filter",
        "joint",
        "--band",
        "19",
        "--band-tol",
        "0",
        "--loading",
        "0",
    ]);
    assert!(
        (central - joint).abs() < 1e-9 * central.abs(),
        "{central} vs {joint}"
    );
    loglik(&[]);
}

/// Estimates as the data arrive: the measurements come through a named pipe and the
/// estimates leave through another. With half of the steps written (and the writer still
/// open), the estimates of exactly those steps arrive before the rest is written; then the
/// rest. Every wait has a time limit, and the process is killed if one passes, so the test
/// cannot hang.
#[cfg(unix)]
#[test]
fn estimates_come_step_by_step_through_named_pipes() {
    use std::io::{BufRead, BufReader, Write};
    use std::sync::mpsc;
    use std::time::Duration;

    let dir = tmp();
    let d = dir.path();
    let config = shipped_config("platoon.toml");
    simulate(&config, &d.join("run"), &[]);
    let (big_n, steps, half) = (20, 200, 100);
    let meas = std::fs::read_to_string(d.join("run/measurements.csv")).unwrap();
    let lines: Vec<&str> = meas.lines().collect();
    assert_eq!(lines.len(), 1 + big_n * steps);
    let fifo = |name: &str| {
        let path = d.join(name);
        let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
        assert_eq!(
            unsafe { libc::mkfifo(c.as_ptr(), 0o600) },
            0,
            "mkfifo {name}"
        );
        path
    };
    let (meas_fifo, out_fifo) = (fifo("meas.fifo"), fifo("out.fifo"));
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_sisfilt"))
        .current_dir(d)
        .args(["estimate", "--config", config.to_str().unwrap()])
        .args([
            "--meas",
            "meas.fifo",
            "--inputs",
            "run/inputs.csv",
            "--out",
            "out.fifo",
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The reader of the estimates: each line as it comes.
    let (line_tx, line_rx) = mpsc::channel::<String>();
    std::thread::spawn(move || {
        let reader = BufReader::new(std::fs::File::open(out_fifo).unwrap());
        for line in reader.lines() {
            if line_tx.send(line.unwrap()).is_err() {
                break;
            }
        }
    });
    // The writer of the measurements: half, then (when told) the rest.
    let (go_tx, go_rx) = mpsc::channel::<()>();
    let text: Vec<String> = lines.iter().map(|l| format!("{l}\n")).collect();
    let writer = std::thread::spawn(move || {
        let mut w = std::fs::OpenOptions::new()
            .write(true)
            .open(meas_fifo)
            .unwrap();
        let first = 1 + big_n * half;
        w.write_all(text[..first].concat().as_bytes()).unwrap();
        w.flush().unwrap();
        if go_rx.recv_timeout(Duration::from_secs(60)).is_ok() {
            w.write_all(text[first..].concat().as_bytes()).unwrap();
        }
    });
    let mut received = Vec::new();
    let mut wait_for = |count: usize, received: &mut Vec<String>| {
        while received.len() < count {
            match line_rx.recv_timeout(Duration::from_secs(30)) {
                Ok(line) => received.push(line),
                Err(_) => {
                    let _ = child.kill();
                    panic!("only {} of {count} lines arrived in time", received.len());
                }
            }
        }
    };
    wait_for(1 + big_n * half, &mut received);
    assert_eq!(received[0], estimates_header(2).join(","));
    assert!(
        received
            .last()
            .unwrap()
            .starts_with(&format!("{half},{big_n},"))
    );
    // Nothing beyond the steps written: the next line would be step half + 1.
    assert!(line_rx.recv_timeout(Duration::from_millis(300)).is_err());
    go_tx.send(()).unwrap();
    writer.join().unwrap();
    wait_for(1 + big_n * steps, &mut received);
    let status = child.wait().unwrap();
    assert!(status.success());
    assert!(
        received
            .last()
            .unwrap()
            .starts_with(&format!("{steps},{big_n},"))
    );
}

/// Smoothing needs the whole file: asked on a stream (standard input), `estimate` says so,
/// and still writes every smoothed step at the end.
#[test]
fn smoothing_a_stream_says_it_waits_for_the_end() {
    let dir = tmp();
    let d = dir.path();
    let config = shipped_config("paper.toml");
    simulate(&config, d, &[]);
    let out = ok(
        estimate(&config, Path::new("-"), &["--smooth", "--out", "s.csv"])
            .current_dir(d)
            .write_stdin(read(&d.join("measurements.csv"))),
    );
    let lines = stderr_lines(&out);
    assert!(
        lines
            .iter()
            .any(|l| l.starts_with("warning: --smooth: standard input is a stream")),
        "{lines:?}"
    );
    let file = read(&d.join("s.csv"));
    assert_eq!(text(&file).lines().count(), 1 + 6 * 150);
}

/// A config without `steps` serves `estimate` (the file says how many steps it has),
/// `check` (which says T is not set) and `simulate --steps`.
#[test]
fn a_config_without_steps_serves_estimate_check_and_simulate_with_steps() {
    let dir = tmp();
    let d = dir.path();
    let shipped = std::fs::read_to_string(shipped_config("platoon.toml")).unwrap();
    let without: String = shipped
        .lines()
        .filter(|l| !l.starts_with("steps"))
        .map(|l| format!("{l}\n"))
        .collect();
    assert_ne!(without.len(), shipped.len());
    write(&d.join("nosteps.toml"), &without);
    let config = d.join("nosteps.toml");
    ok(sisfilt()
        .arg("simulate")
        .arg(&config)
        .args(["--steps", "37", "--out"])
        .arg(d.join("run")));
    let meas = text(&read(&d.join("run/measurements.csv")));
    assert_eq!(meas.lines().count(), 1 + 20 * 37);
    let out = ok(
        estimate(&config, &d.join("run/measurements.csv"), &["--out", "-"])
            .arg("--inputs")
            .arg(d.join("run/inputs.csv")),
    );
    assert_eq!(text(&out.stdout).lines().count(), 1 + 20 * 37);
    let out = ok(sisfilt().arg("check").arg(&config));
    let report = text(&out.stdout);
    assert!(report.contains("T not set"), "{report}");
    assert!(report.contains("t ≥ 1:"), "{report}");
    assert!(!report.contains("smoothing memory"), "{report}");
}
