"""Where the uncertain parameters are drawn: training, validation and held-out designs, disjoint.

An uncertain parameter has a box, `uniform:LOW:HIGH` or `loguniform:LOW:HIGH`. Each design maps
points of the unit cube [0, 1]^p into the box (in log space for a loguniform one), widened by a
share of its width for training and selection, so that the extreme draws lie just outside what is
judged:

- **One uncertain parameter** (the body mass by default): training takes one draw per
  equal-probability stratum of the range widened by `margin`, afresh each step (or the strata's
  midpoints), or a grid with its ends (screen-SLP); selection a 256-point grid of the range widened by
  `margin / 2`; judging a grid of the range itself, ends included (the heaviest mass is the hardest).
- **Several**: each design is the box's 2^p corners (a worst case often sits at one) and points
  inside it: a Latin hypercube drawn afresh each training step (or a fixed scrambled Sobol set), and
  scrambled Sobol sets of other seeds for selection and judging. Training and selection take the
  corners of their widened boxes, judging those of the box itself.

Widening a loguniform box multiplies its ends by (1 + margin)^-1 and (1 + margin); a uniform box
grows by the same share of its half-width on each side (a positive one no lower than LOW / (1 + margin)).
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import numpy as np
from scipy.stats import qmc

from coopjax.config import is_number
from coopjax.errors import InputError
from coopjax.params import PARAMETERS, split_name
from coopjax.sweeps.draws import parse_distribution

KINDS = ("uniform", "loguniform")
MAX_UNCERTAIN = 6  # 2^6 = 64 corners per design
# Selection draws. A worst case can sit in a band of the box a few grams wide, and 48 draws chose
# answers whose worst on 1024 draws was 1.3 x the best known's (`gains_only`, `asymmetric_robots`);
# 256 chose answers within 1.15 x, for a few seconds more per selection (docs/tuning.md).
VALIDATION_COUNT = 256
TRAIN_SOBOL_SEED, VALIDATION_SEED, HELD_OUT_SEED, DENSE_SEED = 101, 202, 303, 404
# A fixed training design over a box of several parameters: the corners and this many Sobol points per
# `n_draws`. Between 4 corners and 8 points, screen-SLP's answer to `stiffness_and_mass` broke between
# the draws (a peak of 45 N against 40 N); with 16 it held (docs/tuning.md).
FIXED_SOBOL = 2
# Draws of a dense design (besides the corners with several uncertain parameters). A worst case over the
# body mass can sit in a band a few grams wide (a peak of 60.3 N at 3.685 kg, 33.1 N at 3.680 kg, for
# `gains_only`'s answer that read 43.1 N on 64 masses), so the benchmarks judge on 1024.
DENSE_COUNT = 1024


def shortest(x) -> str:
    """A number as the shortest text that reads back to the same float (`5`, `0.0123456789`)."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


class Uncertain(NamedTuple):
    """One uncertain parameter and its box."""

    name: str
    kind: str  # uniform | loguniform
    low: float
    high: float

    @property
    def text(self) -> str:
        """`kind:LOW:HIGH`, read back to the same box (shortest round-trip numbers)."""
        return f"{self.kind}:{shortest(self.low)}:{shortest(self.high)}"

    def widened(self, share: float) -> "Uncertain":
        if self.kind == "loguniform":
            return self._replace(low=self.low / (1.0 + share), high=self.high * (1.0 + share))
        half = 0.5 * (self.high - self.low)
        low = self.low - share * half
        if self.low > 0:  # a positive box stays positive
            low = max(low, self.low / (1.0 + share))
        return self._replace(low=low, high=self.high + share * half)

    def at(self, u: np.ndarray) -> np.ndarray:
        """The values at unit-interval points u."""
        if self.kind == "loguniform":
            return np.exp(np.log(self.low) + (np.log(self.high) - np.log(self.low)) * u)
        return self.low + (self.high - self.low) * u


def uncertain(name: str, text: str, where: str = "uncertain") -> Uncertain:
    """An uncertain parameter from `uniform:LOW:HIGH` or `loguniform:LOW:HIGH` (the sweep's syntax)."""
    split_name(name)  # an unknown name is refused with a suggestion
    try:
        dist = parse_distribution(name, text)
    except InputError as error:
        raise InputError(f"{where}: {error}", name) from None
    if dist.kind not in KINDS:
        raise InputError(
            f"{where}: {name} = {text!r}: an uncertain parameter needs a box, uniform:LOW:HIGH or loguniform:LOW:HIGH",
            name,
        )
    low, high = dist.values
    if not low < high:
        raise InputError(f"{where}: {name} = {text!r}: LOW must be below HIGH", name)
    return Uncertain(name, dist.kind, float(low), float(high))


def check(items: tuple[Uncertain, ...]) -> None:
    if not items:
        raise InputError("uncertain: name at least one uncertain parameter (the body mass M_b by default)", "uncertain")
    if len(items) > MAX_UNCERTAIN:
        raise InputError(
            f"uncertain: {len(items)} parameters; at most {MAX_UNCERTAIN} (each design includes all 2^p corners)",
            "uncertain",
        )
    for u in items:
        if (
            u.kind not in KINDS
            or not (is_number(u.low) and is_number(u.high))
            or not (np.isfinite([u.low, u.high]).all())
        ):
            raise InputError(
                f"uncertain: {u.name}: {u.kind!r} from {u.low!r} to {u.high!r}: a box is uniform:LOW:HIGH or "
                "loguniform:LOW:HIGH with finite numbers",
                u.name,
            )
        if not u.low < u.high or (u.kind == "loguniform" and u.low <= 0):
            raise InputError(f"uncertain: {u.name} = {u.text!r}: need LOW < HIGH (and 0 < LOW for loguniform)", u.name)
    names = [u.name for u in items]
    if len(set(names)) != len(names):
        raise InputError(f"uncertain: {', '.join(names)} names a parameter twice", "uncertain")


def _corners(p: int) -> np.ndarray:
    return np.array(list(itertools.product((0.0, 1.0), repeat=p)))


def _map(items, u: np.ndarray) -> np.ndarray:
    return np.stack([item.at(u[:, i]) for i, item in enumerate(items)], axis=1)


def _sobol(p: int, count: int, seed: int) -> np.ndarray:
    if count == 0:
        return np.zeros((0, p))
    # A power of two keeps Sobol's balance; the first `count` of it are taken.
    return qmc.Sobol(d=p, scramble=True, seed=seed).random(2 ** math.ceil(math.log2(count)))[:count]


def training(items, count: int, margin: float, seed: int = 0, step: int = 0, jitter: bool = True) -> np.ndarray:
    """(M, p) training draws of one step: `count` strata (1-D) or corners + a Latin hypercube of `count`."""
    box = [u.widened(margin) for u in items]
    p = len(items)
    if p == 1:
        if not jitter:
            return _map(box, (np.arange(count) + 0.5)[:, None] / count)
        u = (np.arange(count) + np.random.default_rng([seed, step]).random(count)) / count
        return _map(box, u[:, None])
    if not jitter:
        return fixed_training(items, count, margin)
    inner = qmc.LatinHypercube(d=p, seed=np.random.default_rng([seed, step])).random(count)
    return _map(box, np.concatenate([_corners(p), inner]))


def fixed_training(items, count: int, margin: float) -> np.ndarray:
    """(M, p) draws for a tuner that keeps them for the whole run: a grid with its ends (1-D), or the
    widened box's corners and `FIXED_SOBOL x count` Sobol points."""
    box = [u.widened(margin) for u in items]
    p = len(items)
    if p == 1:
        return _map(box, np.linspace(0.0, 1.0, count)[:, None])
    return _map(box, np.concatenate([_corners(p), _sobol(p, FIXED_SOBOL * count, TRAIN_SOBOL_SEED)]))


def validation(items, margin: float, count: int = VALIDATION_COUNT) -> np.ndarray:
    """(M, p) selection draws, within the box widened by margin / 2 (none of them training's)."""
    box = [u.widened(0.5 * margin) for u in items]
    p = len(items)
    if p == 1:
        return _map(box, np.linspace(0.0, 1.0, count)[:, None])
    return _map(box, np.concatenate([_corners(p), _sobol(p, max(0, count - 2**p), VALIDATION_SEED)]))


def held_out(items, count: int) -> np.ndarray:
    """(M, p) judging draws: a grid over the box with its ends (1-D, `count` points), or the box's
    corners and `count` Sobol points inside it."""
    p = len(items)
    if p == 1:
        return _map(items, np.linspace(0.0, 1.0, count)[:, None])
    return _map(items, np.concatenate([_corners(p), _sobol(p, count, HELD_OUT_SEED)]))


def dense(items, count: int = DENSE_COUNT, seed: int = DENSE_SEED) -> np.ndarray:
    """(M, p) a dense design over the box itself, for judging a result beyond its held-out draws: a
    grid of `count` points with its ends (one parameter; with an odd count it shares only the ends
    and the middle with a 12-point held-out grid), or the corners and `count` Sobol points of its own
    seed (several)."""
    p = len(items)
    if p == 1:
        return _map(items, np.linspace(0.0, 1.0, count)[:, None])
    return _map(items, np.concatenate([_corners(p), _sobol(p, count, seed)]))


def describe(items, draws: np.ndarray) -> str:
    """'12 masses from 0.5 to 5 kg' or '28 draws of M_b, K_g (16 corners)'."""
    if len(items) == 1:
        u = items[0]
        unit = PARAMETERS[split_name(u.name)[0]].unit
        return f"{len(draws)} draws of {u.name} from {draws[:, 0].min():.3g} to {draws[:, 0].max():.3g} {unit}"
    return f"{len(draws)} draws of {', '.join(u.name for u in items)} ({2 ** len(items)} corners of the box)"
