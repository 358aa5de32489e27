"""Monte-Carlo and grid sweeps: many parameter sets, chunked, sharded over devices, resumable.

Determinism is by construction:
- Sample i's random draws depend only on (seed, parameter name, i), through a counter-based hash.
  So the chunk size, device count and process count cannot change them.
- Every device always runs the same per-device block of `block` samples (padded if need be), and
  `block` depends only on the sweep size (or is fixed by the caller). XLA therefore compiles the
  same per-device program whatever the chunking, and rounding cannot differ between layouts. The closed loop can amplify
  rounding (docs/model.md, "Step size"), so that matters.

Across machines, processes started with `jax.distributed` take chunks in turn. After each round the
results are gathered with `process_allgather`, and process 0 writes them.
"""

from __future__ import annotations

import dataclasses
import io as io_module
import json
import math
import os
import sys
import zlib
from typing import NamedTuple

import jax
import numpy as np
import pandas as pd
from jax.experimental import multihost_utils
from tqdm.auto import tqdm

from coopjax import devices, objectives, stability, step_check
from coopjax.config import Config
from coopjax.errors import InputError
from coopjax.io import atomic_path
from coopjax.params import PARAMETERS, default_dtype, make_params, split_name
from coopjax.simulation import memory_limit, metrics_of

KINDS = ("uniform", "loguniform", "normal", "choice", "grid")
# Why a sample is not trusted, most basic first. `finite` in the table is 1 only for "ok".
STATUSES = ("ok", "diverged", "unstable_loop", "step_beyond_limit", "step_artefact")
BOOKKEEPING = {
    "finite": "1 if trusted (status ok), else 0", "t_diverged": "s (NaN if it did not)",
    "dt_limit": "s, the largest stable step of the linearised loop", "status": "|".join(STATUSES),
}
STEP_ERROR = {"step_error": "tolerances: the two-step check's largest disagreement between dt and dt/2 "
                            "(above 1: step_artefact)"}
CHUNK_FORMAT = 3  # bumped when a chunk file's layout changes, so --resume never mixes formats


def columns_per_sample(config: Config, check_step: bool = False) -> tuple[str, ...]:
    """The result columns of a sweep table: the configured metrics, then the bookkeeping (and the
    two-step check's column if asked for)."""
    return tuple(config.metrics) + tuple(BOOKKEEPING) + (tuple(STEP_ERROR) if check_step else ())


def column_units(config: Config | None = None) -> dict[str, str]:
    """Every result column's unit: the metrics' own declarations, then the bookkeeping."""
    names = config.metrics if config is not None else tuple(objectives.METRICS)
    return {"sample": "index", **{n: objectives.METRICS[n].unit for n in names}, **BOOKKEEPING, **STEP_ERROR}


def result_columns() -> tuple[str, ...]:
    """Every column a sweep may add beside the parameters (any registered metric)."""
    return ("sample",) + tuple(objectives.METRICS) + tuple(BOOKKEEPING) + tuple(STEP_ERROR)


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
    usage = {"uniform": "uniform:a:b", "loguniform": "loguniform:a:b", "normal": "normal:mean:sd",
             "grid": "grid:a:b:k", "choice": "choice:v1,v2,..."}[kind]
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
        return columns_per_sample(self.config, self.check_step)


def make_spec(config: Config | str = "carry", n=None, vary=None, fixed=None, seed=0, table=None,
              check_step: bool = False, **settings) -> SweepSpec:
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
        raise InputError(f"nothing varies, so all {n} samples would be the same run: vary a parameter "
                         "(or give a table of sets), or simulate one run", "vary")
    if not isinstance(check_step, bool):
        raise InputError(f"check_step is {check_step!r}: True or False", "check_step")
    missing = [m for m in step_check.METRICS if m not in config.metrics]
    if check_step and missing:
        raise InputError(f"the two-step check compares {', '.join(step_check.METRICS)}: add {missing[0]} to the metrics",
                         "check_step")
    columns = len(dists) + len(table) + len(columns_per_sample(config, check_step)) + 1
    if n * columns * 8 > memory_limit():
        raise InputError(f"n = {n}: a table of {n} rows x {columns} columns needs {n * columns * 8 / 2**30:.3g} GiB, "
                         f"more than half of this machine's memory ({memory_limit() / 2**30:.3g} GiB); "
                         f"at most {memory_limit() // (columns * 8):,} samples per sweep here", "n")
    base = make_params(**fixed)  # every fixed value checked now, before any file is written
    spec = SweepSpec(config, int(n), tuple(vary.items()), tuple(fixed.items()), int(seed),
                     tuple((k, tuple(v)) for k, v in table.items()), check_step)
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
            raise InputError(f"{name} = {float(value):g} does not fit in float32 (at most {big:.3g}): "
                             "use float64 (--x64)", name)


def _significant(x: np.ndarray, digits: int) -> np.ndarray:
    """x to `digits` significant digits. The step limit is an eigenvalue estimate: the two robots'
    nearly repeated poles make it move by ~1e-7 with rounding (sqrt of machine epsilon), for example
    between a one- and a two-process run, so more digits would be noise."""
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = 10.0 ** (np.floor(np.log10(np.abs(x))) - digits + 1)
        return np.where(np.isfinite(x) & (x != 0), np.round(x / scale) * scale, x)


def block_size(n: int) -> int:
    """Samples per device per call: a power of two up to `devices.BLOCK`, fixed by the sweep size
    alone (so the compiled per-device program does not depend on the chunking)."""
    return int(min(devices.BLOCK, 2 ** math.ceil(math.log2(max(n, 8)))))


def evaluate(spec: SweepSpec, values: dict[str, np.ndarray], block: int | None = None) -> np.ndarray:
    """The result columns (`spec.columns`, as float64) of the given parameter sets: the metrics, the
    divergence flags, the step check of `simulate` per sample, and the status. `block`: samples per
    device per call (None: `block_size` of the sweep)."""
    block = block or block_size(spec.n)
    config = spec.config
    params = config.cast(make_params(**dict(spec.fixed), **values))
    limit, growth = stability.stable_dt(params, config)
    limit = _significant(limit, 6)
    metrics = devices.run(metrics_of(config), params, fixed_block=True, block=block)
    m = np.stack([np.asarray(x, np.float64) for x in jax.device_get(list(metrics))], axis=1)
    names = metrics._fields
    finite = m[:, names.index("finite")] > 0.5
    # The cause first: an unstable loop, then a step beyond the limit, then a blow-up of unknown
    # cause (`t_diverged` says when any of them blew up).
    status = np.select([growth > 0, config.dt > limit, ~finite], [2, 3, 1], 0)
    extra = []
    if spec.check_step:
        fine = devices.run(metrics_of(step_check.halved(config)), params, fixed_block=True, block=block)
        error = step_check.step_error({n: m[:, names.index(n)] for n in step_check.METRICS},
                                      {n: np.asarray(getattr(fine, n), np.float64) for n in step_check.METRICS})
        status = np.where((status == 0) & step_check.artefacts(error), STATUSES.index("step_artefact"), status)
        extra = [error]
    m[:, names.index("finite")] = status == 0
    return np.column_stack([m, limit, status] + extra)


def run(spec: SweepSpec, chunk: int = 16384, parts: str | None = None, resume: bool = False, progress: bool = False,
        block: int | None = None):
    """Run a sweep and return its table as columns (sample, varied parameters, results).

    `block` fixes the samples per device per call (None: `block_size` of the sweep), so that sweeps
    of different sizes share one compiled program.

    With `parts`, each finished chunk is saved there atomically, and `resume=True` skips those
    already saved. Under `jax.distributed`, chunks are shared among processes and process 0 returns
    the whole table (others return it too, except after a resume, when they return None).
    """
    if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
        raise InputError(f"chunk is {chunk!r}: it must be a whole number, at least 1", "chunk")
    n_chunks = math.ceil(spec.n / chunk)
    n_proc, pid = jax.process_count(), jax.process_index()
    values = sample_values(spec)  # drawn and checked once, before anything is written
    width = len(spec.columns)
    done = np.zeros(n_chunks, bool)
    if parts is not None:
        done = prepare_parts(parts, spec, chunk, resume, n_chunks) if pid == 0 else done
        if n_proc > 1:
            done = np.asarray(multihost_utils.broadcast_one_to_all(done))
    results: dict[int, np.ndarray] = {}
    bar = tqdm(total=spec.n, unit="sample", desc="sweep", disable=not (progress and pid == 0), dynamic_ncols=True,
               mininterval=0.5, file=sys.stderr)
    for k in np.flatnonzero(done) if pid == 0 else ():
        saved = _load_part(parts, int(k), min((k + 1) * chunk, spec.n) - k * chunk, width)
        if saved is None:
            done[k] = False
            continue
        results[int(k)] = saved
        bar.update(len(saved))

    todo = [int(k) for k in np.flatnonzero(~done)]
    for r in range(0, len(todo), n_proc):
        round_chunks = todo[r:r + n_proc]
        mine = round_chunks[pid] if pid < len(round_chunks) else None
        local = np.full((chunk, width), np.nan)
        if mine is not None:
            rows = slice(mine * chunk, min((mine + 1) * chunk, spec.n))
            local[: rows.stop - rows.start] = evaluate(spec, {k: v[rows] for k, v in values.items()}, block)
        if n_proc > 1:
            with jax.enable_x64(True):  # the table is float64 whatever the runs are
                gathered = np.asarray(multihost_utils.process_allgather(local, tiled=False), np.float64)
        else:
            gathered = local[None]
        for p, k in enumerate(round_chunks):
            size = min((k + 1) * chunk, spec.n) - k * chunk
            results[k] = gathered[p][:size]
            if parts is not None and pid == 0:
                save_array(part_path(parts, k), results[k])
            bar.update(size)
    bar.close()

    if len(results) < n_chunks:  # a non-zero process on resume: only process 0 holds saved chunks
        return None
    metrics = np.concatenate([results[k] for k in range(n_chunks)])
    columns = {"sample": np.arange(spec.n), **values}
    for j, name in enumerate(spec.columns):
        columns[name] = metrics[:, j]
    columns["finite"] = columns["finite"] > 0.5
    columns["status"] = np.asarray(STATUSES)[columns["status"].astype(int)]
    return columns


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
                "(e.g. loguniform)", "vary" if sources[name].startswith("vary") else "table")
    return values


def _load_part(parts: str, k: int, rows: int, width: int):
    """A saved chunk, or None (with a note) if it is unreadable or the wrong shape: it is recomputed."""
    path = part_path(parts, k)
    try:
        data = np.load(path)
        if data.shape == (rows, width):
            return data
    except (OSError, ValueError, EOFError):
        pass
    print(f"coopjax: note: {path} is unreadable or incomplete; it is computed again", file=sys.stderr)
    return None


def save_array(path: str, array: np.ndarray) -> None:
    """One .npy file, atomically. Through a buffer: numpy's own file writer reports a short write on
    a full disk without its errno, and Python's says ENOSPC."""
    buffer = io_module.BytesIO()
    np.save(buffer, array)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(buffer.getbuffer())


def part_path(parts: str, k: int) -> str:
    return os.path.join(parts, f"chunk-{k:06d}.npy")


def finished_parts(parts: str) -> int:
    """How many finished chunks a parts folder holds."""
    try:
        return sum(1 for n in os.listdir(parts) if n.startswith("chunk-") and n.endswith(".npy"))
    except OSError:
        return 0


def prepare_parts(parts: str, spec: SweepSpec, chunk: int, resume: bool, n_chunks: int) -> np.ndarray:
    """The parts folder of a sweep: created with its manifest, or checked against it on resume.
    Returns which chunks are already finished."""
    manifest = os.path.join(parts, "manifest.json")
    identity = json.dumps({"spec": json.loads(spec.to_json()), "chunk": chunk, "columns": list(spec.columns),
                           "format": CHUNK_FORMAT}, sort_keys=True)
    if os.path.exists(manifest):
        if not resume:
            raise InputError(f"{parts} holds an unfinished sweep: resume it (--resume), or delete it", "resume")
        try:
            if not os.access(manifest, os.R_OK):
                raise PermissionError(13, "permission denied")
            with open(manifest) as f:
                saved = f.read()
        except OSError as error:
            raise InputError(f"{manifest} is not readable ({error.strerror}): fix its permissions or delete {parts}",
                             "resume") from None
        if not os.access(parts, os.W_OK):
            raise InputError(f"{parts} is not writable: fix its permissions or delete it", "resume")
        if saved != identity:
            raise InputError(f"{parts} belongs to a different sweep (other options or chunk size): "
                             "use the same options, or delete it", "resume")
        return np.array([os.path.exists(part_path(parts, k)) for k in range(n_chunks)])
    if os.path.exists(parts) and not os.path.isdir(parts):
        raise InputError(f"{parts} exists and is not a folder: remove it", "out")
    os.makedirs(parts, exist_ok=True)
    with atomic_path(manifest) as tmp:
        with open(tmp, "w") as f:
            f.write(identity)
    return np.zeros(n_chunks, bool)


def sweep(config: Config | str = "carry", n=None, vary=None, fixed=None, seed=0, table=None, chunk=16384,
          progress=False, **settings):
    """Notebook entry point: the sweep as a pandas DataFrame.

    Example: `sweep("carry", 1000, vary={"M_b": "loguniform:0.5:5", "K_GP": "uniform:0.2:1"})`.
    """
    spec = make_spec(config, n, vary, fixed, seed, table, **settings)
    return pd.DataFrame(run(spec, chunk=chunk, progress=progress))
