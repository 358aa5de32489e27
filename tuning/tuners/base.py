"""The tuner interface (ask/tell), what is asked and told, and the registry."""

from __future__ import annotations

import abc
import dataclasses
import inspect
import math
from typing import Any, Callable, ClassVar, NamedTuple

import numpy as np

from coopjax.config import setting  # noqa: F401  (a tuner declares its settings with it)
from coopjax.errors import InputError


class Query(NamedTuple):
    """What a tuner wants evaluated next."""

    thetas: np.ndarray  # (C, n) log-parameters
    draws: np.ndarray  # (M, p) values of the problem's uncertain parameters ((M,) with one of them)
    derivative: str | None = None  # None; "jacobian" (of every output, forward mode); "gradient" (of `scalar`)
    mode: str = "reverse"  # for "gradient": "forward" or "reverse" mode
    weights: Any = None  # for "gradient": the dynamic arguments of the tuner's `scalar`


class Evaluation(NamedTuple):
    """Per candidate c, on the problem's training model, at the query's draws of every scenario
    (the columns' layout: `Problem.objective_columns`, `constraint_columns`, `grip_columns`)."""

    f: np.ndarray  # (C,) the problem's objective (N): its terms' training aggregates, summed
    c: np.ndarray  # (C, Q) the requirements' constraints, per requirement and draw: met where <= 0
    parts: np.ndarray  # (C, P) the objective terms' weighted values per case (N), term after term
    valid: np.ndarray  # (C,) every run measured (none diverged, every step within its loop's limit), f and c finite
    holds: np.ndarray  # (C,) valid, and every requirement is met at every draw (the judge's rule)
    min_swi: np.ndarray  # (C, G) the grip margin (least Filippov weight) at the grip requirement's cases
    value: np.ndarray | None = None  # (C,) the tuner's scalar, with "gradient"
    gradient: np.ndarray | None = None  # (C, n), with "gradient"
    jacobian: dict | None = None  # {"f": (C, n), "c", "parts", "min_swi": (C, columns, n)}, with "jacobian"
    # (C,) how far from measured, finite: 0 when valid; else the mean over the candidate's runs of
    # 1 for a run that diverged plus, for a step beyond its loop's limit, 1 + log2 of how far. A
    # tuner orders invalid candidates by it (never a NaN that ties them).
    unmeasured: np.ndarray | None = None
    # (C, Q) how far each requirement misses at each draw by the judge's measure (`Terms.miss`:
    # relative to the bound's size, <= 0 when met).
    miss: np.ndarray | None = None

    def bad(self, scale: float) -> np.ndarray:
        """(C,) a finite value for each invalid candidate that orders it above every valid one:
        scale x (1 + unmeasured)."""
        u = np.zeros(len(self.f)) if self.unmeasured is None else self.unmeasured
        return scale * (1.0 + u)


class Best(NamedTuple):
    """The best candidate told so far: one that meets every requirement at every training draw first,
    then the lowest value (the objective, or a tuner's merit). Immutable: `told` returns the next."""

    holds: bool = False
    value: float = math.inf
    theta: np.ndarray | None = None

    def told(self, holds, value, theta) -> "Best":
        """This record after a candidate; a value that is not finite never counts."""
        if np.isfinite(value) and (bool(holds), -float(value)) > (self.holds, -self.value):
            return Best(bool(holds), float(value), np.array(theta, copy=True))
        return self

    def told_all(self, thetas, values, holds, ok) -> "Best":
        """This record after a batch (`ok` False: the candidate's run failed)."""
        best = self
        for x, v, h, good in zip(thetas, values, holds, ok):
            best = best.told(h, v, x) if good else best
        return best


def violation(ev: Evaluation) -> np.ndarray:
    """(C,) the judge's violation at the evaluated draws (`Verdict.violation`): the largest relative
    miss of any requirement at any draw, 0 when all are met."""
    if ev.miss is None or not ev.miss.shape[1]:
        return np.zeros(len(ev.f))
    return np.maximum(np.nan_to_num(ev.miss, nan=np.inf).max(1), 0.0)


def worst_constraint(ev: Evaluation) -> np.ndarray:
    """(C,) the largest constraint value (> 0: a requirement is missed; NaN without requirements)."""
    return ev.c.max(1) if ev.c.shape[1] else np.full(len(ev.f), np.nan)


def least_margin(ev: Evaluation) -> np.ndarray:
    """(C,) the least grip margin over the grip requirement's cases (NaN without one)."""
    return ev.min_swi.min(1) if ev.min_swi.shape[1] else np.full(len(ev.f), np.nan)


def concatenate(evaluations) -> Evaluation:
    """Evaluations of several batches of candidates, as one (values only)."""
    return Evaluation(*(None if x[0] is None else np.concatenate(x) for x in zip(*evaluations)))


class Tuner(abc.ABC):
    """The interface every tuner implements (see the package docstring). A tuner is a frozen
    dataclass whose fields are its settings (declared with `setting`); `register` refuses one
    that leaves an abstract method out.

    `ask` and `tell` never change a state they are given: `tell` returns the next one (copy, then
    change), as optax's `update` does. Replaying a state then gives the same run (a test tells every
    registered tuner made-up evaluations and checks each state it returned against a frozen copy).
    """

    name: ClassVar[str]
    description: ClassVar[str] = ""
    uses_gradient: ClassVar[bool] = False
    # Whether `coopjax tune --method NAME` can run it: it ends on its own, not only when a budget does.
    plain_run: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, problem, starts: np.ndarray, seed: int):
        """The first state, from the problem, the (K, n) log-parameter starts and the seed."""

    @abc.abstractmethod
    def ask(self, state) -> Query | None:
        """What to evaluate next; None when the tuner is done."""

    @abc.abstractmethod
    def tell(self, state, query: Query, evaluation: Evaluation):
        """The next state, after the evaluation of `query`."""

    @abc.abstractmethod
    def candidates(self, state) -> list[np.ndarray]:
        """Log-parameter vectors worth validating, in the tuner's order of preference."""

    def go_on(self, state, theta: np.ndarray, draws: np.ndarray):
        """A state from which the run goes on near `theta` (log parameters, the chosen answer) with
        the (k, p) `draws` added to its training draws: the judge found the answer missing a
        requirement there. None (the default): this tuner does not go on."""
        return None

    def polish_further(self, state, theta: np.ndarray):
        """A state from which the run's last phase goes on where `theta` (log parameters, the chosen
        answer) is that phase's best, so that the selection on the validation draws can keep a longer
        search's answer; its candidates are then the longer search's best alone. None (the default):
        nothing goes on."""
        return None

    def polish_afresh(self, state, theta: np.ndarray):
        """A state from which the run's last phase starts again from `theta` (log parameters, the
        chosen answer), with its first step's reach, for a round trained at a finer step; its
        candidates are then that round's best alone. None (the default): nothing goes on."""
        return None

    def ends(self) -> bool:
        """Whether a run with these settings ends on its own (a plain run needs it); by default,
        `plain_run`."""
        return self.plain_run

    def history(self, state) -> dict:
        """Per step, what the history figure of `coopjax tune` shows: lists under `step`, `f` (or
        `phi`), `holds` and `shortfall` (or `margin`). {}: the tuner keeps none (no figure lines)."""
        return {}

    # What `coopjax tune` prints; a tuner may say more.
    def plan_text(self, n_params: int, starts: int) -> str:
        """One line on how the run will go."""
        return f"{starts} starts"

    def progress_text(self, state, query: Query, evaluation: Evaluation) -> str | None:
        """A line after an evaluation (None: nothing to say)."""
        return None

    def run_text(self, state) -> str | None:
        """What the run did beyond its plan (`plan_text`), for the history figure (None: nothing)."""
        return None

    def largest_batch(self, n_params: int, starts: int) -> tuple[int, str]:
        """The most candidates one query can hold, and the setting that sets it, as its flag and
        value (checked against the machine's memory before any work). By default, the starts."""
        return starts, f"--starts {starts}"

    def kept_bytes(self, n_params: int, starts: int, draws: int) -> tuple[int, str]:
        """The most bytes the tuner's own state holds (its record of evaluated points, say), and the
        setting that sets it, as its flag and value. By default, nothing worth checking."""
        return 0, ""

    def later_queries(self, state) -> list[Query]:
        """Queries of kinds or shapes the run will ask after its first ones, as placeholders (only
        their kind and shapes matter): the driver compiles their programs in the background while
        the first ones run. By default none."""
        return []

    def expected_evaluations(self, starts: int) -> int | None:
        """Evaluations a run takes, for the progress bar (None: not known ahead)."""
        return None

    # With derivative="gradient": the scalar per candidate whose gradient is asked for, a pure JAX
    # function of (problem, f (C,), c (C, M), weights) that is static (hashable) for compilation.
    scalar: ClassVar[Callable | None] = None


TUNERS: dict[str, type[Tuner]] = {}


def register(cls: type[Tuner]) -> type[Tuner]:
    """Class decorator: make a tuner known by name to `coopjax tune`, the race and the plots. An
    incomplete tuner is refused here, not at its first call."""
    missing = ([] if hasattr(cls, "name") else ["name"]) + sorted(getattr(cls, "__abstractmethods__", ()))
    if not (inspect.isclass(cls) and issubclass(cls, Tuner)) or missing:
        raise TypeError(
            f"{getattr(cls, '__name__', cls)!r} is not a complete tuner: it must subclass Tuner and "
            f"define {', '.join(missing) or 'name, init, ask, tell and candidates'}"
        )
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"tuner {cls.name!r} must be a dataclass: its fields are its settings")
    if cls.name in TUNERS and TUNERS[cls.name] is not cls:
        raise ValueError(f"a tuner named {cls.name!r} is already registered")
    TUNERS[cls.name] = cls
    return cls


def get(name: str) -> type[Tuner]:
    if name not in TUNERS:
        raise InputError(f"unknown tuner {name!r}; choose one of: {', '.join(TUNERS)}", "method")
    return TUNERS[name]
