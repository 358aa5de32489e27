"""The shipped example problems, end to end at a small budget, and the optax script of docs/tuning.md.

Each example's verdict in tuned.json must be what a fresh judgement of the written parameters gives,
requirement by requirement, and a requirement that a held-out draw breaks must be reported broken,
with exit code 3 and its name on the last line."""

import glob
import io
import json
import os
import re
from contextlib import redirect_stdout

import numpy as np
import pytest

import tuning
from coopjax import cli
from tuning import judging as judgement
from tuning.problem import Problem

ROOT = os.path.join(os.path.dirname(__file__), "..")
EXAMPLES = sorted(glob.glob(os.path.join(ROOT, "docs", "problems", "*.toml")))
# The smallest run that still tunes, selects and judges: random search, one block of 8 candidates
# (values only: its programs are the cheapest to compile). screen-SLP and the gradient tuner on the
# same problems are measured in docs/tuning.md; their steps on any problem are tests/test_screen_slp.py's.
# The judge's step is doubled too (its two-step check then runs at 1e-3 s): the suite checks that the
# verdict is reported as judged, not the accuracy of the judge's step (tests/test_step_check.py).
SMALL = [
    *("--starts", "1", "--held-out", "2", "--quiet", "--judge-dt", "2e-3"),
    *("--method", "random search", "--generations", "1"),
]


def _path(name: str) -> str:
    return os.path.join(ROOT, "docs", "problems", name + ".toml")


def test_the_tests_run_every_shipped_example():
    assert [os.path.basename(p)[:-5] for p in EXAMPLES] == ["default", "paper_gains", "peak_bound", "robust_plant"]


def check(fresh_dir, capsys, name: str) -> dict:
    """`coopjax tune --problem` on an example, and its tuned.json against a fresh judgement."""
    path = _path(name)
    out_file = fresh_dir / f"{name}.json"
    code = cli.main(["tune", "--problem", path, *SMALL, "--out", str(out_file)])
    out = capsys.readouterr().out
    result = json.loads(out_file.read_text(), parse_constant=lambda c: pytest.fail(f"{c} is not standard JSON"))
    assert code == (0 if result["holds"] else 3), out
    assert (fresh_dir / f"{name}_history.png").stat().st_size > 10_000
    assert (fresh_dir / f"{name}_traces.png").stat().st_size > 10_000
    assert not (fresh_dir / f"{name}.json.ckpt").exists()
    assert result["judge"]["dt"] == 2e-3 and result["judge"]["integrator"] == "filippov"
    problem = Problem.from_toml(path)
    draws = np.column_stack([result["held_out_draws"][u.name] for u in problem.uncertain])
    # Without the two-step check: the requirements' values and verdicts do not depend on it.
    fresh = judgement.judge(result["params"], draws, problem, dt=2e-3, check_step=False)
    assert len(result["requirements"]) == len(problem.require) == len(fresh.requirements)
    nan = lambda x: np.nan if x is None else x  # tuned.json writes a NaN (not measured) as null
    for written, again in zip(result["requirements"], fresh.requirements):
        assert nan(written["worst"]) == pytest.approx(again["worst"], rel=1e-12, nan_ok=True), written
        assert written["met"] == again["met"] and written["bound_value"] == again["bound_value"]
        if not fresh.measured:  # a run did not finish: nothing is claimed, and nothing is met
            assert written["worst"] is None and not written["met"] and code == 3
            continue
        # The worst value is the worst of the per-case values on the requirement's scenarios; a
        # draw that breaks the bound makes the requirement broken.
        cases = [
            v
            for v, s in zip(fresh.per_case[written["metric"]], fresh.per_case["scenario"])
            if s in written["scenarios"]
        ]
        assert written["worst"] == pytest.approx(min(cases) if written["kind"] == "at_least" else max(cases), rel=1e-12)
        tolerance = written["tolerance"]
        broken = [
            v < written["bound_value"] - tolerance if written["kind"] == "at_least" else v > written["bound_value"]
            for v in cases
        ]
        assert written["met"] == (not any(broken)), written
        if not written["met"]:
            assert code == 3 and written["requirement"] in out.strip().splitlines()[-1], out
    assert nan(result["after"]["objective"]) == pytest.approx(fresh.objective, rel=1e-12, nan_ok=True)
    return result


@pytest.mark.slow  # the suite's time: tests/test_session.py runs the command end to end on a tiny problem
def test_the_default_example_runs_end_to_end(fresh_dir, capsys):
    result = check(fresh_dir, capsys, "default")
    assert result["trajectories"] == 8 * len(Problem.from_toml(_path("default")).training_draws())


@pytest.mark.slow  # the suite's time: tests/test_session.py runs the command end to end on a tiny problem
def test_the_peak_bound_example_runs_end_to_end(fresh_dir, capsys):
    # (robust_plant, with four uncertain parameters, and the two-scenario example run under -m slow.)
    for name in ("peak_bound",):
        result = check(fresh_dir, capsys, name)
        assert result["trajectories"] == 8 * len(Problem.from_toml(_path(name)).training_draws())
        if name == "peak_bound":  # the Python API's `tune` is the command's answer
            tuned = tuning.tune(
                Problem.from_toml(_path(name)), "random search", generations=1, starts=1, held_out=2, judge_dt=2e-3
            )
            assert tuned.params == result["params"]
            assert [r["met"] for r in tuned.verdict.requirements] == [r["met"] for r in result["requirements"]]
            written = result["after"]["objective"]  # null: not measured (NaN)
            assert tuned.verdict.objective == pytest.approx(np.nan if written is None else written, nan_ok=True)


@pytest.mark.slow  # the suite's time; the carry examples run the same pipeline end to end in CI
def test_the_robust_plant_example_runs_end_to_end(fresh_dir, capsys):
    check(fresh_dir, capsys, "robust_plant")


@pytest.mark.slow
def test_the_two_scenario_example_runs_end_to_end(fresh_dir, capsys):
    result = check(fresh_dir, capsys, "paper_gains")
    assert result["trajectories"] == 8 * 8 * 2  # 8 candidates x 8 draws x 2 scenarios
    assert {r["scenarios"] == ["carry", "paper"] for r in result["requirements"]} == {True}


@pytest.mark.slow  # compiles the hard model's gradient (25 s); its names and commands are checked in test_docs
def test_the_optax_script_of_the_docs_runs_and_prints_each_requirement():
    text = open(os.path.join(ROOT, "docs", "tuning.md")).read()
    section = text.split("## Tuning from Python", 1)[1]
    script = section.split("```python", 1)[1].split("```", 1)[0]
    assert "STEPS = 30" in script
    script = script.replace("STEPS = 30", "STEPS = 2")  # CI's size
    printed = io.StringIO()
    with redirect_stdout(printed):
        exec(compile(script, "docs/tuning.md", "exec"), {"__name__": "docs_example"})
    lines = printed.getvalue().strip().splitlines()
    assert len(lines) == 3, lines
    assert re.match(r"min_grip >= F_lim: worst .* N, margin .*, (met|MISSED)", lines[0]), lines
    assert re.match(r"peak_grip <= 40.0: worst .* N, margin .*, (met|MISSED)", lines[1]), lines
