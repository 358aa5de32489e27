"""The best-known answer of each problem of benchmarks/problems/, by a long search independent of the
tuner: CMA-ES (the `cma` package) with IPOP restarts from several seeds, on a dense design of the
uncertain parameters, every candidate judged by the hard model at the training step and half of it
(the worse counts); the best ones then judged again on a fresh dense design at dt, dt/2 and dt/4.

    python -m benchmarks.best_known [--minutes 20] [--seeds 3] [--starts-from DIR] [NAME ...]

A best-known answer is the best this search found, a bound on what can be reached, not a proof of
the optimum. The answers go to benchmarks/problems/best_known.json (merged: other problems' entries
are kept), each with how it was found. A problem's recorded answer is judged again with the search's
best ones, and stays where the search found nothing better (its entry then says so). Searches of
different problems can run at the same time (the file is locked while it is rewritten).

The merit is lexicographic in effect: 1e4 per unit of `Verdict.unmeasured` (a run that diverged or
could not be run), then 1e3 per unit of the worst relative violation of a requirement, then the
objective (N). So on a feasible problem the search first reaches the feasible set, and on an
infeasible one it finds the least violation.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import time
from types import SimpleNamespace

import numpy as np

from benchmarks.problem_suite import ladder, problem_files, steps, worst_over_steps

HERE = os.path.dirname(os.path.abspath(__file__))
PROBLEMS = os.path.join(HERE, "problems")
OUT = os.path.join(PROBLEMS, "best_known.json")
SEARCH_COUNT = 16  # search draws: a grid with its ends (one parameter), or corners + 16 Sobol points
SEARCH_SEED = 606
# The search judges at the training step (the hard model's coarsest converged step over the
# problem's scenarios: 2e-3 s on the carry) and half of it; the answers are judged again at the
# judge's step, half and a quarter of it.
KEEP = 6  # distinct best candidates judged again on the fresh dense design


def merit(v) -> float:
    objective = v.objective if np.isfinite(v.objective) else 1e4
    return 1e4 * v.unmeasured + 1e3 * v.violation + objective


def search(
    problem, minutes: float, seeds: int, known: list[dict] = (), recorded: dict | None = None, log=print
) -> dict:
    import cma

    from tuning import design
    from tuning.judging import judge
    from tuning.problem import to_log

    lo, hi = problem.log_bounds()
    base = problem.base()
    first = np.clip(
        to_log({n: float(np.asarray(base.get(n)).ravel()[0]) for n in problem.names}, problem.names), lo, hi
    )
    draws = design.dense(problem.uncertain, SEARCH_COUNT, SEARCH_SEED)
    search_dt = min(c.dt for c in problem.configs)
    end = time.perf_counter() + 60 * minutes
    per_seed = 60 * minutes / seeds
    # Answers found by others (the tool's, with --starts-from): each starts one restart, with a small step.
    others = [np.clip(to_log(k, problem.names), lo, hi) for k in known]
    archive: list[tuple[float, np.ndarray]] = []
    evaluations = restarts = generations = 0
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        stop_seed = min(end, time.perf_counter() + per_seed)
        popsize = 4 + int(3 * np.log(len(lo)))
        run = 0
        while time.perf_counter() < stop_seed:
            sigma = float(min(2.0, 0.3 * np.mean(hi - lo)))
            if seed == 0 and run == 0:
                x0 = first
            elif run == 0 and others:
                x0, sigma = others.pop(0), 0.3
            else:
                x0 = lo + (hi - lo) * rng.random(len(lo))
            es = cma.CMAEvolutionStrategy(
                x0,
                sigma,
                {"bounds": [lo, hi], "popsize": popsize, "seed": 1000 * seed + run + 1, "verbose": -9},
            )
            while not es.stop() and time.perf_counter() < stop_seed:
                xs = es.ask()
                sets = [_values(problem, x) for x in xs]
                # At the search step and half of it, the worse: a search is drawn to the points where
                # one step's grid misses an event, and a value that moves with the step is no answer.
                values = np.maximum(
                    *(
                        [merit(v) for v in judge(sets, draws, problem, base, dt, check_step=False)]
                        for dt in (search_dt, search_dt / 2)
                    )
                ).tolist()
                es.tell(xs, values)
                archive += [(m, np.asarray(x)) for m, x in zip(values, xs)]
                evaluations += len(xs)
                generations += 1
            best = min(archive, key=lambda a: a[0])[0]
            log(f"  seed {seed} run {run} (population {popsize}): {es.countiter} generations, best merit {best:.5g}")
            restarts += 1
            run += 1
            popsize *= 2
    # The best distinct candidates, judged again on a fresh dense design at dt, dt/2 and dt/4.
    archive.sort(key=lambda a: a[0])
    kept: list[np.ndarray] = []
    for _, x in archive:
        if all(np.abs(x - k).max() > 1e-3 for k in kept):
            kept.append(x)
        if len(kept) == KEEP:
            break
    kept += [np.clip(to_log(k, problem.names), lo, hi) for k in known]
    # The recorded best known is judged with them: a shorter search or an earlier answer can be better.
    candidates = [_values(problem, x) for x in kept] + ([recorded["params"]] if recorded else [])
    entry = final(problem, candidates)
    entry["search"] = {
        "method": "CMA-ES with IPOP restarts (cma), merit 1e4 x unmeasured + 1e3 x relative violation + objective, "
        "the worse of search_dt and search_dt / 2",
        "minutes": minutes,
        "seeds": seeds,
        "restarts": restarts,
        "generations": generations,
        "evaluations": evaluations,
        "search_draws": len(draws),
        "search_dt": search_dt,
        "started_from_others": len(known),
        "judged_draws": len(design.dense(problem.uncertain)),
        "judged_dt": steps(),
        "found_by": "search" if entry["index"] < len(kept) - len(known) else "an answer given (--starts-from)",
    }
    if entry["index"] == len(kept):  # the recorded one stays: this search found nothing better
        old = recorded.get("search", {})
        entry["search"]["found_by"] = (
            f"the recorded best known, not beaten by this search ({old.get('found_by', 'search')})"
        )
    entry.pop("index")
    return entry


def final(problem, candidates: list[dict]) -> dict:
    """The best of `candidates` judged on a fresh dense design at dt (with the two-step check), dt/2
    and dt/4, each counted at its worst of the three (`problem_suite.worst_over_steps`), in the
    judge's order (`tuning.judging.preferred`), as an entry of best_known.json."""
    from tuning import design
    from tuning.judging import preferred

    judged = ladder(candidates, design.dense(problem.uncertain), problem)
    worst = [worst_over_steps([s[i] for s in judged]) for i in range(len(candidates))]
    i = preferred([SimpleNamespace(**w) for w in worst])  # reads holds, unmeasured, violation, objective
    v, w = judged[0][i], worst[i]
    return {
        "index": i,
        "params": candidates[i],
        "feasible": w["holds"],
        "objective": w["objective"],
        "violation": w["violation"],
        "binding": None if v.binding is None else v.binding["requirement"],
        "requirements": [
            {k: r[k] for k in ("requirement", "worst", "bound_value", "margin", "met")} for r in v.requirements
        ],
        "step_error": v.step_error,
    }


def _values(problem, x) -> dict:
    return {n: float(np.exp(v)) for n, v in zip(problem.names, x)}


def save(name: str, entry: dict) -> None:
    """Write one problem's entry into best_known.json (atomically; other problems' entries kept, also
    those that searches running at the same time write: the file is locked while it is rewritten)."""
    with open(OUT + ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        known = json.load(open(OUT)) if os.path.exists(OUT) else {}
        known[name] = entry
        with open(OUT + ".tmp", "w") as f:
            json.dump(known, f, indent=1, sort_keys=True)
        os.replace(OUT + ".tmp", OUT)


def merge(paths: list[str], folders: list[str]) -> int:
    """Each problem's recorded best known and the answers of `folders` (NAME.json), judged by `final`:
    the best is kept, and the recorded one, where it stays, with its values judged now."""
    from tuning import design
    from tuning.problem import Problem

    known = json.load(open(OUT)) if os.path.exists(OUT) else {}
    for path in paths:
        name = os.path.basename(path)[:-5]
        sources = [(f, os.path.join(f, name + ".json")) for f in folders]
        sources = [(f, json.load(open(p))) for f, p in sources if os.path.exists(p)]
        sources = [(f"at seed {t['config']['seed']} (`{f}`)", t["params"]) for f, t in sources]
        old = known.get(name)
        candidates = ([old["params"]] if old else []) + [params for _, params in sources]
        if not candidates:
            continue
        problem = Problem.from_toml(path)
        entry = final(problem, candidates)
        i = entry.pop("index")
        judged = {"judged_dt": steps(), "judged_draws": len(design.dense(problem.uncertain))}
        if old and i == 0:  # it stays, with its values as the judge reads them now
            entry["search"] = old.get("search", {}) | judged
            save(name, entry)
            print(
                f"{name}: the recorded best-known stays ({old['objective']:.5g} N, judged now {entry['objective']:.5g})"
            )
            continue
        origin = sources[i - (1 if old else 0)][0]
        entry["search"] = (old or {}).get("search", {}) | judged | {"found_by": f"coopjax tune's answer {origin}"}
        save(name, entry)
        print(
            f"{name}: the answer {origin} is better: objective {entry['objective']:.5g} N, feasible {entry['feasible']}"
        )
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="problem names (default: every file of benchmarks/problems/)")
    parser.add_argument("--minutes", type=float, default=20.0, help="search time per problem")
    parser.add_argument("--seeds", type=int, default=3, help="seeds, each given an equal share of the time")
    parser.add_argument(
        "--starts-from", help="a folder of `coopjax tune` results (NAME.json) whose answers also start a restart"
    )
    parser.add_argument(
        "--merge",
        nargs="+",
        metavar="DIR",
        help="no search: judge the answers of these folders of `coopjax tune` results (NAME.json) with the "
        "recorded best-known one on the fresh dense design, and keep the best (its entry says where it came from)",
    )
    args = parser.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from tuning.problem import Problem

    paths = problem_files(PROBLEMS, args.names)
    if args.merge:
        return merge(paths, args.merge)
    for path in paths:
        name = os.path.basename(path)[:-5]
        print(f"{name}: searching {args.minutes:g} min, {args.seeds} seeds ...", flush=True)
        start = time.perf_counter()
        known = []
        if args.starts_from and os.path.exists(os.path.join(args.starts_from, name + ".json")):
            known = [json.load(open(os.path.join(args.starts_from, name + ".json")))["params"]]
        recorded = json.load(open(OUT)).get(name) if os.path.exists(OUT) else None
        entry = search(Problem.from_toml(path), args.minutes, args.seeds, known, recorded)
        entry["search"]["wall_s"] = round(time.perf_counter() - start, 1)
        save(name, entry)
        state = (
            "feasible" if entry["feasible"] else f"infeasible ({entry['binding']}, violation {entry['violation']:.4g})"
        )
        print(f"{name}: objective {entry['objective']:.5g} N, {state}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
