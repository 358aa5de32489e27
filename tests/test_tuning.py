"""Tuning on the hard model: the constrained objective's gradients, the augmented Lagrangian on a
problem with a known answer, K starts against K single runs, resume by replay, rejected steps."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import coopjax as cj
from tuning import constrained, driver, training
from tuning import problem as pb
from tuning.evaluate import Evaluator
from tuning.tuners import Query
from tuning.tuners.adam import AdamAL

BASE = cj.make_params()
# Two masses per start keep the tests cheap; one heavy enough that Table 1's gains lose the grip, so
# the constraint term is active in the gradient test.
PROBLEM = pb.Problem(names=pb.GAINS, n_draws=2, uncertain=(("M_b", "loguniform", 0.8, 4.5),), margin=0.0, jitter=False)
THETA = np.log(np.asarray([[0.08, 0.078, 2.93, 1224.0], [0.054, 0.3, 1.0, 600.0]]))
TUNER = AdamAL(steps=4, mode="forward", learning_rate=0.2)


def test_the_augmented_lagrangian_finds_a_known_constrained_minimum():
    # min (x0 - 2)^2 + (x1 - 1)^2  s.t.  x0 + x1 <= 2,  x0 >= -5:  x* = (1.5, 0.5), lambda* = (1, 0).
    fun = lambda x: ((x[0] - 2) ** 2 + (x[1] - 1) ** 2, jnp.array([x[0] + x[1] - 2, -x[0] - 5.0]))
    x, mult = constrained.solve(fun, jnp.zeros(2), optax.adam(0.05), outer=20, inner=200)
    np.testing.assert_allclose(x, [1.5, 0.5], atol=1e-4)
    np.testing.assert_allclose(mult.lam, [1.0, 0.0], atol=1e-3)
    # An inactive constraint leaves the unconstrained minimum alone.
    x, mult = constrained.solve(lambda x: ((x[0] - 2) ** 2, jnp.array([x[0] - 3.0])), jnp.zeros(1), optax.adam(0.05))
    np.testing.assert_allclose(x, [2.0], atol=1e-4)
    assert float(mult.lam[0]) == 0.0


def test_multiplier_update_raises_the_penalty_only_while_the_violation_stalls():
    mult = constrained.init((2, 1), rho=1.0)
    g = jnp.array([[0.5], [-1.0]])  # start 0 violates, start 1 is feasible
    mult = constrained.update(mult, g)
    np.testing.assert_allclose(mult.lam[:, 0], [0.5, 0.0])
    np.testing.assert_allclose(mult.rho, [1.0, 1.0])  # the first update only records the violation
    mult = constrained.update(mult, jnp.array([[0.4], [-1.0]]))  # 0.4 > 0.25 x 0.5: too slow
    np.testing.assert_allclose(mult.rho, [10.0, 1.0])
    np.testing.assert_allclose(mult.lam[:, 0], [0.9, 0.0])


@pytest.fixture(scope="module")
def point():
    masses = np.asarray([1.0, 5.0])
    t = jax.jit(lambda th: training.terms(th, BASE, PROBLEM, jnp.asarray(masses)))(jnp.asarray(THETA))
    assert float(np.max(t.c)) > 0.1, "the test point must violate the grip constraint somewhere"
    mult = constrained.Multipliers(jnp.full((2, 2), 3.0), jnp.full(2, 10.0), jnp.full(2, jnp.inf))
    return masses, mult


# Both modes are slow here: test_gradients.py checks reverse mode on the hard model in CI, and the
# tuner's forward mode runs end to end in test_tuning_cli.py.
@pytest.mark.slow
@pytest.mark.parametrize("mode", ["forward", "reverse"])
def test_gradients_of_the_constrained_objective_match_central_differences(point, mode):
    masses, mult = point
    L_fn = jax.jit(lambda th: constrained.lagrangian(*training.terms(th, BASE, PROBLEM, jnp.asarray(masses))[:2], mult))
    ev = Evaluator(PROBLEM, BASE, AdamAL.scalar)(Query(THETA, masses, "gradient", mode, mult))
    np.testing.assert_allclose(ev.value, L_fn(jnp.asarray(THETA)), rtol=1e-12)
    h = 1e-6
    fd = np.zeros(THETA.shape)
    for i in range(THETA.shape[1]):  # one column of every start at once: the starts are separable
        e = np.zeros(THETA.shape)
        e[:, i] = h
        fd[:, i] = (np.asarray(L_fn(jnp.asarray(THETA + e))) - np.asarray(L_fn(jnp.asarray(THETA - e)))) / (2 * h)
    scale = np.abs(fd).max(1, keepdims=True)
    assert np.all(np.abs(ev.gradient - fd) <= 1e-4 * np.abs(fd) + 1e-5 * scale), (ev.gradient, fd)


@pytest.mark.slow
def test_k_starts_in_one_batch_equal_k_single_runs(point):
    masses, _ = point
    evaluate = Evaluator(PROBLEM, BASE)
    both = evaluate(Query(THETA, masses))
    for k in range(THETA.shape[0]):
        one = evaluate(Query(THETA[k : k + 1], masses))
        for name in ("f", "c", "parts", "min_swi"):
            np.testing.assert_allclose(
                getattr(one, name)[0], getattr(both, name)[k], rtol=1e-12, atol=1e-14, err_msg=name
            )


@pytest.mark.slow
def test_resume_is_bit_identical_to_an_uninterrupted_run(tmp_path):
    whole = driver.run(TUNER, PROBLEM, BASE, THETA, 0, recorder=driver.Checkpoint(str(tmp_path / "whole.ckpt")))
    cut = str(tmp_path / "cut.ckpt")
    first = driver.run(
        TUNER, PROBLEM, BASE, THETA, 0, recorder=driver.Checkpoint(cut), budget=driver.Budget(trajectories=2 * 2 * 2)
    )
    assert first.state.step == 2
    with pytest.raises(cj.InputError, match="resume it"):
        driver.run(TUNER, PROBLEM, BASE, THETA, 0, recorder=driver.Checkpoint(cut))  # never silently restarts
    with pytest.raises(cj.InputError, match="other options"):
        driver.run(
            AdamAL(steps=5, mode="forward", learning_rate=0.2),
            PROBLEM,
            BASE,
            THETA,
            0,
            recorder=driver.Checkpoint(cut, resume=True),
        )
    resumed = driver.run(TUNER, PROBLEM, BASE, THETA, 0, recorder=driver.Checkpoint(cut, resume=True))
    assert resumed.state.step == whole.state.step == 4
    for field in ("theta", "good", "scale", "best_theta", "best_f"):
        np.testing.assert_array_equal(getattr(resumed.state, field), getattr(whole.state, field))
    assert resumed.state.history["f"] == whole.state.history["f"]
    for a, b in zip(
        jax.tree_util.tree_leaves((resumed.state.opt_state, resumed.state.mult)),
        jax.tree_util.tree_leaves((whole.state.opt_state, whole.state.mult)),
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # The multipliers moved (al_every = 3 < 4 steps), so the replay carried them.
    assert np.any(np.asarray(whole.state.mult.lam) > 0)


@pytest.mark.slow
def test_a_start_whose_step_blows_up_goes_back_halfway_and_the_others_go_on(monkeypatch):
    seen = []
    real = Evaluator.__call__

    def poisoned(self, query):
        seen.append(np.asarray(query.thetas))
        ev = real(self, query)
        if len(seen) == 2:  # start 1's first move lands somewhere non-finite
            value = ev.value.copy()
            value[1] = np.nan
            ev = ev._replace(value=value)
        return ev

    monkeypatch.setattr(Evaluator, "__call__", poisoned)
    result = driver.run(AdamAL(steps=3, mode="forward", learning_rate=0.2), PROBLEM, BASE, THETA, 0)
    theta0, bad, after = seen
    np.testing.assert_allclose(after[1], (theta0[1] + bad[1]) / 2, rtol=1e-12)  # back halfway
    assert not np.allclose(after[0], bad[0])  # start 0 took its gradient step
    state = result.state
    assert state.history["rejected"] == [0, 1, 0] and state.scale[1] == 0.5 and state.scale[0] == 1.0


def test_ipop_cma_es_restarts_with_twice_the_population_and_writes_no_files(tmp_path, monkeypatch):
    from tuning.tuners import Evaluation
    from tuning.tuners.cmaes import CMAES

    monkeypatch.chdir(tmp_path)
    # No process-wide side effect: the working folder is never changed (a background thread shares it).
    monkeypatch.setattr(os, "chdir", lambda *a: pytest.fail("the CMA-ES tuner changed the working folder"))
    tuner = CMAES()
    state = tuner.init(pb.Problem(names=("K_GP", "K_GI"), n_draws=2), np.log([[0.5, 0.1], [0.2, 0.05]]), 0)
    first = state.popsize
    for _ in range(200):  # a quadratic with its minimum cut off by a constraint: cma soon meets tolfun
        query = tuner.ask(state)
        C = len(query.thetas)
        c = np.maximum(0.0, query.thetas[:, :1] + 1.0) * np.ones((C, 2))
        zeros = np.zeros((C, 2))
        state = tuner.tell(
            state,
            query,
            Evaluation(
                f=(query.thetas**2).sum(1),
                c=c,
                parts=zeros,
                valid=np.ones(C, bool),
                holds=(c == 0).all(1),
                min_swi=zeros,
            ),
        )
    assert state.restarts >= 1 and state.popsize == first * 2**state.restarts
    assert list(tmp_path.iterdir()) == []  # cma's loggers wrote nothing, not even their folder
    import cma.constraints_handler
    import cma.logger

    assert cma.constraints_handler._Logger is not cma.logger.LoggerDummy  # cma's own switch is put back
