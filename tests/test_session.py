"""One tuning session behind every front end: `coopjax tune`, `tuning.tune`, the race and the Pareto
study give the same answer on a small problem (the last two under -m slow); the session's checks are
the command's; a tuner's state is never changed in place."""

import copy
import dataclasses
import json
import pickle

import numpy as np
import pytest

import tuning
from coopjax import cli
from coopjax.errors import InputError
from tuning import driver, session
from tuning.judging import missed_at
from tuning.problem import GAINS, Problem, Requirement
from tuning.studies import pareto, race
from tuning.tuners import TUNERS, Evaluation

# The smallest problem that still trains, selects and judges; random search for one block is the
# cheapest tuner that ends on its own.
PROBLEM = Problem(
    names=GAINS, n_draws=2, n_validation=4, uncertain=(("M_b", "loguniform", 0.8, 4.5),), margin=0.0, jitter=False
)
OPTIONS = session.Options(starts=2, held_out=2, judge_dt=2e-3)
SETTINGS = {"generations": 1}
FLAGS = (
    "--params gains --masses loguniform:0.8:4.5 --train-masses 2 --validation-draws 4 --margin 0 --fixed-masses "
    "--starts 2 --held-out 2 --judge-dt 2e-3 --method random-search --generations 1 --quiet"
).split()


def test_the_command_and_the_api_give_the_same_answer(fresh_dir, capsys):
    tuned = tuning.tune(PROBLEM, "random search", options=OPTIONS, **SETTINGS)
    flags = [f if f != "random-search" else "random search" for f in FLAGS]
    code = cli.main(["tune", *flags, "--out", "t.json"])
    written = json.loads((fresh_dir / "t.json").read_text())
    assert code == (0 if written["holds"] else 3), capsys.readouterr()
    # What the command wrote is what a fresh judgement of the same parameters gives.
    assert written["params"] == tuned.params
    assert written["after"]["objective"] == pytest.approx(tuned.verdict.objective, rel=1e-12)
    assert [r["met"] for r in written["requirements"]] == [r["met"] for r in tuned.verdict.requirements]
    assert (fresh_dir / "t_history.png").stat().st_size > 10_000 and (fresh_dir / "t_traces.png").exists()
    assert sorted(p.name for p in fresh_dir.iterdir()) == ["t.json", "t_history.png", "t_traces.png"]


@pytest.mark.slow  # two more sessions (16 s of the suite's CPU); the command and the API are compared above
def test_the_race_and_the_pareto_study_give_the_apis_answer():
    tuned = tuning.tune(PROBLEM, "random search", options=OPTIONS, **SETTINGS)
    prepared = session.prepare(PROBLEM, TUNERS["random search"](**SETTINGS), OPTIONS)
    raced = race.run({"random search": prepared}, "random search", [OPTIONS.seed], log=lambda s: None)
    front = pareto.run({"random search": prepared}, "random search", [PROBLEM.minimise[-1].weight], log=lambda s: None)
    assert raced["per_seed"][0]["chosen"]["random search"] == tuned.params
    assert next(r["params"] for r in front["pareto"] if r["kind"] == "front") == tuned.params


def test_the_spread_reaches_the_screen_from_every_front_end():
    tuner = TUNERS["screen-SLP"]()
    prepared = session.prepare(PROBLEM, tuner, dataclasses.replace(OPTIONS, spread=0.7))
    assert prepared.tuner.spread == 0.7  # the starts' box and the screen's are one setting
    assert session.prepare(PROBLEM, tuner, OPTIONS).tuner.spread == OPTIONS.spread
    parser = cli.build_parser()
    args = parser.parse_args(["tune", "--spread", "0.7"])
    from tuning import cli as tune_cli

    assert session.with_spread(tune_cli.make_tuner(args), args.spread).spread == 0.7


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(starts=0), "starts"),
        (dict(seed=-1), "seed"),
        (dict(held_out=1), "held_out"),
        (dict(judge_dt=0.05), None),  # beyond filippov's stability limit for the first start
        (dict(judge_dt="1e-3"), "judge_dt"),
    ],
)
def test_prepare_checks_what_the_command_checked_and_names_the_field(change, field):
    with pytest.raises(InputError) as error:
        session.prepare(PROBLEM, TUNERS["random search"](**SETTINGS), dataclasses.replace(OPTIONS, **change))
    if field:
        assert error.value.field == field and str(error.value).startswith(field)


def test_a_tuner_that_never_ends_needs_a_budget_and_too_large_a_batch_is_refused():
    with pytest.raises(InputError, match="budget"):
        session.prepare(PROBLEM, TUNERS["CMA-ES"](), OPTIONS)
    with pytest.raises(InputError, match="more than half of this machine's memory"):
        session.prepare(dataclasses.replace(PROBLEM, n_draws=10**8), TUNERS["screen-SLP"](local=10**4), OPTIONS)


def _fake_evaluation(query, rng):
    C, M = len(query.thetas), len(np.atleast_1d(query.draws))
    holds = rng.random(C) < 0.5
    parts = rng.random((C, 2 * M))
    return Evaluation(
        f=parts.sum(1),
        c=rng.normal(size=(C, M)),
        parts=parts,
        valid=np.ones(C, bool),
        holds=holds,
        min_swi=rng.random((C, M)),
        jacobian=None
        if query.derivative != "jacobian"
        else {
            "f": rng.normal(size=(C, query.thetas.shape[1])),
            "c": rng.normal(size=(C, M, query.thetas.shape[1])),
            "parts": rng.normal(size=(C, 2 * M, query.thetas.shape[1])),
            "min_swi": rng.normal(size=(C, M, query.thetas.shape[1])),
        },
        value=None if query.derivative != "gradient" else parts.sum(1),
        gradient=None if query.derivative != "gradient" else rng.normal(size=query.thetas.shape),
    )


@pytest.mark.parametrize("name", sorted(TUNERS))
def test_no_tuner_changes_a_state_it_returned(name):
    """Tell every tuner made-up evaluations; a frozen copy of each state it returned must still equal
    the state after the later tells, and telling the copy again goes on as the run went."""
    settings = {"random search": SETTINGS, "screen-SLP": {"screen": 8, "local": 2, "steps": 2}}.get(name, {})
    tuner = TUNERS[name](**settings)
    rng = np.random.default_rng(0)
    starts = np.log([[0.054, 0.078, 2.93, 1224.0], [0.5, 0.1, 1.25, 600.0]])
    state = tuner.init(PROBLEM, starts, 0)
    kept = []
    for _ in range(6):
        query = tuner.ask(state)
        if query is None:
            break
        frozen = pickle.dumps(state)
        evaluation = _fake_evaluation(query, rng)
        new = tuner.tell(state, query, evaluation)
        kept.append((frozen, state, query, evaluation, new))
        state = new
    for frozen, before, query, evaluation, after in kept:
        assert pickle.dumps(before) == frozen, f"{name} changed a state it had returned"
        # Told again from the frozen copy, it goes on as it went (what it asks next, what it would hand over).
        again = tuner.tell(copy.deepcopy(pickle.loads(frozen)), query, evaluation)
        _same_query(tuner.ask(again), tuner.ask(after), name)
        assert all(np.array_equal(a, b) for a, b in zip(tuner.candidates(again), tuner.candidates(after))), name


def _same_query(a, b, name):
    assert (a is None) == (b is None), name
    if a is not None:
        assert np.array_equal(a.thetas, b.thetas) and np.array_equal(a.draws, b.draws), name
        assert a.derivative == b.derivative, name


def test_no_module_of_tuning_but_the_command_may_import_argparse():
    """The import contract names every module of `tuning` but the command (a new module is not
    exempt by being missed); `lint-imports` (tests/test_transforms.py) enforces it."""
    import os
    import pkgutil
    import tomllib

    root = os.path.join(os.path.dirname(__file__), "..")
    with open(os.path.join(root, "pyproject.toml"), "rb") as f:
        contracts = tomllib.load(f)["tool"]["importlinter"]["contracts"]
    contract = next(c for c in contracts if "argparse" in c.get("forbidden_modules", []))
    modules = {f"tuning.{m.name}" for m in pkgutil.iter_modules(tuning.__path__)}
    assert set(contract["source_modules"]) == modules - {"tuning.cli"}


@pytest.mark.slow  # a second entrant's runs: the plain study's path is the same-answer test's
def test_the_pareto_study_gives_a_tuner_that_ends_only_by_a_budget_the_plans_time():
    prepared = session.prepare(PROBLEM, TUNERS["random search"](**SETTINGS), OPTIONS)
    others = session.prepare(PROBLEM, TUNERS["CMA-ES"](), OPTIONS, None, tuning.Budget(1))
    weights = [PROBLEM.minimise[-1].weight / 2, PROBLEM.minimise[-1].weight]
    result = pareto.run({"random search": prepared, "CMA-ES": others}, "random search", weights, log=lambda s: None)
    front = [(r["tuner"], r["weight"]) for r in result["pareto"] if r["kind"] == "front"]
    assert front == [(t, w) for w in weights for t in ("random search", "CMA-ES")]


@pytest.mark.slow  # 40 s, most of it compiling a program per step; `polish_afresh` is tested in CI (test_screen_slp)
def test_where_no_answer_holds_and_it_sits_on_the_steps_limit_a_new_polish_runs_at_half_the_step(monkeypatch):
    """A peak bound no gain set meets. Where the chosen answer's loop sits on the training step's
    limit (`step_edge`, made 1 here), rounds of a new polish run at half the step, then a quarter,
    each trained at that step, while each round's best wins on validation; an answer off the limit,
    or `halvings=0`, runs none."""
    problem = dataclasses.replace(PROBLEM, require=PROBLEM.require + (Requirement("peak_grip", "at_most", 1.0),))
    tuner = TUNERS["screen-SLP"](screen=0, local=1, radii=2, steps=1, polish=2, jacobian="fd")
    options = dataclasses.replace(OPTIONS, further=0, again=0, halvings=2)
    trained_at, run = [], driver.run

    def recorded(tuner, trained, *args, **kwargs):
        trained_at.append(trained.train_dt)
        return run(tuner, trained, *args, **kwargs)

    monkeypatch.setattr(driver, "run", recorded)
    monkeypatch.setattr(session, "step_edge", lambda *args: 2.0)
    off = session.run(session.prepare(problem, tuner, options))
    assert off.selection["finer"] == [] and trained_at == [problem.train_dt]
    monkeypatch.setattr(session, "step_edge", lambda *args: 1.0)
    none = session.run(session.prepare(problem, tuner, dataclasses.replace(options, halvings=0)))
    assert none.selection["finer"] == [] and none.params == off.params
    trained_at.clear()
    on = session.run(session.prepare(problem, tuner, options))
    rounds = on.selection["finer"]
    assert not on.validation.holds and 1 <= len(rounds) <= 2
    assert [r["dt"] for r in rounds] == [problem.train_dt / 2, problem.train_dt / 4][: len(rounds)]
    assert trained_at == [problem.train_dt] + [r["dt"] for r in rounds]  # each round trained at its step
    kept = [r["kept"] == session.LONGER for r in rounds]
    assert all(kept[:-1]) and (on.params != off.params) == any(kept)
    assert on.validation.violation <= off.validation.violation


@pytest.mark.slow  # 30 s, most of it compiling; the round's parts are tested in CI (test_screen_slp, test_judging)
def test_an_answer_that_misses_goes_on_with_the_draws_where_it_misses_most():
    """A peak bound no gain set meets, and validation on two bodies alone: the judge finds
    the answer missing more than validation did, and the session goes on from it with the draw
    where it misses most (among the held-out draws and those found between them) added to
    training; without `again`, no round."""
    problem = dataclasses.replace(
        PROBLEM, require=PROBLEM.require + (Requirement("peak_grip", "at_most", 1.0),), n_validation=2
    )
    tuner = TUNERS["screen-SLP"](screen=0, local=1, radii=2, steps=1, polish=1, polish_again=2, jacobian="fd")
    before = session.run(session.prepare(problem, tuner, dataclasses.replace(OPTIONS, again=0)))
    assert not before.verdict.holds and before.selection["again"] == []
    assert before.verdict.violation > before.validation.violation
    judged = np.asarray(before.verdict.per_case["M_b"])[:, None]  # the held-out draws, then those found
    after = session.run(session.prepare(problem, tuner, OPTIONS))
    rounds = after.selection["again"]
    assert 1 <= len(rounds) <= 2
    assert rounds[0]["added"]["M_b"] == missed_at(before.verdict, judged)[:, 0].tolist()
    assert after.result.evaluations == before.result.evaluations + tuner.polish_again * len(rounds)
    kept_new = [r["kept"] == "the new polish's best" for r in rounds]
    assert (after.params != before.params) == any(kept_new)
    assert "step_error" not in after.selection["validation"]  # selection runs no two-step check


@pytest.mark.slow  # 30 s, most of it compiling; the polish's going on is tested in CI (test_screen_slp)
def test_the_polish_goes_on_from_the_chosen_answer_while_it_wins_on_validation():
    """With `further`, the polish goes on from the chosen answer (its best or a local solve's), round by round,
    and each round's best replaces it only where the validation draws prefer it; the rounds stop
    at the first that loses, and without `further` there is none."""
    tuner = TUNERS["screen-SLP"](screen=0, local=1, radii=2, steps=1, polish=4, jacobian="fd")
    problem = dataclasses.replace(PROBLEM, n_validation=48)
    before = session.run(session.prepare(problem, tuner, dataclasses.replace(OPTIONS, further=0)))
    assert before.selection["further"] == []
    after = session.run(session.prepare(problem, tuner, dataclasses.replace(OPTIONS, further=2)))
    rounds = after.selection["further"]
    # Here one won and the next lost: on the validation draws, or with nothing better on the training
    # draws to offer them (which of the two follows the last bits of the runs).
    assert [r["kept"] for r in rounds][0] == session.LONGER and len(rounds) == 2
    assert rounds[1]["kept"] in ("the answer before", "nothing better on the training draws")
    assert after.result.evaluations == before.result.evaluations + tuner.polish * len(rounds)
    kept = [r["kept"] == session.LONGER for r in rounds]
    assert all(kept[:-1])  # a round that loses is the last
    for r, k in zip(rounds, kept):
        if r.get("violation") == [0.0, 0.0]:  # both hold: the lower objective is kept
            assert (r["objective"][1] < r["objective"][0]) == k
    assert (after.params != before.params) == any(kept)
    assert after.validation.objective <= before.validation.objective
