"""Where the step's time goes: `python -m benchmarks.profile_step [--B 4096] [--dtype float32]`.

Carry scenario, hard switch, dt = 1e-3, T = 1 s, one device, XLA's default flags. For each
integrator it times, interleaved (the machine's noise is +-20 % between runs), medians of 3:

- `integrate`: the real loop (metrics and divergence bookkeeping);
- the same scan with the bookkeeping removed piece by piece;
- for plain RK4, four field evaluations per scan step: the field alone;

and prints XLA's cost analysis of one step (FLOP and bytes per sample-step).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--B", type=int, default=4096)
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    args = parser.parse_args(argv)
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    import coopjax as cj
    from coopjax import model, objectives
    from coopjax.integration import INTEGRATORS, SimConfig, integrate
    from coopjax.scenarios import SCENARIOS, Clock

    B, n, dt = args.B, 1000, 1e-3
    rng = np.random.default_rng(0)
    p = cj.make_params(M_b=np.exp(rng.uniform(np.log(0.5), np.log(5), B)), K_GP=rng.uniform(0.3, 0.7, B), dtype=args.dtype)
    scenario, options = SCENARIOS["carry"], model.Options()
    win = objectives.window(scenario, dt, 4000)

    def loop(method, metrics, divergence):
        def run(p):
            def body(carry, k):
                y, acc, bad = carry
                y_new, F, x_ref, F_impact = method.step(p, y, k.astype(y.dtype) * dt, dt, scenario, options)
                if metrics:
                    acc_new = objectives.accumulate(acc, F, x_ref, model.unpack(y)["x_r"], p, k, win, F_impact)
                else:  # the least that keeps the step's outputs alive
                    acc_new = acc.at[4].set(jnp.maximum(acc[4], F[0]))
                if divergence:
                    acc_new = jnp.where(bad[None], acc, acc_new)
                    bad = bad | ~jnp.isfinite(y_new).all(0) | (jnp.abs(F) > 1e6).any(0)
                    y_new = jnp.where(bad[None], y, y_new)
                return (y_new, acc_new, bad), None

            carry = (model.init_state(p), objectives.init(p.batch_shape, p.M_b.dtype), jnp.zeros(p.batch_shape, bool))
            return jax.lax.scan(body, carry, jnp.arange(n, dtype=jnp.int32))[0][1]

        return jax.jit(run)

    def fields_only(p):
        def body(y, k):
            d, _ = model.vector_field(p, y, Clock.at(k.astype(y.dtype) * dt / 4), scenario, options)
            return y + 1e-9 * d, None

        return jax.lax.scan(body, model.init_state(p), jnp.arange(4 * n, dtype=jnp.int32))[0]

    cases = {}
    for name, method in INTEGRATORS.items():
        config = SimConfig("carry", integrator=name, T=n * dt)
        cases[f"{name}: integrate (metrics, divergence)"] = jax.jit(lambda p, c=config: integrate(p, c).metrics.peak_grip)
        cases[f"{name}: step + metrics, no divergence"] = loop(method, True, False)
        cases[f"{name}: step + divergence, no metrics"] = loop(method, False, True)
        cases[f"{name}: step alone"] = loop(method, False, False)
    cases["rk4: 4 field evaluations, nothing else"] = jax.jit(fields_only)

    for fn in cases.values():
        jax.block_until_ready(fn(p))
    times = {k: [] for k in cases}
    for _ in range(3):
        for k, fn in cases.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(p))
            times[k].append(time.perf_counter() - t0)
    print(f"jax {jax.__version__}, {jax.device_count()} device(s), {args.dtype}, B = {B}, {n} steps, carry, hard switch")
    for k, ts in times.items():
        print(f"  {k:44s} {B * n / statistics.median(ts) / 1e6:6.2f} M steps/s")
    for name, method in INTEGRATORS.items():
        step = jax.jit(lambda p, y, t, m=method: m.step(p, y, t, dt, scenario, options)[0])
        cost = step.lower(p, model.init_state(p), jnp.asarray(0.5, p.M_b.dtype)).compile().cost_analysis()
        cost = cost[0] if isinstance(cost, (list, tuple)) else cost
        print(f"  XLA cost analysis, one {name} step: {cost.get('flops', 0) / B:.0f} FLOP and "
              f"{cost.get('bytes accessed', 0) / B / 1e3:.1f} kB per sample-step")


if __name__ == "__main__":
    main()
