"""The integrator interface, the registry, and what a step hands to the metrics.

An integrator is one subclass of `Integrator` in a file of its own, registered once with
`register`. The registry is what the rest of coopjax asks: the command line's choices, the default
integrator of each switch, the step-size check (each integrator's own stability function) and the
step-size note (the steps measured to converge, per scenario and switch).
"""

from __future__ import annotations

import abc
import functools
import inspect
from typing import Callable, ClassVar, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from coopjax import model
from coopjax.errors import InputError


class Path(NamedTuple):
    """The grip force through one step [t_k, t_k + dt], for metrics that integrate or bound it.

    An integrator that cuts the step at events (an impact, the force reaching F_lim) says where: the
    step is S pieces, in order, and the force is continuous on each. `start` and `end` are its values
    at each piece's ends; where one piece's end differs from the next one's start, the force jumps
    there (an impact). A piece of length 0 carries the previous end's value."""

    fraction: jax.Array  # (S, B) each piece's share of the step; they sum to 1
    start: jax.Array  # (S, 2, B) force at each piece's start, N (the first is the step start's)
    end: jax.Array  # (S, 2, B) force at each piece's end, N (the last is the step end's)
    # (S, 2, B) bool or None: the piece ends where the robot's force reaches F_lim (a located switch).
    # The force there is F_lim by definition; `end` carries the location's residue (first order).
    surface: jax.Array | None = None
    impact: jax.Array | None = None  # (S, 2, B) bool or None: the piece ends at the robot's impact

    @classmethod
    def whole(cls, start, end) -> "Path":
        """One piece: a step the integrator does not cut."""
        return cls(jnp.ones((1,) + end.shape[1:], end.dtype), start[None], end[None])


# The checkpoint name of the values a step's path is decided by (for the sliding-mode step: each
# piece's plan with its start's sigma and fractions theta, its cut, and whether it runs). Under
# reverse mode the time loop's checkpoint saves them instead of recomputing them (`loop.integrate`).
# The recomputation is a program of its own, which XLA may round differently; a decision that came
# out the other way there made the backward pass differentiate a path the forward pass had not
# taken: NaN float32 derivatives for 6 bodies in 256 (docs/speed.md, "The first derivative").
DECISIONS = "coopjax_decisions"


def decided(values):
    """`values` (a pytree of arrays) named as path decisions (`DECISIONS`)."""
    return jax.tree_util.tree_map(lambda x: checkpoint_name(x, DECISIONS), values)


class Observation(NamedTuple):
    """What the metrics see at the sample time t_k = k dt (k = 0..N): the state and signals there and,
    for k < N, the force's path through the step that starts there (None at the last sample)."""

    k: jax.Array  # int32 step index
    t: jax.Array  # s
    y: jax.Array  # (20, B) state at t_k
    aux: model.Aux  # signals at t_k, each (2, B)
    path: Path | None


class Integrator(abc.ABC):
    """A fixed-step integrator of the closed loop (the shape of diffrax's `AbstractSolver`).

    Subclasses set `name` and `switches` and implement `step` and `observe`; `register` refuses one
    that does not. `params` in both is the pair `model.robots(params)`, split once outside the time
    loop; `y` is the (20, B) state.
    """

    name: ClassVar[str]
    description: ClassVar[str] = ""
    switches: ClassVar[tuple[str, ...]]  # the switch modes it integrates
    default_for: ClassVar[tuple[str, ...]] = ()  # the switch modes it is the default for
    # (scenario, switch) -> the largest step measured to be within the accuracy tolerances of the
    # dt -> 0 limit (docs/model.md, "Step size"); None: no step tried reached them. Missing: not measured.
    converged_dt: ClassVar[Mapping[tuple[str, str], float | None]] = {}

    @abc.abstractmethod
    def step(self, params, y, t, dt, scenario, options) -> tuple[jax.Array, model.Aux, Path | None]:
        """y(t) -> (y(t + dt), the signals at t, the grip force's path through the step).

        An integrator that does not cut its step may return None for the path: the loop then takes
        the step as one piece, from the force at t to the force `observe` gives at t + dt (one more
        field evaluation a step)."""

    @abc.abstractmethod
    def observe(self, params, y, t, dt, scenario, options) -> model.Aux:
        """The signals recorded at (t, y)."""

    @staticmethod
    def amplification(z):
        """|R(z)| of the linear test equation y' = lambda y, z = lambda dt: classical RK4's by default."""
        return rk4_amplification(z)

    def stable_dt(self, eigenvalues):
        """Largest stable dt per sample for the linearised loop's eigenvalues (B, ...): NumPy, or JAX
        under a trace (`simulate` marks samples beyond it inside the traced program)."""
        return max_stable_dt(eigenvalues, type(self).amplification)

    def batch_order(self, params) -> np.ndarray | None:
        """For a step that decides some of its work for its whole batch at once (the sliding-mode
        step runs a piece's later parts when any sample needs them): the order in which a concrete
        batch (`params`, a batch on the last axis) runs, so that a slab holds like samples; the
        batch is then cut into slabs on one device too (`coopjax.devices.run`). None (the default):
        the step decides nothing per batch, any order and one program do."""
        return None

    def __repr__(self):
        return f"<integrator {self.name}>"


INTEGRATORS: dict[str, Integrator] = {}


def register(cls: type[Integrator]) -> type[Integrator]:
    """Class decorator: make an integrator known by its name. An incomplete one is refused here."""
    missing = [a for a in ("name", "switches") if not hasattr(cls, a)] + sorted(getattr(cls, "__abstractmethods__", ()))
    if not (inspect.isclass(cls) and issubclass(cls, Integrator)) or missing:
        raise TypeError(
            f"{getattr(cls, '__name__', cls)!r} is not a complete coopjax Integrator: it must subclass "
            f"Integrator and define {', '.join(missing) or 'name, switches, step and observe'}"
        )
    if cls.name in INTEGRATORS and type(INTEGRATORS[cls.name]) is not cls:
        raise ValueError(f"an integrator named {cls.name!r} is already registered")
    INTEGRATORS[cls.name] = cls()
    return cls


def get(name: str) -> Integrator:
    try:
        return INTEGRATORS[name]
    except (KeyError, TypeError):
        raise InputError(
            f"unknown integrator {name!r}; choose one of: {', '.join(INTEGRATORS)}", "integrator"
        ) from None


def default_for(switch: str) -> str:
    """The integrator a switch runs with when none is named."""
    for name, integrator in INTEGRATORS.items():
        if switch in integrator.default_for:
            return name
    raise InputError(f"no integrator is registered as the default for the {switch!r} switch", "switch")


# ----------------------------------------------------------------------------------------------
# Linear stability regions of explicit one-step methods


def rk4_amplification(z):
    return np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24)


def _first_exit(theta: np.ndarray, amplification: Callable) -> np.ndarray:
    """|z| at which the ray z = r e^{i theta} from 0 first leaves the stability region (fine scan,
    then bisection). 0 for rays into the right half-plane, where |R(z)| > 1 at once."""
    r = np.linspace(0.0, 6.0, 601)[1:]
    inside = amplification(r[None, :] * np.exp(1j * theta)[:, None]) <= 1 + 1e-12
    first_out = np.where(inside.all(axis=1), r.size, np.argmin(inside, axis=1))
    lo = np.where(first_out > 0, r[np.maximum(first_out - 1, 0)], 0.0)
    hi = r[np.minimum(first_out, r.size - 1)]
    for _ in range(40):
        mid = (lo + hi) / 2
        ok = amplification(mid * np.exp(1j * theta)) <= 1 + 1e-12
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return np.where(first_out == 0, 0.0, lo)


@functools.lru_cache(maxsize=16)
def stability_region(amplification: Callable):
    """The stable radius along each direction of the left half-plane (and the imaginary axis)."""
    theta = np.linspace(np.pi / 2, 3 * np.pi / 2, 4001)
    return theta, _first_exit(theta, amplification)


def max_stable_dt(eigenvalues, amplification: Callable = rk4_amplification):
    """Largest dt with every mode inside the stability region, per sample: min over modes of the
    region's radius along the mode's direction over |lambda| (0 if a mode grows, Re lambda > 0).
    NumPy or (traced) JAX eigenvalues; the region itself is a NumPy table."""
    xp = jnp if isinstance(eigenvalues, jax.Array) else np
    lam = eigenvalues.reshape(eigenvalues.shape[0], -1)
    size = xp.abs(lam)
    theta = xp.mod(xp.angle(lam), 2 * np.pi)
    radius = xp.interp(theta, *stability_region(amplification), left=0.0, right=0.0)
    # Modes at 0 (the free-floating bases, conserved integrals) limit nothing.
    tiny = size <= 1e-9 * xp.maximum(size.max(axis=1, keepdims=True), 1e-300)
    return xp.where(tiny, xp.inf, radius / xp.where(tiny, 1.0, size)).min(axis=1)
