"""CMA-ES (the `cma` package) in log space, with the grip constraint handled by cma's own
augmented Lagrangian (`cma.ConstrainedFitnessAL`) for the requirements, and IPOP restarts. It writes no log files and
changes neither the working folder nor anything outside cma.

Each generation of `popsize` candidates is one batch, on the gradient tuner's mass draws: generation
g sees the training draws of step g. A diverged run is infeasible and bad, not missing. The population is
cma's recommended 4 + 3 ln n by default; when a run meets one of cma's own stopping criteria it
restarts with twice the population (IPOP-CMA-ES, Auger and Hansen 2005), from the next of the given
starts, which every tuner shares.
"""

from __future__ import annotations

import contextlib
import dataclasses
import warnings

import numpy as np

from coopjax.errors import InputError
from tuning.tuners.base import Query, Tuner, register

BAD = 1e6  # the objective given to CMA-ES for a candidate whose run diverged


@contextlib.contextmanager
def _silent_constraint_loggers():
    """cma's augmented Lagrangian builds its loggers, and their folder outcmaes/ in the working
    folder, before it applies `logging=0`. cma's constraints handler names its own switch for that
    (its module's `_Logger`, to be replaced by `cma.logger.LoggerDummy`): set here only while the
    Lagrangian is built. It touches cma alone; with logging=0 the loggers are never called."""
    import cma.constraints_handler as handler
    import cma.logger

    kept = handler._Logger
    handler._Logger = cma.logger.LoggerDummy
    try:
        yield
    finally:
        handler._Logger = kept


def strategy(x0, sigma0, lo, hi, seed, popsize=None):
    """A quiet `cma.CMAEvolutionStrategy` in the box [lo, hi] (log units), from x0 clipped into it,
    writing no log files; popsize None: cma's recommended 4 + 3 ln n."""
    try:
        import cma
    except ImportError:
        raise InputError("CMA-ES needs the cma package: pip install cma") from None
    options = {"bounds": [list(lo), list(hi)], "seed": seed, "verbose": -9, "verb_log": 0, "verb_disp": 0}
    if popsize:
        options["popsize"] = popsize
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return cma.CMAEvolutionStrategy(np.clip(np.asarray(x0), lo, hi), sigma0, options)


@dataclasses.dataclass
class State:
    es: object
    fun: object
    generation: int
    seed: int
    problem: object
    best: list  # (holds, -f, theta) of the best candidate told so far
    starts: np.ndarray  # (K, n) the given starts: restart k begins at starts[k % K]
    restarts: int = 0
    popsize: int = 0  # of the current run


@register
@dataclasses.dataclass(frozen=True)
class CMAES(Tuner):
    name = "CMA-ES"
    description = "CMA-ES (the cma package) with cma's augmented Lagrangian for the grip constraint"

    popsize: int | None = None  # None: cma's recommended 4 + 3 ln n
    sigma0: float = 1.0  # initial step, log units
    generations: int | None = None  # None: until the budget is spent
    ipop: bool = True  # restart with twice the population when a run stops

    def _start(self, problem, x0, seed, popsize):
        lo, hi = problem.log_bounds()
        es = strategy(x0, self.sigma0, lo, hi, seed + 1, popsize)  # first: it refuses a missing cma in one line
        import cma

        cache = {}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # cma's note that an optional archive package is missing
            fun = cma.ConstrainedFitnessAL(
                lambda x: cache[tuple(x)][0], lambda x: cache[tuple(x)][1], logging=0, dimension=len(x0)
            )
        with _silent_constraint_loggers():
            fun.al  # noqa: B018  (built now, while its loggers are silent)
        fun.cache = cache
        return es, fun

    def init(self, problem, starts, seed):
        starts = np.asarray(starts)
        es, fun = self._start(problem, starts[0], seed, self.popsize)
        return State(es, fun, 0, seed, problem, [], starts, 0, es.popsize)

    def ask(self, state):
        if self.generations is not None and state.generation >= self.generations:
            return None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            X = np.asarray(state.es.ask())
        return Query(X, state.problem.training_draws(state.seed, state.generation))

    def tell(self, state, query, ev):
        X, cache = query.thetas, state.fun.cache
        for x, fi, ci, ok in zip(X, ev.f, ev.c, ev.valid):
            cache[tuple(x)] = (float(fi) if ok else BAD, list(np.where(np.isfinite(ci), ci, BAD)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its AL warns about every interquartile range it adapts
            state.es.tell(list(X), [state.fun(x) for x in X])
            state.fun.update(state.es)
        cache.clear()
        for x, f, h, ok in zip(X, ev.f, ev.holds, ev.valid):
            if ok and (not state.best or (bool(h), -float(f)) > tuple(state.best[:2])):
                state.best = [bool(h), -float(f), np.asarray(x)]
        state.generation += 1
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            stopped = self.ipop and state.es.stop()
        if stopped:
            state.restarts += 1
            x0 = state.starts[state.restarts % len(state.starts)]
            state.popsize *= 2
            state.es, state.fun = self._start(state.problem, x0, state.seed + 1000 * state.restarts, state.popsize)
        return state

    def candidates(self, state):
        mean = np.asarray(state.es.mean)
        return ([state.best[2]] if state.best else []) + [mean]
