"""Scenarios: command profiles in closed form, with their horizon, metric windows and amplitudes.

A scenario is one `Scenario` registered with `register`, in a file of its own (`paper.py`,
`carry.py`). It declares the amplitude parameters it reads, so `make_params`, sweeps and the
command line know them, and names the windows its metrics are taken over ("grip", "lag").

The paper's profile is V(t; t0, A) = A (1 - cos 2 pi (t - t0)). Its rest-to-rest form (`bump`) lives
on [t0, t0 + 1): it starts and ends with zero velocity and acceleration and moves exactly A metres, so
bumps add up without kinks that would spoil RK4's order.

A `Clock` carries t with cos 2 pi t and sin 2 pi t. The sliding-mode integrator needs commands at
per-sample sub-step times: `Clock.advance` rotates the step-start phase by the sub-step instead of
calling cos/sin per sample, which dominated a first version's cost. A bump starting at t0 takes its
phase from the clock's by angle subtraction with the constants cos 2 pi t0, sin 2 pi t0.
"""

from coopjax.scenarios.base import SCENARIOS, TWO_PI, Clock, Scenario, bump, get, profile, register, stacked
from coopjax.scenarios import carry, paper  # noqa: E402,F401  (the built-in scenarios register themselves)

__all__ = ["Clock", "SCENARIOS", "Scenario", "TWO_PI", "bump", "get", "profile", "register", "stacked"]
