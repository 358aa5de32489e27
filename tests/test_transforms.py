"""JAX transformations of the public API: vmap against a loop, grad of vmap against vmap of grad,
jit with no recompilation, and the layers of the code (import-linter's contracts in pyproject.toml)."""

import logging
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SETTINGS = dict(switch="smooth", T=0.5)  # a cheap, smooth model: the transforms are what is tested
GAINS = jnp.array([0.3, 0.5, 0.8])


def peak(k, M_b=2.0):
    return cj.simulate(
        cj.make_params(K_GP=k, M_b=M_b), "paper", checkpoint=False, check_dt=False, **SETTINGS
    ).metrics.peak_grip


@pytest.mark.slow
def test_vmap_of_simulate_equals_a_loop_of_single_runs():
    batched = np.asarray(jax.jit(jax.vmap(peak))(GAINS))
    looped = np.array([float(peak(k)) for k in GAINS])
    np.testing.assert_allclose(batched, looped, rtol=1e-12)
    # vmap over two arguments, and against the batch API (a batch axis on the parameters).
    masses = jnp.array([1.0, 2.0, 4.0])
    both = np.asarray(jax.jit(jax.vmap(peak))(GAINS, masses))
    batch = cj.simulate(
        cj.make_params(K_GP=np.asarray(GAINS), M_b=np.asarray(masses)), "paper", checkpoint=False, **SETTINGS
    )
    np.testing.assert_allclose(both, np.asarray(batch.metrics.peak_grip), rtol=1e-12)


def test_grad_of_vmap_equals_vmap_of_the_derivative():
    # Per sample by forward mode (a scalar parameter: one tangent), the sum's by reverse mode.
    per_sample = np.asarray(jax.jit(jax.vmap(lambda k: jax.jvp(peak, (k,), (jnp.ones_like(k),))[1]))(GAINS))
    of_sum = np.asarray(jax.jit(jax.grad(lambda ks: jax.vmap(peak)(ks).sum()))(GAINS))
    np.testing.assert_allclose(of_sum, per_sample, rtol=1e-10)
    assert np.all(np.abs(per_sample) > 0)


def test_second_call_with_new_values_compiles_nothing(caplog):
    cj.simulate(cj.make_params(K_GP=np.array([0.5, 0.6])), "carry", T=1.0, every=100)
    caplog.set_level(logging.WARNING)
    with jax.log_compiles():
        sol = cj.simulate(cj.make_params(K_GP=np.array([0.7, 0.8])), "carry", T=1.0, every=100)
        jax.block_until_ready(sol)
    compiled = [r.getMessage() for r in caplog.records if "Compiling" in r.getMessage()]
    assert compiled == []


def test_the_import_contracts_hold():
    """Layers (params -> model -> integration -> objectives -> sweeps -> cli), coopjax never
    importing tuning, and no cycles among sibling modules."""
    lint = os.path.join(os.path.dirname(sys.executable), "lint-imports")
    run = subprocess.run([lint], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout


@pytest.mark.slow
def test_xla_default_flags_give_the_suites_answer_to_round_off(with_xla_defaults):
    """The suite compiles with faster-compiling XLA flags (conftest.py); users get XLA's defaults.
    A run under the defaults, in a fresh process, equals the suite's to round-off."""
    code = (
        "import json, jax; jax.config.update('jax_enable_x64', True); import coopjax as cj; "
        "m = cj.simulate(cj.make_params(M_b=3.0, K_GP=0.3), 'paper', switch='smooth', T=0.5).metrics; "
        "print(json.dumps({k: float(getattr(m, k)) for k in ('min_grip', 'peak_grip', 'slip', 'crush')}))"
    )
    theirs = with_xla_defaults(code)
    ours = cj.simulate(cj.make_params(M_b=3.0, K_GP=0.3), "paper", switch="smooth", T=0.5).metrics
    for name, value in theirs.items():
        np.testing.assert_allclose(value, float(getattr(ours, name)), rtol=1e-9, atol=1e-12, err_msg=name)
