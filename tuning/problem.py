"""What the tuner optimises: a `Problem`, plain data (how a result is judged: `tuning.judging`).

A problem says which controller parameters are tuned (`names`, within `bounds`), which others are
held (`fixed`), what the answer must hold for (`uncertain` parameters, each a box), on which
`scenarios`, what is minimised and what is required:

    minimise   f = sum_j weight_j * over_j(metric_j)                 over the draws x scenarios
    subject to every requirement at every training draw              (metric >= or <= its bound)

- `over` is `max`, `mean` or `cvar:ALPHA` (the mean of the worst ALPHA share).
- Each requirement evaluates its own slack (`Requirement.slack`, `met`): the one rule training
  (`tuning.training`, which turns it into constraints) and judging (`tuning.judging`) both apply.
  The grip requirement `min_grip >= F_lim` is met within `HOLD_TOLERANCE`: on F = F_lim the hard
  switch slides and min_grip sits there, flat.
- Every field is a declared setting (`coopjax.config.setting`): its file key, flag, unit, help and
  check live on the field, and the problem file (`tuning.problem_file`), the command's flags
  (`tuning.shorthands`) and `validate` are generated from them.
- Training runs the problem's switch, under the sliding-mode integrator for the hard one at each
  scenario's coarsest step within the accuracy tolerances; `tuning.design` places the training,
  validation and held-out draws, which never meet.

The default problem: tune the 14 controller parameters (per-robot gains and impedance), minimise
the worst peak grip plus 1.5 N per mm of the worst RMS lag over body masses 0.5 to 5 kg (log-uniform)
on the carry scenario, with the grip held at F_lim. Parameters enter in log space, so every iterate
is positive.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from coopjax import scenarios
from coopjax.config import Config, check_setting, is_number, setting
from coopjax.errors import InputError
from coopjax.integration import INTEGRATORS
from coopjax.objectives import METRICS
from coopjax.objectives.base import missing_windows
from coopjax.params import PARAMETERS, Params, make_params, split_name
from tuning import design, problem_file
from tuning.design import Uncertain

GAINS = ("K_GP", "K_GI", "tau", "G_e")
GAINS_PER_ROBOT = tuple(f"{g}_{r}" for g in GAINS for r in "LR")
IMPEDANCE = ("M_c", "R_c", "K_c", "M_f", "R_f", "K_f")
# The random-search box of the four gains (log-uniform); every tuner searches the same box. Other
# tunable names get their default x/÷ 10 (impedance) and per-robot names their base name's box.
BOUNDS = {"K_GP": (0.005, 100.0), "K_GI": (0.001, 10.0), "tau": (0.05, 50.0), "G_e": (1.0, 3000.0)}
# "Holds the grip" means min_grip >= F_lim - HOLD_TOLERANCE: on F = F_lim the sliding-mode
# integrator's limit can dip a little below F_lim while the motion enters the surface.
HOLD_TOLERANCE = 0.01  # N
# s: filippov met the accuracy tolerances on 16 of 16 samples at 2e-3 and 1e-3 (docs/model.md, "Step
# size"). Training takes the coarsest; judging (`tuning.judging`) takes 1e-3.
TRAIN_DT = INTEGRATORS["filippov"].converged_dt[("carry", "hard")]
SURROGATE_DT = 2.5e-4  # s: plain RK4 on the smooth surrogates (docs/tuning.md)
SWITCHES = ("hard", "blend", "smooth", "straight_through")
AGGREGATES = ("smoothmax", "cvar", "max", "mean")


def bounds(name: str) -> tuple[float, float]:
    base = split_name(name)[0]
    if base in BOUNDS:
        return BOUNDS[base]
    default = PARAMETERS[base].default
    return default / 10.0, default * 10.0


# What `coopjax tune` may tune: the controller's own positive parameters (they live in log space).
# The plant (masses, gripper), the requirement F_lim and the constants K_ini, alpha_b, delta0 are not.
CONTROLLER = ("K_GP", "K_GI", "tau", "tau_e", "G_e", "rho", "M_c", "R_c", "K_c", "M_f", "R_f", "K_f", "mu_H", "beta_H")


def check_tuned_names(names) -> tuple[str, ...]:
    """Tunable parameters: the controller's, by name or per robot."""
    names = tuple(names)
    if not names:
        raise InputError("names: name at least one parameter to tune", "names")
    for name in names:
        base, robot = split_name(name)
        if base not in CONTROLLER:
            raise InputError(
                f"names: {name} is not a controller parameter; tune the gains (K_GP, K_GI, tau, G_e, "
                f"or per robot K_GP_L ...) or the impedance (M_c R_c K_c M_f R_f K_f); all: "
                f"{' '.join(CONTROLLER)}",
                "names",
            )
    if len(set(names)) != len(names):
        raise InputError("names: a parameter is named twice", "names")
    for name in names:
        base, robot = split_name(name)
        if robot is None and any(split_name(o)[0] == base and o != name for o in names):
            raise InputError(f"names: {name} (both robots) and a per-robot {base}_L/{base}_R are both named", "names")
    return names


def expand_params(text: str) -> tuple[str, ...]:
    """Shorthands: `gains` (4), `per-robot` (8: the gains of each robot), `all` (14)."""
    table = {"gains": GAINS, "per-robot": GAINS_PER_ROBOT, "all": GAINS_PER_ROBOT + IMPEDANCE}
    if text in table:
        return table[text]
    return tuple(x.strip() for x in text.split(",") if x.strip())


TRAINING_METRICS = ("min_grip", "peak_grip", "peak_hold", "slip", "rms_lag", "min_swi")
KINDS = ("at_least", "at_most")


def surrogate_config(switch: str, dt: float | None, scenario: str = "carry") -> Config:
    """The training runs of one scenario: the hard model at its coarsest converged step, or a smooth
    surrogate at its own."""
    if dt is None:
        converged = INTEGRATORS["filippov"].converged_dt.get((scenario, "hard")) or 1e-3
        dt = converged if switch == "hard" else SURROGATE_DT
    return Config(scenario, switch=switch, dt=dt, dtype="float64")


class Objective(NamedTuple):
    """A term of the objective: `weight` x `over` (over draws and scenarios) of `metric`."""

    metric: str
    over: str = "max"  # max | mean | cvar:ALPHA
    weight: float = 1.0  # objective units (N) per unit of the metric
    scenarios: tuple | None = None  # None: every scenario of the problem

    @property
    def alpha(self) -> float | None:
        """cvar:ALPHA's share (None: not a cvar, or ALPHA is not a number; `validate` says so)."""
        if not (isinstance(self.over, str) and self.over.startswith("cvar:")):
            return None
        try:
            return float(self.over.split(":", 1)[1])
        except ValueError:
            return None


class Requirement(NamedTuple):
    """A hard requirement: `metric` at least or at most `bound` at every draw of its scenarios."""

    metric: str
    kind: str  # at_least | at_most
    bound: float | str  # in the metric's unit, or a parameter's name (its value, per draw)
    scenarios: tuple | None = None

    @property
    def is_grip(self) -> bool:
        """The grip requirement min_grip >= F_lim: trained on the shortfall, judged with a tolerance."""
        return self.metric == "min_grip" and self.kind == "at_least" and self.bound == "F_lim"

    @property
    def text(self) -> str:
        where = f" on {', '.join(self.scenarios)}" if self.scenarios else ""
        return f"{self.metric} {'>=' if self.kind == 'at_least' else '<='} {self.bound}{where}"

    @property
    def tolerance(self) -> float:
        """How far below its bound the grip requirement is still met (`HOLD_TOLERANCE`); 0 otherwise."""
        return HOLD_TOLERANCE if self.is_grip else 0.0

    def slack(self, value, bound):
        """How far `value` clears the bound, in the metric's unit (negative: missed); NumPy or JAX."""
        return value - bound if self.kind == "at_least" else bound - value

    def met(self, value, bound):
        """Met by the one rule of training and judging: the slack clears minus the tolerance."""
        return self.slack(value, bound) >= -self.tolerance

    def bound_values(self, params):
        """The bound per sample of `params` (a per-robot parameter: its lower robot's value for
        at_least, as the grip's own check of F_lim takes it, the higher one's for at_most)."""
        if not isinstance(self.bound, str):
            return self.bound
        value = params.get(self.bound)
        if jnp.ndim(value) == 2:  # (robots, batch)
            value = value.min(0) if self.kind == "at_least" else value.max(0)
        return value


DEFAULT_MINIMISE = (Objective("peak_grip", "max", 1.0), Objective("rms_lag", "max", 1500.0))
DEFAULT_REQUIRE = (Requirement("min_grip", "at_least", "F_lim"),)
DEFAULT_UNCERTAIN = (Uncertain("M_b", "loguniform", 0.5, 5.0),)


@dataclasses.dataclass(frozen=True)
class Problem:
    """A tuning problem, as data; hashable, so it can be a jit static argument.

    Build it by keywords, or read it from a file with `Problem.from_toml` (docs/tuning.md gives the
    file's keys); `validate` checks it, `to_toml` writes it back.

    Args:
      names: the tuned parameters (controller parameters, or per robot `K_GP_L` ...).
      scenarios: the registered scenarios every draw runs.
      uncertain: `Uncertain` boxes the answer must hold over (`tuning.design` places the draws).
      minimise: the objective's `Objective` terms.
      require: the `Requirement`s, each at every draw.
      bounds: (name, low, high) search boxes replacing the defaults of `bounds`.
      fixed: (name, value) parameters held at a value (besides the defaults of Table 1).
      n_draws: training draws per step (with several uncertain parameters: besides the corners; twice
        as many in a fixed design, `design.FIXED_SOBOL`).
      jitter: fresh training draws every step; False: a fixed design.
      margin: training draws span the box widened by this share (selection by half of it).
      switch: the training model: hard (sliding-mode integrator) or a smooth surrogate.
      dt: the training step, s (None: each scenario's coarsest converged step, or SURROGATE_DT).
      aggregate: how training smooths a `max` term: smoothmax, cvar, max or mean.
      temperature: smoothmax's softness, in objective units (N).
      cvar_alpha: aggregate="cvar": the worst share averaged.
    """

    # The four gains of the paper alone cannot bring the worst peak under about 31 N while holding
    # the grip at 5 kg (docs/tuning.md); per-robot gains and the controller's impedance can.
    names: tuple[str, ...] = setting(
        GAINS_PER_ROBOT + IMPEDANCE,
        "the tuned parameters: gains (K_GP,K_GI,tau,G_e), per-robot (the 4 gains of each robot: 8), all "
        "(per-robot + M_c,R_c,K_c,M_f,R_f,K_f: 14), or comma-separated names",
        key="tune",
    )
    scenarios: tuple[str, ...] = setting(("carry",), "the registered scenarios every draw runs", key="scenario")
    uncertain: tuple = setting(DEFAULT_UNCERTAIN, "boxes the answer must hold over", key="uncertain")
    minimise: tuple = setting(DEFAULT_MINIMISE, "the objective's terms", key="minimise")
    require: tuple = setting(DEFAULT_REQUIRE, "the requirements, each at every draw", key="require")
    bounds: tuple = setting((), "search boxes of tuned names, replacing the defaults", key="bounds")
    fixed: tuple = setting((), "parameters held at a value, besides Table 1's", key="fixed")
    n_draws: int = setting(
        8,
        "training draws per step (screen-SLP: a grid, ends included; gradient: one per equal-probability "
        "stratum, drawn afresh each step; with several uncertain parameters, besides the box's corners, and "
        "screen-SLP takes twice as many)",
        "--train-masses",
        kind=int,
        key="training.n_draws",
        check=lambda x: None if x >= 2 else "at least 2 (the range's two ends)",
    )
    n_validation: int = setting(
        design.VALIDATION_COUNT,
        "validation draws on which the tuner's candidates are selected (a Sobol design of the box widened by "
        "half the margin; never the training or the held-out draws)",
        "--validation-draws",
        kind=int,
        key="training.n_validation",
        check=lambda x: None if x >= 2 else "at least 2",
    )
    jitter: bool = setting(
        True,
        "fresh training draws every step (the gradient tuner); false: a fixed design",
        "--fixed-masses",
        kind=bool,
        key="training.jitter",
    )
    margin: float = setting(
        0.05,
        "training draws span the box widened by this share (selection by half of it)",
        "--margin",
        kind=float,
        key="training.margin",
        check=lambda x: None if 0 <= x <= 1 else "a share of the box: from 0 to 1",
    )
    switch: str = setting("hard", "the training model", "--switch", SWITCHES, str, "training.switch")
    dt: float | None = setting(
        None,
        f"the training step (default: each scenario's coarsest converged step for hard, {SURROGATE_DT:g} for "
        "the smooth surrogates)",
        "--dt",
        kind=float,
        key="training.dt",
        unit="s",
        check=lambda x: None if x > 0 else "it must be positive",
    )
    aggregate: str = setting(
        "smoothmax", "training's smooth worst case over the draws", "--aggregate", AGGREGATES, str, "training.aggregate"
    )
    temperature: float = setting(
        0.5,
        "softness of smoothmax",
        "--temperature",
        kind=float,
        key="training.temperature",
        unit="N",
        check=lambda x: None if x > 0 else "it must be positive",
    )
    cvar_alpha: float = setting(
        0.25,
        "aggregate cvar: the worst share of draws averaged",
        "--cvar-alpha",
        kind=float,
        key="training.cvar_alpha",
        check=lambda x: None if 0 < x <= 1 else "it must be in (0, 1]",
    )

    @classmethod
    def unstated(cls, path: str) -> list[str]:
        """What a problem file leaves to the defaults that a reader should be told: its tuned names,
        scenarios, uncertain boxes, objective and requirements, as notes (one line each)."""
        fields, _ = problem_file.read(path, cls.file_keys())
        p0, notes = cls(), []
        for name, key, default in (
            ("names", "tune", "all 14 controller parameters"),
            ("uncertain", "uncertain", ", ".join(f"{u.name} {u.text}" for u in p0.uncertain)),
            ("minimise", "[[minimise]]", " + ".join(f"{o.weight:g} x {o.over} {o.metric}" for o in p0.minimise)),
            ("require", "[[require]]", ", ".join(r.text for r in p0.require)),
        ):
            if name not in fields:
                notes.append(f"{path} states no {key}: the default is taken ({default})")
        return notes

    @classmethod
    def file_keys(cls) -> dict:
        """A problem file's keys, as declared: the top-level ones (under None), `[training]`'s."""
        keys = [f.metadata["key"].split(".")[0] for f in dataclasses.fields(cls)]
        return {None: tuple(dict.fromkeys(keys)), "training": tuple(f.name for f in cls.settings("training"))}

    @classmethod
    def settings(cls, table: str | None = None) -> tuple[dataclasses.Field, ...]:
        """The fields a file states in `table` ("training": `[training]` KEY = VALUE), or all of them."""
        fields = dataclasses.fields(cls)
        return fields if table is None else tuple(f for f in fields if f.metadata["key"].startswith(table + "."))

    def __post_init__(self):
        # Hashable, whatever the caller passed (lists from a file, arrays).
        tup = lambda x: tuple(x) if isinstance(x, (list, tuple)) else (x,)
        object.__setattr__(self, "names", tup(self.names))
        object.__setattr__(self, "scenarios", tup(self.scenarios))
        object.__setattr__(self, "uncertain", tuple(Uncertain(*u) for u in self.uncertain))
        object.__setattr__(self, "minimise", tuple(_objective(o) for o in self.minimise))
        object.__setattr__(self, "require", tuple(_requirement(r) for r in self.require))
        object.__setattr__(self, "bounds", tuple((str(n), float(a), float(b)) for n, a, b in self.bounds))
        object.__setattr__(self, "fixed", tuple((str(n), float(v)) for n, v in self.fixed))

    @classmethod
    def from_toml(cls, path: str, **overrides) -> "Problem":
        """Read a problem file (docs/tuning.md, "Problem files"); `overrides` replace fields. A bad
        file raises one `InputError` naming the file, the key and the line."""
        fields, where = problem_file.read(path, cls.file_keys())
        if isinstance(fields.get("names"), str):
            fields["names"] = expand_params(fields["names"])
        try:
            return dataclasses.replace(cls(**fields), **overrides).validate()
        except InputError as error:
            raise problem_file.locate(error, where) from None

    def to_toml(self) -> str:
        """The problem as a file `from_toml` reads back."""
        return problem_file.dump(self)

    # --- what the problem runs

    @property
    def configs(self) -> tuple[Config, ...]:
        """The training runs of each scenario, with the metrics the problem reads there."""
        return tuple(
            dataclasses.replace(surrogate_config(self.switch, self.dt, s), metrics=self.metrics_on(s))
            for s in self.scenarios
        )

    @property
    def config(self) -> Config:
        """The training run whose step is the longest (the one stability limits)."""
        return max(self.configs, key=lambda c: c.dt)

    @property
    def train_dt(self) -> float:
        return self.config.dt

    def metrics_on(self, scenario: str) -> tuple[str, ...]:
        """The metrics training runs on `scenario`: the usual ones the scenario has windows for (one
        program then serves problems that differ only in their terms and requirements), and any
        other its terms and requirements read."""
        names = [n for n in TRAINING_METRICS if not missing_windows(n, scenarios.get(scenario))]
        names += [o.metric for o in self.minimise if _on(o, scenario)]
        for r in self.require:
            if _on(r, scenario):
                names += ["min_grip", "slip", "min_swi"] if r.is_grip else [r.metric]
        return tuple(dict.fromkeys(names))

    def base(self, base: Params | None = None) -> Params:
        """Table 1's parameters (or `base`) with the problem's fixed values."""
        base = make_params(dtype="float64") if base is None else base
        return base.replace(**dict(self.fixed)) if self.fixed else base

    def box(self, name: str) -> tuple[float, float]:
        """The search box of a tuned name."""
        for n, low, high in self.bounds:
            if n == name:
                return low, high
        return bounds(name)

    def log_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = zip(*(self.box(n) for n in self.names))
        return np.log(lo), np.log(hi)

    def log_box_around(self, theta, spread: float) -> tuple[np.ndarray, np.ndarray]:
        """The search box within x/÷ e^spread of the log-point theta (the starts' and the screen's box)."""
        lo, hi = self.log_bounds()
        return np.maximum(lo, theta - spread), np.minimum(hi, theta + spread)

    @property
    def uncertain_names(self) -> tuple[str, ...]:
        return tuple(u.name for u in self.uncertain)

    # --- the draws (tuning.design)

    def training_draws(self, seed: int = 0, step: int = 0) -> np.ndarray:
        """(M, p) training draws of one step, afresh per (seed, step) with `jitter`."""
        return design.training(self.uncertain, self.n_draws, self.margin, seed, step, self.jitter)

    def fixed_training_draws(self, finer: int = 1) -> np.ndarray:
        """(M, p) training draws for a tuner that keeps them for its whole run; `finer` times as many
        (a finer grid, or as many more Sobol points) for a stage that must not overfit the draws."""
        return design.fixed_training(self.uncertain, finer * self.n_draws, self.margin)

    def to_unit(self, draws) -> np.ndarray:
        """(M, p) draws in the box's unit coordinates (log coordinates for a loguniform parameter)."""
        draws = np.asarray(draws, np.float64).reshape(len(draws), -1)

        def span(u, x):
            if u.kind == "loguniform":
                return (np.log(x) - np.log(u.low)) / (np.log(u.high) - np.log(u.low))
            return (x - u.low) / (u.high - u.low)

        return np.stack([span(u, draws[:, i]) for i, u in enumerate(self.uncertain)], 1)

    def within_box(self, draws) -> np.ndarray:
        """(M, p) draws clipped into the uncertain box (training and validation draws span a wider one)."""
        draws = np.asarray(draws, np.float64).reshape(len(draws), -1)
        return np.clip(draws, [u.low for u in self.uncertain], [u.high for u in self.uncertain])

    def validation_draws(self) -> np.ndarray:
        return design.validation(self.uncertain, self.margin, self.n_validation)

    def held_out_draws(self, count: int = 12) -> np.ndarray:
        return design.held_out(self.uncertain, count)

    # --- the layout of an evaluation's columns, for M draws

    def objective_columns(self, M: int) -> list[np.ndarray]:
        """Per objective term, its columns among the cases (scenario-major: case s * M + m)."""
        return [columns_of(self.scenarios, o, M) for o in self.minimise]

    def constraint_columns(self, M: int) -> list[np.ndarray]:
        """Per requirement, its columns in the evaluation's `c` (one per draw of each of its scenarios)."""
        out, at = [], 0
        for r in self.require:
            n = len(columns_of(self.scenarios, r, M))
            out.append(np.arange(at, at + n))
            at += n
        return out

    def grip_columns(self, M: int) -> np.ndarray:
        """The cases of the grip requirement (where `min_swi`, the grip's margin, is read)."""
        grip = [r for r in self.require if r.is_grip]
        return columns_of(self.scenarios, grip[0], M) if grip else np.zeros(0, int)

    def n_constraints(self, M: int) -> int:
        return sum(len(c) for c in self.constraint_columns(M))

    @property
    def n_training(self) -> int:
        return len(self.fixed_training_draws())

    def validate(self) -> "Problem":
        check_tuned_names(self.names)
        if not self.scenarios:
            raise InputError("scenario: name at least one scenario", "scenario")
        for s in self.scenarios:
            if s not in scenarios.SCENARIOS:
                raise InputError(
                    f"scenario {s!r} is not registered; choose from {', '.join(scenarios.SCENARIOS)}", "scenario"
                )
        if len(set(self.scenarios)) != len(self.scenarios):
            raise InputError("scenario: a scenario is named twice", "scenario")
        design.check(self.uncertain)
        tuned = {split_name(n)[0] for n in self.names}
        for u in self.uncertain:
            if split_name(u.name)[0] in tuned:
                raise InputError(f"uncertain: {u.name} is tuned; a parameter is tuned or uncertain, not both", u.name)
        for n, v in self.fixed:
            if split_name(n)[0] in tuned:
                raise InputError(f"fixed: {n} is tuned; a parameter is tuned or fixed, not both", n)
            if any(split_name(n)[0] == split_name(u.name)[0] for u in self.uncertain):
                raise InputError(f"fixed: {n} is uncertain; a parameter is uncertain or fixed, not both", n)
        make_params(**dict(self.fixed))  # each value checked by the parameter's own rule
        for n, low, high in self.bounds:
            if n not in self.names:
                raise InputError(f"bounds: {n} is not tuned (tune = {', '.join(self.names)})", n)
            if not (math.isfinite(low) and math.isfinite(high) and 0 < low < high):
                raise InputError(
                    f"bounds: {n} = {low:g}:{high:g}: a tuned parameter is searched in log space: 0 < LOW < HIGH", n
                )
        if not self.minimise:
            raise InputError("minimise: give at least one objective term", "minimise")
        for o in self.minimise:
            _check_metric(o.metric, "minimise", self._on_scenarios(o))
            if o.over not in ("max", "mean") and not (o.alpha is not None and 0 < o.alpha <= 1):  # (a str)
                raise InputError(
                    f"minimise {o.metric}: over = {o.over!r}: max, mean or cvar:ALPHA with 0 < ALPHA <= 1", "over"
                )
            if not (isinstance(o.weight, float) and math.isfinite(o.weight) and o.weight > 0):
                raise InputError(f"minimise {o.metric}: weight = {o.weight!r}: it must be positive", "weight")
        for r in self.require:
            _check_metric(r.metric, "require", self._on_scenarios(r))
            if r.kind not in KINDS:
                raise InputError(f"require {r.metric}: give at_least or at_most", "require")
            if isinstance(r.bound, str):
                if split_name(r.bound)[0] in tuned:
                    raise InputError(
                        f"require {r.metric}: its bound {r.bound} is tuned; a bound names a fixed or uncertain "
                        "parameter",
                        "require",
                    )
            elif not (isinstance(r.bound, float) and math.isfinite(r.bound)):
                raise InputError(
                    f"require {r.metric}: the bound {r.bound!r} must be a finite number or a parameter's name",
                    "require",
                )
        for f in self.settings("training"):
            check_setting(f, getattr(self, f.name))
        for c in self.configs:  # precision is the run's setting: checking a problem needs no JAX mode
            dataclasses.replace(c, dtype=None).validate()
        return self

    def _on_scenarios(self, item) -> tuple[str, ...]:
        if item.scenarios is None:
            return self.scenarios
        for s in item.scenarios:
            if s not in self.scenarios:
                raise InputError(
                    f"{item.metric}: scenario {s!r} is not one of the problem's ({', '.join(self.scenarios)})",
                    "scenario",
                )
        return tuple(item.scenarios)


def _on(item, scenario: str) -> bool:
    return item.scenarios is None or scenario in item.scenarios


def columns_of(all_scenarios, item, M: int) -> np.ndarray:
    return np.concatenate([np.arange(i * M, (i + 1) * M) for i, s in enumerate(all_scenarios) if _on(item, s)])


def _check_metric(metric: str, where: str, on: tuple[str, ...]) -> None:
    if metric not in METRICS:
        raise InputError(f"{where}: unknown metric {metric!r}; choose from {', '.join(METRICS)}", metric)
    for s in on:
        lacking = missing_windows(metric, scenarios.get(s))
        if lacking:
            raise InputError(
                f"{where}: {metric} is taken over the {lacking[0]!r} window, which scenario {s!r} does not have; "
                f"name the scenarios it applies to (scenario = [...])",
                metric,
            )


def _objective(o) -> Objective:
    o = Objective(*o) if not isinstance(o, Objective) else o
    scen = None if o.scenarios is None else tuple([o.scenarios] if isinstance(o.scenarios, str) else o.scenarios)
    return o._replace(weight=_number(o.weight), scenarios=scen)


def _requirement(r) -> Requirement:
    r = Requirement(*r) if not isinstance(r, Requirement) else r
    scen = None if r.scenarios is None else tuple([r.scenarios] if isinstance(r.scenarios, str) else r.scenarios)
    return r._replace(bound=r.bound if isinstance(r.bound, str) else _number(r.bound), scenarios=scen)


def _number(x):
    """A float where `x` is a number; anything else kept as given, for `validate` to name."""
    return float(x) if is_number(x) else x


def to_log(values: dict[str, float], names) -> np.ndarray:
    return np.log(np.array([values[n] for n in names], np.float64))


def from_log(theta, names) -> dict[str, float]:
    return {n: float(np.exp(v)) for n, v in zip(names, np.asarray(theta))}
