"""The paper's own equations: Eq. 4 (admittance), Eq. 5 and Eq. 7 (driving-point stiffness).

Both use the ground-robot harness `model.ground_robot_field`, which runs the same `controller`
function as the full two-robot model, with gamma frozen at alpha.
"""

import control
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import coopjax as cj
from coopjax import model
from coopjax.integration import rk4

TABLE1 = dict(mu_H=300.0, beta_H=300.0, K_c=500.0, K_f=10.0, M_c=10.0, R_c=5.0, M_f=1.0, R_f=200.0, M_r=1.0)


def k_rob(alpha, p=TABLE1):
    """Eq. 5: 1/K_rob = 1/(mu_H K_c) + beta_H (1 - alpha) / (mu_H K_f)."""
    return 1.0 / (1.0 / (p["mu_H"] * p["K_c"]) + p["beta_H"] * (1 - alpha) / (p["mu_H"] * p["K_f"]))


def test_eq5_worked_example_from_model_md():
    assert k_rob(0.5) == pytest.approx(19.997, abs=5e-4)
    assert k_rob(1.0) == pytest.approx(150000.0)  # Eq. 7


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.1])
def test_eq5_static_deflection_under_constant_effort(alpha):
    params = cj.make_params()
    E, dt, n = 2.0, 5e-3, 60_000  # 300 s: the slowest mode decays at 0.05 1/s

    def body(y, _):
        return rk4(lambda t, y: model.ground_robot_field(params, y, E, alpha), 0.0, y, dt), None

    y, _ = jax.lax.scan(body, jnp.zeros(5), None, length=n)
    velocity = float(y[1])
    deflection = float(y[0])
    assert abs(velocity) < 1e-9 * abs(deflection) / dt
    assert E / deflection == pytest.approx(k_rob(alpha), rel=1e-3)


@pytest.mark.parametrize("alpha", [1.0, 0.5, 0.1])
def test_eq4_admittance_from_the_simulators_linearisation(alpha):
    params = cj.make_params()
    rest = jnp.zeros(5)
    A = jax.jacfwd(lambda y: model.ground_robot_field(params, y, 0.0, alpha))(rest)
    B = jax.jacfwd(lambda e: model.ground_robot_field(params, rest, e, alpha))(0.0)
    C = np.eye(5)[1]  # output: tip velocity v_r
    simulator = control.ss(np.asarray(A), np.asarray(B)[:, None], C[None], 0.0)

    p = TABLE1
    s = control.tf("s")
    R = 1 / (p["M_r"] * s)
    Cc = (p["M_c"] * s**2 + p["R_c"] * s + p["K_c"]) / s
    F = s / (p["M_f"] * s**2 + p["R_f"] * s + p["K_f"])
    g = p["beta_H"] * (1 - alpha)

    omega = np.logspace(-2, 3, 25)
    for w in omega:
        z = 1j * w
        # Eq. 4, evaluated pointwise so no polynomial cancellation can blur it.
        Rz, Cz, Fz = R(z), Cc(z), F(z)
        eq4 = Rz * (1 + g * Fz * Cz) / (1 + p["mu_H"] * Cz * Rz + g * Fz * Cz)
        ours = complex(simulator(z))
        assert abs(ours - eq4) <= 1e-6 * abs(eq4), (w, ours, eq4)
