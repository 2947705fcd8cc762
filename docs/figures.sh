#!/usr/bin/env bash
# Regenerates the pictures of README.md (docs/*.svg) with the worked example's commands.
# Usage: bash docs/figures.sh [SISFILT]   (default: target/release/sisfilt, built when missing)
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
sisfilt=${1:-$repo/target/release/sisfilt}
[[ -x $sisfilt ]] || (cd "$repo" && cargo build --release --locked)
sisfilt=$(cd "$(dirname "$sisfilt")" && pwd)/$(basename "$sisfilt")
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cd "$work"
ln -s "$repo/configs" configs

# The platoon: one run, its estimates, one car's gap error against time.
"$sisfilt" simulate configs/platoon.toml --out run
"$sisfilt" estimate --meas run/measurements.csv --truth run/truth.csv --out run/estimates.csv
"$sisfilt" plot series --estimates run/estimates.csv --truth run/truth.csv \
    --meas run/measurements.csv --subsystem 5 --state 1 --out run/series.svg
# The heat rod: how the (normalised) error spreads along 50 segments.
"$sisfilt" simulate configs/heat_rod.toml --out rod
"$sisfilt" -q estimate --meas rod/measurements.csv --out rod/estimates.csv
"$sisfilt" plot heatmap --estimates rod/estimates.csv --truth rod/truth.csv --out rod/heatmap.svg
# Detecting lost measurements: the rod's joint filter with the mixture update, each reading
# coloured by the probability the filter gave it of having arrived.
"$sisfilt" -q estimate --meas rod/measurements.csv --filter joint --update mixture --out rod/mixture.csv
"$sisfilt" plot series --estimates rod/mixture.csv --truth rod/truth.csv \
    --meas rod/measurements.csv --subsystem 10 --state 1 --out rod/mixture.svg
# Monte Carlo: nine filters on 200 platoon runs, then RMSE and ANEES against p.
"$sisfilt" -q evaluate configs/platoon.toml --runs 200 --out run/evaluate.json > /dev/null
"$sisfilt" plot evaluate --input run/evaluate.json --out run/evaluate.svg
"$sisfilt" -q evaluate configs/platoon.toml --runs 100 --sweep-p 0.3,0.5,0.7,0.85,1 \
    --out run/sweep.json > /dev/null
"$sisfilt" plot evaluate --input run/sweep.json --out run/sweep.svg

# The paper's setting (Q = 0): the two-step filter's NEES collapses, the joint filter's holds.
"$sisfilt" -q evaluate configs/paper.toml --runs 300 --filters distributed,joint,centralized \
    --out run/paper_eval.json > /dev/null
"$sisfilt" plot evaluate --input run/paper_eval.json --out run/paper_nees.svg
# Smoothing: the joint filter and its smoother on the same platoon run.
"$sisfilt" -q estimate --meas run/measurements.csv --filter joint --out run/joint.csv
"$sisfilt" -q estimate --meas run/measurements.csv --filter joint --smooth --out run/joint_smooth.csv
"$sisfilt" plot series --estimates run/joint.csv --smoothed run/joint_smooth.csv \
    --truth run/truth.csv --subsystem 5 --state 1 --out run/smoothed.svg

# The README's evaluate tables: 500 runs of each shipped config, each table (and its notes)
# written between its markers.
for cfg in platoon heat_rod paper; do
    "$sisfilt" -q evaluate "configs/$cfg.toml" --runs 500 > "run/eval_$cfg.txt"
    awk '/^filter /{on=1} on==1 && /^$/{on=2} on==1 || /^note: /{print}' "run/eval_$cfg.txt" \
        > "run/table_$cfg.txt"
done
awk -v dir=run '
    /^<!-- evaluate configs\/[a-z_]+\.toml -->$/ {
        print
        name = $3
        sub(/^configs\//, "", name)
        sub(/\.toml$/, "", name)
        print "```text"
        while ((getline line < (dir "/table_" name ".txt")) > 0) print line
        print "```"
        skip = 1
        next
    }
    /^<!-- end evaluate -->$/ { skip = 0 }
    !skip { print }
' "$repo/README.md" > README.new
cat README.new > "$repo/README.md"

cp run/series.svg rod/heatmap.svg rod/mixture.svg run/evaluate.svg run/sweep.svg run/paper_nees.svg \
    run/smoothed.svg "$repo/docs/"
echo "wrote README.md's evaluate tables and docs/series.svg docs/heatmap.svg docs/mixture.svg docs/evaluate.svg docs/sweep.svg docs/paper_nees.svg docs/smoothed.svg"
