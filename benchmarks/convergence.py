"""Convergence of the hard carry model to its dt -> 0 limit, for `filippov` and plain `rk4`.

    python -m benchmarks.convergence [--quick] [--out benchmarks/convergence.json] [--plot docs/convergence.png]

The limit (docs/model.md, "Step size") is computed two independent ways that must agree within the
tolerances before anything else counts: `filippov` at dt = 1e-5 and plain `rk4` at dt = 1e-6. Then
each integrator runs at a ladder of steps, and its error against the limit is reported for min grip
(N), peak grip and RMS lag (relative). Also measured: converged carry trajectories per second, for
`filippov` at its default step against `rk4` at the largest step of the ladder where it meets the
tolerances on every sample (or its finest step, 1e-5, if none does).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

# The accuracy tolerances (docs/model.md): min grip in N, peak and lag relative.
TOLERANCE = {"min_grip": 0.05, "peak_grip": 0.02, "rms_lag": 0.02}
GAIN_SETS = {
    "table1": dict(K_GP=0.5, K_GI=0.1, tau=1.25, G_e=600.0),
    "holds": dict(K_GP=0.054, K_GI=0.078, tau=2.93, G_e=1224.0),  # issue 11's best known four-gain set
}
MASSES = (0.5, 1.2, 2.5, 5.0)
N_RANDOM = 8
LADDER = {"filippov": (2e-3, 1e-3, 5e-4, 2.5e-4, 1e-4, 5e-5, 2e-5), "rk4": (1e-3, 5e-4, 2.5e-4, 1e-4, 5e-5, 2e-5, 1e-5)}
LIMIT_DT = {"filippov": 1e-5, "rk4": 1e-6}


def samples(n_random: int = N_RANDOM, seed: int = 1) -> dict[str, np.ndarray]:
    """Fixed (gain set x mass) samples plus random gain sets and masses, as parameter columns.

    Random gains are drawn log-uniformly from a box in which dt = 1e-3 passes the stability check
    for most draws (K_GP 0.05-2 1/N, K_GI 0.01-1 1/(N s), tau 0.1-10 1/s, G_e 50-3000 1/s).
    """
    rows = [dict(**gains, M_b=m) for gains in GAIN_SETS.values() for m in MASSES]
    rng = np.random.default_rng(seed)
    box = {"K_GP": (0.05, 2.0), "K_GI": (0.01, 1.0), "tau": (0.1, 10.0), "G_e": (50.0, 3000.0), "M_b": (0.5, 5.0)}
    for _ in range(n_random):
        rows.append({k: float(np.exp(rng.uniform(np.log(a), np.log(b)))) for k, (a, b) in box.items()})
    return {k: np.array([r[k] for r in rows]) for k in rows[0]}


def labels(n_random: int = N_RANDOM) -> list[str]:
    return [f"{g} M_b={m:g}" for g in GAIN_SETS for m in MASSES] + [f"random {i}" for i in range(n_random)]


def run(columns: dict, integrator: str, dt: float) -> dict[str, np.ndarray]:
    import coopjax as cj

    m = cj.simulate(cj.make_params(**columns), "carry", integrator=integrator, dt=dt, check_dt=False).metrics
    return {k: np.asarray(getattr(m, k), np.float64) for k in ("min_grip", "peak_grip", "rms_lag", "finite")}


def errors(got: dict, limit: dict) -> dict[str, np.ndarray]:
    return {
        "min_grip": np.abs(got["min_grip"] - limit["min_grip"]),
        "peak_grip": np.abs(got["peak_grip"] / limit["peak_grip"] - 1),
        "rms_lag": np.abs(got["rms_lag"] / limit["rms_lag"] - 1),
    }


def passes(err: dict) -> np.ndarray:
    return np.all([err[k] <= TOLERANCE[k] for k in TOLERANCE], axis=0)


def trajectories_per_second(integrator: str, dt: float, batch: int, repeats: int) -> float:
    """Carry runs per second (hard model, float64, metrics only), compile time excluded."""
    import jax

    import coopjax as cj
    from coopjax.simulation import metrics_of

    run = metrics_of(cj.Config("carry", integrator=integrator, dt=dt))
    params = cj.make_params(M_b=np.geomspace(0.5, 5.0, batch))
    compiled = jax.jit(lambda p: run(p)).lower(params).compile()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(params))
        times.append(time.perf_counter() - start)
    return batch / float(np.median(times))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.convergence", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="4 random samples, a shorter ladder, no speed figure")
    parser.add_argument("--out", default="benchmarks/convergence.json")
    parser.add_argument("--plot", default="docs/convergence.png")
    parser.add_argument("--batch", type=int, default=64, help="batch for the trajectories-per-second figure")
    args = parser.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    n_random = 4 if args.quick else N_RANDOM
    columns, names = samples(n_random), labels(n_random)
    ladder = {k: v[:4] if args.quick else v for k, v in LADDER.items()}

    start = time.perf_counter()
    limits = {k: run(columns, k, dt) for k, dt in LIMIT_DT.items()}
    agree = errors(limits["rk4"], limits["filippov"])
    routes_agree = passes(agree)
    print(f"the dt -> 0 limit: filippov at {LIMIT_DT['filippov']:g} s against rk4 at {LIMIT_DT['rk4']:g} s "
          f"({time.perf_counter() - start:.0f} s)")
    print(f"{'sample':<22} {'min grip':>9} {'peak':>8} {'lag mm':>8} | {'d min':>8} {'d peak':>8} {'d lag':>8}")
    for i, name in enumerate(names):
        lim = limits["filippov"]
        print(f"{name:<22} {lim['min_grip'][i]:9.4f} {lim['peak_grip'][i]:8.3f} {lim['rms_lag'][i] * 1e3:8.3f} | "
              f"{agree['min_grip'][i]:8.1e} {agree['peak_grip'][i]:8.1e} {agree['rms_lag'][i]:8.1e}"
              + ("" if routes_agree[i] else "  <- routes disagree"))
    reference = limits["filippov"]

    study = {}
    for integrator, dts in ladder.items():
        for dt in dts:
            err = errors(run(columns, integrator, dt), reference)
            ok = passes(err) & routes_agree
            study[integrator, dt] = err
            print(f"{integrator:<9} dt={dt:<8g} pass {int(ok.sum())}/{int(routes_agree.sum())}  max err: "
                  f"min grip {err['min_grip'].max():.2e} N, peak {err['peak_grip'].max():.2%}, lag {err['rms_lag'].max():.2%}")

    result = {
        "tolerance": TOLERANCE,
        "limit_dt": LIMIT_DT,
        "samples": [{"name": n, **{k: float(v[i]) for k, v in columns.items()}} for i, n in enumerate(names)],
        "limit": {k: v.tolist() for k, v in reference.items()},
        "routes_agree": routes_agree.tolist(),
        "route_difference": {k: v.tolist() for k, v in agree.items()},
        "study": [
            {"integrator": k, "dt": dt, "passes": int((passes(e) & routes_agree).sum()),
             **{f"max_{m}": float(e[m][routes_agree].max()) for m in TOLERANCE},
             **{m: e[m].tolist() for m in TOLERANCE}}
            for (k, dt), e in study.items()
        ],
        "machine": {"jax": jax.__version__, "devices": jax.device_count()},
    }
    if not args.quick:
        counted = int(routes_agree.sum())
        rk4_ok = [dt for dt in ladder["rk4"] if (passes(study["rk4", dt]) & routes_agree).sum() == counted]
        rk4_dt = max(rk4_ok) if rk4_ok else min(ladder["rk4"])
        speed = {
            "filippov": {"dt": 1e-3, "per_s": trajectories_per_second("filippov", 1e-3, args.batch, 3)},
            "rk4": {"dt": rk4_dt, "converged": bool(rk4_ok), "per_s": trajectories_per_second("rk4", rk4_dt, args.batch, 1)},
        }
        speed["ratio"] = speed["filippov"]["per_s"] / speed["rk4"]["per_s"]
        result["converged_trajectories_per_s"] = {"batch": args.batch, **speed}
        print(f"converged carry trajectories per second (B = {args.batch}, float64, {jax.device_count()} device): "
              f"filippov at 1e-3: {speed['filippov']['per_s']:.1f}; rk4 at {rk4_dt:g}"
              f"{'' if rk4_ok else ' (not converged even there)'}: {speed['rk4']['per_s']:.3f}; ratio {speed['ratio']:.0f}x")

    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    plot(result, args.plot)
    print(f"wrote {args.out} and {args.plot}")
    return 0


def plot(result: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    titles = {"min_grip": "min grip: |error| [N]", "peak_grip": "peak grip: relative error", "rms_lag": "RMS lag: relative error"}
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), constrained_layout=True)
    style = {"filippov": dict(color="tab:blue", marker="o"), "rk4": dict(color="tab:red", marker="s")}
    floor = 1e-12
    for ax, metric in zip(axes, titles):
        for integrator in ("rk4", "filippov"):
            rows = [r for r in result["study"] if r["integrator"] == integrator]
            dts = np.array([r["dt"] for r in rows])
            errs = np.array([r[metric] for r in rows])[:, np.array(result["routes_agree"])]
            ax.plot(dts, np.maximum(errs.max(1), floor), label=f"{integrator}: worst sample", **style[integrator])
            ax.plot(dts, np.maximum(np.median(errs, 1), floor), ls="--", alpha=0.6, label=f"{integrator}: median",
                    color=style[integrator]["color"])
        ax.axhline(result["tolerance"][metric], color="k", ls=":", lw=1, label="tolerance")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("step dt [s]")
        ax.set_title(titles[metric])
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(fontsize=8)
    n = int(np.sum(result["routes_agree"]))
    fig.suptitle(f"Hard carry model: error against the dt -> 0 limit over {n} (gain set, mass) samples "
                 f"(limit: filippov at 1e-5 s = rk4 at 1e-6 s)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
