"""coopjax against an independent integrator, and RK4's convergence order."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import coopjax as cj
import reference_model as ref


# The carry case takes 80 000 steps (13 s); the paper case and the blend test below keep Radau in CI.
@pytest.mark.parametrize(
    "scenario, T, dt", [("paper", 3.0, 1e-4), pytest.param("carry", 4.0, 5e-5, marks=pytest.mark.slow)]
)
def test_smooth_model_agrees_with_scipy_radau(scenario, T, dt):
    every = int(round(0.01 / dt))
    sol = cj.simulate(cj.make_params(), scenario, switch="smooth", dt=dt, every=every)
    t = np.asarray(sol.trajectory.t)
    ours = np.asarray(sol.trajectory.aux.F)  # (n, 2)

    reference = solve_ivp(
        lambda t, y: ref.rhs(t, y, scenario)[0],
        (0.0, T),
        np.zeros(20),
        method="Radau",
        t_eval=t,
        rtol=1e-10,
        atol=1e-12,
    )
    assert reference.success, reference.message
    theirs = np.array([ref.rhs(tk, yk, scenario)[1] for tk, yk in zip(reference.t, reference.y.T)])
    error = np.max(np.abs(ours - theirs)) / np.max(np.abs(theirs))
    assert error < 1e-4, error
    # The states too, in coopjax's layout.
    y_ref = ref.to_coopjax_order(reference.y[:, -1])
    np.testing.assert_allclose(np.asarray(sol.y_final), y_ref, rtol=1e-4, atol=1e-4 * np.abs(y_ref).max())


@pytest.mark.slow
def test_blend_model_agrees_with_scipy_radau():
    """The blend surrogate (a `coopjax tune --switch` option) against the reference's own blend, over grip and carry."""
    gains = dict(K_GP=0.054, K_GI=0.078, tau=2.93, G_e=1224.0, M_b=2.0)
    dt, T = 1e-4, 2.0
    sol = cj.simulate(cj.make_params(**gains), "carry", switch="blend", dt=dt, T=T, every=100)
    t = np.asarray(sol.trajectory.t)
    ours = np.asarray(sol.trajectory.aux.F)
    p = {**ref.TABLE1, **gains}
    reference = solve_ivp(
        lambda t, y: ref.rhs(t, y, "carry", p, "blend")[0],
        (0.0, T),
        np.zeros(20),
        method="Radau",
        t_eval=t,
        rtol=1e-10,
        atol=1e-12,
    )
    assert reference.success, reference.message
    theirs = np.array([ref.rhs(tk, yk, "carry", p, "blend")[1] for tk, yk in zip(reference.t, reference.y.T)])
    assert theirs.max() > 20.0  # the carry really loads the pushing gripper
    error = np.max(np.abs(ours - theirs)) / np.max(np.abs(theirs))
    assert error < 1e-4, error


@pytest.mark.slow
def test_rk4_converges_with_order_four():
    # Wider surrogates keep the loop smooth enough to be in RK4's asymptotic regime; steps of
    # 1/2^k put the profile's kinks (t = 1 s) on step boundaries.
    params = cj.make_params(k_F=2.0, k_c=2.0, eps_delta=1e-3)
    run = lambda dt: np.asarray(cj.simulate(params, "carry", switch="smooth", dt=dt, T=1.5).y_final)
    exact = run(1 / 16384)
    dts = np.array([1 / 512, 1 / 1024, 1 / 2048, 1 / 4096])
    errors = np.array([np.max(np.abs(run(dt) - exact)) for dt in dts])
    order = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert 3.7 < order < 4.4, (order, errors)


@pytest.mark.slow
def test_blend_surrogate_tracks_the_hard_sliding_motion_where_smooth_substitution_does_not():
    """The sigmoid substitution of the smooth surrogates does not converge to the hard model on F = F_lim.

    On the sliding surface the hard switch's chatter averages the switch-off and switch-on fields
    (Filippov); substituting a fractional w into a field that is nonlinear in w gives another motion.
    The blend surrogate averages the fields, so it keeps the hard model's crush and grip.
    """
    gains = dict(K_GP=0.054, K_GI=0.078, tau=2.93, G_e=1224.0, M_b=1.5)
    hard = cj.simulate(cj.make_params(**gains), "carry", switch="hard", dt=1e-3).metrics  # filippov: the dt -> 0 limit
    narrow = dict(k_F=0.05, k_c=0.05, eps_delta=1e-5)
    blend = cj.simulate(cj.make_params(**gains, **narrow), "carry", switch="blend", dt=5e-5, check_dt=False).metrics
    smooth = cj.simulate(cj.make_params(**gains, **narrow), "carry", switch="smooth", dt=5e-5, check_dt=False).metrics
    assert float(hard.min_grip) >= 10.0 - 0.01
    assert abs(float(blend.min_grip) - float(hard.min_grip)) < 0.5
    assert abs(float(blend.crush) / float(hard.crush) - 1) < 0.15
    assert float(smooth.crush) / float(hard.crush) > 2.0
