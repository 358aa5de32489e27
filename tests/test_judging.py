"""The judge (tuning.judging) on the cases a search is drawn to: a run beyond the judge's step limit,
a run that diverges, a worst case that lies between the judged draws."""

import dataclasses

import numpy as np
import pytest

import coopjax as cj
from coopjax.stability import stable_dt
from coopjax.step_check import TOLERANCE
from tuning import design
from tuning import judging as judgement
from tuning.problem import Problem, Requirement

# Table 1's gains on a gripper four times as damped: its linearised loop needs dt <= 9.96e-4 s,
# just below the judge's 1e-3.
STIFF = Problem(names=("K_GP",), fixed=(("R_g", 400.0),))
TABLE1 = {"K_GP": 0.5}


@pytest.mark.slow  # two runs at 1.25e-4 and 6.25e-5 s (64,000 steps); the refinement itself is in CI (below)
def test_a_run_beyond_the_judges_step_limit_gets_the_limits_values():
    params = cj.make_params(dtype="float64", M_b=np.array([1.0]), R_g=400.0)
    assert stable_dt(params, judgement.judge_config())[0][0] < judgement.JUDGE_DT  # the premise
    v = judgement.judge(TABLE1, [1.0], STIFF, check_step=True)
    assert v.measured and v.unmeasured == 0.0
    assert v.per_case["status"] == ["ok"] and v.per_case["dt"] == [judgement.JUDGE_DT / 2]
    # The dt -> 0 limit, from two finer steps that agree: the judge's values are within tolerances.
    fine = [cj.simulate(params, "carry", dt=dt, check_dt=False).metrics for dt in (1.25e-4, 6.25e-5)]
    for name, (kind, tol) in TOLERANCE.items():
        a, b = (float(np.asarray(getattr(m, name))[0]) for m in fine)
        judged = v.per_case[name][0]
        scale = 1.0 if kind == "absolute" else abs(b)
        assert abs(a - b) < 0.1 * tol * scale, name  # the limit, two ways
        assert abs(judged - b) < tol * scale, name


def test_without_refinement_the_same_run_is_beyond_its_limit():
    config = judgement.judge_config(metrics=("peak_grip",))
    params = cj.make_params(dtype="float64", M_b=np.array([1.0]), R_g=400.0)
    from coopjax import devices, evaluation

    plain = evaluation.evaluate(params, config)
    assert plain["status"].tolist() == [3.0]  # Status.STEP_BEYOND_LIMIT
    # Checked and refined, the sliding-mode step runs dt, dt / 2 and dt / 4 in one program (the step
    # traced): the judge's first answer compiles it once.
    devices._compiled.cache_clear()
    refined = evaluation.evaluate(params, config, check_step=True, refine=2)
    assert refined["status"].tolist() == [0.0] and refined["dt"].tolist() == [5e-4]
    assert np.isfinite(refined["peak_grip"]).all() and refined["step_error"][0] < 1
    assert devices._compiled.cache_info().currsize == 1
    # The judge's unchecked runs (selection, the search between draws) join that program, and their
    # values are the checked run's to round-off.
    unchecked = evaluation.evaluate(params, config, refine=2, shared=True)
    assert devices._compiled.cache_info().currsize == 1
    np.testing.assert_allclose(unchecked["peak_grip"], refined["peak_grip"], rtol=1e-11)
    assert unchecked["dt"].tolist() == [5e-4]


@pytest.mark.slow  # K_GP = 20 is refined to dt/16 before it counts as diverged: four more programs
def test_a_diverging_candidate_orders_below_every_measured_one():
    problem = Problem(names=("K_GP",), require=(Requirement("peak_grip", "at_most", 12.0),))
    # K_GP = 20 diverges at every refined step the judge tries; Table 1's 0.5 runs and misses the
    # (tight) peak bound: a measured miss.
    verdicts = judgement.judge([{"K_GP": 20.0}, TABLE1], [1.0, 4.0], problem, check_step=False)
    diverged, missed = verdicts
    assert not diverged.measured and diverged.unmeasured > 0
    assert np.isfinite(diverged.unmeasured) and np.isfinite(diverged.violation)
    assert missed.measured and missed.unmeasured == 0 and missed.violation > 0 and not missed.holds
    assert judgement.preferred(verdicts) == 1  # a measured miss beats a run that did not finish
    assert judgement.preferred(verdicts[::-1]) == 0
    assert missed.binding["metric"] == "peak_grip"


@pytest.mark.slow  # 7 judgings and a dense scan of 65 draws
def test_a_worst_draw_between_grid_points_is_found():
    # Table 1's peak grip over light bodies has a bump near 0.63 kg, between the grid's points.
    problem = Problem(names=("K_GP",), uncertain=(("M_b", "loguniform", 0.56, 0.72),))
    grid = design.held_out(problem.uncertain, 4)  # 0.56, 0.605, 0.666, 0.72 kg
    v = judgement.judge(TABLE1, grid, problem, check_step=False)
    found = judgement.worst_case(TABLE1, grid, problem, verdict=v, rounds=6)
    # Targets: the grip requirement, the peak term, the lag term. The peak's worst between the grid
    # points is worse than every grid point's, and a dense scan agrees where it is.
    peak_at = found[1]
    w = judgement.judge(TABLE1, found, problem, check_step=False)
    assert w.per_case["peak_grip"][1] > max(v.per_case["peak_grip"])
    dense = design.dense(problem.uncertain, 65)
    scan = judgement.judge(TABLE1, dense, problem, check_step=False).per_case["peak_grip"]
    assert w.per_case["peak_grip"][1] >= max(scan) - 0.02 * max(scan)
    assert not np.isclose(grid[:, 0], peak_at[0]).any()
    # The draw a round that goes on adds to training: where each missed requirement misses most.
    assert judgement.missed_at(v, grid).shape == (0, 1)  # the grip holds on this box
    bound = Requirement("peak_grip", "at_most", float(np.median(v.per_case["peak_grip"])))
    strict = dataclasses.replace(problem, require=problem.require + (bound,))
    both = np.concatenate([grid, found])
    missed = judgement.judge(TABLE1, both, strict, check_step=False)
    assert np.array_equal(judgement.missed_at(missed, both), both[[np.argmax(missed.per_case["peak_grip"])]])


def test_the_draws_a_round_adds_are_where_each_missed_requirement_misses_most():
    """`missed_at` on two scenarios and three draws: the least grip over the scenarios, a run that
    did not finish counts as the worst, and a requirement that is met adds nothing."""
    draws = np.array([[1.0], [2.0], [4.0]])
    requirement = lambda metric, kind, met: {
        "metric": metric,
        "kind": kind,
        "met": met,
        "scenarios": ["carry", "paper"],
    }
    verdict = lambda grip, status: judgement.Verdict(
        objective=0.0,
        terms=[],
        requirements=[requirement("min_grip", "at_least", False), requirement("peak_grip", "at_most", True)],
        worst={},
        finite=True,
        measured=True,
        holds=False,
        unmeasured=0.0,
        step_error=float("nan"),
        step_artefact=False,
        per_case={
            "min_grip": grip,
            "peak_grip": [30.0, 60.0, 20.0, 20.0, 20.0, 20.0],  # the largest at 2 kg, but met
            "status": status,
            "scenario": ["carry"] * 3 + ["paper"] * 3,
            "dt": [1e-3] * 6,
        },
    )
    ok = ["ok"] * 6
    assert judgement.missed_at(verdict([9.0, 9.5, 9.8, 9.9, 9.9, 8.0], ok), draws).tolist() == [[4.0]]
    assert judgement.missed_at(
        verdict([9.0, 9.5, 9.8, 9.9, 9.9, 8.0], ok[:1] + ["diverged"] + ok[2:]), draws
    ).tolist() == [[2.0]]


@pytest.mark.parametrize("status", ["diverged", "step_beyond_limit", "unstable_loop"])
def test_every_unmeasured_case_has_a_finite_badness_of_at_least_one(status):
    from coopjax.status import Status

    code = np.array([Status[status.upper()]])
    badness = judgement._badness(code, np.array([1.0]), np.array([4.0]), np.array([3.0]))
    assert np.isfinite(badness).all() and badness[0] >= 1.0
    assert judgement._badness(np.array([Status.OK]), np.array([np.nan]), np.array([4.0]), np.array([0.5]))[0] == 0


def test_training_prices_a_candidate_beyond_its_step_limit_above_every_measured_one():
    from tuning.evaluate import Evaluator
    from tuning.tuners import Query

    problem = Problem(names=("K_GP",))
    # K_GP = 3: the loop needs dt <= 8.2e-4 s at 1 kg, beyond the training step (2e-3 s).
    thetas = np.log([[0.5], [3.0]])
    ev = Evaluator(problem, None)(Query(thetas, np.array([[1.0], [2.0]])))
    assert ev.valid.tolist() == [True, False]
    assert ev.unmeasured[0] == 0 and 1.0 <= ev.unmeasured[1] < np.inf
    bad = ev.bad(1e6)
    assert np.isfinite(bad).all() and bad[1] > 1e6 > ev.f[0]


def test_the_training_step_is_halved_where_the_starts_box_cannot_be_measured():
    """A wide box of masses and gripper damping (R_g down to 30 N s/m): at the carry's default step
    every point of the starts' box is beyond its loop's limit at some training draw, so every
    candidate would be unmeasured; the session trains at a step where some of the box is measured,
    and says so. The default problem keeps its step, and so does a step the user sets."""
    import dataclasses

    from coopjax.stability import stable_dt
    from tuning.design import uncertain
    from tuning.training import LEAST_MEASURED, PROBES, measurable_step, params_for
    from tuning.problem import to_log

    wide = Problem(
        names=("K_GP", "G_e"), uncertain=(uncertain("M_b", "loguniform:0.3:8"), uncertain("R_g", "uniform:30:200"))
    )
    base = wide.base()
    first = {n: float(np.asarray(base.get(n)).ravel()[0]) for n in wide.names}
    rng = np.random.default_rng(1)  # as many as the session probes: one compiled linearisation
    probes = to_log(first, wide.names) + rng.uniform(-2.5, 2.5, (PROBES + 1, 2))

    def measured(p):  # the share of random points of the box within the limit at every draw
        prm = params_for(base, p, np.asarray(probes), p.fixed_training_draws())
        limit = np.min([np.asarray(stable_dt(prm, c)[0]) for c in p.configs], axis=0).reshape(len(probes), -1)
        return (limit.min(1) >= p.train_dt).mean()

    assert measured(wide) < LEAST_MEASURED  # the premise: nothing to train on at the default step
    slower, note = measurable_step(wide, base, first, 2.5)
    assert slower.train_dt < wide.train_dt <= 4 * slower.train_dt
    assert measured(slower) > LEAST_MEASURED and f"training runs at {slower.train_dt:g} s" in note
    default = Problem(names=("K_GP", "G_e"))
    assert measurable_step(default, base, first, 2.5) == (default, None)
    given = dataclasses.replace(wide, dt=wide.train_dt)
    assert measurable_step(given, base, first, 2.5) == (given, None)


def test_the_tuners_violation_is_the_judges_measure():
    """`Terms.miss` (what the polish minimises where nothing holds) is `Verdict.violation`'s measure:
    a relative miss beyond the tolerance, the grip's from min_grip."""
    from tuning.problem import Requirement
    from tuning.training import requirement_values

    peak = Requirement("peak_grip", "at_most", 8.0)
    grip = Requirement("min_grip", "at_least", "F_lim")
    _, met, miss = requirement_values(peak, {"peak_grip": np.array([12.0, 6.0])}, 8.0)
    assert met.tolist() == [False, True] and np.allclose(miss, [0.5, -0.25])
    slip = np.array([0.0, 4.0])
    _, met, miss = requirement_values(grip, {"min_grip": np.array([10.0, 7.5])}, 10.0, slip)
    assert met.tolist() == [True, False] and np.allclose(miss, [-0.001, 0.249])


def test_training_values_run_in_the_judges_program(monkeypatch):
    """The training step (2e-3 s on the carry) lies on the judge's grid, so the tuner's value runs
    use the program the judge runs at 1e-3 and 5e-4 s (the step traced): judging the same draws
    afterwards compiles no run program, and the values are those of the training step's own program
    to round-off."""
    from coopjax import devices
    from tuning import evaluate
    from tuning.tuners import Query

    problem = Problem(names=("K_GP", "G_e"))
    thetas, draws = np.log([[0.5, 600.0], [0.3, 900.0]]), np.array([[1.0], [3.0]])
    devices._compiled.cache_clear()
    shared = evaluate.Evaluator(problem, None)(Query(thetas, draws))
    programs = devices._compiled.cache_info().currsize
    judgement.judge({"K_GP": 0.3, "G_e": 900.0}, draws, problem)  # checked at dt / 2
    assert devices._compiled.cache_info().currsize == programs
    monkeypatch.setattr(evaluate, "_judged", lambda problem, config: None)
    own = evaluate.Evaluator(problem, None)(Query(thetas, draws))  # the training step's own program
    assert shared.valid.all() and own.valid.all()
    np.testing.assert_allclose(shared.f, own.f, rtol=1e-11)
    np.testing.assert_allclose(shared.c, own.c, rtol=1e-11, atol=1e-11)


def test_the_shared_programs_grid_makes_every_step_exactly():
    """Steps of the judge's grid (the carry's converged 2 ms, the paper's 1 ms) share its program;
    each is grid / r bit for bit, r a power of two; a step off the grid keeps its own."""
    from coopjax import evaluation

    for scenario, dt, grid, r in [
        ("carry", 2e-3, 2e-3, 1),
        ("carry", 1e-3, 2e-3, 2),
        ("carry", 6.25e-5, 2e-3, 32),
        ("paper", 1e-3, 1e-3, 1),
        ("paper", 5e-4, 1e-3, 2),
    ]:
        config = judgement.judge_config(dt, scenario)
        assert evaluation.grid(config) == (grid, r)
        assert grid / r == dt
    assert evaluation.grid(judgement.judge_config(1.5e-3, "carry"))[1] == 1
