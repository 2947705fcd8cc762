//! `sisfilt simulate` (docs/theory.md §13): the files it writes, their layout, determinism, the
//! dropout frequency, the dynamics (P1)–(P4) of the truth, `--mark-missing` and `--out`.
#![allow(non_snake_case)]

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::common::{
    Csv, dense_interconnect, header, mat, one_error_line, sisfilt, toml_matrix, write_file,
};
use nalgebra::{DMatrix, DVector};

/// Runs `sisfilt simulate CONFIG --out OUT [extra…]` and asserts success with empty stdout
/// and stderr.
fn simulate_ok(config: &Path, out: &Path, extra: &[&str]) {
    let output = sisfilt()
        .arg("simulate")
        .arg(config)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "simulate failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(output.stdout.is_empty(), "simulate wrote to stdout");
    assert!(
        output.stderr.is_empty(),
        "simulate wrote to stderr: {}",
        String::from_utf8_lossy(&output.stderr)
    );
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The names in a folder.
fn listing(dir: &Path) -> BTreeSet<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect()
}

fn names(list: &[&str]) -> BTreeSet<String> {
    list.iter().map(|s| s.to_string()).collect()
}

// ------------------------------------------------------------------ a model described in Rust

/// The matrices of (P1), (P2), (P5) of one parameter set.
#[derive(Clone)]
struct Params {
    A: DMatrix<f64>,
    B: DMatrix<f64>,
    C: DMatrix<f64>,
    D: DMatrix<f64>,
    G: DMatrix<f64>,
    H: DMatrix<f64>,
    J: DMatrix<f64>,
    R: DMatrix<f64>,
    M: DMatrix<f64>,
}

impl Params {
    fn set(&mut self, key: &str, m: &DMatrix<f64>) {
        let slot = match key {
            "A" => &mut self.A,
            "B" => &mut self.B,
            "C" => &mut self.C,
            "D" => &mut self.D,
            "G" => &mut self.G,
            "H" => &mut self.H,
            _ => panic!("{key}"),
        };
        *slot = m.clone();
    }
}

struct Override {
    subsystems: Option<(usize, usize)>,
    steps: Option<(usize, usize)>,
    matrices: Vec<(&'static str, DMatrix<f64>)>,
}

/// A chain with Q = 0 and a sine input, written to TOML from these very numbers.
struct Chain {
    subsystems: usize,
    steps: usize,
    plus: usize,
    minus: usize,
    base: Params,
    overrides: Vec<Override>,
    amplitude: f64,
    period: f64,
    phase: f64,
    p: f64,
}

impl Chain {
    fn m(&self) -> usize {
        self.base.C.ncols()
    }

    fn toml(&self) -> String {
        let b = &self.base;
        let n = b.A.nrows();
        let mut text = format!(
            "subsystems = {}\nsteps = {}\nseed = 11\n\n[interconnection]\nplus = {}\nminus = {}\n\n\
             [model]\nA = {}\nB = {}\nC = {}\nD = {}\nG = {}\nH = {}\nJ = {}\nR = {}\nM = {}\n\n\
             [dropout]\np = {:?}\n\n[initial]\nmean = [{}]\ncov = {}\n\n\
             [input]\nkind = \"sine\"\namplitude = {:?}\nperiod = {:?}\nphase = {:?}\n",
            self.subsystems,
            self.steps,
            self.plus,
            self.minus,
            toml_matrix(&b.A),
            toml_matrix(&b.B),
            toml_matrix(&b.C),
            toml_matrix(&b.D),
            toml_matrix(&b.G),
            toml_matrix(&b.H),
            toml_matrix(&b.J),
            toml_matrix(&b.R),
            toml_matrix(&b.M),
            self.p,
            (0..n)
                .map(|k| format!("{:?}", 0.5 - k as f64))
                .collect::<Vec<_>>()
                .join(", "),
            toml_matrix(&DMatrix::identity(n, n)),
            self.amplitude,
            self.period,
            self.phase,
        );
        for o in &self.overrides {
            text += "\n[[override]]\n";
            if let Some((a, b)) = o.subsystems {
                text += &format!("subsystems = [{a}, {b}]\n");
            }
            if let Some((a, b)) = o.steps {
                text += &format!("steps = [{a}, {b}]\n");
            }
            for (key, m) in &o.matrices {
                text += &format!("{key} = {}\n", toml_matrix(m));
            }
        }
        text
    }

    /// The parameters at `(t, i)`: the base set with every override that covers `(t, i)`
    /// applied in order (later ones win).
    fn params(&self, t: usize, i: usize) -> Params {
        let mut p = self.base.clone();
        for o in &self.overrides {
            let in_steps = o.steps.is_none_or(|(a, b)| a <= t && t <= b);
            let in_subs = o.subsystems.is_none_or(|(a, b)| a <= i && i <= b);
            if in_steps && in_subs {
                for (key, m) in &o.matrices {
                    p.set(key, m);
                }
            }
        }
        p
    }

    /// docs/theory.md §13: `u_k(t, i) = amplitude · sin(2π t / period + phase · i)` for every element k.
    fn input(&self, t: usize, i: usize) -> f64 {
        self.amplitude
            * (2.0 * std::f64::consts::PI * t as f64 / self.period + self.phase * i as f64).sin()
    }
}

/// Simulates `chain` and checks (P1)–(P4) with Q = 0 on the truth it writes: for each `t`,
/// `v(t, ·)` is rebuilt by a dense solve of (P2)–(P4) and `x(t+1, i) = A x + B v + C u` must
/// hold to 1e-10 (relative to the size of the state).
fn check_dynamics(chain: &Chain) {
    let dir = tempfile::tempdir().unwrap();
    let config = write_file(dir.path(), "chain.toml", &chain.toml());
    let out = dir.path().join("out");
    simulate_ok(&config, &out, &[]);

    let (big_n, steps, m) = (chain.subsystems, chain.steps, chain.m());
    let n = chain.base.A.nrows();
    let truth = Csv::read(&out.join("truth.csv"));
    assert_eq!(truth.header, header("x", n, &["gamma"]));
    truth.assert_index(steps, big_n);
    let inputs = Csv::read(&out.join("inputs.csv"));
    assert_eq!(inputs.header, header("u", m, &[]));
    inputs.assert_index(steps, big_n);

    let x = truth.numbers(2, n);
    let u = inputs.numbers(2, m);
    let at = |t: usize, i: usize| (t - 1) * big_n + (i - 1);

    // The inputs follow the sine of docs/theory.md §13.
    for t in 1..=steps {
        for i in 1..=big_n {
            for k in 0..m {
                let want = chain.input(t, i);
                let got = u[at(t, i)][k];
                assert!(
                    (got - want).abs() <= 1e-12 * (1.0 + want.abs()),
                    "u{} at t = {t}, i = {i}: {got} vs {want}",
                    k + 1
                );
            }
        }
    }

    let mut worst: f64 = 0.0;
    let mut largest: f64 = 0.0;
    for t in 1..steps {
        let params: Vec<Params> = (1..=big_n).map(|i| chain.params(t, i)).collect();
        let xs: Vec<DVector<f64>> = (1..=big_n)
            .map(|i| DVector::from_column_slice(&x[at(t, i)]))
            .collect();
        let us: Vec<DVector<f64>> = (1..=big_n)
            .map(|i| DVector::from_column_slice(&u[at(t, i)]))
            .collect();
        let z: Vec<DVector<f64>> = (0..big_n)
            .map(|k| &params[k].D * &xs[k] + &params[k].H * &us[k])
            .collect();
        let g: Vec<DMatrix<f64>> = params.iter().map(|p| p.G.clone()).collect();
        let v = dense_interconnect(chain.plus, chain.minus, &g, &z).expect("well posed");
        for k in 0..big_n {
            let p = &params[k];
            let want = &p.A * &xs[k] + &p.B * &v[k] + &p.C * &us[k];
            let got = DVector::from_column_slice(&x[at(t + 1, k + 1)]);
            let scale = 1.0 + want.amax();
            let err = (&got - &want).amax() / scale;
            worst = worst.max(err);
            largest = largest.max(want.amax());
            assert!(
                err <= 1e-10,
                "x(t+1, i) ≠ A x + B v + C u at t = {t}, i = {}: got {got}, want {want}",
                k + 1
            );
        }
    }
    // The check is not vacuous: the states stay of a visible size.
    assert!(largest > 0.05, "states vanished: max |x| = {largest}");
    eprintln!("largest relative error {worst:e}");
}

#[test]
fn truth_satisfies_dynamics_plus_minus_one() {
    let chain = Chain {
        subsystems: 6,
        steps: 40,
        plus: 1,
        minus: 1,
        base: Params {
            A: mat(2, 2, &[0.7, 0.2, -0.1, 0.6]),
            B: mat(2, 2, &[0.3, -0.2, 0.1, 0.25]),
            C: mat(2, 1, &[0.2, 0.5]),
            D: mat(2, 2, &[0.4, -0.3, 0.2, 0.5]),
            G: mat(2, 2, &[0.25, -0.15, 0.3, 0.2]),
            H: mat(2, 1, &[0.3, -0.4]),
            J: mat(1, 2, &[1.0, 0.5]),
            R: mat(1, 1, &[0.1]),
            M: mat(1, 1, &[0.2]),
        },
        overrides: vec![],
        amplitude: 1.5,
        period: 13.0,
        phase: 0.7,
        p: 0.6,
    };
    check_dynamics(&chain);
}

#[test]
fn truth_satisfies_dynamics_plus_two_minus_one_with_overrides() {
    let chain = Chain {
        subsystems: 7,
        steps: 30,
        plus: 2,
        minus: 1,
        base: Params {
            A: mat(2, 2, &[0.6, 0.25, -0.2, 0.7]),
            B: mat(2, 3, &[0.2, -0.1, 0.3, 0.05, 0.25, -0.2]),
            C: mat(2, 2, &[0.3, 0.0, -0.1, 0.4]),
            D: mat(3, 2, &[0.5, -0.2, 0.1, 0.4, -0.3, 0.2]),
            G: mat(3, 3, &[0.2, -0.1, 0.15, 0.05, 0.25, -0.2, 0.3, 0.1, 0.2]),
            H: mat(3, 2, &[0.2, 0.1, -0.3, 0.0, 0.1, 0.4]),
            J: mat(1, 2, &[1.0, -0.5]),
            R: mat(1, 2, &[0.1, 0.2]),
            M: mat(1, 1, &[0.1]),
        },
        overrides: vec![
            Override {
                subsystems: Some((2, 4)),
                steps: Some((5, 12)),
                matrices: vec![
                    ("A", mat(2, 2, &[0.8, -0.1, 0.1, 0.5])),
                    (
                        "G",
                        mat(3, 3, &[-0.2, 0.1, 0.3, 0.2, -0.1, 0.1, -0.25, 0.2, 0.1]),
                    ),
                ],
            },
            Override {
                subsystems: None,
                steps: Some((10, 18)),
                matrices: vec![
                    ("B", mat(2, 3, &[-0.2, 0.1, 0.2, 0.3, -0.15, 0.1])),
                    ("D", mat(3, 2, &[0.3, 0.3, -0.2, 0.5, 0.4, -0.1])),
                    ("H", mat(3, 2, &[-0.1, 0.2, 0.3, -0.2, 0.0, 0.1])),
                ],
            },
            Override {
                subsystems: Some((7, 7)),
                steps: None,
                matrices: vec![
                    (
                        "G",
                        mat(3, 3, &[0.1, 0.3, -0.1, 0.0, 0.2, 0.2, -0.3, 0.1, 0.3]),
                    ),
                    ("C", mat(2, 2, &[0.0, 0.5, 0.5, 0.0])),
                ],
            },
        ],
        amplitude: 2.0,
        period: 9.5,
        phase: -0.4,
        p: 0.5,
    };
    check_dynamics(&chain);
}

// ------------------------------------------------------------------ a small generic config

/// N subsystems, T steps, n = 2, q = `q`, m = 1, plus = minus = 1, with process noise.
fn small_config(subsystems: usize, steps: usize, q: usize, p: &str) -> String {
    let (j, r, m) = match q {
        1 => ("[[1.0, 0.0]]", "[[0.5]]", "[[0.1]]"),
        2 => (
            "[[1.0, 0.0], [0.0, 1.0]]",
            "[[0.5], [0.0]]",
            "[[0.1, 0.02], [0.02, 0.2]]",
        ),
        _ => unreachable!(),
    };
    format!(
        r#"subsystems = {subsystems}
steps = {steps}
seed = 42

[interconnection]
plus = 1
minus = 1

[model]
A = [[0.9, 0.1], [0.0, 0.8]]
B = [[0.1, 0.1], [0.0, 0.0]]
C = [[0.0], [1.0]]
D = [[0.5, 0.0], [0.5, 0.0]]
G = [[0.2, 0.0], [0.0, 0.2]]
J = {j}
R = {r}
M = {m}
Q = [[0.01, 0.0], [0.0, 0.01]]

[dropout]
p = {p}

[initial]
mean = [1.0, 0.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[input]
kind = "sine"
amplitude = 1.0
period = 20.0
phase = 0.3
"#
    )
}

struct Setup {
    dir: tempfile::TempDir,
    config: PathBuf,
}

fn setup(text: &str) -> Setup {
    let dir = tempfile::tempdir().unwrap();
    let config = write_file(dir.path(), "config.toml", text);
    Setup { dir, config }
}

#[test]
fn writes_the_files_of_spec_section_6() {
    let s = setup(&small_config(5, 12, 2, "0.7"));
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &[]);
    assert_eq!(
        listing(&out),
        names(&["truth.csv", "measurements.csv", "inputs.csv", "run.json"])
    );

    let truth = Csv::read(&out.join("truth.csv"));
    assert_eq!(truth.header, ["t", "i", "x1", "x2", "gamma"]);
    truth.assert_index(12, 5);
    for row in &truth.rows {
        assert!(row[4] == "0" || row[4] == "1", "gamma {:?}", row[4]);
        for cell in &row[2..4] {
            assert!(cell.parse::<f64>().unwrap().is_finite());
        }
    }
    let meas = Csv::read(&out.join("measurements.csv"));
    assert_eq!(meas.header, ["t", "i", "y1", "y2"]);
    meas.assert_index(12, 5);
    meas.numbers(2, 2); // every cell a number without --mark-missing
    let inputs = Csv::read(&out.join("inputs.csv"));
    assert_eq!(inputs.header, ["t", "i", "u1"]);
    inputs.assert_index(12, 5);

    // The raw header lines, exactly.
    let first_line = |name: &str| {
        String::from_utf8(read(&out.join(name)))
            .unwrap()
            .lines()
            .next()
            .unwrap()
            .to_string()
    };
    assert_eq!(first_line("truth.csv"), "t,i,x1,x2,gamma");
    assert_eq!(first_line("measurements.csv"), "t,i,y1,y2");
    assert_eq!(first_line("inputs.csv"), "t,i,u1");
}

#[test]
fn run_json_records_seed_version_and_whole_config() {
    let text = small_config(3, 4, 1, "0.7");
    let s = setup(&text);
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &["--seed", "987654321"]);
    let json: serde_json::Value = serde_json::from_slice(&read(&out.join("run.json"))).unwrap();
    assert_eq!(json["seed"], 987654321u64);
    // The version, under some key that says so.
    let obj = json.as_object().unwrap();
    assert!(
        obj.iter()
            .any(|(k, v)| k.contains("version") && v == env!("CARGO_PKG_VERSION")),
        "no version in run.json: {json}"
    );
    // The whole config: verbatim text, or structured data carrying every table.
    let has_text = obj.values().any(|v| v == text.as_str());
    assert!(has_text, "run.json lacks the config text: {json}");

    // Without --seed, the config's seed.
    let out2 = s.dir.path().join("out2");
    simulate_ok(&s.config, &out2, &[]);
    let json: serde_json::Value = serde_json::from_slice(&read(&out2.join("run.json"))).unwrap();
    assert_eq!(json["seed"], 42);
}

#[test]
fn no_inputs_file_without_inputs() {
    let with_inputs = small_config(3, 4, 1, "0.7");
    let text = with_inputs[..with_inputs.find("[input]").unwrap()]
        .replace("C = [[0.0], [1.0]]\n", "")
        .replace("R = [[0.5]]\n", "");
    let s = setup(&text);
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &[]);
    assert_eq!(
        listing(&out),
        names(&["truth.csv", "measurements.csv", "run.json"])
    );
}

#[test]
fn same_seed_same_bytes_other_seed_other_data() {
    let s = setup(&small_config(4, 25, 2, "0.6"));
    let (a, b, c, d) = (
        s.dir.path().join("a"),
        s.dir.path().join("b"),
        s.dir.path().join("c"),
        s.dir.path().join("d"),
    );
    simulate_ok(&s.config, &a, &["--seed", "5"]);
    simulate_ok(&s.config, &b, &["--seed", "5"]);
    simulate_ok(&s.config, &c, &["--seed", "6"]);
    simulate_ok(&s.config, &d, &[]); // the config's seed, 42
    for name in ["truth.csv", "measurements.csv", "inputs.csv", "run.json"] {
        assert_eq!(
            read(&a.join(name)),
            read(&b.join(name)),
            "{name} differs between runs"
        );
    }
    assert_ne!(read(&a.join("truth.csv")), read(&c.join("truth.csv")));
    assert_ne!(
        read(&a.join("measurements.csv")),
        read(&c.join("measurements.csv"))
    );
    // The sine inputs do not depend on the seed.
    assert_eq!(read(&a.join("inputs.csv")), read(&c.join("inputs.csv")));

    // The default seed is the config's: --seed 42 gives the same data.
    let e = s.dir.path().join("e");
    simulate_ok(&s.config, &e, &["--seed", "42"]);
    for name in ["truth.csv", "measurements.csv", "inputs.csv"] {
        assert_eq!(read(&d.join(name)), read(&e.join(name)), "{name}");
    }
    // Every state value differs with another seed (different x(1, ·) draws).
    let ta = Csv::read(&a.join("truth.csv")).numbers(2, 2);
    let tc = Csv::read(&c.join("truth.csv")).numbers(2, 2);
    assert!(ta.iter().zip(&tc).all(|(x, y)| x != y));
}

/// 4 binomial standard deviations around `p` for `k` successes out of `n`.
fn assert_frequency(k: usize, n: usize, p: f64, what: &str) {
    let freq = k as f64 / n as f64;
    let sd = (p * (1.0 - p) / n as f64).sqrt();
    assert!(
        (freq - p).abs() <= 4.0 * sd,
        "{what}: frequency {freq} of gamma = 1 over {n} draws, expected {p} ± 4·{sd}"
    );
}

#[test]
fn dropout_frequency_matches_p() {
    let (big_n, steps, p) = (20, 500, 0.3);
    let s = setup(&small_config(big_n, steps, 1, &format!("{p}")));
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &[]);
    let truth = Csv::read(&out.join("truth.csv"));
    truth.assert_index(steps, big_n);
    let ones = truth.rows.iter().filter(|r| r[4] == "1").count();
    assert_frequency(ones, big_n * steps, p, "p = 0.3");
}

#[test]
fn dropout_frequency_per_subsystem_and_override() {
    let (big_n, steps) = (5, 800);
    let text = small_config(big_n, steps, 1, "[0.0, 1.0, 0.2, 0.5, 0.9]")
        + "\n[[override]]\nsubsystems = [3, 4]\nsteps = [401, 2000]\np = 0.7\n";
    let s = setup(&text);
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &[]);
    let truth = Csv::read(&out.join("truth.csv"));
    truth.assert_index(steps, big_n);
    // counts[i][half] of gamma = 1, half 0 = steps 1..400, half 1 = 401..800.
    let mut counts = [[0usize; 2]; 5];
    for row in &truth.rows {
        let t: usize = row[0].parse().unwrap();
        let i: usize = row[1].parse().unwrap();
        if row[4] == "1" {
            counts[i - 1][usize::from(t > 400)] += 1;
        }
    }
    // p = 0 and p = 1 are exact.
    assert_eq!(counts[0], [0, 0], "p = 0 must never deliver");
    assert_eq!(counts[1], [400, 400], "p = 1 must always deliver");
    let expected = [[0.0, 0.0], [1.0, 1.0], [0.2, 0.7], [0.5, 0.7], [0.9, 0.9]];
    for i in 2..5 {
        for half in 0..2 {
            assert_frequency(
                counts[i][half],
                400,
                expected[i][half],
                &format!("i = {}, half {half}", i + 1),
            );
        }
    }
}

#[test]
fn mark_missing_empties_exactly_the_lost_rows() {
    let (big_n, steps) = (6, 40);
    let s = setup(&small_config(big_n, steps, 2, "0.5"));
    let plain = s.dir.path().join("plain");
    let marked = s.dir.path().join("marked");
    simulate_ok(&s.config, &plain, &["--seed", "3"]);
    simulate_ok(&s.config, &marked, &["--seed", "3", "--mark-missing"]);

    // The same draws: the truth does not change.
    assert_eq!(
        read(&plain.join("truth.csv")),
        read(&marked.join("truth.csv"))
    );
    let truth = Csv::read(&marked.join("truth.csv"));
    let meas = Csv::read(&marked.join("measurements.csv"));
    let meas_plain = Csv::read(&plain.join("measurements.csv"));
    assert_eq!(meas.header, ["t", "i", "y1", "y2"]);
    meas.assert_index(steps, big_n);
    let (mut lost, mut kept) = (0, 0);
    for k in 0..truth.rows.len() {
        let gamma = &truth.rows[k][4];
        let cells = &meas.rows[k][2..];
        if gamma == "0" {
            lost += 1;
            assert!(
                cells.iter().all(String::is_empty),
                "row {k}: gamma = 0 but {cells:?}"
            );
        } else {
            kept += 1;
            assert!(
                cells.iter().all(|c| !c.is_empty()),
                "row {k}: gamma = 1 but {cells:?}"
            );
            // The delivered values are those of the unmarked run.
            assert_eq!(cells, &meas_plain.rows[k][2..], "row {k}");
        }
    }
    assert!(lost > 0 && kept > 0, "lost {lost}, kept {kept}");

    // The raw lines of lost rows are `t,i,,` exactly.
    let raw = String::from_utf8(read(&marked.join("measurements.csv"))).unwrap();
    for (k, line) in raw.lines().skip(1).enumerate() {
        if truth.rows[k][4] == "0" {
            assert_eq!(line, format!("{},{},,", truth.rows[k][0], truth.rows[k][1]));
        }
    }
}

#[test]
fn out_pointing_at_a_file_fails_and_creates_nothing() {
    let s = setup(&small_config(3, 5, 1, "0.7"));
    let work = tempfile::tempdir().unwrap();
    let target = write_file(work.path(), "results", "keep me\n");
    let output = sisfilt()
        .current_dir(work.path())
        .arg("simulate")
        .arg(&s.config)
        .arg("--out")
        .arg(&target)
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(2));
    assert!(output.stdout.is_empty());
    let line = one_error_line(&output.stderr);
    assert!(
        line.contains("results"),
        "error does not name the path: {line}"
    );
    assert_eq!(read(&target), b"keep me\n");
    assert_eq!(listing(work.path()), names(&["results"]));
    assert_eq!(listing(s.dir.path()), names(&["config.toml"]));

    // A folder below a regular file cannot be created either.
    let below = target.join("sub");
    let output = sisfilt()
        .current_dir(work.path())
        .arg("simulate")
        .arg(&s.config)
        .arg("--out")
        .arg(&below)
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(2));
    assert!(output.stdout.is_empty());
    one_error_line(&output.stderr);
    assert_eq!(read(&target), b"keep me\n");
    assert_eq!(listing(work.path()), names(&["results"]));
}

#[test]
fn out_creates_missing_nested_folders() {
    let s = setup(&small_config(3, 5, 1, "0.7"));
    let out = s.dir.path().join("a").join("b").join("c");
    simulate_ok(&s.config, &out, &[]);
    assert_eq!(
        listing(&out),
        names(&["truth.csv", "measurements.csv", "inputs.csv", "run.json"])
    );
    Csv::read(&out.join("truth.csv")).assert_index(5, 3);
}

#[test]
fn out_defaults_to_the_current_folder() {
    let s = setup(&small_config(2, 3, 1, "0.7"));
    let work = tempfile::tempdir().unwrap();
    let output = sisfilt()
        .current_dir(work.path())
        .arg("simulate")
        .arg(&s.config)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(
        listing(work.path()),
        names(&["truth.csv", "measurements.csv", "inputs.csv", "run.json"])
    );
}

#[test]
fn file_inputs_are_read_relative_to_the_config() {
    let (big_n, steps) = (3, 6);
    let text = small_config(big_n, steps, 1, "0.7").replace(
        "kind = \"sine\"\namplitude = 1.0\nperiod = 20.0\nphase = 0.3\n",
        "kind = \"file\"\npath = \"data/u.csv\"\n",
    );
    assert!(text.contains("kind = \"file\""));
    let s = setup(&text);
    std::fs::create_dir(s.dir.path().join("data")).unwrap();
    let mut csv = String::from("t,i,u1\n");
    for t in 1..=steps {
        for i in 1..=big_n {
            csv += &format!("{t},{i},{}\n", (t * 10 + i) as f64 * 0.25 - 3.0);
        }
    }
    write_file(&s.dir.path().join("data"), "u.csv", &csv);
    let work = tempfile::tempdir().unwrap();
    let output = sisfilt()
        .current_dir(work.path())
        .arg("simulate")
        .arg(&s.config)
        .arg("--out")
        .arg("out")
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let got = Csv::read(&work.path().join("out").join("inputs.csv"));
    got.assert_index(steps, big_n);
    let values = got.numbers(2, 1);
    let mut k = 0;
    for t in 1..=steps {
        for i in 1..=big_n {
            assert_eq!(values[k][0], (t * 10 + i) as f64 * 0.25 - 3.0);
            k += 1;
        }
    }
}

#[test]
fn every_shipped_config_simulates() {
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
        let steps = raw["steps"].as_integer().unwrap() as usize;

        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        simulate_ok(&config, &out, &[]);
        let truth = Csv::read(&out.join("truth.csv"));
        assert_eq!(
            truth.header,
            header("x", n, &["gamma"]),
            "{}",
            config.display()
        );
        truth.assert_index(steps, big_n);
        truth.numbers(2, n);
        let meas = Csv::read(&out.join("measurements.csv"));
        assert_eq!(meas.header, header("y", q, &[]), "{}", config.display());
        meas.assert_index(steps, big_n);
        meas.numbers(2, q);
        let mut want = vec!["truth.csv", "measurements.csv", "run.json"];
        if m > 0 {
            want.push("inputs.csv");
            let inputs = Csv::read(&out.join("inputs.csv"));
            assert_eq!(inputs.header, header("u", m, &[]), "{}", config.display());
            inputs.assert_index(steps, big_n);
            inputs.numbers(2, m);
        }
        assert_eq!(listing(&out), names(&want), "{}", config.display());
    }
}

#[test]
fn truth_satisfies_dynamics_one_directional_chains() {
    // plus = 1, minus = 0: signals only travel to the right.
    let right = Chain {
        subsystems: 5,
        steps: 20,
        plus: 1,
        minus: 0,
        base: Params {
            A: mat(2, 2, &[0.7, 0.2, -0.1, 0.6]),
            B: mat(2, 1, &[0.4, -0.3]),
            C: mat(2, 1, &[0.2, 0.5]),
            D: mat(1, 2, &[0.6, -0.3]),
            G: mat(1, 1, &[0.5]),
            H: mat(1, 1, &[0.3]),
            J: mat(1, 2, &[1.0, 0.5]),
            R: mat(1, 1, &[0.1]),
            M: mat(1, 1, &[0.2]),
        },
        overrides: vec![],
        amplitude: 1.0,
        period: 7.0,
        phase: 0.3,
        p: 0.6,
    };
    check_dynamics(&right);
    // plus = 0, minus = 2: signals only travel to the left.
    let left = Chain {
        subsystems: 5,
        steps: 20,
        plus: 0,
        minus: 2,
        base: Params {
            A: mat(2, 2, &[0.7, 0.2, -0.1, 0.6]),
            B: mat(2, 2, &[0.4, -0.3, 0.1, 0.2]),
            C: mat(2, 1, &[0.2, 0.5]),
            D: mat(2, 2, &[0.6, -0.3, 0.2, 0.4]),
            G: mat(2, 2, &[0.3, -0.2, 0.25, 0.1]),
            H: mat(2, 1, &[0.3, -0.1]),
            J: mat(1, 2, &[1.0, 0.5]),
            R: mat(1, 1, &[0.1]),
            M: mat(1, 1, &[0.2]),
        },
        overrides: vec![Override {
            subsystems: Some((3, 5)),
            steps: Some((6, 11)),
            matrices: vec![("G", mat(2, 2, &[-0.3, 0.2, 0.1, 0.4]))],
        }],
        amplitude: 1.0,
        period: 7.0,
        phase: 0.3,
        p: 0.6,
    };
    check_dynamics(&left);
}

#[test]
fn truth_satisfies_dynamics_single_subsystem() {
    // N = 1: nothing enters the chain, v = 0 (docs/theory.md §2), whatever G is.
    let single = Chain {
        subsystems: 1,
        steps: 25,
        plus: 1,
        minus: 1,
        base: Params {
            A: mat(2, 2, &[0.7, 0.2, -0.1, 0.6]),
            B: mat(2, 2, &[0.4, -0.3, 0.1, 0.2]),
            C: mat(2, 1, &[0.2, 0.5]),
            D: mat(2, 2, &[0.6, -0.3, 0.2, 0.4]),
            G: mat(2, 2, &[0.0, 1.0, 1.0, 0.0]),
            H: mat(2, 1, &[0.3, -0.1]),
            J: mat(1, 2, &[1.0, 0.5]),
            R: mat(1, 1, &[0.1]),
            M: mat(1, 1, &[0.2]),
        },
        overrides: vec![],
        amplitude: 1.0,
        period: 7.0,
        phase: 0.3,
        p: 0.6,
    };
    check_dynamics(&single);
}

// ------------------------------------------------------------------ noise statistics

/// Asserts that the sample mean and covariance of `samples` match `mean` and `cov` within
/// 4.5 standard errors (Gaussian samples: var of a sample covariance entry ≈
/// (Σjj Σkk + Σjk²) / n).
fn assert_moments(samples: &[DVector<f64>], mean: &DVector<f64>, cov: &DMatrix<f64>, what: &str) {
    let count = samples.len() as f64;
    let dim = mean.len();
    let sample_mean = samples.iter().fold(DVector::zeros(dim), |a, s| a + s) / count;
    let mut sample_cov = DMatrix::<f64>::zeros(dim, dim);
    for s in samples {
        let d = s - &sample_mean;
        sample_cov += &d * d.transpose();
    }
    sample_cov /= count - 1.0;
    for j in 0..dim {
        let se = (cov[(j, j)] / count).sqrt();
        assert!(
            (sample_mean[j] - mean[j]).abs() <= 4.5 * se,
            "{what}: mean[{j}] = {} vs {} (se {se})",
            sample_mean[j],
            mean[j]
        );
        for k in 0..dim {
            let se = ((cov[(j, j)] * cov[(k, k)] + cov[(j, k)].powi(2)) / count).sqrt();
            assert!(
                (sample_cov[(j, k)] - cov[(j, k)]).abs() <= 4.5 * se,
                "{what}: cov[{j},{k}] = {} vs {} (se {se})",
                sample_cov[(j, k)],
                cov[(j, k)]
            );
        }
    }
}

fn noise_config(subsystems: usize, steps: usize) -> String {
    format!(
        r#"subsystems = {subsystems}
steps = {steps}
seed = 2024

[interconnection]
plus = 1
minus = 1

[model]
A = [[0.6, 0.2], [-0.1, 0.5]]
B = [[0.2, -0.1], [0.1, 0.3]]
C = [[0.5], [0.2]]
D = [[0.4, 0.1], [-0.2, 0.3]]
G = [[0.2, 0.1], [-0.15, 0.25]]
H = [[0.1], [0.3]]
J = [[1.0, 0.5], [0.0, 1.0]]
R = [[0.3], [-0.2]]
M = [[0.5, 0.2], [0.2, 0.3]]
Q = [[0.04, 0.01], [0.01, 0.02]]

[dropout]
p = 0.6

[initial]
mean = [1.0, -2.0]
cov = [[2.0, 0.6], [0.6, 1.0]]

[input]
kind = "sine"
amplitude = 1.0
period = 17.0
phase = 0.4
"#
    )
}

#[test]
fn initial_state_and_measurement_noise_have_the_configured_moments() {
    let big_n = 2000;
    let s = setup(&noise_config(big_n, 1));
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &[]);
    let truth = Csv::read(&out.join("truth.csv"));
    truth.assert_index(1, big_n);
    let meas = Csv::read(&out.join("measurements.csv"));
    let inputs = Csv::read(&out.join("inputs.csv"));
    let x = truth.numbers(2, 2);
    let y = meas.numbers(2, 2);
    let u = inputs.numbers(2, 1);

    let x0: Vec<DVector<f64>> = x.iter().map(|r| DVector::from_column_slice(r)).collect();
    assert_moments(
        &x0,
        &DVector::from_vec(vec![1.0, -2.0]),
        &mat(2, 2, &[2.0, 0.6, 0.6, 1.0]),
        "x(1, i)",
    );

    // d = y − γ J x − R u ~ N(0, M).
    let j = mat(2, 2, &[1.0, 0.5, 0.0, 1.0]);
    let r = mat(2, 1, &[0.3, -0.2]);
    let d: Vec<DVector<f64>> = (0..big_n)
        .map(|k| {
            let gamma: f64 = truth.rows[k][4].parse().unwrap();
            DVector::from_column_slice(&y[k])
                - gamma * &j * &x0[k]
                - &r * DVector::from_column_slice(&u[k])
        })
        .collect();
    assert_moments(
        &d,
        &DVector::zeros(2),
        &mat(2, 2, &[0.5, 0.2, 0.2, 0.3]),
        "d(1, i)",
    );
}

#[test]
fn process_noise_has_the_configured_covariance() {
    let (big_n, steps) = (40, 100);
    let s = setup(&noise_config(big_n, steps));
    let out = s.dir.path().join("out");
    simulate_ok(&s.config, &out, &[]);
    let x = Csv::read(&out.join("truth.csv")).numbers(2, 2);
    let u = Csv::read(&out.join("inputs.csv")).numbers(2, 1);
    let (a, b, c) = (
        mat(2, 2, &[0.6, 0.2, -0.1, 0.5]),
        mat(2, 2, &[0.2, -0.1, 0.1, 0.3]),
        mat(2, 1, &[0.5, 0.2]),
    );
    let (d, g, h) = (
        mat(2, 2, &[0.4, 0.1, -0.2, 0.3]),
        mat(2, 2, &[0.2, 0.1, -0.15, 0.25]),
        mat(2, 1, &[0.1, 0.3]),
    );
    let at = |t: usize, i: usize| (t - 1) * big_n + (i - 1);
    let mut omega = Vec::new();
    for t in 1..steps {
        let xs: Vec<DVector<f64>> = (1..=big_n)
            .map(|i| DVector::from_column_slice(&x[at(t, i)]))
            .collect();
        let us: Vec<DVector<f64>> = (1..=big_n)
            .map(|i| DVector::from_column_slice(&u[at(t, i)]))
            .collect();
        let z: Vec<DVector<f64>> = (0..big_n).map(|k| &d * &xs[k] + &h * &us[k]).collect();
        let v = dense_interconnect(1, 1, &vec![g.clone(); big_n], &z).unwrap();
        for k in 0..big_n {
            let next = DVector::from_column_slice(&x[at(t + 1, k + 1)]);
            omega.push(next - &a * &xs[k] - &b * &v[k] - &c * &us[k]);
        }
    }
    assert_moments(
        &omega,
        &DVector::zeros(2),
        &mat(2, 2, &[0.04, 0.01, 0.01, 0.02]),
        "ω(t, i)",
    );
}
