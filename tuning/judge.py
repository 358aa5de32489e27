"""How a result is judged: the hard model at 1e-3 s, float64, with the two-step check, on body masses
the training never saw; and how candidates are selected on a third grid of validation masses.

Every judging runs through `coopjax.evaluation.evaluate`, the path sweeps take too: the parameter
sets go in as `Params`, the metrics and their statuses (`coopjax.status.Status`) come out.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import numpy as np

from coopjax import evaluation
from coopjax.config import Config
from coopjax.errors import InputError
from coopjax.params import Params, make_params
from coopjax.status import Status, labels
from tuning.problem import HOLD_TOLERANCE

# s: a factor 2 inside the stability limit of Table 1's gains (about 4e-3 s), which shrinks as K_GP
# grows; the sliding-mode step met the accuracy tolerances there on every sample (docs/model.md).
JUDGE_DT = 1e-3
# Runs per device per call of every judging: one block for all sizes, so that the selection, the
# verdict and the race share one compiled program per step (docs/tuning.md, where the time goes).
JUDGE_BLOCK = 128
PER_MASS = ("min_grip", "peak_grip", "rms_lag", "slip", "crush", "impact")


class Verdict(NamedTuple):
    """Worst case over the judged masses, and the per-mass metrics behind it."""

    min_grip: float  # N, least over masses
    peak_grip: float  # N, largest over masses
    rms_lag: float  # m, largest over masses
    slip: float  # N^2, largest over masses
    crush: float  # N^2, largest over masses
    impact: float  # N^2, crush after the grip window (release), largest over masses
    objective: float  # N: peak_grip + w_lag * rms_lag in mm (the hard maximum over masses)
    finite: bool  # no mass's run diverged
    # Every mass's run is `Status.measured` (it ended, within the step's stability limit): the worst
    # values above stand for the runs (NaN otherwise).
    measured: bool
    holds: bool  # every status OK and min_grip >= F_lim - HOLD_TOLERANCE at every mass
    step_error: float  # the two-step check's worst disagreement over masses, in tolerances (NaN: not checked)
    step_artefact: bool  # some mass's answer moved by more than a tolerance between dt and dt/2
    per_mass: dict  # name -> list over masses (and `status`, their labels)

    @property
    def score(self) -> float:
        """The validated objective: `objective` if the grip holds at every mass, else infinity."""
        return self.objective if self.holds else math.inf

    def row(self) -> dict:
        """As a flat dict for files and tables; the lag in mm is for display only."""
        row = dict(self._asdict())
        row["rms_lag_mm"] = self.rms_lag * 1e3
        return row


def judge_config(dt: float = JUDGE_DT) -> Config:
    """The verdict's runs: the hard switch and contact, the sliding-mode integrator, float64."""
    return Config("carry", switch="hard", contact="unilateral", integrator="filippov", dt=dt, dtype="float64")


def judge(
    values: dict[str, float] | list[dict[str, float]],
    masses,
    base: Params | None = None,
    w_lag: float = 1.0,
    dt: float = JUDGE_DT,
    check_step: bool = True,
):
    """Judge one parameter set (or a list of them) with the hard model on `masses`, in float64.

    Args:
      values: the tuned names' values (`K_GP`, per robot `K_GP_L`, ...), or a list of such sets.
      masses: the body masses to judge at, kg.
      base: every other parameter (default Table 1's), a single set.
      w_lag: N of objective per mm of worst RMS lag.
      dt: the judge's step, s.
      check_step: repeat every run at dt / 2 (`coopjax.step_check`): a set whose answers move by more
        than the accuracy tolerances is a step artefact, and does not hold.

    Returns:
      a `Verdict` (a list of them for a list). The runs are sharded over every local device.
    """
    if not jax.config.jax_enable_x64:
        raise InputError("judging runs in float64: call jax.config.update('jax_enable_x64', True) first")
    many = isinstance(values, (list, tuple))
    sets = list(values) if many else [values]
    masses = np.asarray(masses, np.float64)
    base = make_params(dtype="float64") if base is None else base
    if base.batch_shape:
        raise InputError("the base parameters of a judging must be a single set, not a batch", "base")
    G, M = len(sets), len(masses)
    params = base.replace(M_b=np.tile(masses, G), **{n: np.repeat([float(g[n]) for g in sets], M) for n in sets[0]})
    config = judge_config(dt).validate()
    out = evaluation.evaluate(params, config, check_step=check_step, block=JUDGE_BLOCK)
    F_lim = float(np.asarray(base.F_lim).min())
    verdicts = [_verdict({k: v[g * M : (g + 1) * M] for k, v in out.items()}, w_lag, F_lim) for g in range(G)]
    return verdicts if many else verdicts[0]


def select(
    candidates: list[dict],
    masses,
    base: Params | None = None,
    w_lag: float = 1.0,
    dt: float = JUDGE_DT,
    check_step: bool = True,
) -> tuple[int, list[Verdict]]:
    """The candidate a hard-model validation prefers: it holds the grip at every validation mass and
    then has the lowest objective (ties: the earlier candidate). Returns its index and all verdicts.

    This is model selection, not judging: validation masses are never the held-out ones.
    """
    verdicts = judge(list(candidates), masses, base, w_lag, dt, check_step=check_step)
    return preferred(verdicts), verdicts


def preferred(verdicts: list[Verdict]) -> int:
    """`select`'s rule: the first verdict that holds with the lowest objective (or, if none holds, the
    lowest objective)."""
    key = lambda i: (not verdicts[i].holds, verdicts[i].objective if np.isfinite(verdicts[i].objective) else np.inf)
    return min(range(len(verdicts)), key=key)


def _verdict(m: dict, w_lag: float, F_lim: float) -> Verdict:
    status = m["status"].astype(int)
    measured = bool(all(Status(s).measured for s in status))

    def worst(x, pick):  # a step artefact ran to the end: its values are shown, and it does not hold
        return float(pick(x)) if measured else float("nan")

    min_grip, peak, lag = worst(m["min_grip"], np.min), worst(m["peak_grip"], np.max), worst(m["rms_lag"], np.max)
    checked = "step_error" in m
    artefact = bool(np.any(status == Status.STEP_ARTEFACT))
    per_mass = {k: [float(x) for x in m[k]] for k in PER_MASS}
    per_mass["status"] = labels(status).tolist()
    return Verdict(
        min_grip=min_grip,
        peak_grip=peak,
        rms_lag=lag,
        slip=worst(m["slip"], np.max),
        crush=worst(m["crush"], np.max),
        impact=worst(m["impact"], np.max),
        objective=peak + w_lag * 1e3 * lag,
        finite=bool(np.all(m["finite"] > 0.5)),
        measured=measured,
        holds=measured and min_grip >= F_lim - HOLD_TOLERANCE and not artefact,
        step_error=float(np.nanmax(m["step_error"]))
        if checked and np.isfinite(m["step_error"]).any()
        else float("nan"),
        step_artefact=artefact,
        per_mass=per_mass,
    )
