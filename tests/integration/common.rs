//! Helpers shared by the integration tests: running the binary, writing configs, reading the
//! CSV files of docs/theory.md §13, and an independent dense solve of the interconnection equations
//! (P2)–(P4) with the lifted `A_eff` of docs/theory.md §3 built from it.
#![allow(dead_code, non_snake_case)]

use std::path::{Path, PathBuf};

use assert_cmd::Command;
use nalgebra::{DMatrix, DVector};

/// The `sisfilt` binary of this crate.
pub fn sisfilt() -> Command {
    let mut cmd = Command::cargo_bin("sisfilt").expect("the sisfilt binary");
    cmd.env_remove("RUST_BACKTRACE");
    cmd
}

/// The folder of the configs shipped with the crate.
pub fn configs_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("configs")
}

/// A config shipped in `configs/`.
pub fn shipped_config(name: &str) -> PathBuf {
    let path = configs_dir().join(name);
    assert!(path.is_file(), "{} is missing", path.display());
    path
}

/// Every config shipped in `configs/`, in name order.
pub fn shipped_configs() -> Vec<PathBuf> {
    let dir = configs_dir();
    let mut out: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("configs/ exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    out.sort();
    assert!(!out.is_empty(), "no configs in {}", dir.display());
    out
}

/// Writes `text` to `dir/name` and returns the path.
pub fn write_file(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// A matrix as a TOML list of rows; `{:?}` keeps a decimal point on every number.
pub fn toml_matrix(m: &DMatrix<f64>) -> String {
    let rows: Vec<String> = (0..m.nrows())
        .map(|r| {
            let row: Vec<String> = (0..m.ncols()).map(|c| format!("{:?}", m[(r, c)])).collect();
            format!("[{}]", row.join(", "))
        })
        .collect();
    format!("[{}]", rows.join(", "))
}

/// Row-major matrix from a slice.
pub fn mat(rows: usize, cols: usize, data: &[f64]) -> DMatrix<f64> {
    assert_eq!(data.len(), rows * cols);
    DMatrix::from_row_slice(rows, cols, data)
}

/// Asserts the shape of a failed command's standard error (docs/theory.md §13): exactly one line, and it
/// starts with `error: `. Returns that line.
pub fn one_error_line(stderr: &[u8]) -> String {
    let text = String::from_utf8(stderr.to_vec()).expect("utf-8 stderr");
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 1, "expected one stderr line, got {text:?}");
    assert!(
        lines[0].starts_with("error: "),
        "stderr line does not start with `error: `: {text:?}"
    );
    assert!(
        text.ends_with('\n'),
        "stderr not newline-terminated: {text:?}"
    );
    lines[0].to_string()
}

/// A CSV file as its header and rows of raw cells.
pub struct Csv {
    pub header: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Csv {
    pub fn read(path: &Path) -> Csv {
        let mut r = csv::ReaderBuilder::new()
            .has_headers(true)
            .from_path(path)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let header = r.headers().unwrap().iter().map(str::to_string).collect();
        let rows = r
            .records()
            .map(|rec| rec.unwrap().iter().map(str::to_string).collect())
            .collect();
        Csv { header, rows }
    }

    /// Asserts that rows are `(t, i)` for `t = 1..T`, `i = 1..N`, in that order, each once.
    pub fn assert_index(&self, steps: usize, subsystems: usize) {
        assert_eq!(self.rows.len(), steps * subsystems, "row count");
        let mut k = 0;
        for t in 1..=steps {
            for i in 1..=subsystems {
                let row = &self.rows[k];
                assert_eq!(row.len(), self.header.len(), "row {k}: column count");
                assert_eq!(row[0], t.to_string(), "row {k}: t");
                assert_eq!(row[1], i.to_string(), "row {k}: i");
                k += 1;
            }
        }
    }

    /// The numeric cells of columns `first..first+width` of every row.
    pub fn numbers(&self, first: usize, width: usize) -> Vec<Vec<f64>> {
        self.rows
            .iter()
            .map(|r| {
                r[first..first + width]
                    .iter()
                    .map(|c| {
                        c.parse::<f64>()
                            .unwrap_or_else(|_| panic!("not a number: {c:?}"))
                    })
                    .collect()
            })
            .collect()
    }
}

/// The header `t,i,{prefix}1..{prefix}width` plus `extra`.
pub fn header(prefix: &str, width: usize, extra: &[&str]) -> Vec<String> {
    let mut h = vec!["t".to_string(), "i".to_string()];
    h.extend((1..=width).map(|k| format!("{prefix}{k}")));
    h.extend(extra.iter().map(|s| s.to_string()));
    h
}

/// Solves (P2)–(P4) densely, exactly as docs/theory.md §1 writes them: the unknowns are every `w(i)` and
/// `v(i)`; the equations are `w(i) − G(i) v(i) = z(i)`, `v⁺(i) = w⁺(i−1)` (`v⁺(1) = 0`) and
/// `v⁻(i) = w⁻(i+1)` (`v⁻(N) = 0`). Returns `v(1..N)`, or `None` when the system is singular.
pub fn dense_interconnect(
    plus: usize,
    minus: usize,
    g: &[DMatrix<f64>],
    z: &[DVector<f64>],
) -> Option<Vec<DVector<f64>>> {
    let big_n = g.len();
    let s = plus + minus;
    assert_eq!(z.len(), big_n);
    let size = 2 * big_n * s;
    if size == 0 {
        return Some(vec![DVector::zeros(0); big_n]);
    }
    let mut a = DMatrix::<f64>::zeros(size, size);
    let mut b = DVector::<f64>::zeros(size);
    let w_at = |i: usize, k: usize| (i - 1) * s + k;
    let v_at = |i: usize, k: usize| big_n * s + (i - 1) * s + k;
    let mut row = 0;
    for i in 1..=big_n {
        assert_eq!(g[i - 1].shape(), (s, s));
        for k in 0..s {
            a[(row, w_at(i, k))] = 1.0;
            for c in 0..s {
                a[(row, v_at(i, c))] -= g[i - 1][(k, c)];
            }
            b[row] = z[i - 1][k];
            row += 1;
        }
    }
    for i in 1..=big_n {
        for k in 0..s {
            a[(row, v_at(i, k))] = 1.0;
            if k < plus {
                if i > 1 {
                    a[(row, w_at(i - 1, k))] = -1.0;
                }
            } else if i < big_n {
                a[(row, w_at(i + 1, k))] = -1.0;
            }
            row += 1;
        }
    }
    let lu = a.clone().lu();
    // Reject (numerically) singular systems the way a careful user would: by the smallest
    // singular value relative to the largest.
    let sv = a.singular_values();
    if sv.min() <= 1e-13 * sv.max() {
        return None;
    }
    let x = lu.solve(&b)?;
    Some(
        (1..=big_n)
            .map(|i| DVector::from_iterator(s, (0..s).map(|k| x[v_at(i, k)])))
            .collect(),
    )
}

/// One subsystem's matrices needed for `A_eff`.
#[derive(Clone, Debug)]
pub struct Sub {
    pub A: DMatrix<f64>,
    pub B: DMatrix<f64>,
    pub D: DMatrix<f64>,
    pub G: DMatrix<f64>,
}

/// The dense lifted `A_eff` (docs/theory.md §3), column by column from unit states through
/// [`dense_interconnect`].
pub fn dense_a_eff(plus: usize, minus: usize, subs: &[Sub]) -> DMatrix<f64> {
    let n = subs[0].A.nrows();
    let big_n = subs.len();
    let size = big_n * n;
    let g: Vec<DMatrix<f64>> = subs.iter().map(|p| p.G.clone()).collect();
    let mut out = DMatrix::zeros(size, size);
    for col in 0..size {
        let mut x = DVector::<f64>::zeros(size);
        x[col] = 1.0;
        let xi = |i: usize| x.rows(i * n, n).into_owned();
        let z: Vec<DVector<f64>> = (0..big_n).map(|i| &subs[i].D * xi(i)).collect();
        let v = dense_interconnect(plus, minus, &g, &z).expect("well-posed interconnection");
        for i in 0..big_n {
            let next = &subs[i].A * xi(i) + &subs[i].B * &v[i];
            out.view_mut((i * n, col), (n, 1)).copy_from(&next);
        }
    }
    out
}

/// Spectral radius from nalgebra's complex eigenvalues.
pub fn spectral_radius(a: &DMatrix<f64>) -> f64 {
    a.complex_eigenvalues()
        .iter()
        .map(|l| l.norm())
        .fold(0.0, f64::max)
}

/// The spectral radii printed by `check`, one per line that mentions it, as
/// `(line, value)`. The value is the first number after the words "spectral radius".
pub fn printed_radii(stdout: &str) -> Vec<(String, f64)> {
    stdout
        .lines()
        .filter_map(|line| {
            let at = line.find("spectral radius")?;
            let rest = &line[at + "spectral radius".len()..];
            let value = rest
                .split(|c: char| c.is_whitespace() || c == '(' || c == ')' || c == ',')
                .find_map(|tok| tok.parse::<f64>().ok())?;
            Some((line.to_string(), value))
        })
        .collect()
}

/// Runs `sisfilt ARGS…` in `dir`, which must succeed.
pub fn run_ok_in(dir: &Path, args: &[&str]) -> std::process::Output {
    let out = sisfilt().current_dir(dir).args(args).output().unwrap();
    assert!(
        out.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Simulates `config` into `dir/NAME` and runs `sisfilt estimate` on its measurements (the
/// run's config from its `run.json`) into `dir/NAME.csv`.
pub fn estimate_simulated(dir: &Path, config: &Path, name: &str) -> std::process::Output {
    let data = dir.join(name);
    simulate_files(config, &data);
    sisfilt()
        .arg("estimate")
        .arg("--meas")
        .arg(data.join("measurements.csv"))
        .arg("--out")
        .arg(dir.join(format!("{name}.csv")))
        .output()
        .unwrap()
}

/// Runs `sisfilt simulate CONFIG --out DIR`, which must succeed.
pub fn simulate_files(config: &Path, out: &Path) {
    let run = sisfilt()
        .arg("simulate")
        .arg(config)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "simulate {}: {}",
        config.display(),
        String::from_utf8_lossy(&run.stderr)
    );
}

/// A validated model from config text (named `test.toml` in messages).
pub fn model_from(text: &str) -> sisfilt::model::Model {
    let src = sisfilt::config::ConfigSource::from_text("test.toml", ".".into(), text.to_string())
        .unwrap();
    sisfilt::model::Model::from_config(&src).unwrap()
}

/// A shipped config of `configs/`, validated.
pub fn shipped_model(name: &str) -> sisfilt::model::Model {
    let path = shipped_config(name);
    sisfilt::model::Model::from_config(&sisfilt::config::ConfigSource::from_file(&path).unwrap())
        .unwrap()
}

/// One simulated run in memory: per step, `x`, `y`, `u` and `γ` of the whole chain.
pub struct Run {
    pub x: Vec<Vec<f64>>,
    pub y: Vec<Vec<f64>>,
    pub u: Vec<Vec<f64>>,
    pub gamma: Vec<Vec<bool>>,
}

/// Simulates `model.steps` steps with the library's simulator.
pub fn simulate_run(model: &sisfilt::model::Model, seed: u64) -> Run {
    simulate_steps(model, model.horizon().unwrap(), seed)
}

/// Simulates `steps` steps with the library's simulator.
pub fn simulate_steps(model: &sisfilt::model::Model, steps: usize, seed: u64) -> Run {
    let mut run = Run {
        x: vec![],
        y: vec![],
        u: vec![],
        gamma: vec![],
    };
    let mut inputs = sisfilt::inputs::InputStream::open(model, None).unwrap();
    sisfilt::simulate::simulate(model, steps, seed, &mut inputs, |s| {
        run.x.push(s.x.to_vec());
        run.y.push(s.y.to_vec());
        run.u.push(s.u.to_vec());
        run.gamma.push(s.gamma.to_vec());
        Ok(())
    })
    .unwrap();
    run
}

/// The platoon simulated for `steps` steps into `dir` (its `truth.csv`, `inputs.csv`, …), and
/// its measurements with gaps written to `dir/name`: the cells `(t, i)` with
/// `gaps(t, i) = [element 1 empty, element 2 empty]`.
pub fn platoon_with_gaps(
    dir: &Path,
    steps: usize,
    name: &str,
    gaps: impl Fn(usize, usize) -> [bool; 2],
) -> PathBuf {
    sisfilt()
        .args(["-q", "simulate"])
        .arg(shipped_config("platoon.toml"))
        .args(["--steps", &steps.to_string(), "--out"])
        .arg(dir)
        .assert()
        .success();
    let text = std::fs::read_to_string(dir.join("measurements.csv")).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for line in lines.iter_mut().skip(1) {
        let mut cells: Vec<String> = line.split(',').map(str::to_string).collect();
        let (t, i): (usize, usize) = (cells[0].parse().unwrap(), cells[1].parse().unwrap());
        for (k, gap) in gaps(t, i).into_iter().enumerate() {
            if gap {
                cells[2 + k].clear();
            }
        }
        *line = cells.join(",");
    }
    write_file(dir, name, &(lines.join("\n") + "\n"))
}

/// The Python of the tests that need numpy, pandas, pytest and maturin (files written by numpy
/// and pandas, the Python package): `SISFILT_TEST_PYTHON`, else the virtual environment
/// `target/test-python`, made with those packages (from PyPI) the first time a test needs it;
/// `dask[distributed]` is added where pip can install it.
/// `None`, said on standard error, when there is none and none can be made: those tests then
/// pass without running.
pub fn test_python() -> Option<&'static str> {
    static PYTHON: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    PYTHON
        .get_or_init(|| {
            let ready = |python: &Path| {
                std::process::Command::new(python)
                    .args([
                        "-c",
                        "import sys, numpy, pandas, pytest, maturin; assert sys.prefix != sys.base_prefix",
                    ])
                    .output()
                    .is_ok_and(|o| o.status.success())
            };
            if let Some(python) = std::env::var_os("SISFILT_TEST_PYTHON") {
                let python = PathBuf::from(python);
                if ready(&python) {
                    with_dask(&python);
                    return Some(python.display().to_string());
                }
                eprintln!(
                    "skipped: SISFILT_TEST_PYTHON={} is not a virtual environment with numpy, pandas, pytest and maturin",
                    python.display()
                );
                return None;
            }
            let venv = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/test-python");
            let python = venv.join("bin/python");
            if !ready(&python) {
                let succeeds = |c: &mut std::process::Command| c.status().is_ok_and(|s| s.success());
                let made = succeeds(std::process::Command::new("python3").args(["-m", "venv"]).arg(&venv))
                    && succeeds(std::process::Command::new(&python).args([
                        "-m", "pip", "install", "--quiet", "numpy", "pandas", "pytest", "maturin",
                    ]));
                if !made || !ready(&python) {
                    eprintln!(
                        "skipped: could not make {} with numpy, pandas, pytest and maturin (python3 -m venv, then pip from PyPI); set SISFILT_TEST_PYTHON",
                        venv.display()
                    );
                    return None;
                }
            }
            with_dask(&python);
            Some(python.display().to_string())
        })
        .as_deref()
}

/// Installs `dask[distributed]` (from PyPI) into the test Python when it lacks it, for the test
/// of the README's Dask recipe, which says it is skipped when that cannot be done.
fn with_dask(python: &Path) {
    let has = || {
        std::process::Command::new(python)
            .args(["-c", "import dask.distributed"])
            .output()
            .is_ok_and(|o| o.status.success())
    };
    if !has() {
        let _ = std::process::Command::new(python)
            .args(["-m", "pip", "install", "--quiet", "dask[distributed]"])
            .status();
    }
    if !has() {
        eprintln!(
            "note: {} has no dask[distributed] and pip could not install it: the Dask test is skipped",
            python.display()
        );
    }
}
