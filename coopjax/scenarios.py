"""Command profiles of MODEL.md section 5, in closed form.

The paper's profile is V(t; t0, A) = A (1 - cos 2 pi (t - t0)). Its rest-to-rest form lives on
[t0, t0 + 1): it starts and ends with zero velocity and zero acceleration and moves exactly A metres,
so bumps can be added without kinks that would spoil RK4's order.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax.numpy as jnp

from coopjax.params import Params

TWO_PI = 2.0 * jnp.pi


def profile(t, t0, A):
    """V(t; t0, A) for all t >= t0 (not rest-to-rest): velocity, acceleration, displacement."""
    u = t - t0
    v = A * (1.0 - jnp.cos(TWO_PI * u))
    a = A * TWO_PI * jnp.sin(TWO_PI * u)
    x = A * (u - jnp.sin(TWO_PI * u) / TWO_PI)
    return v, a, x


def bump(t, t0, A):
    """Rest-to-rest V on [t0, t0 + 1): zero before, and holds the displacement A after."""
    u = t - t0
    inside = (u >= 0.0) & (u < 1.0)
    v, a, x = profile(t, t0, A)
    zero = jnp.zeros_like(v)
    return (
        jnp.where(inside, v, zero),
        jnp.where(inside, a, zero),
        jnp.where(u < 0.0, zero, jnp.where(inside, x, A + zero)),
    )


def _stack(left, right):
    """(v_cmd, a_cmd, x_ref), each of shape (2, B): robot L then robot R."""
    return tuple(jnp.stack([l, r]) for l, r in zip(left, right))


def paper_command(params: Params, t):
    """Fig. 6 of the paper: equal and opposite squeezing velocities, never stopping."""
    return _stack(profile(t, 0.0, params.A_1), profile(t, 0.0, params.A_2))


def carry_command(params: Params, t):
    """Pick (grip), carry 0.5 m in +x, release, settle. s_L = +1, s_R = -1."""
    out = []
    for s in (1.0, -1.0):
        parts = (
            bump(t, 0.0, s * params.A_g),  # grip: each tip's reference goes A_g into the body
            bump(t, 1.0, params.A_c),  # carry: both move A_c in +x
            bump(t, 2.0, -2.0 * s * params.A_g),  # release: back away A_g beyond first touch
        )
        out.append(tuple(sum(p[k] for p in parts) for k in range(3)))
    return _stack(*out)


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A command profile and the windows its metrics are taken over (MODEL.md section 7).

    `grip_window` bounds min_grip, slip and crush; with `after_reach`, a robot's samples count only
    from the moment its force first reaches F_lim (the paper's claim is about what happens after
    the grip is established). `lag_window` bounds the RMS of x_ref - x_r.
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
