"""The integration loop shared by every integrator: `lax.scan` over fixed steps, streaming metrics and
per-sample divergence flags.

An integrator is a module with `step(params, y, t, dt, scenario, options) -> (y_next, F, x_ref, F_impact)`
(F and x_ref at t, for the metrics) and `observe(params, y, t, dt, scenario, options) -> aux`: `rk4` (plain RK4, any switch) and
`filippov` (the sliding-mode step for the hard switch, SLIDING.md). `F_impact` is the contact force
just after a located impact (or None), which the peak metric must see (MODEL.md section 7).

The jit boundary is `simulate`: everything below it is pure and unjitted, so it composes with
`jax.grad`, `jax.jacfwd` and `jax.vmap`. Static settings (scenario, switch, dt, T, ...) live in a
hashable `SimConfig`; changing one recompiles, changing a parameter value does not.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import model, objectives
from coopjax.integration import filippov, plain_rk4
from coopjax.params import Params, as_batched, check_positive
from coopjax.scenarios import get_scenario

INTEGRATORS = {"filippov": filippov, "rk4": plain_rk4}


# Largest steps measured to be within MODEL.md section 8's tolerances of the dt -> 0 limit of the
# same model (benchmarks/convergence.py; docs/model.md, "Step size"). None: no step tried reached
# them on every sample. A combination missing here was not measured.
CONVERGED_DT = {
    ("carry", "hard", "filippov"): 2e-3,  # 16 of 16 samples, at 2e-3 and every finer step
    ("carry", "hard", "rk4"): None,  # 10 of 16 samples at 1e-5; some gain sets need ~1e-7
    ("carry", "straight_through", "rk4"): None,  # its forward pass is the hard model under plain RK4
    ("carry", "smooth", "rk4"): 1e-4,  # the smooth model's own limit, which is not the hard model's
    ("paper", "hard", "filippov"): 1e-3,  # no sliding: forces within 1e-3 N of rk4 at 1e-4
    ("paper", "hard", "rk4"): 1e-3,
    ("paper", "smooth", "rk4"): 1e-3,
}


def step_size_note(scenario: str, switch: str, integrator: str, dt: float) -> str | None:
    """A sentence for a user whose step is coarser than the model needs, or None."""
    key = (scenario, switch, integrator)
    if key not in CONVERGED_DT:
        return None
    converged = CONVERGED_DT[key]
    if converged is None:
        return (f"note: plain rk4 chatters across F = F_lim with the {switch} switch; in the {scenario} scenario "
                "it met MODEL.md's tolerances on only 10 of 16 samples even at dt = 1e-5 (docs/model.md, "
                "'Step size'). --integrator filippov meets them at dt = 1e-3")
    if dt > converged * (1 + 1e-9):
        return (f"note: {scenario} with the {switch} switch and {integrator} needs dt <= {converged:g} s to be "
                f"within MODEL.md's tolerances of the dt -> 0 limit (docs/model.md, 'Step size'); this run "
                f"used dt = {dt:g} s")
    return None


def default_integrator(switch: str) -> str:
    """The sliding-mode step for the hard switch; plain RK4 for the smooth surrogates."""
    return "filippov" if switch == "hard" else "rk4"


MAX_STEPS = 2**31 - 1


@dataclasses.dataclass(frozen=True)
class SimConfig:
    scenario: str = "carry"
    options: model.Options = model.Options()
    integrator: str | None = None  # "filippov" | "rk4"; None: filippov for the hard switch, else rk4
    dt: float = 1e-3  # s
    T: float | None = None  # s; None takes the scenario's horizon
    every: int | None = None  # record every N steps; None records nothing (metrics only)
    force_bound: float = 1e6  # N; a force beyond this counts as divergence
    # Under reverse-mode differentiation: True rematerialises each step (memory grows with the number
    # of steps, one carry each); "nested" also checkpoints blocks of sqrt(n) steps, so memory grows
    # with sqrt(n) at the cost of one more forward pass; False stores every intermediate.
    checkpoint: bool | str = True
    unroll: int = 1  # lax.scan unroll: 2 and 4 compiled 1.5-2x slower and ran no faster (measured)

    @property
    def method(self) -> str:
        return self.integrator or default_integrator(self.options.switch)

    @property
    def horizon(self) -> float:
        return self.T if self.T is not None else get_scenario(self.scenario).T

    @property
    def n_steps(self) -> int:
        # Rounded, not truncated: T/dt is rarely an exact float.
        return max(1, int(round(self.horizon / self.dt)))

    def validate(self) -> "SimConfig":
        get_scenario(self.scenario)
        model.check_options(self.options)
        if self.method not in INTEGRATORS:
            raise ValueError(f"unknown integrator {self.method!r}; choose one of: {', '.join(INTEGRATORS)}")
        if self.method == "filippov" and self.options.switch != "hard":
            raise ValueError(f"the filippov integrator is for the hard switch (it treats it as a sliding mode); "
                             f"the {self.options.switch} switch runs with rk4 (--integrator rk4, or integrator='rk4')")
        check_positive("dt", self.dt)
        if self.T is not None:
            check_positive("T", self.T)
        if self.every is not None and (not isinstance(self.every, (int, np.integer)) or self.every < 1):
            raise ValueError(f"every is {self.every!r}: it must be a whole number of steps, at least 1")
        if self.checkpoint not in (True, False, "nested"):
            raise ValueError(f"checkpoint is {self.checkpoint!r}: choose True, False or 'nested'")
        if self.dt > self.horizon:
            raise ValueError(f"dt = {self.dt:g} s is longer than the horizon T = {self.horizon:g} s")
        if self.horizon / self.dt > MAX_STEPS:
            raise ValueError(f"T / dt = {self.horizon:g} s / {self.dt:g} s = {self.horizon / self.dt:.3g} steps; at most "
                             f"{MAX_STEPS:,} (a 32-bit step counter): use a larger dt or a shorter T")
        if self.every is not None and self.every > self.n_steps:
            raise ValueError(f"every = {self.every} is more than the run's {self.n_steps} steps: nothing would be "
                             f"recorded after t = 0 (use every <= {self.n_steps})")
        return self


class Trajectory(NamedTuple):
    """Decimated record: times (n,), states (n, 20, B) and signals (n, 2, B); NaN after divergence."""

    t: jax.Array
    y: jax.Array
    aux: model.Aux

    def state(self, name: str) -> jax.Array:
        """A state by name: `x_r_L`, `v_v_R`, `x_o`, ... (see model.STATE_NAMES)."""
        return self.y[:, model.STATE_NAMES.index(name)]


class Solution(NamedTuple):
    metrics: objectives.Metrics
    y_final: jax.Array  # (20, B)
    trajectory: Trajectory | None


def step(params: Params, y: jax.Array, t, config: SimConfig) -> jax.Array:
    """The pure closed-loop step of the configured integrator: state at t -> state at t + dt."""
    method = INTEGRATORS[config.method]
    return method.step(params, y, t, config.dt, get_scenario(config.scenario), config.options)[0]


def integrate(params: Params, config: SimConfig) -> Solution:
    """Run the closed loop from rest over the horizon. Params must carry a batch axis.

    Pure and unjitted; `simulate` is the jitted, validated entry point.
    """
    scenario = get_scenario(config.scenario)
    options, dt, n = config.options, config.dt, config.n_steps
    win = objectives.window(scenario, dt, n)
    dtype = params.M_b.dtype
    batch = params.batch_shape

    method = INTEGRATORS[config.method]
    views = model.robots(params)  # split once, outside the time loop (see `model.robots`)

    def observe(t, y):
        return method.observe(views, y, t, dt, scenario, options)

    def advance(carry, k):
        y, acc, diverged, t_div = carry
        t = k.astype(dtype) * dt
        y_new, F, x_ref, F_impact = method.step(views, y, t, dt, scenario, options)
        x_r = model.unpack(y)["x_r"]
        acc_new = objectives.accumulate(acc, F, x_ref, x_r, params, k, win, F_impact)
        acc = jnp.where(diverged[None], acc, acc_new)
        # A non-finite state or an absurd force freezes the sample at its last good state, so its
        # garbage never reaches the metrics; the other samples are independent by construction.
        bad = ~jnp.isfinite(y_new).all(0) | (jnp.abs(F) > config.force_bound).any(0)
        t_div = jnp.where(bad & ~diverged, t + dt, t_div)
        diverged = diverged | bad
        y = jnp.where(diverged[None], y, y_new)
        return (y, acc, diverged, t_div), None

    if config.checkpoint:
        advance = jax.checkpoint(advance)

    def steps(carry, k0, count):
        ks = k0 + jnp.arange(count, dtype=jnp.int32)
        return jax.lax.scan(advance, carry, ks, unroll=min(config.unroll, max(count, 1)))[0]

    def run(carry, k0, count):
        if config.checkpoint != "nested" or count < 4:
            return steps(carry, k0, count)
        size = math.isqrt(count)
        n_blocks, tail = divmod(count, size)
        block = jax.checkpoint(lambda c, kb: (steps(c, k0 + kb * size, size), None))
        carry = jax.lax.scan(block, carry, jnp.arange(n_blocks, dtype=jnp.int32))[0]
        return steps(carry, k0 + n_blocks * size, tail) if tail else carry

    y0 = model.init_state(params)
    carry = (
        y0,
        objectives.init(batch, dtype),
        jnp.zeros(batch, bool),
        jnp.full(batch, jnp.inf, dtype),
    )

    if config.every is None:
        carry = run(carry, 0, n)
        records = None
    else:
        every = config.every
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
    t_end = jnp.asarray(n * dt, dtype)
    aux_end = observe(t_end, y)
    x_r = model.unpack(y)["x_r"]
    acc_end = objectives.accumulate(acc, aux_end.F, aux_end.x_ref, x_r, params, jnp.int32(n), win)
    acc = jnp.where(diverged[None], acc, acc_end)
    metrics = objectives.finalize(acc, win, diverged, t_div)

    trajectory = None
    if records is not None:
        ts, ys, auxs = jax.tree_util.tree_map(
            lambda r, e: jnp.concatenate([r, e[None]]), records, (t_end, y, aux_end)
        )
        after = ts[:, None] >= t_div[None]  # (n, B)

        def blank(x):
            return jnp.where(after[:, None], jnp.nan, x)

        trajectory = Trajectory(ts, blank(ys), jax.tree_util.tree_map(blank, auxs))
    return Solution(metrics, y, trajectory)


_integrate_jit = jax.jit(integrate, static_argnums=1)


def run_batch(batched: Params, config: SimConfig) -> tuple[Solution, int]:
    """`integrate` on a batch as `simulate` runs it; returns (solution, samples before padding).

    Over several devices, a concrete 1-D batch is cut into slabs (`devices.slabs`) dispatched one
    after another without waiting, each device running its own slice of a slab; otherwise one jitted
    call on the batch as it is.
    """
    from coopjax.devices import shard, slabs

    n_devices = jax.device_count()
    concrete = not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(batched))
    if not (concrete and n_devices > 1 and len(batched.batch_shape) == 1):
        batched, size = shard(batched)
        return _integrate_jit(batched, config), size
    parts, size = slabs(batched)
    run = _integrate_per_device(config, n_devices)
    parts = [run(slab) for slab in parts]
    if len(parts) == 1:
        return parts[0], size
    cat = lambda *xs: jnp.concatenate(xs, axis=-1)
    trajectory = None
    if parts[0].trajectory is not None:  # the record times have no batch axis
        trajectory = Trajectory(parts[0].trajectory.t, cat(*(q.trajectory.y for q in parts)),
                                jax.tree_util.tree_map(cat, *(q.trajectory.aux for q in parts)))
    metrics = jax.tree_util.tree_map(cat, *(q.metrics for q in parts))
    return Solution(metrics, cat(*(q.y_final for q in parts)), trajectory), size


@functools.lru_cache(maxsize=32)
def _integrate_per_device(config: SimConfig, n_devices: int):
    """`integrate` with each of the first n devices running its own slice of the batch (shard_map)."""
    from coopjax.devices import batch_spec, per_device

    def specs(solution):
        specs = jax.tree_util.tree_map(batch_spec, solution)
        if solution.trajectory is not None:  # the record times have no batch axis
            specs = specs._replace(trajectory=specs.trajectory._replace(t=jax.sharding.PartitionSpec()))
        return specs

    fn = lambda p: integrate(p, config)
    return jax.jit(lambda p: per_device(fn, jax.devices()[:n_devices], specs(jax.eval_shape(fn, p)))(p))


def simulate(
    params: Params,
    scenario: str = "carry",
    *,
    switch: str = "hard",
    contact: str = "unilateral",
    integrator: str | None = None,
    dt: float = 1e-3,
    T: float | None = None,
    every: int | None = None,
    gamma_min: float | None = None,
    force_bound: float = 1e6,
    checkpoint: bool | str = True,
    unroll: int = 1,
    check_dt: bool = True,
) -> Solution:
    """Simulate one parameter set or a batch of them (leaves with a trailing batch axis).

    Args:
      params: from `make_params`; unbatched or with batch shape (B,).
      scenario: "paper" or "carry" (MODEL.md section 5).
      switch: "hard" (the reference), "smooth" or "straight_through" (MODEL.md section 4), or "blend"
        (the switch-off and switch-on fields mixed by the smooth switch; see docs/tuning.md).
      contact: "unilateral" (default) or "bilateral".
      integrator: "filippov" (the default for the hard switch: the sliding-mode step of SLIDING.md,
        converged at dt = 1e-3) or "rk4" (plain RK4; the only choice for the smooth surrogates, and
        with the hard switch a chattering, O(dt) approximation kept for comparison).
      dt: step, s. Checked against the fastest mode of the linearised loop (`check_dt`).
      T: horizon, s; default the scenario's.
      every: record the state and signals every this many steps; None keeps only metrics.

    Returns a `Solution`. Bad static input raises ValueError before anything is traced; a sample
    that diverges is flagged in `metrics.finite` and `metrics.t_diverged` and never raises.
    """
    config = SimConfig(
        scenario=scenario,
        options=model.Options(switch=switch, contact=contact, gamma_min=gamma_min),
        integrator=integrator,
        dt=float(dt) if isinstance(dt, (int, float)) else dt,
        T=None if T is None else (float(T) if isinstance(T, (int, float)) else T),
        every=every,
        force_bound=float(force_bound),
        checkpoint=checkpoint,
        unroll=unroll,
    ).validate()
    if check_dt:
        from coopjax.stability import check_step

        check_step(params, config)
    batched, added = as_batched(params)
    from coopjax.devices import unpad

    if every is not None:
        from coopjax.sweeps import memory_limit

        # t, 20 states and 5 two-robot signals per record and sample.
        size = (config.n_steps // every + 1) * (1 + model.N_STATE + 10) * int(np.prod(batched.batch_shape)) * 8
        if size > memory_limit():
            raise ValueError(f"recording every {every} steps of {config.n_steps} needs {size / 2**30:.3g} GiB, more than "
                             f"half of this machine's memory ({memory_limit() / 2**30:.3g} GiB): record less often")
    solution, n_samples = run_batch(batched, config)
    if int(np.prod(solution.metrics.finite.shape)) != n_samples:
        t = None if solution.trajectory is None else solution.trajectory.t
        solution = unpad(solution, n_samples)
        if t is not None:  # the record times have no batch axis
            solution = solution._replace(trajectory=solution.trajectory._replace(t=t))
    if added:
        squeeze = lambda x: x[..., 0]
        trajectory = solution.trajectory
        if trajectory is not None:
            trajectory = Trajectory(trajectory.t, squeeze(trajectory.y), jax.tree_util.tree_map(squeeze, trajectory.aux))
        solution = Solution(jax.tree_util.tree_map(squeeze, solution.metrics), squeeze(solution.y_final), trajectory)
    return solution
