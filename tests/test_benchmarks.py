"""Smoke test of `python -m benchmarks --quick` at tiny sizes: it writes results.json with the
documented fields. The gradient, memory and compile-time studies run only in the full benchmark."""

import json
import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.slow
def test_quick_benchmark_writes_the_documented_fields(tmp_path):
    out, plot = tmp_path / "results.json", tmp_path / "scaling.png"
    run = subprocess.run([sys.executable, "-m", "benchmarks", "--quick", "--max-devices", "1", "--Bs", "2", "--T", "0.05", "--repeats", "1",
                          "--out", str(out), "--plot", str(plot)], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    result = json.load(open(out))
    assert {"jax", "cpu", "cores", "device_counts"} <= set(result["machine"])
    assert all(result["accuracy"]["ok"].values())  # every baseline matched coopjax before timing
    impls = {(r["impl"], r["dtype"], r["devices"]) for r in result["throughput"]}
    assert {("coopjax", "float32", 1), ("coopjax", "float64", 1), ("numpy", "float64", 1)} <= impls
    assert {("coopjax_filippov", "float32", 1), ("coopjax_filippov", "float64", 1)} <= impls
    assert any(i[0] == "numba" for i in impls)
    for r in result["throughput"]:
        assert r["steps_per_s"] > 0 and r["run_s"] > 0
    assert result["lsoda"]["seconds_per_set"] > 0
    assert "gradient" not in result  # the gradient study is left to the full run
    assert result["flops"]["flops_per_sample_step"] > 0 and result["flops_filippov"]["flops_per_sample_step"] > 0
    assert {"coopjax_over_lsoda_per_set", "targets", "filippov_over_rk4_cost"} <= set(result["summary"])
    assert all(v > 0 for v in result["summary"]["filippov_over_rk4_cost"].values())
    # Issue 12's fields (numba's sliding-mode peer is left out of --quick: its compile takes 30 s).
    assert {"rk4_steps_per_s", "filippov_steps_per_s", "coopjax_over_numba", "converged_trajectories_per_s",
            "compile_s", "fraction_of_peak"} <= set(result["summary"])
    assert set(result["summary"]["targets_issue12"]) == {
        "filippov float64 all cores >= 2 x numba filippov", "filippov_over_rk4_cost <= 2.5 (float64, all cores)",
        "rk4 float32 all cores >= 25 M steps/s", "compile < 5 s", "compile flat in the horizon (10x the steps, < 1.5x the time)"}
    assert result["summary"]["rk4_steps_per_s"]["float64_1_device"] > 0
    assert result["summary"]["filippov_steps_per_s"]["float64_1_device"] > 0
    assert plot.stat().st_size > 10_000
