"""What fixes a sweep's table: its configuration, its parameter sets (drawn, gridded or given) and
whether each row gets the two-step check. Validated in full before anything runs or is written."""

from __future__ import annotations

import dataclasses
import json
from typing import NamedTuple

import numpy as np

from coopjax import evaluation, objectives, step_check
from coopjax.config import Config
from coopjax.errors import InputError
from coopjax.params import PARAMETERS, default_dtype, make_params, split_name
from coopjax.simulation import memory_limit
from coopjax.sweeps.draws import Distribution, draw, grid_size, parse_distribution


def column_units(config: Config | None = None) -> dict[str, str]:
    """Every result column's unit: the metrics' own declarations, then the bookkeeping."""
    names = config.metrics if config is not None else tuple(objectives.METRICS)
    return {
        "sample": "index",
        **{n: objectives.METRICS[n].unit for n in names},
        **evaluation.BOOKKEEPING,
        **evaluation.STEP_ERROR,
    }


def result_columns() -> tuple[str, ...]:
    """Every column a sweep may add beside the parameters (any registered metric)."""
    return ("sample",) + tuple(objectives.METRICS) + tuple(evaluation.BOOKKEEPING) + tuple(evaluation.STEP_ERROR)


class SweepSpec(NamedTuple):
    """Everything that fixes a sweep's table. Stored beside the chunk files to guard --resume."""

    config: Config = Config()
    n: int = 0
    vary: tuple = ()  # ((name, text), ...)
    fixed: tuple = ()  # ((name, value), ...)
    seed: int = 0
    table: tuple = ()  # ((name, values), ...) from a table of parameter sets
    check_step: bool = False  # the two-step check on every row (coopjax.step_check)

    def to_json(self) -> str:
        d = self._asdict()
        d["config"] = json.loads(self.config.to_json())
        d["table"] = [(name, list(map(float, v))) for name, v in self.table]
        return json.dumps(d, sort_keys=True)

    def distributions(self) -> dict[str, Distribution]:
        return {name: parse_distribution(name, text) for name, text in self.vary}

    @property
    def columns(self) -> tuple[str, ...]:
        return evaluation.columns(self.config, self.check_step)


def make_spec(
    config: Config | str = "carry",
    *,
    n=None,
    vary=None,
    fixed=None,
    seed=0,
    table=None,
    check_step: bool = False,
    **settings,
) -> SweepSpec:
    """Validate and freeze a sweep description; raises InputError on any mistake.

    `config` (or a scenario name) with `settings` (any `Config` field) fixes how each sample runs;
    `vary` maps names to distributions, `fixed` names to values, `table` names to columns of values.
    `check_step` runs every row again at dt / 2 (`coopjax.step_check`): a `step_error` column, and
    status `step_artefact` where the answers move by more than a tolerance. It triples the cost.
    """
    config = Config.of(config, **settings)
    if config.dtype is None:  # the table must not depend on a global flag at resume time
        config = dataclasses.replace(config, dtype=np.dtype(default_dtype()).name)
    config.validate()
    for arg, value in (("vary", vary), ("fixed", fixed), ("table", table)):
        if value is not None and not isinstance(value, dict):
            raise InputError(f"{arg} must be a dict of names to values, got {type(value).__name__}", arg)
    vary, fixed = dict(vary or {}), dict(fixed or {})
    table = {k: np.asarray(v, np.float64) for k, v in (table or {}).items()}
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed is {seed!r}: a whole number, 0 or more", "seed")
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer))):
        raise InputError(f"n is {n!r}: a whole number of samples", "n")
    dists = {name: parse_distribution(name, text) for name, text in vary.items()}
    for name in list(fixed) + list(table):
        split_name(name)
    clash = (set(vary) & set(fixed)) | (set(table) & (set(vary) | set(fixed)))
    if clash:
        raise InputError(f"{sorted(clash)[0]} is given twice (varied, fixed or from a table): give it once", "vary")
    lengths = {len(v) for v in table.values()}
    if len(lengths) > 1:
        raise InputError(f"the table's columns have different lengths ({sorted(lengths)})", "table")
    implied = grid_size(dists)
    rows = len(next(iter(table.values()))) if table else None
    for candidate in (implied, rows):
        if candidate is not None and n is not None and n != candidate:
            raise InputError(f"n = {n} disagrees with the {candidate} samples implied by the grid or the table", "n")
    if implied is not None and rows is not None and implied != rows:
        raise InputError(f"the grid implies {implied} samples but the table has {rows} rows", "table")
    n = n if n is not None else implied if implied is not None else rows
    if n is None or n < 1:
        raise InputError("say how many samples: n (or grid axes, or a table)", "n")
    if not dists and not table:
        raise InputError(
            f"nothing varies, so all {n} samples would be the same run: vary a parameter "
            "(or give a table of sets), or simulate one run",
            "vary",
        )
    if not isinstance(check_step, bool):
        raise InputError(f"check_step is {check_step!r}: True or False", "check_step")
    missing = [m for m in step_check.METRICS if m not in config.metrics]
    if check_step and missing:
        raise InputError(
            f"the two-step check compares {', '.join(step_check.METRICS)}: add {missing[0]} to the metrics",
            "check_step",
        )
    columns = len(dists) + len(table) + len(evaluation.columns(config, check_step)) + 1
    if n * columns * 8 > memory_limit():
        raise InputError(
            f"n = {n}: a table of {n} rows x {columns} columns needs {n * columns * 8 / 2**30:.3g} GiB, "
            f"more than half of this machine's memory ({memory_limit() / 2**30:.3g} GiB); "
            f"at most {memory_limit() // (columns * 8):,} samples per sweep here",
            "n",
        )
    base = make_params(**fixed)  # every fixed value checked now, before any file is written
    spec = SweepSpec(
        config,
        int(n),
        tuple(vary.items()),
        tuple(fixed.items()),
        int(seed),
        tuple((k, tuple(v)) for k, v in table.items()),
        check_step,
    )
    sample_values(spec)  # every drawn value checked now too
    _check_dtype_range(spec, base)
    return spec


def _check_dtype_range(spec: SweepSpec, base) -> None:
    """A value that float32 cannot hold would become inf inside the run: refuse it now."""
    if spec.config.dtype != "float32":
        return
    big = float(np.finfo(np.float32).max)
    for name, value in list(spec.fixed) + [(n, np.max(np.abs(v))) for n, v in sample_values(spec).items()]:
        if abs(float(value)) > big:
            raise InputError(
                f"{name} = {float(value):g} does not fit in float32 (at most {big:.3g}): use float64 (--x64)", name
            )


def sample_values(spec: SweepSpec) -> dict[str, np.ndarray]:
    """Every sample's varied values (from the table, then the distributions), checked against each
    parameter's sign rule; an InputError names the first offending sample. Cheap: one hash a value."""
    sources = {name: f"vary {name}={text}" for name, text in spec.vary}
    sources.update({name: "the table" for name, _ in spec.table})
    values = {k: np.asarray(v, np.float64) for k, v in spec.table}
    values.update(draw(spec.distributions(), np.arange(spec.n), spec.seed))
    for name, v in values.items():
        rule = PARAMETERS[split_name(name)[0]].check
        bad = ~np.isfinite(v)
        if rule == "positive":
            bad |= v <= 0
        elif rule == "nonnegative":
            bad |= v < 0
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(
                f"{sources[name]} gives {name} = {v[i]:g} at sample {i}, but {name} must be "
                f"{'finite' if rule == 'finite' else rule}: choose a distribution that stays in range "
                "(e.g. loguniform)",
                "vary" if sources[name].startswith("vary") else "table",
            )
    return values
