"""`coopjax tune`: tune on the hard model, judge before/after on held-out masses, write OUT and plots.

Registered with the `coopjax` command through the entry-point group `coopjax.commands` (see
pyproject.toml), so that `coopjax` never imports this package. Modes: a plain run (the default),
`--compare` (the race of every registered tuner over seeds on one clock), and `--pareto` (one run per
lag weight; the front of worst-case peak force against worst-case lag).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import threading
import time

import jax
import numpy as np

from coopjax.cli import interrupts
from coopjax.cli.common import BadInput, assignments, check_output
from coopjax.errors import InputError
from coopjax.io import Outputs, write_json
from coopjax.params import make_params, split_name
from coopjax.simulation import simulate
from coopjax.stability import check_step
from tuning import driver, race
from tuning.plots import plot_history, plot_pareto, plot_race, plot_traces
from tuning.judge import JUDGE_DT, judge, judge_config, select
from tuning.problem import (
    AGGREGATES,
    HOLD_TOLERANCE,
    SURROGATE_DT,
    SWITCHES,
    TRAIN_DT,
    Problem,
    check_mass_range,
    expand_params,
    from_log,
    held_out_masses,
    log_bounds,
    starting_points,
    to_log,
    training_config,
    validation_masses,
)
from tuning.tuners import TUNERS
from tuning.tuners.cmaes import CMAES
from tuning.tuners.screen_slp import ScreenSLP

NAME = "tune"
DEFAULT_OUT = "tuned.json"
# API names of the tuning problem, and the flags that set them (the tuners' own are added from their
# declarations by `add_parser`).
FIELD_FLAGS = {
    "names": "--params",
    "n_masses": "--train-masses",
    "cvar_alpha": "--cvar-alpha",
    "w_lag": "--w-lag",
    "spread": "--spread",
    "masses": "--masses",
}
STARTS, SPREAD = 8, 2.5  # K starting points: the first is the user's (Table 1's), the others drawn near it
DEFAULT_METHOD = ScreenSLP.name


def methods() -> dict:
    """The registered tuners a plain run can end on its own (`Tuner.plain_run`)."""
    return {name: cls for name, cls in TUNERS.items() if cls.plain_run}


def tuner_flags() -> dict[str, list]:
    """Every flag the plain-run tuners declare (`tuners.setting`): flag -> [(tuner class, field)]."""
    flags: dict[str, list] = {}
    for cls in methods().values():
        for field in dataclasses.fields(cls):
            if field.metadata.get("flag"):
                flags.setdefault(field.metadata["flag"], []).append((cls, field))
    return flags


def _dest(flag: str) -> str:
    return "tuner_" + flag[2:].replace("-", "_")


def _add_tuner_flags(p) -> None:
    """One flag per tuner setting, unset by default (the tuner's own default); a flag that several
    tuners declare says what each does with it."""
    for flag, owners in tuner_flags().items():
        first = owners[0][1]
        kind = type(first.default)
        text = "; ".join(f"{cls.name}: {f.metadata['help']} (default {f.default})" for cls, f in owners)
        p.add_argument(
            flag,
            dest=_dest(flag),
            metavar=None if first.metadata.get("choices") else flag[2:].upper().replace("-", "_"),
            type=kind,
            default=None,
            choices=first.metadata.get("choices"),
            help=text,
        )
        for _, f in owners:
            FIELD_FLAGS[f.name] = flag


def add_parser(sub):
    p0 = Problem()
    p = sub.add_parser(
        NAME,
        help="tune the controller on the hard model; judge before/after on held-out masses",
        description="Tune controller parameters on the carry scenario, on the hard switch under the sliding-mode "
        "integrator: minimise worst-case peak grip force + w_lag x worst-case RMS lag, with the grip holding at every "
        "training mass. The default method (screen-SLP) screens hundreds of points in batches (CMA-ES "
        "generations), then runs trust-region linear programs on the worst case from the best of them, with exact "
        "Jacobians; --method gradient runs Adam on an augmented Lagrangian. The result is judged with the hard "
        "model at --judge-dt on held-out masses. "
        "Writes OUT (json; a figure that is not finite is null), OUT's _history.png and _traces.png (with --compare: "
        "_race.png; with --pareto: _pareto.png).",
    )
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        choices=list(methods()),
        help=f"the tuner (default {DEFAULT_METHOD}); its settings are the flags that name it below",
    )
    p.add_argument(
        "--params",
        default="all",
        help="comma-separated names, or gains (K_GP,K_GI,tau,G_e), per-robot "
        "(the 4 gains of each robot: 8) or all (per-robot + M_c,R_c,K_c,M_f,R_f,K_f: 14) (default all)",
    )
    p.add_argument(
        "--masses",
        default="loguniform:0.5:5",
        help="body-mass range, loguniform:LOW:HIGH or uniform:LOW:HIGH, kg (default loguniform:0.5:5)",
    )
    p.add_argument(
        "--train-masses",
        type=int,
        default=p0.n_masses,
        help="training masses (screen-SLP: a grid, ends included; gradient: one per equal-probability stratum, "
        f"drawn afresh each step) (default {p0.n_masses})",
    )
    p.add_argument(
        "--margin",
        type=float,
        default=p0.margin,
        help=f"the training grid spans the range widened by this fraction (default {p0.margin:g})",
    )
    p.add_argument(
        "--fixed-masses",
        dest="jitter",
        action="store_false",
        help="gradient: train on the strata's midpoints every step instead of a fresh draw per stratum",
    )
    p.add_argument(
        "--switch",
        default="hard",
        help=f"training model: {', '.join(SWITCHES)} (default hard: the sliding-mode integrator; the others are "
        "smooth surrogates under plain RK4)",
    )
    p.add_argument(
        "--dt",
        type=float,
        default=None,
        help=f"training step, s (default {TRAIN_DT:g} for hard, {SURROGATE_DT:g} for the surrogates)",
    )
    p.add_argument(
        "--w-lag",
        type=float,
        default=p0.w_lag,
        help=f"N of worst peak force per mm of worst RMS lag (default {p0.w_lag:g})",
    )
    p.add_argument(
        "--aggregate",
        default=p0.aggregate,
        help=f"gradient: its smooth worst case over masses: {', '.join(AGGREGATES)} (default {p0.aggregate})",
    )
    p.add_argument(
        "--temperature",
        type=float,
        default=p0.temperature,
        help=f"gradient: softness of smoothmax, N (default {p0.temperature:g})",
    )
    p.add_argument(
        "--cvar-alpha",
        type=float,
        default=p0.cvar_alpha,
        help=f"gradient, cvar: the worst share of masses averaged (default {p0.cvar_alpha:g})",
    )
    p.add_argument(
        "--starts",
        type=int,
        default=STARTS,
        help=f"starting points run as one batch (default {STARTS}; the first is Table 1's)",
    )
    _add_tuner_flags(p)
    p.add_argument(
        "--spread",
        type=float,
        default=SPREAD,
        help=f"random starts lie within x/÷ e^SPREAD of the first (default {SPREAD:g})",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the random starts and of the mass draws (default 0)")
    p.add_argument(
        "--judge-dt",
        type=float,
        default=JUDGE_DT,
        help=f"step of the hard model for validation and judging, s (default {JUDGE_DT:g})",
    )
    p.add_argument("--held-out", type=int, default=12, help="held-out masses for judging (default 12, ends included)")
    p.add_argument(
        "--set", action="append", default=[], metavar="NAME=VALUE", help="fix another parameter (repeatable)"
    )
    p.add_argument("--out", default=DEFAULT_OUT, help=f"result file (default {DEFAULT_OUT}); plots go beside it")
    p.add_argument("--resume", action="store_true", help="continue an interrupted plain run from OUT.ckpt")
    p.add_argument("--compare", action="store_true", help="race every registered tuner over --seeds on one clock")
    p.add_argument("--seeds", default="0,1,2,3,4", help="seeds of --compare (default 0,1,2,3,4)")
    p.add_argument(
        "--race-budget",
        default="time",
        help="--compare: every tuner gets the --method's wall time (time, "
        "the default) or as many simulated trajectories (trajectories)",
    )
    p.add_argument(
        "--pareto", action="store_true", help="one run per lag weight: the worst-peak / worst-lag front of every tuner"
    )
    p.add_argument("--lag-weights", default="0.5,1.5,4", help="lag weights of --pareto, N/mm (default 0.5,1.5,4)")
    p.add_argument("--devices", type=int, default=None, help="CPU devices (default: one per core)")
    p.add_argument("--quiet", action="store_true", help="a progress bar instead of a line per step")
    return p


def _parse_list(text, what, cast=str):
    items = [x.strip() for x in text.split(",") if x.strip()]
    try:
        out = [cast(x) for x in items]
    except ValueError:
        raise BadInput(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if not out:
        raise BadInput(f"{what}: give at least one value")
    if len(set(out)) != len(out):
        raise BadInput(f"{what}: {text!r} names a value twice")
    return out


def _parse_masses(text: str):
    parts = text.split(":")
    if len(parts) != 3 or parts[0] not in ("uniform", "loguniform"):
        raise BadInput(f"--masses expects loguniform:LOW:HIGH or uniform:LOW:HIGH, got {text!r}")
    try:
        masses = (parts[0], float(parts[1]), float(parts[2]))
    except ValueError:
        raise BadInput(f"--masses {text!r}: LOW and HIGH must be numbers") from None
    check_mass_range(masses)
    return masses


class Plan:
    """Every flag checked, nothing run: the problem, the tuner, the base parameters, the starts."""

    def __init__(self, args):
        names = expand_params(args.params)
        masses = _parse_masses(args.masses)
        if args.held_out < 2:
            raise BadInput(f"--held-out is {args.held_out}: judge on at least 2 masses (the lightest and the heaviest)")
        self.tuner = make_tuner(args)
        if args.starts < 1:
            raise BadInput(f"--starts is {args.starts}: it must be a whole number, at least 1")
        if args.seed < 0:
            raise BadInput(f"--seed is {args.seed}: it must be 0 or more")
        if not (math.isfinite(args.spread) and args.spread >= 0):
            raise BadInput(f"--spread is {args.spread:g}: it must be 0 or more")
        if not (math.isfinite(args.judge_dt) and args.judge_dt > 0):
            raise BadInput(f"--judge-dt is {args.judge_dt:g}: it must be positive")
        if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
            raise BadInput(f"--dt is {args.dt:g}: it must be positive")
        fixed = assignments(args.set)
        if any(split_name(n)[0] == "M_b" for n in fixed):
            raise BadInput("--set M_b: the body mass is what the tuner varies; give its range with --masses")

        def overlaps(a, b):  # the same parameter, for a robot both names cover
            (base_a, robot_a), (base_b, robot_b) = split_name(a), split_name(b)
            return base_a == base_b and (robot_a is None or robot_b is None or robot_a == robot_b)

        clash = [n for n in fixed if any(overlaps(n, t) for t in names)]
        if clash:
            raise BadInput(f"{clash[0]} is both tuned (--params) and fixed (--set): choose one")
        self.base = make_params(**fixed)
        self.first = {n: float(np.asarray(self.base.get(n)).ravel()[0]) for n in names}
        self.problem = Problem(
            names=names,
            masses=masses,
            n_masses=args.train_masses,
            margin=args.margin,
            jitter=args.jitter,
            config=training_config(args.switch, args.dt),
            w_lag=args.w_lag,
            aggregate=args.aggregate,
            temperature=args.temperature,
            cvar_alpha=args.cvar_alpha,
        ).validate()
        self.starts, self.spread, self.seed = args.starts, args.spread, args.seed
        self.held_out = held_out_masses(masses, args.held_out)
        self.judge_dt = args.judge_dt
        # The first start must survive its first step, in training and in judging.
        first = self.base.replace(**self.first)
        check_step(first, self.problem.config)
        check_step(first, judge_config(self.judge_dt).validate())
        if args.compare and args.pareto:
            raise BadInput("--compare and --pareto are separate runs: choose one")
        if args.resume and (args.compare or args.pareto):
            raise BadInput("--resume continues a plain run; --compare and --pareto start afresh")
        if args.race_budget not in race.BUDGETS:
            raise BadInput(f"--race-budget must be one of {', '.join(race.BUDGETS)}, not {args.race_budget!r}")
        self.race_budget = args.race_budget
        self.seeds = _parse_list(args.seeds, "--seeds", int) if args.compare else None
        if self.seeds is not None and min(self.seeds) < 0:
            raise BadInput(f"--seeds {args.seeds!r}: every seed must be 0 or more")
        self.weights = _parse_list(args.lag_weights, "--lag-weights", float) if args.pareto else None
        if self.weights is not None and any(not (x >= 0 and math.isfinite(x)) for x in self.weights):
            raise BadInput(f"--lag-weights {args.lag_weights!r}: give non-negative numbers")
        if args.compare or args.pareto:
            for name, cls in TUNERS.items():  # every tuner of the study must be able to start
                try:
                    cls().init(self.problem, np.clip(to_log(self.first, names), *log_bounds(names))[None], 0)
                except InputError as error:
                    raise BadInput(
                        f"--{'compare' if args.compare else 'pareto'} runs every tuner, and {name} cannot: {error}"
                    ) from None

    def starts_for(self, seed: int, problem: Problem | None = None) -> np.ndarray:
        return starting_points(problem or self.problem, self.base, self.first, self.starts, self.spread, seed)

    def describe(self) -> dict:
        return {
            "problem": _plain(self.problem),
            "tuner": self.tuner.name,
            "tuner_settings": dataclasses.asdict(self.tuner),
            "starts": self.starts,
            "spread": self.spread,
            "seed": self.seed,
            "judge_dt": self.judge_dt,
        }


def make_tuner(args):
    """The --method's tuner with the flags that were given (the others at its defaults). A flag of
    another tuner is refused; the tuner checks its own settings (an `InputError` names the flag)."""
    cls = methods()[args.method]
    settings = {}
    for flag, owners in tuner_flags().items():
        value = getattr(args, _dest(flag))
        if value is None:
            continue
        field = next((f for c, f in owners if c is cls), None)
        if field is None:
            raise BadInput(
                f"{flag} sets the {' and '.join(c.name for c, _ in owners)} tuner; this run's method is {cls.name}"
            )
        settings[field.name] = value
    if "spread" in {f.name for f in dataclasses.fields(cls)}:  # the screen's box is the starts' (--spread)
        settings["spread"] = args.spread
    return cls(**settings)


def _plain(problem: Problem) -> dict:
    d = {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)}
    d["config"] = json.loads(problem.config.to_json())
    return d


def paths(out: str) -> dict:
    stem = out[:-5] if out.endswith(".json") else out
    return {
        "out": out,
        "checkpoint": out + ".ckpt",
        "history": stem + "_history.png",
        "traces": stem + "_traces.png",
        "race": stem + "_race.png",
        "pareto": stem + "_pareto.png",
    }


def run(args) -> int:
    # Both before any array exists: JAX reads them when its backend starts.
    jax.config.update("jax_enable_x64", True)  # training and judging are float64
    if args.devices is not None and args.devices < 1:
        raise BadInput(f"--devices is {args.devices}: it must be at least 1")
    try:
        jax.config.update("jax_num_cpu_devices", args.devices or os.cpu_count() or 1)
    except RuntimeError:  # the backend is already up (a test, or an embedding program): keep its devices
        pass
    check_output(args.out, "--out", ("json",))
    files = paths(args.out)
    written = (
        ["history", "traces", "checkpoint"]
        if not (args.compare or args.pareto)
        else (["race"] if args.compare else ["pareto"])
    )
    for key in written:  # every file this run will write, before any work
        check_output(files[key], f"--out (its {key} file)")
    if os.path.exists(files["checkpoint"]) and not args.resume:
        raise BadInput(f"{files['checkpoint']} holds an interrupted run: add --resume to finish it, or delete it")
    if args.resume and not os.path.exists(files["checkpoint"]):
        raise BadInput(f"--resume: there is no {files['checkpoint']} to continue")
    plan = Plan(args)
    if args.compare:
        return _compare(plan, files, args.quiet)
    if args.pareto:
        return _pareto(plan, files)
    return _tune_and_report(plan, files, args.resume, args.quiet)


def _resumable(files):
    return lambda: (
        f"the checkpoint {files['checkpoint']} is kept; add --resume to the same command to continue"
        if os.path.exists(files["checkpoint"])
        else None
    )


def _tune_and_report(plan: Plan, files, resume: bool, quiet: bool) -> int:
    start = time.perf_counter()
    problem, tuner = plan.problem, plan.tuner
    print(
        f"tuning {', '.join(problem.names)} with {tuner.name}: {tuner.plan_text(len(problem.names), plan.starts)}; "
        f"{problem.switch} model ({problem.config.method}, dt = {problem.dt:g} s)"
    )
    interrupts.report_with(_resumable(files))

    def line(state, query, ev):
        text = tuner.progress_text(state, query, ev)
        if text:
            print(text)

    start_side = _StartSide(plan)
    result = driver.run(
        tuner,
        problem,
        plan.base,
        plan.starts_for(plan.seed),
        plan.seed,
        checkpoint=files["checkpoint"],
        resume=resume,
        progress=quiet,
        total=tuner.expected_evaluations(plan.starts),
        on_step=None if quiet else line,
    )
    tuned, selection = _select(plan, result)
    print(
        f"judging with the hard model (filippov), float64, dt = {plan.judge_dt:g} s, on {len(plan.held_out)} held-out "
        f"masses from {plan.held_out[0]:.3g} to {plan.held_out[-1]:.3g} kg ..."
    )
    before, start_trace = start_side.result()
    after = judge(tuned, plan.held_out, plan.base, problem.w_lag, plan.judge_dt)
    history = dict(tuner.history(result.state))
    history.pop("theta", None)
    data = {
        "params": tuned,
        "start": plan.first,
        "before": before.row(),
        "after": after.row(),
        "held_out_masses": [float(m) for m in plan.held_out],
        "judge": {
            "switch": "hard",
            "contact": "unilateral",
            "integrator": "filippov",
            "dtype": "float64",
            "dt": plan.judge_dt,
            "hold_tolerance_N": HOLD_TOLERANCE,
        },
        "config": plan.describe(),
        "method": tuner.plan_text(len(problem.names), plan.starts),
        "history": history,
        "trajectories": result.trajectories,
        "tuning_seconds": result.elapsed,
        "compile_seconds": result.compile_s,
        "selection": selection,
    }
    with Outputs() as out:  # the result and its figures together, or none of them
        nulls = write_json(out.path(files["out"]), data)
        _plots(plan, tuned, start_trace, result, files, out)
    os.remove(files["checkpoint"])
    interrupts.report_with(lambda: None)
    _print_table(before, after, plan.first, tuned, problem)
    if nulls:
        print(f"({len(nulls)} figure(s) that are not finite are null in {files['out']})")
    print(
        f"{result.trajectories} trajectories, {result.elapsed:.0f} s of tuning (+ {result.compile_s:.0f} s compiling), "
        f"{time.perf_counter() - start:.0f} s in all"
    )
    print(f"wrote {files['out']}, {files['history']} and {files['traces']}")
    return 0


def _select(plan: Plan, result):
    """Among the tuner's candidates, the best on the validation masses."""
    options = [from_log(t, plan.problem.names) for t in result.tuner.candidates(result.state)]
    masses = validation_masses(plan.problem)
    print(
        f"selecting among {len(options)} candidates: hard model on {len(masses)} validation masses from "
        f"{masses[0]:.3g} to {masses[-1]:.3g} kg (none of them held out) ..."
    )
    # The two-step check is the judge's (below): validating every candidate twice would double the
    # selection's compile and run time for a check that the chosen one gets anyway.
    chosen, verdicts = select(options, masses, plan.base, plan.problem.w_lag, plan.judge_dt, check_step=False)
    v = verdicts[chosen]
    held = sum(x.holds for x in verdicts)
    print(
        f"  {held} of {len(options)} hold at every validation mass; the chosen one: min grip {v.min_grip:.3f} N, "
        f"peak {v.peak_grip:.2f} N, lag {v.rms_lag * 1e3:.2f} mm"
    )
    return options[chosen], {
        "candidates": len(options),
        "holding": held,
        "chosen": chosen,
        "validation_masses": [float(m) for m in masses],
        "validation": v.row(),
    }


def _print_table(before, after, start, tuned, problem):
    print()
    print(f"{'':<30} {'start (Table 1)':>16} {'tuned':>12}")
    for n in problem.names:
        print(f"{n:<30} {start[n]:>16.5g} {tuned[n]:>12.5g}")
    rows = [
        ("worst min grip [N]", "min_grip", 1),
        ("worst peak grip [N]", "peak_grip", 1),
        ("worst RMS lag [mm]", "rms_lag", 1e3),
        ("worst slip [N^2]", "slip", 1),
        ("worst crush [N^2]", "crush", 1),
        ("worst after-release crush [N^2]", "impact", 1),
        (f"peak + {problem.w_lag:g} x lag [N]", "objective", 1),
    ]
    for label, key, scale in rows:
        print(f"{label:<30} {getattr(before, key) * scale:>16.4g} {getattr(after, key) * scale:>12.4g}")
    verdict = lambda v: "yes" if v.holds else "NO"
    print(f"{'holds >= F_lim at every mass':<30} {verdict(before):>16} {verdict(after):>12}")
    check = lambda v: (
        "not run"
        if not np.isfinite(v.step_error)
        else f"{'ARTEFACT' if v.step_artefact else 'ok'} ({v.step_error:.2f})"
    )
    print(f"{'dt/2 check (1 = tolerance)':<30} {check(before):>16} {check(after):>12}")
    print()


class _StartSide(threading.Thread):
    """The start's verdict and traces, which do not depend on the tuning, computed in a background
    thread while the tuner runs. A run of small batches leaves part of the cores idle, and these
    compile the judge's programs (at dt and dt/2) and the traces' one, which the tuned set's verdict
    and traces then reuse: 7 to 9 s off a cold default run (with one judging block for every size,
    `JUDGE_BLOCK`). An error is raised where the result is asked."""

    def __init__(self, plan: Plan):
        super().__init__(daemon=True)  # Ctrl-C does not wait for it
        self.plan, self.value, self.error = plan, None, None
        self.start()

    def run(self):
        plan = self.plan
        try:
            self.value = (
                judge(plan.first, plan.held_out, plan.base, plan.problem.w_lag, plan.judge_dt),
                _trace(plan, plan.first),
            )
        except BaseException as error:  # noqa: BLE001 (re-raised in the main thread)
            self.error = error

    def result(self):
        self.join()
        if self.error is not None:
            raise self.error
        return self.value


def _trace(plan: Plan, values):
    """The recorded run of one parameter set at the lightest and heaviest held-out masses."""
    ends = np.array([plan.held_out[0], plan.held_out[-1]])
    params = plan.base.replace(M_b=ends, **values)
    return simulate(params, judge_config(plan.judge_dt), every=1, check_dt=False).trajectory


def _plots(plan: Plan, tuned, start_trace, result, files, out: Outputs):
    p = plan.problem
    what = ", ".join(p.names) if len(p.names) <= 4 else f"{len(p.names)} parameters"
    plot_history(
        plan.tuner.history(result.state),
        out.path(files["history"]),
        f"tuning {what} with {plan.tuner.name} on the {p.switch} model (dt = {p.dt:g} s), {p.n_masses} masses\n"
        f"{plan.tuner.plan_text(len(p.names), plan.starts)}",
    )
    runs = {"start (Table 1)": start_trace, "tuned": _trace(plan, tuned)}
    ends = np.array([plan.held_out[0], plan.held_out[-1]])
    plot_traces(
        runs,
        ends,
        float(np.asarray(plan.base.F_lim).min()),
        float(np.asarray(plan.base.F_max)),
        out.path(files["traces"]),
    )


def _tuners(plan: Plan) -> dict:
    """Every registered tuner, the plan's own with its flags, the others with their defaults."""
    return {name: (plan.tuner if name == plan.tuner.name else cls()) for name, cls in TUNERS.items()}


def _compare(plan: Plan, files, quiet: bool) -> int:
    result = race.run(
        _tuners(plan),
        plan.tuner.name,
        plan.problem,
        plan.base,
        plan.starts_for,
        plan.seeds,
        progress=quiet,
        judge_dt=plan.judge_dt,
        budget=plan.race_budget,
        target=CMAES.name,
    )
    result["config"] = plan.describe()
    with Outputs() as out:
        write_json(out.path(files["out"]), result)
        plot_race(result, out.path(files["race"]))
    race.print_summary(result)
    print(f"wrote {files['out']} and {files['race']}")
    return 0


def _pareto(plan: Plan, files) -> int:
    names = plan.problem.names
    masses = validation_masses(plan.problem)
    tuners = _tuners(plan)
    rows_in: list[tuple[str, str, float | None, dict]] = []  # (kind, tuner, w_lag, params)
    cloud: list[dict] = []
    budget = None
    for w_lag in plan.weights:
        problem = dataclasses.replace(plan.problem, w_lag=w_lag)
        starts = plan.starts_for(plan.seed, problem)
        print(f"-- lag weight {w_lag:g} N/mm")
        for name, tuner in tuners.items():
            limit = driver.Budget() if name == plan.tuner.name else driver.Budget(seconds=budget)
            result = driver.run(tuner, problem, plan.base, starts, plan.seed, budget=limit, progress=True)
            if name == plan.tuner.name:
                budget = result.elapsed
            options = [from_log(t, names) for t in tuner.candidates(result.state)]
            options += [from_log(result.record.thetas[i], names) for _, i in race.snapshots(result.record)]
            if options:
                rows_in.append(
                    ("front", name, w_lag, options[select(options, masses, plan.base, w_lag, plan.judge_dt)[0]])
                )
            if w_lag == plan.weights[0]:  # the cloud of what held in training, once
                cloud += [from_log(t, names) for t, h in zip(result.record.thetas, result.record.holds) if h][:200]
    flat = [(kind, t, w, p) for kind, t, w, p in rows_in] + [("cloud", None, None, p) for p in cloud]
    print(f"judging {len(flat)} parameter sets on the held-out masses ...")
    verdicts = judge([p for *_, p in flat], plan.held_out, plan.base, 1.0, plan.judge_dt)
    rows = [
        {"kind": kind, "tuner": t, "w_lag": w, "params": {k: float(v) for k, v in p.items()}, **v.row()}
        for (kind, t, w, p), v in zip(flat, verdicts)
    ]
    with Outputs() as out:
        write_json(
            out.path(files["out"]),
            {"pareto": rows, "config": plan.describe(), "held_out_masses": [float(m) for m in plan.held_out]},
        )
        plot_pareto(rows, out.path(files["pareto"]))
    for r in rows:
        if r["kind"] == "front":
            print(
                f"  {r['tuner']:<14} w_lag {r['w_lag']:>5g}: holds {'yes' if r['holds'] else 'NO ':>3}, "
                f"peak {r['peak_grip']:6.2f} N, lag {r['rms_lag_mm']:6.2f} mm"
            )
    print(f"wrote {files['out']} and {files['pareto']}")
    return 0
