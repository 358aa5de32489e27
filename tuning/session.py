"""A tuning session: a problem, a tuner and their options, checked (`prepare`), then run (`run`).

Every front end runs the same session: `tuning.tune`, `coopjax tune`, the race (`--compare`) and the
Pareto study (`--pareto`). `prepare` holds every check that needs no simulation beyond one
linearisation, each an `InputError` that names its field; `run` goes through the driver, selects
among the tuner's candidates on validation draws and judges the choice on held-out draws:

    session = prepare(problem, ScreenSLP(), Options(seed=1))
    tuned = run(session)                         # tuned.params, tuned.verdict, tuned.validation, ...

What is kept while a run goes is the recorder's business (OpenMDAO's recorders): `driver.Checkpoint`
keeps the log in a file after every evaluation, and a run resumed from it replays that log.
"""

from __future__ import annotations

import dataclasses
import threading
from typing import Any, Callable, NamedTuple

import numpy as np

from coopjax.config import check_setting, setting
from coopjax.errors import InputError
from coopjax.params import Params
from coopjax.simulation import memory_limit, simulate
from coopjax.stability import check_step
from tuning import driver
from tuning.design import describe as describe_draws
from tuning.judging import JUDGE_DT, REFINE, Verdict, judge, judge_config, missed_at, preferred, select, worst_case
from tuning.problem import Problem, from_log, to_log
from tuning.training import EDGE, measurable_step, starting_points, step_edge
from tuning.tuners import Tuner


@dataclasses.dataclass(frozen=True)
class Options:
    """How a session runs its problem: where it starts, how it is judged. Declared once here; the
    command's flags and `tuning.tune`'s keywords are these fields."""

    starts: int = setting(
        8,
        "starting points run as one batch; the first is the base's (Table 1's)",
        "--starts",
        kind=int,
        check=lambda x: None if x >= 1 else "it must be a whole number, at least 1",
    )
    spread: float = setting(
        2.5,
        "random starts lie within x/÷ e^SPREAD of the first; a screening tuner searches the same box",
        "--spread",
        kind=float,
        check=lambda x: None if x >= 0 else "it must be 0 or more",
    )
    seed: int = setting(
        0,
        "seed of the random starts, the draws and the tuner",
        "--seed",
        kind=int,
        check=lambda x: None if x >= 0 else "it must be 0 or more",
    )
    held_out: int = setting(
        12,
        "held-out draws for judging: a grid with its ends (one uncertain parameter), or Sobol points besides the "
        "box's corners (several)",
        "--held-out",
        kind=int,
        check=lambda x: None if x >= 2 else "judge on at least 2 draws (the lightest and the heaviest)",
    )
    again: int = setting(
        1,
        "rounds that go on from an answer missing a requirement, with the draws where it misses most added to "
        "training (0: none)",
        "--again",
        kind=int,
        check=lambda x: None if x >= 0 else "it must be 0 or more",
    )
    further: int = setting(
        3,
        "rounds that go on polishing (screen-SLP: --polish more generations) while the answer chosen is the "
        "polish's and each round's best beats it on the validation draws (0: none)",
        "--further",
        kind=int,
        check=lambda x: None if x >= 0 else "it must be 0 or more",
    )
    halvings: int = setting(
        4,
        "rounds that go on polishing at half the training step, each, where no answer meets every requirement and "
        "the chosen one's loop sits on the training step's stability limit, while each round's best beats it on "
        "the validation draws, and never below the finest step the judge refines to (0: none)",
        "--halvings",
        kind=int,
        check=lambda x: None if x >= 0 else "it must be 0 or more",
    )
    judge_dt: float = setting(
        JUDGE_DT,
        "step of the hard model for validation and judging",
        "--judge-dt",
        kind=float,
        unit="s",
        check=lambda x: None if x > 0 else "it must be positive",
    )

    def validate(self) -> "Options":
        for field in dataclasses.fields(self):
            check_setting(field, getattr(self, field.name))
        return self


class Session(NamedTuple):
    """A checked session: nothing has run. `first` is the first start (the base's values of the tuned
    names); `held_out` the (M, p) held-out draws."""

    problem: Problem
    tuner: Tuner
    options: Options
    base: Params
    first: dict
    held_out: np.ndarray
    notes: tuple = ()  # what the session changed in the problem, and why (`training.measurable_step`)

    def starts(self, seed: int | None = None) -> np.ndarray:
        """The (K, n) log-parameter starts every tuner of this session begins from."""
        o = self.options
        seed = o.seed if seed is None else seed
        return starting_points(self.problem, self.base, self.first, o.starts, o.spread, seed)

    def describe(self) -> dict:
        """The session as plain data, for result files."""
        return {
            "tuner": self.tuner.name,
            "tuner_settings": dataclasses.asdict(self.tuner),
            **dataclasses.asdict(self.options),
            "notes": list(self.notes),
        }


class Tuned(NamedTuple):
    """What a session found and how it was judged."""

    params: dict  # the tuned names' values
    verdict: Verdict  # on the held-out draws, with the two-step check
    validation: Verdict  # on the validation draws, where it was selected
    result: driver.Result  # the tuner's run: its record, clock and trajectories
    selection: dict  # how many candidates, how many held, which was chosen, on which draws
    start: Verdict | None = None  # the first start's verdict on the held-out draws (run(judge_start=True))
    start_trace: Any = None  # and its recorded run at the ends of the box (for figures)


LONGER = "the longer polish's best"  # `selection.further`: a round whose best replaced the answer

# Bytes one training run holds while a batch runs, per value it carries (its state and metric
# accumulators, each with its tangents): a generous round figure, for refusing absurd sizes up front.
RUN_BYTES = 8 * 4 * (20 + 40)
JUDGED_BYTES = 8 * 2 * 24  # one held-out (draw, scenario) row of the judge's tables, at dt and dt/2


def _check_sizes(problem: Problem, tuner: Tuner, options: Options) -> None:
    """Every size the run holds at once, against half of this machine's memory: one query's batch of
    runs (candidates x training draws x scenarios), the tuner's record, and the judge's tables."""
    limit, scenarios = memory_limit(), len(problem.scenarios)
    gib = lambda b: f"{b / 2**30:.3g} GiB"
    p, n = len(problem.uncertain), len(problem.names)
    draws = problem.n_draws + (2**p if p > 1 else 0)
    if problem.n_draws * p * 8 * 4 > limit:
        raise InputError(
            f"n_draws {problem.n_draws:,}: the training draws alone need {gib(problem.n_draws * p * 32)}, "
            f"more than half of this machine's memory ({gib(limit)})",
            "n_draws",
        )
    count, setting = tuner.largest_batch(n, options.starts)
    runs = count * draws * scenarios
    if runs * RUN_BYTES * (1 + n) > limit:
        raise InputError(
            f"n_draws {problem.n_draws} with {setting}: one step would run {runs:,} trajectories at once "
            f"({count:,} candidates x {draws:,} draws x {scenarios} scenario(s)), about "
            f"{gib(runs * RUN_BYTES * (1 + n))}, more than half of this machine's memory ({gib(limit)}): "
            "lower one of them",
            "n_draws",
        )
    kept, setting = tuner.kept_bytes(n, options.starts, draws * scenarios)
    if kept > limit:
        raise InputError(
            f"{setting}: the tuner would keep {gib(kept)} of results, more than half of this machine's memory "
            f"({gib(limit)})",
            "tuner",
        )
    if options.held_out * scenarios * JUDGED_BYTES > limit:
        raise InputError(
            f"held_out {options.held_out:,}: the judge's tables would need "
            f"{gib(options.held_out * scenarios * JUDGED_BYTES)}, more than half of this machine's memory "
            f"({gib(limit)}); at most {limit // (scenarios * JUDGED_BYTES):,} draws",
            "held_out",
        )


def with_spread(tuner: Tuner, spread: float) -> Tuner:
    """The tuner with the session's spread where it has a search box of its own (screen-SLP's screen
    is the starts' box): one setting, never two that drift."""
    if "spread" in {f.name for f in dataclasses.fields(tuner)}:
        return dataclasses.replace(tuner, spread=spread)
    return tuner


def prepare(
    problem: Problem | None,
    tuner: Tuner,
    options: Options = Options(),
    base: Params | None = None,
    budget: driver.Budget = driver.Budget(),
) -> Session:
    """Check a session before anything runs. Each mistake is one `InputError` naming its field:
    the problem and the options; whether the tuner ends (on its own, or by `budget`) and can start;
    the memory its batches and the judge's tables need; and the first start's step, in training and
    in judging (its linearised loop must be stable there). The training step is halved where nearly
    none of the starts' box can be measured at it (`training.measurable_step`; `Session.notes`).

    Args:
      problem: the problem (default: the default `Problem`).
      tuner: a tuner instance (`tuning.TUNERS[name](**settings)`).
      options: starts, spread, seed, held-out draws and the judge's step.
      base: every parameter the problem neither tunes nor draws (default Table 1's), a single set.
      budget: what ends a tuner that has no end of its own.
    """
    problem = (problem or Problem()).validate()
    options = options.validate()
    if not isinstance(tuner, Tuner):
        raise InputError(f"tuner is {tuner!r}: a Tuner instance (tuning.TUNERS[name](...))", "tuner")
    tuner = with_spread(tuner, options.spread)
    if not tuner.ends() and budget == driver.Budget():
        raise InputError(
            f"{tuner.name} ends only when told how far to go: give it a budget or a setting that ends it", "budget"
        )
    _check_sizes(problem, tuner, options)
    base = problem.base(base)
    if base.batch_shape:
        raise InputError("base: the base parameters of a session must be a single set, not a batch", "base")
    first = {n: float(np.asarray(base.get(n)).ravel()[0]) for n in problem.names}
    problem, note = measurable_step(problem, base, first, options.spread)
    first_set = base.replace(**first)
    for config in problem.configs:  # the first start must survive its first step, in training and judging
        check_step(first_set, config)
        check_step(first_set, judge_config(options.judge_dt, config.scenario).validate())
    try:  # the tuner can start on this problem (a setting it cannot meet here is refused now)
        tuner.init(problem, np.clip(to_log(first, problem.names), *problem.log_bounds())[None], options.seed)
    except InputError as error:
        raise InputError(f"{tuner.name} cannot start on this problem: {error}", error.field or "tuner") from None
    notes = (note,) if note else ()
    return Session(problem, tuner, options, base, first, problem.held_out_draws(options.held_out), notes)


def ends(session: Session) -> np.ndarray:
    """The two held-out draws traced: every uncertain parameter at its box's low end, then its high
    end (the lightest and the heaviest body with the default problem)."""
    p = len(session.problem.uncertain)
    return session.held_out[[0, -1 if p == 1 else 2**p - 1]]


def trace(session: Session, values: dict):
    """The recorded run of one parameter set at the two end draws, on the problem's first scenario."""
    drawn = {u.name: ends(session)[:, i] for i, u in enumerate(session.problem.uncertain)}
    params = session.base.replace(**values, **drawn)
    if "M_b" not in drawn:
        params = params.replace(M_b=np.full(2, float(np.asarray(session.base.M_b))))
    config = judge_config(session.options.judge_dt, session.problem.scenarios[0])
    return simulate(params, config, every=1, check_dt=False).trajectory


class _Background(threading.Thread):
    """A job that does not depend on the tuning, run while the tuner runs: a run of small batches
    leaves part of the cores idle, and the job compiles programs the later steps reuse. An error is
    raised where the result is asked for."""

    def __init__(self, job: Callable):
        super().__init__(daemon=True, name="coopjax-judge")  # Ctrl-C does not wait for it
        self.job, self.value, self.error = job, None, None
        self.start()

    def run(self):
        try:
            self.value = self.job()
        except BaseException as error:  # noqa: BLE001 (re-raised in the caller's thread)
            self.error = error

    def result(self):
        self.join()
        if self.error is not None:
            raise self.error
        return self.value


def _quiet(text: str) -> None:
    pass


def run(
    session: Session,
    *,
    budget: driver.Budget = driver.Budget(),
    recorder: driver.Checkpoint | None = None,
    judge_start: bool = False,
    progress: bool = False,
    on_step: Callable | None = None,
    log: Callable[[str], None] = _quiet,
) -> Tuned:
    """Run a prepared session: the tuner through the driver, the selection among its candidates on
    the validation draws (where the chosen one is the polish's, up to `options.further` rounds that
    go on polishing while each round's best beats it there: `Tuner.polish_further`; where no
    candidate holds and the chosen one sits on the training step's stability limit, up to
    `options.halvings` rounds of a new polish at half the step each: `Tuner.polish_afresh`), and the
    judge's verdict on the held-out draws; where the judge finds the
    answer missing a requirement worse than validation did, up to `options.again` rounds that go
    on from it with the draws where it misses most added to training (`Tuner.go_on`).

    Args:
      session: from `prepare`.
      budget: when a tuner stops, whichever comes first (seconds of evaluation, trajectories).
      recorder: keeps the run's log as it goes (`driver.Checkpoint`), and resumes from it.
      judge_start: also judge the first start, and record its traces, in a background thread while
        the tuner runs (the judge's and the traces' programs are then compiled for the answer's).
      progress: a progress bar on stderr.
      on_step: `on_step(state, query, evaluation)` after each live evaluation.
      log: where the lines saying what runs now go (default: nowhere).
    """
    problem, tuner, o = session.problem, session.tuner, session.options
    background = None
    if judge_start:
        background = _Background(
            lambda: (
                judge(session.first, session.held_out, problem, session.base, o.judge_dt),
                trace(session, session.first),
            )
        )
    result = driver.run(
        tuner,
        problem,
        session.base,
        session.starts(),
        o.seed,
        budget=budget,
        recorder=recorder,
        progress=progress,
        total=tuner.expected_evaluations(o.starts),
        on_step=on_step,
    )
    options = [from_log(t, problem.names) for t in tuner.candidates(result.state)]
    if not options:
        raise InputError(f"{tuner.name} evaluated nothing within the budget", "budget")
    draws = problem.validation_draws()
    log(
        f"selecting among {len(options)} candidates: hard model on {describe_draws(problem.uncertain, draws)} "
        "for validation (none of them held out) ..."
    )
    # The two-step check is the judge's (below): validating every candidate twice would double the
    # selection's compile and run time for a check that the chosen one gets anyway.
    chosen, verdicts = select(options, draws, problem, session.base, o.judge_dt, check_step=False)
    v = verdicts[chosen]
    held = sum(x.holds for x in verdicts)
    log(
        f"  {held} of {len(options)} meet every requirement at every validation draw; the chosen one: "
        + _missing(v)
        + f"; objective {v.objective:.4g} N"
    )
    selection = {
        "candidates": len(options),
        "holding": held,
        "chosen": chosen,
        "validation_draws": {u.name: draws[:, i].tolist() for i, u in enumerate(problem.uncertain)},
        "validation": _validation_row(v),
    }
    selection["trade_off"] = trade_off(verdicts)

    # Where the answer is the polish's, the polish goes on while each round's best beats it on the
    # validation draws: a longer polish generalises on some problems and fits the training draws on
    # others, and only the validation tells them apart.
    def polish_on(trained: Problem, text: str, afresh: bool = False) -> dict | None:
        """One round that goes on polishing the chosen answer (`afresh`: a new polish from it),
        trained on `trained`: its record in `selection`, with "kept" LONGER where its best replaced
        the answer (None: nothing goes on)."""
        nonlocal result, chosen, v
        theta = to_log(options[chosen], problem.names)
        state = (tuner.polish_afresh if afresh else tuner.polish_further)(result.state, theta)
        if state is None:
            return None
        log(text)
        more = driver.run(tuner, trained, session.base, theta[None], o.seed, state=state, progress=progress)
        result = _added(result, more)._replace(state=more.state)
        longer = [from_log(t, problem.names) for t in tuner.candidates(more.state)] if more.evaluations else []
        longer = [x for x in longer if x != options[chosen]]
        if not longer:
            log("  the answer before stands (the longer polish found nothing better on its training draws)")
            return {"evaluations": more.evaluations, "kept": "nothing better on the training draws"}
        # The round's candidates: the polish's best, or each solve's where the solves ran again.
        k, pool = select([options[chosen], *longer], draws, problem, session.base, o.judge_dt, check_step=False)
        best = pool[k] if k else pool[preferred(pool[1:]) + 1]
        record = {
            "evaluations": more.evaluations,
            "kept": LONGER if k else "the answer before",
            "violation": [pool[0].violation, best.violation],
            "objective": [pool[0].objective, best.objective],
        }
        if k == 0:
            longer_text = f"{_missing(best)}; objective {best.objective:.4g}"
            log(f"  the answer before stands (the longer polish's: {longer_text})")
            return record
        options.append(longer[k - 1])
        chosen, v = len(options) - 1, best
        selection["chosen"], selection["trade_off"] = chosen, trade_off(verdicts + [best])
        selection["validation"] = _validation_row(v)
        log(f"  a better answer found: {_missing(v)}; objective {v.objective:.4g} N")
        return record

    selection["further"] = []
    for _ in range(o.further):
        record = polish_on(problem, "the search goes on from the chosen answer (--further) ...")
        if record is not None:
            selection["further"].append(record)
        if record is None or record["kept"] != LONGER:
            break
    # Where no answer meets every requirement and the chosen one's loop sits on the training step's
    # stability limit, the search pressed against what that step can measure (`step_edge`): a new
    # polish from it runs at half the step (`Tuner.polish_afresh`), then at half that, while each
    # round's best beats the answer on the validation draws and sits on the new step's limit again.
    # Later rounds (`again`) train at the step reached.
    trained = problem
    selection["finer"] = []
    for _ in range(o.halvings):
        # Below the judge's finest refinement, a trained answer's values could not be judged.
        if v.holds or trained.train_dt / 2 < o.judge_dt / 2**REFINE * (1 - 1e-9):
            break
        edge = step_edge(trained, session.base, options[chosen])
        if edge > EDGE:
            break
        limit = edge * trained.train_dt
        trained = dataclasses.replace(trained, dt=trained.train_dt / 2)
        record = polish_on(
            trained,
            f"no answer meets every requirement, and the chosen one's loop needs a step of {limit:.3g} s at a "
            f"training draw, the training step's limit: a new polish from it at {trained.train_dt:g} s ...",
            afresh=True,
        )
        if record is not None:
            selection["finer"].append({**record, "dt": trained.train_dt})
        if record is None or record["kept"] != LONGER:
            break
    log(
        f"judging with the hard model (filippov), float64, dt = {o.judge_dt:g} s, on "
        f"{describe_draws(problem.uncertain, session.held_out)}, held out, x {len(problem.scenarios)} scenario(s) ..."
    )
    start, start_trace = background.result() if background else (None, None)
    verdict, new = _judged(session, options[chosen], draws, log)
    # Where the answer misses a requirement at a draw the tuner never trained on (a narrow band of
    # the box between its fixed draws), worse than at every validation draw, that draw goes into the
    # training draws and the tuner goes on from the answer (`Tuner.go_on`); the validation, with the
    # draw, keeps whichever is better, and the judge searches between its draws again.
    selection["again"] = []
    for _ in range(o.again):
        # Only where the judge found the answer missing more than its validation did: where validation
        # saw the miss as large already (a grip lost), a round measured changed nothing but the time.
        if verdict.holds or verdict.violation <= v.violation * (1 + 1e-6):
            break
        add = problem.within_box(missed_at(verdict, np.concatenate([session.held_out, new])))
        theta = to_log(options[chosen], problem.names)
        state = tuner.go_on(result.state, theta, add)
        if state is None:
            break
        log(
            f"the answer misses {', '.join(r['requirement'] for r in verdict.requirements if not r['met'])}: "
            f"going on with {describe_draws(problem.uncertain, add)} in the training draws ..."
        )
        more = driver.run(tuner, trained, session.base, theta[None], o.seed, state=state, progress=progress)
        result = _added(result, more)
        fresh = [from_log(t, problem.names) for t in tuner.candidates(more.state)] if more.evaluations else []
        pool = [options[chosen], *fresh]
        k, verdicts = select(pool, np.concatenate([draws, add]), problem, session.base, o.judge_dt, check_step=False)
        selection["again"].append(
            {
                "added": {u.name: add[:, i].tolist() for i, u in enumerate(problem.uncertain)},
                "candidates": len(fresh),
                "kept": "the new polish's best" if k else "the answer before",
                "violation": [verdicts[0].violation, verdicts[k].violation],
                "objective": [verdicts[0].objective, verdicts[k].objective],
            }
        )
        if k == 0:
            log("  the answer before stands (the round found nothing better on the validation draws with them)")
            break
        options.append(pool[k])
        chosen, v = len(options) - 1, verdicts[k]
        selection["chosen"], selection["trade_off"] = chosen, trade_off(verdicts)
        selection["validation"] = _validation_row(v)
        log(f"  a better answer found: {_missing(v)}; objective {v.objective:.4g} N")
        verdict, new = _judged(session, options[chosen], draws, log)
    return Tuned(options[chosen], verdict, v, result, selection, start, start_trace)


def _validation_row(v: Verdict) -> dict:
    """A validation verdict as data. Selection runs no two-step check: its fields are left out, not
    written as unmeasured."""
    return {k: x for k, x in v.row().items() if k not in ("step_error", "step_artefact")}


def _added(result: driver.Result, more: driver.Result) -> driver.Result:
    """`result`'s clock and counts with a run that went on from it (its record and state stay)."""
    return result._replace(
        elapsed=result.elapsed + more.elapsed,
        compile_s=result.compile_s + more.compile_s,
        trajectories=result.trajectories + more.trajectories,
        evaluations=result.evaluations + more.evaluations,
    )


def _judged(session: Session, values: dict, validation, log) -> tuple[Verdict, np.ndarray]:
    """The judge's verdict on the held-out draws and the worst cases found between them, and those
    (E, p) draws (none when nothing worse was found)."""
    problem, o = session.problem, session.options
    verdict = judge(values, session.held_out, problem, session.base, o.judge_dt)
    # The search starts from the worst of the held-out and the validation draws (brought into the
    # box): a peak in a narrow band of masses (90 N at one validation mass, 53 N at every held-out
    # one) is found only from near it.
    near = np.concatenate([session.held_out, problem.within_box(validation)])
    found = worst_case(values, near, problem, session.base, o.judge_dt)
    new = np.array([x for x in found if not np.isclose(session.held_out, x).all(1).any()]).reshape(-1, found.shape[1])
    if len(new):
        log(f"searching between the held-out draws: {len(new)} worse draw(s) found, judged with them ...")
        verdict = judge(values, session.held_out, problem, session.base, o.judge_dt, extra=new)
    return verdict, new


def _missing(v: Verdict) -> str:
    return "; ".join(f"{r['requirement']}: worst {r['worst']:.4g} {r['unit']}" for r in v.requirements)


def trade_off(verdicts: list[Verdict]) -> str | None:
    """Where no candidate meets every requirement: the requirement that binds (the chosen one's
    worst miss) and the best value of it among the candidates that meet every other one on the
    validation draws ("with min_grip >= F_lim held at every draw, the smallest peak_grip found is
    43.1 N"); None when some candidate holds."""
    if any(v.holds for v in verdicts):
        return None
    chosen = verdicts[preferred(verdicts)]
    if chosen.binding is None:
        return None
    i = [r["requirement"] for r in chosen.requirements].index(chosen.binding["requirement"])
    others = [r["requirement"] for j, r in enumerate(chosen.requirements) if j != i]
    fine = [v for v in verdicts if v.measured and all(r["met"] for j, r in enumerate(v.requirements) if j != i)]
    r = chosen.requirements[i]
    scale, unit = (1e3, "mm") if r["unit"] == "m" else (1.0, r["unit"])
    if not fine:
        return (
            f"no candidate met every requirement but {r['requirement']}; the least miss of it found is "
            f"{-r['margin'] * scale:.4g} {unit}"
        )
    best = min(fine, key=lambda v: -v.requirements[i]["margin"]).requirements[i]
    word = "smallest" if r["kind"] == "at_most" else "largest"
    held = f"with {' and '.join(others)} held at every validation draw, " if others else ""
    return (
        f"{held}the {word} {r['metric']} found is {best['worst'] * scale:.4g} {unit} "
        f"(bound {best['bound_value'] * scale:.4g} {unit})"
    )
