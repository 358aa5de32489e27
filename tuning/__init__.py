"""Tuning for coopjax: the hard model itself, differentiated, with the grip as a constraint.

    objective.py    the problem (worst peak and lag over masses; grip constraint) and `judge`
    constrained.py  an augmented Lagrangian on top of optax
    optimize.py     the multi-start tuner: K starts in one batch, checkpoints, rejected steps (`tune`)
    baselines.py    CMA-ES (with cma's own augmented Lagrangian) and random search, same problem
    race.py         `--compare`: the three tuners on the same clock over seeds; the dimension study
    plots.py        before/after traces, convergence, the race, the Pareto front
    cli.py          `coopjax tune`
"""

from tuning.objective import GAINS, Problem, Verdict, judge
from tuning.optimize import TuneConfig, TuneState, tune
