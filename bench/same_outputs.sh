#!/usr/bin/env bash
# Before/after: runs every command on the shipped configs with the binary of a baseline commit
# and with the working tree's, and compares what they write byte for byte: the files, standard
# output, standard error and the exit code. For refactors that must change no output.
#
# Usage: bench/same_outputs.sh [BASE]   (BASE: a commit, default f497e7e; about 10 minutes
#   with the two release builds)
# Environment: SAME_WORK (target/same-outputs), SAME_KEEP=1 to keep the outputs.
# Clock readings (evaluate's wall_time_s, total_wall_time_s and its time column) are the only
# parts left out of the comparison.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
BASE=${1:-f497e7e}
WORK=${SAME_WORK:-$ROOT/target/same-outputs}
log() { echo "[same-outputs $(date +%H:%M:%S)] $*" >&2; }

rm -rf "$WORK"
mkdir -p "$WORK/bin"
log "building $BASE"
git worktree add --detach -f "$WORK/base-src" "$BASE" >/dev/null 2>&1
trap 'git worktree remove --force "$WORK/base-src" >/dev/null 2>&1 || true' EXIT
# One target folder, so that the dependencies are built once. Cargo takes both trees for the
# same package and judges freshness by the files of the last build, so sisfilt itself is
# cleaned before each build.
cargo clean --release -p sisfilt -q
(cd "$WORK/base-src" && CARGO_TARGET_DIR=$ROOT/target cargo build --release --locked -q)
cp target/release/sisfilt "$WORK/bin/base"
log "building the working tree"
cargo clean --release -p sisfilt -q
cargo build --release --locked -q
cp target/release/sisfilt "$WORK/bin/new"
if cmp -s "$WORK/bin/base" "$WORK/bin/new"; then
    log "note: the two binaries are the same file"
fi

# The cases: one per line, a name and the arguments. `@D` is the case's folder of inputs.
cases() {
    for cfg in platoon paper heat_rod; do
        echo "check-$cfg check configs/$cfg.toml"
        echo "sim-$cfg simulate configs/$cfg.toml --out @O/sim"
        echo "sim-$cfg-known simulate configs/$cfg.toml --mark-missing --seed 5 --out @O/sim"
        local sim="@D/sim-$cfg" known="@D/known-$cfg"
        local meas="--meas $sim/measurements.csv --truth $sim/truth.csv"
        local kmeas="--meas $known/measurements.csv --truth $known/truth.csv"
        for filter in distributed joint centralized; do
            for update in linear mixture; do
                local run="estimate --filter $filter --update $update $meas"
                echo "est-$cfg-$filter-$update-csv $run --out @O/est.csv"
                echo "est-$cfg-$filter-$update-json $run --out @O/est.json"
                echo "est-$cfg-$filter-$update-pred $run --predicted --out @O/est.csv"
                echo "est-$cfg-$filter-$update-smooth $run --smooth --out @O/est.json"
            done
            echo "est-$cfg-$filter-known estimate --filter $filter --dropouts known $kmeas --out @O/est.json"
            echo "est-$cfg-$filter-known-smooth estimate --filter $filter --dropouts known --smooth $kmeas --out @O/est.csv"
        done
        echo "est-$cfg-paper estimate --paper $meas --out @O/est.json"
        echo "est-$cfg-paper-lifted estimate --second-moment lifted --solver transfer $meas --out @O/est.csv"
        echo "est-$cfg-joint-opts estimate --filter joint --band 1 --band-tol 1e-6 --loading 1e-8 --second-moment local $meas --out @O/est.json"
        echo "est-$cfg-stdout estimate --config configs/$cfg.toml --meas $sim/measurements.csv"
        echo "eval-$cfg evaluate configs/$cfg.toml --runs 3 --smooth --out @O/eval.json"
        echo "eval-$cfg-sweep evaluate configs/$cfg.toml --runs 2 --sweep-p 0.5,0.9 --true-p 0.7 --filters distributed,joint-mixture,centralized --out @O/eval.json"
        echo "plot-$cfg-series plot series --estimates $sim/est.csv --truth $sim/truth.csv --meas $sim/measurements.csv --out @O/series.svg"
        echo "plot-$cfg-heatmap plot heatmap --estimates $sim/est.csv --truth $sim/truth.csv --out @O/heat.svg"
        echo "plot-$cfg-eval plot evaluate @D/eval-$cfg.json --out @O/eval.svg"
    done
    # Option combinations that are refused, and their messages.
    local sim="@D/sim-platoon" m="--meas @D/sim-platoon/measurements.csv"
    echo "bad-mixture-known estimate $m --update mixture --dropouts known"
    echo "bad-band-distributed estimate $m --band 3"
    echo "bad-band-tol-centralized estimate $m --filter centralized --band-tol 1e-3"
    echo "bad-loading-distributed estimate $m --loading 1e-3"
    echo "bad-moment-band estimate $m --second-moment band"
    echo "bad-moment-paper-joint estimate $m --filter joint --second-moment paper"
    echo "bad-max-memory estimate $m --max-memory 1G"
    echo "bad-smooth-predicted estimate $m --smooth --predicted"
    echo "bad-band-tol-negative estimate $m --filter joint --band-tol=-1"
    echo "bad-loading-nan estimate $m --filter joint --loading nan"
    echo "bad-max-lifted estimate $m --filter centralized --max-lifted 10"
    echo "bad-max-memory-small estimate $m --smooth --max-memory 1K"
    echo "bad-eval-loading evaluate configs/platoon.toml --runs 1 --loading=-1"
    echo "bad-eval-burn-in evaluate configs/platoon.toml --runs 1 --burn-in 100000"
    echo "bad-eval-runs evaluate configs/platoon.toml --runs 0"
    echo "bad-eval-true-p evaluate configs/platoon.toml --runs 1 --true-p 1.5"
    echo "bad-eval-sweep evaluate configs/platoon.toml --runs 1 --sweep-p 0.5,1.5"
    echo "bad-smooth-memory estimate $m --smooth --max-memory 10K"
    echo "bad-predicted-one-step estimate $m --predicted --truth $sim/truth.csv --filter joint"
}

# The shared inputs, made once by the baseline binary.
DATA=$WORK/data
mkdir -p "$DATA"
for cfg in platoon paper heat_rod; do
    "$WORK/bin/base" -q simulate "configs/$cfg.toml" --out "$DATA/sim-$cfg"
    "$WORK/bin/base" -q simulate "configs/$cfg.toml" --mark-missing --out "$DATA/known-$cfg"
    "$WORK/bin/base" -q estimate --meas "$DATA/sim-$cfg/measurements.csv" --out "$DATA/sim-$cfg/est.csv"
    "$WORK/bin/base" -q evaluate "configs/$cfg.toml" --runs 2 --out "$DATA/eval-$cfg.json" >/dev/null
done

# Leaves the clock readings out of an evaluate JSON (wall_time_s, total_wall_time_s) and
# of its table (the column under `time (s)`).
strip_clock() {
    python3 - "$1" <<'PY'
import re, sys
text = open(sys.argv[1]).read()
text = re.sub(r'("(?:total_)?wall_time_s": )[-0-9.e+]+', r'\1T', text)
out, span = [], None
for line in text.split("\n"):
    if "time (s)" in line:
        end = line.index("time (s)") + len("time (s)")
        start = end - 10
        span = (start, end)
    elif line == "":
        span = None
    elif span and len(line) >= span[1]:
        line = line[: span[0]] + " " * (span[1] - span[0]) + line[span[1]:]
    out.append(line)
sys.stdout.write("\n".join(out))
PY
}

failed=0
count=0
while read -r name args; do
    count=$((count + 1))
    for side in base new; do
        out=$WORK/out/$side/$name
        mkdir -p "$out"
        run_args=${args//@D/$DATA}
        run_args=${run_args//@O/$out}
        set +e
        # shellcheck disable=SC2086
        "$WORK/bin/$side" $run_args >"$out/stdout" 2>"$out/stderr"
        echo $? >"$out/exit"
        set -e
        sed -i -e "s#$out#@O#g" -e "s#$DATA#@D#g" "$out/stdout" "$out/stderr"
        if [[ $name == eval-* ]]; then
            for f in "$out/stdout" "$out"/*.json; do
                [[ -f $f ]] || continue
                strip_clock "$f" >"$f.clockless" && mv "$f.clockless" "$f"
            done
        fi
    done
    if ! diff -r "$WORK/out/base/$name" "$WORK/out/new/$name" >"$WORK/out/$name.diff" 2>&1; then
        failed=$((failed + 1))
        log "DIFFERS: $name ($args)"
        head -n 20 "$WORK/out/$name.diff" >&2
    fi
done < <(cases)

log "$count cases, $failed differ"
[[ ${SAME_KEEP:-0} == 1 ]] || rm -rf "$WORK/out" "$WORK/data"
[[ $failed == 0 ]]
