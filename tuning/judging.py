"""How a result is judged: the hard model at 1e-3 s, float64, with the two-step check, on draws of the
problem's uncertain parameters that training never saw, requirement by requirement; and how
candidates are selected on a third set of validation draws.

Every judging runs through `coopjax.evaluation.evaluate`, the path sweeps take too: the parameter
sets go in as `Params`, the metrics and their statuses (`coopjax.status.Status`) come out.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import numpy as np

from coopjax import evaluation, scenarios
from coopjax.config import Config
from coopjax.errors import InputError
from coopjax.objectives import METRICS
from coopjax.objectives.base import missing_windows
from coopjax.params import Params, make_params
from coopjax.status import Status, labels
from tuning.problem import Problem, columns_of
from tuning.training import aggregate

# s: a factor 2 inside the stability limit of Table 1's gains (about 4e-3 s), which shrinks as K_GP
# grows; the sliding-mode step met the accuracy tolerances there on every sample (docs/model.md).
JUDGE_DT = 1e-3
# Runs per device per call of every judging: one block for all sizes, so that the selection, the
# verdict and the race share one compiled program per step (docs/tuning.md, where the time goes).
JUDGE_BLOCK = 128
# What every verdict reports per case beside the problem's own metrics (where the scenario has them).
PER_CASE = ("min_grip", "peak_grip", "peak_hold", "rms_lag", "slip", "crush", "impact")
LEAST = ("min_grip", "min_swi")  # metrics whose worst is their least value


class Verdict(NamedTuple):
    """A parameter set judged against a problem: each requirement and objective term, worst case over
    the judged draws of every scenario, and the per-case metrics behind them. `v.peak_grip` and the
    like read `worst`."""

    objective: float  # N: the objective's terms with hard aggregates (max, mean, cvar) over the draws
    terms: list  # per objective term: metric, over, weight, value (the aggregate, in the metric's unit)
    requirements: list  # per requirement: text, metric, kind, bound, unit, worst, margin, met
    worst: dict  # metric -> worst over every case (least for min_grip and min_swi, else largest)
    finite: bool  # no run diverged
    # Every run is `Status.measured` (it ended, within the step's stability limit): the worst values
    # above stand for the runs (NaN otherwise).
    measured: bool
    holds: bool  # measured, no step artefact, and every requirement met at every case
    step_error: float  # the two-step check's worst disagreement, in tolerances (NaN: not checked)
    step_artefact: bool  # some case's answer moved by more than a tolerance between dt and dt/2
    per_case: dict  # name -> list over cases; also `status` (labels), `scenario` and each uncertain parameter

    def __getattr__(self, name):
        worst = tuple.__getattribute__(self, "_asdict")()["worst"]
        if name in worst:
            return worst[name]
        raise AttributeError(f"Verdict has no {name!r}; its metrics: {', '.join(worst)}")

    @property
    def score(self) -> float:
        """The validated objective: `objective` if every requirement holds, else infinity."""
        return self.objective if self.holds else math.inf

    @property
    def violation(self) -> float:
        """How far the worst requirement misses, relative to its bound's scale (0: all met)."""
        misses = [max(0.0, -r["margin"]) / max(abs(r["bound_value"]), 1e-12) for r in self.requirements]
        misses = [m if np.isfinite(m) else math.inf for m in misses]
        return max(misses, default=0.0)

    def row(self) -> dict:
        """As a flat dict for files and tables; the lag in mm is for display only."""
        row = {k: v for k, v in self._asdict().items()}
        row.update(self.worst)
        if "rms_lag" in self.worst:
            row["rms_lag_mm"] = self.worst["rms_lag"] * 1e3
        return row


def judge_config(dt: float = JUDGE_DT, scenario: str = "carry", metrics=None) -> Config:
    """The verdict's runs: the hard switch and contact, the sliding-mode integrator, float64."""
    return Config(
        scenario,
        switch="hard",
        contact="unilateral",
        integrator="filippov",
        dt=dt,
        dtype="float64",
        metrics=None if metrics is None else tuple(metrics),
    )


def judged_metrics(problem: Problem, scenario: str) -> tuple[str, ...]:
    """What a verdict reads on a scenario: the problem's metrics and `PER_CASE` (those it has)."""
    s = scenarios.get(scenario)
    names = [m for m in PER_CASE if not missing_windows(m, s)] + list(problem.metrics_on(scenario))
    return tuple(dict.fromkeys(names))


def judge(
    values: dict[str, float] | list[dict[str, float]],
    draws=None,
    problem: Problem | None = None,
    base: Params | None = None,
    dt: float = JUDGE_DT,
    check_step: bool = True,
):
    """Judge one parameter set (or a list of them) against a problem, with the hard model in float64.

    Args:
      values: the tuned names' values (`K_GP`, per robot `K_GP_L`, ...), or a list of such sets.
      draws: (M, p) values of the problem's uncertain parameters, or (M,) of the one (default: the
        problem's held-out draws).
      problem: the requirements and objective judged (default: the default `Problem`).
      base: every other parameter (default Table 1's), a single set; the problem's fixed values apply.
      dt: the judge's step, s.
      check_step: repeat every run at dt / 2 (`coopjax.step_check`): a set whose answers move by more
        than the accuracy tolerances is a step artefact, and does not hold.

    Returns:
      a `Verdict` (a list of them for a list). The runs are sharded over every local device.
    """
    if not jax.config.jax_enable_x64:
        raise InputError("judging runs in float64: call jax.config.update('jax_enable_x64', True) first")
    problem = problem or Problem()
    many = isinstance(values, (list, tuple))
    sets = list(values) if many else [values]
    draws = problem.held_out_draws() if draws is None else np.asarray(draws, np.float64)
    draws = draws[:, None] if draws.ndim == 1 else draws
    base = problem.base(make_params(dtype="float64") if base is None else base)
    if base.batch_shape:
        raise InputError("the base parameters of a judging must be a single set, not a batch", "base")
    G, M = len(sets), len(draws)
    drawn = {u.name: np.tile(draws[:, i], G) for i, u in enumerate(problem.uncertain)}
    tuned = {n: np.repeat([float(g[n]) for g in sets], M) for n in sets[0]}
    params = base.replace(**drawn, **tuned)
    if "M_b" not in drawn:
        params = params.replace(M_b=np.full(G * M, float(np.asarray(base.M_b))))
    runs = []
    for s in problem.scenarios:
        config = judge_config(dt, s, judged_metrics(problem, s)).validate()
        runs.append(evaluation.evaluate(params, config, check_step=check_step, block=JUDGE_BLOCK))
    verdicts = []
    for g in range(G):
        rows = slice(g * M, (g + 1) * M)
        per = [{k: v[rows] for k, v in out.items()} for out in runs]
        bound_values = {
            r: np.broadcast_to(np.asarray(r.bound_values(params), np.float64), (G * M,))[rows]
            for r in problem.require
            if isinstance(r.bound, str)
        }
        verdicts.append(_verdict(problem, per, draws, bound_values))
    return verdicts if many else verdicts[0]


def select(
    candidates: list[dict],
    draws,
    problem: Problem | None = None,
    base: Params | None = None,
    dt: float = JUDGE_DT,
    check_step: bool = True,
) -> tuple[int, list[Verdict]]:
    """The candidate a hard-model validation prefers: it meets every requirement at every validation
    draw and then has the lowest objective (ties: the earlier candidate); if none does, the one that
    misses least. Returns its index and all verdicts.

    This is model selection, not judging: validation draws are never the held-out ones.
    """
    verdicts = judge(list(candidates), draws, problem, base, dt, check_step=check_step)
    return preferred(verdicts), verdicts


def preferred(verdicts: list[Verdict]) -> int:
    """`select`'s rule: the first verdict that holds with the lowest objective; if none holds, the
    least violation of the requirements, then the lowest objective."""
    finite = lambda x: x if np.isfinite(x) else np.inf
    key = lambda i: (
        not verdicts[i].holds,
        0.0 if verdicts[i].holds else finite(verdicts[i].violation),
        finite(verdicts[i].objective),
    )
    return min(range(len(verdicts)), key=key)


def _verdict(problem: Problem, runs: list[dict], draws: np.ndarray, bound_values: dict) -> Verdict:
    M = len(draws)
    names = list(dict.fromkeys(k for out in runs for k in out if k not in ("dt_limit", "t_diverged")))
    nan = np.full(M, np.nan)
    case = {k: np.concatenate([out.get(k, nan) for out in runs]) for k in names}  # scenario-major
    status = case["status"].astype(int)
    measured = bool(all(Status(s).measured for s in status))
    artefact = bool(np.any(status == Status.STEP_ARTEFACT))

    def worst(name, x=None):  # a step artefact ran to the end: its values are shown, and it does not hold
        x = case[name] if x is None else x
        if not measured or np.all(np.isnan(x)):
            return float("nan")
        return float(np.nanmin(x) if name in LEAST else np.nanmax(x))

    metrics = [k for k in names if k in METRICS]
    objective, terms = 0.0, []
    for o, cols in zip(problem.minimise, problem.objective_columns(M)):
        x = case[o.metric][cols]
        value = float(aggregate(x, o.over)) if measured else float("nan")
        objective += o.weight * value
        terms.append(
            {
                "metric": o.metric,
                "over": o.over,
                "weight": o.weight,
                "value": value,
                "scenarios": list(o.scenarios or problem.scenarios),
            }
        )
    requirements = []
    for r in problem.require:
        cols = columns_of(problem.scenarios, r, M)
        x = case[r.metric][cols]
        bound = np.tile(bound_values[r], len(cols) // M) if isinstance(r.bound, str) else np.full(len(cols), r.bound)
        slack = r.slack(x, bound)
        tolerance = r.tolerance
        margin = float(np.min(slack)) if measured and np.isfinite(slack).all() else float("nan")
        at = int(np.argmin(slack)) if np.isfinite(margin) else None
        requirements.append(
            {
                "requirement": r.text,
                "metric": r.metric,
                "kind": r.kind,
                "bound": r.bound,
                "bound_value": float(bound[at]) if at is not None else float(bound[0]),
                "unit": METRICS[r.metric].unit,
                "worst": float(x[at]) if at is not None else float("nan"),
                "margin": margin,
                "tolerance": tolerance,
                "met": bool(np.isfinite(margin) and np.all(r.met(x, bound))),  # training's rule, every case
                "scenarios": list(r.scenarios or problem.scenarios),
            }
        )
    per_case = {k: [float(v) for v in case[k]] for k in metrics}
    per_case["status"] = labels(status).tolist()
    per_case["scenario"] = [s for s in problem.scenarios for _ in range(M)]
    for i, u in enumerate(problem.uncertain):
        per_case[u.name] = [float(v) for v in np.tile(draws[:, i], len(problem.scenarios))]
    checked = "step_error" in case
    return Verdict(
        objective=float(objective),
        terms=terms,
        requirements=requirements,
        worst={k: worst(k) for k in metrics},
        finite=bool(np.all(case["finite"] > 0.5)),
        measured=measured,
        holds=measured and not artefact and all(r["met"] for r in requirements),
        step_error=float(np.nanmax(case["step_error"]))
        if checked and np.isfinite(case["step_error"]).any()
        else float("nan"),
        step_artefact=artefact,
        per_case=per_case,
    )
