"""Gradient-free tuners on the same training objective and trajectory budget: CMA-ES and random search.

Both draw gains in the same log box as the gradient tuner (`objective.BOUNDS`), evaluate the same
surrogate loss at the end-of-anneal widths, and draw a fresh stratified mass batch per evaluation.
Every candidate costs `batch` trajectories, as one gradient step does.
"""

from __future__ import annotations

import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from tuning.objective import NARROW, Objective, draw_masses, log_bounds, training_loss

GENERATION = 8  # CMA-ES population, also the random-search evaluation block


def batch_loss_fn(objective: Objective) -> Callable:
    """(thetas (C, n), masses (C, B), widths, base) -> losses (C,), one jitted call for C candidates."""

    def one(theta, masses, widths, base):
        return training_loss(theta, masses, widths, base, objective)[0]

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None, None)))


class Trace:
    """Best-so-far training loss against trajectories used and wall time."""

    def __init__(self):
        self.trajectories, self.wall, self.best = [], [], []
        self.all_thetas, self.all_losses = [], []
        self.start = time.perf_counter()
        self._best, self._theta = np.inf, None

    def record(self, thetas: np.ndarray, losses: np.ndarray, trajectories: int):
        losses = np.where(np.isfinite(losses), losses, np.inf)  # a diverged candidate is simply bad
        self.all_thetas += list(np.asarray(thetas))
        self.all_losses += list(losses)
        i = int(np.argmin(losses))
        if losses[i] < self._best:
            self._best, self._theta = float(losses[i]), np.asarray(thetas[i])
        self.trajectories.append(trajectories)
        self.wall.append(time.perf_counter() - self.start)
        self.best.append(self._best)

    @property
    def theta(self) -> np.ndarray:
        return self._theta

    def top(self, k: int) -> list[np.ndarray]:
        """The k candidates with the lowest training loss, best first."""
        order = np.argsort(self.all_losses, kind="stable")[:k]
        return [self.all_thetas[i] for i in order]

    def as_dict(self) -> dict:
        return {"trajectories": self.trajectories, "wall": self.wall, "loss": self.best}


def _masses(key, count, masses, batch):
    keys = jax.random.split(key, count)
    return jax.vmap(lambda k: draw_masses(k, masses, batch))(keys)


def random_search(objective: Objective, masses, batch: int, budget: int, base, seed: int = 0,
                  log: Callable[[str], None] = print) -> Trace:
    """Log-uniform draws in the box until `budget` trajectories are spent."""
    f = batch_loss_fn(objective)
    lo, hi = log_bounds(objective.names)
    rng = np.random.default_rng(seed)
    key = jax.random.key(seed + 1)
    widths = jnp.asarray(NARROW, jnp.float64)
    trace, used = Trace(), 0
    for g in range(max(1, -(-budget // (batch * GENERATION)))):  # rounded up: never less than the budget
        thetas = lo + (hi - lo) * rng.random((GENERATION, len(lo)))
        losses = np.asarray(f(jnp.asarray(thetas), _masses(jax.random.fold_in(key, g), GENERATION, masses, batch),
                              widths, base))
        used += GENERATION * batch
        trace.record(thetas, losses, used)
    log(f"random search: {used} trajectories, best training loss {trace.best[-1]:.4g}")
    return trace


def cma_es(objective: Objective, masses, batch: int, budget: int, base, theta0, seed: int = 0,
           log: Callable[[str], None] = print) -> Trace:
    """CMA-ES (the `cma` package) in log-gain space, started where the gradient tuner starts."""
    try:
        import cma
    except ImportError:
        raise ValueError("the CMA-ES baseline needs the cma package: pip install 'coopjax[baselines]'") from None
    f = batch_loss_fn(objective)
    lo, hi = log_bounds(objective.names)
    es = cma.CMAEvolutionStrategy(np.asarray(theta0), 1.0, {
        "bounds": [list(lo), list(hi)], "popsize": GENERATION, "seed": seed + 1, "verbose": -9})
    key = jax.random.key(seed + 2)
    widths = jnp.asarray(NARROW, jnp.float64)
    trace, used = Trace(), 0
    for g in range(max(1, -(-budget // (batch * GENERATION)))):  # rounded up: never less than the budget
        thetas = np.asarray(es.ask())
        losses = np.asarray(f(jnp.asarray(thetas), _masses(jax.random.fold_in(key, g), GENERATION, masses, batch),
                              widths, base))
        es.tell(list(thetas), [float(x) if np.isfinite(x) else 1e12 for x in losses])
        used += GENERATION * batch
        trace.record(thetas, losses, used)
    log(f"CMA-ES: {used} trajectories, best training loss {trace.best[-1]:.4g}")
    return trace


def random_gain_sets(count: int, seed: int = 0, names=("K_GP", "K_GI", "tau", "G_e")) -> list[dict]:
    """The issue's reference: `count` gain sets drawn log-uniformly in the box, to be judged hard."""
    lo, hi = log_bounds(names)
    u = np.random.default_rng(seed).random((count, len(names)))
    return [dict(zip(names, map(float, np.exp(lo + (hi - lo) * row)))) for row in u]
