#!/usr/bin/env python3
"""The figures of `sisfilt fit` (issue 37, docs/theory.md §16) for BENCHMARKS.md.

    bench/fit.py [--seeds K] [--sizes 4,20,50] [--out bench/fit.md]

1. Recovery: the platoon and the heat rod simulated with `p`, `Q × 2` and `M × 0.5` against
   their configs, over K seeds (default 10), fitted from the configs (joint filter, unknown
   dropouts): per parameter the mean estimate, the bias, the spread of the estimates against
   the mean reported standard error, and the coverage of the 95 % intervals; the fit times.
2. Against statsmodels: the platoon with `p = 1` at N = 4, 20, 50 (T = 200), fitted with
   `--filter centralized --dropouts known --params Q,M`, and statsmodels' `MLEModel.fit`
   (L-BFGS) of the same parametrisation (the log variances of Q11, Q22, M11, M22, shared by
   every car) on the lifted chain built here from the config's matrices: time (the whole
   `sisfilt` process; statsmodels' fit alone) and the results side by side.

Needs `target/release/sisfilt` (`cargo build --release`) and, for part 2, numpy and
statsmodels (`pip install numpy statsmodels`; part 2 is skipped without them). SISFILT names
another binary.
"""
import argparse
import csv
import json
import math
import os
import platform
import statistics
import subprocess
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SISFILT = os.environ.get("SISFILT", os.path.join(ROOT, "target", "release", "sisfilt"))

# What each chain is simulated with: p, the diagonals of Q and M (twice and half the config's).
TRUTH = {
    "platoon": {"p": 0.6, "Q": [0.0002, 0.0008], "M": [0.02, 0.005]},
    "heat_rod": {"p": 0.5, "Q": [0.005, 0.02], "M": [0.005]},
}


def sisfilt(*args, cwd):
    out = subprocess.run([SISFILT, *args], cwd=cwd, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"sisfilt {' '.join(args)}: {out.stderr}")
    return out


def toml_diag(values):
    n = len(values)
    rows = [[values[r] if r == c else 0.0 for c in range(n)] for r in range(n)]
    return "[" + ", ".join("[" + ", ".join(repr(v) for v in row) + "]" for row in rows) + "]"


def truth_values(chain):
    t = TRUTH[chain]
    values = {"p": t["p"]}
    values.update({f"Q{k + 1}{k + 1}": v for k, v in enumerate(t["Q"])})
    values.update({f"M{k + 1}{k + 1}": v for k, v in enumerate(t["M"])})
    return values


def recovery(chain, seeds, work):
    config = os.path.join(ROOT, "configs", f"{chain}.toml")
    t = TRUTH[chain]
    sets = ["--set", f"dropout.p={t['p']}", "--set", f"model.Q={toml_diag(t['Q'])}",
            "--set", f"model.M={toml_diag(t['M'])}"]
    fits, shares, times = [], [], []
    for seed in range(1, seeds + 1):
        out = os.path.join(work, f"{chain}-{seed}")
        sisfilt("simulate", config, "--out", out, "--seed", str(seed), "-q", *sets, cwd=work)
        with open(os.path.join(out, "truth.csv")) as f:
            gamma = [row["gamma"] for row in csv.DictReader(f)]
        shares.append(sum(g == "1" for g in gamma) / len(gamma))
        start = time.perf_counter()
        run = sisfilt("fit", "--config", config, "--meas", os.path.join(out, "measurements.csv"),
                      "--format", "json", "-q", cwd=work)
        times.append(time.perf_counter() - start)
        fits.append(json.loads(run.stdout))
    truth = truth_values(chain)
    rows = []
    for k, p in enumerate(fits[0]["parameters"]):
        name = p["name"]
        est = [f["parameters"][k]["estimate"] for f in fits]
        se = [f["parameters"][k]["se"] for f in fits if f["parameters"][k]["se"] is not None]
        covered = [
            f["parameters"][k]["ci_low"] is not None
            and f["parameters"][k]["ci_low"] <= truth[name] <= f["parameters"][k]["ci_high"]
            for f in fits
        ]
        mean = statistics.fmean(est)
        row = {
            "name": name,
            "true": truth[name],
            "mean": mean,
            "bias": mean / truth[name] - 1,
            "sd": statistics.stdev(est),
            "se": statistics.fmean(se) if se else float("nan"),
            "coverage": sum(covered) / len(covered),
            "intervals": len(se),
        }
        if name == "p":
            row["share_bias"] = statistics.fmean(e - s for e, s in zip(est, shares))
        rows.append(row)
    return rows, times, fits


def lifted_transition(cfg, n_sub):
    """`A_eff` of a chain of `n_sub` subsystems without direct interconnection (G = 0): block
    tridiagonal, `A` on the diagonal, `B⁺ D⁺` below it and `B⁻ D⁻` above."""
    import numpy as np

    mdl = cfg["model"]
    a, b, d = (np.array(mdl[k], float) for k in "ABD")
    assert not np.any(np.array(mdl.get("G", [[0.0]]))), "the lifted chain here needs G = 0"
    plus = cfg["interconnection"]["plus"]
    n = a.shape[0]
    a_eff = np.zeros((n_sub * n, n_sub * n))
    for i in range(n_sub):
        a_eff[i * n:(i + 1) * n, i * n:(i + 1) * n] = a
        if i > 0:  # v⁺(i) = w⁺(i − 1) = D⁺ x(i − 1)
            a_eff[i * n:(i + 1) * n, (i - 1) * n:i * n] = b[:, :plus] @ d[:plus, :]
        if i < n_sub - 1:  # v⁻(i) = w⁻(i + 1) = D⁻ x(i + 1)
            a_eff[i * n:(i + 1) * n, (i + 1) * n:(i + 2) * n] = b[:, plus:] @ d[plus:, :]
    return a_eff


def lifted_statsmodels(config_path, meas, inputs, n_sub):
    """statsmodels' fit of log(Q11, Q22, M11, M22) on the lifted platoon (G = 0, R = 0)."""
    import numpy as np
    import tomllib
    from statsmodels.tsa.statespace.mlemodel import MLEModel

    with open(config_path, "rb") as f:
        cfg = tomllib.load(f)
    mdl = cfg["model"]
    c, j = (np.array(mdl[k], float) for k in "CJ")
    n, q = np.array(mdl["A"]).shape[0], j.shape[0]
    big = n_sub * n
    a_eff = lifted_transition(cfg, n_sub)
    design = np.kron(np.eye(n_sub), j)
    y = np.loadtxt(meas, delimiter=",", skiprows=1)[:, 2:]
    steps = y.shape[0] // n_sub
    endog = y.reshape(steps, n_sub * q)
    u = np.loadtxt(inputs, delimiter=",", skiprows=1)[:, 2:].reshape(steps, n_sub, -1)
    # statsmodels' intercept c_t moves the state from t to t + 1, as C u(t) does.
    intercept = np.einsum("km,tim->tik", c, u).reshape(steps, big).T
    m0 = np.tile(np.array(cfg["initial"]["mean"], float), n_sub)
    p0 = np.kron(np.eye(n_sub), np.array(cfg["initial"]["cov"], float))

    class Lifted(MLEModel):
        def __init__(self):
            super().__init__(endog, k_states=big, k_posdef=big)
            self["design"] = design
            self["transition"] = a_eff
            self["selection"] = np.eye(big)
            self["state_intercept"] = intercept
            self.ssm.initialize_known(m0, p0)

        @property
        def param_names(self):
            return ["Q11", "Q22", "M11", "M22"]

        @property
        def start_params(self):
            return np.log([mdl["Q"][0][0], mdl["Q"][1][1], mdl["M"][0][0], mdl["M"][1][1]])

        def update(self, params, **kwargs):
            params = super().update(params, **kwargs)
            v = np.exp(params)
            self["state_cov"] = np.kron(np.eye(n_sub), np.diag(v[:2]))
            self["obs_cov"] = np.kron(np.eye(n_sub), np.diag(v[2:]))

    model = Lifted()
    start = time.perf_counter()
    res = model.fit(disp=False, maxiter=500)
    elapsed = time.perf_counter() - start
    se = np.sqrt(np.diag(res.cov_params_approx)) * np.exp(res.params)
    return np.exp(res.params), se, res.llf, elapsed


def against_statsmodels(sizes, work):
    try:
        import numpy  # noqa: F401
        import statsmodels  # noqa: F401
    except ImportError:
        return None
    config = os.path.join(ROOT, "configs", "platoon.toml")
    rows = []
    for n_sub in sizes:
        out = os.path.join(work, f"lifted-{n_sub}")
        sisfilt("simulate", config, "--out", out, "--steps", "200", "-q", "--set",
                f"subsystems={n_sub}", "--set", "dropout.p=1.0", "--set",
                f"model.Q={toml_diag(TRUTH['platoon']['Q'])}", "--set",
                f"model.M={toml_diag(TRUTH['platoon']['M'])}", cwd=work)
        meas = os.path.join(out, "measurements.csv")
        start = time.perf_counter()
        run = sisfilt("fit", "--config", config, "--set", f"subsystems={n_sub}", "--meas", meas,
                      "--filter", "centralized", "--dropouts", "known", "--params", "Q,M",
                      "--format", "json", "-q", cwd=work)
        ours_time = time.perf_counter() - start
        ours = json.loads(run.stdout)
        est, se, llf, sm_time = lifted_statsmodels(config, meas, os.path.join(out, "inputs.csv"),
                                                   n_sub)
        rows.append({
            "subsystems": n_sub,
            "ours": ours,
            "ours_time": ours_time,
            "sm": (list(est), list(se), llf),
            "sm_time": sm_time,
        })
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--sizes", default="4,20,50")
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "fit.md"))
    args = parser.parse_args()
    version = subprocess.run([SISFILT, "--version"], capture_output=True, text=True).stdout
    lines = [
        "## Fitting `p`, `Q` and `M`: `sisfilt fit` (issue 37)",
        "",
        f"`bench/fit.py` ({version.strip()}, {time.strftime('%Y-%m-%d')}, "
        f"{platform.machine()}, {os.cpu_count()} cores, default threads).",
        "",
    ]
    limits = {"platoon": ("N = 20, T = 200, five parameters", 5.0),
              "heat_rod": ("N = 50, T = 300, four parameters", 20.0)}
    targets = []
    with tempfile.TemporaryDirectory() as work:
        for chain in ["platoon", "heat_rod"]:
            rows, times, _ = recovery(chain, args.seeds, work)
            what, limit = limits[chain]
            median = statistics.median(times)
            targets.append(f"| fit of the {chain.replace('_', ' ')} ({what}) | {median:.2f} s "
                           f"(median of {len(times)}) | ≤ {limit:.0f} s "
                           f"| {'yes' if median <= limit else 'no'} |")
            lines += [
                f"**Recovery, {chain}** ({args.seeds} seeds, simulated with `p`, `Q × 2`, "
                "`M × 0.5` against the config, fitted from the config: joint filter, unknown "
                f"dropouts). Fit time: median {statistics.median(times):.2f} s, "
                f"max {max(times):.2f} s (whole process).",
                "",
                "| parameter | true | mean estimate | bias | sd of the estimates | mean se "
                "| 95 % interval covers the truth |",
                "|---|---|---|---|---|---|---|",
            ]
            for r in rows:
                extra = (f" (against the sample's arrival share: {r['share_bias']:+.4f})"
                         if "share_bias" in r else "")
                lines.append(
                    f"| {r['name']} | {r['true']:.4g} | {r['mean']:.4g} | {r['bias']:+.1%}{extra} "
                    f"| {r['sd']:.3g} | {r['se']:.3g} | {r['coverage']:.0%} "
                    f"({r['intervals']} intervals) |")
            lines.append("")
        lines += ["| target | measured | required | met |", "|---|---|---|---|", *targets, ""]
        sizes = [int(s) for s in args.sizes.split(",") if s]
        rows = against_statsmodels(sizes, work)
    if rows is None:
        lines += ["Against statsmodels: skipped (numpy and statsmodels not installed).", ""]
    else:
        import statsmodels

        lines += [
            f"**Against statsmodels** {statsmodels.__version__} (`MLEModel.fit`, L-BFGS, on the "
            "lifted chain built from the config): the platoon with `p = 1`, `T = 200`, "
            "`fit --filter centralized --dropouts known --params Q,M`; `Q` twice and `M` half "
            "the config's. Time: the whole `sisfilt` process (the fit, its Hessian and scores, "
            "the innovation check) against statsmodels' fit alone (its Hessian comes after).",
            "",
            "| N (states) | sisfilt (filter runs) | statsmodels | statsmodels / sisfilt "
            "| largest relative difference of the estimates | of the se | log-likelihoods |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            ours = r["ours"]["parameters"]
            est, se, llf = r["sm"]
            d_est = max(abs(p["estimate"] - e) / e for p, e in zip(ours, est))
            d_se = max(abs(p["se"] - s) / s for p, s in zip(ours, se))
            lines.append(
                f"| {r['subsystems']} ({2 * r['subsystems']}) | {r['ours_time']:.2f} s "
                f"({r['ours']['evaluations']}) | {r['sm_time']:.2f} s "
                f"| {r['sm_time'] / r['ours_time']:.2f} "
                f"| {d_est:.1e} | {d_se:.1e} | {r['ours']['loglik']:.6f} / {llf:.6f} |")
        lines += [
            "",
            "The estimates, standard errors and log-likelihoods agree (to the optimisers' "
            "tolerances); the time is mostly the centralized filter's runs (bench/centralized.py "
            "measures one run against statsmodels' Kalman filter).",
            "",
        ]
    with open(args.out, "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
