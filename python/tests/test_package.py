"""The package against the command line built from the same library: the same numbers for
the same config, data and options (every filter and update, smoothing, gaps), and errors as
Python exceptions."""

import json
import threading
import time

import numpy as np
import pytest

import sisfilt
from conftest import config, read_steps


@pytest.fixture(scope="module")
def platoon_run(cli, tmp_path_factory):
    """The platoon simulated by the command line for 40 steps, with gaps written into its
    measurements (cells where (t + i) % 7 == 0 lose y1)."""
    d = tmp_path_factory.mktemp("platoon")
    cli("simulate", config("platoon.toml"), "--out", d, "--steps", 40, cwd=d)
    lines = (d / "measurements.csv").read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        if (int(cells[0]) + int(cells[1])) % 7 == 0:
            cells[2] = ""
        out.append(",".join(cells))
    (d / "gaps.csv").write_text("\n".join(out) + "\n")
    return d


def arrays(d, name, n_sub=20):
    _, y = read_steps(d / name, n_sub)
    _, u = read_steps(d / "inputs.csv", n_sub)
    return y, u


@pytest.mark.parametrize("options", [
    [],
    ["--filter", "joint"],
    ["--filter", "centralized"],
    ["--update", "mixture"],
    ["--filter", "joint", "--update", "mixture"],
    ["--filter", "centralized", "--update", "mixture"],
    ["--smooth"],
    ["--filter", "joint", "--smooth"],
    ["--predicted"],
    ["--paper", "--solver", "banded"],
    ["--dropouts", "known", "--filter", "joint"],
])
@pytest.mark.parametrize("meas", ["measurements.csv", "gaps.csv"])
def test_estimate_equals_the_command_line(cli, platoon_run, options, meas):
    d = platoon_run
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    if "--dropouts" in options and meas == "measurements.csv":
        pytest.skip("known dropouts read lost elements as empty cells: the gaps file")
    out = cli("estimate", "--config", config("platoon.toml"), "--meas", meas, "--inputs",
              "inputs.csv", "--nis", "--out", "est.csv", *options, cwd=d)
    header, rows = read_steps(d / "est.csv", 20)
    y, u = arrays(d, meas)
    kwargs = {}
    for flag, value in zip(options[::1], options[1::1]):
        if flag.startswith("--") and not value.startswith("--"):
            kwargs[flag[2:].replace("-", "_")] = value
    for flag in ("--smooth", "--predicted", "--paper"):
        if flag in options:
            kwargs[flag[2:]] = True
    est = sisfilt.estimate(model, y, u, **kwargs)
    n = 2
    assert header[0] == ("t_given" if "--predicted" in options else "t")
    np.testing.assert_array_equal(est.x, rows[:, :, :n])
    p_cols = [(r, c) for r in range(n) for c in range(r, n)]
    for k, (r, c) in enumerate(p_cols):
        np.testing.assert_array_equal(est.P[:, :, r, c], rows[:, :, n + k])
        np.testing.assert_array_equal(est.P[:, :, c, r], rows[:, :, n + k])
    if "arrival" in header:
        np.testing.assert_array_equal(est.arrival, rows[:, :, header.index("arrival") - 2])
    else:
        assert est.arrival is None
    np.testing.assert_array_equal(est.nis, rows[:, :, header.index("nis") - 2])
    frame = est.to_pandas()
    assert list(frame.columns) == header
    np.testing.assert_array_equal(frame.to_numpy(), np.loadtxt(d / "est.csv", delimiter=",",
                                                                skiprows=1, ndmin=2))


def test_loglik_and_innovations_equal_the_command_lines_json(cli, platoon_run):
    d = platoon_run
    out = cli("estimate", "--config", config("platoon.toml"), "--meas", "gaps.csv", "--inputs",
              "inputs.csv", "--filter", "joint", "--update", "mixture", "--format", "json",
              cwd=d)
    doc = json.loads(out.stdout)
    y, u = arrays(d, "gaps.csv")
    est = sisfilt.estimate(sisfilt.Model.from_toml(config("platoon.toml")), y, u,
                           filter="joint", update="mixture")
    assert est.loglik == doc["loglik"]
    assert est.innovations == doc["innovations"]
    # The run's phases, the innovation check among them, within the whole run.
    phases = [est.timings[k] for k in ("read", "filter", "check", "write")]
    assert all(s >= 0 for s in phases) and sum(phases) <= est.timings["run"]


def test_hold_out_equals_the_command_lines_json(cli, platoon_run):
    d = platoon_run
    out = cli("estimate", "--config", config("platoon.toml"), "--meas", "gaps.csv", "--inputs",
              "inputs.csv", "--filter", "joint", "--smooth", "--hold-out", "0.2", "--seed", "4",
              "--format", "json", cwd=d)
    doc = json.loads(out.stdout)
    y, u = arrays(d, "gaps.csv")
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    est = sisfilt.estimate(model, y, u, filter="joint", smooth=True, hold_out=0.2, seed=4)
    assert est.held_out == doc["held_out"] and est.held_out["readings"] > 0
    assert sisfilt.estimate(model, y, u).held_out is None
    with pytest.raises(ValueError, match=r"hold_out = 1\.5: expected a share above 0 and below 1"):
        sisfilt.estimate(model, y, u, hold_out=1.5)
    with pytest.raises(ValueError, match="hold_out and predicted exclude each other"):
        sisfilt.estimate(model, y, u, hold_out=0.1, predicted=True)


def test_simulate_equals_the_command_line(cli, tmp_path):
    cli("simulate", config("heat_rod.toml"), "--out", tmp_path, "--steps", 30, "--seed", 5,
        cwd=tmp_path)
    model = sisfilt.Model.from_toml(config("heat_rod.toml"))
    sim = sisfilt.simulate(model, seed=5, steps=30)
    _, truth = read_steps(tmp_path / "truth.csv", 50)
    _, y = read_steps(tmp_path / "measurements.csv", 50)
    _, u = read_steps(tmp_path / "inputs.csv", 50)
    np.testing.assert_array_equal(sim["x"], truth[:, :, :2])
    np.testing.assert_array_equal(sim["gamma"], truth[:, :, 2] == 1)
    np.testing.assert_array_equal(sim["y"], y)
    np.testing.assert_array_equal(sim["u"], u)
    assert sim["x"].shape == (30, 50, 2) and sim["gamma"].dtype == bool


def test_simulate_refuses_arrays_above_max_memory_before_allocating():
    """10¹² steps would be 10¹⁶ bytes: refused at once (it ran until the memory ran out);
    the limit is the arrays' size, T·N·(8(n + q + m) + 1) bytes."""
    model = sisfilt.Model.from_toml(config("heat_rod.toml"))
    with pytest.raises(ValueError, match=r"steps = 1000000000000: .* above max_memory = 8\.0 GiB"):
        sisfilt.simulate(model, steps=10**12)
    # heat_rod: N = 50, n = 2, q = 1, m = 1: 50 · 33 = 1650 bytes a step.
    sisfilt.simulate(model, steps=30, max_memory=30 * 1650)
    with pytest.raises(ValueError, match="raise max_memory"):
        sisfilt.simulate(model, steps=30, max_memory=30 * 1650 - 1)


def test_filters_above_max_memory_raise_value_error_before_allocating():
    """A raised max_lifted or a wide band on a long chain: the filter's arrays are weighed
    against max_memory before they are allocated (the process aborted), in Filter, fit,
    estimate and evaluate (where the filter is skipped with a note)."""
    text = open(config("paper.toml")).read().replace("subsystems = 6", "subsystems = 100000")
    model = sisfilt.Model.from_toml_str(text)
    with pytest.raises(ValueError, match=r"the joint filter \(band k = 99999.* above max_memory 8\.0 GiB"):
        sisfilt.Filter(model, filter="joint", band=99999)
    with pytest.raises(ValueError, match=r"the centralized filter \(lifted state of size N·n = 200000\)"):
        sisfilt.Filter(model, filter="centralized", max_lifted=10**6)
    with pytest.raises(ValueError, match=r"the joint filter \(band k = 99999"):
        sisfilt.fit(model, np.zeros((2, 100000, 1)), band=99999)
    platoon = sisfilt.Model.from_toml(config("platoon.toml"))
    y = np.zeros((3, 20, 2))
    with pytest.raises(ValueError, match="raise max_memory"):
        sisfilt.estimate(platoon, y, filter="centralized", max_memory=200 * 1024)
    study = sisfilt.evaluate(platoon, 1, filters=["centralized", "distributed"], max_memory=200 * 1024)
    rows = {f["name"]: f for f in study["filters"]}
    assert "above max_memory 200.0 KiB" in rows["centralized"]["skipped"]
    assert rows["distributed"]["skipped"] is None


def test_fit_equals_the_command_lines_json(cli, platoon_run):
    d = platoon_run
    out = cli("fit", "--config", config("platoon.toml"), "--meas", "gaps.csv", "--inputs",
              "inputs.csv", "--params", "p,M", "--format", "json", "--out", "fitted.toml",
              cwd=d)
    doc = json.loads(out.stdout)
    y, u = arrays(d, "gaps.csv")
    report, fitted = sisfilt.fit(sisfilt.Model.from_toml(config("platoon.toml")), y, u,
                                 params=["p", "M"])
    for key in ["loglik_start", "loglik", "iterations", "correlation", "filter", "dropouts"]:
        assert report[key] == doc[key], key
    assert report["parameters"] == doc["parameters"]
    assert fitted.to_toml() == sisfilt.Model.from_toml(d / "fitted.toml").to_toml()


def test_fit_of_each_subsystems_noise_equals_the_command_lines(cli, platoon_run):
    d = platoon_run
    out = cli("fit", "--config", config("platoon.toml"), "--meas", "gaps.csv", "--inputs",
              "inputs.csv", "--params", "Q[i],M", "--dropouts", "known", "--format", "json",
              "--out", "each.toml", cwd=d)
    doc = json.loads(out.stdout)
    y, u = arrays(d, "gaps.csv")
    report, fitted = sisfilt.fit(sisfilt.Model.from_toml(config("platoon.toml")), y, u,
                                 params=["Q[i]", "M"], dropouts="known")
    assert report["filter"] == "centralized"
    assert report["parameters"][2]["name"] == "Q11[i=1]"
    assert report["parameters"] == doc["parameters"]
    assert fitted.to_toml() == sisfilt.Model.from_toml(d / "each.toml").to_toml()


def test_with_changes_a_copy_as_set_does(cli, tmp_path):
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    changed = model.with_(p=0.6, M=np.array([[0.02, 0.0], [0.0, 0.005]]), steps=30)
    assert model.steps == 200 and changed.steps == 30
    cli("simulate", config("platoon.toml"), "--out", tmp_path, "--set", "dropout.p=0.6",
        "--set", "model.M=[[0.02, 0.0], [0.0, 0.005]]", "--set", "steps=30", cwd=tmp_path)
    _, y = read_steps(tmp_path / "measurements.csv", 20)
    np.testing.assert_array_equal(sisfilt.simulate(changed)["y"], y)
    assert changed.check()["dims"] == model.check()["dims"]


def test_arrays_of_other_dtypes_and_layouts_are_converted(platoon_run):
    y, u = arrays(platoon_run, "measurements.csv")
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    want = sisfilt.estimate(model, y, u).x
    strided = np.asfortranarray(y)
    assert not strided.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(sisfilt.estimate(model, strided, u).x, want)
    np.testing.assert_array_equal(sisfilt.estimate(model, y.astype(np.float32), u).x,
                                  sisfilt.estimate(model, y.astype(np.float32).astype(float), u).x)
    np.testing.assert_array_equal(sisfilt.estimate(model, y.tolist(), u).x, want)


@pytest.mark.parametrize("call, message", [
    (lambda m, y, u: sisfilt.estimate(m, y[:, :10], u), "y: expected an array of shape (T, N, q)"),
    (lambda m, y, u: sisfilt.estimate(m, y, u[:5]), "u: expected an array of shape (T, N, m)"),
    (lambda m, y, u: sisfilt.estimate(m, y, u, filter="kalman"), "filter: expected one of"),
    (lambda m, y, u: sisfilt.estimate(m, y, u, update="mixture", dropouts="known"), "mixture"),
    (lambda m, y, u: sisfilt.estimate(m, y[:0], u[:0]), "holds no step"),
    (lambda m, y, u: sisfilt.fit(m, y, u, params=["p", "R"]), "unknown parameter `R`"),
    (lambda m, y, u: m.with_(p=1.5), "dropout.p (from --set)"),
    (lambda m, y, u: sisfilt.Model.from_toml_str("subsystems = 0"), "<string>"),
    (lambda m, y, u: sisfilt.Model.from_toml("no/such/config.toml"), "no/such/config.toml"),
])
def test_bad_input_raises_value_error(platoon_run, call, message):
    y, u = arrays(platoon_run, "measurements.csv")
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    with pytest.raises(ValueError) as caught:
        call(model, y, u)
    assert message in str(caught.value)


def test_a_numerical_breakdown_raises_arithmetic_error():
    text = (config("platoon.toml").read_text()
            .replace("M = [[0.04, 0.0], [0.0, 0.01]]", "M = [[1e-300, 0.0], [0.0, 1e-300]]"))
    model = sisfilt.Model.from_toml_str(text)
    y = np.full((3, 20, 2), 1.7e308)
    with pytest.raises(ArithmeticError) as caught:
        sisfilt.estimate(model, y, filter="joint")
    assert "t = 1" in str(caught.value)


def test_two_threads_filter_at_once(platoon_run):
    y, u = arrays(platoon_run, "measurements.csv")
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    want = sisfilt.estimate(model, y, u, filter="joint").x
    results = [None, None]

    def work(k):
        results[k] = sisfilt.estimate(model, y, u, filter="joint").x

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for r in results:
        np.testing.assert_array_equal(r, want)


@pytest.mark.parametrize("options", [
    {},
    {"filter": "joint", "update": "mixture"},
    {"filter": "centralized"},
    {"dropouts": "known", "filter": "joint"},
])
def test_the_step_by_step_filter_equals_estimate(platoon_run, options):
    y, u = arrays(platoon_run, "gaps.csv")
    model = sisfilt.Model.from_toml(config("platoon.toml"))
    est = sisfilt.estimate(model, y, u, **options)
    live = sisfilt.Filter(model, **options)
    loglik = 0.0
    for t in range(y.shape[0]):
        x, P = live.step(y[t], u[t])
        np.testing.assert_array_equal(x, est.x[t])
        np.testing.assert_array_equal(P, est.P[t])
        if est.arrival is not None:
            np.testing.assert_array_equal(live.arrival, est.arrival[t])
        loglik += live.loglik or 0.0
    assert live.t == y.shape[0]
    if est.loglik is not None:
        assert loglik == pytest.approx(est.loglik, rel=1e-12)
    # Without u_t, the model's own inputs (the platoon's sine), as the files hold them.
    again = sisfilt.Filter(model, **options)
    for t in range(3):
        np.testing.assert_array_equal(again.step(y[t])[0], est.x[t])
    with pytest.raises(ValueError, match=r"y_t: expected an array of shape \(N, q\)"):
        again.step(y[3][:, :1])


def without_times(value):
    """The evaluation without its wall-clock times, which differ from run to run."""
    if isinstance(value, dict):
        return {k: without_times(v) for k, v in value.items() if "wall_time" not in k}
    if isinstance(value, list):
        return [without_times(v) for v in value]
    return value


@pytest.mark.parametrize("options, kwargs", [
    ([], {}),
    (["--sweep-p", "0.6,0.9", "--filters", "distributed,joint-mixture"],
     {"sweep_p": [0.6, 0.9], "filters": ["distributed", "joint-mixture"]}),
    (["--smooth", "--true-p", "0.7", "--seed", "4"], {"smooth": True, "true_p": 0.7, "seed": 4}),
])
def test_evaluate_equals_the_command_lines_json(cli, tmp_path, options, kwargs):
    cli("evaluate", config("platoon.toml"), "--runs", 2, "--set", "steps=25", "--out",
        tmp_path / "e.json", *options, cwd=tmp_path)
    doc = json.loads((tmp_path / "e.json").read_text())
    model = sisfilt.Model.from_toml(config("platoon.toml")).with_(steps=25)
    got = sisfilt.evaluate(model, 2, **kwargs)
    assert without_times(got) == without_times(doc)


def test_ctrl_c_stops_a_long_call():
    """SIGINT (Ctrl-C) during a long filter run raises KeyboardInterrupt within the call,
    and the package works afterwards."""
    import os
    import signal

    model = sisfilt.Model.from_toml(config("platoon.toml")).with_(subsystems=2000)
    y = np.zeros((3000, 2000, 2))
    timer = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            sisfilt.estimate(model, y, filter="joint")
    finally:
        timer.cancel()
    assert sisfilt.estimate(model, y[:2]).x.shape == (2, 2000, 2)


def test_ctrl_c_stops_a_smoother_in_its_forward_pass():
    """SIGINT 0.2 s into a smoothed run raises KeyboardInterrupt during the forward pass, not
    after the backward pass: well before the time a whole run takes (about a tenth of it
    here; the bound is half, so that a busy machine cannot fail the test)."""
    import os
    import signal

    model = sisfilt.Model.from_toml(config("platoon.toml")).with_(subsystems=2000)
    y = np.zeros((600, 2000, 2))
    start = time.perf_counter()
    sisfilt.estimate(model, y[:300], filter="joint", smooth=True)
    whole = 2 * (time.perf_counter() - start)
    timer = threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT))
    start = time.perf_counter()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            sisfilt.estimate(model, y, filter="joint", smooth=True)
    finally:
        timer.cancel()
    assert time.perf_counter() - start < whole / 2


def test_ctrl_c_stops_an_evaluation():
    """SIGINT during a Monte Carlo study (minutes of runs) raises KeyboardInterrupt once the
    runs in progress finish, and evaluate works afterwards."""
    import os
    import signal

    model = sisfilt.Model.from_toml(config("platoon.toml"))
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            sisfilt.evaluate(model, 200_000, filters=["distributed"])
    finally:
        timer.cancel()
    assert sisfilt.evaluate(model, 2, filters=["distributed"])["options"]["runs"] == 2
