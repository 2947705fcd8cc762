#!/usr/bin/env python3
"""The exact centralized filter against statsmodels' Kalman filter (issue 43) for BENCHMARKS.md.

    bench/centralized.py [--sizes 20,100,400] [--steps 200] [--runs 3] [--baseline BIN]
                         [--out bench/centralized.md]

The platoon (configs/platoon.toml) at N subsystems (2 N lifted states), simulated with
`--mark-missing` (lost elements are empty cells), filtered by
`sisfilt estimate --filter centralized --dropouts known` and by statsmodels' `KalmanFilter` on
the lifted chain built here from the config's matrices (`A_eff` block tridiagonal since
`G = 0`; lost elements NaN, which statsmodels leaves out as the known-dropout filter does).
Time: the whole `sisfilt` process (read, filter, write to a file) against statsmodels' filter
alone (its BLAS on the default threads, only the filtered means and covariances stored), best
of `--runs` alternating runs, each after the same pause. The filtered means and the diagonal
blocks of the filtered covariances are compared element by element. `--baseline` names another
sisfilt binary timed alongside (a ratio against an earlier commit).

Needs `target/release/sisfilt` (`cargo build --release`; SISFILT names another binary), numpy
and statsmodels (`pip install numpy statsmodels`).
"""
import argparse
import os
import platform
import subprocess
import tempfile
import time
import tomllib

import numpy as np

from fit import lifted_transition

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SISFILT = os.environ.get("SISFILT", os.path.join(ROOT, "target", "release", "sisfilt"))
CONFIG = os.path.join(ROOT, "configs", "platoon.toml")


# Seconds to wait before each timed run: statsmodels' BLAS threads spin on both cores for a
# while after its filter, and would slow the process timed next; and each run, sisfilt's or
# statsmodels', starts from the same quiet machine (after a pause, starting threads and waking
# the other core take longer on a virtual machine).
QUIET = 0.3


def run(*args, cwd):
    out = subprocess.run(list(args), cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(args)}: {out.stderr}")
    return out


def secs(seconds):
    """A time to three or four digits: milliseconds below a second."""
    return f"{seconds * 1e3:.1f} ms" if seconds < 1 else f"{seconds:.2f} s"


def timed_estimate(binary, meas, out, cwd):
    time.sleep(QUIET)
    start = time.perf_counter()
    run(binary, "estimate", "--meas", meas, "--filter", "centralized", "--dropouts", "known",
        "--max-lifted", "100000", "--out", out, "-q", cwd=cwd)
    return time.perf_counter() - start


def lifted_kalman_filter(n_sub, meas, inputs):
    """statsmodels' KalmanFilter of the lifted platoon (G = 0, R = 0, H = 0)."""
    from statsmodels.tsa.statespace.kalman_filter import (
        MEMORY_NO_FORECAST, MEMORY_NO_GAIN, MEMORY_NO_PREDICTED, MEMORY_NO_SMOOTHING,
        MEMORY_NO_STD_FORECAST, KalmanFilter)

    with open(CONFIG, "rb") as f:
        cfg = tomllib.load(f)
    mdl = cfg["model"]
    c, j, q_cov, m_cov = (np.array(mdl[k], float) for k in "CJQM")
    n, q = np.array(mdl["A"]).shape[0], j.shape[0]
    big = n_sub * n
    a_eff = lifted_transition(cfg, n_sub)
    y = np.genfromtxt(meas, delimiter=",", skip_header=1)[:, 2:]
    steps = y.shape[0] // n_sub
    u = np.loadtxt(inputs, delimiter=",", skiprows=1)[:, 2:].reshape(steps, n_sub, -1)
    kf = KalmanFilter(k_endog=n_sub * q, k_states=big, k_posdef=big)
    kf.bind(np.asfortranarray(y.reshape(steps, n_sub * q).T))
    kf["design"] = np.kron(np.eye(n_sub), j)
    kf["obs_cov"] = np.kron(np.eye(n_sub), m_cov)
    kf["transition"] = a_eff
    kf["selection"] = np.eye(big)
    kf["state_cov"] = np.kron(np.eye(n_sub), q_cov)
    # statsmodels' intercept c_t moves the state from t to t + 1, as C u(t) does.
    kf["state_intercept"] = np.einsum("km,tim->tik", c, u).reshape(steps, big).T
    kf.initialize_known(np.tile(np.array(cfg["initial"]["mean"], float), n_sub),
                        np.kron(np.eye(n_sub), np.array(cfg["initial"]["cov"], float)))
    kf.set_conserve_memory(MEMORY_NO_FORECAST | MEMORY_NO_PREDICTED | MEMORY_NO_GAIN
                           | MEMORY_NO_SMOOTHING | MEMORY_NO_STD_FORECAST)
    time.sleep(QUIET)
    start = time.perf_counter()
    res = kf.filter()
    return res, time.perf_counter() - start


def compare(estimates, res, n_sub):
    """Largest absolute differences of x̂(t|t) and of the diagonal blocks of P(t|t)."""
    ours = np.genfromtxt(estimates, delimiter=",", names=True)
    steps = len(ours) // n_sub
    mean = np.stack([ours["x1"], ours["x2"]], axis=1).reshape(steps, 2 * n_sub)
    d_mean = np.abs(mean - res.filtered_state.T).max()
    cov = res.filtered_state_cov  # (states, states, steps)
    d_cov = 0.0
    for k, name in ((0, "P1_1"), (1, "P2_2")):
        theirs = np.stack([cov[2 * i + k, 2 * i + k, :] for i in range(n_sub)], axis=1)
        d_cov = max(d_cov, np.abs(ours[name].reshape(steps, n_sub) - theirs).max())
    theirs = np.stack([cov[2 * i, 2 * i + 1, :] for i in range(n_sub)], axis=1)
    d_cov = max(d_cov, np.abs(ours["P1_2"].reshape(steps, n_sub) - theirs).max())
    return d_mean, d_cov


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="20,100,400")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--baseline", help="another sisfilt binary, timed alongside")
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "centralized.md"))
    args = parser.parse_args()
    import statsmodels

    version = run(SISFILT, "--version", cwd=ROOT).stdout.strip()
    head = "| N (states) | sisfilt | statsmodels | sisfilt / statsmodels |"
    rule = "|---|---|---|---|"
    if args.baseline:
        head += " baseline | baseline / sisfilt |"
        rule += "---|---|"
    lines = [
        "## The exact centralized filter against statsmodels (issue 43)",
        "",
        f"`bench/centralized.py` ({version}, {time.strftime('%Y-%m-%d')}, "
        f"{platform.machine()}, {os.cpu_count()} cores, default threads; statsmodels "
        f"{statsmodels.__version__}, numpy {np.__version__}). The platoon, T = {args.steps}, "
        "simulated with `--mark-missing`, `estimate --filter centralized --dropouts known`: "
        "the whole `sisfilt` process against statsmodels' `KalmanFilter.filter()` alone, best "
        f"of {args.runs} alternating runs, each after a pause of {QUIET} s.",
        "",
        head + " largest difference of x̂(t|t) | of P(t|t)'s blocks |",
        rule + "---|---|",
    ]
    with tempfile.TemporaryDirectory() as work:
        for n_sub in [int(s) for s in args.sizes.split(",") if s]:
            folder = os.path.join(work, f"platoon-{n_sub}")
            run(SISFILT, "simulate", CONFIG, "--out", folder, "--steps", str(args.steps),
                "--mark-missing", "-q", "--set", f"subsystems={n_sub}", cwd=work)
            meas = os.path.join(folder, "measurements.csv")
            estimates = os.path.join(folder, "estimates.csv")
            ours, theirs, base = [], [], []
            for _ in range(args.runs):
                ours.append(timed_estimate(SISFILT, meas, estimates, work))
                if args.baseline:
                    base.append(timed_estimate(args.baseline, meas, estimates + ".base", work))
                res, elapsed = lifted_kalman_filter(n_sub, meas,
                                                    os.path.join(folder, "inputs.csv"))
                theirs.append(elapsed)
            d_mean, d_cov = compare(estimates, res, n_sub)
            row = (f"| {n_sub} ({2 * n_sub}) | {secs(min(ours))} | {secs(min(theirs))} "
                   f"| {min(ours) / min(theirs):.2f} |")
            if args.baseline:
                row += f" {secs(min(base))} | {min(base) / min(ours):.2f}× |"
            lines.append(row + f" {d_mean:.1e} | {d_cov:.1e} |")
            print(lines[-1], flush=True)
    lines.append("")
    with open(args.out, "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
