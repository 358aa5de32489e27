"""What a derivative costs, in primal runs: `python -m benchmarks.derivative_cost [--params all] [--lanes 8]`.

The tuner's own evaluations (tuning/evaluate.py) on the default tuning problem: the hard model under
the sliding-mode integrator at the training step, `--lanes` parameter sets x the problem's 8 training
masses in one batch, every local device. Timed after compiling, median of `--repeats`:

- values: one primal run of the batch;
- Jacobian, forward mode: every per-mass output's derivative in all n parameters, the n tangents in
  one vmapped pass (what screen-SLP asks for);
- central differences: the same Jacobian from 2n + 1 primal runs of the batch in one call (what the
  ablation screen-SLP/FD asks for);
- gradient, reverse mode: of one scalar per parameter set (the gradient tuner's augmented
  Lagrangian), under each memory policy of `coopjax.simulate`'s `checkpoint`: every step
  rematerialised (the default), segments of sqrt(n) steps checkpointed with every step inside
  rematerialised ("nested"), and segments only, their steps' intermediates stored ("segment").

Each is reported in seconds, in units of the values call, and with the working memory XLA allots
the compiled program. Writes benchmarks/derivative_cost.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="all", help="gains, per-robot or all (default all: 14)")
    parser.add_argument("--lanes", type=int, default=8, help="parameter sets in the batch (default 8)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "derivative_cost.json"))
    args = parser.parse_args(argv)

    import jax

    import numpy as np

    import coopjax as cj

    jax.config.update("jax_enable_x64", True)
    cj.use_all_cores()  # as `coopjax tune`: every core, and XLA's widest vectors
    from tuning import constrained
    from tuning.evaluate import Evaluator
    from tuning.problem import Problem, expand_params
    from tuning.training import starting_points
    from tuning.tuners import Query
    from tuning.tuners.adam import AdamAL

    names = expand_params(args.params)
    problem = Problem(names=names).validate()
    base = cj.make_params()
    first = {n: float(np.asarray(base.get(n)).ravel()[0]) for n in names}
    thetas = starting_points(problem, base, first, args.lanes, 1.0, 0)
    masses = problem.fixed_training_draws()
    n, K = len(names), args.lanes
    shifts = np.concatenate([np.zeros((1, n)), 1e-3 * np.eye(n), -1e-3 * np.eye(n)])
    mult = constrained.init((K, problem.n_constraints(len(masses))), 10.0)
    gradient = Query(thetas, masses, "gradient", "reverse", mult)
    queries = {
        "values": (Query(thetas, masses), True),
        "jacobian (forward, n tangents vmapped)": (Query(thetas, masses, "jacobian"), True),
        f"central differences ({2 * n + 1} runs)": (
            Query((thetas[:, None] + shifts[None]).reshape(-1, n), masses),
            True,
        ),
        "gradient (reverse, every step remat.)": (gradient, True),
        "gradient (reverse, nested segments)": (gradient, "nested"),
        "gradient (reverse, segments only)": (gradient, "segment"),
    }
    rows = {}
    for label, (query, checkpoint) in queries.items():
        evaluator = Evaluator(problem, base, AdamAL.scalar, checkpoint)
        start = time.perf_counter()
        evaluator.warm_up(query)
        compile_s = time.perf_counter() - start
        # The run programs this query compiled (the problem's algebra beside them is small).
        runs = [program for key, program in evaluator.programs.items() if key[0] == "runs"]
        memory = max((p.memory_analysis() for p in runs), key=lambda m: m.temp_size_in_bytes, default=None)
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            evaluator(query)
            times.append(time.perf_counter() - start)
        rows[label] = {
            "median_s": statistics.median(times),
            "compile_s": compile_s,
            "temp_MB": memory.temp_size_in_bytes / 1e6 if memory is not None else float("nan"),
        }
    unit = rows["values"]["median_s"]
    print(
        f"jax {jax.__version__}, {jax.device_count()} devices; {n} parameters, {K} sets x {len(masses)} masses, "
        f"dt = {problem.configs[0].dt:g} s, median of {args.repeats}"
    )
    print(
        f"{'evaluation':<40} {'median [s]':>11} {'primal runs':>12} {'per parameter':>14} {'compile [s]':>12} "
        f"{'memory [MB]':>12}"
    )
    for label, row in rows.items():
        row["primal_runs"] = row["median_s"] / unit
        print(
            f"{label:<40} {row['median_s']:>11.3f} {row['primal_runs']:>12.1f} {row['primal_runs'] / n:>14.2f} "
            f"{row['compile_s']:>12.1f} {row['temp_MB']:>12.1f}"
        )
    with open(args.out, "w") as f:
        json.dump(
            {
                "jax": jax.__version__,
                "devices": jax.device_count(),
                "params": n,
                "lanes": K,
                "masses": len(masses),
                "dt": problem.configs[0].dt,
                "rows": rows,
            },
            f,
            indent=1,
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
