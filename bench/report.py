#!/usr/bin/env python3
"""Helpers of bench/run.sh (standard library only, except `compare`, which needs numpy).

    report.py record RESULTS NAME THREADS TIME_FILE STDERR_FILE [BUILD]
                                                   append one run (JSON line); BUILD is
                                                   "current" (default) or "baseline"
    report.py compare A.csv B.csv                  max |a − b| of two CSVs
    report.py write RESULTS OUT.md                 the BENCHMARKS.md tables
    report.py criterion TARGET_DIR                 criterion's results under TARGET_DIR

`record` reads GNU time's `-v` report (wall clock, peak RSS, CPU times) and the `timings:` line
that `sisfilt estimate --timings` prints (read / filter / check / write split; builds before
the innovation check print no check). `write` takes the
median over the runs of each case and checks the targets of issue 5; with runs of a baseline
build it also gives each case's best run against the baseline's best, as a ratio, and checks
the targets of issues 41 and 42 (ratios against f497e7e).
"""
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import time


def parse_gnu_time(text):
    out = {}
    for line in text.splitlines():
        line = line.strip()
        if line.startswith("Elapsed (wall clock) time"):
            clock = line.rsplit(": ", 1)[1]
            secs = 0.0
            for part in clock.split(":"):
                secs = secs * 60 + float(part)
            out["wall"] = secs
        elif line.startswith("Maximum resident set size"):
            out["rss_kb"] = int(line.rsplit(": ", 1)[1])
        elif line.startswith("User time"):
            out["user"] = float(line.rsplit(": ", 1)[1])
        elif line.startswith("System time"):
            out["sys"] = float(line.rsplit(": ", 1)[1])
        elif line.startswith("Exit status"):
            out["exit"] = int(line.rsplit(": ", 1)[1])
    return out


TIMINGS = re.compile(
    r"timings: read (?P<read>[\d.]+) s, filter (?P<filter>[\d.]+) s, "
    r"(?:check (?P<check>[\d.]+) s, )?write (?P<write>[\d.]+) s, other (?P<other>[\d.]+) s, "
    r"total (?P<total>[\d.]+) s, (?P<rows>\d+) rows.*?writer thread was busy (?P<writer>[\d.]+) s"
)


def record(results, name, threads, time_file, stderr_file, build="current"):
    with open(time_file) as f:
        run = parse_gnu_time(f.read())
    with open(stderr_file) as f:
        err = f.read()
    m = TIMINGS.search(err)
    if m:
        run.update({k: float(v) for k, v in m.groupdict().items() if v is not None})
        run["rows"] = int(m["rows"])
    if run.get("exit", 0) != 0:
        sys.exit(f"error: case {name} failed:\n{err}")
    run.update(name=name, threads=int(threads), build=build)
    with open(results, "a") as f:
        f.write(json.dumps(run) + "\n")


def compare(a_path, b_path):
    import numpy as np

    a = np.loadtxt(a_path, delimiter=",", skiprows=1, ndmin=2)
    b = np.loadtxt(b_path, delimiter=",", skiprows=1, ndmin=2)
    with open(a_path) as f:
        ha = f.readline()
    with open(b_path) as f:
        hb = f.readline()
    if ha != hb or a.shape != b.shape or not (a[:, :2] == b[:, :2]).all():
        sys.exit(f"error: {a_path} and {b_path} differ in header, shape or (t, i) columns")
    diff = np.abs(a[:, 2:] - b[:, 2:])
    rel = diff / np.maximum(1.0, np.abs(b[:, 2:]))
    print(json.dumps({"max_abs": float(diff.max()), "max_rel": float(rel.max()), "rows": len(a)}))


def load(results, build="current"):
    """The runs of one build by case name, in the order the cases ran."""
    cases = {}
    with open(results) as f:
        for line in f:
            run = json.loads(line)
            if run.get("build", "current") == build:
                cases.setdefault(run["name"], []).append(run)
    return cases


def best(runs, key):
    """The best (smallest) value of `key` over the runs: the figure least disturbed by the
    machine's other work, and the one the ratios against a baseline compare."""
    values = [r[key] for r in runs if key in r]
    return min(values) if values else float("nan")


def best_sum(runs, *keys):
    """The best (smallest) sum of `keys` over the runs that have them all."""
    sums = [sum(r[k] for k in keys) for r in runs if all(k in r for k in keys)]
    return min(sums) if sums else float("nan")


def against_section(cases, base_cases, env):
    """The targets of issues 41 and 42 and every case as a ratio against the baseline build
    (its best run over this tree's best run: above 1 is faster), as Markdown lines."""
    sha, threads = env["against"], env["threads"]

    def crit_best(key, threads, bench="threads"):
        name = f"core/{bench}/{threads}"
        rates = [r[name][1] / (r[name][0] * 1e-9) for r in env.get(key, []) if name in r]
        return max(rates) if rates else float("nan")

    core1, base1 = crit_best("core_runs", 1), crit_best("baseline_core_runs", 1)
    core2 = crit_best("core_runs", threads)
    steady1, steady2 = crit_best("core_runs", 1, "steady"), crit_best("core_runs", threads, "steady")
    short1, short1_base = cases.get("W100-1thread", []), base_cases.get("W100-1thread", [])
    short2 = cases.get(f"W100-{threads}threads", [])
    short2_base = base_cases.get(f"W100-{threads}threads", [])

    def rate(runs):
        return best(runs, "rows") / best(runs, "wall") if runs else float("nan")

    # The setup share: "other" of the best run over that run's total.
    fastest = min(short1, key=lambda r: r.get("total", math.inf), default={})
    setup = fastest.get("other", math.nan) / fastest.get("total", math.nan)
    targets = [
        ("41: filter core, one thread (criterion `core/threads/1`, W)", core1 / base1,
         f"{core1 / base1:.2f}× ({fmt_rate(core1)} against {fmt_rate(base1)} subsystem-steps/s)",
         "≥ 2.2×"),
        ("41: filter phase, one thread (`--timings`, N = 10⁴, T = 100)",
         best(short1_base, "filter") / best(short1, "filter"),
         f"{best(short1_base, 'filter') / best(short1, 'filter'):.2f}× "
         f"({best(short1, 'filter'):.3f} s against {best(short1_base, 'filter'):.3f} s)", "≥ 2.2×"),
        ("41 (for information): filter phase and the innovation check, one thread, against the "
         "baseline's filter phase (a baseline without the check has none)",
         best(short1_base, "filter") / best_sum(short1, "filter", "check"),
         f"{best(short1_base, 'filter') / best_sum(short1, 'filter', 'check'):.2f}× "
         f"({best_sum(short1, 'filter', 'check'):.3f} s against "
         f"{best(short1_base, 'filter'):.3f} s)", None),
        (f"41: filter core, {threads} threads / one (criterion `core/steady`, this tree: one "
         "filter stepping on, as in a run)", steady2 / steady1,
         f"{steady2 / steady1:.2f}× ({fmt_rate(steady2)} against {fmt_rate(steady1)} "
         f"subsystem-steps/s; from a fresh filter every 20 steps, `core/threads`: "
         f"{core2 / core1:.2f}×; the machine gave {env.get('capacity', '?')}× for two processes)",
         "≥ 1.7×"),
        ("41: setup (`other`) of the run, one thread, N = 10⁴, T = 100", setup,
         f"{100 * setup:.1f} % ({fastest.get('other', math.nan):.3f} s of "
         f"{fastest.get('total', math.nan):.3f} s)", "≤ 10 %"),
        (f"42: whole CLI to a file, {threads} threads, N = 10⁴, T = 100",
         rate(short2) / rate(short2_base),
         f"{rate(short2) / rate(short2_base):.2f}× ({fmt_rate(rate(short2))} against "
         f"{fmt_rate(rate(short2_base))} rows/s)", "≥ 3×"),
    ]
    required = {"≥ 2.2×": lambda v: v >= 2.2, "≥ 1.7×": lambda v: v >= 1.7,
                "≤ 10 %": lambda v: v <= 0.10, "≥ 3×": lambda v: v >= 3}
    lines = [
        "",
        f"## Against `{sha}` (side by side)",
        "",
        f"`bench/run.sh {sha}` built `{sha}` beside this tree and ran every case with both",
        "binaries alternately; each figure is the best run of each build (these machines differ",
        "by 2–3× from day to day, so only a ratio taken side by side counts). Above 1 is faster.",
        "",
        "| target | measured | required | met |",
        "|---|---|---|---|",
    ]
    for what, value, text, req in targets:
        if req is None:
            lines.append(f"| {what} | {text} | – | – |")
            continue
        ok = math.isfinite(value) and required[req](value)
        lines.append(f"| {what} | {text} | {req} | {'yes' if ok else '**no**'} |")
    agree = env.get("against_compare")
    if agree:
        lines.append(
            f"\nW's estimates of the two builds differ by at most {agree['max_abs']:.2e} absolute,"
            f" {agree['max_rel']:.2e} relative, over {agree['rows']} rows.")
    lines += [
        "",
        "| case | threads | baseline wall | wall | ratio | baseline filter | filter | ratio |",
        "|---|---|---|---|---|---|---|---|",
    ]
    def ratio(base_time, time, shortest):
        # GNU time's wall clock has 10 ms steps and --timings 1 ms: no ratio of shorter runs.
        if min(base_time, time) < shortest:
            return "–"
        return f"{base_time / time:.2f}×"

    for name, runs in cases.items():
        base = base_cases.get(name)
        if not base:
            continue
        wall, base_wall = best(runs, "wall"), best(base, "wall")
        row = (f"| {name} | {runs[0]['threads']} | {base_wall:.2f} s | {wall:.2f} s "
               f"| {ratio(base_wall, wall, 0.1)} |")
        if "filter" in runs[0] and "filter" in base[0]:
            f, bf = best(runs, "filter"), best(base, "filter")
            row += f" {bf:.3f} s | {f:.3f} s | {ratio(bf, f, 0.01)} |"
        else:
            row += " | | |"
        lines.append(row)
    lines.append("\n(– : a run too short for its clock: under 0.1 s of wall clock, or 0.01 s of"
                 " filter time.)")
    return lines, targets


def io_floor_section(cases, base_cases, env):
    """Reading and writing per row against their floors (`cargo bench --bench io`), and what
    the floors leave of issue 42's budget, as Markdown lines."""
    io = {name: ns / elems for name, ns, elems in env.get("io", []) if elems}
    if not io:
        return []
    threads = env["threads"]
    runs = cases.get(f"W100-{threads}threads", [])
    base = base_cases.get(f"W100-{threads}threads", [])
    rows = best(runs, "rows") if runs else math.nan
    cpu = best_sum(runs, "user", "sys")
    write, write_floor = io.get("io/write", math.nan), io.get("io/write_floor", math.nan)
    read, split = io.get("io/read", math.nan), io.get("io/read_split", math.nan)
    parse = io.get("io/read_floor", math.nan)
    # W100 writes one row and reads two lines (measurements and inputs) per subsystem-step.
    floor = rows * (write_floor + 2 * (split + parse)) * 1e-9
    today = rows * (write + 2 * read) * 1e-9
    lines = [
        "",
        "## Reading and writing against their floors (issue 42)",
        "",
        "`cargo bench --bench io` (this tree, one thread, criterion medians): rows of W, 10⁴ a",
        "step; time per row.",
        "",
        "| | per row | what it is |",
        "|---|---|---|",
        f"| `io/write` | {write:.0f} ns | the estimates writer: `t,i` and five floats, CSV |",
        f"| `io/write_floor` | {write_floor:.0f} ns | the five floats formatted by `zmij` alone"
        " (the shortest text that reads back to the same bits; nothing copied) |",
        f"| `io/read` | {read:.0f} ns | the measurement reader: a row `t,i,y1` parsed and checked |",
        f"| `io/read_split` | {split:.0f} ns | the `csv` crate splitting the row into fields |",
        f"| `io/read_floor` | {parse:.0f} ns | `str::parse::<f64>` of the value alone |",
        "",
    ]
    if base and math.isfinite(rows):
        budget = best(base, "wall") / 3 * threads
        lines.append(
            f"W100 ({rows:.0f} rows, {threads} threads) writes a row and reads two lines (the"
            f" measurement and the input file) per subsystem-step: {today:.3f} s of CPU at"
            f" today's rates, {floor:.3f} s at the floors alone. Issue 42's target, 3× the"
            f" baseline's rows/s, is {best(base, 'wall') / 3:.3f} s of wall clock, at most"
            f" {budget:.3f} s of CPU on {threads} cores for the whole run, whose best took"
            f" {cpu:.3f} s (user + sys): the floors of formatting and parsing leave"
            f" {budget - floor:.3f} s for the filter, the innovation check, the setup, the"
            " kernel's reads and writes and everything the reader checks and the writer"
            " arranges beyond the floors.")
    return lines


def med(runs, key):
    values = [r[key] for r in runs if key in r]
    return statistics.median(values) if values else float("nan")


def machine():
    info = {}
    try:
        with open("/proc/cpuinfo") as f:
            text = f.read()
        names = re.findall(r"^model name\s*:\s*(.*)$", text, re.M)
        mhz = re.findall(r"^cpu MHz\s*:\s*(.*)$", text, re.M)
        info["cpu"] = names[0] if names else platform.processor()
        info["cpus"] = len(names) or os.cpu_count()
        info["mhz"] = float(mhz[0]) if mhz else None
        flags = re.findall(r"^flags\s*:\s*(.*)$", text, re.M)
        info["avx"] = [f for f in ("avx2", "avx512f", "fma") if flags and f in flags[0].split()]
    except OSError:
        info["cpu"], info["cpus"], info["mhz"] = platform.processor(), os.cpu_count(), None
    try:
        with open("/proc/meminfo") as f:
            kb = int(re.search(r"MemTotal:\s*(\d+)", f.read()).group(1))
        info["mem_gib"] = kb / 2**20
    except (OSError, AttributeError):
        info["mem_gib"] = None
    info["kernel"] = platform.release()
    return info


def tool(cmd):
    try:
        return subprocess.run(cmd, capture_output=True, text=True).stdout.strip()
    except OSError:
        return "?"


def fmt_rate(x):
    return f"{x / 1e6:.2f} M" if math.isfinite(x) else "n/a"


def fit_exponent(points):
    """Least-squares slope of log(time) against log(N)."""
    xs = [math.log(n) for n, _ in points]
    ys = [math.log(t) for _, t in points]
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    sxx = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx


def write(results, out_md):
    cases = load(results)
    env = json.load(open(os.path.join(os.path.dirname(results), "env.json")))
    m = machine()
    rows = []  # (target, measured, required, ok)

    def check(what, value, text, required, ok):
        rows.append((what, text, required, "yes" if ok else "**no**"))

    w1, w2 = cases.get("W-1thread", []), cases.get(f"W-{env['threads']}threads", [])
    # The filter core without I/O: criterion's `core` group (N = 10⁴, 20 steps per iteration).
    # Run BENCH_RUNS times; the rates are medians, the speed-up the median of the runs' ratios.
    core_runs = env.get("core_runs", [])

    def crit_rate(run, threads):
        ns, elems = run.get(f"core/threads/{threads}", [float("nan"), 0])
        return elems / (ns * 1e-9) if elems else float("nan")

    def median_or_nan(values):
        return statistics.median(values) if values else float("nan")

    core1 = median_or_nan([crit_rate(r, 1) for r in core_runs])
    core2 = median_or_nan([crit_rate(r, env["threads"]) for r in core_runs])
    cli = med(w2, "rows") / med(w2, "wall") if w2 else float("nan")
    cli1 = med(w1, "rows") / med(w1, "wall") if w1 else float("nan")
    check("filter core without I/O, one thread (W, criterion)", core1,
          f"{fmt_rate(core1)} subsystem-steps/s", "≥ 5 M", core1 >= 5e6)
    check("whole CLI (W: read CSV, filter, write CSV)", cli, f"{fmt_rate(cli)} rows/s",
          "≥ 1 M", cli >= 1e6)
    ratios = [crit_rate(r, env["threads"]) / crit_rate(r, 1) for r in core_runs]
    speedup = median_or_nan(ratios)
    cap = env.get("capacity")
    check(f"filter core, {env['threads']} threads / one thread (criterion)", speedup,
          f"{speedup:.2f}× (median of {', '.join(f'{x:.2f}' for x in sorted(ratios))}; "
          f"{fmt_rate(core2)} subsystem-steps/s; the machine gave {cap}× for two processes)",
          "≥ 1.6×", speedup >= 1.6)

    scale = sorted(
        (int(name.split("N", 1)[1]), med(runs, "filter") / med(runs, "rows") * int(name.split("N", 1)[1]))
        for name, runs in cases.items() if name.startswith("scale-N")
    )
    exponent = fit_exponent(scale) if len(scale) >= 2 else float("nan")
    check(f"scaling in N ({scale[0][0]}…{scale[-1][0]}, one thread)" if scale else "scaling in N",
          exponent, f"exponent {exponent:.3f}", "1 ± 0.1", abs(exponent - 1) <= 0.1)

    short, long_ = cases.get("mem-T100", []), cases.get("mem-T10000", [])
    rss_ratio = med(long_, "rss_kb") / med(short, "rss_kb")
    check("peak RSS, T = 10⁴ / T = 10²", rss_ratio,
          f"{rss_ratio:.3f} ({med(long_, 'rss_kb') / 1024:.1f} / {med(short, 'rss_kb') / 1024:.1f} MiB)",
          "≤ 1.2", rss_ratio <= 1.2)

    base = cases.get("baseline-python", [])
    ours = cases.get("baseline-sisfilt", [])
    agree = env.get("baseline_compare")
    if base and ours and agree:
        ratio = med(base, "wall") / med(ours, "wall")
        check("speed-up over the numpy baseline", ratio, f"{ratio:.0f}×", "≥ 100×", ratio >= 100)
        check("agreement with the numpy baseline", agree["max_rel"],
              f"max |Δ| {agree['max_abs']:.1e} (relative {agree['max_rel']:.1e})", "≤ 1e−9",
              agree["max_rel"] <= 1e-9)
    else:
        rows.append(("numpy baseline", "not run (see the log)", "≥ 100×, ≤ 1e−9", "n/a"))

    load_avg = env.get("loadavg", "?")
    lines = [
        "# Benchmarks",
        "",
        "Written by `bench/run.sh` (do not edit by hand; rerun it). Every figure is the median of",
        f"{env['runs']} runs unless said otherwise; the workload is `bench/workload.toml` (workload W",
        "of issue 5: `n = 2, q = 1, m = 1, n⁺ = n⁻ = 1`, distributed filter, default options), with",
        "`subsystems` (N) and `steps` (T) changed per case.",
        "",
        f"- date: {time.strftime('%Y-%m-%d %H:%M %Z')}",
        f"- machine: {m['cpu']}, {m['cpus']} logical CPUs"
        + (f" at {m['mhz']:.0f} MHz" if m.get("mhz") else "")
        + (f", {m['mem_gib']:.0f} GiB" if m.get("mem_gib") else "")
        + (f", {'/'.join(m['avx'])}" if m.get("avx") else "")
        + f"; Linux {m['kernel']}",
        f"- load average when the run started: {load_avg}; parallel capacity measured just before"
        f" the runs: {env.get('capacity', '?')}× (two CPU-bound processes against one: 2 on an idle"
        " 2-core machine; figures taken on a busy machine are noisy and pessimistic)",
        f"- `{env.get('rustc', '?')}`, sisfilt at `{env.get('commit', '?')}`; default threads: "
        f"{env['threads']}",
        "",
        "## Targets",
        "",
        "| target | measured | required | met |",
        "|---|---|---|---|",
    ]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in rows]
    against = []
    if env.get("against"):
        base_cases = load(results, "baseline")
        section, against = against_section(cases, base_cases, env)
        lines += section
        lines += io_floor_section(cases, base_cases, env)

    lines += [
        "",
        "## Whole CLI on W (N = 10⁴, T = 10³: 10⁷ rows)",
        "",
        "`sisfilt estimate --meas W/measurements.csv --out W/estimates.csv --timings` (inputs from",
        "`W/inputs.csv`); the split comes from `--timings`: wall-clock time of the main thread",
        "reading (the measurement and input files side by side), filtering, scoring the",
        "innovations (the check), and handing each step to the writer thread (a copy, plus waiting when the writer falls behind), and the",
        "time the writer thread spent formatting and writing, in parallel with the rest. Peak",
        "RSS from `/usr/bin/time -v`.",
        "",
        "| threads | wall | rows/s | read | filter | check | hand-off to writer | other | writer thread busy | filter phase rate | user + sys CPU | peak RSS |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for runs in (w1, w2):
        if not runs:
            continue
        r0 = runs[0]
        lines.append(
            f"| {r0['threads']} | {med(runs, 'wall'):.2f} s | {fmt_rate(med(runs, 'rows') / med(runs, 'wall'))} "
            f"| {med(runs, 'read'):.2f} s | {med(runs, 'filter'):.2f} s | {med(runs, 'check'):.2f} s "
            f"| {med(runs, 'write'):.2f} s "
            f"| {med(runs, 'other'):.2f} s | {med(runs, 'writer'):.2f} s "
            f"| {fmt_rate(med(runs, 'rows') / med(runs, 'filter'))} subsystem-steps/s "
            f"| {med(runs, 'user') + med(runs, 'sys'):.2f} s | {med(runs, 'rss_kb') / 1024:.1f} MiB |"
        )
    lines.append(f"\nWhole CLI with one thread: {fmt_rate(cli1)} rows/s.")

    lines += [
        "",
        "## Scaling in N (one thread)",
        "",
        "Filter time per step from `--timings`; T chosen so that each run has about 10⁶ rows.",
        "",
        "| N | T | filter time per step | per subsystem-step |",
        "|---|---|---|---|",
    ]
    for n_sub, _ in scale:
        runs = cases[f"scale-N{n_sub}"]
        steps = med(runs, "rows") / n_sub
        per_step = med(runs, "filter") / steps
        lines.append(f"| {n_sub} | {steps:.0f} | {per_step * 1e3:.4f} ms | {per_step / n_sub * 1e9:.0f} ns |")
    lines.append(f"\nFitted exponent of time against N (least squares in log–log): **{exponent:.3f}**.")

    lines += [
        "",
        "## Memory against the horizon (N = 10³, default threads)",
        "",
        "| T | rows | peak RSS |",
        "|---|---|---|",
        f"| 10² | {med(short, 'rows'):.0f} | {med(short, 'rss_kb') / 1024:.1f} MiB |",
        f"| 10⁴ | {med(long_, 'rows'):.0f} | {med(long_, 'rss_kb') / 1024:.1f} MiB |",
        "",
        "Everything streams one time step at a time: the readers hold one step, the filter its",
        "state, the writer one batch of formatted rows.",
    ]

    smooth = cases.get("W-smooth", [])
    if smooth:
        estimate = env.get("smooth_estimate", "?")
        ratio = med(smooth, "rss_kb") * 1024 / env.get("smooth_estimate_bytes", float("nan"))
        lines += [
            "",
            "## Smoothing memory on W (issue 12)",
            "",
            "`sisfilt estimate --meas W/measurements.csv --smooth --out W/smoothed.csv` (the",
            "distributed smoother, default threads) against the estimate of docs/theory.md §9 that",
            f"`sisfilt check` prints for the config ({estimate}): the stored forward pass",
            "`x̂(t|t)`, `x̂(t+1|t)`, `P(t|t)`, `T(t+1)` and the smoothed output, `T·N·(3n + 3n²)·8`",
            "bytes.",
            "",
            "| wall | peak RSS | §10 estimate | RSS / estimate |",
            "|---|---|---|---|",
            f"| {med(smooth, 'wall'):.2f} s | {med(smooth, 'rss_kb') / 1024 ** 2:.2f} GiB "
            f"| {estimate} | {ratio:.2f} |",
        ]

    cvd = {}
    for name, runs in cases.items():
        if name.startswith("cvd-"):
            _, kind, n_sub = name.split("-")
            steps = med(runs, "rows") / int(n_sub[1:])
            cvd.setdefault(int(n_sub[1:]), {})[kind] = (med(runs, "filter") / steps, steps)
    if cvd:
        lines += [
            "",
            "## Centralized against distributed (time per step, filter phase, default threads)",
            "",
            "| N | lifted states | distributed | centralized | centralized / distributed |",
            "|---|---|---|---|---|",
        ]
        for n_sub in sorted(cvd):
            d, c = cvd[n_sub].get("distributed"), cvd[n_sub].get("centralized")
            lines.append(
                f"| {n_sub} | {2 * n_sub} | {d[0] * 1e6:.1f} µs | {c[0] * 1e3:.2f} ms | {c[0] / d[0]:.0f}× |"
            )
        lines += [
            "",
            "The centralized filter is the optimal linear estimator (docs/theory.md §7) at `O((N·n)³)` per",
            "step (asymptotically 27× the time for every tripling of N); the distributed one is",
            "linear in N. The centralized filter is worth running as the yardstick, or for its",
            "honest covariance, on chains of up to about a hundred subsystems, where a step costs",
            "at most milliseconds; beyond that only the distributed filter is practical.",
        ]

    if base and ours and agree:
        lines += [
            "",
            "## Against a numpy baseline",
            "",
            "`bench/baseline.py`: the same distributed filter written with numpy, one subsystem at a",
            "time in a Python loop (as a FilterPy user would write it), reading the same CSV files",
            "and writing the same estimates CSV; compared number by number in the script.",
            "",
            "| | N | T | wall | runs |",
            "|---|---|---|---|---|",
            f"| numpy baseline | {env['baseline_n']} | {env['baseline_t']} | {med(base, 'wall'):.1f} s | {len(base)} |",
            f"| `sisfilt estimate` | {env['baseline_n']} | {env['baseline_t']} | {med(ours, 'wall'):.3f} s | {len(ours)} |",
            "",
            f"Largest difference over {agree['rows']} rows: {agree['max_abs']:.2e} absolute,"
            f" {agree['max_rel']:.2e} relative (to max(1, |value|)).",
        ]

    profile = os.path.join(os.path.dirname(results), "profile.txt")
    if os.path.exists(profile):
        lines += [
            "",
            "## Profile of the remaining hot spots",
            "",
            "`perf record` of `estimate` on W with one thread; self time per function:",
            "",
            "```text",
            open(profile).read().rstrip(),
            "```",
        ]
    crit = env.get("criterion")
    if crit:
        lines += [
            "",
            "## criterion (`cargo bench --bench filter`)",
            "",
            "| benchmark | median time per iteration | throughput |",
            "|---|---|---|",
        ]
        for name, ns, elems in crit:
            lines.append(f"| {name} | {ns / 1e6:.3f} ms | {fmt_rate(elems / (ns * 1e-9))} elements/s |")
    lines.append("")
    # Sections measured by hand and kept beside this script, carried over verbatim: the
    # centralized filter against statsmodels (issue 43, `bench/centralized.py`), the joint
    # filter's (issue 10, `cargo bench --bench joint`) and the mixture update's (issue 25,
    # the `update` and `joint_update` groups), `fit`'s (issue 37, `bench/fit.py`) and the
    # Python package's (issue 38, `bench/python.py`).
    for section in ["centralized.md", "joint.md", "mixture.md", "fit.md", "python.md"]:
        path = os.path.join(os.path.dirname(os.path.abspath(__file__)), section)
        if os.path.exists(path):
            with open(path) as f:
                lines.append(f.read().rstrip("\n"))
            lines.append("")
    with open(out_md, "w") as f:
        f.write("\n".join(lines))
    for a, b, c, d in rows:
        print(f"{a:55} {b:45} {c:12} {d}")
    for what, _, text, req in against:
        print(f"{what:55} {text:45} {req}")


def criterion_results(target):
    """(benchmark, median ns, elements) of every criterion benchmark under TARGET/criterion."""
    out = []
    for dirpath, _, files in os.walk(os.path.join(target, "criterion")):
        if os.path.basename(dirpath) == "new" and "estimates.json" in files:
            est = json.load(open(os.path.join(dirpath, "estimates.json")))
            bench = json.load(open(os.path.join(dirpath, "benchmark.json")))
            tp = bench.get("throughput") or {}
            elems = tp.get("Elements") or 0
            out.append((bench["full_id"], est["median"]["point_estimate"], elems))
    return sorted(out)


if __name__ == "__main__":
    cmd, args = sys.argv[1], sys.argv[2:]
    if cmd == "record":
        record(*args)
    elif cmd == "compare":
        compare(*args)
    elif cmd == "write":
        write(*args)
    elif cmd == "criterion":
        print(json.dumps(criterion_results(args[0])))
    else:
        sys.exit(__doc__)
