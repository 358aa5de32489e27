"""`coopjax tune --compare`: the gradient tuner, CMA-ES and random search on one clock, over seeds.

All three solve the same problem (`objective.terms`: the same model, step, training masses and
box), and each gets the wall time the gradient tuner took on that seed. Compilation is done before
any clock starts and reported apart. Each tuner's running choice, its best candidate so far by the
training criterion (holds at every training mass, then lowest objective), is validated afterwards
on the validation masses with the judging step, so the curves compare what each tuner would hand
over at that moment, on masses none of them trained on.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax.numpy as jnp
import numpy as np

from tuning import baselines
from tuning.objective import from_log, held_out_masses, judge, log_bounds, preferred, to_log, validation_masses
from tuning.optimize import TuneConfig, candidates, init, tune, value_and_grad_fn

TUNERS = ("gradient", "CMA-ES", "random search")
MAX_SNAPSHOTS = 24  # validated points per tuner and seed (log-spaced in time, the last always kept)


def gradient_record(state, names) -> baselines.Record:
    """The gradient tuner's evaluations as a Record: every start at every step."""
    h = state.history
    rec = baselines.Record([], [], [], [], [])
    K = len(h["f"][0]) if h["f"] else 0
    for s in range(len(h["step"])):
        for k in range(K):
            rec.thetas.append(np.asarray(h["theta"][s][k]))
            rec.f.append(h["f"][s][k] if np.isfinite(h["f"][s][k]) else math.inf)
            rec.holds.append(bool(h["holds"][s][k]))
            rec.wall.append(h["wall"][s])
            rec.trajectories.append(h["trajectories"][s])
    return rec


def snapshots(record: baselines.Record) -> list[tuple[float, int]]:
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


def run(config: TuneConfig, base, seeds, log=print, progress: bool = False) -> dict:
    problem, names = config.problem, config.problem.names
    F_lim = float(np.asarray(base.F_lim).min())
    masses = validation_masses(problem)
    held_out = held_out_masses(problem.masses)
    n = len(names)

    log("compiling the three tuners' functions (not on anyone's clock) ...")
    start = time.perf_counter()
    state0 = init(config, base)
    vg = value_and_grad_fn(problem, config.resolved_mode)
    vg(jnp.asarray(state0.theta), jnp.asarray(problem.training_masses()), state0.mult, base)[0].block_until_ready()
    compile_gradient = time.perf_counter() - start
    compile_batch = baselines.Evaluator(problem, base, F_lim).warm_up(n)

    per_seed = []
    for seed in seeds:
        cfg = dataclasses.replace(config, seed=seed)
        state = tune(cfg, base, log=lambda s: None, progress=progress)
        budget = state.elapsed
        records = {"gradient": gradient_record(state, names)}
        theta0 = np.clip(to_log(cfg.start_values, names), *log_bounds(names))
        records["CMA-ES"] = baselines.cma_es(baselines.Evaluator(problem, base, F_lim, seed), names, budget, theta0, seed)
        records["random search"] = baselines.random_search(baselines.Evaluator(problem, base, F_lim, seed), names, budget, seed)
        # Validate every tuner's running choices in one batch. The gradient tuner's last point is what
        # `coopjax tune` hands over: its selection among each start's best and final iterates.
        options = candidates(state, names)
        snaps = {name: snapshots(rec) for name, rec in records.items()}
        flat = [(name, t, from_log(records[name].thetas[i], names)) for name, s in snaps.items() for t, i in s]
        flat += [("gradient", budget, p) for p in options]
        verdicts = judge([p for _, _, p in flat], masses, base, problem.w_lag) if flat else []
        raw = {name: [] for name in records}
        for (name, t, p), v in zip(flat, verdicts):
            raw[name].append((t, v.score, p))
        last = verdicts[-len(options):]
        pick = preferred(last)  # `select`'s rule, on the verdicts already computed
        chosen = {"gradient": options[pick]}
        for name in ("CMA-ES", "random search"):
            chosen[name] = min(raw[name], key=lambda x: x[1])[2] if raw[name] else None
        raw["gradient"] = raw["gradient"][:-len(options)] + [(budget, last[pick].score, options[pick])]
        curves = {name: running_min([(t, v) for t, v, _ in c]) for name, c in raw.items()}
        finals = {name: (c[-1][1] if c else math.inf) for name, c in curves.items()}
        judged = {name: judge(p, held_out, base, problem.w_lag).row() if p else None for name, p in chosen.items()}
        reach = {name: time_to_reach(c, finals["CMA-ES"]) for name, c in curves.items()}
        row = {"seed": seed, "budget_s": budget, "curves": curves, "final": finals, "time_to_cma_final": reach,
               "chosen": chosen, "held_out": judged,
               "evaluations": {name: len(r.f) for name, r in records.items()},
               "trajectories": {name: (r.trajectories[-1] if r.trajectories else 0) for name, r in records.items()}}
        per_seed.append(row)
        g = judged["gradient"]
        log(f"seed {seed}: gradient tuner's answer on the held-out masses: holds {'yes' if g['holds'] else 'NO'}, "
            f"worst min grip {g['min_grip']:.3f} N, peak {g['peak_grip']:.2f} N, lag {g['rms_lag_mm']:.2f} mm")
        log(f"seed {seed}: budget {budget:.1f} s; validated objective " + ", ".join(
            f"{name} {finals[name]:.2f} N" for name in TUNERS) + "; time to CMA-ES's final: " + ", ".join(
            f"{name} {_fmt_time(reach[name])}" for name in TUNERS))
    return {"names": list(names), "seeds": list(seeds), "validation_masses": [float(m) for m in masses],
            "held_out_masses": [float(m) for m in held_out],
            "compile_s": {"gradient": compile_gradient, "CMA-ES and random search": compile_batch},
            "per_seed": per_seed, "summary": summary(per_seed)}


def summary(per_seed: list[dict]) -> dict:
    """Median and worst over seeds of each tuner's final validated objective and time to CMA's final."""
    out = {}
    for name in TUNERS:
        finals = np.array([r["final"][name] for r in per_seed])
        reach = np.array([r["time_to_cma_final"][name] for r in per_seed])
        out[name] = {"final_median": float(np.median(finals)), "final_worst": float(np.max(finals)),
                     "time_to_cma_final_median": float(np.median(reach)), "time_to_cma_final_worst": float(np.max(reach)),
                     "holds_on_seeds": int(np.isfinite(finals).sum())}
    out["budget_s_median"] = float(np.median([r["budget_s"] for r in per_seed]))
    return out


def _fmt_time(t: float) -> str:
    return f"{t:.1f} s" if np.isfinite(t) else "never"


def print_summary(result: dict) -> None:
    s = result["summary"]
    print(f"\nrace over seeds {result['seeds']} ({len(result['names'])} parameters; each tuner gets the gradient "
          f"tuner's wall time, median {s['budget_s_median']:.1f} s; compile apart: "
          + ", ".join(f"{k} {v:.1f} s" for k, v in result["compile_s"].items()) + ")")
    print(f"{'tuner':<15} {'final objective [N], median':>28} {'worst':>8} {'holds':>6} "
          f"{'time to CMA-ES final, median':>29} {'worst':>8}")
    for name in TUNERS:
        r = s[name]
        print(f"{name:<15} {r['final_median']:>28.2f} {r['final_worst']:>8.2f} {r['holds_on_seeds']:>4}/{len(result['seeds'])} "
              f"{_fmt_time(r['time_to_cma_final_median']):>29} {_fmt_time(r['time_to_cma_final_worst']):>8}")
    g, c = s["gradient"]["time_to_cma_final_median"], s["CMA-ES"]["time_to_cma_final_median"]
    verdict = "less" if g < c else "NOT less"
    print(f"on the median over seeds the gradient tuner reaches CMA-ES's final validated objective in {verdict} wall "
          f"time than CMA-ES ({_fmt_time(g)} against {_fmt_time(c)})")
