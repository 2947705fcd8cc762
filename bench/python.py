#!/usr/bin/env python3
"""The Python package's cost over the library (issue 38), for BENCHMARKS.md.

    bench/python.py [--runs 5] [--sample 200] [--out bench/python.md]

On workload W (bench/workload.toml) with N = 10⁴ subsystems and T = 100 steps, simulated with
`sisfilt.simulate`:

1. `sisfilt.estimate(model, y, u)` (the distributed filter, default threads) from numpy arrays:
   the wall-clock time of the call against the library's own run of the same arrays inside it
   (`Estimates.timings["run"]`, what `run::estimate` takes when a Rust program calls it) and
   against the filter time within that run (`timings["filter"]`), best of `--runs` runs and
   the first call of the process;
2. a FilterPy loop doing a per-subsystem Kalman filter (`KalmanFilter.predict`, `update`;
   `F = A`, `H = J`, the subsystem's `Q` and `M`, no interconnection, a lost reading taken as
   received) on `--sample` subsystems, scaled to N = 10⁴: the time a Python user would spend
   looping over the chain, as a ratio to the package's call.

Needs the package (`pip install ./python`), numpy and filterpy (part 2 is skipped without it).
"""
import argparse
import os
import platform
import time

import numpy as np

import sisfilt

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--sample", type=int, default=200)
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "python.md"))
    args = parser.parse_args()
    model = sisfilt.Model.from_toml(os.path.join(ROOT, "bench", "workload.toml")).with_(
        steps=100)
    sim = sisfilt.simulate(model)
    y, u = sim["y"], sim["u"]
    walls, filters, runs = [], [], []
    for _ in range(args.runs):
        start = time.perf_counter()
        est = sisfilt.estimate(model, y, u)
        walls.append(time.perf_counter() - start)
        filters.append(est.timings["filter"])
        runs.append(est.timings["run"])
    best = min(range(args.runs), key=lambda k: walls[k])
    wall, filt, run = walls[best], filters[best], runs[best]
    first = (walls[0], runs[0], filters[0])
    lines = [
        "## The Python package against the library (issue 38)",
        "",
        f"`bench/python.py` (sisfilt {sisfilt.__version__}, {time.strftime('%Y-%m-%d')}, "
        f"{platform.machine()}, {os.cpu_count()} cores, default threads): workload W with "
        f"N = 10⁴, T = 100, the distributed filter, arrays from `sisfilt.simulate`; best of "
        f"{args.runs} calls (the first call of the process in brackets).",
        "",
        "| | time | ratio to the library's run | ratio to its filter time |",
        "|---|---|---|---|",
        f"| `sisfilt.estimate(model, y, u)`, the whole call | {wall:.3f} s ({first[0]:.3f} s) "
        f"| **{wall / run:.3f}×** ({first[0] / first[1]:.3f}×) "
        f"| {wall / filt:.2f}× ({first[0] / first[2]:.2f}×) |",
        f"| the library's run of the same arrays inside it (`timings['run']`: setup, "
        f"checks, filter, the estimates gathered) | {run:.3f} s ({first[1]:.3f} s) | 1 "
        f"| {run / filt:.2f}× ({first[1] / first[2]:.2f}×) |",
        f"| the filter time within that run (`timings['filter']`) | {filt:.3f} s "
        f"({first[2]:.3f} s) | {filt / run:.2f}× | 1 |",
    ]
    try:
        from filterpy.kalman import KalmanFilter
    except ImportError:
        KalmanFilter = None
    if KalmanFilter is not None:
        a = np.array([[0.9, 0.1], [-0.1, 0.8]])
        filters_py = []
        for _ in range(args.sample):
            kf = KalmanFilter(dim_x=2, dim_z=1)
            kf.F, kf.H = a, np.array([[1.0, 0.0]])
            kf.Q, kf.R, kf.P = np.eye(2) * 0.01, np.array([[0.1]]), np.eye(2)
            filters_py.append(kf)
        start = time.perf_counter()
        for t in range(y.shape[0]):
            for i, kf in enumerate(filters_py):
                kf.predict()
                kf.update(y[t, i])
        loop = (time.perf_counter() - start) * y.shape[1] / args.sample
        lines.append(
            f"| a FilterPy loop over the subsystems (measured on {args.sample}, scaled to "
            f"10⁴) | {loop:.1f} s | {loop / wall:.0f}× the package's call | |")
    lines.append("")
    lines.append(
        f"The package adds {wall - run:.3f} s to the library's run ({(wall - run) / run:.1%}): "
        "the arrays in and out, the options, a thread to watch for Ctrl-C. The run's time "
        "beyond the filter is the library's (issue 41): its setup (the chain's factorisation "
        "and the stability estimate of docs/theory.md §3) and gathering the 7·10⁶ numbers of "
        f"the estimates: at {run / filt:.2f}× the filter time, the library's own run leaves "
        "no front end within 1.1× of the filter time alone.")
    lines.append("")
    with open(args.out, "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
