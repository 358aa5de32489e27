"""Gradient-free tuners on the same problem: CMA-ES (with cma's augmented Lagrangian) and random search.

Both evaluate exactly what the gradient tuner trains on (`objective.terms`: the hard model under the
sliding-mode integrator, the same step, the same fixed training masses, the same box in log space),
a generation of `popsize` candidates per jitted call, sharded over the cores like the gradient
tuner's batch. Each candidate costs M trajectories, and each records its wall time, so all three
tuners can be compared on one clock.
"""

from __future__ import annotations

import functools
import time
import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tuning.objective import HOLD_TOLERANCE, Problem, from_log, log_bounds, terms

POPSIZE = 8  # CMA-ES population and the random-search block: the gradient tuner's K starts
BAD = 1e6  # the objective given to CMA-ES for a candidate whose run diverged


@functools.lru_cache(maxsize=8)
def batch_fn(problem: Problem) -> Callable:
    """(thetas (C, n), masses (M,), base) -> (f (C,), c (C, M), min grip (C,)), jitted, for C candidates."""

    def run(thetas, masses, base):
        t = terms(thetas, base, problem, masses)
        return t.f, t.c, t.metrics.min_grip.min(1)

    return jax.jit(run)


class Record(NamedTuple):
    """Every evaluated candidate, in order: its log-parameters, objective, whether it held, and when."""

    thetas: list
    f: list
    holds: list
    wall: list  # s since the tuner started
    trajectories: list

    def best_so_far(self) -> list[int]:
        """For each evaluation, the index of the best candidate so far (holding first, then lowest f)."""
        out, best = [], None
        for i, (f, h) in enumerate(zip(self.f, self.holds)):
            if best is None or (h, -f) > (self.holds[best], -self.f[best]):
                best = i if np.isfinite(f) else best
            out.append(best if best is not None else i)
        return out

    def as_dict(self, names) -> dict:
        return {"params": [from_log(t, names) for t in self.thetas], "f": self.f, "holds": self.holds,
                "wall": self.wall, "trajectories": self.trajectories}


class Evaluator:
    """Runs generations and records them. The clock starts at construction (after compiling)."""

    def __init__(self, problem: Problem, base, F_lim: float, seed: int = 0):
        self.problem, self.base, self.F_lim, self.seed = problem, base, F_lim, seed
        self.fn = batch_fn(problem)
        self.record = Record([], [], [], [], [])
        self.used = self.generation = 0

    def warm_up(self, n: int) -> float:
        """Compile for this generation size; returns the compile (first-call) time, s."""
        start = time.perf_counter()
        jax.block_until_ready(self.fn(jnp.zeros((POPSIZE, n)), jnp.asarray(self.problem.training_masses()), self.base))
        return time.perf_counter() - start

    def start_clock(self):
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def __call__(self, thetas: np.ndarray):
        # The gradient tuner's mass draws: generation g sees what its step g sees.
        masses = self.problem.training_masses(self.seed, self.generation)
        self.generation += 1
        f, c, min_grip = (np.asarray(x) for x in self.fn(jnp.asarray(thetas), jnp.asarray(masses), self.base))
        ok = np.isfinite(f) & np.isfinite(c).all(1)
        holds = ok & (min_grip >= self.F_lim - HOLD_TOLERANCE)
        wall = self.elapsed()
        for i in range(len(thetas)):
            self.used += self.problem.n_masses
            self.record.thetas.append(np.asarray(thetas[i]))
            self.record.f.append(float(f[i]) if ok[i] else float("inf"))
            self.record.holds.append(bool(holds[i]))
            self.record.wall.append(wall)
            self.record.trajectories.append(self.used)
        return np.where(ok, f, np.nan), np.where(ok[:, None], c, np.nan)


def random_search(evaluate: Evaluator, names, budget_s: float, seed: int = 0) -> Record:
    """Log-uniform draws in the box, a generation at a time, until `budget_s` seconds have passed."""
    lo, hi = log_bounds(names)
    rng = np.random.default_rng(seed)
    evaluate.start_clock()
    while evaluate.elapsed() < budget_s:
        evaluate(lo + (hi - lo) * rng.random((POPSIZE, len(names))))
    return evaluate.record


def cma_es(evaluate: Evaluator, names, budget_s: float, theta0, seed: int = 0) -> Record:
    """CMA-ES (the `cma` package) in log space, started where the gradient tuner's first start is,
    with the grip constraint handled by cma's own augmented Lagrangian (`cma.ConstrainedFitnessAL`)."""
    try:
        import cma
    except ImportError:
        raise ValueError("the CMA-ES baseline needs the cma package: pip install 'coopjax[baselines]'") from None
    lo, hi = log_bounds(names)
    es = cma.CMAEvolutionStrategy(np.asarray(theta0), 1.0, {
        "bounds": [list(lo), list(hi)], "popsize": POPSIZE, "seed": seed + 1, "verbose": -9})
    warnings.filterwarnings("ignore", module="cma")  # its AL logs every interquartile range it adapts
    cache = {}
    fun = cma.ConstrainedFitnessAL(lambda x: cache[tuple(x)][0], lambda x: cache[tuple(x)][1])
    evaluate.start_clock()
    while evaluate.elapsed() < budget_s:
        X = np.asarray(es.ask())
        f, c = evaluate(X)
        for x, fi, ci in zip(X, f, c):  # a diverged run is infeasible and bad, not missing
            cache[tuple(x)] = (float(fi) if np.isfinite(fi) else BAD, list(np.where(np.isfinite(ci), ci, BAD)))
        es.tell(list(X), [fun(x) for x in X])
        fun.update(es)
        cache.clear()
    return evaluate.record
