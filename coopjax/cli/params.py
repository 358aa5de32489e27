"""`coopjax params`: every parameter with its default, unit and meaning, and who declares it."""

from __future__ import annotations

from coopjax.params import OWNER, PARAMETERS

NAME = "params"
COMPILES = False  # no compile cache, and no note about it


def add_parser(sub):
    return sub.add_parser(NAME, help="list every parameter with its default, unit and meaning")


def run(args) -> int:
    print(f"{'name':<10} {'default':>10}  {'unit':<8} {'per robot':<11}  meaning")
    for name, spec in PARAMETERS.items():
        per = "yes (_L/_R)" if spec.per_robot else "shared"
        owner = "" if OWNER[name] == "model" else f" [{OWNER[name]}]"
        print(f"{name:<10} {spec.default:>10.4g}  {spec.unit:<8} {per:<11}  {spec.doc}{owner}")
    return 0
