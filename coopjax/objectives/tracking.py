"""Tracking: the RMS lag of each tip behind its reference while the amnesia loop wins it back.

The mean square is the trapezoidal time mean over the lag window's grid points. A plain mean of the
samples weights the window's two ends by a whole step each: an O(dt) error whose derivative, at
dt = 1e-3, moved d rms_lag / d K_GP by 1 % (the README example).
"""

from __future__ import annotations

import jax.numpy as jnp

from coopjax import model
from coopjax.objectives.base import Metric, register


def _update(total, obs, params, ctx):
    x_r = model.unpack(obs.y)["x_r"]
    k0, k1 = ctx.window("lag") or (0, -1)
    weight = jnp.where((obs.k == k0) | (obs.k == k1), 0.5, 1.0) * ctx.inside("lag", obs.k)
    return total + weight.astype(total.dtype) * ((obs.aux.x_ref - x_r) ** 2).sum(0)


def _finalize(total, ctx):
    bounds = ctx.grid_window("lag")
    span = 0 if bounds is None else bounds[1] - bounds[0]  # the window's length in grid steps
    # In the run's steps: `substeps` per grid step (a traced count where the run is refined).
    return jnp.sqrt(total / (2 * span * ctx.substeps)) if span > 0 else jnp.full_like(total, jnp.nan)


RMS_LAG = register(
    Metric(
        "rms_lag",
        "m",
        "RMS of x_ref - x_r over the lag window and both robots (trapezoidal in time)",
        lambda b, d, ctx: jnp.zeros(tuple(b), d),
        _update,
        _finalize,
        windows=("lag",),
    )
)
