"""The example problems of docs/problems/, end to end: each tuned by `coopjax tune --problem` with the
default method and budget and an empty compile cache, its verdict as `tuned.json` writes it, and
each requirement's worst value again from a judgement at half the judge's step.

    python -m benchmarks.problem_examples [--out DIR] [NAME ...]

Prints the table of docs/tuning.md ("The example problems"); the runs' files stay in DIR.
"""

from __future__ import annotations

import argparse
import os
import sys

from benchmarks.problem_suite import problem_files, tune  # one `coopjax tune --problem` with nothing cached (cache "")

ROOT = os.path.join(os.path.dirname(__file__), "..")


def half_step(result: dict, path: str):
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from tuning import judging as judgement
    from tuning.problem import Problem

    problem = Problem.from_toml(path)
    draws = np.column_stack([result["held_out_draws"][u.name] for u in problem.uncertain])
    return judgement.judge(result["params"], draws, problem, dt=judgement.JUDGE_DT / 2, check_step=False)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="example names (default: every file of docs/problems/)")
    parser.add_argument("--out", default="problem_examples", help="folder of the runs' files")
    args = parser.parse_args(argv)
    paths = problem_files(os.path.join(ROOT, "docs", "problems"), args.names)
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for path in paths:
        name = os.path.basename(path)[:-5]
        result, wall, code, _ = tune(path, os.path.join(args.out, name + ".json"), "", ("--quiet",))
        half = half_step(result, path)
        for r, h in zip(result["requirements"], half.requirements):
            scale, unit = (1e3, "mm") if r["unit"] == "m" else (1.0, r["unit"])
            rows.append(
                f"| {name} | {r['requirement']} | {r['worst'] * scale:.4g} {unit} | {r['margin'] * scale:+.3g} | "
                f"{'met' if r['met'] else 'MISSED'} | {h['worst'] * scale:.4g} |"
            )
        terms = ", ".join(
            f"{t['over']} {t['metric']} {t['value'] * (1e3 if 'lag' in t['metric'] else 1):.4g}"
            for t in result["after"]["terms"]
        )
        rows.append(
            f"| {name} | objective: {terms} | {result['after']['objective']:.4g} N | | exit {code}, "
            f"{'holds' if result['holds'] else 'misses'} | {half.objective:.4g} N |"
        )
        rows.append(f"| {name} | time, nothing cached | {wall:.0f} s in all | | | |")
        print(rows[-3:], file=sys.stderr)
    print("| problem | requirement | worst over the held-out draws | margin | verdict | at dt/2 |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
