"""How far screen-SLP's screen gets alone: the best merit phi it finds on the training draws, per seed,
for ways of spending the same screen (`ScreenSLP` builds the draws, the box and the merit).

    python -m benchmarks.screen_study [--problem default] [--points 2048] [--seeds 0,1,2,3,4] VARIANT ...

A VARIANT is `K/SIGMA/SPREAD`: K CMA-ES runs sharing each batch of 32 (population 32 / K each; the
first from Table 1's values, the others from random points of the box), initial step SIGMA log
units, in the box x/÷ e^SPREAD around Table 1 (10: the whole search box). The first batch is 32
scrambled Sobol points of the box, as in the tool. The merit of the problem's best-known answer on
the same draws is printed first, for scale. The merit is the local solves' (the objective, priced
grip shortfall and grip margin), so it is what the screen hands them, not the judge's verdict.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
BATCH = 32


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("variants", nargs="+", help="K/SIGMA/SPREAD, e.g. 1/1/2.5 (one run, as before) 2/1/2.5")
    parser.add_argument("--problem", default="default", help="a problem of benchmarks/problems/ (file name)")
    parser.add_argument("--points", type=int, default=2048, help="points screened after the first batch")
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument(
        "--fixed-sobol",
        type=int,
        help="Sobol points per n_draws of a design over several parameters (default: the tool's)",
    )
    args = parser.parse_args(argv)
    import cma
    import jax

    jax.config.update("jax_enable_x64", True)
    import coopjax

    coopjax.use_cache()  # one CPU device, as the figures of docs/tuning.md were measured
    from scipy.stats import qmc

    from tuning import TUNERS, design
    from tuning.evaluate import Evaluator
    from tuning.problem import Problem, to_log
    from tuning.session import Options, prepare
    from tuning.tuners.base import Query

    if args.fixed_sobol:
        design.FIXED_SOBOL = args.fixed_sobol
    path = os.path.join(HERE, "problems", args.problem + ".toml")
    tuner = TUNERS["screen-SLP"]()
    session = prepare(Problem.from_toml(path), tuner, Options())
    problem = session.problem
    evaluator = Evaluator(problem, session.base, checkpoint=False)
    draws = problem.fixed_training_draws()
    lo, hi = problem.log_bounds()
    first = np.clip(to_log(session.first, problem.names), lo, hi)

    state = tuner.init(problem, first[None], 0)  # the tuner's draws and merit (`ScreenSLP._ok_phi`)

    def phi(thetas):
        """(the merit, inf where not measured; the value CMA-ES is told)"""
        ev = evaluator(Query(np.asarray(thetas), draws))
        _, ok, value = tuner._ok_phi(state, ev)
        return value, np.where(ok, value, ev.bad(1e6))

    known = json.load(open(os.path.join(HERE, "problems", "best_known.json"))).get(args.problem)
    if known:
        x = np.clip(to_log(known["params"], problem.names), lo, hi)
        print(f"{args.problem}: merit of the best known {phi(np.repeat(x[None], BATCH, 0))[0][0]:.2f} N", flush=True)

    def screen(variant: str, seed: int) -> float:
        k, sigma, spread = variant.split("/")
        k, sigma = int(k), float(sigma)
        a, b = problem.log_box_around(first, float(spread))
        x0 = [first] + [a + (b - a) * np.random.default_rng(100 * seed + j).random(len(a)) for j in range(1, k)]
        options = lambda j: {"bounds": [list(a), list(b)], "popsize": BATCH // k, "seed": 10 * seed + j + 1}
        runs = [cma.CMAEvolutionStrategy(x, sigma, options(j) | {"verbose": -9}) for j, x in enumerate(x0)]
        u = qmc.Sobol(len(a), scramble=True, seed=seed).random(BATCH)
        best = phi(a + (b - a) * u)[0].min()
        for _ in range(args.points // BATCH):
            asked = [np.asarray(es.ask()) for es in runs]
            value, told = phi(np.concatenate(asked))
            best = min(best, value.min())
            for j, es in enumerate(runs):
                es.tell(list(asked[j]), list(told[j * (BATCH // k) : (j + 1) * (BATCH // k)]))
        return float(best)

    seeds = [int(s) for s in args.seeds.split(",")]
    print(f"best merit phi over {BATCH + args.points} points, seeds {seeds} (jax {jax.__version__})")
    for variant in args.variants:
        start = time.perf_counter()
        best = [screen(variant, s) for s in seeds]
        print(
            f"{variant}: {' '.join(f'{b:.2f}' for b in best)}; median {np.median(best):.2f} "
            f"({time.perf_counter() - start:.0f} s)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
