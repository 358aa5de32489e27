"""`coopjax simulate`: one closed-loop run from rest, its trajectory as CSV, optionally a plot."""

from __future__ import annotations

import sys

import jax
import numpy as np

from coopjax import model
from coopjax.cli import interrupts
from coopjax.cli.common import (
    EXIT_FAILED,
    PLOT_FORMATS,
    BadInput,
    assignments,
    check_output,
    config_arguments,
    config_from,
)
from coopjax.config import record_size, step_size_note
from coopjax.io import Outputs, write_table
from coopjax.plotting import plot_run
from coopjax.params import make_params
from coopjax.simulation import memory_limit, simulate

NAME = "simulate"
RECORD_EVERY_S = 0.01  # the CSV's default spacing


def add_parser(sub):
    p = sub.add_parser(
        NAME,
        help="run one closed-loop simulation, write its trajectory as CSV and optionally plot it",
        description="Run one closed-loop simulation from rest and write a decimated trajectory.",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="fix a parameter, e.g. --set M_b=2.5 or --set K_GP_L=0.3 (repeatable; a per-robot name wins "
        "over the shared one; `coopjax params` lists the names)",
    )
    config_arguments(p, defaults={"scenario": "paper"})
    p.add_argument(
        "--every",
        type=int,
        default=None,
        help="write every N-th step to the CSV (default: every 10 ms, "
        "or more often to give a short run a hundred rows)",
    )
    p.add_argument(
        "--out",
        default="run.csv",
        help="trajectory CSV (default: run.csv). Columns: t [s]; F_L, F_R "
        "[N]; gamma_L, gamma_R [1]; w_L, w_R [1]; x_ref_L, x_ref_R [m]; then the 20 states (x_* [m], "
        "v_* [m/s], q_c [m], Z [N s], Y_e [m s])",
    )
    p.add_argument(
        "--plot",
        default=None,
        metavar="FIG.png",
        help="also draw grip forces, gamma and positions (from every step, with the located peak marked)",
    )
    return p


def run(args) -> int:
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    check_output(args.out, "--out", ("csv",))
    if args.plot is not None:
        check_output(args.plot, "--plot", PLOT_FORMATS)
    params = make_params(**assignments(args.set))
    config = config_from(args)
    n = config.n_steps
    if args.every is not None and args.every < 1:
        raise BadInput(f"--every is {args.every}: it must be a whole number of steps, at least 1")
    if args.every is not None and args.every > n:
        raise BadInput(
            f"--every {args.every} is more than the run's {n} steps: nothing would be recorded after "
            f"t = 0 (use --every <= {n})"
        )
    # By default every 10 ms, but at least a hundred records (a short run is recorded at every step).
    every = args.every if args.every is not None else max(1, min(int(round(RECORD_EVERY_S / config.dt)), n // 100))
    # A plot is drawn from every step (a decimated record can hide an impact's spike); the CSV takes
    # every `every`-th. Without a plot, only what the CSV needs is recorded.
    record = 1 if args.plot is not None else every
    if record_size(config, record, 1) > memory_limit():
        raise BadInput(
            f"recording {'every step (for --plot)' if record == 1 else f'every {every} steps'} of {n} "
            f"needs more than half of this machine's memory: "
            + ("drop --plot or run a shorter --T" if record == 1 else "use a larger --every or a shorter --T")
        )
    interrupts.report_with(lambda: None)
    solution = simulate(params, config, every=record)
    traj = jax.tree_util.tree_map(lambda x: x[:: every // record], solution.trajectory)
    columns = {"t": traj.t}
    for name, signal in (("F", traj.aux.F), ("gamma", traj.aux.gamma), ("w", traj.aux.w), ("x_ref", traj.aux.x_ref)):
        for i, r in enumerate("LR"):
            columns[f"{name}_{r}"] = signal[:, i]
    for i, name in enumerate(model.STATE_NAMES):
        columns[name] = traj.y[:, i]
    m = solution.metrics
    with Outputs() as out:  # the CSV and the plot together, or neither
        write_table(out.path(args.out), columns)
        if args.plot is not None:
            plot_run(solution.trajectory, params, config.scenario, out.path(args.plot), peak=float(m.peak_grip))

    t, F, gamma = np.asarray(traj.t), np.asarray(traj.aux.F), np.asarray(traj.aux.gamma)
    print(f"coopjax simulate: {config.describe()}")
    print(f"{'t [s]':>6} {'F_L [N]':>9} {'F_R [N]':>9} {'gamma_L':>8} {'gamma_R':>8}")
    for tq in (0.5, 1.0, 2.0, 3.0, 4.0):
        if tq <= t[-1] + 1e-9:
            k = int(np.argmin(np.abs(t - tq)))
            print(f"{t[k]:6.2f} {F[k, 0]:9.3f} {F[k, 1]:9.3f} {gamma[k, 0]:8.3f} {gamma[k, 1]:8.3f}")
    print(summary(m))
    note = step_size_note(config)
    if note:
        print(note)
    print(f"wrote {args.out}" + (f" and {args.plot}" if args.plot is not None else ""))
    if not bool(m.finite):
        at = f"t = {float(m.t_diverged):.4g} s"
        if config.force_bound != type(config)().force_bound:  # the user's own bound: a result, not a numerical failure
            why = f"a grip force passed --force-bound {config.force_bound:g} N at {at} (values after that are NaN)"
        else:
            why = f"the run diverged at {at} (values after that are NaN); try a smaller --dt"
        print(f"coopjax: warning: {why}", file=sys.stderr)
        return EXIT_FAILED
    return 0


def summary(m) -> str:
    """The metrics in one line, each with its unit; a metric whose window the scenario lacks is left out."""
    parts = []
    for name, label, unit in (
        ("min_grip", "min grip", "N"),
        ("peak_grip", "peak grip", "N"),
        ("slip", "slip", "N^2"),
        ("crush", "crush", "N^2"),
        ("rms_lag", "RMS lag", "m"),
    ):
        if name not in m._fields:
            continue
        value = float(getattr(m, name))
        if not np.isfinite(value) and bool(m.finite):
            continue
        if unit == "m":
            parts.append(f"{label} {value * 1e3:.3f} mm")
        elif unit == "N":
            parts.append(f"{label} {value:.3f} N")
        else:
            parts.append(f"{label} {value:.4g} {unit}")
    return ", ".join(parts)
