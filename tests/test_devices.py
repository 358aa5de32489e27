"""`coopjax.devices`: a program compiled ahead of time once per process, whichever threads ask for it
(the tuner compiles its later programs in a background thread while its first ones run); a batch of
several slabs run in order of body mass and returned in the caller's order."""

import threading
import time

import numpy as np
import pytest

import coopjax as cj
from coopjax import devices
from coopjax.simulation import metrics_of


class Slow:
    """A stand-in for a jitted function: `lower(x).compile()` takes a while and is counted."""

    def __init__(self, fail_first=False):
        self.compiles, self.fail_first = 0, fail_first

    def lower(self, x):
        return self

    def compile(self):
        self.compiles += 1
        time.sleep(0.2)
        if self.fail_first and self.compiles == 1:
            raise ValueError("a compile that fails")
        return ("executable", self.compiles)


def test_a_program_that_two_threads_ask_for_at_once_is_compiled_once():
    program, got = Slow(), []
    threads = [threading.Thread(target=lambda: got.append(devices.compiled(program, np.ones(3)))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert program.compiles == 1
    assert got == [("executable", 1)] * 3


def test_a_failed_compile_reaches_the_caller_and_the_next_call_compiles_again():
    program = Slow(fail_first=True)
    with pytest.raises(ValueError, match="a compile that fails"):
        devices.compiled(program, np.ones(3))
    assert devices.compiled(program, np.ones(3)) == ("executable", 2)
    assert devices.compiled(program, np.ones(3)) == ("executable", 2)  # kept from then on


@pytest.mark.parametrize("avx512", [True, False])
def test_wide_vectors_are_asked_for_where_the_cpu_has_them_and_a_users_width_is_kept(avx512, monkeypatch):
    monkeypatch.setattr(devices, "_has_avx512", lambda: avx512)
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    assert devices.wide_vectors() is avx512
    expected = "--xla_cpu_use_fusion_emitters=false" + (" " + devices.WIDE_VECTORS if avx512 else "")
    assert devices.os.environ["XLA_FLAGS"] == expected
    assert devices.wide_vectors() is avx512  # asked twice: added once
    assert devices.os.environ["XLA_FLAGS"] == expected
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_prefer_vector_width=256")
    assert devices.wide_vectors() is False
    assert devices.os.environ["XLA_FLAGS"] == "--xla_cpu_prefer_vector_width=256"


@pytest.mark.slow  # two fresh processes compiling the step (17 s); the flag's handling is checked above
def test_wide_vectors_give_the_same_answers(tmp_path):
    """The sliding-mode step's metrics and final states in float64, with XLA's defaults and with
    512-bit vectors, each in a fresh process: the vector width changes the code, not the arithmetic
    (the same bits, measured in float64 and float32; compared here to 1e-13, in float64 for the
    suite's time)."""
    import os
    import subprocess
    import sys

    code = (
        "import sys, numpy as np, jax; jax.config.update('jax_enable_x64', True); import coopjax as cj; "
        "rng = np.random.default_rng(3); metrics, states = [], []\n"
        "for dtype in ('float64',):\n"
        "    p = cj.make_params(M_b=rng.uniform(0.5, 20, 8), K_GP=rng.uniform(0.1, 0.9, 8), dtype=dtype)\n"
        "    s = cj.simulate(p, 'carry', T=0.6, dtype=dtype)\n"
        "    metrics += [np.asarray(x, np.float64) for x in s.metrics]\n"
        "    states.append(np.asarray(s.y_final, np.float64))\n"
        "np.savez(sys.argv[1], metrics=np.stack(metrics), states=np.concatenate(states))"
    )
    answers = []
    for flags in ("", devices.WIDE_VECTORS):
        out = tmp_path / f"answers{len(answers)}.npz"
        env = {**os.environ, "XLA_FLAGS": flags}
        run = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, env=env)
        assert run.returncode == 0, run.stderr
        answers.append(np.load(out))
    assert np.isfinite(answers[0]["states"]).all()  # (metrics whose window is later than T are NaN)
    for part in ("metrics", "states"):
        np.testing.assert_allclose(answers[1][part], answers[0][part], rtol=1e-13, atol=0)


@pytest.mark.parametrize("cut", [dict(fixed_block=True), dict()])
def test_a_batch_of_several_slabs_runs_by_body_mass_and_gives_every_sample_its_own_bits(cut):
    # Blocks of 4 cut 11 samples into 3 slabs (padded), which run sorted by M_b; one block of 16 runs
    # them in the order given. Sliding-mode step, so that the later pieces are decided per slab.
    # `fixed_block` is how sweeps cut a batch; without it, the order the integrator asks for is what
    # cuts it on one device, as `simulate` runs it.
    rng = np.random.default_rng(3)
    params = cj.make_params(
        M_b=rng.permutation(np.geomspace(0.5, 20.0, 11)), K_GP=rng.uniform(0.3, 0.8, 11), dtype="float64"
    )
    config = cj.Config("carry", integrator="filippov", dt=1e-3, T=1.5, dtype="float64")
    order = metrics_of(config).batch_order(params)
    assert np.all(np.diff(np.asarray(params.M_b)[order]) > 0)
    slabs = devices.run(metrics_of(config), params, block=4, **cut)
    whole = devices.run(metrics_of(config), params, block=16, **cut)
    for name in slabs._fields:
        a, b = np.asarray(getattr(slabs, name)), np.asarray(getattr(whole, name))
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert np.ptp(np.asarray(whole.peak_grip)) > 0  # distinct samples: a wrong order would show
