"""CMA-ES with polished, injected candidates: on the minimax problem with a known answer (analytic
evaluator, no simulation), the polish lands on the kink where three pieces are active, its points
enter CMA-ES's population, and a resumed run replays to the same state."""

import numpy as np
import pytest
from test_screen_slp import CB2_AT, CB2_MIN, Analytic, cb2, solve

from tuning import driver
from tuning.tuners.cma_slp import CMAESPolished

STARTS = [[2.0, 2.0], [0.0, -1.0]]


class Recording(Analytic):
    """Analytic, keeping every query."""

    def __init__(self):
        super().__init__()
        self.queries = []

    def __call__(self, query):
        self.queries.append(query)
        return super().__call__(query)


def test_the_polish_finds_the_minimax_optimum_and_cma_es_samples_it():
    evaluator = Recording()
    tuner = CMAESPolished(every=2, polish=3)
    result = solve(tuner, STARTS, evaluator, budget=driver.Budget(trajectories=3000))
    best = result.tuner.candidates(result.state)[0]  # the polished point comes first
    assert np.allclose(best, CB2_AT, atol=1e-4)
    assert cb2(best)[0].max() == pytest.approx(CB2_MIN, abs=1e-6)
    # Polished points (trial steps of the linear programs, never CMA-ES samples) lead CMA-ES's
    # later generations: they were injected.
    queries = evaluator.queries
    trials = [row for before, q in zip(queries, queries[1:]) if before.derivative == "jacobian" for row in q.thetas]
    generations = [
        q.thetas for before, q in zip(queries, queries[1:]) if q.derivative is None and before.derivative is None
    ]  # a generation follows a generation or a trial
    led = sum(any(np.array_equal(g[0], t) for t in trials) for g in generations)
    assert len(trials) >= 12 and led >= 3


def test_resume_replays_to_the_same_state(tmp_path):
    tuner = CMAESPolished(every=2, polish=2)
    budget = driver.Budget(trajectories=600)
    whole = solve(tuner, STARTS, Analytic(), budget=budget)
    path = str(tmp_path / "run.ckpt")
    solve(tuner, STARTS, Analytic(), recorder=driver.Checkpoint(path), budget=driver.Budget(trajectories=250))
    resumed = solve(tuner, STARTS, Analytic(), recorder=driver.Checkpoint(path, resume=True), budget=budget)
    assert resumed.evaluations == whole.evaluations
    assert resumed.state.history == whole.state.history
    for a, b in zip(resumed.tuner.candidates(resumed.state), whole.tuner.candidates(whole.state)):
        np.testing.assert_array_equal(a, b)


def test_a_tuner_that_does_not_end_on_its_own_is_refused_without_a_budget():
    """--pareto and --compare never hang: every tuner either ends on its own or runs on a budget,
    and the driver refuses the third case before the first evaluation."""
    from coopjax.errors import InputError
    from tuning.tuners import TUNERS

    for name, cls in TUNERS.items():
        tuner = cls()
        if tuner.ends():
            continue
        evaluator = Recording()
        with pytest.raises(InputError, match="does not end on its own"):
            solve(tuner, STARTS, evaluator)
        assert evaluator.queries == []
        assert solve(tuner, STARTS, Analytic(), budget=driver.Budget(trajectories=100)).evaluations > 0
