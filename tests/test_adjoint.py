"""The adjoint: reverse mode pulled back through a forward-mode Jacobian gives the derivatives of
the loop's own transpose, per sample, and its program holds the time loop once."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj
from coopjax.integration import adjoint as adjoint_module
from coopjax.integration import differentiate


def toy(p):
    """Per sample: a scan whose answer depends on a (2, B), b (B,) and n (an integer leaf, B)."""

    def body(x, _):
        return x + 0.1 * (p["a"][0] * jnp.sin(x) + p["a"][1] * p["b"] * x), None

    x = jax.lax.scan(body, p["b"] + 0.0 * p["n"], None, length=5)[0]
    return {"x": x, "whole": jnp.arange(3.0), "hit": x > 0}


def flags(out):
    return {"x": True, "whole": False, "hit": True}


P = {"a": jnp.array([[0.3, -0.2, 0.5], [1.1, 0.7, -0.4]]), "b": jnp.array([0.4, -1.2, 2.0]), "n": jnp.arange(3)}


def scans(fn, *args) -> int:
    return str(jax.make_jaxpr(fn)(*args)).count("scan[")


@pytest.mark.parametrize("copies_up_to", [256, 0], ids=["copies of the batch", "vmap over components"])
@pytest.mark.parametrize("adjoint", ["auto", "forward"])
def test_the_pulled_back_jacobian_equals_the_transposed_loop_per_sample(adjoint, copies_up_to, monkeypatch):
    monkeypatch.setattr(adjoint_module, "COPIES_UP_TO", copies_up_to)
    weights = jnp.array([0.7, -1.3, 2.1])

    def loss(how):
        return lambda a, b: (weights * differentiate(toy, {**P, "a": a, "b": b}, flags, how)["x"]).sum()

    through_jacobian = jax.grad(loss(adjoint), argnums=(0, 1))(P["a"], P["b"])
    transposed = jax.grad(loss("reverse"), argnums=(0, 1))(P["a"], P["b"])
    for mine, theirs in zip(through_jacobian, transposed):
        np.testing.assert_allclose(mine, theirs, rtol=1e-13, atol=1e-15)
    # The Jacobian's program runs the scan once, forward; the transpose runs it forward and back.
    assert scans(jax.grad(loss(adjoint)), P["a"], P["b"]) == 1
    assert scans(jax.grad(loss("reverse")), P["a"], P["b"]) == 2
    # Forward mode is the plain tangent under every adjoint (one scan, one direction).
    assert scans(jax.jacfwd(loss(adjoint)), P["a"], P["b"]) == 1


def test_many_components_are_transposed_through_the_loop_unless_forward_is_asked():
    big = {**P, "a": jnp.tile(P["a"], (5, 1))}  # 10 components per sample, more than MAX_FORWARD

    def fold(p):
        return toy({**p, "a": p["a"].reshape(5, 2, -1).sum(0)})

    def loss(how):
        return lambda a: differentiate(fold, {**big, "a": a}, flags, how)["x"].sum()

    assert scans(jax.grad(loss("auto")), big["a"]) == 2
    assert scans(jax.grad(loss("forward")), big["a"]) == 1
    np.testing.assert_allclose(jax.grad(loss("forward"))(big["a"]), jax.grad(loss("auto"))(big["a"]), rtol=1e-13)


@pytest.mark.slow  # 45 s of compiling under XLA's defaults; float64 forward and reverse agree in CI (below)
def test_float32_derivatives_of_a_sliding_body_agree_in_forward_and_reverse_mode(with_xla_defaults):
    """The 12.0 kg body slides on F_lim, where float32 resolves the force to a few ulps, so its
    derivative depends on the program's rounding. Each mode once had it wrong, under XLA's default
    flags only, which the suite does not compile with (conftest.py): so a fresh process with them.
    - Reverse mode through the loop gave NaN: the backward pass recomputed a step by a program of
      its own, which took another path; that path (each piece's plan and cut) is now kept.
    - Forward mode gave 547 against 187.7 in float64: a piece cut at an event that rounded to the
      step's end dropped the tangent of the (zero) rest; the piece now ends at the step's end."""
    code = (
        "import json, jax, jax.numpy as jnp, coopjax as cj\n"
        "k0, M_b = jnp.full(2, 0.5, jnp.float32), jnp.float32([11.952941, 1.0])\n"
        "def losses(k, adjoint='auto'):\n"
        "    return cj.loss(cj.simulate(cj.make_params(K_GP=k, M_b=M_b), 'carry', adjoint=adjoint).metrics)\n"
        "reverse = jax.jit(jax.grad(lambda k: losses(k, 'reverse').sum()))(k0)\n"
        "forward = jax.jit(lambda k: jax.jvp(losses, (k,), (jnp.ones_like(k),))[1])(k0)\n"
        "print(json.dumps([[float(x) for x in reverse], [float(x) for x in forward]]))"
    )
    reverse, forward = with_xla_defaults(code)
    assert np.isfinite(reverse).all() and np.isfinite(forward).all(), (reverse, forward)
    np.testing.assert_allclose(reverse, forward, rtol=1e-3)


def test_grad_of_a_hard_model_batch_matches_central_differences_and_compiles_the_loop_once():
    """The sliding-mode step, a batch of three bodies, float64: d(per-sample weighted peak grip and
    lag)/d(K_GP, and each sample's own M_b) by `grad` (through the Jacobian) against central
    differences of the same run (all twelve perturbed runs in one batch)."""
    masses = np.array([3.0, 20.0, 80.0])
    weights = np.array([1.0, -2.0, 3.0])
    terms = lambda m: m.peak_grip + 100.0 * m.rms_lag

    def run(k, M_b):
        return cj.simulate(cj.make_params(K_GP=k, K_GI=0.2, tau=2.0, M_b=M_b), "carry", check_dt=False).metrics

    loss = lambda k, M_b: (jnp.asarray(weights) * terms(run(k, M_b))).sum()
    pulled = jax.jit(jax.grad(loss, argnums=(0, 1))).lower(0.3, jnp.asarray(masses))
    pushed = jax.jit(jax.jacfwd(loss, argnums=(0, 1))).lower(0.3, jnp.asarray(masses))
    # One pass of the time loop's while: the grad's program has no transposed copy of it.
    assert pulled.as_text().count("stablehlo.while") == pushed.as_text().count("stablehlo.while")
    d_k, d_M = pulled.compile()(0.3, jnp.asarray(masses))

    hk, hM = 0.3e-6, 1e-6 * masses
    k = np.r_[np.full(3, 0.3 + hk), np.full(3, 0.3 - hk), np.full(6, 0.3)]
    M = np.r_[masses, masses, masses + hM, masses - hM]
    values = np.asarray(terms(run(jnp.asarray(k), jnp.asarray(M))))
    fd_k = weights @ (values[0:3] - values[3:6]) / (2 * hk)
    fd_M = weights * (values[6:9] - values[9:12]) / (2 * hM)
    assert np.all(np.abs(fd_M) > 1e-6)  # each sample's own mass enters its own term
    np.testing.assert_allclose(float(d_k), fd_k, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(d_M), fd_M, rtol=1e-4)
