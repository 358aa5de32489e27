"""Tuning for coopjax: the hard model itself, differentiated, with the grip as a constraint.

    problem.py      the problem (worst peak and lag over masses; grip constraint), `judge`, `select`
    constrained.py  an augmented Lagrangian on top of optax
    tuners/         the tuner interface and registry; one file per tuner (Adam-AL, CMA-ES, random search)
    evaluate.py     the evaluator every tuner shares (values, Jacobians, gradients; compile kept apart)
    driver.py       ask / evaluate / tell on a clock and a budget; checkpoints and resume by replay
    race.py         `--compare`: every registered tuner on one clock over seeds
    plots.py        before/after traces, convergence, the race, the Pareto front
    cli.py          `coopjax tune` (registered with `coopjax` as an entry point)

Imports run one way: `tuning` uses `coopjax`; `coopjax` never imports `tuning`.
"""
