"""The `coopjax` command line.

Any mistake in the input is one line on stderr and exit code 2, with no traceback and no output
file. Files are written atomically, only after the run succeeded.
"""

from __future__ import annotations

import os
import shutil
import sys
import time

import numpy as np

from coopjax.cliutil import EXIT_BAD_INPUT, EXIT_DIVERGED, BadInput, Parser, check_output, parse_assignment

PLOT_FORMATS = ("png", "pdf", "svg")


def resolve_integrator(args) -> str:
    """--integrator, defaulting to the sliding-mode step for the hard switch and RK4 otherwise."""
    from coopjax.integration import INTEGRATORS, default_integrator

    integrator = args.integrator or default_integrator(args.switch)
    if integrator not in INTEGRATORS:
        raise BadInput(f"--integrator {integrator!r}: choose one of {', '.join(INTEGRATORS)}")
    return integrator


def note_step_size(args) -> None:
    from coopjax.integration.loop import step_size_note

    note = step_size_note(args.scenario, args.switch, resolve_integrator(args), args.dt)
    if note:
        print(note)


def build_parser() -> Parser:
    from coopjax.scenarios import SCENARIOS

    parser = Parser(
        prog="coopjax",
        description="Differentiable simulator of two cooperating space robots with virtual-foundation "
        "force control (Pathak et al.). The equations: docs/model.md in the project; tuning: docs/tuning.md; "
        "linear analysis: docs/analysis.md.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True

    # Options every simulating command shares.
    common = Parser(add_help=False)
    common.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE",
        help="fix a parameter, e.g. --set M_b=2.5 or --set K_GP_L=0.3 (repeatable; "
        "`coopjax params` lists the names)",
    )
    common.add_argument("--switch", default="hard", help="hard (default), smooth, blend or straight_through")
    common.add_argument(
        "--integrator", default=None, choices=("filippov", "rk4"),
        help="filippov: the sliding-mode step, the default for the hard switch (its answer is the dt -> 0 "
        "limit at dt = 1e-3); rk4: plain RK4, the only choice for the smooth switches",
    )
    common.add_argument("--dt", type=float, default=1e-3, help="step in s (default 1e-3; see docs/model.md, 'Step size')")
    common.add_argument("--T", type=float, default=None, help="horizon in s (default: the scenario's)")
    common.add_argument("--x64", action="store_true", help="float64 (default: float32)")

    sim = sub.add_parser(
        "simulate", parents=[common],
        help="run one closed-loop simulation, write its trajectory as CSV and optionally plot it",
        description="Run one closed-loop simulation from rest and write a decimated trajectory.",
    )
    sim.add_argument("--scenario", default="paper", help=f"one of: {', '.join(SCENARIOS)} (default: paper)")
    sim.add_argument("--contact", default="unilateral", help="unilateral (default) or bilateral")
    sim.add_argument("--every", type=int, default=None, help="write every N-th step to the CSV (default: every 10 ms)")
    sim.add_argument("--out", default="run.csv", help="trajectory CSV (default: run.csv). Columns: t [s]; F_L, F_R "
                     "[N]; gamma_L, gamma_R [1]; w_L, w_R [1]; x_ref_L, x_ref_R [m]; then the 20 states (x_* [m], "
                     "v_* [m/s], q_c [m], Z [N s], Y_e [m s])")
    sim.add_argument("--plot", default=None, metavar="FIG.png", help="also draw grip forces, gamma and positions "
                     "(from every step, with the located peak marked)")

    sw = sub.add_parser(
        "sweep", parents=[common],
        help="run many parameter sets (Monte-Carlo, grid or a table) and write one row of metrics each",
        description="Sweep the closed loop over parameter sets, sharded over this machine's CPU cores, in "
        "resumable chunks. DIST is uniform:a:b, loguniform:a:b, normal:mean:sd, choice:v1,v2,... or "
        "grid:a:b:k (grid axes form a full factorial and imply --n). Table columns: sample; the varied "
        "parameters (units: `coopjax params`); min_grip [N], peak_grip [N], slip [N^2], crush [N^2], rms_lag [m], "
        "impact [N^2], finite [1 if trusted, else 0], t_diverged [s], dt_limit [s: the largest stable step of the "
        "linearised loop], status [ok | diverged | unstable_loop | step_beyond_limit].",
    )
    sw.add_argument("--scenario", default="carry", help="carry (default) or paper")
    sw.add_argument("--n", type=int, default=None, help="number of samples (implied by grid axes or --from)")
    sw.add_argument("--vary", action="append", default=[], metavar="NAME=DIST", help="a varied parameter (repeatable)")
    sw.add_argument("--from", dest="from_file", default=None, metavar="TABLE", help="parameter sets from a CSV or Parquet table, one row each")
    sw.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sw.add_argument("--chunk", type=int, default=16384, help="samples per saved chunk (default 16384)")
    sw.add_argument("--devices", type=int, default=None, help="CPU devices to shard over (default: one per core)")
    sw.add_argument("--out", default="sweep.csv", help="sweep.csv or sweep.parquet (default sweep.csv)")
    sw.add_argument("--resume", action="store_true", help="finish an interrupted sweep with the same options")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.add_argument("--coordinator", default=os.environ.get("COOPJAX_COORDINATOR"), metavar="HOST:PORT",
                    help="jax.distributed coordinator (or COOPJAX_COORDINATOR)")
    sw.add_argument("--num-processes", type=int, default=None, help="number of processes (or COOPJAX_NUM_PROCESSES)")
    sw.add_argument("--process-id", type=int, default=None, help="this process, 0 to N-1 (or COOPJAX_PROCESS_ID)")

    ps = sub.add_parser("plot-sweep", help="scatter a metric against a parameter, with histograms of the metrics")
    ps.add_argument("table", help="a sweep table (.csv or .parquet)")
    ps.add_argument("--x", default="M_b", help="column on the x axis (default M_b)")
    ps.add_argument("--y", default="min_grip", help="column on the y axis (default min_grip)")
    ps.add_argument("--color", default=None, help="column for the colour scale")
    ps.add_argument("--out", default="sweep.png", help="figure file (default sweep.png)")

    an = sub.add_parser(
        "analyze", help="linear analysis: admittance vs Eq. 4, K_rob vs Eq. 5, poles vs the step, loop margins",
        description="Linearise the closed loop (jax.jacfwd of the model's own field) and check it as a control "
        "engineer would, with python-control: the Bode plot of the driving-point admittance for each alpha with "
        "the paper's Eq. 4 over it (OUT_bode.png), K_rob against alpha with Eq. 5 (OUT_krob.png), the closed-loop "
        "poles at rest and at the force limit over RK4's stability region at --dt (OUT_poles.png), and the gain "
        "and phase margins of the gain-modulation loop at the force limit (printed, and in OUT.json). "
        "Needs python-control: pip install 'coopjax[analysis]'.",
    )
    an.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="fix a parameter, e.g. --set K_GP=0.3 (repeatable; `coopjax params` lists the names)")
    an.add_argument("--alpha", default="1,0.5,0.1", help="comma-separated alphas for the Bode plot (default 1,0.5,0.1)")
    an.add_argument("--robot", default="L", choices=("L", "R"), help="the robot analysed (default L)")
    an.add_argument("--dt", type=float, default=1e-3, help="the step whose RK4 stability region is drawn, s (default 1e-3)")
    an.add_argument("--out", default="analysis", metavar="OUT",
                    help="prefix of the files written: OUT.json, OUT_bode.png, OUT_krob.png, OUT_poles.png (default analysis)")

    from tuning.cli import add_parser as add_tune_parser

    add_tune_parser(sub)
    sub.add_parser("params", help="list every parameter with its default, unit and meaning")
    return parser


def _env_int(flag, value, name):
    """A flag's value, else the environment variable's, which must then be a whole number."""
    if value is not None or not os.environ.get(name):
        return value
    text = os.environ[name].strip()
    if not text.isdigit():
        raise BadInput(f"{name}={text!r} (for {flag}) is not a whole number")
    return int(text)


def _unique(items, flag):
    names = [text.partition("=")[0].strip() for text in items]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise BadInput(f"{flag} {repeated[0]} is given more than once: give each name once")


def cmd_sweep(args) -> int:
    import jax

    args.num_processes = _env_int("--num-processes", args.num_processes, "COOPJAX_NUM_PROCESSES")
    args.process_id = _env_int("--process-id", args.process_id, "COOPJAX_PROCESS_ID")
    distributed = [args.coordinator, args.num_processes, args.process_id]
    if any(v is not None for v in distributed) and not all(v is not None for v in distributed):
        raise BadInput("--coordinator, --num-processes and --process-id go together")
    if args.num_processes is not None and not (args.num_processes >= 1 and 0 <= args.process_id < args.num_processes):
        raise BadInput(f"--process-id {args.process_id} must be between 0 and --num-processes - 1 = {args.num_processes - 1}")
    if args.devices is not None and args.devices < 1:
        raise BadInput(f"--devices is {args.devices}: it must be at least 1")
    devices = args.devices or os.cpu_count() or 1
    _unique(args.vary, "--vary")
    _unique(args.set, "--set")
    check_output(args.out, "--out", ("csv", "parquet"))
    if args.out.lower().endswith(".parquet"):
        try:
            import pandas  # noqa: F401
            import pyarrow  # noqa: F401
        except ImportError:
            raise BadInput("writing Parquet needs pandas and pyarrow: pip install 'coopjax[sweep]', or use --out sweep.csv")

    # Set here, in the entry point, before anything creates an array: the device count is fixed once
    # JAX's backend starts (a caller that already started it keeps its own). No file is touched yet.
    try:
        jax.config.update("jax_num_cpu_devices", devices)
    except RuntimeError:
        pass
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    if all(v is not None for v in distributed):
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    from coopjax import sweeps

    table = None
    if args.from_file:
        table = sweeps.read_table(args.from_file, "--from")
        # A previous sweep's table may be fed back: its result columns are not parameters.
        for name in ("sample",) + sweeps.COLUMNS_PER_SAMPLE:
            table.pop(name, None)
        if not table:
            raise BadInput(f"--from {args.from_file!r} has no parameter columns (`coopjax params` lists the names)")
        for name, column in table.items():
            if column.dtype.kind != "f":
                raise BadInput(f"--from {args.from_file!r}: column {name!r} holds values that are not numbers")
    spec = sweeps.make_spec(
        args.scenario, args.n, dict(_parse_vary(v) for v in args.vary), dict(parse_assignment(s) for s in args.set),
        args.seed, args.switch, args.dt, args.T, args.x64, table, resolve_integrator(args),
    )
    parts = args.out + ".parts"
    start = time.perf_counter()
    columns = sweeps.run(spec, chunk=args.chunk, parts=parts, resume=args.resume, progress=not args.quiet)
    if jax.process_index() == 0:
        sweeps.write_table(args.out, columns)
        shutil.rmtree(parts, ignore_errors=True)
        elapsed = time.perf_counter() - start
        finite = np.asarray(columns["finite"])
        status = np.asarray(columns["status"])
        flagged = ", ".join(f"{int((status == s).sum())} {s}" for s in sweeps.STATUSES[1:] if (status == s).any())
        print(f"coopjax sweep: {spec.n} samples of {spec.scenario} in {elapsed:.1f} s on "
              f"{jax.device_count()} device(s) x {jax.process_count()} process(es); "
              f"{int(finite.sum())} ok" + (f", flagged: {flagged} (see the status column)" if flagged else ""))
        for name in ("min_grip", "peak_grip", "rms_lag"):
            v = np.asarray(columns[name])[finite]
            if v.size:
                print(f"  {name:<10} min {v.min():10.4g}  median {np.median(v):10.4g}  max {v.max():10.4g}")
        note_step_size(args)
        print(f"wrote {args.out}")
    return 0


def _parse_vary(text: str):
    name, sep, dist = text.partition("=")
    if not sep or not name or not dist:
        raise BadInput(f"--vary expects NAME=DIST, got {text!r}")
    return name.strip(), dist.strip()


def cmd_plot_sweep(args) -> int:
    from coopjax import sweeps
    from coopjax.plotting import plot_sweep

    check_output(args.out, "--out", PLOT_FORMATS)
    columns = sweeps.read_table(args.table)
    for name in (args.x, args.y, args.color):
        if name is not None and name not in columns:
            raise BadInput(f"no column {name!r} in {args.table}; it has: {', '.join(columns)}")
        if name is not None and columns[name].dtype.kind != "f":
            raise BadInput(f"column {name!r} of {args.table} is not numeric")
    if "finite" not in columns:
        raise BadInput(f"{args.table} is not a sweep table: it has no 'finite' column")
    plot_sweep(columns, args.x, args.y, args.color, args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_params() -> int:
    from coopjax.params import PARAMETERS

    print(f"{'name':<10} {'default':>10}  {'unit':<8} {'per robot':<11}  meaning")
    for name, spec in PARAMETERS.items():
        per = "yes (_L/_R)" if spec.per_robot else "shared"
        print(f"{name:<10} {spec.default:>10.4g}  {spec.unit:<8} {per:<11}  {spec.doc}")
    return 0


def cmd_simulate(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)

    from coopjax import make_params, simulate
    from coopjax.model import STATE_NAMES
    from coopjax.plotting import plot_run

    check_output(args.out, "--out", ("csv",))
    if args.plot is not None:
        check_output(args.plot, "--plot", PLOT_FORMATS)
    _unique(args.set, "--set")
    overrides = dict(parse_assignment(s) for s in args.set)
    every = args.every if args.every is not None else max(1, int(round(0.01 / args.dt))) if args.dt > 0 else 1
    params = make_params(**overrides)
    # Every step is recorded (a plot must show the true peak); the CSV takes every `every`-th.
    from coopjax.integration import SimConfig
    from coopjax.model import Options

    SimConfig(args.scenario, Options(switch=args.switch, contact=args.contact), resolve_integrator(args), args.dt,
              args.T, every=every).validate()
    solution = simulate(
        params, args.scenario, switch=args.switch, contact=args.contact, integrator=resolve_integrator(args),
        dt=args.dt, T=args.T, every=1,
    )

    full = solution.trajectory
    traj = jax.tree_util.tree_map(lambda x: x[::every], full)
    columns = {"t": traj.t}
    for name, signal in (("F", traj.aux.F), ("gamma", traj.aux.gamma), ("w", traj.aux.w), ("x_ref", traj.aux.x_ref)):
        for i, r in enumerate("LR"):
            columns[f"{name}_{r}"] = signal[:, i]
    for i, name in enumerate(STATE_NAMES):
        columns[name] = traj.y[:, i]
    from coopjax.io import write_csv

    write_csv(args.out, columns)
    if args.plot is not None:
        plot_run(full, params, args.scenario, args.plot, peak=float(solution.metrics.peak_grip))

    m = solution.metrics
    t = np.asarray(traj.t)
    F = np.asarray(traj.aux.F)
    print(f"coopjax simulate: scenario {args.scenario}, switch {args.switch}, integrator {resolve_integrator(args)}, "
          f"dt {args.dt:g} s, "
          f"{'float64' if args.x64 else 'float32'}")
    print(f"{'t [s]':>6} {'F_L [N]':>9} {'F_R [N]':>9} {'gamma_L':>8} {'gamma_R':>8}")
    for tq in (0.5, 1.0, 2.0, 3.0, 4.0):
        if tq <= t[-1] + 1e-9:
            k = int(np.argmin(np.abs(t - tq)))
            g = np.asarray(traj.aux.gamma)[k]
            print(f"{t[k]:6.2f} {F[k, 0]:9.3f} {F[k, 1]:9.3f} {g[0]:8.3f} {g[1]:8.3f}")
    lag = float(m.rms_lag)
    lag_text = f"{lag:.3f} m" if lag >= 1 else f"{lag * 1e3:.3f} mm"
    print(f"min grip {float(m.min_grip):.3f} N, peak grip {float(m.peak_grip):.3f} N, "
          f"slip {float(m.slip):.4g} N^2, crush {float(m.crush):.4g} N^2, RMS lag {lag_text}")
    note_step_size(args)
    print(f"wrote {args.out}" + (f" and {args.plot}" if args.plot is not None else ""))
    if not bool(m.finite):
        print(f"coopjax: warning: the run diverged at t = {float(m.t_diverged):.4g} s "
              "(values after that are NaN); try a smaller --dt", file=sys.stderr)
        return EXIT_DIVERGED
    return 0


def _parse_alphas(text: str) -> list[float]:
    try:
        alphas = [float(a) for a in text.split(",")]
    except ValueError:
        raise BadInput(f"--alpha {text!r}: expected comma-separated numbers, e.g. 1,0.5,0.1") from None
    if not alphas or not all(np.isfinite(alphas)):
        raise BadInput(f"--alpha {text!r}: every alpha must be a finite number")
    if len(set(alphas)) != len(alphas):
        raise BadInput(f"--alpha {text!r} names one value twice")
    return alphas


def cmd_analyze(args) -> int:
    try:
        import control  # noqa: F401
    except ImportError:
        raise BadInput("coopjax analyze needs python-control: pip install 'coopjax[analysis]'") from None
    alphas = _parse_alphas(args.alpha)
    if not (np.isfinite(args.dt) and args.dt > 0):
        raise BadInput(f"--dt {args.dt:g}: it must be a positive number of seconds")
    outputs = {"json": args.out + ".json", "bode": args.out + "_bode.png", "krob": args.out + "_krob.png",
               "poles": args.out + "_poles.png"}
    for path in outputs.values():
        check_output(path, "--out")
    import json
    import warnings

    import jax

    jax.config.update("jax_enable_x64", True)
    from coopjax import analysis, make_params
    from coopjax.io import atomic_path
    from coopjax.plotting import plot_bode, plot_k_rob, plot_poles

    params = make_params(**dict(parse_assignment(s) for s in args.set))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # python-control's nan comparisons on a grid
        report = analysis.report(params, alphas, args.dt, args.robot)

    r, worst = args.robot, lambda row: float(np.max(np.abs(row["simulator"] - row["eq4"]) / np.abs(row["eq4"])))
    print(f"coopjax analyze: robot {r}, linearised by jax.jacfwd, float64; {len(report['omega'])} frequencies "
          f"from {report['omega'][0]:g} to {report['omega'][-1]:g} rad/s")
    print("driving-point admittance V_r/E_env (grip cut, gamma frozen), largest relative difference from Eq. 4:")
    for row in report["bode"]:
        print(f"  alpha = {row['alpha']:<5g} {worst(row):.2e}")
    k = report["k_rob"]
    print(f"{'alpha':>7} {'K_rob [N/m]':>14} {'Eq. 5 [N/m]':>14}  (static deflection under a constant effort)")
    for a in alphas:
        j = int(np.argmin(np.abs(k["alpha"] - a)))
        print(f"{a:7g} {k['simulator'][j]:14.6g} {k['eq5'][j]:14.6g}")
    for point, text in (("rest", "at rest, force control off"), ("limit", "at the force limit, Eq. 8 on")):
        s = report["poles_summary"][point]
        damped = (f"; least damped {s['least_damped'][0]:.3g} +- {s['least_damped'][1]:.4g}j 1/s "
                  f"(damping ratio {s['damping_ratio']:.3f})") if s["least_damped"] else ""
        print(f"poles {text}: fastest |lambda| {s['fastest']:.4g} 1/s{damped}; RK4 stable for dt <= "
              f"{s['rk4_dt_limit']:.3g} s, so dt = {args.dt:g} s is {'inside' if s['dt_inside'] else 'OUTSIDE'}")
    m = report["margins"]
    gm = "infinite (the loop never crosses -180 deg)" if not np.isfinite(m["gain_margin"]) else f"{m['gain_margin']:.4g}"
    print(f"gain-modulation loop of robot {r} at the force limit (cut at gamma; L(0) = {report['loop_dc_gain']:.4g}):")
    print(f"  gain margin {gm}; phase margin {m['phase_margin_deg']:.3g} deg at {m['w_gain_crossover']:.4g} rad/s; "
          f"stability margin (least distance to -1) {m['stability_margin']:.3g} at {m['w_stability_margin']:.4g} rad/s")
    re, im = m["loop_at_gain_crossover"]
    if np.isfinite(m["phase_margin_deg"]) and m["phase_margin_deg"] < 0 and im > 0:
        print(f"  (at the crossover L = {re:.3g} {im:+.3g}j: the phase leads, so the Nyquist curve passes "
              f"{-m['phase_margin_deg']:.3g} deg above -1; python-control counts that as negative)")
    print(f"  closed loop {'stable' if report['closed_loop_stable'] else 'UNSTABLE'} (largest real part of its poles "
          f"{report['poles_summary']['limit']['max_real']:.3g} 1/s)")

    plot_bode(report, outputs["bode"])
    plot_k_rob(report, outputs["krob"])
    plot_poles(report, outputs["poles"])
    plain = dict(
        robot=r, dt=args.dt, overrides=dict(parse_assignment(s) for s in args.set),
        eq4_max_relative_difference={f"{row['alpha']:g}": worst(row) for row in report["bode"]},
        k_rob={"alpha": k["alpha"].tolist(), "simulator": k["simulator"].tolist(), "eq5": k["eq5"].tolist()},
        poles={pt: [[float(z.real), float(z.imag)] for z in v] for pt, v in report["poles"].items()},
        poles_summary=report["poles_summary"], margins=report["margins"], loop_dc_gain=report["loop_dc_gain"],
        closed_loop_stable=report["closed_loop_stable"],
    )
    with atomic_path(outputs["json"]) as tmp:
        with open(tmp, "w") as f:
            json.dump(plain, f, indent=1, allow_nan=True)
    print("wrote " + ", ".join(outputs.values()))
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command == "params":
            return cmd_params()
        if args.command == "sweep":
            return cmd_sweep(args)
        if args.command == "plot-sweep":
            return cmd_plot_sweep(args)
        if args.command == "analyze":
            return cmd_analyze(args)
        if args.command == "tune":
            from tuning.cli import cmd_tune

            return cmd_tune(args)
        return cmd_simulate(args)
    except (BadInput, ValueError) as error:
        print(f"coopjax: error: {error}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        command = getattr(args, "command", None) if "args" in locals() else None
        if command == "sweep" and os.path.isdir(args.out + ".parts"):
            hint = f"finished chunks are kept in {args.out}.parts; add --resume to the same command to continue"
        else:
            hint = "nothing was written"
        print(f"\ncoopjax: interrupted; {hint}", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `coopjax params | head`: the reader left, nothing is wrong
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
