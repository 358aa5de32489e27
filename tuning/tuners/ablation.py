"""The ablation of screen-SLP, in the race beside it: what the exact Jacobian contributes, and what
the local solve does.

- `screen-SLP/FD`: the same tuner with central differences (2n + 1 runs per lane and step) in place of
  forward-mode Jacobians: what a design optimiser without derivatives (Simulink Design Optimization's
  fmincon) pays and gets.
- `screen only`: the same screen, continued batch after batch until the clock ends (further CMA-ES
  generations; with search="sobol", further Sobol points), and no local solve.
"""

from __future__ import annotations

import dataclasses

from tuning.tuners.base import register
from tuning.tuners.screen_slp import ScreenSLP


@register
@dataclasses.dataclass(frozen=True)
class ScreenSLPFiniteDifferences(ScreenSLP):
    name = "screen-SLP/FD"
    description = "the ablation: screen-SLP with central differences instead of exact Jacobians"
    plain_run = False  # a study's entrant, not a --method
    jacobian: str = "fd"

    def ends(self) -> bool:  # as screen-SLP does
        return True


@register
@dataclasses.dataclass(frozen=True)
class ScreenOnly(ScreenSLP):
    name = "screen only"
    description = "the ablation: screen-SLP's screen alone, continued until the clock ends"
    plain_run = False  # it ends only when a budget does
    local_solve = False

    def plan_text(self, n_params, starts):
        return f"a screen of {self._screen_text(starts)}, continued until the budget ends"
