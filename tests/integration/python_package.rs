//! The Python package (`python/`): built from this tree with maturin into the test Python and
//! its pytest suite (`python/tests`) run against the command line of this build, whose
//! numbers the arrays must equal.
//!
//! Python comes from [`test_python`], a virtual environment (the package is installed only into
//! one); without one the test says so and passes.

use std::path::Path;
use std::process::Command;

use crate::common::test_python;

#[test]
fn the_python_package_passes_its_tests() {
    let Some(python) = test_python() else { return };
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    // pip runs the `maturin` of the environment, which is on its PATH only when activated.
    let bin = Path::new(python).parent().unwrap_or(Path::new("."));
    let path = std::env::join_paths(std::iter::once(bin.to_path_buf()).chain(
        std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()),
    ))
    .unwrap();
    let install = Command::new(python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-build-isolation",
            "--no-deps",
        ])
        .arg(root.join("python"))
        .env("PATH", &path)
        .output()
        .unwrap();
    assert!(
        install.status.success(),
        "pip install ./python: {}{}",
        String::from_utf8_lossy(&install.stdout),
        String::from_utf8_lossy(&install.stderr)
    );
    let tests = Command::new(python)
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
        .arg(root.join("python").join("tests"))
        .env("SISFILT_BIN", env!("CARGO_BIN_EXE_sisfilt"))
        .output()
        .unwrap();
    assert!(
        tests.status.success(),
        "pytest python/tests: {}{}",
        String::from_utf8_lossy(&tests.stdout),
        String::from_utf8_lossy(&tests.stderr)
    );
}
