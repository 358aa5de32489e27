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
    ax.set_ylabel("compensation gain gamma (Eq. 8)")
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
