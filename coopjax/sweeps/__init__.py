"""Monte-Carlo and grid sweeps: many parameter sets, chunked, sharded over devices, resumable.

- `draws.py`: the distributions and the counter-based random draws;
- `spec.py`: `SweepSpec` and `make_spec`, which validates and freezes a sweep;
- `runner.py`: `run`, chunk by chunk over devices and processes (`coopjax.evaluation` per chunk);
- `parts.py`: the parts folder that makes a sweep resumable.
"""

from __future__ import annotations

from coopjax.config import Config
from coopjax.sweeps.draws import KINDS, Distribution, draw, parse_distribution
from coopjax.sweeps.parts import finished_parts
from coopjax.sweeps.runner import evaluate, run
from coopjax.sweeps.spec import SweepSpec, column_units, make_spec, result_columns, sample_values

__all__ = [
    "KINDS",
    "Distribution",
    "SweepSpec",
    "column_units",
    "draw",
    "evaluate",
    "finished_parts",
    "make_spec",
    "parse_distribution",
    "result_columns",
    "run",
    "sample_values",
    "sweep",
]


def sweep(
    config: Config | str = "carry",
    n=None,
    vary=None,
    fixed=None,
    seed=0,
    table=None,
    chunk=16384,
    progress=False,
    **settings,
):
    """Notebook entry point: the sweep as a pandas DataFrame.

    Example: `sweep("carry", 1000, vary={"M_b": "loguniform:0.5:5", "K_GP": "uniform:0.2:1"})`.
    """
    import pandas as pd  # on first use (`coopjax.io`)

    spec = make_spec(config, n=n, vary=vary, fixed=fixed, seed=seed, table=table, **settings)
    return pd.DataFrame(run(spec, chunk=chunk, progress=progress))
