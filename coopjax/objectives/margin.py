"""The grip margin: how much of the switch's authority is left while the grip holds.

- min_swi [-]: the least time-averaged switch value over the grip window, both robots.

While a robot's force is above F_lim its switch is on (swi = 1); on F = F_lim the hard switch
slides, and its time average is the Filippov weight w in (0, 1) that holds the force there; below
F_lim it is off (0). The grip is lost when a robot sliding on F = F_lim needs a weight below 0, so
w's least value over the grip window is the distance to losing it. It is 0 once the grip is lost,
and above 0 while it holds. That makes it the constraint a local solver can see: the grip's own
measures (min grip at F_lim, the shortfall at 0) stay flat while the grip holds, and give no
derivative to step along. With the smooth surrogates, swi is the sigmoid; with plain RK4 on the hard
switch, a chattering 0 or 1 (no margin).
"""

from __future__ import annotations

import jax.numpy as jnp

from coopjax.objectives.base import Metric, register


def _update(least, obs, params, ctx):
    inside = ctx.inside("grip", obs.k)
    return jnp.where(inside, jnp.minimum(least, obs.aux.w), least)


def _finalize(least, ctx):
    if ctx.count("grip") == 0:
        return jnp.full(least.shape[1:], jnp.nan, least.dtype)
    return least.min(0)


MIN_SWI = register(
    Metric(
        "min_swi",
        "1",
        "least time-averaged switch swi over the grip window (both robots): the grip margin, 0 once the grip is lost",
        lambda b, d, ctx: jnp.full((2,) + tuple(b), jnp.inf, d),
        _update,
        _finalize,
        windows=("grip",),
    )
)
