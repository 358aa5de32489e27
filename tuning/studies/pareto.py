"""`coopjax tune --pareto`: one session per weight of the problem's last objective term, every tuner;
the front of its first two terms over the held-out draws.

Each point of the front is what `session.run` hands over for that weight (the session `coopjax tune`
runs, judged on the held-out draws). The plan's tuner runs to its own end; every other tuner gets
its wall time. The cloud is what held at every training draw in the first weight's runs.
"""

from __future__ import annotations

import dataclasses

from coopjax.io import Outputs, write_json
from coopjax.objectives import METRICS
from tuning import driver, session
from tuning.judging import judge
from tuning.plots import plot_pareto
from tuning.problem import from_log

CLOUD = 200  # parameter sets of the cloud, per tuner


def scale(metric: str) -> float:
    """Lengths are shown in mm."""
    return 1e3 if METRICS[metric].unit == "m" else 1.0


def unit(metric: str) -> str:
    return "mm" if METRICS[metric].unit == "m" else METRICS[metric].unit


def default_weights(problem) -> list[float]:
    """The last term's weight x 1/3, 1 and 8/3."""
    w = problem.minimise[-1].weight
    return [w / 3, w, w * 8 / 3]


def run(sessions: dict, reference: str, weights, log=print) -> dict:
    """One `session.run` per weight and tuner (`sessions`: tuner name -> prepared session of one
    problem); returns the rows of the front and of the cloud, each judged on the held-out draws."""
    first_session = sessions[reference]
    problem0 = first_session.problem
    first, last = problem0.minimise[0], problem0.minimise[-1]
    order = [reference] + [n for n in sessions if n != reference]
    front, cloud = [], []
    for weight in weights:
        problem = dataclasses.replace(problem0, minimise=problem0.minimise[:-1] + (last._replace(weight=weight),))
        log(f"-- weight of {last.over} {last.metric}: {weight:g}")
        budget = driver.Budget()
        for name in order:
            # The plan's tuner ends on its own; the others (CMA-ES ends only by a budget) get its time.
            prepared = session.prepare(
                problem, sessions[name].tuner, sessions[name].options, first_session.base, budget
            )
            tuned = session.run(prepared, budget=budget, progress=True)
            if name == reference:  # the others get its time
                budget = driver.Budget(seconds=tuned.result.elapsed)
            front.append(("front", name, weight, tuned.params, tuned.verdict))
            if weight == weights[0]:  # the cloud of what held in training, once
                record = tuned.result.record
                cloud += [from_log(t, problem.names) for t, h in zip(record.thetas, record.holds) if h][:CLOUD]
    log(f"judging {len(cloud)} parameter sets of the cloud on the held-out draws ...")
    judged = (
        judge(cloud, first_session.held_out, problem0, first_session.base, first_session.options.judge_dt)
        if cloud
        else []
    )
    rows = []
    for kind, name, weight, params, v in front + [("cloud", None, None, p, v) for p, v in zip(cloud, judged)]:
        rows.append(
            {
                "kind": kind,
                "tuner": name,
                "weight": weight,
                "params": {k: float(x) for k, x in params.items()},
                "x": v.terms[-1]["value"] * scale(last.metric),
                "y": v.terms[0]["value"] * scale(first.metric),
                **v.row(),
            }
        )
    return {
        "pareto": rows,
        "varied": {"metric": last.metric, "over": last.over, "weights": list(weights)},
        "held_out_draws": {u.name: first_session.held_out[:, i].tolist() for i, u in enumerate(problem0.uncertain)},
    }


def print_front(result: dict, first, last) -> None:
    for r in result["pareto"]:
        if r["kind"] == "front":
            print(
                f"  {r['tuner']:<14} weight {r['weight']:>8g}: meets every requirement "
                f"{'yes' if r['holds'] else 'NO ':>3}, {first.over} {first.metric} {r['y']:.4g} {unit(first.metric)}, "
                f"{last.over} {last.metric} {r['x']:.4g} {unit(last.metric)}"
            )


def save(result: dict, problem, path: str, figure: str) -> None:
    """The study's result file and figure, both or neither; then the front."""
    first, last = problem.minimise[0], problem.minimise[-1]
    axis = lambda o: f"{o.over} {o.metric} over the held-out draws [{unit(o.metric)}]"
    with Outputs() as out:
        write_json(out.path(path), result)
        plot_pareto(result["pareto"], out.path(figure), axis(last), axis(first))
    print_front(result, first, last)
    print(f"wrote {path} and {figure}")
