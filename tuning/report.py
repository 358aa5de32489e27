"""What a tuning session reports: the before/after table, the result file's data, the figures and
the exit code. The command prints and writes these; nothing here parses or runs a session."""

from __future__ import annotations

import dataclasses
import json
import textwrap

import numpy as np

from coopjax import scenarios
from coopjax.io import Outputs
from coopjax.objectives import METRICS
from coopjax.params import PARAMETERS, split_name
from tuning.design import describe as describe_draws
from tuning.plots import plot_history, plot_traces
from tuning.problem import HOLD_TOLERANCE, Problem
from tuning.session import LONGER, Session, Tuned, ends, trace

EXIT_MISSED = 3  # the answer written misses a requirement on the held-out draws


def data(session: Session, tuned: Tuned) -> dict:
    """The result file of a plain run."""
    history = dict(session.tuner.history(tuned.result.state))
    history.pop("theta", None)
    result = tuned.result
    return {
        "params": tuned.params,
        "requirements": tuned.verdict.requirements,
        "holds": tuned.verdict.holds,
        "start": session.first,
        "before": tuned.start.row() if tuned.start is not None else None,
        "after": tuned.verdict.row(),
        "held_out_draws": {u.name: session.held_out[:, i].tolist() for i, u in enumerate(session.problem.uncertain)},
        "judge": {
            "switch": "hard",
            "contact": "unilateral",
            "integrator": "filippov",
            "dtype": "float64",
            "dt": session.options.judge_dt,
            "hold_tolerance_N": HOLD_TOLERANCE,
        },
        "config": {"problem": problem_data(session.problem), **session.describe()},
        "method": session.tuner.plan_text(len(session.problem.names), session.options.starts),
        "history": history,
        "trajectories": result.trajectories,
        "tuning_seconds": result.elapsed,
        "compile_seconds": result.compile_s,
        "selection": tuned.selection,
    }


def opening(session: Session) -> None:
    """The run's first line: what is tuned, how, on which model and draws."""
    problem, tuner = session.problem, session.tuner
    plan = tuner.plan_text(len(problem.names), session.options.starts)
    print(
        f"tuning {', '.join(problem.names)} with {tuner.name}: {plan}; "
        f"{problem.switch} model ({problem.config.method}, "
        + ", ".join(f"{c.scenario} dt = {c.dt:g} s" for c in problem.configs)
        + f"); {describe_draws(problem.uncertain, problem.training_draws())} per step"
    )
    for note in session.notes:
        print(f"note: {note}")


def closing(session: Session, tuned: Tuned, files: dict, nulls: list, seconds: float) -> int:
    """The before/after table, what was written, and the exit code."""
    print_table(tuned.start, tuned.verdict, session.first, tuned.params, session.problem)
    if nulls:
        more = f" and {len(nulls) - 4} more" if len(nulls) > 4 else ""
        print(f"(not finite, so null in {files['out']}: {', '.join(nulls[:4])}{more})")
    r = tuned.result
    print(
        f"{r.trajectories} trajectories, {r.elapsed:.0f} s of tuning (+ {r.compile_s:.0f} s compiling), "
        f"{seconds:.0f} s in all"
    )
    print(f"wrote {files['out']}, {files['history']} and {files['traces']}")
    return exit_code(tuned.verdict, tuned.selection.get("trade_off"))


def exit_code(verdict, trade_off: str | None = None) -> int:
    """0 when every requirement holds on the held-out draws; else `EXIT_MISSED`, naming what misses,
    the requirement that binds with its least violation, and the trade-off the candidates showed."""
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
    if verdict.binding is not None:
        r = verdict.binding
        worst, unit = shown(r["worst"], r["unit"])
        print(
            f"binding: {r['requirement']}, worst {worst:.4g} {unit} against {shown(r['bound_value'], r['unit'])[0]:.4g}"
            f" (least violation found {verdict.violation:.3g} of the bound)"
        )
    if trade_off:
        print(f"trade-off: {trade_off}")
    return EXIT_MISSED


def shown(x, unit: str) -> tuple[float, str]:
    """A metric's value and unit for display (lengths in mm)."""
    return (x * 1e3, "mm") if unit == "m" else (x, unit)


def verdict_text(r: dict) -> str:
    """A requirement's verdict and margin: `met` only where the margin clears the bound, `within tol.`
    where the tolerance takes it (the grip's, on the sliding surface), `MISSED` beyond."""
    margin = shown(r["margin"], r["unit"])[0]
    if not np.isfinite(margin):
        return "not measured"
    word = "MISSED" if not r["met"] else "met" if r["margin"] >= 0 else "within tol."
    return f"{word} ({margin:+.3g})"


def print_table(before, after, start, tuned, problem: Problem) -> None:
    print()
    print(f"{'':<34} {'start (Table 1)':>22} {'tuned':>22}")
    for n in problem.names:
        print(f"{n:<34} {start[n]:>22.5g} {tuned[n]:>22.5g}")
    print("requirements, worst over the held-out draws:")
    for rb, ra in zip(before.requirements, after.requirements):
        wb, unit = shown(rb["worst"], rb["unit"])
        wa, _ = shown(ra["worst"], ra["unit"])
        bound = shown(ra["bound_value"], ra["unit"])[0]
        print(f"  {ra['metric'] + f' [{unit}]':<32} {wb:>22.4g} {wa:>22.4g}")
        tolerance = shown(ra["tolerance"], ra["unit"])[0]
        within = f", tolerance {tolerance:g}" if tolerance else ""
        label = f"  {'>=' if ra['kind'] == 'at_least' else '<='} {bound:.4g}{within}: margin"
        print(f"  {label:<32} {verdict_text(rb):>22} {verdict_text(ra):>22}")
    print("objective:")
    for tb, ta in zip(before.terms, after.terms):
        unit = METRICS[ta["metric"]].unit
        vb, label = shown(tb["value"], unit)
        va, _ = shown(ta["value"], unit)
        print(f"  {ta['over'] + ' ' + ta['metric'] + f' [{label}]':<32} {vb:>22.4g} {va:>22.4g}")
    print(f"  {'sum of weight x term [N]':<32} {before.objective:>22.4g} {after.objective:>22.4g}")
    for key, label in (("peak_grip", "worst peak grip [N]"), ("rms_lag", "worst RMS lag [mm]")):
        if key in after.worst and not any(t["metric"] == key for t in after.terms):
            factor = 1e3 if key == "rms_lag" else 1.0
            print(f"  {label:<32} {before.worst[key] * factor:>22.4g} {after.worst[key] * factor:>22.4g}")
    verdict = lambda v: "yes" if v.holds else "NO"
    print(f"{'every requirement holds':<34} {verdict(before):>22} {verdict(after):>22}")
    check = lambda v: (
        "not run"
        if not np.isfinite(v.step_error)
        else f"{'ok' if v.step_error <= 1 else 'ARTEFACT' if v.step_artefact else 'over'} ({v.step_error:.2f})"
    )
    print(f"{'dt/2 check (1 = tolerance)':<34} {check(before):>22} {check(after):>22}")
    print()


def plots(session: Session, tuned: Tuned, files: dict, out: Outputs) -> None:
    """The history of the run and the grip traces of the start and the answer, written through `out`."""
    p, tuner = session.problem, session.tuner
    what = ", ".join(p.names) if len(p.names) <= 4 else f"{len(p.names)} parameters"
    plan = tuner.plan_text(len(p.names), session.options.starts)
    done = tuner.run_text(tuned.result.state)
    plan += f"; {done}" if done else ""
    further = tuned.selection.get("further", [])
    if further:  # not in the figure's curves: the rounds after selection (`session.run`)
        kept = sum(r["kept"] == LONGER for r in further)
        plan += f"; after selection, {len(further)} more round(s) of polish, {kept} kept on the validation draws"
    finer = tuned.selection.get("finer", [])
    if finer:  # the answer sat on the training step's stability limit (`session.run`)
        kept = sum(r["kept"] == LONGER for r in finer)
        plan += (
            f"; then {len(finer)} round(s) of a new polish at half the step each (down to {finer[-1]['dt']:g} s), "
            f"{kept} kept on the validation draws"
        )
    plot_history(
        tuner.history(tuned.result.state),
        out.path(files["history"]),
        f"tuning {what} with {tuner.name} on the {p.switch} model (dt = {p.train_dt:g} s), "
        f"{p.n_training} training draws\n" + textwrap.fill(plan, 130),
    )
    start_trace = tuned.start_trace if tuned.start_trace is not None else trace(session, session.first)
    runs = {"start (Table 1)": start_trace, "tuned": trace(session, tuned.params)}
    units = {u.name: PARAMETERS[split_name(u.name)[0]].unit for u in p.uncertain}
    labels = [
        ", ".join(f"{u.name} = {x:.3g} {units[u.name]}" for u, x in zip(p.uncertain, row)) for row in ends(session)
    ]
    scenario = scenarios.get(p.scenarios[0])
    plot_traces(
        runs,
        labels,
        float(np.asarray(session.base.F_lim).min()),
        float(np.asarray(session.base.F_max)),
        out.path(files["traces"]),
        scenario=scenario.name,
        window=scenario.windows.get("grip"),
    )


def problem_data(problem: Problem) -> dict:
    """The problem as plain data for result files, with the file that states it."""
    d = {f.name: getattr(problem, f.name) for f in dataclasses.fields(problem)}
    d["uncertain"] = {u.name: u.text for u in problem.uncertain}
    d["minimise"] = [o._asdict() for o in problem.minimise]
    d["require"] = [r._asdict() for r in problem.require]
    d["configs"] = [json.loads(c.to_json()) for c in problem.configs]
    d["toml"] = problem.to_toml()
    return d


def paths(out: str) -> dict:
    """The files of a run whose result is OUT: its checkpoint and figures beside it."""
    stem = out[:-5] if out.endswith(".json") else out
    return {
        "out": out,
        "checkpoint": out + ".ckpt",
        "history": stem + "_history.png",
        "traces": stem + "_traces.png",
        "race": stem + "_race.png",
        "pareto": stem + "_pareto.png",
    }
