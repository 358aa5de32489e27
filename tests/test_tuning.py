"""Tuning on the hard model: the constrained objective's gradients, the augmented Lagrangian on a
problem with a known answer, K starts against K single runs, resume, the CLI and its bad flags."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import coopjax as cj
from tuning import constrained
from tuning import objective as obj
from tuning import optimize as opt

BASE = cj.make_params()
# Two masses per start keep the tests cheap; one heavy enough that Table 1's gains lose the grip, so
# the constraint term is active in the gradient test.
PROBLEM = obj.Problem(names=obj.GAINS, n_masses=2, masses=("loguniform", 0.8, 4.5), margin=0.0, jitter=False)
THETA = jnp.log(jnp.asarray([[0.08, 0.078, 2.93, 1224.0], [0.054, 0.3, 1.0, 600.0]]))


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
    masses = jnp.asarray([1.0, 5.0])
    t = jax.jit(lambda th: obj.terms(th, BASE, PROBLEM, masses))(THETA)
    assert float(np.max(t.c)) > 0.1, "the test point must violate the grip constraint somewhere"
    mult = constrained.Multipliers(jnp.full((2, 2), 3.0), jnp.full(2, 10.0), jnp.full(2, jnp.inf))
    return masses, mult


# Forward mode is marked slow: test_gradients.py checks both modes on the hard model in CI, and the
# tuner's default is reverse mode.
@pytest.mark.parametrize("mode", [pytest.param("forward", marks=pytest.mark.slow), "reverse"])
def test_gradients_of_the_constrained_objective_match_central_differences(point, mode):
    masses, mult = point
    L_fn = jax.jit(lambda th: constrained.lagrangian(*obj.terms(th, BASE, PROBLEM, masses)[:2], mult))
    L, grad, _ = opt.value_and_grad_fn(PROBLEM, mode)(THETA, masses, mult, BASE)
    np.testing.assert_allclose(L, L_fn(THETA), rtol=1e-12)
    h = 1e-6
    fd = np.zeros(THETA.shape)
    for i in range(THETA.shape[1]):  # one column of every start at once: the starts are separable
        e = jnp.zeros(THETA.shape).at[:, i].set(h)
        fd[:, i] = (np.asarray(L_fn(THETA + e)) - np.asarray(L_fn(THETA - e))) / (2 * h)
    scale = np.abs(fd).max(1, keepdims=True)
    assert np.all(np.abs(np.asarray(grad) - fd) <= 1e-4 * np.abs(fd) + 1e-5 * scale), (np.asarray(grad), fd)


def test_k_starts_in_one_batch_equal_k_single_runs(point):
    masses, mult = point
    vg = opt.value_and_grad_fn(PROBLEM, "forward")
    L, grad, t = vg(THETA, masses, mult, BASE)
    for k in range(THETA.shape[0]):
        one = jax.tree_util.tree_map(lambda x: x[k:k + 1], mult)
        Lk, gk, tk = vg(THETA[k:k + 1], masses, one, BASE)
        np.testing.assert_allclose(Lk[0], L[k], rtol=1e-12)
        np.testing.assert_allclose(gk[0], grad[k], rtol=1e-10, atol=1e-12 * np.abs(grad[k]).max())
        np.testing.assert_allclose(tk.metrics.peak_grip[0], t.metrics.peak_grip[k], rtol=1e-12)


CONFIG = opt.TuneConfig(problem=PROBLEM, starts=2, steps=4, mode="forward", learning_rate=0.2)


def test_resume_is_bit_identical_to_an_uninterrupted_run(tmp_path):
    quiet = lambda s: None
    whole = opt.tune(CONFIG, BASE, checkpoint=str(tmp_path / "whole.npz"), log=quiet)
    cut = str(tmp_path / "cut.npz")
    first = opt.tune(CONFIG, BASE, checkpoint=cut, log=quiet, stop_after=2)
    assert first.step == 2
    with pytest.raises(ValueError, match="--resume"):
        opt.tune(CONFIG, BASE, checkpoint=cut, log=quiet)  # never silently restarts
    with pytest.raises(ValueError, match="other options"):
        opt.tune(dataclasses.replace(CONFIG, steps=5), BASE, checkpoint=cut, resume=True, log=quiet)
    resumed = opt.tune(CONFIG, BASE, checkpoint=cut, resume=True, log=quiet)
    for field in ("theta", "good", "scale", "best_theta", "best_f"):
        np.testing.assert_array_equal(getattr(resumed, field), getattr(whole, field))
    assert resumed.history["f"] == whole.history["f"] and resumed.history["theta"] == whole.history["theta"]
    for a, b in zip(jax.tree_util.tree_leaves((resumed.opt_state, resumed.mult)),
                    jax.tree_util.tree_leaves((whole.opt_state, whole.mult))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # The multipliers moved (al_every = 3 < 4 steps), so the checkpoint carried them.
    assert np.any(np.asarray(whole.mult.lam) > 0)


def test_a_start_whose_step_blows_up_goes_back_halfway_and_the_others_go_on(monkeypatch):
    real = opt.value_and_grad_fn(CONFIG.problem, "forward")
    calls = []

    def poisoned(theta, masses, mult, base):
        calls.append(np.asarray(theta))
        L, grad, t = real(theta, masses, mult, base)
        if len(calls) == 2:  # start 1's first move lands somewhere non-finite
            L = L.at[1].set(jnp.nan)
        return L, grad, t

    monkeypatch.setattr(opt, "value_and_grad_fn", lambda problem, mode: poisoned)
    state = opt.tune(dataclasses.replace(CONFIG, steps=3), BASE, log=lambda s: None)
    theta0, bad, after = calls
    np.testing.assert_allclose(after[1], (theta0[1] + bad[1]) / 2, rtol=1e-12)  # back halfway
    assert not np.allclose(after[0], bad[0])  # start 0 took its gradient step
    assert state.history["rejected"] == [0, 1, 0] and state.scale[1] == 0.5 and state.scale[0] == 1.0
