#!/bin/bash
# A Slurm job array: 64 shards of one `sisfilt evaluate` study, task K running shard K/64.
# From the repository (sisfilt on the PATH of the compute nodes, e.g. `cargo install --path .`):
#
#   job=$(sbatch --parsable examples/cluster/slurm-array.sh)
#   sbatch --dependency=afterok:$job --wrap 'sisfilt evaluate-merge parts/part-*.json --out study.json'
#
#SBATCH --job-name=sisfilt-study
#SBATCH --array=0-63
#SBATCH --cpus-per-task=2
#SBATCH --time=01:00:00
#SBATCH --output=slurm-%A_%a.out
set -euo pipefail
export RAYON_NUM_THREADS=${SLURM_CPUS_PER_TASK:-2}
mkdir -p parts
sisfilt evaluate configs/platoon.toml --runs 6400 --smooth \
    --shard "$SLURM_ARRAY_TASK_ID/64" --out "parts/part-$SLURM_ARRAY_TASK_ID.json"
