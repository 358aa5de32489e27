"""The metric interface and registry, the accumulator the loop runs, and the combined loss."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping, NamedTuple

import jax
import jax.numpy as jnp

from coopjax.errors import InputError
from coopjax.integration import Observation
from coopjax.params import Params, Spec, declare
from coopjax.scenarios import Scenario
from coopjax.status import Status


class Context(NamedTuple):
    """What a metric knows of the run: the scenario (its windows), the step and the step count.

    `dt` and `n_steps` are the grid the windows are drawn on. A run at `substeps` steps of
    dt / substeps per grid step (a traced count: one program for a step and its halvings, which is
    how the two-step check and the judge's refinements run) counts its steps `k` on the finer grid;
    `h` is its step. The windows must then lie on the grid of dt (`on_grid`), so that each window
    holds the same instants whatever the count. What a metric decides in Python (whether a window is
    empty, its duration) is read on the grid of dt, so it stays static.
    """

    scenario: Scenario
    dt: float
    n_steps: int
    substeps: Any = 1

    @property
    def h(self):
        """The run's step: dt / substeps."""
        return self.dt if _is_one(self.substeps) else self.dt / self.substeps

    def grid_window(self, name: str) -> tuple[int, int] | None:
        """Inclusive bounds of a scenario window on the grid of dt (None without the window)."""
        if name not in self.scenario.windows:
            return None
        t0, t1 = self.scenario.windows[name]
        k0 = max(0, math.ceil(t0 / self.dt - 1e-9))
        k1 = min(self.n_steps, math.floor(t1 / self.dt + 1e-9))
        return k0, k1

    def window(self, name: str):
        """Inclusive step-index bounds of a scenario window, in the run's steps (None if the
        scenario has none by that name). A horizon that ends before the window leaves it empty
        (count 0)."""
        bounds = self.grid_window(name)
        if bounds is None or _is_one(self.substeps):
            return bounds
        return bounds[0] * self.substeps, bounds[1] * self.substeps

    def count(self, name: str) -> int:
        """The window's grid points on the grid of dt (0: the window is missing or empty)."""
        bounds = self.grid_window(name)
        return 0 if bounds is None else max(0, bounds[1] - bounds[0] + 1)

    def duration(self, name: str) -> float:
        """The window's length in s (0.0 without the window): the same at every substep count."""
        bounds = self.grid_window(name)
        return 0.0 if bounds is None else max(0, bounds[1] - bounds[0]) * self.dt

    def inside(self, name: str, k):
        """Whether sample k lies in the named window (a traced bool; False without the window)."""
        bounds = self.window(name)
        if bounds is None:
            return jnp.zeros_like(k, bool)
        return (k >= bounds[0]) & (k <= bounds[1])


def _is_one(substeps) -> bool:
    return isinstance(substeps, int) and substeps == 1


def on_grid(scenario: Scenario, dt: float, T: float) -> bool:
    """Whether the horizon and every window's ends lie on the grid of dt (to 1e-9 of a step): then a
    run at dt / r, for any r, counts r times the grid's steps in each window, as a run configured
    at dt / r would."""
    ends = [T, *(t for pair in scenario.windows.values() for t in pair)]
    return all(abs(t / dt - round(t / dt)) < 1e-9 for t in ends)


@dataclasses.dataclass(frozen=True)
class Metric:
    """One per-sample result of a run.

    `init(batch_shape, dtype, ctx)` -> the accumulator (any pytree of arrays);
    `update(acc, obs, params, ctx)` -> the accumulator after sample `obs` (an `Observation`);
    `finalize(acc, ctx)` -> the value, shape of the batch.
    `parameters` are any the metric reads that the model does not have (declared with it);
    `windows` the scenario windows it is taken over (a scenario without one of them gives NaN).
    """

    name: str
    unit: str
    doc: str
    init: Callable[[tuple, Any, Context], Any]
    update: Callable[[Any, Observation, Params, Context], Any]
    finalize: Callable[[Any, Context], jax.Array]
    parameters: Mapping[str, Spec] = dataclasses.field(default_factory=dict)
    windows: tuple[str, ...] = ()


METRICS: dict[str, Metric] = {}
# Bookkeeping that every run reports beside the registered metrics; `status` is derived from them.
STATUS_FIELDS = {
    "finite": "1 if the run did not diverge, else 0",
    "t_diverged": "s, when it diverged (NaN if it did not)",
}
RESERVED = (*STATUS_FIELDS, "status")


def register(metric: Metric) -> Metric:
    """Make a metric known by name; its parameters are declared with it."""
    if metric.name in METRICS and METRICS[metric.name] is not metric:
        raise ValueError(f"a metric named {metric.name!r} is already registered")
    if metric.name in RESERVED:
        raise ValueError(f"{metric.name!r} is reported by every run already")
    declare(f"metric {metric.name}", dict(metric.parameters))
    METRICS[metric.name] = metric
    return metric


def missing_windows(metric: str, scenario: Scenario) -> tuple[str, ...]:
    """The windows `metric` needs that `scenario` lacks (there the metric is NaN)."""
    return tuple(w for w in METRICS[metric].windows if w not in scenario.windows)


def check_names(names) -> tuple[str, ...]:
    names = tuple(names)
    for name in names:
        if name not in METRICS:
            raise InputError(f"unknown metric {name!r}; choose from: {', '.join(METRICS)}", "metrics")
    if len(set(names)) != len(names):
        raise InputError(f"metrics: {', '.join(names)} names one twice", "metrics")
    return names


@jax.tree_util.register_pytree_with_keys_class
class Metrics:
    """Per-sample results by name (NaN where the sample diverged; see `finite` and `t_diverged`).

    Reads like a NamedTuple: `m.min_grip`, `m._fields`, `m._asdict()`, iteration over the values.
    """

    __slots__ = ("_values",)

    def __init__(self, values: dict):
        object.__setattr__(self, "_values", dict(values))

    def __getattr__(self, name):
        values = object.__getattribute__(self, "_values")
        try:
            return values[name]
        except KeyError:
            raise AttributeError(f"no metric {name!r} in this run; it has: {', '.join(values)}") from None

    def __setattr__(self, name, value):
        raise AttributeError("Metrics is immutable: use ._replace(...)")

    def __reduce__(self):
        return Metrics, (self._values,)

    def __getitem__(self, key):
        return list(self._values.values())[key] if isinstance(key, int) else self._values[key]

    def __iter__(self):
        return iter(self._values.values())

    def __len__(self):
        return len(self._values)

    def __repr__(self):
        return f"Metrics({', '.join(self._values)})"

    @property
    def status(self):
        """Per sample, the run's own `coopjax.status.Status`: OK, or DIVERGED where it did not stay
        finite. (A sweep's checks of the loop and the step add the other codes.)"""
        return jnp.where(self._values["finite"], Status.OK, Status.DIVERGED)

    @property
    def _fields(self) -> tuple[str, ...]:
        return tuple(self._values)

    def _asdict(self) -> dict:
        return dict(self._values)

    def _replace(self, **values) -> "Metrics":
        return Metrics({**self._values, **values})

    def tree_flatten_with_keys(self):
        return [(jax.tree_util.GetAttrKey(k), v) for k, v in self._values.items()], tuple(self._values)

    def tree_flatten(self):
        return list(self._values.values()), tuple(self._values)

    @classmethod
    def tree_unflatten(cls, names, values):
        return cls(dict(zip(names, values)))


class MetricSet(NamedTuple):
    """The metrics of one run, bound to its scenario, step and length: the loop's accumulator."""

    names: tuple[str, ...]
    scenario: Scenario
    dt: float
    n_steps: int
    substeps: Any = 1  # traced: steps of dt / substeps (`Context`)

    @property
    def context(self) -> Context:
        return Context(self.scenario, self.dt, self.n_steps, self.substeps)

    def init(self, batch_shape, dtype):
        return {n: METRICS[n].init(batch_shape, dtype, self.context) for n in self.names}

    def update(self, acc, obs: Observation, params: Params):
        ctx = self.context
        return {n: METRICS[n].update(acc[n], obs, params, ctx) for n in self.names}

    def finalize(self, acc, diverged, t_diverged) -> Metrics:
        ctx = self.context
        values = {}
        for n in self.names:
            values[n] = METRICS[n].finalize(acc[n], ctx)
        values["finite"] = jnp.ones_like(diverged)
        values["t_diverged"] = jnp.where(diverged, t_diverged, jnp.nan)
        return mark_unusable(Metrics(values), diverged)


def mark_unusable(metrics: Metrics, bad) -> Metrics:
    """Metrics with the samples where `bad` holds marked: NaN values whose derivatives are NaN too,
    and finite False. (A `where` would pass a cotangent of 0 to them, so `grad` would give 0.0, a
    derivative an optimiser trusts; a product with NaN gives NaN in forward and reverse mode.)"""
    poison = jnp.where(bad, jnp.nan, 1.0)
    values = {}
    for name, value in metrics._asdict().items():
        if name == "finite":
            values[name] = value & ~bad
        elif name == "t_diverged":
            values[name] = value
        else:
            values[name] = value * poison.astype(value.dtype)  # a product: NaN in both modes
    return Metrics(values)


class Weights(NamedTuple):
    """Weights of the combined objective slip + crush + lag.

    The loss is  slip / N^2 * w_slip + crush / N^2 * w_crush + (rms_lag / lag_scale) ** 2 * w_lag.
    With the defaults, a 1 N shortfall throughout the window, a 1 N excess and a 10 mm RMS lag
    each cost 1.
    """

    slip: float = 1.0
    crush: float = 1.0
    lag: float = 1.0
    lag_scale: float = 0.01  # m


def loss(metrics: Metrics, weights: Weights = Weights()) -> jax.Array:
    """Scalar objective per sample (shape of the batch); average or soft-max it over masses."""
    return (
        weights.slip * metrics.slip
        + weights.crush * metrics.crush
        + weights.lag * (metrics.rms_lag / weights.lag_scale) ** 2
    )
