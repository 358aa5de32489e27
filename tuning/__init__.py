"""Gain tuning for coopjax: optax on log-gains through a differentiable surrogate of the switch.

    objective.py  the training loss (surrogate, mass batch) and the hard-model verdict (`judge`)
    optimize.py   the optax loop: init/step state, annealing, checkpoints, rejected steps (`tune`)
    baselines.py  CMA-ES and random search on the same objective and budget
    plots.py      loss curve, grip traces, tuner comparison, Pareto front
    cli.py        `coopjax tune`
"""

from tuning.objective import GAINS, Objective, Verdict, Weights, judge
from tuning.optimize import TuneConfig, TuneState, tune
