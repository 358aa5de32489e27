"""Integration: the interface and registry of integrators, the built-in ones, and the shared loop.

- `base.py`: `Integrator` (one class per integrator), `register`, `Observation` (what a step hands
  to the metrics), the linear stability regions that the step check uses;
- `plain_rk4.py`: plain fixed-step RK4, for any switch;
- `filippov.py`: the sliding-mode step for the hard switch, the default for it;
- `loop.py`: `integrate`, the `lax.scan` over steps shared by every integrator;
- `adjoint.py`: how reverse mode differentiates a run (through a forward-mode Jacobian, or the loop).
"""

from coopjax.integration.base import (
    INTEGRATORS,
    Integrator,
    Observation,
    Path,
    default_for,
    get,
    max_stable_dt,
    register,
    rk4_amplification,
)
from coopjax.integration.adjoint import ADJOINTS, differentiate, tangents_on_copies
from coopjax.integration.loop import Settings, Solution, Trajectory, batched_leaves, integrate, step
from coopjax.integration import filippov  # noqa: E402,F401  (registers itself, first: the CLI lists it first)
from coopjax.integration.plain_rk4 import rk4

__all__ = [
    "ADJOINTS",
    "INTEGRATORS",
    "Integrator",
    "Observation",
    "Path",
    "Settings",
    "Solution",
    "Trajectory",
    "batched_leaves",
    "default_for",
    "differentiate",
    "get",
    "integrate",
    "max_stable_dt",
    "register",
    "rk4",
    "rk4_amplification",
    "step",
    "tangents_on_copies",
]
