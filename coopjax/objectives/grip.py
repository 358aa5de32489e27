"""The grip metrics: the least and largest grip force, and the squared excursions past the band.

- min_grip [N]: the least grip force over the grip window, both robots;
- peak_grip [N]: the largest grip force over the whole run;
- peak_hold [N]: the largest grip force over the hold window (the squeeze, the carry and the
  release), so that a re-contact with the drifting body near the horizon does not count;
- slip [N^2]: the time mean over the grip window of sum_i max(0, F_lim - F_i)^2, the lower limit;
- crush [N^2]: the time mean over the grip window of sum_i max(0, F_i - F_max)^2, the upper band;
- impact [N^2]: as crush, over the rest of the run after the grip window (release and re-contact).

They are taken over the force's path through each step (`Observation.path`), not only at the
step grid: an impact jumps the force inside a step, and a metric sampled on the grid alone would
jump by a step's worth each time the impact crossed a grid point as a parameter moved. Its value
would then be right to O(dt) but its derivative wrong. The means are trapezoidal integrals over the
pieces the integrator cut the step into; the peak sees the force at every cut, the minimum at the located events.

With a scenario's `after_reach`, a robot's grip counts from the moment its force first reaches
F_lim: the claim of the paper's Fig. 6 is about the grip once established.
"""

from __future__ import annotations

import jax.numpy as jnp

from coopjax.objectives.base import Metric, register
from coopjax.params import Spec

F_MAX = {"F_max": Spec(15.0, "N", False, "finite", "upper force band of the crush and impact metrics")}


def _robots(batch_shape, dtype, value):
    return jnp.full((2,) + tuple(batch_shape), value, dtype)


def _reached(batch_shape, dtype, ctx):
    return _robots(batch_shape, dtype, 0.0) if ctx.scenario.after_reach else None


def _reach(reached, F, params):
    return None if reached is None else jnp.maximum(reached, (F >= params.F_lim).astype(F.dtype))


def _step_inside(ctx, name, k):
    """Whether the step [t_k, t_k+1] lies in the named window."""
    bounds = ctx.window(name)
    if bounds is None:
        return jnp.zeros_like(k, bool)
    return (k >= bounds[0]) & (k < bounds[1])


# --- min_grip: (least force, reached flags); with after_reach also the largest force, which a robot
# that never reaches F_lim reports instead.


def _min_init(batch_shape, dtype, ctx):
    peak = _robots(batch_shape, dtype, -jnp.inf) if ctx.scenario.after_reach else None
    return (_robots(batch_shape, dtype, jnp.inf), peak, _reached(batch_shape, dtype, ctx))


def _min_update(acc, obs, params, ctx):
    least, peak, reached = acc
    F = obs.aux.F
    now = _reach(reached, F, params)
    in_window = ctx.inside("grip", obs.k)
    sample = jnp.broadcast_to(in_window, F.shape) if now is None else in_window & (now > 0)
    F_counted = F
    if now is not None:
        # The force passed through F_lim inside the step that first reaches it, so the exact minimum
        # after reaching includes F_lim itself (a scenario with after_reach starts its contact at rest:
        # no impact jumps over F_lim).
        F_counted = jnp.where((now > 0) & (reached == 0) & (obs.k > 0), jnp.minimum(F, params.F_lim), F)
    least = jnp.where(sample, jnp.minimum(least, F_counted), least)
    if obs.path is not None and obs.path.impact is not None:
        # Between grid points, the events whose force is known: just before a robot's impact (its
        # force jumps there, the grid can miss the separation) and a located switch (F = F_lim by
        # definition). Other cuts are not counted: which cuts a step makes depends on the grid, and
        # the minimum would move with it.
        path = obs.path
        inside = _step_inside(ctx, "grip", obs.k)
        counted = inside if now is None else inside & (now > 0)
        for j in range(path.fraction.shape[0] - 1):
            at_event = jnp.where(path.impact[j], path.end[j], jnp.where(path.surface[j], params.F_lim, jnp.inf))
            least = jnp.where(counted, jnp.minimum(least, at_event), least)
    if peak is not None:
        peak = jnp.maximum(peak, F)
    return (least, peak, now if now is not None else reached)


def _min_finalize(acc, ctx):
    least, peak, _ = acc
    if ctx.duration("grip") == 0:
        return jnp.full(least.shape[1:], jnp.nan, least.dtype)
    if peak is None:
        return least.min(0)
    return jnp.where(jnp.isinf(least), peak, least).min(0)


MIN_GRIP = register(
    Metric(
        "min_grip",
        "N",
        "least grip force over the grip window (both robots)",
        _min_init,
        _min_update,
        _min_finalize,
        windows=("grip",),
    )
)


# --- peak_grip


def _peak_update(peak, obs, params, ctx):
    F = obs.aux.F
    if obs.path is not None:  # an impact's jump inside the step
        F = jnp.maximum(F, jnp.maximum(obs.path.start.max(0), obs.path.end.max(0)))
    return jnp.maximum(peak, F)


PEAK_GRIP = register(
    Metric(
        "peak_grip",
        "N",
        "largest grip force over the whole run, impacts inside a step included",
        lambda b, d, ctx: _robots(b, d, -jnp.inf),
        _peak_update,
        lambda peak, ctx: peak.max(0),
    )
)


# --- peak_hold: peak_grip over the steps inside the hold window


def _peak_hold_update(peak, obs, params, ctx):
    F = jnp.where(ctx.inside("hold", obs.k), obs.aux.F, -jnp.inf)
    if obs.path is not None:  # the step's path, while the step lies in the window
        jump = jnp.maximum(obs.path.start.max(0), obs.path.end.max(0))
        F = jnp.maximum(F, jnp.where(_step_inside(ctx, "hold", obs.k), jump, -jnp.inf))
    return jnp.maximum(peak, F)


def _peak_hold_finalize(peak, ctx):
    if ctx.window("hold") is None:
        return jnp.full(peak.shape[1:], jnp.nan, peak.dtype)
    return peak.max(0)


PEAK_HOLD = register(
    Metric(
        "peak_hold",
        "N",
        "largest grip force over the hold window (squeeze, carry and release), impacts inside a step included",
        lambda b, d, ctx: _robots(b, d, -jnp.inf),
        _peak_hold_update,
        _peak_hold_finalize,
        windows=("hold",),
    )
)


# --- the time means: trapezoidal integrals over each step's two pieces


def _integral(excess, obs, params, ctx, dt, reached):
    """sum_i of the integral over the step of excess(F_i)^2 (robots that have reached F_lim, with a
    reached flag given)."""
    path = obs.path
    g = lambda x: excess(x, params) ** 2
    total = 0.0
    for j in range(path.fraction.shape[0]):
        piece = 0.5 * path.fraction[j][None] * (g(path.start[j]) + g(path.end[j]))
        if reached is not None:  # each piece counts from the moment its robot has reached F_lim
            reached = _reach(reached, path.start[j], params)
            piece = jnp.where(reached > 0, piece, 0.0)
            reached = _reach(reached, path.end[j], params)
        total = total + piece
    return dt * total.sum(0)


def _window_mean(excess, window):
    def init(batch_shape, dtype, ctx):
        return jnp.zeros(tuple(batch_shape), dtype), _reached(batch_shape, dtype, ctx)

    def update(acc, obs, params, ctx):
        total, reached = acc
        now = _reach(reached, obs.aux.F, params)
        if obs.path is not None:
            inside = _step_inside(ctx, window, obs.k).astype(total.dtype)
            total = total + inside * _integral(excess, obs, params, ctx, ctx.h, now)
        return total, now if now is not None else reached

    def finalize(acc, ctx):
        span = ctx.duration(window)
        return acc[0] / span if span else jnp.full_like(acc[0], jnp.nan)

    return init, update, finalize


SLIP = register(
    Metric(
        "slip",
        "N^2",
        "time mean over the grip window of sum_i max(0, F_lim - F_i)^2",
        *_window_mean(lambda F, p: jnp.maximum(p.F_lim - F, 0.0), "grip"),
        windows=("grip",),
    )
)
CRUSH = register(
    Metric(
        "crush",
        "N^2",
        "time mean over the grip window of sum_i max(0, F_i - F_max)^2",
        *_window_mean(lambda F, p: jnp.maximum(F - p.F_max[None], 0.0), "grip"),
        parameters=F_MAX,
        windows=("grip",),
    )
)


# --- impact: crush over the rest of the run after the grip window


def _impact_update(total, obs, params, ctx):
    if obs.path is None:
        return total
    bounds = ctx.window("grip")
    after = (obs.k >= (bounds[1] if bounds else 0)).astype(total.dtype)
    return total + after * _integral(lambda F, p: jnp.maximum(F - p.F_max[None], 0.0), obs, params, ctx, ctx.h, None)


def _impact_finalize(total, ctx):
    bounds = ctx.grid_window("grip")  # on the grid of dt: the same span at every substep count
    span = max(0, ctx.n_steps - (bounds[1] if bounds else 0)) * ctx.dt
    return total / span if span else jnp.full_like(total, jnp.nan)


IMPACT = register(
    Metric(
        "impact",
        "N^2",
        "as crush, over the rest of the run after the grip window (release)",
        lambda b, d, ctx: jnp.zeros(tuple(b), d),
        _impact_update,
        _impact_finalize,
        parameters=F_MAX,
        windows=("grip",),
    )
)
