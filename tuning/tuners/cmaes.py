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
import copy
import dataclasses
import warnings
from typing import NamedTuple

import numpy as np

from coopjax.errors import InputError
from tuning.tuners.base import Best, Query, Tuner, register

BAD = 1e6  # the objective given to CMA-ES for a candidate whose runs are not measured (x (1 + unmeasured))


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


class Normal:
    """cma's normal samples (its `randn(lam, N)` option) from a generator of the strategy's own, so
    that a copy of a strategy samples what the strategy would (cma's default draws from numpy's
    global generator, which it seeds: the same numbers, but shared by every strategy and copy)."""

    def __init__(self, seed: int):
        self.rng = np.random.RandomState(seed)

    def __call__(self, *shape):
        return self.rng.randn(*shape)


def strategy(x0, sigma0, lo, hi, seed, popsize=None):
    """A quiet `cma.CMAEvolutionStrategy` in the box [lo, hi] (log units), from x0 clipped into it,
    writing no log files, sampling from its own generator (`Normal`); popsize None: cma's
    recommended 4 + 3 ln n."""
    try:
        import cma
    except ImportError:
        raise InputError("CMA-ES needs the cma package: pip install cma") from None
    options = {"bounds": [list(lo), list(hi)], "randn": Normal(seed), "verbose": -9, "verb_log": 0, "verb_disp": 0}
    if popsize:
        options["popsize"] = popsize
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return cma.CMAEvolutionStrategy(np.clip(np.asarray(x0), lo, hi), sigma0, options)


def sample(es) -> np.ndarray:
    """The population a strategy asks for next, without changing it (it asks a copy)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.asarray(copy.deepcopy(es).ask())


def told(es, thetas, values) -> object:
    """A copy of the strategy after the population it asks for next was evaluated."""
    es = copy.deepcopy(es)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        asked = np.asarray(es.ask())
        if not np.array_equal(asked, thetas):
            raise ValueError("the strategy was told a population it did not ask for")
        es.tell(list(thetas), list(values))
    return es


class Told:
    """What cma's augmented Lagrangian asks for: the objective and the constraints of the candidates
    of the current tell, looked up (a class, not closures, so that a copy looks up its own)."""

    def __init__(self):
        self.values = {}

    def f(self, x):
        return self.values[tuple(x)][0]

    def g(self, x):
        return self.values[tuple(x)][1]


class State(NamedTuple):
    es: object  # cma's strategy: never told in place (`told`)
    fun: object  # cma's augmented Lagrangian, with its `Told`
    generation: int
    seed: int
    problem: object
    best: Best
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

        lookup = Told()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # cma's note that an optional archive package is missing
            fun = cma.ConstrainedFitnessAL(lookup.f, lookup.g, logging=0, dimension=len(x0))
        with _silent_constraint_loggers():
            fun.al  # noqa: B018  (built now, while its loggers are silent)
        fun.lookup = lookup
        return es, fun

    def init(self, problem, starts, seed):
        starts = np.asarray(starts)
        es, fun = self._start(problem, starts[0], seed, self.popsize)
        return State(es, fun, 0, seed, problem, Best(), starts, 0, es.popsize)

    def ask(self, state):
        if self.generations is not None and state.generation >= self.generations:
            return None
        return Query(sample(state.es), state.problem.training_draws(state.seed, state.generation))

    def tell(self, state, query, ev):
        X = query.thetas
        fun = copy.deepcopy(state.fun)
        for x, fi, ci, ok, bad in zip(X, ev.f, ev.c, ev.valid, ev.bad(BAD)):
            fun.lookup.values[tuple(x)] = (float(fi) if ok else bad, list(np.where(np.isfinite(ci), ci, bad)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its AL warns about every interquartile range it adapts
            es = told(state.es, X, [fun(x) for x in X])
            fun.update(es)
            stopped = self.ipop and es.stop()
        fun.lookup.values.clear()
        state = state._replace(
            es=es,
            fun=fun,
            generation=state.generation + 1,
            best=state.best.told_all(X, ev.f, ev.holds, ev.valid),
        )
        if stopped:
            restarts, popsize = state.restarts + 1, state.popsize * 2
            x0 = state.starts[restarts % len(state.starts)]
            es, fun = self._start(state.problem, x0, state.seed + 1000 * restarts, popsize)
            state = state._replace(es=es, fun=fun, restarts=restarts, popsize=popsize)
        return state

    def candidates(self, state):
        mean = np.asarray(state.es.mean)
        return ([] if state.best.theta is None else [state.best.theta]) + [mean]
