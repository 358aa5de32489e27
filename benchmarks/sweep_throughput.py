"""Sweep throughput on 1 and on all CPU devices, through the sweep runner (per-sample step check
included), for plain RK4 and the sliding-mode step.

    python benchmarks/sweep_throughput.py [--B 4096] [--repeats 5]

Carry scenario, dt = 1e-3, hard switch, XLA's flags as `use_all_cores` sets them. Each device
count runs in its own process, because the count is fixed once JAX starts. Compile time is
reported apart; runs are medians and wait for the result; the 2-device / 1-device ratio is taken
in this one invocation.
"""

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, statistics, sys, time
import jax
import coopjax as cj
devices, B, repeats = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
x64, integrator = sys.argv[4] == "1", sys.argv[5]
cj.use_all_cores(devices)
jax.config.update("jax_enable_x64", x64)
import numpy as np
from coopjax import sweeps
vary = {"M_b": "loguniform:0.5:5", "K_GP": "uniform:0.3:0.7"}
spec = sweeps.make_spec("carry", n=B, vary=vary, integrator=integrator)
values = sweeps.sample_values(spec)
t0 = time.perf_counter(); sweeps.evaluate(spec, values); first = time.perf_counter() - t0
times = []
for _ in range(repeats):
    t0 = time.perf_counter(); sweeps.evaluate(spec, values); times.append(time.perf_counter() - t0)
run = statistics.median(times)
print(json.dumps(dict(devices=devices, x64=x64, integrator=integrator, first_call_s=first, compile_s=first - run,
                      run_s=run, steps_per_s=B * spec.config.n_steps / run, jax=jax.__version__)))
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--B", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    results = []
    for integrator in ("rk4", "filippov"):
        for x64 in (0, 1):
            for devices in (1, os.cpu_count() or 1):
                out = subprocess.run(
                    [sys.executable, "-c", CHILD, str(devices), str(args.B), str(args.repeats), str(x64), integrator],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                r = json.loads(out.stdout.strip().splitlines()[-1])
                results.append(r)
                print(
                    f"{integrator} {'float64' if x64 else 'float32'}, {devices} device(s): compile "
                    f"~{r['compile_s']:.2f} s, "
                    f"run median {r['run_s']:.3f} s, {r['steps_per_s'] / 1e6:.2f} M parameter-set steps/s"
                )
            one, many = results[-2], results[-1]
            print(f"  ratio {many['devices']} devices / 1 device: {many['steps_per_s'] / one['steps_per_s']:.2f}")
    print(f"jax {results[0]['jax']}, cores {os.cpu_count()}, B = {args.B}, 4000 steps")


if __name__ == "__main__":
    main()
