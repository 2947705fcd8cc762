#!/usr/bin/env bash
# Reproduces every figure of BENCHMARKS.md (issue 5) and rewrites that file:
#   - builds sisfilt in release mode; measures the parallel capacity of the machine (two
#     CPU-bound processes against one) and the filter core without I/O (criterion, one and
#     two threads, from a fresh filter every 20 steps and one filter stepping on);
#   - generates workload W (bench/workload.toml, N = 10⁴, T = 10³) with `sisfilt simulate`
#     and runs the whole CLI on it under /usr/bin/time -v, with one thread and with all
#     cores (RAYON_NUM_THREADS), reporting the read / filter / write split (`--timings`);
#   - peak RSS at T = 10² and T = 10⁴ (N = 10³), the scaling in N (10² … 10⁵, one thread,
#     fitted exponent), centralized against distributed time per step (N = 10, 30, 100, 300);
#   - the numpy baseline (bench/baseline.py) against `sisfilt estimate` on a workload it
#     finishes in about a minute, with both outputs compared number by number;
#   - reading and writing without the filter against their floors (`cargo bench --bench io`);
#   - a `perf` profile of the remaining hot spots, when perf is installed.
# Every case runs BENCH_RUNS times (default 3) and the medians are reported.
#
# With a baseline commit (`bench/run.sh f497e7e`), that commit is built too (a worktree in
# $TMPDIR, its build under BENCH_WORK) and every command-line case and the criterion core run with both binaries
# alternately (baseline, then this tree; BENCH_RUNS defaults to 5): BENCHMARKS.md then gives
# each figure as a ratio against the baseline, the best run of each against the best of the
# other, since these machines differ by 2–3× from day to day and only a ratio taken side by
# side says anything; W's estimates of both builds are compared number by number.
#
# Usage: bench/run.sh [BASELINE]  (about 5 minutes on a quiet 2-core machine, plus the builds;
#                                  twice that with a baseline)
# Environment: BENCH_RUNS (3), BENCH_WORK (target/bench), BENCH_OUT (BENCHMARKS.md),
#   BENCH_BASELINE_STEPS (12000; N = 100), BENCH_CRITERION=1 to also run `cargo bench` and
#   list its results, BENCH_KEEP=1 to keep the generated data.
# Needs: cargo, python3 ≥ 3.11; installs GNU time (apt-get, as root) and numpy (in a venv
# under BENCH_WORK, from PyPI) when they are missing.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
WORK=${BENCH_WORK:-$ROOT/target/bench}
BASELINE=${1:-}
if [ -n "$BASELINE" ]; then
    BASELINE_SHA=$(git rev-parse --verify --quiet "$BASELINE^{commit}") || {
        echo "error: baseline '$BASELINE' is not a commit of this repository" >&2
        exit 2
    }
    RUNS=${BENCH_RUNS:-5}
else
    RUNS=${BENCH_RUNS:-3}
fi
OUT=${BENCH_OUT:-$ROOT/BENCHMARKS.md}
BASELINE_N=100
BASELINE_T=${BENCH_BASELINE_STEPS:-12000}
THREADS=$(nproc)
RESULTS=$WORK/results.jsonl
log() { echo "[bench $(date +%H:%M:%S)] $*" >&2; }

# --- tools -------------------------------------------------------------------------------
if [ ! -c /dev/null ]; then
    echo "error: /dev/null is not a character device (something replaced it with a file);" \
        "restore it first: rm /dev/null && mknod -m 666 /dev/null c 1 3" >&2
    exit 1
fi
if [ ! -x /usr/bin/time ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        log "installing GNU time"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq time >/dev/null
    else
        echo "error: /usr/bin/time (GNU time) is missing; install the package 'time'" >&2
        exit 1
    fi
fi
python3 -c 'import sys, tomllib; assert sys.version_info >= (3, 11)' 2>/dev/null || {
    echo "error: python3 ≥ 3.11 is needed (bench/baseline.py reads TOML with tomllib)" >&2
    exit 1
}
mkdir -p "$WORK"
VENV=$WORK/venv
if ! "$VENV/bin/python" -c 'import numpy' 2>/dev/null; then
    log "creating a Python venv with numpy in $VENV"
    python3 -m venv "$VENV"
    "$VENV/bin/pip" install -q numpy
fi
PY=$VENV/bin/python

log "building (release, and the criterion benches)"
cargo build --release --locked -q
cargo bench --locked --bench filter --no-run -q 2>/dev/null
BIN=${CARGO_TARGET_DIR:-$ROOT/target}/release/sisfilt
BASE_BIN=
if [ -n "$BASELINE" ]; then
    # Outside this repository: a package under it would count as a member of its workspace.
    BASE_SRC=${TMPDIR:-/tmp}/sisfilt-bench-baseline
    BASE_TARGET=$WORK/baseline-target
    if [ "$(git -C "$BASE_SRC" rev-parse HEAD 2>/dev/null)" != "$BASELINE_SHA" ]; then
        git worktree remove --force "$BASE_SRC" 2>/dev/null || rm -rf "$BASE_SRC"
        git worktree prune
        git worktree add --detach --force -q "$BASE_SRC" "$BASELINE_SHA"
    fi
    log "building the baseline ${BASELINE_SHA:0:7} (release, and its criterion benches)"
    (cd "$BASE_SRC" && CARGO_TARGET_DIR=$BASE_TARGET cargo build --release --locked -q &&
        CARGO_TARGET_DIR=$BASE_TARGET cargo bench --locked --bench filter --no-run -q 2>/dev/null)
    BASE_BIN=$BASE_TARGET/release/sisfilt
fi

: >"$RESULTS"
python3 - "$WORK/env.json" "$RUNS" "$THREADS" "$BASELINE_N" "$BASELINE_T" \
    "$(cut -d' ' -f1-3 /proc/loadavg)" "$(rustc --version)" \
    "$(git rev-parse --short HEAD 2>/dev/null || echo unknown)$(git diff --quiet 2>/dev/null || echo '+changes')" \
    "${BASELINE_SHA:0:7}" <<'EOF'
import json, sys
path, runs, threads, bn, bt, load, rustc, commit, against = sys.argv[1:]
json.dump(dict(runs=int(runs), threads=int(threads), baseline_n=int(bn), baseline_t=int(bt),
               loadavg=load, rustc=rustc, commit=commit, against=against or None),
          open(path, "w"))
EOF

# How many cores the machine gives right now: two CPU-bound processes against one (2 on an
# idle 2-core machine; less when others are busy, and then thread speed-ups are capped too).
capacity=$(python3 - <<'EOF'
import subprocess, sys, time
spin = "x = 0\nfor i in range(12_000_000): x += i"
def run(k):
    t = time.time()
    procs = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(k)]
    for p in procs: p.wait()
    return time.time() - t
one = min(run(1) for _ in range(2)); two = min(run(2) for _ in range(2))
print(f"{2 * one / two:.2f}")
EOF
)
log "parallel capacity of the machine: ${capacity}× (two CPU-bound processes against one)"
python3 - "$WORK/env.json" "$capacity" <<'EOF'
import json, sys
env = json.load(open(sys.argv[1])); env["capacity"] = float(sys.argv[2])
json.dump(env, open(sys.argv[1], "w"))
EOF

# A config: workload W with N and T replaced. usage: config N T NAME -> $WORK/NAME.toml
config() {
    sed -e "s/^subsystems = .*/subsystems = $1/" -e "s/^steps = .*/steps = $2/" \
        bench/workload.toml >"$WORK/$3.toml"
}
# Simulated data of a config. usage: data N T NAME -> $WORK/NAME/
data() {
    config "$1" "$2" "$3"
    rm -rf "${WORK:?}/$3"
    "$BIN" simulate "$WORK/$3.toml" --out "$WORK/$3" 2>/dev/null
}
# Runs `sisfilt ARGS…` BENCH_RUNS times under /usr/bin/time -v and records each run; with a
# baseline, each run of this tree follows one of the baseline's (recorded as build "baseline").
# usage: measure NAME THREADS ARGS…
measure() {
    local name=$1 threads=$2 build exe
    shift 2
    for _ in $(seq "$RUNS"); do
        for build in ${BASE_BIN:+baseline} current; do
            exe=$BIN
            [ "$build" = baseline ] && exe=$BASE_BIN
            RAYON_NUM_THREADS=$threads /usr/bin/time -v -o "$WORK/time.txt" "$exe" "$@" \
                >/dev/null 2>"$WORK/stderr.txt" || {
                cat "$WORK/stderr.txt" >&2
                exit 1
            }
            python3 bench/report.py record "$RESULTS" "$name" "$threads" "$WORK/time.txt" \
                "$WORK/stderr.txt" "$build"
        done
    done
}

# How far two estimates files differ (report.py compare), into env.json under KEY.
# usage: agree KEY A.csv B.csv
agree() {
    local agreement
    agreement=$("$PY" bench/report.py compare "$2" "$3")
    python3 - "$WORK/env.json" "$1" "$agreement" <<'EOF'
import json, sys
env = json.load(open(sys.argv[1])); env[sys.argv[2]] = json.loads(sys.argv[3])
json.dump(env, open(sys.argv[1], "w"))
EOF
}

# The criterion results of this tree whose names start with PREFIX, into env.json under KEY.
# usage: criterion_into KEY PREFIX
criterion_into() {
    python3 - "$WORK/env.json" "$1" "$2" \
        "$(python3 bench/report.py criterion "${CARGO_TARGET_DIR:-$ROOT/target}")" <<'EOF'
import json, sys
env = json.load(open(sys.argv[1]))
env[sys.argv[2]] = [r for r in json.loads(sys.argv[4]) if r[0].startswith(sys.argv[3])]
json.dump(env, open(sys.argv[1], "w"))
EOF
}

# `estimate` on the data of NAME, to a file, with one thread and with all cores: the cases
# NAME-1thread and NAME-<cores>threads. usage: whole_cli NAME
whole_cli() {
    local threads suffix
    for threads in 1 "$THREADS"; do
        suffix=$([ "$threads" = 1 ] && echo 1thread || echo "${threads}threads")
        log "$1: estimate, $threads thread(s)"
        measure "$1-$suffix" "$threads" estimate --meas "$WORK/$1/measurements.csv" \
            --out "$WORK/$1/estimates.csv" --timings
    done
}

# --- filter core (criterion, no I/O) -----------------------------------------------------
log "filter core: cargo bench --bench filter -- core (one and $THREADS threads), $RUNS times"
# One criterion run of the core group. usage: core_run SOURCE_DIR TARGET_DIR KEY
core_run() {
    rm -rf "$2/criterion/core"
    (cd "$1" && CARGO_TARGET_DIR=$2 cargo bench --locked --bench filter -q -- core \
        --warm-up-time 2 --measurement-time 8 >/dev/null 2>&1)
    python3 - "$WORK/env.json" "$3" "$(python3 bench/report.py criterion "$2")" <<'EOF'
import json, sys
env = json.load(open(sys.argv[1]))
run = {name: [ns, elems] for name, ns, elems in json.loads(sys.argv[3]) if name.startswith("core/")}
env.setdefault(sys.argv[2], []).append(run)
json.dump(env, open(sys.argv[1], "w"))
EOF
}
for _ in $(seq "$RUNS"); do
    if [ -n "$BASE_BIN" ]; then core_run "$BASE_SRC" "$BASE_TARGET" baseline_core_runs; fi
    core_run "$ROOT" "${CARGO_TARGET_DIR:-$ROOT/target}" core_runs
done

# --- workload W --------------------------------------------------------------------------
log "workload W: simulate N = 10000, T = 1000"
data 10000 1000 W
whole_cli W
if [ -n "$BASE_BIN" ]; then
    log "workload W: the estimates of both builds, number by number"
    "$BASE_BIN" estimate --meas "$WORK/W/measurements.csv" --out "$WORK/W/baseline.csv" 2>/dev/null
    agree against_compare "$WORK/W/estimates.csv" "$WORK/W/baseline.csv"
    rm -f "$WORK/W/baseline.csv"
fi
rm -f "$WORK/W/estimates.csv" "$WORK/W/truth.csv"
# Smoothing stores the forward pass: peak RSS against docs/theory.md §9's estimate (`sisfilt check`).
log "workload W: estimate --smooth (distributed smoother)"
measure W-smooth "$THREADS" estimate --meas "$WORK/W/measurements.csv" --smooth \
    --out "$WORK/W/smoothed.csv"
rm -f "$WORK/W/smoothed.csv"
python3 - "$WORK/env.json" "$("$BIN" check "$WORK/W.toml" 2>&1)" <<'EOF'
import json, re, sys
env = json.load(open(sys.argv[1]))
m = re.search(r"smoothing memory for T = \d+: distributed ([\d.]+) (GiB|MiB|KiB)", sys.argv[2])
if m:
    env["smooth_estimate"] = f"{m.group(1)} {m.group(2)}"
    scale = {"GiB": 1 << 30, "MiB": 1 << 20, "KiB": 1 << 10}[m.group(2)]
    env["smooth_estimate_bytes"] = float(m.group(1)) * scale
json.dump(env, open(sys.argv[1], "w"))
EOF

# --- the chain of issues 41 and 42 (N = 10⁴, T = 100): setup share and whole-CLI rows/s ---
log "workload W, T = 100: simulate"
data 10000 100 W100
whole_cli W100
rm -rf "${WORK:?}/W100"
# Reading and writing without the filter, and their floors (issue 42): this tree only.
log "reading and writing: cargo bench --bench io"
rm -rf "${CARGO_TARGET_DIR:-$ROOT/target}/criterion/io"
cargo bench --locked --bench io -q -- --warm-up-time 2 --measurement-time 5 >/dev/null 2>&1
criterion_into io io/

# --- peak memory against T ---------------------------------------------------------------
for steps in 100 10000; do
    log "memory: N = 1000, T = $steps"
    data 1000 "$steps" "mem$steps"
    measure "mem-T$steps" "$THREADS" estimate --meas "$WORK/mem$steps/measurements.csv" \
        --out "$WORK/mem$steps/estimates.csv" --timings
    rm -rf "${WORK:?}/mem$steps"
done

# --- scaling in N ------------------------------------------------------------------------
for n_sub in 100 1000 10000 100000; do
    steps=$((1000000 / n_sub))
    [ "$steps" -lt 20 ] && steps=20
    log "scaling: N = $n_sub, T = $steps"
    data "$n_sub" "$steps" "scale$n_sub"
    measure "scale-N$n_sub" 1 estimate --meas "$WORK/scale$n_sub/measurements.csv" \
        --out /dev/null --timings
    rm -rf "${WORK:?}/scale$n_sub"
done

# --- centralized against distributed -----------------------------------------------------
for n_sub in 10 30 100 300; do
    case $n_sub in
    10) central_steps=500 ;;
    30) central_steps=100 ;;
    100) central_steps=10 ;;
    *) central_steps=3 ;;
    esac
    log "centralized vs distributed: N = $n_sub"
    data "$n_sub" 2000 "cvd$n_sub"
    measure "cvd-distributed-N$n_sub" "$THREADS" estimate \
        --meas "$WORK/cvd$n_sub/measurements.csv" --out /dev/null --timings
    data "$n_sub" "$central_steps" "cvdc$n_sub"
    measure "cvd-centralized-N$n_sub" "$THREADS" estimate --filter centralized \
        --meas "$WORK/cvdc$n_sub/measurements.csv" --out /dev/null --timings
    rm -rf "${WORK:?}/cvd$n_sub" "${WORK:?}/cvdc$n_sub"
done

# --- numpy baseline ----------------------------------------------------------------------
log "baseline: N = $BASELINE_N, T = $BASELINE_T"
data "$BASELINE_N" "$BASELINE_T" base
B=$WORK/base
measure baseline-sisfilt "$THREADS" estimate --meas "$B/measurements.csv" --out "$B/sisfilt.csv"
log "baseline: numpy (one run; about a minute)"
/usr/bin/time -v -o "$WORK/time.txt" "$PY" bench/baseline.py "$B.toml" "$B/measurements.csv" \
    "$B/inputs.csv" "$B/numpy.csv" 2>"$WORK/stderr.txt"
python3 bench/report.py record "$RESULTS" baseline-python 1 "$WORK/time.txt" "$WORK/stderr.txt"
agree baseline_compare "$B/sisfilt.csv" "$B/numpy.csv"
rm -rf "${WORK:?}/base"

# --- profile -----------------------------------------------------------------------------
if command -v perf >/dev/null && perf record -o /dev/null true >/dev/null 2>&1; then
    log "profile: perf record, W with one thread"
    data 10000 200 prof
    RAYON_NUM_THREADS=1 perf record -q -o "$WORK/perf.data" "$BIN" estimate \
        --meas "$WORK/prof/measurements.csv" --out "$WORK/prof/estimates.csv" 2>/dev/null
    perf report -i "$WORK/perf.data" --no-children --percent-limit 1.5 --stdio 2>/dev/null |
        grep -E '^ +[0-9]' | sed -E 's/ +\[\.\] / /; s/^ +//' | cut -c1-110 | head -25 >"$WORK/profile.txt"
    rm -rf "${WORK:?}/prof" "$WORK/perf.data"
else
    log "profile: perf is not available, skipped"
    rm -f "$WORK/profile.txt"
fi

# --- criterion (optional) ----------------------------------------------------------------
if [ "${BENCH_CRITERION:-0}" = 1 ]; then
    log "criterion: cargo bench --bench filter"
    cargo bench --locked --bench filter -q >/dev/null 2>&1
    criterion_into criterion ""
fi

[ "${BENCH_KEEP:-0}" = 1 ] || rm -rf "${WORK:?}/W"
python3 bench/report.py write "$RESULTS" "$OUT"
log "wrote $OUT"
