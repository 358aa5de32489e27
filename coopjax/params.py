"""Parameters of the closed loop as one pytree, declared in one table.

Every parameter is an array leaf, so `jax.grad`, `jax.jacfwd` and `jax.vmap` work over any of them.
Per-robot parameters carry a leading axis of length 2 (index 0 is robot L, 1 is robot R); shared
ones (the body, the scenario amplitudes, the surrogate widths) do not. A batch of parameter sets
adds one trailing axis of length B to every leaf, matching the state's batch-last layout.

The table `PARAMETERS` starts with the model's own parameters (the paper's Table 1). A scenario or a
metric that needs parameters of its own declares them with `declare`, in the file that defines it.

Names: `K_GP` sets both robots, `K_GP_L` / `K_GP_R` one robot. A per-robot name always wins over
the shared name, whatever the order they are given in.
"""

from __future__ import annotations

import difflib
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from coopjax.errors import InputError
from coopjax.traced import is_tracer


class Spec(NamedTuple):
    default: float
    unit: str
    per_robot: bool
    check: str  # "positive", "nonnegative" or "finite"
    doc: str


# Table 1 of the paper, with the realisation choices (docs/model.md).
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
    "k_F": Spec(0.5, "N", False, "positive", "smooth switch width"),
    "k_c": Spec(0.5, "N", False, "positive", "smooth contact-force width"),
    "eps_delta": Spec(1e-4, "m", False, "positive", "smooth contact-engagement width"),
}
OWNER: dict[str, str] = {name: "model" for name in PARAMETERS}  # who declared each parameter
ROBOTS = ("L", "R")


def declare(owner: str, specs: dict[str, Spec]) -> None:
    """Add parameters to the table (a scenario's amplitudes, a metric's band). Declaring the same
    spec again (two metrics sharing a band) is harmless; another spec under a taken name is a
    programming error."""
    for name, spec in specs.items():
        if name in PARAMETERS and PARAMETERS[name] != spec:
            raise ValueError(f"parameter {name!r} is already declared by {OWNER[name]}")
        if any(name.endswith("_" + r) for r in ROBOTS):
            raise ValueError(f"parameter {name!r}: names ending in _L or _R are the per-robot spellings")
    for name, spec in specs.items():
        PARAMETERS[name] = spec
        OWNER.setdefault(name, owner)


def per_robot_names() -> tuple[str, ...]:
    return tuple(n for n, s in PARAMETERS.items() if s.per_robot)


@jax.tree_util.register_pytree_with_keys_class
class Params:
    """All parameters by name, every leaf an array. Build with `make_params`, update with `.replace`.

    `p.K_GP` is a leaf; `p.get("K_GP_L")` takes one robot's value by its public name.
    """

    __slots__ = ("_leaves",)

    def __init__(self, leaves: dict):
        object.__setattr__(self, "_leaves", dict(leaves))

    def __getattr__(self, name):
        leaves = object.__getattribute__(self, "_leaves")
        try:
            return leaves[name]
        except KeyError:
            raise AttributeError(f"no parameter {name!r} in these Params{_suggest(name, list(leaves))}") from None

    def __setattr__(self, name, value):
        raise AttributeError("Params is immutable: use .replace(...)")

    def __reduce__(self):
        return Params, (self._leaves,)

    def __repr__(self):
        return f"Params({', '.join(self._leaves)}; batch shape {self.batch_shape})"

    def tree_flatten_with_keys(self):
        return [(jax.tree_util.GetAttrKey(k), v) for k, v in self._leaves.items()], tuple(self._leaves)

    def tree_flatten(self):
        return list(self._leaves.values()), tuple(self._leaves)

    @classmethod
    def tree_unflatten(cls, names, leaves):
        return cls(dict(zip(names, leaves)))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._leaves)

    def leaves(self) -> dict:
        return dict(self._leaves)

    def with_leaves(self, **leaves) -> "Params":
        """New leaves as they are, unchecked (internal: robot views, operating points)."""
        return Params({**self._leaves, **leaves})

    def replace(self, **values) -> "Params":
        """Like `make_params`: `K_GP` sets both robots, `K_GP_L` one. Shapes are not broadcast."""
        return make_params(self, **values)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(np.shape(self._leaves["M_b"]))

    @property
    def dtype(self):
        return self._leaves["M_b"].dtype

    def astype(self, dtype) -> "Params":
        dtype = resolve_dtype(dtype)
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), self)

    def get(self, name: str):
        """A parameter by its public name, e.g. `K_GP_L` or `M_b`."""
        base, robot = split_name(name)
        value = getattr(self, base)
        return value if robot is None else value[ROBOTS.index(robot)]


def default_dtype():
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


def resolve_dtype(dtype):
    """A dtype from its name or object; float64 only in JAX's 64-bit mode (it would silently be float32)."""
    try:
        dtype = jnp.dtype(dtype)
    except TypeError:
        raise InputError(f"dtype {dtype!r}: choose float32 or float64", "dtype") from None
    if dtype not in (jnp.float32, jnp.float64):
        raise InputError(f"dtype {dtype.name}: choose float32 or float64", "dtype")
    if dtype == jnp.float64 and not jax.config.jax_enable_x64:
        raise InputError(
            "float64 needs JAX's 64-bit mode: call jax.config.update('jax_enable_x64', True) "
            "before anything creates an array",
            "dtype",
        )
    return dtype


def split_name(name: str) -> tuple[str, str | None]:
    """`K_GP_L` -> (`K_GP`, `L`); `M_b` -> (`M_b`, None). Raises InputError if unknown."""
    if not isinstance(name, str):
        raise InputError(f"a parameter name must be a string, got {name!r}")
    if name in PARAMETERS:
        return name, None
    for robot in ROBOTS:
        base = name[: -len(robot) - 1]
        if name.endswith("_" + robot) and base in PARAMETERS:
            if PARAMETERS[base].per_robot:
                return base, robot
            raise InputError(f"{base} is shared by both robots; set {base}, not {name}", name)
    raise InputError(f"unknown parameter {name!r}{_suggest(name)}", name)


def public_names() -> list[str]:
    """Every name `make_params` accepts."""
    names = []
    for n in PARAMETERS:
        names.append(n)
        if PARAMETERS[n].per_robot:
            names += [f"{n}_{r}" for r in ROBOTS]
    return names


def _suggest(name: str, names=None) -> str:
    close = difflib.get_close_matches(str(name), names or public_names(), n=3, cutoff=0.6)
    if close:
        return "; did you mean " + " or ".join(repr(c) for c in close) + "?"
    return "; run `coopjax params` for the list"


def _as_value(name, value):
    """A scalar or a 1-D array of numbers (a traced value passes as it is)."""
    if is_tracer(value):
        return value
    if isinstance(value, (str, bytes, dict, set)) or value is None:
        raise InputError(f"{name}: expected a number or a 1-D array of numbers, got {value!r}", name)
    try:
        value = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number or a 1-D array of numbers, got {value!r}", name) from None
    if value.ndim > 1:
        raise InputError(f"{name}: expected a scalar or a 1-D batch, got shape {value.shape}", name)
    if value.ndim == 1 and value.shape[0] == 0:
        raise InputError(f"{name}: an empty batch; give at least one value", name)
    return value


def make_params(base: Params | None = None, dtype=None, **values) -> Params:
    """Table 1 defaults (or `base`), overridden by `values`.

    A value is a scalar or a 1-D array of length B (one entry per parameter set); every 1-D value
    must have the same B, and then every leaf gets the batch axis. `K_GP` sets both robots and
    `K_GP_L` one; the per-robot name wins whatever the order. Static checks (names, types,
    finiteness, signs) raise `InputError` here, before anything is traced.
    """
    if base is not None and not isinstance(base, Params):
        raise InputError(f"base must be a Params from make_params, got {type(base).__name__}", "base")
    dtype = resolve_dtype(dtype) if dtype is not None else (base.dtype if base is not None else default_dtype())
    leaves = {}
    for n, spec in PARAMETERS.items():
        if base is not None and n in base.names:
            leaves[n] = base.leaves()[n]
        elif spec.per_robot:
            leaves[n] = np.full((2,), spec.default)
        else:
            leaves[n] = np.asarray(spec.default)

    batch = None if base is None else base.batch_shape
    shared, specific = [], []
    for name, value in values.items():
        base_name, robot = split_name(name)
        value = _as_value(name, value)
        if np.ndim(value) == 1:
            if batch not in (None, (), np.shape(value)):
                raise InputError(f"{name}: batch of {np.shape(value)[0]} does not match the batch of {batch[0]}", name)
            batch = np.shape(value)
        (shared if robot is None else specific).append((base_name, robot, value))
    batch = batch or ()

    def widen(x, per_robot):
        target = ((2,) if per_robot else ()) + batch
        if np.shape(x) == target:
            return x
        if len(batch) and np.ndim(x) == (1 if per_robot else 0):
            x = x[..., None]
        return (jnp if is_tracer(x) else np).broadcast_to(x, target)

    for n in PARAMETERS:
        leaves[n] = widen(leaves[n], PARAMETERS[n].per_robot)
    # Shared names first, then per-robot ones: `K_GP_L` beats `K_GP` in any order.
    for n, robot, value in shared + specific:
        value = value if np.ndim(value) == len(batch) else (jnp if is_tracer(value) else np).broadcast_to(value, batch)
        if PARAMETERS[n].per_robot:
            rows = [value if robot in (None, r) else leaves[n][i] for i, r in enumerate(ROBOTS)]
            leaves[n] = (jnp if any(map(is_tracer, rows)) else np).stack(rows)
        else:
            leaves[n] = value

    params = Params({n: jnp.asarray(v, dtype) for n, v in leaves.items()})
    validate(params)
    return params


def validate(params: Params) -> None:
    """Raise InputError on a non-finite value or a sign that makes the model meaningless.

    Traced leaves (inside grad or vmap) cannot be inspected and are skipped.
    """
    for n, spec in PARAMETERS.items():
        if n not in params.names:
            raise InputError(f"these Params have no {n} (made before it was declared?): rebuild them with make_params")
        leaf = getattr(params, n)
        if is_tracer(leaf):
            continue
        x = np.asarray(leaf)
        where = _where(n, x, spec.per_robot)
        bad = ~np.isfinite(x)
        if bad.any():
            raise InputError(f"{where(bad)} is {_first(x, bad)}: every parameter must be finite", n)
        if spec.check == "positive" and (x <= 0).any():
            raise InputError(f"{where(x <= 0)} is {_first(x, x <= 0)} {spec.unit}: it must be positive ({spec.doc})", n)
        if spec.check == "nonnegative" and (x < 0).any():
            raise InputError(
                f"{where(x < 0)} is {_first(x, x < 0)} {spec.unit}: it must not be negative ({spec.doc})", n
            )


def _first(x, mask):
    return f"{x[mask].ravel()[0]:g}"


def _where(name, x, per_robot):
    def describe(mask):
        idx = np.argwhere(mask)[0]
        label = f"{name}_{ROBOTS[idx[0]]}" if per_robot else name
        sample = idx[1:] if per_robot else idx
        return label + (f" (sample {int(sample[0])})" if len(sample) else "")

    return describe


def check_positive(name: str, value, what: str = "") -> float:
    """For the integration settings (dt, T): finite and > 0."""
    if isinstance(value, bool):
        raise InputError(f"{name} must be a number, got {value!r}", name)
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}", name) from None
    if not math.isfinite(value) or value <= 0:
        raise InputError(f"{name} is {value:g}{what}: it must be positive and finite", name)
    return value


def as_batched(params: Params) -> tuple[Params, bool]:
    """Give every leaf a batch axis of at least 1; also say whether one was added."""
    if params.batch_shape:
        return params, False
    return jax.tree_util.tree_map(lambda x: x[..., None], params), True
