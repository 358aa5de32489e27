"""Every mistake a user can make, per command: one line on stderr naming the problem, exit code 2,
no traceback, and the folder exactly as it was (no output, no OUT.parts/, no temporary file).

One table, run in-process through `coopjax.cli.main`. Each case may first write input files
(`setup`); the folder is compared, names and contents, before and after."""

import os
import re
import subprocess
import sys

import numpy as np
import pytest

import coopjax as cj
from coopjax import cli, io, sweeps

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SMALL = ["--scenario", "paper", "--T", "0.05", "--devices", "1", "--quiet"]
VARY = ["--vary", "M_b=uniform:1:2", "--n", "4"]
SWEEP_TABLE = "sample,M_b,min_grip,finite\n0,1.0,nan,0\n1,2.0,nan,0\n"

# (id, setup: {file: text, or None for a folder}, argv, env, a fragment the one line must contain)
CASES = [
    # 1. A sweep that varies nothing.
    ("sweep-nothing-varies", {}, ["sweep", *SMALL, "--n", "8"], {}, "nothing varies"),
    ("sweep-nothing-varies-set", {}, ["sweep", *SMALL, "--n", "8", "--set", "K_GP=0.3"], {}, "nothing varies"),
    # 2. Output paths, before any work.
    ("sweep-out-folder", {"s.csv": None}, ["sweep", *SMALL, *VARY, "--out", "s.csv"], {}, "is a folder"),
    ("sweep-out-missing-folder", {}, ["sweep", *SMALL, *VARY, "--out", "no/s.csv"], {}, "does not exist"),
    ("sweep-out-extension", {}, ["sweep", *SMALL, *VARY, "--out", "s.txt"], {}, "must end in one of"),
    ("simulate-out-folder", {"run.csv": None}, ["simulate", "--out", "run.csv"], {}, "is a folder"),
    ("simulate-plot-folder", {"f.png": None}, ["simulate", "--plot", "f.png"], {}, "is a folder"),
    ("simulate-plot-empty", {}, ["simulate", "--plot", ""], {}, "give a file name"),
    ("simulate-plot-extension", {}, ["simulate", "--plot", "f.txt"], {}, "must end in one of"),
    (
        "plot-sweep-out-folder",
        {"t.csv": SWEEP_TABLE, "p.png": None},
        ["plot-sweep", "t.csv", "--out", "p.png"],
        {},
        "is a folder",
    ),
    ("tune-history-folder", {"t_history.png": None}, ["tune", "--steps", "1", "--out", "t.json"], {}, "is a folder"),
    ("tune-traces-folder", {"t_traces.png": None}, ["tune", "--steps", "1", "--out", "t.json"], {}, "is a folder"),
    ("tune-out-extension", {}, ["tune", "--out", "t.txt"], {}, "must end in one of"),
    ("analyze-out-missing-folder", {}, ["analyze", "--out", "no/a"], {}, "does not exist"),
    # 4. Values refused before OUT.parts/ exists.
    ("sweep-set-unknown", {}, ["sweep", *SMALL, *VARY, "--set", "K_XX=1"], {}, "unknown parameter 'K_XX'"),
    ("sweep-set-nonpositive", {}, ["sweep", *SMALL, *VARY, "--set", "K_f=0"], {}, "must be positive"),
    ("sweep-set-not-a-number", {}, ["sweep", *SMALL, *VARY, "--set", "G_e=abc"], {}, "is not a number"),
    # 5. Table input.
    ("from-missing", {}, ["sweep", *SMALL, "--from", "t.csv"], {}, "no such file"),
    ("from-empty", {"t.csv": ""}, ["sweep", *SMALL, "--from", "t.csv"], {}, "is empty"),
    ("from-folder", {"t.csv": None}, ["sweep", *SMALL, "--from", "t.csv"], {}, "is a folder"),
    ("from-header-only", {"t.csv": "M_b\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "has no rows"),
    ("from-unknown-column", {"t.csv": "a,b\n1,2\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "unknown parameter 'a'"),
    ("from-ragged", {"t.csv": "M_b,K_GP\n1,2\n3\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "line 3"),
    ("from-not-numbers", {"t.csv": "M_b\n1\nheavy\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "not numbers"),
    (
        "from-results-only",
        {"t.csv": "sample,min_grip\n0,1\n"},
        ["sweep", *SMALL, "--from", "t.csv"],
        {},
        "no parameter columns",
    ),
    ("from-negative-mass", {"t.csv": "M_b\n1\n-2\n"}, ["sweep", *SMALL, "--from", "t.csv"], {}, "at sample 1"),
    (
        "from-binary",
        {"t.parquet": "not parquet"},
        ["sweep", *SMALL, "--from", "t.parquet"],
        {},
        "not a readable Parquet",
    ),
    ("plot-sweep-empty", {"t.csv": ""}, ["plot-sweep", "t.csv"], {}, "is empty"),
    ("plot-sweep-folder", {"t.csv": None}, ["plot-sweep", "t.csv"], {}, "is a folder"),
    ("plot-sweep-missing", {}, ["plot-sweep", "t.csv"], {}, "no such file"),
    ("plot-sweep-no-column", {"t.csv": "a,b\n1,2\n"}, ["plot-sweep", "t.csv"], {}, "no column 'M_b'"),
    ("plot-sweep-not-a-sweep", {"t.csv": "M_b,min_grip\n1,2\n"}, ["plot-sweep", "t.csv"], {}, "not a sweep table"),
    ("plot-sweep-text-column", {"t.csv": "M_b,min_grip,finite\nx,1,1\n"}, ["plot-sweep", "t.csv"], {}, "not numeric"),
    # 8. Huge numbers: a clear refusal with the limit.
    ("sweep-huge-horizon", {}, ["sweep", "--devices", "1", *VARY, "--T", "1e9"], {}, "at most 2,147,483,647"),
    ("sweep-tiny-step", {}, ["sweep", "--devices", "1", *VARY, "--dt", "1e-12"], {}, "at most 2,147,483,647"),
    ("simulate-huge-steps", {}, ["simulate", "--T", "1e7", "--dt", "1e-6"], {}, "32-bit step counter"),
    ("simulate-huge-every", {}, ["simulate", "--every", "1000000000000"], {}, "more than the run's 3000 steps"),
    (
        "sweep-huge-n",
        {},
        ["sweep", "--devices", "1", "--vary", "M_b=uniform:1:2", "--n", "1000000000000"],
        {},
        "more than half of this machine's memory",
    ),
    # 9. Unstable parameters blame the parameters, not the step.
    ("simulate-negative-force-limit", {}, ["simulate", "--set", "F_lim=-5"], {}, "make the loop unstable"),
    ("simulate-negative-gain", {}, ["simulate", "--set", "K_GP=-5"], {}, "make the loop unstable"),
    ("simulate-tiny-mass", {}, ["simulate", "--set", "M_b=1e-30"], {}, "extremely stiff"),
    ("simulate-step-too-large", {}, ["simulate", "--dt", "0.02"], {}, "too large for filippov"),
    # 11. Nothing silently accepted.
    ("sweep-devices-zero", {}, ["sweep", *SMALL[:4], *VARY, "--devices", "0"], {}, "--devices is 0"),
    ("sweep-repeated-vary", {}, ["sweep", *SMALL, *VARY, "--vary", "M_b=uniform:2:3"], {}, "more than once"),
    ("sweep-repeated-set", {}, ["sweep", *SMALL, *VARY, "--set", "G_e=1", "--set", "G_e=2"], {}, "more than once"),
    ("simulate-repeated-set", {}, ["simulate", "--set", "G_e=1", "--set", "G_e=2"], {}, "more than once"),
    ("sweep-env-processes", {}, ["sweep", *SMALL, *VARY], {"COOPJAX_NUM_PROCESSES": "two"}, "not a whole number"),
    ("sweep-distributed-partial", {}, ["sweep", *SMALL, *VARY, "--num-processes", "2"], {}, "go together"),
    (
        "sweep-process-id-range",
        {},
        ["sweep", *SMALL, *VARY, "--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"],
        {},
        "between 0 and",
    ),
    ("tune-devices-zero", {}, ["tune", "--devices", "0"], {}, "--devices is 0"),
    ("tune-steps-zero", {}, ["tune", "--steps", "0"], {}, "at least 1"),
    ("tune-repeated-set", {}, ["tune", "--set", "G_e=1", "--set", "G_e=2"], {}, "given more than once"),
    ("analyze-alpha", {}, ["analyze", "--alpha", "1,x"], {}, "comma-separated numbers"),
    ("analyze-robot", {}, ["analyze", "--robot", "Q"], {}, "invalid choice"),
    ("unknown-command", {}, ["orbit"], {}, "invalid choice"),
    # simulate
    ("simulate-scenario", {}, ["simulate", "--scenario", "orbit"], {}, "unknown scenario 'orbit'"),
    ("simulate-set-unknown", {}, ["simulate", "--set", "K_XX=1"], {}, "unknown parameter 'K_XX'"),
    ("simulate-set-form", {}, ["simulate", "--set", "K_GP"], {}, "expects NAME=VALUE"),
    ("simulate-set-text", {}, ["simulate", "--set", "K_GP=abc"], {}, "is not a number"),
    ("simulate-set-nan", {}, ["simulate", "--set", "M_b=nan"], {}, "is not finite"),
    ("simulate-set-inf", {}, ["simulate", "--set", "M_b=inf"], {}, "is not finite"),
    ("simulate-negative-mass", {}, ["simulate", "--set", "M_b=-2"], {}, "it must be positive"),
    ("simulate-zero-stiffness", {}, ["simulate", "--set", "K_f=0"], {}, "it must be positive"),
    ("simulate-dt-zero", {}, ["simulate", "--dt", "0"], {}, "--dt is 0 s: it must be positive"),
    ("simulate-T-negative", {}, ["simulate", "--T", "-1"], {}, "--T is -1 s: it must be positive"),
    ("simulate-every-zero", {}, ["simulate", "--every", "0"], {}, "at least 1"),
    ("simulate-dt-text", {}, ["simulate", "--dt", "abc"], {}, "invalid float value"),
    ("simulate-out-nowhere", {}, ["simulate", "--out", "nowhere/run.csv"], {}, "does not exist"),
    ("simulate-switch", {}, ["simulate", "--switch", "soft"], {}, "unknown switch 'soft'"),
    ("simulate-integrator", {}, ["simulate", "--integrator", "euler"], {}, "unknown integrator 'euler'"),
    (
        "simulate-smooth-filippov",
        {},
        ["simulate", "--switch", "smooth", "--integrator", "filippov"],
        {},
        "the smooth switch runs with rk4",
    ),
    ("simulate-gamma-min", {}, ["simulate", "--gamma-min", "nan"], {}, "--gamma-min is nan"),
    ("simulate-force-bound", {}, ["simulate", "--force-bound", "0"], {}, "--force-bound is 0 N"),
    ("simulate-plot-memory", {}, ["simulate", "--T", "1e6", "--dt", "1e-3", "--plot", "f.png"], {}, "drop --plot"),
    # sweep: the distributions and the table
    ("vary-arity", {}, ["sweep", *SMALL, "--n", "4", "--vary", "M_b=uniform:1"], {}, "expected uniform:a:b"),
    ("vary-kind", {}, ["sweep", *SMALL, "--n", "4", "--vary", "M_b=gauss:1:2"], {}, "unknown distribution 'gauss'"),
    ("vary-sign", {}, ["sweep", *SMALL, "--n", "4", "--vary", "M_b=uniform:-1:2"], {}, "M_b must be positive"),
    ("vary-log-zero", {}, ["sweep", *SMALL, "--n", "4", "--vary", "M_b=loguniform:0:2"], {}, "positive lower bound"),
    ("vary-bounds", {}, ["sweep", *SMALL, "--n", "4", "--vary", "M_b=uniform:3:2"], {}, "upper bound is below"),
    ("vary-grid-size", {}, ["sweep", *SMALL, "--vary", "K_GP=grid:0:1:2.5"], {}, "whole number"),
    ("vary-unknown", {}, ["sweep", *SMALL, "--n", "4", "--vary", "K_XX=uniform:0:1"], {}, "unknown parameter 'K_XX'"),
    ("vary-form", {}, ["sweep", *SMALL, "--n", "4", "--vary", "M_b"], {}, "expects NAME=DIST"),
    ("vary-and-set", {}, ["sweep", *SMALL, *VARY, "--set", "M_b=3"], {}, "given twice"),
    ("vary-no-n", {}, ["sweep", *SMALL, "--vary", "K_GP=uniform:1:2"], {}, "say how many samples"),
    ("vary-grid-n", {}, ["sweep", *SMALL, "--vary", "K_GP=grid:1:2:3", "--n", "5"], {}, "disagrees"),
    ("sweep-chunk-zero", {}, ["sweep", *SMALL, *VARY, "--chunk", "0"], {}, "at least 1"),
    (
        "vary-normal-negative",
        {},
        ["sweep", *SMALL, "--vary", "M_b=normal:1:2", "--n", "50"],
        {},
        "--vary M_b=normal:1:2 gives M_b = -",
    ),
    ("sweep-float32-overflow", {}, ["sweep", *SMALL, *VARY, "--set", "K_g=1e40"], {}, "does not fit in float32"),
    ("sweep-scenario", {}, ["sweep", "--scenario", "orbit", *VARY], {}, "unknown scenario 'orbit'"),
    (
        "from-unreadable",
        {"t.csv": "M_b\n1\n"},
        ["sweep", *SMALL, "--from", "t.csv"],
        {"chmod": "t.csv"},
        "not readable",
    ),
    ("plot-sweep-unreadable", {"t.csv": SWEEP_TABLE}, ["plot-sweep", "t.csv"], {"chmod": "t.csv"}, "not readable"),
    (
        "sweep-parts-unreadable",
        {"s.csv.parts": None, "s.csv.parts/manifest.json": "{}"},
        ["sweep", *SMALL, *VARY, "--out", "s.csv", "--resume"],
        {"chmod": "s.csv.parts/manifest.json"},
        "not readable",
    ),
    (
        "sweep-parts-read-only",
        {"s.csv.parts": None, "s.csv.parts/manifest.json": "{}"},
        ["sweep", *SMALL, *VARY, "--out", "s.csv", "--resume"],
        {"chmod": "s.csv.parts"},
        "is not writable",
    ),
    # tune
    (
        "tune-mode",
        {},
        ["tune", "--method", "gradient", "--mode", "sideways"],
        {},
        "argument --mode: invalid choice: 'sideways'",
    ),
    ("tune-method", {}, ["tune", "--method", "newton"], {}, "argument --method: invalid choice: 'newton'"),
    ("tune-flag-of-another-method", {}, ["tune", "--lr", "0.1"], {}, "--lr sets the gradient tuner"),
    (
        "tune-screen-flag-of-another-method",
        {},
        ["tune", "--method", "gradient", "--local", "4"],
        {},
        "--local sets the screen-SLP tuner",
    ),
    ("tune-screen-negative", {}, ["tune", "--screen", "-1"], {}, "--screen is -1"),
    ("tune-local-zero", {}, ["tune", "--local", "0"], {}, "--local is 0"),
    ("tune-search", {}, ["tune", "--search", "grid"], {}, "argument --search: invalid choice: 'grid'"),
    (
        "tune-search-of-another-method",
        {},
        ["tune", "--method", "gradient", "--search", "sobol"],
        {},
        "--search sets the screen-SLP tuner",
    ),
    ("tune-masses-kind", {}, ["tune", "--masses", "normal:1:2"], {}, "--masses expects"),
    ("tune-masses-order", {}, ["tune", "--masses", "loguniform:5:0.5"], {}, "0 < LOW < HIGH"),
    ("tune-params-unknown", {}, ["tune", "--params", "K_XX"], {}, "unknown parameter 'K_XX'"),
    ("tune-params-mass", {}, ["tune", "--params", "M_b"], {}, "not a controller parameter"),
    ("tune-params-force-limit", {}, ["tune", "--params", "F_lim"], {}, "--params: F_lim is not a controller parameter"),
    ("tune-params-plant", {}, ["tune", "--params", "K_g,M_v"], {}, "not a controller parameter"),
    ("tune-params-twice", {}, ["tune", "--params", "K_GP,K_GP"], {}, "named twice"),
    ("tune-params-both", {}, ["tune", "--params", "K_GP,K_GP_L"], {}, "both named"),
    ("tune-starts-zero", {}, ["tune", "--starts", "0"], {}, "--starts is 0"),
    ("tune-train-masses", {}, ["tune", "--train-masses", "1"], {}, "--train-masses is 1"),
    ("tune-switch", {}, ["tune", "--switch", "soft"], {}, "argument --switch: invalid choice: 'soft'"),
    ("tune-aggregate", {}, ["tune", "--aggregate", "median"], {}, "argument --aggregate: invalid choice: 'median'"),
    ("tune-lr", {}, ["tune", "--method", "gradient", "--lr", "-1"], {}, "--lr is -1"),
    ("tune-w-lag", {}, ["tune", "--w-lag", "-1"], {}, "--w-lag is -1"),
    ("tune-set-tuned", {}, ["tune", "--set", "K_GP=0.2"], {}, "both tuned (--params) and fixed"),
    ("tune-set-mass", {}, ["tune", "--set", "M_b=2"], {}, "the body mass is what the tuner varies"),
    ("tune-held-out", {}, ["tune", "--held-out", "1"], {}, "at least 2 draws"),
    ("tune-pareto-weights", {}, ["tune", "--pareto", "--pareto-weights", "a,b"], {}, "not a comma-separated list"),
    ("tune-seeds-twice", {}, ["tune", "--compare", "--seeds", "1,1"], {}, "names a value twice"),
    ("tune-compare-pareto", {}, ["tune", "--compare", "--pareto"], {}, "choose one"),
    (
        "tune-race-budget",
        {},
        ["tune", "--compare", "--race-budget", "money"],
        {},
        "argument --race-budget: invalid choice: 'money'",
    ),
    ("tune-resume-nothing", {}, ["tune", "--resume"], {}, "no tuned.json.ckpt to continue"),
    # Sizes beyond this machine's memory, refused before any work, naming tune's own flags.
    ("tune-train-masses-huge", {}, ["tune", "--train-masses", "100000000"], {}, "--train-masses 100000000"),
    ("tune-screen-huge", {}, ["tune", "--screen", "1000000000"], {}, "--screen 1000000000"),
    ("tune-local-huge", {}, ["tune", "--local", "100000000"], {}, "--local 100000000"),
    ("tune-held-out-huge", {}, ["tune", "--held-out", "100000000"], {}, "--held-out 100,000,000"),
    ("tune-judge-dt-zero", {}, ["tune", "--judge-dt", "0"], {}, "--judge-dt is 0"),
    ("tune-judge-dt-unstable", {}, ["tune", "--judge-dt", "0.05"], {}, "too large for filippov"),
    ("tune-judge-dt-horizon", {}, ["tune", "--judge-dt", "10"], {}, "longer than the horizon"),
    ("tune-dt-unstable", {}, ["tune", "--dt", "0.05"], {}, "too large"),
    ("tune-seed-negative", {}, ["tune", "--seed", "-1"], {}, "--seed is -1"),
    ("tune-stale-checkpoint", {"tuned.json.ckpt": "x"}, ["tune"], {}, "holds an interrupted run"),
    # analyze
    ("analyze-alpha-range", {}, ["analyze", "--alpha", "0.5,-1"], {}, "between 0 and 1"),
    ("analyze-out-empty", {}, ["analyze", "--out", ""], {}, "give a file name"),
    ("analyze-repeated-set", {}, ["analyze", "--set", "K_GP=1", "--set", "K_GP=2"], {}, "given more than once"),
]


def snapshot(folder):
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = os.path.join(root, name)
            out[os.path.relpath(path, folder)] = None if os.path.isdir(path) else open(path, "rb").read()
    return out


def deny(monkeypatch, path):
    """Make `path` unreadable and unwritable, also for root (whom permissions do not stop)."""
    os.chmod(path, 0)
    if os.geteuid() == 0:
        real, target = os.access, os.path.abspath(path)
        monkeypatch.setattr(
            os, "access", lambda p, mode, **kw: False if os.path.abspath(p) == target else real(p, mode, **kw)
        )


@pytest.mark.parametrize("setup, argv, env, fragment", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_mistake_is_one_line_exit_2_and_leaves_the_folder_as_it_was(
    fresh_dir, capsys, monkeypatch, setup, argv, env, fragment
):
    for name, text in setup.items():
        os.mkdir(name) if text is None else open(name, "w").write(text)
    for key, value in env.items():
        if key == "chmod":
            deny(monkeypatch, value)
        else:
            monkeypatch.setenv(key, value)
    before = snapshot(fresh_dir)
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert fragment in err, err
    assert snapshot(fresh_dir) == before


def test_the_table_covers_every_command():
    commands = {c[2][0] for c in CASES}
    assert {"simulate", "sweep", "plot-sweep", "tune", "analyze"} <= commands and len(CASES) >= 50


# The Python API: the same mistakes raise coopjax.InputError (a ValueError), in API terms.
API_CASES = [
    ("unknown-name", lambda: cj.make_params(K_XX=1.0), "unknown parameter 'K_XX'"),
    ("close-name", lambda: cj.make_params(K_GPP=1.0), "did you mean 'K_GP'"),
    ("nan", lambda: cj.make_params(M_b=float("nan")), "must be finite"),
    ("negative-mass", lambda: cj.make_params(M_v_L=-1.0), "M_v_L is -1 kg: it must be positive"),
    ("zero-stiffness", lambda: cj.make_params(K_g=0.0), "K_g_L is 0 N/m: it must be positive"),
    ("shared-per-robot", lambda: cj.make_params(M_b_L=1.0), "M_b is shared by both robots; set M_b, not M_b_L"),
    ("text-value", lambda: cj.make_params(K_GP="abc"), "K_GP: expected a number"),
    ("none-value", lambda: cj.make_params(K_GP=None), "K_GP: expected a number"),
    ("empty-batch", lambda: cj.make_params(M_b=np.array([])), "an empty batch"),
    ("matrix-value", lambda: cj.make_params(M_b=np.ones((2, 2))), "expected a scalar or a 1-D batch"),
    ("batch-mismatch", lambda: cj.make_params(M_b=np.ones(3), K_GP=np.ones(2)), "does not match the batch"),
    ("base-type", lambda: cj.make_params({"K_GP": 1.0}), "base must be a Params"),
    ("params-type", lambda: cj.simulate({"K_GP": 1.0}), "params must be a Params"),
    ("scenario", lambda: cj.simulate(cj.make_params(), "orbit"), "unknown scenario 'orbit'"),
    ("scenario-type", lambda: cj.simulate(cj.make_params(), 3), "expected a Config or a scenario name"),
    ("setting", lambda: cj.simulate(cj.make_params(), swich="hard"), "unknown setting 'swich'"),
    ("dt-zero", lambda: cj.simulate(cj.make_params(), dt=0.0), "dt is 0 s: it must be positive"),
    ("dt-negative", lambda: cj.simulate(cj.make_params(), dt=-1e-3), "dt is -0.001 s: it must be positive"),
    ("dt-text", lambda: cj.simulate(cj.make_params(), dt="fast"), "dt must be a number"),
    ("T-negative", lambda: cj.simulate(cj.make_params(), T=-1.0), "T is -1 s: it must be positive"),
    ("every-zero", lambda: cj.simulate(cj.make_params(), every=0), "at least 1"),
    ("every-float", lambda: cj.simulate(cj.make_params(), every=2.5), "a whole number of steps"),
    ("switch", lambda: cj.simulate(cj.make_params(), switch="soft"), "unknown switch 'soft'"),
    ("switch-type", lambda: cj.simulate(cj.make_params(), switch=1), "switch must be a name"),
    ("dtype", lambda: cj.simulate(cj.make_params(), dtype="int8"), "choose float32 or float64"),
    ("checkpoint", lambda: cj.simulate(cj.make_params(), checkpoint="yes"), "checkpoint is 'yes'"),
    ("adjoint", lambda: cj.simulate(cj.make_params(), adjoint="backward"), "adjoint is 'backward'"),
    ("step-too-large", lambda: cj.simulate(cj.make_params(), dt=0.01), "too large for filippov"),
    ("step-beyond-limit", lambda: cj.simulate(cj.make_params(K_GP=100.0), dt=1e-3), "stable only for dt <="),
    ("unstable", lambda: cj.simulate(cj.make_params(K_GP=-5.0), "paper"), "make the loop unstable"),
    ("steps", lambda: cj.simulate(cj.make_params(), "paper", T=1e7, dt=1e-6), "32-bit step counter"),
    (
        "state-name",
        lambda: cj.simulate(cj.make_params(), "paper", T=0.01, every=1).trajectory.state("x_q"),
        "unknown state 'x_q'",
    ),
    ("sweep-nothing-varies", lambda: cj.sweep("paper", 8, T=0.05), "nothing varies"),
    ("sweep-vary-type", lambda: cj.sweep("paper", 8, vary={"M_b": 2.0}), "expected a distribution"),
    ("sweep-vary-dict", lambda: cj.sweep("paper", 8, vary=["M_b"]), "vary must be a dict"),
    ("sweep-seed", lambda: cj.sweep("paper", 8, vary={"M_b": "uniform:1:2"}, seed=-1), "seed is -1"),
    ("use-all-cores", lambda: cj.use_all_cores(0), "at least one device"),
]


@pytest.mark.parametrize("call, fragment", [c[1:] for c in API_CASES], ids=[c[0] for c in API_CASES])
def test_the_python_api_raises_input_error_in_api_terms(call, fragment):
    with pytest.raises(cj.InputError) as info:
        call()
    assert fragment in str(info.value) and "--" not in str(info.value), str(info.value)


def test_a_stale_temporary_file_from_a_killed_write_is_gone_after_the_next_success(fresh_dir):
    # What a kill -9 between writing and renaming leaves: the target's temporary file.
    stale = fresh_dir / ".s.csv.tmp-abcd1234.csv"
    stale.write_text("half a table")
    other = fresh_dir / ".other.csv.tmp-zz.csv"  # another target's file is not ours to remove
    other.write_text("x")
    io.write_table("s.csv", {"a": np.arange(3.0)})
    assert not stale.exists() and other.exists()
    # A write that fails leaves nothing, and the old file stays whole.
    with pytest.raises(RuntimeError):
        with io.atomic_path("s.csv") as tmp:
            open(tmp, "w").write("partial")
            raise RuntimeError
    assert sorted(os.listdir(fresh_dir)) == [".other.csv.tmp-zz.csv", "s.csv"]
    assert io.read_table("s.csv")["a"].tolist() == [0.0, 1.0, 2.0]


@pytest.mark.slow
def test_kill_9_during_the_final_write_then_resume_leaves_no_temporary_file(tmp_path):
    """A real kill -9 while the table is being written (a hook sleeps inside the write), then --resume."""
    args = [
        sys.executable,
        "-c",
        "import time, coopjax.io as io, sys\n"
        "def slow(path, columns):\n"
        "    with io.atomic_path(path) as tmp:\n"
        "        open(tmp, 'w').write('partial'); print('writing', flush=True); time.sleep(60)\n"
        "import coopjax.cli.sweep as s; s.write_table = slow\n"
        "from coopjax.cli import main; sys.exit(main(sys.argv[1:]))",
        "sweep",
        *SMALL,
        *VARY,
        "--chunk",
        "2",
        "--out",
        "s.csv",
    ]
    proc = subprocess.Popen(args, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("writing"):
            break
    proc.kill()
    proc.wait()
    assert any(n.startswith(".s.csv.tmp-") for n in os.listdir(tmp_path))
    done = subprocess.run(
        [sys.executable, "-m", "coopjax.cli", "sweep", *SMALL, *VARY, "--chunk", "2", "--out", "s.csv", "--resume"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert sorted(os.listdir(tmp_path)) == ["s.csv"]


def test_csv_and_parquet_of_one_sweep_are_equal(fresh_dir):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("pyarrow")
    spec = sweeps.make_spec(
        "paper",
        n=6,
        vary={"K_GP": "choice:0.5,30,-3", "M_b": "loguniform:0.5:5"},
        T=0.3,
        seed=2,
        integrator="rk4",
        dt=2e-3,
    )
    table = sweeps.run(spec, chunk=6)
    assert len(set(table["status"])) >= 2  # strings and numbers both round-trip
    io.write_table("s.csv", table)
    io.write_table("s.PARQUET", table)  # the extension in any case
    assert open("s.PARQUET", "rb").read(4) == b"PAR1"
    csv, parquet = io.read_table("s.csv"), io.read_table("s.PARQUET")
    assert list(csv) == list(parquet) == list(table)
    for name in table:
        if table[name].dtype.kind in "fb":
            np.testing.assert_array_equal(csv[name], np.asarray(parquet[name], np.float64), err_msg=name)
            np.testing.assert_array_equal(csv[name], np.asarray(table[name], np.float64), err_msg=name)
        else:
            assert csv[name].tolist() == parquet[name].tolist() == table[name].tolist()
    assert pd.read_csv("s.csv")["peak_grip"].equals(pd.read_parquet("s.PARQUET")["peak_grip"])


def test_blown_up_and_unstable_samples_are_flagged_and_their_neighbours_stay_exact():
    """Paper scenario at dt = 3 ms: K_GP = 10 puts the step beyond the linearised limit (its run stays
    finite but means nothing), K_GP = 100 does too and blows up, K_GP = -3 makes the loop itself
    unstable. Table 1 (K_GP = 0.5) is fine, and its rows equal a single run."""
    spec = sweeps.make_spec(
        "paper", n=8, vary={"K_GP": "choice:0.5,10,-3,100"}, T=1.0, seed=0, integrator="rk4", dt=3e-3
    )
    table = sweeps.run(spec, chunk=8)
    expect = {0.5: "ok", 10.0: "step_beyond_limit", -3.0: "unstable_loop", 100.0: "step_beyond_limit"}
    for k, status in zip(table["K_GP"], table["status"]):
        assert status == expect[k], (k, status)
    assert set(table["K_GP"]) == set(expect)
    blew_up = np.isfinite(table["t_diverged"])
    assert blew_up[table["K_GP"] == 100].all() and not blew_up[np.isin(table["K_GP"], [0.5, 10])].any()
    assert (table["finite"] == ~blew_up).all()  # `finite` says the run did not diverge; `status` why it is flagged
    beyond = table["status"] == "step_beyond_limit"
    assert (table["dt_limit"][beyond] < 3e-3).all() and (table["dt_limit"][table["status"] == "ok"] >= 3e-3).all()
    single = cj.simulate(cj.make_params(K_GP=0.5), "paper", T=1.0, integrator="rk4", dt=3e-3).metrics
    ok = table["status"] == "ok"
    np.testing.assert_allclose(table["peak_grip"][ok], float(single.peak_grip), rtol=1e-12)


def test_help_and_readme_agree():
    """Every flag in `coopjax COMMAND --help` is in the README's synopsis for that command, and back."""
    readme = open(os.path.join(ROOT, "README.md")).read()
    block = readme.split("## Command line", 1)[1].split("```", 2)[1]
    synopsis = {}
    command = None
    for line in block.splitlines():
        m = re.match(r"coopjax ([a-z-]+)", line.strip())
        if m:
            command = m.group(1)
        if command:
            synopsis.setdefault(command, set()).update(re.findall(r"(--[A-Za-z0-9-]+)", line))
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(synopsis) == set(sub.choices)
    for name, p in sub.choices.items():
        flags = {s for a in p._actions for s in a.option_strings if s.startswith("--") and s != "--help"}
        assert flags == synopsis[name], (name, flags ^ synopsis[name])
    # The defaults the README quotes in `[--flag VALUE]` form are the parser's.
    for name, p in sub.choices.items():
        for a in p._actions:
            for s in a.option_strings:
                m = re.search(re.escape(s) + r" ([0-9][0-9.e-]*)\]", block)
                if m and isinstance(a.default, (int, float)) and not isinstance(a.default, bool):
                    assert float(m.group(1)) == float(a.default), (name, s, m.group(1), a.default)


def test_tune_pareto_without_cma_is_refused_before_any_work(fresh_dir, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "cma", None)  # as if it were not installed
    assert cli.main(["tune", "--pareto"]) == 2
    err = capsys.readouterr().err
    assert "CMA-ES" in err and "pip install" in err and err.count("\n") == 1, err
    assert list(fresh_dir.iterdir()) == []
