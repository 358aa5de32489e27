"""Plain fixed-step RK4 on the model's field, whatever the switch (hard, smooth, blend, straight-through).

With the hard switch it chatters across F = F_lim and converges to the sliding motion only at
O(dt) (MODEL.md section 8); `filippov` is the integrator for that case.
"""

from __future__ import annotations

from coopjax import model
from coopjax.scenarios import Clock


def rk4(f, t, y, dt, k1=None):
    """One classical RK4 step of dy/dt = f(t, y); pass k1 = f(t, y) if already known."""
    k1 = f(t, y) if k1 is None else k1
    k2 = f(t + dt / 2, y + (dt / 2) * k1)
    k3 = f(t + dt / 2, y + (dt / 2) * k2)
    k4 = f(t + dt, y + dt * k3)
    return y + (dt / 6) * (k1 + 2 * k2 + 2 * k3 + k4)


def step(params, y, t, dt, scenario, options):
    """y(t) -> (y(t + dt), F and x_ref at t, None): the loop's step protocol (no located impact force)."""

    def field(t, y):
        return model.vector_field(params, y, Clock.at(t), scenario, options)

    k1, aux = field(t, y)
    return rk4(lambda t, y: field(t, y)[0], t, y, dt, k1), aux.F, aux.x_ref, None


def observe(params, y, t, dt, scenario, options) -> model.Aux:
    """The signals recorded at (t, y)."""
    return model.vector_field(params, y, Clock.at(t), scenario, options)[1]
