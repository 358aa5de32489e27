"""Command profiles of MODEL.md section 5, in closed form.

The paper's profile is V(t; t0, A) = A (1 - cos 2 pi (t - t0)). Its rest-to-rest form lives on
[t0, t0 + 1): it starts and ends with zero velocity and zero acceleration and moves exactly A metres,
so bumps can be added without kinks that would spoil RK4's order.

Every bump starts at a whole second, so all of them share the phase 2 pi t: cos 2 pi (t - t0) =
cos 2 pi t. A `Clock` carries t with that phase's cosine and sine. The sliding-mode integrator needs
commands at per-sample sub-step times; `Clock.advance` rotates the step-start phase by the sub-step
instead of calling cos/sin per sample (SLIDING.md, "Impacts"), which dominated a first version's cost.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax.numpy as jnp

from coopjax.params import Params

TWO_PI = 2.0 * jnp.pi


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


def profile(clock: Clock, t0, A):
    """V(t; t0, A) for all t >= t0 (not rest-to-rest): velocity, acceleration, displacement.

    t0 must be a whole number of seconds (the phase is shared, see the module docstring).
    """
    u = clock.t - t0
    v = A * (1.0 - clock.cos)
    a = A * TWO_PI * clock.sin
    x = A * (u - clock.sin / TWO_PI)
    return v, a, x


def bump(clock: Clock, t0, A):
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


def paper_command(params: Params, clock: Clock):
    """Fig. 6 of the paper: equal and opposite squeezing velocities, never stopping."""
    unit = profile(clock, 0.0, 1.0)  # V is linear in A: one profile for both robots
    return tuple(tuple(A * x for x in unit) for A in (params.A_1, params.A_2))


def carry_command(params: Params, clock: Clock):
    """Pick (grip), carry 0.5 m in +x, release, settle. s_L = +1, s_R = -1.

    Each phase is a unit bump (a function of t alone, so one value per step, not per sample) times
    its amplitude: grip, each tip's reference goes A_g into the body; carry, both move A_c in +x;
    release, back away A_g beyond first touch.
    """
    grip, carry, release = (bump(clock, t0, 1.0) for t0 in (0.0, 1.0, 2.0))
    return tuple(
        tuple(s * params.A_g * g + params.A_c * c - 2.0 * s * params.A_g * r for g, c, r in zip(grip, carry, release))
        for s in (1.0, -1.0)
    )


def stacked(command):
    """A command as (v_cmd, a_cmd, x_ref), each (2, B) with robot L first."""
    return tuple(jnp.stack([left, right]) for left, right in zip(*command))


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A command profile and the windows its metrics are taken over (MODEL.md section 7).

    `command(params, clock)` gives one (v_cmd, a_cmd, x_ref) per robot, L first, each (B,) (`stacked`
    makes them (2, B)). `grip_window` bounds
    min_grip, slip and crush; with `after_reach`, a robot's samples count only from the moment its
    force first reaches F_lim (the paper's claim is about what happens after the grip is
    established). `lag_window` bounds the RMS of x_ref - x_r.
    """

    name: str
    T: float
    command: Callable
    grip_window: tuple[float, float]
    lag_window: tuple[float, float]
    after_reach: bool
    description: str


SCENARIOS = {
    "paper": Scenario(
        "paper", 3.0, paper_command, (0.0, 3.0), (2.0, 3.0), True,
        "the paper's Fig. 6: +-10 m/s squeeze commands, Table 1 gains, T = 3 s",
    ),
    "carry": Scenario(
        "carry", 4.0, carry_command, (0.5, 2.0), (2.5, 4.0), False,
        "pick, carry 0.5 m, release, settle: the tuning scenario, T = 4 s",
    ),
}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; choose one of: {', '.join(SCENARIOS)}") from None
