"""Forward throughput of the carry scenario: parameter-set steps per second.

    python benchmarks/throughput.py [--B 4096] [--repeats 5] [--x64]

Compile time is measured apart (`lower(...).compile()`), runs wait with `block_until_ready`, and
the figure is the median over repeats. It also times the alternative layout the design chose
against: `jax.vmap` over a single-sample (20,) state instead of one (20, B) carry.
"""

import argparse
import os
import platform
import statistics
import time


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--B", type=int, default=4096)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--x64", action="store_true")
    parser.add_argument("--dt", type=float, default=1e-3)
    args = parser.parse_args()

    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import numpy as np

    import coopjax as cj
    from coopjax.integration import SimConfig, integrate
    from coopjax.model import Options

    rng = np.random.default_rng(0)
    params = cj.make_params(M_b=rng.uniform(0.5, 5.0, args.B), K_GP=rng.uniform(0.3, 0.7, args.B))
    config = SimConfig("carry", Options(), dt=args.dt)
    steps = config.n_steps

    def vmapped(p):
        # One sample per vmap lane, each with batch shape (1,), then flattened back.
        single = jax.tree_util.tree_map(lambda x: x[..., None], p)
        return integrate(single, config).metrics

    in_axes = jax.tree_util.tree_map(lambda x: x.ndim - 1, params)
    layouts = {
        "(20, B) carry": jax.jit(lambda p: integrate(p, config).metrics),
        "vmap over (20,)": jax.jit(jax.vmap(vmapped, in_axes=(in_axes,), out_axes=0)),
    }
    print(f"jax {jax.__version__}, devices {jax.devices()}, cpu {platform.processor() or platform.machine()}, "
          f"cores {os.cpu_count()}, {'float64' if args.x64 else 'float32'}, B = {args.B}, {steps} steps")
    results = {}
    for name, fn in layouts.items():
        t0 = time.perf_counter()
        compiled = fn.lower(params).compile()
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(params))
            times.append(time.perf_counter() - t0)
        run = statistics.median(times)
        results[name] = args.B * steps / run
        print(f"{name:>16}: compile {compile_s:6.2f} s, run median {run:7.3f} s, "
              f"{results[name] / 1e6:7.2f} M parameter-set steps/s")
    a, b = results.values()
    print(f"ratio (20, B) carry / vmap: {a / b:.2f}")


if __name__ == "__main__":
    main()
