"""Tuners: one interface, one registry.

A tuner is one class in a file of its own, registered with `register`. It never runs a simulation
itself: it asks for evaluations and is told their results (ask/tell), so that the driver
(`tuning.driver`) can batch them, put them on the devices, time them, checkpoint them and replay them
on resume, the same way for every tuner.

    state = tuner.init(problem, starts, seed)     # starts: (K, n) log-parameters; the first is the user's
    while (query := tuner.ask(state)) is not None:
        state = tuner.tell(state, query, evaluate(query))
    tuner.candidates(state)                       # what it would hand over, to be validated

`ask` returns a `Query`: candidates (C, n), the draws of the uncertain parameters to run them at,
and which derivatives it needs. The `Evaluation` holds, per candidate, the objective, the objective
terms' values and the requirements' constraints per draw (and, if asked, their exact derivatives).
Gradient tuners keep pure state (optax's `init`/`update` shape: `tell` is the update); population
tuners may keep the state of a library such as `cma`. Either way a tuner must be deterministic given
its seed and the evaluations it is told: that is what makes resume-by-replay bit-identical.
"""

from tuning.tuners.base import TUNERS, Best, Evaluation, Query, Tuner, concatenate, get, register, setting
from tuning.tuners import ablation, adam, cma_slp, cmaes, random_search, screen_slp  # noqa: E402,F401  (the built-in tuners register themselves)

__all__ = ["Best", "Evaluation", "Query", "TUNERS", "Tuner", "concatenate", "get", "register", "setting"]
