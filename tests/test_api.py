"""The Python API: no recompilation, float32, static checks, and the paper's claim."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj
from coopjax.status import Status


def test_float32_runs_in_float32_and_tracks_float64():
    p64 = cj.make_params()
    p32 = p64.astype(jnp.float32)
    m32 = cj.simulate(p32, "paper").metrics
    m64 = cj.simulate(p64, "paper").metrics
    assert m32.peak_grip.dtype == jnp.float32 and m64.peak_grip.dtype == jnp.float64
    assert float(m32.peak_grip) == pytest.approx(float(m64.peak_grip), rel=1e-4)


def test_paper_claim_grip_stays_at_or_above_F_lim_once_reached():
    """Pathak et al.: 'the minimum prescribed gripping force is maintained by the controller'."""
    sol = cj.simulate(cj.make_params(), "paper", switch="hard", dt=1e-3, every=1)
    F = np.asarray(sol.trajectory.aux.F)  # (n, 2)
    for i in range(2):
        reached = np.argmax(F[:, i] >= 10.0)
        assert F[reached, i] >= 10.0
        assert F[reached:, i].min() >= 10.0
    assert float(sol.metrics.min_grip) >= 10.0
    assert bool(sol.metrics.finite)


@pytest.mark.slow
def test_surrogates_tend_to_the_hard_model_as_widths_shrink():
    hard = cj.simulate(cj.make_params(), "paper", switch="hard", dt=1e-4, every=10)
    gaps = []
    for scale in (4.0, 1.0, 0.25):
        widths = dict(k_F=0.5 * scale, k_c=0.5 * scale, eps_delta=1e-4 * scale)
        smooth = cj.simulate(cj.make_params(**widths), "paper", switch="smooth", dt=1e-4, every=10)
        gaps.append(np.abs(np.asarray(smooth.trajectory.aux.F) - np.asarray(hard.trajectory.aux.F)).mean())
    assert gaps[0] > 2 * gaps[1] > 4 * gaps[2], gaps


@pytest.mark.slow
def test_straight_through_is_hard_forward_and_has_gradients():
    p = cj.make_params()
    hard = cj.simulate(p, "paper", switch="hard", integrator="rk4", T=0.5).metrics
    st = cj.simulate(p, "paper", switch="straight_through", T=0.5).metrics
    assert float(st.peak_grip) == pytest.approx(float(hard.peak_grip), rel=1e-12)
    g = jax.grad(
        lambda k: cj.simulate(cj.make_params(K_GP=k), "paper", switch="straight_through", T=0.5).metrics.peak_grip
    )(0.5)
    assert np.isfinite(float(g)) and float(g) != 0.0


@pytest.mark.slow
def test_bilateral_contact_pulls_where_unilateral_lets_go():
    # In the release phase the tips back away: a unilateral gripper goes slack, a bilateral one pulls.
    run = lambda contact: np.asarray(
        cj.simulate(cj.make_params(), "carry", switch="smooth", contact=contact, dt=1e-4, every=100).trajectory.aux.F
    )
    unilateral, bilateral = run("unilateral"), run("bilateral")
    assert unilateral.min() >= 0.0
    assert bilateral.min() < -1.0


@pytest.mark.slow
def test_use_all_cores_shards_a_batch_and_changes_only_round_off(tmp_path):
    """`coopjax.use_all_cores(2)` in a fresh process: 5 samples (padded to 6 over 2 devices) give the
    metrics and final states of this one-device process, to round-off: a sample's SIMD lane (a full
    vector or the loop's tail) depends on the per-device batch, and XLA may contract a*b+c into one
    FMA in one and not the other (measured: 4e-12 absolute on a 3e3 N^2 slip)."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np, coopjax as cj; cj.use_all_cores(2); import jax; "
        "jax.config.update('jax_enable_x64', True); "
        "s = cj.simulate(cj.make_params(M_b=np.geomspace(0.5, 5, 5), K_GP=np.linspace(0.3, 0.9, 5)), 'paper', T=0.5); "
        "assert jax.device_count() == 2 and s.metrics.peak_grip.shape == (5,); "
        "np.save(sys.argv[1], np.concatenate([np.stack([np.asarray(x, np.float64) for x in s.metrics]), s.y_final]))"
    )
    out = tmp_path / "two.npy"
    run = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    s = cj.simulate(cj.make_params(M_b=np.geomspace(0.5, 5, 5), K_GP=np.linspace(0.3, 0.9, 5)), "paper", T=0.5)
    mine = np.concatenate([np.stack([np.asarray(x, np.float64) for x in s.metrics]), np.asarray(s.y_final)])
    np.testing.assert_allclose(np.load(out), mine, rtol=1e-12, atol=1e-12)


def _body_mass(params):
    return params.M_b


def test_a_large_batch_on_one_core_of_several_says_so(monkeypatch):
    import warnings

    from coopjax import devices

    monkeypatch.setattr(devices, "_warned", False)
    monkeypatch.setattr(devices.os, "cpu_count", lambda: 4)
    params = cj.make_params(M_b=np.ones(devices.LARGE_BATCH))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        devices.run(_body_mass, params)
        devices.run(_body_mass, params)  # once only
    assert len(caught) == 1 and "use_all_cores" in str(caught[0].message)
    # A device count asked for (here the one this process has) is not warned about.
    monkeypatch.setattr(devices, "_warned", False)
    monkeypatch.setattr(devices, "wide_vectors", lambda: False)
    devices.use_all_cores(jax.device_count())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        devices.run(_body_mass, params)
    assert caught == []


@pytest.mark.parametrize(
    "dt", [jnp.asarray(2e-3), np.float64(2e-3), np.asarray(2e-3)], ids=["jax", "numpy-scalar", "0-d"]
)
def test_dt_and_T_accept_concrete_jax_and_numpy_scalars(dt):
    a = cj.simulate(cj.make_params(), "paper", dt=dt, T=np.asarray(0.2)).metrics
    b = cj.simulate(cj.make_params(), "paper", dt=2e-3, T=0.2).metrics
    assert float(a.peak_grip) == float(b.peak_grip)


@pytest.mark.parametrize("dt, fragment", [("0.001", "dt must be a number"), ([1e-3], "dt must be a number")])
def test_dt_of_another_type_is_an_input_error_naming_it(dt, fragment):
    with pytest.raises(cj.InputError, match=fragment):
        cj.simulate(cj.make_params(), "paper", dt=dt)


def test_an_unstable_step_is_marked_not_raised_under_a_trace_and_its_derivative_is_nan():
    """A loss at K_GP = 50 (beyond the step's stability limit at dt = 2e-3 s, paper scenario):
    concretely an InputError; under grad a NaN value with a NaN derivative, never 0.0;
    with check_dt="mark", a per-sample flag. (The blend switch: its gradient compiles in seconds;
    the marking is `simulate`'s, whatever the switch.)"""
    run = lambda k, **kw: cj.simulate(cj.make_params(K_GP=k), "paper", dt=2e-3, T=0.06, switch="blend", **kw).metrics
    with pytest.raises(cj.InputError, match="too large"):
        run(50.0)
    # Crush and slip: over this short horizon the lag's window has not begun (its value is NaN).
    loss = lambda m: m.crush + m.slip
    slopes = jax.jit(jax.vmap(jax.grad(lambda k: loss(run(k)))))(jnp.array([0.5, 50.0]))
    assert np.isfinite(float(slopes[0])) and np.isnan(float(slopes[1]))
    solution = cj.simulate(
        cj.make_params(K_GP=jnp.array([0.5, 50.0])), "paper", dt=2e-3, T=0.06, switch="blend", check_dt="mark"
    )
    marked = solution.metrics
    assert marked.finite.tolist() == [True, False]
    # The solution says why: the one status vocabulary of sweeps and the judge.
    assert [Status(int(s)) for s in solution.status] == [Status.OK, Status.STEP_BEYOND_LIMIT]
    assert marked.finite.tolist() == (np.asarray(solution.status) == Status.OK).tolist()
    assert np.isnan(float(marked.peak_grip[1])) and np.isfinite(float(marked.peak_grip[0]))


def test_the_traced_mark_is_the_concrete_check_and_has_no_host_callback():
    """Under a trace, `simulate` marks a sample where the concrete check (`check_step`) would refuse
    it: the same linearisation and eigenvalues, computed inside the program (in float64), on samples
    from well inside the limit to far beyond it, stable and unstable loops (negative gains). No host
    callback is left in the program: JAX's persistent cache never keeps a program that has one."""
    from coopjax import stability
    from coopjax.config import Config

    rng = np.random.default_rng(3)
    n = 48
    params = cj.make_params(
        K_GP=10 ** rng.uniform(-1, 2.5, n) * rng.choice([1.0, 1.0, 1.0, -1.0], n),
        G_e=10 ** rng.uniform(0, 3.5, n),
        M_b=10 ** rng.uniform(-1, 1.5, n),
        tau=10 ** rng.uniform(-2, 0.5, n),
    )
    for scenario, dt in (("carry", 1e-3), ("paper", 4e-3)):
        config = Config.of(scenario, dt=dt).validate()
        eig = stability.fastest_modes(params, config)
        concrete = (stability.growing_mode(eig) > 0) | (dt > cj.INTEGRATORS[config.method].stable_dt(eig))
        traced = jax.jit(lambda p: stability.beyond_limit(p, config))
        assert 0 < concrete.sum() < n  # both kinds present
        np.testing.assert_array_equal(np.asarray(traced(params)), concrete)
        assert "callback" not in traced.lower(params).as_text()


def test_the_switch_on_limit_does_not_hang_on_round_off():
    """The check linearises the loop at switch-on just above F_lim, on the switch-on field's side of
    the kink. On sets near Table 1 the stable step is then the same from float32 parameters (what a
    traced float32 run marks with) as from float64 ones (what `check_step` refuses with), to the
    1e-3 that float32's operating point (64 of its units of round-off above F_lim) moves the fast
    mode; taken at F_lim itself, round-off put each sample on either side, and the two differed by
    up to 20x on one set in ten."""
    from coopjax import stability
    from coopjax.config import Config
    from coopjax.params import as_batched

    rng = np.random.default_rng(1)
    n, table1 = 256, cj.make_params()
    names = ("K_GP", "K_GI", "G_e", "tau", "M_b", "K_g", "F_lim")
    params = cj.make_params(**{k: float(getattr(table1, k).ravel()[0]) * 3 ** rng.uniform(-1, 1, n) for k in names})
    config = Config.of("carry", dtype="float32").validate()
    limit64, _ = stability.stable_dt(params, config)
    J = jax.jit(lambda p: stability._jacobians(as_batched(p)[0], config.scenario, config.options))(config.cast(params))
    assert J.dtype == jnp.float32
    limit32 = cj.INTEGRATORS["filippov"].stable_dt(np.linalg.eigvals(np.asarray(J, np.float64)))
    np.testing.assert_allclose(limit32, limit64, rtol=1e-3)
