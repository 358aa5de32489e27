"""The paper's own equations by simulation: Eq. 5 and Eq. 7 (driving-point stiffness) as the static
deflection of the ground robot. Eq. 4 (admittance) is checked through `coopjax.linearize` in
test_analysis.py.

This uses the ground-robot harness `model.ground_robot_field`, which runs the same `controller`
function as the full two-robot model, with gamma frozen at alpha.
"""

import jax
import jax.numpy as jnp
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
