"""The one evaluation path of sweeps and the tuner's judge: a batch of parameter sets in, per sample
the metrics with their status out.

`evaluate` runs the batch on every local device, checks each sample's step against its linearised
loop and, on request, runs it again at dt / 2 (`coopjax.step_check`); the status (`coopjax.status`)
says which of those failed, most basic cause first. Columns are float64 numpy arrays.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from coopjax import devices, scenarios, stability, step_check
from coopjax.config import Config
from coopjax.integration import INTEGRATORS
from coopjax.objectives import on_grid
from coopjax.params import Params
from coopjax.simulation import MetricsRefined, metrics_of, refinable
from coopjax.status import LABELS, Status

# Every sample's bookkeeping beside its metrics, with its unit or meaning.
BOOKKEEPING = {
    "finite": "1 if the run did not diverge, else 0",
    "t_diverged": "s (NaN if it did not)",
    "dt_limit": "s, the largest stable step of the linearised loop",
    "status": "|".join(LABELS),
}
STEP_ERROR = {
    "step_error": "tolerances: the two-step check's largest disagreement between dt and dt/2 (above 1: step_artefact)"
}
REFINED = {"dt": "s, the step the sample ran at (below the configured one where its loop needed it: refine)"}


def columns(config: Config, check_step: bool = False, refine: int = 0) -> tuple[str, ...]:
    """What `evaluate` returns, in order: the configured metrics, then the bookkeeping (and the
    two-step check's column, and the step each sample ran at, if asked for)."""
    return (
        tuple(config.metrics)
        + tuple(BOOKKEEPING)
        + (tuple(STEP_ERROR) if check_step else ())
        + (tuple(REFINED) if refine else ())
    )


def block_size(n: int) -> int:
    """Samples per device per call for a batch of n: a power of two up to `devices.BLOCK`, fixed by
    n alone (so a sweep's compiled per-device program does not depend on its chunking)."""
    return int(min(devices.BLOCK, 2 ** math.ceil(math.log2(max(n, 8)))))


def significant(x: np.ndarray, digits: int) -> np.ndarray:
    """x to `digits` significant digits. The step limit is an eigenvalue estimate: the two robots'
    nearly repeated poles make it move by ~1e-7 with rounding (sqrt of machine epsilon), for example
    between a one- and a two-process run, so more digits would be noise."""
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = 10.0 ** (np.floor(np.log10(np.abs(x))) - digits + 1)
        return np.where(np.isfinite(x) & (x != 0), np.round(x / scale) * scale, x)


def evaluate(
    params: Params,
    config: Config,
    *,
    check_step: bool = False,
    block: int | None = None,
    refine: int = 0,
    shared: bool = False,
) -> dict:
    """Per sample of the batch `params` (leaves with a trailing batch axis), the columns
    `columns(config, check_step, refine)` as float64 arrays; `status` holds `Status` codes.

    Args:
      params: a batch of parameter sets (`make_params` with 1-D values); cast to the config's dtype.
      config: how every sample runs (validated by the caller).
      check_step: run every sample again at dt / 2: a `step_error` column, and status
        `step_artefact` where the answers move by more than a tolerance. It triples the cost.
      block: samples per device per call (None: `block_size` of the batch).
      refine: a sample whose step is beyond its loop's stability limit runs again at dt / 2^k, the
        longest such step within the limit, for k up to `refine` (and is checked at half that step):
        its values then stand for the model, not for a step it cannot take. With `check_step`, a
        step artefact runs again the same way, at dt / 2, dt / 4, ... until its check agrees: where
        dt misses an event that decides a value, the first two steps that agree give the limit's.
        The `dt` column says the step each sample ran at. 0: such samples keep their status.
      shared: run unchecked samples in the program a checked evaluation runs (`shares_program`), so
        that a caller evaluating both ways (the tuner's judge: selection, search, verdict) compiles
        one program, not two. Values move by round-off only (1e-11 relative in float64).
    """
    params = config.cast(params)
    block = block or block_size(params.batch_shape[0])
    limit, growth = stability.stable_dt(params, config)
    limit = significant(limit, 6)
    out = _runs(params, config, check_step, block, shared=shared)
    # The cause first: an unstable loop, then a step beyond the limit, then a blow-up of unknown
    # cause (`t_diverged` says when any of them blew up).
    status = _status(out, growth, config.dt > limit, check_step)
    out["dt"] = np.full(len(status), config.dt)
    for k in range(1, refine + 1):
        # The longest halving within the limit (each such sample refined once, at its own step), and
        # every sample whose check still disagrees.
        beyond = (status == Status.STEP_BEYOND_LIMIT) & (config.dt / 2**k <= limit)
        rows = np.flatnonzero(beyond | (status == Status.STEP_ARTEFACT))
        if not len(rows):
            continue
        part = jax.tree_util.tree_map(lambda x: x[..., rows], params)
        again = _runs(part, config, check_step, block, 2**k, shared)
        for name, value in again.items():
            out[name][rows] = value
        out["dt"][rows] = config.dt / 2**k
        status[rows] = _status(again, growth[rows], np.zeros(len(rows), bool), check_step)
    out["dt_limit"] = limit
    out["status"] = status.astype(np.float64)
    return {name: out[name] for name in columns(config, check_step, refine)}


def shared_runs(params: Params, config: Config, block: int, compile_only: bool = False):
    """The metrics of every sample at config.dt, unchecked, in the program `evaluate` with `shared`
    runs: a caller that also judges (the tuner, whose training runs at a step of the judge's grid,
    `grid`) compiles one program for both. With `compile_only`, the compiled program is returned
    and nothing runs."""
    if not shares_program(config):
        raise ValueError(f"{config.method} at dt = {config.dt} shares no program (shares_program)")
    return _runs(config.cast(params), config, False, block, shared=True, compile_only=compile_only)


def grid(config: Config) -> tuple[float, int]:
    """(the grid step, r): the shared program's grid, and the substeps per grid step that make
    config.dt. The grid is config.dt doubled while it stays on the scenario's windows and no coarser
    than the scenario's converged step (its integrator's `converged_dt`), so that runs at the
    training step, the judge's step and their halvings share one program (r traced). dt = grid / r
    is exact in floating point (r a power of two)."""
    scenario = scenarios.get(config.scenario)
    coarsest = INTEGRATORS[config.method].converged_dt.get((config.scenario, config.switch)) or config.dt
    r = 1
    while config.dt * 2 * r <= coarsest * (1 + 1e-9) and on_grid(scenario, config.dt * 2 * r, config.horizon):
        r *= 2
    return config.dt * r, r


def _runs(
    params: Params,
    config: Config,
    check_step: bool,
    block: int,
    r: int = 1,
    shared: bool = False,
    compile_only: bool = False,
):
    """The metrics (and with `check_step` the two-step check's error) of every sample at config.dt / r
    (with `compile_only`, the compiled program, where it is shared; nothing runs)."""
    if shares_program(config) and (check_step or r > 1 or shared):
        # One program for every step of the check and the refinements (r traced), on the grid of
        # `grid`: the run, its dt / 2 and every halving compile once (a lone run at dt keeps its own,
        # 4 % faster). Its round-off differs from a program built for one step (dt a constant):
        # 1e-11 relative in float64, which the sliding-mode step does not amplify.
        metrics = step_check.halved(config).metrics if check_step or shared else config.metrics
        step, r0 = grid(config)
        program = MetricsRefined(dataclasses.replace(config, dt=step, metrics=metrics))

        def at(substeps):
            counts = np.full(params.batch_shape[0], r0 * substeps, np.int32)
            return devices.run(program, (params, counts), fixed_block=True, block=block, compile_only=compile_only)

        if compile_only:
            return at(r)
        coarse, fine = at(r), at(2 * r) if check_step else None
    else:
        stepped = config if r == 1 else dataclasses.replace(config, dt=config.dt / r)
        coarse = devices.run(metrics_of(stepped), params, fixed_block=True, block=block)
        if check_step:
            fine = devices.run(metrics_of(step_check.halved(stepped)), params, fixed_block=True, block=block)
    out = {n: np.array(v, np.float64) for n, v in zip(coarse._fields, jax.device_get(list(coarse)))}
    if check_step:
        names = step_check.checked(config)
        out["step_error"] = step_check.step_error(
            {n: out[n] for n in names}, {n: np.asarray(getattr(fine, n), np.float64) for n in names}
        )
    return out


def shares_program(config: Config) -> bool:
    """Whether a run's dt / 2 and its refinements share its program (`MetricsRefined`): with the
    sliding-mode step, where the horizon and windows lie on the grid. Plain RK4 on the hard switch
    chatters, and its chatter follows round-off, so its runs keep programs of their own, and a sweep's
    values equal `simulate`'s bit for bit."""
    return config.method == "filippov" and refinable(config)


def _status(out: dict, growth, beyond, check_step: bool) -> np.ndarray:
    status = np.select(
        [growth > 0, beyond, out["finite"] < 0.5],
        [Status.UNSTABLE_LOOP, Status.STEP_BEYOND_LIMIT, Status.DIVERGED],
        Status.OK,
    )
    if check_step:
        status = np.where((status == Status.OK) & step_check.artefacts(out["step_error"]), Status.STEP_ARTEFACT, status)
    return status
