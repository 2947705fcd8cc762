#!/usr/bin/env python3
"""A study in shards against one run of it (issue 39), for BENCHMARKS.md.

    bench/shards.py [--bin target/release/sisfilt] [--runs 3] [--out bench/shards.md]

The study: `sisfilt evaluate configs/platoon.toml --runs 400 --smooth` (N = 20, T = 200, nine
filters and six smoothers). Measured, alternating, best of `--runs`:

1. one `evaluate` of the whole study, default threads (every core);
2. four shards (`--shard K/4`) started side by side as separate processes, each on one thread
   (`RAYON_NUM_THREADS=1`), from the first start to the last end, then `evaluate-merge`;
3. the same with the default threads in each shard;
4. `evaluate-merge` alone on the four parts, as a share of the whole study's time.

The merged JSON is compared with the whole study's (largest relative gap, clock readings aside).
"""
import argparse
import json
import os
import platform
import subprocess
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
STUDY = ["evaluate", os.path.join(ROOT, "configs", "platoon.toml"), "--runs", "400", "--smooth"]


def timed(commands, env=None):
    """Starts every command at once; seconds until the last ends."""
    start = time.perf_counter()
    procs = [subprocess.Popen(c, env=env, stdout=subprocess.DEVNULL) for c in commands]
    for p in procs:
        assert p.wait() == 0
    return time.perf_counter() - start


def gap(a, b):
    if isinstance(a, dict):
        return max([gap(a[k], b[k]) for k in a if "time" not in k] or [0.0])
    if isinstance(a, list):
        return max([gap(x, y) for x, y in zip(a, b)] or [0.0])
    if isinstance(a, float) and isinstance(b, float):
        return abs(a - b) / max(abs(a), abs(b), 1e-300)
    assert a == b
    return 0.0


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bin", default=os.path.join(ROOT, "target", "release", "sisfilt"))
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "shards.md"))
    args = parser.parse_args()
    work = tempfile.mkdtemp(prefix="sisfilt-shards-")
    whole_json = os.path.join(work, "whole.json")
    parts = [os.path.join(work, f"part-{k}.json") for k in range(4)]
    merged_json = os.path.join(work, "merged.json")
    shard = lambda k: [args.bin, "-q", *STUDY, "--shard", f"{k}/4", "--out", parts[k]]
    merge = [args.bin, "-q", "evaluate-merge", *parts, "--out", merged_json]
    one_thread = dict(os.environ, RAYON_NUM_THREADS="1")
    best = {"whole": [], "shards1": [], "shardsN": [], "merge": []}
    for _ in range(args.runs):
        best["whole"].append(timed([[args.bin, "-q", *STUDY, "--out", whole_json]]))
        best["shards1"].append(timed([shard(k) for k in range(4)], one_thread))
        best["merge"].append(min(timed([merge]) for _ in range(5)))
        best["shardsN"].append(timed([shard(k) for k in range(4)]))
    t = {k: min(v) for k, v in best.items()}
    with open(whole_json) as f, open(merged_json) as g:
        worst = gap(json.load(f), json.load(g))
    size = sum(os.path.getsize(p) for p in parts) / 4 / 1024
    lines = [
        f"`bench/shards.py` (sisfilt {subprocess.run([args.bin, '--version'], capture_output=True, text=True).stdout.split()[-1]}, "
        f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores): "
        f"`{' '.join(['sisfilt', *STUDY[:1], 'configs/platoon.toml', *STUDY[2:]])}`; best of {args.runs} alternating runs.",
        "",
        "| | wall time | ratio to one run |",
        "|---|---|---|",
        f"| one `evaluate` of the whole study, default threads | {t['whole']:.2f} s | 1 |",
        f"| four shards side by side, one thread each, then the merge | {t['shards1'] + t['merge']:.2f} s | {(t['shards1'] + t['merge']) / t['whole']:.3f}× |",
        f"| four shards side by side, default threads each, then the merge | {t['shardsN'] + t['merge']:.2f} s | {(t['shardsN'] + t['merge']) / t['whole']:.3f}× |",
        f"| `evaluate-merge` of the four parts alone | {t['merge'] * 1000:.1f} ms | **{100 * t['merge'] / t['whole']:.2f} %** of the study |",
        "",
        f"A part is {size:.0f} KB. The merged JSON against the whole study's: largest relative gap {worst:.1e} (the clock readings aside).",
    ]
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
