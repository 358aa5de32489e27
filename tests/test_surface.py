"""The problem-file and checkpoint surface, concurrent runs on one output, and verdict lines a reader
can trust: each mistake is one line naming the file, the key and the line, exit 2, nothing written."""

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from coopjax import cache, cli, io
from coopjax.errors import InputError
from tuning import driver, report
from tuning.design import Uncertain
from tuning.problem import Objective, Problem, Requirement

from test_problem_file import GOOD

ROOT = os.path.join(os.path.dirname(__file__), "..")


def one_line(capsys, code, *fragments):
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for fragment in fragments:
        assert fragment in err, err
    return err


@pytest.mark.parametrize(
    "text, fragments",
    [
        ('[training]\ndt = "abc"\n', ["dt is 'abc'", "line 2"]),
        ('[training]\ntemperature = "hot"\n', ["temperature is 'hot'", "line 2"]),
        ('[training]\ncvar_alpha = "x"\n', ["cvar_alpha is 'x'", "line 2"]),
        ('[[minimise]]\nmetric = "rms_lag"\nover = "cvar:abc"\n', ["cvar:abc", "line 1"]),
        ("[training]\nmargin = 50\n", ["margin is 50", "from 0 to 1", "line 2"]),
        ('[training]\njitter = "maybe"\n', ["jitter is 'maybe'", "true or false", "line 2"]),
        ("x = " + "[" * 5000 + "]" * 5000 + "\n", ["nested too deeply"]),
    ],
)
def test_a_wrong_type_or_shape_in_a_problem_file_is_one_line(fresh_dir, capsys, text, fragments):
    (fresh_dir / "p.toml").write_text(text)
    one_line(capsys, cli.main(["tune", "--problem", "p.toml", "--show-problem"]), "p.toml", *fragments)
    assert sorted(os.listdir(fresh_dir)) == ["p.toml"]


@pytest.mark.parametrize(
    "fields, fragment",
    [
        (dict(dt="1e-3"), "dt is '1e-3'"),
        (dict(temperature="hot"), "temperature is 'hot'"),
        (dict(cvar_alpha="x"), "cvar_alpha is 'x'"),
        (dict(minimise=[("rms_lag", "cvar:abc", 1.0)]), "cvar:abc"),
        (dict(minimise=[("rms_lag", "max", "x")]), "weight = 'x'"),
        (dict(margin=50), "margin is 50"),
        (dict(jitter="maybe"), "jitter is 'maybe'"),
        (dict(uncertain=[("M_b", "normal", 1.0, 2.0)]), "M_b"),
    ],
)
def test_the_python_api_raises_the_same_input_error(fields, fragment):
    with pytest.raises(InputError, match=fragment.replace("(", r"\(")):
        Problem(**fields).validate()


def test_a_fifo_or_a_huge_file_is_refused_at_once(fresh_dir, capsys):
    os.mkfifo(fresh_dir / "pipe.toml")
    done = []
    thread = threading.Thread(target=lambda: done.append(cli.main(["tune", "--problem", "pipe.toml"])), daemon=True)
    thread.start()
    thread.join(10)
    assert done, "reading a FIFO hung"
    one_line(capsys, done[0], "not a regular file")
    (fresh_dir / "big.toml").write_text("# " + "x" * (2 << 20) + "\n")
    one_line(capsys, cli.main(["tune", "--problem", "big.toml"]), "bytes")


def test_an_omitted_objective_is_stated(fresh_dir, capsys):
    (fresh_dir / "empty.toml").write_text("")
    assert cli.main(["tune", "--problem", "empty.toml", "--show-problem"]) == 0
    out = capsys.readouterr().out
    assert "states no [[minimise]]: the default is taken" in out and out.startswith("# note:")
    assert Problem.from_toml(str(fresh_dir / "empty.toml")) == Problem()


def _random_problem(rng) -> Problem:
    r = lambda lo, hi: float(np.exp(rng.uniform(np.log(lo), np.log(hi))) * (1 + rng.normal() * 1e-9))
    low = r(0.1, 2.0)
    return Problem(
        names=("K_GP", "K_GI", "tau", "G_e"),
        bounds=(("tau", r(0.01, 0.1), r(1.0, 10.0)),),
        fixed=(("F_lim", r(5.0, 20.0)),),
        uncertain=(
            Uncertain("M_b", "loguniform", low, low * r(1.5, 10)),
            Uncertain("K_g", "uniform", r(1, 500), 900.0),
        ),
        minimise=(Objective("peak_grip", "max", r(0.1, 10)), Objective("rms_lag", f"cvar:{r(0.05, 1.0)}", r(10, 1e4))),
        require=(Requirement("min_grip", "at_least", "F_lim"), Requirement("peak_grip", "at_most", r(20, 60))),
        n_draws=int(rng.integers(2, 30)),
        margin=r(0.001, 0.9),
        temperature=r(0.01, 5),
        cvar_alpha=min(1.0, r(0.01, 1.0)),
        dt=r(1e-4, 2e-3),
    ).validate()


def test_show_problem_round_trips_exactly_over_random_problems(tmp_path):
    rng = np.random.default_rng(0)
    for i in range(40):
        problem = _random_problem(rng)
        path = tmp_path / f"p{i}.toml"
        path.write_text(problem.to_toml())
        assert Problem.from_toml(str(path)) == problem, problem.to_toml()
    # The issue's own values: 6 significant digits used to change them.
    exact = Problem(
        names=("K_GP",), bounds=(("K_GP", 0.0123456789, 1.0),), uncertain=(("M_b", "loguniform", 0.50000001, 5.0),)
    )
    (tmp_path / "e.toml").write_text(exact.to_toml())
    assert Problem.from_toml(str(tmp_path / "e.toml")) == exact


def test_reading_a_problem_needs_no_global_jax_mode(tmp_path):
    (tmp_path / "p.toml").write_text(GOOD)
    code = "import tuning, sys; p = tuning.Problem.from_toml(sys.argv[1]); print(p.names)"
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    run = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "p.toml")], capture_output=True, text=True, env=env
    )
    assert run.returncode == 0 and "K_GP" in run.stdout, run.stderr


def _checkpoint(path, index):
    with open(path, "wb") as f:  # (a name would get .npz added)
        np.savez(f, index=np.array(json.dumps(index)))


@pytest.mark.parametrize("drop", ["format", "identity", "fingerprint", "entries", "clock"])
def test_a_checkpoint_whose_index_lacks_a_key_is_one_line(tmp_path, drop):
    index = {"kind": driver.CHECKPOINT_KIND, "format": driver.CHECKPOINT_FORMAT, "identity": {}, "fingerprint": ""}
    index |= {"entries": [], "clock": []}
    index.pop(drop)
    path = str(tmp_path / "t.json.ckpt")
    _checkpoint(path, index)
    with pytest.raises(InputError, match=f"lacks '{drop}'"):
        driver.load_checkpoint(path, {})


def test_a_second_run_on_an_output_another_live_run_holds_is_refused(fresh_dir, capsys):
    with io.one_run("tuned.json", "--out"):
        code = cli.main(["tune", "--out", "tuned.json"])
    one_line(capsys, code, "another coopjax run", str(os.getpid()))
    assert os.listdir(fresh_dir) == []  # the lock is gone with its run


def test_a_run_killed_with_9_leaves_no_lock_that_holds(fresh_dir):
    code = (
        "import time; from coopjax import io\n"
        "with io.one_run('tuned.json', '--out'):\n    print('held', flush=True); time.sleep(60)"
    )
    child = subprocess.Popen([sys.executable, "-c", code], cwd=fresh_dir, stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "held"
    with pytest.raises(InputError, match="another coopjax run"):
        with io.one_run(str(fresh_dir / "tuned.json"), "--out"):
            pass
    child.send_signal(signal.SIGKILL)
    child.wait()
    with io.one_run(str(fresh_dir / "tuned.json"), "--out"):  # the OS freed it
        pass
    assert os.listdir(fresh_dir) == []


def test_the_verdict_says_met_only_where_the_margin_clears_the_bound():
    row = lambda margin, met, tolerance=0.01: {"margin": margin, "met": met, "unit": "N", "tolerance": tolerance}
    assert report.verdict_text(row(-1.1e-6, True)).startswith("within tol.")
    assert report.verdict_text(row(0.5, True)).startswith("met")
    assert report.verdict_text(row(-0.5, False)).startswith("MISSED")
    assert report.verdict_text(row(float("nan"), False)) == "not measured"


def test_the_step_check_says_ok_only_within_its_tolerance(capsys):
    class V:  # a verdict's fields the table reads
        requirements, terms, worst, holds = [], [], {}, True
        objective = 1.0

        def __init__(self, error, artefact):
            self.step_error, self.step_artefact = error, artefact

    report.print_table(V(0.4, False), V(2.28, False), {"K_GP": 1.0}, {"K_GP": 1.0}, Problem(names=("K_GP",)))
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("dt/2 check"))
    assert "ok (0.40)" in line and "ok (2.28)" not in line and "over (2.28)" in line


def test_a_cache_entry_cut_short_by_a_failed_write_is_removed(tmp_path):
    (tmp_path / "kept-cache").write_bytes(b"a" * 10)
    cache.record(str(tmp_path))
    (tmp_path / "partial-cache").write_bytes(b"b" * 64)  # written in a run where a write failed
    cache.record(str(tmp_path), trust_new=False)
    assert sorted(os.listdir(tmp_path)) == [cache.SUMS, "kept-cache"]


def test_the_readme_states_its_machine_and_the_test_commands_time():
    text = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    test_part = text.split("**Test it**", 1)[1].split("## ", 1)[0]
    assert "idle" in text.split("**Test it**", 1)[0] and "idle" in test_part
    assert " min" in test_part


# --- the fault script: random mutations of a valid problem file and of a checkpoint ---------------


def _mutate(rng: random.Random, data: bytes) -> bytes:
    data = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        kind, at = rng.randrange(4), rng.randrange(max(1, len(data)))
        if kind == 0 and data:
            del data[at : at + rng.randint(1, 20)]
        elif kind == 1:
            data[at:at] = bytes(rng.choice(b'[]{}="#:.-0123456789abc\n\x00\xff') for _ in range(rng.randint(1, 8)))
        elif kind == 2 and data:
            data[at] = rng.randrange(256)
        else:
            data = data[: rng.randrange(len(data) + 1)]
    return bytes(data)


@pytest.mark.slow  # 30 fresh processes
def test_thirty_mutated_problem_files_each_give_one_line_or_a_correct_answer(tmp_path):
    rng, outcomes = random.Random(0), {"one line": 0, "read": 0}
    for i in range(30):
        path = tmp_path / f"m{i}.toml"
        path.write_bytes(_mutate(rng, GOOD.encode()))
        run = subprocess.run(
            [sys.executable, "-m", "coopjax.cli", "tune", "--problem", str(path), "--show-problem"],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )
        assert "Traceback" not in run.stderr, run.stderr
        if run.returncode == 0:  # a mutation that is still a problem: what it prints reads back to it
            (tmp_path / "back.toml").write_text(run.stdout)
            assert Problem.from_toml(str(tmp_path / "back.toml")) == Problem.from_toml(str(path))
            outcomes["read"] += 1
        else:
            assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
            outcomes["one line"] += 1
    print(outcomes)


def test_thirty_mutated_checkpoints_each_give_one_line_or_load(tmp_path):
    from test_tuning import PROBLEM, THETA, TUNER

    from tuning.tuners import Evaluation, Query

    ident = driver.identity(TUNER, PROBLEM, THETA, 0)
    q = Query(THETA, np.array([1.0, 2.0]), "gradient", "forward")
    e = Evaluation(*(np.ones((2, 2)),) * 6)
    path = str(tmp_path / "c.ckpt")
    driver.save_checkpoint(path, ident, [(q, e)], [(1.0, 8)])
    good = open(path, "rb").read()
    rng, outcomes = random.Random(1), {"one line": 0, "loaded": 0}
    start = time.perf_counter()
    for i in range(30):
        with open(path, "wb") as f:
            f.write(_mutate(rng, good))
        try:
            driver.load_checkpoint(path, ident)
            outcomes["loaded"] += 1
        except InputError as error:
            assert "\n" not in str(error)
            outcomes["one line"] += 1
    assert time.perf_counter() - start < 30
    assert sum(outcomes.values()) == 30
