"""`coopjax tune`: parse the flags, run a tuning session (`tuning.session`), report (`tuning.report`).

Registered with the `coopjax` command through the entry-point group `coopjax.commands` (see
pyproject.toml), so that `coopjax` never imports this package. Modes: a plain run (the default),
`--compare` (the race of every registered tuner over seeds, `tuning.studies.race`), and `--pareto`
(one run per weight of the last objective term, `tuning.studies.pareto`). Every flag is generated
from a declaration: the session's `Options`, the problem's settings and aliases
(`tuning.shorthands`), and each tuner's settings.
"""

from __future__ import annotations

import dataclasses
import os
import time

import jax

from coopjax import devices
from coopjax.cli import interrupts
from coopjax.cli.common import BadInput, add_setting, check_output
from coopjax.errors import InputError
from coopjax.io import Outputs, one_run, write_json
from tuning import driver, report, session, shorthands
from tuning.api import DEFAULT_METHOD
from tuning.problem import Problem
from tuning.studies import pareto, race
from tuning.tuners import TUNERS

NAME = "tune"
DEFAULT_OUT = "tuned.json"
EXIT_MISSED = report.EXIT_MISSED


def methods() -> dict:
    """The registered tuners a plain run can end on its own (`Tuner.plain_run`)."""
    return {name: cls for name, cls in TUNERS.items() if cls.plain_run}


def tuner_flags() -> dict[str, list]:
    """Every flag the plain-run tuners declare: flag -> [(tuner class, field)]."""
    flags: dict[str, list] = {}
    for cls in methods().values():
        for field in dataclasses.fields(cls):
            if field.metadata.get("flag"):
                flags.setdefault(field.metadata["flag"], []).append((cls, field))
    return flags


# API names whose flag is not their own spelling (`names` is --params, `learning_rate` --lr), for
# `coopjax`'s messages.
FIELD_FLAGS = {dest: flag for flag, dest, _ in shorthands.flags()} | {
    f.name: flag for flag, owners in tuner_flags().items() for _, f in owners
}


def _dest(flag: str) -> str:
    return "tuner_" + flag[2:].replace("-", "_")


def add_parser(sub):
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
        help="the tuning problem, a TOML file (docs/tuning.md); the "
        "flags of the default problem (below) are then refused",
    )
    p.add_argument("--show-problem", action="store_true", help="print the effective problem as a file, and stop")
    p.add_argument(
        "--method",
        default=DEFAULT_METHOD,
        choices=list(methods()),
        help=f"the tuner (default {DEFAULT_METHOD}); its settings are the flags that name it below",
    )
    problem = p.add_argument_group("the default problem (without --problem)")
    for flag, dest, declared in shorthands.flags():
        if isinstance(declared, shorthands.Alias):
            problem.add_argument(
                flag,
                dest=dest,
                metavar=declared.metavar,
                type=declared.kind,
                help=declared.help,
                action="append" if declared.repeat else "store",
            )
        else:
            add_setting(problem, declared, dest)
    options = p.add_argument_group("the session")
    for field in dataclasses.fields(session.Options):
        add_setting(options, field, field.name, field.default)
    for flag, owners in tuner_flags().items():
        text = "; ".join(f"{cls.name}: {f.metadata['help']} (default {f.default})" for cls, f in owners)
        add_setting(p, owners[0][1], _dest(flag), text=text)
    p.add_argument("--out", default=DEFAULT_OUT, help=f"result file (default {DEFAULT_OUT}); plots go beside it")
    p.add_argument("--resume", action="store_true", help="continue an interrupted plain run from OUT.ckpt")
    p.add_argument("--compare", action="store_true", help="race every registered tuner over --seeds on one clock")
    p.add_argument("--seeds", default="0,1,2,3,4", help="seeds of --compare (default 0,1,2,3,4)")
    p.add_argument(
        "--race-budget",
        default="time",
        choices=race.BUDGETS,
        help="--compare: every tuner gets the --method's wall time (time, the default) or as many "
        "simulated trajectories (trajectories)",
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
    p.add_argument("--devices", type=int, default=None, help="CPU devices (default: one per core)")
    p.add_argument("--quiet", action="store_true", help="a progress bar instead of a line per step")
    return p


def _numbers(text, what, cast):
    try:
        out = [cast(x.strip()) for x in text.split(",") if x.strip()]
    except ValueError:
        raise BadInput(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if not out:
        raise BadInput(f"{what}: give at least one value")
    if len(set(out)) != len(out):
        raise BadInput(f"{what}: {text!r} names a value twice")
    return out


def build_problem(args) -> Problem:
    """The problem of a run: the --problem file, or the default problem with its flags."""
    given = _given(args)
    if args.problem is not None:
        if given:
            flag = next(f for f, d, _ in shorthands.flags() if d in given)
            raise BadInput(f"{flag} contradicts --problem {args.problem}: state it in the file instead")
        return Problem.from_toml(args.problem)
    return shorthands.problem_from(given)


def _given(args) -> dict:
    """The default problem's flags that were given."""
    return {dest: getattr(args, dest) for _, dest, _ in shorthands.flags() if getattr(args, dest) is not None}


def make_tuner(args):
    """The --method's tuner with the flags that were given (the others at its defaults); a flag of
    another tuner is refused."""
    cls, settings = methods()[args.method], {}
    for flag, owners in tuner_flags().items():
        value = getattr(args, _dest(flag))
        field = next((f for c, f in owners if c is cls), None)
        if value is not None and field is None:
            raise BadInput(
                f"{flag} sets the {' and '.join(c.name for c, _ in owners)} tuner; this run's method is {cls.name}"
            )
        if value is not None:
            settings[field.name] = value
    tuner = cls(**settings)
    if not tuner.ends():
        flags = [f for f, owners in tuner_flags().items() if any(c is cls for c, _ in owners)]
        raise BadInput(f"--method {cls.name} ends only when told how far to go: give {' or '.join(flags)}")
    return tuner


def _sessions(prepared, study: str) -> dict:
    """A study's sessions: the plan's tuner first (it sets the others' budget), then every other
    registered tuner with its defaults; each must be able to run this problem."""
    out = {prepared.tuner.name: prepared}
    for name, cls in TUNERS.items():
        if name != prepared.tuner.name:
            try:
                out[name] = session.prepare(prepared.problem, cls(), prepared.options, prepared.base, driver.Budget(1))
            except InputError as error:
                raise BadInput(f"--{study} runs every tuner, and {name} cannot: {error}") from None
    return out


def run(args) -> int:
    jax.config.update("jax_enable_x64", True)  # training and judging are float64; before any array exists
    if args.devices is not None and args.devices < 1:
        raise BadInput(f"--devices is {args.devices}: it must be at least 1")
    try:
        devices.request_devices(args.devices or None)  # a count asked for is not warned about
    except InputError:  # the backend is already up (a test, or an embedding program): keep its devices
        pass
    notes = Problem.unstated(args.problem) if args.problem is not None and not _given(args) else []
    if args.show_problem:  # before any output is checked: it writes nothing
        problem = build_problem(args)
        print("".join(f"# note: {n}\n" for n in notes) + problem.to_toml(), end="")
        return 0
    check_output(args.out, "--out", ("json",))
    files = report.paths(args.out)
    written = ["race"] if args.compare else ["pareto"] if args.pareto else ["history", "traces", "checkpoint"]
    for key in written:  # every file this run will write, before any work
        check_output(files[key], f"--out (its {key} file)")
    if args.compare and args.pareto:
        raise BadInput("--compare and --pareto are separate runs: choose one")
    with one_run(args.out, "--out"):  # one run per output, checkpoint and figures
        return _held(args, files, notes)


def _held(args, files, notes) -> int:
    if args.resume and (args.compare or args.pareto):
        raise BadInput("--resume continues a plain run; --compare and --pareto start afresh")
    if os.path.exists(files["checkpoint"]) and not args.resume:
        raise BadInput(f"{files['checkpoint']} holds an interrupted run: add --resume to finish it, or delete it")
    if args.resume and not os.path.exists(files["checkpoint"]):
        raise BadInput(f"--resume: there is no {files['checkpoint']} to continue")
    problem = build_problem(args)
    options = session.Options(**{f.name: getattr(args, f.name) for f in dataclasses.fields(session.Options)})
    prepared = session.prepare(problem, make_tuner(args), options)
    if args.compare:
        seeds = _numbers(args.seeds, "--seeds", int)
        if min(seeds) < 0:
            raise BadInput(f"--seeds {args.seeds!r}: every seed must be 0 or more")
        result = race.run(
            _sessions(prepared, "compare"),
            prepared.tuner.name,
            seeds,
            progress=args.quiet,
            budget=args.race_budget,
            target="CMA-ES",
        )
        result["config"] = {"problem": report.problem_data(problem), **prepared.describe()}
        race.save(result, files["out"], files["race"])
        return 0
    if args.pareto:
        if len(problem.minimise) < 2:
            raise BadInput("--pareto needs a problem with two objective terms (it varies the weight of the last)")
        weights = pareto.default_weights(problem)
        if args.pareto_weights is not None:
            weights = _numbers(args.pareto_weights, "--pareto-weights", float)
            if not all(w > 0 and w < float("inf") for w in weights):
                raise BadInput("--pareto-weights: give positive numbers")
        result = pareto.run(_sessions(prepared, "pareto"), prepared.tuner.name, weights)
        result["config"] = {"problem": report.problem_data(problem), **prepared.describe()}
        pareto.save(result, problem, files["out"], files["pareto"])
        return 0
    for note in notes:
        print(f"note: {note}")
    return _tune(prepared, files, args.resume, args.quiet)


def _tune(prepared, files, resume: bool, quiet: bool) -> int:
    start = time.perf_counter()
    problem, tuner = prepared.problem, prepared.tuner
    recorder = driver.Checkpoint(files["checkpoint"], resume)
    if resume:  # a checkpoint that is not this run's is refused before anything starts or prints
        recorder.saved(driver.identity(tuner, problem, prepared.starts(), prepared.options.seed))
    report.opening(prepared)
    interrupts.report_with(
        lambda: (
            f"the checkpoint {files['checkpoint']} is kept; add --resume to the same command to continue"
            if os.path.exists(files["checkpoint"])
            else None
        )
    )

    def line(state, query, ev):
        text = tuner.progress_text(state, query, ev)
        if text:
            print(text)

    tuned = session.run(
        prepared, recorder=recorder, judge_start=True, progress=quiet, on_step=None if quiet else line, log=print
    )
    with Outputs() as out:  # the result and its figures together, or none of them
        nulls = write_json(out.path(files["out"]), report.data(prepared, tuned))
        report.plots(prepared, tuned, files, out)
    recorder.discard()
    interrupts.report_with(lambda: None)
    return report.closing(prepared, tuned, files, nulls, time.perf_counter() - start)
