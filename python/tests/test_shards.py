"""A study in shards: `evaluate(…, shard=(K, M))` and `evaluate_merge`, against one `evaluate`
of the whole study and the command line's parts, and the README's Dask recipe on a real
`dask.distributed` cluster of two worker processes."""

import json
import math

import pytest

import sisfilt
from conftest import config

RUNS = 8


def model():
    return sisfilt.Model.from_toml(config("platoon.toml")).with_(steps=25)


def assert_close(a, b, rel=1e-12, at=""):
    """Equal keys, strings and integers, floats within `rel`; clock readings aside."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), at
        for k in a:
            if "time" not in k:
                assert_close(a[k], b[k], rel, f"{at}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), at
        for k, (x, y) in enumerate(zip(a, b)):
            assert_close(x, y, rel, f"{at}[{k}]")
    elif isinstance(a, float) or isinstance(b, float):
        assert math.isclose(a, b, rel_tol=rel, abs_tol=0.0) or a == b, (at, a, b)
    else:
        assert a == b, (at, a, b)


@pytest.mark.parametrize("kwargs", [{}, {"sweep_p": [0.6, 0.9], "smooth": True}])
def test_shards_merge_to_the_whole_study(kwargs):
    parts = [sisfilt.evaluate(model(), RUNS, shard=(k, 4), **kwargs) for k in range(4)]
    assert [p["runs"] for p in parts] == [[0, 2], [2, 4], [4, 6], [6, 8]]
    merged = sisfilt.evaluate_merge(parts[::-1])
    assert_close(merged, sisfilt.evaluate(model(), RUNS, **kwargs))


def test_a_part_equals_the_command_lines_part(cli, tmp_path):
    cli("evaluate", config("platoon.toml"), "--runs", RUNS, "--set", "steps=25", "--shard",
        "1/4", "--out", tmp_path / "part.json", cwd=tmp_path)
    doc = json.loads((tmp_path / "part.json").read_text())
    part = sisfilt.evaluate(model(), RUNS, shard=(1, 4))
    assert_close(part, doc, rel=0.0)
    # The parts of the command line merge in Python, and the other way round.
    parts = [doc] + [sisfilt.evaluate(model(), RUNS, shard=(k, 4)) for k in (0, 2, 3)]
    assert_close(sisfilt.evaluate_merge(parts), sisfilt.evaluate(model(), RUNS))


def test_parts_that_are_not_one_study_raise_value_error():
    parts = [sisfilt.evaluate(model(), RUNS, shard=(k, 3)) for k in range(3)]
    with pytest.raises(ValueError, match=r"missing from the study: shard 1/3 "):
        sisfilt.evaluate_merge([parts[0], parts[2]])
    with pytest.raises(ValueError, match=r"parts\[2\] and parts\[1\] are both shard 1/3"):
        sisfilt.evaluate_merge([parts[0], parts[1], parts[1], parts[2]])
    other = sisfilt.evaluate(model().with_(p=0.5), RUNS, shard=(1, 3))
    with pytest.raises(ValueError, match=r"parts\[1\]: .*the models differ"):
        sisfilt.evaluate_merge([parts[0], other, parts[2]])
    with pytest.raises(ValueError, match=r"parts\[0\]: not a part"):
        sisfilt.evaluate_merge([{"filters": []}])
    with pytest.raises(ValueError, match="no parts"):
        sisfilt.evaluate_merge([])
    with pytest.raises(ValueError, match="shard 3/3"):
        sisfilt.evaluate(model(), RUNS, shard=(3, 3))
    with pytest.raises(ValueError, match="at most one shard per run"):
        sisfilt.evaluate(model(), 2, shard=(0, 3))


def test_the_dask_recipe_on_a_local_cluster_of_two_worker_processes():
    """The README's recipe: `client.map` over the shards on workers in other processes, then
    the merge, equal to one run of the whole study."""
    distributed = pytest.importorskip(
        "dask.distributed", reason="dask[distributed] could not be installed here"
    )
    path = str(config("platoon.toml"))

    # Defined here, so that Dask ships it to the workers by value.
    def shard(k, shards):
        m = sisfilt.Model.from_toml(path).with_(steps=25)
        return sisfilt.evaluate(m, RUNS, shard=(k, shards))

    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster, distributed.Client(cluster) as client:
        parts = client.gather(client.map(shard, range(4), shards=4))
        pids = client.run(lambda: __import__("os").getpid())
    assert len(set(pids.values())) == 2
    assert_close(sisfilt.evaluate_merge(parts), sisfilt.evaluate(model(), RUNS))


def test_the_readmes_dask_script_as_written(tmp_path, monkeypatch):
    """examples/cluster/dask_study.py, run as a user runs it (from a folder holding
    configs/platoon.toml): its study.json equals one run of the whole study."""
    pytest.importorskip("dask.distributed", reason="dask[distributed] could not be installed here")
    import shutil
    import subprocess
    import sys

    (tmp_path / "configs").mkdir()
    shutil.copy(config("platoon.toml"), tmp_path / "configs")
    script = config("platoon.toml").parents[1] / "examples" / "cluster" / "dask_study.py"
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert "centralized          RMSE" in run.stdout
    study = json.loads((tmp_path / "study.json").read_text())
    monkeypatch.chdir(tmp_path)
    whole = sisfilt.evaluate(sisfilt.Model.from_toml("configs/platoon.toml"), 400)
    assert_close(study, whole)
