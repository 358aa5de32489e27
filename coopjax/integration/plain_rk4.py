"""Plain fixed-step RK4 on the model's field, whatever the switch (hard, smooth, blend, straight-through).

With the hard switch it chatters across F = F_lim and converges to the sliding motion only at O(dt)
(docs/model.md, "Step size"); `filippov` is the integrator for that case.
"""

from __future__ import annotations

import jax.numpy as jnp

from coopjax import model, surrogates
from coopjax.integration.base import Integrator, Path, register
from coopjax.integration.tableau import RK4
from coopjax.scenarios import Clock


def rk4(f, t, y, dt, k1=None):
    """One classical RK4 step of dy/dt = f(t, y) (`tableau.RK4`); pass k1 = f(t, y) if already known."""
    k = [f(t, y) if k1 is None else k1]
    for a in RK4.a[1:]:
        k.append(f(t + a * dt, y + (a * dt) * k[-1]))
    weighted = [b * kj for b, kj in zip(RK4.b, k)]
    return y + (dt / RK4.denominator) * sum(weighted[1:], weighted[0])


def contact_forces(params, y, options):
    """Both grip forces (2, B) at the state y: the contact alone, no field."""
    st = model.split(y)
    return jnp.stack(
        [
            surrogates.contact_force(params[i], *model.geometry(params[i], st[i], model.SIGNS[i])[:2], options)
            for i in range(2)
        ]
    )


@register
class PlainRK4(Integrator):
    name = "rk4"
    description = (
        "plain RK4: the only choice for the smooth switches; with the hard switch a chattering, O(dt) approximation"
    )
    switches = ("hard", "smooth", "blend", "straight_through")
    default_for = ("smooth", "blend", "straight_through")
    converged_dt = {
        ("carry", "hard"): None,  # 10 of 16 samples at 1e-5; some gain sets need ~1e-7
        ("carry", "straight_through"): None,  # its forward pass is the hard model under plain RK4
        ("carry", "smooth"): 1e-4,  # the smooth model's own limit, which is not the hard model's
        ("paper", "hard"): 1e-3,
        ("paper", "smooth"): 1e-3,
    }

    def step(self, params, y, t, dt, scenario, options):
        def field(t, y):
            return model.vector_field(params, y, Clock.at(t), scenario, options)

        k1, aux = field(t, y)
        new = rk4(lambda t, y: field(t, y)[0], t, y, dt, k1)
        return new, aux, Path.whole(aux.F, contact_forces(params, new, options))

    def observe(self, params, y, t, dt, scenario, options) -> model.Aux:
        return model.vector_field(params, y, Clock.at(t), scenario, options)[1]
