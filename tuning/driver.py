"""One loop for every tuner: ask, evaluate, tell; a clock, a budget, a record, checkpoints, resume.

The checkpoint is the log of what was evaluated, not the tuner's state: a resumed run replays the
log through the tuner (asking, checking that it asks for exactly what it asked before, and telling it
the logged results), then goes on live. Tuners are deterministic given their seed and what they are
told, so a resumed run ends bit-identical to an uninterrupted one, whatever state a tuner keeps
(optax moments, a `cma` strategy, a running solver).
"""

from __future__ import annotations

import hashlib
import io as io_module
import json
import math
import os
import time
from typing import Any, NamedTuple

import numpy as np

from coopjax.errors import InputError
from coopjax.io import atomic_path
from coopjax.progress import bar as progress_bar
from tuning.evaluate import Evaluator
from tuning.tuners import Evaluation, Query, Tuner

CHECKPOINT_FORMAT = 3  # 3: arrays and JSON in an .npz (2 was a pickle)
CHECKPOINT_KIND = "coopjax tuning checkpoint"


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
    recorder: "Checkpoint | None" = None,
    progress: bool = False,
    total: int | None = None,
    evaluator: Evaluator | None = None,
    on_step=None,
    state=None,
) -> Result:
    """Run (or resume) one tuner until it finishes or the budget is spent.

    `state`: go on from it (`Tuner.go_on`) instead of from the tuner's first state; nothing is
    replayed or recorded then (the round that goes on follows from the recorded run).

    A `recorder` (`Checkpoint`) is given the log after every evaluation, and gives back the log of
    an interrupted run to replay before going on. `total` sizes the progress bar (a tuner's step
    count); `on_step(state, query, evaluation)` is called after each live evaluation.
    """
    if budget.seconds is None and budget.trajectories is None and not tuner.ends():
        # A run that cannot end would hang its caller (a study, a script): a budget comes first.
        raise InputError(f"{tuner.name} with these settings does not end on its own: give it a budget", "budget")
    evaluator = evaluator or Evaluator(problem, base, type(tuner).scalar)
    ident = identity(tuner, problem, starts, seed)
    log: list[tuple[Query, Evaluation]] = []
    clock: list[tuple[float, int]] = []  # (elapsed s, trajectories) after each logged evaluation
    if state is None:
        state = tuner.init(problem, np.asarray(starts), seed)
        evaluator.prepare(tuner.later_queries(state))
    else:
        recorder = None
    record = Record.empty()
    elapsed, trajectories = 0.0, 0
    saved = recorder.saved(ident) if recorder is not None else None
    if saved is not None:
        for (query, evaluation), (wall, used) in zip(saved["log"], saved["clock"]):
            asked = tuner.ask(state)
            if asked is None or not _same(asked, query):
                raise InputError(
                    f"{recorder.path} does not replay with this code and these options: delete it", "resume"
                )
            # The tuner's own query goes on (the file keeps what identifies it, not its `weights`).
            state = tuner.tell(state, asked, evaluation)
            log.append((asked, evaluation))
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
        if recorder is not None:
            recorder.record(ident, log, clock)
        bar.update(1)
        if on_step is not None:
            on_step(state, query, evaluation)
    bar.close()
    return Result(tuner, state, record, elapsed, evaluator.compile_s, trajectories, len(log))


class Checkpoint:
    """A recorder that keeps a run's log in a file after every evaluation, and resumes from it.

    `resume=False` refuses a file that is already there (a run is never silently restarted);
    `resume=True` replays it. `discard` removes the file once the run's results are safe."""

    def __init__(self, path: str, resume: bool = False):
        self.path, self.resume = path, resume

    def saved(self, ident: dict) -> dict | None:
        """The log to replay (None: start afresh)."""
        if not os.path.exists(self.path):
            return None
        if not self.resume:
            raise InputError(f"{self.path} holds an earlier tuning run: resume it, or delete it", "resume")
        return load_checkpoint(self.path, ident)

    def record(self, ident: dict, log, clock) -> None:
        save_checkpoint(self.path, ident, log, clock)

    def discard(self) -> None:
        if os.path.exists(self.path):
            os.remove(self.path)


def _same(a: Query, b: Query) -> bool:
    return (
        a.derivative == b.derivative
        and a.mode == b.mode
        and np.array_equal(a.thetas, b.thetas)
        and np.array_equal(a.draws, b.draws)
    )


def _fingerprint(ident: dict) -> str:
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


def save_checkpoint(path: str, ident: dict, log, clock) -> None:
    """The log as data: one `.npz` of plain arrays, read back with `allow_pickle=False`, so that
    loading a checkpoint (a planted one included) can never run code. The index (what each entry
    holds, the clock, the run's identity and its fingerprint) is JSON inside it."""
    arrays, entries = {}, []
    for i, (query, evaluation) in enumerate(log):
        arrays[f"q{i}.thetas"], arrays[f"q{i}.draws"] = np.asarray(query.thetas), np.asarray(query.draws)
        fields = [name for name in Evaluation._fields if name != "jacobian" and getattr(evaluation, name) is not None]
        for name in fields:
            arrays[f"e{i}.{name}"] = np.asarray(getattr(evaluation, name))
        jacobian = sorted(evaluation.jacobian) if evaluation.jacobian is not None else None
        for key in jacobian or ():
            arrays[f"e{i}.jacobian.{key}"] = np.asarray(evaluation.jacobian[key])
        entries.append({"derivative": query.derivative, "mode": query.mode, "fields": fields, "jacobian": jacobian})
    index = {
        "kind": CHECKPOINT_KIND,
        "format": CHECKPOINT_FORMAT,
        "identity": ident,
        "fingerprint": _fingerprint(ident),
        "entries": entries,
        "clock": [[float(wall), int(used)] for wall, used in clock],
    }
    arrays["index"] = np.array(json.dumps(index))
    buffer = io_module.BytesIO()  # whole, then one write: numpy's writer hides a full disk's errno
    np.savez(buffer, **arrays)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())


def load_checkpoint(path: str, ident: dict) -> dict:
    """A checkpoint's log, after checking that it is one, of this format, and of this run. Nothing in
    the file is executed: it is read as arrays and JSON only."""

    def refuse(why: str):
        return InputError(f"{path} is not a coopjax tuning checkpoint ({why}): delete it", "resume")

    try:
        data = np.load(path, allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an archive")
        with data:
            stored = {name: data[name] for name in data.files}
        index = json.loads(str(stored.pop("index")))
        if index.get("kind") != CHECKPOINT_KIND:
            raise ValueError("no checkpoint index")
    except Exception:  # a foreign, damaged or pickled file: said, never run
        try:
            with open(path, "rb") as f:
                pickled = f.read(1) == b"\x80"  # a pickle's protocol mark
        except OSError:
            pickled = False
        raise refuse(
            "a pickle, which is never loaded" if pickled else "not an archive of arrays with an index"
        ) from None
    missing = [key for key in ("format", "identity", "fingerprint", "entries", "clock") if key not in index]
    if missing:
        raise refuse(f"its index lacks {', '.join(map(repr, missing))}")
    if index["format"] != CHECKPOINT_FORMAT:
        raise InputError(
            f"{path} was written by another version of coopjax (format {index['format']}): delete it", "resume"
        )
    if index["identity"] != ident or index["fingerprint"] != _fingerprint(ident):
        raise InputError(f"{path} belongs to a run with other options; use the same flags, or delete it", "resume")
    log = []
    try:
        for i, entry in enumerate(index["entries"]):
            query = Query(stored[f"q{i}.thetas"], stored[f"q{i}.draws"], entry["derivative"], entry["mode"])
            values = {name: stored[f"e{i}.{name}"] for name in entry["fields"]}
            if entry["jacobian"] is not None:
                values["jacobian"] = {key: stored[f"e{i}.jacobian.{key}"] for key in entry["jacobian"]}
            log.append((query, Evaluation(**values)))
        clock = [(wall, used) for wall, used in index["clock"]]
    except Exception as error:  # noqa: BLE001 (whatever is wrong in a half-formed index: one line)
        raise refuse(f"incomplete: {type(error).__name__} {error}") from None
    return {"identity": ident, "log": log, "clock": clock}
