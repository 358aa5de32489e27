"""The grip metrics: the least and largest grip force, and the squared excursions past the band.

- min_grip [N]: the least grip force over the grip window, both robots;
- peak_grip [N]: the largest grip force over the whole run, impacts located inside a step included
  (sampling the force only on the step grid misses part of an impact's jump);
- slip [N^2]: mean over the grip window of sum_i max(0, F_lim - F_i)^2, the lower limit;
- crush [N^2]: mean over the grip window of sum_i max(0, F_i - F_max)^2, the upper band;
- impact [N^2]: as crush, over the rest of the run after the grip window (release and re-contact).

With a scenario's `after_reach`, a robot's grip samples count from the moment its force first
reaches F_lim: the claim of the paper's Fig. 6 is about the grip once established.
"""

from __future__ import annotations

import jax.numpy as jnp

from coopjax.objectives.base import Metric, register
from coopjax.params import Spec

F_MAX = {"F_max": Spec(15.0, "N", False, "finite", "upper force band of the crush and impact metrics")}


def _counted(reached, obs, params, ctx):
    """Per robot, whether this sample counts in the grip window, and the reached flags after it
    (kept only for a scenario with `after_reach`: in the scan's carry they cost memory traffic)."""
    F = obs.aux.F
    in_grip = ctx.inside("grip", obs.k)
    if not ctx.scenario.after_reach:
        return jnp.broadcast_to(in_grip, F.shape), None
    now = jnp.maximum(reached, (F >= params.F_lim).astype(F.dtype))
    return in_grip & (now > 0), now


def _robots(batch_shape, dtype, value):
    return jnp.full((2,) + tuple(batch_shape), value, dtype)


def _reached(batch_shape, dtype, ctx):
    return _robots(batch_shape, dtype, 0.0) if ctx.scenario.after_reach else None


# --- min_grip: its accumulator is (least force, largest force, reached flags), each (2, B); the last
# two only with after_reach (a robot that never reaches F_lim reports its peak).


def _min_init(batch_shape, dtype, ctx):
    peak = _robots(batch_shape, dtype, -jnp.inf) if ctx.scenario.after_reach else None
    return (_robots(batch_shape, dtype, jnp.inf), peak, _reached(batch_shape, dtype, ctx))


def _min_update(acc, obs, params, ctx):
    least, peak, reached = acc
    F = obs.aux.F
    counted, now = _counted(reached, obs, params, ctx)
    if now is None:
        return (jnp.where(counted, jnp.minimum(least, F), least), peak, reached)
    F_counted = F
    if ctx.scenario.after_reach:
        # The force passed through F_lim inside the step that first reaches it, so the exact minimum
        # after reaching includes F_lim itself; the first grid sample alone sits up to dF/dt * dt above
        # it (0.23 N at dt = 1e-3 in the paper scenario). Only a scenario whose contact starts at rest
        # (no impact that could jump over F_lim) should use after_reach.
        newly = (now > 0) & (reached == 0) & (obs.k > 0)
        F_counted = jnp.where(newly, jnp.minimum(F, params.F_lim), F)
    return (jnp.where(counted, jnp.minimum(least, F_counted), least), jnp.maximum(peak, F), now)


def _min_finalize(acc, ctx):
    least, peak, _ = acc
    if ctx.count("grip") == 0:
        return jnp.full(least.shape[1:], jnp.nan, least.dtype)
    if peak is None:
        return least.min(0)
    # A robot that never reached F_lim (only possible with after_reach) reports its peak instead.
    return jnp.where(jnp.isinf(least), peak, least).min(0)


MIN_GRIP = register(Metric("min_grip", "N", "least grip force over the grip window (both robots)",
                           _min_init, _min_update, _min_finalize))


# --- peak_grip


def _peak_update(peak, obs, params, ctx):
    F = obs.aux.F if obs.F_impact is None else jnp.maximum(obs.aux.F, obs.F_impact)
    return jnp.maximum(peak, F)


PEAK_GRIP = register(Metric("peak_grip", "N", "largest grip force over the whole run, located impacts included",
                            lambda b, d, ctx: _robots(b, d, -jnp.inf), _peak_update, lambda peak, ctx: peak.max(0)))


# --- slip and crush: sums over the grip window, with the reached flags for after_reach


def _window_sum(excess):
    def init(batch_shape, dtype, ctx):
        return jnp.zeros(tuple(batch_shape), dtype), _reached(batch_shape, dtype, ctx)

    def update(acc, obs, params, ctx):
        total, reached = acc
        counted, now = _counted(reached, obs, params, ctx)
        term = jnp.where(counted, excess(obs.aux.F, params) ** 2, 0.0).sum(0)
        return total + term, reached if now is None else now

    def finalize(acc, ctx):
        n = ctx.count("grip")
        return acc[0] / n if n else jnp.full_like(acc[0], jnp.nan)

    return init, update, finalize


SLIP = register(Metric("slip", "N^2", "mean over the grip window of sum_i max(0, F_lim - F_i)^2",
                       *_window_sum(lambda F, p: jnp.maximum(p.F_lim - F, 0.0))))
CRUSH = register(Metric("crush", "N^2", "mean over the grip window of sum_i max(0, F_i - F_max)^2",
                        *_window_sum(lambda F, p: jnp.maximum(F - p.F_max[None], 0.0)), parameters=F_MAX))


# --- impact: crush over the rest of the run after the grip window


def _impact_update(total, obs, params, ctx):
    bounds = ctx.window("grip")
    after = (obs.k > (bounds[1] if bounds else -1)).astype(total.dtype)
    return total + after * (jnp.maximum(obs.aux.F - params.F_max[None], 0.0) ** 2).sum(0)


def _impact_finalize(total, ctx):
    bounds = ctx.window("grip")
    n = max(0, ctx.n_steps - (bounds[1] if bounds else -1))
    return total / n if n else jnp.full_like(total, jnp.nan)


IMPACT = register(Metric("impact", "N^2", "as crush, over the rest of the run after the grip window (release)",
                         lambda b, d, ctx: jnp.zeros(tuple(b), d), _impact_update, _impact_finalize, parameters=F_MAX))
