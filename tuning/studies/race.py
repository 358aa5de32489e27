"""`coopjax tune --compare`: every registered tuner on the same problem and clock, over seeds.

All tuners solve the same problem (the same model, step, training draws and box) from the same
starting points, and each gets the wall time the reference tuner (the one `coopjax tune` runs) took
on that seed. Each runs the session `coopjax tune` runs (`tuning.session.run`), so each hands over
what its selection chooses. Compilation is done before any clock starts and reported apart. Each
tuner's running choice, its best candidate so far by the training criterion (meets every
requirement at every training draw, then lowest objective), is validated afterwards on the
validation draws with the judging step, so the curves compare what each tuner would hand over at
that moment, on draws none of them trained on.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from coopjax.io import Outputs, write_json
from tuning import driver, session
from tuning.plots import plot_race
from tuning.judging import judge
from tuning.problem import from_log

MAX_SNAPSHOTS = 24  # validated points per tuner and seed (log-spaced in time, the last always kept)


def snapshots(record: driver.Record) -> list[tuple[float, int]]:
    """(wall time, candidate index) each time the running choice changes; at most MAX_SNAPSHOTS."""
    changes, last = [], None
    for i, b in enumerate(record.best_so_far()):
        if b != last and record.holds[b]:
            changes.append((record.wall[i], b))
            last = b
    if len(changes) > MAX_SNAPSHOTS:
        keep = np.unique(np.geomspace(1, len(changes), MAX_SNAPSHOTS).astype(int) - 1)
        changes = [changes[i] for i in keep] + ([changes[-1]] if keep[-1] != len(changes) - 1 else [])
    return changes


def running_min(curve: list[tuple[float, float]]) -> list[tuple[float, float]]:
    out, best = [], math.inf
    for t, v in curve:
        best = min(best, v)
        out.append((t, best))
    return out


def time_to_reach(curve, target: float) -> float:
    """First wall time at which a running-minimum curve is at or below target (inf if never)."""
    return next((t for t, v in curve if v <= target * (1 + 1e-12)), math.inf)


BUDGETS = ("time", "trajectories")


def run(
    sessions: dict,
    reference: str,
    seeds,
    log=print,
    progress: bool = False,
    budget: str = "time",
    target: str | None = None,
) -> dict:
    """Race prepared sessions (tuner name -> `session.Session`, one problem) over `seeds`.

    Each session runs through `session.run`, as `coopjax tune` runs it: the reference to its own
    end, every other one with the reference's wall time (`budget="time"`) or as many simulated
    trajectories (`"trajectories"`); each hands over the candidate its selection chooses. The curves
    are each tuner's running choice (`snapshots`), validated afterwards. Times to reach are to
    `target`'s final validated objective (default: the first other tuner)."""
    first = sessions[reference]
    problem, base, judge_dt = first.problem, first.base, first.options.judge_dt
    names = problem.names
    masses = problem.validation_draws()
    order = [reference] + [n for n in sessions if n != reference]
    per_seed, compile_s = [], {}
    for seed in seeds:
        tuned = {}
        for name in order:
            # No round that goes on from the judge's draws (`Options.again`): only screen-SLP has one,
            # and its draws come from the judge, which the others never see. Nor a longer polish
            # (`Options.further`): the race compares each tuner's recorded run.
            options = dataclasses.replace(sessions[name].options, seed=seed, again=0, further=0)
            prepared = sessions[name]._replace(options=options)
            if name == reference:
                limit = driver.Budget()
            elif budget == "time":
                limit = driver.Budget(seconds=tuned[reference].result.elapsed)
            else:
                limit = driver.Budget(trajectories=tuned[reference].result.trajectories)
            tuned[name] = session.run(prepared, budget=limit, progress=progress and name == reference)
            compile_s[name] = max(compile_s.get(name, 0.0), tuned[name].result.compile_s)
        results = {name: t.result for name, t in tuned.items()}
        budget_s = results[reference].elapsed
        # Validate every tuner's running choices in one batch.
        flat = [
            (name, t, from_log(results[name].record.thetas[i], names))
            for name in order
            for t, i in snapshots(results[name].record)
        ]
        verdicts = judge([p for _, _, p in flat], masses, problem, base, judge_dt) if flat else []
        curves = {}
        for name in order:
            points = [(t, v.score) for (n, t, _), v in zip(flat, verdicts) if n == name]
            # The handed-over answer counts from the moment the tuner stopped.
            points.append((results[name].elapsed, tuned[name].validation.score))
            curves[name] = running_min(points)
        final = {name: c[-1][1] for name, c in curves.items()}
        chosen = {name: t.params for name, t in tuned.items()}
        judged = {name: t.verdict.row() for name, t in tuned.items()}
        others = [n for n in order if n != reference]
        target_name = target if target in results else (others[0] if others else reference)
        reach = {name: time_to_reach(c, final[target_name]) for name, c in curves.items()}
        row = {
            "seed": seed,
            "budget_s": budget_s,
            "curves": curves,
            "final": final,
            "target": target_name,
            "time_to_target": reach,
            "chosen": chosen,
            "held_out": judged,
            "evaluations": {name: len(r.record.f) for name, r in results.items()},
            "trajectories": {name: r.trajectories for name, r in results.items()},
        }
        per_seed.append(row)
        g = judged[reference]
        log(
            f"seed {seed}: {reference}'s answer on the held-out draws: meets every requirement "
            f"{'yes' if g['holds'] else 'NO'}; "
            + "; ".join(f"{r['requirement']}: worst {r['worst']:.4g} {r['unit']}" for r in g["requirements"])
            + f"; objective {g['objective']:.3f} N"
        )
        log(
            f"seed {seed}: budget {budget_s:.1f} s; validated objective "
            + ", ".join(f"{name} {final[name]:.2f} N" for name in order)
            + f"; time to {target_name}'s final: "
            + ", ".join(f"{name} {_fmt_time(reach[name])}" for name in order)
        )
    return {
        "names": list(names),
        "seeds": list(seeds),
        "tuners": order,
        "reference": reference,
        "budget": budget,
        "validation_draws": masses.tolist(),
        "held_out_draws": first.held_out.tolist(),
        "compile_s": compile_s,
        "per_seed": per_seed,
        "summary": summary(per_seed, order),
    }


def summary(per_seed: list[dict], order) -> dict:
    """Median and worst over seeds of each tuner's final validated objective and time to the target's final."""
    out = {}
    for name in order:
        finals = np.array([r["final"][name] for r in per_seed])
        reach = np.array([r["time_to_target"][name] for r in per_seed])
        out[name] = {
            "final_median": float(np.median(finals)),
            "final_worst": float(np.max(finals)),
            "time_to_target_median": float(np.median(reach)),
            "time_to_target_worst": float(np.max(reach)),
            "holds_on_seeds": int(np.isfinite(finals).sum()),
        }
    out["budget_s_median"] = float(np.median([r["budget_s"] for r in per_seed]))
    if per_seed:  # seeds on which the reference ends strictly better than the target
        ref, tgt = order[0], per_seed[0]["target"]
        out["reference_better_on_seeds"] = int(sum(r["final"][ref] < r["final"][tgt] for r in per_seed))
    return out


def _fmt_time(t: float) -> str:
    return f"{t:.1f} s" if np.isfinite(t) else "never"


def print_summary(result: dict) -> None:
    s, order = result["summary"], result["tuners"]
    target = result["per_seed"][0]["target"] if result["per_seed"] else order[0]
    kind = "wall time" if result.get("budget", "time") == "time" else "simulated trajectories (its wall time"
    print(
        f"\nrace over seeds {result['seeds']} ({len(result['names'])} parameters; each tuner gets "
        f"{result['reference']}'s "
        f"{kind}, median {s['budget_s_median']:.1f} s{')' if kind != 'wall time' else ''}; compile apart: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in result["compile_s"].items())
        + ")"
    )
    print(
        f"{'tuner':<15} {'final objective [N], median':>28} {'worst':>8} {'holds':>6} "
        f"{'time to ' + target + ' final, median':>32} {'worst':>8}"
    )
    for name in order:
        r = s[name]
        print(
            f"{name:<15} {r['final_median']:>28.2f} {r['final_worst']:>8.2f} "
            f"{r['holds_on_seeds']:>4}/{len(result['seeds'])} "
            f"{_fmt_time(r['time_to_target_median']):>32} {_fmt_time(r['time_to_target_worst']):>8}"
        )
    ref, tgt = s[result["reference"]]["time_to_target_median"], s[target]["time_to_target_median"]
    if target != result["reference"]:
        verdict = "less" if ref < tgt else "NOT less"
        print(
            f"on the median over seeds {result['reference']} reaches {target}'s final validated objective in {verdict} "
            f"wall time than {target} ({_fmt_time(ref)} against {_fmt_time(tgt)}); it ends better than {target} on "
            f"{s.get('reference_better_on_seeds', 0)} of {len(result['seeds'])} seeds"
        )


def save(result: dict, path: str, figure: str) -> None:
    """The race's result file and figure, both or neither; then its summary."""
    with Outputs() as out:
        write_json(out.path(path), result)
        plot_race(result, out.path(figure))
    print_summary(result)
    print(f"wrote {path} and {figure}")
