"""Tuning for coopjax: the hard model itself, differentiated, against a user's requirements.

The public API:

    Problem, Objective, Requirement, Uncertain   a tuning problem as data (`Problem.from_toml` reads a file)
    terms(theta, base, problem, draws)           its differentiable objective and constraints, for a batch
    tune(problem, method, ...)                   tune it with any registered tuner (`TUNERS`), select, judge
    prepare(problem, tuner, options), run(...)   the same as a session: checked first, then run
    judge(values, draws, problem, ...)           a parameter set's verdict, requirement by requirement
    to_log, from_log                             a parameter dict <-> the log-values tuners work in

The modules:

    design.py       where the uncertain parameters are drawn: training, validation, held-out
    problem_file.py problem files (TOML): read, with errors that name the line; written
    problem.py      the problem as data: what is tuned, uncertain, minimised, required (each requirement's slack)
    training.py     its training algebra: the differentiable terms (`terms`), the starting points
    shorthands.py   the default problem's flags: its settings' own, and aliases
    judging.py      how an answer is judged (`judge`) and selected (`select`)
    constrained.py  an augmented Lagrangian on top of optax
    tuners/         the tuner interface and registry; one file per tuner (screen-SLP, Adam-AL, CMA-ES, ...)
    evaluate.py     the evaluator every tuner shares (values, Jacobians, gradients; compile kept apart)
    driver.py       ask / evaluate / tell on a clock and a budget; recorders (checkpoints) and resume by replay
    session.py      a session: `prepare` (every check), `run` (the driver, the selection, the judge)
    api.py          `tune`: a session in one call
    studies/        sessions by the many: the race (`--compare`) and the Pareto front (`--pareto`)
    plots.py        before/after traces, convergence, the race, the Pareto front
    report.py       a run's table, result file, figures and exit code
    cli.py          `coopjax tune`: flags in, a session run, its report out (an entry point of `coopjax`)

Imports run one way: `tuning` uses `coopjax`; `coopjax` never imports `tuning`.
"""

from tuning.api import tune
from tuning.session import Options, Session, Tuned, prepare, run
from tuning.design import Uncertain
from tuning.driver import Budget
from tuning.judging import Verdict, judge, select
from tuning.problem import Objective, Problem, Requirement, from_log, to_log
from tuning.training import Terms, terms
from tuning.tuners import TUNERS

__all__ = [
    "Budget",
    "Options",
    "Session",
    "prepare",
    "run",
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
