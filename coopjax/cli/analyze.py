"""`coopjax analyze`: the loop linearised by jax.jacfwd, checked as a control engineer would."""

from __future__ import annotations

import warnings

import jax
import numpy as np

from coopjax import analysis
from coopjax.cli.common import BadInput, assignments, check_output
from coopjax.io import Outputs, write_json
from coopjax.params import make_params
from coopjax.plotting import plot_bode, plot_k_rob, plot_poles

NAME = "analyze"


def add_parser(sub):
    p = sub.add_parser(
        NAME,
        help="linear analysis: admittance vs Eq. 4, K_rob vs Eq. 5, poles vs the step, loop margins",
        description="Linearise the closed loop (jax.jacfwd of the model's own field) and check it as a control "
        "engineer would, with python-control: the Bode plot of the driving-point admittance for each alpha with "
        "the paper's Eq. 4 over it (OUT_bode.png), K_rob against alpha with Eq. 5 (OUT_krob.png), the closed-loop "
        "poles at rest and at the force limit over RK4's stability region at --dt (OUT_poles.png), and the gain "
        "and phase margins of the gain-modulation loop at the force limit (printed, and in OUT.json; a figure that "
        "is not finite, such as an infinite gain margin, is written as null). "
        "Needs python-control: pip install 'coopjax[analysis]'.",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="fix a parameter, e.g. --set K_GP=0.3 (repeatable; `coopjax params` lists the names)",
    )
    p.add_argument(
        "--alpha",
        default="1,0.5,0.1",
        help="comma-separated alphas (the frozen gamma of the paper's "
        "section 2, between 0 and 1) for the Bode plot (default 1,0.5,0.1)",
    )
    p.add_argument("--robot", default="L", choices=("L", "R"), help="the robot analysed (default L)")
    p.add_argument(
        "--dt", type=float, default=1e-3, help="the step whose RK4 stability region is drawn, s (default 1e-3)"
    )
    p.add_argument(
        "--out",
        default="analysis",
        metavar="OUT",
        help="prefix of the files written: OUT.json, OUT_bode.png, OUT_krob.png, OUT_poles.png (default analysis)",
    )
    return p


def parse_alphas(text: str) -> list[float]:
    try:
        alphas = [float(a) for a in text.split(",")]
    except ValueError:
        raise BadInput(f"--alpha {text!r}: expected comma-separated numbers, e.g. 1,0.5,0.1") from None
    if not alphas or not all(np.isfinite(alphas)):
        raise BadInput(f"--alpha {text!r}: every alpha must be a finite number")
    if any(a < 0 or a > 1 for a in alphas):
        raise BadInput(f"--alpha {text!r}: alpha is the frozen gamma of the paper's section 2, between 0 and 1")
    if len(set(alphas)) != len(alphas):
        raise BadInput(f"--alpha {text!r} names one value twice")
    return alphas


def run(args) -> int:
    try:
        import control  # noqa: F401
    except ImportError:
        raise BadInput("coopjax analyze needs python-control: pip install 'coopjax[analysis]'") from None
    alphas = parse_alphas(args.alpha)
    if not (np.isfinite(args.dt) and args.dt > 0):
        raise BadInput(f"--dt {args.dt:g}: it must be a positive number of seconds")
    outputs = {
        "json": args.out + ".json",
        "bode": args.out + "_bode.png",
        "krob": args.out + "_krob.png",
        "poles": args.out + "_poles.png",
    }
    check_output(args.out + ".json", "--out", ("json",))
    for path in outputs.values():
        check_output(path, "--out")
    overrides = assignments(args.set)
    jax.config.update("jax_enable_x64", True)
    params = make_params(**overrides)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # python-control's nan comparisons on a grid
        report = analysis.report(params, alphas, args.dt, args.robot)

    r, worst = args.robot, lambda row: float(np.max(np.abs(row["simulator"] - row["eq4"]) / np.abs(row["eq4"])))
    print(
        f"coopjax analyze: robot {r}, linearised by jax.jacfwd, float64; {len(report['omega'])} frequencies "
        f"from {report['omega'][0]:g} to {report['omega'][-1]:g} rad/s"
    )
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
        damped = (
            (
                f"; least damped {s['least_damped'][0]:.3g} +- {s['least_damped'][1]:.4g}j 1/s "
                f"(damping ratio {s['damping_ratio']:.3f})"
            )
            if s["least_damped"]
            else ""
        )
        if s["max_real"] > 1e-9 * s["fastest"]:
            verdict = f"UNSTABLE: a mode grows at {s['max_real']:.3g} 1/s, so no step is stable"
        else:
            verdict = (
                f"RK4 stable for dt <= {s['rk4_dt_limit']:.3g} s, so dt = {args.dt:g} s is "
                f"{'inside' if s['dt_inside'] else 'OUTSIDE'}"
            )
        print(f"poles {text}: fastest |lambda| {s['fastest']:.4g} 1/s{damped}; {verdict}")
    m = report["margins"]
    print(f"gain-modulation loop of robot {r} at the force limit (cut at gamma; L(0) = {report['loop_dc_gain']:.4g}):")
    print("  " + describe_margins(m))
    re, im = m["loop_at_gain_crossover"]
    if np.isfinite(m["phase_margin_deg"]) and m["phase_margin_deg"] < 0 and im > 0:
        print(
            f"  (at the crossover L = {re:.3g} {im:+.3g}j: the phase leads, so the Nyquist curve passes "
            f"{-m['phase_margin_deg']:.3g} deg above -1; python-control counts that as negative)"
        )
    print(
        f"  closed loop {'stable' if report['closed_loop_stable'] else 'UNSTABLE'} (largest real part of its poles "
        f"{report['poles_summary']['limit']['max_real']:.3g} 1/s)"
    )

    plain = dict(
        robot=r,
        dt=args.dt,
        overrides=overrides,
        eq4_max_relative_difference={f"{row['alpha']:g}": worst(row) for row in report["bode"]},
        k_rob={"alpha": k["alpha"].tolist(), "simulator": k["simulator"].tolist(), "eq5": k["eq5"].tolist()},
        poles={pt: [[float(z.real), float(z.imag)] for z in v] for pt, v in report["poles"].items()},
        poles_summary=report["poles_summary"],
        margins=report["margins"],
        loop_dc_gain=report["loop_dc_gain"],
        closed_loop_stable=report["closed_loop_stable"],
    )
    with Outputs() as out:
        nulls = write_json(out.path(outputs["json"]), plain)
        plot_bode(report, out.path(outputs["bode"]))
        plot_k_rob(report, out.path(outputs["krob"]))
        plot_poles(report, out.path(outputs["poles"]))
    if nulls:
        print(
            f"  ({len(nulls)} figure(s) that are not finite are null in {outputs['json']}: {', '.join(nulls[:4])}"
            + (", ..." if len(nulls) > 4 else "")
            + ")"
        )
    print("wrote " + ", ".join(outputs.values()))
    return 0


def describe_margins(m: dict) -> str:
    """Gain, phase and stability margins in words; a crossover that does not exist is said so."""
    gm = (
        "infinite (the loop never crosses -180 deg)"
        if not np.isfinite(m["gain_margin"])
        else f"{m['gain_margin']:.4g} at {m['w_phase_crossover']:.4g} rad/s"
    )
    pm = (
        "none (|L| never crosses 1)"
        if not np.isfinite(m["w_gain_crossover"])
        else f"{m['phase_margin_deg']:.3g} deg at {m['w_gain_crossover']:.4g} rad/s"
    )
    sm = (
        "not defined"
        if not np.isfinite(m["stability_margin"])
        else f"{m['stability_margin']:.3g} at {m['w_stability_margin']:.4g} rad/s"
    )
    return f"gain margin {gm}; phase margin {pm}; stability margin (least distance to -1) {sm}"
