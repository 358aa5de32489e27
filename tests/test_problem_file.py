"""Problem files: every bad file is one line naming the file, the key and its line, exit 2, nothing
written and nothing compiled; a good file reads back to the problem it was written from."""

import glob
import os
import subprocess
import sys

import numpy as np
import pytest

from coopjax import cli
from coopjax.errors import InputError
from tuning import design
from tuning.problem import Problem, Requirement

GOOD = """scenario = "carry"
tune = "gains"
[bounds]
tau = "0.1:2"
[fixed]
F_lim = 10.0
[uncertain]
M_b = "loguniform:0.5:5"
K_g = "loguniform:500:2000"
[[minimise]]
metric = "peak_grip"
over = "max"
weight = 1.0
[[minimise]]
metric = "rms_lag"
over = "cvar:0.5"
weight = 1500.0
[[require]]
metric = "min_grip"
at_least = "F_lim"
[[require]]
metric = "peak_grip"
at_most = 30.0
"""

# (name, the text changed, what the one line must name: the key and the line number)
BAD = [
    ("unknown key", GOOD.replace('tune = "gains"', 'tune = "gains"\nspeed = 3'), ["speed", "line 3", "unknown key"]),
    ("unknown metric", GOOD.replace('metric = "peak_grip"\nat_most', 'metric = "peek"\nat_most'), ["peek", "line 21"]),
    ("unknown parameter", GOOD.replace("F_lim = 10.0", "F_limit = 10.0"), ["F_limit", "line 6", "F_lim"]),
    ("both bounds", GOOD.replace("at_most = 30.0", "at_most = 30.0\nat_least = 5.0"), ["at_least", "line 24", "both"]),
    ("log bound not positive", GOOD.replace('tau = "0.1:2"', 'tau = "0:2"'), ["tau", "line 4", "0 < LOW"]),
    (
        "distribution typo",
        GOOD.replace('"loguniform:500:2000"', '"logunifrom:500:2000"'),
        ["K_g", "line 9", "logunifrom"],
    ),
    (
        "missing window",
        GOOD.replace('scenario = "carry"', 'scenario = ["carry", "paper"]'),
        ["rms_lag", "'lag'", "paper"],
    ),
    ("syntax error", GOOD.replace("weight = 1.0", "weight = = 1.0"), ["line 13", "not valid TOML"]),
    ("tuned and uncertain", GOOD.replace('K_g = "loguniform', 'K_GP = "loguniform'), ["K_GP", "line 9", "tuned"]),
    ("weight not a number", GOOD.replace("weight = 1.0", 'weight = "heavy"'), ["weight", "line 13"]),
]


def _file(tmp_path, text, name="problem.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_a_good_file_reads_back_from_what_it_writes(tmp_path):
    problem = Problem.from_toml(_file(tmp_path, GOOD))
    assert problem.names == ("K_GP", "K_GI", "tau", "G_e") and problem.box("tau") == (0.1, 2.0)
    assert problem.minimise[1].over == "cvar:0.5" and problem.minimise[1].weight == 1500.0
    assert problem.require[1] == Requirement("peak_grip", "at_most", 30.0)
    assert Problem.from_toml(_file(tmp_path, problem.to_toml(), "again.toml")) == problem
    # The default problem, written and read back, is the default problem.
    assert Problem.from_toml(_file(tmp_path, Problem().to_toml(), "default.toml")) == Problem()


@pytest.mark.parametrize("name, text, named", BAD, ids=[b[0] for b in BAD])
def test_a_bad_file_is_one_line_naming_the_file_the_key_and_the_line(tmp_path, capsys, name, text, named):
    path = _file(tmp_path, text)
    out = tmp_path / "tuned.json"
    code = cli.main(["tune", "--problem", path, "--out", str(out)])
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert path in lines[0], err
    for word in named:
        assert word in lines[0], (word, err)
    assert sorted(os.listdir(tmp_path)) == ["problem.toml"]  # nothing written


def test_a_flag_of_the_default_problem_contradicts_a_problem_file(tmp_path, capsys):
    path = _file(tmp_path, GOOD)
    for flag in (["--w-lag", "2"], ["--params", "gains"], ["--set", "F_lim=9"], ["--masses", "uniform:1:2"]):
        assert cli.main(["tune", "--problem", path, *flag]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and flag[0] in err[0] and "--problem" in err[0], err


def test_show_problem_prints_an_editable_file_and_compiles_nothing(tmp_path):
    # A fresh process, with JAX logging every compilation: there must be none.
    run = subprocess.run(
        [sys.executable, "-m", "coopjax.cli", "tune", "--show-problem", "--params", "gains", "--w-lag", "2000"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=os.environ | {"JAX_LOG_COMPILES": "1"},
    )
    assert run.returncode == 0 and "Compiling" not in run.stderr, run.stderr
    problem = Problem.from_toml(_file(tmp_path, run.stdout))
    # One unit per quantity: the flag's weight is the file's, N per m of lag.
    assert problem.names == ("K_GP", "K_GI", "tau", "G_e") and problem.minimise[1].weight == 2000.0
    assert os.listdir(tmp_path) == ["problem.toml"]


def test_every_shipped_example_problem_is_valid(tmp_path):
    files = sorted(glob.glob(os.path.join(os.path.dirname(__file__), "..", "docs", "problems", "*.toml")))
    assert len(files) >= 4
    for path in files:
        problem = Problem.from_toml(path)
        assert Problem.from_toml(_file(tmp_path, problem.to_toml())) == problem, path


def test_designs_are_disjoint_and_include_the_corners():
    one = Problem()
    several = Problem(
        uncertain=(design.uncertain("M_b", "loguniform:0.5:2"), design.uncertain("K_g", "uniform:500:2000"))
    )
    for problem in (one, several):
        train = np.concatenate([problem.training_draws(0, s) for s in range(3)] + [problem.fixed_training_draws()])
        validation, held_out = problem.validation_draws(), problem.held_out_draws()
        for a, b in ((train, validation), (train, held_out), (validation, held_out)):
            close = np.isclose(a[:, None, :], b[None, :, :], rtol=1e-9).all(-1)
            assert not close.any(), problem.uncertain
    corners = several.held_out_draws()[:4]
    assert sorted(map(tuple, corners)) == [(0.5, 500.0), (0.5, 2000.0), (2.0, 500.0), (2.0, 2000.0)]
    lo, hi = several.held_out_draws().min(0), several.held_out_draws().max(0)
    np.testing.assert_allclose([lo, hi], [[0.5, 500.0], [2.0, 2000.0]])


def test_problem_errors_without_a_file_name_the_field():
    with pytest.raises(InputError, match="uncertain: K_GP is tuned"):
        Problem(names=("K_GP",), uncertain=(("K_GP", "loguniform", 0.1, 1.0),)).validate()
    with pytest.raises(InputError, match="at least one objective term"):
        Problem(minimise=()).validate()
    with pytest.raises(InputError, match="its bound K_GP is tuned"):
        Problem(names=("K_GP",), require=(Requirement("peak_grip", "at_most", "K_GP"),)).validate()


def test_a_setting_declared_on_the_problem_is_a_file_key_a_flag_and_a_check(tmp_path):
    # `n_validation` is declared once, on `Problem`: the file's key, the flag and the check follow.
    from tuning import shorthands
    from tuning.cli import build_problem

    path = _file(tmp_path, 'tune = "gains"\n[[minimise]]\nmetric = "rms_lag"\n[training]\nn_validation = 5\n')
    problem = Problem.from_toml(path)
    assert problem.n_validation == 5 and len(problem.validation_draws()) == 5
    assert Problem.from_toml(_file(tmp_path, problem.to_toml())) == problem
    args = cli.build_parser().parse_args(["tune", "--validation-draws", "5", "--params", "gains"])
    assert build_problem(args).n_validation == 5
    assert "--validation-draws" in [flag for flag, _, _ in shorthands.flags()]
    with pytest.raises(InputError, match="n_validation is 1: at least 2"):
        Problem(n_validation=1).validate()
    with pytest.raises(InputError, match="n_validation is 'many': expected a whole number"):
        Problem(n_validation="many").validate()
