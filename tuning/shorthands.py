"""The default problem in short: the flags that change it without a problem file.

Every `[training]` setting of `Problem` that declares a flag is its own flag (`Problem.settings`);
the rest are aliases, each a flag that sets one field of the problem from a short text:

    --params gains|per-robot|all|NAME,...    names
    --masses loguniform:LOW:HIGH             uncertain (the body mass, kg)
    --w-lag W                                minimise (the lag term's weight, N per m of RMS lag)
    --set NAME=VALUE                         fixed

`problem_from` builds the problem from what was given; a mistake is one `InputError` naming its flag.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, NamedTuple

from coopjax.errors import InputError
from coopjax.params import split_name
from tuning.design import uncertain
from tuning.problem import Objective, Problem, expand_params


class Alias(NamedTuple):
    """A flag that sets `field` of the default problem from a short text."""

    flag: str
    field: str
    metavar: str
    help: str
    value: Callable  # (text or list of texts, the default problem) -> the field's value
    kind: type = str
    repeat: bool = False  # the flag may be given several times (a list of texts)


def _masses(text: str, p0: Problem):
    if text.split(":")[0] not in ("uniform", "loguniform"):
        raise InputError(f"--masses expects loguniform:LOW:HIGH or uniform:LOW:HIGH, got {text!r}", "uncertain")
    try:
        return (uncertain("M_b", text, "--masses"),)
    except InputError as error:
        raise InputError(f"{str(error).replace('M_b = ', '')} (need 0 < LOW < HIGH, kg)", "uncertain") from None


def _w_lag(weight: float, p0: Problem):
    if not (math.isfinite(weight) and weight >= 0):
        raise InputError(f"--w-lag is {weight:g}: it must be finite and not negative", "minimise")
    peak, lag = p0.minimise
    # A weight of 0 drops the term (the objective's weights are positive).
    return (peak,) + ((Objective(lag.metric, lag.over, weight),) if weight else ())


def _fixed(items: list, p0: Problem):
    out: dict[str, float] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not sep or not name or not math.isfinite(value):
            raise InputError(f"--set {item!r}: expected NAME=VALUE with a finite number", "fixed")
        split_name(name)  # an unknown name is refused with the parameters' own message
        if name in out:
            raise InputError(f"--set: {name} given more than once", "fixed")
        if split_name(name)[0] == "M_b":
            raise InputError("--set M_b: the body mass is what the tuner varies; give its range with --masses", "fixed")
        out[name] = value
    return tuple(out.items())


ALIASES = (
    Alias(
        "--params",
        "names",
        "NAMES",
        Problem.__dataclass_fields__["names"].metadata["help"],
        lambda t, p0: expand_params(t),
    ),
    Alias("--masses", "uncertain", "KIND:LOW:HIGH", "the body-mass range, kg (default loguniform:0.5:5)", _masses),
    Alias(
        "--w-lag",
        "minimise",
        "W",
        f"N of worst peak force per m of worst RMS lag (default {Problem().minimise[1].weight:g}, i.e. 1.5 N per mm)",
        _w_lag,
        float,
    ),
    Alias("--set", "fixed", "NAME=VALUE", "fix another parameter (repeatable)", _fixed, str, True),
)


def flags() -> list[tuple[str, str, dataclasses.Field | Alias]]:
    """(flag, dest, declaration) of every flag of the default problem: the settings, then the aliases."""
    out = [(f.metadata["flag"], f.name, f) for f in Problem.settings("training") if f.metadata["flag"]]
    return out + [(a.flag, a.field, a) for a in ALIASES]


def problem_from(given: dict) -> Problem:
    """The default problem with the given flags' values (dest -> value; None: not given), validated."""
    p0, fields = Problem(), {}
    for flag, dest, declared in flags():
        value = given.get(dest)
        if value is not None:
            fields[dest] = declared.value(value, p0) if isinstance(declared, Alias) else value
    problem = Problem(**fields)
    tuned = problem.names
    clash = [n for n, _ in problem.fixed if any(_overlaps(n, t) for t in tuned)]
    if clash:
        raise InputError(f"{clash[0]} is both tuned (--params) and fixed (--set): choose one", "fixed")
    return problem.validate()


def _overlaps(a, b) -> bool:
    """The same parameter, for a robot both names cover."""
    (base_a, robot_a), (base_b, robot_b) = split_name(a), split_name(b)
    return base_a == base_b and (robot_a is None or robot_b is None or robot_a == robot_b)
