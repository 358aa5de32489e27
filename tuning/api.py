"""Tuning from Python: a problem in, the tuned parameters and their verdict out.

    import jax; jax.config.update("jax_enable_x64", True)
    import tuning
    problem = tuning.Problem.from_toml("docs/problems/peak_bound.toml")
    tuned = tuning.tune(problem, method="screen-SLP", seed=0)
    tuned.params, tuned.verdict.holds, tuned.verdict.requirements

`coopjax tune` is this with checkpoints, printing and figures.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from coopjax.errors import InputError
from coopjax.params import Params
from tuning import driver
from tuning.judging import JUDGE_DT, Verdict, judge, select
from tuning.problem import Problem, from_log, starting_points
from tuning.tuners import TUNERS, get


class Tuned(NamedTuple):
    """What `tune` found and how it was judged."""

    params: dict  # the tuned names' values
    verdict: Verdict  # on the held-out draws, with the two-step check
    validation: Verdict  # on the validation draws, where it was selected
    result: driver.Result  # the tuner's run: its record, clock and trajectories


def tune(
    problem: Problem | None = None,
    method: str = "screen-SLP",
    *,
    seed: int = 0,
    starts: int = 8,
    spread: float = 2.5,
    base: Params | None = None,
    budget: driver.Budget = driver.Budget(),
    held_out: int = 12,
    judge_dt: float = JUDGE_DT,
    progress: bool = False,
    **settings,
) -> Tuned:
    """Tune a problem's parameters with a registered tuner, select on validation draws, and judge.

    Args:
      problem: the problem (default: the default `Problem`); it is validated here.
      method: a registered tuner's name (`tuning.TUNERS`): "screen-SLP", "gradient", "CMA-ES", ...
      seed: the seed of the starting points, the draws and the tuner.
      starts: starting points; the first is `base`'s values (Table 1's), the others drawn within
        x/÷ e^spread of it.
      spread: see `starts`.
      base: every parameter the problem neither tunes nor draws (default Table 1's), a single set.
      budget: when a tuner that has no end of its own (CMA-ES, random search) stops.
      held_out: held-out draws (one uncertain parameter: a grid with its ends; several: Sobol
        points besides the box's corners).
      judge_dt: the judge's step, s.
      progress: a progress bar on stderr.
      **settings: the tuner's settings (its dataclass fields, e.g. `steps=4`).

    Returns:
      `Tuned`: the parameters, their verdict on the held-out draws and on the validation draws, and
      the tuner's run.
    """
    problem = (problem or Problem()).validate()
    tuner = get(method)(**settings)
    if not tuner.ends() and budget == driver.Budget():
        raise InputError(f"{method} ends only when a budget does: pass budget=tuning.Budget(seconds=...)", "budget")
    base = problem.base(base)
    first = {n: float(np.asarray(base.get(n)).ravel()[0]) for n in problem.names}
    points = starting_points(problem, base, first, starts, spread, seed)
    result = driver.run(tuner, problem, base, points, seed, budget=budget, progress=progress)
    options = [from_log(t, problem.names) for t in tuner.candidates(result.state)]
    if not options:
        raise InputError(f"{method} evaluated nothing within the budget", "budget")
    chosen, verdicts = select(options, problem.validation_draws(), problem, base, judge_dt, check_step=False)
    verdict = judge(options[chosen], problem.held_out_draws(held_out), problem, base, judge_dt)
    return Tuned(options[chosen], verdict, verdicts[chosen], result)


__all__ = ["TUNERS", "Tuned", "tune"]
