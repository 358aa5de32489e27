"""Figures of tuning: per-start history, grip traces before/after, the race, the Pareto front."""

from __future__ import annotations

import numpy as np

from coopjax.plotting import _pyplot, _save  # one home for the figure helpers


COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")


def style(names) -> dict:
    """A colour and a marker per tuner, by its place in the list (no tuner's name is special)."""
    return {n: (COLORS[i % len(COLORS)], MARKERS[i % len(MARKERS)]) for i, n in enumerate(names)}


def plot_history(history: dict, path: str, title: str) -> None:
    """Each start's (or lane's) objective and grip constraint against the step.

    A history with `phi` (screen-SLP) shows each lane's merit and its grip margin (the least Filippov
    weight over the training draws); otherwise the objective f and the worst constraint."""
    plt = _pyplot()
    if not history.get("step"):  # a tuner that keeps no per-step history (`Tuner.history`)
        fig, a = plt.subplots(figsize=(6, 2.5), constrained_layout=True)
        a.text(0.5, 0.5, "this tuner keeps no per-step history", ha="center", va="center")
        a.set_axis_off()
        fig.suptitle(title, fontsize=10)
        _save(fig, path)
        return
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.8), constrained_layout=True)
    steps = np.asarray(history["step"]) + 1
    lanes = "phi" in history
    f = np.asarray(history["phi" if lanes else "f"], float)
    right = np.asarray(history["margin" if lanes else "shortfall"], float)
    holds = np.asarray(history["holds"], bool)
    for k in range(f.shape[1]):
        label = f"lane {k}" if lanes else f"start {k}" + (" (Table 1)" if k == 0 else "")
        (line,) = a.semilogy(steps, f[:, k], lw=1, label=label)
        a.plot(steps[holds[:, k]], f[holds[:, k], k], ".", color=line.get_color(), ms=4)
        if lanes:
            b.plot(steps, right[:, k], lw=1, color=line.get_color())
        else:
            b.semilogy(steps, np.maximum(right[:, k], 1e-4), lw=1, color=line.get_color())
    finite = f[np.isfinite(f)]
    if finite.size:  # a start that blows up for one step must not flatten everyone else's curve
        a.set_ylim(0.9 * finite.min(), 1.1 * min(finite.max(), 10 * np.percentile(finite, 90)))
    a.set_xlabel("step")
    if lanes:
        a.set_ylabel("merit: the objective (hard aggregates) + penalties [N]")
        a.set_title(
            "merit per lane (dots: meets every requirement at every training draw;\n"
            "a jump: the lane starts from a new screen point)",
            fontsize=10,
        )
        b.set_ylabel("grip margin: least Filippov weight over the draws")
        b.axhline(history.get("margin_asked", [0.0])[0], color="0.3", ls="--", lw=1, label="the margin asked for")
        b.set_ylim(-0.05, 1.05)
        b.set_title("the grip constraint: 0 once the grip is lost", fontsize=10)
        b.legend(fontsize=8)
        if not np.isfinite(right).any():  # NaN without a grip requirement at F_lim: say so, not an empty axis
            b.set_xlim(steps.min(), steps.max())
            text = "no grip margin to show: the problem requires no grip at F_lim\n(or no lane's runs were measured)"
            b.text(0.5, 0.5, text, ha="center", va="center", transform=b.transAxes, fontsize=10, color="0.3")
    else:
        a.set_ylabel("objective f (training aggregates) [N]")
        a.set_title("objective per start (dots: meets every requirement at every training draw)", fontsize=10)
        b.set_ylabel("worst constraint: grip shortfall [N], others in their unit (floored at 1e-4)")
        b.set_title("the requirements: met at <= 0 (the grip: 0 while it holds)", fontsize=10)
    a.set_xlabel("step")
    a.legend(fontsize=7, ncol=2)
    b.set_xlabel("step")
    for ax in (a, b):
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=10)
    _save(fig, path)


def plot_traces(
    runs: dict, cases: list, F_lim: float, F_max: float, path: str, scenario: str = "carry", window=(0.5, 2.0)
) -> None:
    """Grip forces (hard model) for each gain set in `runs` (label -> Trajectory over the batch
    described by `cases`, one label per sample), with the scenario's grip window shaded."""
    masses = cases
    plt = _pyplot()
    labels = list(runs)
    fig, axes = plt.subplots(
        len(masses),
        len(labels),
        figsize=(5.5 * len(labels), 3.4 * len(masses)),
        sharex=True,
        sharey="row",
        constrained_layout=True,
        squeeze=False,
    )
    for j, label in enumerate(labels):
        traj = runs[label]
        t = np.asarray(traj.t)
        F = np.asarray(traj.aux.F)  # (n, 2, masses)
        for i, m in enumerate(masses):
            ax = axes[i, j]
            if window is not None:
                ax.axvspan(*window, color="0.93", zorder=0, label=f"grip window [{window[0]:g}, {window[1]:g}] s")
            ax.plot(t, F[:, 0, i], color="tab:blue", lw=1, label="F_L")
            ax.plot(t, F[:, 1, i], color="tab:red", lw=1, label="F_R")
            ax.axhline(F_lim, color="k", ls="--", lw=1, label=f"F_lim = {F_lim:g} N")
            ax.axhline(F_max, color="grey", ls=":", lw=1, label=f"F_max = {F_max:g} N")
            ax.set_title(f"{label}, {m}", fontsize=9)
            top = max(np.nanmax(np.asarray(r.aux.F)[:, :, i]) for r in runs.values())
            ax.set_ylim(-0.03 * top, 1.05 * top)
            if j == 0:
                ax.set_ylabel("grip force [N]")
            if i == len(masses) - 1:
                ax.set_xlabel("time [s]")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{scenario} scenario, hard switch and contact (float64): grip forces before and after tuning")
    _save(fig, path)


def plot_race(result: dict, path: str) -> None:
    """Best-so-far validated objective against wall time: median and worst over seeds, per tuner."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.5, 5), constrained_layout=True)
    horizon = max(r["budget_s"] for r in result["per_seed"])
    grid = np.linspace(0.0, horizon, 400)
    for name, (color, _) in style(result["tuners"]).items():
        values = []
        for r in result["per_seed"]:
            curve = r["curves"][name]
            v = np.full(grid.shape, np.inf)
            for t, score in curve:  # a step function: the running choice from time t on
                v[grid >= t] = score
            values.append(v)
        values = np.array(values)
        median, worst = np.median(values, 0), values.max(0)
        ax.plot(grid, np.where(np.isfinite(median), median, np.nan), color=color, lw=2, label=f"{name}: median")
        ax.plot(grid, np.where(np.isfinite(worst), worst, np.nan), color=color, lw=1, ls="--", label=f"{name}: worst")
    ax.set_yscale("log")
    ax.set_xlabel("wall time [s] (compilation excluded, reported apart)")
    ax.set_ylabel("validated objective: worst peak + w_lag x worst lag [N]")
    ax.set_title(
        f"{len(result['names'])} parameters, seeds {result['seeds']}: each tuner's choice so far, judged on "
        "validation masses\n(no line yet: nothing that holds the grip at every validation mass)",
        fontsize=9,
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    _save(fig, path)


def plot_pareto(rows: list[dict], path: str, x_label: str, y_label: str) -> None:
    """The first objective term (y) against the last (x) on the held-out draws: each tuner's answers
    (rows of kind "front", one per weight of the last term) over the cloud of every candidate that
    met the requirements in training (rows of kind "cloud"). Rows carry `x`, `y`, `weight`, `holds`."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 5), constrained_layout=True)
    cloud = [r for r in rows if r["kind"] == "cloud"]
    held = [r for r in cloud if r["holds"]]
    fronts = list(dict.fromkeys(r["tuner"] for r in rows if r["kind"] == "front"))
    tuned = [r for r in rows if r["kind"] == "front" and r["holds"]]
    # Zoom on the tuners' answers: the cloud's worst sets reach kN and metres.
    x_max = 3 * max([r["x"] for r in tuned] or [50.0])
    y_max = 2 * max([r["y"] for r in tuned] or [100.0])
    shown = [r for r in held if r["x"] <= x_max and r["y"] <= y_max]
    if cloud:
        ax.scatter(
            [r["x"] for r in shown],
            [r["y"] for r in shown],
            marker="x",
            color="grey",
            s=14,
            label=f"candidates that met the requirements in training ({len(held)} of {len(cloud)} meet them here, "
            f"{len(held) - len(shown)} off the axes)",
        )
    for tuner, (color, marker) in style(fronts).items():
        pts = sorted((r for r in rows if r["tuner"] == tuner and r["kind"] == "front"), key=lambda r: r["x"])
        ok = [r for r in pts if r["holds"]]
        if ok:
            ax.plot(
                [r["x"] for r in ok],
                [r["y"] for r in ok],
                marker + "-",
                color=color,
                label=f"{tuner}, one run per weight",
            )
            for r in ok:
                ax.annotate(
                    f"w={r['weight']:g}",
                    (r["x"], r["y"]),
                    fontsize=7,
                    xytext=(4, 4),
                    textcoords="offset points",
                    color=color,
                )
        lost = [r for r in pts if not r["holds"]]
        if lost:
            ax.scatter(
                [r["x"] for r in lost],
                [r["y"] for r in lost],
                facecolors="none",
                edgecolors=color,
                marker=marker,
                label=f"{tuner}: misses a requirement on a held-out draw",
            )
    ax.set_xlim(0, x_max)
    ax.set_ylim(0, y_max)
    ax.set_xlabel(x_label)
    ax.set_ylabel(y_label)
    ax.set_title("the front of the objective's terms (hard model, held-out draws)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _save(fig, path)
