"""Monte-Carlo and grid sweeps: many parameter sets, chunked, sharded over devices, resumable.

Determinism is by construction:
- Sample i's random draws depend only on (seed, parameter name, i), through a counter-based hash.
  So the chunk size, device count and process count cannot change them.
- Every device always runs the same per-device block of `block` samples (padded if need be), and
  `block` depends only on the sweep size. XLA therefore compiles the same per-device program
  whatever the chunking, and rounding cannot differ between layouts. The closed loop can amplify
  rounding (docs/model.md, "Step size"), so that matters.

Across machines, processes started with `jax.distributed` take chunks in turn. After each round the
results are gathered with `process_allgather`, and process 0 writes them.
"""

from __future__ import annotations

import functools
import json
import math
import os
import zlib
from typing import NamedTuple

import numpy as np

from coopjax import objectives
from coopjax.io import atomic_path
from coopjax.params import PARAMETERS, split_name
from coopjax.progress import Progress

KINDS = ("uniform", "loguniform", "normal", "choice", "grid")
METRICS = objectives.METRIC_NAMES
# Why a sample is not trusted, most basic first. `finite` in the table is 1 only for "ok".
STATUSES = ("ok", "diverged", "unstable_loop", "step_beyond_limit")
COLUMNS_PER_SAMPLE = METRICS + ("dt_limit", "status")
COLUMN_UNITS = {
    "sample": "index", "min_grip": "N", "peak_grip": "N", "slip": "N^2", "crush": "N^2", "rms_lag": "m",
    "impact": "N^2", "finite": "1 if trusted (status ok), else 0", "t_diverged": "s (NaN if it did not)",
    "dt_limit": "s, the largest stable step of the linearised loop", "status": "|".join(STATUSES),
}
CHUNK_FORMAT = 2  # bumped when a chunk file's columns change, so --resume never mixes formats


class Distribution(NamedTuple):
    kind: str
    values: tuple[float, ...]

    @property
    def size(self) -> int | None:
        return int(self.values[2]) if self.kind == "grid" else None


def parse_distribution(name: str, text: str) -> Distribution:
    """`uniform:a:b`, `loguniform:a:b`, `normal:mean:sd`, `choice:v1,v2,...`, `grid:a:b:k`."""
    base, _ = split_name(name)
    kind, _, rest = text.partition(":")
    if kind not in KINDS:
        raise ValueError(f"--vary {name}={text}: unknown distribution {kind!r}; use one of {', '.join(KINDS)}")
    parts = rest.split(",") if kind == "choice" else rest.split(":")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise ValueError(f"--vary {name}={text}: {rest!r} are not all numbers") from None
    expected = {"uniform": 2, "loguniform": 2, "normal": 2, "grid": 3}.get(kind)
    usage = {"uniform": "uniform:a:b", "loguniform": "loguniform:a:b", "normal": "normal:mean:sd",
             "grid": "grid:a:b:k", "choice": "choice:v1,v2,..."}[kind]
    if (expected and len(values) != expected) or not values or not all(map(math.isfinite, values)):
        raise ValueError(f"--vary {name}={text}: expected {usage} with finite numbers")
    if kind in ("uniform", "loguniform", "grid") and values[1] < values[0]:
        raise ValueError(f"--vary {name}={text}: the upper bound is below the lower bound")
    if kind == "loguniform" and values[0] <= 0:
        raise ValueError(f"--vary {name}={text}: loguniform needs a positive lower bound")
    if kind == "normal" and values[1] < 0:
        raise ValueError(f"--vary {name}={text}: the standard deviation must not be negative")
    if kind == "grid" and (values[2] < 1 or values[2] != int(values[2])):
        raise ValueError(f"--vary {name}={text}: the grid size k must be a whole number >= 1")
    check = PARAMETERS[base].check
    low = {"uniform": values[0], "loguniform": values[0], "grid": values[0], "choice": min(values)}.get(kind)
    if check == "positive" and low is not None and low <= 0:
        raise ValueError(f"--vary {name}={text}: {base} must be positive, but the range reaches {low:g}")
    if check == "nonnegative" and low is not None and low < 0:
        raise ValueError(f"--vary {name}={text}: {base} must not be negative, but the range reaches {low:g}")
    return Distribution(kind, values)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    x = (x + np.uint64(0x9E3779B97F4A7C15)).astype(np.uint64)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _uniform(seed: int, stream: str, index: np.ndarray) -> np.ndarray:
    """U[0, 1) with 53 bits, a pure function of (seed, stream, index)."""
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

    scenario: str = "carry"
    n: int = 0
    vary: tuple = ()  # ((name, text), ...)
    fixed: tuple = ()  # ((name, value), ...)
    seed: int = 0
    switch: str = "hard"
    dt: float = 1e-3
    T: float | None = None
    x64: bool = False
    table: tuple = ()  # ((name, values), ...) from --from
    integrator: str | None = None  # None: filippov for the hard switch, rk4 otherwise

    def to_json(self) -> str:
        d = self._asdict()
        d["table"] = [(name, list(map(float, v))) for name, v in self.table]
        return json.dumps(d, sort_keys=True)

    def distributions(self) -> dict[str, Distribution]:
        return {name: parse_distribution(name, text) for name, text in self.vary}


def make_spec(scenario="carry", n=None, vary=None, fixed=None, seed=0, switch="hard", dt=1e-3, T=None,
              x64=False, table=None, integrator=None) -> SweepSpec:
    """Validate and freeze a sweep description; raises ValueError on any mistake."""
    from coopjax.integration import SimConfig, default_integrator
    from coopjax.model import Options

    integrator = integrator or default_integrator(switch)
    SimConfig(scenario, Options(switch=switch), integrator=integrator, dt=float(dt), T=T).validate()
    vary = dict(vary or {})
    fixed = dict(fixed or {})
    table = {k: np.asarray(v, np.float64) for k, v in (table or {}).items()}
    dists = {name: parse_distribution(name, text) for name, text in vary.items()}
    for name in list(fixed) + list(table):
        split_name(name)
    clash = (set(vary) & set(fixed)) | (set(table) & (set(vary) | set(fixed)))
    if clash:
        raise ValueError(f"{sorted(clash)[0]} is given twice (--vary, --set or --from): give it once")
    implied = grid_size(dists)
    rows = len(next(iter(table.values()))) if table else None
    for candidate in (implied, rows):
        if candidate is not None and n is not None and n != candidate:
            raise ValueError(f"--n {n} disagrees with the {candidate} samples implied by the grid or the table")
    if implied is not None and rows is not None and implied != rows:
        raise ValueError(f"the grid implies {implied} samples but the table has {rows} rows")
    n = n if n is not None else implied if implied is not None else rows
    if n is None or n < 1:
        raise ValueError("say how many samples: --n N (or use grid axes, or --from a table)")
    if not dists and not table:
        raise ValueError(f"nothing varies, so all {n} samples would be the same run: add --vary NAME=DIST "
                         "(or --from TABLE), or use `coopjax simulate` for one run")
    columns = len(dists) + len(table) + len(METRICS) + 3
    if n * columns * 8 > memory_limit():
        raise ValueError(f"--n {n}: a table of {n} rows x {columns} columns needs {n * columns * 8 / 2**30:.3g} GiB, "
                         f"more than half of this machine's memory ({memory_limit() / 2**30:.3g} GiB); "
                         f"at most {memory_limit() // (columns * 8):,} samples per sweep here")
    from coopjax.params import make_params

    make_params(**fixed)  # every --set value checked now, before any file is written
    return SweepSpec(scenario, int(n), tuple(vary.items()), tuple(fixed.items()), int(seed), switch,
                     float(dt), T, bool(x64), tuple((k, tuple(v)) for k, v in table.items()), integrator)


def _significant(x: np.ndarray, digits: int) -> np.ndarray:
    """x to `digits` significant digits. The step limit is an eigenvalue estimate: the two robots'
    nearly repeated poles make it move by ~1e-7 with rounding (sqrt of machine epsilon), for example
    between a one- and a two-process run, so more digits would be noise."""
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = 10.0 ** (np.floor(np.log10(np.abs(x))) - digits + 1)
        return np.where(np.isfinite(x) & (x != 0), np.round(x / scale) * scale, x)


def memory_limit() -> int:
    """Half of this machine's physical memory, in bytes: the most one table may take."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 2
    except (ValueError, OSError, AttributeError):
        return 8 * 2**30


def block_size(n: int) -> int:
    """Samples per device per call: a power of two up to 256, fixed by the sweep size alone.

    256 measured fastest on this 2-core CPU (12.8 M steps/s against 10.6 M at 4096): the step's
    intermediates stay in cache.
    """
    from coopjax.devices import BLOCK

    return int(min(BLOCK, 2 ** math.ceil(math.log2(max(n, 8)))))


@functools.lru_cache(maxsize=16)
def _metrics_fn(config, devices=None):
    """One jitted metrics function per configuration (and device tuple), so repeated sweeps (tuning's
    selection and judging call them many times) compile once, not once per call. Over several
    devices each runs its own slice (`devices.per_device`)."""
    import jax

    from coopjax.devices import per_device
    from coopjax.integration import integrate

    fn = lambda p: integrate(p, config).metrics
    return jax.jit(fn if devices is None or len(devices) == 1 else per_device(fn, list(devices)))


class _Runner:
    """Compiles once, then evaluates slabs of `devices x block` samples."""

    def __init__(self, spec: SweepSpec, devices):
        from coopjax.integration import SimConfig
        from coopjax.model import Options

        self.spec = spec
        self.devices = list(devices)
        self.block = block_size(spec.n)
        self.config = SimConfig(spec.scenario, Options(switch=spec.switch), integrator=spec.integrator, dt=spec.dt,
                                T=spec.T)
        self.run = _metrics_fn(self.config, tuple(self.devices))

    @property
    def slab(self) -> int:
        return len(self.devices) * self.block

    def __call__(self, values: dict[str, np.ndarray]) -> np.ndarray:
        import jax

        from coopjax import stability
        from coopjax.devices import place
        from coopjax.params import make_params

        m = len(next(iter(values.values())))
        out = np.empty((m, len(COLUMNS_PER_SAMPLE)))
        for start in range(0, m, self.slab):
            stop = min(start + self.slab, m)
            pad = self.slab - (stop - start)
            slab = {k: np.concatenate([v[start:stop], np.repeat(v[stop - 1:stop], pad)]) for k, v in values.items()}
            params = make_params(**dict(self.spec.fixed), **slab)
            # The step check of `simulate`, per sample. Not overlapped with the run: compiling it while
            # the devices compute made a small sweep 5x slower (thread contention, measured).
            eig = stability.fastest_modes(params, self.config)
            limit, growth = _significant(stability.max_stable_dt(eig), 6), stability.growing_mode(eig)
            pending = self.run(place(params, self.devices))
            metrics = np.stack([np.asarray(x, np.float64) for x in jax.device_get(pending)], axis=1)
            finite = metrics[:, METRICS.index("finite")] > 0.5
            # The cause first: an unstable loop, then a step beyond the limit, then a blow-up of
            # unknown cause (`t_diverged` says when any of them blew up).
            status = np.select([growth > 0, self.spec.dt > limit, ~finite], [2, 3, 1], 0)
            metrics[:, METRICS.index("finite")] = status == 0
            out[start:stop] = np.column_stack([metrics, limit, status])[: stop - start]
        return out


def run(spec: SweepSpec, chunk: int = 16384, parts: str | None = None, resume: bool = False,
        progress: bool = False, devices=None) -> dict[str, np.ndarray]:
    """Run a sweep and return its table as columns (sample, varied parameters, metrics).

    With `parts`, each finished chunk is saved there atomically, and `resume=True` skips those
    already saved. Under `jax.distributed`, chunks are shared among processes and process 0 returns
    the whole table (others return it too, except after a resume, when they return None).
    """
    import jax

    if chunk < 1:
        raise ValueError(f"--chunk is {chunk}: it must be at least 1")
    n_chunks = math.ceil(spec.n / chunk)
    n_proc, pid = jax.process_count(), jax.process_index()
    runner = _Runner(spec, devices or jax.local_devices())
    values = sample_values(spec)  # drawn and checked once, before anything is written
    done = np.zeros(n_chunks, bool)
    if parts is not None:
        done = _prepare_parts(parts, spec, chunk, resume, n_chunks) if pid == 0 else done
        if n_proc > 1:
            from jax.experimental import multihost_utils

            done = np.asarray(multihost_utils.broadcast_one_to_all(done))
    results: dict[int, np.ndarray] = {}
    bar = Progress(spec.n, progress and pid == 0)
    for k in np.flatnonzero(done) if pid == 0 else ():
        saved = _load_part(parts, int(k), min((k + 1) * chunk, spec.n) - k * chunk)
        if saved is None:
            done[k] = False
            continue
        results[int(k)] = saved
        bar.update(len(saved))

    todo = [int(k) for k in np.flatnonzero(~done)]
    for r in range(0, len(todo), n_proc):
        round_chunks = todo[r:r + n_proc]
        mine = round_chunks[pid] if pid < len(round_chunks) else None
        local = np.full((chunk, len(COLUMNS_PER_SAMPLE)), np.nan)
        if mine is not None:
            rows = slice(mine * chunk, min((mine + 1) * chunk, spec.n))
            local[: rows.stop - rows.start] = runner({k: v[rows] for k, v in values.items()})
        if n_proc > 1:
            from jax.experimental import multihost_utils

            gathered = np.asarray(multihost_utils.process_allgather(local, tiled=False))
        else:
            gathered = local[None]
        for p, k in enumerate(round_chunks):
            size = min((k + 1) * chunk, spec.n) - k * chunk
            results[k] = gathered[p][:size]
            if parts is not None and pid == 0:
                with atomic_path(_part_path(parts, k)) as tmp:
                    with open(tmp, "wb") as f:
                        np.save(f, results[k])
            bar.update(size)

    if len(results) < n_chunks:  # a non-zero process on resume: only process 0 holds saved chunks
        return None
    metrics = np.concatenate([results[k] for k in range(n_chunks)])
    columns = {"sample": np.arange(spec.n), **values}
    for j, name in enumerate(COLUMNS_PER_SAMPLE):
        columns[name] = metrics[:, j]
    columns["finite"] = columns["finite"] > 0.5
    columns["status"] = np.asarray(STATUSES)[columns["status"].astype(int)]
    return columns


def sample_values(spec: SweepSpec) -> dict[str, np.ndarray]:
    """Every sample's varied values (from --from, then --vary), checked against each parameter's
    sign rule; a ValueError names the first offending sample. Cheap: one hash per value."""
    sources = {name: f"--vary {name}={text}" for name, text in spec.vary}
    sources.update({name: "--from" for name, _ in spec.table})
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
            raise ValueError(
                f"{sources[name]} gives {name} = {v[i]:g} at sample {i}, but {name} must be "
                f"{'finite' if rule == 'finite' else rule}: choose a distribution that stays in range "
                "(e.g. loguniform)"
            )
    return values


def _load_part(parts: str, k: int, rows: int):
    """A saved chunk, or None (with a note) if it is unreadable or the wrong shape: it is recomputed."""
    path = _part_path(parts, k)
    try:
        data = np.load(path)
        if data.shape == (rows, len(COLUMNS_PER_SAMPLE)):
            return data
    except (OSError, ValueError, EOFError):
        pass
    import sys

    print(f"coopjax: note: {path} is unreadable or incomplete; it is computed again", file=sys.stderr)
    return None


def _part_path(parts: str, k: int) -> str:
    return os.path.join(parts, f"chunk-{k:06d}.npy")


def _prepare_parts(parts: str, spec: SweepSpec, chunk: int, resume: bool, n_chunks: int) -> np.ndarray:
    manifest = os.path.join(parts, "manifest.json")
    identity = json.dumps({"spec": json.loads(spec.to_json()), "chunk": chunk, "format": CHUNK_FORMAT}, sort_keys=True)
    if os.path.exists(manifest):
        if not resume:
            raise ValueError(f"{parts} holds an unfinished sweep: add --resume to finish it, or delete it")
        if open(manifest).read() != identity:
            raise ValueError(f"--resume: {parts} belongs to a different sweep (other options or chunk size)")
        return np.array([os.path.exists(_part_path(parts, k)) for k in range(n_chunks)])
    os.makedirs(parts, exist_ok=True)
    with atomic_path(manifest) as tmp:
        with open(tmp, "w") as f:
            f.write(identity)
    return np.zeros(n_chunks, bool)


def sweep(scenario="carry", n=None, vary=None, fixed=None, seed=0, switch="hard", dt=1e-3, T=None,
          table=None, chunk=16384, progress=False, integrator=None):
    """Notebook entry point: the sweep as a pandas DataFrame (or a dict of columns without pandas).

    Example: `sweep("carry", 1000, vary={"M_b": "loguniform:0.5:5", "K_GP": "uniform:0.2:1"})`.
    """
    import jax

    spec = make_spec(scenario, n, vary, fixed, seed, switch, dt, T, jax.config.jax_enable_x64, table, integrator)
    columns = run(spec, chunk=chunk, progress=progress)
    try:
        import pandas as pd
    except ImportError:
        return columns
    return pd.DataFrame(columns)


def is_parquet(path: str) -> bool:
    return path.lower().endswith(".parquet")


def write_table(path: str, columns: dict[str, np.ndarray]) -> None:
    """CSV (full precision: Python's shortest round-trip repr) or Parquet (pandas + pyarrow), atomically."""
    if is_parquet(path):
        import pandas as pd

        with atomic_path(path) as tmp:
            pd.DataFrame(columns).to_parquet(tmp, index=False)
        return
    from coopjax.io import write_csv

    write_csv(path, columns)


def read_table(path: str, what: str = "table") -> dict[str, np.ndarray]:
    """A sweep or parameter table; any problem with the file is one ValueError that names it."""
    if os.path.isdir(path):
        raise ValueError(f"{what} {path!r} is a folder, not a file")
    if not os.path.exists(path):
        raise ValueError(f"{what} {path!r}: no such file")
    if os.path.getsize(path) == 0:
        raise ValueError(f"{what} {path!r} is empty")
    if is_parquet(path):
        try:
            import pandas as pd

            frame = pd.read_parquet(path)
        except ImportError:
            raise ValueError("reading Parquet needs pandas and pyarrow: pip install 'coopjax[sweep]'") from None
        except Exception as error:  # pyarrow raises several types for a damaged file
            raise ValueError(f"{what} {path!r} is not a readable Parquet file ({type(error).__name__})") from None
        columns = {c: frame[c].to_numpy() for c in frame.columns}
    else:
        from coopjax.io import read_csv

        columns = read_csv(path, what)
    if not columns or not len(next(iter(columns.values()))):
        raise ValueError(f"{what} {path!r} has no rows")
    return columns
