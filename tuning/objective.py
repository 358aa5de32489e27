"""What the tuner optimises and how a result is judged (MODEL.md section 7).

The problem is constrained, on the hard model itself:

    minimise   f = smax_m peak_m + w_lag * smax_m lag_m          (worst case over the body masses)
    subject to c_m = 0 at every training mass m                  (the grip never drops below F_lim)

- `peak_m` is the largest grip force of the run [N] and `lag_m` the RMS tracking lag [mm] at body
  mass m; `smax` is a smooth maximum (or CVaR) over the mass batch, so the worst mass is what is
  pushed down, not the average one.
- `c_m = sqrt(slip_m + eps^2) - eps` is the RMS shortfall of the grip below F_lim over the grip
  window [N]: zero exactly while the grip holds (the hard switch slides on F = F_lim), smooth, and
  growing with both the depth and the duration of a loss.
- Training runs the hard switch and contact under the sliding-mode integrator (`filippov`) at the
  coarsest step within MODEL.md's tolerances (2e-3 s), one mass per stratum of the range per step.
  The smooth surrogates remain available (`switch=`), under plain RK4 at their own step.
- `judge` is the verdict: the same hard model at 1e-3 s, on held-out masses the training grid never
  hits; `select` picks among candidates on a third grid of validation masses.

Parameters enter in log space, so every iterate is positive.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import coopjax as cj
from coopjax.integration import CONVERGED_DT, SimConfig, integrate
from coopjax.model import Options
from coopjax.params import PARAMETERS, Params, split_name

GAINS = ("K_GP", "K_GI", "tau", "G_e")
GAINS_PER_ROBOT = tuple(f"{g}_{r}" for g in GAINS for r in "LR")
IMPEDANCE = ("M_c", "R_c", "K_c", "M_f", "R_f", "K_f")
# The random-search box of the four gains (log-uniform); every tuner searches the same box. Other
# tunable names get their default x/÷ 10 (impedance) and per-robot names their base name's box.
BOUNDS = {"K_GP": (0.005, 100.0), "K_GI": (0.001, 10.0), "tau": (0.05, 50.0), "G_e": (1.0, 3000.0)}
# "Holds the grip" means min_grip >= F_lim - HOLD_TOLERANCE: on F = F_lim the sliding-mode
# integrator's limit can dip a little below F_lim while the motion enters the surface.
HOLD_TOLERANCE = 0.01  # N
# s: filippov met MODEL.md's tolerances on 16 of 16 samples at 2e-3 and 1e-3 (docs/model.md, "Step
# size"). Training takes the coarsest; judging takes 1e-3, a factor 2 inside the stability limit of
# Table 1's gains (about 4e-3 s), which shrinks as K_GP grows.
TRAIN_DT = CONVERGED_DT[("carry", "hard", "filippov")]
JUDGE_DT = 1e-3
SURROGATE_DT = 2.5e-4  # s: plain RK4 on the smooth surrogates (docs/tuning.md)
SWITCHES = ("hard", "blend", "smooth", "straight_through")
AGGREGATES = ("smoothmax", "cvar", "max", "mean")
EPS_DEFICIT = 0.01  # N: the smoothing of c = sqrt(slip + eps^2) - eps near 0


def bounds(name: str) -> tuple[float, float]:
    base = split_name(name)[0]
    if base in BOUNDS:
        return BOUNDS[base]
    default = PARAMETERS[base].default
    return default / 10.0, default * 10.0


def check_tuned_names(names) -> tuple[str, ...]:
    """Tunable parameters: known names with a positive default (they live in log space)."""
    names = tuple(names)
    if not names:
        raise ValueError("--params: name at least one parameter to tune")
    for name in names:
        base, robot = split_name(name)
        if base in ("M_b",) or not PARAMETERS[base].per_robot:
            raise ValueError(f"--params: {name} is not a controller parameter; tune gains (K_GP, K_GI, tau, G_e, "
                             "or K_GP_L ...) or the impedance (M_c R_c K_c M_f R_f K_f)")
        if PARAMETERS[base].default <= 0:
            raise ValueError(f"--params: {name} has default {PARAMETERS[base].default:g}; only positive "
                             "parameters can be tuned (the tuner works on their logarithm)")
    if len(set(names)) != len(names):
        raise ValueError("--params: a parameter is named twice")
    for name in names:
        base, robot = split_name(name)
        if robot is None and any(split_name(o)[0] == base and o != name for o in names):
            raise ValueError(f"--params: {name} (both robots) and a per-robot {base}_L/{base}_R are both named")
    return names


def expand_params(text: str) -> tuple[str, ...]:
    """`--params` shorthands: `gains` (4), `per-robot` (8: the gains of each robot), `all` (14)."""
    table = {"gains": GAINS, "per-robot": GAINS_PER_ROBOT, "all": GAINS_PER_ROBOT + IMPEDANCE}
    if text in table:
        return table[text]
    return tuple(x.strip() for x in text.split(",") if x.strip())


@dataclasses.dataclass(frozen=True)
class Problem:
    """Static description of the tuning problem; hashable, so it can be a jit static argument."""

    # The four gains of the paper alone cannot bring the worst peak under about 31 N while holding
    # the grip at 5 kg (docs/tuning.md); per-robot gains and the controller's impedance can.
    names: tuple[str, ...] = GAINS_PER_ROBOT + IMPEDANCE
    masses: tuple = ("loguniform", 0.5, 5.0)  # the range the grip must hold over (and is judged on)
    n_masses: int = 8  # training strata: each keeps its own multiplier
    jitter: bool = True  # a fresh mass in each stratum every step; False: the strata's midpoints
    margin: float = 0.05  # the training grid spans [low / (1 + margin), high (1 + margin)]
    switch: str = "hard"  # "hard" (sliding-mode integrator) or a smooth surrogate under plain RK4
    dt: float = TRAIN_DT  # s
    w_lag: float = 1.5  # N of worst peak per mm of worst RMS lag
    aggregate: str = "smoothmax"  # over the mass batch: "smoothmax", "cvar", "max" or "mean"
    temperature: float = 0.5  # N: softness of smoothmax (it exceeds the max by at most T log M)
    cvar_alpha: float = 0.25  # cvar: the mean of the worst alpha share of the masses

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(self.names))  # hashable, whatever the caller passed
        object.__setattr__(self, "masses", tuple(self.masses))

    def validate(self) -> "Problem":
        check_tuned_names(self.names)
        check_mass_range(self.masses)
        if self.switch not in SWITCHES:
            raise ValueError(f"--switch must be one of {', '.join(SWITCHES)}, not {self.switch!r}")
        if self.aggregate not in AGGREGATES:
            raise ValueError(f"--aggregate must be one of {', '.join(AGGREGATES)}, not {self.aggregate!r}")
        if not isinstance(self.n_masses, int) or self.n_masses < 2:
            raise ValueError(f"--train-masses is {self.n_masses!r}: at least 2 (the range's two ends)")
        for flag, value in (("--w-lag", self.w_lag), ("--margin", self.margin)):
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{flag} is {value:g}: it must be finite and not negative")
        if not (self.temperature > 0 and math.isfinite(self.temperature)):
            raise ValueError(f"--temperature is {self.temperature:g}: it must be positive")
        if not 0 < self.cvar_alpha <= 1:
            raise ValueError(f"--cvar-alpha is {self.cvar_alpha:g}: it must be in (0, 1]")
        self.config.validate()
        return self

    @property
    def config(self) -> SimConfig:
        integrator = "filippov" if self.switch == "hard" else "rk4"
        return SimConfig("carry", Options(switch=self.switch), integrator=integrator, dt=self.dt)

    @property
    def training_range(self) -> tuple:
        kind, low, high = self.masses
        return kind, low / (1.0 + self.margin), high * (1.0 + self.margin)

    def training_masses(self, seed: int = 0, step: int = 0) -> np.ndarray:
        """One mass per equal-probability stratum of the widened range, drawn afresh for each
        (seed, step) when `jitter` is on, so that over a run the batch covers the whole range (the
        worst case can sit in a narrow band of masses) while each stratum keeps its multiplier."""
        if not self.jitter:
            return grid(self.training_range, self.n_masses, midpoints=True)
        kind, low, high = self.training_range
        u = (np.arange(self.n_masses) + np.random.default_rng([seed, step]).random(self.n_masses)) / self.n_masses
        if kind == "loguniform":
            return np.exp(np.log(low) + (np.log(high) - np.log(low)) * u)
        return low + (high - low) * u


def check_mass_range(masses) -> None:
    kind, low, high = masses
    if kind not in ("uniform", "loguniform") or not (math.isfinite(low) and math.isfinite(high) and 0 < low < high):
        raise ValueError(f"--masses {kind}:{low:g}:{high:g}: need loguniform or uniform, and 0 < LOW < HIGH (kg)")


def grid(masses, count: int, midpoints: bool = False) -> np.ndarray:
    """`count` masses over the range, ends included; or the midpoints of `count` equal strata."""
    kind, low, high = masses
    u = (np.arange(count) + 0.5) / count if midpoints else np.linspace(0.0, 1.0, count)
    if kind == "loguniform":
        return np.exp(np.log(low) + (np.log(high) - np.log(low)) * u)
    return low + (high - low) * u


def held_out_masses(masses, count: int = 12) -> np.ndarray:
    """The judging grid: ends included (the heaviest mass is the hardest). Training never hits it."""
    return grid(masses, count)


def validation_masses(problem: "Problem", count: int = 48) -> np.ndarray:
    """The selection grid: the training range (the judged one widened by the margin), ends included.
    Its masses are not on the held-out grid, and the extreme ones lie just outside the judged range,
    so a candidate that fails at the heaviest judged mass is not chosen."""
    return grid(problem.training_range, count)


def to_log(values: dict[str, float], names) -> np.ndarray:
    return np.log(np.array([values[n] for n in names], np.float64))


def from_log(theta, names) -> dict[str, float]:
    return {n: float(np.exp(v)) for n, v in zip(names, np.asarray(theta))}


def log_bounds(names) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = zip(*(bounds(n) for n in names))
    return np.log(lo), np.log(hi)


class Surrogate(NamedTuple):
    """Widths of the smooth switch and contact (MODEL.md section 4), used with switch != 'hard'."""

    k_F: float  # N
    k_c: float  # N
    eps_delta: float  # m


NARROW = Surrogate(k_F=0.1, k_c=0.1, eps_delta=2e-5)


def params_for(base: Params, names, theta, masses, problem: Problem | None = None) -> Params:
    """Parameter sets for starts x masses: theta is (K, n) log-values, masses (M,); batch K * M.

    Sample k * M + m is start k at mass m. Per-robot names (`K_GP_L`) set one robot.
    """
    K, M = theta.shape[0], masses.shape[0]
    values = {n: jnp.repeat(jnp.exp(theta[:, i]), M) for i, n in enumerate(names)}
    extra = {}
    if problem is not None and problem.switch != "hard":
        extra = {k: jnp.full((K * M,), v, theta.dtype) for k, v in NARROW._asdict().items()}
    return base.replace(M_b=jnp.tile(jnp.asarray(masses, theta.dtype), K), **values, **extra)


class Terms(NamedTuple):
    """Per start: the objective f (N), the constraints c (K, M) (N), and the per-(start, mass) metrics."""

    f: jax.Array
    c: jax.Array
    metrics: cj.Metrics


def smooth_max(x, problem: Problem, axis=-1):
    if problem.aggregate == "smoothmax":
        T = problem.temperature
        return T * jax.nn.logsumexp(x / T, axis=axis)
    if problem.aggregate == "cvar":
        k = max(1, math.ceil(problem.cvar_alpha * x.shape[axis]))
        return jnp.mean(jnp.sort(x, axis=axis)[..., -k:], axis=axis)
    if problem.aggregate == "max":
        return x.max(axis)
    return x.mean(axis)


def deficit(slip):
    """c = sqrt(slip + eps^2) - eps: the RMS grip shortfall (N), smooth at 0 where sqrt is not."""
    return jnp.sqrt(slip + EPS_DEFICIT**2) - EPS_DEFICIT


def terms(theta, base: Params, problem: Problem, masses) -> Terms:
    """Objective and constraints of every start at every mass; theta is (K, n) log-values, masses
    (M,). Pure; jit it outside."""
    masses = jnp.asarray(masses, theta.dtype)
    K, M = theta.shape[0], masses.shape[0]
    m = _metrics(params_for(base, problem.names, theta, masses, problem), problem.config)
    peak = m.peak_grip.reshape(K, M)
    lag_mm = 1e3 * m.rms_lag.reshape(K, M)
    f = smooth_max(peak, problem) + smooth_max(problem.w_lag * lag_mm, problem)
    c = deficit(m.slip.reshape(K, M))
    return Terms(f, c, jax.tree_util.tree_map(lambda x: x.reshape(K, M), m))


def _metrics(params: Params, config) -> "cj.Metrics":
    """The run's metrics, the batch split over every local device (all cores) when it divides evenly.

    Each device runs its own slice (`coopjax.devices.per_device`): under a GSPMD sharding
    constraint, the sliding-mode step's batch-wide "does any sample hit" became a cross-device
    all-reduce per substep, and a tuning step took 2x as long (measured).
    """
    devices = jax.local_devices()
    B = params.batch_shape[0]
    run = lambda p: integrate(p, config).metrics
    if len(devices) < 2 or B % len(devices):
        return run(params)
    from coopjax.devices import per_device

    return per_device(run, devices)(params)


# ----------------------------------------------------------------------------------------------
# Judging: hard switch, sliding-mode integrator, float64, masses the training never saw


class Verdict(NamedTuple):
    """Worst case over the judged masses, and the per-mass metrics behind it."""

    min_grip: float  # N, least over masses
    peak_grip: float  # N, largest over masses
    rms_lag: float  # m, largest over masses
    slip: float  # N^2, largest over masses
    crush: float  # N^2, largest over masses
    impact: float  # N^2, crush after the grip window (release), largest over masses
    objective: float  # N: peak_grip + w_lag * rms_lag in mm (the hard maximum over masses)
    finite: bool
    holds: bool  # min_grip >= F_lim - HOLD_TOLERANCE at every mass
    per_mass: dict  # name -> list over masses

    @property
    def score(self) -> float:
        """The validated objective: `objective` if the grip holds at every mass, else infinity."""
        return self.objective if self.holds else math.inf

    def row(self) -> dict:
        row = dict(self._asdict())
        row["rms_lag_mm"] = self.rms_lag * 1e3
        return row


def judge(values: dict[str, float] | list[dict[str, float]], masses, base: Params | None = None, w_lag: float = 1.0,
          dt: float = JUDGE_DT, progress: bool = False):
    """Judge one parameter set (or a list of them) with the hard model on `masses`, in float64.

    All runs go through the sweep runner, so they are sharded over every local device.
    """
    from coopjax import sweeps

    if not jax.config.jax_enable_x64:
        raise ValueError("judging runs in float64: call jax.config.update('jax_enable_x64', True) first")
    many = isinstance(values, (list, tuple))
    sets = list(values) if many else [values]
    masses = np.asarray(masses, np.float64)
    G, M = len(sets), len(masses)
    fixed = _fixed_from(base, set().union(*map(set, sets)))
    table = {n: np.repeat([float(g[n]) for g in sets], M) for n in sets[0]}
    table["M_b"] = np.tile(masses, G)
    spec = sweeps.make_spec("carry", None, {}, fixed, 0, "hard", dt, None, True, table, "filippov")
    columns = sweeps.run(spec, chunk=max(G * M, 1), progress=progress)
    F_lim = float(np.asarray((base or cj.make_params()).F_lim).min())
    verdicts = [_verdict({k: columns[k][g * M:(g + 1) * M] for k in sweeps.METRICS}, w_lag, F_lim) for g in range(G)]
    return verdicts if many else verdicts[0]


def select(candidates: list[dict], masses, base: Params | None = None, w_lag: float = 1.0,
           dt: float = JUDGE_DT) -> tuple[int, list[Verdict]]:
    """The candidate a hard-model validation prefers: it holds the grip at every validation mass and
    then has the lowest objective (ties: the earlier candidate). Returns its index and all verdicts.

    This is model selection, not judging: validation masses are never the held-out ones.
    """
    verdicts = judge(list(candidates), masses, base, w_lag, dt)
    return preferred(verdicts), verdicts


def preferred(verdicts: list[Verdict]) -> int:
    """`select`'s rule: the first verdict that holds with the lowest objective (or, if none holds, the
    lowest objective)."""
    key = lambda i: (not verdicts[i].holds, verdicts[i].objective if np.isfinite(verdicts[i].objective) else np.inf)
    return min(range(len(verdicts)), key=key)


def _fixed_from(base: Params | None, tuned: set) -> dict[str, float]:
    """The non-default scalar values of `base` as --set style overrides (tuned names excluded)."""
    if base is None:
        return {}
    default = cj.make_params()
    fixed = {}
    for name in PARAMETERS:
        value, ref = np.asarray(getattr(base, name), np.float64), np.asarray(getattr(default, name), np.float64)
        if value.shape != ref.shape:
            raise ValueError("the base parameters of a tuning run must be a single set, not a batch")
        if np.array_equal(value, ref) or name in tuned or name == "M_b":
            continue
        if PARAMETERS[name].per_robot:
            fixed[f"{name}_L"], fixed[f"{name}_R"] = float(value[0]), float(value[1])
        else:
            fixed[name] = float(value)
    tuned_bases = {split_name(n)[0] for n in tuned if split_name(n)[1] is None}
    return {k: v for k, v in fixed.items() if k not in tuned and split_name(k)[0] not in tuned_bases}


def _verdict(m: dict, w_lag: float, F_lim: float) -> Verdict:
    finite = bool(np.all(m["finite"] > 0.5))

    def worst(x, pick):
        return float(pick(x)) if finite else float("nan")

    min_grip, peak, lag = worst(m["min_grip"], np.min), worst(m["peak_grip"], np.max), worst(m["rms_lag"], np.max)
    return Verdict(
        min_grip=min_grip,
        peak_grip=peak,
        rms_lag=lag,
        slip=worst(m["slip"], np.max),
        crush=worst(m["crush"], np.max),
        impact=worst(m["impact"], np.max),
        objective=peak + w_lag * 1e3 * lag,
        finite=finite,
        holds=finite and min_grip >= F_lim - HOLD_TOLERANCE,
        per_mass={k: [float(x) for x in m[k]] for k in ("min_grip", "peak_grip", "rms_lag", "slip", "crush", "impact")},
    )
