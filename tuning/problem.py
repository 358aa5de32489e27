"""What the tuner optimises (how a result is judged: `tuning.judge`).

The problem is constrained, on the hard model itself:

    minimise   f = smax_m peak_m + w_lag * smax_m lag_m          (worst case over the body masses)
    subject to c_m = 0 at every training mass m                  (the grip never drops below F_lim)

- `peak_m` is the largest grip force of the run [N] and `lag_m` the RMS tracking lag [mm] at body
  mass m; `smax` is a smooth maximum (or CVaR) over the mass batch, so the worst mass is what is
  pushed down, not the average one.
- `c_m = sqrt(slip_m + eps^2) - eps` is the RMS shortfall of the grip below F_lim over the grip
  window [N]: zero exactly while the grip holds (the hard switch slides on F = F_lim), smooth, and
  growing with both the depth and the duration of a loss.
- Training runs the problem's `config`: by default the hard switch and contact under the
  sliding-mode integrator at the coarsest step within the accuracy tolerances (2e-3 s).
- `held_out_masses` and `validation_masses` are the grids `tuning.judge` judges and selects on;
  the training grid never hits them.

Parameters enter in log space, so every iterate is positive.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coopjax import devices
from coopjax.config import Config
from coopjax.errors import InputError
from coopjax.integration import INTEGRATORS
from coopjax.objectives import Metrics
from coopjax.params import PARAMETERS, Params, split_name
from coopjax.simulation import metrics_of
from coopjax.stability import stable_dt

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
# size"). Training takes the coarsest; judging (`tuning.judge`) takes 1e-3.
TRAIN_DT = INTEGRATORS["filippov"].converged_dt[("carry", "hard")]
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


TRAINING_METRICS = ("min_grip", "peak_grip", "slip", "rms_lag", "min_swi")  # what the problem is built from


def training_config(switch: str = "hard", dt: float | None = None) -> Config:
    """The training runs: the hard model at the coarsest converged step, or a surrogate at its own."""
    return Config(
        "carry",
        switch=switch,
        dt=dt if dt is not None else (TRAIN_DT if switch == "hard" else SURROGATE_DT),
        dtype="float64",
        metrics=TRAINING_METRICS,
    )


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
    config: Config = training_config()  # the training runs (scenario carry)
    w_lag: float = 1.5  # N of worst peak per mm of worst RMS lag
    aggregate: str = "smoothmax"  # over the mass batch: "smoothmax", "cvar", "max" or "mean"
    temperature: float = 0.5  # N: softness of smoothmax (it exceeds the max by at most T log M)
    cvar_alpha: float = 0.25  # cvar: the mean of the worst alpha share of the masses

    def __post_init__(self):
        object.__setattr__(self, "names", tuple(self.names))  # hashable, whatever the caller passed
        object.__setattr__(self, "masses", tuple(self.masses))

    @property
    def switch(self) -> str:
        return self.config.switch

    @property
    def dt(self) -> float:
        return self.config.dt

    def validate(self) -> "Problem":
        check_tuned_names(self.names)
        check_mass_range(self.masses)
        if not isinstance(self.config, Config):
            raise InputError(f"config must be a coopjax.Config, got {type(self.config).__name__}", "config")
        if self.config.scenario != "carry":
            raise InputError(
                f"the tuning problem is posed on the carry scenario, not {self.config.scenario!r}", "config"
            )
        if self.switch not in SWITCHES:
            raise InputError(f"switch must be one of {', '.join(SWITCHES)}, not {self.switch!r}", "switch")
        if self.aggregate not in AGGREGATES:
            raise InputError(f"aggregate must be one of {', '.join(AGGREGATES)}, not {self.aggregate!r}", "aggregate")
        if isinstance(self.n_masses, bool) or not isinstance(self.n_masses, int) or self.n_masses < 2:
            raise InputError(f"n_masses is {self.n_masses!r}: at least 2 (the range's two ends)", "n_masses")
        for field, value in (("w_lag", self.w_lag), ("margin", self.margin)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InputError(f"{field} is {value!r}: it must be finite and not negative", field)
        if not (self.temperature > 0 and math.isfinite(self.temperature)):
            raise InputError(f"temperature is {self.temperature:g}: it must be positive", "temperature")
        if not 0 < self.cvar_alpha <= 1:
            raise InputError(f"cvar_alpha is {self.cvar_alpha:g}: it must be in (0, 1]", "cvar_alpha")
        self.config.validate()
        return self

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
        raise InputError(
            f"masses {kind}:{low:g}:{high:g}: need loguniform or uniform, and 0 < LOW < HIGH (kg)", "masses"
        )


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
    """Widths of the smooth switch and contact (docs/model.md, "Smooth surrogates"), with switch != 'hard'."""

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
    metrics: Metrics


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


def terms(theta, base: Params, problem: Problem, masses, checkpoint: bool | str = True) -> Terms:
    """Objective and constraints of every start at every mass; theta is (K, n) log-values, masses
    (M,). Pure; jit it outside. The batch is split over every local device (`devices.run`).
    `checkpoint` is the reverse-mode memory policy of `coopjax.simulate`."""
    masses = jnp.asarray(masses, theta.dtype)
    K, M = theta.shape[0], masses.shape[0]
    params = params_for(base, problem.names, theta, masses, problem)
    m = devices.run(metrics_of(problem.config, checkpoint), params, shard_traced=True)
    peak = m.peak_grip.reshape(K, M)
    lag_mm = 1e3 * m.rms_lag.reshape(K, M)
    f = smooth_max(peak, problem) + smooth_max(problem.w_lag * lag_mm, problem)
    c = deficit(m.slip.reshape(K, M))
    return Terms(f, c, jax.tree_util.tree_map(lambda x: x.reshape(K, M), m))


def starting_points(
    problem: Problem, base: Params, first: dict[str, float], count: int, spread: float, seed: int
) -> np.ndarray:
    """The first start (log of `first`, clipped to the box), then `count - 1` log-uniform draws within
    x/÷ e^spread of it, each stable at the training step: a draw whose linearised loop needs dt below
    1.5 x the training step is drawn again (up to 50 rounds), so no start begins where its very first
    step would blow up. Every tuner starts from these points."""
    names = problem.names
    lo, hi = log_bounds(names)
    start = np.clip(to_log(first, names), lo, hi)
    rng = np.random.default_rng(seed)
    points = [start]
    a, b = np.maximum(lo, start - spread), np.minimum(hi, start + spread)
    for _ in range(50):
        if len(points) >= count:
            break
        draws = a + (b - a) * rng.random((4 * count, len(names)))
        params = base.replace(M_b=np.ones(len(draws)), **{n: np.exp(draws[:, i]) for i, n in enumerate(names)})
        limit, _ = stable_dt(params, problem.config)
        points += [d for d, ok in zip(draws, limit >= 1.5 * problem.dt) if ok]
    if len(points) < count:
        raise InputError(
            f"found only {len(points)} stable starting points in 50 rounds; try a smaller spread", "spread"
        )
    return np.stack(points[:count])
