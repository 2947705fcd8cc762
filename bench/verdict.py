#!/usr/bin/env python3
"""How often the innovation verdict (docs/theory.md §14) warns on the true model, and whether
it names the cause of a wrong one (issue 67, "tests that must exist").

    bench/verdict.py [--seeds K] [--sizes 60,300,1000,5000] [--power-seeds K] [--out bench/verdict.md]

1. False alarms: each chain simulated from its own config (T = 200) and estimated with that
   config by every filter that runs on it (the distributed filter on the weakly coupled
   platoon only: on the strongly coupled springs its covariance is overconfident by
   construction and the run says so; the centralized filter up to 600 lifted states), over K
   seeds (default 20) per size: the runs whose verdict names any cause, against the
   family-wise level 0.001 (0 expected in K runs; the tolerance stated is at most 1 of K).
2. Power: the platoon (N = 20, T = 200) simulated from its config, estimated by the joint
   filter with a wrong config (M or Q ten times too large or too small, p = 0.6 or 0.95
   against 0.85), over K seeds (default 10): how often the verdict names the right cause.

Needs `target/release/sisfilt` (`cargo build --release`); SISFILT names another binary. About
15 minutes on a 2-core machine with the defaults.
"""
import argparse
import json
import os
import platform
import subprocess
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SISFILT = os.environ.get("SISFILT", os.path.join(ROOT, "target", "release", "sisfilt"))
PLATOON = os.path.join(ROOT, "configs", "platoon.toml")
STEPS = 200
MAX_CENTRALIZED_LIFTED = 600

# Masses on springs (n = q = 2), each pulled by its neighbours' positions: strongly coupled,
# the chain of issue 67 whose true model the former verdict rejected.
SPRINGS = """\
subsystems = 20
steps = 200
[interconnection]
plus = 1
minus = 1
[model]
A = [[1.0, 0.1], [-0.2, 0.95]]
B = [[0.0, 0.0], [0.1, 0.1]]
D = [[1.0, 0.0], [1.0, 0.0]]
G = [[0.0, 0.0], [0.0, 0.0]]
J = [[1.0, 0.0], [0.0, 1.0]]
M = [[0.01, 0.0], [0.0, 0.01]]
Q = [[0.0001, 0.0], [0.0, 0.0004]]
[dropout]
p = 0.9
[initial]
cov = [[1.0, 0.0], [0.0, 0.25]]
"""

# The wrong configs of part 2 and the cause the verdict should name (docs/theory.md §14).
WRONG = [
    ("M × 10", ["--set", "model.M=[[0.4, 0.0], [0.0, 0.1]]"], "m_too_large"),
    ("M / 10", ["--set", "model.M=[[0.004, 0.0], [0.0, 0.001]]"], "m_too_small"),
    ("Q × 10", ["--set", "model.Q=[[0.001, 0.0], [0.0, 0.004]]"], "q_too_large"),
    ("Q / 10", ["--set", "model.Q=[[0.00001, 0.0], [0.0, 0.00004]]"], "q_too_small"),
    ("p = 0.6", ["--set", "dropout.p=0.6"], "p_wrong"),
    ("p = 0.95", ["--set", "dropout.p=0.95"], "p_wrong"),
]


def sisfilt(*args, cwd):
    out = subprocess.run([SISFILT, *map(str, args)], cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"sisfilt {' '.join(map(str, args))}: {out.stderr}")
    return out


def verdict(config, data, filter_name, extra, cwd):
    """The causes the verdict of `estimate` names, and the run's seconds."""
    started = time.perf_counter()
    sisfilt("-q", "estimate", "--config", config, "--meas", os.path.join(data, "measurements.csv"),
            "--filter", filter_name, *extra, "--format", "json",
            "--out", os.path.join(cwd, "estimates.json"), cwd=cwd)
    with open(os.path.join(cwd, "estimates.json")) as f:
        doc = json.load(f)
    return doc["innovations"]["verdict"], time.perf_counter() - started


def false_alarms(seeds, sizes, tmp):
    springs = os.path.join(tmp, "springs.toml")
    with open(springs, "w") as f:
        f.write(SPRINGS)
    rows = []
    for chain, config, n, filters in [
        ("platoon", PLATOON, 2, ["distributed", "joint", "centralized"]),
        ("springs", springs, 2, ["joint", "centralized"]),
    ]:
        for size in sizes:
            counts = {f: [0, 0, 0.0] for f in filters if f != "centralized"
                      or size * n <= MAX_CENTRALIZED_LIFTED}
            for seed in range(1, seeds + 1):
                data = os.path.join(tmp, f"{chain}-{size}-{seed}")
                sisfilt("-q", "simulate", config, "--set", f"subsystems={size}", "--steps",
                        STEPS, "--seed", seed, "--out", data, cwd=tmp)
                for f, c in counts.items():
                    causes, seconds = verdict(config, data, f, ["--set", f"subsystems={size}"],
                                              tmp)
                    c[0] += bool(causes)
                    c[1] += 1
                    c[2] += seconds
                subprocess.run(["rm", "-rf", data], check=True)
            for f, (alarms, runs, seconds) in counts.items():
                rows.append((chain, size, f, alarms, runs, seconds / runs))
                print(f"{chain} N = {size} {f}: {alarms} of {runs} ({seconds / runs:.2f} s a run)",
                      flush=True)
    return rows


def power(seeds, tmp):
    rows = []
    for name, settings, cause in WRONG:
        named, alone = 0, 0
        for seed in range(1, seeds + 1):
            data = os.path.join(tmp, f"power-{seed}")
            if not os.path.isdir(data):
                sisfilt("-q", "simulate", PLATOON, "--seed", seed, "--out", data, cwd=tmp)
            causes, _ = verdict(PLATOON, data, "joint", settings, tmp)
            named += cause in causes
            alone += causes == [cause]
        rows.append((name, cause, named, alone, seeds))
        print(f"{name}: {cause} named in {named} of {seeds} ({alone} alone)", flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--sizes", default="60,300,1000,5000")
    parser.add_argument("--power-seeds", type=int, default=10)
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "verdict.md"))
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    version = sisfilt("--version", cwd=ROOT).stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        alarms = false_alarms(args.seeds, sizes, tmp)
        found = power(args.power_seeds, tmp)
    lines = [
        "## The innovation verdict on true and wrong models (issue 67)",
        "",
        f"`bench/verdict.py` ({version}, {time.strftime('%Y-%m-%d')}, {platform.machine()}, "
        f"{os.cpu_count()} cores), T = {STEPS}.",
        "",
        f"**False alarms**: runs on data simulated from the estimating config whose verdict "
        f"names any cause ({args.seeds} seeds per row; family-wise level 0.001, so 0 expected; "
        f"tolerance: at most 1 per row).",
        "",
        "| chain | N | filter | runs with a warning | seconds a run |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {c} | {n} | {f} | {a} of {r} | {s:.2f} |" for c, n, f, a, r, s in alarms]
    lines += [
        "",
        f"**Power**: the platoon (N = 20) simulated from its config, estimated by the joint "
        f"filter with a wrong one ({args.power_seeds} seeds).",
        "",
        "| wrong config | cause | named | named alone |",
        "|---|---|---|---|",
    ]
    lines += [f"| {w} | `{c}` | {k} of {s} | {a} of {s} |" for w, c, k, a, s in found]
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    worst = max(a for _, _, _, a, _, _ in alarms)
    print(f"wrote {args.out}; the most false alarms in a row: {worst}")
    return 0 if worst <= 1 else 1


if __name__ == "__main__":
    raise SystemExit(main())
