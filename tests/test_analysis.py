"""Linear analysis (`coopjax.linearize`): the paper's Eq. 4 and 5 through the public function, the
poles against an independent eigen-decomposition and the dt check, and a linearisation at a
simulated state against a small-perturbation simulation of the nonlinear model."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import coopjax as cj
from coopjax import analysis, model, stability
from coopjax.integration import rk4

TABLE1 = dict(mu_H=300.0, beta_H=300.0, K_c=500.0, K_f=10.0, M_c=10.0, R_c=5.0, M_f=1.0, R_f=200.0, M_r=1.0)
ALPHAS = [1.0, 0.5, 0.1]


def eq4(alpha, s, p=TABLE1):
    """Eq. 4 written out here, independently of coopjax.analysis.admittance_eq4."""
    R = 1 / (p["M_r"] * s)
    C = (p["M_c"] * s**2 + p["R_c"] * s + p["K_c"]) / s
    F = s / (p["M_f"] * s**2 + p["R_f"] * s + p["K_f"])
    g = p["beta_H"] * (1 - alpha)
    return R * (1 + g * F * C) / (1 + p["mu_H"] * C * R + g * F * C)


def eq5(alpha, p=TABLE1):
    return 1.0 / (1.0 / (p["mu_H"] * p["K_c"]) + p["beta_H"] * (1 - alpha) / (p["mu_H"] * p["K_f"]))


@pytest.mark.parametrize("alpha", ALPHAS)
def test_linearised_admittance_is_eq4_at_25_frequencies(alpha):
    sys_ = cj.linearize(analysis.free_robot(cj.make_params()), "limit", alpha=alpha, inputs="e_env_L", outputs="v_r_L")
    assert sys_.input_labels == ["e_env_L"] and sys_.output_labels == ["v_r_L"] and sys_.nstates == 20
    omega = np.logspace(-2, 3, 25)
    ours = np.asarray(sys_(1j * omega)).reshape(-1)
    np.testing.assert_allclose(ours, eq4(alpha, 1j * omega), rtol=1e-6)
    np.testing.assert_allclose(
        analysis.admittance_eq4(cj.make_params(), alpha, 1j * omega), eq4(alpha, 1j * omega), rtol=1e-12
    )


def test_static_stiffness_is_eq5_and_eq7():
    params = cj.make_params()
    for alpha in ALPHAS:
        assert analysis.k_rob(params, alpha) == pytest.approx(eq5(alpha), rel=1e-3)
    assert analysis.k_rob(params, 1.0) == pytest.approx(300.0 * 500.0, rel=1e-6)  # Eq. 7
    # Robot R with its own gains: the linearisation keeps the robots apart.
    right = cj.make_params(K_c_R=250.0, K_f_R=20.0)
    assert analysis.k_rob(right, 0.5, "R") == pytest.approx(eq5(0.5, {**TABLE1, "K_c": 250.0, "K_f": 20.0}), rel=1e-3)
    assert analysis.k_rob(right, 0.5, "L") == pytest.approx(eq5(0.5), rel=1e-3)


def field_jacobian(params, point):
    """The Jacobian written independently of coopjax.analysis: the full `model.vector_field` with
    the hard switch (its derivative is 0 away from the surface) and bilateral contact."""
    p = jax.tree_util.tree_map(lambda x: x[..., None], params)
    if point == "limit":  # on F = F_lim from a pre-compression, just above it so the hard switch is on
        p = p.with_leaves(delta0=p.F_lim * (1 + 1e-12) / p.K_g)
    options = model.Options(switch="hard", contact="bilateral")
    scenario = cj.SCENARIOS["paper"]
    f = lambda y: model.vector_field(p, y[:, None], 0.0, scenario, options)[0][:, 0]
    return np.asarray(jax.jacfwd(f)(jnp.zeros(model.N_STATE)))


@pytest.mark.parametrize("overrides", [{}, dict(K_GP=3.0, K_GI=0.7, G_e=200.0, M_b=4.0, K_c_R=800.0)])
def test_poles_match_eigvals_and_the_dt_check(overrides):
    params = cj.make_params(**overrides)
    config = cj.Config("paper")
    modes = stability.fastest_modes(params, config)[0]  # what `simulate`'s dt check uses, (2 points, 20)
    for k, point in enumerate(("rest", "limit")):
        poles = np.sort_complex(np.asarray(cj.linearize(params, point).poles()))
        independent = np.sort_complex(np.linalg.eigvals(field_jacobian(params, point)))
        scale = np.abs(independent).max()
        np.testing.assert_allclose(poles, independent, atol=1e-8 * scale)
        np.testing.assert_allclose(np.abs(poles).max(), np.abs(modes[k]).max(), rtol=1e-9)
        summary = analysis.poles_summary(poles, 1e-3)
        assert summary["rk4_dt_limit"] == pytest.approx(stability.max_stable_dt(modes[k][None])[0], rel=1e-9)


def test_linearisation_at_a_simulated_state_predicts_a_perturbed_run():
    """Paper scenario at t = 1 s: both grips at about 65 N, force control on, away from the switch.
    Integrate the nonlinear hard model for 20 ms from y(t) and from y(t) + eps v; their difference
    over eps is exp(A tau) v to first order (the Jacobian varies along the run, O(tau^2))."""
    params = cj.make_params()
    t0, tau, dt = 1.0, 0.02, 1e-5
    op = analysis.operating_point(params, t0)
    assert op.w.all() and op.contact.all()
    A = np.asarray(cj.linearize(params, t0).A)

    p = jax.tree_util.tree_map(lambda x: x[..., None], params)
    scenario = cj.SCENARIOS["paper"]
    field = lambda t, y: model.vector_field(p, y, t, scenario, model.Options())[0]

    @jax.jit
    def run(y):
        def body(y, k):
            return rk4(field, t0 + k * dt, y, dt), None

        return jax.lax.scan(body, y, jnp.arange(int(round(tau / dt))))[0]

    rng = np.random.default_rng(0)
    scale = np.maximum(np.abs(op.y), 1e-3)
    v = rng.standard_normal(model.N_STATE) * scale
    eps = 1e-6
    y0 = jnp.asarray(op.y)[:, None]
    nominal = np.asarray(run(y0))[:, 0]
    perturbed = np.asarray(run(y0 + eps * jnp.asarray(v)[:, None]))[:, 0]
    measured = (perturbed - nominal) / eps
    predicted = scipy.linalg.expm(A * tau) @ v
    frozen = v  # what no dynamics at all would predict: the check must beat it by far
    err = np.linalg.norm((measured - predicted) / scale)
    assert err <= 2e-2 * np.linalg.norm(measured / scale), err / np.linalg.norm(measured / scale)
    assert err <= 0.05 * np.linalg.norm((measured - frozen) / scale)


def test_cutting_the_gain_modulation_loop_and_closing_it_again_gives_the_closed_loop():
    import control

    params = cj.make_params()
    loop = analysis.grip_loop(params)  # L = -G, G = gamma_law / gamma_in
    closed = control.feedback(analysis.prune(loop), 1)  # 1 + L = 0
    uncut = np.asarray(cj.linearize(params, "limit").poles())
    for pole in np.asarray(closed.poles()):
        assert np.min(np.abs(uncut - pole)) <= 1e-6 * max(1.0, abs(pole)), pole
    assert analysis.margins(loop)["stability_margin"] > 0


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(point="middle"), "point 'middle'"),
        (dict(inputs="force"), "unknown input 'force'"),
        (dict(outputs=("F_L", "F_L")), "names one twice"),
        (dict(point="rest", alpha=0.5), "use point='limit'"),
        (dict(point="rest", inputs="gamma_L"), "force control is off"),
        (dict(point=-1.0), "time >= 0"),
    ],
)
def test_bad_requests_are_one_clear_value_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        cj.linearize(cj.make_params(), **kwargs)


def test_reference_velocity_input_is_proper_and_moves_the_reference():
    """v_ref enters through v_cmd, its derivative a_ref (a feed-through) and its integral x_ref (two
    added states). At rest the grip's static answer to a step of v_ref_L is a ramp; the DC gain from
    v_ref_L to the tip velocity is 1 (the tip follows the commanded velocity)."""
    sys_ = cj.linearize(cj.make_params(), "rest", inputs="v_ref_L", outputs=("v_r_L", "x_ref_L"))
    assert sys_.nstates == 22 and sys_.state_labels[-2:] == ["x_ref_L", "x_ref_R"]
    H = lambda w: np.asarray(sys_(1j * w)).reshape(2)
    assert H(1e-4)[1] == pytest.approx(1 / (1e-4j), rel=1e-9)  # x_ref = integral of v_ref
    assert abs(H(1e-4)[0] - 1) < 1e-2


def test_analyze_command_writes_its_figures_and_refuses_bad_input(fresh_dir, capsys):
    from coopjax.cli import main

    assert main(["analyze", "--out", "a"]) == 0
    out = capsys.readouterr().out
    for name in ("a.json", "a_bode.png", "a_krob.png", "a_poles.png"):
        assert (fresh_dir / name).stat().st_size > 1000
    result = json.load(open(fresh_dir / "a.json"))
    assert max(result["eq4_max_relative_difference"].values()) < 1e-6
    assert result["margins"]["stability_margin"] == pytest.approx(
        analysis.margins(analysis.grip_loop(cj.make_params()))["stability_margin"], rel=1e-9
    )
    assert "phase margin" in out and "RK4 stable for dt <=" in out
    before = sorted(p.name for p in fresh_dir.iterdir())
    for args in (
        ["--alpha", "1,x"],
        ["--alpha", "1,1"],
        ["--dt", "-1"],
        ["--set", "K_GP=abc"],
        ["--set", "K_GQ=1"],
        ["--out", "nowhere/a"],
        ["--robot", "Q"],
    ):
        assert main(["analyze", *args]) == 2, args
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, (args, err)
    assert sorted(p.name for p in fresh_dir.iterdir()) == before
