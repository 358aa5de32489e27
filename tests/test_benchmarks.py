"""The speed benchmark: its summary (in CI, from rows of known rates), the strong peer against
coopjax and the FLOP count of its source (slow: the peer compiles for minutes), and a smoke run of
`python -m benchmarks --quick` at tiny sizes (slow)."""

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.__main__ import summarise  # noqa: E402


def _row(impl, dtype, devices, rate, B=4096, integrator=None):
    row = dict(impl=impl, dtype=dtype, devices=devices, B=B, steps=4000, run_s=B * 4000 / rate, steps_per_s=rate)
    if integrator:
        row["integrator"] = integrator
    return row


def test_the_summary_states_coopjax_against_the_strong_peer_and_the_peak():
    rows = [
        _row("coopjax", "float64", 2, 8e6),
        _row("coopjax", "float32", 2, 12e6),
        _row("coopjax", "float64", 1, 4e6),
        _row("coopjax_filippov", "float64", 2, 2e6),
        _row("coopjax_filippov", "float32", 2, 3e6),
        _row("strong_peer", "float64", 2, 10e6, integrator="filippov"),
        _row("strong_peer", "float32", 2, 20e6, integrator="filippov"),
        _row("strong_peer", "float64", 2, 16e6, integrator="rk4"),
        _row("strong_peer", "float64", 2, 1e6, B=64, integrator="rk4"),  # another B: not the summary's
        _row("numba", "float64", 2, 4e6),
    ]
    result = dict(
        throughput=rows,
        machine=dict(cores=2, peak_gflops_estimate=dict(float64=80.0, float32=160.0)),
        config=dict(T=4.0),
        lsoda=dict(seconds_per_set=0.1),
        peer_flops=dict(filippov=2000.0, rk4=1000.0),
    )
    s = summarise(result)
    ratio = s["coopjax_over_strong_peer"]
    assert ratio["filippov_float64"] == pytest.approx(0.2) and ratio["filippov_float32"] == pytest.approx(0.15)
    assert ratio["rk4_float64"] == pytest.approx(0.5) and ratio["rk4_float32"] is None  # no peer row
    # At the peer's FLOP count for both: 2e6 steps/s x 2000 FLOP = 4 GFLOP/s of 80.
    assert s["fraction_of_peak"]["filippov_float64"] == pytest.approx(dict(coopjax=0.05, strong_peer=0.25))
    assert s["fraction_of_peak"]["rk4_float32"]["strong_peer"] is None
    assert s["strong_peer_steps_per_s"]["rk4_float64"] == 16e6
    assert s["targets"]["strong peer filippov float64 >= 30 M steps/s"] is False
    assert s["targets"]["coopjax filippov float64 (all devices) >= 0.35 x strong peer"] is False
    assert s["targets"]["coopjax rk4 float32 (all devices) >= 0.35 x strong peer"] is None
    assert s["coopjax_over_numba_float64"] == pytest.approx(2.0)


# Samples for the peer's agreement: light and heavy bodies (impacts, long sliding), soft and stiff gains,
# and two where a robot leaves the surface with sigma on it to round-off (test_sliding.ROUND_OFF_JUMPS:
# the peer without that rule differs from the step by 3e-5 and 1.5e-6 there).
PEER_SAMPLES = dict(
    M_b=[0.5, 2.0, 5.0, 20.0, 4.247574395009304, 0.9331055493261957],
    K_GP=[0.05, 0.5, 1.5, 0.3, 0.5803716038956519, 0.7964010263953576],
    K_GI=[0.01, 0.1, 0.8, 0.3, 0.28873584454412243, 0.08626336688937561],
    tau=[0.2, 1.25, 4.0, 1.0, 1.1020025798727022, 1.0082307541733402],
    G_e=[50.0, 600.0, 3000.0, 200.0, 763.5063919366245, 795.9660435769277],
)
AGREEMENT = """
import sys, jax
jax.config.update("jax_enable_x64", True)
import coopjax as cj
from benchmarks.strong_peer import agreement
params = cj.make_params(**{samples})
print(agreement("filippov", params, 4.0, block=4), agreement("rk4", params, 1.0, block=4))
"""


def test_the_strong_peer_does_the_same_step_as_coopjax():
    # The peer's own source run as Python (NUMBA_DISABLE_JIT=1), so that a change to the step that
    # forgets the peer fails here, in every run; two blocks, one partial.
    run = subprocess.run(
        [sys.executable, "-c", AGREEMENT.format(samples=PEER_SAMPLES)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env=dict(os.environ, NUMBA_DISABLE_JIT="1"),
    )
    assert run.returncode == 0, run.stderr[-3000:]
    filippov, rk4 = map(float, run.stdout.split())
    assert filippov <= 1e-9 and rk4 <= 1e-9, (filippov, rk4)


@pytest.mark.slow
def test_the_compiled_strong_peer_is_coopjax_to_1e_9():
    import jax

    jax.config.update("jax_enable_x64", True)
    import coopjax as cj
    from benchmarks.strong_peer import agreement

    params = cj.make_params(**PEER_SAMPLES)
    assert agreement("filippov", params, 4.0, block=4) <= 1e-9
    assert agreement("rk4", params, 1.0, block=4) <= 1e-9


@pytest.mark.slow
def test_the_flop_count_of_the_peer_source():
    # RK4 is four field evaluations of both robots a step, each some 90 operations a robot.
    run = subprocess.run(
        [sys.executable, "-m", "benchmarks.strong_peer", "--T", "0.05"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env=dict(os.environ, NUMBA_DISABLE_JIT="1"),
    )
    assert run.returncode == 0, run.stderr[-2000:]
    counts = json.loads(run.stdout.strip().splitlines()[-1])
    assert 4 * 2 * 90 < counts["rk4"] < 4 * 2 * 200
    assert counts["filippov"] > 1.3 * counts["rk4"]  # two fields a robot at every stage, and the plan
    refused = subprocess.run(
        [sys.executable, "-m", "benchmarks.strong_peer"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"},
    )
    assert refused.returncode == 2 and "NUMBA_DISABLE_JIT=1" in refused.stderr


@pytest.mark.slow
def test_quick_benchmark_writes_the_documented_fields(tmp_path):
    out, plot = tmp_path / "results.json", tmp_path / "scaling.png"
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks",
            "--quick",
            "--max-devices",
            "1",
            "--Bs",
            "2",
            "--T",
            "0.05",
            "--repeats",
            "1",
            "--out",
            str(out),
            "--plot",
            str(plot),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    result = json.load(open(out))
    assert {"jax", "cpu", "cores", "device_counts"} <= set(result["machine"])
    assert all(result["accuracy"]["ok"].values())  # every baseline matched coopjax before timing
    assert {"strong_peer_filippov_metrics", "strong_peer_rk4_metrics"} <= set(result["accuracy"])
    impls = {(r["impl"], r.get("integrator"), r["dtype"], r["devices"]) for r in result["throughput"]}
    assert {("coopjax", "rk4", "float32", 1), ("coopjax", "rk4", "float64", 1)} <= impls
    assert {("coopjax_filippov", "filippov", "float32", 1), ("coopjax_filippov", "filippov", "float64", 1)} <= impls
    assert {i[:3] for i in impls} >= {("strong_peer", "filippov", "float64"), ("strong_peer", "rk4", "float64")}
    for r in result["throughput"]:
        assert r["steps_per_s"] > 0 and r["run_s"] > 0
    assert result["peer_flops"]["filippov"] > result["peer_flops"]["rk4"] > 0
    s = result["summary"]
    assert {
        "coopjax_over_strong_peer",
        "fraction_of_peak",
        "strong_peer_steps_per_s",
        "targets",
        "filippov_over_rk4_cost",
        "coopjax_over_lsoda_per_set",
        "compile_s",
    } <= set(s)
    assert set(s["coopjax_over_strong_peer"]) == {"filippov_float32", "filippov_float64", "rk4_float32", "rk4_float64"}
    assert plot.stat().st_size > 10_000


def test_the_suite_counts_an_answer_at_its_worst_over_the_judges_steps():
    """A value that moves with the step is not the dt -> 0 limit's: an answer that holds at dt and
    dt/2 but misses at dt/4 is not solved, and its least violation and objective are the worst
    of the three steps (the best known's are judged so too)."""
    from types import SimpleNamespace

    from benchmarks.problem_suite import worst_over_steps

    at = lambda holds, objective, violation: SimpleNamespace(
        holds=holds, objective=objective, violation=violation, unmeasured=0.0
    )
    worst = worst_over_steps([at(True, 15.1, 0.0), at(True, 15.0, 0.0), at(False, 22.7, 1.83)])
    assert worst == {"holds": False, "objective": 22.7, "violation": 1.83, "unmeasured": 0.0}
    assert worst_over_steps([at(True, 15.1, 0.0)] * 3)["holds"]


def test_every_best_known_was_judged_on_the_design_the_suite_judges_on():
    """A ratio compares two answers judged alike: each problem's best known must have been judged on
    the dense design the suite uses now (its size) at the suite's steps, and a change of either
    means judging the best knowns again (`python -m benchmarks.best_known --merge`)."""
    import json
    import os

    from benchmarks.problem_suite import PROBLEMS, problem_files, steps
    from tuning import design
    from tuning.problem import Problem

    known = json.load(open(os.path.join(PROBLEMS, "best_known.json")))
    for path in problem_files(PROBLEMS):
        name = os.path.basename(path)[:-5]
        problem = Problem.from_toml(path)
        search = known[name]["search"]
        assert search["judged_draws"] == len(design.dense(problem.uncertain)), name
        assert search["judged_dt"] == list(steps()), name
