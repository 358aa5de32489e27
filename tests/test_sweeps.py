"""Sweeps: rows equal single runs, determinism across layouts, resume, jax.distributed, bad input."""

import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

import coopjax as cj
from coopjax import cli, io, sweeps

# A small, well-conditioned sweep (the paper scenario is step-converged at dt = 1e-3).
BASE = [
    "sweep",
    "--scenario",
    "paper",
    "--T",
    "1.0",
    "--vary",
    "M_b=loguniform:0.5:5",
    "--vary",
    "K_GP=uniform:0.3:0.9",
    "--set",
    "G_e=500",
    "--quiet",
]


def sweep_cli(*extra, cwd, devices=1, env=None, background=False, default_xla=False):
    """The sweep command in a process of its own; `default_xla` drops the suite's XLA flags (conftest.py),
    so that it compiles as a user's run does."""
    cmd = [sys.executable, "-m", "coopjax.cli"] + BASE + ["--devices", str(devices)] + list(extra)
    environment = {**os.environ, **(env or {})}
    if default_xla:
        environment.pop("XLA_FLAGS", None)
    kwargs = dict(cwd=cwd, env=environment, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    if background:
        return subprocess.Popen(cmd, **kwargs)
    return subprocess.run(cmd, **kwargs, timeout=300)


def read(path):
    return io.read_table(str(path))


def assert_same_table(a, b):
    """Bit-identical, except the step limit: an eigenvalue estimate that rounding moves by ~1e-7 and
    that is stored to 6 digits (sweeps._significant), so it may differ in the last one."""
    assert list(a) == list(b)
    for k in a:
        if k == "dt_limit":
            np.testing.assert_allclose(a[k], b[k], rtol=2e-6)
        else:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.mark.slow
def test_rows_equal_single_simulate_runs():
    spec = sweeps.make_spec(
        "paper", n=12, vary={"M_b": "loguniform:0.5:5", "K_GP": "uniform:0.3:0.9"}, fixed={"G_e": 500.0}, T=1.0
    )
    table = sweeps.run(spec, chunk=5)
    for i in range(12):
        single = cj.simulate(cj.make_params(M_b=table["M_b"][i], K_GP=table["K_GP"][i], G_e=500.0), "paper", T=1.0)
        for name in ("min_grip", "peak_grip", "slip", "crush", "rms_lag"):
            assert table[name][i] == pytest.approx(float(getattr(single.metrics, name)), rel=1e-9, nan_ok=True), name


def test_draws_follow_their_distributions_and_grids_are_factorial():
    spec = sweeps.make_spec("carry", n=None, vary={"K_GP": "grid:0.1:0.5:3", "tau": "grid:1:2:2", "M_b": "choice:1,2"})
    assert spec.n == 6
    d = sweeps.draw(spec.distributions(), np.arange(6), 0)
    np.testing.assert_allclose(d["K_GP"], [0.1, 0.1, 0.3, 0.3, 0.5, 0.5])
    assert d["tau"].tolist() == [1, 2, 1, 2, 1, 2]
    big = sweeps.draw(
        {
            "x": sweeps.parse_distribution("M_b", "loguniform:0.5:5"),
            "y": sweeps.parse_distribution("K_GP", "normal:2:0.5"),
        },
        np.arange(200_000),
        7,
    )
    assert 0.5 <= big["x"].min() and big["x"].max() <= 5
    assert np.log(big["x"]).mean() == pytest.approx(np.log(np.sqrt(0.5 * 5)), abs=0.01)
    assert big["y"].mean() == pytest.approx(2, abs=0.01) and big["y"].std() == pytest.approx(0.5, abs=0.01)


@pytest.mark.slow
def test_same_seed_same_table_whatever_the_chunk_size():
    spec = sweeps.make_spec("paper", n=30, vary={"M_b": "loguniform:0.5:5", "K_GP": "uniform:0.3:0.9"}, T=1.0, seed=3)
    assert_same_table(sweeps.run(spec, chunk=7), sweeps.run(spec, chunk=30))


@pytest.mark.slow
def test_one_and_two_devices_give_the_identical_table_under_xla_defaults(tmp_path):
    """Also the suite's run of the default compile path (the other tests use faster-compiling flags).
    Every device runs the same block of samples; the one-device program is compiled unpartitioned,
    and XLA's defaults round it as the partitioned one (under the suite's flags, only to round-off)."""
    for d in (1, 2):
        run = sweep_cli("--n", "24", "--chunk", "16", "--out", f"d{d}.csv", cwd=tmp_path, devices=d, default_xla=True)
        assert run.returncode == 0, run.stderr
        assert f"on {d} device(s)" in run.stdout
    assert_same_table(read(tmp_path / "d1.csv"), read(tmp_path / "d2.csv"))


@pytest.mark.slow
def test_resume_after_kill_9_gives_the_uninterrupted_table(tmp_path):
    whole = sweep_cli("--n", "24", "--chunk", "2", "--out", "whole.csv", cwd=tmp_path)
    assert whole.returncode == 0, whole.stderr
    proc = sweep_cli("--n", "24", "--chunk", "2", "--out", "cut.csv", cwd=tmp_path, background=True)
    parts = tmp_path / "cut.csv.parts"
    deadline = time.time() + 120
    while time.time() < deadline and len(list(parts.glob("chunk-*.npy"))) < 3:
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    saved = len(list(parts.glob("chunk-*.npy")))
    assert 3 <= saved < 12 and not (tmp_path / "cut.csv").exists()
    again = sweep_cli("--n", "24", "--chunk", "2", "--out", "cut.csv", cwd=tmp_path)
    assert again.returncode == 2 and "--resume" in again.stderr  # never silently restarts
    resumed = sweep_cli("--n", "24", "--chunk", "2", "--out", "cut.csv", "--resume", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert_same_table(read(tmp_path / "whole.csv"), read(tmp_path / "cut.csv"))
    assert not parts.exists()


def test_two_processes_under_jax_distributed_give_the_single_process_table(tmp_path):
    # The single process runs beside the two (each mostly compiling), not before them.
    single = sweep_cli("--n", "24", "--chunk", "8", "--out", "single.csv", cwd=tmp_path, background=True)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [
        sweep_cli(
            "--n",
            "24",
            "--chunk",
            "8",
            "--out",
            "multi.csv",
            "--coordinator",
            f"127.0.0.1:{port}",
            "--num-processes",
            "2",
            "--process-id",
            str(i),
            cwd=tmp_path,
            background=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert "x 2 process(es)" in outs[0][0]
    single_out = single.communicate(timeout=300)
    assert single.returncode == 0, single_out[1]
    assert_same_table(read(tmp_path / "single.csv"), read(tmp_path / "multi.csv"))


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _distributed(i, *extra, port, cwd):
    flags = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)]
    return sweep_cli(*extra, *flags, cwd=cwd, background=True)


def _coopjax_lines(err):
    return [ln for ln in err.splitlines() if ln.strip()]


@pytest.mark.slow  # three processes (14 s); the two-process table itself stays in CI
def test_processes_with_different_options_are_refused_by_every_one_before_any_work(tmp_path):
    port = _free_port()
    procs = [
        _distributed(i, "--n", n, "--chunk", "8", "--timeout", "60", port=port, cwd=tmp_path)
        for i, n in ((0, "24"), (1, "32"))
    ]
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, outs):
        lines = _coopjax_lines(err)
        assert p.returncode == 2 and len(lines) == 1 and "runs a different sweep from process 0" in lines[0], err
    assert os.listdir(tmp_path) == []


@pytest.mark.slow  # CI's time (13 s, mostly waiting): two processes give the single-process table above
def test_a_partner_that_never_joins_is_one_line_within_the_timeout(tmp_path):
    start = time.perf_counter()
    proc = _distributed(0, "--n", "24", "--chunk", "8", "--timeout", "1", port=_free_port(), cwd=tmp_path)
    _, err = proc.communicate(timeout=120)
    lines = _coopjax_lines(err)
    assert proc.returncode == 1 and len(lines) == 1, err
    assert "did not join" in lines[0] and "nothing was kept" in lines[0], lines
    assert time.perf_counter() - start < 60
    assert sorted(os.listdir(tmp_path)) == ["sweep.csv.distributed.log"]  # XLA's details, said in the line


@pytest.mark.slow
def test_a_partner_killed_during_the_sweep_is_one_line_and_resume_finishes_it(tmp_path):
    single = sweep_cli("--n", "96", "--chunk", "8", "--out", "single.csv", cwd=tmp_path)
    assert single.returncode == 0, single.stderr
    port, parts = _free_port(), tmp_path / "multi.csv.parts"
    args = ("--n", "96", "--chunk", "8", "--out", "multi.csv", "--timeout", "10")
    procs = [_distributed(i, *args, port=port, cwd=tmp_path) for i in range(2)]
    while not (parts.exists() and sum(n.startswith("chunk-") for n in os.listdir(parts)) >= 2):
        assert procs[0].poll() is None, procs[0].communicate()
        time.sleep(0.2)
    procs[1].send_signal(signal.SIGKILL)
    start = time.perf_counter()
    _, err = procs[0].communicate(timeout=120)
    lines = _coopjax_lines(err)
    assert procs[0].returncode == 1 and len(lines) == 1 and "a partner process was lost" in lines[0], err
    assert "finished chunks kept in multi.csv.parts" in lines[0] and time.perf_counter() - start < 60
    resumed = sweep_cli(*args[:-2], "--resume", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert_same_table(read(tmp_path / "single.csv"), read(tmp_path / "multi.csv"))


def test_a_diverging_sample_is_flagged_and_the_others_are_right():
    # K_GP = 100 takes plain RK4 at dt = 1e-3 beyond its stability limit in the paper scenario.
    spec = sweeps.make_spec("paper", n=6, vary={"K_GP": "choice:0.5,100"}, T=1.5, seed=1, integrator="rk4")
    table = sweeps.run(spec, chunk=6)
    bad = table["K_GP"] == 100
    assert bad.any() and (~bad).any()
    assert (table["finite"] == ~bad).all()
    assert np.isfinite(table["t_diverged"][bad]).all() and np.isnan(table["t_diverged"][~bad]).all()
    single = cj.simulate(cj.make_params(K_GP=0.5), "paper", T=1.5, integrator="rk4").metrics
    np.testing.assert_allclose(table["peak_grip"][~bad], float(single.peak_grip), rtol=1e-9)


def test_parquet_output_and_from_table_round_trip(fresh_dir):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    code = cli.main(
        [
            "sweep",
            "--scenario",
            "paper",
            "--T",
            "1",
            "--devices",
            "1",
            "--quiet",
            "--n",
            "6",
            "--vary",
            "M_b=uniform:1:3",
            "--out",
            "s.parquet",
        ]
    )
    assert code == 0
    frame = pd.read_parquet("s.parquet")
    assert list(frame.columns[:2]) == ["sample", "M_b"] and frame["finite"].dtype == bool
    frame[["M_b"]].to_csv("sets.csv", index=False)
    assert (
        cli.main(
            [
                "sweep",
                "--scenario",
                "paper",
                "--T",
                "1",
                "--devices",
                "1",
                "--quiet",
                "--from",
                "sets.csv",
                "--out",
                "again.csv",
            ]
        )
        == 0
    )
    again = io.read_table("again.csv")
    np.testing.assert_allclose(again["peak_grip"], frame["peak_grip"], rtol=1e-9)
    api = cj.sweep("paper", table={"M_b": frame["M_b"].to_numpy()}, T=1.0, dtype="float32")
    np.testing.assert_allclose(api["peak_grip"], frame["peak_grip"], rtol=1e-9)


def test_one_status_vocabulary_with_a_message_each():
    from coopjax.status import LABELS, MESSAGES, Status, labels

    assert set(MESSAGES) == set(Status) and all(MESSAGES[s] for s in Status)
    assert LABELS == ("ok", "diverged", "unstable_loop", "step_beyond_limit", "step_artefact")
    assert labels(np.arange(len(Status))).tolist() == list(LABELS)
    assert [s.measured for s in Status] == [True, False, False, False, True]
    # The bookkeeping's help names every label, and a metric cannot take a status column's name.
    assert sweeps.column_units()["status"] == "|".join(LABELS)
    from coopjax import objectives

    with pytest.raises(ValueError, match="reported by every run"):
        objectives.register(
            objectives.Metric("status", "1", "x", lambda b, d, c: 0, lambda a, o, p, c: a, lambda a, c: a)
        )
    # A run's own metrics speak it too: OK, or DIVERGED where the run did not stay finite.
    m = cj.simulate(
        cj.make_params(K_GP=np.array([0.5, 100.0])), "paper", T=1.5, integrator="rk4", check_dt=False
    ).metrics
    assert [Status(int(s)) for s in m.status] == [Status.OK, Status.DIVERGED]
