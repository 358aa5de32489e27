"""`coopjax tune`: tune the gains, judge them with the hard model, write tuned.json and the plots.

Modes: a plain run (the default), `--compare` (the gradient tuner against CMA-ES and random search on
the same budget, plus the issue's 300 random gain sets judged hard), and `--pareto` (one run per lag
weight, and the front of worst-case peak force against RMS lag).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

from coopjax.io import atomic_path

DEFAULT_OUT = "tuned.json"


def add_parser(sub, check_output):
    from tuning.objective import GAINS, JUDGE_DT, SURROGATES, Weights
    from tuning.optimize import TuneConfig

    d, w = TuneConfig(), Weights()
    p = sub.add_parser(
        "tune", help="tune K_GP, K_GI, tau and G_e by gradient descent; judge before/after with the hard model",
        description="Tune gains on the carry scenario with optax Adam in log space, through a differentiable "
        "surrogate of the switch, over random body masses. The result is judged with the hard switch and "
        "contact, in float64, on held-out masses. Writes OUT (json), OUT's _loss.png and _traces.png.",
    )
    p.add_argument("--scenario", default="carry", help="carry (the only tuning scenario)")
    p.add_argument("--params", default=",".join(GAINS), help=f"comma-separated gains to tune (default {','.join(GAINS)})")
    p.add_argument("--masses", default="loguniform:0.5:5", help="body-mass distribution, loguniform:LOW:HIGH or uniform:LOW:HIGH in kg")
    p.add_argument("--margin", type=float, default=d.margin, help=f"train on the mass range widened by this fraction (default {d.margin:g})")
    p.add_argument("--batch", type=int, default=d.batch, help=f"body masses per step (default {d.batch})")
    p.add_argument("--steps", type=int, default=d.steps, help=f"optimiser steps (default {d.steps})")
    p.add_argument("--mode", default=d.mode, help="forward (jacfwd, default) or reverse (grad with checkpointing)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of the mass draws (default 0)")
    p.add_argument("--lr", type=float, default=d.learning_rate, help=f"peak learning rate in log-gain units (default {d.learning_rate})")
    p.add_argument("--surrogate", default="blend", help=f"training switch: {', '.join(SURROGATES)} (default blend; see docs/tuning.md)")
    p.add_argument("--no-anneal", dest="anneal", action="store_false", help="keep the narrow surrogate widths from the start")
    p.add_argument("--dt", type=float, default=d.objective.dt, help=f"training RK4 step in s (default {d.objective.dt:g})")
    p.add_argument("--judge-dt", type=float, default=JUDGE_DT, help=f"step of the hard model (sliding-mode integrator) for validation and judging, s (default {JUDGE_DT:g})")
    p.add_argument("--select", type=int, default=20, help="judge the last N iterates on validation masses and keep the best (default 20; 1 = the final iterate)")
    p.add_argument("--held-out", type=int, default=12, help="held-out masses for judging (default 12, ends included)")
    p.add_argument("--aggregate", default="mean", help="mean (default) or smoothmax over the mass batch")
    p.add_argument("--temperature", type=float, default=20.0, help="softness of smoothmax, in loss units (default 20)")
    p.add_argument("--w-slip", type=float, default=w.slip, help=f"weight of the slip term (default {w.slip:g})")
    p.add_argument("--w-crush", type=float, default=w.crush, help=f"weight of the crush term (default {w.crush:g})")
    p.add_argument("--w-lag", type=float, default=w.lag, help=f"weight of the lag term (default {w.lag:g})")
    p.add_argument("--w-impact", type=float, default=w.impact, help=f"weight of the after-release crush term (default {w.impact:g}; 0 = MODEL.md's objective)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="fix another parameter (repeatable)")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"result file (default {DEFAULT_OUT}); plots go beside it")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from OUT.ckpt.npz")
    p.add_argument("--compare", action="store_true", help="also run CMA-ES and random search on the same budget")
    p.add_argument("--pareto", action="store_true", help="sweep the lag weight and plot the peak-force / lag front")
    p.add_argument("--lag-weights", default="1,3,10,30,100", help="lag weights of --pareto (default 1,3,10,30,100)")
    p.add_argument("--random-sets", type=int, default=300, help="random gain sets judged hard by --compare/--pareto (default 300)")
    p.add_argument("--devices", type=int, default=None, help="CPU devices (default: one per core)")
    p.add_argument("--quiet", action="store_true", help="a progress bar instead of a line per step")
    return p


def _parse_list(text, what, cast=str):
    items = [x.strip() for x in text.split(",") if x.strip()]
    try:
        return [cast(x) for x in items]
    except ValueError:
        raise ValueError(f"{what}: {text!r} is not a comma-separated list of numbers") from None


def build(args):
    """Check every flag and return (TuneConfig, base Params, held-out masses); nothing is run."""
    from coopjax.cli import parse_assignment
    from coopjax.params import make_params
    from tuning.objective import Objective, Weights, check_tuned_names, held_out_masses, parse_masses
    from tuning.optimize import PAPER_GAINS, TuneConfig

    if args.scenario != "carry":
        raise ValueError(f"--scenario {args.scenario!r}: tuning is defined on the carry scenario only (MODEL.md section 7)")
    names = check_tuned_names(_parse_list(args.params, "--params"))
    masses = parse_masses(args.masses)
    if args.select < 1:
        raise ValueError(f"--select is {args.select}: at least 1 (the final iterate)")
    if args.held_out < 2:
        raise ValueError(f"--held-out is {args.held_out}: judge on at least 2 masses (the lightest and the heaviest)")
    for flag in ("judge_dt", "dt"):
        value = getattr(args, flag)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"--{flag.replace('_', '-')} is {value:g}: it must be positive")
    fixed = dict(parse_assignment(s) for s in args.set)
    clash = [n for n in fixed if n in names]
    if clash:
        raise ValueError(f"{clash[0]} is both tuned (--params) and fixed (--set): choose one")
    base = make_params(**fixed)
    start = {n: (PAPER_GAINS[n] if n in PAPER_GAINS else float(np.asarray(base.get(n)).ravel()[0])) for n in names}
    objective = Objective(names=names, switch=args.surrogate, dt=args.dt,
                          weights=Weights(args.w_slip, args.w_crush, args.w_lag, args.w_impact),
                          aggregate=args.aggregate, temperature=args.temperature)
    config = TuneConfig(objective=objective, masses=masses, margin=args.margin, batch=args.batch, steps=args.steps, mode=args.mode,
                        anneal=args.anneal, seed=args.seed, learning_rate=args.lr, start=tuple(start.items()))
    config.validate()
    if args.pareto:
        weights = _parse_list(args.lag_weights, "--lag-weights", float)
        if not weights or any(not (x >= 0 and math.isfinite(x)) for x in weights):
            raise ValueError(f"--lag-weights {args.lag_weights!r}: give non-negative numbers")
    if args.random_sets < 1:
        raise ValueError(f"--random-sets is {args.random_sets}: at least 1")
    return config, base, held_out_masses(masses, args.held_out)


def paths(out: str) -> dict:
    stem = out[:-5] if out.endswith(".json") else out
    return {"out": out, "checkpoint": out + ".ckpt.npz", "loss": stem + "_loss.png", "traces": stem + "_traces.png",
            "compare": stem + "_compare.png", "pareto": stem + "_pareto.png"}


def cmd_tune(args, check_output) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)  # before any parameter exists: training and judging are float64
    check_output(args.out, "--out", ("json",))
    config, base, held_out = build(args)
    devices = args.devices or os.cpu_count() or 1
    if devices < 1:
        raise ValueError(f"--devices is {devices}: it must be at least 1")
    try:
        jax.config.update("jax_num_cpu_devices", devices)
    except RuntimeError:
        pass
    files = paths(args.out)
    if os.path.exists(files["checkpoint"]) and not args.resume:
        raise ValueError(f"{files['checkpoint']} holds an interrupted run: add --resume to finish it, or delete it")
    from tuning.optimize import Rejected

    try:
        if args.pareto:
            return _pareto(args, config, base, held_out, files)
        return _tune_and_report(args, config, base, held_out, files)
    except Rejected as error:  # not bad input: the run itself went non-finite
        print(f"coopjax tune: error: {error}", file=sys.stderr)
        return 1


def _log(args):
    return (lambda text: None) if args.quiet else print


def _tune_and_report(args, config, base, held_out, files) -> int:
    from tuning.objective import HOLD_TOLERANCE, judge
    from tuning.optimize import tune

    log = print  # the gradient check and rejections are always shown
    start = time.perf_counter()
    state = tune(config, base, checkpoint=files["checkpoint"], resume=args.resume, log=log, progress=args.quiet)
    start_gains = dict(config.start)
    tuned, selection = _select_iterate(args, config, base, state)
    print(f"judging with the hard model (filippov), float64, dt = {args.judge_dt:g} s, on {len(held_out)} held-out masses "
          f"from {held_out[0]:.3g} to {held_out[-1]:.3g} kg ...")
    before, after = judge([start_gains, tuned], held_out, base, config.objective.weights, args.judge_dt)
    result = {
        "gains": tuned,
        "start": start_gains,
        "before": _row(before),
        "after": _row(after),
        "held_out_masses": [float(m) for m in held_out],
        "judge": {"switch": "hard", "contact": "unilateral", "integrator": "filippov", "dtype": "float64", "dt": args.judge_dt,
                  "hold_tolerance_N": HOLD_TOLERANCE},
        "weights": config.objective.weights._asdict(),
        "config": json.loads(config.to_json()),
        "history": state.history,
        "trajectories": state.trajectories,
        "tuning_seconds": state.elapsed,
        "selection": selection,
    }
    if args.compare:
        result["compare"] = _compare(args, config, base, held_out, state, tuned, files)
    _write_json(files["out"], result)
    _plots(config, base, held_out, start_gains, tuned, state, files, args.judge_dt)
    os.remove(files["checkpoint"])
    _print_table(before, after, start_gains, tuned, config)
    print(f"{state.trajectories} trajectories, {state.elapsed:.0f} s of tuning, {time.perf_counter() - start:.0f} s in all")
    print(f"wrote {files['out']}, {files['loss']} and {files['traces']}"
          + (f" and {files['compare']}" if args.compare else ""))
    return 0


def iterates(state, names, last: int) -> list[dict]:
    """The final iterate and the `last` - 1 before it whose loss was finite (newest first)."""
    from tuning.objective import from_log

    h = state.history
    out = [from_log(state.theta, names)]
    for i in range(len(h["loss"]) - 1, -1, -1):
        if len(out) >= last:
            break
        if np.isfinite(h["loss"][i]):
            out.append({n: h[n][i] for n in names})
    return out


def _select_iterate(args, config, base, state):
    """Pick among the last `--select` iterates with the hard model on validation masses."""
    from tuning.objective import select, validation_masses

    names = config.objective.names
    candidates = iterates(state, names, args.select)
    if len(candidates) == 1:
        return candidates[0], {"candidates": 1, "chosen": 0}
    masses = validation_masses(config.training_masses)
    print(f"selecting among the last {len(candidates)} iterates: hard model on {len(masses)} validation masses "
          f"({', '.join(f'{m:.3g}' for m in masses)} kg; none of them held out) ...")
    chosen, verdicts = select(candidates, masses, base, config.objective.weights, args.judge_dt)
    v = verdicts[chosen]
    held = sum(x.holds for x in verdicts)
    print(f"  {held} of {len(candidates)} hold at every validation mass; chose the one {chosen} step(s) before the end "
          f"(validation: min grip {v.min_grip:.3f} N, peak {v.peak_grip:.1f} N, lag {v.rms_lag * 1e3:.1f} mm)")
    return candidates[chosen], {"candidates": len(candidates), "chosen_steps_before_end": chosen, "holding": held,
                                "validation_masses": [float(m) for m in masses], "validation": _row(v)}


def _row(verdict) -> dict:
    row = verdict.row()
    row["rms_lag_mm"] = row["rms_lag"] * 1e3
    return row


def _write_json(path, data):
    with atomic_path(path) as tmp:
        with open(tmp, "w") as f:
            json.dump(data, f, indent=1, allow_nan=True)


def _print_table(before, after, start, tuned, config):
    names = config.objective.names
    print()
    print(f"{'':<28} {'start (Table 1)':>16} {'tuned':>12}")
    for n in names:
        print(f"{n:<28} {start[n]:>16.5g} {tuned[n]:>12.5g}")
    rows = [("worst min grip [N]", "min_grip", 1), ("worst peak grip [N]", "peak_grip", 1),
            ("worst RMS lag [mm]", "rms_lag", 1e3), ("worst slip [N^2]", "slip", 1), ("worst crush [N^2]", "crush", 1),
            ("worst lag term", "lag_term", 1), ("worst impact [N^2]", "impact", 1), ("mean loss (hard)", "loss", 1)]
    for label, key, scale in rows:
        print(f"{label:<28} {getattr(before, key) * scale:>16.4g} {getattr(after, key) * scale:>12.4g}")
    verdict = lambda v: "yes" if v.holds else "NO"
    print(f"{'holds >= F_lim at every mass':<28} {verdict(before):>16} {verdict(after):>12}")
    print()


def _plots(config, base, held_out, start_gains, tuned, state, files, judge_dt):
    import coopjax as cj
    from tuning.plots import plot_loss, plot_traces

    plot_loss(state.history, files["loss"], f"tuning {', '.join(config.objective.names)}: "
              f"{config.objective.switch} surrogate, {config.mode} mode, batch {config.batch}")
    ends = np.array([held_out[0], held_out[-1]])
    runs = {}
    for label, gains in (("Table 1 gains", start_gains), ("tuned gains", tuned)):
        params = base.replace(M_b=ends, **gains)
        runs[label] = cj.simulate(params, "carry", switch="hard", integrator="filippov", dt=judge_dt,
                                  every=max(1, round(1e-3 / judge_dt)), check_dt=False).trajectory
    plot_traces(runs, ends, float(np.asarray(base.F_lim).min()), float(np.asarray(base.F_max)), files["traces"])


def _compare(args, config, base, held_out, state, tuned, files) -> dict:
    from tuning.baselines import cma_es, random_gain_sets, random_search
    from tuning.objective import from_log, judge, select, validation_masses
    from tuning.plots import plot_compare

    budget = state.trajectories
    print(f"baselines on the same objective and budget ({budget} trajectories) ...")
    traces = {f"gradient ({config.mode} mode)": {"trajectories": state.history["trajectories"],
                                                 "wall": state.history["wall"],
                                                 "loss": list(np.minimum.accumulate(state.history["loss"]))}}
    rs = random_search(config.objective, config.training_masses, config.batch, budget, base, config.seed)
    theta0 = np.log([dict(config.start)[n] for n in config.objective.names])
    cm = cma_es(config.objective, config.training_masses, config.batch, budget, base, theta0, config.seed)
    traces["CMA-ES"] = cm.as_dict()
    traces["random search"] = rs.as_dict()
    plot_compare(traces, files["compare"])
    names = config.objective.names
    # The same hard-model validation picks each tuner's answer from its own candidates: the gradient
    # tuner's last iterates (done above), and the baselines' best by training loss.
    masses = validation_masses(config.training_masses)
    finals = {"gradient": tuned}
    for name, trace in (("CMA-ES", cm), ("random search", rs)):
        candidates = [from_log(t, names) for t in trace.top(args.select)]
        finals[name] = candidates[select(candidates, masses, base, config.objective.weights, args.judge_dt)[0]]
    print(f"judging the {args.random_sets} random gain sets of the issue's aim, hard, on the held-out masses ...")
    reference = random_gain_sets(args.random_sets, config.seed) if names == ("K_GP", "K_GI", "tau", "G_e") else []
    verdicts = judge(list(finals.values()) + reference, held_out, base, config.objective.weights, args.judge_dt,
                     progress=True)
    table = {}
    print(f"\n{'tuner':<16} {'trajectories':>12} {'wall [s]':>9} {'train loss':>11} {'min grip':>9} {'peak':>7} "
          f"{'lag [mm]':>9} {'hard loss':>10} {'holds':>6}")
    for (name, gains), v in zip(finals.items(), verdicts):
        tr = traces[next(k for k in traces if k.startswith(name))]
        table[name] = {"gains": gains, "verdict": _row(v), "trajectories": tr["trajectories"][-1],
                       "wall_s": tr["wall"][-1], "training_loss": tr["loss"][-1]}
        print(f"{name:<16} {tr['trajectories'][-1]:>12} {tr['wall'][-1]:>9.1f} {tr['loss'][-1]:>11.4g} "
              f"{v.min_grip:>9.3f} {v.peak_grip:>7.2f} {v.rms_lag * 1e3:>9.2f} {v.loss:>10.4g} {'yes' if v.holds else 'NO':>6}")
    ref = verdicts[len(finals):]
    out = {"tuners": table, "traces": traces}
    if ref:
        held = [(g, v) for g, v in zip(reference, ref) if v.holds]
        print(f"\nthe issue's reference: {len(held)} of {len(ref)} random gain sets hold the grip at every held-out mass")
        if held:
            best = min(held, key=lambda gv: gv[1].loss)
            lowest_peak = min(held, key=lambda gv: gv[1].peak_grip)
            lowest_lag = min(held, key=lambda gv: gv[1].rms_lag)
            for label, (g, v) in (("lowest hard loss", best), ("lowest peak", lowest_peak), ("lowest lag", lowest_lag)):
                print(f"  {label:<17} peak {v.peak_grip:7.2f} N  lag {v.rms_lag * 1e3:6.2f} mm  loss {v.loss:8.4g}  "
                      + "  ".join(f"{n} {x:.4g}" for n, x in g.items()))
            grad = verdicts[0]
            beats = grad.holds and grad.peak_grip < best[1].peak_grip and grad.rms_lag < best[1].rms_lag
            print(f"  the gradient-tuned gains {'DO' if beats else 'do NOT'} hold with both a lower peak and a lower "
                  "lag than the best (lowest-loss) random set")
            out["aim_met"] = bool(beats)
        out["random_sets"] = [{"gains": g, **_row(v)} for g, v in zip(reference, ref)]
    return out


def _pareto(args, config, base, held_out, files) -> int:
    import dataclasses

    from tuning.baselines import random_gain_sets
    from tuning.objective import judge
    from tuning.optimize import tune
    from tuning.plots import plot_pareto

    weights = _parse_list(args.lag_weights, "--lag-weights", float)
    points, log = [], _log(args)
    for w_lag in weights:
        objective = dataclasses.replace(config.objective, weights=config.objective.weights._replace(lag=w_lag))
        run = dataclasses.replace(config, objective=objective)
        print(f"-- lag weight {w_lag:g}")
        state = tune(run, base, log=log, check_gradient=False, progress=args.quiet)
        gains, _ = _select_iterate(args, run, base, state)
        v = judge(gains, held_out, base, objective.weights, args.judge_dt)
        print(f"   holds {v.holds}, min {v.min_grip:.3f} N, peak {v.peak_grip:.2f} N, lag {v.rms_lag * 1e3:.2f} mm")
        points.append({"w_lag": w_lag, "gains": gains, **_row(v)})
    reference = []
    if config.objective.names == ("K_GP", "K_GI", "tau", "G_e"):
        print(f"judging {args.random_sets} random gain sets for reference ...")
        sets = random_gain_sets(args.random_sets, config.seed)
        reference = [{"gains": g, **_row(v)} for g, v in
                     zip(sets, judge(sets, held_out, base, config.objective.weights, args.judge_dt, progress=True))]
    _write_json(files["out"], {"pareto": points, "random_sets": reference, "config": json.loads(config.to_json()),
                               "held_out_masses": [float(m) for m in held_out]})
    plot_pareto(points, reference, files["pareto"])
    print(f"wrote {files['out']} and {files['pareto']}")
    return 0
