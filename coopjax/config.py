"""One configuration object for every run: `simulate`, sweeps, tuning and the benchmarks.

`Config` holds what fixes a run's answer besides the parameter values: the scenario, the switch and
contact models, the integrator, the step, the horizon, the dtype. Each setting is declared once,
here, with its help text; the command line builds its flags from these declarations, and
`Config.validate` is the one place they are checked. Changing a setting recompiles; changing a
parameter value does not.
"""

from __future__ import annotations

import dataclasses
import math
import json

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import model, objectives, scenarios
from coopjax.errors import InputError
from coopjax.integration import INTEGRATORS, default_for
from coopjax.params import Params, check_positive, resolve_dtype
from coopjax.traced import is_tracer

MAX_STEPS = 2**31 - 1  # a 32-bit step counter


def setting(
    default,
    help: str,
    flag: str | None = None,
    choices=None,
    kind: type | None = None,
    key: str | None = None,
    unit: str = "",
    check=None,
):
    """A declared setting: a dataclass field whose metadata every front end reads, so that a setting
    is declared once (`Config`, a tuner's settings, `tuning.Problem`, a session's options).

    Args:
      default: its default.
      help: one line for a flag's help and a file's comment.
      flag: its command-line flag (None: not on the command line).
      choices: a closed set of values, or a callable giving it.
      kind: the type of its value where the default does not say it (None for a default of None).
      key: where a file states it (`tuning.Problem`: "TABLE.KEY" or a top-level key).
      unit: the unit its value is in (SI; a display may convert).
      check: `check(value) -> str | None`: what is wrong with a value of the right kind.
    """
    metadata = dict(help=help, flag=flag, choices=choices, kind=kind, key=key, unit=unit, check=check)
    return dataclasses.field(default=default, metadata=metadata)


def choices_of(field: dataclasses.Field) -> tuple | None:
    """A setting's closed set of values (None: open)."""
    choices = field.metadata.get("choices")
    return tuple(choices()) if callable(choices) else choices


def is_number(x) -> bool:
    """A Python or NumPy real number, booleans excluded (they are not numbers to a setting)."""
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, (bool, np.bool_))


def check_setting(field: dataclasses.Field, value) -> None:
    """A declared scalar setting's value: its kind, its choices and its check, or one `InputError`
    naming it. Booleans are not numbers here, and whole numbers are numbers of a float setting."""
    kind, name = field.metadata["kind"], field.name
    if value is None and field.default is None:
        return
    real = is_number(value)
    ok = {
        bool: isinstance(value, (bool, np.bool_)),
        int: real and float(value).is_integer() and not isinstance(value, (float, np.floating)),
        float: real and math.isfinite(float(value)),
        str: isinstance(value, str),
    }[kind]
    what = {bool: "true or false", int: "a whole number", float: "a finite number", str: "a name"}[kind]
    if not ok:
        raise InputError(f"{name} is {value!r}: expected {what}", name)
    choices = choices_of(field)
    if choices and value not in choices:
        raise InputError(f"{name} must be one of {', '.join(choices)}, not {value!r}", name)
    problem = field.metadata["check"](value) if field.metadata["check"] else None
    if problem:
        raise InputError(f"{name} is {value!r}: {problem}", name)


def _number(name: str, value):
    """A setting that fixes the program's shape (the step count) as a Python float: a Python or
    NumPy number, or a concrete 0-d JAX or NumPy array; anything else is an InputError naming it."""
    if isinstance(value, (bool, np.bool_)) or isinstance(value, str):
        raise InputError(f"{name} must be a number, got {value!r} (a {type(value).__name__})", name)
    if isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if is_tracer(value):
        raise InputError(
            f"{name} is traced (under jit, grad or vmap): it sets the number of steps, so it must be a concrete "
            "number; pass it as a static argument",
            name,
        )
    if isinstance(value, (np.ndarray, jax.Array)) and np.ndim(value) == 0 and np.issubdtype(value.dtype, np.number):
        return float(value)
    raise InputError(f"{name} must be a number, got a {type(value).__name__}", name)


@dataclasses.dataclass(frozen=True)
class Config:
    scenario: str = setting(
        "carry",
        "scenario: the command profile, its horizon and its metric windows",
        "--scenario",
        lambda: scenarios.SCENARIOS,
    )
    switch: str = setting(
        "hard",
        "the switch swi of Eq. 8: hard (the reference model) or a smooth surrogate",
        "--switch",
        lambda: model.SWITCHES,
    )
    contact: str = setting(
        "unilateral",
        "gripper contact: unilateral (pushes, never pulls) or bilateral",
        "--contact",
        lambda: model.CONTACTS,
    )
    integrator: str | None = setting(
        None, "integrator (default: the registered default for the switch)", "--integrator", lambda: INTEGRATORS
    )
    dt: float = setting(1e-3, "fixed step in s", "--dt")
    T: float | None = setting(None, "horizon in s (default: the scenario's)", "--T")
    dtype: str | None = setting(None, "float32 or float64 (default: the parameters' own)")
    gamma_min: float | None = setting(
        None, "floor on gamma (default: none; the paper leaves gamma unclipped)", "--gamma-min"
    )
    force_bound: float = setting(1e6, "a grip force beyond this, in N, counts as divergence", "--force-bound")
    metrics: tuple | None = setting(None, "the metrics to compute (default: every registered one)")

    def __post_init__(self):
        if self.metrics is None:
            object.__setattr__(self, "metrics", tuple(objectives.METRICS))
        elif not isinstance(self.metrics, tuple):
            object.__setattr__(
                self, "metrics", tuple(self.metrics) if isinstance(self.metrics, (list, tuple)) else self.metrics
            )
        for name in ("dt", "T", "force_bound"):  # a concrete JAX or NumPy scalar is a number
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _number(name, value))

    @classmethod
    def of(cls, config: "Config | str | None" = None, **overrides) -> "Config":
        """A Config from another (or a scenario name), with some settings replaced."""
        if config is None:
            base = cls()
        elif isinstance(config, Config):
            base = config
        elif isinstance(config, str):
            base = cls(scenario=config)
        else:
            raise InputError(f"expected a Config or a scenario name, got {type(config).__name__}", "scenario")
        unknown = set(overrides) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise InputError(
                f"unknown setting {sorted(unknown)[0]!r}; the settings are: "
                f"{', '.join(f.name for f in dataclasses.fields(cls))}",
                sorted(unknown)[0],
            )
        return dataclasses.replace(base, **overrides) if overrides else base

    @property
    def method(self) -> str:
        return self.integrator or default_for(self.switch)

    @property
    def horizon(self) -> float:
        return self.T if self.T is not None else scenarios.get(self.scenario).T

    @property
    def n_steps(self) -> int:
        # Rounded, not truncated: T/dt is rarely an exact float.
        return max(1, int(round(self.horizon / self.dt)))

    @property
    def options(self) -> model.Options:
        return model.Options(switch=self.switch, contact=self.contact, gamma_min=self.gamma_min)

    def validate(self) -> "Config":
        for name in ("scenario", "switch", "contact"):
            if not isinstance(getattr(self, name), str):
                raise InputError(f"{name} must be a name, got {getattr(self, name)!r}", name)
        scenarios.get(self.scenario)
        model.check_options(self.options)
        if self.integrator is not None and self.integrator not in INTEGRATORS:
            raise InputError(
                f"unknown integrator {self.integrator!r}; choose one of: {', '.join(INTEGRATORS)}", "integrator"
            )
        integrator = INTEGRATORS[self.method]
        if self.switch not in integrator.switches:
            raise InputError(
                f"the {self.method} integrator does not integrate the {self.switch} switch (it takes: "
                f"{', '.join(integrator.switches)}); the {self.switch} switch runs with "
                f"{default_for(self.switch)}",
                "integrator",
            )
        check_positive("dt", self.dt, " s")
        if self.T is not None:
            check_positive("T", self.T, " s")
        if self.dtype is not None:
            resolve_dtype(self.dtype)
        check_positive("force_bound", self.force_bound, " N")
        if not isinstance(self.metrics, tuple):
            raise InputError(f"metrics must be a tuple of names, got {self.metrics!r}", "metrics")
        objectives.check_names(self.metrics)
        if self.dt > self.horizon:
            raise InputError(f"dt = {self.dt:g} s is longer than the horizon T = {self.horizon:g} s", "dt")
        if self.horizon / self.dt > MAX_STEPS:
            raise InputError(
                f"T / dt = {self.horizon:g} s / {self.dt:g} s = {self.horizon / self.dt:.3g} steps; at most "
                f"{MAX_STEPS:,} (a 32-bit step counter): use a larger dt or a shorter T",
                "dt",
            )
        return self

    def cast(self, params: Params) -> Params:
        """The parameters in this configuration's dtype (as they are if it sets none)."""
        return params if self.dtype is None else params.astype(self.dtype)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True, default=list)

    def describe(self) -> str:
        dtype = self.dtype or ("float64" if jnp.zeros(()).dtype == jnp.float64 else "float32")
        return (
            f"scenario {self.scenario}, switch {self.switch}, contact {self.contact}, integrator {self.method}, "
            f"dt {self.dt:g} s, T {self.horizon:g} s, {dtype}"
        )


def step_size_note(config: Config) -> str | None:
    """A sentence for a user whose step is coarser than the model was measured to need, or None."""
    key = (config.scenario, config.switch)
    measured = INTEGRATORS[config.method].converged_dt
    if key not in measured:
        return None
    converged = measured[key]
    if converged is None:
        return (
            f"note: {config.method} with the {config.switch} switch did not reach the accuracy tolerances of the "
            f"dt -> 0 limit in the {config.scenario} scenario at any step measured (docs/model.md, 'Step size')"
            + (
                f"; {default_for(config.switch)} meets them at dt = 1e-3"
                if default_for(config.switch) != config.method
                else ""
            )
        )
    if config.dt > converged * (1 + 1e-9):
        return (
            f"note: {config.scenario} with the {config.switch} switch and {config.method} needs dt <= {converged:g} s "
            f"to be within the accuracy tolerances of the dt -> 0 limit (docs/model.md, 'Step size'); this run "
            f"used dt = {config.dt:g} s"
        )
    return None


def record_size(config: Config, every: int, batch: int) -> int:
    """Bytes of a trajectory recorded every `every` steps: t, 20 states and 5 two-robot signals."""
    return (config.n_steps // every + 1) * (1 + model.N_STATE + 10) * batch * 8


def check_every(config: Config, every) -> None:
    if every is None:
        return
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise InputError(f"every is {every!r}: it must be a whole number of steps, at least 1", "every")
    if every > config.n_steps:
        raise InputError(
            f"every = {every} is more than the run's {config.n_steps} steps: nothing would be "
            f"recorded after t = 0 (use every <= {config.n_steps})",
            "every",
        )
