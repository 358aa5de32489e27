"""Figures of a tuning run: loss curve, grip traces before/after, tuner comparison, Pareto front."""

from __future__ import annotations

import numpy as np

from coopjax.io import atomic_path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path):
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.rsplit(".", 1)[-1])
    _pyplot().close(fig)


def plot_loss(history: dict, path: str, title: str) -> None:
    """Training loss per step, with the surrogate width k_F and any rejected moves."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5), constrained_layout=True)
    steps = np.asarray(history["step"]) + 1
    ax.semilogy(steps, history["loss"], "o-", ms=3, label="training loss (this step's mass batch)")
    rejected = np.asarray(history["rejected"]) > 0
    if rejected.any():
        ax.semilogy(steps[rejected], np.asarray(history["loss"])[rejected], "rx", ms=8, label="after a rejected move")
    ax.set_xlabel("step")
    ax.set_ylabel("loss (slip, crush, lag and impact, weighted)")
    ax.set_title(title)
    twin = ax.twinx()
    twin.plot(steps, history["k_F"], color="grey", ls=":", label="switch width k_F [N]")
    twin.set_ylabel("surrogate width k_F [N]", color="grey")
    lines = ax.get_legend_handles_labels()
    more = twin.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=8, loc="upper right")
    _save(fig, path)


def plot_traces(runs: dict, masses, F_lim: float, F_max: float, path: str) -> None:
    """Grip forces (hard model) for each gain set in `runs` (label -> Trajectory over `masses`)."""
    plt = _pyplot()
    labels = list(runs)
    fig, axes = plt.subplots(len(masses), len(labels), figsize=(5.5 * len(labels), 3.4 * len(masses)),
                             sharex=True, sharey="row", constrained_layout=True, squeeze=False)
    for j, label in enumerate(labels):
        traj = runs[label]
        t = np.asarray(traj.t)
        F = np.asarray(traj.aux.F)  # (n, 2, masses)
        for i, m in enumerate(masses):
            ax = axes[i, j]
            ax.axvspan(0.5, 2.0, color="0.93", zorder=0, label="grip window [0.5, 2] s")
            ax.plot(t, F[:, 0, i], color="tab:blue", lw=1, label="F_L")
            ax.plot(t, F[:, 1, i], color="tab:red", lw=1, label="F_R")
            ax.axhline(F_lim, color="k", ls="--", lw=1, label=f"F_lim = {F_lim:g} N")
            ax.axhline(F_max, color="grey", ls=":", lw=1, label=f"F_max = {F_max:g} N")
            ax.set_title(f"{label}, M_b = {m:.3g} kg", fontsize=10)
            top = max(np.nanmax(np.asarray(r.aux.F)[:, :, i]) for r in runs.values())
            ax.set_ylim(-0.03 * top, 1.05 * top)
            if j == 0:
                ax.set_ylabel("grip force [N]")
            if i == len(masses) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle("carry scenario, hard switch and contact (float64): grip forces before and after tuning")
    _save(fig, path)


def plot_compare(traces: dict, path: str) -> None:
    """Best training loss so far against trajectories and against wall time, one line per tuner."""
    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.3), constrained_layout=True)
    for name, tr in traces.items():
        a.semilogy(tr["trajectories"], tr["loss"], label=name)
        b.semilogy(tr["wall"], tr["loss"], label=name)
    a.set_xlabel("simulated trajectories")
    b.set_xlabel("wall time [s]")
    for ax in (a, b):
        ax.set_ylabel("best training loss so far")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("tuners on the same objective and trajectory budget")
    _save(fig, path)


def plot_pareto(points: list[dict], reference: list[dict], path: str) -> None:
    """Worst-case peak force against worst-case RMS lag, for gain sets that hold the grip."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5), constrained_layout=True)
    held = [r for r in reference if r["holds"]]
    if held:
        ax.scatter([r["rms_lag"] * 1e3 for r in held], [r["peak_grip"] for r in held], marker="x", color="grey",
                   label=f"random gain sets that hold ({len(held)} of {len(reference)})")
    tuned = [p for p in points if p["holds"]]
    if tuned:
        order = sorted(tuned, key=lambda p: p["rms_lag"])
        ax.plot([p["rms_lag"] * 1e3 for p in order], [p["peak_grip"] for p in order], "o-", color="tab:blue",
                label="tuned, one per lag weight")
        for p in order:
            ax.annotate(f"w_lag={p['w_lag']:g}", (p["rms_lag"] * 1e3, p["peak_grip"]), fontsize=7,
                        xytext=(4, 4), textcoords="offset points")
    lost = [p for p in points if not p["holds"]]
    if lost:
        ax.scatter([p["rms_lag"] * 1e3 for p in lost], [p["peak_grip"] for p in lost], facecolors="none",
                   edgecolors="tab:red", label="tuned, but loses the grip (not on the front)")
    ax.set_xlabel("worst-case RMS lag over held-out masses [mm]")
    ax.set_ylabel("worst-case peak grip force [N]")
    ax.set_title("what the four gains can reach (hard model, held-out masses)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)
