"""The README derivative's first call: `python -m benchmarks.first_gradient [--repeats 2] [--mode all]`.

The README's loss (carry, hard switch, the sliding-mode step at dt = 1e-3, default dtype), its value
and its derivative in K_GP in one jitted program, in forward mode (`jax.jvp`, as the README's
`jax.jacfwd`) and in reverse mode (`jax.value_and_grad`), the latter with the default adjoint
(the pull-back through a forward-mode Jacobian) and with `adjoint="reverse"` (the transpose of
the time loop). Each run is a fresh Python process with
`coopjax.use_cache()` on a folder of its own: a first run with the folder empty, then the same
program again, which loads what the first compiled. It prints, per run, the time from the call to
the first derivative and its parts: tracing (`jit(...).trace`), lowering to StableHLO, XLA's
compile (or the cache's load) and the first run; then the medians. Import time is apart. The
processes run one after another on all cores (`use_all_cores`).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

CHILD = """
import json, sys, time
import jax
import coopjax as cj
cj.use_all_cores()
cj.use_cache(sys.argv[1])
adjoint = "reverse" if sys.argv[2] == "reverse-loop" else "auto"
loss = lambda k: cj.loss(cj.simulate(cj.make_params(K_GP=k), "carry", adjoint=adjoint).metrics)
if sys.argv[2] == "forward":
    grad = jax.jit(lambda k: jax.jvp(loss, (k,), (jax.numpy.ones_like(k),)))
else:
    grad = jax.jit(jax.value_and_grad(loss))
t0 = time.perf_counter()
traced = grad.trace(0.5)
t1 = time.perf_counter()
lowered = traced.lower()
t2 = time.perf_counter()
compiled = lowered.compile()
t3 = time.perf_counter()
value, slope = jax.block_until_ready(compiled(0.5))
t4 = time.perf_counter()
print(json.dumps(dict(trace=t1 - t0, lower=t2 - t1, compile=t3 - t2, run=t4 - t3, total=t4 - t0, slope=float(slope))))
"""
MODES = ("forward", "reverse", "reverse-loop")
PARTS = ("total", "trace", "lower", "compile", "run")


def child(folder: str, mode: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    done = subprocess.run([sys.executable, "-c", CHILD, folder, mode], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"the measuring process failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2, help="pairs of runs (empty cache, then cached)")
    parser.add_argument(
        "--mode",
        default="all",
        choices=(*MODES, "all"),
        help="reverse: value_and_grad with the default adjoint; reverse-loop: with adjoint='reverse'",
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    import jax

    modes = MODES if args.mode == "all" else (args.mode,)
    rows = {(m, c): [] for m in modes for c in ("empty cache", "cached")}
    for _ in range(args.repeats):  # the modes in turn, so that both see the same machine
        for mode in modes:
            with tempfile.TemporaryDirectory() as folder:
                rows[mode, "empty cache"].append(child(folder, mode))
                rows[mode, "cached"].append(child(folder, mode))
    print(f"jax {jax.__version__}, {os.cpu_count()} cores; seconds from the call to the first derivative")
    print(f"{'':26}" + "".join(f"{p:>10}" for p in PARTS))
    for (mode, cache), runs in rows.items():
        for row in runs:
            print(f"{mode + ', ' + cache:26}" + "".join(f"{row[p]:10.1f}" for p in PARTS))
        print(f"{'  median':26}" + "".join(f"{statistics.median(r[p] for r in runs):10.1f}" for p in PARTS))
    for mode in modes:
        slopes = sorted({row["slope"] for (m, _), runs in rows.items() if m == mode for row in runs})
        print(f"{mode}: d loss / d K_GP = {', '.join(map(repr, slopes))}")


if __name__ == "__main__":
    main()
