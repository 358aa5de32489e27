"""Tuning from Python: a problem in, the tuned parameters and their verdict out.

    import jax; jax.config.update("jax_enable_x64", True)   # training and judging are float64
    import tuning
    problem = tuning.Problem.from_toml("docs/problems/peak_bound.toml")
    tuned = tuning.tune(problem, method="screen-SLP", seed=0)
    tuned.params, tuned.verdict.holds, tuned.verdict.requirements

This is `tuning.session` in one call; `coopjax tune` runs the same session and adds checkpoints,
printing and figures.
"""

from __future__ import annotations

import dataclasses

from coopjax.params import Params
from tuning import driver, session
from tuning.problem import Problem
from tuning.session import Options, Tuned
from tuning.tuners import TUNERS, get

DEFAULT_METHOD = "screen-SLP"


def tune(
    problem: Problem | None = None,
    method: str = DEFAULT_METHOD,
    *,
    base: Params | None = None,
    budget: driver.Budget = driver.Budget(),
    progress: bool = False,
    options: Options | None = None,
    **settings,
) -> Tuned:
    """Tune a problem's parameters with a registered tuner, select on validation draws, and judge.

    Args:
      problem: the problem (default: the default `Problem`); it is validated here.
      method: a registered tuner's name (`tuning.TUNERS`): "screen-SLP", "gradient", "CMA-ES", ...
      base: every parameter the problem neither tunes nor draws (default Table 1's), a single set.
      budget: when a tuner that has no end of its own (CMA-ES, random search) stops.
      progress: a progress bar on stderr.
      options: a `tuning.Options`; or give its fields as keywords: `seed`, `starts`, `spread`,
        `held_out`, `again`, `further`, `halvings`, `judge_dt`.
      **settings: the session's options (above), then the tuner's settings (its dataclass fields,
        e.g. `steps=4`).

    Returns:
      `Tuned`: the parameters, their verdict on the held-out draws and on the validation draws, and
      the tuner's run.
    """
    names = {f.name for f in dataclasses.fields(Options)}
    given = {k: settings.pop(k) for k in list(settings) if k in names}
    options = dataclasses.replace(options or Options(), **given)
    prepared = session.prepare(problem, get(method)(**settings), options, base, budget)
    return session.run(prepared, budget=budget, progress=progress)


__all__ = ["DEFAULT_METHOD", "TUNERS", "Tuned", "tune"]
