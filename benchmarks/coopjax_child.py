"""coopjax's side of the benchmark, in its own process (the CPU device count is fixed at JAX start).

    python -m benchmarks.coopjax_child --devices D [--quick] [--extras]

Prints one JSON object as its last line. Every figure is a median over repeats, compile time is
measured apart (`lower(...).compile()`), and every run waits with `block_until_ready`.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time


def timed(compiled, *args, repeats):
    import jax

    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def compile_timed(fn, *args):
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    return compiled, time.perf_counter() - t0


def make_batch(B, dtype):
    import numpy as np

    import coopjax as cj

    rng = np.random.default_rng(0)
    return cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B), dtype=dtype)


IMPL = {"rk4": "coopjax", "filippov": "coopjax_filippov"}  # the NumPy and numba peers are plain RK4


def throughput(Bs, dtypes, devices, repeats, T):
    """Forward parameter-set steps per second, carry, hard switch, dt = 1e-3, sharded over devices,
    for plain RK4 and for the sliding-mode step."""
    import jax

    import coopjax as cj
    from coopjax import devices as dispatch
    from coopjax.simulation import metrics_of

    rows = []
    for integrator, dtype, B in ((i, d, B) for i in IMPL for d in dtypes for B in Bs):
        config = cj.Config("carry", integrator=integrator, dt=1e-3, T=T, dtype=dtype)
        if B % devices:  # a batch that does not split evenly is the 1-device child's figure
            continue
        params = make_batch(B, dtype)
        used = devices
        # As `simulate` runs it (`coopjax.devices.run`): each device its own slice, in blocks.
        compiled = lambda p: dispatch.run(metrics_of(config), p)  # as `simulate` cuts the batch
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params))  # compiles, then runs once
        first = time.perf_counter() - t0
        run_s = timed(compiled, params, repeats=repeats)
        compile_s = max(first - run_s, 0.0)
        rows.append(
            dict(
                impl=IMPL[integrator],
                integrator=integrator,
                dtype=dtype,
                devices=used,
                B=B,
                steps=config.n_steps,
                compile_s=compile_s,
                run_s=run_s,
                steps_per_s=B * config.n_steps / run_s,
            )
        )
        print(
            f"  coopjax {integrator} {dtype} {used} device(s) B={B}: {rows[-1]['steps_per_s'] / 1e6:.2f} M steps/s",
            flush=True,
        )
    return rows


def gradient_cost(B, repeats, T):
    """Time of the four-gain derivatives over one forward run (smooth switch, float64): forward mode,
    reverse mode with the default adjoint, and reverse mode through the loop."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import coopjax as cj
    from coopjax.simulation import metrics_of

    config = cj.Config("carry", switch="smooth", dt=1e-3, T=T)
    masses = jnp.asarray(np.geomspace(0.5, 5.0, B))
    names = ("K_GP", "K_GI", "tau", "G_e")

    def loss(theta, adjoint="auto"):
        gains = {n: jnp.broadcast_to(jnp.exp(theta[i]), (B,)) for i, n in enumerate(names)}
        return cj.loss(metrics_of(config, adjoint=adjoint)(cj.make_params(M_b=masses, **gains))).mean()

    theta = jnp.log(jnp.array([0.5, 0.1, 1.25, 600.0]))
    out = {}
    programs = (
        ("forward", loss),
        ("jacfwd", jax.jacfwd(loss)),
        ("grad", jax.grad(loss)),  # pulled back through the forward-mode Jacobian (8 components)
        ("grad_loop", jax.grad(lambda th: loss(th, "reverse"))),  # transposed through the time loop
    )
    for name, fn in programs:
        compiled, compile_s = compile_timed(jax.jit(fn), theta)
        jax.block_until_ready(compiled(theta))
        out[name] = dict(run_s=timed(compiled, theta, repeats=repeats), compile_s=compile_s)
    return dict(
        B=B,
        T=T,
        switch="smooth",
        dtype="float64",
        **out,
        jacfwd_over_forward=out["jacfwd"]["run_s"] / out["forward"]["run_s"],
        grad_over_forward=out["grad"]["run_s"] / out["forward"]["run_s"],
        grad_loop_over_forward=out["grad_loop"]["run_s"] / out["forward"]["run_s"],
    )


def memory(B, horizons, repeats):
    """Reverse-mode temporary memory (XLA's analysis of the compiled gradient) and run time, with
    the gradient transposed through the time loop (`adjoint="reverse"`), whose memory `checkpoint` sets."""
    import jax
    import jax.numpy as jnp

    import coopjax as cj
    from coopjax.simulation import metrics_of

    rows = []
    for checkpoint in (False, True, "nested"):
        for T in horizons:
            run = metrics_of(cj.Config("carry", switch="smooth", dt=1e-3, T=T), checkpoint, "reverse")
            loss = lambda k: cj.loss(run(cj.make_params(K_GP=k, M_b=jnp.linspace(0.5, 5.0, B)))).mean()
            compiled, compile_s = compile_timed(jax.jit(jax.grad(loss)), 0.5)
            temp = compiled.memory_analysis().temp_size_in_bytes
            run_s = None
            if temp < 4e9:  # run only what fits comfortably in this machine's memory
                jax.block_until_ready(compiled(0.5))
                run_s = timed(compiled, 0.5, repeats=repeats)
            rows.append(
                dict(checkpoint=str(checkpoint), T=T, B=B, temp_bytes=int(temp), run_s=run_s, compile_s=compile_s)
            )
            print(
                f"  grad, checkpoint={checkpoint}, T={T:g} s: {temp / 1e6:.1f} MB, "
                f"{'%.2f s' % run_s if run_s else 'not run'}",
                flush=True,
            )
    return rows


def compile_vs_horizon(horizons):
    import jax

    import coopjax as cj
    from coopjax.simulation import metrics_of

    params = make_batch(64, "float32")
    rows = []
    for integrator in IMPL:
        for T in horizons:
            config = cj.Config("carry", integrator=integrator, dt=1e-3, T=T)
            run = metrics_of(config)
            _, compile_s = compile_timed(jax.jit(lambda p: run(p)), params)
            rows.append(dict(integrator=integrator, T=T, n_steps=config.n_steps, compile_s=compile_s))
    return rows


def flops(B, steps_per_s, integrator="rk4"):
    """XLA's cost analysis of one step at batch B, and the rate it implies at the measured speed."""
    import jax

    import coopjax as cj
    from coopjax.integration import step
    from coopjax.model import init_state

    params = make_batch(B, "float32")
    config = cj.Config("carry", integrator=integrator, dt=1e-3)
    y = init_state(params)
    compiled = jax.jit(lambda p, y, t: step(p, y, t, config)).lower(params, y, 0.5).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    per_step = float(cost.get("flops", 0.0))
    moved = float(cost.get("bytes accessed", 0.0))
    calls = steps_per_s / B
    return dict(
        B=B,
        flops_per_batch_step=per_step,
        flops_per_sample_step=per_step / B,
        bytes_per_batch_step=moved,
        achieved_gflops=per_step * calls / 1e9,
        achieved_gbytes_per_s=moved * calls / 1e9,
    )


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--devices", type=int, default=1)
    parser.add_argument("--Bs", default="1,64,1024,4096,16384")
    parser.add_argument("--dtypes", default="float32,float64")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--T", type=float, default=4.0)
    parser.add_argument("--extras", action="store_true", help="also gradient cost, memory, compile time, FLOPs")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()

    import jax

    import coopjax as cj

    cj.use_all_cores(args.devices)  # as a user's program: its devices, and XLA's widest vectors
    jax.config.update("jax_enable_x64", True)  # float32 runs ask for float32 explicitly
    Bs = [int(b) for b in args.Bs.split(",")]
    result = dict(
        jax=jax.__version__,
        device_count=jax.device_count(),
        throughput=throughput(Bs, args.dtypes.split(","), args.devices, args.repeats, args.T),
    )
    if args.extras:
        quick, T = args.quick, args.T
        if not quick:  # gradient and shape studies: several extra compilations each, left to the full run
            print("  gradient cost ...", flush=True)
            result["gradient"] = gradient_cost(64, args.repeats, T)
            print("  reverse-mode memory ...", flush=True)
            result["memory"] = memory(8, (T, 10 * T), 3)
            result["compile_vs_horizon"] = compile_vs_horizon((T / 10, T, 10 * T))
        for integrator, key in (("rk4", "flops"), ("filippov", "flops_filippov")):
            best = max(
                (r for r in result["throughput"] if r["dtype"] == "float32" and r["integrator"] == integrator),
                key=lambda r: r["B"],
            )
            result[key] = flops(best["B"], best["steps_per_s"], integrator)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
