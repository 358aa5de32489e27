"""Gradients of the hard model against central finite differences, in both AD modes.

Under the sliding-mode integrator the hard model has exact gradients (docs/model.md, "Derivatives"). The
tuner's constrained objective, built on these, is checked the same way in test_tuning.py.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj

GAINS = ("K_GP", "K_GI", "tau", "G_e")
TERMS = ("slip", "crush", "rms_lag", "impact")
HARD_POINT = dict(K_GP=0.3, K_GI=0.2, tau=2.0, G_e=900.0)  # slides, loses some grip, and re-contacts: every term > 0
HARD_MASS = 3.0  # kg


def hard_terms(theta, dt, M_b=HARD_MASS, checkpoint=True, adjoint="reverse"):
    params = cj.make_params(**dict(zip(GAINS, theta)), M_b=M_b)
    m = cj.simulate(params, "carry", dt=dt, check_dt=False, checkpoint=checkpoint, adjoint=adjoint).metrics
    return jnp.stack([getattr(m, k) for k in TERMS], axis=0)


@pytest.mark.parametrize(
    "dt, modes, checkpoint, adjoint",
    [
        pytest.param(1e-3, ("forward", "reverse"), True, "reverse", marks=pytest.mark.slow),
        pytest.param(2e-3, ("forward", "reverse"), "nested", "reverse", marks=pytest.mark.slow),
        pytest.param(1e-3, ("forward", "reverse"), True, "forward", marks=pytest.mark.slow),
        # Reverse mode of the hard model in CI: tests/test_transforms.py (grad of vmap against vmap
        # of the derivative), tests/test_adjoint.py and the docs' optax script (tests/test_examples.py).
        pytest.param(2e-3, ("reverse",), True, "reverse", marks=pytest.mark.slow),
    ],
)
def test_hard_model_gradients_match_finite_differences_in_both_modes(dt, modes, checkpoint, adjoint):
    """d(slip, crush, lag, impact)/d(K_GP, K_GI, tau, G_e) of the hard model, filippov, against
    central differences of the same grid: AD differentiates the step it runs.

    Reverse mode runs transposed through the time loop (`adjoint="reverse"`, with per-step or
    nested checkpointing) and pulled back through the forward-mode Jacobian (`adjoint="forward"`).
    These run under `-m slow`. Whether these
    derivatives are the dt -> 0 limit's is test_derivatives.py's question."""
    theta = np.array([HARD_POINT[g] for g in GAINS])
    # Central differences, all eight perturbed runs in one batch. A relative step of 1e-6 stays
    # clear of the switching events, which a larger step can cross.
    h = 1e-6 * theta
    shifted = np.repeat(theta[None], 8, 0)
    for i in range(4):
        shifted[2 * i, i] += h[i]
        shifted[2 * i + 1, i] -= h[i]
    values = np.asarray(hard_terms(jnp.asarray(shifted.T), dt, M_b=np.full(8, HARD_MASS)))  # (4 terms, 8)
    fd = (values[:, 0::2] - values[:, 1::2]) / (2 * h)
    assert np.all(np.asarray(hard_terms(jnp.asarray(theta), dt)) > 0)  # every term is active
    assert np.all(np.abs(fd) > 0)
    scale = np.abs(fd).max(axis=1, keepdims=True)  # per term: an element tiny against its row gets an absolute floor
    if "forward" in modes:
        forward = np.asarray(jax.jit(jax.jacfwd(hard_terms), static_argnums=1)(jnp.asarray(theta), dt))
        error = np.abs(forward - fd)
        assert np.all(error <= 1e-4 * np.abs(fd) + 1e-6 * scale), error / np.abs(fd)
    if "reverse" in modes:
        # One vector-Jacobian product with random weights on the four terms: every entry of the
        # Jacobian enters it, and one backward pass compiles far faster than jacrev's four.
        weights = np.random.default_rng(0).uniform(0.5, 1.5, len(TERMS)) / np.abs(fd).max(axis=1)
        loss = lambda th: jnp.dot(jnp.asarray(weights), hard_terms(th, dt, HARD_MASS, checkpoint, adjoint))
        reverse = np.asarray(jax.jit(jax.grad(loss))(jnp.asarray(theta)))
        fd_weighted = weights @ fd
        np.testing.assert_allclose(reverse, fd_weighted, rtol=1e-4, atol=1e-6 * np.abs(fd_weighted).max())
        if "forward" in modes:
            np.testing.assert_allclose(reverse, weights @ forward, rtol=1e-9)


@pytest.mark.slow
def test_plain_rk4_finite_differences_of_the_hard_model_are_noise():
    """Why the sliding-mode step matters for tuning: under plain RK4 the hard switch chatters, and
    central differences of the lag with respect to K_GP at two nearby relative steps disagree."""
    theta = np.array([HARD_POINT[g] for g in GAINS])
    shifted = np.repeat(theta[None], 8, 0)
    for j, rel in enumerate((1e-4, 1e-6)):
        shifted[2 * j, 0] *= 1 + rel
        shifted[2 * j + 1, 0] *= 1 - rel
    shifted = shifted[:4]
    fd = {}
    for integrator in ("rk4", "filippov"):
        params = cj.make_params(**{g: shifted[:, i] for i, g in enumerate(GAINS)}, M_b=np.full(4, HARD_MASS))
        lag = np.asarray(cj.simulate(params, "carry", integrator=integrator, dt=1e-3).metrics.rms_lag)
        fd[integrator] = [(lag[0] - lag[1]) / (2e-4 * theta[0]), (lag[2] - lag[3]) / (2e-6 * theta[0])]
    assert abs(fd["filippov"][0] / fd["filippov"][1] - 1) < 1e-2  # a smooth function of K_GP
    assert abs(fd["rk4"][0] / fd["rk4"][1] - 1) > 0.5, fd  # noise


@pytest.mark.slow
def test_block_checkpointing_keeps_the_gradient_and_grows_memory_sub_linearly():
    from coopjax.simulation import Run

    def compiled(checkpoint, T):
        run = Run(cj.Config("carry", switch="smooth", dt=1e-3, T=T), checkpoint=checkpoint, adjoint="reverse")
        f = lambda k: cj.loss(run(cj.make_params(K_GP=k, M_b=jnp.ones(2))).metrics).mean()
        return jax.jit(jax.grad(f)).lower(0.5).compile()

    # Compiled here, not loaded from the suite's compilation cache: a loaded program reports no memory.
    cached = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    try:
        # Horizons that both reach into the grip window: before it the loss does not depend on K_GP,
        # and XLA removes the whole backward pass.
        programs = {(c, T): compiled(c, T) for c in (True, "nested", "segment") for T in (1.0, 4.0)}
    finally:
        jax.config.update("jax_enable_compilation_cache", cached)
    memory = {key: program.memory_analysis().temp_size_in_bytes for key, program in programs.items()}
    assert 3.5 < memory[True, 4.0] / memory[True, 1.0] < 4.5  # one carry per step: linear
    for blocks in ("nested", "segment"):
        assert memory[blocks, 4.0] / memory[blocks, 1.0] < 2.5, blocks  # sqrt(4) = 2
    assert memory["nested", 4.0] < memory[True, 4.0] / 5
    step, nested, segment = (float(programs[c, 4.0](0.5)) for c in (True, "nested", "segment"))
    assert nested == pytest.approx(step, rel=1e-5)  # the same gradient, up to the order of operations
    assert segment == pytest.approx(step, rel=1e-5)
