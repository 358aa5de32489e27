"""Random search: log-uniform draws in the box, a block at a time. The floor any tuner must beat."""

from __future__ import annotations

import dataclasses

import numpy as np

from tuning.problem import log_bounds
from tuning.tuners.base import Query, Tuner, register


@dataclasses.dataclass
class State:
    rng: np.random.Generator
    generation: int
    seed: int
    problem: object
    best: list


@register
@dataclasses.dataclass(frozen=True)
class RandomSearch(Tuner):
    name = "random search"
    description = "log-uniform draws in the search box"

    block: int = 8  # candidates per evaluation
    generations: int | None = None

    def init(self, problem, starts, seed):
        return State(np.random.default_rng(seed), 0, seed, problem, [])

    def ask(self, state):
        if self.generations is not None and state.generation >= self.generations:
            return None
        lo, hi = log_bounds(state.problem.names)
        return Query(
            lo + (hi - lo) * state.rng.random((self.block, len(lo))),
            state.problem.training_masses(state.seed, state.generation),
        )

    def tell(self, state, query, ev):
        for x, f, h, ok in zip(query.thetas, ev.f, ev.holds, ev.valid):
            if ok and (not state.best or (bool(h), -float(f)) > tuple(state.best[:2])):
                state.best = [bool(h), -float(f), np.asarray(x)]
        state.generation += 1
        return state

    def candidates(self, state):
        return [state.best[2]] if state.best else []
