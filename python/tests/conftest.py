"""Fixtures of the package's tests: the repository, the command line built from it (the
reference the arrays must equal), and runs of it."""

import csv
import os
import pathlib
import subprocess

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def sisfilt_binary():
    """The `sisfilt` binary: SISFILT_BIN, else the newest one built in target/."""
    given = os.environ.get("SISFILT_BIN")
    if given:
        return given
    built = [ROOT / "target" / kind / "sisfilt" for kind in ("debug", "release")]
    built = [p for p in built if p.exists()]
    if not built:
        pytest.skip("no sisfilt binary: run `cargo build` first or set SISFILT_BIN")
    return str(max(built, key=lambda p: p.stat().st_mtime))


@pytest.fixture(scope="session")
def cli():
    """Runs the command line; returns its completed process (a failure fails the test)."""
    binary = sisfilt_binary()

    def run(*args, cwd):
        out = subprocess.run([binary, "-q", *map(str, args)], cwd=cwd, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return out

    return run


def config(name):
    return ROOT / "configs" / name


def read_steps(path, subsystems, first=2, last=None):
    """A `t,i,…` CSV as an array [T, N, columns] (empty cells NaN)."""
    with open(path) as f:
        rows = list(csv.reader(f))
    header, rows = rows[0], rows[1:]
    cells = [[float(c) if c != "" else np.nan for c in row[first:last]] for row in rows]
    values = np.array(cells, dtype=float)
    return header, values.reshape(len(rows) // subsystems, subsystems, -1)
