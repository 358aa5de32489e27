"""Parameters of the closed loop (MODEL.md section 1) as one pytree.

Every parameter is an array leaf, so `jax.grad`, `jax.jacfwd` and `jax.vmap` work over any of
them. Per-robot parameters carry a leading axis of length 2 (index 0 is robot L, 1 is robot R);
shared ones (the body, the scenario amplitudes, surrogate widths) do not. A batch of parameter
sets adds one trailing axis of length B to every leaf, matching the state's batch-last layout.

Names: `K_GP` sets both robots, `K_GP_L` / `K_GP_R` set one robot only.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Spec(NamedTuple):
    default: float
    unit: str
    per_robot: bool
    check: str  # "positive", "nonnegative" or "finite"
    doc: str


# Table 1 of the paper, with the realisation choices of MODEL.md.
PARAMETERS: dict[str, Spec] = {
    "M_v": Spec(10.0, "kg", True, "positive", "space-vehicle base mass"),
    "M_r": Spec(1.0, "kg", True, "positive", "robot (end-effector link) mass"),
    "K_g": Spec(1000.0, "N/m", True, "positive", "gripper stiffness"),
    "R_g": Spec(100.0, "N s/m", True, "nonnegative", "gripper damping"),
    "M_c": Spec(10.0, "kg", True, "positive", "controller inertance"),
    "R_c": Spec(5.0, "N s/m", True, "nonnegative", "controller damping"),
    "K_c": Spec(500.0, "N/m", True, "positive", "controller stiffness"),
    "M_f": Spec(1.0, "kg", True, "positive", "virtual-foundation mass"),
    "R_f": Spec(200.0, "N s/m", True, "nonnegative", "virtual-foundation damping"),
    "K_f": Spec(10.0, "N/m", True, "positive", "virtual-foundation stiffness"),
    "mu_H": Spec(300.0, "1", True, "positive", "feed-forward (actuator) gain"),
    "beta_H": Spec(300.0, "1", True, "positive", "virtual-foundation feedback gain"),
    "F_lim": Spec(10.0, "N", True, "finite", "force limit: minimum gripping force"),
    "K_ini": Spec(0.0, "1", True, "finite", "gain-modulation constant (Eq. 8)"),
    "K_GP": Spec(0.5, "1/N", True, "finite", "gain-modulation proportional gain (Eq. 8)"),
    "K_GI": Spec(0.1, "1/(N s)", True, "finite", "gain-modulation integral gain (Eq. 8)"),
    "tau": Spec(100.0 / 80.0, "1/s", True, "nonnegative", "force-error relaxation K_r/R_r (Eq. 9)"),
    "tau_e": Spec(10.0 / 6.0, "1/s", True, "nonnegative", "amnesia relaxation K_e/R_e (Eq. 10)"),
    "G_e": Spec(600.0, "1/s", True, "nonnegative", "amnesia-removal gain (Eq. 11, G_a in Table 1)"),
    "rho": Spec(200.0, "1/s", True, "nonnegative", "reset rate of the switched memories"),
    "delta0": Spec(0.0, "m", True, "finite", "initial gripper compression"),
    "alpha_b": Spec(1.0, "1", True, "finite", "base-velocity compensation gain (1 = full)"),
    "M_b": Spec(1.0, "kg", False, "positive", "body mass"),
    "A_1": Spec(10.0, "m/s", False, "finite", "paper scenario: left command amplitude"),
    "A_2": Spec(-10.0, "m/s", False, "finite", "paper scenario: right command amplitude"),
    "A_g": Spec(0.1, "m/s", False, "finite", "carry scenario: grip amplitude"),
    "A_c": Spec(0.5, "m/s", False, "finite", "carry scenario: carry amplitude"),
    "F_max": Spec(15.0, "N", False, "finite", "upper force band of the crush objective"),
    "k_F": Spec(0.5, "N", False, "positive", "smooth switch width"),
    "k_c": Spec(0.5, "N", False, "positive", "smooth contact-force width"),
    "eps_delta": Spec(1e-4, "m", False, "positive", "smooth contact-engagement width"),
}

PER_ROBOT = tuple(n for n, s in PARAMETERS.items() if s.per_robot)
SHARED = tuple(n for n, s in PARAMETERS.items() if not s.per_robot)
ROBOTS = ("L", "R")


def _field(name):
    return dataclasses.field(metadata={"spec": PARAMETERS[name]})


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Params:
    """All parameters; leaves are arrays. Build with `make_params`, update with `.replace`."""

    M_v: jax.Array = _field("M_v")
    M_r: jax.Array = _field("M_r")
    K_g: jax.Array = _field("K_g")
    R_g: jax.Array = _field("R_g")
    M_c: jax.Array = _field("M_c")
    R_c: jax.Array = _field("R_c")
    K_c: jax.Array = _field("K_c")
    M_f: jax.Array = _field("M_f")
    R_f: jax.Array = _field("R_f")
    K_f: jax.Array = _field("K_f")
    mu_H: jax.Array = _field("mu_H")
    beta_H: jax.Array = _field("beta_H")
    F_lim: jax.Array = _field("F_lim")
    K_ini: jax.Array = _field("K_ini")
    K_GP: jax.Array = _field("K_GP")
    K_GI: jax.Array = _field("K_GI")
    tau: jax.Array = _field("tau")
    tau_e: jax.Array = _field("tau_e")
    G_e: jax.Array = _field("G_e")
    rho: jax.Array = _field("rho")
    delta0: jax.Array = _field("delta0")
    alpha_b: jax.Array = _field("alpha_b")
    M_b: jax.Array = _field("M_b")
    A_1: jax.Array = _field("A_1")
    A_2: jax.Array = _field("A_2")
    A_g: jax.Array = _field("A_g")
    A_c: jax.Array = _field("A_c")
    F_max: jax.Array = _field("F_max")
    k_F: jax.Array = _field("k_F")
    k_c: jax.Array = _field("k_c")
    eps_delta: jax.Array = _field("eps_delta")

    def replace(self, **values) -> "Params":
        """Like `make_params`: `K_GP` sets both robots, `K_GP_L` one. Shapes are not broadcast."""
        return make_params(self, **values)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self.M_b))

    def astype(self, dtype) -> "Params":
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), self)

    def get(self, name: str):
        """A parameter by its public name, e.g. `K_GP_L` or `M_b`."""
        base, robot = split_name(name)
        value = getattr(self, base)
        return value if robot is None else value[ROBOTS.index(robot)]


def default_dtype():
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


def split_name(name: str) -> tuple[str, str | None]:
    """`K_GP_L` -> (`K_GP`, `L`); `M_b` -> (`M_b`, None). Raises ValueError if unknown."""
    if name in PARAMETERS:
        return name, None
    for robot in ROBOTS:
        base = name[: -len(robot) - 1]
        if name.endswith("_" + robot) and base in PER_ROBOT:
            return base, robot
        if name.endswith("_" + robot) and base in SHARED:
            raise ValueError(f"{base} is shared by both robots; set {base}, not {name}")
    raise ValueError(f"unknown parameter {name!r}{_suggest(name)}")


def public_names() -> list[str]:
    """Every name `make_params` accepts."""
    names = []
    for n in PARAMETERS:
        names.append(n)
        if PARAMETERS[n].per_robot:
            names += [f"{n}_{r}" for r in ROBOTS]
    return names


def _suggest(name: str) -> str:
    close = difflib.get_close_matches(name, public_names(), n=3, cutoff=0.6)
    if close:
        return "; did you mean " + " or ".join(repr(c) for c in close) + "?"
    return "; run `coopjax params` for the list"


def make_params(base: Params | None = None, dtype=None, **values) -> Params:
    """Table 1 defaults (or `base`), overridden by `values`.

    A value is a scalar or a 1-D array of length B (one entry per parameter set); every 1-D value
    must have the same B, and then every leaf gets the batch axis. Static checks (names,
    finiteness, signs) raise `ValueError` here, before anything is traced.
    """
    dtype = dtype or (base.M_b.dtype if base is not None else default_dtype())
    leaves = {}
    for n, spec in PARAMETERS.items():
        if base is not None:
            leaves[n] = base.__dict__[n]
        elif spec.per_robot:
            leaves[n] = np.full((2,), spec.default)
        else:
            leaves[n] = np.asarray(spec.default)

    batch = None if base is None else base.batch_shape
    updates: dict[str, list] = {}
    for name, value in values.items():
        base_name, robot = split_name(name)
        if not _is_tracer(value):
            value = np.asarray(value, dtype=np.float64)
            if value.ndim > 1:
                raise ValueError(f"{name}: expected a scalar or a 1-D batch, got shape {value.shape}")
        if np.ndim(value) == 1:
            if batch not in (None, (), np.shape(value)):
                raise ValueError(
                    f"{name}: batch of {np.shape(value)[0]} does not match the batch of {batch[0]}"
                )
            batch = np.shape(value)
        updates.setdefault(base_name, []).append((robot, value))
    batch = batch or ()

    def widen(x, per_robot):
        target = ((2,) if per_robot else ()) + batch
        if np.shape(x) == target:
            return x
        if len(batch) and np.ndim(x) == (1 if per_robot else 0):
            x = x[..., None]
        return (jnp if _is_tracer(x) else np).broadcast_to(x, target)

    for n in PARAMETERS:
        leaves[n] = widen(leaves[n], PARAMETERS[n].per_robot)
    for n, items in updates.items():
        for robot, value in items:
            value = value if np.ndim(value) == len(batch) else widen_shared(value, batch)
            if PARAMETERS[n].per_robot:
                rows = [value if robot in (None, r) else leaves[n][i] for i, r in enumerate(ROBOTS)]
                leaves[n] = (jnp if _any_tracer(rows) else np).stack(rows)
            else:
                leaves[n] = value

    params = Params(**{n: jnp.asarray(v, dtype) for n, v in leaves.items()})
    validate(params)
    return params


def widen_shared(value, batch):
    return (jnp if _is_tracer(value) else np).broadcast_to(value, batch)


def _is_tracer(x) -> bool:
    return isinstance(x, jax.core.Tracer)


def _any_tracer(xs) -> bool:
    return any(_is_tracer(x) for x in xs)


def validate(params: Params) -> None:
    """Raise ValueError on a non-finite value or a sign that makes the model meaningless.

    Traced leaves (inside grad or vmap) cannot be inspected and are skipped.
    """
    for n, spec in PARAMETERS.items():
        leaf = getattr(params, n)
        if _is_tracer(leaf):
            continue
        x = np.asarray(leaf)
        where = _where(n, x, spec.per_robot)
        bad = ~np.isfinite(x)
        if bad.any():
            raise ValueError(f"{where(bad)} is {_first(x, bad)}: every parameter must be finite")
        if spec.check == "positive" and (x <= 0).any():
            raise ValueError(f"{where(x <= 0)} is {_first(x, x <= 0)} {spec.unit}: it must be positive ({spec.doc})")
        if spec.check == "nonnegative" and (x < 0).any():
            raise ValueError(f"{where(x < 0)} is {_first(x, x < 0)} {spec.unit}: it must not be negative ({spec.doc})")


def _first(x, mask):
    return f"{x[mask].ravel()[0]:g}"


def _where(name, x, per_robot):
    def describe(mask):
        idx = np.argwhere(mask)[0]
        label = f"{name}_{ROBOTS[idx[0]]}" if per_robot else name
        sample = idx[1:] if per_robot else idx
        return label + (f" (sample {int(sample[0])})" if len(sample) else "")

    return describe


def check_positive(name: str, value: float) -> float:
    """For the integration settings (dt, T): finite and > 0."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} is {value:g}: it must be positive and finite")
    return value


def as_batched(params: Params) -> tuple[Params, bool]:
    """Give every leaf a batch axis of at least 1; also say whether one was added."""
    if params.batch_shape:
        return params, False
    return jax.tree_util.tree_map(lambda x: x[..., None], params), True
