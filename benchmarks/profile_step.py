"""Where coopjax's step time goes: `python -m benchmarks.profile_step [--dtype float64] [--integrator filippov]`.

Carry scenario, hard switch, dt = 1e-3, one device, XLA's flags as `coopjax.use_all_cores` sets
them. It times, per time step (medians of 5, 500 steps), at batch sizes 1, 32, 256 and 1024:

- the step alone in a `lax.scan` (no metrics, no divergence bookkeeping);
- `integrate`, the real loop (metrics, divergence).

The time at B = 1 is the part of a step that does not grow with the batch (the dispatch of its
thunks, the while loops of the pieces and stages); the growth from B = 1 to 256 (the slab one
device runs) is the part per sample: arithmetic and memory traffic. XLA's cost analysis of one
step gives its FLOP and bytes per sample-step (each while-loop body counted once).
"""

from __future__ import annotations

import argparse
import statistics
import time


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dtype", default="float64", choices=("float32", "float64"))
    parser.add_argument("--integrator", default="filippov", choices=("filippov", "rk4"))
    parser.add_argument("--steps", type=int, default=500)
    args = parser.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import coopjax as cj
    from coopjax import model

    cj.use_all_cores(1)  # one device, XLA's widest vectors as a user's program has them
    from coopjax.integration import INTEGRATORS
    from coopjax.scenarios import get
    from coopjax.simulation import metrics_of

    n, dt, scenario = args.steps, 1e-3, get("carry")
    integrator = INTEGRATORS[args.integrator]
    config = cj.Config("carry", integrator=args.integrator, dt=dt, T=n * dt, dtype=args.dtype)
    run = metrics_of(config)

    def step_alone(p):
        views = model.robots(p)

        def body(y, k):
            return integrator.step(views, y, k.astype(y.dtype) * dt, dt, scenario, config.options)[0], None

        return jax.lax.scan(body, model.init_state(p), jnp.arange(n, dtype=jnp.int32))[0]

    cases = {"step alone": jax.jit(step_alone), "integrate": jax.jit(lambda p: run(p))}
    Bs = (1, 32, 256, 1024)
    per_step = {name: [] for name in cases}
    print(f"jax {jax.__version__}, {jax.device_count()} device(s), {args.integrator}, {args.dtype}, {n} steps")
    for B in Bs:
        rng = np.random.default_rng(0)
        p = cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B), dtype=args.dtype)
        line = f"  B = {B:5d}:"
        for name, fn in cases.items():
            jax.block_until_ready(fn(p))
            times = []
            for _ in range(5):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(p))
                times.append(time.perf_counter() - t0)
            per_step[name].append(statistics.median(times) / n)
            line += f"  {name} {per_step[name][-1] * 1e6:8.1f} us/step ({B / per_step[name][-1] / 1e6:5.2f} M steps/s)"
        print(line, flush=True)
    rng = np.random.default_rng(0)
    B = Bs[-1]
    p = cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B), dtype=args.dtype)
    single = jax.jit(lambda p, y, t: integrator.step(model.robots(p), y, t, dt, scenario, config.options)[0])
    cost = single.lower(p, model.init_state(p), jnp.asarray(0.5, p.M_b.dtype)).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    flop, moved = cost.get("flops", 0.0) / B, cost.get("bytes accessed", 0.0) / B
    print(
        f"  XLA cost analysis of one step: {flop:.0f} FLOP and {moved / 1e3:.1f} kB per sample-step "
        "(while-loop bodies counted once)"
    )
    slab = Bs.index(256)  # the samples one device runs per dispatch (coopjax.devices.BLOCK)
    for name, ts in per_step.items():
        per_sample = (ts[slab] - ts[0]) / (Bs[slab] - 1)
        print(
            f"  {name}: {ts[0] * 1e6:.1f} us per step at B = 1 (the part that does not grow with the batch: "
            f"{100 * ts[0] / ts[slab]:.0f}% of a B = {Bs[slab]} step), then {per_sample * 1e9:.0f} ns per "
            f"sample-step up "
            f"to B = {Bs[slab]}; {ts[-1] / Bs[-1] * 1e9:.0f} ns at B = {Bs[-1]}"
        )


if __name__ == "__main__":
    main()
