"""The sliding-mode step's time-loop carry as one (20, B) array or as named (B,) rows:
`python -m benchmarks.carry_layout [--dtypes float64,float32] [--Bs 256,1024] [--rounds 5]`.

The step works on `filippov.Rows` inside (split once on entry, joined once on exit); carried as rows,
the time loop does neither. Each layout runs the step alone in a `lax.scan` (carry scenario, hard
switch, dt = 1e-3, 1000 steps, one device, XLA's flags as `coopjax.use_all_cores` sets them). The
two are checked bit for bit first, then timed in turn, `--rounds` times each: medians, and their
ratio (rows over array) from the same process.
"""

from __future__ import annotations

import argparse
import statistics
import time


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dtypes", default="float64,float32")
    parser.add_argument("--Bs", default="256,1024")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=1000)
    args = parser.parse_args(argv)

    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    import coopjax as cj
    from coopjax import model

    cj.use_all_cores(1)
    from coopjax.integration import filippov
    from coopjax.scenarios import get

    n, dt, scenario = args.steps, 1e-3, get("carry")
    options = cj.Config("carry", integrator="filippov", dt=dt, T=n * dt).options
    ks = jnp.arange(n, dtype=jnp.int32)

    def as_array(p):
        views = model.robots(p)

        def body(y, k):
            return filippov.step(views, y, k.astype(y.dtype) * dt, dt, scenario, options)[0], None

        return jax.lax.scan(body, model.init_state(p), ks)[0]

    def as_rows(p):
        views = model.robots(p)

        def body(rows, k):
            t = k.astype(rows.body["x_o"].dtype) * dt
            return filippov.step_rows(views, rows, t, dt, scenario, options)[0], None

        return jax.lax.scan(body, filippov.Rows.of(model.init_state(p)), ks)[0].array()

    devices = jax.device_count()
    print(f"jax {jax.__version__}, {devices} device(s), sliding-mode step, {n} steps, medians of {args.rounds}")
    for dtype in args.dtypes.split(","):
        for B in map(int, args.Bs.split(",")):
            rng = np.random.default_rng(0)
            p = cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B), dtype=dtype)
            fns = {"array": jax.jit(as_array), "rows": jax.jit(as_rows)}
            finals = {name: np.asarray(fn(p)) for name, fn in fns.items()}
            if not np.array_equal(finals["array"], finals["rows"], equal_nan=True):
                raise SystemExit(f"{dtype} B = {B}: the two layouts' final states differ")
            times = {name: [] for name in fns}
            for _ in range(args.rounds):
                for name, fn in fns.items():
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(p))
                    times[name].append(time.perf_counter() - t0)
            med = {name: statistics.median(ts) for name, ts in times.items()}
            rates = "  ".join(f"{name} {B * n / m / 1e6:.2f} M steps/s" for name, m in med.items())
            ratio = med["array"] / med["rows"]
            print(f"  {dtype} B = {B:5d}: {rates}  rows / array {ratio:.2f} (same bits)", flush=True)


if __name__ == "__main__":
    main()
