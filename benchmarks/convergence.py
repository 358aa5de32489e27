"""Convergence of the hard carry model to its dt -> 0 limit, for `filippov` and plain `rk4`: its values,
and (with --derivatives) its derivatives.

    python -m benchmarks.convergence [--quick] [--out benchmarks/convergence.json] [--plot docs/convergence.png]
    python -m benchmarks.convergence --derivatives [--n 64] [--out benchmarks/derivatives.json]
        [--plot docs/derivatives.png]
    python -m benchmarks.convergence --readme-gradient
    python -m benchmarks.convergence --step-check [--n 2048]
    python -m benchmarks.convergence --artefact-search

The limit (docs/model.md, "Step size") is computed two independent ways that must agree within the
tolerances before anything else counts: `filippov` at dt = 1e-5 and plain `rk4` at dt = 1e-6. Then
each integrator runs at a ladder of steps, and its error against the limit is reported for min grip
(N), peak grip and RMS lag (relative). Also measured: converged carry trajectories per second, for
`filippov` at its default step against `rk4` at the largest step of the ladder where it meets the
tolerances on every sample (or its finest step, 1e-5, if none does).

The derivative study compares AD derivatives (forward mode) of min grip, peak grip, RMS lag and the
grip shortfall with respect to log K_GP, K_GI, tau and G_e, at the default and training steps, with
central secants of the converged model (filippov at `--ref-dt`, 1e-4 s) at two widths in the log gain,
1e-2 and 3e-3. An entry counts only where the two secants agree (the limit is smooth there); it
agrees where |AD - secant| <= 10 % |secant| + 0.01, both as elasticities (derivative over
max(|value|, 1 N or 1 mm)).

The step-check study runs a sweep of random gain sets and masses with and without the two-step check
(`coopjax sweep --check-step`), times both, and judges every flagged row against the limit. The
artefact search optimises against one coarse step on purpose (a cross-entropy search) and judges
its best candidates against the limit: the case tests/test_step_check.py keeps comes from it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from coopjax.step_check import TOLERANCE as _TOLERANCE

# The accuracy tolerances (docs/model.md): min grip in N, peak and lag relative.
TOLERANCE = {name: tol for name, (_, tol) in _TOLERANCE.items()}
GAIN_SETS = {
    "table1": dict(K_GP=0.5, K_GI=0.1, tau=1.25, G_e=600.0),
    "holds": dict(K_GP=0.054, K_GI=0.078, tau=2.93, G_e=1224.0),  # a four-gain set that holds the grip at every mass
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


# --- the derivative study

GAINS = ("K_GP", "K_GI", "tau", "G_e")
OUTPUTS = ("min_grip", "peak_grip", "rms_lag", "shortfall")
FLOOR = {
    "min_grip": 1.0,
    "peak_grip": 1.0,
    "rms_lag": 1e-3,
    "shortfall": 1.0,
}  # N, N, m, N: the elasticity's scale floor
SHORTFALL_EPS = 0.01  # N: shortfall = sqrt(slip + eps^2) - eps, the tuner's grip constraint
WIDTHS = (1e-2, 3e-3)  # secant half-widths in log gain
AGREE = (0.10, 0.01)  # relative, absolute (elasticity)
STUDY_DTS = (1e-3, 2e-3)  # the default and the training step
STUDY_BOX = {"K_GP": (0.05, 2.0), "K_GI": (0.01, 1.0), "tau": (0.1, 10.0), "G_e": (50.0, 3000.0)}  # log-uniform
F_LIM = 10.0  # N, Table 1's force limit: the studies do not vary it


def derivative_samples(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n (log gains, mass) samples, half of them with heavy masses (2.5-5 kg, where Table 1's gains
    lose the grip and the constraint is active), each stable at dt = 3e-3 by the linearised check
    (so both study steps run well inside RK4's region)."""
    import coopjax as cj
    from coopjax import stability

    rng = np.random.default_rng(seed)
    thetas, masses = [], []
    while len(thetas) < n:
        gains = {k: float(np.exp(rng.uniform(np.log(a), np.log(b)))) for k, (a, b) in STUDY_BOX.items()}
        low = 2.5 if len(thetas) % 2 == 0 else 0.5
        mass = float(np.exp(rng.uniform(np.log(low), np.log(5.0))))
        limit, growth = stability.stable_dt(cj.make_params(**gains, M_b=mass), cj.Config("carry"))
        if limit[0] >= 3e-3 and growth[0] == 0:
            thetas.append(np.log([gains[g] for g in GAINS]))
            masses.append(mass)
    return np.array(thetas), np.array(masses)


def study_outputs(theta, masses, dt):
    """(N, 4) outputs of the hard carry model at log gains theta (N, 4)."""
    import jax.numpy as jnp

    import coopjax as cj

    params = cj.make_params(**{g: jnp.exp(theta[:, i]) for i, g in enumerate(GAINS)}, M_b=masses)
    m = cj.simulate(params, "carry", dt=dt, check_dt=False).metrics
    shortfall = jnp.sqrt(m.slip + SHORTFALL_EPS**2) - SHORTFALL_EPS
    return jnp.stack([m.min_grip, m.peak_grip, m.rms_lag, shortfall], axis=1)


def ad_derivatives(theta, masses, dt):
    """Values (N, 4) and forward-mode derivatives (N, 4 outputs, 4 gains) at dt."""
    import jax
    import jax.numpy as jnp

    theta, masses = jnp.asarray(theta), jnp.asarray(masses)
    basis = jnp.eye(len(GAINS))[:, None, :] * jnp.ones_like(theta)[None]
    f = lambda th: study_outputs(th, masses, dt)
    values, tangents = jax.jit(jax.vmap(lambda v: jax.jvp(f, (theta,), (v,)), out_axes=(None, 0)))(basis)
    return np.asarray(values), np.moveaxis(np.asarray(tangents), 0, -1)


def secant_derivatives(theta, masses, dt, widths=WIDTHS):
    """Central secants (len(widths), N, 4 outputs, 4 gains) of the model at dt, all runs in one batch."""
    N = theta.shape[0]
    shifted = []
    for w in widths:
        for i in range(len(GAINS)):
            for sign in (1, -1):
                t = theta.copy()
                t[:, i] += sign * w
                shifted.append(t)
    values = np.asarray(study_outputs(np.concatenate(shifted), np.tile(masses, len(shifted)), dt))
    values = values.reshape(len(widths), len(GAINS), 2, N, len(OUTPUTS))
    secants = (values[:, :, 0] - values[:, :, 1]) / (2 * np.asarray(widths)[:, None, None, None])
    return np.transpose(secants, (0, 2, 3, 1))


def compare(ad: np.ndarray, secants: np.ndarray, values: np.ndarray) -> dict:
    """Elasticities, where the limit is smooth, and where AD agrees with it (module docstring)."""
    scale = np.maximum(np.abs(values), np.array([FLOOR[o] for o in OUTPUTS]))[:, :, None]
    wide, narrow = secants[0] / scale, secants[1] / scale
    smooth = np.abs(wide - narrow) <= 0.02 * np.maximum(np.abs(wide), np.abs(narrow)) + 0.002
    e = ad / scale
    agrees = np.abs(e - narrow) <= AGREE[0] * np.abs(narrow) + AGREE[1]
    wrong_sign = (np.sign(e) != np.sign(narrow)) & (np.abs(narrow) > AGREE[1]) & (np.abs(e) > AGREE[1])
    return {"ad": e, "reference": narrow, "smooth": smooth, "agrees": agrees, "wrong_sign": wrong_sign & smooth}


def derivative_study(n: int, ref_dt: float, dts=STUDY_DTS, log=print) -> dict:
    import jax

    theta, masses = derivative_samples(n)
    start = time.perf_counter()
    ref_values = np.asarray(study_outputs(theta, masses, ref_dt))
    secants = secant_derivatives(theta, masses, ref_dt)
    log(
        f"reference: central secants of filippov at dt = {ref_dt:g} s, widths {WIDTHS} in log gain "
        f"({time.perf_counter() - start:.0f} s)"
    )
    result = {
        "n": n,
        "ref_dt": ref_dt,
        "widths": WIDTHS,
        "agree": AGREE,
        "gains": GAINS,
        "outputs": OUTPUTS,
        "masses": masses.tolist(),
        "gains_log": theta.tolist(),
        "rows": [],
        "machine": {"jax": jax.__version__, "devices": jax.device_count()},
    }
    log(f"{'dt [s]':>8} {'output':>10} {'agree':>7} {'entries':>8} {'wrong sign':>11}")
    for dt in dts:
        start = time.perf_counter()
        _, ad = ad_derivatives(theta, masses, dt)
        c = compare(ad, secants, ref_values)
        elapsed = time.perf_counter() - start
        for j, name in enumerate(OUTPUTS + ("all",)):
            pick = (slice(None), slice(None)) if name == "all" else (slice(None), j)
            counted = c["smooth"][pick]
            row = {
                "dt": dt,
                "output": name,
                "entries": int(counted.sum()),
                "agree": float(c["agrees"][pick][counted].mean()),
                "wrong_sign": int(c["wrong_sign"][pick].sum()),
            }
            result["rows"].append(row)
            log(f"{dt:8g} {name:>10} {row['agree']:7.1%} {row['entries']:8d} {row['wrong_sign']:11d}")
        result[f"dt={dt:g}"] = {k: v.tolist() for k, v in c.items()} | {"seconds": elapsed}
    return result


README_TERMS = ("slip", "crush", "lag", "loss")


def readme_terms(k, dt):
    """The README's loss at K_GP = k (M_b = 1 kg) and its three terms, (len(k), 4)."""
    import jax.numpy as jnp

    import coopjax as cj

    m = cj.simulate(cj.make_params(K_GP=k), "carry", dt=dt, check_dt=False).metrics
    w = cj.Weights()
    return jnp.stack([w.slip * m.slip, w.crush * m.crush, w.lag * (m.rms_lag / w.lag_scale) ** 2, cj.loss(m, w)], -1)


def central_secants(f, x, dt, widths=WIDTHS) -> np.ndarray:
    """Central secants of f(xs, dt) (xs a batch of points) at x, one row per width."""
    import jax.numpy as jnp

    v = np.asarray(f(jnp.array([x + s * w for w in widths for s in (1, -1)]), dt))
    return np.stack([(v[2 * i] - v[2 * i + 1]) / (2 * w) for i, w in enumerate(widths)])


def readme_gradient(dts=(2e-3, 1e-3, 5e-4, 2.5e-4, 1e-4), at=0.5, log=print) -> dict:
    """d/d K_GP of the README's loss and of each term: AD at each step against central secants
    (widths 1e-2 and 3e-3 in K_GP) of the same step; the finest step's secants are the limit's slope."""
    import jax
    import jax.numpy as jnp

    rows = []
    log(f"{'dt [s]':>8} " + " ".join(f"{t + ': AD':>12} {'secants':>17}" for t in README_TERMS))
    for dt in dts:
        _, ad = jax.jvp(lambda k: readme_terms(k, dt), (jnp.array([at]),), (jnp.array([1.0]),))
        secants = central_secants(readme_terms, at, dt)
        rows.append({"dt": dt, "ad": np.asarray(ad)[0].tolist(), "secants": secants.tolist()})
        log(
            f"{dt:8g} "
            + " ".join(
                f"{float(ad[0, j]):+12.4f} {secants[0, j]:+8.4f}/{secants[1, j]:+8.4f}"
                for j in range(len(README_TERMS))
            )
        )
    return {"terms": README_TERMS, "K_GP": at, "rows": rows}


def _wrong(coarse: dict, limit: dict) -> np.ndarray:
    """Rows whose answer at a step misses the limit by more than a tolerance."""
    return ~passes(errors(coarse, limit))


def step_check_study(n: int, dt: float = 1e-3, ref_dt: float = 1e-4, log=print) -> dict:
    """A sweep of n random gain sets (the derivative study's box) and masses (0.5 to 5 kg) at dt, with
    and without the two-step check; the flagged rows against the limit (filippov at ref_dt)."""
    from coopjax import sweeps

    vary = {g: f"loguniform:{a}:{b}" for g, (a, b) in STUDY_BOX.items()} | {"M_b": "loguniform:0.5:5"}
    seconds, tables = {}, {}
    for checked in (False, True):
        spec = sweeps.make_spec("carry", n=n, vary=vary, fixed={}, seed=0, dt=dt, check_step=checked)
        start = time.perf_counter()
        tables[checked] = sweeps.run(spec)
        seconds[checked] = time.perf_counter() - start
    cols = tables[True]
    flagged = np.asarray(cols["status"]) == "step_artefact"
    passed = np.asarray(cols["status"]) == "ok"
    # Every row at the limit: what the check flags, and what it lets through.
    table = {k: np.asarray(cols[k]) for k in (*STUDY_BOX, "M_b")}
    limit = {
        k: np.asarray(v)
        for k, v in sweeps.run(
            sweeps.make_spec("carry", n=None, vary={}, fixed={}, seed=0, table=table, dt=ref_dt)
        ).items()
    }
    wrong_all = _wrong({k: np.asarray(cols[k]) for k in TOLERANCE}, limit)
    wrong = wrong_all[flagged]
    error = np.asarray(cols["step_error"], float)
    result = {
        "n": n,
        "dt": dt,
        "ref_dt": ref_dt,
        "flagged": int(flagged.sum()),
        "flagged_wrong_at_dt": int(wrong.sum()),
        "ok_wrong_at_dt": int((wrong_all & passed).sum()),
        "wrong_where_the_grip_holds": int((wrong_all & (limit["min_grip"] >= F_LIM - TOLERANCE["min_grip"])).sum()),
        "median_step_error_ok": float(np.median(error[passed])),
        "p99_step_error_ok": float(np.percentile(error[passed], 99)),
        "status_counts": {str(k): int(v) for k, v in zip(*np.unique(np.asarray(cols["status"]), return_counts=True))},
        "seconds": {"unchecked": seconds[False], "checked": seconds[True]},
    }
    log(
        f"{n} rows at dt = {dt:g}: {result['flagged']} flagged step_artefact, of which {result['flagged_wrong_at_dt']} "
        f"miss the limit (filippov at {ref_dt:g}) by more than a tolerance; of the rows ok, {result['ok_wrong_at_dt']} "
        f"miss it; {result['wrong_where_the_grip_holds']} of all that miss it hold the grip in the limit; rows "
        f"ok: median step_error "
        f"{result['median_step_error_ok']:.3g}, 99th percentile {result['p99_step_error_ok']:.3g}; statuses "
        f"{result['status_counts']}; {seconds[True]:.1f} s checked against {seconds[False]:.1f} s unchecked "
        f"(x{seconds[True] / seconds[False]:.2f}, compile included)"
    )
    return result


def artefact_search(
    dt: float = 5e-3,
    mass: float = 4.0,
    rounds: int = 4,
    population: int = 1024,
    seed: int = 0,
    ref_dts=(1e-4, 5e-5),
    log=print,
) -> dict:
    """Optimise against one step on purpose: a cross-entropy search over the 8 per-robot gains (log
    box of the derivative study) on peak + 1.5 x lag in mm, the grip held (min grip within 0.05 N of
    F_lim) and dt within the linearised stability limit, at one mass. Those of its 64 best that
    meet these are then judged against the limit (filippov at two fine steps) and by the two-step
    check."""
    import coopjax as cj
    from coopjax import stability, step_check

    names = [f"{g}_{r}" for g in STUDY_BOX for r in "LR"]
    lo = np.log([STUDY_BOX[n[:-2]][0] for n in names])
    hi = np.log([STUDY_BOX[n[:-2]][1] for n in names])
    rng = np.random.default_rng(seed)

    def metrics(x, step):
        p = cj.make_params(**{n: np.exp(x[:, i]) for i, n in enumerate(names)}, M_b=np.full(len(x), mass))
        m = cj.simulate(p, "carry", dt=step, check_dt=False).metrics
        return {k: np.asarray(getattr(m, k)) for k in ("min_grip", "peak_grip", "rms_lag", "finite")}, p

    def score(x):
        m, p = metrics(x, dt)
        limit, growth = stability.stable_dt(p, cj.Config("carry"))
        ok = (
            m["finite"]
            & (m["min_grip"] >= F_LIM - TOLERANCE["min_grip"])
            & (np.asarray(limit) >= dt)
            & (np.asarray(growth) == 0)
        )
        return np.where(ok, m["peak_grip"] + 1.5e3 * m["rms_lag"], np.inf)

    mean, spread = (lo + hi) / 2, (hi - lo) / 2
    x = rng.uniform(lo, hi, (population, len(names)))
    for r in range(rounds):
        if r:
            x = np.clip(mean + spread * rng.standard_normal((population, len(names))), lo, hi)
        s = score(x)
        order = np.argsort(s)
        elite = x[order[: population // 10]]
        mean, spread = elite.mean(0), elite.std(0) + 1e-3
    best = x[order[:64]]
    best = best[np.isfinite(s[order[:64]])]
    coarse, _ = metrics(best, dt)
    half, _ = metrics(best, dt / 2)
    limits = [metrics(best, ref)[0] for ref in ref_dts]
    wrong = _wrong(coarse, limits[0])
    flagged = step_check.artefacts(step_check.step_error(coarse, half))
    rows = []
    for i in np.nonzero(wrong | flagged)[0]:
        rows.append(
            {
                "rank": int(i),
                "gains": dict(zip(names, np.exp(best[i]).tolist())),
                "at_dt": {k: float(coarse[k][i]) for k in TOLERANCE},
                "limit": [{k: float(lim[k][i]) for k in TOLERANCE} for lim in limits],
                "wrong_at_dt": bool(wrong[i]),
                "flagged": bool(flagged[i]),
            }
        )
        log(
            f"rank {i}: at dt = {dt:g} peak {coarse['peak_grip'][i]:.1f} N, lag {coarse['rms_lag'][i] * 1e3:.2f} mm; "
            f"limit peak {limits[0]['peak_grip'][i]:.1f} N, lag {limits[0]['rms_lag'][i] * 1e3:.2f} mm; "
            f"{'wrong' if wrong[i] else 'right'} at dt, {'flagged' if flagged[i] else 'not flagged'} by the "
            f"two-step check"
        )
    log(
        f"{len(best)} best candidates at dt = {dt:g}: {int(wrong.sum())} miss the limit by more than a tolerance, "
        f"the two-step check flags {int(flagged.sum())} ({int((wrong & flagged).sum())} of the wrong ones)"
    )
    return {
        "dt": dt,
        "mass": mass,
        "candidates": len(best),
        "wrong": int(wrong.sum()),
        "flagged": int(flagged.sum()),
        "wrong_and_flagged": int((wrong & flagged).sum()),
        "rows": rows,
    }


def plot_derivatives(result: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dts = [r["dt"] for r in result["rows"] if r["output"] == "all"]
    fig, axes = plt.subplots(1, len(dts), figsize=(5.2 * len(dts), 4.8), constrained_layout=True, squeeze=False)
    colours = dict(zip(OUTPUTS, ("tab:blue", "tab:orange", "tab:green", "tab:red")))
    for ax, dt in zip(axes[0], dts):
        c = {k: np.asarray(v) for k, v in result[f"dt={dt:g}"].items() if k != "seconds"}
        for j, name in enumerate(OUTPUTS):
            s = c["smooth"][:, j]
            ax.scatter(c["reference"][:, j][s], c["ad"][:, j][s], s=9, alpha=0.7, color=colours[name], label=name)
            bad = s & ~c["agrees"][:, j]
            ax.scatter(c["reference"][:, j][bad], c["ad"][:, j][bad], s=40, facecolors="none", edgecolors="k", lw=0.8)
        lim = np.nanmax(np.abs(c["reference"][c["smooth"]])) * 1.1
        ax.plot([-lim, lim], [-lim, lim], "k:", lw=1)
        ax.set_xscale("symlog", linthresh=0.01)
        ax.set_yscale("symlog", linthresh=0.01)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        row = next(r for r in result["rows"] if r["dt"] == dt and r["output"] == "all")
        ax.set_title(
            f"AD at dt = {dt:g} s: {row['agree']:.1%} of {row['entries']} agree, {row['wrong_sign']} wrong sign",
            fontsize=10,
        )
        ax.set_xlabel(f"secant of the converged model (dt = {result['ref_dt']:g} s), elasticity")
        ax.set_ylabel("AD derivative, elasticity")
        ax.grid(True, alpha=0.3)
    axes[0][0].legend(fontsize=8, title="circled: disagrees", title_fontsize=8)
    fig.suptitle(
        f"Derivatives of the hard carry model: {result['n']} (gain set, mass) samples, d output / d log gain",
        fontsize=11,
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.convergence", description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="4 random samples, a shorter ladder, no speed figure")
    parser.add_argument("--out", default=None, help="default benchmarks/convergence.json (derivatives.json)")
    parser.add_argument("--plot", default=None, help="default docs/convergence.png (derivatives.png)")
    parser.add_argument("--batch", type=int, default=64, help="batch for the trajectories-per-second figure")
    parser.add_argument("--derivatives", action="store_true", help="the derivative study instead of the value study")
    parser.add_argument(
        "--n",
        type=int,
        default=None,
        help="derivative study: (gain set, mass) samples (default 64); step check: rows (default 2048)",
    )
    parser.add_argument("--ref-dt", type=float, default=1e-4, help="derivative study: the converged model's step")
    parser.add_argument(
        "--readme-gradient",
        action="store_true",
        help="the README's gradient example and each of its terms, AD against secants, dt 2e-3 to 1e-4",
    )
    parser.add_argument(
        "--step-check",
        action="store_true",
        help="the two-step check on a sweep of --n random rows (default 2048 here): flags, cost, against the limit",
    )
    parser.add_argument(
        "--artefact-search",
        action="store_true",
        help="optimise against dt = 5e-3 on purpose and judge the 64 best against the limit and the check",
    )
    args = parser.parse_args(argv)

    import jax

    import coopjax as cj

    cj.use_all_cores()
    jax.config.update("jax_enable_x64", True)
    if args.readme_gradient:
        readme_gradient()
        return 0
    if args.step_check or args.artefact_search:
        out = args.out or ("benchmarks/step_check.json" if args.step_check else "benchmarks/artefacts.json")
        result = step_check_study(args.n or 2048) if args.step_check else artefact_search()
        result["machine"] = {"jax": jax.__version__, "devices": jax.device_count()}
        with open(out, "w") as f:
            json.dump(result, f, indent=1)
        print(f"wrote {out}")
        return 0
    if args.derivatives:
        out, plot_path = args.out or "benchmarks/derivatives.json", args.plot or "docs/derivatives.png"
        result = derivative_study(args.n or 64, args.ref_dt)
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        with open(out, "w") as f:
            json.dump(result, f)
        plot_derivatives(result, plot_path)
        print(f"wrote {out} and {plot_path}")
        return 0
    args.out, args.plot = args.out or "benchmarks/convergence.json", args.plot or "docs/convergence.png"
    n_random = 4 if args.quick else N_RANDOM
    columns, names = samples(n_random), labels(n_random)
    ladder = {k: v[:4] if args.quick else v for k, v in LADDER.items()}

    start = time.perf_counter()
    limits = {k: run(columns, k, dt) for k, dt in LIMIT_DT.items()}
    agree = errors(limits["rk4"], limits["filippov"])
    routes_agree = passes(agree)
    print(
        f"the dt -> 0 limit: filippov at {LIMIT_DT['filippov']:g} s against rk4 at {LIMIT_DT['rk4']:g} s "
        f"({time.perf_counter() - start:.0f} s)"
    )
    print(f"{'sample':<22} {'min grip':>9} {'peak':>8} {'lag mm':>8} | {'d min':>8} {'d peak':>8} {'d lag':>8}")
    for i, name in enumerate(names):
        lim = limits["filippov"]
        print(
            f"{name:<22} {lim['min_grip'][i]:9.4f} {lim['peak_grip'][i]:8.3f} {lim['rms_lag'][i] * 1e3:8.3f} | "
            f"{agree['min_grip'][i]:8.1e} {agree['peak_grip'][i]:8.1e} {agree['rms_lag'][i]:8.1e}"
            + ("" if routes_agree[i] else "  <- routes disagree")
        )
    reference = limits["filippov"]

    study = {}
    for integrator, dts in ladder.items():
        for dt in dts:
            err = errors(run(columns, integrator, dt), reference)
            ok = passes(err) & routes_agree
            study[integrator, dt] = err
            print(
                f"{integrator:<9} dt={dt:<8g} pass {int(ok.sum())}/{int(routes_agree.sum())}  max err: "
                f"min grip {err['min_grip'].max():.2e} N, peak {err['peak_grip'].max():.2%}, lag "
                f"{err['rms_lag'].max():.2%}"
            )

    result = {
        "tolerance": TOLERANCE,
        "limit_dt": LIMIT_DT,
        "samples": [{"name": n, **{k: float(v[i]) for k, v in columns.items()}} for i, n in enumerate(names)],
        "limit": {k: v.tolist() for k, v in reference.items()},
        "routes_agree": routes_agree.tolist(),
        "route_difference": {k: v.tolist() for k, v in agree.items()},
        "study": [
            {
                "integrator": k,
                "dt": dt,
                "passes": int((passes(e) & routes_agree).sum()),
                **{f"max_{m}": float(e[m][routes_agree].max()) for m in TOLERANCE},
                **{m: e[m].tolist() for m in TOLERANCE},
            }
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
            "rk4": {
                "dt": rk4_dt,
                "converged": bool(rk4_ok),
                "per_s": trajectories_per_second("rk4", rk4_dt, args.batch, 1),
            },
        }
        speed["ratio"] = speed["filippov"]["per_s"] / speed["rk4"]["per_s"]
        result["converged_trajectories_per_s"] = {"batch": args.batch, **speed}
        print(
            f"converged carry trajectories per second (B = {args.batch}, float64, {jax.device_count()} device): "
            f"filippov at 1e-3: {speed['filippov']['per_s']:.1f}; rk4 at {rk4_dt:g}"
            f"{'' if rk4_ok else ' (not converged even there)'}: {speed['rk4']['per_s']:.3f}; ratio "
            f"{speed['ratio']:.0f}x"
        )

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

    titles = {
        "min_grip": "min grip: |error| [N]",
        "peak_grip": "peak grip: relative error",
        "rms_lag": "RMS lag: relative error",
    }
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), constrained_layout=True)
    style = {"filippov": dict(color="tab:blue", marker="o"), "rk4": dict(color="tab:red", marker="s")}
    floor = 1e-12
    for ax, metric in zip(axes, titles):
        for integrator in ("rk4", "filippov"):
            rows = [r for r in result["study"] if r["integrator"] == integrator]
            dts = np.array([r["dt"] for r in rows])
            errs = np.array([r[metric] for r in rows])[:, np.array(result["routes_agree"])]
            ax.plot(dts, np.maximum(errs.max(1), floor), label=f"{integrator}: worst sample", **style[integrator])
            ax.plot(
                dts,
                np.maximum(np.median(errs, 1), floor),
                ls="--",
                alpha=0.6,
                label=f"{integrator}: median",
                color=style[integrator]["color"],
            )
        ax.axhline(result["tolerance"][metric], color="k", ls=":", lw=1, label="tolerance")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("step dt [s]")
        ax.set_title(titles[metric])
        ax.grid(True, which="major", alpha=0.3)
    axes[0].legend(fontsize=8)
    n = int(np.sum(result["routes_agree"]))
    fig.suptitle(
        f"Hard carry model: error against the dt -> 0 limit over {n} (gain set, mass) samples "
        f"(limit: filippov at 1e-5 s = rk4 at 1e-6 s)"
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
