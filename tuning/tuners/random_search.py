"""Random search: log-uniform draws in the box, a block at a time. The floor any tuner must beat."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from coopjax.errors import InputError

from tuning.tuners.base import Best, Query, Tuner, register, setting


class State(NamedTuple):
    generation: int
    seed: int
    problem: object
    best: Best


@register
@dataclasses.dataclass(frozen=True)
class RandomSearch(Tuner):
    name = "random search"
    description = "log-uniform draws in the search box"
    plain_run = True  # with --generations: a baseline, or the cheapest end-to-end run of a problem

    block: int = 8  # candidates per evaluation
    generations: int | None = setting(
        None,
        "blocks of 8 candidates drawn (a plain run needs it; the race: until the budget ends)",
        "--generations",
        kind=int,
    )

    def __post_init__(self):
        g = self.generations
        if g is not None and (isinstance(g, bool) or not isinstance(g, (int, np.integer)) or g < 1):
            raise InputError(f"generations is {g!r}: a whole number, at least 1", "generations")

    def ends(self) -> bool:
        return self.generations is not None

    def init(self, problem, starts, seed):
        return State(0, seed, problem, Best())

    def ask(self, state):
        if self.generations is not None and state.generation >= self.generations:
            return None
        lo, hi = state.problem.log_bounds()
        rng = np.random.default_rng([state.seed, state.generation])  # a block's draws follow from its state
        return Query(
            lo + (hi - lo) * rng.random((self.block, len(lo))),
            state.problem.training_draws(state.seed, state.generation),
        )

    def tell(self, state, query, ev):
        best = state.best.told_all(query.thetas, ev.f, ev.holds, ev.valid)
        return state._replace(generation=state.generation + 1, best=best)

    def candidates(self, state):
        return [] if state.best.theta is None else [state.best.theta]
