//! `sisfilt check` (docs/theory.md §2, §13): dimensions, the spectral radius of `A_eff` (checked against
//! an independent dense computation), the instability warning and ill-posed interconnections.
#![allow(non_snake_case)]

use std::path::Path;

use crate::common::{
    Sub, dense_a_eff, dense_interconnect, mat, one_error_line, printed_radii, simulate_files,
    sisfilt, spectral_radius, toml_matrix, write_file,
};
use nalgebra::{DMatrix, DVector};

struct Run {
    code: Option<i32>,
    stdout: String,
    stderr: String,
    stderr_raw: Vec<u8>,
}

fn check(config: &Path) -> Run {
    let out = sisfilt().arg("check").arg(config).output().unwrap();
    Run {
        code: out.status.code(),
        stdout: String::from_utf8(out.stdout).unwrap(),
        stderr: String::from_utf8(out.stderr.clone()).unwrap(),
        stderr_raw: out.stderr,
    }
}

fn check_text(text: &str) -> (tempfile::TempDir, std::path::PathBuf, Run) {
    let dir = tempfile::tempdir().unwrap();
    let path = write_file(dir.path(), "chain.toml", text);
    let run = check(&path);
    (dir, path, run)
}

/// The `subs` of a config's `[model]`, one per subsystem (no overrides).
fn model_subs(raw: &toml::Value) -> Sub {
    let m = |key: &str| -> DMatrix<f64> {
        let rows = raw["model"][key].as_array().unwrap();
        let cols = rows[0].as_array().unwrap().len();
        DMatrix::from_fn(rows.len(), cols, |r, c| {
            let v = &rows[r].as_array().unwrap()[c];
            v.as_float().or(v.as_integer().map(|i| i as f64)).unwrap()
        })
    };
    Sub {
        A: m("A"),
        B: m("B"),
        D: m("D"),
        G: m("G"),
    }
}

/// Largest `N n` whose eigenvalues are taken with nalgebra here.
const DENSE_CHECK_MAX: usize = 40;

#[test]
fn shipped_configs_pass_with_dimensions_and_spectral_radius() {
    for config in crate::common::shipped_configs() {
        let text = std::fs::read_to_string(&config).unwrap();
        let raw: toml::Value = toml::from_str(&text).unwrap();
        let rows = |key: &str| {
            raw["model"]
                .get(key)
                .and_then(|m| m.as_array())
                .map(|a| a.len())
        };
        let cols = |key: &str| {
            raw["model"]
                .get(key)
                .and_then(|m| m.as_array())
                .and_then(|a| a.first())
                .and_then(|r| r.as_array())
                .map(|r| r.len())
        };
        let n = rows("A").unwrap();
        let q = rows("J").unwrap();
        let m = cols("C").or(cols("H")).or(cols("R")).unwrap_or(0);
        let big_n = raw["subsystems"].as_integer().unwrap() as usize;
        let plus = raw["interconnection"]["plus"].as_integer().unwrap() as usize;
        let minus = raw["interconnection"]["minus"].as_integer().unwrap() as usize;

        let run = check(&config);
        let name = config.display();
        assert_eq!(run.code, Some(0), "{name}: {}", run.stderr);
        assert!(
            !run.stderr.contains("error"),
            "{name}: stderr {}",
            run.stderr
        );
        for want in [
            format!("n = {n}"),
            format!("m = {m}"),
            format!("q = {q}"),
            format!("N = {big_n}"),
        ] {
            assert!(
                run.stdout.contains(&want),
                "{name}: no `{want}` in\n{}",
                run.stdout
            );
        }
        let radii = printed_radii(&run.stdout);
        assert!(
            !radii.is_empty(),
            "{name}: no spectral radius line in\n{}",
            run.stdout
        );

        // Without overrides there is one window, and its radius is that of the dense A_eff
        // built here. nalgebra's eigenvalue iteration can stall on the clustered spectra of
        // long uniform chains, so longer ones take their eigenvalues from faer.
        if raw.get("override").is_none() {
            assert_eq!(radii.len(), 1, "{name}: {radii:?}");
            let sub = model_subs(&raw);
            let subs = vec![sub; big_n];
            let a_eff = dense_a_eff(plus, minus, &subs);
            let rho = if big_n * n <= DENSE_CHECK_MAX {
                spectral_radius(&a_eff)
            } else {
                let size = a_eff.nrows();
                let f = faer::Mat::from_fn(size, size, |r, c| a_eff[(r, c)]);
                let eig = f.eigenvalues().expect("faer eigenvalues");
                eig.iter().map(|l| l.norm()).fold(0.0, f64::max)
            };
            assert!(
                (radii[0].1 - rho).abs() <= 1e-5,
                "{name}: printed {} vs computed {rho}",
                radii[0].1
            );
            // A stable shipped config warns about nothing.
            if rho < 1.0 {
                assert!(run.stderr.is_empty(), "{name}: stderr {}", run.stderr);
            }
        }
    }
}

/// A scalar chain (n = 1, q = 1) with `plus = minus = 1`.
fn scalar_chain(big_n: usize, a: f64, b: [f64; 2], d: [f64; 2], g: [f64; 4]) -> String {
    format!(
        r#"subsystems = {big_n}
steps = 20

[interconnection]
plus = 1
minus = 1

[model]
A = [[{a:?}]]
B = [[{:?}, {:?}]]
D = [[{:?}], [{:?}]]
G = [[{:?}, {:?}], [{:?}, {:?}]]
J = [[1.0]]
M = [[1.0]]

[dropout]
p = 0.9

[initial]
cov = [[1.0]]
"#,
        b[0], b[1], d[0], d[1], g[0], g[1], g[2], g[3]
    )
}

#[test]
fn unstable_chain_warns_about_the_spectral_radius() {
    let text = scalar_chain(5, 1.05, [0.1, 0.1], [0.5, 0.5], [0.1, 0.0, 0.0, 0.1]);
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let warnings: Vec<&str> = run
        .stderr
        .lines()
        .filter(|l| l.starts_with("warning: "))
        .collect();
    assert_eq!(
        warnings.len(),
        run.stderr.lines().count(),
        "every stderr line is a warning: {}",
        run.stderr
    );
    assert!(
        warnings.iter().any(|l| l.contains("spectral radius")),
        "no warning about the spectral radius: {}",
        run.stderr
    );
    // The printed radius is the true one, above 1.
    let radii = printed_radii(&run.stdout);
    assert_eq!(radii.len(), 1, "{}", run.stdout);
    let sub = Sub {
        A: mat(1, 1, &[1.05]),
        B: mat(1, 2, &[0.1, 0.1]),
        D: mat(2, 1, &[0.5, 0.5]),
        G: mat(2, 2, &[0.1, 0.0, 0.0, 0.1]),
    };
    let rho = spectral_radius(&dense_a_eff(1, 1, &vec![sub; 5]));
    assert!(rho > 1.0);
    assert!(
        (radii[0].1 - rho).abs() <= 1e-3 * rho,
        "{} vs {rho}",
        radii[0].1
    );

    // An uncoupled chain with A = 1.05: radius 1.05 exactly.
    let text = scalar_chain(4, 1.05, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0, 0.0, 0.0]);
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0));
    assert!(
        run.stderr
            .lines()
            .any(|l| l.starts_with("warning: ") && l.contains("spectral radius")),
        "{}",
        run.stderr
    );
    assert!((printed_radii(&run.stdout)[0].1 - 1.05).abs() <= 1e-6);
}

#[test]
fn stable_chain_has_no_warning() {
    let text = scalar_chain(5, 0.5, [0.1, 0.1], [0.5, 0.5], [0.1, 0.0, 0.0, 0.1]);
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0));
    assert!(run.stderr.is_empty(), "{}", run.stderr);
}

#[test]
fn singular_interconnection_is_an_error_at_t_1() {
    let text = scalar_chain(2, 0.5, [0.1, 0.1], [1.0, 1.0], [0.0, 1.0, 1.0, 0.0]);
    // Independently: the dense system of (P2)–(P4) is singular.
    let g = vec![mat(2, 2, &[0.0, 1.0, 1.0, 0.0]); 2];
    let z = vec![DVector::from_vec(vec![1.0, 2.0]); 2];
    assert!(dense_interconnect(1, 1, &g, &z).is_none());

    let (_dir, _path, run) = check_text(&text);
    assert_eq!(
        run.code,
        Some(2),
        "stdout {}\nstderr {}",
        run.stdout,
        run.stderr
    );
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("t = 1"), "{line}");
}

#[test]
fn singular_interconnection_error_names_the_file() {
    let text = scalar_chain(2, 0.5, [0.1, 0.1], [1.0, 1.0], [0.0, 1.0, 1.0, 0.0]);
    let (_dir, path, run) = check_text(&text);
    assert_eq!(run.code, Some(2));
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains(&path.display().to_string()), "{line}");
}

#[test]
fn singular_interconnection_in_a_later_window() {
    // Well posed except on steps 4..6, where an override makes G singular.
    let text = scalar_chain(3, 0.5, [0.1, 0.1], [1.0, 1.0], [0.1, 0.0, 0.0, 0.1])
        + "\n[[override]]\nsteps = [4, 6]\nG = [[0.0, 1.0], [1.0, 0.0]]\n";
    let (dir, path, run) = check_text(&text);
    assert_eq!(
        run.code,
        Some(2),
        "stdout {}\nstderr {}",
        run.stdout,
        run.stderr
    );
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("t = 4"), "{line}");

    // simulate fails the same way, with exit 2.
    let out = sisfilt()
        .arg("simulate")
        .arg(&path)
        .arg("--out")
        .arg(dir.path().join("out"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let line = one_error_line(&out.stderr);
    assert!(line.contains("t = 4"), "{line}");
}

#[test]
fn ill_posed_config_prints_nothing_on_stdout() {
    let text = scalar_chain(2, 0.5, [0.1, 0.1], [1.0, 1.0], [0.0, 1.0, 1.0, 0.0]);
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(2));
    assert!(run.stdout.is_empty(), "stdout: {}", run.stdout);
}

#[test]
fn ill_posed_only_after_the_horizon_is_fine() {
    // docs/theory.md §13: override steps may reach past T; only the steps that exist are affected.
    let text = scalar_chain(3, 0.5, [0.1, 0.1], [1.0, 1.0], [0.1, 0.0, 0.0, 0.1])
        + "\n[[override]]\nsteps = [21, 30]\nG = [[0.0, 1.0], [1.0, 0.0]]\n";
    let (dir, path, run) = check_text(&text);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    assert!(run.stderr.is_empty(), "{}", run.stderr);
    simulate_files(&path, &dir.path().join("out"));
}

#[test]
fn single_subsystem_radius_is_that_of_a() {
    // N = 1: v = 0, so A_eff = A whatever G is (even a G that would be singular in a chain).
    let text = scalar_chain(1, 0.5, [0.4, 0.4], [1.0, 1.0], [0.0, 1.0, 1.0, 0.0])
        .replace("A = [[0.5]]", "A = [[0.5, 0.8], [-0.6, 0.3]]")
        .replace("B = [[0.4, 0.4]]", "B = [[0.4, 0.4], [0.1, 0.2]]")
        .replace("D = [[1.0], [1.0]]", "D = [[1.0, 0.0], [1.0, 0.0]]")
        .replace("J = [[1.0]]", "J = [[1.0, 0.0]]")
        .replace("cov = [[1.0]]", "cov = [[1.0, 0.0], [0.0, 1.0]]");
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    // Eigenvalues of [[0.5, 0.8], [-0.6, 0.3]]: 0.4 ± i·sqrt(0.63 − 0.16), so |λ|² = det = 0.63.
    let rho = (0.5f64 * 0.3 + 0.8 * 0.6).sqrt();
    let radii = printed_radii(&run.stdout);
    assert_eq!(radii.len(), 1, "{}", run.stdout);
    assert!(
        (radii[0].1 - rho).abs() <= 1e-5,
        "printed {} vs {rho}",
        radii[0].1
    );
}

/// A chain of `N = 4` with n = 2, plus = 2, minus = 1, non-zero G, and overrides that make
/// `A_eff` differ between time windows.
#[test]
fn spectral_radius_matches_dense_computation_per_window() {
    let (big_n, plus, minus) = (4, 2, 1);
    let base = Sub {
        A: mat(2, 2, &[0.6, 0.3, -0.2, 0.5]),
        B: mat(2, 3, &[0.3, -0.2, 0.4, 0.1, 0.35, -0.25]),
        D: mat(3, 2, &[0.5, -0.3, 0.2, 0.6, -0.4, 0.3]),
        G: mat(3, 3, &[0.2, -0.25, 0.15, 0.3, 0.1, -0.2, 0.25, 0.2, 0.3]),
    };
    let over_a = mat(2, 2, &[0.9, -0.4, 0.3, 0.7]);
    let over_g = mat(3, 3, &[-0.3, 0.2, 0.1, 0.1, -0.2, 0.3, 0.2, 0.3, -0.1]);
    let text = format!(
        r#"subsystems = {big_n}
steps = 12

[interconnection]
plus = {plus}
minus = {minus}

[model]
A = {}
B = {}
D = {}
G = {}
J = [[1.0, 0.0]]
M = [[0.5]]

[dropout]
p = 0.7

[initial]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[override]]
subsystems = [2, 3]
steps = [4, 7]
A = {}

[[override]]
subsystems = [1, 2]
steps = [6, 9]
G = {}
"#,
        toml_matrix(&base.A),
        toml_matrix(&base.B),
        toml_matrix(&base.D),
        toml_matrix(&base.G),
        toml_matrix(&over_a),
        toml_matrix(&over_g),
    );
    let params_at = |t: usize| -> Vec<Sub> {
        (1..=big_n)
            .map(|i| {
                let mut s = base.clone();
                if (2..=3).contains(&i) && (4..=7).contains(&t) {
                    s.A = over_a.clone();
                }
                if (1..=2).contains(&i) && (6..=9).contains(&t) {
                    s.G = over_g.clone();
                }
                s
            })
            .collect()
    };
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let radii = printed_radii(&run.stdout);
    // Every step 1..12 must be covered by exactly one printed window, and each window's
    // radius must be that of A_eff at any of its steps.
    let mut covered = [0usize; 13];
    let mut distinct = Vec::new();
    for (line, value) in &radii {
        let (first, last) = window_of(line);
        for t in first..=last {
            covered[t] += 1;
            let rho = spectral_radius(&dense_a_eff(plus, minus, &params_at(t)));
            assert!(
                (value - rho).abs() <= 1e-5,
                "t = {t} (line {line:?}): printed {value}, computed {rho}"
            );
        }
        distinct.push(*value);
    }
    assert!(
        covered[1..].iter().all(|&c| c == 1),
        "{covered:?}\n{}",
        run.stdout
    );
    distinct.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    assert!(distinct.len() >= 3, "windows not distinguished: {radii:?}");
}

/// The step range `t = a..b` at the start of a window line.
fn window_of(line: &str) -> (usize, usize) {
    let rest = line
        .split("t = ")
        .nth(1)
        .unwrap_or_else(|| panic!("no `t = ` in {line:?}"));
    let range: String = rest
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.')
        .collect();
    let mut parts = range.split("..");
    let first = parts.next().unwrap().parse().unwrap();
    let last = parts.next().map_or(first, |s| s.parse().unwrap());
    (first, last)
}

#[test]
fn spectral_radius_of_a_scalar_chain() {
    // N = 4, n = 1: small enough to see every number.
    let (a, b, d, g) = (0.7, [0.4, -0.3], [0.8, 0.6], [0.3, -0.2, 0.25, 0.1]);
    let text = scalar_chain(4, a, b, d, g);
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let sub = Sub {
        A: mat(1, 1, &[a]),
        B: mat(1, 2, &b),
        D: mat(2, 1, &d),
        G: mat(2, 2, &g),
    };
    let a_eff = dense_a_eff(1, 1, &vec![sub; 4]);
    // The lifted matrix couples neighbours: it is not diagonal.
    assert!(a_eff[(0, 1)].abs() > 1e-3 && a_eff[(1, 0)].abs() > 1e-3);
    let rho = spectral_radius(&a_eff);
    let radii = printed_radii(&run.stdout);
    assert_eq!(radii.len(), 1, "{}", run.stdout);
    assert!(
        (radii[0].1 - rho).abs() <= 1e-5,
        "printed {} vs {rho}",
        radii[0].1
    );
}

// ------------------------------------------------------------------ inputs file

fn file_input_chain(path: &str) -> String {
    scalar_chain(2, 0.5, [0.1, 0.1], [0.5, 0.5], [0.1, 0.0, 0.0, 0.1])
        .replace("J = [[1.0]]", "C = [[1.0]]\nJ = [[1.0]]")
        + &format!("\n[input]\nkind = \"file\"\npath = \"{path}\"\n")
}

#[test]
fn check_reads_the_inputs_file() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_file(dir.path(), "chain.toml", &file_input_chain("u.csv"));
    // Missing file.
    let run = check(&config);
    assert_eq!(run.code, Some(2), "{}", run.stdout);
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("u.csv"), "{line}");

    // A file that stops at t = 19 of 20.
    let mut csv = String::from("t,i,u1\n");
    for t in 1..=19 {
        for i in 1..=2 {
            csv += &format!("{t},{i},0.5\n");
        }
    }
    write_file(dir.path(), "u.csv", &csv);
    let run = check(&config);
    assert_eq!(run.code, Some(2));
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("u.csv"), "{line}");

    // A non-number names the file and the line.
    let mut csv = String::from("t,i,u1\n");
    for t in 1..=20 {
        for i in 1..=2 {
            let v = if (t, i) == (3, 2) {
                "abc".into()
            } else {
                format!("{}", t as f64)
            };
            csv += &format!("{t},{i},{v}\n");
        }
    }
    write_file(dir.path(), "u.csv", &csv);
    let run = check(&config);
    assert_eq!(run.code, Some(2));
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("u.csv") && line.contains("line 7"), "{line}");

    // A file with a step beyond T = 20 (docs/theory.md §13: exactly the steps 1..T).
    let mut csv = String::from("t,i,u1\n");
    for t in 1..=21 {
        for i in 1..=2 {
            csv += &format!("{t},{i},0.5\n");
        }
    }
    write_file(dir.path(), "u.csv", &csv);
    let run = check(&config);
    assert_eq!(run.code, Some(2));
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("u.csv"), "{line}");

    // The complete file passes.
    let mut csv = String::from("t,i,u1\n");
    for t in 1..=20 {
        for i in 1..=2 {
            csv += &format!("{t},{i},{}\n", t as f64 * 0.1);
        }
    }
    write_file(dir.path(), "u.csv", &csv);
    let run = check(&config);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
}

#[test]
fn missing_inputs_file_message_says_the_cause_once() {
    let dir = tempfile::tempdir().unwrap();
    let config = write_file(dir.path(), "chain.toml", &file_input_chain("u.csv"));
    let run = check(&config);
    assert_eq!(run.code, Some(2));
    let line = one_error_line(&run.stderr_raw);
    assert!(line.contains("u.csv"), "{line}");
    let cause = std::io::Error::from(std::io::ErrorKind::NotFound).to_string();
    let os_cause = "No such file or directory";
    let count = line
        .matches(os_cause)
        .count()
        .max(line.matches(&cause).count());
    assert_eq!(count, 1, "cause repeated: {line}");
}

/// `check` tells a marginally stable chain (`ρ = 1`: the second moment grows linearly) from an
/// unstable one (`ρ > 1`: it grows exponentially and the unknown-dropout filter diverges).
#[test]
fn stability_warnings_tell_rho_one_from_above_one() {
    let dir = tempfile::tempdir().unwrap();
    let config = |a: f64, b: &str| {
        format!(
            "subsystems = 5\nsteps = 10\n[interconnection]\nplus = 1\nminus = 1\n[model]\nA = {a}\nB = {b}\nD = [[0.5], [0.5]]\nJ = 1\nM = 0.05\nQ = 0.01\n[dropout]\np = 0.8\n[initial]\ncov = 1\n"
        )
    };
    for (text, says) in [
        (
            config(1.0, "[[0.0, 0.0]]"),
            &[
                "is 1.000000 = 1 (to ",
                "): the chain is marginally stable: its second moment S grows like a power of t",
            ][..],
        ),
        (
            config(1.2, "[[0.1, 0.1]]"),
            &[
                "> 1: the chain is unstable, its second moment grows exponentially, and the unknown-dropout filter diverges",
            ],
        ),
    ] {
        let path = crate::common::write_file(dir.path(), "c.toml", &text);
        let out = crate::common::sisfilt()
            .arg("check")
            .arg(&path)
            .output()
            .unwrap();
        assert!(out.status.success());
        let stderr = String::from_utf8(out.stderr).unwrap();
        for says in says {
            assert!(stderr.contains(says), "{stderr}");
        }
    }
}

// ------------------------------------------------------------------ Krylov estimates

/// The bench chain (bench/workload.toml: n = 2, a complex pair of dominant eigenvalues) with
/// `big_n` subsystems, and the spectral radius of its dense `A_eff` by faer's eigenvalue solver
/// (nalgebra's Schur iteration stalls on such clustered spectra). `A_eff` is the library's
/// (`lifted::a_eff_dense`, which `spectral_radius_of_a_scalar_chain` and the shipped configs'
/// test check against the dense solve of docs/theory.md §1): too long a chain for that solve.
fn bench_chain(big_n: usize) -> (String, f64) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("bench/workload.toml");
    let text = std::fs::read_to_string(path)
        .unwrap()
        .replace("subsystems = 10000", &format!("subsystems = {big_n}"));
    let model = crate::common::model_from(&text);
    let solver = sisfilt::interconnect::ChainSolver::new(&model, 1).unwrap();
    let a = sisfilt::lifted::a_eff_dense(&model, 1, &solver);
    let a = faer::Mat::from_fn(a.nrows(), a.ncols(), |r, c| a[(r, c)]);
    let eigenvalues = a.eigenvalues().expect("converged");
    (
        text,
        eigenvalues.iter().map(|l| l.norm()).fold(0.0, f64::max),
    )
}

/// Above `exact_max` lifted states the radius is the largest Ritz value of an Arnoldi process
/// (docs/theory.md §3): against the dense eigenvalues of `A_eff`, 20 and 40 steps (the default)
/// come within 1e−3 relative, with a finite bound; a chain of at most `krylov` states is exact.
#[test]
fn krylov_estimate_against_the_dense_radius() {
    use sisfilt::stability::RadiusEffort;
    let estimate = |model: &sisfilt::model::Model, krylov| {
        let solver = sisfilt::interconnect::ChainSolver::new(model, 1).unwrap();
        let effort = RadiusEffort {
            exact_max: 0,
            krylov,
        };
        sisfilt::stability::spectral_radius(model, 1, &solver, effort)
    };
    let (text, rho) = bench_chain(300);
    let model = crate::common::model_from(&text);
    for krylov in [20, RadiusEffort::DEFAULT.krylov] {
        let figure = estimate(&model, krylov);
        assert!(!figure.exact);
        assert!(
            (figure.value - rho).abs() <= 1e-3 * rho,
            "{krylov} steps: {} vs {rho}",
            figure.value
        );
        assert!(figure.bound > 0.0 && figure.bound < 1.0, "{figure:?}");
    }

    // Eight states, twenty steps: the Krylov space is the whole space.
    let text = bench_chain(4).0;
    let small = estimate(&crate::common::model_from(&text), 20);
    let raw: toml::Value = toml::from_str(&text).unwrap();
    let rho = spectral_radius(&dense_a_eff(1, 1, &vec![model_subs(&raw); 4]));
    assert!(small.exact);
    assert!(
        (small.value - rho).abs() <= 1e-12,
        "{} vs {rho}",
        small.value
    );
}

/// `check` above 400 lifted states says its figure is an estimate, within 1e−3 of the dense
/// radius.
#[test]
fn check_of_a_long_chain_prints_a_krylov_estimate() {
    let (text, rho) = bench_chain(250);
    let (_dir, _path, run) = check_text(&text);
    assert_eq!(run.code, Some(0), "{}", run.stderr);
    let radii = printed_radii(&run.stdout);
    assert_eq!(radii.len(), 1, "{}", run.stdout);
    assert!(radii[0].0.contains("(Krylov estimate ± "), "{}", radii[0].0);
    assert!(
        (radii[0].1 - rho).abs() <= 1e-3 * rho,
        "{} vs {rho}",
        radii[0].1
    );
}

/// A run with unknown dropouts warns when a chain it will filter is unstable, naming the
/// window it starts (docs/theory.md §3); a stable chain gets no such warning.
#[test]
fn estimate_warns_about_an_unstable_window() {
    let dir = tempfile::tempdir().unwrap();
    let stable = scalar_chain(40, 0.8, [0.1, 0.1], [0.5, 0.5], [0.1, 0.0, 0.0, 0.1]);
    // From t = 11 every subsystem's A is 1.05: ρ of that window exceeds 1.05.
    let unstable = format!("{stable}\n[[override]]\nsteps = [11, 20]\nA = [[1.05]]\n");
    for (name, text, want) in [("stable", &stable, None), ("unstable", &unstable, Some(11))] {
        let config = write_file(dir.path(), &format!("{name}.toml"), text);
        let out = crate::common::estimate_simulated(dir.path(), &config, name);
        let stderr = String::from_utf8(out.stderr).unwrap();
        assert!(out.status.success(), "{stderr}");
        let warning = stderr
            .lines()
            .find(|l| l.starts_with("warning: ") && l.contains("spectral radius"));
        match want {
            None => assert!(warning.is_none(), "{stderr}"),
            Some(first) => {
                let line = warning.unwrap_or_else(|| panic!("no warning in {stderr}"));
                assert!(line.contains(&format!("from t = {first}, ")), "{line}");
                assert!(line.contains("> 1: the chain is unstable"), "{line}");
            }
        }
    }
}

/// `check` visits the windows of parameters, not the steps: a horizon of 10¹² steps with
/// generated inputs is checked at once (it walked every step's inputs, about half an hour;
/// the time limit is only there to fail rather than hang).
#[test]
fn a_horizon_of_a_trillion_steps_is_checked_window_by_window() {
    let shipped = std::fs::read_to_string(crate::common::shipped_config("platoon.toml")).unwrap();
    let text: String = shipped
        .lines()
        .map(|line| {
            if line.starts_with("steps =") {
                "steps = 1000000000000"
            } else {
                line
            }
        })
        .collect::<Vec<_>>()
        .join("\n");
    assert!(text.contains("kind = \"sine\""), "generated inputs");
    let dir = tempfile::tempdir().unwrap();
    let path = write_file(dir.path(), "long.toml", &text);
    let out = sisfilt()
        .arg("check")
        .arg(&path)
        .timeout(std::time::Duration::from_secs(120))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(stdout.contains("T = 1000000000000 steps"), "{stdout}");
    assert!(
        stdout.contains("t = 1..1000000000000: interconnection"),
        "{stdout}"
    );
}
