"""Figures: the paper's Fig. 6 (grip forces) with gain-modulation and tracking panels."""

from __future__ import annotations

import numpy as np

from coopjax.errors import InputError
from coopjax.io import atomic_path
from coopjax.params import PARAMETERS, split_name
from coopjax.stability import rk4_amplification
from coopjax.status import Status
from coopjax.sweeps import column_units


def _pyplot():
    """pyplot on the non-interactive backend (figures are only written to files)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path):
    """Write the figure atomically in the format its extension names, then free it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.rsplit(".", 1)[-1].lower())
    _pyplot().close(fig)


def plot_run(trajectory, params, scenario: str, path: str, title: str | None = None, peak: float | None = None) -> None:
    """Grip forces, gamma and positions against time. Pass every step (a decimated trajectory can
    hide an impact spike); `peak` marks the metrics' peak, which includes located impacts between steps."""
    plt = _pyplot()
    t = np.asarray(trajectory.t)
    F = np.asarray(trajectory.aux.F)
    gamma = np.asarray(trajectory.aux.gamma)
    x_ref = np.asarray(trajectory.aux.x_ref)
    F_lim = np.asarray(params.F_lim)
    colours = {"L": "tab:blue", "R": "tab:red"}

    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True, constrained_layout=True)
    ax = axes[0]
    for i, r in enumerate("LR"):
        ax.plot(t, F[:, i], color=colours[r], label=f"gripper {r}")
    ax.axhline(F_lim[0], color="k", ls="--", lw=1, label=f"F_lim = {F_lim[0]:g} N")
    if peak is not None and np.isfinite(peak):
        k = np.unravel_index(np.nanargmax(F), F.shape)
        ax.plot(
            [t[k[0]]],
            [peak],
            "v",
            color="k",
            ms=7,
            label=f"peak {peak:.4g} N (impact located between steps)"
            if peak > F[k] * (1 + 1e-9)
            else f"peak {peak:.4g} N",
        )
    if scenario == "carry":
        F_max = float(np.asarray(params.F_max))
        ax.axhline(F_max, color="grey", ls=":", lw=1, label=f"F_max = {F_max:g} N")
    ax.set_ylabel("grip force on body [N]")
    ax.set_title(title or f"{scenario} scenario: grip forces (cf. the paper's Fig. 6)")
    ax.legend(loc="best", fontsize=8)

    ax = axes[1]
    for i, r in enumerate("LR"):
        ax.plot(t, gamma[:, i], color=colours[r], label=f"gamma {r}")
    ax.axhline(1.0, color="k", lw=0.5)
    ax.set_ylabel("gamma (Eq. 8; its time average while sliding)")
    ax.legend(loc="best", fontsize=8)

    ax = axes[2]
    for i, r in enumerate("LR"):
        ax.plot(t, trajectory.state(f"x_r_{r}"), color=colours[r], label=f"tip {r}")
        ax.plot(t, x_ref[:, i], color=colours[r], ls="--", lw=1, label=f"reference {r}")
    ax.plot(t, trajectory.state("x_o"), color="k", label="body x_o")
    ax.set_ylabel("position [m]")
    ax.set_xlabel("time t [s]")
    ax.legend(loc="best", fontsize=8, ncol=2)

    _save(fig, path)


def _label(name: str) -> str:
    """A column name with its unit: parameters from PARAMETERS, metrics from their declarations."""
    unit = column_units().get(name)
    if unit is None:
        try:
            unit = PARAMETERS[split_name(name)[0]].unit
        except (KeyError, InputError):
            return name
    return f"{name} [{unit.split(',')[0]}]"


def plot_sweep(columns, x: str, y: str, color: str | None, path: str) -> None:
    """Scatter of y against x for the trusted samples; the flagged ones (status not ok) in a strip of
    their own below, never as if they had a value; histograms of the grip metrics."""
    plt = _pyplot()
    status = (
        np.asarray(columns["status"])
        if "status" in columns
        else np.where(np.asarray(columns["finite"]) > 0.5, Status.OK.label, Status.DIVERGED.label)
    )
    ok = status == Status.OK.label
    xs, ys = np.asarray(columns[x], float), np.asarray(columns[y], float)
    shown = ok & np.isfinite(xs) & np.isfinite(ys)
    metrics = [m for m in ("min_grip", "peak_grip", "rms_lag") if m in columns]
    fig = plt.figure(figsize=(11, 7.5), constrained_layout=True)
    grid = fig.add_gridspec(3, max(len(metrics), 1), height_ratios=[4, 0.6, 2.6])
    ax = fig.add_subplot(grid[0, :])
    if color:
        points = ax.scatter(xs[shown], ys[shown], c=np.asarray(columns[color], float)[shown], s=8, cmap="viridis")
        fig.colorbar(points, ax=ax, label=_label(color))
    else:
        ax.scatter(xs[shown], ys[shown], s=8)
    if not shown.any():
        ax.text(0.5, 0.5, f"no trusted sample has a finite {y}", transform=ax.transAxes, ha="center")
    if y in ("min_grip", "peak_grip") and "F_lim" not in columns:
        ax.axhline(10.0, color="k", ls="--", lw=1, label="F_lim (Table 1)")
        ax.legend(fontsize=8)
    positive = xs[shown & (xs > 0)]
    logx = positive.size == shown.sum() > 0 and (x == "M_b" or positive.max() / positive.min() > 50)
    if logx:
        ax.set_xscale("log")
    ax.set_ylabel(_label(y))
    ax.set_title(
        f"{y} against {x}: {int(shown.sum())} trusted samples of {len(xs)}"
        + (f"; {int((~ok).sum())} flagged (strip below)" if (~ok).any() else "")
    )
    strip = fig.add_subplot(grid[1, :], sharex=ax)
    for k, s in enumerate(sorted(set(status[~ok].tolist()))):
        mask = (status == s) & ~ok
        strip.scatter(
            xs[mask], np.full(mask.sum(), k), marker="x", s=14, color=f"C{k + 1}", label=f"{s} ({mask.sum()})"
        )
    strip.set_yticks([])
    strip.set_xlabel(_label(x))
    if (~ok).any():
        strip.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.0, 0.5))
        strip.set_ylabel("flagged", fontsize=8)
    else:
        strip.text(0.5, 0.5, "no flagged samples", transform=strip.transAxes, ha="center", va="center", fontsize=8)
    plt.setp(ax.get_xticklabels(), visible=False)
    for j, m in enumerate(metrics):
        h = fig.add_subplot(grid[2, j])
        v = np.asarray(columns[m], float)[ok]
        v = v[np.isfinite(v)]
        if v.size:
            h.hist(v, bins=40)
        else:
            h.text(0.5, 0.5, "no finite values", transform=h.transAxes, ha="center")
        h.set_xlabel(_label(m))
        h.set_ylabel("trusted samples")
        h.tick_params(axis="x", labelrotation=30)
    _save(fig, path)


def plot_bode(report: dict, path: str) -> None:
    """Driving-point admittance: the linearised simulator (lines) with Eq. 4 over it (dots)."""
    plt = _pyplot()
    omega = report["omega"]
    fig, (mag, phase) = plt.subplots(2, 1, figsize=(8, 7), sharex=True, constrained_layout=True)
    every = max(1, len(omega) // 40)
    for k, row in enumerate(report["bode"]):
        c = f"C{k}"
        label = f"alpha = {row['alpha']:g}"
        mag.loglog(omega, np.abs(row["simulator"]), color=c, label=f"{label}: simulator (jacfwd)")
        mag.loglog(omega[::every], np.abs(row["eq4"][::every]), "o", color=c, ms=4, mfc="none", label=f"{label}: Eq. 4")
        phase.semilogx(omega, np.degrees(np.angle(row["simulator"])), color=c)
        phase.semilogx(omega[::every], np.degrees(np.angle(row["eq4"][::every])), "o", color=c, ms=4, mfc="none")
    mag.set_ylabel("|Y(j omega)| = |V_r / E_env|  [m/(N s)]")
    mag.set_title(f"Driving-point admittance of robot {report['robot']} (grip cut, gamma frozen at alpha)")
    mag.legend(fontsize=8, ncol=2)
    mag.grid(True, which="both", alpha=0.3)
    phase.set_ylabel("phase [deg]")
    phase.set_xlabel("angular frequency omega [rad/s]")
    phase.grid(True, which="both", alpha=0.3)
    _save(fig, path)


def plot_k_rob(report: dict, path: str) -> None:
    """Static stiffness against alpha: the simulator's steady state (dots) with Eq. 5 (line)."""
    plt = _pyplot()
    k = report["k_rob"]
    fig, ax = plt.subplots(figsize=(7, 5), constrained_layout=True)
    ax.semilogy(
        k["alpha_fine"],
        k["eq5_fine"],
        "-",
        color="k",
        lw=1,
        label="Eq. 5: 1/K = 1/(mu_H K_c) + beta_H (1 - alpha)/(mu_H K_f)",
    )
    ax.semilogy(
        k["alpha"],
        k["simulator"],
        "o",
        color="C1",
        ms=5,
        mfc="none",
        label="simulator: static deflection under a constant effort",
    )
    ax.set_xlabel("alpha (gamma frozen)")
    ax.set_ylabel("driving-point stiffness K_rob [N/m]")
    ax.set_title(f"Robot {report['robot']}: stiffness softens as gamma falls (Eq. 5; Eq. 7 at alpha = 1)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)


def plot_poles(report: dict, path: str) -> None:
    """Closed-loop poles at rest and at the force limit, over RK4's stability region at dt."""
    plt = _pyplot()
    dt = report["dt"]
    fig, (wide, near) = plt.subplots(1, 2, figsize=(12, 5.5), constrained_layout=True)
    x = np.linspace(-3.2, 0.6, 600) / dt
    y = np.linspace(-3.2, 3.2, 600) / dt
    X, Y = np.meshgrid(x, y)
    stable = rk4_amplification((X + 1j * Y) * dt) <= 1
    styles = {"rest": ("o", "C0", "at rest (force control off)"), "limit": ("x", "C3", "at the force limit (Eq. 8 on)")}
    for ax, span in ((wide, None), (near, 30.0)):
        ax.contourf(X, Y, stable, levels=[0.5, 1.5], colors=["#d9ead3"])
        ax.contour(X, Y, stable.astype(float), levels=[0.5], colors=["#38761d"], linewidths=1)
        for point, poles in report["poles"].items():
            marker, c, label = styles[point]
            s = report["poles_summary"][point]
            ax.plot(
                poles.real,
                poles.imag,
                marker,
                color=c,
                ms=6,
                mfc="none" if marker == "o" else c,
                label=f"{label}: fastest {s['fastest']:.4g} 1/s, RK4 needs dt <= {s['rk4_dt_limit']:.3g} s",
            )
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(0, color="k", lw=0.5)
        ax.set_xlabel("Re(lambda) [1/s]")
        ax.set_ylabel("Im(lambda) [1/s]")
        if span:
            ax.set_xlim(-span, 0.2 * span)
            ax.set_ylim(-span, span)
            ax.set_title(f"zoom on the slow modes (|lambda| < {span:g} 1/s)")
    allp = np.concatenate(list(report["poles"].values()))
    reach = max(np.abs(allp).max() * 1.3, 3.0 / dt)
    wide.set_xlim(-reach, 0.2 * reach)
    wide.set_ylim(-0.7 * reach, 0.7 * reach)
    wide.set_title(f"closed-loop poles; green: RK4 stable at dt = {dt:g} s (|R(lambda dt)| <= 1)")
    wide.legend(fontsize=8, loc="upper left")
    _save(fig, path)
