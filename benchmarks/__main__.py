"""coopjax against what a user would otherwise write, on this machine: `python -m benchmarks [--quick]`.

Writes benchmarks/results.json and benchmarks/scaling.png, and prints a table. The carry scenario
(docs/model.md, "Scenarios") at dt = 1e-3 s, T = 4 s. Before any timing counts, every baseline is checked
against coopjax's forces in float64 (smooth switch with wide widths over the whole carry, hard
switch over the first 0.25 s, before the hard loop starts to chatter and amplify round-off).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
TOLERANCE = 1e-6  # relative, float64, for the RK4 baselines
LSODA_RTOL = 1e-8
LSODA_TOLERANCE = 1e-3  # relative: LSODA's own error at this rtol (see accuracy())


def machine() -> dict:
    info = dict(python=platform.python_version(), platform=platform.platform(), cores=os.cpu_count())
    model, mhz, flags = platform.processor() or platform.machine(), None, set()
    try:
        for line in open("/proc/cpuinfo"):
            key, _, value = line.partition(":")
            key = key.strip()
            if key == "model name":
                model = value.strip()
            elif key == "cpu MHz" and mhz is None:
                mhz = float(value)
            elif key == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    info.update(cpu=model, mhz=mhz)
    # Peak: cores x clock x FLOPs per cycle. Two 256-bit FMA pipes (AVX2 + FMA, e.g. AMD Zen, Intel
    # since Haswell) give 16 float64 / 32 float32 FLOPs per cycle. An estimate, stated as such.
    if mhz and {"avx2", "fma"} <= flags:
        info["peak_gflops_estimate"] = {
            "float64": os.cpu_count() * mhz / 1e3 * 16,
            "float32": os.cpu_count() * mhz / 1e3 * 32,
        }
        info["peak_basis"] = "cores x cpu MHz x (16 float64 | 32 float32) FLOPs/cycle: two 256-bit FMA pipes"
    import jax
    import scipy

    info.update(jax=jax.__version__, numpy=np.__version__, scipy=scipy.__version__)
    try:
        import numba

        info["numba"] = numba.__version__
    except ImportError:
        info["numba"] = None
    return info


def peer_flops(T: float) -> dict:
    """FLOP per sample-step of the strong peer's source (its own process: the count runs the source
    as Python, with numba's JIT disabled)."""
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.strong_peer", "--T", str(T)],
        cwd=os.path.dirname(HERE),
        env=env,
        stdout=subprocess.PIPE,
        text=True,
        check=True,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_child(devices: int, args, extras: bool) -> dict:
    cmd = (
        [
            sys.executable,
            "-m",
            "benchmarks.coopjax_child",
            "--devices",
            str(devices),
            "--Bs",
            args.Bs,
            "--repeats",
            str(args.repeats),
            "--T",
            str(args.T),
        ]
        + (["--extras"] if extras else [])
        + (["--quick"] if args.quick else [])
    )
    env = dict(os.environ)  # the child asks for what `use_all_cores` gives a user (XLA_FLAGS of the user's kept)
    print(f"coopjax on {devices} device(s) ...", flush=True)
    proc = subprocess.run(cmd, cwd=os.path.dirname(HERE), env=env, stdout=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"benchmark child failed ({proc.returncode})")
    lines = proc.stdout.strip().splitlines()
    for line in lines[:-1]:
        print(line)
    return json.loads(lines[-1])


def table1() -> dict:
    import coopjax as cj
    from benchmarks.implementations import PER_ROBOT, SHARED

    return {n: cj.params.PARAMETERS[n].default for n in PER_ROBOT + SHARED}


def accuracy(numba_rk4, horizon: float = 4.0, peers=None) -> dict:
    """Every baseline against coopjax in float64, before any timing counts (over `horizon` s of the
    carry scenario; --quick checks the first second only, which the smoke test needs to be cheap)."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import coopjax as cj
    from benchmarks import implementations as im

    rng = np.random.default_rng(1)
    # Wide surrogate widths: at dt = 1e-3 the narrow ones chatter on F = F_lim and amplify round-off
    # (a different but equally right order of operations then ends 1e-2 apart), which would test
    # the loop's sensitivity, not the transcription.
    params = cj.make_params(
        M_b=rng.uniform(0.5, 5.0, 4), K_GP=rng.uniform(0.3, 0.7, 4), k_F=2.0, k_c=2.0, eps_delta=1e-3
    )
    P = im.parameter_matrix(params)
    out = {}
    for switch, T in (("smooth", horizon), ("hard", 0.25)):
        n, every = int(round(T / 1e-3)), 10
        ours = np.asarray(
            cj.simulate(
                params, "carry", switch=switch, integrator="rk4", dt=1e-3, T=T, every=every, check_dt=False
            ).trajectory.aux.F
        )
        scale = np.abs(ours).max()
        out[f"numpy_{switch}"] = float(np.abs(im.numpy_rk4(P, 1e-3, n, every, switch == "smooth") - ours).max() / scale)
        if numba_rk4 is not None:
            out[f"numba_{switch}"] = float(
                np.abs(numba_rk4(P, 1e-3, n, every, switch == "smooth") - ours).max() / scale
            )
    # LSODA solves the ODE itself, so it is compared with a converged coopjax run (dt = 1e-4).
    ours = np.asarray(
        cj.simulate(cj.make_params(), "carry", switch="smooth", dt=1e-4, T=horizon, every=100).trajectory.aux.F
    )
    t_eval = np.arange(ours.shape[0]) * 1e-2
    F, _ = im.lsoda(table1(), horizon, t_eval, smooth=True, rtol=LSODA_RTOL, atol=LSODA_RTOL * 1e-3)
    out["lsoda_smooth"] = float(np.abs(F - ours).max() / np.abs(ours).max())
    out["ok"] = {k: v <= (LSODA_TOLERANCE if k.startswith("lsoda") else TOLERANCE) for k, v in out.items()}
    if peers:
        # The strong peer against coopjax's carry metrics, 1e-9 relative (`strong_peer.agreement`).
        from benchmarks.strong_peer import agreement

        rng = np.random.default_rng(2)
        B = 8
        params = cj.make_params(
            M_b=np.exp(rng.uniform(np.log(0.5), np.log(5.0), B)),
            K_GP=rng.uniform(0.05, 1.5, B),
            K_GI=rng.uniform(0.01, 0.8, B),
            tau=rng.uniform(0.2, 4.0, B),
            G_e=np.exp(rng.uniform(np.log(50.0), np.log(3000.0), B)),
        )
        for step, T in (("filippov", horizon), ("rk4", min(horizon, 1.0))):
            worst = agreement(step, params, T)
            out[f"strong_peer_{step}_metrics"] = worst
            out["ok"][f"strong_peer_{step}_metrics"] = worst <= 1e-9
    return out


def numba_threads() -> int:
    import numba

    return numba.get_num_threads()


def baselines(args, numba_rk4, peers=None) -> tuple[list, dict]:
    from benchmarks import implementations as im

    import coopjax as cj

    rows = []
    Bs = [int(b) for b in args.Bs.split(",")]
    numpy_steps = 50 if args.quick else 200
    numba_steps = 500 if args.quick else int(round(args.T / 1e-3))
    for B in Bs:
        rng = np.random.default_rng(0)
        P = im.parameter_matrix(cj.make_params(M_b=rng.uniform(0.5, 5.0, B), K_GP=rng.uniform(0.3, 0.7, B)))
        for impl, fn, steps in (("numpy", im.numpy_rk4, numpy_steps), ("numba", numba_rk4, numba_steps)):
            if fn is None:
                continue
            times = []
            for _ in range(max(1, args.repeats if impl == "numba" else min(args.repeats, 3))):
                t0 = time.perf_counter()
                fn(P, 1e-3, steps, steps)
                times.append(time.perf_counter() - t0)
            run_s = statistics.median(times)
            rows.append(
                dict(
                    impl=impl,
                    dtype="float64",
                    devices=os.cpu_count() if impl == "numba" else 1,
                    B=B,
                    steps=steps,
                    run_s=run_s,
                    steps_per_s=B * steps / run_s,
                )
            )
            print(f"  {impl} float64 B={B}: {rows[-1]['steps_per_s'] / 1e6:.3f} M steps/s ({steps} steps)", flush=True)
        for (step, dtype), peer in (peers or {}).items():
            steps = int(round(args.T / 1e-3))
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                peer(P, T_end=args.T)
                times.append(time.perf_counter() - t0)
            run_s = statistics.median(times)
            rows.append(
                dict(
                    impl="strong_peer",
                    integrator=step,
                    dtype=dtype,
                    devices=numba_threads(),
                    B=B,
                    steps=steps,
                    run_s=run_s,
                    steps_per_s=B * steps / run_s,
                )
            )
            print(f"  strong peer {step} {dtype} B={B}: {rows[-1]['steps_per_s'] / 1e6:.3f} M steps/s", flush=True)
    # LSODA: one parameter set per call, the smooth switch (the hard one makes it chatter: see README).
    p = table1()
    times = []
    for k in range(1 if args.quick else 3):
        p_k = dict(p, M_b=1.0 + k)
        t0 = time.perf_counter()
        _, nfev = im.lsoda(p_k, args.T, None, smooth=True, rtol=LSODA_RTOL, atol=LSODA_RTOL * 1e-3)
        times.append(time.perf_counter() - t0)
    lsoda = dict(seconds_per_set=statistics.median(times), rtol=LSODA_RTOL, switch="smooth", T=args.T, nfev=nfev)
    lsoda["steps_per_s_equivalent"] = round(args.T / 1e-3) / lsoda["seconds_per_set"]
    if args.lsoda_hard:  # minutes per set: the hard switch chatters and LSODA follows every switch
        t0 = time.perf_counter()
        _, nfev_hard = im.lsoda(p, args.T, None, smooth=False, rtol=1e-3, atol=1e-6)
        lsoda["hard"] = dict(seconds_per_set=time.perf_counter() - t0, rtol=1e-3, nfev=nfev_hard)
        print(f"  LSODA (hard, rtol 1e-3): {lsoda['hard']['seconds_per_set']:.1f} s for one parameter set", flush=True)
    print(f"  LSODA (smooth, rtol {LSODA_RTOL:g}): {lsoda['seconds_per_set']:.3f} s per parameter set", flush=True)
    return rows, lsoda


def plot(rows, lsoda, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from coopjax.io import atomic_path

    fig, ax = plt.subplots(figsize=(11, 5.2), constrained_layout=True)
    groups = {}
    for r in rows:
        name = f"strong peer {r['integrator']}" if r["impl"] == "strong_peer" else r["impl"]
        label = f"{name} {r['dtype']}" + (
            f", {r['devices']} device(s)"
            if r["impl"].startswith("coopjax")
            else f", {r['devices']} thread(s)"
            if r["impl"].startswith(("numba", "strong"))
            else ""
        )
        groups.setdefault(label, []).append(r)
    colours = plt.get_cmap("tab20").colors
    for j, (label, rs) in enumerate(sorted(groups.items())):
        rs = sorted(rs, key=lambda r: r["B"])
        style = "-" if label.startswith("coopjax") else "--"
        ax.loglog(
            [r["B"] for r in rs],
            [r["steps_per_s"] for r in rs],
            style,
            marker="o",
            label=label,
            color=colours[j % len(colours)],
        )
    ax.axhline(
        lsoda["steps_per_s_equivalent"], color="k", ls=":", label=f"LSODA, one set per call (rtol {lsoda['rtol']:g})"
    )
    ax.set_xlabel("batch size B (parameter sets per call)")
    ax.set_ylabel("parameter-set steps per second")
    ax.set_title(
        "carry scenario, dt = 1e-3 s, hard switch: plain RK4 (coopjax, numba, numpy, strong peer rk4) and\n"
        "the sliding-mode step (coopjax_filippov, strong peer filippov); LSODA on the smooth switch",
        fontsize=9,
    )
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def summarise(result) -> dict:
    rows = result["throughput"]

    def best(impl, dtype, B, devices=None):
        cands = [
            r
            for r in rows
            if r["impl"] == impl
            and r["dtype"] == dtype
            and r["B"] == B
            and (devices is None or r["devices"] == devices)
        ]
        return max((r["steps_per_s"] for r in cands), default=None)

    B = 4096 if any(r["B"] == 4096 for r in rows) else max(r["B"] for r in rows)
    cores = result["machine"]["cores"]
    s = {"B": B}
    for dtype in ("float32", "float64"):
        s[f"coopjax_{dtype}_1_device"] = best("coopjax", dtype, B, 1)
        s[f"coopjax_{dtype}_all_devices"] = best("coopjax", dtype, B, cores)
    s["numba_float64"] = best("numba", "float64", B)
    s["numpy_float64"] = best("numpy", "float64", B)
    top64 = max(x for x in (s["coopjax_float64_1_device"], s["coopjax_float64_all_devices"]) if x)
    if s["numba_float64"]:
        s["coopjax_over_numba_float64"] = top64 / s["numba_float64"]
    if s["numpy_float64"]:
        s["coopjax_over_numpy_float64"] = top64 / s["numpy_float64"]
    per_set = round(result["config"]["T"] / 1e-3) / top64
    s["coopjax_seconds_per_set_float64"] = per_set
    s["coopjax_over_lsoda_per_set"] = result["lsoda"]["seconds_per_set"] / per_set
    # The sliding-mode step against plain RK4, same dtype and device count.
    s["filippov_over_rk4_cost"] = {}
    for dtype in ("float32", "float64"):
        for devices in (1, cores):
            rk4, filippov = best("coopjax", dtype, B, devices), best("coopjax_filippov", dtype, B, devices)
            if rk4 and filippov:
                s["filippov_over_rk4_cost"][f"{dtype}_{devices}_device"] = rk4 / filippov
    s["rk4_steps_per_s"] = {
        f"{d}_{n}_device": best("coopjax", d, B, n) for d in ("float32", "float64") for n in (1, cores)
    }
    s["filippov_steps_per_s"] = {
        f"{d}_{n}_device": best("coopjax_filippov", d, B, n) for d in ("float32", "float64") for n in (1, cores)
    }
    # The strong peer (benchmarks/strong_peer.py), all threads, against coopjax on all devices.
    ours = {"filippov": "coopjax_filippov", "rk4": "coopjax"}
    s["strong_peer_steps_per_s"], s["coopjax_over_strong_peer"], s["fraction_of_peak"] = {}, {}, {}
    flops, peak = result.get("peer_flops", {}), result["machine"].get("peak_gflops_estimate", {})
    for step in ("filippov", "rk4"):
        for dtype in ("float32", "float64"):
            key = f"{step}_{dtype}"
            peer = max(
                (
                    r["steps_per_s"]
                    for r in rows
                    if r["impl"] == "strong_peer" and r["integrator"] == step and r["dtype"] == dtype and r["B"] == B
                ),
                default=None,
            )
            coop = best(ours[step], dtype, B, cores)
            s["strong_peer_steps_per_s"][key] = peer
            s["coopjax_over_strong_peer"][key] = coop / peer if coop and peer else None
            if step in flops and dtype in peak:  # at the peer's FLOP count per sample-step, for both
                s["fraction_of_peak"][key] = {
                    name: (rate * flops[step] / (peak[dtype] * 1e9) if rate else None)
                    for name, rate in (("coopjax", coop), ("strong_peer", peer))
                }
    s["fraction_of_peak_basis"] = (
        "FLOP per sample-step counted from the strong peer's source (python -m "
        "benchmarks.strong_peer), times sample-steps per second, over the estimated peak"
    )
    steps_per_run = round(result["config"]["T"] / 1e-3)  # filippov at dt = 1e-3 is within the accuracy tolerances
    ours_fil = s["filippov_steps_per_s"][f"float64_{cores}_device"]
    peer_fil = s["strong_peer_steps_per_s"]["filippov_float64"]
    s["converged_trajectories_per_s"] = {
        "coopjax": ours_fil / steps_per_run if ours_fil else None,
        "strong_peer": peer_fil / steps_per_run if peer_fil else None,
    }
    s["compile_s"] = {
        f"{r['impl']}_{r['dtype']}_{r['devices']}_device": r["compile_s"]
        for r in rows
        if "compile_s" in r and r["B"] == B
    }
    ratio = s["coopjax_over_strong_peer"]
    s["targets"] = {
        "strong peer filippov float64 >= 30 M steps/s": None if peer_fil is None else peer_fil >= 30e6,
        "coopjax filippov float64 (all devices) >= 0.35 x strong peer": None
        if ratio["filippov_float64"] is None
        else ratio["filippov_float64"] >= 0.35,
        "coopjax rk4 float32 (all devices) >= 0.35 x strong peer": None
        if ratio["rk4_float32"] is None
        else ratio["rk4_float32"] >= 0.35,
        "coopjax filippov float64 (all devices) >= 1.0 x strong peer": None
        if ratio["filippov_float64"] is None
        else ratio["filippov_float64"] >= 1.0,
        ">= 1e4 x LSODA per set": s["coopjax_over_lsoda_per_set"] >= 1e4,
    }
    if "gradient" in result:
        s["targets"]["forward-mode gradient <= 5 x forward"] = result["gradient"]["jacfwd_over_forward"] <= 5
    return s


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick",
        action="store_true",
        help="small sizes, one repeat, no gradient, memory or "
        "compile-time study, the strong peer in float64 only: about 3 minutes",
    )
    parser.add_argument("--Bs", default=None, help="batch sizes (default 1,64,1024,4096; quick 1,64,1024)")
    parser.add_argument(
        "--repeats", type=int, default=None, help="runs per figure, median reported (default 5; quick 1)"
    )
    parser.add_argument("--T", type=float, default=4.0, help="horizon in s (default 4, the carry scenario)")
    parser.add_argument("--lsoda-hard", action="store_true", help="also time LSODA on the hard switch (minutes)")
    parser.add_argument(
        "--max-devices", type=int, default=None, help="largest XLA CPU device count to time (default: one per core)"
    )
    parser.add_argument(
        "--out",
        default=None,
        help="results file (default benchmarks/results.json; with --quick "
        "benchmarks/results_quick.json, beside the committed full run, never over it)",
    )
    parser.add_argument(
        "--plot", default=None, help="figure (default benchmarks/scaling.png; quick: scaling_quick.png)"
    )
    args = parser.parse_args(argv)
    suffix = "_quick" if args.quick else ""
    args.out = args.out or os.path.join(HERE, f"results{suffix}.json")
    args.plot = args.plot or os.path.join(HERE, f"scaling{suffix}.png")
    args.Bs = args.Bs or ("1,64,1024" if args.quick else "1,64,1024,4096")
    args.repeats = args.repeats or (1 if args.quick else 5)
    if args.quick:
        args.T = min(args.T, 1.0)
    start = time.perf_counter()

    try:
        from benchmarks.implementations import make_numba_rk4

        numba_rk4 = make_numba_rk4()
        numba_rk4(np.ones((46, 2)), 1e-3, 2, 1)  # compile before anything is timed
    except ImportError:
        print("numba is not installed (pip install 'coopjax[bench]'): the numba baseline is skipped")
        numba_rk4 = None

    peers = {}
    if numba_rk4 is not None:  # the strong peer: numba compiles each step and dtype for minutes (docs/speed.md)
        from benchmarks.strong_peer import make_peer

        print("compiling the strong peer ...", flush=True)
        for step in ("filippov", "rk4"):
            for dtype in ("float64",) if args.quick else ("float32", "float64"):
                peers[step, dtype] = make_peer(step, dtype)
                peers[step, dtype](np.ones((46, 2)), T_end=2e-3, block=2)  # compile before anything is timed
        from benchmarks.strong_peer import vectorisation

        # Whether LLVM vectorised each peer over its samples, from its own machine code.
        vectorised = {f"{step}_{dtype}": vectorisation(peer) for (step, dtype), peer in peers.items()}
        for key, counts in vectorised.items():
            print(
                f"  strong peer {key.replace('_', ' ')}: arithmetic instructions {counts['packed_zmm']} zmm-packed, "
                f"{counts['packed_ymm']} ymm-packed, {counts['packed_xmm']} xmm-packed, {counts['scalar']} scalar "
                f"(ymm or zmm: {counts['wide_share']:.2f})"
            )

    result = dict(
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        machine=machine(),
        config=dict(scenario="carry", dt=1e-3, T=args.T, switch="hard", quick=args.quick, repeats=args.repeats),
    )
    if peers:
        result["peer_vectorisation"] = vectorised
    print("accuracy of the baselines against coopjax (float64) ...", flush=True)
    result["accuracy"] = accuracy(numba_rk4, 1.0 if args.quick else 4.0, peers)
    for name, ok in result["accuracy"]["ok"].items():
        print(f"  {name}: max relative force error {result['accuracy'][name]:.2e} {'ok' if ok else 'FAILED'}")
    if not all(result["accuracy"]["ok"].values()):
        print("a baseline disagrees with coopjax: its timings would not count; stopping", file=sys.stderr)
        return 1

    rows = []
    cores = min(os.cpu_count() or 1, args.max_devices or os.cpu_count() or 1)
    children = [run_child(1, args, extras=True)] + ([run_child(cores, args, extras=False)] if cores > 1 else [])
    for child in children:
        rows += child["throughput"]
    first = children[0]
    for key in ("gradient", "memory", "compile_vs_horizon", "flops", "flops_filippov"):
        if key in first:
            result[key] = first[key]
    result["machine"]["device_counts"] = [c["device_count"] for c in children]
    print("baselines ...", flush=True)
    base_rows, result["lsoda"] = baselines(args, numba_rk4, peers)
    if peers:
        print("counting the strong peer's FLOP per sample-step from its source ...", flush=True)
        result["peer_flops"] = peer_flops(0.2 if args.quick else args.T)
    result["throughput"] = rows + base_rows
    peak = result["machine"].get("peak_gflops_estimate")
    if peak:
        for key in ("flops", "flops_filippov"):
            if key in result:
                result[key]["peak_gflops_estimate_float32"] = peak["float32"]
                result[key]["fraction_of_peak"] = result[key]["achieved_gflops"] / peak["float32"]
    result["summary"] = summarise(result)
    result["seconds"] = time.perf_counter() - start

    from coopjax.io import atomic_path

    with atomic_path(args.out) as tmp:
        with open(tmp, "w") as f:
            json.dump(result, f, indent=1)
    plot(result["throughput"], result["lsoda"], args.plot)
    report(result)
    print(f"wrote {args.out} and {args.plot} in {result['seconds']:.0f} s")
    return 0


def report(result):
    m, s = result["machine"], result["summary"]
    print(f"\n{m['cpu']}, {m['cores']} cores, jax {m['jax']}, device counts {m['device_counts']}, numba {m['numba']}")
    print(f"{'implementation':<34} {'B':>6} {'M steps/s':>10} {'compile [s]':>12}")
    for r in sorted(
        result["throughput"], key=lambda r: (r["impl"], r.get("integrator", ""), r["dtype"], r["devices"], r["B"])
    ):
        name = f"strong_peer {r['integrator']}" if r["impl"] == "strong_peer" else r["impl"]
        label = f"{name} {r['dtype']} x{r['devices']}"
        compile_s = f"{r['compile_s']:.2f}" if "compile_s" in r else ""
        print(f"{label:<34} {r['B']:>6} {r['steps_per_s'] / 1e6:>10.3f} {compile_s:>12}")
    lsoda = result["lsoda"]
    print(
        f"{'LSODA (smooth), one set per call':<34} {1:>6} {lsoda['steps_per_s_equivalent'] / 1e6:>10.4f}"
        f"   ({lsoda['seconds_per_set']:.3f} s per set)"
    )
    g = result.get("gradient")
    if g:
        print(
            f"\nfour-gain gradient / forward (B = {g['B']}, T = {g['T']:g} s): forward mode "
            f"{g['jacfwd_over_forward']:.2f}x, "
            f"reverse mode {g['grad_over_forward']:.2f}x "
            f"(through the loop: {g.get('grad_loop_over_forward', float('nan')):.2f}x)"
        )
    for r in result.get("memory", []):
        run = f"{r['run_s']:.2f} s" if r["run_s"] else "not run"
        print(f"reverse mode, checkpoint={r['checkpoint']:<6} T={r['T']:>5g} s: {r['temp_bytes'] / 1e6:9.1f} MB, {run}")
    if "compile_vs_horizon" in result:
        print(
            "compile time: "
            + ", ".join(
                f"{r.get('integrator', '')} T={r['T']:g} s ({r['n_steps']} steps) {r['compile_s']:.2f} s"
                for r in result["compile_vs_horizon"]
            )
        )
    f = result["flops"]
    peak = f.get("peak_gflops_estimate_float32")
    print(
        f"XLA cost analysis: {f['flops_per_sample_step']:.0f} FLOP per sample-step; achieved "
        f"{f['achieved_gflops']:.1f} "
        f"GFLOP/s (float32, 1 device, B = {f['B']})"
        + (f" = {100 * f['fraction_of_peak']:.1f}% of an estimated {peak:.0f} GFLOP/s peak" if peak else "")
    )
    print(
        f"\nat B = {s['B']}: coopjax / numba (plain RK4, per-sample loops) "
        f"{s.get('coopjax_over_numba_float64', float('nan')):.2f}x, "
        f"coopjax / numpy {s.get('coopjax_over_numpy_float64', float('nan')):.1f}x, per parameter set vs LSODA "
        f"{s['coopjax_over_lsoda_per_set']:.3g}x"
    )
    for key, ratio in s["coopjax_over_strong_peer"].items():
        peak = s["fraction_of_peak"].get(key, {})
        pct = lambda x: "n/a" if x is None else f"{100 * x:.1f}%"
        share = (
            ""
            if not peak
            else (
                f"; of the CPU's peak (at the peer's FLOP count): coopjax "
                f"{pct(peak['coopjax'])}, peer {pct(peak['strong_peer'])}"
            )
        )
        print(
            f"coopjax / strong peer, {key.replace('_', ' ')}: "
            + ("not measured" if ratio is None else f"{ratio:.2f}x")
            + share
        )
    for key, cost in s["filippov_over_rk4_cost"].items():
        print(f"cost of a filippov step over a plain RK4 step, {key.replace('_', ' ')}: {cost:.2f}x")
    for target, met in s["targets"].items():
        print(f"  target {target}: {'not measured in this run' if met is None else 'met' if met else 'NOT met'}")


if __name__ == "__main__":
    sys.exit(main())
