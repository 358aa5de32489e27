"""Tracking: the RMS lag of each tip behind its reference while the amnesia loop wins it back."""

from __future__ import annotations

import jax.numpy as jnp

from coopjax import model
from coopjax.objectives.base import Metric, register


def _update(total, obs, params, ctx):
    x_r = model.unpack(obs.y)["x_r"]
    inside = ctx.inside("lag", obs.k).astype(total.dtype)
    return total + inside * ((obs.aux.x_ref - x_r) ** 2).sum(0)


def _finalize(total, ctx):
    n = ctx.count("lag")
    return jnp.sqrt(total / (2 * n)) if n else jnp.full_like(total, jnp.nan)


RMS_LAG = register(Metric("rms_lag", "m", "RMS of x_ref - x_r over the lag window and both robots",
                          lambda b, d, ctx: jnp.zeros(tuple(b), d), _update, _finalize))
