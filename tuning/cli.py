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
from coopjax import devices, scenarios
from coopjax.objectives import METRICS
from coopjax.params import PARAMETERS, split_name
from coopjax.simulation import memory_limit, simulate
from coopjax.stability import check_step
from tuning import driver, race
from tuning.plots import plot_history, plot_pareto, plot_race, plot_traces
from tuning.judging import JUDGE_DT, judge, judge_config, select
from tuning.design import describe as describe_draws, uncertain
from tuning.problem import (
    AGGREGATES,
    DEFAULT_MINIMISE,
    HOLD_TOLERANCE,
    SURROGATE_DT,
    SWITCHES,
    TRAIN_DT,
    Objective,
    Problem,
    expand_params,
    from_log,
    starting_points,
    to_log,
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
    "n_draws": "--train-masses",
    "cvar_alpha": "--cvar-alpha",
    "spread": "--spread",
}
# The flags that state the default problem, in short; a --problem file states it instead.
PROBLEM_FLAGS = (
    "--params",
    "--masses",
    "--train-masses",
    "--margin",
    "--fixed-masses",
    "--switch",
    "--dt",
    "--w-lag",
    "--aggregate",
    "--temperature",
    "--cvar-alpha",
    "--set",
)
EXIT_MISSED = 3  # the answer written misses a requirement on the held-out draws
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
        kind = first.metadata.get("kind") or type(first.default)
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
        help="tune the controller to a problem's requirements on the hard model; judge them on held-out draws",
        description="Tune controller parameters on the hard switch under the sliding-mode integrator. The problem "
        "(--problem FILE, a TOML file: docs/tuning.md) says what is tuned, over which uncertain parameters and "
        "scenarios, what is minimised and what is required; without it, the default problem: minimise worst-case "
        "peak grip force + w_lag x worst-case RMS lag over the body mass on the carry scenario, with the grip "
        "holding at F_lim (--show-problem prints it as a file). The default method (screen-SLP) screens hundreds "
        "of points in batches (CMA-ES generations), then runs trust-region linear programs on the worst case from "
        "the best of them, with exact Jacobians; --method gradient runs Adam on an augmented Lagrangian. The "
        "answer is judged with the hard model at --judge-dt on held-out draws, requirement by requirement. "
        f"Exit code 0: every requirement holds there; {EXIT_MISSED}: the answer written misses one. "
        "Writes OUT (json; a figure that is not finite is null), OUT's _history.png and _traces.png (with --compare: "
        "_race.png; with --pareto: _pareto.png).",
    )
    p.add_argument(
        "--problem",
        metavar="FILE",
        default=None,
        help="the tuning problem, a TOML file (docs/tuning.md, 'Problem files'); the flags of the default "
        "problem (--params, --masses, --w-lag, --set, ...) are then refused",
    )
    p.add_argument(
        "--show-problem",
        action="store_true",
        help="print the effective problem as a file you can edit and pass to --problem, and stop",
    )
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        choices=list(methods()),
        help=f"the tuner (default {DEFAULT_METHOD}); its settings are the flags that name it below",
    )
    p.add_argument(
        "--params",
        default=None,
        help="default problem: comma-separated names, or gains (K_GP,K_GI,tau,G_e), per-robot "
        "(the 4 gains of each robot: 8) or all (per-robot + M_c,R_c,K_c,M_f,R_f,K_f: 14) (default all)",
    )
    p.add_argument(
        "--masses",
        default=None,
        help="default problem: the body-mass range, loguniform:LOW:HIGH or uniform:LOW:HIGH, kg "
        "(default loguniform:0.5:5)",
    )
    p.add_argument(
        "--train-masses",
        type=int,
        default=None,
        help="training draws per step (screen-SLP: a grid, ends included; gradient: one per equal-probability "
        "stratum, drawn afresh each step; with several uncertain parameters, besides the box's corners) "
        f"(default {p0.n_draws})",
    )
    p.add_argument(
        "--margin",
        type=float,
        default=None,
        help=f"training draws span the box widened by this share (default {p0.margin:g})",
    )
    p.add_argument(
        "--fixed-masses",
        dest="jitter",
        action="store_const",
        const=False,
        default=None,
        help="gradient: train on a fixed design every step instead of fresh draws",
    )
    p.add_argument(
        "--switch",
        default=None,
        help=f"training model: {', '.join(SWITCHES)} (default hard: the sliding-mode integrator; the others are "
        "smooth surrogates under plain RK4)",
    )
    p.add_argument(
        "--dt",
        type=float,
        default=None,
        help=f"training step, s (default {TRAIN_DT:g} for hard on carry, {SURROGATE_DT:g} for the surrogates)",
    )
    p.add_argument(
        "--w-lag",
        type=float,
        default=None,
        help="default problem: N of worst peak force per mm of worst RMS lag "
        f"(default {DEFAULT_MINIMISE[1].weight / 1e3:g})",
    )
    p.add_argument(
        "--aggregate",
        default=None,
        help=f"training's smooth worst case over the draws: {', '.join(AGGREGATES)} (default {p0.aggregate})",
    )
    p.add_argument(
        "--temperature",
        type=float,
        default=None,
        help=f"softness of smoothmax, N (default {p0.temperature:g})",
    )
    p.add_argument(
        "--cvar-alpha",
        type=float,
        default=None,
        help=f"--aggregate cvar: the worst share of draws averaged (default {p0.cvar_alpha:g})",
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
    p.add_argument(
        "--held-out",
        type=int,
        default=12,
        help="held-out draws for judging: a grid with its ends (one uncertain parameter), or Sobol points besides "
        "the box's corners (several) (default 12)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=None,
        metavar="NAME=VALUE",
        help="default problem: fix another parameter (repeatable)",
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
        "--pareto",
        action="store_true",
        help="one run per weight of the problem's last objective term: the front of its first two terms, every tuner",
    )
    p.add_argument(
        "--pareto-weights",
        default=None,
        help="--pareto: weights of the last objective term, in its own unit (default: its weight x 1/3, 1, 8/3)",
    )
    p.add_argument(
        "--lag-weights",
        default=None,
        help="--pareto on the default problem: lag weights in N/mm (0.5,1.5,4 is the default of --pareto-weights)",
    )
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


def _given(args) -> list[str]:
    """The default problem's flags that were given."""
    dest = lambda flag: "jitter" if flag == "--fixed-masses" else flag[2:].replace("-", "_")
    return [flag for flag in PROBLEM_FLAGS if getattr(args, dest(flag)) is not None]


def build_problem(args) -> Problem:
    """The problem of a run: the --problem file, or the default problem with its shorthands."""
    given = _given(args)
    if args.problem is not None:
        if given:
            raise BadInput(f"{given[0]} contradicts --problem {args.problem}: state it in the file instead")
        return Problem.from_toml(args.problem)
    p0 = Problem()
    fields: dict = {}
    if args.params is not None:
        fields["names"] = expand_params(args.params)
    if args.masses is not None:
        if args.masses.split(":")[0] not in ("uniform", "loguniform"):
            raise BadInput(f"--masses expects loguniform:LOW:HIGH or uniform:LOW:HIGH, got {args.masses!r}")
        try:
            fields["uncertain"] = (uncertain("M_b", args.masses, "--masses"),)
        except InputError as error:
            raise BadInput(f"{str(error).replace('M_b = ', '')} (need 0 < LOW < HIGH, kg)") from None
    if args.w_lag is not None:
        if not (math.isfinite(args.w_lag) and args.w_lag >= 0):
            raise BadInput(f"--w-lag is {args.w_lag:g}: it must be finite and not negative")
        peak, lag = p0.minimise
        # A weight of 0 drops the term (the objective's weights are positive).
        fields["minimise"] = (peak,) + ((Objective(lag.metric, lag.over, 1e3 * args.w_lag),) if args.w_lag else ())
    if args.set is not None:
        fields["fixed"] = tuple(assignments(args.set).items())
        if any(split_name(name)[0] == "M_b" for name, _ in fields["fixed"]):
            raise BadInput("--set M_b: the body mass is what the tuner varies; give its range with --masses")
    for field, value in (
        ("n_draws", args.train_masses),
        ("margin", args.margin),
        ("jitter", args.jitter),
        ("switch", args.switch),
        ("dt", args.dt),
        ("aggregate", args.aggregate),
        ("temperature", args.temperature),
        ("cvar_alpha", args.cvar_alpha),
    ):
        if value is not None:
            fields[field] = value
    problem = Problem(**fields)
    tuned = problem.names
    clash = [n for n, _ in problem.fixed if any(_overlaps(n, t) for t in tuned)]
    if clash:
        raise BadInput(f"{clash[0]} is both tuned (--params) and fixed (--set): choose one")
    return problem.validate()


def _overlaps(a, b) -> bool:
    """The same parameter, for a robot both names cover."""
    (base_a, robot_a), (base_b, robot_b) = split_name(a), split_name(b)
    return base_a == base_b and (robot_a is None or robot_b is None or robot_a == robot_b)


class Plan:
    """Every flag checked, nothing run: the problem, the tuner, the base parameters, the starts."""

    def __init__(self, args):
        self.problem = problem = build_problem(args)
        names = problem.names
        if args.held_out < 2:
            raise BadInput(f"--held-out is {args.held_out}: judge on at least 2 draws (the lightest and the heaviest)")
        self.tuner = make_tuner(args)
        if args.starts < 1:
            raise BadInput(f"--starts is {args.starts}: it must be a whole number, at least 1")
        if args.seed < 0:
            raise BadInput(f"--seed is {args.seed}: it must be 0 or more")
        if not (math.isfinite(args.spread) and args.spread >= 0):
            raise BadInput(f"--spread is {args.spread:g}: it must be 0 or more")
        if not (math.isfinite(args.judge_dt) and args.judge_dt > 0):
            raise BadInput(f"--judge-dt is {args.judge_dt:g}: it must be positive")
        _check_sizes(args, problem, self.tuner)
        self.base = problem.base()
        self.first = {n: float(np.asarray(self.base.get(n)).ravel()[0]) for n in names}
        self.starts, self.spread, self.seed = args.starts, args.spread, args.seed
        self.held_out_count = args.held_out
        self.held_out = problem.held_out_draws(args.held_out)
        self.judge_dt = args.judge_dt
        # The first start must survive its first step, in training and in judging.
        first = self.base.replace(**self.first)
        for config in problem.configs:
            check_step(first, config)
            check_step(first, judge_config(self.judge_dt, config.scenario).validate())
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
        self.weights = _pareto_weights(args, problem) if args.pareto else None
        if args.compare or args.pareto:
            for name, cls in TUNERS.items():  # every tuner of the study must be able to start
                try:
                    cls().init(self.problem, np.clip(to_log(self.first, names), *problem.log_bounds())[None], 0)
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


# Bytes one training run holds while a batch runs, per value it carries (its state and metric
# accumulators, each with its tangents): a generous round figure, for refusing absurd sizes up front.
RUN_BYTES = 8 * 4 * (20 + 40)
JUDGED_BYTES = 8 * 2 * 24  # one held-out (draw, scenario) row of the judge's tables, at dt and dt/2


def _check_sizes(args, problem: Problem, tuner) -> None:
    """Every size the run holds at once, against half of this machine's memory, before any work:
    one query's batch of runs (candidates x training draws x scenarios), and the judge's tables."""
    limit, scenarios = memory_limit(), len(problem.scenarios)
    gib = lambda b: f"{b / 2**30:.3g} GiB"
    p, n = len(problem.uncertain), len(problem.names)
    draws = problem.n_draws + (2**p if p > 1 else 0)
    draws_flag = "--train-masses" if args.problem is None else "n_draws"
    if problem.n_draws * p * 8 * 4 > limit:
        raise BadInput(
            f"{draws_flag} {problem.n_draws:,}: the training draws alone need {gib(problem.n_draws * p * 32)}, "
            f"more than half of this machine's memory ({gib(limit)})"
        )
    count, setting = tuner.largest_batch(n, args.starts)
    runs = count * draws * scenarios
    if runs * RUN_BYTES * (1 + n) > limit:
        raise BadInput(
            f"{setting} with {draws_flag} {problem.n_draws}: one step would run {runs:,} trajectories at once "
            f"({count:,} candidates x {draws:,} draws x {scenarios} scenario(s)), about "
            f"{gib(runs * RUN_BYTES * (1 + n))}, more than half of this machine's memory ({gib(limit)}): "
            "lower one of them"
        )
    kept, setting = tuner.kept_bytes(n, args.starts, draws * scenarios)
    if kept > limit:
        raise BadInput(
            f"{setting}: the tuner would keep {gib(kept)} of results, more than half of this machine's memory "
            f"({gib(limit)})"
        )
    if args.held_out * scenarios * JUDGED_BYTES > limit:
        raise BadInput(
            f"--held-out {args.held_out:,}: the judge's tables would need "
            f"{gib(args.held_out * scenarios * JUDGED_BYTES)}, more than half of this machine's memory "
            f"({gib(limit)}); at most "
            f"{limit // (scenarios * JUDGED_BYTES):,} draws"
        )


def _pareto_weights(args, problem: Problem) -> list[float]:
    """--pareto's weights of the problem's last objective term."""
    if len(problem.minimise) < 2:
        raise BadInput("--pareto needs a problem with two objective terms (it varies the weight of the last)")
    last = problem.minimise[-1]
    if args.lag_weights is not None and args.pareto_weights is not None:
        raise BadInput("--lag-weights and --pareto-weights say the same thing: give one")
    if args.lag_weights is not None:
        if last.metric != "rms_lag":
            raise BadInput(f"--lag-weights is for a last term on rms_lag; this problem's is {last.metric}")
        weights = [1e3 * w for w in _parse_list(args.lag_weights, "--lag-weights", float)]
    elif args.pareto_weights is not None:
        weights = _parse_list(args.pareto_weights, "--pareto-weights", float)
    else:
        weights = [last.weight / 3, last.weight, last.weight * 8 / 3]
    if any(not (w > 0 and math.isfinite(w)) for w in weights):
        raise BadInput(f"--{'lag' if args.lag_weights else 'pareto'}-weights: give positive numbers")
    return weights


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
    tuner = cls(**settings)
    if not tuner.ends():
        flags = [f for f, owners in tuner_flags().items() if any(c is cls for c, _ in owners)]
        raise BadInput(f"--method {cls.name} ends only when told how far to go: give {' or '.join(flags)}")
    return tuner


def _plain(problem: Problem) -> dict:
    d = {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)}
    d["uncertain"] = {u.name: u.text for u in problem.uncertain}
    d["minimise"] = [o._asdict() for o in problem.minimise]
    d["require"] = [r._asdict() for r in problem.require]
    d["configs"] = [json.loads(c.to_json()) for c in problem.configs]
    d["toml"] = problem.to_toml()
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
        devices.request_devices(args.devices or None)  # a count asked for is not warned about
    except InputError:  # the backend is already up (a test, or an embedding program): keep its devices
        pass
    if args.show_problem:  # before any output is checked: it writes nothing
        print(build_problem(args).to_toml(), end="")
        return 0
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
    starts = plan.starts_for(plan.seed)
    if resume:  # a checkpoint that is not this run's is refused before anything starts or prints
        driver.load_checkpoint(files["checkpoint"], driver.identity(tuner, problem, starts, plan.seed))
    print(
        f"tuning {', '.join(problem.names)} with {tuner.name}: {tuner.plan_text(len(problem.names), plan.starts)}; "
        f"{problem.switch} model ({problem.config.method}, "
        + ", ".join(f"{c.scenario} dt = {c.dt:g} s" for c in problem.configs)
        + f"); {describe_draws(problem.uncertain, problem.training_draws())} per step"
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
        starts,
        plan.seed,
        checkpoint=files["checkpoint"],
        resume=resume,
        progress=quiet,
        total=tuner.expected_evaluations(plan.starts),
        on_step=None if quiet else line,
    )
    tuned, selection = _select(plan, result)
    print(
        f"judging with the hard model (filippov), float64, dt = {plan.judge_dt:g} s, on "
        f"{describe_draws(problem.uncertain, plan.held_out)}, held out, x {len(problem.scenarios)} scenario(s) ..."
    )
    before, start_trace = start_side.result()
    after = judge(tuned, plan.held_out, problem, plan.base, plan.judge_dt)
    history = dict(tuner.history(result.state))
    history.pop("theta", None)
    data = {
        "params": tuned,
        "requirements": after.requirements,
        "holds": after.holds,
        "start": plan.first,
        "before": before.row(),
        "after": after.row(),
        "held_out_draws": {u.name: plan.held_out[:, i].tolist() for i, u in enumerate(problem.uncertain)},
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
    return _exit_code(after)


def _exit_code(verdict) -> int:
    """0 when every requirement holds on the held-out draws; else `EXIT_MISSED`, naming what misses."""
    if verdict.holds:
        return 0
    missed = [r for r in verdict.requirements if not r["met"]]
    reasons = [
        f"{r['requirement']} (margin {r['margin']:.4g} {r['unit']})" if np.isfinite(r["margin"]) else r["requirement"]
        for r in missed
    ]
    if not verdict.measured:
        reasons.append("a held-out run did not finish (diverged, or beyond its step's stability limit)")
    elif verdict.step_artefact:
        reasons.append("a held-out answer moves by more than a tolerance between dt and dt/2 (a step artefact)")
    print(f"the answer written misses: {'; '.join(reasons)} (exit code {EXIT_MISSED})")
    return EXIT_MISSED


def _select(plan: Plan, result):
    """Among the tuner's candidates, the best on the validation draws."""
    problem = plan.problem
    options = [from_log(t, problem.names) for t in result.tuner.candidates(result.state)]
    draws = problem.validation_draws()
    print(
        f"selecting among {len(options)} candidates: hard model on {describe_draws(problem.uncertain, draws)} "
        "for validation (none of them held out) ..."
    )
    # The two-step check is the judge's (below): validating every candidate twice would double the
    # selection's compile and run time for a check that the chosen one gets anyway.
    chosen, verdicts = select(options, draws, problem, plan.base, plan.judge_dt, check_step=False)
    v = verdicts[chosen]
    held = sum(x.holds for x in verdicts)
    print(
        f"  {held} of {len(options)} meet every requirement at every validation draw; the chosen one: "
        + "; ".join(f"{r['requirement']}: worst {r['worst']:.4g} {r['unit']}" for r in v.requirements)
        + f"; objective {v.objective:.4g} N"
    )
    return options[chosen], {
        "candidates": len(options),
        "holding": held,
        "chosen": chosen,
        "validation_draws": {u.name: draws[:, i].tolist() for i, u in enumerate(problem.uncertain)},
        "validation": v.row(),
    }


def _shown(x, unit: str) -> tuple[float, str]:
    """A metric's value and unit for the table (lengths in mm)."""
    return (x * 1e3, "mm") if unit == "m" else (x, unit)


def _print_table(before, after, start, tuned, problem):
    print()
    print(f"{'':<34} {'start (Table 1)':>16} {'tuned':>12}")
    for n in problem.names:
        print(f"{n:<34} {start[n]:>16.5g} {tuned[n]:>12.5g}")
    print("requirements, worst over the held-out draws:")
    met = lambda r, m: f"{'met' if r['met'] else 'MISSED'} ({m:+.3g})"
    for rb, ra in zip(before.requirements, after.requirements):
        wb, unit = _shown(rb["worst"], rb["unit"])
        wa, _ = _shown(ra["worst"], ra["unit"])
        bound = _shown(ra["bound_value"], ra["unit"])[0]
        print(f"  {ra['metric'] + f' [{unit}]':<32} {wb:>16.4g} {wa:>12.4g}")
        label = f"  {'>=' if ra['kind'] == 'at_least' else '<='} {bound:.4g}: met? (margin)"
        print(
            f"  {label:<32} {met(rb, _shown(rb['margin'], rb['unit'])[0]):>16} "
            f"{met(ra, _shown(ra['margin'], ra['unit'])[0]):>12}"
        )
    print("objective:")
    for tb, ta in zip(before.terms, after.terms):
        unit = METRICS[ta["metric"]].unit
        vb, shown = _shown(tb["value"], unit)
        va, _ = _shown(ta["value"], unit)
        print(f"  {ta['over'] + ' ' + ta['metric'] + f' [{shown}]':<32} {vb:>16.4g} {va:>12.4g}")
    print(f"  {'sum of weight x term [N]':<32} {before.objective:>16.4g} {after.objective:>12.4g}")
    for key, label in (("peak_grip", "worst peak grip [N]"), ("rms_lag", "worst RMS lag [mm]")):
        if key in after.worst and not any(t["metric"] == key for t in after.terms):
            scale = 1e3 if key == "rms_lag" else 1.0
            print(f"  {label:<32} {before.worst[key] * scale:>16.4g} {after.worst[key] * scale:>12.4g}")
    verdict = lambda v: "yes" if v.holds else "NO"
    print(f"{'every requirement holds':<34} {verdict(before):>16} {verdict(after):>12}")
    check = lambda v: (
        "not run"
        if not np.isfinite(v.step_error)
        else f"{'ARTEFACT' if v.step_artefact else 'ok'} ({v.step_error:.2f})"
    )
    print(f"{'dt/2 check (1 = tolerance)':<34} {check(before):>16} {check(after):>12}")
    print()


class _StartSide(threading.Thread):
    """The start's verdict and traces, which do not depend on the tuning, computed in a background
    thread while the tuner runs. A run of small batches leaves part of the cores idle, and these
    compile the judge's programs (at dt and dt/2) and the traces' one, which the tuned set's verdict
    and traces then reuse: 7 to 9 s off a cold default run (with one judging block for every size,
    `JUDGE_BLOCK`). An error is raised where the result is asked."""

    def __init__(self, plan: Plan):
        super().__init__(daemon=True, name="coopjax-judge")  # Ctrl-C does not wait for it
        self.plan, self.value, self.error = plan, None, None
        self.start()

    def run(self):
        plan = self.plan
        try:
            self.value = (
                judge(plan.first, plan.held_out, plan.problem, plan.base, plan.judge_dt),
                _trace(plan, plan.first),
            )
        except BaseException as error:  # noqa: BLE001 (re-raised in the main thread)
            self.error = error

    def result(self):
        self.join()
        if self.error is not None:
            raise self.error
        return self.value


def _ends(plan: Plan) -> np.ndarray:
    """The two held-out draws traced: every uncertain parameter at its box's low end, then its high
    end (the lightest and the heaviest body with the default problem)."""
    p = len(plan.problem.uncertain)
    return plan.held_out[[0, -1 if p == 1 else 2**p - 1]]


def _trace(plan: Plan, values):
    """The recorded run of one parameter set at the two end draws, on the problem's first scenario."""
    ends = _ends(plan)
    drawn = {u.name: ends[:, i] for i, u in enumerate(plan.problem.uncertain)}
    params = plan.base.replace(**values, **drawn)
    if "M_b" not in drawn:
        params = params.replace(M_b=np.full(2, float(np.asarray(plan.base.M_b))))
    config = judge_config(plan.judge_dt, plan.problem.scenarios[0])
    return simulate(params, config, every=1, check_dt=False).trajectory


def _plots(plan: Plan, tuned, start_trace, result, files, out: Outputs):
    p = plan.problem
    what = ", ".join(p.names) if len(p.names) <= 4 else f"{len(p.names)} parameters"
    plot_history(
        plan.tuner.history(result.state),
        out.path(files["history"]),
        f"tuning {what} with {plan.tuner.name} on the {p.switch} model (dt = {p.train_dt:g} s), "
        f"{p.n_training} training draws\n{plan.tuner.plan_text(len(p.names), plan.starts)}",
    )
    runs = {"start (Table 1)": start_trace, "tuned": _trace(plan, tuned)}
    units = {u.name: PARAMETERS[split_name(u.name)[0]].unit for u in p.uncertain}
    labels = [", ".join(f"{u.name} = {x:.3g} {units[u.name]}" for u, x in zip(p.uncertain, row)) for row in _ends(plan)]
    scenario = scenarios.get(p.scenarios[0])
    plot_traces(
        runs,
        labels,
        float(np.asarray(plan.base.F_lim).min()),
        float(np.asarray(plan.base.F_max)),
        out.path(files["traces"]),
        scenario=scenario.name,
        window=scenario.windows.get("grip"),
    )


def _tuners(plan: Plan) -> dict:
    """Every registered tuner: the plan's own first, with its flags (it sets the others' budget),
    then the others with their defaults."""
    others = {name: cls() for name, cls in TUNERS.items() if name != plan.tuner.name}
    return {plan.tuner.name: plan.tuner} | others


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
        held_out_count=plan.held_out_count,
    )
    result["config"] = plan.describe()
    with Outputs() as out:
        write_json(out.path(files["out"]), result)
        plot_race(result, out.path(files["race"]))
    race.print_summary(result)
    print(f"wrote {files['out']} and {files['race']}")
    return 0


def _pareto(plan: Plan, files) -> int:
    problem0 = plan.problem
    names = problem0.names
    draws = problem0.validation_draws()
    tuners = _tuners(plan)
    first, last = problem0.minimise[0], problem0.minimise[-1]
    rows_in: list[tuple[str, str, float | None, dict]] = []  # (kind, tuner, weight, params)
    cloud: list[dict] = []
    budget = None
    for weight in plan.weights:
        problem = dataclasses.replace(problem0, minimise=problem0.minimise[:-1] + (last._replace(weight=weight),))
        starts = plan.starts_for(plan.seed, problem)
        print(f"-- weight of {last.over} {last.metric}: {weight:g}")
        for name, tuner in tuners.items():
            # The plan's tuner first (`_tuners` puts it first), to its own end; the others get its time.
            limit = driver.Budget() if name == plan.tuner.name else driver.Budget(seconds=budget)
            result = driver.run(tuner, problem, plan.base, starts, plan.seed, budget=limit, progress=True)
            if name == plan.tuner.name:
                budget = result.elapsed
            options = [from_log(t, names) for t in tuner.candidates(result.state)]
            options += [from_log(result.record.thetas[i], names) for _, i in race.snapshots(result.record)]
            if options:
                chosen = select(options, draws, problem, plan.base, plan.judge_dt)[0]
                rows_in.append(("front", name, weight, options[chosen]))
            if weight == plan.weights[0]:  # the cloud of what held in training, once
                cloud += [from_log(t, names) for t, h in zip(result.record.thetas, result.record.holds) if h][:200]
    flat = [(kind, t, w, p) for kind, t, w, p in rows_in] + [("cloud", None, None, p) for p in cloud]
    print(f"judging {len(flat)} parameter sets on the held-out draws ...")
    verdicts = judge([p for *_, p in flat], plan.held_out, problem0, plan.base, plan.judge_dt)
    scale = lambda metric: 1e3 if METRICS[metric].unit == "m" else 1.0
    rows = [
        {
            "kind": kind,
            "tuner": t,
            "weight": w,
            "params": {k: float(v) for k, v in p.items()},
            "x": v.terms[-1]["value"] * scale(last.metric),
            "y": v.terms[0]["value"] * scale(first.metric),
            **v.row(),
        }
        for (kind, t, w, p), v in zip(flat, verdicts)
    ]
    unit = lambda o: _shown(1.0, METRICS[o.metric].unit)[1]
    axis = lambda o: f"{o.over} {o.metric} over the held-out draws [{unit(o)}]"
    with Outputs() as out:
        write_json(
            out.path(files["out"]),
            {
                "pareto": rows,
                "config": plan.describe(),
                "varied": {"metric": last.metric, "over": last.over, "weights": plan.weights},
                "held_out_draws": {u.name: plan.held_out[:, i].tolist() for i, u in enumerate(problem0.uncertain)},
            },
        )
        plot_pareto(rows, out.path(files["pareto"]), axis(last), axis(first))
    for r in rows:
        if r["kind"] == "front":
            print(
                f"  {r['tuner']:<14} weight {r['weight']:>8g}: meets every requirement "
                f"{'yes' if r['holds'] else 'NO ':>3}, {first.over} {first.metric} {r['y']:.4g} {unit(first)}, "
                f"{last.over} {last.metric} {r['x']:.4g} {unit(last)}"
            )
    print(f"wrote {files['out']} and {files['pareto']}")
    return 0
