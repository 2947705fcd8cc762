//! Config validation (docs/theory.md §13): every kind of bad config is rejected with a message that names
//! the file and the TOML key (or, for errors the TOML parser finds, the line).

use std::path::PathBuf;

use crate::common::{one_error_line, sisfilt, write_file};
use sisfilt::config::ConfigSource;
use sisfilt::model::Model;

const NAME: &str = "test.toml";

/// A valid config with every section: n = 2, m = 1, q = 1, plus = minus = 1, N = 4.
const BASE: &str = r#"subsystems = 4
steps = 10
seed = 5

[interconnection]
plus = 1
minus = 1

[model]
A = [[0.9, 0.1], [0.0, 0.8]]
B = [[0.1, 0.1], [0.0, 0.0]]
C = [[0.0], [1.0]]
D = [[0.5, 0.0], [0.5, 0.0]]
G = [[0.2, 0.0], [0.0, 0.2]]
H = [[0.0], [0.0]]
J = [[1.0, 0.0]]
R = [[0.0]]
M = [[0.05]]
Q = [[0.01, 0.0], [0.0, 0.01]]

[dropout]
p = 0.8

[initial]
mean = [0.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[input]
kind = "sine"
amplitude = 1.0
period = 50.0
phase = 0.0
"#;

/// `BASE` with whole lines replaced; each `from` must be a line of the text (so that a typo in
/// a test cannot silently leave the config valid). An empty `to` deletes the line.
fn edit(text: &str, edits: &[(&str, &str)]) -> String {
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for &(from, to) in edits {
        let k = lines
            .iter()
            .position(|l| l == from)
            .unwrap_or_else(|| panic!("line {from:?} not in the config"));
        if to.is_empty() {
            lines.remove(k);
        } else {
            lines[k] = to.to_string();
        }
    }
    lines.join("\n") + "\n"
}

fn with(edits: &[(&str, &str)]) -> String {
    edit(BASE, edits)
}

/// `BASE` plus an `[[override]]` table with the given body lines.
fn with_override(body: &str) -> String {
    format!("{BASE}\n[[override]]\n{body}\n")
}

/// Parses and validates; returns the error message of whichever stage fails.
fn load(text: &str) -> Result<Model, String> {
    let src = ConfigSource::from_text(NAME, PathBuf::from("."), text.to_string())
        .map_err(|e| e.to_string())?;
    Model::from_config(&src).map_err(|e| e.to_string())
}

fn error_of(text: &str) -> String {
    match load(text) {
        Ok(_) => panic!("config accepted:\n{text}"),
        Err(msg) => {
            assert!(
                msg.starts_with(NAME),
                "message does not name the file: {msg}"
            );
            assert!(!msg.contains('\n'), "message is not one line: {msg:?}");
            msg
        }
    }
}

/// The error must name `key` as the TOML key path, in the form `file: key: …`.
fn assert_key_error(text: &str, key: &str, also: &[&str]) -> String {
    let msg = error_of(text);
    assert!(
        msg.starts_with(&format!("{NAME}: {key}: ")),
        "message does not name the key `{key}`: {msg}"
    );
    for a in also {
        assert!(msg.contains(a), "message lacks {a:?}: {msg}");
    }
    msg
}

/// The error must name the line (TOML parser errors) and contain each of `also`.
fn assert_line_error(text: &str, line: usize, also: &[&str]) -> String {
    let msg = error_of(text);
    assert!(
        msg.starts_with(&format!("{NAME}: line {line}: ")),
        "message does not name line {line}: {msg}"
    );
    for a in also {
        assert!(msg.contains(a), "message lacks {a:?}: {msg}");
    }
    msg
}

/// 1-based line number of `needle` (a whole line) in `text`.
fn line_of(text: &str, needle: &str) -> usize {
    text.lines()
        .position(|l| l == needle)
        .expect("line present")
        + 1
}

#[test]
fn base_config_is_valid() {
    let model = load(BASE).unwrap();
    let d = model.dims;
    assert_eq!((d.n, d.m, d.q, d.plus, d.minus), (2, 1, 1, 1, 1));
    assert_eq!(
        (model.subsystems, model.steps, model.seed),
        (4, Some(10), 5)
    );
}

// ---------------------------------------------------------------- TOML syntax and structure

#[test]
fn malformed_toml_names_the_line() {
    let text = with(&[("steps = 10", "steps = = 10")]);
    assert_line_error(&text, 2, &[]);
    let text = with(&[("[model]", "[model")]);
    assert_line_error(&text, line_of(BASE, "[model]"), &[]);
    let text = with(&[("p = 0.8", "p 0.8")]);
    assert_line_error(&text, line_of(BASE, "p = 0.8"), &[]);
}

#[test]
fn unknown_top_level_key() {
    let text = with(&[("seed = 5", "seed = 5\nsubsytems = 4")]);
    assert_line_error(&text, 4, &["`subsytems`"]);
}

#[test]
fn unknown_key_in_model() {
    let text = with(&[("M = [[0.05]]", "M = [[0.05]]\nK = [[1.0]]")]);
    assert_line_error(&text, line_of(BASE, "M = [[0.05]]") + 1, &["`K`"]);
}

#[test]
fn unknown_key_in_other_tables() {
    let text = with(&[("p = 0.8", "p = 0.8\nprob = 0.8")]);
    assert_line_error(&text, line_of(BASE, "p = 0.8") + 1, &["`prob`"]);
    let text = with_override("steps = [1, 2]\nP = 0.5");
    let line = text.lines().count();
    assert_line_error(&text, line, &["`P`"]);
}

/// `steps` may be left out (`estimate` takes `T` from its data); what needs it names it.
#[test]
fn missing_steps() {
    let model = load(&with(&[("steps = 10", "")])).unwrap();
    assert_eq!(model.steps, None);
    let msg = model.horizon().unwrap_err().to_string();
    assert!(msg.starts_with(&format!("{NAME}: steps: not set")), "{msg}");
}

#[test]
fn missing_initial_cov() {
    let text = with(&[("cov = [[1.0, 0.0], [0.0, 1.0]]", "")]);
    let msg = error_of(&text);
    assert!(msg.contains("missing") && msg.contains("`cov`"), "{msg}");
    assert!(msg.starts_with(&format!("{NAME}: line ")), "{msg}");
}

#[test]
fn missing_dropout() {
    let text = with(&[("[dropout]", ""), ("p = 0.8", "")]);
    let msg = error_of(&text);
    assert!(
        msg.contains("missing") && msg.contains("`dropout`"),
        "{msg}"
    );
}

#[test]
fn missing_required_matrix() {
    let text = with(&[("J = [[1.0, 0.0]]", "")]);
    let msg = error_of(&text);
    assert!(msg.contains("missing") && msg.contains("`J`"), "{msg}");
}

#[test]
fn non_numeric_entry_names_the_line() {
    let text = with(&[(
        "A = [[0.9, 0.1], [0.0, 0.8]]",
        r#"A = [[0.9, "x"], [0.0, 0.8]]"#,
    )]);
    assert_line_error(&text, line_of(BASE, "A = [[0.9, 0.1], [0.0, 0.8]]"), &[]);
    let text = with(&[("p = 0.8", r#"p = "high""#)]);
    let msg = error_of(&text);
    assert!(msg.starts_with(&format!("{NAME}: line ")), "{msg}");
}

// ---------------------------------------------------------------- shapes

#[test]
fn wrong_shape_a() {
    let text = with(&[(
        "A = [[0.9, 0.1], [0.0, 0.8]]",
        "A = [[0.9, 0.1, 0.0], [0.0, 0.8, 0.0]]",
    )]);
    assert_key_error(&text, "model.A", &["2 × 3"]);
    let text = with(&[("A = [[0.9, 0.1], [0.0, 0.8]]", "A = []")]);
    assert_key_error(&text, "model.A", &["0 × 0"]);
}

#[test]
fn wrong_shape_b() {
    let text = with(&[(
        "B = [[0.1, 0.1], [0.0, 0.0]]",
        "B = [[0.1, 0.1, 0.0], [0.0, 0.0, 0.0]]",
    )]);
    let msg = assert_key_error(&text, "model.B", &["2 × 2", "found 2 × 3"]);
    assert_eq!(
        msg,
        "test.toml: model.B: expected 2 × 2 (n × (plus+minus)), found 2 × 3"
    );
}

#[test]
fn wrong_shape_c() {
    let text = with(&[("C = [[0.0], [1.0]]", "C = [[1.0]]")]);
    assert_key_error(&text, "model.C", &["2 × 1", "found 1 × 1"]);
}

#[test]
fn wrong_shape_d() {
    let text = with(&[("D = [[0.5, 0.0], [0.5, 0.0]]", "D = [[0.5, 0.0]]")]);
    assert_key_error(&text, "model.D", &["2 × 2", "found 1 × 2"]);
}

#[test]
fn wrong_shape_g() {
    let text = with(&[("G = [[0.2, 0.0], [0.0, 0.2]]", "G = [[0.2]]")]);
    assert_key_error(&text, "model.G", &["2 × 2", "found 1 × 1"]);
}

#[test]
fn wrong_shape_h() {
    let text = with(&[("H = [[0.0], [0.0]]", "H = [[0.0], [0.0], [0.0]]")]);
    assert_key_error(&text, "model.H", &["2 × 1", "found 3 × 1"]);
}

#[test]
fn wrong_shape_j() {
    let text = with(&[("J = [[1.0, 0.0]]", "J = [[1.0, 0.0, 0.0]]")]);
    assert_key_error(&text, "model.J", &["1 × 2", "found 1 × 3"]);
}

#[test]
fn wrong_shape_r() {
    let text = with(&[("R = [[0.0]]", "R = [[0.0], [0.0]]")]);
    assert_key_error(&text, "model.R", &["1 × 1", "found 2 × 1"]);
}

#[test]
fn wrong_shape_m() {
    let text = with(&[("M = [[0.05]]", "M = [[0.05, 0.0], [0.0, 0.05]]")]);
    assert_key_error(&text, "model.M", &["1 × 1", "found 2 × 2"]);
}

#[test]
fn wrong_shape_q() {
    let text = with(&[("Q = [[0.01, 0.0], [0.0, 0.01]]", "Q = [[0.01]]")]);
    assert_key_error(&text, "model.Q", &["2 × 2", "found 1 × 1"]);
}

#[test]
fn wrong_shape_in_override() {
    let text = with_override("steps = [2, 3]\nB = [[0.1], [0.0]]");
    assert_key_error(&text, "override[1].B", &["2 × 2", "found 2 × 1"]);
}

#[test]
fn wrong_shape_initial() {
    let text = with(&[("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[1.0]]")]);
    assert_key_error(&text, "initial.cov", &["2 × 2", "found 1 × 1"]);
    let text = with(&[("mean = [0.0, 0.0]", "mean = [0.0, 0.0, 0.0]")]);
    assert_key_error(&text, "initial.mean", &["3"]);
}

#[test]
fn ragged_rows() {
    let text = with(&[("A = [[0.9, 0.1], [0.0, 0.8]]", "A = [[0.9, 0.1], [0.0]]")]);
    assert_key_error(&text, "model.A", &["ragged"]);
    let text = with(&[("G = [[0.2, 0.0], [0.0, 0.2]]", "G = [[0.2, 0.0], [0.0]]")]);
    assert_key_error(&text, "model.G", &["ragged"]);
    let text = with(&[(
        "cov = [[1.0, 0.0], [0.0, 1.0]]",
        "cov = [[1.0, 0.0], [0.0, 1.0, 0.0]]",
    )]);
    assert_key_error(&text, "initial.cov", &["ragged"]);
}

#[test]
fn column_counts_of_c_h_r_disagree() {
    // C says m = 1, H says m = 2.
    let text = with(&[("H = [[0.0], [0.0]]", "H = [[0.0, 0.0], [0.0, 0.0]]")]);
    assert_key_error(&text, "model.H", &["model.C", "1", "2"]);
    // C says m = 1, R says m = 2.
    let text = with(&[("R = [[0.0]]", "R = [[0.0, 0.0]]")]);
    assert_key_error(&text, "model.R", &["model.C"]);
    // Without C: H says m = 1, R says m = 3.
    let text = with(&[
        ("C = [[0.0], [1.0]]", ""),
        ("R = [[0.0]]", "R = [[0.0, 0.0, 0.0]]"),
    ]);
    assert_key_error(&text, "model.R", &["model.H"]);
}

// ---------------------------------------------------------------- values

#[test]
fn nan_and_inf_entries_name_the_key() {
    let text = with(&[(
        "A = [[0.9, 0.1], [0.0, 0.8]]",
        "A = [[0.9, nan], [0.0, 0.8]]",
    )]);
    assert_key_error(&text, "model.A", &["finite"]);
    let text = with(&[("M = [[0.05]]", "M = [[inf]]")]);
    assert_key_error(&text, "model.M", &["finite"]);
    let text = with(&[(
        "D = [[0.5, 0.0], [0.5, 0.0]]",
        "D = [[0.5, 0.0], [-inf, 0.0]]",
    )]);
    assert_key_error(&text, "model.D", &["finite"]);
    let text = with(&[("p = 0.8", "p = nan")]);
    assert_key_error(&text, "dropout.p", &[]);
    let text = with(&[("mean = [0.0, 0.0]", "mean = [0.0, inf]")]);
    assert_key_error(&text, "initial.mean", &["finite"]);
    let text = with(&[(
        "cov = [[1.0, 0.0], [0.0, 1.0]]",
        "cov = [[nan, 0.0], [0.0, 1.0]]",
    )]);
    assert_key_error(&text, "initial.cov", &["finite"]);
    let text = with(&[("amplitude = 1.0", "amplitude = inf")]);
    assert_key_error(&text, "input.amplitude", &["finite"]);
    let text = with(&[("phase = 0.0", "phase = nan")]);
    assert_key_error(&text, "input.phase", &["finite"]);
    let text = with_override("steps = [1, 2]\nG = [[0.2, 0.0], [0.0, nan]]");
    assert_key_error(&text, "override[1].G", &["finite"]);
}

#[test]
fn m_not_positive_definite() {
    let text = with(&[("M = [[0.05]]", "M = [[0.0]]")]);
    assert_key_error(&text, "model.M", &["positive definite"]);
    let text = with(&[("M = [[0.05]]", "M = [[-1.0]]")]);
    assert_key_error(&text, "model.M", &["positive definite"]);
    // q = 2: PSD but singular.
    let text = with(&[
        ("J = [[1.0, 0.0]]", "J = [[1.0, 0.0], [0.0, 1.0]]"),
        ("R = [[0.0]]", "R = [[0.0], [0.0]]"),
        ("M = [[0.05]]", "M = [[1.0, 1.0], [1.0, 1.0]]"),
    ]);
    assert_key_error(&text, "model.M", &["positive definite"]);
    let text = with_override("M = [[0.0]]");
    assert_key_error(&text, "override[1].M", &["positive definite"]);
}

#[test]
fn q_not_positive_semidefinite() {
    let text = with(&[(
        "Q = [[0.01, 0.0], [0.0, 0.01]]",
        "Q = [[0.01, 0.0], [0.0, -0.01]]",
    )]);
    assert_key_error(&text, "model.Q", &["semidefinite"]);
    let text = with(&[(
        "Q = [[0.01, 0.0], [0.0, 0.01]]",
        "Q = [[1.0, 2.0], [2.0, 1.0]]",
    )]);
    assert_key_error(&text, "model.Q", &["semidefinite"]);
    // A PSD but singular Q is fine.
    let text = with(&[(
        "Q = [[0.01, 0.0], [0.0, 0.01]]",
        "Q = [[1.0, 1.0], [1.0, 1.0]]",
    )]);
    load(&text).unwrap();
    let text = with_override("subsystems = [2, 2]\nQ = [[-1.0, 0.0], [0.0, 0.0]]");
    assert_key_error(&text, "override[1].Q", &["semidefinite"]);
}

#[test]
fn initial_cov_not_positive_semidefinite() {
    let text = with(&[(
        "cov = [[1.0, 0.0], [0.0, 1.0]]",
        "cov = [[1.0, 2.0], [2.0, 1.0]]",
    )]);
    assert_key_error(&text, "initial.cov", &["semidefinite"]);
    // Zero is a valid P0 (a known initial state).
    let text = with(&[(
        "cov = [[1.0, 0.0], [0.0, 1.0]]",
        "cov = [[0.0, 0.0], [0.0, 0.0]]",
    )]);
    load(&text).unwrap();
}

#[test]
fn non_symmetric_covariances() {
    let text = with(&[(
        "Q = [[0.01, 0.0], [0.0, 0.01]]",
        "Q = [[0.01, 0.005], [0.0, 0.01]]",
    )]);
    assert_key_error(&text, "model.Q", &["symmetric"]);
    let text = with(&[(
        "cov = [[1.0, 0.0], [0.0, 1.0]]",
        "cov = [[1.0, 0.0], [0.5, 1.0]]",
    )]);
    assert_key_error(&text, "initial.cov", &["symmetric"]);
    let text = with(&[
        ("J = [[1.0, 0.0]]", "J = [[1.0, 0.0], [0.0, 1.0]]"),
        ("R = [[0.0]]", "R = [[0.0], [0.0]]"),
        ("M = [[0.05]]", "M = [[1.0, 0.1], [0.2, 1.0]]"),
    ]);
    assert_key_error(&text, "model.M", &["symmetric"]);
}

#[test]
fn p_outside_unit_interval() {
    let text = with(&[("p = 0.8", "p = 1.5")]);
    assert_key_error(&text, "dropout.p", &["1.5"]);
    let text = with(&[("p = 0.8", "p = -0.1")]);
    assert_key_error(&text, "dropout.p", &["-0.1"]);
    let text = with(&[("p = 0.8", "p = [0.5, 0.5, 1.2, 0.5]")]);
    assert_key_error(&text, "dropout.p", &["1.2"]);
    let text = with_override("p = 2.0");
    assert_key_error(&text, "override[1].p", &["2"]);
    // The bounds themselves are valid.
    load(&with(&[("p = 0.8", "p = [0.0, 1.0, 0, 1]")])).unwrap();
}

#[test]
fn p_list_of_wrong_length() {
    let text = with(&[("p = 0.8", "p = [0.5, 0.5, 0.5]")]);
    assert_key_error(&text, "dropout.p", &["4", "3"]);
    let text = with(&[("p = 0.8", "p = [0.5, 0.5, 0.5, 0.5, 0.5]")]);
    assert_key_error(&text, "dropout.p", &["5"]);
}

#[test]
fn override_subsystems_out_of_bounds() {
    let text = with_override("subsystems = [3, 5]\np = 0.5");
    assert_key_error(&text, "override[1].subsystems", &["[3, 5]"]);
    let text = with_override("subsystems = [0, 2]\np = 0.5");
    assert_key_error(&text, "override[1].subsystems", &["[0, 2]"]);
    let text = with_override("steps = [0, 2]\np = 0.5");
    assert_key_error(&text, "override[1].steps", &["[0, 2]"]);
    // The second override is the bad one.
    let text = format!(
        "{}\n[[override]]\nsubsystems = [1, 9]\np = 0.1\n",
        with_override("subsystems = [1, 4]\np = 0.5")
    );
    assert_key_error(&text, "override[2].subsystems", &[]);
    // Steps may reach past T (docs/theory.md §13).
    load(&with_override("steps = [5, 1000]\np = 0.5")).unwrap();
    load(&with_override(
        "subsystems = [4, 4]\nsteps = [11, 20]\np = 0.5",
    ))
    .unwrap();
}

#[test]
fn override_reversed_range() {
    let text = with_override("subsystems = [3, 2]\np = 0.5");
    assert_key_error(&text, "override[1].subsystems", &["[3, 2]"]);
    let text = with_override("steps = [7, 4]\np = 0.5");
    assert_key_error(&text, "override[1].steps", &["[7, 4]"]);
}

#[test]
fn subsystems_zero() {
    let text = with(&[("subsystems = 4", "subsystems = 0")]);
    assert_key_error(&text, "subsystems", &["0"]);
    let text = with(&[("subsystems = 4", "subsystems = -3")]);
    assert_key_error(&text, "subsystems", &["-3"]);
}

#[test]
fn steps_zero() {
    let text = with(&[("steps = 10", "steps = 0")]);
    assert_key_error(&text, "steps", &["0"]);
}

#[test]
fn negative_interconnection_size() {
    let text = with(&[("plus = 1", "plus = -1")]);
    assert_key_error(&text, "interconnection.plus", &["-1"]);
}

#[test]
fn sine_input_without_period() {
    let text = with(&[("period = 50.0", "")]);
    assert_key_error(&text, "input.period", &["sine"]);
    let text = with(&[("period = 50.0", "period = 0.0")]);
    assert_key_error(&text, "input.period", &[]);
    let text = with(&[("period = 50.0", "period = -2.0")]);
    assert_key_error(&text, "input.period", &[]);
}

#[test]
fn file_input_without_path() {
    let text = with(&[(r#"kind = "sine""#, r#"kind = "file""#)]);
    assert_key_error(&text, "input.path", &["file"]);
}

#[test]
fn unknown_input_kind() {
    let text = with(&[(r#"kind = "sine""#, r#"kind = "square""#)]);
    let msg = assert_line_error(&text, line_of(BASE, r#"kind = "sine""#), &[]);
    assert!(msg.contains("square"), "{msg}");
}

// ---------------------------------------------------------------- through the CLI

/// Runs `sisfilt check` on `text` written to a temp folder; asserts exit 2, empty stdout and
/// one `error: ` line naming the file; returns that line.
fn check_fails(text: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let path = write_file(dir.path(), "bad-config.toml", text);
    let out = sisfilt().arg("check").arg(&path).output().unwrap();
    assert_eq!(
        out.status.code(),
        Some(2),
        "exit code; stderr {:?}",
        out.stderr
    );
    assert!(
        out.stdout.is_empty(),
        "stdout not empty: {:?}",
        String::from_utf8_lossy(&out.stdout)
    );
    let line = one_error_line(&out.stderr);
    assert!(
        line.contains(&path.display().to_string()),
        "error does not name the file {}: {line}",
        path.display()
    );
    line
}

#[test]
fn cli_wrong_shape() {
    let line = check_fails(&with(&[(
        "B = [[0.1, 0.1], [0.0, 0.0]]",
        "B = [[0.1, 0.1, 0.0], [0.0, 0.0, 0.0]]",
    )]));
    assert!(
        line.ends_with("model.B: expected 2 × 2 (n × (plus+minus)), found 2 × 3"),
        "{line}"
    );
}

#[test]
fn cli_unknown_key() {
    let line = check_fails(&with(&[("M = [[0.05]]", "M = [[0.05]]\nK = [[1.0]]")]));
    assert!(line.contains("`K`"), "{line}");
    let want = format!("line {}", line_of(BASE, "M = [[0.05]]") + 1);
    assert!(line.contains(&want), "{line}");
}

#[test]
fn cli_malformed_toml() {
    let line = check_fails(&with(&[("steps = 10", "steps = = 10")]));
    assert!(line.contains("line 2"), "{line}");
}

#[test]
fn cli_missing_key() {
    let line = check_fails(&with(&[("cov = [[1.0, 0.0], [0.0, 1.0]]", "")]));
    assert!(line.contains("`cov`"), "{line}");
}

#[test]
fn cli_not_positive_definite() {
    let line = check_fails(&with(&[("M = [[0.05]]", "M = [[0.0]]")]));
    assert!(line.contains("model.M"), "{line}");
}

#[test]
fn cli_nan_entry() {
    let line = check_fails(&with(&[("p = 0.8", "p = inf")]));
    assert!(line.contains("dropout.p"), "{line}");
}

#[test]
fn cli_override_range() {
    let line = check_fails(&with_override("subsystems = [2, 9]\np = 0.5"));
    assert!(line.contains("override[1].subsystems"), "{line}");
}

#[test]
fn cli_missing_config_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("nope.toml");
    let out = sisfilt().arg("check").arg(&path).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(out.stdout.is_empty());
    let line = one_error_line(&out.stderr);
    assert!(line.contains("nope.toml"), "{line}");
}

#[test]
fn cli_simulate_rejects_bad_config_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_file(
        dir.path(),
        "bad.toml",
        &with(&[("Q = [[0.01, 0.0], [0.0, 0.01]]", "Q = [[0.01]]")]),
    );
    let out_dir = dir.path().join("out");
    let out = sisfilt()
        .arg("simulate")
        .arg(&path)
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(out.stdout.is_empty());
    let line = one_error_line(&out.stderr);
    assert!(
        line.contains("bad.toml") && line.contains("model.Q"),
        "{line}"
    );
    assert!(
        !out_dir.exists(),
        "simulate created its folder for a bad config"
    );
}
