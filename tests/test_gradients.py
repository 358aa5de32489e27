"""Gradients of the carry objective against central finite differences, in both AD modes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj

GAINS = ("K_GP", "K_GI", "tau", "G_e")
DT = 1e-4  # converged for the smooth model (see test_reference); 1e-3 is not, for carry


def objective(theta, dt=DT):
    params = cj.make_params(**dict(zip(GAINS, theta)), M_b=2.0)
    metrics = cj.simulate(params, "carry", switch="smooth", dt=dt).metrics
    return cj.loss(metrics)


@pytest.fixture(scope="module")
def reference():
    theta = np.array([0.5, 0.1, 1.25, 600.0])
    fd = []
    for i in range(4):
        h = 1e-5 * theta[i]
        e = np.zeros(4)
        e[i] = h
        fd.append((float(objective(theta + e)) - float(objective(theta - e))) / (2 * h))
    return theta, np.array(fd)


def test_reverse_mode_matches_finite_differences(reference):
    theta, fd = reference
    grad = np.asarray(jax.grad(objective)(jnp.asarray(theta)))
    np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_forward_mode_matches_finite_differences_and_reverse(reference):
    theta, fd = reference
    jac = np.asarray(jax.jacfwd(objective)(jnp.asarray(theta)))
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())
    assert np.all(np.abs(fd) > 0)  # each gain really moves the objective


def test_nested_checkpointing_keeps_the_gradient_and_grows_memory_sub_linearly():
    from coopjax.integration import SimConfig, integrate
    from coopjax.model import Options

    def compiled(checkpoint, T):
        config = SimConfig("carry", Options(switch="smooth"), dt=1e-3, T=T, checkpoint=checkpoint)
        f = lambda k: cj.loss(integrate(cj.make_params(K_GP=k, M_b=jnp.ones(2)), config).metrics).mean()
        return jax.jit(jax.grad(f)).lower(0.5).compile()

    programs = {(c, T): compiled(c, T) for c in (True, "nested") for T in (0.5, 2.0)}
    memory = {key: program.memory_analysis().temp_size_in_bytes for key, program in programs.items()}
    assert 3.5 < memory[True, 2.0] / memory[True, 0.5] < 4.5  # one carry per step: linear
    assert memory["nested", 2.0] / memory["nested", 0.5] < 2.5  # sqrt(4) = 2
    assert memory["nested", 2.0] < memory[True, 2.0] / 5
    step, nested = (float(programs[c, 2.0](0.5)) for c in (True, "nested"))
    assert nested == pytest.approx(step, rel=1e-5)  # the same gradient, up to the order of operations
