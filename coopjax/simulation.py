"""`simulate`: the validated, jitted entry point of a run, on one parameter set or a batch.

It checks every setting and the step against the linearised loop before anything is traced, casts
the parameters to the configuration's dtype, and puts the batch on the devices (`devices.run`).
"""

from __future__ import annotations

import os
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import devices, objectives, scenarios, stability
from coopjax.config import Config, check_every, record_size
from coopjax.errors import InputError
from coopjax.integration import ADJOINTS, INTEGRATORS, Solution, Trajectory, batched_leaves, differentiate, integrate
from coopjax.objectives import mark_unusable
from coopjax.status import Status
from coopjax.params import Params, as_batched
from coopjax.traced import differentiated, is_traced


class Run(NamedTuple):
    """One run's static settings as a hashable callable: params (batched) -> Solution."""

    config: Config
    every: int | None = None
    checkpoint: bool | str = True
    unroll: int = 1
    adjoint: str = "auto"

    def metric_set(self, substeps=1) -> objectives.MetricSet:
        c = self.config
        return objectives.MetricSet(c.metrics, scenarios.get(c.scenario), c.dt, c.n_steps, substeps)

    def __call__(self, params: Params) -> Solution:
        return differentiate(self._integrate, params, batched_leaves, self.adjoint)

    def batch_order(self, params: Params):
        """The integrator's order for a concrete batch (`coopjax.devices.run` asks)."""
        return INTEGRATORS[self.config.method].batch_order(params)

    def _integrate(self, params: Params) -> Solution:
        return integrate(
            params, self.config, self.metric_set(), every=self.every, checkpoint=self.checkpoint, unroll=self.unroll
        )


class MetricsOf(NamedTuple):
    """A run's metrics only, as a hashable callable (what sweeps and the tuner evaluate)."""

    config: Config
    checkpoint: bool | str = True
    adjoint: str = "auto"

    def __call__(self, params: Params):
        return Run(self.config, checkpoint=self.checkpoint, adjoint=self.adjoint)(params).metrics

    def batch_order(self, params: Params):
        return INTEGRATORS[self.config.method].batch_order(params)


def metrics_of(config: Config, checkpoint: bool | str = True, adjoint: str = "auto") -> MetricsOf:
    return MetricsOf(config, checkpoint, adjoint)


class MetricsRefined(NamedTuple):
    """A run's metrics at dt / r, r a traced count: called on `(params, r)`, r an int32 batch whose
    values are all equal (the batch's r is its first). One program for a step and its halvings,
    where `refinable(config)`: a configuration at dt / 2 compiles nothing new. Forward only."""

    config: Config

    def __call__(self, args):
        params, r = args
        substeps = r.reshape(-1)[0]
        metrics = Run(self.config).metric_set(substeps)
        return integrate(params, self.config, metrics, checkpoint=False, substeps=substeps).metrics

    def batch_order(self, args):
        return INTEGRATORS[self.config.method].batch_order(args[0])


def refinable(config: Config) -> bool:
    """Whether `MetricsRefined` can run this configuration: its horizon and windows lie on its grid."""
    return objectives.on_grid(scenarios.get(config.scenario), config.dt, config.horizon)


def memory_limit() -> int:
    """Half of this machine's physical memory, in bytes: the most one table or record may take."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def simulate(
    params: Params,
    config: Config | str = "carry",
    *,
    every: int | None = None,
    checkpoint: bool | str = True,
    adjoint: str = "auto",
    unroll: int = 1,
    check_dt: bool | str = True,
    **settings,
) -> Solution:
    """Simulate one parameter set or a batch of them (leaves with a trailing batch axis).

    Args:
      params: from `make_params`; unbatched or with batch shape (B,).
      config: a `Config`, or a scenario name ("paper", "carry", or any registered one).
      every: record the state and signals every this many steps; None keeps only metrics.
      adjoint: how reverse mode (`grad`, `vjp`) differentiates the run. "forward" pulls back through
        the Jacobian along every differentiated parameter component, computed in forward mode (one
        tangent each): half the program of reverse mode through the loop, and faster for a few
        parameters. "reverse" transposes the time loop (memory as `checkpoint` says). "auto" (the
        default) is "forward" for at most 8 differentiated components and "reverse" above.
        Forward mode (`jvp`, `jacfwd`) gives the same derivatives under all three. Through the
        Jacobian, a loss that takes in a NaN metric (one whose window a short run never reaches)
        has a NaN derivative as well as a NaN value.
      checkpoint: under reverse-mode differentiation through the loop, True rematerialises each
        step from its start but keeps the path the forward pass took (the sliding-mode step's plans
        and cuts); "nested" also checkpoints blocks of sqrt(n) steps (memory grows with sqrt(n));
        "segment" checkpoints the blocks only and stores the steps inside one; False stores
        everything.
      check_dt: True refuses (InputError) a step beyond the stability limit of the linearised loop,
        or an unstable loop; under a trace (jit, grad, vmap), where nothing can be refused, and with
        "mark", such a sample is marked instead: NaN metrics with NaN derivatives, `finite` False,
        as a sweep flags it. False runs every sample as given.
      **settings: any `Config` field, e.g. `switch="smooth"`, `integrator="rk4"`, `dt=2e-3`, `T=1.0`.

    Returns a `Solution`. Bad static input raises InputError before anything is traced; a sample
    that diverges is flagged and never raises: `status` says why a sample's metrics are not an
    answer (`coopjax.status.Status`: diverged, or, where marked, an unstable loop or a step beyond
    its limit), `metrics.finite` is `status == ok`, and `metrics.t_diverged` says when it blew up.
    """
    if not isinstance(params, Params):
        raise InputError(f"params must be a Params from make_params, got {type(params).__name__}", "params")
    config = Config.of(config, **settings).validate()
    check_every(config, every)
    if checkpoint not in (True, False, "nested", "segment"):
        raise InputError(f"checkpoint is {checkpoint!r}: choose True, False, 'nested' or 'segment'", "checkpoint")
    if adjoint not in ADJOINTS:
        raise InputError(f"adjoint is {adjoint!r}: choose {', '.join(map(repr, ADJOINTS))}", "adjoint")
    if isinstance(unroll, bool) or not isinstance(unroll, (int, np.integer)) or unroll < 1:
        raise InputError(f"unroll is {unroll!r}: a whole number, at least 1", "unroll")
    params = config.cast(params)
    if config.switch == "hard" and config.method == "rk4" and differentiated(params):
        warnings.warn(
            "differentiating the hard switch under plain RK4 differentiates its chatter across F = F_lim: "
            "the derivatives are noise (often NaN or huge). Use integrator='filippov' (the default for the hard "
            "switch), whose derivatives are those of the sliding motion (docs/model.md, 'Derivatives')",
            RuntimeWarning,
            stacklevel=2,
        )
    if check_dt not in (True, False, "mark"):
        raise InputError(f"check_dt is {check_dt!r}: choose True, False or 'mark'", "check_dt")
    mark = check_dt == "mark" or (check_dt and is_traced(params))
    if check_dt and not mark:
        stability.check_step(params, config)
    batched, added = as_batched(params)
    if every is not None:
        size = record_size(config, every, int(np.prod(batched.batch_shape)))
        if size > memory_limit():
            raise InputError(
                f"recording every {every} steps of {config.n_steps} needs {size / 2**30:.3g} GiB, more than "
                f"half of this machine's memory ({memory_limit() / 2**30:.3g} GiB): record less often "
                "(a larger every) or run a shorter T",
                "every",
            )
    solution = devices.run(
        Run(config, every, checkpoint, unroll, adjoint),
        batched,
        batched=batched_leaves,
    )
    status = jnp.where(solution.metrics.finite, Status.OK, Status.DIVERGED).astype(jnp.int32)
    if mark:
        # No exception under a trace: a sample whose step is beyond its stability limit is marked as a
        # diverged one is (NaN metrics, NaN derivatives, finite False), never a number to trust.
        limits = stability.step_status(batched, config)
        status = jnp.where(limits != Status.OK, limits, status)
        solution = solution._replace(metrics=mark_unusable(solution.metrics, limits != Status.OK))
    solution = solution._replace(status=status)
    if added:
        squeeze = lambda x: x[..., 0]
        trajectory = solution.trajectory
        if trajectory is not None:
            trajectory = Trajectory(
                trajectory.t, squeeze(trajectory.y), jax.tree_util.tree_map(squeeze, trajectory.aux)
            )
        solution = Solution(
            jax.tree_util.tree_map(squeeze, solution.metrics),
            squeeze(solution.y_final),
            trajectory,
            squeeze(solution.status),
        )
    return solution


__all__ = ["MetricsOf", "Run", "memory_limit", "metrics_of", "simulate"]
