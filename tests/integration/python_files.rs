//! Files as numpy and pandas write them by default, written by numpy and pandas themselves:
//! `t` and `i` as floats (`1.0`, `1.000000000000000000e+00`), `NaN`, `nan` and empty cells for
//! missing values, `numpy.savetxt`'s `# ` before the header. Each must give the same estimates,
//! byte for byte, as the same numbers written by hand; a DataFrame written with its index is
//! refused with a hint.
//!
//! Python comes from [`test_python`]; without one the tests say so and pass.

use std::path::Path;
use std::process::Command;

use crate::common::{one_error_line, platoon_with_gaps, shipped_config, sisfilt, test_python};

/// Runs `script` with `python` in `dir`.
fn run_python(python: &str, dir: &Path, script: &str) {
    let out = Command::new(python)
        .current_dir(dir)
        .args(["-c", script])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The estimates (CSV bytes) of `meas` and `inputs` under `args`.
fn estimates(dir: &Path, meas: &str, inputs: &str, args: &[&str]) -> Vec<u8> {
    let out = sisfilt()
        .current_dir(dir)
        .args(["-q", "estimate", "--config"])
        .arg(shipped_config("platoon.toml"))
        .args(["--meas", meas, "--inputs", inputs])
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{meas}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
}

#[test]
fn files_written_by_numpy_and_pandas_are_read_as_they_are() {
    let Some(python) = test_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    // Car 3's row empty at t = 4..6, car 5's second element empty throughout.
    platoon_with_gaps(dir, 15, "by_hand.csv", |t, i| {
        let silent = i == 3 && (4..=6).contains(&t);
        [silent, silent || i == 5]
    });
    run_python(
        python,
        dir,
        r##"
import numpy as np, pandas as pd
df = pd.read_csv("by_hand.csv")
# pandas: t and i become floats (as after any merge with missing values); NaN as empty cells
# (the default) and as the text NaN.
df.astype({"t": float, "i": float}).to_csv("pandas_empty.csv", index=False)
df.to_csv("pandas_nan.csv", index=False, na_rep="NaN")
df.to_csv("pandas_index.csv")
# numpy: everything %.18e, nan as `nan`, the header after "# ".
a = np.genfromtxt("by_hand.csv", delimiter=",", skip_header=1)
np.savetxt("numpy.csv", a, delimiter=",", header="t,i,y1,y2")
u = np.loadtxt("inputs.csv", delimiter=",", skiprows=1)
np.savetxt("numpy_inputs.csv", u, delimiter=",", header="t,i,u1")
"##,
    );
    let numpy_head = std::fs::read_to_string(dir.join("numpy.csv")).unwrap();
    assert!(
        numpy_head.starts_with("# t,i,y1,y2\n1.000000000000000000e+00,")
            && numpy_head.contains(",nan"),
        "{}",
        &numpy_head[..200]
    );
    for args in [
        &["--filter", "joint", "--update", "mixture", "--nis"][..],
        &["--dropouts", "known"][..],
        &["--smooth"][..],
    ] {
        let by_hand = estimates(dir, "by_hand.csv", "inputs.csv", args);
        for (meas, inputs) in [
            ("pandas_empty.csv", "inputs.csv"),
            ("pandas_nan.csv", "inputs.csv"),
            ("numpy.csv", "numpy_inputs.csv"),
        ] {
            assert!(
                estimates(dir, meas, inputs, args) == by_hand,
                "{meas} with {inputs}, {args:?}: not the estimates of the same numbers by hand"
            );
        }
    }
    let out = sisfilt()
        .current_dir(dir)
        .args(["estimate", "--config"])
        .arg(shipped_config("platoon.toml"))
        .args(["--meas", "pandas_index.csv", "--inputs", "inputs.csv"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let msg = one_error_line(&out.stderr);
    assert!(
        msg.contains("pandas_index.csv: line 1:") && msg.contains("index=False"),
        "{msg}"
    );
}
