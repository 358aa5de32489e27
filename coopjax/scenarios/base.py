"""The scenario interface and registry, and the paper's command profile on a shared clock."""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Mapping, NamedTuple

import jax.numpy as jnp

from coopjax.errors import InputError
from coopjax.params import Spec, declare

TWO_PI = 2.0 * math.pi


def _cos_sin_small(x):
    """cos x and sin x by their Taylor series, for |x| <= 2 pi dt (< 0.7 for any stable dt here).

    Terms to x^11: the truncation error is about 3e-11 at |x| = 0.7 and below float64 round-off for
    the steps in use (|x| <= 0.03).
    """
    x2 = x * x
    cos = 1.0 - x2 / 2 * (1 - x2 / 12 * (1 - x2 / 30 * (1 - x2 / 56 * (1 - x2 / 90))))
    sin = x * (1.0 - x2 / 6 * (1 - x2 / 20 * (1 - x2 / 42 * (1 - x2 / 72 * (1 - x2 / 110)))))
    return cos, sin


class Clock(NamedTuple):
    """Time t (a scalar, or one time per sample) with cos 2 pi t and sin 2 pi t."""

    t: object
    cos: object
    sin: object

    @classmethod
    def at(cls, t) -> "Clock":
        return cls(t, jnp.cos(TWO_PI * t), jnp.sin(TWO_PI * t))

    def advance(self, u) -> "Clock":
        """The clock at t + u for a short u (scalar or per sample): angle addition, no per-sample trig."""
        c, s = _cos_sin_small(TWO_PI * u)
        return Clock(self.t + u, self.cos * c - self.sin * s, self.sin * c + self.cos * s)

    def phase_since(self, t0: float):
        """cos and sin of 2 pi (t - t0) for a constant t0 (exact for a whole number of seconds)."""
        t0 = float(t0)
        if t0.is_integer():
            return self.cos, self.sin
        c0, s0 = math.cos(TWO_PI * t0), math.sin(TWO_PI * t0)
        return self.cos * c0 + self.sin * s0, self.sin * c0 - self.cos * s0


def profile(clock: Clock, t0: float, A):
    """V(t; t0, A) for all t >= t0 (not rest-to-rest): velocity, acceleration, displacement."""
    u = clock.t - t0
    cos, sin = clock.phase_since(t0)
    v = A * (1.0 - cos)
    a = A * TWO_PI * sin
    x = A * (u - sin / TWO_PI)
    return v, a, x


def bump(clock: Clock, t0: float, A):
    """Rest-to-rest V on [t0, t0 + 1): zero before, and holds the displacement A after."""
    u = clock.t - t0
    inside = (u >= 0.0) & (u < 1.0)
    v, a, x = profile(clock, t0, A)
    zero = jnp.zeros_like(v)
    return (
        jnp.where(inside, v, zero),
        jnp.where(inside, a, zero),
        jnp.where(u < 0.0, zero, jnp.where(inside, x, A + zero)),
    )


def stacked(command):
    """A command as (v_cmd, a_cmd, x_ref), each (2, B) with robot L first."""
    return tuple(jnp.stack([left, right]) for left, right in zip(*command))


@dataclasses.dataclass(frozen=True, eq=False)
class Scenario:
    """A command profile, its horizon and the windows its metrics are taken over.

    `command(params, clock)` gives one (v_cmd, a_cmd, x_ref) per robot, L first, each (B,).
    `windows` maps a window's name to its (start, end) in s: the grip metrics use "grip", the
    tracking lag "lag", the squeeze's peak "hold"; a metric whose window a scenario lacks is NaN
    there. With `after_reach`, a robot's grip samples count only from the moment its force first
    reaches F_lim.
    `parameters` are the amplitudes the command reads (shared by both robots).
    """

    name: str
    T: float
    command: Callable
    windows: Mapping[str, tuple[float, float]]
    description: str = ""
    after_reach: bool = False
    parameters: Mapping[str, Spec] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        for name, spec in self.parameters.items():
            if spec.per_robot:
                raise ValueError(f"scenario {self.name}: amplitude {name} must be shared (per_robot=False)")
        for window, (t0, t1) in self.windows.items():
            if not 0 <= t0 <= t1:
                raise ValueError(f"scenario {self.name}: window {window} = ({t0}, {t1}) must have 0 <= start <= end")


SCENARIOS: dict[str, Scenario] = {}


def register(scenario: Scenario) -> Scenario:
    """Make a scenario known by name to `simulate`, sweeps, tuning and the command line."""
    if scenario.name in SCENARIOS and SCENARIOS[scenario.name] is not scenario:
        raise ValueError(f"a scenario named {scenario.name!r} is already registered")
    declare(f"scenario {scenario.name}", dict(scenario.parameters))
    SCENARIOS[scenario.name] = scenario
    return scenario


def get(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except (KeyError, TypeError):
        raise InputError(f"unknown scenario {name!r}; choose one of: {', '.join(SCENARIOS)}", "scenario") from None
