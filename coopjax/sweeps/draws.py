"""A sweep's distributions and its random draws.

Sample i's draws depend only on (seed, parameter name, i), through a counter-based hash, so the chunk
size, the device count and the process count cannot change them.
"""

from __future__ import annotations

import math
import zlib
from typing import NamedTuple

import numpy as np

from coopjax.errors import InputError
from coopjax.params import PARAMETERS, split_name

KINDS = ("uniform", "loguniform", "normal", "choice", "grid")


class Distribution(NamedTuple):
    kind: str
    values: tuple[float, ...]

    @property
    def size(self) -> int | None:
        return int(self.values[2]) if self.kind == "grid" else None


def parse_distribution(name: str, text: str) -> Distribution:
    """`uniform:a:b`, `loguniform:a:b`, `normal:mean:sd`, `choice:v1,v2,...`, `grid:a:b:k`."""
    base, _ = split_name(name)
    if not isinstance(text, str):
        raise InputError(f"vary {name}: expected a distribution such as 'uniform:a:b', got {text!r}", "vary")
    where = f"vary {name}={text}"
    kind, _, rest = text.partition(":")
    if kind not in KINDS:
        raise InputError(f"{where}: unknown distribution {kind!r}; use one of {', '.join(KINDS)}", "vary")
    parts = rest.split(",") if kind == "choice" else rest.split(":")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise InputError(f"{where}: {rest!r} are not all numbers", "vary") from None
    expected = {"uniform": 2, "loguniform": 2, "normal": 2, "grid": 3}.get(kind)
    usage = {
        "uniform": "uniform:a:b",
        "loguniform": "loguniform:a:b",
        "normal": "normal:mean:sd",
        "grid": "grid:a:b:k",
        "choice": "choice:v1,v2,...",
    }[kind]
    if (expected and len(values) != expected) or not values or not all(map(math.isfinite, values)):
        raise InputError(f"{where}: expected {usage} with finite numbers", "vary")
    if kind in ("uniform", "loguniform", "grid") and values[1] < values[0]:
        raise InputError(f"{where}: the upper bound is below the lower bound", "vary")
    if kind == "loguniform" and values[0] <= 0:
        raise InputError(f"{where}: loguniform needs a positive lower bound", "vary")
    if kind == "normal" and values[1] < 0:
        raise InputError(f"{where}: the standard deviation must not be negative", "vary")
    if kind == "grid" and (values[2] < 1 or values[2] != int(values[2])):
        raise InputError(f"{where}: the grid size k must be a whole number >= 1", "vary")
    check = PARAMETERS[base].check
    low = {"uniform": values[0], "loguniform": values[0], "grid": values[0], "choice": min(values)}.get(kind)
    if check == "positive" and low is not None and low <= 0:
        raise InputError(f"{where}: {base} must be positive, but the range reaches {low:g}", "vary")
    if check == "nonnegative" and low is not None and low < 0:
        raise InputError(f"{where}: {base} must not be negative, but the range reaches {low:g}", "vary")
    return Distribution(kind, values)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    x = (x + np.uint64(0x9E3779B97F4A7C15)).astype(np.uint64)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _uniform(seed: int, stream: str, index: np.ndarray) -> np.ndarray:
    """U[0, 1) with 53 bits, a pure function of (seed, stream, index). A counter-based hash rather
    than numpy's generators: sample i's draw must not depend on how many samples came before it."""
    with np.errstate(over="ignore"):
        key = _splitmix64(np.uint64(seed & 0xFFFFFFFFFFFFFFFF) ^ np.uint64(zlib.crc32(stream.encode())))
        bits = _splitmix64(key ^ _splitmix64(index.astype(np.uint64)))
    return (bits >> np.uint64(11)).astype(np.float64) * 2.0**-53


def grid_size(dists: dict[str, Distribution]) -> int | None:
    sizes = [d.size for d in dists.values() if d.kind == "grid"]
    return int(np.prod(sizes)) if sizes else None


def draw(dists: dict[str, Distribution], index: np.ndarray, seed: int) -> dict[str, np.ndarray]:
    """The varied parameters' values for the given sample indices."""
    out = {}
    grid_axes = [(n, d) for n, d in dists.items() if d.kind == "grid"]
    radix = index.copy()
    for name, d in reversed(grid_axes):  # first grid axis varies slowest
        k = d.size
        out[name] = np.linspace(d.values[0], d.values[1], k)[radix % k]
        radix = radix // k
    for name, d in dists.items():
        if d.kind == "grid":
            continue
        u = _uniform(seed, name, index)
        if d.kind == "uniform":
            out[name] = d.values[0] + (d.values[1] - d.values[0]) * u
        elif d.kind == "loguniform":
            lo, hi = np.log(d.values[0]), np.log(d.values[1])
            out[name] = np.exp(lo + (hi - lo) * u)
        elif d.kind == "normal":  # Box-Muller from a second independent stream
            u2 = _uniform(seed, name + "#2", index)
            out[name] = d.values[0] + d.values[1] * np.sqrt(-2 * np.log1p(-u)) * np.cos(2 * np.pi * u2)
        else:
            out[name] = np.asarray(d.values)[np.minimum((u * len(d.values)).astype(np.int64), len(d.values) - 1)]
    return {name: out[name] for name in dists}
