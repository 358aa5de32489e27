"""CMA-ES (the `cma` package) in log space, with the grip constraint handled by cma's own
augmented Lagrangian (`cma.ConstrainedFitnessAL`). It writes no log files.

Each generation of `popsize` candidates is one batch, on the gradient tuner's mass draws: generation
g sees the masses of step g. A diverged run is infeasible and bad, not missing.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from coopjax.errors import InputError
from tuning.problem import log_bounds
from tuning.tuners.base import Query, Tuner, register

BAD = 1e6  # the objective given to CMA-ES for a candidate whose run diverged


@dataclasses.dataclass
class State:
    es: object
    fun: object
    generation: int
    seed: int
    problem: object
    best: list  # (holds, -f, theta) of the best candidate told so far


@register
@dataclasses.dataclass(frozen=True)
class CMAES(Tuner):
    name = "CMA-ES"
    description = "CMA-ES (the cma package) with cma's augmented Lagrangian for the grip constraint"

    popsize: int | None = 8  # None: cma's recommended 4 + 3 ln n
    sigma0: float = 1.0  # initial step, log units
    generations: int | None = None  # None: until the budget is spent

    def init(self, problem, starts, seed):
        try:
            import cma
        except ImportError:
            raise InputError("the CMA-ES tuner needs the cma package: pip install 'coopjax[baselines]'") from None
        lo, hi = log_bounds(problem.names)
        options = {"bounds": [list(lo), list(hi)], "seed": seed + 1, "verbose": -9, "verb_log": 0, "verb_disp": 0}
        if self.popsize is not None:
            options["popsize"] = self.popsize
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            es = cma.CMAEvolutionStrategy(np.asarray(starts[0]), self.sigma0, options)
        cache = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # cma's note that an optional archive package is missing
            fun = cma.ConstrainedFitnessAL(lambda x: cache[tuple(x)][0], lambda x: cache[tuple(x)][1], logging=0)
        fun.cache = cache
        return State(es, fun, 0, seed, problem, [])

    def ask(self, state):
        if self.generations is not None and state.generation >= self.generations:
            return None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            X = np.asarray(state.es.ask())
        return Query(X, state.problem.training_masses(state.seed, state.generation))

    def tell(self, state, query, ev):
        X, cache = query.thetas, state.fun.cache
        for x, fi, ci, ok in zip(X, ev.f, ev.c, ev.finite):
            cache[tuple(x)] = (float(fi) if ok else BAD, list(np.where(np.isfinite(ci), ci, BAD)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its AL warns about every interquartile range it adapts
            state.es.tell(list(X), [state.fun(x) for x in X])
            state.fun.update(state.es)
        cache.clear()
        for x, f, h, ok in zip(X, ev.f, ev.holds, ev.finite):
            if ok and (not state.best or (bool(h), -float(f)) > tuple(state.best[:2])):
                state.best = [bool(h), -float(f), np.asarray(x)]
        state.generation += 1
        return state

    def candidates(self, state):
        mean = np.asarray(state.es.mean)
        return ([state.best[2]] if state.best else []) + [mean]
