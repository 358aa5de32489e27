"""Tuning for coopjax: the hard model itself, differentiated, against a user's requirements.

The public API:

    Problem, Objective, Requirement, Uncertain   a tuning problem as data (`Problem.from_toml` reads a file)
    terms(theta, base, problem, draws)           its differentiable objective and constraints, for a batch
    tune(problem, method, ...)                   tune it with any registered tuner (`TUNERS`), select, judge
    judge(values, draws, problem, ...)           a parameter set's verdict, requirement by requirement
    to_log, from_log                             a parameter dict <-> the log-values tuners work in

The modules:

    design.py       where the uncertain parameters are drawn: training, validation, held-out
    problem_file.py problem files (TOML): read, with errors that name the line; written
    problem.py      the problem, its terms (`terms`), the starting points
    judging.py      how an answer is judged (`judge`) and selected (`select`)
    constrained.py  an augmented Lagrangian on top of optax
    tuners/         the tuner interface and registry; one file per tuner (screen-SLP, Adam-AL, CMA-ES, ...)
    evaluate.py     the evaluator every tuner shares (values, Jacobians, gradients; compile kept apart)
    driver.py       ask / evaluate / tell on a clock and a budget; checkpoints and resume by replay
    api.py          `tune`
    race.py         `--compare`: every registered tuner on one clock over seeds
    plots.py        before/after traces, convergence, the race, the Pareto front
    cli.py          `coopjax tune` (registered with `coopjax` as an entry point)

Imports run one way: `tuning` uses `coopjax`; `coopjax` never imports `tuning`.
"""

from tuning.api import Tuned, tune
from tuning.design import Uncertain
from tuning.driver import Budget
from tuning.judging import Verdict, judge, select
from tuning.problem import Objective, Problem, Requirement, Terms, from_log, terms, to_log
from tuning.tuners import TUNERS

__all__ = [
    "Budget",
    "Objective",
    "Problem",
    "Requirement",
    "TUNERS",
    "Terms",
    "Tuned",
    "Uncertain",
    "Verdict",
    "from_log",
    "judge",
    "select",
    "terms",
    "to_log",
    "tune",
]
