"""Figures: the paper's Fig. 6 (grip forces) with gain-modulation and tracking panels."""

from __future__ import annotations

import numpy as np

from coopjax.io import atomic_path


def plot_run(trajectory, params, scenario: str, path: str, title: str | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.rsplit(".", 1)[-1] if "." in path else "png")
    plt.close(fig)


def plot_sweep(columns, x: str, y: str, color: str | None, path: str) -> None:
    """Scatter of y against x (diverged samples marked), and histograms of the grip metrics."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finite = np.asarray(columns["finite"]) > 0.5
    metrics = [m for m in ("min_grip", "peak_grip", "rms_lag") if m in columns]
    fig = plt.figure(figsize=(11, 7), constrained_layout=True)
    grid = fig.add_gridspec(2, len(metrics))
    ax = fig.add_subplot(grid[0, :])
    xs, ys = np.asarray(columns[x], float), np.asarray(columns[y], float)
    if color:
        points = ax.scatter(xs[finite], ys[finite], c=np.asarray(columns[color], float)[finite], s=8, cmap="viridis")
        fig.colorbar(points, ax=ax, label=color)
    else:
        ax.scatter(xs[finite], ys[finite], s=8)
    if (~finite).any():
        ax.scatter(xs[~finite], np.full((~finite).sum(), np.nanmin(ys) if finite.any() else 0.0), marker="x",
                   color="red", label=f"diverged ({(~finite).sum()})")
        ax.legend()
    if y in ("min_grip", "peak_grip") and "F_lim" not in columns:
        ax.axhline(10.0, color="k", ls="--", lw=1, label="F_lim (Table 1)")
    if x in ("M_b",) or (xs[finite] > 0).all() and xs.max() / max(xs.min(), 1e-300) > 50:
        ax.set_xscale("log")
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.set_title(f"{y} against {x}: {len(xs)} samples")
    for j, m in enumerate(metrics):
        h = fig.add_subplot(grid[1, j])
        v = np.asarray(columns[m], float)[finite]
        h.hist(v[np.isfinite(v)], bins=40)
        h.set_xlabel(m)
        h.set_ylabel("samples")
        h.tick_params(axis="x", labelrotation=30)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.rsplit(".", 1)[-1])
    plt.close(fig)
