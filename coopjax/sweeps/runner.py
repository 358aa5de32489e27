"""Running a sweep: its chunks on every local device, or shared among the processes of a
`jax.distributed` run, saved to a parts folder as they finish.

Every device always runs the same per-device block of samples (padded if need be), and the block
depends only on the sweep size (or is fixed by the caller). XLA therefore compiles the same
per-device program whatever the chunking, and rounding cannot differ between layouts; the closed loop
can amplify rounding (docs/model.md, "Step size"), so that matters. Across machines, processes take
chunks in turn; after each round the results are gathered with `process_allgather`, and process 0
writes them.
"""

from __future__ import annotations

import math

import jax
import numpy as np
from jax.experimental import multihost_utils

from coopjax import evaluation
from coopjax.errors import InputError
from coopjax.params import make_params
from coopjax.progress import bar as progress_bar
from coopjax.status import labels
from coopjax.sweeps.parts import load_part, part_path, prepare_parts, save_array
from coopjax.sweeps.spec import SweepSpec, sample_values


def evaluate(spec: SweepSpec, values: dict[str, np.ndarray], block: int | None = None) -> np.ndarray:
    """The result columns (`spec.columns`, as float64) of the given parameter sets
    (`evaluation.evaluate`). `block`: samples per device per call (None: the sweep's own)."""
    params = make_params(**dict(spec.fixed), **values)
    out = evaluation.evaluate(
        params, spec.config, check_step=spec.check_step, block=block or evaluation.block_size(spec.n)
    )
    return np.column_stack([out[name] for name in spec.columns])


def run(
    spec: SweepSpec,
    chunk: int = 16384,
    parts: str | None = None,
    resume: bool = False,
    progress: bool = False,
    block: int | None = None,
):
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
    bar = progress_bar(total=spec.n, desc="sweep", unit="sample", enabled=progress and pid == 0)
    for k in np.flatnonzero(done) if pid == 0 else ():
        saved = load_part(parts, int(k), min((k + 1) * chunk, spec.n) - k * chunk, width)
        if saved is None:
            done[k] = False
            continue
        results[int(k)] = saved
        bar.update(len(saved))

    todo = [int(k) for k in np.flatnonzero(~done)]
    for r in range(0, len(todo), n_proc):
        round_chunks = todo[r : r + n_proc]
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
    columns["status"] = labels(columns["status"])
    return columns
