"""`coopjax plot-sweep`: a metric against a parameter, with histograms of the metrics."""

from __future__ import annotations

from coopjax.cli.common import PLOT_FORMATS, BadInput, check_output
from coopjax.io import Outputs, read_table
from coopjax.plotting import plot_sweep

NAME = "plot-sweep"
COMPILES = False  # a table and a figure: no compile cache


def add_parser(sub):
    p = sub.add_parser(NAME, help="scatter a metric against a parameter, with histograms of the metrics")
    p.add_argument("table", help="a sweep table (.csv or .parquet)")
    p.add_argument("--x", default="M_b", help="column on the x axis (default M_b)")
    p.add_argument("--y", default="min_grip", help="column on the y axis (default min_grip)")
    p.add_argument("--color", default=None, help="column for the colour scale")
    p.add_argument("--out", default="sweep.png", help="figure file (default sweep.png)")
    return p


def run(args) -> int:
    check_output(args.out, "--out", PLOT_FORMATS)
    columns = read_table(args.table)
    for name in (args.x, args.y, args.color):
        if name is not None and name not in columns:
            raise BadInput(f"no column {name!r} in {args.table}; it has: {', '.join(columns)}")
        if name is not None and columns[name].dtype.kind != "f":
            raise BadInput(f"column {name!r} of {args.table} is not numeric")
    if "finite" not in columns:
        raise BadInput(f"{args.table} is not a sweep table: it has no 'finite' column")
    with Outputs() as out:
        plot_sweep(columns, args.x, args.y, args.color, out.path(args.out))
    print(f"wrote {args.out}")
    return 0
