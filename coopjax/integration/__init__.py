"""Integration layer: the shared loop (`loop`) and the integrators it runs, side by side.

- `rk4`: plain fixed-step RK4, for any switch.
- `filippov`: the sliding-mode step for the hard switch (SLIDING.md), the default for it.
"""

from coopjax.integration.loop import (CONVERGED_DT, INTEGRATORS, SimConfig, Solution, Trajectory, default_integrator, integrate,
                                      simulate, step)
from coopjax.integration.plain_rk4 import rk4
