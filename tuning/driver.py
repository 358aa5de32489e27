"""One loop for every tuner: ask, evaluate, tell; a clock, a budget, a record, checkpoints, resume.

The checkpoint is the log of what was evaluated, not the tuner's state: a resumed run replays the
log through the tuner (asking, checking that it asks for exactly what it asked before, and telling it
the logged results), then goes on live. Tuners are deterministic given their seed and what they are
told, so a resumed run ends bit-identical to an uninterrupted one, whatever state a tuner keeps
(optax moments, a `cma` strategy, a running solver).
"""

from __future__ import annotations

import math
import os
import pickle
import time
from typing import Any, NamedTuple

import numpy as np

from coopjax.errors import InputError
from coopjax.io import atomic_path
from coopjax.progress import bar as progress_bar
from tuning.evaluate import Evaluator
from tuning.tuners import Evaluation, Query, Tuner

CHECKPOINT_FORMAT = 2


class Budget(NamedTuple):
    """When a run stops, whichever comes first (None: no limit of that kind)."""

    seconds: float | None = None  # of evaluation, compile time excluded
    trajectories: int | None = None  # simulated (candidate, mass) runs


class Record(NamedTuple):
    """Every evaluated candidate, in order: its log-parameters, objective, whether it held, and when."""

    thetas: list
    f: list
    holds: list
    wall: list  # s since the tuner started, compile time excluded
    trajectories: list

    @classmethod
    def empty(cls) -> "Record":
        return cls([], [], [], [], [])

    def add(self, query: Query, evaluation: Evaluation, wall: float, trajectories: int) -> None:
        for i in range(len(query.thetas)):
            ok = bool(evaluation.valid[i])
            self.thetas.append(np.asarray(query.thetas[i]))
            self.f.append(float(evaluation.f[i]) if ok else math.inf)
            self.holds.append(bool(evaluation.holds[i]))
            self.wall.append(wall)
            self.trajectories.append(trajectories)

    def best_so_far(self) -> list[int]:
        """For each evaluation, the index of the best candidate so far (holding first, then lowest f)."""
        out, best = [], None
        for i, (f, h) in enumerate(zip(self.f, self.holds)):
            if np.isfinite(f) and (best is None or (h, -f) > (self.holds[best], -self.f[best])):
                best = i
            out.append(best if best is not None else i)
        return out


class Result(NamedTuple):
    tuner: Tuner
    state: Any
    record: Record
    elapsed: float  # s of evaluation and tuner work, compile excluded
    compile_s: float
    trajectories: int
    evaluations: int


def identity(tuner: Tuner, problem, starts, seed) -> dict:
    return {
        "format": CHECKPOINT_FORMAT,
        "tuner": tuner.name,
        "settings": repr(tuner),
        "problem": repr(problem),
        "starts": np.asarray(starts).tolist(),
        "seed": seed,
    }


def run(
    tuner: Tuner,
    problem,
    base,
    starts: np.ndarray,
    seed: int = 0,
    *,
    budget: Budget = Budget(),
    checkpoint: str | None = None,
    resume: bool = False,
    progress: bool = False,
    total: int | None = None,
    evaluator: Evaluator | None = None,
    on_step=None,
) -> Result:
    """Run (or resume) one tuner until it finishes or the budget is spent.

    With `checkpoint`, the log is saved atomically after every evaluation; `resume=True` continues
    from it. `total` sizes the progress bar (a tuner's step count); `on_step(state, query, evaluation)`
    is called after each live evaluation.
    """
    evaluator = evaluator or Evaluator(problem, base, type(tuner).scalar)
    ident = identity(tuner, problem, starts, seed)
    log: list[tuple[Query, Evaluation]] = []
    clock: list[tuple[float, int]] = []  # (elapsed s, trajectories) after each logged evaluation
    state = tuner.init(problem, np.asarray(starts), seed)
    record = Record.empty()
    elapsed, trajectories = 0.0, 0
    if checkpoint and os.path.exists(checkpoint):
        if not resume:
            raise InputError(f"{checkpoint} holds an earlier tuning run: resume it, or delete it", "resume")
        saved = load_checkpoint(checkpoint, ident)
        for (query, evaluation), (wall, used) in zip(saved["log"], saved["clock"]):
            asked = tuner.ask(state)
            if asked is None or not _same(asked, query):
                raise InputError(f"{checkpoint} does not replay with this code and these options: delete it", "resume")
            state = tuner.tell(state, query, evaluation)
            log.append((query, evaluation))
            clock.append((wall, used))
            record.add(query, evaluation, wall, used)
            elapsed, trajectories = wall, used
    bar = progress_bar(total=total, initial=len(log), desc=f"tune ({tuner.name})", unit="step", enabled=progress)
    while True:
        if budget.seconds is not None and elapsed >= budget.seconds:
            break
        if budget.trajectories is not None and trajectories >= budget.trajectories:
            break
        start, compiled = time.perf_counter(), evaluator.compile_s
        query = tuner.ask(state)
        if query is None:
            break
        evaluator.warm_up(query)  # compile apart from the clock (a no-op once compiled)
        evaluation = evaluator(query)
        state = tuner.tell(state, query, evaluation)
        elapsed += time.perf_counter() - start - (evaluator.compile_s - compiled)
        trajectories += len(query.thetas) * len(query.draws) * len(problem.scenarios)
        log.append((query, evaluation))
        clock.append((elapsed, trajectories))
        record.add(query, evaluation, elapsed, trajectories)
        if checkpoint:
            save_checkpoint(checkpoint, ident, log, clock)
        bar.update(1)
        if on_step is not None:
            on_step(state, query, evaluation)
    bar.close()
    return Result(tuner, state, record, elapsed, evaluator.compile_s, trajectories, len(log))


def _same(a: Query, b: Query) -> bool:
    return (
        a.derivative == b.derivative
        and a.mode == b.mode
        and np.array_equal(a.thetas, b.thetas)
        and np.array_equal(a.draws, b.draws)
    )


def save_checkpoint(path: str, ident: dict, log, clock) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            pickle.dump({"identity": ident, "log": log, "clock": clock}, f, protocol=pickle.HIGHEST_PROTOCOL)


def load_checkpoint(path: str, ident: dict) -> dict:
    """A checkpoint's log, after checking it belongs to this run. (A checkpoint is a pickle: load only
    your own.)"""
    try:
        with open(path, "rb") as f:
            saved = pickle.load(f)
        saved["identity"], saved["log"], saved["clock"]
    except Exception as error:  # a foreign or damaged file: say so rather than crash
        raise InputError(
            f"{path} is not a coopjax tuning checkpoint ({type(error).__name__}): delete it", "resume"
        ) from None
    if saved["identity"] != ident:
        raise InputError(f"{path} belongs to a run with other options; use the same flags, or delete it", "resume")
    return saved
