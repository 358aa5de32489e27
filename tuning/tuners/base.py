"""The tuner interface (ask/tell), what is asked and told, and the registry."""

from __future__ import annotations

from typing import Any, Callable, ClassVar, NamedTuple

import numpy as np

from coopjax.errors import InputError


class Query(NamedTuple):
    """What a tuner wants evaluated next."""

    thetas: np.ndarray  # (C, n) log-parameters
    masses: np.ndarray  # (M,) body masses, kg
    derivative: str | None = None  # None; "jacobian" (of every output, forward mode); "gradient" (of `scalar`)
    mode: str = "reverse"  # for "gradient": "forward" or "reverse" mode
    weights: Any = None  # for "gradient": the dynamic arguments of the tuner's `scalar`


class Evaluation(NamedTuple):
    """Per candidate c and mass m (all on the problem's training model)."""

    f: np.ndarray  # (C,) the problem's objective: smooth max of peak + w_lag x smooth max of lag, N
    c: np.ndarray  # (C, M) grip shortfall, N (0 while the grip holds)
    peak: np.ndarray  # (C, M) N
    lag_mm: np.ndarray  # (C, M) mm
    min_grip: np.ndarray  # (C, M) N
    finite: np.ndarray  # (C,) every run finite (and f, c finite)
    holds: np.ndarray  # (C,) finite, and the grip holds at every mass
    value: np.ndarray | None = None  # (C,) the tuner's scalar, with "gradient"
    gradient: np.ndarray | None = None  # (C, n), with "gradient"
    jacobian: dict | None = None  # {"peak", "lag_mm", "c", "min_swi", "f"}: (C, M, n) ((C, n) for f), with "jacobian"
    min_swi: np.ndarray | None = None  # (C, M) the grip margin: least Filippov weight over the grip window


class Tuner:
    """The interface every tuner implements (see the module docstring)."""

    name: ClassVar[str]
    description: ClassVar[str] = ""
    uses_gradient: ClassVar[bool] = False

    def init(self, problem, starts: np.ndarray, seed: int):
        raise NotImplementedError

    def ask(self, state) -> Query | None:
        raise NotImplementedError

    def tell(self, state, query: Query, evaluation: Evaluation):
        raise NotImplementedError

    def candidates(self, state) -> list[np.ndarray]:
        """Log-parameter vectors worth validating, in the tuner's order of preference."""
        raise NotImplementedError

    # What `coopjax tune` prints; a tuner may say more.
    def plan_text(self, n_params: int, starts: int) -> str:
        """One line on how the run will go."""
        return f"{starts} starts"

    def progress_text(self, state, query: Query, evaluation: Evaluation) -> str | None:
        """A line after an evaluation (None: nothing to say)."""
        return None

    def expected_evaluations(self, starts: int) -> int | None:
        """Evaluations a run takes, for the progress bar (None: not known ahead)."""
        return None

    # With derivative="gradient": the scalar per candidate whose gradient is asked for, a pure JAX
    # function of (problem, f (C,), c (C, M), weights) that is static (hashable) for compilation.
    scalar: ClassVar[Callable | None] = None


TUNERS: dict[str, type[Tuner]] = {}


def register(cls: type[Tuner]) -> type[Tuner]:
    """Class decorator: make a tuner known by name to `coopjax tune`, the race and the plots."""
    if cls.name in TUNERS and TUNERS[cls.name] is not cls:
        raise ValueError(f"a tuner named {cls.name!r} is already registered")
    TUNERS[cls.name] = cls
    return cls


def get(name: str) -> type[Tuner]:
    if name not in TUNERS:
        raise InputError(f"unknown tuner {name!r}; choose one of: {', '.join(TUNERS)}", "method")
    return TUNERS[name]

