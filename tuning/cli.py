"""`coopjax tune`: tune on the hard model, judge before/after on held-out masses, write OUT and plots.

Modes: a plain run (the default), `--compare` (the race of the gradient tuner, CMA-ES and random
search over seeds on one clock), and `--pareto` (one run per lag weight; the front of worst-case
peak force against worst-case lag, with CMA-ES's and random search's points).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time

import numpy as np

from coopjax.cliutil import BadInput, check_output, parse_assignment
from coopjax.io import atomic_path

DEFAULT_OUT = "tuned.json"


def add_parser(sub):
    from tuning.objective import AGGREGATES, JUDGE_DT, SURROGATE_DT, SWITCHES, TRAIN_DT, Problem
    from tuning.optimize import TuneConfig

    d, p0 = TuneConfig(), Problem()
    p = sub.add_parser(
        "tune", help="tune the controller on the hard model; judge before/after on held-out masses",
        description="Tune controller parameters on the carry scenario: K starting points at once, Adam on an "
        "augmented Lagrangian (worst-case peak grip force + w_lag x worst-case RMS lag, subject to the grip "
        "holding at every training mass), differentiated through the hard switch under the sliding-mode "
        "integrator. The result is judged with the hard model at --judge-dt on held-out masses. Writes OUT "
        "(json), OUT's _history.png and _traces.png (with --compare: _race.png; with --pareto: _pareto.png).",
    )
    p.add_argument("--params", default="all", help="comma-separated names, or gains (K_GP,K_GI,tau,G_e), per-robot "
                   "(the 4 gains of each robot: 8) or all (per-robot + M_c,R_c,K_c,M_f,R_f,K_f: 14) (default all)")
    p.add_argument("--masses", default="loguniform:0.5:5", help="body-mass range, loguniform:LOW:HIGH or uniform:LOW:HIGH, kg (default loguniform:0.5:5)")
    p.add_argument("--train-masses", type=int, default=p0.n_masses, help=f"training masses per step, one per equal-probability stratum (default {p0.n_masses})")
    p.add_argument("--margin", type=float, default=p0.margin, help=f"the training grid spans the range widened by this fraction (default {p0.margin:g})")
    p.add_argument("--fixed-masses", dest="jitter", action="store_false", help="train on the strata's midpoints every step instead of a fresh draw per stratum")
    p.add_argument("--switch", default="hard", help=f"training model: {', '.join(SWITCHES)} (default hard: the sliding-mode integrator; the others are smooth surrogates under plain RK4)")
    p.add_argument("--dt", type=float, default=None, help=f"training step, s (default {TRAIN_DT:g} for hard, {SURROGATE_DT:g} for the surrogates)")
    p.add_argument("--w-lag", type=float, default=p0.w_lag, help=f"N of worst peak force per mm of worst RMS lag (default {p0.w_lag:g})")
    p.add_argument("--aggregate", default=p0.aggregate, help=f"worst case over masses: {', '.join(AGGREGATES)} (default {p0.aggregate})")
    p.add_argument("--temperature", type=float, default=p0.temperature, help=f"softness of smoothmax, N (default {p0.temperature:g})")
    p.add_argument("--cvar-alpha", type=float, default=p0.cvar_alpha, help=f"cvar: the worst share of masses averaged (default {p0.cvar_alpha:g})")
    p.add_argument("--starts", type=int, default=d.starts, help=f"starting points run as one batch (default {d.starts}; the first is Table 1's)")
    p.add_argument("--steps", type=int, default=d.steps, help=f"optimiser steps (default {d.steps})")
    p.add_argument("--mode", default=d.mode, help="forward, reverse, or auto: forward up to 4 parameters, reverse above (default auto)")
    p.add_argument("--lr", type=float, default=d.learning_rate, help=f"peak learning rate, log units (default {d.learning_rate:g})")
    p.add_argument("--rho", type=float, default=d.rho, help=f"initial penalty of the augmented Lagrangian, 1/N (default {d.rho:g})")
    p.add_argument("--al-every", type=int, default=d.al_every, help=f"steps between multiplier updates (default {d.al_every})")
    p.add_argument("--spread", type=float, default=d.spread, help=f"random starts lie within x/÷ e^SPREAD of the first (default {d.spread:g})")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the random starts and of the mass draws (default 0)")
    p.add_argument("--judge-dt", type=float, default=JUDGE_DT, help=f"step of the hard model for validation and judging, s (default {JUDGE_DT:g})")
    p.add_argument("--held-out", type=int, default=12, help="held-out masses for judging (default 12, ends included)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="fix another parameter (repeatable)")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"result file (default {DEFAULT_OUT}); plots go beside it")
    p.add_argument("--resume", action="store_true", help="continue an interrupted plain run from OUT.ckpt.npz")
    p.add_argument("--compare", action="store_true", help="race the gradient tuner, CMA-ES and random search over --seeds on one clock")
    p.add_argument("--seeds", default="0,1,2,3,4", help="seeds of --compare (default 0,1,2,3,4)")
    p.add_argument("--pareto", action="store_true", help="one run per lag weight: the worst-peak / worst-lag front, with CMA-ES and random search")
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


def build(args):
    """Check every flag and return (TuneConfig, base Params, held-out masses); nothing is run."""
    from coopjax.params import make_params
    from tuning.objective import (SURROGATE_DT, TRAIN_DT, Problem, check_tuned_names, expand_params, held_out_masses)
    from tuning.optimize import PAPER_GAINS, TuneConfig

    names = check_tuned_names(expand_params(args.params))
    masses = _parse_masses(args.masses)
    if args.held_out < 2:
        raise BadInput(f"--held-out is {args.held_out}: judge on at least 2 masses (the lightest and the heaviest)")
    dt = args.dt if args.dt is not None else (TRAIN_DT if args.switch == "hard" else SURROGATE_DT)
    for flag, value in (("--judge-dt", args.judge_dt), ("--dt", dt)):
        if not (math.isfinite(value) and value > 0):
            raise BadInput(f"{flag} is {value:g}: it must be positive")
    fixed = dict(parse_assignment(s) for s in args.set)
    if len(fixed) != len(args.set):
        raise BadInput("--set names a parameter twice")
    tuned_bases = {n.rsplit("_", 1)[0] if n.endswith(("_L", "_R")) else n for n in names}
    clash = [n for n in fixed if n in names or n in tuned_bases or (n.endswith(("_L", "_R")) and n[:-2] in names)]
    if clash:
        raise BadInput(f"{clash[0]} is both tuned (--params) and fixed (--set): choose one")
    base = make_params(**fixed)
    start = {}
    for n in names:
        b = n[:-2] if n.endswith(("_L", "_R")) else n
        start[n] = PAPER_GAINS[b] if (b in PAPER_GAINS and b not in fixed) else float(np.asarray(base.get(n)).ravel()[0])
    problem = Problem(names=names, masses=masses, n_masses=args.train_masses, margin=args.margin, jitter=args.jitter,
                      switch=args.switch,
                      dt=dt, w_lag=args.w_lag, aggregate=args.aggregate, temperature=args.temperature,
                      cvar_alpha=args.cvar_alpha)
    config = TuneConfig(problem=problem, starts=args.starts, steps=args.steps, mode=args.mode, seed=args.seed,
                        learning_rate=args.lr, al_every=args.al_every, rho=args.rho, spread=args.spread,
                        start=tuple(start.items()))
    config.validate()
    from coopjax.stability import check_step

    check_step(base.replace(**start), problem.config)  # the first start must survive its first step
    if args.compare and args.pareto:
        raise BadInput("--compare and --pareto are separate runs: choose one")
    if args.resume and (args.compare or args.pareto):
        raise BadInput("--resume continues a plain run; --compare and --pareto start afresh")
    if args.compare:
        _parse_list(args.seeds, "--seeds", int)
    if args.pareto:
        weights = _parse_list(args.lag_weights, "--lag-weights", float)
        if any(not (x >= 0 and math.isfinite(x)) for x in weights):
            raise BadInput(f"--lag-weights {args.lag_weights!r}: give non-negative numbers")
    return config, base, held_out_masses(masses, args.held_out)


def _parse_masses(text: str):
    from tuning.objective import check_mass_range

    parts = text.split(":")
    if len(parts) != 3 or parts[0] not in ("uniform", "loguniform"):
        raise BadInput(f"--masses expects loguniform:LOW:HIGH or uniform:LOW:HIGH, got {text!r}")
    try:
        masses = (parts[0], float(parts[1]), float(parts[2]))
    except ValueError:
        raise BadInput(f"--masses {text!r}: LOW and HIGH must be numbers") from None
    check_mass_range(masses)
    return masses


def paths(out: str) -> dict:
    stem = out[:-5] if out.endswith(".json") else out
    return {"out": out, "checkpoint": out + ".ckpt.npz", "history": stem + "_history.png", "traces": stem + "_traces.png",
            "race": stem + "_race.png", "pareto": stem + "_pareto.png"}


def cmd_tune(args) -> int:
    import jax

    # Both before any array exists: JAX reads them when its backend starts.
    jax.config.update("jax_enable_x64", True)  # training and judging are float64
    if args.devices is not None and args.devices < 1:
        raise BadInput(f"--devices is {args.devices}: it must be at least 1")
    try:
        jax.config.update("jax_num_cpu_devices", args.devices or os.cpu_count() or 1)
    except RuntimeError:  # the backend is already up (a test, or an embedding program): keep its devices
        pass
    check_output(args.out, "--out", ("json",))
    config, base, held_out = build(args)
    files = paths(args.out)
    written = ["history", "traces", "checkpoint"] if not (args.compare or args.pareto) else (
        ["race"] if args.compare else ["pareto"])
    for key in written:  # every file this run will write, before any work
        check_output(files[key], f"--out (its {key} file)")
    if os.path.exists(files["checkpoint"]) and not args.resume:
        raise BadInput(f"{files['checkpoint']} holds an interrupted run: add --resume to finish it, or delete it")
    if args.resume and not os.path.exists(files["checkpoint"]):
        raise BadInput(f"--resume: there is no {files['checkpoint']} to continue")
    try:
        if args.compare:
            return _compare(args, config, base, files)
        if args.pareto:
            return _pareto(args, config, base, held_out, files)
        return _tune_and_report(args, config, base, held_out, files)
    except KeyboardInterrupt:
        resumable = os.path.exists(files["checkpoint"])
        print("\ncoopjax tune: interrupted" + ("; add --resume to the same command to continue" if resumable else ""),
              file=sys.stderr)
        return 130


def _tune_and_report(args, config, base, held_out, files) -> int:
    from tuning.objective import HOLD_TOLERANCE, judge
    from tuning.optimize import tune

    start = time.perf_counter()
    mode = config.resolved_mode
    print(f"tuning {', '.join(config.problem.names)}: {config.starts} starts x {config.problem.n_masses} training masses "
          f"per step, {config.problem.switch} model ({config.problem.config.method}, dt = {config.problem.dt:g} s), "
          f"{mode} mode, {config.steps} steps")
    state = tune(config, base, checkpoint=files["checkpoint"], resume=args.resume, progress=args.quiet)
    start_values = config.start_values
    tuned, selection = _select(args, config, base, state)
    print(f"judging with the hard model (filippov), float64, dt = {args.judge_dt:g} s, on {len(held_out)} held-out masses "
          f"from {held_out[0]:.3g} to {held_out[-1]:.3g} kg ...")
    w_lag = config.problem.w_lag
    before, after = judge([start_values, tuned], held_out, base, w_lag, args.judge_dt)
    result = {
        "params": tuned,
        "start": start_values,
        "before": before.row(),
        "after": after.row(),
        "held_out_masses": [float(m) for m in held_out],
        "judge": {"switch": "hard", "contact": "unilateral", "integrator": "filippov", "dtype": "float64",
                  "dt": args.judge_dt, "hold_tolerance_N": HOLD_TOLERANCE},
        "config": json.loads(config.to_json()),
        "mode": mode,
        "history": {k: v for k, v in state.history.items() if k != "theta"},
        "trajectories": state.trajectories,
        "tuning_seconds": state.elapsed,
        "selection": selection,
    }
    _write_json(files["out"], result)
    _plots(config, base, held_out, start_values, tuned, state, files, args.judge_dt)
    os.remove(files["checkpoint"])
    _print_table(before, after, start_values, tuned, config)
    print(f"{state.trajectories} trajectories, {state.elapsed:.0f} s of tuning, {time.perf_counter() - start:.0f} s in all")
    print(f"wrote {files['out']}, {files['history']} and {files['traces']}")
    return 0


def _select(args, config, base, state):
    """Among each start's best holding iterate and its final one, the best on validation masses."""
    from tuning.objective import select, validation_masses
    from tuning.optimize import candidates

    options = candidates(state, config.problem.names)
    masses = validation_masses(config.problem)
    print(f"selecting among {len(options)} candidates (each start's best holding iterate and its last): hard model on "
          f"{len(masses)} validation masses from {masses[0]:.3g} to {masses[-1]:.3g} kg (none of them held out) ...")
    chosen, verdicts = select(options, masses, base, config.problem.w_lag, args.judge_dt)
    v = verdicts[chosen]
    held = sum(x.holds for x in verdicts)
    print(f"  {held} of {len(options)} hold at every validation mass; the chosen one: min grip {v.min_grip:.3f} N, "
          f"peak {v.peak_grip:.2f} N, lag {v.rms_lag * 1e3:.2f} mm")
    return options[chosen], {"candidates": len(options), "holding": held, "chosen": chosen,
                             "validation_masses": [float(m) for m in masses], "validation": v.row()}


def _write_json(path, data):
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(data, f, indent=1, allow_nan=True)


def _print_table(before, after, start, tuned, config):
    names = config.problem.names
    print()
    print(f"{'':<30} {'start (Table 1)':>16} {'tuned':>12}")
    for n in names:
        print(f"{n:<30} {start[n]:>16.5g} {tuned[n]:>12.5g}")
    rows = [("worst min grip [N]", "min_grip", 1), ("worst peak grip [N]", "peak_grip", 1),
            ("worst RMS lag [mm]", "rms_lag", 1e3), ("worst slip [N^2]", "slip", 1), ("worst crush [N^2]", "crush", 1),
            ("worst after-release crush [N^2]", "impact", 1),
            (f"peak + {config.problem.w_lag:g} x lag [N]", "objective", 1)]
    for label, key, scale in rows:
        print(f"{label:<30} {getattr(before, key) * scale:>16.4g} {getattr(after, key) * scale:>12.4g}")
    verdict = lambda v: "yes" if v.holds else "NO"
    print(f"{'holds >= F_lim at every mass':<30} {verdict(before):>16} {verdict(after):>12}")
    print()


def _plots(config, base, held_out, start_values, tuned, state, files, judge_dt):
    import coopjax as cj
    from tuning.plots import plot_history, plot_traces

    plot_history(state.history, files["history"], config)
    ends = np.array([held_out[0], held_out[-1]])
    runs = {}
    for label, values in (("start (Table 1)", start_values), ("tuned", tuned)):
        params = base.replace(M_b=ends, **values)
        runs[label] = cj.simulate(params, "carry", switch="hard", integrator="filippov", dt=judge_dt,
                                  every=1, check_dt=False).trajectory
    plot_traces(runs, ends, float(np.asarray(base.F_lim).min()), float(np.asarray(base.F_max)), files["traces"])


def _compare(args, config, base, files) -> int:
    from tuning import race
    from tuning.plots import plot_race

    seeds = _parse_list(args.seeds, "--seeds", int)
    result = race.run(config, base, seeds, progress=args.quiet)
    result["config"] = json.loads(config.to_json())
    _write_json(files["out"], result)
    plot_race(result, files["race"])
    race.print_summary(result)
    print(f"wrote {files['out']} and {files['race']}")
    return 0


def _pareto(args, config, base, held_out, files) -> int:
    from tuning import baselines, race
    from tuning.objective import from_log, judge, log_bounds, select, to_log, validation_masses
    from tuning.optimize import candidates, tune
    from tuning.plots import plot_pareto

    weights = _parse_list(args.lag_weights, "--lag-weights", float)
    names, F_lim = config.problem.names, float(np.asarray(base.F_lim).min())
    masses = validation_masses(config.problem)
    points = {"gradient": [], "CMA-ES": [], "random search": []}
    random_record = None
    for w_lag in weights:
        problem = dataclasses.replace(config.problem, w_lag=w_lag)
        run = dataclasses.replace(config, problem=problem)
        print(f"-- lag weight {w_lag:g} N/mm")
        state = tune(run, base, log=lambda s: None, progress=True)
        options = candidates(state, names)
        points["gradient"].append((w_lag, options[select(options, masses, base, w_lag, args.judge_dt)[0]]))
        theta0 = np.clip(to_log(config.start_values, names), *log_bounds(names))
        record = baselines.cma_es(baselines.Evaluator(problem, base, F_lim, config.seed), names, state.elapsed, theta0,
                                  config.seed)
        # As in the race: CMA-ES's running choices, and the one the validation masses prefer.
        options = [from_log(record.thetas[i], names) for _, i in race.snapshots(record)] or [from_log(theta0, names)]
        points["CMA-ES"].append((w_lag, options[select(options, masses, base, w_lag, args.judge_dt)[0]]))
        if random_record is None:  # one run: its cloud does not depend on the weight
            random_record = baselines.random_search(baselines.Evaluator(problem, base, F_lim, config.seed), names, state.elapsed,
                                                    config.seed)
    held = [i for i, h in enumerate(random_record.holds) if h]
    cloud = [dict(zip(names, np.exp(random_record.thetas[i]))) for i in held]
    flat = [(tuner, w, p) for tuner, pts in points.items() for w, p in pts] + [("random search", None, p) for p in cloud]
    print(f"judging {len(flat)} parameter sets on the held-out masses ...")
    verdicts = judge([p for _, _, p in flat], held_out, base, 1.0, args.judge_dt, progress=True)
    rows = [{"tuner": t, "w_lag": w, "params": {k: float(v) for k, v in p.items()}, **v.row()}
            for (t, w, p), v in zip(flat, verdicts)]
    _write_json(files["out"], {"pareto": rows, "config": json.loads(config.to_json()),
                               "held_out_masses": [float(m) for m in held_out]})
    plot_pareto(rows, files["pareto"])
    for r in rows:
        if r["tuner"] != "random search":
            print(f"  {r['tuner']:<14} w_lag {r['w_lag']:>5g}: holds {'yes' if r['holds'] else 'NO ':>3}, "
                  f"peak {r['peak_grip']:6.2f} N, lag {r['rms_lag_mm']:6.2f} mm")
    print(f"wrote {files['out']} and {files['pareto']}")
    return 0
