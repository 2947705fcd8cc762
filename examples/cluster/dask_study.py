"""One `evaluate` study in shards on a Dask cluster, then the merge (README, "Beyond one
machine"). Run from the repository: python examples/cluster/dask_study.py [SCHEDULER]

Without an address it starts a cluster of two worker processes on this machine; with one
(e.g. tcp://scheduler:8786) it uses that cluster, whose workers need the sisfilt package and
the config at the same path. Writes study.json, which `sisfilt plot evaluate` draws."""

import json
import sys

from dask.distributed import Client, LocalCluster

import sisfilt

CONFIG = "configs/platoon.toml"
RUNS, SHARDS = 400, 8


def shard(k):
    """Shard k of the study, on a worker: a dict of sums, small to send back."""
    return sisfilt.evaluate(sisfilt.Model.from_toml(CONFIG), RUNS, shard=(k, SHARDS))


def main():
    if len(sys.argv) > 1:
        client = Client(sys.argv[1])
    else:
        client = Client(LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None))
    with client:
        parts = client.gather(client.map(shard, range(SHARDS)))
    study = sisfilt.evaluate_merge(parts)
    with open("study.json", "w") as f:
        json.dump(study, f, indent=1)
    for f in study["filters"]:
        if f["accuracy"] is not None:
            ratio = f["rmse_ratio"] if f["rmse_ratio"] is not None else float("nan")
            print(f"{f['name']:<20} RMSE {f['accuracy']['rmse_overall']:.4e}  / central {ratio:.4f}")


if __name__ == "__main__":
    main()
