"""The tuning problems of benchmarks/problems/, each solved by `coopjax tune --problem` at the default
method and budget, and judged apart from the tuner: on a dense, fresh design of the uncertain
parameters (`tuning.design.dense`: none of the tuner's draws), at the judge's step and at half of
it and a quarter of it (each value the worst of the three), after a search between the draws for
each requirement's worst case (`tuning.judging.worst_case`).

    python -m benchmarks.problem_suite [--out DIR] [--cached] [NAME ...]

Per problem: solved (every requirement met on the dense design, at dt, dt/2 and dt/4), the objective
against the best-known answer (benchmarks/problems/best_known.json, `python -m benchmarks.best_known`),
the least violation where the problem is infeasible, the exit code and the requirement the command
named, and the wall time with an empty compile cache (and with it filled by that run: `--cached`).
Writes DIR/suite.json and prints the table of docs/tuning.md ("The problem suite").
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
PROBLEMS = os.path.join(HERE, "problems")


def tune(path: str, out: str, cache: str, extra=(), tool: str | None = None) -> tuple[dict, float, int, str]:
    """One `coopjax tune --problem` with its compile cache in `cache` (`tool`: the coopjax checkout
    to run instead of this one): (result, wall s, exit, stdout)."""
    start = time.perf_counter()
    env = os.environ | {"COOPJAX_CACHE": cache} | ({"PYTHONPATH": tool} if tool else {})
    # In the tool's folder: `python -m` puts the working folder ahead of PYTHONPATH, so a run started
    # from another checkout would import that one's code.
    done = subprocess.run(
        [sys.executable, "-m", "coopjax.cli", "tune", "--problem", os.path.abspath(path)]
        + ["--out", os.path.abspath(out), *extra],
        cwd=tool,
        env=env,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - start
    if done.returncode not in (0, 3):
        raise SystemExit(f"{path}: exit {done.returncode}\n{done.stderr[-3000:]}")
    return json.load(open(out)), wall, done.returncode, done.stdout


# The judge's step and its halves. A value that moves between them is not yet the dt -> 0 limit's
# (an event the grid does not resolve): each answer is counted at its worst over the three. At dt the
# two-step check runs, and a draw it flags reads the first of dt/2, dt/4, ... that agrees with its
# half (the judge's refinement): one grid's miss of an event is not the model's value.
HALVINGS = (1, 2, 4)


def steps() -> list[float]:
    """The judge's steps of `HALVINGS`, s."""
    from tuning.judging import JUDGE_DT

    return [JUDGE_DT / r for r in HALVINGS]


def ladder(sets: list[dict], draws, problem, extra=None) -> list[list]:
    """Per step of `steps()`, the verdicts of `sets` on `draws` (and `extra`); at the judge's step
    with the two-step check, so that a step artefact does not hold."""
    from tuning.judging import judge

    return [
        judge(list(sets), draws, problem, dt=dt, check_step=r == 1, extra=extra) for r, dt in zip(HALVINGS, steps())
    ]


def worst_over_steps(verdicts: list) -> dict:
    """One answer's verdicts at the steps of `HALVINGS`, counted at their worst."""
    return {
        "holds": all(v.holds for v in verdicts),
        "objective": max(v.objective for v in verdicts),
        "violation": max(v.violation for v in verdicts),
        "unmeasured": max(v.unmeasured for v in verdicts),
    }


def judged(params: dict, problem) -> dict:
    """The dense, fresh judgement of one answer, with the worst cases found between the draws added:
    at dt (with the two-step check), dt/2 and dt/4, each value the worst of the three."""
    from tuning import design
    from tuning.judging import judge, worst_case

    draws = design.dense(problem.uncertain)
    first = judge(params, draws, problem, check_step=True)
    extra = worst_case(params, draws, problem, verdict=first)
    judged = [vs[0] for vs in ladder([params], draws, problem, extra)]
    v, half, quarter = judged
    worst = worst_over_steps(judged)
    return {
        "solved": worst["holds"],
        "objective": worst["objective"],
        "objective_half": half.objective,
        "violation": worst["violation"],
        "violation_steps": [s.violation for s in judged],
        "unmeasured": worst["unmeasured"],
        "binding": None if v.binding is None else v.binding["requirement"],
        "requirements": [
            {k: r[k] for k in ("requirement", "worst", "margin", "met")}
            | {"worst_half": h["worst"], "worst_quarter": q["worst"]}
            for r, h, q in zip(v.requirements, half.requirements, quarter.requirements)
        ],
        "step_error": v.step_error,
        "draws": len(draws) + len(extra),
        "found_between": len(extra),
    }


def problem_files(folder: str, names=()) -> list[str]:
    """The problem files of `folder`, sorted; only those of `names` (file names without .toml) if given."""
    paths = sorted(glob.glob(os.path.join(folder, "*.toml")))
    return [p for p in paths if os.path.basename(p)[:-5] in names] if names else paths


def named(stdout: str) -> str:
    """The command's own line on what an answer misses (empty when it holds)."""
    return next((line for line in stdout.splitlines() if line.startswith("the answer written misses")), "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="problem names (default: every file of benchmarks/problems/)")
    parser.add_argument("--out", default="problem_suite", help="folder of the runs' files")
    parser.add_argument("--cached", action="store_true", help="run each problem again with its compile cache filled")
    parser.add_argument("--seed", type=int, default=0, help="the tuner's seed")
    parser.add_argument("--tool", help="a coopjax checkout whose command solves the problems (default: this one)")
    parser.add_argument(
        "--table", action="store_true", help="run nothing: print the table of DIR/suite.json against best_known.json"
    )
    args = parser.parse_args(argv)
    import jax

    import coopjax

    coopjax.use_all_cores()  # the judging runs here, between the commands, on every core
    jax.config.update("jax_enable_x64", True)
    from tuning.problem import Problem

    known_path = os.path.join(PROBLEMS, "best_known.json")
    known = json.load(open(known_path)) if os.path.exists(known_path) else {}
    if args.table:
        rows = [compare(r, known.get(r["problem"])) for r in json.load(open(os.path.join(args.out, "suite.json")))]
        print(table(rows))
        return 0
    paths = problem_files(PROBLEMS, args.names)
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for path in paths:
        name = os.path.basename(path)[:-5]
        problem = Problem.from_toml(path)
        out = os.path.join(args.out, name + ".json")
        with tempfile.TemporaryDirectory() as cache:
            extra = ("--seed", str(args.seed))
            result, cold, code, stdout = tune(path, out, cache, extra, args.tool)
            cached = tune(path, out + ".cached.json", cache, extra, args.tool)[1] if args.cached else None
        row = {"problem": name, "exit": code, "named": named(stdout), "cold_s": cold, "cached_s": cached}
        row |= judged(result["params"], problem)
        rows.append(compare(row, known.get(name)))
        print(json.dumps(row), file=sys.stderr, flush=True)
        with open(os.path.join(args.out, "suite.json"), "w") as f:
            json.dump(rows, f, indent=1)
    print(table(rows))
    return 0


def compare(row: dict, best: dict | None) -> dict:
    """The row with its best-known objective (feasible problems) or least violation (infeasible)."""
    if best:
        row["best_known"] = best["objective"] if best["feasible"] else None
        row["best_violation"] = None if best["feasible"] else best["violation"]
        row["ratio"] = row["objective"] / best["objective"] if best["feasible"] and row["solved"] else None
        row["violation_ratio"] = (
            row["violation"] / best["violation"] if not best["feasible"] and best["violation"] > 0 else None
        )
    return row


def table(rows: list[dict]) -> str:
    fmt = lambda x, spec: "" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)
    lines = [
        "| problem | solved | objective (N) | best known | ratio | least violation (best known) | exit "
        "| cold s | cached s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        violation = "" if r["solved"] else f"{r['violation']:.3g} ({fmt(r.get('best_violation'), '.3g')})"
        lines.append(
            f"| {r['problem']} | {'yes' if r['solved'] else 'no'} | {fmt(r['objective'], '.4g')} | "
            f"{fmt(r.get('best_known'), '.4g')} | {fmt(r.get('ratio'), '.3f')} | {violation} | {r['exit']} | "
            f"{r['cold_s']:.0f} | {fmt(r['cached_s'], '.0f')} |"
        )
    ratios = [r["ratio"] for r in rows if r.get("ratio") is not None]
    if ratios:
        lines.append("")
        lines.append(
            f"solved {sum(r['solved'] for r in rows if r.get('best_known') is not None)} of "
            f"{sum(r.get('best_known') is not None for r in rows)} feasible; objective / best known: median "
            f"{statistics.median(ratios):.3f}, worst {max(ratios):.3f}"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
