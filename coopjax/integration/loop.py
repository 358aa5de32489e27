"""The integration loop shared by every integrator: `lax.scan` over fixed steps, streaming the samples
into the metrics' accumulators, with per-sample divergence flags.

Everything here is pure and unjitted, so it composes with `jax.grad`, `jax.jacfwd` and `jax.vmap`;
`coopjax.simulate` is the jitted, validated entry point. The loop knows the metrics only as an
accumulator with `init(batch_shape, dtype)`, `update(acc, observation, params)` and
`finalize(acc, diverged, t_diverged)` (`coopjax.objectives.MetricSet`).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp

from coopjax import model
from coopjax.errors import InputError
from coopjax.integration.base import DECISIONS, INTEGRATORS, Observation, Path
from coopjax.params import Params
from coopjax.scenarios import get


class Settings(Protocol):
    """What the loop reads of a run's configuration (`coopjax.Config` provides it)."""

    scenario: str
    dt: float
    force_bound: float

    @property
    def method(self) -> str: ...

    @property
    def n_steps(self) -> int: ...

    @property
    def options(self) -> model.Options: ...


class Trajectory(NamedTuple):
    """Decimated record: times (n,), states (n, 20, B) and signals (n, 2, B); NaN after divergence."""

    t: jax.Array
    y: jax.Array
    aux: model.Aux

    def state(self, name: str) -> jax.Array:
        """A state by name: `x_r_L`, `v_v_R`, `x_o`, ... (see model.STATE_NAMES)."""
        if name not in model.STATE_NAMES:
            raise InputError(f"unknown state {name!r}; choose from: {', '.join(model.STATE_NAMES)}", "name")
        return self.y[:, model.STATE_NAMES.index(name)]


class Solution(NamedTuple):
    metrics: object  # coopjax.objectives.Metrics
    y_final: jax.Array  # (20, B)
    trajectory: Trajectory | None
    # Per sample, why its metrics are (or are not) an answer: `coopjax.status.Status` codes
    # (`simulate` sets it: ok, diverged, or with check_dt "mark" an unstable loop or a step beyond
    # the limit). `metrics.finite` is `status == ok`.
    status: jax.Array | None = None


def batched_leaves(solution) -> "Solution":
    """Which leaves of a Solution carry the batch as their last axis: all but the record times."""
    flags = jax.tree_util.tree_map(lambda _: True, solution)
    if solution.trajectory is not None:
        flags = flags._replace(trajectory=flags.trajectory._replace(t=False))
    return flags


def _zero_from(params: Params) -> jax.Array:
    """0 per sample (B,), computed from every parameter of that sample (a non-finite one gives NaN)."""
    total = 0.0
    for leaf in jax.tree_util.tree_leaves(params):
        total = total + (
            leaf.reshape((-1,) + params.batch_shape).sum(0) if leaf.ndim > len(params.batch_shape) else leaf
        )
    return 0.0 * total


def step(params: Params, y: jax.Array, t, settings: Settings) -> jax.Array:
    """The pure closed-loop step of the configured integrator: state at t -> state at t + dt."""
    integrator = INTEGRATORS[settings.method]
    return integrator.step(model.robots(params), y, t, settings.dt, get(settings.scenario), settings.options)[0]


def integrate(
    params: Params,
    settings: Settings,
    metrics,
    *,
    every: int | None = None,
    checkpoint=True,
    unroll: int = 1,
    substeps=None,
) -> Solution:
    """Run the closed loop from rest over the horizon. Params must carry a batch axis.

    `every` records the state and signals every this many steps (None: metrics only). Under
    reverse-mode differentiation, `checkpoint=True` rematerialises each step except the values its
    integrator names as its path (`base.DECISIONS`; memory grows with the number of steps, one carry
    and one path each); "nested" also checkpoints blocks of sqrt(n) steps, so memory
    grows with sqrt(n) at the cost of one more forward pass; "segment" checkpoints only the blocks
    and keeps every intermediate inside one (sqrt(n) steps of them), which on CPU is the slowest
    (benchmarks/derivative_cost.py); False stores every intermediate.

    `substeps` (a traced int32 scalar; `metrics` built with the same) runs `substeps` steps of
    dt / substeps per step of the configured grid: one program for a step and its halvings (the
    two-step check, the judge's refinements), where the horizon and the windows lie on the grid
    (`objectives.on_grid`). Not with `every`, and not for reverse mode (its inner loop has a traced
    trip count).
    """
    scenario = get(settings.scenario)
    options, dt, n = settings.options, settings.dt, settings.n_steps
    dtype = params.M_b.dtype
    if substeps is not None:
        if every is not None:
            raise InputError("a run with traced substeps records no trajectory: pass every=None", "every")
        dt = jnp.asarray(dt, dtype) / substeps.astype(dtype)
    batch = params.batch_shape
    integrator = INTEGRATORS[settings.method]
    views = model.robots(params)  # split once, outside the time loop (see `model.robots`)

    def observe(t, y):
        return integrator.observe(views, y, t, dt, scenario, options)

    def advance(carry, k):
        y, acc, diverged, t_div = carry
        t = k.astype(dtype) * dt
        y_new, aux, path = integrator.step(views, y, t, dt, scenario, options)
        if path is None:  # a step the integrator does not cut: one piece, to the force at its end
            path = Path.whole(aux.F, observe(t + dt, y_new).F)
        acc_new = metrics.update(acc, Observation(k, t, y, aux, path), params)
        acc = jax.tree_util.tree_map(lambda new, old: jnp.where(diverged, old, new), acc_new, acc)
        # A non-finite state or an absurd force freezes the sample at its last good state, so its
        # garbage never reaches the metrics; the other samples are independent by construction.
        bad = ~jnp.isfinite(y_new).all(0) | (jnp.abs(aux.F) > settings.force_bound).any(0)
        t_div = jnp.where(bad & ~diverged, t + dt, t_div)
        diverged = diverged | bad
        y = jnp.where(diverged[None], y, y_new)
        return (y, acc, diverged, t_div), None

    if checkpoint in (True, "nested"):
        # The step is recomputed from its carry, but not the path it took (`DECISIONS`).
        advance = jax.checkpoint(advance, policy=jax.checkpoint_policies.save_only_these_names(DECISIONS))

    def steps(carry, k0, count):
        ks = k0 + jnp.arange(count, dtype=jnp.int32)
        return jax.lax.scan(advance, carry, ks, unroll=min(unroll, max(count, 1)))[0]

    def run(carry, k0, count):
        if checkpoint not in ("nested", "segment") or count < 4:
            return steps(carry, k0, count)
        size = math.isqrt(count)
        n_blocks, tail = divmod(count, size)
        block = jax.checkpoint(lambda c, kb: (steps(c, k0 + kb * size, size), None))
        carry = jax.lax.scan(block, carry, jnp.arange(n_blocks, dtype=jnp.int32))[0]
        return steps(carry, k0 + n_blocks * size, tail) if tail else carry

    # The initial carry is made to depend on the parameters (by adding a zero that does): under jvp
    # or vmap, scan then sees tangents and batch axes in its carry from the start. Otherwise it
    # traces its body again until they settle, and every scan inside it as often: that made the
    # gradient's tracing take several seconds.
    anchor = _zero_from(params)
    start = (model.init_state(params), metrics.init(batch, dtype))
    start = jax.tree_util.tree_map(
        lambda x: x + jnp.broadcast_to(anchor, x.shape).astype(x.dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x,
        start,
    )
    carry = (*start, jnp.zeros(batch, bool), jnp.full(batch, jnp.inf, dtype) + anchor)
    if substeps is not None:  # one loop of n * substeps steps (a while loop, as scan's own)
        carry = jax.lax.fori_loop(0, n * substeps, lambda k, c: advance(c, k)[0], carry)
        records = None
    elif every is None:
        carry = run(carry, 0, n)
        records = None
    else:
        n_blocks, tail = divmod(n, every)

        def block(carry, kb):
            k0 = kb * every
            y = carry[0]
            record = (k0.astype(dtype) * dt, y, observe(k0.astype(dtype) * dt, y))
            return run(carry, k0, every), record

        carry, records = jax.lax.scan(block, carry, jnp.arange(n_blocks, dtype=jnp.int32))
        if tail:
            carry = run(carry, n_blocks * every, tail)

    # The final sample t_N = T, which no step started from.
    y, acc, diverged, t_div = carry
    t_end = jnp.asarray(n * settings.dt, dtype)
    k_end = jnp.int32(n) if substeps is None else n * substeps
    aux_end = observe(t_end, y)
    acc_end = metrics.update(acc, Observation(k_end, t_end, y, aux_end, None), params)
    acc = jax.tree_util.tree_map(lambda new, old: jnp.where(diverged, old, new), acc_end, acc)
    result = metrics.finalize(acc, diverged, t_div)

    trajectory = None
    if records is not None:
        ts, ys, auxs = jax.tree_util.tree_map(lambda r, e: jnp.concatenate([r, e[None]]), records, (t_end, y, aux_end))
        after = ts[:, None] >= t_div[None]  # (n, B)

        def blank(x):
            return jnp.where(after[:, None], jnp.nan, x)

        trajectory = Trajectory(ts, blank(ys), jax.tree_util.tree_map(blank, auxs))
    return Solution(result, y, trajectory)
