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
# A run whose loop needs a finer step than the judge's runs at dt / 2^k (k up to this; dt / 16 =
# 6.25e-5 s): its values are then the model's, where a run beyond its limit would say nothing.
REFINE = 4
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
    # How far from measured: 0 when every case is; else the mean over cases of a badness that is 0
    # for a measured case and at least 1 for one that is not, growing with how early it diverged,
    # how far its step is beyond the loop's limit, or how fast its loop grows (`unmeasured`).
    unmeasured: float
    step_error: float  # the two-step check's worst disagreement, in tolerances (NaN: not checked)
    # Some case's answer still moved by more than a tolerance between its step and half of it after
    # `REFINE` halvings (a case whose check agrees at a finer step reads that step's values).
    step_artefact: bool
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

    def _misses(self) -> list[float]:
        """Per requirement, how far it misses beyond its tolerance, relative to its bound's scale (0: met)."""
        return [max(0.0, -r["margin"] - r["tolerance"]) / max(abs(r["bound_value"]), 1e-12) for r in self.requirements]

    @property
    def violation(self) -> float:
        """How far the worst requirement misses, relative to its bound's scale (0: all met), over the
        measured cases; finite, so that it orders candidates."""
        return max([m for m in self._misses() if np.isfinite(m)], default=0.0)

    @property
    def binding(self) -> dict | None:
        """The requirement that misses most (relative to its bound's scale), or None if all are met."""
        misses = self._misses()
        if not self.requirements or max(misses) <= 0:
            return None
        return self.requirements[int(np.argmax(misses))]

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
    extra=None,
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
      extra: (E, p) draws judged besides `draws` (the worst cases `worst_case` found between them): they
        count for the requirements and the `max` terms, not for a `mean` or `cvar` term, which
        stays the aggregate over `draws`, the design.

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
    design_count = len(draws)
    if extra is not None and len(extra):
        draws = np.concatenate([draws, np.asarray(extra, np.float64).reshape(-1, draws.shape[1])])
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
        # Checked or not (the verdict, the selection, the search between draws), one program.
        out = evaluation.evaluate(params, config, check_step=check_step, block=JUDGE_BLOCK, refine=REFINE, shared=True)
        runs.append(out)
    verdicts = []
    for g in range(G):
        rows = slice(g * M, (g + 1) * M)
        per = [{k: v[rows] for k, v in out.items()} for out in runs]
        bound_values = {
            r: np.broadcast_to(np.asarray(r.bound_values(params), np.float64), (G * M,))[rows]
            for r in problem.require
            if isinstance(r.bound, str)
        }
        verdicts.append(_verdict(problem, per, draws, bound_values, design_count))
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
    most nearly measured (`Verdict.unmeasured`: a run that diverged or could not be run orders below
    every measured one), then the least violation of the requirements, then the lowest objective."""
    finite = lambda x: x if np.isfinite(x) else np.inf
    key = lambda i: (
        not verdicts[i].holds,
        verdicts[i].unmeasured,
        0.0 if verdicts[i].holds else verdicts[i].violation,
        finite(verdicts[i].objective),
    )
    return min(range(len(verdicts)), key=key)


def _badness(status, t_diverged, T, beyond) -> np.ndarray:
    """Per case, 0 if measured, else at least 1: a diverged run 1 + the share of its horizon it did
    not reach, a step beyond the limit 2 + log2 of how far, an unstable loop 2 + that + 4 (all
    finite: candidates are ordered by them, never tied as NaN)."""
    late = np.nan_to_num(1.0 - t_diverged / T, nan=1.0)
    over = np.log2(np.maximum(np.nan_to_num(beyond, nan=1e3, posinf=1e3), 1.0))
    return np.select(
        [status == Status.DIVERGED, status == Status.STEP_BEYOND_LIMIT, status == Status.UNSTABLE_LOOP],
        [1.0 + np.clip(late, 0.0, 1.0), 2.0 + over, 6.0 + over],
        0.0,
    )


def _verdict(problem: Problem, runs: list[dict], draws: np.ndarray, bound_values: dict, design: int) -> Verdict:
    M = len(draws)
    names = list(dict.fromkeys(k for out in runs for k in out if k not in ("dt_limit", "t_diverged", "dt")))
    nan = np.full(M, np.nan)
    case = {k: np.concatenate([out.get(k, nan) for out in runs]) for k in names}  # scenario-major
    status = case["status"].astype(int)
    measured = bool(all(Status(s).measured for s in status))
    artefact = bool(np.any(status == Status.STEP_ARTEFACT))
    ok = np.array([Status(s).measured for s in status])
    badness = _badness(
        status,
        np.concatenate([out["t_diverged"] for out in runs]),
        np.concatenate([np.full(M, scenarios.get(s).T) for s in problem.scenarios]),
        np.concatenate([out["dt"] / np.maximum(out["dt_limit"], 1e-300) for out in runs]),
    )
    case = {k: np.where(ok, v, np.nan) if k in METRICS else v for k, v in case.items()}

    def worst(name, x=None):  # over the measured cases (a step artefact's too: it ran to the end, flagged)
        x = case[name] if x is None else x
        if np.all(np.isnan(x)):
            return float("nan")
        return float(np.nanmin(x) if name in LEAST else np.nanmax(x))

    metrics = [k for k in names if k in METRICS]
    objective, terms = 0.0, []
    for o, cols in zip(problem.minimise, problem.objective_columns(M)):
        x = case[o.metric][cols]
        if o.over != "max":  # a mean or cvar is over the design's draws, not the worst cases added
            x = x[(cols % M) < design]
        x = x[np.isfinite(x)]
        value = float(aggregate(x, o.over)) if len(x) else float("nan")
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
        margin = float(np.nanmin(slack)) if np.isfinite(slack).any() else float("nan")
        at = int(np.nanargmin(slack)) if np.isfinite(margin) else None
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
                "met": bool(np.isfinite(slack).all() and np.all(r.met(x, bound))),  # training's rule, every case
                "scenarios": list(r.scenarios or problem.scenarios),
            }
        )
    per_case = {k: [float(v) for v in case[k]] for k in metrics}
    per_case["status"] = labels(status).tolist()
    per_case["dt"] = [float(v) for v in np.concatenate([out["dt"] for out in runs])]
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
        unmeasured=float(badness.mean()),
        step_error=float(np.nanmax(case["step_error"]))
        if checked and np.isfinite(case["step_error"]).any()
        else float("nan"),
        step_artefact=artefact,
        per_case=per_case,
    )


def worst_case(
    values: dict[str, float],
    draws,
    problem: Problem,
    base: Params | None = None,
    dt: float = JUDGE_DT,
    rounds: int = 5,
    verdict: Verdict | None = None,
) -> np.ndarray:
    """Draws of the uncertain box worse than any of `draws` for one parameter set: a search between
    the draws for the worst case of each requirement (its least slack) and of each `max` term of the
    objective (its largest value), by the hard model at `dt`.

    Each target starts at its worst draw and takes `rounds` rounds of a pattern search in the box's
    unit coordinates (log coordinates for a loguniform parameter): the 2p points a step h away along
    each axis, in one batch with every other target's; the worst replaces the point where it is worse,
    else h halves. h starts at half the spacing of a grid of len(draws) points. Returns the (T, p)
    points reached (T targets), to be judged with the draws; a point where nothing worse was found is
    its starting draw. `verdict`: the set's verdict on `draws`, if judged already.
    """
    draws = np.asarray(draws, np.float64)
    draws = draws[:, None] if draws.ndim == 1 else draws
    items = problem.uncertain
    p = len(items)
    from_unit = lambda z: np.stack([u.at(z[:, i]) for i, u in enumerate(items)], 1)
    targets = _targets(problem)
    if not targets:
        return np.zeros((0, p))
    v = verdict or judge(values, draws, problem, base, dt, check_step=False)
    scores = np.stack([_score(v, t, len(draws)) for t in targets])  # (T, M): larger is worse
    best = scores.argmax(1)
    point, score = problem.to_unit(draws)[best], scores[np.arange(len(targets)), best]
    h = np.full(len(targets), 0.5 / max(1, round(len(draws) ** (1.0 / p)) - 1))
    steps = np.concatenate([np.eye(p), -np.eye(p)])
    for _ in range(rounds):
        trial = np.clip(point[:, None, :] + h[:, None, None] * steps[None], 0.0, 1.0)  # (T, 2p, p)
        flat = trial.reshape(-1, p)
        v = judge(values, from_unit(flat), problem, base, dt, check_step=False)
        got = np.stack([_score(v, t, len(flat)) for t in targets]).reshape(len(targets), len(targets), 2 * p)
        T = np.arange(len(targets))
        own = got[T, T]  # (T, 2p): each target's score at its own trials
        j = own.argmax(1)
        better = own[T, j] > score
        point = np.where(better[:, None], trial[T, j], point)
        score = np.where(better, own[T, j], score)
        h = np.where(better, h, h / 2)
    return from_unit(point)


def missed_at(verdict: Verdict, draws) -> np.ndarray:
    """(k, p) draws: for each requirement `verdict` misses, the draw among those it was judged on
    (`draws`, then any `extra`, in the judge's order) where it misses most; none when it holds."""
    draws = np.asarray(draws, np.float64)
    draws = draws[:, None] if draws.ndim == 1 else draws
    out = [
        draws[int(np.argmax(_score(verdict, ("require", i), len(draws))))]
        for i, r in enumerate(verdict.requirements)
        if not r["met"]
    ]
    return np.unique(np.reshape(out, (-1, draws.shape[1])), axis=0)


def _targets(problem: Problem) -> list:
    """What a worst case is searched for: each requirement, each `max` term."""
    return [("require", i) for i in range(len(problem.require))] + [
        ("minimise", i) for i, o in enumerate(problem.minimise) if o.over == "max"
    ]


def _score(v: Verdict, target, M: int) -> np.ndarray:
    """Per draw (M), how bad the target is there (the largest over its scenarios): a requirement's
    metric signed so that larger is worse, a term's value; a run that is not measured is worst of
    all (+inf), a metric the scenario lacks never worst (-inf)."""
    kind, i = target
    problem_item = v.requirements[i] if kind == "require" else v.terms[i]
    cases = {k: np.asarray(x, np.float64) for k, x in v.per_case.items() if k not in ("status", "scenario")}
    S = len(cases["dt"]) // M
    x = cases[problem_item["metric"]].reshape(S, M)
    if kind == "require":
        x = -x if problem_item["kind"] == "at_least" else x  # larger is worse; the bound shifts all alike
    unmeasured = ~np.isin(np.asarray(v.per_case["status"]), ("ok", "step_artefact")).reshape(S, M)
    x = np.where(unmeasured, np.inf, np.nan_to_num(x, nan=-np.inf))
    on = [s for s in range(S) if v.per_case["scenario"][s * M] in problem_item["scenarios"]]
    return x[on].max(axis=0)
